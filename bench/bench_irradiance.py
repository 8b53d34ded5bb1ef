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

Writes (merging) bench/results/irradiance.json under ``--label``.  Timings on the shared
2-core machine move with the other jobs (``loadavg`` beside each).
"""
from __future__ import annotations

import argparse
import glob
import json
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
    args = ap.parse_args()
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


if __name__ == "__main__":
    main()
