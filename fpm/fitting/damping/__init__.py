"""Stage 2 of the two-stage calibration, after the chains: the polished stiffness, the depth,
the fastest-settling nodal damping d and the validation run beside them.

The stage's driver is :mod:`fpm.fitting.damping.stage`; the modules, named by what they do:
polish (the chains' best stiffness, polished on static equilibria), depth (depth 'auto'),
search (choosing d: the prediction from the slowest modes, then the search's runs), lockstep
(one d's runs, all load cases in lockstep pieces, and their verdicts), margin (the smallest d
that still settles), unsettled (the errors of a search that cannot settle), validation (the
last run and the validation cases) and settings (the stage's constants, one object).
"""
