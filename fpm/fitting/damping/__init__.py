"""Stage 2 of the two-stage calibration, after the chains: the polished stiffness, the depth,
the fastest-settling nodal damping d and the validation run beside them. Its driver is
:mod:`fpm.fitting.damping.stage`; the modules' parts: docs/explanation/layout.md.
"""
