"""Judging a registration: overlap and folding metrics, the consistency test, tuning by consistency.

Modules
-------
metrics
    Dice, surface distances, folded fractions.
consistency
    The consistency test (paper Section 6): warp forward and back, the original must come back.
review
    Plausibility checks of a finished registration (labels lost, Dice worse than identity,
    implausible linear parts); their findings are warnings in the report and on stderr.
tune
    Scoring warp settings by consistency and hold-out surface distance.
"""
