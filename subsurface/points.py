"""Irradiance sample points spread uniformly over a mesh (Jensen-Buhler 2002 pass 1).

The hierarchical BSSRDF evaluation (docs/science.md §4) first places points over the
surface so that every point stands for the same area; irradiance is then computed at each
point per light (``lighting/irradiance.py``) and gathered through an octree
(``subsurface/octree.py``, ``subsurface/gather.py``).  The ``samples`` stage
(``stages/samples.py``) runs :func:`sample_points` once per mesh.

Choices made here (and why):

* **Sampler.**  open3d's ``sample_points_poisson_disk`` (Yuksel 2015 sample elimination)
  gives exactly N blue-noise points from ``INIT_FACTOR`` x N candidates that this module
  draws itself (:func:`_stratified_surface_samples`: area-stratified triangle counts, an R2
  low-discrepancy sequence inside each triangle, seeded numpy generator, so the result is
  deterministic per seed).  libigl's ``blue_noise`` was measured on the 9k-vertex LPS head
  (x10 to mm): 250k points took 90 s and gave 453k points for the radius asked (the count
  is not controllable).  An exact count lets every point carry exactly area / N.  The
  elimination costs ~ INIT_FACTOR^2 (candidates x neighbours per candidate): on the LPS
  head at 1M triangles, 245k points, 2 cores: 15.7 s at 5 (open3d's default), 5.7 s at 3,
  2.0 s at 2.  With the stratified candidates and Lloyd samples below, factor 2 + 2 Lloyd
  steps gives a better partition of unity than open3d's own factor-5 sampler did with 2
  steps (max deviation 0.41-0.48 % vs 0.92-1.21 % on a finely tessellated plane, 3 seeds;
  bench/bench_samples.py), so 2 it is.
* **Normals.**  Each point's normal is the angle-weighted vertex normal (docs/science.md §6)
  interpolated at the point's closest position on the mesh (open3d RaycastingScene closest
  points give triangle ids and barycentrics).
* **Relaxation.**  Sample elimination leaves low-frequency density noise (measured on a
  plane at 1 mm spacing: +-9 % point count per 25 mm^2, and the partition of unity
  sum G_sigma A has 8 % spread at sigma = spacing), which the gather inherits directly as
  exitance error.  Lloyd (centroidal Voronoi) relaxation on the surface removes most of it
  (tests/test_samples.py::test04); ``DEFAULT_RELAX_ITERATIONS`` = 2 because the
  partition-of-unity weights below work far better on relaxed points.  The centroids come
  from ``LLOYD_SAMPLES`` stratified low-discrepancy samples per point (uniform random ones
  made centroid noise the limit: with them, max deviation at sigma = spacing was 2.9 % with
  0 steps, 1.5 % with 1, 0.7 % with 2, 1.0 % with 4).  Measured now (bench/bench_samples.py,
  finely tessellated plane, 3 seeds): 5.1 % with 0 steps, 1.05 % with 1, 0.48 % with 2;
  a step costs ~2 s for 245k points on 2 cores.  A Turk (1992) repulsion step was tried first:
  it made the nearest-neighbour spread worse (CV 0.075 -> 0.107) and was dropped.
* **Areas: partition of unity** (``area_weights="pou"``, default).  The gather
  (``subsurface/profile_table.py``) treats the irradiance as reconstructed from the points with a
  Gaussian of width sigma = ``KERNEL_SIGMA_FACTOR`` x spacing, E(y) ~ sum_p A_p E_p
  G_sigma(y - p), so it convolves the profile with G_sigma once on the host.  A constant E
  is reproduced exactly iff the areas make the Gaussians a partition of unity,
  sum_p A_p G_sigma(y - p) = 1; on a flat slab the exitance error is then bounded by the
  largest deviation of that sum (R >= 0 averages it).  Equal areas (area / N) leave a
  6-8 % spread (density noise of sample elimination); the areas here solve
  sum_q A_q G_sigma(p - q) = 1 at the points by the multiplicative fixed point
  A <- A / sum_q A_q G(p - q) (``POU_ITERATIONS`` steps: it stays positive, where an exact
  CG solve of the ill-conditioned Gaussian system gave negative weights), then are rescaled
  so the mean of the sum over random surface probes is 1 (:func:`pou_areas`).  Measured on a plane at spacing 1, sigma = spacing, 2000-6000
  random probes (tests/test_samples.py::test07 repeats it): equal areas max deviation
  23-26 %, exact Voronoi cell areas 2.6 % (3 Lloyd steps), these weights 1.0 % (std 0.18 %).  Points within
  4 sigma of an open mesh boundary keep area / N (the sum cannot reach 1 there; solving
  for it would pile weight onto the rim and ring inwards).  Pairs whose normals disagree
  (n_p . n_q <= 0: the two sides of an ear or a lip) are not neighbours.
* **Density rule** (:func:`spacing_from_mfp`): one point per pi l^2 / multiplier, where l is
  the smallest reduced mean free path 1/sigma_t' of the layer stack (docs/science.md §4,
  following the thesis), but at most ``MFP_CAP_MM`` = 0.1 mm; ``spacing_mm`` means "each
  point covers spacing_mm^2 of surface".  The cap: since the BSSRDF evaluates the
  profile's near part at each shading point (``subsurface/near_field.py``), the
  spacing no longer has to resolve the profile; it sets how much of the profile comes from
  the points (the far part, beyond 2-3.5 sigma) and the blur of area and environment light
  (sigma).  Without the cap the mfp rule spreads skin1's points 8.4 mm apart at the default
  density (blurring area-light shading by 8.4 mm); with it every preset gets the two-layer
  skin's ~1.25 mm (~250k points on a head, the irradiance pass's budget at 64 shadow
  samples).  Knife-edge error at 1.25 mm (tests/test_knife_edge.py): <= 1.1 % of Rd.
* **Cost** (default scene, ~241k points, 2 cores, bench/bench_stages.py, 2 runs at load
  average 1.3-2.2): on the 1.13M-triangle mesh 14.4-15.6 CPU s (11.6-13.9 s wall), on the
  17k-triangle one 10.9-11.7 CPU s (8.4-9.0 s wall); the version before took 24.0-25.6 and
  17.9-18.8 CPU s (23.0-24.3 and 14.6-17.6 s wall) for byte-identical output; quiet, one run
  each: 18.5 -> 11.4 and 14.2 -> 9.6 CPU s (bench/results/stage_speed_cpu.json).  Sample elimination ~3 s (open3d, one core, holding the GIL, so
  nothing overlaps it); each Lloyd step ~2.2 s wall (3.9M dense samples ~0.5 s CPU, their
  nearest-point query ~2.5 s CPU, the projection back ~0.3 s, its tree ~0.7 s once on the
  1.1M-triangle mesh); the areas ~3-4 s (pair search ~0.4 s on one core, sparse matrix
  ~0.5 s, 40 products ~0.8 s, probe sums ~1.9 s CPU).  What made it so, all with the same
  bits: the stratified samples built one coordinate at a time (np.repeat of (F, 3) rows had
  no fast path: 1.4-2.1 s -> 0.5 s per 3.9M); the Lloyd search bounded by one spacing
  (-25 % CPU); the large temporaries in pieces of ``PIECE`` (system time, mostly page
  faults, was 3-7 s per run, now 1-2 s); the neighbour matrix built from its upper
  triangle; the probe tree reused from the pair search; the boundary edges found by
  sorting edge keys (0.87 s -> 0.13 s on a closed 1.1M-face mesh, where
  igl.boundary_facets found none).
"""
from __future__ import annotations

