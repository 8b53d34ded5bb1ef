"""The BSSRDF's local limit (docs/science.md §4 "Local limit"): the profile's total
reflectance Rd applied where the light enters, M = Rd E(x), with no gather
(``subsurface/local.py``), behind the same Fresnel exit and surface term as
``models/bssrdf.py``.  Rendered beside the full BSSRDF it measures what subsurface transport
along the surface does to the image (the requirement table's "subsurface transport" effect,
reports/requirements.py).
"""
from __future__ import annotations

from dermis.models.bssrdf import check_scene
from dermis.models.model import Model
from dermis.subsurface.local import local_limit_exitance

__all__ = ["MODEL"]

MODEL = Model(name="bssrdf_local", label="BSSRDF (local limit, Rd E)", stage="bssrdf",
              doc="docs/science.md §4", profiles=True, check=check_scene, glossy=True,
              exitance=local_limit_exitance)
