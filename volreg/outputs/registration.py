"""Every output of a label registration, written into one folder, all or nothing.

:func:`write_outputs` writes a finished registration (a
:class:`~volreg.pipeline.labels.LabelRegistration`): the displacement field on the fixed grid
and its inverse on the moving grid (ANTs/ITK conventions), the warped labels, the model, the
linear part, the Jacobian map and the report; :func:`write_registration` registers and writes
in one transaction.  The files are written in the background as their arrays come, and
recorded in the output folder once complete, so an error or an interrupt leaves nothing
half-written (:func:`~volreg.io._atomic.output_folder`).
"""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Mapping
from concurrent.futures import Future
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from volreg._threads import JobQueue
from volreg.evaluation.report import RegistrationReport, landmark_errors, registration_report, scores_before
from volreg import io
from volreg.io._atomic import OutputFolder, output_folder
from volreg.io.fields import write_displacement, write_itk_composite, write_itk_linear
from volreg.pipeline.arguments import (
    bool_argument,
    callable_argument,
    drive_labels_argument,
    label_volume_argument,
    landmarks_argument,
    mapping_argument,
    path_argument,
    protocol_argument,
)
from volreg.io import report_figure
from volreg.pipeline.grid_fields import FixedGridFields, inverse_on_moving_grid, sample_on_fixed_grid
from volreg.pipeline.labels import LabelRegistration, register_labels
from volreg.errors import ArgumentTypeError
from volreg.settings import Protocol

__all__ = ["ITK_H5_OUTPUTS", "REGISTRATION_OUTPUTS", "registration_outputs", "write_outputs", "write_registration"]

ProgressCallback = Callable[[str, int, int], None]
PointMap = Callable[[np.ndarray], np.ndarray]

#: The files :func:`write_registration` writes into its output folder with the default protocol.
REGISTRATION_OUTPUTS = (
    "warp.nii.gz", "inverse_warp.nii.gz", "warped.nii.gz", "model.npz", "jacobian.nii.gz", "linear.tfm", "report.json",
    "report.png", "warp.h5", "inverse_warp.h5",
)

#: The outputs left out when the protocol's ``[outputs] itk_h5`` is false.
ITK_H5_OUTPUTS = ("warp.h5", "inverse_warp.h5")


def registration_outputs(protocol: Protocol | None = None) -> tuple[str, ...]:
    """The files :func:`write_registration` writes with ``protocol`` (default: the default protocol's).

    Returns
    -------
    tuple of str
        :data:`REGISTRATION_OUTPUTS`, less :data:`ITK_H5_OUTPUTS` when ``protocol.outputs.itk_h5`` is false.
    """
    if protocol is None or protocol.outputs.itk_h5:
        return REGISTRATION_OUTPUTS
    return tuple(name for name in REGISTRATION_OUTPUTS if name not in ITK_H5_OUTPUTS)


