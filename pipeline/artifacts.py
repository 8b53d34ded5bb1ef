"""Artifact types exchanged between stages, and their on-disk form.

Every artifact is a dataclass whose fields are numpy arrays, numbers, strings,
``None`` or JSON-able dicts.  ``save`` writes the arrays to ``data.npz`` and the
rest to ``fields.json`` inside a directory; ``load`` reverses it.  Stages exchange
data only through these types.

Conventions (docs/science.md "Conventions"): lengths in mm, coefficients in 1/mm, colour in linear
RGB unless a field says ``srgb``.  UV origin is the bottom-left of the texture
(OBJ convention): texel row counted from the top is ``(1 - v) * (H - 1)``.
"""
from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dermis.pipeline.errors import ConfigError, DermisError

__all__ = ["Mesh", "BakedMaps", "LayerProfile", "RenderedImage", "SurfacePoints", "SlabCurves",
           "PointIrradiance", "PixelSamples", "SAMPLE_LIT", "SAMPLE_CONTROL", "save",
           "load", "ARTIFACT_TYPES"]


@dataclass
class Mesh:
    """A triangle mesh in mm with optional per-corner UVs and an albedo texture.

    vertices : (V, 3) float64, mm
    faces : (F, 3) int32, counter-clockwise seen from outside
    normals : (V, 3) float32 unit angle-weighted vertex normals, or None
    uv : (T, 2) float32 texture coordinates, or None
    uv_faces : (F, 3) int32 indices into ``uv`` per face corner (seams allowed), or None
    texture_srgb : (H, W, 3) uint8 sRGB albedo texture, or None
    info : dict of JSON-able facts (source, repairs made, units converted, ...)
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    uv: np.ndarray | None = None
    uv_faces: np.ndarray | None = None
    texture_srgb: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    @property
    def n_triangles(self) -> int:
        return int(len(self.faces))

    def check(self, what: str, *, need_uv: bool = False) -> None:
        """Raise DermisError naming ``what`` (e.g. ``"bake: low"``) if an array is malformed.

        Checks vertices (finite, (V, 3)), faces ((F, 3) indices into them), normals ((V, 3)
        when set) and the UVs (``uv`` and ``uv_faces`` together, finite (T, 2) and (F, 3)
        indices into ``uv``).  ``need_uv``: missing UVs raise ConfigError.
        """
        v, f = np.asarray(self.vertices), np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise DermisError(f"{what}.vertices has shape {v.shape}; need (V, 3) with V > 0")
        if not np.all(np.isfinite(v)):
            raise DermisError(f"{what}.vertices contains NaN/inf")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise DermisError(f"{what}.faces has shape {f.shape}; need (F, 3) with F > 0")
        if f.min() < 0 or f.max() >= len(v):
            raise DermisError(f"{what}.faces indexes vertices outside [0, {len(v) - 1}]")
        if self.normals is not None and np.shape(self.normals) != v.shape:
            raise DermisError(f"{what}.normals has shape {np.shape(self.normals)}; need {v.shape}")
        if self.uv is None and self.uv_faces is None:
            if need_uv:
                raise ConfigError(f"{what}.uv is None; the mesh needs UVs (uv + uv_faces)")
            return
        if (self.uv is None) != (self.uv_faces is None):
            raise DermisError(f"{what}.uv and .uv_faces must both be given or both be None")
        uv, uvf = np.asarray(self.uv), np.asarray(self.uv_faces)
        if uv.ndim != 2 or uv.shape[1] != 2 or not np.all(np.isfinite(uv)):
            raise DermisError(f"{what}.uv has shape {uv.shape} or non-finite values; "
                              "need finite (T, 2)")
        if uvf.shape != f.shape:
            raise DermisError(f"{what}.uv_faces has shape {uvf.shape}; need {f.shape} "
                              "(one UV index per face corner)")
        if uvf.min() < 0 or uvf.max() >= len(uv):
            raise DermisError(f"{what}.uv_faces indexes uv outside [0, {len(uv) - 1}]")


@dataclass
class BakedMaps:
    """Albedo and bump maps baked from the high mesh into the low mesh's UV space.

    albedo_srgb : (R, R, 3) uint8 sRGB albedo, dilated past chart borders
    bump : (R, R) float32 height in [0, 1]; height_mm = bump_min_mm + bump * bump_range_mm
    bump_blur : (R, R) float32 Gaussian-blurred ``bump`` (same scale)
    coverage : (R, R) bool, texels inside a chart (before dilation)
    bump_min_mm, bump_range_mm : float, the bump's mm scale
    blur_sigma_px : float, the Gaussian sigma used for ``bump_blur``
    info : dict of JSON-able facts (misses, threshold, timings)
    """

    albedo_srgb: np.ndarray
    bump: np.ndarray
    bump_blur: np.ndarray
    coverage: np.ndarray
    bump_min_mm: float
    bump_range_mm: float
    blur_sigma_px: float
    info: dict = field(default_factory=dict)


@dataclass
class LayerProfile:
    """Radial diffuse reflectance/transmittance profiles of a layer stack (the "layer file").

    r_mm : (N,) float64 radial grid, mm
    R, T : (N, 3) float64 profiles in 1/mm^2, normalised so that
        integral 2 pi r R(r) dr = Rd (likewise T -> Tt)
    Rd, Tt : (3,) float64 totals
    cutoff_mm : (3,) float64 radius containing all but ``energy_beyond_cutoff`` of Rd
    energy_beyond_cutoff : (3,) float64 fraction of Rd beyond ``cutoff_mm``
    info : dict (layers, pole counts, grid sizes, timings)
    """

    r_mm: np.ndarray
    R: np.ndarray
    T: np.ndarray
    Rd: np.ndarray
    Tt: np.ndarray
    cutoff_mm: np.ndarray
    energy_beyond_cutoff: np.ndarray
    info: dict = field(default_factory=dict)


@dataclass
class RenderedImage:
    """One rendered image (model x light x geometry).

    linear : (H, W, 3) float32 linear RGB radiance, 0 where the camera ray missed
    mask : (H, W) bool, camera ray hit the mesh
    timings : dict of seconds (visibility, shadows, shading, kernel_seconds, total, ...)
    info : dict (model, light, geometry, samples, ray counts)
    noise : (H, W, 3) float32 or None, the signed half-difference (A - B) / 2 of two
        independent half images whose mean is ``linear``: per pixel noise^2 estimates the
        variance of ``linear``, and the variance of a block or region mean is the sum over its
        pixels of (block-averaged noise)^2 / N^2 (independent pixels).  None: no estimate.
    blend : (H, W) float32 or None, a model's blend weight between its cheap and its full
        evaluation (the adaptive BSSRDF's: 0 local, 1 gathered); None: the model has none.
    """

    linear: np.ndarray
    mask: np.ndarray
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    noise: np.ndarray | None = None
    blend: np.ndarray | None = None


@dataclass
class SurfacePoints:
    """Points spread uniformly over a mesh for irradiance caching (Jensen-Buhler pass 1).

    positions : (N, 3) float32, mm; normals : (N, 3) float32 unit; areas : (N,) float32 mm^2
    (each point's share of the surface, summing to the mesh area); info : dict
    """

    positions: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    info: dict = field(default_factory=dict)


@dataclass
class PointIrradiance:
    """Irradiance at each :class:`SurfacePoints` point from one lighting condition.

    irradiance : (N, 3) float32, light units / mm^2 (point, disc) or as the light's
    intensity (directional) or radiance x sr (environment); info : dict (samples, timings)
    noise : (N, 3) float32 or None, the signed half difference (A - B) / 2 of two independent
        half estimates whose mean is ``irradiance`` (lighting/irradiance.py "Halves"): per
        point noise^2 estimates its variance; the points are independent.  None: no estimate.
    """

    irradiance: np.ndarray
    info: dict = field(default_factory=dict)
    noise: np.ndarray | None = None


@dataclass
class PixelSamples:
    """What the camera sees of one mesh under one lighting condition, shared by every model
    (the ``visibility`` stage): sub-pixel camera hits and their unoccluded light samples.

    width, height, spp : image size and camera samples per pixel
    pixel : (M,) int32 flat pixel index (row-major from the top-left) of each sample that hit
    tri : (M,) int32 triangle hit; bary : (M, 2) float32 barycentrics (b1, b2), Embree's
    counts : (M,) int32 unoccluded light samples of each hit; their rows in ``directions`` and
        ``weights`` are consecutive, in hit order
    directions : (K, 3) float32 unit, towards the light; weights : (K, 3) float32 RGB, so a
        hit's radiance is sum f(wo, wi) weight cos(theta_i) (lighting/emitters.py)
    info : dict (rays traced, samples per hit, light names)
    flags : (K,) uint8 (always set by rendering/cast.py; None in hand-made samples: every
        sample lit, in both halves): bit 0 (LIT) the sample is unoccluded and above the
        geometric horizon, bit 1 (CONTROL) it lies in the control variate's region of an
        environment light (lighting/control.py), bits 2-3 the half image(s) it counts in
        (rendering/halves.py: the image's own noise estimate)
    control_bin : (M,) int32 or None, each hit's control bin; control_table : (bins, 3, 3)
        float32 or None, the moments M_b (RGB x world xyz): the control variate's integral
        at a hit is n_s . M_b
    sub : (M,) int32 or None, each hit's camera sample in [0, spp) (its half of the image,
        rendering/halves.py); None in hand-made samples
    """

    width: int
    height: int
    spp: int
    pixel: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    counts: np.ndarray
    directions: np.ndarray
    weights: np.ndarray
    info: dict = field(default_factory=dict)
    flags: np.ndarray | None = None
    control_bin: np.ndarray | None = None
    control_table: np.ndarray | None = None
    sub: np.ndarray | None = None


# PixelSamples.flags bits
SAMPLE_LIT = 1
SAMPLE_CONTROL = 2

@dataclass
class SlabCurves:
    """Cycles' flat semi-infinite slab as a function of its Base Color, at Subsurface Radius 1
    (one subsurface method, IOR, roughness, anisotropy; dermis/cycles/slab.py).

    grid : (K,) base colours; rd_e : (K, 3) reflectance per entered flux at normal
    incidence; mean_radius : (K, 3) mean exit radius (radius units); specular : (3,) the
    boundary's own reflectance; info : dict (samples, seconds, standard errors)
    """

    grid: np.ndarray
    rd_e: np.ndarray
    mean_radius: np.ndarray
    specular: np.ndarray
    info: dict = field(default_factory=dict)


ARTIFACT_TYPES = {cls.__name__: cls for cls in (Mesh, BakedMaps, LayerProfile, RenderedImage,
                                                SurfacePoints, PointIrradiance, PixelSamples,
                                                SlabCurves)}


def nonfinite_fields(artifact: Any) -> list[str]:
    """Names of the artifact's float array fields that hold NaN or Inf."""
    bad = []
    for f in dataclasses.fields(artifact):
        v = getattr(artifact, f.name)
        if isinstance(v, np.ndarray) and v.dtype.kind == "f" and not np.all(np.isfinite(v)):
            bad.append(f.name)
    return bad


def _jsonable(value: Any) -> Any:
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def save(artifact: Any, directory: str | os.PathLike) -> None:
    """Write ``artifact`` (a dataclass from this module) into ``directory``."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    arrays, scalars = {}, {"__type__": type(artifact).__name__}
    for f in dataclasses.fields(artifact):
        value = getattr(artifact, f.name)
        if isinstance(value, np.ndarray):
            arrays[f.name] = value
        else:
            scalars[f.name] = _jsonable(value)
    np.savez(directory / "data.npz", **arrays)
    (directory / "fields.json").write_text(json.dumps(scalars, indent=1, sort_keys=True))


def load(directory: str | os.PathLike) -> Any:
    """Read back an artifact written by :func:`save`."""
    directory = Path(directory)
    scalars = json.loads((directory / "fields.json").read_text())
    cls = ARTIFACT_TYPES[scalars.pop("__type__")]
    with np.load(directory / "data.npz", allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    return cls(**arrays, **scalars)
