/* fpm_step.c: see fpm_step.h. C99; OpenMP when compiled with it, one thread without.

   Layout in memory, for the machine: positions are copied to structure-of-arrays (all x, then
   y, z) at the start of a step. Most springs are pulled: cut into slots of LANES consecutive
   nodes (a window) and one offset to the other ends, each spring in the slots of both its ends,
   so that a window's spring forces are summed in registers and stored once, loads only (a
   spring computed twice costs less than two stores to nodes another spring reads). The springs
   whose slots would be mostly empty (irregular parts) are reordered into blocks of up to LANES
   springs whose ends i are consecutive nodes and whose j - i is the same, and the hexahedra
   into blocks side by side along x: a block's lanes load their nodes with contiguous vector
   loads and add their forces with contiguous vector stores; the springs and hexahedra in no
   block take gathers. The nodes are cut into PARTS ranges, and the forces summed into PARTS
   partial sums, part p over the slots of its windows and the blocks whose first node is in its
   range (a thread per part: it copies, sums and steps its own nodes, so that two threads share
   only the nodes near where their ranges meet), added node by node in a fixed order: the
   threads change no bit of the step. With AVX-512 (float64), 1 / length comes from the 14-bit
   reciprocal square root estimate and two Newton steps instead of a square root and a
   division. Against the NumPy recipe (fpm.runtime) the step differs in the order of sums and
   in that 1 / length: within rounding. */
#include "fpm_step.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#ifdef _OPENMP
#include <omp.h>
#endif

#ifdef FPM_FLOAT32
#define SQRT sqrtf
#else
#define SQRT sqrt
#endif

#if defined(__GNUC__)
#define INLINE static inline __attribute__((always_inline))
#define UNROLL _Pragma("GCC unroll 24")
#else
#define UNROLL
#define INLINE static inline
#endif

#define MESSAGE_BYTES 320
#define LANES 8 /* springs and hexahedra side by side in a block */
#define PARTS 2 /* partial sums of the forces: fixed, so that threads change no bit */
#define SCRATCH (24 * LANES + 64) /* a part's scratch, fpm_real: 24 LANES and a gap, so that
                                     no two parts share a cache line */
#define POWER_ITERATIONS 40
#define SLOT_LANES 4 /* a slot of pulled springs fills at least this many of its LANES */

#if defined(__AVX512F__) && !defined(FPM_FLOAT32)
#include <immintrin.h>
#define FPM_AVX512 1 /* a block of LANES = 8 doubles is one AVX-512 register */
#else
#define FPM_AVX512 0
#endif

struct fpm_model {
    uint32_t n, s, h, ncases, nshare;
    double d, dt, settle_tolerance, settle_stiffness, gravity[3];
    double stable_dt; /* Gershgorin's bound, s */
    double omega2;    /* a lower bound of the largest eigenvalue of M^-1 K at rest, 1/s^2 */
    double mass_min;  /* the lightest free node, kg */
    fpm_real *rest, *mass, *a, *denom, *mg; /* a = dt / m, denom = 1 + a d, mg = m g (3 N) */
    unsigned char *fixed;
    fpm_real *free_;     /* 1 at a free node, 0 at a fixed one */
    fpm_real *no_forces; /* 3 N zeros */
    uint32_t *si, *sj;                /* S spring ends, blocks first */
    uint32_t nsblocks, nhblocks;      /* blocks of 2..LANES springs, hexahedra */
    uint32_t spart[PARTS + 1], hpart[PARTS + 1];     /* part p's blocks: from [p] to [p + 1] */
    uint32_t ssingle[PARTS + 1], hsingle[PARTS + 1]; /* part p's single items */
    uint32_t nslots, slot_part[PARTS + 1]; /* pulled springs: slots, part p's from [p] */
    uint32_t *slot_window;                 /* the slot's nodes: LANES w .. LANES w + 7 */
    int32_t *slot_offset;                  /* the other ends: those nodes plus it */
    unsigned char *slot_live;              /* bit l: a spring in lane l */
    fpm_real *slot_k, *slot_length;        /* LANES a slot: N/m, m */
    uint32_t *sblock, *hblock; /* block b: items sblock[b]..sblock[b + 1]; then the single ones */
    fpm_real *rest_length, *stiffness; /* S */
    uint32_t *hex;                    /* 8 H corners, hexahedron by hexahedron */
    uint32_t *corner;                 /* the same, corner by corner: corner[a H + c] */
    fpm_real *kappa, *volume0;        /* H */
    fpm_real *Xbuf, *X; /* 3 NP, NP = N + 2 LANES: positions, all x then y, z, each with LANES
                          zeros before and after (X: the first x) */
    fpm_real *acc;     /* PARTS x 3 NP: the passes' partial sums of the internal forces */
    fpm_real *scratch; /* PARTS x 24 LANES */
    uint32_t *case_offset, *case_node;
    double *case_force;
    uint32_t *share_node, *share_offset, *share_index;
    double *share_weight;
    int threads;
    double load_scale, moved_scale;
    char message[MESSAGE_BYTES];
};

/* ---------------------------------------------------------------- the volume of a hexahedron */

/* The volume of the trilinear hexahedron with corners (x_n, y_n, z_n), n in NATURAL order
   (---), (+--), (++-), (-+-), (--+), (+-+), (+++), (-++), and its gradient with respect to the
   corners into g[(3 n + d) stride] (fpm.runtime.hexahedron_volumes). From the coefficients
   a_k = 1/8 sum_n C_kn x_n of r, s, t, rs, rt, st of the trilinear map,
   V = 8 [a0, a1, a2] + 8/3 ([a0, a3, a4] + [a3, a1, a5] + [a4, a5, a2]), the triple products
   [p, q, r] = p . (q x r). Straight-line code, so that a loop over hexahedra runs in SIMD lanes. */
