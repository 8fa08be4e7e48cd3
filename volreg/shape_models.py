"""Statistical shape and deformation models of a cohort, from the correspondences of ``volreg template``.

:func:`build_shape_models` (and ``volreg shape-model TEMPLATE_OUT``) reads the folder
:func:`volreg.template.build_template` wrote: the template labels and, per subject, the pull-back
field ``u_i`` on the template grid (template point ``x`` corresponds to subject point
``x + u_i(x)``).  Every subject is then the same points carried by its own warp:

- **surface model**: each template label's boundary mesh (marching cubes), its vertices ``v``
  carried to ``v + u_i(v)`` (trilinear), so that all subjects share the template's vertices and
  triangles;
- **deformation model** (Rueckert & Frangi): the template's voxel centres ``x`` in its labelled
  region (the labels dilated by two voxels) carried to ``x + u_i(x)``; a mode is a displacement
  of the whole region, interior structures included.  The field is taken on the template grid
  (not at kernel centres: the grid is where every subject's field is already written, and a
  mode drawn there applies to the label map directly).

Both are optionally aligned by generalised Procrustes (``align``), then modelled by PCA
(:class:`~volreg.pipeline.shape_model.ShapeModel`), and judged by compactness, generalization and
specificity (:func:`~volreg.evaluation.shape_quality.model_quality`) and by the correspondence
both ways: each subject's reconstruction (its own coefficients, every mode kept) against the
boundary of its own label map, and that boundary against the reconstruction (mm).

A :class:`LabelShapeModel` (a ``ShapeModel`` with the template's labels, meshes and region) draws
the meshes and the label map of any coefficients (:meth:`LabelShapeModel.label_map`): the
deformation model's displacement is its region's, extended to the grid by nearest region voxel;
the surface model's is spread from its vertices by a thin plate spline.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from volreg import __version__
from volreg._memory import MAX_MEMORY, memory_limit
from volreg.errors import UsageError, VolregIOError
from volreg.evaluation.shape_quality import model_quality
from volreg.features.label_surfaces import surfaces_of_volumes
from volreg.grid import LabelVolume
from volreg.io import read_labels
from volreg.io.archives import read_arrays, write_arrays
from volreg.io.documents import parse_json
from volreg.io.fields import read_displacement
from volreg.pipeline.shape_fields import (
    fill_field, labelled_region, labels_at, labels_of_displacement, nearest_region_index,
    sample_field, vertex_spline,
)
from volreg.pipeline.shape_model import ALIGNMENTS, ShapeModel
from volreg.settings import SurfaceSettings

__all__ = ["KINDS", "SHAPE_MODEL_FORMAT", "LabelShapeModel", "ShapeModelResult", "build_shape_models",
           "read_template_folder"]

#: The two models of a cohort, in the order they are built.
KINDS = ("surface", "deformation")
#: The largest template report read (a template's report is a few kB per subject).
MAX_REPORT_BYTES = 256 * 10**6
#: The ``format`` member of a saved :class:`LabelShapeModel`.
SHAPE_MODEL_FORMAT = "volreg-shape-model-1"

ProgressCallback = Callable[[str, int, int], None]


# ----------------------------------------------------------------------------- the model of a label map


@dataclass
class LabelShapeModel:
    """A :class:`~volreg.pipeline.shape_model.ShapeModel` of a template's labels (the module notes).

    Attributes
    ----------
    kind : {"surface", "deformation"}
    model : ShapeModel
        Its points are the template's mesh vertices (``"surface"``) or region voxel centres
        (``"deformation"``), mm.
    template : LabelVolume
    labels : list of int
        The template labels with a mesh, in the meshes' order.
    vertices : (V, D) float array, mm
        The template's meshes' vertices, label after label.
    offsets : (L + 1,) int array
        Label ``labels[j]``'s vertices are ``vertices[offsets[j]:offsets[j + 1]]``.
    faces : list of (F_j, D) int arrays
        Each label's triangles, indices into its own vertices.
    region : bool array, optional
        The deformation model's region on the template grid (None for ``"surface"``).
    """

    kind: str
    model: ShapeModel
    template: LabelVolume
    labels: list[int]
    vertices: np.ndarray
    offsets: np.ndarray
    faces: list[np.ndarray]
    region: np.ndarray | None = None
    _nearest: np.ndarray | None = field(default=None, repr=False)
    _points: np.ndarray | None = field(default=None, repr=False)
    _basis: np.ndarray | None = field(default=None, repr=False)

    # ------------------------------------------------------------------------- shapes of coefficients

    def _region(self) -> np.ndarray:
        return self.region if self.region is not None else labelled_region(self.template.array)

    def _nearest_index(self) -> np.ndarray:
        if self._nearest is None:
            self._nearest = nearest_region_index(self._region())
        return self._nearest

    def _region_points(self) -> np.ndarray:
        if self._points is None:
            self._points = self.template.grid_points()[self._region()]
        return self._points

    def _spline_basis(self) -> np.ndarray:
        """The surface model's displacement on the region for the mean and for 1 sd of each mode:
        ``(K + 1, P, D)`` float32, one spline through the vertices carrying them all (it is linear)."""
        if self._basis is None:
            m = self.model
            k, d = m.n_modes, m.mean.shape[1]
            columns = np.concatenate([m.mean - self.vertices] + [np.sqrt(m.variances[j]) * m.modes[j] for j in range(k)],
                                     axis=1)  # (V, (K + 1) D)
            values = vertex_spline(self.vertices, columns)(self._region_points())
            self._basis = values.reshape(len(values), k + 1, d).transpose(1, 0, 2).astype(np.float32)
        return self._basis

    def _region_values(self, coefficients) -> np.ndarray:
        """A shape's displacement at the region's voxel centres: (P, D) mm."""
        b = self.model.check_coefficients(coefficients)
        if self.kind == "deformation":
            return self.model.sample(b) - self._region_points()
        basis = self._spline_basis()
        return basis[0] + np.tensordot(b, basis[1:len(b) + 1], axes=1)

    def displacement(self, coefficients=()) -> np.ndarray:
        """The template grid's displacement ``x -> x + d(x)`` of a shape: ``(*shape, D)`` mm.

        Parameters
        ----------
        coefficients : (M,) array-like, standard deviations of the leading modes
        """
        return fill_field(self._region_values(coefficients), self._nearest_index())

    def displacement_function(self, coefficients=()):
        """The displacement ``d`` of a shape as a function of world points (N, D) -> (N, D) mm
        (:meth:`displacement` read trilinearly)."""
        field_ = self.displacement(coefficients)
        return lambda points: sample_field(field_, self.template.grid, points)

    def labels_at(self, points: np.ndarray, coefficients=()) -> np.ndarray:
        """The template's labels in a shape at world points (N, D) mm (a slice, say), without the whole grid."""
        return labels_at(self.template, self.displacement_function(coefficients), points)

    def mesh_vertices(self, coefficients=(), displacement: np.ndarray | None = None) -> np.ndarray:
        """The template meshes' vertices in a shape: (V, D) mm (``displacement`` reused where given)."""
        if self.kind == "surface":
            return self.model.sample(coefficients)
        d = self.displacement(coefficients) if displacement is None else displacement
        return self.vertices + sample_field(d, self.template.grid, self.vertices)

    def meshes(self, coefficients=(), displacement: np.ndarray | None = None) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Each label's mesh (vertices mm, triangles) in a shape."""
        v = self.mesh_vertices(coefficients, displacement)
        return {lab: (v[self.offsets[j]:self.offsets[j + 1]], self.faces[j]) for j, lab in enumerate(self.labels)}

    def label_map(self, coefficients=(), displacement: np.ndarray | None = None) -> LabelVolume:
        """The template's label map in a shape, on the template grid (``template(phi^-1(y))``)."""
        d = self.displacement(coefficients) if displacement is None else displacement
        return labels_of_displacement(self.template, d)

    # ------------------------------------------------------------------------- files

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Every array of the model, for :func:`volreg.io.archives.write_arrays`."""
        t = self.template
        out = {
            **self.model.to_arrays(), "kind": np.array(self.kind), "volreg_version": np.array(__version__),
            "template_labels": t.array, "template_origin": t.origin, "template_spacing": t.spacing,
            "template_direction": t.direction,
            "labels": np.array(self.labels, np.int64), "vertices": self.vertices, "offsets": self.offsets,
            "faces": np.concatenate(self.faces) if self.faces else np.zeros((0, t.ndim), np.int64),
            "face_offsets": np.cumsum([0] + [len(f) for f in self.faces]),
        }
        if self.region is not None:
            out["region"] = self.region
        return out

    def save(self, path: str | os.PathLike[str], *, force: bool = False) -> None:
        """Write the model to ``path`` (``.npz``, no pickle), atomically."""
        write_arrays(self.to_arrays(), path, format=SHAPE_MODEL_FORMAT, force=force)

    @classmethod
    def load(cls, path: str | os.PathLike[str], *, option: str | None = None) -> "LabelShapeModel":
        """Read a model :meth:`save` wrote.

        Raises
        ------
        VolregIOError
            One line naming the file, if it is not such a model.
        """
        a = read_arrays(path, "Shape model", SHAPE_MODEL_FORMAT, option=option)
        label = f"{option} `{os.fspath(path)}`" if option else f"Shape model `{os.fspath(path)}`"
        try:
            model = ShapeModel.from_arrays(a)
            template = LabelVolume(a["template_labels"], a["template_origin"], a["template_spacing"],
                                   a["template_direction"])
            fo = np.asarray(a["face_offsets"], np.int64)
            faces = [np.asarray(a["faces"][fo[j]:fo[j + 1]], np.int64) for j in range(len(fo) - 1)]
            out = cls(str(a["kind"]), model, template, [int(v) for v in a["labels"]], np.asarray(a["vertices"], float),
                      np.asarray(a["offsets"], np.int64), faces, a["region"].astype(bool) if "region" in a else None)
        except (KeyError, ValueError, TypeError, IndexError) as exc:
            raise VolregIOError(f"{label} is not a complete shape model: {str(exc)[:80]}.") from None
        p, d = model.mean.shape
        expected = len(out.vertices) if out.kind == "surface" else int(out.region.sum()) if out.region is not None else -1
        if out.kind not in KINDS or p != expected or model.modes.shape[1:] != (p, d) \
                or len(model.variances) != len(model.modes) or len(out.labels) + 1 != len(out.offsets) \
                or len(out.faces) != len(out.labels) or out.vertices.ndim != 2 or out.vertices.shape[1] != d \
                or d != template.ndim or (out.region is not None and out.region.shape != template.shape) \
                or int(out.offsets[-1]) != len(out.vertices) \
                or any(len(f) and (f.min() < 0 or f.max() >= out.offsets[j + 1] - out.offsets[j])
                       for j, f in enumerate(out.faces)):
            raise VolregIOError(f"{label} is not a consistent shape model: its arrays do not agree in size.")
        return out


# ----------------------------------------------------------------------------- reading a template folder


@dataclass
class TemplateFolder:
    """What :func:`read_template_folder` found: the template, its subjects and their warps' files.

    Attributes
    ----------
    path : Path
    template : LabelVolume
    ids : list of str
        The subjects registered to the template, in the manifest's order.
    sources : dict of str to Path
        Each subject's own label map (as the template's report names it).
    warps : dict of str to Path
        Each subject's ``warp.nii.gz`` (on the template grid).
    """

    path: Path
    template: LabelVolume
    ids: list[str]
    sources: dict[str, Path]
    warps: dict[str, Path]


def read_template_folder(folder: str | os.PathLike[str]) -> TemplateFolder:
    """The template, subjects and warps of a finished ``volreg template`` folder.

    Raises
    ------
    UsageError
        ``folder`` is not a finished template folder, or lists fewer than two subjects.
    VolregIOError
        A subject's warp is missing.
    """
    path = Path(folder)
    report = path / "report.json"
    if not path.is_dir():
        raise UsageError(f"TEMPLATE_OUT `{path}` is not a folder; expected the folder `volreg template` wrote.")
    if not report.is_file() or not (path / "template.nii.gz").is_file():
        raise UsageError(f"TEMPLATE_OUT `{path}` holds no finished template (report.json and template.nii.gz); "
                         "expected the folder `volreg template` wrote.")
    if report.stat().st_size > MAX_REPORT_BYTES:
        raise UsageError(f"TEMPLATE_OUT report `{report}` is {report.stat().st_size / 1e6:.0f} MB; expected the report "
                         f"`volreg template` wrote (at most {MAX_REPORT_BYTES // 10**6} MB).")
    try:
        text = report.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise VolregIOError(f"TEMPLATE_OUT report `{report}` cannot be read: {exc}.") from None
    try:
        data = parse_json(text, f"TEMPLATE_OUT report `{report}`")
    except ValueError:  # not JSON: its content is not echoed
        raise UsageError(f"TEMPLATE_OUT report `{report}` is not JSON; expected the report `volreg template` "
                         "wrote.") from None
    subjects = data.get("subjects") if isinstance(data, dict) else None
    if not isinstance(data, dict) or data.get("command") != "template" or not isinstance(subjects, list):
        raise UsageError(f"TEMPLATE_OUT report `{report}` is not a `volreg template` report; expected the folder "
                         "`volreg template` wrote.")
    ids, sources, warps = [], {}, {}
    for row in subjects:
        if not isinstance(row, dict) or not isinstance(row.get("id"), str):
            raise UsageError(f"TEMPLATE_OUT report `{report}` lists a subject without an id.")
        sid = row["id"]
        if sid in warps or not sid or sid in (".", "..") or sid.startswith(".") or any(c in sid for c in "/\\") \
                or any(c < " " or c == "\x7f" for c in sid):
            raise UsageError(f"TEMPLATE_OUT report `{report}` lists the subject id {sid[:100]!r} twice or as a name "
                             "that is no folder of its own; expected the unique ids of the manifest.")
        warp = path / "subjects" / sid / "warp.nii.gz"
        if not warp.is_file():
            raise VolregIOError(f"TEMPLATE_OUT `{path}`: subject `{sid[:100]}` has no `subjects/{sid[:100]}/warp.nii.gz`; "
                                "expected every subject's registration to the template.")
        ids.append(sid)
        warps[sid] = warp
        source = Path(str(row.get("path", "")))
        if not source.is_absolute() and not source.exists() and (path.parent / source).exists():
            source = path.parent / source  # a relative path, read from beside the template folder
        sources[sid] = source
    if len(ids) < 2:
        raise UsageError(f"TEMPLATE_OUT `{path}` lists {len(ids)} subject; expected at least two for a shape model.")
    return TemplateFolder(path, read_labels(path / "template.nii.gz"), ids, sources, warps)


# ----------------------------------------------------------------------------- building both models


@dataclass
class ShapeModelResult:
    """What :func:`build_shape_models` made: the models, their quality and the run's report.

    Attributes
    ----------
    models : dict of str to LabelShapeModel
        ``"surface"`` and ``"deformation"``.
    quality : dict of str to dict
        Per model, :func:`~volreg.evaluation.shape_quality.model_quality`'s measures plus
        ``"correspondence"`` (both ways, mm).
    report : dict
    """

    models: dict[str, LabelShapeModel]
    quality: dict[str, dict]
    report: dict = field(default_factory=dict)


def _nearest_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each point of ``a`` (N, D), the distance to the nearest point of ``b`` (mm)."""
    return cKDTree(b).query(a)[0]


