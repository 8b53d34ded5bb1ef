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
 * roulette below W_MIN (an argument) with survival 1/ROULETTE_M (MCML's 1e-4 and 10).  A photon still
 * alive after MAX_STEPS interactions is scored as "lost" (only sigma_a ~ 0 media do this).
 *
 * SIMD layout (why: PoCL vectorises across work-items only for loop-free kernels, and a
 * photon is a loop; docs/software.md "what was measured").  Each work-item carries LANES
 * photons (LANES = 8 fills one AVX2 register, 16 one AVX-512 register; the host picks by
 * the device's preferred float vector width, optics/monte_carlo_slab.py lanes_for.  On a 2-core
 * AVX-512 machine the first loop, without splitting, ran 8 lanes at half the speed of 16;
 * on the 2-core AVX2 machine the present one, whose window and splitting keep ~20 vectors
 * live, spills at 16 and ran 8 lanes 1.25x faster, A/B on two_layer)
 * as floatN state and runs one event per lane per loop trip: a free flight that ends
 * either in an interaction or on a boundary.  Lanes are masked with select(); a lane
 * whose photon died is refilled with the work-item's next photon in the same trip, so
 * lanes stay busy until the work-item's budget of photons_per_item is spent (only its
 * last photons run with idle lanes: occupancy ~0.97 at >= 256 photons per lane, reported
 * as info["lane_occupancy"]).  Boundary handling and escape scoring run only when some
 * lane needs them (any_lane): rare per event in thick media.  The remaining free path is
 * kept as a length in the current layer (rescaled by sigma_t / sigma_t' on entering
 * another layer), and the boundary test |s uz| >= |zb - z| needs no division.
 *
 * Random numbers: one Philox4x32 block (PHILOX_ROUNDS rounds) per lane per trip (rng.h), counter (trip,
 * work-item * LANES + lane, channel, trip carry), key (seed, "mc_s").  Its four words
 * are used as: u0 free path, u1 HG cosine, u2 azimuth, u3 Fresnel (boundary event) or
 * roulette (interaction event) - an event is one or the other, so no word is used twice.
 * Results depend only on (seed, device arithmetic): the same seed repeats exactly.
 * Measured: Philox is about half of the time per event (a doubled Philox call took the
 * MCML case from 2.0 to 3.1 us per photon per core).
 *
 * Cheap math, accuracy stated and checked by test05: -ln(u) by an atanh series (|error|
 * < 1e-9 + float rounding), cos/sin of the azimuth from Taylor polynomials of the half
 * angle on [-pi/2, pi/2] (|error| < 6e-8 + rounding), no acos/atan/log/sin/cos calls
 * (PoCL's vector log is a 70-instruction call with a division); the direction is
 * renormalised by one Newton step instead of rsqrt (PoCL: sqrt + division).
 *
 * Radial splitting (variance reduction for the profile tables; docs/profiles.md).  Far
 * from the source R(r) falls by orders of magnitude, so analog photons leave its rings at
 * large r nearly empty.  A weight window W = exp(-kappa clamp(rho - rho0, 0, rho1 - rho0) +
 * lambda z) of the lateral distance rho and the depth z (kappa, rho0, rho1, lambda per channel
 * from the host; all 0 switch it off; lambda: deep photons matter less; no splitting
 * beyond rho1, the last ring: else photons that wander off
 * would be split without end, and kappa must not exceed the decay rate of the light
 * reaching rho, or the number of copies grows with rho)
 * keeps the weight of photons at rho near W: after an interaction a photon heavier than
 * 2 W is split in two halves, and below W_MIN W Russian roulette keeps it with probability
 * w / W at weight W (W_MIN an argument).  Both are unbiased.  The second half goes
 * onto a per-work-item stack in global
 * memory (BANK entries; when full, no split: still unbiased) and is traced later by the
 * first lane that falls idle, before any new photon is launched.  The log of the weight
 * is carried along (per-layer log(1 - sigma_a / sigma_t) in the layer table), so the window
 * test needs no exp or log: ln w > ln 2 - kappa (rho - rho0).
 *
 * Scoring: per work-item private slices of global memory (no atomics: PoCL's float atomics
 * are compare-exchange loops), radial rings between the given edges (binary search) for
 * escapes through the top (R) and the bottom (T); per-lane totals R, T, absorbed, lost in private float arrays
 * (absorbed in a vector: it changes every interaction), summed over lanes at the end.
 * The host sums the slices in float64 and groups work-items into batches for standard
 * errors.
 *
 * Layer table (host: optics/monte_carlo_slab.py _layer_table), per channel and layer 8 floats:
 * z_top, z_bot, sigma_t, 1/sigma_t, sigma_a/sigma_t, g, eta, log(1 - sigma_a/sigma_t).
 *
 * Conventions: z down into the slab, mm and 1/mm, float32.
 * Guarded by tests/test_mc_slab.py (exact Rd of Chandrasekhar and van de Hulst, ballistic
 * two-layer closed form, split-layer identity, conservation, repeatability, extremes,
 * Philox known answers, accuracy of the cheap math).
 */
#include "rng.h"

#define ROULETTE_M 10.0f
#define MAX_STEPS 1000000
/* per work-item totals: R, T, absorbed, lost, interactions, busy lane-trips, trips (the
 * last two measure lane occupancy, reported by optics/monte_carlo_slab.py and the benchmark) */
#define N_TOTALS 7

#ifndef LANES
#define LANES 8
#endif
/* Philox rounds of the tracer: 7 (Philox4x32-7, the fewest that pass BigCrush in Salmon et
 * al. 2011, Table 2) or 10 (the paper's safety margin).  A/B on two_layer (2-core AVX2
 * machine, PoCL): 10 -> 7 rounds 1.12x faster (docs/profiles.md "The Monte Carlo table"). */
#ifndef PHILOX_ROUNDS
#define PHILOX_ROUNDS 7
#endif
#if PHILOX_ROUNDS == 7
#define PHILOX_TRACE PHILOX4X32_7
#elif PHILOX_ROUNDS == 10
#define PHILOX_TRACE PHILOX4X32_10
#else
#error "PHILOX_ROUNDS must be 7 or 10"
#endif
/* entries of the per-work-item stack of split photons; floats per entry:
 * x, y, z, ux, uy, uz, w, ln w, remaining path, layer */
#ifndef BANK
#define BANK 256
#endif
#define BANK_FLOATS 10
#define MAX_SPLITS_PER_PHOTON 64
#define LN2_SPLIT 0.69314718055994531f
#define LN_ROULETTE_M 2.30258509299405f

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define vf CAT(float, LANES)
#define vi CAT(int, LANES)
#define vu CAT(uint, LANES)
#define cvt_f CAT(convert_float, LANES)
#define cvt_i CAT(convert_int, LANES)
#define cvt_u CAT(convert_uint, LANES)
#define as_vf CAT(as_float, LANES)
#define as_vi CAT(as_int, LANES)
#define as_vu CAT(as_uint, LANES)
#define VSTORE CAT(vstore, LANES)
#define VLOAD CAT(vload, LANES)

#if LANES == 16
#define MULHILO(c, m, hi, lo) \
    PHILOX_MULHILO_WIDE(c, m, hi, lo, ulong16, convert_ulong16, convert_uint16)
#define LANE_IDS ((vi)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#define LAST(v) ((v).sf)
#elif LANES == 8
#define MULHILO(c, m, hi, lo) \
    PHILOX_MULHILO_WIDE(c, m, hi, lo, ulong8, convert_ulong8, convert_uint8)
#define LANE_IDS ((vi)(0, 1, 2, 3, 4, 5, 6, 7))
#define LAST(v) ((v).s7)
#else
#error "LANES must be 8 or 16"
#endif

/* any lane set: OR-fold to one int (PoCL's any() tests lane by lane, a branch each) */
inline int any_lane(vi m) {
#if LANES == 16
    int8 a = m.lo | m.hi;
#else
    int8 a = m;
#endif
    int4 b = a.lo | a.hi;
    int2 c = b.lo | b.hi;
    return (c.x | c.y) < 0;
}

#define LN2_F 0.69314718055994531f
#define SQRT2_F 1.41421356237309505f
#define PI_F 3.14159265358979323846f

/* -ln(u) for u in (0, 1]: u = m 2^e with m in [sqrt(1/2), sqrt(2)), ln m = 2 atanh(s),
 * s = (m - 1) / (m + 1), |s| <= 0.1716; the series to s^9 leaves 2 s^11 / 11 < 7e-10
 * (Abramowitz & Stegun 4.1.28).  One division, no call. */
inline vf neg_log(vf u) {
    vi bits = as_vi(u);
    vi e = ((bits >> 23) & 0xff) - 127;
    vf m = as_vf((bits & 0x007fffff) | 0x3f800000);
    vi big = m > SQRT2_F;
    m = select(m, m * 0.5f, big);
    e -= big;                                   /* big is -1 where true */
    vf s = (m - 1.0f) / (m + 1.0f);
    vf s2 = s * s;
    vf p = s * (2.0f + s2 * (2.0f / 3.0f + s2 * (2.0f / 5.0f + s2 * (2.0f / 7.0f +
                                                                    s2 * (2.0f / 9.0f)))));
    return -(cvt_f(e) * LN2_F + p);
}

/* (cos phi, sin phi) for phi = 2 pi u - pi, uniform on the circle like 2 pi u.  Half
 * angle h = pi (u - 1/2) in (-pi/2, pi/2]: Taylor sin to h^11 (remainder
 * (pi/2)^13 / 13! < 6e-8) and cos to h^12 (< 7e-9); then cos 2h = c^2 - s^2,
 * sin 2h = 2 s c.  No range reduction, no trig calls. */
inline void azimuth(vf u, vf *cph, vf *sph) {
    vf h = PI_F * (u - 0.5f);
    vf h2 = h * h;
    vf s = h * (1.0f + h2 * (-1.0f / 6.0f + h2 * (1.0f / 120.0f + h2 * (-1.0f / 5040.0f +
               h2 * (1.0f / 362880.0f + h2 * (-1.0f / 39916800.0f))))));
    vf c = 1.0f + h2 * (-0.5f + h2 * (1.0f / 24.0f + h2 * (-1.0f / 720.0f + h2 * (
               1.0f / 40320.0f + h2 * (-1.0f / 3628800.0f + h2 * (1.0f / 479001600.0f))))));
    *cph = c * c - s * s;
    *sph = 2.0f * s * c;
}

/* Per-lane copy of layer parameters: lanes in `mask` take those of layer `idx`. */
#define LOAD_LAYER(mask, idx) do {                                                     \
        for (int k_ = 0; k_ < n_layers; ++k_) {                                        \
            vi m_ = (mask) & ((idx) == k_);                                            \
            __global const float *q_ = L + k_ * 8;                                     \
            z0 = select(z0, (vf)(q_[0]), m_); z1 = select(z1, (vf)(q_[1]), m_);        \
            inv_mut = select(inv_mut, (vf)(q_[3]), m_);                                \
            fa = select(fa, (vf)(q_[4]), m_); g = select(g, (vf)(q_[5]), m_);          \
            l1a = select(l1a, (vf)(q_[7]), m_);                                        \
        }                                                                              \
    } while (0)

