"""The far gather: radiant exitance from the octree of irradiance points on the device
(Jensen-Buhler 2002 pass 2; docs/science.md §4).

The host flattens the octree (``subsurface/octree.py``) over the irradiance points
(``subsurface/points.py``, irradiance from ``lighting/irradiance.py``) into arrays; the device
(``cl/bssrdf_gather.cl``) walks it for every query point (pixel surface point) and sums
M_o(x) = sum R(|x - p|) E A with the layer file's radial profile R (``optics/layer_profiles.py``),
tabulated and blurred by ``subsurface/profile_table.py``.  ``subsurface/exitance.py`` adds
the near field; ``subsurface/radiance.py`` turns M_o into outgoing radiance.

Choices made here (and why):

* **Second-order clusters.**  Jensen-Buhler approximate a node by R(d) sum E A.  We add
  the second-order Taylor term over the node's positional covariance C (same weights as
  its mean position): sum w R(|x - p|) ~ W [R(d) + 1/2 ((R'' - R'/d) u^T C u + R'/d tr C)],
  u = (p - x) / d.  Six more floats per node; measured 6-13x lower error at equal epsilon
  (bench/bench_gather.py), which lets epsilon grow and the walk shrink.
  ``GatherTuning(second_order=False)`` gives the plain method.
* **Query order.**  Queries are sorted along a Morton curve before the launch (neighbouring
  work-items walk nearly the same nodes, which keeps the tree in cache) and unsorted after.
* **Tile walk** (``GatherTuning.tile``, default 16).  PoCL cannot vectorise a data-dependent
  tree walk across work-items, so one work-item takes 16 Morton-adjacent queries, walks the
  tree once with the tile's bounding sphere (a node is clustered only if every query may
  cluster it, so no query gets coarser clusters than its own walk would give it) and
  evaluates the 16 queries in float16 vector lanes.  Sources farther than max(expand_mm,
  expand_rt x tile radius) (``GatherTuning``: 1.5 mm, 3) are evaluated by a Taylor expansion
  of R in the distance about the tile centre (one scalar table lookup per source instead of
  16 gathered ones).  Measured on bench/bench_gather.py's head: ~2x less kernel time at
  equal error than the per-query walk.
* **Sub-tile expansion** (``GatherTuning.subtiles``, tile 16).  Sources too near for the
  tile's expansion but far from each of its 4 sub-tiles (4 Morton-adjacent queries, own
  bounding sphere, median radius ~1/3 of the tile's) are expanded about the sub-tile
  centres (4 contiguous table rows instead of 16 gathered ones; lanes interleaved so the 4
  coefficients spread as one float4 repeated).  The expansion is quartic (d4R/dr4 / 24 in
  the table's spare slots; measured 0.350 % vs 0.367 % rel RMSE against cubic at eps 0.5,
  same time).  Measured on the bench head (eps 0.6, leaf 16, old expansion radii): 0.196 s
  vs 0.216 s at equal error; the cheaper expansion then allowed smaller radii
  (``GatherTuning.expand_mm``).
* **Defaults.**  One per knob.  Epsilon and the leaf size are scene settings: their only
  defaults are the scene schema's (``[bssrdf]`` in ``pipeline/config.py``, chosen from
  bench/results/gather.json); :func:`gather` requires epsilon and :func:`build_octree` reads
  the schema's leaf size.  The research knobs (walk, tile, expansion radii, work-group size)
  are :class:`GatherTuning` fields, defaulting to what the pipeline runs.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from dermis.pipeline.cl import event_seconds, get_env, to_device
from dermis.pipeline.errors import DermisError
from dermis.pipeline.reuse import RecentResults, content_key
from dermis.subsurface.near_field import split_profile
from dermis.subsurface.octree import Octree, morton_order
from dermis.subsurface.profile_table import kernel_sigma, profile_table
# pyopencl is imported inside the functions that launch kernels: loading a stage module to
# build the graph needs no OpenCL

__all__ = ["KERNELS", "GatherTuning", "gather", "TILE_SIZES"]

KERNELS = ("bssrdf_gather.cl",)

# Queries per work-item: 1 (one query per work-item, gather_tree) or an OpenCL vector width
# (the tile walk, gather_tile_v).
TILE_SIZES = (1, 4, 8, 16)


@dataclass(frozen=True)
class GatherTuning:
    """Research knobs of :func:`gather` (not scene settings).  The defaults are what the
    pipeline runs, measured with bench/bench_gather.py (LPS head x10 mm, 250k points, 640k
    camera queries, skin2, cut-off 24 mm; 2-core PoCL; bench/results/gather.json).

    tile : int
        Queries per work-item, one of ``TILE_SIZES``: Morton-adjacent queries share one walk
        with a conservative opening test, evaluated in float<tile> vector lanes (module
        docstring); 1 gives the per-query walk.  16 beat 8 and 4 at equal error (wider
        vectors, one walk per 16 queries; its conservative opening test costs ~40 % more
        visits per query).
    expand_mm, expand_rt : float
        Sources farther than max(expand_mm, expand_rt x tile radius) from every query of a
        tile are evaluated by a Taylor expansion about the tile centre (and, tile 16, about
        the 4 sub-tile centres with the sub-tile radius); expand_mm = inf evaluates every
        source exactly.  The radius factor keeps tiles that straddle a gap of the Morton
        curve exact (a polynomial diverges beyond its radius: without it the error was
        1-3 %).  Measured (leaf 16, quartic expansion), eps 0.5: (1.5 mm, 3.0) 0.179 s, rel
        RMSE 0.376 %; (3 mm, 4.0) 0.193 s, 0.350 %; (3 mm, 6.0) 0.228 s, 0.318 %; (1.0 mm,
        2.5) 0.179 s, 0.390 %; every source exact 0.373 s, 0.281 %.  At eps 0.2: 0.277 s,
        0.059 % (before sub-tiles, cubic, (3 mm, 6.0): 0.386 s, 0.045 %).  The older cubic
        tile-only expansion with (3 mm, 6): eps 0.4, 0.234 % vs 0.214 % exact.
    subtiles : bool
        (tile 16) Also expand nearer sources about the centres of the tile's 4 sub-tiles of
        4 queries (module docstring); False: those are evaluated exactly.
    expand_sub_rt : float or None
        The radius factor for the sub-tiles (None: ``expand_rt``).
    second_order : bool
        Add the second-order (covariance) term to every cluster (module docstring); False
        gives the plain Jensen-Buhler point-cluster approximation.
    sort_queries : bool
        Launch the queries in Morton order (results are returned in the input order).  The
        tile walk always sorts.
    local_size : int or None
        OpenCL work-group size of the per-query and brute-force walks (None: the runtime's
        choice; the tile walk uses min(local_size or 8, 8)).  Measured on PoCL: 64 vs None vs
        256 made < 5 % difference.
    kernel_sigma_mm : float or None
        Width of the Gaussian that reconstructs irradiance between the points (module
        docstring); None: :func:`kernel_sigma` of the octree; 0 gathers the raw profile.
    cutoff_mm : float or None
        Override the profile's per-channel cut-off with one radius for all channels.
    """

    tile: int = 16
    expand_mm: float = 1.5
    expand_rt: float = 3.0
    subtiles: bool = True
    expand_sub_rt: float | None = None
    second_order: bool = True
    sort_queries: bool = True
    local_size: int | None = 64
    kernel_sigma_mm: float | None = None
    cutoff_mm: float | None = None

    def __post_init__(self):
        if isinstance(self.tile, bool) or self.tile not in TILE_SIZES:
            raise DermisError(f"gather: tile = {self.tile!r}: must be one of {TILE_SIZES} (1: "
                              "one query per work-item; 4, 8, 16: OpenCL vector widths)")


def gather(octree: Octree, profile, query_positions: np.ndarray, *, epsilon: float | None,
           normalisation: str = "energy", env=None, brute_force: bool = False, progress=None,
           tuning: GatherTuning = GatherTuning(), part: str = "all") -> tuple[np.ndarray, dict]:
    """Radiant exitance M_o at query points from the octree's irradiance points.

    Parameters
    ----------
    octree : Octree
        From :func:`build_octree`.
    profile : LayerProfile
        r_mm (N,), R (N, 3) in 1/mm^2, Rd (3,), cutoff_mm (3,) (stage ``profiles``).
    query_positions : (Q, 3) float ndarray, mm
        Surface points to shade (one per pixel).
    epsilon : float
        Solid-angle criterion A / d^2 < epsilon (docs/science.md §4).  No default here: the
        scene's ``[bssrdf] epsilon`` (pipeline/config.py) is the shipped value (anchors with
        zeroth-order clusters: pbrt-v2 0.05, Mitsuba 0.2).  Ignored (may be None) with
        ``brute_force``.
    normalisation : {"energy", "thesis"}
        "energy": M = sum R E A with the table normalised to integrate to Rd (flat slab gives
        M = Rd E).  "thesis": M = Rd * sum R E A / sum R A (the thesis's normalisation by
        the total profile weight of the points in range; 0 where nothing is in range).
    env : pipeline.cl.ClEnv, optional
        OpenCL environment (default ``pipeline.cl.get_env()``).
    brute_force : bool
        Sum every point with no clustering (the reference; O(Q N)).
    progress : callable(float), optional
        Called with the fraction done (the launch is split into chunks when given).
    tuning : GatherTuning
        Research knobs (walk, expansion radii, work-group size, ...); the defaults are what
        the pipeline runs.
    part : {"all", "far", "near"}
        Which part of the profile to gather (:func:`split_profile`): the whole profile, or
        its far or near part about the window at ``NEAR_INNER``..``NEAR_OUTER`` x the
        reconstruction width ("energy" normalisation only; :func:`exitance` evaluates the
        near part per shading point for point and directional lights).

    Returns
    -------
    M : (Q, 3) float32 ndarray
        Radiant exitance in the unit of the irradiance.
    stats : dict
        kernel_seconds (profiling events), wall_seconds, mean_visits (nodes + points
        evaluated per query, hierarchical only), epsilon, normalisation, brute_force, device.

    Raises
    ------
    DermisError
        Bad shapes, NaN/infinite inputs, epsilon <= 0, unknown normalisation.
    """
    t0 = time.perf_counter()
    qp = _check_queries(query_positions, epsilon=epsilon, normalisation=normalisation,
                        brute_force=brute_force)
    nq = len(qp)
    if nq == 0:
        return np.zeros((0, 3), np.float32), {"kernel_seconds": 0.0, "wall_seconds": 0.0}
    run = _prepare(octree, profile, env or get_env(), normalisation=normalisation,
                   tuning=tuning, progress=progress, part=part)
    perm, q4, tiles = _ordered_queries(qp, brute_force=brute_force, tuning=tuning)
    if brute_force:
        out, visits, events = _walk_brute(run, q4)
    elif tuning.tile > 1:
        out, visits, events = _walk_tiles(run, q4, tiles, octree, epsilon)
    else:
        out, visits, events = _walk_queries(run, q4, octree, epsilon)
    run.env.queue.finish()
    m = np.empty((nq, 3), np.float32)
    m[perm] = out[:, :3]
    vis = np.empty(nq, np.int32)
    vis[perm] = visits
    stats = {"kernel_seconds": event_seconds(events), "wall_seconds": time.perf_counter() - t0,
             "epsilon": None if brute_force else float(epsilon), "normalisation": normalisation,
             "brute_force": bool(brute_force), "cutoff_mm": run.cmax, "queries": nq,
             "kernel_sigma_mm": run.sigma, "points": run.n_points, "part": part,
             "device": run.env.description}
    if not brute_force:
        stats["mean_visits"] = float(vis.mean())
    return m, stats


def _check_queries(query_positions, *, epsilon, normalisation: str,
                   brute_force: bool) -> np.ndarray:
    """Validate the options and the query points; the queries as (Q, 3) float64."""
    if normalisation not in ("energy", "thesis"):
        raise DermisError(f"gather: normalisation = {normalisation!r}: must be 'energy' or 'thesis'")
    if not brute_force and not (epsilon is not None and epsilon > 0 and math.isfinite(epsilon)):
        raise DermisError(f"gather: epsilon = {epsilon}: must be a finite number > 0")
    qp = np.asarray(query_positions, np.float64)
    if qp.ndim != 2 or qp.shape[1] != 3:
        raise DermisError(f"gather: query_positions must be (Q, 3); got {qp.shape}")
    if not np.isfinite(qp).all():
        raise DermisError("gather: query_positions contains NaN or infinity")
    return qp


@dataclass
class _Run:
    """What every walk needs: the device, the profile tables (host) and the point buffers
    (device), the normalisation defines, the tuning and the progress chunking."""

    env: object
    tuning: GatherTuning
    sigma: float          # reconstruction width the profile was blurred with, mm
    tab: np.ndarray       # (TABLE_N, 4) R rgb
    h: float              # table step, mm
    cmax: float           # largest cut-off (after the blur's reach), mm
    deriv: np.ndarray     # (2 TABLE_N, 4) R'' - R'/r, R'/r
    taytab: np.ndarray    # (4 TABLE_N, 4) Taylor rows of the far-field expansion
    rd_vec: object        # cl float4 Rd rgb (thesis mode)
    n_points: int
    d_pa: object          # (N) float4 x, y, z, A in leaf order
    d_pe: object          # (N) float4 E A rgb, 0
    d_tab: object
    defines: dict
    chunks: int
    progress: object

    @property
    def inv_h(self) -> np.float32:
        return np.float32(1.0 / self.h)

    def launch(self, n: int, enqueue) -> list:
        """Enqueue ``enqueue(a, b, whole)`` for each launch chunk [a, b) of n items (one chunk
        without a progress callback); report progress after each.  Returns the events."""
        events = []
        bounds = _chunk_bounds(n, self.chunks)
        for c in range(self.chunks):
            a, b = bounds[c], bounds[c + 1]
            if b <= a:
                continue
            events.append(enqueue(a, b, a == 0 and b == n))
            if self.progress is not None:
                events[-1].wait()
                self.progress(b / n)
        return events


# Device tables per (profile content, normalisation, cut-off, sigma, part), kept across
# runs of this process (pipeline/reuse.py): the blur costs ~0.3 s and every image of a mesh
# uses the same tables.
_TABLES = RecentResults(8)


def _prepare(octree: Octree, profile, env, *, normalisation: str, tuning: GatherTuning,
             progress, part: str = "all") -> _Run:
    """Profile tables (blurred with the octree's reconstruction width) and point buffers."""
    import pyopencl as cl

    sigma = kernel_sigma(octree) if tuning.kernel_sigma_mm is None else float(tuning.kernel_sigma_mm)
    if part not in ("all", "far", "near"):
        raise DermisError(f"gather: part = {part!r}: must be 'all', 'far' or 'near'")
    if part != "all" and (normalisation != "energy" or not sigma > 0):
        raise DermisError("gather: a near/far part needs the 'energy' normalisation and a "
                          "reconstruction width > 0")

    def tables():
        src = profile
        if part != "all":
            split = split_profile(profile, sigma, cutoff_mm=tuning.cutoff_mm)
            src = split.far if part == "far" else split.near
        return profile_table(src, normalisation=normalisation, cutoff_mm=tuning.cutoff_mm,
                             sigma_mm=sigma, taylor=True)
    key = (_profile_key(profile), normalisation, tuning.cutoff_mm, sigma, part)
    tab, h, cmax, deriv, taytab = _TABLES.get(key, tables)
    rd = np.zeros(4, np.float32)
    rd[:3] = np.asarray(profile.Rd, np.float32)
    pts_pa = np.zeros((len(octree.positions), 4), np.float32)
    pts_pa[:, :3] = octree.positions
    pts_pa[:, 3] = octree.areas
    pts_e = np.zeros_like(pts_pa)
    pts_e[:, :3] = octree.irradiance * octree.areas[:, None]
    defines = {"TABLE_N": len(tab), "THESIS_NORM": int(normalisation == "thesis"),
               "SECOND_ORDER": int(bool(tuning.second_order))}
    return _Run(env=env, tuning=tuning, sigma=sigma, tab=tab, h=h, cmax=cmax, deriv=deriv,
                taytab=taytab, rd_vec=cl.cltypes.make_float4(*rd), n_points=int(len(pts_pa)),
                d_pa=to_device(env, pts_pa), d_pe=to_device(env, pts_e), d_tab=to_device(env, tab),
                defines=defines, chunks=16 if progress is not None else 1, progress=progress)


def _profile_key(profile) -> str:
    """Content key of a layer profile (what the tables are made of)."""
    return content_key(*(np.asarray(getattr(profile, f), np.float64)
                         for f in ("r_mm", "R", "Rd", "cutoff_mm")))


def _query_order(qp: np.ndarray, *, brute_force: bool, tuning: GatherTuning) -> np.ndarray:
    """Launch order of the queries: Morton (results are returned in the input order).  The
    tile walk always forms its tiles along the Morton curve (unsorted tiles span the scene:
    measured 40x slower for random order); ``sort_queries`` applies to the other walks."""
    tiled = not brute_force and tuning.tile > 1
    return morton_order(qp) if (tuning.sort_queries or tiled) else np.arange(len(qp))


# Query orders and tiles of the last shading points (pipeline/reuse.py): every image of a
# geometry shades the same points (~0.6 s of sorting and tiling for 1.2M camera samples).
_QUERY_TILES = RecentResults(2)


def _ordered_queries(qp: np.ndarray, *, brute_force: bool, tuning: GatherTuning):
    """The launch order ``perm`` (:func:`_query_order`), the ordered queries (Q, 4) float32
    and, for the tile walk, their tiles (:func:`_tile_queries`; else None)."""
    tiled = not brute_force and tuning.tile > 1
    use_sub = tiled and tuning.tile == 16 and bool(tuning.subtiles)

    def make():
        perm = _query_order(qp, brute_force=brute_force, tuning=tuning)
        q4 = np.zeros((len(qp), 4), np.float32)
        q4[:, :3] = qp[perm]
        tiles = _tile_queries(q4, tuning.tile, use_sub) if tiled else ()
        for a in (perm, q4, *tiles):
            a.setflags(write=False)   # shared by later images
        return perm, q4, tiles or None
    return _QUERY_TILES.get(content_key(qp, brute_force, tuning.sort_queries,
                                        tuning.tile if tiled else 1, use_sub), make)


def _part(buf, whole: bool, a: int, b: int, item_bytes: int):
    """Sub-buffer of items [a, b) (the whole buffer when the chunk is all of it)."""
    return buf if whole else buf.get_sub_region(a * item_bytes, (b - a) * item_bytes)


def _walk_brute(run: _Run, q4: np.ndarray):
    """Every point for every query (gather_brute): the reference.  (out (Q, 4), visits 0, events)"""
    import pyopencl as cl

    env, nq, ls = run.env, len(q4), run.tuning.local_size
    d_q = to_device(env, q4)
    out = np.empty((nq, 4), np.float32)
    d_out = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
    knl = env.kernel("bssrdf_gather.cl", "gather_brute", run.defines)
    events = run.launch(nq, lambda a, b, whole: knl(
        env.queue, _global(b - a, ls), _local(ls), _part(d_q, whole, a, b, 16), run.d_pa,
        run.d_pe, np.int32(run.n_points), run.d_tab, run.inv_h, run.rd_vec, np.int32(b - a),
        _part(d_out, whole, a, b, 16)))
    cl.enqueue_copy(env.queue, out, d_out)
    return out, np.zeros(nq, np.int32), events


def _walk_queries(run: _Run, q4: np.ndarray, octree: Octree, epsilon: float):
    """One tree walk per query (gather_tree, ``tile`` 1).  (out (Q, 4), visits (Q,), events)"""
    import pyopencl as cl

    env, nq, ls = run.env, len(q4), run.tuning.local_size
    d_q = to_device(env, q4)
    d_node = to_device(env, _node_records(octree, epsilon, run.cmax))
    d_start = to_device(env, octree.start.astype(np.int32))
    d_deriv = to_device(env, run.deriv)
    out = np.empty((nq, 4), np.float32)
    visits = np.zeros(nq, np.int32)
    d_out = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
    d_vis = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, visits.nbytes)
    knl = env.kernel("bssrdf_gather.cl", "gather_tree", run.defines)
    events = run.launch(nq, lambda a, b, whole: knl(
        env.queue, _global(b - a, ls), _local(ls), _part(d_q, whole, a, b, 16), d_node, d_start,
        np.int32(octree.n_nodes), run.d_pa, run.d_pe, run.d_tab, d_deriv, run.inv_h,
        run.rd_vec, np.int32(b - a), _part(d_out, whole, a, b, 16),
        _part(d_vis, whole, a, b, 4)))
    cl.enqueue_copy(env.queue, visits, d_vis)
    cl.enqueue_copy(env.queue, out, d_out)
    return out, visits, events