def _correspondence(lsm: LabelShapeModel, aligned: np.ndarray, boundaries: dict[str, dict], ids: list[str]) -> dict:
    """Each subject's reconstruction (in its own frame) against its own label boundary, both ways (mm)."""
    per = []
    model = lsm.model
    for i, sid in enumerate(ids):
        if sid not in boundaries:
            continue
        b = model.project(aligned[i])
        back = np.linalg.inv(model.transforms[i])
        if lsm.kind == "surface":
            verts = model.sample(b)
        else:
            verts = lsm.mesh_vertices(b)
        d = verts.shape[1]
        verts = verts @ back[:d, :d].T + back[:d, d]
        to_b, from_b = [], []
        for j, lab in enumerate(lsm.labels):
            own = boundaries[sid].get(lab)
            if own is None or not len(own):
                continue
            mine = verts[lsm.offsets[j]:lsm.offsets[j + 1]]
            to_b.append(_nearest_distances(mine, own))
            from_b.append(_nearest_distances(own, mine))
        if to_b:
            a, c = np.concatenate(to_b), np.concatenate(from_b)
            per.append({"id": sid, "to_boundary_mm": float(a.mean()), "from_boundary_mm": float(c.mean()),
                        "to_boundary_p95_mm": float(np.percentile(a, 95)),
                        "from_boundary_p95_mm": float(np.percentile(c, 95))})
    if not per:
        return {"subjects": [], "to_boundary_mm": None, "from_boundary_mm": None}
    return {"subjects": per, "to_boundary_mm": float(np.mean([p["to_boundary_mm"] for p in per])),
            "from_boundary_mm": float(np.mean([p["from_boundary_mm"] for p in per])),
            "worst": max(per, key=lambda p: max(p["to_boundary_mm"], p["from_boundary_mm"]))["id"]}


