"""Hanrahan-Krueger two-layer BRDF (cl/brdf_hk93.cl, cl/optics.h, docs/science.md §2)."""
from __future__ import annotations

import math
import re
from types import SimpleNamespace

import numpy as np
import pytest

from brdf_testutil import hemisphere, mc_albedo, sample_pairs, with_cos
from dermis.pipeline.cl import CL_DIR
from dermis.pipeline.errors import ConfigError
from dermis.optics.layers import PRESETS, Layer
from dermis.optics.fresnel import dipole_Rd
from brdf_reference import hk93_f_np
from dermis.models import hk93
from dermis.models.evaluate import evaluate
from dermis.models.hk93 import (HK93_NPARAMS, HK93Params, hk93_params_from_layers,
                               hk93_single_scattering_albedo)

# float32 kernel vs float64 reference: ~40 float32 operations incl. exp/expm1/sqrt (<= 4 ulp
# each in OpenCL's full profile); errors add in quadrature-ish, 64 ulp is a safe bound.
# ATOL: f values below 1e-9 /sr (Fresnel-killed grazing) are compared absolutely.
RTOL_F32 = 64 * 2.0 ** -24
ATOL_F32 = 1e-9
RTOL_RECIPROCITY = 8 * 2.0 ** -24      # same arithmetic with operands swapped
N_MC = 1 << 16
N_SIGMA = 5.0
THETA_GRID = [0, 15, 30, 45, 60, 70, 80, 85, 87, 89]

SKIN = dict(eta=1.4, sigma_a=(0.255, 0.443, 0.897), sigma_s_prime=(4.78, 6.08, 9.20), g=0.8)
# a second, deliberately asymmetric stack: different indices, backward-scattering top layer
ODD = [dict(thickness_mm=0.1, eta=1.5, sigma_a=(0.1, 0.5, 2.0), sigma_s_prime=(3.0, 2.0, 1.0),
            g=-0.3),
       dict(thickness_mm=2.0, eta=1.2, sigma_a=(0.05, 0.2, 0.4), sigma_s_prime=(1.0, 1.5, 2.0),
            g=0.9)]


def _layer(**kw):
    d = dict(thickness_mm=math.inf, **SKIN)
    d.update(kw)
    return d


def _f(params):
    return lambda wo, wi: evaluate(hk93.MODEL, wo, wi, params)


@pytest.mark.parametrize("layers, ms, match", [
    ([_layer(eta=0.9)], None, r"hk93\.layers\[0\]\.eta = 0\.9: must be in \[1, 3\]"),
    ([_layer(g=1.0)], None, r"hk93\.layers\[0\]\.g = 1\.0: must satisfy -1 < g < 1"),
    ([_layer(sigma_a=(0.1, -0.2, 0.3))], None,
     r"hk93\.layers\[0\]\.sigma_a = \[0\.1, -0\.2, 0\.3\] \(1/mm\): must be >= 0"),
    ([_layer(sigma_a=(0, 0, 0), sigma_s_prime=(1, 0, 1))], None,
     r"sigma_a \+ sigma_s_prime = .*must be > 0 per channel"),
    ([_layer(sigma_s_prime=(1, 2))], None, r"sigma_s_prime = .*must have shape \(3,\)"),
    ([_layer(thickness_mm=-1.0)], None, r"thickness_mm = -1\.0 \(mm\): must be >= 0"),
    ([_layer(), _layer()], None, r"layers\[0\]\.thickness_mm = inf.*inf only for the last"),
    ([_layer(thickness_mm=1.0)] * 2 + [_layer()], None, r"3 layers .*takes 1 or 2"),
    ([], None, r"0 layers .*takes 1 or 2"),
    ([{"eta": 1.4}], None, r"hk93\.layers\[0\]: missing key 'thickness_mm'"),
    ([SimpleNamespace(thickness_mm=1.0, eta=1.4, sigma_a=(1, 1, 1), g=0.0)], None,
     r"SimpleNamespace has no attribute 'sigma_s_prime'"),
    ([_layer()], (0.5, 1.0, 0.5), r"multiple_scattering = \[0\.5, 1\.0, 0\.5\]: must be in \[0, 1\)"),
    ([_layer()], (0.5, -0.1, 0.5), r"multiple_scattering = .*must be in \[0, 1\)"),
    # white, index-matched, isotropic: single scattering alone reaches ~0.5 at grazing
    ([_layer(eta=1.0, g=0.0, sigma_a=(0, 0, 0))], (0.6, 0.6, 0.6),
     r"multiple_scattering = .*must be <= 1 - max single-scattering albedo"),
])
def test01_params_rejected(layers, ms, match):
    with pytest.raises(ConfigError, match=match):
        HK93Params(layers, ms)


