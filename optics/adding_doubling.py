"""Exact plane-parallel totals of a layer stack: adding-doubling (van de Hulst 1980; Prahl 1995).

The 1-D radiative transfer of the stack (HG phase with delta-M, Fresnel boundaries) gives
the totals diffusion gets wrong in thin and absorbing layers (docs/profiles.md).  Fluxes
are vectors over quadrature directions mu_i in (0, 1] (one per hemisphere), each entry the
power travelling in that direction, so layers compose by plain matrix products.  The
quadrature is split at every critical angle of the boundaries (Fresnel has a kink there;
without the split the totals converge like 1/N) and its last node is mu = 1 (Radau), the
direction of the entering beam.  Checked against van de Hulst's slab (Rd 0.09739, Tt
0.66096) and Chandrasekhar's semi-infinite albedo (0.41495) to 5 digits, and against the
Monte Carlo (tests/test_profile_mc.py).

Exact totals in the layer file (``totals="transport"``, the default with "pbd";
:mod:`dermis.optics.layer_profiles`): :func:`exact_totals` gives each layer's R and T for
collimated and for diffuse light and, when all layers share one eta, the whole stack's; the
diffusion fields are scaled to them (``info["scale_to_exact"]``: exact / diffusion, the
diffusion model's own error).  ``totals="diffusion"`` keeps diffusion's own totals.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.polynomial.legendre import leggauss

from dermis.optics.fresnel import fresnel_normal, fresnel_reflectance_inside
from dermis.optics.layers import LayerStack

__all__ = ["ExactTotals", "exact_totals", "AD_NODES", "AD_NODES_FORWARD"]

# Directions per hemisphere.  Measured against 1e6-photon Monte Carlo runs: 32 converges the
# g = 0.8 skin stacks to < 0.1 %; g = 0.9 needs 48 (the forward peak).
AD_NODES = 32
AD_NODES_FORWARD = 48
AD_FORWARD_G = 0.85
# Optical thickness of the first (single-scattering) layer, relative to the smallest mu.
AD_THIN = 1e-6
# A semi-infinite layer is doubled until R changes by less than this (and T ~ 0).
AD_CONVERGED = 1e-13


def _radau01(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Radau nodes and weights on [0, 1] with a fixed node at 1 (n >= 2)."""
    c = np.zeros(n + 1)
    c[n - 1] = c[n] = 1.0                       # P_{n-1} + P_n vanishes at -1 and at the nodes
    r = np.sort(np.polynomial.legendre.legroots(c))[1:]
    pn1 = np.polynomial.legendre.legval(r, np.eye(n)[n - 1])
    w = (1.0 - r) / (n * n * pn1**2)
    x = -np.concatenate([[-1.0], r])[::-1]
    w = np.concatenate([[2.0 / n**2], w])[::-1]
    return 0.5 * (x + 1.0), 0.5 * w


@lru_cache(maxsize=64)
def _ad_quadrature(n: int, cuts: tuple) -> tuple[np.ndarray, np.ndarray]:
    """~n directions on (0, 1], Gauss-Legendre per segment between the critical cosines
    ``cuts``, Radau on the last segment (node at mu = 1); nodes per segment ~ its length."""
    bounds = [0.0] + sorted(c for c in cuts if 0.0 < c < 1.0) + [1.0]
    mus, ws = [], []
    for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        m = max(4, int(round(n * (b - a))))
        if k == len(bounds) - 2:
            x, w = _radau01(m)
        else:
            x, w = leggauss(m)
            x, w = 0.5 * (x + 1.0), 0.5 * w
        mus.append(a + (b - a) * x)
        ws.append((b - a) * w)
    return np.concatenate(mus), np.concatenate(ws)


