"""The plausibility review of a registration, on synthetic figures."""

import json

import numpy as np
import pytest

from volreg.evaluation.review import (
    Finding,
    ReviewLimits,
    findings_summary,
    judged_labels,
    label_voxel_counts,
    review_registration,
)

GOOD_LINEAR = dict(matrix=np.eye(3).tolist(), translation=[4.0, -2.0, 1.0], rotation_deg=20.0,
                   scales=[1.1, 1.0, 0.9], determinant=0.99)


def _case(n=10, before=0.7, after=0.93, distance=0.8, voxels=5000):
    """Scores of labels 1..n (and the background 0), as label_scores gives them."""
    labels = [0] + list(range(1, n + 1))
    scores_before = {v: {"dice": before, "mean_surface_distance_mm": 3.0, "hd95_mm": 6.0} for v in labels}
    scores_after = {v: {"dice": after, "mean_surface_distance_mm": distance, "hd95_mm": 2.0} for v in labels}
    return scores_before, scores_after, {v: voxels for v in labels}


def _review(scores_before, scores_after, label_voxels, **kw):
    kw.setdefault("voxel_mm", 1.0)
    kw.setdefault("linear", GOOD_LINEAR)
    return review_registration(scores_before, scores_after, label_voxels=label_voxels, **kw)


def _one_line(findings):
    for f in findings:
        assert isinstance(f, Finding) and f.message and "\n" not in f.message


def test_a_good_registration_gives_no_findings():
    findings = _review(*_case())
    assert findings == []
    summary = findings_summary(findings)
    assert summary["plausible"] is True and summary["findings"] == []
    assert summary["limits"]["min_voxels"] == 100


def test_distance_rule_names_the_label_the_figure_and_the_limit():
    before, after, voxels = _case()
    after[7]["mean_surface_distance_mm"] = 4.1
    findings = _review(before, after, voxels)
    assert len(findings) == 1
    f = findings[0]
    assert (f.label, f.figure, f.value, f.limit, f.labels) == (7, "mean_surface_distance_mm", 4.1, 2.0, (7,))
    assert "label 7" in f.message and "4.1 mm" in f.message and "limit 2.0 mm" in f.message
    assert "try" in f.message
    _one_line(findings)


@pytest.mark.parametrize("voxel_mm, distance, fires, limit", [
    (1.0, 2.5, True, 2.0),    # 2 voxels = 2 mm
    (1.5, 2.5, False, 3.0),   # 2 voxels of 1.5 mm = 3 mm
    (1.5, 3.2, True, 3.0),
    (0.5, 1.5, False, 2.0),   # the 2 mm floor on a fine grid
    (0.5, 2.1, True, 2.0),
])
def test_distance_limit_is_two_voxels_or_two_mm(voxel_mm, distance, fires, limit):
    before, after, voxels = _case()
    after[3]["mean_surface_distance_mm"] = distance
    findings = _review(before, after, voxels, voxel_mm=voxel_mm)
    assert [f.label for f in findings] == ([3] if fires else [])
    if fires:
        assert findings[0].limit == pytest.approx(limit)


def test_low_dice_rule():
    before, after, voxels = _case()
    before[4]["dice"], after[4]["dice"] = 0.35, 0.42  # improved, yet below 0.5
    findings = _review(before, after, voxels)
    assert [(f.label, f.figure) for f in findings] == [(4, "dice")]
    assert findings[0].limit == 0.5 and "label 4" in findings[0].message and "Dice 0.42" in findings[0].message


@pytest.mark.parametrize("after_dice, fires", [(0.80, True), (0.86, False)])
def test_dice_drop_rule(after_dice, fires):
    before, after, voxels = _case()
    before[5]["dice"], after[5]["dice"] = 0.90, after_dice  # drops of 0.10 and 0.04
    findings = _review(before, after, voxels)
    assert [(f.label, f.figure) for f in findings] == ([(5, "dice_drop")] if fires else [])
    if fires:
        f = findings[0]
        assert f.value == pytest.approx(0.10) and f.limit == 0.05
        assert "label 5" in f.message and "from 0.90 to 0.80" in f.message


def test_mean_dice_rule():
    findings = _review(*_case(before=0.5, after=0.55))  # no label below 0.5, the mean below 0.6
    assert [(f.label, f.figure) for f in findings] == [(None, "mean_dice")]
    f = findings[0]
    assert f.value == pytest.approx(0.55) and f.limit == 0.6 and f.labels == tuple(range(1, 11))
    assert "mean Dice" in f.message and "0.55" in f.message and "10 judged labels" in f.message


