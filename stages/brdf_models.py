"""Local reflectance models: parameters, packing for the OpenCL kernels, evaluation, references.

Three models, one ``.cl`` file each (their header comments give equations and variants):

* ``lafortune`` - measured-skin Lafortune BRDF with an albedo texture (docs/science.md §1),
  ``cl/brdf_lafortune.cl``;
* ``hk93`` - Hanrahan-Krueger two-layer single scattering + constant multiple scattering
  (docs/science.md §2), ``cl/brdf_hk93.cl``;
* ``asperity`` - Koenderink-Pont asperity scattering term, added on top of a base model
  (docs/science.md §5), ``cl/asperity.cl``.

Each parameter dataclass validates itself on construction (:class:`ConfigError` naming the
field, the value and the rule) and ``pack()``s into the float32 block its kernel reads.
:func:`evaluate` runs a model's ``<model>_eval`` kernel on arrays of direction pairs.  The
float64 NumPy single-scattering term of HK93 (written from the formulas, in angles, not the
kernel's vector algebra) stays here because :class:`HK93Params` derives rho_ms from it; the
tests' float64 references of the three BRDFs are in ``tests/brdf_reference.py``.

Conventions: local shading frame with z along the shading normal, ``wo`` and ``wi`` unit
vectors pointing away from the surface, f excludes the cosine, RGB linear, mm and 1/mm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from dermis.pipeline.config import ASPERITY_BASES
from dermis.optics.fresnel import fresnel_transmittance
from dermis.pipeline.errors import ConfigError

__all__ = [
    "VERSION", "KERNELS", "MODELS", "LafortuneParams", "HK93Params", "HK93Layer",
    "AsperityParams", "hk93_params_from_layers", "evaluate", "hk93_single_scattering_albedo",
    "lafortune_lobe_albedo", "LAFORTUNE_NPARAMS", "HK93_NPARAMS", "ASPERITY_NPARAMS",
    "LAFORTUNE_ALBEDO_NODES", "Transmittance",
]

VERSION = 1
KERNELS = ("brdf_lafortune.cl", "brdf_hk93.cl", "asperity.cl")
MODELS = ("lafortune", "hk93", "asperity")
KERNEL_FILES = dict(zip(MODELS, KERNELS))

# Parameter-block sizes; must equal the #defines in the .cl files (checked by the tests).
# Lafortune: 27 lobe coefficients, the coupling block (flag, 1 / (1 - mean lobe albedo) RGB)
# and the lobes' directional albedo at LAFORTUNE_ALBEDO_NODES cosines (cl/brdf_lafortune.cl).
LAFORTUNE_ALBEDO_NODES = 64
LAFORTUNE_NPARAMS = 27 + 4 + 3 * LAFORTUNE_ALBEDO_NODES
HK93_NPARAMS = 20
ASPERITY_NPARAMS = 8

# Grazing floor of the outside cosines in hk93_f (HK93_COS_MIN in cl/brdf_hk93.cl) and the
# optical depth standing for a semi-infinite layer (HK93_TAU_MAX): part of the model.
HK93_COS_MIN = 1e-7
HK93_TAU_MAX = 1e30

_F32_MAX = float(np.finfo(np.float32).max)


# --------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------

def _fmt(v) -> str:
    """A value on one line for an error message."""
    return str(np.asarray(v).tolist()) if np.ndim(v) else f"{v}"


def _array(value, name: str, shape: tuple[int, ...], unit: str = "") -> np.ndarray:
    """``value`` as a float64 array of ``shape`` with finite entries, else ConfigError."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} = {value!r}{unit}: must be numbers of shape {shape}") from None
    if a.shape != shape:
        raise ConfigError(f"{name} = {_fmt(a)}{unit}: must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{name} = {_fmt(a)}{unit}: must be finite")
    return a


def _check(ok, name: str, value, unit: str, rule: str) -> None:
    if not np.all(ok):
        raise ConfigError(f"{name} = {_fmt(value)}{unit}: {rule}")


# --------------------------------------------------------------------------------------
# Lafortune (docs/science.md §1)
# --------------------------------------------------------------------------------------

# pbrt-v1 materials/skin.cpp three-lobe fit of measured skin (Lafortune et al. 1997 model),
# table in docs/science.md §1. Rows: lobe 0 (grazing, non-zero past ~46 deg), lobe 1 (broad),
# lobe 2 (sharp specular); columns R, G, B.
_SKIN_RHO_D = (0.428425, 0.301341, 0.331054)
_SKIN_CXY = ((-1.131747, -1.016939, -0.966018),
             (-0.546570, -0.643533, -0.638934),
             (-0.998888, -1.020153, -1.027479))
_SKIN_CZ = ((-1.209182, -1.462488, -1.222419),
            (0.380123, 0.410559, 0.437367),
            (0.857998, 0.703913, 0.573625))
_SKIN_N = ((6.421658, 3.699932, 3.524889),
           (3.685044, 4.266495, 4.539742),
           (64.208486, 63.919687, 43.809866))


