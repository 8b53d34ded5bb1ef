"""Stage ``images``: every rendered image tone-mapped to PNG, with contact sheets.

One exposure per lighting condition, shared by every model and geometry under it
(:mod:`dermis.reports.comparison_images`), so brightness differences between models are
real; the exposures are saved in ``exposure.json``.
"""
from __future__ import annotations

from dermis.pipeline.graph import Node, StageResult
from dermis.reports.comparison_images import write_pngs

NAME = "images"
VERSION = 2
KERNELS = ()


def node(scene, render_ids: list[str]) -> Node:
    """Tone-map every rendered image (one exposure per lighting condition), PNGs + sheets."""
    return Node(NAME, NAME, __name__, {"renders": sorted(render_ids)}, tuple(render_ids),
                label="tone-mapped PNGs")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    files = write_pngs({nid: inputs[nid] for nid in params["renders"]}, ctx.out_dir,
                       thumbnails=True)
    return StageResult(files=[f.name for f in files])


def plan(scene, plan) -> None:
    """Every rendered image of the run, when there is one."""
    images = plan.provided("image")
    if images:
        plan.add(node(scene, [n.id for n in images]), target=True)
