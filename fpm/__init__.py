"""Force propagation model (Choi et al. 2004) calibrated against a hexahedral FEM reference."""

from .calibration import CalibrationResult, calibrate
from .fem import FemResult, solve_fem
from .problem import LoadCase, Problem, load_problem
from .simulation import SimulationResult, simulate
from .spec import ProblemSpec

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
