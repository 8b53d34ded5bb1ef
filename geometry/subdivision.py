"""Subdivision and displacement: the thesis's ~1M-triangle "scan" from a coarser mesh.

1-to-4 splits by Loop's rule (C. Loop, "Smooth subdivision surfaces based on triangles", 1987) or
at edge midpoints, with the UVs split linearly per corner so charts stay continuous and seams stay
seams; then an optional displacement along the angle-weighted normals by a height map sampled at
the UVs (:func:`sample_image`), with the calibration of the Lee Perry-Smith scan's map.

Conventions (pipeline/artifacts.py): mm; UV origin bottom-left (OBJ convention): texel row from
the top is ``(1 - v) * (H - 1)``, column ``u * (W - 1)``.
"""
from __future__ import annotations

import numpy as np

from dermis.pipeline.artifacts import Mesh
from dermis.geometry.normals import angle_weighted_normals
from dermis.pipeline.errors import DermisError

__all__ = ["LPS_DISPLACEMENT_SCALE_MM", "LPS_DISPLACEMENT_MID", "make_high", "sample_image",
           "vertex_uv_pairs"]

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

# make_high: "already dense" if the mesh has at least this fraction of the requested count.
_DENSE_FRACTION = 0.8


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


def vertex_uv_pairs(f: np.ndarray, uvf: np.ndarray, n_uv: int):
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
        pv, pt = vertex_uv_pairs(f, uvf, len(uv))
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
