/* brdf_lafortune.cl - measured-skin Lafortune BRDF with an albedo texture (docs/physics.md §1).
 *
 * Model: generalised cosine lobes, Lafortune, Foo, Torrance & Greenberg, "Non-linear
 * approximation of reflectance functions", SIGGRAPH 1997, eq. 4, isotropic (Cx = Cy):
 *     f(wo, wi) = albedo / pi + sum_k max(0, Cxy_k (wo.x wi.x + wo.y wi.y) + Cz_k wo.z wi.z)^n_k
 * per RGB channel.  Coefficients: the three-lobe skin fit shipped in pbrt-v1
 * materials/skin.cpp (table in docs/physics.md §1, defaults in stages/brdf_models.py
 * LafortuneParams).  Variant: per-lobe rho_s folded into C (as pbrt-v1), and the constant
 * rho_d replaced by a linear-RGB albedo per shading point, as the thesis did (Arizpe 2006).
 * Energy: the directional albedo is  albedo + L(theta_o), where the fitted lobes alone give
 * L = (0.031, 0.022, 0.022) at normal incidence rising to (0.264, 0.261, 0.241) at 89 deg
 * (quadrature of the float64 reference; Monte Carlo of this kernel agrees).  So it exceeds 1
 * wherever the albedo texture is above 1 - L: above ~0.97 at normal incidence, ~0.74 at
 * 89 deg; with pbrt-v1's rho_d it peaks at 0.69 (R, 89 deg).  Not corrected (the thesis used
 * the fit as is); documented and bounded in tests/test_brdf_lafortune.py test04_*.
 *
 * Conventions: local shading frame, z = shading normal; wo and wi unit vectors pointing away
 * from the surface; f excludes the cosine; float32.  f = 0 if wo or wi is on or below the
 * horizon (z <= 0).  The model is symmetric in (wo, wi), hence reciprocal.
 *
 * Parameter block (LAFORTUNE_NPARAMS floats, __constant): for lobe k = 0..2 at 9k:
 *     Cxy (R,G,B), Cz (R,G,B), n (R,G,B).
 * A shading kernel may #include this file; define DERMIS_NO_EVAL_KERNELS to leave out the
 * test kernel.
 * Guarded by tests/test_brdf_lafortune.py (float64 reference, lobes-off closed form,
 * reciprocity, Monte Carlo directional albedo, grazing/back-facing finiteness).
 */
#ifndef DERMIS_BRDF_LAFORTUNE_CL
#define DERMIS_BRDF_LAFORTUNE_CL

#include "common.h"

#define LAFORTUNE_NLOBES  3
#define LAFORTUNE_NPARAMS 27

/* One generalised cosine lobe, RGB; a non-positive base gives 0 (pbrt-v1 skin.cpp). */
inline float3 lafortune_lobe(float xy, float zz, __constant const float *lobe) {
    float3 cxy = vload3(0, lobe);
    float3 cz = vload3(1, lobe);
    float3 n = vload3(2, lobe);
    float3 base = cxy * xy + cz * zz;
    /* base^n as exp2(n log2 base): PoCL's powr is a scalar libm call (7x slower in
     * bench/bench_brdf.py); clamp before, select after, so no NaN or -inf is ever formed */
    float3 v = exp2(n * log2(fmax(base, (float3)(FLT_MIN))));
    return select((float3)(0.0f), v, isgreater(base, (float3)(0.0f)));
}

/* f(wo, wi) in 1/sr, RGB. albedo: linear RGB diffuse albedo replacing rho_d. */
inline float3 lafortune_f(float3 wo, float3 wi, float3 albedo, __constant const float *p) {
    float xy = wo.x * wi.x + wo.y * wi.y;
    float zz = wo.z * wi.z;
    float3 f = albedo * DERMIS_INV_PI
             + lafortune_lobe(xy, zz, p)
             + lafortune_lobe(xy, zz, p + 9)
             + lafortune_lobe(xy, zz, p + 18);
    /* back-facing or horizon: no reflection */
    return (wo.z > 0.0f && wi.z > 0.0f) ? f : (float3)(0.0f);
}

#ifndef DERMIS_NO_EVAL_KERNELS
/* Evaluate f for n (wo, wi, albedo) triples stored as packed xyz float arrays (tests). */
__kernel void lafortune_eval(__global const float *wo, __global const float *wi,
                             __global const float *albedo, __constant const float *params,
                             __global float *out, const int n) {
    int i = get_global_id(0);
    if (i >= n) return;
    vstore3(lafortune_f(vload3(i, wo), vload3(i, wi), vload3(i, albedo), params), i, out);
}
#endif

#endif
