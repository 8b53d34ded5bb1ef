"""Radial diffuse reflectance/transmittance profiles of a layer stack (the "layer file").

Two profile models produce the same :class:`~dermis.pipeline.artifacts.LayerProfile`
(``build_profiles(stack, model=...)``; docs/profiles.md has the measurements):

* ``"multipole"``: diffusion per layer in float64 on the host for the radial shapes, layers
  combined by the adding equations in frequency space, every total set to the exact
  plane-parallel radiative-transfer value (adding-doubling).
* ``"monte_carlo"``: R(r), T(r) tabulated from the OpenCL layered Monte Carlo
  (:mod:`dermis.stages.mc_slab`) for the stack itself, with per-ring standard errors and
  radial splitting for the far rings.

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
all light added as collimated) for before/after comparisons; it is what the issue measured.

Exact totals (``totals="transport"``, the default with "pbd").  Adding-doubling of the 1-D
transport problem (HG with delta-M, Fresnel faces, directions split at the critical
angles) gives each layer's R and T for collimated and for diffuse light and, when all
layers share one eta, the whole stack's; the diffusion fields are scaled to them
(``info["scale_to_exact"]``: exact / diffusion, the diffusion model's own error).
``totals="diffusion"`` keeps diffusion's own totals.

Adding.  Layers are folded top-down, per spatial frequency (stack A above layer B): light
that A passes on collimated enters B as collimated light, diffuse light as diffuse light;
U = (tau_A R_Bc + R_Bd T_Ac) / (1 - R_Bd R'_Ad) goes up into A, R = R_Ac + T'_Ad U, and so
on (``_combine``).  The profiles are radially symmetric, so their 2-D grid is even in x and
y; the 2-D DFT of an even periodic grid is a 2-D DCT-I of one quadrant
(``scipy.fft.dctn(type=1)``), padded x2 against wrap-around.  Pixels hold ring averages
from each source's closed-form cumulative energy, and each spectrum's DC term is set to
its total exactly.

Negative values.  Diffusion sums can go negative (thin layers far from the source, FFT
ringing).  They are never clipped silently: every negative lobe beyond float64 round-off
is recorded in ``info["negative_lobes"]`` (layer, light, field, channel, radii, energy
fraction), set to zero, and the rest of that profile rescaled so its energy is kept.

Output table.  r_k = k h, values are averages over rings [r_k - h/2, r_k + h/2) (a disk for
k = 0), in 1/mm^2, so sum_k R_k * ring_area_k = the energy inside the table (exactly: the
radial fit is rescaled to the grid's energy inside its radius).  ``Rd``/``Tt`` are per
photon that entered the top surface (the specular reflection at entry excluded; MCML's
per-incident-photon values are these times 1 - R_sp) and include energy beyond the table;
``Tt`` includes the collimated transmission.  The cut-off radius is the smallest r_k whose
rings hold ``CUTOFF_FRACTION`` = 99.9 % of Rd.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft
from numpy.polynomial.legendre import leggauss

from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.artifacts import LayerProfile
from dermis.pipeline.errors import DermisError
from dermis.optics.fresnel import (diffusion_A, diffusion_boundary, fresnel_normal,
                                    fresnel_transmittance)
from dermis.optics.layers import (Layer, LayerStack, PROFILE_MODELS, DEFAULT_PROFILE_MODEL,
                                   DEFAULT_MC_PHOTONS, DEFAULT_MC_SEED)

__all__ = ["VERSION", "KERNELS", "NAME", "node", "run", "build_profiles", "multipole_profiles",
           "multipole_totals", "monte_carlo_profiles", "mc_bin_edges", "DEFAULT_POLES",
           "CUTOFF_FRACTION", "DIFFUSION_MODELS", "PROFILE_MODELS", "RD_CONVENTION"]

VERSION = 2   # 2: beam-integrated P1 diffusion with real extinction, explicit negative lobes,
              #    Monte Carlo tables

KERNELS = ()  # the Monte Carlo model builds mc_slab.cl through stages/mc_slab.py

DIFFUSION_MODELS = ("pbd", "dj2005")

RD_CONVENTION = ("per photon that entered the top surface: the specular reflection at entry "
                 "is not counted (multiply by 1 - R_sp for per incident photon)")

# Pole pairs i = -n..n.  Measured (tests/test_profiles.py::test03_pole_convergence): for the
# 0.25 mm epidermis of the two_layer preset Rd changes by 7e-6 from n = 2 to 5 and < 1e-12
# beyond; Donner-Jensen's public code used n = 5 (11 pairs).  A fixed n fails for thick,
# weakly absorbing slabs (a 5 mm slab with albedo 0.9999 gave negative tails at n = 10), so
# the default adapts n to sigma_tr and the slab period.
DEFAULT_POLES = None  # adaptive, see _chan
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
# sources leave the layer).  Measured (tests/test_profiles.py::test03_beam_convergence):
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
# Fraction of Rd inside the reported cut-off radius.
CUTOFF_FRACTION = 0.999
# Auto grid: spacing = min reduced mean free path / GRID_FINE (convergence test: R changes
# by < 0.5 % at r >= 2 mfp from 4 to 8 points per mfp), half-width = GRID_DECAY / sigma_tr_min
# (e^{-14} ~ 1e-6 of the dipole tail is beyond it), capped by GRID_MAX_MFP mean free paths
# (sigma_a = 0 has a power-law tail) and GRID_MAX_POINTS points per half-width.
GRID_FINE = 4.0
GRID_DECAY = 14.0
GRID_MAX_MFP = 300.0
GRID_MAX_POINTS = 1024
# A negative value counts as a lobe (and is reported) when its energy exceeds this fraction
# of the profile's energy; below it is float64 round-off of cancelling images.
NEGATIVE_ROUNDOFF = 1e-9


# ---------------------------------------------------------------------------------------
# One layer, one channel, one direction of travel


@dataclass(frozen=True)
class _Chan:
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
    mu = (np.arange(4000) + 0.5) / 4000
    F = 1.0 - fresnel_transmittance(mu, 1.0 / eta)
    hg = (1.0 - g * g) / (1.0 + g * g - 2.0 * g * mu) ** 1.5
    return (fresnel_normal(eta), float(np.sum(hg * F) / np.sum(hg)),
            float(2.0 * np.sum(F * mu) / 4000))


def _chan(layer: Layer, c: int, eta_top: float, eta_bot: float, diffusion: str,
          poles: int | None) -> _Chan:
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
    return _Chan(d, sa, ss, ssp, g, D, sig, zb_t, zb_b, cphi_t, ce_t, cphi_b, ce_b,
                 fr_t, fr_b, n, diffusion, reach, tail)


def _flip(ch: _Chan) -> _Chan:
    """The same layer lit from its bottom."""
    return _Chan(ch.d, ch.sa, ch.ss, ch.ssp, ch.g, ch.D, ch.sig, ch.zb_b, ch.zb_t, ch.cphi_b,
                 ch.ce_b, ch.cphi_t, ch.ce_t, ch.fr_b, ch.fr_t, ch.poles, ch.diffusion,
                 ch.reach, ch.tail)


@dataclass
class _Sources:
    """Diffusion sources for unit flux entering the top of one layer."""

    t: np.ndarray        # (S,) depths, mm (inside [0, d))
    w: np.ndarray        # (S,) strengths (albedo x quadrature weight)
    ballistic: float     # unscattered at the bottom (e^{-sigma_t d}; 2 E3(sigma_t d) if diffuse)
    forward: float       # scattered forward out of the bottom (collimated)
    nodes: int


def _sources(ch: _Chan, nq: int = NQ_BEAM, diffuse: bool = False,
             shift_on: bool = True) -> _Sources:
    """Sources for collimated flux at normal incidence, or for diffuse (Lambertian) flux:
    then the beam integral runs over ``NMU_DIFFUSE`` Gauss nodes in the cosine mu (weights
    2 mu dmu), each ray's collisions at depth mu s and its flux moment along mu."""
    finite = not math.isinf(ch.d)
    if ch.diffusion == "dj2005":
        # dermis <= 1: one source at the mean depth of the first reduced collision within the
        # slab, strength alpha' (1 - e^{-sigma_t' d}); e^{-sigma_t' d} passes through
        st, alpha = ch.stp, ch.ssp / ch.stp
        if not finite:
            return _Sources(np.array([1.0 / st]), np.array([alpha]), 0.0, 0.0, 1)
        x = st * ch.d
        tau = math.exp(-x)
        collided = -math.expm1(-x)
        z0 = 1.0 / st - ch.d * tau / collided if x > 1e-4 else ch.d * (0.5 - x / 12.0)
        return _Sources(np.array([z0]), np.array([alpha * collided]), tau, 0.0, 1)
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
            ts.append(np.maximum(s + shift, 0.0))       # g < 0 displaces upwards: at most to the top
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
    return _Sources(np.concatenate(ts), np.concatenate(ws), bal, fwd, nq)


