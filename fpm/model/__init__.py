"""The model and its geometry (paper Sec. 3.1): the problem spec and its arrays, the lattice of
nodes and springs built from hexahedra, the model's force terms (springs and the cells' volume
term) and their stiffness modes, the perturbed list, and whether the fixed nodes hold the solid.

Modules: spec (the pydantic schema), problem (spec -> arrays), geometry, hexahedron,
perturbed_list, forces, volume, stiffness, support. Only volume is compiled (numba), and it is
loaded only where a volume term is computed: the service validates specs with
:mod:`fpm.model.spec` and :mod:`fpm.model.problem` without numba or SciPy's solvers.
"""
