"""Radiant exitance by hierarchical gather of cached irradiance (Jensen-Buhler 2002 pass 2).

docs/science.md §4.  The host builds an octree over the irradiance sample points
(``stages/samples.py``, irradiance from ``lighting/lights.py``) and flattens it into arrays;
the device (``cl/bssrdf_gather.cl``) walks it for every query point (pixel surface point)
and sums M_o(x) = sum R(|x - p|) E A with the layer file's radial profile R
(``stages/profiles.py``).  :func:`exitance_to_radiance` turns M_o into outgoing radiance.

Choices made here (and why):

* **Octree.**  Points are sorted along a 21-bit-per-axis Morton curve of their bounding
  cube; a node is a run of points sharing a Morton prefix, split while it holds more than
  ``leaf_size`` points (Jensen-Buhler and pbrt-v2 use 8).  Nodes are stored in depth-first
  pre-order (sort by (first point, depth)) with a skip index, so the device walk is a
  forward loop without a stack.  Each node keeps total area, the sum of E A (so the
  area-weighted mean irradiance is sum E A / A), the irradiance-weighted mean position
  (weights E A summed over channels; the area-weighted centroid where a node has no
  irradiance), a bounding box (host) and the bounding-sphere radius about that position
  (device: the "outside the node" test and the cut-off skip).
* **Profile table.**  R is resampled on a uniform grid of ``TABLE_N`` entries up to the
  largest cut-off radius, each channel zeroed beyond its own ``cutoff_mm``.  In the
  energy-correct mode each channel is rescaled so the table's exact integral
  (piecewise-linear R, int 2 pi r R dr) equals the layer file's Rd: the <= 0.1 % the cut-off
  drops is put back, and a flat slab under uniform irradiance leaves M = Rd E.
* **Reconstruction blur** (``kernel_sigma_mm``).  The points carry irradiance samples,
  not cells: between them E is reconstructed as sum_p A_p E_p G_sigma(y - p) with the
  2-D Gaussian of ``stages/samples.py`` (sigma = ``KERNEL_SIGMA_FACTOR`` x spacing, areas
  solved so the Gaussians are a partition of unity).  Then M(x) = int R(|x - y|) E(y) dy =
  sum_p E_p A_p (R * G_sigma)(|x - p|): the device gathers with the profile convolved with
  G_sigma, built once on the host in float64 (radial convolution with the Bessel I0
  kernel), which integrates to the same Rd.  On a flat slab the error per query is then at
  most the partition-of-unity deviation (R >= 0 weights it), 0.7 % at the default, where
  the raw profile on the same points is off by up to 25-48 % (blue, skin1: the density
  rule's 1.2 mm spacing against a 0.67 mm mean free path).  A disc of one point's area
  (the cell average) was measured too: max error 22 % even with Voronoi areas, because
  an indicator's partition of unity is a point count.  The price is a blur of sigma
  (1.2 mm for skin1 at point_density 1), the irradiance sampling's own resolution.
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
from dataclasses import dataclass, field, fields

import numpy as np

from dermis.pipeline.config import BssrdfConfig
from dermis.pipeline.errors import DermisError
from dermis.pipeline.reuse import RecentResults, content_key
from dermis.optics.fresnel import diffuse_fresnel_external, fresnel_transmittance
from dermis.stages.brdf_models import Transmittance  # entry/exit transmittance (re-exported)

__all__ = ["VERSION", "KERNELS", "Octree", "build_octree", "gather", "GatherTuning",
           "profile_table", "exitance_to_radiance", "morton_order", "blurred_profile",
           "kernel_sigma", "TILE_SIZES", "TABLE_N", "exitance", "Transmittance",
           "split_profile", "near_tables", "near_window", "shadow_edges", "edge_sum",
           "edge_sum_cl", "sharp_visibility",
           "sharp_near_field", "ShadowEdges", "ProfileSplit", "EdgeTable", "NEAR_INNER",
           "NEAR_OUTER", "SHARP_LIGHTS"]

VERSION = 5
KERNELS = ("bssrdf_gather.cl",)


def _scene_default(name: str):
    """The scene schema's default of ``[bssrdf] <name>`` (pipeline/config.py BssrdfConfig):
    the library keeps no second copy of a scene setting's number."""
    return next(f.default for f in fields(BssrdfConfig) if f.name == name)


# Profile table entries: 1024 over a 30 mm cut-off is a 0.03 mm step, far below the point
# spacing (>= 0.1 mm) and the profile's own grid (mfp/4), so interpolation adds nothing visible.
TABLE_N = 1024
MORTON_BITS = 21
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


