"""Monte Carlo reference for layered slabs: radial R(r), T(r) and totals with standard errors.

An OpenCL photon tracer in the spirit of MCML (Wang, Jacques, Zheng 1995): Henyey-Greenstein
phase (sigma_s = sigma_s_prime / (1 - g)), Fresnel at every boundary, Russian roulette,
radial binning, Philox counter-based random numbers keyed by ``seed`` so results repeat.
Model details and conventions are in the header of ``cl/mc_slab.cl``.  Normalisation is the
one of the layer file (:class:`pipeline.artifacts.LayerProfile`): per photon that entered
the top surface (the specular reflection at entry is not counted), densities in 1/mm^2 with
integral 2 pi r R(r) dr = Rd.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from dermis.pipeline import cl as dcl
from dermis.pipeline.errors import DermisError
from dermis.optics.layers import LayerStack

__all__ = ["VERSION", "KERNELS", "McResult", "WeightWindow", "simulate", "combine"]

VERSION = 3   # 3: ring edges of any spacing, radial splitting (weight window), log weights
KERNELS = ("mc_slab.cl",)

# Photons in flight per work-item: 8 (one AVX2 register) unless the device prefers float16
# vectors (AVX-512); measured in cl/mc_slab.cl's header.  None: by the device (lanes_for).
LANES: int | None = None
# Philox rounds of the tracer (cl/mc_slab.cl PHILOX_ROUNDS): 7 or 10.
PHILOX_ROUNDS = 7
# Work-items per channel = batches * k with k the largest value <= MAX_ITEMS_PER_BATCH that
# leaves every lane at least MIN_PHOTONS_PER_LANE photons: a work-item ends with idle lanes
# while its last photons finish (up to ~1e4 steps in high-albedo media), so lanes need many
# photons each to amortise that tail; 3 * batches >= 48 work-items keep 2 cores balanced.
MIN_PHOTONS_PER_LANE = 256
MAX_ITEMS_PER_BATCH = 4
# Per work-item totals written by the kernel (cl/mc_slab.cl N_TOTALS): R, T, absorbed, lost,
# interactions, busy lane-trips, trips.
N_TOTALS = 7
# Entries of the per-work-item stack of split photons (cl/mc_slab.cl BANK); 10 floats each.
# Splitting halves a photon at most once per interaction and the stack is last in, first
# out, so it holds about (splits along one photon's path) x LANES entries: measured < 100
# on two_layer; a full stack only stops splitting (unbiased).
BANK = 256
BANK_FLOATS = 10
# Russian roulette threshold (MCML's 1e-4), survival 1/10 (cl/mc_slab.cl ROULETTE_M).
W_MIN = 1e-4


def lanes_for(env) -> int:
    """Photons per work-item on ``env``'s device: LANES if set, else 16 where the device
    prefers float16 vectors (AVX-512), 8 otherwise."""
    if LANES is not None:
        return int(LANES)
    return 16 if env.queue.device.preferred_vector_width_float >= 16 else 8


def kernel_defines(env) -> dict:
    """Build defines of cl/mc_slab.cl for ``env``."""
    return {"LANES": lanes_for(env), "BANK": BANK, "PHILOX_ROUNDS": PHILOX_ROUNDS}


@dataclass
class McResult:
    """Monte Carlo estimate on rings [r_edges[k], r_edges[k+1]).

    r_edges : (B+1,) mm; r_centres : (B,) mm (ring mid-radius)
    R, T, R_err, T_err : (B, 3) 1/mm^2 ring averages and their standard errors
    Rd, Tt, absorbed, lost : (3,) totals per entered photon (lost: photons cut at the step cap)
    Rd_err, Tt_err, absorbed_err : (3,) standard errors (from ``batches`` independent batches)
    photons : int per channel (the mean if they differ; info["photons_per_channel"]);
    seconds : kernel time; photons_per_second : all photons traced / seconds
    info : device, items (work-items per channel), lanes (photons in flight per work-item),
        batches, seed, wall_seconds, interactions_per_second, lane_occupancy (fraction of
        lane-trips with a live photon), layers
    """

    r_edges: np.ndarray
    r_centres: np.ndarray
    R: np.ndarray
    T: np.ndarray
    R_err: np.ndarray
    T_err: np.ndarray
    Rd: np.ndarray
    Tt: np.ndarray
    absorbed: np.ndarray
    lost: np.ndarray
    Rd_err: np.ndarray
    Tt_err: np.ndarray
    absorbed_err: np.ndarray
    photons: int
    seconds: float
    photons_per_second: float
    info: dict = field(default_factory=dict)


def _layer_table(stack: LayerStack) -> np.ndarray:
    """(3, L, 8) float32 per channel and layer: z_top, z_bot, sigma_t, 1/sigma_t,
    sigma_a/sigma_t, g, eta, log(1 - sigma_a/sigma_t) (ratios in float64, rounded once)."""
    lays = stack.layers
    tab = np.zeros((3, len(lays), 8), np.float32)
    z = 0.0
    for k, lay in enumerate(lays):
        z1 = z + lay.thickness_mm
        for c in range(3):
            mut = float(lay.sigma_a[c]) + float(lay.sigma_s[c])
            fa = lay.sigma_a[c] / mut
            l1a = math.log1p(-fa) if fa < 1.0 else -1e30
            tab[c, k] = (z, z1, mut, 1.0 / mut, fa, lay.g, lay.eta, l1a)
        z = z1
    return tab


@dataclass(frozen=True)
class WeightWindow:
    """Radial splitting and Russian roulette of the tracer (cl/mc_slab.cl): a photon heavier
    than its window W(rho, z) is split, one lighter than ``w_min`` x W is rouletted."""

    params: object = None
    """(3, 4) array_like per channel: (kappa 1/mm, rho0 mm, rho1 mm, lambda 1/mm) of
    W = exp(-kappa clamp(rho - rho0, 0, rho1 - rho0) + lambda z); None or all 0: W = 1, no
    splitting (the analog tracer with MCML's roulette).  kappa must not exceed the decay rate
    of the light reaching rho (else the copies multiply without bound);
    :func:`dermis.optics.monte_carlo_table.monte_carlo_profiles` caps it at MC_KAPPA_CAP
    sigma_tr of the least absorbing layer."""
    w_min: float = W_MIN
    """Russian roulette below w_min x W(rho), survival 1/10 (MCML: 1e-4)."""


def simulate(stack: LayerStack, *, photons: int, r_max_mm: float | None = None,
             bins: int | None = None, seed: int = 0, batches: int = 16, env=None,
             edges: np.ndarray | None = None,
             weight_window: WeightWindow = WeightWindow()) -> McResult:
    """Trace ``photons`` photons per RGB channel through ``stack`` on OpenCL.

    Parameters
    ----------
    stack : LayerStack
        Layers top to bottom; zero-thickness layers are dropped (they are the identity).
    photons : int or (3,) ints
        Photons per channel, one for all or one each (rounded up to a multiple of the
        work-item count).
    r_max_mm, bins : float, int
        Radial histogram: ``bins`` rings of equal width over [0, r_max_mm).
    edges : (B+1,) array_like, optional
        Ring edges in mm instead (increasing, edges[0] = 0): any spacing.
    seed : int
        Random seed (0 .. 2**32 - 1); the same seed gives the same result on the same device.
    batches : int
        Number of independent batches for standard errors (>= 2).
    env : pipeline.cl.ClEnv, optional
        OpenCL environment; default ``pipeline.cl.get_env()`` (PoCL CPU).
    weight_window : WeightWindow
        Radial splitting and roulette (default: no splitting, MCML's roulette at W_MIN).

    Returns
    -------
    McResult
    """
    import pyopencl as cl   # the OpenCL runtime: loaded only when photons are traced

    window, w_min = weight_window.params, weight_window.w_min
    want = np.broadcast_to(np.asarray(photons), (3,))
    if not (np.all(np.isfinite(want.astype(np.float64))) and np.all(want >= 1)):
        raise DermisError(f"mc_slab: photons = {photons}: must be >= 1 (one int, or one per "
                          "channel)")
    want = want.astype(np.int64)
    if edges is None:
        if r_max_mm is None or bins is None or not (r_max_mm > 0 and math.isfinite(r_max_mm)) \
                or bins < 1:
            raise DermisError(f"mc_slab: r_max_mm = {r_max_mm}, bins = {bins}: need > 0 "
                              "(or give edges)")
        edges = np.linspace(0.0, r_max_mm, bins + 1)
    edges = np.asarray(edges, np.float64)
    if edges.ndim != 1 or len(edges) < 2 or edges[0] != 0.0 or not np.all(np.diff(edges) > 0) \
            or not np.isfinite(edges[-1]):
        raise DermisError("mc_slab: edges must be finite, increasing and start at 0")
    bins = len(edges) - 1
    win = np.zeros((3, 4), np.float32)
    if window is not None:
        win[:] = np.asarray(window, np.float64).reshape(3, 4)
        if not (np.all(np.isfinite(win)) and np.all(win >= 0)):
            raise DermisError(f"mc_slab: window = {win.tolist()}: need finite kappa, rho0, "
                              "rho1, lambda >= 0")
    if batches < 2:
        raise DermisError(f"mc_slab: batches = {batches}: must be >= 2 for standard errors")
    if not 0 <= seed < 2**32:
        raise DermisError(f"mc_slab: seed = {seed}: must be in 0 .. 2**32 - 1")
    stack = stack.nonzero()
    env = env or dcl.get_env()
    lanes = lanes_for(env)
    k = int(want.max()) // (batches * lanes * MIN_PHOTONS_PER_LANE)
    items = batches * max(1, min(MAX_ITEMS_PER_BATCH, k))
    per_item = np.ceil(want / items).astype(np.int32)      # per channel
    n_total = per_item.astype(np.int64) * items
    tab = _layer_table(stack)
    # a fresh Kernel object: no pyopencl retrieval warning
    knl = cl.Kernel(env.program("mc_slab.cl", kernel_defines(env)), "mc_slab")
    mf = cl.mem_flags
    d_tab = cl.Buffer(env.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=tab)
    d_edges = cl.Buffer(env.context, mf.READ_ONLY | mf.COPY_HOST_PTR,
                        hostbuf=edges.astype(np.float32))
    d_win = cl.Buffer(env.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=win)
    d_budget = cl.Buffer(env.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=per_item)
    d_bank = cl.Buffer(env.context, mf.READ_WRITE, 3 * items * BANK * BANK_FLOATS * 4)
    hist = np.zeros((3, items, 2, bins), np.float32)
    tots = np.zeros((3, items, N_TOTALS), np.float32)
    d_hist = cl.Buffer(env.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=hist)
    d_tots = cl.Buffer(env.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=tots)
    t0 = time.perf_counter()
    ev = knl(env.queue, (items, 3), (1, 1), d_tab, np.int32(len(stack.layers)),
             np.float32(stack.eta_above), np.float32(stack.eta_below), np.uint32(seed),
             d_budget, np.int32(bins), d_edges, np.float32(math.log(w_min)), d_win,
             d_bank, d_hist, d_tots)
    ev.wait()
    wall = time.perf_counter() - t0
    seconds = dcl.event_seconds(ev) or wall
    cl.enqueue_copy(env.queue, hist, d_hist)
    cl.enqueue_copy(env.queue, tots, d_tots)

    # batch b holds work-items b, b + batches, ...: per-batch means, then mean +- s.e.
    per_batch = (n_total // batches).astype(np.float64)
    hb = hist.astype(np.float64).reshape(3, items // batches, batches, 2, bins).sum(1)
    tb = tots[..., :4].astype(np.float64).reshape(3, items // batches, batches, 4).sum(1)
    hb /= per_batch[:, None, None, None]
    tb /= per_batch[:, None, None]
    area = np.pi * np.diff(edges**2)

    def mean_err(a, axis=1):
        return a.mean(axis), a.std(axis, ddof=1) / math.sqrt(batches)

    (h_mean, h_err) = mean_err(hb)            # (3, 2, bins)
    (t_mean, t_err) = mean_err(tb)            # (3, 4)
    R = (h_mean[:, 0] / area).T
    T = (h_mean[:, 1] / area).T
    R_err = (h_err[:, 0] / area).T
    T_err = (h_err[:, 1] / area).T
    counts = tots[..., 4:].astype(np.float64).sum((0, 1))   # interactions, busy, trips
    if not np.all(np.isfinite(tots)):
        raise DermisError("mc_slab: non-finite weights from the kernel "
                          f"(device {env.description}); please report this stack")
    return McResult(
        r_edges=edges, r_centres=0.5 * (edges[1:] + edges[:-1]), R=R, T=T, R_err=R_err,
        T_err=T_err, Rd=t_mean[:, 0], Tt=t_mean[:, 1], absorbed=t_mean[:, 2],
        lost=t_mean[:, 3], Rd_err=t_err[:, 0], Tt_err=t_err[:, 1], absorbed_err=t_err[:, 2],
        photons=int(round(n_total.mean())), seconds=seconds,
        photons_per_second=float(n_total.sum() / seconds),
        info={"device": env.description, "items": items, "lanes": lanes, "philox_rounds": PHILOX_ROUNDS,
              "batches": batches,
              "seed": seed, "wall_seconds": wall,
              "photons_per_channel": n_total.tolist(), "window": win.tolist(),
              "interactions": float(counts[0]),
              "interactions_per_second": float(counts[0] / seconds),
              # loop trips per channel: the channels' shares of the kernel time
              "trips_per_channel": tots[..., 6].astype(np.float64).sum(1).tolist(),
              # fraction of lane-trips that carried a live photon (the rest is the idle tail)
              "lane_occupancy": float(counts[1] / max(counts[2] * lanes, 1.0)),
              "layers": stack.to_dict()})


def combine(a: McResult, b: McResult) -> McResult:
    """Two independent runs on the same rings as one: per channel the photon-weighted mean,
    standard errors added in quadrature with the same weights (both are means of independent
    photons, so this is the estimate of the pooled photons)."""
    if not np.array_equal(a.r_edges, b.r_edges):
        raise DermisError("mc_slab.combine: the runs have different rings")
    na = np.asarray(a.info["photons_per_channel"], np.float64)
    nb = np.asarray(b.info["photons_per_channel"], np.float64)
    wa, wb = na / (na + nb), nb / (na + nb)

    def mean(x, y):
        return wa * x + wb * y

    def err(x, y):
        return np.hypot(wa * x, wb * y)

    seconds = a.seconds + b.seconds
    n = (na + nb).astype(np.int64)
    interactions = a.info["interactions"] + b.info["interactions"]
    info = dict(b.info)
    info.update(photons_per_channel=n.tolist(), wall_seconds=a.info["wall_seconds"]
                + b.info["wall_seconds"], interactions=interactions,
                interactions_per_second=interactions / seconds,
                trips_per_channel=(np.add(a.info["trips_per_channel"],
                                          b.info["trips_per_channel"])).tolist(),
                # pooled over loop trips (busy lane-trips / lane-trips), not over seconds:
                # a time-weighted mean made the artifact's bytes depend on the machine's load
                lane_occupancy=(a.info["lane_occupancy"] * sum(a.info["trips_per_channel"])
                                + b.info["lane_occupancy"] * sum(b.info["trips_per_channel"]))
                / max(sum(a.info["trips_per_channel"]) + sum(b.info["trips_per_channel"]), 1.0),
                runs=[{"seed": r.info["seed"], "photons_per_channel": r.info["photons_per_channel"],
                       "seconds": r.seconds} for r in (a, b)])
    return McResult(
        r_edges=a.r_edges, r_centres=a.r_centres, R=mean(a.R, b.R), T=mean(a.T, b.T),
        R_err=err(a.R_err, b.R_err), T_err=err(a.T_err, b.T_err), Rd=mean(a.Rd, b.Rd),
        Tt=mean(a.Tt, b.Tt), absorbed=mean(a.absorbed, b.absorbed), lost=mean(a.lost, b.lost),
        Rd_err=err(a.Rd_err, b.Rd_err), Tt_err=err(a.Tt_err, b.Tt_err),
        absorbed_err=err(a.absorbed_err, b.absorbed_err), photons=int(round(n.mean())),
        seconds=seconds, photons_per_second=float(n.sum() / seconds), info=info)
