"""The BSSRDF over the single layer with the skin stack's total reflectance (docs/science.md
§8, optics/single_layer.py): the same gather as ``models/bssrdf.py``, its profile without
the stack's layering, rendered beside it to measure what the layering changes at equal Rd
(the requirement table's "layering" effect).
"""
from __future__ import annotations

from dermis.models.bssrdf import check_scene
from dermis.models.model import Model

__all__ = ["MODEL"]

MODEL = Model(name="bssrdf_single", label="BSSRDF (single layer, same Rd)", stage="bssrdf",
              doc="docs/science.md §8", profile="single_layer", profiles=True,
              check=check_scene, glossy=True)
