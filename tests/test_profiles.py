"""Layer optics: diffusion profiles, exact totals, FFT adding (optics/multipole.py,
optics/adding_doubling.py, optics/layer_convolution.py, optics/layer_profiles.py,
docs/profiles.md).  The comparisons with the Monte Carlo are in tests/test_profile_mc.py."""
import math

import numpy as np
import pytest

from dermis.pipeline.errors import ConfigError, DermisError
from dermis.optics.layers import PRESETS, Layer, LayerStack, parse_layer_stack
from dermis.optics.adding_doubling import exact_totals
from dermis.optics.layer_file import CUTOFF_FRACTION
from dermis.optics.layer_profiles import MultipoleOptions, build_profiles
from dermis.optics.multipole import NQ_BEAM, multipole_profiles, multipole_totals
from dermis.optics.fresnel import dipole_Rd, diffusion_boundary, fresnel_moments

SKIN1 = PRESETS["skin1"].layers[0]
EPI = PRESETS["two_layer"].layers[0]


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


def test02_only_last_layer_infinite_and_eta_above():
    lay = {"thickness_mm": "inf", "eta": 1.3, "sigma_a": [0.1] * 3, "sigma_s_prime": [1.0] * 3}
    with pytest.raises(ConfigError, match=r"layers\[0\]\.thickness_mm = inf: only the last"):
        parse_layer_stack({"layers": [lay, lay]}, where="x.toml")
    with pytest.raises(ConfigError, match=r"eta_above = 0.5: must be >= 1"):
        parse_layer_stack({"layers": [lay], "eta_above": 0.5}, where="x.toml")
    s = parse_layer_stack({"layers": [
        {"thickness_mm": 1, "eta": 1.3, "sigma_a": [0.1] * 3, "sigma_s": [5.0] * 3, "g": 0.8}]},
        where="x.toml")
    assert s.layers[0].sigma_s_prime == pytest.approx((1.0, 1.0, 1.0))


def test03_model_arguments_rejected():
    with pytest.raises(DermisError, match=r"model = 'mc': must be one of 'multipole', 'monte_carlo'"):
        build_profiles(PRESETS["skin1"], model="mc")
    with pytest.raises(DermisError, match=r"diffusion = 'pdb': must be one of 'pbd', 'dj2005'"):
        build_profiles(PRESETS["skin1"], options=MultipoleOptions(diffusion="pdb"))
    with pytest.raises(DermisError, match=r"totals = 'exact': must be 'transport' or 'diffusion'"):
        build_profiles(PRESETS["skin1"], options=MultipoleOptions(totals="exact"))


# ---- 02 closed forms -----------------------------------------------------------------
# Jensen 2001 publishes Rd to two digits: Skin1 (0.44, 0.22, 0.13), Skin2 (0.63, 0.44, 0.34)
# -> tolerance half a unit of the last digit plus rounding of the inputs: 0.01.  The dj2005
# model (dermis <= 1) is the dipole exactly; the default's totals are the radiative-transfer
# ones (checked against the Monte Carlo in test_profile_mc.py).
@pytest.mark.parametrize("name, published", [("skin1", (0.44, 0.22, 0.13)),
                                             ("skin2", (0.63, 0.44, 0.34))])
def test04_jensen_skin_Rd(name, published):
    lay = PRESETS[name].layers[0]
    assert dipole_Rd(lay.sigma_a, lay.sigma_s_prime, 1.3) == pytest.approx(published, abs=0.01)
    prof = build_profiles(PRESETS[name], options=MultipoleOptions(diffusion="dj2005"))
    np.testing.assert_allclose(prof.Rd, dipole_Rd(lay.sigma_a, lay.sigma_s_prime, 1.3),
                               rtol=1e-12)


def test05_fresnel_moments():
    # eta = 1: no reflection; 2 C1 is the diffuse reflectance Fdr, which the Egan-Hilgeman
    # fit approximates (within 0.01 at eta 1.3, 1.4); A at eta = 1.4 (d'Eon 2012: ~2.95).
    assert fresnel_moments(1.0) == (0.0, 0.0)
    for eta in (1.3, 1.4):
        c1, _ = fresnel_moments(eta)
        fdr = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
        assert abs(2 * c1 - fdr) < 0.01
    A, cphi, ce = diffusion_boundary(1.4)
    assert A == pytest.approx(2.95, abs=0.01)
    assert diffusion_boundary(1.0) == pytest.approx((1.0, 0.25, 0.5))


