/* An engine's loop around the native step: load a binary export, push its first load case on
   and off, step at the export's dt until the model settles.

   Build and run (from the repository root):

       fpmcal calibrate examples/paper-material-a.json --json > result.json
       fpmcal export examples/paper-material-a.json result.json --format binary -o cube.fpmb
       cc -O3 -march=native -fopenmp -Ifpm/native examples/native_step.c fpm/native/fpm_step.c \
          -o native_step -lm
       ./native_step cube.fpmb

   It prints the steps the load case took to settle, the largest displacement, and the steps
   back to rest after the load is released. Exit status 1 with the loader's or the step's message
   (naming the field) when the file or a step is refused. */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>

#include "fpm_step.h"

/* Step under forces (NULL: none) until settled or max_steps; the steps taken, -1 on an error. */
static long settle(fpm_model *model, fpm_real **x, fpm_real **x_next, fpm_real *v,
                   const fpm_real *forces, long max_steps) {
    fpm_stats stats;
    for (long n = 1; n <= max_steps; n++) {
        if (fpm_step(model, *x, *x_next, v, forces, &stats) != FPM_OK) return -1;
        fpm_real *swap = *x; /* the new positions are the next step's input */
        *x = *x_next;
        *x_next = swap;
        if (stats.settled) return n;
    }
    return max_steps;
}

int main(int argc, char **argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: %s EXPORT.fpmb\n", argv[0]);
        return 2;
    }
    char error[512];
    fpm_model *model = NULL;
    if (fpm_load_file(argv[1], &model, error, sizeof error) != FPM_OK) {
        fprintf(stderr, "%s: %s\n", argv[1], error);
        return 1;
    }
    const size_t n = fpm_node_count(model);
    fpm_real *rest = malloc(3 * n * sizeof *rest), *x = malloc(3 * n * sizeof *x);
    fpm_real *x_next = malloc(3 * n * sizeof *x_next), *v = calloc(3 * n, sizeof *v);
    fpm_real *forces = malloc(3 * n * sizeof *forces);
    int status = 1;
    if (!rest || !x || !x_next || !v || !forces || fpm_case_count(model) == 0) {
        fprintf(stderr, "%s\n", fpm_case_count(model) ? "out of memory" : "no load case");
        goto done;
    }
    fpm_rest_positions(model, rest);
    fpm_rest_positions(model, x);
    fpm_case_forces(model, 0, forces);
    printf("%zu nodes, %u springs, %u hexahedra, dt %g s (stable below %g s), d %g N s/m\n", n,
           fpm_spring_count(model), fpm_hexahedron_count(model), fpm_dt(model),
           fpm_stable_dt(model), fpm_damping(model));
    const long loaded = settle(model, &x, &x_next, v, forces, 1000000);
    if (loaded < 0) goto failed;
    double largest = 0.0;
    for (size_t k = 0; k < 3 * n; k++) largest = fmax(largest, fabs((double)(x[k] - rest[k])));
    const long released = settle(model, &x, &x_next, v, NULL, 1000000);
    if (released < 0) goto failed;
    printf("load case 1: settled in %ld steps, largest displacement %.6g m; at rest again in "
           "%ld steps\n", loaded, largest, released);
    status = 0;
    goto done;
failed:
    fprintf(stderr, "step: %s\n", fpm_error(model));
done:
    free(rest), free(x), free(x_next), free(v), free(forces);
    fpm_free(model);
    return status;
}
