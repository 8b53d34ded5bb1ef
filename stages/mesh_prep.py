"""Mesh preparation, geometry steps: load a scan, validate it, build the high and low meshes.

The thesis setup (physics.md section 6) renders a ~1M-triangle scan and a ~16,750-triangle
QSlim simplification of it whose texture coordinates are transferred from the scan ("nearest
old vertex -> its UV(s); at seams pick the UV combination with the smallest texture-space
perimeter; repair triangles that straddle the cut").  This module holds those steps as pure
functions on :class:`pipeline.artifacts.Mesh`; the bake lives in ``stages/bake.py`` and the
lead composes the steps into the cached graph.

Steps
-----
``load_scan``      OBJ / PLY / glTF / GLB -> Mesh (mm, welded positions, per-corner UVs, uint8 sRGB albedo)
``validate``       refuse NaN/Inf, non-manifold edges, missing UVs/texture; remove degenerate and
                   duplicate faces and unreferenced vertices (reported)
``make_high``      subdivide (Loop or midpoint) to a target count, optionally displace along normals
``simplify``       quadric-error decimation (fast-simplification, measured against libigl)
``vertex_normals`` angle-weighted vertex normals (Thuermer & Wuethrich 1998, physics.md section 6)
``transfer_uv``    the thesis's nearest-vertex UV transfer with seam choice and straddle repair

Conventions (pipeline/artifacts.py): mm; UV origin bottom-left (OBJ convention): texel row from
the top is ``(1 - v) * (H - 1)``, column ``u * (W - 1)``.
"""
from __future__ import annotations

import json
import os
import struct
import tempfile
from pathlib import Path

import numpy as np

from pipeline.artifacts import Mesh, angle_weighted_normals
from pipeline.errors import DermisError
from pipeline.store import file_digest

__all__ = [
    "VERSION", "KERNELS", "LPS_DISPLACEMENT_SCALE_MM", "LPS_DISPLACEMENT_MID",
    "load_scan", "validate", "make_high", "simplify", "vertex_normals", "transfer_uv",
    "sample_image", "read_grey_image",
]

VERSION = 1
KERNELS: tuple[str, ...] = ()

# Millimetres per unit for the ``units`` option of load_scan (physics.md: mm inside the pipeline).
_UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}

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
# loading
# ----------------------------------------------------------------------------------------------

# glTF files known to store TEXCOORD_0 in OBJ convention (v = 0 at the image bottom) against the
# glTF spec (v = 0 at the top).  Keyed by SHA-256 of the whole file, so only these exact bytes are
# treated specially.  See /work/shared/data/lps_head/README.md ("UV pitfall").
_GLTF_OBJ_CONVENTION_SHA256 = {
    "402b8a8ac9f03232e6d64b5962929703a069daf99d3c49ac8eb0e48bedc9c576":
        "three.js examples/models/gltf/LeePerrySmith/LeePerrySmith.glb",
}


