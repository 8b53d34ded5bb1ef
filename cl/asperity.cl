/* asperity.cl - Koenderink-Pont asperity scattering term (docs/science.md §5 in this repository).
 *
 * Source: J. J. Koenderink, S. C. Pont, "The secret of velvety skin", Machine Vision and
 * Applications 14:260-268, 2003 (doi:10.1007/s00138-002-0089-7): a thin layer (thickness
 * Delta) of sparse scatterers with mean free path lambda = 1/(sigma_t rho) >> Delta, single
 * scattering, isotropic phase function 1/(4 pi).  The optically thin limit of the slab
 * single-scattering BRDF  W/(4 pi (mu_i + mu_o)) (1 - exp(-tau (1/mu_i + 1/mu_o))),
 * tau = Delta/lambda, is
 *     f = albedo * Delta / (4 pi lambda max(mu_i, Delta/lambda) max(mu_o, Delta/lambda))
 * Variant: both cosines clamped below at Delta/lambda (the thesis's fix for the grazing
 * singularity, Arizpe 2006; it is where the thin-layer expansion stops holding, since the
 * slant optical depth tau/mu reaches 1); optional cap f <= f_max (one public renderer
 * clamped f to 1; default here: no cap, the cosine clamp already bounds f by
 * lambda/(4 pi Delta)).  With the clamp the directional albedo has the closed form
 *     a(mu_o) = albedo * tau (1 - tau/2) / (2 max(mu_o, tau)) < 1/2,
 * checked in tests/test_asperity.py.  albedo is the scatterers' single-scattering albedo
 * (K-P use 1).
 * This is a term ADDED on top of a skin model (the base is the renderer's choice; the default
 * is documented with models/asperity.py AsperityParams), never a material on its own.
 * The base lies under the layer, so its light crosses the layer twice (flag [5];
 * docs/science.md §5, asperity scattering).  To the model's own first order the layer intercepts
 * e1(mu) = tau (1 - tau/2) / max(mu, tau) of a beam (same clamp), scatters a of it (half
 * back: the term's albedo A = a e1 / 2; half on, its angular spread neglected) and absorbs
 * 1 - a: the base receives T(mu) = 1 - (1 - a/2) e1(mu), both ways, so cl/shade.cl
 * multiplies the base by asperity_transmit = T(mu_i) T(mu_o).  Then the directional albedo
 * of term + base is at most A + T = 1 - (1 - a) e1 <= 1 for any base whose own albedo is
 * <= 1 (tests/test_energy.py); without it a Lambert base above albedo ~0.51 exceeds 1 near
 * grazing.  Reciprocal (symmetric product).
 *
 * Conventions: local frame, z = shading normal; wo, wi unit, pointing away from the surface;
 * f excludes the cosine; float32; Delta and lambda in mm (only their ratio enters f).
 * f = 0 when wo or wi is on or below the horizon.  Symmetric, hence reciprocal.
 * Parameter block (ASPERITY_NPARAMS floats, __constant; packed by models/asperity.py):
 *   [0] tau = Delta/lambda  [1] f_max  [2..4] albedo (R,G,B)  [5] attenuate the base
 *   (1) or not (0)  [6..7] unused (0)
 * Guarded by tests/test_asperity.py (float64 reference, closed forms, reciprocity, albedo,
 * grazing/back-facing finiteness).
 */
#ifndef DERMIS_ASPERITY_CL
#define DERMIS_ASPERITY_CL

#include "common.h"

#define ASPERITY_NPARAMS 8

/* f(wo, wi) in 1/sr, RGB, of the asperity layer alone. */
inline float3 asperity_f(float3 wo, float3 wi, __constant const float *p) {
    float tau = p[0], f_max = p[1];
    float3 albedo = vload3(0, p + 2);
    /* grazing: clamp cos at Delta/lambda (Koenderink-Pont; thesis) */
    float mo = fmax(wo.z, tau), mi = fmax(wi.z, tau);
    float3 f = fmin(albedo * (tau * DERMIS_INV_4PI / (mo * mi)), (float3)(f_max));
    /* back-facing or horizon: no reflection */
    return (wo.z > 0.0f && wi.z > 0.0f) ? f : (float3)(0.0f);
}

/* Transmittance of the layer seen by a base model below it, both ways, RGB (header
 * comment); 1 where the flag is off. */
inline float3 asperity_transmit(float3 wo, float3 wi, __constant const float *p) {
    float tau = p[0];
    float3 keep = (float3)(1.0f) - 0.5f * vload3(0, p + 2);   /* 1 - a/2 */
    float e = tau * (1.0f - 0.5f * tau);
    float3 t = ((float3)(1.0f) - keep * (e / fmax(wo.z, tau)))
             * ((float3)(1.0f) - keep * (e / fmax(wi.z, tau)));
    return p[5] != 0.0f ? t : (float3)(1.0f);
}

#ifndef DERMIS_NO_EVAL_KERNELS
/* Evaluate f for n (wo, wi) pairs stored as packed xyz float arrays (tests). */
__kernel void asperity_eval(__global const float *wo, __global const float *wi,
                            __constant const float *params, __global float *out, const int n) {
    int i = get_global_id(0);
    if (i >= n) return;
    vstore3(asperity_f(vload3(i, wo), vload3(i, wi), params), i, out);
}
#endif

#endif
