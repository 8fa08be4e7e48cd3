"""An unbiased template of a cohort's label maps, with every subject's registration to it.

:func:`build_template` (and ``volreg template``):

1. **Linear start.**  Every subject is aligned to a provisional reference (the first subject)
   by the affine stage of ``register``; the template's pose is the log-Euclidean mean of those
   maps (:func:`~volreg.pipeline.template_shape.mean_linear_map`), so that the subjects' maps from
   the template average to the identity and no subject's position or size is privileged.  (A
   medoid pose would need every pair registered; the mean needs one map per subject.)  The grid
   has the finest input spacing (or ``spacing``) and holds every aligned subject.  The first
   template is the labels of the *medoid* subject read through its map into that mean pose (nearest
   neighbour, which keeps a thin structure's volume where interpolating labels thins it): the
   subject with the largest mean Dice to the others once all are read through their maps
   (:func:`~volreg.pipeline.template_shape.medoid`).  Not their vote: where the subjects differ by
   more than a structure's thickness after the linear stage (a thin shell, a thin gap), no label
   has the majority there and the vote loses the structure; the registrations to a template
   without it cannot align it, so no later round brings it back.  One subject's labels hold every
   structure.  Starting from one subject's shape does not bias the result: the pose is the mean's,
   and every round moves the template by the subjects' mean displacement, so that it ends at the
   cohort's mean shape wherever it starts (the fixed point of step 2); the medoid starts nearest
   that mean, with the fewest rounds to go.
2. **Iterations.**  Every subject is registered to the current template (``volreg register
   TEMPLATE SUBJECT``, as Dask tasks by :func:`volreg.cohort.register_cohort`, resumable).  Each
   registration gives the pull-back field ``u_i`` on the template grid (template point ``x``
   corresponds to subject point ``x + u_i(x)``) and the subject in template space.  Their mean
   ``u_bar`` is the template's offset from the cohort's mean shape: the next template is moved by
   ``phi(x) = x + u_bar(x)`` (its inverse by fixed-point iteration on the grid), as the vote of
   the subjects each read once from its own labels, by nearest neighbour, at
   ``phi^-1(y) + u_i(phi^-1(y))`` (its registration composed with the inverse update; not the
   warped subjects resampled again, which would blur the labels twice).  The vote keeps each
   label's mean volume over the subjects (:func:`~volreg.pipeline.template_shape.vote_volumes`):
   the majority would thin a structure at its edges, wherever the registrations' residual
   disagreement is a fair part of its thickness, and the next round would register to the thinner
   one.  The iterations stop when the mean of ``|u_bar|`` over the template's
   labels is at most ``tolerance`` (the template is then the cohort's mean: the subjects'
   displacements average to about zero over it), when it no longer falls (the registrations'
   own error and the labels' voxels set a floor to it), or after ``iterations``.
3. **Outputs** (``OUT``): ``template.nii.gz`` (the last template registered to), ``probabilities.nii.gz``
   (4-D: one frame per label, the fraction of subjects with that label at each voxel, from that last
   registration), ``subjects/<id>/`` (each subject's registration to ``template.nii.gz``, the files of
   ``volreg register``), ``report.json`` and ``report.png`` (per iteration: the update's mean and maximum,
   the subjects' mean Dice to the template, each label's probability sharpness; the subjects ranked by
   their distance to the template, outliers named; timings).  The work of the iterations is in
   ``OUT/iterations/`` until the template is complete; a rerun continues from there.
"""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from volreg import __version__
from volreg.cohort import read_manifest, register_cohort
from volreg.errors import TemplateError, UsageError, VolregError
from volreg.evaluation.metrics import dice
from volreg.grid import Grid, LabelVolume
from volreg.io import read_labels, write_json, write_labels, write_text
from volreg.io.fields import read_displacement
from volreg.io.frames import write_frames
from volreg.io.protocol import load_protocol
from volreg.linear_map import LinearMap
from volreg.pipeline.template_shape import (
    invert_displacement, mean_linear_map, medoid, pull_back_points, rank_subjects, sharpness, template_grid,
    vote_volumes,
)
from volreg.warp.linear import fit_linear
from volreg.warp.resample import resample_labels

__all__ = ["TEMPLATE_OUTPUTS", "TemplateResult", "build_template"]

