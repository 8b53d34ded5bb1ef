"""Tests of the bake (geometry/bake.py, uv_raster.py, texture_fill.py) and geometry/bump.py: UV
rasterisation, albedo/bump bake, blur, dilation, bump normals.

Independent evidence: analytic spheres (tests/bake_fixtures.py) and, for the texel -> surface
point mapping, matplotlib's trapezoid-map triangle finder instead of the bake's own rasteriser.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from matplotlib.tri import Triangulation

from bake_fixtures import (bumpy_radius, direction_of_uv, latlong_sphere, latlong_texture,
                           smooth_colour, srgb8)
from dermis.geometry.bake import bake_maps
from dermis.geometry.bump import (bump_shading_normals, bump_shading_normals_at_hits,
                                  triangle_tangent_frames)
from dermis.geometry.texture_fill import masked_blur, nearest_fill_indices, nearest_within
from dermis.geometry.uv_raster import rasterise
from dermis.pipeline.artifacts import BakedMaps, Mesh
from dermis.pipeline.errors import ConfigError, DermisError

R_MM = 100.0            # sphere radius
AMPLITUDE_MM = 1.0      # bump amplitude a in r = R + a f, |f| <= 1
RES = 256               # map side for the fast tests

# Coarse low sphere: 24 x 48 grid, mean edge ~12.6 mm, chord sagitta <= ~0.3 mm.
LOW_GRID = (24, 48)
# Fine high sphere: 160 x 320 grid (~100k triangles): its own sagitta is <= e^2 / 8R ~ 0.004 mm.
HIGH_GRID = (160, 320)


def _texel_surface_points(low: Mesh, res: int):
    """Independent texel -> low-surface mapping with matplotlib's triangle finder.

    Returns (rows, cols, points (N, 3)) for texel centres inside a UV triangle.
    """
    tri = Triangulation(low.uv[:, 0].astype(np.float64), low.uv[:, 1].astype(np.float64),
                        low.uv_faces)
    finder = tri.get_trifinder()
    rows, cols = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    u, v = cols.ravel() / (res - 1), 1.0 - rows.ravel() / (res - 1)
    t = finder(u, v)
    inside = t >= 0
    t, u, v = t[inside], u[inside], v[inside]
    c = low.uv[low.uv_faces[t]].astype(np.float64)                  # (N, 3, 2)
    m = np.stack([c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]], axis=2)    # (N, 2, 2)
    b12 = np.linalg.solve(m, np.stack([u, v], 1)[..., None] - c[:, 0, :, None])[..., 0]
    w = np.concatenate([1 - b12.sum(1, keepdims=True), b12], axis=1)
    p = np.einsum("nk,nkd->nd", w, low.vertices[low.faces[t]])
    return rows.ravel()[inside], cols.ravel()[inside], p


@pytest.fixture(scope="module")
def low():
    return latlong_sphere(*LOW_GRID, R_MM)


@pytest.fixture(scope="module")
def textured_high():
    return latlong_sphere(*HIGH_GRID, R_MM, texture_srgb=latlong_texture(256, 512))


@pytest.fixture(scope="module")
def bumpy_high():
    return latlong_sphere(*HIGH_GRID, bumpy_radius(R_MM, AMPLITUDE_MM))


@pytest.fixture(scope="module")
def bumpy_maps(low, bumpy_high):
    """Heights from the flat low triangles (the thesis's literal rule)."""
    return bake_maps(low, bumpy_high, resolution=RES, blur_sigma_px=4.0, reference="flat")


@pytest.fixture(scope="module")
def bumpy_maps_phong(low, bumpy_high):
    """Heights from the low mesh's Phong surface (the default)."""
    return bake_maps(low, bumpy_high, resolution=RES, blur_sigma_px=4.0)


# ---------------------------------------------------------------------------------------
def test01_bad_args_rejected(low, textured_high):
    for kwargs, name in [({"resolution": 0}, "resolution"), ({"resolution": -4}, "resolution"),
                         ({"resolution": 64.5}, "resolution"),
                         ({"blur_sigma_px": -1.0}, "blur_sigma_px"),
                         ({"max_distance_mm": 0.0}, "max_distance_mm"),
                         ({"dilate_px": -1}, "dilate_px")]:
        with pytest.raises(ConfigError, match=name):
            bake_maps(low, textured_high, **{"resolution": 32, **kwargs})
    no_uv = dataclasses.replace(low, uv=None, uv_faces=None)
    with pytest.raises(ConfigError, match=r"low\.uv"):
        bake_maps(no_uv, textured_high, resolution=32)
    bad_faces = dataclasses.replace(low, faces=low.faces + 10_000)
    with pytest.raises(DermisError, match=r"low\.faces"):
        bake_maps(bad_faces, textured_high, resolution=32)


def test02_rasteriser_matches_independent_trifinder(low):
    # Coverage must equal the set of texel centres inside some UV triangle; only centres
    # lying exactly on a chart's outer edge (here u = 0 / u = 1 columns and pole triangle
    # hypotenuses) may differ, as the two inside tests round differently there.
    flat, tri, _, info = rasterise(low.uv, low.uv_faces, RES)
    rows, cols, _ = _texel_surface_points(low, RES)
    ours = np.zeros(RES * RES, bool)
    ours[flat] = True
    ref = np.zeros(RES * RES, bool)
    ref[rows * RES + cols] = True
    assert len(np.unique(flat)) == len(flat)
    assert info["degenerate_uv_triangles"] == 0
    mismatch = np.count_nonzero(ours != ref)
    assert mismatch <= 0.002 * ref.sum(), mismatch


def test03_albedo_reproduces_source_texture(low, textured_high):
    # Expected: the colour field at the surface point of each texel (the high sphere has the
    # same radius, so the radial ray hits the same direction).  Error budget: 8-bit rounding
    # twice (source texture and output, ~56 dB alone), bilinear texture reconstruction and the
    # high mesh's linear UV interpolation (both O(h^2) of a field varying on ~100 mm).
    # Measured 59.2 dB.  Bound 57 dB: shifting the source UVs by half a texel measured
    # 55.7 dB, skipping the sRGB decode 14.7 dB, so both fail it.
    PSNR_MIN_DB = 57.0
    maps = bake_maps(low, textured_high, resolution=RES)
    rows, cols, p = _texel_surface_points(low, RES)
    expected = srgb8(smooth_colour(p / np.linalg.norm(p, axis=1, keepdims=True))).astype(float)
    got = maps.albedo_srgb[rows, cols].astype(float)
    mse = np.mean((got - expected) ** 2)
    psnr = 10 * np.log10(255.0 ** 2 / mse)
    assert psnr >= PSNR_MIN_DB, psnr
    assert maps.info["misses"] == 0
    assert maps.albedo_srgb.dtype == np.uint8 and maps.albedo_srgb.shape == (RES, RES, 3)


def test04_bump_reproduces_analytic_height(low, bumpy_maps):
    # Expected height along the (radial, exact) normal: r(dir(p)) - |p|.  Error budget: the
    # high mesh lies inside the analytic surface by its chord deficit, <= d^2 / 2R with the
    # half-diagonal d ~ 1.4 mm of its grid cells, i.e. <= 0.01 mm = 1 % of the amplitude
    # (a one-sided bias); float32 ray origins add ~1e-5 mm.  Bounds relative to the
    # amplitude: max 2 %, rms 1 % (measured ~1.0 % / 0.5 %).
    MAX_ERR_REL, RMS_ERR_REL = 0.02, 0.01
    maps = bumpy_maps
    rows, cols, p = _texel_surface_points(low, RES)
    dist = np.linalg.norm(p, axis=1)
    expected = bumpy_radius(R_MM, AMPLITUDE_MM)(p / dist[:, None]) - dist
    got = maps.bump_min_mm + maps.bump[rows, cols].astype(float) * maps.bump_range_mm
    err = np.abs(got - expected) / AMPLITUDE_MM
    assert err.max() <= MAX_ERR_REL, err.max()
    assert np.sqrt(np.mean(err ** 2)) <= RMS_ERR_REL
    assert maps.info["misses"] == 0
    assert 0.0 <= maps.bump.min() and maps.bump.max() <= 1.0
    assert maps.bump_range_mm > AMPLITUDE_MM      # spans at least the bumps' peak-to-peak / 2


def test04b_phong_reference_keeps_only_the_bumps(low, bumpy_maps_phong):
    # With the Phong reference (alpha 1/2 reproduces a sphere to second order) the height is
    # the bump above the sphere, r(dir) - R, not the chord dip (up to 0.43 mm = 43 % of the
    # amplitude here, which the flat reference keeps).  Error budget as test04 plus the
    # third-order Phong residual; measured max 1.0 %, rms 0.43 %.
    MAX_ERR_REL, RMS_ERR_REL = 0.02, 0.01
    maps = bumpy_maps_phong
    rows, cols, p = _texel_surface_points(low, RES)
    expected = bumpy_radius(R_MM, AMPLITUDE_MM)(p / np.linalg.norm(p, axis=1)[:, None]) - R_MM
    got = maps.bump_min_mm + maps.bump[rows, cols].astype(float) * maps.bump_range_mm
    err = np.abs(got - expected) / AMPLITUDE_MM
    assert err.max() <= MAX_ERR_REL, err.max()
    assert np.sqrt(np.mean(err ** 2)) <= RMS_ERR_REL
    assert maps.info["height_reference"] == "phong"
    with pytest.raises(ConfigError, match="bake.reference = 'bent': must be 'phong' or 'flat'"):
        bake_maps(low, low, resolution=16, reference="bent")


def test05_blur_lowers_gradient_energy(bumpy_maps):
    def gradient_energy(img, mask):
        gy, gx = np.gradient(img.astype(float))
        return np.sum((gx ** 2 + gy ** 2)[mask])
    inner = bumpy_maps.coverage.copy()
    sharp = gradient_energy(bumpy_maps.bump, inner)
    blurred = gradient_energy(bumpy_maps.bump_blur, inner)
    assert blurred < 0.9 * sharp, (blurred, sharp)
    assert bumpy_maps.bump_blur.dtype == np.float32
    assert 0.0 <= bumpy_maps.bump_blur.min() and bumpy_maps.bump_blur.max() <= 1.0
    assert np.isfinite(bumpy_maps.bump_blur).all()


def test06_masked_blur_keeps_chart_borders_unbiased():
    # Normalised convolution: a constant over an irregular chart stays exactly constant up to
    # the chart border (a plain blur with the background at 0 halves it there; one of the
    # nearest-filled map weights border texels up), texels away from the border match a plain
    # Gaussian, and outputs stay inside the covered values' range.
    SIGMA = 3.0
    FLOAT_TOL = 1e-5          # float32 filter accumulation
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:96, :96]
    mask = ((yy - 40) ** 2 + (xx - 50) ** 2 < 30 ** 2) & (xx + yy > 50)
    const = np.full(mask.shape, 0.7, np.float32)
    out = masked_blur(const, mask, SIGMA)
    assert np.abs(out[mask] - 0.7).max() < FLOAT_TOL
    assert (out[~mask] == 0).all()
    from scipy import ndimage
    plain = ndimage.gaussian_filter(np.where(mask, const, 0).astype(np.float32), SIGMA)
    assert np.abs(plain[mask] - 0.7).max() > 0.2          # what the masking avoids
    noise = rng.random(mask.shape).astype(np.float32)
    out = masked_blur(noise, mask, SIGMA)
    inner = ndimage.binary_erosion(mask, np.ones((3, 3), bool), iterations=int(4 * SIGMA) + 1)
    ref = ndimage.gaussian_filter(noise, SIGMA, mode="constant")
    assert np.abs(out[inner] - ref[inner]).max() < FLOAT_TOL
    assert noise[mask].min() <= out[mask].min() and out[mask].max() <= noise[mask].max()
    assert np.array_equal(masked_blur(noise, mask, 0.0), noise)