# The largest float below 1: a beam fraction u that rounds to 1 (an optically thick layer,
# 1 - e^{-sigma_t d} = 1.0 in float64 beyond sigma_t d ~ 37) would put the collision at
# infinite depth and the forward sum at e^{+inf} (found by the thorough stability profile:
# a 11 mm layer with sigma_t d = 147, issue 16); capped, it lands at the layer's bottom.
U_BELOW_ONE = float(np.nextafter(1.0, 0.0))


def _heights(ch: _Chan, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed depths below the top of the positive and negative images, (S, P) each."""
    if math.isinf(ch.d):
        return t[:, None], (-t - 2.0 * ch.zb_t)[:, None]
    i = np.arange(-ch.poles, ch.poles + 1, dtype=np.float64)
    period = 2.0 * (ch.d + ch.zb_t + ch.zb_b)
    zp = i[None, :] * period + t[:, None]
    zm = zp - 2.0 * (t[:, None] + ch.zb_t)
    return zp, zm


def _side(ch: _Chan, zp, zm, side: str):
    """Heights above the exit plane and the exitance weights for ``side`` (top or bottom)."""
    if side == "top":
        return zp, zm, ch.cphi_t, ch.ce_t
    return ch.d - zp, ch.d - zm, ch.cphi_b, ch.ce_b


def _image_sum(ch: _Chan, src: _Sources, side: str, what: str, r: np.ndarray | None = None):
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
            e = _image_sum(ch, src, side, what, np.append(r[inside], ch.reach))
            out[inside] = e[:-1]
            out[~inside] = e[-1]
        else:
            out[inside] = _image_sum(ch, src, side, what, r[inside])
        return out
    out = np.zeros(r.size)
    step = max(1, int(4_000_000 // max(z.size, 1)))
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
class _Response:
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


def _response(ch: _Chan, nq: int = NQ_BEAM, diffuse: bool = False,
              fresnel_return: bool = True) -> _Response:
    src = _sources(ch, nq, diffuse)
    finite = not math.isinf(ch.d)
    unshifted = False
    if finite and src.t.size == 0:
        # a layer thinner than the P1 displacement: every source would leave it; keep the
        # sources at their collision depths so the layer still has R and T shapes (their
        # totals come from the exact plane-parallel solution)
        src = _sources(ch, nq, diffuse, shift_on=False)
        unshifted = True
    Rd = _image_sum(ch, src, "top", "total")
    Td = _image_sum(ch, src, "bot", "total") if finite else 0.0
    terms_R = [(ch, src, "top", 1.0)]
    terms_T = [(ch, src, "bot", 1.0)] if finite else []
    # Fresnel at the far side: collimated ballistic light at normal incidence, forward-
    # scattered light as once-scattered HG light, and all direct light of diffuse incidence
    # as diffuse light
    f_col, f_fwd, f_dif = ch.fr_b
    f_bal, f_fwd = (f_dif, f_dif) if diffuse else (f_col, f_fwd)
    bal_out, fwd_out = src.ballistic * (1.0 - f_bal), src.forward * (1.0 - f_fwd)
    resp = _Response(terms_R, terms_T, Rd, Td, bal_out + fwd_out, 0.0, bal_out, fwd_out, 0.0)
    resp.unshifted = unshifted
    back_c = src.ballistic * f_bal if not diffuse else 0.0
    back_d = src.forward * f_fwd + (src.ballistic * f_bal if diffuse else 0.0)
    resp.returned = back_c + back_d
    if not finite or not fresnel_return or back_c + back_d <= 0.0:
        return resp
    # the reflected direct light enters the layer again from below, once
    fl = _flip(ch)
    for back, dif in ((back_c, False), (back_d, True)):
        if back <= 0.0:
            continue
        r = _response(fl, nq, dif, fresnel_return=False)
        resp.terms_R += [(c_, s_, sd, wt * back) for c_, s_, sd, wt in r.terms_T]
        resp.terms_T += [(c_, s_, sd, wt * back) for c_, s_, sd, wt in r.terms_R]
        resp.Rd += back * r.Td
        resp.Td += back * r.Rd
        resp.R_direct += back * r.direct
        resp.dropped += back * r.returned
    return resp


def _terms_eval(terms, what: str, r: np.ndarray) -> np.ndarray:
    out = np.zeros(np.asarray(r).size)
    for ch, src, side, wt in terms:
        if src.t.size:
            out += wt * _image_sum(ch, src, side, what, r)
    return out


def _eta_rel(stack: LayerStack, k: int) -> tuple[float, float]:
    """Relative eta (layer / neighbour) at the top and bottom boundary of layer k."""
    lay = stack.layers
    above = lay[k - 1].eta if k > 0 else stack.eta_above
    below = lay[k + 1].eta if k + 1 < len(lay) else stack.eta_below
    return lay[k].eta / above, lay[k].eta / below


def _check_diffusion(diffusion: str) -> None:
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
        from the source); :func:`build_profiles` reports and removes such lobes.
    """
    _check_diffusion(diffusion)
    r = np.asarray(r_mm, dtype=np.float64).ravel()
    R = np.zeros((r.size, 3))
    T = np.zeros((r.size, 3))
    if layer.thickness_mm == 0:
        return R, T
    for c in range(3):
        ch = _chan(layer, c, layer.eta / eta_above, layer.eta / eta_below, diffusion, poles)
        resp = _response(ch, nq)
        R[:, c] = _terms_eval(resp.terms_R, "density", r)
        T[:, c] = _terms_eval(resp.terms_T, "density", r)
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
    :func:`build_profiles` adds with ``totals="diffusion"``).  "dj2005" always gives its own.
    R includes light the bottom reflects straight back.
    """
    _check_diffusion(diffusion)
    Rd, Td, col = np.zeros(3), np.zeros(3), np.zeros(3)
    if layer.thickness_mm == 0:
        return Rd, Td, np.ones(3)
    diffuse = light == "diffuse"
    if light not in ("collimated", "diffuse"):
        raise DermisError(f"profiles: light = {light!r}: must be 'collimated' or 'diffuse'")
    for c in range(3):
        ch = _chan(layer, c, layer.eta / eta_above, layer.eta / eta_below, diffusion, poles)
        resp = _response(ch, nq, diffuse=diffuse)
        ex = None
        if totals == "transport" and diffusion == "pbd":
            ex = _ad_totals([layer], c, layer.eta / eta_above, layer.eta / eta_below)
            ex = (ex.Rd, ex.Td, None) if diffuse else (ex.Rc, ex.Tc, ex.Tu)
        Rf, Rdl, Tf, Tdl, _ = _scaled(resp, ex and ex[0], ex and ex[1], diffuse, ex and ex[2])
        Rd[c], Td[c], col[c] = Rf + Rdl, Tf, Tdl
    return Rd, Td, col


# ---------------------------------------------------------------------------------------
# Exact plane-parallel totals: adding-doubling (van de Hulst 1980; Prahl 1995)
#
# The 1-D radiative transfer of the stack (HG phase with delta-M, Fresnel boundaries) gives
# the totals diffusion gets wrong in thin and absorbing layers (docs/profiles.md).  Fluxes
# are vectors over quadrature directions mu_i in (0, 1] (one per hemisphere), each entry the
# power travelling in that direction, so layers compose by plain matrix products.  The
# quadrature is split at every critical angle of the boundaries (Fresnel has a kink there;
# without the split the totals converge like 1/N) and its last node is mu = 1 (Radau), the
# direction of the entering beam.  Checked against van de Hulst's slab (Rd 0.09739, Tt
# 0.66096) and Chandrasekhar's semi-infinite albedo (0.41495) to 5 digits, and against the
# Monte Carlo (tests/test_profile_mc.py).

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


def _fresnel_nodes(mu: np.ndarray, eta: float) -> np.ndarray:
    return np.zeros_like(mu) if eta == 1.0 else 1.0 - fresnel_transmittance(mu, 1.0 / eta)


@dataclass
class _Exact:
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


def _ad_totals(layers, c: int, eta_top: float, eta_bot: float) -> _Exact:
    """Exact totals of ``layers`` (all of the same eta) between media of relative index
    eta_top, eta_bot (layer / outside) above and below."""
    eta = layers[0].eta
    S, n, cuts = _ad_layers(None, c, layers, (eta / eta_top, eta / eta_bot))
    mu, w = _ad_quadrature(n, cuts)
    Ft, Fb = _fresnel_nodes(mu, eta_top), _fresnel_nodes(mu, eta_bot)
    col = np.zeros(len(mu))
    col[-1] = 1.0
    lam = 2.0 * mu * w
    lam /= lam.sum()
    Rc, Tall = _ad_bounded(S, Ft, Fb, col)
    # unscattered: the beam e^{-sigma_t d} through every layer, with its normal-incidence
    # Fresnel bounces between the outer faces
    tau = sum(float(l.sigma_a[c] + l.sigma_s[c]) * float(l.thickness_mm) for l in layers)
    r0t, r0b = fresnel_normal(eta_top), fresnel_normal(eta_bot)
    Tu = 0.0 if math.isinf(tau) else math.exp(-tau) * (1 - r0b) / (1 - r0t * r0b * math.exp(-2 * tau))
    Rd, Td = _ad_bounded(S, Ft, Fb, lam)
    Sf = (S[2], S[3], S[0], S[1])
    Rud, Tud = _ad_bounded(Sf, Fb, Ft, lam)
    return _Exact(Rc, max(Tall - Tu, 0.0), Tu, Rd, Td, Rud, Tud)


# ---------------------------------------------------------------------------------------
# The layer file of a stack


def _auto_grid(stack: LayerStack) -> tuple[float, float]:
    """(spacing h, half-width r_max) in mm from the stack's length scales (see constants)."""
    mfp_min = min(1.0 / (a + s) for l in stack.layers for a, s in zip(l.sigma_a, l.sigma_s_prime))
    mfp_max = max(1.0 / (a + s) for l in stack.layers for a, s in zip(l.sigma_a, l.sigma_s_prime))
    str_min = min(math.sqrt(3 * a * (a + s)) for l in stack.layers
                  for a, s in zip(l.sigma_a, l.sigma_s_prime))
    thin = min((l.thickness_mm for l in stack.layers), default=math.inf)
    h = min(mfp_min, thin) / GRID_FINE
    r_max = GRID_MAX_MFP * mfp_max
    if str_min > 0:
        r_max = min(r_max, GRID_DECAY / str_min)
    r_max = max(r_max, 20.0 * h)
    h = max(h, r_max / GRID_MAX_POINTS)
    return h, r_max


