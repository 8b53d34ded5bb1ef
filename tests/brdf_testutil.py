"""Direction sampling and Monte Carlo helpers shared by the reflectance-model tests."""
from __future__ import annotations

import numpy as np


def hemisphere(rng, n: int) -> np.ndarray:
    """(n, 3) float64 directions uniform on the upper hemisphere."""
    z = rng.random(n)
    phi = 2 * np.pi * rng.random(n)
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def with_cos(cos_theta, phi) -> np.ndarray:
    """(n, 3) float64 unit directions with the given cosines and azimuths."""
    cos_theta = np.asarray(cos_theta, np.float64)
    s = np.sqrt(np.maximum(0.0, 1 - cos_theta ** 2))
    return np.stack([s * np.cos(phi), s * np.sin(phi), cos_theta], axis=1)


def sample_pairs(rng, n: int = 10_000) -> tuple[np.ndarray, np.ndarray]:
    """Seeded (wo, wi) float32 pairs: 80 % uniform, 20 % with one or both cosines grazing
    (log-uniform in [1e-6, 1e-1]), plus normal incidence and mirror/retro configurations."""
    wo = hemisphere(rng, n)
    wi = hemisphere(rng, n)
    k = n // 10
    graze = 10.0 ** rng.uniform(-6, -1, size=(2, k))
    wo[:k] = with_cos(graze[0], 2 * np.pi * rng.random(k))
    wi[k:2 * k] = with_cos(graze[1], 2 * np.pi * rng.random(k))
    wo[2 * k:2 * k + 10] = wi[2 * k:2 * k + 10] = (0.0, 0.0, 1.0)
    m = slice(2 * k + 10, 2 * k + 200)                  # mirror pairs (specular lobes)
    wo[m] = wi[m] * (-1.0, -1.0, 1.0)
    r = slice(2 * k + 200, 2 * k + 400)                 # retro-reflection pairs
    wo[r] = wi[r]
    return wo.astype(np.float32), wi.astype(np.float32)


def cosine_hemisphere(rng, n: int) -> np.ndarray:
    """(n, 3) float64 directions with pdf cos(theta)/pi (Malley's method)."""
    r = np.sqrt(rng.random(n))
    phi = 2 * np.pi * rng.random(n)
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0, 1 - r * r))], 1)


def mc_albedo(eval_f, theta_o_deg, rng, n: int = 1 << 16):
    """Monte Carlo directional albedo a(theta_o) = integral f cos dw_i per channel.

    ``eval_f(wo, wi) -> (N, 3) f``; returns (mean, standard error), each (len(theta), 3).
    Cosine-weighted sampling: the estimator is pi * f.
    """
    theta = np.radians(np.asarray(theta_o_deg, np.float64))
    wi = cosine_hemisphere(rng, n)
    wo_all, wi_all = [], []
    for t in theta:
        wo_all.append(np.broadcast_to([np.sin(t), 0.0, np.cos(t)], (n, 3)))
        wi_all.append(wi)
    f = eval_f(np.concatenate(wo_all).astype(np.float32),
               np.concatenate(wi_all).astype(np.float32)).astype(np.float64)
    est = (np.pi * f).reshape(len(theta), n, 3)
    return est.mean(axis=1), est.std(axis=1) / np.sqrt(n)
