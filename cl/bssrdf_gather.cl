/* bssrdf_gather.cl - hierarchical (Jensen-Buhler 2002) and brute-force gather of radiant
 * exitance from cached irradiance sample points through a radial diffusion profile.
 *
 * Model: M_o(x) = sum_p R(|x - p|) E_p A_p  (docs/science.md §4; Jensen & Buhler 2002,
 * "A rapid hierarchical rendering technique for translucent materials", eq. 3-4).  R(r) is
 * the layer file's radial profile R(r) in 1/mm^2 (optics/layer_file.py), resampled on the
 * host into a uniform table that is zero beyond the per-channel cut-off radius.  The host
 * passes R convolved with the points' reconstruction Gaussian (subsurface/profile_table.py
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
/* Order of the far-field expansion in the distance (gather_tile_v): 1.0f adds the quartic
 * term R''''/24 (xtab row k: .w of its float4 0, 1, 2 = red, green, blue), 0.0f stops at
 * the cubic. */
#ifndef QUARTIC
#define QUARTIC 1.0f
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

/* Tile walk (the default; subsurface/gather.py GatherTuning.tile): one work-item gathers for
 * TILE queries that are neighbours on the Morton curve, walking the tree once for all of
 * them.  The tile is bounded by a sphere (centre c, radius rt, host-computed), and every test
 * uses the lower bound d_c - rt of the distance from any of its queries to the node: a node
 * is skipped only when it is beyond the cut-off for every query, clustered only when every
 * query may cluster it (so each query sees the same or finer clusters than its own walk
 * would give it: the error at a given epsilon can only fall), otherwise opened.  At each
 * cluster or leaf point the TILE queries are evaluated as float<TILE> vectors (TILE 4, 8 or
 * 16; PoCL cannot vectorise the data-dependent walk across work-items).  Node record for
 * this walk: n0.w = reach = cut-off + radius, n1.w = open = max(sqrt(A / epsilon), radius)
 * (distances, not squares, because of the - rt).
 * Queries and results are planar per tile: query[(g * 3 + axis) * TILE + l],
 * out[(g * 3 + channel) * TILE + l]; visits[g] = nodes + points walked.  Table rows are
 * fetched lane by lane through a private index array (the only scalar part); everything else
 * is vector arithmetic.
 * ptab row k: 12 floats (R rgb, R''-R'/r rgb, R'/r rgb, 0 0 0); table row k: R rgb, 0. */
#ifndef TILE
#define TILE 16
#endif
#if TILE == 4 || TILE == 8 || TILE == 16   /* OpenCL vector widths */
#define CATX(a, b) a##b
#define CAT(a, b) CATX(a, b)
#define VT CAT(float, TILE)
#define VI CAT(int, TILE)
#define VLOAD CAT(vload, TILE)
#define VSTORE CAT(vstore, TILE)
#define CONVI CAT(convert_int, TILE)
#define CONVF CAT(convert_float, TILE)

/* Far-field expansion about the tile centre c: for a query x = c + delta and a source (node
 * or point) at c + v, d = |v|, u = v / d, s = u . delta, the second-order Taylor expansion of
 * R(|v - delta|) plus the node's own covariance term is
 *   R - R' s + 1/2 (R'' - R'/d)(s^2 + u^T C u) + 1/2 (R'/d)(|delta|^2 + tr C)
 * (the tile offset enters exactly like the node's spread).  One scalar table lookup per
 * source, then 3 fused multiply-adds per channel and lane.  Used when the source is at least
 * `xd` = max(expand_mm, expand_rt * rt) from every query of the tile (remainder of the
 * quartic ~ |d5R/dr5| rt^5 / 120); nearer sources are expanded about the sub-tile centres
 * (SUBTILE, below) or evaluated exactly lane by lane.
 * xtab row k: 4 float4 = R, R', R''/2, R'''/6 (rgb) at r = k h; their .w (rows 0-2) hold
 * R''''/24 of red, green, blue (the quartic term, QUARTIC). */
