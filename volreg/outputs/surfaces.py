"""The outputs of surface work: a surface registration, a label volume's surfaces, a transferred array.

:func:`write_surface_registration` registers one surface to another and writes what
``volreg register-surfaces`` promises (the warped source as VTK in LPS and, on request, GIFTI
in RAS; the correspondence table; the model; the report), all or nothing;
:func:`write_label_surfaces` writes the boundary meshes, fitted implicit surfaces and signed
distances of a label volume's labels, as ``volreg surface`` does; :func:`write_transferred_array`
carries a per-vertex array from the target onto the source through a saved registration, as
``volreg transfer`` does.  The helpers they and :mod:`volreg.outputs.morph` share read a
surface with its per-vertex data (:func:`read_surface_with_data`), load a saved surface model
(:func:`load_surface_model`) and write a moved surface (:func:`write_moved_surface`,
:func:`write_moved_gifti_surface`).
"""

from __future__ import annotations

import csv
import os
import re
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from io import StringIO
from pathlib import Path

import numpy as np

from volreg import __version__
from volreg import io
from volreg.errors import SurfaceError, UsageError, VolregWarning
from volreg.evaluation.review import Finding
from volreg.evaluation.surface_review import (
    SurfaceReviewLimits,
    diameter,
    review_landmarks,
    review_surface_distance,
    review_surface_extents,
    review_surface_translation,
)
from volreg.features import label_surfaces as surface_features
from volreg.grid import LabelVolume
from volreg.io._atomic import OutputFolder, output_folder
from volreg.io.gifti import GiftiArrayMeta, GiftiSurfaceMeta, is_gifti, write_gifti, write_gifti_data
from volreg.io.meshes import SurfaceData, add_vertex_data, read_surface
from volreg.io.summary import file_sha256, json_safe, package_versions
from volreg.morph import closest_points, surface_gaps, transfer_values
from volreg.pipeline.surface_inputs import MIN_VERTICES
from volreg.pipeline.surfaces import register_surface_pair
from volreg.settings import Protocol, SurfaceSettings
from volreg.warp.model import KernelWarp

__all__ = [
    "FRAMES", "LABEL_SURFACE_OUTPUTS", "SURFACE_REGISTRATION_GIFTI", "SURFACE_REGISTRATION_OUTPUTS", "TransferredArray", "WrittenLabelSurfaces",
    "WrittenSurfaceRegistration", "data_file_name", "is_label_array", "load_surface_model", "read_surface_with_data",
    "select_vertex_array", "vertex_array_meta", "write_label_surfaces", "write_moved_gifti_surface",
    "write_moved_surface", "write_surface_registration", "write_transferred_array",
]

ProgressCallback = Callable[[str, int, int], None]

#: The frame of each kind of surface output, as the reports state it.
FRAMES = {".vtk": "LPS mm", ".gii": "RAS mm", ".csv": "LPS mm"}

#: The files :func:`write_surface_registration` writes.
SURFACE_REGISTRATION_OUTPUTS = ("warped.vtk", "correspondence.csv", "model.npz", "report.json")

#: Every file :func:`write_label_surfaces` may write, whatever its labels (an earlier run's that
#: this one does not write are removed with ``force``): each label's mesh, GIFTI surface and
#: signed distance, the summary.
LABEL_SURFACE_OUTPUTS = ("label_*.vtk", "label_*.surf.gii", "sdf_*.nii.gz", "surface.json")

#: Written besides :data:`SURFACE_REGISTRATION_OUTPUTS` with ``gifti=True``.
SURFACE_REGISTRATION_GIFTI = "warped.surf.gii"

#: GIFTI POINTSETs of label meshes: in the world of the label volume, which NIfTI calls scanner RAS (code 1).
_SCANNER_RAS = GiftiSurfaceMeta(dataspace=1, xformspace=1)

_SURFACE_DEFAULTS = SurfaceSettings()


def _issue(message: str) -> None:
    """Where the caller passed no callback: the message as a :class:`~volreg.errors.VolregWarning`."""
    warnings.warn(message, VolregWarning, stacklevel=3)


def _issue_findings(findings: list[Finding]) -> None:
    for finding in findings:
        _issue(finding.message)


# ----------------------------------------------------------------------------- surfaces read and written

