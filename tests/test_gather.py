"""Tests of subsurface/ (octree, profile table, gather, near field, shadow edges, radiance) and
cl/bssrdf_gather.cl: octree invariants, the flat-slab energy test, hierarchy against brute
force, zero irradiance, exitance -> radiance.

The profiles used here are built in the test from the closed-form Jensen et al. 2001 dipole
(independent of optics/layer_profiles.py), whose total diffuse reflectance Rd is known exactly.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from dermis.pipeline.artifacts import LayerProfile
from dermis.pipeline.config import BssrdfConfig
from dermis.pipeline.errors import DermisError
from dermis.optics.fresnel import diffuse_fresnel_external
from dermis.subsurface import gather as G
from dermis.subsurface import points as S
from dermis.subsurface.near_field import near_tables, split_profile
from dermis.subsurface.octree import build_octree
from dermis.subsurface.profile_table import BLUR_REACH
from dermis.subsurface.radiance import exitance_to_radiance
from dermis.subsurface.shadow_edges import (ShadowEdges, edge_sum, edge_sum_cl, near_bracket,
                                            sharp_visibility)

# The shipped settings: the scene schema's [bssrdf] defaults (the library has no others).
SHIPPED = BssrdfConfig()
EPS = SHIPPED.epsilon

# Jensen et al. 2001 measured skin1 (docs/science.md §3), 1/mm, eta 1.3.
SKIN1_SIGMA_A = np.array([0.032, 0.17, 0.48])
SKIN1_SIGMA_SP = np.array([0.74, 0.88, 1.01])
SKIN1_ETA = 1.3


def _fdr(eta):
    """Internal diffuse Fresnel reflectance, Egan-Hilgeman fit (docs/science.md §3)."""
    return -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta


def dipole_profile(sigma_a, sigma_sp, eta, *, r_max=60.0, h=0.02, cutoff_fraction=0.999):
    """Jensen 2001 dipole R(r) (1/mm^2) tabulated on [0, r_max], with exact Rd and cut-off."""
    sigma_a, sigma_sp = np.asarray(sigma_a, float), np.asarray(sigma_sp, float)
    st = sigma_a + sigma_sp
    alpha = sigma_sp / st
    tr = np.sqrt(3 * sigma_a * st)
    A = (1 + _fdr(eta)) / (1 - _fdr(eta))
    zr = 1 / st
    zv = zr * (1 + 4 * A / 3)
    r = np.arange(0.0, r_max + h / 2, h)
    dr = np.sqrt(r[:, None] ** 2 + zr**2)
    dv = np.sqrt(r[:, None] ** 2 + zv**2)
    R = alpha / (4 * np.pi) * (zr * (1 + tr * dr) * np.exp(-tr * dr) / dr**3
                               + zv * (1 + tr * dv) * np.exp(-tr * dv) / dv**3)
    s = np.sqrt(3 * (1 - alpha))
    Rd = alpha / 2 * (1 + np.exp(-4 / 3 * A * s)) * np.exp(-s)
    def cum(rr):
        """Energy inside radius rr: int 2 pi r z (1 + tr d) e^{-tr d} / d^3 dr = 2 pi z e^{-tr d} / d."""
        rr = np.asarray(rr, float)[:, None]
        a = np.sqrt(rr**2 + zr**2)
        b = np.sqrt(rr**2 + zv**2)
        return alpha / 2 * (np.exp(-tr * zr) - zr * np.exp(-tr * a) / a
                            + np.exp(-tr * zv) - zv * np.exp(-tr * b) / b)
    inside = cum(r)
    cut = np.array([r[np.searchsorted(inside[:, c], cutoff_fraction * Rd[c])] for c in range(3)])
    beyond = 1 - np.diag(cum(cut)) / Rd
    return LayerProfile(r_mm=r, R=R, T=np.zeros_like(R), Rd=Rd, Tt=np.zeros(3), cutoff_mm=cut,
                        energy_beyond_cutoff=beyond, info={"source": "test dipole"})


@pytest.fixture(scope="module")
def skin1():
    return dipole_profile(SKIN1_SIGMA_A, SKIN1_SIGMA_SP, SKIN1_ETA)


def plane_points(half, spacing, seed=3):
    """Blue-noise points on the square [-half, half]^2 at z = 0 (through subsurface/points.py)."""
    v = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return S.sample_points(v, f, spacing_mm=spacing, seed=seed)


def rel_rmse(h, b):
    return np.sqrt(((h - b) ** 2).mean(0) / (b**2).mean(0)).max()


# ------------------------------------------------------------------ the dipole reference itself
def test01_dipole_profile_integrates_to_rd(skin1):
    """The test's own dipole table integrates to its closed-form Rd (guards the reference)."""
    r, R = skin1.r_mm, skin1.R
    total = np.trapezoid(2 * np.pi * r[:, None] * R, r, axis=0)
    # the 60 mm table holds all but e^{-sigma_tr 60} ~ 1e-4 of red; trapezoid error < 1e-4
    np.testing.assert_allclose(total, skin1.Rd, rtol=3e-3)
    # docs/science.md §3: Jensen 2001 skin1 Rd ~ (0.44, 0.22, 0.13)
    np.testing.assert_allclose(skin1.Rd, [0.44, 0.22, 0.13], atol=0.01)


