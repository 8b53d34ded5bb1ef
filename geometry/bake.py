"""Albedo and bump maps baked from the high mesh into the low mesh's UV space.

The bake follows the thesis (docs/science.md §6, "Bake"): every low-poly triangle is
rasterised in UV space, rays are cast both ways along the interpolated normal into the
high-poly mesh, the signed distance of the nearest hit becomes the bump height and the hit's
texture colour becomes the albedo; hits beyond a threshold distance are ignored.

Conventions (pipeline/artifacts.py): mm; UV origin bottom-left, so the texel centre of
column ``c`` and row ``r`` (counted from the top) of an ``R x R`` map sits at
``u = c / (R - 1)``, ``v = 1 - r / (R - 1)`` -- the same ``(1 - v) * (H - 1)`` rule used to
read the high mesh's texture.  Heights are outward positive: a positive height means the
high surface lies outside the low surface (along the low mesh's outward normal).

The steps live in :mod:`dermis.geometry.uv_raster` (the rasteriser),
:mod:`dermis.geometry.bake_texels` (each texel's point, normal, rays and hits),
:mod:`dermis.geometry.texture_lookup` (bilinear lookups) and :mod:`dermis.geometry.texture_fill`
(masked blur, nearest-texel fills); the renderer's bump mapping with the baked maps (Blinn 1978)
is :mod:`dermis.geometry.bump`.

Everything is numpy/scipy plus Embree through open3d's ``RaycastingScene``: the rasteriser is
a vectorised scanline fill (no per-texel Python loop) and measured fast enough
(bench/bench_bake.py), so no OpenCL kernel is used.

Two threads share the work (the result does not depend on it: every thread writes its own
texels).  The texels are cast in chunks taken by two threads, so one chunk's numpy steps run
while Embree casts another's rays (Embree holds the GIL but uses every core); what needs only
the coverage mask (the dilation band's distance transform, the blur's denominator) runs on a
second thread meanwhile, and after the cast the albedo's miss fill runs there while the bump
is blurred.  On the default scene (4096^2, 1.1M triangles, 2 cores) that took the node from
28 s to 18.5 s wall (bench/bench_stages.py, bench/results/stage_speed.json).

CPU seconds (all threads) then went, byte-identical, from ~36 to ~25-26 (bench_stages.py, one
run each on a shared machine; Embree's ~8.5 s of casting is left); on a quiet machine 35.8 ->
22.3 CPU s, 20.4 -> 12.7 s wall (bench/results/stage_speed_cpu.json, baseline c9ef14f).  Nearest-texel fills run an
EDT only on 128^2 tiles that need one, grown by the reach (:func:`nearest_within`: dilation
band 3.5 -> 0.3 s, miss fill 2 -> 0.05 s); per-texel arithmetic runs on (3, m) coordinate
planes (:func:`texel_points` 250 -> 105 ms, the texture lookup 340 -> 120 ms per 1M-texel
chunk); the rasteriser repeats per-row values instead of gathering per texel (3.9 -> 0.9 s
cold); the albedo is encoded per chunk (no 184 MB float map).
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

from dermis.geometry.bake_texels import (HighTexture, TriangleFrames, nearest_hits, rays_both_ways,
                                         texel_points)
from dermis.geometry.texture_fill import (blur_weights, masked_blur, nearest_fill_indices,
                                          nearest_within)
from dermis.geometry.texture_lookup import SRGB8_TO_LINEAR
from dermis.geometry.uv_raster import rasterise
from dermis.pipeline.artifacts import BakedMaps, Mesh
from dermis.pipeline.errors import ConfigError, DermisError
from dermis.rendering.color import linear_to_srgb8
from dermis.geometry.normals import renormalise_f64, vertex_normals

__all__ = ["bake_maps", "DEFAULT_MAX_DISTANCE_EDGE_FRACTION", "MAX_RESOLUTION"]

# Default ray length: half the low mesh's mean edge length.  The low mesh deviates from the
# high one by the simplification error, which quadric simplification keeps well below an edge
# length (Garland-Heckbert 1997), plus the displacement detail (pores/wrinkles, sub-mm to a
# few mm on a face); a longer reach starts to find the far side of thin parts (ears, nostrils).
DEFAULT_MAX_DISTANCE_EDGE_FRACTION = 0.5
# Largest map side accepted: 16384^2 texels is ~1 GB per RGB uint8 map; beyond that the
# memory budget of mesh prep (architecture: <= 4 GB) cannot hold.
MAX_RESOLUTION = 16384
# Texels per ray-casting chunk: bounds the per-chunk arrays (2 rays per texel, ~150 B per
# texel in flight) to ~150 MB while keeping Embree's per-call overhead negligible.
CHUNK_TEXELS = 1 << 20
# Threads that take the chunks (see _cast_texels): two overlap one chunk's numpy steps with
# another's ray casting on the 2-core reference machine.
CHUNK_THREADS = 2
# Rays start this fraction of max_distance behind the texel's point so that a high surface
# passing exactly through it (t = 0) is still reported by Embree (which uses tnear = 0).
RAY_BACKOFF_FRACTION = 1e-4
# Reach of the miss fill's windowed search (texels); misses farther from every hit fall back
# to the whole map's EDT.  On the default scene the 939 misses lie <= 4 texels from a hit.
MISS_FILL_REACH_PX = 16
# Neutral sRGB grey used for albedo only when nothing at all can be looked up (no texture on
# the high mesh, no hit): 0.5 linear reflectance.
NEUTRAL_LINEAR_ALBEDO = 0.5


# ----------------------------------------------------------------------------------------
# Colour helpers (the sRGB curves themselves live in rendering.color)
# ----------------------------------------------------------------------------------------
# Encoding table: linear quantised to 1/65535 (an sRGB step of <= 12.92 / 65535 = 2e-4,
# far below the 1/255 output step) -> sRGB uint8; 50x faster than pow() on 16M texels.  Against
# linear_to_srgb8 of the unquantised value it differs by one level (never more) on 0.10 % of the
# float32 values in [0, 1] (1,095,183 of 1,065,353,217, all of them compared).
_ENCODE_LEVELS = 65535
_LINEAR16_TO_SRGB8 = linear_to_srgb8(np.arange(_ENCODE_LEVELS + 1, dtype=np.float64) / _ENCODE_LEVELS)


def _encode_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear float -> sRGB uint8, rounded to nearest (table lookup)."""
    q = np.clip(linear, 0.0, 1.0) * np.float32(_ENCODE_LEVELS) + np.float32(0.5)
    return _LINEAR16_TO_SRGB8[q.astype(np.uint16)]


