"""Benchmark: a sweep serial vs on Dask LocalClusters of 1 worker (all cores, or one) and 2
workers (one core each: pipeline/distributed.py local_cluster); task statistics;
the wall time of a 1,000-point sweep on 50 machines estimated from them.

Scene: the quick scene cut to the BSSRDF and Lafortune models under the point and area lights
on the high mesh, sweeping the gather epsilon and the light samples (one knob at a time).  Each
configuration runs from an empty cache after a warm-up sweep in a throw-away cache, the Dask
ones on their own cluster (so imports, OpenCL programs and disk caches are warm for all: a
fresh worker otherwise pays them inside the timed run).  Reported: wall seconds, speed-up, task count, mean task
duration, scheduler overhead per task (wall time not explained by node work at perfect
packing), the critical path (longest dependency chain of node seconds: the serial fraction),
the serial run's CPU seconds per wall second (how many cores one process already keeps busy:
PoCL and numpy threads), and the machine load before and after each configuration.

    python3 bench/bench_sweep.py [--out bench/results/sweep_dask.json]
"""
from __future__ import annotations

import argparse
import json
import os
import re
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


SMOKE = """
[sweep]
[sweep.knobs]
"bssrdf.epsilon" = [1.0]
"""


def scene(tmp: Path, smoke: bool = False) -> Path:
    src = (REPO / "scenes" / "quick.toml").read_text()
    for a, b in ((r"^models = .*$", 'models = ["lafortune", "bssrdf"]'),
                 (r"^lights = .*$", 'lights = ["point", "area"]'),
                 (r"^geometries = .*$", 'geometries = ["high"]'),
                 (r"^width = 160$", "width = 160" if smoke else "width = 320"),
                 (r"^height = 160$", "height = 160" if smoke else "height = 320"),
                 (r"^previews = true$", "previews = false"),
                 (r'^output_dir = "out"$', f'output_dir = "{tmp / "out"}"')):
        src, n = re.subn(a, b, src, count=1, flags=re.M)
        assert n == 1, a
    path = tmp / "sweep.toml"
    path.write_text(src + (SMOKE if smoke else SWEEP))
    return path


def base_tasks(path: Path) -> int:
    """Tasks of the scene as written (what every point shares unless its knob changes it)."""
    import tomllib
    from dermis.pipeline.config import scene_from_dict
    from dermis.pipeline.graph import plan_order
    from dermis.pipeline.plan import build_graph
    from dermis.reports.sweep import IMAGE_STAGES
    table = tomllib.loads(path.read_text())
    table.pop("sweep")
    nodes, _ = build_graph(scene_from_dict(table, where=str(path)))
    return len(plan_order(nodes, [n for n, v in nodes.items() if v.stage in IMAGE_STAGES]))