# ------------------------------------------------------------------ octree invariants
@pytest.mark.parametrize("leaf_size", [1, 8, 13])
def test02_octree_invariants(rng, leaf_size):
    n = 5000
    p = rng.normal(size=(n, 3)) * [30, 20, 5]
    p[:50] = p[0]  # a cluster of coincident points (deeper than any split can separate)
    a = rng.uniform(0.5, 2.0, n)
    e = rng.uniform(0.0, 1.0, (n, 3))
    e[100:300] = 0.0
    t = build_octree(p, a, e, leaf_size=leaf_size)
    k = t.n_nodes
    start, skip = t.start.astype(int), t.skip.astype(int)
    end = start[skip[:k]]
    start = start[:k]
    # points are a permutation of the input
    np.testing.assert_array_equal(np.sort(t.order), np.arange(n))
    np.testing.assert_allclose(t.positions, p[t.order].astype(np.float32))
    # every point in exactly one leaf
    cover = np.zeros(n, int)
    for i in np.flatnonzero(t.is_leaf):
        cover[start[i]:end[i]] += 1
    np.testing.assert_array_equal(cover, 1)
    # leaves hold <= leaf_size points, except unsplittable coincident points
    sizes = (end - start)[t.is_leaf]
    big = np.flatnonzero(t.is_leaf)[sizes > leaf_size]
    for i in big:
        assert np.ptp(t.positions[start[i]:end[i]], axis=0).max() == 0
    # a leaf's skip is i + 1; an internal node's first child is i + 1 with the same start
    internal = np.flatnonzero(~t.is_leaf)
    assert (skip[internal] > internal + 1).all()
    assert (start[internal + 1] == start[internal]).all()
    # area and E A sums, and each internal node equals the sum over its children
    pa = t.areas.astype(float)
    np.testing.assert_allclose(t.area[0], a.sum(), rtol=1e-6)
    for i in internal[:200]:
        c, child_area, child_ea = i + 1, 0.0, 0.0
        while c < skip[i]:
            child_area += t.area[c]
            child_ea = child_ea + t.ea_sum[c]
            c = skip[c]
        assert c == skip[i]
        np.testing.assert_allclose(child_area, t.area[i], rtol=1e-9)
        np.testing.assert_allclose(child_ea, t.ea_sum[i], rtol=1e-9)
    for i in range(k):
        seg = t.positions[start[i]:end[i]]
        np.testing.assert_allclose(t.area[i], pa[start[i]:end[i]].sum(), rtol=1e-5)
        assert (seg >= t.bbox_min[i]).all() and (seg <= t.bbox_max[i]).all()
        assert (np.linalg.norm(seg - t.position[i], axis=1) <= t.radius[i]).all()
        # the irradiance-weighted mean lies in the box
        assert (t.position[i] >= t.bbox_min[i] - 1e-4).all()
        assert (t.position[i] <= t.bbox_max[i] + 1e-4).all()


def test03_octree_rejects_bad_input():
    p = np.zeros((4, 3))
    with pytest.raises(DermisError, match="irradiance contains NaN"):
        build_octree(p, np.ones(4), np.full((4, 3), np.nan))
    with pytest.raises(DermisError, match="must be .4,. and .4, 3."):
        build_octree(p, np.ones(3), np.ones((4, 3)))
    with pytest.raises(DermisError, match="leaf_size = 0"):
        build_octree(p, np.ones(4), np.ones((4, 3)), leaf_size=0)


