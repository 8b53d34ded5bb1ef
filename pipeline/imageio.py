"""Image files through OpenImageIO: read textures/HDRs, write linear EXR and sRGB PNG."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dermis.rendering.color import linear_to_srgb

from .errors import DermisError

__all__ = ["read_image", "write_exr", "write_png"]


def read_image(path: str | Path, *, channels: int | None = None, what: str = "image") -> np.ndarray:
    """Read an image as float32 (H, W, C) in the file's own encoding (no colour conversion).

    8-bit files come back in [0, 1]. ``channels`` keeps the first N channels (grey -> repeated).
    """
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise DermisError(f"{what} {path} does not exist")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise DermisError(f"{what} {path} cannot be read: "
                          f"{oiio.geterror().strip() or 'not an image format OpenImageIO reads'}")
    try:  # every channel of the first subimage (OIIO 3 reads one channel for chend = -1)
        spec = inp.spec()
        nchannels = spec.nchannels
        pixels = inp.read_image("float")
        reason = inp.geterror().strip() if hasattr(inp, "geterror") else ""
    finally:
        inp.close()
    if pixels is None or not isinstance(pixels, np.ndarray):
        reason = (reason or oiio.geterror().strip() or "no pixels") + (
            f" (the header declares {spec.width} x {spec.height} pixels; the pixel data is "
            f"missing or truncated: the file has {path.stat().st_size} bytes)")
        raise DermisError(f"{what} {path} cannot be decoded: {reason}")
    img = np.asarray(pixels, dtype=np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[2] != nchannels:
        raise DermisError(f"{what} {path}: decoded {img.shape[2]} of its {nchannels} channels")
    if channels is not None:
        if img.shape[2] < channels:
            img = np.repeat(img[..., :1], channels, axis=2)
        img = img[..., :channels]
    if not np.all(np.isfinite(img)):
        raise DermisError(f"{what} {path} contains NaN or Inf pixels")
    return img


def _write(path: Path, img: np.ndarray, fmt: str) -> Path:
    import OpenImageIO as oiio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.ascontiguousarray(img)
    if img.ndim == 2:
        img = img[..., None]
    spec = oiio.ImageSpec(img.shape[1], img.shape[0], img.shape[2], fmt)
    spec.attribute("DateTime", "")   # no time stamp: the same pixels give the same bytes
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise DermisError(f"cannot write {path}: {oiio.geterror()}")
    try:
        out.write_image(img)
    finally:
        out.close()
    return path


def write_exr(path: str | Path, linear: np.ndarray) -> Path:
    """Write a linear float image as half-float EXR."""
    return _write(Path(path), np.asarray(linear, dtype=np.float32), "half")


def write_png(path: str | Path, img: np.ndarray, *, encode_srgb: bool = False) -> Path:
    """Write a PNG from uint8, or from floats in [0, 1] (sRGB-encoded first if ``encode_srgb``)."""
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = linear_to_srgb(img) if encode_srgb else np.clip(img, 0.0, 1.0)
        img = np.round(img * 255.0).astype(np.uint8)
    return _write(Path(path), img, "uint8")
