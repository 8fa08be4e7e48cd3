"""Every output of a cohort's shape models, and of one shape drawn from a model, all or nothing.

:func:`write_shape_models` writes, for each model of a
:class:`~volreg.shape_models.ShapeModelResult` (``OUT/surface/`` and ``OUT/deformation/``):

- ``model.npz`` (:meth:`~volreg.shape_models.LabelShapeModel.save`, read by ``volreg shape-model sample``);
- ``modes.csv`` (``mode,variance,fraction,cumulative``: variance in mm^2, leading first) and
  ``scores.csv`` (``id,mode_1,...,mode_K``: each subject's coefficients in standard deviations);
- ``quality.json`` (compactness, generalization, specificity over M = 1 .. K with standard
  errors; the correspondence both ways) and ``quality.png``;
- ``mean_label<L>.vtk`` and ``mean_label<L>.surf.gii`` per template label, and for each of the
  leading :data:`RENDERED_MODES` modes ``mode_<k>_-2sd`` / ``mode_<k>_+2sd``: the label map
  (``.nii.gz`` on the template grid, as ``volreg apply`` writes labels) and the meshes
  (``_label<L>.vtk``), and ``mode_<k>.gif`` (a slice of the label map, the mean's boundary
  drawn over it, along -2 .. +2 standard deviations);

and ``OUT/report.json`` (the inputs, both models' leading variances and quality, timings).
:func:`write_shape_sample` writes one shape: ``shape.nii.gz`` and ``shape_label<L>.vtk``.
"""

from __future__ import annotations

import csv
import io as _io
import os
from pathlib import Path

import numpy as np

from volreg.io import atomic_output, write_json, write_labels, write_mesh, write_text
from volreg.io._atomic import output_folder
from volreg.io.gifti import write_gifti
from volreg.shape_models import KINDS, LabelShapeModel, ShapeModelResult, build_shape_models

__all__ = ["RENDERED_MODES", "SHAPE_MODEL_OUTPUTS", "build_and_write_shape_models", "write_shape_models",
           "write_shape_sample"]

#: Leading modes whose -2 / +2 standard deviation shapes and GIF are written.
RENDERED_MODES = 3
#: Files of each model's folder (patterns): an earlier run's that this one does not write are removed.
SHAPE_MODEL_OUTPUTS = ("model.npz", "modes.csv", "scores.csv", "quality.json", "quality.png", "mean_label*.vtk",
                       "mean_label*.surf.gii", "mode_*")
#: Frames of a mode's GIF: one period of -2 .. +2 standard deviations.
GIF_FRAMES = 16


def _csv(rows: list[list]) -> str:
    out = _io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    return out.getvalue()


def _modes_table(lsm: LabelShapeModel) -> str:
    m = lsm.model
    fraction = m.fractions()
    rows = [["mode", "variance", "fraction", "cumulative"]]
    rows += [[k + 1, f"{m.variances[k]:.6g}", f"{fraction[k]:.6f}", f"{fraction[:k + 1].sum():.6f}"]
             for k in range(m.n_modes)]
    return _csv(rows)


def _scores_table(lsm: LabelShapeModel) -> str:
    m = lsm.model
    rows = [["id"] + [f"mode_{k + 1}" for k in range(m.n_modes)]]
    rows += [[sid] + [f"{v:.6f}" for v in m.scores[i]] for i, sid in enumerate(m.ids)]
    return _csv(rows)


def _quality_figure(quality: dict, title: str, path: Path, force: bool) -> None:
    """Compactness, generalization and specificity over the number of modes, with standard errors."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.2), dpi=100)
    FigureCanvasAgg(fig)
    modes = quality["modes"]
    for j, (key, se, name, unit) in enumerate((("compactness", "compactness_se", "compactness", "fraction"),
                                               ("generalization_mm", "generalization_se_mm", "generalization", "mm"),
                                               ("specificity_mm", "specificity_se_mm", "specificity", "mm"))):
        ax = fig.add_subplot(1, 3, j + 1)
        ax.errorbar(modes, quality[key], yerr=quality[se], marker="o", ms=3, capsize=2)
        ax.set_xlabel("modes")
        ax.set_ylabel(unit)
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_output(path, force=force) as tmp:
        fig.canvas.print_png(str(tmp))


def _slice(lsm: LabelShapeModel) -> tuple[int, int]:
    """The axis and index of the GIF's slice: across the template's thinnest extent, through its labels' centre."""
    a = lsm.template.array
    axis = int(np.argmin(a.shape))
    nz = np.nonzero(a)
    return axis, int(round(float(np.mean(nz[axis])))) if len(nz[axis]) else a.shape[axis] // 2


