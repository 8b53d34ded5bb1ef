"""Scan loading: OBJ (+ MTL), PLY (ascii / binary) and glTF / GLB into a :class:`Mesh` in mm,
with the scan's albedo texture and grey (displacement) images.

Pure file parsing (the format parsers are in :mod:`dermis.geometry.mesh_formats`) with no
geometry processing beyond welding exactly equal positions and merging duplicate UVs;
:func:`dermis.geometry.validation.validate` checks the result.  Written
here rather than taken from open3d / trimesh because those drop per-corner UVs at seams or
the embedded glTF texture (measured on the LPS scan; docs/software.md).

Conventions: mm; UV origin bottom-left (OBJ): texel row from the top is ``(1 - v) * (H - 1)``.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from dermis.geometry.mesh_formats import read_gltf, read_obj, read_ply
from dermis.pipeline.artifacts import Mesh
from dermis.pipeline.errors import DermisError
from dermis.pipeline.store import file_digest
from dermis.rendering.color import linear_to_srgb8

__all__ = ["load_scan", "read_grey_image", "UNITS_MM"]

# Millimetres per unit for the ``units`` option of load_scan (docs/science.md: mm inside).
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
# ----------------------------------------------------------------------------------------------
# loading
# ----------------------------------------------------------------------------------------------

# glTF files known to store TEXCOORD_0 in OBJ convention (v = 0 at the image bottom) against the
# glTF spec (v = 0 at the top).  Keyed by SHA-256 of the whole file, so only these exact bytes are
# treated specially: the three.js copy of the Lee Perry-Smith glb, whose v runs from the image
# bottom (checked against all four of its maps; the shipped OBJ's UVs follow the OBJ rule).
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
    if units not in UNITS_MM:
        raise DermisError(f"load_scan: units = {units!r} for {path}: must be one of {sorted(UNITS_MM)}")
    if not path.is_file():
        raise DermisError(f"mesh file not found: {path} (scene key mesh.source)")
    ext = path.suffix.lower()
    try:
        if ext == ".obj":
            raw = read_obj(path)
        elif ext == ".ply":
            raw = read_ply(path)
        elif ext in (".gltf", ".glb"):
            raw = read_gltf(path)
        else:
            raise DermisError(f"mesh file {path}: unknown format {ext!r}; supported: .obj .ply .gltf .glb")
    except DermisError:
        raise
    except Exception as exc:  # parse errors of any kind become one user-facing message
        raise DermisError(f"mesh file {path} could not be read: {type(exc).__name__}: {exc}") from exc

    positions, faces, uv, uv_faces, tex_path, tex_bytes = raw
    _check_indices(path, faces, len(positions), "vertex", ext)
    if uv is not None and uv_faces is not None:
        _check_indices(path, uv_faces, len(uv), "texture coordinate", ext)
    tex_from = "scene key mesh.texture" if texture is not None else (
        f"named by the material of {path}")
    info: dict = {"source": str(path), "format": ext.lstrip("."), "units": units,
                  "mm_per_unit": UNITS_MM[units]}

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
    vertices = positions[first[order]] * UNITS_MM[units]
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
        texture_srgb = _read_texture(Path(tex_path), what=tex_from)
        info["texture"] = str(tex_path)

    return Mesh(vertices=vertices, faces=faces.astype(np.int32), normals=None, uv=uv,
                uv_faces=uv_faces, texture_srgb=texture_srgb, info=info)


def _check_indices(path: Path, idx, count: int, what: str, ext: str) -> None:
    """Refuse faces that name a vertex (or texture coordinate) the file does not have."""
    idx = np.asarray(idx).reshape(-1, 3)
    bad = ((idx < 0) | (idx >= count)).any(axis=1)
    if not bad.any():
        return
    face = int(np.flatnonzero(bad)[0])
    value = int(next(v for v in idx[face] if not 0 <= v < count))
    one = ext == ".obj"   # OBJ counts from 1 (negative: relative to the end)
    raise DermisError(
        f"mesh file {path}: {int(bad.sum())} faces use {what} indices out of range, e.g. "
        f"triangle {face} uses {what} {(value + 1 if value >= 0 else value - count) if one else value}"
        f"{' (1-based, as in the file)' if one else ''}, but the file has {count} "
        f"(allowed: {'1' if one else '0'}..{count if one else count - 1}); fix the export")


def _decode(path: Path, label: str, fmt):
    """(spec, pixels) of the first subimage of an image file, read whole with OpenImageIO in
    ``fmt`` (a type, or a function of the file's spec giving one); refuses (DermisError
    starting with ``label``, which names the file) a file the reader met an error in.

    Read through ``ImageInput``, whose error state reports what the decoder met: a JPEG cut
    to a third of its bytes decodes with no error through an ``ImageBuf`` (the rows past the
    cut come back as grey 128) while its ``ImageInput`` reports "Premature end of JPEG file";
    an ``ImageBuf`` of a truncated PNG, TIFF, EXR or HDR sets its error only when its
    pixels are read, not when it is opened.  For an intact file the pixels are those of an
    ``ImageBuf`` (the same reader and conversion)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise DermisError(f"{label} could not be read: "
                          f"{oiio.geterror().strip() or 'not an image format OpenImageIO reads'}")
    try:
        spec = inp.spec()
        if spec.width < 1 or spec.height < 1:
            raise DermisError(f"{label} could not be read: no pixel data")
        pixels = inp.read_image(fmt(spec) if callable(fmt) else fmt)
        reason = "; ".join(dict.fromkeys(inp.geterror().strip().splitlines()))
    finally:
        inp.close()
    if reason or not isinstance(pixels, np.ndarray):
        raise DermisError(
            f"{label} could not be decoded: {reason or 'no pixels'} (the header declares "
            f"{spec.width} x {spec.height} pixels, the file has {path.stat().st_size} bytes: "
            "it is truncated or damaged, and what a reader returns for it is partly made "
            "up); export or copy the image again")
    return spec, pixels


def _linear(spec) -> bool:
    """Whether an image file holds linear values (float formats tagged linear, e.g. EXR)."""
    import OpenImageIO as oiio
    return spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE) and \
        "linear" in spec.get_string_attribute("oiio:ColorSpace", "linear").lower()


def _read_texture(path: Path, what: str = "scene key mesh.texture") -> np.ndarray:
    """Read an albedo image as (H, W, 3) uint8 sRGB with OpenImageIO (``what``: where the
    path came from, for messages); a truncated or damaged file is refused (:func:`_decode`)."""
    import OpenImageIO as oiio

    if not path.is_file():
        hint = "" if what.startswith("scene key") else (
            "; fix the material file or set scene key mesh.texture")
        raise DermisError(f"texture file not found: {path} ({what}){hint}")
    spec, img = _decode(path, f"texture file {path} ({what})",
                        lambda spec: oiio.FLOAT if _linear(spec) else oiio.UINT8)
    if _linear(spec):
        # Float images (EXR) hold linear values: encode with the sRGB curve before quantising.
        img = linear_to_srgb8(img, np.float64)
    else:
        img = np.asarray(img)
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
    px = np.asarray(_decode(path, f"image file {path}", oiio.FLOAT)[1], dtype=np.float32)
    if px.ndim == 3:
        px = px[:, :, 0]
    return np.ascontiguousarray(px)
