"""The BSSRDF reading the Monte Carlo profile table (docs/science.md §3): the same gather as
``models/bssrdf.py`` over profiles tabulated by the Monte Carlo slab instead of the scene's
``[optics] profile``, rendered beside it to measure what the diffusion profile misses.
"""
from __future__ import annotations

from dermis.models.bssrdf import check_scene
from dermis.models.model import Model

__all__ = ["MODEL"]

MODEL = Model(name="bssrdf_mc", label="BSSRDF (Monte Carlo profile)", stage="bssrdf",
              doc="docs/science.md §3", profile="monte_carlo", profiles=True,
              check=check_scene, glossy=True)
