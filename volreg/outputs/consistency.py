"""The consistency test's outputs, and both directions of a pair written as registrations.

:func:`write_both_ways` registers A to B and B to A (:func:`~volreg.pipeline.two_way.register_both_ways`)
and writes each direction's outputs (:func:`~volreg.outputs.registration.write_registration`) into
``outdir/forward`` and ``outdir/backward``; :func:`write_consistency_test` runs the consistency test
(paper Section 5, :func:`~volreg.evaluation.consistency.consistency_test`) and writes its report,
error map and figure, all or nothing, as ``volreg consistency`` does; :func:`load_saved_warp`
reads the warp of a saved direction, checked against the grid it must have been registered on.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from volreg import __version__
from volreg.errors import UsageError
from volreg.evaluation.consistency import consistency_test
from volreg.evaluation.report import RegistrationReport
from volreg.grid import LabelVolume
from volreg.io import write_json, write_scalar
from volreg.io.fields import axis_order_of, read_displacement
from volreg.io._atomic import output_folder
from volreg.io.report_figure import write_error_figure
from volreg.io.summary import json_safe, package_versions
from volreg.outputs.registration import register_and_write
from volreg.pipeline.arguments import mapping_argument, path_argument
from volreg.pipeline.labels import LabelRegistration
from volreg.pipeline.two_way import TwoWayRegistration, register_both_ways
from volreg.settings import Protocol
from volreg.warp.model import KernelWarp

__all__ = ["CONSISTENCY_OUTPUTS", "WrittenBothWays", "load_saved_warp", "write_both_ways", "write_consistency_test"]

ProgressCallback = Callable[[str, int, int], None]


@dataclass
class WrittenBothWays(TwoWayRegistration):
    """Both registrations of a pair (:class:`~volreg.pipeline.two_way.TwoWayRegistration`) and
    their written reports.

    Attributes
    ----------
    reports : dict of str to RegistrationReport
        ``{"forward": report, "backward": report}``, as written to each direction's ``report.json``.
    """

    reports: dict[str, RegistrationReport] = field(default_factory=dict)


def write_both_ways(
    a: LabelVolume,
    b: LabelVolume,
    outdir: str | os.PathLike[str],
    *,
    protocol: Protocol | None = None,
    drive_labels: Sequence[int] | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    force: bool = False,
    inputs: Mapping | None = None,
    progress: ProgressCallback | None = None,
    on_fit: Callable[[LabelRegistration], None] | None = None,
) -> WrittenBothWays:
    """Register A to B and B to A and write each registration's outputs into
    ``outdir/forward`` and ``outdir/backward``.

    Parameters
    ----------
    a, b : LabelVolume or path-like
    outdir : path-like
    protocol, drive_labels, landmarks, progress
        As :func:`~volreg.pipeline.two_way.register_both_ways`.
    force : bool, default False
        Write into non-empty folders, replacing outputs.
    inputs : dict, optional
        ``{"A": ..., "B": ...}``, what the reports record as A and B.
    on_fit : callable, optional
        Called with each direction's registration once it is fitted, before its outputs.

    Returns
    -------
    WrittenBothWays
    """
    outdir = path_argument(outdir, "outdir")  # the other arguments: as each direction's registration checks them
    inputs = mapping_argument(inputs, "inputs")
    reports = {}
    keys = {"forward": ("A", "B"), "backward": ("B", "A")}

    def register(name, fixed, moving, points, prior) -> LabelRegistration:
        fixed_key, moving_key = keys[name]
        records = None if inputs is None else {"fixed": inputs[fixed_key], "moving": inputs[moving_key]}
        result, reports[name] = register_and_write(
            fixed, moving, Path(outdir) / name, protocol=protocol, drive_labels=drive_labels, landmarks=points,
            force=force, inputs=records, truth=None, prior=prior, progress=progress, on_fit=on_fit,
        )
        return result

    both = register_both_ways(a, b, protocol=protocol, landmarks=landmarks, register=register)
    return WrittenBothWays(both.forward, both.backward, reports)


#: The files :func:`write_consistency_test` writes into its output folder (besides
#: ``forward/`` and ``backward/`` when it registers).
CONSISTENCY_OUTPUTS = ("consistency.json", "consistency_error.nii.gz", "consistency.png")


def write_consistency_test(
    a: LabelVolume,
    b: LabelVolume,
    outdir: str | os.PathLike[str],
    *,
    forward=None,
    backward=None,
    directions: Mapping | None = None,
    protocol=None,
    drive_labels: Sequence[int] | None = None,
    force: bool = False,
    inputs: Mapping | None = None,
    progress: ProgressCallback | None = None,
    on_fit: Callable | None = None,
) -> dict:
    """Register A to B and B to A (or take both warps), run :func:`~volreg.evaluation.consistency.consistency_test`, write its outputs.

    Without ``forward`` and ``backward``, both directions are registered with
    :func:`write_both_ways` and written into ``outdir/forward`` and
    ``outdir/backward`` (every output of :func:`~volreg.outputs.registration.write_registration`).
    Then ``outdir`` gets :data:`CONSISTENCY_OUTPUTS`: ``consistency.json`` (the report
    returned), ``consistency_error.nii.gz`` (the error on A's grid, mm) and
    ``consistency.png``.

    Parameters
    ----------
    a, b : LabelVolume
    outdir : path-like
        The output folder; created with missing parents.
    forward, backward : KernelWarp, optional
        Both warps, when they are not to be registered (A -> B and B -> A).
    directions : dict, optional
        With ``forward`` and ``backward``: what the report records of where they came
        from (``{"forward": {...}, "backward": {...}}``).
    protocol : Protocol, optional
        When registering; default :func:`volreg.io.protocol.load_protocol` ``("default")``.
    drive_labels : sequence of int, optional
        When registering, as :func:`~volreg.pipeline.labels.register_labels`.
    force : bool, default False
        Write into a non-empty ``outdir``, replacing outputs.
    inputs : dict, optional
        ``{"A": ..., "B": ...}``: what the reports record as the inputs.
    progress, on_fit : callable, optional
        As :func:`~volreg.outputs.registration.write_registration`.

    Returns
    -------
    dict
        The report, as written to ``consistency.json`` (NaN as ``None``): the figures of
        :func:`~volreg.evaluation.consistency.consistency_test` plus ``inputs``, ``directions`` (per direction its output
        folder and, when registered here, its mean Dice and seconds), ``lambda_consistency``
        (the symmetric option's weight, as the backward warp records it), ``seconds`` and
        ``versions``.

    Raises
    ------
    VolregError
        As :func:`~volreg.outputs.registration.write_registration`.  On any error (and on an interrupt)
        every file written so far, the registrations' too, and the folders created are removed.
    """
    if (forward is None) != (backward is None):
        raise ValueError("Expected both `forward` and `backward` warps, or neither (to register both ways).")
    start = time.perf_counter()
    outdir = Path(outdir)
    with output_folder(outdir, force, outputs=CONSISTENCY_OUTPUTS) as folder:
        paths = folder.check_writable(CONSISTENCY_OUTPUTS, force=force)  # in staging, swapped in at the end
        if forward is None:
            both = write_both_ways(a, b, outdir, protocol=protocol, drive_labels=drive_labels, force=force,
                                   inputs=inputs, progress=progress, on_fit=on_fit)
            forward, backward = both.forward.warp, both.backward.warp
            directions = {name: {"outdir": str(outdir / name), "mean_dice": rep.mean_dice, "seconds": rep.seconds,
                                 "folded_fraction": rep.jacobian["folded_fraction"], "review": rep.review}
                          for name, rep in both.reports.items()}
        figures, error = consistency_test(a, b, forward, backward, progress=progress)
        report = {
            "volreg_version": __version__,
            "command": "consistency",
            "inputs": {} if inputs is None else inputs,
            "directions": {} if directions is None else directions,
            # the symmetric option's weight, as recorded in the backward warp's settings
            "lambda_consistency": backward.settings.get("lambda_consistency", 0.0),
            **figures,
            "seconds": time.perf_counter() - start,
            "versions": package_versions(),
        }
        write_scalar(error, a, paths["consistency_error.nii.gz"], force=force)
        folder.record(paths["consistency_error.nii.gz"])
        r = figures["region"]
        write_error_figure(paths["consistency.png"], a.array, error, spacing=a.spacing, force=force,
                           title=f"volreg consistency: |tau_BA(tau_AB(x)) - x|, mean {r['mean_mm'] or 0:.3g} mm, "
                           f"p95 {r['p95_mm'] or 0:.3g} mm over A's padded labels")
        folder.record(paths["consistency.png"])
        report = json_safe(report)
        write_json(report, paths["consistency.json"], force=force)
        folder.record(paths["consistency.json"])
    return report


def load_saved_warp(result: str | os.PathLike[str], grid: LabelVolume, *, option: str, grid_path: object,
                    role: str) -> KernelWarp:
    """The warp of a saved ``volreg register`` output folder, checked to be registered on ``grid``.

    Parameters
    ----------
    result : path-like
        The folder; its ``model.npz`` is read, and its ``warp.nii.gz`` tells the fixed grid.
    grid : LabelVolume
        The volume the result's fixed grid must be (A for the forward direction, B for the backward).
    option : str
        How messages name the result, e.g. ``"--forward"``.
    grid_path : str or path-like
        The file ``grid`` was read from, named in the messages.
    role : {"A", "B"}
        Which volume ``grid`` is.

    Returns
    -------
    KernelWarp

    Raises
    ------
    UsageError
        A folder without ``model.npz`` or ``warp.nii.gz``, registered on another grid, or holding a
        warp of another dimension.
    """
    result = Path(result)
    model = result / "model.npz"
    field_path = result / "warp.nii.gz"
    for p in (model, field_path):
        if not p.is_file():
            raise UsageError(f"{option} `{result}` has no `{p.name}`; expected an OUTDIR written by `volreg register`.")
    _, field_grid = read_displacement(field_path)
    if axis_order_of(field_grid, grid, atol=1e-3) is None:  # a single-voxel axis is stored first (write_displacement)
        raise UsageError(
            f"{option} `{result}` was registered on a grid of shape {field_grid.shape} (origin "
            f"{np.round(field_grid.origin, 3).tolist()} mm), not on the grid of {role} `{grid_path}` (shape "
            f"{grid.shape}, origin {np.round(grid.origin, 3).tolist()} mm); expected the result of "
            f"`volreg register {'A B' if role == 'A' else 'B A'}`."
        )
    warp = KernelWarp.load(model)
    if warp.dim != grid.ndim:
        raise UsageError(f"{option} `{model}` is a {warp.dim}-D warp but {role} `{grid_path}` is {grid.ndim}-D.")
    return warp
