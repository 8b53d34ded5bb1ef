"""The near field of the BSSRDF: the profile split at the points' resolution, and the
boundary-integral table of its near part (docs/science.md §4 "Near field").

The optics-resolved BSSRDF.  The points reconstruct irradiance at the resolution sigma of
their spacing, far coarser than the skin's profile (two_layer: half of Rd within 0.17-0.5 mm,
sigma 1.24 mm at the default density), so the gather alone blurs the image by sigma.  The
profile is split by a smooth window w(r) (1 inside NEAR_INNER sigma, a raised cosine down to
0 at NEAR_OUTER sigma): the far part R (1 - w) is smooth at the points' resolution and is
gathered from them (``subsurface/gather.py``; blurred by sigma: the knife-edge error of that
is <= 1.1 % of Rd at these radii), and the near part R w is evaluated at each shading point.
For point and directional lights (one sample per point: every point and pixel sees the same
shadow curve) the near part is exact: M_near(x) = C(x) [Rd_near V(x) - sum over the shadow
edges within NEAR_OUTER sigma of a boundary integral], with C(x) the light's entering
irradiance at the shading point unshadowed, V(x) its shadow ray, and the edges located
between the points by bisection (``subsurface/shadow_edges.py``; which side of the shadow
curve x lies on comes from V(x) alone, its distance to the curve from the edges:
``shadow_edges.near_bracket``).  Disc and environment
lights (per-point random samples: no common shadow curve) keep the points' reconstruction
for the near part too.  ``subsurface/exitance.py`` puts the parts together.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import trapezoid

__all__ = ["NEAR_INNER", "NEAR_OUTER", "SHARP_LIGHTS", "ProfileSplit", "near_window",
           "split_profile", "EdgeTable", "near_tables"]

# Window radii in sigma, measured with the knife edge (tests/test_knife_edge.py, 1.25 mm
# spacing, worst channel of skin1 / skin2): (1.5, 3.0) 1.43 / 1.18 %, (2.0, 3.5) 1.07 /
# 0.92 %, (2.0, 4.0) 0.87 / 0.75 %.  The far part's blur is the error; a wider window leaves
# more of the profile to the shading point, where (for point and directional lights) the
# unshadowed irradiance is taken at the point itself, so fine geometric shading is not
# blurred within it; (2.0, 3.5) halves the far error for 1.2x the window.
NEAR_INNER = 2.0
NEAR_OUTER = 3.5
# Light types whose near field is resolved at the shading point.
SHARP_LIGHTS = ("point", "directional")
# Boundary-integral table Q(omega, phi): omega in [0, NEAR_OUTER sigma], phi in [0, pi/2].
EDGE_TABLE_OMEGA = 512
EDGE_TABLE_PHI = 256


@dataclass
class ProfileSplit:
    """The profile split at the near-field window (:func:`split_profile`).

    near, far : profile-like objects (``r_mm``, ``R``, ``Rd``, ``cutoff_mm``) of R w and
        R (1 - w), canonical (linear in r, zero beyond each cut-off, energy-normalised)
    rd_near : (3,) energy of the near part; far.Rd = Rd - rd_near
    r_in, r_out : the window's radii, mm
    cum_near : (r (M,), m (M, 3)) cumulative energy of the near part int_0^r 2 pi s R w ds
    """

    near: object
    far: object
    rd_near: np.ndarray
    r_in: float
    r_out: float
    cum_near: tuple


@dataclass
class _PartProfile:
    r_mm: np.ndarray
    R: np.ndarray
    Rd: np.ndarray
    cutoff_mm: np.ndarray


def near_window(r: np.ndarray, r_in: float, r_out: float) -> np.ndarray:
    """w(r): 1 for r <= r_in, a raised cosine down to 0 at r_out, 0 beyond."""
    u = np.clip((np.asarray(r, np.float64) - r_in) / max(r_out - r_in, 1e-300), 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * u))


def split_profile(profile, sigma_mm: float, *, cutoff_mm: float | None = None,
                  inner: float = NEAR_INNER, outer: float = NEAR_OUTER) -> ProfileSplit:
    """Split the layer profile into near and far parts about the window at ``inner`` ..
    ``outer`` x ``sigma_mm`` (module docstring).

    The profile is first made canonical exactly as the gather integrates it: R linear in r
    on a grid 4x finer than the layer file's (and <= r_out / 1000), each channel zero beyond
    its cut-off (``profile.cutoff_mm`` or ``cutoff_mm``) and scaled so int 2 pi r R dr = Rd.
    """
    r0 = np.asarray(profile.r_mm, np.float64)
    R0 = np.asarray(profile.R, np.float64)
    rd = np.asarray(profile.Rd, np.float64)
    cut = (np.full(3, float(cutoff_mm)) if cutoff_mm is not None
           else np.asarray(profile.cutoff_mm, np.float64))
    r_in, r_out = inner * float(sigma_mm), outer * float(sigma_mm)
    top = max(float(cut.max()), r_out)
    step = min(float(np.min(np.diff(r0))) / 4.0, r_out / 1000.0)
    r = np.arange(0.0, top + 0.5 * step, step)
    R = np.stack([np.interp(r, r0, R0[:, c], right=0.0) for c in range(3)], axis=1)
    R[r[:, None] > cut[None, :]] = 0.0
    ring = 2.0 * np.pi * r[:, None] * R
    total = trapezoid(ring, r, axis=0)   # scipy's: numpy 1.26 (bpy's pin) has no np.trapezoid
    R *= np.where(total > 0, rd / np.where(total > 0, total, 1.0), 0.0)
    w = near_window(r, r_in, r_out)[:, None]
    Rn, Rf = R * w, R * (1.0 - w)
    seg = 0.5 * (2.0 * np.pi * (r[1:, None] * Rn[1:] + r[:-1, None] * Rn[:-1])) * step
    cum = np.vstack([np.zeros((1, 3)), np.cumsum(seg, axis=0)])
    rd_near = cum[-1].copy()
    near = _PartProfile(r, Rn, rd_near, np.minimum(cut, r_out))
    far = _PartProfile(r, Rf, np.maximum(rd - rd_near, 0.0), cut)
    return ProfileSplit(near, far, rd_near, r_in, r_out, (r, cum))


@dataclass
class EdgeTable:
    """Q(omega, phi) = 1/(2 pi) int_0^phi m_K(omega / cos t) dt per channel, with
    m_K(r) = Rd_near - (near energy within r): the boundary integral over a straight edge
    segment seen from a point at distance omega from its line is
    sign(w) [Q(omega, phi_2) - Q(omega, phi_1)] (:func:`near_tables`)."""

    q: np.ndarray            # (EDGE_TABLE_OMEGA + 1, EDGE_TABLE_PHI + 1, 3) float64
    d_omega: float
    d_phi: float
    rd_near: np.ndarray
    r_out: float
    mk: np.ndarray | None = None   # (EDGE_TABLE_OMEGA + 1, 3) m_K(k d_omega), for the device

    def lookup(self, omega: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Q at (omega >= 0, phi in [-pi/2, pi/2]), bilinear, odd in phi; 0 beyond r_out.
        (M, 3) float32 (the table's values are exact to float64; the lookup's rounding,
        ~1e-7 of Rd, is far below the tests' tolerance)."""
        no, nphi = self.q.shape[0] - 1, self.q.shape[1] - 1
        if getattr(self, "_flat", None) is None:
            self._flat = np.ascontiguousarray(self.q.reshape(-1, 3), np.float32)
        a = np.clip(np.asarray(omega, np.float32) * np.float32(1.0 / self.d_omega), 0, no)
        b = np.clip(np.abs(np.asarray(phi, np.float32)) * np.float32(1.0 / self.d_phi), 0, nphi)
        i = np.minimum(a.astype(np.int32), no - 1)
        j = np.minimum(b.astype(np.int32), nphi - 1)
        fa, fb = (a - i)[:, None], (b - j)[:, None]
        k = i * np.int32(nphi + 1) + j
        q = self._flat
        v00, v01 = q.take(k, axis=0), q.take(k + 1, axis=0)
        v10, v11 = q.take(k + (nphi + 1), axis=0), q.take(k + (nphi + 2), axis=0)
        v01 -= v00
        v01 *= fb
        v00 += v01          # row omega_i at phi
        v11 -= v10
        v11 *= fb
        v10 += v11          # row omega_i+1 at phi
        v10 -= v00
        v10 *= fa
        v00 += v10
        v00 *= np.sign(phi).astype(np.float32)[:, None]
        return v00


