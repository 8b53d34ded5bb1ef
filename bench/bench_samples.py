"""Benchmark of subsurface/points.py: seconds per sub-step, before (the committed HEAD version,
loaded from git) and after (the working tree), on the Lee Perry-Smith head at ~1M triangles
and spacing 1.22 mm (~245k points), plus the accuracy numbers the speed must not cost:
nearest-neighbour CV, the partition-of-unity spread over random probes on the head, and the
partition-of-unity max deviation on a finely tessellated 60 mm plane (3 seeds; the quantity
tests/test_samples.py::test07 bounds, on triangles as small as the head's).

    python3 bench/bench_samples.py [--out bench/results/samples.json] [--no-baseline]
                                   [--baseline-ref HEAD] [--relax 0,1,2]
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "lps_head" / "LeePerrySmith_cm.obj"
SPACING_MM = 1.22  # the pipeline's default density on skin presets (~245k points on the head)
STEP_KEYS = ("seconds_sampling", "seconds_relax", "seconds_normals", "seconds_areas", "seconds")


def load_module(ref: str | None):
    """subsurface.points from the working tree (ref None) or from git at ``ref``
    (``stages/samples.py`` at a commit without subsurface/points.py)."""
    if ref is None:
        from dermis.subsurface import points
        return points
    for path in ("subsurface/points.py", "stages/samples.py"):
        shown = subprocess.run(["git", "show", f"{ref}:{path}"], cwd=ROOT, capture_output=True,
                               text=True)
        if shown.returncode == 0:
            break
    shown.check_returncode()
    src = shown.stdout
    tmp = Path(tempfile.mkdtemp()) / "samples_baseline.py"
    tmp.write_text(src)
    spec = importlib.util.spec_from_file_location("samples_baseline", tmp)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["samples_baseline"] = mod
    spec.loader.exec_module(mod)
    return mod


def fine_plane(half=30.0, cells=75, seed=1):
    """A jittered-grid tessellated square: triangles of ~0.3 mm^2, like the head's."""
    g = np.linspace(-half, half, cells + 1)
    x, y = np.meshgrid(g, g)
    v = np.stack([x.ravel(), y.ravel(), 0 * x.ravel()], 1)
    inner = (np.abs(v[:, :2]) < half - 1e-9).all(1)
    v[:, :2] += np.random.default_rng(seed).uniform(-0.2, 0.2, (len(v), 2)) * inner[:, None]
    idx = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def plane_pou(mod, relax):
    """Max |sum_p A_p G_sigma(y - p) - 1| over 2000 probes >= 10 sigma from the edges, 3 seeds."""
    v, f = fine_plane()
    y = np.zeros((2000, 3))
    y[:, :2] = np.random.default_rng(5).uniform(-20, 20, (2000, 2))
    out = []
    for seed in (4, 5, 6):
        sp = getattr(mod, "sample_points", getattr(mod, "run", None))(v, f, spacing_mm=1.0, seed=seed, relax_iterations=relax)
        d = mod.density_spread(sp.positions.astype(float), sp.areas.astype(float), y,
                               sp.info["kernel_sigma_mm"])
        out.append({"max_abs_dev": d["max_abs_dev"], "std": d["std"], "nn_cv": sp.info["nn_cv"]})
    return out


def head_run(mod, v, f, relax):
    t = time.perf_counter()
    sp = getattr(mod, "sample_points", getattr(mod, "run", None))(v, f, spacing_mm=SPACING_MM, seed=0, relax_iterations=relax)
    wall = time.perf_counter() - t
    i = sp.info
    row = {k: i.get(k) for k in STEP_KEYS}
    row.update(wall=wall, points=int(i["count"]), nn_cv=i["nn_cv"],
               pou_probe_std=i.get("pou_probe_std"), relax_iterations=relax,
               sampler=i.get("sampler"))
    return row, sp


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "samples.json"))
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--baseline-ref", default="HEAD")
    ap.add_argument("--relax", default="0,1,2", help="Lloyd step counts to measure (new code)")
    args = ap.parse_args()
    if not DATA.exists():
        sys.exit(f"bench_samples: {DATA} not found")
    from dermis.geometry.subdivision import make_high
    from dermis.geometry.scan import load_scan
    load = os.getloadavg()
    print(f"load average before timing: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} "
          f"({os.cpu_count()} cores)")
    high = make_high(load_scan(str(DATA), units="cm"), target_triangles=1_000_000)
    v, f = np.asarray(high.vertices, np.float64), np.asarray(high.faces, np.int64)
    print(f"mesh: {len(f)} triangles")
    res = {"mesh_triangles": int(len(f)), "spacing_mm": SPACING_MM, "loadavg": list(load),
           "runs": {}}
    new = load_module(None)
    mods = [] if args.no_baseline else [("before", load_module(args.baseline_ref),
                                          [new.DEFAULT_RELAX_ITERATIONS])]
    mods.append(("after", new, [int(x) for x in args.relax.split(",")]))
    for name, mod, relaxes in mods:
        for relax in relaxes:
            key = f"{name}_relax{relax}"
            row, _ = head_run(mod, v, f, relax)
            row["plane_pou"] = plane_pou(mod, relax)
            row["plane_pou_max_dev"] = max(r["max_abs_dev"] for r in row["plane_pou"])
            res["runs"][key] = row
            steps = " ".join(f"{k.replace('seconds_', '')} {row[k]:.2f}" for k in STEP_KEYS
                             if row.get(k) is not None)
            print(f"{key:15s} {steps} | wall {row['wall']:.2f} s, {row['points']} points, "
                  f"nn CV {row['nn_cv']:.3f}, head PoU std {row['pou_probe_std']:.4f}, "
                  f"plane PoU max dev {row['plane_pou_max_dev']:.4f}")
    if not args.no_baseline:
        d = new.DEFAULT_RELAX_ITERATIONS
        res["speedup"] = res["runs"][f"before_relax{d}"]["wall"] / res["runs"][f"after_relax{d}"]["wall"]
        print(f"speed-up at the default {d} Lloyd steps: {res['speedup']:.2f}x")
    res["loadavg_after"] = list(os.getloadavg())
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
