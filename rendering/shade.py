"""BRDF images: shared visibility (camera and shadow rays), OpenCL shading, box-filtered pixels.

Pipeline of :func:`render` (docs/software.md "Where the work runs"):

1. **visibility** - ``spp`` stratified camera rays per pixel, their light samples and shadow
   rays (:func:`dermis.rendering.cast.cast`).  In the pipeline this is the ``visibility``
   node of the mesh and lighting condition, cast once and shared by every model (its
   :class:`~dermis.pipeline.artifacts.PixelSamples` is an input of this stage); called
   directly, :func:`render` casts it itself unless ``options.samples`` is given.
2. **surface** - ``cl/surface.cl`` at every camera hit (rendering/surface.py): position,
   two-sided geometric normal, shading normal (interpolated, bump-mapped from the baked map
   for the low-mesh variants, bent towards the viewer where it faced away), UV and linear
   albedo.
3. **shading** - ``cl/shade.cl`` evaluates f(wo, wi) W cos(theta_i) for every unoccluded light
   sample (one work-item each, loop-free); the host sums them per pixel and divides by spp
   (a box filter over the stratified sub-pixel samples: anti-aliased silhouettes, shadow
   edges and lip boundaries).

Decisions touched here (docs/science.md §6):

* Disc lights emit from both faces (lighting/emitters.py docstring): only the axis matters.
* Every camera hit is shaded: back faces are two-sided, and shading normals facing away from
  the camera are bent towards it (cl/surface.cl), so creases at eyelids, lips and nostrils
  are no longer black outlines.  The BRDF models stay one-sided in their own frame.
* Samples below the geometric horizon are dropped before any ray is traced (the shadow ray
  would start inside the surface); below the shading horizon cos(theta_i) = 0 in the kernel.
* Pixels average ``spp`` camera samples (``[render] spp``); a pixel's light samples
  (disc, environment) are spread over them, so anti-aliasing adds camera rays and surface
  work but no light samples (rendering/cast.py).  spp = 1 is one ray through the pixel
  centre, the pre-anti-aliasing renderer.
* Asperity is a term added to a base model (docs/science.md §5; ``Model.bases``); the base
  is chosen by the caller (``RenderOptions.base``, in scenes ``[render] asperity_base``);
  ``"none"`` renders the term alone, a linear image a caller may add to another image of the
  same light and camera (a BSSRDF image, say); no stage does.

Conventions: mm, linear RGB, camera y-up.  A pixel's value is the sum of its hit samples /
spp (missed samples count 0); ``mask`` is true where any sample hit.  Guarded by
tests/test_render.py, tests/test_antialias.py and tests/test_lights.py.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from dermis.lighting.control import control_estimate
from dermis.lighting.visibility import Visibility
from dermis.models.model import Model
from dermis.pipeline.artifacts import SAMPLE_CONTROL
from dermis.pipeline.shared import RunCache
from dermis.pipeline.cl import event_seconds, get_env, to_device
from dermis.pipeline.errors import ConfigError
from dermis.rendering.cast import cast
from dermis.rendering.indirect_shading import indirect_radiance
from dermis.rendering.halves import signs_of
from dermis.rendering.options import RenderOptions
from dermis.rendering.surface import PixelSurface, check_bump, global_size, pixel_surface

__all__ = ["KERNELS", "RenderResult", "render", "shade", "CHUNK_SAMPLES"]

KERNELS = ("shade.cl",)
# cl/shade.cl with nothing selected (f = 0); a model's ``shade`` defines select its base BRDF
# (DERMIS_BASE) or its term (DERMIS_ASPERITY)
_SHADE_NONE = {"DERMIS_BASE": -1, "DERMIS_ASPERITY": 0}

# Light samples shaded per batch: bounds memory (~60 bytes a sample on the host) while
# keeping batches large enough that OpenCL call overheads stay negligible.
CHUNK_SAMPLES = 1 << 21


@dataclass
class RenderResult:
    """One rendered image.

    linear : (H, W, 3) float32 linear RGB radiance (0 where the mesh is missed)
    mask : (H, W) bool, True where a camera ray hit the mesh
    coverage : (H, W) float32, fraction of the pixel's camera samples that hit the mesh
    timings : dict, seconds: ``visibility`` (camera and shadow rays when cast here, 0 when
        ``samples`` were given), ``surface`` (cl/surface.cl), ``shading`` (BRDF kernel +
        sums), ``kernel_seconds`` (OpenCL profiling time, part of the above), ``total``,
        ``scene_build`` (Embree scene, 0 when one was passed in)
    info : dict of JSON-able facts (model, lights, samples, ray counts, device)
    noise : (H, W, 3) float32 the image's own noise estimate (A - B) / 2 of its two half
        images (rendering/halves.py), or None where the samples carry no halves
    """

    linear: np.ndarray
    mask: np.ndarray
    coverage: np.ndarray | None = None
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    noise: np.ndarray | None = None


def _resolve(model: Model, params, base: str | None, base_params):
    """(base model or None, its params, term params or None) of a model: a BRDF is its own
    base; a term (``model.bases``) goes over the base ``base`` (default ``params.base``),
    or alone for "none"."""
    if model.stage != "render":
        raise ConfigError(f'model = "{model.name}": rendered by the {model.stage} stage, not the '
                          'BRDF renderer; render its asperity term with model="asperity", '
                          'base="none" and add the two images')
    if not model.bases:
        return model, model.checked(params, f"params for model {model.name!r}"), None
    term = model.checked(params, f"params for model {model.name!r}")
    base = base or term.base
    names = ("none",) + tuple(m.name for m in model.bases)
    if base not in names:
        raise ConfigError(f"{model.name} base = {base!r}: must be one of {', '.join(names)} "
                          "(a BSSRDF is no base: render the term with 'none' and add it to the "
                          "BSSRDF image)")
    if base == "none":
        return None, None, term
    bm = model.base(base)
    return bm, bm.checked(base_params, f"base_params for {model.name} base {base!r}"), term


def _fallback_albedo(base: Model | None, base_params) -> np.ndarray:
    """Constant linear albedo where no texture exists: the model's own diffuse albedo."""
    if base is not None and base.albedo is not None and base_params is not None:
        return np.asarray(getattr(base_params, base.albedo), dtype=np.float32)
    return np.full(3, 0.5, dtype=np.float32)


