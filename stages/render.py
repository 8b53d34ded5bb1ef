"""BRDF images: shared visibility (camera and shadow rays), OpenCL shading, box-filtered pixels.

Pipeline of :func:`render` (docs/software.md "Where the work runs"):

1. **visibility** - ``spp`` stratified camera rays per pixel, their light samples and shadow
   rays (:func:`dermis.stages.visibility.cast`).  In the pipeline this is the ``visibility``
   node of the mesh and lighting condition, cast once and shared by every model (its
   :class:`~dermis.pipeline.artifacts.PixelSamples` is an input of this stage); called
   directly, :func:`render` casts it itself unless ``samples`` is given.
2. **surface** - ``cl/surface.cl`` at every camera hit: position, two-sided geometric normal,
   shading normal (interpolated, bump-mapped from the baked map for the low-mesh variants,
   bent towards the viewer where it faced away), UV and linear albedo.
3. **shading** - ``cl/shade.cl`` evaluates f(wo, wi) W cos(theta_i) for every unoccluded light
   sample (one work-item each, loop-free); the host sums them per pixel and divides by spp
   (a box filter over the stratified sub-pixel samples: anti-aliased silhouettes, shadow
   edges and lip boundaries).

Decisions touched here (docs/science.md §6):

* Disc lights emit from both faces (lighting/lights.py docstring): only the axis matters.
* Every camera hit is shaded: back faces are two-sided, and shading normals facing away from
  the camera are bent towards it (cl/surface.cl), so creases at eyelids, lips and nostrils
  are no longer black outlines.  The BRDF models stay one-sided in their own frame.
* Samples below the geometric horizon are dropped before any ray is traced (the shadow ray
  would start inside the surface); below the shading horizon cos(theta_i) = 0 in the kernel.
* Pixels average ``spp`` camera samples (``[render] spp``); a pixel's light samples
  (disc, environment) are spread over them, so anti-aliasing adds camera rays and surface
  work but no light samples (stages/visibility.py).  spp = 1 is one ray through the pixel
  centre, the pre-anti-aliasing renderer.
* Asperity is a term added to a base model (docs/science.md §5); the base is chosen by the
  caller (``RenderConfig.asperity_base``); ``"none"`` renders the term alone so the BSSRDF
  stage can add it to its own image (same light, same exposure: images are linear).

Conventions: mm, linear RGB, camera y-up.  A pixel's value is the sum of its hit samples /
spp (missed samples count 0); ``mask`` is true where any sample hit.  Guarded by
tests/test_render.py, tests/test_antialias.py and tests/test_lights.py.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np

from dermis.pipeline.artifacts import PixelSamples, RenderedImage
from dermis.pipeline.config import ASPERITY_BASES as SCENE_ASPERITY_BASES
from dermis.pipeline.config import BSSRDF_MODELS, MODELS as SCENE_MODELS
from dermis.pipeline.config import CameraConfig
from dermis.pipeline.errors import ConfigError, DermisError
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.cl import to_device
from dermis.pipeline.imageio import write_exr
from dermis.lighting.visibility import Visibility, camera_rays, camera_vectors
from dermis.stages.visibility import (LightSampling, _global_size, cast,
                                      surface_attributes)

__all__ = ["VERSION", "KERNELS", "MODELS", "LambertParams", "LightSampling", "RenderResult",
           "PixelSurface", "render", "shade", "camera_rays", "pixel_surface", "NAME", "node",
           "run"]

VERSION = 2
KERNELS = ("surface.cl", "shade.cl")
# Models this renderer shades ("bssrdf", "bssrdf_mc" images come from the BSSRDF stage).
# lambert: a test material; "none" renders the asperity term alone.
MODELS = ("lambert",) + tuple(m for m in SCENE_MODELS if m not in BSSRDF_MODELS)
ASPERITY_BASES = ("none",) + SCENE_ASPERITY_BASES
_BASE_CODE = {"none": -1, "lambert": 0, "lafortune": 1, "hk93": 2}

# Light samples shaded per batch: bounds memory (~60 bytes a sample on the host) while
# keeping batches large enough that OpenCL call overheads stay negligible.
CHUNK_SAMPLES = 1 << 21

_camera_vectors = camera_vectors   # kept for callers of the old private name


@dataclass(frozen=True)
class LambertParams:
    """Lambertian test material f = albedo / pi (albedo from the texture when there is one).

    albedo : (3,) floats in [0, 1], linear RGB, used where no texture is given.
    """

    albedo: Any = (0.5, 0.5, 0.5)

    def __post_init__(self):
        a = np.asarray(self.albedo, dtype=np.float64)
        if a.shape != (3,) or not np.all((a >= 0) & (a <= 1)):
            raise ConfigError(f"lambert.albedo = {self.albedo!r}: must be 3 numbers in [0, 1]")
        object.__setattr__(self, "albedo", a)

    def pack(self) -> np.ndarray:
        """(4,) float32 placeholder block (the albedo travels per pixel)."""
        return np.zeros(4, dtype=np.float32)


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
    """

    linear: np.ndarray
    mask: np.ndarray
    coverage: np.ndarray | None = None
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- helpers
def _resolve_model(model: str, params, asperity_base, base_params):
    """(base name, base params, asperity params or None) for a model name."""
    from dermis.stages.brdf_models import AsperityParams, HK93Params, LafortuneParams

    defaults = {"lambert": LambertParams, "lafortune": LafortuneParams, "hk93": HK93Params}
    if model in BSSRDF_MODELS:
        raise ConfigError(f'model = "{model}": rendered by the BSSRDF stage, not the BRDF '
                          'renderer; render its asperity term with model="asperity", '
                          'asperity_base="none" and add the two images')
    if model not in MODELS:
        raise ConfigError(f"model = {model!r}: must be one of {', '.join(MODELS)}")
    if model != "asperity":
        p = params if params is not None else defaults[model]()
        if not isinstance(p, defaults[model]):
            raise ConfigError(f"params for model {model!r} must be {defaults[model].__name__}, "
                              f"got {type(p).__name__}")
        return model, p, None
    asp = params if params is not None else AsperityParams()
    if not isinstance(asp, AsperityParams):
        raise ConfigError(f"params for model 'asperity' must be AsperityParams, got "
                          f"{type(asp).__name__}")
    base = asperity_base or asp.base
    if base not in ASPERITY_BASES:
        raise ConfigError(f"asperity_base = {base!r}: must be one of {', '.join(ASPERITY_BASES)}"
                          + (" (a BSSRDF base: render the term with 'none' and add it to the "
                             "BSSRDF image)" if base == "bssrdf" else ""))
    if base == "none":
        return base, None, asp
    bp = base_params if base_params is not None else defaults[base]()
    if not isinstance(bp, defaults[base]):
        raise ConfigError(f"base_params for asperity base {base!r} must be "
                          f"{defaults[base].__name__}, got {type(bp).__name__}")
    return base, bp, asp