class _Lobes:
    """Collects negative lobes: where a diffusion sum (or the inverse transform) went below
    zero beyond round-off, and how much energy that was."""

    def __init__(self):
        self.items: list[dict] = []
        self.min_rel = 0.0

    def fix(self, vals: np.ndarray, area: np.ndarray, radius: np.ndarray, where: dict,
            total: float | None = None) -> np.ndarray:
        """Zero the negative values of ``vals`` (densities on cells of ``area`` at ``radius``)
        and rescale the rest to ``total`` (default: the signed energy before), recording
        the lobe if it exceeds round-off."""
        peak = float(np.abs(vals).max()) if vals.size else 0.0
        if peak <= 0.0:
            return vals
        neg = vals < 0
        self.min_rel = min(self.min_rel, float(vals.min() / peak))
        if not neg.any():
            if total is None:
                return vals
            e_all = float(np.sum(vals * area))
            return vals * (total / e_all) if e_all > 0 and total > 0 else vals
        e_all = float(np.sum(vals * area))
        e_neg = float(-np.sum(vals[neg] * area[neg]))
        e_pos = e_all + e_neg
        keep = e_all if total is None else total
        out = np.where(neg, 0.0, vals)
        if e_pos > 0 and keep > 0:
            out = out * (keep / e_pos)
        frac = e_neg / max(e_pos, 1e-300)
        if frac > NEGATIVE_ROUNDOFF:
            rn = radius[neg]
            self.items.append(dict(where, r_mm=[float(rn.min()), float(rn.max())],
                                   energy_fraction=frac, min_rel=float(vals.min() / peak)))
        return out


