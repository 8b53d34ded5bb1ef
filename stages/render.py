"""BRDF images: camera rays, Embree visibility, light samples with shadow rays, OpenCL shading.

Pipeline of :func:`render` (docs/architecture.md "Where the work runs"):

1. **visibility** - one pinhole ray per pixel centre through Embree
   (:class:`physics.visibility.Visibility`); the hits (triangle id + barycentrics) go to
   ``cl/surface.cl``, which returns position, geometric and shading normal (interpolated,
   bump-mapped from the baked map for the low-mesh variants), UV and linear albedo.
2. **shadows** - :func:`physics.lights.sample_lights` draws the light samples (environment
   lights: MIS of luminance and cosine samples about the geometric normal); samples
   below the geometric or the shading horizon are dropped before any ray is traced, and the
   rest go through Embree occlusion queries.  Pixels that miss the mesh or see a back face
   trace nothing.
3. **shading** - ``cl/shade.cl`` evaluates f(wo, wi) W cos(theta_i) for every surviving
   sample (one work-item each, loop-free); the host sums them per pixel.

Decisions touched here (docs/physics.md §6):

* Disc lights emit from both faces (physics/lights.py docstring): only the axis matters.
* Back faces (geometric normal facing away from the camera, e.g. inside an open neck) are
  covered (mask true) but black: the BRDF models are one-sided (f = 0 for wo.z <= 0), as in
  pbrt.  Same for pixels whose shading normal faces away from the camera (silhouettes of
  a low mesh with smooth or bumped normals).
* Samples are culled against BOTH horizons: below the geometric one the shadow ray would
  start inside the surface; below the shading one cos(theta_i) = 0.
* One camera ray per pixel centre (no anti-aliasing): the thesis images' quality is set by
  the shading, and 800x800 at one sample per pixel keeps the 2 s budget.
* Asperity is a term added to a base model (docs/physics.md §5); the base is chosen by the
  caller (``RenderConfig.asperity_base``); ``"none"`` renders the term alone so the BSSRDF
  stage can add it to its own image (same light, same exposure: images are linear).

Conventions: mm, linear RGB, camera y-up.  Output pixels that miss the mesh are 0 with
mask false.  Guarded by tests/test_render.py and tests/test_lights.py.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Callable

import numpy as np

from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.config import ASPERITY_BASES as SCENE_ASPERITY_BASES
from dermis.pipeline.config import MODELS as SCENE_MODELS
from dermis.pipeline.config import CameraConfig, LightConfig
from dermis.pipeline.errors import ConfigError, DermisError
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.imageio import write_exr
from dermis.physics.color import srgb_to_linear
from dermis.physics.lights import EnvironmentMap, environment_map, sample_lights
from dermis.physics.visibility import Visibility, shared as shared_visibility

__all__ = ["VERSION", "KERNELS", "MODELS", "LambertParams", "LightSampling", "RenderResult",
           "render", "camera_rays", "pixel_surface", "NAME", "node", "run"]

VERSION = 1
KERNELS = ("surface.cl", "shade.cl")
# Models this renderer shades ("bssrdf" images come from the BSSRDF stage).
# lambert: a test material; "none" renders the asperity term alone.
MODELS = ("lambert",) + tuple(m for m in SCENE_MODELS if m != "bssrdf")
ASPERITY_BASES = ("none",) + SCENE_ASPERITY_BASES
_BASE_CODE = {"none": -1, "lambert": 0, "lafortune": 1, "hk93": 2}

# Light samples processed per batch: bounds memory (~60 bytes a sample on the host) while
# keeping batches large enough that Embree and OpenCL call overheads stay negligible.
CHUNK_SAMPLES = 1 << 20


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


@dataclass(frozen=True)
class LightSampling:
    """Research options of the light sampling (the pipeline uses the defaults).

    shadow_samples : samples per pixel for disc and environment lights (None: each light's
        ``samples``, 16 in the thesis)
    env : pre-built EnvironmentMap for an environment light (None: from ``light.map``, cached)
    env_strategy : "mis" (luminance and cosine samples about the geometric normal) or
        "luminance" (:func:`physics.lights.sample_lights`)
    """

    shadow_samples: int | None = None
    env: EnvironmentMap | None = None
    env_strategy: str = "mis"


@dataclass
class RenderResult:
    """One rendered image.

    linear : (H, W, 3) float32 linear RGB radiance (0 where the mesh is missed)
    mask : (H, W) bool, True where a camera ray hit the mesh
    timings : dict, seconds: ``visibility`` (camera rays + surface kernel), ``shadows``
        (light sampling + occlusion rays), ``light_sampling`` (the part of ``shadows`` spent
        drawing samples), ``shading`` (BRDF kernel + sums), ``kernel_seconds`` (OpenCL
        profiling time, part of the above), ``total``, ``scene_build`` (Embree scene, 0 when
        one was passed in)
    info : dict of JSON-able facts (model, lights, samples, ray counts, device)
    """

    linear: np.ndarray
    mask: np.ndarray
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- camera
def _camera_vectors(camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Position and orthonormal forward/right/up of a CameraConfig (errors name the key)."""
    pos = np.asarray(camera.position, dtype=np.float64)
    look = np.asarray(camera.look_at, dtype=np.float64)
    up = np.asarray(camera.up, dtype=np.float64)
    fwd = look - pos
    if not np.linalg.norm(fwd) > 0:
        raise ConfigError(f"camera.look_at = {tuple(look)}: must differ from camera.position")
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    if not np.linalg.norm(right) > 1e-9 * max(np.linalg.norm(up), 1e-300):
        raise ConfigError(f"camera.up = {tuple(up)}: must not be parallel to the view "
                          "direction (camera.look_at - camera.position)")
    right /= np.linalg.norm(right)
    return pos, fwd, right, np.cross(right, fwd)


