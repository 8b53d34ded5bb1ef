"""BRDF-lobe sampling: extra environment-sampling strategies about a direction the BRDF
favours, combined with the luminance and cosine strategies by multiple importance sampling
(lighting/emitters.py ``sample_lights``, argument ``lobe``).

* :class:`GlossyLobe` - a share of the samples drawn about the glossy reflection of the
  view.  Measured on the Lee Perry-Smith head under the Venice sunset (Lafortune, 800 x
  800, 4 camera samples x 4 light samples per pixel) it removed a third of the specular
  lobes' own outliers but, taking samples from the diffuse strategies, made the whole
  Lafortune image noisier (off by default).
* :class:`LafortuneLobes` - the Lafortune skin fit's three lobes (docs/science.md §1) as they
  are: a table of their f cos per view cosine over the incident directions, sampled where the
  lobes reflect most, with a share of the samples per hit set by how much of the hit's
  reflection the lobes carry (:meth:`LafortuneLobes.fractions`).  It replaces
  :class:`GlossyLobe` where a scene renders the lobes (rendering/cast.py ``glossy_lobes``).
* :class:`RetroLobe` - a backward-scattering layer (HK93 with g < RETRO_G_MAX) instead draws
  a share about the view direction itself, where its Henyey-Greenstein backscatter peak
  lies (wi = wo): at g = -0.99 that peak is ~1e3 times its mean and the other strategies
  land in it too rarely (fireflies, docs/hardening.md; measured in
  bench/results/hk93_retro.json).

Each lobe gives the share of the samples it draws (``fraction``), directions for uniform
numbers (``sample``) and their solid-angle density (``pdf``); the MIS weights count that
density whatever the BRDF is, so the estimate stays unbiased for every model.

Guarded by tests/test_lights.py (the retro lobe is unbiased and tames a backscatter peak)
and tests/test_hardening.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import functools

import numpy as np

from dermis.lighting.warps import about_axis, normalize, tangent_frames

__all__ = ["GlossyLobe", "LafortuneLobes", "RetroLobe", "RETRO_G_MAX", "RETRO_FRACTION",
           "LOBE_TABLE", "LOBE_SHARE_SCALE", "LOBE_SHARE_SCALE_CONTROL", "LOBE_SHARE_MAX"]

_TWO_PI = 2.0 * math.pi


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

    def fractions(self) -> np.ndarray:
        """(N,) the share of each point's samples (``fraction`` everywhere)."""
        return np.full(len(self.view), float(self.fraction))

    def axis(self) -> np.ndarray:
        v = np.asarray(self.view, np.float64)
        nrm = normalize(np.asarray(self.normals, np.float64))
        vn = np.einsum("ij,ij->i", v, nrm)[:, None]
        return normalize(-(v - vn * nrm) + self.tilt * vn * nrm)

    def sample(self, u: np.ndarray) -> np.ndarray:
        """(N, S, 3) directions for uniform (N, S, 2) numbers."""
        a = self.axis()
        cos_a = u[..., 0] ** (1.0 / (self.exponent + 1.0))
        return about_axis(a, cos_a, _TWO_PI * u[..., 1])

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

    def fractions(self) -> np.ndarray:
        """(N,) the share of each point's samples (``fraction`` everywhere)."""
        return np.full(len(self.view), float(self.fraction))

    def sample(self, u: np.ndarray) -> np.ndarray:
        """(N, S, 3) directions for uniform (N, S, 2) numbers."""
        a = normalize(np.asarray(self.view, np.float64))
        k = self.k
        if k < 1e-3:
            cos_a = 1.0 - 2.0 * u[..., 0]
        else:
            sq = (1.0 - k * k) / (1.0 - k + 2.0 * k * u[..., 0])
            cos_a = np.clip((1.0 + k * k - sq * sq) / (2.0 * k), -1.0, 1.0)
        return about_axis(a, cos_a, _TWO_PI * u[..., 1])

    def pdf(self, directions: np.ndarray) -> np.ndarray:
        """(N, S) solid-angle density of (N, S, 3) directions."""
        a = normalize(np.asarray(self.view, np.float64))
        c = np.einsum("nsk,nk->ns", directions, a)
        k = self.k
        return (1.0 - k * k) / (4.0 * math.pi * np.maximum(1.0 + k * k - 2.0 * k * c, 1e-30)
                                ** 1.5)


