"""Noise of the environment-lit images: the default scene under the sunset, per model, against a
converged render.

Setup: the default scene (the Lee Perry-Smith scan, ``scenes/default.toml``), its high mesh, the
Venice sunset alone, the scene's camera at 200 x 200 pixels (the whole head, so the scalp and
forehead where the Lafortune lobes speckle are in frame, and the cheeks and neck lit by the sun
and the sky), the scene's ``[render] spp`` and light samples.  The default scene rather than the
quick one: the speckle comes from the Venice map's bright sky behind the head seen in the
grazing glossy lobes of the scalp; the procedural sunset's sky is dim and smooth there.  A pixel
of the 200 x 200 image averages the same number of camera and light samples as one of the
800 x 800 image, so its noise is the default image's per-pixel noise (the structure inside a
pixel is coarser).

Per model (Lafortune, HK93, the asperity term on its scene base, the BSSRDF): ``--seeds``
renders at the default settings (seeds ``mesh.seed + k``) and a converged render: ``--pieces``
renders of ``--piece-samples`` light samples per pixel each (seeds 10000 + k), averaged; its
own variance (of the mean, from the pieces' spread) is subtracted from the squared errors, so
the numbers estimate the error against the exact image.  The BSSRDF image is its subsurface
part (the pipeline's ``render-bssrdf`` node of this setup, minus its surface term) plus the
Lafortune-lobes surface term shaded with the same rays as the BRDF models: the light samples
change only that term, as in the pipeline.

Measures over the skin (pixels whose every camera sample hit the head), all channels:

* ``rel_rmse``: sqrt(mean (x - ref)^2 - var_ref) / sqrt(mean ref^2), over pixels, channels and
  seeds (the report's relative RMSE of one image);
* ``pixel_median``, ``pixel_p95``: each pixel's relative RMSE over its channels and the seeds
  (reference variance subtracted), the median and 95th percentile over the skin;
* ``seconds``, ``cpu_seconds``: the shared visibility (camera rays, light sampling, shadow
  rays) of one image and each model's shading, medians over the seeds.

The converged render is kept in ``<cache>/bench_env_noise/`` (``--reuse-reference`` reuses it,
so "before" and "after" are measured against the same one); ``--memory`` also measures the
peak resident memory of a one-piece render with 64x the light samples in a child process.

    python bench/bench_env_noise.py --label before [--seeds 4] [--pieces 64] [--cache DIR]

-> ``bench/results/env_noise.json`` (one entry per ``--label``).
"""
from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
sys.path.insert(0, str(REPO / "bench"))
from labelled import save_labelled  # noqa: E402

SIZE = 200
MODELS = ("lafortune", "hk93", "asperity", "bssrdf")
LABEL = "sunset"


def _scene():
    from dermis.pipeline.config import load_scene
    return load_scene(None, overrides={
        "camera": {"width": SIZE, "height": SIZE},
        "render": {"models": ["lafortune", "hk93", "asperity", "bssrdf"], "lights": [LABEL],
                   "geometries": ["high"]}})


def _inputs(scene, cache):
    """The high mesh, the sunset light(s) and the BSSRDF image's subsurface part."""
    from dermis.pipeline import api, artifacts
    summary = api.run(scene, cache=cache, until="bssrdf", export=False)
    got = {rep.id: rep.path for rep in summary.nodes}
    mesh = artifacts.load(got["mesh_high"])
    lights = dict(scene.light_groups())[LABEL]
    vis = artifacts.load(got[f"visibility-mesh_high-{LABEL}"])
    bssrdf = artifacts.load(got[f"render-bssrdf-{LABEL}-high"]).linear.astype(np.float64)
    return mesh, lights, vis, bssrdf


def _shaders(scene):
    """name -> callable(mesh, samples, env) -> (image (H, W, 3) float64, RenderResult): the BRDF
    models as the render stage builds them, and the BSSRDF's surface term (Lafortune's lobes,
    rho_d = 0, untextured: stages/bssrdf.py _surface_term)."""
    from dermis.models import lafortune
    from dermis.pipeline.registry import model
    from dermis.rendering.options import RenderOptions
    from dermis.rendering.shade import render
    out = {}
    for name in ("lafortune", "hk93", "asperity"):
        m = model(name)
        base = scene.render.asperity_base if m.bases else None
        config = {"optics": scene.optics.to_dict(), "asperity_base": base}
        p = m.scene_params(config, None)
        bp = m.base(base).scene_params(config, None) if base else None

        def shade(mesh, samples, env, m=m, p=p, bp=bp, base=base):
            r = render(mesh, [], m, p, scene.camera,
                       RenderOptions(samples=samples, base=base, base_params=bp), cl_env=env)
            return r.linear.astype(np.float64), r
        out[name] = shade

    def surface(mesh, samples, env):
        r = render(mesh, [], lafortune.MODEL, lafortune.LafortuneParams(rho_d=(0.0, 0.0, 0.0)),
                   scene.camera, RenderOptions(samples=samples, textured=False), cl_env=env)
        return r.linear.astype(np.float64), r
    out["surface"] = surface
    return out