def _fallback_albedo(base: str, base_params) -> np.ndarray:
    """Constant linear albedo where no texture exists: the model's own diffuse albedo."""
    for name in ("albedo", "rho_d"):
        if base_params is not None and hasattr(base_params, name):
            return np.asarray(getattr(base_params, name), dtype=np.float32)
    return np.full(3, 0.5, dtype=np.float32)


def _check_bump(mesh, maps, bump) -> None:
    """Raise unless ``bump`` is None, or "sharp"/"blur" with maps and a mesh with UVs."""
    if bump not in (None, "sharp", "blur"):
        raise ConfigError(f"bump = {bump!r}: must be None, 'sharp' or 'blur'")
    if bump is not None and (maps is None or mesh.uv is None):
        raise DermisError(f"bump = {bump!r} needs baked maps and a mesh with UVs "
                          f"(maps {'missing' if maps is None else 'given'}, "
                          f"uv {'missing' if mesh.uv is None else 'given'})")


def _check_samples(samples: PixelSamples, camera, mesh) -> None:
    if (samples.width, samples.height) != (int(camera.width), int(camera.height)):
        raise DermisError(f"render: visibility samples are {samples.width} x {samples.height}, "
                          f"the camera {camera.width} x {camera.height}")
    if len(samples.tri) and int(samples.tri.max()) >= len(mesh.faces):
        raise DermisError("render: visibility samples name triangles the mesh does not have "
                          "(cast on another mesh)")


