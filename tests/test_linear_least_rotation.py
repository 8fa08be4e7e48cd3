"""The linear stage's least rotation: of the maps that fit a symmetric object equally well, the least
rotated is kept (so that a turned cube is not reported as a wrong orientation header), and the
review's suggestions name no kind of linear stage that is already set."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from volreg import LabelVolume
from volreg.evaluation.review import ReviewLimits, review_registration
from volreg.io import write_labels
from volreg.warp.linear import fit_linear
from volreg.warp.linear_refine import symmetry_turns

from helpers import TEST_PROTOCOL, run

N = 40


def _offsets(dim: int) -> np.ndarray:
    """Voxel centres of an N^dim grid about its centre (index units = mm)."""
    return np.stack(np.meshgrid(*[np.arange(N)] * dim, indexing="ij"), -1).astype(float) - (N - 1) / 2


def _volume(array: np.ndarray) -> LabelVolume:
    dim = array.ndim
    return LabelVolume(array.astype(np.uint8), np.zeros(dim), np.ones(dim), np.eye(dim))


def _turned(dim: int, degrees: float, axis=(0.0, 0.0, 1.0)) -> np.ndarray:
    if dim == 2:
        t = np.radians(degrees)
        return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    return Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis, float)).as_matrix()


def cube(dim: int = 3, rotation: np.ndarray | None = None, half: float = 8.0) -> LabelVolume:
    """A cube (square) of side 2 ``half`` mm at the grid's centre, turned by ``rotation``."""
    x = _offsets(dim) @ (np.eye(dim) if rotation is None else rotation)  # R^T x, row-wise
    return _volume(np.all(np.abs(x) <= half, axis=-1))


def chiral(rotation: np.ndarray | None = None, mirrored: bool = False) -> LabelVolume:
    """A ball with three smaller balls of other labels on three axes at three distances: no turn
    carries it onto itself, nor onto its mirror image."""
    x = _offsets(3) @ (np.eye(3) if rotation is None else rotation)
    if mirrored:
        x = x * [-1.0, 1.0, 1.0]
    array = np.zeros((N,) * 3, np.uint8)
    array[(x ** 2).sum(-1) < 14 ** 2] = 1
    for label, centre in ((2, (9.0, 0.0, 0.0)), (3, (0.0, 7.0, 0.0)), (4, (0.0, 0.0, 5.0))):
        array[((x - centre) ** 2).sum(-1) < 4 ** 2] = label
    return _volume(array)


def _angle(matrix: np.ndarray) -> float:
    dim = len(matrix)
    cos = (np.trace(matrix) - (dim - 2)) / 2 if dim == 3 else matrix[0, 0]
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def least_cube_rotation(rotation: np.ndarray) -> float:
    """The least rotation of ``rotation`` after a turn that carries the cube (square) onto itself."""
    return min(_angle(rotation @ s) for s in [np.eye(len(rotation))] + symmetry_turns([np.eye(len(rotation))]))


@pytest.mark.parametrize("dim", [2, 3])
def test_symmetry_turns_are_the_rotations_of_the_cube(dim):
    turns = symmetry_turns([np.eye(dim)])
    assert len(turns) == (3 if dim == 2 else 23)
    for s in turns:
        np.testing.assert_allclose(s @ s.T, np.eye(dim), atol=1e-12)
        assert np.isclose(np.linalg.det(s), 1.0) and not np.allclose(s, np.eye(dim))
    frame = _turned(dim, 30.0, (1.0, 2.0, 3.0) / np.sqrt(14.0))
    more = symmetry_turns([np.eye(dim), frame])
    # another frame, other turns (in 2-D turns commute: a square's are the same in every frame)
    assert len(more) == len(turns) if dim == 2 else len(more) > len(turns)
    assert len(symmetry_turns([np.eye(dim), np.eye(dim)])) == len(turns)  # each turn once


CUBE_TURNS = [(45.0, (0, 0, 1)), (135.0, (0, 0, 1)), (45.0, (1, 0, 0)), (60.0, (1, 1, 0)), (30.0, (0, 1, 0)),
              (90.0, (0, 0, 1)), (170.0, (0, 0, 1))]


@pytest.mark.parametrize("kind", ["rigid", "similarity", "affine"])
@pytest.mark.parametrize("degrees, axis", CUBE_TURNS, ids=[f"{d:g} deg about {a}" for d, a in CUBE_TURNS])
def test_turned_cube_reported_by_its_least_rotation(kind, degrees, axis):
    rotation = _turned(3, degrees, axis)
    fit = fit_linear(cube(), cube(rotation=rotation), kind=kind)
    want = least_cube_rotation(rotation)
    assert fit.map.describe()["rotation_deg"] == pytest.approx(want, abs=2.0), fit.log.get("least_rotation")
    if want < ReviewLimits().max_rotation_deg - 2.0:  # no false alarm
        assert fit.map.describe()["rotation_deg"] < ReviewLimits().max_rotation_deg