# ------------------------------------------------------------------ flat slab (energy)
# Tolerance: 1 % per query, the gather's accuracy target.  Derivation: with partition-of-unity
# areas the gathered exitance on a flat slab is M / (Rd E) - 1 = int R (PoU - 1) / Rd, the
# profile-weighted mean of the partition-of-unity deviation (<= its max, 1.05 % measured over random
# probes, tests/test_samples.py::test07), plus the clustering error (small at SLAB_EPS,
# below) and float32 sums (~1e-5).  Measured on sample_points() points at the default density,
# 2000 queries x 2 seeds: max 0.53 % (skin1 blue), 0.27 % (skin2), 0.10 % (two_layer);
# RMS <= 0.09 %.  The raw profile on the same points: max 25-48 %.
SLAB_RTOL = 0.01
# The flat-slab tests check the quadrature (areas, reconstruction blur, energy
# normalisation), so they gather at an epsilon whose clustering error is small beside the
# bound: 0.2 (test04b's whole error measured max 0.19 % there).  At the shipped epsilon
# (0.5, chosen for the RMSE that test06 guards) the clustering error on these slabs is
# larger: test04b measured max 0.82 % (skin1), 1.17 % (skin2 blue), 0.86 % (two_layer),
# RMS <= 0.72 %.
SLAB_EPS = 0.2


def hex_plane(half, spacing):
    """A hexagonal lattice of points with equal areas on [-half, half]^2 at z = 0."""
    ny = int(2 * half / (spacing * math.sqrt(3) / 2))
    nx = int(2 * half / spacing)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    p = np.stack([-half + (i + 0.5 * (j % 2)) * spacing,
                  -half + j * spacing * math.sqrt(3) / 2, 0.0 * i], -1).reshape(-1, 3)
    return p, np.full(len(p), spacing * spacing * math.sqrt(3) / 2)


@pytest.fixture(scope="module")
def slab(skin1):
    spacing = 1.19   # skin1's one point per pi mfp^2 (the density rule before its cap)
    half = 2 * float(skin1.cutoff_mm.max()) + 10.0
    sp = plane_points(half, spacing)
    return sp, half


def test04_flat_slab_energy(cl_env, skin1, rng):
    """Uniform normal irradiance on a large plane: M / E = Rd within 1 % away from the edges."""
    half = float(skin1.cutoff_mm.max()) + 12.0
    p, a = hex_plane(half, 0.5)
    E = 2.5
    t = build_octree(p, a, np.full((len(a), 3), E))
    inner = half - float(skin1.cutoff_mm.max()) - 1.0
    q = np.zeros((300, 3))
    q[:, :2] = rng.uniform(-inner, inner, (300, 2))
    m, stats = G.gather(t, skin1, q, epsilon=SLAB_EPS, env=cl_env)
    ratio = m / E / skin1.Rd
    assert np.abs(ratio - 1).max() < SLAB_RTOL, (ratio.min(0), ratio.max(0))
    # the brute-force sum too (so the 1 % is the quadrature, not the clustering)
    mb, _ = G.gather(t, skin1, q[:40], epsilon=None, env=cl_env, brute_force=True)
    assert np.abs(mb / E / skin1.Rd - 1).max() < SLAB_RTOL
    # and near the edge the energy mode loses light (part of the plane is missing)
    edge = np.array([[half - 0.3, 0.0, 0.0]])
    me, _ = G.gather(t, skin1, edge, epsilon=EPS, env=cl_env)
    assert (me[0] / E / skin1.Rd < 0.7).all()


@pytest.fixture(scope="module")
def preset_profiles():
    from dermis.optics.layer_profiles import build_profiles
    from dermis.optics.layers import PRESETS
    return {k: (PRESETS[k], build_profiles(PRESETS[k])) for k in ("skin1", "skin2", "two_layer")}