# The lobe table: view cosines x incident cosines x incident azimuths about the view's (bins
# uniform in each); the sharp lobe (exponent ~60, ~8 deg wide) spans ~6 x 3 cells at grazing.
LOBE_TABLE = (32, 64, 128)
# Share of a hit's environment samples drawn from the lobes: LOBE_SHARE_SCALE x the lobes'
# part of the hit's directional albedo, rho_L(mu_o) / (rho_L + rho_d (1 - rho_L)) (luminance;
# rho_d the fit's diffuse albedo), at most LOBE_SHARE_MAX: ~4 % at normal view, ~20 % at
# grazing.  Measured on the default scan under the Venice sunset (200 x 200, 4 seeds,
# relative RMSE Lafortune / HK93 / BSSRDF, cosine share 1/8; bench/results/env_noise.json
# "shares"): scale 0 -> 0.109 / 0.095 / 0.061, 0.25 -> 0.100 / 0.098 / 0.041, 0.5 -> 0.102 /
# 0.103 / 0.032, 1 -> 0.112 / 0.117 / 0.023, 2 -> 0.139 / 0.149 / 0.018: 0.5 is the largest
# that keeps the diffuse models (HK93, asperity) within 5 % of their noise without lobe
# samples (the lobes take samples from the sky they need).  With the control variate the
# diffuse noise is mostly gone and the lobes may take more: 2 -> 0.046 / 0.044 / 0.018
# against 0.5 -> 0.050 / 0.039 / 0.032.
LOBE_SHARE_SCALE = 0.5
LOBE_SHARE_SCALE_CONTROL = 2.0
LOBE_SHARE_MAX = 0.75


@functools.lru_cache(maxsize=4)
def _lobe_table(key: tuple) -> dict:
    """The lobes' f cos integrated over each cell (midpoints, 2 x 2 per cell), per view-cosine
    bin (at its centre), summed over the RGB channels, as row and cell CDFs."""
    cxy, cz, ex = (np.array(key[i], np.float64).reshape(3, 3) for i in range(3))
    nmu, ni, nj = LOBE_TABLE
    sub = 2
    mu_o = (np.arange(nmu) + 0.5) / nmu
    ci = ((np.arange(ni)[:, None] + (np.arange(sub) + 0.5) / sub) / ni).ravel()
    phi = ((np.arange(nj)[:, None] + (np.arange(sub) + 0.5) / sub) / nj * _TWO_PI - math.pi).ravel()
    si = np.sqrt(1.0 - ci * ci)
    cells = np.zeros((nmu, ni, nj))
    for m, mo in enumerate(mu_o):
        xy = math.sqrt(1.0 - mo * mo) * si[:, None] * np.cos(phi)[None, :]
        zz = np.broadcast_to(mo * ci[:, None], xy.shape)
        tot = np.zeros(xy.shape)
        for k in range(3):
            for c in range(3):
                base = cxy[k, c] * xy + cz[k, c] * zz
                tot += np.where(base > 0, np.abs(base) ** ex[k, c], 0.0)
        tot *= ci[:, None]
        cells[m] = tot.reshape(ni, sub, nj, sub).mean(axis=(1, 3))
    rows = cells.sum(axis=2)                                            # (nmu, ni)
    row_cum = np.cumsum(rows, axis=1)
    total = row_cum[:, -1:]
    pmf = cells / np.where(total > 0, total, 1.0)[..., None]           # per view bin
    cell_cum = np.cumsum(cells, axis=2)
    last = cell_cum[..., -1:]
    # each row's CDF normalised (uniform where the row is empty)
    cond = np.where(last > 0, cell_cum / np.where(last > 0, last, 1.0),
                    (np.arange(nj) + 1.0) / nj)
    row_cum = row_cum / np.where(total > 0, total, 1.0)
    from dermis.lighting.environment import _tree
    return {"pmf_flat": pmf.ravel() * (ni * nj / _TWO_PI), "row_cum": row_cum,
            "row_tree": _tree(row_cum), "cell_tree": _tree(cond.reshape(nmu * ni, nj)),
            "cond": cond.reshape(-1)}


