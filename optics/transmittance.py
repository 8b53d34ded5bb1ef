"""Transmittance of the skin's surface (docs/science.md §4): the fraction of light that
enters at cosine mu (the irradiance stage weights every light sample by it) and, by
reciprocity, leaves (the BSSRDF's exit weight): smooth-dielectric Fresnel, capped by what the
BSSRDF's surface term (the Lafortune lobes, ``models/lafortune.py``) already reflects.
"""
from __future__ import annotations

import numpy as np

from dermis.models.lafortune import LAFORTUNE_ALBEDO_NODES, LafortuneParams, lobe_albedo_table
from dermis.optics.fresnel import fresnel_transmittance
from dermis.pipeline.errors import ConfigError

__all__ = ["Transmittance"]


class Transmittance:
    """The fraction of light that crosses the skin's surface at cosine mu, per channel:
    entering (the irradiance stage applies it per light sample) and, by reciprocity,
    leaving (the BSSRDF's exit weight, ``subsurface/radiance.py exitance_to_radiance``).

    T(mu) = Ft(mu; eta), the smooth-dielectric Fresnel transmittance, or with the BSSRDF's
    surface term (``surface_reflection = "lafortune_lobes"``) min(Ft(mu), 1 - L(mu)), L the
    lobes' directional albedo (:func:`lafortune_lobe_albedo`): light the surface term
    already reflects cannot also enter, so surface + subsurface reflect L(mu) + a T(mu) <= 1
    for any albedo a <= 1.  The skin fit's lobes reflect more than a smooth surface below
    ~55 deg (eta 1.4) or ~62 deg (eta 1.3): L = 0.031 at normal incidence against
    F = 0.028 / 0.017, so the cap lowers T_mean by 0.3 % / 1.5 %.  ``mean`` =
    int T 2 mu dmu normalises the exit (docs/science.md §4).
    """

    _TABLES: dict = {}
    N = 2049
    LOOKUP = 1 << 16

    def __init__(self, eta: float, surface_reflection: str = "none"):
        if surface_reflection not in ("none", "lafortune_lobes"):
            raise ConfigError(f"surface_reflection = {surface_reflection!r}: must be "
                              "'none' or 'lafortune_lobes'")
        self.eta = float(eta)
        self.surface_reflection = surface_reflection
        key = (self.eta, surface_reflection)
        if key not in self._TABLES:
            mu = np.linspace(0.0, 1.0, self.N)
            t = np.repeat(fresnel_transmittance(mu, self.eta)[:, None], 3, axis=1)
            if surface_reflection == "lafortune_lobes":
                lob, _ = lobe_albedo_table(LafortuneParams())
                nodes = np.linspace(0.0, 1.0, LAFORTUNE_ALBEDO_NODES)
                lob = np.stack([np.interp(mu, nodes, lob[:, c]) for c in range(3)], axis=1)
                t = np.minimum(t, 1.0 - lob)
            mid = (np.arange(4096) + 0.5) / 4096
            tm = np.stack([np.interp(mid, mu, t[:, c]) for c in range(3)], axis=1)
            self._TABLES[key] = (mu, t, (tm * 2.0 * mid[:, None]).sum(axis=0) / 4096)
        self._mu, self._t, self.mean = self._TABLES[key]
        fine = np.linspace(0.0, 1.0, self.LOOKUP + 1)
        self._fine = np.stack([np.interp(fine, self._mu, self._t[:, k]) for k in range(3)],
                              axis=1).astype(np.float32)
        self._fine[0] = 0.0   # cos <= 0 (clipped to 0): nothing crosses

    def __call__(self, cos) -> np.ndarray:
        """(..., 3) float32 T at cosines ``cos`` (0 where cos <= 0): the nearest of
        ``LOOKUP`` + 1 uniform cosines (the irradiance pass applies it to ~16M light samples
        per mesh and light; error < 3e-5 at grazing, where T rises steepest, ~1e-6 elsewhere)."""
        c = np.asarray(cos, np.float32)
        x = np.clip(c.ravel(), 0.0, 1.0)
        x *= np.float32(self.LOOKUP)
        x += np.float32(0.5)
        return self._fine.take(x.astype(np.intp), axis=0).reshape(c.shape + (3,))

    def __repr__(self) -> str:
        return f"Transmittance(eta={self.eta}, surface_reflection={self.surface_reflection!r})"