def build_profiles(stack: LayerStack, *, model: str = "multipole", poles: int | None = None,
                   grid: tuple[float, float] | None = None, force_fft: bool = False,
                   diffusion: str = "pbd", nq: int = NQ_BEAM, photons: int = DEFAULT_MC_PHOTONS,
                   seed: int = DEFAULT_MC_SEED, env=None, progress=None,
                   totals: str = "transport") -> LayerProfile:
    """Build the layer file of ``stack``: radial R(r), T(r) per channel and totals.

    Parameters
    ----------
    stack : LayerStack
        Validated layers, top to bottom (see :mod:`dermis.optics.layers`).
    model : {"multipole", "monte_carlo"}
        Diffusion (layers added in frequency space) or the Monte Carlo table
        (:func:`monte_carlo_profiles`; uses ``photons``, ``seed``, ``env``).
    poles : int, optional
        n in the pole pairs i = -n..n per finite layer (default: adaptive).
    grid : (float, float), optional
        (spacing h, half-width r_max) in mm of the radial table and of the 2-D FFT grid
        (which is 2 r_max wide with x2 zero padding).  Default: from the stack's mean free
        paths and sigma_tr (``_auto_grid``).  "multipole" only.
    force_fft : bool
        Route a single layer through the FFT combination too (tests the transform path);
        by default a single layer is tabulated directly from the closed forms.
    diffusion : {"pbd", "dj2005"}
        Per-layer diffusion model (module docstring); "dj2005" is dermis <= 1's.
    nq : int
        Beam quadrature nodes per layer and channel ("pbd").
    photons, seed, env, progress
        Monte Carlo photons per channel, seed, OpenCL env, progress callback
        ("monte_carlo").
    totals : {"transport", "diffusion"}
        "transport" (default): every energy (per layer, per kind of incident light, and of
        the whole stack) is set to the exact plane-parallel radiative-transfer value
        (adding-doubling), diffusion supplying the radial shapes; "diffusion": diffusion's
        own totals (to measure its error).  "dj2005" always uses its own.

    Returns
    -------
    LayerProfile
        r_mm (N,); R, T (N, 3) ring averages in 1/mm^2; Rd, Tt (3,) totals per entered
        photon (``RD_CONVENTION``) including energy beyond the table and the collimated
        transmission; cutoff_mm (3,), the smallest r_k holding 99.9 % of Rd;
        energy_beyond_cutoff (3,).  ``info`` holds the model, the stack, poles, grid,
        T_ballistic (unscattered) and T_forward, the negative lobes removed (with where and
        how much energy), the most negative value relative to the peak before removal
        (``min_clipped_rel``) and the build time.

    References
    ----------
    Donner, C., Jensen, H. W. (2005). Light diffusion in multi-layered translucent
    materials. ACM TOG 24(3), 1032-1039. doi:10.1145/1073204.1073308
    d'Eon, E. (2012). A better dipole. Technical report.
    Habel, R., Christensen, P. H., Jarosz, W. (2013). Photon beam diffusion: a hybrid Monte
    Carlo method for subsurface scattering. Computer Graphics Forum 32(4).
    doi:10.1111/cgf.12148
    """
    if model not in PROFILE_MODELS:
        raise DermisError(f"profiles: model = {model!r}: must be one of "
                          + ", ".join(repr(m) for m in PROFILE_MODELS))
    if model == "monte_carlo":
        return monte_carlo_profiles(stack, photons=photons, seed=seed, env=env,
                                    progress=progress)
    _check_diffusion(diffusion)
    t0 = time.perf_counter()
    poles = DEFAULT_POLES if poles is None else int(poles)
    if poles is not None and poles < 0:
        raise DermisError(f"profiles: poles = {poles}: must be >= 0")
    full = stack
    stack = stack.nonzero()
    if not stack.layers:
        raise DermisError("profiles: every layer has thickness 0; nothing to profile")
    h, r_max = grid if grid is not None else _auto_grid(stack)
    if not (h > 0 and r_max > h and math.isfinite(h) and math.isfinite(r_max)):
        raise DermisError(f"profiles: grid = ({h}, {r_max}) (mm): need 0 < spacing < half-width")
    n = int(math.ceil(r_max / h))
    if n > 8192:
        raise DermisError(f"profiles: grid = ({h}, {r_max}) (mm) needs {n} points per half-width;"
                          " at most 8192 are allowed (use a coarser spacing)")
    r_out = np.arange(n + 1) * h
    edges = np.concatenate([[0.0], (np.arange(n + 1) + 0.5) * h])
    ring_area = np.pi * np.diff(edges**2)

    info = {"model": "multipole", "diffusion": diffusion, "layers": full.to_dict(),
            "poles": poles, "nq": nq, "grid_h_mm": h, "grid_rmax_mm": n * h,
            "convention": RD_CONVENTION}
    lobes = _Lobes()
    chans = [[_chan(lay, c, *_eta_rel(stack, k), diffusion, poles) for c in range(3)]
             for k, lay in enumerate(stack.layers)]
    info["poles_used"] = [[ch.poles for ch in row] for row in chans]
    if totals not in ("transport", "diffusion"):
        raise DermisError(f"profiles: totals = {totals!r}: must be 'transport' or 'diffusion'")
    use_exact = totals == "transport" and diffusion == "pbd"
    exact = exact_stack = None
    if use_exact:
        # exact plane-parallel totals per layer (with its neighbours' indices) and, when
        # every layer has the same eta, of the whole stack
        exact = [[_ad_totals([lay], c, *_eta_rel(stack, k)) for c in range(3)]
                 for k, lay in enumerate(stack.layers)]
        if len(stack.layers) > 1 and len({l.eta for l in stack.layers}) == 1:
            eta = stack.layers[0].eta
            exact_stack = [_ad_totals(stack.layers, c, eta / stack.eta_above,
                                      eta / stack.eta_below) for c in range(3)]
            info["stack_totals"] = "adding-doubling of the whole stack"
        elif len(stack.layers) > 1:
            info["stack_totals"] = ("adding of the exact layer totals (layers of different eta: "
                                    "no whole-stack solution)")
    info["totals"] = totals if diffusion == "pbd" else "diffusion"
    scales: list = []
    if len(stack.layers) == 1 and not force_fft:
        R = np.zeros((n + 1, 3))
        T = np.zeros((n + 1, 3))
        Rd, Tt, bal, fwd, dropped = (np.zeros(3) for _ in range(5))
        for c in range(3):
            resp = _response(chans[0][c], nq)
            ex = exact[0][c] if exact is not None else None
            Rf, Rdl, Tf, Tdl, sc = _scaled(resp, ex and ex.Rc, ex and ex.Tc, False, ex and ex.Tu)
            scales.append(dict(layer=0, channel="RGB"[c], light="collimated", **sc))
            for key, terms, out, total in (("R", resp.terms_R, R, Rf), ("T", resp.terms_T, T, Tf)):
                if not terms:
                    continue
                vals = np.diff(_terms_eval(terms, "energy", edges)) / ring_area
                energy = float(np.sum(vals * ring_area))
                vals = lobes.fix(vals, ring_area, r_out,
                                 {"layer": 0, "field": key, "channel": "RGB"[c]})
                # the table's energy: the closed-form total (scaled) minus what lies beyond
                full_e = float(np.sum(vals * ring_area))
                want = (total / (resp.Rd if key == "R" else resp.Td)) * energy \
                    if (resp.Rd if key == "R" else resp.Td) > 0 else 0.0
                out[:, c] = vals * (want / full_e) if full_e > 0 else vals
            R[0, c] += Rdl / ring_area[0]
            T[0, c] += Tdl / ring_area[0]
            Rd[c] = Rf + Rdl
            Tt[c] = Tf + Tdl
            bal[c] = resp.ballistic if ex is None else ex.Tu
            fwd[c], dropped[c] = Tdl - bal[c], resp.dropped
        info["method"] = "closed form (single layer)"
    else:
        R, T, Rd, Tt, bal, fwd, dropped = _combine(stack, chans, nq, h, n, lobes, exact,
                                                   exact_stack, scales)
        info["method"] = "fft adding (dctn type 1 on the even quadrant)"
    # exact / diffusion totals per layer, light and channel: the diffusion's own error
    info["scale_to_exact"] = scales if use_exact else []
    info["T_ballistic"] = bal.tolist()
    info["T_forward"] = fwd.tolist()
    info["fresnel_second_order_dropped"] = dropped.tolist()
    info["negative_lobes"] = lobes.items
    info["min_clipped_rel"] = lobes.min_rel
    prof = _finish(r_out, R, T, Rd, Tt, ring_area, info)
    prof.info["seconds"] = time.perf_counter() - t0
    return prof


