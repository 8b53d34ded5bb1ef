"""BRDF images: camera rays, Embree visibility, light samples with shadow rays, OpenCL shading.

Pipeline of :func:`render` (architecture.md "Where the work runs"):

1. **visibility** - one pinhole ray per pixel centre through Embree
   (:class:`pipeline.visibility.Visibility`); the hits (triangle id + barycentrics) go to
   ``cl/surface.cl``, which returns position, geometric and shading normal (interpolated,
   bump-mapped from the baked map for the low-mesh variants), UV and linear albedo.
2. **shadows** - :func:`pipeline.lights.sample_lights` draws the light samples (environment
   lights: MIS of luminance and cosine samples about the geometric normal); samples
   below the geometric or the shading horizon are dropped before any ray is traced, and the
   rest go through Embree occlusion queries.  Pixels that miss the mesh or see a back face
   trace nothing.
3. **shading** - ``cl/shade.cl`` evaluates f(wo, wi) W cos(theta_i) for every surviving
   sample (one work-item each, loop-free); the host sums them per pixel.

Decisions on physics.md "check" items touched here:

* Disc lights emit from both faces (pipeline/lights.py docstring): only the axis matters.
* Back faces (geometric normal facing away from the camera, e.g. inside an open neck) are
  covered (mask true) but black: the BRDF models are one-sided (f = 0 for wo.z <= 0), as in
  pbrt.  Same for pixels whose shading normal faces away from the camera (silhouettes of
  a low mesh with smooth or bumped normals).
* Samples are culled against BOTH horizons: below the geometric one the shadow ray would
  start inside the surface; below the shading one cos(theta_i) = 0.
* One camera ray per pixel centre (no anti-aliasing): the thesis images' quality is set by
  the shading, and 800x800 at one sample per pixel keeps the 2 s budget.
* Asperity is a term added to a base model (physics.md s5); the base is chosen by the
  caller (``RenderConfig.asperity_base``); ``"none"`` renders the term alone so the BSSRDF
  stage can add it to its own image (same light, same exposure: images are linear).

Conventions: mm, linear RGB, camera y-up.  Output pixels that miss the mesh are 0 with
mask false.  Guarded by tests/test_render.py and tests/test_lights.py.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
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

__all__ = ["VERSION", "KERNELS", "MODELS", "LambertParams", "RenderResult", "render",
           "camera_rays", "pixel_surface", "vertex_normals", "NAME", "node", "run"]

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


def camera_rays(camera, *, width: int | None = None, height: int | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole camera rays through pixel centres, row-major from the top-left pixel.

    Parameters
    ----------
    camera : pipeline.config.CameraConfig
        ``position``, ``look_at``, ``up`` (mm), ``fov_deg`` (full angle across the SHORTER
        image side, pbrt's convention), ``width``, ``height``.
    width, height : int, optional
        Override the camera's image size.

    Returns
    -------
    origins, directions : (H*W, 3) float32 (directions unit)
    """
    w = int(width or camera.width)
    h = int(height or camera.height)
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
def vertex_normals(mesh) -> np.ndarray:
    """(V, 3) float32 unit vertex normals: the mesh's own, or angle-weighted ones (physics.md s6)."""
    try:
        return mesh.vertex_normals()
    except ValueError as exc:
        raise DermisError(str(exc)) from None


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


