"""Fresnel and diffusion closed forms used on the host (docs/science.md §3).

The kernel-side versions of the same formulas live in ``cl/optics.h``; the tests compare them.
``eta`` is always the relative index n_inside / n_outside.
"""
from __future__ import annotations

import numpy as np

__all__ = ["fresnel_diffuse_reflectance", "diffusion_A", "dipole_Rd", "fresnel_transmittance",
           "diffuse_fresnel_external", "fresnel_normal", "fresnel_reflectance_inside",
           "fresnel_moments", "diffusion_boundary"]


def fresnel_diffuse_reflectance(eta: float) -> float:
    """Fdr(eta), the diffuse Fresnel reflectance seen from inside the medium.

    Egan & Hilgeman's polynomial fits as quoted by Jensen et al. 2001 (eta >= 1) and its
    companion fit for eta < 1 (docs/science.md §3; same as ``cl/optics.h``).
    """
    if eta >= 1.0:
        return -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    return -0.4399 + 0.7099 / eta - 0.3319 / eta**2 + 0.0636 / eta**3


def diffusion_A(eta: float) -> float:
    """Boundary mismatch factor A = (1 + Fdr) / (1 - Fdr) of the diffusion boundary condition."""
    f = fresnel_diffuse_reflectance(eta)
    return (1.0 + f) / (1.0 - f)


def dipole_Rd(sigma_a, sigma_s_prime, eta) -> np.ndarray:
    """Total diffuse reflectance of a semi-infinite medium, Jensen et al. 2001 dipole (eq. 5 form).

    Rd = a'/2 (1 + exp(-4/3 A sqrt(3 (1 - a')))) exp(-sqrt(3 (1 - a'))), a' = s'/(s' + a).
    Inputs are scalars or (3,) arrays in 1/mm; returns float64.
    """
    sa = np.asarray(sigma_a, dtype=np.float64)
    ssp = np.asarray(sigma_s_prime, dtype=np.float64)
    alpha = ssp / (sa + ssp)
    q = np.sqrt(3.0 * (1.0 - alpha))
    return 0.5 * alpha * (1.0 + np.exp(-4.0 / 3.0 * diffusion_A(float(eta)) * q)) * np.exp(-q)


def fresnel_transmittance(cos_o: np.ndarray, eta: float) -> np.ndarray:
    """Unpolarised Fresnel transmittance 1 - F across a smooth boundary at outside cosine cos_o
    (float64 host version of ``cl/optics.h`` fresnel_dielectric); 0 where cos_o <= 0."""
    c = np.clip(np.asarray(cos_o, np.float64), 0.0, 1.0)
    ct = np.sqrt(np.maximum(eta * eta - 1.0 + c * c, 0.0)) / eta
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = (c - eta * ct) / (c + eta * ct)
        rp = (eta * c - ct) / (eta * c + ct)
    f = 0.5 * (rs * rs + rp * rp)
    return np.where(c > 0, 1.0 - np.nan_to_num(f, nan=1.0), 0.0)


def diffuse_fresnel_external(eta: float, n: int = 4096) -> float:
    """Cosine-weighted hemispherical mean of the Fresnel reflectance seen from outside,
    int F(mu) 2 mu dmu (midpoint rule; 4096 steps is exact to < 1e-6)."""
    mu = (np.arange(n) + 0.5) / n
    return float(np.sum((1.0 - fresnel_transmittance(mu, eta)) * 2 * mu) / n)


def fresnel_normal(eta: float) -> float:
    """Fresnel reflectance at normal incidence, ((eta - 1) / (eta + 1))^2 (either side)."""
    return ((eta - 1.0) / (eta + 1.0)) ** 2


def fresnel_reflectance_inside(mu: np.ndarray, eta: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance F(mu) seen from inside a medium of relative index
    ``eta`` at inside cosine ``mu`` (1 beyond the critical angle; 0 everywhere at eta = 1):
    light going out sees the outside medium at relative index 1/eta."""
    return np.zeros_like(mu) if eta == 1.0 else 1.0 - fresnel_transmittance(mu, 1.0 / eta)


def fresnel_moments(eta: float, n: int = 20000) -> tuple[float, float]:
    """Fresnel moments seen from inside, C1 = int_0^1 F(mu) mu dmu and C2 = int_0^1 F(mu) mu^2 dmu.

    ``eta`` = n_inside / n_outside and mu is the cosine inside; F = 1 beyond the critical
    angle.  2 C1 is the diffuse Fresnel reflectance from inside (the quantity Fdr fits).
    Midpoint rule: the integrand has one kink (the critical angle), so 20000 steps are
    exact to ~1e-8.  (d'Eon 2012, "A better dipole", eqs. 4-6; docs/profiles.md.)
    """
    if eta == 1.0:
        return 0.0, 0.0
    mu = (np.arange(n) + 0.5) / n
    F = fresnel_reflectance_inside(mu, eta)
    return float(np.sum(F * mu) / n), float(np.sum(F * mu * mu) / n)


def diffusion_boundary(eta: float) -> tuple[float, float, float]:
    """(A, C_phi, C_E) of the partial-current boundary from the Fresnel moments (d'Eon 2012).

    A = (1 + 3 C2) / (1 - 2 C1) sets the extrapolation distance z_b = 2 A D; the radiant
    exitance through the boundary is C_phi phi + C_E J_n with C_phi = (1 - 2 C1) / 4 and
    C_E = (1 - 3 C2) / 2 (phi the fluence, J_n the diffusive flux along the outward normal).
    At eta = 1: A = 1, C_phi = 1/4, C_E = 1/2 (the outgoing partial current).
    """
    c1, c2 = fresnel_moments(eta)
    return (1.0 + 3.0 * c2) / (1.0 - 2.0 * c1), 0.25 * (1.0 - 2.0 * c1), 0.5 * (1.0 - 3.0 * c2)
