"""The flat slab: the path tracer's own reflectance of a layer stack, the albedo's normaliser.

The albedo convention (docs/ground-truth.md): a texture value a is the reflectance, per unit
of flux that crossed the skin's surface at normal incidence, of what lies below the surface
(the layer file's Rd, which the BSSRDF and HK93 divide the texture by).  The reference
exports it as a transmission tint t = sqrt(a / Rd_entered) per boundary crossing
(:func:`dermis.groundtruth.scene_export.tint_texture`), with Rd_entered the path tracer's
own, measured here on a wide flat slab: a flat patch then reflects a (1 - specular) of a
normally incident light, as every model's flat patch reflects a T(1).

Measured by reciprocity: a radiance meter looking straight down at the slab under a uniform
sky of unit radiance (:func:`uniform_sky`; a black floor under the slab hides the sky below)
reads the slab's hemispherical-directional reflectance at normal view, which equals the
exitance under a normally incident directional light of unit irradiance (Helmholtz
reciprocity; both ways agree within their noise, bench/results/convention.json).  It is the
path tracer's low-noise direction: the directional light is reached only by next-event
estimation through the rough boundary, whose weight is heavy-tailed (ground-truth.md trap 10:
+-1.6-1.9 % at 2^18 paths), while a sky is reached by any escaping path (+-0.2-0.3 % at 2^18
paths on the two-layer skin, in less time).  The same slab checks the units against
dermis's Monte Carlo slab and the multipole (tests/test_reference.py).

:func:`meter_reading` and the meters are also how tests/test_convention.py measures a
textured flat plate exported like the head.
"""
from __future__ import annotations

import math
import time
import zlib
from dataclasses import dataclass, field

import numpy as np

from dermis.groundtruth.pixel_tracing import sensor_mean
from dermis.groundtruth.scene_export import (boundary_bsdf, dielectric_bsdf, medium_dict,
                                             rgb_spectrum)
from dermis.pipeline.shared import Shared

__all__ = ["SlabResult", "slab_reflectance", "slab_boxes", "slab_scene_dict", "uniform_sky",
           "black_floor", "radiance_meter", "irradiance_meter", "meter_reading",
           "SLAB_HALF_WIDTH_MM", "SLAB_DEPTH_MM",
           "SLABS"]

# one slab per stack and boundary in a run: every lighting condition's reference reads it
SLABS = Shared("reference_slab")


@dataclass
class SlabResult:
    """Reflectance of a flat slab at normal incidence (measured by reciprocity, module doc).

    Rd : (3,) subsurface reflectance per incident irradiance (boundary reflection removed)
    Rd_stderr : (3,) its standard error (between independent batches, the specular's included)
    specular : (3,) the boundary's own reflection (rendered with a black interior)
    Rd_entered : (3,) Rd / (1 - specular): per unit of flux that entered (the Monte Carlo
        slab's and the layer file's normalisation): the albedo tint's normaliser
        (:func:`dermis.groundtruth.scene_export.tint_texture`)
    seconds, samples : cost
    """

    Rd: np.ndarray
    Rd_stderr: np.ndarray
    specular: np.ndarray
    Rd_entered: np.ndarray
    seconds: float
    samples: int
    info: dict = field(default_factory=dict)


# A slab of this half-width and depth stands for an infinite one: skin's diffusion lengths
# are < 10 mm (sigma_tr >= 0.1 / mm in every preset), so the escaped fraction is ~e^-100.
SLAB_HALF_WIDTH_MM = 50.0
SLAB_DEPTH_MM = 50.0


# --------------------------------------------------------------------------- light, meters
def uniform_sky() -> dict:
    """A sky of unit radiance in every direction (Mitsuba's ``constant`` emitter)."""
    return {"type": "constant", "radiance": rgb_spectrum((1.0, 1.0, 1.0))}


