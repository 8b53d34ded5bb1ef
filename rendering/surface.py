"""The surface seen through each pixel: ``cl/surface.cl`` at the camera hits of the shared
visibility (position, two-sided geometric normal, shading normal bump-mapped from the baked
map for the low-mesh variants and bent towards the viewer where it faced away, UV, linear
albedo), the per-pixel box filter over a pixel's camera samples (:class:`PixelSurface`), and
the run's one surface pass per geometry shared by its images.

Shared by the BRDF renderer (``rendering/shade.py``) and the BSSRDF gather
(``stages/bssrdf.py``), so both see the same surface.  Conventions: mm, linear RGB, pixel
index row-major from the top-left.  Guarded by tests/test_render.py.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from dermis.pipeline.artifacts import PixelSamples
from dermis.pipeline.cl import event_seconds, get_env, to_device
from dermis.pipeline.errors import ConfigError, DermisError
from dermis.pipeline.reuse import content_key
from dermis.pipeline.shared import RunCache, Shared
from dermis.rendering.color import srgb_to_linear
from dermis.rendering.options import RenderOptions
from dermis.geometry.normals import vertex_normals

__all__ = ["KERNELS", "PixelSurface", "pixel_surface", "surface_attributes", "global_size",
           "SURFACE_CACHE_SIZE"]

KERNELS = ("surface.cl",)


def global_size(n: int) -> tuple[int]:
    """The global NDRange of ``n`` work-items (one per item), rounded up to a multiple of 64."""
    return (max(64, -(-n // 64) * 64),)


def surface_attributes(env, mesh, hits_tri, hits_bary, camera_pos, *, texture=None,
                       bump_map=None, bump_range=0.0, albedo_const=(0.5, 0.5, 0.5)):
    """Run cl/surface.cl on the hits: dict of (M, k) float32 arrays (position, geo_normal,
    shading_normal, wo, uv, albedo) and the kernel seconds.

    Normals are two-sided (both face the camera) and the shading normal is bent to at least
    ``NS_MIN_COS`` towards the camera (cl/surface.cl), so every hit can be shaded.
    """
    import pyopencl as cl  # optional until a kernel runs (pipeline/cl.py NoOpenCLError)

    m = len(hits_tri)
    has_uv = mesh.uv is not None
    defines = {"HAS_UV": int(has_uv), "HAS_TEXTURE": int(texture is not None and has_uv),
               "HAS_BUMP": int(bump_map is not None and has_uv)}
    kern = cl.Kernel(env.program("surface.cl", defines), "surface")
    lut = srgb_to_linear(np.arange(256, dtype=np.float32) / 255.0).astype(np.float32)
    tex = texture if texture is not None else np.zeros((1, 1, 3), np.uint8)
    bmp = bump_map if bump_map is not None else np.zeros((1, 1), np.float32)
    ins = [
        to_device(env, np.asarray(hits_tri, dtype=np.int32)),
        to_device(env, np.asarray(hits_bary, dtype=np.float32)),
        np.int32(m),
        to_device(env, np.asarray(mesh.vertices, dtype=np.float32)),
        to_device(env, np.asarray(mesh.faces, dtype=np.int32)),
        to_device(env, vertex_normals(mesh)),
        to_device(env, np.asarray(mesh.uv if has_uv else np.zeros((1, 2)), dtype=np.float32)),
        to_device(env, np.asarray(mesh.uv_faces if has_uv else np.zeros((1, 3)), dtype=np.int32)),
        to_device(env, np.ascontiguousarray(tex, dtype=np.uint8)),
        np.int32(tex.shape[1]), np.int32(tex.shape[0]), to_device(env, lut),
        to_device(env, np.asarray(bmp, dtype=np.float32)),
        np.int32(bmp.shape[1]), np.int32(bmp.shape[0]), np.float32(bump_range),
        *(np.float32(c) for c in camera_pos),
    ]
    shapes = {"position": 3, "geo_normal": 3, "shading_normal": 3, "wo": 3, "uv": 2,
              "albedo": 3}
    outs = {k: np.empty((max(m, 1), c), dtype=np.float32) for k, c in shapes.items()}
    bufs = {k: cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, a.nbytes) for k, a in outs.items()}
    ev = kern(env.queue, global_size(m), None, *ins, *bufs.values(),
              *(np.float32(c) for c in albedo_const))
    for k in outs:
        cl.enqueue_copy(env.queue, outs[k], bufs[k], wait_for=[ev])
    env.queue.finish()
    return {k: v[:m] for k, v in outs.items()}, event_seconds(ev)


def check_bump(mesh, maps, bump) -> None:
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
# the BSSRDF and its surface term) share one camera cast (rendering/cast.py), so without
# it they computed the same attributes ~20 times over (0.3-1.3 s per image; 0.06 s shared):
# the 36 BRDF images of the 48-image matrix went from 29.3 to 14.7 s of node time with the
# bake, samples and light-sampling speed-ups (bench/results/pipeline_default_48.json, per_stage
# and before).
SURFACE_CACHE_SIZE = 3
SURFACES = Shared("pixel_surface", keep=SURFACE_CACHE_SIZE)


def pixel_surface(mesh, camera, samples: PixelSamples,
                  options: RenderOptions = RenderOptions(), *, albedo_const=(0.5, 0.5, 0.5),
                  cl_env=None, shared: RunCache | None = None,
                  keys: tuple | None = None) -> PixelSurface:
    """cl/surface.cl at the camera hits of ``samples``: the shading inputs of every hit.

    ``samples`` : the visibility artifact (:func:`dermis.rendering.cast.cast`).
    ``options`` : its ``maps``, ``bump`` and ``textured`` are read; ``textured=False`` ignores
    the albedo texture (``albedo_const`` everywhere).
    ``shared`` : the run's shared intermediates: the attributes of a geometry are then
    computed once per run (``SURFACE_CACHE_SIZE`` geometries kept) and shared read-only by its
    images.  ``keys`` : the content keys of the mesh and the maps (their nodes' cache keys);
    by default digests of the arrays read.
    """
    env_cl = cl_env or get_env()
    maps, bump = options.maps, options.bump
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
    if keys is None and shared is not None:
        keys = tuple(None if a is None else content_key(a)
                     for a in (np.asarray(mesh.vertices), texture, bump_map))
    surf, ks, seconds = compute() if shared is None else _shared_surface(
        shared, (tuple(keys), options.bump if maps is not None else None, texture is None),
        (bump_range, tuple(cam_pos)), samples, compute)
    if texture is None or not options.textured:
        # cl/surface.cl writes the constant as the albedo of every hit when it has no texture:
        # the same float32 values, so the shared attributes serve every albedo
        texture = None
        surf = {**surf, "albedo": np.broadcast_to(const, surf["albedo"].shape)}
    m = len(samples.tri)
    return PixelSurface(samples.width, samples.height, samples.spp,
                        samples.pixel.astype(np.int64), surf, np.arange(m), samples, texture, ks,
                        seconds)


def _shared_surface(shared: RunCache, inputs: tuple, values: tuple, samples, compute):
    """``compute()``'s (surf, kernel seconds, seconds), once per run for equal inputs: keyed by
    ``inputs`` (the content keys of the mesh and maps, the bump variant, whether a texture is
    read), ``values`` and the content of the camera hits (each lighting condition's
    visibility node holds its own copy of the same hits; the cast stored their fingerprint).
    The arrays are shared read-only; a reuse reports 0 kernel seconds (no kernel ran)."""
    def make():
        surf, ks, seconds = compute()
        for a in surf.values():
            a.setflags(write=False)
        return surf, ks, seconds
    hits = ((samples.info or {}).get("camera_hits_key")      # rendering/cast.py cast
            or content_key(samples.tri, samples.bary))
    (surf, ks, seconds), made = shared.get_made(SURFACES, (inputs, values, hits), make)
    return surf, (ks if made else 0.0), seconds

