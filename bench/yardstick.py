"""The C yardstick of the FPM bench (its part 2, :mod:`bench.bench_fpm`): the compiled step's
Gauss-Seidel sweep as a plain C loop (same CSR arrays, same order, same update, same settle and
divergence checks), compiled here with ``cc -O2`` and called through ctypes
(:func:`build_yardstick`), and one load case's arrays ready for the numba step or the C loop
(:class:`Kernel`)."""

from __future__ import annotations

import ctypes
import shutil
import subprocess
from pathlib import Path

import numpy as np

YARDSTICK_C = r"""
#include <math.h>
#include <stdint.h>

/* fpm.dynamics.voigt.run_steps, line for line: returns steps taken; *state = 0 running, 1 settled,
   2 diverged; *worst = largest |F_i + F_s| of the last sweep. Arrays are C-contiguous. */
int64_t run_steps(const int32_t *order, int64_t m, const int64_t *ptr, const int32_t *neighbour,
                  const double *rest_length, const double *factor, int64_t scaled,
                  const double *rest, double *x, double *v, const double *external,
                  const double *mass, double k, double d, double dt, int64_t max_steps,
                  double settle_force, double max_move, int64_t *state, double *worst_out)
{
    double limit2 = max_move * max_move, worst = 0.0;
    for (int64_t step = 1; step <= max_steps; step++) {
        double worst2 = 0.0;
        for (int64_t o = 0; o < m; o++) {
            int64_t i = order[o];
            double xi0 = x[3 * i], xi1 = x[3 * i + 1], xi2 = x[3 * i + 2];
            double f0 = external[3 * i], f1 = external[3 * i + 1], f2 = external[3 * i + 2];
            for (int64_t e = ptr[i]; e < ptr[i + 1]; e++) {
                int64_t j = neighbour[e];
                double r0 = x[3 * j] - xi0, r1 = x[3 * j + 1] - xi1, r2 = x[3 * j + 2] - xi2;
                double length = sqrt(r0 * r0 + r1 * r1 + r2 * r2);
                double s = k * (length - rest_length[e]) / length;
                if (scaled) s *= factor[e];
                f0 += s * r0;
                f1 += s * r1;
                f2 += s * r2;
            }
            double f2sum = f0 * f0 + f1 * f1 + f2 * f2;
            if (f2sum > worst2) worst2 = f2sum;
            double a = dt / mass[i];
            double damp = 1.0 / (1.0 + a * d);
            double v0 = (v[3 * i] + a * f0) * damp;
            double v1 = (v[3 * i + 1] + a * f1) * damp;
            double v2 = (v[3 * i + 2] + a * f2) * damp;
            v[3 * i] = v0; v[3 * i + 1] = v1; v[3 * i + 2] = v2;
            xi0 += dt * v0;
            xi1 += dt * v1;
            xi2 += dt * v2;
            x[3 * i] = xi0; x[3 * i + 1] = xi1; x[3 * i + 2] = xi2;
            double u0 = xi0 - rest[3 * i], u1 = xi1 - rest[3 * i + 1], u2 = xi2 - rest[3 * i + 2];
            if (!(u0 * u0 + u1 * u1 + u2 * u2 <= limit2)) {
                *state = 2; *worst_out = sqrt(worst2); return step;
            }
        }
        worst = sqrt(worst2);
        if (worst < settle_force) { *state = 1; *worst_out = worst; return step; }
    }
    *state = 0; *worst_out = worst; return max_steps;
}
"""


NO_CELLS = (
    np.zeros((0, 8), dtype=np.int64),
    np.zeros((0, 6, 3)),
    np.zeros(0),
    np.zeros(0),
    np.zeros((0, 3)),
)
"""The kernel's volume-term arguments for a model without it (the C yardstick has none)."""
NO_TARGET = (np.zeros((0, 3)), 0.0, 0.0)
"""The kernel's target-criterion arguments for none (the C yardstick has none)."""


class Kernel:
    """One load case's arrays, ready for the numba step or the C yardstick."""

    def __init__(self, model, order: np.ndarray):
        p = model.problem
        a = model.adjacency
        self.order = np.ascontiguousarray(order, dtype=np.int32)
        self.ptr, self.neighbour = a.ptr, a.neighbour
        self.rest_length, self.factor = a.rest_length, a.stiffness_factor
        self.rest = p.nodes
        self.external = p.load_cases[0].dense(p.n_nodes)
        self.mass = p.solid.masses
        self.size = p.size
        self.x = p.nodes.copy()
        self.v = np.zeros_like(self.x)

    def reset(self) -> None:
        self.x[:] = self.rest
        self.v[:] = 0.0

    def numba(self, k: float, d: float, dt: float, steps: int) -> tuple[int, int, float]:
        from fpm.dynamics.voigt import run_steps

        taken, state, worst, *_ = run_steps(
            self.order, self.ptr, self.neighbour, self.rest_length, self.factor, self.rest,
            self.x, self.v, self.external, self.mass, k, d, dt, steps, 0.0, 0.0, self.size,
            *NO_CELLS, *NO_TARGET,
        )  # fmt: skip
        return taken, state, worst

    def c(self, lib, k: float, d: float, dt: float, steps: int) -> tuple[int, int, float]:
        state, worst = ctypes.c_int64(), ctypes.c_double()
        p = ctypes.c_void_p
        factor = self.factor if len(self.factor) else np.zeros(1)
        taken = lib.run_steps(
            p(self.order.ctypes.data), len(self.order), p(self.ptr.ctypes.data),
            p(self.neighbour.ctypes.data), p(self.rest_length.ctypes.data),
            p(factor.ctypes.data), int(len(self.factor) > 0), p(self.rest.ctypes.data),
            p(self.x.ctypes.data), p(self.v.ctypes.data), p(self.external.ctypes.data),
            p(self.mass.ctypes.data), k, d, dt, steps, 0.0, self.size,
            ctypes.byref(state), ctypes.byref(worst),
        )  # fmt: skip
        return taken, state.value, worst.value


def build_yardstick(workdir: Path):
    """The C loop as a ctypes function, or None (with the reason) if it cannot be built."""
    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        return None, "no C compiler (cc) on PATH"
    src, lib_path = workdir / "yardstick.c", workdir / "yardstick.so"
    src.write_text(YARDSTICK_C)
    out = subprocess.run(
        [cc, "-O2", "-shared", "-fPIC", "-o", str(lib_path), str(src), "-lm"],
        capture_output=True,
        text=True,
    )
    if out.returncode:
        return None, f"cc failed: {out.stderr.strip()[:300]}"
    lib = ctypes.CDLL(str(lib_path))
    lib.run_steps.restype = ctypes.c_int64
    lib.run_steps.argtypes = [
        ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
        ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
        ctypes.c_void_p, ctypes.c_void_p, ctypes.c_double, ctypes.c_double, ctypes.c_double,
        ctypes.c_int64, ctypes.c_double, ctypes.c_double, ctypes.c_void_p, ctypes.c_void_p,
    ]  # fmt: skip
    return lib, f"{cc} -O2"