def read_surface_with_data(path: str | os.PathLike[str], role: str, data: Sequence[str | os.PathLike[str]] = ()) \
        -> SurfaceData:
    """A surface (mesh or point cloud) with the per-vertex arrays of its GIFTI data files.

    Parameters
    ----------
    path : path-like
        The surface: ``.vtk``, ``.vtp``, ``.ply``, ``.stl``, ``.obj`` or ``.gii`` (read in LPS mm).
    role : str
        How errors name it, e.g. ``"SOURCE"``.
    data : sequence of path-like
        GIFTI data files (``.shape.gii``, ``.func.gii``, ``.label.gii``) over its vertices.

    Returns
    -------
    SurfaceData
        With at least :data:`~volreg.pipeline.surface_inputs.MIN_VERTICES` vertices.

    Raises
    ------
    UsageError
        Fewer vertices than that.
    VolregIOError
        A file that cannot be read, or data of another vertex count.
    """
    surface = read_surface(path)
    if len(surface.vertices) < MIN_VERTICES:
        raise UsageError(f"{role} `{path}` has {len(surface.vertices)} vertices; expected at least {MIN_VERTICES} to "
                         "fit a surface.")
    add_vertex_data(surface, data, f"{role} `{path}`")
    return surface


def write_moved_surface(path: str | os.PathLike[str], surface: SurfaceData, vertices: np.ndarray, arrays: dict,
                        force: bool = False) -> None:
    """``surface``'s faces on moved ``vertices`` with per-vertex ``arrays``, as VTK/VTP in LPS.

    Parameters
    ----------
    path : path-like
        ``.vtk`` or ``.vtp``.
    surface : SurfaceData
        Gives the faces (none for a point cloud).
    vertices : (N, 3) float ndarray
        The moved vertices, LPS mm, in ``surface``'s order.
    arrays : dict of str to (N, ...) ndarray
        Per-vertex arrays (may be empty).
    force : bool, default False
        Replace an existing file.
    """
    io.write_mesh(vertices, surface.triangles, path, point_data=arrays or None, force=force, allow_points=True)


def write_moved_gifti_surface(path: str | os.PathLike[str], surface: SurfaceData, vertices: np.ndarray,
                              force: bool = False) -> None:
    """``surface``'s faces on moved ``vertices`` as a GIFTI surface in RAS, with ``surface``'s metadata.

    Parameters
    ----------
    path : path-like
        ``.surf.gii``.
    surface : SurfaceData
        Gives the faces and the GIFTI metadata (none for a surface not read from GIFTI).
    vertices : (N, 3) float ndarray
        The moved vertices, LPS mm (written as RAS).
    force : bool, default False
        Replace an existing file.
    """
    write_gifti(vertices, surface.triangles, path, meta=surface.gifti, force=force)


def is_label_array(surface: SurfaceData, name: str) -> bool:
    """Whether ``surface``'s per-vertex array ``name`` holds labels: integers, or a GIFTI label array."""
    meta = surface.array_meta.get(name)
    return np.asarray(surface.arrays[name]).dtype.kind in "iub" or (meta is not None and meta.is_label)


def vertex_array_meta(surface: SurfaceData, name: str) -> GiftiArrayMeta:
    """The GIFTI metadata of ``surface``'s array ``name``: as read, or a bare one (``label`` or
    ``shape``, by :func:`is_label_array`) for an array not read from GIFTI."""
    meta = surface.array_meta.get(name)
    if meta is not None:
        return meta
    return GiftiArrayMeta(kind="label" if is_label_array(surface, name) else "shape")


def data_file_name(stem: str, name: str, meta: GiftiArrayMeta) -> str:
    """``<stem>.<name>.<kind>.gii``, with characters unsafe in file names replaced by ``_``."""
    safe = re.sub(r"[^A-Za-z0-9._+-]", "_", name) or "array"
    return f"{stem}.{safe}.{meta.kind}.gii"