@pytest.mark.parametrize("diffusion", ["pbd", "dj2005"])
def test06_thick_slab_is_semi_infinite(diffusion):
    r = np.linspace(0, 10, 101)
    Rinf, _ = multipole_profiles(SKIN1, r, eta_above=1.0, eta_below=1.0, diffusion=diffusion)
    thick = Layer(400.0, SKIN1.eta, SKIN1.sigma_a, SKIN1.sigma_s_prime)
    Rd, T = multipole_profiles(thick, r, eta_above=1.0, eta_below=1.0, diffusion=diffusion)
    # 400 mm of sigma_tr >= 0.27/mm: images are e^{-100} away -> float64 agreement
    np.testing.assert_allclose(Rd, Rinf, rtol=1e-9)
    assert np.all(T < 1e-30)


def test07_ring_table_integrates_to_Rd():
    prof = build_profiles(PRESETS["skin2"])
    h = prof.r_mm[1]
    edges = np.concatenate([[0.0], (np.arange(len(prof.r_mm)) + 0.5) * h])
    inside = (prof.R * (np.pi * np.diff(edges**2))[:, None]).sum(0)
    np.testing.assert_allclose(inside / prof.Rd, 1 - np.array(prof.info["energy_beyond_table"]),
                               rtol=1e-9)
    assert np.all(prof.energy_beyond_cutoff <= 1 - CUTOFF_FRACTION + 1e-9)


# Exact plane-parallel totals (adding-doubling): published transport solutions.
def test08_adding_doubling_published():
    # van de Hulst's slab (MCML's validation case): a = 0.9, tau = 2, g = 0.75, n = 1:
    # Rd = 0.09739, Tt = 0.66096; Chandrasekhar's semi-infinite isotropic a = 0.9 plane
    # albedo at normal incidence 0.41495.  5 digits.
    vdh = Layer(0.2, 1.0, (1.0,) * 3, (9.0 * 0.25,) * 3, 0.75)
    ex = exact_totals([vdh], 0, 1.0, 1.0)
    assert ex.Rc == pytest.approx(0.09739, abs=1e-5)
    assert ex.Tc + ex.Tu == pytest.approx(0.66096, abs=1e-5)
    semi = Layer(math.inf, 1.0, (1.0,) * 3, (9.0,) * 3, 0.0)
    assert exact_totals([semi], 0, 1.0, 1.0).Rc == pytest.approx(0.41495, abs=1e-5)


def test09_adding_doubling_conserves_energy():
    # no absorption: everything that enters leaves (R + T = 1), Fresnel faces included, up
    # to the round-off of ~2^33 doublings from the 1e-6 mu_min first layer (~4e-7)
    for g in (0.8, -0.5):      # g < 0: delta-M's peak points backwards (kept as scattering)
        _conserves(Layer(0.5, 1.4, (0.0,) * 3, (2.0, 5.0, 9.0), g))


def _conserves(lay):
    for c in range(3):
        ex = exact_totals([lay], c, 1.4, 1.4 / 1.33)
        assert ex.Rc + ex.Tc + ex.Tu == pytest.approx(1.0, abs=1e-6)
        assert ex.Rd + ex.Td == pytest.approx(1.0, abs=1e-6)
        assert ex.Rud + ex.Tud == pytest.approx(1.0, abs=1e-6)


# ---- 03 convergence --------------------------------------------------------------------
def test10_pole_convergence():
    r = np.array([0.0, 0.1, 0.5, 2.0])
    prev = None
    diffs = []
    for n in (1, 2, 5, 10, 20):
        R, T = multipole_profiles(EPI, r, eta_above=1.0, eta_below=1.4, poles=n)
        if prev is not None:
            diffs.append(np.abs(np.concatenate([R, T]) - prev).max())
        prev = np.concatenate([R, T])
    assert diffs[-1] < 1e-9 and diffs[0] > diffs[-1]  # monotone approach to a limit