@dataclass(frozen=True)
class LafortuneParams:
    """Isotropic three-lobe Lafortune BRDF; defaults are pbrt-v1's measured-skin fit.

    Parameters
    ----------
    cxy, cz : (3, 3) floats, [lobe, RGB]
        Lobe coefficients (per-lobe rho_s folded in, as in pbrt-v1 skin.cpp).
    n : (3, 3) floats, [lobe, RGB], > 0
        Lobe exponents.
    rho_d : (3,) floats in [0, 1]
        Diffuse albedo used when no per-point albedo (texture) is given.
    coupled : bool
        Energy coupling of the diffuse term to the lobes (default True; docs/science.md §1):
        f_d = albedo (1 - L(mu_i)) (1 - L(mu_o)) / (pi (1 - L_mean)), L the lobes'
        directional albedo (:func:`lafortune_lobe_albedo`) and L_mean its cosine-weighted
        mean (Kelemen & Szirmay-Kalos 2001's coupled matte term).  The directional albedo
        is then L(mu_o) + albedo (1 - L(mu_o)) <= 1 for every albedo <= 1, and f stays
        reciprocal.  False: the fit as pbrt-v1 and the thesis used it, f_d = albedo / pi,
        whose albedo exceeds 1 above albedo 1 - L (~0.74 at 89 deg).
    """

    cxy: Any = _SKIN_CXY
    cz: Any = _SKIN_CZ
    n: Any = _SKIN_N
    rho_d: Any = _SKIN_RHO_D
    coupled: bool = True

    def __post_init__(self):
        for name in ("cxy", "cz", "n"):
            object.__setattr__(self, name, _array(getattr(self, name), f"lafortune.{name}", (3, 3)))
        rho_d = _array(self.rho_d, "lafortune.rho_d", (3,))
        object.__setattr__(self, "rho_d", rho_d)
        _check(self.n > 0, "lafortune.n", self.n, "", "every lobe exponent must be > 0")
        _check((rho_d >= 0) & (rho_d <= 1), "lafortune.rho_d", rho_d, "",
               "must be in [0, 1] (linear RGB albedo)")
        object.__setattr__(self, "coupled", bool(self.coupled))

    def pack(self) -> np.ndarray:
        """(LAFORTUNE_NPARAMS,) float32 (cl/brdf_lafortune.cl): per lobe k at 9k: Cxy RGB,
        Cz RGB, n RGB; [27] coupling flag, [28..30] 1 / (1 - L_mean) RGB; from [31] the
        lobes' directional albedo L(mu) RGB at mu = j / (LAFORTUNE_ALBEDO_NODES - 1)."""
        out = np.zeros(LAFORTUNE_NPARAMS, dtype=np.float64)
        out[:27] = np.stack([self.cxy, self.cz, self.n], axis=1).ravel()
        if self.coupled:
            table, mean = _lobe_albedo_table(self)
            out[27] = 1.0
            out[28:31] = 1.0 / np.maximum(1.0 - mean, 1e-6)
            # lobes reflecting more than everything (L > 1: not the skin fit, arbitrary lobes)
            # would make 1 - L and so the coupled diffuse term negative; it stops at 0
            out[31:] = np.minimum(table, 1.0).ravel()
        return out.astype(np.float32)

    def lobe_albedo(self, mu) -> np.ndarray:
        """Directional albedo (len(mu), 3) of the lobes alone at cosines ``mu``
        (:func:`lafortune_lobe_albedo`)."""
        return lafortune_lobe_albedo(mu, self)

    def lobes_off(self) -> "LafortuneParams":
        """The same BRDF with every lobe coefficient 0: f = albedo / pi."""
        z = np.zeros((3, 3))
        return LafortuneParams(z, z, self.n, self.rho_d, self.coupled)


# Quadrature of the lobes' directional albedo: Gauss-Legendre in cos theta_i x midpoints in
# phi over [0, pi] (the lobes are even in phi about the plane of wo).  48 x 96 agrees with
# 192 x 384 to 1e-9 at every cosine in [0, 1] and with the 1500 x 1500 midpoint grid of
# tests/test_brdf_lafortune.py (LOBE_ALBEDO) to 1e-5.
_LOBE_QUAD = (48, 96)


def lafortune_lobe_albedo(mu, params: "LafortuneParams | None" = None) -> np.ndarray:
    """Directional albedo int lobes(wo, wi) cos_i dw_i of the Lafortune lobes alone, float64.

    Parameters
    ----------
    mu : float or (M,) floats in [0, 1], the outgoing (or, by reciprocity, incoming) cosine
    params : LafortuneParams, optional (default pbrt-v1's skin fit); rho_d is ignored

    Returns
    -------
    (M, 3) float64 ndarray.  For the skin fit: (0.031, 0.022, 0.022) at normal incidence,
    (0.264, 0.261, 0.241) at 89 deg, (0.278, 0.272, 0.249) at the horizon.
    """
    params = params or LafortuneParams()
    nmu, nphi = _LOBE_QUAD
    x, w = np.polynomial.legendre.leggauss(nmu)
    mu_i, w_mu = 0.5 * (x + 1.0), 0.5 * w
    phi = (np.arange(nphi) + 0.5) / nphi * np.pi
    m, p = np.meshgrid(mu_i, phi, indexing="ij")
    weight = (m * w_mu[:, None]) * (2.0 * np.pi / nphi)
    horiz = np.sqrt(1.0 - m * m) * np.cos(p)
    out = []
    for c in np.atleast_1d(np.asarray(mu, np.float64)):
        c = min(max(float(c), 0.0), 1.0)
        xy = math.sqrt(1.0 - c * c) * horiz       # wo = (sin theta_o, 0, cos theta_o)
        zz = c * m
        tot = np.zeros(3)
        for k in range(3):
            base = params.cxy[k] * xy[..., None] + params.cz[k] * zz[..., None]
            val = np.where(base > 0, np.abs(base) ** params.n[k], 0.0)
            tot += (val * weight[..., None]).sum(axis=(0, 1))
        out.append(tot)
    return np.array(out)


_LOBE_TABLES: dict = {}