def _check_mesh(mesh) -> None:
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or not np.all(np.isfinite(v)):
        raise DermisError(f"render: mesh.vertices must be finite (V, 3), got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or f.min() < 0 or f.max() >= len(v):
        raise DermisError(f"render: mesh.faces must be (F, 3) indices into the {len(v)} "
                          f"vertices, got shape {f.shape}")
    if (mesh.uv is None) != (mesh.uv_faces is None):
        raise DermisError("render: mesh.uv and mesh.uv_faces must be given together")
    if mesh.uv_faces is not None and np.shape(mesh.uv_faces) != f.shape:
        raise DermisError(f"render: mesh.uv_faces has shape {np.shape(mesh.uv_faces)}; need "
                          f"{f.shape}")


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
        _buf(cl, env, vertex_normals(mesh)),
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
                  visibility: Visibility | None = None, cl_env=None, width: int | None = None,
                  height: int | None = None, textured: bool = True,
                  albedo_const=(0.5, 0.5, 0.5)) -> PixelSurface:
    """Camera rays through Embree, then cl/surface.cl: the shading inputs of every pixel.

    Shared by the BRDF renderer and the BSSRDF gather so both see the same surface.
    ``textured=False`` ignores the albedo texture (``albedo_const`` everywhere).
    """
    from dermis.pipeline.cl import get_env

    env_cl = cl_env or get_env()
    visibility = visibility or Visibility(mesh.vertices, mesh.faces)
    w = int(width or camera.width)
    h = int(height or camera.height)
    origins, directions = camera_rays(camera, width=w, height=h)
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
def render(mesh, light, model: str, params, camera, *, maps=None, bump: str | None = None,
           shadow_samples: int | None = None, seed: int = 0, env: EnvironmentMap | None = None,
           visibility: Visibility | None = None, asperity_base: str | None = None,
           base_params=None, cl_env=None, width: int | None = None,
           height: int | None = None, textured: bool = True, env_strategy: str = "mis",
           progress: Callable[[float], None] | None = None) -> RenderResult:
    """Render one image of ``mesh`` under ``light`` with a BRDF model.

    Parameters
    ----------
    mesh : pipeline.artifacts.Mesh
        Triangles in mm; vertex normals (else libigl angle-weighted ones); UVs and
        ``texture_srgb`` optional (albedo texture).
    light : LightConfig or sequence of LightConfig
        Point, disc, directional (several are summed, e.g. the thesis's two) or environment.
    model : {"lambert", "lafortune", "hk93", "asperity"}
    params : LambertParams, LafortuneParams, HK93Params or AsperityParams, or None
        Parameters of ``model`` (None: the model's defaults).
    camera : pipeline.config.CameraConfig
    maps : pipeline.artifacts.BakedMaps, optional
        Baked maps of a low mesh; their ``albedo_srgb`` replaces the mesh's texture.
    bump : {None, "sharp", "blur"}
        Bump-map the shading normal with ``maps.bump`` or ``maps.bump_blur`` (needs maps
        and UVs).
    shadow_samples : int, optional
        Samples per pixel for disc and environment lights (default: ``light.samples``, 16
        in the thesis).
    seed : int
        Seed of the light samples (results are deterministic for a seed and chunk size).
    env : EnvironmentMap, optional
        Pre-built map for an environment light (else from ``light.map``, cached).
    visibility : pipeline.visibility.Visibility, optional
        Embree scene of ``mesh`` built earlier (build once, render many).
    asperity_base : {"none", "lambert", "lafortune", "hk93"}, optional
        Base model under the asperity term (default ``params.base``); "none" = term alone.
    base_params : optional
        Parameters of the asperity base model (default: its defaults).
    cl_env : pipeline.cl.ClEnv, optional
    width, height : int, optional
        Override the camera's image size.
    textured : bool
        False ignores the albedo texture (the model's constant albedo everywhere), e.g. to
        render only Lafortune's specular lobes (rho_d = 0) on top of a BSSRDF image.
    env_strategy : {"mis", "luminance"}
        Sampling of environment lights (:func:`pipeline.lights.sample_lights`): "mis"
        (default) mixes luminance and cosine samples about the geometric normal.
    progress : callable(float), optional
        Called with the completed fraction in [0, 1].

    Returns
    -------
    RenderResult

    Raises
    ------
    ConfigError
        Unknown model, wrong parameter type, bad camera or light.
    DermisError
        Malformed mesh or maps, bump without maps/UVs.
    """
    from dermis.pipeline.cl import event_seconds, get_env
    import pyopencl as cl

    t_start = time.perf_counter()
    _check_mesh(mesh)
    base, bparams, asp = _resolve_model(model, params, asperity_base, base_params)
    lights = list(light) if isinstance(light, (list, tuple)) else [light]
    if bump not in (None, "sharp", "blur"):
        raise ConfigError(f"bump = {bump!r}: must be None, 'sharp' or 'blur'")
    if bump is not None and (maps is None or mesh.uv is None):
        raise DermisError(f"bump = {bump!r} needs baked maps and a mesh with UVs "
                          f"(maps {'missing' if maps is None else 'given'}, "
                          f"uv {'missing' if mesh.uv is None else 'given'})")
    if shadow_samples is not None and int(shadow_samples) < 1:
        raise ConfigError(f"shadow_samples = {shadow_samples}: must be >= 1")
    for lt in lights:
        if lt.type == "environment" and env is None:
            env = environment_map(lt)
    env_cl = cl_env or get_env()
    kernel_s = 0.0

    # ---- visibility: camera rays, Embree closest hits, surface attributes
    t0 = time.perf_counter()
    if visibility is None:
        visibility = Visibility(mesh.vertices, mesh.faces)
        scene_build = time.perf_counter() - t0
    else:
        scene_build = 0.0
    t0 = time.perf_counter()
    px = pixel_surface(mesh, camera, maps=maps, bump=bump, visibility=visibility,
                       cl_env=env_cl, width=width, height=height, textured=textured,
                       albedo_const=_fallback_albedo(base, bparams))
    w, h, hits, hit_idx, surf, texture = px.width, px.height, px.hits, px.hit_idx, px.surf, px.texture
    kernel_s += px.kernel_seconds
    ng, ns, wo = surf["geo_normal"], surf["shading_normal"], surf["wo"]
    shade_idx = px.front_idx
    t_visibility = time.perf_counter() - t0

    # ---- per-model device program and constant buffers
    prog_defines = {"DERMIS_BASE": _BASE_CODE[base], "DERMIS_ASPERITY": int(asp is not None)}
    shade_kernel = cl.Kernel(env_cl.program("shade.cl", prog_defines), "shade_samples")
    base_block = bparams.pack() if bparams is not None else np.zeros(4, np.float32)
    asp_block = asp.pack() if asp is not None else np.zeros(8, np.float32)
    base_buf = _buf(cl, env_cl, np.asarray(base_block, dtype=np.float32))
    asp_buf = _buf(cl, env_cl, np.asarray(asp_block, dtype=np.float32))
    ns_buf = _buf(cl, env_cl, ns)
    wo_buf = _buf(cl, env_cl, wo)
    albedo = surf["albedo"]
    if base == "hk93":  # the texture tints rho_ms: shade.cl expects albedo / Rd (1 = untinted)
        albedo = (albedo / bparams.texture_reference()).astype(np.float32) if texture is not None \
            else np.ones_like(albedo)
    albedo_buf = _buf(cl, env_cl, albedo)

    # ---- shadows and shading, in batches of points
    per_point = sum(1 if lt.type in ("point", "directional")
                    else int(shadow_samples or lt.samples) for lt in lights)
    chunk = max(1, CHUNK_SAMPLES // per_point)
    radiance = np.zeros((len(hit_idx), 3), dtype=np.float64)
    t_shadows = t_shading = t_sampling = 0.0
    n_shadow = n_shaded = 0
    pos = surf["position"]
    for c, start in enumerate(range(0, len(shade_idx), chunk)):
        pts = shade_idx[start:start + chunk]
        t0 = time.perf_counter()
        ls = sample_lights(lights, pos[pts], ng[pts], samples=shadow_samples, seed=(seed, c),
                           env=env, env_strategy=env_strategy)
        t_sampling += time.perf_counter() - t0
        cos_s = np.einsum("nsk,nk->ns", ls.directions, ns[pts])
        live = (cos_s > 0) & np.any(ls.weights > 0, axis=2)
        ip, isamp = np.nonzero(live)
        dirs = ls.directions[ip, isamp]
        blocked = visibility.occluded(pos[pts][ip], ng[pts][ip], dirs, ls.distance[ip, isamp])
        n_shadow += len(ip)
        keep = ~blocked
        ip, isamp, dirs = ip[keep], isamp[keep], dirs[keep]
        wts = ls.weights[ip, isamp]
        t_shadows += time.perf_counter() - t0

        t0 = time.perf_counter()
        k = len(ip)
        if k:
            gidx = pts[ip].astype(np.int32)
            out = np.empty((k, 3), dtype=np.float32)
            out_buf = cl.Buffer(env_cl.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
            ev = shade_kernel(env_cl.queue, _global_size(k), None,
                              _buf(cl, env_cl, gidx), _buf(cl, env_cl, dirs),
                              _buf(cl, env_cl, wts), np.int32(k), ns_buf, wo_buf, albedo_buf,
                              base_buf, asp_buf, out_buf)
            cl.enqueue_copy(env_cl.queue, out, out_buf, wait_for=[ev])
            env_cl.queue.finish()
            kernel_s += event_seconds(ev)
            for ch in range(3):
                radiance[:, ch] += np.bincount(gidx, weights=out[:, ch], minlength=len(hit_idx))
            n_shaded += k
        t_shading += time.perf_counter() - t0
        if progress is not None:
            progress(min(1.0, (start + len(pts)) / max(len(shade_idx), 1)))

    image = np.zeros((h * w, 3), dtype=np.float32)
    image[hit_idx] = radiance.astype(np.float32)
    bad = ~np.isfinite(image)
    nonfinite = int(bad.any(axis=1).sum())
    if nonfinite:  # never hand a NaN on; the count is recorded (tests require 0)
        image[bad] = 0.0
    mask = hits.hit.reshape(h, w)
    if progress is not None:
        progress(1.0)
    timings = {"visibility": t_visibility, "shadows": t_shadows, "shading": t_shading,
               "light_sampling": t_sampling, "kernel_seconds": kernel_s, "scene_build": scene_build,
               "total": time.perf_counter() - t_start}
    info = {
        "model": model, "base": base if asp is not None else model,
        "lights": [lt.name for lt in lights], "light_types": [lt.type for lt in lights],
        "width": w, "height": h, "samples_per_pixel": per_point, "seed": int(seed),
        "bump": bump, "textured": texture is not None, "env_strategy": env_strategy,
        "primary_rays": int(h * w), "hits": int(len(hit_idx)), "shaded_pixels": int(len(shade_idx)),
        "shadow_rays": int(n_shadow), "shaded_samples": int(n_shaded),
        "triangles": int(len(mesh.faces)), "nonfinite_pixels": nonfinite,
        "device": env_cl.description,
    }
    return RenderResult(linear=image.reshape(h, w, 3), mask=mask, timings=timings, info=info)


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
                geometry_inputs(geometry), label=f"{model} / {label} / {geometry}")


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