def _check_result_kind(result: Path, option: str) -> None:
    """Refuse an OUTDIR whose report.json says another command than ``register-surfaces`` wrote it.

    A label-volume registration (``volreg register``) saves a 3-D ``model.npz`` too, of fixed
    points to moving points: taken for a surface registration it would carry values between
    unrelated surfaces without a word.  A folder without a report (a model copied alone), or
    with one that is not JSON, is left to the model's own checks.
    """
    import json

    from volreg.io.documents import parse_json

    report = result / "report.json"
    try:
        data = parse_json(report.read_text(encoding="utf-8"), f"{option} `{result}`: report.json", error=UsageError)
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return
    if not isinstance(data, dict):
        return
    command = data.get("command")
    inputs = data.get("inputs")
    labels = command == "register" or (command is None and isinstance(inputs, dict) and "fixed" in inputs)
    if labels:
        raise UsageError(f"{option} `{result}` is a label-volume registration (its report.json says `volreg "
                         "register`); expected a surface registration from `volreg register-surfaces`.")
    if isinstance(command, str) and command != "register-surfaces":
        raise UsageError(f"{option} `{result}` was written by `volreg {' '.join(command.split())[:40]}` (its "
                         "report.json says so); expected a surface registration from `volreg register-surfaces`.")


def load_surface_model(result: str | os.PathLike[str], option: str = "--result") -> KernelWarp:
    """The 3-D warp saved in a ``volreg register-surfaces`` output folder.

    Parameters
    ----------
    result : path-like
        The folder; its ``model.npz`` is read.  A folder whose ``report.json`` names another
        command (a label-volume registration saves a 3-D model too) is refused.
    option : str, default "--result"
        The argument's name in messages.

    Returns
    -------
    KernelWarp
        Source points -> target points, LPS mm.

    Raises
    ------
    UsageError
        No ``model.npz`` there, a folder another command wrote, or a warp that is not 3-D.
    """
    result = Path(result)
    model = result / "model.npz"
    if not model.is_file():
        raise UsageError(f"`{result}` has no model.npz; expected an OUTDIR written by `volreg register-surfaces`.")
    _check_result_kind(result, option)
    warp = KernelWarp.load(model)
    if warp.dim != 3:
        raise UsageError(f"`{model}` is a {warp.dim}-D warp; expected a 3-D surface registration.")
    return warp


# ----------------------------------------------------------------------------- register-surfaces

@dataclass
class WrittenSurfaceRegistration:
    """What :func:`write_surface_registration` wrote.

    Attributes
    ----------
    report : dict
        The contents of ``report.json`` (before :func:`~volreg.io.summary.json_safe`).
    warp : KernelWarp
        The fitted warp, source points -> target points, LPS mm.
    files : int
        How many files were written.
    """

    report: dict
    warp: KernelWarp
    files: int


@dataclass
class _SurfaceFit:
    """The warped source and the figures the review and the report take from it."""

    warped: np.ndarray  # (N, 3) mm: tau at every source vertex
    jacobian: np.ndarray  # (N, 3, 3)
    closest: np.ndarray  # (N, 3) mm: the target point nearest to each warped vertex
    distance: np.ndarray  # (N,) mm: how far that is
    gaps: np.ndarray  # the distances the review judges
    measured: str  # what they measure (GAPS_MEASURED)
    target_diameter: float
    landmark_error: np.ndarray | None  # (L,) mm
    findings: list[Finding]


def _review_surface_fit(warp: KernelWarp, source: SurfaceData, target: SurfaceData, landmarks,
                        limits: SurfaceReviewLimits) -> _SurfaceFit:
    """The warp at the source vertices, their distances to the target, and the review's findings."""
    warped, jac = warp.evaluate(source.vertices, order=1)
    closest, distance, _ = closest_points(warped, target.vertices, target.triangles)  # per vertex, for the table
    # a point cloud TARGET is a sample of its surface: the review allows for the samples' spacing
    gaps, measured = (distance, "source_to_target") if len(target.triangles) else \
        surface_gaps(warped, target.vertices, target.triangles)
    target_diameter = diameter(target.vertices)
    findings = review_surface_distance(gaps, target_diameter, limits, measured=measured,
                                       hint="Check that SOURCE and TARGET are in the same frame and unit, and turned "
                                            "alike (surfaces are aligned by their centroids only).")
    findings += review_surface_translation(warp.linear.translation, diameter(source.vertices), limits)
    landmark_error = None
    if landmarks is not None:
        landmark_error = np.linalg.norm(warp(landmarks[0]) - landmarks[1], axis=1)
        off = np.maximum(closest_points(landmarks[0], source.vertices, source.triangles)[1],
                         closest_points(landmarks[1], target.vertices, target.triangles)[1])
        findings += review_landmarks(landmark_error, target_diameter, limits, off_surface=off)
    return _SurfaceFit(warped, jac, closest, distance, gaps, measured, target_diameter, landmark_error, findings)