__kernel void mc_slab(__global const float *layers, const int n_layers,
                      const float eta_above, const float eta_below,
                      const uint seed,
                      __global const int *photons_per_item,  /* [3]: per channel */
                      const int n_bins, __global const float *edges, /* [n_bins + 1] */
                      const float ln_w_min,   /* roulette below W_MIN W: ln W_MIN */
                      __global const float *window,  /* [3][4]: kappa, rho0, rho1, lambda */
                      __global float *bank,   /* [3][items][BANK][BANK_FLOATS] */
                      __global float *hist,   /* [3][items][2][n_bins] */
                      __global float *totals) /* [3][items][N_TOTALS] */
{
    const int item = get_global_id(0);
    const int items = get_global_size(0);
    const int ch = get_global_id(1);
    __global const float *L = layers + ch * n_layers * 8;
    __global float *hR = hist + ((size_t)(ch * items + item) * 2) * n_bins;
    __global float *hT = hR + n_bins;
    __global float *B = bank + (size_t)(ch * items + item) * BANK * BANK_FLOATS;
    const float kappa = window[4 * ch], rho0 = window[4 * ch + 1];
    const float span = fmax(window[4 * ch + 2] - rho0, 0.0f), lambda = window[4 * ch + 3];
    const int windowed = kappa > 0.0f || lambda > 0.0f;
    /* at most MAX_SPLITS_PER_PHOTON splits per launched photon per work-item: bounds the
     * work if the window falls faster than the light (skipping a split is unbiased) */
    const int budget = photons_per_item[ch];
    const long max_splits = (long)MAX_SPLITS_PER_PHOTON * budget;
    long splits = 0;
    const float r_last = edges[n_bins];
    int bank_n = 0;
    const vi lane = LANE_IDS;
    const vu stream = cvt_u(item * LANES + lane);
    uint trip = 0u, trip_hi = 0u;

    /* all lanes start a photon (lanes beyond the budget start dead) */
    vi alive = lane < budget;
    int launched = min(budget, LANES);
    vf x = 0.0f, y = 0.0f, z = 0.0f, ux = 0.0f, uy = 0.0f, uz = 1.0f, w = 1.0f, lw = 0.0f;
    vf srem = 0.0f;    /* remaining free path in the current layer, mm (0: draw one) */
    vi lay = 0, psteps = 0;
    vf z0 = L[0], z1 = L[1], inv_mut = L[3], fa = L[4], g = L[5], l1a = L[7];
    vf sumA = 0.0f;
    /* rarely updated per-lane tallies live in private memory, not in vector registers
     * (the hot loop already needs ~20 of the 32 zmm registers) */
    float accR[LANES], accT[LANES], accL[LANES];
    uint acc_steps[LANES], acc_hits[LANES];
    for (int i = 0; i < LANES; ++i) {
        accR[i] = accT[i] = accL[i] = 0.0f;
        acc_steps[i] = acc_hits[i] = 0u;
    }

    while (any_lane(alive) || bank_n > 0) {
        vu c0 = (vu)(trip), c1 = stream, c2 = (vu)((uint)ch), c3 = (vu)(trip_hi);
        PHILOX_TRACE(vu, MULHILO, c0, c1, c2, c3, seed, 0x6d635f73u);
        if (++trip == 0u) ++trip_hi;
        vf u0 = PHILOX_UNIFORM(c0, cvt_f), u1 = PHILOX_UNIFORM(c1, cvt_f);
        vf u2 = PHILOX_UNIFORM(c2, cvt_f), u3 = PHILOX_UNIFORM(c3, cvt_f);

        /* free flight: the remaining path in this layer, or a new one -ln(u) / sigma_t;
         * it ends on the boundary ahead when |s uz| >= |zb - z| (no division here: the
         * distance to the boundary is computed only for lanes that reach it) */
        vf s = select(srem, neg_log(u0) * inv_mut, srem <= 0.0f);
        vi down = uz > 0.0f;
        vf zb = select(z0, z1, down);
        vi hit = alive & (uz != 0.0f) & (fabs(s * uz) >= fabs(zb - z));
        vi inter = alive & ~hit;
        x = select(x, mad(s, ux, x), inter);
        y = select(y, mad(s, uy, y), inter);
        z = select(z, mad(s, uz, z), inter);
        srem = select(srem, (vf)(0.0f), inter);

        /* interaction: deposit sigma_a / sigma_t of the weight, then HG deflection */
        vf dw = w * fa;
        sumA += select((vf)(0.0f), dw, inter);
        w = select(w, w - dw, inter);
        lw = select(lw, lw + l1a, inter);
        /* HG inversion (MCML Spin): t = (1 - g^2) / (1 - g + 2 g u), cos = (1 + g^2 - t^2)
         * / (2 g), written over one common denominator: one division instead of two */
        vf g2 = g * g, hA = 1.0f - g2, hB = mad(2.0f * g, u1, 1.0f - g), hB2 = hB * hB;
        vf cth = select(((1.0f + g2) * hB2 - hA * hA) / (2.0f * g * hB2),
                        mad(2.0f, u1, -1.0f), fabs(g) <= 1e-3f);
        cth = clamp(cth, -1.0f, 1.0f);
        vf sth = sqrt(fmax(1.0f - cth * cth, 0.0f));
        vf cph, sph;
        azimuth(u2, &cph, &sph);
        /* MCML Spin: rotate (sth cph, sth sph, cth) into the frame of (ux, uy, uz) */
        vf tmp = sqrt(fmax(1.0f - uz * uz, 0.0f));
        vf q = sth / tmp;
        vf nx = q * (ux * uz * cph - uy * sph) + ux * cth;
        vf ny = q * (uy * uz * cph + ux * sph) + uy * cth;
        vf nz = uz * cth - sth * cph * tmp;
        vi pole = fabs(uz) > 0.99999f;
        nx = select(nx, sth * cph, pole);
        ny = select(ny, sth * sph, pole);
        nz = select(nz, select(-cth, cth, uz > 0.0f), pole);   /* uz = +-1: cth or -cth */
        /* renormalise: float rounding drifts over thousands of deflections.  |n|^2 = 1 + e
         * with |e| ~ 1e-6, so one Newton step of 1/sqrt from 1, (3 - |n|^2) / 2, is exact
         * to O(e^2) ~ 1e-12 and needs no sqrt or division */
        vf inv = 0.5f * (3.0f - (nx * nx + ny * ny + nz * nz));
        ux = select(ux, nx * inv, inter);
        uy = select(uy, ny * inv, inter);
        uz = select(uz, nz * inv, inter);
        /* weight window: ln W = -kappa clamp(rho - rho0, 0, rho1 - rho0) + lambda z (0 when
         * off) */
        vf lnW = (vf)(0.0f);
        if (windowed)
            lnW = mad((vf)(lambda), z, -kappa * clamp(sqrt(x * x + y * y) - rho0, 0.0f, span));
        /* Russian roulette below W_MIN W (u3: an interaction event draws no Fresnel number):
         * MCML's (survive 1 in ROULETTE_M, weight x ROULETTE_M) without a window, else to the
         * window (survive with probability w / W, weight W) */
        vi low = inter & (lw < lnW + ln_w_min);
        if (!windowed) {
            vi win = u3 * ROULETTE_M <= 1.0f;
            w = select(w, w * ROULETTE_M, low & win);
            lw = select(lw, lw + LN_ROULETTE_M, low & win);
            alive &= ~(low & ~win);
        } else if (any_lane(low)) {
            vi win = u3 <= exp(lw - lnW);
            w = select(w, exp(lnW), low & win);
            lw = select(lw, lnW, low & win);
            alive &= ~(low & ~win);
        }
        /* split above 2 W: the second half onto the stack (none when it is full) */
        vi heavy = inter & alive & (lw > lnW + LN2_SPLIT);
        if (windowed && splits < max_splits && any_lane(heavy)) {
            float sx[LANES], sy[LANES], sz[LANES], sux[LANES], suy[LANES], suz[LANES];
            float sw[LANES], slw[LANES], ss[LANES];
            int sl[LANES], sh[LANES];
            VSTORE(x, 0, sx); VSTORE(y, 0, sy); VSTORE(z, 0, sz);
            VSTORE(ux, 0, sux); VSTORE(uy, 0, suy); VSTORE(uz, 0, suz);
            VSTORE(w, 0, sw); VSTORE(lw, 0, slw); VSTORE(srem, 0, ss);
            VSTORE(lay, 0, sl); VSTORE(heavy, 0, sh);
            for (int i = 0; i < LANES; ++i) {
                if (sh[i] == 0 || bank_n >= BANK || splits >= max_splits) { sh[i] = 0; continue; }
                __global float *e = B + bank_n * BANK_FLOATS;
                e[0] = sx[i]; e[1] = sy[i]; e[2] = sz[i]; e[3] = sux[i]; e[4] = suy[i];
                e[5] = suz[i]; e[6] = 0.5f * sw[i]; e[7] = slw[i] - LN2_SPLIT; e[8] = ss[i];
                e[9] = (float)sl[i];
                ++bank_n;
                ++splits;
            }
            vi done = VLOAD(0, sh);
            w = select(w, 0.5f * w, done);
            lw = select(lw, lw - LN2_SPLIT, done);
        }
        psteps -= inter;                           /* inter is -1 where true */
        vi cap = alive & (psteps >= MAX_STEPS);
        if (any_lane(cap)) {
            VSTORE(VLOAD(0, accL) + select((vf)(0.0f), w, cap), 0, accL);
            alive &= ~cap;
        }

        /* boundary: Fresnel reflect or refract (u3), escape through top or bottom */
        if (any_lane(hit)) {
            VSTORE(VLOAD(0, acc_hits) - as_vu(hit), 0, acc_hits);
            /* move the lanes that hit onto the boundary; they keep the rest of the path */
            vf db = (zb - z) / uz;
            x = select(x, mad(db, ux, x), hit);
            y = select(y, mad(db, uy, y), hit);
            z = select(z, zb, hit);
            srem = select(srem, s - db, hit);
            vi nb = lay + select((vi)(-1), (vi)(1), down);
            vf n2 = select((vf)(eta_below), (vf)(eta_above), nb < 0), eta = 0.0f;
            for (int k = 0; k < n_layers; ++k) {
                n2 = select(n2, (vf)(L[k * 8 + 6]), nb == k);
                eta = select(eta, (vf)(L[k * 8 + 6]), lay == k);
            }
            vf ci = fabs(uz);
            vf ratio = eta / n2;
            vf st2 = ratio * ratio * (1.0f - ci * ci);
            vf ct = sqrt(fmax(1.0f - st2, 0.0f));
            vf a1 = eta * ci, a2 = n2 * ct, b1 = eta * ct, b2 = n2 * ci;
            vf rs = (a1 - a2) / (a1 + a2), rp = (b1 - b2) / (b1 + b2);
            vf rf = select(0.5f * (rs * rs + rp * rp), (vf)(1.0f), st2 >= 1.0f);
            vi same = n2 == eta;
            rf = select(rf, (vf)(0.0f), same);
            ct = select(ct, ci, same);
            vi refl = hit & (u3 <= rf);
            uz = select(uz, -uz, refl);
            vi trans = hit & ~refl;
            vi top = trans & (nb < 0), bot = trans & (nb >= n_layers);
            vi inner = trans & ~(top | bot);
            if (any_lane(inner)) {                      /* Snell into the neighbouring layer */
                ux = select(ux, ux * ratio, inner);
                uy = select(uy, uy * ratio, inner);
                uz = select(uz, copysign(ct, uz), inner);
                lay = select(lay, nb, inner);
                vf old_inv_mut = inv_mut;
                LOAD_LAYER(inner, nb);
                /* the remaining optical depth carries over: s' = s sigma_t / sigma_t' */
                srem = select(srem, srem * inv_mut / old_inv_mut, inner);
            }
            vi esc = top | bot;
            if (any_lane(esc)) {
                vf rr = sqrt(x * x + y * y);
                int ee[LANES];
                float ew[LANES], er[LANES];
                VSTORE(rr, 0, er);
                VSTORE(top - bot, 0, ee);          /* -1 top, +1 bottom, 0 neither */
                VSTORE(w, 0, ew);
                for (int i = 0; i < LANES; ++i) {
                    if (ee[i] == 0) continue;
                    if (ee[i] < 0) accR[i] += ew[i];
                    else accT[i] += ew[i];
                    if (er[i] >= r_last) continue;
                    int lo = 0, hi = n_bins;       /* edges[lo] <= r < edges[hi] */
                    while (hi - lo > 1) {
                        int mid = (lo + hi) >> 1;
                        if (er[i] >= edges[mid]) lo = mid; else hi = mid;
                    }
                    (ee[i] < 0 ? hR : hT)[lo] += ew[i];
                }
                alive &= ~esc;
            }
        }

        /* refill dead lanes: split photons from the stack first (last in, first out), in
         * lane order */
        if (bank_n > 0 && any_lane(~alive)) {
            float sx[LANES], sy[LANES], sz[LANES], sux[LANES], suy[LANES], suz[LANES];
            float sw[LANES], slw[LANES], ss[LANES];
            int sl[LANES], sa_[LANES];
            VSTORE(x, 0, sx); VSTORE(y, 0, sy); VSTORE(z, 0, sz);
            VSTORE(ux, 0, sux); VSTORE(uy, 0, suy); VSTORE(uz, 0, suz);
            VSTORE(w, 0, sw); VSTORE(lw, 0, slw); VSTORE(srem, 0, ss);
            VSTORE(lay, 0, sl); VSTORE(alive, 0, sa_);
            int got[LANES];
            for (int i = 0; i < LANES; ++i) {
                got[i] = 0;
                if (sa_[i] != 0 || bank_n == 0) continue;
                --bank_n;
                __global const float *e = B + bank_n * BANK_FLOATS;
                sx[i] = e[0]; sy[i] = e[1]; sz[i] = e[2]; sux[i] = e[3]; suy[i] = e[4];
                suz[i] = e[5]; sw[i] = e[6]; slw[i] = e[7]; ss[i] = e[8]; sl[i] = (int)e[9];
                got[i] = -1;
            }
            vi popped = VLOAD(0, got);
            VSTORE(VLOAD(0, acc_steps) + select((vu)(0u), as_vu(psteps), popped), 0, acc_steps);
            x = VLOAD(0, sx); y = VLOAD(0, sy); z = VLOAD(0, sz);
            ux = VLOAD(0, sux); uy = VLOAD(0, suy); uz = VLOAD(0, suz);
            w = VLOAD(0, sw); lw = VLOAD(0, slw); srem = VLOAD(0, ss);
            lay = VLOAD(0, sl);
            psteps = select(psteps, (vi)(0), popped);
            alive |= popped;
            LOAD_LAYER(popped, lay);
        }
        /* then new photons while the budget lasts; the k-th dead lane (in lane order) gets
         * photon launched + k, so the assignment is deterministic */
        if (launched < budget) {
            vi need = ~alive;
            if (any_lane(need)) {
                vi scan = need & 1;
                #pragma unroll
                for (int k = 1; k < LANES; k <<= 1) {
                    vi sh = shuffle(scan, cvt_u(max(lane - k, 0)));
                    scan += select((vi)(0), sh, lane >= k);
                }
                vi start = need & ((launched - 1 + scan) < budget);
                VSTORE(VLOAD(0, acc_steps) + select((vu)(0u), as_vu(psteps), start), 0, acc_steps);
                launched = min(launched + LAST(scan), budget);
                alive |= start;
                x = select(x, (vf)(0.0f), start);
                y = select(y, (vf)(0.0f), start);
                z = select(z, (vf)(0.0f), start);
                ux = select(ux, (vf)(0.0f), start);
                uy = select(uy, (vf)(0.0f), start);
                uz = select(uz, (vf)(1.0f), start);
                w = select(w, (vf)(1.0f), start);
                lw = select(lw, (vf)(0.0f), start);
                srem = select(srem, (vf)(0.0f), start);
                psteps = select(psteps, (vi)(0), start);
                lay = select(lay, (vi)(0), start);
                LOAD_LAYER(start, lay);
            }
        }
    }

    /* the last photon of every lane has not been tallied at a refill */
    VSTORE(VLOAD(0, acc_steps) + as_vu(psteps), 0, acc_steps);
    float r[N_TOTALS] = {0.0f};
    float ta[LANES];
    VSTORE(sumA, 0, ta);
    for (int i = 0; i < LANES; ++i) {
        r[0] += accR[i]; r[1] += accT[i]; r[2] += ta[i]; r[3] += accL[i];
        r[4] += (float)acc_steps[i]; r[5] += (float)(acc_steps[i] + acc_hits[i]);
    }
    r[6] = (float)trip + 4294967296.0f * (float)trip_hi;
    __global float *out = totals + (size_t)(ch * items + item) * N_TOTALS;
    for (int i = 0; i < N_TOTALS; ++i) out[i] = r[i];
}