def test_rotation_rule_suggests_the_headers_or_a_rigid_stage():
    linear = dict(GOOD_LINEAR, rotation_deg=178.0)
    findings = _review(*_case(), linear=linear)
    assert [(f.label, f.figure, f.value, f.limit) for f in findings] == [(None, "rotation_deg", 178.0, 60.0)]
    text = findings[0].message
    assert "178.0 deg" in text and "limit 60.0 deg" in text and "header" in text
    assert 'kind = "rigid"' in text and '"none"' in text


@pytest.mark.parametrize("scales, value, limit", [([2.0, 1.0, 1.0], 2.0, 1.67), ([1.0, 0.9, 0.5], 0.5, 0.6)])
def test_scale_rule(scales, value, limit):
    findings = _review(*_case(), linear=dict(GOOD_LINEAR, scales=scales))
    assert [(f.figure, f.value, f.limit) for f in findings] == [("scale", value, limit)]
    assert "spacing" in findings[0].message


def test_no_linear_part_is_not_judged():
    assert _review(*_case(), linear=None) == []


def test_folding_rule():
    findings = _review(*_case(), folded_fraction=0.0012)
    assert [(f.label, f.figure, f.value, f.limit) for f in findings] == [(None, "folded_fraction", 0.0012, 0.0)]
    assert "0.12 %" in findings[0].message and "lambda_fold" in findings[0].message


def test_kernel_warp_left_out_rule():
    """A kernel warp left out for lowering the overlap is reported, with both figures and the
    coarser grid's spacing; one that was kept is not."""
    kept = {"dice_linear": 0.91, "dice_warp": 0.93, "margin": 0.02, "kept": "warp"}
    assert _review(*_case(), kernel_warp=kept) == []
    left_out = {"dice_linear": 0.969, "dice_warp": 0.885, "margin": 0.02, "kept": "linear"}
    findings = _review(*_case(), kernel_warp=left_out, voxel_mm=5.0)
    _one_line(findings)
    assert [(f.label, f.figure, f.limit) for f in findings] == [(None, "kernel_warp_dice_drop", 0.02)]
    assert findings[0].value == pytest.approx(0.084)
    assert "0.969" in findings[0].message and "0.885" in findings[0].message and "5 mm" in findings[0].message


def test_kernel_warp_left_out_with_cut_labels_names_them():
    left_out = {"dice_linear": 0.965, "dice_warp": 0.935, "margin": 0.02, "kept": "linear"}
    findings = _review(*_case(), kernel_warp=left_out, cut_labels=iter([2, 1]))
    _one_line(findings)
    assert "labels [1, 2] are cut by an image edge or absent from one volume" in findings[0].message
    assert "cut by" not in _review(*_case(), kernel_warp=left_out)[0].message


def test_whole_registration_findings_come_first():
    before, after, voxels = _case()
    after[2]["mean_surface_distance_mm"] = 5.0
    findings = _review(before, after, voxels, linear=dict(GOOD_LINEAR, rotation_deg=90.0), folded_fraction=0.01)
    assert [f.figure for f in findings] == ["rotation_deg", "folded_fraction", "mean_surface_distance_mm"]


def test_small_labels_are_not_judged():
    before, after, voxels = _case()
    # Label 6: 99 voxels, hopeless figures, not judged; label 8: 100 voxels, judged.
    for v in (6, 8):
        after[v].update(dice=0.1, mean_surface_distance_mm=9.0)
    voxels[6], voxels[8] = 99, 100
    findings = _review(before, after, voxels)
    assert {f.label for f in findings} == {8}
    assert {f.figure for f in findings} == {"mean_surface_distance_mm", "dice", "dice_drop"}
    # A label absent from the fixed volume's counts (present only in the moving one) is not judged.
    del voxels[8]
    assert _review(before, after, voxels) == []


def test_cut_labels_are_not_judged_nor_in_the_mean():
    before, after, voxels = _case(n=3, after=0.85)
    after[2].update(dice=0.0, mean_surface_distance_mm=20.0)  # the mean Dice with it 0.57, without it 0.85
    findings = _review(before, after, voxels, cut_labels=[2])
    assert findings == []
    assert {f.label for f in _review(before, after, voxels)} == {2, None}