def _finish(r_out, R, T, Rd, Tt, ring_area, info, cut_radii=None) -> LayerProfile:
    """Cut-off radius and energy bookkeeping shared by both models (``cut_radii``: the
    radius reported for ring k, default ``r_out``)."""
    cut_radii = r_out if cut_radii is None else cut_radii
    cum = np.cumsum(R * ring_area[:, None], axis=0)
    cutoff = np.zeros(3)
    beyond = np.zeros(3)
    n = len(r_out) - 1
    for c in range(3):
        if Rd[c] <= 0:
            continue
        k = int(np.searchsorted(cum[:, c], CUTOFF_FRACTION * Rd[c]))
        k = min(k, n)
        cutoff[c] = cut_radii[k]
        beyond[c] = max(0.0, 1.0 - cum[k, c] / Rd[c])
    info["energy_beyond_table"] = [max(0.0, 1.0 - cum[-1, c] / Rd[c]) if Rd[c] > 0 else 0.0
                                   for c in range(3)]
    return LayerProfile(r_mm=r_out, R=R, T=T, Rd=np.asarray(Rd, float),
                        Tt=np.asarray(Tt, float), cutoff_mm=cutoff,
                        energy_beyond_cutoff=beyond, info=info)


def _ring_grid(terms, lo: np.ndarray, hi: np.ndarray, h: float) -> np.ndarray:
    """Ring-average density of ``terms`` between radii ``lo`` and ``hi`` (pixel grids).

    The cumulative energy is evaluated in closed form on a 1-D grid (h/32 up to 4 h, h/2
    beyond: E varies on the scale of a mean free path >= 4 h) and interpolated with a cubic
    spline, which keeps the cost at O(pixels) instead of O(pixels x images x sources)
    exponentials.
    """
    from scipy.interpolate import CubicSpline
    top = float(hi.max())
    fine = np.arange(0.0, min(4.0 * h, top), h / 32.0)
    coarse = np.arange(fine[-1] + h / 2.0 if fine.size else 0.0, top + h / 2.0, h / 2.0)
    rf = np.concatenate([fine, coarse])
    e = _terms_eval(terms, "energy", rf)
    spline = CubicSpline(rf, e)
    return (spline(hi) - spline(lo)) / (np.pi * (hi**2 - lo**2))



def _scaled(resp: _Response, exact_R: float | None, exact_T: float | None, diffuse: bool,
            exact_Tu: float | None = None) -> tuple[float, float, float, float, dict]:
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


