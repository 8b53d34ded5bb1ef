"""The camera and shadow rays of one mesh under one lighting condition, cast once (stage
``visibility``) and shared by every model rendered with them (BRDF models and the BSSRDF).

Per (mesh, lighting condition, camera, ``[render] spp``, seed) :func:`cast`

1. casts ``spp`` stratified camera rays per pixel through Embree
   (:func:`dermis.rendering.camera.subpixel_offsets`; one ray through the pixel centre
   when spp = 1);
2. evaluates the model-independent surface attributes at the hits with ``cl/surface.cl``
   (:func:`dermis.rendering.surface.surface_attributes`: position, two-sided geometric
   normal facing the camera, interpolated vertex normal);
3. draws the light samples of every hit (:func:`dermis.lighting.emitters.sample_lights` with
   ``share = spp``: a disc or environment light's S samples per pixel are spread over the
   pixel's sub-pixel samples, ceil(S / spp) each, so anti-aliasing costs no extra light
   samples, and stratified over the whole pixel, :class:`~dermis.lighting.strata.PixelStrata`)
   and traces their shadow rays;
4. keeps the unoccluded samples above the geometric horizon: direction and weight per sample,
   grouped by hit (:class:`dermis.pipeline.artifacts.PixelSamples`).

The render nodes (``stages/render.py``, ``stages/bssrdf.py``) take this artifact as an input,
so the models under one light on one mesh shade the same rays, and changing a model's
parameters recasts no ray.  The sharing is also why the model images are comparable pixel
by pixel: their Monte Carlo noise is the same noise.  Bump-mapped geometries of the low mesh
share its visibility too: the bump moves the shading normal only (samples it puts below the
shading horizon get cos = 0 in the shading kernel).

Conventions: mm, linear RGB; pixel index row-major from the top-left.
Guarded by tests/test_antialias.py and tests/test_render.py.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from dermis.lighting.emitters import (ENV_STRATEGIES, SamplingOptions, light_columns,
                                      sample_lights)
from dermis.lighting.environment import environment_map
from dermis.lighting.lobes import (LOBE_SHARE_SCALE, LOBE_SHARE_SCALE_CONTROL, RETRO_FRACTION,
                                   RETRO_G_MAX, GlossyLobe, LafortuneLobes, RetroLobe)
from dermis.lighting.strata import PixelStrata
from dermis.lighting.visibility import Visibility
from dermis.rendering.camera import camera_rays, subpixel_offsets
from dermis.pipeline.artifacts import SAMPLE_CONTROL, SAMPLE_LIT, PixelSamples
from dermis.pipeline.cl import get_env
from dermis.pipeline.errors import ConfigError
from dermis.pipeline.registry import model
from dermis.pipeline.reuse import content_key
from dermis.pipeline.shared import RunCache, Shared
from dermis.rendering.halves import half_flags, sample_signs
from dermis.rendering.options import LightSampling, RenderOptions
from dermis.rendering.surface import surface_attributes

__all__ = ["cast", "glossy_lobes", "retro_lobe", "samples_per_hit"]

# Light samples drawn and traced per batch: bounds memory (~100 bytes a sample while
# sampling) while keeping Embree and numpy calls large.
# a mesh's camera hits and their surface attributes, shared by its lighting conditions (one
# camera per mesh of the run: the high and the low mesh)
CAMERA_HITS = Shared("camera_hits", keep=2)
CHUNK_SAMPLES = 1 << 20
# Camera rays per Embree call.
CHUNK_RAYS = 1 << 21


def retro_lobe(scene) -> dict | None:
    """The retro lobe a scene's images need: {"fraction", "k"} when a BRDF rendered reads the
    scene's layers (HK93, or the asperity term on HK93: ``Model.reads_optics``) and one of its
    layers scatters backwards (g < RETRO_G_MAX: the Henyey-Greenstein backscatter peak at
    wi = wo would give fireflies, docs/hardening.md), else None.  The most backward layer sets
    the lobe's width."""
    base = scene.render.asperity_base
    if not any(m.stage == "render" and m.reads_optics(base if m.bases else None)
               for m in map(model, scene.render.models)):
        return None
    layer = min(scene.optics.layers, key=lambda l: l.g)
    if not layer.g < RETRO_G_MAX:
        return None
    return {"fraction": RETRO_FRACTION, "k": RetroLobe.k_for_layer(layer.g, layer.eta)}