import math
import time

import numpy as np

from dermis.pipeline.artifacts import SurfacePoints
from dermis.pipeline.errors import DermisError
# scipy, open3d and igl are imported inside the functions that use them: loading the stage
# module to build the graph needs none of them

__all__ = ["sample_points", "spacing_from_mfp", "mesh_area", "nearest_neighbour_spread",
           "density_spread", "pou_areas", "MAX_POINTS", "KERNEL_SIGMA_FACTOR",
           "DEFAULT_RELAX_ITERATIONS", "MFP_CAP_MM"]

# open3d sample elimination starts from INIT_FACTOR x N stratified candidates.  open3d's
# default (and Yuksel 2015's) is 5; 2 was measured enough before 2 Lloyd steps and is ~8x
# cheaper (module docstring, "Sampler").
INIT_FACTOR = 2
# Hard ceiling on the point count: 4M points is ~5 min of sampling and ~300 MB of tree on
# the 2-core reference machine; beyond that the user surely mistyped the spacing.
MAX_POINTS = 4_000_000
# Lloyd relaxation: dense stratified surface samples per point per iteration (more gives
# smoother centroids; 8 was measured 1.6x worse in partition-of-unity max deviation than 16;
# 16 keeps an iteration at ~2.2 s wall for 241k points on 2 cores: module docstring, "Cost").
LLOYD_SAMPLES = 16
# Width of the Gaussian that reconstructs irradiance between points, in units of the
# spacing (subsurface/profile_table.py convolves the profile with it).  Measured partition-of-unity
# max deviation on relaxed points (2 Lloyd steps): 1.7 % at 0.85, 0.7 % at 1.0, 0.46 % at
# 1.15; flat-slab exitance max error, skin1 blue (the narrowest profile per spacing):
# 1.6 % at 0.85, 0.7 % at 1.0.  1.0 is the smallest factor (least blur) that keeps the
# flat slab within 1 % per query.  The blur it adds is the irradiance sampling's own
# resolution: raise bssrdf.point_density to sharpen it.
KERNEL_SIGMA_FACTOR = 1.0
# Lloyd steps by default (see the module docstring's measurements).
DEFAULT_RELAX_ITERATIONS = 2
# Largest mean free path the density rule uses, mm (module docstring, "Density rule"): the
# two-layer skin's own (0.099 mm), so skin1 and skin2 get its spacing at equal density.
MFP_CAP_MM = 0.1
# Fixed-point steps for the partition-of-unity areas.  Measured (plane, sigma = spacing,
# relaxed points): max deviation 1.5 % after 10, 0.7 % after 30, 0.45 % after 60, 0.37 %
# after 200 (where rim weights start to collapse to 0); 40 cost ~0.8 CPU s for 241k points
# (6M pairs).
POU_ITERATIONS = 40
# Gaussian truncation radius in sigma for the neighbour sums (2-D tail mass e^-8 = 3e-4,
# a near-constant offset that the rescaling to the mesh area absorbs).
POU_RADIUS = 4.0
# Elements per piece of the large temporaries (dense Lloyd samples, neighbour pairs, probe
# neighbours), processed piece by piece in the same order (same bits): pieces of a few MB
# stay in cache and in memory the allocator reuses, where whole arrays (3.9M dense samples,
# 6M pairs, 200k x 76 probe neighbours) were paid in page faults every time.  Measured on
# the 1.13M-triangle node (CPU s, 2 runs each): 2^16 17.2-17.6, 2^18 15.7-17.0, 2^20
# 16.2-17.0, 2^23 (whole arrays) 18.6-19.6 of which 4.4 s system time (2^18: 1.4-1.7 s).
PIECE = 1 << 18
# Probes for the mean level of the partition of unity (its spread is ~0.3 %, so 200k
# probes fix the mean to ~1e-5).
POU_PROBES = 200_000


