/* The memory-stream bound of bench/bench_native.py: seconds per pass of a loop that reads
   `count` doubles once (a sum, on the step's threads), the bytes the native step reads and
   writes once per step. Built with the step's compiler and flags. */
#include <stddef.h>

double stream_pass(const double *data, long count, int threads, long passes) {
    double total = 0.0;
    (void)threads;
    for (long p = 0; p < passes; p++) {
        double sum = 0.0;
#pragma omp parallel for simd schedule(static) num_threads(threads) reduction(+ : sum)
        for (long k = 0; k < count; k++) sum += data[k];
        total += sum;
    }
    return total;
}
