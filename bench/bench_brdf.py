"""Throughput of the three local reflectance models' eval kernels (800 x 800 direction pairs).

Prints BRDF evaluations per second per model, from the OpenCL profiling events (kernel time
only; buffers are uploaded once) and from wall time around enqueue+finish, and writes JSON.

    python bench/bench_brdf.py [--out bench/results/brdf.json] [--repeats 7] [--device SPEC]
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import pyopencl as cl

from dermis.pipeline.cl import event_seconds, get_env, to_device
from dermis.models import asperity, hk93, lafortune

SIDE = 800                      # thesis images are 800 x 800 (docs/science.md §7, the thesis's timings)


def _pairs(rng, n):
    def hemi():
        z = rng.random(n)
        phi = 2 * np.pi * rng.random(n)
        r = np.sqrt(1 - z * z)
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1).astype(np.float32)
    return hemi(), hemi()


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench/results/brdf.json")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--device", default=None, help="OpenCL device spec (see pipeline.cl)")
    args = ap.parse_args(argv)

    env = get_env(args.device)
    n = SIDE * SIDE
    rng = np.random.default_rng(800)
    wo, wi = _pairs(rng, n)
    albedo = rng.random((n, 3)).astype(np.float32)
    out_buf = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, n * 3 * 4)
    results = {}
    for model in (lafortune.MODEL, hk93.MODEL, asperity.MODEL):
        t0 = time.perf_counter()
        prg = env.program(model.kernel)
        build_s = time.perf_counter() - t0
        kernel = cl.Kernel(prg, f"{model.name}_eval")
        arrays = [wo, wi] + ([albedo] if model.albedo else []) + [model.params().pack()]
        bufs = [to_device(env, a) for a in arrays]
        kernel.set_args(*bufs, out_buf, np.int32(n))
        cl.enqueue_nd_range_kernel(env.queue, kernel, (n,), None).wait()      # warm-up
        dev, wall = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            ev = cl.enqueue_nd_range_kernel(env.queue, kernel, (n,), None)
            ev.wait()
            wall.append(time.perf_counter() - t0)
            dev.append(event_seconds(ev))
        dev_s, wall_s = statistics.median(dev), statistics.median(wall)
        results[model.name] = {
            "pairs": n, "kernel_s_median": dev_s, "wall_s_median": wall_s,
            "evals_per_s_kernel": n / dev_s, "evals_per_s_wall": n / wall_s,
            "build_or_cache_s": build_s, "repeats": args.repeats,
        }
        print(f"{model.name:10s} {n / dev_s / 1e6:8.1f} M eval/s (kernel {dev_s * 1e3:7.2f} ms, "
              f"wall {wall_s * 1e3:7.2f} ms for {SIDE}x{SIDE} pairs)")
    report = {"device": env.description, "host": platform.node(),
              "cpu_count_note": "PoCL CPU uses all host cores", "models": results}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    print(f"wrote {out}")
    return report


if __name__ == "__main__":
    main()
