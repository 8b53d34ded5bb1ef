"""Cycles' own flat semi-infinite slab, measured by rendering it: the curves the ``matched``
mapping inverts (:mod:`dermis.cycles.mapping`).

For one subsurface method, IOR, roughness and anisotropy, at Subsurface Radius 1, and for
base colours b on ``GRID`` (three per render, one per channel: light transport is
independent per channel):

* reflectance per entered flux, Rd_e(b) = (L(b) - L(0)) / (1 - L(0)): L is the radiance the
  camera sees looking straight down at the slab under a uniform sky of radiance 1 (by
  reciprocity, the directional-hemispherical reflectance at normal incidence); L(0), the
  slab of base colour 0, is the boundary's own (specular) reflectance;
* mean exit radius m(b) = integral_0^inf (1 - F(R)) dR, F(R) the fraction of the reflected
  light that exits within R of where it entered: the sun straight down through a hole of
  radius R in a black screen, seen at the hole's centre, is the reflection of the light that
  entered within R of that point (translation invariance, reciprocity), so
  F(R) = (L_R(b) - L_R(0)) / (L_inf(b) - L_inf(0)), on a geometric grid of radii
  ``RADII`` (trapezoids; the last radius stands for infinity).

Noise: ``SKY_SPP`` and ``HOLE_SPP`` samples per pixel on 4 x 4 pixels; the standard error of
every Rd_e and F is estimated from two seeds and kept in ``info``.
"""
from __future__ import annotations

import time

import numpy as np
from scipy.integrate import trapezoid

from dermis.cycles.job import run_job
from dermis.pipeline.artifacts import SlabCurves

__all__ = ["GRID", "RADII", "SKY_SPP", "HOLE_SPP", "slab_curves", "slab_response"]

# base colours: dense where skin's albedos lie (0.05-0.7), up to 0.98
GRID = (0.02, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.98)
# The slab is rendered at Subsurface Radius SCALE, in a box of half-width and depth SIDE
# radius units, and its exit distances divided by SCALE (they scale with the radius).  Cycles'
# random walk loses light on large triangles: a sun-lit flat plate of base colour 0.486 and
# radius 1 (or 3: the same) reflects 0.493 / 0.491 / 0.307 at half-widths of 1e2 / 1e4 / 1e6
# scene units, whatever the radius (float precision of the hit points grows with the
# coordinates).  So the box stays small in scene units: 200 radii, beyond the largest hole
# (60) and the walks' reach, at a radius of 1 unit.  The camera's 4 pixels see WINDOW, half
# the smallest hole.
SCALE = 1.0
WINDOW = 0.01
SIDE = 200.0         # the slab's half-width and depth, radius units
# hole radii (radius units): 0.02 to 60, 32 geometric steps (ratio 1.3): the exit profiles
# of the three methods lie within (docs/cycles.md)
RADII = tuple(float(r) for r in np.geomspace(0.02, 60.0, 32))
SKY_SPP = 1024       # x 16 pixels per seed
HOLE_SPP = 256       # x 16 pixels per radius and seed


def _material(method, colour, radius, ior, roughness, anisotropy) -> dict:
    return {"method": method, "base_colour": [float(c) for c in colour],
            "radius": [float(r) for r in radius], "ior": ior, "subsurface_ior": ior,
            "roughness": roughness, "anisotropy": anisotropy}


