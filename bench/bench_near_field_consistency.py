"""Does the near field's shadow ray agree with its shadow edges?  (docs/science.md §4 "Near
field").

For point and directional lights the near part of the exitance at a shading point x is
C(x) [Rd_near V(x) - s(x)]: V(x) the pixel's own shadow ray, s(x) the boundary integral over
the shadow-edge segments located between the irradiance points.  The identity holds when
V(x) is the indicator of the region the segments bound; then the bracket lies in
[0, Rd_near] per channel (s is Rd_near minus the near energy of the lit region when x is lit,
minus that energy when x is shadowed), and its sign tells the side of the edges x lies on.
This benchmark counts, per near-field evaluation of a scene:

* ``live``: shading points facing the light (C > 0); ``in_reach``: those with an edge within
  the window (s != 0);
* ``disagree``: live points where V(x) and the side the segments give x disagree (the
  bracket outside [0, Rd_near] in a channel), split into ``shadowed_but_lit_side`` (V = 0,
  s > 0: a negative bracket) and ``lit_but_shadow_side`` (V = 1, s < 0: a bracket above
  Rd_near), with quantiles of how far outside (in Rd_near) and the distance to the nearest
  segment;
* ``disagree_rendered_sharp``: of those, how many the code under test still renders with the
  bracket (its returned near term equal to C (Rd_near V - s), where that differs from
  C [Rd_near V - (2 V - 1) |s|] by more than 1e-5 C Rd_near);
* ``edge_sum_above_rd_near``: live points with |s| > Rd_near in a channel (segments that
  bound no region as seen from x);
* ``negative_near_terms``: returned near terms with a negative channel, and the smallest in
  units of C Rd_near;
* the minimum of each rendered image (pipeline scenes) or exitance (synthetic scenes).

It works with any checkout of dermis that PYTHONPATH imports (``sharp_near_field`` is
wrapped where ``subsurface/exitance.py`` calls it; the counts use only ``edge_sum_cl``,
``sample_lights`` and the arguments: tests/near_field_scenes.py ``near_parts``,
``recording``), so two checkouts under two labels measure the same things.  The results'
"before" label is git 9b9797f (the bracket Rd_near V - s with the edges' side), "after"
this code.

Usage: python bench/bench_near_field_consistency.py [--label after] [--scenes quick,sphere]
       [--default] [--cache DIR] [--out bench/results/near_field_consistency.json]
``--default`` adds the default scene's point light on the high mesh (minutes).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from labelled import save_labelled

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
from near_field_scenes import near_parts, recording  # noqa: E402  (tests/: shared with the tests)


# ------------------------------------------------------------------------ the counter
def nearest_segment(x: np.ndarray, ns: np.ndarray, ed) -> np.ndarray:
    """Distance (mm) from each point to the nearest segment whose surface normal agrees with
    its own (dot > 0.5, as the edge sums count them); inf where none."""
    from scipy.spatial import cKDTree
    best = np.full(len(x), np.inf)
    if len(ed.origin) == 0 or len(x) == 0:
        return best
    centre = ed.origin + (0.5 * (ed.hi + ed.lo))[:, None] * ed.tangent
    _, kk = cKDTree(centre).query(x, k=min(32, len(centre)))
    kk = kk.reshape(len(x), -1)
    for j in range(kk.shape[1]):
        k = kk[:, j]
        rel = x - ed.origin[k]
        t = np.clip(np.einsum("ij,ij->i", rel, ed.tangent[k]), ed.lo[k], ed.hi[k])
        d = np.linalg.norm(rel - t[:, None] * ed.tangent[k], axis=1)
        ok = np.einsum("ij,ij->i", ns, ed.normal[k]) > 0.5
        best = np.where(ok & (d < best), d, best)
    return best


def _q(a, qs=(10, 50, 90)):
    return np.percentile(a, qs).round(4).tolist() if len(a) else None


def count(call: dict, returned: np.ndarray, env) -> dict:
    """The counts of the module docstring for one call and the near term it returned."""
    p = near_parts(call, env)
    live, b, rd, c = p["live"], p["bracket"], p["rd_near"], p["c"]
    lo = live & (b < 0).any(axis=1)
    hi = live & (b > rd).any(axis=1) & ~lo
    dis = lo | hi
    sharp = c * b
    scale = np.maximum(np.abs(c * rd).max(axis=1), 1e-30)
    same = np.abs(np.asarray(returned, np.float64) - sharp).max(axis=1) <= 1e-5 * scale
    # where |s| is tiny the identity and any side rule give the same value: count only the
    # queries where taking the side from the segments or from V differs (by 2 |s| C in the
    # channels whose s has the other sign)
    side_from_v = np.where(p["visible"][:, None], rd - np.abs(p["s"]), np.abs(p["s"]))
    distinct = np.abs(c * (b - side_from_v)).max(axis=1) > 1e-5 * scale
    ret = np.asarray(returned, np.float64)
    neg = (ret < 0).any(axis=1)
    rel = (ret / np.where(c * rd > 0, c * rd, np.inf)).min(axis=1)
    i = np.flatnonzero(dis)
    dist = nearest_segment(np.asarray(call["queries"], np.float64)[i],
                           np.asarray(call["shading_normals"], np.float64)[i], call["edges"])
    return {"light": call["light"].name, "queries": int(len(b)), "live": int(live.sum()),
            "in_reach": int((live & (p["s"] != 0).any(axis=1)).sum()),
            "crossings": int(call["edges"].info.get("crossings", 0)),
            "disagree": int(dis.sum()), "shadowed_but_lit_side": int(lo.sum()),
            "lit_but_shadow_side": int(hi.sum()),
            "below_zero_q10_50_90": _q(-(b[lo] / rd).min(axis=1)),
            "above_rd_near_q10_50_90": _q((b[hi] / rd).max(axis=1) - 1.0),
            "disagree_over_1pct": int((live & ((b < -0.01 * rd) | (b > 1.01 * rd)).any(axis=1)).sum()),
            "nearest_segment_mm_q10_50_90": _q(dist[np.isfinite(dist)]),
            "disagree_rendered_sharp": int((dis & same & distinct).sum()),
            "edge_sum_above_rd_near": int((live & (np.abs(p["s"]) > rd).any(axis=1)).sum()),
            "negative_near_terms": int(neg.sum()),
            "min_near_over_c_rd_near": float(rel[live].min()) if live.any() else 0.0,
            "near_above_c_rd_near_1pct": int((live & (ret > 1.01 * c * rd).any(axis=1)).sum())}


# ------------------------------------------------------------------------ scenes
def pipeline_scene(path: Path, cache: Path, overrides: dict, env) -> dict:
    """Render the scene's BSSRDF images (as ``overrides`` restrict them) in-process, the
    bssrdf nodes forced; the counts of every near-field call and each image's minimum."""
    from dermis.pipeline import api
    from dermis.pipeline.config import load_scene
    scene = load_scene(path, overrides=overrides)
    t0 = time.perf_counter()
    api.run(scene, cache=cache, export=False, jobs=1)       # everything upstream, cached
    with recording() as (calls, rendered):
        api.run(scene, cache=cache, export=False, force=["bssrdf"], jobs=1)
    seconds = time.perf_counter() - t0
    counts = [count(a, r, env) for a, r in calls]
    images = {node: {"min": float(lin.min()), "max": float(lin.max()),
                     "min_over_max": float(lin.min() / max(lin.max(), 1e-30)),
                     "negative_pixels": int((lin < 0).any(axis=2).sum()),
                     "nonfinite_pixels": int((~np.isfinite(lin)).any(axis=2).sum())}
              for node, lin in sorted(rendered.items())}
    return {"near_field_calls": counts, "images": images, "seconds": seconds,
            "totals": totals(counts)}


