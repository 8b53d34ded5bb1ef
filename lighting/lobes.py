"""BRDF-lobe sampling: extra environment-sampling strategies about a direction the BRDF
favours, combined with the luminance and cosine strategies by multiple importance sampling
(lighting/emitters.py ``sample_lights``, argument ``lobe``).

* :class:`GlossyLobe` - a share of the samples drawn about the glossy reflection of the
  view.  Measured on the Lee Perry-Smith head under the Venice sunset (Lafortune, 800 x
  800, 4 camera samples x 4 light samples per pixel) it removed a third of the specular
  lobes' own outliers but, taking samples from the diffuse strategies, made the whole
  Lafortune image noisier (off by default).
* :class:`RetroLobe` - a backward-scattering layer (HK93 with g < RETRO_G_MAX) instead draws
  a share about the view direction itself, where its Henyey-Greenstein backscatter peak
  lies (wi = wo): at g = -0.99 that peak is ~1e3 times its mean and the other strategies
  land in it too rarely (fireflies, docs/hardening.md; measured in
  bench/results/hk93_retro.json).

Each lobe gives the share of the samples it draws (``fraction``), directions for uniform
numbers (``sample``) and their solid-angle density (``pdf``); the MIS weights count that
density whatever the BRDF is, so the estimate stays unbiased for every model.

Guarded by tests/test_lights.py (the retro lobe is unbiased and tames a backscatter peak)
and tests/test_hardening.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dermis.lighting.warps import about_axis, normalize

__all__ = ["GlossyLobe", "RetroLobe", "RETRO_G_MAX", "RETRO_FRACTION"]

_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class GlossyLobe:
    """A third environment-sampling strategy for glossy reflection seen at ``view``: the
    cosine-power lobe p(wi) = (e + 1) / (2 pi) max(0, a . wi)^e about the axis
    a = normalize(-wo_t, tilt x wo_n) (wo_t, wo_n: the view's parts along and across the
    surface of ``normals``): tilt 1 is the mirror direction; the Lafortune skin fit's sharp
    lobe has Cz / |Cxy| ~ 0.75 and exponent ~60 (docs/science.md §1).  Any model may shade
    these samples: the MIS weights count the lobe's density whatever the BRDF is.

    view : (N, 3) unit directions to the eye; normals : (N, 3) unit (interpolated) normals
    fraction : share of the samples drawn from the lobe; exponent, tilt : the lobe's shape
    """

    view: np.ndarray
    normals: np.ndarray
    fraction: float = 0.25
    exponent: float = 32.0
    tilt: float = 0.75

    def __getitem__(self, sl) -> "GlossyLobe":
        return GlossyLobe(self.view[sl], self.normals[sl], self.fraction, self.exponent,
                          self.tilt)

    def axis(self) -> np.ndarray:
        v = np.asarray(self.view, np.float64)
        nrm = normalize(np.asarray(self.normals, np.float64))
        vn = np.einsum("ij,ij->i", v, nrm)[:, None]
        return normalize(-(v - vn * nrm) + self.tilt * vn * nrm)

    def sample(self, u: np.ndarray) -> np.ndarray:
        """(N, S, 3) directions for uniform (N, S, 2) numbers."""
        a = self.axis()
        cos_a = u[..., 0] ** (1.0 / (self.exponent + 1.0))
        return about_axis(a, cos_a, _TWO_PI * u[..., 1])

    def pdf(self, directions: np.ndarray) -> np.ndarray:
        """(N, S) solid-angle density of (N, S, 3) directions."""
        c = np.maximum(np.einsum("nsk,nk->ns", directions, self.axis()), 0.0)
        return (self.exponent + 1.0) / _TWO_PI * c ** self.exponent


# A layer scattering more backwards than this gets the retro lobe (RetroLobe).  Its HG peak
# at g is (1 - g^2) / (4 pi (1 - |g|)^3) / (1 / 4 pi) times the isotropic value: 20 at
# g = -0.5, 1e4 at -0.99 (against 4 samples per hit).
RETRO_G_MAX = -0.5
# Share of the environment samples drawn from the retro lobe (one of 4 per hit at the
# default 16 per pixel / 4 camera samples): measured in bench/results/hk93_retro.json.
RETRO_FRACTION = 0.25


@dataclass(frozen=True)
class RetroLobe:
    """An environment-sampling strategy for a backward-scattering layer seen at ``view``:
    the Henyey-Greenstein distribution p(wi) = (1 - k^2) / (4 pi (1 + k^2 - 2 k wi.wo)^1.5)
    about the view direction wo (Henyey & Greenstein 1941; inverted as in pbrt-v3
    ``HenyeyGreenstein::Sample_p``).  A layer of mean cosine g < 0 and index eta backscatters
    about wi = wo with an angular width ~(1 - |g|) inside, ~eta (1 - |g|) outside (Snell near
    normal incidence), so k = 1 - eta (1 - |g|) (:meth:`for_layer`); the MIS weights count
    this density whatever the BRDF is, so the estimate stays unbiased for every model.

    view : (N, 3) unit directions to the eye; fraction : share of the samples; k : in [0, 1)
    """

    view: np.ndarray
    fraction: float = RETRO_FRACTION
    k: float = 0.9

    @staticmethod
    def k_for_layer(g: float, eta: float) -> float:
        return float(min(max(1.0 - eta * (1.0 - abs(g)), 0.0), 0.999))

    def __getitem__(self, sl) -> "RetroLobe":
        return RetroLobe(self.view[sl], self.fraction, self.k)

    def sample(self, u: np.ndarray) -> np.ndarray:
        """(N, S, 3) directions for uniform (N, S, 2) numbers."""
        a = normalize(np.asarray(self.view, np.float64))
        k = self.k
        if k < 1e-3:
            cos_a = 1.0 - 2.0 * u[..., 0]
        else:
            sq = (1.0 - k * k) / (1.0 - k + 2.0 * k * u[..., 0])
            cos_a = np.clip((1.0 + k * k - sq * sq) / (2.0 * k), -1.0, 1.0)
        return about_axis(a, cos_a, _TWO_PI * u[..., 1])

    def pdf(self, directions: np.ndarray) -> np.ndarray:
        """(N, S) solid-angle density of (N, S, 3) directions."""
        a = normalize(np.asarray(self.view, np.float64))
        c = np.einsum("nsk,nk->ns", directions, a)
        k = self.k
        return (1.0 - k * k) / (4.0 * math.pi * np.maximum(1.0 + k * k - 2.0 * k * c, 1e-30)
                                ** 1.5)