def _lobe_albedo_table(params: "LafortuneParams") -> tuple[np.ndarray, np.ndarray]:
    """(LAFORTUNE_ALBEDO_NODES, 3) lobe albedo at mu = j / (nodes - 1) and its cosine-
    weighted mean int L(mu) 2 mu dmu (Gauss-Legendre, 64 nodes), cached per lobe set."""
    key = (params.cxy.tobytes(), params.cz.tobytes(), params.n.tobytes())
    if key not in _LOBE_TABLES:
        nodes = np.linspace(0.0, 1.0, LAFORTUNE_ALBEDO_NODES)
        x, w = np.polynomial.legendre.leggauss(64)
        mu = 0.5 * (x + 1.0)
        mean = (lafortune_lobe_albedo(mu, params) * (mu * w)[:, None]).sum(axis=0)
        _LOBE_TABLES[key] = (lafortune_lobe_albedo(nodes, params), mean)
    return _LOBE_TABLES[key]


# --------------------------------------------------------------------------------------
# The surface of the BSSRDF: what the surface term does not reflect enters (docs/science.md §4)
# --------------------------------------------------------------------------------------

class Transmittance:
    """The fraction of light that crosses the skin's surface at cosine mu, per channel:
    entering (the irradiance stage applies it per light sample) and, by reciprocity,
    leaving (the BSSRDF's exit weight, ``stages/gather.py exitance_to_radiance``).

    T(mu) = Ft(mu; eta), the smooth-dielectric Fresnel transmittance, or with the BSSRDF's
    surface term (``surface_reflection = "lafortune_lobes"``) min(Ft(mu), 1 - L(mu)), L the
    lobes' directional albedo (:func:`lafortune_lobe_albedo`): light the surface term
    already reflects cannot also enter, so surface + subsurface reflect L(mu) + a T(mu) <= 1
    for any albedo a <= 1.  The skin fit's lobes reflect more than a smooth surface below
    ~55 deg (eta 1.4) or ~62 deg (eta 1.3): L = 0.031 at normal incidence against
    F = 0.028 / 0.017, so the cap lowers T_mean by 0.3 % / 1.5 %.  ``mean`` =
    int T 2 mu dmu normalises the exit (docs/science.md §4).
    """

    _TABLES: dict = {}
    N = 2049
    LOOKUP = 1 << 16

    def __init__(self, eta: float, surface_reflection: str = "none"):
        if surface_reflection not in ("none", "lafortune_lobes"):
            raise ConfigError(f"surface_reflection = {surface_reflection!r}: must be "
                              "'none' or 'lafortune_lobes'")
        self.eta = float(eta)
        self.surface_reflection = surface_reflection
        key = (self.eta, surface_reflection)
        if key not in self._TABLES:
            mu = np.linspace(0.0, 1.0, self.N)
            t = np.repeat(fresnel_transmittance(mu, self.eta)[:, None], 3, axis=1)
            if surface_reflection == "lafortune_lobes":
                lob, _ = _lobe_albedo_table(LafortuneParams())
                nodes = np.linspace(0.0, 1.0, LAFORTUNE_ALBEDO_NODES)
                lob = np.stack([np.interp(mu, nodes, lob[:, c]) for c in range(3)], axis=1)
                t = np.minimum(t, 1.0 - lob)
            mid = (np.arange(4096) + 0.5) / 4096
            tm = np.stack([np.interp(mid, mu, t[:, c]) for c in range(3)], axis=1)
            self._TABLES[key] = (mu, t, (tm * 2.0 * mid[:, None]).sum(axis=0) / 4096)
        self._mu, self._t, self.mean = self._TABLES[key]
        fine = np.linspace(0.0, 1.0, self.LOOKUP + 1)
        self._fine = np.stack([np.interp(fine, self._mu, self._t[:, k]) for k in range(3)],
                              axis=1).astype(np.float32)
        self._fine[0] = 0.0   # cos <= 0 (clipped to 0): nothing crosses

    def __call__(self, cos) -> np.ndarray:
        """(..., 3) float32 T at cosines ``cos`` (0 where cos <= 0): the nearest of
        ``LOOKUP`` + 1 uniform cosines (the irradiance pass applies it to ~16M light samples
        per mesh and light; error < 3e-5 at grazing, where T rises steepest, ~1e-6 elsewhere)."""
        c = np.asarray(cos, np.float32)
        x = np.clip(c.ravel(), 0.0, 1.0)
        x *= np.float32(self.LOOKUP)
        x += np.float32(0.5)
        return self._fine.take(x.astype(np.intp), axis=0).reshape(c.shape + (3,))

    def __repr__(self) -> str:
        return f"Transmittance(eta={self.eta}, surface_reflection={self.surface_reflection!r})"


# --------------------------------------------------------------------------------------
# Hanrahan-Krueger 1993 (docs/science.md §2)
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class HK93Layer:
    """One HK93 layer: thickness (mm, ``inf`` allowed for the last), eta >= 1, RGB sigma_a and
    sigma_s_prime (1/mm), HG mean cosine g in (-1, 1); sigma_s = sigma_s_prime / (1 - g)."""

    thickness_mm: float
    eta: float
    sigma_a: Any
    sigma_s_prime: Any
    g: float

    @property
    def sigma_s(self) -> np.ndarray:
        return np.asarray(self.sigma_s_prime, dtype=np.float64) / (1.0 - self.g)


def _layer_attr(layer, key: str, where: str):
    if isinstance(layer, dict):
        if key not in layer:
            raise ConfigError(f"{where}: missing key '{key}' (a layer needs thickness_mm, eta, "
                              "sigma_a, sigma_s_prime, g)")
        return layer[key]
    if not hasattr(layer, key):
        raise ConfigError(f"{where}: {type(layer).__name__} has no attribute '{key}' (a layer "
                          "needs thickness_mm, eta, sigma_a, sigma_s_prime, g)")
    return getattr(layer, key)


