"""Benchmark Blender Cycles' skin models: seconds per image at equal noise, the samples that
took, the noise reached, and the matched mapping's fitted inputs per skin preset.

Runs the default scene's Cycles part (packaged scan, high mesh, the four lighting
conditions of the main camera, both mappings: ``dermis run --until cycles``, no reference)
into a cache (cold unless ``--cache`` holds it: the meshes and the Monte Carlo profile are
seeded from ``--seed-cache`` when given, so only the Cycles nodes are timed), reads every
Cycles image and slab node back, and fits the matched inputs of every optics preset on the
slab curves:

* ``bench/results/cycles.json``: the run's wall and CPU seconds (this process and its
  Blender processes, ``os.getloadavg`` before and after: the machine may be shared); per
  image (model, mapping, lighting) the wall and CPU seconds of its job (a serving Blender
  process's start counted in its first job), render seconds, samples per pixel, noise
  reached on ``[cycles] noise_block`` blocks and the inputs Cycles got; per method the slab
  curves (Rd_e(b), m(b)) and their cost; per preset and method the matched and native
  inputs.

    python3 bench/bench_cycles.py [--cache DIR] [--seed-cache DIR] [--size 800]
                                  [--cycles-size reference|camera] [--lights L ...] [--no-run]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_reference import newest  # noqa: E402  (bench/ is on sys.path when run as a script)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cache", default=str(REPO / ".dermis-cache-bench-cycles"))
    ap.add_argument("--seed-cache", default=None,
                    help="a cache whose mesh and profile nodes are copied in first")
    ap.add_argument("--size", type=int, default=800, help="camera pixels (square)")
    ap.add_argument("--cycles-size", default="reference", choices=("reference", "camera"))
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
        "cycles": {"size": args.cycles_size},
        "reference": {"enabled": False}, "output": {"previews": False}})
    cache = Path(args.cache)
    if args.seed_cache and not args.no_run:
        seed = Path(args.seed_cache)
        (cache / "index").mkdir(parents=True, exist_ok=True)
        for n in ("mesh_source", "mesh_high", "profiles-monte_carlo"):
            if (seed / n).is_dir() and not (cache / n).exists():
                shutil.copytree(seed / n, cache / n)
                shutil.copy(seed / "index" / f"{n}.json", cache / "index" / f"{n}.json")
    from dermis.cycles.job import close_servers
    load0 = os.getloadavg()
    t0, c0 = time.perf_counter(), time.process_time()
    if not args.no_run:
        run(scene, cache=cache, export=False, until="cycles")
        close_servers()     # its CPU time counts once it has been waited for
    wall, cpu_self = time.perf_counter() - t0, time.process_time() - c0
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    load1 = os.getloadavg()
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
                       "cpu_seconds": art.timings.get("cpu"),
                       "startup_seconds": art.timings.get("startup"),
                       "scene_build_seconds": art.timings.get("scene_build"),
                       "rendered_size": info.get("rendered_size"),
                       "mesh_reused": info.get("mesh_reused"),
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
    out = {"scene": "default (packaged scan), high mesh, Cycles models only "
                    "(dermis run --until cycles)",
           "size": args.size, "cycles_size": args.cycles_size, "lights": args.lights or "all",
           "cores": os.cpu_count(),
           "run": None if args.no_run else {
               "wall_seconds": wall, "cpu_seconds_self": cpu_self,
               "cpu_seconds_children": ch.ru_utime + ch.ru_stime,
               "cpu_seconds": cpu_self + ch.ru_utime + ch.ru_stime,
               "max_rss_children_mb": ch.ru_maxrss / 1024.0,
               "loadavg_before": load0, "loadavg_after": load1},
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
