/* fpm_step.c: see fpm_step.h. C99; OpenMP when compiled with it, one thread without.

   Layout in memory, for the machine: the springs are kept twice, once per end, as per-node
   rows (neighbour, rest length, stiffness: structure of arrays, read in order), so each node
   sums its own spring forces with no scatter and the nodes share out between threads without
   locks; each spring's force is computed at both ends, from r = x_other - x_node (exactly minus
   the other end's), so the sum at a node is the NumPy recipe's term for term, in the same
   (spring index) order. The volume term is a pass over the hexahedra (corner forces into a
   buffer) followed by a per-node sum over the node's corners, in corner-slot order. */
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

#define MESSAGE_BYTES 320
#define POWER_ITERATIONS 40

struct fpm_model {
    uint32_t n, s, h, ncases, nshare;
    double d, dt, settle_tolerance, settle_stiffness, gravity[3];
    double stable_dt; /* Gershgorin's bound, s */
    double omega2;    /* a lower bound of the largest eigenvalue of M^-1 K at rest, 1/s^2 */
    double mass_min;  /* the lightest free node, kg */
    fpm_real *rest, *mass, *a, *denom, *mg; /* a = dt / m, denom = 1 + a d, mg = m g (3 N) */
    unsigned char *fixed;
    uint32_t *row, *nbr; /* the springs by node: row[n]..row[n + 1] in nbr, rest, stiff */
    fpm_real *rest_length, *stiffness;
    uint32_t *hex;           /* 8 H corners */
    fpm_real *kappa, *volume0; /* H */
    uint32_t *corner_row, *corner_slot; /* the corners by node: slots 8 h + c of fc */
    fpm_real *fc;            /* 3 * 8 H corner forces of the last hexahedron pass */
    uint32_t *case_offset, *case_node;
    double *case_force;
    uint32_t *share_node, *share_offset, *share_index;
    double *share_weight;
    int threads;
    double load_scale, moved_scale;
    char message[MESSAGE_BYTES];
};

/* ---------------------------------------------------------------- the volume of a hexahedron */

/* a_k = 1/8 sum_n C_kn x_n, the coefficients of r, s, t, rs, rt, st of the trilinear map, for
   the corners in NATURAL order: (---), (+--), (++-), (-+-), (--+), (+-+), (+++), (-++). */
static inline void coefficients(const fpm_real p[8][3], fpm_real a[6][3]) {
    for (int d = 0; d < 3; d++) {
        const fpm_real s01 = p[1][d] - p[0][d], s32 = p[2][d] - p[3][d];
        const fpm_real s45 = p[5][d] - p[4][d], s76 = p[6][d] - p[7][d];
        const fpm_real q01 = p[0][d] + p[1][d], q23 = p[2][d] + p[3][d];
        const fpm_real q45 = p[4][d] + p[5][d], q67 = p[6][d] + p[7][d];
        a[0][d] = ((s01 + s32) + (s45 + s76)) / 8;
        a[1][d] = ((q23 - q01) + (q67 - q45)) / 8;
        a[2][d] = ((q45 + q67) - (q01 + q23)) / 8;
        a[3][d] = ((s32 - s01) + (s76 - s45)) / 8;
        a[4][d] = ((s45 + s76) - (s01 + s32)) / 8;
        a[5][d] = ((q01 - q23) + (q67 - q45)) / 8;
    }
}

/* g_n = 1/8 sum_k C_kn ga_k: the gradient with respect to the corners of a function of a. */
static inline void corner_gradient(const fpm_real ga[6][3], fpm_real g[8][3]) {
    for (int d = 0; d < 3; d++) {
        const fpm_real A = ga[0][d], B = ga[1][d], C = ga[2][d];
        const fpm_real D = ga[3][d], E = ga[4][d], F = ga[5][d];
        const fpm_real ab = A + B, a_b = A - B, de = D + E, d_e = D - E;
        const fpm_real fc = F - C, f_c = F + C;
        g[0][d] = (de - ab + fc) / 8;
        g[1][d] = (a_b - de + fc) / 8;
        g[2][d] = (ab + d_e - f_c) / 8;
        g[3][d] = (-a_b - d_e - f_c) / 8;
        g[4][d] = (d_e - ab - fc) / 8;
        g[5][d] = (a_b - d_e + C - F) / 8;
        g[6][d] = (ab + de + f_c) / 8;
        g[7][d] = (-a_b - de + f_c) / 8;
    }
}

static inline void cross(const fpm_real *a, const fpm_real *b, fpm_real *out) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* V = sum w [a_p, a_q, a_r] over these (p, q, r), w = 8, 8/3, 8/3, 8/3. */
static const int TRIPLE[4][3] = {{0, 1, 2}, {0, 3, 4}, {3, 1, 5}, {4, 5, 2}};

