"""Layers combined in frequency space: the convolution of layer profiles (Donner & Jensen 2005).

A stack's R(r), T(r) are convolutions of its layers' radial profiles, so the adding
equations of plane-parallel layers hold per spatial frequency.  Layers are folded top-down
(stack A above layer B): light that A passes on collimated enters B as collimated light,
diffuse light as diffuse light; U = (tau_A R_Bc + R_Bd T_Ac) / (1 - R_Bd R'_Ad) goes up
into A, R = R_Ac + T'_Ad U, and so on (:func:`combine_layers`).  The profiles are radially
symmetric, so their 2-D grid is even in x and y; the 2-D DFT of an even periodic grid is a
2-D DCT-I of one quadrant (``scipy.fft.dctn(type=1)``), padded x2 against wrap-around.
Pixels hold ring averages from each source's closed-form cumulative energy
(:mod:`dermis.optics.multipole`), and each spectrum's DC term is set to its total exactly.
The grid is the layer file's (:func:`dermis.optics.layer_file.auto_grid`).
"""
from __future__ import annotations

import math

import numpy as np
import scipy.fft

from dermis.optics.forward_spread import RadialShape
from dermis.optics.layer_file import NegativeLobes
from dermis.optics.layers import LayerStack
from dermis.optics.multipole import (direct_parts, evaluate_terms, layer_response,
                                     lit_from_below, scaled_to_exact)

__all__ = ["combine_layers"]


def _ring_grid(terms, lo: np.ndarray, hi: np.ndarray, h: float) -> np.ndarray:
    """Ring-average density of ``terms`` between radii ``lo`` and ``hi`` (pixel grids).

    The cumulative energy is evaluated in closed form on a 1-D grid (h/32 up to 4 h, h/2
    beyond: E varies on the scale of a mean free path >= 4 h) and interpolated with a cubic
    spline, which keeps the cost at O(pixels) instead of O(pixels x images x sources)
    exponentials.
    """
    from scipy.interpolate import CubicSpline   # ~0.3 s to import: layered stacks only
    top = float(hi.max())
    fine = np.arange(0.0, min(4.0 * h, top), h / 32.0)
    coarse = np.arange(fine[-1] + h / 2.0 if fine.size else 0.0, top + h / 2.0, h / 2.0)
    rf = np.concatenate([fine, coarse])
    e = evaluate_terms(terms, "energy", rf)
    spline = CubicSpline(rf, e)
    return (spline(hi) - spline(lo)) / (np.pi * (hi**2 - lo**2))