SPHERES = {
    # (light, elevation, plate edge x, bump amplitude) on a 20 mm sphere, two_layer
    "sphere_smooth_dir": dict(light="directional", elevation_deg=40.0, edge_mm=4.0),
    "sphere_bumpy_dir": dict(light="directional", elevation_deg=40.0, edge_mm=4.0, bump_mm=0.3),
    "sphere_smooth_point_grazing": dict(light="point", elevation_deg=15.0, edge_mm=12.0),
    "sphere_bumpy_point_grazing": dict(light="point", elevation_deg=15.0, edge_mm=12.0,
                                       bump_mm=0.3),
}


def reference_bracket(call: dict, sc: dict, prof, idx: np.ndarray, samples: int,
                      rng) -> np.ndarray:
    """Monte Carlo reference of the bracket at the queries ``idx``, (len(idx), 3): the near
    energy of the lit region, int R_near(r) V(y) dA over the window, y = x + r (cos t, sin t)
    in x's tangent plane moved onto the mesh along the normal, V(y) whether the light
    reaches y (its geometric normal faces the light and the shadow ray is free): what
    C(x) [Rd_near V(x) - s(x)] claims to compute, from the mesh alone (no shadow edges, no
    points).  r is drawn with density 2 pi r sum_c R_near,c(r) (importance sampling)."""
    from dermis.lighting.irradiance import irradiance
    from dermis.subsurface.near_field import split_profile
    split = split_profile(prof, float(sc["pts"].info["kernel_sigma_mm"]))
    r_grid, R = split.near.r_mm, split.near.R
    ring = 2 * np.pi * r_grid * R.sum(axis=1)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (ring[1:] + ring[:-1]) * np.diff(r_grid))])
    total = cdf[-1]
    vis = sc["vis"]
    verts, faces = sc["mesh"]
    x = np.asarray(call["queries"], np.float64)[idx]
    n = np.asarray(call["shading_normals"], np.float64)[idx]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    a = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    out = np.zeros((len(x), 3))
    h = 3.0
    for i in range(len(x)):
        r = np.interp(rng.random(samples) * total, cdf, r_grid)
        th = 2 * np.pi * rng.random(samples)
        y = x[i] + r[:, None] * (np.cos(th)[:, None] * t1[i] + np.sin(th)[:, None] * t2[i])
        hits = vis.intersect((y + h * n[i]).astype(np.float32),
                             np.tile(-n[i], (samples, 1)).astype(np.float32))
        ok = hits.hit & (hits.t < 2 * h) & (hits.tri < len(faces))
        p = (y + h * n[i] - hits.t[:, None] * n[i])[ok]
        f = faces[hits.tri[ok]]
        ng = np.cross(verts[f[:, 1]] - verts[f[:, 0]], verts[f[:, 2]] - verts[f[:, 0]])
        ng /= np.linalg.norm(ng, axis=1, keepdims=True)
        lit = np.zeros(samples, bool)
        lit[ok] = irradiance(p.astype(np.float32), ng.astype(np.float32), [call["light"]],
                             vis.occluded).sum(axis=1) > 0
        Rn = np.stack([np.interp(r, r_grid, R[:, c]) for c in range(3)], axis=1)
        w = Rn / np.maximum(Rn.sum(axis=1, keepdims=True), 1e-300)
        out[i] = (w * lit[:, None]).sum(axis=0) * total / samples
    return out


