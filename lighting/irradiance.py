"""The irradiance pass: irradiance E at surface points from one light or several, with
shadow rays (docs/science.md §6; thesis: 64 samples for area and environment lights), the
input of the BSSRDF's gather (stages/irradiance.py, subsurface/exitance.py).

E = sum_s V_s cos_s weights_s over the light samples of lighting/emitters.py
``sample_lights`` (V_s: 1 if the shadow ray is unoccluded, lighting/visibility.py
``Visibility.occluded``), optionally times a per-sample transmittance (the part that enters
the surface).  Points are processed in independent batches (own seed, own rows of the
result) on IRRADIANCE_THREADS threads, so the result does not depend on the thread count.

Halves (``halves=True``, the pipeline's irradiance stage).  Each point's S samples of a disc
or environment light are two independent halves, each an Owen-scrambled Sobol net of S / 2
(lighting/strata.py ``PixelStrata``, the point a pixel of its own), so E = (A + B) / 2 and
noise = (A - B) / 2 estimates E's variance per point (E[noise^2] = Var E, as the renderer's
images, rendering/halves.py); point and directional lights have no sampling noise and count
in both halves.  An environment light is drawn as the renderer draws it (the mixture,
lighting/mixture.py) with its control variate (lighting/control.py): the unoccluded light
is known exactly, alpha n . M_b with alpha the cosine-weighted mean of the entry
transmittance, and the samples estimate only what occluders and T's change with the cosine
take from it, through the never-negative ``control_estimate`` (each half its own).  Measured
on 20,000 of the default head's irradiance points against 2,048 samples a point (64 samples,
4 seeds; bench/results/irradiance.json "halves"): under the Venice sunset the relative RMSE
falls from 0.040 (one jittered set, luminance x cosine strategy) to 0.017, the noise estimate
0.017, the bias +0.09 %; under the disc light 0.0033 -> 0.0032.  Its cost on all of the
high mesh's 241k points (medians of 3): sunset 7.8 -> 11.2 CPU s, disc 3.3 -> 4.4 (the
nets' scrambling, the mixture's draws, the control's sums); the plain estimator would need
~5x the samples for the sunset's noise.

Guarded by tests/test_lights.py (directional E cos theta, shadowed), tests/test_energy.py
and tests/test_knife_edge.py.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

from dermis.lighting.control import control_estimate
from dermis.lighting.emitters import (ENV_STRATEGIES, SamplingOptions, check_points,
                                      light_columns, sample_lights)
from dermis.lighting.strata import PixelStrata
from dermis.pipeline.errors import DermisError
from dermis.rendering.halves import sample_signs

__all__ = ["irradiance", "run_batches", "IRRADIANCE_THREADS"]


# Batches of the irradiance pass run on this many threads (results independent of it).
IRRADIANCE_THREADS = 2


def irradiance(points: np.ndarray, normals: np.ndarray, light,
               occlusion_fn: Callable | None, *, seed: int = 0,
               options: SamplingOptions = SamplingOptions(), chunk: int = 8192,
               transmittance: Callable | None = None, halves: bool = False):
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
    halves : bool
        The pipeline's estimator, with its own noise estimate (module docstring, "Halves"):
        returns (E, noise) instead of E.

    Returns
    -------
    (N, 3) float32 irradiance E = integral of L cos(theta) over the hemisphere (units of the
    light's intensity / mm^2 for point and disc lights, of ``intensity`` for directional
    lights, of radiance x sr for environment maps); with ``transmittance``, the entering
    part integral of T L cos(theta); with ``halves``, also its noise (N, 3) float32.
    """
    p, n = check_points(points, normals)
    if n is None:
        raise DermisError("irradiance: normals are required")
    if halves:
        return _irradiance_halves(p, n, light, occlusion_fn, seed=seed, options=options,
                                  chunk=chunk, transmittance=transmittance)
    out = np.zeros((len(p), 3), dtype=np.float32)

    def batch(c: int) -> None:
        start = c * chunk
        ps, ns = p[start:start + chunk], n[start:start + chunk]
        ls = sample_lights(light, ps, ns, seed=(seed, c), options=options, horizon=False)
        cos, factor = _lit_cosines(ls, ps, ns, occlusion_fn)
        w = ls.weights
        if transmittance is not None:
            t = np.asarray(transmittance(np.maximum(cos, 0.0)), dtype=np.float32)
            w = np.multiply(w, t, out=w if w.flags.writeable else None)   # a fresh array
        out[start:start + chunk] = np.einsum("ns,nsk->nk", factor, w)

    run_batches(batch, len(p), chunk)
    return out


