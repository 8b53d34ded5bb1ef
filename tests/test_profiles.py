"""Layer-optics stage: multipole profiles and FFT adding (stages/profiles.py, physics.md s3)."""
import math

import numpy as np
import pytest

from dermis.pipeline.errors import ConfigError
from dermis.physics.layers import PRESETS, Layer, LayerStack, parse_layer_stack
from dermis.stages import profiles as P
from dermis.physics.fresnel import dipole_Rd

SKIN1 = PRESETS["skin1"].layers[0]


def stack_of(*layers, above=1.0, below=1.0):
    return LayerStack(tuple(layers), above, below)


# ---- 01 validation ------------------------------------------------------------------
@pytest.mark.parametrize("patch, match", [
    ({"sigma_a": [-1, 0, 0]}, r"layers\[0\]\.sigma_a = \[-1, 0, 0\] \(1/mm\): must be >= 0"),
    ({"g": 1.0}, r"layers\[0\]\.g = 1: must be in \(-1, 1\)"),
    ({"eta": 0.9}, r"layers\[0\]\.eta = 0.9: must be >= 1"),
    ({"thickness_mm": -1}, r"thickness_mm = -1 \(mm\): must be >= 0"),
    ({"sigma_a": [0, 0, 0], "sigma_s_prime": [0, 1, 1]}, r"sigma_a \+ sigma_s_prime = 0"),
    ({"sigma_aa": [1, 1, 1]}, r"unknown key \(did you mean 'sigma_a'\?\)"),
    ({"sigma_s": [1, 1, 1]}, r"give exactly one"),
    ({"sigma_a": [1, 1]}, r"must be 3 numbers"),
])
def test01_validation_messages(patch, match):
    lay = {"thickness_mm": "inf", "eta": 1.3, "sigma_a": [0.1] * 3, "sigma_s_prime": [1.0] * 3}
    lay.update(patch)
    with pytest.raises(ConfigError, match=match):
        parse_layer_stack({"layers": [lay]}, where="x.toml")


def test01_only_last_layer_infinite_and_eta_above():
    lay = {"thickness_mm": "inf", "eta": 1.3, "sigma_a": [0.1] * 3, "sigma_s_prime": [1.0] * 3}
    with pytest.raises(ConfigError, match=r"layers\[0\]\.thickness_mm = inf: only the last"):
        parse_layer_stack({"layers": [lay, lay]}, where="x.toml")
    with pytest.raises(ConfigError, match=r"eta_above = 0.5: must be >= 1"):
        parse_layer_stack({"layers": [lay], "eta_above": 0.5}, where="x.toml")
    s = parse_layer_stack({"layers": [dict(lay, sigma_s_prime=None, sigma_s=[5.0] * 3, g=0.8)
                                      | {}] if False else [
        {"thickness_mm": 1, "eta": 1.3, "sigma_a": [0.1] * 3, "sigma_s": [5.0] * 3, "g": 0.8}]},
        where="x.toml")
    assert s.layers[0].sigma_s_prime == pytest.approx((1.0, 1.0, 1.0))


# ---- 02 closed forms -----------------------------------------------------------------
# Jensen 2001 publishes Rd to two digits: Skin1 (0.44, 0.22, 0.13), Skin2 (0.63, 0.44, 0.34)
# -> tolerance half a unit of the last digit plus rounding of the inputs: 0.01.
@pytest.mark.parametrize("name, published", [("skin1", (0.44, 0.22, 0.13)),
                                             ("skin2", (0.63, 0.44, 0.34))])
def test02_jensen_skin_Rd(name, published):
    lay = PRESETS[name].layers[0]
    assert dipole_Rd(lay.sigma_a, lay.sigma_s_prime, 1.3) == pytest.approx(published, abs=0.01)
    prof = P.build_profiles(PRESETS[name])
    np.testing.assert_allclose(prof.Rd, dipole_Rd(lay.sigma_a, lay.sigma_s_prime, 1.3),
                               rtol=1e-12)


def test02_thick_slab_is_dipole():
    r = np.linspace(0, 10, 101)
    Rinf, _ = P.multipole_profiles(SKIN1, r, eta_above=1.0, eta_below=1.0)
    thick = Layer(400.0, SKIN1.eta, SKIN1.sigma_a, SKIN1.sigma_s_prime)
    Rd, T = P.multipole_profiles(thick, r, eta_above=1.0, eta_below=1.0)
    # 400 mm of sigma_tr >= 0.27/mm: images are e^{-100} away -> float64 agreement
    np.testing.assert_allclose(Rd, Rinf, rtol=1e-9)
    assert np.all(T < 1e-30)


def test02_ring_table_integrates_to_Rd():
    prof = P.build_profiles(PRESETS["skin2"])
    h = prof.r_mm[1]
    edges = np.concatenate([[0.0], (np.arange(len(prof.r_mm)) + 0.5) * h])
    inside = (prof.R * (np.pi * np.diff(edges**2))[:, None]).sum(0)
    np.testing.assert_allclose(inside / prof.Rd, 1 - np.array(prof.info["energy_beyond_table"]),
                               rtol=1e-9)
    assert np.all(prof.energy_beyond_cutoff <= 1 - P.CUTOFF_FRACTION + 1e-9)


