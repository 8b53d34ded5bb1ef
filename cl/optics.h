/* optics.h - interface optics and phase functions shared by the reflectance models.
 *
 * Contents: Snell refraction of cosines, unpolarised Fresnel reflectance of a smooth
 * dielectric boundary, its diffuse (hemispherical) average Fdr, and the Henyey-Greenstein
 * phase function.  docs/science.md §2, §3.
 *
 * Conventions (common.h): float32; cosines measured from the shading normal; "eta" is
 * always the RELATIVE index n_transmitted / n_incident unless the name says otherwise.
 * Guarded by tests/test_brdf_hk93.py (through hk93_f) and models/hk93.py's float64
 * references.
 */
#ifndef DERMIS_OPTICS_H
#define DERMIS_OPTICS_H

#include "common.h"

/* Cosine of the refracted angle for a ray entering a medium of relative index eta >= 1
 * with cosine cos_i (>= 0).  Written as sqrt(eta^2 - 1 + cos_i^2)/eta instead of
 * sqrt(1 - (1 - cos_i^2)/eta^2): the latter cancels to 0 in float32 at grazing when eta = 1.
 * Snell's law across parallel interfaces depends only on the outside angle, so
 * refract_cos(cos_0, n_k) gives the cosine inside layer k of a stack directly. */
inline float refract_cos(float cos_i, float eta) {
    return sqrt(fmax(eta * eta - 1.0f + cos_i * cos_i, 0.0f)) / eta;
}

/* Unpolarised Fresnel reflectance of a smooth dielectric boundary from the two cosines
 * (incident cos_i, transmitted cos_t) and relative index eta = n_t / n_i (Born & Wolf;
 * pbrt-v3 FrDielectric).  Symmetric under (cos_i, cos_t, eta) -> (cos_t, cos_i, 1/eta), so
 * the transmittance in and out of a layer is the same function of the ray: reciprocity.
 * cos_i = cos_t = 0 gives 0/0; callers keep cosines >= a small positive floor. */
inline float fresnel_dielectric(float cos_i, float cos_t, float eta) {
    float rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    float rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    return 0.5f * (rs * rs + rp * rp);
}

/* Fresnel transmittance 1 - F for the same arguments, written as
 * 1 - r^2 = (1 - r)(1 + r) per polarisation: 2 eta ci ct (1/(ci + eta ct)^2 + 1/(eta ci + ct)^2).
 * At grazing F -> 1 and the plain 1 - F loses every digit in float32; this form keeps
 * T ~ cos_i accurate to a few ulp. */
inline float fresnel_transmit(float cos_i, float cos_t, float eta) {
    float s = cos_i + eta * cos_t;
    float p = eta * cos_i + cos_t;
    return 2.0f * eta * cos_i * cos_t * (1.0f / (s * s) + 1.0f / (p * p));
}

/* Diffuse Fresnel reflectance Fdr(eta), polynomial fits quoted in docs/science.md §3
 * (Egan & Hilgeman 1973 for eta >= 1; Jensen et al. 2001 eq. for eta < 1). */
inline float fresnel_diffuse_reflectance(float eta) {
    float inv = 1.0f / eta;
    return eta >= 1.0f
        ? -1.440f * inv * inv + 0.710f * inv + 0.668f + 0.0636f * eta
        : -0.4399f + 0.7099f * inv - 0.3319f * inv * inv + 0.0636f * inv * inv * inv;
}

/* Henyey-Greenstein phase function (1/sr) of the cosine of the scattering angle between the
 * propagation directions before and after scattering; normalised over the sphere. */
inline float henyey_greenstein(float cos_theta, float g) {
    float denom = 1.0f + g * g - 2.0f * g * cos_theta;
    return DERMIS_INV_4PI * (1.0f - g * g) / (denom * sqrt(denom));
}

/* The same phase function from 1 - cos and 1 + cos of the scattering angle, for callers that
 * have them without cancellation (|a - b|^2 / 2 and |a + b|^2 / 2 of the unit propagation
 * directions a, b).  1 + g^2 - 2 g cos = (1 - g)^2 + 2 g (1 - cos) = (1 + g)^2 - 2 g (1 + cos):
 * the form picked by the sign of g adds two non-negative terms, so the peak of |g| -> 1,
 * where the plain form cancels to (1 - |g|)^2, keeps full float32 accuracy; (1 - g)(1 + g)
 * likewise replaces 1 - g^2. */
inline float henyey_greenstein_split(float one_minus_cos, float one_plus_cos, float g) {
    float a = 1.0f - g, b = 1.0f + g;
    float denom = g >= 0.0f ? a * a + 2.0f * g * one_minus_cos : b * b - 2.0f * g * one_plus_cos;
    return DERMIS_INV_4PI * (a * b) / (denom * sqrt(denom));
}

#endif