def _as_hk93_layer(layer, i: int, last: bool) -> HK93Layer:
    """Validate one duck-typed layer (dict or object) into an HK93Layer."""
    where = f"hk93.layers[{i}]"
    d = _layer_attr(layer, "thickness_mm", where)
    try:
        d = float(d)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}.thickness_mm = {d!r}: must be a number (mm) or inf") from None
    if math.isnan(d) or d < 0 or (math.isinf(d) and not last):
        raise ConfigError(f"{where}.thickness_mm = {d} (mm): must be >= 0, and inf only for "
                          "the last layer")
    eta = float(_array(_layer_attr(layer, "eta", where), f"{where}.eta", ()))
    _check(1.0 <= eta <= 3.0, f"{where}.eta", eta, "", "must be in [1, 3] (absolute index)")
    g = float(_array(_layer_attr(layer, "g", where), f"{where}.g", ()))
    _check(-1.0 < g < 1.0, f"{where}.g", g, "", "must satisfy -1 < g < 1 (HG mean cosine)")
    sa = _array(_layer_attr(layer, "sigma_a", where), f"{where}.sigma_a", (3,), " (1/mm)")
    ssp = _array(_layer_attr(layer, "sigma_s_prime", where), f"{where}.sigma_s_prime", (3,),
                 " (1/mm)")
    _check(sa >= 0, f"{where}.sigma_a", sa, " (1/mm)", "must be >= 0")
    _check(ssp >= 0, f"{where}.sigma_s_prime", ssp, " (1/mm)", "must be >= 0")
    _check(sa + ssp > 0, f"{where}.sigma_a + sigma_s_prime", sa + ssp, " (1/mm)",
           "must be > 0 per channel")
    return HK93Layer(d, eta, tuple(sa), tuple(ssp), g)


_PROFILE_RD: dict = {}
# Radial grid (spacing, half-width; mm) of the layer file built for its Rd alone: the layer
# file's totals are closed-form / plane-parallel transport values that do not depend on the
# radial grid (stages/profiles.py), so a coarse grid gives the profiles stage's Rd exactly
# (measured equal to 1e-15 on two_layer and a two-index stack) in a fraction of the time
# (two_layer 3.2 s against 11.7 s; tests/test_energy.py checks the equality).
RD_GRID = (0.5, 32.0)


def _profile_rd(layers: Sequence[HK93Layer], eta_below: float = 1.0) -> np.ndarray:
    """Total diffuse reflectance Rd (RGB, per entering photon) of the layers' profile: the
    BSSRDF's own layer file, ``stages/profiles.py build_profiles`` of the same stack
    (air above, grid ``RD_GRID``), cached per stack in the process."""
    import json
    from dermis.optics.layers import Layer, LayerStack
    from dermis.stages.profiles import build_profiles
    stack = LayerStack(tuple(Layer(l.thickness_mm, l.eta, tuple(float(v) for v in l.sigma_a),
                                   tuple(float(v) for v in l.sigma_s_prime), l.g)
                             for l in layers), 1.0, float(eta_below))
    key = json.dumps(stack.to_dict(), sort_keys=True)
    if key not in _PROFILE_RD:
        _PROFILE_RD[key] = np.asarray(build_profiles(stack, grid=RD_GRID).Rd, np.float64)
    return _PROFILE_RD[key]


# Outgoing cosines at which the single-scattering albedo's maximum is sought: it peaks at
# grazing for eta = 1 (a forward lobe g > 0 reaches alpha / 2 only as cos theta_o -> 0:
# 0.325 at 1e-3, 0.50 at 1e-7 for g = 0.99), near normal incidence for eta > 1 where
# Fresnel cuts grazing light.
_SS_COS_GRID = np.array([1.0, 0.9, 0.75, 0.5, 0.3, 0.15, 0.07, 0.03, 0.01, 0.003, 0.001,
                         1e-5, 1e-7])
# Quadrature: midpoint in (theta_i, phi) - uniform in theta, not cos theta, so a peak at the
# pole (the backward lobe g < 0 at normal view) is resolved as well as one at the horizon.
# The Henyey-Greenstein peak is ~(1 - |g|) rad wide, so the cells are sized to it:
# n = 5 / (1 - |g|) per axis, at least 96 (skin g = 0.8: 96 and 384 agree to 2e-3, the
# 1/(mu_i + mu_o) peak at grazing the worst case, which SS_ALBEDO_TOL absorbs) and at most
# 512 (|g| = 0.99: 512 and 1024 agree to < 3e-3 at every cosine of the grid,
# tests/test_brdf_models.py test_hk93_single_scattering_quadrature_converges).
_SS_QUAD_MIN, _SS_QUAD_MAX = 96, 512
SS_ALBEDO_TOL = 5e-3


def _ss_quad_n(layers) -> int:
    g = max(abs(float(l.g)) for l in layers)
    return int(min(_SS_QUAD_MAX, max(_SS_QUAD_MIN, math.ceil(5.0 / max(1.0 - g, 1e-6)))))