def rectangle(rotation: np.ndarray | None = None) -> LabelVolume:
    """A rectangle of 18 x 10 mm at the grid's centre, turned by ``rotation``: a half turn carries it
    onto itself."""
    x = _offsets(2) @ (np.eye(2) if rotation is None else rotation)
    return _volume((np.abs(x[..., 0]) <= 9.0) & (np.abs(x[..., 1]) <= 5.0))


@pytest.mark.parametrize("kind", ["rigid", "affine"])
@pytest.mark.parametrize("degrees, least", [(150.0, 30.0), (120.0, 60.0), (100.0, 80.0), (30.0, 30.0)])
def test_turned_rectangle_reported_by_its_least_rotation(kind, degrees, least):
    fit = fit_linear(rectangle(), rectangle(rotation=_turned(2, degrees)), kind=kind)
    assert fit.map.describe()["rotation_deg"] == pytest.approx(least, abs=2.0)


@pytest.mark.parametrize("degrees", [100.0, 150.0])
def test_object_without_symmetry_keeps_its_turn(degrees):
    """No turn carries the object onto itself: every other map fits worse, and the turn found is
    the one the images differ by (above the review's limit: a true alarm)."""
    fit = fit_linear(chiral(), chiral(rotation=_turned(3, degrees)), kind="rigid")
    assert fit.map.describe()["rotation_deg"] == pytest.approx(degrees, abs=3.0)
    searched = fit.log["least_rotation"]
    assert searched["tried"] >= 23 and searched["kept_rotation_deg"] == searched["rotation_deg"]


def test_small_turns_search_nothing():
    fit = fit_linear(cube(), cube(rotation=_turned(3, 20.0)), kind="rigid")
    assert "least_rotation" not in fit.log and fit.map.describe()["rotation_deg"] == pytest.approx(20.0, abs=2.0)


def test_register_reports_a_turned_cube_without_an_alarm(tmp_path, capsys):
    write_labels(cube(), tmp_path / "f.nii.gz")
    write_labels(cube(rotation=_turned(3, 45.0)), tmp_path / "m.nii.gz")
    assert run(["register", tmp_path / "f.nii.gz", tmp_path / "m.nii.gz", "-o", tmp_path / "out", "--quiet"]) == 0
    assert "orientation header" not in capsys.readouterr().err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["linear"]["rotation_deg"] == pytest.approx(45.0, abs=2.0)
    assert report["review"]["plausible"] and report["mean_dice"]["after"] > 0.9


# ----------------------------------------------------------------------------- the review's suggestions

def _scores(dice: float) -> tuple[dict, dict, dict]:
    labels = [0, 1, 2, 3]
    before = {v: {"dice": 0.3, "mean_surface_distance_mm": 1.0} for v in labels}
    after = {v: {"dice": dice, "mean_surface_distance_mm": 1.0} for v in labels}
    return before, after, {v: 5000 for v in labels}


TURNED = dict(matrix=np.eye(3).tolist(), translation=[0.0] * 3, rotation_deg=120.0, scales=[1.0] * 3,
              determinant=1.0)
STRAIGHT = dict(TURNED, rotation_deg=0.0)


@pytest.mark.parametrize("kind", [None, "none", "rigid", "similarity", "affine"])
@pytest.mark.parametrize("case", ["rotation", "mean Dice", "label Dice", "labels' Dice"])
def test_suggestions_name_no_kind_already_set(kind, case):
    before, after, voxels = _scores(0.3 if case == "mean Dice" else 0.95)
    if case == "label Dice":
        after[2]["dice"] = 0.2
    if case == "labels' Dice":
        for v in (1, 2, 3):
            after[v]["dice"] = 0.4
    limits = ReviewLimits(max_listed=2) if case == "labels' Dice" else ReviewLimits()
    findings = review_registration(before, after, voxel_mm=1.0, label_voxels=voxels, limits=limits, linear_kind=kind,
                                   linear=TURNED if case == "rotation" else STRAIGHT)
    wanted = {"rotation": "rotation_deg", "mean Dice": "mean_dice", "label Dice": "dice", "labels' Dice": "dice"}[case]
    messages = [f.message for f in findings if f.figure == wanted]
    assert messages, [f.message for f in findings]
    for message in messages:
        if kind is not None:
            assert f'kind = "{kind}"' not in message, message
        if kind == "rigid":
            assert ("mirrored" in message) != (case == "rotation"), message
            assert ('kind = "none"' in message) == (case == "rotation"), message
        else:
            assert 'kind = "rigid"' in message, message


def test_mirrored_volume_under_a_rigid_stage_is_named_as_such(tmp_path, capsys):
    write_labels(chiral(), tmp_path / "f.nii.gz")
    write_labels(chiral(mirrored=True), tmp_path / "m.nii.gz")
    (tmp_path / "rigid.toml").write_text(TEST_PROTOCOL + '[linear]\nkind = "rigid"\n')
    assert run(["register", tmp_path / "f.nii.gz", tmp_path / "m.nii.gz", "-o", tmp_path / "out", "--quiet",
                "--protocol", tmp_path / "rigid.toml"]) == 0
    err = capsys.readouterr().err
    assert "mirrored" in err and 'kind = "rigid"' not in err, err
