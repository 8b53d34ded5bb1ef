"""The Lambertian BRDF f = albedo / pi: the renderer's test material (closed-form images,
tests/test_render.py) and a base under the asperity term (docs/science.md §5).  No kernel
file of its own: ``cl/shade.cl`` evaluates it inline (``DERMIS_BASE`` 0).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dermis.models.model import Model
from dermis.pipeline.errors import ConfigError

__all__ = ["LambertParams", "MODEL"]


@dataclass(frozen=True)
class LambertParams:
    """Lambertian test material f = albedo / pi (albedo from the texture when there is one).

    albedo : (3,) floats in [0, 1], linear RGB, used where no texture is given.
    """

    albedo: Any = (0.5, 0.5, 0.5)

    def __post_init__(self):
        a = np.asarray(self.albedo, dtype=np.float64)
        if a.shape != (3,) or not np.all((a >= 0) & (a <= 1)):
            raise ConfigError(f"lambert.albedo = {self.albedo!r}: must be 3 numbers in [0, 1]")
        object.__setattr__(self, "albedo", a)

    def pack(self) -> np.ndarray:
        """(4,) float32 placeholder block (the albedo travels per pixel)."""
        return np.zeros(4, dtype=np.float32)


def _scene_params(scene: dict, shared) -> LambertParams:
    """The default grey: a scene sets no Lambert parameter."""
    return LambertParams()


MODEL = Model(name="lambert", label="lambert", stage="render", doc="docs/science.md §5",
              params=LambertParams, albedo="albedo", shade=(("DERMIS_BASE", 0),),
              scene_params=_scene_params)