def mesh_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Total surface area of a triangle mesh, mm^2 (float64)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    e1 = v[f[:, 1]] - v[f[:, 0]]
    e2 = v[f[:, 2]] - v[f[:, 0]]
    return float(0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum())


def spacing_from_mfp(profile_or_stack, multiplier: float = 1.0) -> float:
    """Point spacing (mm) from the smallest mean free path of a layer stack.

    Parameters
    ----------
    profile_or_stack : LayerStack or LayerProfile
        A :class:`optics.layers.LayerStack`, or a LayerProfile whose ``info["layers"]``
        holds the stack's ``to_dict()`` (as ``optics/layer_profiles.py`` and
        ``optics/monte_carlo_table.py`` write it).
    multiplier : float
        Point density multiplier (scene key ``bssrdf.point_density``); 2 means twice as
        many points.

    Returns
    -------
    float
        spacing_mm such that each point covers spacing_mm^2 = pi l^2 / multiplier, with
        l = min(MFP_CAP_MM, min over layers and channels of 1 / (sigma_a + sigma_s')).

    Notes
    -----
    docs/science.md §4: "density about one point per pi l^2 for the smallest mean free
    path l, or finer" (Jensen & Buhler 2002, sec. 4.1, and the thesis); the cap: module
    docstring.
    """
    if not (multiplier > 0 and math.isfinite(multiplier)):
        raise DermisError(f"samples: point density multiplier = {multiplier}: must be > 0")
    layers = getattr(profile_or_stack, "layers", None)
    if layers is None:
        info = getattr(profile_or_stack, "info", {}) or {}
        layers = (info.get("layers") or {}).get("layers")
        if not layers:
            raise DermisError("samples: spacing_from_mfp needs a LayerStack or a LayerProfile "
                              "whose info['layers'] lists the layers")
        pairs = [(l["sigma_a"], l["sigma_s_prime"]) for l in layers
                 if l["thickness_mm"] == "inf" or float(l["thickness_mm"]) > 0]
    else:
        pairs = [(l.sigma_a, l.sigma_s_prime) for l in layers if l.thickness_mm > 0]
    mfp = min([MFP_CAP_MM] + [1.0 / (a + s) for sa, ss in pairs for a, s in zip(sa, ss)])
    return math.sqrt(math.pi * mfp * mfp / multiplier)


