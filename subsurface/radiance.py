"""Outgoing radiance from the BSSRDF's radiant exitance: the Fresnel exit (docs/science.md §4).

The exitance M_o (``subsurface/exitance.py``) leaves through the surface weighted by the
Fresnel transmittance towards the eye, normalised so that the radiance integrates back to
M_o over the hemisphere (Jensen et al. 2001's S ~ Ft(wo) Rd / pi); the skin texture either
replaces the profile's Rd or tints it.
"""
from __future__ import annotations

import numpy as np

from dermis.optics.fresnel import diffuse_fresnel_external, fresnel_transmittance
from dermis.pipeline.errors import DermisError
from dermis.optics.transmittance import Transmittance

__all__ = ["exitance_to_radiance"]


def exitance_to_radiance(M: np.ndarray, cos_o: np.ndarray, eta: float, *,
                         albedo: np.ndarray | None = None, albedo_mode: str = "replace",
                         rd: np.ndarray | None = None, mode: str = "fresnel",
                         transmittance: "Transmittance | None" = None) -> np.ndarray:
    """Outgoing radiance from radiant exitance (energy-conserving Fresnel weighting).

    Parameters
    ----------
    M : (Q, 3) float ndarray
        Radiant exitance (``subsurface/exitance.py``).
    cos_o : (Q,) float ndarray
        Cosine between the shading normal and the direction to the eye.
    eta : float
        Relative index of refraction of the top layer (inside / outside).
    albedo : (Q, 3) float ndarray, optional
        Linear albedo from the texture at each query point.
    albedo_mode : {"replace", "modulate"}
        "replace" (default): the texture is the total diffuse reflectance and the profile
        only shapes the blur: M -> M * albedo / Rd (needs ``rd``); a flat slab of uniform
        texture a then reflects exactly a E, as the BRDF models with rho_d = a do.
        "modulate": M -> M * albedo (the texture tints the profile's own colour).
    rd : (3,) float ndarray, optional
        The profile's Rd (needed by "replace").
    mode : {"fresnel", "lambert"}
        "fresnel": L = Ft(cos_o) M / (pi (1 - Fdr_ext(eta))), Ft = 1 - F; the divisor makes
        int L cos dw = M exactly (Jensen 2001's S ~ Ft(wo) Rd / pi, normalised).
        "lambert": L = M / pi.
    transmittance : Transmittance, optional
        ("fresnel" mode) The exit weight T(cos_o) / (pi T_mean) per channel, with T the same
        transmittance the entry applied (:class:`Transmittance`; with the surface term it is
        min(Ft, 1 - L_lobes)); int L cos dw = M still holds exactly.  None: Ft(cos_o) /
        (pi (1 - Fdr_ext(eta))).

    Returns
    -------
    (Q, 3) float32 ndarray; 0 where cos_o <= 0; never NaN.
    """
    M = np.asarray(M, np.float64)
    if albedo is not None:
        alb = np.asarray(albedo, np.float64)
        if albedo_mode == "replace":
            if rd is None:
                raise DermisError("gather: albedo_mode 'replace' needs the profile's Rd")
            rdv = np.asarray(rd, np.float64)
            M = M * np.where(rdv > 0, alb / np.where(rdv > 0, rdv, 1.0), 0.0)
        elif albedo_mode == "modulate":
            M = M * alb
        else:
            raise DermisError(f"gather: albedo_mode = {albedo_mode!r}: must be 'replace' or "
                              "'modulate'")
    c = np.asarray(cos_o, np.float64)
    if mode == "fresnel" and transmittance is not None:
        w = transmittance(c) / (np.pi * transmittance.mean)[None, :]
    elif mode == "fresnel":
        w = (fresnel_transmittance(c, eta) / (np.pi * (1.0 - diffuse_fresnel_external(eta))))[:, None]
    elif mode == "lambert":
        w = np.where(c > 0, 1.0 / np.pi, 0.0)[:, None]
    else:
        raise DermisError(f"gather: mode = {mode!r}: must be 'fresnel' or 'lambert'")
    out = np.nan_to_num(M * w, nan=0.0, posinf=0.0, neginf=0.0)
    # a finite float64 beyond float32's range (M * albedo / Rd with Rd ~ 1e-308) would cast to inf
    return np.minimum(out, np.finfo(np.float32).max).astype(np.float32)
