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

Also here, for the renderer: :func:`triangle_tangent_frames` and :func:`bump_shading_normals`
(Blinn 1978 bump mapping with the bump map's mm scale) and a convenience
:func:`bump_shading_normals_at_hits` that starts from triangle ids and barycentrics.

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
EDT only on 128^2 tiles that need one, grown by the reach (:func:`_nearest_within`: dilation
band 3.5 -> 0.3 s, miss fill 2 -> 0.05 s); per-texel arithmetic runs on (3, m) coordinate
planes (:func:`_texel_points` 250 -> 105 ms, the texture lookup 340 -> 120 ms per 1M-texel
chunk); the rasteriser repeats per-row values instead of gathering per texel (3.9 -> 0.9 s
cold); the albedo is encoded per chunk (no 184 MB float map).
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
from scipy import ndimage

from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.artifacts import BakedMaps, Mesh, renormalise_f64
from dermis.pipeline.errors import ConfigError, DermisError
from dermis.rendering.color import linear_to_srgb, srgb_to_linear

__all__ = [
    "VERSION", "KERNELS", "bake_maps", "NAME", "node", "run", "triangle_tangent_frames", "bump_shading_normals",
    "bump_shading_normals_at_hits", "DEFAULT_MAX_DISTANCE_EDGE_FRACTION",
]

VERSION = 2
PHONG_ALPHA = 0.5   # shape factor of the Phong reference surface (see _texel_points)
KERNELS: tuple[str, ...] = ()

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
# Tolerance of the inside test, in texels: texel centres lying on a shared UV edge are taken
# by both triangles (no cracks); the duplicate is dropped afterwards.
EDGE_EPS_PX = 1e-4
# Rays start this fraction of max_distance behind the texel's point so that a high surface
# passing exactly through it (t = 0) is still reported by Embree (which uses tnear = 0).
RAY_BACKOFF_FRACTION = 1e-4
# Tile side of the windowed nearest-texel searches (_nearest_within).  On the default scene's
# dilation band (1.4M uncovered texels in 20 % of the 128^2 tiles) 128 took 0.31 CPU s, 64 0.32
# and 256 0.45, against 3.5 s for the EDT of the whole 4096^2 map.
NEAREST_TILE_PX = 128
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
# far below the 1/255 output step) -> sRGB uint8; 50x faster than pow() on 16M texels.
_ENCODE_LEVELS = 65535
_LINEAR16_TO_SRGB8 = np.rint(
    linear_to_srgb(np.arange(_ENCODE_LEVELS + 1, dtype=np.float64) / _ENCODE_LEVELS) * 255.0
).astype(np.uint8)


def _encode_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear float -> sRGB uint8, rounded to nearest (table lookup)."""
    q = np.clip(linear, 0.0, 1.0) * np.float32(_ENCODE_LEVELS) + np.float32(0.5)
    return _LINEAR16_TO_SRGB8[q.astype(np.uint16)]


_SRGB8_TO_LINEAR = srgb_to_linear(np.arange(256, dtype=np.float32) / 255.0)
# Textures up to this many texels are decoded to linear float32 once (4096^2 -> 200 MB);
# larger ones are decoded per lookup through the 256-entry table.
_DECODE_ONCE_MAX_TEXELS = 4096 * 4096


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
# UV-space rasteriser
# ----------------------------------------------------------------------------------------
def _barycentric_planes(px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Affine barycentric functions of each triangle in texel coordinates.

    px : (F, 3, 2) float64 corner positions (x = column, y = row from top).
    Returns coef (F, 3, 3) with lambda_k(x, y) = coef[:, k, 0] x + coef[:, k, 1] y + coef[:, k, 2],
    and the doubled signed area (F,).
    """
    x0, y0 = px[:, 0, 0], px[:, 0, 1]
    x1, y1 = px[:, 1, 0], px[:, 1, 1]
    x2, y2 = px[:, 2, 0], px[:, 2, 1]
    area2 = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    inv = np.divide(1.0, area2, out=np.zeros_like(area2), where=area2 != 0)
    coef = np.empty((len(px), 3, 3))
    # lambda_1 = ((x - x0)(y2 - y0) - (x2 - x0)(y - y0)) / area2
    coef[:, 1, 0] = (y2 - y0) * inv
    coef[:, 1, 1] = -(x2 - x0) * inv
    coef[:, 1, 2] = (-x0 * (y2 - y0) + (x2 - x0) * y0) * inv
    # lambda_2 = ((x1 - x0)(y - y0) - (x - x0)(y1 - y0)) / area2
    coef[:, 2, 0] = -(y1 - y0) * inv
    coef[:, 2, 1] = (x1 - x0) * inv
    coef[:, 2, 2] = (-(x1 - x0) * y0 + x0 * (y1 - y0)) * inv
    coef[:, 0] = -coef[:, 1] - coef[:, 2]
    coef[:, 0, 2] += 1.0
    return coef, area2


def _rasterise(uv: np.ndarray, uv_faces: np.ndarray, resolution: int):
    """Texel centres covered by each UV triangle (vectorised scanline fill).

    Returns (flat, tri, coef, info): flat (N,) int64 texel index row * R + col of each covered
    texel (each texel once), tri (N,) int32 its triangle, coef the barycentric planes.
    """
    r1 = resolution - 1
    tuv = np.asarray(uv, dtype=np.float64)[uv_faces]                # (F, 3, 2)
    px = np.empty_like(tuv)
    px[..., 0] = tuv[..., 0] * r1
    px[..., 1] = (1.0 - tuv[..., 1]) * r1
    coef, area2 = _barycentric_planes(px)
    degenerate = np.abs(area2) < 1e-12
    # Rows whose centres the triangle may cover, clipped to the map.
    ylo = np.maximum(np.ceil(px[..., 1].min(1) - EDGE_EPS_PX), 0)
    yhi = np.minimum(np.floor(px[..., 1].max(1) + EDGE_EPS_PX), r1)
    nrows = np.where(degenerate, 0, np.maximum(yhi - ylo + 1, 0)).astype(np.int64)
    tri_of_row = np.repeat(np.arange(len(px), dtype=np.int64), nrows)
    starts = np.cumsum(nrows) - nrows
    y = (ylo[tri_of_row] + (np.arange(len(tri_of_row)) - starts[tri_of_row])).astype(np.float64)
    # Per row: x interval where every lambda_k >= -tol_k (tol in texels times |grad lambda_k|).
    xlo = np.maximum(np.ceil(px[tri_of_row, :, 0].min(1) - EDGE_EPS_PX), 0.0)
    xhi = np.minimum(np.floor(px[tri_of_row, :, 0].max(1) + EDGE_EPS_PX), float(r1))
    c = coef[tri_of_row]                                            # (Nrows, 3, 3)
    for k in range(3):
        a, b, d = c[:, k, 0], c[:, k, 1], c[:, k, 2]
        tol = EDGE_EPS_PX * np.hypot(a, b)
        rhs = -tol - (b * y + d)                                    # need a x >= rhs
        flat_edge = np.abs(a) < 1e-14
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = rhs / a
        xlo = np.where(~flat_edge & (a > 0), np.maximum(xlo, np.ceil(bound)), xlo)
        xhi = np.where(~flat_edge & (a < 0), np.minimum(xhi, np.floor(bound)), xhi)
        xhi = np.where(flat_edge & (rhs > 0), -1.0, xhi)           # row entirely outside
    counts = np.maximum(xhi - xlo + 1, 0).astype(np.int64)
    del c
    n = int(counts.sum())
    row_start = np.cumsum(counts) - counts
    # A row's texels are consecutive: texel i of the run is (row's first texel - row_start) + i.
    # Built by np.repeat of per-row values, not per-texel gathers: on the default scene (15M
    # texels) that and int32 ids below took the rasteriser from 3.9 to 0.9 CPU s (cold process).
    flat = np.repeat(y.astype(np.int64) * resolution + xlo.astype(np.int64) - row_start, counts)
    flat += np.arange(n, dtype=np.int64)
    tri = np.repeat(tri_of_row.astype(np.int32), counts)
    # Texels claimed twice (on shared edges, or overlapping charts): keep the last claim.
    ids = np.arange(n, dtype=np.int32 if n < 2 ** 31 else np.int64)
    owner = np.full(resolution * resolution, -1, dtype=ids.dtype)
    owner[flat] = ids
    keep = owner[flat] == ids
    del owner, ids
    info = {"degenerate_uv_triangles": int(degenerate.sum()),
            "texels_claimed_twice": int(n - keep.sum())}
    return flat[keep], tri[keep], coef, info


# ----------------------------------------------------------------------------------------
# Texture lookups
# ----------------------------------------------------------------------------------------
def _bilinear(image: np.ndarray, uv: np.ndarray, lut: np.ndarray | None = None) -> np.ndarray:
    """Bilinear lookup of ``image`` (H, W[, C]) at ``uv`` (N, 2), clamp-to-edge, texel centres
    at u = col / (W - 1), v = 1 - row / (H - 1); ``lut`` maps uint8 values before weighting."""
    h, w = image.shape[:2]
    if image.ndim == 2:
        return _bilinear_planes(image.reshape(1, h * w), h, w, uv[:, 0], uv[:, 1], lut)[:, 0]
    return _bilinear_planes(_planes(image), h, w, uv[:, 0], uv[:, 1], lut)


def _planes(image: np.ndarray) -> np.ndarray:
    """(C, H * W) contiguous channel planes of an (H, W, C) image."""
    return np.ascontiguousarray(np.moveaxis(image, 2, 0)).reshape(image.shape[2], -1)


def _bilinear_planes(planes: np.ndarray, h: int, w: int, u: np.ndarray, v: np.ndarray,
                     lut: np.ndarray | None = None) -> np.ndarray:
    """:func:`_bilinear` of an image given as (C, H * W) channel planes; returns (N, C) float32.

    Each channel is weighted on its own 1-D arrays: on the default scene's 1M-texel chunks that
    took the lookup from 214 to ~80 ms against (N, C) arrays times (N, 1) weights (numpy's
    inner loop then runs over the 3 channels only).  The float64 weighting is unchanged."""
    x = np.clip(u.astype(np.float32) * (w - 1), 0, w - 1)
    y = np.clip((1.0 - v.astype(np.float32)) * (h - 1), 0, h - 1)
    x0 = np.minimum(x.astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(y.astype(np.int64), max(h - 2, 0))
    fx, fy = x - x0, y - y0                                         # float64
    i00 = y0 * w + x0
    i01 = i00 + (np.minimum(x0 + 1, w - 1) - x0)                    # clamped right neighbour
    i10 = i00 + (np.minimum(y0 + 1, h - 1) - y0) * w                # clamped lower neighbour
    i11 = i10 + (i01 - i00)
    del x, y, x0, y0
    gx, gy = 1 - fx, 1 - fy
    out = np.empty((len(fx), len(planes)), dtype=np.float32)
    for c, plane in enumerate(planes):
        def at(i):
            t = plane.take(i)
            return lut[t] if lut is not None else t.astype(np.float32)
        top = at(i00) * gx
        top += at(i01) * fx
        bottom = at(i10) * gx
        bottom += at(i11) * fx
        top *= gy
        bottom *= fy
        top += bottom
        out[:, c] = top
    return out


def _blur_weights(mask: np.ndarray, sigma: float) -> np.ndarray:
    """G * mask, the denominator of :func:`_masked_blur` (it depends on the mask only)."""
    return ndimage.gaussian_filter(mask.astype(np.float32), sigma, mode="constant", cval=0.0)


def _masked_blur(image: np.ndarray, mask: np.ndarray, sigma: float,
                 den: np.ndarray | None = None) -> np.ndarray:
    """Gaussian blur over the ``mask`` texels only (normalised convolution G*(x m) / G*m);
    zero outside the mask; sigma 0 returns a copy.  ``den``: ``_blur_weights(mask, sigma)``
    when already computed."""
    if sigma <= 0:
        return image.copy()
    num = ndimage.gaussian_filter(np.multiply(image, mask, dtype=np.result_type(image, np.float32)),
                                  sigma, mode="constant", cval=0.0)
    if den is None:
        den = _blur_weights(mask, sigma)
    # A convex mix of covered values: the clip removes only float rounding beyond their range.
    covered = image[mask]
    lo, hi = (float(covered.min()), float(covered.max())) if len(covered) else (0.0, 0.0)
    del covered
    num /= np.maximum(den, 1e-12)
    ratio = np.clip(num, lo, hi, out=num)
    ratio[~mask] = 0.0
    return ratio.astype(np.float32, copy=False)


def _nearest_fill_indices(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every texel, the (row, col) of the nearest valid texel (Euclidean, scipy EDT)."""
    return ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)


def _nearest_within(valid: np.ndarray, query: np.ndarray, reach: int,
                    tile: int = NEAREST_TILE_PX) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nearest ``valid`` texel of each ``query`` texel that has one within ``reach`` texels,
    the very one the EDT of the whole map (:func:`_nearest_fill_indices`) gives.

    Returns flat indices (row * W + col): the query texels with a valid texel within reach,
    that texel of each, and the query texels without one.

    scipy's feature transform picks, among the valid texels nearest a texel, the one of
    smallest column, then smallest row (a 1-D pass down each column, then the lower envelope
    along each row; their ties keep the first): a choice among the valid texels within that
    distance only.  So the EDT of a tile grown by ``reach`` on every side answers exactly
    for each tile texel whose nearest valid texel is within reach, and farther ones see
    nothing nearer than reach.  Only the tiles holding query texels are transformed
    (tests/test_bake.py checks this against the whole map's EDT).
    """
    h, w = valid.shape
    nty, ntx = -(-h // tile), -(-w // tile)
    padded = np.zeros((nty * tile, ntx * tile), dtype=bool)
    padded[:h, :w] = query
    busy = padded.reshape(nty, tile, ntx, tile).any(axis=(1, 3))
    del padded
    dst, src, far = [], [], []
    for ty, tx in zip(*np.nonzero(busy)):
        y0, x0 = ty * tile, tx * tile
        wy0, wx0 = max(y0 - reach, 0), max(x0 - reach, 0)
        ys, xs = np.nonzero(query[y0:y0 + tile, x0:x0 + tile])
        ys += y0 - wy0                                  # window coordinates
        xs += x0 - wx0
        win = valid[wy0:y0 + tile + reach, wx0:x0 + tile + reach]
        near = np.zeros(len(ys), dtype=bool)
        if win.any():
            iy, ix = _nearest_fill_indices(win)
            sy, sx = iy[ys, xs], ix[ys, xs]
            near = (sy - ys) ** 2 + (sx - xs) ** 2 <= reach * reach
            src.append((sy[near] + wy0).astype(np.int64) * w + sx[near] + wx0)
        dst.append((ys[near] + wy0) * w + xs[near] + wx0)
        far.append((ys[~near] + wy0) * w + xs[~near] + wx0)
    empty = np.zeros(0, dtype=np.int64)
    return tuple(np.concatenate(a) if a else empty for a in (dst, src, far))


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


@dataclass
class _HighTexture:
    """The high mesh's albedo texture as (3, H * W) channel ``planes``, linear float32, or sRGB
    uint8 with ``lut``; ``face_uv`` (F, 6) holds per high face uv0, uv1 - uv0 and uv2 - uv0
    (one row gathered per hit instead of corner indices, then corners)."""

    planes: np.ndarray
    shape: tuple[int, int]
    lut: np.ndarray | None
    face_uv: np.ndarray

    @classmethod
    def of(cls, high: Mesh) -> "_HighTexture | None":
        """The texture of ``high``, or None when it has no texture or no UVs."""
        if high.texture_srgb is None or high.uv is None:
            return None
        tex = np.asarray(high.texture_srgb)
        if tex.ndim == 2:
            tex = np.repeat(tex[..., None], 3, axis=2)
        if tex.dtype != np.uint8 or tex.ndim != 3 or tex.shape[2] < 3:
            raise DermisError(f"bake: high.texture_srgb has dtype {tex.dtype} shape {tex.shape}; "
                              "need (H, W, 3) uint8 sRGB")
        planes = _planes(tex[..., :3])
        lut = _SRGB8_TO_LINEAR
        if tex.shape[0] * tex.shape[1] <= _DECODE_ONCE_MAX_TEXELS:
            planes, lut = _SRGB8_TO_LINEAR[planes], None
        c = np.asarray(high.uv, dtype=np.float32)[np.asarray(high.uv_faces)]   # (F, 3, 2)
        face_uv = np.concatenate([c[:, 0], c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]], axis=1)
        return cls(planes, tex.shape[:2], lut, face_uv)

    def at_hits(self, ans, ray_idx: np.ndarray) -> np.ndarray:
        """Linear albedo at the hits of rays ``ray_idx``: the hit's barycentrics interpolate
        the high mesh's UVs, the texture is read bilinearly in linear RGB."""
        pid = ans["primitive_ids"].numpy().take(ray_idx)
        b = ans["primitive_uvs"].numpy().take(ray_idx, axis=0)
        f = self.face_uv.take(pid, axis=0)                                  # (k, 6)
        b1, b2 = b[:, 0], b[:, 1]
        u = f[:, 0] + b1 * f[:, 2] + b2 * f[:, 4]
        v = f[:, 1] + b1 * f[:, 3] + b2 * f[:, 5]
        del f, b
        return _bilinear_planes(self.planes, *self.shape, u, v, self.lut)

    def mean_colour(self) -> np.ndarray:
        """Mean linear colour of a <= 256^2 subsample (albedo when no texel hit anything)."""
        h, w = self.shape
        sub = self.planes.reshape(3, h, w)[:, ::max(1, h // 256), ::max(1, w // 256)]
        sub = np.ascontiguousarray(sub.reshape(3, -1).T)        # (n, 3), as the image's rows
        return (sub if self.lut is None else self.lut[sub]).mean(0)


@dataclass
class _TriangleFrames:
    """Per low triangle, float32 relative to corner 0 (mm-scale positions keep ~3e-5 mm in
    float32; the rays are float32 anyway), as (3, F) coordinate planes: position, edges,
    normals; (F, 3) face normals; and the barycentric gradients in texel space (4, F):
    lambda_1 = grad[0] dx + grad[1] dy, lambda_2 = grad[2] dx + grad[3] dy, (dx, dy) from x0, y0.

    Planes, so that every per-texel step of :func:`_texel_points` runs on contiguous 1-D
    arrays: on the default scene's 1M-texel chunks that took it from 240 to ~110 ms against
    (m, 3) arrays times (m, 1) factors (numpy's inner loop then spans 3 values)."""

    p0: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    n0: np.ndarray
    dn1: np.ndarray
    dn2: np.ndarray
    face_normals: np.ndarray
    grad: np.ndarray
    x0: np.ndarray
    y0: np.ndarray

    @classmethod
    def of(cls, vertices, faces, normals, coef, uv, uv_faces, resolution: int) -> "_TriangleFrames":
        corners_v = vertices[faces]
        corners_n = normals[faces]
        e1 = (corners_v[:, 1] - corners_v[:, 0]).astype(np.float32)
        e2 = (corners_v[:, 2] - corners_v[:, 0]).astype(np.float32)
        fn = np.cross(e1, e2)
        uvc = np.asarray(uv, dtype=np.float64)[uv_faces[:, 0]]
        plane = lambda a: np.ascontiguousarray(a.T, dtype=np.float32)  # noqa: E731
        return cls(p0=plane(corners_v[:, 0]), e1=plane(e1), e2=plane(e2),
                   n0=plane(corners_n[:, 0]),
                   dn1=plane(corners_n[:, 1] - corners_n[:, 0]),
                   dn2=plane(corners_n[:, 2] - corners_n[:, 0]),
                   face_normals=fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30),
                   grad=plane(coef[:, 1:, :2].reshape(-1, 4)),                    # (4, F)
                   x0=(uvc[:, 0] * (resolution - 1)).astype(np.float32),
                   y0=((1.0 - uvc[:, 1]) * (resolution - 1)).astype(np.float32))


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per column dot product of (3, m) planes, bit for bit ``np.einsum("nd,nd->n")`` of the
    (m, 3) arrays: float32, summed in order from a +0 accumulator (so an all -0 sum is +0)."""
    d = a[0] * b[0]
    d += a[1] * b[1]
    d += a[2] * b[2]
    d += 0.0
    return d


def _texel_points(tf: _TriangleFrames, f_idx: np.ndarray, fl: np.ndarray, resolution: int,
                  reference: str):
    """Surface point ``p``, unit interpolated normal ``nrm`` (both (3, m) planes) and reference
    height ``h_ref`` (mm along ``nrm``; 0 for "flat") at each texel ``fl`` of triangle ``f_idx``."""
    f = f_idx.astype(np.intp)
    # Barycentrics relative to corner 0 in float32: (x - x0) stays small, so no
    # cancellation (an absolute affine form would lose ~1e-4 at 4096 texels).
    dx = (fl % resolution).astype(np.float32) - tf.x0.take(f)
    dy = (fl // resolution).astype(np.float32) - tf.y0.take(f)
    g = tf.grad.take(f, axis=1)                                      # (4, m)
    l1 = np.clip(g[0] * dx + g[1] * dy, 0.0, 1.0)
    l2 = np.clip(g[2] * dx + g[3] * dy, 0.0, 1.0)
    over = l1 + l2
    np.maximum(over, 1.0, out=over)          # clip back onto the triangle (edge texels)
    l1 /= over
    l2 /= over
    del g, dx, dy, over
    e1f, e2f = tf.e1.take(f, axis=1), tf.e2.take(f, axis=1)          # (3, m)
    d0 = l1 * e1f
    d0 += l2 * e2f                                                   # p - v0
    p = tf.p0.take(f, axis=1)
    p += d0
    n0f, dn1f, dn2f = tf.n0.take(f, axis=1), tf.dn1.take(f, axis=1), tf.dn2.take(f, axis=1)
    nrm = l1 * dn1f
    np.add(n0f, nrm, out=nrm)
    nrm += l2 * dn2f
    length = np.sqrt(_dot(nrm, nrm))
    bad = length < 1e-6         # opposite vertex normals cancel: use the face normal
    if bad.any():
        nrm[:, bad] = tf.face_normals[f_idx[bad]].T
        length[bad] = 1.0
    nrm /= length
    if reference != "phong":
        return p, nrm, np.zeros(len(length), np.float32)
    # Height of the Phong-tessellated surface (Boubekeur & Alexa 2008) above the flat
    # triangle, along nrm: alpha * sum_i l_i (projection of p on vertex i's tangent
    # plane - p).  The renderer's interpolated normals already bend with that smooth
    # surface, so the bump must hold only what lies beyond it, or every triangle's dip
    # below the curved surface shows as a facet pattern.  alpha = 1/2 (not their 3/4):
    # on a sphere the full projection sum is exactly twice the chord's dip to second
    # order, so 1/2 reproduces the sphere (tests/test_bake.py test04b).
    n1f, n2f = n0f + dn1f, n0f + dn2f
    del dn1f, dn2f
    h_ref = -PHONG_ALPHA * ((1.0 - l1 - l2) * _dot(d0, n0f) * _dot(n0f, nrm)
                            + l1 * _dot(d0 - e1f, n1f) * _dot(n1f, nrm)
                            + l2 * _dot(d0 - e2f, n2f) * _dot(n2f, nrm))
    return p, nrm, h_ref


def _rays_both_ways(p: np.ndarray, nrm: np.ndarray, backoff: float) -> np.ndarray:
    """(2m, 6) float32 rays from (3, m) planes: m along +nrm, then m along -nrm, each starting
    ``backoff`` behind p."""
    m = p.shape[1]
    rays = np.empty((2 * m, 6), dtype=np.float32)
    off = np.float32(backoff) * nrm
    np.subtract(p, off, out=rays[:m, :3].T)
    rays[:m, 3:].T[...] = nrm
    np.add(p, off, out=rays[m:, :3].T)
    np.negative(nrm, out=rays[m:, 3:].T)
    return rays


def _nearest_hits(ans, nrm: np.ndarray, backoff: float, max_distance: float):
    """Per texel the nearer of its two hits within reach on a high face facing like ``nrm``
    ((3, m) planes; a back-facing hit is the far side of a thin part, never the surface ``p``
    approximates).

    Returns (signed t: +t along +nrm, -t along -nrm; got; use_f: the +nrm ray won;
    number of in-reach hits rejected as back-facing).
    """
    m = nrm.shape[1]
    t_hit = ans["t_hit"].numpy() - np.float32(backoff)
    pn = ans["primitive_normals"].numpy()
    facing = np.concatenate([_dot(pn[:m].T, nrm), _dot(pn[m:].T, nrm)]) > 0
    del pn
    in_reach = np.isfinite(t_hit) & (t_hit <= max_distance)
    rejected = int(np.count_nonzero(in_reach & ~facing))
    ok = in_reach & facing
    tf = np.where(ok[:m], t_hit[:m], np.inf)
    tb = np.where(ok[m:], t_hit[m:], np.inf)
    use_f = tf <= tb
    got = np.isfinite(np.minimum(tf, tb))
    return np.where(use_f, tf, -tb), got, use_f, rejected


def _cast_texels(scene, tf: _TriangleFrames, flat, tri, resolution, reference, max_distance,
                 texture: _HighTexture | None, timings: dict, report):
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
        p, nrm, h_ref = _texel_points(tf, tri[s:e], flat[s:e], resolution, reference)
        rays = _rays_both_ways(p, nrm, backoff)
        del p
        t1 = time.perf_counter()
        ans = scene.cast_rays(o3c.Tensor(rays))
        t2 = time.perf_counter()
        signed_t, got, use_f, rejected = _nearest_hits(ans, nrm, backoff, max_distance)
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
        dst, src, far = _nearest_within(hit_img, miss_img, MISS_FILL_REACH_PX)
        albedo[dst] = albedo[src]
        if len(far):            # misses far from every hit: the whole map's EDT
            iy, ix = _nearest_fill_indices(hit_img)
            albedo[far] = albedo[iy.ravel()[far] * resolution + ix.ravel()[far]]
    return albedo


def _mean_linear(albedo_cov: np.ndarray) -> np.ndarray:
    """``_SRGB8_TO_LINEAR[albedo_cov].mean(0)`` bit for bit (numpy sums the rows in order, in
    float32, then divides by the count) without the (N, 3) float32 copy: chunks carry the sum."""
    total = np.zeros(3, dtype=np.float32)
    for s in range(0, len(albedo_cov), CHUNK_TEXELS):
        part = _SRGB8_TO_LINEAR[albedo_cov[s:s + CHUNK_TEXELS]]
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
    dst, src, _ = _nearest_within(coverage, ~coverage, dilate_px)
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
    1. Rasterise every low triangle in UV space at texel centres (:func:`_rasterise`).
    2. Interpolate position and unit normal (:func:`_texel_points`).
    3. Cast rays both ways along the normal (Embree) and keep the nearest hit in reach on a
       face facing the same way (:func:`_nearest_hits`); height = +t along +n, -t along -n.
    4. Albedo: the high texture at the hit, bilinear in linear RGB (:class:`_HighTexture`).
    5. Texels without a hit: height 0 mm, albedo of the nearest texel with a hit (counted in
       ``info["misses"]``).
    6. Normalise heights over the covered texels to [0, 1] (``bump_min_mm``, ``bump_range_mm``).
    7. Blur by normalised convolution over the coverage mask (:func:`_masked_blur`), so chart
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
    flat, tri, coef, rast_info = _rasterise(low.uv, low.uv_faces, resolution)
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
        weights_job = (pool.submit(_timed, _blur_weights, coverage, blur_sigma_px)
                       if blur_sigma_px > 0 else None)
        t0 = time.perf_counter()
        scene = _raycasting_scene(high)
        timings["scene_build_s"] = time.perf_counter() - t0
        texture = _HighTexture.of(high)
        frames = _TriangleFrames.of(vertices, faces, renormalise_f64(low.vertex_normals()), coef,
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
        bump_blur = _masked_blur(bump, coverage, blur_sigma_px, den=weights)
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


# ----------------------------------------------------------------------------------------
# Bump mapping for the renderer
# ----------------------------------------------------------------------------------------
def triangle_tangent_frames(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                            uv_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-triangle partial derivatives of position with respect to the texture coordinates.

    Parameters
    ----------
    vertices : (V, 3) float, mm
    faces : (F, 3) int
    uv : (T, 2) float
    uv_faces : (F, 3) int, per-corner indices into ``uv``

    Returns
    -------
    dpdu, dpdv : (F, 3) float64 each, mm per unit of u (resp. v)
        Solve ``[p1 - p0, p2 - p0] = [dpdu, dpdv] @ [[u1 - u0, u2 - u0], [v1 - v0, v2 - v0]]``
        (pbrt's ``Triangle::Intersect`` derivation).  Triangles with a degenerate UV
        parameterisation (|det| < 1e-20) get zero vectors, which turns bump mapping off there.
    """
    v = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    t = np.asarray(uv, dtype=np.float64)[np.asarray(uv_faces)]
    dp1, dp2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    du1, du2 = t[:, 1, 0] - t[:, 0, 0], t[:, 2, 0] - t[:, 0, 0]
    dv1, dv2 = t[:, 1, 1] - t[:, 0, 1], t[:, 2, 1] - t[:, 0, 1]
    det = du1 * dv2 - du2 * dv1
    ok = np.abs(det) > 1e-20
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)[:, None]
    dpdu = (dv2[:, None] * dp1 - dv1[:, None] * dp2) * inv
    dpdv = (du1[:, None] * dp2 - du2[:, None] * dp1) * inv
    return dpdu, dpdv


def bump_shading_normals(normals: np.ndarray, dpdu: np.ndarray, dpdv: np.ndarray,
                         uv: np.ndarray, bump: np.ndarray, *, bump_range_mm: float,
                         step_texels: float = 1.0) -> np.ndarray:
    """Blinn bump-mapped unit shading normals at surface points.

    Parameters
    ----------
    normals : (N, 3) float
        Interpolated (smooth) shading normals of the low mesh, outward; need not be unit.
    dpdu, dpdv : (N, 3) float, mm per unit u / v
        Tangent frame of the triangle under each point (``triangle_tangent_frames()[tri]``).
    uv : (N, 2) float
        Texture coordinates of the points (bottom-left origin).
    bump : (R, R) float
        Normalised bump map (``BakedMaps.bump`` or ``bump_blur``).
    bump_range_mm : float
        mm per unit of ``bump`` (``BakedMaps.bump_range_mm``); the offset does not matter.
    step_texels : float, optional
        Half-width of the central difference, texels.  Default 1 (the map's own resolution;
        smaller steps only resolve the bilinear kinks).

    Returns
    -------
    (N, 3) float32 unit normals.  Zero bump, or zero (degenerate) tangent frames, return the
    normalised input normals unchanged.

    Notes
    -----
    The bumped surface is ``p'(u, v) = p + h(u, v) n`` with height ``h`` in mm, outward
    positive (positive ``h`` raises the surface along ``n``).  Dropping the ``h dn/du`` terms
    (Blinn 1978; pbrt's ``BumpMap`` keeps them, but they are O(h / radius of curvature), < 1 %
    for sub-mm bumps on a face) and writing ``n`` for ``dpdu x dpdv / |dpdu x dpdv|`` gives

        n' = normalize( n + s * (h_u (n x dpdv) - h_v (n x dpdu)) / |dpdu x dpdv| ),

    with ``h_u = dh/du``, ``h_v = dh/dv`` (central differences of bilinear lookups) and
    ``s = sign((dpdu x dpdv) . n)``, which is -1 on mirrored UV charts and keeps the tilt
    right there.  Check on a plane ``p = (a u, a v, 0)``: a ramp ``h = k u`` gives
    ``n' ∝ (-k / a, 0, 1)``, i.e. the normal tilts toward ``-dpdu`` by ``atan(k / a)`` --
    the exact normal of the surface ``z = k x / a``.

    References
    ----------
    J. F. Blinn, "Simulation of wrinkled surfaces", SIGGRAPH 1978, doi:10.1145/965139.507101.
    """
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    dpdu = np.asarray(dpdu, dtype=np.float64)
    dpdv = np.asarray(dpdv, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    bump = np.asarray(bump, dtype=np.float32)
    if bump.ndim != 2:
        raise DermisError(f"bump_shading_normals: bump has shape {bump.shape}; need (R, R)")
    step = np.array([step_texels / max(bump.shape[1] - 1, 1),
                     step_texels / max(bump.shape[0] - 1, 1)])
    du = np.array([step[0], 0.0])
    dv = np.array([0.0, step[1]])
    h_u = (_bilinear(bump, uv + du) - _bilinear(bump, uv - du)) * (bump_range_mm / (2 * step[0]))
    h_v = (_bilinear(bump, uv + dv) - _bilinear(bump, uv - dv)) * (bump_range_mm / (2 * step[1]))
    cross = np.cross(dpdu, dpdv)
    area = np.linalg.norm(cross, axis=1)
    sign = np.where(np.einsum("nd,nd->n", cross, n) < 0, -1.0, 1.0)
    scale = np.divide(sign, area, out=np.zeros_like(area), where=area > 1e-300)
    perturbed = n + scale[:, None] * (h_u[:, None] * np.cross(n, dpdv)
                                      - h_v[:, None] * np.cross(n, dpdu))
    out = perturbed / np.maximum(np.linalg.norm(perturbed, axis=1, keepdims=True), 1e-300)
    return out.astype(np.float32)


def bump_shading_normals_at_hits(low: Mesh, maps: BakedMaps, tri_ids: np.ndarray,
                                 bary: np.ndarray, *, blurred: bool = False) -> np.ndarray:
    """Bump-mapped shading normals at points given by low-mesh triangle and barycentrics.

    Parameters
    ----------
    low : Mesh
        The mesh the maps were baked into (uv, uv_faces; normals or libigl's).
    maps : BakedMaps
    tri_ids : (N,) int, triangle index of each point
    bary : (N, 2) float, barycentrics (b1, b2) of corners 1 and 2, as Embree's / open3d's
        ``primitive_uvs``: point = (1 - b1 - b2) p0 + b1 p1 + b2 p2
    blurred : bool, optional
        Use ``maps.bump_blur`` instead of ``maps.bump``.

    Returns
    -------
    (N, 3) float32 unit shading normals (see :func:`bump_shading_normals`).
    """
    low.check("bump mapping: low", need_uv=True)
    tri_ids = np.asarray(tri_ids, dtype=np.int64)
    b = np.asarray(bary, dtype=np.float64)
    w = np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], axis=1)
    faces = np.asarray(low.faces)
    uvf = np.asarray(low.uv_faces)
    normals = renormalise_f64(low.vertex_normals())
    n = np.einsum("nk,nkd->nd", w, normals[faces[tri_ids]])
    uv = np.einsum("nk,nkd->nd", w, np.asarray(low.uv, dtype=np.float64)[uvf[tri_ids]])
    dpdu, dpdv = triangle_tangent_frames(low.vertices, faces, low.uv, uvf)
    return bump_shading_normals(n, dpdu[tri_ids], dpdv[tri_ids], uv,
                                maps.bump_blur if blurred else maps.bump,
                                bump_range_mm=maps.bump_range_mm)


# ----------------------------------------------------------------------------------------
# Stage ``bake``: albedo and bump maps in the low mesh's UV space (sharp + Gaussian-blurred)

NAME = "bake"


def node(scene) -> Node:
    return Node(NAME, NAME, __name__, asdict(scene.bake), {"low": "mesh_low", "high": "mesh_high"},
                label="bake albedo + bump")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    maps = bake_maps(inputs["low"], inputs["high"], resolution=params["resolution"],
                     max_distance_mm=params["max_distance"] or None,
                     blur_sigma_px=params["blur_sigma_px"], dilate_px=params["dilate_px"],
                     reference=params["reference"], progress=ctx.progress)
    return StageResult(maps, info=maps.info)