def test07_dilation_fills_outside_and_keeps_covered(low, textured_high):
    DILATE = 5
    scaled = dataclasses.replace(low, uv=(0.1 + 0.8 * low.uv).astype(np.float32))
    plain = bake_maps(scaled, textured_high, resolution=128, dilate_px=0, blur_sigma_px=2.0)
    dil = bake_maps(scaled, textured_high, resolution=128, dilate_px=DILATE, blur_sigma_px=2.0)
    cov = plain.coverage
    assert (cov == dil.coverage).all() and not cov.all()
    for a, b in [(plain.albedo_srgb, dil.albedo_srgb), (plain.bump, dil.bump),
                 (plain.bump_blur, dil.bump_blur)]:
        assert np.array_equal(a[cov], b[cov])
    # Band texels take the value of a nearest covered texel (checked against a k-d tree search
    # over covered texels; any of several equidistant ones may be chosen), and the band is
    # exactly the texels within DILATE of a chart.  Farther texels get the neutral height.
    from scipy.spatial import cKDTree
    cy, cx = np.nonzero(cov)
    tree = cKDTree(np.stack([cy, cx], 1))
    oy, ox = np.nonzero(~cov)
    d, j = tree.query(np.stack([oy, ox], 1), k=8)
    band = d[:, 0] <= DILATE
    assert band.any() and (~band).any()
    assert dil.info["dilated_texels"] == band.sum()
    tie = d[band] <= d[band, :1] + 1e-9                                  # (Nb, 8)
    candidates = dil.bump[cy[j[band]], cx[j[band]]]                      # (Nb, 8)
    got = dil.bump[oy[band], ox[band]][:, None]
    assert ((candidates == got) & tie).any(axis=1).all()
    neutral = np.clip(-dil.bump_min_mm / dil.bump_range_mm, 0, 1)
    assert np.allclose(dil.bump[oy[~band], ox[~band]], neutral)
    assert np.isfinite(dil.bump).all() and np.isfinite(dil.bump_blur).all()