def glossy_lobes(scene) -> bool:
    """Whether a scene's images show the Lafortune lobes (``Model.glossy``: Lafortune, a
    BSSRDF whose surface term is the lobes, the asperity term over a Lafortune base): its
    environment-lit rays then draw a share of their samples from them
    (:class:`~dermis.lighting.lobes.LafortuneLobes`)."""
    base = scene.render.asperity_base
    for m in map(model, scene.render.models):
        if m.bases:
            if base in {b.name for b in m.bases} and m.base(base).glossy:
                return True
        elif m.glossy and (m.stage == "render"
                           or scene.bssrdf.surface_reflection == "lafortune_lobes"):
            return True
    return False


def _light_sampling(sampling: LightSampling | None, lights) -> LightSampling:
    """``sampling`` (defaults when None), checked, with the environment map a light needs."""
    sampling = sampling if sampling is not None else LightSampling()
    if sampling.shadow_samples is not None and int(sampling.shadow_samples) < 1:
        raise ConfigError(f"shadow_samples = {sampling.shadow_samples}: must be >= 1")
    env = sampling.env
    for lt in lights:
        if lt.type == "environment" and env is None:
            env = environment_map(lt)
    return replace(sampling, env=env)


def samples_per_hit(lights, spp: int, shadow_samples: int | None = None) -> int:
    """Light samples drawn per camera hit, all lights (:func:`light_columns`)."""
    return sum(light_columns(lights, spp, shadow_samples))