INLINE fpm_real hex_gradient(fpm_real x0, fpm_real x1, fpm_real x2, fpm_real x3, fpm_real x4,
                            fpm_real x5, fpm_real x6, fpm_real x7, fpm_real y0, fpm_real y1,
                            fpm_real y2, fpm_real y3, fpm_real y4, fpm_real y5, fpm_real y6,
                            fpm_real y7, fpm_real z0, fpm_real z1, fpm_real z2, fpm_real z3,
                            fpm_real z4, fpm_real z5, fpm_real z6, fpm_real z7, fpm_real *restrict
                            g, long stride) {
    const fpm_real s01x = x1 - x0, s32x = x2 - x3;
    const fpm_real s45x = x5 - x4, s76x = x6 - x7;
    const fpm_real q01x = x0 + x1, q23x = x2 + x3;
    const fpm_real q45x = x4 + x5, q67x = x6 + x7;
    const fpm_real a0x = ((s01x + s32x) + (s45x + s76x)) / 8;
    const fpm_real a1x = ((q23x - q01x) + (q67x - q45x)) / 8;
    const fpm_real a2x = ((q45x + q67x) - (q01x + q23x)) / 8;
    const fpm_real a3x = ((s32x - s01x) + (s76x - s45x)) / 8;
    const fpm_real a4x = ((s45x + s76x) - (s01x + s32x)) / 8;
    const fpm_real a5x = ((q01x - q23x) + (q67x - q45x)) / 8;
    const fpm_real s01y = y1 - y0, s32y = y2 - y3;
    const fpm_real s45y = y5 - y4, s76y = y6 - y7;
    const fpm_real q01y = y0 + y1, q23y = y2 + y3;
    const fpm_real q45y = y4 + y5, q67y = y6 + y7;
    const fpm_real a0y = ((s01y + s32y) + (s45y + s76y)) / 8;
    const fpm_real a1y = ((q23y - q01y) + (q67y - q45y)) / 8;
    const fpm_real a2y = ((q45y + q67y) - (q01y + q23y)) / 8;
    const fpm_real a3y = ((s32y - s01y) + (s76y - s45y)) / 8;
    const fpm_real a4y = ((s45y + s76y) - (s01y + s32y)) / 8;
    const fpm_real a5y = ((q01y - q23y) + (q67y - q45y)) / 8;
    const fpm_real s01z = z1 - z0, s32z = z2 - z3;
    const fpm_real s45z = z5 - z4, s76z = z6 - z7;
    const fpm_real q01z = z0 + z1, q23z = z2 + z3;
    const fpm_real q45z = z4 + z5, q67z = z6 + z7;
    const fpm_real a0z = ((s01z + s32z) + (s45z + s76z)) / 8;
    const fpm_real a1z = ((q23z - q01z) + (q67z - q45z)) / 8;
    const fpm_real a2z = ((q45z + q67z) - (q01z + q23z)) / 8;
    const fpm_real a3z = ((s32z - s01z) + (s76z - s45z)) / 8;
    const fpm_real a4z = ((s45z + s76z) - (s01z + s32z)) / 8;
    const fpm_real a5z = ((q01z - q23z) + (q67z - q45z)) / 8;
    const fpm_real w0 = 8, w = (fpm_real)(8.0 / 3.0);
    fpm_real volume = 0;
    /* [a0, a1, a2] */
    const fpm_real qr0x = a1y * a2z - a1z * a2y;
    const fpm_real qr0y = a1z * a2x - a1x * a2z;
    const fpm_real qr0z = a1x * a2y - a1y * a2x;
    const fpm_real rp0x = a2y * a0z - a2z * a0y;
    const fpm_real rp0y = a2z * a0x - a2x * a0z;
    const fpm_real rp0z = a2x * a0y - a2y * a0x;
    const fpm_real pq0x = a0y * a1z - a0z * a1y;
    const fpm_real pq0y = a0z * a1x - a0x * a1z;
    const fpm_real pq0z = a0x * a1y - a0y * a1x;
    volume += w0 * (a0x * qr0x + a0y * qr0y + a0z * qr0z);
    const fpm_real g0x0 = w0 * qr0x;
    const fpm_real g0y0 = w0 * qr0y;
    const fpm_real g0z0 = w0 * qr0z;
    const fpm_real g1x0 = w0 * rp0x;
    const fpm_real g1y0 = w0 * rp0y;
    const fpm_real g1z0 = w0 * rp0z;
    const fpm_real g2x0 = w0 * pq0x;
    const fpm_real g2y0 = w0 * pq0y;
    const fpm_real g2z0 = w0 * pq0z;
    /* [a0, a3, a4] */
    const fpm_real qr1x = a3y * a4z - a3z * a4y;
    const fpm_real qr1y = a3z * a4x - a3x * a4z;
    const fpm_real qr1z = a3x * a4y - a3y * a4x;
    const fpm_real rp1x = a4y * a0z - a4z * a0y;
    const fpm_real rp1y = a4z * a0x - a4x * a0z;
    const fpm_real rp1z = a4x * a0y - a4y * a0x;
    const fpm_real pq1x = a0y * a3z - a0z * a3y;
    const fpm_real pq1y = a0z * a3x - a0x * a3z;
    const fpm_real pq1z = a0x * a3y - a0y * a3x;
    volume += w * (a0x * qr1x + a0y * qr1y + a0z * qr1z);
    const fpm_real g0x1 = g0x0 + w * qr1x;
    const fpm_real g0y1 = g0y0 + w * qr1y;
    const fpm_real g0z1 = g0z0 + w * qr1z;
    const fpm_real g3x1 = w * rp1x;
    const fpm_real g3y1 = w * rp1y;
    const fpm_real g3z1 = w * rp1z;
    const fpm_real g4x1 = w * pq1x;
    const fpm_real g4y1 = w * pq1y;
    const fpm_real g4z1 = w * pq1z;
    /* [a3, a1, a5] */
    const fpm_real qr2x = a1y * a5z - a1z * a5y;
    const fpm_real qr2y = a1z * a5x - a1x * a5z;
    const fpm_real qr2z = a1x * a5y - a1y * a5x;
    const fpm_real rp2x = a5y * a3z - a5z * a3y;
    const fpm_real rp2y = a5z * a3x - a5x * a3z;
    const fpm_real rp2z = a5x * a3y - a5y * a3x;
    const fpm_real pq2x = a3y * a1z - a3z * a1y;
    const fpm_real pq2y = a3z * a1x - a3x * a1z;
    const fpm_real pq2z = a3x * a1y - a3y * a1x;
    volume += w * (a3x * qr2x + a3y * qr2y + a3z * qr2z);
    const fpm_real g3x2 = g3x1 + w * qr2x;
    const fpm_real g3y2 = g3y1 + w * qr2y;
    const fpm_real g3z2 = g3z1 + w * qr2z;
    const fpm_real g1x2 = g1x0 + w * rp2x;
    const fpm_real g1y2 = g1y0 + w * rp2y;
    const fpm_real g1z2 = g1z0 + w * rp2z;
    const fpm_real g5x2 = w * pq2x;
    const fpm_real g5y2 = w * pq2y;
    const fpm_real g5z2 = w * pq2z;
    /* [a4, a5, a2] */
    const fpm_real qr3x = a5y * a2z - a5z * a2y;
    const fpm_real qr3y = a5z * a2x - a5x * a2z;
    const fpm_real qr3z = a5x * a2y - a5y * a2x;
    const fpm_real rp3x = a2y * a4z - a2z * a4y;
    const fpm_real rp3y = a2z * a4x - a2x * a4z;
    const fpm_real rp3z = a2x * a4y - a2y * a4x;
    const fpm_real pq3x = a4y * a5z - a4z * a5y;
    const fpm_real pq3y = a4z * a5x - a4x * a5z;
    const fpm_real pq3z = a4x * a5y - a4y * a5x;
    volume += w * (a4x * qr3x + a4y * qr3y + a4z * qr3z);
    const fpm_real g4x3 = g4x1 + w * qr3x;
    const fpm_real g4y3 = g4y1 + w * qr3y;
    const fpm_real g4z3 = g4z1 + w * qr3z;
    const fpm_real g5x3 = g5x2 + w * rp3x;
    const fpm_real g5y3 = g5y2 + w * rp3y;
    const fpm_real g5z3 = g5z2 + w * rp3z;
    const fpm_real g2x3 = g2x0 + w * pq3x;
    const fpm_real g2y3 = g2y0 + w * pq3y;
    const fpm_real g2z3 = g2z0 + w * pq3z;
    /* g_n = 1/8 sum_k C_kn dV/da_k */
    const fpm_real abx = g0x1 + g1x2, a_bx = g0x1 - g1x2;
    const fpm_real dex = g3x2 + g4x3, d_ex = g3x2 - g4x3;
    const fpm_real fcx = g5x3 - g2x3, f_cx = g5x3 + g2x3;
    g[0 * stride] = (dex - abx + fcx) / 8;
    g[3 * stride] = (a_bx - dex + fcx) / 8;
    g[6 * stride] = (abx + d_ex - f_cx) / 8;
    g[9 * stride] = (-a_bx - d_ex - f_cx) / 8;
    g[12 * stride] = (d_ex - abx - fcx) / 8;
    g[15 * stride] = (a_bx - d_ex + g2x3 - g5x3) / 8;
    g[18 * stride] = (abx + dex + f_cx) / 8;
    g[21 * stride] = (-a_bx - dex + f_cx) / 8;
    const fpm_real aby = g0y1 + g1y2, a_by = g0y1 - g1y2;
    const fpm_real dey = g3y2 + g4y3, d_ey = g3y2 - g4y3;
    const fpm_real fcy = g5y3 - g2y3, f_cy = g5y3 + g2y3;
    g[1 * stride] = (dey - aby + fcy) / 8;
    g[4 * stride] = (a_by - dey + fcy) / 8;
    g[7 * stride] = (aby + d_ey - f_cy) / 8;
    g[10 * stride] = (-a_by - d_ey - f_cy) / 8;
    g[13 * stride] = (d_ey - aby - fcy) / 8;
    g[16 * stride] = (a_by - d_ey + g2y3 - g5y3) / 8;
    g[19 * stride] = (aby + dey + f_cy) / 8;
    g[22 * stride] = (-a_by - dey + f_cy) / 8;
    const fpm_real abz = g0z1 + g1z2, a_bz = g0z1 - g1z2;
    const fpm_real dez = g3z2 + g4z3, d_ez = g3z2 - g4z3;
    const fpm_real fcz = g5z3 - g2z3, f_cz = g5z3 + g2z3;
    g[2 * stride] = (dez - abz + fcz) / 8;
    g[5 * stride] = (a_bz - dez + fcz) / 8;
    g[8 * stride] = (abz + d_ez - f_cz) / 8;
    g[11 * stride] = (-a_bz - d_ez - f_cz) / 8;
    g[14 * stride] = (d_ez - abz - fcz) / 8;
    g[17 * stride] = (a_bz - d_ez + g2z3 - g5z3) / 8;
    g[20 * stride] = (abz + dez + f_cz) / 8;
    g[23 * stride] = (-a_bz - dez + f_cz) / 8;
    return volume;
}

#define CORNERS(v) v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7]
#define XYZ(n) const fpm_real x##n = X[AT(n)], y##n = Y[AT(n)], z##n = Z[AT(n)]
#define LOAD_CORNERS XYZ(0); XYZ(1); XYZ(2); XYZ(3); XYZ(4); XYZ(5); XYZ(6); XYZ(7)
#define SCALARS(v) v##0, v##1, v##2, v##3, v##4, v##5, v##6, v##7

/* The pressure term's factor for hexahedron c of this volume: its corner forces are this times
   the volume's gradient. */
INLINE fpm_real minus_pressure(const fpm_model *m, long c, fpm_real volume) {
    return -(m->kappa[c] * (volume - m->volume0[c]) / m->volume0[c]);
}

/* The corners in the order their forces are added: those one node apart along x (0 and 1, 3
   and 2, 4 and 5, 7 and 6) far apart, so that a load of a window waits for no store to the
   window one node over still in flight. */
static const int APART[8] = {0, 2, 4, 6, 1, 3, 5, 7};

/* Part p's share of the hexahedra: blocks b0..b1 (their lanes side by side along x, corners
   lane 0's plus l: vector loads and stores; lanes past a block's end add nothing) and the
   single hexahedra c0..c1 (gathers), their corner forces added to acc (3 NP: x, y, z). */
