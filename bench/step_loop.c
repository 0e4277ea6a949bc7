/* The native step timed from C, as an engine embedding fpm_step.c calls it (no Python between
   steps): seconds per step of `steps` steps of the binary export in `data` from rest, under
   `npush` force fields (3 N each) taken in turn, so that the forces change every step.
   threads: 0 for the step's default. Returns -1 when the export does not load. Built with the
   step's compiler and flags, with fpm_step.c (bench/bench_native.py). */
#define _POSIX_C_SOURCE 199309L
#include "fpm_step.h"

#include <stdlib.h>
#include <time.h>

static double seconds(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

double step_seconds(const void *data, size_t size, const fpm_real *pushes, long npush,
                    long steps, int threads) {
    fpm_model *m;
    char error[320];
    if (fpm_load(data, size, &m, error, sizeof error) != FPM_OK) return -1.0;
    if (threads > 0) fpm_set_threads(m, threads);
    const size_t n3 = 3 * (size_t)fpm_node_count(m);
    fpm_real *x = malloc(n3 * sizeof *x), *x_next = malloc(n3 * sizeof *x);
    fpm_real *v = calloc(n3, sizeof *v);
    double elapsed = -1.0;
    if (x && x_next && v) {
        fpm_stats stats;
        fpm_rest_positions(m, x);
        double t0 = 0.0;
        for (long k = -20; k < steps; k++) { /* 20 steps to warm up */
            if (k == 0) t0 = seconds();
            fpm_step(m, x, x_next, v, pushes + n3 * (size_t)((k + 20) % npush), &stats);
            fpm_real *swap = x;
            x = x_next, x_next = swap;
        }
        elapsed = (seconds() - t0) / (double)steps;
    }
    free(x), free(x_next), free(v);
    fpm_free(m);
    return elapsed;
}