# --------------------------------------------------------------------------- casting
def _primary(vis: Visibility, camera, spp: int, seed: int):
    """Camera hits: (flat pixel index, sub-sample index, triangle, barycentrics) of every
    sub-pixel ray that hit, and the number of rays cast."""
    w, h = int(camera.width), int(camera.height)
    rng = np.random.default_rng((int(seed), 1))
    offsets = subpixel_offsets(w * h, spp, rng)
    rows_per = max(1, CHUNK_RAYS // (w * spp))
    pix, sub, tri, bary = [], [], [], []
    for r0 in range(0, h, rows_per):
        r1 = min(h, r0 + rows_per)
        o, d = camera_rays(camera, offsets, rows=(r0, r1))
        hits = vis.intersect(o, d)
        ok = np.flatnonzero(hits.hit)
        pix.append((ok // spp + r0 * w).astype(np.int32))
        sub.append((ok % spp).astype(np.int32))
        tri.append(hits.tri[ok])
        bary.append(hits.bary[ok])
    return (np.concatenate(pix), np.concatenate(sub), np.concatenate(tri), np.concatenate(bary),
            w * h * spp)


def _camera_hits(mesh, camera, spp: int, seed: int, vis: Visibility, env_cl,
                 shared: RunCache | None, mesh_key: str | None):
    """Camera hits and their surface attributes, which depend on the mesh, camera, spp and
    seed but not on the light: shared in the run (``CAMERA_HITS``) so the lighting conditions
    of a mesh cast its camera rays once."""
    if shared is None:
        return _cast_camera_hits(mesh, camera, spp, seed, vis, env_cl)
    key = (mesh_key or content_key(np.asarray(mesh.vertices), np.asarray(mesh.faces)),
           repr(camera), int(spp), int(seed))
    out, made = shared.get_made(CAMERA_HITS, key, lambda: _cast_camera_hits(
        mesh, camera, spp, seed, vis, env_cl))
    return out if made else out[:-1] + (0.0,)     # no kernel ran for this node


def _cast_camera_hits(mesh, camera, spp: int, seed: int, vis: Visibility, env_cl):
    pixel, sub, tri, bary, n_rays = _primary(vis, camera, spp, seed)
    cam_pos = np.asarray(camera.position, dtype=np.float64)
    surf, k_s = surface_attributes(env_cl, mesh, tri, bary, cam_pos)
    # the hits' fingerprint, as the artifact stores them: every image of the mesh finds its
    # shared surface pass by it (rendering/surface.py) instead of hashing ~30 MB per image
    hits_key = content_key(tri.astype(np.int32), bary.astype(np.float32))
    return pixel, sub, tri, bary, n_rays, surf, hits_key, k_s


def cast(mesh, lights, camera, options: RenderOptions = RenderOptions(), *, cl_env=None,
         progress=None, shared: RunCache | None = None,
         mesh_key: str | None = None) -> PixelSamples:
    """Camera rays, light samples and shadow rays of one image (module docstring).

    Parameters
    ----------
    mesh : pipeline.artifacts.Mesh (mm)
    lights : LightConfig or sequence of LightConfig (summed)
    camera : pipeline.config.CameraConfig
    options : RenderOptions; read are ``spp`` (>= 1, camera samples per pixel, 1 = the pixel
        centre), ``seed`` (the sub-pixel jitter and the light samples, deterministic),
        ``visibility`` (the Embree scene of ``mesh`` built earlier, optional) and
        ``sampling`` (LightSampling, optional research options)
    cl_env : pipeline.cl.ClEnv, optional
    progress : callable(float), optional
    shared : RunCache, optional
        The run's shared intermediates: the camera hits of a mesh are then cast once for all
        its lighting conditions (the same rays, so the same result).
    mesh_key : str, optional
        The mesh's content key (its node's cache key); by default a digest of the mesh.

    Returns
    -------
    pipeline.artifacts.PixelSamples
    """
    t_start = time.perf_counter()
    spp, seed = int(options.spp), options.seed
    if spp < 1:
        raise ConfigError(f"render.spp = {spp}: must be >= 1")
    lights = list(lights) if isinstance(lights, (list, tuple)) else [lights]
    sampling = _light_sampling(options.sampling, lights)
    env_cl = cl_env or get_env()
    vis = options.visibility or Visibility(mesh.vertices, mesh.faces)
    pixel, sub, tri, bary, n_rays, surf, hits_key, k_s = _camera_hits(
        mesh, camera, spp, seed, vis, env_cl, shared, mesh_key)
    # a pixel's light samples, stratified over its sub-samples (one sample: per point)
    strata = PixelStrata(pixel, sub, spp, int(seed), independent=sampling.independent_halves)
    t_primary = time.perf_counter() - t_start

    t0 = time.perf_counter()
    pos, ng = surf["position"], surf["geo_normal"]
    lobe = None
    if sum((sampling.glossy_fraction > 0, sampling.retro_fraction > 0,
            bool(sampling.glossy_lobes))) > 1:
        raise ConfigError("sampling: more than one of glossy_fraction, retro_fraction and "
                          "glossy_lobes; one environment lobe at a time")
    # the renderer's estimator replaces the default strategy; "mis" and "luminance" stay
    mixture = sampling.mixture and sampling.env_strategy == ENV_STRATEGIES[0]
    if sampling.control_variate and not mixture:
        raise ConfigError("sampling: control_variate needs mixture (and env_strategy "
                          f"{ENV_STRATEGIES[0]!r})")
    if sampling.glossy_lobes and mixture:
        lobe = LafortuneLobes(surf["wo"], surf["shading_normal"],
                              scale=(LOBE_SHARE_SCALE_CONTROL if sampling.control_variate
                                     else LOBE_SHARE_SCALE))
    elif sampling.glossy_fraction > 0:
        lobe = GlossyLobe(surf["wo"], surf["shading_normal"], sampling.glossy_fraction,
                          sampling.glossy_exponent, sampling.glossy_tilt)
    elif sampling.retro_fraction > 0:
        lobe = RetroLobe(surf["wo"], sampling.retro_fraction, sampling.retro_k)
    t_surface = time.perf_counter() - t0

    columns = light_columns(lights, spp, sampling.shadow_samples)
    per_hit = sum(columns)
    chunk = max(1, CHUNK_SAMPLES // max(per_hit, 1))
    m = len(tri)
    counts = np.zeros(m, dtype=np.int32)
    dirs, wts, flags, cbins = [], [], [], []
    table = None
    t_sampling = t_shadows = 0.0
    n_shadow = 0
    for c, start in enumerate(range(0, m, chunk)):
        sl = slice(start, min(m, start + chunk))
        t0 = time.perf_counter()
        ls = sample_lights(lights, pos[sl], ng[sl], seed=(int(seed), 0, c),
                           options=SamplingOptions(samples=sampling.shadow_samples,
                                                   env=sampling.env,
                                                   env_strategy=sampling.env_strategy),
                           share=spp,
                           strata=strata[sl] if strata is not None else None,
                           lobe=lobe[sl] if lobe is not None else None,
                           mixture=mixture, control=sampling.control_variate,
                           product_normals=surf["shading_normal"][sl] if mixture else None)
        # the live samples by flat index, row-major (grouped by hit, in hit order), and one
        # ``take`` per array; with the control variate the live ones above the geometric
        # horizon get shadow rays and every sample of its region is kept, lit or not
        live = ls.live()
        if ls.control is not None:
            live &= np.einsum("nsk,nk->ns", ls.directions, ng[sl]) > 0
        flat = np.flatnonzero(live)
        ip = flat // live.shape[1]
        t1 = time.perf_counter()
        t_sampling += t1 - t0
        blocked = vis.occluded(pos[sl].take(ip, axis=0), ng[sl].take(ip, axis=0),
                               ls.directions.reshape(-1, 3).take(flat, axis=0),
                               ls.distance.reshape(-1).take(flat))
        n_shadow += len(ip)
        # each sample's half (rendering/halves.py): the image's own noise estimate; with an
        # even spp a camera sample's samples share its half
        if spp % 2 == 0:
            halves = half_flags(sample_signs(sub[sl], spp, [1]))[:, 0]
        else:
            halves = half_flags(sample_signs(sub[sl], spp, columns)).reshape(-1)
        if ls.control is None:
            keep = np.flatnonzero(~blocked)
            ip, flat = ip.take(keep), flat.take(keep)
            flags.append((halves.take(ip) if spp % 2 == 0 else halves.take(flat))
                         | np.uint8(SAMPLE_LIT))
        else:
            lit = np.zeros(live.shape, bool)
            lit.reshape(-1)[flat[~blocked]] = True
            kept = lit | ls.control
            flat = np.flatnonzero(kept)
            ip = flat // live.shape[1]
            flags.append(lit.reshape(-1).take(flat).astype(np.uint8) * SAMPLE_LIT
                         + ls.control.reshape(-1).take(flat).astype(np.uint8) * SAMPLE_CONTROL
                         + (halves.take(ip) if spp % 2 == 0 else halves.take(flat)))
            cbins.append(ls.control_bin)
            table = ls.control_table
        counts[sl] = np.bincount(ip, minlength=sl.stop - sl.start)
        dirs.append(ls.directions.reshape(-1, 3).take(flat, axis=0))
        wts.append(ls.weights.reshape(-1, 3).take(flat, axis=0))
        t_shadows += time.perf_counter() - t1
        if progress is not None:
            progress(min(1.0, sl.stop / max(m, 1)))
    directions = np.concatenate(dirs) if dirs else np.zeros((0, 3), np.float32)
    weights = np.concatenate(wts) if wts else np.zeros((0, 3), np.float32)
    w, h = int(camera.width), int(camera.height)
    info = {"lights": [lt.name for lt in lights], "light_types": [lt.type for lt in lights],
            "width": w, "height": h, "spp": spp, "seed": int(seed),
            "light_samples_per_hit": per_hit, "env_strategy": sampling.env_strategy,
            "env_lobe": (None if lobe is None else {"type": type(lobe).__name__,
                                                    "fraction": float(np.mean(lobe.fractions()))
                                                    if len(tri) else 0.0}),
            "primary_rays": int(n_rays), "hits": int(m), "camera_hits_key": hits_key,
            "shadow_rays": int(n_shadow), "env_mixture": mixture,
            "env_control": table is not None,
            "glossy_lobes": isinstance(lobe, LafortuneLobes),
            "unoccluded_samples": int(sum(int(np.count_nonzero(f & SAMPLE_LIT))
                                          for f in flags)),
            "stored_samples": int(len(directions)), "triangles": int(len(mesh.faces)),
            "timings": {"primary": t_primary, "surface": t_surface,
                        "light_sampling": t_sampling, "shadows": t_shadows,
                        "kernel_seconds": k_s, "total": time.perf_counter() - t_start}}
    return PixelSamples(width=w, height=h, spp=spp, pixel=pixel.astype(np.int32),
                        tri=tri.astype(np.int32), bary=bary.astype(np.float32), counts=counts,
                        directions=np.ascontiguousarray(directions, dtype=np.float32),
                        weights=np.ascontiguousarray(weights, dtype=np.float32), info=info,
                        flags=(np.concatenate(flags) if flags else np.zeros(0, np.uint8)),
                        control_bin=(np.concatenate(cbins).astype(np.int32)
                                     if table is not None else None),
                        control_table=table, sub=sub.astype(np.int32))