def load_scan(path, *, units: str = "mm", texture=None, flip_v: bool | None = None) -> Mesh:
    """Read a textured triangle mesh (OBJ, PLY, glTF, GLB) into a :class:`Mesh` in mm.

    Parameters
    ----------
    path : str or os.PathLike
        The mesh file.  ``.obj`` (with ``mtllib``/``map_Kd``), ``.ply`` (ascii or binary, per-vertex
        ``u,v``/``s,t``/``texture_u,texture_v`` or per-face ``texcoord`` lists, ``comment TextureFile``),
        ``.gltf``/``.glb`` (triangle primitives of the default scene with node transforms,
        ``TEXCOORD_0``, ``baseColorTexture``).
    units : {"mm", "cm", "m"}, optional
        Unit of the file's coordinates; positions are multiplied into mm.
    texture : str or os.PathLike, optional
        Albedo image to use instead of the one named by the file's material (scene key
        ``mesh.texture``).  Read with OpenImageIO and kept as uint8 sRGB.
    flip_v : bool, optional
        Replace v by 1 - v.  Default (None): glTF files follow the glTF spec (v = 0 at the image top),
        so v is flipped into this pipeline's OBJ convention -- except for files known to store OBJ-
        convention UVs (the three.js LeePerrySmith.glb, recognised by its SHA-256; see the lps_head
        README "UV pitfall"), which are left as stored.  OBJ and PLY are never flipped by default.

    Returns
    -------
    Mesh
        ``vertices`` (V, 3) float64 mm with exactly equal positions welded (seam-split vertices share
        topology), ``faces`` (F, 3) int32, ``uv`` (T, 2) float32 (exact duplicates merged) with
        ``uv_faces`` (F, 3) int32 per corner, ``texture_srgb`` (H, W, 3) uint8 or None, ``normals``
        None (the file's normals are per split vertex; :func:`validate` computes angle-weighted ones),
        ``info`` with source, format, units, scale, weld counts and the UV convention applied.

    Raises
    ------
    DermisError
        The file (or its texture) is missing or unreadable, the format or unit is unknown.
    """
    path = Path(path)
    if units not in _UNITS_MM:
        raise DermisError(f"load_scan: units = {units!r} for {path}: must be one of {sorted(_UNITS_MM)}")
    if not path.is_file():
        raise DermisError(f"mesh file not found: {path} (scene key mesh.path)")
    ext = path.suffix.lower()
    try:
        if ext == ".obj":
            raw = _read_obj(path)
        elif ext == ".ply":
            raw = _read_ply(path)
        elif ext in (".gltf", ".glb"):
            raw = _read_gltf(path)
        else:
            raise DermisError(f"mesh file {path}: unknown format {ext!r}; supported: .obj .ply .gltf .glb")
    except DermisError:
        raise
    except Exception as exc:  # parse errors of any kind become one user-facing message
        raise DermisError(f"mesh file {path} could not be read: {type(exc).__name__}: {exc}") from exc

    positions, faces, uv, uv_faces, tex_path, tex_bytes = raw
    info: dict = {"source": str(path), "format": ext.lstrip("."), "units": units,
                  "mm_per_unit": _UNITS_MM[units]}

    # UV convention: see the docstring; record what was done so a wrong texture can be traced.
    if flip_v is None:
        flip_v = False
        if ext in (".gltf", ".glb"):
            digest = file_digest(path)
            known = _GLTF_OBJ_CONVENTION_SHA256.get(digest)
            flip_v = known is None
            info["uv_convention"] = (f"stored in OBJ convention ({known}); not flipped" if known
                                     else "glTF convention (v=0 at top); flipped to v=1-v")
        else:
            info["uv_convention"] = "OBJ convention (v=0 at bottom); not flipped"
    else:
        info["uv_convention"] = f"flip_v={flip_v} given explicitly"
    if uv is not None and flip_v:
        uv = uv.copy()
        uv[:, 1] = 1.0 - uv[:, 1]

    # Weld exactly equal positions so seam-split vertices share topology; keep first-occurrence order.
    positions = np.asarray(positions, dtype=np.float64)
    _, first, inverse = np.unique(positions, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    vertices = positions[first[order]] * _UNITS_MM[units]
    faces = rank[inverse[np.asarray(faces, dtype=np.int64)]]
    info["vertices_in_file"] = int(len(positions))
    info["vertices_welded"] = int(len(positions) - len(vertices))

    if uv is not None:
        uv = np.asarray(uv, dtype=np.float32)
        uv_unique, uv_inv = np.unique(uv, axis=0, return_inverse=True)
        uv_faces = uv_inv.reshape(-1)[np.asarray(uv_faces, dtype=np.int64)].astype(np.int32)
        uv = uv_unique.astype(np.float32)

    if texture is not None:
        tex_path, tex_bytes = Path(texture), None
    texture_srgb = None
    if tex_bytes is not None:
        texture_srgb = _read_image_bytes(tex_bytes, f"{path} (embedded baseColorTexture)")
        info["texture"] = f"{path}#embedded"
    elif tex_path is not None:
        texture_srgb = _read_texture(Path(tex_path))
        info["texture"] = str(tex_path)

    return Mesh(vertices=vertices, faces=faces.astype(np.int32), normals=None, uv=uv,
                uv_faces=uv_faces, texture_srgb=texture_srgb, info=info)


def _read_texture(path: Path) -> np.ndarray:
    """Read an albedo image as (H, W, 3) uint8 sRGB with OpenImageIO."""
    import OpenImageIO as oiio

    if not path.is_file():
        raise DermisError(f"texture file not found: {path} (scene key mesh.texture)")
    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise DermisError(f"texture file {path} could not be read: {buf.geterror()}")
    spec = buf.spec()
    linear = spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE) and \
        "linear" in spec.get_string_attribute("oiio:ColorSpace", "linear").lower()
    if linear:
        # Float images (EXR) hold linear values: encode with the sRGB curve before quantising.
        px = np.clip(np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float64), 0.0, 1.0)
        px = np.where(px <= 0.0031308, 12.92 * px, 1.055 * px ** (1 / 2.4) - 0.055)
        img = np.round(px * 255.0).astype(np.uint8)
    else:
        img = np.asarray(buf.get_pixels(oiio.UINT8))
    if img.ndim == 2:
        img = img[:, :, None]
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    elif img.shape[2] == 2:  # grey + alpha
        img = np.repeat(img[:, :, :1], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])


