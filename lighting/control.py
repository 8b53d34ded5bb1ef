"""The control variate of an environment light: the light a surface would receive unoccluded,
known exactly, so the samples estimate only what differs from it (docs/science.md §6).

For a hit with geometric normal n_g, the normals are binned (:data:`CONTROL_BINS`, lat-long,
each bin inside one bin of the product strategy's tables, lighting/environment.py); a bin b
has a centre n_b and a region R_b of the map: the pixels whose centre lies above n_b's horizon
and that the product strategy of the hit's bin can draw (positive block mass and luminance).
The control function of a hit with shading normal n_s is

    g(w) = L(w) (n_s . w) 1[w in R_b],   int g dw = n_s . M_b,   M_b = sum_{i in R_b} L_i m_i,

with m_i = int_pixel w dw in closed form for a lat-long pixel (:func:`pixel_moments`), so
the integral is exact for every n_s (bumped normals included) and the table M_b (per bin,
RGB x xyz) is computed once per map.  A BRDF f then estimates

    int f L cos V dw = alpha n_s . M_b + sum_s [f W cos V - alpha W (n_s . w_s) 1[w_s in R_b]],

W the sample's multiple-importance weight L / sum_k n_k p_k (lighting/mixture.py) and alpha
any number fixed per hit (the model's cosine-weighted mean of its diffuse part, cl/shade.cl):
the added terms have mean zero whatever alpha is, so the estimate stays unbiased, and where
the surface is unoccluded and diffuse the two sums cancel sample by sample.  That difference
estimator goes negative where occluders hide more of the region than the samples' average;
the renderer combines the sums per pixel (the irradiance pass per point) instead as a
non-negative estimator - the difference where the control sum is below its integral, the
ratio (the lit sum scaled by the integral over the control sum) above it - biased by
O(1 / samples) (:func:`control_estimate`).  The product strategy covers R_b by construction
(R_b keeps only pixels it can draw), so the control sum is unbiased for n_s . M_b.  Why: under the Venice sunset one hit's irradiance from 4 samples
had a relative spread of 10-30 % even with samples drawn in proportion to luminance x cosine:
the map's colour (a red sun, a blue sky, an orange horizon) cannot follow one scalar pdf;
measured on the default scan (bench/results/env_noise.json).

Guarded by tests/test_env_sampling.py (moments against quadrature, the estimator's mean
against brute force).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dermis.pipeline.reuse import built_once

__all__ = ["CONTROL_SPLIT", "ControlTable", "control_table", "pixel_moments", "control_estimate"]

# Normal bins of the control variate: CONTROL_SPLIT x CONTROL_SPLIT inside each of the
# product strategy's 16 x 32 (PRODUCT_NORMAL_BINS), so a hit's control region is one its
# product strategy covers.  The control's integral is exact for any normal (linear in n_s);
# the bin sets only where its region's edge lies, within ~4 deg of the horizon of a normal in
# the bin.
CONTROL_SPLIT = 2


@dataclass(frozen=True)
class ControlTable:
    """The control variate's tables for one map.

    kr, kc : normal bins (rows in theta, columns in phi, the map's lat-long convention)
    moments : (kr kc, 3, 3) float64 M_b, RGB x world xyz
    centres : (kr kc, 3) float64 the bins' centre normals n_b
    arcs : (kr kc, 3) float64 per bin (n_y, |n_xz|, phi_0 in column units): the pixel centres
        of one map row above n_b's horizon are an arc of columns (:meth:`arc`)
    rows : (H, 2) float64 cos and sin of each map row's centre
    excluded : whether some pixel above a bin's horizon lies in a block its product
        table cannot draw (then :meth:`member` tests the tables too)
    """

    kr: int
    kc: int
    moments: np.ndarray
    centres: np.ndarray
    arcs: np.ndarray
    rows: np.ndarray
    excluded: bool

    def bins(self, env, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(control bin, product bin) of each unit normal (N, 3): the product bin is the
        control bin's parent, so the two always nest."""
        t = env._product()
        d = np.asarray(normals, np.float64)
        theta = np.arccos(np.clip(d[:, 1], -1.0, 1.0))
        phi = np.arctan2(-d[:, 0], d[:, 2]) - env.rotation
        u = np.mod(phi / (2.0 * math.pi) + 0.5, 1.0)
        r = np.minimum((theta / math.pi * self.kr).astype(np.int64), self.kr - 1)
        c = np.minimum((u * self.kc).astype(np.int64), self.kc - 1)
        return r * self.kc + c, (r // CONTROL_SPLIT) * t["kc"] + c // CONTROL_SPLIT

    def arc(self, bins: np.ndarray, row: np.ndarray, width: int
            ) -> tuple[np.ndarray, np.ndarray]:
        """(first column, count) of the pixel centres of map row ``row`` strictly above the
        horizon of bin ``bins``'s centre n: with c the centre's direction, n . c =
        n_y cos t + |n_xz| sin t cos(p - p0) > 0 on an arc about p0 of half-width
        arccos(-n_y cos t / (|n_xz| sin t)), all or none of the row beyond.  One formula for
        the table and for :meth:`member`, so both see the same set of pixels."""
        a = self.arcs.take(bins, axis=0)
        ct, st = self.rows[row, 0], self.rows[row, 1]
        ny, rxz, x0 = a[..., 0], a[..., 1], a[..., 2]
        lateral = rxz * st
        with np.errstate(divide="ignore", invalid="ignore"):
            q = np.where(lateral > 0, -ny * ct / np.where(lateral > 0, lateral, 1.0),
                         np.where(ny * ct > 0, -2.0, 2.0))
        half = np.arccos(np.clip(q, -1.0, 1.0)) * (width / (2.0 * math.pi))
        lo = np.floor(x0 - half).astype(np.int64) + 1
        count = np.ceil(x0 + half).astype(np.int64) - lo
        count = np.where(q < -1.0, width, np.where(q >= 1.0, 0, np.clip(count, 0, width)))
        return lo, count

    def member(self, env, control_bins: np.ndarray, row: np.ndarray, col: np.ndarray,
               directions: np.ndarray | None = None) -> np.ndarray:
        """Whether map pixels (row, col) (...) lie in the region R_b of their hit's control
        bin (``control_bins`` broadcast against them).  With ``directions`` (..., 3), unit
        directions inside those pixels, only those within a pixel's radius of n_b's horizon
        are tested against the arcs: farther ones lie on the same side as their pixel's
        centre."""
        bins = np.broadcast_to(control_bins, row.shape)
        if directions is not None:
            nb = self.centres.astype(np.float32)
            dot = np.einsum("...k,...k->...", directions, nb[control_bins])
            h, w = env.height, env.width
            near = np.abs(dot) < 1.01 * (0.5 * math.pi / h + math.pi / w) + 1e-6
            inside = dot > 0
            if near.any():
                lo, count = self.arc(bins[near], row[near], w)
                inside[near] = np.mod(col[near] - lo, w) < count
        else:
            lo, count = self.arc(bins, row, env.width)
            inside = np.mod(col - lo, env.width) < count
        if self.excluded:
            t = env._product()
            parent = _parent(bins, self.kc, t["kc"])
            block = t["block_of"][0].take(row) + t["block_of"][1].take(col)
            inside &= t["table"].take(parent * t["nb"] + block) > 0
        return inside


def _parent(control_bins, kc: int, parent_kc: int) -> np.ndarray:
    r, c = np.divmod(np.asarray(control_bins, np.int64), kc)
    return (r // CONTROL_SPLIT) * parent_kc + c // CONTROL_SPLIT


def pixel_moments(env) -> np.ndarray:
    """(H, W, 3) float64 m_i = int_pixel w dw of every map pixel, in closed form: with
    w = (-sin t sin p, cos t, sin t cos p) and dw = sin t dt dp over the pixel's theta and
    phi ranges, x = -A (cos p0 - cos p1), y = B (p1 - p0), z = A (sin p1 - sin p0), where
    A = int sin^2 t dt and B = int cos t sin t dt."""
    h, w = env.height, env.width
    t0, t1 = np.arange(h) / h * math.pi, (np.arange(h) + 1) / h * math.pi
    p0 = 2.0 * math.pi * (np.arange(w) / w - 0.5) + env.rotation
    p1 = 2.0 * math.pi * ((np.arange(w) + 1) / w - 0.5) + env.rotation
    a = (t1 - t0) / 2.0 - (np.sin(2.0 * t1) - np.sin(2.0 * t0)) / 4.0
    b = (np.sin(t1) ** 2 - np.sin(t0) ** 2) / 2.0
    m = np.empty((h, w, 3))
    m[..., 0] = -a[:, None] * (np.cos(p0) - np.cos(p1))[None, :]
    m[..., 1] = b[:, None] * (p1 - p0)[None, :]
    m[..., 2] = a[:, None] * (np.sin(p1) - np.sin(p0))[None, :]
    return m


def control_table(env) -> ControlTable:
    """The map's :class:`ControlTable` (built once per map and kept on it).

    Each map row's share of M_b is a difference of the row's prefix sums of L m over the
    arc of columns above n_b's horizon (:meth:`ControlTable.arc`); pixels the bin's product
    table cannot draw (whole blocks of zero weight) are taken out again, block by block."""
    return built_once(env, "_control", lambda: _control_table(env))


def _control_table(env) -> ControlTable:
    t = env._product()
    h, w = env.height, env.width
    kr, kc = t["kr"] * CONTROL_SPLIT, t["kc"] * CONTROL_SPLIT
    lm = (env.radiance.astype(np.float64)[..., None]
          * pixel_moments(env)[:, :, None, :]).reshape(h, w, 9)
    prefix = np.zeros((h, w + 1, 9))
    np.cumsum(lm, axis=1, out=prefix[:, 1:])
    brow, bcol = np.divmod(np.arange(kr * kc), kc)
    nrm, _ = env._dirs((bcol + 0.5) / kc, (brow + 0.5) / kr)
    # the bins' arcs: n . c = n_y cos t + sin t (n_z cos p - n_x sin p), p = 2 pi (x + 0.5) / w
    # - pi + rotation at column coordinate x, so p0 = atan2(-n_x, n_z) sits at column x0
    phi0 = np.arctan2(-nrm[:, 0], nrm[:, 2])
    x0 = np.mod((phi0 - env.rotation + math.pi) / (2.0 * math.pi), 1.0) * w - 0.5
    arcs = np.stack([nrm[:, 1], np.hypot(nrm[:, 0], nrm[:, 2]), x0], axis=1)
    theta = (np.arange(h) + 0.5) / h * math.pi
    rows = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    out = ControlTable(kr, kc, np.zeros((kr * kc, 3, 3)), nrm, arcs, rows, False)
    moments = np.zeros((kr * kc, 9))
    r = np.arange(h)
    for s in range(0, kr * kc, 256):
        b = np.arange(s, min(s + 256, kr * kc))[:, None]
        lo, count = out.arc(b, np.broadcast_to(r, (len(b), h)), w)
        start = np.mod(lo, w)
        end = start + count
        wrap = end > w
        rr = np.broadcast_to(r, start.shape)
        part = prefix[rr, np.minimum(end, w)] - prefix[rr, start]
        part += np.where(wrap[..., None], prefix[rr, np.where(wrap, end - w, 0)], 0.0)
        moments[s:s + len(b)] = part.sum(axis=1)
    excluded = _exclude(env, t, out, lm.reshape(-1, 9), moments)
    return ControlTable(kr, kc, moments.reshape(-1, 3, 3), nrm, arcs, rows, excluded)


def _exclude(env, t, table: ControlTable, lm: np.ndarray, moments: np.ndarray) -> bool:
    """Take out of ``moments`` the pixels above a bin's horizon in blocks its product table
    cannot draw (zero weight); whether any were."""
    h, w = env.height, env.width
    weights = t["table"].reshape(-1, t["nb"])
    # each block's pixel centres and the cone about their mean that holds them: a block whose
    # cone lies below n_b's horizon has no pixel above it
    rows = t["rows_of"][0][:, None] + t["rows_of"][1][None, :]          # (blocks, per)
    cols = t["cols_of"][0][:, None] + t["cols_of"][1][None, :]
    ok = (rows < h) & (cols < w)
    rows, cols = np.minimum(rows, h - 1), np.minimum(cols, w - 1)
    centre, _ = env._dirs((cols + 0.5) / w, (rows + 0.5) / h)
    mean = np.where(ok[..., None], centre, 0.0).sum(axis=1)
    axis = mean / np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-30)
    cos_in = np.where(ok, np.einsum("bpk,bk->bp", centre, axis), 1.0).min(axis=1)
    sin_r = np.sin(np.arccos(np.clip(cos_in, -1.0, 1.0)) + 1e-9)
    parent = _parent(np.arange(len(moments)), table.kc, t["kc"])
    pairs = []
    for s in range(0, len(moments), 256):
        sl = slice(s, min(s + 256, len(moments)))
        near = (weights[parent[sl]] <= 0) & (table.centres[sl] @ axis.T >= -sin_r[None, :])
        b, k = np.nonzero(near)
        pairs.append((b + s, k))
    bi = np.concatenate([p[0] for p in pairs])
    blk = np.concatenate([p[1] for p in pairs])
    if not len(bi):
        return False
    rows, cols, ok = rows[blk], cols[blk], ok[blk]
    lo, count = table.arc(np.broadcast_to(bi[:, None], rows.shape), rows, w)
    inside = ok & (np.mod(cols - lo, w) < count)
    if not inside.any():
        return False
    q, p = np.nonzero(inside)
    np.add.at(moments, bi[q], -lm[rows[q, p] * w + cols[q, p]])
    return True


def control_estimate(total, signed, ctrl, ctrl_signed, exact, exact_signed):
    """The control variate (lighting/control.py) per pixel and channel as a non-negative
    estimator: Y the sum of the control region's samples (the others, a split sun's
    (lighting/sun.py), are added as they are: scaling them by the sky's C / X would add the
    sky's noise to the sun's light), X the control samples' sum, C the control's exact
    integral,

        Y + (C - X)                where X <= C   (the difference estimator, >= Y >= 0),
        Y C / X = Y + (C - X) Y / X  where X > C   (the ratio estimator, Y scaled down),

    so the estimate is Y + beta (C - X) with beta = min over the two (1 or Y / X): never
    negative, and the scale C / X < 1 never amplifies a sample.  Where the surface is
    unoccluded and diffuse Y = X sample by sample and both give C.  The difference estimator
    alone (beta = 1, unbiased) went negative where the control samples outweigh what is lit
    (occluded hits: X > C + Y); the ratio estimator alone blew up where X is small (HK93's
    single scattering over a near-empty control sum: 0.34 relative noise).  Biased by
    O(1 / samples) where X > C: E[Y / X] C is not E[Y] (Cochran 1977, "Sampling Techniques",
    §6.8), measured in bench/results/env_noise.json.  The halves (rendering/halves.py) each
    take their own estimate; the noise is half their difference.  Returns the estimate and
    the noise (or None).  Per pixel in the renderer (rendering/shade.py), per point in the
    irradiance pass (lighting/irradiance.py)."""
    def est(y, x, c):
        over = x > c
        return np.where(over, y * c / np.where(over, x, 1.0), y + (c - x))

    image = est(total, ctrl, exact)
    if signed is None:
        return image, None
    half = [est((total + k * signed) / 2, (ctrl + k * ctrl_signed) / 2,
                (exact + k * exact_signed) / 2) for k in (1, -1)]
    return image, half[0] - half[1]
