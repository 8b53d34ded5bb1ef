"""Benchmark of the hierarchical BSSRDF gather (subsurface/gather.py) against brute force.

Scene: the LPS head OBJ (ASSET: the same bytes as scenes/assets/lps_head/LeePerrySmith_cm.obj;
centimetres -> mm, ~369,000 mm^2), blue-noise points from subsurface/points.py, irradiance of
one directional light from the upper front right, E = max(0, n.l) with a hard shadow ray per
point (open3d), profile from optics/layer_profiles.py (default preset skin2, cut-off 24 mm).
Query points: the surface points seen by an orthographic camera looking down -z at the face,
in scanline order, up to --queries of them.  Falls back to a unit-sphere-like synthetic mesh
if the asset is absent.

Measured: kernel time (profiling events) and relative RMSE (per channel
sqrt(mean((h - b)^2)) / sqrt(mean(b^2)), max over channels) of the hierarchical gather against
brute force, for several epsilon, leaf sizes and query orders; gather time as the number of
points grows.  Brute force over all queries is far too slow: it runs on a random subset of
--brute-queries queries and its full time is extrapolated linearly (it is exactly O(Q N)).

Usage: python bench/bench_gather.py [--points 250000] [--queries 640000] [--out FILE] [--quick]
The 2-core machine is shared with other jobs: treat the times as noisy (+-20 %).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
ASSET = REPO.parent / "shared" / "data" / "lps_head" / "LeePerrySmith_cm.obj"


def load_mesh():
    import open3d as o3d
    if ASSET.is_file():
        m = o3d.io.read_triangle_mesh(str(ASSET))
        return np.asarray(m.vertices) * 10.0, np.asarray(m.triangles), "lps_head_obj_x10"
    m = o3d.geometry.TriangleMesh.create_sphere(radius=170.0, resolution=200)
    return np.asarray(m.vertices), np.asarray(m.triangles), "sphere_r170"


def irradiance(v, f, pos, nrm):
    import open3d as o3d
    light = np.array([0.5, 0.5, 0.7])
    light /= np.linalg.norm(light)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    org = pos + nrm * 0.05
    rays = np.hstack([org, np.broadcast_to(light, org.shape)]).astype(np.float32)
    lit = ~np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())
    e = np.clip(nrm @ light, 0, None) * lit
    return np.repeat(e[:, None], 3, axis=1) * np.array([1.0, 0.95, 0.9]), scene


def camera_queries(scene, v, n_target):
    import open3d as o3d
    lo, hi = v.min(0), v.max(0)
    res = int(np.sqrt(n_target / 0.5)) + 1
    for _ in range(6):
        xs = np.linspace(lo[0], hi[0], res)
        ys = np.linspace(hi[1], lo[1], res)
        X, Y = np.meshgrid(xs, ys)
        org = np.stack([X.ravel(), Y.ravel(), np.full(X.size, hi[2] + 10.0)], 1)
        rays = np.hstack([org, np.tile([0, 0, -1.0], (len(org), 1))]).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        hit = np.isfinite(t)
        if hit.sum() >= n_target:
            pts = org[hit] + np.array([0, 0, -1.0]) * t[hit, None]
            return pts[:n_target], res
        res = int(res * np.sqrt(n_target / max(hit.sum(), 1)) * 1.05) + 1
    raise RuntimeError("could not get enough query points")


def rel_rmse(h, b):
    return float(np.max(np.sqrt(((h - b) ** 2).mean(0) / np.maximum((b ** 2).mean(0), 1e-30))))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=250_000)
    ap.add_argument("--queries", type=int, default=640_000)
    ap.add_argument("--brute-queries", type=int, default=2000)
    ap.add_argument("--preset", default="skin2")
    ap.add_argument("--quick", action="store_true", help="fewer points/queries (smoke run)")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "gather.json"))
    args = ap.parse_args()
    if args.quick:
        args.points, args.queries, args.brute_queries = 30_000, 50_000, 500

    from dermis.pipeline.cl import get_env
    from dermis.pipeline.config import BssrdfConfig
    from dermis.optics.layers import PRESETS
    from dermis.optics.layer_profiles import build_profiles
    from dermis.subsurface import gather as G
    from dermis.subsurface.octree import build_octree
    from dermis.subsurface.points import mesh_area, sample_points

    shipped = BssrdfConfig()  # the scene defaults: the epsilon and leaf size the pipeline runs
    env = get_env()
    res = {"device": env.description, "preset": args.preset,
           "shipped": {"epsilon": shipped.epsilon, "leaf_size": shipped.leaf_size}, "note":
           "2-core shared machine, other jobs running: times noisy (+-20 %)",
           "loadavg_start": list(__import__("os").getloadavg())}
    prof = build_profiles(PRESETS[args.preset])
    res["cutoff_mm"] = prof.cutoff_mm.tolist()
    v, f, mesh_name = load_mesh()
    area = mesh_area(v, f)
    res["mesh"] = mesh_name
    res["mesh_area_mm2"] = area

    def make_points(n, seed=1):
        sp = sample_points(v, f, spacing_mm=float(np.sqrt(area / n)), seed=seed)
        e, scene = irradiance(v, f, sp.positions.astype(np.float64), sp.normals.astype(np.float64))
        return sp, e, scene

    t = time.perf_counter()
    sp, e, scene = make_points(args.points)
    res["sampling_seconds"] = time.perf_counter() - t
    res["points"] = len(sp.positions)
    res["nn_cv"] = sp.info.get("nn_cv")
    q, cam_res = camera_queries(scene, v, args.queries)
    res["queries"] = len(q)
    res["camera_resolution"] = cam_res
    rng = np.random.default_rng(7)
    sub = rng.choice(len(q), min(args.brute_queries, len(q)), replace=False)

    t = time.perf_counter()
    tree = build_octree(sp.positions, sp.areas, e, leaf_size=shipped.leaf_size,
                          kernel_sigma_mm=sp.info.get("kernel_sigma_mm"))
    res["octree_build_seconds"] = time.perf_counter() - t
    res["octree"] = tree.info
    print(f"{mesh_name}: {len(sp.positions)} points, {len(q)} queries, tree {tree.info}", flush=True)

    b, sb = G.gather(tree, prof, q[sub], epsilon=None, env=env, brute_force=True)
    brute_full = sb["kernel_seconds"] * len(q) / len(sub)
    res["brute"] = {"subset_queries": len(sub), "subset_kernel_s": sb["kernel_seconds"],
                    "estimated_full_kernel_s": brute_full}
    print(f"brute force: {sb['kernel_seconds']:.2f} s for {len(sub)} queries -> "
          f"estimated {brute_full:.0f} s for {len(q)}", flush=True)

    # walks: the default tile walk (16 queries per work-item, far-field Taylor expansion about
    # the tile and its 4 sub-tiles), without the sub-tile expansion, with every source exact,
    # and the per-query walk (tile=1)
    walks = {"tile16": {}, "tile16_nosub": {"subtiles": False},
             "tile16_exact": {"expand_mm": 1e30}, "query": {"tile": 1}}
    for kw in walks.values():  # build/warm the kernels
        for second in (True, False):
            G.gather(tree, prof, q[:1000], env=env, epsilon=0.1,
                     tuning=G.GatherTuning(second_order=second, **kw))
    rows = []
    for walk, kw in walks.items():
        for second in (True, False):
            for eps in (1.0, 0.8, 0.6, 0.5, 0.4, 0.25, 0.15, 0.1, 0.05):
                if (not second and (eps > 0.4 or walk != "query")) or \
                        (walk in ("tile16_exact", "tile16_nosub") and eps not in (0.6, 0.5, 0.4)):
                    continue
                h, st = G.gather(tree, prof, q, env=env, epsilon=eps,
                                 tuning=G.GatherTuning(second_order=second, **kw))
                err = rel_rmse(h[sub], b)
                row = {"walk": walk, "epsilon": eps, "second_order": second,
                       "kernel_s": st["kernel_seconds"], "rel_rmse": err,
                       "mean_visits": st["mean_visits"], "speedup": brute_full / st["kernel_seconds"]}
                rows.append(row)
                print(f"{walk:12s} {'2nd' if second else 'plain'} eps {eps:5.3f}: "
                      f"{st['kernel_seconds']:6.2f} s  rel RMSE {100 * err:.3f} %  visits "
                      f"{st['mean_visits']:.0f}  speedup {row['speedup']:.0f}x", flush=True)
    res["epsilon_sweep"] = rows
    res["loadavg_after_sweep"] = list(__import__("os").getloadavg())

    # query order (at the shipped epsilon): Morton vs scanline vs random (the tile walk always
    # sorts, so sort_queries=False only changes the launch order of the per-query walk)
    order_rows = []
    perm = rng.permutation(len(q))
    for name, qq, srt in (("morton", q, True), ("scanline", q, False), ("random", q[perm], False)):
        _, st = G.gather(tree, prof, qq, env=env, epsilon=shipped.epsilon,
                         tuning=G.GatherTuning(sort_queries=srt))
        order_rows.append({"order": name, "kernel_s": st["kernel_seconds"]})
        print(f"order {name}: {st['kernel_seconds']:.2f} s", flush=True)
    res["query_order"] = order_rows

    # leaf size (at the shipped epsilon and at 0.6)
    leaf_rows = []
    for ls in (4, 8, 16, 32):
        tr = build_octree(sp.positions, sp.areas, e, leaf_size=ls,
                            kernel_sigma_mm=sp.info.get("kernel_sigma_mm"))
        for eps in (shipped.epsilon, 0.6):
            h, st = G.gather(tr, prof, q, env=env, epsilon=eps)
            leaf_rows.append({"leaf_size": ls, "epsilon": eps, "kernel_s": st["kernel_seconds"],
                              "rel_rmse": rel_rmse(h[sub], b), "nodes": tr.info["nodes"]})
            print(f"leaf {ls} eps {eps}: {st['kernel_seconds']:.2f} s  rel RMSE "
                  f"{100 * leaf_rows[-1]['rel_rmse']:.3f} %", flush=True)
    res["leaf_size"] = leaf_rows

    # growth with the number of points (fixed query subset of 64k, shipped epsilon)
    growth = []
    qg = q[rng.choice(len(q), min(64_000, len(q)), replace=False)]
    for n in sorted({args.points // 16, args.points // 4, args.points}):
        spn, en, _ = make_points(n, seed=2) if n != args.points else (sp, e, None)
        tr = build_octree(spn.positions, spn.areas, en,
                            kernel_sigma_mm=spn.info.get("kernel_sigma_mm"))
        _, st = G.gather(tr, prof, qg, env=env, epsilon=shipped.epsilon)
        _, sbn = G.gather(tr, prof, qg[:500], epsilon=None, env=env, brute_force=True)
        growth.append({"points": len(spn.positions), "tree_kernel_s": st["kernel_seconds"],
                       "brute_kernel_s_est": sbn["kernel_seconds"] * len(qg) / 500,
                       "queries": len(qg)})
        print(f"growth N={len(spn.positions)}: tree {st['kernel_seconds']:.3f} s, brute est "
              f"{growth[-1]['brute_kernel_s_est']:.1f} s ({len(qg)} queries)", flush=True)
    res["growth"] = growth

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
