"""Error bars of a distance to the reference: the reference's noise and the model's own.

Both images are Monte Carlo estimates.  The reference carries its noise as the signed
half-difference of two independent halves (``RenderedImage.noise`` when it is set) or, as
the reference stage records it, as the standard error of each face region's mean and the
relative noise of its block means (``info["regions"]``, ``info["noise"]``,
``info["region_rel_se"]``).  A model image carries its own as ``RenderedImage.noise``, or
None (its noise is then taken as 0 and the report says "own noise not estimated").

With independent pixels the variance of a mean over n pixels is sum(var_p) / n^2, and a
pixel's variance is estimated by noise_p^2 (E[((A - B) / 2)^2] = var((A + B) / 2)).  A
model's noise is first averaged over the camera pixels of each reference pixel (the
block's half-difference: correlation inside the block is kept) and squared there.

For a difference r = m / q - 1 of a model mean m from a reference mean q (first-order
error propagation, the two independent)::

    sigma_r^2 = (se_m / q)^2 + (1 + r)^2 ((se_q / q)^2 + c^2)

c being the reference's calibration error (relative, the albedo tint's; a common scale of
the reference, so it enters region means but not the block RMSE's noise floor).  For the
relative RMSE e over blocks (e^2 = sum (D - M)^2 / sum M^2, every channel and block), noise
alone gives E[e^2] = sigma_ref^2 + sigma_model^2 with sigma^2 = sum var / sum M^2; a
distance counts as resolved when e > ``RESOLVE_K`` sqrt(sigma_ref^2 + sigma_model^2).

Two models a, b are compared by s = e^2 - sigma_model^2 (the reference's share of E[e^2] is
the same for both); on their common blocks, with u = D - M and v the per-element
variances (Gaussian noise)::

    var(s_a - s_b) = [4 sum((D_a - D_b)^2 v_M + u_a^2 v_a + u_b^2 v_b + (v_a + v_b) v_M)
                      + 2 sum(v_a^2 + v_b^2)] / (sum M^2)^2

(u^2 and (D_a - D_b)^2 are estimated from the noisy images: slightly conservative).
"""
from __future__ import annotations

import math

import numpy as np

from dermis.geometry.regions import REGION_LABELS, block_mean
from dermis.rendering.color import LUMINANCE

__all__ = ["RESOLVE_K", "VERDICTS", "HOLDS", "FAILS", "UNRESOLVED", "model_noise_on",
           "ref_var_map", "ref_scale_noise", "scale_noise", "region_difference",
           "mean_se", "pair_test", "rank_ranges", "compare", "combine_verdicts"]

RESOLVE_K = 2.0   # a difference must exceed 2 standard errors (about 95 %, two-sided) to count
HOLDS, FAILS, UNRESOLVED = "holds", "does not hold", "not resolved at this noise"
VERDICTS = (HOLDS, FAILS, UNRESOLVED)
_LUM2 = LUMINANCE * LUMINANCE


def model_noise_on(image, shape, block) -> np.ndarray | None:
    """The model's half-difference averaged over the camera pixels of each reference pixel
    ((h, w, 3) float64), or None when the image has no noise estimate."""
    noise = getattr(image, "noise", None)
    if noise is None:
        return None
    n = np.asarray(noise, np.float64)
    if n.shape != np.shape(image.linear):
        return None
    h, w = shape
    return block_mean(n, np.asarray(image.mask, bool), block)[0][:h, :w]


