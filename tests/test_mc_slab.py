"""OpenCL Monte Carlo reference (optics/monte_carlo_slab.py, cl/mc_slab.cl, cl/rng.h)."""
import math

import numpy as np
import pytest

from dermis.optics.layers import PRESETS, Layer, LayerStack
from dermis.optics import monte_carlo_slab as M
from dermis.optics.layer_profiles import MultipoleOptions, build_profiles


@pytest.fixture(scope="module")
def env():
    from dermis.pipeline import cl as dcl
    try:
        return dcl.get_env()
    except Exception as exc:  # pragma: no cover
        pytest.skip(f"no OpenCL device: {exc}")


def test01_repeatable_and_conserving(env):
    st = LayerStack((Layer(0.5, 1.4, (0.5, 0.2, 1.0), (5.0, 2.0, 9.0), 0.8),
                     Layer(2.0, 1.33, (0.05, 0.1, 0.2), (2.0, 2.0, 2.0), 0.0)))
    a = M.simulate(st, photons=30000, r_max_mm=5, bins=20, seed=7, env=env)
    b = M.simulate(st, photons=30000, r_max_mm=5, bins=20, seed=7, env=env)
    np.testing.assert_array_equal(a.R, b.R)
    # R + T + absorbed = 1: roulette is unbiased, so the sum is 1 up to its noise; float32
    # per-item sums add ~1e-6.  5 sigma of the three errors combined, plus 1e-5.
    tol = 5 * np.sqrt(a.Rd_err**2 + a.Tt_err**2 + a.absorbed_err**2) + 1e-5
    assert np.all(np.abs(a.Rd + a.Tt + a.absorbed + a.lost - 1) < tol)
    c = M.simulate(st, photons=30000, r_max_mm=5, bins=20, seed=8, env=env)
    assert not np.array_equal(a.R, c.R)


def test02_matched_semi_infinite_published(env):
    # Isotropic, albedo 0.9, matched boundary, normal incidence: exact plane albedo
    # 1 - H(1) sqrt(1 - a) = 0.41495 (Chandrasekhar 1960; H(1) = 1.85010 computed by
    # iterating the H equation on 200 Gauss points).  Tolerance 5 standard errors.
    st = LayerStack((Layer(math.inf, 1.0, (1.0,) * 3, (9.0,) * 3),))
    r = M.simulate(st, photons=100000, r_max_mm=5, bins=10, env=env)
    assert np.all(np.abs(r.Rd - 0.41495) < 5 * r.Rd_err + 1e-4)


def test03_mcml_slab_van_de_hulst(env):
    # Wang & Jacques 1995 (MCML) validation slab: n = 1, mu_a = 10/cm, mu_s = 90/cm,
    # g = 0.75, d = 0.02 cm.  van de Hulst: Rd = 0.09739, Tt = 0.66096.  5 sigma.
    st = LayerStack((Layer(0.2, 1.0, (1.0,) * 3, (9.0 * 0.25,) * 3, 0.75),))
    r = M.simulate(st, photons=100000, r_max_mm=5, bins=10, env=env)
    assert np.all(np.abs(r.Rd - 0.09739) < 5 * r.Rd_err + 2e-4)
    assert np.all(np.abs(r.Tt - 0.66096) < 5 * r.Tt_err + 2e-4)


def test04_multipole_agrees_beyond_two_mfp(env):
    # Skin2 (semi-infinite, eta 1.3, g = 0).  Measured (bench/bench_profiles.py, 4e5
    # photons): multipole/MC ratio of R(r) 1.09-1.26 at 2 mfp, 0.91-0.98 at 4 mfp,
    # 0.92-0.97 at 8 mfp; Rd within 2 %.  Tolerance: ratio in 0.75..1.35, Rd within 5 %
    # (the model error plus ~5 % MC noise per ring at 2e5 photons).  A wrong sign, pole or
    # normalisation moves these by far more.
    st = PRESETS["skin2"]
    prof = build_profiles(st, options=MultipoleOptions(grid=(0.1, 20.0)))
    mc = M.simulate(st, photons=200000, r_max_mm=20.0, bins=200, env=env)
    assert np.all(np.abs(prof.Rd / mc.Rd - 1) < 0.05)
    for c, lay_mfp in enumerate(1 / (np.array(st.layers[0].sigma_a) +
                                     np.array(st.layers[0].sigma_s_prime))):
        for rr in (2 * lay_mfp, 4 * lay_mfp, 8 * lay_mfp):
            k = int(rr / 0.1)
            ratio = np.interp(mc.r_centres[k], prof.r_mm, prof.R[:, c]) / mc.R[k, c]
            assert 0.75 < ratio < 1.35, (c, rr, ratio)