static void hex_part(fpm_model *m, long b0, long b1, long c0, long c1, fpm_real *restrict acc,
                     fpm_real *restrict g) {
    const long H = m->h, NP = m->n + 2 * LANES;
    const fpm_real *restrict X = m->X, *restrict Y = X + NP, *restrict Z = X + 2 * NP;
    const uint32_t *restrict corner = m->corner;
    for (long b = b0; b < b1; b++) {
        const long first = m->hblock[b], count = m->hblock[b + 1] - first;
        const long q0 = corner[first], q1 = corner[H + first], q2 = corner[2 * H + first];
        const long q3 = corner[3 * H + first], q4 = corner[4 * H + first];
        const long q5 = corner[5 * H + first], q6 = corner[6 * H + first];
        const long q7 = corner[7 * H + first];
        const long q[8] = {q0, q1, q2, q3, q4, q5, q6, q7};
#define AT(n) (q##n + l)
#pragma omp simd
        for (long l = 0; l < LANES; l++) {
            LOAD_CORNERS;
            const fpm_real volume = hex_gradient(SCALARS(x), SCALARS(y), SCALARS(z), g + l, LANES);
            const fpm_real pressure = minus_pressure(m, first + l, volume);
            const fpm_real factor = l < count ? pressure : 0;
            UNROLL for (int k = 0; k < 24; k++) g[k * LANES + l] *= factor;
        }
#undef AT
        for (int c = 0; c < 8; c++) {
            const int n = APART[c];
            for (int d = 0; d < 3; d++) {
                fpm_real *restrict out = acc + d * NP + q[n];
                const fpm_real *restrict from = g + (3 * n + d) * LANES;
#pragma omp simd
                for (long l = 0; l < LANES; l++) out[l] += from[l];
            }
        }
    }
    for (long first = c0; first < c1; first += LANES) {
        const long count = c1 - first < LANES ? c1 - first : LANES;
#define AT(n) ((size_t)corner[(n) * H + first + l])
#pragma omp simd
        for (long l = 0; l < count; l++) {
            LOAD_CORNERS;
            const fpm_real volume = hex_gradient(SCALARS(x), SCALARS(y), SCALARS(z), g + l, LANES);
            const fpm_real factor = minus_pressure(m, first + l, volume);
            UNROLL for (int k = 0; k < 24; k++) g[k * LANES + l] *= factor;
        }
#undef AT
        for (long l = 0; l < count; l++)
            for (int k = 0; k < 24; k++)
                acc[(k % 3) * NP + corner[(k / 3) * H + first + l]] += g[k * LANES + l];
    }
}

/* c (k (L - L0) / L, L = |r|) of spring e at r = x_j - x_i: its force on end i is c r. */
INLINE fpm_real spring_factor(const fpm_model *m, long e, fpm_real rx, fpm_real ry, fpm_real rz) {
    const fpm_real length = SQRT(rx * rx + ry * ry + rz * rz);
    return m->stiffness[e] * (length - m->rest_length[e]) / length;
}

#if FPM_AVX512
/* c = k (L - L0) / L of 8 springs at r = (rx, ry, rz) (0 in the lanes not in live), its force on
   end i c r: 1 / L from the 14-bit reciprocal square root estimate and two Newton steps (to
   within an ulp or two), no square root and no division. */
INLINE __m512d spring_coefficients(__m512d rx, __m512d ry, __m512d rz, __m512d k, __m512d rest,
                                   __mmask8 live) {
    const __m512d r2 = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(rx, rx), _mm512_mul_pd(ry, ry)),
                                     _mm512_mul_pd(rz, rz));
    const __m512d half_r2 = _mm512_mul_pd(_mm512_set1_pd(0.5), r2);
    __m512d y = _mm512_rsqrt14_pd(r2);
    for (int newton = 0; newton < 2; newton++)
        y = _mm512_mul_pd(y, _mm512_sub_pd(_mm512_set1_pd(1.5),
                                           _mm512_mul_pd(half_r2, _mm512_mul_pd(y, y))));
    const __m512d stretch = _mm512_sub_pd(_mm512_set1_pd(1.0), _mm512_mul_pd(rest, y));
    return _mm512_maskz_mul_pd(live, k, stretch);
}
#endif

/* Part p's share of the springs: blocks b0..b1 (ends i consecutive, j - i the same: vector
   loads and stores) and the single springs e0..e1 (gathers), their forces added to acc (+ on
   end i, - on end j). f: 3 LANES scratch. */
static void spring_part(fpm_model *m, long b0, long b1, long e0, long e1, fpm_real *restrict acc,
                        fpm_real *restrict f) {
    const long NP = m->n + 2 * LANES;
    const fpm_real *restrict X = m->X, *restrict Y = X + NP, *restrict Z = X + 2 * NP;
    const uint32_t *restrict si = m->si, *restrict sj = m->sj;
    for (long b = b0; b < b1; b++) {
        const long first = m->sblock[b], count = m->sblock[b + 1] - first;
        const long i = si[first], j = sj[first];
#if FPM_AVX512
        const __mmask8 live = (__mmask8)((1u << count) - 1u);
        const __m512d rx = _mm512_sub_pd(_mm512_loadu_pd(X + j), _mm512_loadu_pd(X + i));
        const __m512d ry = _mm512_sub_pd(_mm512_loadu_pd(Y + j), _mm512_loadu_pd(Y + i));
        const __m512d rz = _mm512_sub_pd(_mm512_loadu_pd(Z + j), _mm512_loadu_pd(Z + i));
        const __m512d c = spring_coefficients(rx, ry, rz, _mm512_loadu_pd(m->stiffness + first),
                                              _mm512_loadu_pd(m->rest_length + first), live);
        const __m512d f[3] = {_mm512_mul_pd(c, rx), _mm512_mul_pd(c, ry), _mm512_mul_pd(c, rz)};
        for (int d = 0; d < 3; d++) {
            fpm_real *at_i = acc + d * NP + i, *at_j = acc + d * NP + j;
            _mm512_storeu_pd(at_i, _mm512_add_pd(_mm512_loadu_pd(at_i), f[d]));
            _mm512_storeu_pd(at_j, _mm512_sub_pd(_mm512_loadu_pd(at_j), f[d]));
        }
#else
#pragma omp simd
        for (long l = 0; l < LANES; l++) {
            const fpm_real rx = X[j + l] - X[i + l], ry = Y[j + l] - Y[i + l];
            const fpm_real rz = Z[j + l] - Z[i + l];
            const fpm_real factor = spring_factor(m, first + l, rx, ry, rz);
            const fpm_real c = l < count ? factor : 0;
            f[l] = c * rx, f[LANES + l] = c * ry, f[2 * LANES + l] = c * rz;
        }
        for (int d = 0; d < 3; d++) {
            fpm_real *restrict at_i = acc + d * NP + i, *restrict at_j = acc + d * NP + j;
#pragma omp simd
            for (long l = 0; l < LANES; l++) at_i[l] += f[d * LANES + l];
#pragma omp simd
            for (long l = 0; l < LANES; l++) at_j[l] -= f[d * LANES + l];
        }
#endif
    }
    for (long first = e0; first < e1; first += LANES) {
        const long count = e1 - first < LANES ? e1 - first : LANES;
#pragma omp simd
        for (long l = 0; l < count; l++) {
            const size_t i = si[first + l], j = sj[first + l];
            const fpm_real rx = X[j] - X[i], ry = Y[j] - Y[i], rz = Z[j] - Z[i];
            const fpm_real c = spring_factor(m, first + l, rx, ry, rz);
            f[l] = c * rx, f[LANES + l] = c * ry, f[2 * LANES + l] = c * rz;
        }
        for (long l = 0; l < count; l++)
            for (int d = 0; d < 3; d++) {
                acc[d * NP + si[first + l]] += f[d * LANES + l];
                acc[d * NP + sj[first + l]] -= f[d * LANES + l];
            }
    }
}

/* Part p's pulled springs: slots u0..u1, window by window. A slot holds the springs from the
   window's nodes (lanes) to the nodes offset further, each spring in the slots of both its
   ends: the window's forces are summed in registers over its slots and added to acc once, no
   store to a node another slot of the same pass reads. */
