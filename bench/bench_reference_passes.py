"""Benchmark the reference's progressive passes: noise against time per lighting condition.

Renders the default scene's references (high mesh, 100 x 100, every lighting condition) with
no time budget until every face region's luminance mean reaches ``--target`` relative standard
error (or ``--max-spp`` per half), and records per pass the seconds, the paths and the worst
region's relative standard error, and per light:

* the time to reach 2 % and 1 % (the report's targets) from the pass log;
* the gain of the adaptive passes: the paths uniform sampling of every head pixel would need
  for the same worst-region error (every pixel at the samples the worst region needed,
  n_r (s_r / target)^2 scaled from the uniform passes) against the paths spent;
* the wall time on 1, 10 and 100 two-core machines (``wall_estimate``, from each task's
  logged seconds: the passes are sequential, a pass's tasks spread over the workers);
* the gain of tracing only the head's pixels: a whole-frame ``mi.render`` pass timed against
  the same samples traced at the head's pixels (``--frame-check``, ``frame_check``).

    python3 bench/bench_reference_passes.py [--cache DIR] [--target 0.01] [--max-spp 4096]

Writes ``bench/results/reference_passes.json``.  CPU-heavy: minutes per lighting condition.
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


def time_to(log: list, target: float) -> float | None:
    """Seconds of rendering until the worst region first reached ``target``."""
    t = 0.0
    for p in log:
        t += p["seconds"]
        if p["worst_rel_se"] <= target:
            return t
    return None


def wall_estimate(log: list, machines: int, scene_load_s: float) -> float | None:
    """Wall seconds of the passes on ``machines`` workers of this machine's speed: the passes
    run one after another (each decides the next), a pass's tasks spread longest first
    (LPT) over the workers, plus one scene load per worker; None without task times."""
    import heapq
    if not log or any("task_seconds" not in p for p in log):
        return None
    total = scene_load_s
    for p in log:
        loads = [0.0] * min(machines, max(len(p["task_seconds"]), 1))
        for t in sorted(p["task_seconds"], reverse=True):
            heapq.heapreplace(loads, loads[0] + t)     # the least loaded worker takes it
        total += max(loads)
    return total


def frame_check(cache: str, spp: int = 8, repeats: int = 3) -> dict:
    """Whole-frame ``mi.render`` against the same samples traced at the head's pixels only
    (the default scene's point light, 100 x 100): seconds per head-pixel sample, each the
    median of ``repeats``."""
    import statistics
    import numpy as np
    from dermis.groundtruth import mitsuba
    from dermis.groundtruth.passes import pixel_hits
    from dermis.groundtruth.pixel_tracing import trace_pixels
    from dermis.groundtruth.scene_export import HeadSceneOptions, head_scene, release
    from dermis.pipeline import artifacts
    from dermis.pipeline.config import load_scene
    scene = load_scene(None)
    mesh_dir = max((d for d in (Path(cache) / "mesh_high").glob("*") if (d / "meta.json").is_file()),
                   key=lambda d: d.stat().st_mtime)
    mesh = artifacts.load(mesh_dir)
    mi = mitsuba.load_mitsuba("auto")
    head = head_scene(mi, mesh, scene.optics, scene.camera, dict(scene.light_groups())["point"],
                      width=100, height=100, options=HeadSceneOptions(roughness=0.3))
    try:
        hit, _ = pixel_hits(mi, head.scene, width=100, height=100)
        ys, xs = np.nonzero(hit)
        px = np.stack([xs, ys], axis=1)
        frame, pixels = [], []
        for k in range(repeats):
            t0 = time.perf_counter()
            np.asarray(mi.render(head.scene, spp=spp, seed=k))
            frame.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            trace_pixels(mi, head.scene, px, spp, 100 + k, width=100, height=100)
            pixels.append(time.perf_counter() - t0)
    finally:
        release(head)
    n = int(hit.sum()) * spp
    f, p = statistics.median(frame), statistics.median(pixels)
    return {"spp": spp, "head_pixels": int(hit.sum()), "frame_pixels": 10000,
            "frame_seconds": f, "head_only_seconds": p, "frame_us_per_head_sample": 1e6 * f / n,
            "head_only_us_per_sample": 1e6 * p / n, "head_only_speedup": f / p,
            "loadavg": os.getloadavg()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/tmp/dermis-bench-reference-passes")
    ap.add_argument("--target", type=float, default=0.01)
    ap.add_argument("--max-spp", type=int, default=4096)
    ap.add_argument("--required", type=float, default=0.0,
                    help="[reference] required_rel_se (0: the passes aim at --target throughout, "
                         "as measured in reference_passes.json)")
    ap.add_argument("--lights", nargs="*", default=None)
    ap.add_argument("--frame-check", action="store_true",
                    help="also time a whole-frame render against the head's pixels alone")
    ap.add_argument("--no-run", action="store_true",
                    help="analyse the newest reference entries the cache holds")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "reference_passes.json"))
    args = ap.parse_args(argv)

    from dermis.pipeline import api, artifacts
    from dermis.pipeline.config import load_scene
    over = {"render": {"geometries": ["high"], "models": []}, "output": {"previews": False},
            "reference": {"budget_s": 0, "target_rel_se": args.target,
                          "required_rel_se": args.required, "max_spp": args.max_spp}}
    if args.lights:
        over["reference"]["lights"] = args.lights
    scene = load_scene(None, overrides=over)
    load0, t0, c0 = os.getloadavg(), time.perf_counter(), time.process_time()
    if args.no_run:
        paths = [max((d for d in (Path(args.cache) / f"reference-{label}").glob("*")
                      if (d / "meta.json").is_file()), key=lambda d: d.stat().st_mtime)
                 for label, _ in scene.light_groups()
                 if (Path(args.cache) / f"reference-{label}").is_dir()]
    else:
        summary = api.run(scene, cache=args.cache, export=False, until="reference")
        paths = [Path(rep.path) for rep in summary.nodes if rep.stage == "reference"]
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    out = {"scene": "scenes/default.toml (high mesh, reference only)", "target": args.target,
           "max_spp": args.max_spp, "wall_seconds": wall, "cpu_seconds": cpu,
           "loadavg_before": load0, "loadavg_after": os.getloadavg(), "cpus": os.cpu_count(),
           "lights": {}}
    from dermis.pipeline.graph import restore_measurements
    for path in paths:
        meta = json.loads((path / "meta.json").read_text())
        ref = restore_measurements(artifacts.load(path), meta.get("measurements", {}))
        info = ref.info
        log = info["pass_log"]
        uniform = [p for p in log if p.get("uniform")]
        hit = int(info["hit_pixels"])
        # uniform sampling to the same worst-region error: the regions' errors after the
        # uniform passes, scaled as 1 / sqrt(samples)
        last_u = uniform[-1] if uniform else None
        paths_uniform = None
        if last_u:
            n_u = last_u["spp_min"]           # both halves
            k = (last_u["worst_rel_se"] / max(max(info["region_rel_se"].values()), 1e-12)) ** 2
            paths_uniform = hit * n_u * k
        rec = {"passes": info["passes"], "stopped": info["stopped"],
               "seconds": ref.timings.get("render"), "scene_load": ref.timings.get("scene_load"),
               "slab_seconds": ref.timings.get("slab"), "paths": info["paths"],
               "hit_pixels": hit, "spp_mean": info["spp"], "spp_min": info["spp_min"],
               "spp_max": info["spp_max"], "region_rel_se": info["region_rel_se"],
               "noise": {f: v["rel"] for f, v in info["noise"].items()},
               "seconds_to_2pct": time_to(log, 0.02), "seconds_to_1pct": time_to(log, 0.01),
               "paths_uniform_same_worst_error": paths_uniform,
               "adaptive_gain": (paths_uniform / info["paths"]) if paths_uniform else None,
               "seconds_per_path": ref.timings.get("render") / max(info["paths"], 1),
               "tasks": sum(len(p.get("task_seconds", [])) for p in log),
               "wall_estimate_s": {str(n): wall_estimate(log, n, ref.timings.get("scene_load", 0.0))
                                   for n in (1, 10, 100)},
               "pass_log": log}
        out["lights"][info["light"]] = rec
        print(f"{info['light']:>20s}: {rec['seconds']:.0f} s, {info['passes']} passes, "
              f"stopped {info['stopped']}, worst {max(info['region_rel_se'].values()):.4f}, "
              f"to 2 % {rec['seconds_to_2pct']}, to 1 % {rec['seconds_to_1pct']}, "
              f"adaptive gain {rec['adaptive_gain']}", flush=True)
    if args.frame_check:
        out["frame_check"] = frame_check(args.cache)
        print("frame check:", out["frame_check"])
    Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True, default=float))
    print(f"wall {wall:.0f} s, cpu {cpu:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
