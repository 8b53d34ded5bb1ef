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
* ``negative_channels``: the share of pixel channels below zero (the control variate's);
* ``own_rel_noise``, ``own_noise_ratio``: the images' own noise estimates
  (``RenderedImage.noise``, rendering/halves.py): sqrt(mean noise^2) / sqrt(mean ref^2), and
  mean noise^2 over the reference-corrected mean squared error (1: the estimate is the error;
  the BSSRDF's is its surface term's, the part the light samples change);
* ``seconds``, ``cpu_seconds``: the shared visibility (camera rays, light sampling, shadow
  rays) of one image and each model's shading at 200 x 200, medians over the seeds.

Light sampling variants (``--variants``, VARIANTS): ``previous`` (the estimator before the
mixture: fixed product and cosine shares; bit-identical to the "before" entry), ``default``
(the pipeline's: lighting/mixture.py with the Lafortune lobes where the scene renders them,
the control variate of lighting/control.py through rendering/shade.py's non-negative
estimator, a strong sun split off the map, lighting/sun.py), ``mixture`` and
``mixture_whole_map`` (the default before: no control variate; with and without the sun
split), ``whole_map`` (the default, no sun split) and ``joint_net`` (one net for the pixel's
samples instead of one per half, lighting/strata.py).  ``--procedural`` measures under the
procedural sunset instead (its strong sun: lighting/environment.py), the converged render
kept apart.  ``--shares`` sweeps the
lobe and cosine shares; ``--brightness`` the map's sampling weight (luminance, RGB mean, RGB
norm); ``--sample-counts`` measures the default at other light sample counts; ``--cost`` times the visibility and the shading of every variant at
the scene's own 800 x 800 (interleaved, medians); ``--memory`` measures the peak resident
memory of a child that casts and shades this setup with 16 and with 1024 light samples per
pixel in one piece (what the 64x render needs) and the bytes per stored light sample.
``--bssrdf-own K`` measures only the pipeline's BSSRDF image: its own noise estimate (the
surface term's halves and the points' irradiance halves gathered, stages/bssrdf.py) against
its spread over K values of the scene's seed (no converged render needed).
``--own-noise-default`` records every model's own noise estimate at the default scene's
800 x 800 under the sunset and the disc (the per-pixel noise a default run has).

The converged render is kept in ``<cache>/bench_env_noise/`` (``--reuse-reference`` reuses it,
so "before" and "after" are measured against the same one).

    python bench/bench_env_noise.py --label before [--seeds 4] [--pieces 64] [--cache DIR]
    python bench/bench_env_noise.py --label after --reuse-reference --seeds 8 \
        --variants previous,default,control_variate --shares --cost --memory
    python bench/bench_env_noise.py --label after_nets --reuse-reference --seeds 8 \
        --variants previous,default,joint_net,control_variate --brightness --shares \
        --sample-counts 32,64,128,256 --cost --memory

-> ``bench/results/env_noise.json`` (one entry per ``--label``).
"""
from __future__ import annotations

import argparse
import math
import json
import os
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


def _scene(full: bool = False, seed: int | None = None):
    """The setup's scene (``full``: at the default scene's own camera size; ``seed``: the
    scene's ``mesh.seed`` instead of its own)."""
    from dermis.pipeline.config import load_scene
    return load_scene(None, overrides={
        **({} if full else {"camera": {"width": SIZE, "height": SIZE}}),
        **({} if seed is None else {"mesh": {"seed": seed}}),
        "render": {"models": ["lafortune", "hk93", "asperity", "bssrdf"], "lights": [LABEL],
                   "geometries": ["high"]}, "views": []})


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


VARIANTS = {
    # the previous estimator: fixed shares of product and cosine samples (3 + 1 per hit),
    # the block coordinate stratified in 1-D (bit-identical to "before" until the pixel's
    # samples became nets)
    "previous": {"mixture": False, "split_sun": False, "control_variate": False},
    # the pipeline's default (stages/visibility.py)
    "default": {},
    # the mixture without the control variate: the default before rendering/shade.py's
    # non-negative control estimator, with and without the sun split (lighting/sun.py)
    "mixture": {"control_variate": False},
    "mixture_whole_map": {"control_variate": False, "split_sun": False},
    # the default without the sun split, and with the split forced on a weak sun (the Venice
    # sunset's, 0.046 of the light: below the split's threshold, lighting/emitters.py)
    "whole_map": {"split_sun": False},
    "forced_split": {"split_sun": "always"},
    "mixture_forced_split": {"control_variate": False, "split_sun": "always"},
    # one net for the pixel's light samples, not one per half (rendering/halves.py)
    "joint_net": {"independent_halves": False},
}