def reference_errors(call: dict, returned, sc: dict, prof, env, *, per_group: int = 150,
                     samples: int = 4096, seed: int = 7) -> dict:
    """Error of the rendered bracket (the returned near term / C(x)) against
    :func:`reference_bracket`, in units of Rd_near (worst channel: mean, 90th percentile),
    at up to ``per_group`` random queries where the shadow ray and the edges disagree and as
    many in reach of an edge where they agree; the Monte Carlo standard error alongside (from
    two independent half-estimates)."""
    rng = np.random.default_rng(seed)
    p = near_parts(call, env)
    live, b, rd, c = p["live"], p["bracket"], p["rd_near"], p["c"]
    dis = live & ((b < 0) | (b > rd)).any(axis=1)
    agree = live & ~dis & (p["s"] != 0).any(axis=1)
    out = {}
    for name, sel in (("disagree", dis), ("agree_in_reach", agree)):
        i = np.flatnonzero(sel)
        if len(i) == 0:
            continue
        i = np.sort(rng.choice(i, min(per_group, len(i)), replace=False))
        ref = reference_bracket(call, sc, prof, i, samples, rng)
        ref2 = reference_bracket(call, sc, prof, i, samples, rng)
        se = (np.abs(ref - ref2) / 2 / rd).max(axis=1)
        v = p["visible"][i, None]
        cands = {"rendered": np.asarray(returned, np.float64)[i] / c[i],
                 # alternatives: the bracket as the identity gives it, and with the side of
                 # s taken from V (x at the same distance from the curve, on V's side)
                 "identity": b[i], "side_from_v": np.where(v, rd - np.abs(p["s"][i]),
                                                           np.abs(p["s"][i]))}
        out[name] = {"queries": int(len(i)), "mc_standard_error_mean": float(se.mean())}
        for k, got in cands.items():
            err = (np.abs(got - 0.5 * (ref + ref2)) / rd).max(axis=1)
            out[name][k] = {"mean_err": round(float(err.mean()), 4),
                            "q90_err": round(float(np.percentile(err, 90)), 4),
                            "max_err": round(float(err.max()), 4)}
    return out