#: The files ``build_template`` writes in ``OUT`` besides ``subjects/``.
TEMPLATE_OUTPUTS = ("template.nii.gz", "probabilities.nii.gz", "labels.csv", "report.json", "report.png")
#: Largest template (voxels x labels) the vote counts may hold: 2 bytes each.
MAX_COUNT_CELLS = 3_000_000_000
_PAIR = "template__{}"

ProgressCallback = Callable[[str, int, int], None]


@dataclass
class TemplateResult:
    """What :func:`build_template` made.

    Attributes
    ----------
    template : LabelVolume
        The template labels (``OUT/template.nii.gz``).
    probabilities : (L, *shape) float32 ndarray
        Per label of ``labels``, the fraction of subjects with it at each template voxel.
    labels : list of int
    subjects : dict of str to Path
        Each subject's registration folder (``OUT/subjects/<id>``).
    report : dict
        ``OUT/report.json``.
    """

    template: LabelVolume
    probabilities: np.ndarray
    labels: list[int]
    subjects: dict[str, Path] = field(default_factory=dict)
    report: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- the linear start


def _subjects(subjects, outdir: Path) -> tuple[Path, list[tuple[str, Path]]]:
    """The manifest and its (id, path) rows: ``subjects`` is a manifest path, or a mapping of ids
    to label volumes or paths (written to ``OUT/iterations/manifest.csv``, volumes under
    ``OUT/iterations/inputs/``)."""
    if isinstance(subjects, (str, os.PathLike)):
        manifest = Path(subjects)
        return manifest, read_manifest(manifest)
    if not isinstance(subjects, Mapping) or not subjects:
        raise UsageError(f"Expected `subjects` as a manifest path or a non-empty mapping of ids to label volumes "
                         f"or paths, got {type(subjects).__name__}.")
    work = outdir / "iterations"
    (work / "inputs").mkdir(parents=True, exist_ok=True)
    rows = []
    for sid, value in subjects.items():
        if isinstance(value, LabelVolume):
            path = work / "inputs" / f"{sid}.nii.gz"
            write_labels(value, path, force=True)
        elif isinstance(value, (str, os.PathLike)):
            path = Path(value).resolve()
        else:
            raise UsageError(f"Expected subject `{sid}` as a LabelVolume or a path, got {type(value).__name__}.")
        rows.append((str(sid), path))
    manifest = work / "manifest.csv"
    with open(manifest, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "path"])
        w.writerows([(sid, str(p)) for sid, p in rows])
    return manifest, read_manifest(manifest)


def _linear_start(rows, kind: str, work: Path, progress) -> dict[str, LinearMap]:
    """Each subject's map from the template's coordinates (the subjects' mean pose) to its own:
    ``A_i = L_i o M^-1`` for ``L_i`` the affine map from the first subject to subject i and ``M``
    their mean.  Kept in ``work``/linear.json (read again on a rerun)."""
    saved = work / "linear.json"
    if saved.is_file():
        data = json.loads(saved.read_text())
        if data.get("ids") == [sid for sid, _ in rows] and data.get("kind") == kind:
            return {sid: LinearMap(np.array(m["matrix"]), np.array(m["translation"])) for sid, m in data["maps"].items()}
    reference = read_labels(rows[0][1])
    maps = {}
    for i, (sid, path) in enumerate(rows):
        if i == 0:
            maps[sid] = LinearMap.identity(reference.ndim)
        else:
            try:
                maps[sid] = fit_linear(reference, read_labels(path), kind=kind).map
            except (ValueError, VolregError) as exc:
                raise UsageError(f"Subject `{sid}` ({path}) cannot be aligned to the first subject `{rows[0][0]}`: "
                                 f"{exc}") from None
        if progress is not None:
            progress("template linear start", i + 1, len(rows))
    mean = mean_linear_map(list(maps.values()))
    to_subject = {sid: mean.inverse().then(m) for sid, m in maps.items()}
    write_json({"kind": kind, "ids": [sid for sid, _ in rows],
                "maps": {sid: {"matrix": m.matrix.tolist(), "translation": m.translation.tolist()}
                         for sid, m in to_subject.items()}}, saved, force=True)
    return to_subject


def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    bits = np.array(list(np.ndindex(*([2] * len(lo)))), dtype=float)
    return lo + bits * (hi - lo)