def test02_pack_layout_and_duck_typing():
    src = (CL_DIR / "brdf_hk93.cl").read_text()
    assert int(re.search(r"#define HK93_NPARAMS (\d+)", src).group(1)) == HK93_NPARAMS
    stack = PRESETS["two_layer"]
    as_dicts = [lay.to_dict() | {"thickness_mm": lay.thickness_mm} for lay in stack.layers]
    packs = [hk93_params_from_layers(x) for x in
             (stack, list(stack.layers), as_dicts,
              [SimpleNamespace(**vars(lay)) for lay in stack.layers])]
    for p in packs[1:]:
        np.testing.assert_array_equal(p, packs[0])
    p = packs[0]
    assert p.shape == (HK93_NPARAMS,) and p.dtype == np.float32
    assert np.all(p[13:16] == np.float32(1e30)), "semi-infinite dermis: tau clamped"
    sigma_s = np.array(stack.layers[0].sigma_s_prime) / 0.2
    np.testing.assert_allclose(p[7:10], (np.array(stack.layers[0].sigma_a) + sigma_s) * 0.25,
                               rtol=1e-6)
    single = hk93_params_from_layers([stack.layers[1]])
    assert np.all(single[10:16] == 0) and single[1] == single[0]
    # zero-thickness layers are the identity and are dropped (pipeline.layers allows them)
    z = hk93_params_from_layers([Layer(0.0, 1.4, (1, 1, 1), (1, 1, 1), 0.0), stack.layers[1]])
    np.testing.assert_array_equal(z, single)


@pytest.mark.parametrize("layers", ["default", "odd", "single_finite", "thin"])
def test03_matches_reference(cl_env, rng, layers):
    """Single scattering alone (rho_ms = 0: the constant would hide its grazing errors).
    "thin" (tau ~ 0.02) puts tau (1/mu_i + 1/mu_o) on both sides of the kernel's switch from
    the Taylor series to 1 - exp(-x) at x = 0.1."""
    zero = (0.0, 0.0, 0.0)
    params = {"default": HK93Params(multiple_scattering=zero),
              "odd": HK93Params(ODD, zero),
              "single_finite": HK93Params([ODD[0]], zero),
              "thin": HK93Params([dict(ODD[0], thickness_mm=0.002)], zero)}[layers]
    wo, wi = sample_pairs(rng)
    got = evaluate(hk93.MODEL, wo, wi, params, env=cl_env)
    want = hk93_f_np(wo, wi, params)
    np.testing.assert_allclose(got, want, rtol=RTOL_F32, atol=ATOL_F32)


def test04_closed_form_chandrasekhar(cl_env, rng):
    """Index-matched, non-absorbing, isotropic, semi-infinite: f = 1/(4 pi (mu_i + mu_o))
    (Chandrasekhar's first-order term; docs/science.md §2 BRDF form)."""
    params = HK93Params([_layer(eta=1.0, g=0.0, sigma_a=(0, 0, 0))], (0, 0, 0))
    wo, wi = sample_pairs(rng, 4000)
    got = evaluate(hk93.MODEL, wo, wi, params, env=cl_env)
    mu_o = np.maximum(wo[:, 2].astype(np.float64), 1e-7)
    mu_i = np.maximum(wi[:, 2].astype(np.float64), 1e-7)
    want = 1.0 / (4 * np.pi * (mu_i + mu_o))
    np.testing.assert_allclose(got, np.repeat(want[:, None], 3, 1), rtol=RTOL_F32)


def test05_closed_form_thin_layer(cl_env, rng):
    """tau -> 0: f -> T_in T_out W p tau / (eta^2 mu_1i mu_1o) (optically thin limit)."""
    d, eta, g = 1e-4, 1.4, 0.5
    sa, ssp = np.array([0.5, 1.0, 2.0]), np.array([5.0, 4.0, 3.0])
    params = HK93Params([dict(thickness_mm=d, eta=eta, sigma_a=sa, sigma_s_prime=ssp, g=g)],
                        (0, 0, 0))
    wo = with_cos(rng.uniform(0.1, 1, 2000), 2 * np.pi * rng.random(2000)).astype(np.float32)
    wi = with_cos(rng.uniform(0.1, 1, 2000), 2 * np.pi * rng.random(2000)).astype(np.float32)
    got = evaluate(hk93.MODEL, wo, wi, params, env=cl_env)
    ss = ssp / (1 - g)
    st = sa + ss
    mo, mi = wo[:, 2].astype(np.float64), wi[:, 2].astype(np.float64)
    m1o, m1i = np.sqrt(1 - (1 - mo**2) / eta**2), np.sqrt(1 - (1 - mi**2) / eta**2)

    def transmit(c0, c1):     # 1 - Fresnel, written from the s/p amplitude ratios
        rs = (c0 - eta * c1) / (c0 + eta * c1)
        rp = (eta * c0 - c1) / (eta * c0 + c1)
        return 1 - 0.5 * (rs**2 + rp**2)

    cos_scatter = -(wo[:, 0] * wi[:, 0] + wo[:, 1] * wi[:, 1]) / eta**2 - m1o * m1i
    hg = (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * cos_scatter) ** 1.5)
    want = (transmit(mo, m1o) * transmit(mi, m1i) * hg / (eta**2 * m1o * m1i))[:, None] \
        * (ss / st) * (st * d)
    # (1 - e^-x)/x = 1 - x/2 + ...: relative deviation <= x/2, x = tau (1/m1i + 1/m1o)
    x_max = st.max() * d * 2 / np.sqrt(1 - 0.99 / eta**2)
    np.testing.assert_allclose(got, want, rtol=x_max / 2 + RTOL_F32)