def _peak_rss_gb() -> float:
    """Peak resident memory of this process so far, GB (Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def _stage(name: str, t0: float) -> dict:
    """A stage record: its name, seconds since ``t0`` and the peak memory so far (GB)."""
    return dict(stage=name, seconds=time.perf_counter() - t0, peak_rss_gb=round(_peak_rss_gb(), 3))


class _OutputWrites:
    """The registration's files, each written in the background (a :class:`~volreg._threads.JobQueue`)
    as soon as its array exists, into ``folder`` (an :class:`~volreg.io._atomic.OutputFolder`),
    and recorded there once complete.

    The fields on the fixed grid, the model and the linear part are written while the inverse
    and the metrics are computed (compressing and writing release the GIL, and those stages
    leave part of the second core idle); the inverse's field once it exists; the report figure
    once the metrics give its title.
    """

    def __init__(self, jobs, folder, fixed, moving, force: bool, itk_h5: bool) -> None:
        self.jobs, self.folder, self.fixed, self.moving = jobs, folder, fixed, moving
        self.force, self.itk_h5 = force, itk_h5

    def _submit(self, *outputs: tuple[str, Callable[[Path], None]]) -> None:
        """Write the named outputs one after the other, as one background job."""
        def job() -> None:
            for name, writer in outputs:
                path = self.folder.path / name
                writer(path)
                self.folder.record(path)  # once complete: a failed run removes it
        self.jobs.submit(job)

    def fields(self, warp, fields: FixedGridFields) -> None:
        """The fixed grid's displacement, Jacobian map and warped labels, the model and the linear part."""
        fixed, moving, force = self.fixed, self.moving, self.force
        warped = fields.warped.astype(moving.array.dtype, copy=False)
        # Largest first; the files are independent, so they are written side by side.
        self._submit(("warp.nii.gz", lambda p: write_displacement(fields.displacement, fixed, p, force=force)))
        self._submit(("jacobian.nii.gz", lambda p: io.write_scalar(fields.jacobian, fixed, p, force=force)))
        self._submit(("warped.nii.gz", lambda p: io.write_labels(fixed.with_array(warped), p, force=force)),
                     ("model.npz", lambda p: warp.save(p, force=force)),
                     ("linear.tfm", lambda p: write_itk_linear(p, warp.linear, force=force)))

    def inverse(self, u_fixed: np.ndarray, u_inverse: np.ndarray) -> None:
        """The inverse's displacement on the moving grid (and both fields as ITK composite transforms
        when asked for); ``u_fixed`` is the forward displacement on the fixed grid."""
        fixed, moving, force = self.fixed, self.moving, self.force
        self._submit(("inverse_warp.nii.gz", lambda p: write_displacement(u_inverse, moving, p, force=force)))
        if self.itk_h5:
            # The two HDF5 files in one job, one after the other: ITK's HDF5 library may not be thread-safe.
            self._submit(("warp.h5", lambda p: write_itk_composite(u_fixed, fixed, p, force=force)),
                         ("inverse_warp.h5", lambda p: write_itk_composite(u_inverse, moving, p, force=force)))

    def figure(self, fields: FixedGridFields, report: RegistrationReport) -> None:
        """The report figure, titled with the report's mean Dice before and after."""
        fixed, moving = self.fixed, self.moving
        title = (f"volreg register: mean Dice {report.mean_dice['before']:.3f} -> "
                 f"{report.mean_dice['after']:.3f}")
        # The displacement in LPS mm, turned into the fixed grid's voxels on the drawn slices only
        self._submit(("report.png", lambda p: report_figure.write_report_figure(
            p, fixed.array, moving.array, fields.warped, fields.displacement, fixed_spacing=fixed.spacing,
            moving_spacing=moving.spacing, force=self.force, title=title, to_voxels=fixed.direction / fixed.spacing)))


def _write_result(folder: OutputFolder, jobs: JobQueue, fixed, moving, result: LabelRegistration, *,
                  protocol: Protocol, landmarks, force: bool, inputs, truth, progress, before: Future | dict | None,
                  started: float) -> RegistrationReport:
    """Compute and write every output of ``result`` into the open ``folder``; the report."""
    stages = [dict(stage=st.stage, seconds=st.seconds, peak_rss_gb=round(_peak_rss_gb(), 3)) for st in result.stages]
    t0 = time.perf_counter()
    fields = sample_on_fixed_grid(result.warp, fixed, moving, protocol.warp.max_folded_fraction, progress)
    stages.append(_stage("resample", t0))
    # From here on the outputs are written in the background as their arrays come; the
    # inverse and metrics stages below share the cores with those writes, and the write
    # stage is what is left of them at the end.
    writes = _OutputWrites(jobs, folder, fixed, moving, force, protocol.outputs.itk_h5)
    writes.fields(result.warp, fields)

    t0 = time.perf_counter()
    inverse, u_inverse = inverse_on_moving_grid(result.warp, moving, progress, fixed, fields.displacement)
    writes.inverse(fields.displacement, u_inverse)
    stages.append(_stage("inverse", t0))

    t0 = time.perf_counter()
    before = before.result() if isinstance(before, Future) else before
    report = registration_report(fixed, moving, result, fields, inverse, protocol, inputs=inputs, truth=truth,
                                 before=before)
    if landmarks is not None:
        report.landmarks = landmark_errors(result.warp, landmarks, fixed)
    writes.figure(fields, report)
    stages.append(_stage("metrics", t0))

    t0 = time.perf_counter()
    jobs.wait()
    stages.append(_stage("write", t0))
    report.stages = stages
    report.seconds = time.perf_counter() - started
    report.peak_rss_gb = round(_peak_rss_gb(), 3)
    io.write_json(report.to_json(), folder.path / "report.json", force=force)
    folder.record(folder.path / "report.json")
    return report


