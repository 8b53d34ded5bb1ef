"""Benchmark Blender Cycles' skin models: seconds per image at equal noise, the samples that
took, the noise reached, and the matched mapping's fitted inputs per skin preset.

Runs the default scene (packaged scan, high mesh, the four lighting conditions) with only
the Cycles models and no reference into a cache (``--size`` pixels square, default 400,
whose reference blocks are 4 x 4 camera pixels), reads every Cycles image and slab node
back, and fits the matched inputs of every optics preset on the slab curves:

* ``bench/results/cycles.json``: per image (model, mapping, lighting) the wall seconds (the
  Blender process, its start and scene build included), render seconds, samples per pixel,
  noise reached on reference-pixel blocks and the inputs Cycles got; per method the slab
  curves (Rd_e(b), m(b)) and their cost; per preset and method the matched and native
  inputs.

    python3 bench/bench_cycles.py [--cache DIR] [--size 400] [--lights L ...] [--no-run]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_reference import newest  # noqa: E402  (bench/ is on sys.path when run as a script)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cache", default=str(REPO / ".dermis-cache-bench-cycles"))
    ap.add_argument("--size", type=int, default=400)
    ap.add_argument("--lights", nargs="*", default=None,
                    help="lighting conditions (default: the scene's four)")
    ap.add_argument("--no-run", action="store_true")
    args = ap.parse_args(argv)
    from dermis.cycles import mapping
    from dermis.optics.layer_profiles import build_profiles
    from dermis.optics.layers import PRESETS
    from dermis.pipeline.api import load_scene, run
    from dermis.pipeline.config import default_scene_path
    from dermis.pipeline.plan import build_graph
    models = ["cycles_burley", "cycles_random_walk", "cycles_random_walk_skin"]
    scene = load_scene(default_scene_path(), overrides={
        "render": {"models": models, "geometries": ["high"],
                   **({"lights": args.lights} if args.lights else {})},
        "camera": {"width": args.size, "height": args.size},
        "reference": {"enabled": False}, "output": {"previews": False}})
    cache = Path(args.cache)
    t0 = time.perf_counter()
    if not args.no_run:
        run(scene, cache=cache, export=False)
    wall = time.perf_counter() - t0
    nodes, _ = build_graph(scene)
    images, slabs = [], {}
    for nid, node in nodes.items():
        if node.stage != "cycles":
            continue
        art = newest(cache, nid)
        if art is None:
            continue
        if node.params["kind"] == "slab":
            slabs[node.params["method"]] = {
                "grid": art.grid.tolist(), "rd_e": art.rd_e[:, 0].tolist(),
                "mean_radius": art.mean_radius[:, 0].tolist(),
                "specular": art.specular.tolist(), **art.info}
            continue
        info = art.info
        images.append({"image": info["model"], "method": info["method"],
                       "mapping": info["mapping"], "light": info["light"],
                       "seconds": art.timings["total"], "render_seconds": art.timings["render"],
                       "spp": info["spp"], "noise": info["noise"],
                       "noise_block": info["noise_block"],
                       "target_noise": info["target_noise"], "inputs": info["inputs"]})
    fits = {}
    for preset, stack in PRESETS.items():
        prof = build_profiles(stack)
        rd, r_skin = prof.Rd, mapping.mean_exit_radius(prof)
        rec = {"Rd_multipole": rd.tolist(), "mean_exit_radius_mm": r_skin.tolist(),
               "native": mapping.native_inputs(stack, rd, 0.3)}
        for method, s in slabs.items():
            from dermis.pipeline.artifacts import SlabCurves
            import numpy as np
            curves = SlabCurves(np.array(s["grid"]), np.repeat(np.array(s["rd_e"])[:, None], 3, 1),
                                np.repeat(np.array(s["mean_radius"])[:, None], 3, 1),
                                np.array(s["specular"]))
            try:
                rec[f"matched_{method}"] = mapping.matched_inputs(stack, rd, r_skin, curves, 0.3)
            except ValueError as exc:
                rec[f"matched_{method}"] = {"error": str(exc)}
        fits[preset] = rec
    out = {"scene": "default (packaged scan), high mesh, Cycles models only",
           "size": args.size, "lights": args.lights or "all", "run_wall_seconds": wall, "cores": 2,
           "images": sorted(images, key=lambda r: (r["image"], r["light"])),
           "slab_curves": slabs, "fits_multipole_targets": fits,
           "note": "fits here target the multipole profile (no Monte Carlo table); the run "
                   "targets the Monte Carlo profile (stages/cycles.py PROFILE)"}
    path = REPO / "bench" / "results" / "cycles.json"
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "fits_multipole_targets"},
                     indent=1)[:4000])
    return 0


if __name__ == "__main__":
    sys.exit(main())
