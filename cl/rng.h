/* rng.h - counter-based random numbers: Philox4x32-10 (Salmon, Moraes, Dror, Shaw 2011,
 * "Parallel random numbers: as easy as 1, 2, 3", SC11).  Stateless: the output is a pure
 * function of (counter, key), so a photon's random stream depends only on the seed, the
 * work-item and its own draw count, and results repeat exactly on any device.
 * Constants: multipliers 0xD2511F53, 0xCD9E8D57 and Weyl key increments 0x9E3779B9,
 * 0xBB67AE85 from the paper; 10 rounds (the paper's recommended Crush-resistant count).
 * Guarded by tests/test_mc_slab.py (repeatability, moments of the uniform stream).
 */
#ifndef DERMIS_RNG_H
#define DERMIS_RNG_H

typedef struct { uint4 ctr; uint2 key; uint4 out; int used; } philox_t;

inline uint4 philox_round(uint4 c, uint2 k) {
    uint hi0 = mul_hi(0xD2511F53u, c.x), lo0 = 0xD2511F53u * c.x;
    uint hi1 = mul_hi(0xCD9E8D57u, c.z), lo1 = 0xCD9E8D57u * c.z;
    return (uint4)(hi1 ^ c.y ^ k.x, lo1, hi0 ^ c.w ^ k.y, lo0);
}

inline uint4 philox4x32_10(uint4 c, uint2 k) {
    #pragma unroll
    for (int i = 0; i < 10; ++i) {
        c = philox_round(c, k);
        k += (uint2)(0x9E3779B9u, 0xBB67AE85u);
    }
    return c;
}

/* Stream for (seed, stream id): counter (0, id, 0, 0), key (seed lo, seed hi). */
inline philox_t philox_init(uint seed_lo, uint seed_hi, uint stream, uint sub) {
    philox_t s;
    s.ctr = (uint4)(0u, stream, sub, 0u);
    s.key = (uint2)(seed_lo, seed_hi);
    s.used = 4;
    s.out = (uint4)(0u);
    return s;
}

/* Uniform float in (0, 1]: 24 random bits, never 0 (so -log(u) is finite). */
inline float philox_uniform(philox_t *s) {
    if (s->used == 4) {
        s->out = philox4x32_10(s->ctr, s->key);
        s->ctr.x += 1u;
        if (s->ctr.x == 0u) s->ctr.w += 1u;
        s->used = 0;
    }
    uint v = s->used == 0 ? s->out.x : s->used == 1 ? s->out.y : s->used == 2 ? s->out.z : s->out.w;
    s->used += 1;
    return ((float)(v >> 8) + 1.0f) * (1.0f / 16777216.0f);
}

#endif