# ----------------------------------------------------------------------------------------
# Validation
# ----------------------------------------------------------------------------------------
def _check_options(resolution, max_distance_mm, blur_sigma_px, dilate_px, reference) -> None:
    """Raise ConfigError naming the first bad option."""
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) \
            or not 2 <= resolution <= MAX_RESOLUTION:
        raise ConfigError(f"bake: resolution = {resolution!r}: must be an integer in "
                          f"[2, {MAX_RESOLUTION}] (texels per side)")
    if max_distance_mm is not None and not (np.isfinite(max_distance_mm) and max_distance_mm > 0):
        raise ConfigError(f"bake: max_distance_mm = {max_distance_mm!r}: must be > 0 (mm) or None "
                          f"(default: {DEFAULT_MAX_DISTANCE_EDGE_FRACTION} x mean low edge length)")
    if not (np.isfinite(blur_sigma_px) and blur_sigma_px >= 0):
        raise ConfigError(f"bake: blur_sigma_px = {blur_sigma_px!r}: must be >= 0 (texels)")
    if isinstance(dilate_px, bool) or not isinstance(dilate_px, (int, np.integer)) or dilate_px < 0:
        raise ConfigError(f"bake: dilate_px = {dilate_px!r}: must be an integer >= 0 (texels)")
    if reference not in ("phong", "flat"):
        raise ConfigError(f"bake.reference = {reference!r}: must be 'phong' or 'flat'")