class _Shader:
    """cl/shade.cl built for one model, with the per-hit shading inputs on the device."""

    def __init__(self, env_cl, base: Model | None, bparams, term: Model | None, asp,
                 px: PixelSurface):
        import pyopencl as cl  # optional until a kernel runs (pipeline/cl.py NoOpenCLError)

        self.env = env_cl
        defines = dict(_SHADE_NONE)
        for m in (base, term):
            if m is not None:
                defines.update(m.shade)
        program = env_cl.program("shade.cl", defines)
        self.kernel = cl.Kernel(program, "shade_samples")
        self.control_kernel = cl.Kernel(program, "shade_control")
        base_block = bparams.pack() if bparams is not None else np.zeros(4, np.float32)
        asp_block = asp.pack() if asp is not None else np.zeros(8, np.float32)
        albedo = px.surf["albedo"]
        if base is not None and base.shade_albedo is not None:   # e.g. HK93's tint of rho_ms
            albedo = base.shade_albedo(bparams, albedo, px.texture is not None)
        self.inputs = [to_device(env_cl, px.surf["shading_normal"]),
                       to_device(env_cl, px.surf["wo"]), to_device(env_cl, albedo),
                       to_device(env_cl, np.asarray(base_block, dtype=np.float32)),
                       to_device(env_cl, np.asarray(asp_block, dtype=np.float32))]

    def __call__(self, gidx: np.ndarray, dirs: np.ndarray, wts: np.ndarray,
                 flags: np.ndarray | None = None, split: bool = False):
        """Each sample of hit ``gidx``: f W cos(theta_i) where lit, minus the control term
        (cl/shade.cl; ``flags`` None: all lit): (k, 3) float32, kernel seconds.  ``split``:
        (lit term, control term, kernel seconds), both (k, 3) float32, from one pass."""
        import pyopencl as cl  # optional until a kernel runs (pipeline/cl.py NoOpenCLError)

        env, k = self.env, len(gidx)
        out = np.empty((k, 3), dtype=np.float32)
        out_buf = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
        ctrl = np.empty((k, 3) if split else (1, 3), dtype=np.float32)
        ctrl_buf = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, ctrl.nbytes)
        fl = (np.ascontiguousarray(flags, dtype=np.uint8) if flags is not None
              else np.ones(1, np.uint8))
        ev = self.kernel(env.queue, global_size(k), None, to_device(env, gidx),
                         to_device(env, dirs), to_device(env, wts), np.int32(k), *self.inputs,
                         to_device(env, fl), np.int32(flags is not None), out_buf, ctrl_buf,
                         np.int32(split))
        cl.enqueue_copy(env.queue, out, out_buf, wait_for=[ev])
        if split:
            cl.enqueue_copy(env.queue, ctrl, ctrl_buf, wait_for=[ev])
        env.queue.finish()
        return (out, ctrl, event_seconds(ev)) if split else (out, event_seconds(ev))

    def control(self, control_bin: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, float]:
        """The control variate's integral alpha n_s . M_b of every hit: (M, 3) float32, kernel
        seconds."""
        import pyopencl as cl  # optional until a kernel runs (pipeline/cl.py NoOpenCLError)

        env, m = self.env, len(control_bin)
        out = np.empty((max(m, 1), 3), dtype=np.float32)
        out_buf = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
        ev = self.control_kernel(env.queue, global_size(m), None, np.int32(m),
                                 to_device(env, np.asarray(control_bin, np.int32)),
                                 to_device(env, np.asarray(table, np.float32)),
                                 *self.inputs[:3], *self.inputs[3:], out_buf)
        cl.enqueue_copy(env.queue, out, out_buf, wait_for=[ev])
        env.queue.finish()
        return out[:m], event_seconds(ev)


