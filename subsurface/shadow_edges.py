"""Shadow edges of point and directional lights between the irradiance points, and the exact
near part of the exitance they bound (docs/science.md §4 "Near field";
``subsurface/near_field.py`` for the split of the profile and the boundary-integral table).

For a point or directional light every point and pixel sees the same shadow curve.  The
curve is located between the irradiance points by bisection along the chords of neighbour
pairs whose shadow rays disagree, cut into straight segments (:func:`shadow_edges`), and the
near part at a shading point is C(x) [Rd_near V(x) - the boundary integral s(x) over the
segments within the window] (:func:`sharp_near_field`; the sums in numpy, :func:`edge_sum`, or
on the device, :func:`edge_sum_cl`).  Which side of the curve a shading point lies on comes
from its own shadow ray V(x) alone, and from the segments only how far from the curve it
lies, |s(x)| (:func:`near_bracket`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from dermis.lighting.emitters import sample_lights
from dermis.lighting.irradiance import irradiance as point_irradiance
from dermis.pipeline.artifacts import SAMPLE_LIT
from dermis.pipeline.cl import event_seconds, to_device
from dermis.pipeline.errors import DermisError
from dermis.subsurface.gather import _global, _local
from dermis.subsurface.near_field import SHARP_LIGHTS, EdgeTable
# scipy and pyopencl are imported inside the functions that use them: loading a stage module
# to build the graph needs neither

__all__ = ["KERNELS", "ShadowEdges", "shadow_edges", "edge_sum", "edge_sum_cl",
           "sharp_visibility", "near_bracket", "sharp_near_field"]

KERNELS = ("bssrdf_gather.cl",)

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


@dataclass
class ShadowEdges:
    """The shadow edges of one point or directional light on a point set, as straight
    segments ``origin + t tangent``, t in [lo, hi] (:func:`shadow_edges`).

    origin, tangent, outward, normal : (K, 3) crossing point, unit edge direction, unit
        in-surface normal of the edge pointing from the lit to the shadowed side, surface
        normal
    lo, hi : (K,) segment extent along ``tangent``, mm
    irradiance : (N, 3) float32 the light's entering irradiance at the points (what
        :func:`lighting.irradiance.irradiance` gives for this light alone)
    info : dict (pairs tested, crossings, seconds)
    lit : (N,) bool, which points the light reaches (its irradiance there > 0), or None
    """

    origin: np.ndarray
    tangent: np.ndarray
    outward: np.ndarray
    normal: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    irradiance: np.ndarray
    info: dict = field(default_factory=dict)
    lit: np.ndarray | None = None


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _lit(light, visibility, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(M,) bool: the light's one sample faces the normal and its shadow ray is free."""
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
    ShadowEdges (the constants above and ``subsurface/near_field.py`` for the construction).
    """
    from scipy.spatial import cKDTree

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
                            "seconds": time.perf_counter() - t0}, lit)
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
    return ShadowEdges(origin, tangent, outward, normal, lo, hi, e, info, lit)


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
             table: EdgeTable, *, tree=None) -> np.ndarray:
    """Sum over the segments within r_out of each query of the boundary integral
    sign(w) [Q(|w|, phi_2) - Q(|w|, phi_1)] (:func:`near_tables`), (Q, 3) float64.
    ``tree``: a scipy cKDTree of ``queries`` to reuse."""
    from scipy.spatial import cKDTree
    x = np.asarray(queries, np.float64)
    out = np.zeros((len(x), 3))
    if len(edges.origin) == 0 or len(x) == 0:
        return out
    half = 0.5 * (edges.hi - edges.lo)
    centre = edges.origin + (0.5 * (edges.hi + edges.lo))[:, None] * edges.tangent
    tree = cKDTree(x) if tree is None else tree
    lists = tree.query_ball_point(centre, table.r_out + half, return_sorted=False)
    cnt = np.fromiter((len(l) for l in lists), np.int64, len(lists))
    if cnt.sum() == 0:
        return out
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
    return out


# Most cells per axis of the device grid of edge segments (edge_sum_cl): the cell grows
# beyond r_out + the longest half-segment when the segments spread wider.
EDGE_GRID_MAX = 128


def edge_sum_cl(queries: np.ndarray, normals: np.ndarray, edges: ShadowEdges,
                table: EdgeTable, env) -> np.ndarray:
    """:func:`edge_sum` on the OpenCL device (``cl/bssrdf_gather.cl`` edge_near): the same
    sums in float32, the segments binned in a uniform grid instead of a kd-tree, and
    segments shorter than 0.15 x their distance integrated by the midpoint rule
    (cl EDGE_MIDPOINT; max difference from :func:`edge_sum` 3e-4 of Rd_near,
    tests/test_gather.py test13; on the LPS head with 1M camera samples the kernel took
    ~0.35 s against ~3.6 s for the numpy version, on a loaded machine)."""
    import pyopencl as cl
    x = np.asarray(queries, np.float32)
    nq = len(x)
    if len(edges.origin) == 0 or nq == 0:
        return np.zeros((nq, 3))
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
    if len(sel) == 0:
        return s_out
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
             np.float32(table.r_out), np.int32(nq), d_out)
    cl.enqueue_copy(env.queue, out, d_out, wait_for=[ev])
    edges.info["kernel_seconds"] = edges.info.get("kernel_seconds", 0.0) + event_seconds([ev])
    s_out[sel] = out[:, :3]
    return s_out


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
    flags = getattr(samples, "flags", None)
    if flags is not None:            # only the lit samples (the others: an environment's
        keep &= (flags & SAMPLE_LIT) > 0       # control variate, lighting/control.py)
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


def near_bracket(visible: np.ndarray, s: np.ndarray, rd_near: np.ndarray):
    """The bracket of the near part, the near energy of the lit region about each shading
    point, from its shadow ray ``visible`` (Q,) and the edge sums ``s`` (Q, 3): Rd_near - |s|
    where the point is lit, |s| where it is shadowed.  Also (Q,) bool, where that holds:
    |s| <= Rd_near in every channel.

    For a region bounded by the segments, s = Rd_near - (the near energy of the region) at a
    point inside and s = -(that energy) outside: |s| is the near energy beyond the curve (a
    function of the point's distance to it) and its sign the side of the curve the segments
    put the point on, so Rd_near V - s is Rd_near - |s| or |s| whenever V(x) and the
    segments agree.  The segments trace the curve at the points' resolution, the shadow ray
    at the pixel's; where they put x on opposite sides (the curve bends or wiggles between
    crossings), the side is taken from V(x) alone: x is treated as lying at the same
    distance from the curve on its own shadow ray's side, which is continuous across each
    segment (|s| = Rd_near / 2 on both sides of a straight edge) and lies in [0, Rd_near].
    |s| > Rd_near cannot come from a curve bounding one region (the segments seen from x
    subtend more than a full turn: pieces of two surface sheets, overlapping ends)."""
    mag = np.abs(np.asarray(s, np.float64))
    rd = np.asarray(rd_near, np.float64)[None, :]
    bracket = np.where(np.asarray(visible, bool)[:, None], rd - mag, mag)
    return bracket, (mag <= rd).all(axis=1)


def sharp_near_field(queries, shading_normals, geo_normals, light, visibility,
                     edges: ShadowEdges, table: EdgeTable, *, lit_near,
                     transmittance=None, tree=None, env=None,
                     visible: np.ndarray | None = None, stats: dict | None = None) -> np.ndarray:
    """The near part of the exitance from one point or directional light at shading points,
    (Q, 3) float64: C(x) [Rd_near V(x) - s(x)] (``subsurface/near_field.py``), s the edge
    sums, with the side of the curve from V(x) alone (:func:`near_bracket`): C(x) times
    Rd_near - |s| where lit, |s| where shadowed; C(x) ``lit_near(idx)`` where |s| exceeds
    Rd_near (no region the segments could bound).

    C(x) is the light's entering irradiance at x with the shading normal (0 below the
    geometric or the shading horizon, as the BRDF renderer culls), V(x) its shadow ray
    (offset along the geometric normal).  With ``env`` (an OpenCL environment) the edge
    sums run on the device (:func:`edge_sum_cl`), else in numpy (``tree``: a scipy
    cKDTree of ``queries`` to reuse).  ``visible`` (Q,) bool: V(x) already known (the shared
    visibility, :func:`sharp_visibility`); else a shadow ray per shading point.
    ``lit_near(idx)``: (len(idx), 3) the near energy of the lit region at the queries
    ``idx`` reconstructed from the points' own shadow rays (the near part of the profile
    gathered over ``edges.lit``; ``subsurface/exitance.py``).
    ``stats``: if given, its "near_fallback" counts the queries that took it, and
    "near_side_from_visibility" those whose shadow ray and segments put them on opposite
    sides of the curve (s > 0 shadowed, s < 0 lit)."""
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
    if env is not None:
        s = edge_sum_cl(x[live], ns[live], edges, table, env)
    else:
        s = edge_sum(x, ns, edges, table, tree=tree)[live]
    bracket, region = near_bracket(vis, s, table.rd_near)
    if not region.all():
        bracket[~region] = lit_near(np.flatnonzero(live)[~region])
    if stats is not None:
        other = np.where(vis[:, None], s < 0, s > 0).any(axis=1) & region
        for k, n in (("near_fallback", (~region).sum()), ("near_side_from_visibility", other.sum())):
            stats[k] = stats.get(k, 0) + int(n)
    out[live] = c * bracket
    return out