def _mean_edge_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Mean length of the face edges (each interior edge counted twice: same mean)."""
    v = vertices[faces]
    e = np.concatenate([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]])
    return float(np.linalg.norm(e, axis=1).mean())


# ----------------------------------------------------------------------------------------
# Steps of the bake
# ----------------------------------------------------------------------------------------
def _max_distance(vertices: np.ndarray, faces: np.ndarray, max_distance_mm) -> tuple[float, str]:
    """Ray reach in mm and the rule that gave it."""
    if max_distance_mm is None:
        return (DEFAULT_MAX_DISTANCE_EDGE_FRACTION * _mean_edge_length(vertices, faces),
                f"{DEFAULT_MAX_DISTANCE_EDGE_FRACTION} x mean low edge length")
    return float(max_distance_mm), "given"


def _raycasting_scene(high: Mesh):
    """Embree scene of the high mesh (open3d ``RaycastingScene``)."""
    import open3d as o3d
    import open3d.core as o3c
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3c.Tensor(np.ascontiguousarray(high.vertices, dtype=np.float32)),
                        o3c.Tensor(np.ascontiguousarray(high.faces, dtype=np.uint32)))
    return scene


def _cast_texels(scene, tf: TriangleFrames, flat, tri, resolution, reference, max_distance,
                 texture: HighTexture | None, timings: dict, report):
    """Steps 2-4 in chunks of ``CHUNK_TEXELS``: heights, hit flags, sRGB albedo per texel
    and the count of back-facing rejections.  Chunks are independent and write disjoint
    slices, so ``CHUNK_THREADS`` threads take them: one chunk's numpy steps (which release
    the GIL) run while another's rays are cast (Embree on every core; it holds the GIL)."""
    import open3d.core as o3c
    n_cov = len(flat)
    height = np.zeros(n_cov, dtype=np.float32)
    hit = np.zeros(n_cov, dtype=bool)
    albedo = np.zeros((n_cov, 3), dtype=np.uint8)
    backoff = RAY_BACKOFF_FRACTION * max_distance

    def chunk(s: int):
        """Cast chunk ``[s, s + CHUNK_TEXELS)``; returns (rejected rays, seconds per step)."""
        e = min(s + CHUNK_TEXELS, n_cov)
        t0 = time.perf_counter()
        p, nrm, h_ref = texel_points(tf, tri[s:e], flat[s:e], resolution, reference)
        rays = rays_both_ways(p, nrm, backoff)
        del p
        t1 = time.perf_counter()
        ans = scene.cast_rays(o3c.Tensor(rays))
        t2 = time.perf_counter()
        signed_t, got, use_f, rejected = nearest_hits(ans, nrm, backoff, max_distance)
        height[s:e] = np.where(got, signed_t - h_ref, 0.0)
        hit[s:e] = got
        if texture is not None:
            lin = np.zeros((e - s, 3), dtype=np.float32)
            if got.any():
                sel = np.nonzero(got)[0]
                lin[sel] = texture.at_hits(ans, np.where(use_f[sel], sel, sel + (e - s)))
            albedo[s:e] = _encode_srgb8(lin)   # per chunk: no (N, 3) float32 map (184 MB)
        return rejected, (t1 - t0, t2 - t1, time.perf_counter() - t2), e

    rejected_backfacing = 0
    seconds = np.zeros(3)
    with ThreadPoolExecutor(max_workers=CHUNK_THREADS) as pool:
        for rejected, step_seconds, e in pool.map(chunk, range(0, n_cov, CHUNK_TEXELS)):
            rejected_backfacing += rejected
            seconds += step_seconds
            report(0.05 + 0.75 * e / n_cov)
    # summed over the chunks (so over both threads: they can add up to more than the wall time)
    timings["interpolate_s"], timings["raycast_s"], timings["hit_lookup_s"] = seconds.tolist()
    return height, hit, albedo, rejected_backfacing


