"""What the three Cycles models share as model plugins (models/cycles_*.py): their
``Model`` entry, the subsurface method that tells them apart, and what they need of a scene.

A Cycles model is an image of the ``cycles`` stage (stages/cycles.py): Blender renders the
scene's high (or low) mesh, camera, lights and albedo texture with a Principled BSDF whose
subsurface method is the model's; its inputs come from the scene's ``[optics]`` layer stack
by a mapping (:mod:`dermis.cycles.mapping`).  docs/cycles.md states them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from dermis.models.model import Model

__all__ = ["CyclesMethod", "cycles_model", "check_scene", "METHODS", "ANISOTROPY_MAX"]

METHODS = ("BURLEY", "RANDOM_WALK", "RANDOM_WALK_SKIN")
# Cycles clamps the random walk's phase anisotropy to [0, 0.9] (Principled BSDF, Blender
# manual "Subsurface Anisotropy"); a layer outside cannot be rendered as given
ANISOTROPY_MAX = 0.9


@dataclass(frozen=True)
class CyclesMethod:
    """The Principled BSDF's subsurface method of a Cycles model."""

    method: str = "BURLEY"

    def pack(self):   # no OpenCL kernel reads it: the model API's parameter block
        import numpy as np
        return np.zeros(4, np.float32)


def check_scene(stack, sections: dict, where: str) -> list[str]:
    """What Cycles cannot render as dermis states it, refused at load: a stack whose last
    layer is finite (a head is filled by its last layer), layers of different refractive
    index (one Principled BSDF has one IOR) and a phase anisotropy outside Cycles' [0, 0.9]."""
    out = []
    layers = stack.layers
    if not math.isinf(layers[-1].thickness_mm):
        out.append(f"{where}: optics: the Cycles models need a semi-infinite last layer "
                   '(thickness_mm = "inf"); this stack is finite')
    if len({round(l.eta, 9) for l in layers}) > 1:
        out.append(f"{where}: optics: the Cycles models have one refractive index; layers' eta "
                   f"= {[l.eta for l in layers]} differ")
    g = layers[-1].g
    if not 0.0 <= g <= ANISOTROPY_MAX:
        out.append(f"{where}: optics: layer g = {g}: Cycles' random walk takes anisotropy in "
                   f"[0, {ANISOTROPY_MAX}]")
    return out


def cycles_model(name: str, label: str, method: str) -> Model:
    """The ``Model`` of a Cycles subsurface method; its images are the matched mapping's
    (the native mapping's are ``<name>_native``, labelled "(native)": models/catalog.py)."""
    return Model(name=name, label=f"{label} (matched)", stage="cycles", doc="docs/cycles.md",
                 params=CyclesMethod, optics=True,
                 scene_params=lambda scene, shared: CyclesMethod(method), check=check_scene)
