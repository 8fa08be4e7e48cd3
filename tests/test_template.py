"""``volreg template`` and :func:`volreg.template.build_template` on cohorts with a known mean shape.

Four subjects are one base shape deformed by a local bump and by its opposite, at two places:
their mean shape is the base (to first order), which none of them is.  An unbiased template
must come closer to the base than any subject.  A second cohort has a thin shell (two voxels)
that the subjects' bumps move by more than its thickness, in opposite directions: the template
must keep it.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from volreg.cli import main
from volreg.errors import CohortInterrupted, UsageError
from volreg.evaluation.metrics import dice
from volreg.grid import LabelVolume
from volreg.io import read_labels, write_labels
from volreg.io.fields import read_displacement
from volreg.io.frames import read_frames
from volreg.synthetic import GaussianBumps, deform_labels
from volreg.template import build_template
from volreg.warp.linear import fit_linear
from volreg.warp.resample import resample_labels

from helpers import TEST_PROTOCOL

pytest.importorskip("dask.distributed")

LABELS = (1, 2, 3, 4)


def _base(n=36, spacing=2.0) -> LabelVolume:
    """An ellipsoid with three inner structures, none on a symmetry axis of the others."""
    x = np.indices((n, n, n)).reshape(3, -1).T * spacing - (n - 1) * spacing / 2
    a = np.zeros(len(x), np.uint8)
    a[((x / [28, 20, 15]) ** 2).sum(1) <= 1] = 1
    a[(((x - [8, 0, 0]) / [11, 8, 7]) ** 2).sum(1) <= 1] = 2
    a[(((x + [13, 0, 0]) / [7, 7, 6]) ** 2).sum(1) <= 1] = 3
    a[(((x - [-2, 10, 5]) / [6, 5, 5]) ** 2).sum(1) <= 1] = 4
    return LabelVolume(a.reshape(n, n, n), np.full(3, -(n - 1) * spacing / 2), np.full(3, spacing), np.eye(3))


def _mean_dice(a: LabelVolume, b: LabelVolume) -> float:
    w = b.array if b.same_geometry(a) else resample_labels(b, a.grid_points(), method="nearest")
    return float(np.mean([dice(a.array == v, w == v) for v in LABELS]))


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    root = tmp_path_factory.mktemp("cohort")
    base = _base()
    rows = ["id,path"]
    subjects = {}
    for j, (centre, amplitude) in enumerate((([9, 0, 0], [0, 0, 5]), ([-11, 6, 0], [0, 5, 0]))):
        for sign, tag in ((1, "p"), (-1, "m")):
            bump = GaussianBumps(np.array([centre], float), sign * np.array([amplitude], float), 11.0)
            sid = f"s{j}{tag}"
            subjects[sid] = deform_labels(base, bump)
            write_labels(subjects[sid], root / f"{sid}.nii.gz")
            rows.append(f"{sid},{sid}.nii.gz")
    (root / "manifest.csv").write_text("\n".join(rows) + "\n")
    (root / "test.toml").write_text(TEST_PROTOCOL)
    out = root / "out"
    result = build_template(root / "manifest.csv", out, iterations=3, workers=1, protocol=str(root / "test.toml"))
    return root, base, subjects, out, result


def test_the_template_is_nearer_the_mean_shape_than_any_subject(cohort):
    _, base, subjects, out, result = cohort
    nearest_subject = max(_mean_dice(base, s) for s in subjects.values())
    template = read_labels(out / "template.nii.gz")
    assert set(np.unique(template.array)) == {0, *LABELS}
    assert _mean_dice(base, template) > nearest_subject + 0.03


def test_the_subjects_displacements_average_to_little(cohort):
    _, _, subjects, out, result = cohort
    report = json.loads((out / "report.json").read_text())
    template = read_labels(out / "template.nii.gz")
    fields = [read_displacement(out / "subjects" / sid / "warp.nii.gz") for sid in subjects]
    for _, grid in fields:
        assert grid.same_geometry(template, atol=1e-3)  # the pull-back field on the template grid
    inside = template.array > 0
    mean = np.mean([u[inside] for u, _ in fields], axis=0)
    single = np.mean([np.linalg.norm(u[inside], axis=1).mean() for u, _ in fields])
    assert np.linalg.norm(mean, axis=1).mean() == pytest.approx(report["mean_displacement_mm"]["mean"], rel=1e-6)
    assert report["mean_displacement_mm"]["mean"] < 0.5 * single  # the subjects move, their mean much less
    assert report["mean_displacement_mm"]["mean"] < 1.0  # mm, on a 2 mm grid


def test_outputs_and_report(cohort):
    _, _, subjects, out, result = cohort
    frames, affine = read_frames(out / "probabilities.nii.gz")
    template = read_labels(out / "template.nii.gz")
    assert frames.shape == (len(LABELS), *template.shape)
    assert frames.min() >= 0 and frames.max() <= 1 and frames.sum(axis=0).max() <= 1 + 1e-6
    np.testing.assert_allclose(affine, template.affine, atol=1e-4)
    # the subjects in template space vote for the template's labels: the vote of the probabilities
    # agrees with the template almost everywhere (the template is that of the previous round, moved)
    voted = np.array((0, *LABELS))[np.concatenate([1 - frames.sum(0)[None], frames]).argmax(0)]
    labelled = (template.array > 0) | (voted > 0)
    assert np.mean(voted[labelled] == template.array[labelled]) > 0.95
    report = json.loads((out / "report.json").read_text())
    assert [s["id"] for s in report["subjects"]] == list(subjects)
    assert {r["id"] for r in report["ranking"]} == set(subjects)
    assert report["stopped"] in ("tolerance", "no progress", "iterations")
    for it in report["iterations"]:
        assert it["update_max_mm"] >= it["update_mean_mm"] >= 0 and 0 < it["mean_dice"] <= 1
        assert set(it["sharpness"]) <= {str(v) for v in LABELS}
    for sid in subjects:
        assert (out / "subjects" / sid / "warped.nii.gz").is_file()
        assert (out / "subjects" / sid / "model.npz").is_file()
    assert (out / "report.png").stat().st_size > 1000
    assert (out / "labels.csv").read_text().splitlines()[0] == "frame,label,template_voxels,sharpness"


def test_a_finished_template_is_not_replaced_without_force(cohort):
    root, _, _, out, _ = cohort
    with pytest.raises(UsageError, match="finished template"):
        build_template(root / "manifest.csv", out, iterations=3, workers=1)
    assert main(["template", str(root / "manifest.csv"), "-o", str(out), "--quiet"]) == 2


def test_an_unfinished_run_continues_without_registering_again(cohort, tmp_path):
    root, _, _, out, _ = cohort
    models = {p: p.stat().st_mtime_ns for p in (out / "iterations").rglob("model.npz")}
    (out / "report.json").unlink()  # as if stopped after the last registrations
    again = build_template(root / "manifest.csv", out, iterations=3, workers=1, protocol=str(root / "test.toml"))
    assert {p: p.stat().st_mtime_ns for p in (out / "iterations").rglob("model.npz")} == models
    np.testing.assert_array_equal(again.template.array, read_labels(out / "template.nii.gz").array)


@pytest.mark.parametrize("option, value", [("--iterations", "0"), ("--tolerance", "-1"), ("--spacing", "nan")])
def test_bad_options(cohort, tmp_path, capsys, option, value):
    root = cohort[0]
    assert main(["template", str(root / "manifest.csv"), "-o", str(tmp_path / "o"), option, value]) == 2
    assert option in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_one_subject_is_refused(tmp_path):
    write_labels(_base(n=12), tmp_path / "a.nii.gz")
    (tmp_path / "m.csv").write_text("id,path\na,a.nii.gz\n")
    with pytest.raises(UsageError, match="at least two"):
        build_template(tmp_path / "m.csv", tmp_path / "out")


def test_a_subject_sharing_no_label_is_named(tmp_path):
    base = _base(n=20)
    write_labels(base, tmp_path / "a.nii.gz")
    write_labels(base.with_array(np.where(base.array > 0, base.array + 10, 0).astype(np.uint8)), tmp_path / "b.nii.gz")
    (tmp_path / "m.csv").write_text("id,path\na,a.nii.gz\nb,b.nii.gz\n")
    with pytest.raises(UsageError, match="Subject `b`.*cannot be aligned"):
        build_template(tmp_path / "m.csv", tmp_path / "out")


def test_a_subject_whose_registration_fails_is_left_out_with_a_warning(cohort, tmp_path):
    root = cohort[0]
    for sid in ("s0p", "s0m", "s1p"):
        (tmp_path / f"{sid}.nii.gz").write_bytes((root / f"{sid}.nii.gz").read_bytes())
    (tmp_path / "bad.nii.gz").write_bytes((root / "s1m.nii.gz").read_bytes())
    (tmp_path / "m.csv").write_text("id,path\ns0p,s0p.nii.gz\ns0m,s0m.nii.gz\ns1p,s1p.nii.gz\nbad,bad.nii.gz\n")

    def progress(stage, done, total):
        if stage == "template first template" and done == total:  # read by the start; unreadable for the registrations
            (tmp_path / "bad.nii.gz").write_bytes(b"not an image")

    warnings = []
    result = build_template(tmp_path / "m.csv", tmp_path / "out", iterations=1, workers=1, progress=progress,
                            warn=warnings.append, protocol=str(root / "test.toml"))
    assert len(warnings) == 1 and "subject bad left out of iteration 1" in warnings[0]
    assert result.report["left_out"] == ["bad"] and set(result.subjects) == {"s0p", "s0m", "s1p"}
    assert not (tmp_path / "out" / "subjects" / "bad").exists()


# ----------------------------------------------------------------------------- a thin shell


def _shelled(n=32, spacing=2.0, thickness=4.0) -> LabelVolume:
    """An ellipsoidal core (label 1) in a shell ``thickness`` mm thick (label 2), with an inner
    structure off the centre (label 3)."""
    x = np.indices((n, n, n)).reshape(3, -1).T * spacing - (n - 1) * spacing / 2
    axes = np.array([24.0, 18.0, 15.0])
    a = np.zeros(len(x), np.uint8)
    a[((x / axes) ** 2).sum(1) <= 1] = 2
    a[((x / (axes - thickness)) ** 2).sum(1) <= 1] = 1
    a[(((x - [-8, 4, 2]) / [6, 5, 5]) ** 2).sum(1) <= 1] = 3
    return LabelVolume(a.reshape(n, n, n), np.full(3, -(n - 1) * spacing / 2), np.full(3, spacing), np.eye(3))


def _aligned_dice(known: LabelVolume, built: LabelVolume, label: int) -> float:
    """Dice of ``label`` between the known shape and the built template read through the affine
    map that aligns them (the template's global pose is free)."""
    to_built = fit_linear(known, built, kind="affine").map
    read = resample_labels(built, to_built(known.grid_points().reshape(-1, 3))).reshape(known.shape)
    return float(dice(known.array == label, read == label))


@pytest.fixture(scope="module")
def shell_cohort(tmp_path_factory):
    """Bumps normal to the shell at the eight octants, signs alternating so that they hold no
    linear part; pairs of opposite bumps (5 mm and 2.5 mm) average to the base."""
    root = tmp_path_factory.mktemp("shell")
    base = _shelled()
    axes = np.array([24.0, 18.0, 15.0])
    octants = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    centres = octants / np.sqrt(3) * axes
    normals = centres / axes ** 2
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    signs = np.prod(octants, axis=1)[:, None]
    rows = ["id,path"]
    subjects = {}
    for j, size in enumerate((5.0, 2.5)):
        for sign, tag in ((1, "p"), (-1, "m")):
            sid = f"s{j}{tag}"
            subjects[sid] = deform_labels(base, GaussianBumps(centres, sign * size * signs * normals, 11.0))
            write_labels(subjects[sid], root / f"{sid}.nii.gz")
            rows.append(f"{sid},{sid}.nii.gz")
    (root / "manifest.csv").write_text("\n".join(rows) + "\n")
    (root / "test.toml").write_text(TEST_PROTOCOL)
    out = root / "out"
    result = build_template(root / "manifest.csv", out, iterations=2, workers=1, protocol=str(root / "test.toml"))
    return root, base, subjects, out, result


def test_a_thin_shell_moved_further_than_its_thickness_is_kept(shell_cohort):
    _, base, subjects, out, result = shell_cohort
    nearest_subject = max(_aligned_dice(base, s, 2) for s in subjects.values())
    assert nearest_subject < 0.85  # the subjects' shells overlap the base's little
    shell = _aligned_dice(base, read_labels(out / "template.nii.gz"), 2)
    assert shell > 0.85 and shell > nearest_subject + 0.03
    start = result.report["linear_start"]
    assert start["first_template"] == "medoid" and start["medoid"] in subjects
    assert start["medoid"] == max(start["medoid_mean_dice"], key=start["medoid_mean_dice"].get)


class _Killed(Exception):
    """Stands for the process's end."""


def test_a_killed_run_continues_to_the_same_bytes(shell_cohort, tmp_path):
    root, _, _, reference, _ = shell_cohort
    options = {"iterations": 2, "workers": 1, "protocol": str(root / "test.toml")}
    out = tmp_path / "out"

    def notify(line):  # once the first round's registrations are done, before the next template
        if line.startswith("template iteration 1"):
            raise _Killed

    with pytest.raises(_Killed):
        build_template(root / "manifest.csv", out, notify=notify, **options)
    assert not (out / "iterations" / "02").exists()

    def progress(stage, done, total):  # the second round: killed after its first registration
        if stage == "registrations" and done == 1 and (out / "iterations" / "02" / "template.nii.gz").is_file():
            raise KeyboardInterrupt

    with pytest.raises(CohortInterrupted):
        build_template(root / "manifest.csv", out, progress=progress, **options)
    assert not (out / "report.json").exists()
    done = list((out / "iterations" / "02" / "pairs").glob("*/batch_row.json"))
    assert 1 <= len(done) < 4

    build_template(root / "manifest.csv", out, **options)
    for name in ("template.nii.gz", "probabilities.nii.gz", "labels.csv"):
        assert (out / name).read_bytes() == (reference / name).read_bytes(), name
    for sid in ("s0p", "s1m"):
        assert (out / "subjects" / sid / "warp.nii.gz").read_bytes() == \
            (reference / "subjects" / sid / "warp.nii.gz").read_bytes()


def test_the_shape_model_of_the_template_finds_the_cohorts_two_bumps(cohort, tmp_path, capsys):
    """The cohort varies by two bumps, each once up and once down: from the template's own
    registrations, two modes hold most of the deformation, and each separates one pair."""
    _, _, subjects, out, _ = cohort
    model_dir = tmp_path / "model"
    assert main(["shape-model", str(out), "-o", str(model_dir), "--samples", "20", "--quiet"]) == 0
    assert "4 subjects" in capsys.readouterr().out
    from volreg.shape_models import LabelShapeModel

    for kind in ("surface", "deformation"):
        lsm = LabelShapeModel.load(model_dir / kind / "model.npz")
        q = json.loads((model_dir / kind / "quality.json").read_text())
        assert q["compactness"][1] > 0.8, (kind, q["compactness"])
        scores = dict(zip(lsm.model.ids, lsm.model.scores[:, :2]))
        for pair in (("s0p", "s0m"), ("s1p", "s1m")):
            a, b = scores[pair[0]], scores[pair[1]]
            k = int(np.argmax(np.abs(a)))  # the mode of this pair's bump: opposite signs on it
            assert a[k] * b[k] < 0 and abs(b[k]) > abs(b[1 - k]), (kind, pair, a, b)
        c = q["correspondence"]
        assert c["to_boundary_mm"] < 2.0 and c["from_boundary_mm"] < 2.0, c  # 2 mm voxels