@pytest.mark.parametrize("preset", ["skin1", "skin2", "two_layer"])
def test04b_flat_slab_sample_points(cl_env, preset_profiles, preset):
    """The real flat slab: sample_points()'s random blue-noise points at the default density on
    a large plane, uniform normal irradiance, the presets' layer files: M / E = Rd within
    1 % at every query farther than the kernel's reach from the edges."""
    stack, prof = preset_profiles[preset]
    spacing = S.spacing_from_mfp(stack, SHIPPED.point_density)
    sigma = S.KERNEL_SIGMA_FACTOR * spacing
    reach = float(prof.cutoff_mm.max()) + BLUR_REACH * sigma
    half = reach + 2 * spacing + S.POU_RADIUS * sigma  # interior + the frozen rim band
    v = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0.0]])
    sp = S.sample_points(v, np.array([[0, 1, 2], [0, 2, 3]]), spacing_mm=spacing, seed=8)
    E = 1.7
    t = build_octree(sp.positions, sp.areas, np.full((len(sp.areas), 3), E),
                       kernel_sigma_mm=sp.info["kernel_sigma_mm"])
    inner = half - reach - 1.0
    q = np.zeros((600, 3))
    q[:, :2] = np.random.default_rng(9).uniform(-inner, inner, (600, 2))
    m, st = G.gather(t, prof, q, epsilon=SLAB_EPS, env=cl_env)
    err = m / E / prof.Rd - 1
    assert st["kernel_sigma_mm"] == pytest.approx(sigma)
    assert np.abs(err).max() < SLAB_RTOL, (np.abs(err).max(0), np.sqrt((err**2).mean(0)))
    mb, _ = G.gather(t, prof, q[:60], epsilon=None, env=cl_env, brute_force=True)
    assert np.abs(mb / E / prof.Rd - 1).max() < SLAB_RTOL
    if preset == "skin1":
        # the test can fail: the raw profile (no reconstruction blur) on the same points
        raw, _ = G.gather(t, prof, q, epsilon=SLAB_EPS, env=cl_env,
                          tuning=G.GatherTuning(kernel_sigma_mm=0.0))
        assert np.abs(raw / E / prof.Rd - 1).max() > 5 * SLAB_RTOL


# Sphere: the area of a sphere within chord distance d of a point is pi d^2 (Archimedes'
# hat-box theorem) for d <= 2 R, so a radial kernel of reach <= 2 R in chord distance
# integrates over the sphere exactly as over a plane, and uniform irradiance must give
# M = Rd E everywhere (no edges) with the flat slab's bound; the facets of the resolution-
# 100 mesh sag by R (1 - cos(pi / 100)) = 0.01 mm, far below sigma.  Measured max 0.5 %.
def test04c_sphere_uniform_irradiance(cl_env, preset_profiles):
    import open3d as o3d
    stack, prof = preset_profiles["skin1"]
    radius = 20.0
    spacing = S.spacing_from_mfp(stack, SHIPPED.point_density)
    assert float(prof.cutoff_mm.max()) + BLUR_REACH * S.KERNEL_SIGMA_FACTOR * spacing < 2 * radius
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=100)
    sp = S.sample_points(np.asarray(mesh.vertices), np.asarray(mesh.triangles), spacing_mm=spacing, seed=3)
    t = build_octree(sp.positions, sp.areas, np.ones((len(sp.areas), 3)),
                       kernel_sigma_mm=sp.info["kernel_sigma_mm"])
    q = np.random.default_rng(4).normal(size=(600, 3))
    q *= radius / np.linalg.norm(q, axis=1, keepdims=True)
    m, _ = G.gather(t, prof, q, epsilon=SLAB_EPS, env=cl_env)
    err = m / prof.Rd - 1
    assert np.abs(err).max() < SLAB_RTOL, (np.abs(err).max(0), np.sqrt((err**2).mean(0)))


def test05_flat_slab_thesis_normalisation(cl_env, skin1, slab):
    """The thesis normalisation gives Rd E everywhere on a uniformly lit plane, edges included."""
    sp, half = slab
    E = 1.0
    t = build_octree(sp.positions, sp.areas, np.full((len(sp.areas), 3), E))
    q = np.array([[0.0, 0.0, 0.0], [half - 0.5, 0.0, 0.0], [half - 0.5, half - 0.5, 0.0]])
    m, _ = G.gather(t, skin1, q, epsilon=EPS, normalisation="thesis", env=cl_env)
    # float32 ratio of two sums of the same terms: exact to ~1e-5
    np.testing.assert_allclose(m / skin1.Rd, 1.0, rtol=1e-4)


# ------------------------------------------------------------------ hierarchy vs brute force
# Accuracy of the SHIPPED epsilon (BssrdfConfig().epsilon, 0.5) on pixel-like queries.
# Tolerance derivation: bench/results/gather.json measured on the LPS head (250k points, 640k
# camera queries, skin2, the default tile walk, leaf 16) a relative RMSE against brute force
# of 0.376 % at eps 0.5 (sweep neighbours: 0.273 % at 0.4, 0.550 % at 0.6).  The bound is that
# measurement plus one third for the spread between scenes, 0.376 % x 4/3 = 0.50 % (the
# gather's 0.5 % budget); it lies below the bench's next coarser sweep point (0.6: 0.55 %).
# This scene reproduces the bench's regime, self-contained: the walk and tiling the pipeline
# runs, on Morton-adjacent queries on a 0.5 mm grid (camera pixels), smooth lighting and a
# hard shadow edge (x20).  Measured here: 0.32 % (0.40 % on a 0.25 mm grid; 0.23 % at eps
# 0.4, 0.41 % at 0.6), so the bound sits 1.56x above this scene's value.
SHIPPED_EPS_RMSE = 0.376e-2 * 4 / 3


