"""Stage ``differences``: the difference images and metrics of one lighting condition.

Every model against the BSSRDF and every low geometry against the high mesh, under one
light (:mod:`dermis.reports.light_differences`): ``diff-*.png`` and ``geomdiff-*.png``
(exported into the report folder), the light's ``metrics.json`` and thumbnails of its
difference images for the report's grids and PDF.  One node per lighting condition, so a
changed light redraws only its own comparisons; the ``report`` node merges them.
"""
from __future__ import annotations

from dermis.pipeline.graph import Node, StageResult
from dermis.reports.light_differences import write_light_differences

NAME = "differences"
VERSION = 1
KERNELS = ()
OUTPUT_FOLDER = "report"      # the difference PNGs go beside the report
# the model every other is compared with here (the thesis's most complete model); the
# distance to the path-traced reference, when there is one, is the report's
# (reports/ground_truth.py), whose pages show these differences beside it
BASELINE = "bssrdf"


def compared(scene) -> bool:
    """Whether the scene renders the baseline and at least one model to compare with it."""
    return BASELINE in scene.render.models and len(scene.render.models) > 1


def node_id(label: str) -> str:
    return f"{NAME}-{label}"


def node(scene, label: str, render_ids: list[str]) -> Node:
    ids = sorted(render_ids)
    return Node(node_id(label), NAME, __name__, {"label": label, "renders": ids},
                tuple(ids), label=f"differences / {label}")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    images = {nid: inputs[nid] for nid in params["renders"]}
    files = write_light_differences(images, ctx.out_dir, reference_model=BASELINE)
    return StageResult(files=[f.name for f in files])


def plan(scene, plan) -> None:
    """One node per lighting condition, over that condition's images."""
    if not compared(scene):
        return
    images = plan.provided("image")
    for label, _ in scene.light_groups():
        plan.add(node(scene, label, [n.id for n in images if n.params.get("label") == label]))
