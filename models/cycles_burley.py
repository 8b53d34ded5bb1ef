"""Blender Cycles' Principled BSDF with the BURLEY subsurface method, rendered by Cycles
itself (stages/cycles.py; docs/cycles.md).  Its inputs come from the scene's layer stack by
the mapping of ``[cycles] mappings`` (dermis/cycles/mapping.py).
"""
from __future__ import annotations

from dermis.cycles.skin_model import cycles_model

__all__ = ["MODEL"]

MODEL = cycles_model("cycles_burley", "Cycles Burley", "BURLEY")