def hk93_single_scattering_albedo(layers, cos_theta_o, n: int | None = None) -> np.ndarray:
    """Directional albedo of HK93's single-scattering part, (len(cos_theta_o), 3) float64.

    Midpoint quadrature of the float64 reference over (theta_i, phi) with ``n`` cells per
    axis (None: sized to the layers' Henyey-Greenstein peak, ``_ss_quad_n``); ``layers`` are
    validated HK93Layer objects (``HK93Params(...).layers``).
    """
    n = _ss_quad_n(layers) if n is None else int(n)
    cos_o = np.atleast_1d(np.asarray(cos_theta_o, np.float64))
    key = (tuple((float(l.thickness_mm), float(l.eta), tuple(np.asarray(l.sigma_a, float)),
                  tuple(np.asarray(l.sigma_s_prime, float)), float(l.g)) for l in layers),
           tuple(cos_o), n)
    if key not in _SS_ALBEDO:          # seconds at |g| = 0.99 (n = 500), so kept per process
        _SS_ALBEDO[key] = _ss_albedo_quadrature(layers, cos_o, n)
    return _SS_ALBEDO[key].copy()


_SS_ALBEDO: dict = {}


def _ss_albedo_quadrature(layers, cos_o: np.ndarray, n: int) -> np.ndarray:
    theta = (np.arange(n) + 0.5) / n * (0.5 * np.pi)
    phi = (np.arange(n) + 0.5) / n * np.pi          # f is even in phi: integrate [0, pi] twice
    t, p = (a.ravel() for a in np.meshgrid(theta, phi, indexing="ij"))
    m, s = np.cos(t), np.sin(t)
    wi = np.stack([s * np.cos(p), s * np.sin(p), m], axis=1)
    weight = (m * s)[:, None] * (2.0 * np.pi * 0.5 * np.pi / (n * n))
    out = []
    for c in cos_o:
        wo = np.broadcast_to([math.sqrt(max(0.0, 1.0 - c * c)), 0.0, c], wi.shape)
        f = _hk93_single_np(wo, wi, layers)
        out.append((f * weight).sum(axis=0))
    return np.array(out)


def _max_single_scattering_albedo(layers) -> np.ndarray:
    """Per-channel maximum over _SS_COS_GRID of the single-scattering directional albedo."""
    return hk93_single_scattering_albedo(layers, _SS_COS_GRID).max(axis=0)


# Outgoing-cosine nodes of the hemispherical single-scattering albedo (Gauss-Legendre on
# [0, 1]): 12 nodes agree with 48 to < 1e-4 on the skin presets.
_SS_HEMI_NODES = 12


def _single_scattering_hemispherical(layers) -> np.ndarray:
    """int rho_ss(mu) 2 mu dmu: the single-scattering part's reflectance under uniform light."""
    x, w = np.polynomial.legendre.leggauss(_SS_HEMI_NODES)
    mu = 0.5 * (x + 1.0)
    return (hk93_single_scattering_albedo(layers, mu) * (mu * w)[:, None]).sum(axis=0)


def _default_multiple_scattering(layers: Sequence[HK93Layer], ss_max, rd) -> np.ndarray:
    """rho_ms so that HK93 and the BSSRDF reflect the same under uniform light (the thesis's
    constant term, made consistent; docs/science.md §2): the BSSRDF's uniform-light
    reflectance is (1 - Fdr_ext(eta)) Rd (entry Fresnel averaged over the cosine-weighted
    hemisphere, times the profile's Rd per entering photon), and HK93's is
    int rho_ss 2 mu dmu + rho_ms.  Clamped to [0, 1 - max rho_ss] so the directional albedo
    never exceeds 1 (a white medium with strong single scattering would ask for more)."""
    from dermis.optics.fresnel import diffuse_fresnel_external
    target = (1.0 - diffuse_fresnel_external(layers[0].eta)) * np.asarray(rd, np.float64)
    return np.clip(target - _single_scattering_hemispherical(layers), 0.0, 1.0 - ss_max)


def _default_hk93_layers() -> tuple:
    # Same skin as the multipole model (docs/science.md §2: "derive both layers from the same
    # epidermis/dermis optical parameters"): pipeline.layers PRESETS["two_layer"], an
    # epidermis of 0.25 mm over a semi-infinite dermis, eta 1.4, g 0.8.
    from dermis.optics.layers import PRESETS
    return tuple(PRESETS["two_layer"].layers)