def near_tables(split: ProfileSplit) -> EdgeTable:
    """The boundary-integral table of the near part (docs/science.md §4 "Near field").

    For the lit region Omega around a shading point x, int_Omega R_near(|x - y|) dy =
    Rd_near 1_Omega(x) - int_Omega K(x - y) dy with K = Rd_near delta - R_near, and the
    divergence theorem turns the last integral into a line integral over the shadow edges of
    the field v m_K(|v|) / (2 pi |v|^2), m_K(r) = Rd_near - m_near(r): zero beyond r_out, so
    only edges within r_out of x count.  Along a straight segment at signed distance w from
    x, t = |w| tan(phi) makes the integrand sign(w) m_K(|w| / cos phi) / (2 pi) dphi.
    """
    r, cum = split.cum_near
    rd_n = split.rd_near
    no, nphi, sub = EDGE_TABLE_OMEGA, EDGE_TABLE_PHI, 4
    omega = np.linspace(0.0, split.r_out, no + 1)
    phi = np.linspace(0.0, 0.5 * np.pi, nphi * sub + 1)
    cosphi = np.cos(phi)
    q = np.zeros((no + 1, nphi + 1, 3))
    for c in range(3):
        mk_r = rd_n[c] - cum[:, c]
        with np.errstate(divide="ignore"):
            rr = omega[:, None] / cosphi[None, :]
        rr[0] = 0.0
        mk = np.interp(rr.ravel(), r, mk_r, right=0.0).reshape(rr.shape)
        mk[0, -1] = mk[0, -2]
        mk[1:, -1] = 0.0
        integ = np.concatenate([np.zeros((no + 1, 1)), np.cumsum(
            0.5 * (mk[:, 1:] + mk[:, :-1]) * (phi[1] - phi[0]), axis=1)], axis=1)
        q[:, :, c] = integ[:, ::sub] / (2.0 * np.pi)
    q[-1] = 0.0  # omega = r_out: nothing of the near part reaches past the edge line
    mk = np.stack([np.interp(omega, r, rd_n[c] - cum[:, c], right=0.0) for c in range(3)], 1)
    mk[-1] = 0.0
    return EdgeTable(q, float(omega[1] - omega[0]), float(0.5 * np.pi / nphi), rd_n,
                     split.r_out, mk)
