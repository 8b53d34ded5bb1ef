"""Stage ``mesh_previews``: PNGs of the baked maps and of high vs low + bump shading.

For eyeballing a bake, not for the report's measured images; the pictures are drawn by
:mod:`dermis.reports.previews`.
"""
from __future__ import annotations

from pathlib import Path

from dermis.lighting.visibility import EMBREE_SCENES, embree_scene
from dermis.pipeline.graph import Node, StageResult
from dermis.reports.previews import save_map_previews, save_shaded_comparison

NAME = "mesh_previews"
VERSION = 1
KERNELS = ()
PREVIEW_SIZE = 800
SHARES = (EMBREE_SCENES,)   # the renders' scenes of the same meshes


def node(scene, with_low: bool) -> Node:
    """PNG previews of the baked maps and of high vs low+bump shading (high only if no low)."""
    deps = {"high": "mesh_high", **({"low": "mesh_low", "maps": "bake"} if with_low else {})}
    return Node(NAME, NAME, __name__, {"size": PREVIEW_SIZE, "low": with_low}, deps,
                label="PNG previews")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    files = []
    scenes = tuple(embree_scene(inputs[role], ctx.shared, ctx.input_keys[role])
                   if role in inputs else None for role in ("high", "low"))
    if params["low"]:
        files += save_map_previews(inputs["maps"], ctx.out_dir)
        out = ctx.out_dir / "shaded_high_vs_low.png"
        save_shaded_comparison(inputs["high"], inputs["low"], inputs["maps"], out,
                               size=params["size"], scenes=scenes)
    else:
        out = ctx.out_dir / "shaded_high.png"
        save_shaded_comparison(inputs["high"], None, None, out, size=params["size"],
                               scenes=scenes)
    files.append(out)
    return StageResult(files=[Path(f).name for f in files])


def plan(scene, plan) -> None:
    """When ``[output] previews``; with the low mesh's maps when the bake is planned."""
    if scene.output.previews:
        plan.add(node(scene, bool(plan.of_stage("bake"))), target=True)