def _surface_registration_report(fit: _SurfaceFit, warp: KernelWarp, source: SurfaceData, target: SurfaceData,
                                 protocol: Protocol, names: Sequence[str], limits: SurfaceReviewLimits,
                                 source_path, target_path, source_data) -> dict:
    """``report.json``'s contents, but for its ``seconds``."""
    gaps = fit.gaps
    report = {
        "volreg_version": __version__,
        "command": "register-surfaces",
        "inputs": {"source": {"path": str(source_path), "sha256": file_sha256(source_path),
                              "vertices": len(source.vertices), "triangles": len(source.triangles),
                              "data": [{"path": str(p), "sha256": file_sha256(p)} for p in source_data]},
                   "target": {"path": str(target_path), "sha256": file_sha256(target_path),
                              "vertices": len(target.vertices), "triangles": len(target.triangles)}},
        "direction": "source vertex v corresponds to target point tau(v) (LPS mm)",
        "frames": {name: FRAMES[Path(name).suffix] for name in names if Path(name).suffix in FRAMES},
        "distance_to_target_mm": {"mean": float(gaps.mean()), "median": float(np.median(gaps)),
                                  "p95": float(np.percentile(gaps, 95)), "max": float(gaps.max()),
                                  "measured": fit.measured},
        "target_diameter_mm": fit.target_diameter,
        # the centroids' translation the warp starts from (register_surfaces' align_centroids), or zeros
        "translation_mm": [float(v) for v in warp.linear.translation],
        "source_diameter_mm": diameter(source.vertices),
        "review": {"plausible": not fit.findings, "findings": [f.to_dict() for f in fit.findings],
                   "limits": asdict(limits)},
        "folded_fraction_at_vertices": float(np.mean(np.linalg.det(fit.jacobian) <= 0)),
        "protocol": protocol.to_dict(),
        "versions": package_versions(),
    }
    if fit.landmark_error is not None:
        err = fit.landmark_error
        report["landmark_error"] = {"mean_mm": float(err.mean()), "max_mm": float(err.max()),
                                    "mean_percent_of_diameter": float(100 * err.mean() / fit.target_diameter)}
    return report


def _correspondence_csv(source: SurfaceData, fit: _SurfaceFit) -> str:
    """``correspondence.csv``: each source vertex, where the warp sends it, and the target point nearest there."""
    table = StringIO()
    w = csv.writer(table, lineterminator="\n")
    w.writerow(["vertex", "x", "y", "z", "tau_x", "tau_y", "tau_z", "target_x", "target_y", "target_z", "distance_mm"])
    for i in range(len(fit.warped)):
        # shortest round-trip text of each float: six digits would round coordinates far from
        # the origin (1e6 mm) to several millimetres
        w.writerow([i, *map(float, source.vertices[i]), *map(float, fit.warped[i]), *map(float, fit.closest[i]),
                    float(fit.distance[i])])
    return table.getvalue()


def _write_surface_registration_files(folder: OutputFolder, paths: dict[str, Path], warp: KernelWarp,
                                      source: SurfaceData, fit: _SurfaceFit, force: bool) -> None:
    """The model, the warped source (VTK, and GIFTI where asked) and the table, each recorded once written."""
    warp.save(paths["model.npz"], force=force)
    folder.record(paths["model.npz"])
    write_moved_surface(paths["warped.vtk"], source, fit.warped, source.arrays, force)
    folder.record(paths["warped.vtk"])
    if SURFACE_REGISTRATION_GIFTI in paths:
        write_moved_gifti_surface(paths[SURFACE_REGISTRATION_GIFTI], source, fit.warped, force)
        folder.record(paths[SURFACE_REGISTRATION_GIFTI])
    io.write_text(_correspondence_csv(source, fit), paths["correspondence.csv"], force=force)
    folder.record(paths["correspondence.csv"])