static void pull_part(fpm_model *m, long u0, long u1, fpm_real *restrict acc) {
    const long NP = m->n + 2 * LANES;
    const fpm_real *restrict X = m->X, *restrict Y = X + NP, *restrict Z = X + 2 * NP;
    const fpm_real *restrict slot_k = m->slot_k, *restrict slot_length = m->slot_length;
    for (long u = u0; u < u1;) {
        const long w = m->slot_window[u], base = LANES * w;
#if FPM_AVX512
        const __m512d x0 = _mm512_loadu_pd(X + base), y0 = _mm512_loadu_pd(Y + base);
        const __m512d z0 = _mm512_loadu_pd(Z + base);
        __m512d fx = _mm512_setzero_pd(), fy = _mm512_setzero_pd(), fz = _mm512_setzero_pd();
        for (; u < u1 && m->slot_window[u] == (uint32_t)w; u++) {
            const long o = base + m->slot_offset[u];
            const __m512d rx = _mm512_sub_pd(_mm512_loadu_pd(X + o), x0);
            const __m512d ry = _mm512_sub_pd(_mm512_loadu_pd(Y + o), y0);
            const __m512d rz = _mm512_sub_pd(_mm512_loadu_pd(Z + o), z0);
            const __m512d c = spring_coefficients(rx, ry, rz, _mm512_loadu_pd(slot_k + LANES * u),
                                                  _mm512_loadu_pd(slot_length + LANES * u),
                                                  (__mmask8)m->slot_live[u]);
            fx = _mm512_add_pd(fx, _mm512_mul_pd(c, rx));
            fy = _mm512_add_pd(fy, _mm512_mul_pd(c, ry));
            fz = _mm512_add_pd(fz, _mm512_mul_pd(c, rz));
        }
        fpm_real *at_x = acc + base, *at_y = acc + NP + base, *at_z = acc + 2 * NP + base;
        _mm512_storeu_pd(at_x, _mm512_add_pd(_mm512_loadu_pd(at_x), fx));
        _mm512_storeu_pd(at_y, _mm512_add_pd(_mm512_loadu_pd(at_y), fy));
        _mm512_storeu_pd(at_z, _mm512_add_pd(_mm512_loadu_pd(at_z), fz));
#else
        fpm_real f[3][LANES] = {{0}};
        for (; u < u1 && m->slot_window[u] == (uint32_t)w; u++) {
            const long o = base + m->slot_offset[u];
            const unsigned live = m->slot_live[u];
#pragma omp simd
            for (long l = 0; l < LANES; l++) {
                const fpm_real rx = X[o + l] - X[base + l], ry = Y[o + l] - Y[base + l];
                const fpm_real rz = Z[o + l] - Z[base + l];
                const fpm_real length = SQRT(rx * rx + ry * ry + rz * rz);
                const fpm_real factor =
                    slot_k[LANES * u + l] * (length - slot_length[LANES * u + l]) / length;
                const fpm_real c = (live >> l) & 1u ? factor : 0;
                f[0][l] += c * rx, f[1][l] += c * ry, f[2][l] += c * rz;
            }
        }
        for (int d = 0; d < 3; d++)
#pragma omp simd
            for (long l = 0; l < LANES; l++) acc[d * NP + base + l] += f[d][l];
#endif
    }
}

/* Where part p of PARTS starts on n nodes: a multiple of LANES, so that no window of LANES
   nodes is in two parts. */
static long share(long n, long p) { return p >= PARTS ? n : n * p / PARTS / LANES * LANES; }

/* The part of node i: the p with share(n, p) <= i < share(n, p + 1). */
static long part_of(long n, long i) {
    long p = 0;
    while (p + 1 < PARTS && share(n, p + 1) <= i) p++;
    return p;
}

/* The spring and volume forces at positions x into model->acc: PARTS partial sums, part p over
   the springs and hexahedra whose first node is one of its nodes, shared out between the
   threads of the enclosing parallel region (the same sums in the same order however many
   threads). A part's nodes and the items it sums are those its thread copies and steps, so
   that threads exchange only the nodes near where two parts meet. The sums must be zero
   before (the step zeroes them as it reads them). */
static void passes(fpm_model *m, const fpm_real *x) {
    const long N = m->n, NP = N + 2 * LANES;
#pragma omp for schedule(static)
    for (long p = 0; p < PARTS; p++)
        for (long i = share(N, p); i < share(N, p + 1); i++) {
            m->X[i] = x[3 * i];
            m->X[NP + i] = x[3 * i + 1];
            m->X[2 * NP + i] = x[3 * i + 2];
        }
#pragma omp for schedule(static)
    for (long p = 0; p < PARTS; p++) {
        fpm_real *acc = m->acc + p * 3 * NP, *scratch = m->scratch + p * SCRATCH;
        hex_part(m, m->hpart[p], m->hpart[p + 1], m->hsingle[p], m->hsingle[p + 1], acc, scratch);
        spring_part(m, m->spart[p], m->spart[p + 1], m->ssingle[p], m->ssingle[p + 1], acc,
                    scratch);
        pull_part(m, m->slot_part[p], m->slot_part[p + 1], acc);
    }
}

/* The internal force at node i from the last passes, the partial sums zeroed for the next. */
INLINE void take_node_force(fpm_model *m, long i, fpm_real f[3]) {
    const long NP = m->n + 2 * LANES;
    for (int d = 0; d < 3; d++) {
        fpm_real sum = m->acc[d * NP + i];
        m->acc[d * NP + i] = 0;
        for (int p = 1; p < PARTS; p++) {
            sum += m->acc[(3 * p + d) * NP + i];
            m->acc[(3 * p + d) * NP + i] = 0;
        }
        f[d] = sum;
    }
}

static int thread_count(const fpm_model *m) {
#ifdef _OPENMP
    if (m->threads > 0) return m->threads;
    return m->n >= FPM_THREAD_NODES ? omp_get_max_threads() : 1;
#else
    (void)m;
    return 1;
#endif
}

static int fail(fpm_model *m, int code, const char *format, ...) {
    va_list args;
    va_start(args, format);
    vsnprintf(m->message, MESSAGE_BYTES, format, args);
    va_end(args);
    return code;
}

/* ---------------------------------------------------------------------------- the step */

void fpm_reset(fpm_model *m) {
    if (m) m->load_scale = m->moved_scale = 0.0;
}

int fpm_internal_forces(fpm_model *m, const fpm_real *x, fpm_real *out) {
    if (!m || !x || !out) return FPM_ERR_ARGUMENT;
    const long n = m->n;
    const int threads = thread_count(m);
    (void)threads;
#pragma omp parallel num_threads(threads) if (threads > 1)
    {
        passes(m, x);
#pragma omp for schedule(static)
        for (long p = 0; p < PARTS; p++)
            for (long i = share(n, p); i < share(n, p + 1); i++) take_node_force(m, i, out + 3 * i);
    }
    m->message[0] = '\0';
    return FPM_OK;
}

/* The Voigt step of nodes i0..i1 from the last passes (the partial sums zeroed as they are
   read): v' = (v + a f) / (1 + a d), x' = x + dt v'. Branch-free, so that it runs in SIMD
   lanes: a fixed node's velocity is multiplied by 0 (it stays at x) and its force
   counts in no sum. Into sums: the largest |f|^2 and |f_applied|^2 of a free node, the sum of
   |f|^2 over the free nodes and of |x - rest|^2 over all. */
static void advance(fpm_model *m, const fpm_real *restrict x, fpm_real *restrict x_next,
                    fpm_real *restrict v, const fpm_real *restrict forces, long i0, long i1,
                    double sums[4]) {
    const long NP = m->n + 2 * LANES;
    const fpm_real dt = (fpm_real)m->dt;
    fpm_real *restrict acc = m->acc;
    const fpm_real *restrict mg = m->mg, *restrict rest = m->rest, *restrict a = m->a;
    const fpm_real *restrict denom = m->denom, *restrict free_ = m->free_;
    double unbalanced2 = 0, load2 = 0, sum2 = 0, moved2 = 0;
#pragma omp simd reduction(max : unbalanced2, load2) reduction(+ : sum2, moved2)
    for (long i = i0; i < i1; i++) {
        double mag2 = 0, pull2 = 0;
        for (int d = 0; d < 3; d++) {
            fpm_real f = acc[d * NP + i];
            acc[d * NP + i] = 0;
            for (int p = 1; p < PARTS; p++) {
                f += acc[(3 * p + d) * NP + i];
                acc[(3 * p + d) * NP + i] = 0;
            }
            const fpm_real applied = mg[3 * i + d] + forces[3 * i + d];
            const fpm_real total = applied + f;
            const fpm_real u = x[3 * i + d] - rest[3 * i + d];
            moved2 += (double)(u * u);
            mag2 += (double)(total * total);
            pull2 += (double)(applied * applied);
            const fpm_real vn = free_[i] * ((v[3 * i + d] + a[i] * total) / denom[i]);
            v[3 * i + d] = vn;
            x_next[3 * i + d] = x[3 * i + d] + dt * vn;
        }
        mag2 *= free_[i];
        pull2 *= free_[i];
        sum2 += mag2;
        unbalanced2 = mag2 > unbalanced2 ? mag2 : unbalanced2;
        load2 = pull2 > load2 ? pull2 : load2;
    }
    sums[0] = unbalanced2, sums[1] = load2, sums[2] = sum2, sums[3] = moved2;
}

int fpm_step(fpm_model *m, const fpm_real *x, fpm_real *x_next, fpm_real *v,
             const fpm_real *forces, fpm_stats *stats) {
    if (!m || !x || !x_next || !v) return FPM_ERR_ARGUMENT;
    const long n = m->n;
    if (forces) {
        fpm_real check = 0; /* 0 * f is NaN only where f is not finite */
#pragma omp simd reduction(+ : check)
        for (long k = 0; k < 3 * n; k++) check += 0 * forces[k];
        if (check != 0 || check != check)
            for (long k = 0; k < 3 * n; k++)
                if (!isfinite(forces[k]))
                    return fail(m, FPM_ERR_FORCES, "forces[%ld].%c: not finite (%g)", k / 3,
                                "xyz"[k % 3], (double)forces[k]);
    }
    double unbalanced2 = 0, load2 = 0, sum2 = 0, moved2 = 0;
    const int threads = thread_count(m);
    (void)threads;
#pragma omp parallel num_threads(threads) if (threads > 1)
    {
        passes(m, x);
#pragma omp for schedule(static) reduction(max : unbalanced2, load2) \
    reduction(+ : sum2, moved2)
        for (long p = 0; p < PARTS; p++) {
            double part[4];
            advance(m, x, x_next, v, forces ? forces : m->no_forces, share(n, p), share(n, p + 1),
                    part);
            unbalanced2 = part[0] > unbalanced2 ? part[0] : unbalanced2;
            load2 = part[1] > load2 ? part[1] : load2;
            sum2 += part[2];
            moved2 += part[3];
        }
    }
    const double unbalanced = sqrt((double)unbalanced2), load = sqrt((double)load2);
    if (!isfinite(sum2) || !isfinite(moved2))
        return fail(m, FPM_ERR_DIVERGED,
                    "the state is not finite: the step diverged (dt %g s, d %g N s/m)", m->dt,
                    m->d);
    if (load > 0) {
        m->load_scale = load;
        m->moved_scale = sqrt(moved2);
    }
    if (stats) {
        stats->unbalanced = unbalanced;
        stats->load = load;
        stats->settled = unbalanced < m->settle_tolerance * m->load_scale ||
                         sqrt(sum2) < m->settle_stiffness * m->moved_scale;
    }
    m->message[0] = '\0';
    return FPM_OK;
}

