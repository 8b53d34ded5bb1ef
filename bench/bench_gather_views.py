"""Benchmark of the BSSRDF gather's solid-angle criterion ``[bssrdf] epsilon`` on every view
of a scene (default: scenes/default.toml, high mesh; a close-up's conditions are labelled
"<lighting>@<view>"): per lighting condition and epsilon, the full BSSRDF's exitance at all
camera samples against the brute-force gather (every point summed, no clusters) at
``--samples`` random camera samples, as relative RMSE over all channels, and the exitance's
seconds and kernel seconds (medians of ``--repeats``).

Why per view.  The gather's cluster error was measured on the main view (640k pixels of
0.37 mm); a close-up at 8 px/mm samples the surface 20x more densely, where the clusters of
a loose criterion show.

How it measures.  bench/bench_bssrdf_adaptive.py's scene variant and Runner build the inputs
(no reference); the full BSSRDF node is run once to capture its inputs, then
``subsurface.exitance.exitance`` is called directly per epsilon with the run's shared octree
and shadow edges (made by the first call, excluded from the seconds).

Usage: python bench/bench_gather_views.py [--scene FILE] [--cache DIR] [--epsilons 0.5,0.25,0.1]
       [--lights point,area@lips,...] [--samples 4000] [--repeats 3]
       [--out bench/results/gather_views.json] [--label default]
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_bssrdf_adaptive import REPO, Runner, exitance_inputs, variant
from labelled import save_labelled


def without_gathers(shared):
    """A RunCache holding ``shared``'s octrees, shadow edges, near tables and kd-trees but no
    gathers (a kept gather would be reused, not timed)."""
    from dermis.pipeline.shared import RunCache
    return RunCache(_stores={k: v for k, v in shared._stores.items()
                             if k in Runner.SHARED_KINDS})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=str(REPO / "scenes" / "default.toml"))
    ap.add_argument("--cache", default=None)
    ap.add_argument("--epsilons", default="0.5,0.25,0.1")
    ap.add_argument("--lights", default="")
    ap.add_argument("--samples", type=int, default=4000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "gather_views.json"))
    ap.add_argument("--label", default="default")
    args = ap.parse_args()
    from dermis.pipeline import api
    from dermis.subsurface.exitance import ShadingPoints, exitance
    work = Path(args.cache or tempfile.mkdtemp(prefix="bench-gather-views-"))
    work.mkdir(parents=True, exist_ok=True)
    scene = api.load_scene(variant(Path(args.scene), work / "scene.toml", False))
    api.run(scene, cache=work / "cache", export=False, jobs=1)
    runner = Runner(scene, work / "cache")
    labels = [lab for lab, _ in scene.light_groups()]
    if args.lights:
        labels = [lab for lab in labels if lab in args.lights.split(",")]
    rows = {}
    for lab in labels:
        (points, E, profile, sh), kw = exitance_inputs(runner, f"render-bssrdf_adaptive-{lab}-high")
        common = dict(lights=kw["lights"], visibility=kw["visibility"])
        pick = np.sort(np.random.default_rng(1).choice(
            len(sh.positions), min(args.samples, len(sh.positions)), replace=False))
        sub = ShadingPoints(sh.positions[pick], sh.shading_normals[pick], sh.geo_normals[pick],
                            None if sh.visible is None else sh.visible[pick])
        brute, _ = exitance(points, E, profile, sub, options=dataclasses.replace(
            kw["options"], brute_force=True), **common)
        brute = np.asarray(brute, np.float64)
        row = {"camera_samples": int(len(sh.positions)), "brute_force_samples": int(len(pick))}
        for eps in (float(e) for e in args.epsilons.split(",") if e):
            opts = dataclasses.replace(kw["options"], epsilon=eps)
            secs, kern = [], []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                m, st = exitance(points, E, profile, sh, options=opts, shared=without_gathers(
                    kw["shared"]), keys=kw["keys"], **common)
                secs.append(time.perf_counter() - t0)
                kern.append(float(st.get("kernel_seconds", 0.0)))
            m = np.asarray(m, np.float64)[pick]
            row[str(eps)] = {
                "rel_rmse_vs_brute_force": float(np.sqrt(((m - brute) ** 2).mean())
                                                 / np.sqrt((brute ** 2).mean())),
                "seconds_median": statistics.median(secs), "seconds_all": secs,
                "kernel_seconds_median": statistics.median(kern)}
            print(lab, eps, {k: (round(v, 5) if isinstance(v, float) else v)
                             for k, v in row[str(eps)].items() if k != "seconds_all"}, flush=True)
        rows[lab] = row
    save_labelled(args.out, args.label, {
        "scene": str(args.scene), "geometry": "high", "repeats": args.repeats,
        "loadavg": os.getloadavg(), "cpus": os.cpu_count(),
        "note": "exitance of the full BSSRDF at all camera samples (the run's octree and shadow "
                "edges made by a first call and excluded); relative RMSE against the brute-force "
                "gather at the random camera samples, all channels",
        "lights": rows})
    print("wrote", args.out, "label", args.label)


if __name__ == "__main__":
    main()