/* Self-test for tests/test_mc_slab.py: Philox known answers (Random123 kat_vectors) from
 * the scalar form (10 rounds) and from lanes 2 and 3 of the vector form (the tracer's
 * PHILOX_ROUNDS), and the cheap math of the
 * tracer (neg_log, azimuth) on given uniforms u (n a multiple of LANES).
 * kat: [0..3] scalar ctr 0, key 0; [4..7] lane 2: ctr all ones, key all ones; [8..11]
 * lane 3: ctr (243f6a88 85a308d3 13198a2e 03707344), key (a4093822 299f31d0).
 * math: [0, n) -ln u, [n, 2n) cos(2 pi u - pi), [2n, 3n) sin(2 pi u - pi). */
__kernel void mc_selftest(__global uint *kat, __global const float *u, __global float *math)
{
    const int i = get_global_id(0);
    const int n = get_global_size(0) * LANES;
    if (i == 0) {
        uint4 r = philox4x32_10((uint4)(0u), (uint2)(0u));
        kat[0] = r.x; kat[1] = r.y; kat[2] = r.z; kat[3] = r.w;
        vi three = LANE_IDS == 3;
        vu c0 = select((vu)(0xffffffffu), (vu)(0x243f6a88u), as_vu(three));
        vu c1 = select((vu)(0xffffffffu), (vu)(0x85a308d3u), as_vu(three));
        vu c2 = select((vu)(0xffffffffu), (vu)(0x13198a2eu), as_vu(three));
        vu c3 = select((vu)(0xffffffffu), (vu)(0x03707344u), as_vu(three));
        vu d0 = c0, d1 = c1, d2 = c2, d3 = c3;
        PHILOX_TRACE(vu, MULHILO, c0, c1, c2, c3, 0xffffffffu, 0xffffffffu);
        PHILOX_TRACE(vu, MULHILO, d0, d1, d2, d3, 0xa4093822u, 0x299f31d0u);
        kat[4] = c0.s2; kat[5] = c1.s2; kat[6] = c2.s2; kat[7] = c3.s2;
        kat[8] = d0.s3; kat[9] = d1.s3; kat[10] = d2.s3; kat[11] = d3.s3;
    }
    vf v = VLOAD(i, u), c, s;
    azimuth(v, &c, &s);
    VSTORE(neg_log(v), i, math);
    VSTORE(c, i, math + n);
    VSTORE(s, i, math + 2 * n);
}
