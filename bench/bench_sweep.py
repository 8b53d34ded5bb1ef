"""Benchmark: a sweep serial vs on a 2-worker Dask LocalCluster; task statistics; scaling estimate.

Scene: the quick scene cut to the BSSRDF and Lafortune models under the point and area lights
on the high mesh, sweeping the gather epsilon and the light samples (one knob at a time).  Each
configuration runs from an empty cache after a warm-up sweep in a throw-away cache (so disk and
import caches are warm for both).  Reported: wall seconds, speed-up, task count, mean task
duration, scheduler overhead per task (wall time not explained by node work at perfect
packing), and from them the wall time of a 1,000-point sweep on 50 two-core machines.

    python3 bench/bench_sweep.py [--out bench/results/sweep.json]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

SWEEP = """
[sweep]
targets = [0.01, 0.05]
[sweep.knobs]
"bssrdf.epsilon" = [1.0, 0.5, 0.25]
"lights.samples" = [4, 8, 16]
"""


def scene(tmp: Path) -> Path:
    src = (REPO / "scenes" / "quick.toml").read_text()
    for a, b in (('models = ["lafortune", "hk93", "bssrdf", "asperity"]',
                  'models = ["lafortune", "bssrdf"]'),
                 ('lights = ["point", "area", "dir_left+dir_right", "sunset"]',
                  'lights = ["point", "area"]'),
                 ('geometries = ["high", "low_bump", "low_bump_blur"]', 'geometries = ["high"]'),
                 ("width = 160", "width = 320"), ("height = 160", "height = 320"),
                 ("previews = true", "previews = false"),
                 ('output_dir = "out"', f'output_dir = "{tmp / "out"}"')):
        src = src.replace(a, b)
    path = tmp / "sweep.toml"
    path.write_text(src + SWEEP)
    return path


def main() -> None:
    from dermis.reports.sweep import run_sweep

    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "sweep.json"))
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_sweep_"))
    path = scene(tmp)
    run_sweep(path, cache=tmp / "warm", out_dir=tmp / "warm_res")          # warm-up
    res = {}
    for workers in (1, 2):
        cache = tmp / f"cache{workers}"
        t0 = time.perf_counter()
        r = run_sweep(path, cache=cache, out_dir=tmp / f"res{workers}", workers=workers)
        res[workers] = {"wall_seconds": time.perf_counter() - t0, **r["distributed"],
                        "points": len(r["points"])}
        shutil.rmtree(cache)
    one, two = res[1], res[2]
    speedup = one["wall_seconds"] / two["wall_seconds"]
    # A 1,000-point sweep of this kind: per point, the tasks the knob changes (the rest is
    # shared and runs once); on M machines x C workers, at the measured mean task time and
    # per-task scheduler overhead.
    points = one["points"]
    tasks_per_point = (one["tasks"] - one["tasks"] / (points + 1)) / points
    mean_task = one["mean_task_seconds"]
    overhead = two["overhead_per_task_seconds"]
    machines, cores = 50, 2
    est = 1000 * tasks_per_point * (mean_task + overhead) / (machines * cores)
    out = {"scene": "quick (lafortune + bssrdf, point + area, high, 320x320)",
           "serial": one, "dask_2_workers": two, "speedup_2_workers": speedup,
           "estimate_1000_points_50_machines_seconds": est,
           "estimate_inputs": {"tasks_per_point": tasks_per_point, "mean_task_seconds": mean_task,
                               "overhead_per_task_seconds": overhead, "machines": machines,
                               "workers_per_machine": cores},
           "cpu_count": os.cpu_count(), "loadavg": os.getloadavg()}
    print(json.dumps(out, indent=1))
    Path(args.out).write_text(json.dumps(out, indent=1))
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
