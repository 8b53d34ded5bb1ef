"""The flat slab: Mitsuba's own total diffuse reflectance of a layer stack.

The albedo texture is exported as a transmission tint t = sqrt(albedo / Rd) per boundary
crossing (:func:`dermis.groundtruth.scene_export.tint_texture`), with Rd the path tracer's
own total diffuse reflectance of the stack, measured here on a wide flat slab under a
normally incident directional light (docs/ground-truth.md).  The same slab checks the units
against dermis's Monte Carlo slab and the multipole (tests/test_reference.py).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from dermis.groundtruth.pixel_tracing import sensor_mean
from dermis.groundtruth.scene_export import (boundary_bsdf, dielectric_bsdf, medium_dict,
                                              rgb_spectrum)
from dermis.pipeline.shared import Shared

__all__ = ["SlabResult", "slab_reflectance", "slab_boxes", "SLAB_HALF_WIDTH_MM", "SLAB_DEPTH_MM",
           "SLABS"]

# one slab per stack and boundary in a run: every lighting condition's reference reads it
SLABS = Shared("reference_slab")


@dataclass
class SlabResult:
    """Total reflectance of a flat slab under a normally incident directional light.

    Rd : (3,) subsurface reflectance per incident irradiance (boundary reflection removed)
    Rd_stderr : (3,) its standard error (between independent batches)
    specular : (3,) the boundary's own reflection (rendered with a black interior)
    Rd_entered : (3,) Rd / (1 - specular): per unit of flux that entered (the Monte Carlo
        slab's and the layer file's normalisation)
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


def _slab_scene(mi, stack, roughness: float, *, black: bool, incidence_deg: float = 0.0,
                max_depth: int = -1, rr_depth: int = 1024):
    """Scene: stacked boxes (top at z = 0), an irradiance meter just above, a directional light."""
    T = mi.ScalarTransform4f
    d: dict = {"type": "scene", "integrator": {"type": "volpathmis", "max_depth": int(max_depth),
                                               "rr_depth": int(rr_depth)}}
    d.update(slab_boxes(mi, stack, roughness, black=black))
    th = math.radians(incidence_deg)
    d["light"] = {"type": "directional", "direction": [math.sin(th), 0.0, -math.cos(th)],
                  "irradiance": rgb_spectrum((1.0, 1.0, 1.0))}
    # meter: a 200 mm square 1 mm above the slab facing down, transparent to light
    d["meter"] = {"type": "rectangle", "bsdf": {"type": "null"},
                  "to_world": T().translate([0.0, 0.0, 0.1]) @ T().rotate([1.0, 0.0, 0.0], 180.0)
                  @ T().scale([10.0, 10.0, 1.0]),
                  "sensor": {"type": "irradiancemeter",
                             "film": {"type": "hdrfilm", "width": 1, "height": 1,
                                      "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                             "sampler": {"type": "independent", "sample_count": 1}}}
    return mi.load_dict(d)


def slab_reflectance(mi, stack, *, roughness: float, samples: int = 1 << 18, batches: int = 8,
                     seed: int = 0, max_depth: int = -1, rr_depth: int = 1024) -> SlabResult:
    """Mitsuba's total diffuse reflectance of a flat slab of ``stack`` at normal incidence.

    An irradiance meter above a wide slab measures the exitance M under irradiance E = 1;
    the same render with a black interior gives the boundary's own reflection, and
    Rd = M - specular (per incident irradiance, the reading every dermis model gives the
    albedo texture).  A finite stack ends on vacuum.  Standard errors from ``batches``
    independent renders, each summed in a fixed order (:func:`~dermis.groundtruth.
    pixel_tracing.sensor_mean`: the same bytes on every run).
    """
    t0 = time.perf_counter()
    sc = _slab_scene(mi, stack, roughness, black=False, max_depth=max_depth, rr_depth=rr_depth)
    per = max(1, samples // batches)
    vals = []
    for b in range(batches):
        vals.append(sensor_mean(mi, sc, per, int(seed) * 1000 + b))
    vals = np.array(vals)
    spec_sc = _slab_scene(mi, stack, roughness, black=True)
    spec = sensor_mean(mi, spec_sc, 1 << 14, int(seed) * 1000 + 999)
    M = vals.mean(axis=0)
    err = vals.std(axis=0, ddof=1) / math.sqrt(batches)
    rd = M - spec
    return SlabResult(rd, err, spec, rd / np.maximum(1.0 - spec, 1e-9),
                      time.perf_counter() - t0, per * batches,
                      {"roughness": float(roughness), "batches": batches,
                       "max_depth": int(max_depth), "rr_depth": int(rr_depth),
                       "variant": mi.variant()})