def write_surface_registration(
    source: SurfaceData,
    target: SurfaceData,
    outdir: str | os.PathLike[str],
    *,
    protocol: Protocol,
    source_path: str | os.PathLike[str],
    target_path: str | os.PathLike[str],
    source_data: Sequence[str | os.PathLike[str]] = (),
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    gifti: bool = False,
    force: bool = False,
    progress: ProgressCallback | None = None,
    on_findings: Callable[[list[Finding]], None] | None = None,
    started: float | None = None,
) -> WrittenSurfaceRegistration:
    """Register ``source`` to ``target`` and write every output into ``outdir``, all or nothing.

    The outputs (:data:`SURFACE_REGISTRATION_OUTPUTS`, and :data:`SURFACE_REGISTRATION_GIFTI` with
    ``gifti``) are checked to be writable before the registration starts.

    Parameters
    ----------
    source, target : SurfaceData
        The surfaces, LPS mm (:func:`read_surface_with_data`).
    outdir : path-like
        The output folder.
    protocol : Protocol
        Its ``warp`` settings.
    source_path, target_path : path-like
        The files the surfaces were read from (the report records them and their checksums;
        errors name them).
    source_data : sequence of path-like
        The GIFTI data files read onto ``source`` (recorded in the report).
    landmarks : pair of (L, 3) float ndarrays, optional
        Source points and their target partners, LPS mm.
    gifti : bool, default False
        Also write the warped source as a GIFTI surface (RAS mm).
    force : bool, default False
        Write into a folder that is not empty, replacing outputs.
    progress : callable, optional
        ``progress(stage, done, total)``.
    on_findings : callable, optional
        Called with the plausibility review's findings (a list, maybe empty) once the warp is
        fitted, before any file is written; default: each one a
        :class:`~volreg.errors.VolregWarning`.
    started : float, optional
        The :func:`time.perf_counter` value the report's ``seconds`` count from (default: now).

    Returns
    -------
    WrittenSurfaceRegistration
    """
    start = time.perf_counter() if started is None else started
    names = SURFACE_REGISTRATION_OUTPUTS + ((SURFACE_REGISTRATION_GIFTI,) if gifti else ())
    limits = SurfaceReviewLimits()
    with output_folder(outdir, force, outputs=(*SURFACE_REGISTRATION_OUTPUTS, SURFACE_REGISTRATION_GIFTI)) as folder:
        paths = folder.check_writable(names, force=force)  # in staging, swapped into outdir at the end
        # surfaces of other sizes (units) are refused by register_surface_pair
        warp = register_surface_pair(source, target, protocol, landmarks, progress,
                                     names=(f"SOURCE `{source_path}`", f"TARGET `{target_path}`"))
        fit = _review_surface_fit(warp, source, target, landmarks, limits)
        (on_findings or _issue_findings)(fit.findings)
        report = _surface_registration_report(fit, warp, source, target, protocol, names, limits, source_path,
                                              target_path, source_data)
        _write_surface_registration_files(folder, paths, warp, source, fit, force)
        report["seconds"] = time.perf_counter() - start
        io.write_json(json_safe(report), paths["report.json"], force=force)
        folder.record(paths["report.json"])
    return WrittenSurfaceRegistration(report=report, warp=warp, files=len(folder.written))


# ----------------------------------------------------------------------------- label surfaces

@dataclass
class WrittenLabelSurfaces:
    """What :func:`write_label_surfaces` wrote.

    Attributes
    ----------
    labels : list of int
        The labels that gave a surface, ascending.
    summary : dict
        The contents of ``surface.json``.
    files : int
        How many files were written.
    """

    labels: list[int]
    summary: dict
    files: int


def _boundary_meshes(volume: LabelVolume, labels: Sequence[int], image_path, *, skip_small: bool, smoothing: float,
                     progress: ProgressCallback | None, warn: Callable[[str], None] | None) -> dict:
    """Each label's boundary mesh (:func:`volreg.features.label_surfaces.label_surfaces`); the warnings
    for labels skipped passed to ``warn`` (or left to the caller's filters without it)."""
    on_small = "warn" if skip_small else "error"
    try:
        if warn is None:
            surfaces = surface_features.label_surfaces(volume, labels, on_small=on_small, smoothing=smoothing,
                                                       progress=progress)
        else:
            with warnings.catch_warnings(record=True) as caught:
                # label_surfaces warns for each label it skips (on_small="warn").
                warnings.simplefilter("always")
                surfaces = surface_features.label_surfaces(volume, labels, on_small=on_small, smoothing=smoothing,
                                                           progress=progress)
            for w in caught:
                warn(str(w.message))
    except SurfaceError as exc:
        if "min_voxels" not in str(exc):
            raise
        # a stray speck of a label, common in segmentations
        raise UsageError(f"{str(exc).rstrip('.')} in `{image_path}`, too few for a surface; pass "
                         "--skip-small to skip such labels, or --labels to choose the labels.") from exc
    if not surfaces:
        raise UsageError(f"No label of `{image_path}` gave a surface; nothing to write.")
    return surfaces