def _tile_queries(q4: np.ndarray, tile: int, use_sub: bool):
    """Morton-sorted queries cut into tiles of ``tile``, the last padded with copies of the
    last query (their results are dropped).  Returns the planar per-tile queries (G, 3, T)
    (with sub-tiles lane l belongs to sub-tile l % 4: cl SUBTILE), the tile spheres (G, 4) and
    the sub-tile spheres (4 G, 4; each over 4 consecutive queries)."""
    nq = len(q4)
    ntiles = -(-nq // tile)
    qt = np.zeros((ntiles * tile, 4), np.float32)
    qt[:nq] = q4
    qt[nq:] = q4[-1]
    sph = _tile_spheres(qt[:, :3].astype(np.float64).reshape(ntiles, tile, 3))
    ssph = _tile_spheres(qt[:, :3].astype(np.float64).reshape(ntiles * 4, tile // 4, 3))
    q3 = qt[:, :3].reshape(ntiles, tile, 3)
    if use_sub:
        q3 = q3.reshape(ntiles, 4, 4, 3).transpose(0, 2, 1, 3).reshape(ntiles, tile, 3)
    return np.ascontiguousarray(q3.transpose(0, 2, 1)), sph, ssph


def _untile(planar: np.ndarray, tile: int, use_sub: bool, nq: int) -> np.ndarray:
    """Planar per-tile results (G, 3, T) back to (Q, 4) in query order (column 3 unset)."""
    ntiles = len(planar)
    if use_sub:  # back from the interleaved lane order
        planar = planar.reshape(ntiles, 3, 4, 4).transpose(0, 1, 3, 2).reshape(ntiles, 3, tile)
    outt = np.empty((ntiles * tile, 4), np.float32)
    outt[:, :3] = planar.transpose(0, 2, 1).reshape(-1, 3)
    return outt[:nq]


def _walk_tiles(run: _Run, q4: np.ndarray, tiles, octree: Octree, epsilon: float):
    """One walk per tile of Morton-adjacent queries in vector lanes (gather_tile_v), with the
    far-field expansion about the tile and (tile 16) its sub-tiles; ``tiles`` are the
    queries' (:func:`_tile_queries`).  (out (Q, 4), visits (Q,): the tile's, events)"""
    import pyopencl as cl

    env, nq, tn = run.env, len(q4), run.tuning
    tile = tn.tile
    use_sub = tile == 16 and bool(tn.subtiles)
    sub_rt = tn.expand_rt if tn.expand_sub_rt is None else tn.expand_sub_rt
    qt, sph, ssph = tiles
    ntiles = len(qt)
    d_qt, d_sph, d_ssph = to_device(env, qt), to_device(env, sph), to_device(env, ssph)
    d_node = to_device(env, _node_records(octree, epsilon, run.cmax, distances=True))
    d_start = to_device(env, octree.start.astype(np.int32))
    d_ptab = to_device(env, _packed_table(run.tab, run.deriv))
    d_xtab = to_device(env, run.taytab)
    d_out = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, ntiles * tile * 16)
    tvis = np.zeros(ntiles, np.int32)
    d_vis = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, tvis.nbytes)
    knl = env.kernel("bssrdf_gather.cl", "gather_tile_v", dict(run.defines, TILE=int(tile)))
    tl = min(tn.local_size or 8, 8)  # few, heavy work-items: small groups keep both cores busy
    tbytes = tile * 12  # planar xyz queries / rgb results per tile
    events = run.launch(ntiles, lambda a, b, whole: knl(
        env.queue, _global(b - a, tl), (tl,), _part(d_qt, whole, a, b, tbytes),
        _part(d_sph, whole, a, b, 16), _part(d_ssph, whole, a, b, 64), np.int32(use_sub),
        np.float32(sub_rt), d_node, d_start, np.int32(octree.n_nodes), run.d_pa, run.d_pe,
        run.d_tab, d_ptab, d_xtab, run.inv_h, np.float32(tn.expand_mm),
        np.float32(tn.expand_rt), run.rd_vec, np.int32(b - a),
        _part(d_out, whole, a, b, tbytes), _part(d_vis, whole, a, b, 4)))
    planar = np.empty((ntiles, 3, tile), np.float32)
    cl.enqueue_copy(env.queue, planar, d_out)
    cl.enqueue_copy(env.queue, tvis, d_vis)
    return _untile(planar, tile, use_sub, nq), np.repeat(tvis, tile)[:nq], events


def _node_records(t: Octree, epsilon: float, cutoff: float, *,
                  distances: bool = False) -> np.ndarray:
    """Device node records, 4 float4 (64 bytes, one cache line) per node; layout in the .cl
    (``distances``: reach and opening distance for gather_tile_v, else their squares)."""
    k = t.n_nodes
    rec = np.zeros((k, 4, 4), np.float32)
    radius = t.radius.astype(np.float64)
    rec[:, 0, :3] = t.position
    rec[:, 1, :3] = t.ea_sum
    # cluster when d^2 > A / epsilon (solid angle) and d > radius (x outside the node)
    open2 = np.maximum(t.area / epsilon, radius**2)
    if distances:
        rec[:, 0, 3] = cutoff + radius
        rec[:, 1, 3] = np.minimum(np.sqrt(open2), np.finfo(np.float32).max)
    else:
        rec[:, 0, 3] = (cutoff + radius) ** 2
        rec[:, 1, 3] = np.minimum(open2, np.finfo(np.float32).max)
    rec[:, 2, :] = t.covariance[:, :4]
    rec[:, 3, 0:2] = t.covariance[:, 4:6]
    rec[:, 3, 2] = t.area
    rec[:, 3, 3] = t.skip[:k].astype(np.int32).view(np.float32)
    return rec.reshape(4 * k, 4)


def _tile_spheres(tq: np.ndarray) -> np.ndarray:
    """Bounding spheres (centre of the box, radius) of query tiles (G, T, 3) -> (G, 4) float32,
    the radius padded so float32 rounding never puts a query outside its sphere."""
    c = 0.5 * (tq.min(axis=1) + tq.max(axis=1))
    r = np.linalg.norm(tq - c[:, None, :], axis=2).max(axis=1)
    scale = max(float(np.abs(tq).max()), 1e-30)
    sph = np.empty((len(tq), 4), np.float32)
    sph[:, :3] = c
    sph[:, 3] = r * (1 + 1e-5) + 1e-6 * scale
    return sph


def _packed_table(tab: np.ndarray, deriv: np.ndarray) -> np.ndarray:
    """(R, R'' - R'/r, R'/r) per table entry for gather_tile_v's ptab: 12 floats per row,
    rgb rgb rgb then 3 zeros."""
    n = len(tab)
    out = np.zeros((n, 3, 4), np.float32)
    out[:, 0] = tab
    out[:, 1:] = deriv.reshape(n, 2, 4)
    flat = np.zeros((n, 12), np.float32)
    flat[:, :9] = out[:, :, :3].reshape(n, 9)
    return flat


def _chunk_bounds(n: int, chunks: int) -> np.ndarray:
    """Launch chunk boundaries, multiples of 32 items (sub-buffer origins must be aligned to
    the device's base address alignment, 128 bytes on PoCL; 32 x 4-byte visit counters)."""
    b = (np.linspace(0, n, chunks + 1) // 32).astype(int) * 32
    b[-1] = n
    return np.maximum.accumulate(b)


def _global(n: int, local: int | None) -> tuple[int]:
    """Global size rounded up to the work-group size (the kernel guards the tail)."""
    if not local:
        return (n,)
    return (int(math.ceil(n / local)) * local,)


def _local(local: int | None):
    return (local,) if local else None
