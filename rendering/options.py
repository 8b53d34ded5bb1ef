"""What one image is rendered with, apart from its mesh, lights, camera and model: the
options of :func:`dermis.rendering.shade.render`, of which the camera and shadow rays
(:func:`dermis.rendering.cast.cast`) and the surface pass
(:func:`dermis.rendering.surface.pixel_surface`) read their part, and the research options
of the light sampling.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dermis.lighting.emitters import ENV_STRATEGIES
from dermis.lighting.environment import EnvironmentMap
from dermis.lighting.visibility import Visibility
from dermis.pipeline.artifacts import PixelSamples

__all__ = ["LightSampling", "RenderOptions"]


@dataclass(frozen=True)
class LightSampling:
    """Research options of the light sampling (the pipeline uses the defaults).

    shadow_samples : light samples per PIXEL for disc and environment lights (None: each
        light's ``samples``, 16 in the thesis); spread over the pixel's camera samples
    env : pre-built EnvironmentMap for an environment light (None: from ``light.map``, cached)
    env_strategy : "product" (luminance x cosine and cosine samples about the geometric
        normal), "mis" (luminance and cosine) or "luminance"
        (:func:`lighting.emitters.sample_lights`)
    glossy_fraction, glossy_exponent, glossy_tilt : under "mis", the share of environment
        samples drawn about the glossy reflection of the view
        (:class:`lighting.lobes.GlossyLobe`; fraction 0 = none)
    retro_fraction, retro_k : the share of environment samples drawn about the view
        direction from a Henyey-Greenstein lobe of mean cosine ``retro_k``
        (:class:`lighting.lobes.RetroLobe`; fraction 0 = none);
        :func:`rendering.cast.retro_lobe` sets it for a scene whose HK93 layers scatter
        backwards
    mixture : with ``env_strategy`` "product", environment lights through the renderer's
        estimator (lighting/mixture.py: per-hit strategy shares, samples stratified over the
        pixel in 2-D); False: fixed shares, as the irradiance pass samples
    glossy_lobes : with ``mixture``, a share of each hit's environment samples drawn from the
        Lafortune lobes (:class:`lighting.lobes.LafortuneLobes`, per-hit shares);
        :func:`rendering.cast.glossy_lobes` sets it for a scene that renders them
    control_variate : with ``mixture``, the control variate of lighting/control.py: the
        unoccluded diffuse light known exactly, the samples estimating only the rest, through
        the never-negative difference/ratio estimator of lighting/control.py
        ``control_estimate``.  The pipeline turns it on (stages/visibility.py): under the
        Venice sunset it takes the Lafortune image's relative RMSE from 0.072 to 0.043
        (bench/results/env_noise.json "split") for 1.3x the rays and shading CPU time
        ("one_pass_cost").  False: the plain mixture estimator
    independent_halves : the two half images of the image's own noise estimate
        (rendering/halves.py) drawn from two independently scrambled nets of the pixel's
        light samples (:class:`lighting.strata.PixelStrata` ``independent``), so noise^2
        estimates the image's variance.  False: one net of all the pixel's samples, a less
        noisy image whose noise^2 overstates its variance (E[noise^2] = 2 Var_indep - Var,
        rendering/halves.py).  Measured on the default scan under the Venice sunset, 200 x
        200, 8 seeds, relative RMSE against the converged render, Lafortune / HK93 (mean
        noise^2 / squared error): True 0.0722 / 0.0715 (1.015 / 1.017), False 0.0614 /
        0.0605 (1.79 / 1.83) (bench/results/env_noise.json "after_nets", variants
        "default" and "joint_net")
    """

    shadow_samples: int | None = None
    env: EnvironmentMap | None = None
    env_strategy: str = ENV_STRATEGIES[0]
    glossy_fraction: float = 0.0
    glossy_exponent: float = 32.0
    glossy_tilt: float = 0.75
    retro_fraction: float = 0.0
    retro_k: float = 0.0
    mixture: bool = True
    glossy_lobes: bool = False
    control_variate: bool = False
    independent_halves: bool = True


@dataclass(frozen=True, eq=False)
class RenderOptions:
    """How one image is rendered; the defaults are the pipeline's.

    maps : pipeline.artifacts.BakedMaps, optional
        Baked maps of a low mesh; their ``albedo_srgb`` replaces the mesh's texture.
    bump : {None, "sharp", "blur"}
        Bump-map the shading normal with ``maps.bump`` or ``maps.bump_blur`` (needs maps and
        UVs).
    textured : bool
        False ignores the albedo texture (the model's constant albedo everywhere), e.g. to
        render only Lafortune's specular lobes (rho_d = 0) on top of a BSSRDF image.
    base : str, optional
        Base model under a term model (the asperity term): the name of one of its
        ``bases``, or "none" for the term alone; default ``params.base``.
    base_params : optional
        Parameters of the base model (default: its defaults).
    samples : PixelSamples, optional
        The shared visibility (stage ``visibility``) of this mesh, light and camera; the
        light, ``seed``, ``spp``, ``sampling`` and ``visibility`` are then not used for casting.
    seed : int
        Seed of the camera jitter and light samples when they are cast here.
    spp : int
        Camera samples per pixel when cast here (1 = the pixel centre).
    sampling : LightSampling, optional
        Research options of the light sampling (sample count, environment map, strategy);
        only used when the samples are cast here.
    visibility : lighting.visibility.Visibility, optional
        Embree scene of the mesh built earlier (build once, render many).
    indirect : (V, 3) float array, optional
        One bounce of indirect irradiance at the mesh's vertices (stage ``indirect``): the
        model's diffuse response to it is added (rendering/indirect_shading.py); None: direct
        light only, as in the thesis.
    """

    maps: Any = None
    bump: str | None = None
    textured: bool = True
    base: str | None = None
    base_params: Any = None
    samples: PixelSamples | None = None
    seed: int = 0
    spp: int = 1
    sampling: LightSampling | None = None
    visibility: Visibility | None = None
    indirect: Any = None