def _fit_implicit_surfaces(volume: LabelVolume, surfaces: dict, names: dict[str, dict[int, Path]],
                           min_width_voxels: float, progress: ProgressCallback | None) -> tuple[dict, list[dict]]:
    """Each label's implicit surface, one at a time, and its record for ``surface.json``."""
    records = []
    implicit = {}
    for i, (label, surf) in enumerate(surfaces.items()):
        t0 = time.perf_counter()
        implicit[label] = surface_features.implicit_surfaces(volume, {label: surf},
                                                             min_width_voxels=min_width_voxels)[label]
        fit_seconds = time.perf_counter() - t0
        model = implicit[label]
        records.append(
            {
                "label": int(label),
                "mesh": names["mesh"][label].name,
                **({"gifti": names["gifti"][label].name} if names["gifti"] else {}),
                "sdf": names["sdf"][label].name,
                "vertices": int(len(surf.vertices)),
                "cells": int(len(surf.cells)),
                "smoothing_mm": float(surf.smoothing),
                "levels": [float(w) for w in model.widths],
                "centres": int(sum(len(level.centres) for level in model.levels)),
                "fit_seconds": round(fit_seconds, 3),
            }
        )
        if progress is not None:
            progress("fit implicit surfaces", i + 1, len(surfaces))
    return implicit, records


def _write_label_surface_files(folder: OutputFolder, volume: LabelVolume, surfaces: dict, implicit: dict,
                               paths: dict[str, dict[int, Path]], force: bool,
                               progress: ProgressCallback | None) -> None:
    """Each label's mesh (and GIFTI surface) and signed distance on the volume's grid, recorded once written."""
    for i, (label, surf) in enumerate(surfaces.items()):
        io.write_mesh(surf.vertices, surf.cells, paths["mesh"][label], normals=surf.normals, force=force)
        folder.record(paths["mesh"][label])
        if paths["gifti"]:
            write_gifti(surf.vertices, surf.cells, paths["gifti"][label], meta=_SCANNER_RAS, force=force)
            folder.record(paths["gifti"][label])
        sdf = surface_features.implicit_on_grid(implicit[label], volume)
        io.write_scalar(sdf, volume, paths["sdf"][label], force=force)
        folder.record(paths["sdf"][label])
        if progress is not None:
            progress("sample and write", i + 1, len(surfaces))


def _surface_summary(volume: LabelVolume, image_path, records: list[dict], *, skipped: list[int], smoothing: float,
                     min_width_voxels: float, skip_small: bool, seconds: float) -> dict:
    """``surface.json``'s contents: the input and its grid, the parameters, one record per label."""
    return {
        "volreg_version": __version__,
        "command": "surface",
        "input": str(image_path),
        "grid": {
            "shape": [int(n) for n in volume.shape],
            "origin_mm": volume.origin.tolist(),
            "spacing_mm": volume.spacing.tolist(),
            "direction": volume.direction.tolist(),
            "frame": "LPS",
        },
        "parameters": {
            "smoothing_voxels": smoothing,
            "min_width_voxels": min_width_voxels,
            "skip_small": bool(skip_small),
        },
        "labels": records,
        "skipped": skipped,
        "seconds": seconds,
    }


