"""BRDF images of the default scene: seconds, anti-aliasing error per spp, and fireflies.

Meshes and maps are the default scene's (the Lee Perry-Smith scan, ``scenes/default.toml``),
built or read through the pipeline cache (``--cache``, else ``$DERMIS_CACHE`` / ``./.dermis-cache``).

Modes (each writes JSON):

* ``--timing`` (default): per lighting condition and mesh, the shared visibility
  (camera rays, light sampling, shadow rays) and each BRDF model's shading, 800 x 800.
  -> ``bench/results/render.json``
* ``--spp 1,4,9,16``: the point light (hard shadows) and the sunset, Lafortune on the high
  mesh: seconds (visibility + shading) and the relative RMSE of the image against an
  spp = 64 render, over the head's pixels, per spp: what anti-aliasing buys for its cost.
  -> ``bench/results/render_spp.json``
* ``--fireflies``: under the sunset, the fraction of inner head pixels whose luminance is
  more than 1.5x (and 2x) their converged value (a 384-sample-per-pixel render), for the
  scene's settings; the three BRDF models.  -> ``bench/results/render_fireflies.json``

    python bench/bench_render.py [--timing] [--spp 1,4,9,16] [--fireflies] [--cache DIR]

Numbers on a shared 2-core machine are noisy; CPU seconds (``process_time``, all threads)
are recorded beside wall seconds.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"

# Firefly: a pixel more than this times its converged luminance ("about 1 % of head pixels"
# at 16 samples before anti-aliasing is measured with this threshold, bench/results/
# render_fireflies.json "before").
FIREFLY_FACTOR = 1.5


def _inputs(cache):
    """(scene, {"mesh_high": Mesh, "mesh_low": Mesh, "bake": BakedMaps}) of the default scene."""
    from dermis.pipeline import api, artifacts
    from dermis.pipeline.config import load_scene
    scene = load_scene(None)
    summary = api.run(scene, cache=cache, until="bake", export=False)
    got = {}
    for rep in summary.nodes:
        if rep.id in ("mesh_high", "mesh_low", "bake"):
            got[rep.id] = artifacts.load(rep.path)
    return scene, got


def _models(scene):
    """name -> (Model, its parameters, its base's parameters, its base) of the scene's three
    BRDF models, built as the render stage builds them (``Model.scene_params``)."""
    from dermis.pipeline.registry import model
    out = {}
    for name in ("lafortune", "hk93", "asperity"):
        m = model(name)
        base = scene.render.asperity_base if m.bases else None
        config = {"optics": scene.optics.to_dict(), "asperity_base": base}
        out[name] = (m, m.scene_params(config, None),
                     m.base(base).scene_params(config, None) if base else None, base)
    return out


def _shade(mesh, samples, pb, cam, env, **kw):
    from dermis.rendering.options import RenderOptions
    from dermis.rendering.shade import render
    m, p, bp, base = pb
    return render(mesh, [], m, p, cam,
                  RenderOptions(samples=samples, base=base, base_params=bp, **kw), cl_env=env)


def _lum(img):
    return np.asarray(img, np.float64) @ np.array([0.2126, 0.7152, 0.0722])


def timing(scene, got, env, spp: int) -> dict:
    from dermis.lighting.visibility import Visibility
    from dermis.rendering.cast import cast
    from dermis.rendering.options import RenderOptions
    cam = scene.camera
    out = {}
    for mesh_node, extra in (("mesh_high", {}),
                             ("mesh_low", {"maps": got["bake"], "bump": "sharp"})):
        mesh = got[mesh_node]
        t = time.perf_counter()
        vis = Visibility(mesh.vertices, mesh.faces)
        rec = {"triangles": int(len(mesh.faces)), "scene_build_s": time.perf_counter() - t,
               "lights": {}}
        for label, lights in scene.light_groups():
            t, c = time.perf_counter(), time.process_time()
            s = cast(mesh, lights, cam, RenderOptions(spp=spp, seed=0, visibility=vis), cl_env=env)
            row = {"visibility_s": time.perf_counter() - t, "visibility_cpu_s": time.process_time() - c,
                   "visibility_parts": s.info["timings"], "hits": s.info["hits"],
                   "shadow_rays": s.info["shadow_rays"],
                   "unoccluded_samples": s.info["unoccluded_samples"], "models": {}}
            for model, pb in _models(scene).items():
                t, c = time.perf_counter(), time.process_time()
                r = _shade(mesh, s, pb, cam, env, **extra)
                row["models"][model] = {"seconds": time.perf_counter() - t,
                                        "cpu_seconds": time.process_time() - c,
                                        "surface_s": r.timings["surface"],
                                        "shading_s": r.timings["shading"],
                                        "kernel_seconds": r.timings["kernel_seconds"]}
            rec["lights"][label] = row
            print(f"  {mesh_node:9s} {label:20s} visibility {row['visibility_s']:5.2f} s  "
                  + "  ".join(f"{m} {v['seconds']:.2f}" for m, v in row["models"].items()))
        out[mesh_node] = rec
    return out


def spp_sweep(scene, got, env, values) -> dict:
    from dermis.lighting.visibility import Visibility
    from dermis.rendering.cast import cast
    from dermis.rendering.options import RenderOptions
    cam, mesh = scene.camera, got["mesh_high"]
    vis = Visibility(mesh.vertices, mesh.faces)
    pb = _models(scene)["lafortune"]
    groups = dict(scene.light_groups())
    out = {}
    for label in ("point", "sunset"):
        lights = groups[label]
        ref = _shade(mesh, cast(mesh, lights, cam, RenderOptions(spp=64, seed=99, visibility=vis),
                                cl_env=env), pb, cam, env).linear
        head = _lum(ref) > 0
        rows = {}
        for spp in values:
            t, c = time.perf_counter(), time.process_time()
            s = cast(mesh, lights, cam, RenderOptions(spp=spp, seed=1, visibility=vis), cl_env=env)
            img = _shade(mesh, s, pb, cam, env).linear
            secs, cpu = time.perf_counter() - t, time.process_time() - c
            d = (img - ref)[head]
            rows[spp] = {"seconds": secs, "cpu_seconds": cpu,
                         "rel_rmse_vs_spp64": float(np.sqrt((d ** 2).mean() / (ref[head] ** 2).mean())),
                         "unoccluded_samples": s.info["unoccluded_samples"]}
            print(f"  {label:8s} spp {spp:3d}: {secs:5.2f} s, relative RMSE vs spp 64 "
                  f"{rows[spp]['rel_rmse_vs_spp64']:.4f}")
        out[label] = rows
    return out


def fireflies(scene, got, env, passes: int = 6) -> dict:
    from scipy.ndimage import binary_erosion
    from dermis.lighting.visibility import Visibility
    from dermis.rendering.cast import cast
    from dermis.rendering.options import LightSampling, RenderOptions
    cam, mesh = scene.camera, got["mesh_high"]
    vis = Visibility(mesh.vertices, mesh.faces)
    lights = dict(scene.light_groups())["sunset"]
    models = _models(scene)
    acc = {m: 0.0 for m in models}
    for k in range(passes):          # converged: passes x 64 light samples per pixel
        s = cast(mesh, lights, cam, RenderOptions(spp=4, seed=5000 + k, visibility=vis,
                                                  sampling=LightSampling(shadow_samples=64)),
                 cl_env=env)
        for m, pb in models.items():
            acc[m] = acc[m] + _shade(mesh, s, pb, cam, env).linear.astype(np.float64)
    s = cast(mesh, lights, cam, RenderOptions(spp=scene.render.spp, seed=scene.mesh.seed,
                                              visibility=vis), cl_env=env)
    out = {"reference_samples_per_pixel": 64 * passes, "spp": scene.render.spp,
           "light_samples_per_pixel": lights[0].samples, "models": {}}
    for m, pb in models.items():
        ref = _lum(acc[m] / passes)
        img = _lum(_shade(mesh, s, pb, cam, env).linear)
        inner = binary_erosion(ref > 0)
        sel = inner & (ref > 0.01 * np.percentile(ref[inner], 99))
        out["models"][m] = {f">{f}x": float(np.mean(img[sel] > f * ref[sel]))
                            for f in (FIREFLY_FACTOR, 2.0)}
        out["models"][m]["pixels"] = int(sel.sum())
        print(f"  {m:10s} fireflies (> {FIREFLY_FACTOR}x converged): "
              f"{out['models'][m][f'>{FIREFLY_FACTOR}x']:.4%}")
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--timing", action="store_true")
    ap.add_argument("--spp", default=None, help="comma-separated spp values to sweep")
    ap.add_argument("--fireflies", action="store_true")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--device", default=None)
    args = ap.parse_args(argv)
    from dermis.pipeline.cl import get_env
    env = get_env(args.device)
    scene, got = _inputs(args.cache)
    meta = {"machine": platform.processor() or platform.machine(), "device": env.description,
            "size": [scene.camera.width, scene.camera.height], "scene": scene.path,
            "note": "shared 2-core machine: noisy"}
    RESULTS.mkdir(parents=True, exist_ok=True)
    results = {}
    if args.timing or not (args.spp or args.fireflies):
        results["timing"] = {**meta, "spp": scene.render.spp,
                             "meshes": timing(scene, got, env, scene.render.spp)}
        (RESULTS / "render.json").write_text(json.dumps(results["timing"], indent=1))
    if args.spp:
        values = [int(v) for v in args.spp.split(",")]
        results["spp"] = {**meta, "lights": spp_sweep(scene, got, env, values)}
        (RESULTS / "render_spp.json").write_text(json.dumps(results["spp"], indent=1))
    if args.fireflies:
        results["fireflies"] = {**meta, **fireflies(scene, got, env)}
        (RESULTS / "render_fireflies.json").write_text(json.dumps(results["fireflies"], indent=1))
    return results


if __name__ == "__main__":
    main()
