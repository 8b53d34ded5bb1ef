"""Stage ``bake``: albedo and bump maps in the low mesh's UV space (sharp + Gaussian-blurred),
by :func:`dermis.geometry.bake.bake_maps`."""
from __future__ import annotations

from dataclasses import asdict

from dermis.geometry.bake import bake_maps
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.registry import stage

__all__ = ["NAME", "VERSION", "KERNELS", "node", "run"]

NAME = "bake"
VERSION = 2
KERNELS: tuple[str, ...] = ()


def node(scene) -> Node:
    return Node(NAME, NAME, __name__, asdict(scene.bake), {"low": "mesh_low", "high": "mesh_high"},
                label="bake albedo + bump")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    maps = bake_maps(inputs["low"], inputs["high"], resolution=params["resolution"],
                     max_distance_mm=params["max_distance"] or None,
                     blur_sigma_px=params["blur_sigma_px"], dilate_px=params["dilate_px"],
                     reference=params["reference"], progress=ctx.progress)
    return StageResult(maps, info=maps.info)


def plan(scene, plan) -> None:
    """Only for a bump geometry."""
    if any(stage("render").GEOMETRY[g][1] for g in scene.render.geometries):
        plan.add(node(scene), target=True)
