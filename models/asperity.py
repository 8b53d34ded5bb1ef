"""The Koenderink-Pont asperity scattering term (docs/science.md §5): a thin layer of sparse
scatterers (vellus hair) over the skin, added to a base BRDF, never a material on its own.

Kernel ``cl/asperity.cl`` (its header comment gives the equations); ``cl/shade.cl`` adds the
term over the base chosen by :attr:`AsperityParams.base` (one of :data:`BASES`, or "none":
the term alone, which the BSSRDF image adds to its own).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dermis.models import hk93, lafortune, lambert
from dermis.models.checks import checked_array, require
from dermis.models.model import Model
from dermis.pipeline.errors import ConfigError

__all__ = ["AsperityParams", "ASPERITY_NPARAMS", "BASES", "KERNELS", "MODEL"]

KERNELS = ("asperity.cl",)

# Parameter-block size; must equal the #define in cl/asperity.cl (checked by the tests).
ASPERITY_NPARAMS = 8

# The base models the term is added to.
BASES = (lambert.MODEL, lafortune.MODEL, hk93.MODEL)
_BASE_NAMES = tuple(m.name for m in BASES)

_F32_MAX = float(np.finfo(np.float32).max)


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
        d = float(checked_array(self.delta_mm, "asperity.delta_mm", ()))
        lam = float(checked_array(self.lambda_mm, "asperity.lambda_mm", ()))
        require(d > 0, "asperity.delta_mm", d, " (mm)", "must be > 0")
        require(lam > d, "asperity.lambda_mm", lam, " (mm)",
                f"must be > delta_mm = {d} (the thin-layer model needs Delta/lambda < 1)")
        albedo = checked_array(self.albedo, "asperity.albedo", (3,))
        require((albedo >= 0) & (albedo <= 1), "asperity.albedo", albedo, "", "must be in [0, 1]")
        try:
            f_max = float(self.f_max)
        except (TypeError, ValueError):
            raise ConfigError(f"asperity.f_max = {self.f_max!r}: must be a number > 0") from None
        require(f_max > 0 and not math.isnan(f_max), "asperity.f_max", f_max, " (1/sr)",
                "must be > 0 (inf for no cap)")
        if self.base not in _BASE_NAMES:
            raise ConfigError(f"asperity.base = {self.base!r}: must be one of {_BASE_NAMES}")
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


def _scene_params(scene: dict, shared) -> AsperityParams:
    """The default layer over the scene's ``[render] asperity_base``."""
    return AsperityParams(base=scene["asperity_base"])


def _check_scene(stack, sections: dict, where: str) -> list[str]:
    """What the base under the term needs of the scene (``[render] asperity_base``)."""
    render = sections.get("render")
    base = next((b for b in BASES if render is not None and b.name == render.asperity_base), None)
    return base.check(stack, sections, where) if base is not None and base.check else []


MODEL = Model(name="asperity", label="asperity", stage="render", doc="docs/science.md §5",
              params=AsperityParams, kernel=KERNELS[0], shade=(("DERMIS_ASPERITY", 1),),
              bases=BASES, scene_params=_scene_params, check=_check_scene)
