"""Face regions defined once, on the mesh, and the statistics measured over them.

The ground-truth comparison (docs/ground-truth.md) reports errors on region means because a
path-traced reference affordable on a CPU is too noisy per pixel: the mean over N
independent pixels has 1/sqrt(N) of a pixel's noise.  A region is a set of mesh faces, so
it is the same piece of skin seen from any camera; its pixels are the pixels whose
camera ray at the pixel centre hits one of its faces.

Regions (:data:`REGIONS`, label = index + 1; 0 = no region) are placed relative to two
landmarks that every head dermis renders has: the nose tip (the frontmost vertex; heads
face +z, y is up, docs/science.md conventions) and the head's half-width ``w`` at the height
of the nose tip (largest |x| within 15 mm of that height).  Rules on a face's centroid
(x, y, z relative to the nose tip) and its unit normal n, in this order (first match wins,
so the regions are disjoint):

* ``nostril``: the thin parts of the nose's base -- the alae (0.07 w < |x| < 0.2 w,
  -0.18 w < y < 0.06 w, -0.3 w < z < -0.05 w) and, between them, the columella and the
  nostrils' openings (|x| <= 0.07 w, -0.18 w < y < -0.03 w, z > -0.3 w, facing down:
  n_y < -0.3);
* ``nose``: |x| < 0.2 w, -0.15 w < y < 0.45 w, z > -0.3 w (what ``nostril`` left: the
  bridge, the sides and the tip);
* ``ear``: |x| > 0.82 w, -0.45 w < y < 0.55 w, z < -0.7 w (the lateral protrusions
  behind the cheeks; the shoulders of a scan are below -0.45 w);
* ``forehead``: 0.7 w < y < 1.15 w, |x| < 0.45 w, n_z > 0.35;
* ``cheek``: 0.25 w < x < 0.68 w, -0.45 w < y < 0.25 w, z > -0.75 w, n_z > 0.15 -- the +x
  cheek, the side the thesis's point and disc lights (and the image's right side with
  dermis's default camera) face;
* ``shadowed_side``: the mirror image of ``cheek`` (-0.68 w < x < -0.25 w), the cheek
  away from the point and disc lights.  Its name follows the thesis's key light; under the
  sunset (sun 36 deg towards -x) this cheek is the lit one;
* ``lips``: |x| < 0.27 w, -0.5 w < y < -0.22 w, z > -0.3 w, n_z > 0.3 (both lips and the
  corners of the mouth; the close-up of the default scene's ``lips`` view);
* ``eyelid``: 0.18 w < |x| < 0.5 w, 0.22 w < y < 0.45 w, z > -0.55 w, n_z > 0.4 (the lids
  and the crease above them; on the procedural head also the open eyes' exposed eyeballs);

The fractions were chosen by looking at label images of the Lee Perry-Smith scan and of the
procedural head from the front, from below and from the side (tests/test_reference.py checks
that every region is non-empty on both heads and that two cameras see the same faces).
``ear`` and ``nostril`` are the thin parts, where light crosses the tissue: a model of a
locally flat surface misses that light, so they are measured apart.  Labels keep their
numbers as regions are added (``eyelid`` is the last).

Pure functions only; numpy.
"""
from __future__ import annotations

import numpy as np

from dermis.pipeline.errors import DermisError

__all__ = ["REGIONS", "REGION_COLOURS", "region_colours", "landmarks", "face_regions",
           "block_mean", "region_stats", "REGION_LABELS", "THIN_REGIONS"]

REGIONS = ("forehead", "cheek", "nose", "ear", "shadowed_side", "nostril", "lips", "eyelid")
REGION_LABELS = {name: i + 1 for i, name in enumerate(REGIONS)}
THIN_REGIONS = ("ear", "nostril")
# Label-image colours (sRGB 8-bit): index 0 = no hit, k = REGIONS[k - 1], the last = a hit
# outside every region.
REGION_COLOURS = ((0, 0, 0), (230, 60, 60), (60, 200, 60), (60, 60, 230), (230, 200, 40),
                  (160, 60, 200), (40, 210, 210), (240, 130, 170), (150, 110, 60),
                  (128, 128, 128))
# Height band (mm) around the nose tip in which the half-width w is measured.
_WIDTH_BAND_MM = 15.0


def landmarks(vertices) -> tuple[np.ndarray, float]:
    """(nose tip (3,) mm, half-width w mm) of a head facing +z (module docstring)."""
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise DermisError(f"regions: vertices have shape {v.shape}; need (V, 3)")
    tip = v[int(np.argmax(v[:, 2]))]
    band = v[np.abs(v[:, 1] - tip[1]) < _WIDTH_BAND_MM]
    w = float(np.abs(band[:, 0] - tip[0]).max())
    if not w > 0:
        raise DermisError("regions: the mesh has no width at the height of its nose tip")
    return tip, w


