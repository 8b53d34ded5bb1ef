"""The adaptive BSSRDF (subsurface/adaptive.py, docs/science.md §4 "Adaptive gather").

* A flat plate under a uniform directional light needs no gather: the predictor flags under
  1 % of the pixels and the local model equals the full BSSRDF within 0.5 % (the gather's
  own approximation error on a uniform plate: its clusters, 0.17-0.38 % relative RMSE at
  epsilon 0.5 against brute force, bench/results/gather.json and pipeline/config.py; the
  points' partition of unity to 0.1 %, subsurface/points.py).
* A knife-edge shadow (tests/test_knife_edge.py's scene) makes it gather along the edge, and
  the blend follows the profile's edge-spread function within the knife-edge test's
  tolerance (2 % of E Rd everywhere across +-5 half-energy radii).
* A thin slab lit from behind: its front gets all its light through the slab (the local
  limit says 0); the adaptive model carries it, from the gather sampled on the image and
  interpolated, equal to the full BSSRDF within the plate's tolerance.  A slab thicker than
  the profile's reach stays black.

The shading points are the hits of a pinhole camera looking straight down at the plate
(computed here on the plane z = 0: no ray caster needed), one per pixel.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from dermis.lighting.irradiance import irradiance
from dermis.lighting.visibility import Visibility
from dermis.optics.layers import PRESETS
from dermis.optics.transmittance import Transmittance
from dermis.pipeline.config import BssrdfConfig, CameraConfig, LightConfig
from dermis.subsurface import points as S
from dermis.subsurface.adaptive import adaptive_exitance
from dermis.subsurface.exitance import ExitanceOptions, ShadingPoints, exitance

from test_knife_edge import edge_spread, half_energy_radius, knife_scene

STACK = PRESETS["two_layer"]
# the knife-edge test's tolerance (tests/test_knife_edge.py TOL)
KNIFE_TOL = 0.02
# a uniform plate: the gather's approximation error (module docstring)
PLATE_TOL = 0.005


@pytest.fixture(scope="module")
def profile():
    from dermis.optics.layer_profiles import build_profiles
    return build_profiles(STACK)


def _transmittance():
    return Transmittance(STACK.layers[0].eta / STACK.eta_above, BssrdfConfig().surface_reflection)


def _options(cl_env):
    cfg = BssrdfConfig()
    return ExitanceOptions(epsilon=cfg.epsilon, leaf_size=cfg.leaf_size,
                           transmittance=_transmittance(), env=cl_env)


def looking_down(centre, width_mm: float, pixels: int, height_mm: float = 400.0):
    """A camera above the plane z = 0 looking down at ``centre`` (x, y) over ``width_mm``,
    ``pixels`` square, and its pixel centres' hits on the plane: (camera, (P, 3) points)."""
    fov = 2.0 * math.degrees(math.atan(0.5 * width_mm / height_mm))
    cam = CameraConfig(position=(centre[0], centre[1], height_mm),
                       look_at=(centre[0], centre[1], 0.0), up=(0.0, 1.0, 0.0), fov_deg=fov,
                       width=pixels, height=pixels)
    from dermis.rendering.camera import camera_vectors
    pos, fwd, right, up = camera_vectors(cam)
    t = math.tan(math.radians(fov) / 2.0)
    j, i = np.meshgrid(np.arange(pixels), np.arange(pixels))
    u = (2.0 * (j.ravel() + 0.5) / pixels - 1.0) * t
    v = (1.0 - 2.0 * (i.ravel() + 0.5) / pixels) * t
    d = fwd[None, :] + u[:, None] * right[None, :] + v[:, None] * up[None, :]
    hit = pos[None, :] + d * (-pos[2] / d[:, 2])[:, None]
    hit[:, 2] = 0.0
    return cam, hit


def _rel_rmse(a, b) -> float:
    """Relative RMSE of ``a`` against ``b`` over all channels (reports/diff.py's)."""
    return float(np.sqrt(((a - b) ** 2).mean()) / np.sqrt((b ** 2).mean()))


def _up(n):
    return np.tile([0.0, 0.0, 1.0], (n, 1))


def test01_uniform_plate_needs_no_gather(cl_env, profile):
    from flat_plate import flat_points
    plate = flat_points(STACK, profile, BssrdfConfig())
    inner = plate.half - plate.reach - 2.0
    cam, q = looking_down((0.0, 0.0), 2.0 * inner, 48)
    light = LightConfig(name="sun", type="directional", direction=(0.0, 0.0, 1.0),
                        intensity=(1.0, 1.0, 1.0))
    t = _transmittance()
    E = irradiance(plate.points.positions, plate.points.normals, [light],
                   plate.visibility.occluded, transmittance=t)
    shading = ShadingPoints(q, _up(len(q)), _up(len(q)))
    opts = _options(cl_env)
    full, _ = exitance(plate.points, E, profile, shading, lights=[light],
                       visibility=plate.visibility, options=opts)
    got, st = adaptive_exitance(plate.points, E, profile, shading, lights=[light],
                                visibility=plate.visibility, options=opts, camera=cam,
                                pixels=np.arange(len(q)))
    assert st["gathered_pixel_fraction"] < 0.01, st
    assert _rel_rmse(got, full) < PLATE_TOL
    # the local model is the profile's total reflectance times the irradiance
    np.testing.assert_allclose(got.mean(axis=0), profile.Rd * E.mean(axis=0), rtol=PLATE_TOL)


