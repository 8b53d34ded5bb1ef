/* surface.cl - surface attributes at primary-ray hits (renderer, rendering/surface.py).
 *
 * For each hit (triangle id + Embree barycentrics b1, b2 with p = (1-b1-b2) p0 + b1 p1 + b2 p2)
 * this computes: position (mm), unit geometric normal (counter-clockwise winding = outside),
 * unit interpolated vertex normal, unit direction to the camera wo, texture coordinates,
 * linear-RGB albedo, and the shading normal.
 *
 * Albedo: bilinear lookup of an sRGB uint8 texture, each texel decoded to linear through a
 * 256-entry IEC 61966-2-1 table BEFORE weighting (interpolating encoded values would darken
 * edges).  Texel centres at u = col / (W-1), v = 1 - row / (H-1), clamp to edge: the
 * convention of pipeline/artifacts.py and geometry/texture_lookup.py bilinear.
 * Shading normal with BUMP: Blinn 1978 bump mapping, height outward-positive in mm,
 *     n' = normalize(n + s (h_u (n x dpdv) - h_v (n x dpdu)) / |dpdu x dpdv|),
 *     s = sign((dpdu x dpdv) . n),
 * h_u, h_v central differences (half-width BUMP_STEP texels) of bilinear lookups, dpdu/dpdv
 * from the triangle's positions and UVs (pbrt's derivation) - the same definition as
 * geometry/bump.py bump_shading_normals(), which tests/test_render.py compares against.
 * Degenerate UV triangles (|det| <= 1e-20) and zero-area ones switch the bump off.
 * Two-sided: when the camera sees the back of a triangle (geometric normal facing away, e.g.
 * a folded scan triangle at an eyelid) both normals are flipped to the camera's side, as a
 * two-sided material would; shadow rays then leave on that side.
 * Shading normals facing away from the camera: an interpolated (or bumped) normal can face
 * away where the triangle seen faces the camera (creases at eyelids, lips, nostrils, and
 * the rim of a smooth low mesh).  Such pixels used to be black; instead the shading normal
 * is bent towards the viewer, keeping its azimuth about wo, until cos(n_s, wo) = NS_MIN_COS
 * (the shading-normal adaptation of Keller et al. 2017, "The Iray Light Transport Simulation
 * and Rendering System", sec. A.3, applied to the view direction).  Continuous at the
 * threshold: normals with cos >= NS_MIN_COS are untouched.
 *
 * Compile-time options (-D): HAS_UV (0/1), HAS_TEXTURE (0/1, needs HAS_UV), HAS_BUMP (0/1,
 * needs HAS_UV).  Conventions: float32, mm.  One work-item per hit, straight-line code.
 * Guarded by tests/test_render.py (analytic sphere image, texture lookup vs numpy, bump vs
 * geometry/bump.py, no NaN).
 */
#include "common.h"

#ifndef HAS_UV
#define HAS_UV 0
#endif
#ifndef HAS_TEXTURE
#define HAS_TEXTURE 0
#endif
#ifndef HAS_BUMP
#define HAS_BUMP 0
#endif
/* half-width of the bump central difference, texels (geometry/bump.py default step_texels) */
#define BUMP_STEP 1.0f
/* below this |det| the UV parameterisation is degenerate (geometry/bump.py uses 1e-20 too) */
#define UV_DET_MIN 1e-20f
/* smallest cosine between the shading normal and wo (84.3 deg): our choice, small enough to
 * leave every normally seen pixel alone, large enough that the Fresnel exit of the BSSRDF
 * (T ~ 0.55 at eta 1.4) and the BRDFs' wo.z > 0 tests do not blacken a crease */
#define NS_MIN_COS 0.1f

/* Unit vector, or (0,0,0) for a zero vector (no NaN from normalize(0)). */
inline float3 safe_normalize(float3 v) {
    float l2 = dot(v, v);
    return l2 > 0.0f ? v * rsqrt(l2) : (float3)(0.0f);
}

/* Bilinear tap positions for texture coordinate uv in a W x H image (clamp to edge). */
inline void bilinear_taps(float2 uv, int w, int h, int *x0, int *y0, int *x1, int *y1,
                          float *fx, float *fy) {
    float x = clamp(uv.x * (float)(w - 1), 0.0f, (float)(w - 1));
    float y = clamp((1.0f - uv.y) * (float)(h - 1), 0.0f, (float)(h - 1));
    *x0 = min((int)x, max(w - 2, 0));
    *y0 = min((int)y, max(h - 2, 0));
    *fx = x - (float)(*x0);
    *fy = y - (float)(*y0);
    *x1 = min(*x0 + 1, w - 1);
    *y1 = min(*y0 + 1, h - 1);
}

/* Bilinear lookup of a single-channel float map. */
inline float bilinear1(__global const float *img, int w, int h, float2 uv) {
    int x0, y0, x1, y1;
    float fx, fy;
    bilinear_taps(uv, w, h, &x0, &y0, &x1, &y1, &fx, &fy);
    float top = img[y0 * w + x0] * (1.0f - fx) + img[y0 * w + x1] * fx;
    float bot = img[y1 * w + x0] * (1.0f - fx) + img[y1 * w + x1] * fx;
    return top * (1.0f - fy) + bot * fy;
}

/* Linear RGB of one sRGB uint8 texel through the decoding table. */
inline float3 texel_linear(__global const uchar *tex, __constant const float *lut, int idx) {
    return (float3)(lut[tex[3 * idx]], lut[tex[3 * idx + 1]], lut[tex[3 * idx + 2]]);
}

