"""The template's numerics: mean pose, votes, medoid, inverse of a mean displacement, the points
where a subject is read for the moved template, outliers among the subjects."""

from __future__ import annotations

import numpy as np
import pytest

from volreg.grid import Grid
from volreg.linear_map import LinearMap
from volreg.pipeline.template_shape import (
    invert_displacement, mean_linear_map, medoid, pull_back_points, rank_subjects, sharpness, template_grid,
    vote, vote_volumes,
)


def _rotation_z(deg):
    t = np.radians(deg)
    return np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1.0]])


def test_mean_of_one_map_is_that_map():
    m = LinearMap(_rotation_z(20) @ np.diag([1.1, 0.9, 1.0]), [3.0, -2.0, 1.0])
    out = mean_linear_map([m])
    np.testing.assert_allclose(out.matrix, m.matrix, atol=1e-10)
    np.testing.assert_allclose(out.translation, m.translation, atol=1e-10)


def test_mean_of_opposite_turns_and_shifts_is_the_identity():
    a = LinearMap(_rotation_z(15), [5.0, 0.0, 0.0])
    out = mean_linear_map([a, a.inverse()])
    np.testing.assert_allclose(out.matrix, np.eye(3), atol=1e-10)
    np.testing.assert_allclose(out.translation, 0.0, atol=1e-10)


def test_mean_of_scales_is_geometric():
    out = mean_linear_map([LinearMap(np.eye(3) * 2.0, np.zeros(3)), LinearMap(np.eye(3) * 0.5, np.zeros(3))])
    np.testing.assert_allclose(out.matrix, np.eye(3), atol=1e-10)


def test_mean_refuses_no_map():
    with pytest.raises(ValueError, match="at least one"):
        mean_linear_map([])


def test_template_grid_holds_every_box():
    boxes = [(np.array([-10.0, 0, 0]), np.array([5.0, 8, 3])), (np.array([-2.0, -6, 1]), np.array([12.0, 2, 9]))]
    g = template_grid(boxes, 1.5, margin=2.0)
    lo, hi = g.origin, g.origin + (np.array(g.shape) - 1) * g.spacing
    assert np.all(lo <= np.array([-12.0, -8, -2]) + 1e-9) and np.all(hi >= np.array([14.0, 10, 11]) - 1e-9)
    np.testing.assert_allclose(g.spacing, 1.5)


def test_vote_takes_the_majority_and_the_background_wins_ties():
    counts = np.array([[[3, 1, 2, 0]], [[0, 2, 2, 1]]], np.uint16)[:, :, :, None]  # labels 4, 7 of 4 subjects
    out = vote(counts, 4, np.array([4, 7]))
    # voxel 0: 4 has 3 votes; voxel 1: 7 has 2, background 1; voxel 2: 0 background votes, 4 and 7
    # tie -> the lower label; voxel 3: background 3
    assert out[0, :, 0].tolist() == [4, 7, 4, 0]
    assert vote(np.array([[[[2]]]]), 4, np.array([1]))[0, 0, 0] == 0  # 2 of 4 against 2: background


def test_the_volume_vote_keeps_a_thin_layer_that_the_majority_loses():
    # four subjects, each with a one-voxel layer (label 2) on a block (label 1) at rows 3, 4, 5, 6
    counts = np.zeros((2, 10, 6, 6), np.uint16)
    for top in (3, 4, 5, 6):
        counts[0, :top] += 1
        counts[1, top] += 1
    labels = np.array([1, 2])
    assert not (vote(counts, 4, labels) == 2).any()  # one vote of four: the block's or the background's
    out = vote_volumes(counts, 4, labels)
    # each label's mean volume: the layer's one row, where it has most votes around it (rows 4, 5)
    assert (out == 2).sum() == 36 and not (out[:4] == 2).any()
    assert (out == 1).sum() == 4.5 * 36 and (out[:4] == 1).all()  # 4.5 rows: the mean of 3, 4, 5, 6
    assert not out[6:].any()


def test_the_volume_vote_is_the_majority_where_the_subjects_agree():
    counts = np.zeros((3, 8, 8, 8), np.uint16)
    counts[0, :3] = 5
    counts[1, 3:5] = 5
    counts[2, 5:7, 2:6] = 5
    labels = np.array([1, 4, 9])
    np.testing.assert_array_equal(vote_volumes(counts, 5, labels), vote(counts, 5, labels))
    assert vote_volumes(counts, 5, labels).dtype == np.uint8


