"""The BSSRDF irradiance pass (stages/irradiance.py, lighting/irradiance.py ``irradiance``) per
mesh and light: wall and CPU seconds, the machine's load, and the estimate's noise.

Reads the meshes, sample points and scene of an earlier ``bench_bssrdf.py`` run (its
``--cache``, default /tmp/dermis-bench-bssrdf), builds the Embree scene once per mesh and runs
the pass as the stage does (64 samples, entry transmittance, the scene's seed) with seeds 0
and 1.  Noise: the relative RMS difference of the two seeds' point luminance / sqrt 2 (points
above 1e-3 of the maximum), so a change of the sampling code can be checked to leave the
estimator's variance where it was; ``mean_luminance`` checks the mean.

    python bench/bench_irradiance.py [--cache DIR] [--label after] [--meshes mesh_high,mesh_low]
                                     [--lights area,sunset] [--chunks 65536,8192,4096]
    python bench/bench_irradiance.py --halves [--label halves]

``--halves``: the pipeline's estimator (``irradiance(..., halves=True)``: two independent
halves, the environment's mixture and control variate) against the plain one (one jittered
set, the product strategy) on the default scene's high-mesh points (made here through the
pipeline, cache /tmp/dermis-bench-irradiance), under the disc light and the Venice sunset:
on 20,000 random points against 2 x 1,024 plain samples, over 4 seeds, the relative RMSE,
the bias of the mean and the halves' own noise estimate; on all points, CPU and wall
seconds, medians of 3 interleaved repeats.

Writes (merging) bench/results/irradiance.json under ``--label``.  Timings on the shared
2-core machine move with the other jobs (``loadavg`` beside each).
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os
import time
from pathlib import Path

import numpy as np

from labelled import save_labelled

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/tmp/dermis-bench-bssrdf")
    ap.add_argument("--label", default="after")
    ap.add_argument("--meshes", default="mesh_high,mesh_low")
    ap.add_argument("--lights", default="point,area,dir_left+dir_right,sunset")
    ap.add_argument("--chunks", default="", help="also time these chunk sizes (seed 0)")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "irradiance.json"))
    ap.add_argument("--halves", action="store_true", help="the halves estimator against the "
                    "plain one (module docstring)")
    args = ap.parse_args()
    if args.halves:
        save_labelled(args.out, args.label, halves())
        return
    import dermis
    from dermis.pipeline import artifacts
    from dermis.pipeline.config import BssrdfConfig, load_scene
    from dermis.lighting.emitters import SamplingOptions
    from dermis.lighting.irradiance import irradiance
    from dermis.rendering.color import LUMINANCE
    from dermis.lighting.visibility import Visibility
    from dermis.optics.transmittance import Transmittance
    root = Path(args.cache).resolve()
    ld = lambda n: artifacts.load(glob.glob(str(root / "cache" / n / "*"))[0])  # noqa: E731
    scene = load_scene(str(root / "scene.toml"))
    cfg = BssrdfConfig()
    T = Transmittance(scene.optics.layers[0].eta / scene.optics.eta_above, cfg.surface_reflection)
    res = {"dermis": str(Path(dermis.__file__).parent), "samples": cfg.irradiance_samples,
           "loadavg_start": list(os.getloadavg()),
           "note": "2-core shared machine; wall seconds move with the load, CPU seconds less"}
    for mesh_node in args.meshes.split(","):
        mesh, pts = ld(mesh_node), ld(f"samples-{mesh_node}")
        vis = Visibility(mesh.vertices, mesh.faces)
        for label in args.lights.split(","):
            lights = [l for l in scene.lights if l.name in label.split("+")]
            run = lambda seed, sl=slice(None), **kw: irradiance(  # noqa: E731
                pts.positions[sl], pts.normals[sl], lights, vis.occluded,
                seed=seed, options=SamplingOptions(samples=cfg.irradiance_samples),
                transmittance=T, **kw)
            run(0, slice(0, 1000))  # warm: the environment map's tables, first calls
            entry = {"points": int(len(pts.positions))}
            lum = []
            for seed in (0, 1):
                la, t0, c0 = os.getloadavg(), time.perf_counter(), time.process_time()
                E = run(seed)
                entry[f"seed{seed}"] = {"wall_s": round(time.perf_counter() - t0, 3),
                                        "cpu_s": round(time.process_time() - c0, 3),
                                        "loadavg": [round(x, 2) for x in la]}
                lum.append(E @ LUMINANCE)
            a, b = lum
            m = 0.5 * (a + b)
            ok = m > 1e-3 * m.max()
            entry["rel_noise"] = float(np.sqrt(np.mean(((a - b)[ok] / m[ok]) ** 2) / 2))
            entry["mean_luminance"] = [float(a.mean()), float(b.mean())]
            for chunk in [int(c) for c in args.chunks.split(",") if c]:
                la, t0, c0 = os.getloadavg(), time.perf_counter(), time.process_time()
                run(0, chunk=chunk)
                entry.setdefault("chunk", {})[str(chunk)] = {
                    "wall_s": round(time.perf_counter() - t0, 3),
                    "cpu_s": round(time.process_time() - c0, 3),
                    "loadavg": [round(x, 2) for x in la]}
            res[f"{mesh_node}/{label}"] = entry
            print(mesh_node, label, json.dumps(entry), flush=True)
    res["loadavg_end"] = list(os.getloadavg())
    save_labelled(args.out, args.label, res)


def halves(points: int = 20000, seeds: int = 4, reps: int = 3) -> dict:
    """The halves estimator against the plain one (module docstring, ``--halves``)."""
    from dermis.lighting.emitters import SamplingOptions
    from dermis.lighting.irradiance import irradiance
    from dermis.lighting.visibility import Visibility
    from dermis.optics.transmittance import Transmittance
    from dermis.pipeline import api, artifacts
    from dermis.pipeline.config import load_scene
    scene = load_scene(None, overrides={"render": {"models": ["bssrdf"], "geometries": ["high"],
                                                   "lights": ["area", "sunset"]}, "views": []})
    summary = api.run(scene, cache="/tmp/dermis-bench-irradiance", until="samples", export=False)
    got = {rep.id: rep.path for rep in summary.nodes}
    mesh, pts = artifacts.load(got["mesh_high"]), artifacts.load(got["samples-mesh_high"])
    vis = Visibility(mesh.vertices, mesh.faces)
    T = Transmittance(scene.optics.layers[0].eta / scene.optics.eta_above,
                      scene.bssrdf.surface_reflection)
    S = scene.bssrdf.irradiance_samples
    sel = np.random.default_rng(1).choice(len(pts.positions), points, replace=False)
    out = {"code": _commit(), "samples": S, "points": int(len(pts.positions)),
           "subset": points, "seeds": seeds, "reps": reps, "loadavg_start": list(os.getloadavg())}
    groups = dict(scene.light_groups())
    for label in ("area", "sunset"):
        lights = groups[label]

        def run(seed, samples=S, sl=sel, halves=False):
            return irradiance(pts.positions[sl], pts.normals[sl], lights, vis.occluded,
                              seed=seed, options=SamplingOptions(samples=samples),
                              transmittance=T, halves=halves)
        ref = np.mean([run(1000 + k, 1024) for k in range(2)], axis=0).astype(np.float64)
        ms = float((ref ** 2).mean())
        entry = {}
        for name, hv in (("plain", False), ("halves", True)):
            err, own, bias = [], [], []
            for k in range(seeds):
                r = run(k, halves=hv)
                e = (r[0] if hv else r).astype(np.float64)
                err.append(float(((e - ref) ** 2).mean() / ms))
                bias.append(float((e - ref).mean() / ref.mean()))
                if hv:
                    own.append(float((r[1].astype(np.float64) ** 2).mean() / ms))
            entry[name] = {"rel_rmse": math.sqrt(np.mean(err)), "rel_bias": float(np.mean(bias)),
                           "own_rel_noise": math.sqrt(np.mean(own)) if own else None}
        times = {"plain": [], "halves": []}
        for rep in range(reps):
            for name, hv in (("plain", False), ("halves", True)):
                t0, c0 = time.perf_counter(), time.process_time()
                run(rep, sl=slice(None), halves=hv)
                times[name].append((time.perf_counter() - t0, time.process_time() - c0))
        for name, tt in times.items():
            entry[name]["wall_s"] = float(np.median([t[0] for t in tt]))
            entry[name]["cpu_s"] = float(np.median([t[1] for t in tt]))
        out[label] = entry
        print(label, json.dumps(entry), flush=True)
    out["loadavg_end"] = list(os.getloadavg())
    return out


def _commit() -> str:
    import subprocess
    try:
        return subprocess.run(["git", "-C", str(REPO), "log", "-1", "--format=%h %s"],
                              capture_output=True, text=True, check=True).stdout.strip()[:80]
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


if __name__ == "__main__":
    main()