inline void xlookup(__global const float4 *xtab, float t, float4 *r, float4 *r1, float4 *ta,
                    float4 *tb) {
    int k = (int)t;
    float f = t - (float)k;
    __global const float4 *row = xtab + 4 * k;
    *r = mix(row[0], row[4], f);
    *r1 = mix(row[1], row[5], f);
    *ta = mix(row[2], row[6], f);
    *tb = mix(row[3], row[7], f);
}

/* Exact lane-by-lane evaluation (table rows fetched through a private index array). */
#define LANE_TABLE(rr, rg, rb, dx, dy, dz)                                                   \
    {                                                                                        \
        VT t_ = fmin(sqrt(dx * dx + dy * dy + dz * dz) * inv_h, tmax);                      \
        VI k_ = CONVI(t_);                                                                   \
        VT f_ = t_ - CONVF(k_);                                                              \
        VSTORE(k_, 0, kk);                                                                   \
        for (int l = 0; l < TILE; ++l) {                                                     \
            __global const float *row = table + 4 * kk[l];                                   \
            for (int c = 0; c < 3; ++c) { lo[c][l] = row[c]; hi[c][l] = row[4 + c]; }        \
        }                                                                                    \
        rr = mix(VLOAD(0, lo[0]), VLOAD(0, hi[0]), f_);                                      \
        rg = mix(VLOAD(0, lo[1]), VLOAD(0, hi[1]), f_);                                      \
        rb = mix(VLOAD(0, lo[2]), VLOAD(0, hi[2]), f_);                                      \
    }

/* Sub-tile expansion (TILE 16 only): the 16 lanes are 4 Morton-adjacent sub-tiles of 4
 * queries, each with its own bounding sphere (host-computed, subsph[4 g + s]); the host
 * interleaves them (lane l belongs to sub-tile l % 4) so a float4 over the sub-tiles spreads
 * to the lanes as (float16)(v, v, v, v).  A source too near the tile centre for the tile's
 * expansion but at least max(expand_mm, expand_rt x sub-tile radius) from every query of
 * every sub-tile is expanded about each sub-tile's centre: 4 contiguous xtab lookups instead
 * of 16 gathered table rows.  Same formula and error bound per sub-tile as the tile
 * expansion, with the sub-tile's radius (median ~1/3 of the tile's on the bench head).
 * Measured on bench/bench_gather.py's head: see subsurface/gather.py (GatherTuning.subtiles). */
#if TILE == 16
#define SUBTILE 1
#define S16(v) (float16)(v, v, v, v)
/* distances from source P to the 4 sub-tile centres (float4), and whether all are far */
#define SUB_DIST(P)                                                                          \
    float4 ex_ = (P).x - scx, ey_ = (P).y - scy, ez_ = (P).z - scz;                          \
    float4 sd4 = sqrt(ex_ * ex_ + ey_ * ey_ + ez_ * ez_);                                    \
    bool sub_far = use_sub && all(sd4 > sx4);
/* R, R', R''/2, R'''/6 at the 4 sub-tile distances, one float4 (over sub-tiles) per channel */
#define SUB_LOOKUPS                                                                          \
    float4 t4_ = fmin(sd4 * inv_h, tmax);                                                    \
    int4 k4_ = convert_int4(t4_);                                                            \
    float4 f4_ = t4_ - convert_float4(k4_);                                                  \
    __global const float4 *w0_ = xtab + 4 * k4_.s0, *w1_ = xtab + 4 * k4_.s1;                \
    __global const float4 *w2_ = xtab + 4 * k4_.s2, *w3_ = xtab + 4 * k4_.s3;                \
    float4 Rx, Ry, Rz, Ax, Ay, Az, Bx, By, Bz, Cx, Cy, Cz;                                   \
    float4 Qx, Qy, Qz, Q_;                                                                   \
    SUB_ROW(0, Rx, Ry, Rz, Qx) SUB_ROW(1, Ax, Ay, Az, Qy) SUB_ROW(2, Bx, By, Bz, Qz)         \
    SUB_ROW(3, Cx, Cy, Cz, Q_)                                                               \
    Qx *= QUARTIC; Qy *= QUARTIC; Qz *= QUARTIC;
