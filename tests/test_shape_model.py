"""Shape and deformation models of a cohort generated from a known template with known modes.

The cohort: a template of three labels, twelve subjects warped by ``x + sum_m b_im e_m(x)`` with
three known modes ``e_m`` (pairs of opposite Gaussian bumps pushing along x, y and z, at 1 sd 4, 2.5 and
1.5 mm)
and whitened known coefficients ``b`` (:class:`volreg.synthetic.KnownModes`).  The template
folder is written as ``volreg template`` writes it, with each subject's true pull-back field as
its warp, so that the model is judged on exact correspondences.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from scipy.linalg import subspace_angles

from volreg.cli import main
from volreg.errors import UsageError, VolregIOError
from volreg.evaluation.metrics import dice
from volreg.evaluation.shape_quality import model_quality
from volreg.grid import LabelVolume
from volreg.io import read_labels
from volreg.outputs.shape_model import write_shape_models, write_shape_sample
from volreg.pipeline.shape_model import ShapeModel, fit_similarity, procrustes
from volreg.shape_models import LabelShapeModel, build_shape_models
from volreg.synthetic import KnownModes, deform_labels

from helpers import write_template_folder

N_SUBJECTS = 12
MODES = KnownModes(np.array([[12.0, 0, 0], [-6.0, 9, 0], [4.0, 0, 7]]), np.eye(3), np.array([4.0, 2.5, 1.5]), 10.0)


def _template(n=34, spacing=2.0) -> LabelVolume:
    x = np.indices((n, n, n)).reshape(3, -1).T * spacing - (n - 1) * spacing / 2
    a = np.zeros(len(x), np.uint8)
    a[((x / [26, 19, 14]) ** 2).sum(1) <= 1] = 1
    a[(((x - [8, 0, 0]) / [10, 8, 7]) ** 2).sum(1) <= 1] = 2
    a[(((x + [12, -3, 0]) / [7, 6, 6]) ** 2).sum(1) <= 1] = 3
    return LabelVolume(a.reshape(n, n, n), np.full(3, -(n - 1) * spacing / 2), np.full(3, spacing), np.eye(3))


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    root = tmp_path_factory.mktemp("shape_cohort")
    template = _template()
    b = MODES.coefficients(N_SUBJECTS, seed=3)
    x = template.grid_points().reshape(-1, 3)
    warps = [MODES.warp(bi).displacement(x).reshape(template.shape + (3,)) for bi in b]
    subjects = [deform_labels(template, MODES.warp(bi)) for bi in b]
    ids = [f"sub-{i:02d}" for i in range(N_SUBJECTS)]
    folder = write_template_folder(root, template, warps, subjects, ids)
    result = build_shape_models(folder, align="none", modes=6, samples=40)
    return root, template, b, subjects, ids, folder, result


# ----------------------------------------------------------------------------- the PCA itself


def test_procrustes_undoes_known_similarities():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(200, 3)) * 10
    shapes = []
    for k in range(5):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        q *= np.sign(np.linalg.det(q))
        shapes.append(1.3**k * base @ q.T + rng.normal(size=3) * 30)
    aligned, transforms = procrustes(np.stack(shapes), "similarity", reference=base)
    assert np.abs(aligned - base).max() < 1e-8
    rigid = fit_similarity(shapes[2], base, "rigid")
    assert np.allclose(np.linalg.svd(rigid[:3, :3])[1], 1.0)  # no scale, no reflection
    assert np.linalg.det(rigid[:3, :3]) > 0
    with pytest.raises(UsageError, match="--align 'affine'"):
        procrustes(np.stack(shapes), "affine")


def test_the_gram_pca_matches_the_covariance_pca():
    rng = np.random.default_rng(1)
    shapes = rng.normal(size=(7, 50, 3))
    model = ShapeModel.fit(shapes)
    flat = shapes.reshape(7, -1)
    w, v = np.linalg.eigh(np.cov(flat.T))
    assert np.allclose(model.variances, w[::-1][:6], rtol=1e-9)
    assert np.allclose(np.abs(model.modes.reshape(6, -1) @ v[:, ::-1][:, :6]), np.eye(6), atol=1e-6)
    assert np.allclose(model.scores.std(0, ddof=1), 1.0)
    # a training shape's coefficients rebuild it (all modes), and project back to its scores
    assert np.allclose(model.sample(model.scores[3]), shapes[3])
    assert np.allclose(model.project(shapes[3]), model.scores[3])
    assert model.total_variance == pytest.approx(np.trace(np.cov(flat.T)))


def test_leave_one_out_matches_refitting_without_the_subject():
    rng = np.random.default_rng(2)
    shapes = rng.normal(size=(6, 40, 3)) + np.linspace(0, 3, 6)[:, None, None] * rng.normal(size=(40, 3))
    model = ShapeModel.fit(shapes)
    q = model_quality(model, shapes, samples=5)
    assert model_quality(model, shapes, samples=5) == q  # seeded
    # the mean over subjects of the refits' errors, against the Gram shortcut
    refit = np.mean([[np.linalg.norm(ShapeModel.fit(np.delete(shapes, i, axis=0)).reconstruct(shapes[i], m)
                                     - shapes[i], axis=1).mean() for m in (1, 2, 3)] for i in range(6)], axis=0)
    assert np.allclose(q["generalization_mm"][:3], refit, rtol=1e-8)


def test_a_point_model_round_trips_without_pickle(tmp_path):
    rng = np.random.default_rng(4)
    model = ShapeModel.fit(rng.normal(size=(5, 30, 3)), ids=list("abcde"), align="rigid")
    model.save(tmp_path / "m.npz")
    back = ShapeModel.load(tmp_path / "m.npz")
    assert back.ids == list("abcde") and back.align == "rigid"
    np.testing.assert_allclose(back.sample([1.0, -0.5]), model.sample([1.0, -0.5]), atol=1e-5)
    np.testing.assert_array_equal(back.scores, model.scores)
    with pytest.raises(VolregIOError, match="not a volreg shape model"):
        LabelShapeModel.load(tmp_path / "m.npz")  # a point model is not a label map's


def test_bad_model_arguments_are_refused():
    with pytest.raises(UsageError, match="N >= 2"):
        ShapeModel.fit(np.zeros((1, 4, 3)))
    with pytest.raises(UsageError, match="--modes 0"):
        ShapeModel.fit(np.zeros((3, 4, 3)), modes=0)
    model = ShapeModel.fit(np.random.default_rng(0).normal(size=(4, 5, 3)))
    with pytest.raises(UsageError, match="--coefficients"):
        model.sample([1, 2, 3, 4])
    with pytest.raises(UsageError, match="--coefficients"):
        model.sample([np.nan])


# ----------------------------------------------------------------------------- known modes recovered


@pytest.mark.parametrize("kind", ["surface", "deformation"])
def test_the_leading_modes_span_the_known_ones(cohort, kind):
    _, template, b, _, _, _, result = cohort
    lsm = result.models[kind]
    points = lsm.vertices if kind == "surface" else template.grid_points()[lsm.region]
    known = MODES.fields(points).reshape(3, -1)
    angles = np.degrees(subspace_angles(lsm.model.modes[:3].reshape(3, -1).T, known.T))
    assert angles.max() < 1.0, angles  # exact correspondences: the subspace to within a degree
    # each mode on its own (orthogonal known modes, distinct variances): variance and direction
    expected = (known**2).sum(1)  # the whitened cohort's variance along each known mode, mm^2
    assert np.allclose(lsm.model.variances[:3], expected, rtol=0.02), (lsm.model.variances[:3], expected)
    unit = known / np.linalg.norm(known, axis=1, keepdims=True)
    assert np.allclose(np.abs(np.diag(lsm.model.modes[:3].reshape(3, -1) @ unit.T)), 1.0, atol=0.01)
    # the rest is nothing: three modes hold all the variance
    assert result.quality[kind]["compactness"][2] > 0.995
    # the scores are the known coefficients (up to each mode's sign)
    for m in range(3):
        r = np.corrcoef(lsm.model.scores[:, m], b[:, m])[0, 1]
        assert abs(r) > 0.999, (m, r)


def test_a_shape_sampled_at_a_subjects_coefficients_is_that_subject(cohort):
    _, template, b, subjects, _, _, result = cohort
    for kind in ("surface", "deformation"):
        lsm = result.models[kind]
        m = lsm.model
        signs = np.sign([np.corrcoef(m.scores[:, k], b[:, k])[0, 1] for k in range(3)])
        i = 5
        coefficients = b[i] * signs  # the known coefficients, in the model's signs
        truth = lsm.vertices + MODES.warp(b[i]).displacement(lsm.vertices)
        verts = lsm.mesh_vertices(coefficients)
        error = np.linalg.norm(verts - truth, axis=1)
        assert error.mean() < 0.05 and error.max() < 0.3, (kind, error.mean(), error.max())
        drawn = lsm.label_map(coefficients)
        for v in (1, 2, 3):
            assert dice(drawn.array == v, subjects[i].array == v) > 0.93, (kind, v)


def test_quality_measures(cohort):
    *_, result = cohort
    for kind in ("surface", "deformation"):
        q = result.quality[kind]
        assert q["modes"] == [1, 2, 3]  # three known modes: the other directions hold no variance and are dropped
        assert np.all(np.diff(q["compactness"]) >= -1e-12) and q["compactness"][-1] <= 1 + 1e-9
        # exact data of three modes: three modes generalise to (almost) nothing, one does not
        assert q["generalization_mm"][2] < 0.05 < q["generalization_mm"][0]
        assert np.all(np.array(q["generalization_se_mm"]) >= 0)
        assert q["specificity_mm"][0] > 0 and len(q["specificity_se_mm"]) == 3
        # correspondence both ways: exact warps carry the template's boundary onto the subject's own,
        # to within the subjects' voxels (2 mm; their boundaries are extracted from label maps)
        c = q["correspondence"]
        assert len(c["subjects"]) == N_SUBJECTS
        assert c["to_boundary_mm"] < 0.8 and c["from_boundary_mm"] < 0.8, c


def test_a_posed_cohort_gives_the_same_model_once_aligned(cohort, tmp_path):
    root, template, b, subjects, ids, folder, result = cohort
    rng = np.random.default_rng(7)
    x = template.grid_points().reshape(-1, 3)
    warps = []
    for bi in b:
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        q *= np.sign(np.linalg.det(q))
        angle = np.radians(8)
        rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        rot = q @ rot @ q.T
        y = MODES.warp(bi)(x) @ rot.T + rng.normal(size=3) * 4
        warps.append((y - x).reshape(template.shape + (3,)))
    posed_folder = write_template_folder(tmp_path, template, warps, subjects, ids)
    aligned = build_shape_models(posed_folder, align="rigid", modes=6, samples=10)
    unposed = build_shape_models(folder, align="rigid", modes=6, samples=10)
    for kind in ("surface", "deformation"):
        a, u = aligned.models[kind].model, unposed.models[kind].model
        angles = np.degrees(subspace_angles(a.modes[:3].reshape(3, -1).T, u.modes[:3].reshape(3, -1).T))
        assert angles.max() < 3.0, (kind, angles)
        assert np.allclose(a.variances[:3], u.variances[:3], rtol=0.05), (kind, a.variances[:3], u.variances[:3])
    # unaligned, the poses swamp the shape
    none = build_shape_models(posed_folder, align="none", modes=6, samples=10)
    assert none.models["surface"].model.variances[0] > 2 * aligned.models["surface"].model.variances[0]


# ----------------------------------------------------------------------------- files and the command


def test_the_model_file_round_trips_without_pickle(cohort, tmp_path):
    *_, result = cohort
    for kind in ("surface", "deformation"):
        lsm = result.models[kind]
        lsm.save(tmp_path / f"{kind}.npz")
        back = LabelShapeModel.load(tmp_path / f"{kind}.npz")
        assert back.kind == kind and back.labels == lsm.labels and back.model.ids == lsm.model.ids
        assert np.allclose(back.model.modes, lsm.model.modes, atol=1e-6)
        assert np.mean(back.label_map([1.0]).array == lsm.label_map([1.0]).array) > 0.999  # modes kept in float32
        with np.load(tmp_path / f"{kind}.npz", allow_pickle=False) as data:
            assert all(data[k].dtype != object for k in data.files)
    np.savez(tmp_path / "other.npz", format=np.array("volreg-kernel-warp"))
    with pytest.raises(VolregIOError, match="not a volreg shape model"):
        LabelShapeModel.load(tmp_path / "other.npz")
    with pytest.raises(VolregIOError, match="does not exist"):
        LabelShapeModel.load(tmp_path / "missing.npz")


def test_the_command_writes_both_models(cohort, tmp_path, capsys):
    _, template, b, subjects, ids, folder, _ = cohort
    out = tmp_path / "model"
    assert main(["shape-model", str(folder), "-o", str(out), "--align", "none", "--modes", "2", "--samples", "20",
                 "--quiet"]) == 0
    line = capsys.readouterr().out
    assert "surface" in line and "deformation" in line
    report = json.loads((out / "report.json").read_text())
    assert report["subjects"] == ids and set(report["models"]) == {"surface", "deformation"}
    for kind in ("surface", "deformation"):
        d = out / kind
        with open(d / "modes.csv") as f:
            rows = list(csv.DictReader(f))
        assert list(rows[0]) == ["mode", "variance", "fraction", "cumulative"] and len(rows) == 2
        assert [float(r["variance"]) for r in rows] == sorted([float(r["variance"]) for r in rows], reverse=True)
        with open(d / "scores.csv") as f:
            scores = list(csv.reader(f))
        assert scores[0] == ["id", "mode_1", "mode_2"] and [r[0] for r in scores[1:]] == ids
        q = json.loads((d / "quality.json").read_text())
        assert len(q["compactness"]) == len(q["generalization_mm"]) == len(q["specificity_mm"]) == 2
        for name in ("model.npz", "quality.png", "mean_label1.vtk", "mean_label1.surf.gii", "mode_1_-2sd.nii.gz",
                     "mode_1_+2sd.nii.gz", "mode_1_+2sd_label2.vtk", "mode_2.gif"):
            assert (d / name).is_file(), (kind, name)
        assert not (d / "mode_3.gif").exists()  # --modes 2
        # -2 and +2 sd of the leading mode move the labels apart
        minus, plus = read_labels(d / "mode_1_-2sd.nii.gz"), read_labels(d / "mode_1_+2sd.nii.gz")
        assert minus.same_geometry(template) and set(np.unique(plus.array)) == {0, 1, 2, 3}
        assert dice(minus.array == 2, plus.array == 2) < 0.9
    # again without --force: refused, the result kept
    assert main(["shape-model", str(folder), "-o", str(out), "--quiet"]) == 2
    assert "--force" in capsys.readouterr().err
    # a sampled shape from the saved model
    sample = tmp_path / "sample"
    assert main(["shape-model", "sample", str(out / "deformation" / "model.npz"), "--coefficients", "1.5,-1",
                 "-o", str(sample)]) == 0
    shape = read_labels(sample / "shape.nii.gz")
    lsm = LabelShapeModel.load(out / "deformation" / "model.npz")
    assert np.array_equal(shape.array, lsm.label_map([1.5, -1]).array)
    assert (sample / "shape_label3.vtk").is_file()
    # a first coefficient below zero, as users type it
    assert main(["shape-model", "sample", str(out / "deformation" / "model.npz"), "--coefficients", "-2,0.5",
                 "-o", str(tmp_path / "negative")]) == 0
    assert np.array_equal(read_labels(tmp_path / "negative" / "shape.nii.gz").array, lsm.label_map([-2, 0.5]).array)


@pytest.mark.parametrize("args, message", [
    (["shape-model", "{tmp}", "-o", "{tmp}/o"], "holds no finished template"),
    (["shape-model", "{folder}", "-o", "{tmp}/o", "--align", "affine"], "--align"),
    (["shape-model", "{folder}", "-o", "{tmp}/o", "--modes", "0"], "--modes"),
    (["shape-model", "{folder}", "-o", "{tmp}/o", "--coefficients", "1"], "--coefficients"),
    (["shape-model", "sample", "{folder}/report.json", "--coefficients", "1", "-o", "{tmp}/o"], "MODEL"),
    (["shape-model", "sample", "{model}", "--coefficients", "1,x", "-o", "{tmp}/o"], "--coefficients"),
    (["shape-model", "sample", "{model}", "--coefficients", "1,1,1,1,1,1,1,1,1,1,1,1", "-o", "{tmp}/o"],
     "--coefficients"),
    (["shape-model", "sample", "{model}", "-o", "{tmp}/o"], "--coefficients"),
    (["shape-model", "{dup}", "-o", "{tmp}/o"], "twice or as a name"),
    (["shape-model", "{secret}", "-o", "{tmp}/o"], "is not JSON"),
    (["shape-model", "{model}", "-o", "{tmp}/o"], "is not a folder"),
    (["shape-model", "sample", "{tampered}", "--coefficients", "1", "-o", "{tmp}/o"], "not a consistent shape model"),
])
def test_bad_command_lines_are_refused_in_one_line(cohort, tmp_path, capsys, args, message):
    *_, folder, result = cohort
    model = tmp_path / "m.npz"
    result.models["deformation"].save(model)
    dup = tmp_path / "dup"
    dup.mkdir()
    (dup / "template.nii.gz").write_bytes((folder / "template.nii.gz").read_bytes())
    (dup / "subjects").symlink_to(folder / "subjects", target_is_directory=True)
    report = json.loads((folder / "report.json").read_text())
    report["subjects"] = report["subjects"][:2] + report["subjects"][:1]
    (dup / "report.json").write_text(json.dumps(report))
    tampered = tmp_path / "t" / "m.npz"
    tampered.parent.mkdir()
    with np.load(model, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    region = arrays["region"]
    arrays["region"] = np.concatenate([region, np.zeros((3,) + region.shape[1:], bool)])  # same count, other shape
    np.savez(tampered, **arrays)
    secret = tmp_path / "secret"
    secret.mkdir()
    (secret / "template.nii.gz").write_bytes((folder / "template.nii.gz").read_bytes())
    (tmp_path / "secret.txt").write_text("SECRET-TOKEN-123\n")
    (secret / "report.json").symlink_to(tmp_path / "secret.txt")  # a report linked to another file
    filled = [a.format(tmp=tmp_path, folder=folder, model=model, dup=dup, tampered=tampered, secret=secret)
              for a in args]
    assert main(filled) == 2
    err = capsys.readouterr().err.strip().splitlines()  # (argparse's usage lines, then) one error line
    assert err[-1].startswith("volreg shape-model: error:") and message in err[-1], err
    assert "SECRET" not in "\n".join(err)
    assert not (tmp_path / "o").exists()


def test_write_functions_refuse_an_existing_result(cohort, tmp_path):
    *_, result = cohort
    write_shape_sample(result.models["surface"], [0.5], tmp_path / "s")
    with pytest.raises(UsageError):
        write_shape_sample(result.models["surface"], [0.5], tmp_path / "s")
    write_shape_sample(result.models["surface"], [-0.5], tmp_path / "s", force=True)
    report = write_shape_models(result, tmp_path / "m")
    assert report["models"]["deformation"]["modes"] == 3


def test_a_cohort_too_large_for_memory_is_refused_before_reading_warps(cohort, monkeypatch):
    *_, folder, _ = cohort
    monkeypatch.setenv("VOLREG_MAX_MEMORY_GB", "0.001")
    with pytest.raises(UsageError, match="would need about .* GB of memory"):
        build_shape_models(folder)


def test_a_rerun_gives_the_same_models_and_quality(cohort):
    *_, folder, result = cohort
    again = build_shape_models(folder, align="none", modes=6, samples=40)
    assert again.quality == result.quality
    for kind in ("surface", "deformation"):
        np.testing.assert_array_equal(again.models[kind].model.modes, result.models[kind].model.modes)


def test_modes_as_a_numpy_integer_and_subjects_listed_by_relative_paths(cohort, tmp_path, monkeypatch):
    root, _, _, _, ids, folder, _ = cohort
    # the template's report naming each subject relative to the folder above the template folder
    moved = tmp_path / "template"
    moved.mkdir()
    for name in ("template.nii.gz",):
        (moved / name).write_bytes((folder / name).read_bytes())
    (moved / "subjects").symlink_to(folder / "subjects", target_is_directory=True)
    for sid in ids:
        (tmp_path / f"{sid}.nii.gz").write_bytes((root / f"{sid}.nii.gz").read_bytes())
    report = json.loads((folder / "report.json").read_text())
    report["subjects"] = [{"id": r["id"], "path": f"{r['id']}.nii.gz"} for r in report["subjects"]]
    (moved / "report.json").write_text(json.dumps(report))
    monkeypatch.chdir(root.parent)  # not where the subjects are
    result = build_shape_models(moved, align="none", modes=np.int64(2), samples=5)
    assert result.models["surface"].model.n_modes == 2
    assert len(result.quality["surface"]["correspondence"]["subjects"]) == len(ids)