def test06_closed_form_normal_incidence(cl_env):
    """wo = wi = normal, one slab: f = (1 - R0)^2 W HG(-1) (1 - e^{-2 tau}) / (2 eta^2) + rho/pi,
    R0 = ((eta - 1)/(eta + 1))^2."""
    eta, g, d = 1.33, 0.7, 0.2
    sa, ssp, ms = np.array([0.2, 0.3, 0.4]), np.array([2.0, 2.5, 3.0]), np.array([0.1, 0.2, 0.3])
    params = HK93Params([dict(thickness_mm=d, eta=eta, sigma_a=sa, sigma_s_prime=ssp, g=g)], ms)
    n = np.array([[0.0, 0.0, 1.0]], np.float32)
    got = evaluate(hk93.MODEL, n, n, params, env=cl_env)[0]
    ss = ssp / (1 - g)
    r0 = ((eta - 1) / (eta + 1)) ** 2
    hg_back = (1 - g * g) / (4 * np.pi * (1 + g) ** 3)
    want = (1 - r0) ** 2 * ss / (sa + ss) * hg_back * (1 - np.exp(-2 * (sa + ss) * d)) \
        / (2 * eta**2) + ms / np.pi
    np.testing.assert_allclose(got, want, rtol=RTOL_F32)


def test07_layer_split_invariance(cl_env, rng):
    """A semi-infinite medium cut into a 0.3 mm slab over the same medium reflects exactly as
    the uncut medium: layer 2's light must be attenuated by layer 1 on the way in AND out."""
    whole = HK93Params([_layer()], (0, 0, 0))
    split = HK93Params([_layer(thickness_mm=0.3), _layer()], (0, 0, 0))
    wo, wi = sample_pairs(rng, 4000)
    np.testing.assert_allclose(evaluate(hk93.MODEL, wo, wi, split, env=cl_env),
                               evaluate(hk93.MODEL, wo, wi, whole, env=cl_env),
                               rtol=RTOL_F32, atol=ATOL_F32)


def test08_default_multiple_scattering():
    """rho_ms = (1 - Fdr_ext(eta)) Rd - int rho_ss 2 mu dmu with Rd the layer profile's
    (the BSSRDF's own layer file): HK93 then reflects what the BSSRDF does under uniform
    light (tests/test_energy.py checks the whole BRDF's reflectance)."""
    from dermis.optics.fresnel import diffuse_fresnel_external
    skin1 = PRESETS["skin1"].layers[0]
    p = HK93Params([Layer(math.inf, 1.3, skin1.sigma_a, skin1.sigma_s_prime, 0.8)])
    mu = (np.arange(64) + 0.5) / 64
    ss_hemi = (hk93_single_scattering_albedo(p.layers, mu) * 2 * mu[:, None]).mean(axis=0)
    assert np.all(ss_hemi > 0) and np.all(ss_hemi < 0.02)
    # the layer file's Rd (exact plane-parallel transport) of this g = 0.8 medium lies below
    # the classical dipole's, which sees the medium through sigma_s' alone (measured 1-30 %)
    assert np.all(p.diffuse_reflectance < dipole_Rd(skin1.sigma_a, skin1.sigma_s_prime, 1.3))
    want = (1 - diffuse_fresnel_external(1.3)) * p.diffuse_reflectance - ss_hemi
    np.testing.assert_allclose(p.multiple_scattering, want, rtol=2e-3)
    # an explicit Rd is used as given
    q = HK93Params(p.layers, diffuse_reflectance=(0.5, 0.4, 0.3))
    np.testing.assert_allclose(q.multiple_scattering,
                               (1 - diffuse_fresnel_external(1.3)) * np.array([0.5, 0.4, 0.3])
                               - ss_hemi, rtol=2e-3)
    np.testing.assert_allclose(q.texture_reference(), [0.5, 0.4, 0.3])


