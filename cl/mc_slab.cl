/* mc_slab.cl - Monte Carlo photon transport in a layered slab (the project's ground truth
 * for layer optics), in the spirit of MCML (Wang, Jacques, Zheng 1995, "MCML - Monte Carlo
 * modeling of light transport in multi-layered tissues", Comput. Meth. Prog. Biomed. 47).
 *
 * Model: a pencil beam at normal incidence at the origin enters layer 0 with weight 1 (the
 * specular reflection Rsp at entry is left out: R and T are per photon that entered, the
 * normalisation of the diffusion profiles; MCML's numbers per incident photon are ours
 * times 1 - Rsp).  Free paths exp(-sigma_t s) with sigma_t = sigma_a + sigma_s of the
 * current layer; a step that reaches a boundary stops there and keeps its remaining
 * optical depth for the next layer (MCML's step splitting).  At every boundary,
 * including those between layers of different eta, unpolarised Fresnel reflectance
 * decides reflect or refract (all-or-none, MCML's default); total internal reflection
 * when sin_t >= 1.  At an interaction the weight drops by sigma_a / sigma_t (scored as
 * absorbed), and the direction is drawn from Henyey-Greenstein (MCML's "Spin").  Russian
 * roulette below W_MIN with survival 1/ROULETTE_M (MCML's 1e-4 and 10).  A photon still
 * alive after MAX_STEPS interactions is scored as "lost" (only sigma_a ~ 0 media do this).
 *
 * Scoring: per work-item private slices of global memory (no atomics: PoCL's float atomics
 * are compare-exchange loops), radial bins of width 1/inv_dr for escapes through the top
 * (R) and the bottom (T); totals R, T, absorbed, lost.  The host sums the slices in float64
 * and groups work-items into batches for standard errors.
 *
 * Conventions: z down into the slab, mm and 1/mm, float32.  Random numbers: Philox4x32-10
 * keyed by the seed, one stream per (work-item, channel) (rng.h).
 * Guarded by tests/test_mc_slab.py.
 */
#include "rng.h"

#define DERMIS_PI_F 3.14159265358979323846f

#define W_MIN 1e-4f
#define ROULETTE_M 10.0f
#define MAX_STEPS 1000000