/* ------------------------------------------------------------------ forces, queries */

const char *fpm_error(const fpm_model *m) { return m ? m->message : "no model"; }
uint32_t fpm_node_count(const fpm_model *m) { return m ? m->n : 0; }
uint32_t fpm_spring_count(const fpm_model *m) { return m ? m->s : 0; }
uint32_t fpm_hexahedron_count(const fpm_model *m) { return m ? m->h : 0; }
uint32_t fpm_case_count(const fpm_model *m) { return m ? m->ncases : 0; }
double fpm_dt(const fpm_model *m) { return m ? m->dt : 0.0; }
double fpm_damping(const fpm_model *m) { return m ? m->d : 0.0; }
double fpm_stable_dt(const fpm_model *m) { return m ? m->stable_dt : 0.0; }

int fpm_thread_count(const fpm_model *m) { return m ? thread_count(m) : 0; }

int fpm_set_threads(fpm_model *m, int threads) {
    if (!m) return FPM_ERR_ARGUMENT;
    if (threads < 0) return fail(m, FPM_ERR_ARGUMENT, "threads: %d, must be >= 0", threads);
    m->threads = threads;
    return FPM_OK;
}

int fpm_rest_positions(const fpm_model *m, fpm_real *x) {
    if (!m || !x) return FPM_ERR_ARGUMENT;
    memcpy(x, m->rest, 3 * (size_t)m->n * sizeof(fpm_real));
    return FPM_OK;
}

int fpm_case_forces(const fpm_model *m, uint32_t c, fpm_real *forces) {
    if (!m || !forces || c >= m->ncases) return FPM_ERR_ARGUMENT;
    memset(forces, 0, 3 * (size_t)m->n * sizeof(fpm_real));
    for (uint32_t e = m->case_offset[c]; e < m->case_offset[c + 1]; e++)
        for (int d = 0; d < 3; d++)
            forces[3 * (size_t)m->case_node[e] + d] = (fpm_real)m->case_force[3 * (size_t)e + d];
    return FPM_OK;
}

int fpm_applied(const fpm_model *m, const fpm_real *forces, fpm_real *out) {
    if (!m || !forces || !out || forces == out) return FPM_ERR_ARGUMENT;
    const size_t n3 = 3 * (size_t)m->n;
    if (!m->nshare) {
        memcpy(out, forces, n3 * sizeof(fpm_real));
        return FPM_OK;
    }
    memcpy(out, forces, n3 * sizeof(fpm_real));
    for (uint32_t r = 0; r < m->nshare; r++)
        for (int d = 0; d < 3; d++) out[3 * (size_t)m->share_node[r] + d] = 0;
    for (uint32_t r = 0; r < m->nshare; r++) {
        const fpm_real *f = forces + 3 * (size_t)m->share_node[r];
        for (uint32_t e = m->share_offset[r]; e < m->share_offset[r + 1]; e++) {
            fpm_real *o = out + 3 * (size_t)m->share_index[e];
            const fpm_real w = (fpm_real)m->share_weight[e];
            for (int d = 0; d < 3; d++) o[d] += w * f[d];
        }
    }
    return FPM_OK;
}

/* -------------------------------------------------------------------------- stability */

/* Gershgorin's bound (fpm.dynamics.stability, steps 3 and 5) from the springs i, j, k. */
static double gershgorin_dt(const fpm_model *m, const uint32_t *si, const uint32_t *sj,
                            const double *k) {
    double *rows = calloc(m->n ? m->n : 1, sizeof(double));
    if (!rows) return -1.0;
    for (uint32_t s = 0; s < m->s; s++) {
        rows[si[s]] += 2.0 * k[s];
        rows[sj[s]] += 2.0 * k[s];
    }
    for (uint32_t c = 0; c < m->h; c++) {
        fpm_real x[8], y[8], z[8], g[24];
        double norm[8], sum = 0.0;
        for (int a = 0; a < 8; a++) {
            const fpm_real *p = m->rest + 3 * (size_t)m->hex[8 * c + a];
            x[a] = p[0], y[a] = p[1], z[a] = p[2];
        }
        hex_gradient(CORNERS(x), CORNERS(y), CORNERS(z), g, 1);
        for (int a = 0; a < 8; a++) {
            const double gx = g[3 * a], gy = g[3 * a + 1], gz = g[3 * a + 2];
            norm[a] = sqrt(gx * gx + gy * gy + gz * gz);
            sum += norm[a];
        }
        for (int a = 0; a < 8; a++)
            rows[m->hex[8 * c + a]] += (double)m->kappa[c] / (double)m->volume0[c] * norm[a] * sum;
    }
    double top = 0.0;
    for (uint32_t i = 0; i < m->n; i++)
        if (!m->fixed[i] && rows[i] / (double)m->mass[i] > top) top = rows[i] / (double)m->mass[i];
    free(rows);
    return top > 0 ? 2.0 / sqrt(top) : INFINITY;
}

/* A lower bound of the largest eigenvalue of M^-1 K at rest over the free nodes: the largest
   Rayleigh quotient u.Ku / u.Mu met by power iteration, K u by central differences of the
   internal forces. Returns -1 when out of memory. */
static double top_eigenvalue(fpm_model *m) {
    const size_t n3 = 3 * (size_t)m->n;
    fpm_real *u = malloc(n3 * sizeof(fpm_real)), *y = malloc(n3 * sizeof(fpm_real));
    fpm_real *plus = malloc(n3 * sizeof(fpm_real)), *minus = malloc(n3 * sizeof(fpm_real));
    double best = 0.0, scale = 0.0;
    if (!u || !y || !plus || !minus) {
        free(u), free(y), free(plus), free(minus);
        return -1.0;
    }
    for (uint32_t e = 0; e < m->s; e++) scale += (double)m->rest_length[e];
    const double relative = sizeof(fpm_real) == 4 ? 1e-3 : 1e-6; /* above the rounding of x */
    scale = m->s ? relative * scale / m->s : relative;
    uint64_t state = 0x9E3779B97F4A7C15ull;
    for (size_t k = 0; k < n3; k++) {
        state = state * 6364136223846793005ull + 1442695040888963407ull;
        u[k] = m->fixed[k / 3] ? 0 : (fpm_real)((double)(state >> 11) / 9007199254740992.0 - 0.5);
    }
    for (int it = 0; it < POWER_ITERATIONS; it++) {
        double top = 0.0, ku = 0.0, mu = 0.0, norm = 0.0;
        for (size_t k = 0; k < n3; k++) top = fmax(top, fabs((double)u[k]));
        if (top == 0.0) break;
        const double eps = scale / top;
        for (size_t k = 0; k < n3; k++) {
            plus[k] = m->rest[k] + (fpm_real)(eps * u[k]);
            minus[k] = m->rest[k] - (fpm_real)(eps * u[k]);
        }
        fpm_internal_forces(m, plus, y);
        fpm_internal_forces(m, minus, plus);
        for (size_t k = 0; k < n3; k++) {
            const double kuk = m->fixed[k / 3] ? 0.0 : -((double)y[k] - plus[k]) / (2.0 * eps);
            ku += kuk * u[k];
            mu += (double)m->mass[k / 3] * u[k] * u[k];
            y[k] = (fpm_real)(kuk / m->mass[k / 3]);
            norm += (double)y[k] * y[k];
        }
        if (mu > 0 && ku / mu > best) best = ku / mu;
        if (!(norm > 0) || !isfinite(norm)) break;
        norm = sqrt(norm);
        for (size_t k = 0; k < n3; k++) u[k] = (fpm_real)(y[k] / norm);
    }
    free(u), free(y), free(plus), free(minus);
    return best;
}

/* Refuses d < 0, dt <= 0, and a dt at which the step is certainly unstable: w dt beyond
   sqrt(4 + 2 c), c = dt d / m the most damped node's (fpm.dynamics.stability, step 2), for a
   mode w no faster than the fastest. */
static int check_parameters(fpm_model *m, double d, double dt) {
    if (!isfinite(d) || d < 0) return fail(m, FPM_ERR_VALUE, "d: %g, must be finite and >= 0", d);
    if (!isfinite(dt) || dt <= 0) return fail(m, FPM_ERR_VALUE, "dt: %g, must be finite and > 0", dt);
    const double c = m->mass_min > 0 ? dt * d / m->mass_min : 0.0;
    const double limit = m->omega2 > 0 ? sqrt((4.0 + 2.0 * c) / m->omega2) : INFINITY;
    if (dt > limit)
        return fail(m, FPM_ERR_UNSTABLE,
                    "dt: %g s is above the lattice's stability limit (%.4g s for its fastest mode "
                    "at d %g N s/m; %.4g s is stable at any d): the step would diverge",
                    dt, limit, d, m->stable_dt);
    return FPM_OK;
}