def _first_template(rows, to_subject: dict[str, LinearMap], spacing: float | None, progress):
    """The template grid, its labels, the first template (the medoid subject read through its
    linear map, the module notes) and the start's record (the medoid, each subject's mean Dice to
    the others)."""
    volumes = {}
    boxes = []
    finest = np.inf
    for sid, path in rows:
        v = read_labels(path)
        pts = v.grid_points()[v.array > 0]
        if len(pts) == 0:
            raise UsageError(f"Subject `{sid}` ({path}) holds no label; expected a label map.")
        finest = min(finest, float(v.spacing.min()))
        half = 0.5 * v.spacing.max()
        corners = to_subject[sid].inverse()(_corners(pts.min(0) - half, pts.max(0) + half))
        boxes.append((corners.min(0), corners.max(0)))
        volumes[sid] = v
    step = float(spacing) if spacing is not None else finest
    grid = template_grid(boxes, step, margin=4 * step)
    labels = sorted({int(x) for v in volumes.values() for x in v.labels() if x != 0})
    cells = int(np.prod(grid.shape)) * len(labels)
    if cells > MAX_COUNT_CELLS:
        raise UsageError(f"The template grid {grid.shape} at {step:g} mm with {len(labels)} labels needs "
                         f"{2 * cells / 1e9:.1f} GB of vote counts; expected at most {2 * MAX_COUNT_CELLS / 1e9:.0f} GB "
                         "(choose a coarser --spacing).")
    y = grid.grid_points().reshape(-1, grid.ndim)
    dtype = np.result_type(np.min_scalar_type(int(max(labels, default=0))), np.uint8)
    aligned = []  # each subject in the mean pose (one byte a voxel for label values up to 255)
    for i, (sid, v) in enumerate(volumes.items()):
        aligned.append(resample_labels(v, to_subject[sid](y), method="nearest").reshape(grid.shape).astype(dtype))
        if progress is not None:
            progress("template first template", i + 1, len(volumes))
    del y
    best, mean_dice = medoid(aligned, np.array(labels))
    ids = list(volumes)
    start = {"first_template": "medoid", "medoid": ids[best],
             "medoid_mean_dice": {sid: float(d) for sid, d in zip(ids, mean_dice)}}
    return grid, labels, aligned[best], start


def _add_votes(counts: np.ndarray, labels: list[int], array: np.ndarray) -> None:
    index = {v: k for k, v in enumerate(labels)}
    for value in np.unique(array):
        if int(value) in index:
            counts[index[int(value)]] += array == value


# ----------------------------------------------------------------------------- the iterations


def _registered(work: Path, rows, grid: Grid, labels: list[int], template: np.ndarray):
    """Read the iteration's registrations: vote counts of the warped subjects, the mean
    displacement, each subject's Dice to the template and distance to the mean."""
    counts = np.zeros((len(labels), *grid.shape), np.uint16)
    mean = np.zeros((*grid.shape, grid.ndim))
    scores = {}
    present = [v for v in labels if (template == v).any()]
    for sid, _ in rows:
        folder = work / "pairs" / _PAIR.format(sid)
        u, g = read_displacement(folder / "warp.nii.gz")
        if not g.same_geometry(grid, atol=1e-3):
            raise TemplateError(f"The registration of `{sid}` in {folder} is not on the template grid; remove "
                                f"{work} and run again.")
        mean += u
        warped = read_labels(folder / "warped.nii.gz").array
        _add_votes(counts, labels, warped)
        scores[sid] = float(np.mean([dice(template == v, warped == v) for v in present])) if present else 0.0
    mean /= len(rows)
    inside = template > 0
    distances = {}
    for sid, _ in rows:
        u, _ = read_displacement(work / "pairs" / _PAIR.format(sid) / "warp.nii.gz")
        distances[sid] = float(np.linalg.norm((u - mean)[inside], axis=1).mean())
    return counts, mean, scores, distances