# --------------------------------------------------------------------------- surface
@dataclass
class PixelSurface:
    """Surface attributes at every camera sample that hit the mesh.

    width, height, spp : image size and camera samples per pixel
    hit_idx : (M,) flat pixel index of each hit (a pixel appears up to spp times)
    surf : dict of (M, k) float32 arrays: position (mm), geo_normal (facing the camera),
        shading_normal (bump-mapped, facing the camera), wo (unit, towards the eye), uv,
        albedo (linear)
    front_idx : indices of the hits that are shaded (all of them: cl/surface.cl makes every
        hit face the camera)
    samples : the PixelSamples the hits come from (light samples included)
    texture : the albedo texture used (None: ``albedo_const``)
    kernel_seconds : cl/surface.cl's kernel seconds in this call (0 when shared)
    surface_seconds : seconds of the surface pass these attributes came from (computed here
        or earlier in the run and shared)
    """

    width: int
    height: int
    spp: int
    hit_idx: np.ndarray
    surf: dict
    front_idx: np.ndarray
    samples: PixelSamples
    texture: object
    kernel_seconds: float
    surface_seconds: float = 0.0

    @property
    def coverage(self) -> np.ndarray:
        """(H, W) float32 fraction of each pixel's camera samples that hit."""
        c = np.bincount(self.hit_idx, minlength=self.width * self.height) / self.spp
        return c.astype(np.float32).reshape(self.height, self.width)

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: some camera sample of the pixel hit."""
        m = np.zeros(self.width * self.height, bool)
        m[self.hit_idx] = True
        return m.reshape(self.height, self.width)

    def pixels(self, values: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """(H*W, 3) float32 image of per-hit values (of hits ``idx``, default all): each
        pixel is the sum of its hits' values / spp (box filter; misses count 0)."""
        pix = self.hit_idx if idx is None else self.hit_idx[idx]
        values = np.asarray(values, dtype=np.float64)
        out = np.stack([np.bincount(pix, weights=values[:, c], minlength=self.width * self.height)
                        for c in range(values.shape[1])], axis=1)
        return (out / self.spp).astype(np.float32)


# Surface attributes kept per run (``memo``) for this many geometries (mesh, camera hits, bump
# map): one per geometry of the default matrix (high, low_bump, low_bump_blur), each ~68 bytes
# a hit (~175 MB at 800x800 x 4 spp).  The images of a geometry (4 lights x the BRDF models,
# the BSSRDF and its surface term) share one camera cast (stages/visibility.py), so without
# it they computed the same attributes ~20 times over (0.3-1.3 s per image; 0.06 s shared):
# the 36 BRDF images of the 48-image matrix went from 29.3 to 14.7 s of node time with the
# session's other changes (bench/results/pipeline_default_48.json, per_stage and before).
SURFACE_CACHE_SIZE = 3