static void set_step_arrays(fpm_model *m) {
    for (uint32_t i = 0; i < m->n; i++) {
        m->a[i] = (fpm_real)m->dt / m->mass[i];
        m->denom[i] = (fpm_real)1.0 + m->a[i] * (fpm_real)m->d;
    }
}

int fpm_set_parameters(fpm_model *m, double d, double dt) {
    if (!m) return FPM_ERR_ARGUMENT;
    const int status = check_parameters(m, d, dt);
    if (status) return status;
    m->d = d;
    m->dt = dt;
    set_step_arrays(m);
    m->message[0] = '\0';
    return FPM_OK;
}

/* ------------------------------------------------------------------------------ loading */

static uint32_t crc32_of(const unsigned char *p, size_t size) {
    uint32_t table[256], crc = 0xFFFFFFFFu;
    for (uint32_t b = 0; b < 256; b++) {
        uint32_t c = b;
        for (int k = 0; k < 8; k++) c = (c & 1u) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
        table[b] = c;
    }
    for (size_t k = 0; k < size; k++) crc = table[(crc ^ p[k]) & 0xFFu] ^ (crc >> 8);
    return crc ^ 0xFFFFFFFFu;
}

static uint32_t u32_at(const unsigned char *p) {
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

static uint64_t u64_at(const unsigned char *p) {
    return (uint64_t)u32_at(p) | (uint64_t)u32_at(p + 4) << 32;
}

static double f64_at(const unsigned char *p) {
    const uint64_t bits = u64_at(p);
    double value;
    memcpy(&value, &bits, sizeof value);
    return value;
}

/* A reader over the arrays after the header, in the layout's order. */
typedef struct {
    const unsigned char *p;
    fpm_model *m;
} reader;

static int read_u32(reader *r, const char *field, size_t count, uint32_t bound, uint32_t *out) {
    for (size_t k = 0; k < count; k++, r->p += 4) {
        out[k] = u32_at(r->p);
        if (out[k] >= bound)
            return fail(r->m, FPM_ERR_VALUE, "%s[%zu]: %u, must be < %u", field, k, out[k],
                        bound);
    }
    return FPM_OK;
}

/* lower: 0 none, 1 >= 0, 2 > 0 */
static int read_f64(reader *r, const char *field, size_t count, int lower, double *out) {
    static const char *const RULE[3] = {"finite", "finite and >= 0", "finite and > 0"};
    for (size_t k = 0; k < count; k++, r->p += 8) {
        const double value = f64_at(r->p);
        if (!isfinite(value) || (lower == 1 && value < 0) || (lower == 2 && value <= 0))
            return fail(r->m, FPM_ERR_VALUE, "%s[%zu]: %g, must be %s", field, k, value,
                        RULE[lower]);
        out[k] = value;
    }
    return FPM_OK;
}

static int read_offsets(reader *r, const char *field, size_t count, uint32_t end, uint32_t *out) {
    for (size_t k = 0; k < count; k++, r->p += 4) {
        out[k] = u32_at(r->p);
        if ((k == 0 && out[k] != 0) || (k > 0 && out[k] < out[k - 1]) ||
            (k + 1 == count && out[k] != end))
            return fail(r->m, FPM_ERR_VALUE,
                        "%s[%zu]: %u, offsets must start at 0, not decrease and end at %u",
                        field, k, out[k], end);
    }
    return FPM_OK;
}

void fpm_free(fpm_model *m) {
    if (!m) return;
    void *owned[] = {m->free_, m->no_forces, m->rest, m->mass,        m->a,           m->denom,
                     m->mg,          m->fixed,       m->si,          m->sj,
                     m->rest_length, m->stiffness,   m->hex,         m->corner,
                     m->kappa,       m->volume0,     m->Xbuf,        m->acc,
                     m->scratch,     m->sblock,      m->hblock,
                     m->case_offset, m->case_node,   m->case_force,  m->share_node,
                     m->share_offset, m->share_index, m->share_weight, m->slot_window,
                     m->slot_offset, m->slot_live, m->slot_k, m->slot_length};
    for (size_t k = 0; k < sizeof owned / sizeof owned[0]; k++) free(owned[k]);
    free(m);
}

static void copy_message(char *error, size_t error_size, const char *message) {
    if (error && error_size) {
        strncpy(error, message, error_size - 1);
        error[error_size - 1] = '\0';
    }
}

/* ------------------------------------------------------------------------- blocks */

typedef struct {
    long part;   /* the part that sums it */
    long key[8]; /* what the lanes of a block share (offsets), then where it runs (key[7]) */
    uint32_t index;
} block_key;

static int compare_keys(const void *a, const void *b) {
    const block_key *p = a, *q = b;
    if (p->part != q->part) return p->part < q->part ? -1 : 1;
    for (int k = 0; k < 8; k++)
        if (p->key[k] != q->key[k]) return p->key[k] < q->key[k] ? -1 : 1;
    return p->index < q->index ? -1 : p->index > q->index;
}

/* An order of count items: first blocks of 2..LANES items of one part that share key[0..6] and
   whose key[7] counts up by one from lane to lane (block b is order[start[b]..start[b + 1]],
   *blocks of them; part p's are blocks parts[p]..parts[p + 1]), then the single items part by
   part (part p's from singles[p] to singles[p + 1]). Returns the order and *start (both to
   free), NULL when out of memory. */
static uint32_t *block_order(block_key *keys, uint32_t count, uint32_t **start,
                             uint32_t *blocks, uint32_t parts[PARTS + 1],
                             uint32_t singles[PARTS + 1]) {
    uint32_t *order = malloc(((size_t)count + 1) * 4);
    unsigned char *taken = calloc((size_t)count + 1, 1);
    *start = malloc(((size_t)count / 2 + 2) * 4);
    if (!order || !taken || !*start) {
        free(order), free(taken), free(*start);
        return NULL;
    }
    qsort(keys, count, sizeof *keys, compare_keys);
    uint32_t filled = 0, b = 0;
    long part = 0;
    parts[0] = 0;
    for (uint32_t r = 0; r < count;) {
        while (part < keys[r].part) parts[++part] = b;
        uint32_t end = r + 1;
        while (end < count && end - r < LANES && keys[end].part == keys[r].part &&
               keys[end].key[7] == keys[end - 1].key[7] + 1 &&
               memcmp(keys[end].key, keys[r].key, 7 * sizeof(long)) == 0)
            end++;
        if (end - r > 1) {
            (*start)[b++] = filled;
            for (uint32_t k = r; k < end; k++) order[filled++] = keys[k].index, taken[keys[k].index] = 1;
        }
        r = end;
    }
    while (part < PARTS) parts[++part] = b;
    (*start)[b] = filled;
    *blocks = b;
    part = 0;
    singles[0] = filled;
    for (uint32_t r = 0; r < count; r++) {
        while (part < keys[r].part) singles[++part] = filled;
        if (!taken[keys[r].index]) order[filled++] = keys[r].index;
    }
    while (part < PARTS) singles[++part] = filled;
    free(taken);
    return order;
}

/* A spring end for the slots: its window, the offset to the other end, its lane. */
typedef struct {
    long part, window, offset;
    uint32_t lane, spring;
} end_key;

static int compare_ends(const void *a, const void *b) {
    const end_key *p = a, *q = b;
    if (p->part != q->part) return p->part < q->part ? -1 : 1;
    if (p->window != q->window) return p->window < q->window ? -1 : 1;
    if (p->offset != q->offset) return p->offset < q->offset ? -1 : 1;
    if (p->lane != q->lane) return p->lane < q->lane ? -1 : 1;
    return p->spring < q->spring ? -1 : p->spring > q->spring;
}

static int same_slot(const end_key *p, const end_key *q) {
    return p->window == q->window && p->offset == q->offset;
}

/* The pulled springs (pulled[e] = 1) and their slots: a spring is pulled when each of its ends
   is in a slot of at least SLOT_LANES lanes of pulled springs (a window of LANES nodes, one
   offset to the other ends, at most one spring a lane); the others are left to the blocks. */
static int make_slots(fpm_model *m, unsigned char *pulled) {
    const uint32_t s = m->s;
    const size_t count = 2 * (size_t)s;
    end_key *ends = malloc((count + 1) * sizeof *ends);
    if (!ends) return FPM_ERR_MEMORY;
    for (uint32_t e = 0; e < s; e++)
        for (int end = 0; end < 2; end++) {
            const long node = end ? m->sj[e] : m->si[e], other = end ? m->si[e] : m->sj[e];
            ends[2 * (size_t)e + end] = (end_key){part_of(m->n, node), node / LANES,
                                                  other - node, (uint32_t)(node % LANES), e};
        }
    qsort(ends, count, sizeof *ends, compare_ends);
    memset(pulled, 1, s);
    for (int changed = 1; changed;) {
        changed = 0;
        for (size_t r = 0; r < count;) {
            size_t end = r;
            unsigned live = 0;
            int lanes = 0;
            for (; end < count && same_slot(ends + end, ends + r); end++) {
                if (!pulled[ends[end].spring]) continue;
                if ((live >> ends[end].lane) & 1u) { /* a second spring in the lane */
                    pulled[ends[end].spring] = 0, changed = 1;
                } else {
                    live |= 1u << ends[end].lane, lanes++;
                }
            }
            if (lanes > 0 && lanes < SLOT_LANES)
                for (size_t k = r; k < end; k++)
                    if (pulled[ends[k].spring]) pulled[ends[k].spring] = 0, changed = 1;
            r = end;
        }
    }
    uint32_t slots = 0; /* those with a pulled spring */
    for (size_t r = 0, end; r < count; r = end) {
        int any = 0;
        for (end = r; end < count && same_slot(ends + end, ends + r); end++)
            any |= pulled[ends[end].spring];
        slots += (uint32_t)any;
    }
    m->slot_window = malloc(((size_t)slots + 1) * 4);
    m->slot_offset = malloc(((size_t)slots + 1) * 4);
    m->slot_live = calloc((size_t)slots + 1, 1);
    m->slot_k = calloc(LANES * ((size_t)slots + 1), sizeof(fpm_real));
    m->slot_length = calloc(LANES * ((size_t)slots + 1), sizeof(fpm_real));
    if (!m->slot_window || !m->slot_offset || !m->slot_live || !m->slot_k || !m->slot_length) {
        free(ends);
        return FPM_ERR_MEMORY;
    }
    uint32_t u = 0;
    long part = 0;
    m->slot_part[0] = 0;
    for (size_t r = 0, end; r < count; r = end) {
        int any = 0;
        for (end = r; end < count && same_slot(ends + end, ends + r); end++)
            any |= pulled[ends[end].spring];
        if (any) {
            while (part < ends[r].part) m->slot_part[++part] = u;
            m->slot_window[u] = (uint32_t)ends[r].window;
            m->slot_offset[u] = (int32_t)ends[r].offset;
            for (size_t k = r; k < end; k++) {
                const uint32_t e = ends[k].spring, l = ends[k].lane;
                if (!pulled[e]) continue;
                m->slot_live[u] |= (unsigned char)(1u << l);
                m->slot_k[LANES * (size_t)u + l] = m->stiffness[e];
                m->slot_length[LANES * (size_t)u + l] = m->rest_length[e];
            }
            u++;
        }
    }
    while (part < PARTS) m->slot_part[++part] = u;
    m->nslots = u;
    free(ends);
    return FPM_OK;
}

/* The springs and hexahedra reordered into blocks (model->sblock, hblock) for the passes. */
static int make_blocks(fpm_model *m) {
    const uint32_t s = m->s, h = m->h;
    unsigned char *pulled = calloc((size_t)s + 1, 1);
    uint32_t *subset = malloc(((size_t)s + 1) * 4);
    block_key *keys = malloc(((size_t)(s > h ? s : h) + 1) * sizeof *keys);
    if (!pulled || !subset || !keys || make_slots(m, pulled)) {
        free(pulled), free(subset), free(keys);
        return FPM_ERR_MEMORY;
    }
    uint32_t scattered = 0;
    for (uint32_t e = 0; e < s; e++)
        if (!pulled[e]) subset[scattered++] = e;
    for (uint32_t k = 0; k < scattered; k++) {
        const uint32_t e = subset[k];
        memset(keys[k].key, 0, sizeof keys[k].key);
        keys[k].key[0] = (long)m->sj[e] - (long)m->si[e];
        keys[k].key[7] = m->si[e];
        keys[k].part = part_of(m->n, m->si[e]);
        keys[k].index = k;
    }
    uint32_t *blocks =
        block_order(keys, scattered, &m->sblock, &m->nsblocks, m->spart, m->ssingle);
    uint32_t *order = malloc(((size_t)s + 1) * 4);
    uint32_t *u32 = malloc(((size_t)(s > 8 * h ? s : 8 * h) + 1) * 4);
    fpm_real *real = malloc(((size_t)(s > h ? s : h) + 1) * sizeof(fpm_real));
    if (!blocks || !order || !u32 || !real) {
        free(pulled), free(subset), free(keys), free(blocks), free(order), free(u32), free(real);
        return FPM_ERR_MEMORY;
    }
    for (uint32_t k = 0; k < scattered; k++) order[k] = subset[blocks[k]];
    for (uint32_t e = 0, k = scattered; e < s; e++) /* then the pulled ones */
        if (pulled[e]) order[k++] = e;
    free(pulled), free(subset), free(blocks);
#define PERMUTE(array, tmp, count)                                                             \
    do {                                                                                       \
        for (uint32_t e = 0; e < (count); e++) tmp[e] = array[order[e]];                       \
        memcpy(array, tmp, (size_t)(count) * sizeof *array);                                   \
    } while (0)
    PERMUTE(m->si, u32, s);
    PERMUTE(m->sj, u32, s);
    PERMUTE(m->rest_length, real, s);
    PERMUTE(m->stiffness, real, s);
    free(order);
    for (uint32_t c = 0; c < h; c++) {
        for (int n = 1; n < 8; n++) keys[c].key[n - 1] = (long)m->hex[8 * c + n] - m->hex[8 * c];
        keys[c].key[7] = m->hex[8 * c];
        keys[c].part = part_of(m->n, m->hex[8 * c]);
        keys[c].index = c;
    }
    order = block_order(keys, h, &m->hblock, &m->nhblocks, m->hpart, m->hsingle);
    free(keys);
    if (!order) {
        free(u32), free(real);
        return FPM_ERR_MEMORY;
    }
    for (uint32_t c = 0; c < h; c++)
        for (int n = 0; n < 8; n++) m->corner[(size_t)n * h + c] = m->hex[8 * (size_t)order[c] + n];
    PERMUTE(m->kappa, real, h);
    PERMUTE(m->volume0, real, h);
#undef PERMUTE
    free(order), free(u32), free(real);
    return FPM_OK;
}

/* Everything after the header's checks: arrays read, validated, rearranged for the step. */
static int build(fpm_model *m, const unsigned char *data, uint32_t nfixed, uint32_t entries,
                 uint32_t share_entries) {
    const uint32_t n = m->n, s = m->s, h = m->h, L = m->ncases, R = m->nshare;
    reader r = {data + FPM_HEADER_BYTES, m};
    int status = FPM_OK;
    double *rest = malloc((3 * (size_t)n + 1) * sizeof(double));
    double *mass = malloc(((size_t)n + 1) * sizeof(double));
    uint32_t *fixed = malloc(((size_t)nfixed + 1) * 4);
    uint32_t *si = m->si = malloc(((size_t)s + 1) * 4), *sj = m->sj = malloc(((size_t)s + 1) * 4);
    double *length = malloc(((size_t)s + 1) * 8), *k = malloc(((size_t)s + 1) * 8);
    double *kappa = malloc(((size_t)h + 1) * 8), *volume0 = malloc(((size_t)h + 1) * 8);
    m->rest = malloc((3 * (size_t)n + 1) * sizeof(fpm_real));
    m->mass = malloc(((size_t)n + 1) * sizeof(fpm_real));
    m->a = malloc(((size_t)n + 1) * sizeof(fpm_real));
    m->denom = malloc(((size_t)n + 1) * sizeof(fpm_real));
    m->mg = malloc((3 * (size_t)n + 1) * sizeof(fpm_real));
    m->fixed = calloc((size_t)n + 1, 1);
    m->free_ = malloc(((size_t)n + 1) * sizeof(fpm_real));
    m->no_forces = calloc(3 * (size_t)n + 1, sizeof(fpm_real));
    m->rest_length = malloc(((size_t)s + LANES) * sizeof(fpm_real)); /* lanes past the end */
    m->stiffness = malloc(((size_t)s + LANES) * sizeof(fpm_real));
    m->Xbuf = calloc(3 * ((size_t)n + 2 * LANES), sizeof(fpm_real));
    m->X = m->Xbuf ? m->Xbuf + LANES : NULL;
    m->acc = calloc(3 * PARTS * ((size_t)n + 2 * LANES), sizeof(fpm_real)); /* zero: passes add */
    m->scratch = malloc(PARTS * SCRATCH * sizeof(fpm_real));
    m->hex = malloc((8 * (size_t)h + 1) * 4);
    m->corner = malloc((8 * (size_t)h + 1) * 4);
    m->kappa = malloc(((size_t)h + LANES) * sizeof(fpm_real));
    m->volume0 = malloc(((size_t)h + LANES) * sizeof(fpm_real));
    m->case_offset = malloc(((size_t)L + 1) * 4);
    m->case_node = malloc(((size_t)entries + 1) * 4);
    m->case_force = malloc((3 * (size_t)entries + 1) * 8);
    m->share_node = malloc(((size_t)R + 1) * 4);
    m->share_offset = malloc(((size_t)R + 1) * 4);
    m->share_index = malloc(((size_t)share_entries + 1) * 4);
    m->share_weight = malloc(((size_t)share_entries + 1) * 8);
    if (!rest || !mass || !fixed || !si || !sj || !length || !k || !kappa || !volume0 ||
        !m->rest || !m->mass || !m->a || !m->denom || !m->mg || !m->fixed || !m->free_ ||
        !m->no_forces || !m->scratch ||
        !m->X || !m->acc || !m->rest_length ||
        !m->stiffness || !m->hex || !m->corner || !m->kappa || !m->volume0 ||
        !m->case_offset || !m->case_node ||
        !m->case_force || !m->share_node || !m->share_offset || !m->share_index ||
        !m->share_weight) {
        status = fail(m, FPM_ERR_MEMORY, "out of memory for %u nodes, %u springs", n, s);
        goto done;
    }
    if ((status = read_f64(&r, "nodes", 3 * (size_t)n, 0, rest)) ||
        (status = read_f64(&r, "masses", n, 2, mass)) ||
        (status = read_u32(&r, "fixed", nfixed, n, fixed)) ||
        (status = read_u32(&r, "spring_i", s, n, si)) ||
        (status = read_u32(&r, "spring_j", s, n, sj)) ||
        (status = read_f64(&r, "rest_lengths", s, 2, length)) ||
        (status = read_f64(&r, "stiffness", s, 1, k)) ||
        (status = read_u32(&r, "hexahedra", 8 * (size_t)h, n, m->hex)) ||
        (status = read_f64(&r, "volume_stiffness", h, 1, kappa)) ||
        (status = read_f64(&r, "rest_volumes", h, 2, volume0)) ||
        (status = read_offsets(&r, "case_offsets", (size_t)L + 1, entries, m->case_offset)) ||
        (status = read_u32(&r, "case_nodes", entries, n, m->case_node)) ||
        (status = read_f64(&r, "case_forces", 3 * (size_t)entries, 0, m->case_force)) ||
        (status = read_u32(&r, "share_nodes", R, n, m->share_node)) ||
        (status = read_offsets(&r, "share_offsets", (size_t)R + 1, share_entries,
                               m->share_offset)) ||
        (status = read_u32(&r, "share_indices", share_entries, n, m->share_index)) ||
        (status = read_f64(&r, "share_weights", share_entries, 0, m->share_weight)))
        goto done;
    for (uint32_t e = 0; e < s; e++)
        if (si[e] == sj[e]) {
            status = fail(m, FPM_ERR_VALUE, "spring_i[%u] = spring_j[%u] = %u: a spring needs two "
                          "nodes", e, e, si[e]);
            goto done;
        }
    for (uint32_t i = 0; i < nfixed; i++) m->fixed[fixed[i]] = 1;
    for (uint32_t i = 0; i < n; i++) m->free_[i] = m->fixed[i] ? 0 : 1;
    m->mass_min = INFINITY;
    for (uint32_t i = 0; i < n; i++) {
        m->mass[i] = (fpm_real)mass[i];
        for (int d = 0; d < 3; d++) {
            m->rest[3 * i + d] = (fpm_real)rest[3 * i + d];
            m->mg[3 * i + d] = (fpm_real)(mass[i] * m->gravity[d]);
        }
        if (!m->fixed[i] && mass[i] < m->mass_min) m->mass_min = mass[i];
    }
    for (uint32_t e = 0; e < s + LANES; e++) {
        m->rest_length[e] = e < s ? (fpm_real)length[e] : 1;
        m->stiffness[e] = e < s ? (fpm_real)k[e] : 0;
    }
    for (uint32_t c = 0; c < h + LANES; c++) {
        m->kappa[c] = c < h ? (fpm_real)kappa[c] : 0;
        m->volume0[c] = c < h ? (fpm_real)volume0[c] : 1;
    }
    m->stable_dt = gershgorin_dt(m, si, sj, k);
    if (m->stable_dt < 0 || make_blocks(m)) {
        status = fail(m, FPM_ERR_MEMORY, "out of memory for %u nodes", n);
        goto done;
    }
    m->omega2 = top_eigenvalue(m);
    if (m->omega2 < 0) {
        status = fail(m, FPM_ERR_MEMORY, "out of memory for %u nodes", n);
        goto done;
    }
    if ((status = check_parameters(m, m->d, m->dt))) goto done;
    set_step_arrays(m);
done:
    free(rest), free(mass), free(fixed), free(length), free(k);
    free(kappa), free(volume0);
    return status;
}

int fpm_load(const void *data, size_t size, fpm_model **model, char *error, size_t error_size) {
    if (!model) return FPM_ERR_ARGUMENT;
    *model = NULL;
    fpm_model *m = calloc(1, sizeof *m);
    if (!m) {
        copy_message(error, error_size, "out of memory");
        return FPM_ERR_MEMORY;
    }
    const unsigned char *p = data;
    int status = FPM_OK;
    if (!p) {
        status = fail(m, FPM_ERR_ARGUMENT, "no data");
    } else if (size < FPM_HEADER_BYTES) {
        status = fail(m, FPM_ERR_TRUNCATED, "truncated: %zu bytes, the header alone is %u", size,
                      FPM_HEADER_BYTES);
    } else if (memcmp(p, FPM_MAGIC, 4) != 0) {
        status = fail(m, FPM_ERR_FORMAT, "magic: not an FPM binary export (it must start with %s)",
                      FPM_MAGIC);
    } else if (u32_at(p + 4) != FPM_VERSION) {
        status = fail(m, FPM_ERR_FORMAT, "version: %u, this reader knows version %u",
                      u32_at(p + 4), FPM_VERSION);
    } else {
        m->n = u32_at(p + 8);
        m->s = u32_at(p + 12);
        m->h = u32_at(p + 16);
        const uint32_t nfixed = u32_at(p + 20);
        m->ncases = u32_at(p + 24);
        const uint32_t entries = u32_at(p + 28);
        m->nshare = u32_at(p + 32);
        const uint32_t share_entries = u32_at(p + 36);
        m->d = f64_at(p + 40);
        m->dt = f64_at(p + 48);
        m->settle_tolerance = f64_at(p + 56);
        m->settle_stiffness = f64_at(p + 64);
        for (int d = 0; d < 3; d++) m->gravity[d] = f64_at(p + 72 + 8 * d);
        const uint64_t total = u64_at(p + 96);
        const uint64_t expected =
            (uint64_t)FPM_HEADER_BYTES + 32ull * m->n + 4ull * nfixed + 24ull * m->s +
            48ull * m->h + 4ull * (m->ncases + 1ull) + 28ull * entries + 4ull * m->nshare +
            4ull * (m->nshare + 1ull) + 12ull * share_entries + 4ull;
        const char *names[] = {"settle_tolerance", "settle_stiffness", "gravity[0]",
                               "gravity[1]", "gravity[2]"};
        const double values[] = {m->settle_tolerance, m->settle_stiffness, m->gravity[0],
                                 m->gravity[1], m->gravity[2]};
        if (total != expected) {
            status = fail(m, FPM_ERR_FORMAT,
                          "total_bytes: %llu, the counts in the header make %llu",
                          (unsigned long long)total, (unsigned long long)expected);
        } else if (size < total) {
            status = fail(m, FPM_ERR_TRUNCATED, "truncated: %zu bytes of %llu", size,
                          (unsigned long long)total);
        } else if (size > total) {
            status = fail(m, FPM_ERR_FORMAT, "%zu bytes, the header says %llu", size,
                          (unsigned long long)total);
        } else if (u32_at(p + total - 4) != crc32_of(p, (size_t)total - 4)) {
            status = fail(m, FPM_ERR_CHECKSUM, "crc32: the bytes do not match their checksum "
                          "(the file is corrupt)");
        } else if (m->n == 0) {
            status = fail(m, FPM_ERR_VALUE, "n_nodes: 0, a lattice needs nodes");
        } else {
            for (int v = 0; v < 5 && !status; v++)
                if (!isfinite(values[v]) || (v < 2 && values[v] < 0))
                    status = fail(m, FPM_ERR_VALUE, "%s: %g, must be finite%s", names[v],
                                  values[v], v < 2 ? " and >= 0" : "");
            if (!status) status = build(m, p, nfixed, entries, share_entries);
        }
    }
    if (status) {
        copy_message(error, error_size, m->message);
        fpm_free(m);
        return status;
    }
    m->message[0] = '\0';
    *model = m;
    return FPM_OK;
}

int fpm_load_file(const char *path, fpm_model **model, char *error, size_t error_size) {
    if (!model || !path) return FPM_ERR_ARGUMENT;
    *model = NULL;
    FILE *file = fopen(path, "rb");
    char message[MESSAGE_BYTES];
    if (!file) {
        snprintf(message, sizeof message, "%s: cannot open", path);
        copy_message(error, error_size, message);
        return FPM_ERR_IO;
    }
    unsigned char *data = NULL;
    size_t size = 0, capacity = 0, got;
    do {
        if (size == capacity) {
            capacity = capacity ? 2 * capacity : 1 << 16;
            unsigned char *grown = realloc(data, capacity);
            if (!grown) {
                free(data);
                fclose(file);
                copy_message(error, error_size, "out of memory");
                return FPM_ERR_MEMORY;
            }
            data = grown;
        }
        got = fread(data + size, 1, capacity - size, file);
        size += got;
    } while (got > 0);
    const int bad = ferror(file);
    fclose(file);
    if (bad) {
        free(data);
        snprintf(message, sizeof message, "%s: read error", path);
        copy_message(error, error_size, message);
        return FPM_ERR_IO;
    }
    const int status = fpm_load(data, size, model, error, error_size);
    free(data);
    return status;
}
