"""The single layer that reflects what a layer stack reflects: the stack's layering removed,
its total diffuse reflectance kept (docs/science.md §8, the "layering" effect).

One semi-infinite layer with the top layer's refractive index (the boundary the light
crosses) and the deepest layer's reduced scattering and anisotropy (the bulk most diffuse
light travels in); its absorption is fitted per channel so that the multipole profile of
the single layer has the stack's total diffuse reflectance Rd.  Rd of a semi-infinite
medium falls monotonically as absorption rises (more absorption, less light returns), so
bisection on log sigma_a converges to any Rd between the two ends of the bracket.  Comparing
the BSSRDF over this profile with the BSSRDF over the stack's isolates what the layering
changes -- the profile's shape and colour at equal total reflectance -- from the total.
"""
from __future__ import annotations

import math

import numpy as np

from dermis.optics.layers import Layer, LayerStack

__all__ = ["single_layer_equivalent", "RD_TOLERANCE"]

# relative tolerance on Rd per channel (bisection stops below it): well under the 1 %
# effect threshold of the requirement table ([report] effect_threshold)
RD_TOLERANCE = 1e-4
_SIGMA_A_RANGE = (1e-6, 1e3)     # 1/mm: Rd -> its no-absorption limit .. ~0


def _rd(layer: Layer, stack: LayerStack) -> np.ndarray:
    from dermis.optics.layer_profiles import build_profiles
    single = LayerStack((layer,), stack.eta_above, stack.eta_below)
    return np.asarray(build_profiles(single).Rd, np.float64)


def single_layer_equivalent(stack: LayerStack, rd_target) -> tuple[LayerStack, dict]:
    """(the single-layer stack, info) whose multipole Rd equals ``rd_target`` (the stack's
    Rd per channel, as its profile reports it) within :data:`RD_TOLERANCE`.

    Raises ValueError where no absorption reaches the target (above the no-absorption
    limit, or not positive)."""
    top, bulk = stack.layers[0], stack.layers[-1]
    target = np.asarray(rd_target, np.float64)
    lo = np.full(3, math.log(_SIGMA_A_RANGE[0]))
    hi = np.full(3, math.log(_SIGMA_A_RANGE[1]))

    def layer(log_a):
        return Layer(math.inf, top.eta, tuple(float(math.exp(v)) for v in log_a),
                     bulk.sigma_s_prime, bulk.g)
    r_lo, r_hi = _rd(layer(lo), stack), _rd(layer(hi), stack)
    if np.any(target >= r_lo) or np.any(target <= r_hi):
        raise ValueError(f"Rd {target.tolist()} is outside what one layer with eta "
                         f"{top.eta} and sigma_s' {bulk.sigma_s_prime} reflects "
                         f"({r_hi.tolist()} .. {r_lo.tolist()})")
    steps = 0
    while True:
        mid = (lo + hi) / 2.0
        r = _rd(layer(mid), stack)
        steps += 1
        if np.all(np.abs(r / target - 1.0) < RD_TOLERANCE) or steps >= 60:
            break
        high = r > target            # too bright: more absorption
        lo = np.where(high, mid, lo)
        hi = np.where(high, hi, mid)
    out = LayerStack((layer(mid),), stack.eta_above, stack.eta_below)
    return out, {"steps": steps, "Rd": r.tolist(), "Rd_target": target.tolist(),
                 "sigma_a": list(out.layers[0].sigma_a)}