def test11_beam_convergence():
    # the beam integral: 16 nodes (the default) against 64, R(r) at r >= 0.05 mm: the
    # epidermis lit from above (measured < 1e-6) and the semi-infinite dermis (5e-4)
    r = np.linspace(0.05, 3.0, 60)
    a, _ = multipole_profiles(EPI, r, eta_above=1.0, eta_below=1.4, nq=NQ_BEAM)
    b, _ = multipole_profiles(EPI, r, eta_above=1.0, eta_below=1.4, nq=64)
    assert np.abs(a / b - 1).max() < 1e-4
    der = PRESETS["two_layer"].layers[1]
    a, _ = multipole_profiles(der, r, eta_above=1.4, eta_below=1.0, nq=NQ_BEAM)
    b, _ = multipole_profiles(der, r, eta_above=1.4, eta_below=1.0, nq=64)
    assert np.abs(a / b - 1).max() < 2e-3


def test12_grid_convergence():
    # FFT path of a single layer against its closed form: error must shrink ~h^2.
    st = PRESETS["skin2"]
    errs = []
    for h in (0.2, 0.1):
        a = build_profiles(st, options=MultipoleOptions(grid=(h, 20.0)))
        b = build_profiles(st, options=MultipoleOptions(grid=(h, 20.0), force_fft=True))
        k = slice(int(round(0.4 / h)), int(round(5.0 / h)))
        errs.append(np.abs(b.R[k] / a.R[k] - 1).max())
    assert errs[1] < 0.5 * errs[0]
    assert errs[1] < 0.02  # measured 0.8 % at h = 0.1 mm


# ---- 04 combination invariants -------------------------------------------------------------
def _adding_on_totals(st, totals):
    """The two-kind adding of build_profiles (collimated light passed on as collimated,
    diffuse light as diffuse) on the closed-form totals of each layer."""
    etas = [st.eta_above] + [l.eta for l in st.layers] + [st.eta_below]
    A = None
    for k, lay in enumerate(st.layers):
        up, dn = etas[k], etas[k + 2]
        kw = dict(totals=totals)
        Rc, Tc, tau = multipole_totals(lay, eta_above=up, eta_below=dn, **kw)
        Rd, Td, Tdd = multipole_totals(lay, eta_above=up, eta_below=dn, light="diffuse", **kw)
        Ru, Tu, Tud = multipole_totals(lay, eta_above=dn, eta_below=up, light="diffuse", **kw)
        B = dict(Rc=Rc, Tc=Tc, tau=tau, Rd=Rd, Td=Td + Tdd, Rud=Ru, Tud=Tu + Tud)
        if A is None:
            A = B
            continue
        den = 1 / (1 - B["Rd"] * A["Rud"])
        U = (A["tau"] * B["Rc"] + B["Rd"] * A["Tc"]) * den
        down = A["Tc"] + A["Rud"] * U
        Uu = B["Tud"] * den
        A = dict(Rc=A["Rc"] + A["Tud"] * U, Tc=A["tau"] * B["Tc"] + B["Td"] * down,
                 tau=A["tau"] * B["tau"], Rud=B["Rud"] + B["Td"] * A["Rud"] * Uu,
                 Tud=A["Tud"] * Uu)
    return A["Rc"], A["Tc"] + A["tau"]


@pytest.mark.parametrize("totals", ["diffusion", "transport"])
def test13_dc_equals_adding_on_totals(totals):
    # different eta per layer: no whole-stack transport solution, so the transport totals
    # are the adding of the exact layer totals too
    top = Layer(0.3, 1.4, (0.3, 0.4, 0.9), (4.0, 6.0, 9.0), 0.8)
    mid = Layer(0.5, 1.3, (0.05, 0.2, 0.4), (2.0, 3.0, 4.0))
    bot = Layer(2.0, 1.45, (0.02, 0.1, 0.3), (1.0, 1.5, 2.0))
    st = stack_of(top, mid, bot, above=1.0, below=1.0)
    prof = build_profiles(st, options=MultipoleOptions(grid=(0.05, 10.0), totals=totals))
    R, T = _adding_on_totals(st, totals)
    np.testing.assert_allclose(prof.Rd, R, rtol=1e-10)
    np.testing.assert_allclose(prof.Tt, T, rtol=1e-10)