def _combine(stack: LayerStack, chans, nq: int, h: float, n: int, lobes: _Lobes,
             exact=None, exact_stack=None, scales=None):
    """Adding in frequency space on the even quadrant; returns tables and totals."""
    m = 2 * n  # quadrant 0..2n: data in 0..n, zeros beyond (x2 padding)
    ax = np.arange(m + 1) * h
    rho = np.hypot(ax[:, None], ax[None, :])
    inside = rho <= (n + 0.5) * h
    rq = rho[:n + 1, :n + 1]
    # ring index per quadrant pixel, with multiplicity (axis pixels stand for 2, others 4)
    mult = np.full((m + 1, m + 1), 4.0)
    mult[0, :] = 2.0
    mult[:, 0] = 2.0
    mult[0, 0] = 1.0
    sel = inside[:n + 1, :n + 1]
    cell = (mult[:n + 1, :n + 1] * h * h)[sel]
    radius = rq[sel]
    # pixel radii are h sqrt(i^2 + j^2): evaluate each distinct one once
    ij = (np.arange(n + 1)[:, None] ** 2 + np.arange(n + 1)[None, :] ** 2)[sel]
    uniq, back = np.unique(ij, return_inverse=True)
    ur = h * np.sqrt(uniq.astype(np.float64))
    ulo = np.maximum(ur - 0.5 * h, 0.0)
    uhi = np.where(ur == 0, h / math.sqrt(math.pi), ur + 0.5 * h)  # centre: disk of area h^2
    nl = len(stack.layers)
    zero = None

    def spectrum(terms, total: float, where: dict) -> np.ndarray:
        nonlocal zero
        if not terms or total == 0:
            if zero is None:
                zero = np.zeros((m + 1, m + 1))
            return zero
        g = np.zeros((m + 1, m + 1))
        if terms:
            vals = _ring_grid(terms, ulo, uhi, h)[back]
            v = lobes.fix(vals, cell, radius, where, total=total)
            block = np.zeros((n + 1, n + 1))
            block[sel] = v * h * h
            g[:n + 1, :n + 1] = block
            # rescale the sampled energy to the closed-form total so DC is exact
            s = _quadrant_sum(g)
            if s > 0 and total != 0:
                g *= total / s
        return scipy.fft.dctn(g, type=1, workers=-1)

    R_out = np.zeros((n + 1, 3))
    T_out = np.zeros((n + 1, 3))
    Rd, Tt = np.zeros(3), np.zeros(3)
    bal, fwd, dropped = np.zeros(3), np.zeros(3), np.zeros(3)
    radial = _RadialAverager(rho, mult, h, n)
    ring_area = np.pi * np.diff(np.concatenate([[0.0], (np.arange(n + 1) + 0.5) * h]) ** 2)
    r_k = np.arange(n + 1) * h
    for c in range(3):
        # Per layer: collimated light from above (Rc, Tc diffuse; tau collimated through),
        # diffuse light from above (Rd, Td; not needed for the top layer) and from below
        # (Rud, Tud; not needed for the bottom layer).  Light that a layer passes on
        # diffusely enters its neighbour as diffuse light, the collimated part as collimated.
        A = None
        R_delta = 0.0
        bal_c = 1.0
        for k in range(nl):
            ch = chans[k][c]
            ex = exact[k][c] if exact is not None else None
            w = {"layer": k, "channel": "RGB"[c]}
            dc = _response(ch, nq)
            Rf, Rdl, Tf, Tdl, sc = _scaled(dc, ex and ex.Rc, ex and ex.Tc, False, ex and ex.Tu)
            B = {"Rc": spectrum(dc.terms_R, Rf, dict(w, light="collimated", field="R")),
                 "Tc": spectrum(dc.terms_T, Tf, dict(w, light="collimated", field="T")),
                 "tau": Tdl}
            if scales is not None:
                scales.append(dict(w, light="collimated", **sc))
            dropped[c] += dc.dropped
            bal_c *= dc.ballistic if ex is None else ex.Tu
            if k == 0:
                R_delta = Rdl
            else:
                # not in place: spectrum() hands out one shared zero grid for layers without
                # a diffusion shape (sigma_s' = 0), and += on it leaked this delta into every
                # later layer and channel (Rd + Tt up to 1.33, test_stability test11)
                B["Rc"] = B["Rc"] + Rdl
                dd = _response(ch, nq, diffuse=True)
                Rf, Rdl, Tf, Tdl, sc = _scaled(dd, ex and ex.Rd, ex and ex.Td, True)
                B["Rd"] = spectrum(dd.terms_R, Rf, dict(w, light="diffuse", field="R")) + Rdl
                B["Td"] = spectrum(dd.terms_T, Tf, dict(w, light="diffuse", field="T")) + Tdl
                dropped[c] += dd.dropped
                if scales is not None:
                    scales.append(dict(w, light="diffuse", **sc))
            if k + 1 < nl:
                du = _response(_flip(ch), nq, diffuse=True)
                Rf, Rdl, Tf, Tdl, sc = _scaled(du, ex and ex.Rud, ex and ex.Tud, True)
                B["Rud"] = spectrum(du.terms_R, Rf, dict(w, light="diffuse from below",
                                                         field="R")) + Rdl
                B["Tud"] = spectrum(du.terms_T, Tf, dict(w, light="diffuse from below",
                                                         field="T")) + Tdl
                dropped[c] += du.dropped
                if scales is not None:
                    scales.append(dict(w, light="diffuse from below", **sc))
            if A is None:
                A = B
                continue
            den = 1.0 / (1.0 - B["Rd"] * A["Rud"])
            U = (A["tau"] * B["Rc"] + B["Rd"] * A["Tc"]) * den     # diffuse up into A
            down = A["Tc"] + A["Rud"] * U                            # diffuse down into B
            new = {"Rc": A["Rc"] + A["Tud"] * U,
                   "Tc": A["tau"] * B["Tc"] + B["Td"] * down,
                   "tau": A["tau"] * B["tau"]}
            if k + 1 < nl:
                Uu = B["Tud"] * den
                new["Rud"] = B["Rud"] + B["Td"] * A["Rud"] * Uu
                new["Tud"] = A["Tud"] * Uu
            A = new
        es = exact_stack[c] if exact_stack is not None else None
        if es is not None:
            # the adding above treats light passed between layers as Lambertian; the exact
            # plane-parallel solution of the whole stack sets the final totals
            r_tot = float(A["Rc"][0, 0]) + R_delta
            if r_tot > 0:
                A["Rc"] = A["Rc"] * (es.Rc / r_tot)
                R_delta *= es.Rc / r_tot
            t_sc = float(A["Tc"][0, 0]) + float(A["tau"]) - bal_c
            if t_sc > 0:
                fwd_c = float(A["tau"]) - bal_c
                A["Tc"] = A["Tc"] * (es.Tc / t_sc)
                A["tau"] = es.Tu + fwd_c * es.Tc / t_sc
            bal_c = es.Tu
            if scales is not None:
                scales.append({"layer": "stack", "channel": "RGB"[c], "light": "collimated",
                               "R": es.Rc / r_tot if r_tot > 0 else 1.0,
                               "T": es.Tc / t_sc if t_sc > 0 else 1.0})
        tau = float(A["tau"])
        Rd[c] = A["Rc"][0, 0] + R_delta
        Tt[c] = A["Tc"][0, 0] + tau
        bal[c] = bal_c
        fwd[c] = max(tau - bal_c, 0.0)
        for key, spec, out in (("R", A["Rc"], R_out), ("T", A["Tc"], T_out)):
            if not np.any(spec):
                continue
            e = scipy.fft.idctn(spec, type=1, workers=-1)  # energy per pixel
            vals = radial(e / (h * h))
            # the fitted radial table is not energy-exact (the local linear fit reads up to
            # ~1 % high near the source): it holds the grid's energy inside its radius
            energy = float(np.sum((e * mult)[inside]))
            out[:, c] = lobes.fix(vals, ring_area, r_k,
                                  {"layer": "stack", "field": key, "channel": "RGB"[c],
                                   "light": "inverse transform"}, total=energy)
        R_out[0, c] += R_delta / ring_area[0]
        T_out[0, c] += tau / ring_area[0]
    return R_out, T_out, Rd, Tt, bal, fwd, dropped


class _RadialAverager:
    """Quadrant grid -> values at r_k = k h by a hat-weighted local linear fit in radius.

    Plain ring binning of pixels is biased at small k: the lattice puts the pixel radii of a
    ring unevenly (ring 5 holds radii 0.50..0.54 h-units only), which read 3-4 % low on
    skin profiles.  Fitting value = a + b (rho - r_k) with hat weights over (r_k - h,
    r_k + h) removes the first-order bias; where the fit is degenerate (k = 0) the weighted
    mean is used.
    """

    def __init__(self, rho: np.ndarray, mult: np.ndarray, h: float, n: int):
        x = rho / h
        k0 = np.floor(x).astype(np.int64)
        t = x - k0
        self.n = n
        self.parts = []
        for k, w in ((k0, 1.0 - t), (k0 + 1, t)):
            sel = (k <= n) & (w > 0)
            self.parts.append((k[sel], (w * mult)[sel], (x - k)[sel], sel))
        s = [np.zeros(n + 1) for _ in range(3)]
        for k, w, dx, _ in self.parts:
            for p in range(3):
                s[p] += np.bincount(k, weights=w * dx**p, minlength=n + 1)
        self.s0, self.s1, self.s2 = s
        self.det = self.s0 * self.s2 - self.s1**2

    def __call__(self, grid: np.ndarray) -> np.ndarray:
        sv = np.zeros(self.n + 1)
        sxv = np.zeros(self.n + 1)
        for k, w, dx, sel in self.parts:
            v = grid[sel]
            sv += np.bincount(k, weights=w * v, minlength=self.n + 1)
            sxv += np.bincount(k, weights=w * dx * v, minlength=self.n + 1)
        mean = sv / np.maximum(self.s0, 1e-300)
        ok = self.det > 1e-9 * np.maximum(self.s0 * self.s2, 1e-300)
        lin = (self.s2 * sv - self.s1 * sxv) / np.where(ok, self.det, 1.0)
        return np.where(ok, lin, mean)


def _quadrant_sum(g: np.ndarray) -> float:
    """Sum of the full even grid represented by quadrant ``g`` (axes counted once)."""
    return float(4.0 * g[1:, 1:].sum() + 2.0 * g[0, 1:].sum() + 2.0 * g[1:, 0].sum() + g[0, 0])


# ---------------------------------------------------------------------------------------
# The Monte Carlo table