def ref_var_map(ref, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Per reference pixel and channel, the variance of the reference's value ((h, w, 3)), and
    its signed half-difference when the artifact carries one (else None).

    Without a half-difference: a pixel of region k gets that region's per-pixel variance,
    (stderr_rgb x sqrt(pixels))^2; any other pixel the image's mean one,
    (noise["1"]["rel_rgb"] x rms of the channel)^2 (0 when the reference records neither).
    """
    M = np.asarray(ref.linear, np.float64)
    hd = getattr(ref, "noise", None)
    if hd is not None and np.shape(hd) == M.shape:
        hd = np.asarray(hd, np.float64)
        return hd * hd, hd
    info = ref.info or {}
    mask = np.asarray(ref.mask, bool)
    rel = (info.get("noise", {}).get("1", {}) or {}).get("rel_rgb")
    var = np.zeros(M.shape)
    if rel is not None and mask.any():
        rms = np.sqrt((M[mask] ** 2).mean(axis=0))
        var[:] = (np.asarray(rel, np.float64) * rms) ** 2
    for name, rr in (info.get("regions") or {}).items():
        if name not in REGION_LABELS or "stderr_rgb" not in rr or not rr.get("pixels"):
            continue
        sel = labels == REGION_LABELS[name]
        var[sel] = (np.asarray(rr["stderr_rgb"], np.float64) * math.sqrt(rr["pixels"])) ** 2
    return var, None


def scale_noise(noise_on_grid, Mb: np.ndarray, mb: np.ndarray, f: int, valid) -> float | None:
    """sqrt(sum (block-mean noise)^2 / sum M_b^2) over the blocks ``mb`` at factor f: the
    relative RMSE that this noise alone gives (None when there is no noise)."""
    if noise_on_grid is None:
        return None
    Nb, _ = block_mean(noise_on_grid, valid, f)
    den = float((Mb[mb] ** 2).sum())
    return math.sqrt(float((Nb[mb] ** 2).sum()) / den) if den > 0 else 0.0


def ref_scale_noise(ref, ref_hd, Mb, mb, f: int, valid) -> float:
    """The reference's relative block noise at factor f over the blocks compared: from its
    half-difference when it has one, else as the reference stage measured it
    (``info["noise"][f]["rel"]``, 0 when missing)."""
    if ref_hd is not None:
        return scale_noise(ref_hd, Mb, mb, f, valid)
    return float(((ref.info or {}).get("noise", {}).get(str(f), {}) or {}).get("rel", 0.0))


def mean_se(sel: np.ndarray, *, var: np.ndarray | None = None, hd: np.ndarray | None = None
            ) -> tuple[np.ndarray, float]:
    """(standard error per channel, standard error of the luminance) of the mean over the
    pixels ``sel``: from the signed half-difference ``hd`` (luminance of the half-difference)
    or, without it, from per-channel variances (channels independent)."""
    n = int(sel.sum())
    if n == 0:
        return np.zeros(3), 0.0
    if hd is not None:
        h = hd[sel]
        return np.sqrt((h * h).sum(axis=0)) / n, math.sqrt(float(((h @ LUMINANCE) ** 2).sum())) / n
    if var is None:
        return np.zeros(3), 0.0
    v = var[sel]
    return np.sqrt(v.sum(axis=0)) / n, math.sqrt(float((v @ _LUM2).sum())) / n


def _rel(m, q, se_m, se_q, calib):
    """(r, sigma_r, the three components) of r = m / q - 1 (module docstring)."""
    q = np.maximum(q, 1e-30)
    r = m / q - 1.0
    a, b = se_m / q, se_q / q
    sig = np.sqrt(a * a + (1.0 + r) ** 2 * (b * b + calib * calib))
    return r, sig, a, b


def region_difference(D, M, sel, *, model_hd, ref_var, ref_hd, ref_region: dict | None,
                      calib: np.ndarray) -> dict:
    """One region's record: model and reference means, their relative difference per channel
    and in luminance, each with its standard error from both images' noise and the
    reference's calibration, and whether the difference is resolved (> RESOLVE_K sigma).

    ``ref_region``: the reference's own record of the region (``info["regions"][name]`` with
    ``info["region_rel_se"][name]`` as ``rel_se``); without a half-difference its standard
    errors are taken from it, scaled by sqrt(pixels / n) when only n of its pixels are
    compared."""
    n = int(sel.sum())
    mref, mmod = M[sel].mean(axis=0), D[sel].mean(axis=0)
    lr, lm = float(mref @ LUMINANCE), float(mmod @ LUMINANCE)
    se_m, se_ml = mean_se(sel, hd=model_hd) if model_hd is not None else (np.zeros(3), 0.0)
    if ref_hd is not None or not ref_region or "stderr_rgb" not in ref_region:
        se_q, se_ql = mean_se(sel, var=ref_var, hd=ref_hd)
    else:
        k = math.sqrt(max(int(ref_region.get("pixels", n)), 1) / n)
        se_q = np.asarray(ref_region["stderr_rgb"], np.float64) * k
        if ref_region.get("rel_se") is not None:
            se_ql = float(ref_region["rel_se"]) * lr * k
        else:
            se_ql = math.sqrt(float((se_q * se_q) @ _LUM2))
    r, sig, a, b = _rel(mmod, mref, se_m, se_q, calib)
    cl = float(calib @ LUMINANCE)
    rl, sl, al, bl = _rel(lm, lr, se_ml, se_ql, cl)
    rl, sl = float(rl), float(sl)
    return {"pixels": n, "ref_rgb": [float(v) for v in mref], "model_rgb": [float(v) for v in mmod],
            "rel_rgb": [float(v) for v in r], "sigma_rgb": [float(v) for v in sig],
            "rel_lum": rl, "sigma_lum": sl,
            "model_se_lum": float(al) if model_hd is not None else None,
            "ref_se_lum": float(bl), "calibration_lum": cl,
            "resolved": bool(lr > 0 and abs(rl) > RESOLVE_K * sl)}


def pair_test(Da, va, Db, vb, M, vM) -> tuple[float, float, int]:
    """(s_a - s_b, its standard error, elements) on the elements both cover, s = e^2 -
    sigma_model^2 (module docstring).  D, M: (K, 3) block means; v: their variances."""
    den = float((M * M).sum())
    if den <= 0 or not len(M):
        return 0.0, 0.0, 0
    ua, ub = Da - M, Db - M
    sa = float((ua * ua).sum() - va.sum()) / den
    sb = float((ub * ub).sum() - vb.sum()) / den
    var = (4 * ((Da - Db) ** 2 * vM + ua * ua * va + ub * ub * vb + (va + vb) * vM).sum()
           + 2 * (va * va + vb * vb).sum()) / den ** 2
    return sa - sb, math.sqrt(max(float(var), 0.0)), int(M.size)


def compare(d: float, se: float) -> str:
    """"closer" / "farther" / "tied" of a score difference d = s_a - s_b with error se."""
    if d < -RESOLVE_K * se:
        return "closer"
    if d > RESOLVE_K * se:
        return "farther"
    return "tied"


def rank_ranges(order: list, pairs: dict) -> dict:
    """model -> (best, worst) rank (1 = closest) consistent with the pair comparisons:
    best = 1 + models resolved closer, worst = N - models resolved farther."""
    n = len(order)
    out = {}
    for a in order:
        closer = sum(1 for b in order if b != a and pairs[(a, b)] == "farther")
        farther = sum(1 for b in order if b != a and pairs[(a, b)] == "closer")
        out[a] = (1 + closer, n - farther)
    return out


def combine_verdicts(per: list[str]) -> str:
    """A claim made for every light: fails where it fails under one, holds where it holds
    under all, else not resolved."""
    if not per:
        return UNRESOLVED
    if FAILS in per:
        return FAILS
    return HOLDS if all(v == HOLDS for v in per) else UNRESOLVED