def _sampling(scene, shadow_samples=None, **over):
    """The light sampling of the pipeline's visibility node for this scene
    (stages/visibility.py), with ``over`` replacing fields (``split_sun``: lighting/emitters.py
    SPLIT_SUN, set by :func:`_cast`)."""
    from dataclasses import fields
    over.pop("split_sun", None)
    from dermis.rendering.options import LightSampling
    from dermis.rendering import cast as cast_mod
    names = {f.name for f in fields(LightSampling)}
    kw = {"control_variate": True}      # the stage's (stages/visibility.py)
    retro = cast_mod.retro_lobe(scene)
    if retro:
        kw.update(retro_fraction=retro["fraction"], retro_k=retro["k"])
    elif "glossy_lobes" in names and cast_mod.glossy_lobes(scene):
        kw["glossy_lobes"] = True
    kw.update(over)
    return LightSampling(shadow_samples=shadow_samples, **kw)


def _cast(scene, mesh, lights, vis, env, seed, shadow_samples=None, variant="default",
          camera=None):
    from dermis.lighting import emitters
    from dermis.rendering.cast import cast
    from dermis.rendering.options import RenderOptions
    sampling = _sampling(scene, shadow_samples, **VARIANTS[variant])
    from dermis.lighting.environment import environment_map
    from dermis.lighting.sun import split_sun
    keep = emitters.SPLIT_SUN
    mode = VARIANTS[variant].get("split_sun", True)
    emitters.SPLIT_SUN = bool(mode)
    sun = split_sun(environment_map(lights[0])) if mode == "always" else None
    share = sun.sun.share if sun is not None else None
    if sun is not None:
        sun.sun.share = 1.0            # split whatever the sun's share of the light
    try:
        return cast(mesh, lights, camera or scene.camera,
                    RenderOptions(spp=scene.render.spp, seed=seed, sampling=sampling,
                                  visibility=vis), cl_env=env)
    finally:
        emitters.SPLIT_SUN = keep
        if sun is not None:
            sun.sun.share = share


