"""Peak memory of render runs against the load-time estimate (``pipeline/resources.py``
``estimate_memory``), and the fit of its per-pixel and per-light-sample costs.

Each measured run is its own process: ``dermis run`` of the quick scene (scenes/quick.toml)
cut to one geometry (the high mesh) and the given models and lighting conditions, at a square
camera of ``size`` pixels, with the meshes, sample points and layer profiles already cached
and every node that grows with the image recomputed (visibility, render, irradiance, bssrdf,
images).  The peak is the process's maximum resident set size (``getrusage`` ru_maxrss),
threads and the OpenCL (PoCL) runtime included, so it is what the machine must hold.

Each configuration also runs once at the smallest size with an empty PoCL kernel cache
(``POCL_CACHE_DIR``): a first run compiles its OpenCL kernels, which raises the peak.

The fit: per configuration, peak = base + pixels x cost (least squares over the sizes with
the kernels cached, and the slope between the two largest).  The estimate's constants per
camera sample and per light sample (``pipeline/resources.py``) are set above these costs:
at spp 4 a pixel draws 4 light samples under the point light and 16 under the disc.
``bench/results/memory_estimate.json`` holds the runs, the fits and the estimate of every
run next to its peak (``--reestimate`` recomputes the estimates of the stored runs).

    python3 bench/bench_memory_estimate.py [--sizes 64,256,512] [--cache DIR]
        [--out bench/results/memory_estimate.json] [--reestimate]

``--light-samples 256,1024,2048`` instead measures what a requested light sample costs where
the rendered surface fills the frame (a close-up of the face, ``CLOSEUP``: every pixel's
camera samples hit, so nearly every sample a pixel requests is drawn above the horizon and
stored): BRDF and BSSRDF runs under the sunset at one size, the light's sample count varied;
the slope of the peak over the requested samples per pixel is the estimate's per-sample
cost (``pipeline/resources.py`` LIGHT_SAMPLE_BYTES), stored as "light_samples" in --out
beside the other runs.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

from dermis.pipeline import api
from dermis.pipeline.config import load_scene
from dermis.pipeline.resources import estimate_memory, light_samples_per_pixel

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "scenes" / "quick.toml"
DEFAULT_CACHE = Path(tempfile.gettempdir()) / "dermis-bench-memory"
VENICE = ROOT / "scenes" / "assets" / "env_sunset" / "venice_sunset_1k.hdr"   # 1024 x 512
# Recomputed in every measured run: the nodes whose memory grows with the image.
FORCED = ("visibility", "render", "irradiance", "bssrdf", "images")
# (name, models, lighting conditions, other settings): light samples per pixel at spp 4 are
# 4 (point), 16 (disc, 16 samples), 16 (environment, 16 samples); "matrix" runs several
# nodes at once (two at a time, the default --jobs).
CONFIGS = (
    ("brdf_point", ["lafortune"], ["point"], {}),
    ("brdf_area", ["lafortune"], ["area"], {}),
    ("brdf_sunset", ["lafortune"], ["sunset"], {}),
    ("bssrdf_point", ["bssrdf"], ["point"], {}),
    ("bssrdf_area", ["bssrdf"], ["area"], {}),
    ("bssrdf_sunset", ["bssrdf"], ["sunset"], {}),
    ("bssrdf_sunset_dense", ["bssrdf"], ["sunset"], {"bssrdf": {"point_density": 0.02}}),
    ("bssrdf_venice", ["bssrdf"], ["sunset"], {"lights": "venice"}),
    ("brdf_venice", ["lafortune"], ["sunset"], {"lights": "venice"}),
    ("hk93_point", ["hk93"], ["point"], {}),
    ("low_bump_256", ["lafortune"], ["point"], {"render": {"geometries": ["low_bump"]},
                                                "bake": {"resolution": 256}}),
    ("low_bump_1024", ["lafortune"], ["point"], {"render": {"geometries": ["low_bump"]},
                                                 "bake": {"resolution": 1024}}),
    ("matrix", ["lafortune", "hk93", "bssrdf"], ["point", "area", "sunset"], {}),
)


# A close-up of the quick scene's face: the surface fills the frame (measured coverage 1.0).
CLOSEUP = {"fov_deg": 5.0}


def overrides(size: int, models, lights, cache_root: Path, extra: dict) -> dict:
    """The quick scene cut to one geometry, ``models`` and ``lights``, at size x size."""
    over = {"camera": {"width": size, "height": size},
            "render": {"models": list(models), "lights": list(lights), "geometries": ["high"]},
            "output": {"previews": False, "output_dir": str(cache_root / "out")}}
    for table, values in extra.items():
        if table == "light_samples":   # the disc's and the environment's sample count
            lights = tomllib.loads(QUICK.read_text())["lights"]
            for light in lights:
                if light["type"] in ("disc", "environment"):
                    light["samples"] = int(values)
            over["lights"] = lights
        elif table == "lights":   # the sunset light with the default scene's 1k HDR map
            lights = tomllib.loads(QUICK.read_text())["lights"]
            for light in lights:
                if light["type"] == "environment":
                    light["map"] = str(VENICE)
            over["lights"] = lights
        else:
            over.setdefault(table, {}).update(values)
    return over


def child(spec: dict) -> None:
    """In a fresh process: run the scene of ``spec``; print the peak RSS (bytes) as JSON."""
    scene = load_scene(QUICK, overrides=spec["overrides"])
    t0 = time.perf_counter()
    for until in spec.get("prepare", ()):
        api.run(scene, cache=spec["cache"], until=until, export=False)
    if not spec.get("prepare"):
        from dermis.pipeline.plan import build_graph
        stages = {node.stage for node in build_graph(scene)[0].values()}
        api.run(scene, cache=spec["cache"], force=[f for f in FORCED if f in stages])
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024   # KiB on Linux
    print(json.dumps({"peak_bytes": peak, "seconds": time.perf_counter() - t0}))


def measure(spec: dict, cold: bool = False) -> dict:
    """Run ``spec`` in a fresh process; ``cold``: with an empty PoCL kernel cache, so the run
    compiles its OpenCL kernels (as a first run does)."""
    env = os.environ.copy()
    with tempfile.TemporaryDirectory() as kcache:
        if cold:
            env["POCL_CACHE_DIR"] = kcache
        out = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)],
                             capture_output=True, text=True, check=False, env=env)
    if out.returncode != 0:
        raise SystemExit(f"child failed ({out.returncode}):\n{out.stderr[-4000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def reestimate(path: Path, cache: Path) -> None:
    """Recompute the estimate of every run in ``path`` with the current estimate_memory (the
    measured peaks stay as they are)."""
    result = json.loads(path.read_text())
    extras = {c[0]: c[3] for c in CONFIGS}
    for r in result["runs"]:
        extra = (extras.get(r["config"], {}) if r["config"] != "triangles"
                 else {"mesh": {"high_triangles": r["high_triangles"]}})
        scene = load_scene(QUICK, overrides=overrides(r["size"], r["models"], r["lights"],
                                                      cache, extra))
        r["estimate_mb"] = max((b for _, _, b in estimate_memory(scene)), default=0) / 2**20
    result["estimate_is_upper_bound"] = all(r["estimate_mb"] >= r["peak_mb"]
                                            for r in result["runs"])
    ratios = [r["estimate_mb"] / r["peak_mb"] for r in result["runs"]]
    result["estimate_over_peak"] = [min(ratios), max(ratios)]
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: result[k] for k in ("estimate_is_upper_bound", "estimate_over_peak")}))


def light_sample_study(cache: Path, size: int, counts: list[int], out: Path) -> dict:
    """Peaks of close-up BRDF and BSSRDF runs under the sunset at ``counts`` light samples,
    their slope per requested light sample per pixel, and the estimate of each run."""
    rows, fits = [], {}
    for kind, models in (("brdf", ["lafortune"]), ("bssrdf", ["bssrdf"])):
        for n in counts:
            extra = {"camera": CLOSEUP, "light_samples": n}
            over = overrides(size, models, ["sunset"], cache, extra)
            over["camera"].update(CLOSEUP)
            prepare = ["mesh_high"] + (["samples", "profiles"] if kind == "bssrdf" else [])
            measure({"overrides": over, "cache": str(cache), "prepare": prepare})
            res = measure({"overrides": over, "cache": str(cache)})
            scene = load_scene(QUICK, overrides=over)
            row = {"kind": kind, "models": models, "size": size, "pixels": size * size,
                   "spp": scene.render.spp, "light_samples": n,
                   "light_samples_per_pixel": light_samples_per_pixel(scene),
                   "peak_mb": res["peak_bytes"] / 2**20,
                   "estimate_mb": max(b for _, _, b in estimate_memory(scene)) / 2**20,
                   "seconds": res["seconds"], "load": os.getloadavg()[0]}
            print(json.dumps(row), flush=True)
            rows.append(row)
        mine = [r for r in rows if r["kind"] == kind]
        lpp = np.array([r["light_samples_per_pixel"] for r in mine], float)
        peak = np.array([r["peak_mb"] for r in mine], float) * 2**20
        slope = np.polyfit(lpp * size * size, peak, 1)[0]
        fits[kind] = {"bytes_per_requested_light_sample": float(slope),
                      "bytes_between_largest": float((peak[-1] - peak[-2])
                                                     / ((lpp[-1] - lpp[-2]) * size * size))}
    study = {"what": "close-up (the surface fills the frame), sunset, light sample count "
                     "varied at one size", "camera": CLOSEUP, "runs": rows, "fits": fits,
             "estimate_is_upper_bound": all(r["estimate_mb"] >= r["peak_mb"] for r in rows)}
    result = json.loads(out.read_text()) if out.is_file() else {}
    result["light_samples"] = study
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(fits, indent=1))
    return study


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--sizes", default="64,256,512")
    ap.add_argument("--check", default="1024", help="sizes run to check the extrapolation "
                    "(not fitted)")
    ap.add_argument("--check-configs", default="brdf_point,brdf_area,bssrdf_area,matrix")
    ap.add_argument("--configs", default=",".join(c[0] for c in CONFIGS))
    ap.add_argument("--triangles", default="60000,250000",
                    help="high-mesh triangle counts measured at the smallest size (BRDF, point)")
    ap.add_argument("--cache", default=str(DEFAULT_CACHE))
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "memory_estimate.json"))
    ap.add_argument("--reestimate", action="store_true",
                    help="keep the measured runs of --out, recompute their estimates")
    ap.add_argument("--light-samples", default="",
                    help="comma-separated light sample counts of the close-up study")
    ap.add_argument("--light-samples-size", type=int, default=64)
    args = ap.parse_args()
    if args.child:
        child(json.loads(args.child))
        return
    if args.light_samples:
        light_sample_study(Path(args.cache), args.light_samples_size,
                           [int(n) for n in args.light_samples.split(",")], Path(args.out))
        return
    if args.reestimate:
        reestimate(Path(args.out), Path(args.cache))
        return
    cache = Path(args.cache)
    sizes = [int(s) for s in args.sizes.split(",")]
    configs = [c for c in CONFIGS if c[0] in args.configs.split(",")]
    runs = []

    def one(name, models, lights, size, extra, fitted=True, cold=False):
        over = overrides(size, models, lights, cache, extra)
        prepare = ["mesh_high"] + (["bake"] if "low_bump" in str(extra) else []) + (
            ["samples", "profiles"] if "bssrdf" in models else [])
        measure({"overrides": over, "cache": str(cache), "prepare": prepare})
        res = measure({"overrides": over, "cache": str(cache)}, cold=cold)
        scene = load_scene(QUICK, overrides=over)
        est = max((b for _, _, b in estimate_memory(scene)), default=0)
        row = {"config": name, "models": models, "lights": lights, "size": size,
               "pixels": size * size, "spp": scene.render.spp,
               "light_samples_per_pixel": light_samples_per_pixel(scene),
               "high_triangles": scene.mesh.high_triangles,
               "kernels": "compiled" if cold else "cached", "fitted": fitted and not cold,
               "peak_mb": res["peak_bytes"] / 2**20, "estimate_mb": est / 2**20,
               "seconds": res["seconds"], "load": os.getloadavg()[0]}
        print(json.dumps(row), flush=True)
        runs.append(row)

    for name, models, lights, extra in configs:
        one(name, models, lights, sizes[0], extra, cold=True)    # a first run: kernels compile
        for size in sizes:
            one(name, models, lights, size, extra)
    checks = [c for c in CONFIGS if c[0] in args.check_configs.split(",")]
    for size in [int(s) for s in args.check.split(",") if s]:
        for name, models, lights, extra in checks:
            one(name, models, lights, size, extra, fitted=False)
    for tris in [int(t) for t in args.triangles.split(",") if t]:
        one("triangles", ["lafortune"], ["point"], sizes[0], {"mesh": {"high_triangles": tris}})
    fits = {}
    for name, _, _, _ in configs:
        rows = [r for r in runs if r["config"] == name and r["fitted"]]
        if len(rows) >= 2:
            px = np.array([r["pixels"] for r in rows], float)
            mb = np.array([r["peak_mb"] for r in rows], float)
            slope, icpt = np.polyfit(px, mb * 2**20, 1)
            last = (mb[-1] - mb[-2]) * 2**20 / (px[-1] - px[-2])
            fits[name] = {"bytes_per_pixel": slope, "base_mb": icpt / 2**20,
                          "bytes_per_pixel_between_largest": last,
                          "light_samples_per_pixel": rows[0]["light_samples_per_pixel"],
                          "spp": rows[0]["spp"]}
    tri = [r for r in runs if r["config"] == "triangles" and r["fitted"]]
    if len(tri) >= 2:
        fits["triangles"] = {"bytes_per_triangle": float(np.polyfit(
            [r["high_triangles"] for r in tri], [r["peak_mb"] * 2**20 for r in tri], 1)[0])}
    ratios = [r["estimate_mb"] / r["peak_mb"] for r in runs]
    result = {"what": " ".join(__doc__.split("\n\n")[0].split()),
              "machine_cores": os.cpu_count(),
              "runs": runs, "fits": fits,
              "estimate_is_upper_bound": all(r["estimate_mb"] >= r["peak_mb"] for r in runs),
              "estimate_over_peak": [min(ratios), max(ratios)]}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(fits, indent=1))


if __name__ == "__main__":
    main()
