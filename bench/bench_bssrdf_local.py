"""Benchmark of the BSSRDF's local limit (models/bssrdf_local.py, subsurface/local.py)
against the full BSSRDF: per lighting condition and view of a scene (default:
scenes/default.toml, high mesh), the seconds of each image (the node's "total", its
exitance alone "gather", and the process's CPU seconds, PoCL's threads included), medians of
``--repeats`` interleaved calls on cached inputs with the run's shared intermediates made
once (``bench_bssrdf_adaptive.Runner``), and the two images' relative RMSE and mean ratio
(the size of the "subsurface transport" effect over the whole head).  It decides whether
``bssrdf_local`` is cheap enough to render by default (docs/science.md §4 "Local limit").

Usage: python bench/bench_bssrdf_local.py [--scene FILE] [--cache DIR] [--repeats 3]
       [--out bench/results/bssrdf_local.json]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import tempfile
from pathlib import Path

import numpy as np

from bench_bssrdf_adaptive import REPO, Runner, rel_rmse, variant


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=str(REPO / "scenes" / "default.toml"))
    ap.add_argument("--cache", default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "bssrdf_local.json"))
    args = ap.parse_args()
    from dermis.pipeline import api
    work = Path(args.cache or tempfile.mkdtemp(prefix="bench-local-"))
    work.mkdir(parents=True, exist_ok=True)
    scene_file = variant(Path(args.scene), work / "scene_local.toml", False)
    text = re.sub(r'^models = .*$', 'models = ["bssrdf", "bssrdf_local"]',
                  scene_file.read_text(), flags=re.M)
    scene_file.write_text(text)
    scene = api.load_scene(scene_file)
    api.run(scene, cache=work / "cache", export=False, jobs=1)
    runner = Runner(scene, work / "cache")
    out = {"scene": str(args.scene), "geometry": "high", "repeats": args.repeats,
           "loadavg_start": os.getloadavg(), "cpus": os.cpu_count(), "views": {}}
    for lab, _ in scene.light_groups():
        ids = {"bssrdf": f"render-bssrdf-{lab}-high",
               "bssrdf_local": f"render-bssrdf_local-{lab}-high"}
        runner.call(ids["bssrdf"])       # makes the shared intermediates (not measured)
        times = {m: [] for m in ids}
        images = {}
        for r in range(args.repeats):
            for m in (("bssrdf", "bssrdf_local") if r % 2 == 0 else ("bssrdf_local", "bssrdf")):
                res, _, _ = runner.call(ids[m])
                tm = res.artifact.timings
                times[m].append({k: tm[k] for k in ("total", "cpu", "gather",
                                                    "surface_reflection") if k in tm})
                images[m] = res.artifact
        full, local = images["bssrdf"], images["bssrdf_local"]
        mask = np.asarray(full.mask, bool)
        out["views"][lab] = {
            "seconds_median": {m: {k: statistics.median(t[k] for t in ts) for k in ts[0]}
                               for m, ts in times.items()},
            "seconds_all": times,
            "rel_rmse_local_vs_bssrdf": rel_rmse(local.linear, full.linear, mask),
            "mean_ratio_local_over_bssrdf": float(local.linear[mask].mean()
                                                  / full.linear[mask].mean())}
        print(lab, {m: round(v["total"], 2) for m, v in
                    out["views"][lab]["seconds_median"].items()}, flush=True)
    out["loadavg_end"] = os.getloadavg()
    out["note"] = ("2-core machine shared with other jobs: wall seconds noisy, CPU seconds "
                   "steadier; A/B interleaved, medians of the repeats")
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print("wrote", args.out)


if __name__ == "__main__":
    main()
