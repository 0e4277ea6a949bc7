"""Fitting the FPM to the FEM (paper Sec. 4.2-4.4): the cost of Eq. (2) and the scale-free
figures, simulated annealing, the damping search, the reduced linear model of families+volume,
the calibration methods (two-stage and the paper's), and the diagnoses a user reads when a fit
cannot proceed.

Modules: cost, annealing, reduced, bounds (the search box), calibration (the orchestration:
calibrate, finalize) with its stages stiffness_stage (the chains, the polish) and the package
damping (stage 2: polish, depth, d, and validation, the fit against its reference), result
(CalibrationResult), diagnosis.
"""
