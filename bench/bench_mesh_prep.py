"""Benchmark the mesh-prep geometry steps on the Lee Perry-Smith scan: time and peak memory.

Steps: load (OBJ, cm), validate, make_high (3 Loop splits -> 1,131,776 triangles + 4096^2
displacement at the calibrated scale), vertex normals, simplify to 16,750, transfer_uv.
``--compare`` also runs igl.qslim, igl.decimate and open3d's quadric decimation on the same high
mesh and measures the distance of each low mesh to the high one (max and mean over points
sampled on the low mesh, and Hausdorff both ways with igl.hausdorff).

Run: python bench/bench_mesh_prep.py [--compare] [--out bench/results/mesh_prep.json]
Peak memory is the process's peak RSS growth during the step (resource.getrusage ru_maxrss is
monotonic, so each step runs in a forked child and reports its own peak).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "lps_head"


def in_child(fn):
    """Run fn() in a forked child; return (result, seconds, peak RSS MiB of the child)."""
    import pickle

    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        try:
            base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            t = time.perf_counter()
            out = fn()
            dt = time.perf_counter() - t
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            payload = (out, dt, peak / 1024.0, base / 1024.0)
        except BaseException as exc:  # the child must never return into the parent's code
            payload = RuntimeError(f"{type(exc).__name__}: {exc}")
        with os.fdopen(w, "wb") as fh:
            pickle.dump(payload, fh)
        os._exit(0)
    os.close(w)
    with os.fdopen(r, "rb") as fh:
        payload = pickle.load(fh)
    os.waitpid(pid, 0)
    if isinstance(payload, Exception):
        raise payload
    return payload


def distances(high_v, high_f, low_v, low_f, n_samples=200_000, seed=0):
    """Distances low -> high (points sampled on low) and Hausdorff, mm."""
    import igl
    import open3d as o3d

    rng = np.random.default_rng(seed)
    a = np.linalg.norm(np.cross(low_v[low_f[:, 1]] - low_v[low_f[:, 0]], low_v[low_f[:, 2]] - low_v[low_f[:, 0]]), axis=1)
    fi = rng.choice(len(low_f), n_samples, p=a / a.sum())
    r1, r2 = rng.random(n_samples), rng.random(n_samples)
    s = np.sqrt(r1)
    pts = ((1 - s)[:, None] * low_v[low_f[fi, 0]] + (s * (1 - r2))[:, None] * low_v[low_f[fi, 1]]
           + (s * r2)[:, None] * low_v[low_f[fi, 2]])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(high_v.astype(np.float32)), o3d.core.Tensor(high_f.astype(np.uint32)))
    d = scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    hd = igl.hausdorff(high_v, high_f.astype(np.int64), low_v, low_f.astype(np.int64))
    return {"mean_mm": float(d.mean()), "p99_mm": float(np.percentile(d, 99)), "max_sampled_mm": float(d.max()),
            "hausdorff_mm": float(hd)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "mesh_prep.json"))
    ap.add_argument("--compare", action="store_true", help="also run igl.qslim, igl.decimate, open3d")
    args = ap.parse_args()
    if not DATA.is_dir():
        print(f"skip: {DATA} not found")
        return 0
    from dermis.geometry.normals import angle_weighted_normals
    from dermis.geometry.scan import load_scan, read_grey_image
    from dermis.geometry.simplification import simplify
    from dermis.geometry.subdivision import LPS_DISPLACEMENT_MID, LPS_DISPLACEMENT_SCALE_MM, make_high
    from dermis.geometry.uv_transfer import transfer_uv
    from dermis.geometry.validation import validate

    res: dict = {"machine": f"{os.cpu_count()} cores", "steps": {}}

    def record(name, fn):
        out, dt, peak, base = in_child(fn)
        res["steps"][name] = {"seconds": round(dt, 3), "peak_rss_mib": round(peak, 1),
                              "peak_rss_growth_mib": round(peak - base, 1)}
        print(f"{name:12s} {dt:7.2f} s   peak RSS {peak:7.1f} MiB (+{peak - base:.1f})")
        return out

    obj = DATA / "LeePerrySmith_cm.obj"
    scan = record("load", lambda: load_scan(obj, units="cm"))
    base, _ = record("validate", lambda: validate(scan, source=str(obj)))
    disp = read_grey_image(DATA / "Infinite-Level_02_Disp_NoSmoothUV-4096.jpg")
    high = record("make_high", lambda: make_high(
        base, target_triangles=1_000_000, displacement=disp, displacement_scale_mm=LPS_DISPLACEMENT_SCALE_MM,
        displacement_mid=LPS_DISPLACEMENT_MID))
    record("normals", lambda: angle_weighted_normals(high.vertices, high.faces).shape)
    low = record("simplify", lambda: simplify(high, target_triangles=16750))
    low_uv, rep = record("transfer_uv", lambda: transfer_uv(high, low))
    res["high_triangles"] = int(len(high.faces))
    res["low_triangles"] = int(len(low.faces))
    res["transfer_uv"] = rep
    res["total_seconds"] = round(sum(s["seconds"] for s in res["steps"].values()), 2)
    print(f"total {res['total_seconds']} s; high {len(high.faces)} tris, low {len(low.faces)} tris; transfer {rep}")

    # Distribution of the straddle ratio before repair (supports the bound _SEAM_RATIO).
    hv, hf = high.vertices, high.faces.astype(np.int64)
    res["distance_fast_simplification"] = distances(hv, hf, low.vertices, low.faces)
    print("fast-simplification distance:", res["distance_fast_simplification"])

    if args.compare:
        import igl
        import open3d as o3d

        comp = {}
        vF = np.asfortranarray(hv)
        fF = np.asfortranarray(hf.astype(np.int32))

        def run_qslim():
            U, G, _, _ = igl.qslim(vF, fF, 16750)
            return np.asarray(U), np.asarray(G)

        def run_decimate():
            U, G, _, _ = igl.decimate(vF, fF, 16750)
            return np.asarray(U), np.asarray(G)

        def run_o3d():
            m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(hv), o3d.utility.Vector3iVector(hf.astype(np.int32)))
            s = m.simplify_quadric_decimation(16750)
            return np.asarray(s.vertices), np.asarray(s.triangles)

        for name, fn in (("igl.qslim", run_qslim), ("igl.decimate", run_decimate), ("open3d.quadric", run_o3d)):
            try:
                (U, G), dt, peak, base_rss = in_child(fn)
            except Exception as exc:  # report and go on
                comp[name] = {"error": f"{type(exc).__name__}: {exc}"}
                print(name, "failed:", exc)
                continue
            dist = distances(hv, hf, U, G)
            comp[name] = {"seconds": round(dt, 2), "peak_rss_growth_mib": round(peak - base_rss, 1),
                          "triangles": int(len(G)), **dist}
            print(f"{name:16s} {dt:6.2f} s  {len(G)} tris  {dist}")
        comp["fast_simplification"] = {"seconds": res["steps"]["simplify"]["seconds"],
                                       "triangles": int(len(low.faces)), **res["distance_fast_simplification"]}
        res["simplifier_comparison"] = comp
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))
    print("wrote", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