def shade(px: PixelSurface, shader, progress=None) -> tuple[np.ndarray, dict]:
    """Sum f W cos over every unoccluded light sample into its pixel, / spp; with the control
    variate (lighting/control.py), the non-negative estimator of
    :func:`dermis.lighting.control.control_estimate`.

    Returns (H*W, 3) float64 radiance and a dict of seconds and counts; its ``"noise"``:
    (H*W, 3) float64 the signed half difference of the samples' halves, / spp
    (rendering/halves.py), or None where the samples carry no halves.
    """
    samples = px.samples
    n_pix = px.width * px.height
    owner = np.repeat(np.arange(len(samples.counts), dtype=np.int32), samples.counts)
    k_total = len(owner)
    flags = getattr(samples, "flags", None)
    halves = flags is not None and len(flags) == k_total
    control = getattr(samples, "control_bin", None) is not None
    # per pixel: the sum and the signed (half A minus half B) sum of the samples' terms;
    # with the control variate also those of the control terms alpha W (n_s . w) 1[R_b]
    radiance = np.zeros((n_pix, 3), dtype=np.float64)
    noise = np.zeros((n_pix, 3), dtype=np.float64) if halves else None
    ctrl = np.zeros((n_pix, 3), dtype=np.float64) if control else None
    ctrl_signed = np.zeros((n_pix, 3), dtype=np.float64) if control and halves else None
    # the samples outside the control region (few: a split sun's), summed apart; the
    # region's sums are the totals less theirs
    other = np.zeros((n_pix, 3), dtype=np.float64) if control else None
    other_signed = np.zeros((n_pix, 3), dtype=np.float64) if control and halves else None
    stats = {"kernel_seconds": 0.0, "shaded_samples": int(k_total)}

    def add(total, signed, pix, out, sign):
        for ch in range(3):
            total[:, ch] += np.bincount(pix, weights=out[:, ch], minlength=n_pix)
        if signed is not None:
            out = out * sign[:, None]
            for ch in range(3):
                signed[:, ch] += np.bincount(pix, weights=out[:, ch], minlength=n_pix)

    for start in range(0, k_total, CHUNK_SAMPLES):
        sl = slice(start, min(k_total, start + CHUNK_SAMPLES))
        gidx = owner[sl]
        fl = flags[sl] if flags is not None else None
        if control:     # f W cos V of every sample and the control terms alpha W (n_s . w)
            out, cterm, seconds = shader(gidx, samples.directions[sl], samples.weights[sl],
                                         fl, split=True)
        else:
            out, seconds = shader(gidx, samples.directions[sl], samples.weights[sl], fl)
        stats["kernel_seconds"] += seconds
        pix = px.hit_idx[gidx]
        sign = signs_of(fl) if halves else None
        if control:
            idx = np.flatnonzero(fl & SAMPLE_CONTROL)
            add(ctrl, ctrl_signed, pix.take(idx), cterm.take(idx, axis=0), None if sign is None
                else sign.take(idx))
            rest = np.flatnonzero((fl & SAMPLE_CONTROL) == 0)
            if len(rest):
                add(other, other_signed, pix.take(rest), out.take(rest, axis=0),
                    None if sign is None else sign.take(rest))
        add(radiance, noise, pix, out, sign)
        if progress is not None:
            progress(min(1.0, sl.stop / max(k_total, 1)))
    if control:    # the control variate's integral per hit, alpha n_s . M_b
        out, seconds = shader.control(samples.control_bin, samples.control_table)
        stats["kernel_seconds"] += seconds
        hit_sign = None
        if halves:       # a hit's half: its samples' where they share one, else both
            # halves (0: an odd camera sample split by its columns, or no samples)
            mean = np.bincount(owner, weights=signs_of(flags), minlength=len(samples.counts))
            mean /= np.maximum(samples.counts, 1)
            hit_sign = np.where(np.abs(mean) == 1.0, mean, 0.0)
        exact = np.zeros((n_pix, 3))
        exact_signed = np.zeros((n_pix, 3)) if halves else None
        add(exact, exact_signed, px.hit_idx, out, hit_sign)
        # the region's samples through the estimator, the others (a split sun's) as they are
        region = radiance - other
        region_signed = None if noise is None else noise - other_signed
        radiance, noise = control_estimate(region, region_signed, ctrl, ctrl_signed, exact,
                                           exact_signed)
        radiance += other
        if noise is not None:
            noise += other_signed
    stats["noise"] = noise / px.spp if noise is not None else None
    return radiance / px.spp, stats