def _check_memory(folder: TemplateFolder, n: int, points: int, vertices: int, grid, modes) -> None:
    """Refuse a cohort whose models would not fit in memory, before any warp is read: the data
    (float32 region, float64 vertices) and their aligned copies, a float64 block of the Gram
    matrix's columns per subject, the modes (float64, and their float32 copy when saved), and four
    fields of the template grid."""
    k = min(n - 1, modes or n - 1)
    need = 2 * (12 * n * points + 24 * n * vertices) + 8 * n * (1 << 18) + 36 * k * (points + vertices) \
        + 96 * int(np.prod(grid.shape))
    available, known_as = memory_limit()
    if available is not None and need > available:
        raise UsageError(f"TEMPLATE_OUT `{folder.path}`: the models of {n} subjects over {points} region voxels would "
                         f"need about {need / 1024**3:.1f} GB of memory and {available / 1024**3:.1f} GB is {known_as}; "
                         f"expected a template of a coarser spacing, fewer subjects or more free memory (set "
                         f"{MAX_MEMORY} to change the limit).")


def _check_options(align: str, modes, samples, seed) -> None:
    if align not in ALIGNMENTS:
        raise UsageError(f"--align {align!r}: expected one of {', '.join(ALIGNMENTS)}.")
    for name, value, least in (("modes", modes, 1), ("samples", samples, 1), ("seed", seed, 0)):
        if value is None and name == "modes":
            continue
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < least:
            raise UsageError(f"--{name} {value!r}: expected an integer of at least {least}.")