def pixel_surface(mesh, camera, *, samples: PixelSamples | None = None, maps=None,
                  bump: str | None = None, visibility: Visibility | None = None, cl_env=None,
                  textured: bool = True, albedo_const=(0.5, 0.5, 0.5), spp: int = 1,
                  seed: int = 0, lights=None, memo: dict | None = None) -> PixelSurface:
    """cl/surface.cl at the camera hits of ``samples``: the shading inputs of every hit.

    Shared by the BRDF renderer and the BSSRDF gather so both see the same surface.
    ``samples`` : the visibility artifact (stages/visibility.py); None casts camera rays here
    (``spp``, ``seed``; and light samples of ``lights`` when given).
    ``textured=False`` ignores the albedo texture (``albedo_const`` everywhere).
    ``memo`` : the run's scratch dict: the attributes of a geometry are then computed once per
    run (``SURFACE_CACHE_SIZE`` geometries kept) and shared read-only by its images.
    """
    from dermis.pipeline.cl import get_env

    env_cl = cl_env or get_env()
    if samples is None:
        samples = cast(mesh, lights or [], camera, spp=spp, seed=seed, visibility=visibility,
                       cl_env=env_cl)
    _check_samples(samples, camera, mesh)
    texture = maps.albedo_srgb if maps is not None else mesh.texture_srgb
    if mesh.uv is None:
        texture = None  # no UVs: the constant albedo stands in
    bump_map = None
    if bump is not None:
        bump_map = maps.bump if bump == "sharp" else maps.bump_blur
    cam_pos = np.asarray(camera.position, dtype=np.float64)
    bump_range = float(maps.bump_range_mm) if maps is not None else 0.0
    const = np.asarray(albedo_const, dtype=np.float32)

    def compute():
        t0 = time.perf_counter()
        surf, ks = surface_attributes(env_cl, mesh, samples.tri, samples.bary, cam_pos,
                                      texture=texture, bump_map=bump_map,
                                      bump_range=bump_range, albedo_const=const)
        return surf, ks, time.perf_counter() - t0
    surf, ks, seconds = compute() if memo is None else _shared_surface(
        memo, (mesh, texture, bump_map), (bump_range, tuple(cam_pos)), samples, compute)
    if texture is None or not textured:
        # cl/surface.cl writes the constant as the albedo of every hit when it has no texture:
        # the same float32 values, so the shared attributes serve every albedo
        texture = None
        surf = {**surf, "albedo": np.broadcast_to(const, surf["albedo"].shape)}
    m = len(samples.tri)
    return PixelSurface(samples.width, samples.height, samples.spp,
                        samples.pixel.astype(np.int64), surf, np.arange(m), samples, texture, ks,
                        seconds)


def _shared_surface(memo: dict, objects: tuple, values: tuple, samples, compute):
    """``compute()``'s (surf, kernel seconds, seconds), once per run for equal inputs: keyed by the
    identity of ``objects`` (the run's loaded mesh, texture and bump map; the entry holds them,
    so their ids stay theirs), ``values`` and the content of the camera hits (each lighting
    condition's visibility node holds its own copy of the same hits; the cast stored their
    fingerprint).  The arrays are shared
    read-only; a reuse reports 0 kernel seconds (no kernel ran)."""
    from dermis.pipeline.reuse import content_key, recent_in_run

    def make():
        surf, ks, seconds = compute()
        for a in surf.values():
            a.setflags(write=False)
        return objects, surf, ks, seconds
    hits = ((samples.info or {}).get("camera_hits_key")      # stages/visibility.py cast
            or content_key(samples.tri, samples.bary))
    key = (tuple(id(o) for o in objects), values, hits)
    (_, surf, ks, seconds), made = recent_in_run(memo, ("pixel_surface",), SURFACE_CACHE_SIZE,
                                                 key, make)
    return surf, (ks if made else 0.0), seconds


# --------------------------------------------------------------------------- render
class _Shader:
    """cl/shade.cl built for one model, with the per-hit shading inputs on the device."""

    def __init__(self, env_cl, base: str, bparams, asp, px: PixelSurface):
        import pyopencl as cl

        self.env = env_cl
        defines = {"DERMIS_BASE": _BASE_CODE[base], "DERMIS_ASPERITY": int(asp is not None)}
        self.kernel = cl.Kernel(env_cl.program("shade.cl", defines), "shade_samples")
        base_block = bparams.pack() if bparams is not None else np.zeros(4, np.float32)
        asp_block = asp.pack() if asp is not None else np.zeros(8, np.float32)
        albedo = px.surf["albedo"]
        if base == "hk93":  # the texture tints rho_ms: shade.cl expects albedo / Rd (1 = untinted)
            albedo = (albedo / bparams.texture_reference()).astype(np.float32) \
                if px.texture is not None else np.ones_like(albedo)
        self.inputs = [to_device(env_cl, px.surf["shading_normal"]),
                       to_device(env_cl, px.surf["wo"]), to_device(env_cl, albedo),
                       to_device(env_cl, np.asarray(base_block, dtype=np.float32)),
                       to_device(env_cl, np.asarray(asp_block, dtype=np.float32))]

    def __call__(self, gidx: np.ndarray, dirs: np.ndarray, wts: np.ndarray) -> tuple[np.ndarray, float]:
        """f W cos(theta_i) of each sample of hit ``gidx``: (k, 3) float32, kernel seconds."""
        import pyopencl as cl
        from dermis.pipeline.cl import event_seconds

        env, k = self.env, len(gidx)
        out = np.empty((k, 3), dtype=np.float32)
        out_buf = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
        ev = self.kernel(env.queue, _global_size(k), None, to_device(env, gidx),
                         to_device(env, dirs), to_device(env, wts), np.int32(k), *self.inputs,
                         out_buf)
        cl.enqueue_copy(env.queue, out, out_buf, wait_for=[ev])
        env.queue.finish()
        return out, event_seconds(ev)


