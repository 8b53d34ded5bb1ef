"""The environment light: a lat-long radiance map and its sampling distributions
(docs/science.md §6).

* :class:`EnvironmentMap` - a lat-long radiance map with a brightness x sin(theta) sampling
  distribution (brightness: the RGB norm, :func:`brightness`; sin: the pixel's solid angle),
  inverted through the flattened CDF, and the tables of the "product" strategy: the map's
  brightness mass in ~PRODUCT_BLOCKS blocks of
  pixels weighted by the cosine between each block and the normal, tabulated for
  PRODUCT_NORMAL_BINS lat-long bins of normals (the strategies: lighting/emitters.py).
* :func:`procedural_sunset` - the embedded sunset sky (sun 3 deg above the horizon, thesis).
* :func:`environment_map` - the map of an environment ``LightConfig``: an HDR/EXR read with
  OpenImageIO or the procedural sunset, scaled and rotated, cached.

Lat-long convention: y is up; image row 0 is the zenith; the image centre (u = 0.5) looks
along +z, in front of the face and behind the default camera, and the panorama is seen
unmirrored from inside (u grows towards -x).  With it, the Venice sunset map's sun
(column 614/1024) lands in front of the face, on the screen's left.

Guarded by tests/test_lights.py (constant environment gives pi L, importance-sampling
consistency, the lat-long convention and the sunset's sun, colour maps) and
tests/test_render.py.
"""
from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np

from dermis.pipeline.errors import ConfigError, DermisError
from dermis.pipeline.imageio import read_image
from dermis.pipeline.reuse import built_once
from dermis.rendering.color import LUMINANCE

__all__ = ["EnvironmentMap", "brightness", "procedural_sunset", "environment_map", "SUNSET_SUN_ELEVATION_DEG",
           "SUNSET_SUN_AZIMUTH_DEG", "SUNSET_SUN_IRRADIANCE", "PRODUCT_BLOCKS",
           "PRODUCT_NORMAL_BINS"]

# The "product" strategy's tables: the map in about 64 x 128 blocks of pixels, normals in
# 16 x 32 lat-long bins (512 tables of 8192 blocks: 32 MB, built once per map).
PRODUCT_BLOCKS = (64, 128)
PRODUCT_NORMAL_BINS = (16, 32)

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


def brightness(radiance: np.ndarray) -> np.ndarray:
    """The map's sampling weight per pixel: the Euclidean norm of its linear RGB radiance
    (float64).  Each channel's image is an error of its own (relative RMSE over the channels,
    bench/bench_env_noise.py): where the sky and the sun differ in colour - a blue zenith, an
    orange horizon - luminance (0.07 of the weight in blue) leaves the blue channel's sky and
    the red channel's horizon undersampled.  Measured on the default scan under the Venice
    sunset, 200 x 200, 8 seeds, relative RMSE against the converged render, Lafortune / HK93
    / BSSRDF: luminance 0.0854 / 0.0853 / 0.0296, RGB mean 0.0798 / 0.0796 / 0.0293, RGB
    norm 0.0722 / 0.0715 / 0.0292 (bench/results/env_noise.json "after_nets" "brightness")."""
    rad = np.asarray(radiance, np.float64)
    return np.sqrt(np.einsum("...k,...k->...", rad, rad))


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


class EnvironmentMap:
    """A lat-long radiance map with a brightness x sin(theta) sampling distribution
    (:func:`brightness`).

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
        weight = brightness(rad) * sin_t[:, None]
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

    # -- brightness x cosine ("product" strategy): tables per bin of normals, lazily built
    def _product(self) -> dict:
        """Tables of the product strategy (lighting/emitters.py docstring): the map's brightness mass in
        blocks of about PRODUCT_BLOCKS pixels, weighted per normal bin by the cosine of the
        block (padded by the block's and the bin's angular radius, so a block partly above
        a normal's horizon keeps some mass), and the pixels' share inside each block."""
        return built_once(self, "_prod", self._product_tables)

    def _product_tables(self) -> dict:
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
        # the block's and the pixel's CDFs as search trees (_tree), a block in two steps:
        # the row of blocks among the bin's row ends (the marginal over rows), then the block
        # in the bin's CDF along that row (the same block as one search of the bin's whole
        # CDF, and the two steps of the 2-D warp of product_sample's u2); and the pixels' CDF
        # in each block
        per = bh * bw
        row_cum = np.ascontiguousarray(cum[:, wc - 1::wc])             # (K, hc)
        # a pixel's block and position in the block as the sums of lookups by its row and its
        # column, and back (integer divisions of millions of samples cost more)
        r, c, b, q = np.arange(hc * bh), np.arange(wc * bw), np.arange(hc * wc), np.arange(per)
        return {"bh": bh, "bw": bw, "hc": hc, "wc": wc, "table": table.ravel(),
                "block_of": ((r // bh) * wc, c // bw), "pos_of": ((r % bh) * bw, c % bw),
                "rows_of": ((b // wc) * bh, q // bw), "cols_of": ((b % wc) * bw, q % bw),
                "nb": hc * wc, "per": per, "cum_last": cum[:, -1],
                "row_cum": row_cum, "row_tree": _tree(row_cum),
                "col_cum": cum.ravel(), "col_tree": _tree(cum.reshape(-1, wc)),
                "fine_tree": _tree(np.cumsum(share, axis=1)),
                "share": share.ravel(), "kr": kr, "kc": kc}

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

    def product_sample(self, u0: np.ndarray, jitter: np.ndarray, bins: np.ndarray,
                       pixel: bool = False, u2: np.ndarray | None = None):
        """Directions, radiance and pdf of the product strategy for uniform numbers ``u0``
        (M,) (the block) and ``jitter`` (M, 3) (the pixel in the block, then the point in
        the pixel: column, row) and the normal bin of each sample (M,) (:meth:`normal_bin`);
        with ``pixel`` also the picked pixel's (row, col).

        The block inverts the bin's CDF at u0 (u0 is stratified per point; an alias table
        would lose that).  With ``u2`` (M,) the pair (u0, u2) is warped in 2-D instead: the
        row of blocks by u0 through the bin's marginal over rows, the block along that row
        by u2 - the same block probabilities, so points stratified in 2-D stay stratified
        over the sphere, in elevation and in azimuth (u0 alone spreads them in elevation)."""
        t = self._product()
        per, wc = t["per"], t["wc"]
        rc = t["row_cum"]
        hc = rc.shape[1]
        bins = np.asarray(bins, np.int64)
        key = u0 * t["cum_last"].take(bins)
        key *= 1.0 - 1e-12
        r = _tree_search(t["row_tree"], bins, key)
        r = np.minimum(r, hc - 1, out=r)
        at = bins * hc + r
        if u2 is not None:     # the position along the row by u2
            flat = rc.ravel()
            hi = flat.take(at)
            lo = np.where(r > 0, flat.take(np.maximum(at - 1, 0)), 0.0)
            key = lo + u2 * (hi - lo)
            key *= 1.0 - 1e-12
        c = _tree_search(t["col_tree"], at, key)
        b = r * wc
        b += np.minimum(c, wc - 1, out=c)
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
        out = d, self.radiance_at(row, col), self.product_pdf(d, bins, row, col, b, j)
        return out + ((row, col),) if pixel else out

    def radiance_at(self, row: np.ndarray, col: np.ndarray) -> np.ndarray:
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