@dataclass(frozen=True)
class HK93Params:
    """Hanrahan-Krueger layers (1 or 2, top first) and the constant multiple-scattering albedo.

    Parameters
    ----------
    layers : sequence of 1 or 2 layers
        Objects or dicts with ``thickness_mm`` (mm; inf allowed for the last), ``eta`` (>= 1),
        ``sigma_a`` and ``sigma_s_prime`` (RGB, 1/mm) and ``g`` (HG mean cosine), e.g.
        :class:`pipeline.layers.Layer`.  Zero-thickness layers are dropped.  Default: the
        ``two_layer`` skin preset of :mod:`pipeline.layers`.
    multiple_scattering : (3,) floats in [0, 1) or None
        rho_ms, the albedo of the constant (Lambertian) multiple-scattering term
        f_ms = rho_ms / pi.  None derives it from the same layers as the BSSRDF: under
        uniform light HK93 then reflects what the BSSRDF does, (1 - Fdr_ext) Rd (see
        ``_default_multiple_scattering``).  Must not push the directional albedo above 1.
    diffuse_reflectance : (3,) floats or None
        Rd of the layers per entering photon; None: the layer profile's
        (``stages/profiles.py build_profiles`` of the same stack, cached per process).
    """

    layers: Any = field(default_factory=_default_hk93_layers)
    multiple_scattering: Any = None
    diffuse_reflectance: Any = None

    def __post_init__(self):
        layers = self.layers
        eta_below = 1.0
        if hasattr(layers, "layers") and not isinstance(layers, dict):  # a LayerStack
            eta_below = float(getattr(layers, "eta_below", 1.0))
            layers = layers.layers
        try:
            layers = list(layers)
        except TypeError:
            raise ConfigError(f"hk93.layers = {layers!r}: must be a list of 1 or 2 layers") from None
        checked = [_as_hk93_layer(l, i, i == len(layers) - 1) for i, l in enumerate(layers)]
        checked = [l for l in checked if l.thickness_mm > 0]
        if not 1 <= len(checked) <= 2:
            raise ConfigError(f"hk93.layers: {len(checked)} layers of non-zero thickness; the "
                              "HK93 model takes 1 or 2")
        object.__setattr__(self, "layers", tuple(checked))
        ss_max = _max_single_scattering_albedo(checked)
        ms = self.multiple_scattering
        rd = self.diffuse_reflectance
        if rd is not None:
            rd = _array(rd, "hk93.diffuse_reflectance", (3,))
            _check((rd >= 0) & (rd <= 1), "hk93.diffuse_reflectance", rd, "", "must be in [0, 1]")
        elif ms is None:
            rd = _profile_rd(checked, eta_below)
        if ms is None:
            ms = _default_multiple_scattering(checked, ss_max, rd)
        ms = _array(ms, "hk93.multiple_scattering", (3,))
        _check((ms >= 0) & (ms < 1), "hk93.multiple_scattering", ms, "",
               "must be in [0, 1) (albedo of the constant multiple-scattering term)")
        limit = 1.0 - ss_max + SS_ALBEDO_TOL
        _check(ms <= limit, "hk93.multiple_scattering", ms, "",
               f"must be <= 1 - max single-scattering albedo of these layers = "
               f"{_fmt(np.round(limit, 4))} (else the directional albedo exceeds 1)")
        object.__setattr__(self, "multiple_scattering", ms)
        object.__setattr__(self, "diffuse_reflectance", rd)
        object.__setattr__(self, "_ss_max", ss_max)

    def texture_reference(self) -> np.ndarray:
        """(3,) the albedo at which a texture leaves rho_ms unchanged: the layers' Rd (the
        texture is read as total diffuse reflectance, as the BSSRDF's "replace" mode reads
        it), raised where needed to rho_ms / (1 - max rho_ss).  The renderer tints the
        multiple-scattering term per pixel as rho_ms * albedo / reference, so with any
        albedo <= 1 the directional albedo stays <= max rho_ss + rho_ms / reference <= 1."""
        rd = self.diffuse_reflectance
        if rd is None:
            rd = _profile_rd(self.layers)
        ms = np.asarray(self.multiple_scattering, np.float64)
        cap = ms / np.maximum(1.0 - np.asarray(self._ss_max, np.float64), 1e-12)
        return np.maximum(np.asarray(rd, np.float64), cap)

    @classmethod
    def from_layers(cls, layers, *, multiple_scattering=None) -> "HK93Params":
        """HK93Params from duck-typed layers (list, or a LayerStack with ``.layers``)."""
        return cls(layers, multiple_scattering)

    def pack(self) -> np.ndarray:
        """(20,) float32 block of cl/brdf_hk93.cl: eta1, eta2, g1, g2, W1, tau1, W2, tau2, rho_ms."""
        out = np.zeros(HK93_NPARAMS, dtype=np.float64)
        l1 = self.layers[0]
        l2 = self.layers[1] if len(self.layers) == 2 else None
        out[0] = l1.eta
        out[1] = l2.eta if l2 else l1.eta   # single layer: equal index, so T_12 = 1 ...
        out[2] = l1.g
        out[3] = l2.g if l2 else 0.0
        for k, lay in enumerate([l1, l2]):
            if lay is None:                  # ... and W_2 = tau_2 = 0: no second slab
                continue
            ss = lay.sigma_s
            st = np.asarray(lay.sigma_a) + ss
            # tau = sigma_t d; a semi-infinite layer (d = inf) becomes HK93_TAU_MAX
            tau = np.minimum(st * lay.thickness_mm, HK93_TAU_MAX)
            out[4 + 6 * k: 7 + 6 * k] = ss / st
            out[7 + 6 * k: 10 + 6 * k] = tau
        out[16:19] = self.multiple_scattering
        return out.astype(np.float32)


def hk93_params_from_layers(layers, *, multiple_scattering=None) -> np.ndarray:
    """Packed float32 HK93 parameter block from 1-2 duck-typed layers.

    Parameters
    ----------
    layers : list of layers (objects or dicts) or a LayerStack
        ``thickness_mm`` (mm, inf allowed last), ``eta``, ``sigma_a`` (3, 1/mm),
        ``sigma_s_prime`` (3, 1/mm), ``g``.
    multiple_scattering : (3,) floats or None
        Constant multiple-scattering albedo; None derives it (see :class:`HK93Params`).

    Returns
    -------
    (20,) float32 ndarray, the layout documented in ``cl/brdf_hk93.cl``.

    Raises
    ------
    ConfigError
        A layer misses a field or breaks a rule (message names layer, field, value, rule).
    """
    return HK93Params(layers, multiple_scattering).pack()


