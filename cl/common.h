/* common.h - shared device math for every dermis kernel.
 * Conventions (docs/science.md): float32, lengths in mm, coefficients in 1/mm; local shading
 * frame with z along the shading normal, wo and wi both pointing away from the surface.
 */
#ifndef DERMIS_COMMON_H
#define DERMIS_COMMON_H

#define DERMIS_PI      3.14159265358979323846f
#define DERMIS_INV_PI  0.31830988618379067154f
#define DERMIS_INV_4PI 0.07957747154594766788f

inline float sqr(float x) { return x * x; }

/* Orthonormal basis around unit n (Duff et al. 2017, branchless). */
inline void make_frame(float3 n, float3 *t, float3 *b) {
    float s = n.z >= 0.0f ? 1.0f : -1.0f;
    float a = -1.0f / (s + n.z);
    float c = n.x * n.y * a;
    *t = (float3)(1.0f + s * n.x * n.x * a, s * c, -s * n.x);
    *b = (float3)(c, s + n.y * n.y * a, -n.y);
}

inline float3 to_local(float3 v, float3 t, float3 b, float3 n) {
    return (float3)(dot(v, t), dot(v, b), dot(v, n));
}

#endif
