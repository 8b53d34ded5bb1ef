"""The Monte Carlo layer file: R(r), T(r) of a stack tabulated from the OpenCL layered tracer.

:func:`monte_carlo_profiles` runs :mod:`dermis.optics.monte_carlo_slab` (cl/mc_slab.cl) for
the stack itself on rings from :func:`mc_bin_edges` (fine near the source, geometric beyond),
with radial splitting in a weight window that follows a coarse diffusion layer file of the
same stack (the "guide"), photons shared among the channels by a pilot run so that all three
reach the same noise, and per-ring standard errors from independent batches.  The table has
the fields and units of the multipole one (:mod:`dermis.optics.layer_file`);
docs/profiles.md has the measurements.
"""
from __future__ import annotations

import math
import time
from functools import lru_cache

import numpy as np

from dermis.pipeline.artifacts import LayerProfile
from dermis.pipeline.errors import DermisError
from dermis.optics.layer_file import RD_CONVENTION, auto_grid, finish_table
from dermis.optics.layers import LayerStack, DEFAULT_MC_PHOTONS, DEFAULT_MC_SEED
from dermis.optics.monte_carlo_slab import WeightWindow, combine, simulate

__all__ = ["monte_carlo_profiles", "mc_bin_edges", "MC_SPLIT", "MC_BATCHES", "MC_W_MIN",
           "NOISE_BAND_MM"]

# Rings of the Monte Carlo table: width MC_FINE x the smallest mean free path 1/sigma_t' near
# the source (the gather resamples the table finer still, and its blur is >= 0.1 mm), growing
# geometrically by MC_GROWTH per ring beyond, so every ring holds a comparable share of
# r^2 R(r) (equal noise per ring) out to MC_REACH x the diffusion cut-off (>= MC_MIN_RMAX).
MC_FINE = 0.25
MC_GROWTH = 0.06
MC_REACH = 1.2
MC_MIN_RMAX = 5.5
# Radial splitting (cl/mc_slab.cl): the weight window follows the diffusion estimate of the
# energy per ring, fitted as exp(-kappa (r - r_peak)) beyond its peak, kappa x MC_KAPPA_BOOST
# capped at MC_KAPPA_CAP sigma_tr of the least absorbing layer, times exp(MC_DEPTH sigma_tr z)
# (deep photons matter less); Russian roulette below MC_W_MIN of the window.  Tuned on
# two_layer by the figure of merit 1 / (max relative ring noise^2 x kernel time) over
# [0.05, 5] mm (analog tracer: infinite, the blue tail is empty): roulette at 0.25 instead of
# MCML's 1e-4 x 3.5, depth term x 2.2, boost/cap 1.1/1.25 x 1.5 (1.2/1.4 multiplied the
# copies: x 6.5 in time).  With the photons allocated per channel (MC_PILOT below) each
# channel may converge at its own rate, and boost/cap 1.0/1.0 - the window never falls
# faster than the light - took 0.26-0.30 G loop trips to 1 % against 0.33 for 1.1/1.25 with
# equal shares (trips: the machine-independent cost; bench/results/profiles_table.json).
MC_SPLIT = True
# Points of the diffusion guide over its reach (it sets only the rings' reach and the
# window's slope and start): 128 builds in 0.23 s against 2.1 s for 512 on two_layer, with
# the same 67 rings, kappa within 0.3 % and the window start within one ring.
MC_GUIDE_POINTS = 128
# Independent batches behind the per-ring standard errors: 128, the error of an error
# 1 / sqrt(2 x 127) = 6 % (32 batches: 13 %, and the largest of ~60 such estimates, the
# noise the table reports, then read ~25 % above the true largest error).  Batches only
# group the work-items (cl/mc_slab.cl), so they cost nothing.
MC_BATCHES = 128
MC_KAPPA_BOOST = 1.0
MC_KAPPA_CAP = 1.0
MC_W_MIN = 0.25
MC_DEPTH = 0.5


# Photon allocation among the channels: a pilot of MC_PILOT x photons per channel (seed
# _pilot_seed(seed)) measures each channel's largest relative ring noise over NOISE_BAND_MM;
# the rest of the 3 x photons goes to the channels in proportion to noise^2 x photons, so
# all three end with about the same noise (the pilot's photons are kept: monte_carlo_slab.combine).
# Without it every channel gets the same photons and the slowest-converging channel sets the
# count: on two_layer the blue far tail needs 3x the red's photons (bench/results/
# profiles_table.json, "runs" photons_per_channel).  Below MC_PILOT_MIN pilot photons: equal shares.
MC_PILOT = 0.1
MC_PILOT_MIN = 2000
NOISE_BAND_MM = (0.05, 5.0)


def _pilot_seed(seed: int) -> int:
    """The pilot run's seed: another Philox key, so its photons are independent of the
    main run's."""
    return (int(seed) ^ 0x9E3779B9) & 0xFFFFFFFF


