"""The finite element reference (paper Sec. 4.1): linear-elastic 8-node hexahedra (elasticity,
assembly into K, sparse solves) and, for large deformations, compressible neo-Hookean hexahedra
under dead loads solved by Newton's method.

Modules: reference (solve_fem, FemResult: the entry point for both models), elasticity,
assembly, linear_solver (shared with the FPM's static equilibrium), hyperelastic,
neo_hookean, tet10 (10-node tetrahedra on the spec's reference.mesh, read at the lattice nodes).
"""