# --------------------------------------------------------------------------------------
# Asperity (docs/science.md §5)
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AsperityParams:
    """Koenderink-Pont asperity layer; the term is added to a base model by the renderer.

    Parameters
    ----------
    delta_mm : float > 0
        Thickness of the layer of sparse scatterers (vellus hair).  Default 1 mm: the order
        of a facial vellus hair's length (< 2 mm).
    lambda_mm : float > delta_mm
        Mean free path 1/(sigma_t rho) among the scatterers.  Default 20 mm, an
        order-of-magnitude estimate: ~3 follicles per mm^2 on the face (forehead counts of
        ~290 /cm^2) times a mean projected area pi L d / 4 of a hair of length L = 1 mm and
        diameter d ~ 0.02 mm gives 1/lambda ~ 0.05 /mm.  Only Delta/lambda = 0.05 matters:
        at normal incidence and view the term is ~3 % of the skin diffuse albedo/pi, at 80 deg
        ~17 %, and it is capped at 1/(4 pi Delta/lambda) = 1.6 /sr at grazing (the "peach
        fuzz" rim).  Not confirmed against a measurement here; a scene may override it.
    albedo : (3,) floats in [0, 1]
        Single-scattering albedo of the scatterers; default (1, 1, 1) as in Koenderink-Pont
        (unpigmented fuzz).
    f_max : float > 0
        Optional cap f <= f_max (1/sr); default inf (none: the cosine clamp already bounds f).
    base : str
        Base model the renderer adds the term to; default "lambert" (albedo texture / pi):
        the thesis's timings (docs/science.md §7) put its asperity renders below the Lafortune
        ones in every light (e.g. 19:45 vs 28:56 for the area light), so its base cannot
        have been Lafortune or HK93 plus an extra term; a Lambertian albedo base is the
        cheaper candidate.  "lafortune" and "hk93" are accepted.
    attenuate_base : bool
        The base is seen through the asperity layer (default True; docs/science.md §5): its
        BRDF is multiplied by T(mu_i) T(mu_o), T(mu) = 1 - (1 - albedo/2) e1(mu), the light
        the layer neither reflects nor absorbs to the term's own first order
        (e1 = tau (1 - tau/2) / max(mu, tau) intercepted, half of the scattered part sent
        back as the term, half on to the base).  Then term + base reflect at most
        1 - (1 - albedo) e1 <= 1 for any base whose own albedo is <= 1 (cl/asperity.cl).
        False adds the term on top of the full base (the thesis's sum), which exceeds albedo
        1 for a Lambert base above ~0.51 near grazing.
    """

    delta_mm: float = 1.0
    lambda_mm: float = 20.0
    albedo: Any = (1.0, 1.0, 1.0)
    f_max: float = math.inf
    base: str = "lambert"
    attenuate_base: bool = True

    def __post_init__(self):
        d = float(_array(self.delta_mm, "asperity.delta_mm", ()))
        lam = float(_array(self.lambda_mm, "asperity.lambda_mm", ()))
        _check(d > 0, "asperity.delta_mm", d, " (mm)", "must be > 0")
        _check(lam > d, "asperity.lambda_mm", lam, " (mm)",
               f"must be > delta_mm = {d} (the thin-layer model needs Delta/lambda < 1)")
        albedo = _array(self.albedo, "asperity.albedo", (3,))
        _check((albedo >= 0) & (albedo <= 1), "asperity.albedo", albedo, "", "must be in [0, 1]")
        try:
            f_max = float(self.f_max)
        except (TypeError, ValueError):
            raise ConfigError(f"asperity.f_max = {self.f_max!r}: must be a number > 0") from None
        _check(f_max > 0 and not math.isnan(f_max), "asperity.f_max", f_max, " (1/sr)",
               "must be > 0 (inf for no cap)")
        if self.base not in ASPERITY_BASES:
            raise ConfigError(f"asperity.base = {self.base!r}: must be one of {ASPERITY_BASES}")
        object.__setattr__(self, "delta_mm", d)
        object.__setattr__(self, "lambda_mm", lam)
        object.__setattr__(self, "albedo", albedo)
        object.__setattr__(self, "f_max", f_max)
        object.__setattr__(self, "attenuate_base", bool(self.attenuate_base))

    @property
    def tau(self) -> float:
        """Optical thickness Delta / lambda of the asperity layer."""
        return self.delta_mm / self.lambda_mm

    def pack(self) -> np.ndarray:
        """(8,) float32 block of cl/asperity.cl: tau, f_max, albedo RGB, attenuate-base
        flag, 2 unused."""
        out = np.zeros(ASPERITY_NPARAMS, dtype=np.float64)
        out[0] = self.tau
        out[1] = min(self.f_max, _F32_MAX)
        out[2:5] = self.albedo
        out[5] = float(self.attenuate_base)
        return out.astype(np.float32)


# --------------------------------------------------------------------------------------
# evaluation on the OpenCL device
# --------------------------------------------------------------------------------------

_PARAM_TYPES = {"lafortune": LafortuneParams, "hk93": HK93Params, "asperity": AsperityParams}


def _directions(v, name: str) -> np.ndarray:
    a = np.asarray(v)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ConfigError(f"{name}: must be an (N, 3) array of directions, got shape {a.shape}")
    a = np.ascontiguousarray(a, dtype=np.float32)
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{name}: contains NaN or Inf")
    return a


