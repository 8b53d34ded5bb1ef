"""The adaptive BSSRDF (docs/science.md §4 "Adaptive gather"): the BSSRDF of
``models/bssrdf.py`` shaded with its local limit, Rd E(x) (``subsurface/local.py``),
everywhere, and gathered only where a predictor (irradiance varying within the profile's
reach on the image, occlusion, and the gather's change measured on a sparse grid of pixels)
says the gather changes the pixel by more than ``subsurface.adaptive.TARGET``, blended
smoothly between the two (``subsurface/adaptive.py``).  Rendered by the BSSRDF stage beside the full one, with its
blend mask (``render/bssrdf_adaptive-<lighting>-<geometry>-blend.exr``); measured against it
in bench/results/bssrdf_adaptive.json.
"""
from __future__ import annotations

from dermis.models.bssrdf import check_scene
from dermis.models.model import Model
from dermis.subsurface.adaptive import adaptive_exitance

__all__ = ["MODEL"]

MODEL = Model(name="bssrdf_adaptive", label="BSSRDF (adaptive)", stage="bssrdf",
              doc="docs/science.md §4", profiles=True, check=check_scene, glossy=True,
              exitance=adaptive_exitance)