@lru_cache(maxsize=256)
def _ad_redistribution(n: int, cuts: tuple, g: float):
    """Azimuth-averaged delta-M HG redistribution between the directions: (P_same, P_opp,
    f), P[i, j] the probability that a photon travelling along mu_j scatters into mu_i of
    the same / the opposite hemisphere (columns renormalised to 1 against quadrature
    error); f = g^(2N) is the delta-M forward fraction scaled out of the slab (N = number
    of directions; 0 for g < 0, whose delta-M peak points backwards)."""
    if g < 0:
        # HG(-|g|) is HG(|g|) reversed: same and opposite hemispheres swap, and delta-M's
        # forward peak becomes a backward one, a real scattering (kept, not scaled out)
        Ps, Po, f = _ad_redistribution(n, cuts, -g)
        return (1.0 - f) * Po, (1.0 - f) * Ps + f * np.eye(len(Ps)), 0.0
    mu, w = _ad_quadrature(n, cuts)
    L = 2 * len(mu)
    f = g ** L
    P = np.zeros((L, len(mu)))                  # Legendre P_l(mu) by the recurrence
    P[0] = 1.0
    if L > 1:
        P[1] = mu
    for l in range(1, L - 1):
        P[l + 1] = ((2 * l + 1) * mu * P[l] - l * P[l - 1]) / (l + 1)
    l = np.arange(L)
    chi = (g ** l - f) / (1.0 - f)
    coef = (2 * l + 1) * chi
    same = np.einsum("l,li,lj->ij", coef, P, P)
    opp = np.einsum("l,li,lj->ij", coef * (-1.0) ** l, P, P)
    Ps = np.maximum(0.5 * same * w[:, None], 0.0)   # truncation ringing is < 1e-6: clip
    Po = np.maximum(0.5 * opp * w[:, None], 0.0)
    tot = Ps.sum(0) + Po.sum(0)
    return Ps / tot, Po / tot, f


def _ad_slab(n: int, cuts: tuple, sigma_a: float, sigma_s: float, g: float, d: float):
    """(R, T) flux matrices of a homogeneous slab (symmetric: the same from both sides)."""
    mu, _ = _ad_quadrature(n, cuts)
    Ps, Po, f = _ad_redistribution(n, cuts, g)
    st = sigma_a + sigma_s
    a = sigma_s / st
    a_m = a * (1.0 - f) / (1.0 - a * f)             # delta-M scaled albedo and thickness
    dt = AD_THIN * float(mu.min())
    k = 0
    if not math.isinf(d):
        tau = st * d * (1.0 - a * f)
        k = max(0, int(math.ceil(math.log2(max(tau / dt, 1.0)))))
        dt = tau / 2.0**k
    x = dt / mu
    hit = -np.expm1(-x)                             # collides in the thin layer (single scattering)
    T = np.diag(np.exp(-x)) + a_m * Ps * hit[None, :]
    R = a_m * Po * hit[None, :]
    eye = np.eye(len(mu))
    conservative = sigma_a == 0.0

    def double(R, T):
        M = np.linalg.solve(eye - R @ R, R @ T)
        R2, T2 = R + T @ M, T @ np.linalg.solve(eye - R @ R, T)
        if conservative:
            # no absorption: every column of R + T is 1 exactly; (1 - R R) becomes singular as
            # the slab thickens and its round-off, compounded over the doublings, gave R + T up
            # to 1.097 (5000 mfp, g = 0.99, found by test_stability test11): renormalised
            s = (R2 + T2).sum(0)
            R2, T2 = R2 / s[None, :], T2 / s[None, :]
        return R2, T2

    if math.isinf(d):
        for _ in range(400):
            R2, T2 = double(R, T)
            done = np.abs(R2 - R).max() < AD_CONVERGED and T2.sum(0).max() < 1e-10
            R, T = R2, T2
            if done:
                break
        return R, np.zeros_like(T)
    for _ in range(k):
        R, T = double(R, T)
    return R, T


def _ad_add(A, B):
    """Stack A over B, each (R, T, R', T') with primes for light from below."""
    RA, TA, RpA, TpA = A
    RB, TB, RpB, TpB = B
    eye = np.eye(RA.shape[0])
    down = np.linalg.inv(eye - RpA @ RB)        # multiple reflections between A and B
    up = np.linalg.inv(eye - RB @ RpA)
    return (RA + TpA @ RB @ down @ TA, TB @ down @ TA,
            RpB + TB @ RpA @ up @ TpB, TpA @ up @ TpB)


