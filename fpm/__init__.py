"""Force propagation model (Choi et al. 2004) calibrated against a hexahedral FEM reference.

The public names are loaded on first use (PEP 562), so that ``import fpm.model.spec`` or
``import fpm.model.problem`` (what the REST service needs to validate a spec) does not pull in the
compiled kernels, SciPy's solvers or numba.
"""

from importlib import import_module
from typing import TYPE_CHECKING, Any

_WHERE = {
    "CalibrationResult": "fitting.result",
    "calibrate": "fitting.calibration",
    "FemResult": "fem.reference",
    "solve_fem": "fem.reference",
    "LoadCase": "model.problem",
    "Problem": "model.problem",
    "load_problem": "model.problem",
    "SimulationResult": "dynamics.simulation",
    "simulate": "dynamics.simulation",
    "ProblemSpec": "model.spec",
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
    from .dynamics.simulation import SimulationResult, simulate
    from .fem.reference import FemResult, solve_fem
    from .fitting.calibration import calibrate
    from .fitting.result import CalibrationResult
    from .model.problem import LoadCase, Problem, load_problem
    from .model.spec import ProblemSpec


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'fpm' has no attribute {name!r}")
    return getattr(import_module(f".{_WHERE[name]}", __name__), name)
