"""UV transfer from the high mesh to its simplification (thesis method, docs/science.md §6).

The thesis gives the ~16,750-triangle QSlim simplification the scan's texture coordinates by
"nearest old vertex -> its UV(s); at seams pick the UV combination with the smallest texture-space
perimeter; repair triangles that straddle the cut".  :func:`transfer_uv` does exactly that, the
repair extrapolating a good corner's chart (its Notes).

Conventions (pipeline/artifacts.py): mm; UV origin bottom-left (OBJ convention): texel row from
the top is ``(1 - v) * (H - 1)``, column ``u * (W - 1)``.
"""
from __future__ import annotations

import numpy as np

from dermis.geometry.subdivision import vertex_uv_pairs
from dermis.pipeline.artifacts import Mesh
from dermis.pipeline.errors import DermisError

__all__ = ["transfer_uv"]

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
        self.pv, self.pt = vertex_uv_pairs(hf, huvf, nuv)
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