def nearest_neighbour_spread(positions: np.ndarray) -> dict:
    """Nearest-neighbour distance statistics: mean, std, coefficient of variation, min."""
    from scipy.spatial import cKDTree
    d, _ = cKDTree(positions).query(positions, k=2, workers=-1)
    nn = d[:, 1]
    return {"nn_mean_mm": float(nn.mean()), "nn_std_mm": float(nn.std()),
            "nn_cv": float(nn.std() / nn.mean()), "nn_min_mm": float(nn.min())}


def _closest(scene, points: np.ndarray):
    """Closest surface points, triangle ids and barycentric (u, v) via open3d."""
    import open3d as o3d
    res = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    return (res["points"].numpy(), res["primitive_ids"].numpy().astype(np.int64),
            res["primitive_uvs"].numpy())


_PLASTIC = 1.324717957244746  # real root of x^3 = x + 1
_R2_STEP = np.array([1.0 / _PLASTIC, 1.0 / _PLASTIC**2])


def _stratified_surface_samples(v, f, count, rng, e1=None, e2=None, w=None,
                                return_triangles=False):
    """``count`` area-stratified points on the mesh, in triangle order.

    Systematic sampling of the cumulative area (one random offset) gives every triangle the
    floor or the ceiling of its expected count, so the per-triangle counts carry no Poisson
    noise (uniform random allocation would: the Lloyd centroids inherit it), and the points
    come out grouped by triangle, which keeps later tree queries cache-friendly (4M points
    on the LPS head: 0.7-0.9 s, against 2.7 s for ``rng.choice`` allocation)."""
    if e1 is None:
        e1 = v[f[:, 1]] - v[f[:, 0]]
        e2 = v[f[:, 2]] - v[f[:, 0]]
        w = np.linalg.norm(np.cross(e1, e2), axis=1)
    ends, shift = _stratified_plan(w, count, rng)
    pts = _stratified_place(v, f, e1, e2, ends, shift, 0, len(f))
    if return_triangles:
        return pts, np.repeat(np.arange(len(f)), np.diff(ends, prepend=0))
    return pts


def _stratified_plan(w, count, rng):
    """Per triangle: the end of its run of ``count`` stratified points (cumulative counts) and
    the random shift of its R2 sequence (see :func:`_stratified_surface_samples`)."""
    c = np.cumsum(w)
    c *= count / c[-1]
    c[-1] = count  # floor(count + offset) = count: exactly count points in all
    ends = np.floor(c + rng.random()).astype(np.int64)
    return ends, rng.random((len(w), 2))


def _stratified_place(v, f, e1, e2, ends, shift, t0, t1):
    """The stratified points of triangles t0 .. t1 - 1 (:func:`_stratified_plan`)."""
    start = int(ends[t0 - 1]) if t0 else 0
    ends = ends[t0:t1]
    cnt = np.diff(ends, prepend=start)
    # within a triangle: the R2 low-discrepancy sequence (Roberts 2018, the plastic number
    # g: steps 1/g, 1/g^2) with a random shift per triangle, folded onto the triangle;
    # uniform random barycentrics leave clumps and holes that add noise to Lloyd centroids.
    # One coordinate at a time on flat arrays: np.repeat of 8-byte items has a fast path
    # that rows of 3 doubles lack, and no (count, 3) temporaries (same bits, 3-4x faster:
    # 3.9M points 0.5 s instead of 1.4-2.1 s)
    i = np.arange(int(ends[-1]) - start if len(ends) else 0, dtype=np.float64)
    i -= np.repeat((ends - cnt - start).astype(np.float64), cnt)  # index within the triangle
    u0 = i * _R2_STEP[0]
    u0 += np.repeat(shift[t0:t1, 0], cnt)
    u0 -= np.floor(u0)
    u1 = i
    u1 *= _R2_STEP[1]
    u1 += np.repeat(shift[t0:t1, 1], cnt)
    u1 -= np.floor(u1)
    flip = u0 + u1 > 1
    np.subtract(1.0, u0, out=u0, where=flip)
    np.subtract(1.0, u1, out=u1, where=flip)
    pts = np.empty((len(i), 3))
    v0 = v[f[t0:t1, 0]]
    for x in range(3):
        col = np.repeat(e1[t0:t1, x], cnt)
        col *= u0
        t = np.repeat(e2[t0:t1, x], cnt)
        t *= u1
        col += t
        col += np.repeat(v0[:, x], cnt)
        pts[:, x] = col
    return pts


