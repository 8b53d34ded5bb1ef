"""The octree over the irradiance points (Jensen & Buhler 2002 pass 2; docs/science.md §4).

The points (``subsurface/points.py``) with their irradiance are sorted along a Morton curve and
grouped into a flattened octree that the device (``cl/bssrdf_gather.cl``, launched by
``subsurface/gather.py``) walks for every shading point.

* **Octree.**  Points are sorted along a 21-bit-per-axis Morton curve of their bounding
  cube; a node is a run of points sharing a Morton prefix, split while it holds more than
  ``leaf_size`` points (Jensen-Buhler and pbrt-v2 use 8).  Nodes are stored in depth-first
  pre-order (sort by (first point, depth)) with a skip index, so the device walk is a
  forward loop without a stack.  Each node keeps total area, the sum of E A (so the
  area-weighted mean irradiance is sum E A / A), the irradiance-weighted mean position
  (weights E A summed over channels; the area-weighted centroid where a node has no
  irradiance), a bounding box (host) and the bounding-sphere radius about that position
  (device: the "outside the node" test and the cut-off skip), and the positional
  covariance about that position for the second-order cluster term (``subsurface/gather.py``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, fields, replace

import numpy as np

from dermis.pipeline.config import BssrdfConfig
from dermis.pipeline.errors import DermisError

__all__ = ["Octree", "build_octree", "morton_order", "scene_default", "MORTON_BITS"]

MORTON_BITS = 21


def scene_default(name: str):
    """The scene schema's default of ``[bssrdf] <name>`` (pipeline/config.py BssrdfConfig):
    the library keeps no second copy of a scene setting's number."""
    return next(f.default for f in fields(BssrdfConfig) if f.name == name)


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

    def carrying(self, values: np.ndarray) -> "Octree":
        """The same tree - nodes, their irradiance-weighted positions and covariances, the
        points' order - carrying other per-point values (N, 3) of any sign (in the input
        points' order) in place of the irradiance: a gather of it is the gather of
        ``values`` through the irradiance's clusters, linear in them (the irradiance's
        noise, ``subsurface/exitance.py`` :func:`exitance_noise`).  A node's sum of values x
        area covers its subtree, the points [start[i], start[skip[i]])."""
        v = np.asarray(values, np.float64)
        if v.shape != (len(self.order), 3) or not np.isfinite(v).all():
            raise DermisError(f"octree: values {v.shape} must be finite and "
                              f"({len(self.order)}, 3)")
        v = v[self.order]
        k = self.n_nodes
        cum = np.vstack([np.zeros((1, 3)), np.cumsum(v * self.areas[:, None], axis=0)])
        sums = cum[self.start[self.skip[:k]]] - cum[self.start[:k]]
        return replace(self, ea_sum=sums, irradiance=v.astype(np.float32))


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
    """Permutation sorting points along a Morton (Z-order) curve of their bounding cube.

    21 bits per axis, x the most significant bit of each triple: the order of the octree and
    of the gather's query tiles.  ``subsurface/points.py`` stores the points in another
    Morton order (10 bits per axis, x the least significant); the two disagree at 97-99 %
    of the positions of the tests' point sets and of a sample_points() output, so neither
    replaces the other without changing results."""
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
                 leaf_size: int = scene_default("leaf_size"),
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