def _image(radiance: np.ndarray, px: PixelSurface,
           noise: np.ndarray | None = None) -> tuple[np.ndarray, int, np.ndarray | None]:
    """(H, W, 3) float32 image of per-pixel radiance and its noise; non-finite values zeroed
    (in both, where either is), pixels counted."""
    image = radiance.astype(np.float32)
    bad = ~np.isfinite(image)
    if noise is not None:
        noise = noise.astype(np.float32)
        bad |= ~np.isfinite(noise)
    nonfinite = int(bad.any(axis=1).sum())
    if nonfinite:  # never hand a NaN on; the count is recorded (tests require 0)
        image[bad] = 0.0
        if noise is not None:
            noise[bad] = 0.0
    shape = (px.height, px.width, 3)
    return image.reshape(shape), nonfinite, None if noise is None else noise.reshape(shape)


def render(mesh, light, model: Model, params, camera, options: RenderOptions = RenderOptions(),
           *, cl_env=None, progress: Callable[[float], None] | None = None,
           shared: RunCache | None = None, keys: tuple | None = None) -> RenderResult:
    """Render one image of ``mesh`` under ``light`` with a BRDF model.

    Parameters
    ----------
    mesh : pipeline.artifacts.Mesh
        Triangles in mm; vertex normals (else angle-weighted ones); UVs and ``texture_srgb``
        optional (albedo texture).
    light : LightConfig or sequence of LightConfig
        Point, disc, directional (several are summed, e.g. the thesis's two) or environment.
    model : models.model.Model of stage "render" (e.g. ``models.lafortune.MODEL``)
    params : an instance of ``model.params``, or None (its defaults)
    camera : pipeline.config.CameraConfig (its ``width`` x ``height`` is the image size)
    options : RenderOptions
        Baked maps and bump, texture on or off, the base under a term model, and the shared
        visibility (``samples``) or how to cast it here.
    cl_env : pipeline.cl.ClEnv, optional
    progress : callable(float), optional
        Called with the completed fraction in [0, 1].
    shared, keys : RunCache and the (mesh, maps) content keys, optional
        The run's shared intermediates: surface attributes shared with the run's other
        images (:func:`dermis.rendering.surface.pixel_surface`).

    Raises
    ------
    ConfigError
        A model of another stage, wrong parameter type, bad camera, light or sampling option.
    DermisError
        Malformed mesh or maps, bump without maps/UVs, samples of another camera or mesh.
    """
    t_start = time.perf_counter()
    mesh.check("render: mesh")
    base, bparams, asp = _resolve(model, params, options.base, options.base_params)
    term = model if asp is not None else None
    lights = list(light) if isinstance(light, (list, tuple)) else [light]
    check_bump(mesh, options.maps, options.bump)
    env_cl = cl_env or get_env()

    scene_build = t_visibility = 0.0
    samples = options.samples
    if samples is None:
        t0 = time.perf_counter()
        visibility = options.visibility
        if visibility is None:
            visibility = Visibility(mesh.vertices, mesh.faces)
            scene_build = time.perf_counter() - t0
        samples = cast(mesh, lights, camera, replace(options, visibility=visibility),
                       cl_env=env_cl)
        t_visibility = time.perf_counter() - t0 - scene_build
    t0 = time.perf_counter()
    px = pixel_surface(mesh, camera, samples, options,
                       albedo_const=_fallback_albedo(base, bparams), cl_env=env_cl,
                       shared=shared, keys=keys)
    t_surface = time.perf_counter() - t0

    t0 = time.perf_counter()
    shader = _Shader(env_cl, base, bparams, term, asp, px)
    radiance, stats = shade(px, shader, progress)
    if options.indirect is not None:   # one diffuse bounce (rendering/indirect_shading.py)
        radiance += indirect_radiance(px, lambda hits: _Shader(env_cl, base, bparams, term, asp,
                                                               hits), mesh.faces, options.indirect)
    image, nonfinite, noise = _image(radiance, px, stats["noise"])
    t_shading = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    # in a run (``shared``) every image of a geometry shares one surface pass, as every image
    # of a mesh and light shares its visibility: its seconds are kept apart ("surface_shared",
    # the same in each image) and ``total`` is this image's own work, whichever image made it
    own = time.perf_counter() - t_start - (t_surface if shared is not None else 0.0)
    timings = {"visibility": t_visibility, "surface": t_surface,
               "surface_shared": px.surface_seconds, "shading": t_shading,
               "kernel_seconds": px.kernel_seconds + stats["kernel_seconds"],
               "scene_build": scene_build, "total": own}
    w, h = px.width, px.height
    vinfo = samples.info or {}
    info = {
        "model": model.name,
        "base": (base.name if base is not None else "none") if term is not None
        else model.name,
        "lights": vinfo.get("lights", [lt.name for lt in lights]),
        "light_types": vinfo.get("light_types", [lt.type for lt in lights]),
        "width": w, "height": h, "spp": int(samples.spp),
        "light_samples_per_hit": vinfo.get("light_samples_per_hit"),
        "seed": vinfo.get("seed", int(options.seed)),
        "bump": options.bump, "textured": px.texture is not None,
        "env_strategy": vinfo.get("env_strategy"),
        "primary_rays": vinfo.get("primary_rays"), "hits": int(len(px.hit_idx)),
        "shadow_rays": vinfo.get("shadow_rays"),
        "shaded_samples": int(stats["shaded_samples"]), "triangles": int(len(mesh.faces)),
        "nonfinite_pixels": nonfinite, "device": env_cl.description,
    }
    return RenderResult(linear=image, mask=px.mask, coverage=px.coverage, timings=timings,
                        info=info, noise=noise)