class LafortuneLobes:
    """An environment-sampling strategy for the Lafortune lobes seen at ``view``: directions
    drawn in proportion to a table of the lobes' f cos (summed over RGB) for the view's
    cosine, piecewise constant over cells of incident cosine and azimuth about the view
    (:data:`LOBE_TABLE`): a cell by its share, a point uniformly in it.  The density of a
    direction is its cell's share over the cell's solid angle, so any model may shade these
    samples (the multiple-importance weights count it).

    view : (N, 3) unit directions to the eye; normals : (N, 3) unit (shading) normals;
    params : the LafortuneParams whose lobes are drawn (default: the skin fit).  The frame
    of each point (its view-cosine bin, t along the view's tangential part, b, n) is computed
    once; indexing (``lobes[idx]``) takes its rows.
    """

    def __init__(self, view, normals, params=None, scale: float = None, _frame=None):
        from dermis.models.lafortune import LafortuneParams
        self.params = params if params is not None else LafortuneParams()
        self.scale = float(LOBE_SHARE_SCALE if scale is None else scale)
        self._key = (tuple(self.params.cxy.ravel()), tuple(self.params.cz.ravel()),
                     tuple(self.params.n.ravel()))
        self.frame = _frame if _frame is not None else self._make_frame(view, normals)

    @staticmethod
    def _make_frame(view, normals) -> tuple:
        n = normalize(np.asarray(normals, np.float64))
        v = np.asarray(view, np.float64)
        mu = np.einsum("ij,ij->i", v, n)
        t = v - mu[:, None] * n
        length = np.sqrt(np.einsum("ij,ij->i", t, t))
        ok = length > 1e-6
        t /= np.where(ok, length, 1.0)[:, None]
        if not ok.all():                        # normal view: the lobes are symmetric
            t[~ok] = tangent_frames(n[~ok])[0]
        b = np.cross(n, t)
        nmu = LOBE_TABLE[0]
        m = np.minimum((np.clip(mu, 0.0, 1.0) * nmu).astype(np.int64), nmu - 1)
        return m, t, b, n, mu

    def __len__(self) -> int:
        return len(self.frame[0])

    def __getitem__(self, sl) -> "LafortuneLobes":
        return LafortuneLobes(None, None, self.params, self.scale,
                              tuple(a[sl] for a in self.frame))

    def _table(self) -> dict:
        return _lobe_table(self._key)

    def fractions(self) -> np.ndarray:
        """(N,) share of each point's environment samples drawn from the lobes (module
        constants LOBE_SHARE_SCALE and LOBE_SHARE_MAX)."""
        from dermis.models.lafortune import lobe_albedo_table
        from dermis.rendering.color import LUMINANCE
        table, _ = lobe_albedo_table(self.params)
        mu = self.frame[4]
        nodes = np.linspace(0.0, 1.0, len(table))
        rho_l = np.interp(np.clip(mu, 0.0, 1.0), nodes, table @ LUMINANCE)
        rho_d = float(np.asarray(self.params.rho_d, np.float64) @ LUMINANCE)
        share = rho_l / np.maximum(rho_l + rho_d * (1.0 - rho_l), 1e-12)
        return np.minimum(self.scale * share, LOBE_SHARE_MAX)

    def sample(self, u: np.ndarray) -> np.ndarray:
        """(N, S, 3) directions for uniform (N, S, 2) numbers: u[..., 0] picks the row of
        incident cosines, u[..., 1] the cell along it (a 2-D warp: stratified points stay
        stratified), what is left of each places the point in the cell."""
        from dermis.lighting.environment import _tree_search
        t = self._table()
        nmu, ni, nj = LOBE_TABLE
        m, tt, bb, n, _ = self.frame
        shape = u.shape[:-1]
        mm = np.broadcast_to(m.reshape((-1,) + (1,) * (len(shape) - 1)), shape).ravel()
        u = u.reshape(-1, 2)
        # the row of incident cosines (the view bin's CDF over rows), then the cell along it
        k1 = u[:, 0] * (1.0 - 1e-12)
        r = np.minimum(_tree_search(t["row_tree"], mm, k1), ni - 1)
        rf = t["row_cum"].ravel()
        base = mm * ni
        hi = rf.take(base + r)
        lo = np.where(r > 0, rf.take(np.maximum(base + r - 1, 0)), 0.0)
        f1 = np.clip((k1 - lo) / np.maximum(hi - lo, 1e-300), 0.0, 1.0)
        row = base + r
        k2 = u[:, 1] * (1.0 - 1e-12)
        j = np.minimum(_tree_search(t["cell_tree"], row, k2), nj - 1)
        cond = t["cond"]
        at = row * nj + j
        hi2 = cond.take(at)
        lo2 = np.where(j > 0, cond.take(np.maximum(at - 1, 0)), 0.0)
        f2 = np.clip((k2 - lo2) / np.maximum(hi2 - lo2, 1e-300), 0.0, 1.0)
        r, j, f1, f2 = (a.reshape(shape) for a in (r, j, f1, f2))
        cos_i = (r + f1) / ni
        phi = (j + f2) * (_TWO_PI / nj) - math.pi
        sin_i = np.sqrt(np.maximum(1.0 - cos_i * cos_i, 0.0))
        x, y = sin_i * np.cos(phi), sin_i * np.sin(phi)
        ex = (slice(None),) + (None,) * (len(shape) - 1)
        d = np.empty(shape + (3,))
        for k in range(3):
            d[..., k] = x * tt[ex + (k,)] + y * bb[ex + (k,)] + cos_i * n[ex + (k,)]
        return d

    def pdf(self, directions: np.ndarray) -> np.ndarray:
        """(N, S) solid-angle density of (N, S, 3) directions: the cell's share over its solid
        angle (2 pi / (ni nj)); 0 below the horizon."""
        t = self._table()
        nmu, ni, nj = LOBE_TABLE
        m, tt, bb, n, _ = self.frame
        d = np.asarray(directions)
        if d.dtype == np.float32:             # the renderer's directions: float32 throughout
            tt, bb, n = (a.astype(np.float32) for a in (tt, bb, n))
        c = np.einsum("nsk,nk->ns", d, n)
        x = np.einsum("nsk,nk->ns", d, tt)
        y = np.einsum("nsk,nk->ns", d, bb)
        i = np.minimum((np.clip(c, 0.0, 1.0) * ni).astype(np.int64), ni - 1)
        phi = np.arctan2(y, x)
        phi += math.pi
        phi *= nj / _TWO_PI
        j = np.minimum(phi.astype(np.int64), nj - 1)
        i *= nj
        i += j
        i += (m * (ni * nj))[:, None]
        p = t["pmf_flat"].take(i)
        p[~(c > 0)] = 0.0
        return p