def evaluate(model: str, wo, wi, params=None, *, albedo=None, env=None) -> np.ndarray:
    """Evaluate a model's BRDF on the OpenCL device for N direction pairs.

    Parameters
    ----------
    model : {"lafortune", "hk93", "asperity"}
    wo, wi : (N, 3) float arrays
        Unit directions in the local shading frame (z = normal), both pointing away from the
        surface.  Directions on or below the horizon give f = 0.
    params : LafortuneParams | HK93Params | AsperityParams | None
        The model's parameters; None uses the defaults.
    albedo : (N, 3) or (3,) floats, optional
        Lafortune only: linear-RGB albedo per pair (replaces rho_d); default params.rho_d.
    env : pipeline.cl.ClEnv, optional
        OpenCL environment; default ``pipeline.cl.get_env()``.

    Returns
    -------
    (N, 3) float32 ndarray
        f(wo, wi) in 1/sr per RGB channel (cosine not included).

    Raises
    ------
    ConfigError
        Unknown model, parameters of the wrong type, or malformed direction/albedo arrays.
    """
    if model not in _PARAM_TYPES:
        raise ConfigError(f"model = {model!r}: must be one of {MODELS}")
    ptype = _PARAM_TYPES[model]
    if params is None:
        params = ptype()
    if not isinstance(params, ptype):
        raise ConfigError(f"params for model {model!r} must be {ptype.__name__}, "
                          f"got {type(params).__name__}")
    wo = _directions(wo, "wo")
    wi = _directions(wi, "wi")
    if wo.shape != wi.shape:
        raise ConfigError(f"wo and wi must have the same shape, got {wo.shape} and {wi.shape}")
    n = wo.shape[0]
    args = [wo, wi]
    if model == "lafortune":
        alb = params.rho_d if albedo is None else albedo
        alb = np.asarray(alb, dtype=np.float32)
        if alb.shape == (3,):
            alb = np.broadcast_to(alb, (n, 3))
        if alb.shape != (n, 3):
            raise ConfigError(f"albedo: must have shape (3,) or ({n}, 3), got {alb.shape}")
        if not np.all(np.isfinite(alb)):
            raise ConfigError("albedo: contains NaN or Inf")
        args.append(np.ascontiguousarray(alb))
    elif albedo is not None:
        raise ConfigError(f"albedo is a Lafortune parameter; model {model!r} takes none")
    out = np.zeros((n, 3), dtype=np.float32)
    if n == 0:
        return out

    import pyopencl as cl
    from dermis.pipeline.cl import get_env, to_device
    env = env or get_env()
    kernel = cl.Kernel(env.program(KERNEL_FILES[model]), f"{model}_eval")
    bufs = [to_device(env, a) for a in args] + [to_device(env, params.pack())]
    out_buf = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
    kernel(env.queue, (n,), None, *bufs, out_buf, np.int32(n))
    cl.enqueue_copy(env.queue, out, out_buf)
    return out


# --------------------------------------------------------------------------------------
# float64 NumPy single scattering of HK93 (written from the formulas, in angles): the
# pipeline's rho_ms (HK93Params) and the tests' reference (tests/brdf_reference.py)
# --------------------------------------------------------------------------------------

def _angles(w):
    """(cos theta, sin theta, phi) of (N, 3) directions, float64."""
    w = np.asarray(w, dtype=np.float64)
    cos_t = w[:, 2]
    sin_t = np.hypot(w[:, 0], w[:, 1])
    phi = np.arctan2(w[:, 1], w[:, 0])
    return cos_t, sin_t, phi


def _fresnel_angles(theta_i, theta_t, eta_rel):
    """Unpolarised Fresnel reflectance from angles (sin/tan form), normal-incidence limit."""
    small = theta_i < 1e-6
    ti = np.where(small, 0.5, theta_i)   # placeholder angles where the limit applies
    tt = np.where(small, 0.4, theta_t)
    rs = -np.sin(ti - tt) / np.sin(ti + tt)
    rp = np.tan(ti - tt) / np.tan(ti + tt)
    normal = ((eta_rel - 1.0) / (eta_rel + 1.0)) ** 2
    return np.where(small, normal, 0.5 * (rs * rs + rp * rp))


def _hk93_single_np(wo, wi, layers) -> np.ndarray:
    """HK93 single scattering (N, 3) float64, summed over the layers (docs/science.md §2):
    no horizon test, no constant term (tests/brdf_reference.py hk93_f_np adds those)."""
    co, so, po = _angles(wo)
    ci, si, pi_ = _angles(wi)
    # grazing floor HK93_COS_MIN (part of the model, cl/brdf_hk93.cl)
    co = np.maximum(co, HK93_COS_MIN)
    ci = np.maximum(ci, HK93_COS_MIN)
    th0o, th0i = np.arccos(co), np.arccos(ci)
    n = co.shape[0]
    f = np.zeros((n, 3))
    through = np.ones((n, 3))      # product of transmittances/attenuations above the layer
    eta_prev, tho_prev, thi_prev = 1.0, th0o, th0i
    for lay in layers:
        tho = np.arcsin(np.sin(th0o) / lay.eta)
        thi = np.arcsin(np.sin(th0i) / lay.eta)
        rel = lay.eta / eta_prev
        t_in = 1.0 - _fresnel_angles(thi_prev, thi, rel)
        t_out = 1.0 - _fresnel_angles(tho_prev, tho, rel)
        through = through * (t_in * t_out)[:, None]
        # propagation directions inside the layer: down along -wi refracted, up along wo
        d_in = np.stack([-np.sin(thi) * np.cos(pi_), -np.sin(thi) * np.sin(pi_), -np.cos(thi)], 1)
        d_out = np.stack([np.sin(tho) * np.cos(po), np.sin(tho) * np.sin(po), np.cos(tho)], 1)
        cos_scatter = np.sum(d_in * d_out, axis=1)
        g = lay.g
        hg = (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * cos_scatter) ** 1.5)
        sigma_t = np.asarray(lay.sigma_a) + lay.sigma_s
        albedo = lay.sigma_s / sigma_t
        path = (1 / np.cos(thi) + 1 / np.cos(tho))[:, None]
        if math.isinf(lay.thickness_mm):
            depth = np.ones((n, 3))
        else:
            depth = -np.expm1(-sigma_t * lay.thickness_mm * path)
        single = albedo * (hg / (lay.eta ** 2 * (np.cos(thi) + np.cos(tho))))[:, None] * depth
        f += through * single
        if not math.isinf(lay.thickness_mm):
            through = through * np.exp(-sigma_t * lay.thickness_mm * path)
        eta_prev, tho_prev, thi_prev = lay.eta, tho, thi
    return f
