"""Stage ``reference``: a Mitsuba 3 volumetric path-traced image of one lighting condition.

The ground truth every model is measured against (docs/ground-truth.md): the scene exported
by :mod:`dermis.groundtruth.scene_export` (high mesh in mm, camera, lights, the layer stack as
media inside a rough dielectric boundary, the albedo texture as a transmission tint) and
rendered twice with independent seeds, so the reference carries its own noise:

* the image is the mean of the two renders; (A - B) / 2 estimates its per-pixel error;
* ``info["noise"]``: the relative RMSE noise of the image on ``factor`` x ``factor`` block
  means (factor 1 = reference pixels), the same measure as the models' relative RMSE
  (:mod:`dermis.groundtruth.noise`);
* ``info["regions"]``: per face region (:mod:`dermis.geometry.regions`) the mean RGB and the
  standard error of that mean (sqrt(sum ((A - B) / 2)^2) / N, independent pixels), plus
  the calibration error of the albedo tint (``info["slab"]``);
* ``info["noise_curve"]``: the same noise at 1/16 .. 1 of the samples, and the fitted
  constant c = noise x sqrt(spp) per factor, from which :mod:`dermis.reports.ground_truth`
  computes the path tracer's time to reach a given error.

The image is at ``[reference] width`` x ``height``, an integer fraction of the camera's
size: a reference pixel is the average over the block of camera pixels it covers (box
filter), so the models' images are compared block-averaged.  One node per lighting
condition, on the high mesh; the node exists only when ``[reference] enabled = true`` and
Mitsuba is installed (:func:`unavailable_reason`; the planner then skips it with one
message).
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict

import numpy as np

from dermis.geometry.regions import REGIONS, REGION_LABELS, face_regions, region_stats
from dermis.groundtruth import mitsuba
from dermis.groundtruth.noise import noise_curve, noise_fit, two_seed_noise
from dermis.groundtruth.passes import render_two_seeds
from dermis.groundtruth.scene_export import HeadSceneOptions, head_scene, release
from dermis.groundtruth.slab import SLABS, slab_reflectance
from dermis.lighting.emitters import light_params
from dermis.optics.layers import LayerStack
from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.config import CameraConfig, LightConfig
from dermis.pipeline.errors import ConfigError
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.imageio import write_exr, write_png

NAME = "reference"
VERSION = 1
KERNELS = ()
SHARES = (SLABS,)
GEOMETRY = "high"
MESH_NODE = "mesh_high"


def unavailable_reason() -> str | None:
    """Why the stage cannot run here (Mitsuba missing), or None."""
    return mitsuba.mitsuba_missing_reason()


def node_id(label: str) -> str:
    return f"{NAME}-{label}"


def node(scene, label: str, lights: tuple) -> Node:
    r = scene.reference
    cam = scene.camera
    if cam.width % r.width or cam.height % r.height:
        raise ConfigError(f"{scene.path}: reference.width x height = {r.width} x {r.height}: "
                          f"must divide the camera's {cam.width} x {cam.height} (a reference "
                          "pixel is a block of camera pixels)")
    if cam.width // r.width != cam.height // r.height:
        raise ConfigError(f"{scene.path}: reference.width x height = {r.width} x {r.height}: "
                          f"must keep the camera's aspect ({cam.width} x {cam.height})")
    params = {"label": label, "camera": asdict(cam), **light_params(lights),
              "optics": scene.optics.to_dict(), "reference": asdict(r)}
    return Node(node_id(label), NAME, __name__, params, {"mesh": MESH_NODE},
                label=f"reference / {label} (Mitsuba)")


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
    t0 = time.perf_counter()
    head = head_scene(mi, mesh, stack, camera, lights, width=r["width"], height=r["height"],
                      options=HeadSceneOptions(roughness=r["roughness"], tint_rd=slab.Rd_entered,
                                               env_clamp=r["env_clamp"],
                                               max_depth=r["max_depth"],
                                               rr_depth=r["rr_depth"]))
    t_load = time.perf_counter() - t0
    w, h, spp = r["width"], r["height"], int(r["spp"])
    try:
        two = render_two_seeds(mi, head.scene, width=w, height=h, spp=spp, seed=r["seed"],
                               progress=ctx.progress)
    finally:
        release(head)
    img_a, img_b, hit, total = two.img_a, two.img_b, two.hit, 2 * spp
    labels = np.where(hit, face_regions(mesh.vertices, mesh.faces)[np.maximum(two.prim, 0)], 0)
    mean = (img_a + img_b) / 2.0
    noise = two_seed_noise(img_a, img_b, hit)
    curve = noise_curve(two.curve_a, two.curve_b, hit)
    fit = noise_fit(noise, curve, spp)
    regions = region_stats(mean, labels, half_diff=(img_a - img_b) / 2.0)
    seconds = two.seconds
    timings = {"total": time.perf_counter() - t_start, "render": seconds, "scene_load": t_load,
               "slab": slab.seconds, "seconds_per_spp": seconds / total, "kernel_seconds": 0.0}
    name = f"reference-{params['label']}"
    write_exr(ctx.out_dir / f"{name}.exr", mean.astype(np.float32))
    write_exr(ctx.out_dir / f"{name}-seedA.exr", img_a.astype(np.float32))
    write_exr(ctx.out_dir / f"{name}-seedB.exr", img_b.astype(np.float32))
    palette = np.array([[0, 0, 0], [230, 60, 60], [60, 200, 60], [60, 60, 230], [230, 200, 40],
                        [160, 60, 200], [128, 128, 128]], np.uint8)
    lab_img = palette[np.where(hit & (labels == 0), len(REGIONS) + 1, labels)]
    write_png(ctx.out_dir / f"{name}-regions.png", lab_img)
    info = {"model": "reference", "light": params["label"], "geometry": GEOMETRY,
            "variant": variant, "width": w, "height": h, "spp": total,
            "spp_per_seed": spp, "seeds": [2 * r["seed"], 2 * r["seed"] + 1],
            "noise": noise, "noise_curve": curve, "noise_fit": fit,
            "regions": regions, "region_labels": REGION_LABELS,
            "slab": {"Rd": [float(v) for v in slab.Rd],
                     "Rd_stderr": [float(v) for v in slab.Rd_stderr],
                     "specular": [float(v) for v in slab.specular],
                     "Rd_entered": [float(v) for v in slab.Rd_entered],
                     "samples": slab.samples, "seconds": slab.seconds},
            "export": head.export, "env_clamp": r["env_clamp"],
            "hit_pixels": int(hit.sum())}
    files = [f"{name}.exr", f"{name}-seedA.exr", f"{name}-seedB.exr", f"{name}-regions.png"]
    return StageResult(RenderedImage(mean.astype(np.float32), hit, timings, info), files=files,
                       info={"timings": timings, "variant": variant, "noise": noise,
                             "kernel_seconds": 0.0})


_SKIP_NOTICES: set = set()   # each reason once per process


def plan(scene, plan) -> None:
    """One reference per lighting condition of ``[reference] lights`` (all when empty), when
    enabled; where Mitsuba cannot run, none, with the reason said once and recorded for the
    report."""
    if not scene.reference.enabled:
        return
    groups = dict(scene.light_groups())
    wanted = scene.reference.lights or tuple(groups)
    unknown = [l for l in wanted if l not in groups]
    if unknown:
        raise ConfigError(f"{scene.path}: reference.lights: {unknown[0]!r} is not a lighting "
                          f"condition of [render] lights ({', '.join(groups)})")
    reason = unavailable_reason()
    if reason:
        if reason not in _SKIP_NOTICES:
            _SKIP_NOTICES.add(reason)
            print(f"dermis: reference stage skipped: {reason}", file=sys.stderr)
        plan.skipped[NAME] = f"Reference stage skipped: {reason}"
        return
    for label in wanted:
        plan.add(node(scene, label, groups[label]), target=True)