def test_labels_without_interior_are_not_judged():
    before, after, voxels = _case(n=4)
    for v in (2, 3):
        after[v].update(dice=0.3, mean_surface_distance_mm=12.0)
    # Label 2: a sheet or specks (no interior voxel); label 3: 2 % interior, judged.
    interior = {1: 3000, 2: 0, 3: 100, 4: 2500}
    findings = _review(before, after, voxels, label_interior=interior)
    assert {f.label for f in findings} == {3}
    assert judged_labels(after, label_voxels=voxels, label_interior=interior) == [1, 3, 4]
    assert judged_labels(after, label_voxels=voxels) == [1, 2, 3, 4]
    assert judged_labels(after, label_voxels=voxels, label_interior=interior, cut_labels=[4],
                         limits=ReviewLimits(min_interior_fraction=0.5)) == [1]


def test_label_voxel_counts_3d():
    a = np.zeros((9, 9, 9), dtype=np.int16)
    a[1:6, 1:6, 1:6] = 1  # a 5-voxel cube: 3 x 3 x 3 interior
    a[7, :, :] = 2  # a one-voxel sheet: no interior
    a[0:3, 6:9, 6:9] = 3  # a 3-voxel cube in a corner: only its centre (1, 7, 7) is interior
    a[0:2, 0, 0:3] = 4  # a 2 x 1 x 3 rod: no interior
    voxels, interior = label_voxel_counts(a)
    assert voxels == {1: 125, 2: 81, 3: 27, 4: 6}
    assert interior == {1: 27, 2: 0, 3: 1, 4: 0}
    a[0, 7, 7] = 0  # its centre's neighbour towards the edge leaves the label
    assert label_voxel_counts(a)[1][3] == 0


def test_label_voxel_counts_2d_and_large_values():
    a = np.zeros((6, 7), dtype=np.int64)
    a[1:5, 1:6] = 2**40  # 4 x 5: 2 x 3 interior
    a[5, :] = -3
    voxels, interior = label_voxel_counts(a)
    assert voxels == {2**40: 20, -3: 7} and interior == {2**40: 6, -3: 0}
    with pytest.raises(ValueError, match="`array`"):
        label_voxel_counts(np.zeros((3, 3)))


def test_background_is_not_judged():
    before, after, voxels = _case()
    after[0].update(dice=0.2, mean_surface_distance_mm=30.0)
    assert _review(before, after, voxels) == []


def test_a_label_lost_by_the_warp_fails_on_dice_not_on_distance():
    before, after, voxels = _case()
    after[9].update(dice=0.0, mean_surface_distance_mm=float("nan"), hd95_mm=float("nan"))
    findings = _review(before, after, voxels)
    assert [(f.label, f.figure) for f in findings] == [(9, "dice"), (9, "dice_drop")]
    json.dumps(findings_summary(findings), allow_nan=False)


def test_five_failing_labels_give_five_findings_six_give_one():
    before, after, voxels = _case(n=20)
    for v, d in zip(range(1, 6), (3.0, 5.5, 2.5, 4.0, 6.5)):
        after[v]["mean_surface_distance_mm"] = d
    five = _review(before, after, voxels)
    assert [f.label for f in five] == [5, 2, 4, 1, 3]  # worst first
    after[11]["mean_surface_distance_mm"] = 2.2
    six = _review(before, after, voxels)
    assert len(six) == 1
    f = six[0]
    assert f.label is None and f.labels == (1, 2, 3, 4, 5, 11) and f.value == 6.5 and f.limit == 2.0
    assert f.figure == "mean_surface_distance_mm"
    assert "6 labels" in f.message
    assert "worst: label 5 6.5 mm, label 2 5.5 mm, label 4 4.0 mm;" in f.message
    _one_line(six)


def test_aggregation_is_per_rule():
    before, after, voxels = _case(n=20)
    for v in range(1, 8):  # seven labels below 0.5 that were at 0.7: two rules, seven labels each
        after[v]["dice"] = 0.3 + 0.01 * v
    findings = _review(before, after, voxels)
    assert [(f.label, f.figure, len(f.labels)) for f in findings] == [(None, "dice", 7), (None, "dice_drop", 7)]
    assert findings[0].value == pytest.approx(0.31) and findings[1].value == pytest.approx(0.39)
    assert "label 1 0.31, label 2 0.32, label 3 0.33" in findings[0].message