@dataclass
class Octree:
    """A flattened octree over irradiance points (depth-first pre-order, skip links).

    Nodes (K of them, plus a sentinel at index K whose ``start`` is the point count):
      position : (K, 3) float32 irradiance-weighted mean position, mm
      area : (K,) float64 total area, mm^2
      ea_sum : (K, 3) float64 sum of E A over the node's points (mean E = ea_sum / area)
      bbox_min, bbox_max : (K, 3) float32 axis-aligned bounds of the node's points, mm
      radius : (K,) float32 bounding-sphere radius about ``position``, mm
      covariance : (K, 6) float64 positional covariance (xx xy xz yy yz zz) with the same
        weights as ``position``, mm^2 (the second-order cluster term)
      skip : (K + 1,) int32 index of the next node outside the subtree (leaf: i + 1)
      start : (K + 1,) int32 first point (in ``order``); a leaf owns [start[i], start[i+1])
      depth : (K,) int32
      is_leaf : (K,) bool
    Points in leaf order:
      order : (N,) int64 permutation: points[order] is leaf order
      positions, irradiance, areas : the reordered inputs (float32)
    leaf_size : int; info : dict
    """

    position: np.ndarray
    area: np.ndarray
    ea_sum: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    radius: np.ndarray
    covariance: np.ndarray
    skip: np.ndarray
    start: np.ndarray
    depth: np.ndarray
    is_leaf: np.ndarray
    order: np.ndarray
    positions: np.ndarray
    irradiance: np.ndarray
    areas: np.ndarray
    leaf_size: int
    info: dict = field(default_factory=dict)

    @property
    def n_nodes(self) -> int:
        return int(len(self.area))

    @property
    def mean_irradiance(self) -> np.ndarray:
        """Area-weighted mean irradiance per node, (K, 3)."""
        return self.ea_sum / np.maximum(self.area, 1e-300)[:, None]


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Interleave two zero bits after each of the low 21 bits (Morton encoding helper)."""
    x = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def _morton_keys(p: np.ndarray, lo: np.ndarray, size: float) -> np.ndarray:
    """63-bit Morton keys of points in the cube [lo, lo + size]^3."""
    scale = ((1 << MORTON_BITS) - 1) / max(size, 1e-30)
    q = np.clip(((p - lo) * scale), 0, (1 << MORTON_BITS) - 1).astype(np.uint64)
    return (_spread_bits(q[:, 0]) << np.uint64(2)) | (_spread_bits(q[:, 1]) << np.uint64(1)) \
        | _spread_bits(q[:, 2])


def morton_order(points: np.ndarray) -> np.ndarray:
    """Permutation sorting points along a Morton (Z-order) curve of their bounding cube."""
    p = np.asarray(points, np.float64)
    if len(p) == 0:
        return np.zeros(0, np.int64)
    lo = p.min(axis=0)
    size = float((p.max(axis=0) - lo).max())
    return np.argsort(_morton_keys(p, lo, size), kind="stable")


def _check_points(positions, areas, irradiance):
    p = np.asarray(positions, np.float64)
    a = np.asarray(areas, np.float64)
    e = np.asarray(irradiance, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise DermisError(f"gather: positions must be a non-empty (N, 3) array; got {p.shape}")
    n = len(p)
    if e.ndim == 1:
        e = np.repeat(e[:, None], 3, axis=1)
    if a.shape != (n,) or e.shape != (n, 3):
        raise DermisError(f"gather: areas {a.shape} and irradiance {e.shape} must be ({n},) and "
                          f"({n}, 3) to match positions")
    for name, arr in (("positions", p), ("areas", a), ("irradiance", e)):
        if not np.isfinite(arr).all():
            raise DermisError(f"gather: {name} contains NaN or infinity")
    if (a < 0).any() or (e < 0).any():
        raise DermisError("gather: areas and irradiance must be >= 0")
    return p, a, e


def build_octree(positions: np.ndarray, areas: np.ndarray, irradiance: np.ndarray, *,
                 leaf_size: int = _scene_default("leaf_size"),
                 kernel_sigma_mm: float | None = None) -> Octree:
    """Build the flattened octree over irradiance sample points.

    Parameters
    ----------
    positions : (N, 3) float ndarray, mm
    areas : (N,) float ndarray, mm^2 (each point's share of the surface)
    irradiance : (N, 3) or (N,) float ndarray, irradiance E per point (any radiometric unit;
        the exitance comes out in the same unit)
    leaf_size : int
        Maximum points per leaf; default the scene schema's ``[bssrdf] leaf_size`` (16:
        bench/results/gather.json, LPS head, eps 0.5: 0.179 s vs 0.195 s kernel and rel RMSE
        0.376 % vs 0.391 % against 8, the Jensen-Buhler and pbrt-v2 value; one tile visit
        then sums 16 points in vector lanes).  Only points with identical Morton keys at
        full depth can exceed it.
    kernel_sigma_mm : float, optional
        The points' reconstruction width (``SurfacePoints.info["kernel_sigma_mm"]``), kept in
        ``info`` for :func:`gather`; None: derived there from the mean area.

    Returns
    -------
    Octree
        See :class:`Octree`; nodes in depth-first pre-order with skip links.

    Notes
    -----
    Level by level, vectorised: at depth L a node is a run of points sharing the top 3L
    Morton bits whose parent held more than ``leaf_size`` points.
    """
    t0 = time.perf_counter()
    if int(leaf_size) < 1:
        raise DermisError(f"gather: leaf_size = {leaf_size}: must be >= 1")
    leaf_size = int(leaf_size)
    p, a, e = _check_points(positions, areas, irradiance)
    n = len(p)
    lo = p.min(axis=0)
    size = float((p.max(axis=0) - lo).max())
    keys = _morton_keys(p, lo, size)
    order = np.argsort(keys, kind="stable")
    keys, p, a, e = keys[order], p[order], a[order], e[order]
    start, end, depth = _node_ranges(keys, leaf_size)
    k = len(start)
    skip = np.searchsorted(start, end, side="left").astype(np.int64)
    # nodes with the same start and a deeper level come first in `start` order only after
    # the shallower one; searchsorted(side=left) finds the shallowest node starting at `end`
    is_leaf = skip == np.arange(1, k + 1)
    area, ea_sum, position, cov = _node_moments(p, a, e, start, end)
    bmin, bmax, radius = _node_bounds(p, position, start, end, depth)
    # float32 rounding of positions/radius must never exclude a point from its sphere
    radius = radius * (1 + 1e-5) + 1e-6 * max(size, 1e-30)

    info = {"points": n, "nodes": k, "leaves": int(is_leaf.sum()), "max_depth": int(depth.max()),
            "max_leaf_points": int((end - start)[is_leaf].max()), "leaf_size": leaf_size,
            "kernel_sigma_mm": None if kernel_sigma_mm is None else float(kernel_sigma_mm),
            "seconds": time.perf_counter() - t0}
    return Octree(
        position=position.astype(np.float32), area=area, ea_sum=ea_sum,
        bbox_min=bmin.astype(np.float32), bbox_max=bmax.astype(np.float32),
        radius=radius.astype(np.float32), covariance=cov,
        skip=np.append(skip, k + 1).astype(np.int32), start=np.append(start, n).astype(np.int32),
        depth=depth, is_leaf=is_leaf, order=order, positions=p.astype(np.float32),
        irradiance=e.astype(np.float32), areas=a.astype(np.float32), leaf_size=leaf_size,
        info=info)


def _node_ranges(keys: np.ndarray, leaf_size: int):
    """Octree nodes over Morton-sorted keys as point ranges [start, end) with their depth, in
    depth-first pre-order (sorted by (start, depth)).  Level by level: the children of a range
    holding more than ``leaf_size`` points are its runs of equal Morton prefix one level down;
    chains of single children with the same points collapse to their shallowest node."""
    n = len(keys)
    starts_all, ends_all, depth_all = [], [], []
    active_starts = np.array([0], np.int64)
    active_ends = np.array([n], np.int64)
    for depth in range(MORTON_BITS + 1):
        if depth == 0:
            s, t = active_starts, active_ends
        else:
            # children of the active (split) ranges: runs of equal prefix inside each range
            shift = np.uint64(3 * (MORTON_BITS - depth))
            idx = _ranges(active_starts, active_ends)
            pref = keys[idx] >> shift
            brk = np.ones(len(idx), bool)
            brk[1:] = (pref[1:] != pref[:-1]) | (idx[1:] != idx[:-1] + 1)
            first = np.flatnonzero(brk)
            s = idx[first]
            t = idx[np.append(first[1:], len(idx)) - 1] + 1  # one past each run's last point
        starts_all.append(s)
        ends_all.append(t)
        depth_all.append(np.full(len(s), depth, np.int32))
        split = (t - s) > leaf_size
        if depth == MORTON_BITS or not split.any():
            break
        active_starts, active_ends = s[split], t[split]

    start = np.concatenate(starts_all)
    end = np.concatenate(ends_all)
    depth = np.concatenate(depth_all)
    dfs = np.lexsort((depth, start))
    start, end, depth = start[dfs], end[dfs], depth[dfs]
    # a node whose points all share the next Morton digit has one child with the same
    # points: keep only the shallowest node of such a chain (the walk would visit each)
    keep = np.ones(len(start), bool)
    keep[1:] = (start[1:] != start[:-1]) | (end[1:] != end[:-1])
    return start[keep], end[keep], depth[keep]


def _node_moments(p, a, e, start, end):
    """Per-node area, sum of E A, position and positional covariance (float64), from prefix
    sums over the sorted points: irradiance-weighted (weights E A summed over channels), area-
    weighted where a node is dark, the plain mean where it has no area either."""
    n = len(p)
    # coordinates centred first so the float64 second moments do not cancel
    centre = p.mean(axis=0)
    pc = p - centre
    ca = np.concatenate([[0.0], np.cumsum(a)])
    cea = np.vstack([np.zeros((1, 3)), np.cumsum(e * a[:, None], axis=0)])
    area = ca[end] - ca[start]
    ea_sum = cea[end] - cea[start]
    w = (e * a[:, None]).sum(axis=1)
    wsum = np.concatenate([[0.0], np.cumsum(w)])
    rel = (wsum[end] - wsum[start]) > 1e-12 * max(float(wsum[-1]), 1e-300)
    mean_w, cov_w = _weighted_moments(pc, w, start, end)
    mean_a, cov_a = _weighted_moments(pc, a, start, end)
    mean_1, cov_1 = _weighted_moments(pc, np.ones(n), start, end)
    has_a = area > 0
    position = np.where(rel[:, None], mean_w, np.where(has_a[:, None], mean_a, mean_1))
    cov = np.where(rel[:, None], cov_w, np.where(has_a[:, None], cov_a, cov_1))
    cov[:, [0, 3, 5]] = np.maximum(cov[:, [0, 3, 5]], 0.0)
    return area, ea_sum, position + centre, cov


def _node_bounds(p, position, start, end, depth):
    """Per-node bounding box and bounding-sphere radius about ``position`` (float64), level by
    level (the ranges at one depth are disjoint)."""
    k = len(start)
    bmin = np.empty((k, 3))
    bmax = np.empty((k, 3))
    radius = np.empty(k)
    pad = np.vstack([p, p[-1:]])  # reduceat needs indices < len
    for dl in np.unique(depth):
        sel = np.flatnonzero(depth == dl)
        s, t = start[sel], end[sel]
        ind = np.empty(2 * len(sel), np.int64)
        ind[0::2], ind[1::2] = s, t
        bmin[sel] = np.minimum.reduceat(pad, ind, axis=0)[0::2]
        bmax[sel] = np.maximum.reduceat(pad, ind, axis=0)[0::2]
        owner = np.repeat(np.arange(len(sel)), t - s)
        pts = _ranges(s, t)
        d = np.linalg.norm(p[pts] - position[sel][owner], axis=1)
        radius[sel] = np.maximum.reduceat(np.append(d, 0.0), np.cumsum(np.r_[0, t - s])[:-1])
    return bmin, bmax, radius


def _weighted_moments(p, w, start, end):
    """Weighted mean (K, 3) and covariance (K, 6: xx xy xz yy yz zz) of point runs."""
    def run_sum(x):
        c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)], axis=0)
        return c[end] - c[start]
    ws = run_sum(w)
    safe = np.where(ws > 0, ws, 1.0)
    mean = run_sum(p * w[:, None]) / safe[:, None]
    pairs = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    second = run_sum(np.stack([p[:, i] * p[:, j] for i, j in pairs], axis=1) * w[:, None])
    cov = second / safe[:, None] - np.stack([mean[:, i] * mean[:, j] for i, j in pairs], axis=1)
    return mean, cov


def _ranges(s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s_i, t_i) for all i, vectorised."""
    lens = t - s
    total = int(lens.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offs = np.repeat(s - np.cumsum(np.r_[0, lens[:-1]]), lens)
    return np.arange(total, dtype=np.int64) + offs


# ----------------------------------------------------------------------------- profile table
# Gaussian tail kept by the blurred profile, in sigma: each channel's cut-off grows by this
# much (2-D mass beyond 4 sigma is e^-8 = 3e-4, and the energy normalisation puts it back).
BLUR_REACH = 4.0
# Most grid points of the host convolution (row blocks of 512 x M float64 kernel values).
BLUR_MAX_N = 4000


def kernel_sigma(octree: Octree) -> float:
    """The octree's reconstruction width: ``info["kernel_sigma_mm"]`` if set, else
    ``samples.KERNEL_SIGMA_FACTOR`` x sqrt(total area / N) (the spacing)."""
    s = octree.info.get("kernel_sigma_mm")
    if s is not None:
        return float(s)
    from dermis.stages.samples import KERNEL_SIGMA_FACTOR
    return KERNEL_SIGMA_FACTOR * math.sqrt(float(octree.area[0]) / max(len(octree.areas), 1))


def blurred_profile(r: np.ndarray, R: np.ndarray, sigma: float, r_max: float):
    """The radial profile convolved (2-D) with a normalised Gaussian of width sigma, float64.

    (R * G)(r) = int_0^inf R(s) (s / sigma^2) exp(-(r - s)^2 / (2 sigma^2)) I0e(r s / sigma^2) ds
    (the angular integral of the 2-D Gaussian is the Bessel I0; I0e keeps it finite), by the
    trapezoid rule on a uniform grid of step <= sigma / 8 and <= the profile's own step,
    with R linear between its samples.  Returns (grid (M,), blurred (M, 3)) on [0, r_max].
    """
    from scipy.special import i0e
    step = min(sigma / 8.0, float(np.min(np.diff(r))))
    step = max(step, (r_max + BLUR_REACH * sigma) / (BLUR_MAX_N - 1))
    g = np.arange(0.0, r_max + 0.5 * step, step)
    s = np.arange(0.0, min(float(r[-1]), r_max + BLUR_REACH * sigma) + 0.5 * step, step)
    Rs = np.stack([np.interp(s, r, R[:, c], right=0.0) for c in range(R.shape[1])], axis=1)
    wt = np.full(len(s), step)
    wt[0] = wt[-1] = 0.5 * step
    out = np.empty((len(g), R.shape[1]))
    inv = 1.0 / (sigma * sigma)
    for b in range(0, len(g), 512):  # row blocks bound the memory
        gg = g[b:b + 512, None]
        ker = (s * inv) * np.exp(-0.5 * inv * (gg - s) ** 2) * i0e(gg * s * inv) * wt
        out[b:b + 512] = ker @ Rs
    return g, out


def profile_table(profile, *, normalisation: str = "energy", cutoff_mm: float | None = None,
                  n: int = TABLE_N, sigma_mm: float = 0.0, taylor: bool = False):
    """Uniform device tables: R(r) (float32 (n, 4)), step h (mm), cut-off (mm), and the
    derivative terms (R'' - R'/r, R'/r) interleaved (float32 (2 n, 4)).

    Each channel is zero beyond its own cut-off (``profile.cutoff_mm``, or ``cutoff_mm`` for
    all channels).  With ``sigma_mm`` > 0 the profile is first convolved with a 2-D
    Gaussian of that width (:func:`blurred_profile`; module docstring) and every cut-off
    grows by ``BLUR_REACH`` sigma.  In "energy" mode each channel is scaled so that the
    exact integral of the piecewise-linear table, int 2 pi r R dr, equals ``profile.Rd``.
    """
    r = np.asarray(profile.r_mm, np.float64)
    R = np.asarray(profile.R, np.float64)
    rd = np.asarray(profile.Rd, np.float64)
    if r.ndim != 1 or R.shape != (len(r), 3) or len(r) < 2:
        raise DermisError(f"gather: profile r_mm {r.shape} / R {R.shape} must be (N,) and (N, 3)")
    if not (np.isfinite(R).all() and np.isfinite(rd).all()):
        raise DermisError("gather: the layer profile contains NaN or infinity")
    if not (sigma_mm >= 0 and math.isfinite(sigma_mm)):
        raise DermisError(f"gather: kernel_sigma_mm = {sigma_mm}: must be a finite number >= 0")
    cut = (np.full(3, float(cutoff_mm)) if cutoff_mm is not None
           else np.asarray(profile.cutoff_mm, np.float64))
    cut = np.where(cut > 0, cut, 0.0)
    if sigma_mm > 0:
        cut = np.where(cut > 0, cut + BLUR_REACH * sigma_mm, 0.0)
        r, R = blurred_profile(r, R, float(sigma_mm), float(cut.max()))
    cmax = float(cut.max())
    if not cmax > 0:
        raise DermisError(f"gather: profile cut-off {cut.tolist()} mm: needs one > 0")
    h = cmax / (n - 2)  # entries n-2 and n-1 lie at/after the largest cut-off: zero
    rr = np.arange(n) * h
    tab = np.zeros((n, 4))
    for c in range(3):
        tab[:, c] = np.interp(rr, r, R[:, c], right=0.0)
        tab[rr > cut[c], c] = 0.0
    tab[-2:, :3] = 0.0
    scale = np.ones(3)
    if normalisation == "energy":
        # exact integral of 2 pi r (a + b r) on each segment of the piecewise-linear table
        r0, r1 = rr[:-1], rr[1:]
        for c in range(3):
            y0, y1 = tab[:-1, c], tab[1:, c]
            slope = (y1 - y0) / h
            seg = 2 * np.pi * ((y0 - slope * r0) * (r1**2 - r0**2) / 2 + slope * (r1**3 - r0**3) / 3)
            total = seg.sum()
            if total > 0:
                scale[c] = rd[c] / total
                tab[:, c] *= scale[c]
    # derivatives for the second-order cluster term, from central differences on the
    # profile's own grid (smoother than differentiating the piecewise-linear table twice),
    # scaled like the table, zero beyond each channel's cut-off
    deriv = np.zeros((n, 2, 4))
    for c in range(3):
        d1 = np.gradient(R[:, c], r)
        d2 = np.gradient(d1, r)
        r1 = np.interp(rr, r, d1) * scale[c]
        r2 = np.interp(rr, r, d2) * scale[c]
        inside = (rr <= cut[c]) & (rr > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            deriv[:, 0, c] = np.where(inside, r2 - r1 / rr, 0.0)
            deriv[:, 1, c] = np.where(inside, r1 / rr, 0.0)
    deriv[-2:] = 0.0
    if taylor:
        # R, R', R''/2 and d3R/dr3 / 6 for gather_tile_v's 1-D Taylor expansion (same grid and
        # scale), and the quartic coefficient d4R/dr4 / 24 per channel in the .w of rows 0-2
        tay = np.zeros((n, 4, 4))
        tay[:, 0] = tab
        for c in range(3):
            d1 = np.gradient(R[:, c], r)
            d2 = np.gradient(d1, r)
            d3 = np.gradient(d2, r)
            d4 = np.gradient(d3, r)
            inside = rr <= cut[c]
            for o, (dd, fac) in enumerate(((d1, 1.0), (d2, 0.5), (d3, 1.0 / 6.0)), start=1):
                tay[:, o, c] = np.where(inside, np.interp(rr, r, dd) * scale[c] * fac, 0.0)
            # d4R/dr4 / 24 of channel c in the spare .w of float4 c (cl: QUARTIC)
            tay[:, c, 3] = np.where(inside, np.interp(rr, r, d4) * scale[c] / 24.0, 0.0)
        tay[-2:] = 0.0
        return (tab.astype(np.float32), h, cmax, deriv.reshape(2 * n, 4).astype(np.float32),
                tay.reshape(4 * n, 4).astype(np.float32))
    return tab.astype(np.float32), h, cmax, deriv.reshape(2 * n, 4).astype(np.float32)


# ----------------------------------------------------------------------------- gather
def gather(octree: Octree, profile, query_positions: np.ndarray, *, epsilon: float | None,
           normalisation: str = "energy", env=None, brute_force: bool = False, progress=None,
           tuning: GatherTuning = GatherTuning(), part: str = "all") -> tuple[np.ndarray, dict]:
    """Radiant exitance M_o at query points from the octree's irradiance points.

    Parameters
    ----------
    octree : Octree
        From :func:`build_octree`.
    profile : LayerProfile
        r_mm (N,), R (N, 3) in 1/mm^2, Rd (3,), cutoff_mm (3,) (``stages/profiles.py``).
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
    from dermis.pipeline.cl import event_seconds, get_env

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
    from dermis.pipeline.cl import to_device

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
    from dermis.pipeline.cl import to_device

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
    from dermis.pipeline.cl import to_device

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
    from dermis.pipeline.cl import to_device

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


# ----------------------------------------------------------------------------- near field
# The optics-resolved BSSRDF (docs/science.md §4 "Near field").  The points reconstruct
# irradiance at the resolution sigma of their spacing, far coarser than the skin's profile
# (two_layer: half of Rd within 0.17-0.5 mm, sigma 1.24 mm at the default density), so the
# gather alone blurs the image by sigma.  The profile is split by a smooth window w(r)
# (1 inside NEAR_INNER sigma, a raised cosine down to 0 at NEAR_OUTER sigma): the far part
# R (1 - w) is smooth at the points' resolution and is gathered from them (blurred by sigma:
# the knife-edge error of that is <= 1.1 % of Rd at these radii), and
# the near part R w is evaluated at each shading point.  For point and directional lights
# (one sample per point: every point and pixel sees the same shadow curve) the near part is
# exact: M_near(x) = C(x) [Rd_near V(x) - sum over the shadow edges within NEAR_OUTER sigma
# of a boundary integral], with C(x) the light's entering irradiance at the shading point
# unshadowed, V(x) its shadow ray, and the edges located between the points by bisection
# (:func:`shadow_edges`).  Disc and environment lights (per-point random samples: no
# common shadow curve) keep the points' reconstruction for the near part too.
# Window radii in sigma, measured with the knife edge (tests/test_knife_edge.py, 1.25 mm
# spacing, worst channel of skin1 / skin2): (1.5, 3.0) 1.43 / 1.18 %, (2.0, 3.5) 1.07 /
# 0.92 %, (2.0, 4.0) 0.87 / 0.75 %.  The far part's blur is the error; a wider window leaves
# more of the profile to the shading point, where (for point and directional lights) the
# unshadowed irradiance is taken at the point itself, so fine geometric shading is not
# blurred within it; (2.0, 3.5) halves the far error for 1.2x the window.
NEAR_INNER = 2.0
NEAR_OUTER = 3.5
# Light types whose near field is resolved at the shading point.
SHARP_LIGHTS = ("point", "directional")
# Gathers kept per run by :func:`exitance` for reuse: the same points, irradiance, profile and
# query positions give the same exitance, and the low mesh's two bump variants of a lighting
# condition shade the same positions (the bump moves normals only) and run together.  Each
# is a (Q, 3) float32 array, ~30 MB at 800 x 800 x 4 spp; 4 hold a condition's far and soft
# parts for two profiles.
SHARED_GATHERS = 4
# Boundary-integral table Q(omega, phi): omega in [0, NEAR_OUTER sigma], phi in [0, pi/2].
EDGE_TABLE_OMEGA = 512
EDGE_TABLE_PHI = 256
# Shadow-edge search between the points: neighbour pairs closer than PAIR_RADIUS x spacing
# whose normals agree (dot > PAIR_MIN_DOT: the same side of a thin part) and whose shadow
# rays disagree are bisected EDGE_BISECTIONS times along their chord (re-projected onto
# the surface each step): 12 halvings of <= 2 spacings locate the edge to spacing / 2048
# (0.6 um at 1.24 mm; the knife-edge test needs ~7 um for two_layer blue).
PAIR_RADIUS = 2.0
PAIR_MIN_DOT = 0.5
EDGE_BISECTIONS = 12
# Each crossing owns a straight segment of the edge: its direction from the crossings
# among its EDGE_NEIGHBOURS nearest (principal axis in the tangent plane), its extent the
# 1-D Voronoi cell of the crossings along it (so a straight edge is tiled exactly), capped
# at EDGE_END_CAP x spacing where no neighbour follows (the end of an edge).
EDGE_NEIGHBOURS = 16
EDGE_END_CAP = 0.5
# Shading points closer than EDGE_ON_LINE x the bisection's precision to a located edge take
# their side of it from the edge, not from their own shadow ray (:func:`edge_sum`).
EDGE_ON_LINE = 8.0


@dataclass
class ProfileSplit:
    """The profile split at the near-field window (:func:`split_profile`).

    near, far : profile-like objects (``r_mm``, ``R``, ``Rd``, ``cutoff_mm``) of R w and
        R (1 - w), canonical (linear in r, zero beyond each cut-off, energy-normalised)
    rd_near : (3,) energy of the near part; far.Rd = Rd - rd_near
    r_in, r_out : the window's radii, mm
    cum_near : (r (M,), m (M, 3)) cumulative energy of the near part int_0^r 2 pi s R w ds
    """

    near: object
    far: object
    rd_near: np.ndarray
    r_in: float
    r_out: float
    cum_near: tuple


@dataclass
class _PartProfile:
    r_mm: np.ndarray
    R: np.ndarray
    Rd: np.ndarray
    cutoff_mm: np.ndarray


def near_window(r: np.ndarray, r_in: float, r_out: float) -> np.ndarray:
    """w(r): 1 for r <= r_in, a raised cosine down to 0 at r_out, 0 beyond."""
    u = np.clip((np.asarray(r, np.float64) - r_in) / max(r_out - r_in, 1e-300), 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * u))


def split_profile(profile, sigma_mm: float, *, cutoff_mm: float | None = None,
                  inner: float = NEAR_INNER, outer: float = NEAR_OUTER) -> ProfileSplit:
    """Split the layer profile into near and far parts about the window at ``inner`` ..
    ``outer`` x ``sigma_mm`` (module section "near field").

    The profile is first made canonical exactly as the gather integrates it: R linear in r
    on a grid 4x finer than the layer file's (and <= r_out / 1000), each channel zero beyond
    its cut-off (``profile.cutoff_mm`` or ``cutoff_mm``) and scaled so int 2 pi r R dr = Rd.
    """
    r0 = np.asarray(profile.r_mm, np.float64)
    R0 = np.asarray(profile.R, np.float64)
    rd = np.asarray(profile.Rd, np.float64)
    cut = (np.full(3, float(cutoff_mm)) if cutoff_mm is not None
           else np.asarray(profile.cutoff_mm, np.float64))
    r_in, r_out = inner * float(sigma_mm), outer * float(sigma_mm)
    top = max(float(cut.max()), r_out)
    step = min(float(np.min(np.diff(r0))) / 4.0, r_out / 1000.0)
    r = np.arange(0.0, top + 0.5 * step, step)
    R = np.stack([np.interp(r, r0, R0[:, c], right=0.0) for c in range(3)], axis=1)
    R[r[:, None] > cut[None, :]] = 0.0
    ring = 2.0 * np.pi * r[:, None] * R
    total = np.trapezoid(ring, r, axis=0)
    R *= np.where(total > 0, rd / np.where(total > 0, total, 1.0), 0.0)
    w = near_window(r, r_in, r_out)[:, None]
    Rn, Rf = R * w, R * (1.0 - w)
    seg = 0.5 * (2.0 * np.pi * (r[1:, None] * Rn[1:] + r[:-1, None] * Rn[:-1])) * step
    cum = np.vstack([np.zeros((1, 3)), np.cumsum(seg, axis=0)])
    rd_near = cum[-1].copy()
    near = _PartProfile(r, Rn, rd_near, np.minimum(cut, r_out))
    far = _PartProfile(r, Rf, np.maximum(rd - rd_near, 0.0), cut)
    return ProfileSplit(near, far, rd_near, r_in, r_out, (r, cum))


@dataclass
class EdgeTable:
    """Q(omega, phi) = 1/(2 pi) int_0^phi m_K(omega / cos t) dt per channel, with
    m_K(r) = Rd_near - (near energy within r): the boundary integral over a straight edge
    segment seen from a point at distance omega from its line is
    sign(w) [Q(omega, phi_2) - Q(omega, phi_1)] (:func:`near_tables`)."""

    q: np.ndarray            # (EDGE_TABLE_OMEGA + 1, EDGE_TABLE_PHI + 1, 3) float64
    d_omega: float
    d_phi: float
    rd_near: np.ndarray
    r_out: float
    mk: np.ndarray | None = None   # (EDGE_TABLE_OMEGA + 1, 3) m_K(k d_omega), for the device

    def lookup(self, omega: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Q at (omega >= 0, phi in [-pi/2, pi/2]), bilinear, odd in phi; 0 beyond r_out.
        (M, 3) float32 (the table's values are exact to float64; the lookup's rounding,
        ~1e-7 of Rd, is far below the tests' tolerance)."""
        no, nphi = self.q.shape[0] - 1, self.q.shape[1] - 1
        if getattr(self, "_flat", None) is None:
            self._flat = np.ascontiguousarray(self.q.reshape(-1, 3), np.float32)
        a = np.clip(np.asarray(omega, np.float32) * np.float32(1.0 / self.d_omega), 0, no)
        b = np.clip(np.abs(np.asarray(phi, np.float32)) * np.float32(1.0 / self.d_phi), 0, nphi)
        i = np.minimum(a.astype(np.int32), no - 1)
        j = np.minimum(b.astype(np.int32), nphi - 1)
        fa, fb = (a - i)[:, None], (b - j)[:, None]
        k = i * np.int32(nphi + 1) + j
        q = self._flat
        v00, v01 = q.take(k, axis=0), q.take(k + 1, axis=0)
        v10, v11 = q.take(k + (nphi + 1), axis=0), q.take(k + (nphi + 2), axis=0)
        v01 -= v00
        v01 *= fb
        v00 += v01          # row omega_i at phi
        v11 -= v10
        v11 *= fb
        v10 += v11          # row omega_i+1 at phi
        v10 -= v00
        v10 *= fa
        v00 += v10
        v00 *= np.sign(phi).astype(np.float32)[:, None]
        return v00


def near_tables(split: ProfileSplit) -> EdgeTable:
    """The boundary-integral table of the near part (docs/science.md §4 "Near field").

    For the lit region Omega around a shading point x, int_Omega R_near(|x - y|) dy =
    Rd_near 1_Omega(x) - int_Omega K(x - y) dy with K = Rd_near delta - R_near, and the
    divergence theorem turns the last integral into a line integral over the shadow edges of
    the field v m_K(|v|) / (2 pi |v|^2), m_K(r) = Rd_near - m_near(r): zero beyond r_out, so
    only edges within r_out of x count.  Along a straight segment at signed distance w from
    x, t = |w| tan(phi) makes the integrand sign(w) m_K(|w| / cos phi) / (2 pi) dphi.
    """
    r, cum = split.cum_near
    rd_n = split.rd_near
    no, nphi, sub = EDGE_TABLE_OMEGA, EDGE_TABLE_PHI, 4
    omega = np.linspace(0.0, split.r_out, no + 1)
    phi = np.linspace(0.0, 0.5 * np.pi, nphi * sub + 1)
    cosphi = np.cos(phi)
    q = np.zeros((no + 1, nphi + 1, 3))
    for c in range(3):
        mk_r = rd_n[c] - cum[:, c]
        with np.errstate(divide="ignore"):
            rr = omega[:, None] / cosphi[None, :]
        rr[0] = 0.0
        mk = np.interp(rr.ravel(), r, mk_r, right=0.0).reshape(rr.shape)
        mk[0, -1] = mk[0, -2]
        mk[1:, -1] = 0.0
        integ = np.concatenate([np.zeros((no + 1, 1)), np.cumsum(
            0.5 * (mk[:, 1:] + mk[:, :-1]) * (phi[1] - phi[0]), axis=1)], axis=1)
        q[:, :, c] = integ[:, ::sub] / (2.0 * np.pi)
    q[-1] = 0.0  # omega = r_out: nothing of the near part reaches past the edge line
    mk = np.stack([np.interp(omega, r, rd_n[c] - cum[:, c], right=0.0) for c in range(3)], 1)
    mk[-1] = 0.0
    return EdgeTable(q, float(omega[1] - omega[0]), float(0.5 * np.pi / nphi), rd_n,
                     split.r_out, mk)


@dataclass
class ShadowEdges:
    """The shadow edges of one point or directional light on a point set, as straight
    segments ``origin + t tangent``, t in [lo, hi] (:func:`shadow_edges`).

    origin, tangent, outward, normal : (K, 3) crossing point, unit edge direction, unit
        in-surface normal of the edge pointing from the lit to the shadowed side, surface
        normal
    lo, hi : (K,) segment extent along ``tangent``, mm
    irradiance : (N, 3) float32 the light's entering irradiance at the points (what
        :func:`lighting.lights.irradiance` gives for this light alone)
    info : dict (pairs tested, crossings, seconds)
    """

    origin: np.ndarray
    tangent: np.ndarray
    outward: np.ndarray
    normal: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    irradiance: np.ndarray
    info: dict = field(default_factory=dict)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _lit(light, visibility, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(M,) bool: the light's one sample faces the normal and its shadow ray is free."""
    from dermis.lighting.lights import sample_lights
    ls = sample_lights(light, p, n)
    wi, wt, dist = ls.directions[:, 0], ls.weights[:, 0], ls.distance[:, 0]
    ok = (np.einsum("ij,ij->i", wi, n) > 0) & (wt.sum(axis=1) > 0)
    out = np.zeros(len(p), bool)
    if ok.any():
        out[ok] = ~visibility.occluded(p[ok], n[ok], wi[ok], dist[ok])
    return out


def _project(visibility, p: np.ndarray, n: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Points ``p`` moved onto the surface along their normal ``n`` (a ray from p + h n
    towards -n; kept where it misses or lands farther than 2 h)."""
    origins = (p + h[:, None] * n).astype(np.float32)
    hits = visibility.intersect(origins, (-n).astype(np.float32))
    t = hits.t.astype(np.float64)
    ok = hits.hit & (t < 2.0 * h)
    return np.where(ok[:, None], origins - t[:, None] * n, p)


def shadow_edges(positions, normals, light, visibility, spacing_mm: float, *,
                 transmittance=None, irradiance: np.ndarray | None = None) -> ShadowEdges:
    """The shadow edges of a point or directional light between irradiance points.

    Parameters
    ----------
    positions, normals : (N, 3) float, the points (``SurfacePoints``) and their unit normals
    light : LightConfig of type "point" or "directional"
    visibility : lighting.visibility.Visibility of the mesh
    spacing_mm : float, the points' spacing (pairs closer than PAIR_RADIUS x it are tested)
    transmittance : callable, optional, the entry transmittance (``Transmittance``)
    irradiance : (N, 3) float, optional
        This light's entering irradiance at the points when already known (a lighting
        condition of this one light: the irradiance stage's); else computed here.

    Returns
    -------
    ShadowEdges (module section "near field" for the construction).
    """
    from scipy.spatial import cKDTree
    from dermis.lighting.lights import irradiance as point_irradiance, sample_lights

    t0 = time.perf_counter()
    if light.type not in SHARP_LIGHTS:
        raise DermisError(f"gather: shadow edges need a point or directional light, not "
                          f"{light.type!r} ({light.name})")
    p = np.asarray(positions, np.float64)
    n = _unit(np.asarray(normals, np.float64))
    if irradiance is not None:
        e = np.asarray(irradiance, np.float32)
    else:
        e = point_irradiance(p.astype(np.float32), n.astype(np.float32), [light],
                             visibility.occluded, transmittance=transmittance)
    ls = sample_lights(light, p.astype(np.float32), n.astype(np.float32))
    facing = (np.einsum("ij,ij->i", ls.directions[:, 0], n) > 0) & (ls.weights[:, 0].sum(1) > 0)
    lit = e.sum(axis=1) > 0
    s = float(spacing_mm)
    lit_i = np.flatnonzero(facing & lit)
    dark_i = np.flatnonzero(facing & ~lit)
    n_pairs = 0
    if len(lit_i) and len(dark_i):
        sdm = cKDTree(p[lit_i]).sparse_distance_matrix(cKDTree(p[dark_i]), PAIR_RADIUS * s,
                                                       output_type="ndarray")
        a, b = lit_i[sdm["i"]], dark_i[sdm["j"]]   # lit end, shadowed end
        n_pairs = len(a)
        agree = np.einsum("ij,ij->i", n[a], n[b]) > PAIR_MIN_DOT
        a, b = a[agree], b[agree]
    else:
        a = b = np.zeros(0, np.int64)
    pa, na, pb, nb = p[a], n[a], p[b], n[b]
    d0 = pb - pa
    for _ in range(EDGE_BISECTIONS):
        nm = _unit(na + nb)
        pm = _project(visibility, 0.5 * (pa + pb), nm, 0.5 * np.linalg.norm(pb - pa, axis=1) + 1e-6)
        ok = _lit(light, visibility, pm, nm) if len(pm) else np.zeros(0, bool)
        pa = np.where(ok[:, None], pm, pa)
        na = np.where(ok[:, None], nm, na)
        pb = np.where(ok[:, None], pb, pm)
        nb = np.where(ok[:, None], nb, nm)
    origin = 0.5 * (pa + pb)
    normal = _unit(na + nb)
    k = len(origin)
    empty = np.zeros((0, 3))
    if k == 0:
        return ShadowEdges(empty, empty, empty, empty, np.zeros(0), np.zeros(0), e,
                           {"pairs": n_pairs, "crossings": 0, "precision_mm": 0.0,
                            "seconds": time.perf_counter() - t0})
    d0 = d0 - np.einsum("ij,ij->i", d0, normal)[:, None] * normal   # in the tangent plane
    kk = min(EDGE_NEIGHBOURS, k)
    _, idx = cKDTree(origin).query(origin, k=kk)
    idx = idx.reshape(k, kk)
    off = origin[idx] - origin[:, None, :]
    off = off - np.einsum("kmj,kj->km", off, normal)[..., None] * normal[:, None, :]
    near = np.linalg.norm(off, axis=2) < PAIR_RADIUS * s
    tangent = _principal(off, near, normal, d0)
    outward = _unit(np.cross(normal, tangent))
    flip = np.einsum("ij,ij->i", outward, d0) < 0
    outward[flip] *= -1.0
    # second pass: only crossings of the same edge (same lit side, on its line) count
    same = (near & (np.einsum("kmj,kj->km", outward[idx], outward) > 0.5)
            & (np.abs(np.einsum("kmj,kj->km", off, outward)) < 0.5 * s))
    tangent = _principal(off, same, normal, d0)
    outward = _unit(np.cross(normal, tangent))
    flip = np.einsum("ij,ij->i", outward, d0) < 0
    outward[flip] *= -1.0
    t = np.einsum("kmj,kj->km", off, tangent)
    # ties (t == 0, e.g. the crossing itself) go to the side of the lower index
    rank = idx < np.arange(k)[:, None]
    neg = same & ((t < 0) | ((t == 0) & rank)) & (idx != np.arange(k)[:, None])
    pos = same & ((t > 0) | ((t == 0) & ~rank)) & (idx != np.arange(k)[:, None])
    cap = EDGE_END_CAP * s
    lo = np.maximum(np.where(neg, t, -np.inf).max(axis=1) / 2.0, -cap)
    hi = np.minimum(np.where(pos, t, np.inf).min(axis=1) / 2.0, cap)
    info = {"pairs": n_pairs, "crossings": int(k),
            "edge_length_mm": float((hi - lo).sum()),
            "precision_mm": PAIR_RADIUS * s / 2 ** EDGE_BISECTIONS,
            "seconds": time.perf_counter() - t0}
    return ShadowEdges(origin, tangent, outward, normal, lo, hi, e, info)


def _principal(off: np.ndarray, mask: np.ndarray, normal: np.ndarray,
               crossing: np.ndarray) -> np.ndarray:
    """Unit principal direction (in the tangent plane) of the masked offsets of each row;
    where fewer than two offsets count, the direction across ``crossing``."""
    m = mask[..., None].astype(np.float64)
    cnt = mask.sum(axis=1)
    mean = (off * m).sum(axis=1) / np.maximum(cnt, 1)[:, None]
    dev = (off - mean[:, None, :]) * m
    cov = np.einsum("kmi,kmj->kij", dev, dev)
    _, vec = np.linalg.eigh(cov)
    tan = vec[:, :, -1]
    fallback = _unit(np.cross(normal, crossing))
    spread = np.einsum("kmj,kj->km", dev, tan)
    weak = (cnt < 2) | (np.abs(spread).max(axis=1) <= 0)
    tan = np.where(weak[:, None], fallback, tan)
    tan = tan - np.einsum("ij,ij->i", tan, normal)[:, None] * normal
    return _unit(tan)


def edge_sum(queries: np.ndarray, normals: np.ndarray, edges: ShadowEdges,
             table: EdgeTable, *, on_edge_mm: float = 0.0,
             tree=None) -> tuple[np.ndarray, np.ndarray]:
    """Sum over the segments within r_out of each query of the boundary integral
    sign(w) [Q(|w|, phi_2) - Q(|w|, phi_1)] (:func:`near_tables`), and which side of an
    edge each query lies on where it is within ``on_edge_mm`` of a segment's line (inside
    its extent): +1 lit, -1 shadowed, 0 farther.  The shadow ray of such a query cannot be
    trusted to agree with the located edge (its position is known to ~spacing / 2048), and
    the near field jumps by Rd_near there unless the two agree.
    ``tree``: a scipy cKDTree of ``queries`` to reuse.
    Returns ((Q, 3) float64, (Q,) int8)."""
    from scipy.spatial import cKDTree
    x = np.asarray(queries, np.float64)
    out = np.zeros((len(x), 3))
    side = np.zeros(len(x), np.int8)
    if len(edges.origin) == 0 or len(x) == 0:
        return out, side
    half = 0.5 * (edges.hi - edges.lo)
    centre = edges.origin + (0.5 * (edges.hi + edges.lo))[:, None] * edges.tangent
    tree = cKDTree(x) if tree is None else tree
    lists = tree.query_ball_point(centre, table.r_out + half, return_sorted=False)
    cnt = np.fromiter((len(l) for l in lists), np.int64, len(lists))
    if cnt.sum() == 0:
        return out, side
    seg = np.repeat(np.arange(len(lists), dtype=np.int32), cnt)
    px = np.concatenate([np.asarray(l, np.int32) for l in lists])
    # float32 per pair: w and t0 are differences of ~100 mm coordinates, exact to ~1e-5 mm
    nrm = np.asarray(normals, np.float32)
    good = np.einsum("ij,ij->i", nrm[px], edges.normal[seg].astype(np.float32)) > 0.5
    seg, px = seg[good], px[good]
    xf = x.astype(np.float32)[px]
    # w = (e - x).n_out and t0 = (x - e).tangent, from per-segment constants e.n_out, e.tangent
    ew = np.einsum("ij,ij->i", edges.origin, edges.outward).astype(np.float32)
    et = np.einsum("ij,ij->i", edges.origin, edges.tangent).astype(np.float32)
    w = ew[seg] - np.einsum("ij,ij->i", xf, edges.outward.astype(np.float32)[seg])
    t0 = np.einsum("ij,ij->i", xf, edges.tangent.astype(np.float32)[seg]) - et[seg]
    del xf
    om = np.abs(w)
    sgn = np.where(w >= 0, np.float32(1), np.float32(-1))   # on the line: counted lit
    lo, hi = edges.lo.astype(np.float32)[seg], edges.hi.astype(np.float32)[seg]
    ph = np.arctan2(np.concatenate([hi - t0, lo - t0]), np.concatenate([om, om]))
    q12 = table.lookup(np.concatenate([om, om]), ph)
    val = q12[:len(om)]
    val -= q12[len(om):]
    val *= sgn[:, None]
    for c in range(3):
        out[:, c] = np.bincount(px, weights=val[:, c], minlength=len(x))
    close = (om <= on_edge_mm) & (t0 >= lo) & (t0 <= hi)
    if close.any():
        side[px[close]] = sgn[close].astype(np.int8)
    return out, side


# Most cells per axis of the device grid of edge segments (edge_sum_cl): the cell grows
# beyond r_out + the longest half-segment when the segments spread wider.
EDGE_GRID_MAX = 128


def edge_sum_cl(queries: np.ndarray, normals: np.ndarray, edges: ShadowEdges,
                table: EdgeTable, env, *, on_edge_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`edge_sum` on the OpenCL device (``cl/bssrdf_gather.cl`` edge_near): the same
    sums in float32, the segments binned in a uniform grid instead of a kd-tree, and
    segments shorter than 0.15 x their distance integrated by the midpoint rule
    (cl EDGE_MIDPOINT; max difference from :func:`edge_sum` 3e-4 of Rd_near,
    tests/test_gather.py test13; on the LPS head with 1M camera samples the kernel took
    ~0.35 s against ~3.6 s for the numpy version, on a loaded machine)."""
    import pyopencl as cl
    from dermis.pipeline.cl import event_seconds, to_device
    x = np.asarray(queries, np.float32)
    nq = len(x)
    if len(edges.origin) == 0 or nq == 0:
        return np.zeros((nq, 3)), np.zeros(nq, np.int8)
    k = len(edges.origin)
    reach = float(np.maximum(np.abs(edges.lo), np.abs(edges.hi)).max())
    lo = edges.origin.min(axis=0)
    ext = edges.origin.max(axis=0) - lo
    cell = max(table.r_out + reach, float(ext.max()) / (EDGE_GRID_MAX - 2)) * (1 + 1e-4) + 1e-6
    dims = np.maximum(np.ceil(ext / cell).astype(np.int64) + 1, 1)
    ijk = np.minimum(((edges.origin - lo) / cell).astype(np.int64), dims - 1)
    cid = (ijk[:, 2] * dims[1] + ijk[:, 1]) * dims[0] + ijk[:, 0]
    order = np.argsort(cid, kind="stable").astype(np.int32)
    start = np.searchsorted(cid[order], np.arange(int(np.prod(dims)) + 1)).astype(np.int32)
    # only queries with a segment in their 27 cells go to the device (half of them on a lit
    # head; the rest would walk empty cells)
    from scipy.ndimage import binary_dilation
    occupied = np.zeros(tuple(dims[::-1] + 2), bool)   # one cell of margin all round
    occupied[ijk[:, 2] + 1, ijk[:, 1] + 1, ijk[:, 0] + 1] = True
    near = binary_dilation(occupied, structure=np.ones((3, 3, 3), bool))
    g = np.floor((x - lo) / cell).astype(np.int64) + 1
    inside = np.all((g >= 0) & (g < dims + 2), axis=1)
    gi = np.clip(g, 0, dims + 1)
    sel = np.flatnonzero(inside & near[gi[:, 2], gi[:, 1], gi[:, 0]])
    s_out = np.zeros((nq, 3))
    side_out = np.zeros(nq, np.int8)
    if len(sel) == 0:
        return s_out, side_out
    x = x[sel]
    normals = np.asarray(normals, np.float32)[sel]
    nq = len(sel)

    def f4(a, w):
        r = np.zeros((len(a), 4), np.float32)
        r[:, :3] = a
        r[:, 3] = w
        return r
    zeros = np.zeros(k)
    q4 = f4(x, 0.0)
    n4 = f4(np.asarray(normals, np.float32), 0.0)
    qt = np.zeros((table.q.shape[0] * table.q.shape[1], 4), np.float32)
    qt[:, :3] = table.q.reshape(-1, 3)
    mk = np.zeros((len(table.mk), 4), np.float32)
    mk[:, :3] = table.mk
    out = np.empty((nq, 4), np.float32)
    d_out = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
    knl = env.kernel("bssrdf_gather.cl", "edge_near", {})
    half = 0.5 * (edges.hi - edges.lo)
    centre = edges.origin + (0.5 * (edges.hi + edges.lo))[:, None] * edges.tangent
    ev = knl(env.queue, _global(nq, 64), _local(64), to_device(env, q4), to_device(env, n4),
             to_device(env, f4(centre, (table.r_out + half) ** 2)),
             to_device(env, f4(edges.origin, edges.lo)), to_device(env, f4(edges.tangent, edges.hi)),
             to_device(env, f4(edges.outward, zeros)), to_device(env, f4(edges.normal, zeros)),
             to_device(env, start), to_device(env, order),
             cl.cltypes.make_float4(*lo.astype(np.float32), np.float32(1.0 / cell)),
             np.int32(dims[0]), np.int32(dims[1]), np.int32(dims[2]), to_device(env, qt),
             np.int32(table.q.shape[0] - 1), np.int32(table.q.shape[1] - 1),
             np.float32(1.0 / table.d_omega), np.float32(1.0 / table.d_phi),
             to_device(env, mk), np.int32(len(mk)), np.float32(1.0 / table.d_omega),
             np.float32(table.r_out), np.float32(on_edge_mm), np.int32(nq), d_out)
    cl.enqueue_copy(env.queue, out, d_out, wait_for=[ev])
    edges.info["kernel_seconds"] = edges.info.get("kernel_seconds", 0.0) + event_seconds([ev])
    s_out[sel] = out[:, :3]
    side_out[sel] = np.rint(out[:, 3]).astype(np.int8)
    return s_out, side_out


def sharp_visibility(samples, hits: np.ndarray, positions: np.ndarray, lights) -> np.ndarray:
    """(Q, number of point/directional lights) bool: which of those lights each hit sees,
    read from the shared visibility artifact (``stages/visibility.py`` PixelSamples: the
    unoccluded light samples of every camera hit, the same shadow rays the BRDF images
    use) instead of tracing them again.  ``hits`` (Q,) index its hits, ``positions`` (Q, 3)
    their surface points.  A hit sees a light when one of its samples points at it."""
    sharp = [l for l in lights if l.type in SHARP_LIGHTS]
    hits = np.asarray(hits, np.int64)
    if not sharp:
        return np.zeros((len(hits), 0), bool)
    counts = np.asarray(samples.counts, np.int64)
    row_hit = np.repeat(np.arange(len(counts)), counts)
    # samples of the queried hits only, and which query each belongs to
    qof = np.full(len(counts), -1, np.int64)
    qof[hits] = np.arange(len(hits))
    keep = qof[row_hit] >= 0
    rows, qi = np.flatnonzero(keep), qof[row_hit[keep]]
    d = np.asarray(samples.directions, np.float64)[rows]
    x = np.asarray(positions, np.float64)[qi]
    out = np.zeros((len(hits), len(sharp)), bool)
    for k, light in enumerate(sharp):
        if light.type == "directional":
            to = np.asarray(light.direction, np.float64)
            to = np.broadcast_to(to / np.linalg.norm(to), d.shape)
        else:
            to = _unit(np.asarray(light.position, np.float64) - x)
        match = np.einsum("ij,ij->i", d, to) > 1.0 - 1e-5
        out[qi[match], k] = True
    return out


def sharp_near_field(queries, shading_normals, geo_normals, light, visibility,
                     edges: ShadowEdges, table: EdgeTable, *,
                     transmittance=None, tree=None, env=None,
                     visible: np.ndarray | None = None) -> np.ndarray:
    """The near part of the exitance from one point or directional light at shading points,
    (Q, 3) float64: C(x) [Rd_near V(x) - edge_sum(x)] (module section "near field").

    C(x) is the light's entering irradiance at x with the shading normal (0 below the
    geometric or the shading horizon, as the BRDF renderer culls), V(x) its shadow ray
    (offset along the geometric normal).  With ``env`` (an OpenCL environment) the edge
    sums run on the device (:func:`edge_sum_cl`), else in numpy (``tree``: a scipy
    cKDTree of ``queries`` to reuse).  ``visible`` (Q,) bool: V(x) already known (the shared
    visibility, :func:`sharp_visibility`); else a shadow ray per shading point."""
    from dermis.lighting.lights import sample_lights
    x = np.asarray(queries, np.float32)
    ns = _unit(np.asarray(shading_normals, np.float64))
    ng = np.asarray(geo_normals, np.float32)
    out = np.zeros((len(x), 3))
    if len(x) == 0:
        return out
    ls = sample_lights(light, x, ng)
    wi, wt, dist = ls.directions[:, 0], ls.weights[:, 0].astype(np.float64), ls.distance[:, 0]
    cos = np.einsum("ij,ij->i", wi, ns)
    live = (cos > 0) & (wt.sum(axis=1) > 0)
    if not live.any():
        return out
    c = wt[live] * cos[live, None]
    if transmittance is not None:
        c = c * np.asarray(transmittance(cos[live]))
    if visible is not None:
        vis = np.asarray(visible, bool)[live]
    else:
        vis = ~visibility.occluded(x[live], ng[live], wi[live], dist[live])
    on_edge = EDGE_ON_LINE * edges.info.get("precision_mm", 0.0)
    if env is not None:
        s, side = edge_sum_cl(x[live], ns[live], edges, table, env, on_edge_mm=on_edge)
    else:
        s, side = edge_sum(x, ns, edges, table, tree=tree, on_edge_mm=on_edge)
        s, side = s[live], side[live]
    vis = np.where(side != 0, side > 0, vis)
    out[live] = c * (table.rd_near[None, :] * vis[:, None] - s)
    return out


def exitance(points, irradiance: np.ndarray, profile, queries: np.ndarray, *,
             shading_normals: np.ndarray, geo_normals: np.ndarray, lights, visibility,
             epsilon: float | None, transmittance=None, normalisation: str = "energy",
             leaf_size: int = _scene_default("leaf_size"), brute_force: bool = False,
             near_field: bool = True, env=None, memo: dict | None = None, progress=None,
             tuning: GatherTuning = GatherTuning(),
             visible: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Radiant exitance of the BSSRDF at shading points: the far part of the profile
    gathered from the points, the near part at each point (module section "near field").

    Parameters
    ----------
    points : SurfacePoints (positions, normals, areas, info["kernel_sigma_mm"], info
        ["spacing_mm"]) and ``irradiance`` (N, 3) their entering irradiance for ``lights``
    profile : LayerProfile
    queries, shading_normals, geo_normals : (Q, 3) the shading points
    lights : sequence of LightConfig, the lighting condition ``irradiance`` was computed for
    visibility : lighting.visibility.Visibility of the mesh the points lie on
    epsilon, normalisation, brute_force, env, progress, tuning : as :func:`gather`
    transmittance : callable, optional, the entry transmittance (``Transmittance``)
    leaf_size : octree leaf size (scene ``[bssrdf] leaf_size``)
    near_field : bool
        False: the thesis's method, the whole profile gathered from the points (blurred by
        their reconstruction width); so is the "thesis" normalisation.
    memo : dict, optional
        The run's scratch dict: octrees, edges and tables are kept per (points, irradiance),
        made once when several nodes ask at the same time, and the gathers of the last
        ``SHARED_GATHERS`` query sets (the low mesh's bump variants shade the same positions:
        only the sharp near field sees their normals) are reused.
    visible : (Q, number of point/directional lights) bool, optional
        Which of those lights each shading point sees (:func:`sharp_visibility` of the
        shared visibility); None traces a shadow ray per point and light.

    Returns
    -------
    M : (Q, 3) float32; stats : dict (the gathers' stats, timings of each part)
    """
    from dermis.pipeline.reuse import content_key, once, recent_in_run
    t0 = time.perf_counter()
    memo = {} if memo is None else memo
    sigma = float(points.info.get("kernel_sigma_mm") or 0.0)
    spacing = float(points.info.get("spacing_mm") or math.sqrt(
        float(np.sum(points.areas)) / max(len(points.areas), 1)))
    lights = list(lights)
    sharp = [l for l in lights if l.type in SHARP_LIGHTS]
    soft = [l for l in lights if l.type not in SHARP_LIGHTS]
    resolved = (near_field and normalisation == "energy" and sigma > 0 and sharp
                and tuning.kernel_sigma_mm is None)
    E = np.asarray(irradiance, np.float32)
    key = (id(points), id(irradiance))

    def tree(name, e):
        return once(memo, ("octree", name) + key, lambda: (
            points, irradiance, build_octree(points.positions, points.areas, e(),
                                             leaf_size=leaf_size,
                                             kernel_sigma_mm=sigma or None)))[2]

    gkw = dict(epsilon=epsilon, normalisation=normalisation, env=env, brute_force=brute_force,
               progress=progress, tuning=tuning)
    qkey = content_key(queries)

    def gathered(name, e, part):
        """gather() of the octree ``name`` at the queries, or the same gather made earlier in
        the run (its stats then with no kernel seconds of this call; which node made it
        depends on the run's order, so nothing else says so: the artifact stays the same)."""
        gk = (("gather", name, part, qkey, id(profile), epsilon, normalisation, brute_force,
               repr(tuning)) + key)
        (_, (m, st)), made = recent_in_run(
            memo, ("gather", "results"), SHARED_GATHERS, gk,
            lambda: ((points, irradiance, profile),
                     gather(tree(name, e), profile, queries, part=part, **gkw)))
        return m, (st if made else {**st, "kernel_seconds": 0.0})

    stats: dict = {"near_field": bool(resolved)}
    if not resolved:
        m, st = gathered("all", lambda: E, "all")
        stats.update(st)
        stats["seconds"] = time.perf_counter() - t0
        return m, stats

    def locate_edges():
        # the shadow edges (host numpy and Embree, one thread each) are located while this
        # thread builds the octree and the device gathers the far part: independent work
        # whose results do not depend on the overlap
        from concurrent.futures import ThreadPoolExecutor
        own = E if len(lights) == 1 else None   # a condition of one light: E is that light's
        pool = ThreadPoolExecutor(max_workers=len(sharp))
        pending = [pool.submit(shadow_edges, points.positions, points.normals, l, visibility,
                               spacing, transmittance=transmittance, irradiance=own)
                   for l in sharp]
        pool.shutdown(wait=False)
        return points, irradiance, pending
    pending = once(memo, ("edges",) + key, locate_edges)[2]
    m_far, st = gathered("all", lambda: E, "far")
    edges = [f.result() for f in pending]
    t_edges = sum(ed.info["seconds"] for ed in edges)
    stats.update(st)
    M = m_far.astype(np.float64)
    if soft:
        m_soft, st_soft = gathered("soft", lambda: np.maximum(
            E - sum(ed.irradiance for ed in edges), 0.0).astype(np.float32), "near")
        M += m_soft
        stats["kernel_seconds"] += st_soft["kernel_seconds"]
    t1 = time.perf_counter()
    table = once(memo, ("near_table", id(profile), sigma, tuning.cutoff_mm), lambda: (
        profile, near_tables(split_profile(profile, sigma, cutoff_mm=tuning.cutoff_mm))))[1]
    from dermis.pipeline.cl import get_env
    for k, (light, ed) in enumerate(zip(sharp, edges)):
        M += sharp_near_field(queries, shading_normals, geo_normals, light, visibility, ed,
                              table, transmittance=transmittance, env=env or get_env(),
                              visible=None if visible is None else visible[:, k])
    stats.update({"edges_seconds": t_edges, "near_seconds": time.perf_counter() - t1,
                  "rd_near": table.rd_near.tolist(), "near_radius_mm": table.r_out,
                  "edge_crossings": [ed.info["crossings"] for ed in edges],
                  "seconds": time.perf_counter() - t0})
    return np.nan_to_num(M, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32), stats


# ----------------------------------------------------------------------------- radiance
def exitance_to_radiance(M: np.ndarray, cos_o: np.ndarray, eta: float, *,
                         albedo: np.ndarray | None = None, albedo_mode: str = "replace",
                         rd: np.ndarray | None = None, mode: str = "fresnel",
                         transmittance: "Transmittance | None" = None) -> np.ndarray:
    """Outgoing radiance from radiant exitance (energy-conserving Fresnel weighting).

    Parameters
    ----------
    M : (Q, 3) float ndarray
        Radiant exitance from :func:`gather`.
    cos_o : (Q,) float ndarray
        Cosine between the shading normal and the direction to the eye.
    eta : float
        Relative index of refraction of the top layer (inside / outside).
    albedo : (Q, 3) float ndarray, optional
        Linear albedo from the texture at each query point.
    albedo_mode : {"replace", "modulate"}
        "replace" (default): the texture is the total diffuse reflectance and the profile
        only shapes the blur: M -> M * albedo / Rd (needs ``rd``); a flat slab of uniform
        texture a then reflects exactly a E, as the BRDF models with rho_d = a do.
        "modulate": M -> M * albedo (the texture tints the profile's own colour).
    rd : (3,) float ndarray, optional
        The profile's Rd (needed by "replace").
    mode : {"fresnel", "lambert"}
        "fresnel": L = Ft(cos_o) M / (pi (1 - Fdr_ext(eta))), Ft = 1 - F; the divisor makes
        int L cos dw = M exactly (Jensen 2001's S ~ Ft(wo) Rd / pi, normalised).
        "lambert": L = M / pi.
    transmittance : Transmittance, optional
        ("fresnel" mode) The exit weight T(cos_o) / (pi T_mean) per channel, with T the same
        transmittance the entry applied (:class:`Transmittance`; with the surface term it is
        min(Ft, 1 - L_lobes)); int L cos dw = M still holds exactly.  None: Ft(cos_o) /
        (pi (1 - Fdr_ext(eta))).

    Returns
    -------
    (Q, 3) float32 ndarray; 0 where cos_o <= 0; never NaN.
    """
    M = np.asarray(M, np.float64)
    if albedo is not None:
        alb = np.asarray(albedo, np.float64)
        if albedo_mode == "replace":
            if rd is None:
                raise DermisError("gather: albedo_mode 'replace' needs the profile's Rd")
            rdv = np.asarray(rd, np.float64)
            M = M * np.where(rdv > 0, alb / np.where(rdv > 0, rdv, 1.0), 0.0)
        elif albedo_mode == "modulate":
            M = M * alb
        else:
            raise DermisError(f"gather: albedo_mode = {albedo_mode!r}: must be 'replace' or "
                              "'modulate'")
    c = np.asarray(cos_o, np.float64)
    if mode == "fresnel" and transmittance is not None:
        w = transmittance(c) / (np.pi * transmittance.mean)[None, :]
    elif mode == "fresnel":
        w = (fresnel_transmittance(c, eta) / (np.pi * (1.0 - diffuse_fresnel_external(eta))))[:, None]
    elif mode == "lambert":
        w = np.where(c > 0, 1.0 / np.pi, 0.0)[:, None]
    else:
        raise DermisError(f"gather: mode = {mode!r}: must be 'fresnel' or 'lambert'")
    out = np.nan_to_num(M * w, nan=0.0, posinf=0.0, neginf=0.0)
    # a finite float64 beyond float32's range (M * albedo / Rd with Rd ~ 1e-308) would cast to inf
    return np.minimum(out, np.finfo(np.float32).max).astype(np.float32)