def _ad_bounded(S, Ft, Fb, x):
    """(out through the top, out through the bottom) for flux ``x`` entering just inside
    the top, with internal Fresnel reflectances Ft, Fb (per direction) at the two faces."""
    R, T, Rp, Tp = S
    m = R.shape[0]
    eye = np.eye(m)
    # unknowns d0 (down just inside the top), u1 (up just inside the bottom):
    # d0 = x + Ft (R d0 + Tp u1),  u1 = Fb (T d0 + Rp u1)
    A = np.block([[eye - Ft[:, None] * R, -Ft[:, None] * Tp],
                  [-Fb[:, None] * T, eye - Fb[:, None] * Rp]])
    sol = np.linalg.solve(A, np.concatenate([x, np.zeros(m)]))
    d0, u1 = sol[:m], sol[m:]
    u0 = R @ d0 + Tp @ u1
    d1 = T @ d0 + Rp @ u1
    return float(np.sum((1.0 - Ft) * u0)), float(np.sum((1.0 - Fb) * d1))


def _critical_cosine(eta: float) -> float:
    return math.sqrt(1.0 - 1.0 / eta**2) if eta > 1.0 else 0.0


@dataclass
class ExactTotals:
    """Plane-parallel totals per unit flux entering: collimated from above (R, T scattered,
    T unscattered), diffuse (Lambertian) from above and from below (R, T)."""

    Rc: float
    Tc: float
    Tu: float
    Rd: float
    Td: float
    Rud: float
    Tud: float


def _ad_setup(layers, etas_outer: tuple[float, float]):
    g_max = max(float(l.g) for l in layers)
    n = AD_NODES_FORWARD if g_max >= AD_FORWARD_G else AD_NODES
    eta = layers[0].eta
    cuts = tuple(sorted({round(_critical_cosine(eta / e), 12) for e in etas_outer}))
    return n, cuts


def _ad_layers(stack: LayerStack, c: int, layers=None, etas=None) -> tuple:
    """Slab matrices of ``layers`` (default: the stack's), added, with quadrature info."""
    layers = stack.layers if layers is None else layers
    etas = (stack.eta_above, stack.eta_below) if etas is None else etas
    n, cuts = _ad_setup(layers, etas)
    S = None
    for lay in layers:
        R, T = _ad_slab(n, cuts, float(lay.sigma_a[c]), float(lay.sigma_s[c]), float(lay.g),
                        float(lay.thickness_mm))
        S = (R, T, R, T) if S is None else _ad_add(S, (R, T, R, T))
    return S, n, cuts


def exact_totals(layers, c: int, eta_top: float, eta_bot: float) -> ExactTotals:
    """Exact totals of ``layers`` (all of the same eta) between media of relative index
    eta_top, eta_bot (layer / outside) above and below."""
    eta = layers[0].eta
    S, n, cuts = _ad_layers(None, c, layers, (eta / eta_top, eta / eta_bot))
    mu, w = _ad_quadrature(n, cuts)
    Ft, Fb = fresnel_reflectance_inside(mu, eta_top), fresnel_reflectance_inside(mu, eta_bot)
    col = np.zeros(len(mu))
    col[-1] = 1.0
    lam = 2.0 * mu * w
    lam /= lam.sum()
    Rc, Tall = _ad_bounded(S, Ft, Fb, col)
    # unscattered: the beam e^{-sigma_t d} through every layer, with its normal-incidence
    # Fresnel bounces between the outer faces
    tau = sum(float(l.sigma_a[c] + l.sigma_s[c]) * float(l.thickness_mm) for l in layers)
    r0t, r0b = fresnel_normal(eta_top), fresnel_normal(eta_bot)
    Tu = 0.0 if math.isinf(tau) else \
        math.exp(-tau) * (1 - r0b) / (1 - r0t * r0b * math.exp(-2 * tau))
    Rd, Td = _ad_bounded(S, Ft, Fb, lam)
    Sf = (S[2], S[3], S[0], S[1])
    Rud, Tud = _ad_bounded(Sf, Fb, Ft, lam)
    return ExactTotals(Rc, max(Tall - Tu, 0.0), Tu, Rd, Td, Rud, Tud)