def _read_image_bytes(data: bytes, what: str) -> np.ndarray:
    """Decode an in-memory image (glTF bufferView) through a temporary file for OpenImageIO."""
    fd, tmp = tempfile.mkstemp(suffix=".img")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        try:
            return _read_texture(Path(tmp))
        except DermisError as exc:
            raise DermisError(f"texture {what} could not be decoded: {exc}") from exc
    finally:
        os.unlink(tmp)


def read_grey_image(path) -> np.ndarray:
    """Read a single-channel image (displacement/bump) as (H, W) float32 in [0, 1].

    Multi-channel images use their first channel.  Raises DermisError naming the path.
    """
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise DermisError(f"image file not found: {path}")
    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise DermisError(f"image file {path} could not be read: {buf.geterror()}")
    px = np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)
    if px.ndim == 3:
        px = px[:, :, 0]
    return np.ascontiguousarray(px)


def _read_obj(path: Path):
    """Parse an OBJ: positions, triangulated faces, per-corner vt indices, map_Kd path."""
    v_lines, vt_lines, f_lines = [], [], []
    mtllibs, usemtl = [], []
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.startswith("v "):
                v_lines.append(line[2:])
            elif line.startswith("vt"):
                vt_lines.append(line[3:])
            elif line.startswith("f "):
                f_lines.append(line[2:].split())
            elif line.startswith("mtllib"):
                mtllibs.append(line.split(None, 1)[1].strip())
            elif line.startswith("usemtl"):
                usemtl.append(line.split(None, 1)[1].strip())
    if not v_lines or not f_lines:
        raise DermisError(f"mesh file {path}: no vertices or faces (found {len(v_lines)} v, {len(f_lines)} f)")
    positions = np.array([ln.split()[:3] for ln in v_lines], dtype=np.float64)
    uv = np.array([ln.split()[:2] for ln in vt_lines], dtype=np.float64) if vt_lines else None
    nv, nvt = len(positions), (0 if uv is None else len(uv))

    tri_v, tri_t = [], []
    missing_vt = False
    for toks in f_lines:
        vi, ti = [], []
        for tok in toks:
            parts = tok.split("/")
            a = int(parts[0])
            vi.append(a - 1 if a > 0 else nv + a)
            if len(parts) > 1 and parts[1]:
                b = int(parts[1])
                ti.append(b - 1 if b > 0 else nvt + b)
            else:
                missing_vt = True
                ti.append(-1)
        for k in range(1, len(vi) - 1):  # fan-triangulate polygons
            tri_v.append((vi[0], vi[k], vi[k + 1]))
            tri_t.append((ti[0], ti[k], ti[k + 1]))
    faces = np.array(tri_v, dtype=np.int64)
    uv_faces = np.array(tri_t, dtype=np.int64)
    if uv is None or missing_vt:
        uv, uv_faces = None, None

    tex_path = None
    mats = _read_mtl(path, mtllibs)
    used = [m for m in (usemtl or list(mats)) if m in mats and mats[m]]
    textures = sorted({mats[m] for m in used})
    if len(textures) > 1:
        raise DermisError(f"mesh file {path}: materials use {len(textures)} different map_Kd textures "
                          f"({', '.join(textures)}); bake them into one atlas or set mesh.texture")
    if textures:
        tex_path = Path(textures[0])
    return positions, faces, uv, uv_faces, tex_path, None