@pytest.fixture(scope="module")
def lit_bump(skin1):
    """A 120 mm bumpy sheet lit by a directional light with a sharp shadow edge."""
    sp = plane_points(60.0, 0.8, seed=5)
    p = sp.positions.astype(float)
    p[:, 2] = 4.0 * np.sin(p[:, 0] / 7.0) * np.cos(p[:, 1] / 9.0)
    e = np.clip(0.6 + 0.4 * np.sin(p[:, 0] / 5.0), 0, None)[:, None] * [1.0, 0.8, 0.6]
    e[p[:, 1] > 10.0] *= 0.05  # a shadow boundary
    rng = np.random.default_rng(11)
    q = p[rng.choice(len(p), 600, replace=False)] + rng.normal(scale=0.2, size=(600, 3))
    return build_octree(p, sp.areas, e), q


@pytest.fixture(scope="module")
def pixel_queries():
    """Dense Morton-adjacent queries on the sheet: a 0.5 mm grid (like camera pixels) across
    the shadow edge at y = 10 mm."""
    g = np.arange(-20.0, 20.0, 0.5)
    X, Y = (a.ravel() for a in np.meshgrid(g, g))
    return np.stack([X, Y, 4.0 * np.sin(X / 7.0) * np.cos(Y / 9.0)], axis=1)


def test06_shipped_epsilon_matches_brute_force(cl_env, skin1, lit_bump, pixel_queries):
    """The shipped settings (epsilon and leaf size from the scene schema, default tuning) on
    pixel-like queries: relative RMSE vs brute force within the bench-derived bound."""
    t, _ = lit_bump
    assert t.leaf_size == SHIPPED.leaf_size
    q = pixel_queries
    b, _ = G.gather(t, skin1, q, epsilon=None, env=cl_env, brute_force=True)
    h, _ = G.gather(t, skin1, q, epsilon=EPS, env=cl_env)
    assert rel_rmse(h, b) < SHIPPED_EPS_RMSE, rel_rmse(h, b)


def test06b_error_falls_with_epsilon(cl_env, skin1, lit_bump, pixel_queries):
    """Convergence: the error against brute force shrinks as epsilon -> 0, from coarser than
    the shipped value down to the far-field expansion's own floor; with every source exact
    the walk converges to brute force."""
    t, q = lit_bump
    b, _ = G.gather(t, skin1, q, epsilon=None, env=cl_env, brute_force=True)
    errs = []
    for eps in sorted({0.8, EPS, 0.3, 0.2, 0.03, 0.005}, reverse=True):
        h, st = G.gather(t, skin1, q, epsilon=eps, env=cl_env)
        errs.append(rel_rmse(h, b))
    # the error shrinks as epsilon -> 0 (allow float32 noise at the small end)
    assert all(e2 <= e1 * 1.05 + 1e-6 for e1, e2 in zip(errs, errs[1:])), errs
    # ... down to the far-field expansion's own error, which does not depend on epsilon:
    # measured 7.3e-5 here with the default radii (1.5 mm, 3 x tile radius); the bound is
    # 1/25 of the 0.5 % budget.  With every source exact the walk converges to brute force.
    assert errs[-1] < 2e-4, errs
    hx, _ = G.gather(t, skin1, q, epsilon=0.005, env=cl_env, tuning=G.GatherTuning(expand_mm=1e30))
    assert rel_rmse(hx, b) < 1e-3 * errs[0] + 2e-6, (rel_rmse(hx, b), errs)
    # thesis mode too: error falls with epsilon, and stays within the 0.5 % budget at the
    # shipped value on these queries (measured 0.084 %, 0.031 % at 0.2)
    bt, _ = G.gather(t, skin1, q, epsilon=None, env=cl_env, brute_force=True,
                     normalisation="thesis")
    et = [rel_rmse(G.gather(t, skin1, q, epsilon=eps, env=cl_env, normalisation="thesis")[0], bt)
          for eps in (EPS, 0.2)]
    assert et[1] <= et[0] * 1.05 + 1e-6 and et[0] < 0.005, et
    # on the pixel-like queries too: 0.4 x the shipped value well below it (measured
    # 0.032 % at 0.1 against 0.11 % at 0.25; the error falls about linearly with epsilon)
    qd = pixel_queries
    bd, _ = G.gather(t, skin1, qd, epsilon=None, env=cl_env, brute_force=True)
    e_ship = rel_rmse(G.gather(t, skin1, qd, epsilon=EPS, env=cl_env)[0], bd)
    e_fine = rel_rmse(G.gather(t, skin1, qd, epsilon=0.4 * EPS, env=cl_env)[0], bd)
    assert e_fine < 0.5 * e_ship, (e_fine, e_ship)