def shade(px: PixelSurface, shader, progress=None) -> tuple[np.ndarray, dict]:
    """Sum f W cos over every unoccluded light sample into its pixel, / spp.

    Returns (H*W, 3) float64 radiance and a dict of seconds and counts.
    """
    samples = px.samples
    n_pix = px.width * px.height
    owner = np.repeat(np.arange(len(samples.counts), dtype=np.int32), samples.counts)
    k_total = len(owner)
    radiance = np.zeros((n_pix, 3), dtype=np.float64)
    stats = {"kernel_seconds": 0.0, "shaded_samples": int(k_total)}
    for start in range(0, k_total, CHUNK_SAMPLES):
        sl = slice(start, min(k_total, start + CHUNK_SAMPLES))
        gidx = owner[sl]
        out, seconds = shader(gidx, samples.directions[sl], samples.weights[sl])
        stats["kernel_seconds"] += seconds
        pix = px.hit_idx[gidx]
        for ch in range(3):
            radiance[:, ch] += np.bincount(pix, weights=out[:, ch], minlength=n_pix)
        if progress is not None:
            progress(min(1.0, sl.stop / max(k_total, 1)))
    return radiance / px.spp, stats


def _image(radiance: np.ndarray, px: PixelSurface) -> tuple[np.ndarray, int]:
    """(H, W, 3) float32 image of per-pixel radiance; non-finite values zeroed, pixels counted."""
    image = radiance.astype(np.float32)
    bad = ~np.isfinite(image)
    nonfinite = int(bad.any(axis=1).sum())
    if nonfinite:  # never hand a NaN on; the count is recorded (tests require 0)
        image[bad] = 0.0
    return image.reshape(px.height, px.width, 3), nonfinite