def write_label_surfaces(
    volume: LabelVolume,
    labels: Sequence[int],
    outdir: str | os.PathLike[str],
    *,
    image_path: str | os.PathLike[str],
    requested: Sequence[int] | None = None,
    skip_small: bool = False,
    smoothing: float = _SURFACE_DEFAULTS.smoothing,
    min_width_voxels: float = _SURFACE_DEFAULTS.min_width_voxels,
    gifti: bool = False,
    force: bool = False,
    progress: ProgressCallback | None = None,
    warn: Callable[[str], None] | None = None,
    started: float | None = None,
) -> WrittenLabelSurfaces:
    """Boundary meshes, implicit surfaces (paper Section 4) and their signed distances of ``labels``.

    Writes into ``outdir``, all or nothing: ``label_<id>.vtk`` (LPS mm, outward normals; line
    segments for a 2-D volume), with ``gifti`` ``label_<id>.surf.gii`` (scanner RAS mm),
    ``sdf_<id>.nii.gz`` (the implicit surface sampled on the volume's grid: float32 signed
    distance, mm, negative inside) and ``surface.json``.  Existing outputs are refused one by one
    (unless ``force``) before any work, other files of ``outdir`` kept.

    Parameters
    ----------
    volume : LabelVolume
    labels : sequence of int
        The labels to process, each present in ``volume``.
    outdir : path-like
        The output folder (created if missing).
    image_path : path-like
        The file ``volume`` was read from (``surface.json`` records it; errors name it).
    requested : sequence of int, optional
        The labels asked for, if a choice was made (``surface.json``'s ``skipped`` lists those of
        them that gave no surface); default ``labels``.
    skip_small : bool, default False
        Skip labels too small for a surface (with a warning) instead of refusing them.
    smoothing : float
        Gaussian blur (s.d.) of each mask before contouring, in units of the largest voxel spacing.
    min_width_voxels : float
        The implicit surfaces' finest kernel width, in units of the largest voxel spacing.
    gifti : bool, default False
        Also write each mesh as GIFTI (3-D volumes only).
    force : bool, default False
        Replace existing outputs.
    progress : callable, optional
        ``progress(stage, done, total)``.
    warn : callable, optional
        ``warn(message)`` for each label skipped; default: the warnings are left to the caller's filters.
    started : float, optional
        The :func:`time.perf_counter` value ``surface.json``'s ``seconds`` count from (default: now).

    Returns
    -------
    WrittenLabelSurfaces

    Raises
    ------
    UsageError
        A label too small for a surface without ``skip_small``, or no label giving one.
    """
    start = time.perf_counter() if started is None else started
    outdir = Path(outdir)
    names = {"mesh": {v: outdir / f"label_{v}.vtk" for v in labels},
             "gifti": {v: outdir / f"label_{v}.surf.gii" for v in labels} if gifti else {},
             "sdf": {v: outdir / f"sdf_{v}.nii.gz" for v in labels}}
    summary_name = "surface.json"
    # Existing outputs are refused one by one (check_writable), not the folder as a whole.
    with output_folder(outdir, force, require_empty=False, outputs=LABEL_SURFACE_OUTPUTS) as folder:
        folder.check_writable([p.name for kind in names.values() for p in kind.values()] + [summary_name],
                              force=force)
        # written into the run's staging folder, swapped into outdir at the end
        paths = {kind: {v: folder.path / p.name for v, p in each.items()} for kind, each in names.items()}
        surfaces = _boundary_meshes(volume, labels, image_path, skip_small=skip_small, smoothing=smoothing,
                                    progress=progress, warn=warn)
        implicit, records = _fit_implicit_surfaces(volume, surfaces, paths, min_width_voxels, progress)
        _write_label_surface_files(folder, volume, surfaces, implicit, paths, force, progress)
        skipped = [int(v) for v in (requested or labels) if v not in surfaces]
        summary = _surface_summary(volume, image_path, records, skipped=skipped, smoothing=smoothing,
                                   min_width_voxels=min_width_voxels, skip_small=skip_small,
                                   seconds=round(time.perf_counter() - start, 3))
        io.write_json(summary, folder.path / summary_name, force=force)
        folder.record(folder.path / summary_name)
    return WrittenLabelSurfaces(labels=sorted(surfaces), summary=summary, files=len(folder.written))


# ----------------------------------------------------------------------------- transfer