def test14_equal_eta_stack_takes_the_whole_stack_solution():
    st = PRESETS["two_layer"]
    prof = build_profiles(st, options=MultipoleOptions(grid=(0.05, 8.0)))
    eta = st.layers[0].eta
    exact = [exact_totals(st.layers, c, eta / st.eta_above, eta / st.eta_below) for c in range(3)]
    np.testing.assert_allclose(prof.Rd, [e.Rc for e in exact], rtol=1e-10)
    assert prof.info["stack_totals"].startswith("adding-doubling")


@pytest.mark.parametrize("name", ["two_layer"])
def test15_nonnegative_after_combination(name):
    prof = build_profiles(PRESETS[name])
    assert np.all(prof.R >= 0) and np.all(prof.T >= 0)
    # with the partial-current exitance nothing but round-off goes negative here
    assert prof.info["min_clipped_rel"] > -1e-12 and prof.info["negative_lobes"] == []


def test16_negative_lobes_reported_and_energy_kept():
    # dermis <= 1's flux-only exitance goes negative far out in the epidermis (its top z_b
    # exceeds half the slab): the lobe is reported (where, how much) and the profile keeps
    # the closed-form energy instead of losing it to clipping
    st = stack_of(EPI, above=1.0, below=1.4)
    prof = build_profiles(st, options=MultipoleOptions(diffusion="dj2005"))
    lobes = [l for l in prof.info["negative_lobes"] if l["field"] == "R"]
    assert lobes and all(l["energy_fraction"] > 0 and l["r_mm"][0] > 0.2 for l in lobes)
    assert np.all(prof.R >= 0)
    h = prof.r_mm[1]
    edges = np.concatenate([[0.0], (np.arange(len(prof.r_mm)) + 0.5) * h])
    inside = (prof.R * (np.pi * np.diff(edges**2))[:, None]).sum(0)
    Rd, _, _ = multipole_totals(EPI, eta_above=1.0, eta_below=1.4, diffusion="dj2005")
    np.testing.assert_allclose(inside + prof.Rd * np.array(prof.info["energy_beyond_table"]),
                               Rd, rtol=1e-9)


def test17_negative_lobe_fraction_is_scale_free():
    # a lobe's energy fraction is a property of the profile's shape: the same profile at
    # 1e-303 of the light (a 660 mm layer's transmittance) has ring energies below the float64
    # range, which read 0 and hid a 0.65 % lobe (tests/test_stability.py test11's example)
    from dermis.optics.layer_file import NegativeLobes
    h = 0.0079
    r = np.arange(500) * h
    area = np.pi * np.diff(np.concatenate([[0.0], (np.arange(500) + 0.5) * h]) ** 2)
    vals = np.exp(-r / 0.1) - 0.05 * np.exp(-((r - 1.0) / 0.3) ** 2)
    fractions = []
    for scale in (1.0, 1e-303):
        lobes = NegativeLobes()
        out = lobes.fix(vals * scale, area, r, {"field": "T"}, total=2.0 * scale)
        assert len(lobes.items) == 1 and np.all(out >= 0)
        assert float(np.sum(out * area)) == pytest.approx(2.0 * scale, rel=1e-12)
        fractions.append(lobes.items[0]["energy_fraction"])
    assert fractions[1] == pytest.approx(fractions[0], rel=1e-12) and fractions[0] > 1e-3


def test18_zero_thickness_top_is_identity():
    a = build_profiles(PRESETS["two_layer"], options=MultipoleOptions(grid=(0.05, 8.0)))
    zero = Layer(0.0, 1.7, (5.0, 5.0, 5.0), (1.0, 1.0, 1.0))
    b = build_profiles(LayerStack((zero,) + PRESETS["two_layer"].layers),
                       options=MultipoleOptions(grid=(0.05, 8.0)))
    np.testing.assert_array_equal(a.R, b.R)
    np.testing.assert_array_equal(a.Rd, b.Rd)