def _render(labels: np.ndarray, outline: np.ndarray, scale: int) -> np.ndarray:
    """A label slice as RGB (a fixed palette), the outline (bool) in white, each voxel ``scale`` pixels."""
    from matplotlib import colormaps

    palette = (np.asarray(colormaps["tab20"].colors) * 255).astype(np.uint8)
    values = np.unique(labels)
    rgb = np.zeros(labels.shape + (3,), np.uint8)
    for v in values[values != 0]:
        rgb[labels == v] = palette[int(v) % len(palette)]
    rgb[outline] = 255
    return np.kron(rgb.transpose(1, 0, 2)[::-1], np.ones((scale, scale, 1), np.uint8))


def _edges(labels: np.ndarray) -> np.ndarray:
    e = np.zeros(labels.shape, bool)
    e[1:] |= labels[1:] != labels[:-1]
    e[:, 1:] |= labels[:, 1:] != labels[:, :-1]
    return e


def _write_gif(lsm: LabelShapeModel, k: int, path: Path, force: bool) -> None:
    """Mode ``k`` (0-based) as a looping GIF of a template slice along -2 .. +2 standard deviations
    (the labels drawn at the slice's voxel centres only)."""
    from PIL import Image

    template = lsm.template
    if template.ndim == 3:
        axis, index = _slice(lsm)
        cut = [slice(None)] * 3
        cut[axis] = index
        shape = tuple(n for d, n in enumerate(template.shape) if d != axis)
        points = template.grid_points()[tuple(cut)].reshape(-1, 3)
    else:
        shape = template.shape
        points = template.grid_points().reshape(-1, 2)
    outline = _edges(lsm.labels_at(points).reshape(shape))
    scale = max(1, 256 // max(shape))
    frames = []
    for t in range(GIF_FRAMES):
        b = np.zeros(k + 1)
        b[k] = 2.0 * np.sin(2 * np.pi * t / GIF_FRAMES)
        frames.append(Image.fromarray(_render(lsm.labels_at(points, b).reshape(shape), outline, scale)))
    with atomic_output(path, force=force) as tmp:
        frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:], duration=120, loop=0)


def _write_meshes(lsm: LabelShapeModel, meshes: dict, stem: str, where: Path, record, force: bool,
                  gifti: bool = False) -> None:
    for lab, (verts, tris) in meshes.items():
        path = where / f"{stem}_label{lab}.vtk"
        write_mesh(verts, tris, path, force=force)
        record(path)
        if gifti and verts.shape[1] == 3:
            path = where / f"{stem}_label{lab}.surf.gii"
            write_gifti(verts, tris, path, force=force)
            record(path)


def _write_model(lsm: LabelShapeModel, quality: dict, where: Path, record, force: bool, progress) -> None:
    """One model's folder (module notes)."""
    lsm.save(where / "model.npz", force=force)
    record(where / "model.npz")
    for name, text in (("modes.csv", _modes_table(lsm)), ("scores.csv", _scores_table(lsm))):
        write_text(text, where / name, force=force)
        record(where / name)
    write_json(quality, where / "quality.json", force=force)
    record(where / "quality.json")
    _quality_figure(quality, f"{lsm.kind} model: {len(lsm.model.ids)} subjects, {lsm.model.n_modes} modes",
                    where / "quality.png", force)
    record(where / "quality.png")
    _write_meshes(lsm, lsm.meshes(()), "mean", where, record, force, gifti=True)
    shown = min(RENDERED_MODES, lsm.model.n_modes)
    for k in range(shown):
        for sign, tag in ((-2.0, "-2sd"), (2.0, "+2sd")):
            b = np.zeros(k + 1)
            b[k] = sign
            d = lsm.displacement(b)
            stem = f"mode_{k + 1}_{tag}"
            write_labels(lsm.label_map(b, d), where / f"{stem}.nii.gz", force=force)
            record(where / f"{stem}.nii.gz")
            _write_meshes(lsm, lsm.meshes(b, d), stem, where, record, force)
        _write_gif(lsm, k, where / f"mode_{k + 1}.gif", force)
        record(where / f"mode_{k + 1}.gif")
        if progress is not None:
            progress(f"{lsm.kind} model outputs", k + 1, shown)