def _iteration(k: int, work: Path, manifest: Path, rows, grid: Grid, labels, template: np.ndarray, options: dict,
               tolerance: float, previous: float | None):
    """Register every subject to iteration ``k``'s template; its statistics and the next template
    (None when the mean update is at most ``tolerance`` or not below the ``previous`` one)."""
    t0 = time.perf_counter()
    folder = work / f"{k:02d}"
    path = folder / "template.nii.gz"
    if not path.is_file():
        folder.mkdir(parents=True, exist_ok=True)
        write_labels(grid.with_array(template), path, force=True)
    summary = register_cohort(manifest, folder, template=path, **{k: v for k, v in options.items() if k != "warn"})
    failed = {str(r.get("moving_id")): r.get("error") or "no message" for r in summary.failed}
    for sid, error in failed.items():
        options["warn"](f"subject {sid} left out of iteration {k}: its registration to the template failed: {error}")
    rows = [r for r in rows if r[0] not in failed]
    if len(rows) < 2:
        raise TemplateError(f"Registration to the template failed for {len(failed)} subject(s) "
                            f"({', '.join(list(failed)[:5])}); fewer than two are left to average (see "
                            f"{folder / 'batch.csv'}).")
    counts, mean, scores, distances = _registered(folder, rows, grid, labels, template)
    size = np.linalg.norm(mean[template > 0], axis=1)
    stats = {"iteration": k, "update_mean_mm": float(size.mean()), "update_max_mm": float(size.max()),
             "mean_dice": float(np.mean(list(scores.values()))), "dice": scores, "distance_mm": distances,
             "sharpness": {str(v): s for v, s in sharpness(counts, len(rows), template, np.array(labels)).items()},
             "left_out": sorted(failed), "seconds": time.perf_counter() - t0}
    following = None
    if stats["update_mean_mm"] > tolerance and not (previous is not None and stats["update_mean_mm"] >= previous):
        following = _moved_template(folder, rows, grid, labels, invert_displacement(mean, grid), options["progress"])
    return stats, counts, following


def _moved_template(work: Path, rows, grid: Grid, labels: list[int], inverse: np.ndarray, progress) -> np.ndarray:
    """The next template: the subjects' vote keeping each label's mean volume, each subject read once
    from its own file (nearest neighbour) through its registration composed with the inverse shape
    update (``inverse``: ``phi^-1(y) = y + inverse(y)``)."""
    counts = np.zeros((len(labels), *grid.shape), np.uint16)
    for i, (sid, path) in enumerate(rows):
        u, _ = read_displacement(work / "pairs" / _PAIR.format(sid) / "warp.nii.gz")
        points = pull_back_points(grid, inverse, u)
        del u
        _add_votes(counts, labels, resample_labels(read_labels(path), points, method="nearest").reshape(grid.shape))
        if progress is not None:
            progress("template update", i + 1, len(rows))
    return vote_volumes(counts, len(rows), np.array(labels))