def test_summary_is_json_ready():
    before, after, voxels = _case(n=12)
    for v in range(1, 9):
        after[v].update(dice=0.2, mean_surface_distance_mm=float(v))
    after[10].update(mean_surface_distance_mm=float("nan"))
    limits = ReviewLimits(max_listed=3)
    findings = _review(before, after, voxels, linear=dict(GOOD_LINEAR, rotation_deg=np.float64(120.0)),
                       folded_fraction=np.float64(0.02), limits=limits)
    judged = judged_labels(after, label_voxels=voxels, limits=limits)
    summary = findings_summary(findings, limits=limits, judged=judged)
    text = json.dumps(summary, allow_nan=False)
    back = json.loads(text)
    assert back["plausible"] is False
    assert len(back["findings"]) == len(findings) >= 5
    assert back["limits"]["max_listed"] == 3
    assert set(back["findings"][0]) == {"label", "labels", "figure", "value", "limit", "message"}
    assert back["judged_labels"] == list(range(1, 13))


@pytest.mark.parametrize("kw, match", [
    (dict(voxel_mm=0.0), "`voxel_mm`"),
    (dict(voxel_mm=float("nan")), "`voxel_mm`"),
    (dict(folded_fraction=1.5), "`folded_fraction`"),
    (dict(linear={"rotation_deg": 5.0}), "`linear`"),
])
def test_bad_arguments(kw, match):
    with pytest.raises(ValueError, match=match):
        _review(*_case(), **kw)


def test_scores_without_the_figures_are_refused():
    before, after, voxels = _case()
    del after[7]["dice"]
    with pytest.raises(ValueError, match=r"`scores_after\[7\]`"):
        _review(before, after, voxels)


@pytest.mark.parametrize("kw, match", [
    (dict(min_scale=1.2), "`min_scale`"),
    (dict(max_scale=0.9), "`max_scale`"),
    (dict(min_dice=1.5), "`min_dice`"),
    (dict(max_listed=0), "`max_listed`"),
    (dict(min_voxels=-1), "`min_voxels`"),
    (dict(max_distance_mm=-1.0), "`max_distance_mm`"),
])
def test_bad_limits(kw, match):
    with pytest.raises(ValueError, match=match):
        ReviewLimits(**kw)


def test_a_single_slice_stored_as_a_volume_has_interior_voxels():
    """An axis of length 1 has no neighbours: a 2-D label map stored as (n, m, 1) is judged as 2-D."""
    from volreg.evaluation.review import label_voxel_counts

    a = np.zeros((40, 40, 1), np.uint8)
    a[5:25, 5:25, 0] = 1
    voxels, interior = label_voxel_counts(a)
    assert voxels == {1: 400} and interior == {1: 18 * 18}
    assert label_voxel_counts(a[:, :, 0]) == (voxels, interior)


def test_nothing_judged_is_a_finding():
    """When every label is excluded (here: cut by the image edge), the review says the result was not
    checked instead of calling it plausible."""
    before, after, voxels = _case(n=3)
    findings = _review(before, after, voxels, cut_labels=[1, 2, 3])
    assert [f.figure for f in findings] == ["judged_labels"]
    assert "not checked" in findings[0].message and "\n" not in findings[0].message
    only_background = {0: after[0]}
    assert _review({0: before[0]}, only_background, voxels) == []


def test_labels_in_one_volume_get_one_note_line(capsys):
    from volreg.cli._common import _warn_review

    _warn_review("register", {"review": {"findings": []}, "labels_in_one_volume": {"fixed": [3], "moving": [7, 9]}})
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("volreg register: note: ")
    assert "labels [3] only in the fixed volume and labels [7, 9] only in the moving volume" in err
    _warn_review("register", {"review": {"findings": []}, "labels_in_one_volume": {"fixed": [], "moving": []}})
    assert capsys.readouterr().err == ""


def test_the_dice_drop_is_measured_from_the_lower_reading_before():
    """Labels 1-10 before 0.80 by nearest neighbour, after 0.72: a drop of 0.08 on each.  Read
    before as after is read (per-label interpolation), label 3 had 0.73: no drop there."""
    before, after, voxels = _case(before=0.8, after=0.72)
    findings = _review(before, after, voxels)
    assert [f.figure for f in findings] == ["dice_drop"] and "10 labels" in findings[0].message
    findings = _review(before, after, voxels, dice_before_interpolated={3: 0.73, 4: 0.95})
    assert [f.figure for f in findings] == ["dice_drop"] and "9 labels" in findings[0].message
    assert not _review(before, after, voxels, dice_before_interpolated={v: 0.74 for v in range(1, 11)})
