"""Judging a registration: overlap and folding metrics, the consistency test, tuning by consistency.

Modules
-------
metrics
    Dice, surface distances, folded fractions.
consistency
    The consistency test (paper Section 6): warp forward and back, the original must come back.
tune
    Scoring warp settings by consistency and hold-out surface distance.
"""
