/* brdf_lafortune.cl - measured-skin Lafortune BRDF with an albedo texture (docs/science.md §1).
 *
 * Model: generalised cosine lobes, Lafortune, Foo, Torrance & Greenberg, "Non-linear
 * approximation of reflectance functions", SIGGRAPH 1997, eq. 4, isotropic (Cx = Cy):
 *     f(wo, wi) = albedo / pi + sum_k max(0, Cxy_k (wo.x wi.x + wo.y wi.y) + Cz_k wo.z wi.z)^n_k
 * per RGB channel.  Coefficients: the three-lobe skin fit shipped in pbrt-v1
 * materials/skin.cpp (table in docs/science.md §1, defaults in models/lafortune.py
 * LafortuneParams).  Variant: per-lobe rho_s folded into C (as pbrt-v1), and the constant
 * rho_d replaced by a linear-RGB albedo per shading point, as the thesis did (Arizpe 2006).
 * Energy: the fitted lobes alone reflect L(theta) = (0.031, 0.022, 0.022) at normal incidence
 * rising to (0.264, 0.261, 0.241) at 89 deg (quadrature of the float64 reference).  With the
 * plain diffuse term albedo / pi the directional albedo, albedo + L, exceeds 1 wherever the
 * texture is above 1 - L (~0.74 at 89 deg).  The default couples the diffuse term to the
 * lobes (Kelemen & Szirmay-Kalos 2001, "A microfacet based coupled specular-matte BRDF
 * model with importance sampling", Eurographics short papers):
 *     f_d = albedo (1 - L(mu_i)) (1 - L(mu_o)) / (pi (1 - L_mean)),  L_mean = int L 2 mu dmu,
 * whose directional albedo is albedo (1 - L(mu_o)), so the whole BRDF reflects
 * L + albedo (1 - L) <= 1 for any albedo <= 1, and stays reciprocal (docs/science.md §1).
 * L is tabulated on the host (models/lafortune.py lafortune_lobe_albedo) at
 * LAFORTUNE_ALBEDO_NODES cosines and interpolated linearly here; flag [27] = 0 gives the
 * uncoupled fit (the thesis's).  Guarded by tests/test_energy.py and
 * tests/test_brdf_lafortune.py test04_*.
 *
 * Conventions: local shading frame, z = shading normal; wo and wi unit vectors pointing away
 * from the surface; f excludes the cosine; float32.  f = 0 if wo or wi is on or below the
 * horizon (z <= 0).  The model is symmetric in (wo, wi), hence reciprocal.
 *
 * Parameter block (LAFORTUNE_NPARAMS floats, __constant): for lobe k = 0..2 at 9k:
 *     Cxy (R,G,B), Cz (R,G,B), n (R,G,B); [27] coupling flag (1: coupled diffuse term),
 *     [28..30] 1 / (1 - L_mean) RGB, [31 + 3 j + c] L(mu_j) of channel c at
 *     mu_j = j / (LAFORTUNE_ALBEDO_NODES - 1).
 * A shading kernel may #include this file; define DERMIS_NO_EVAL_KERNELS to leave out the
 * test kernel.
 * Guarded by tests/test_brdf_lafortune.py (float64 reference, lobes-off closed form,
 * reciprocity, Monte Carlo directional albedo, grazing/back-facing finiteness).
 */
#ifndef DERMIS_BRDF_LAFORTUNE_CL
#define DERMIS_BRDF_LAFORTUNE_CL

#include "common.h"

#define LAFORTUNE_NLOBES  3
#define LAFORTUNE_ALBEDO_NODES 64
#define LAFORTUNE_NPARAMS 223   /* 27 + 4 + 3 * LAFORTUNE_ALBEDO_NODES */

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

/* 1 - L(mu): one minus the lobes' directional albedo at cosine mu (linear in the table). */
inline float3 lafortune_unreflected(float mu, __constant const float *p) {
    float t = clamp(mu, 0.0f, 1.0f) * (float)(LAFORTUNE_ALBEDO_NODES - 1);
    int j = min((int)t, LAFORTUNE_ALBEDO_NODES - 2);
    float3 a = vload3(0, p + 31 + 3 * j), b = vload3(0, p + 34 + 3 * j);
    return (float3)(1.0f) - mix(a, b, t - (float)j);
}

/* f(wo, wi) in 1/sr, RGB. albedo: linear RGB diffuse albedo replacing rho_d. */
inline float3 lafortune_f(float3 wo, float3 wi, float3 albedo, __constant const float *p) {
    float xy = wo.x * wi.x + wo.y * wi.y;
    float zz = wo.z * wi.z;
    float3 diffuse = albedo * DERMIS_INV_PI;
    if (p[27] != 0.0f)   /* coupled to the lobes (header comment) */
        diffuse *= lafortune_unreflected(wi.z, p) * lafortune_unreflected(wo.z, p)
                 * vload3(0, p + 28);
    float3 f = diffuse
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