def black_floor(mi, z_mm: float) -> dict:
    """A black plane at height ``z_mm`` facing up, wide enough to hide the sky below a flat
    sample above it (light leaving a finite slab's underside is absorbed, as under a light
    from above)."""
    T = mi.ScalarTransform4f
    return {"type": "rectangle", "to_world": T().translate([0.0, 0.0, float(z_mm)])
            @ T().scale([1e5, 1e5, 1.0]),
            "bsdf": {"type": "diffuse", "reflectance": rgb_spectrum((0.0, 0.0, 0.0))}}


def _film() -> dict:
    return {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"},
            "pixel_format": "rgb"}


def radiance_meter(target, view_deg: float = 0.0, distance_mm: float = 10.0) -> dict:
    """A radiance meter looking at the point ``target`` (mm) of a flat sample with normal +z
    from ``view_deg`` off the normal (in the x-z plane).  Under :func:`uniform_sky` it reads the
    sample's hemispherical-directional reflectance there, by reciprocity its exitance per
    unit irradiance under a directional light from ``view_deg``."""
    th = math.radians(view_deg)
    d = np.array([math.sin(th), 0.0, math.cos(th)])
    origin = np.asarray(target, np.float64) + distance_mm * d
    return {"type": "radiancemeter", "origin": [float(c) for c in origin],
            "direction": [float(c) for c in -d], "film": _film(),
            "sampler": {"type": "independent", "sample_count": 1}}


def irradiance_meter(mi, name: str, target, half_mm: float = 1.0, height_mm: float = 0.1
                     ) -> dict:
    """A ``half_mm`` square irradiance meter (sensor id ``name``) ``height_mm`` above the
    point ``target`` of a flat sample with normal +z, facing it, transparent to light: it
    reads the sample's exitance there."""
    T = mi.ScalarTransform4f
    c = np.asarray(target, np.float64) + [0.0, 0.0, height_mm]
    # Mitsuba's parser merges plugins of equal properties, and one sensor cannot sit on two
    # shapes: the sampler's (unused, :func:`meter_reading` seeds every render) seed tells
    # the meters apart
    return {"type": "rectangle", "bsdf": {"type": "null"},
            "to_world": T().translate([float(v) for v in c]) @ T().rotate([1.0, 0.0, 0.0], 180.0)
            @ T().scale([half_mm, half_mm, 1.0]),
            name: {"type": "irradiancemeter", "film": _film(),
                   "sampler": {"type": "independent", "sample_count": 1,
                               "seed": zlib.crc32(name.encode()) & 0x7FFFFFFF}}}