@pytest.mark.parametrize("layers", ["default", "odd"])
def test09_reciprocity(cl_env, rng, layers):
    params = HK93Params() if layers == "default" else HK93Params(ODD)
    wo, wi = sample_pairs(rng)
    a = evaluate(hk93.MODEL, wo, wi, params, env=cl_env)
    b = evaluate(hk93.MODEL, wi, wo, params, env=cl_env)
    np.testing.assert_allclose(a, b, rtol=RTOL_RECIPROCITY, atol=0)


def test10_energy_chandrasekhar_exact(cl_env, rng):
    """White isotropic index-matched half-space: a(mu) = (1 - mu ln((1 + mu)/mu))/2 exactly."""
    params = HK93Params([_layer(eta=1.0, g=0.0, sigma_a=(0, 0, 0))], (0, 0, 0))
    mean, err = mc_albedo(_f(params), THETA_GRID, rng, N_MC)
    mu = np.cos(np.radians(THETA_GRID))
    exact = 0.5 * (1 - mu * np.log((1 + mu) / mu))
    assert np.all(np.abs(mean - exact[:, None]) <= N_SIGMA * err)


@pytest.mark.parametrize("case", ["default", "odd", "white_backscatter"])
def test11_energy_albedo_at_most_one(cl_env, rng, case):
    """Directional albedo <= 1 (+5 sigma) to 89 deg, derived rho_ms included; the white,
    index-matched, backward-scattering half-space is the hardest case (Rd = 1)."""
    params = {"default": HK93Params(), "odd": HK93Params(ODD),
              "white_backscatter": HK93Params([_layer(eta=1.0, g=-0.5, sigma_a=(0, 0, 0))])
              }[case]
    mean, err = mc_albedo(_f(params), THETA_GRID, rng, N_MC)
    assert np.all(mean - N_SIGMA * err <= 1.0), mean
    assert np.all(mean > params.multiple_scattering), "single scattering adds, never removes"
    if case == "white_backscatter":      # rho_ms was chosen so the maximum is ~Rd = 1
        assert mean.max() > 0.95


def test12_grazing_and_backfacing_finite(cl_env, rng):
    n = 400
    phi = 2 * np.pi * rng.random(n)
    graze = with_cos(np.repeat([0.0, 1e-8, 1e-30, 1e-3], n // 4), phi)
    other = hemisphere(rng, n)
    below = other * (1.0, 1.0, -1.0)
    for params in (HK93Params(), HK93Params(ODD),
                   HK93Params([_layer(eta=1.0, g=0.0, sigma_a=(0, 0, 0))], (0, 0, 0))):
        for wo, wi in [(graze, other), (other, graze), (graze, graze[::-1]),
                       (below, other), (other, below), (below, below)]:
            f = evaluate(hk93.MODEL, wo, wi, params, env=cl_env)
            assert np.all(np.isfinite(f)) and np.all(f >= 0)
            on_or_below = (wo[:, 2] <= 0) | (wi[:, 2] <= 0)
            assert np.all(f[on_or_below] == 0)


@pytest.mark.parametrize("g", [-0.99, 0.99])
@pytest.mark.parametrize("eta", [1.0, 1.4])
def test13_single_scattering_quadrature_converges(g, eta):
    """HK93Params' maximum single-scattering albedo (which caps rho_ms) is converged for the
    sharpest Henyey-Greenstein lobes: its own grid against 1024 cells per axis within
    SS_ALBEDO_TOL; for eta = 1 the grazing limit alpha / 2 (for a horizontal view direction
    the phase function's integral over the upper hemisphere is 1/2 by mirror symmetry, and
    mu_i / (mu_i + mu_o) -> 1) is reached.  Before: 96 cells uniform in cos theta and a grid
    ending at 1e-3 read 0.325 for g = 0.99, so rho_ms = 0.675 and the albedo 1.18 at grazing."""
    from dermis.models.hk93 import SS_ALBEDO_TOL, _SS_COS_GRID, _max_single_scattering_albedo
    alpha = 1.0 - 1e-7
    lay = Layer(math.inf, eta, (1e-7,) * 3, (1e-3 * (1 - g),) * 3, g)   # sigma_s = 1e-3
    p = HK93Params([lay], multiple_scattering=(0.0, 0.0, 0.0))
    got = _max_single_scattering_albedo(p.layers)
    ref = hk93_single_scattering_albedo(p.layers, _SS_COS_GRID, n=1024).max(axis=0)
    np.testing.assert_allclose(got, ref, atol=SS_ALBEDO_TOL)
    if eta == 1.0:
        np.testing.assert_allclose(got, alpha / 2, atol=SS_ALBEDO_TOL)
    # and the derived rho_ms keeps the whole directional albedo <= 1 at every grid cosine
    q = HK93Params([lay], diffuse_reflectance=(0.97,) * 3)
    assert np.all(ref + q.multiple_scattering <= 1.0 + SS_ALBEDO_TOL)