def _cast(scene, mesh, lights, vis, env, seed, shadow_samples=None):
    from dermis.rendering.cast import cast, retro_lobe
    from dermis.rendering.options import LightSampling, RenderOptions
    retro = retro_lobe(scene)
    sampling = LightSampling(shadow_samples=shadow_samples,
                             **({"retro_fraction": retro["fraction"], "retro_k": retro["k"]}
                                if retro else {}))
    return cast(mesh, lights, scene.camera,
                RenderOptions(spp=scene.render.spp, seed=seed, sampling=sampling, visibility=vis),
                cl_env=env)


def _images(shaders, mesh, samples, env, subsurface, timed=False):
    """model -> image (and model -> (seconds, cpu seconds) of its shading when ``timed``)."""
    imgs, secs = {}, {}
    for name, shade in shaders.items():
        t, c = time.perf_counter(), time.process_time()
        imgs[name], r = shade(mesh, samples, env)
        secs[name] = (time.perf_counter() - t, time.process_time() - c)
    imgs["bssrdf"] = subsurface + imgs["surface"]
    secs["bssrdf"] = secs["surface"]   # the gather does not depend on the light samples
    coverage = r.coverage
    return (imgs, secs, coverage) if timed else (imgs, coverage)


def reference(scene, mesh, lights, vis, env, shaders, subsurface, pieces, piece_samples, path,
              reuse):
    """model -> (mean image, variance of the mean) of ``pieces`` renders of ``piece_samples``
    light samples per pixel (stored in ``path``; the subsurface part is added on load)."""
    if reuse and path.is_file():
        z = np.load(path)
        meta = json.loads(str(z["meta"]))
        ref = {m: (z[f"{m}_mean"], z[f"{m}_var"]) for m in ("lafortune", "hk93", "asperity",
                                                              "surface")}
        print(f"  reference: {path} ({meta['pieces']} x {meta['piece_samples']} samples/pixel)")
    else:
        s1 = s2 = None
        t = time.perf_counter()
        for k in range(pieces):
            samples = _cast(scene, mesh, lights, vis, env, 10000 + k, piece_samples)
            imgs, _ = _images(shaders, mesh, samples, env, subsurface)
            del imgs["bssrdf"]
            if s1 is None:
                s1 = {m: np.zeros_like(v) for m, v in imgs.items()}
                s2 = {m: np.zeros_like(v) for m, v in imgs.items()}
            for m, v in imgs.items():
                s1[m] += v
                s2[m] += v * v
            print(f"  reference piece {k + 1}/{pieces} ({time.perf_counter() - t:.0f} s)",
                  flush=True)
        ref = {}
        for m in s1:
            mean = s1[m] / pieces
            var = np.maximum(s2[m] / pieces - mean * mean, 0.0) * pieces / (pieces - 1)
            ref[m] = (mean, var / pieces)
        meta = {"pieces": pieces, "piece_samples": piece_samples,
                "seconds": time.perf_counter() - t,
                "code": _commit()}
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, meta=json.dumps(meta),
                            **{f"{m}_mean": v[0] for m, v in ref.items()},
                            **{f"{m}_var": v[1] for m, v in ref.items()})
    ref["bssrdf"] = (subsurface + ref["surface"][0], ref["surface"][1])
    return ref, meta


