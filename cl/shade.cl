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

/* alpha: the control variate's coefficient of a hit (lighting/control.py): the cosine-weighted
 * mean over wi of the model's diffuse part, f_mean = int f_diffuse cos dwi / pi, so that
 * alpha L cos follows f L cos where f is diffuse.  Any value fixed per hit keeps the estimate
 * unbiased (the control terms have mean zero); this one makes the two cancel on unoccluded
 * diffuse surfaces.  Lambert: a / pi.  Lafortune: the coupled diffuse term's mean,
 * a (1 - L(mu_o)) / pi (its directional albedo is a (1 - L(mu_o)), docs/science.md §1), the
 * lobes left to the samples.  HK93: the constant multiple scattering rho_ms a / pi, single
 * scattering left to the samples.  Asperity (docs/science.md §5): the base's alpha x T(mu_o)
 * x the cosine-weighted mean of T(mu_i), 1 - (1 - a/2) tau (1 - tau/2) (2 - tau), plus the
 * term's directional albedo / pi, albedo tau (1 - tau/2) / (2 pi max(mu_o, tau)). */
inline float3 control_alpha(float3 wo, float3 a, __constant const float *base_params,
                            __constant const float *asperity_params) {
#if DERMIS_BASE == 0
    float3 alpha = a * DERMIS_INV_PI;
#elif DERMIS_BASE == 1
    float3 alpha = a * DERMIS_INV_PI;
    if (base_params[27] != 0.0f)
        alpha *= lafortune_unreflected(wo.z, base_params);
#elif DERMIS_BASE == 2
    float3 alpha = vload3(0, base_params + 16) * a * DERMIS_INV_PI;
#else
    float3 alpha = (float3)(0.0f);
#endif
#if DERMIS_ASPERITY
    {
        __constant const float *p = asperity_params;
        float tau = p[0];
        float3 alb = vload3(0, p + 2);
        float e = tau * (1.0f - 0.5f * tau);
        float mo = fmax(wo.z, tau);
        if (p[5] != 0.0f) {
            float3 keep = (float3)(1.0f) - 0.5f * alb;
            alpha *= ((float3)(1.0f) - keep * (e / mo))
                   * ((float3)(1.0f) - keep * (e * (2.0f - tau)));
        }
        alpha += alb * (e * 0.5f * DERMIS_INV_PI / mo);
    }
#endif
    return wo.z > 0.0f ? alpha : (float3)(0.0f);
}

/* Per sample (flags: bit 0 lit - unoccluded, above the geometric horizon; bit 1 in the control
 * variate's region; has_flags = 0: every sample lit):
 *     out = [lit] f(wo, wi) W cos_i  -  [control] alpha W (n_s . wi)
 * (n_s . wi not clamped: the control function is linear in n_s); with split_ctrl the two
 * terms apart: out = [lit] f W cos_i, ctrl_out = [control] alpha W (n_s . wi). */
__kernel void shade_samples(
    __global const int *point, __global const float *wi_world, __global const float *weight,
    const int n,
    __global const float *shading_normal, __global const float *wo_world,
    __global const float *albedo,
    __constant const float *base_params, __constant const float *asperity_params,
    __global const uchar *flags, const int has_flags,
    __global float *out, __global float *ctrl_out, const int split_ctrl)
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
    uchar fl = has_flags ? flags[i] : (uchar)1;

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

    float3 w = vload3(i, weight);
    float3 res = (fl & 1) ? f * w * fmax(wi.z, 0.0f) : (float3)(0.0f);
    float3 c = (fl & 2) ? control_alpha(wo, a, base_params, asperity_params) * w * wi.z
                        : (float3)(0.0f);
    /* split_ctrl: the lit term and the control term apart (one pass for both sums) */
    if (split_ctrl) vstore3(c, i, ctrl_out);
    else res -= c;
    vstore3(res, i, out);
}

/* The control variate's integral at each hit (lighting/control.py): alpha n_s . M_b, M_b the
 * (3 x 3, RGB x world xyz) moments of the hit's bin (bin < 0: none). */
__kernel void shade_control(
    const int n, __global const int *control_bin, __global const float *table,
    __global const float *shading_normal, __global const float *wo_world,
    __global const float *albedo,
    __constant const float *base_params, __constant const float *asperity_params,
    __global float *out)
{
    int h = get_global_id(0);
    if (h >= n) return;
    int bin = control_bin[h];
    float3 nrm = vload3(h, shading_normal);
    float3 res = (float3)(0.0f);
    if (bin >= 0) {
        float3 t, b;
        make_frame(nrm, &t, &b);
        float3 wo = to_local(vload3(h, wo_world), t, b, nrm);
        float3 m = (float3)(dot(vload3(3 * bin, table), nrm), dot(vload3(3 * bin + 1, table), nrm),
                            dot(vload3(3 * bin + 2, table), nrm));
        res = control_alpha(wo, vload3(h, albedo), base_params, asperity_params) * m;
    }
    vstore3(res, h, out);
}