def test02_knife_edge_is_gathered_along_the_edge(cl_env, profile):
    sc = knife_scene(profile, STACK)
    radius = float(half_energy_radius(profile).max())
    span = 10.0 * radius
    cam, q = looking_down((sc["edge"], 0.0), span, 64)
    shading = ShadingPoints(q, _up(len(q)), _up(len(q)))
    opts = ExitanceOptions(epsilon=BssrdfConfig().epsilon, transmittance=sc["transmit"],
                           env=cl_env)
    got, st = adaptive_exitance(sc["pts"], sc["E"], profile, shading, lights=[sc["light"]],
                                visibility=sc["vis"], options=opts, camera=cam,
                                pixels=np.arange(len(q)))
    u = q[:, 0] - sc["edge"]
    w = st["blend"]
    # every pixel within two half-energy radii of the edge is gathered whole
    assert np.all(w[np.abs(u) < 2.0 * radius] == 1.0)
    ref = sc["lit"] * edge_spread(profile, u)
    err = np.abs(got - ref) / (sc["lit"] * profile.Rd)
    assert np.all(err.max(axis=0) < KNIFE_TOL), err.max(axis=0)


def _slab(thickness: float, half: float):
    """A closed box |x|, |y| < half, -thickness < z < 0 (outward normals)."""
    x0, x1, y0, y1, z0, z1 = -half, half, -half, half, -thickness, 0.0
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]])
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    return v, f


@pytest.mark.parametrize("thickness,thin", [(1.0, True), (40.0, False)])
def test03_thin_slab_lit_from_behind_carries_transmission(cl_env, profile, thickness, thin):
    cfg = BssrdfConfig()
    spacing = S.spacing_from_mfp(STACK, cfg.point_density)
    half = float(profile.cutoff_mm.max()) + 8.0 * spacing + 10.0
    v, f = _slab(thickness, half)
    pts = S.sample_points(v, f, spacing_mm=spacing, seed=3)
    vis = Visibility(v, f)
    light = LightConfig(name="back", type="directional", direction=(0.0, 0.0, -1.0),
                        intensity=(1.0, 1.0, 1.0))
    E = irradiance(pts.positions, pts.normals, [light], vis.occluded,
                   transmittance=_transmittance())
    cam, q = looking_down((0.0, 0.0), 8.0, 16)
    shading = ShadingPoints(q, _up(len(q)), _up(len(q)))
    opts = _options(cl_env)
    got, st = adaptive_exitance(pts, E, profile, shading, lights=[light], visibility=vis,
                                options=opts, camera=cam, pixels=np.arange(len(q)))
    # the front is unlit: the local limit (Rd C V) says 0, what reaches it is transported
    from dermis.subsurface.local import local_limit_exitance
    local, _ = local_limit_exitance(pts, E, profile, shading, lights=[light], visibility=vis,
                                    options=opts)
    assert np.all(local == 0.0)
    if thin:
        full, _ = exitance(pts, E, profile, shading, lights=[light], visibility=vis,
                           options=opts)
        # light does come through (the far part: red; the near part of a directional light
        # is taken at the shading point, subsurface/near_field.py, unlit here)
        assert full.max(axis=1).min() > 0
        # the sampled gather carries it to every pixel: gathered there, interpolated between
        assert st["sampled_points"] > 0 and got.max(axis=1).min() > 0
        assert _rel_rmse(got, full) < PLATE_TOL
    else:
        assert np.all(got == 0.0)


def test04_interpolation_never_extrapolates():
    """Pixels past the outermost samples (a close-up's border) take the nearest samples'
    values, never a linear extrapolation (which made a pixel of the default scene's ear
    close-up -7.6e-11: radiance cannot be negative)."""
    from dermis.subsurface.sparse_gather import interpolate, sample_grid
    w = h = 16
    pixels = np.arange(w * h)
    grid = sample_grid(pixels, w, h, 4)
    rows, cols = pixels[grid.points] // w, pixels[grid.points] % w
    # non-negative ramps, zero at the first sample row / column: extrapolated past it they
    # go negative
    values = np.stack([rows - rows.min(), cols - cols.min(), np.full(len(rows), 2.0)],
                      axis=1).astype(np.float64)
    out, ok, _ = interpolate(grid, values, pixels, w)
    assert ok.all()
    assert out.min() >= 0.0
    lo, hi = values.min(axis=0), values.max(axis=0)
    assert np.all((out >= lo - 1e-12) & (out <= hi + 1e-12))
    r, c = pixels // w, pixels % w
    inside = (r >= rows.min()) & (r <= rows.max()) & (c >= cols.min()) & (c <= cols.max())
    # between the samples it is bilinear: exact for a linear function
    np.testing.assert_allclose(out[inside, 0], (r - rows.min())[inside], atol=1e-12)
