"""Mesh preparation, geometry steps: load a scan, validate it, build the high and low meshes.

The thesis setup (docs/science.md §6) renders a ~1M-triangle scan and a ~16,750-triangle
QSlim simplification of it whose texture coordinates are transferred from the scan ("nearest
old vertex -> its UV(s); at seams pick the UV combination with the smallest texture-space
perimeter; repair triangles that straddle the cut").  This module holds those steps as pure
functions on :class:`pipeline.artifacts.Mesh`; the bake lives in ``stages/bake.py`` and the
lead composes the steps into the cached graph.

Steps
-----
(``load_scan``, in :mod:`dermis.stages.scan_io`: OBJ / PLY / glTF / GLB -> Mesh in mm)
``validate``       refuse NaN/Inf, non-manifold edges, missing UVs/texture; remove degenerate and
                   duplicate faces and unreferenced vertices (reported)
``make_high``      subdivide (Loop or midpoint) to a target count, optionally displace along normals
``simplify``       quadric-error decimation (fast-simplification, measured against libigl)
``transfer_uv``    the thesis's nearest-vertex UV transfer with seam choice and straddle repair

Conventions (pipeline/artifacts.py): mm; UV origin bottom-left (OBJ convention): texel row from
the top is ``(1 - v) * (H - 1)``, column ``u * (W - 1)``.
"""
from __future__ import annotations

import numpy as np

from dermis.pipeline.artifacts import Mesh, angle_weighted_normals
from dermis.pipeline.errors import DermisError

__all__ = [
    "VERSION", "KERNELS", "LPS_DISPLACEMENT_SCALE_MM", "LPS_DISPLACEMENT_MID",
    "validate", "make_high", "simplify", "transfer_uv", "sample_image",
]

VERSION = 1
KERNELS: tuple[str, ...] = ()

# Displacement calibration for the Lee Perry-Smith scan (lps_head README: the 8-bit JPEG lost the
# original's absolute scale and neutral level).  bench/calibrate_lps_displacement.py, results in
# bench/results/lps_displacement_calibration.json:
# A (used): the base mesh's own vertices lie on the scan while the Loop surface shrinks away from
#   them, so a map baked against the smoothed surface must restore them.  Least squares of
#   (v_base - v_loop) . n_loop = s (d - mid) over all 8,844 base vertices after 3 Loop splits (what
#   make_high builds for the thesis's ~1M triangles) gives s = 6.69 mm, mid = 0.498, correlation
#   0.988, rms residual 0.060 mm of 0.398 mm (1 split: 5.15 mm; 2: 6.38 mm -- the scale belongs to
#   the 3-split Loop surface).  The neutral level is thus ~127/255, not the map's median 135/255.
# B (cross-check, the README's suggestion): mean angle between the displaced surface's normals (map
#   box-filtered to 1024) and the tangent normal map, green up: 2.99 deg at 0 mm, 2.46 deg at 4 mm,
#   2.64 deg at 6 mm.  Its minimum is shallow and lower than A, as expected when the compared normals
#   carry independent noise (JPEG, "SmoothUV" vs "NoSmoothUV" layouts), which pulls a least-error fit
#   towards zero amplitude; A's direct distance fit is the stronger evidence.
LPS_DISPLACEMENT_SCALE_MM = 6.69
LPS_DISPLACEMENT_MID = 0.498

# validate: a face counts as zero-area when twice its area is below this fraction of the squared
# bounding-box diagonal.  1e-14 is ~100x float64 round-off for a cross product of coordinates of
# that size, so only faces that are degenerate up to round-off are removed.
_DEGENERATE_REL_AREA = 1e-14

# make_high: "already dense" if the mesh has at least this fraction of the requested count (brief).
_DENSE_FRACTION = 0.8

# transfer_uv: a low triangle straddles a seam when its UV perimeter exceeds this multiple of its
# 3-D perimeter times the local UV/3-D scale (see transfer_uv Notes).  Measured on the LPS scan
# (16,750 triangles from the 3x Loop mesh, before repair): median ratio 0.98, 90th percentile 1.24;
# 643 triangles above 2, 584 above 3, 500 above 6, 238 above 30 -- the straddlers form a long tail
# reaching ~300 and the range 2..6 is sparse, so 3 sits in the gap.  A merely stretched triangle
# above the bound is re-laid in its own chart by the repair, which is harmless.
_SEAM_RATIO = 3.0
# transfer_uv: at most this many candidate UVs per high vertex enter the perimeter enumeration
# (K^3 combinations per seam triangle).  Scan atlases have 2, rarely 3-4 UVs at a seam vertex;
# more (e.g. a lat-long pole) are truncated and the straddle repair fixes the triangle.
_MAX_CANDIDATES = 4
# transfer_uv: passes of the straddle repair (a triangle touching three charts needs two).
_REPAIR_PASSES = 2


# ----------------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------------