def _read_mtl(obj_path: Path, mtllibs: list[str]) -> dict[str, str | None]:
    """Material name -> absolute map_Kd path (None if the material has none)."""
    mats: dict[str, str | None] = {}
    for lib in mtllibs:
        lib_path = obj_path.parent / lib
        if not lib_path.is_file():
            continue  # a missing .mtl only means no texture; validate() reports that
        current = None
        for line in lib_path.read_text(encoding="utf-8", errors="replace").splitlines():
            toks = line.split()
            if not toks:
                continue
            if toks[0] == "newmtl":
                current = " ".join(toks[1:])
                mats[current] = None
            elif toks[0] == "map_Kd" and current is not None and len(toks) > 1:
                # options (-bm 1, -s ...) come first; the file name is the last token
                mats[current] = str((lib_path.parent / toks[-1]).resolve())
    return mats


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _read_ply(path: Path):
    """Parse a PLY (ascii / binary): positions, faces, per-vertex or per-face texcoords, TextureFile."""
    with open(path, "rb") as fh:
        data = fh.read()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise DermisError(f"mesh file {path}: not a PLY file (no 'ply' magic / end_header)")
    body_start = data.index(b"\n", end) + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements, texture_file = None, [], None
    for line in header:
        toks = line.split()
        if not toks:
            continue
        if toks[0] == "format":
            fmt = toks[1]
        elif toks[0] == "comment" and len(toks) > 2 and toks[1].lower() == "texturefile":
            texture_file = " ".join(toks[2:])
        elif toks[0] == "element":
            elements.append((toks[1], int(toks[2]), []))
        elif toks[0] == "property":
            if toks[1] == "list":
                elements[-1][2].append((toks[4], ("list", _PLY_TYPES[toks[2]], _PLY_TYPES[toks[3]])))
            else:
                elements[-1][2].append((toks[2], _PLY_TYPES[toks[1]]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DermisError(f"mesh file {path}: unsupported PLY format {fmt!r}")
    endian = ">" if fmt == "binary_big_endian" else "<"

    values: dict[str, dict] = {}
    if fmt == "ascii":
        lines = data[body_start:].decode("ascii", errors="replace").split("\n")
        pos = 0
        for name, count, props in elements:
            rows = [lines[pos + i].split() for i in range(count)]
            pos += count
            values[name] = _ply_ascii_element(rows, props)
    else:
        offset = body_start
        for name, count, props in elements:
            values[name], offset = _ply_binary_element(data, offset, count, props, endian)

    vert = values.get("vertex", {})
    face = values.get("face", {})
    if "x" not in vert or not face:
        raise DermisError(f"mesh file {path}: PLY needs 'vertex' (x, y, z) and 'face' elements")
    positions = np.stack([vert["x"], vert["y"], vert["z"]], axis=1).astype(np.float64)
    idx_key = "vertex_indices" if "vertex_indices" in face else "vertex_index"
    polys = face[idx_key]
    faces, corner_src = _fan(polys)
    uv, uv_faces = None, None
    for ku, kv in (("u", "v"), ("s", "t"), ("texture_u", "texture_v")):
        if ku in vert and kv in vert:
            uv = np.stack([vert[ku], vert[kv]], axis=1)
            uv_faces = faces.copy()
            break
    if uv is None and "texcoord" in face:
        # MeshLab style: per face a list of 2 * n floats, one (u, v) per corner
        tc = face["texcoord"]
        flat = [np.asarray(t, dtype=np.float64).reshape(-1, 2) for t in tc]
        corner_uv = np.concatenate(flat)
        starts = np.cumsum([0] + [len(f) for f in flat[:-1]])
        uv = corner_uv
        uv_faces = starts[corner_src[:, 0]][:, None] + corner_src[:, 1:]
    tex_path = (path.parent / texture_file).resolve() if texture_file else None
    return positions, faces, uv, uv_faces, tex_path, None


def _fan(polys) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons; returns faces and (poly, corner_a, corner_b, corner_c) per triangle."""
    if isinstance(polys, np.ndarray) and polys.ndim == 2 and polys.shape[1] == 3:
        n = len(polys)
        src = np.stack([np.arange(n), np.zeros(n, int), np.ones(n, int), np.full(n, 2)], axis=1)
        return polys.astype(np.int64), src
    tris, src = [], []
    for p, poly in enumerate(polys):
        for k in range(1, len(poly) - 1):
            tris.append((poly[0], poly[k], poly[k + 1]))
            src.append((p, 0, k, k + 1))
    return np.array(tris, dtype=np.int64), np.array(src, dtype=np.int64)


def _ply_ascii_element(rows, props) -> dict:
    """Decode the rows of one ascii PLY element."""
    out = {name: [] for name, _ in props}
    for toks in rows:
        i = 0
        for name, typ in props:
            if isinstance(typ, tuple):
                n = int(toks[i])
                out[name].append([float(t) if typ[2][0] == "f" else int(t) for t in toks[i + 1:i + 1 + n]])
                i += 1 + n
            else:
                out[name].append(float(toks[i]))
                i += 1
    res = {}
    for name, typ in props:
        if isinstance(typ, tuple):
            lens = {len(r) for r in out[name]}
            res[name] = np.array(out[name]) if len(lens) == 1 else out[name]
        else:
            res[name] = np.array(out[name], dtype=np.float64)
    return res


def _ply_binary_element(data: bytes, offset: int, count: int, props, endian: str):
    """Decode one binary PLY element; vectorised when every list has the first row's length."""
    if not any(isinstance(t, tuple) for _, t in props):
        dt = np.dtype([(n, endian + t) for n, t in props])
        arr = np.frombuffer(data, dtype=dt, count=count, offset=offset)
        return {n: arr[n].astype(np.float64) for n, _ in props}, offset + dt.itemsize * count
    # Try a fixed layout using the list lengths of the first row, then verify every row.
    fields, probe = [], offset
    for name, typ in props:
        if isinstance(typ, tuple):
            n = int(np.frombuffer(data, dtype=endian + typ[1], count=1, offset=probe)[0])
            fields.append((name + "__n", endian + typ[1]))
            fields.append((name, endian + typ[2], (n,)))
            probe += np.dtype(typ[1]).itemsize + n * np.dtype(typ[2]).itemsize
        else:
            fields.append((name, endian + typ))
            probe += np.dtype(typ).itemsize
    dt = np.dtype(fields)
    if offset + dt.itemsize * count <= len(data):
        arr = np.frombuffer(data, dtype=dt, count=count, offset=offset)
        ok = all(np.all(arr[name + "__n"] == arr[name].shape[1])
                 for name, typ in props if isinstance(typ, tuple))
        if ok:
            return ({n: (arr[n] if isinstance(t, tuple) else arr[n].astype(np.float64)) for n, t in props},
                    offset + dt.itemsize * count)
    out = {name: [] for name, _ in props}  # general path: variable-length lists
    for _ in range(count):
        for name, typ in props:
            if isinstance(typ, tuple):
                n = int(np.frombuffer(data, dtype=endian + typ[1], count=1, offset=offset)[0])
                offset += np.dtype(typ[1]).itemsize
                out[name].append(np.frombuffer(data, dtype=endian + typ[2], count=n, offset=offset))
                offset += n * np.dtype(typ[2]).itemsize
            else:
                out[name].append(np.frombuffer(data, dtype=endian + typ, count=1, offset=offset)[0])
                offset += np.dtype(typ).itemsize
    return ({n: (out[n] if isinstance(t, tuple) else np.array(out[n], dtype=np.float64)) for n, t in props},
            offset)


_GLTF_COMPONENTS = {5120: "i1", 5121: "u1", 5122: "i2", 5123: "u2", 5125: "u4", 5126: "f4"}
_GLTF_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def _read_gltf(path: Path):
    """Parse glTF 2.0 / GLB: triangle primitives of the default scene, TEXCOORD_0, baseColorTexture."""
    raw = path.read_bytes()
    bin_chunk = None
    if path.suffix.lower() == ".glb":
        magic, version, _ = struct.unpack_from("<4sII", raw, 0)
        if magic != b"glTF" or version != 2:
            raise DermisError(f"mesh file {path}: not a glTF 2.0 binary (magic {magic!r}, version {version})")
        clen, _ = struct.unpack_from("<I4s", raw, 12)
        doc = json.loads(raw[20:20 + clen])
        off = 20 + clen
        if off + 8 <= len(raw):
            blen, btype = struct.unpack_from("<I4s", raw, off)
            if btype == b"BIN\x00":
                bin_chunk = raw[off + 8:off + 8 + blen]
    else:
        doc = json.loads(raw)

    def buffer_bytes(i):
        buf = doc["buffers"][i]
        uri = buf.get("uri")
        if uri is None:
            return bin_chunk
        if uri.startswith("data:"):
            import base64
            return base64.b64decode(uri.split(",", 1)[1])
        return (path.parent / uri).read_bytes()

    buffers: dict[int, bytes] = {}

    def view_bytes(vi):
        view = doc["bufferViews"][vi]
        b = view["buffer"]
        if b not in buffers:
            buffers[b] = buffer_bytes(b)
        start = view.get("byteOffset", 0)
        return buffers[b][start:start + view["byteLength"]], view.get("byteStride")

    def accessor(ai):
        acc = doc["accessors"][ai]
        width = _GLTF_WIDTH[acc["type"]]
        dt = np.dtype("<" + _GLTF_COMPONENTS[acc["componentType"]])
        data, stride = view_bytes(acc["bufferView"])
        off = acc.get("byteOffset", 0)
        count = acc["count"]
        if stride and stride != width * dt.itemsize:
            rows = np.lib.stride_tricks.as_strided(
                np.frombuffer(data, dtype=np.uint8, offset=off), shape=(count, width * dt.itemsize),
                strides=(stride, 1))
            arr = np.ascontiguousarray(rows).view(dt).reshape(count, width)
        else:
            arr = np.frombuffer(data, dtype=dt, count=count * width, offset=off).reshape(count, width)
        if acc.get("normalized") and dt.kind in "iu":
            arr = arr.astype(np.float64) / float(np.iinfo(dt).max)
        return arr

    pos_all, face_all, uv_all, mats = [], [], [], []
    nbase = 0

    def node_matrix(node):
        if "matrix" in node:
            return np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T
        t = np.array(node.get("translation", [0, 0, 0]), dtype=np.float64)
        x, y, z, w = node.get("rotation", [0, 0, 0, 1])
        s = np.array(node.get("scale", [1, 1, 1]), dtype=np.float64)
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        m = np.eye(4)
        m[:3, :3] = r * s[None, :]
        m[:3, 3] = t
        return m

    def visit(ni, parent):
        nonlocal nbase
        node = doc["nodes"][ni]
        m = parent @ node_matrix(node)
        if "mesh" in node:
            for prim in doc["meshes"][node["mesh"]]["primitives"]:
                if prim.get("mode", 4) != 4:
                    continue  # points/lines carry no surface
                p = accessor(prim["attributes"]["POSITION"]).astype(np.float64)
                p = p @ m[:3, :3].T + m[:3, 3]
                if "indices" in prim:
                    f = accessor(prim["indices"]).reshape(-1, 3).astype(np.int64)
                else:
                    f = np.arange(len(p), dtype=np.int64).reshape(-1, 3)
                if np.linalg.det(m[:3, :3]) < 0:
                    f = f[:, ::-1]  # a mirroring transform flips the winding
                t = accessor(prim["attributes"]["TEXCOORD_0"]).astype(np.float64) \
                    if "TEXCOORD_0" in prim["attributes"] else None
                pos_all.append(p)
                face_all.append(f + nbase)
                uv_all.append(t)
                mats.append(prim.get("material"))
                nbase += len(p)
        for child in node.get("children", []):
            visit(child, m)

    scene = doc.get("scene", 0)
    roots = doc["scenes"][scene]["nodes"] if doc.get("scenes") else range(len(doc.get("nodes", [])))
    for ni in roots:
        visit(ni, np.eye(4))
    if not pos_all:
        raise DermisError(f"mesh file {path}: no triangle primitives in scene {scene}")
    positions = np.concatenate(pos_all)
    faces = np.concatenate(face_all)
    uv = uv_faces = None
    if all(t is not None for t in uv_all):
        uv = np.concatenate(uv_all)
        uv_faces = faces.copy()

    tex_path, tex_bytes = None, None
    tex_ids = set()
    for mi in mats:
        if mi is None:
            continue
        ref = doc["materials"][mi].get("pbrMetallicRoughness", {}).get("baseColorTexture")
        if ref is not None:
            tex_ids.add(ref["index"])
    if len(tex_ids) > 1:
        raise DermisError(f"mesh file {path}: primitives use {len(tex_ids)} different baseColorTextures; "
                          "bake them into one atlas or set mesh.texture")
    if tex_ids:
        img = doc["images"][doc["textures"][tex_ids.pop()]["source"]]
        if "bufferView" in img:
            tex_bytes = bytes(view_bytes(img["bufferView"])[0])
        elif img.get("uri", "").startswith("data:"):
            import base64
            tex_bytes = base64.b64decode(img["uri"].split(",", 1)[1])
        else:
            tex_path = (path.parent / img["uri"]).resolve()
    return positions, faces, uv, uv_faces, tex_path, tex_bytes


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
               normals=vertex_normals(v, f), uv=uv.astype(np.float32), uv_faces=uvf.astype(np.int32),
               texture_srgb=tex, info=info)
    return out, report


# ----------------------------------------------------------------------------------------------
# normals
# ----------------------------------------------------------------------------------------------

def vertex_normals(vertices, faces) -> np.ndarray:
    """Angle-weighted vertex normals (physics.md section 6: "area-independent, angle-weighted").

    Parameters
    ----------
    vertices : (V, 3) float ndarray, mm
    faces : (F, 3) int ndarray, counter-clockwise seen from outside

    Returns
    -------
    (V, 3) float32 ndarray
        Unit normals; vertices used by no face get (0, 0, 0).

    References
    ----------
    G. Thuermer, C. Wuethrich, "Computing vertex normals from polygonal facets", JGT 3(1), 1998.
    Computed by ``igl.per_vertex_normals`` (weighting ANGLE).
    """
    return angle_weighted_normals(vertices, faces)


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
    code = f.reshape(-1).astype(np.int64) * n_uv + uvf.reshape(-1)
    uniq = np.unique(code)
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
    normals = vertex_normals(v, f)
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
        normals = vertex_normals(v, f)
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
    """Quadric-error simplification to about ``target_triangles`` (physics.md section 6: QSlim).

    Parameters
    ----------
    mesh : Mesh
        The high mesh.
    target_triangles : int
        Wanted count; default 16,750 is the thesis's low-quality mesh (physics.md section 6).

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
        return Mesh(vertices=v, faces=f, normals=vertex_normals(v, f), info=info)
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
    return Mesh(vertices=vo, faces=fo.astype(np.int32), normals=vertex_normals(vo, fo), info=info)


# ----------------------------------------------------------------------------------------------
# UV transfer
# ----------------------------------------------------------------------------------------------

def _uv_perimeter(t0, t1, t2):
    """Perimeter of UV triangles (any leading shape, last axis 2)."""
    return (np.linalg.norm(t1 - t0, axis=-1) + np.linalg.norm(t2 - t1, axis=-1)
            + np.linalg.norm(t0 - t2, axis=-1))


def transfer_uv(high: Mesh, low: Mesh) -> tuple[Mesh, dict]:
    """Give the low mesh texture coordinates from the high mesh (thesis method, physics.md section 6).

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
        ``{"triangles", "seam_choices", "repaired", "unrepaired", "max_uv_perimeter_ratio",
        "truncated_candidates"}``.

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
    from scipy.spatial import cKDTree

    if high.uv is None or high.uv_faces is None:
        raise DermisError("transfer_uv: the high mesh has no UVs; run validate() on it first")
    hv = np.asarray(high.vertices, dtype=np.float64)
    hf = np.asarray(high.faces, dtype=np.int64)
    huv = np.asarray(high.uv, dtype=np.float64)
    huvf = np.asarray(high.uv_faces, dtype=np.int64)
    lv = np.asarray(low.vertices, dtype=np.float64)
    lf = np.asarray(low.faces, dtype=np.int64)
    nh, nuv = len(hv), len(huv)

    # (vertex, uv) pairs of the high mesh, CSR by vertex.
    pv, pt = _vertex_uv_pairs(hf, huvf, nuv)
    pcount = np.bincount(pv, minlength=nh)
    pstart = np.concatenate([[0], np.cumsum(pcount)[:-1]])

    # Per high face: UV and 3-D perimeters, area, Jacobian d(uv)/d(x).
    p0, p1, p2 = hv[hf[:, 0]], hv[hf[:, 1]], hv[hf[:, 2]]
    t0, t1, t2 = huv[huvf[:, 0]], huv[huvf[:, 1]], huv[huvf[:, 2]]
    per3 = np.linalg.norm(p1 - p0, axis=1) + np.linalg.norm(p2 - p1, axis=1) + np.linalg.norm(p0 - p2, axis=1)
    peruv = _uv_perimeter(t0, t1, t2)
    corner_v = hf.reshape(-1)
    sig_num = np.bincount(corner_v, weights=np.repeat(peruv, 3), minlength=nh)
    sig_den = np.bincount(corner_v, weights=np.repeat(per3, 3), minlength=nh)
    sigma_h = sig_num / np.maximum(sig_den, 1e-300)

    # Nearest high vertex per low vertex.
    _, near = cKDTree(hv).query(lv, k=1)
    near = np.asarray(near, dtype=np.int64)

    # Candidates per low triangle corner: (F, 3, K) pair indices, -1 padded.
    K = _MAX_CANDIDATES
    nl = len(lf)
    corner_h = near[lf]                            # (F, 3)
    ncand = pcount[corner_h]
    truncated = int((ncand > K).sum())
    ks = np.arange(K)
    cand = np.where(ks[None, None, :] < np.minimum(ncand, K)[:, :, None],
                    pstart[corner_h][:, :, None] + ks[None, None, :], -1)
    chosen = cand[:, :, 0].copy()                  # pair index per corner
    multi = (ncand > 1).any(axis=1)
    seam_tris = np.flatnonzero(multi)
    if len(seam_tris):
        c = cand[seam_tris]                         # (S, 3, K)
        # all K^3 combinations
        i0, i1, i2 = np.meshgrid(ks, ks, ks, indexing="ij")
        combos = np.stack([i0.ravel(), i1.ravel(), i2.ravel()], axis=1)   # (K^3, 3)
        sel = np.stack([c[:, 0, combos[:, 0]], c[:, 1, combos[:, 1]], c[:, 2, combos[:, 2]]], axis=2)  # (S, K^3, 3)
        valid = (sel >= 0).all(axis=2)
        uvs = huv[pt[np.maximum(sel, 0)]]           # (S, K^3, 3, 2)
        per = _uv_perimeter(uvs[:, :, 0], uvs[:, :, 1], uvs[:, :, 2])
        per[~valid] = np.inf
        best = np.argmin(per, axis=1)
        chosen[seam_tris] = sel[np.arange(len(seam_tris)), best]

    # Low UV table: one entry per used pair, then repaired corners appended.
    used_pairs, corner_uv_idx = np.unique(chosen, return_inverse=True)
    corner_uv_idx = corner_uv_idx.reshape(nl, 3)
    low_uv = huv[pt[used_pairs]]

    # Per-pair Jacobian: area-weighted mean over the high faces using that (vertex, uv) corner.
    e1, e2 = p1 - p0, p2 - p0
    d1, d2 = t1 - t0, t2 - t0
    g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    det = g11 * g22 - g12 * g12
    inv_det = np.where(det > 0, 1.0 / np.maximum(det, 1e-300), 0.0)
    # pinv(E) rows: (g22 e1 - g12 e2)/det, (g11 e2 - g12 e1)/det ; J = D @ pinv(E)
    r1 = (g22[:, None] * e1 - g12[:, None] * e2) * inv_det[:, None]
    r2 = (g11[:, None] * e2 - g12[:, None] * e1) * inv_det[:, None]
    jac = d1[:, :, None] * r1[:, None, :] + d2[:, :, None] * r2[:, None, :]     # (Fh, 2, 3)
    area = 0.5 * np.sqrt(np.maximum(det, 0))

    def pair_jacobian(pairs: np.ndarray) -> np.ndarray:
        """Area-weighted mean Jacobian of the high faces around each (vertex, uv) pair."""
        want = np.full(len(pt), -1, np.int64)
        want[pairs] = np.arange(len(pairs))
        code_v = corner_v
        code_t = huvf.reshape(-1)
        # pair index of each high corner: position in (pv, pt) sorted codes
        codes = pv * nuv + pt
        corner_pair = np.searchsorted(codes, code_v * nuv + code_t)
        slot = want[corner_pair]
        m = slot >= 0
        face_of = np.repeat(np.arange(len(hf)), 3)[m]
        w = area[face_of]
        out = np.zeros((len(pairs), 2, 3))
        for a in range(2):
            for b in range(3):
                out[:, a, b] = np.bincount(slot[m], weights=w * jac[face_of, a, b], minlength=len(pairs))
        wsum = np.bincount(slot[m], weights=w, minlength=len(pairs))
        return out / np.maximum(wsum, 1e-300)[:, None, None]

    lp = lv[lf]                                                         # (F, 3, 3)
    per3_low = (np.linalg.norm(lp[:, 1] - lp[:, 0], axis=1) + np.linalg.norm(lp[:, 2] - lp[:, 1], axis=1)
                + np.linalg.norm(lp[:, 0] - lp[:, 2], axis=1))
    sigma_low = sigma_h[corner_h].mean(axis=1)
    expect = np.maximum(per3_low * sigma_low, 1e-300)

    def ratios():
        t = low_uv[corner_uv_idx]
        return _uv_perimeter(t[:, 0], t[:, 1], t[:, 2]) / expect

    r = ratios()
    flagged0 = r > _SEAM_RATIO
    repaired_any = np.zeros(nl, bool)
    corner_pair = used_pairs[corner_uv_idx]  # pair index (into pv/pt) of each corner, -1 after repair
    for _ in range(_REPAIR_PASSES):
        bad = np.flatnonzero(r > _SEAM_RATIO)
        if not len(bad):
            break
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
                jac_g[ok] = pair_jacobian(gpair[ok])
            dp = lp[bad, off] - lp[bad, gk]
            new_uv += t[rows, gk] + np.einsum("nij,nj->ni", jac_g, dp)
        new_uv *= 0.5
        start = len(low_uv)
        low_uv = np.concatenate([low_uv, new_uv])
        corner_uv_idx[bad, off] = start + rows
        corner_pair[bad, off] = -1
        repaired_any[bad] = True
        r = ratios()
    # Last resort for triangles still above the bound (corners in three charts, or a good pair that is
    # itself stretched): keep the corner nearest the others in UV and lay the other two out with its
    # Jacobian, i.e. flatten the triangle into the anchor's chart.
    bad = np.flatnonzero(r > _SEAM_RATIO)
    if len(bad):
        t = low_uv[corner_uv_idx[bad]]
        dist = np.stack([np.linalg.norm(t[:, k] - t[:, (k + 1) % 3], axis=1)
                         + np.linalg.norm(t[:, k] - t[:, (k + 2) % 3], axis=1) for k in range(3)], 1)
        pairs_ok = corner_pair[bad] >= 0
        dist[~pairs_ok] = np.inf                   # anchor must be an original (vertex, uv) pair
        has_anchor = np.isfinite(dist).any(axis=1)
        bad, dist, t = bad[has_anchor], dist[has_anchor], t[has_anchor]
        anchor = np.argmin(dist, axis=1)
        rows = np.arange(len(bad))
        jac_a = pair_jacobian(corner_pair[bad, anchor])
        for step in (1, 2):
            k = (anchor + step) % 3
            dp = lp[bad, k] - lp[bad, anchor]
            start = len(low_uv)
            low_uv = np.concatenate([low_uv, t[rows, anchor] + np.einsum("nij,nj->ni", jac_a, dp)])
            corner_uv_idx[bad, k] = start + rows
            corner_pair[bad, k] = -1
        repaired_any[bad] = True
        r = ratios()
    still = r > _SEAM_RATIO
    report = {
        "triangles": int(nl),
        "seam_choices": int(len(seam_tris)),
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
