/* rng.h - counter-based random numbers: Philox4x32-10 and -7 (Salmon, Moraes, Dror, Shaw 2011,
 * "Parallel random numbers: as easy as 1, 2, 3", SC11).  Stateless: the output is a pure
 * function of (counter, key), so a photon's random stream depends only on the seed, the
 * stream id and its own draw count, and results repeat exactly on any device.
 * Constants: multipliers 0xD2511F53, 0xCD9E8D57 and Weyl key increments 0x9E3779B9,
 * 0xBB67AE85 from the paper; 10 rounds (the paper's recommended Crush-resistant count).
 *
 * Two forms of the same function: PHILOX4X32_10(T, MULHILO, ...) is a statement macro for
 * any uint type T (uint, uint8, uint16: one independent stream per lane, so a float16
 * kernel draws 16 lanes' blocks at once in SIMD registers); philox4x32_10 is the scalar
 * uint4 form.  Both give the paper's known-answer vectors (Random123 kat_vectors), checked
 * by tests/test_mc_slab.py::test05_philox_known_answers_and_cheap_math.
 */
#ifndef DERMIS_RNG_H
#define DERMIS_RNG_H

#define PHILOX_M0 0xD2511F53u
#define PHILOX_M1 0xCD9E8D57u
#define PHILOX_W0 0x9E3779B9u
#define PHILOX_W1 0xBB67AE85u

/* 32 x 32 -> 64-bit products of each lane of c with the constant m: high and low words.
 * PHILOX_MULHILO is the plain form for any uint type.  PHILOX_MULHILO_WIDE is the same
 * for uint vectors through an explicit 64-bit product (ULN: the ulong vector type of the
 * same width, CVT_UL / CVT_U its convert_ functions): PoCL 3.1 compiles mul_hi on uint16
 * to far slower code: the whole tracer ran 1.4x faster with this form (A/B timing of the
 * MCML case; an even/odd-lane as_ulong8 variant was ~3 % slower than this one). */
#define PHILOX_MULHILO(c, m, hi, lo) do {                                              \
        hi = mul_hi(c, (__typeof__(c))(m)); lo = (c) * (m);                            \
    } while (0)

#define PHILOX_MULHILO_WIDE(c, m, hi, lo, ULN, CVT_UL, CVT_U) do {                     \
        ULN p_ = CVT_UL(c) * (ulong)(m);                                               \
        hi = CVT_U(p_ >> 32); lo = (c) * (m);                                          \
    } while (0)

/* One round on the four counter words c0..c3 (lvalues of one uint type T) with the scalar
 * round keys k0, k1; MULHILO(c, m, hi, lo) is one of the two product forms above. */
#define PHILOX_ROUND(T, MULHILO, c0, c1, c2, c3, k0, k1) do {                          \
        T hi0_, lo0_, hi1_, lo1_;                                                      \
        MULHILO(c0, PHILOX_M0, hi0_, lo0_);                                            \
        MULHILO(c2, PHILOX_M1, hi1_, lo1_);                                            \
        c0 = hi1_ ^ (c1) ^ (k0); c1 = lo1_; c2 = hi0_ ^ (c3) ^ (k1); c3 = lo0_;         \
    } while (0)

/* Round r (0-based) of the key schedule: round keys key + r x Weyl increment. */
#define PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, key0, key1, r)                        \
    PHILOX_ROUND(T, MULHILO, c0, c1, c2, c3, (key0) + (r) * PHILOX_W0, (key1) + (r) * PHILOX_W1)

/* Seven rounds in place: Philox4x32-7, the fewest rounds the paper found to pass TestU01's
 * BigCrush (its Table 2; ten keep a safety margin).  Used by the photon tracer, where the
 * generator is half the time per event (cl/mc_slab.cl).  The key schedule is scalar (the same
 * seed for every lane), so it costs nothing per lane. */
#define PHILOX4X32_7(T, MULHILO, c0, c1, c2, c3, key0, key1) do {                      \
        const uint pk0_ = (key0), pk1_ = (key1);                                       \
        PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, pk0_, pk1_, 0u);                    \
        PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, pk0_, pk1_, 1u);                    \
        PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, pk0_, pk1_, 2u);                    \
        PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, pk0_, pk1_, 3u);                    \
        PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, pk0_, pk1_, 4u);                    \
        PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, pk0_, pk1_, 5u);                    \
        PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, pk0_, pk1_, 6u);                    \
    } while (0)

/* Ten rounds in place (the paper's Philox4x32-10): the seven, then rounds 7-9. */
#define PHILOX4X32_10(T, MULHILO, c0, c1, c2, c3, key0, key1) do {                     \
        const uint qk0_ = (key0), qk1_ = (key1);                                       \
        PHILOX4X32_7(T, MULHILO, c0, c1, c2, c3, qk0_, qk1_);                          \
        PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, qk0_, qk1_, 7u);                    \
        PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, qk0_, qk1_, 8u);                    \
        PHILOX_ROUND_R(T, MULHILO, c0, c1, c2, c3, qk0_, qk1_, 9u);                    \
    } while (0)

/* Scalar form: counter c, key k (the paper's Philox4x32-10). */
inline uint4 philox4x32_10(uint4 c, uint2 k) {
    uint c0 = c.x, c1 = c.y, c2 = c.z, c3 = c.w;
    PHILOX4X32_10(uint, PHILOX_MULHILO, c0, c1, c2, c3, k.x, k.y);
    return (uint4)(c0, c1, c2, c3);
}

/* Uniform float in (0, 1] from the top 24 bits, never 0 (so -log(u) is finite).  Works on
 * uint and on uintN through the CONVERT argument (convert_float, convert_float16, ...). */
#define PHILOX_UNIFORM(v, CONVERT) \
    ((CONVERT((v) >> 8) + 1.0f) * (1.0f / 16777216.0f))

#endif
