"""The model and its geometry (paper Sec. 3.1): the problem spec and its arrays, the lattice of
nodes and springs built from hexahedra, spring stiffness per family, the perturbed list, and
whether the fixed nodes hold the solid.

Modules: spec (the pydantic schema), problem (spec -> arrays), geometry, hexahedron,
perturbed_list, stiffness, support. Nothing here needs numba or SciPy's solvers: the service
validates specs with :mod:`fpm.model.spec` and :mod:`fpm.model.problem`.
"""
