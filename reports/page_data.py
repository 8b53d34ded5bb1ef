"""The compact float data of the interactive comparison page (``report.html``).

A browser opening a page from the file system may not ``fetch()`` the files beside it
(Chromium refuses ``file://`` requests), so the page carries its data: every image is one
block ``<script type="application/x-dermis-data" id="d-<key>">BASE64</script>`` at the end
of the document (a script of an unknown type is neither run nor shown; the page reads its
text when it first shows the image at full size).  The base64 text decodes to a zlib stream
(RFC 1950, the browsers' ``DecompressionStream("deflate")``) of:

* **linear images** (:func:`encode_linear`): IEEE 754 half floats (binary16: 11
  significant bits, relative precision 2^-11 = 4.9e-4 for normal values, absolute 2^-24 =
  6.0e-8 below 2^-14 = 6.1e-5) of the linear RGB radiance, channel planes R, G, B one after
  another, each row-major from the top row, little-endian, and *byte-shuffled*: the low
  bytes of all values first, then the high bytes (the high bytes of neighbouring pixels
  repeat, so the stream compresses about twice as well).  Values beyond the half range
  (65504) are stored as 65504; every image dermis writes is finite and non-negative.
* **8-bit maps** (:func:`encode_u8`): one byte per pixel, row-major -- the face-region
  label of each pixel (0 = none, k = ``REGIONS[k - 1]``) and HDR-FLIP error maps (the
  FLIP value in [0, 1] times 255, rounded).

:func:`decode_linear` is the inverse (the tests' and the page's check of the read-out).
"""
from __future__ import annotations

import base64
import zlib

import numpy as np

__all__ = ["HALF_MAX", "HALF_REL_PRECISION", "HALF_ABS_PRECISION", "encode_linear",
           "decode_linear", "encode_u8", "decode_u8", "data_block", "DATA_TYPE"]

HALF_MAX = 65504.0
HALF_REL_PRECISION = 2.0 ** -11     # half of binary16's spacing, relative (rounding to nearest)
HALF_ABS_PRECISION = 2.0 ** -25     # half the subnormal spacing 2^-24
DATA_TYPE = "application/x-dermis-data"   # the type of the page's data blocks
# zlib level 6 (its default): level 9 saved 1-2 % more on rendered images at twice the time
_LEVEL = 6


def encode_linear(linear: np.ndarray) -> bytes:
    """zlib stream of the shuffled half-float planes of an (H, W, 3) linear image."""
    x = np.asarray(linear, np.float32)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"encode_linear: shape {x.shape}; need (H, W, 3)")
    x = np.nan_to_num(x, nan=0.0, posinf=HALF_MAX, neginf=-HALF_MAX)
    planes = np.clip(x, -HALF_MAX, HALF_MAX).transpose(2, 0, 1).astype("<f2")
    raw = planes.reshape(-1).view(np.uint8).reshape(-1, 2)
    return zlib.compress(np.ascontiguousarray(raw.T).tobytes(), _LEVEL)


def decode_linear(blob: bytes, width: int, height: int) -> np.ndarray:
    """(H, W, 3) float32 image of :func:`encode_linear`'s stream."""
    raw = np.frombuffer(zlib.decompress(blob), np.uint8).reshape(2, -1)
    planes = np.ascontiguousarray(raw.T).view("<f2").reshape(3, height, width)
    return planes.transpose(1, 2, 0).astype(np.float32)


def encode_u8(values: np.ndarray) -> bytes:
    """zlib stream of an (H, W) uint8 map."""
    return zlib.compress(np.ascontiguousarray(values, np.uint8).tobytes(), _LEVEL)


def decode_u8(blob: bytes, width: int, height: int) -> np.ndarray:
    return np.frombuffer(zlib.decompress(blob), np.uint8).reshape(height, width)


def data_block(key: str, blob: bytes) -> str:
    """The page's data block of ``blob`` under ``key`` (letters, digits, '-', '_')."""
    return (f'<script type="{DATA_TYPE}" id="d-{key}">'
            f'{base64.b64encode(blob).decode("ascii")}</script>\n')
