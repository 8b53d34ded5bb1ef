"""An environment light's samples for the renderer: one-sample multiple importance sampling over
three strategies with per-hit shares, samples stratified over the pixel in two dimensions,
and the control variate's region (docs/science.md §6).

Each of a hit's S samples draws its strategy by a number u1 stratified over the pixel's
samples (lighting/strata.py :class:`PixelStrata`): u1 < c_env the product strategy
(luminance x cosine, lighting/environment.py), then the cosine hemisphere about the
geometric normal (c_cos), then the lobe strategy (c_lobe, lighting/lobes.py), the shares
per hit (the lobe's from :meth:`LafortuneLobes.fractions`: where the lobes carry much of the
reflection, at grazing views, they draw most).  What is left of u1 inside the chosen share and
a second stratified number u2 make a 2-D point for the strategy's warp (the product's row of
map blocks, then the block; the cosine's disc; the lobe table's row, then the cell), so the
pixel's samples of each strategy spread over the sphere in elevation and in azimuth.

Estimator (Veach 1997 §9.2.4, the one-sample model with the balance heuristic, summed over
the S samples): every sample, whichever strategy drew it, has weight

    W = L(w) / (S sum_k c_k p_k(w)),

all three densities evaluated at its direction.  Unbiased: over a hit's S samples (and the
pixel's random rotation of the strata) the pairs (u1, u2) fill [0, 1)^2 uniformly, so
strategy k is drawn S c_k times in expectation, and sum_k S c_k E_k[h / (S sum c p)] = int h
wherever sum c p > 0 (tests/test_env_sampling.py against brute force).  The cosine strategy
covers the geometric normal's hemisphere, where the renderer shades; the product strategy
covers the control variate's region (lighting/control.py), so the control sum is unbiased
too.

Measured on the default scan under the Venice sunset (200 x 200, 8 seeds, relative RMSE
against a 32,768-sample render; bench/results/env_noise.json "after"): Lafortune 0.121 ->
0.097, BSSRDF 0.065 -> 0.032, HK93 0.106 -> 0.099, asperity 0.104 -> 0.098 against the fixed
shares (3 product + 1 cosine sample per hit, the block coordinate stratified in 1-D); with the
control variate 0.045 / 0.017 / 0.043 / 0.048.  The product tables' bin is the hit's
interpolated normal's (``product_normals``: the cosine the image shades with), the cosine
strategy's hemisphere the geometric normal's (every direction the renderer shades).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dermis.lighting.control import control_table
from dermis.lighting.warps import cosine_hemisphere, normalize

__all__ = ["EnvironmentSamples", "sample_environment", "COSINE_SHARE"]

# Share of the samples not drawn from the lobe that come from the cosine hemisphere (the rest:
# the product strategy); it covers what the product tables miss.  Measured on the default
# scan under the Venice sunset (200 x 200, 8 seeds, relative RMSE Lafortune / HK93 / BSSRDF,
# lobe scale 0.5, the pixel's nets; bench/results/env_noise.json "after_nets" "shares"):
# 1/8 -> 0.0787 / 0.0783 / 0.0300, 1/16 -> 0.0750 / 0.0745 / 0.0294, 1/32 -> 0.0722 /
# 0.0715 / 0.0292, 1/64 -> 0.0709 / 0.0700 / 0.0291: below 1/32 the gain is under 2 %,
# and 1/32 keeps twice 1/64's samples where the tables' padded cosine misses.
COSINE_SHARE = 1.0 / 32.0


@dataclass
class EnvironmentSamples:
    """S samples per point of one environment light.

    directions : (N, S, 3) float32; weights : (N, S, 3) float32 W (module docstring), 0 where
    the map is black; with the control variate (else None): control : (N, S) bool, in its
    region of the point's bin; control_bin : (N,) int32 the point's control bin; table : its
    ControlTable
    """

    directions: np.ndarray
    weights: np.ndarray
    control: np.ndarray
    control_bin: np.ndarray
    table: object


def _uniforms(rng, n: int, s: int, strata, salt: int) -> tuple[np.ndarray, np.ndarray]:
    """Two (n, s) numbers whose pairs (u1, u2) are stratified over the pixel: the cells of its
    jittered grid (:meth:`PixelStrata.uniform_2d`, one cell per sample of the pixel when it
    has a square number of them), else u1 and u2 each stratified and paired at random; per
    point without strata, a Latin hypercube.  Over a point's samples (and the pixel's random
    rotation of the strata) the pairs fill [0, 1)^2 uniformly, so each sample's strategy is
    drawn with the shares c_k on average."""
    if strata is not None:
        g = strata.uniform_2d(rng, s, 2 * salt)
        return g[..., 0], g[..., 1]
    else:
        u1 = (np.arange(s)[None, :] + rng.random((n, s))) / s
        u2 = (np.arange(s)[None, :] + rng.random((n, s))) / s
    # pair them at random: a point's j-th numbers both lie in [j / s, (j + 1) / s), so u2 is
    # shuffled among its samples (else the pairs would crowd the diagonal)
    return u1, np.take_along_axis(u2, np.argsort(rng.random((n, s)), axis=1), axis=1)


def sample_environment(env, normals: np.ndarray, rng, samples: int, *, strata=None,
                       salt: int = 0, lobe=None, control: bool = False,
                       horizon: bool = False,
                       product_normals: np.ndarray | None = None) -> EnvironmentSamples:
    """The samples of one environment map ``env`` for points with unit geometric ``normals``
    (N, 3) (module docstring).  ``lobe``: a strategy with ``fractions()`` (N,) shares,
    ``__getitem__``, ``sample(u)`` and ``pdf(directions)`` (lighting/lobes.py), or None;
    ``control``: also the control variate's region (lighting/control.py); ``horizon``: weights
    0 below the normals' horizon (but in the control variate's region); ``product_normals``
    (N, 3): the normals whose bins the product strategy's tables are read for (default
    ``normals``; not with ``control``)."""
    n, s = len(normals), int(samples)
    nrm = normalize(np.asarray(normals, np.float64))
    table = control_table(env) if control else None
    if control:
        cbin, bins = table.bins(env, nrm)
    else:
        cbin, bins = None, env.normal_bin(nrm)
    if product_normals is not None and not control:
        bins = env.normal_bin(normalize(np.asarray(product_normals, np.float64)))
    if env.black or n == 0:
        z = np.zeros((n, s), bool)
        return EnvironmentSamples(np.zeros((n, s, 3), np.float32),
                                  np.zeros((n, s, 3), np.float32), z if control else None,
                                  None if cbin is None else cbin.astype(np.int32), table)
    c_l = (np.clip(np.asarray(lobe.fractions(), np.float64), 0.0, 0.95) if lobe is not None
           else np.zeros(n))
    c_c = (1.0 - c_l) * COSINE_SHARE
    c_e = 1.0 - c_l - c_c
    u1, u2 = _uniforms(rng, n, s, strata, salt)
    u1, u2 = u1.ravel(), u2.ravel()
    hit = np.repeat(np.arange(n), s)                         # each sample's point
    e_end = np.repeat(c_e, s)
    c_end = e_end + np.repeat(c_c, s)
    k = n * s
    wi = np.empty((k, 3), np.float32)
    row = np.empty(k, np.int64)
    col = np.empty(k, np.int64)
    den = np.empty(k)
    w = np.empty((k, 3), np.float32)
    # the product strategy: the block by the 2-D warp, then the pixel and the point in it
    ie = np.flatnonzero(u1 < e_end)
    h = hit.take(ie)
    d, rad, pdf, (r, c) = env.product_sample(u1.take(ie) / e_end.take(ie),
                                             rng.random((len(ie), 3)), bins.take(h),
                                             pixel=True, u2=u2.take(ie))
    wi[ie], w[ie], row[ie], col[ie] = d, rad, r, c
    den[ie] = pdf * c_e.take(h)
    # the cosine hemisphere about the geometric normal, and the lobe
    io = np.flatnonzero(u1 >= e_end)
    ic = np.flatnonzero((u1 >= e_end) & (u1 < c_end))
    h = hit.take(ic)
    uc = np.stack([(u1.take(ic) - e_end.take(ic)) / c_c.take(h), u2.take(ic)], axis=-1)
    wi[ic] = cosine_hemisphere(np.clip(uc, 0.0, 1.0 - 1e-12)[:, None, :], nrm[h])[0][:, 0]
    if lobe is not None:
        il = np.flatnonzero(u1 >= c_end)
        if len(il):
            h = hit.take(il)
            ul = np.stack([(u1.take(il) - c_end.take(il)) / np.maximum(c_l.take(h), 1e-30),
                           u2.take(il)], axis=-1)
            wi[il] = lobe[h].sample(np.clip(ul, 0.0, 1.0 - 1e-12)[:, None, :])[:, 0]
    if len(io):
        h = hit.take(io)
        d = wi[io]
        r, c = env.pixel_of(d)
        row[io], col[io] = r, c
        w[io] = env.radiance_at(r, c)
        den[io] = env.product_pdf(d, bins.take(h), r, c) * c_e.take(h)
    # the balance heuristic over the three densities, at every sample's direction
    wi = wi.reshape(n, s, 3)
    den = den.reshape(n, s)
    cos = np.einsum("nsk,nk->ns", wi, nrm.astype(np.float32))
    below = cos <= 0
    np.maximum(cos, 0.0, out=cos)
    den += (c_c / math.pi)[:, None] * cos
    if lobe is not None:
        den += c_l[:, None] * lobe.pdf(wi)
    den *= s
    with np.errstate(divide="ignore"):
        inv = np.where(den > 0, 1.0 / np.where(den > 0, den, 1.0), 0.0).astype(np.float32)
    member = None
    if control:
        member = table.member(env, cbin[:, None], row.reshape(n, s), col.reshape(n, s), wi)
        member &= den > 0
    if horizon:
        inv[below & (~member if member is not None else True)] = 0.0
    w = w.reshape(n, s, 3)
    for k in range(3):
        w[..., k] *= inv
    if not control:
        return EnvironmentSamples(wi, w, None, None, None)
    return EnvironmentSamples(wi, w, member, cbin.astype(np.int32), table)