def _band_noise(mc, band: np.ndarray) -> np.ndarray:
    """(3,) the largest relative R error per channel over the rings in ``band`` (inf where a
    ring there is empty, 0 without rings in the band)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(mc.R > 0, mc.R_err / mc.R, np.inf)
    return rel[band].max(axis=0) if band.any() else np.zeros(3)


@lru_cache(maxsize=8)
def _diffusion_guide(stack: LayerStack) -> LayerProfile:
    """The diffusion layer file (its own totals) that sizes the Monte Carlo table's rings
    and weight window; cached per stack (it takes seconds for a layered stack)."""
    h, r_max = auto_grid(stack)
    h = max(2.0 * h, r_max / MC_GUIDE_POINTS)       # coarse: only its shape and reach are used
    # function-local: build_profiles dispatches to this module (import cycle)
    from dermis.optics.layer_profiles import MultipoleOptions, build_profiles
    return build_profiles(stack, options=MultipoleOptions(totals="diffusion", grid=(h, r_max)))


def mc_bin_edges(stack: LayerStack, r_max_mm: float | None = None) -> np.ndarray:
    """Ring edges (mm) of the Monte Carlo table of ``stack``: uniform near the source, then
    geometric (module constants), out to ``r_max_mm`` (default: MC_REACH x the diffusion
    cut-off of the stack, at least MC_MIN_RMAX)."""
    st = stack.nonzero()
    mfp_min = min(1.0 / (a + s) for l in st.layers for a, s in zip(l.sigma_a, l.sigma_s_prime))
    if r_max_mm is None:
        prof = _diffusion_guide(st)
        r_max_mm = max(MC_MIN_RMAX, MC_REACH * float(prof.cutoff_mm.max()))
    d0 = MC_FINE * mfp_min
    r1 = d0 / MC_GROWTH
    e = list(np.arange(0.0, r1 + 0.5 * d0, d0))
    while e[-1] < r_max_mm:
        e.append(e[-1] * (1.0 + MC_GROWTH))
    e[-1] = max(e[-1], r_max_mm)
    return np.asarray(e)


def _mc_window(stack: LayerStack, prof: LayerProfile, edges: np.ndarray,
               reach_mm: float | None = None) -> np.ndarray:
    """(3, 4) weight-window parameters (kappa, rho0, rho1, lambda) per channel from a diffusion
    profile: its energy per unit log-radius r^2 R(r) fitted by exp(-kappa (r - rho0)) beyond
    its peak rho0, kappa (x MC_KAPPA_BOOST) capped at MC_KAPPA_CAP sigma_tr of the least
    absorbing layer (light reaching rho decays no faster than that; a faster window would
    multiply copies without bound), no splitting beyond rho1 = the last ring (or ``reach_mm``
    if nearer)."""
    win = np.zeros((3, 4))
    mid = 0.5 * (edges[1:] + edges[:-1])
    for c in range(3):
        Rr = np.interp(mid, prof.r_mm, prof.R[:, c], right=0.0)
        e = Rr * mid**2               # energy per unit log-radius: the geometric rings
        if not np.any(e > 0):
            continue
        k0 = int(np.argmax(e))
        sel = (np.arange(len(e)) >= k0) & (e > e[k0] * 1e-12)
        if sel.sum() < 3:
            continue
        slope = np.polyfit(mid[sel], np.log(e[sel]), 1)[0]
        s_min = min(math.sqrt(3.0 * l.sigma_a[c] * (l.sigma_a[c] + l.sigma_s_prime[c]))
                    for l in stack.layers)
        reach = edges[-1] if reach_mm is None else min(edges[-1], reach_mm)
        win[c] = (min(MC_KAPPA_BOOST * max(-slope, 0.0), MC_KAPPA_CAP * s_min), mid[k0],
                  reach, MC_DEPTH * s_min)
    return win


def monte_carlo_profiles(stack: LayerStack, *, photons: int = DEFAULT_MC_PHOTONS,
                         seed: int = DEFAULT_MC_SEED, env=None, progress=None,
                         edges: np.ndarray | None = None, split: bool = MC_SPLIT,
                         batches: int = MC_BATCHES) -> LayerProfile:
    """The layer file of ``stack`` from the OpenCL layered Monte Carlo.

    Parameters
    ----------
    stack : LayerStack
        The scene's layers (the same stack the multipole model would use).
    photons : int
        Photons launched per colour channel on average: 3 x photons in all, shared among the
        channels by a pilot run so that they reach the same noise (with ``split``; module
        notes at MC_PILOT), else the same in each.
    seed : int
        Random seed (0 .. 2**32 - 1): the same seed gives the same table on the same device.
    env : pipeline.cl.ClEnv, optional
        OpenCL environment (default PoCL CPU).
    edges : (B+1,) array_like, optional
        Ring edges, mm (default :func:`mc_bin_edges`).
    split : bool
        Radial splitting with a weight window from the diffusion profile (variance
        reduction far from the source; unbiased), out to MC_REACH x the diffusion cut-off
        (>= MC_MIN_RMAX) even when ``edges`` reach further.
    batches : int
        Independent batches for the standard errors.

    Returns
    -------
    LayerProfile
        The same fields and units as the multipole model: ``r_mm`` (B,) ring mid-radii
        (0 for the central disk), ``R``, ``T`` (B, 3) ring averages in 1/mm^2 per entered
        photon, ``Rd``, ``Tt`` the Monte Carlo totals (escapes beyond the table included),
        ``cutoff_mm`` the outer edge of the ring where 99.9 % of Rd is reached,
        ``energy_beyond_cutoff``.  ``info`` adds ``r_edges``, the per-ring standard errors
        ``R_err``, ``T_err`` (1/mm^2, from the batch spread), ``Rd_err``, ``Tt_err``,
        ``absorbed``, photons, seed, seconds, photons_per_second, device, the weight
        window and ``noise_max_rel`` (largest relative R error per channel over
        [0.05, 5] mm).
    """
    t0 = time.perf_counter()
    st = stack.nonzero()
    if not st.layers:
        raise DermisError("profiles: every layer has thickness 0; nothing to profile")
    diff = _diffusion_guide(st) if (edges is None or split) else None
    reach = max(MC_MIN_RMAX, MC_REACH * float(diff.cutoff_mm.max())) if diff is not None else None
    if edges is None:
        edges = mc_bin_edges(st, reach)
    edges = np.asarray(edges, np.float64)
    window = _mc_window(st, diff, edges, reach) if split else None
    mid = 0.5 * (edges[1:] + edges[:-1])
    band = (mid >= NOISE_BAND_MM[0]) & (mid <= NOISE_BAND_MM[1])
    run = dict(edges=edges, batches=batches, env=env,
               weight_window=WeightWindow(window, MC_W_MIN))
    budget = 3 * int(photons)
    pilot_n = int(MC_PILOT * photons)
    if split and pilot_n >= MC_PILOT_MIN:
        # a pilot run measures each channel's noise per photon; the rest of the budget goes
        # where it equalises the channels' final noise
        # (docs/profiles.md "Photons shared among the channels")
        pilot = simulate(st, photons=pilot_n, seed=_pilot_seed(seed), **run)
        n_pilot = np.asarray(pilot.info["photons_per_channel"], np.float64)
        per_photon = n_pilot * np.square(_band_noise(pilot, band))   # noise^2 x photons
        if np.all(np.isfinite(per_photon)) and np.all(per_photon > 0):
            want = budget * per_photon / per_photon.sum() - n_pilot
        else:
            want = np.full(3, budget / 3.0) - n_pilot
        rest = np.maximum(want, MC_PILOT_MIN).round().astype(np.int64)
        mc = combine(pilot, simulate(st, photons=rest, seed=int(seed), **run))
    else:
        mc = simulate(st, photons=int(photons), seed=int(seed), **run)
    ring_area = np.pi * np.diff(edges**2)
    r_mm = 0.5 * (edges[1:] + edges[:-1])
    r_mm[0] = 0.0
    noise = _band_noise(mc, band).tolist()
    info = {"model": "monte_carlo", "layers": stack.to_dict(), "convention": RD_CONVENTION,
            "r_edges": edges.tolist(), "R_err": mc.R_err.tolist(), "T_err": mc.T_err.tolist(),
            "Rd_err": mc.Rd_err.tolist(), "Tt_err": mc.Tt_err.tolist(),
            "absorbed": mc.absorbed.tolist(), "lost": mc.lost.tolist(),
            "photons": int(mc.photons),
            "photons_per_channel": mc.info["photons_per_channel"], "seed": int(seed),
            "runs": mc.info.get("runs", [{"seed": int(seed),
                                          "photons_per_channel": mc.info["photons_per_channel"],
                                          "seconds": mc.seconds}]), "kernel_seconds": mc.seconds,
            "photons_per_second": mc.photons_per_second, "device": mc.info["device"],
            "window": mc.info["window"], "noise_max_rel": noise,
            "noise_band_mm": list(NOISE_BAND_MM), "batches": batches,
            "trips_per_channel": mc.info["trips_per_channel"],
            "lane_occupancy": mc.info["lane_occupancy"],
            "interactions_per_second": mc.info["interactions_per_second"],
            "T_ballistic": [math.exp(-sum((l.sigma_a[c] + l.sigma_s[c]) * l.thickness_mm
                                          for l in st.layers)) if all(
                math.isfinite(l.thickness_mm) for l in st.layers) else 0.0 for c in range(3)]}
    prof = finish_table(r_mm, mc.R, mc.T, mc.Rd, mc.Tt, ring_area, info, cut_radii=edges[1:])
    prof.info["seconds"] = time.perf_counter() - t0
    return prof