def test_the_volume_vote_gives_a_voxel_two_labels_want_to_the_one_with_more_votes():
    counts = np.zeros((2, 1, 1, 4), np.uint16)  # labels 1 and 2, 3 subjects, 4 voxels
    counts[0, 0, 0] = [3, 2, 0, 0]  # label 1: 5 votes, mean volume 2 (rounded from 5/3)
    counts[1, 0, 0] = [0, 1, 2, 0]  # label 2: 3 votes, mean volume 1
    out = vote_volumes(counts, 3, np.array([1, 2]))
    assert out[0, 0].tolist() == [1, 1, 2, 0]


def test_sharpness_is_one_where_every_subject_agrees():
    counts = np.zeros((2, 4, 4, 4), np.uint16)
    counts[0, :2] = 5
    counts[1, 2:] = 3
    template = vote(counts, 5, np.array([1, 2]))
    s = sharpness(counts, 5, template, np.array([1, 2]))
    assert s[1] == pytest.approx(1.0) and s[2] == pytest.approx(0.6)


def _grid(n=24, spacing=1.0):
    return Grid((n, n, n), np.full(3, -(n - 1) * spacing / 2), np.full(3, spacing), np.eye(3))


def test_inverse_of_a_smooth_displacement():
    g = _grid()
    x = g.grid_points()
    u = 2.0 * np.exp(-(x ** 2).sum(-1) / (2 * 6.0 ** 2))[..., None] * np.array([1.0, 0.5, 0.0])
    v = invert_displacement(u, g)
    y = x.reshape(-1, 3)
    back = y + v.reshape(-1, 3)  # phi^-1(y)
    ub = 2.0 * np.exp(-(back ** 2).sum(-1) / (2 * 6.0 ** 2))[:, None] * np.array([1.0, 0.5, 0.0])
    err = np.linalg.norm(back + ub - y, axis=1)  # phi(phi^-1(y)) - y, u read exactly
    inner = np.all(np.abs(y) < 8, axis=1)
    assert err[inner].max() < 0.02  # mm: the trilinear reading of u on a 1 mm grid


def test_a_subject_is_read_through_its_registration_composed_with_the_inverse_update():
    g = _grid()
    x = g.grid_points()
    shift = np.zeros((*g.shape, 3))
    shift[..., 0] = 3.0  # phi(x) = x + 3 e_x, so phi^-1(y) = y - 3 e_x
    u = 0.1 * x[..., [1, 2, 0]]  # the subject's pull-back field, linear: read exactly between voxels
    points = pull_back_points(g, invert_displacement(shift, g), u)
    y = x.reshape(-1, 3)
    back = y - [3.0, 0, 0]
    expected = back + 0.1 * back[:, [1, 2, 0]]
    inner = np.all(np.abs(y) < 8, axis=1)  # phi^-1(y) on the grid, u not clipped at its edge
    np.testing.assert_allclose(points[inner], expected[inner], atol=1e-6)
    np.testing.assert_allclose(pull_back_points(g, np.zeros_like(u), u), (x + u).reshape(-1, 3), atol=1e-9)


def _ball(n, centre, radius):
    x = np.indices((n, n, n)).transpose(1, 2, 3, 0)
    return (np.linalg.norm(x - centre, axis=-1) <= radius).astype(np.uint8)


def test_the_medoid_is_the_map_nearest_the_others():
    maps = [_ball(20, [10 + dx, 10, 10], 5) for dx in (-3, 0, 1, 4)]
    best, mean = medoid(maps, np.array([1]))
    assert best == 1  # centred among shifts -3, 1, 4: the nearest on average
    assert mean.shape == (4,) and np.all((mean > 0) & (mean < 1)) and mean[1] == mean.max()
    # Dice over the labels either holds: a label only one map has counts as 0 for that pair
    a, b = _ball(12, [6, 6, 6], 3), _ball(12, [6, 6, 6], 3)
    b[0, 0, 0] = 2
    _, pair = medoid([a, b], np.array([1, 2]))
    np.testing.assert_allclose(pair, [0.5, 0.5])
    assert medoid([a], np.array([1])) == (0, pytest.approx(np.ones(1)))


def test_outliers_are_far_from_the_rest():
    d = {"a": 1.0, "b": 1.1, "c": 0.9, "d": 1.05, "e": 4.0}
    ranked, outliers = rank_subjects(d)
    assert ranked[0] == "c" and ranked[-1] == "e" and outliers == ["e"]
    assert rank_subjects({"a": 1.0, "b": 1.0})[1] == []