#define SUB_ROW(o, X, Y, Z, W)                                                               \
    {                                                                                        \
        float4 a0 = w0_[o], a1 = w1_[o], a2 = w2_[o], a3 = w3_[o];                           \
        float4 b0 = w0_[o + 4], b1 = w1_[o + 4], b2 = w2_[o + 4], b3 = w3_[o + 4];           \
        X = mix((float4)(a0.x, a1.x, a2.x, a3.x), (float4)(b0.x, b1.x, b2.x, b3.x), f4_);    \
        Y = mix((float4)(a0.y, a1.y, a2.y, a3.y), (float4)(b0.y, b1.y, b2.y, b3.y), f4_);    \
        Z = mix((float4)(a0.z, a1.z, a2.z, a3.z), (float4)(b0.z, b1.z, b2.z, b3.z), f4_);    \
        W = mix((float4)(a0.w, a1.w, a2.w, a3.w), (float4)(b0.w, b1.w, b2.w, b3.w), f4_);    \
    }
#else
#define SUBTILE 0
#endif

__kernel void gather_tile_v(__global const float *query,
                            __global const float4 *sphere,
                            __global const float4 *subsph,  /* (4 G) sub-tile spheres */
                            const int use_sub,
                            const float sub_rt,            /* expand_rt of the sub-tiles */
                            __global const float4 *node,
                            __global const int *node_start,
                            const int n_nodes,
                            __global const float4 *pts_pa,
                            __global const float4 *pts_e,
                            __global const float *table,   /* 4 floats per row */
                            __global const float *ptab,    /* 12 floats per row */
                            __global const float4 *xtab,   /* 4 float4 per row */
                            const float inv_h,
                            const float expand_mm,
                            const float expand_rt,
                            const float4 rd,
                            const int n_tiles,
                            __global float *out,
                            __global int *visits)
{
    int g = get_global_id(0);
    if (g >= n_tiles) return;
    VT qx = VLOAD(3 * g, query), qy = VLOAD(3 * g + 1, query), qz = VLOAD(3 * g + 2, query);
    VT mr = (VT)(0.0f), mg = (VT)(0.0f), mb = (VT)(0.0f);
#if THESIS_NORM
    VT wr = (VT)(0.0f), wg = (VT)(0.0f), wb = (VT)(0.0f);
#endif
    const float tmax = (float)(TABLE_N - 2);
    float4 ts = sphere[g];
    float xd = fmax(expand_mm, expand_rt * ts.w);
    int kk[TILE];
    float lo[9][TILE], hi[9][TILE];
#if SUBTILE
    float4 s0 = subsph[4 * g], s1 = subsph[4 * g + 1], s2 = subsph[4 * g + 2], s3 = subsph[4 * g + 3];
    float4 scx = (float4)(s0.x, s1.x, s2.x, s3.x), scy = (float4)(s0.y, s1.y, s2.y, s3.y);
    float4 scz = (float4)(s0.z, s1.z, s2.z, s3.z), srad = (float4)(s0.w, s1.w, s2.w, s3.w);
    /* a source is expanded about the sub-tile centres beyond these centre distances */
    float4 sx4 = srad + fmax((float4)(expand_mm), sub_rt * srad);
#endif
    int count = 0;
    int i = 0;
    while (i < n_nodes) {
        float4 n0 = node[4 * i];
        float4 n3 = node[4 * i + 3];
        int skip = as_int(n3.w);
        float3 dc = n0.xyz - ts.xyz;
        float dcen = sqrt(dot(dc, dc));
        float dlow = dcen - ts.w;
        count++;
        if (dlow > n0.w) { i = skip; continue; }
        float4 n1 = node[4 * i + 1];
        if (dlow > n1.w) {
            float4 c0 = node[4 * i + 2];
            float ht = 0.5f * (c0.x + c0.w + n3.y);
            VT rr, rg, rb;
            if (dlow > xd) {                       /* 1-D Taylor about the centre distance */
                float4 R, R1, H2, H3;
                xlookup(xtab, fmin(dcen * inv_h, tmax), &R, &R1, &H2, &H3);
                float4 Q4 = QUARTIC * (float4)(R.w, R1.w, H2.w, 0.0f);
                VT dx = n0.x - qx, dy = n0.y - qy, dz = n0.z - qz;
                VT d2 = dx * dx + dy * dy + dz * dz;
                VT dl = sqrt(d2) - dcen;
#if SECOND_ORDER
                /* the covariance term per lane, with R'' - R'/d and R'/d at the centre */
                float4 tb = R1 / dcen;
                float4 ta = 2.0f * H2 - tb;
                VT cx = c0.x * dx + c0.y * dy + c0.z * dz;
                VT cy = c0.y * dx + c0.w * dy + n3.x * dz;
                VT cz = c0.z * dx + n3.x * dy + n3.y * dz;
                VT quad = 0.5f * (dx * cx + dy * cy + dz * cz) / d2;
                /* and their first-order change with distance: (R'/d)' = ta / d,
                 * ta' = d3R/dr3 - ta / d */
                float4 dtb = ta / dcen, dta = 6.0f * H3 - dtb;
                VT ax = ta.x + dl * dta.x, ay = ta.y + dl * dta.y, az = ta.z + dl * dta.z;
                VT bx = tb.x + dl * dtb.x, by = tb.y + dl * dtb.y, bz = tb.z + dl * dtb.z;
                rr = fmax(R.x + ax * quad + bx * ht + dl * (R1.x + dl * (H2.x + dl * (H3.x + dl * Q4.x))), 0.0f);
                rg = fmax(R.y + ay * quad + by * ht + dl * (R1.y + dl * (H2.y + dl * (H3.y + dl * Q4.y))), 0.0f);
                rb = fmax(R.z + az * quad + bz * ht + dl * (R1.z + dl * (H2.z + dl * (H3.z + dl * Q4.z))), 0.0f);
#else
                rr = fmax(R.x + dl * (R1.x + dl * (H2.x + dl * (H3.x + dl * Q4.x))), 0.0f);
                rg = fmax(R.y + dl * (R1.y + dl * (H2.y + dl * (H3.y + dl * Q4.y))), 0.0f);
                rb = fmax(R.z + dl * (R1.z + dl * (H2.z + dl * (H3.z + dl * Q4.z))), 0.0f);
#endif
            } else {
                VT dx = n0.x - qx, dy = n0.y - qy, dz = n0.z - qz;
#if SUBTILE
                SUB_DIST(n0.xyz)
                if (sub_far) {
                    SUB_LOOKUPS
                    VT d2 = dx * dx + dy * dy + dz * dz;
                    VT dl = sqrt(d2) - S16(sd4);
#if SECOND_ORDER
                    float4 tbx = Ax / sd4, tby = Ay / sd4, tbz = Az / sd4;
                    float4 tax = 2.0f * Bx - tbx, tay = 2.0f * By - tby, taz = 2.0f * Bz - tbz;
                    float4 ebx = tax / sd4, eby = tay / sd4, ebz = taz / sd4;
                    float4 eax = 6.0f * Cx - ebx, eay = 6.0f * Cy - eby, eaz = 6.0f * Cz - ebz;
                    VT cx = c0.x * dx + c0.y * dy + c0.z * dz;
                    VT cy = c0.y * dx + c0.w * dy + n3.x * dz;
                    VT cz = c0.z * dx + n3.x * dy + n3.y * dz;
                    VT quad = 0.5f * (dx * cx + dy * cy + dz * cz) / d2;
#define CH(c) fmax(S16(R##c) + (S16(ta##c) + dl * S16(ea##c)) * quad \
                   + (S16(tb##c) + dl * S16(eb##c)) * ht \
                   + dl * (S16(A##c) + dl * (S16(B##c) + dl * (S16(C##c) + dl * S16(Q##c)))), 0.0f)
#else
#define CH(c) fmax(S16(R##c) + dl * (S16(A##c) + dl * (S16(B##c) + dl * (S16(C##c) + dl * S16(Q##c)))), 0.0f)
#endif
                    rr = CH(x); rg = CH(y); rb = CH(z);
#undef CH
                } else {
#endif
#if SECOND_ORDER
                VT d2 = dx * dx + dy * dy + dz * dz;
                VT t = fmin(sqrt(d2) * inv_h, tmax);
                VI k = CONVI(t);
                VT f = t - CONVF(k);
                VSTORE(k, 0, kk);
                for (int l = 0; l < TILE; ++l) {
                    __global const float *row = ptab + 12 * kk[l];
                    for (int c = 0; c < 9; ++c) { lo[c][l] = row[c]; hi[c][l] = row[12 + c]; }
                }
                VT cx = c0.x * dx + c0.y * dy + c0.z * dz;
                VT cy = c0.y * dx + c0.w * dy + n3.x * dz;
                VT cz = c0.z * dx + n3.x * dy + n3.y * dz;
                VT quad = 0.5f * (dx * cx + dy * cy + dz * cz) / d2;
#define CH(c) fmax(mix(VLOAD(0, lo[c]), VLOAD(0, hi[c]), f) \
                   + mix(VLOAD(0, lo[c + 3]), VLOAD(0, hi[c + 3]), f) * quad \
                   + mix(VLOAD(0, lo[c + 6]), VLOAD(0, hi[c + 6]), f) * ht, 0.0f)
                rr = CH(0); rg = CH(1); rb = CH(2);
#undef CH
#else
                LANE_TABLE(rr, rg, rb, dx, dy, dz)
#endif
#if SUBTILE
                }
#endif
            }
            mr += rr * n1.x; mg += rg * n1.y; mb += rb * n1.z;
#if THESIS_NORM
            wr += rr * n3.z; wg += rg * n3.z; wb += rb * n3.z;
#endif
            i = skip;
            continue;
        }
        if (skip == i + 1) {
            int end = node_start[i + 1];
            int j = node_start[i];
            count += end - j;
            for (; j < end; ++j) {
                float4 p = pts_pa[j];
                float4 e = pts_e[j];
                float3 v = p.xyz - ts.xyz;
                float dp = sqrt(dot(v, v));
                VT rr, rg, rb;
                if (dp - ts.w > xd) {
                    float4 R, R1, H2, H3;
                    xlookup(xtab, fmin(dp * inv_h, tmax), &R, &R1, &H2, &H3);
                    float4 Q4 = QUARTIC * (float4)(R.w, R1.w, H2.w, 0.0f);
                    VT dx = p.x - qx, dy = p.y - qy, dz = p.z - qz;
                    VT dl = sqrt(dx * dx + dy * dy + dz * dz) - dp;
                    rr = fmax(R.x + dl * (R1.x + dl * (H2.x + dl * (H3.x + dl * Q4.x))), 0.0f);
                    rg = fmax(R.y + dl * (R1.y + dl * (H2.y + dl * (H3.y + dl * Q4.y))), 0.0f);
                    rb = fmax(R.z + dl * (R1.z + dl * (H2.z + dl * (H3.z + dl * Q4.z))), 0.0f);
                } else {
                    VT dx = p.x - qx, dy = p.y - qy, dz = p.z - qz;
#if SUBTILE
                    SUB_DIST(p.xyz)
                    if (sub_far) {
                        SUB_LOOKUPS
                        VT dl = sqrt(dx * dx + dy * dy + dz * dz) - S16(sd4);
#define CH(c) fmax(S16(R##c) + dl * (S16(A##c) + dl * (S16(B##c) + dl * (S16(C##c) + dl * S16(Q##c)))), 0.0f)
                        rr = CH(x); rg = CH(y); rb = CH(z);
#undef CH
                    } else
#endif
                    LANE_TABLE(rr, rg, rb, dx, dy, dz)
                }
                mr += rr * e.x; mg += rg * e.y; mb += rb * e.z;
#if THESIS_NORM
                wr += rr * p.w; wg += rg * p.w; wb += rb * p.w;
#endif
            }
        }
        i++;
    }
#if THESIS_NORM
    mr = select((VT)(0.0f), rd.x * mr / wr, wr > 0.0f);
    mg = select((VT)(0.0f), rd.y * mg / wg, wg > 0.0f);
    mb = select((VT)(0.0f), rd.z * mb / wb, wb > 0.0f);
#endif
    VSTORE(mr, 3 * g, out);
    VSTORE(mg, 3 * g + 1, out);
    VSTORE(mb, 3 * g + 2, out);
    visits[g] = count;
}

#endif  /* TILE is a vector width */

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

/* Near field of point and directional lights (subsurface/shadow_edges.py edge_sum):
 * for each shading point x, the sum over the located shadow-edge segments within r_out of
 * the boundary integral of the near profile, sign(w) [Q(|w|, phi2) - Q(|w|, phi1)], with
 * w = (e - x).n_out the signed distance of x from the segment's line, t0 = (x - e).tangent
 * its foot, phi = atan2(lo/hi - t0, |w|), and Q the host's table (bilinear, odd in phi, 0
 * at omega >= r_out).  Segments are binned by origin in a uniform grid whose cell is at
 * least r_out + the longest half-segment, so the 27 cells around x hold every segment that
 * can reach it; a segment counts where its centre lies within r_out + its half length of x
 * (3-D distance, as edge_sum's ball query: a fold of the surface within its tangent plane
 * but far along the normal does not) and the surface normals agree (> 0.5: the same side
 * of a thin part).  out[q] = (S rgb, 0).
 * Segments shorter than EDGE_MIDPOINT x their distance from x (most of them) are
 * integrated by the midpoint rule on the line integrand m_K(rho) w / (2 pi rho^2) instead
 * (one 1-D lookup of mktab, no atan2): at 0.15 the difference from the exact table is
 * 3e-4 of Rd_near (tests/test_gather.py test13).
 * Segment records (float4): sc = (centre, (r_out + half length)^2) (read first: most
 * candidates fail its distance test), so = (origin, lo), st = (tangent, hi),
 * sn = (outward, 0), sm = (surface normal, 0).  qtab rows (omega_i, phi_j) at i * (n_phi + 1) + j: Q rgb, 0.
 * Guarded by tests/test_gather.py (against the numpy edge_sum) and tests/test_knife_edge.py. */
#ifndef EDGE_MIDPOINT
#define EDGE_MIDPOINT 0.15f
#endif
inline float3 qtab_lookup(__global const float4 *qtab, float om, float ph, int n_om, int n_ph,
                          float inv_dom, float inv_dph) {
    float a = clamp(om * inv_dom, 0.0f, (float)n_om);
    float b = clamp(fabs(ph) * inv_dph, 0.0f, (float)n_ph);
    int i = min((int)a, n_om - 1), j = min((int)b, n_ph - 1);
    float fa = a - (float)i, fb = b - (float)j;
    int k = i * (n_ph + 1) + j;
    float3 lo = mix(qtab[k].xyz, qtab[k + 1].xyz, fb);
    float3 hi = mix(qtab[k + n_ph + 1].xyz, qtab[k + n_ph + 2].xyz, fb);
    return copysign((float3)(1.0f), (float3)(ph)) * mix(lo, hi, fa);
}

__kernel void edge_near(__global const float4 *query,      /* (Q) x, y, z, - */
                        __global const float4 *qnormal,    /* (Q) shading normal, - */
                        __global const float4 *sc,         /* (K) centre, reach^2 */
                        __global const float4 *so,         /* (K) origin, lo */
                        __global const float4 *st,         /* (K) tangent, hi */
                        __global const float4 *sn,         /* (K) outward, - */
                        __global const float4 *sm,         /* (K) surface normal, - */
                        __global const int *cell_start,    /* (ncells + 1) */
                        __global const int *cell_seg,      /* segment ids by cell */
                        const float4 grid_lo,              /* xyz corner, w = 1 / cell */
                        const int nx, const int ny, const int nz,
                        __global const float4 *qtab,
                        const int n_om, const int n_ph, const float inv_dom, const float inv_dph,
                        __global const float4 *mktab,      /* m_K(k dmk) rgb, k < n_mk */
                        const int n_mk, const float inv_dmk,
                        const float r_out,
                        const int n_query,
                        __global float4 *out)
{
    int q = get_global_id(0);
    if (q >= n_query) return;
    float3 x = query[q].xyz;
    float3 nq = qnormal[q].xyz;
    float3 s = (float3)(0.0f);
    float3 g = (x - grid_lo.xyz) * grid_lo.w;
    int cx = (int)floor(g.x), cy = (int)floor(g.y), cz = (int)floor(g.z);
    for (int iz = max(cz - 1, 0); iz <= min(cz + 1, nz - 1); ++iz)
    for (int iy = max(cy - 1, 0); iy <= min(cy + 1, ny - 1); ++iy)
    for (int ix = max(cx - 1, 0); ix <= min(cx + 1, nx - 1); ++ix) {
        int c = (iz * ny + iy) * nx + ix;
        for (int k = cell_start[c]; k < cell_start[c + 1]; ++k) {
            int e = cell_seg[k];
            /* the segment's centre within r_out + its half length (as edge_sum's ball) */
            float4 c4 = sc[e];
            float3 dc = c4.xyz - x;
            if (dot(dc, dc) > c4.w) continue;
            if (dot(sm[e].xyz, nq) <= 0.5f) continue;
            float4 o = so[e], t = st[e];
            float3 d = o.xyz - x;
            float w = dot(d, sn[e].xyz);
            float om = fabs(w);
            if (om >= r_out) continue;
            float t0 = -dot(d, t.xyz);
            float sg = w >= 0.0f ? 1.0f : -1.0f;   /* on the line: counted lit */
            float len = t.w - o.w, tm = 0.5f * (o.w + t.w) - t0;
            float rho2 = om * om + tm * tm;
            if (len * len < EDGE_MIDPOINT * EDGE_MIDPOINT * rho2) {
                /* a short segment far from x: the line integrand m_K(rho) w / (2 pi rho^2)
                 * at its middle times its length (midpoint rule; relative error ~
                 * (len / rho)^2 / 24 of a contribution that is itself small) */
                float rho = sqrt(rho2);
                float u = fmin(rho * inv_dmk, (float)(n_mk - 1) - 1e-3f);
                int i = (int)u;
                float3 mk = mix(mktab[i].xyz, mktab[i + 1].xyz, u - (float)i);
                s += mk * (w * len * (0.5f * DERMIS_INV_PI) / rho2);
            } else {
                float p2 = atan2(t.w - t0, om), p1 = atan2(o.w - t0, om);
                s += sg * (qtab_lookup(qtab, om, p2, n_om, n_ph, inv_dom, inv_dph)
                           - qtab_lookup(qtab, om, p1, n_om, n_ph, inv_dom, inv_dph));
            }
        }
    }
    out[q] = (float4)(s, 0.0f);
}