def _commit() -> str:
    try:
        out = subprocess.run(["git", "-C", str(REPO), "log", "-1", "--format=%h %s"],
                             capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--", "*.py",
                                "*.cl", "*.h"], capture_output=True, text=True).stdout.strip()
        return out[:120] + (" (+ uncommitted changes)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def metrics(images: list, ref_mean, ref_var, skin) -> dict:
    """The module docstring's measures of ``images`` (renders of independent seeds)."""
    r, v = ref_mean[skin], ref_var[skin]                    # (P, 3)
    sq = np.mean([(im[skin] - r) ** 2 for im in images], axis=0) - v   # (P, 3)
    rel = float(np.sqrt(max(sq.mean(), 0.0) / (r * r).mean()))
    raw = float(np.sqrt(np.mean([(im[skin] - r) ** 2 for im in images]) / (r * r).mean()))
    px = np.sqrt(np.maximum(sq.mean(axis=1), 0.0) / np.maximum((r * r).mean(axis=1), 1e-30))
    ref_noise = float(np.sqrt(v.mean() / (r * r).mean()))
    # reference-free: the spread between the seeds (unbiased for the variance of one image)
    stack = np.stack([im[skin] for im in images])
    seed_var = stack.var(axis=0, ddof=1) if len(images) > 1 else np.zeros_like(r)
    return {"rel_rmse": rel, "rel_rmse_uncorrected": raw,
            "pixel_median": float(np.median(px)), "pixel_p95": float(np.percentile(px, 95)),
            "pixel_p99": float(np.percentile(px, 99)),
            "rel_noise_between_seeds": float(np.sqrt(seed_var.mean() / (r * r).mean())),
            "rel_bias": float(np.mean(stack.mean(axis=0) - r) / np.mean(r)),
            "reference_rel_noise": ref_noise}


def memory_peak(scene_samples: int, cache) -> dict:
    """Peak resident memory of the pipeline's visibility and Lafortune nodes of this setup with
    ``scene_samples`` light samples on the sunset, in a child process (one render, no pieces)."""
    code = f"""
import resource, sys, time
sys.path.insert(0, {str(REPO / 'bench')!r})
import bench_env_noise as b
from dermis.pipeline import api
from dermis.pipeline.config import load_scene
scene = load_scene(None, overrides={{
    "camera": {{"width": {SIZE}, "height": {SIZE}}},
    "render": {{"models": ["lafortune"], "lights": ["{LABEL}"], "geometries": ["high"]}}}})
import dataclasses
lights = [dataclasses.replace(l, samples={scene_samples}) if l.name == "{LABEL}" else l
          for l in scene.lights]
scene = dataclasses.replace(scene, lights=type(scene.lights)(lights))
t = time.perf_counter()
api.run(scene, cache={str(cache)!r}, until="render", export=False, force=("visibility", "render"))
print(time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if out.returncode:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr else "failed"}
    secs, kb = out.stdout.split()[-2:]
    return {"light_samples_per_pixel": scene_samples, "size": [SIZE, SIZE],
            "seconds": float(secs), "peak_rss_bytes": int(kb) * 1024}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", default="before")
    ap.add_argument("--seeds", type=int, default=4, help="renders at the default settings")
    ap.add_argument("--pieces", type=int, default=64, help="pieces of the converged render")
    ap.add_argument("--piece-samples", type=int, default=256,
                    help="light samples per pixel of one piece")
    ap.add_argument("--reuse-reference", action="store_true")
    ap.add_argument("--memory", action="store_true")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--device", default=None)
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args(argv)
    from dermis.pipeline.api import cache_dir_for
    from dermis.pipeline.cl import get_env
    env = get_env(args.device)
    scene = _scene()
    cache = cache_dir_for(scene, args.cache)
    mesh, lights, vis_default, bssrdf = _inputs(scene, cache)
    from dermis.lighting.visibility import Visibility
    vis = Visibility(mesh.vertices, mesh.faces)
    shaders = _shaders(scene)
    subsurface = bssrdf - shaders["surface"](mesh, vis_default, env)[0]
    ref, ref_meta = reference(scene, mesh, lights, vis, env, shaders, subsurface, args.pieces,
                              args.piece_samples,
                              Path(cache) / "bench_env_noise" / "reference.npz",
                              args.reuse_reference)
    renders = {m: [] for m in MODELS}
    times = {m: [] for m in MODELS}
    vis_times = []
    coverage = None
    for k in range(args.seeds):
        t, c = time.perf_counter(), time.process_time()
        samples = _cast(scene, mesh, lights, vis, env, scene.mesh.seed + k)
        vis_times.append((time.perf_counter() - t, time.process_time() - c))
        imgs, secs, coverage = _images(shaders, mesh, samples, env, subsurface, timed=True)
        for m in MODELS:
            renders[m].append(imgs[m])
            times[m].append(secs[m])
    skin = np.asarray(coverage) >= 1.0
    vis_s = np.median([t[0] for t in vis_times])
    vis_cpu = np.median([t[1] for t in vis_times])
    out = {"setup": {"scene": "default", "mesh": "high", "light": LABEL, "size": [SIZE, SIZE],
                     "spp": scene.render.spp, "light_samples_per_pixel": lights[0].samples,
                     "seeds": args.seeds, "skin_pixels": int(skin.sum())},
           "code": _commit(), "machine": platform.processor() or platform.machine(),
           "device": env.description,
           "reference": {**ref_meta,
                         "samples_per_pixel": ref_meta["pieces"] * ref_meta["piece_samples"]},
           "visibility_seconds": float(vis_s), "visibility_cpu_seconds": float(vis_cpu),
           "models": {}}
    for m in MODELS:
        row = metrics(renders[m], *ref[m], skin)
        row["shading_seconds"] = float(np.median([t[0] for t in times[m]]))
        row["seconds"] = float(vis_s + row["shading_seconds"])
        row["cpu_seconds"] = float(vis_cpu + np.median([t[1] for t in times[m]]))
        out["models"][m] = row
        print(f"  {m:10s} rel RMSE {row['rel_rmse']:.4f}  pixel median {row['pixel_median']:.4f}"
              f"  p95 {row['pixel_p95']:.4f}  bias {row['rel_bias']:+.4f}  "
              f"{row['seconds']:.2f} s ({row['cpu_seconds']:.2f} CPU s)", flush=True)
    if args.memory:
        out["memory"] = {"converged_one_piece": memory_peak(64 * lights[0].samples, cache),
                         "default": memory_peak(lights[0].samples, cache)}
        print("  memory:", out["memory"])
    out["bench_peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    if not args.no_save:
        RESULTS.mkdir(parents=True, exist_ok=True)
        save_labelled(RESULTS / "env_noise.json", args.label, out)
    return out


if __name__ == "__main__":
    main()