/* The volume of the trilinear hexahedron with corners p (8 x 3) and its gradient g (8 x 3). */
static inline fpm_real hex_volume(fpm_real p[8][3], fpm_real g[8][3]) {
    fpm_real a[6][3], ga[6][3] = {{0}}, qr[3], rp[3], pq[3], volume = 0;
    coefficients((const fpm_real(*)[3])p, a);
    for (int t = 0; t < 4; t++) {
        const int P = TRIPLE[t][0], Q = TRIPLE[t][1], R = TRIPLE[t][2];
        const fpm_real w = t == 0 ? (fpm_real)8.0 : (fpm_real)(8.0 / 3.0);
        cross(a[Q], a[R], qr);
        cross(a[R], a[P], rp);
        cross(a[P], a[Q], pq);
        volume += w * (a[P][0] * qr[0] + a[P][1] * qr[1] + a[P][2] * qr[2]);
        for (int d = 0; d < 3; d++) {
            ga[P][d] += w * qr[d];
            ga[Q][d] += w * rp[d];
            ga[R][d] += w * pq[d];
        }
    }
    corner_gradient((const fpm_real(*)[3])ga, g);
    return volume;
}

/* Corner forces of hexahedron c at positions x into model->fc. */
static inline void hex_forces(fpm_model *m, const fpm_real *x, long c) {
    fpm_real p[8][3], g[8][3];
    const uint32_t *corner = m->hex + 8 * c;
    for (int n = 0; n < 8; n++)
        for (int d = 0; d < 3; d++) p[n][d] = x[3 * (size_t)corner[n] + d];
    const fpm_real volume = hex_volume(p, g);
    const fpm_real pressure = m->kappa[c] * (volume - m->volume0[c]) / m->volume0[c];
    fpm_real *out = m->fc + 24 * c;
    for (int n = 0; n < 8; n++)
        for (int d = 0; d < 3; d++) out[3 * n + d] = -pressure * g[n][d];
}

/* The internal force at node i (springs, then the corner forces of the last hexahedron pass). */
static inline void node_force(const fpm_model *m, const fpm_real *x, long i, fpm_real f[3]) {
    const fpm_real xi = x[3 * i], yi = x[3 * i + 1], zi = x[3 * i + 2];
    fpm_real sx = 0, sy = 0, sz = 0;
#pragma omp simd reduction(+ : sx, sy, sz)
    for (uint32_t e = m->row[i]; e < m->row[i + 1]; e++) {
        const size_t j = 3 * (size_t)m->nbr[e];
        const fpm_real rx = x[j] - xi, ry = x[j + 1] - yi, rz = x[j + 2] - zi;
        const fpm_real length = SQRT(rx * rx + ry * ry + rz * rz);
        const fpm_real c = m->stiffness[e] * (length - m->rest_length[e]) / length;
        sx += c * rx;
        sy += c * ry;
        sz += c * rz;
    }
    if (m->h) {
        fpm_real cx = 0, cy = 0, cz = 0;
        for (uint32_t e = m->corner_row[i]; e < m->corner_row[i + 1]; e++) {
            const fpm_real *fc = m->fc + 3 * (size_t)m->corner_slot[e];
            cx += fc[0];
            cy += fc[1];
            cz += fc[2];
        }
        sx += cx;
        sy += cy;
        sz += cz;
    }
    f[0] = sx;
    f[1] = sy;
    f[2] = sz;
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
    const long n = m->n, h = m->h;
    const int threads = thread_count(m);
    (void)threads;
#pragma omp parallel num_threads(threads) if (threads > 1)
    {
#pragma omp for schedule(static)
        for (long c = 0; c < h; c++) hex_forces(m, x, c);
#pragma omp for schedule(static)
        for (long i = 0; i < n; i++) node_force(m, x, i, out + 3 * i);
    }
    m->message[0] = '\0';
    return FPM_OK;
}