def _report_figure(report: dict, path: Path) -> None:
    """Three panels: the update per iteration, the mean Dice per iteration, the subjects' distances."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    from volreg.io import atomic_output

    its = report["iterations"]
    k = [s["iteration"] for s in its]
    fig = Figure(figsize=(12, 3.6))
    FigureCanvasAgg(fig)
    a, b, c = fig.subplots(1, 3)
    a.plot(k, [s["update_mean_mm"] for s in its], "o-", label="mean")
    a.plot(k, [s["update_max_mm"] for s in its], "s-", label="maximum")
    a.axhline(report["tolerance_mm"], color="grey", ls=":", label="tolerance")
    a.set(xlabel="iteration", ylabel="shape update |u_bar| (mm)", title="Template update")
    a.legend()
    b.plot(k, [s["mean_dice"] for s in its], "o-")
    b.set(xlabel="iteration", ylabel="mean Dice, subjects to template", title="Agreement")
    for ax in (a, b):
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ranked = report["ranking"]
    names = [r["id"] for r in ranked]
    colours = ["tab:red" if n in report["outliers"] else "tab:blue" for n in names]
    c.barh(range(len(names)), [r["distance_mm"] for r in ranked], color=colours)
    c.set_yticks(range(len(names)), names, fontsize=7)
    c.invert_yaxis()
    c.set(xlabel="mean |u_i - u_bar| (mm)", title="Subjects' distance (outliers red)")
    fig.tight_layout()
    with atomic_output(path, force=True) as tmp:
        fig.savefig(tmp, format="png", dpi=90)


def _link_tree(source: Path, target: Path) -> None:
    """``target`` a copy of ``source``, files hard-linked where the file system allows."""
    if target.exists():
        shutil.rmtree(target)
    try:
        shutil.copytree(source, target, copy_function=os.link)
    except OSError:
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(source, target)


def build_template(
    subjects,
    outdir: str | os.PathLike[str],
    *,
    iterations: int = 5,
    tolerance: float | None = None,
    spacing: float | None = None,
    linear: str = "affine",
    protocol: str = "default",
    workers: int | None = None,
    scheduler: str | None = None,
    progress: ProgressCallback | None = None,
    notify: Callable[[str], None] | None = None,
    force: bool = False,
    compile_helpers: list | None = None,
    warn: Callable[[str], None] | None = None,
) -> TemplateResult:
    """Build the unbiased template of a cohort's label maps (the module notes) and write it to ``outdir``.

    Parameters
    ----------
    subjects : path-like or mapping
        A manifest (CSV ``id,path``, paths relative to it, as ``volreg batch`` reads), or a mapping
        of ids to :class:`~volreg.grid.LabelVolume` or paths.  At least two subjects.
    outdir : path-like
        Created if missing; a rerun into an unfinished one continues its iterations.
    iterations : int
        At most this many registrations of the cohort to the template (at least 1).
    tolerance : float, optional, mm
        Stop once the shape update's mean ``|u_bar|`` over the template's labels is at most this
        (default: a quarter of the template spacing).
    spacing : float, optional, mm
        The template's isotropic spacing (default: the finest spacing among the subjects).
    linear : {"rigid", "similarity", "affine"}
        The family of the linear start.
    protocol : str
        A preset name or a protocol file, for every registration.
    workers, scheduler
        As for :func:`volreg.cohort.register_cohort`.
    progress : callable, optional
        ``progress(stage, done, total)``.
    notify : callable, optional
        Called with a line of news (an iteration's update).
    force : bool
        Replace a finished template in ``outdir``.
    compile_helpers : list, optional
        As for :func:`volreg.cohort.register_cohort`.
    warn : callable, optional
        Called with a line for each subject left out of an iteration (its registration failed:
        it does not count in that iteration's average).

    Returns
    -------
    TemplateResult

    Raises
    ------
    UsageError
        Bad arguments, fewer than two subjects, or a finished template in ``outdir`` without ``force``.
    TemplateError
        Fewer than two subjects' registrations succeeded in an iteration.
    """
    outdir = Path(outdir)
    _check_request(outdir, iterations, tolerance, spacing, linear, protocol, force)
    outdir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    manifest, rows = _subjects(subjects, outdir)
    if len(rows) < 2:
        raise UsageError(f"MANIFEST `{manifest}` has {len(rows)} subject; expected at least two for a template.")
    work = outdir / "iterations"
    work.mkdir(exist_ok=True)

    t0 = time.perf_counter()
    to_subject = _linear_start(rows, linear, work, progress)
    grid, labels, template, medoid_info = _first_template(rows, to_subject, spacing, progress)
    start_info = {"kind": linear, "reference": rows[0][0],
                  "mean_of": "log-Euclidean mean of the affine maps from the reference", **medoid_info,
                  "seconds": time.perf_counter() - t0}
    tolerance = 0.25 * float(grid.spacing[0]) if tolerance is None else float(tolerance)
    options = {"protocol": protocol, "workers": workers, "scheduler": scheduler, "progress": progress,
               "notify": notify, "compile_helpers": compile_helpers, "warn": warn or (lambda line: None)}
    history, counts = _iterate(work, manifest, rows, grid, labels, template, options, tolerance, iterations, notify)
    report = {"volreg_version": __version__, "command": "template", "linear_start": start_info, "protocol": protocol,
              "tolerance_mm": tolerance}
    return _write_outputs(outdir, work, rows, grid, labels, history, counts, report, start)


def _check_request(outdir: Path, iterations, tolerance, spacing, linear, protocol, force: bool) -> None:
    """Refuse bad arguments, or a finished template in ``outdir`` without ``force`` (whose
    outputs and work are removed with it), before any work."""
    if not isinstance(iterations, int) or isinstance(iterations, bool) or iterations < 1:
        raise UsageError(f"--iterations {iterations!r}: expected a positive integer.")
    for name, value in (("tolerance", tolerance), ("spacing", spacing)):
        if value is not None and not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
            raise UsageError(f"--{name} {value!r}: expected a positive number of mm.")
    if linear not in ("rigid", "similarity", "affine"):
        raise UsageError(f"--linear {linear!r}: expected rigid, similarity or affine.")
    load_protocol(protocol)
    if (outdir / "report.json").exists() and not force:
        raise UsageError(f"OUTDIR `{outdir}` holds a finished template; expected a new folder (or --force to build "
                         "it again).")
    if force:
        for name in TEMPLATE_OUTPUTS:
            (outdir / name).unlink(missing_ok=True)
        shutil.rmtree(outdir / "iterations", ignore_errors=True)
        shutil.rmtree(outdir / "subjects", ignore_errors=True)


def _iterate(work: Path, manifest: Path, rows, grid: Grid, labels, template: np.ndarray, options: dict,
             tolerance: float, iterations: int, notify) -> tuple[list[dict], np.ndarray | None]:
    """The rounds of registration (module notes, step 2): each one's statistics in order, and the
    last round's vote counts where this run registered it (None where an earlier run did).  A round
    an earlier run finished (its ``stats.json`` and the next template on disk) is read, not redone."""
    history, counts = [], None
    for k in range(1, iterations + 1):
        saved = work / f"{k:02d}" / "stats.json"
        nxt = work / f"{k + 1:02d}" / "template.nii.gz"
        if saved.is_file() and (nxt.is_file() or json.loads(saved.read_text()).get("converged")):
            stats = json.loads(saved.read_text())  # done by an earlier run
            history.append(stats)
            if stats.get("converged"):
                break
            template = read_labels(nxt).array
            counts = None
            continue
        previous = history[-1]["update_mean_mm"] if history else None
        stats, counts, following = _iteration(k, work, manifest, rows, grid, labels, template, options, tolerance,
                                              previous)
        stats["converged"] = following is None
        stats["stopped"] = ("tolerance" if stats["update_mean_mm"] <= tolerance else "no progress") \
            if following is None else ("iterations" if k == iterations else None)
        history.append(stats)
        if notify is not None:
            notify(f"template iteration {k}: update mean {stats['update_mean_mm']:.2f} mm, max "
                   f"{stats['update_max_mm']:.2f} mm; mean Dice {stats['mean_dice']:.3f}")
        if following is not None and k < iterations:
            nxt.parent.mkdir(parents=True, exist_ok=True)
            write_labels(grid.with_array(following), nxt, force=True)
        write_json(stats, saved, force=True)  # after the next template: the round is then complete
        if following is None:
            break
        if k < iterations:  # another round: these counts are not the last one's
            template, counts = following, None
    return history, counts


def _write_outputs(outdir: Path, work: Path, rows, grid: Grid, labels, history: list[dict], counts, report: dict,
                   start: float) -> TemplateResult:
    """The template, probabilities, subjects' folders, labels.csv, report.json and report.png
    from the last round (report.json last: it marks the template finished); its vote ``counts``
    read again from its registrations where None."""
    last = history[-1]
    folder = work / f"{last['iteration']:02d}"
    template = read_labels(folder / "template.nii.gz")
    rows = [r for r in rows if r[0] not in set(last.get("left_out", []))]
    if counts is None:
        counts = _registered(folder, rows, grid, labels, template.array)[0]
    probabilities = counts.astype(np.float32) / len(rows)
    ranked, outliers = rank_subjects(last["distance_mm"])
    subjects_out = {}
    for sid, _ in rows:
        subjects_out[sid] = outdir / "subjects" / sid
        _link_tree(folder / "pairs" / _PAIR.format(sid), subjects_out[sid])
    write_labels(template, outdir / "template.nii.gz", force=True)
    write_frames(probabilities, template, outdir / "probabilities.nii.gz", force=True)
    table = io.StringIO()
    w = csv.writer(table, lineterminator="\n")
    w.writerow(["frame", "label", "template_voxels", "sharpness"])
    for i, v in enumerate(labels):
        w.writerow([i, v, int((template.array == v).sum()), last["sharpness"].get(str(v), "")])
    write_text(table.getvalue(), outdir / "labels.csv", force=True)
    report |= {
        "subjects": [{"id": sid, "path": str(Path(p).resolve())} for sid, p in rows],
        "left_out": last.get("left_out", []),
        "template": {"shape": list(grid.shape), "spacing_mm": grid.spacing.tolist(), "origin_mm": grid.origin.tolist(),
                     "labels": labels},
        "converged": last.get("stopped") == "tolerance",
        "stopped": last.get("stopped"),
        "iterations": [{k: v for k, v in s.items() if k not in ("dice", "distance_mm")} for s in history],
        "mean_displacement_mm": {"mean": last["update_mean_mm"], "max": last["update_max_mm"]},
        "ranking": [{"id": s, "distance_mm": last["distance_mm"][s], "dice": last["dice"][s]} for s in ranked],
        "outliers": outliers,
        "seconds": time.perf_counter() - start,
    }
    _report_figure(report, outdir / "report.png")
    write_json(report, outdir / "report.json", force=True)
    for k in range(1, last["iteration"]):  # earlier rounds' registrations: their templates and statistics stay
        shutil.rmtree(work / f"{k:02d}" / "pairs", ignore_errors=True)
    return TemplateResult(template, probabilities, labels, subjects_out, report)
