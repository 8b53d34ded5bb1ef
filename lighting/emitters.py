"""Light sampling shared by the BRDF renderer and the BSSRDF irradiance stage (docs/science.md §6).

Every light type answers one question: for surface points ``p`` (N, 3) with normals ``n``,
give S samples per point of

* ``directions`` (N, S, 3): unit vectors from the point towards the light sample,
* ``weights`` (N, S, 3): the sample's RGB contribution, defined so that the reflected
  radiance estimate is ``sum_s f(wo, wi_s) * weights_s * cos(theta_s) * V_s`` and the
  irradiance estimate ``sum_s weights_s * cos(theta_s) * V_s`` (V: 1 if unoccluded),
* ``distance`` (N, S): distance to the sample in mm (``inf`` for lights at infinity), the
  shadow ray's length.

Weights of samples below the horizon of ``normals`` (cos <= 0) are 0, so callers skip them
(no shadow ray is traced for them).

Light types (``pipeline.config.LightConfig``, lengths in mm):

* ``point`` - intensity I (RGB, per steradian): weight = I / d^2 (inverse square).
* ``directional`` - ``intensity`` is the irradiance E on a surface facing the light:
  weight = E.  Any number of them may be given at once (a list of lights concatenates the
  samples; the thesis preset uses two, front-left and front-right).
* ``disc`` - radius r, axis ``direction``, ``intensity`` I = the on-axis intensity, so the
  radiance is L = I / (pi r^2) and the disc tends to a point light of intensity
  I |cos theta_l| as r -> 0.  **Decision: the disc emits from both faces (|cos theta_l|)**,
  so the sign of the scene's ``direction`` cannot silently turn the light off; only the axis
  matters.  Samples: S points stratified on the disc (jittered sqrt(S) x sqrt(S) grid when S
  is a square, Latin hypercube otherwise) through Shirley & Chiu's concentric map (area
  preserving), area-sampling estimator weight = L |cos theta_l| (pi r^2) / (d^2 S).
  Default S = 16, r = 70 mm (thesis, docs/science.md §6).
* ``environment`` - a lat-long radiance map: an HDR/EXR read with OpenImageIO or the
  embedded procedural sunset sky (sun 3 deg above the horizon, thesis).  Three strategies
  (``env_strategy``):

  - ``"luminance"``: S samples importance sampled by pixel brightness x sin(theta) (the
    pixel's solid angle; brightness: the RGB norm, lighting/environment.py
    ``brightness``, luminance until the measurement there), stratified in the flattened
    CDF; weight = L / (S p_env).
  - ``"mis"``: multiple importance sampling (Veach &
    Guibas 1995; Veach's thesis 1997, ch. 9).  n_cos = round(3 S / 8) samples (6 of 16)
    from the cosine-weighted hemisphere around the normal, p_cos = cos/pi (Malley's method
    on a stratified concentric disc), and n_env = S - n_cos from p_env as above, combined
    with the balance heuristic: every sample, whichever strategy drew it, gets weight
    L / (n_env p_env + n_cos p_cos), both pdfs evaluated at its direction.  Unbiased
    wherever either pdf covers the integrand (p_cos covers the whole upper hemisphere).
    Why: 67 % of the procedural sunset's luminance mass is the sun 3 deg above the horizon;
    on surfaces facing away from it (or where it is occluded) luminance sampling spends most
    of the S samples on a zero contribution and the sky is estimated from one or two.
    Measured on the procedural sunset at S = 16 (relative std of one point's estimate,
    luminance -> mis): normal 60 deg above the anti-sun direction 36 % -> 13 %, anti-sun
    62 % -> 18 %, straight down 42 % -> 7 %, up 6.9 % -> 2.7 %, sun-facing 7.2 % -> 6.2 %.
    Choices, measured on the same normals (see MIS_COSINE_FRACTION): 3/8 of the samples
    beats 1/4 and 1/2 (half leaves too few luminance samples for the sun: 9.2 % on the
    sun-facing point); the balance heuristic beats the power heuristic (beta = 2) on the
    sky-lit normals (up: 2.7 % vs 4.8 %) and ties elsewhere, and is simpler.  With S = 1 or
    without normals the luminance strategy is used.
  - ``"product"`` (default when normals are given): as "mis", but the first strategy samples
    luminance x cosine: the map's luminance mass in ~64 x 128 blocks of pixels is weighted
    by the cosine between each block and the normal, tabulated for 16 x 32 lat-long bins of
    normals (the cosine padded by the block's and the bin's angular radius so no block
    partly above a normal's horizon is left out), then the pixel inside the block by its
    luminance (EnvironmentMap._product; the pdf is the table's, so the estimate stays
    unbiased, and the cosine strategy covers what a bin's table misses).  Luminance
    samples below a surface's horizon - for a face under a sunset, every sun sample of the
    sides turned from the sun - are no longer drawn.  floor(S / 4) >= 1 cosine samples
    (PRODUCT_COSINE_FRACTION).  Measured on the Lee Perry-Smith head under the Venice
    sunset, Lafortune, 800 x 800, 4 camera samples x 4 light samples per pixel: noise
    (relative RMSE of one image, from two seeds) 0.188 with "mis" -> 0.094; pixels above
    1.5x their converged value 1.8 % -> 0.5 % (bench/results/render_fireflies.json).
    With 2 of 4 cosine samples the noise was 0.120.
  Optionally (``lobe``, lighting/lobes.py) a share of the samples is drawn about a
  direction the BRDF favours (the glossy reflection of the view, or the view itself for a
  backward-scattering layer), weighted by the same balance heuristic.
  The renderer (rendering/cast.py) samples environment lights with ``mixture=True`` instead:
  lighting/mixture.py draws each sample's strategy (product, cosine, lobe) with per-point
  shares from a number stratified over the pixel, stratifies the pixel's samples in 2-D and,
  on request (``control=True``), marks the control variate's region (lighting/control.py).

The environment map, its lat-long convention and the product strategy's tables:
lighting/environment.py; the warps and strata the samples come from: lighting/warps.py,
lighting/strata.py; the irradiance pass built on these samples: lighting/irradiance.py.

Guarded by tests/test_lights.py (inverse square, disc -> point limit and closed form,
constant environment gives pi L, importance-sampling consistency, MIS and product
unbiasedness and their variance reduction) and tests/test_render.py.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Protocol, Sequence

import numpy as np

from dermis.lighting.environment import EnvironmentMap, environment_map
from dermis.lighting.mixture import sample_environment
from dermis.lighting.strata import PixelStrata, stratified_2d
from dermis.lighting.sun import split_sun
from dermis.lighting.warps import concentric_disc, cosine_hemisphere, normalize, tangent_frame
from dermis.pipeline.errors import ConfigError, DermisError
from dermis.pipeline.store import file_digest

__all__ = ["LightSamples", "SamplingOptions", "Lobe", "sample_lights", "light_columns",
           "light_params", "check_points", "ENV_STRATEGIES", "PRODUCT_COSINE_FRACTION",
           "MIS_COSINE_FRACTION"]

# Environment-light sampling strategies (module docstring); the first is the default.
ENV_STRATEGIES = ("product", "mis", "luminance")
# Share of the "product" strategy's samples drawn from the cosine hemisphere (rounded down,
# at least 1: one of the 4 samples of an anti-aliased pixel's camera sample).
PRODUCT_COSINE_FRACTION = 0.25
# Share of an environment light's samples drawn from the cosine hemisphere under "mis":
# measured on the procedural sunset at S = 16 over 6 normals (module docstring), shares
# 1/8, 1/4, 3/8, 1/2 tried: 3/8 is the largest that is nowhere noisier than pure luminance
# sampling (1/2: 9.2 % vs 7.2 % on the sun-facing normal), and beats 1/8 and 1/4 on every
# normal facing away from the sun (anti-sun: 18 % vs 34 % and 24 %).
MIS_COSINE_FRACTION = 0.375
# An environment map's sun is sampled on its own (lighting/sun.py) by SUN_SAMPLE_SHARE of a
# point's samples (:func:`sun_samples`), the sky by the rest, where the sun carries at least
# that share of the light on a surface facing it (``Sun.share``): a weaker sun is left in the
# map, where the product strategy draws it in proportion to its light.  Measured on the
# default scan (200 x 200, 4 camera x 16 light samples per pixel, relative noise between 4
# seeds, Lafortune, bench/results/env_noise.json "split"): the procedural sunset (sun 0.86
# of the light) 0.051 whole -> 0.027 split; the Venice sunset (sun 0.046) 0.072 whole ->
# 0.089 split.  SPLIT_SUN False samples every map whole (bench/bench_env_noise.py).
SPLIT_SUN = True
SUN_SAMPLE_SHARE = 0.25
# The strata salt of the sun's samples (apart from every light's other draws).
SUN_SALT = 1 << 20


@dataclass
class LightSamples:
    """Light samples for N points, S per point (see the module docstring).

    directions : (N, S, 3) float32 unit vectors towards the light
    weights : (N, S, 3) float32 contribution weights (0 below the normal's horizon, except
        for samples in the control variate's region)
    distance : (N, S) float32 distance to the light sample, mm (inf at infinity)
    control, control_bin, control_table : with ``control=True`` (:func:`sample_lights`), the
        (N, S) bool samples in the control variate's region of an environment light, each
        point's (N,) int32 control bin and the (bins, 3, 3) float32 moments M_b (RGB x xyz;
        lighting/control.py); None otherwise
    """

    directions: np.ndarray
    weights: np.ndarray
    distance: np.ndarray
    control: np.ndarray | None = None
    control_bin: np.ndarray | None = None
    control_table: np.ndarray | None = None

    @property
    def count(self) -> int:
        return int(self.directions.shape[1])

    def live(self) -> np.ndarray:
        """(N, S) bool: samples with some weight (any channel > 0), one comparison per channel
        (a reduction over the length-3 axis, ``weights.max(axis=2)``, was ~10x slower: 3.8 of
        46 s of a sunset + area irradiance pass, py-spy)."""
        w = self.weights
        live = (w[..., 0] > 0) | (w[..., 1] > 0)
        live |= w[..., 2] > 0
        return live


@dataclass(frozen=True)
class SamplingOptions:
    """How disc and environment lights are sampled (:func:`sample_lights`,
    lighting/irradiance.py); the defaults are the pipeline's.

    samples : samples per point for disc and environment lights (None: each light's
        ``samples``, 16 in the thesis).  Point and directional lights take one.
    env : pre-built map for an environment light (None: built from ``light.map``, cached)
    env_strategy : one of ENV_STRATEGIES, how environment lights are sampled (module
        docstring): "product" (default) draws luminance x cosine and cosine samples, "mis"
        mixes luminance and cosine-hemisphere samples about the normals (3/8 of them) with
        the balance heuristic; "luminance" is pure luminance importance sampling.  "product"
        and "mis" fall back to "luminance" when the normals are None or S = 1.
    """

    samples: int | None = None
    env: EnvironmentMap | None = None
    env_strategy: str = ENV_STRATEGIES[0]


class Lobe(Protocol):
    """An extra environment-sampling strategy (lighting/lobes.py :class:`GlossyLobe`,
    :class:`RetroLobe`): the share of the samples it draws, (N, S, 3) directions for uniform
    (N, S, 2) numbers, and the (N, S) solid-angle density of (N, S, 3) directions."""

    fraction: float

    def sample(self, u: np.ndarray) -> np.ndarray: ...

    def pdf(self, directions: np.ndarray) -> np.ndarray: ...


def check_points(points, normals) -> tuple[np.ndarray, np.ndarray | None]:
    """``points`` (N, 3) and ``normals`` (N, 3) or None as float32 arrays (shapes checked)."""
    p = np.asarray(points, dtype=np.float32)
    if p.ndim != 2 or p.shape[1] != 3:
        raise DermisError(f"lights: points have shape {p.shape}; need (N, 3)")
    n = None
    if normals is not None:
        n = np.asarray(normals, dtype=np.float32)
        if n.shape != p.shape:
            raise DermisError(f"lights: normals have shape {n.shape}; need {p.shape}")
    return p, n


def _vec(value, name: str, light) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ConfigError(f"lights.{light.name}.{name} = {value!r}: must be 3 finite numbers")
    return v


# --------------------------------------------------------------------------- light types
def _point(light, p: np.ndarray, rng) -> tuple:
    pos = _vec(light.position, "position", light).astype(np.float32)
    d = pos[None, :] - p
    dist = np.linalg.norm(d, axis=1)
    safe = np.maximum(dist, np.float32(1e-6))
    wi = d / safe[:, None]
    # inverse square (docs/science.md §6); a point exactly at the light gets weight 0, not inf
    w = _vec(light.intensity, "intensity", light).astype(np.float32)[None, :] \
        / np.where(dist > 1e-6, safe * safe, np.inf)[:, None]
    return wi[:, None], w[:, None], dist[:, None]


def _directional(light, p: np.ndarray, rng) -> tuple:
    d = _vec(light.direction, "direction", light)
    if np.linalg.norm(d) == 0:
        raise ConfigError(f"lights.{light.name}.direction = {light.direction!r}: must be non-zero")
    wi = np.broadcast_to((d / np.linalg.norm(d)).astype(np.float32), (len(p), 1, 3))
    w = np.broadcast_to(_vec(light.intensity, "intensity", light).astype(np.float32),
                        (len(p), 1, 3))
    dist = np.full((len(p), 1), np.inf, dtype=np.float32)
    return wi, w, dist


def _disc(light, p: np.ndarray, rng, samples: int, strata=None, salt: int = 0) -> tuple:
    centre = _vec(light.position, "position", light)
    axis = _vec(light.direction, "direction", light)
    if np.linalg.norm(axis) == 0:
        raise ConfigError(f"lights.{light.name}.direction = {light.direction!r}: the disc's "
                          "axis must be non-zero")
    axis = axis / np.linalg.norm(axis)
    radius = float(light.radius)
    if not radius > 0:
        raise ConfigError(f"lights.{light.name}.radius = {radius} (mm): must be > 0")
    t, b = tangent_frame(axis)
    u = (strata.uniform_2d(rng, samples, salt) if strata is not None
         else stratified_2d(rng, len(p), samples))
    # float32 throughout (the outputs are float32): the map, the sample point q on the disc
    # as centre + x t + y b, and d = q - p (the irradiance pass's 15M samples; measured in
    # bench/results/irradiance.json); (N, S, 3) arrays one component at a time (numpy
    # broadcasts along a trailing axis of 3 several times slower)
    xy = concentric_disc(u.astype(np.float32))
    xy *= np.float32(radius)
    frame = np.stack([t, b]).astype(np.float32)                       # (2, 3)
    d = xy @ frame
    to_centre = centre.astype(np.float32)[None, :] - p
    for k in range(3):
        d[..., k] += to_centre[:, k, None]
    dist2 = np.einsum("nsk,nsk->ns", d, d)
    dist = np.sqrt(dist2)
    far = dist > 1e-6
    inv = np.float32(1.0) / np.where(far, dist, np.float32(1.0))
    wi = d
    for k in range(3):
        wi[..., k] *= inv
    # two-sided emitter (module docstring): |cos theta_l|; L (pi r^2) = I; a point exactly
    # on the disc gets weight 0, not inf
    cos_l = wi @ axis.astype(np.float32)
    cos_l = np.abs(cos_l, out=cos_l)
    inv *= inv
    cos_l *= inv
    cos_l *= np.float32(1.0 / samples)
    scale = np.where(far, cos_l, np.float32(0.0))
    intensity = _vec(light.intensity, "intensity", light).astype(np.float32)
    w = np.empty(scale.shape + (3,), dtype=np.float32)
    for k in range(3):
        np.multiply(scale, intensity[k], out=w[..., k])
    return wi, w, dist


def sun_samples(samples: int, even: bool = False) -> int:
    """Of a point's S >= 2 samples of an environment light with a sun, those on the sun
    (SUN_SAMPLE_SHARE of them, at least one, at most S - 1; ``even``: an even number, at
    least 2, so each half of the point's samples holds as many; 0 where S < 3 then)."""
    n = min(max(int(samples * SUN_SAMPLE_SHARE + 1e-9), 1), samples - 1)
    if even:
        n = max(2, n - n % 2)
        return n if n <= samples - 1 else 0
    return n


def _sun(sun, n: int, rng, samples: int, normals, strata, salt: int, horizon: bool) -> tuple:
    """``samples`` per point on the ``sun`` (lighting/sun.py): the pixel by a number stratified
    over the pixel's samples (or the point's), the point in it by a second one and a
    uniform number; weights / samples, 0 below the normals' horizon when ``horizon``."""
    u = np.empty((n, samples, 3))
    u[..., :2] = (strata.uniform_2d(rng, samples, SUN_SALT + salt) if strata is not None
                  else stratified_2d(rng, n, samples))
    u[..., 2] = rng.random((n, samples))
    wi, w = sun.sample(u)
    w *= np.float32(1.0 / samples)
    if horizon and normals is not None:
        w[np.einsum("nsk,nk->ns", wi, np.asarray(normals, np.float32)) <= 0] = 0.0
    return wi, w, np.full((n, samples), np.inf, dtype=np.float32)


def _environment(light, p: np.ndarray, rng, samples: int, env, normals, strategy: str,
                 strata=None, salt: int = 0,
                 lobe: "Lobe | None" = None, mixture: bool = False,
                 control: bool = False, horizon: bool = True,
                 product_normals: np.ndarray | None = None, halves: bool = False) -> tuple:
    """An environment light's samples: with normals, S >= 2, the renderer's mixture or the
    "product" strategy and a map with a sun (lighting/sun.py) carrying at least
    SUN_SAMPLE_SHARE of the light, :func:`sun_samples` of them on the sun and the rest on the
    sky without it (:func:`_environment_map`); else the whole map's.  ``halves``: the first
    and the second half of a point's samples are the two halves of the image's noise
    estimate (rendering/halves.py, an odd ``share``), so each holds half the sun's and half
    the sky's samples, in that order (an odd sample out, last, is the sky's)."""
    if env is None:
        env = environment_map(light)
    split = (split_sun(env) if SPLIT_SUN and normals is not None and samples >= 2
             and (mixture or strategy == "product") else None)
    n_sun = sun_samples(samples, even=halves) if split is not None else 0
    if split is None or split.sun.share < SUN_SAMPLE_SHARE or n_sun == 0:
        return _environment_map(light, p, rng, samples, env, normals, strategy, strata, salt,
                                lobe, mixture, control, horizon, product_normals)
    sun = _sun(split.sun, len(p), rng, n_sun, normals, strata, salt, horizon)
    sky = _environment_map(light, p, rng, samples - n_sun, split.sky, normals, strategy,
                           strata, salt, lobe, mixture, control, horizon, product_normals)
    a, b = (n_sun // 2, (samples - n_sun) // 2) if halves else (n_sun, 0)

    def join(x, y):                  # the halves' sun and sky samples, in turn
        return np.concatenate([x[:, :a], y[:, :b], x[:, a:], y[:, b:]], axis=1)
    wi, w, dist = (join(x, y) for x, y in zip(sun, sky[:3]))
    if len(sky) == 3:
        return wi, w, dist
    es = sky[3]
    flags = None
    if es.control is not None:
        flags = join(np.zeros((len(p), n_sun), bool), es.control)
    return wi, w, dist, replace(es, directions=wi, weights=w, control=flags)


def _environment_map(light, p: np.ndarray, rng, samples: int, env, normals, strategy: str,
                     strata=None, salt: int = 0,
                     lobe: "Lobe | None" = None, mixture: bool = False,
                     control: bool = False, horizon: bool = True,
                     product_normals: np.ndarray | None = None) -> tuple:
    n = len(p)
    if mixture and normals is not None:     # the renderer's estimator (lighting/mixture.py)
        es = sample_environment(env, normals, rng, samples, strata=strata, salt=salt, lobe=lobe,
                                control=control, horizon=horizon,
                                product_normals=product_normals)
        dist = np.full((n, samples), np.inf, dtype=np.float32)
        return es.directions, es.weights, dist, es
    mis = strategy in ("mis", "product") and normals is not None and samples >= 2 \
        and not env.black
    product = mis and strategy == "product"
    if product:   # floor: the product samples carry the sun and the cosine already
        n_cos = min(max(int(samples * PRODUCT_COSINE_FRACTION + 1e-9), 1), samples - 1)
    else:
        n_cos = min(max(int(round(samples * MIS_COSINE_FRACTION)), 1), samples - 1) if mis else 0
    n_lobe = 0
    if mis and lobe is not None and samples >= 3:
        # the lobe's samples come out of the cosine ones (the luminance samples carry the sun)
        n_lobe = min(max(int(round(samples * lobe.fraction)), 1), samples - 2)
        n_cos = max(1, n_cos - n_lobe)
    n_env = samples - n_cos - n_lobe
    # stratify the flattened-CDF coordinate per point; jitter inside the pixel at random
    u0 = ((np.arange(n_env)[None, :] + rng.random((n, n_env))) / n_env
          if strata is None else strata.uniform_1d(rng, n_env, 2 * salt))
    jitter = rng.random((n, n_env, 3 if product else 2))
    if not product:
        u = np.empty((n, n_env, 3))
        u[..., 0] = u0
        u[..., 1:] = jitter
    if not mis:
        wi, w = env.sample(u.reshape(-1, 3))
        wi = wi.reshape(n, samples, 3)
        w = (w / np.float32(samples)).reshape(n, samples, 3)
        dist = np.full((n, samples), np.inf, dtype=np.float32)
        return wi, w, dist
    # multiple importance sampling, balance heuristic (module docstring): for a sample x of
    # any strategy i, w_i(x) L / (n_i p_i(x)) with w_i = n_i p_i / sum_j n_j p_j reduces to
    # L(x) / sum_j n_j p_j(x) (Veach 1997, eq. 9.13), every pdf evaluated at x
    nrm = normalize(np.asarray(normals, dtype=np.float64))
    if product:   # luminance x cosine of the point's normal bin (EnvironmentMap._product)
        bins = env.normal_bin(nrm)
        d_env, rad_env, pdf_env = env.product_sample(u0.ravel(), jitter.reshape(-1, 3),
                                                     np.repeat(bins, n_env))
    else:
        d_env, rad_env, pdf_env = env.sample_pdf(u.reshape(-1, 3))   # pdf known from the pick
    dirs = [cosine_hemisphere(stratified_2d(rng, n, n_cos) if strata is None
                              else strata.uniform_2d(rng, n_cos, 2 * salt + 1), nrm)[0]]
    if n_lobe:
        dirs.append(lobe.sample(stratified_2d(rng, n, n_lobe) if strata is None
                                else strata.uniform_2d(rng, n_lobe, 2 * salt + 7)))
    other = np.concatenate(dirs, axis=1) if len(dirs) > 1 else dirs[0]
    if product:   # one pixel lookup for the radiance and the product pdf
        row, col = env.pixel_of(other)
        rad_other = env.radiance_at(row, col)
        pdf_other = env.product_pdf(other, np.broadcast_to(bins[:, None], other.shape[:2]),
                                    row, col)
    else:
        pdf_other, rad_other = env.pdf_radiance(other)
    # the S samples side by side: directions float32 (as returned), the pdfs float64
    wi = np.empty((n, samples, 3), dtype=np.float32)
    wi[:, :n_env] = d_env.reshape(n, n_env, 3)
    wi[:, n_env:] = other
    den = np.concatenate([pdf_env.reshape(n, n_env), pdf_other], axis=1)
    w = np.concatenate([rad_env.reshape(n, n_env, 3), rad_other], axis=1)   # float32
    den *= n_env
    cos = np.einsum("nsk,nk->ns", wi, nrm.astype(np.float32))
    cos = np.maximum(cos, 0.0, out=cos)
    cos *= n_cos / math.pi          # float32, as (n_cos / pi) * cos
    den += cos
    if n_lobe:
        den += n_lobe * lobe.pdf(np.concatenate([d_env.reshape(n, n_env, 3), other], axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.divide(1.0, den).astype(np.float32)
    inv[~(den > 0)] = 0.0
    for k in range(3):   # w *= inv[..., None], one channel at a time (cosine_hemisphere)
        w[..., k] *= inv
    dist = np.full((n, samples), np.inf, dtype=np.float32)
    return wi, w, dist


# --------------------------------------------------------------------------- public API
def light_columns(lights, spp: int, shadow_samples: int | None = None) -> list[int]:
    """Light samples drawn per camera hit, per light: 1 per point or directional light,
    ceil(S / spp) per disc or environment light (S = ``shadow_samples`` or the light's
    ``samples``), in the order :func:`sample_lights` concatenates them (``share`` = spp)."""
    return [1 if lt.type in ("point", "directional")
            else -(-int(shadow_samples or lt.samples) // spp) for lt in lights]

def sample_lights(lights, points: np.ndarray, normals: np.ndarray | None = None, *,
                  seed: int | Sequence[int] = 0, options: SamplingOptions = SamplingOptions(),
                  share: int = 1, strata: "PixelStrata | None" = None,
                  lobe: "Lobe | None" = None,
                  horizon: bool = True, mixture: bool = False,
                  control: bool = False,
                  product_normals: np.ndarray | None = None) -> LightSamples:
    """Sample one light or several (summed) for N surface points.

    Parameters
    ----------
    lights : LightConfig or sequence of LightConfig
        Several lights (e.g. the two directional lights of the thesis preset) concatenate
        their samples along the S axis, so the estimate sums them.
    points : (N, 3) float, mm
    normals : (N, 3) float, optional
        Unit surface normals; samples with cos <= 0 get weight 0.  None keeps every sample.
    seed : int or sequence of int
        Seeds ``numpy.random.default_rng`` (pass ``(seed, chunk)`` for chunked calls).
    options : SamplingOptions
        Samples per point, a pre-built environment map and the environment strategy.
    share : int
        Points that share one pixel's samples (the renderer's sub-pixel samples): each point
        draws ceil(S / share) samples of a disc or environment light, so a pixel of ``share``
        sub-pixel samples still averages about S light samples (point and directional
        lights: one each).
    strata : PixelStrata, optional
        Which pixel and sub-sample each point is (``share`` = its share): the pixel's light
        samples are then stratified over all its sub-samples (:class:`PixelStrata`).
    lobe : GlossyLobe or RetroLobe, optional
        Environment lights under "mis" also draw ``lobe.fraction`` of their samples about
        the glossy reflection of the view (lighting/lobes.py :class:`GlossyLobe`) or the view
        itself (:class:`RetroLobe`).
    horizon : bool
        Zero the weights of samples below the normals' horizon (default).  False leaves
        them for a caller that tests cos > 0 itself (lighting/irradiance.py: one cosine pass).
    mixture : bool
        The renderer's estimator for environment lights (lighting/mixture.py): the product,
        cosine and ``lobe`` strategies with per-point shares (``lobe.fractions()``), samples
        stratified in 2-D.  Needs ``normals``.
    control : bool
        With ``mixture``, the control variate of the first environment light
        (lighting/control.py: ``control``, ``control_bin`` and ``control_table`` of the
        result; samples of its region keep their weights below the horizon).
    product_normals : (N, 3) float, optional
        With ``mixture``, the normals whose bins the product strategy's tables are read for
        (the renderer's interpolated normals: the cosine it shades with); the horizon and
        the cosine strategy stay ``normals``'.

    Returns
    -------
    LightSamples
    """
    if not isinstance(lights, (list, tuple)):
        lights = [lights]
    if not lights:
        raise DermisError("lights: no light given")
    samples, env, env_strategy = options.samples, options.env, options.env_strategy
    p, n = check_points(points, normals)
    if env_strategy not in ENV_STRATEGIES:
        raise ConfigError(f"env_strategy = {env_strategy!r}: must be one of "
                          f"{', '.join(ENV_STRATEGIES)}")
    rng = np.random.default_rng(seed)
    if strata is not None and (strata.share != share or len(strata.pixel) != len(p)):
        raise DermisError(f"lights: strata for {len(strata.pixel)} points sharing "
                          f"{strata.share}; need {len(p)} and share = {share}")
    parts = []
    ctrl = None
    for index, light in enumerate(lights):
        s = int(samples if samples is not None else getattr(light, "samples", 16))
        if s < 1:
            raise ConfigError(f"lights.{light.name}.samples = {s}: must be >= 1")
        s = -(-s // max(int(share), 1))
        kind = light.type
        if kind == "point":
            part = _point(light, p, rng)
        elif kind == "directional":
            part = _directional(light, p, rng)
        elif kind == "disc":
            part = _disc(light, p, rng, s, strata, salt=3 * index)
        elif kind == "environment":
            part = _environment(light, p, rng, s, env, n, env_strategy, strata,
                                salt=3 * index + 1, lobe=lobe,
                                mixture=mixture and n is not None,
                                control=control and ctrl is None, horizon=horizon,
                                product_normals=product_normals,
                                halves=strata is not None and strata.share % 2 == 1)
        else:
            raise ConfigError(f"lights.{light.name}.type = {kind!r}: must be one of point, "
                              "disc, directional, environment")
        if len(part) == 4:                # the mixture zeroes below the horizon itself
            es = part[3]
            part = part[:3]
            if es.control is not None:    # the first environment light's control variate
                ctrl = (len(parts), es)
        elif n is not None and horizon:   # weights 0 below the normals' horizon
            up = np.einsum("nsk,nk->ns", np.asarray(part[0], np.float32), n) > 0
            part = (part[0], np.where(up[..., None], part[1], np.float32(0.0)), part[2])
        parts.append(part)
    wi, w, dist = (np.ascontiguousarray(np.concatenate(
        [np.asarray(q[k], dtype=np.float32) for q in parts], axis=1) if len(parts) > 1
        else parts[0][k], dtype=np.float32) for k in range(3))
    if ctrl is None:
        return LightSamples(wi, w, dist)
    at, es = ctrl
    start = sum(q[0].shape[1] for q in parts[:at])
    flags = np.zeros(wi.shape[:2], bool)
    flags[:, start:start + es.control.shape[1]] = es.control
    return LightSamples(wi, w, dist, control=flags, control_bin=es.control_bin,
                        control_table=es.table.moments.astype(np.float32))


def light_params(lights) -> dict:
    """The lights as config slices, with the content hash of any environment map file."""
    params = {"lights": [asdict(l) for l in lights]}
    for light in lights:
        if light.type == "environment" and light.map != "procedural_sunset":
            params[f"map_sha256_{light.name}"] = file_digest(light.map)
    return params