def render(mesh, light, model: str, params, camera, *, maps=None, bump: str | None = None,
           seed: int = 0, visibility: Visibility | None = None, asperity_base: str | None = None,
           base_params=None, cl_env=None, textured: bool = True,
           sampling: LightSampling | None = None, samples: PixelSamples | None = None,
           spp: int = 1, progress: Callable[[float], None] | None = None,
           memo: dict | None = None) -> RenderResult:
    """Render one image of ``mesh`` under ``light`` with a BRDF model.

    Parameters
    ----------
    mesh : pipeline.artifacts.Mesh
        Triangles in mm; vertex normals (else angle-weighted ones); UVs and ``texture_srgb``
        optional (albedo texture).
    light : LightConfig or sequence of LightConfig
        Point, disc, directional (several are summed, e.g. the thesis's two) or environment.
    model : {"lambert", "lafortune", "hk93", "asperity"}
    params : LambertParams, LafortuneParams, HK93Params or AsperityParams, or None (defaults)
    camera : pipeline.config.CameraConfig (its ``width`` x ``height`` is the image size)
    maps : pipeline.artifacts.BakedMaps, optional
        Baked maps of a low mesh; their ``albedo_srgb`` replaces the mesh's texture.
    bump : {None, "sharp", "blur"}
        Bump-map the shading normal with ``maps.bump`` or ``maps.bump_blur`` (needs maps and UVs).
    seed : int
        Seed of the camera jitter and light samples when they are cast here.
    visibility : lighting.visibility.Visibility, optional
        Embree scene of ``mesh`` built earlier (build once, render many).
    asperity_base : {"none", "lambert", "lafortune", "hk93"}, optional
        Base model under the asperity term (default ``params.base``); "none" = term alone.
    base_params : optional
        Parameters of the asperity base model (default: its defaults).
    cl_env : pipeline.cl.ClEnv, optional
    textured : bool
        False ignores the albedo texture (the model's constant albedo everywhere), e.g. to
        render only Lafortune's specular lobes (rho_d = 0) on top of a BSSRDF image.
    sampling : LightSampling, optional
        Research options of the light sampling (sample count, environment map, strategy);
        only used when the samples are cast here.
    samples : PixelSamples, optional
        The shared visibility (stages/visibility.py) of this mesh, light and camera; ``light``,
        ``seed``, ``spp`` and ``sampling`` are then not used for casting.
    spp : int
        Camera samples per pixel when cast here (1 = the pixel centre).
    progress : callable(float), optional
        Called with the completed fraction in [0, 1].
    memo : dict, optional
        The run's scratch dict: surface attributes shared with the run's other images
        (:func:`pixel_surface`).

    Raises
    ------
    ConfigError
        Unknown model, wrong parameter type, bad camera, light or sampling option.
    DermisError
        Malformed mesh or maps, bump without maps/UVs, samples of another camera or mesh.
    """
    from dermis.pipeline.cl import get_env

    t_start = time.perf_counter()
    mesh.check("render: mesh")
    base, bparams, asp = _resolve_model(model, params, asperity_base, base_params)
    lights = list(light) if isinstance(light, (list, tuple)) else [light]
    _check_bump(mesh, maps, bump)
    env_cl = cl_env or get_env()

    scene_build = t_visibility = 0.0
    if samples is None:
        t0 = time.perf_counter()
        if visibility is None:
            visibility = Visibility(mesh.vertices, mesh.faces)
            scene_build = time.perf_counter() - t0
        samples = cast(mesh, lights, camera, spp=spp, seed=seed, visibility=visibility,
                       sampling=sampling, cl_env=env_cl)
        t_visibility = time.perf_counter() - t0 - scene_build
    t0 = time.perf_counter()
    px = pixel_surface(mesh, camera, samples=samples, maps=maps, bump=bump, cl_env=env_cl,
                       textured=textured, albedo_const=_fallback_albedo(base, bparams),
                       memo=memo)
    t_surface = time.perf_counter() - t0

    t0 = time.perf_counter()
    shader = _Shader(env_cl, base, bparams, asp, px)
    radiance, stats = shade(px, shader, progress)
    image, nonfinite = _image(radiance, px)
    t_shading = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    # in a run (``memo``) every image of a geometry shares one surface pass, as every image of a
    # mesh and light shares its visibility: its seconds are kept apart ("surface_shared", the
    # same in each image) and ``total`` is this image's own work, whichever image made the pass
    own = time.perf_counter() - t_start - (t_surface if memo is not None else 0.0)
    timings = {"visibility": t_visibility, "surface": t_surface,
               "surface_shared": px.surface_seconds, "shading": t_shading,
               "kernel_seconds": px.kernel_seconds + stats["kernel_seconds"],
               "scene_build": scene_build, "total": own}
    w, h = px.width, px.height
    vinfo = samples.info or {}
    info = {
        "model": model, "base": base if asp is not None else model,
        "lights": vinfo.get("lights", [lt.name for lt in lights]),
        "light_types": vinfo.get("light_types", [lt.type for lt in lights]),
        "width": w, "height": h, "spp": int(samples.spp),
        "light_samples_per_hit": vinfo.get("light_samples_per_hit"),
        "seed": vinfo.get("seed", int(seed)),
        "bump": bump, "textured": px.texture is not None,
        "env_strategy": vinfo.get("env_strategy"),
        "primary_rays": vinfo.get("primary_rays"), "hits": int(len(px.hit_idx)),
        "shadow_rays": vinfo.get("shadow_rays"),
        "shaded_samples": int(stats["shaded_samples"]), "triangles": int(len(mesh.faces)),
        "nonfinite_pixels": nonfinite, "device": env_cl.description,
    }
    return RenderResult(linear=image, mask=px.mask, coverage=px.coverage, timings=timings,
                        info=info)