def meter_reading(mi, scene, sensor: str, *, samples: int, batches: int = 8, seed: int = 0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(3,) mean reading of the one-pixel sensor with id ``sensor`` over ``samples`` paths in
    ``batches`` independent renders (seeds ``seed`` * 1000 + b), and (3,) its standard error
    (between the batches)."""
    found = [s for s in scene.sensors() if s.id() == sensor]
    if len(found) != 1:
        raise KeyError(f"scene has no sensor {sensor!r}: {[s.id() for s in scene.sensors()]}")
    per = max(1, int(samples) // int(batches))
    # summed here in a fixed order (sensor_mean): mi.render adds a one-pixel film's samples
    # with atomics, whose order changed the last bits from run to run
    vals = np.array([sensor_mean(mi, scene, per, int(seed) * 1000 + b, sensor=found[0])
                     for b in range(int(batches))])
    return vals.mean(axis=0), vals.std(axis=0, ddof=1) / math.sqrt(len(vals))


# --------------------------------------------------------------------------- the slab
def slab_boxes(mi, stack, roughness: float, *, black: bool = False) -> dict:
    """The stack as nested boxes (top at z = 0), keys ``layer<k>``: a Mitsuba scene's shapes.

    ``roughness`` 0: a smooth boundary (:func:`dermis.groundtruth.scene_export.
    dielectric_bsdf`).  ``black``: the top layer only, purely absorbing (only the boundary's
    own reflection returns)."""
    T = mi.ScalarTransform4f
    layers = stack.layers
    d: dict = {}
    W = SLAB_HALF_WIDTH_MM
    finite = not math.isinf(layers[-1].thickness_mm)
    total = sum(l.thickness_mm for l in layers) if finite else SLAB_DEPTH_MM
    top = 0.0
    for k, lay in enumerate(layers):
        inset = 1e-3 * k  # nested boxes share no face: each lies just inside the one above
        med = medium_dict(lay)
        if black:  # purely absorbing interior: only the boundary's own reflection returns
            med = {"type": "homogeneous", "albedo": rgb_spectrum((0.0, 0.0, 0.0)),
                   "sigma_t": rgb_spectrum((1.0, 1.0, 1.0)), "scale": 1e3, "sample_emitters": False}
        lo, hi = -total + inset, top
        xf = T().translate([0.0, 0.0, 0.5 * (lo + hi)]) @ T().scale([W - inset, W - inset,
                                                                     0.5 * (hi - lo)])
        eta_out = stack.eta_above if k == 0 else layers[k - 1].eta
        box = {"type": "cube", "to_world": xf, "interior": med,
               "bsdf": (boundary_bsdf(lay.eta, eta_out, roughness) if k else
                        dielectric_bsdf(lay.eta, stack.eta_above, roughness))}
        if k:
            box["exterior"] = medium_dict(layers[k - 1])
        d[f"layer{k}"] = box
        if black or math.isinf(lay.thickness_mm):
            break
        top -= lay.thickness_mm
    return d


def slab_scene_dict(mi, stack, roughness: float, *, black: bool, view_deg: float = 0.0,
                    max_depth: int = -1, rr_depth: int = 1024) -> dict:
    """Scene dictionary: stacked boxes (top at z = 0, the top face's BSDF ``layer0``'s
    ``bsdf``; GGX of alpha ``roughness``, smooth at 0) over a black floor, a uniform sky, a
    radiance meter (id ``meter``) looking at the top's centre from ``view_deg``."""
    layers = stack.layers
    d: dict = {"type": "scene", "integrator": {"type": "volpathmis", "max_depth": int(max_depth),
                                               "rr_depth": int(rr_depth)}}
    d.update(slab_boxes(mi, stack, roughness, black=black))
    total = (sum(l.thickness_mm for l in layers) if not math.isinf(layers[-1].thickness_mm)
             else SLAB_DEPTH_MM)
    d["floor"] = black_floor(mi, -total - 1.0)
    d["sky"] = uniform_sky()
    d["meter"] = radiance_meter((0.0, 0.0, 0.0), view_deg)
    return d


def slab_reflectance(mi, stack, *, roughness: float, samples: int = 1 << 18, batches: int = 8,
                     seed: int = 0, max_depth: int = -1, rr_depth: int = 1024) -> SlabResult:
    """Mitsuba's reflectance of a flat slab of ``stack`` at normal incidence, per incident
    irradiance and per entered flux.

    The radiance meter over a wide slab under the unit sky reads its total reflectance M at
    normal incidence (module docstring); the same render with a black interior gives the
    boundary's own reflection, and Rd = M - specular.  A finite stack ends on vacuum.
    Standard errors from ``batches`` independent renders.
    """
    t0 = time.perf_counter()
    sc = mi.load_dict(slab_scene_dict(mi, stack, roughness, black=False, max_depth=max_depth,
                                      rr_depth=rr_depth))
    M, err = meter_reading(mi, sc, "meter", samples=samples, batches=batches, seed=seed)
    spec_sc = mi.load_dict(slab_scene_dict(mi, stack, roughness, black=True))
    # the black interior ends every path at the boundary: as many paths cost ~1/30 of the time
    spec, spec_err = meter_reading(mi, spec_sc, "meter", samples=samples, batches=batches,
                                   seed=int(seed) + 1)
    rd = M - spec
    return SlabResult(rd, np.hypot(err, spec_err), spec, rd / np.maximum(1.0 - spec, 1e-9),
                      time.perf_counter() - t0, max(1, samples // batches) * batches,
                      {"roughness": float(roughness), "batches": batches,
                       "max_depth": int(max_depth), "rr_depth": int(rr_depth),
                       "method": "radiance meter at normal view under a uniform sky",
                       "specular_stderr": [float(v) for v in spec_err],
                       "variant": mi.variant()})