def _relax(pos: np.ndarray, v, f, e1, e2, w, scene, iterations: int, seed: int):
    """Lloyd (centroidal Voronoi) relaxation on the surface: every point moves to the centroid
    of the dense surface samples nearest to it, then back onto the surface.  Returns the
    last projection (points, triangle ids, barycentrics), as :func:`_closest` does."""
    from scipy.spatial import cKDTree
    rng = np.random.default_rng(seed)
    n = len(pos)
    spacing = math.sqrt(0.5 * float(w.sum()) / n)
    for _ in range(iterations):
        ends, shift = _stratified_plan(w, LLOYD_SAMPLES * n, rng)
        # the dense samples in pieces of ~PIECE, split between triangles; np.add.at
        # accumulates them in the same order as one np.bincount over all would (same bits)
        cuts = np.searchsorted(ends, np.arange(PIECE, ends[-1], PIECE)) + 1
        cuts = np.unique(np.concatenate([[0], cuts, [len(f)]]))
        tree = cKDTree(pos)
        cnt = np.zeros(n)
        cen = np.zeros((3, n))
        for t0, t1 in zip(cuts[:-1], cuts[1:]):
            dense = _stratified_place(v, f, e1, e2, ends, shift, t0, t1)
            # the nearest point lies within one spacing for ~99 % of the samples (LPS head,
            # before the first step): bounding the search there prunes the tree from the
            # start (~25 % less CPU); the rest are searched again unbounded (same owners)
            _, owner = tree.query(dense, distance_upper_bound=spacing, workers=-1)
            far = np.flatnonzero(owner == n)
            if len(far):
                owner[far] = tree.query(dense[far], workers=-1)[1]
            np.add.at(cnt, owner, 1.0)
            for k in range(3):
                np.add.at(cen[k], owner, dense[:, k])
        moved = np.where(cnt[:, None] > 0, cen.T / np.maximum(cnt, 1)[:, None], pos)
        closest = _closest(scene, moved)
        pos = closest[0].astype(np.float64)
    return closest


def _morton_order(p: np.ndarray) -> np.ndarray:
    """Permutation that sorts points along a 3-D Morton (Z-order) curve, so that neighbours
    sit close in memory for the tree queries and the sparse neighbour sums.

    10 bits per axis, x the least significant bit of each triple: the order the points are
    stored in.  It is not the octree's order (``subsurface/octree.py`` morton_order: 21 bits,
    x the most significant), which differs at 97-99 % of the positions of a
    sample_points() output; the stored order is part of the points artifact."""
    lo = p.min(0)
    q = ((p - lo) / max(float((p.max(0) - lo).max()), 1e-30) * 1023).astype(np.uint64)
    code = np.zeros(len(p), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def density_spread(positions: np.ndarray, areas: np.ndarray, queries: np.ndarray,
                   sigma: float) -> dict:
    """Partition-of-unity test of a point set: sum_i G_sigma(x - p_i) A_i at query points
    (2-D Gaussian, plane-like neighbourhoods).  1 everywhere for a perfect quadrature; its
    spread is the relative error a gather of a profile of width ~sigma inherits."""
    from scipy.spatial import cKDTree
    tree = cKDTree(positions)
    vals = np.empty(len(queries))
    for k, (x, idx) in enumerate(zip(queries, tree.query_ball_point(queries, 5 * sigma))):
        d2 = ((positions[idx] - x) ** 2).sum(1)
        vals[k] = (np.exp(-d2 / (2 * sigma * sigma)) * areas[idx]).sum() / (2 * np.pi * sigma**2)
    return {"mean": float(vals.mean()), "std": float(vals.std()),
            "max_abs_dev": float(np.abs(vals - 1).max())}


def _boundary_points(v, f, sigma):
    """Points along the open boundary edges of a mesh, at most sigma / 4 apart (or None)."""
    # the edges that belong to one face only, as that face orients them (the edges
    # igl.boundary_facets gives, 0.13 s instead of 0.87 s on a closed 1.1M-face mesh)
    f = np.asarray(f, np.int64)
    g = f[:, [1, 2, 0]]
    key = np.minimum(f, g)
    key *= len(v)
    key += np.maximum(f, g)
    s = np.sort(key, axis=None)
    once = np.ones(len(s), bool)
    same = s[1:] == s[:-1]
    once[1:] &= ~same
    once[:-1] &= ~same
    if not once.any():
        return None
    fi, k = np.nonzero(np.isin(key, s[once]))
    edges = np.stack([f[fi, k], g[fi, k]], 1)
    a, b = v[edges[:, 0]], v[edges[:, 1]]
    steps = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / (0.25 * sigma))).astype(int)
    owner = np.repeat(np.arange(len(edges)), steps + 1)
    # t = 0, 1/k, ..., 1 along each edge, bit for bit np.linspace(0, 1, k + 1), without a
    # Python loop over the edges
    first = np.cumsum(steps + 1) - (steps + 1)
    t = (np.arange(len(owner)) - first[owner]) * (1.0 / steps[owner])
    t[first + steps] = 1.0
    return a[owner] + (b - a)[owner] * t[:, None]