# --------------------------------------------------------------------------- stage
# Stage ``render``: one image per BRDF model x lighting condition x geometry.

NAME = "render"
# geometry -> (mesh node, bump map variant)
GEOMETRY = {"high": ("mesh_high", None), "low": ("mesh_low", None),
            "low_bump": ("mesh_low", "sharp"), "low_bump_blur": ("mesh_low", "blur")}


def geometry_inputs(geometry: str, label: str | None = None) -> dict:
    """Upstream roles of an image of ``geometry``: its mesh, the baked maps when bumped, and
    (given the lighting ``label``) the shared visibility of that mesh and lighting."""
    mesh_node, bump = GEOMETRY[geometry]
    return {"mesh": mesh_node, **({"maps": "bake"} if bump else {}),
            **({"visibility": visibility_id(mesh_node, label)} if label is not None else {})}


def visibility_id(mesh_node: str, label: str) -> str:
    """Node id of the shared visibility of a mesh and lighting condition (stages/visibility.py)."""
    return f"visibility-{mesh_node}-{label}"


def node(scene, model: str, label: str, lights: tuple, geometry: str) -> Node:
    """One image; the lights, camera rays and seed reach it through its visibility input."""
    base = scene.render.asperity_base if model == "asperity" else None
    uses_optics = model == "hk93" or base == "hk93"
    params = {"model": model, "label": label, "geometry": geometry,
              "camera": asdict(scene.camera), "bump": GEOMETRY[geometry][1],
              "asperity_base": base,
              "optics": scene.optics.to_dict() if uses_optics else None}
    return Node(f"render-{model}-{label}-{geometry}", NAME, __name__, params,
                geometry_inputs(geometry, label), label=f"{model} / {label} / {geometry}")


def model_params(model: str, asperity_base: str | None, optics: dict | None,
                 memo: dict | None = None):
    """The parameter objects of a BRDF model and of its asperity base, from the config slice
    (HK93 shares the BSSRDF's layer stack).  ``memo`` (the run's scratch dict) keeps one
    HK93Params per layer stack: building one integrates the layers' albedo (~0.8 s), and
    the 12 HK93 images of a matrix share it."""
    import json
    from dermis.optics.layers import LayerStack
    from dermis.stages.brdf_models import AsperityParams, HK93Params, LafortuneParams

    def hk():
        key = ("hk93_params", json.dumps(optics, sort_keys=True, default=str))
        if memo is None:
            return HK93Params(layers=LayerStack.from_dict(optics))
        if key not in memo:
            memo[key] = HK93Params(layers=LayerStack.from_dict(optics))
        return memo[key]
    if model == "lafortune":
        return LafortuneParams(), None
    if model == "hk93":
        return hk(), None
    base_params = {"lafortune": LafortuneParams, "hk93": hk}.get(asperity_base, lambda: None)()
    return AsperityParams(base=asperity_base), base_params


def run(params: dict, inputs: dict, ctx) -> StageResult:
    mesh, model, samples = inputs["mesh"], params["model"], inputs["visibility"]
    p, base_params = model_params(model, params["asperity_base"], params["optics"], ctx.memo)
    result = render(mesh, [], model, p, CameraConfig(**params["camera"]),
                    maps=inputs.get("maps"), bump=params["bump"], samples=samples,
                    asperity_base=params["asperity_base"], base_params=base_params,
                    cl_env=ctx.cl, progress=ctx.progress, memo=ctx.memo)
    result.timings["visibility_shared"] = float(
        (samples.info.get("timings") or {}).get("total", 0.0))
    name = f"{model}-{params['label']}-{params['geometry']}"
    write_exr(ctx.out_dir / f"{name}.exr", result.linear)
    image = RenderedImage(result.linear, result.mask, dict(result.timings),
                          {**result.info, "model": model, "light": params["label"],
                           "geometry": params["geometry"]})
    return StageResult(image, files=[f"{name}.exr"],
                       info={"timings": result.timings,
                             "kernel_seconds": result.timings.get("kernel_seconds", 0.0)})
