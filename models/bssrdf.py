"""The BSSRDF of layered skin (docs/science.md §3, §4): Jensen-Buhler's two-pass hierarchical
gather over the radial profiles of the scene's layer stack, with the Fresnel exit and the
Lafortune lobes as its surface term.  Rendered by the BSSRDF stage (``stages/bssrdf.py``)
from the irradiance points, not by ``cl/shade.cl``; its parameters are the scene's
``[bssrdf]`` and ``[optics]`` sections.
"""
from __future__ import annotations

from dermis.models.model import Model
from dermis.pipeline.scene_rules import fmt as _fmt
from dermis.pipeline.resources import HEAD_AREA_MM2
from dermis.subsurface.points import spacing_from_mfp

__all__ = ["MODEL", "check_scene"]


def check_scene(stack, sections: dict, where: str) -> list[str]:
    """What a BSSRDF needs of the scene: a layer that scatters (else there is no profile)
    and at least one irradiance point on a head-sized surface at ``bssrdf.point_density``."""
    out = []
    render, bssrdf, mesh = sections.get("render"), sections.get("bssrdf"), sections.get("mesh")
    layers = [(i, l) for i, l in enumerate(stack.layers) if l.thickness_mm > 0]
    if not any(s > 0 for _, l in layers for s in l.sigma_s_prime):
        models = list(render.models) if render is not None else []
        out.append(f"{where}: optics: sigma_s_prime = 0 in every layer and channel: with "
                   f"render.models = {_fmt(models)} some layer must scatter "
                   "(a stack that only absorbs reflects no diffuse light: the BSSRDF has no "
                   "profile)")
    if bssrdf is not None and mesh is not None:
        area = HEAD_AREA_MM2["procedural" if mesh.source == "procedural" else "scan"]
        points = area / spacing_from_mfp(stack, bssrdf.point_density) ** 2
        if not points >= 1:
            least = bssrdf.point_density / points
            out.append(f"{where}: bssrdf.point_density = {_fmt(bssrdf.point_density)}: "
                       f"gives {points:.3g} irradiance points on a head-sized surface "
                       f"({area:.3g} mm^2); must give at least 1 (point_density >= "
                       f"{least:.3g} for this layer stack)")
    return out


MODEL = Model(name="bssrdf", label="bssrdf", stage="bssrdf", doc="docs/science.md §4",
              profiles=True, check=check_scene, glossy=True)