@pytest.mark.parametrize("totals", ["diffusion", "transport"])
def test19_thin_slab_tends_to_identity(totals):
    for d in (1e-3, 1e-6):
        lay = Layer(d, 1.4, (0.3, 0.4, 0.9), (4.0, 6.0, 9.0))
        Rd, Td, tau = multipole_totals(lay, eta_above=1.4, eta_below=1.4, totals=totals)
        assert np.all(Rd < 20 * d) and np.all(np.abs(Td + tau - 1) < 20 * d)


def test20_ballistic_is_the_real_extinction():
    # the unscattered transmission of a layer is e^{-sigma_t d} with sigma_t = sigma_a +
    # sigma_s (not sigma_t'), times the normal-incidence Fresnel transmission at the bottom
    lay = Layer(0.25, 1.4, (0.27,) * 3, (2.03,) * 3, 0.8)
    prof = build_profiles(stack_of(lay, above=1.0, below=1.0))
    st = 0.27 + 2.03 / 0.2
    r0 = ((1.4 - 1) / 2.4) ** 2
    want = math.exp(-st * 0.25) * (1 - r0) / (1 - r0 * r0 * math.exp(-2 * st * 0.25))
    np.testing.assert_allclose(prof.info["T_ballistic"], want, rtol=1e-12)
    assert want == pytest.approx(0.074 * (1 - r0), rel=0.01)      # not e^{-sigma_t' d} = 0.563


# ---- 05 extremes ---------------------------------------------------------------------------
@pytest.mark.parametrize("lay", [
    Layer(math.inf, 1.3, (1e4, 1e-4, 0.0), (1e-4, 1e4, 1.0)),   # albedo ~0, ~1, sigma_a = 0
    Layer(1e-5, 1.0, (0.1, 0.1, 0.1), (1.0, 1.0, 1.0)),         # thickness -> 0, matched eta
    Layer(1e3, 1.4, (1e-3, 0.01, 0.1), (0.1, 1.0, 10.0), 0.99),  # thickness >> mfp, g ~ 1
    Layer(5.0, 1.4, (2e-4, 1.0, 3.0), (2.0, 1.0, 0.0), -0.99),  # albedo 0.9999, g ~ -1
])
def test21_extremes_are_finite_and_nonnegative(lay):
    prof = build_profiles(LayerStack((lay,)))
    for a in (prof.R, prof.T, prof.Rd, prof.Tt, prof.cutoff_mm):
        assert np.all(np.isfinite(a)) and np.all(a >= 0)
    assert np.all(prof.Rd + prof.Tt <= 1 + 1e-9)
    assert all(l["energy_fraction"] >= 0 for l in prof.info["negative_lobes"])
    # coarse grid keeps the test fast; positivity must hold on any grid
    two = build_profiles(LayerStack((Layer(0.2, 1.4, (0.3,) * 3, (4.0,) * 3), lay)),
                         options=MultipoleOptions(grid=(0.05, 8.0)))
    assert np.all(np.isfinite(two.R)) and np.all(two.R >= 0) and np.all(two.T >= 0)


def test_optically_thick_forward_scattering_layer_stays_finite():
    # a 11 mm, g = 0.99 layer (sigma_t d = 147 in blue, so 1 - e^{-sigma_t d} is 1.0 in
    # float64) under a pure absorber: the collision depth of the beam's last quadrature node
    # was infinite and the forward sum e^{+inf} (the thorough stability profile).
    # The pure absorbers' transmission is e^{-sum sigma_a d} exactly (eta = 1: no Fresnel).
    st = LayerStack((Layer(1.0, 1.0, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), -0.99),
                     Layer(11.0, 1.0, (1.0, 1.0, 0.875), (0.0, 0.0, 0.125), 0.99)), 1.0, 1.0)
    p = build_profiles(st)
    assert np.isfinite(p.R).all() and np.isfinite(p.T).all()
    np.testing.assert_allclose(p.Tt[:2], math.exp(-12.0), rtol=1e-6)
    assert (p.Rd + p.Tt <= 1.0).all() and p.Rd[2] > 0
