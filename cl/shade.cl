/* shade.cl - reflected radiance of light samples through a BRDF (renderer, rendering/shade.py).
 *
 * One work-item per (surface point, light sample) pair that survived the host's culling
 * (above both horizons, unoccluded).  It writes
 *     L_s = f(wo, wi) * W_s * cos(theta_i)
 * and the host sums L_s per point, so the pixel is the estimator of lighting/emitters.py:
 * L_o = sum_s f(wo, wi_s) W_s cos(theta_s) V_s.  One item per sample instead of a loop over
 * samples keeps the body loop-free, so PoCL vectorises it across work-items
 * (docs/software.md, measured there).
 *
 * Models (docs/science.md §1, §2, §5), chosen with -D DERMIS_BASE:
 *   0 lambert (albedo / pi, test material and asperity base), 1 lafortune
 *   (cl/brdf_lafortune.cl, albedo texture replaces rho_d as in the thesis), 2 hk93
 *   (cl/brdf_hk93.cl), -1 none (the asperity term alone: a linear image a caller may add to
 *   another, e.g. a BSSRDF image; no stage does).
 * -D DERMIS_ASPERITY=1 adds the Koenderink-Pont term (cl/asperity.cl) on top of the base:
 * "a term added on top of a skin model" (docs/science.md §5); the base is seen through the
 * asperity layer (asperity_transmit), which keeps the sum's albedo <= 1.
 *
 * Conventions: local shading frame from the (bumped) shading normal with make_frame
 * (common.h); wo, wi unit, pointing away from the surface; f excludes the cosine; cos is
 * measured from the shading normal and clamped at 0; float32.  Back-facing views
 * (wo.z <= 0) give 0 through the models themselves.
 * Guarded by tests/test_render.py (analytic Lambertian sphere, Lafortune lobes-off image,
 * model images finite).
 */
#define DERMIS_NO_EVAL_KERNELS
#include "common.h"
#include "brdf_lafortune.cl"
#include "brdf_hk93.cl"
#include "asperity.cl"

#ifndef DERMIS_BASE
#define DERMIS_BASE 0
#endif
#ifndef DERMIS_ASPERITY
#define DERMIS_ASPERITY 0
#endif

__kernel void shade_samples(
    __global const int *point, __global const float *wi_world, __global const float *weight,
    const int n,
    __global const float *shading_normal, __global const float *wo_world,
    __global const float *albedo,
    __constant const float *base_params, __constant const float *asperity_params,
    __global float *out)
{
    int i = get_global_id(0);
    if (i >= n) return;
    int h = point[i];
    float3 nrm = vload3(h, shading_normal);
    float3 t, b;
    make_frame(nrm, &t, &b);
    float3 wo = to_local(vload3(h, wo_world), t, b, nrm);
    float3 wi = to_local(vload3(i, wi_world), t, b, nrm);
    float3 a = vload3(h, albedo);

#if DERMIS_BASE == 0
    float3 f = (wo.z > 0.0f && wi.z > 0.0f) ? a * DERMIS_INV_PI : (float3)(0.0f);
#elif DERMIS_BASE == 1
    float3 f = lafortune_f(wo, wi, a, base_params);
#elif DERMIS_BASE == 2
    /* texture tint of the constant multiple-scattering term: the host passes albedo / Rd of
     * the layers (1 where untextured), so rho_ms -> rho_ms * a (HK93Params.texture_reference) */
    float3 f = hk93_f(wo, wi, base_params)
             + vload3(0, base_params + 16) * (a - (float3)(1.0f)) * DERMIS_INV_PI;
    if (!(wo.z > 0.0f && wi.z > 0.0f)) f = (float3)(0.0f);
#else
    float3 f = (float3)(0.0f);
#endif
#if DERMIS_ASPERITY
    f = f * asperity_transmit(wo, wi, asperity_params) + asperity_f(wo, wi, asperity_params);
#endif

    vstore3(f * vload3(i, weight) * fmax(wi.z, 0.0f), i, out);
}