def test07_query_order_does_not_change_results(cl_env, skin1, lit_bump):
    t, q = lit_bump
    # one query per work-item: the walk is per query, so the order changes nothing
    a, _ = G.gather(t, skin1, q, epsilon=EPS, env=cl_env,
                    tuning=G.GatherTuning(sort_queries=True, tile=1))
    b, _ = G.gather(t, skin1, q, epsilon=EPS, env=cl_env,
                    tuning=G.GatherTuning(sort_queries=False, local_size=None, tile=1))
    np.testing.assert_array_equal(a, b)
    # the tile walk always forms its tiles along the Morton curve (sort_queries applies to
    # the per-query walk), so the input order changes nothing either
    a, _ = G.gather(t, skin1, q, epsilon=EPS, env=cl_env)
    b, _ = G.gather(t, skin1, q[::-1], epsilon=EPS, env=cl_env,
                    tuning=G.GatherTuning(sort_queries=False))
    np.testing.assert_array_equal(a, b[::-1])


def test07b_tile_walk_is_conservative(cl_env, skin1, lit_bump):
    """The tile walk with every source evaluated exactly never clusters more coarsely than
    the per-query walk, so its error at one epsilon is no larger; the far-field Taylor
    expansion adds little to it."""
    t, q = lit_bump
    b, _ = G.gather(t, skin1, q, epsilon=None, env=cl_env, brute_force=True)
    exact = G.GatherTuning(expand_mm=1e30)
    for eps in (0.8, 0.3):
        e1 = rel_rmse(G.gather(t, skin1, q, epsilon=eps, env=cl_env,
                               tuning=G.GatherTuning(tile=1))[0], b)
        ex = rel_rmse(G.gather(t, skin1, q, epsilon=eps, env=cl_env, tuning=exact)[0], b)
        et = rel_rmse(G.gather(t, skin1, q, epsilon=eps, env=cl_env)[0], b)
        assert ex <= e1 * 1.05 + 1e-6, (eps, ex, e1)
        # the expansion: measured < 1.3x the exact tile walk's error here
        assert et <= 2 * ex + 2e-4, (eps, et, ex)
    # every tile size, with and without the expansion, agrees with brute force at a small
    # epsilon
    for kw in ({"tile": 4}, {"tile": 8}, {"tile": 4, "expand_mm": 1e30},
               {"tile": 16, "expand_mm": 1e30}):
        h, _ = G.gather(t, skin1, q, epsilon=0.05, env=cl_env, tuning=G.GatherTuning(**kw))
        assert rel_rmse(h, b) < 1e-3, kw


def test07c_subtile_expansion_on_dense_queries(cl_env, skin1, lit_bump, pixel_queries):
    """Dense Morton-adjacent queries (a 0.5 mm grid, like camera pixels) exercise the
    sub-tile expansion of the 16-query tiles: its results differ from the exact-near-field
    walk (the path is taken) but stay close to brute force."""
    t, _ = lit_bump
    q = pixel_queries
    b, _ = G.gather(t, skin1, q, epsilon=None, env=cl_env, brute_force=True)
    ex = rel_rmse(G.gather(t, skin1, q, epsilon=0.3, env=cl_env,
                           tuning=G.GatherTuning(expand_mm=1e30))[0], b)
    es = rel_rmse(G.gather(t, skin1, q, epsilon=0.3, env=cl_env)[0], b)
    hs, _ = G.gather(t, skin1, q, epsilon=0.05, env=cl_env)
    hn, _ = G.gather(t, skin1, q, epsilon=0.05, env=cl_env, tuning=G.GatherTuning(subtiles=False))
    # measured: 0.058 % exact, 0.139 % with the expansions (2.4x); sub-tiles vs not 7e-5
    assert es <= 3 * ex + 2e-4, (es, ex)
    assert 1e-6 < rel_rmse(hs, hn) < 3e-4
    # measured 1.6e-4 at epsilon 0.05
    assert rel_rmse(hs, b) < 3e-4
    # a progress callback splits the launch into aligned chunks: same results, every chunk
    done = []
    hp, _ = G.gather(t, skin1, q, epsilon=0.05, env=cl_env, progress=done.append)
    np.testing.assert_array_equal(hp, hs)
    assert done[-1] == 1.0 and len(done) > 1


