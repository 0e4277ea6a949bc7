"""Force propagation model (Choi et al. 2004) calibrated against a hexahedral FEM reference."""

from .problem import LoadCase, Problem, load_problem
from .spec import ProblemSpec

__all__ = ["LoadCase", "Problem", "ProblemSpec", "load_problem"]
