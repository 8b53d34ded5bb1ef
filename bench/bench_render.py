"""Seconds per 800 x 800 BRDF image, per model and light, on a ~1M and a ~17k-triangle head.

Meshes: the Lee Perry-Smith scan (17,684 triangles, the thesis's ~16,750-triangle "low"
stand-in) and its Loop subdivision to ~1.1M triangles (stages.mesh_prep.make_high; the
"high" stand-in, without displacement).  When the shared data or the mesh stage is missing,
icospheres of 20,480 and 1,310,720 triangles stand in (the JSON says which).
Also measures Embree's rays/s here (closest-hit and occlusion, random rays through the
high mesh) and the share of visibility / shadows / shading in each image.

    python bench/bench_render.py [--out bench/results/render.json] [--size 800]
        [--models lafortune,hk93,asperity] [--lights point,area,directional,environment]

Numbers on a shared 2-core machine are noisy; run it alone for figures to quote.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from dermis.pipeline.cl import get_env  # noqa: E402
from dermis.pipeline.config import CameraConfig, LightConfig  # noqa: E402
from dermis.physics.visibility import Visibility  # noqa: E402
from dermis.stages.render import render  # noqa: E402

SHARED = REPO.parent / "shared" / "data" / "lps_head" / "LeePerrySmith_cm.obj"

# The thesis's four lights (docs/physics.md §6; positions as in scenes/default.toml, relative to
# the face centre).
def _lights(centre: np.ndarray) -> dict:
    c = centre
    key = tuple(float(x) for x in c + np.array([350.0, 450.0, 600.0]))
    return {
        "point": [LightConfig(name="point", type="point", position=key, intensity=(4e5,) * 3)],
        "area": [LightConfig(name="area", type="disc", position=key, radius=70.0,
                             direction=(0.35, 0.45, 0.6), intensity=(4e5,) * 3, samples=16)],
        "directional": [LightConfig(name="dir_left", type="directional",
                                    direction=(-0.6, 0.3, 0.75), intensity=(0.6,) * 3),
                        LightConfig(name="dir_right", type="directional",
                                    direction=(0.6, 0.3, 0.75), intensity=(0.6,) * 3)],
        "environment": [LightConfig(name="sunset", type="environment", samples=16)],
    }


def _meshes():
    """(name, mesh, source note) for the low and high geometry."""
    try:
        from dermis.stages.mesh_prep import make_high
        from dermis.stages.scan_io import load_scan
        if not SHARED.is_file():
            raise FileNotFoundError(SHARED)
        low = load_scan(SHARED, units="cm")
        high = make_high(low, target_triangles=1_000_000, scheme="loop")
        return [("low", low, "Lee Perry-Smith scan"),
                ("low_bump", low, "LPS + synthetic 4096^2 albedo/bump maps, bump='sharp'"),
                ("high", high, "LPS, Loop-subdivided")]
    except Exception as exc:  # the bench must run on a bare checkout too
        from render_fixtures import icosphere
        note = f"icosphere stand-in ({type(exc).__name__}: {exc})"
        return [("low", icosphere(100.0, 5), note), ("high", icosphere(100.0, 8), note)]


def _synthetic_maps(resolution: int = 4096):
    """BakedMaps of the thesis's size (4096^2) with a smooth random bump: timing stand-in."""
    from scipy.ndimage import zoom
    from dermis.pipeline.artifacts import BakedMaps
    rng = np.random.default_rng(1)
    bump = zoom(rng.random((64, 64)).astype(np.float32), resolution / 64, order=1)
    albedo = np.full((resolution, resolution, 3), (200, 150, 130), np.uint8)
    return BakedMaps(albedo_srgb=albedo, bump=bump, bump_blur=bump,
                     coverage=np.ones(bump.shape, bool), bump_min_mm=0.0, bump_range_mm=0.5,
                     blur_sigma_px=0.0)


