"""Koenderink-Pont asperity scattering term (cl/asperity.cl, docs/science.md §5)."""
from __future__ import annotations

import math
import re

import numpy as np
import pytest

from brdf_testutil import hemisphere, mc_albedo, sample_pairs, with_cos
from dermis.pipeline.cl import CL_DIR
from dermis.pipeline.errors import ConfigError
from brdf_reference import asperity_f_np
from dermis.models import asperity
from dermis.models.asperity import ASPERITY_NPARAMS, AsperityParams
from dermis.models.evaluate import evaluate
from dermis.models.lafortune import LafortuneParams

# f = albedo tau / (4 pi m_i m_o): four float32 roundings and one division
RTOL_F32 = 8 * 2.0 ** -24
RTOL_RECIPROCITY = 2 * 2.0 ** -24
N_MC = 1 << 16
N_SIGMA = 5.0
THETA_GRID = [0, 15, 30, 45, 60, 70, 80, 85, 87, 89]


@pytest.mark.parametrize("kwargs, match", [
    (dict(delta_mm=0.0), r"asperity\.delta_mm = 0\.0 \(mm\): must be > 0"),
    (dict(delta_mm=-1.0), r"asperity\.delta_mm = -1\.0 \(mm\): must be > 0"),
    (dict(lambda_mm=0.5), r"asperity\.lambda_mm = 0\.5 \(mm\): must be > delta_mm = 1\.0"),
    (dict(lambda_mm=math.nan), r"asperity\.lambda_mm = nan.*must be finite"),
    (dict(albedo=(1.0, 1.1, 0.5)), r"asperity\.albedo = \[1\.0, 1\.1, 0\.5\]: must be in \[0, 1\]"),
    (dict(f_max=0.0), r"asperity\.f_max = 0\.0 \(1/sr\): must be > 0"),
    (dict(f_max="big"), r"asperity\.f_max = 'big': must be a number"),
    (dict(base="phong"), r"asperity\.base = 'phong': must be one of"),
])
def test01_params_rejected(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        AsperityParams(**kwargs)


def test02_pack_and_evaluate_contract(cl_env):
    src = (CL_DIR / "asperity.cl").read_text()
    assert int(re.search(r"#define ASPERITY_NPARAMS (\d+)", src).group(1)) == ASPERITY_NPARAMS
    p = AsperityParams(delta_mm=0.5, lambda_mm=10.0, albedo=(0.9, 0.8, 0.7), f_max=2.0)
    np.testing.assert_allclose(p.pack(), [0.05, 2.0, 0.9, 0.8, 0.7, 1, 0, 0], rtol=1e-7)
    assert AsperityParams(attenuate_base=False).pack()[5] == 0.0
    assert AsperityParams().pack()[1] == np.finfo(np.float32).max, "no cap: FLT_MAX"
    n = np.array([[0.0, 0.0, 1.0]])
    with pytest.raises(ConfigError, match=r"albedo: model 'asperity' reads no albedo"):
        evaluate(asperity.MODEL, n, n, albedo=np.ones(3))
    with pytest.raises(ConfigError, match=r"must be AsperityParams, got LafortuneParams"):
        evaluate(asperity.MODEL, n, n, LafortuneParams())


@pytest.mark.parametrize("kwargs", [{}, dict(delta_mm=0.3, lambda_mm=2.0, f_max=0.5,
                                             albedo=(0.9, 0.5, 0.2))])
def test03_matches_reference(cl_env, rng, kwargs):
    params = AsperityParams(**kwargs)
    wo, wi = sample_pairs(rng)
    got = evaluate(asperity.MODEL, wo, wi, params, env=cl_env)
    np.testing.assert_allclose(got, asperity_f_np(wo, wi, params), rtol=RTOL_F32)


def test04_closed_forms(cl_env):
    """Normal/normal: albedo tau/(4 pi); both grazing: albedo/(4 pi tau) (clamped cosines);
    one grazing: albedo/(4 pi cos); f_max caps all of it."""
    p = AsperityParams(delta_mm=1.0, lambda_mm=20.0, albedo=(1.0, 0.5, 0.25))
    tau = 0.05
    wo = with_cos([1.0, 0.0, 1e-3, 1e-3, 0.5], [0, 0, 0, 1, 2]).astype(np.float32)
    wi = with_cos([1.0, 1.0, 1e-3, 1e-6, 0.5], [0, 1, 2, 3, 4]).astype(np.float32)
    got = evaluate(asperity.MODEL, wo, wi, p, env=cl_env)
    scale = np.array([tau / (4 * np.pi), 0.0, 1 / (4 * np.pi * tau), 1 / (4 * np.pi * tau),
                      tau / (4 * np.pi * 0.25)])
    np.testing.assert_allclose(got, scale[:, None] * p.albedo, rtol=RTOL_F32)
    capped = evaluate(asperity.MODEL, wo, wi, AsperityParams(f_max=0.1), env=cl_env)
    assert capped.max() == np.float32(0.1)


def test05_reciprocity(cl_env, rng):
    wo, wi = sample_pairs(rng)
    p = AsperityParams(albedo=(0.9, 0.5, 0.2))
    np.testing.assert_allclose(evaluate(asperity.MODEL, wo, wi, p, env=cl_env),
                               evaluate(asperity.MODEL, wi, wo, p, env=cl_env),
                               rtol=RTOL_RECIPROCITY, atol=0)


@pytest.mark.parametrize("delta, lam", [(1.0, 20.0), (0.5, 1.0)])
def test06_energy_exact(cl_env, rng, delta, lam):
    """Directional albedo = albedo tau (1 - tau/2) / (2 max(cos_o, tau)) < 1/2 (clamp form)."""
    p = AsperityParams(delta_mm=delta, lambda_mm=lam)
    tau = delta / lam
    mean, err = mc_albedo(lambda wo, wi: evaluate(asperity.MODEL, wo, wi, p), THETA_GRID, rng, N_MC)
    mu = np.cos(np.radians(THETA_GRID))
    exact = tau * (1 - tau / 2) / (2 * np.maximum(mu, tau))
    assert np.all(np.abs(mean - exact[:, None]) <= N_SIGMA * err + 1e-6)
    assert np.all(mean - N_SIGMA * err <= 0.5)


def test07_grazing_and_backfacing_finite(cl_env, rng):
    n = 400
    graze = with_cos(np.repeat([0.0, 1e-8, 1e-30, 1e-3], n // 4), 2 * np.pi * rng.random(n))
    other = hemisphere(rng, n)
    below = other * (1.0, 1.0, -1.0)
    for wo, wi in [(graze, other), (other, graze), (graze, graze[::-1]),
                   (below, other), (other, below), (below, below)]:
        f = evaluate(asperity.MODEL, wo, wi, env=cl_env)
        assert np.all(np.isfinite(f)) and np.all(f >= 0)
        on_or_below = (wo[:, 2] <= 0) | (wi[:, 2] <= 0)
        assert np.all(f[on_or_below] == 0) and np.all(f[~on_or_below] > 0)
        assert f.max() <= 1 / (4 * np.pi * 0.05) * (1 + RTOL_F32)
