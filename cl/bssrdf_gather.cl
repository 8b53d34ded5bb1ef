/* bssrdf_gather.cl - hierarchical (Jensen-Buhler 2002) and brute-force gather of radiant
 * exitance from cached irradiance sample points through a radial diffusion profile.
 *
 * Model: M_o(x) = sum_p R(|x - p|) E_p A_p  (physics.md section 4; Jensen & Buhler 2002,
 * "A rapid hierarchical rendering technique for translucent materials", eq. 3-4).  R(r) is
 * the layer file's radial profile R(r) in 1/mm^2 (stages/profiles.py), resampled on the
 * host into a uniform table that is zero beyond the per-channel cut-off radius.  The host
 * passes R convolved with the points' reconstruction Gaussian (stages/gather.py
 * blurred_profile; the flat-slab bound rests on it), so nothing here depends on which.
 *
 * Tree walk: the octree is flattened in depth-first pre-order with one "skip" index per
 * node (the next node outside its subtree), so the walk is a single forward loop with no
 * stack and no recursion (PoCL does not recurse; a skip index is one int per node where an
 * explicit stack would be a private array).  A node whose first child is not i+1 is internal;
 * a leaf has skip == i + 1 and owns points [start_i, start_{i+1}) (a sentinel node at the end
 * holds start = point count).
 * A node is used as one cluster when x lies outside its bounding sphere and its solid angle
 * A / d^2 < EPSILON (d = distance to its irradiance-weighted mean position); both tests are
 * folded on the host into one threshold open^2 = max(A / epsilon, radius^2) per node.  A node
 * whose bounding sphere lies wholly beyond the cut-off is skipped (the thesis gathered only
 * points in range); otherwise it is opened, and a leaf that cannot be clustered is summed
 * point by point.
 *
 * Cluster term (compile-time SECOND_ORDER, default 1): Jensen-Buhler use the zeroth-order
 * R(d) W; we add the second-order Taylor term of R(|x - p|) over the node's weighted
 * positional covariance (see cluster_profile).  Measured (bench/bench_gather.py): 6-13x lower
 * error at the same epsilon for ~20 % more time per visited node.
 *
 * Normalisation (compile-time THESIS_NORM):
 *   0 energy-correct: M = sum R E A with a table whose integral 2 pi r R dr equals Rd
 *     (tests/test_gather.py::test04_flat_slab_energy);
 *   1 thesis: M = Rd * sum R E A / sum R A (per channel), i.e. a profile-weighted average
 *     of the irradiance in range times Rd.
 *
 * Data layout (float32, mm): nodes are 4 float4 = 64 bytes (one cache line), see
 * gather_tree; node_start[i] = first point of node i (leaves own [start_i, start_{i+1}));
 *   pts_pa[j] = (x, y, z, A), pts_e[j] = (E A rgb, 0)  points in leaf (DFS) order;
 *   table[k] = R(k * TABLE_H) rgb; deriv[2k], deriv[2k+1] = R'' - R'/r, R'/r at the same r;
 *   TABLE_N entries, the last two zero (beyond every cut-off).
 * Guarded by tests/test_gather.py (flat slab on hex and on samples.run points per preset,
 * sphere, hierarchy vs brute force, zero irradiance).
 */
#include "common.h"

#ifndef TABLE_N
#define TABLE_N 1024
#endif
#ifndef THESIS_NORM
#define THESIS_NORM 0
#endif
#ifndef SECOND_ORDER
#define SECOND_ORDER 1
#endif

/* Linear interpolation in the uniform profile table; zero past its end (beyond cut-off). */
inline float3 profile_lookup(__global const float4 *table, float d, float inv_h) {
    float t = d * inv_h;
    int k = min((int)t, TABLE_N - 2);  /* entries TABLE_N-2.. are zero: clamping is exact */
    float f = t - (float)k;
    float4 a = table[k];
    float4 b = table[k + 1];
    return (t < (float)(TABLE_N - 1)) ? mix(a.xyz, b.xyz, f) : (float3)(0.0f);
}

/* Finish one query: energy mode stores M, thesis mode divides by the profile weight. */
inline float4 finish(float3 m, float3 w, float4 rd) {
#if THESIS_NORM
    float3 out = (float3)(w.x > 0.0f ? rd.x * m.x / w.x : 0.0f,
                          w.y > 0.0f ? rd.y * m.y / w.y : 0.0f,
                          w.z > 0.0f ? rd.z * m.z / w.z : 0.0f);
    return (float4)(out, 0.0f);
#else
    return (float4)(m, 0.0f);
#endif
}

/* Second-order cluster term: sum_i w_i R(|x - p_i|) ~ W [R(d) + 1/2 tr(H C)] with C the node's
 * weighted positional covariance and H the Hessian of R(|x - p|) at the node position:
 * H = R'' u u^T + (R'/d)(I - u u^T), so 1/2 tr(H C) = 1/2 [(R'' - R'/d) u^T C u + (R'/d) tr C].
 * TAB_A = R'' - R'/d and TAB_B = R'/d are tabulated per channel (float64 on the host). */
