"""From dermis's skin to the Principled BSDF's inputs: the ``native`` and ``matched`` mappings.

Both give the same surface: the stack's relative index as IOR (and Subsurface IOR), the
reference's GGX alpha as Roughness^2 (Cycles squares its roughness input), the deepest
layer's phase mean cosine as Subsurface Anisotropy, Subsurface Weight 1 and Scale 1.  They
differ in Base Color and Subsurface Radius (docs/cycles.md "Mappings"):

* ``native`` - what an artist types: Radius = the skin's diffuse mean free path
  l_d = 1 / sigma_tr, sigma_tr = sqrt(3 sigma_a (sigma_a + sigma_s')) of the semi-infinite
  layer (the "mean free path" of Jensen et al. 2001's measured skin, which Blender's manual
  asks for), and Base Color = the albedo (the texture's linear value: the skin's total
  diffuse reflectance per entered flux, dermis's albedo convention).
* ``matched`` - fitted per channel so that a flat semi-infinite slab rendered by Cycles
  itself reflects what the skin reflects: Base Color b with Cycles' slab reflectance per
  entered flux Rd_e(b) = a (the texel's albedo, or the stack's Rd without a texture), and
  Radius rho with Cycles' slab mean exit radius rho m(b) = the skin's mean exit radius
  (of its layer profile R(r): integral r R 2 pi r dr / Rd).  Rd_e and m are measured once
  per method, IOR, roughness and anisotropy (:mod:`dermis.cycles.slab`); on a flat semi-
  infinite slab the reflectance does not depend on the radius and the exit distances scale
  with it, so Rd_e(b) and m(b) at radius 1 fix both inputs, b by inverting the measured
  Rd_e curve (monotone), rho = r_skin / m(b).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.integrate import trapezoid

__all__ = ["MAPPINGS", "diffuse_mean_free_path", "mean_exit_radius", "surface_inputs",
           "native_inputs", "matched_inputs", "invert_reflectance"]

MAPPINGS = ("matched", "native")


def diffuse_mean_free_path(stack) -> np.ndarray:
    """(3,) l_d = 1 / sigma_tr of the stack's semi-infinite (last) layer, mm."""
    layer = stack.layers[-1]
    sa = np.asarray(layer.sigma_a, np.float64)
    sp = np.asarray(layer.sigma_s_prime, np.float64)
    return 1.0 / np.sqrt(3.0 * sa * (sa + sp))


def mean_exit_radius(profile) -> np.ndarray:
    """(3,) mean distance from entry to exit of the light a layer profile reflects, mm:
    integral r R(r) 2 pi r dr / integral R(r) 2 pi r dr over its radial grid (trapezoids)."""
    r = np.asarray(profile.r_mm, np.float64)
    R = np.asarray(profile.R, np.float64)
    w = 2.0 * math.pi * r[:, None] * R
    return trapezoid(r[:, None] * w, r, axis=0) / trapezoid(w, r, axis=0)


def surface_inputs(stack, roughness: float) -> dict:
    """The inputs both mappings share (module docstring)."""
    eta = stack.layers[0].eta / stack.eta_above
    return {"ior": float(eta), "subsurface_ior": float(eta), "roughness": float(roughness),
            "anisotropy": float(stack.layers[-1].g)}


def native_inputs(stack, rd, roughness: float) -> dict:
    """Radius = l_d, Base Color = ``rd`` (used where there is no texture)."""
    return {**surface_inputs(stack, roughness),
            "radius": [float(x) for x in diffuse_mean_free_path(stack)],
            "base_colour": [float(x) for x in np.clip(rd, 0.0, 1.0)]}


def invert_reflectance(target, grid, rd_e) -> np.ndarray:
    """Base colours b (per channel, same shape as ``target`` (..., 3)) with Rd_e(b) = target:
    the measured curve ``rd_e`` (K, 3) at base colours ``grid`` (K,) inverted by monotone
    cubic (PCHIP) interpolation of b against Rd_e (linear interpolation left 1.1 % errors
    between grid points on the random walk's curve, measured by tests/test_cycles.py
    test05), clamped to the measured range."""
    from scipy.interpolate import PchipInterpolator
    t = np.asarray(target, np.float64)
    out = np.empty_like(t)
    g = np.asarray(grid, np.float64)
    for c in range(3):
        y = np.asarray(rd_e, np.float64)[:, c]
        keep = np.zeros(len(y), bool)     # the strictly increasing points (noise may
        top = -np.inf                     # leave two neighbours out of order)
        for i, v in enumerate(y):
            if v > top:
                keep[i], top = True, v
        f = PchipInterpolator(y[keep], g[keep], extrapolate=False)
        out[..., c] = f(np.clip(t[..., c], y[keep][0], y[keep][-1]))
    return out


def _at(grid, values, b) -> float:
    from scipy.interpolate import PchipInterpolator
    return float(PchipInterpolator(np.asarray(grid, np.float64), np.asarray(values, np.float64))(b))


def matched_inputs(stack, rd, r_skin, curves, roughness: float) -> dict:
    """Base Color and Radius fitted to the skin's ``rd`` (3,) and mean exit radius ``r_skin``
    (3,) mm on Cycles' slab ``curves`` (``grid`` (K,), ``rd_e`` (K, 3), ``mean_radius`` (K, 3)
    at radius 1: :class:`dermis.cycles.slab.SlabCurves`)."""
    b = invert_reflectance(np.asarray(rd, np.float64), curves.grid, curves.rd_e)
    m = np.array([_at(curves.grid, np.asarray(curves.mean_radius)[:, c], b[c]) for c in range(3)])
    radius = np.asarray(r_skin, np.float64) / m
    return {**surface_inputs(stack, roughness), "radius": [float(x) for x in radius],
            "base_colour": [float(x) for x in b]}