def slab_response(method: str, colours, *, radius=(1.0, 1.0, 1.0), ior: float,
                  roughness: float, anisotropy: float, threads: int, seed: int = 1,
                  sky_spp: int = SKY_SPP, hole_spp: int = HOLE_SPP) -> dict:
    """Rd_e and mean exit radius (in the units of ``radius``) of Cycles' slab for each RGB
    base colour of ``colours`` (N, 3) at ``radius`` (3,), with their standard errors (two
    seeds).  Rendered at the radii scaled to a largest of ``SCALE`` units (module
    docstring)."""
    colours = np.asarray(colours, np.float64)
    unit = float(max(radius)) / SCALE
    radius = [float(r) / unit for r in radius]
    sets = [np.zeros(3)] + list(colours)
    renders = []
    for s in (seed, seed + 1):
        for c in sets:
            m = _material(method, c, radius, ior, roughness, anisotropy)
            renders.append({"material": m, "light": "sky", "side": SIDE * max(radius),
                            "spp": sky_spp, "seed": s, "window": WINDOW})
            renders.append({"material": m, "light": "holes", "radii": [r * max(radius) for r
                                                                       in RADII],
                            "side": SIDE * max(radius), "spp": hole_spp, "seed": s,
                            "window": WINDOW})
    t0 = time.perf_counter()
    result, arrays = run_job({"kind": "slab", "threads": threads, "renders": renders})
    seconds = time.perf_counter() - t0
    n = len(sets)
    radii = np.asarray(RADII) * max(radius)
    per_seed = []
    for k in range(2):
        sky = [arrays[f"image{2 * (k * n + j)}"][0].astype(np.float64) for j in range(n)]
        holes = [arrays[f"image{2 * (k * n + j) + 1}"].astype(np.float64) for j in range(n)]
        spec = sky[0]
        rd_e = np.array([(sky[j] - spec) / (1.0 - spec) for j in range(1, n)])
        mean_r = []
        for j in range(1, n):
            d = holes[j] - holes[0]                       # (R, 3) subsurface part
            F = d / np.where(d[-1] != 0, d[-1], 1.0)
            one_minus = np.concatenate([np.ones((1, 3)), 1.0 - F])
            r = np.concatenate([[0.0], radii])
            mean_r.append(trapezoid(one_minus, r, axis=0) * unit)
        per_seed.append((spec, rd_e, np.array(mean_r)))
    spec = (per_seed[0][0] + per_seed[1][0]) / 2
    rd_e = (per_seed[0][1] + per_seed[1][1]) / 2
    mean_r = (per_seed[0][2] + per_seed[1][2]) / 2
    return {"specular": spec, "rd_e": rd_e, "mean_radius": mean_r,
            "rd_e_stderr": np.abs(per_seed[0][1] - per_seed[1][1]) / 2,
            "mean_radius_stderr": np.abs(per_seed[0][2] - per_seed[1][2]) / 2,
            "seconds": seconds, "process_seconds": result.get("process_seconds", 0.0),
            "cpu_seconds": result.get("cpu_seconds", 0.0)}


def slab_curves(method: str, *, ior: float, roughness: float, anisotropy: float,
                threads: int, seed: int = 1) -> SlabCurves:
    """Rd_e(b) and m(b) of Cycles' slab per unit radius on ``GRID`` (module docstring)."""
    g = np.asarray(GRID, np.float64)
    colours = g.reshape(-1, 3)          # three base colours per render, one per channel
    r = slab_response(method, colours, ior=ior, roughness=roughness, anisotropy=anisotropy,
                      threads=threads, seed=seed)
    rd_e = r["rd_e"].reshape(-1)        # (sets, 3) -> the grid's order
    mean_r = r["mean_radius"].reshape(-1)
    se = r["rd_e_stderr"].reshape(-1)
    mse = r["mean_radius_stderr"].reshape(-1)
    same = lambda v: np.repeat(v[:, None], 3, axis=1)   # one curve, the same per channel
    return SlabCurves(g, same(rd_e), same(mean_r), np.asarray(r["specular"], np.float64),
                      {"method": method, "ior": ior, "roughness": roughness,
                       "anisotropy": anisotropy, "rd_e_stderr": se.tolist(),
                       "mean_radius_stderr": mse.tolist(), "seconds": r["seconds"],
                       "cpu_seconds": r["cpu_seconds"],
                       "sky_spp": SKY_SPP, "hole_spp": HOLE_SPP, "radii": list(RADII)})