inline float3 cluster_profile(__global const float4 *table, __global const float4 *deriv,
                              float d2, float3 dv, float4 c0, float4 c1, float inv_h) {
    float d = sqrt(d2);
    float3 r = profile_lookup(table, d, inv_h);
#if SECOND_ORDER
    float t = d * inv_h;
    int k = min((int)t, TABLE_N - 2);
    float f = t - (float)k;
    float4 a0 = deriv[2 * k], b0 = deriv[2 * k + 1];
    float4 a1 = deriv[2 * k + 2], b1 = deriv[2 * k + 3];
    float3 ta = mix(a0.xyz, a1.xyz, f);
    float3 tb = mix(b0.xyz, b1.xyz, f);
    /* c0 = (Cxx, Cxy, Cxz, Cyy), c1 = (Cyz, Czz, -, -) */
    float3 cd = (float3)(c0.x * dv.x + c0.y * dv.y + c0.z * dv.z,
                         c0.y * dv.x + c0.w * dv.y + c1.x * dv.z,
                         c0.z * dv.x + c1.x * dv.y + c1.y * dv.z);
    float quad = dot(dv, cd) / d2;
    float trace = c0.x + c0.w + c1.y;
    r += 0.5f * (ta * quad + tb * trace);
    r = (t < (float)(TABLE_N - 1)) ? fmax(r, 0.0f) : (float3)(0.0f);
#endif
    return r;
}

__kernel void gather_tree(__global const float4 *query,     /* (Q) x, y, z, unused */
                          __global const float4 *node,      /* (K) 4 float4 per node */
                          __global const int *node_start,   /* (K + 1) first point */
                          const int n_nodes,
                          __global const float4 *pts_pa,
                          __global const float4 *pts_e,
                          __global const float4 *table,
                          __global const float4 *deriv,     /* (2 TABLE_N) R''-R'/d, R'/d */
                          const float inv_h,
                          const float4 rd,                  /* Rd rgb (thesis mode) */
                          const int n_query,
                          __global float4 *out,             /* (Q) M rgb */
                          __global int *visits)             /* (Q) nodes + points evaluated */
{
    /* node[4i]   = (p.xyz, reach^2)    reach = cut-off + bounding radius
     * node[4i+1] = (E A rgb, open^2)   open^2 = max(A / epsilon, radius^2): cluster beyond it
     * node[4i+2] = (Cxx, Cxy, Cxz, Cyy) weighted positional covariance
     * node[4i+3] = (Cyz, Czz, A, as_float(skip)) */
    int q = get_global_id(0);
    if (q >= n_query) return;
    float3 x = query[q].xyz;
    float3 m = (float3)(0.0f);
    float3 w = (float3)(0.0f);
    int count = 0;
    int i = 0;
    while (i < n_nodes) {
        float4 n0 = node[4 * i];
        float4 n3 = node[4 * i + 3];
        int skip = as_int(n3.w);
        float3 dv = n0.xyz - x;
        float d2 = dot(dv, dv);
        count++;
        if (d2 > n0.w) { i = skip; continue; }                    /* wholly beyond cut-off */
        float4 n1 = node[4 * i + 1];
        if (d2 > n1.w) {                                           /* small solid angle: cluster */
            float4 n2 = node[4 * i + 2];
            float3 r = cluster_profile(table, deriv, d2, dv, n2, n3.xyzw, inv_h);
            m += r * n1.xyz;
            w += r * n3.z;
            i = skip;
            continue;
        }
        if (skip == i + 1) {                                       /* leaf: sum its points */
            int end = node_start[i + 1];
            int j = node_start[i];
            count += end - j;
            for (; j < end; ++j) {
                float4 p = pts_pa[j];
                float3 dp = p.xyz - x;
                float3 r = profile_lookup(table, sqrt(dot(dp, dp)), inv_h);
                m += r * pts_e[j].xyz;
                w += r * p.w;
            }
        }
        i++;  /* first child, or (leaf) the next node: skip == i + 1 */
    }
    out[q] = finish(m, w, rd);
    visits[q] = count;
}

/* Reference: every point, no clustering, same profile lookup and normalisation. */
__kernel void gather_brute(__global const float4 *query,
                           __global const float4 *pts_pa,
                           __global const float4 *pts_e,
                           const int n_points,
                           __global const float4 *table,
                           const float inv_h,
                           const float4 rd,
                           const int n_query,
                           __global float4 *out)
{
    int q = get_global_id(0);
    if (q >= n_query) return;
    float3 x = query[q].xyz;
    float3 m = (float3)(0.0f);
    float3 w = (float3)(0.0f);
    for (int j = 0; j < n_points; ++j) {
        float4 p = pts_pa[j];
        float3 dp = p.xyz - x;
        float3 r = profile_lookup(table, sqrt(dot(dp, dp)), inv_h);
        m += r * pts_e[j].xyz;
        w += r * p.w;
    }
    out[q] = finish(m, w, rd);
}