def test08_far_high_mesh_gives_counted_misses(low, textured_high):
    # The high sphere moved 1000 mm along +x: rays from the low sphere's +x side hit it at
    # ~800 mm, far beyond max_distance, so every texel is a miss.
    far = dataclasses.replace(textured_high, vertices=textured_high.vertices + [1000.0, 0, 0])
    maps = bake_maps(low, far, resolution=64)
    assert maps.info["hits"] == 0
    assert maps.info["misses"] == maps.info["covered_texels"] == int(maps.coverage.sum()) > 0
    assert maps.bump_range_mm == 0.0 and maps.bump_min_mm == 0.0
    for arr in (maps.bump, maps.bump_blur):
        assert np.isfinite(arr).all()
    # The same with a reach long enough does find it (so the threshold is what excluded it).
    reach = bake_maps(low, far, resolution=64, max_distance_mm=2000.0)
    assert reach.info["hits"] > 0


def test09_misses_inside_charts_are_neutral_and_filled(low, textured_high):
    # Remove the high sphere's northern cap: texels there miss, get height 0 mm and the
    # albedo of the nearest texel with a hit.
    keep = textured_high.vertices[textured_high.faces].mean(1)[:, 2] < 0.7 * R_MM
    cut = dataclasses.replace(textured_high, faces=textured_high.faces[keep],
                              uv_faces=textured_high.uv_faces[keep])
    maps = bake_maps(low, cut, resolution=RES)
    assert maps.info["misses"] > 0 and maps.info["hits"] > 0
    rows, cols, p = _texel_surface_points(low, RES)
    cap = p[:, 2] / np.linalg.norm(p, axis=1) > 0.75
    h = maps.bump_min_mm + maps.bump[rows[cap], cols[cap]] * maps.bump_range_mm
    assert np.allclose(h, 0.0, atol=1e-5 * max(maps.bump_range_mm, 1.0))
    assert (maps.albedo_srgb[rows[cap], cols[cap]].sum(1) > 0).all()