def camera_rays(camera) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole camera rays through pixel centres, row-major from the top-left pixel.

    ``camera`` (CameraConfig): ``position``, ``look_at``, ``up`` (mm), ``fov_deg`` (full angle
    across the SHORTER image side, pbrt's convention), ``width``, ``height``.  Returns origins
    and unit directions, (H*W, 3) float32 each.
    """
    w = int(camera.width)
    h = int(camera.height)
    if w < 1 or h < 1:
        raise ConfigError(f"camera width x height = {w} x {h}: both must be >= 1")
    fov = float(camera.fov_deg)
    if not 0 < fov < 180:
        raise ConfigError(f"camera.fov_deg = {fov}: must be in (0, 180)")
    pos, fwd, right, up = _camera_vectors(camera)
    tan = math.tan(math.radians(fov) / 2)
    short = min(w, h)
    x = ((np.arange(w) + 0.5) / w * 2.0 - 1.0) * tan * (w / short)
    y = (1.0 - (np.arange(h) + 0.5) / h * 2.0) * tan * (h / short)
    d = fwd[None, None, :] + x[None, :, None] * right + y[:, None, None] * up
    d = (d / np.linalg.norm(d, axis=2, keepdims=True)).reshape(-1, 3).astype(np.float32)
    o = np.broadcast_to(pos.astype(np.float32), d.shape)
    return np.ascontiguousarray(o), d


# --------------------------------------------------------------------------- helpers
def _resolve_model(model: str, params, asperity_base, base_params):
    """(base name, base params, asperity params or None) for a model name."""
    from dermis.stages.brdf_models import AsperityParams, HK93Params, LafortuneParams

    defaults = {"lambert": LambertParams, "lafortune": LafortuneParams, "hk93": HK93Params}
    if model == "bssrdf":
        raise ConfigError('model = "bssrdf": rendered by the BSSRDF stage, not the BRDF '
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


def _buf(cl, env, array):
    array = np.ascontiguousarray(array)
    if array.nbytes == 0:
        array = np.zeros(4, dtype=array.dtype)
    return cl.Buffer(env.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                     hostbuf=array)


def _global_size(n: int) -> tuple[int]:
    return (max(64, -(-n // 64) * 64),)


# --------------------------------------------------------------------------- surface
def _surface(env, mesh, hits_tri, hits_bary, camera_pos, *, texture, bump_map, bump_range,
             albedo_const):
    """Run cl/surface.cl on the hits; returns dict of per-hit arrays and kernel seconds."""
    import pyopencl as cl

    m = len(hits_tri)
    has_uv = mesh.uv is not None
    defines = {"HAS_UV": int(has_uv), "HAS_TEXTURE": int(texture is not None and has_uv),
               "HAS_BUMP": int(bump_map is not None and has_uv)}
    kern = cl.Kernel(env.program("surface.cl", defines), "surface")
    lut = srgb_to_linear(np.arange(256, dtype=np.float32) / 255.0).astype(np.float32)
    tex = texture if texture is not None else np.zeros((1, 1, 3), np.uint8)
    bmp = bump_map if bump_map is not None else np.zeros((1, 1), np.float32)
    ins = [
        _buf(cl, env, hits_tri.astype(np.int32)), _buf(cl, env, hits_bary.astype(np.float32)),
        np.int32(m),
        _buf(cl, env, np.asarray(mesh.vertices, dtype=np.float32)),
        _buf(cl, env, np.asarray(mesh.faces, dtype=np.int32)),
        _buf(cl, env, mesh.vertex_normals()),
        _buf(cl, env, np.asarray(mesh.uv if has_uv else np.zeros((1, 2)), dtype=np.float32)),
        _buf(cl, env, np.asarray(mesh.uv_faces if has_uv else np.zeros((1, 3)), dtype=np.int32)),
        _buf(cl, env, np.ascontiguousarray(tex, dtype=np.uint8)),
        np.int32(tex.shape[1]), np.int32(tex.shape[0]), _buf(cl, env, lut),
        _buf(cl, env, np.asarray(bmp, dtype=np.float32)),
        np.int32(bmp.shape[1]), np.int32(bmp.shape[0]), np.float32(bump_range),
        *(np.float32(c) for c in camera_pos),
    ]
    shapes = {"position": 3, "geo_normal": 3, "shading_normal": 3, "wo": 3, "uv": 2,
              "albedo": 3}
    outs = {k: np.empty((max(m, 1), c), dtype=np.float32) for k, c in shapes.items()}
    bufs = {k: cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, a.nbytes) for k, a in outs.items()}
    ev = kern(env.queue, _global_size(m), None, *ins, *bufs.values(),
              *(np.float32(c) for c in albedo_const))
    for k in outs:
        cl.enqueue_copy(env.queue, outs[k], bufs[k], wait_for=[ev])
    env.queue.finish()
    from dermis.pipeline.cl import event_seconds
    return {k: v[:m] for k, v in outs.items()}, event_seconds(ev)


@dataclass
class PixelSurface:
    """Surface attributes at every pixel whose camera ray hits the mesh.

    hits : Embree hits of all pixels; hit_idx : (M,) flat pixel indices of the hits;
    surf : dict of (M, k) float32 arrays: position (mm), geo_normal, shading_normal (bump-
    mapped), wo (unit, towards the eye), uv, albedo (linear); front_idx : indices into the M
    hits that face the camera (geometric and shading normal); texture : the albedo texture
    used (None: ``albedo_const``).
    """

    width: int
    height: int
    hits: object
    hit_idx: np.ndarray
    surf: dict
    front_idx: np.ndarray
    texture: object
    kernel_seconds: float


def pixel_surface(mesh, camera, *, maps=None, bump: str | None = None,
                  visibility: Visibility | None = None, cl_env=None, textured: bool = True,
                  albedo_const=(0.5, 0.5, 0.5)) -> PixelSurface:
    """Camera rays through Embree, then cl/surface.cl: the shading inputs of every pixel.

    Shared by the BRDF renderer and the BSSRDF gather so both see the same surface.
    ``textured=False`` ignores the albedo texture (``albedo_const`` everywhere).
    """
    from dermis.pipeline.cl import get_env

    env_cl = cl_env or get_env()
    visibility = visibility or Visibility(mesh.vertices, mesh.faces)
    w, h = int(camera.width), int(camera.height)
    origins, directions = camera_rays(camera)
    hits = visibility.intersect(origins, directions)
    hit_idx = np.flatnonzero(hits.hit)
    texture = maps.albedo_srgb if maps is not None else mesh.texture_srgb
    if not textured or (texture is not None and mesh.uv is None):
        texture = None  # no UVs (or asked for none): the constant albedo stands in
    bump_map = None
    if bump is not None:
        bump_map = maps.bump if bump == "sharp" else maps.bump_blur
    cam_pos = np.asarray(camera.position, dtype=np.float64)
    surf, ks = _surface(env_cl, mesh, hits.tri[hit_idx], hits.bary[hit_idx], cam_pos,
                        texture=texture, bump_map=bump_map,
                        bump_range=float(maps.bump_range_mm) if maps is not None else 0.0,
                        albedo_const=np.asarray(albedo_const, dtype=np.float32))
    ng, ns, wo = surf["geo_normal"], surf["shading_normal"], surf["wo"]
    # back faces and views below the shading horizon stay black (module docstring)
    front = (np.einsum("ij,ij->i", ng, wo) > 0) & (np.einsum("ij,ij->i", ns, wo) > 0)
    return PixelSurface(w, h, hits, hit_idx, surf, np.flatnonzero(front), texture, ks)


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
        self.inputs = [_buf(cl, env_cl, px.surf["shading_normal"]), _buf(cl, env_cl, px.surf["wo"]),
                       _buf(cl, env_cl, albedo),
                       _buf(cl, env_cl, np.asarray(base_block, dtype=np.float32)),
                       _buf(cl, env_cl, np.asarray(asp_block, dtype=np.float32))]

    def __call__(self, gidx: np.ndarray, dirs: np.ndarray, wts: np.ndarray) -> tuple[np.ndarray, float]:
        """f W cos(theta_i) of each sample of hit ``gidx``: (k, 3) float32, kernel seconds."""
        import pyopencl as cl
        from dermis.pipeline.cl import event_seconds

        env, k = self.env, len(gidx)
        out = np.empty((k, 3), dtype=np.float32)
        out_buf = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
        ev = self.kernel(env.queue, _global_size(k), None, _buf(cl, env, gidx), _buf(cl, env, dirs),
                         _buf(cl, env, wts), np.int32(k), *self.inputs, out_buf)
        cl.enqueue_copy(env.queue, out, out_buf, wait_for=[ev])
        env.queue.finish()
        return out, event_seconds(ev)


def _unshadowed_samples(lights, visibility: Visibility, surf: dict, pts: np.ndarray,
                        sampling: LightSampling, seed):
    """Light samples of hits ``pts`` above both horizons that reach the light.

    Returns (index into ``pts``, directions, weights, shadow rays traced, sampling seconds).
    """
    pos, ng, ns = surf["position"], surf["geo_normal"], surf["shading_normal"]
    t0 = time.perf_counter()
    ls = sample_lights(lights, pos[pts], ng[pts], samples=sampling.shadow_samples, seed=seed,
                       env=sampling.env, env_strategy=sampling.env_strategy)
    t_sampling = time.perf_counter() - t0
    cos_s = np.einsum("nsk,nk->ns", ls.directions, ns[pts])
    live = (cos_s > 0) & np.any(ls.weights > 0, axis=2)
    ip, isamp = np.nonzero(live)
    dirs = ls.directions[ip, isamp]
    blocked = visibility.occluded(pos[pts][ip], ng[pts][ip], dirs, ls.distance[ip, isamp])
    keep = ~blocked
    ip, isamp, dirs = ip[keep], isamp[keep], dirs[keep]
    return ip, dirs, ls.weights[ip, isamp], len(keep), t_sampling


def _shade_hits(px: PixelSurface, lights, visibility: Visibility, shader: _Shader,
                sampling: LightSampling, seed: int, per_point: int, progress):
    """Shadows and shading of the front-facing hits in batches of ``CHUNK_SAMPLES`` samples.

    Returns (M, 3) float64 radiance per hit and a dict of seconds and ray counts.
    """
    shade_idx, n_hits = px.front_idx, len(px.hit_idx)
    chunk = max(1, CHUNK_SAMPLES // per_point)
    radiance = np.zeros((n_hits, 3), dtype=np.float64)
    stats = dict.fromkeys(("shadows", "shading", "light_sampling", "kernel_seconds"), 0.0)
    stats.update(shadow_rays=0, shaded_samples=0)
    for c, start in enumerate(range(0, len(shade_idx), chunk)):
        pts = shade_idx[start:start + chunk]
        t0 = time.perf_counter()
        ip, dirs, wts, n_traced, t_sampling = _unshadowed_samples(lights, visibility, px.surf, pts,
                                                                  sampling, (seed, c))
        stats["light_sampling"] += t_sampling
        stats["shadow_rays"] += n_traced
        stats["shadows"] += time.perf_counter() - t0

        t0 = time.perf_counter()
        if len(ip):
            gidx = pts[ip].astype(np.int32)
            out, seconds = shader(gidx, dirs, wts)
            stats["kernel_seconds"] += seconds
            for ch in range(3):
                radiance[:, ch] += np.bincount(gidx, weights=out[:, ch], minlength=n_hits)
            stats["shaded_samples"] += len(ip)
        stats["shading"] += time.perf_counter() - t0
        if progress is not None:
            progress(min(1.0, (start + len(pts)) / max(len(shade_idx), 1)))
    return radiance, stats


def _image(radiance: np.ndarray, px: PixelSurface) -> tuple[np.ndarray, int]:
    """(H, W, 3) float32 image of the hits' radiance; non-finite values zeroed, pixels counted."""
    image = np.zeros((px.height * px.width, 3), dtype=np.float32)
    image[px.hit_idx] = radiance.astype(np.float32)
    bad = ~np.isfinite(image)
    nonfinite = int(bad.any(axis=1).sum())
    if nonfinite:  # never hand a NaN on; the count is recorded (tests require 0)
        image[bad] = 0.0
    return image.reshape(px.height, px.width, 3), nonfinite


def render(mesh, light, model: str, params, camera, *, maps=None, bump: str | None = None,
           seed: int = 0, visibility: Visibility | None = None, asperity_base: str | None = None,
           base_params=None, cl_env=None, textured: bool = True,
           sampling: LightSampling | None = None,
           progress: Callable[[float], None] | None = None) -> RenderResult:
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
        Seed of the light samples (results are deterministic for a seed and chunk size).
    visibility : physics.visibility.Visibility, optional
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
        Research options of the light sampling (sample count, environment map, strategy).
    progress : callable(float), optional
        Called with the completed fraction in [0, 1].

    Raises
    ------
    ConfigError
        Unknown model, wrong parameter type, bad camera, light or sampling option.
    DermisError
        Malformed mesh or maps, bump without maps/UVs.
    """
    from dermis.pipeline.cl import get_env

    t_start = time.perf_counter()
    mesh.check("render: mesh")
    base, bparams, asp = _resolve_model(model, params, asperity_base, base_params)
    lights = list(light) if isinstance(light, (list, tuple)) else [light]
    _check_bump(mesh, maps, bump)
    sampling = _light_sampling(sampling, lights)
    env_cl = cl_env or get_env()

    t0 = time.perf_counter()
    if visibility is None:
        visibility = Visibility(mesh.vertices, mesh.faces)
        scene_build = time.perf_counter() - t0
    else:
        scene_build = 0.0
    t0 = time.perf_counter()
    px = pixel_surface(mesh, camera, maps=maps, bump=bump, visibility=visibility, cl_env=env_cl,
                       textured=textured, albedo_const=_fallback_albedo(base, bparams))
    t_visibility = time.perf_counter() - t0

    shader = _Shader(env_cl, base, bparams, asp, px)
    per_point = sum(1 if lt.type in ("point", "directional")
                    else int(sampling.shadow_samples or lt.samples) for lt in lights)
    radiance, stats = _shade_hits(px, lights, visibility, shader, sampling, seed, per_point,
                                  progress)
    image, nonfinite = _image(radiance, px)
    if progress is not None:
        progress(1.0)
    timings = {"visibility": t_visibility, "shadows": stats["shadows"], "shading": stats["shading"],
               "light_sampling": stats["light_sampling"],
               "kernel_seconds": px.kernel_seconds + stats["kernel_seconds"],
               "scene_build": scene_build, "total": time.perf_counter() - t_start}
    w, h = px.width, px.height
    info = {
        "model": model, "base": base if asp is not None else model,
        "lights": [lt.name for lt in lights], "light_types": [lt.type for lt in lights],
        "width": w, "height": h, "samples_per_pixel": per_point, "seed": int(seed),
        "bump": bump, "textured": px.texture is not None, "env_strategy": sampling.env_strategy,
        "primary_rays": int(h * w), "hits": int(len(px.hit_idx)),
        "shaded_pixels": int(len(px.front_idx)), "shadow_rays": int(stats["shadow_rays"]),
        "shaded_samples": int(stats["shaded_samples"]), "triangles": int(len(mesh.faces)),
        "nonfinite_pixels": nonfinite, "device": env_cl.description,
    }
    return RenderResult(linear=image, mask=px.hits.hit.reshape(h, w), timings=timings, info=info)


# --------------------------------------------------------------------------- stage
# Stage ``render``: one image per BRDF model x lighting condition x geometry.

NAME = "render"
# geometry -> (mesh node, bump map variant)
GEOMETRY = {"high": ("mesh_high", None), "low": ("mesh_low", None),
            "low_bump": ("mesh_low", "sharp"), "low_bump_blur": ("mesh_low", "blur")}


def geometry_inputs(geometry: str) -> dict:
    """Upstream roles of an image of ``geometry``: its mesh, and the baked maps when bumped."""
    mesh_node, bump = GEOMETRY[geometry]
    return {"mesh": mesh_node, **({"maps": "bake"} if bump else {})}


def node(scene, model: str, label: str, lights: tuple, geometry: str) -> Node:
    from dermis.physics.lights import light_params
    base = scene.render.asperity_base if model == "asperity" else None
    uses_optics = model == "hk93" or base == "hk93"
    params = {"model": model, "label": label, "geometry": geometry, **light_params(lights),
              "camera": asdict(scene.camera), "bump": GEOMETRY[geometry][1],
              "seed": scene.mesh.seed, "asperity_base": base,
              "optics": scene.optics.to_dict() if uses_optics else None}
    return Node(f"render-{model}-{label}-{geometry}", NAME, __name__, params,
                geometry_inputs(geometry), label=f"{model} / {label} / {geometry}",
                locations=("lights[].map",))


def model_params(model: str, asperity_base: str | None, optics: dict | None):
    """The parameter objects of a BRDF model and of its asperity base, from the config slice
    (HK93 shares the BSSRDF's layer stack)."""
    from dermis.physics.layers import LayerStack
    from dermis.stages.brdf_models import AsperityParams, HK93Params, LafortuneParams
    hk = lambda: HK93Params(layers=LayerStack.from_dict(optics))  # noqa: E731
    if model == "lafortune":
        return LafortuneParams(), None
    if model == "hk93":
        return hk(), None
    base_params = {"lafortune": LafortuneParams, "hk93": hk}.get(asperity_base, lambda: None)()
    return AsperityParams(base=asperity_base), base_params


def run(params: dict, inputs: dict, ctx) -> StageResult:
    mesh, model = inputs["mesh"], params["model"]
    p, base_params = model_params(model, params["asperity_base"], params["optics"])
    lights = [LightConfig(**d) for d in params["lights"]]
    result = render(mesh, lights, model, p, CameraConfig(**params["camera"]),
                    maps=inputs.get("maps"), bump=params["bump"], seed=params["seed"],
                    visibility=shared_visibility(mesh, ctx.memo),
                    asperity_base=params["asperity_base"], base_params=base_params,
                    cl_env=ctx.cl, progress=ctx.progress)
    name = f"{model}-{params['label']}-{params['geometry']}"
    write_exr(ctx.out_dir / f"{name}.exr", result.linear)
    image = RenderedImage(result.linear, result.mask, dict(result.timings),
                          {**result.info, "model": model, "light": params["label"],
                           "geometry": params["geometry"]})
    return StageResult(image, files=[f"{name}.exr"],
                       info={"timings": result.timings,
                             "kernel_seconds": result.timings.get("kernel_seconds", 0.0)})
