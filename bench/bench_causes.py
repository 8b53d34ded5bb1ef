"""Benchmark the reference's controlled variants: interreflection gain and boundary effect.

On the default scene (packaged scan, high mesh, reference 100x100):

1. the ``causes`` stage at its default ``[causes]`` budget, one node per lighting condition
   (``dermis run --until causes`` with ``[reference] enabled``): its seconds and effects;
2. the area light with a long budget (``--diffuse-spp``, ``--rough-spp``, ``--smooth-spp``
   per half-buffer), calling :mod:`dermis.groundtruth.variants` directly: the
   interreflection gain and the smooth-vs-rough boundary effect per face region with their
   standard errors, the flat slabs' Rd and each render's seconds per sample.

Writes ``bench/results/causes.json``.

    python3 bench/bench_causes.py [--cache DIR] [--lights a,b] [--no-default] [--no-long]

CPU-heavy: the long area run takes ~15 min on 2 cores (most of it the smooth boundary).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _regions(regions: dict) -> dict:
    keep = ("pixels", "lit_pixels", "effect_lum", "se_lum", "effect_rgb", "se_rgb")
    return {n: {k: r[k] for k in keep if k in r} for n, r in regions.items()}


def default_budget(scene_path, cache: Path, lights) -> dict:
    """The causes stage at its default budget, one lighting condition at a time (serial)."""
    from dermis.pipeline import artifacts
    from dermis.pipeline.api import run
    from dermis.pipeline.config import load_scene
    out = {}
    for label in lights:
        scene = load_scene(scene_path, overrides={"reference": {"enabled": True,
                                                                "lights": [label]},
                                                  "output": {"previews": False}})
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        summary = run(scene, cache=cache, until="causes", export=False, jobs=1,
                      force=("causes",))
        wall = time.perf_counter() - t0
        rep = next(n for n in summary.nodes if n.id == f"causes-{label}")
        art = artifacts.load(rep.path)
        meta = json.loads((Path(rep.path) / "meta.json").read_text())
        out[label] = {"wall_seconds": wall, "timings": meta.get("measurements", {}).get(
            "timings", {}), "loadavg_before": load0,
            "causes": art.info["causes"], "boundary": art.info.get("boundary")}
        print(label, f"{wall:.1f} s", json.dumps({c: {r: round(v.get("effect_lum") or 0, 4)
                                                      for r, v in d.items()}
                                                  for c, d in art.info["causes"].items()}),
              flush=True)
    return out


def _face_noise(h, hit) -> float:
    """Relative standard deviation of the whole-face luminance mean of one sample per pixel."""
    import numpy as np
    from dermis.rendering.color import LUMINANCE
    m, d = h.mean[hit] @ LUMINANCE, h.half_diff[hit] @ LUMINANCE
    return float(np.sqrt((d ** 2).sum()) / m.sum() * np.sqrt(2 * h.spp))


def long_area(scene_path, cache: Path, args) -> dict:
    """The area light's variants at a long budget."""
    from dermis.pipeline import artifacts
    from dermis.pipeline.api import run
    from dermis.pipeline.config import load_scene
    from dermis.groundtruth.mitsuba import load_mitsuba
    from dermis.groundtruth.variants import (VariantOptions, boundary_variant,
                                             interreflection_variant)
    from dermis.optics.layers import LayerStack
    scene = load_scene(scene_path)
    summary = run(scene, cache=cache, until="mesh_high", export=False)
    mesh = artifacts.load(next(n for n in summary.nodes if n.id == "mesh_high").path)
    lights = dict(scene.light_groups())["area"]
    r = scene.reference
    mi = load_mitsuba(r.variant)
    opts = VariantOptions(width=r.width, height=r.height, seed=scene.causes.seed,
                          diffuse_spp=args.diffuse_spp, rough_spp=args.rough_spp,
                          smooth_spp=args.smooth_spp, roughness=r.roughness,
                          smooth_roughness=scene.causes.smooth_roughness,
                          slab_samples=args.slab_samples, max_depth=r.max_depth,
                          rr_depth=r.rr_depth, env_clamp=r.env_clamp)
    load0 = os.getloadavg()
    inter = interreflection_variant(mi, mesh, scene.camera, lights, opts)
    print("interreflection", f"{inter['seconds']:.1f} s",
          {k: (round(v["effect_lum"], 4), round(v["se_lum"] or 0, 4))
           for k, v in inter["regions"].items()}, flush=True)
    b = boundary_variant(mi, mesh, LayerStack.from_dict(scene.optics.to_dict()), scene.camera,
                         lights, opts, labels=(inter["hit"], inter["labels"]))
    print("boundary", f"{b['seconds']:.1f} s",
          {k: (round(v["effect_lum"] or 0, 4), round(v["se_lum"] or 0, 4))
           for k, v in b["regions"].items()}, flush=True)
    slabs = {k: {"Rd": s.Rd.tolist(), "Rd_stderr": s.Rd_stderr.tolist(),
                 "specular": s.specular.tolist(), "Rd_entered": s.Rd_entered.tolist(),
                 "samples": s.samples, "seconds": s.seconds} for k, s in b["slabs"].items()}
    return {"light": "area", "width": r.width, "height": r.height,
            "spp_per_half": {"diffuse": args.diffuse_spp, "rough": args.rough_spp,
                             "smooth": args.smooth_spp},
            "alphas": b["alphas"], "normalised": b["normalised"],
            "interreflection": _regions(inter["regions"]),
            "boundary": _regions(b["regions"]), "slabs": slabs,
            "seconds": {"interreflection": inter["seconds"], "boundary": b["seconds"]},
            "seconds_per_spp": {"diffuse": (inter["direct"].seconds + inter["all"].seconds)
                                / (4 * args.diffuse_spp),
                                "rough": b["rough"].seconds / (2 * args.rough_spp),
                                "smooth": b["smooth"].seconds / (2 * args.smooth_spp)},
            "noise_per_sample": {k: _face_noise(b[k], inter["hit"]) for k in ("rough",
                                                                               "smooth")},
            "loadavg_before": load0, "loadavg_after": os.getloadavg()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/tmp/dermis-bench-causes")
    ap.add_argument("--scene", default=str(REPO / "scenes" / "default.toml"))
    ap.add_argument("--lights", default="point,area,dir_left+dir_right,sunset")
    ap.add_argument("--diffuse-spp", type=int, default=256)
    ap.add_argument("--rough-spp", type=int, default=64)
    ap.add_argument("--smooth-spp", type=int, default=512)
    ap.add_argument("--slab-samples", type=int, default=1 << 18)
    ap.add_argument("--no-default", action="store_true", help="skip the default-budget runs")
    ap.add_argument("--no-long", action="store_true", help="skip the long area run")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "causes.json"))
    ap.add_argument("--long-key", default="area_long",
                    help="where the long run's results go in the JSON")
    args = ap.parse_args(argv)
    cache = Path(args.cache)
    out = Path(args.out)
    res = json.loads(out.read_text()) if out.is_file() else {}
    res.update({"scene": "scenes/default.toml", "cpus": os.cpu_count()})
    if not args.no_default:
        res.setdefault("default_budget", {}).update(
            default_budget(args.scene, cache, args.lights.split(",")))
        out.write_text(json.dumps(res, indent=1))
    if not args.no_long:
        res[args.long_key] = long_area(args.scene, cache, args)
        out.write_text(json.dumps(res, indent=1))
    print("wrote", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