/* layer table: per channel and layer 8 floats: z_top, z_bot, sigma_a, sigma_s, g, eta, -, - */
__kernel void mc_slab(__global const float *layers, const int n_layers,
                      const float eta_above, const float eta_below,
                      const uint seed, const int photons_per_item,
                      const int n_bins, const float inv_dr,
                      __global float *hist,   /* [3][items][2][n_bins] */
                      __global float *totals) /* [3][items][5]: R, T, absorbed, lost, interactions */
{
    const int item = get_global_id(0);
    const int items = get_global_size(0);
    const int ch = get_global_id(1);
    __global const float *L = layers + ch * n_layers * 8;
    __global float *hR = hist + ((size_t)(ch * items + item) * 2) * n_bins;
    __global float *hT = hR + n_bins;
    philox_t rng = philox_init(seed, 0x6d635f73u, (uint)item, (uint)ch);

    float sumR = 0.0f, sumT = 0.0f, sumA = 0.0f, sumLost = 0.0f;
    uint n_steps = 0u;
    for (int p = 0; p < photons_per_item; ++p) {
        float x = 0.0f, y = 0.0f, z = 0.0f;
        float ux = 0.0f, uy = 0.0f, uz = 1.0f;
        float w = 1.0f, tau = 0.0f;
        int lay = 0;
        float z0 = L[0], z1 = L[1], mua = L[2], mus = L[3], g = L[4], eta = L[5];
        float mut = mua + mus, inv_mut = 1.0f / mut;
        int steps = 0;
        for (;;) {
            if (tau <= 0.0f) tau = -native_log(philox_uniform(&rng));
            float s = tau * inv_mut;
            float db = uz > 0.0f ? (z1 - z) / uz : (uz < 0.0f ? (z0 - z) / uz : INFINITY);
            if (s >= db) {
                /* boundary: move onto it, keep the remaining optical depth */
                x += db * ux; y += db * uy; z = uz > 0.0f ? z1 : z0;
                tau -= db * mut;
                int nb = uz > 0.0f ? lay + 1 : lay - 1;
                float n2 = nb < 0 ? eta_above : (nb >= n_layers ? eta_below : L[nb * 8 + 5]);
                float ci = fabs(uz);
                float rf = 0.0f, ct = ci;
                if (n2 != eta) {
                    float ratio = eta / n2;
                    float st2 = ratio * ratio * (1.0f - ci * ci);
                    if (st2 >= 1.0f) {
                        rf = 1.0f;                       /* total internal reflection */
                    } else {
                        ct = sqrt(1.0f - st2);
                        float rs = (eta * ci - n2 * ct) / (eta * ci + n2 * ct);
                        float rp = (eta * ct - n2 * ci) / (eta * ct + n2 * ci);
                        rf = 0.5f * (rs * rs + rp * rp);
                    }
                }
                if (philox_uniform(&rng) <= rf) {
                    uz = -uz;
                    continue;
                }
                if (nb < 0) {                             /* escapes through the top */
                    int b = (int)(sqrt(x * x + y * y) * inv_dr);
                    if (b < n_bins) hR[b] += w;
                    sumR += w;
                    break;
                }
                if (nb >= n_layers) {                     /* escapes through the bottom */
                    int b = (int)(sqrt(x * x + y * y) * inv_dr);
                    if (b < n_bins) hT[b] += w;
                    sumT += w;
                    break;
                }
                /* refract into the neighbouring layer (Snell), continue the step there */
                float ratio = eta / n2;
                ux *= ratio; uy *= ratio; uz = copysign(ct, uz);
                lay = nb;
                __global const float *q = L + nb * 8;
                z0 = q[0]; z1 = q[1]; mua = q[2]; mus = q[3]; g = q[4]; eta = q[5];
                mut = mua + mus; inv_mut = 1.0f / mut;
                continue;
            }
            x += s * ux; y += s * uy; z += s * uz;
            tau = 0.0f;
            /* absorption: deposit the fraction sigma_a / sigma_t */
            float dw = w * (mua * inv_mut);
            sumA += dw;
            w -= dw;
            /* Henyey-Greenstein deflection (MCML Spin) */
            float u1 = philox_uniform(&rng);
            float cth;
            if (fabs(g) > 1e-3f) {
                float t = (1.0f - g * g) / (1.0f - g + 2.0f * g * u1);
                cth = (1.0f + g * g - t * t) / (2.0f * g);
            } else {
                cth = 2.0f * u1 - 1.0f;
            }
            cth = clamp(cth, -1.0f, 1.0f);
            float sth = native_sqrt(fmax(1.0f - cth * cth, 0.0f));
            float phi = 2.0f * DERMIS_PI_F * philox_uniform(&rng);
            float cph = native_cos(phi), sph = native_sin(phi);
            if (fabs(uz) > 0.99999f) {
                ux = sth * cph; uy = sth * sph; uz = uz > 0.0f ? cth : -cth;
            } else {
                float tmp = native_sqrt(1.0f - uz * uz);
                float itmp = native_recip(tmp);
                float nx = sth * (ux * uz * cph - uy * sph) * itmp + ux * cth;
                float ny = sth * (uy * uz * cph + ux * sph) * itmp + uy * cth;
                uz = -sth * cph * tmp + uz * cth;
                ux = nx; uy = ny;
            }
            /* renormalise: float rounding drifts over thousands of deflections */
            float inv = native_rsqrt(ux * ux + uy * uy + uz * uz);
            ux *= inv; uy *= inv; uz *= inv;
            if (w < W_MIN) {
                if (philox_uniform(&rng) * ROULETTE_M <= 1.0f) w *= ROULETTE_M;
                else break;
            }
            if (++steps >= MAX_STEPS) { sumLost += w; break; }
        }
        n_steps += (uint)steps;
    }
    __global float *t = totals + (size_t)(ch * items + item) * 5;
    t[0] = sumR; t[1] = sumT; t[2] = sumA; t[3] = sumLost; t[4] = (float)n_steps;
}