def test09b_windowed_nearest_matches_whole_map_edt():
    # _nearest_within transforms only tiles grown by the reach; it must pick the very texel
    # the whole map's EDT picks, ties included (sparse random masks give many equidistant
    # texels), and report exactly the query texels with none within reach as far.
    rng = np.random.default_rng(7)
    for _ in range(200):
        h, w = (int(n) for n in rng.integers(3, 90, 2))
        valid = rng.random((h, w)) < rng.choice([0.002, 0.02, 0.1, 0.6])
        if not valid.any():
            continue
        query = ~valid & (rng.random((h, w)) < rng.choice([0.05, 1.0]))
        reach, tile = int(rng.integers(0, 10)), int(rng.integers(1, 40))
        iy, ix = nearest_fill_indices(valid)
        rows, cols = np.nonzero(query)
        d2 = (iy[rows, cols] - rows) ** 2 + (ix[rows, cols] - cols) ** 2
        near = d2 <= reach * reach
        dst, src, far = nearest_within(valid, query, reach, tile)
        order = np.argsort(dst)
        assert np.array_equal(dst[order], (rows * w + cols)[near])
        assert np.array_equal(src[order], (iy[rows, cols] * w + ix[rows, cols])[near])
        assert np.array_equal(np.sort(far), (rows * w + cols)[~near])