def sphere_scenes(env, density: float | None) -> dict:
    """tests/near_field_scenes.py's shadowed sphere in the configurations of SPHERES."""
    import near_field_scenes as NS
    from dermis.optics.layer_profiles import build_profiles
    from dermis.optics.layers import PRESETS
    stack = PRESETS["two_layer"]
    prof = build_profiles(stack)
    out = {}
    for name, kw in SPHERES.items():
        t0 = time.perf_counter()
        sc = NS.shadowed_sphere(prof, stack, density=density, **kw)
        with recording() as (calls, _):
            M, _ = NS.scene_exitance(sc, prof, env)
        counts = [count(a, r, env) for a, r in calls]
        ref = [reference_errors(a, r, sc, prof, env) for a, r in calls]
        out[name] = {**kw, "spacing_mm": sc["spacing"], "near_field_calls": counts,
                     "against_monte_carlo": ref,
                     "exitance_min_over_max": float(M.min() / max(M.max(), 1e-30)),
                     "negative_exitance": int((M < 0).any(axis=1).sum()),
                     "seconds": time.perf_counter() - t0, "totals": totals(counts)}
    return out


def totals(counts: list[dict]) -> dict:
    keys = ("live", "in_reach", "disagree", "shadowed_but_lit_side", "lit_but_shadow_side",
            "disagree_over_1pct", "disagree_rendered_sharp", "edge_sum_above_rd_near",
            "negative_near_terms",
            "near_above_c_rd_near_1pct")
    t = {k: int(sum(c[k] for c in counts)) for k in keys}
    t["min_near_over_c_rd_near"] = min((c["min_near_over_c_rd_near"] for c in counts),
                                       default=0.0)
    return t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--label", default="after")
    ap.add_argument("--scenes", default="quick,sphere")
    ap.add_argument("--default", action="store_true",
                    help="also the default scene's point light on the high mesh (minutes)")
    ap.add_argument("--sphere-density", type=float, default=None,
                    help="point density of the sphere scenes (default: the scene default)")
    ap.add_argument("--cache", default="/tmp/dermis-near-field-consistency")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "near_field_consistency.json"))
    args = ap.parse_args()
    from dermis.pipeline.cl import get_env
    env = get_env()
    cache = Path(args.cache)
    res: dict = {}
    wanted = args.scenes.split(",") if args.scenes else []
    if "quick" in wanted:
        res["quick"] = pipeline_scene(
            REPO / "scenes" / "quick.toml", cache / "quick",
            {"render": {"models": ["bssrdf"], "lights": ["point", "dir_left+dir_right"]}}, env)
    if "sphere" in wanted:
        res["spheres"] = sphere_scenes(env, args.sphere_density)
    if args.default:
        res["default_point_high"] = pipeline_scene(
            REPO / "scenes" / "default.toml", cache / "default",
            {"render": {"models": ["bssrdf"], "lights": ["point"], "geometries": ["high"]}}, env)
    for name, r in res.items():
        for sub, rr in ([(name, r)] if "totals" in r else r.items()):
            print(sub, rr["totals"], rr.get("against_monte_carlo", ""))
            for node, im in rr.get("images", {}).items():
                print("  ", node, im)
    save_labelled(args.out, args.label, res)


if __name__ == "__main__":
    main()