def validate(mesh: Mesh, *, source: str) -> tuple[Mesh, dict]:
    """Check a mesh at the pipeline boundary; repair what is safe, refuse the rest.

    Parameters
    ----------
    mesh : Mesh
        As from :func:`load_scan` (or a procedural head).
    source : str
        What to name in messages (file path or scene key).

    Returns
    -------
    mesh : Mesh
        Copy with degenerate and duplicate faces removed, unreferenced vertices dropped (indices
        compacted; UVs untouched) and angle-weighted ``normals`` computed.
    report : dict
        ``{"degenerate_faces_removed", "duplicate_faces_removed", "unreferenced_vertices_removed",
        "boundary_edges", "triangles", "vertices"}``; also stored in ``mesh.info["validate"]``.

    Raises
    ------
    DermisError
        Refused, with the source named: empty mesh or bad array shapes; face indices out of range;
        NaN/Inf vertex coordinates (count and first index) or UVs; non-manifold edges (an edge shared
        by more than two faces: count and one example with its vertex indices and position); missing
        UVs; missing albedo texture.

    Notes
    -----
    Repaired (reported, not refused): a *degenerate* face repeats a vertex index or has zero area
    (twice its area below ``1e-14`` x the squared bounding-box diagonal: round-off level); a
    *duplicate* face uses the same three vertices as an earlier face in any order or orientation
    (the first is kept).  Non-manifold edges are refused rather than repaired because splitting
    them changes the surface the bake and the ray caster see; fix them in the scan tool (e.g.
    MeshLab "Repair non-manifold edges").  Open boundaries are allowed and counted.
    """
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise DermisError(f"{source}: vertices must be a non-empty (V, 3) array, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise DermisError(f"{source}: faces must be a non-empty (F, 3) array of triangles, got shape {f.shape}")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DermisError(f"{source}: {int(bad.sum())} vertices have NaN/Inf coordinates "
                          f"(first: vertex {first} = {v[first].tolist()}); fix the export")
    if f.min() < 0 or f.max() >= len(v):
        raise DermisError(f"{source}: face indices must lie in [0, {len(v) - 1}], got "
                          f"[{int(f.min())}, {int(f.max())}]")
    if mesh.uv is None or mesh.uv_faces is None:
        raise DermisError(f"{source}: the mesh has no texture coordinates (UVs); the bake needs them. "
                          "Export the scan with UVs (OBJ 'vt', glTF TEXCOORD_0, PLY u/v)")
    uv = np.asarray(mesh.uv)
    uvf = np.asarray(mesh.uv_faces)
    if uvf.shape != f.shape or uvf.min() < 0 or uvf.max() >= len(uv):
        raise DermisError(f"{source}: uv_faces must be (F, 3) indices into uv (F = {len(f)}, "
                          f"{len(uv)} UVs), got shape {uvf.shape}")
    if not np.isfinite(uv).all():
        raise DermisError(f"{source}: {int((~np.isfinite(uv).all(axis=1)).sum())} UVs are NaN/Inf")
    if mesh.texture_srgb is None:
        raise DermisError(f"{source}: no albedo texture: the file's material names none (or it was not "
                          "found). Set scene key mesh.texture = \"path/to/albedo.png\"")
    tex = np.asarray(mesh.texture_srgb)
    if tex.ndim != 3 or tex.shape[2] != 3 or tex.dtype != np.uint8:
        raise DermisError(f"{source}: texture must be (H, W, 3) uint8 sRGB, got {tex.shape} {tex.dtype}")

    # Degenerate faces: repeated index or round-off-level area.
    diag2 = float(np.sum((v.max(axis=0) - v.min(axis=0)) ** 2))
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    twice_area = np.linalg.norm(cross, axis=1)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    degenerate = repeated | (twice_area <= _DEGENERATE_REL_AREA * diag2)
    keep = ~degenerate
    # Duplicate faces: same vertex set, any order/orientation; keep the first.
    fs = np.sort(f, axis=1)
    _, first = np.unique(fs[keep], axis=0, return_index=True)
    kept_idx = np.flatnonzero(keep)
    dup_mask = np.ones(len(kept_idx), bool)
    dup_mask[first] = False
    n_dup = int(dup_mask.sum())
    keep[kept_idx[dup_mask]] = False
    f = f[keep]
    uvf = uvf[keep]

    # Non-manifold edges: an undirected edge used by more than two faces.
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    nm = counts > 2
    if nm.any():
        a, b = (int(x) for x in uniq[np.flatnonzero(nm)[0]])
        raise DermisError(f"{source}: {int(nm.sum())} non-manifold edges (shared by more than two faces), "
                          f"e.g. edge ({a}, {b}) at {np.round(v[a], 3).tolist()} mm used by "
                          f"{int(counts[nm][0])} faces; repair the scan (e.g. MeshLab 'Repair non-manifold "
                          "edges') and export again")
    # Drop unreferenced vertices (indices compacted; UVs are per corner and unaffected).
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    remap = np.cumsum(used) - 1
    v = v[used]
    f = remap[f]
    report = {
        "degenerate_faces_removed": int(degenerate.sum()),
        "duplicate_faces_removed": n_dup,
        "unreferenced_vertices_removed": int((~used).sum()),
        "boundary_edges": int((counts == 1).sum()),
        "triangles": int(len(f)),
        "vertices": int(len(v)),
    }
    info = dict(mesh.info)
    info["validate"] = report
    out = Mesh(vertices=v.astype(np.float64), faces=f.astype(np.int32),
               normals=angle_weighted_normals(v, f), uv=uv.astype(np.float32),
               uv_faces=uvf.astype(np.int32), texture_srgb=tex, info=info)
    return out, report


