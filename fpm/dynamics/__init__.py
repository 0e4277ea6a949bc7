"""FPM dynamics and statics (paper Sec. 3.2): the compiled Voigt time step, a load case run to
rest, and the static equilibrium that a settled run reaches, found directly.

Modules: voigt (the one hot loop, numba), simulation, equilibrium.
"""
