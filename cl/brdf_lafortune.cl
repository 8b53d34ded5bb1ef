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
 * reciprocity, Monte Carlo directional albedo, grazing/back-facing finiteness, the lobes'
 * edge against the exact sum) and tests/test_stability.py.
 */
#ifndef DERMIS_BRDF_LAFORTUNE_CL
#define DERMIS_BRDF_LAFORTUNE_CL

#include "common.h"

#define LAFORTUNE_NLOBES  3
#define LAFORTUNE_ALBEDO_NODES 64
#define LAFORTUNE_NPARAMS 223   /* 27 + 4 + 3 * LAFORTUNE_ALBEDO_NODES */

/* The lobes' shared arguments x = wo.x wi.x + wo.y wi.y and z = wo.z wi.z, each as an
 * unevaluated float32 pair hi + lo: (x_hi, x_lo, z_hi, z_lo).  Both products of x and z are
 * split exactly by fma (a b = fl(a b) + fma(a, b, -fl(a b))) and x_hi + x_lo by Knuth's
 * TwoSum, so z is exact and x exact but for the roundings of x_lo: 3 2^-48 (|wo.x wi.x| +
 * |wo.y wi.y|) at most.  No contraction here: it would break the splits. */
inline float4 lafortune_args(float3 wo, float3 wi) {
#pragma OPENCL FP_CONTRACT OFF
    float p = wo.x * wi.x, q = wo.y * wi.y, z = wo.z * wi.z;
    float s = p + q, v = s - p;
    float t = (p - (s - v)) + (q - v);                  /* p + q = s + t exactly */
    float lo = t + (fma(wo.x, wi.x, -p) + fma(wo.y, wi.y, -q));
    return (float4)(s, lo, z, fma(wo.z, wi.z, -z));
}

/* One generalised cosine lobe, RGB; a non-positive base gives 0 (pbrt-v1 skin.cpp).
 * base = Cxy x + Cz z is a sum of terms up to |C| that cancel at the lobe's edge: where the
 * horizontal parts of wo and wi are at right angles (x = 0 from two products ~0.4) or a
 * grazing z balances Cxy x.  Plain float32 errs there by ~2^-24 of the terms, which is all
 * of a base of 1e-7, and base^n keeps n times the base's relative error: at n = 0.1 a base of
 * 5e-7 came out 2.3 % low, f 0.23 % (float32 0.7012287 against 0.7028639 in float64).  Here
 * the products are exact (args above, Kahan's fma pair for Cz z_hi) and the low parts are
 * added last, so base is within 2^-23 of itself plus 2^-45 (|Cxy| (|wo.x wi.x| + |wo.y wi.y|)
 * + |Cz z|): f_lobe within n 2^-23 plus the exp2/log2 error of the value for the given float32
 * directions (tests/test_brdf_lafortune.py test06 against the exact sum).  Cost: the eval
 * kernel 15 % slower (bench/bench_brdf.py's pairs, A/B medians of 100 on shared cores). */
inline float3 lafortune_lobe(float4 a, __constant const float *lobe) {
#pragma OPENCL FP_CONTRACT OFF
    float3 cxy = vload3(0, lobe);
    float3 cz = vload3(1, lobe);
    float3 n = vload3(2, lobe);
    float3 w = cz * a.z;
    float3 e = fma(cz, (float3)(a.z), -w);                  /* Cz z_hi = w + e exactly */
    float3 lo = fma(cxy, (float3)(a.y), fma(cz, (float3)(a.w), e));
    float3 base = fma(cxy, (float3)(a.x), w) + lo;
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
    float4 a = lafortune_args(wo, wi);
    float3 diffuse = albedo * DERMIS_INV_PI;
    if (p[27] != 0.0f)   /* coupled to the lobes (header comment) */
        diffuse *= lafortune_unreflected(wi.z, p) * lafortune_unreflected(wo.z, p)
                 * vload3(0, p + 28);
    float3 f = diffuse
             + lafortune_lobe(a, p)
             + lafortune_lobe(a, p + 9)
             + lafortune_lobe(a, p + 18);
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