# ----------------------------------------------------------------------------------------------
# subdivision and displacement
# ----------------------------------------------------------------------------------------------

def _edge_ids(f: np.ndarray):
    """Unique undirected edges of faces and, per face, the edge id of sides (0-1, 1-2, 2-0)."""
    half = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1).reshape(-1, 2)
    key = np.sort(half, axis=1)
    n = int(f.max()) + 1
    code = key[:, 0].astype(np.int64) * n + key[:, 1]
    uniq, inv = np.unique(code, return_inverse=True)
    edges = np.stack([uniq // n, uniq % n], axis=1)
    return edges, inv.reshape(-1, 3)


def _subdivide_once(v, f, uv, uvf, scheme: str):
    """One 1-to-4 split; positions by Loop (or midpoints), UVs always linear (per corner)."""
    nv = len(v)
    edges, eid = _edge_ids(f)
    ne = len(edges)
    a, b = v[edges[:, 0]], v[edges[:, 1]]
    if scheme == "loop":
        # Loop 1987: odd vertex = 3/8 (a + b) + 1/8 (c + d) for interior edges, midpoint on a boundary.
        opp = f[:, [2, 0, 1]].reshape(-1)  # vertex opposite sides (0-1, 1-2, 2-0)
        e_flat = eid.reshape(-1)
        count = np.bincount(e_flat, minlength=ne)
        opp_sum = np.stack([np.bincount(e_flat, weights=v[opp, k], minlength=ne) for k in range(3)], axis=1)
        interior = count == 2
        odd = 0.5 * (a + b)
        odd[interior] = 0.375 * (a[interior] + b[interior]) + 0.125 * opp_sum[interior]
        # Even vertices: (1 - n beta) v + beta sum(neighbours), Loop's beta; boundary: 3/4 v + 1/8 (two nbrs).
        i, j = edges[:, 0], edges[:, 1]
        valence = np.bincount(np.concatenate([i, j]), minlength=nv).astype(np.float64)
        nbr = np.stack([np.bincount(i, weights=v[j, k], minlength=nv) + np.bincount(j, weights=v[i, k], minlength=nv)
                        for k in range(3)], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            beta = (0.625 - (0.375 + 0.25 * np.cos(2 * np.pi / valence)) ** 2) / valence
        beta = np.nan_to_num(beta)
        even = (1 - valence * beta)[:, None] * v + beta[:, None] * nbr
        bnd = ~interior
        if bnd.any():
            bi, bj = i[bnd], j[bnd]
            bsum = np.stack([np.bincount(bi, weights=v[bj, k], minlength=nv) + np.bincount(bj, weights=v[bi, k], minlength=nv)
                             for k in range(3)], axis=1)
            on_b = np.zeros(nv, bool)
            on_b[bi] = on_b[bj] = True
            even[on_b] = 0.75 * v[on_b] + 0.125 * bsum[on_b]
    elif scheme == "midpoint":
        odd = 0.5 * (a + b)
        even = v
    else:
        raise DermisError(f"make_high: scheme = {scheme!r}: must be 'loop' or 'midpoint'")
    new_v = np.concatenate([even, odd])
    m = nv + eid  # odd vertex per side
    c0, c1, c2 = f[:, 0], f[:, 1], f[:, 2]
    m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
    new_f = np.concatenate([np.stack([c0, m01, m20], 1), np.stack([m01, c1, m12], 1),
                            np.stack([m20, m12, c2], 1), np.stack([m01, m12, m20], 1)])
    # UVs: same split in UV-index space, so seams stay seams and charts stay continuous.
    nt = len(uv)
    uedges, ueid = _edge_ids(uvf)
    new_uv = np.concatenate([uv, 0.5 * (uv[uedges[:, 0]] + uv[uedges[:, 1]])])
    um = nt + ueid
    t0, t1, t2 = uvf[:, 0], uvf[:, 1], uvf[:, 2]
    new_uvf = np.concatenate([np.stack([t0, um[:, 0], um[:, 2]], 1), np.stack([um[:, 0], t1, um[:, 1]], 1),
                              np.stack([um[:, 2], um[:, 1], t2], 1), np.stack([um[:, 0], um[:, 1], um[:, 2]], 1)])
    return new_v, new_f, new_uv, new_uvf


def sample_image(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an (H, W[, C]) image at (N, 2) UVs (row = (1 - v)(H - 1), col = u(W - 1)).

    UVs outside [0, 1] are clamped to the border.
    """
    img = np.asarray(image)
    h, w = img.shape[:2]
    x = np.clip(np.asarray(uv[:, 0], dtype=np.float64), 0, 1) * (w - 1)
    y = (1.0 - np.clip(np.asarray(uv[:, 1], dtype=np.float64), 0, 1)) * (h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2 if w > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2 if h > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    if img.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def _vertex_uv_pairs(f: np.ndarray, uvf: np.ndarray, n_uv: int):
    """Unique (vertex, uv index) pairs used by face corners, sorted by vertex."""
    code = np.sort(f.reshape(-1).astype(np.int64) * n_uv + uvf.reshape(-1))
    # = np.unique(code), whose hash-based path took 1.4 s on the 3.4M corners of the scan
    # (numpy 2.x) against ~0.25 s for this sort
    first = np.ones(len(code), dtype=bool)
    first[1:] = code[1:] != code[:-1]
    uniq = code[first]
    return uniq // n_uv, uniq % n_uv


def make_high(mesh: Mesh, *, target_triangles: int, displacement=None, displacement_scale_mm: float = 0.0,
              displacement_mid: float = 0.5, scheme: str = "loop") -> Mesh:
    """Subdivide (and optionally displace) a mesh into the thesis's ~1M-triangle "scan".

    Parameters
    ----------
    mesh : Mesh
        A validated mesh with per-corner UVs.
    target_triangles : int
        Wanted triangle count (> 0).  A mesh with at least 0.8 x this many triangles is returned
        unchanged (a real scan is already "high"; a displacement is then *not* applied, because the
        scan already carries the detail; ``info["make_high"]`` says so).
    displacement : (H, W) float ndarray in [0, 1], optional
        Height map in the mesh's UV space.
    displacement_scale_mm : float
        mm per unit of the map: offset = (d - displacement_mid) * displacement_scale_mm.
    displacement_mid : float
        Map value with zero offset.
    scheme : {"loop", "midpoint"}
        Position rule.  "loop" (Loop 1987) approximates the smooth limit surface that sculpting tools
        displace (ZBrush subdivision levels are smoothed), "midpoint" keeps the facets.  UVs are always
        split linearly in UV-index space, so chart interiors stay continuous and seams stay seams.

    Returns
    -------
    Mesh
        ``ceil(log4(target / F))`` 1-to-4 splits; normals recomputed (angle-weighted) after the
        displacement; uv/uv_faces/texture carried; ``info["make_high"]`` records splits and scale.

    Notes
    -----
    The displacement is sampled bilinearly at each vertex's UV.  A seam vertex has several UVs; it
    takes the mean of the samples at all of them, so both sides of a seam move the same distance and
    the surface stays watertight.  The direction is the angle-weighted normal of the undisplaced
    subdivided surface.
    """
    if target_triangles <= 0:
        raise DermisError(f"make_high: target_triangles = {target_triangles}: must be > 0")
    info = dict(mesh.info)
    f = np.asarray(mesh.faces, dtype=np.int64)
    if len(f) >= _DENSE_FRACTION * target_triangles:
        info["make_high"] = {"splits": 0, "reason": f"already {len(f)} >= {_DENSE_FRACTION} x {target_triangles} "
                             "triangles; returned unchanged (no displacement applied)"}
        return Mesh(vertices=mesh.vertices, faces=mesh.faces, normals=mesh.normals, uv=mesh.uv,
                    uv_faces=mesh.uv_faces, texture_srgb=mesh.texture_srgb, info=info)
    if mesh.uv is None or mesh.uv_faces is None:
        raise DermisError("make_high: the mesh has no UVs; run validate() first")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    uv = np.asarray(mesh.uv, dtype=np.float64)
    uvf = np.asarray(mesh.uv_faces, dtype=np.int64)
    splits = 0
    while len(f) < target_triangles:
        v, f, uv, uvf = _subdivide_once(v, f, uv, uvf, scheme)
        splits += 1
    normals = angle_weighted_normals(v, f)
    rec = {"splits": splits, "scheme": scheme, "triangles": int(len(f))}
    if displacement is not None:
        d_img = np.asarray(displacement, dtype=np.float32)
        if d_img.ndim != 2:
            raise DermisError(f"make_high: displacement must be an (H, W) image, got shape {d_img.shape}")
        if not np.isfinite(displacement_scale_mm):
            raise DermisError(f"make_high: displacement_scale_mm = {displacement_scale_mm}: must be finite")
        pv, pt = _vertex_uv_pairs(f, uvf, len(uv))
        d = sample_image(d_img, uv[pt])
        cnt = np.bincount(pv, minlength=len(v))
        d_v = np.bincount(pv, weights=d, minlength=len(v)) / np.maximum(cnt, 1)
        offset = (d_v - displacement_mid) * displacement_scale_mm
        v = v + offset[:, None] * normals.astype(np.float64)
        normals = angle_weighted_normals(v, f)
        rec.update({"displacement_scale_mm": float(displacement_scale_mm), "displacement_mid": float(displacement_mid),
                    "offset_mm_min": float(offset.min()), "offset_mm_max": float(offset.max()),
                    "displacement_shape": list(d_img.shape)})
    info["make_high"] = rec
    return Mesh(vertices=v, faces=f.astype(np.int32), normals=normals, uv=uv.astype(np.float32),
                uv_faces=uvf.astype(np.int32), texture_srgb=mesh.texture_srgb, info=info)


# ----------------------------------------------------------------------------------------------
# simplification
# ----------------------------------------------------------------------------------------------

def simplify(mesh: Mesh, *, target_triangles: int = 16750) -> Mesh:
    """Quadric-error simplification to about ``target_triangles`` (docs/science.md §6: QSlim).

    Parameters
    ----------
    mesh : Mesh
        The high mesh.
    target_triangles : int
        Wanted count; default 16,750 is the thesis's low-quality mesh (docs/science.md §6).

    Returns
    -------
    Mesh
        Vertices/faces/normals only (UVs come from :func:`transfer_uv`); ``info["simplify"]``.

    Notes
    -----
    fast-simplification (Forstmann's quadric simplifier: Garland-Heckbert error quadrics with a
    threshold sweep instead of QSlim's heap) was chosen over ``igl.qslim`` and ``igl.decimate`` by
    measurement on the LPS head (1,131,776 triangles, Loop 3x + displacement) -> 16,750, this machine
    (2 cores); distance from the low to the high mesh, mm (bench/bench_mesh_prep.py --compare; mean
    and Hausdorff from 200k points sampled on the low mesh / igl.hausdorff):

    ======================  =======  =========  =========
    method                  seconds  mean (mm)  Hausdorff
    ======================  =======  =========  =========
    fast-simplification     3.1      0.064      0.81
    igl.qslim               16.4     0.039      0.80
    open3d quadric          37.7     0.039      0.75
    igl.decimate (edge len) 15.8     0.153      6.19
    ======================  =======  =========  =========

    The quadric methods share the worst-case error; fast-simplification's mean error is 0.025 mm
    larger (far below the 0.4 mm rms displacement that the bump bake captures) and it is the only
    one under the 5 s budget.  Lower ``agg`` (4, 2) stops far short of the target count.
    """
    import fast_simplification

    if target_triangles < 4:
        raise DermisError(f"simplify: target_triangles = {target_triangles}: must be >= 4")
    v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    f = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    info = dict(mesh.info)
    if len(f) <= target_triangles:
        info["simplify"] = {"triangles_in": int(len(f)), "triangles_out": int(len(f)), "note": "already small"}
        return Mesh(vertices=v, faces=f, normals=angle_weighted_normals(v, f), info=info)
    vo, fo = fast_simplification.simplify(v, f, target_count=int(target_triangles))
    fo = np.asarray(fo, dtype=np.int64)
    # Drop vertices no face uses any more (the library keeps none, but be sure) and degenerate faces.
    fo = fo[(fo[:, 0] != fo[:, 1]) & (fo[:, 1] != fo[:, 2]) & (fo[:, 2] != fo[:, 0])]
    used = np.zeros(len(vo), bool)
    used[fo.ravel()] = True
    remap = np.cumsum(used) - 1
    vo = np.asarray(vo, dtype=np.float64)[used]
    fo = remap[fo]
    info["simplify"] = {"method": "fast-simplification", "triangles_in": int(len(f)),
                        "triangles_out": int(len(fo)), "target": int(target_triangles)}
    return Mesh(vertices=vo, faces=fo.astype(np.int32), normals=angle_weighted_normals(vo, fo),
                info=info)


# ----------------------------------------------------------------------------------------------
# UV transfer
# ----------------------------------------------------------------------------------------------

def _perimeter(t0, t1, t2):
    """Perimeter of triangles with corners t0, t1, t2 (any leading shape, points on the last axis)."""
    return (np.linalg.norm(t1 - t0, axis=-1) + np.linalg.norm(t2 - t1, axis=-1)
            + np.linalg.norm(t0 - t2, axis=-1))


class _HighCharts:
    """The high mesh's UV parameterisation, as the UV transfer reads it.

    ``pv``/``pt``: the (vertex, uv) pairs of the face corners, sorted by vertex (``pstart``,
    ``pcount``: CSR by vertex); ``sigma``: local UV/3-D scale per vertex (transfer_uv Notes 3);
    :meth:`pair_jacobian`: the chart's d(uv)/d(x) around a pair (Notes 4).
    """

    def __init__(self, high: Mesh):
        hv = np.asarray(high.vertices, dtype=np.float64)
        hf = np.asarray(high.faces, dtype=np.int64)
        huv = np.asarray(high.uv, dtype=np.float64)
        huvf = np.asarray(high.uv_faces, dtype=np.int64)
        nh, nuv = len(hv), len(huv)
        self.vertices, self.uv = hv, huv
        self.pv, self.pt = _vertex_uv_pairs(hf, huvf, nuv)
        self.pcount = np.bincount(self.pv, minlength=nh)
        self.pstart = np.concatenate([[0], np.cumsum(self.pcount)[:-1]])
        p0, p1, p2 = hv[hf[:, 0]], hv[hf[:, 1]], hv[hf[:, 2]]
        t0, t1, t2 = huv[huvf[:, 0]], huv[huvf[:, 1]], huv[huvf[:, 2]]
        corner_v = hf.reshape(-1)
        sig_num = np.bincount(corner_v, weights=np.repeat(_perimeter(t0, t1, t2), 3), minlength=nh)
        sig_den = np.bincount(corner_v, weights=np.repeat(_perimeter(p0, p1, p2), 3), minlength=nh)
        self.sigma = sig_num / np.maximum(sig_den, 1e-300)
        # the faces' Jacobians are made in pair_jacobian for the faces it needs (the seam
        # pairs: ~0.1 % of the 1.1M faces; all of them took 1.5 of mesh_low's 8 s)
        self._faces, self._uv_faces = hf, huvf
        # pair index of each high face corner
        self.corner_pair = np.searchsorted(self.pv * nuv + self.pt, corner_v * nuv + huvf.reshape(-1))

    @staticmethod
    def _face_jacobians(e1, e2, d1, d2):
        """Per face: area and the Jacobian J = D pinv(E) (2 x 3) of uv with respect to x."""
        g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
        det = g11 * g22 - g12 * g12
        inv_det = np.where(det > 0, 1.0 / np.maximum(det, 1e-300), 0.0)
        # pinv(E) rows: (g22 e1 - g12 e2)/det, (g11 e2 - g12 e1)/det ; J = D @ pinv(E)
        r1 = (g22[:, None] * e1 - g12[:, None] * e2) * inv_det[:, None]
        r2 = (g11[:, None] * e2 - g12[:, None] * e1) * inv_det[:, None]
        jac = d1[:, :, None] * r1[:, None, :] + d2[:, :, None] * r2[:, None, :]     # (Fh, 2, 3)
        return 0.5 * np.sqrt(np.maximum(det, 0)), jac

    def nearest_vertex(self, points: np.ndarray) -> np.ndarray:
        """Index of the nearest high vertex of each point (scipy cKDTree)."""
        from scipy.spatial import cKDTree

        _, near = cKDTree(self.vertices).query(points, k=1)
        return np.asarray(near, dtype=np.int64)

    def pair_jacobian(self, pairs: np.ndarray) -> np.ndarray:
        """Area-weighted mean Jacobian of the high faces around each (vertex, uv) pair."""
        want = np.full(len(self.pt), -1, np.int64)
        want[pairs] = np.arange(len(pairs))
        slot = want[self.corner_pair]
        m = slot >= 0
        face_of = np.repeat(np.arange(len(self._faces)), 3)[m]
        faces, face_of = np.unique(face_of, return_inverse=True)
        f, tf = self._faces[faces], self._uv_faces[faces]
        hv, huv = self.vertices, self.uv
        area, jac = self._face_jacobians(hv[f[:, 1]] - hv[f[:, 0]], hv[f[:, 2]] - hv[f[:, 0]],
                                         huv[tf[:, 1]] - huv[tf[:, 0]],
                                         huv[tf[:, 2]] - huv[tf[:, 0]])
        w = area[face_of]
        out = np.zeros((len(pairs), 2, 3))
        for a in range(2):
            for b in range(3):
                out[:, a, b] = np.bincount(slot[m], weights=w * jac[face_of, a, b], minlength=len(pairs))
        wsum = np.bincount(slot[m], weights=w, minlength=len(pairs))
        return out / np.maximum(wsum, 1e-300)[:, None, None]


def _smallest_perimeter_pairs(charts: _HighCharts, corner_h: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Notes 1-2: per low corner the high pair of the smallest-UV-perimeter combination.

    Returns the (F, 3) pair indices, the number of triangles with a choice ("seam_choices")
    and of corners with more than ``_MAX_CANDIDATES`` candidates ("truncated_candidates").
    """
    K = _MAX_CANDIDATES
    ncand = charts.pcount[corner_h]
    truncated = int((ncand > K).sum())
    ks = np.arange(K)
    cand = np.where(ks[None, None, :] < np.minimum(ncand, K)[:, :, None],
                    charts.pstart[corner_h][:, :, None] + ks[None, None, :], -1)   # (F, 3, K)
    chosen = cand[:, :, 0].copy()
    seam_tris = np.flatnonzero((ncand > 1).any(axis=1))
    if len(seam_tris):
        c = cand[seam_tris]                         # (S, 3, K)
        i0, i1, i2 = np.meshgrid(ks, ks, ks, indexing="ij")
        combos = np.stack([i0.ravel(), i1.ravel(), i2.ravel()], axis=1)   # (K^3, 3)
        sel = np.stack([c[:, 0, combos[:, 0]], c[:, 1, combos[:, 1]], c[:, 2, combos[:, 2]]], axis=2)  # (S, K^3, 3)
        valid = (sel >= 0).all(axis=2)
        uvs = charts.uv[charts.pt[np.maximum(sel, 0)]]           # (S, K^3, 3, 2)
        per = _perimeter(uvs[:, :, 0], uvs[:, :, 1], uvs[:, :, 2])
        per[~valid] = np.inf
        best = np.argmin(per, axis=1)
        chosen[seam_tris] = sel[np.arange(len(seam_tris)), best]
    return chosen, int(len(seam_tris)), truncated


def _uv_ratio(low_uv, corner_uv_idx, expect):
    """Notes 3: UV perimeter of each low triangle over its expected value."""
    t = low_uv[corner_uv_idx]
    return _perimeter(t[:, 0], t[:, 1], t[:, 2]) / expect


def _relay_odd_corner(charts, low_uv, corner_uv_idx, corner_pair, lp, bad):
    """Notes 4, one pass: the odd corner of each triangle in ``bad`` gets a new UV extrapolated
    from the two good corners' charts.  Returns the extended UV table (indices updated in place)."""
    t = low_uv[corner_uv_idx[bad]]                                  # (B, 3, 2)
    dist = np.stack([np.linalg.norm(t[:, 0] - t[:, 1], axis=1) + np.linalg.norm(t[:, 0] - t[:, 2], axis=1),
                     np.linalg.norm(t[:, 1] - t[:, 0], axis=1) + np.linalg.norm(t[:, 1] - t[:, 2], axis=1),
                     np.linalg.norm(t[:, 2] - t[:, 0], axis=1) + np.linalg.norm(t[:, 2] - t[:, 1], axis=1)], 1)
    off = np.argmax(dist, axis=1)
    goods = np.stack([(off + 1) % 3, (off + 2) % 3], axis=1)
    rows = np.arange(len(bad))
    new_uv = np.zeros((len(bad), 2))
    for g in range(2):
        gk = goods[:, g]
        gpair = corner_pair[bad, gk]
        ok = gpair >= 0
        jac_g = np.zeros((len(bad), 2, 3))
        if ok.any():
            jac_g[ok] = charts.pair_jacobian(gpair[ok])
        dp = lp[bad, off] - lp[bad, gk]
        new_uv += t[rows, gk] + np.einsum("nij,nj->ni", jac_g, dp)
    new_uv *= 0.5
    start = len(low_uv)
    corner_uv_idx[bad, off] = start + rows
    corner_pair[bad, off] = -1
    return np.concatenate([low_uv, new_uv])


def _flatten_into_anchor_chart(charts, low_uv, corner_uv_idx, corner_pair, lp, bad):
    """Notes 4, last resort: keep the corner of ``bad`` nearest the others in UV (an original
    pair) and lay the other two out with its Jacobian.  Returns (UV table, triangles changed)."""
    t = low_uv[corner_uv_idx[bad]]
    dist = np.stack([np.linalg.norm(t[:, k] - t[:, (k + 1) % 3], axis=1)
                     + np.linalg.norm(t[:, k] - t[:, (k + 2) % 3], axis=1) for k in range(3)], 1)
    dist[~(corner_pair[bad] >= 0)] = np.inf
    has_anchor = np.isfinite(dist).any(axis=1)
    bad, dist, t = bad[has_anchor], dist[has_anchor], t[has_anchor]
    anchor = np.argmin(dist, axis=1)
    rows = np.arange(len(bad))
    jac_a = charts.pair_jacobian(corner_pair[bad, anchor])
    for step in (1, 2):
        k = (anchor + step) % 3
        dp = lp[bad, k] - lp[bad, anchor]
        start = len(low_uv)
        low_uv = np.concatenate([low_uv, t[rows, anchor] + np.einsum("nij,nj->ni", jac_a, dp)])
        corner_uv_idx[bad, k] = start + rows
        corner_pair[bad, k] = -1
    return low_uv, bad


def transfer_uv(high: Mesh, low: Mesh) -> tuple[Mesh, dict]:
    """Give the low mesh texture coordinates from the high mesh (thesis method, docs/science.md §6).

    Parameters
    ----------
    high : Mesh
        Mesh with ``uv``/``uv_faces`` (and ``texture_srgb``), mm.
    low : Mesh
        Simplification of ``high`` (no UVs needed), mm.

    Returns
    -------
    low : Mesh
        Copy of ``low`` with ``uv`` (T, 2) float32, ``uv_faces`` (F, 3) int32 and ``texture_srgb``
        from ``high``.
    report : dict
        ``{"triangles", "seam_choices", "straddling", "repaired", "unrepaired",
        "max_uv_perimeter_ratio", "truncated_candidates", "seam_ratio_bound"}``.

    Notes
    -----
    1. Each low vertex takes its nearest high vertex (scipy cKDTree); that vertex's UVs (several on
       a seam, at most 4 used) are the candidates.
    2. Per low triangle the combination of corner candidates with the smallest UV perimeter is
       chosen ("seam_choices" counts triangles where a corner had more than one candidate).
    3. Straddle test.  The local UV/3-D scale of a high vertex is sigma_h = (sum of UV perimeters) /
       (sum of 3-D perimeters) of its incident high faces.  A low triangle with 3-D perimeter P and
       UV perimeter P_uv has ratio r = P_uv / (P * mean sigma_h over its corners' nearest high
       vertices).  r is ~1 inside a chart (up to the atlas's anisotropic stretch) and is as large as
       the gap between charts / the triangle's size when the triangle straddles a seam, because the
       low vertices need not lie on the high mesh's cut.  r > 3 (``_SEAM_RATIO``) counts as straddling.
    4. Repair.  The offending corner is the one with the largest summed UV distance to the other
       two.  It gets a new UV entry (the old one may be shared by correct triangles): the mean over
       the two good corners g of ``uv_g + J_g (p - p_g)``, where J_g (2x3) is the area-weighted mean
       Jacobian d(uv)/d(x) of the high faces around g's nearest high vertex in g's chart, i.e. the
       good chart's parameterisation extrapolated to the corner.  Up to two passes (a triangle
       touching three charts); a triangle still above the bound is flattened into the chart of its
       corner nearest the others (both other corners laid out with that corner's Jacobian).
       "straddling" counts triangles above the bound before repair, "repaired" those fixed,
       "unrepaired" those still above it (only at parameterisation singularities such as a lat-long
       pole); "max_uv_perimeter_ratio" is the largest r after repair.
    """
    if high.uv is None or high.uv_faces is None:
        raise DermisError("transfer_uv: the high mesh has no UVs; run validate() on it first")
    charts = _HighCharts(high)
    lv = np.asarray(low.vertices, dtype=np.float64)
    lf = np.asarray(low.faces, dtype=np.int64)
    nl = len(lf)
    corner_h = charts.nearest_vertex(lv)[lf]                            # (F, 3)
    chosen, seam_choices, truncated = _smallest_perimeter_pairs(charts, corner_h)

    # Low UV table: one entry per used pair, then repaired corners appended.
    used_pairs, corner_uv_idx = np.unique(chosen, return_inverse=True)
    corner_uv_idx = corner_uv_idx.reshape(nl, 3)
    low_uv = charts.uv[charts.pt[used_pairs]]
    corner_pair = used_pairs[corner_uv_idx]  # pair index (into pv/pt) of each corner, -1 after repair

    lp = lv[lf]                                                         # (F, 3, 3)
    expect = np.maximum(_perimeter(lp[:, 0], lp[:, 1], lp[:, 2]) * charts.sigma[corner_h].mean(axis=1),
                        1e-300)
    r = _uv_ratio(low_uv, corner_uv_idx, expect)
    flagged0 = r > _SEAM_RATIO
    repaired_any = np.zeros(nl, bool)
    for _ in range(_REPAIR_PASSES):
        bad = np.flatnonzero(r > _SEAM_RATIO)
        if not len(bad):
            break
        low_uv = _relay_odd_corner(charts, low_uv, corner_uv_idx, corner_pair, lp, bad)
        repaired_any[bad] = True
        r = _uv_ratio(low_uv, corner_uv_idx, expect)
    bad = np.flatnonzero(r > _SEAM_RATIO)
    if len(bad):
        low_uv, flattened = _flatten_into_anchor_chart(charts, low_uv, corner_uv_idx, corner_pair,
                                                       lp, bad)
        repaired_any[flattened] = True
        r = _uv_ratio(low_uv, corner_uv_idx, expect)
    still = r > _SEAM_RATIO
    report = {
        "triangles": int(nl),
        "seam_choices": seam_choices,
        "straddling": int(flagged0.sum()),
        "repaired": int((repaired_any & ~still).sum()),
        "unrepaired": int(still.sum()),
        "max_uv_perimeter_ratio": float(r.max()) if nl else 0.0,
        "truncated_candidates": truncated,
        "seam_ratio_bound": _SEAM_RATIO,
    }
    info = dict(low.info)
    info["transfer_uv"] = report
    out = Mesh(vertices=low.vertices, faces=low.faces, normals=low.normals,
               uv=low_uv.astype(np.float32), uv_faces=corner_uv_idx.astype(np.int32),
               texture_srgb=high.texture_srgb, info=info)
    return out, report
