"""The architecture's one rule that code can break silently: the service validates specs with
fpm.spec / fpm.problem but never loads the numerical kernels (docs/service.md)."""

import subprocess
import sys

KERNELS = ("numba", "fpm.voigt", "fpm.simulation", "fpm.fem", "fpm.calibration", "pyamg")


def test_the_service_does_not_import_the_numerical_kernels():
    code = f"import sys, service.main\nprint([m for m in {KERNELS!r} if m in sys.modules])\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_fpm_public_names_load_on_first_use():
    import fpm

    assert set(fpm.__all__) >= {"load_problem", "simulate", "solve_fem", "calibrate"}
    assert callable(fpm.calibrate) and fpm.ProblemSpec.__name__ == "ProblemSpec"
