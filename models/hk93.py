"""The Hanrahan-Krueger 1993 BRDF of layered skin (docs/science.md §2): single scattering in
one or two layers plus a constant multiple-scattering term derived from the BSSRDF's layers.

Kernel ``cl/brdf_hk93.cl`` (its header comment gives the equations).  :class:`HK93Params`
validates the layers on construction (:class:`ConfigError` naming layer, field, value and
rule), derives rho_ms from the float64 NumPy single scattering at the end of this module
(written from the formulas, in angles, not the kernel's vector algebra; also the tests'
reference, ``tests/brdf_reference.py``), and ``pack()``s into the float32 block the kernel
reads.

Conventions: local shading frame with z along the shading normal, ``wo`` and ``wi`` unit
vectors pointing away from the surface, f excludes the cosine, RGB linear, mm and 1/mm.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from dermis.models.checks import checked_array, format_value, require
from dermis.models.model import Model
from dermis.optics.fresnel import diffuse_fresnel_external
from dermis.optics.layer_profiles import MultipoleOptions, build_profiles
from dermis.optics.layers import PRESETS, Layer, LayerStack
from dermis.pipeline.shared import Shared
from dermis.pipeline.errors import ConfigError

__all__ = ["HK93Layer", "HK93Params", "hk93_params_from_layers",
           "hk93_single_scattering_albedo", "HK93_NPARAMS", "SS_ALBEDO_TOL", "KERNELS", "MODEL"]

KERNELS = ("brdf_hk93.cl",)

# Parameter-block size; must equal the #define in cl/brdf_hk93.cl (checked by the tests).
HK93_NPARAMS = 20

# Grazing floor of the outside cosines in hk93_f (HK93_COS_MIN in cl/brdf_hk93.cl) and the
# optical depth standing for a semi-infinite layer (HK93_TAU_MAX): part of the model.
HK93_COS_MIN = 1e-7
HK93_TAU_MAX = 1e30


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
    eta = float(checked_array(_layer_attr(layer, "eta", where), f"{where}.eta", ()))
    require(1.0 <= eta <= 3.0, f"{where}.eta", eta, "", "must be in [1, 3] (absolute index)")
    g = float(checked_array(_layer_attr(layer, "g", where), f"{where}.g", ()))
    require(-1.0 < g < 1.0, f"{where}.g", g, "", "must satisfy -1 < g < 1 (HG mean cosine)")
    sa = checked_array(_layer_attr(layer, "sigma_a", where), f"{where}.sigma_a", (3,), " (1/mm)")
    ssp = checked_array(_layer_attr(layer, "sigma_s_prime", where), f"{where}.sigma_s_prime",
                        (3,), " (1/mm)")
    require(sa >= 0, f"{where}.sigma_a", sa, " (1/mm)", "must be >= 0")
    require(ssp >= 0, f"{where}.sigma_s_prime", ssp, " (1/mm)", "must be >= 0")
    require(sa + ssp > 0, f"{where}.sigma_a + sigma_s_prime", sa + ssp, " (1/mm)",
            "must be > 0 per channel")
    return HK93Layer(d, eta, tuple(sa), tuple(ssp), g)


_PROFILE_RD: dict = {}
# Radial grid (spacing, half-width; mm) of the layer file built for its Rd alone: the layer
# file's totals are closed-form / plane-parallel transport values that do not depend on the
# radial grid (optics/layer_profiles.py), so a coarse grid gives the profiles stage's Rd exactly
# (measured equal to 1e-15 on two_layer and a two-index stack) in a fraction of the time
# (two_layer 3.2 s against 11.7 s; tests/test_energy.py checks the equality).
RD_GRID = (0.5, 32.0)


def _profile_rd(layers: Sequence[HK93Layer], eta_below: float = 1.0) -> np.ndarray:
    """Total diffuse reflectance Rd (RGB, per entering photon) of the layers' profile: the
    BSSRDF's own layer file, ``optics/layer_profiles.py build_profiles`` of the same stack
    (air above, grid ``RD_GRID``), cached per stack in the process."""
    stack = LayerStack(tuple(Layer(l.thickness_mm, l.eta, tuple(float(v) for v in l.sigma_a),
                                   tuple(float(v) for v in l.sigma_s_prime), l.g)
                             for l in layers), 1.0, float(eta_below))
    key = json.dumps(stack.to_dict(), sort_keys=True)
    if key not in _PROFILE_RD:
        prof = build_profiles(stack, options=MultipoleOptions(grid=RD_GRID))
        _PROFILE_RD[key] = np.asarray(prof.Rd, np.float64)
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
# tests/test_brdf_hk93.py test13_single_scattering_quadrature_converges).
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
    target = (1.0 - diffuse_fresnel_external(layers[0].eta)) * np.asarray(rd, np.float64)
    return np.clip(target - _single_scattering_hemispherical(layers), 0.0, 1.0 - ss_max)


def _default_hk93_layers() -> tuple:
    # Same skin as the multipole model (docs/science.md §2: "derive both layers from the same
    # epidermis/dermis optical parameters"): pipeline.layers PRESETS["two_layer"], an
    # epidermis of 0.25 mm over a semi-infinite dermis, eta 1.4, g 0.8.
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
        (``optics/layer_profiles.py build_profiles`` of the same stack, cached per process).
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
            rd = checked_array(rd, "hk93.diffuse_reflectance", (3,))
            require((rd >= 0) & (rd <= 1), "hk93.diffuse_reflectance", rd, "", "must be in [0, 1]")
        elif ms is None:
            rd = _profile_rd(checked, eta_below)
        if ms is None:
            ms = _default_multiple_scattering(checked, ss_max, rd)
        ms = checked_array(ms, "hk93.multiple_scattering", (3,))
        require((ms >= 0) & (ms < 1), "hk93.multiple_scattering", ms, "",
                "must be in [0, 1) (albedo of the constant multiple-scattering term)")
        limit = 1.0 - ss_max + SS_ALBEDO_TOL
        require(ms <= limit, "hk93.multiple_scattering", ms, "",
                f"must be <= 1 - max single-scattering albedo of these layers = "
                f"{format_value(np.round(limit, 4))} (else the directional albedo exceeds 1)")
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
# float64 NumPy single scattering (written from the formulas, in angles): the
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


# The Hanrahan-Krueger model's range of a layer's (absolute) refractive index and its number
# of layers of non-zero thickness (HK93Params validates them again when it is built)
ETA_RANGE = (1.0, 3.0)
LAYER_COUNTS = (1, 2)


def check_scene(stack, sections: dict, where: str) -> list[str]:
    """What the Hanrahan-Krueger model needs of the layer stack, checked at load."""
    out = []
    layers = [(i, l) for i, l in enumerate(stack.layers) if l.thickness_mm > 0]
    lo, hi = ETA_RANGE
    for i, l in layers:
        if not lo <= l.eta <= hi:
            out.append(f"{where}: optics.layers[{i}].eta = {l.eta:g}: must be in "
                       f"[{lo:g}, {hi:g}] for the hk93 model (absolute refractive index; "
                       "the Hanrahan-Krueger model's range)")
    if not LAYER_COUNTS[0] <= len(layers) <= LAYER_COUNTS[1]:
        out.append(f"{where}: optics: {len(layers)} layers of non-zero thickness; the hk93 "
                   f"model takes {LAYER_COUNTS[0]} or {LAYER_COUNTS[1]}")
    return out


# The parameters of a layer stack, shared by the HK93 images of a run: building them
# integrates the layers' albedo (~0.8 s), and the 12 HK93 images of a matrix read the same
PARAMS_OF_STACK = Shared("hk93_params")


def _scene_params(scene: dict, shared) -> HK93Params:
    """HK93Params of the render node's ``optics`` slice (the BSSRDF's layer stack), one per
    layer stack in a run (``shared``, the run's RunCache; None builds them here)."""
    optics = scene["optics"]
    if shared is None:
        return HK93Params(layers=LayerStack.from_dict(optics))
    return shared.get(PARAMS_OF_STACK, json.dumps(optics, sort_keys=True, default=str),
                      lambda: HK93Params(layers=LayerStack.from_dict(optics)))


def _shade_albedo(params: HK93Params, albedo: np.ndarray, textured: bool) -> np.ndarray:
    """The texture tints rho_ms: cl/shade.cl expects albedo / Rd (1 = untinted)."""
    return (albedo / params.texture_reference()).astype(np.float32) \
        if textured else np.ones_like(albedo)


MODEL = Model(name="hk93", label="hk93", stage="render", doc="docs/science.md §2",
              params=HK93Params, kernel=KERNELS[0], shade=(("DERMIS_BASE", 2),), optics=True,
              scene_params=_scene_params, shade_albedo=_shade_albedo,
              shares=(PARAMS_OF_STACK,), check=check_scene)