/* Bilinear lookup of an sRGB uint8 RGB texture, decoded to linear before weighting. */
inline float3 bilinear_srgb(__global const uchar *tex, __constant const float *lut, int w,
                            int h, float2 uv) {
    int x0, y0, x1, y1;
    float fx, fy;
    bilinear_taps(uv, w, h, &x0, &y0, &x1, &y1, &fx, &fy);
    float3 top = texel_linear(tex, lut, y0 * w + x0) * (1.0f - fx)
               + texel_linear(tex, lut, y0 * w + x1) * fx;
    float3 bot = texel_linear(tex, lut, y1 * w + x0) * (1.0f - fx)
               + texel_linear(tex, lut, y1 * w + x1) * fx;
    return top * (1.0f - fy) + bot * fy;
}

__kernel void surface(
    __global const int *tri, __global const float *bary, const int n,
    __global const float *vertices, __global const int *faces,
    __global const float *vnormals,
    __global const float *uv, __global const int *uv_faces,
    __global const uchar *tex, const int tex_w, const int tex_h, __constant const float *lut,
    __global const float *bump, const int bump_w, const int bump_h, const float bump_range_mm,
    const float cam_x, const float cam_y, const float cam_z,
    __global float *position, __global float *geo_normal, __global float *shading_normal,
    __global float *wo_out, __global float *uv_out, __global float *albedo_out,
    const float albedo_r, const float albedo_g, const float albedo_b)
{
    int i = get_global_id(0);
    if (i >= n) return;
    int f = tri[i];
    float b1 = bary[2 * i], b2 = bary[2 * i + 1];
    float b0 = 1.0f - b1 - b2;
    int3 vi = vload3(f, faces);
    float3 p0 = vload3(vi.x, vertices), p1 = vload3(vi.y, vertices), p2 = vload3(vi.z, vertices);
    float3 p = b0 * p0 + b1 * p1 + b2 * p2;
    float3 e1 = p1 - p0, e2 = p2 - p0;
    float3 cr = cross(e1, e2);
    float3 ng = safe_normalize(cr);
    float3 ns = safe_normalize(b0 * vload3(vi.x, vnormals) + b1 * vload3(vi.y, vnormals)
                               + b2 * vload3(vi.z, vnormals));
    /* interpolated normals can cancel (opposite vertex normals): fall back to the face */
    ns = dot(ns, ns) > 0.0f ? ns : ng;
    float3 cam = (float3)(cam_x, cam_y, cam_z);
    float3 wo = safe_normalize(cam - p);
    float3 albedo = (float3)(albedo_r, albedo_g, albedo_b);
    float2 st = (float2)(0.0f);

#if HAS_UV
    int3 ti = vload3(f, uv_faces);
    float2 t0 = vload2(ti.x, uv), t1 = vload2(ti.y, uv), t2 = vload2(ti.z, uv);
    st = b0 * t0 + b1 * t1 + b2 * t2;
#if HAS_TEXTURE
    albedo = bilinear_srgb(tex, lut, tex_w, tex_h, st);
#endif
#if HAS_BUMP
    /* tangent frame dp/du, dp/dv of the triangle (pbrt Triangle::Intersect) */
    float du1 = t1.x - t0.x, du2 = t2.x - t0.x, dv1 = t1.y - t0.y, dv2 = t2.y - t0.y;
    float det = du1 * dv2 - du2 * dv1;
    float inv = fabs(det) > UV_DET_MIN ? 1.0f / det : 0.0f;
    float3 dpdu = (dv2 * e1 - dv1 * e2) * inv;
    float3 dpdv = (du1 * e2 - du2 * e1) * inv;
    /* height gradient, mm per unit u / v: central differences of bilinear lookups */
    float su = BUMP_STEP / (float)max(bump_w - 1, 1), sv = BUMP_STEP / (float)max(bump_h - 1, 1);
    float h_u = (bilinear1(bump, bump_w, bump_h, st + (float2)(su, 0.0f))
               - bilinear1(bump, bump_w, bump_h, st - (float2)(su, 0.0f))) * (bump_range_mm / (2.0f * su));
    float h_v = (bilinear1(bump, bump_w, bump_h, st + (float2)(0.0f, sv))
               - bilinear1(bump, bump_w, bump_h, st - (float2)(0.0f, sv))) * (bump_range_mm / (2.0f * sv));
    float3 cuv = cross(dpdu, dpdv);
    float area = length(cuv);
    /* mirrored UV charts flip dpdu x dpdv: s keeps the tilt on the right side */
    float s = dot(cuv, ns) < 0.0f ? -1.0f : 1.0f;
    float scale = area > 0.0f ? s / area : 0.0f;
    float3 bumped = ns + scale * (h_u * cross(ns, dpdv) - h_v * cross(ns, dpdu));
    float3 nb = safe_normalize(bumped);
    ns = dot(nb, nb) > 0.0f ? nb : ns;
#endif
#endif
    /* two-sided, then the view-facing shading normal (file comment) */
    if (dot(ng, wo) < 0.0f) {
        ng = -ng;
        ns = -ns;
    }
    float c = dot(ns, wo);
    if (c < NS_MIN_COS) {
        float3 perp = ns - c * wo;
        float lp = length(perp);
        ns = lp > 0.0f ? perp * (sqrt(1.0f - NS_MIN_COS * NS_MIN_COS) / lp) + NS_MIN_COS * wo
                       : ng;
    }

    vstore3(p, i, position);
    vstore3(ng, i, geo_normal);
    vstore3(ns, i, shading_normal);
    vstore3(wo, i, wo_out);
    vstore2(st, i, uv_out);
    vstore3(albedo, i, albedo_out);
}
