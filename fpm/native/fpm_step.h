/* fpm_step.h: the fitted FPM lattice stepped in time, every node at once (C99, no dependencies).

   The step of fpm.runtime (the JSON export's recipe), on the binary export (fpmcal export
   --format binary; the layout is in docs/reference/native-step.md and fpm/io/export_binary.py):

       F = F_ext + m g + F_springs(x) + F_volume(x)              per node, N
       v <- (v + dt F / m) / (1 + dt d / m)                        damping taken implicitly
       x <- x + dt v                                               fixed nodes never move

   Build: cc -O3 -march=native -fno-math-errno -fno-trapping-math -fopenmp -c fpm_step.c
   (without -fopenmp: one thread; with -DFPM_FLOAT32 the state and the model are float, the file stays float64).

   State arrays (positions x, velocities v, forces) hold 3 values per node, x y z, in node order:
   a vertex buffer as engines keep it. Every function returns FPM_OK (0) or an error code, and
   never aborts: the message (fpm_error, or the load's error buffer) names the field. */
#ifndef FPM_STEP_H
#define FPM_STEP_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#ifdef FPM_FLOAT32
typedef float fpm_real;
#else
typedef double fpm_real;
#endif

#define FPM_MAGIC "FPMB"
#define FPM_VERSION 1u
#define FPM_HEADER_BYTES 104u
#define FPM_THREAD_NODES 1024u

enum fpm_status {
    FPM_OK = 0,
    FPM_ERR_ARGUMENT = 1,  /* a NULL pointer, a case out of range */
    FPM_ERR_TRUNCATED = 2, /* fewer bytes than the header or its counts say */
    FPM_ERR_FORMAT = 3,    /* not this layout: magic, version, sizes */
    FPM_ERR_CHECKSUM = 4,  /* the CRC-32 of the file does not match: corrupt */
    FPM_ERR_VALUE = 5,     /* a value out of its range (index, mass, stiffness, non-finite) */
    FPM_ERR_UNSTABLE = 6,  /* dt above the lattice's stability limit */
    FPM_ERR_MEMORY = 7,
    FPM_ERR_FORCES = 8,    /* a non-finite applied force (the state is left as it was) */
    FPM_ERR_DIVERGED = 9,  /* the state became non-finite */
    FPM_ERR_IO = 10        /* the file could not be read */
};

typedef struct fpm_model fpm_model;

/* What a step saw at its start (fpm.runtime.Runtime's attributes of the same names). */
typedef struct fpm_stats {
    double unbalanced; /* the largest |F_i| over the free nodes, N */
    double load;       /* the largest applied nodal force (m g included) over the free nodes, N */
    int settled;       /* 1 when the settle criteria of the export held */
} fpm_stats;

/* The model of a binary export held in memory (the bytes are copied; free with fpm_free).
   On failure *model is NULL and error (if not NULL) holds a message of at most error_size. */
int fpm_load(const void *data, size_t size, fpm_model **model, char *error, size_t error_size);
int fpm_load_file(const char *path, fpm_model **model, char *error, size_t error_size);
void fpm_free(fpm_model *model);

/* The last error message of calls on model ("" after success). */
const char *fpm_error(const fpm_model *model);

uint32_t fpm_node_count(const fpm_model *model);
uint32_t fpm_spring_count(const fpm_model *model);
uint32_t fpm_hexahedron_count(const fpm_model *model);
uint32_t fpm_case_count(const fpm_model *model);
double fpm_dt(const fpm_model *model);      /* s */
double fpm_damping(const fpm_model *model); /* d, N s/m */
/* The guaranteed-stable time step near rest (Gershgorin's bound, fpm.dynamics.stability), s. */
double fpm_stable_dt(const fpm_model *model);

/* Nodal damping d (N s/m) and time step dt (s) for the steps that follow; refused
   (FPM_ERR_UNSTABLE, FPM_ERR_VALUE) as the file's are. */
int fpm_set_parameters(fpm_model *model, double d, double dt);
/* Threads for the step: 0 = all OpenMP's on lattices of FPM_THREAD_NODES nodes or more, one on
   smaller ones; n = n threads (1 without OpenMP). The nodes are stepped in two fixed halves,
   one thread each, so the step's result is the same on any number of threads, and a third
   thread has nothing to do. */
int fpm_set_threads(fpm_model *model, int threads);
/* The threads the step runs on (1 without OpenMP). */
int fpm_thread_count(const fpm_model *model);

/* The rest positions, 3 N values, m. */
int fpm_rest_positions(const fpm_model *model, fpm_real *x);
/* The nodal forces of load case c (0-based), 3 N values, N. */
int fpm_case_forces(const fpm_model *model, uint32_t c, fpm_real *forces);
/* Forces as the fit applied them (the export's load shares, loads "hat"): out = shared forces;
   a copy of forces where the export has no shares. 3 N values each, N. */
int fpm_applied(const fpm_model *model, const fpm_real *forces, fpm_real *out);
/* Spring and volume forces at positions x: -dE/dx without the applied forces, 3 N values, N. */
int fpm_internal_forces(fpm_model *model, const fpm_real *x, fpm_real *out);

/* Forget the settle criteria's memory of the last loaded step (back to rest). */
void fpm_reset(fpm_model *model);
/* One step under forces (3 N values, N; NULL: none) from positions x and velocities v: writes
   the new positions to x_next (not x: the step reads every x while it writes) and updates v in
   place. stats may be NULL. */
int fpm_step(fpm_model *model, const fpm_real *x, fpm_real *x_next, fpm_real *v,
             const fpm_real *forces, fpm_stats *stats);

#ifdef __cplusplus
}
#endif

#endif