def combine_layers(stack: LayerStack, chans, nq: int, h: float, n: int, lobes: NegativeLobes,
                   exact=None, exact_stack=None, scales=None):
    """Adding in frequency space on the even quadrant; returns tables and totals."""
    m = 2 * n  # quadrant 0..2n: data in 0..n, zeros beyond (x2 padding)
    ax = np.arange(m + 1) * h
    rho = np.hypot(ax[:, None], ax[None, :])
    inside = rho <= (n + 0.5) * h
    rq = rho[:n + 1, :n + 1]
    # ring index per quadrant pixel, with multiplicity (axis pixels stand for 2, others 4)
    mult = np.full((m + 1, m + 1), 4.0)
    mult[0, :] = 2.0
    mult[:, 0] = 2.0
    mult[0, 0] = 1.0
    sel = inside[:n + 1, :n + 1]
    cell = (mult[:n + 1, :n + 1] * h * h)[sel]
    radius = rq[sel]
    # pixel radii are h sqrt(i^2 + j^2): evaluate each distinct one once
    ij = (np.arange(n + 1)[:, None] ** 2 + np.arange(n + 1)[None, :] ** 2)[sel]
    uniq, back = np.unique(ij, return_inverse=True)
    ur = h * np.sqrt(uniq.astype(np.float64))
    ulo = np.maximum(ur - 0.5 * h, 0.0)
    uhi = np.where(ur == 0, h / math.sqrt(math.pi), ur + 0.5 * h)  # centre: disk of area h^2
    nl = len(stack.layers)
    zero = None

    def pixels(terms, total: float, where: dict) -> np.ndarray | None:
        """Pixel energies of ``terms`` on the quadrant (None without any), their sum set to
        the closed-form ``total`` so the spectrum's DC term is exact."""
        if not terms or total == 0:
            return None
        g = np.zeros((m + 1, m + 1))
        if len(terms) == 1 and isinstance(terms[0], RadialShape):
            # spread direct light: its cumulative energy is cheap and monotone, so it is
            # evaluated at the pixel radii themselves (no spline, no overshoot)
            vals = ((terms[0].energy(uhi) - terms[0].energy(ulo))
                    / (np.pi * (uhi**2 - ulo**2)))[back]
        else:
            vals = _ring_grid(terms, ulo, uhi, h)[back]
        v = lobes.fix(vals, cell, radius, where, total=total)
        g[:n + 1, :n + 1][sel] = v * h * h
        s = _quadrant_sum(g)
        if s > 0 and total != 0:
            g *= total / s
        return g

    def spectrum(terms, total: float, where: dict, spread=None) -> np.ndarray:
        """DCT-I of ``terms`` (energy ``total``) plus the spread direct light ``spread``
        (a weighted RadialShape or None): one transform of the summed pixels."""
        nonlocal zero
        grids = [pixels(terms, total, where)]
        if spread is not None:
            grids.append(pixels([spread], spread.weight, dict(where, field=where["field"]
                                                              + " direct")))
        grids = [x for x in grids if x is not None]
        if not grids:
            if zero is None:
                zero = np.zeros((m + 1, m + 1))
            return zero
        for extra in grids[1:]:
            grids[0] += extra                     # in place: one grid, not three
        return scipy.fft.dctn(grids[0], type=1, workers=-1)

    def diffuse_fields(resp, exact_R, exact_T, light: str, w: dict, c: int):
        """(R, T) spectra of one layer lit by diffuse light (from above or from below):
        scaled to the exact totals, the direct part spread, dropped energy and scales noted."""
        Rf, Rdl, Tf, Tdl, sc = scaled_to_exact(resp, exact_R, exact_T, True)
        Rp, Rs, Tp, Ts = direct_parts(resp, Rdl, Tdl, True)
        lit = dict(w, light=light)
        R = spectrum(resp.terms_R, Rf, dict(lit, field="R"), Rs) + Rp
        T = spectrum(resp.terms_T, Tf, dict(lit, field="T"), Ts) + Tp
        dropped[c] += resp.dropped
        if scales is not None:
            scales.append(dict(w, light=light, **sc))
        return R, T

    R_out = np.zeros((n + 1, 3))
    T_out = np.zeros((n + 1, 3))
    Rd, Tt = np.zeros(3), np.zeros(3)
    bal, fwd, dropped = np.zeros(3), np.zeros(3), np.zeros(3)
    radial = _RadialAverager(rho, mult, h, n)
    ring_area = np.pi * np.diff(np.concatenate([[0.0], (np.arange(n + 1) + 0.5) * h]) ** 2)
    r_k = np.arange(n + 1) * h
    for c in range(3):
        # Per layer: collimated light from above (Rc, Tc diffuse; tau collimated through),
        # diffuse light from above (Rd, Td; not needed for the top layer) and from below
        # (Rud, Tud; not needed for the bottom layer).  Light that a layer passes on
        # diffusely enters its neighbour as diffuse light, the collimated part as collimated.
        A = None
        R_delta = 0.0
        bal_c = 1.0
        for k in range(nl):
            ch = chans[k][c]
            ex = exact[k][c] if exact is not None else None
            w = {"layer": k, "channel": "RGB"[c]}
            dc = layer_response(ch, nq)
            Rf, Rdl, Tf, Tdl, sc = scaled_to_exact(dc, ex and ex.Rc, ex and ex.Tc, False,
                                                   ex and ex.Tu)
            # direct light: the unscattered beam stays at r = 0 (a constant spectrum), the
            # rest lands where optics/forward_spread.py puts it
            Rp, Rs, Tp, Ts = direct_parts(dc, Rdl, Tdl, False, ex and ex.Tu)
            lit = dict(w, light="collimated")
            B = {"Rc": spectrum(dc.terms_R, Rf, dict(lit, field="R"), Rs),
                 "Tc": spectrum(dc.terms_T, Tf, dict(lit, field="T")),
                 "tau": Tp + spectrum([], 0.0, dict(lit, field="T"), Ts) if Ts is not None else Tp,
                 "bal": Tp}
            if scales is not None:
                scales.append(dict(w, light="collimated", **sc))
            dropped[c] += dc.dropped
            bal_c *= dc.ballistic if ex is None else ex.Tu
            if k == 0:
                R_delta = Rp
            else:
                # not in place: spectrum() hands out one shared zero grid for layers without
                # a diffusion shape (sigma_s' = 0), and += on it leaked this delta into every
                # later layer and channel (Rd + Tt up to 1.33, test_stability test11)
                B["Rc"] = B["Rc"] + Rp
                B["Rd"], B["Td"] = diffuse_fields(layer_response(ch, nq, diffuse=True),
                                                  ex and ex.Rd, ex and ex.Td, "diffuse", w, c)
            if k + 1 < nl:
                B["Rud"], B["Tud"] = diffuse_fields(
                    layer_response(lit_from_below(ch), nq, diffuse=True), ex and ex.Rud,
                    ex and ex.Tud, "diffuse from below", w, c)
            if A is None:
                A = B
                continue
            den = 1.0 / (1.0 - B["Rd"] * A["Rud"])
            U = (A["tau"] * B["Rc"] + B["Rd"] * A["Tc"]) * den     # diffuse up into A
            down = A["Tc"] + A["Rud"] * U                            # diffuse down into B
            new = {"Rc": A["Rc"] + A["Tud"] * U,
                   "Tc": A["tau"] * B["Tc"] + B["Td"] * down,
                   "tau": _product(A["tau"], B["tau"]), "bal": A["bal"] * B["bal"]}
            if k + 1 < nl:
                Uu = B["Tud"] * den
                new["Rud"] = B["Rud"] + B["Td"] * A["Rud"] * Uu
                new["Tud"] = A["Tud"] * Uu
            A = new
        es = exact_stack[c] if exact_stack is not None else None
        if es is not None:
            # the adding above treats light passed between layers as Lambertian; the exact
            # plane-parallel solution of the whole stack sets the final totals
            r_tot = float(A["Rc"][0, 0]) + R_delta
            if r_tot > 0:
                A["Rc"] = A["Rc"] * (es.Rc / r_tot)
                R_delta *= es.Rc / r_tot
            t_sc = float(A["Tc"][0, 0]) + _dc(A["tau"]) - bal_c
            if t_sc > 0:
                # the scattered part of the collimated light (spread or not) scales with
                # the diffuse T; the unscattered beam becomes the whole stack's
                A["Tc"] = A["Tc"] * (es.Tc / t_sc)
                A["tau"] = es.Tu + (A["tau"] - bal_c) * (es.Tc / t_sc)
                A["bal"] = es.Tu + (A["bal"] - bal_c) * (es.Tc / t_sc)
            bal_c = es.Tu
            if scales is not None:
                scales.append({"layer": "stack", "channel": "RGB"[c], "light": "collimated",
                               "R": es.Rc / r_tot if r_tot > 0 else 1.0,
                               "T": es.Tc / t_sc if t_sc > 0 else 1.0})
        tau = _dc(A["tau"])
        Rd[c] = A["Rc"][0, 0] + R_delta
        Tt[c] = A["Tc"][0, 0] + tau
        bal[c] = bal_c
        fwd[c] = max(tau - bal_c, 0.0)
        # the collimated light that was spread (scattered forward) joins the T field; the
        # unscattered beam (A["bal"]) stays a delta at r = 0
        T_spec = A["Tc"] + (A["tau"] - A["bal"]) if isinstance(A["tau"], np.ndarray) \
            else A["Tc"]
        T_point = A["bal"] if isinstance(A["tau"], np.ndarray) else tau
        for key, spec, out in (("R", A["Rc"], R_out), ("T", T_spec, T_out)):
            if not np.any(spec):
                continue
            e = scipy.fft.idctn(spec, type=1, workers=-1)  # energy per pixel
            vals = radial(e / (h * h))
            # the fitted radial table is not energy-exact (the local linear fit reads up to
            # ~1 % high near the source): it holds the grid's energy inside its radius
            energy = float(np.sum((e * mult)[inside]))
            out[:, c] = lobes.fix(vals, ring_area, r_k,
                                  {"layer": "stack", "field": key, "channel": "RGB"[c],
                                   "light": "inverse transform"}, total=energy)
        R_out[0, c] += R_delta / ring_area[0]
        T_out[0, c] += T_point / ring_area[0]
    return R_out, T_out, Rd, Tt, bal, fwd, dropped


