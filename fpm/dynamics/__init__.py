"""FPM dynamics and statics (paper Sec. 3.2): the compiled Voigt time step, a load case run to
rest, the static equilibrium that a settled run reaches, found directly, and the lattice's
stability estimate (dt auto).

Modules: voigt (the one hot loop, numba), simulation, equilibrium (the static solver) with
spring_system (its energy and tangent), cell_terms (the volume term's kernels) and predictor
(its warm starts), stability.
"""
