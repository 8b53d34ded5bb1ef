"""The BSSRDF's local limit (models/bssrdf_local.py, subsurface/local.py; docs/science.md §4
"Local limit").

* On a flat plate under a directional light it is exactly Rd times the entering irradiance
  the light gives the shading point, C(x) (its intensity, cosine and entry transmittance,
  as ``lighting.irradiance`` gives the points): float32 rounding apart; and it equals the
  full BSSRDF there within the gather's own error on a uniform plate (tests/
  test_bssrdf_adaptive.py PLATE_TOL).
* Energy: under a disc light it is Rd times a convex combination of the points' irradiance
  (normalised Gaussian weights, Shepard 1968), so it lies within Rd times their range and
  never exceeds Rd times the largest.
* It is a registered BSSRDF-stage model with its own exitance, the requirement table's
  "subsurface transport" pair.
"""
from __future__ import annotations

import numpy as np
import pytest

from dermis.lighting.irradiance import irradiance
from dermis.optics.layers import PRESETS
from dermis.pipeline.config import BssrdfConfig, LightConfig
from dermis.subsurface.exitance import ShadingPoints, exitance
from dermis.subsurface.local import local_limit_exitance

from test_bssrdf_adaptive import PLATE_TOL, _options, _rel_rmse, _transmittance, _up, looking_down

STACK = PRESETS["two_layer"]
# float32 arithmetic of the light's evaluation at the shading point vs the points'
FLOAT_TOL = 1e-5


@pytest.fixture(scope="module")
def profile():
    from dermis.optics.layer_profiles import build_profiles
    return build_profiles(STACK)


@pytest.fixture(scope="module")
def plate(profile):
    from flat_plate import flat_points
    return flat_points(STACK, profile, BssrdfConfig())


def test01_directional_plate_is_rd_times_irradiance(cl_env, profile, plate):
    inner = plate.half - plate.reach - 2.0
    cam, q = looking_down((0.0, 0.0), 2.0 * inner, 32)
    light = LightConfig(name="sun", type="directional", direction=(0.3, 0.0, 1.0),
                        intensity=(1.0, 0.8, 0.6))
    t = _transmittance()
    shading = ShadingPoints(q, _up(len(q)), _up(len(q)))
    opts = _options(cl_env)
    got, st = local_limit_exitance(plate.points, None, profile, shading, lights=[light],
                                   visibility=plate.visibility, options=opts,
                                   pixels=np.arange(len(q)))
    e_here = irradiance(q, _up(len(q)), [light], plate.visibility.occluded, transmittance=t)
    np.testing.assert_allclose(got, profile.Rd[None, :] * e_here, rtol=FLOAT_TOL)
    E = irradiance(plate.points.positions, plate.points.normals, [light],
                   plate.visibility.occluded, transmittance=t)
    full, _ = exitance(plate.points, E, profile, shading, lights=[light],
                       visibility=plate.visibility, options=opts)
    assert _rel_rmse(got, full) < PLATE_TOL


def test02_disc_light_within_rd_times_the_points_range(cl_env, profile, plate):
    inner = plate.half - plate.reach - 2.0
    cam, q = looking_down((0.0, 0.0), 2.0 * inner, 32)
    # a disc close to the plate: the irradiance falls off across it
    light = LightConfig(name="disc", type="disc", position=(0.0, 0.0, 10.0),
                        direction=(0.0, 0.0, -1.0), radius=2.0, intensity=(1.0, 1.0, 1.0),
                        samples=16)
    E = irradiance(plate.points.positions, plate.points.normals, [light],
                   plate.visibility.occluded, transmittance=_transmittance())
    shading = ShadingPoints(q, _up(len(q)), _up(len(q)))
    got, _ = local_limit_exitance(plate.points, E, profile, shading, lights=[light],
                                  visibility=plate.visibility, options=_options(cl_env),
                                  pixels=np.arange(len(q)))
    assert np.all(np.isfinite(got)) and np.all(got >= 0.0)
    top = profile.Rd * E.max(axis=0)
    assert np.all(got <= top[None, :] * (1.0 + FLOAT_TOL))
    # the irradiance does vary over the view (the test can fail)
    assert got[:, 0].max() > 1.2 * got[:, 0].min()


def test03_registered_as_the_transport_pair():
    from dermis.pipeline import registry
    from dermis.reports.requirements import EFFECTS
    m = registry.model("bssrdf_local")
    assert m.stage == "bssrdf" and m.exitance is local_limit_exitance and m.profiles
    pair = next(e for e in EFFECTS if e.name == "subsurface transport")
    assert pair.with_ == ("bssrdf", "high") and pair.without == ("bssrdf_local", "high")


def test04_the_requirement_table_measures_transport_with_it():
    from test_requirements import ear_brighter, image, run
    req = run([image("bssrdf", ear_brighter(0.5, 0.05)), image("bssrdf_local", 0.5)])
    rows = req["main"]["point"]["regions"]
    e = rows["ear"]["effects"]["subsurface transport"]
    assert e["measured"] and e["verdict"] == "visible" and abs(e["signed"] - 0.05) < 1e-6
    assert rows["cheek"]["effects"]["subsurface transport"]["verdict"] == "absent"