def _camera(mesh, size: int) -> CameraConfig:
    """Frame the head like the thesis figures: the top 330 mm of the mesh (a face is ~300 mm
    tall, docs/physics.md "Conventions") seen from 900 mm along +z."""
    v = np.asarray(mesh.vertices)
    lo, hi = v.min(0), v.max(0)
    extent = min(330.0, hi[1] - lo[1])
    front = np.array([(lo[0] + hi[0]) / 2, hi[1] - extent / 2, hi[2]])
    fov = float(np.degrees(2 * np.arctan(0.5 * extent / 900.0)))
    return CameraConfig(position=tuple(front + [0, 0, 900.0]), look_at=tuple(front),
                        fov_deg=fov, width=size, height=size)


def _embree_rays_per_second(vis: Visibility, mesh, n: int = 2_000_000) -> dict:
    rng = np.random.default_rng(0)
    v = np.asarray(mesh.vertices)
    lo, hi = v.min(0), v.max(0)
    o = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = time.perf_counter()
    vis.intersect(o, d)
    closest = n / (time.perf_counter() - t)
    t = time.perf_counter()
    vis.occluded(o, d, d, np.full(n, np.inf, np.float32))
    occl = n / (time.perf_counter() - t)
    return {"closest_hit_rays_per_s": closest, "occlusion_rays_per_s": occl, "rays": n}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "render.json"))
    ap.add_argument("--size", type=int, default=800)
    ap.add_argument("--models", default="lafortune,hk93,asperity")
    ap.add_argument("--lights", default="point,area,directional,environment")
    ap.add_argument("--device", default=None)
    args = ap.parse_args(argv)

    env = get_env(args.device)
    from dermis.stages.brdf_models import AsperityParams
    results = {"machine": platform.processor() or platform.machine(), "device": env.description,
               "size": args.size, "note": "shared 2-core machine: noisy", "meshes": {}}
    for gname, mesh, note in _meshes():
        t = time.perf_counter()
        vis = Visibility(mesh.vertices, mesh.faces)
        build = time.perf_counter() - t
        cam = _camera(mesh, args.size)
        extra = {}
        if gname == "low_bump" and mesh.uv is not None:
            extra = {"maps": _synthetic_maps(), "bump": "sharp"}
        lights = _lights(np.asarray(cam.look_at))
        rec = {"source": note, "triangles": int(len(mesh.faces)), "scene_build_s": build,
               "embree": _embree_rays_per_second(vis, mesh), "images": {}}
        print(f"[{gname}] {note}: {len(mesh.faces):,} triangles, Embree build {build:.2f} s, "
              f"{rec['embree']['closest_hit_rays_per_s'] / 1e6:.2f} M closest / "
              f"{rec['embree']['occlusion_rays_per_s'] / 1e6:.2f} M occlusion rays/s")
        # warm-up: compile every kernel variant outside the timings
        for model in args.models.split(","):
            params = AsperityParams(base="hk93") if model == "asperity" else None
            render(mesh, lights["point"], model, params, replace(cam, width=16, height=16),
                   visibility=vis, cl_env=env, **extra)
        for lname in args.lights.split(","):
            for model in args.models.split(","):
                params = AsperityParams(base="hk93") if model == "asperity" else None
                res = render(mesh, lights[lname], model, params, cam, visibility=vis, cl_env=env,
                             **extra)
                tm = res.timings
                busy = tm["visibility"] + tm["shadows"] + tm["shading"]
                row = {**tm, "shadow_rays": res.info["shadow_rays"],
                       "shadow_rays_per_s": res.info["shadow_rays"] / max(tm["shadows"], 1e-9),
                       "coverage": float(res.mask.mean()),
                       "share": {k: tm[k] / busy for k in ("visibility", "shadows", "shading")}}
                rec["images"][f"{model}/{lname}"] = row
                print(f"  {model:10s} {lname:12s} {tm['total']:6.2f} s  (vis {tm['visibility']:.2f}"
                      f", shadows {tm['shadows']:.2f} (sampling {tm['light_sampling']:.2f}), shading {tm['shading']:.2f}, kernels "
                      f"{tm['kernel_seconds']:.2f}; {res.info['shadow_rays'] / 1e6:.2f} M shadow "
                      f"rays, coverage {row['coverage']:.2f})")
        results["meshes"][gname] = rec
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out}")
    return results


if __name__ == "__main__":
    main()
