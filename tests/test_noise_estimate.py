"""A render's own noise estimate (rendering/halves.py, ``RenderedImage.noise``) and the pixel
nets its halves are drawn from (lighting/strata.py ``PixelStrata``).

* the halves are the image split in two: rendering each half's samples alone gives
  ``linear + noise`` and ``linear - noise``;
* where a light has no sampling noise the estimate is exactly 0: point and directional lights
  at one camera ray per pixel (the pixel centre), and a uniform plane under a directional
  light at any spp;
* where the halves are independent and alike, E[noise^2] is the image's variance: over
  independent seeds, the mean over pixels of (mean noise^2 - sample variance of the image)
  is zero within 5 of its standard errors (pixels are independent: their jitters, strata
  and scrambles are drawn per pixel).  Cases: the camera jitter over a texture that varies
  along one image axis (the halves hold the same columns and rows of the pixel's 2 x 2
  grid), and a plane under an environment map (the light samples' two nets); and with one
  net for the pixel the relation E[noise^2] = 2 Var_indep - Var (module docstring of
  rendering/halves.py);
* the pixel's light samples are a (0, m, 2)-net and so is each half and each camera
  sample's share; their points are uniform (chi-square against uniform counts); so are a
  point's 64 samples of the irradiance pass and each half's 32.
Images are 32 x 32 on planes of a few triangles.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from dermis.lighting.environment import EnvironmentMap, procedural_sunset
from dermis.lighting.strata import PixelStrata
from dermis.lighting.visibility import Visibility
from dermis.models import lafortune, lambert
from dermis.pipeline.artifacts import SAMPLE_LIT
from dermis.pipeline.config import CameraConfig, LightConfig
from dermis.rendering.cast import cast
from dermis.rendering.halves import signs_of
from dermis.rendering.options import LightSampling, RenderOptions
from dermis.rendering.shade import render

sys.path.insert(0, str(Path(__file__).parent))
from render_fixtures import icosphere, plane  # noqa: E402

Z_MAX = 5.0          # standard errors: a false alarm below 1e-6 per assertion (normal tails)
CAMERA = CameraConfig(position=(0.0, 0.0, 400.0), look_at=(0.0, 0.0, 0.0), fov_deg=20.0,
                      width=32, height=32)


@pytest.fixture(scope="module")
def flat():
    """A 400 mm plane facing the camera, filling the view (every pixel fully covered)."""
    mesh = plane(size=400.0, n=4)
    return mesh, Visibility(mesh.vertices, mesh.faces)


@pytest.fixture(scope="module")
def sunset():
    return EnvironmentMap(procedural_sunset(256))


def _subset(samples, keep: np.ndarray, scale: np.ndarray):
    """The samples ``keep`` (K,) bool with weights times ``scale`` (K,), halves dropped."""
    from dataclasses import replace
    owner = np.repeat(np.arange(len(samples.counts)), samples.counts)
    return replace(samples, counts=np.bincount(owner[keep], minlength=len(samples.counts)
                                               ).astype(np.int32),
                   directions=samples.directions[keep],
                   weights=(samples.weights[keep] * scale[keep, None]).astype(np.float32),
                   flags=np.full(int(keep.sum()), SAMPLE_LIT, np.uint8))


def _z(d: np.ndarray) -> float:
    """The mean of independent per-pixel differences (H, W, 3) in units of its standard error
    (a pixel's channels are not independent of each other: their mean is one number)."""
    d = np.asarray(d, np.float64).reshape(-1, 3).mean(axis=1)
    return float(d.mean() / (d.std(ddof=1) / math.sqrt(len(d))))


# ---------------------------------------------------------------------------- bookkeeping
@pytest.mark.parametrize("spp", (1, 4))
def test01_the_halves_are_the_image_in_two(cl_env, spp):
    """Half A's image is 2 x its samples' sum plus the samples in both halves (/ spp): render
    the samples of each half alone, weights doubled, and they are linear +- noise."""
    mesh = icosphere(100.0, 4)
    vis = Visibility(mesh.vertices, mesh.faces)
    cam = CameraConfig(position=(0.0, 0.0, 600.0), look_at=(0.0, 0.0, 0.0), fov_deg=22.0,
                       width=32, height=32)
    lights = [LightConfig(name="e", type="environment", samples=16),
              LightConfig(name="p", type="point", position=(300.0, 300.0, 400.0),
                          intensity=(3e5,) * 3)]
    samples = cast(mesh, lights, cam, RenderOptions(spp=spp, seed=3, visibility=vis,
                   sampling=LightSampling(env=EnvironmentMap(procedural_sunset(128)))),
                   cl_env=cl_env)
    sign = signs_of(samples.flags)
    # at one camera sample the point light's samples are in both halves; at 4 each camera
    # sample's samples are in its half
    assert set(np.unique(sign)) == ({-1.0, 0.0, 1.0} if spp == 1 else {-1.0, 1.0})
    full = render(mesh, [], lafortune.MODEL, None, cam, RenderOptions(samples=samples),
                  cl_env=cl_env)
    halves = [render(mesh, [], lafortune.MODEL, None, cam,
                     RenderOptions(samples=_subset(samples, sign * s >= 0, 1.0 + (sign * s > 0))),
                     cl_env=cl_env).linear for s in (1.0, -1.0)]
    scale = float(np.abs(full.linear).max())
    np.testing.assert_allclose(halves[0], full.linear + full.noise, atol=1e-5 * scale)
    np.testing.assert_allclose(halves[1], full.linear - full.noise, atol=1e-5 * scale)
    assert full.noise.dtype == np.float32 and full.noise.shape == full.linear.shape
    assert np.abs(full.noise).max() > 1e-3 * scale       # the environment light's noise


def test02_no_noise_where_no_light_sample_is_random(cl_env, flat):
    """One camera ray through the pixel centre and point / directional lights: nothing is
    random, the estimate is exactly 0 (a textured Lafortune sphere: edges, shading, texture).
    A uniform Lambertian plane under a directional light at 4 camera samples: every camera
    sample returns the same radiance, so the covered pixels' noise is exactly 0 (and the
    silhouette's, whose camera samples hit or miss, is not all 0)."""
    tex = np.random.default_rng(5).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    lights = [LightConfig(name="p", type="point", position=(300.0, 300.0, 400.0),
                          intensity=(3e5,) * 3),
              LightConfig(name="d", type="directional", direction=(-0.5, 0.2, 1.0),
                          intensity=(0.5,) * 3)]
    cam = CameraConfig(position=(0.0, 0.0, 600.0), look_at=(0.0, 0.0, 0.0), fov_deg=22.0,
                       width=32, height=32)
    sphere = icosphere(100.0, 4)
    for mesh in (sphere, plane(300.0, 4, texture_srgb=tex)):
        res = render(mesh, lights, lafortune.MODEL, None, cam, RenderOptions(spp=1, seed=1),
                     cl_env=cl_env)
        assert res.linear.max() > 0 and np.all(res.noise == 0)
    env = render(sphere, LightConfig(name="e", type="environment", samples=16),
                 lafortune.MODEL, None, cam,
                 RenderOptions(spp=1, seed=1, sampling=LightSampling(
                     env=EnvironmentMap(procedural_sunset(128)))), cl_env=cl_env)
    assert np.count_nonzero(env.noise) > 0.5 * np.count_nonzero(env.mask)

    small = plane(size=100.0, n=4)                    # smaller than the view: a silhouette
    res = render(small, lights[1], lambert.MODEL, None, CAMERA,
                 RenderOptions(spp=4, seed=2, textured=False), cl_env=cl_env)
    inner = res.coverage >= 1
    edge = (res.coverage > 0) & (res.coverage < 1)
    assert inner.sum() > 100 and np.all(res.noise[inner] == 0)
    assert edge.sum() > 20 and np.count_nonzero(res.noise[edge].any(axis=-1)) > 0


# ---------------------------------------------------------------------- noise^2 = variance
def _seeds(render_one, seeds) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (all channels): the sample variance of the image over ``seeds`` renders and
    the mean noise^2."""
    imgs, n2 = [], []
    for s in seeds:
        r = render_one(s)
        imgs.append(r.linear.astype(np.float64))
        n2.append(r.noise.astype(np.float64) ** 2)
    return np.stack(imgs).var(axis=0, ddof=1), np.mean(n2, axis=0)


@pytest.mark.parametrize("axis", (0, 1))
def test03_camera_jitter_noise2_is_the_variance(cl_env, flat, axis):
    """A texture of random stripes along one image axis, a directional light, Lambert,
    4 camera samples: each pixel's value varies with where its jittered camera samples fall,
    and the halves (the diagonals of the 2 x 2 grid) hold one column and one row cell each,
    their jitters independent: E[noise^2] = Var exactly."""
    mesh, vis = flat
    stripes = np.random.default_rng(7).integers(0, 256, (1, 96, 1), dtype=np.uint8)
    tex = np.broadcast_to(stripes, (96, 96, 3)).copy()
    if axis:
        tex = tex.transpose(1, 0, 2).copy()
    mesh = plane(size=400.0, n=4, texture_srgb=tex)
    light = LightConfig(name="d", type="directional", direction=(0.0, 0.0, 1.0),
                        intensity=(1.0,) * 3)
    var, n2 = _seeds(lambda s: render(mesh, light, lambert.MODEL, None, CAMERA,
                                      RenderOptions(spp=4, seed=s, visibility=vis),
                                      cl_env=cl_env), range(32))
    assert var.mean() > 1e-4 * 0.25 ** 2          # the stripes make the pixels vary
    assert abs(_z(n2 - var)) < Z_MAX, (n2.mean(), var.mean())


@pytest.mark.parametrize("spp", (1, 4))
def test04_environment_noise2_is_the_variance(cl_env, flat, sunset, spp, monkeypatch):
    """A Lambertian plane under the procedural sunset, 16 samples per pixel: with the halves'
    own nets (the default) E[noise^2] = Var; with one net for the pixel E[noise^2] = 2 Var_ind
    - Var, Var_ind the independent halves' image variance (rendering/halves.py): both as
    zero-mean per-pixel differences over independent seeds (the two designs' seeds
    disjoint).  The map is sampled whole: the second relation needs each half of the one net
    to be distributed as a net of its own, true for 2^k points per pixel, not for the sky's
    12 of a split sun (lighting/sun.py; the default design with the split: test_env_sun.py)."""
    from dermis.lighting import emitters
    monkeypatch.setattr(emitters, "SPLIT_SUN", False)
    mesh, vis = flat
    light = LightConfig(name="e", type="environment", samples=16)

    def design(independent, offset):
        return _seeds(lambda s: render(
            mesh, light, lambert.MODEL, None, CAMERA,
            RenderOptions(spp=spp, seed=offset + s, visibility=vis, textured=False,
                          sampling=LightSampling(env=sunset, independent_halves=independent)),
            cl_env=cl_env), range(40))

    var_y, n2_y = design(True, 0)
    var_x, n2_x = design(False, 1000)
    assert abs(_z(n2_y - var_y)) < Z_MAX, (n2_y.mean(), var_y.mean())
    assert abs(_z(n2_x - 2 * var_y + var_x)) < Z_MAX, (n2_x.mean(), var_x.mean(), var_y.mean())
    assert var_x.mean() < var_y.mean()             # one net of 16 beats two of 8 here


# -------------------------------------------------------------------------------- the nets
def _is_net(points: np.ndarray) -> bool:
    """(P, n, 2) points, n = 2^m: every pixel's n points fill the n boxes of every shape
    2^-a x 2^-(m - a)."""
    n = points.shape[1]
    m = n.bit_length() - 1
    ok = True
    for a in range(m + 1):
        box = (np.floor(points[..., 0] * (1 << a)).astype(np.int64) * (1 << (m - a))
               + np.floor(points[..., 1] * (1 << (m - a))).astype(np.int64))
        ok &= bool(np.all(np.sort(box, axis=1) == np.arange(n)))
    return ok


@pytest.mark.parametrize("independent", (False, True))
def test05_pixel_samples_are_nets_and_uniform(rng, independent):
    """16 light samples per pixel over 4 camera samples: each camera sample's 4 points are a
    (0, 2, 2)-net, each half's 8 (camera samples 0 and 3, 1 and 2) a (0, 3, 2)-net, the
    pixel's 16 a (0, 4, 2)-net with one net (two nets of 8 with the halves' own); over pixels
    the points are uniform: chi-square of 8 x 8 counts below its 1e-6 quantile."""
    pixels = 4000
    pix = np.repeat(np.arange(pixels), 4)
    sub = np.tile(np.arange(4), pixels)
    strata = PixelStrata(pix, sub, 4, seed=9, independent=independent)
    u = strata.uniform_2d(rng, 4, salt=3).reshape(pixels, 4, 4, 2)     # pixel, sub, i, xy
    assert _is_net(u.reshape(-1, 4, 2))
    for half in ((0, 3), (1, 2)):
        assert _is_net(u[:, list(half)].reshape(pixels, 8, 2))
    assert _is_net(u.reshape(pixels, 16, 2)) != independent
    counts = np.histogram2d(u[..., 0].ravel(), u[..., 1].ravel(), bins=8,
                            range=[[0, 1], [0, 1]])[0]
    expected = u[..., 0].size / 64
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    assert chi2 < 132.0, chi2          # chi-square, 63 degrees of freedom: P(> 132) < 1e-6
    v = strata.uniform_1d(rng, 4, salt=4).reshape(pixels, 4, 4)
    if not independent:                # van der Corput: one point per 1/16 of [0, 1)
        assert np.all(np.sort(np.floor(v.reshape(pixels, 16) * 16).astype(int), axis=1)
                      == np.arange(16))
    for half in ((0, 3), (1, 2)):      # and per half, one per 1/8
        h = v[:, list(half)].reshape(pixels, 8)
        assert np.all(np.sort(np.floor(h * 8).astype(int), axis=1) == np.arange(8))


@pytest.mark.parametrize("independent", (False, True))
def test05b_a_points_64_samples_are_nets(rng, independent):
    """The irradiance pass's layout (lighting/irradiance.py "Halves": a point its own pixel,
    64 samples): each half's 32 points a (0, 5, 2)-net, the point's 64 a (0, 6, 2)-net with
    one net (the 5- and 6-digit trees, looked up by value for their first 4 digits)."""
    points = 3000
    strata = PixelStrata(np.arange(points), np.zeros(points, np.int64), 1, seed=4,
                         independent=independent)
    u = strata.uniform_2d(rng, 64, salt=2)
    assert all(_is_net(u[:, h * 32:(h + 1) * 32]) for h in (0, 1))
    assert _is_net(u) != independent
    v = strata.uniform_1d(rng, 64, salt=5)
    for h in (0, 1):
        assert np.all(np.sort(np.floor(v[:, h * 32:(h + 1) * 32] * 32).astype(int), axis=1)
                      == np.arange(32))


# ---------------------------------------------------------------------------- the artifact
def test06_render_stage_stores_the_noise(tmp_path):
    """A pipeline run's BRDF image artifact holds the render's noise estimate (float32, the
    image's shape) through the cache's save and load; an image without one loads as None."""
    import tomllib
    from scene_toml import QUICK, TINY, merge, to_toml
    from dermis.pipeline import api, artifacts
    from dermis.pipeline.artifacts import RenderedImage
    from dermis.pipeline.config import load_scene
    scene_dict = merge(tomllib.loads(QUICK.read_text()),
                       merge(TINY, {"render": {"lights": ["sunset"]},
                                    "output": {"output_dir": str(tmp_path / "out")}}))
    path = tmp_path / "tiny.toml"
    path.write_text(to_toml(scene_dict))
    summary = api.run(load_scene(path), cache=tmp_path / "cache", until="render", export=False)
    got = {rep.id: rep.path for rep in summary.nodes}
    image = artifacts.load(got["render-lafortune-sunset-high"])
    assert image.noise.dtype == np.float32 and image.noise.shape == image.linear.shape
    assert np.any(image.noise != 0) and np.all(image.noise[~image.mask] == 0)
    artifacts.save(RenderedImage(image.linear, image.mask), tmp_path / "plain")
    assert artifacts.load(tmp_path / "plain").noise is None
