"""The Lafortune BRDF of measured skin (docs/science.md §1): pbrt-v1's three-lobe fit
(Lafortune et al. 1997 model), with the diffuse term energy-coupled to the lobes.

Kernel ``cl/brdf_lafortune.cl`` (its header comment gives the equations and variants); the
albedo texture replaces rho_d per point, as in the thesis.  :class:`LafortuneParams`
validates itself on construction and ``pack()``s into the float32 block the kernel reads;
:func:`lafortune_lobe_albedo` is the lobes' directional albedo, tabulated for the coupling
and for the BSSRDF's surface term (``optics/transmittance.py``).

Conventions: local shading frame with z along the shading normal, ``wo`` and ``wi`` unit
vectors pointing away from the surface, f excludes the cosine, RGB linear.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dermis.models.checks import checked_array, require
from dermis.models.model import Model

__all__ = ["LafortuneParams", "lafortune_lobe_albedo", "lobe_albedo_table",
           "LAFORTUNE_NPARAMS", "LAFORTUNE_ALBEDO_NODES", "KERNELS", "MODEL"]

KERNELS = ("brdf_lafortune.cl",)

# Parameter-block size; must equal the #define in cl/brdf_lafortune.cl (checked by the tests):
# 27 lobe coefficients, the coupling block (flag, 1 / (1 - mean lobe albedo) RGB) and the
# lobes' directional albedo at LAFORTUNE_ALBEDO_NODES cosines.
LAFORTUNE_ALBEDO_NODES = 64
LAFORTUNE_NPARAMS = 27 + 4 + 3 * LAFORTUNE_ALBEDO_NODES

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
            object.__setattr__(self, name,
                               checked_array(getattr(self, name), f"lafortune.{name}", (3, 3)))
        rho_d = checked_array(self.rho_d, "lafortune.rho_d", (3,))
        object.__setattr__(self, "rho_d", rho_d)
        require(self.n > 0, "lafortune.n", self.n, "", "every lobe exponent must be > 0")
        require((rho_d >= 0) & (rho_d <= 1), "lafortune.rho_d", rho_d, "",
                "must be in [0, 1] (linear RGB albedo)")
        object.__setattr__(self, "coupled", bool(self.coupled))

    def pack(self) -> np.ndarray:
        """(LAFORTUNE_NPARAMS,) float32 (cl/brdf_lafortune.cl): per lobe k at 9k: Cxy RGB,
        Cz RGB, n RGB; [27] coupling flag, [28..30] 1 / (1 - L_mean) RGB; from [31] the
        lobes' directional albedo L(mu) RGB at mu = j / (LAFORTUNE_ALBEDO_NODES - 1)."""
        out = np.zeros(LAFORTUNE_NPARAMS, dtype=np.float64)
        out[:27] = np.stack([self.cxy, self.cz, self.n], axis=1).ravel()
        if self.coupled:
            table, mean = lobe_albedo_table(self)
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


def lobe_albedo_table(params: "LafortuneParams") -> tuple[np.ndarray, np.ndarray]:
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


def _scene_params(scene: dict, shared) -> LafortuneParams:
    """The measured-skin fit: a scene sets no Lafortune parameter."""
    return LafortuneParams()


MODEL = Model(name="lafortune", label="lafortune", stage="render", doc="docs/science.md §1",
              params=LafortuneParams, kernel=KERNELS[0], albedo="rho_d",
              shade=(("DERMIS_BASE", 1),), scene_params=_scene_params, glossy=True)