int fpm_step(fpm_model *m, const fpm_real *x, fpm_real *x_next, fpm_real *v,
             const fpm_real *forces, fpm_stats *stats) {
    if (!m || !x || !x_next || !v) return FPM_ERR_ARGUMENT;
    const long n = m->n, h = m->h;
    if (forces)
        for (long k = 0; k < 3 * n; k++)
            if (!isfinite(forces[k]))
                return fail(m, FPM_ERR_FORCES, "forces[%ld].%c: not finite (%g)", k / 3,
                            "xyz"[k % 3], (double)forces[k]);
    const fpm_real dt = (fpm_real)m->dt;
    double unbalanced = 0.0, load = 0.0, sum2 = 0.0, moved2 = 0.0;
    const int threads = thread_count(m);
    (void)threads;
#pragma omp parallel num_threads(threads) if (threads > 1)
    {
#pragma omp for schedule(static)
        for (long c = 0; c < h; c++) hex_forces(m, x, c);
#pragma omp for schedule(static) reduction(max : unbalanced, load) reduction(+ : sum2, moved2)
        for (long i = 0; i < n; i++) {
            fpm_real f[3], applied[3], total[3];
            node_force(m, x, i, f);
            for (int d = 0; d < 3; d++) {
                applied[d] = m->mg[3 * i + d];
                if (forces) applied[d] = applied[d] + forces[3 * i + d];
                total[d] = applied[d] + f[d];
                const fpm_real u = x[3 * i + d] - m->rest[3 * i + d];
                moved2 += (double)(u * u);
            }
            if (m->fixed[i]) {
                for (int d = 0; d < 3; d++) {
                    v[3 * i + d] = 0;
                    x_next[3 * i + d] = x[3 * i + d];
                }
                continue;
            }
            const double mag2 = (double)(total[0] * total[0] + total[1] * total[1] +
                                         total[2] * total[2]);
            const double magnitude = sqrt(mag2);
            sum2 += mag2;
            if (magnitude > unbalanced) unbalanced = magnitude;
            const double pull = sqrt((double)(applied[0] * applied[0] + applied[1] * applied[1] +
                                              applied[2] * applied[2]));
            if (pull > load) load = pull;
            const fpm_real a = m->a[i], denom = m->denom[i];
            for (int d = 0; d < 3; d++) {
                const fpm_real vn = (v[3 * i + d] + a * total[d]) / denom;
                v[3 * i + d] = vn;
                x_next[3 * i + d] = x[3 * i + d] + dt * vn;
            }
        }
    }
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
        fpm_real p[8][3], g[8][3];
        double norm[8], sum = 0.0;
        for (int a = 0; a < 8; a++)
            for (int d = 0; d < 3; d++) p[a][d] = m->rest[3 * (size_t)m->hex[8 * c + a] + d];
        hex_volume(p, g);
        for (int a = 0; a < 8; a++) {
            norm[a] = sqrt((double)(g[a][0] * g[a][0] + g[a][1] * g[a][1] + g[a][2] * g[a][2]));
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
    for (uint32_t e = 0; e < m->row[m->n]; e++) scale += (double)m->rest_length[e];
    const double relative = sizeof(fpm_real) == 4 ? 1e-3 : 1e-6; /* above the rounding of x */
    scale = m->row[m->n] ? relative * scale / m->row[m->n] : relative;
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
    void *owned[] = {m->rest,        m->mass,        m->a,           m->denom,
                     m->mg,          m->fixed,       m->row,         m->nbr,
                     m->rest_length, m->stiffness,   m->hex,         m->kappa,
                     m->volume0,     m->corner_row,  m->corner_slot, m->fc,
                     m->case_offset, m->case_node,   m->case_force,  m->share_node,
                     m->share_offset, m->share_index, m->share_weight};
    for (size_t k = 0; k < sizeof owned / sizeof owned[0]; k++) free(owned[k]);
    free(m);
}

static void copy_message(char *error, size_t error_size, const char *message) {
    if (error && error_size) {
        strncpy(error, message, error_size - 1);
        error[error_size - 1] = '\0';
    }
}

/* Everything after the header's checks: arrays read, validated, rearranged for the step. */
static int build(fpm_model *m, const unsigned char *data, uint32_t nfixed, uint32_t entries,
                 uint32_t share_entries) {
    const uint32_t n = m->n, s = m->s, h = m->h, L = m->ncases, R = m->nshare;
    reader r = {data + FPM_HEADER_BYTES, m};
    int status = FPM_OK;
    double *rest = malloc((3 * (size_t)n + 1) * sizeof(double));
    double *mass = malloc(((size_t)n + 1) * sizeof(double));
    uint32_t *fixed = malloc(((size_t)nfixed + 1) * 4), *si = malloc(((size_t)s + 1) * 4);
    uint32_t *sj = malloc(((size_t)s + 1) * 4);
    double *length = malloc(((size_t)s + 1) * 8), *k = malloc(((size_t)s + 1) * 8);
    double *kappa = malloc(((size_t)h + 1) * 8), *volume0 = malloc(((size_t)h + 1) * 8);
    m->rest = malloc((3 * (size_t)n + 1) * sizeof(fpm_real));
    m->mass = malloc(((size_t)n + 1) * sizeof(fpm_real));
    m->a = malloc(((size_t)n + 1) * sizeof(fpm_real));
    m->denom = malloc(((size_t)n + 1) * sizeof(fpm_real));
    m->mg = malloc((3 * (size_t)n + 1) * sizeof(fpm_real));
    m->fixed = calloc((size_t)n + 1, 1);
    m->row = calloc((size_t)n + 1, 4);
    m->nbr = malloc((2 * (size_t)s + 1) * 4);
    m->rest_length = malloc((2 * (size_t)s + 1) * sizeof(fpm_real));
    m->stiffness = malloc((2 * (size_t)s + 1) * sizeof(fpm_real));
    m->hex = malloc((8 * (size_t)h + 1) * 4);
    m->kappa = malloc(((size_t)h + 1) * sizeof(fpm_real));
    m->volume0 = malloc(((size_t)h + 1) * sizeof(fpm_real));
    m->corner_row = calloc((size_t)n + 1, 4);
    m->corner_slot = malloc((8 * (size_t)h + 1) * 4);
    m->fc = malloc((24 * (size_t)h + 1) * sizeof(fpm_real));
    m->case_offset = malloc(((size_t)L + 1) * 4);
    m->case_node = malloc(((size_t)entries + 1) * 4);
    m->case_force = malloc((3 * (size_t)entries + 1) * 8);
    m->share_node = malloc(((size_t)R + 1) * 4);
    m->share_offset = malloc(((size_t)R + 1) * 4);
    m->share_index = malloc(((size_t)share_entries + 1) * 4);
    m->share_weight = malloc(((size_t)share_entries + 1) * 8);
    if (!rest || !mass || !fixed || !si || !sj || !length || !k || !kappa || !volume0 ||
        !m->rest || !m->mass || !m->a || !m->denom || !m->mg || !m->fixed || !m->row ||
        !m->nbr || !m->rest_length || !m->stiffness || !m->hex || !m->kappa || !m->volume0 ||
        !m->corner_row || !m->corner_slot || !m->fc || !m->case_offset || !m->case_node ||
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
    m->mass_min = INFINITY;
    for (uint32_t i = 0; i < n; i++) {
        m->mass[i] = (fpm_real)mass[i];
        for (int d = 0; d < 3; d++) {
            m->rest[3 * i + d] = (fpm_real)rest[3 * i + d];
            m->mg[3 * i + d] = (fpm_real)(mass[i] * m->gravity[d]);
        }
        if (!m->fixed[i] && mass[i] < m->mass_min) m->mass_min = mass[i];
    }
    /* the springs by node, each row in spring index order */
    for (uint32_t e = 0; e < s; e++) m->row[si[e] + 1]++, m->row[sj[e] + 1]++;
    for (uint32_t i = 0; i < n; i++) m->row[i + 1] += m->row[i];
    {
        uint32_t *fill = malloc(((size_t)n + 1) * 4);
        if (!fill) {
            status = fail(m, FPM_ERR_MEMORY, "out of memory for %u nodes", n);
            goto done;
        }
        memcpy(fill, m->row, (size_t)n * 4);
        for (uint32_t e = 0; e < s; e++) {
            const uint32_t ends[2][2] = {{si[e], sj[e]}, {sj[e], si[e]}};
            for (int t = 0; t < 2; t++) {
                const uint32_t slot = fill[ends[t][0]]++;
                m->nbr[slot] = ends[t][1];
                m->rest_length[slot] = (fpm_real)length[e];
                m->stiffness[slot] = (fpm_real)k[e];
            }
        }
        /* the corners by node, in slot order */
        for (size_t q = 0; q < 8 * (size_t)h; q++) m->corner_row[m->hex[q] + 1]++;
        for (uint32_t i = 0; i < n; i++) m->corner_row[i + 1] += m->corner_row[i];
        memcpy(fill, m->corner_row, (size_t)n * 4);
        for (size_t q = 0; q < 8 * (size_t)h; q++) m->corner_slot[fill[m->hex[q]]++] = (uint32_t)q;
        free(fill);
    }
    for (uint32_t c = 0; c < h; c++) {
        m->kappa[c] = (fpm_real)kappa[c];
        m->volume0[c] = (fpm_real)volume0[c];
    }
    m->stable_dt = gershgorin_dt(m, si, sj, k);
    m->omega2 = top_eigenvalue(m);
    if (m->stable_dt < 0 || m->omega2 < 0) {
        status = fail(m, FPM_ERR_MEMORY, "out of memory for %u nodes", n);
        goto done;
    }
    if ((status = check_parameters(m, m->d, m->dt))) goto done;
    set_step_arrays(m);
done:
    free(rest), free(mass), free(fixed), free(si), free(sj), free(length), free(k);
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
