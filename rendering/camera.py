"""The pinhole camera: its frame from a CameraConfig, sub-pixel sample positions (stratified)
and the primary rays through them, row-major from the top-left pixel (pbrt's field-of-view
convention: the full angle across the shorter image side)."""
from __future__ import annotations

import math

import numpy as np

from dermis.lighting.strata import stratified_2d
from dermis.pipeline.errors import ConfigError

__all__ = ["camera_vectors", "subpixel_offsets", "camera_rays"]


def camera_vectors(camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Position and orthonormal forward/right/up of a CameraConfig (errors name the key)."""
    pos = np.asarray(camera.position, dtype=np.float64)
    look = np.asarray(camera.look_at, dtype=np.float64)
    up = np.asarray(camera.up, dtype=np.float64)
    fwd = look - pos
    if not np.linalg.norm(fwd) > 0:
        raise ConfigError(f"camera.look_at = {tuple(look)}: must differ from camera.position")
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    if not np.linalg.norm(right) > 1e-9 * max(np.linalg.norm(up), 1e-300):
        raise ConfigError(f"camera.up = {tuple(up)}: must not be parallel to the view "
                          "direction (camera.look_at - camera.position)")
    right /= np.linalg.norm(right)
    return pos, fwd, right, np.cross(right, fwd)


def subpixel_offsets(n_pixels: int, spp: int, rng: np.random.Generator | None) -> np.ndarray:
    """(n_pixels, spp, 2) float64 sample positions inside each pixel, in [0, 1)^2.

    spp = 1: the pixel centre (0.5, 0.5), so one sample per pixel is the classic pinhole
    image.  spp > 1: stratified (Shirley 1991, "Discrepancy as a quality measure for sample
    distributions"): a jittered m x m grid when spp = m^2, else Latin hypercube strata
    (lighting/strata.py ``stratified_2d``), one independent jitter per pixel from ``rng``.
    (x, y) = (right, down) from the pixel's top-left corner.
    """
    if spp == 1:
        return np.full((n_pixels, 1, 2), 0.5)
    return stratified_2d(rng, n_pixels, spp)


def camera_rays(camera, offsets: np.ndarray | None = None, *,
                rows: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole camera rays, row-major from the top-left pixel.

    ``camera`` (CameraConfig): ``position``, ``look_at``, ``up`` (mm), ``fov_deg`` (full angle
    across the SHORTER image side, pbrt's convention), ``width``, ``height``.
    ``offsets`` : (H*W, S, 2) positions inside each pixel in [0, 1)^2 (:func:`subpixel_offsets`;
    x right, y down); None = the pixel centres.  ``rows`` = (r0, r1): only the rays of image
    rows r0 <= row < r1.  Returns origins and unit directions, (N*S, 3) float32 each (N pixels),
    the S rays of a pixel consecutive.
    """
    w = int(camera.width)
    h = int(camera.height)
    if w < 1 or h < 1:
        raise ConfigError(f"camera width x height = {w} x {h}: both must be >= 1")
    fov = float(camera.fov_deg)
    if not 0 < fov < 180:
        raise ConfigError(f"camera.fov_deg = {fov}: must be in (0, 180)")
    pos, fwd, right, up = camera_vectors(camera)
    tan = math.tan(math.radians(fov) / 2)
    short = min(w, h)
    r0, r1 = rows if rows is not None else (0, h)
    if offsets is None:
        offsets = np.full((h * w, 1, 2), 0.5)
    offsets = offsets[r0 * w:r1 * w]
    col = np.tile(np.arange(w), r1 - r0)[:, None] + offsets[..., 0]        # (N, S)
    row = np.repeat(np.arange(r0, r1), w)[:, None] + offsets[..., 1]
    x = ((col / w) * 2.0 - 1.0) * (tan * (w / short))
    y = (1.0 - (row / h) * 2.0) * (tan * (h / short))
    d = (fwd[None, None, :] + x[..., None] * right + y[..., None] * up).reshape(-1, 3)
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    o = np.broadcast_to(pos.astype(np.float32), d.shape)
    return np.ascontiguousarray(o), d