def pou_areas(positions: np.ndarray, normals: np.ndarray | None, sigma: float,
              total_area: float, *, boundary: np.ndarray | None = None,
              probes: tuple[np.ndarray, np.ndarray] | None = None,
              iterations: int = POU_ITERATIONS) -> tuple[np.ndarray, dict]:
    """Point areas that make 2-D Gaussians of width sigma a partition of unity.

    Parameters
    ----------
    positions : (N, 3) float ndarray, mm, points on the surface
    normals : (N, 3) float ndarray or None
        Unit normals; neighbours with n_p . n_q <= 0 are ignored (opposite sides of a
        thin part).  None: no such test.
    sigma : float
        Gaussian width, mm.
    total_area : float
        The surface area, mm^2 (the start value total_area / N).
    boundary : (B, 3) float ndarray, optional
        Points along the open boundary; points within ``POU_RADIUS`` sigma of them keep
        total_area / N.
    probes : ((M, 3), (M, 3)) float ndarrays, optional
        Uniform random surface points and their normals.  The fixed point makes the sum 1
        *at the points*, where each sees its own peak; the level that matters is its mean
        over the surface, so the areas are divided by the mean of sum_p A_p G(y - p) over
        the probes farther than ``POU_RADIUS`` sigma from the boundary.  (Rescaling to the
        mesh area instead was measured 1.2 % low on a plane: sample elimination crowds
        points along open edges.)  None: rescale to sum to total_area.
    iterations : int
        Fixed-point steps A <- A / sum_q A_q G_sigma(p - q).

    Returns
    -------
    areas : (N,) float64, mm^2
    info : dict (pou_iterations, pou_frozen_points, pou_scale: the rescaling applied
        (1 / mean level), pou_probe_std: the spread of the sum over the probes,
        pou_area_ratio: sum of the areas / total_area)
    """
    from scipy.spatial import cKDTree
    p = np.asarray(positions, np.float64)
    n = len(p)
    rad = POU_RADIUS * sigma
    tree = cKDTree(p)
    pairs = tree.query_pairs(rad, output_type="ndarray")
    nc = None if normals is None else np.ascontiguousarray(np.asarray(normals, np.float64).T)
    pc = np.ascontiguousarray(p.T)
    norm = 1.0 / (2.0 * np.pi * sigma * sigma)
    parts = []
    for s in range(0, len(pairs) or 1, PIECE):
        i, j = pairs[s:s + PIECE, 0], pairs[s:s + PIECE, 1]
        # per coordinate on (pairs,) arrays, summed x + y + z as numpy sums the rows of
        # (pairs, 3) arrays (the same bits), without those (pairs, 3) gathers
        if nc is not None:
            dot = nc[0][i] * nc[0][j]
            dot += nc[1][i] * nc[1][j]
            dot += nc[2][i] * nc[2][j]
            ok = dot > 0
            i, j = i[ok], j[ok]
        d2 = np.zeros(len(i))
        for x in pc:
            dx = x[i] - x[j]
            d2 += dx * dx
        # int32 indices: what the sparse matrix keeps (no copies to convert them there)
        parts.append((i.astype(np.int32), j.astype(np.int32),
                      np.exp(-d2 / (2.0 * sigma * sigma)) * norm))
    i, j, w = (np.concatenate(x) for x in zip(*parts))
    del pairs, parts
    frozen = np.zeros(n, bool)
    if boundary is not None and len(boundary):
        d, _ = cKDTree(boundary).query(p, distance_upper_bound=rad)
        frozen = np.isfinite(d)
    a = np.full(n, total_area / n)

    # symmetric neighbour matrix in CSR: one sparse product per step (was two bincounts over
    # the pair list, 4x slower on 250k points).  Built as U + U^T from the upper triangle
    # (i < j): the same sorted CSR as converting both halves at once, with half the sorting
    # (6M pairs on the LPS head: 0.45 s instead of 0.7-2 s)
    import scipy.sparse as sps
    wm = sps.csr_matrix((w, (i, j)), shape=(n, n))
    wm = wm + wm.T.tocsr()

    def pou(a):
        return a * norm + wm @ a

    for _ in range(int(iterations)):
        a = np.where(frozen, a, a / pou(a))
    spread = float("nan")
    scale = total_area / a.sum()
    if probes is not None:
        y, ny = probes
        if boundary is not None and len(boundary):
            keep = ~np.isfinite(cKDTree(boundary).query(y, distance_upper_bound=rad)[0])
            y, ny = y[keep], ny[keep]
        if len(y) >= 100:
            level = _probe_sums(p, normals, a, y, ny, sigma, tree)
            scale = 1.0 / level.mean()
            spread = float(level.std() * scale)
    a = a * scale
    return a, {"pou_iterations": int(iterations), "pou_frozen_points": int(frozen.sum()),
               "pou_scale": float(scale), "pou_probe_std": spread,
               "pou_area_ratio": float(a.sum() / total_area)}