def face_regions(vertices, faces) -> np.ndarray:
    """(F,) int8 region label of every face (0: none; ``REGIONS[k - 1]`` for label k)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tip, w = landmarks(v)
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    c = (p0 + p1 + p2) / 3.0 - tip
    n = np.cross(p1 - p0, p2 - p0)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    x, y, z = c[:, 0] / w, c[:, 1] / w, c[:, 2] / w
    rules = {
        "nostril": (((np.abs(x) > 0.07) & (np.abs(x) < 0.2) & (y > -0.18) & (y < 0.06)
                     & (z > -0.3) & (z < -0.05))
                    | ((np.abs(x) <= 0.07) & (y > -0.18) & (y < -0.03) & (z > -0.3)
                       & (n[:, 1] < -0.3))),
        "nose": (np.abs(x) < 0.2) & (y > -0.15) & (y < 0.45) & (z > -0.3),
        "ear": (np.abs(x) > 0.82) & (y > -0.45) & (y < 0.55) & (z < -0.7),
        "forehead": (y > 0.7) & (y < 1.15) & (np.abs(x) < 0.45) & (n[:, 2] > 0.35),
        "cheek": (x > 0.25) & (x < 0.68) & (y > -0.45) & (y < 0.25) & (z > -0.75)
                 & (n[:, 2] > 0.15),
        "shadowed_side": (x < -0.25) & (x > -0.68) & (y > -0.45) & (y < 0.25) & (z > -0.75)
                         & (n[:, 2] > 0.15),
        "lips": (np.abs(x) < 0.27) & (y > -0.5) & (y < -0.22) & (z > -0.3) & (n[:, 2] > 0.3),
        "eyelid": (np.abs(x) > 0.18) & (np.abs(x) < 0.5) & (y > 0.22) & (y < 0.45)
                  & (z > -0.55) & (n[:, 2] > 0.4),
    }
    out = np.zeros(len(f), np.int8)
    for name in ("nostril", "nose", "ear", "forehead", "cheek", "shadowed_side", "lips",
                 "eyelid"):  # first wins
        out[(out == 0) & rules[name]] = REGION_LABELS[name]
    return out


def region_colours(labels: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 picture of per-pixel region ``labels`` (0: none) where ``hit``: a
    colour per region, grey for head pixels in no region, black off the head."""
    palette = np.array(REGION_COLOURS, np.uint8)
    return palette[np.where(np.asarray(hit, bool) & (labels == 0), len(palette) - 1, labels)]


def block_mean(image: np.ndarray, mask: np.ndarray, factor: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """Average ``image`` (H, W, C) over ``factor`` x ``factor`` blocks.

    Returns the (H // f, W // f, C) block means and a (H // f, W // f) mask of the blocks
    whose every pixel is in ``mask`` (partly covered blocks are dropped: at a silhouette
    the reference integrates background that a model's pixel-centre ray never sees).
    """
    f = int(factor)
    img = np.asarray(image, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if f < 1:
        raise DermisError(f"block_mean: factor = {factor}; must be >= 1")
    h, w = (img.shape[0] // f) * f, (img.shape[1] // f) * f
    if h == 0 or w == 0:
        raise DermisError(f"block_mean: factor {f} exceeds the image size {img.shape[:2]}")
    b = img[:h, :w].reshape(h // f, f, w // f, f, -1).mean(axis=(1, 3))
    bm = m[:h, :w].reshape(h // f, f, w // f, f).all(axis=(1, 3))
    return b, bm


def region_stats(image: np.ndarray, labels: np.ndarray, *, half_diff: np.ndarray | None = None
                 ) -> dict:
    """Per region: pixel count, mean RGB and (optionally) the standard error of that mean.

    ``half_diff`` = (seed A - seed B) / 2 of a two-seed reference whose image is the mean of
    the seeds: each pixel's (half_diff)^2 estimates the variance of that pixel's mean, so
    the mean's standard error is sqrt(sum half_diff^2) / N (independent pixels).
    """
    img = np.asarray(image, dtype=np.float64)
    lab = np.asarray(labels)
    out = {}
    for name in REGIONS:
        sel = lab == REGION_LABELS[name]
        n = int(sel.sum())
        rec = {"pixels": n, "mean_rgb": [float(v) for v in img[sel].mean(axis=0)] if n
               else [0.0, 0.0, 0.0]}
        if half_diff is not None:
            hd = np.asarray(half_diff, dtype=np.float64)[sel]
            rec["stderr_rgb"] = ([float(v) for v in np.sqrt((hd * hd).sum(axis=0)) / n] if n
                                 else [0.0, 0.0, 0.0])
        out[name] = rec
    return out
