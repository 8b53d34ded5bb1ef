"""Diffusion in one layer: the multipole (Donner & Jensen 2005) with sources along the beam.

R(r) and T(r) of one layer lit by collimated or diffuse light, per channel, in float64 on
the host, as sums over sources and image sources with closed-form densities, cumulative
energies and totals; :mod:`dermis.optics.layer_profiles` builds a stack's layer file from
them (docs/profiles.md has the measurements).

Per-layer diffusion (``diffusion="pbd"``, the default; why each choice: docs/profiles.md):

* **Sources along the beam, real extinction.**  The refracted beam's first collisions are
  integrated in depth (photon beam diffusion, Habel, Christensen & Jarosz 2013) by
  Gauss-Legendre in u = 1 - e^{-sigma* t} (``NQ_BEAM`` nodes; diffuse light: ``NMU_DIFFUSE``
  cosines x ``NQ_DIFFUSE``).  delta-P1 (Carp, Prahl & Venugopalan 2004): the fraction
  f = g^2 of each scattering is forward, sigma_s* = sigma_s (1 - g^2), g* = g / (1 + g).
  Only e^{-sigma_t d} (sigma_t = sigma_a + sigma_s, sigma_s = sigma_s' / (1 - g)) leaves a
  slab unscattered (``info["T_ballistic"]``).
* **Anisotropic sources (P1).**  A collision's flux moment is an isotropic source moved
  3 D g* mu deeper.  A source moved past the bottom of a finite layer is light scattered
  forward out of it: collimated, attenuated by e^{-sigma_a (d - t) / (g* mu)}
  (``info["T_forward"]``, with the delta-P1 forward peak).
* **Boundaries (d'Eon 2012, "A better dipole").**  Grosjean's D = (2 sigma_a + sigma_s')
  / (3 sigma_t'^2), extrapolation distance z_b = 2 A D with A = (1 + 3 C2) / (1 - 2 C1)
  from the Fresnel moments, and exitance C_phi phi + C_E J_n (the Fresnel-weighted
  outgoing partial current) instead of the flux J_n alone: J_n alone turns negative far
  from the source in layers thinner than their top z_b.
* **Images.**  Finite layers use pole pairs i = -n..n about the two extrapolated
  boundaries (Donner & Jensen 2005), n per channel so the first omitted pair is damped by
  e^{-20}.  Weakly absorbing layers (sigma_a = 0 included), whose images decay only
  algebraically, stop their field where its lowest slab mode has decayed by e^{-30}, run
  the images to 10x that radius and add the rest as their integral (``POLE_REACH``).
* **Collimated light at a mismatched boundary** (ballistic + forward) reflects with the
  normal-incidence Fresnel factor (forward light: averaged over a once-scattered HG lobe;
  diffuse light: 2 C1); the reflected light re-enters the layer from that side and is
  followed once (the second order, < r0^2, is recorded as dropped).

``diffusion="dj2005"`` keeps the model of dermis <= 1 (a single source at the mean reduced
collision depth, flux-only exitance, e^{-sigma_t' d} passed through as if unscattered,
all light added as collimated) for before/after comparisons.

Totals: :func:`scaled_to_exact` sets a layer's diffusion energies to the exact
plane-parallel ones of :mod:`dermis.optics.adding_doubling` (``totals="transport"``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.polynomial.legendre import leggauss

from dermis.pipeline.errors import DermisError
from dermis.optics.adding_doubling import exact_totals
from dermis.optics.forward_spread import RadialShape, convolve, diffuse_shape, forward_shape, mix
from dermis.optics.fresnel import (diffusion_A, diffusion_boundary, fresnel_moments,
                                    fresnel_normal, fresnel_reflectance_inside)
from dermis.optics.layers import Layer, LayerStack

__all__ = ["multipole_profiles", "multipole_totals", "DiffusionConstants",
           "diffusion_constants", "lit_from_below", "BeamSources", "beam_sources", "image_sum",
           "LayerResponse", "layer_response", "direct_spreads", "direct_parts",
           "evaluate_terms", "relative_indices",
           "check_diffusion", "scaled_to_exact", "DIFFUSION_MODELS", "DEFAULT_POLES",
           "MAX_POLES", "NQ_BEAM", "IMAGE_SUM_CHUNK"]

DIFFUSION_MODELS = ("pbd", "dj2005")

# Pole pairs i = -n..n.  Measured (tests/test_profiles.py::test10_pole_convergence): for the
# 0.25 mm epidermis of the two_layer preset Rd changes by 7e-6 from n = 2 to 5 and < 1e-12
# beyond; Donner-Jensen's public code used n = 5 (11 pairs).  A fixed n fails for thick,
# weakly absorbing slabs (a 5 mm slab with albedo 0.9999 gave negative tails at n = 10), so
# the default adapts n to sigma_tr and the slab period.
DEFAULT_POLES = None  # adaptive, see diffusion_constants
MIN_POLES = 3
MAX_POLES = 2000
POLE_DAMPING = 20.0
# Weakly absorbing finite layers (sigma_tr (d + z_b,t + z_b,b) small, sigma_a = 0 included):
# the images decay only algebraically, but the layer's own field decays exponentially in r,
# at least as its lowest slab mode K0(kappa r), kappa = sqrt(sigma_tr^2 + (pi / L)^2),
# L = d + z_b,t + z_b,b: beyond POLE_REACH / kappa it holds a fraction
# sqrt(pi kappa r / 2) e^{-kappa r} = 6e-13 of its energy and is set to zero (the cumulative
# energy held at its value there).  Images run out to POLE_FAR x that reach (48 pairs at
# most: kappa L >= pi), the omitted ones are added as their integral (2-point Gauss over
# each end's width) plus the midpoint rule's first Euler-Maclaurin term; with sigma_a = 0
# the totals are then exact ((d + z_b,b - t) / L through the top).  Used where it needs
# fewer images than the e^{-20} damping (never for the presets: their layers are damped
# first, and their tables are byte-identical).  Measured (bench/bench_profiles_extreme.py,
# bench/results/profiles_extreme.json): cumulative energy within 3e-10 of the sources'
# energy of the same sum with 4000 pairs (error ~ POLE_FAR^-6: 8e-10 at 8, 4e-9 at 6; the
# 200 mm images of 5e8c639: up to 7e-4); sigma_a = 0 two_layer 47 s -> 7 s.
POLE_REACH = 30.0
POLE_FAR = 10.0
# Gauss-Legendre nodes along the beam (u = 1 - e^{-sigma_t t}, split where the displaced
# sources leave the layer).  Measured (tests/test_profiles.py::test11_beam_convergence):
# 16 -> 64 nodes changes the epidermis R(r) by < 1e-6 and the semi-infinite dermis by
# < 0.05 % at r >= 0.05 mm.
NQ_BEAM = 16
# Gauss nodes in the cosine, and beam nodes per cosine, for diffuse incidence (measured:
# 4 x 8 -> 6 x 12 (with 32 collimated nodes) changes the two_layer R(r) by < 0.14 % at
# r >= 0.05 mm).
NMU_DIFFUSE = 4
NQ_DIFFUSE = 8
# Nodes for the forward-scattered part of the beam (light leaving the layer's bottom).
NQ_FORWARD = 8
# At most this many (source x image) pairs per layer and channel: weakly absorbing thick
# slabs need thousands of images, and then fewer beam nodes are used (>= 4).
MAX_SOURCE_IMAGES = 40000
# Midpoint steps in the cosine of the boundary reflectances seen from inside (the HG-weighted
# forward one and 2 C1).  fresnel_moments' default 20000 (the extrapolation distance) would
# move 2 C1 by 7.8e-7 at eta 1.4 and two_layer's R(r) by up to 5e-8 relative.
BOUNDARY_NODES = 4000
# Image sums are evaluated over radii in chunks of about this many (radius x image) pairs,
# which bounds their temporaries (unless one radius alone has more images).
IMAGE_SUM_CHUNK = 4_000_000


@dataclass(frozen=True)
class DiffusionConstants:
    """Diffusion constants of one layer in one channel, lit from its top (1/mm, mm)."""

    d: float            # thickness (inf: semi-infinite)
    sa: float           # sigma_a
    ss: float           # sigma_s = sigma_s' / (1 - g)
    ssp: float          # sigma_s'
    g: float
    D: float
    sig: float          # sigma_tr = sqrt(sigma_a / D)
    zb_t: float         # extrapolation distances, top and bottom
    zb_b: float
    cphi_t: float       # exitance weights C_phi, C_E at the top and bottom
    ce_t: float
    cphi_b: float
    ce_b: float
    fr_t: tuple         # Fresnel reflectance at the top / bottom for (collimated, once-scattered
    fr_b: tuple         #   forward (HG about the normal), diffuse) light arriving from inside
    poles: int          # n of the pole pairs i = -n..n (0 for a semi-infinite layer)
    diffusion: str
    reach: float = math.inf  # field set to zero beyond this radius (weakly absorbing slab)
    tail: bool = False       # omitted images added as their integral
    eta_t: float = 1.0       # relative indices (layer / neighbour) at the top and bottom
    eta_b: float = 1.0

    @property
    def st(self) -> float:
        return self.sa + self.ss

    @property
    def stp(self) -> float:
        return self.sa + self.ssp


def _boundary_reflectances(eta: float, g: float) -> tuple[float, float, float]:
    """Fresnel reflectance seen from inside at relative index ``eta`` for normal (collimated)
    light, for once-scattered forward light (HG(g) about the normal, photon-weighted over
    the forward hemisphere) and for diffuse (Lambertian) light (= 2 C1)."""
    if eta == 1.0:
        return 0.0, 0.0, 0.0
    mu = (np.arange(BOUNDARY_NODES) + 0.5) / BOUNDARY_NODES
    F = fresnel_reflectance_inside(mu, eta)
    hg = (1.0 - g * g) / (1.0 + g * g - 2.0 * g * mu) ** 1.5
    c1, _ = fresnel_moments(eta, BOUNDARY_NODES)
    return fresnel_normal(eta), float(np.sum(hg * F) / np.sum(hg)), 2.0 * c1


def diffusion_constants(layer: Layer, c: int, eta_top: float, eta_bot: float, diffusion: str,
                        poles: int | None) -> DiffusionConstants:
    """Constants of ``layer`` in channel ``c``; ``eta_top``/``eta_bot`` are relative indices
    (layer / neighbour) at its top and bottom boundary."""
    sa, ssp, g, d = float(layer.sigma_a[c]), float(layer.sigma_s_prime[c]), float(layer.g), \
        float(layer.thickness_mm)
    ss = ssp / (1.0 - g)
    stp = sa + ssp
    if diffusion == "pbd":
        D = (2.0 * sa + ssp) / (3.0 * stp * stp)
        A_t, cphi_t, ce_t = diffusion_boundary(eta_top)
        A_b, cphi_b, ce_b = diffusion_boundary(eta_bot)
        fr_t, fr_b = _boundary_reflectances(eta_top, g), _boundary_reflectances(eta_bot, g)
    elif diffusion == "dj2005":
        D = 1.0 / (3.0 * stp)
        A_t, A_b = diffusion_A(eta_top), diffusion_A(eta_bot)
        cphi_t = cphi_b = 0.0
        ce_t = ce_b = 1.0
        fr_t = fr_b = (0.0, 0.0, 0.0)
    else:
        raise DermisError(f"profiles: diffusion = {diffusion!r}: must be one of "
                          + ", ".join(DIFFUSION_MODELS))
    sig = math.sqrt(sa / D)
    zb_t, zb_b = 2.0 * A_t * D, 2.0 * A_b * D
    reach, tail = math.inf, False
    if math.isinf(d):
        n = 0
    elif poles is not None:
        n = int(poles)
    else:
        # enough images that the next pair is damped by e^{-20} (POLE_DAMPING), at least
        # MIN_POLES; weakly absorbing layers: images out to POLE_FAR x the field's reach,
        # the rest as their integral (see POLE_REACH)
        period = 2.0 * (d + zb_t + zb_b)
        kappa = math.hypot(sig, 2.0 * math.pi / period)
        reach = POLE_REACH / kappa
        far = POLE_FAR * reach / period
        need = POLE_DAMPING / (sig * period) if sig > 0 else math.inf
        if need <= far:
            n, reach = int(min(max(MIN_POLES, math.ceil(need)), MAX_POLES)), math.inf
        else:
            n, tail = int(max(MIN_POLES, math.ceil(far))), True
    return DiffusionConstants(d, sa, ss, ssp, g, D, sig, zb_t, zb_b, cphi_t, ce_t, cphi_b,
                              ce_b, fr_t, fr_b, n, diffusion, reach, tail, eta_top, eta_bot)


def lit_from_below(ch: DiffusionConstants) -> DiffusionConstants:
    """The same layer lit from its bottom."""
    return DiffusionConstants(ch.d, ch.sa, ch.ss, ch.ssp, ch.g, ch.D, ch.sig, ch.zb_b, ch.zb_t,
                              ch.cphi_b, ch.ce_b, ch.cphi_t, ch.ce_t, ch.fr_b, ch.fr_t, ch.poles,
                              ch.diffusion, ch.reach, ch.tail, ch.eta_b, ch.eta_t)


@dataclass
class BeamSources:
    """Diffusion sources for unit flux entering the top of one layer."""

    t: np.ndarray        # (S,) depths, mm (inside [0, d))
    w: np.ndarray        # (S,) strengths (albedo x quadrature weight)
    ballistic: float     # unscattered at the bottom (e^{-sigma_t d}; 2 E3(sigma_t d) if diffuse)
    forward: float       # scattered forward out of the bottom (collimated)
    nodes: int


def beam_sources(ch: DiffusionConstants, nq: int = NQ_BEAM, diffuse: bool = False,
                 shift_on: bool = True) -> BeamSources:
    """Sources for collimated flux at normal incidence, or for diffuse (Lambertian) flux:
    then the beam integral runs over ``NMU_DIFFUSE`` Gauss nodes in the cosine mu (weights
    2 mu dmu), each ray's collisions at depth mu s and its flux moment along mu."""
    finite = not math.isinf(ch.d)
    if ch.diffusion == "dj2005":
        # dermis <= 1: one source at the mean depth of the first reduced collision within the
        # slab, strength alpha' (1 - e^{-sigma_t' d}); e^{-sigma_t' d} passes through
        st, alpha = ch.stp, ch.ssp / ch.stp
        if not finite:
            return BeamSources(np.array([1.0 / st]), np.array([alpha]), 0.0, 0.0, 1)
        x = st * ch.d
        tau = math.exp(-x)
        collided = -math.expm1(-x)
        z0 = 1.0 / st - ch.d * tau / collided if x > 1e-4 else ch.d * (0.5 - x / 12.0)
        return BeamSources(np.array([z0]), np.array([alpha * collided]), tau, 0.0, 1)
    # delta-P1 (Carp, Prahl & Venugopalan 2004): the forward fraction f = g^2 of every
    # scattering is treated as unscattered, the rest scatters with g* = g / (1 + g)
    f = ch.g * ch.g if ch.g > 0 else 0.0
    ss_star = ch.ss * (1.0 - f)
    st = ch.sa + ss_star
    g_star = (ch.g - f) / (1.0 - f) if f < 1 else 0.0
    images = 2 * (2 * ch.poles + 1)
    if diffuse:
        xm, wm = leggauss(NMU_DIFFUSE)
        mus = 0.5 * (xm + 1.0)
        wmu = 0.5 * wm * 2.0 * mus
    else:
        mus, wmu = np.ones(1), np.ones(1)
    if diffuse:
        nq = min(nq, NQ_DIFFUSE)
    nq = int(max(4, min(nq, MAX_SOURCE_IMAGES // (images * len(mus)))))
    x, wq = leggauss(nq)
    ts, ws, bal, fwd = [], [], 0.0, 0.0
    xf, wf = leggauss(NQ_FORWARD)
    for mu, wm_ in zip(mus, wmu):
        shift = (3.0 * ch.D * g_star * mu) if shift_on else 0.0     # P1: the flux moment
        U = -math.expm1(-st * ch.d / mu) if finite else 1.0
        # collisions whose displaced source stays inside the layer: u below U_in (the
        # quadrature ends exactly there, so the integrand has no jump)
        U_in = U if not finite else (-math.expm1(-st * max(ch.d - shift, 0.0) / mu)
                                     if ch.d > shift else 0.0)
        if U_in > 0.0:
            u = 0.5 * U_in * (x + 1.0)
            w = 0.5 * U_in * wq * (ss_star / st) * wm_
            s = -np.log1p(-np.minimum(u, U_BELOW_ONE)) / st * mu   # depth of the first collision
            # g < 0 displaces upwards: at most to the top
            ts.append(np.maximum(s + shift, 0.0))
            ws.append(w)
        if finite:
            # unscattered: the real extinction; the delta-P1 forward peak that crosses the
            # layer unscattered in the model is forward-scattered light
            bal += wm_ * math.exp(-ch.st * ch.d / mu)
            fwd += wm_ * (math.exp(-st * ch.d / mu) - math.exp(-ch.st * ch.d / mu))
            if U > U_in:
                # scattered forward out of the layer: attenuated along the straight path at
                # mean cosine g* mu from the collision to the bottom
                u = U_in + 0.5 * (U - U_in) * (xf + 1.0)
                w = 0.5 * (U - U_in) * wf * (ss_star / st) * wm_
                s = np.minimum(-np.log1p(-np.minimum(u, U_BELOW_ONE)) / st * mu, ch.d)
                fwd += float(np.sum(w * np.exp(-ch.sa * (ch.d - s) / (max(g_star, 1e-3) * mu))))
    if not ts:
        ts, ws = [np.zeros(0)], [np.zeros(0)]
    return BeamSources(np.concatenate(ts), np.concatenate(ws), bal, fwd, nq)


# The largest float below 1: a beam fraction u that rounds to 1 (an optically thick layer,
# 1 - e^{-sigma_t d} = 1.0 in float64 beyond sigma_t d ~ 37) would put the collision at
# infinite depth and the forward sum at e^{+inf} (found by the thorough stability profile:
# a 11 mm layer with sigma_t d = 147; tests/test_profiles.py
# test_optically_thick_forward_scattering_layer_stays_finite); capped, it lands at the
# layer's bottom.
U_BELOW_ONE = float(np.nextafter(1.0, 0.0))


def _heights(ch: DiffusionConstants, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed depths below the top of the positive and negative images, (S, P) each."""
    if math.isinf(ch.d):
        return t[:, None], (-t - 2.0 * ch.zb_t)[:, None]
    i = np.arange(-ch.poles, ch.poles + 1, dtype=np.float64)
    period = 2.0 * (ch.d + ch.zb_t + ch.zb_b)
    zp = i[None, :] * period + t[:, None]
    zm = zp - 2.0 * (t[:, None] + ch.zb_t)
    return zp, zm


def _side(ch: DiffusionConstants, zp, zm, side: str):
    """Heights above the exit plane and the exitance weights for ``side`` (top or bottom)."""
    if side == "top":
        return zp, zm, ch.cphi_t, ch.ce_t
    return ch.d - zp, ch.d - zm, ch.cphi_b, ch.ce_b


def image_sum(ch: DiffusionConstants, src: BeamSources, side: str, what: str,
              r: np.ndarray | None = None):
    """Sum over sources and images of the exitance through ``side``.

    what = "density": 1/mm^2 at radii r; "energy": energy inside radius r (cumulative);
    "total": the whole plane.  Per image of signed height z and distance q = sqrt(r^2 + z^2):
    flux  J  = z (1 + s q) e^{-s q} / (4 pi q^3),  int = (sgn z e^{-s|z|} - z e^{-s q} / q) / 2,
    fluence phi = e^{-s q} / (4 pi D q),           int = (e^{-s|z|} - e^{-s q}) / (2 D s)
    (s = sigma_tr; at s = 0 the fluence integrals drop a constant common to all images,
    which cancels between the positive and negative ones).
    """
    if src.t.size == 0:
        return 0.0 if what == "total" else np.zeros(np.asarray(r).size)
    zp, zm = _heights(ch, src.t)
    wp = np.broadcast_to(src.w[:, None], zp.shape)
    wm = -np.broadcast_to(src.w[:, None], zm.shape)
    if ch.tail:
        # the images beyond pair n as their integral: pairs i > n are a line of dipoles,
        # sum_{i>n} [f(iP + t) - f(iP - t - 2 z_b)] ~ -(1/P) int f over [b - t - 2 z_b, b + t]
        # (b = (n + 1/2) P), likewise +(1/P) int f over [-b - t - 2 z_b, -b + t] for i < -n;
        # 2-point Gauss over each interval; plus the midpoint rule's first Euler-Maclaurin
        # term, +-g'(+-(n + 1/2)) / 24, by the difference of pairs n + 1 and n
        period = 2.0 * (ch.d + ch.zb_t + ch.zb_b)
        b = (ch.poles + 0.5) * period
        half = (src.t + ch.zb_t)[:, None]
        x = np.array([[-1.0, 1.0]]) / math.sqrt(3.0)
        wt = np.broadcast_to((half / period) * src.w[:, None], (src.t.size, 2))
        ends = np.array([0, -1])
        w24 = src.w[:, None] / 24.0
        wp, wm = wp.copy(), wm.copy()
        wp[:, ends] -= w24
        wm[:, ends] += w24
        zx = np.concatenate([zp[:, :1] - period, zp[:, -1:] + period], axis=1)   # pairs -+(n+1)
        zmx = np.concatenate([zm[:, :1] - period, zm[:, -1:] + period], axis=1)
        zp = np.concatenate([zp, zx, -b - ch.zb_t + half * x], axis=1)
        wp = np.concatenate([wp, w24, w24, wt], axis=1)
        zm = np.concatenate([zm, zmx, b - ch.zb_t + half * x], axis=1)
        wm = np.concatenate([wm, -w24, -w24, -wt], axis=1)
    zp, zm, cphi, ce = _side(ch, zp, zm, side)
    sig, D = ch.sig, ch.D
    z = np.concatenate([zp, zm], axis=1).ravel()             # (S, 2P)
    sgn = np.concatenate([wp, wm], axis=1).ravel()
    az = np.abs(z)
    ez = np.exp(-sig * az)
    if what == "total":
        flux = 0.5 * np.sign(z) * ez
        flu = ez / (2.0 * D * sig) if sig > 0 else -az / (2.0 * D)
        return float(np.sum(sgn * (ce * flux + cphi * flu)))
    r = np.asarray(r, np.float64).ravel()
    if r.size and r.max() > ch.reach:
        # the layer's field is zero beyond its reach (POLE_REACH): density 0, energy held
        inside = r <= ch.reach
        out = np.zeros(r.size)
        if what == "energy":
            e = image_sum(ch, src, side, what, np.append(r[inside], ch.reach))
            out[inside] = e[:-1]
            out[~inside] = e[-1]
        else:
            out[inside] = image_sum(ch, src, side, what, r[inside])
        return out
    out = np.zeros(r.size)
    step = max(1, int(IMAGE_SUM_CHUNK // max(z.size, 1)))
    for a in range(0, r.size, step):
        rr = r[a:a + step][:, None]
        q = np.sqrt(rr * rr + z[None, :] ** 2)
        qs = np.maximum(q, 1e-300)
        eq = np.exp(-sig * q)
        if what == "density":
            val = ce * z * (1.0 + sig * q) * eq / (4.0 * np.pi * qs**3) \
                + cphi * eq / (4.0 * np.pi * D * qs)
        else:
            near = np.where(q > 0, z * eq / qs, np.sign(z))
            # e^{-s|z|} - e^{-s q} loses < 1e-11 relative at the smallest radii tabulated
            flu = (ez - eq) / (2.0 * D * sig) if sig > 0 else (q - az) / (2.0 * D)
            val = ce * 0.5 * (np.sign(z) * ez - near) + cphi * flu
        out[a:a + step] = val @ sgn
    return out


@dataclass
class LayerResponse:
    """One layer lit by unit flux (collimated or diffuse) from one side, after the first-order
    Fresnel return of its direct light at the far side: diffuse R and T as
    (chan, sources, side, weight) terms, their totals, and the direct light (a delta at
    r = 0): leaving through the far side (``direct``; collimated for collimated incidence,
    diffuse in angle for diffuse incidence) and returned through the near side."""

    terms_R: list
    terms_T: list
    Rd: float
    Td: float
    direct: float
    R_direct: float
    ballistic: float     # the unscattered part of ``direct``
    forward: float       # the forward-scattered part of ``direct``
    dropped: float       # second-order Fresnel energy not followed
    returned: float = 0.0  # direct light the far side reflected back into the layer
    unshifted: bool = False  # sources kept at their collision depths (layer too thin)
    ch: DiffusionConstants | None = None
    diffuse: bool = False
    # the far side's reflections of the direct light, (energy, how it arrived: "point"
    # (collimated unscattered) / "forward" / "diffuse", the response of the layer to it)
    returns: tuple = ()


def layer_response(ch: DiffusionConstants, nq: int = NQ_BEAM, diffuse: bool = False,
                   fresnel_return: bool = True) -> LayerResponse:
    src = beam_sources(ch, nq, diffuse)
    finite = not math.isinf(ch.d)
    unshifted = False
    if finite and src.t.size == 0:
        # a layer thinner than the P1 displacement: every source would leave it; keep the
        # sources at their collision depths so the layer still has R and T shapes (their
        # totals come from the exact plane-parallel solution)
        src = beam_sources(ch, nq, diffuse, shift_on=False)
        unshifted = True
    Rd = image_sum(ch, src, "top", "total")
    Td = image_sum(ch, src, "bot", "total") if finite else 0.0
    terms_R = [(ch, src, "top", 1.0)]
    terms_T = [(ch, src, "bot", 1.0)] if finite else []
    # Fresnel at the far side: collimated ballistic light at normal incidence, forward-
    # scattered light as once-scattered HG light, and all direct light of diffuse incidence
    # as diffuse light
    f_col, f_fwd, f_dif = ch.fr_b
    f_bal, f_fwd = (f_dif, f_dif) if diffuse else (f_col, f_fwd)
    bal_out, fwd_out = src.ballistic * (1.0 - f_bal), src.forward * (1.0 - f_fwd)
    resp = LayerResponse(terms_R, terms_T, Rd, Td, bal_out + fwd_out, 0.0, bal_out, fwd_out, 0.0)
    resp.unshifted = unshifted
    resp.ch, resp.diffuse = ch, diffuse
    back_c = src.ballistic * f_bal if not diffuse else 0.0
    back_d = src.forward * f_fwd + (src.ballistic * f_bal if diffuse else 0.0)
    resp.returned = back_c + back_d
    if not finite or not fresnel_return or back_c + back_d <= 0.0:
        return resp
    # the reflected direct light enters the layer again from below, once
    fl = lit_from_below(ch)
    returns = []
    for back, dif in ((back_c, False), (back_d, True)):
        if back <= 0.0:
            continue
        r = layer_response(fl, nq, dif, fresnel_return=False)
        returns.append((back, "point" if not dif else ("diffuse" if diffuse else "forward"), r))
        resp.terms_R += [(c_, s_, sd, wt * back) for c_, s_, sd, wt in r.terms_T]
        resp.terms_T += [(c_, s_, sd, wt * back) for c_, s_, sd, wt in r.terms_R]
        resp.Rd += back * r.Td
        resp.Td += back * r.Rd
        resp.R_direct += back * r.direct
        resp.dropped += back * r.returned
    resp.returns = tuple(returns)
    return resp


def direct_spreads(resp: LayerResponse) -> tuple[RadialShape | None, float, RadialShape | None]:
    """Where the direct light of ``resp`` lands (:mod:`dermis.optics.forward_spread`):
    (shape of the spread part of ``direct``: the forward-scattered part for collimated
    incidence, all of it for diffuse incidence; the part of ``R_direct`` that stays at
    r = 0; shape of the rest of ``R_direct``).  Shapes are normalised (weight 1); None
    where there is no such light or the layer is semi-infinite."""
    ch = resp.ch
    if ch is None or math.isinf(ch.d) or ch.diffusion != "pbd":
        return None, resp.R_direct, None
    layer = (ch.d, ch.sa, ch.ss, ch.g)
    # the forward light of a collimated beam: as many small-angle scattering orders as its
    # energy holds (optics/forward_spread.py forward_shape)
    energy = _collimated_forward(ch)

    def forward(eta: float, which: str):
        return forward_shape(*layer, eta, which, energy) if ch.ss > 0 else None

    # what leaves through the far face (its Fresnel transmission by direction), and what it
    # reflects back up (its reflectance), which then leaves through the top
    if resp.diffuse:
        shape_T = diffuse_shape(*layer, resp.ballistic, resp.forward, ch.eta_b, "T", energy)
    else:
        shape_T = forward(ch.eta_b, "T") if resp.forward > 0 else None
    point, parts = 0.0, []
    for back, arrived, r in resp.returns:
        # the returned light crosses the layer again: its spread on the way down, then the
        # direct light's spread on the way up (point: the unscattered beam reflected)
        if arrived == "point":
            point += back * r.ballistic
            parts.append((back * r.forward, forward(ch.eta_t, "T")))
            continue
        if r.direct <= 0.0 or (ch.ss <= 0.0 and arrived == "forward") or \
                (arrived == "diffuse" and resp.direct <= 0.0):
            point += back * r.direct
            continue
        parts.append((back * r.direct, _returned(layer, arrived, ch.eta_t, ch.eta_b,
                                                 resp.ballistic, resp.forward, r.ballistic,
                                                 r.forward, energy)))
    shape_R = mix([(w, sh) for w, sh in parts if sh is not None])
    point += sum(w for w, sh in parts if sh is None)
    return (shape_T.scaled(1.0) if shape_T is not None else None, point,
            shape_R.scaled(1.0) if shape_R is not None else None)


@lru_cache(maxsize=256)
def _returned(layer: tuple, arrived: str, eta_t: float, eta_b: float, bal_down: float,
              fwd_down: float, bal_up: float, fwd_up: float, energy: float) -> RadialShape:
    """Spread of direct light the far face reflected: down to it ("forward": scattered out
    of a collimated beam; "diffuse": diffuse incidence's direct light), reflected, and up
    through the top as diffuse incidence's direct light (normalised)."""
    up = diffuse_shape(*layer, bal_up, fwd_up, eta_t, "T", energy)
    down = forward_shape(*layer, eta_b, "R", energy) if arrived == "forward" else \
        diffuse_shape(*layer, bal_down, fwd_down, eta_b, "R", energy)
    return convolve(down.scaled(1.0), up.scaled(1.0))


@lru_cache(maxsize=256)
def _collimated_forward(ch: DiffusionConstants) -> float:
    """The light a collimated beam at normal incidence leaves the layer with, scattered
    forward (per unit flux, before the far face)."""
    return beam_sources(ch, NQ_BEAM).forward


def direct_parts(resp: LayerResponse, R_delta: float, T_delta: float, diffuse: bool,
                 exact_Tu: float | None = None):
    """Split the direct totals of :func:`scaled_to_exact` (``R_delta``, ``T_delta``) into
    what stays at r = 0 and what spreads: (R at r = 0, R spread as a weighted
    :class:`RadialShape` or None, T at r = 0, T spread or None).  For collimated incidence
    the unscattered beam (``exact_Tu`` when given) stays at r = 0."""
    shape_T, r_point, shape_R = direct_spreads(resp)
    T_point = T_delta
    T_spread = None
    if shape_T is not None:
        T_point = 0.0 if diffuse else min(T_delta, resp.ballistic if exact_Tu is None
                                          else exact_Tu)
        if T_delta - T_point > 0.0:
            T_spread = shape_T.scaled(T_delta - T_point)
        else:
            T_point = T_delta
    R_point, R_spread = R_delta, None
    if shape_R is not None and resp.R_direct > 0.0:
        R_point = R_delta * min(r_point / resp.R_direct, 1.0)
        if R_delta - R_point > 0.0:
            R_spread = shape_R.scaled(R_delta - R_point)
        else:
            R_point = R_delta
    return R_point, R_spread, T_point, T_spread


def evaluate_terms(terms, what: str, r: np.ndarray) -> np.ndarray:
    """Sum of ``terms``: diffusion terms (ch, sources, side, weight) and spread direct light
    (:class:`~dermis.optics.forward_spread.RadialShape`, cumulative energy only)."""
    out = np.zeros(np.asarray(r).size)
    for term in terms:
        if isinstance(term, RadialShape):
            if what != "energy":
                raise DermisError(f"profiles: direct light has no {what!r} (energy only)")
            out += term.energy(np.asarray(r, np.float64).ravel())
            continue
        ch, src, side, wt = term
        if src.t.size:
            out += wt * image_sum(ch, src, side, what, r)
    return out


def relative_indices(stack: LayerStack, k: int) -> tuple[float, float]:
    """Relative eta (layer / neighbour) at the top and bottom boundary of layer k."""
    lay = stack.layers
    above = lay[k - 1].eta if k > 0 else stack.eta_above
    below = lay[k + 1].eta if k + 1 < len(lay) else stack.eta_below
    return lay[k].eta / above, lay[k].eta / below


def check_diffusion(diffusion: str) -> None:
    if diffusion not in DIFFUSION_MODELS:
        raise DermisError(f"profiles: diffusion = {diffusion!r}: must be one of "
                          + ", ".join(repr(m) for m in DIFFUSION_MODELS))


def multipole_profiles(layer: Layer, r_mm, *, eta_above: float, eta_below: float,
                       poles: int | None = DEFAULT_POLES, diffusion: str = "pbd",
                       nq: int = NQ_BEAM) -> tuple[np.ndarray, np.ndarray]:
    """Point values of the diffusion R(r) and T(r) of one layer lit from above.

    Parameters
    ----------
    layer : Layer
        Thickness (mm, ``inf`` for a semi-infinite layer), eta, RGB coefficients (1/mm), g.
    r_mm : (N,) array_like
        Radii, mm.
    eta_above, eta_below : float
        Refractive index of the media (or layers) just above and below this layer.
    poles : int or None
        n in the pole pairs i = -n..n (ignored for a semi-infinite layer); None picks n per
        channel so the first omitted pair is damped by e^{-20} (10 <= n <= 2000).
    diffusion : {"pbd", "dj2005"}
        Per-layer model (module docstring).
    nq : int
        Beam quadrature nodes ("pbd").

    Returns
    -------
    R, T : (N, 3) float64 ndarray, 1/mm^2
        Diffuse reflectance and transmittance densities, per photon entering the top
        (T excludes the collimated delta at r = 0; T = 0 for a semi-infinite layer).
        integral 2 pi r R dr = Rd.  May be negative where diffusion fails (thin layers far
        from the source); :func:`~dermis.optics.layer_profiles.build_profiles` reports and
        removes such lobes.
    """
    check_diffusion(diffusion)
    r = np.asarray(r_mm, dtype=np.float64).ravel()
    R = np.zeros((r.size, 3))
    T = np.zeros((r.size, 3))
    if layer.thickness_mm == 0:
        return R, T
    for c in range(3):
        ch = diffusion_constants(layer, c, layer.eta / eta_above, layer.eta / eta_below,
                                 diffusion, poles)
        resp = layer_response(ch, nq)
        R[:, c] = evaluate_terms(resp.terms_R, "density", r)
        T[:, c] = evaluate_terms(resp.terms_T, "density", r)
    return R, T


def multipole_totals(layer: Layer, *, eta_above: float, eta_below: float,
                     poles: int | None = DEFAULT_POLES, diffusion: str = "pbd",
                     nq: int = NQ_BEAM, light: str = "collimated",
                     totals: str = "transport") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Totals of one layer lit from above: (R, T_diffuse, T_direct), (3,) each.

    light = "collimated" (normal incidence): T_direct is the collimated transmission, the
    unscattered e^{-sigma_t d} plus the light scattered forward out of the layer ("pbd";
    e^{-sigma_t' d} for "dj2005"), after the Fresnel reflection at the bottom; "diffuse"
    (Lambertian flux entering): T_direct is the direct (unscattered or forward) diffuse light.
    totals = "transport" (default, what the layer file uses): the exact plane-parallel
    values (adding-doubling), split between T_diffuse and T_direct as the diffusion model
    splits them; "diffusion": the per-layer model's own closed forms (what
    :func:`~dermis.optics.layer_profiles.build_profiles` adds with ``totals="diffusion"``).
    "dj2005" always gives its own.
    R includes light the bottom reflects straight back.
    """
    check_diffusion(diffusion)
    Rd, Td, col = np.zeros(3), np.zeros(3), np.zeros(3)
    if layer.thickness_mm == 0:
        return Rd, Td, np.ones(3)
    diffuse = light == "diffuse"
    if light not in ("collimated", "diffuse"):
        raise DermisError(f"profiles: light = {light!r}: must be 'collimated' or 'diffuse'")
    for c in range(3):
        ch = diffusion_constants(layer, c, layer.eta / eta_above, layer.eta / eta_below,
                                 diffusion, poles)
        resp = layer_response(ch, nq, diffuse=diffuse)
        ex = None
        if totals == "transport" and diffusion == "pbd":
            ex = exact_totals([layer], c, layer.eta / eta_above, layer.eta / eta_below)
            ex = (ex.Rd, ex.Td, None) if diffuse else (ex.Rc, ex.Tc, ex.Tu)
        Rf, Rdl, Tf, Tdl, _ = scaled_to_exact(resp, ex and ex[0], ex and ex[1], diffuse,
                                              ex and ex[2])
        Rd[c], Td[c], col[c] = Rf + Rdl, Tf, Tdl
    return Rd, Td, col


def scaled_to_exact(resp: LayerResponse, exact_R: float | None, exact_T: float | None,
                    diffuse: bool, exact_Tu: float | None = None
                    ) -> tuple[float, float, float, float, dict]:
    """Totals (R field, R delta, T field, T delta) of ``resp`` with its energies set to the
    exact plane-parallel ones (``None``: diffusion's own).  For collimated light the T delta
    is the unscattered light plus the forward-scattered part (collimated); for diffuse light
    it is the direct diffuse light.  Also returns the scale factors (exact / diffusion)."""
    eR = resp.Rd + resp.R_direct
    eT = resp.Td + (resp.direct if diffuse else resp.forward)
    sR = exact_R / eR if exact_R is not None and eR > 0 else 1.0
    sT = exact_T / eT if exact_T is not None and eT > 0 else 1.0
    info = {"R": sR, "T": sT}
    R_field, R_delta = resp.Rd * sR, resp.R_direct * sR
    if exact_R is not None and eR <= 0 < exact_R:
        R_delta = exact_R                        # no diffusion shape: the energy at r = 0
        info["R"] = "no shape"
    T_field = resp.Td * sT
    if diffuse:
        T_delta = resp.direct * sT
    else:
        T_delta = resp.forward * sT + (resp.ballistic if exact_Tu is None else exact_Tu)
    if exact_T is not None and eT <= 0 < exact_T:
        T_delta += exact_T
        info["T"] = "no shape"
    return R_field, R_delta, T_field, T_delta, info