def _product(a, b):
    """a * b for spectra or numbers; a zero number stays a number (a semi-infinite layer
    passes nothing on: no grid of zeros)."""
    if (not isinstance(a, np.ndarray) and a == 0) or (not isinstance(b, np.ndarray) and b == 0):
        return 0.0
    return a * b


def _dc(spec) -> float:
    """Total energy of a spectrum (its DC term) or of a delta (a number)."""
    return float(spec[0, 0]) if isinstance(spec, np.ndarray) else float(spec)


class _RadialAverager:
    """Quadrant grid -> values at r_k = k h by a hat-weighted local linear fit in radius.

    Plain ring binning of pixels is biased at small k: the lattice puts the pixel radii of a
    ring unevenly (ring 5 holds radii 0.50..0.54 h-units only), which read 3-4 % low on
    skin profiles.  Fitting value = a + b (rho - r_k) with hat weights over (r_k - h,
    r_k + h) removes the first-order bias; where the fit is degenerate (k = 0) the weighted
    mean is used.
    """

    def __init__(self, rho: np.ndarray, mult: np.ndarray, h: float, n: int):
        x = rho / h
        k0 = np.floor(x).astype(np.int64)
        t = x - k0
        self.n = n
        self.parts = []
        for k, w in ((k0, 1.0 - t), (k0 + 1, t)):
            sel = (k <= n) & (w > 0)
            self.parts.append((k[sel], (w * mult)[sel], (x - k)[sel], sel))
        s = [np.zeros(n + 1) for _ in range(3)]
        for k, w, dx, _ in self.parts:
            for p in range(3):
                s[p] += np.bincount(k, weights=w * dx**p, minlength=n + 1)
        self.s0, self.s1, self.s2 = s
        self.det = self.s0 * self.s2 - self.s1**2

    def __call__(self, grid: np.ndarray) -> np.ndarray:
        sv = np.zeros(self.n + 1)
        sxv = np.zeros(self.n + 1)
        for k, w, dx, sel in self.parts:
            v = grid[sel]
            sv += np.bincount(k, weights=w * v, minlength=self.n + 1)
            sxv += np.bincount(k, weights=w * dx * v, minlength=self.n + 1)
        mean = sv / np.maximum(self.s0, 1e-300)
        ok = self.det > 1e-9 * np.maximum(self.s0 * self.s2, 1e-300)
        lin = (self.s2 * sv - self.s1 * sxv) / np.where(ok, self.det, 1.0)
        return np.where(ok, lin, mean)


def _quadrant_sum(g: np.ndarray) -> float:
    """Sum of the full even grid represented by quadrant ``g`` (axes counted once)."""
    return float(4.0 * g[1:, 1:].sum() + 2.0 * g[0, 1:].sum() + 2.0 * g[1:, 0].sum() + g[0, 0])