def build_shape_models(
    template_folder: str | os.PathLike[str],
    *,
    align: str = "rigid",
    modes: int | None = 10,
    samples: int = 100,
    seed: int = 0,
    progress: ProgressCallback | None = None,
    warn: Callable[[str], None] | None = None,
) -> ShapeModelResult:
    """The surface and deformation models of a template's cohort, and their quality (the module notes).

    Parameters
    ----------
    template_folder : path-like
        The folder ``volreg template`` wrote.
    align : {"none", "rigid", "similarity"}
        Generalised Procrustes alignment of the subjects first (default rigid: the subjects'
        positions and orientations in their scanners are not shape; their sizes are).
    modes : int, optional
        At most this many modes per model (default 10; ``None``: ``N - 1``).
    samples : int
        Shapes drawn for the specificity.
    seed : int
        For the specificity's draws and the measured points' subset.
    progress : callable, optional
        ``progress(stage, done, total)``.
    warn : callable, optional
        Called with a line for each subject whose own label map cannot be read (left out of the
        correspondence measure).

    Returns
    -------
    ShapeModelResult
    """
    _check_options(align, modes, samples, seed)
    start = time.perf_counter()
    folder = read_template_folder(template_folder)
    template = folder.template
    grid = template.grid
    [(meshes, missing)] = surfaces_of_volumes([template], smoothing=[SurfaceSettings.smoothing])
    if not meshes:
        raise UsageError(f"TEMPLATE_OUT `{folder.path}`: the template has no label large enough for a mesh.")
    labels = list(meshes)
    vertices = np.concatenate([meshes[v].vertices for v in labels])
    offsets = np.cumsum([0] + [len(meshes[v].vertices) for v in labels])
    faces = [np.asarray(meshes[v].cells, np.int64) for v in labels]
    region = labelled_region(template.array)
    points = grid.grid_points()[region]
    n = len(folder.ids)
    _check_memory(folder, n, len(points), len(vertices), grid, modes)
    surface = np.empty((n, len(vertices), grid.ndim), np.float64)
    deformation = np.empty((n, len(points), grid.ndim), np.float32)
    t0 = time.perf_counter()
    for i, sid in enumerate(folder.ids):
        u, ugrid = read_displacement(folder.warps[sid])
        if not ugrid.same_geometry(grid, atol=1e-3):  # (NIfTI keeps the geometry in float32)
            raise VolregIOError(f"Warp `{folder.warps[sid]}` is not on the template's grid; expected the field "
                                "`volreg template` wrote for that subject.")
        surface[i] = vertices + sample_field(u, grid, vertices)
        deformation[i] = points + u[region]
        if progress is not None:
            progress("read warps", i + 1, n)
    read_seconds = time.perf_counter() - t0
    boundaries = _subject_boundaries(folder, labels, warn or (lambda line: None), progress)
    models, quality, timings = {}, {}, {"read_warps": read_seconds}
    for kind, shapes, reference in (("surface", surface, vertices), ("deformation", deformation, points)):
        t0 = time.perf_counter()
        model = ShapeModel.fit(shapes, ids=folder.ids, align=align, modes=modes, reference=reference)
        lsm = LabelShapeModel(kind, model, template, labels, vertices, offsets, faces,
                              region if kind == "deformation" else None)
        aligned = model.aligned
        fitted = time.perf_counter() - t0
        q = model_quality(model, aligned, samples=samples, seed=seed)
        q["correspondence"] = _correspondence(lsm, aligned, boundaries, folder.ids)
        models[kind], quality[kind] = lsm, q
        timings[kind] = {"fit": fitted, "quality": time.perf_counter() - t0 - fitted}
        if progress is not None:
            progress("models", len(models), len(KINDS))
    report = {
        "volreg_version": __version__, "command": "shape-model", "template_folder": str(folder.path),
        "subjects": folder.ids, "align": align, "modes_requested": modes,
        "labels": labels, "labels_without_mesh": sorted(int(v) for v in missing),
        "surface_points": int(len(vertices)), "deformation_points": int(len(points)),
        "deformation_points_where": "template voxel centres in the labelled region dilated by 2 voxels",
        "memory_bytes": {"surface": int(surface.nbytes), "deformation": int(deformation.nbytes)},
        "seconds": {k: v for k, v in timings.items()},
    }
    report["seconds"]["total"] = time.perf_counter() - start
    return ShapeModelResult(models, quality, report)


def _subject_boundaries(folder: TemplateFolder, labels: list[int], warn, progress) -> dict[str, dict]:
    """Each subject's own label boundaries (mesh vertices per label, mm), where its label map can be read."""
    volumes = {}
    for sid in folder.ids:
        try:
            volumes[sid] = read_labels(folder.sources[sid])
        except (VolregIOError, OSError, ValueError) as exc:
            warn(f"subject `{sid[:100]}`: its label map cannot be read ({str(exc)[:120]}); it is left out of the "
                 "correspondence measure.")
    if not volumes:
        return {}
    found = surfaces_of_volumes(list(volumes.values()), labels, smoothing=[SurfaceSettings.smoothing] * len(volumes))
    if progress is not None:
        progress("subject boundaries", len(volumes), len(volumes))
    return {sid: {lab: s.vertices for lab, s in meshes.items()} for sid, (meshes, _) in zip(volumes, found)}