# ---- 03 convergence --------------------------------------------------------------------
def test03_pole_convergence():
    lay = PRESETS["two_layer"].layers[0]
    r = np.array([0.0, 0.1, 0.5, 2.0])
    prev = None
    diffs = []
    for n in (1, 2, 5, 10, 20):
        R, T = P.multipole_profiles(lay, r, eta_above=1.0, eta_below=1.4, poles=n)
        if prev is not None:
            diffs.append(np.abs(np.concatenate([R, T]) - prev).max())
        prev = np.concatenate([R, T])
    assert diffs[-1] < 1e-9 and diffs[0] > diffs[-1]  # monotone approach to a limit


def test03_grid_convergence():
    # FFT path of a single layer against its closed form: error must shrink ~h^2.
    st = PRESETS["skin2"]
    errs = []
    for h in (0.2, 0.1):
        a = P.build_profiles(st, grid=(h, 20.0))
        b = P.build_profiles(st, grid=(h, 20.0), force_fft=True)
        k = slice(int(round(0.4 / h)), int(round(5.0 / h)))
        errs.append(np.abs(b.R[k] / a.R[k] - 1).max())
    assert errs[1] < 0.5 * errs[0]
    assert errs[1] < 0.02  # measured 0.8 % at h = 0.1 mm


# ---- 04 combination invariants -------------------------------------------------------------
def test04_dc_equals_adding_on_totals():
    top = Layer(0.3, 1.4, (0.3, 0.4, 0.9), (4.0, 6.0, 9.0))
    mid = Layer(0.5, 1.3, (0.05, 0.2, 0.4), (2.0, 3.0, 4.0))
    bot = Layer(2.0, 1.45, (0.02, 0.1, 0.3), (1.0, 1.5, 2.0))
    st = stack_of(top, mid, bot, above=1.0, below=1.0)
    prof = P.build_profiles(st, grid=(0.05, 10.0))
    etas = [1.0, 1.4, 1.3, 1.45, 1.0]
    RA = TA = RpA = TpA = None
    for k, lay in enumerate(st.layers):
        Rd, Td, tau = P.multipole_totals(lay, eta_above=etas[k], eta_below=etas[k + 2])
        Rup, Tup, _ = P.multipole_totals(lay, eta_above=etas[k + 2], eta_below=etas[k])
        Tb, Tpb = Td + tau, Tup + tau
        if RA is None:
            RA, TA, RpA, TpA = Rd, Tb, Rup, Tpb
            continue
        den = 1 / (1 - RpA * Rd)
        RA, TA, RpA, TpA = (RA + TA * Rd * TpA * den, TA * Tb * den,
                            Rup + Tpb * RpA * Tb * den, Tpb * TpA * den)
    np.testing.assert_allclose(prof.Rd, RA, rtol=1e-10)
    np.testing.assert_allclose(prof.Tt, TA, rtol=1e-10)


@pytest.mark.parametrize("name", ["two_layer"])
def test04_nonnegative_after_combination(name):
    prof = P.build_profiles(PRESETS[name])
    assert np.all(prof.R >= 0) and np.all(prof.T >= 0)
    # clipping is only allowed at float64 round-off relative to the peak
    assert prof.info["min_clipped_rel"] > -1e-12


def test04_zero_thickness_top_is_identity():
    a = P.build_profiles(PRESETS["two_layer"], grid=(0.05, 8.0))
    zero = Layer(0.0, 1.7, (5.0, 5.0, 5.0), (1.0, 1.0, 1.0))
    b = P.build_profiles(LayerStack((zero,) + PRESETS["two_layer"].layers), grid=(0.05, 8.0))
    np.testing.assert_array_equal(a.R, b.R)
    np.testing.assert_array_equal(a.Rd, b.Rd)


def test04_thin_slab_tends_to_identity():
    for d in (1e-3, 1e-6):
        lay = Layer(d, 1.4, (0.3, 0.4, 0.9), (4.0, 6.0, 9.0))
        Rd, Td, tau = P.multipole_totals(lay, eta_above=1.0, eta_below=1.0)
        assert np.all(Rd < 20 * d) and np.all(np.abs(Td + tau - 1) < 20 * d)


# ---- 05 extremes ---------------------------------------------------------------------------
@pytest.mark.parametrize("lay", [
    Layer(math.inf, 1.3, (1e4, 1e-4, 0.0), (1e-4, 1e4, 1.0)),   # albedo ~0, ~1, sigma_a = 0
    Layer(1e-5, 1.0, (0.1, 0.1, 0.1), (1.0, 1.0, 1.0)),         # thickness -> 0, matched eta
    Layer(1e3, 1.4, (1e-3, 0.01, 0.1), (0.1, 1.0, 10.0), 0.99),  # thickness >> mfp, g ~ 1
    Layer(5.0, 1.4, (2e-4, 1.0, 3.0), (2.0, 1.0, 0.0), -0.99),  # albedo 0.9999, g ~ -1
])
def test05_extremes_are_finite_and_nonnegative(lay):
    prof = P.build_profiles(LayerStack((lay,)))
    for a in (prof.R, prof.T, prof.Rd, prof.Tt, prof.cutoff_mm):
        assert np.all(np.isfinite(a)) and np.all(a >= 0)
    assert np.all(prof.Rd + prof.Tt <= 1 + 1e-9)
    assert prof.info["min_clipped_rel"] > -1e-9  # only round-off was clipped
    # coarse grid keeps the test fast; positivity must hold on any grid
    two = P.build_profiles(LayerStack((Layer(0.2, 1.4, (0.3,) * 3, (4.0,) * 3), lay)), grid=(0.05, 8.0))
    assert np.all(np.isfinite(two.R)) and np.all(two.R >= 0) and np.all(two.T >= 0)