# ---------------------------------------------------------------------------------------
def _plane_frame(n_points, a=2.0, seed=0):
    """Points on the plane p = (a u, a v, 0) with n = +z."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(0.2, 0.8, (n_points, 2))
    normals = np.tile([0.0, 0.0, 1.0], (n_points, 1))
    dpdu = np.tile([a, 0.0, 0.0], (n_points, 1))
    dpdv = np.tile([0.0, a, 0.0], (n_points, 1))
    return uv, normals, dpdu, dpdv


def test10_zero_bump_leaves_normals():
    uv, n, dpdu, dpdv = _plane_frame(100)
    n = n + np.random.default_rng(1).normal(0, 0.2, n.shape)
    out = bump_shading_normals(n, dpdu, dpdv, uv, np.full((64, 64), 0.3, np.float32),
                               bump_range_mm=5.0)
    assert np.allclose(out, n / np.linalg.norm(n, axis=1, keepdims=True), atol=1e-6)


@pytest.mark.parametrize("mirrored", [False, True])
def test11_ramp_in_u_tilts_normal_by_analytic_angle(mirrored):
    # h(u) = range * u (bump = u across the map).  On p = (a u, a v, 0) the displaced surface
    # is z = range * x / a, whose normal is (-range / a, 0, 1) / norm: tilted toward -dpdu by
    # atan(range / a).  A mirrored chart (v running along -y) must give the same normal.
    a, rng_mm = 2.0, 1.5
    res = 128
    bump = np.tile(np.linspace(0, 1, res, dtype=np.float32), (res, 1))
    uv, n, dpdu, dpdv = _plane_frame(50, a)
    if mirrored:
        dpdv = -dpdv
    out = bump_shading_normals(n, dpdu, dpdv, uv, bump, bump_range_mm=rng_mm)
    expected = np.array([-rng_mm / a, 0.0, 1.0]) / np.hypot(rng_mm / a, 1.0)
    assert np.allclose(out, expected, atol=1e-5)
    angle = np.degrees(np.arccos(out[:, 2]))
    assert np.allclose(angle, np.degrees(np.arctan(rng_mm / a)), atol=1e-3)


def test12_ramp_in_v_and_tangent_frames_on_mesh():
    # The tangent frames of a lat-long sphere point east (dp/du) and north (dp/dv), and a ramp
    # in v tilts the normals of equatorial texels toward -dp/dv (south).
    sphere = latlong_sphere(24, 48, R_MM)
    dpdu, dpdv = triangle_tangent_frames(sphere.vertices, sphere.faces, sphere.uv,
                                         sphere.uv_faces)
    cent = sphere.vertices[sphere.faces].mean(1)
    d = cent / np.linalg.norm(cent, axis=1, keepdims=True)
    east = np.cross([0, 0, 1.0], d)
    eq = np.abs(d[:, 2]) < 0.5
    east /= np.linalg.norm(east, axis=1, keepdims=True)
    assert (np.einsum("nd,nd->n", dpdu[eq], east[eq]) > 0.99 * np.linalg.norm(dpdu[eq], axis=1)).all()
    assert (dpdv[eq][:, 2] > 0).all()
    # |dp/du| = 2 pi R sin(theta) along the triangle's ring edge; the centroid's sin(theta)
    # differs from the ring's by up to cos(theta) * dtheta (dtheta = 7.5 deg) -> 5 % here.
    assert np.allclose(np.linalg.norm(dpdu[eq], axis=1),
                       2 * np.pi * R_MM * np.hypot(d[eq, 0], d[eq, 1]), rtol=0.05)
    res = 128
    bump = np.tile(np.linspace(1, 0, res, dtype=np.float32)[:, None], (1, res))  # bump = v
    tri = np.nonzero(eq)[0]
    bary = np.full((len(tri), 2), 1 / 3)
    maps = BakedMaps(albedo_srgb=np.zeros((res, res, 3), np.uint8), bump=bump,
                     bump_blur=bump, coverage=np.ones((res, res), bool), bump_min_mm=0.0,
                     bump_range_mm=10.0, blur_sigma_px=0.0)
    out = bump_shading_normals_at_hits(sphere, maps, tri, bary)
    # slope dh/ds = 10 mm / (pi R) along the meridian (|dp/dv| ~ pi R): tilt ~ atan(0.0318)
    tilt = np.einsum("nd,nd->n", out, d[tri])
    assert np.allclose(np.degrees(np.arccos(np.clip(tilt, -1, 1))),
                       np.degrees(np.arctan(10.0 / (np.pi * R_MM))), atol=0.3)
    assert (out[:, 2] < d[tri, 2]).all()      # tilted south, i.e. toward -dp/dv


def test13_direction_fixture_sanity():
    # The fixture's lat-long direction rule matches the mesh's vertices (guards the fixtures).
    sphere = latlong_sphere(6, 12, 1.0)
    t = sphere.uv_faces[:, 1]
    v = sphere.faces[:, 1]
    assert np.allclose(direction_of_uv(sphere.uv[t, 0], sphere.uv[t, 1]), sphere.vertices[v],
                       atol=1e-6)