def main() -> None:
    from dermis.pipeline.distributed import local_cluster
    from dermis.reports.sweep import run_sweep

    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "sweep_dask.json"))
    ap.add_argument("--smoke", action="store_true", help="one point, 160x160 (checks the script)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_sweep_"))
    path = scene(tmp, args.smoke)
    load0 = os.getloadavg()
    run_sweep(path, cache=tmp / "warm", out_dir=tmp / "warm_res")          # warm-up
    res = {}
    cores = os.cpu_count() or 1
    # (label, workers, threads per worker): the 1-worker cluster with all cores is the serial
    # run's equal; with one core it is the unit the 2-worker cluster (one core each) scales
    configs = (("serial", 1, cores), ("dask_1_worker", 1, cores),
               ("dask_1_worker_1_thread", 1, 1), ("dask_2_workers", 2, max(1, cores // 2)))
    for label, workers, threads in configs:
        cache = tmp / f"cache_{label}"
        before = os.getloadavg()
        cluster, startup = None, 0.0
        if label != "serial":   # started before the clock (run_sweep --workers 1 is serial)
            t0 = time.perf_counter()
            cluster = local_cluster(workers, threads)
            startup = time.perf_counter() - t0
            # warm the workers as the serial run is warm (imports, OpenCL programs, Embree):
            # the same sweep into a throw-away cache, before the clock
            run_sweep(path, cache=tmp / f"warm_{label}", out_dir=tmp / f"warm_res_{label}",
                      workers=workers, scheduler=cluster.scheduler_address)
            shutil.rmtree(tmp / f"warm_{label}", ignore_errors=True)
        t0 = time.perf_counter()
        r = run_sweep(path, cache=cache, out_dir=tmp / f"res_{label}", workers=workers,
                      scheduler=cluster.scheduler_address if cluster else None)
        wall = time.perf_counter() - t0
        if cluster is not None:
            cluster.close()
        res[label] = {"wall_seconds": wall, **r["distributed"], "workers": workers,
                      "threads_per_worker": threads,
                      "cluster_startup_seconds": startup, "points": len(r["points"]),
                      "loadavg_before": before, "loadavg_after": os.getloadavg()}
        print(label, json.dumps(res[label]), flush=True)
        shutil.rmtree(cache)
    one, dask1, two = res["serial"], res["dask_1_worker"], res["dask_2_workers"]
    dask1t = res["dask_1_worker_1_thread"]
    # A 1,000-point sweep of this kind: the tasks every point shares run once (their critical
    # path), then per point the tasks its knob changes, spread over M machines x C workers at
    # the measured mean task time plus the measured per-task scheduler overhead.
    points = one["points"]
    shared = base_tasks(path)
    tasks_per_point = (one["tasks"] - shared) / points
    mean_task = one["mean_task_seconds"]
    # Dask's own cost per task: the 1-worker cluster runs the same tasks one at a time as the
    # serial run does, plus submission, scheduling, pickling and the worker round trip
    overhead = max(dask1["wall_seconds"] - one["wall_seconds"], 0.0) / one["tasks"]
    machines, cores = 50, 2   # the estimate's machines: 2 cores each, like this one
    est = one["critical_path_seconds"] + 1000 * tasks_per_point * (mean_task + overhead) / (
        machines * cores)
    out = {"scene": "quick (lafortune + bssrdf, point + area, high, 320x320), "
                    "bssrdf.epsilon x3 + lights.samples x3",
           "serial": one, "dask_1_worker": dask1, "dask_1_worker_1_thread": dask1t,
           "dask_2_workers": two,
           "speedup_2_workers_vs_1_worker_1_thread": dask1t["wall_seconds"] / two["wall_seconds"],
           "speedup_2_workers_vs_serial": one["wall_seconds"] / two["wall_seconds"],
           "speedup_2_workers_vs_1_worker": dask1["wall_seconds"] / two["wall_seconds"],
           "serial_cores_busy": one["process_cpu_seconds"] / one["wall_seconds"],
           "scheduler_overhead_per_task_seconds": overhead,
           "note": "clusters started before the clock (startup listed); overhead per task = "
                   "(1-worker Dask wall - serial wall) / tasks; bound_speedup = task seconds / "
                   "max(critical path, task seconds / workers); serial_cores_busy = CPU s / wall"
                   " s of the serial process (> 1: PoCL/numpy threads already use 2 cores)",
           "estimate_1000_points_50_machines_seconds": est,
           "estimate_inputs": {"shared_tasks": shared, "tasks_per_point": tasks_per_point,
                               "mean_task_seconds": mean_task,
                               "overhead_per_task_seconds": overhead,
                               "shared_critical_path_seconds": one["critical_path_seconds"],
                               "machines": machines, "workers_per_machine": cores},
           "cpu_count": os.cpu_count(), "loadavg_start": load0, "loadavg_end": os.getloadavg()}
    print(json.dumps(out, indent=1))
    Path(args.out).write_text(json.dumps(out, indent=1))
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