def _images(shaders, mesh, samples, env, subsurface, timed=False, noise=None):
    """model -> image (and model -> (seconds, cpu seconds) of its shading when ``timed``);
    ``noise``: a dict filled with model -> the image's own noise estimate (None without)."""
    imgs, secs = {}, {}
    for name, shade in shaders.items():
        t, c = time.perf_counter(), time.process_time()
        imgs[name], r = shade(mesh, samples, env)
        secs[name] = (time.perf_counter() - t, time.process_time() - c)
        if noise is not None:
            est = getattr(r, "noise", None)
            noise[name] = None if est is None else est.astype(np.float64)
    imgs["bssrdf"] = subsurface + imgs["surface"]
    secs["bssrdf"] = secs["surface"]   # the gather does not depend on the light samples
    if noise is not None:             # the subsurface part is held fixed: the surface term's
        noise["bssrdf"] = noise.get("surface")
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
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain",
                                "--untracked-files=no", "--", "*.py", "*.cl", "*.h"],
                               capture_output=True, text=True).stdout.strip()
        return out[:120] + (" (+ uncommitted changes)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def metrics(images: list, ref_mean, ref_var, skin, noises: list | None = None) -> dict:
    """The module docstring's measures of ``images`` (renders of independent seeds) and, with
    their own noise estimates ``noises``, how those compare with the error."""
    r, v = ref_mean[skin], ref_var[skin]                    # (P, 3)
    sq = np.mean([(im[skin] - r) ** 2 for im in images], axis=0) - v   # (P, 3)
    rel = float(np.sqrt(max(sq.mean(), 0.0) / (r * r).mean()))
    raw = float(np.sqrt(np.mean([(im[skin] - r) ** 2 for im in images]) / (r * r).mean()))
    px = np.sqrt(np.maximum(sq.mean(axis=1), 0.0) / np.maximum((r * r).mean(axis=1), 1e-30))
    ref_noise = float(np.sqrt(v.mean() / (r * r).mean()))
    # reference-free: the spread between the seeds (unbiased for the variance of one image)
    stack = np.stack([im[skin] for im in images])
    seed_var = stack.var(axis=0, ddof=1) if len(images) > 1 else np.zeros_like(r)
    every = np.stack([im[np.asarray(skin)] for im in images])
    own = {}
    if noises and all(x is not None for x in noises):
        n2 = float(np.mean([x[skin] ** 2 for x in noises]))
        own = {"own_rel_noise": float(np.sqrt(n2 / (r * r).mean())),
               # the estimate's mean noise^2 over the reference-corrected squared error
               "own_noise_ratio": float(n2 / max(sq.mean(), 1e-300)),
               "own_noise_ratio_seeds": float(n2 / max(seed_var.mean(), 1e-300))}
    return {**own, "rel_rmse": rel, "rel_rmse_uncorrected": raw,
            "pixel_median": float(np.median(px)), "pixel_p95": float(np.percentile(px, 95)),
            "pixel_p99": float(np.percentile(px, 99)),
            "rel_noise_between_seeds": float(np.sqrt(seed_var.mean() / (r * r).mean())),
            "rel_bias": float(np.mean(stack.mean(axis=0) - r) / np.mean(r)),
            "reference_rel_noise": ref_noise,
            "negative_channels": float(np.mean(every < 0)),
            "most_negative_rel": float(min(every.min(), 0.0) / np.median(r))}


def _measure(scene, mesh, lights, vis, env, shaders, subsurface, ref, seeds, variant,
             verbose=True, shadow_samples=None) -> dict:
    """The measures of ``seeds`` renders of ``variant`` (VARIANTS) at the default settings
    (``shadow_samples``: light samples per pixel instead of the light's)."""
    renders = {m: [] for m in MODELS}
    noises = {m: [] for m in MODELS}
    times = {m: [] for m in MODELS}
    vis_times = []
    coverage = None
    for k in range(seeds):
        t, c = time.perf_counter(), time.process_time()
        samples = _cast(scene, mesh, lights, vis, env, scene.mesh.seed + k, shadow_samples,
                        variant=variant)
        vis_times.append((time.perf_counter() - t, time.process_time() - c))
        own = {}
        imgs, secs, coverage = _images(shaders, mesh, samples, env, subsurface, timed=True,
                                       noise=own)
        for m in MODELS:
            renders[m].append(imgs[m])
            noises[m].append(own.get(m))
            times[m].append(secs[m])
    skin = np.asarray(coverage) >= 1.0
    vis_s = np.median([t[0] for t in vis_times])
    vis_cpu = np.median([t[1] for t in vis_times])
    out = {"variant": variant, "sampling": repr(_sampling(scene, **VARIANTS[variant])),
           "split_sun": VARIANTS[variant].get("split_sun", True),
           "skin_pixels": int(skin.sum()), "seeds": seeds,
           "visibility_seconds": float(vis_s), "visibility_cpu_seconds": float(vis_cpu),
           "models": {}}
    for m in MODELS:
        row = metrics(renders[m], *ref[m], skin, noises[m])
        row["shading_seconds"] = float(np.median([t[0] for t in times[m]]))
        row["seconds"] = float(vis_s + row["shading_seconds"])
        row["cpu_seconds"] = float(vis_cpu + np.median([t[1] for t in times[m]]))
        out["models"][m] = row
        if verbose:
            print(f"  {variant:16s} {m:10s} rel RMSE {row['rel_rmse']:.4f}  pixel median "
                  f"{row['pixel_median']:.4f}  p95 {row['pixel_p95']:.4f}  bias "
                  f"{row['rel_bias']:+.4f}  negative {row['negative_channels']:.1e}  own noise "
                  f"{row.get('own_rel_noise', float('nan')):.4f} (ratio "
                  f"{row.get('own_noise_ratio', float('nan')):.3f})", flush=True)
    return out


# The shares swept by --shares: the lobe's scale (lighting/lobes.py LOBE_SHARE_SCALE; 0 = no
# lobe samples) and the cosine share of the rest (lighting/mixture.py COSINE_SHARE).
SHARE_GRID = {"lobe_scale": (0.0, 0.25, 0.5, 1.0, 2.0),
              "cosine_share": (1 / 64, 1 / 32, 1 / 16, 1 / 8)}


def shares(scene, mesh, lights, vis, env, shaders, subsurface, ref, seeds) -> list:
    """Relative RMSE per model over SHARE_GRID, with and without the control variate."""
    from dermis.lighting import mixture
    from dermis.rendering import cast as cast_mod
    keep = (mixture.COSINE_SHARE, cast_mod.LOBE_SHARE_SCALE, cast_mod.LOBE_SHARE_SCALE_CONTROL)
    rows = []
    try:
        for variant in ("mixture", "default"):
            for scale in SHARE_GRID["lobe_scale"]:
                for cos in SHARE_GRID["cosine_share"]:
                    if cos != 1 / 32 and scale not in (0.5, 2.0):
                        continue        # the cosine share at the two chosen lobe scales only
                    mixture.COSINE_SHARE = cos
                    cast_mod.LOBE_SHARE_SCALE = cast_mod.LOBE_SHARE_SCALE_CONTROL = scale
                    r = _measure(scene, mesh, lights, vis, env, shaders, subsurface, ref, seeds,
                                 variant, verbose=False)
                    row = {"variant": variant, "lobe_scale": scale, "cosine_share": cos,
                           **{m: round(v["rel_rmse"], 4) for m, v in r["models"].items()}}
                    rows.append(row)
                    print("  shares", row, flush=True)
    finally:
        (mixture.COSINE_SHARE, cast_mod.LOBE_SHARE_SCALE,
         cast_mod.LOBE_SHARE_SCALE_CONTROL) = keep
    return rows


BRIGHTNESS = ("luminance", "rgb_mean", "rgb_norm")


def brightness(scene, mesh, lights, vis, env, shaders, subsurface, ref, seeds) -> dict:
    """The default variant with the map's sampling weight per pixel (lighting/environment.py
    ``brightness``) replaced by each of BRIGHTNESS."""
    from dermis.lighting.environment import environment_map
    from dermis.rendering.color import LUMINANCE
    emap = environment_map(lights[0])
    keep = (emap.pmf, emap.cdf, getattr(emap, "_prod", None))
    rad = emap.radiance.astype(np.float64)
    sin_t = np.sin((np.arange(emap.height) + 0.5) / emap.height * np.pi)[:, None]
    weights = {"luminance": rad @ np.asarray(LUMINANCE, np.float64),
               "rgb_mean": rad.mean(axis=-1), "rgb_norm": np.sqrt((rad * rad).sum(-1))}
    out = {}
    try:
        for name in BRIGHTNESS:
            w = weights[name] * sin_t
            emap.pmf = (w / w.sum()).ravel()
            emap.cdf = np.cumsum(emap.pmf)
            vars(emap).pop("_prod", None)   # the product tables rebuilt for these weights
            r = _measure(scene, mesh, lights, vis, env, shaders, subsurface, ref, seeds,
                         "default", verbose=False)
            out[name] = {m: round(v["rel_rmse"], 4) for m, v in r["models"].items()}
            print("  brightness", name, out[name], flush=True)
    finally:
        emap.pmf, emap.cdf = keep[:2]
        vars(emap).pop("_prod", None)
        if keep[2] is not None:
            emap._prod = keep[2]
    return out


def sample_counts(scene, mesh, lights, vis, env, shaders, subsurface, ref, seeds,
                  counts) -> dict:
    """Relative RMSE (and the own noise estimate) of the default variant at other light
    sample counts per pixel, with the visibility's CPU seconds at 200 x 200."""
    out = {}
    for n in counts:
        r = _measure(scene, mesh, lights, vis, env, shaders, subsurface, ref, seeds, "default",
                     verbose=False, shadow_samples=n)
        out[str(n)] = {"visibility_cpu_seconds": r["visibility_cpu_seconds"],
                       **{m: {"rel_rmse": round(v["rel_rmse"], 4),
                              "own_rel_noise": round(v.get("own_rel_noise", float("nan")), 4)}
                          for m, v in r["models"].items()}}
        print("  samples", n, out[str(n)], flush=True)
    return out


def bssrdf_noise(cache, seeds: int, env, shaders, ref=None) -> dict:
    """The BSSRDF image's noise from its points' irradiance: the pipeline's subsurface part
    (the ``render-bssrdf`` node minus its surface term) at ``seeds`` values of ``mesh.seed``
    (new points, their irradiance and the gather; the surface term's light samples are
    subtracted out), over the skin: the relative spread between the seeds, and the surface
    term's own noise estimate on the same images for comparison (the two add in quadrature
    to the image's noise).  ``ref``: the converged surface term's mean, for the relative
    measures' denominator (the BSSRDF image's RMS)."""
    parts, own, coverage = [], [], None
    base = _scene().mesh.seed
    for k in range(seeds):
        sc = _scene(seed=base + k)
        mesh, lights, vis_k, bssrdf = _inputs(sc, cache)
        surface, r = shaders["surface"](mesh, vis_k, env)
        parts.append(bssrdf - surface)
        own.append(r.noise.astype(np.float64))
        coverage = r.coverage
    skin = np.asarray(coverage) >= 1.0
    st = np.stack([x[skin] for x in parts])
    image = st.mean(axis=0) + (ref[skin] if ref is not None else 0.0)
    ms = float((image ** 2).mean())
    return {"seeds": seeds,
            "subsurface_rel_noise": float(np.sqrt(st.var(axis=0, ddof=1).mean() / ms)),
            "surface_own_rel_noise": float(np.sqrt(np.mean([x[skin] ** 2 for x in own]) / ms)),
            "subsurface_share_of_image": float(np.sqrt((st.mean(axis=0) ** 2).mean() / ms))}


def bssrdf_own_noise(cache, seeds: int) -> dict:
    """The pipeline's BSSRDF image (``render-bssrdf``) at ``seeds`` values of ``mesh.seed``
    (new points, their irradiance, the gather, the surface term's light samples), over the
    skin (coverage 1, from the visibility's hits): the relative spread of the images between
    the seeds, against their own noise estimates (``RenderedImage.noise``: the surface term's
    halves plus the points' irradiance halves gathered, stages/bssrdf.py), all relative to
    the mean image's RMS.  The spread also holds what the points' placement changes with the
    seed, which the estimate leaves out."""
    from dermis.pipeline import api, artifacts
    base = _scene().mesh.seed
    imgs, noises = [], []
    for k in range(seeds):
        sc = _scene(seed=base + k)
        summary = api.run(sc, cache=cache, until="bssrdf", export=False)
        got = {rep.id: rep.path for rep in summary.nodes}
        im = artifacts.load(got[f"render-bssrdf-{LABEL}-high"])
        imgs.append(im.linear.astype(np.float64))
        noises.append(np.asarray(im.noise, np.float64))
        hits = artifacts.load(got[f"visibility-mesh_high-{LABEL}"])
        skin = np.bincount(hits.pixel, minlength=SIZE * SIZE).reshape(SIZE, SIZE) \
            >= hits.spp
    st = np.stack([x[skin] for x in imgs])
    ms = float((st.mean(axis=0) ** 2).mean())
    return {"seeds": seeds, "skin_pixels": int(skin.sum()),
            "rel_spread_between_seeds": float(np.sqrt(st.var(axis=0, ddof=1).mean() / ms)),
            "own_rel_noise": float(np.sqrt(np.mean([n[skin] ** 2 for n in noises]) / ms))}


def own_noise_default(cache) -> dict:
    """Every model's own noise estimate (``RenderedImage.noise``, the halves) on the default
    scene's main view at its own 800 x 800, high mesh, under the sunset and the disc, as the
    pipeline renders them: relative RMSE over the skin (coverage 1) and the median pixel's
    (the noise's RGB norm over the pixel's).  The estimate's ratio to the true squared error
    was measured at 200 x 200 (1.01-1.03, "split"; BSSRDF "bssrdf_own")."""
    from dermis.pipeline import api, artifacts
    from dermis.pipeline.config import load_scene
    models = ["lafortune", "hk93", "asperity", "bssrdf", "bssrdf_local", "bssrdf_adaptive"]
    labels = ["sunset", "area"]
    scene = load_scene(None, overrides={"render": {"models": models, "lights": labels,
                                                   "geometries": ["high"]}, "views": []})
    got = {rep.id: rep.path for until in ("render", "bssrdf")
           for rep in api.run(scene, cache=cache, until=until, export=False).nodes}
    out = {"size": [scene.camera.width, scene.camera.height], "spp": scene.render.spp}
    for lab in labels:
        vis = artifacts.load(got[f"visibility-mesh_high-{lab}"])
        skin = (np.bincount(vis.pixel, minlength=vis.width * vis.height) >= vis.spp).reshape(
            vis.height, vis.width)
        for m in models:
            im = artifacts.load(got[f"render-{m}-{lab}-high"])
            x, n = im.linear[skin].astype(np.float64), im.noise[skin].astype(np.float64)
            px = np.sqrt((n ** 2).sum(axis=1) / np.maximum((x ** 2).sum(axis=1), 1e-30))
            out[f"{m}-{lab}"] = {"own_rel_noise": float(np.sqrt((n ** 2).mean() / (x ** 2).mean())),
                                 "pixel_median": float(np.median(px)),
                                 "pixel_p95": float(np.percentile(px, 95))}
            print(m, lab, out[f"{m}-{lab}"], flush=True)
        out[f"allocation-{lab}"] = allocation_bound(
            {m: artifacts.load(got[f"render-{m}-{lab}-high"]) for m in models[:3]})
        print("allocation", lab, out[f"allocation-{lab}"], flush=True)
    return out


def allocation_bound(images: dict, box: int = 5) -> dict:
    """What the best per-pixel allocation of the same light samples would give the BRDF images
    sharing them: each pixel's variance is its own estimate's noise^2 averaged over a box x
    box window; n_i proportional to the square root of the images' summed variance (the
    optimum for their sum, Neyman allocation; at least a quarter of the mean) divides pixel
    i's variance by n_i.  Returns per model the variance ratio (uniform / allocated) and the
    relative RMSE it would leave: a bound on what adaptive sampling at the default cost could
    reach, not a render."""
    from scipy.ndimage import uniform_filter
    mask = next(iter(images.values())).mask
    var = {m: np.maximum(uniform_filter((im.noise.astype(np.float64) ** 2).sum(axis=-1),
                                        box)[mask], 0.0)   # the filter's rounding: >= 0
           for m, im in images.items()}
    n = np.sqrt(sum(var.values()))
    n = np.maximum(n / n.mean(), 0.25)
    n /= n.mean()
    out = {"box": box}
    for m, im in images.items():
        gain = float(var[m].sum() / (var[m] / n).sum())
        x = im.linear[mask].astype(np.float64)
        noise = math.sqrt(float((im.noise[mask].astype(np.float64) ** 2).sum(axis=-1).mean()
                                / (x ** 2).sum(axis=-1).mean()))
        out[m] = {"variance_gain": gain, "rel_noise": noise,
                  "rel_noise_allocated": noise / math.sqrt(gain)}
    return out


def spread(scene, mesh, lights, vis, env, shaders, seeds, variants) -> dict:
    """Without a converged render: per variant and BRDF model, the relative noise between
    ``seeds`` renders (the seeds' variance over the skin, relative to their mean image's
    RMS), the images' own noise estimate and the share of negative channels; the median CPU
    seconds of the visibility and shadings of one seed (``--procedural``)."""
    out = {}
    for v in variants:
        imgs = {m: [] for m in ("lafortune", "hk93", "asperity")}
        own = {m: [] for m in imgs}
        cpu = []
        coverage = None
        for k in range(seeds):
            c = time.process_time()
            samples = _cast(scene, mesh, lights, vis, env, scene.mesh.seed + k, variant=v)
            for m in imgs:
                im, r = shaders[m](mesh, samples, env)
                imgs[m].append(im)
                own[m].append(r.noise.astype(np.float64))
                coverage = r.coverage
            cpu.append(time.process_time() - c)
        skin = np.asarray(coverage) >= 1.0
        row = {"cpu_seconds": float(np.median(cpu))}
        for m in imgs:
            st = np.stack([x[skin] for x in imgs[m]])
            ms = float((st.mean(axis=0) ** 2).mean())
            row[m] = {"rel_noise_between_seeds": float(np.sqrt(st.var(axis=0, ddof=1).mean()
                                                                / ms)),
                      "own_rel_noise": float(np.sqrt(np.mean([x[skin] ** 2 for x in own[m]])
                                                     / ms)),
                      "negative_channels": float(np.mean(st < 0))}
        out[v] = row
        print(f"  spread {v:18s}", {m: round(x["rel_noise_between_seeds"], 4)
                                   for m, x in row.items() if m != "cpu_seconds"}, flush=True)
    return out


def cost(scene, mesh, lights, vis, env, reps: int = 3) -> dict:
    """CPU and wall seconds of the shared visibility and of each model's shading at the scene's
    own camera (800 x 800), per VARIANTS entry, interleaved ``reps`` times (medians): what an
    image of the default matrix costs under the sunset.  Each variant's one-time tables are
    built before timing (kept per process, as in a pipeline run)."""
    full = _scene(full=True)
    shaders = _shaders(full)
    out = {v: {"cast": [], **{m: [] for m in shaders}} for v in VARIANTS}
    for v in VARIANTS:             # warm: the tables built once per process
        _cast(full, mesh, lights, vis, env, 999, variant=v)
    for rep in range(reps):
        for v in VARIANTS:
            t, c = time.perf_counter(), time.process_time()
            samples = _cast(full, mesh, lights, vis, env, scene.mesh.seed + rep, variant=v)
            out[v]["cast"].append((time.perf_counter() - t, time.process_time() - c,
                                   samples.info["timings"]["light_sampling"],
                                   samples.info.get("stored_samples", len(samples.weights))))
            for m, shade in shaders.items():
                t, c = time.perf_counter(), time.process_time()
                shade(mesh, samples, env)
                out[v][m].append((time.perf_counter() - t, time.process_time() - c))
    res = {"size": [full.camera.width, full.camera.height], "reps": reps}
    for v, d in out.items():
        cast_rows = np.array(d["cast"])
        row = {"cast_seconds": float(np.median(cast_rows[:, 0])),
               "cast_cpu_seconds": float(np.median(cast_rows[:, 1])),
               "light_sampling_seconds": float(np.median(cast_rows[:, 2])),
               "stored_samples": int(np.median(cast_rows[:, 3]))}
        for m in shaders:
            a = np.array(d[m])
            row[f"{m}_seconds"] = float(np.median(a[:, 0]))
            row[f"{m}_cpu_seconds"] = float(np.median(a[:, 1]))
        row["cast_and_shading_cpu_seconds"] = row["cast_cpu_seconds"] + sum(
            row[f"{m}_cpu_seconds"] for m in shaders if m != "surface")
        res[v] = row
        print(f"  cost {v:16s} cast {row['cast_cpu_seconds']:.2f} CPU s (sampling "
              f"{row['light_sampling_seconds']:.2f} s), cast + 3 BRDF shadings "
              f"{row['cast_and_shading_cpu_seconds']:.2f} CPU s", flush=True)
    return res


def memory_peak(scene_samples: int, cache, variant: str = "default") -> dict:
    """Peak resident memory (VmHWM) of a child process that casts this setup's sunset rays with
    ``scene_samples`` light samples per pixel in one piece and shades Lafortune, and the
    samples it stored: the memory a render with that many samples needs."""
    code = f"""
import sys, time, dataclasses
sys.path.insert(0, {str(REPO / 'bench')!r})
import bench_env_noise as b
from dermis.lighting.visibility import Visibility
from dermis.pipeline.cl import get_env
scene = b._scene()
mesh, lights, vis_default, bssrdf = b._inputs(scene, {str(cache)!r})
del vis_default, bssrdf
env = get_env(None)
vis = Visibility(mesh.vertices, mesh.faces)
shade = b._shaders(scene)["lafortune"]
before = int([l for l in open("/proc/self/status") if l.startswith("VmRSS")][0].split()[1])
t = time.perf_counter()
samples = b._cast(scene, mesh, lights, vis, env, 7, {scene_samples}, {variant!r})
shade(mesh, samples, env)
hwm = int([l for l in open("/proc/self/status") if l.startswith("VmHWM")][0].split()[1])
print(time.perf_counter() - t, before, hwm, len(samples.weights))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if out.returncode:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr else "failed"}
    secs, before, hwm, stored = out.stdout.split()[-4:]
    return {"light_samples_per_pixel": scene_samples, "size": [SIZE, SIZE],
            "seconds": float(secs), "rss_before_bytes": int(before) * 1024,
            "peak_rss_bytes": int(hwm) * 1024, "stored_samples": int(stored)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", default="before")
    ap.add_argument("--variants", default="default",
                    help="comma-separated VARIANTS to measure (previous, default, "
                         "control_variate)")
    ap.add_argument("--seeds", type=int, default=4, help="renders at the default settings")
    ap.add_argument("--pieces", type=int, default=64, help="pieces of the converged render")
    ap.add_argument("--piece-samples", type=int, default=256,
                    help="light samples per pixel of one piece")
    ap.add_argument("--reuse-reference", action="store_true")
    ap.add_argument("--shares", action="store_true", help="sweep SHARE_GRID")
    ap.add_argument("--cost", action="store_true", help="seconds at 800 x 800 per variant")
    ap.add_argument("--brightness", action="store_true",
                    help="the map's sampling weight: luminance, RGB mean, RGB norm")
    ap.add_argument("--sample-counts", default="",
                    help="comma-separated light samples per pixel to measure the default at")
    ap.add_argument("--memory", action="store_true")
    ap.add_argument("--bssrdf-seeds", type=int, default=0,
                    help="the BSSRDF's noise from its points' irradiance over this many seeds")
    ap.add_argument("--bssrdf-own", type=int, default=0,
                    help="only the BSSRDF image's own noise estimate against its spread over "
                         "this many seeds (bssrdf_own_noise; no reference needed)")
    ap.add_argument("--own-noise-default", action="store_true",
                    help="only every model's own noise estimate at the default scene's 800 x "
                         "800 (own_noise_default; no reference needed)")
    ap.add_argument("--procedural", action="store_true",
                    help="the variants' noise between seeds under the procedural sunset")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--device", default=None)
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args(argv)
    from dermis.pipeline.api import cache_dir_for
    from dermis.pipeline.cl import get_env
    env = get_env(args.device)
    scene = _scene()
    cache = cache_dir_for(scene, args.cache)
    if args.own_noise_default:
        out = {"code": _commit(), "load": list(os.getloadavg()),
               "own_noise_default": own_noise_default(cache)}
        if not args.no_save:
            save_labelled(RESULTS / "env_noise.json", args.label, out)
        return out
    if args.bssrdf_own:
        out = {"code": _commit(), "load": list(os.getloadavg()),
               "setup": {"scene": "default", "mesh": "high", "light": LABEL,
                         "size": [SIZE, SIZE]},
               "bssrdf_own_noise": bssrdf_own_noise(cache, args.bssrdf_own)}
        print(out, flush=True)
        if not args.no_save:
            save_labelled(RESULTS / "env_noise.json", args.label, out)
        return out
    mesh, lights, vis_default, bssrdf = _inputs(scene, cache)
    from dermis.lighting.visibility import Visibility
    vis = Visibility(mesh.vertices, mesh.faces)
    shaders = _shaders(scene)
    subsurface = bssrdf - shaders["surface"](mesh, vis_default, env)[0]
    if args.procedural:       # no converged render: the noise between seeds
        from dataclasses import replace
        out = {"setup": {"scene": "default", "mesh": "high", "light": "procedural_sunset",
                         "size": [SIZE, SIZE], "spp": scene.render.spp,
                         "light_samples_per_pixel": lights[0].samples, "seeds": args.seeds},
               "code": _commit(), "load": list(os.getloadavg()),
               "spread": spread(scene, mesh, [replace(lights[0], map="procedural_sunset")],
                                vis, env, shaders, args.seeds, args.variants.split(","))}
        if not args.no_save:
            save_labelled(RESULTS / "env_noise.json", args.label, out)
        return out
    ref, ref_meta = reference(scene, mesh, lights, vis, env, shaders, subsurface, args.pieces,
                              args.piece_samples,
                              Path(cache) / "bench_env_noise" / "reference.npz",
                              args.reuse_reference)
    out = {"setup": {"scene": "default", "mesh": "high", "light": LABEL, "size": [SIZE, SIZE],
                     "spp": scene.render.spp, "light_samples_per_pixel": lights[0].samples},
           "code": _commit(), "machine": platform.processor() or platform.machine(),
           "load": list(os.getloadavg()),
           "device": env.description,
           "reference": {**ref_meta,
                         "samples_per_pixel": ref_meta["pieces"] * ref_meta["piece_samples"]},
           "variants": {}}
    for v in args.variants.split(","):
        out["variants"][v] = _measure(scene, mesh, lights, vis, env, shaders, subsurface, ref,
                                      args.seeds, v)
    if args.shares:
        out["shares"] = shares(scene, mesh, lights, vis, env, shaders, subsurface, ref,
                               args.seeds)
    if args.brightness:
        out["brightness"] = brightness(scene, mesh, lights, vis, env, shaders, subsurface, ref,
                                       args.seeds)
    if args.sample_counts:
        out["sample_counts"] = sample_counts(scene, mesh, lights, vis, env, shaders, subsurface,
                                             ref, max(args.seeds // 2, 2),
                                             [int(x) for x in args.sample_counts.split(",")])
    if args.bssrdf_seeds:
        out["bssrdf_irradiance_noise"] = bssrdf_noise(cache, args.bssrdf_seeds, env, shaders,
                                                      ref["surface"][0])
        print("  bssrdf irradiance noise:", out["bssrdf_irradiance_noise"], flush=True)
    if args.cost:
        out["cost"] = cost(scene, mesh, lights, vis, env)
    if args.memory:
        out["memory"] = {"default_samples": memory_peak(lights[0].samples, cache),
                         "converged_one_piece": memory_peak(64 * lights[0].samples, cache)}
        a, b = out["memory"]["default_samples"], out["memory"]["converged_one_piece"]
        if "error" not in a and "error" not in b:
            out["memory"]["bytes_per_stored_sample"] = (
                (b["peak_rss_bytes"] - b["rss_before_bytes"]
                 - (a["peak_rss_bytes"] - a["rss_before_bytes"]))
                / max(b["stored_samples"] - a["stored_samples"], 1))
        print("  memory:", out["memory"])
    out["bench_peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(f"  this process's peak resident memory {out['bench_peak_rss_bytes'] / 2**30:.2f} GiB")
    if not args.no_save:
        RESULTS.mkdir(parents=True, exist_ok=True)
        save_labelled(RESULTS / "env_noise.json", args.label, out)
    return out


if __name__ == "__main__":
    main()