def _albedo_without_texture_or_hits(albedo_cov: np.ndarray, texture, n_hit: int) -> str:
    """In place on the sRGB albedo: neutral grey without a texture, the mean texture colour
    when no texel hit.  Returns the albedo source recorded in ``info``."""
    if texture is None:
        albedo_cov[:] = _encode_srgb8(np.full(3, NEUTRAL_LINEAR_ALBEDO, dtype=np.float32))
        return "neutral grey (high mesh has no texture_srgb/uv)"
    if n_hit == 0:
        albedo_cov[:] = _encode_srgb8(np.full(3, texture.mean_colour(), dtype=np.float32))
        return "no hit: mean texture colour"
    return "high texture"


def _albedo_image(albedo_cov: np.ndarray, flat, resolution: int, hit) -> np.ndarray:
    """Step 5: the (R*R, 3) sRGB map; unless ``hit`` is None, covered texels without a hit
    take the albedo of the nearest texel with one (docs/science.md §6: the thesis leaves it open)."""
    n_pix = resolution * resolution
    albedo = np.zeros((n_pix, 3), dtype=np.uint8)
    # 3-byte texels as one void item each: half the time of the (N, 3) row scatter (0.25 s)
    albedo.view("V3").ravel()[flat] = np.ascontiguousarray(albedo_cov).view("V3").ravel()
    if hit is not None and 0 < hit.sum() < len(flat):
        hit_img = np.zeros(n_pix, dtype=bool)
        hit_img[flat] = hit
        miss_img = np.zeros(n_pix, dtype=bool)
        miss_img[flat[~hit]] = True
        hit_img, miss_img = (a.reshape(resolution, resolution) for a in (hit_img, miss_img))
        dst, src, far = nearest_within(hit_img, miss_img, MISS_FILL_REACH_PX)
        albedo[dst] = albedo[src]
        if len(far):            # misses far from every hit: the whole map's EDT
            iy, ix = nearest_fill_indices(hit_img)
            albedo[far] = albedo[iy.ravel()[far] * resolution + ix.ravel()[far]]
    return albedo


def _mean_linear(albedo_cov: np.ndarray) -> np.ndarray:
    """``SRGB8_TO_LINEAR[albedo_cov].mean(0)`` bit for bit (numpy sums the rows in order, in
    float32, then divides by the count) without the (N, 3) float32 copy: chunks carry the sum."""
    total = np.zeros(3, dtype=np.float32)
    for s in range(0, len(albedo_cov), CHUNK_TEXELS):
        part = SRGB8_TO_LINEAR[albedo_cov[s:s + CHUNK_TEXELS]]
        part[0] += total
        total = part.sum(0)
    return np.true_divide(total, np.intp(len(albedo_cov)), out=total, casting="unsafe")


def _coverage(flat, resolution: int) -> np.ndarray:
    """(R, R) bool mask of the texels some low triangle covers."""
    coverage = np.zeros(resolution * resolution, dtype=bool)
    coverage[flat] = True
    return coverage.reshape(resolution, resolution)


def _normalised_bump(height: np.ndarray, flat, resolution: int):
    """Step 6: (bump in [0, 1], h_min, h_max, neutral bump of 0 mm) over covered texels."""
    h_min, h_max = float(height.min()), float(height.max())
    h_range = h_max - h_min
    bump = np.zeros(resolution * resolution, dtype=np.float32)
    if h_range > 0:
        bump[flat] = (height - np.float32(h_min)) / np.float32(h_range)
    neutral = float(np.clip((0.0 - h_min) / h_range, 0.0, 1.0)) if h_range > 0 else 0.0
    return bump.reshape(resolution, resolution), h_min, h_max, neutral


def _dilation_band(coverage: np.ndarray, dilate_px: int):
    """Texels within ``dilate_px`` outside the charts and the covered texel each copies:
    (band mask, (rows, cols) of the band texels, (rows, cols) of their sources), or None when
    everything is covered."""
    if coverage.all():
        return None
    dst, src, _ = nearest_within(coverage, ~coverage, dilate_px)
    band = np.zeros(coverage.size, dtype=bool)
    band[dst] = True
    w = coverage.shape[1]
    return band.reshape(coverage.shape), divmod(dst, w), divmod(src, w)


