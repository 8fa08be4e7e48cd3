"""Every output of a finished result, written into a folder inside one output transaction.

The pipeline (:mod:`volreg.pipeline`) computes results and :mod:`volreg.evaluation` judges
them; the modules here turn a result into the files the commands promise, through the
formats of :mod:`volreg.io`, all or nothing.
"""