# Rings of the Monte Carlo table: width MC_FINE x the smallest mean free path 1/sigma_t' near
# the source (the gather resamples the table finer still, and its blur is >= 0.1 mm), growing
# geometrically by MC_GROWTH per ring beyond, so every ring holds a comparable share of
# r^2 R(r) (equal noise per ring) out to MC_REACH x the diffusion cut-off (>= MC_MIN_RMAX).
MC_FINE = 0.25
MC_GROWTH = 0.06
MC_REACH = 1.2
MC_MIN_RMAX = 5.5
# Radial splitting (cl/mc_slab.cl): the weight window follows the diffusion estimate of the
# energy per ring, fitted as exp(-kappa (r - r_peak)) beyond its peak, kappa x MC_KAPPA_BOOST
# capped at MC_KAPPA_CAP sigma_tr of the least absorbing layer, times exp(MC_DEPTH sigma_tr z)
# (deep photons matter less); Russian roulette below MC_W_MIN of the window.  Tuned on
# two_layer by the figure of merit 1 / (max relative ring noise^2 x kernel time) over
# [0.05, 5] mm (analog tracer: infinite, the blue tail is empty): roulette at 0.25 instead of
# MCML's 1e-4 x 3.5, depth term x 2.2, boost/cap 1.1/1.25 x 1.5 (1.2/1.4 multiplied the
# copies: x 6.5 in time).  With the photons allocated per channel (MC_PILOT below) each
# channel may converge at its own rate, and boost/cap 1.0/1.0 - the window never falls
# faster than the light - took 0.26-0.30 G loop trips to 1 % against 0.33 for 1.1/1.25 with
# equal shares (trips: the machine-independent cost; bench/results/profiles_table.json).
MC_SPLIT = True
# Points of the diffusion guide over its reach (it sets only the rings' reach and the
# window's slope and start): 128 builds in 0.23 s against 2.1 s for 512 on two_layer, with
# the same 67 rings, kappa within 0.3 % and the window start within one ring.
MC_GUIDE_POINTS = 128
# Independent batches behind the per-ring standard errors: 128, the error of an error
# 1 / sqrt(2 x 127) = 6 % (32 batches: 13 %, and the largest of ~60 such estimates, the
# noise the table reports, then read ~25 % above the true largest error).  Batches only
# group the work-items (cl/mc_slab.cl), so they cost nothing.
MC_BATCHES = 128
MC_KAPPA_BOOST = 1.0
MC_KAPPA_CAP = 1.0
MC_W_MIN = 0.25
MC_DEPTH = 0.5


# Photon allocation among the channels: a pilot of MC_PILOT x photons per channel (seed
# _pilot_seed(seed)) measures each channel's largest relative ring noise over NOISE_BAND_MM;
# the rest of the 3 x photons goes to the channels in proportion to noise^2 x photons, so
# all three end with about the same noise (the pilot's photons are kept: mc_slab.combine).
# Without it every channel gets the same photons and the slowest-converging channel sets the
# count: on two_layer the blue far tail needs 3x the red's photons (bench/results/
# profiles_table.json "allocation").  Below MC_PILOT_MIN pilot photons: equal shares.
MC_PILOT = 0.1
MC_PILOT_MIN = 2000
NOISE_BAND_MM = (0.05, 5.0)


def _pilot_seed(seed: int) -> int:
    """The pilot run's seed: another Philox key, so its photons are independent of the
    main run's."""
    return (int(seed) ^ 0x9E3779B9) & 0xFFFFFFFF