def write_outputs(
    result: LabelRegistration,
    fixed,
    moving,
    outdir: str | os.PathLike[str],
    *,
    protocol: Protocol | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    force: bool = False,
    inputs: Mapping | None = None,
    truth: PointMap | None = None,
    progress: ProgressCallback | None = None,
) -> RegistrationReport:
    """Write every output of a finished registration of ``moving`` to ``fixed`` into ``outdir``.

    The same files as :func:`write_registration` (:func:`registration_outputs`), from ``result``
    as it is: nothing is registered again.

    Parameters
    ----------
    result : LabelRegistration
        :func:`~volreg.pipeline.labels.register_labels` of ``fixed`` and ``moving``.
    fixed, moving : LabelVolume or path-like
        The volumes, or the paths of label images.
    outdir : path-like
        The output folder, all or nothing (see :func:`write_registration`).
    protocol : Protocol, str or path-like, optional
        The protocol ``result`` was registered with, or its preset name or file (its ``outputs`` and
        ``warp.max_folded_fraction`` apply, and the report records it); default the default protocol.
    landmarks : pair of (L, D) float ndarrays, optional
        Fixed landmarks and their moving partners, mm: the report gives the warp's error at them.
    force, inputs, truth, progress
        As :func:`write_registration`.

    Returns
    -------
    RegistrationReport
        As written to ``report.json``; its ``seconds`` count the outputs alone.
    """
    if not isinstance(result, LabelRegistration):
        raise ArgumentTypeError(f"Expected `result` to be the LabelRegistration of register_labels, got "
                                f"{type(result).__name__}.")
    fixed, moving, outdir, protocol, landmarks, force, inputs, truth, progress = _checked(
        fixed, moving, outdir, protocol, landmarks, force, inputs, truth, progress)
    with output_folder(outdir, force, outputs=REGISTRATION_OUTPUTS) as folder, JobQueue() as jobs:  # the jobs end before the folder closes
        folder.check_writable(registration_outputs(protocol), force=force)
        started = time.perf_counter()
        return _write_result(folder, jobs, fixed, moving, result, protocol=protocol, landmarks=landmarks,
                             force=force, inputs=inputs, truth=truth, progress=progress, before=None,
                             started=started)


def _checked(fixed, moving, outdir, protocol, landmarks, force, inputs, truth, progress) -> tuple:
    """The arguments the writers share, checked (:mod:`volreg.pipeline.arguments`) before a folder is
    made: volumes or their paths, the output folder's path, a protocol or its name, landmarks of the
    volumes' dimension, ``force`` true or false, the inputs' record a mapping, callables."""
    fixed, moving = label_volume_argument(fixed, "fixed"), label_volume_argument(moving, "moving")
    return (fixed, moving, path_argument(outdir, "outdir"), protocol_argument(protocol),
            landmarks_argument(landmarks, fixed.ndim), bool_argument(force, "force"), mapping_argument(inputs, "inputs"),
            callable_argument(truth, "truth", "of (N, D) fixed points, mm"),
            callable_argument(progress, "progress", "progress(stage, done, total)"))


def register_and_write(fixed, moving, outdir, *, protocol: Protocol | None = None,
                       drive_labels: Sequence[int] | None = None, landmarks=None, force: bool = False, inputs=None,
                       truth: PointMap | None = None, prior: PointMap | None = None,
                       progress: ProgressCallback | None = None,
                       on_fit: Callable[[LabelRegistration], None] | None = None
                       ) -> tuple[LabelRegistration, RegistrationReport]:
    """:func:`write_registration`, also returning the registration itself."""
    fixed, moving, outdir, protocol, landmarks, force, inputs, truth, progress = _checked(
        fixed, moving, outdir, protocol, landmarks, force, inputs, truth, progress)
    drive_labels = drive_labels_argument(drive_labels)
    prior = callable_argument(prior, "prior", "of (N, D) fixed points, mm")
    on_fit = callable_argument(on_fit, "on_fit", "of a LabelRegistration")
    with output_folder(outdir, force, outputs=REGISTRATION_OUTPUTS) as folder, JobQueue() as jobs:  # the jobs end before the folder closes
        folder.check_writable(registration_outputs(protocol), force=force)
        started = time.perf_counter()
        # The scores before registration need only the inputs: computed in the background while
        # the linear stage and the fit leave a core partly idle, not in the metrics stage.
        before = jobs.submit(scores_before, fixed, moving)
        result = register_labels(fixed, moving, drive_labels=drive_labels, landmarks=landmarks,
                                 protocol=protocol, prior=prior, progress=progress)
        if on_fit is not None:
            on_fit(result)
        report = _write_result(folder, jobs, fixed, moving, result, protocol=protocol, landmarks=landmarks,
                               force=force, inputs=inputs, truth=truth, progress=progress, before=before,
                               started=started)
    return result, report


