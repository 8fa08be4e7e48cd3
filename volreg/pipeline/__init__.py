"""Registration by stage: label features, the label and surface front ends, both directions.

A registration is a short chain of stages, each a function of arrays that hands the next a
typed result: the pair is checked (:mod:`~volreg.pipeline.checks`), each label becomes feature
pairs (:mod:`~volreg.pipeline.label_features`), the linear stage and the kernel warp are
fitted (:mod:`~volreg.pipeline.labels`, :mod:`~volreg.pipeline.surfaces`), and the
consistency test registers both ways (:mod:`~volreg.pipeline.two_way`).  Nothing here reads or
writes files: :mod:`volreg.outputs` writes a finished result.
"""
