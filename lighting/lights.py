"""Light sampling shared by the BRDF renderer and the BSSRDF irradiance stage (docs/science.md §6).

Every light type answers one question: for surface points ``p`` (N, 3) with normals ``n``,
give S samples per point of

* ``directions`` (N, S, 3): unit vectors from the point towards the light sample,
* ``weights`` (N, S, 3): the sample's RGB contribution, defined so that the reflected
  radiance estimate is ``sum_s f(wo, wi_s) * weights_s * cos(theta_s) * V_s`` and the
  irradiance estimate ``sum_s weights_s * cos(theta_s) * V_s`` (V: 1 if unoccluded),
* ``distance`` (N, S): distance to the sample in mm (``inf`` for lights at infinity), the
  shadow ray's length.

Weights of samples below the horizon of ``normals`` (cos <= 0) are 0, so callers skip them
(no shadow ray is traced for them).

Light types (``pipeline.config.LightConfig``, lengths in mm):

* ``point`` - intensity I (RGB, per steradian): weight = I / d^2 (inverse square).
* ``directional`` - ``intensity`` is the irradiance E on a surface facing the light:
  weight = E.  Any number of them may be given at once (a list of lights concatenates the
  samples; the thesis preset uses two, front-left and front-right).
* ``disc`` - radius r, axis ``direction``, ``intensity`` I = the on-axis intensity, so the
  radiance is L = I / (pi r^2) and the disc tends to a point light of intensity
  I |cos theta_l| as r -> 0.  **Decision: the disc emits from both faces (|cos theta_l|)**,
  so the sign of the scene's ``direction`` cannot silently turn the light off; only the axis
  matters.  Samples: S points stratified on the disc (jittered sqrt(S) x sqrt(S) grid when S
  is a square, Latin hypercube otherwise) through Shirley & Chiu's concentric map (area
  preserving), area-sampling estimator weight = L |cos theta_l| (pi r^2) / (d^2 S).
  Default S = 16, r = 70 mm (thesis, docs/science.md §6).
* ``environment`` - a lat-long radiance map: an HDR/EXR read with OpenImageIO or the
  embedded procedural sunset sky (sun 3 deg above the horizon, thesis).  Three strategies
  (``env_strategy``):

  - ``"luminance"``: S samples importance sampled by pixel luminance x sin(theta) (the
    pixel's solid angle), stratified in the flattened CDF; weight = L / (S p_env).
  - ``"mis"``: multiple importance sampling (Veach &
    Guibas 1995; Veach's thesis 1997, ch. 9).  n_cos = round(3 S / 8) samples (6 of 16)
    from the cosine-weighted hemisphere around the normal, p_cos = cos/pi (Malley's method
    on a stratified concentric disc), and n_env = S - n_cos from p_env as above, combined
    with the balance heuristic: every sample, whichever strategy drew it, gets weight
    L / (n_env p_env + n_cos p_cos), both pdfs evaluated at its direction.  Unbiased
    wherever either pdf covers the integrand (p_cos covers the whole upper hemisphere).
    Why: 67 % of the procedural sunset's luminance mass is the sun 3 deg above the horizon;
    on surfaces facing away from it (or where it is occluded) luminance sampling spends most
    of the S samples on a zero contribution and the sky is estimated from one or two.
    Measured on the procedural sunset at S = 16 (relative std of one point's estimate,
    luminance -> mis): normal 60 deg above the anti-sun direction 36 % -> 13 %, anti-sun
    62 % -> 18 %, straight down 42 % -> 7 %, up 6.9 % -> 2.7 %, sun-facing 7.2 % -> 6.2 %.
    Choices, measured on the same normals (see MIS_COSINE_FRACTION): 3/8 of the samples
    beats 1/4 and 1/2 (half leaves too few luminance samples for the sun: 9.2 % on the
    sun-facing point); the balance heuristic beats the power heuristic (beta = 2) on the
    sky-lit normals (up: 2.7 % vs 4.8 %) and ties elsewhere, and is simpler.  With S = 1 or
    without normals the luminance strategy is used.
  - ``"product"`` (default when normals are given): as "mis", but the first strategy samples
    luminance x cosine: the map's luminance mass in ~64 x 128 blocks of pixels is weighted
    by the cosine between each block and the normal, tabulated for 16 x 32 lat-long bins of
    normals (the cosine padded by the block's and the bin's angular radius so no block
    partly above a normal's horizon is left out), then the pixel inside the block by its
    luminance (EnvironmentMap._product; the pdf is the table's, so the estimate stays
    unbiased, and the cosine strategy covers what a bin's table misses).  Luminance
    samples below a surface's horizon - for a face under a sunset, every sun sample of the
    sides turned from the sun - are no longer drawn.  floor(S / 4) >= 1 cosine samples
    (PRODUCT_COSINE_FRACTION).  Measured on the Lee Perry-Smith head under the Venice
    sunset, Lafortune, 800 x 800, 4 camera samples x 4 light samples per pixel: noise
    (relative RMSE of one image, from two seeds) 0.188 with "mis" -> 0.094; pixels above
    1.5x their converged value 1.8 % -> 0.5 % (bench/results/render_fireflies.json).
    With 2 of 4 cosine samples the noise was 0.120.
  Optionally (``lobe``, :class:`GlossyLobe`) a share of the samples is drawn about the
  glossy reflection of the view; measured on the same image it removed a third of the
  specular lobes' own outliers but, taking samples from the diffuse strategies, made the
  whole Lafortune image noisier (off by default).
  A backward-scattering layer (HK93 with g < RETRO_G_MAX, :class:`RetroLobe`) instead draws
  a share about the view direction itself, where its Henyey-Greenstein backscatter peak
  lies (wi = wo): at g = -0.99 that peak is ~1e3 times its mean and the other strategies
  land in it too rarely (fireflies, issue 16 item 10).

Lat-long convention: y is up; image row 0 is the zenith; the image centre (u = 0.5) looks
along +z, in front of the face and behind the default camera, and the panorama is seen
unmirrored from inside (u grows towards -x).  With it, the Venice sunset map's sun
(column 614/1024) lands in front of the face, on the screen's left.

Renderers spread a pixel's S samples over its camera samples (``share``) and stratify them
over the whole pixel (:class:`PixelStrata`).

Guarded by tests/test_lights.py (inverse square, disc -> point limit and closed form,
constant environment gives pi L, importance-sampling consistency, MIS and product
unbiasedness and their variance reduction) and tests/test_render.py.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from dermis.pipeline.errors import ConfigError, DermisError
from dermis.rendering.color import LUMINANCE

__all__ = [
    "LightSamples", "EnvironmentMap", "sample_lights", "irradiance", "environment_map",
    "procedural_sunset", "light_params", "concentric_disc", "cosine_hemisphere", "LUMINANCE",
    "SUNSET_SUN_ELEVATION_DEG", "ENV_STRATEGIES", "stratified_2d", "PixelStrata", "GlossyLobe",
    "RetroLobe", "RETRO_G_MAX",
]

# Environment-light sampling strategies (module docstring); the first is the default.
ENV_STRATEGIES = ("product", "mis", "luminance")
# The "product" strategy's tables: the map in about 64 x 128 blocks of pixels, normals in
# 16 x 32 lat-long bins (512 tables of 8192 blocks: 32 MB, built once per map).
PRODUCT_BLOCKS = (64, 128)
# Share of the "product" strategy's samples drawn from the cosine hemisphere (rounded down,
# at least 1: one of the 4 samples of an anti-aliased pixel's camera sample).
PRODUCT_COSINE_FRACTION = 0.25
PRODUCT_NORMAL_BINS = (16, 32)
# Share of an environment light's samples drawn from the cosine hemisphere under "mis":
# measured on the procedural sunset at S = 16 over 6 normals (module docstring), shares
# 1/8, 1/4, 3/8, 1/2 tried: 3/8 is the largest that is nowhere noisier than pure luminance
# sampling (1/2: 9.2 % vs 7.2 % on the sun-facing normal), and beats 1/8 and 1/4 on every
# normal facing away from the sun (anti-sun: 18 % vs 34 % and 24 %).
MIS_COSINE_FRACTION = 0.375

# Procedural sunset (our embedded default map).  Sun elevation: thesis, docs/science.md §6
# ("sun ~3 deg above the horizon"); the Venice map's sun is at 3.3 deg (its README).
SUNSET_SUN_ELEVATION_DEG = 3.0
# Sun azimuth: where the Venice sunset map puts it under our lat-long convention (u = 0.6,
# i.e. 36 deg from +z towards -x), so both sunset maps light the face the same way.
SUNSET_SUN_AZIMUTH_DEG = 36.0
# The sun's angular radius, 0.267 deg (solar diameter 0.533 deg as seen from Earth).
SUNSET_SUN_RADIUS_DEG = 0.267
# Irradiance of the sun on a surface facing it, and colour (linear RGB, normalised to unit
# luminance): our choice.  A sun at 3 deg crosses ~15 air masses, so it is reddened and
# weak; E_sun = 1.0 puts a sun-facing cheek near the thesis preset's two 0.6 directional
# lights, and the sky adds ~0.3 on an upward surface.
SUNSET_SUN_IRRADIANCE = 1.0
SUNSET_SUN_COLOUR = (1.0, 0.55, 0.25)
SUNSET_ZENITH_RADIANCE = (0.02, 0.035, 0.08)    # deep blue (our choice)
SUNSET_HORIZON_RADIANCE = (0.14, 0.08, 0.04)    # orange horizon band (our choice)
SUNSET_GROUND_RADIANCE = (0.02, 0.017, 0.015)   # dark ground below the horizon (our choice)
SUNSET_WIDTH = 2048     # 0.18 deg per pixel: the sun spans ~3 pixels

_TWO_PI = 2.0 * math.pi


@dataclass
class LightSamples:
    """Light samples for N points, S per point (see the module docstring).

    directions : (N, S, 3) float32 unit vectors towards the light
    weights : (N, S, 3) float32 contribution weights (0 below the normal's horizon)
    distance : (N, S) float32 distance to the light sample, mm (inf at infinity)
    """

    directions: np.ndarray
    weights: np.ndarray
    distance: np.ndarray

    @property
    def count(self) -> int:
        return int(self.directions.shape[1])

    def live(self) -> np.ndarray:
        """(N, S) bool: samples with some weight (any channel > 0), one comparison per channel
        (a reduction over the length-3 axis, ``weights.max(axis=2)``, was ~10x slower: 3.8 of
        46 s of a sunset + area irradiance pass, py-spy)."""
        w = self.weights
        live = (w[..., 0] > 0) | (w[..., 1] > 0)
        live |= w[..., 2] > 0
        return live


# --------------------------------------------------------------------------- helpers
def _length(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=-1)`` of (..., 3) vectors, the same sum ((x^2 + y^2) + z^2)
    taken component by component (numpy reduces and broadcasts along a trailing axis of 3
    several times slower)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    s = x * x
    s += y * y
    s += z * z
    return np.sqrt(s, out=s)


def _normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis (zero vectors stay zero)."""
    if v.ndim < 2 or v.shape[-1] != 3:
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-30)
    n = _length(v)
    n = np.maximum(n, 1e-30, out=n)
    out = np.empty(v.shape, np.result_type(v, n))
    for k in range(3):
        np.divide(v[..., k], n, out=out[..., k])
    return out