def select_vertex_array(surface: SurfaceData, name: str | None, role: str) -> str:
    """The per-vertex array of ``surface`` to transfer: ``name``, or its only one.

    Parameters
    ----------
    surface : SurfaceData
    name : str or None
        The array asked for (``--array``); ``None`` takes the surface's only array.
    role : str
        How errors name the surface, e.g. ``TARGET `b.vtk```.

    Returns
    -------
    str
        The array's name.

    Raises
    ------
    UsageError
        No such array, none or several without ``name``, or values that are not finite numbers.
    """
    available = ", ".join(sorted(surface.arrays)) or "none"
    if name is None:
        if len(surface.arrays) != 1:
            raise UsageError(f"--array is needed: {role} has {len(surface.arrays)} per-vertex arrays "
                             f"({available}); expected exactly one without --array.")
        name = next(iter(surface.arrays))
    elif name not in surface.arrays:
        raise UsageError(f"--array `{name}` is not a per-vertex array of {role}; it has: {available}.")
    data = np.asarray(surface.arrays[name])
    if data.dtype.kind not in "iubf":
        raise UsageError(f"Per-vertex array `{name}` of {role} holds {data.dtype} values; expected "
                         "numbers (scalars, vectors or integer labels).")
    if data.dtype.kind == "f" and not np.all(np.isfinite(data)):
        raise UsageError(f"Per-vertex array `{name}` of {role} holds "
                         f"{int(np.count_nonzero(~np.isfinite(data)))} NaN/Inf values; expected finite per-vertex "
                         "values (interpolation would spread them to their neighbours).")
    return name


@dataclass
class TransferredArray:
    """What :func:`write_transferred_array` wrote.

    Attributes
    ----------
    method : {"nearest", "barycentric"}
        How the values were taken (labels always from the nearest vertex).
    vertices : int
        How many source vertices received a value.
    median_gap_mm : float
        The median distance of the warped source from the target, mm.
    measured : str
        What that distance measures (a key of :data:`~volreg.evaluation.surface_review.GAPS_MEASURED`).
    """

    method: str
    vertices: int
    median_gap_mm: float
    measured: str


def write_transferred_array(source: SurfaceData, target: SurfaceData, warp: KernelWarp, name: str,
                            output: str | os.PathLike[str], *, method: str = "barycentric", force: bool = False,
                            on_findings: Callable[[list[Finding]], None] | None = None) -> TransferredArray:
    """Carry ``target``'s per-vertex array ``name`` onto ``source`` through ``warp`` and write it.

    Each source vertex v takes the value at the target point nearest to tau(v) (interpolated in
    the nearest triangle, or the nearest vertex's; labels always the nearest vertex's).

    Parameters
    ----------
    source, target : SurfaceData
        LPS mm.
    warp : KernelWarp
        Source points -> target points (:func:`load_surface_model`).
    name : str
        The array (:func:`select_vertex_array`).
    output : path-like
        ``.vtk`` or ``.vtp`` (``source`` with every array and the new one, LPS mm), or a GIFTI data
        file (the array alone, with the metadata of ``target``'s array and ``source``'s structure).
    method : {"barycentric", "nearest"}
        For arrays that are not labels.
    force : bool, default False
        Replace an existing ``output``.
    on_findings : callable, optional
        Called, before the values are taken, with the review's findings (sizes in other units, the
        warped source far from the target, a large starting translation); default: each one a
        :class:`~volreg.errors.VolregWarning`.

    Returns
    -------
    TransferredArray
    """
    findings = review_surface_extents(source.vertices, target.vertices)
    warped = warp(source.vertices)
    gaps, measured = surface_gaps(warped, target.vertices, target.triangles)
    findings += review_surface_distance(
        gaps, diameter(target.vertices), measured=measured,
        hint="Check that SOURCE and TARGET are the surfaces registered in --result, read in the same frame.")
    findings += review_surface_translation(warp.linear.translation, diameter(source.vertices))
    (on_findings or _issue_findings)(findings)
    method = "nearest" if is_label_array(target, name) else method
    values = transfer_values(warped, target.vertices, target.triangles, target.arrays[name], method=method)
    if is_gifti(output):
        structure = source.gifti.structure() if source.gifti is not None else None
        write_gifti_data(values, output, meta=vertex_array_meta(target, name), structure=structure, force=force)
    else:
        arrays = dict(source.arrays)
        arrays[name] = values
        io.write_mesh(source.vertices, source.triangles, output, point_data=arrays, force=force, allow_points=True)
    return TransferredArray(method=method, vertices=len(values), median_gap_mm=float(np.median(gaps)),
                            measured=measured)
