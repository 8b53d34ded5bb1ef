"""Mesh validation at the pipeline boundary: refuse what cannot be rendered, repair what is safe.

Refused (with the source named): NaN/Inf coordinates or UVs, bad shapes or indices, non-manifold
edges, missing UVs or albedo texture (:func:`validate`); coordinates beyond what float32 ray
casting holds, a sub-micron extent, no triangle of non-zero area, or a size no human subject
has, which is a unit mistake (:func:`check_extent`).
Repaired and reported: degenerate and duplicate faces, unreferenced vertices.  The scan readers
(:mod:`dermis.geometry.scan`) hand their meshes here.

Conventions (pipeline/artifacts.py): mm; UV origin bottom-left (OBJ convention): texel row from
the top is ``(1 - v) * (H - 1)``, column ``u * (W - 1)``.
"""
from __future__ import annotations

import numpy as np

from dermis.pipeline.artifacts import Mesh
from dermis.geometry.normals import angle_weighted_normals
from dermis.geometry.scan import UNITS_MM
from dermis.pipeline.errors import DermisError

__all__ = ["validate", "check_extent", "MAX_COORDINATE_MM", "MIN_EXTENT_MM",
           "SUBJECT_SIZE_MM"]

# validate: a face counts as zero-area when twice its area is below this fraction of the squared
# bounding-box diagonal.  1e-14 is ~100x float64 round-off for a cross product of coordinates of
# that size, so only faces that are degenerate up to round-off are removed.
_DEGENERATE_REL_AREA = 1e-14

# Coordinates the pipeline can render (mm, after mesh.units): the ray caster and the kernels
# work in float32, whose squares overflow near 1.8e19; a head is ~200 mm.  A mesh beyond
# 1e7 mm (10 km) or smaller than 1e-3 mm (1 um) across is a unit mistake, not a face.
MAX_COORDINATE_MM = 1e7
MIN_EXTENT_MM = 1e-3

# The sizes a scanned subject can have (mm, the largest side of its bounding box): a skin
# patch of 1 cm up to a whole body with room to spare.  The shipped head scan is 431 x 400 x
# 261 mm (scenes/assets/lps_head, head and shoulders), the procedural head 149 x 300 x 221
# mm.  A file in mm declared as m (or in m declared as mm) is 1000 times off: that head at
# 431,000 mm or 0.43 mm.  Rendered with the quick scene's camera and point light (Lafortune,
# 64 x 64), the first gives an image of mean 1.7e-6 against 0.0147 at the right scale
# (near-black), the second one that no camera ray hits.
SUBJECT_SIZE_MM = (10.0, 5000.0)
# where the likely unit puts the subject: closest to this size (a head) on a log scale
_TYPICAL_SIZE_MM = 300.0


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


def check_extent(mesh, *, source: str, units: str) -> None:
    """Refuse a mesh whose size the pipeline cannot render, which has no surface, or whose
    size no human subject has: finite coordinates beyond MAX_COORDINATE_MM, an extent below
    MIN_EXTENT_MM, no triangle of non-zero area (every face degenerate: repeated indices or
    collinear corners), or a largest bounding-box side outside SUBJECT_SIZE_MM (a unit
    mistake: the message names the measured size, ``units`` and the likely unit)."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces)
    finite = np.isfinite(v).all(axis=1)
    if not finite.all() or v.size == 0 or f.size == 0:
        return  # validate() names NaN/Inf vertices and empty meshes
    used = v[np.unique(f.ravel())] if f.max() < len(v) and f.min() >= 0 else v
    peak = float(np.abs(used).max())
    extent = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    if peak > MAX_COORDINATE_MM:
        raise DermisError(f"{source}: coordinates reach {peak:.3g} mm (mesh.units = \"{units}\"); "
                          f"allowed: |x| <= {MAX_COORDINATE_MM:g} mm. Check mesh.units, or "
                          "scale the scan in the export")
    if extent < MIN_EXTENT_MM:
        raise DermisError(f"{source}: the mesh is {extent:.3g} mm across (mesh.units = "
                          f"\"{units}\"); allowed: >= {MIN_EXTENT_MM:g} mm. Check mesh.units")
    a, b, c = (v[f[:, k]] for k in range(3))
    twice_area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    good = ~repeated & (twice_area > _DEGENERATE_REL_AREA * extent ** 2)
    if not good.any():
        raise DermisError(f"{source}: all {len(f)} triangles are degenerate (repeated vertex "
                          "indices or zero area): the mesh has no surface to render")
    _check_subject_size(used.max(axis=0) - used.min(axis=0), source=source, units=units)


def _check_subject_size(sides, *, source: str, units: str) -> None:
    """Refuse bounding-box ``sides`` (mm) whose largest lies outside SUBJECT_SIZE_MM, naming
    the unit of :data:`dermis.geometry.scan.UNITS_MM` that would bring it inside (the one
    nearest a head's size), if any."""
    lo, hi = SUBJECT_SIZE_MM
    size = float(np.max(sides))
    if lo <= size <= hi:
        return
    declared = UNITS_MM.get(units, 1.0)
    fits = {u: size / declared * mm for u, mm in UNITS_MM.items()
            if u != units and lo <= size / declared * mm <= hi}
    dims = " x ".join(f"{float(x):.3g}" for x in sides)
    if fits:
        unit = min(fits, key=lambda u: abs(np.log(fits[u] / _TYPICAL_SIZE_MM)))
        fix = (f"the file is likely in {unit} (largest side {fits[unit]:.3g} mm): set "
               f"mesh.units = \"{unit}\"")
    else:
        fix = "no unit of mesh.units brings it there: scale the scan in the export"
    raise DermisError(f"{source}: the mesh is {dims} mm (largest side {size:.3g} mm) with "
                      f"mesh.units = \"{units}\"; a human subject's largest side is {lo:g} to "
                      f"{hi:g} mm (a head about 200-450 mm): {fix}")
