"""Force propagation model (Choi et al. 2004) calibrated against a hexahedral FEM reference."""

from .fem import FemResult, solve_fem
from .problem import LoadCase, Problem, load_problem
from .simulation import SimulationResult, simulate
from .spec import ProblemSpec

__all__ = [
    "FemResult",
    "LoadCase",
    "Problem",
    "ProblemSpec",
    "SimulationResult",
    "load_problem",
    "simulate",
    "solve_fem",
]
