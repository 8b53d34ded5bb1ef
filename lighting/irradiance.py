"""The irradiance pass: irradiance E at surface points from one light or several, with
shadow rays (docs/science.md §6; thesis: 64 samples for area and environment lights), the
input of the BSSRDF's gather (stages/irradiance.py, subsurface/exitance.py).

E = sum_s V_s cos_s weights_s over the light samples of lighting/emitters.py
``sample_lights`` (V_s: 1 if the shadow ray is unoccluded, lighting/visibility.py
``Visibility.occluded``), optionally times a per-sample transmittance (the part that enters
the surface).  Points are processed in independent batches (own seed, own rows of the
result) on IRRADIANCE_THREADS threads, so the result does not depend on the thread count.

Guarded by tests/test_lights.py (directional E cos theta, shadowed), tests/test_energy.py
and tests/test_knife_edge.py.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

from dermis.lighting.emitters import SamplingOptions, check_points, sample_lights
from dermis.pipeline.errors import DermisError

__all__ = ["irradiance", "run_batches", "IRRADIANCE_THREADS"]


# Batches of the irradiance pass run on this many threads (results independent of it).
IRRADIANCE_THREADS = 2


def irradiance(points: np.ndarray, normals: np.ndarray, light,
               occlusion_fn: Callable | None, *, seed: int = 0,
               options: SamplingOptions = SamplingOptions(), chunk: int = 8192,
               transmittance: Callable | None = None) -> np.ndarray:
    """Irradiance E at surface points from one light (or a list of lights), with shadows.

    Parameters
    ----------
    points : (N, 3) float, mm
    normals : (N, 3) float, unit outward normals (also the shadow-ray offset direction)
    light : LightConfig or sequence of LightConfig
    occlusion_fn : callable or None
        ``occlusion_fn(points, normals, directions, max_distance) -> (M,) bool`` (True =
        blocked), e.g. :meth:`lighting.visibility.Visibility.occluded`; None: no shadows.
    seed : int
    options : SamplingOptions
        Samples per point for disc/environment lights (thesis: 64 for BSSRDF irradiance), a
        pre-built environment map and the environment strategy (lighting/emitters.py
        :func:`sample_lights`).
    chunk : int
        Points per batch (bounds memory to ~chunk x samples rays).  8192: the batch's
        arrays (~0.5M samples, a few MB each) stay in cache; CPU seconds at 64 samples, chunk
        65536 / 8192 / 4096, high mesh: sunset 14.7 / 13.1 / 13.9, disc 6.6 / 5.6 / 5.6; low
        mesh: sunset 13.1 / 11.7 / 11.6, disc 6.3 / 4.7 / 4.9 (bench/results/irradiance.json,
        "after", "chunk"; load 4-6).
    transmittance : callable, optional
        ``transmittance(cos) -> (..., 3)``: the fraction of each light sample that enters
        the surface at its cosine (e.g. Fresnel transmittance, ``optics/transmittance.py
        Transmittance``), applied per sample; None counts all of it (plain irradiance).

    Returns
    -------
    (N, 3) float32 irradiance E = integral of L cos(theta) over the hemisphere (units of the
    light's intensity / mm^2 for point and disc lights, of ``intensity`` for directional
    lights, of radiance x sr for environment maps); with ``transmittance``, the entering
    part integral of T L cos(theta).
    """
    p, n = check_points(points, normals)
    if n is None:
        raise DermisError("irradiance: normals are required")
    out = np.zeros((len(p), 3), dtype=np.float32)

    def batch(c: int) -> None:
        start = c * chunk
        ps, ns = p[start:start + chunk], n[start:start + chunk]
        ls = sample_lights(light, ps, ns, seed=(seed, c), options=options, horizon=False)
        # one cosine pass: samples below the horizon (or of zero weight) are not live, get
        # no shadow ray and add nothing; the sum is E = sum_s V_s cos_s (T_s) weights_s
        cos = np.einsum("nsk,nk->ns", ls.directions, ns)
        live = ls.live()
        live &= cos > 0
        factor = np.where(live, cos, np.float32(0.0))
        if occlusion_fn is not None and live.any():
            # shadow rays of the live samples only (flat indices: one ``take`` per array)
            idx = np.flatnonzero(live)
            rep = idx // live.shape[1]
            blocked = occlusion_fn(ps.take(rep, axis=0), ns.take(rep, axis=0),
                                   ls.directions.reshape(-1, 3).take(idx, axis=0),
                                   ls.distance.ravel().take(idx))
            factor.ravel()[idx[blocked]] = 0.0
        w = ls.weights
        if transmittance is not None:
            t = np.asarray(transmittance(np.maximum(cos, 0.0)), dtype=np.float32)
            w = np.multiply(w, t, out=w if w.flags.writeable else None)   # a fresh array
        out[start:start + chunk] = np.einsum("ns,nsk->nk", factor, w)

    run_batches(batch, len(p), chunk)
    return out


def run_batches(batch: Callable[[int], None], count: int, chunk: int) -> None:
    """``batch(c)`` for every chunk c of ``count`` points, on :data:`IRRADIANCE_THREADS`
    threads: the batches are independent (own seed, own rows of the output), so the result
    does not depend on the thread count; numpy and the ray caster release the GIL for their
    bulk work."""
    batches = range(-(-count // chunk))
    if IRRADIANCE_THREADS > 1 and len(batches) > 1:
        with ThreadPoolExecutor(IRRADIANCE_THREADS) as pool:
            list(pool.map(batch, batches))
    else:
        for c in batches:
            batch(c)