@pytest.mark.parametrize("lay", [
    Layer(math.inf, 1.3, (1e3, 1e-3, 0.0), (1e-3, 10.0, 1.0)),   # albedo ~0, ~1, sigma_a 0
    Layer(1e-4, 1.0, (0.1,) * 3, (1.0,) * 3, 0.99),             # thin, g -> 1
    Layer(3.0, 1.4, (0.1,) * 3, (2.0,) * 3, -0.99),             # g -> -1
])
def test05_extremes_finite(env, lay):
    r = M.simulate(LayerStack((lay,)), photons=6000, r_max_mm=5, bins=10, env=env)
    for a in (r.R, r.T, r.Rd, r.Tt, r.absorbed):
        assert np.all(np.isfinite(a)) and np.all(a >= 0)


def test06_philox_known_answers_and_cheap_math(env):
    # Philox4x32 known-answer vectors (Random123 kat_vectors; Salmon et al. 2011) from
    # the scalar form (10 rounds) and the vector (uint8/uint16 lanes) form in cl/rng.h with
    # the tracer's rounds (7 and 10 both checked).
    import pyopencl as cl
    for rounds in (7, 10):
        _check_philox_and_cheap_math(env, cl, rounds)


def _check_philox_and_cheap_math(env, cl, rounds):
    lanes = M.lanes_for(env)
    knl = cl.Kernel(env.program("mc_slab.cl", dict(M.kernel_defines(env), PHILOX_ROUNDS=rounds)),
                    "mc_selftest")
    n = 1 << 16
    # u = (k + 1) / 2^24: the tracer's uniforms, k spread over [0, 2^24) plus both ends
    k = (np.arange(n, dtype=np.uint64) * 2654435761) % (1 << 24)
    k[:2] = (0, (1 << 24) - 1)
    u = ((k + 1).astype(np.float64) / 2.0**24).astype(np.float32)
    mf = cl.mem_flags
    d_kat = cl.Buffer(env.context, mf.READ_WRITE, 12 * 4)
    d_u = cl.Buffer(env.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=u)
    d_m = cl.Buffer(env.context, mf.READ_WRITE, 3 * n * 4)
    knl(env.queue, (n // lanes,), None, d_kat, d_u, d_m)
    kat = np.zeros(12, np.uint32)
    m = np.zeros(3 * n, np.float32)
    cl.enqueue_copy(env.queue, kat, d_kat)
    cl.enqueue_copy(env.queue, m, d_m)
    want = [0x6627e8d5, 0xe169c58d, 0xbc57ac4c, 0x9b00dbd8]      # scalar, 10 rounds, zeros
    want += {10: [0x408f276d, 0x41c83b0e, 0xa20bc7c6, 0x6d5451fd,   # all ones
                  0xd16cfe09, 0x94fdcceb, 0x5001e420, 0x24126ea1],  # digits of pi
             7: [0x5207ddc2, 0x45165e59, 0x4d8ee751, 0x8c52f662,
                 0x4dfccaba, 0x190a87f0, 0xc47362ba, 0xb6b5242a]}[rounds]
    assert [int(v) for v in kat] == want
    # -ln u: series error < 7e-10 plus float32 rounding of the result (|ln u| <= 16.7,
    # 2^-24 relative -> 1e-6) and of the intermediate (a few ulp): 2e-6 absolute.
    u64 = u.astype(np.float64)
    np.testing.assert_allclose(m[:n], -np.log(u64), rtol=0, atol=2e-6)
    # cos, sin of 2 pi u - pi: Taylor remainder < 6e-8, float rounding of pi (u - 1/2)
    # (~1e-7 relative) and the double-angle step: 1e-6 absolute.
    phi = 2 * np.pi * u64 - np.pi
    np.testing.assert_allclose(m[n:2 * n], np.cos(phi), rtol=0, atol=1e-6)
    np.testing.assert_allclose(m[2 * n:], np.sin(phi), rtol=0, atol=1e-6)


def test07_split_layer_is_identity(env):
    # Splitting a layer into two identical layers must not change R or T: exercises the
    # boundary hit, the carried-over free path and the transmission between layers of the
    # SIMD kernel.  Different seeds -> independent estimates; 5 combined standard errors.
    one = LayerStack((Layer(1.0, 1.4, (0.1, 0.3, 0.02), (2.0, 4.0, 1.0), 0.5),))
    two = LayerStack((Layer(0.3, 1.4, (0.1, 0.3, 0.02), (2.0, 4.0, 1.0), 0.5),
                      Layer(0.7, 1.4, (0.1, 0.3, 0.02), (2.0, 4.0, 1.0), 0.5)))
    a = M.simulate(one, photons=40000, r_max_mm=5, bins=10, seed=3, env=env)
    b = M.simulate(two, photons=40000, r_max_mm=5, bins=10, seed=4, env=env)
    assert np.all(np.abs(a.Rd - b.Rd) < 5 * np.hypot(a.Rd_err, b.Rd_err))
    assert np.all(np.abs(a.Tt - b.Tt) < 5 * np.hypot(a.Tt_err, b.Tt_err))


def test08_ballistic_two_layer_absorber(env):
    # Pure absorbers (sigma_s = 0): photons fly along the normal, a free path that
    # reaches the inner boundary carries its optical depth into the second layer, so the
    # survival per pass is exp(-tau), tau = sum sigma_a d, and Fresnel at normal incidence
    # R = ((n - 1) / (n + 1))^2 reflects at the faces.  Exact: T = (1 - R) e^-tau / (1 -
    # R^2 e^-2tau), Rd = R (1 - R) e^-2tau / (1 - R^2 e^-2tau) (geometric series of
    # reflections).  5 standard errors + 1e-4 (float32 layer table).
    sa1, sa2 = np.array([1.0, 2.0, 0.5]), np.array([0.5, 0.2, 1.0])
    st = LayerStack((Layer(0.5, 1.4, tuple(sa1), (0.0,) * 3),
                     Layer(1.0, 1.4, tuple(sa2), (0.0,) * 3)))
    r = M.simulate(st, photons=50000, r_max_mm=5, bins=10, env=env)
    e = np.exp(-(0.5 * sa1 + 1.0 * sa2))
    R = (0.4 / 2.4) ** 2
    T = (1 - R) * e / (1 - R**2 * e**2)
    Rd = R * (1 - R) * e**2 / (1 - R**2 * e**2)
    assert np.all(np.abs(r.Tt - T) < 5 * r.Tt_err + 1e-4), (r.Tt, T)
    assert np.all(np.abs(r.Rd - Rd) < 5 * r.Rd_err + 1e-4), (r.Rd, Rd)


def test09_combine_pools_runs_and_per_channel_budgets(env):
    # per-channel photon budgets are honoured; pooling a run with itself keeps the means and
    # divides the standard errors by sqrt(2) (equal weights); pooling unequal runs weights by
    # photons per channel
    st = LayerStack((Layer(math.inf, 1.4, (0.1, 0.3, 1.0), (2.0, 2.0, 2.0), 0.5),))
    a = M.simulate(st, photons=(4000, 8000, 16000), r_max_mm=5, bins=10, seed=1, env=env)
    n = np.asarray(a.info["photons_per_channel"])
    want = np.array([4000, 8000, 16000])
    assert np.all(n >= want) and np.all(n < want + a.info["items"])   # rounded up per item
    c = M.combine(a, a)
    np.testing.assert_allclose(c.R, a.R, rtol=1e-12)
    np.testing.assert_allclose(c.Rd_err, a.Rd_err / math.sqrt(2), rtol=1e-12)
    assert c.info["photons_per_channel"] == (2 * n).tolist()
    b = M.simulate(st, photons=(12000, 8000, 4000), r_max_mm=5, bins=10, seed=2, env=env)
    nb = np.asarray(b.info["photons_per_channel"])
    d = M.combine(a, b)
    np.testing.assert_allclose(d.Rd, (n * a.Rd + nb * b.Rd) / (n + nb), rtol=1e-12)
    # and the pooled estimate agrees with both within their errors (5 sigma)
    assert np.all(np.abs(a.Rd - b.Rd) < 5 * np.hypot(a.Rd_err, b.Rd_err))
