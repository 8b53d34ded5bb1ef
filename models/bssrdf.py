"""The BSSRDF of layered skin (docs/science.md §3, §4): Jensen-Buhler's two-pass hierarchical
gather over the radial profiles of the scene's layer stack, with the Fresnel exit and the
Lafortune lobes as its surface term.  Rendered by the BSSRDF stage (``stages/bssrdf.py``)
from the irradiance points, not by ``cl/shade.cl``; its parameters are the scene's
``[bssrdf]`` and ``[optics]`` sections.
"""
from __future__ import annotations

from dermis.models.model import Model

__all__ = ["MODEL"]

MODEL = Model(name="bssrdf", label="bssrdf", stage="bssrdf", doc="docs/science.md §4",
              glossy=True)