def _probe_sums(p, normals, a, y, ny, sigma, tree=None):
    """sum_p A_p G_sigma(y - p) at probe points y (normals must agree), vectorised by kNN
    (``tree``: a cKDTree of p, if built already)."""
    from scipy.spatial import cKDTree
    tree = cKDTree(p) if tree is None else tree
    rad = POU_RADIUS * sigma
    # neighbours inside the radius: ~ pi rad^2 / (mean area); 1.5x margin for density noise
    k = int(min(len(p), max(8, math.ceil(1.5 * math.pi * rad * rad / (a.sum() / len(p))))))
    af = np.asarray(a, np.float32)
    if normals is not None:
        nr = np.asarray(normals, np.float32).T.copy()
        ny = np.asarray(ny, np.float32)
    out = np.empty(len(y))
    step = max(1, PIECE // k)
    for s in range(0, len(y), step):
        d, idx = tree.query(y[s:s + step], k=k, distance_upper_bound=rad, workers=-1)
        idx = np.minimum(idx, len(p) - 1)  # missing neighbours: d = inf, so their weight is 0
        # float32 (M, k) arrays, one normal component at a time: the (M, k, 3) float64
        # gather was the slowest part of the area solve
        w = np.exp(-(d.astype(np.float32) ** 2) * np.float32(0.5 / (sigma * sigma)))
        w *= af[idx]
        if normals is not None:
            q = ny[s:s + step]
            dot = nr[0][idx] * q[:, :1]
            dot += nr[1][idx] * q[:, 1:2]
            dot += nr[2][idx] * q[:, 2:]
            w *= dot > 0
        out[s:s + step] = w.sum(1, dtype=np.float64)
    return out / (2 * np.pi * sigma * sigma)


def sample_points(vertices: np.ndarray, faces: np.ndarray, *, spacing_mm: float, seed: int = 0,
        relax_iterations: int = DEFAULT_RELAX_ITERATIONS,
        vertex_normals: np.ndarray | None = None, area_weights: str = "pou",
        kernel_sigma_factor: float = KERNEL_SIGMA_FACTOR) -> SurfacePoints:
    """Spread blue-noise points uniformly over a mesh, each covering the same area.

    Parameters
    ----------
    vertices : (V, 3) float ndarray, mm
    faces : (F, 3) int ndarray, counter-clockwise seen from outside
    spacing_mm : float
        Each point covers spacing_mm^2 of surface: N = round(area / spacing_mm^2)
        (see :func:`spacing_from_mfp`).
    seed : int
        Seed of the candidate, Lloyd and probe samples (same seed, same points).
    relax_iterations : int
        Lloyd relaxation steps after sampling (0 = none; default
        ``DEFAULT_RELAX_ITERATIONS``).
    vertex_normals : (V, 3) float ndarray, optional
        Unit vertex normals; default: libigl angle-weighted normals.
    area_weights : {"pou", "uniform"}
        "pou" (default): areas that make Gaussians of width sigma a partition of unity
        (:func:`pou_areas`); "uniform": area / N each.
    kernel_sigma_factor : float
        sigma = kernel_sigma_factor x spacing_mm (default ``KERNEL_SIGMA_FACTOR``); the
        gather must use the same sigma (``info["kernel_sigma_mm"]``).

    Returns
    -------
    SurfacePoints
        positions and normals (N, 3) float32, areas (N,) float32 (they sum to the mesh area
        to within the sampler's edge crowding on open meshes: ``info["pou_area_ratio"]``);
        ``info["kernel_sigma_mm"]`` is the reconstruction width to pass to
        ``subsurface.octree.build_octree`` / ``subsurface.gather.gather``.

    Raises
    ------
    DermisError
        Empty/degenerate mesh, non-positive spacing, or more than ``MAX_POINTS`` points.
    """
    import open3d as o3d

    t0 = time.perf_counter()
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise DermisError(f"samples: mesh must be (V,3) vertices and (F,3) faces; got "
                          f"{v.shape} and {f.shape}")
    if not (spacing_mm > 0 and math.isfinite(spacing_mm)):
        raise DermisError(f"samples: spacing_mm = {spacing_mm}: must be a finite number > 0")
    if area_weights not in ("pou", "uniform"):
        raise DermisError(f"samples: area_weights = {area_weights!r}: must be 'pou' or 'uniform'")
    if not (kernel_sigma_factor > 0 and math.isfinite(kernel_sigma_factor)):
        raise DermisError(f"samples: kernel_sigma_factor = {kernel_sigma_factor}: must be > 0")
    e1 = v[f[:, 1]] - v[f[:, 0]]
    e2 = v[f[:, 2]] - v[f[:, 0]]
    tri_w = np.linalg.norm(np.cross(e1, e2), axis=1)  # twice the triangle areas
    area = float(0.5 * tri_w.sum())
    if not area > 0:
        raise DermisError("samples: the mesh has zero surface area")
    n = max(1, int(round(area / spacing_mm**2)))
    if n > MAX_POINTS:
        raise DermisError(
            f"samples: spacing_mm = {spacing_mm:g} on {area:.0f} mm^2 gives {n} points; at most "
            f"{MAX_POINTS} are allowed (lower bssrdf.point_density or coarsen the spacing)")

    rng = np.random.default_rng(int(seed))
    # int32 faces: open3d copies them as one block (int64 goes element by element, ~0.7 s at 1M)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v),
                                     o3d.utility.Vector3iVector(f.astype(np.int32)))
    cand = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        _stratified_surface_samples(v, f, max(n, int(round(INIT_FACTOR * n))), rng,
                                    e1, e2, tri_w)))
    pcd = mesh.sample_points_poisson_disk(number_of_points=n, pcl=cand)
    pos = np.asarray(pcd.points, np.float64)
    pos = pos[_morton_order(pos)]
    t_sample = time.perf_counter() - t0

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                        o3d.core.Tensor(f.astype(np.uint32)))
    t1 = time.perf_counter()
    if relax_iterations > 0:
        # the last Lloyd projection already gives the closest triangles and barycentrics
        pos_c, tri, uv = _relax(pos, v, f, e1, e2, tri_w, scene, int(relax_iterations),
                                int(seed))
        pos = pos_c.astype(np.float64)
    else:
        pos_c, tri, uv = _closest(scene, pos)
    t_relax = time.perf_counter() - t1
    t1 = time.perf_counter()

    # normals: angle-weighted vertex normals interpolated at the closest surface point
    if vertex_normals is None:
        import igl
        vn = igl.per_vertex_normals(v, f.astype(np.int64),
                                    igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_ANGLE)
    else:
        vn = np.asarray(vertex_normals, np.float64)
    bad = ~np.isfinite(vn).all(axis=1)
    if bad.any():  # libigl's angle weights are 0/0 at zero-area faces: area-weighted there
        cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        acc = np.zeros((len(v), 3))
        for k in range(3):
            np.add.at(acc, f[:, k], cross)
        vn = np.where(bad[:, None], acc / np.maximum(
            np.linalg.norm(acc, axis=1, keepdims=True), 1e-300), vn)
    w = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    nrm = (vn[f[tri]] * w[..., None]).sum(axis=1)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)

    sigma = float(kernel_sigma_factor) * float(spacing_mm)
    info = {"count": n, "spacing_mm": float(spacing_mm), "mesh_area_mm2": area,
            "sampler": f"open3d sample_points_poisson_disk on {INIT_FACTOR} x N stratified "
                       "R2 candidates",
            "seed": int(seed), "relax_iterations": int(relax_iterations),
            "area_weights": area_weights, "kernel_sigma_mm": sigma,
            "seconds_sampling": t_sample, "seconds_relax": t_relax,
            "seconds_normals": time.perf_counter() - t1}
    if area_weights == "pou" and n > 1:
        t1 = time.perf_counter()
        rng = np.random.default_rng(int(seed) + 7919)
        probe, ptri = _stratified_surface_samples(v, f, min(max(n, 20000), POU_PROBES), rng,
                                                  e1, e2, tri_w, return_triangles=True)
        fn = np.cross(e1[ptri], e2[ptri])
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
        areas, pinfo = pou_areas(pos_c.astype(np.float64), nrm, sigma, area,
                                 boundary=_boundary_points(v, f, sigma), probes=(probe, fn))
        info.update(pinfo, seconds_areas=time.perf_counter() - t1)
    else:
        areas = np.full(n, area / n)
    areas = areas.astype(np.float32)
    info["seconds"] = time.perf_counter() - t0
    if n > 1:
        info.update(nearest_neighbour_spread(pos))
    return SurfacePoints(positions=pos_c.astype(np.float32), normals=nrm.astype(np.float32),
                        areas=areas, info=info)
