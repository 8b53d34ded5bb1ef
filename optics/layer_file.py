"""The layer file's table: grid, rings, units, cut-off radius and negative lobes.

Both profile models (:mod:`dermis.optics.layer_profiles`) hand their radial tables to
:func:`finish_table`, which adds the cut-off radius and the energy bookkeeping of the
:class:`~dermis.pipeline.artifacts.LayerProfile`; :class:`NegativeLobes` removes and records
the negative values of diffusion sums; :func:`auto_grid` sizes the multipole table (and the
FFT grid of :mod:`dermis.optics.layer_convolution`) from the stack's length scales.

Negative values.  Diffusion sums can go negative (thin layers far from the source, FFT
ringing).  They are never clipped silently: every negative lobe beyond float64 round-off
is recorded in ``info["negative_lobes"]`` (layer, light, field, channel, radii, energy
fraction), set to zero, and the rest of that profile rescaled so its energy is kept.

Output table.  r_k = k h, values are averages over rings [r_k - h/2, r_k + h/2) (a disk for
k = 0), in 1/mm^2, so sum_k R_k * ring_area_k = the energy inside the table (exactly: the
radial fit is rescaled to the grid's energy inside its radius).  ``Rd``/``Tt`` are per
photon that entered the top surface (the specular reflection at entry excluded; MCML's
per-incident-photon values are these times 1 - R_sp) and include energy beyond the table;
``Tt`` includes the collimated transmission.  The cut-off radius is the smallest r_k whose
rings hold ``CUTOFF_FRACTION`` = 99.9 % of Rd.
"""
from __future__ import annotations

import math

import numpy as np

from dermis.pipeline.artifacts import LayerProfile
from dermis.optics.layers import LayerStack

__all__ = ["RD_CONVENTION", "CUTOFF_FRACTION", "NEGATIVE_ROUNDOFF", "NegativeLobes",
           "finish_table", "auto_grid", "GRID_FINE", "GRID_DECAY", "GRID_MAX_MFP",
           "GRID_MAX_POINTS"]

RD_CONVENTION = ("per photon that entered the top surface: the specular reflection at entry "
                 "is not counted (multiply by 1 - R_sp for per incident photon)")

# Fraction of Rd inside the reported cut-off radius.
CUTOFF_FRACTION = 0.999
# A negative value counts as a lobe (and is reported) when its energy exceeds this fraction
# of the profile's energy; below it is float64 round-off of cancelling images.
NEGATIVE_ROUNDOFF = 1e-9

# Auto grid: spacing = min reduced mean free path / GRID_FINE (convergence test: R changes
# by < 0.5 % at r >= 2 mfp from 4 to 8 points per mfp), half-width = GRID_DECAY / sigma_tr_min
# (e^{-14} ~ 1e-6 of the dipole tail is beyond it), capped by GRID_MAX_MFP mean free paths
# (sigma_a = 0 has a power-law tail) and GRID_MAX_POINTS points per half-width.
GRID_FINE = 4.0
GRID_DECAY = 14.0
GRID_MAX_MFP = 300.0
GRID_MAX_POINTS = 1024


def auto_grid(stack: LayerStack) -> tuple[float, float]:
    """(spacing h, half-width r_max) in mm from the stack's length scales (see constants)."""
    mfp_min = min(1.0 / (a + s) for l in stack.layers for a, s in zip(l.sigma_a, l.sigma_s_prime))
    mfp_max = max(1.0 / (a + s) for l in stack.layers for a, s in zip(l.sigma_a, l.sigma_s_prime))
    str_min = min(math.sqrt(3 * a * (a + s)) for l in stack.layers
                  for a, s in zip(l.sigma_a, l.sigma_s_prime))
    thin = min((l.thickness_mm for l in stack.layers), default=math.inf)
    h = min(mfp_min, thin) / GRID_FINE
    r_max = GRID_MAX_MFP * mfp_max
    if str_min > 0:
        r_max = min(r_max, GRID_DECAY / str_min)
    r_max = max(r_max, 20.0 * h)
    h = max(h, r_max / GRID_MAX_POINTS)
    return h, r_max


class NegativeLobes:
    """Collects negative lobes: where a diffusion sum (or the inverse transform) went below
    zero beyond round-off, and how much energy that was."""

    def __init__(self):
        self.items: list[dict] = []
        self.min_rel = 0.0

    def fix(self, vals: np.ndarray, area: np.ndarray, radius: np.ndarray, where: dict,
            total: float | None = None) -> np.ndarray:
        """Zero the negative values of ``vals`` (densities on cells of ``area`` at ``radius``)
        and rescale the rest to ``total`` (default: the signed energy before), recording
        the lobe if it exceeds round-off."""
        peak = float(np.abs(vals).max()) if vals.size else 0.0
        if peak <= 0.0:
            return vals
        neg = vals < 0
        self.min_rel = min(self.min_rel, float(vals.min() / peak))
        # energies of vals / peak: a profile of a layer that passes ~1e-300 of the light has
        # products vals * area below the float64 range, and its lobe's energy fraction read 0
        # (a 660 mm layer's transmittance, tests/test_stability.py test11)
        unit = vals / peak
        if not neg.any():
            if total is None:
                return vals
            e_all = float(np.sum(unit * area))
            return unit * (total / e_all) if e_all > 0 and total > 0 else vals
        e_all = float(np.sum(unit * area))
        e_neg = float(-np.sum(unit[neg] * area[neg]))
        e_pos = e_all + e_neg
        keep = e_all * peak if total is None else total
        out = np.where(neg, 0.0, unit)
        out = out * (keep / e_pos) if e_pos > 0 and keep > 0 else out * peak
        frac = e_neg / e_pos if e_pos > 0 else 1.0
        if frac > NEGATIVE_ROUNDOFF:
            rn = radius[neg]
            self.items.append(dict(where, r_mm=[float(rn.min()), float(rn.max())],
                                   energy_fraction=frac, min_rel=float(vals.min() / peak)))
        return out


def finish_table(r_out, R, T, Rd, Tt, ring_area, info, cut_radii=None) -> LayerProfile:
    """Cut-off radius and energy bookkeeping shared by both models (``cut_radii``: the
    radius reported for ring k, default ``r_out``)."""
    cut_radii = r_out if cut_radii is None else cut_radii
    cum = np.cumsum(R * ring_area[:, None], axis=0)
    cutoff = np.zeros(3)
    beyond = np.zeros(3)
    n = len(r_out) - 1
    for c in range(3):
        if Rd[c] <= 0:
            continue
        k = int(np.searchsorted(cum[:, c], CUTOFF_FRACTION * Rd[c]))
        k = min(k, n)
        cutoff[c] = cut_radii[k]
        beyond[c] = max(0.0, 1.0 - cum[k, c] / Rd[c])
    info["energy_beyond_table"] = [max(0.0, 1.0 - cum[-1, c] / Rd[c]) if Rd[c] > 0 else 0.0
                                   for c in range(3)]
    return LayerProfile(r_mm=r_out, R=R, T=T, Rd=np.asarray(Rd, float),
                        Tt=np.asarray(Tt, float), cutoff_mm=cutoff,
                        energy_beyond_cutoff=beyond, info=info)