def _summary(result: ShapeModelResult) -> dict:
    out = dict(result.report)
    out["models"] = {}
    for kind in KINDS:
        lsm, q = result.models[kind], result.quality[kind]
        m = min(3, lsm.model.n_modes)
        out["models"][kind] = {
            "modes": lsm.model.n_modes, "points": int(lsm.model.mean.shape[0]), "leading": m,
            "leading_variances_mm2": lsm.model.variances[:m].tolist(),
            "compactness_leading": q["compactness"][m - 1] if m else None,
            "generalization_leading_mm": q["generalization_mm"][m - 1] if m else None,
            "specificity_leading_mm": q["specificity_mm"][m - 1] if m else None,
            "correspondence_mm": {"to_boundary": q["correspondence"]["to_boundary_mm"],
                                  "from_boundary": q["correspondence"]["from_boundary_mm"]},
        }
    return out


def _write_all(result: ShapeModelResult, outdir: Path, top, force: bool, progress) -> dict:
    for kind in KINDS:
        with output_folder(outdir / kind, force, outputs=SHAPE_MODEL_OUTPUTS) as folder:
            _write_model(result.models[kind], result.quality[kind], folder.path, folder.record, force, progress)
    report = _summary(result)
    write_json(report, top.path / "report.json", force=force)
    top.record(top.path / "report.json")
    return report


def write_shape_models(result: ShapeModelResult, outdir: str | os.PathLike[str], *, force: bool = False,
                       progress=None) -> dict:
    """Write both models' folders and ``report.json`` into ``outdir`` (module notes), all or nothing.

    Returns
    -------
    dict
        The ``report.json`` written.
    """
    outdir = Path(outdir)
    with output_folder(outdir, force, outputs=("report.json",)) as top:
        return _write_all(result, outdir, top, force, progress)


def build_and_write_shape_models(template_folder: str | os.PathLike[str], outdir: str | os.PathLike[str], *,
                                 force: bool = False, progress=None, **options) -> tuple[ShapeModelResult, dict]:
    """:func:`~volreg.shape_models.build_shape_models` and :func:`write_shape_models` in one transaction:
    ``outdir`` is checked (empty or ``force``, writable, not in use) before any work.

    Parameters
    ----------
    template_folder, outdir : path-like
    force : bool
    progress : callable, optional
    **options
        :func:`~volreg.shape_models.build_shape_models`'s keywords (``align``, ``modes``,
        ``samples``, ``seed``, ``warn``).

    Returns
    -------
    (ShapeModelResult, dict)
        The models and the ``report.json`` written.
    """
    outdir = Path(outdir)
    with output_folder(outdir, force, outputs=("report.json",)) as top:
        result = build_shape_models(template_folder, progress=progress, **options)
        return result, _write_all(result, outdir, top, force, progress)


def write_shape_sample(lsm: LabelShapeModel, coefficients, outdir: str | os.PathLike[str], *,
                       force: bool = False) -> list[str]:
    """The label map (``shape.nii.gz``) and meshes (``shape_label<L>.vtk``) of one shape of ``lsm``.

    Returns
    -------
    list of str
        The files written, relative to ``outdir``.
    """
    b = np.asarray(coefficients, float)
    lsm.model.sample(b)  # refuses bad coefficients before any file
    with output_folder(outdir, force, outputs=("shape.nii.gz", "shape_label*.vtk")) as folder:
        d = lsm.displacement(b)
        write_labels(lsm.label_map(b, d), folder.path / "shape.nii.gz", force=force)
        folder.record(folder.path / "shape.nii.gz")
        _write_meshes(lsm, lsm.meshes(b, d), "shape", folder.path, folder.record, force)
        names = [p.name for p in folder.written]
    return names
