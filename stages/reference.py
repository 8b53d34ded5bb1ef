"""Stage ``reference``: a Mitsuba 3 volumetric path-traced image of one lighting condition.

The ground truth every model is measured against (docs/ground-truth.md): the scene exported
by :mod:`dermis.stages.mitsuba_scene` (high mesh in mm, camera, lights, the layer stack as
media inside a rough dielectric boundary, the albedo texture as a transmission tint) and
rendered twice with independent seeds, so the reference carries its own noise:

* the image is the mean of the two renders; (A - B) / 2 estimates its per-pixel error;
* ``info["noise"]``: the relative RMSE noise of the image on ``factor`` x ``factor`` block
  means (factor 1 = reference pixels), the same measure as the models' relative RMSE;
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
import math
import time
from dataclasses import asdict

import numpy as np

from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.config import CameraConfig, LightConfig
from dermis.pipeline.errors import ConfigError
from dermis.pipeline.graph import Node, StageResult
from dermis.optics.layers import LayerStack
from dermis.lighting.lights import light_params
from dermis.geometry.regions import REGIONS, REGION_LABELS, block_mean, face_regions, region_stats

NAME = "reference"
VERSION = 1
KERNELS = ()
GEOMETRY = "high"
MESH_NODE = "mesh_high"
# Block factors (on the reference's own pixel grid) at which noise and errors are reported.
NOISE_FACTORS = (1, 2, 4, 8)
# Fractions of the samples at which the two-seed noise is measured (the noise-vs-spp curve).
CURVE_FRACTIONS = (1 / 16, 1 / 8, 1 / 4, 1 / 2, 1)


def unavailable_reason() -> str | None:
    """Why the stage cannot run here (Mitsuba missing), or None."""
    from dermis.stages.mitsuba_scene import mitsuba_missing_reason
    return mitsuba_missing_reason()


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
    return Node(f"reference-{label}", NAME, __name__, params, {"mesh": MESH_NODE},
                label=f"reference / {label} (Mitsuba)")


def two_seed_noise(a: np.ndarray, b: np.ndarray, mask: np.ndarray, factors=NOISE_FACTORS
                   ) -> dict:
    """Relative RMSE noise of the mean of two independent renders, per block factor.

    noise = sqrt(mean ((A - B) / 2)^2) / sqrt(mean ((A + B) / 2)^2) over the fully covered
    blocks and all channels (the definition of the models' ``rel_rmse``); ``_rgb`` per
    channel.  A single render's noise is sqrt(2) times this.
    """
    out = {}
    for f in factors:
        A, m = block_mean(a, mask, f)
        B, _ = block_mean(b, mask, f)
        if not m.any():
            continue
        hd, mean = (A - B)[m] / 2.0, (A + B)[m] / 2.0
        rms = math.sqrt(float((mean * mean).mean()))
        out[str(f)] = {"rel": math.sqrt(float((hd * hd).mean())) / rms if rms > 0 else 0.0,
                       "rel_rgb": [float(math.sqrt((hd[:, c] ** 2).mean())
                                         / max(math.sqrt((mean[:, c] ** 2).mean()), 1e-30))
                                   for c in range(3)],
                       "blocks": int(m.sum())}
    return out


def run(params: dict, inputs: dict, ctx) -> StageResult:
    from dermis.pipeline.imageio import write_exr, write_png
    from dermis.stages import mitsuba_scene as ms

    t_start = time.perf_counter()
    r = params["reference"]
    mesh = inputs["mesh"]
    camera = CameraConfig(**params["camera"])
    lights = [LightConfig(**d) for d in params["lights"]]
    stack = LayerStack.from_dict(params["optics"])
    mi = ms.load_mitsuba(r["variant"])
    variant = mi.variant()

    # the path tracer's own Rd of the stack: the albedo tint's normalisation (one per run)
    key = ("reference_slab", json.dumps(params["optics"], sort_keys=True), r["roughness"],
           r["max_depth"], r["rr_depth"], r["slab_samples"], variant)
    if key not in ctx.memo:
        ctx.memo[key] = ms.slab_reflectance(mi, stack, roughness=r["roughness"],
                                            samples=r["slab_samples"], seed=r["seed"],
                                            max_depth=r["max_depth"], rr_depth=r["rr_depth"])
    slab = ctx.memo[key]
    t0 = time.perf_counter()
    head = ms.head_scene(mi, mesh, stack, camera, lights, width=r["width"], height=r["height"],
                         roughness=r["roughness"], tint_rd=slab.Rd, env_clamp=r["env_clamp"],
                         max_depth=r["max_depth"], rr_depth=r["rr_depth"])
    t_load = time.perf_counter() - t0
    try:
        w, h = r["width"], r["height"]
        hit, prim = ms.pixel_hits(mi, head.scene, width=w, height=h)
        labels = np.where(hit, face_regions(mesh.vertices, mesh.faces)[np.maximum(prim, 0)], 0)
        spp = int(r["spp"])
        marks = sorted({max(1, int(round(spp * f))) for f in CURVE_FRACTIONS})
        total = 2 * spp

        def progress(offset):
            return (lambda n: ctx.progress((offset + n) / total)) if ctx.progress else None

        img_a, curve_a, t_a = ms.render_passes(mi, head.scene, spp=spp, seed=2 * r["seed"],
                                               checkpoints=marks, progress=progress(0))
        img_b, curve_b, t_b = ms.render_passes(mi, head.scene, spp=spp, seed=2 * r["seed"] + 1,
                                               checkpoints=marks, progress=progress(spp))
    finally:
        ms.release(head)
    mean = (img_a + img_b) / 2.0
    noise = two_seed_noise(img_a, img_b, hit)
    curve = []
    for (n, a), (_, b) in zip(curve_a, curve_b):
        curve.append({"spp": 2 * n, "noise": {f: v["rel"] for f, v in
                                               two_seed_noise(a, b, hit).items()}})
    # c = noise x sqrt(spp): the mean over the checkpoints from 1/4 of the samples on (the
    # early ones carry the heavy-tailed start-up of the estimate)
    fit = {}
    for f in noise:
        vals = [p["noise"][f] * math.sqrt(p["spp"]) for p in curve if f in p["noise"]
                and p["spp"] >= 2 * spp / 4]
        fit[f] = float(np.mean(vals)) if vals else 0.0
    regions = region_stats(mean, labels, half_diff=(img_a - img_b) / 2.0)
    seconds = t_a + t_b
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