def _dilate(coverage: np.ndarray, dilation_band, maps_and_far_values) -> int:
    """Step 8, in place: texels of the band (:func:`_dilation_band`) take the nearest covered
    texel's value, farther ones the given neutral value.  Returns the band's texel count."""
    if dilation_band is None:
        return 0
    band, dst, src = dilation_band
    for image, _ in maps_and_far_values:
        image[dst] = image[src]
    far = ~(band | coverage)
    for image, far_value in maps_and_far_values:
        image[far] = far_value
    return len(dst[0])


# ----------------------------------------------------------------------------------------
# The bake
# ----------------------------------------------------------------------------------------
def _timed(fn, *args):
    """(fn(*args), its wall seconds): the timing of a step run on the second thread."""
    t0 = time.perf_counter()
    return fn(*args), time.perf_counter() - t0


def bake_maps(low: Mesh, high: Mesh, *, resolution: int = 4096, max_distance_mm: float | None = None,
              blur_sigma_px: float = 8.0, dilate_px: int = 16, reference: str = "phong",
              progress: Callable[[float], None] | None = None) -> BakedMaps:
    """Bake albedo and bump maps of ``high`` into the UV space of ``low`` (docs/science.md §6).

    Parameters
    ----------
    low : Mesh
        The simplified mesh, mm, with ``uv`` + ``uv_faces`` (per corner, seams allowed);
        ``normals`` (angle-weighted ones when None).
    high : Mesh
        The detailed mesh, mm, faces counter-clockwise seen from outside.  ``uv``/``uv_faces``
        and ``texture_srgb`` (H, W, 3) uint8 give the albedo; without them the albedo is a
        neutral grey (recorded in ``info["albedo_source"]``).
    resolution : int
        Side of the square maps in texels, 2..16384.
    max_distance_mm : float or None
        Longest accepted distance from the low surface to a high-mesh hit, mm.  Default
        ``DEFAULT_MAX_DISTANCE_EDGE_FRACTION`` (0.5) times the low mesh's mean edge length.
    blur_sigma_px : float
        Gaussian sigma of ``bump_blur``, texels (0 gives a copy).
    dilate_px : int
        Width in texels of the band outside the charts filled with the nearest chart texel.
    reference : {"phong", "flat"}
        Surface the heights are measured from: the low mesh's Phong-tessellated smooth
        surface, which the renderer's interpolated normals already describe, or the flat
        triangle (the thesis's literal rule: on a coarse mesh it shows as a facet pattern).
    progress : callable, optional
        Called with the completed fraction in [0, 1].

    Returns
    -------
    BakedMaps
        ``info`` has hit/miss counts, ``max_distance_mm`` and its rule, per-step timings (s).

    Raises
    ------
    ConfigError
        A bad option (named) or a low mesh without UVs.
    DermisError
        Malformed meshes, or UVs that cover no texel centre.

    Notes
    -----
    1. Rasterise every low triangle in UV space at texel centres (:func:`rasterise`).
    2. Interpolate position and unit normal (:func:`texel_points`).
    3. Cast rays both ways along the normal (Embree) and keep the nearest hit in reach on a
       face facing the same way (:func:`nearest_hits`); height = +t along +n, -t along -n.
    4. Albedo: the high texture at the hit, bilinear in linear RGB (:class:`HighTexture`).
    5. Texels without a hit: height 0 mm, albedo of the nearest texel with a hit (counted in
       ``info["misses"]``).
    6. Normalise heights over the covered texels to [0, 1] (``bump_min_mm``, ``bump_range_mm``).
    7. Blur by normalised convolution over the coverage mask (:func:`masked_blur`), so chart
       borders are not pulled toward the dilated background.
    8. Dilate all three maps past chart borders (:func:`_dilate`); texels farther out get 0 mm
       height and the mean covered albedo.
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    _check_options(resolution, max_distance_mm, blur_sigma_px, dilate_px, reference)
    low.check("bake: low", need_uv=True)
    high.check("bake: high")
    resolution = int(resolution)
    report = progress if progress is not None else (lambda _f: None)
    vertices = np.asarray(low.vertices, dtype=np.float64)
    faces = np.asarray(low.faces, dtype=np.int64)
    max_distance, distance_rule = _max_distance(vertices, faces, max_distance_mm)

    t0 = time.perf_counter()
    flat, tri, coef, rast_info = rasterise(low.uv, low.uv_faces, resolution)
    timings["rasterise_s"] = time.perf_counter() - t0
    n_cov = len(flat)
    if n_cov == 0:
        raise DermisError(f"bake: low.uv covers no texel centre of a {resolution}^2 map; "
                          "UVs must lie inside [0, 1]^2 and the resolution must be large enough")
    report(0.05)
    # Work that needs only the coverage mask (the dilation band and the blur's denominator,
    # scipy, GIL released) runs on a second thread while the rays are cast.
    coverage = _coverage(flat, resolution)
    with ThreadPoolExecutor(max_workers=1) as pool:
        band_job = pool.submit(_timed, _dilation_band, coverage, dilate_px)
        weights_job = (pool.submit(_timed, blur_weights, coverage, blur_sigma_px)
                       if blur_sigma_px > 0 else None)
        t0 = time.perf_counter()
        scene = _raycasting_scene(high)
        timings["scene_build_s"] = time.perf_counter() - t0
        texture = HighTexture.of(high)
        frames = TriangleFrames.of(vertices, faces, renormalise_f64(vertex_normals(low)), coef,
                                   low.uv, np.asarray(low.uv_faces), resolution)
        height, hit, albedo_cov, rejected_backfacing = _cast_texels(
            scene, frames, flat, tri, resolution, reference, max_distance, texture, timings,
            report)
        del scene, coef, frames
        n_hit = int(hit.sum())

        # The albedo's miss fill (a distance transform of the hit mask) on the second thread,
        # the bump and its blur here.
        t0 = time.perf_counter()
        albedo_source = _albedo_without_texture_or_hits(albedo_cov, texture, n_hit)
        mean_albedo = _encode_srgb8(_mean_linear(albedo_cov))
        albedo_job = pool.submit(_timed, _albedo_image, albedo_cov, flat, resolution,
                                 hit if texture is not None else None)
        timings["albedo_encode_s"] = time.perf_counter() - t0
        report(0.85)

        bump, h_min, h_max, neutral_bump = _normalised_bump(height, flat, resolution)
        del height
        t0 = time.perf_counter()
        weights = None
        if weights_job is not None:
            weights, timings["blur_weights_s"] = weights_job.result()
        bump_blur = masked_blur(bump, coverage, blur_sigma_px, den=weights)
        del weights
        timings["blur_s"] = time.perf_counter() - t0
        report(0.9)
        albedo, timings["miss_fill_s"] = albedo_job.result()
        albedo = albedo.reshape(resolution, resolution, 3)
        dilation_band, timings["dilation_band_s"] = band_job.result()

    t0 = time.perf_counter()
    n_band = _dilate(coverage, dilation_band, [(albedo, mean_albedo), (bump, neutral_bump),
                                                (bump_blur, neutral_bump)])
    timings["dilate_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    report(1.0)
    info = {
        "resolution": resolution, "covered_texels": n_cov, "hits": n_hit, "misses": n_cov - n_hit,
        "rejected_backfacing_rays": rejected_backfacing, "max_distance_mm": max_distance,
        "max_distance_rule": distance_rule, "height_min_mm": h_min, "height_max_mm": h_max,
        "miss_height_mm": 0.0, "height_reference": reference, "dilated_texels": n_band,
        "dilate_px": int(dilate_px), "albedo_source": albedo_source,
        "blur": "normalised convolution over covered texels (mode=constant)",
        "low_triangles": int(len(faces)), "high_triangles": int(len(high.faces)),
        "timings": {k: round(v, 4) for k, v in timings.items()},
        **rast_info,
    }
    return BakedMaps(albedo_srgb=albedo, bump=bump, bump_blur=bump_blur, coverage=coverage,
                     bump_min_mm=h_min, bump_range_mm=h_max - h_min,
                     blur_sigma_px=float(blur_sigma_px), info=info)
