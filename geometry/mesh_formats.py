"""Triangle-mesh file formats: OBJ (+ MTL), PLY (ascii / binary) and glTF 2.0 / GLB parsers.

Each reader returns the file's raw arrays, ``(positions, faces, uv, uv_faces, texture path,
embedded texture bytes)``, in the file's own units and UV convention, polygons fan-
triangulated; :func:`dermis.geometry.scan.load_scan` welds, converts and checks them.
"""
from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

from dermis.pipeline.errors import DermisError

__all__ = ["read_obj", "read_ply", "read_gltf"]


def read_obj(path: Path):
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
    short = next((i for i, ln in enumerate(v_lines) if len(ln.split()) < 3), None)
    if short is not None:
        raise DermisError(f"mesh file {path}: vertex {short + 1} ('v {v_lines[short].strip()}') "
                          "has fewer than 3 coordinates")
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
            if a == 0:
                raise DermisError(f"mesh file {path}: face 'f {' '.join(toks)}' uses index 0; "
                                  "OBJ indices start at 1 (negative: from the end)")
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


def read_ply(path: Path):
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
            bad = [t for t in (toks[2:4] if toks[1] == "list" else toks[1:2]) if t not in _PLY_TYPES]
            if bad or not elements or len(toks) < (5 if toks[1] == "list" else 3):
                raise DermisError(f"mesh file {path}: PLY header line {line.strip()!r} is not a "
                                  "valid property (types: " + ", ".join(sorted(_PLY_TYPES)) + ")")
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
            if pos + count > len(lines):
                raise DermisError(f"mesh file {path}: truncated: the header declares {count} "
                                  f"'{name}' rows but the file ends {pos + count - len(lines)} "
                                  "rows short")
            rows = [lines[pos + i].split() for i in range(count)]
            pos += count
            values[name] = _ply_ascii_element(rows, props)
    else:
        offset = body_start
        for name, count, props in elements:
            try:
                values[name], offset = _ply_binary_element(data, offset, count, props, endian)
            except (ValueError, IndexError):
                raise DermisError(f"mesh file {path}: truncated: the header declares {count} "
                                  f"'{name}' elements but the file ends at byte {len(data)} "
                                  "before them") from None

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


def read_gltf(path: Path):
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
            tex_bytes = base64.b64decode(img["uri"].split(",", 1)[1])
        else:
            tex_path = (path.parent / img["uri"]).resolve()
    return positions, faces, uv, uv_faces, tex_path, tex_bytes
