"""Float64 NumPy references of the three local reflectance models, used only by the tests.

Written from the formulas (angles, not the kernels' vector algebra) to check the OpenCL
``<model>_eval`` kernels of ``models/``.  Conventions as there: local shading
frame with z along the shading normal, ``wo`` and ``wi`` unit vectors pointing away from the
surface, f excludes the cosine, RGB linear.  HK93's single-scattering term is the
pipeline's own float64 function (``models/hk93.py _hk93_single_np``: HK93Params derives its
constant multiple-scattering albedo from it), so it is imported rather than copied.
"""
from __future__ import annotations

import numpy as np

from dermis.models.asperity import AsperityParams
from dermis.models.hk93 import HK93Params, _angles, _hk93_single_np
from dermis.models.lafortune import LafortuneParams

__all__ = ["lafortune_f_np", "hk93_f_np", "asperity_f_np"]


def lafortune_f_np(wo, wi, params: LafortuneParams | None = None, albedo=None) -> np.ndarray:
    """Float64 Lafortune BRDF (N, 3): rho/pi + sum_k max(0, Cxy sin sin cos(dphi) + Cz cos cos)^n
    (docs/science.md §1); with ``params.coupled`` the diffuse term is
    rho (1 - L(cos_i)) (1 - L(cos_o)) / (pi (1 - L_mean)), L read from the packed table
    and interpolated linearly as the kernel does (the table itself is checked against the
    quadrature in tests/test_energy.py)."""
    params = params or LafortuneParams()
    co, so, po = _angles(wo)
    ci, si, pi_ = _angles(wi)
    n = co.shape[0]
    rho = np.broadcast_to(np.asarray(params.rho_d if albedo is None else albedo, np.float64),
                          (n, 3))
    horizontal = (so * si * np.cos(po - pi_))[:, None]
    vertical = (co * ci)[:, None]
    f = rho / np.pi
    if params.coupled:
        packed = params.pack().astype(np.float64)
        table = packed[31:].reshape(-1, 3)
        nodes = np.linspace(0.0, 1.0, len(table))

        def unreflected(mu):
            m = np.clip(mu, 0.0, 1.0)
            return 1.0 - np.stack([np.interp(m, nodes, table[:, c]) for c in range(3)], 1)
        f = f * unreflected(ci) * unreflected(co) * packed[28:31]
    for k in range(3):
        base = params.cxy[k] * horizontal + params.cz[k] * vertical
        f = f + np.where(base > 0, np.abs(base) ** params.n[k], 0.0)
    front = (co > 0) & (ci > 0)
    return np.where(front[:, None], f, 0.0)


def hk93_f_np(wo, wi, params: HK93Params | None = None) -> np.ndarray:
    """Float64 HK93 BRDF (N, 3): single scattering per layer + rho_ms/pi (docs/science.md §2).

    Walks the stack top-down: the beam refracts by Snell (sin theta_k = sin theta_0 / eta_k),
    loses the Fresnel transmittance of each interface in both directions and exp(-tau/cos)
    of each layer above, and each layer adds W HG / (eta^2 (cos_i + cos_o))
    (1 - exp(-tau (1/cos_i + 1/cos_o))).  Scattering angles from 3-D refracted vectors.
    """
    params = params or HK93Params()
    f = _hk93_single_np(wo, wi, params.layers) + params.multiple_scattering / np.pi
    front = (np.asarray(wo)[:, 2] > 0) & (np.asarray(wi)[:, 2] > 0)
    return np.where(front[:, None], f, 0.0)


def asperity_f_np(wo, wi, params: AsperityParams | None = None) -> np.ndarray:
    """Float64 asperity term (N, 3): albedo Delta / (4 pi lambda max(cos_i, tau) max(cos_o, tau))
    (docs/science.md §5)."""
    params = params or AsperityParams()
    co = np.asarray(wo, np.float64)[:, 2]
    ci = np.asarray(wi, np.float64)[:, 2]
    tau = params.delta_mm / params.lambda_mm
    f = params.albedo * (params.delta_mm / (4 * np.pi * params.lambda_mm
                                            * np.maximum(co, tau) * np.maximum(ci, tau)))[:, None]
    f = np.minimum(f, params.f_max)
    return np.where(((co > 0) & (ci > 0))[:, None], f, 0.0)