# ------------------------------------------------------------------ zero irradiance, errors
def test08_zero_irradiance_is_black_not_nan(cl_env, skin1):
    sp = plane_points(20.0, 1.0)
    t = build_octree(sp.positions, sp.areas, np.zeros((len(sp.areas), 3)))
    q = np.array([[0.0, 0, 0], [500.0, 0, 0]])  # the second has nothing in range
    for norm in ("energy", "thesis"):
        for brute in (False, True):
            m, _ = G.gather(t, skin1, q, epsilon=EPS, normalisation=norm, brute_force=brute,
                            env=cl_env)
            assert np.isfinite(m).all() and (m == 0).all()
    L = exitance_to_radiance(m, np.array([1.0, -0.2]), 1.3, albedo=np.ones((2, 3)),
                               rd=skin1.Rd)
    assert np.isfinite(L).all() and (L == 0).all()


def test09_gather_rejects_bad_options(cl_env, skin1, lit_bump):
    t, q = lit_bump
    with pytest.raises(DermisError, match="normalisation = 'x'"):
        G.gather(t, skin1, q, epsilon=EPS, normalisation="x", env=cl_env)
    with pytest.raises(DermisError, match="epsilon = 0"):
        G.gather(t, skin1, q, epsilon=0, env=cl_env)
    with pytest.raises(DermisError, match="query_positions contains NaN"):
        G.gather(t, skin1, np.full((2, 3), np.nan), epsilon=EPS, env=cl_env)
    with pytest.raises(DermisError, match="epsilon = None"):
        G.gather(t, skin1, q, epsilon=None, env=cl_env)
    # the tile walk exists for the OpenCL vector widths only (and 1: one query per item)
    for tile in (0, 2, 5, 32):
        with pytest.raises(DermisError, match=f"tile = {tile}: must be one of"):
            G.GatherTuning(tile=tile)


# ------------------------------------------------------------------ exitance -> radiance
def test10_radiance_integrates_back_to_exitance():
    """int L cos dw over the hemisphere = M (fresnel mode), by quadrature in the test."""
    n = 20000
    mu = (np.arange(n) + 0.5) / n
    M = np.array([[0.7, 0.4, 0.2]])
    for eta in (1.0, 1.3, 1.4):
        L = exitance_to_radiance(np.repeat(M, n, 0), mu, eta).astype(float)
        back = (L * 2 * np.pi * mu[:, None]).sum(0) / n
        np.testing.assert_allclose(back, M[0], rtol=1e-4)
    # external diffuse Fresnel reflectance and the internal fit are tied by
    # 1 - Fdr_ext = eta^2 (1 - Fdr_int) (reciprocity); the fit is good to ~1 %
    eta = 1.3
    np.testing.assert_allclose(1 - diffuse_fresnel_external(eta), eta**2 * (1 - _fdr(eta)),
                               rtol=0.015)


def test11_albedo_replace_mode(skin1):
    """'replace': a slab reflecting Rd E with texture albedo a gives radiosity a E."""
    E, a = 2.0, np.array([[0.5, 0.3, 0.2]])
    M = (skin1.Rd * E)[None]
    L = exitance_to_radiance(M, np.array([1.0]), 1.0, albedo=a, rd=skin1.Rd, mode="lambert")
    np.testing.assert_allclose(L[0] * np.pi, a[0] * E, rtol=1e-6)
    with pytest.raises(DermisError, match="needs the profile's Rd"):
        exitance_to_radiance(M, np.array([1.0]), 1.0, albedo=a)


# ------------------------------------------------------------------ the real layer file
def test12_flat_slab_with_profiles_stage(cl_env, rng):
    """The flat-slab test with the skin1 layer file of optics/layer_profiles.py."""
    from dermis.optics.layer_profiles import build_profiles
    from dermis.optics.layers import PRESETS
    prof = build_profiles(PRESETS["skin1"])
    half = float(prof.cutoff_mm.max()) + 12.0
    p, a = hex_plane(half, 0.5)
    t = build_octree(p, a, np.ones((len(a), 3)))
    inner = half - float(prof.cutoff_mm.max()) - 1.0
    q = np.zeros((200, 3))
    q[:, :2] = rng.uniform(-inner, inner, (200, 2))
    m, _ = G.gather(t, prof, q, epsilon=SLAB_EPS, env=cl_env)
    assert np.abs(m / prof.Rd - 1).max() < SLAB_RTOL