def _frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to unit ``axis`` (Duff et al. 2017, as cl/common.h)."""
    x, y, z = (float(c) for c in axis)
    s = 1.0 if z >= 0 else -1.0
    a = -1.0 / (s + z)
    b = x * y * a
    t = np.array([1.0 + s * x * x * a, s * b, -s * x])
    bt = np.array([b, s + y * y * a, -y])
    return t, bt


def _frames(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised :func:`_frame`: (N, 3) unit axes -> two (N, 3) orthonormal tangents."""
    x, y, z = axes[:, 0], axes[:, 1], axes[:, 2]
    s = np.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (s + z)
    b = x * y * a
    t = np.stack([1.0 + s * x * x * a, s * b, -s * x], axis=1)
    bt = np.stack([b, s + y * y * a, -y], axis=1)
    return t, bt



def _about_axis(axis: np.ndarray, cos_a: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(N, S, 3) unit directions at polar cosine ``cos_a`` and azimuth ``phi`` (N, S) about
    the (N, 3) unit ``axis``."""
    sin_a = np.sqrt(np.maximum(1.0 - cos_a * cos_a, 0.0))
    t, b = _frames(axis)
    d = ((sin_a * np.cos(phi))[..., None] * t[:, None] + (sin_a * np.sin(phi))[..., None]
         * b[:, None] + cos_a[..., None] * axis[:, None])
    return _normalize(d)

def cosine_hemisphere(u: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-weighted directions about each normal (Malley's method, concentric disc).

    u : (N, S, 2) uniform numbers in [0, 1); normals : (N, 3) unit.
    Returns (N, S, 3) float64 unit directions and their cosine with the normal (N, S);
    the solid-angle pdf is cos / pi.
    """
    n = _normalize(np.asarray(normals, dtype=np.float64))
    xy = concentric_disc(u)
    x, y = xy[..., 0], xy[..., 1]
    cos = x * x
    cos += y * y
    np.subtract(1.0, cos, out=cos)
    np.sqrt(np.maximum(cos, 0.0, out=cos), out=cos)
    t, b = _frames(n)
    # x t + y b + cos n, normalised: one component at a time (numpy broadcasts along a
    # trailing axis of 3 several times slower)
    dk = [x * t[:, k, None] for k in range(3)]
    for k in range(3):
        dk[k] += y * b[:, k, None]
        dk[k] += cos * n[:, k, None]
    length = dk[0] * dk[0]      # as _normalize
    length += dk[1] * dk[1]
    length += dk[2] * dk[2]
    length = np.maximum(np.sqrt(length, out=length), 1e-30, out=length)
    d = np.empty(cos.shape + (3,))
    for k in range(3):
        np.divide(dk[k], length, out=d[..., k])
    return d, cos


def concentric_disc(u: np.ndarray) -> np.ndarray:
    """Shirley & Chiu 1997 concentric map of [0, 1)^2 onto the unit disc (area preserving).

    u : (..., 2) float in [0, 1); returns (..., 2) points in the unit disc, in u's float
    type (float32 in, float32 math: the disc light's 15M samples of an irradiance pass).
    """
    a = 2 * u[..., 0] - 1
    b = 2 * u[..., 1] - 1
    first = np.abs(a) > np.abs(b)
    r = np.where(first, a, b)
    # phi = pi/4 (b / a) or pi/2 - pi/4 (a / b): one division of the smaller by the larger
    ratio = np.where(first, b, a) / np.where(r == 0, 1, r)
    phi = np.where(first, ratio, 2 - ratio) * (math.pi / 4)
    return np.stack([r * np.cos(phi), r * np.sin(phi)], axis=-1)


def stratified_2d(rng: np.random.Generator, n: int, s: int) -> np.ndarray:
    """(n, s, 2) points in [0, 1)^2: a jittered grid if s is a square, else Latin hypercube."""
    m = int(round(math.sqrt(s)))
    jitter = rng.random((n, s, 2))
    if m * m == s:
        k = np.arange(s)
        jitter += np.stack([k % m, k // m], axis=-1).astype(np.float64)   # the cell
        jitter /= m
        return jitter
    # Latin hypercube: each axis stratified, strata paired by an independent permutation
    perm = np.argsort(rng.random((n, s)), axis=1)
    ax0 = (np.arange(s)[None, :] + jitter[..., 0]) / s
    ax1 = (perm + jitter[..., 1]) / s
    return np.stack([ax0, ax1], axis=-1)


def _search(table: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """``np.searchsorted(table, keys, side="right")`` through the sorted keys: a large table
    is then walked in order instead of at random (3-4x faster for millions of keys into a
    table of millions of entries, cache misses being the cost); the same result."""
    order = np.argsort(keys)
    out = np.empty(len(keys), dtype=np.int64)
    out[order] = np.searchsorted(table, keys[order], side="right")
    return out


def _tree(rows: np.ndarray) -> list[np.ndarray]:
    """Sorted rows (R, n) as implicit binary search trees, stored level by level (level l:
    the 2^l nodes of each row in turn; node i has children 2i and 2i + 1), each row padded
    with +inf to a width w = 2^L >= max(n, 2) and its tree made of the first w - 1."""
    r, n = rows.shape
    width = 1 << max(n - 1, 1).bit_length()
    if width > n:
        pad = np.full((r, width), np.inf)
        pad[:, :n] = rows
        rows = pad
    # level l: the entries (2i + 1) s - 1 of a row, s = w / 2^(l + 1)
    return [np.ascontiguousarray(rows[:, (width >> (lv + 1)) - 1::width >> lv]).ravel()
            for lv in range(width.bit_length() - 1)]


def _tree_search(tree: list[np.ndarray], row: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """For each key, min(w - 1, the number of entries <= the key in its ``row`` of
    :func:`_tree`) (``np.searchsorted(.., side="right")`` of the row): branchless, one
    gather per level, the first levels small enough to stay in cache (for 0.4M keys, 14 ms
    in 512 rows of 8192 where a search of the sorted keys in the flat table took 24 ms, and
    8 ms in 8192 rows of 64 where a binary search of each padded row took 17 ms)."""
    q = np.asarray(row, np.int64)
    for i, level in enumerate(tree):
        hit = level.take(q) <= keys
        q = np.add(q, q, out=q if i else None)     # the child 2 q + hit
        q += hit
    q -= np.left_shift(row, len(tree), dtype=np.int64)
    return q


def _hash_u64(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser (Steele, Lea & Flood 2014) of uint64 values: a fixed, seedable
    integer hash, the same for a pixel wherever its samples fall in a batch."""
    z = x.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z ^= z >> np.uint64(30)
    z *= np.uint64(0xBF58476D1CE4E5B9)
    z ^= z >> np.uint64(27)
    z *= np.uint64(0x94D049BB133111EB)
    z ^= z >> np.uint64(31)
    return z


@dataclass(frozen=True)
class PixelStrata:
    """The sub-pixel samples of pixels that share the pixels' light samples.

    A disc or environment light's T = s x share strata per pixel (s per sub-pixel sample) are
    dealt to the pixel's ``share`` sub-samples like a comb: sub-sample j takes stratum
    share k + (j + r) mod share of each group k, with r a per-pixel random rotation (hashed
    from ``seed`` and the pixel).  Every sub-sample then draws a uniformly random one of
    ``share`` stratum sets, so each sub-sample's estimate stays unbiased (its integrand
    differs from its neighbours'), while the pixel's samples fill all T strata: the pixel is
    stratified as if one point drew all T (padding with decorrelating rotations, as in Kollig
    & Keller 2002, "Efficient multidimensional sampling").

    pixel : (N,) int pixel index of each point; sub : (N,) int in [0, share); share : int
    """

    pixel: np.ndarray
    sub: np.ndarray
    share: int
    seed: int = 0

    def __getitem__(self, sl) -> "PixelStrata":
        return PixelStrata(self.pixel[sl], self.sub[sl], self.share, self.seed)

    def strata(self, s: int, salt: int) -> np.ndarray:
        """(N, s) int64 stratum indices in [0, s x share) (class docstring)."""
        key = (np.asarray(self.pixel, np.uint64) * np.uint64(0x100000001B3)
               + np.uint64(int(self.seed) * 1000003 + int(salt)))
        r = (_hash_u64(key) % np.uint64(self.share)).astype(np.int64)
        j = (np.asarray(self.sub, np.int64) + r) % self.share
        return j[:, None] + self.share * np.arange(s, dtype=np.int64)[None, :]

    def uniform_1d(self, rng, s: int, salt: int) -> np.ndarray:
        """(N, s) numbers in [0, 1), one per stratum of :meth:`strata`."""
        c = self.strata(s, salt)
        u = rng.random((len(self.pixel), s))
        u += c
        u /= s * self.share
        return u

    def uniform_2d(self, rng, s: int, salt: int) -> np.ndarray:
        """(N, s, 2) points in [0, 1)^2: the strata are the cells of an m x m jittered grid
        when T = m^2 (cell c: row c // m, column (c + row) mod m, so a sub-sample's cells
        spread over rows and columns), else the first coordinate is stratified only."""
        total = s * self.share
        c = self.strata(s, salt)
        m = int(round(math.sqrt(total)))
        u = rng.random((len(self.pixel), s, 2))   # the jitter, then the point
        if m * m == total:
            k = np.arange(total)    # each cell's column and row, looked up
            u[..., 0] += ((k % m + k // m) % m).astype(np.float64).take(c)
            u[..., 1] += (k // m).astype(np.float64).take(c)
            u /= m
            return u
        u[..., 0] += c
        u[..., 0] /= total
        return u


def _check_points(points, normals) -> tuple[np.ndarray, np.ndarray | None]:
    p = np.asarray(points, dtype=np.float32)
    if p.ndim != 2 or p.shape[1] != 3:
        raise DermisError(f"lights: points have shape {p.shape}; need (N, 3)")
    n = None
    if normals is not None:
        n = np.asarray(normals, dtype=np.float32)
        if n.shape != p.shape:
            raise DermisError(f"lights: normals have shape {n.shape}; need {p.shape}")
    return p, n


def _vec(value, name: str, light) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ConfigError(f"lights.{light.name}.{name} = {value!r}: must be 3 finite numbers")
    return v


# --------------------------------------------------------------------------- light types
def _point(light, p: np.ndarray, rng) -> tuple:
    pos = _vec(light.position, "position", light).astype(np.float32)
    d = pos[None, :] - p
    dist = np.linalg.norm(d, axis=1)
    safe = np.maximum(dist, np.float32(1e-6))
    wi = d / safe[:, None]
    # inverse square (docs/science.md §6); a point exactly at the light gets weight 0, not inf
    w = _vec(light.intensity, "intensity", light).astype(np.float32)[None, :] \
        / np.where(dist > 1e-6, safe * safe, np.inf)[:, None]
    return wi[:, None], w[:, None], dist[:, None]


def _directional(light, p: np.ndarray, rng) -> tuple:
    d = _vec(light.direction, "direction", light)
    if np.linalg.norm(d) == 0:
        raise ConfigError(f"lights.{light.name}.direction = {light.direction!r}: must be non-zero")
    wi = np.broadcast_to((d / np.linalg.norm(d)).astype(np.float32), (len(p), 1, 3))
    w = np.broadcast_to(_vec(light.intensity, "intensity", light).astype(np.float32),
                        (len(p), 1, 3))
    dist = np.full((len(p), 1), np.inf, dtype=np.float32)
    return wi, w, dist


def _disc(light, p: np.ndarray, rng, samples: int, strata=None, salt: int = 0) -> tuple:
    centre = _vec(light.position, "position", light)
    axis = _vec(light.direction, "direction", light)
    if np.linalg.norm(axis) == 0:
        raise ConfigError(f"lights.{light.name}.direction = {light.direction!r}: the disc's "
                          "axis must be non-zero")
    axis = axis / np.linalg.norm(axis)
    radius = float(light.radius)
    if not radius > 0:
        raise ConfigError(f"lights.{light.name}.radius = {radius} (mm): must be > 0")
    t, b = _frame(axis)
    u = (strata.uniform_2d(rng, samples, salt) if strata is not None
         else stratified_2d(rng, len(p), samples))
    # float32 throughout (the outputs are float32): the map, the sample point q on the disc
    # as centre + x t + y b, and d = q - p (the irradiance pass's 15M samples; measured in
    # bench/results/irradiance.json); (N, S, 3) arrays one component at a time (numpy
    # broadcasts along a trailing axis of 3 several times slower)
    xy = concentric_disc(u.astype(np.float32))
    xy *= np.float32(radius)
    frame = np.stack([t, b]).astype(np.float32)                       # (2, 3)
    d = xy @ frame
    to_centre = centre.astype(np.float32)[None, :] - p
    for k in range(3):
        d[..., k] += to_centre[:, k, None]
    dist2 = np.einsum("nsk,nsk->ns", d, d)
    dist = np.sqrt(dist2)
    far = dist > 1e-6
    inv = np.float32(1.0) / np.where(far, dist, np.float32(1.0))
    wi = d
    for k in range(3):
        wi[..., k] *= inv
    # two-sided emitter (module docstring): |cos theta_l|; L (pi r^2) = I; a point exactly
    # on the disc gets weight 0, not inf
    cos_l = wi @ axis.astype(np.float32)
    cos_l = np.abs(cos_l, out=cos_l)
    inv *= inv
    cos_l *= inv
    cos_l *= np.float32(1.0 / samples)
    scale = np.where(far, cos_l, np.float32(0.0))
    intensity = _vec(light.intensity, "intensity", light).astype(np.float32)
    w = np.empty(scale.shape + (3,), dtype=np.float32)
    for k in range(3):
        np.multiply(scale, intensity[k], out=w[..., k])
    return wi, w, dist


@dataclass(frozen=True)
class GlossyLobe:
    """A third environment-sampling strategy for glossy reflection seen at ``view``: the
    cosine-power lobe p(wi) = (e + 1) / (2 pi) max(0, a . wi)^e about the axis
    a = normalize(-wo_t, tilt x wo_n) (wo_t, wo_n: the view's parts along and across the
    surface of ``normals``): tilt 1 is the mirror direction; the Lafortune skin fit's sharp
    lobe has Cz / |Cxy| ~ 0.75 and exponent ~60 (docs/science.md §1).  Any model may shade
    these samples: the MIS weights count the lobe's density whatever the BRDF is.

    view : (N, 3) unit directions to the eye; normals : (N, 3) unit (interpolated) normals
    fraction : share of the samples drawn from the lobe; exponent, tilt : the lobe's shape
    """

    view: np.ndarray
    normals: np.ndarray
    fraction: float = 0.25
    exponent: float = 32.0
    tilt: float = 0.75

    def __getitem__(self, sl) -> "GlossyLobe":
        return GlossyLobe(self.view[sl], self.normals[sl], self.fraction, self.exponent,
                          self.tilt)

    def axis(self) -> np.ndarray:
        v = np.asarray(self.view, np.float64)
        nrm = _normalize(np.asarray(self.normals, np.float64))
        vn = np.einsum("ij,ij->i", v, nrm)[:, None]
        return _normalize(-(v - vn * nrm) + self.tilt * vn * nrm)

    def sample(self, u: np.ndarray) -> np.ndarray:
        """(N, S, 3) directions for uniform (N, S, 2) numbers."""
        a = self.axis()
        cos_a = u[..., 0] ** (1.0 / (self.exponent + 1.0))
        return _about_axis(a, cos_a, _TWO_PI * u[..., 1])

    def pdf(self, directions: np.ndarray) -> np.ndarray:
        """(N, S) solid-angle density of (N, S, 3) directions."""
        c = np.maximum(np.einsum("nsk,nk->ns", directions, self.axis()), 0.0)
        return (self.exponent + 1.0) / _TWO_PI * c ** self.exponent


# A layer scattering more backwards than this gets the retro lobe (RetroLobe).  Its HG peak
# at g is (1 - g^2) / (4 pi (1 - |g|)^3) / (1 / 4 pi) times the isotropic value: 20 at
# g = -0.5, 1e4 at -0.99 (against 4 samples per hit).
RETRO_G_MAX = -0.5
# Share of the environment samples drawn from the retro lobe (one of 4 per hit at the
# default 16 per pixel / 4 camera samples): measured in bench/results/hk93_retro.json.
RETRO_FRACTION = 0.25


@dataclass(frozen=True)
class RetroLobe:
    """An environment-sampling strategy for a backward-scattering layer seen at ``view``:
    the Henyey-Greenstein distribution p(wi) = (1 - k^2) / (4 pi (1 + k^2 - 2 k wi.wo)^1.5)
    about the view direction wo (Henyey & Greenstein 1941; inverted as in pbrt-v3
    ``HenyeyGreenstein::Sample_p``).  A layer of mean cosine g < 0 and index eta backscatters
    about wi = wo with an angular width ~(1 - |g|) inside, ~eta (1 - |g|) outside (Snell near
    normal incidence), so k = 1 - eta (1 - |g|) (:meth:`for_layer`); the MIS weights count
    this density whatever the BRDF is, so the estimate stays unbiased for every model.

    view : (N, 3) unit directions to the eye; fraction : share of the samples; k : in [0, 1)
    """

    view: np.ndarray
    fraction: float = RETRO_FRACTION
    k: float = 0.9

    @staticmethod
    def k_for_layer(g: float, eta: float) -> float:
        return float(min(max(1.0 - eta * (1.0 - abs(g)), 0.0), 0.999))

    def __getitem__(self, sl) -> "RetroLobe":
        return RetroLobe(self.view[sl], self.fraction, self.k)

    def sample(self, u: np.ndarray) -> np.ndarray:
        """(N, S, 3) directions for uniform (N, S, 2) numbers."""
        a = _normalize(np.asarray(self.view, np.float64))
        k = self.k
        if k < 1e-3:
            cos_a = 1.0 - 2.0 * u[..., 0]
        else:
            sq = (1.0 - k * k) / (1.0 - k + 2.0 * k * u[..., 0])
            cos_a = np.clip((1.0 + k * k - sq * sq) / (2.0 * k), -1.0, 1.0)
        return _about_axis(a, cos_a, _TWO_PI * u[..., 1])

    def pdf(self, directions: np.ndarray) -> np.ndarray:
        """(N, S) solid-angle density of (N, S, 3) directions."""
        a = _normalize(np.asarray(self.view, np.float64))
        c = np.einsum("nsk,nk->ns", directions, a)
        k = self.k
        return (1.0 - k * k) / (4.0 * math.pi * np.maximum(1.0 + k * k - 2.0 * k * c, 1e-30)
                                ** 1.5)


def _environment(light, p: np.ndarray, rng, samples: int, env, normals, strategy: str,
                 strata=None, salt: int = 0,
                 lobe: "GlossyLobe | RetroLobe | None" = None) -> tuple:
    if env is None:
        env = environment_map(light)
    n = len(p)
    mis = strategy in ("mis", "product") and normals is not None and samples >= 2 \
        and not env.black
    product = mis and strategy == "product"
    if product:   # floor: the product samples carry the sun and the cosine already
        n_cos = min(max(int(samples * PRODUCT_COSINE_FRACTION + 1e-9), 1), samples - 1)
    else:
        n_cos = min(max(int(round(samples * MIS_COSINE_FRACTION)), 1), samples - 1) if mis else 0
    n_lobe = 0
    if mis and lobe is not None and samples >= 3:
        # the lobe's samples come out of the cosine ones (the luminance samples carry the sun)
        n_lobe = min(max(int(round(samples * lobe.fraction)), 1), samples - 2)
        n_cos = max(1, n_cos - n_lobe)
    n_env = samples - n_cos - n_lobe
    # stratify the flattened-CDF coordinate per point; jitter inside the pixel at random
    u0 = ((np.arange(n_env)[None, :] + rng.random((n, n_env))) / n_env
          if strata is None else strata.uniform_1d(rng, n_env, 2 * salt))
    jitter = rng.random((n, n_env, 3 if product else 2))
    if not product:
        u = np.empty((n, n_env, 3))
        u[..., 0] = u0
        u[..., 1:] = jitter
    if not mis:
        wi, w = env.sample(u.reshape(-1, 3))
        wi = wi.reshape(n, samples, 3)
        w = (w / np.float32(samples)).reshape(n, samples, 3)
        dist = np.full((n, samples), np.inf, dtype=np.float32)
        return wi, w, dist
    # multiple importance sampling, balance heuristic (module docstring): for a sample x of
    # any strategy i, w_i(x) L / (n_i p_i(x)) with w_i = n_i p_i / sum_j n_j p_j reduces to
    # L(x) / sum_j n_j p_j(x) (Veach 1997, eq. 9.13), every pdf evaluated at x
    nrm = _normalize(np.asarray(normals, dtype=np.float64))
    if product:   # luminance x cosine of the point's normal bin (EnvironmentMap._product)
        bins = env.normal_bin(nrm)
        d_env, rad_env, pdf_env = env.product_sample(u0.ravel(), jitter.reshape(-1, 3),
                                                     np.repeat(bins, n_env))
    else:
        d_env, rad_env, pdf_env = env.sample_pdf(u.reshape(-1, 3))   # pdf known from the pick
    dirs = [cosine_hemisphere(stratified_2d(rng, n, n_cos) if strata is None
                              else strata.uniform_2d(rng, n_cos, 2 * salt + 1), nrm)[0]]
    if n_lobe:
        dirs.append(lobe.sample(stratified_2d(rng, n, n_lobe) if strata is None
                                else strata.uniform_2d(rng, n_lobe, 2 * salt + 7)))
    other = np.concatenate(dirs, axis=1) if len(dirs) > 1 else dirs[0]
    if product:   # one pixel lookup for the radiance and the product pdf
        row, col = env.pixel_of(other)
        rad_other = env._radiance_at(row, col)
        pdf_other = env.product_pdf(other, np.broadcast_to(bins[:, None], other.shape[:2]),
                                    row, col)
    else:
        pdf_other, rad_other = env.pdf_radiance(other)
    # the S samples side by side: directions float32 (as returned), the pdfs float64
    wi = np.empty((n, samples, 3), dtype=np.float32)
    wi[:, :n_env] = d_env.reshape(n, n_env, 3)
    wi[:, n_env:] = other
    den = np.concatenate([pdf_env.reshape(n, n_env), pdf_other], axis=1)
    w = np.concatenate([rad_env.reshape(n, n_env, 3), rad_other], axis=1)   # float32
    den *= n_env
    cos = np.einsum("nsk,nk->ns", wi, nrm.astype(np.float32))
    cos = np.maximum(cos, 0.0, out=cos)
    cos *= n_cos / math.pi          # float32, as (n_cos / pi) * cos
    den += cos
    if n_lobe:
        den += n_lobe * lobe.pdf(np.concatenate([d_env.reshape(n, n_env, 3), other], axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.divide(1.0, den).astype(np.float32)
    inv[~(den > 0)] = 0.0
    for k in range(3):   # w *= inv[..., None], one channel at a time (cosine_hemisphere)
        w[..., k] *= inv
    dist = np.full((n, samples), np.inf, dtype=np.float32)
    return wi, w, dist


# --------------------------------------------------------------------------- public API
def sample_lights(lights, points: np.ndarray, normals: np.ndarray | None = None, *,
                  samples: int | None = None, seed: int | Sequence[int] = 0,
                  env: "EnvironmentMap | None" = None,
                  env_strategy: str = ENV_STRATEGIES[0], share: int = 1,
                  strata: "PixelStrata | None" = None,
                  lobe: "GlossyLobe | RetroLobe | None" = None,
                  horizon: bool = True) -> LightSamples:
    """Sample one light or several (summed) for N surface points.

    Parameters
    ----------
    lights : LightConfig or sequence of LightConfig
        Several lights (e.g. the two directional lights of the thesis preset) concatenate
        their samples along the S axis, so the estimate sums them.
    points : (N, 3) float, mm
    normals : (N, 3) float, optional
        Unit surface normals; samples with cos <= 0 get weight 0.  None keeps every sample.
    samples : int, optional
        Samples per point for disc and environment lights (default: each light's
        ``samples``, 16 in the thesis).  Point and directional lights take one.
    seed : int or sequence of int
        Seeds ``numpy.random.default_rng`` (pass ``(seed, chunk)`` for chunked calls).
    env : EnvironmentMap, optional
        Pre-built map for an environment light (else built from ``light.map``, cached).
    env_strategy : {"mis", "luminance"}
        How environment lights are sampled (module docstring): "mis" (default) mixes
        luminance and cosine-hemisphere samples about ``normals`` (3/8 of them) with the
        balance heuristic; "luminance" is pure luminance importance sampling.  "mis" falls back to
        "luminance" when ``normals`` is None or S = 1.
    share : int
        Points that share one pixel's samples (the renderer's sub-pixel samples): each point
        draws ceil(S / share) samples of a disc or environment light, so a pixel of ``share``
        sub-pixel samples still averages about S light samples (point and directional
        lights: one each).
    strata : PixelStrata, optional
        Which pixel and sub-sample each point is (``share`` = its share): the pixel's light
        samples are then stratified over all its sub-samples (:class:`PixelStrata`).
    lobe : GlossyLobe, optional
        Environment lights under "mis" also draw ``lobe.fraction`` of their samples about
        the glossy reflection of the view (:class:`GlossyLobe`).
    horizon : bool
        Zero the weights of samples below the normals' horizon (default).  False leaves
        them for a caller that tests cos > 0 itself (:func:`irradiance`: one cosine pass).

    Returns
    -------
    LightSamples
    """
    if not isinstance(lights, (list, tuple)):
        lights = [lights]
    if not lights:
        raise DermisError("lights: no light given")
    p, n = _check_points(points, normals)
    if env_strategy not in ENV_STRATEGIES:
        raise ConfigError(f"env_strategy = {env_strategy!r}: must be one of "
                          f"{', '.join(ENV_STRATEGIES)}")
    rng = np.random.default_rng(seed)
    if strata is not None and (strata.share != share or len(strata.pixel) != len(p)):
        raise DermisError(f"lights: strata for {len(strata.pixel)} points sharing "
                          f"{strata.share}; need {len(p)} and share = {share}")
    parts = []
    for index, light in enumerate(lights):
        s = int(samples if samples is not None else getattr(light, "samples", 16))
        if s < 1:
            raise ConfigError(f"lights.{light.name}.samples = {s}: must be >= 1")
        s = -(-s // max(int(share), 1))
        kind = light.type
        if kind == "point":
            parts.append(_point(light, p, rng))
        elif kind == "directional":
            parts.append(_directional(light, p, rng))
        elif kind == "disc":
            parts.append(_disc(light, p, rng, s, strata, salt=3 * index))
        elif kind == "environment":
            parts.append(_environment(light, p, rng, s, env, n, env_strategy, strata,
                                      salt=3 * index + 1, lobe=lobe))
        else:
            raise ConfigError(f"lights.{light.name}.type = {kind!r}: must be one of point, "
                              "disc, directional, environment")
    wi, w, dist = (np.ascontiguousarray(np.concatenate(
        [np.asarray(q[k], dtype=np.float32) for q in parts], axis=1) if len(parts) > 1
        else parts[0][k], dtype=np.float32) for k in range(3))
    if n is not None and horizon:
        cos = np.einsum("nsk,nk->ns", wi, n)
        w = np.where((cos > 0)[..., None], w, np.float32(0.0))
    return LightSamples(wi, w, dist)


# Batches of the irradiance pass run on this many threads (results independent of it).
IRRADIANCE_THREADS = 2


def irradiance(points: np.ndarray, normals: np.ndarray, light,
               occlusion_fn: Callable | None, *, samples: int | None = None,
               seed: int = 0, env: "EnvironmentMap | None" = None,
               chunk: int = 8192, env_strategy: str = ENV_STRATEGIES[0],
               transmittance: Callable | None = None) -> np.ndarray:
    """Irradiance E at surface points from one light (or a list of lights), with shadows.

    Parameters
    ----------
    points : (N, 3) float, mm
    normals : (N, 3) float, unit outward normals (also the shadow-ray offset direction)
    light : LightConfig or sequence of LightConfig
    occlusion_fn : callable or None
        ``occlusion_fn(points, normals, directions, max_distance) -> (M,) bool`` (True =
        blocked), e.g. :meth:`pipeline.visibility.Visibility.occluded`; None: no shadows.
    samples : int, optional
        Samples per point for disc/environment lights (thesis: 64 for BSSRDF irradiance).
    seed : int
    env : EnvironmentMap, optional
    chunk : int
        Points per batch (bounds memory to ~chunk x samples rays).  8192: the batch's
        arrays (~0.5M samples, a few MB each) stay in cache; CPU seconds at 64 samples, chunk
        65536 / 8192 / 4096, high mesh: sunset 14.7 / 13.1 / 13.9, disc 6.6 / 5.6 / 5.6; low
        mesh: sunset 13.1 / 11.7 / 11.6, disc 6.3 / 4.7 / 4.9 (bench/results/irradiance.json,
        "after", "chunk"; load 4-6).
    env_strategy : {"mis", "luminance"}
        Environment sampling strategy (:func:`sample_lights`).
    transmittance : callable, optional
        ``transmittance(cos) -> (..., 3)``: the fraction of each light sample that enters
        the surface at its cosine (e.g. Fresnel transmittance, ``stages/brdf_models.py
        Transmittance``), applied per sample; None counts all of it (plain irradiance).

    Returns
    -------
    (N, 3) float32 irradiance E = integral of L cos(theta) over the hemisphere (units of the
    light's intensity / mm^2 for point and disc lights, of ``intensity`` for directional
    lights, of radiance x sr for environment maps); with ``transmittance``, the entering
    part integral of T L cos(theta).
    """
    p, n = _check_points(points, normals)
    if n is None:
        raise DermisError("irradiance: normals are required")
    out = np.zeros((len(p), 3), dtype=np.float32)

    def batch(c: int) -> None:
        start = c * chunk
        ps, ns = p[start:start + chunk], n[start:start + chunk]
        ls = sample_lights(light, ps, ns, samples=samples, seed=(seed, c), env=env,
                           env_strategy=env_strategy, horizon=False)
        # one cosine pass: samples below the horizon (or of zero weight) are not live, get
        # no shadow ray and add nothing; the sum is E = sum_s V_s cos_s (T_s) weights_s
        cos = np.einsum("nsk,nk->ns", ls.directions, ns)
        live = ls.live()
        live &= cos > 0
        factor = np.where(live, cos, np.float32(0.0))
        if occlusion_fn is not None and live.any():
            # shadow rays of the live samples only (flat indices: one ``take`` per array)
            idx = np.flatnonzero(live)
            rep = idx // live.shape[1]
            blocked = occlusion_fn(ps.take(rep, axis=0), ns.take(rep, axis=0),
                                   ls.directions.reshape(-1, 3).take(idx, axis=0),
                                   ls.distance.ravel().take(idx))
            factor.ravel()[idx[blocked]] = 0.0
        w = ls.weights
        if transmittance is not None:
            t = np.asarray(transmittance(np.maximum(cos, 0.0)), dtype=np.float32)
            w = np.multiply(w, t, out=w if w.flags.writeable else None)   # a fresh array
        out[start:start + chunk] = np.einsum("ns,nsk->nk", factor, w)

    batches = range(-(-len(p) // chunk))
    if IRRADIANCE_THREADS > 1 and len(batches) > 1:
        # batches are independent (own seed, own rows of ``out``): the result does not depend
        # on the thread count; numpy and the ray caster release the GIL for their bulk work
        from concurrent.futures import ThreadPoolExecutor
        with ThreadPoolExecutor(IRRADIANCE_THREADS) as pool:
            list(pool.map(batch, batches))
    else:
        for c in batches:
            batch(c)
    return out


# --------------------------------------------------------------------------- environment
class EnvironmentMap:
    """A lat-long radiance map with a luminance x sin(theta) sampling distribution.

    Parameters
    ----------
    radiance : (H, W, 3) float, linear RGB radiance (row 0 = zenith; module docstring)
    rotation_deg : float, optional
        Rotation of the map about +y (the up axis), degrees, counter-clockwise seen from
        above; 0 = the convention of the module docstring.
    name : str, optional
    """

    def __init__(self, radiance: np.ndarray, *, rotation_deg: float = 0.0, name: str = ""):
        rad = np.asarray(radiance, dtype=np.float32)
        if rad.ndim != 3 or rad.shape[2] != 3 or rad.shape[0] < 1 or rad.shape[1] < 1:
            raise DermisError(f"environment map {name!r}: shape {rad.shape}; need (H, W, 3)")
        if not np.all(np.isfinite(rad)) or np.any(rad < 0):
            raise DermisError(f"environment map {name!r}: radiance must be finite and >= 0")
        self.radiance = np.ascontiguousarray(rad)
        self.name = name
        self.rotation = math.radians(rotation_deg)
        h, w = rad.shape[:2]
        self.height, self.width = h, w
        sin_t = np.sin((np.arange(h) + 0.5) / h * math.pi)
        weight = (rad.astype(np.float64) @ LUMINANCE) * sin_t[:, None]
        total = weight.sum()
        self.pmf = (weight / total).ravel() if total > 0 else np.zeros(h * w)
        self.cdf = np.cumsum(self.pmf)
        self.black = not total > 0

    # direction <-> lat-long coordinates (module docstring)
    def _dirs(self, u: np.ndarray, s: np.ndarray, dtype=np.float64
              ) -> tuple[np.ndarray, np.ndarray]:
        """Unit directions and sin(theta) at lat-long coordinates (u, s) in [0, 1], computed
        in ``dtype`` (float32 for the product strategy's samples: 2-3x faster trigonometry,
        directions within 1e-7 of float64; their pixel and pdf come from the picked pixel,
        not from the direction)."""
        theta = (s * math.pi).astype(dtype, copy=False)
        phi = (_TWO_PI * (u - 0.5) + self.rotation).astype(dtype, copy=False)
        st = np.sin(theta)
        d = np.stack([-st * np.sin(phi), np.cos(theta), st * np.cos(phi)], axis=-1)
        return d, st

    def pixel_of(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of the pixel seen along each unit direction (..., 3)."""
        d = np.asarray(directions, dtype=np.float64)
        theta = np.arccos(np.clip(d[..., 1], -1.0, 1.0))
        phi = np.arctan2(-d[..., 0], d[..., 2]) - self.rotation
        u = np.mod(phi / _TWO_PI + 0.5, 1.0)
        row = np.minimum((theta / math.pi * self.height).astype(np.int64), self.height - 1)
        col = np.minimum((u * self.width).astype(np.int64), self.width - 1)
        return row, col

    def lookup(self, directions: np.ndarray) -> np.ndarray:
        """Radiance (..., 3) along unit directions (piecewise constant, as sampled)."""
        row, col = self.pixel_of(directions)
        return self.radiance[row, col]

    def pdf(self, directions: np.ndarray) -> np.ndarray:
        """Solid-angle density (1/sr) with which :meth:`sample` draws each direction."""
        d = np.asarray(directions, dtype=np.float64)
        row, col = self.pixel_of(d)
        sin_t = np.sqrt(np.maximum(1.0 - d[..., 1] ** 2, 0.0))
        p = self.pmf[row * self.width + col] * (self.height * self.width)
        return np.where(sin_t > 0, p / (2.0 * math.pi * math.pi * np.maximum(sin_t, 1e-30)), 0.0)

    def pdf_radiance(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`pdf` and :meth:`lookup` of the same directions, sharing one pixel lookup."""
        d = np.asarray(directions)
        row, col = self.pixel_of(d)
        sin_t = np.sqrt(np.maximum(1.0 - d[..., 1].astype(np.float64) ** 2, 0.0))
        p = self.pmf[row * self.width + col] * (self.height * self.width)
        pdf = np.where(sin_t > 0, p / (2.0 * math.pi * math.pi * np.maximum(sin_t, 1e-30)), 0.0)
        return pdf, self.radiance[row, col]

    def sample_pdf(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Directions, radiance and solid-angle pdf for uniform numbers ``u`` (M, 3) in [0, 1).

        u[:, 0] picks the pixel through the flattened CDF, u[:, 1:] places the direction
        uniformly inside it (in (u, v)); returns (M, 3) float64 unit directions, (M, 3)
        float32 radiance of the picked pixel and (M,) float64 pdf (1/sr; 0 for a black map).
        """
        m = len(u)
        if self.black:
            d = np.zeros((m, 3))
            d[:, 1] = 1.0
            return d, np.zeros((m, 3), dtype=np.float32), np.zeros(m)
        idx = _search(self.cdf, u[:, 0] * self.cdf[-1])
        idx = np.minimum(idx, len(self.pmf) - 1)
        row, col = np.divmod(idx, self.width)
        d, sin_t = self._dirs((col + u[:, 2]) / self.width, (row + u[:, 1]) / self.height)
        # pdf over solid angle: pmf * H W / (2 pi^2 sin theta)
        pdf = self.pmf[idx] * (self.height * self.width) / (
            2.0 * math.pi * math.pi * np.maximum(sin_t, 1e-30))
        return d, self.radiance[row, col], np.where(sin_t > 0, pdf, 0.0)

    # -- luminance x cosine ("product" strategy): tables per bin of normals, lazily built
    def _product(self) -> dict:
        """Tables of the product strategy (module docstring): the map's luminance mass in
        blocks of about PRODUCT_BLOCKS pixels, weighted per normal bin by the cosine of the
        block (padded by the block's and the bin's angular radius, so a block partly above
        a normal's horizon keeps some mass), and the pixels' share inside each block."""
        if getattr(self, "_prod", None) is not None:
            return self._prod
        h, w = self.height, self.width
        bh = max(1, -(-h // PRODUCT_BLOCKS[0]))
        bw = max(1, -(-w // PRODUCT_BLOCKS[1]))
        hc, wc = -(-h // bh), -(-w // bw)
        pmf = np.zeros((hc * bh, wc * bw))
        pmf[:h, :w] = self.pmf.reshape(h, w)
        blocks = pmf.reshape(hc, bh, wc, bw).transpose(0, 2, 1, 3).reshape(hc * wc, bh * bw)
        mass = blocks.sum(axis=1)                                     # (B,)
        rows, cols = np.divmod(np.arange(hc * wc), wc)
        centre, sin_c = self._dirs((cols + 0.5) * bw / w, np.minimum((rows + 0.5) * bh / h, 1.0))
        theta_hi = np.minimum((rows + 1) * bh / h, 1.0) * math.pi
        theta_lo = rows * bh / h * math.pi
        sin_max = np.where((theta_lo < math.pi / 2) & (theta_hi > math.pi / 2), 1.0,
                           np.maximum(np.sin(theta_lo), np.sin(theta_hi)))
        rho_b = np.hypot(0.5 * math.pi * bh / h, 0.5 * _TWO_PI * bw / w * sin_max)
        kr, kc = PRODUCT_NORMAL_BINS
        nrow, ncol = np.divmod(np.arange(kr * kc), kc)
        nrm, _ = self._dirs((ncol + 0.5) / kc, (nrow + 0.5) / kr)
        rho_k = math.hypot(0.5 * math.pi / kr, 0.5 * _TWO_PI / kc)
        cos = nrm @ centre.T                                          # (K, B)
        weight = mass[None, :] * np.maximum(cos + np.sin(np.minimum(rho_b[None, :] + rho_k,
                                                                      math.pi / 2)), 0.0)
        total = weight.sum(axis=1, keepdims=True)
        table = weight / np.where(total > 0, total, 1.0)              # (K, B) block pmf per bin
        cum = np.cumsum(table, axis=1)                                # (K, B) per-bin CDF
        share = blocks / np.where(mass > 0, mass, 1.0)[:, None]       # pixel share in block
        # the block's and the pixel's CDFs as search trees (_tree): each bin's row of the
        # flat per-bin CDF (cum + bin, as the keys of product_sample), and the pixels' CDF
        # in each block.  Searching a key's own row finds the same block as a search of the
        # whole flat table (clipped to the row) when the flat table is sorted across rows as
        # well and every key (u0 <= 1) stays below the next row; else the flat table is
        # kept and searched
        cum_flat = cum + np.arange(kr * kc)[:, None]    # sorted in each row
        per = bh * bw
        k = np.arange(kr * kc)
        exact = bool(np.all(cum_flat[1:, 0] >= cum_flat[:-1, -1])
                     and np.all(k + cum[:, -1] * (1.0 - 1e-12) < k + 1))
        # a pixel's block and position in the block as the sums of lookups by its row and its
        # column, and back (integer divisions of millions of samples cost more)
        r, c, b, q = np.arange(hc * bh), np.arange(wc * bw), np.arange(hc * wc), np.arange(per)
        self._prod = {"bh": bh, "bw": bw, "hc": hc, "wc": wc, "table": table.ravel(),
                      "block_of": ((r // bh) * wc, c // bw), "pos_of": ((r % bh) * bw, c % bw),
                      "rows_of": ((b // wc) * bh, q // bw), "cols_of": ((b % wc) * bw, q % bw),
                      "nb": hc * wc, "per": per, "cum_last": cum[:, -1],
                      "block_tree": _tree(cum_flat) if exact else None,
                      "cum_flat": None if exact else cum_flat.ravel(),
                      "fine_tree": _tree(np.cumsum(share, axis=1)),
                      "share": share.ravel(), "kr": kr, "kc": kc}
        return self._prod

    def normal_bin(self, normals: np.ndarray) -> np.ndarray:
        """(N,) index of the product strategy's bin of each unit normal."""
        t = self._product()
        d = np.asarray(normals, np.float64)
        theta = np.arccos(np.clip(d[:, 1], -1.0, 1.0))
        phi = np.arctan2(-d[:, 0], d[:, 2]) - self.rotation
        u = np.mod(phi / _TWO_PI + 0.5, 1.0)
        r = np.minimum((theta / math.pi * t["kr"]).astype(np.int64), t["kr"] - 1)
        c = np.minimum((u * t["kc"]).astype(np.int64), t["kc"] - 1)
        return r * t["kc"] + c

    def product_sample(self, u0: np.ndarray, jitter: np.ndarray, bins: np.ndarray):
        """Directions, radiance and pdf of the product strategy for uniform numbers ``u0``
        (M,) (the block) and ``jitter`` (M, 3) (the pixel in the block, then the point in
        the pixel: column, row) and the normal bin of each sample (M,) (:meth:`normal_bin`)."""
        t = self._product()
        nb, per = t["nb"], t["per"]
        # the block: inversion of the bin's CDF at u0 (u0 is stratified per point; an alias
        # table would lose that), a search of the bin's row
        key = u0 * t["cum_last"].take(bins)
        key *= 1.0 - 1e-12
        key += bins
        if t["block_tree"] is not None:
            b = _tree_search(t["block_tree"], bins, key)
        else:
            b = _search(t["cum_flat"], key) - bins * nb
        b = np.clip(b, 0, nb - 1, out=b)
        # the pixel in the block: a search of its CDF row
        j = _tree_search(t["fine_tree"], b, jitter[:, 0] * (1.0 - 1e-12))
        j = np.minimum(j, per - 1, out=j)
        row = t["rows_of"][0].take(b) + t["rows_of"][1].take(j)
        col = t["cols_of"][0].take(b) + t["cols_of"][1].take(j)
        if t["hc"] * t["bh"] > self.height or t["wc"] * t["bw"] > self.width:
            row = np.minimum(row, self.height - 1)   # blocks padded beyond the map
            col = np.minimum(col, self.width - 1)
            b, j = None, None
        x = col + jitter[:, 1]
        x /= self.width
        y = row + jitter[:, 2]
        y /= self.height
        d, _ = self._dirs(x, y, np.float32)
        return d, self._radiance_at(row, col), self.product_pdf(d, bins, row, col, b, j)

    def _radiance_at(self, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """``radiance[row, col]`` through one flat index (a single ``take``: ~4x faster than
        the two-index gather for millions of samples)."""
        flat = row * self.width + col
        return self.radiance.reshape(-1, 3).take(flat.ravel(), axis=0).reshape(
            np.shape(flat) + (3,))

    def product_pdf(self, directions: np.ndarray, bins: np.ndarray, row=None, col=None,
                    block=None, pos=None):
        """Solid-angle density of the product strategy for normal bins ``bins`` (...) at
        ``directions`` (..., 3) (their pixel ``row``, ``col``, or its ``block`` and
        position ``pos`` in the block, when known)."""
        t = self._product()
        d = np.asarray(directions)
        if block is None:
            if row is None:
                row, col = self.pixel_of(d)
            block = t["block_of"][0].take(row) + t["block_of"][1].take(col)
            pos = t["pos_of"][0].take(row) + t["pos_of"][1].take(col)
        # the block's pmf in the bin x the pixel's share of the block's mass
        p = t["table"].take(bins * t["nb"] + block)
        p *= t["share"].take(block * t["per"] + pos)
        # over solid angle: p H W / (2 pi^2 sin theta), 0 at the poles
        sin_t = d[..., 1].astype(np.float64)
        sin_t *= sin_t
        np.subtract(1.0, sin_t, out=sin_t)
        np.sqrt(np.maximum(sin_t, 0.0, out=sin_t), out=sin_t)
        p *= self.height * self.width
        p /= np.maximum(sin_t, 1e-30) * (2.0 * math.pi * math.pi)
        p[~(sin_t > 0)] = 0.0
        return p

    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Directions and radiance / pdf for uniform numbers ``u`` (M, 3) in [0, 1).

        As :meth:`sample_pdf`; returns (M, 3) float32 unit directions and (M, 3) float32
        L / pdf (sr x radiance), 0 for a black map or a zero-mass pixel.
        """
        d, rad, pdf = self.sample_pdf(u)
        inv_pdf = np.where(pdf > 0, 1.0 / np.where(pdf > 0, pdf, 1.0), 0.0)
        w = rad * inv_pdf[:, None].astype(np.float32)
        return d.astype(np.float32), w.astype(np.float32)


def procedural_sunset(width: int = SUNSET_WIDTH) -> np.ndarray:
    """The embedded sunset sky: (width/2, width, 3) float32 linear radiance, lat-long.

    A warm horizon band fading to a deep-blue zenith, a glow around the sun, dark ground, and
    a sun disc of the true angular radius at 3 deg elevation whose radiance is set so that
    its irradiance on a surface facing it is exactly ``SUNSET_SUN_IRRADIANCE`` at this
    resolution (the disc is only a few pixels wide).  Colours are our choice (constants
    above); only the sun's elevation comes from the thesis.
    """
    h = max(width // 2, 2)
    env = EnvironmentMap(np.zeros((1, 1, 3), dtype=np.float32))  # for the convention only
    rows = (np.arange(h) + 0.5) / h
    cols = (np.arange(width) + 0.5) / width
    uu, ss = np.meshgrid(cols, rows)
    env.height, env.width = h, width
    d, sin_t = env._dirs(uu, ss)
    elev = np.arcsin(np.clip(d[..., 1], -1.0, 1.0))
    el_s = math.radians(SUNSET_SUN_ELEVATION_DEG)
    az_s = math.radians(SUNSET_SUN_AZIMUTH_DEG)
    sun = np.array([-math.sin(az_s) * math.cos(el_s), math.sin(el_s),
                    math.cos(az_s) * math.cos(el_s)])
    cos_sun = np.clip(d @ sun, -1.0, 1.0)
    zen, hor, gnd = (np.array(c) for c in (SUNSET_ZENITH_RADIANCE, SUNSET_HORIZON_RADIANCE,
                                           SUNSET_GROUND_RADIANCE))
    # sky: horizon colour fading to the zenith with elevation; forward glow near the sun
    t = np.clip(np.sin(np.maximum(elev, 0.0)), 0.0, 1.0)[..., None] ** 0.5
    sky = hor * (1.0 - t) + zen * t
    glow = (np.exp((cos_sun - 1.0) / 0.08) * 0.8)[..., None] * np.array(SUNSET_SUN_COLOUR)
    sky = sky + glow * np.exp(-np.maximum(elev, 0.0) / 0.15)[..., None]
    img = np.where((elev >= 0)[..., None], sky, gnd)
    # sun disc: radiance normalised so that sum L cos(0) dOmega_pixel = SUNSET_SUN_IRRADIANCE
    in_sun = cos_sun >= math.cos(math.radians(SUNSET_SUN_RADIUS_DEG))
    if not in_sun.any():  # low resolution: the nearest pixel stands for the sun
        r, c = env.pixel_of(sun)
        in_sun = np.zeros_like(in_sun)
        in_sun[r, c] = True
    pix_sr = (math.pi / h) * (_TWO_PI / width) * sin_t
    colour = np.array(SUNSET_SUN_COLOUR) / (np.array(SUNSET_SUN_COLOUR) @ LUMINANCE)
    solid = float((pix_sr * cos_sun * in_sun).sum())
    img[in_sun] += colour * (SUNSET_SUN_IRRADIANCE / solid)
    return img.astype(np.float32)


@functools.lru_cache(maxsize=4)
def _cached_map(source: str, mtime: float, scale: float, rotation_deg: float) -> EnvironmentMap:
    """Build (once per source, scale and rotation) an environment map."""
    if source == "procedural_sunset":
        rad = procedural_sunset()
    else:
        from dermis.pipeline.imageio import read_image
        rad = read_image(source, channels=3, what="environment map")
    return EnvironmentMap(rad * np.float32(scale), rotation_deg=rotation_deg, name=source)


def environment_map(light, *, rotation_deg: float = 0.0) -> EnvironmentMap:
    """The :class:`EnvironmentMap` of an environment ``LightConfig`` (cached).

    ``light.map`` is ``"procedural_sunset"`` or a lat-long HDR/EXR path read with
    OpenImageIO (:func:`pipeline.imageio.read_image`); ``light.scale`` multiplies it.
    """
    source = str(getattr(light, "map", "procedural_sunset"))
    mtime = 0.0
    if source != "procedural_sunset":
        path = Path(source).expanduser()
        if not path.is_file():
            raise ConfigError(f"lights.{light.name}.map = {source!r}: file not found; use "
                              '"procedural_sunset" for the embedded sky')
        source, mtime = str(path.resolve()), path.stat().st_mtime
    scale = float(getattr(light, "scale", 1.0))
    if not (scale >= 0 and math.isfinite(scale)):
        raise ConfigError(f"lights.{light.name}.scale = {scale}: must be finite and >= 0")
    rotation_deg = rotation_deg or float(getattr(light, "rotation_deg", 0.0))
    try:
        return _cached_map(source, mtime, scale, float(rotation_deg))
    except DermisError as exc:  # name the scene key as well as the file
        raise type(exc)(f"lights.{light.name}.map = {source!r}: {exc}") from None


def light_params(lights) -> dict:
    """The lights as config slices, with the content hash of any environment map file."""
    from dataclasses import asdict
    from dermis.pipeline.store import file_digest
    params = {"lights": [asdict(l) for l in lights]}
    for light in lights:
        if light.type == "environment" and light.map != "procedural_sunset":
            params[f"map_sha256_{light.name}"] = file_digest(light.map)
    return params
