"""Image files through OpenImageIO: read textures/HDRs, write linear EXR and sRGB PNG.

EXRs are written in 32-bit float, the precision of the rendered data: in half floats (largest
65504, smallest subnormal 6e-8) the head under a point light of 1e12 is +Inf and under one of
1e-3 all zero, while the float32 data are finite and non-zero (docs/hardening.md, "Outputs
and the cache").  Where an image holds values that float32
cannot represent (beyond +-3.4e38, NaN, Inf, or non-zero values below its smallest
subnormal), :func:`write_exr` still writes it and warns with :class:`ImageRangeWarning`,
naming the image and its value range.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np


from .errors import DermisError

__all__ = ["read_image", "write_exr", "write_png", "ImageRangeWarning", "unrepresentable"]


class ImageRangeWarning(UserWarning):
    """An image holds values its file cannot represent (written anyway, see the message)."""


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
    if reason:   # pixels, but the decoder met an error: a truncated JPEG's missing rows are grey
        raise DermisError(f"{what} {path} cannot be decoded: {reason} (the file has "
                          f"{path.stat().st_size} bytes: it is truncated or damaged)")
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


def unrepresentable(values: np.ndarray, stored: np.ndarray) -> str | None:
    """Why ``stored`` (float32) does not hold ``values``, or None when it does: NaN or Inf,
    finite values beyond float32's range (stored as Inf), non-zero values below its smallest
    subnormal (stored as 0).  The reason names the value range of the finite values."""
    values = np.asarray(values)
    finite = np.isfinite(values)
    problems = []
    if not finite.all():
        problems.append(f"{int(values.size - np.count_nonzero(finite))} NaN or Inf values")
    lost_big = finite & ~np.isfinite(stored)
    if lost_big.any():
        problems.append(f"{int(np.count_nonzero(lost_big))} values beyond the float32 maximum "
                        f"{float(np.finfo(np.float32).max):.3g}, stored as Inf")
    lost_small = finite & (values != 0) & (stored == 0)
    if lost_small.any():
        problems.append(f"{int(np.count_nonzero(lost_small))} non-zero values below the "
                        f"smallest float32 {float(np.finfo(np.float32).smallest_subnormal):.3g}, "
                        "stored as 0")
    if not problems:
        return None
    held = values[finite]
    span = (f"finite values from {float(held.min()):.6g} to {float(held.max()):.6g}"
            if held.size else "no finite values")
    return f"{'; '.join(problems)} ({span})"


def write_exr(path: str | Path, linear: np.ndarray) -> Path:
    """Write a linear image as a 32-bit float EXR (the precision of the rendered data).

    Values float32 cannot hold (see :func:`unrepresentable`) are written as float32 stores
    them, with an :class:`ImageRangeWarning` naming the file and the value range."""
    path = Path(path)
    values = np.asarray(linear)
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        stored = values.astype(np.float32, copy=False)
    why = unrepresentable(values, stored)
    if why is not None:
        warnings.warn(f"{path.name}: {why}; the EXR holds them as float32 stores them",
                      ImageRangeWarning, stacklevel=2)
    return _write(path, stored, "float")


def write_png(path: str | Path, img: np.ndarray) -> Path:
    """Write a PNG from uint8, or from already encoded floats in [0, 1] (the colour curves
    are rendering/color.py's: the engine stores values, it does not encode them)."""
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)
    return _write(Path(path), img, "uint8")
