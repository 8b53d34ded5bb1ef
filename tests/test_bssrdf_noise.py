"""The BSSRDF image's own noise estimate: the irradiance pass's halves (lighting/irradiance.py
"Halves"), their gather (subsurface/exitance.py ``noise``, ``Octree.carrying``) and the
BSSRDF stage's ``RenderedImage.noise`` (stages/bssrdf.py).

* point and directional lights have no sampling noise: the noise is exactly 0 and E is the
  plain estimator's, to float32 rounding;
* under a disc light and under the procedural sunset (mixture, control variate, sun split), on
  irradiance points of a plate beside an occluding wall: no point negative; the mean over
  seeds within 5 standard errors (its own and the reference's) of a many-sample plain
  estimate, or within a tenth of one estimate's noise (the control estimator's O(1 / S)
  bias, as tests/test_env_sun.py); the mean noise^2 over the seeds' variance within
  0.6 - 1.6 (thousands of point channels x 11 degrees of freedom: wide against the chi-square
  spread, narrow against a factor 2 of a broken estimate); and under the sunset the control
  variate's spread below the plain estimator's;
* the gather is linear in what the tree carries: the irradiance itself carried through its
  own clusters gathers to the exitance (soft light: the whole profile from the points);
* the exitance's noise tracks its spread over seeds (the same band: the queries' noise is
  correlated over the profile's reach, hundreds of independent regions x 11 degrees of
  freedom remain);
* the pipeline's BSSRDF images - full, local, adaptive - carry a noise field of their shape,
  nonzero under the sunset, zero off the head.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from dermis.lighting.environment import EnvironmentMap, procedural_sunset
from dermis.lighting.emitters import SamplingOptions
from dermis.lighting.irradiance import irradiance
from dermis.lighting.visibility import Visibility
from dermis.optics.layers import PRESETS
from dermis.optics.transmittance import Transmittance
from dermis.pipeline.config import BssrdfConfig, LightConfig
from dermis.subsurface import points as S
from dermis.subsurface.exitance import ExitanceOptions, ShadingPoints, exitance

STACK = PRESETS["two_layer"]     # conftest.py two_layer_profile: its profiles
SEEDS = 12
SAMPLES = 16


@pytest.fixture(scope="module")
def scene():
    """A 60 mm plate (z = 0, up) with a 40 mm wall along its back edge (y = -30, facing +y),
    each face with vertices of its own (flat normals); blue-noise points at 1 mm."""
    plate = np.array([[-30, -30, 0], [30, -30, 0], [30, 30, 0], [-30, 30, 0]], np.float64)
    wall = np.array([[-30, -30, 0], [30, -30, 0], [30, -30, 40], [-30, -30, 40]], np.float64)
    v = np.vstack([plate, wall])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]], np.int64)
    vn = np.vstack([np.tile([0.0, 0.0, 1.0], (4, 1)), np.tile([0.0, 1.0, 0.0], (4, 1))])
    pts = S.sample_points(v, f, spacing_mm=1.0, seed=3, vertex_normals=vn)
    vis = Visibility(v, f.astype(np.int32))
    env = EnvironmentMap(procedural_sunset(512), name="procedural")
    eta = STACK.layers[0].eta / STACK.eta_above
    return {"pts": pts, "vis": vis, "env": env,
            "transmit": Transmittance(eta, BssrdfConfig().surface_reflection)}


def _light(kind: str) -> LightConfig:
    if kind == "disc":     # behind the wall: its penumbra on the plate, its front dark
        return LightConfig(name="disc", type="disc", position=(0.0, -80.0, 100.0),
                           direction=(0.0, 0.62, -0.78), radius=20.0,
                           intensity=(1e3, 1e3, 1e3), samples=SAMPLES)
    return LightConfig(name="sunset", type="environment", samples=SAMPLES)


def _halves(sc, light, seed, samples=SAMPLES):
    return irradiance(sc["pts"].positions, sc["pts"].normals, [light], sc["vis"].occluded,
                      seed=seed, options=SamplingOptions(samples=samples, env=sc["env"]),
                      transmittance=sc["transmit"], halves=True)


@pytest.mark.parametrize("kind", ("point", "directional"))
def test01_sharp_lights_have_no_noise(scene, kind):
    light = (LightConfig(name="lamp", type="point", position=(40.0, -100.0, 150.0),
                         intensity=(1e4, 1e4, 1e4)) if kind == "point" else
             LightConfig(name="sun", type="directional", direction=(0.2, -0.5, 0.8),
                         intensity=(1.0, 0.9, 0.8)))
    E, noise = _halves(scene, light, 0)
    assert np.all(noise == 0)
    plain = irradiance(scene["pts"].positions, scene["pts"].normals, [light],
                       scene["vis"].occluded, transmittance=scene["transmit"])
    assert 0.3 < (plain > 0).mean() < 0.7   # lit and shadowed points
    np.testing.assert_allclose(E, plain, rtol=1e-6, atol=1e-6 * float(plain.max()))


@pytest.mark.parametrize("kind", ("disc", "sunset"))
def test02_points_noise_is_their_variance_and_unbiased(scene, kind):
    light = _light(kind)
    runs = [_halves(scene, light, s) for s in range(SEEDS)]
    E = np.stack([r[0] for r in runs]).astype(np.float64)         # (seeds, N, 3)
    assert np.all(np.isfinite(E)) and np.all(E >= 0)
    pts, opts = scene["pts"], SamplingOptions(samples=1024, env=scene["env"])
    ref = np.stack([irradiance(pts.positions, pts.normals, [light], scene["vis"].occluded,
                               seed=100 + s, options=opts, transmittance=scene["transmit"])
                    for s in range(2)]).astype(np.float64)
    var = E.var(axis=0, ddof=1)
    lit = ref.mean(0).sum(axis=1) > 0
    assert (~lit).any() or kind == "sunset"      # the disc leaves the wall's front dark
    diff = E.mean(0)[lit] - ref.mean(0)[lit]
    var_r = ref.var(axis=0, ddof=1)[lit] / 2
    se = math.sqrt((var[lit] / SEEDS + var_r).sum()) / diff.size
    noise = math.sqrt(var[lit].mean())
    assert noise > 0
    assert abs(diff.mean()) < max(5 * se, 0.1 * noise), (diff.mean(), se, noise)
    own = np.mean([r[1][lit].astype(np.float64) ** 2 for r in runs])
    ratio = own / var[lit].mean()
    assert 0.6 < ratio < 1.6, ratio
    if kind == "sunset":   # the control variate pays: the plain estimator's spread is larger
        plain = np.stack([irradiance(pts.positions, pts.normals, [light], scene["vis"].occluded,
                                     seed=200 + s, options=SamplingOptions(samples=SAMPLES,
                                                                           env=scene["env"]),
                                     transmittance=scene["transmit"]) for s in range(SEEDS)])
        assert plain.astype(np.float64).var(axis=0, ddof=1)[lit].mean() > 1.5 * var[lit].mean()


def _options(cl_env):
    cfg = BssrdfConfig()
    return ExitanceOptions(epsilon=cfg.epsilon, leaf_size=cfg.leaf_size, env=cl_env)


def _queries(n: int, rng):
    """Plate points away from its border and the wall (beyond the profile's reach)."""
    q = np.zeros((n, 3))
    q[:, 0] = rng.uniform(-18.0, 18.0, n)
    q[:, 1] = rng.uniform(-18.0, 18.0, n)
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    return ShadingPoints(q, up, up)


def test03_carrying_the_irradiance_gathers_the_exitance(cl_env, scene, two_layer_profile,
                                                        rng):
    profile = two_layer_profile
    E, _ = _halves(scene, _light("disc"), 0)
    shading = _queries(2000, rng)
    M, st = exitance(scene["pts"], E, profile, shading, lights=[_light("disc")],
                     visibility=scene["vis"], options=_options(cl_env), noise=E)
    assert M.max() > 0
    np.testing.assert_allclose(st["noise"], M, rtol=1e-4, atol=1e-5 * float(M.max()))


def test04_exitance_noise_tracks_its_spread(cl_env, scene, two_layer_profile, rng):
    profile = two_layer_profile
    light = _light("sunset")
    shading = _queries(4000, rng)
    Ms, noises = [], []
    for s in range(SEEDS):
        E, noise = _halves(scene, light, s)
        M, st = exitance(scene["pts"], E, profile, shading, lights=[light],
                         visibility=scene["vis"], options=_options(cl_env), noise=noise)
        Ms.append(M.astype(np.float64))
        noises.append(st["noise"].astype(np.float64))
    var = np.stack(Ms).var(axis=0, ddof=1)
    assert var.mean() > 0
    ratio = np.mean([n ** 2 for n in noises]) / var.mean()
    assert 0.6 < ratio < 1.6, ratio
    # without the points' noise, none
    _, st = exitance(scene["pts"], E, profile, shading, lights=[light], visibility=scene["vis"],
                     options=_options(cl_env))
    assert st["noise"] is None


def test05_pipeline_bssrdf_images_carry_their_noise(tmp_path):
    import tomllib
    from scene_toml import QUICK, TINY, merge, to_toml
    from dermis.pipeline import api, artifacts
    from dermis.pipeline.config import load_scene
    models = ["bssrdf", "bssrdf_local", "bssrdf_adaptive"]
    scene_dict = merge(tomllib.loads(QUICK.read_text()),
                       merge(TINY, {"render": {"lights": ["sunset"], "models": models},
                                    "output": {"output_dir": str(tmp_path / "out")}}))
    path = tmp_path / "tiny.toml"
    path.write_text(to_toml(scene_dict))
    summary = api.run(load_scene(path), cache=tmp_path / "cache", until="bssrdf", export=False)
    got = {rep.id: rep.path for rep in summary.nodes}
    for m in models:
        image = artifacts.load(got[f"render-{m}-sunset-high"])
        assert image.noise is not None, m
        assert image.noise.dtype == np.float32 and image.noise.shape == image.linear.shape
        assert np.all(np.isfinite(image.noise)) and np.all(image.noise[~image.mask] == 0), m
        assert np.any(image.noise[image.mask] != 0), m
