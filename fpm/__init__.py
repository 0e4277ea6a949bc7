"""Force propagation model (Choi et al. 2004) calibrated against a hexahedral FEM reference.

The public names are loaded on first use (PEP 562), so that ``import fpm.spec`` or
``import fpm.problem`` (what the REST service needs to validate a spec) does not pull in the
compiled kernels, SciPy's solvers or numba.
"""

from importlib import import_module
from typing import TYPE_CHECKING, Any

_WHERE = {
    "CalibrationResult": "calibration",
    "calibrate": "calibration",
    "FemResult": "fem",
    "solve_fem": "fem",
    "LoadCase": "problem",
    "Problem": "problem",
    "load_problem": "problem",
    "SimulationResult": "simulation",
    "simulate": "simulation",
    "ProblemSpec": "spec",
}

__all__ = [
    "CalibrationResult",
    "FemResult",
    "LoadCase",
    "Problem",
    "ProblemSpec",
    "SimulationResult",
    "calibrate",
    "load_problem",
    "simulate",
    "solve_fem",
]

if TYPE_CHECKING:
    from .calibration import CalibrationResult, calibrate
    from .fem import FemResult, solve_fem
    from .problem import LoadCase, Problem, load_problem
    from .simulation import SimulationResult, simulate
    from .spec import ProblemSpec


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'fpm' has no attribute {name!r}")
    return getattr(import_module(f".{_WHERE[name]}", __name__), name)