def _band_noise(mc, band: np.ndarray) -> np.ndarray:
    """(3,) the largest relative R error per channel over the rings in ``band`` (inf where a
    ring there is empty, 0 without rings in the band)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(mc.R > 0, mc.R_err / mc.R, np.inf)
    return rel[band].max(axis=0) if band.any() else np.zeros(3)


@lru_cache(maxsize=8)
def _diffusion_guide(stack: LayerStack) -> LayerProfile:
    """The diffusion layer file (its own totals) that sizes the Monte Carlo table's rings
    and weight window; cached per stack (it takes seconds for a layered stack)."""
    h, r_max = _auto_grid(stack)
    h = max(2.0 * h, r_max / MC_GUIDE_POINTS)       # coarse: only its shape and reach are used
    return build_profiles(stack, totals="diffusion", grid=(h, r_max))


def mc_bin_edges(stack: LayerStack, r_max_mm: float | None = None) -> np.ndarray:
    """Ring edges (mm) of the Monte Carlo table of ``stack``: uniform near the source, then
    geometric (module constants), out to ``r_max_mm`` (default: MC_REACH x the diffusion
    cut-off of the stack, at least MC_MIN_RMAX)."""
    st = stack.nonzero()
    mfp_min = min(1.0 / (a + s) for l in st.layers for a, s in zip(l.sigma_a, l.sigma_s_prime))
    if r_max_mm is None:
        prof = _diffusion_guide(st)
        r_max_mm = max(MC_MIN_RMAX, MC_REACH * float(prof.cutoff_mm.max()))
    d0 = MC_FINE * mfp_min
    r1 = d0 / MC_GROWTH
    e = list(np.arange(0.0, r1 + 0.5 * d0, d0))
    while e[-1] < r_max_mm:
        e.append(e[-1] * (1.0 + MC_GROWTH))
    e[-1] = max(e[-1], r_max_mm)
    return np.asarray(e)


def _mc_window(stack: LayerStack, prof: LayerProfile, edges: np.ndarray,
               reach_mm: float | None = None) -> np.ndarray:
    """(3, 4) weight-window parameters (kappa, rho0, rho1, lambda) per channel from a diffusion
    profile: its energy per unit log-radius r^2 R(r) fitted by exp(-kappa (r - rho0)) beyond
    its peak rho0, kappa (x MC_KAPPA_BOOST) capped at MC_KAPPA_CAP sigma_tr of the least absorbing layer (light
    reaching rho decays no faster than that; a faster window would multiply copies without
    bound), no splitting beyond rho1 = the last ring (or ``reach_mm`` if nearer)."""
    win = np.zeros((3, 4))
    mid = 0.5 * (edges[1:] + edges[:-1])
    for c in range(3):
        Rr = np.interp(mid, prof.r_mm, prof.R[:, c], right=0.0)
        e = Rr * mid**2               # energy per unit log-radius: the geometric rings
        if not np.any(e > 0):
            continue
        k0 = int(np.argmax(e))
        sel = (np.arange(len(e)) >= k0) & (e > e[k0] * 1e-12)
        if sel.sum() < 3:
            continue
        slope = np.polyfit(mid[sel], np.log(e[sel]), 1)[0]
        s_min = min(math.sqrt(3.0 * l.sigma_a[c] * (l.sigma_a[c] + l.sigma_s_prime[c]))
                    for l in stack.layers)
        reach = edges[-1] if reach_mm is None else min(edges[-1], reach_mm)
        win[c] = (min(MC_KAPPA_BOOST * max(-slope, 0.0), MC_KAPPA_CAP * s_min), mid[k0],
                  reach, MC_DEPTH * s_min)
    return win


def monte_carlo_profiles(stack: LayerStack, *, photons: int = DEFAULT_MC_PHOTONS,
                         seed: int = DEFAULT_MC_SEED, env=None, progress=None,
                         edges: np.ndarray | None = None, split: bool = MC_SPLIT,
                         batches: int = MC_BATCHES) -> LayerProfile:
    """The layer file of ``stack`` from the OpenCL layered Monte Carlo.

    Parameters
    ----------
    stack : LayerStack
        The scene's layers (the same stack the multipole model would use).
    photons : int
        Photons launched per colour channel on average: 3 x photons in all, shared among the
        channels by a pilot run so that they reach the same noise (with ``split``; module
        notes at MC_PILOT), else the same in each.
    seed : int
        Random seed (0 .. 2**32 - 1): the same seed gives the same table on the same device.
    env : pipeline.cl.ClEnv, optional
        OpenCL environment (default PoCL CPU).
    edges : (B+1,) array_like, optional
        Ring edges, mm (default :func:`mc_bin_edges`).
    split : bool
        Radial splitting with a weight window from the diffusion profile (variance
        reduction far from the source; unbiased), out to MC_REACH x the diffusion cut-off
        (>= MC_MIN_RMAX) even when ``edges`` reach further.
    batches : int
        Independent batches for the standard errors.

    Returns
    -------
    LayerProfile
        The same fields and units as the multipole model: ``r_mm`` (B,) ring mid-radii
        (0 for the central disk), ``R``, ``T`` (B, 3) ring averages in 1/mm^2 per entered
        photon, ``Rd``, ``Tt`` the Monte Carlo totals (escapes beyond the table included),
        ``cutoff_mm`` the outer edge of the ring where 99.9 % of Rd is reached,
        ``energy_beyond_cutoff``.  ``info`` adds ``r_edges``, the per-ring standard errors
        ``R_err``, ``T_err`` (1/mm^2, from the batch spread), ``Rd_err``, ``Tt_err``,
        ``absorbed``, photons, seed, seconds, photons_per_second, device, the weight
        window and ``noise_max_rel`` (largest relative R error per channel over
        [0.05, 5] mm).
    """
    from dermis.stages import mc_slab

    t0 = time.perf_counter()
    st = stack.nonzero()
    if not st.layers:
        raise DermisError("profiles: every layer has thickness 0; nothing to profile")
    diff = _diffusion_guide(st) if (edges is None or split) else None
    reach = max(MC_MIN_RMAX, MC_REACH * float(diff.cutoff_mm.max())) if diff is not None else None
    if edges is None:
        edges = mc_bin_edges(st, reach)
    edges = np.asarray(edges, np.float64)
    window = _mc_window(st, diff, edges, reach) if split else None
    mid = 0.5 * (edges[1:] + edges[:-1])
    band = (mid >= NOISE_BAND_MM[0]) & (mid <= NOISE_BAND_MM[1])
    run = dict(edges=edges, batches=batches, env=env, window=window, w_min=MC_W_MIN)
    budget = 3 * int(photons)
    pilot_n = int(MC_PILOT * photons)
    if split and pilot_n >= MC_PILOT_MIN:
        # a pilot run measures each channel's noise per photon; the rest of the budget goes
        # where it equalises the channels' final noise (docs/profiles.md "allocation")
        pilot = mc_slab.simulate(st, photons=pilot_n, seed=_pilot_seed(seed), **run)
        n_pilot = np.asarray(pilot.info["photons_per_channel"], np.float64)
        per_photon = n_pilot * np.square(_band_noise(pilot, band))   # noise^2 x photons
        if np.all(np.isfinite(per_photon)) and np.all(per_photon > 0):
            want = budget * per_photon / per_photon.sum() - n_pilot
        else:
            want = np.full(3, budget / 3.0) - n_pilot
        rest = np.maximum(want, MC_PILOT_MIN).round().astype(np.int64)
        mc = mc_slab.combine(pilot, mc_slab.simulate(st, photons=rest, seed=int(seed), **run))
    else:
        mc = mc_slab.simulate(st, photons=int(photons), seed=int(seed), **run)
    ring_area = np.pi * np.diff(edges**2)
    r_mm = 0.5 * (edges[1:] + edges[:-1])
    r_mm[0] = 0.0
    noise = _band_noise(mc, band).tolist()
    info = {"model": "monte_carlo", "layers": stack.to_dict(), "convention": RD_CONVENTION,
            "r_edges": edges.tolist(), "R_err": mc.R_err.tolist(), "T_err": mc.T_err.tolist(),
            "Rd_err": mc.Rd_err.tolist(), "Tt_err": mc.Tt_err.tolist(),
            "absorbed": mc.absorbed.tolist(), "lost": mc.lost.tolist(),
            "photons": int(mc.photons),
            "photons_per_channel": mc.info["photons_per_channel"], "seed": int(seed),
            "runs": mc.info.get("runs", [{"seed": int(seed),
                                          "photons_per_channel": mc.info["photons_per_channel"],
                                          "seconds": mc.seconds}]), "kernel_seconds": mc.seconds,
            "photons_per_second": mc.photons_per_second, "device": mc.info["device"],
            "window": mc.info["window"], "noise_max_rel": noise,
            "noise_band_mm": list(NOISE_BAND_MM), "batches": batches,
            "trips_per_channel": mc.info["trips_per_channel"],
            "lane_occupancy": mc.info["lane_occupancy"],
            "interactions_per_second": mc.info["interactions_per_second"],
            "T_ballistic": [math.exp(-sum((l.sigma_a[c] + l.sigma_s[c]) * l.thickness_mm
                                          for l in st.layers)) if all(
                math.isfinite(l.thickness_mm) for l in st.layers) else 0.0 for c in range(3)]}
    prof = _finish(r_mm, mc.R, mc.T, mc.Rd, mc.Tt, ring_area, info, cut_radii=edges[1:])
    prof.info["seconds"] = time.perf_counter() - t0
    return prof


# ---------------------------------------------------------------------------------------
# Stage ``profiles``: the scene's layer stack -> radial profiles R(r), T(r) per channel

NAME = "profiles"


def node(scene, model: str | None = None) -> Node:
    """The layer profiles of the scene's stack with ``model`` (None: ``[optics] profile``);
    the model, and for the Monte Carlo ``[optics] photons`` and ``seed``, are in the key."""
    from dermis.pipeline.config import profiles_node_id
    optics = scene.optics
    model = model or getattr(optics, "profile", DEFAULT_PROFILE_MODEL)
    params = {"stack": LayerStack.to_dict(optics), "model": model}
    if model == "monte_carlo":
        params["photons"] = int(getattr(optics, "photons", DEFAULT_MC_PHOTONS))
        params["seed"] = int(getattr(optics, "seed", DEFAULT_MC_SEED))
    return Node(profiles_node_id(scene, model), NAME, __name__, params, (),
                label=f"layer profiles ({model})")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    model = params.get("model", "multipole")
    stack = LayerStack.from_dict(params["stack"])
    if model == "monte_carlo":
        prof = build_profiles(stack, model=model, photons=params["photons"],
                              seed=params["seed"], env=ctx.cl, progress=ctx.progress)
        kernel_seconds = prof.info.get("kernel_seconds", 0.0)
    else:
        prof = build_profiles(stack)
        kernel_seconds = 0.0
    return StageResult(prof, info={"model": model, "Rd": list(map(float, prof.Rd)),
                                   "Tt": list(map(float, prof.Tt)),
                                   "negative_lobes": len(prof.info.get("negative_lobes", [])),
                                   "kernel_seconds": kernel_seconds})
