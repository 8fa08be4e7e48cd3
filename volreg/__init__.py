"""volreg: kernel registration of labelled volumes and surfaces.

Implements Schölkopf, Steinke & Blanz, "Object Correspondence as a Machine
Learning Problem" (ICML 2005).  World coordinates are ITK physical space (LPS, mm).

The public API is importable from here (loaded on first use, so ``import volreg``
stays light)::

    import volreg
    fixed = volreg.read_labels("fixed.nii.gz")
    moving = volreg.read_labels("moving.nii.gz")
    result = volreg.register_labels(fixed, moving)   # result.warp maps fixed -> moving points
"""

import sys as _sys

if _sys.argv[0].endswith(("/volreg", "\\volreg", "volreg.exe")) or (
        _sys.argv[:1] == ["-m"] and "volreg" in getattr(_sys, "orig_argv", [])[1:3]):
    # ``python -m volreg`` (argv[0] is "-m" while the package is imported; not ``-m volreg.X``,
    # the compiling helpers) or the console command: the command line's first signal handlers, before anything heavy is loaded.
    from volreg._signals import exit_on_early_signals as _exit_on_early_signals

    _exit_on_early_signals()

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("volreg")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

#: Public name -> the module that defines it.
_API = {
    # the main jobs
    "register_labels": "volreg.pipeline.labels",
    "register_surfaces": "volreg.pipeline.surfaces",
    "register_both_ways": "volreg.pipeline.two_way",
    "TwoWayRegistration": "volreg.pipeline.two_way",
    "write_registration": "volreg.outputs.registration",
    "write_outputs": "volreg.outputs.registration",
    "write_both_ways": "volreg.outputs.consistency",
    "write_surface_registration": "volreg.outputs.surfaces",
    "write_label_surfaces": "volreg.outputs.surfaces",
    "write_transferred_array": "volreg.outputs.surfaces",
    "write_morph": "volreg.outputs.morph",
    "write_moved_point_set": "volreg.outputs.apply",
    "write_resampled_image": "volreg.outputs.apply",
    "RegistrationReport": "volreg.evaluation.report",
    "check_pair": "volreg.pipeline.checks",
    "register_cohort": "volreg.cohort",
    "read_manifest": "volreg.cohort",
    "CohortSummary": "volreg.cohort",
    "build_template": "volreg.template",
    "TemplateResult": "volreg.template",
    "ShapeModel": "volreg.pipeline.shape_model",
    "LabelShapeModel": "volreg.shape_models",
    "build_shape_models": "volreg.shape_models",
    "ShapeModelResult": "volreg.shape_models",
    "write_shape_models": "volreg.outputs.shape_model",
    "write_shape_sample": "volreg.outputs.shape_model",
    "model_quality": "volreg.evaluation.shape_quality",
    "LabelRegistration": "volreg.pipeline.labels",
    "RegistrationResult": "volreg.warp.fit",
    # data and files
    "LabelVolume": "volreg.grid",
    "Grid": "volreg.grid",
    "read_grid": "volreg.io",
    "read_labels": "volreg.io",
    "read_image": "volreg.io",
    "write_labels": "volreg.io",
    "read_mesh": "volreg.io",
    "write_mesh": "volreg.io",
    "read_landmarks": "volreg.io.landmarks",
    "read_displacement": "volreg.io.fields",
    "write_displacement": "volreg.io.fields",
    "read_itk_linear": "volreg.io.fields",
    "write_itk_linear": "volreg.io.fields",
    "write_itk_composite": "volreg.io.fields",
    # settings
    "load_protocol": "volreg.io.protocol",
    "Protocol": "volreg.settings",
    "SurfaceSettings": "volreg.settings",
    "WarpSettings": "volreg.settings",
    "LinearSettings": "volreg.settings",
    "ReviewSettings": "volreg.settings",
    "OutputSettings": "volreg.settings",
    # the warp
    "KernelWarp": "volreg.warp.model",
    "LinearMap": "volreg.linear_map",
    "fit_linear": "volreg.warp.linear",
    "InverseWarp": "volreg.warp.inverse",
    "resample_labels": "volreg.warp.resample",
    "displacement_on_grid": "volreg.warp.field",
    "transform_points": "volreg.warp.points",
    "transform_normals": "volreg.warp.points",
    "DisplacementField": "volreg.warp.points",
    # evaluation
    "label_scores": "volreg.evaluation.metrics",
    "review_registration": "volreg.evaluation.review",
    "consistency_test": "volreg.evaluation.consistency",
    "write_consistency_test": "volreg.outputs.consistency",
    "tune_settings": "volreg.evaluation.tune",
    # errors
    "VolregError": "volreg.errors",
    "VolregIOError": "volreg.errors",
    "GeometryError": "volreg.errors",
    "SurfaceError": "volreg.errors",
    "ProtocolError": "volreg.errors",
    "RegistrationInputError": "volreg.errors",
    "RegistrationDiverged": "volreg.errors",
    "UsageError": "volreg.errors",
    "ArgumentTypeError": "volreg.errors",
    "SchedulerUnavailable": "volreg.errors",
    "VolregWarning": "volreg.errors",
}

__all__ = sorted(_API) + ["__version__"]


def __getattr__(name: str):
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'volreg' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value  # later lookups skip this hook
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
