"""Radial diffuse reflectance/transmittance profiles of a layer stack (the "layer file").

Two profile models produce the same :class:`~dermis.pipeline.artifacts.LayerProfile`
(``build_profiles(stack, model=...)``; docs/profiles.md has the measurements):

* ``"multipole"``: diffusion per layer in float64 on the host for the radial shapes
  (:mod:`dermis.optics.multipole`), layers combined by the adding equations in frequency
  space (:mod:`dermis.optics.layer_convolution`), every total set to the exact
  plane-parallel radiative-transfer value (adding-doubling,
  :mod:`dermis.optics.adding_doubling`).
* ``"monte_carlo"``: R(r), T(r) tabulated from the OpenCL layered Monte Carlo
  (:mod:`dermis.optics.monte_carlo_table`) for the stack itself, with per-ring standard
  errors and radial splitting for the far rings.

Both tables follow :mod:`dermis.optics.layer_file` (rings, units, cut-off radius, negative
lobes).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from dermis.pipeline.artifacts import LayerProfile
from dermis.pipeline.errors import DermisError
from dermis.optics.adding_doubling import exact_totals
from dermis.optics.layer_convolution import combine_layers
from dermis.optics.layer_file import RD_CONVENTION, NegativeLobes, auto_grid, finish_table
from dermis.optics.layers import (LayerStack, PROFILE_MODELS, DEFAULT_MC_PHOTONS,
                                   DEFAULT_MC_SEED)
from dermis.optics.monte_carlo_table import monte_carlo_profiles
from dermis.optics.multipole import (DEFAULT_POLES, NQ_BEAM, check_diffusion,
                                     diffusion_constants, direct_parts, evaluate_terms,
                                     layer_response, relative_indices, scaled_to_exact)

__all__ = ["build_profiles", "MultipoleOptions"]


@dataclass(frozen=True)
class MultipoleOptions:
    """Numerical options of the multipole model (the defaults build the stage's layer file)."""

    poles: int | None = None
    """n in the pole pairs i = -n..n per finite layer (None: adaptive,
    :func:`dermis.optics.multipole.diffusion_constants`)."""
    grid: tuple[float, float] | None = None
    """(spacing h, half-width r_max) in mm of the radial table and of the 2-D FFT grid
    (which is 2 r_max wide with x2 zero padding); None: from the stack's mean free paths and
    sigma_tr (:func:`dermis.optics.layer_file.auto_grid`)."""
    force_fft: bool = False
    """Route a single layer through the FFT combination too (tests the transform path); by
    default a single layer is tabulated directly from the closed forms."""
    diffusion: str = "pbd"
    """Per-layer diffusion model, "pbd" or "dj2005" (dermis <= 1's;
    :mod:`dermis.optics.multipole`)."""
    nq: int = NQ_BEAM
    """Beam quadrature nodes per layer and channel ("pbd")."""
    totals: str = "transport"
    """"transport": every energy (per layer, per kind of incident light, and of the whole
    stack) is set to the exact plane-parallel radiative-transfer value (adding-doubling),
    diffusion supplying the radial shapes; "diffusion": diffusion's own totals (to measure
    its error).  "dj2005" always uses its own."""


def build_profiles(stack: LayerStack, *, model: str = "multipole",
                   options: MultipoleOptions = MultipoleOptions(),
                   photons: int = DEFAULT_MC_PHOTONS, seed: int = DEFAULT_MC_SEED, env=None,
                   progress=None) -> LayerProfile:
    """Build the layer file of ``stack``: radial R(r), T(r) per channel and totals.

    Parameters
    ----------
    stack : LayerStack
        Validated layers, top to bottom (see :mod:`dermis.optics.layers`).
    model : {"multipole", "monte_carlo"}
        Diffusion (layers added in frequency space) or the Monte Carlo table
        (:func:`~dermis.optics.monte_carlo_table.monte_carlo_profiles`; uses ``photons``,
        ``seed``, ``env``).
    options : MultipoleOptions
        Poles, grid, per-layer diffusion model, beam nodes and totals of the "multipole"
        model (the defaults are the stage's).
    photons, seed, env, progress
        Monte Carlo photons per channel, seed, OpenCL env, progress callback
        ("monte_carlo").

    Returns
    -------
    LayerProfile
        r_mm (N,); R, T (N, 3) ring averages in 1/mm^2; Rd, Tt (3,) totals per entered
        photon (``RD_CONVENTION``) including energy beyond the table and the collimated
        transmission; cutoff_mm (3,), the smallest r_k holding 99.9 % of Rd;
        energy_beyond_cutoff (3,).  ``info`` holds the model, the stack, poles, grid,
        T_ballistic (unscattered) and T_forward, the negative lobes removed (with where and
        how much energy), the most negative value relative to the peak before removal
        (``min_clipped_rel``) and the build time.

    References
    ----------
    Donner, C., Jensen, H. W. (2005). Light diffusion in multi-layered translucent
    materials. ACM TOG 24(3), 1032-1039. doi:10.1145/1073204.1073308
    d'Eon, E. (2012). A better dipole. Technical report.
    Habel, R., Christensen, P. H., Jarosz, W. (2013). Photon beam diffusion: a hybrid Monte
    Carlo method for subsurface scattering. Computer Graphics Forum 32(4).
    doi:10.1111/cgf.12148
    """
    if model not in PROFILE_MODELS:
        raise DermisError(f"profiles: model = {model!r}: must be one of "
                          + ", ".join(repr(m) for m in PROFILE_MODELS))
    if model == "monte_carlo":
        return monte_carlo_profiles(stack, photons=photons, seed=seed, env=env,
                                    progress=progress)
    poles, grid, force_fft = options.poles, options.grid, options.force_fft
    diffusion, nq, totals = options.diffusion, options.nq, options.totals
    check_diffusion(diffusion)
    t0 = time.perf_counter()
    poles = DEFAULT_POLES if poles is None else int(poles)
    if poles is not None and poles < 0:
        raise DermisError(f"profiles: poles = {poles}: must be >= 0")
    full = stack
    stack = stack.nonzero()
    if not stack.layers:
        raise DermisError("profiles: every layer has thickness 0; nothing to profile")
    h, r_max = grid if grid is not None else auto_grid(stack)
    if not (h > 0 and r_max > h and math.isfinite(h) and math.isfinite(r_max)):
        raise DermisError(f"profiles: grid = ({h}, {r_max}) (mm): need 0 < spacing < half-width")
    n = int(math.ceil(r_max / h))
    if n > 8192:
        raise DermisError(f"profiles: grid = ({h}, {r_max}) (mm) needs {n} points per half-width;"
                          " at most 8192 are allowed (use a coarser spacing)")
    r_out = np.arange(n + 1) * h
    edges = np.concatenate([[0.0], (np.arange(n + 1) + 0.5) * h])
    ring_area = np.pi * np.diff(edges**2)

    info = {"model": "multipole", "diffusion": diffusion, "layers": full.to_dict(),
            "poles": poles, "nq": nq, "grid_h_mm": h, "grid_rmax_mm": n * h,
            "convention": RD_CONVENTION}
    lobes = NegativeLobes()
    chans = [[diffusion_constants(lay, c, *relative_indices(stack, k), diffusion, poles)
              for c in range(3)] for k, lay in enumerate(stack.layers)]
    info["poles_used"] = [[ch.poles for ch in row] for row in chans]
    if totals not in ("transport", "diffusion"):
        raise DermisError(f"profiles: totals = {totals!r}: must be 'transport' or 'diffusion'")
    use_exact = totals == "transport" and diffusion == "pbd"
    exact = exact_stack = None
    if use_exact:
        # exact plane-parallel totals per layer (with its neighbours' indices) and, when
        # every layer has the same eta, of the whole stack
        exact = [[exact_totals([lay], c, *relative_indices(stack, k)) for c in range(3)]
                 for k, lay in enumerate(stack.layers)]
        if len(stack.layers) > 1 and len({l.eta for l in stack.layers}) == 1:
            eta = stack.layers[0].eta
            exact_stack = [exact_totals(stack.layers, c, eta / stack.eta_above,
                                        eta / stack.eta_below) for c in range(3)]
            info["stack_totals"] = "adding-doubling of the whole stack"
        elif len(stack.layers) > 1:
            info["stack_totals"] = ("adding of the exact layer totals (layers of different eta: "
                                    "no whole-stack solution)")
    info["totals"] = totals if diffusion == "pbd" else "diffusion"
    scales: list = []
    if len(stack.layers) == 1 and not force_fft:
        R = np.zeros((n + 1, 3))
        T = np.zeros((n + 1, 3))
        Rd, Tt, bal, fwd, dropped = (np.zeros(3) for _ in range(5))
        for c in range(3):
            resp = layer_response(chans[0][c], nq)
            ex = exact[0][c] if exact is not None else None
            Rf, Rdl, Tf, Tdl, sc = scaled_to_exact(resp, ex and ex.Rc, ex and ex.Tc, False,
                                                   ex and ex.Tu)
            scales.append(dict(layer=0, channel="RGB"[c], light="collimated", **sc))
            for key, terms, out, total in (("R", resp.terms_R, R, Rf), ("T", resp.terms_T, T, Tf)):
                if not terms:
                    continue
                vals = np.diff(evaluate_terms(terms, "energy", edges)) / ring_area
                energy = float(np.sum(vals * ring_area))
                vals = lobes.fix(vals, ring_area, r_out,
                                 {"layer": 0, "field": key, "channel": "RGB"[c]})
                # the table's energy: the closed-form total (scaled) minus what lies beyond
                full_e = float(np.sum(vals * ring_area))
                want = (total / (resp.Rd if key == "R" else resp.Td)) * energy \
                    if (resp.Rd if key == "R" else resp.Td) > 0 else 0.0
                out[:, c] = vals * (want / full_e) if full_e > 0 else vals
            # the direct light: the unscattered beam at r = 0, the rest where it lands
            Rp, Rs, Tp, Ts = direct_parts(resp, Rdl, Tdl, False, ex and ex.Tu)
            R[0, c] += Rp / ring_area[0]
            T[0, c] += Tp / ring_area[0]
            for out, spread in ((R, Rs), (T, Ts)):
                if spread is not None:
                    out[:, c] += np.diff(spread.energy(edges)) / ring_area
            Rd[c] = Rf + Rdl
            Tt[c] = Tf + Tdl
            bal[c] = resp.ballistic if ex is None else ex.Tu
            fwd[c], dropped[c] = Tdl - bal[c], resp.dropped
        info["method"] = "closed form (single layer)"
    else:
        R, T, Rd, Tt, bal, fwd, dropped = combine_layers(stack, chans, nq, h, n, lobes, exact,
                                                         exact_stack, scales)
        info["method"] = "fft adding (dctn type 1 on the even quadrant)"
    # exact / diffusion totals per layer, light and channel: the diffusion's own error
    info["scale_to_exact"] = scales if use_exact else []
    info["T_ballistic"] = bal.tolist()
    info["T_forward"] = fwd.tolist()
    info["fresnel_second_order_dropped"] = dropped.tolist()
    info["negative_lobes"] = lobes.items
    info["min_clipped_rel"] = lobes.min_rel
    prof = finish_table(r_out, R, T, Rd, Tt, ring_area, info)
    prof.info["seconds"] = time.perf_counter() - t0
    return prof