def write_registration(
    fixed,
    moving,
    outdir: str | os.PathLike[str],
    *,
    protocol: Protocol | None = None,
    drive_labels: Sequence[int] | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    force: bool = False,
    inputs: Mapping | None = None,
    truth: PointMap | None = None,
    prior: PointMap | None = None,
    progress: ProgressCallback | None = None,
    on_fit: Callable[[LabelRegistration], None] | None = None,
) -> RegistrationReport:
    """Register ``moving`` to ``fixed`` (:func:`~volreg.pipeline.labels.register_labels`) and write every output into ``outdir``.

    The outputs (:func:`registration_outputs`): ``warp.nii.gz`` (the displacement
    u(x) = tau(x) - x on the fixed grid, LPS mm, as ANTs/ITK read it),
    ``inverse_warp.nii.gz`` (the inverse's displacement on the moving grid),
    ``warp.h5`` and ``inverse_warp.h5`` (the same two fields as ITK composite
    transforms, unless the protocol's ``outputs.itk_h5`` is false),
    ``warped.nii.gz`` (the moving labels on the fixed grid), ``model.npz`` (the
    warp, paper eq. 9 with its linear part), ``linear.tfm`` (the linear part alone,
    an ITK transform), ``jacobian.nii.gz`` (det d tau / dx on the fixed grid),
    ``report.png`` and ``report.json`` (the report returned).

    Parameters
    ----------
    fixed, moving : LabelVolume or path-like
        The volumes, or the paths of label images (:func:`volreg.io.read_labels`).
    outdir : path-like
        The output folder; created with missing parents.  A warp folding more than
        ``protocol.warp.max_folded_fraction`` of the fixed grid is refused before
        anything is written.
    protocol : Protocol, str or path-like, optional
        A protocol, or a preset name or protocol file; default
        :func:`volreg.io.protocol.load_protocol` ``("default")``.
    drive_labels, landmarks, prior
        As :func:`~volreg.pipeline.labels.register_labels`.
    force : bool, default False
        Write into a non-empty ``outdir``, replacing outputs.
    inputs : dict, optional
        What the report records as the inputs (e.g. paths and checksums).
    truth : callable, optional
        The true warp, ``truth(points (N, D) mm) -> (N, D) mm``: the report then gives the
        endpoint error ``|tau(x) - truth(x)|`` over the fixed labels' voxels, mm.
    progress : callable, optional
        ``progress(stage, done, total)``.
    on_fit : callable, optional
        Called with the :class:`~volreg.pipeline.labels.LabelRegistration` once the warp is fitted, before the
        outputs are computed (e.g. to log its stages and levels).

    Returns
    -------
    RegistrationReport
        The report, as written to ``report.json`` (its ``to_json()``, NaN as ``None``): Dice per label before
        and after, the Jacobian determinant's range and folded fractions, displacement
        figures in mm, the inverse's residual, the fit's ``levels`` and ``stages`` (seconds
        and peak memory, GB), ``seconds`` and ``peak_rss_gb``.

    Raises
    ------
    VolregError
        An argument of the wrong kind (:class:`~volreg.errors.ArgumentTypeError`, a ``TypeError``)
        or value, before anything is made; inputs that cannot be registered, a non-empty ``outdir`` without ``force``, an output
        that cannot be written, a warp that diverges or folds.  On any error (and on an
        interrupt) the files written so far and the folders created are removed.
    """
    return register_and_write(fixed, moving, outdir, protocol=protocol, drive_labels=drive_labels,
                              landmarks=landmarks, force=force, inputs=inputs, truth=truth, prior=prior,
                              progress=progress, on_fit=on_fit)[1]
