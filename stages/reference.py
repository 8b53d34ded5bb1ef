"""Stage ``reference``: a Mitsuba 3 volumetric path-traced image of one lighting condition.

The ground truth every model is measured against (docs/ground-truth.md): the scene exported
by :mod:`dermis.groundtruth.scene_export` (high mesh in mm, camera, lights, the layer stack as
media inside a rough dielectric boundary, the albedo texture as a transmission tint), traced
in progressive passes of two independent half-buffers over the head's pixels until every face
region's mean is known to ``target_rel_se`` or ``budget_s`` runs out
(:mod:`dermis.groundtruth.progressive`).  The image is the mean of the halves; (A - B) / 2
estimates its error:

* ``info["noise"]``: the relative RMSE noise of the image on ``factor`` x ``factor`` block
  means (:mod:`dermis.groundtruth.noise`); ``info["noise_curve"]``/``["noise_fit"]``: that
  noise during the uniform passes and c = noise x sqrt(spp), from which
  :mod:`dermis.reports.ground_truth` computes the path tracer's time to reach an error;
* ``info["regions"]``: per face region the mean RGB and its standard error
  (sqrt(sum ((A - B) / 2)^2) / N); ``info["region_rel_se"]`` that error of the luminance
  mean, relative; ``passes``, ``stopped`` (target, budget, max_spp or max_passes) say how
  far it got.

The image is at ``[reference] width`` x ``height``, an integer fraction of the camera's
size: a reference pixel is the average over the block of camera pixels it covers (box
filter).  One node per lighting condition, on the high mesh, when ``[reference] enabled``
(the default) and Mitsuba can run (:func:`unavailable_reason`; else the planner skips it with
one message).  ``budget_s`` and ``max_passes`` are resumable: a run with a larger budget
continues from the passes of the cached entry (``passes.npz``) instead of starting over.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, fields

import numpy as np

from dermis.geometry.regions import REGION_LABELS, face_regions, region_colours, region_stats
from dermis.groundtruth import mitsuba
from dermis.groundtruth.noise import noise_fit, two_seed_noise
from dermis.groundtruth.passes import pixel_hits
from dermis.groundtruth.pixel_tracing import TraceJob, forget, job_scene, job_sensor, trace_tile
from dermis.groundtruth.progressive import HalfBuffers, PassSettings, refine, region_rel_se
from dermis.groundtruth.scene_export import HeadSceneOptions
from dermis.groundtruth.slab import SLABS, slab_reflectance
from dermis.lighting.emitters import light_params
from dermis.optics.layers import LayerStack
from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.config import CameraConfig, LightConfig
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.schema import condition_of
from dermis.pipeline.scene_rules import reference_size
from dermis.pipeline.imageio import write_exr, write_png

NAME = "reference"
VERSION = 2   # 2: progressive half-buffers over the head's pixels
KERNELS = ()
SHARES = (SLABS,)
GEOMETRY = "high"
MESH_NODE = "mesh_high"
PASSES = "passes.npz"    # the half-buffers' sums, what a larger budget continues from


def unavailable_reason() -> str | None:
    """Why the stage cannot run here (Mitsuba missing), or None."""
    return mitsuba.mitsuba_missing_reason()


def node_id(label: str) -> str:
    return f"{NAME}-{label}"


def node(scene, label: str, lights: tuple) -> Node:
    """The reference of one lighting condition (``[reference]`` checked at load)."""
    camera = scene.camera_of(label)
    w, h = reference_size(camera, scene.reference)
    params = {"label": label, "camera": asdict(camera), **light_params(lights),
              "optics": scene.optics.to_dict(),
              "reference": {**asdict(scene.reference), "width": w, "height": h}}
    return Node(node_id(label), NAME, __name__, params, {"mesh": MESH_NODE},
                label=f"reference / {label} (Mitsuba)", locations=("lights[].map",),
                resumable=("reference.budget_s", "reference.max_passes", "reference.max_paths"))


@mitsuba.exclusive
def run(params: dict, inputs: dict, ctx) -> StageResult:
    t_start = time.perf_counter()
    r = params["reference"]
    mesh = inputs["mesh"]
    camera = CameraConfig(**params["camera"])
    lights = [LightConfig(**d) for d in params["lights"]]
    stack = LayerStack.from_dict(params["optics"])
    mi = mitsuba.load_mitsuba(r["variant"])
    variant = mi.variant()

    # the path tracer's own Rd of the stack: the albedo tint's normalisation (one per run)
    key = ("reference_slab", json.dumps(params["optics"], sort_keys=True), r["roughness"],
           r["max_depth"], r["rr_depth"], r["slab_samples"], variant)
    slab = ctx.shared.get(SLABS, key, lambda: slab_reflectance(
        mi, stack, roughness=r["roughness"], samples=r["slab_samples"], seed=r["seed"],
        max_depth=r["max_depth"], rr_depth=r["rr_depth"]))
    w, h = r["width"], r["height"]
    options = HeadSceneOptions(roughness=r["roughness"], tint_rd=slab.Rd_entered,
                               env_clamp=r["env_clamp"], max_depth=r["max_depth"],
                               rr_depth=r["rr_depth"])
    job = TraceJob(f"{NAME}-{params['label']}-{time.time_ns()}", mesh, stack, camera, lights,
                   w, h, options, variant, getattr(ctx, "input_keys", {}).get("mesh", ""))
    settings = PassSettings(**{f.name: r[f.name] for f in fields(PassSettings)})
    try:
        t0 = time.perf_counter()
        _, head = job_scene(job)
        t_load = time.perf_counter() - t0
        export = head.export
        hit, prim = pixel_hits(mi, head.scene, width=w, height=h, sensor=job_sensor(job))
        labels = np.where(hit, face_regions(mesh.vertices, mesh.faces)[np.maximum(prim, 0)], 0)
        buffers, resumed = _resumed(ctx, h, w)
        stopped = refine(lambda tiles: ctx.tasks.map(trace_tile, job, tiles), buffers, hit,
                         labels, settings, seed=r["seed"], progress=ctx.progress)
    finally:
        forget(job.token)
        ctx.tasks.each_worker(forget, job.token)
    buffers.save(ctx.out_dir / PASSES)
    img_a, img_b = buffers.halves()
    mean = buffers.image()
    noise = two_seed_noise(img_a, img_b, hit)
    curve = [{"spp": p["spp_min"], "noise": p["noise"]} for p in buffers.log if "noise" in p]
    regions = region_stats(mean, labels, half_diff=buffers.half_diff())
    rel_se = region_rel_se(buffers, labels)
    seconds = buffers.seconds
    paths = 2 * int(buffers.count.sum())
    timings = {"total": time.perf_counter() - t_start, "render": seconds, "scene_load": t_load,
               "slab": slab.seconds, "seconds_per_spp": seconds * hit.sum() / max(paths, 1),
               "kernel_seconds": 0.0}
    name = f"reference-{params['label']}"
    write_exr(ctx.out_dir / f"{name}.exr", mean.astype(np.float32))
    write_exr(ctx.out_dir / f"{name}-halfA.exr", img_a.astype(np.float32))
    write_exr(ctx.out_dir / f"{name}-halfB.exr", img_b.astype(np.float32))
    write_exr(ctx.out_dir / f"{name}-spp.exr",
              np.repeat(2.0 * buffers.count[..., None], 3, axis=2).astype(np.float32))
    write_png(ctx.out_dir / f"{name}-regions.png", region_colours(labels, hit))
    info = {"model": "reference", "light": params["label"], "geometry": GEOMETRY,
            "variant": variant, "width": w, "height": h,
            "spp": paths / max(int(hit.sum()), 1), "spp_min": 2 * int(buffers.count[hit].min())
            if hit.any() else 0, "spp_max": 2 * int(buffers.count.max()),
            "paths": paths, "passes": buffers.passes, "resumed_passes": resumed,
            "stopped": stopped, "target_rel_se": settings.target_rel_se,
            "required_rel_se": settings.required_rel_se,
            "required_met": settings.required_met(rel_se), "max_paths": settings.max_paths,
            "budget_s": settings.budget_s, "region_rel_se": rel_se,
            "noise": noise, "noise_curve": curve,
            "noise_fit": noise_fit(noise, curve, curve[-1]["spp"] // 2) if curve else {},
            "regions": regions, "region_labels": REGION_LABELS,
            "slab": {"Rd": [float(v) for v in slab.Rd],
                     "Rd_stderr": [float(v) for v in slab.Rd_stderr],
                     "specular": [float(v) for v in slab.specular],
                     "Rd_entered": [float(v) for v in slab.Rd_entered],
                     "samples": slab.samples, "seconds": slab.seconds},
            "export": export, "env_clamp": r["env_clamp"],
            "hit_pixels": int(hit.sum()), "pass_log": buffers.log, "camera": params["camera"]}
    files = [f"{name}.exr", f"{name}-halfA.exr", f"{name}-halfB.exr", f"{name}-spp.exr",
             f"{name}-regions.png"]
    return StageResult(RenderedImage(mean.astype(np.float32), hit, timings, info), files=files,
                       info={"timings": timings, "variant": variant, "noise": noise,
                             "passes": buffers.passes, "resumed_passes": resumed,
                             "stopped": stopped, "region_rel_se": rel_se,
                             "kernel_seconds": 0.0})


def _resumed(ctx, height: int, width: int) -> tuple[HalfBuffers, int]:
    """The half-buffers of an earlier entry of the same work (a smaller or larger budget,
    ``Node.resumable``) and their pass count, else empty ones and 0."""
    earlier = getattr(ctx, "resume_from", None)
    if earlier is not None and (earlier / PASSES).is_file():
        buffers = HalfBuffers.load(earlier / PASSES)
        if buffers.count.shape == (height, width):
            return buffers, buffers.passes
    return HalfBuffers.empty(height, width), 0


_SKIP_NOTICES: set = set()   # each reason once per process


def plan(scene, plan) -> None:
    """One reference per lighting condition of ``[reference] lights`` (all when empty), when
    enabled; where Mitsuba cannot run, none, with the reason said once and recorded for the
    report."""
    if not scene.reference.enabled:
        return
    groups = dict(scene.light_groups())
    wanted = scene.reference.lights or tuple(groups)   # names checked at load (scene_rules)
    reason = unavailable_reason()
    if reason:
        if reason not in _SKIP_NOTICES:
            _SKIP_NOTICES.add(reason)
            print(f"dermis: reference stage skipped: {reason}", file=sys.stderr)
        plan.skipped[NAME] = f"Reference stage skipped: {reason}"
        return
    # the close-ups right after the main camera's condition of the same lights: they trace
    # the same loaded scene (groundtruth/pixel_tracing.py, KEEP_SCENES)
    conditions = list(dict.fromkeys(condition_of(label) for label in wanted))
    for label in sorted(wanted, key=lambda l: conditions.index(condition_of(l))):
        plan.add(node(scene, label, groups[label]), target=True)