# ------------------------------------------------------------------ near field pieces
def _edges_on_a_plane(rng, n=400):
    """A wavy shadow edge on the plane z = 0 (points along y = 3 sin(x / 4)), as segments."""
    xs = np.sort(rng.uniform(-30, 30, n))
    o = np.stack([xs, 3 * np.sin(xs / 4), np.zeros(n)], 1)
    t = np.stack([np.ones(n), 0.75 * np.cos(xs / 4), np.zeros(n)], 1)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    nz = np.tile([0.0, 0.0, 1.0], (n, 1))
    out = np.cross(nz, t)
    gap = np.diff(xs)
    lo = -np.r_[gap[0], gap] / 2 * np.linalg.norm(t[:, :2] / t[:, :1], axis=1)
    hi = np.r_[gap, gap[-1]] / 2 * np.linalg.norm(t[:, :2] / t[:, :1], axis=1)
    return ShadowEdges(o, t, out, nz, lo, hi, np.zeros((1, 3)), {"precision_mm": 1e-4})


def test13_edge_sums_device_matches_numpy(cl_env, rng):
    """The device edge sums (grid, midpoint rule for short far segments) agree with the
    numpy reference (kd-tree, exact table) to 2e-3 of the near part's energy (measured 2e-4)."""
    from dermis.optics.layers import PRESETS
    from dermis.optics.layer_profiles import build_profiles
    prof = build_profiles(PRESETS["skin2"])
    table = near_tables(split_profile(prof, 1.25))
    edges = _edges_on_a_plane(rng)
    q = np.zeros((20000, 3))
    q[:, :2] = rng.uniform(-25, 25, (20000, 2))
    q[:50, 1] = 3 * np.sin(q[:50, 0] / 4) + rng.normal(scale=1e-4, size=50)   # on the edge
    nrm = np.tile([0.0, 0.0, 1.0], (len(q), 1))
    a = edge_sum(q, nrm, edges, table)
    b = edge_sum_cl(q, nrm, edges, table, cl_env)
    # compare what the near field uses: the bracket with the side from the geometry (on the
    # edge float32 rounding may put a point on either side of a segment: |s| is continuous)
    lit = q[:, 1] < 3 * np.sin(q[:, 0] / 4)          # outward = z x tangent points to +y
    near_a, ok_a = near_bracket(lit, a, table.rd_near)
    near_b, ok_b = near_bracket(lit, b, table.rd_near)
    assert ok_a.all() and ok_b.all()
    assert np.abs(near_a - near_b).max() < 2e-3 * table.rd_near.max(), np.abs(near_a - near_b).max()
    assert np.abs(a).max() > 0.3 * table.rd_near.max()      # the edge is in range
    # off the edge the geometry's side and the sums' agree: Rd_near V - s is the bracket
    np.testing.assert_allclose((table.rd_near * lit[:, None] - a)[50:], near_a[50:], atol=1e-6)


def test14_shared_visibility_of_point_and_directional_lights():
    """sharp_visibility reads each hit's unoccluded samples: a hit sees a light when one
    of its samples points at it (directional: its direction; point: towards it)."""
    from types import SimpleNamespace
    from dermis.pipeline.config import LightConfig
    sun = LightConfig(name="s", type="directional", direction=(0.0, 0.0, 2.0))
    lamp = LightConfig(name="p", type="point", position=(0.0, 100.0, 0.0))
    disc = LightConfig(name="d", type="disc", position=(0.0, 0.0, 50.0))
    x = np.array([[0.0, 0, 0], [10.0, 0, 0], [0.0, 0, 5.0]])
    to_lamp = lambda p: (lamp.position - p) / np.linalg.norm(lamp.position - p)  # noqa: E731
    # hit 0 sees both, hit 1 only the lamp (plus a disc sample), hit 2 nothing
    dirs = np.array([[0, 0, 1.0], to_lamp(x[0]), to_lamp(x[1]), [0.3, 0.3, 0.9]])
    samples = SimpleNamespace(counts=np.array([2, 2, 0]), directions=dirs.astype(np.float32))
    v = sharp_visibility(samples, np.array([0, 1, 2]), x, [sun, disc, lamp])
    np.testing.assert_array_equal(v, [[True, True], [False, True], [False, False]])
    v = sharp_visibility(samples, np.array([1]), x[1:2], [lamp])
    np.testing.assert_array_equal(v, [[True]])
    # no point or directional light (a disc or the environment alone): no columns, no work
    v = sharp_visibility(samples, np.array([0, 1, 2]), x, [disc])
    assert v.shape == (3, 0) and v.dtype == bool