def _lit_cosines(ls, ps, ns, occlusion_fn) -> tuple[np.ndarray, np.ndarray]:
    """(cos, V cos) (N, S) float32 of the light samples ``ls`` at points ``ps`` with normals
    ``ns``, in one cosine pass: samples below the horizon (or of zero weight) are not live,
    get no shadow ray and count 0; V from ``occlusion_fn`` (1 without it)."""
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
    return cos, factor


def _irradiance_halves(p, n, light, occlusion_fn, *, seed, options, chunk, transmittance):
    """The pipeline's estimator (module docstring, "Halves"): (E, noise), each (N, 3) float32."""
    lights = list(light) if isinstance(light, (list, tuple)) else [light]
    # each sample column's half, as the renderer's for a pixel of one camera sample (the
    # first S // 2 of a disc or environment light's S, the next S // 2; point and directional
    # lights, and an odd one out, in both)
    signs = sample_signs(np.zeros(1, np.int64), 1,
                         light_columns(lights, 1, options.samples))[0].astype(np.float32)
    out = np.zeros((len(p), 3), dtype=np.float32)
    noise = np.zeros((len(p), 3), dtype=np.float32)
    # the control's coefficient: any value fixed per point keeps E unbiased; the cosine-
    # weighted mean of T makes the lit and control sums cancel on unoccluded skin but for
    # T's change with the cosine
    alpha = np.asarray(getattr(transmittance, "mean", np.ones(3)), np.float32)
    # the renderer's estimator where the strategy is the default one (rendering/cast.py)
    mixture = options.env_strategy == ENV_STRATEGIES[0]

    def batch(c: int) -> None:
        start = c * chunk
        ps, ns = p[start:start + chunk], n[start:start + chunk]
        m = len(ps)
        strata = PixelStrata(np.arange(start, start + m), np.zeros(m, np.int64), 1, seed,
                             independent=True)
        ls = sample_lights(light, ps, ns, seed=(seed, c), options=options, share=1,
                           strata=strata, mixture=mixture, control=mixture,
                           product_normals=ns if mixture else None)
        cos, factor = _lit_cosines(ls, ps, ns, occlusion_fn)
        w = ls.weights
        terms = w * factor[..., None]      # V cos (T) weights per sample
        if transmittance is not None:
            terms *= np.asarray(transmittance(np.maximum(cos, 0.0)), np.float32)

        def sums(x, where=None):   # (sum, signed sum) over a point's samples, (m, 3) each
            y = x if where is None else x * where[..., None]
            return (np.einsum("nsk->nk", y, dtype=np.float64),
                    np.einsum("nsk,s->nk", y, signs, dtype=np.float64))
        lit, lit_signed = sums(terms)
        if ls.control is None:
            e, d = lit, lit_signed
        else:   # the first environment light's control variate (lighting/control.py)
            region = ls.control
            other, other_signed = sums(terms, ~region)
            ctrl, ctrl_signed = sums(w * (alpha * np.where(region, cos, np.float32(0.0))[
                ..., None]))
            moments = np.asarray(ls.control_table, np.float64).take(ls.control_bin, axis=0)
            exact = alpha * np.einsum("nkj,nj->nk", moments, ns.astype(np.float64))
            e, d = control_estimate(lit - other, lit_signed - other_signed, ctrl, ctrl_signed,
                                    exact, np.zeros_like(exact))
            e += other
            d += other_signed
        out[start:start + m] = e
        noise[start:start + m] = d
    run_batches(batch, len(p), chunk)
    return out, noise


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
