"""The linear stage (volreg.warp.linear.fit_linear) on label pairs posed by a known map.

Every pair is built as moving(y) = fixed(T^-1 y): the label function of analytic shapes
is sampled (nearest neighbour, at voxel centres) at T^-1 of the moving grid's voxel
centres, so that T (x -> A x + b, fixed mm -> moving mm) is the answer.  The recovered
map is compared with T at the fixed volume's label voxels: the mean of
|A x + b - T x| in mm.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from shapes import (BLOBS, Disc2D, Ellipsoid, ball_and_shifted_cube, folded_blob_inside, label_volume, rotation,
                    thick_slice_pair)
from shapes import grid_around as _around
from shapes import posed_volume as _volume

from volreg.grid import LabelVolume
from volreg.linear_map import LinearMap
from volreg.warp.linear import LinearFit, cut_labels, fit_linear


def _error(fit: LinearFit, matrix, translation, fixed: LabelVolume) -> float:
    """Mean |A x + b - T x| (mm) over the fixed volume's label voxels."""
    x = fixed.grid_points()[fixed.array > 0]
    return float(np.mean(np.linalg.norm(fit.map(x) - (x @ np.asarray(matrix).T + translation), axis=1)))


def test_asymmetric_ellipsoid_rigid_is_recovered_up_to_its_symmetries():
    """One label: the principal axes start.  An ellipsoid with three different semi-axes
    is mapped onto itself by the half turns about its axes, so the pose is defined up to
    those four maps; the fit must be within half a voxel of one of them."""
    ellipsoid = Ellipsoid((20, 13, 8), (0, 0, 0))
    rot = rotation(30, (0.3, 0.5, 0.8))
    shift = np.array([25.0, -20.0, 24.0])
    shift *= 40.0 / np.linalg.norm(shift)
    fixed = _volume([ellipsoid], (48, 48, 48), (1, 1, 1), _around((0, 0, 0), (48,) * 3, (1, 1, 1)))
    moving = _volume([ellipsoid], (56, 56, 56), (1, 1, 1), _around(shift, (56,) * 3, (1, 1, 1)),
                     matrix=rot, translation=shift)
    fit = fit_linear(fixed, moving, kind="rigid")
    # One label: no centroid Procrustes; principal axes and the centroid translation compete.
    names = [c["name"] for c in fit.log["candidates"]]
    assert sum(name.startswith("principal axes") for name in names) == 4
    assert not any(name.startswith("centroids (") for name in names)
    errors = [_error(fit, rot @ np.diag(s), shift, fixed) for s in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1])]
    # A quarter of the 1 mm voxel: each boundary voxel is placed to within half a voxel
    # by nearest-neighbour sampling, and the fit averages thousands of them (measured:
    # 0.05 mm).
    assert min(errors) < 0.25, errors
    assert abs(np.linalg.det(fit.map.matrix) - 1.0) < 1e-9  # rigid stays rigid


@pytest.mark.parametrize("kind", ["rigid", "similarity"])
def test_ellipsoid_with_a_bump_has_one_answer(kind):
    """An ellipsoid with a bump has no symmetry: 45 degrees and 50 mm, the exact pose."""
    shapes = [Ellipsoid((20, 13, 9), (0, 0, 0)), Ellipsoid((6, 6, 6), (14, 8, 3))]
    scale = 1.0 if kind == "rigid" else 1.15
    a = scale * rotation(45, (0.3, -0.5, 0.8))
    shift = np.array([30.0, 30.0, -28.0])
    shift *= 50.0 / np.linalg.norm(shift)
    fixed = _volume(shapes, (52, 52, 52), (1, 1, 1), _around((2, 0, 0), (52,) * 3, (1, 1, 1)))
    moving = _volume(shapes, (64, 64, 64), (1, 1, 1), _around(shift, (64,) * 3, (1, 1, 1)), matrix=a,
                     translation=shift)
    fit = fit_linear(fixed, moving, kind=kind)
    # A quarter of the 1 mm voxel (nearest-neighbour boundaries, averaged over the
    # surface; measured: 0.03 mm).
    assert _error(fit, a, shift, fixed) < 0.25
    assert fit.log["map"]["scales"] == pytest.approx([scale] * 3, abs=0.01)


def test_blobs_similarity_45_degrees_50_mm_scale_1_2():
    """Six labels: the centroid (Umeyama) start, then the distance fit."""
    a = 1.2 * rotation(45, (0.3, 0.5, 0.8))
    shift = np.array([30.0, -30.0, 28.0])
    shift *= 50.0 / np.linalg.norm(shift)
    fixed = _volume(BLOBS, (56, 56, 56), (1, 1, 1), _around((0, 0, 0), (56,) * 3, (1, 1, 1)))
    moving = _volume(BLOBS, (72, 72, 72), (1, 1, 1), _around(shift, (72,) * 3, (1, 1, 1)), matrix=a,
                     translation=shift)
    fit = fit_linear(fixed, moving, kind="similarity")
    assert fit.log["start"] == "centroids"
    assert fit.log["labels"] == [1, 2, 3, 4, 5, 6]
    # A quarter of the 1 mm voxel (nearest-neighbour boundaries, averaged over six
    # surfaces; measured: 0.01 mm).
    assert _error(fit, a, shift, fixed) < 0.25
    described = fit.map.describe()
    assert described["rotation_deg"] == pytest.approx(45.0, abs=0.5)
    assert described["scales"] == pytest.approx([1.2] * 3, abs=0.01)


def test_blobs_affine_with_scales_0_8_to_1_25():
    """A general affine map (scales 0.8, 1 and 1.25 along oblique axes, then a rotation)."""
    axes = rotation(20, (0, 0, 1))
    a = rotation(30, (1, -0.4, 0.3)) @ axes.T @ np.diag([0.8, 1.0, 1.25]) @ axes
    shift = np.array([-20.0, 25.0, 15.0])
    fixed = _volume(BLOBS, (56, 56, 56), (1, 1, 1), _around((0, 0, 0), (56,) * 3, (1, 1, 1)))
    moving = _volume(BLOBS, (72, 72, 72), (1, 1, 1), _around(shift, (72,) * 3, (1, 1, 1)), matrix=a,
                     translation=shift)
    fit = fit_linear(fixed, moving, kind="affine")
    # A quarter of the 1 mm voxel, as for the rigid fits: the symmetric cost keeps the
    # affine map from shrinking (measured: 0.04 mm).
    assert _error(fit, a, shift, fixed) < 0.25
    assert np.abs(fit.map.matrix - a).max() < 0.02
    assert sorted(fit.log["map"]["scales"]) == pytest.approx([0.8, 1.0, 1.25], abs=0.02)


def test_fixed_at_2_mm_moving_at_1_mm():
    rot = rotation(25, (-0.2, 0.6, 0.3))
    shift = np.array([12.0, 20.0, -15.0])
    fixed = _volume(BLOBS, (30, 30, 30), (2, 2, 2), _around((0, 0, 0), (30,) * 3, (2, 2, 2)))
    moving = _volume(BLOBS, (64, 64, 64), (1, 1, 1), _around(shift, (64,) * 3, (1, 1, 1)), matrix=rot,
                     translation=shift)
    fit = fit_linear(fixed, moving, kind="rigid")
    # A quarter of the coarser (2 mm) voxel: its boundaries are placed to +-1 mm, and
    # the fit averages them (measured: 0.02 mm).
    assert _error(fit, rot, shift, fixed) < 0.5
    # The distance maps are never finer than the coarser volume's voxel.
    assert min(level["spacing_mm"] for level in fit.log["levels"]) == pytest.approx(2.0)


@pytest.mark.parametrize("oblique_in", ["fixed", "moving"])
def test_anisotropic_oblique_volume_against_1_mm(oblique_in):
    """0.8 x 0.8 x 2.5 mm voxels against 1 mm, with an oblique direction matrix in one header."""
    rot = rotation(25, (-0.2, 0.6, 0.3))
    shift = np.array([12.0, 20.0, -15.0])
    oblique = rotation(20, (1, 2, 0.5))
    thick = {"shape": (70, 70, 24), "spacing": (0.8, 0.8, 2.5)}
    if oblique_in == "fixed":
        fixed = _volume(BLOBS, thick["shape"], thick["spacing"],
                        _around((0, 0, 0), thick["shape"], thick["spacing"], oblique), oblique)
        moving = _volume(BLOBS, (64, 64, 64), (1, 1, 1), _around(shift, (64,) * 3, (1, 1, 1)), matrix=rot,
                         translation=shift)
    else:
        fixed = _volume(BLOBS, (56, 56, 56), (1, 1, 1), _around((0, 0, 0), (56,) * 3, (1, 1, 1)))
        moving = _volume(BLOBS, thick["shape"], thick["spacing"],
                         _around(shift, thick["shape"], thick["spacing"], oblique), oblique, matrix=rot,
                         translation=shift)
    fit = fit_linear(fixed, moving, kind="rigid")
    # A quarter of the coarser volume's voxel, taken as the geometric mean of its sides
    # (0.8 * 0.8 * 2.5) ** (1 / 3) = 1.17 mm: boundaries across the 2.5 mm slices are
    # placed to +-1.25 mm, those within a slice to +-0.4 mm (measured: 0.05-0.08 mm).
    assert _error(fit, rot, shift, fixed) < 0.29


def test_identical_volumes_give_the_identity():
    fixed = _volume(BLOBS, (56, 56, 56), (1, 1, 1), _around((0, 0, 0), (56,) * 3, (1, 1, 1)))
    fit = fit_linear(fixed, fixed, kind="affine")
    # Every boundary sample lies exactly on the other volume's zero level: the identity
    # is the exact minimum, reached to the solver's tolerance.
    assert np.abs(fit.map.matrix - np.eye(3)).max() < 1e-3
    assert np.abs(fit.map.translation).max() < 0.05


def test_moving_cut_through_one_label_still_recovers_the_map():
    """A partial field of view: the moving image ends across one label (a seventh blob
    that sticks out), whose centroid is then biased."""
    shapes = BLOBS + [Ellipsoid((7, 6, 6), (2, 4, 27))]
    rot = rotation(25, (-0.2, 0.6, 0.3))
    shift = np.array([12.0, 20.0, -15.0])
    fixed = _volume(shapes, (48, 48, 72), (1, 1, 1), _around((0, 0, 7), (48, 48, 72), (1, 1, 1)))
    moving = _volume(shapes, (80, 80, 80), (1, 1, 1), _around(shift, (80,) * 3, (1, 1, 1)), matrix=rot,
                     translation=shift)
    assert cut_labels(fixed) == [] and cut_labels(moving) == []
    # The index plane along axis 2 that keeps 40-70 % of label 7 and every other label whole.
    full = np.count_nonzero(moving.array == 7)
    stop = next(k for k in range(80, 0, -1) if np.count_nonzero(moving.array[:, :, :k] == 7) < 0.7 * full)
    cropped = LabelVolume(moving.array[:, :, :stop], moving.origin, moving.spacing, moving.direction)
    assert np.count_nonzero(cropped.array == 7) > 0.4 * full
    assert all(np.count_nonzero(cropped.array == v) == np.count_nonzero(moving.array == v) for v in range(1, 7))
    assert cut_labels(cropped) == [7]
    fit = fit_linear(fixed, cropped, kind="similarity")
    assert fit.log["cut_labels"] == {"fixed": [], "moving": [7]}
    assert 7 in fit.log["labels"]  # the cut label stays in the cost
    assert fit.log["levels"][-1]["samples_outside_view"] > 0
    # A quarter of the 1 mm voxel, as for the whole field of view: the samples that
    # fall outside the cropped image carry no cost instead of pulling the map
    # (measured: 0.02 mm).
    assert _error(fit, rot, shift, fixed) < 0.25


@pytest.mark.parametrize("kind", ["rigid", "similarity", "affine"])
def test_two_dimensional(kind):
    """2-D: one label, an ellipse with a round bump (which breaks the ellipse's
    symmetry), 40 degrees, 32 mm."""
    shapes = [Disc2D((18, 10), (0, 0)), Disc2D((5, 5), (14, 9))]
    fixed = _volume(shapes, (64, 64), (1, 1), _around((0, 0), (64, 64), (1, 1)))
    fixed = fixed.with_array(np.where(fixed.array > 0, 1, 0).astype(np.uint8))  # one label
    theta = np.deg2rad(40)
    a = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    if kind != "rigid":
        a = a @ np.diag([1.2, 1.2 if kind == "similarity" else 0.9])
    shift = np.array([20.0, -25.0])
    moving = _volume(shapes, (80, 80), (1, 1), _around(shift, (80, 80), (1, 1)), matrix=a, translation=shift)
    moving = moving.with_array(np.where(moving.array > 0, 1, 0).astype(np.uint8))
    fit = fit_linear(fixed, moving, kind=kind)
    assert fit.map.dim == 2
    # A quarter of the 1 mm pixel (nearest-neighbour outlines, averaged along them, with
    # fewer samples than in 3-D; measured: 0.03-0.14 mm).
    assert _error(fit, a, shift, fixed) < 0.25


def test_kind_none_gives_the_identity_at_once():
    fixed = _volume(BLOBS[:2], (40, 40, 40), (1, 1, 1), _around((0, 0, 0), (40,) * 3, (1, 1, 1)))
    moving = _volume(BLOBS[:2], (40, 40, 40), (1, 1, 1), _around((5, 0, 0), (40,) * 3, (1, 1, 1)),
                     matrix=np.eye(3), translation=np.array([5.0, 0.0, 0.0]))
    fit = fit_linear(fixed, moving, kind="none")
    assert fit.map.is_identity
    assert fit.log["kind"] == "none" and fit.log["levels"] == []


def test_bad_kind_is_a_value_error_naming_it():
    fixed = _volume(BLOBS[:1], (40, 40, 40), (1, 1, 1), _around((-12, -8, 3), (40,) * 3, (1, 1, 1)))
    with pytest.raises(ValueError, match=r"`kind`.*'shear'"):
        fit_linear(fixed, fixed, kind="shear")


def test_requested_label_absent_is_a_value_error():
    fixed = _volume(BLOBS[:2], (40, 40, 40), (1, 1, 1), _around((0, 0, 0), (40,) * 3, (1, 1, 1)))
    with pytest.raises(ValueError, match=r"`labels`.*\[7\]"):
        fit_linear(fixed, fixed, kind="rigid", labels=[1, 7])


def test_cut_labels_are_those_on_the_outermost_layer():
    array = np.zeros((6, 7, 5), dtype=np.int16)
    array[0, 3, 2] = 3  # first layer of axis 0
    array[2, 6, 1] = 5  # last layer of axis 1
    array[2:4, 2:4, 1:4] = 9  # inside
    array[3, 3, 4] = 11  # last layer of axis 2
    volume = LabelVolume(array, (0, 0, 0), (1, 1, 1), np.eye(3))
    assert cut_labels(volume) == [3, 5, 11]
    # An axis of length 1 is no edge: a single slice cuts nothing along its normal.
    flat = LabelVolume(np.pad(np.full((3, 3, 1), 4, np.uint8), ((1, 1), (1, 1), (0, 0))), (0, 0, 0), (1, 1, 1),
                       np.eye(3))
    assert cut_labels(flat) == []


def test_log_is_json_ready_and_progress_is_reported():
    a = rotation(10, (0, 0, 1))
    shift = np.array([3.0, -2.0, 1.0])
    fixed = _volume(BLOBS, (56, 56, 56), (1, 1, 1), _around((0, 0, 0), (56,) * 3, (1, 1, 1)))
    moving = _volume(BLOBS, (56, 56, 56), (1, 1, 1), _around(shift, (56,) * 3, (1, 1, 1)), matrix=a,
                     translation=shift)
    reports = []
    fit = fit_linear(fixed, moving, kind="rigid", labels=[1, 2, 3, 4], progress=lambda *r: reports.append(r))
    text = json.dumps(fit.log, allow_nan=False)
    log = json.loads(text)
    assert log["labels"] == [1, 2, 3, 4]
    assert log["start"] in ("centroids", "principal axes", "identity")
    assert {c["name"] for c in log["candidates"]} >= {"identity"}
    assert all(level["iterations"] >= 1 and level["spacing_mm"] >= 1.0 for level in log["levels"])
    assert log["seconds"] > 0
    stages = [r[0] for r in reports]
    assert "linear start" in stages and reports[-1] == ("fit linear", len(log["levels"]), len(log["levels"]))
    assert isinstance(fit.map, LinearMap)


def test_grids_here_match_label_volume_of_the_shapes_module():
    """``label_volume`` of tests/shapes.py and this file's ``_volume`` agree (same voxel centres)."""
    ellipsoid = BLOBS[0]
    origin = _around((0, 0, 0), (40,) * 3, (1, 1, 1))
    ours = _volume([ellipsoid], (40, 40, 40), (1, 1, 1), origin)
    theirs = label_volume((40, 40, 40), (1, 1, 1), np.eye(3), origin, lambda p: ellipsoid.signed_distance(p))
    assert np.array_equal(ours.array, theirs.array)


def test_cost_jacobian_is_the_derivative_of_the_residuals():
    """The analytic Jacobian (chain rule through the interpolated maps) against central
    differences, on distance maps that are linear functions (interpolated exactly)."""
    from volreg.warp import linear_cost as cost_module
    from volreg.warp import linear_labels as labels_module

    rng = np.random.default_rng(7)
    for dim in (2, 3):
        q, _ = np.linalg.qr(rng.normal(size=(dim, dim)))
        q[:, 0] *= np.sign(np.linalg.det(q))
        vol_f = LabelVolume(np.zeros((40,) * dim, np.uint8), rng.normal(size=dim), rng.uniform(0.7, 1.5, dim), q)
        vol_m = LabelVolume(np.zeros((40,) * dim, np.uint8), rng.normal(size=dim), rng.uniform(0.7, 1.5, dim),
                            np.eye(dim))

        def linear_map(volume, dim=dim):
            cells = np.stack(np.meshgrid(*[np.arange(30.0)] * dim, indexing="ij"), axis=-1)
            value = cells @ (rng.normal(size=dim) * volume.spacing)
            grads = np.gradient(value, *volume.spacing)
            return np.full(dim, 3.0), volume.spacing.copy(), np.stack([value, *grads], axis=-1)

        bank_f = labels_module._MapBank(vol_f, [linear_map(vol_f)])
        bank_m = labels_module._MapBank(vol_m, [linear_map(vol_m)])
        fwd = labels_module._Samples(vol_f.index_to_world(rng.uniform(12, 22, (40, dim))), np.zeros(40, int),
                                     np.ones(40))
        back = labels_module._Samples(vol_m.index_to_world(rng.uniform(12, 22, (40, dim))), np.zeros(40, int),
                                      np.ones(40))
        a0 = np.eye(dim) + 0.05 * rng.normal(size=(dim, dim))
        start = LinearMap(a0, vol_m.index_to_world(np.full((1, dim), 17.0))[0]
                          - a0 @ vol_f.index_to_world(np.full((1, dim), 17.0))[0])
        for kind in ("rigid", "similarity", "affine"):
            local = cost_module._Local(kind, dim)
            cost = cost_module._Cost(local, start, rng.normal(size=dim), bank_f, bank_m, fwd, back)
            p = 0.03 * rng.normal(size=local.size)
            _, jac = cost.evaluate(p)
            numeric = np.zeros_like(jac)
            for k in range(local.size):
                e = np.zeros(local.size)
                e[k] = 1e-6
                numeric[:, k] = (cost.evaluate(p + e)[0] - cost.evaluate(p - e)[0]) / 2e-6
            assert np.abs(jac - numeric).max() < 1e-6 * np.abs(numeric).max(), (dim, kind)


def test_a_label_pushed_out_of_view_does_not_win():
    """A ball (symmetric under half turns about its centre) and a small cube beside it, the
    cube shifted by 3 mm in the moving volume.  Half turns fit the ball exactly and would
    carry the cube out of the image; the cube's samples keep their cost out there (it is
    not cut by the image edge), so the map stays near the identity."""
    fixed_a, moving_a = ball_and_shifted_cube()
    geometry = {"spacing": np.full(3, 1.5), "origin": np.zeros(3), "direction": np.eye(3)}
    fixed, moving = LabelVolume(fixed_a, **geometry), LabelVolume(moving_a, **geometry)
    for kind in ("rigid", "affine"):
        fit = fit_linear(fixed, moving, kind=kind)
        assert fit.log["map"]["rotation_deg"] < 5.0, (kind, fit.log["map"])
        assert fit.log["levels"][-1]["samples_outside_view"] == 0


def test_a_volume_filled_by_one_label_gives_the_identity():
    """No label boundary inside the fixed image: nothing to align, the identity (no traceback)."""
    grid = {"origin": np.zeros(3), "spacing": np.ones(3), "direction": np.eye(3)}
    fixed = LabelVolume(np.ones((12, 12, 12), np.uint8), **grid)
    moving_a = np.zeros((12, 12, 12), np.uint8)
    moving_a[3:9, 3:9, 3:9] = 1
    fit = fit_linear(fixed, LabelVolume(moving_a, **grid), kind="affine")
    assert fit.map.is_identity and "no label boundary" in fit.log["start_candidate"]
    json.dumps(fit.log)


@pytest.mark.parametrize("join", [True, False])
def test_a_bank_of_maps_samples_each_map_as_a_bank_of_it_alone(monkeypatch, join):
    """Samples of several labels' distance maps, read from one joined array or from each map's
    own block, equal those of one-map banks bit for bit (interpolated inside a map's box,
    continued beyond it)."""
    from volreg.warp import linear_labels
    from volreg.warp.linear_labels import _distance_map, _MapBank

    monkeypatch.setattr(linear_labels, "_JOIN_BYTES", 64 << 20 if join else 0)

    rng = np.random.default_rng(5)
    array = np.zeros((30, 26, 22), dtype=np.int16)
    array[4:14, 5:20, 3:12] = 1
    array[15:27, 8:18, 10:20] = 2
    volume = LabelVolume(array, np.array([3.0, -7.0, 11.0]), np.array([1.0, 1.5, 2.0]), rotation(20.0, (1, 2, 3)))
    boxes = volume.label_boxes()
    entries = [_distance_map(volume, v, boxes[v], np.array(f), 4.0) for v, f in ((1, (1, 1, 1)), (2, (2, 1, 1)))]
    both = _MapBank(volume, entries)
    assert (both.joined is not None) == join
    which = rng.integers(0, 2, 400)
    lo, hi = volume.index_to_world(np.zeros((1, 3))), volume.index_to_world(np.array([array.shape]) - 1.0)
    points = rng.uniform(np.minimum(lo, hi) - 8.0, np.maximum(lo, hi) + 8.0, (400, 3))
    dist, grad = both.sample(both.lookup(which), points)
    for m in (0, 1):
        alone = _MapBank(volume, [entries[m]])
        rows = which == m
        d1, g1 = alone.sample(alone.lookup(np.zeros(int(rows.sum()), dtype=np.int64)), points[rows])
        assert np.array_equal(dist[rows], d1) and np.array_equal(grad[rows], g1)
    assert np.all(np.isfinite(dist)) and dist.min() < 0 < dist.max()  # inside and outside samples


@pytest.mark.parametrize("shape", [(7, 5, 9), (3, 40, 2), (11, 6)])
def test_gradient_slab_by_slab_is_numpys_gradient_bit_for_bit(monkeypatch, shape):
    """The distance maps' gradient, written slab by slab into single precision, equals
    ``np.gradient`` along every axis cast to float32, with slabs of the fewest rows (4), a few
    rows and all."""
    from volreg.warp import linear_labels

    rng = np.random.default_rng(len(shape))
    dist = rng.normal(0.0, 10.0, shape)
    step = rng.uniform(0.5, 3.0, len(shape))
    expected = np.stack([np.gradient(dist, step[a], axis=a) for a in range(len(shape))], axis=-1).astype(np.float32)
    for slab in (1, 2 * int(np.prod(shape[1:])), 1 << 16):
        monkeypatch.setattr(linear_labels, "_SLAB_VALUES", slab)
        out = np.full(shape + (len(shape),), np.nan, dtype=np.float32)
        linear_labels._gradient_into(dist, step, out)
        assert np.array_equal(out, expected)


def test_distance_map_is_signed_distance_to_the_faces_and_its_gradient():
    """A label map's values: distance to the faces between inside and outside cells (negative
    inside) and its central differences, on a grid of unequal spacings."""
    from volreg.warp.linear_labels import _distance_map

    array = np.zeros((24, 20, 18), dtype=np.int16)
    array[6:16, 5:15, 4:12] = 3
    volume = LabelVolume(array, np.zeros(3), np.array([1.0, 1.5, 2.0]), np.eye(3))
    origin, step, values = _distance_map(volume, 3, volume.label_boxes()[3], np.array([1, 1, 1]), 3.0)
    assert values.dtype == np.float32 and values.shape[-1] == 4
    assert np.array_equal(step, volume.spacing)
    dist = values[..., 0].astype(float)
    # Along the first axis through the middle of the box: faces half a cell (0.5 mm) beyond the
    # first and last inside cells; inside, the nearest face may lie along another axis.
    i, j, k = (np.array([10, 9, 7]) - origin).astype(int)
    line = dist[:, j, k]
    inside = np.flatnonzero(line < 0)
    assert line[inside[0] - 1] == pytest.approx(0.5) and line[inside[0]] == pytest.approx(-0.5)
    assert line[inside[-1] + 1] == pytest.approx(0.5) and line[inside[-1]] == pytest.approx(-0.5)
    assert line[inside[0] - 3] == pytest.approx(2.5)
    grad = values[..., 1:].astype(float)
    assert np.allclose(grad[1:-1, j, k, 0], (dist[2:, j, k] - dist[:-2, j, k]) / 2.0, atol=1e-6)
    # Outside, one cell beyond the nearest: the distance falls by 1 mm per mm towards the label.
    assert grad[inside[0] - 2, j, k, 0] == pytest.approx(-1.0) and grad[inside[-1] + 2, j, k, 0] == pytest.approx(1.0)


def test_overlap_of_maps_is_the_labels_dice():
    """A box of 10 voxels along x against the same box 2 voxels along: Dice 8/10 through the
    identity, 1 through the shift."""
    from volreg.warp.linear import mean_dice_through

    a = np.zeros((40, 30, 30), np.uint8)
    a[10:20, 10:20, 10:20] = 1
    b = np.zeros_like(a)
    b[12:22, 10:20, 10:20] = 1
    fixed = LabelVolume(a, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(3))
    moving = LabelVolume(b, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(3))
    maps = [LinearMap.identity(3), LinearMap(np.eye(3), np.array([2.0, 0.0, 0.0]))]
    assert mean_dice_through(fixed, moving, maps, [1], fixed.label_boxes()) == pytest.approx([0.8, 1.0])


def test_a_fit_that_overlaps_clearly_worse_than_its_start_gives_way(monkeypatch):
    """Where the coarse-to-fine solve runs into a degenerate map (forced here: every level
    squashes x by half), the labels' overlap keeps the chosen start instead, and the log says so."""
    import volreg.warp.linear_refine as refine

    run = refine._run

    def squashing(local, start, *args, **kwargs):
        found, info, used = run(local, start, *args, **kwargs)
        if args[-2] == refine._LEVEL_EVALUATIONS:
            found = LinearMap(found.matrix @ np.diag([0.5, 1.0, 1.0]), found.translation)
        return found, info, used

    monkeypatch.setattr(refine, "_run", squashing)
    fixed = _volume(BLOBS, (32, 32, 32), (1.5,) * 3, _around((0, 0, 0), (32,) * 3, (1.5,) * 3))
    moving = _volume(BLOBS, (32, 32, 32), (1.5,) * 3, _around((4, 0, 0), (32,) * 3, (1.5,) * 3),
                     matrix=np.eye(3), translation=np.array([4.0, 0.0, 0.0]))
    fit = fit_linear(fixed, moving, kind="affine")
    assert fit.log["kept_instead"] == "start", fit.log["overlap"]
    assert fit.log["overlap"]["start"] > fit.log["overlap"]["refined"] + 0.05
    assert _error(fit, np.eye(3), [4.0, 0.0, 0.0], fixed) < 0.75  # the centroids' start: half a voxel


def test_a_moving_image_cut_through_every_label_does_not_squeeze_the_fixed_ones():
    """Two balls at 1 mm, and the same balls at 2 mm in a moving image that stops half-way through
    both (every label cut, no motion).  The closed-form start from the cut labels' moments is a
    scale of 0.79; read over every fixed voxel it overlapped better than the identity, since the
    identity sends half the balls beyond the moving image, where it reads background (the fit
    kept it: 3.5 mm of motion on average).  Compared only where every candidate map lands inside
    the moving image, the identity is kept."""

    def balls(p):
        out = np.zeros(len(p), np.uint8)
        out[np.linalg.norm(p - [8.0, 0, 0], axis=1) < 10] = 1
        out[np.linalg.norm(p + [8.0, 0, 0], axis=1) < 9] = 2
        return out

    def volume(shape, spacing, origin):
        grid = LabelVolume(np.zeros(shape, np.uint8), origin, (spacing,) * 3, np.eye(3))
        return grid.with_array(balls(grid.grid_points().reshape(-1, 3)).reshape(shape))

    fixed = volume((60, 60, 60), 1.0, (-29.5,) * 3)
    moving = volume((30, 30, 15), 2.0, (-29.0,) * 3)
    fit = fit_linear(fixed, moving)
    assert fit.log["cut_labels"]["moving"] == [1, 2]
    x = fixed.grid_points()[fixed.array > 0]
    assert np.linalg.norm(fit.map(x) - x, axis=1).mean() < 0.3, fit.map.describe()


@pytest.mark.parametrize("shift", [(40.0, 0.0, 0.0), (70.0, 0.0, 0.0), (60.0, 40.0, 0.0), (0.0, 0.0, -75.0)])
def test_images_apart_keep_the_translation_their_labels_show(shift):
    """The blobs and the same blobs shifted by 40-75 mm, each grid centred on its blobs: where the
    two images overlap under the identity they hold no label, so the identity aligns nothing it
    can be scored on.  The start (the centroids' translation) is kept, within 0.5 mm."""
    b = np.array(shift)
    fixed = _volume(BLOBS, (64,) * 3, (1.5,) * 3, _around((0, 0, 0), (64,) * 3, (1.5,) * 3))
    moving = _volume(BLOBS, (64,) * 3, (1.5,) * 3, _around(b, (64,) * 3, (1.5,) * 3), matrix=np.eye(3),
                     translation=b)
    fit = fit_linear(fixed, moving)
    assert fit.log["overlap"]["identity"] == 0.0
    assert np.abs(fit.map.translation - b).max() < 0.5 and np.abs(fit.map.matrix - np.eye(3)).max() < 0.01


@pytest.mark.parametrize("kind, limit", [("affine", 0.05), ("similarity", 0.4)])
def test_one_organ_over_a_few_thick_slices_stretched_in_plane(kind, limit):
    """One ellipsoid (semi-axes 6 / 5 / 12 mm) over five slices of 0.3 x 0.3 x 5 mm, against the same
    grid holding it stretched to 6.5 mm along x and moved 0.6 mm.  The cost, read at the 5 mm spacing
    on an object 10 mm across in-plane, does not know the answer (its fit overlaps worse than its
    start); an affine map's start from the second moments along the principal axes is the stretch
    itself (measured 0.018 mm from it), and the overlap keeps it.  A similarity cannot stretch one
    axis: its start, the volume ratio's scale, is 0.21 mm off."""
    fixed, moving, truth = thick_slice_pair()
    fit = fit_linear(fixed, moving, kind=kind)
    x = fixed.grid_points()[fixed.array > 0]
    error = np.linalg.norm(fit.map(x) - truth(x), axis=1).mean()
    assert error < limit, (error, fit.log["overlap"])
    if kind == "affine":
        assert fit.log["start"] == "principal axes" and fit.log["kept_instead"] == "start", fit.log["overlap"]
        assert fit.map.matrix[0, 0] == pytest.approx(6.5 / 6.0, abs=0.01)


def test_a_turned_spheroid_is_turned_back_not_stretched():
    """Two nested labels of a spheroid (semi-axes 30 / 40 / 30 mm: grey shell over a white core) at
    2 mm against the same at 1 mm turned 20 degrees about (0.4, -0.2, 1) and moved.  An affine map
    matches the turned spheroid by a stretch along oblique axes as well as by the turn
    (``A = L R L^-1``), and the overlap cannot tell them apart; fitted affine from the coarsest level
    on, the map stopped at 6 degrees with scales 1.08 / 0.93 and the long axis 11.5 degrees off.  The
    coarser levels now fit a similarity, the finest the affine map: the long axis comes within
    a degree (measured 0.3) and the scales within 0.01 of 1.  The turn about the long axis itself
    is not determined by the shapes and is not asserted."""
    axes = np.array([30.0, 40.0, 30.0])
    turn, shift = rotation(20, (0.4, -0.2, 1.0)), np.array([8.0, -6.0, 5.0])

    def volume(shape, spacing, centre, posed):
        grid = LabelVolume(np.zeros(shape, np.uint8), _around(centre, shape, (spacing,) * 3), (spacing,) * 3, np.eye(3))
        p = grid.grid_points().reshape(-1, 3)
        r = np.linalg.norm(((p - shift) @ turn if posed else p) / axes, axis=1)
        return grid.with_array(np.where(r < 0.9, 2, np.where(r < 1.0, 1, 0)).astype(np.uint8).reshape(shape))

    fixed = volume((36, 46, 36), 2.0, (0, 0, 0), False)
    moving = volume((76, 96, 76), 1.0, shift, True)
    fit = fit_linear(fixed, moving, kind="affine")
    long = fit.map.matrix @ np.array([0.0, 1.0, 0.0])
    tilt = np.degrees(np.arccos(abs(long @ turn[:, 1]) / np.linalg.norm(long)))
    assert tilt < 2.0, (tilt, fit.log["map"])
    assert fit.log["map"]["scales"] == pytest.approx([1.0] * 3, abs=0.02)
    assert fit.log["map"]["rotation_deg"] == pytest.approx(20.0, abs=3.0)


def _folded_spheroid(spacing: float, centre, matrix=None, translation=None) -> LabelVolume:
    """A brain-like phantom on a grid of ``spacing`` mm around ``centre``: a folded spheroid
    (semi-axes 78 / 93 / 78 mm, sulci 12 mm deep and about 9 mm apart) as a grey shell (1) 3 mm
    thick over a white core (2), posed by ``x -> matrix x + translation``."""
    axes = np.array([78.0, 93.0, 78.0])
    shape = tuple(int(v) for v in np.ceil(2 * (axes + 8) / spacing))
    grid = LabelVolume(np.zeros(shape, np.uint8), _around(centre, shape, (spacing,) * 3), (spacing,) * 3, np.eye(3))
    p = grid.grid_points().reshape(-1, 3)
    if matrix is not None:
        p = (p - translation) @ np.linalg.inv(matrix).T
    inside = folded_blob_inside(p, axes=axes, depth=12.0, wavelength=18.0)
    core = folded_blob_inside(p, axes=axes - 3.0, depth=12.0, wavelength=18.0)
    return grid.with_array(np.where(core, 2, np.where(inside, 1, 0)).astype(np.uint8).reshape(shape))


def test_a_spheroid_turned_about_its_long_axis_is_found_by_its_folds():
    """The phantom's moments are those of a spheroid: they do not show its turn about the long
    axis, and two nested labels have no spread of centroids that would; at the coarse levels
    every turn about that axis fits as well.  Turned 40 degrees about (0.2, 1, 0.1) at 3 mm, the
    fit stopped at 10.5 degrees, 35.7 mm off on average.  The finest level's cost is now searched
    over that turn (steps of 5 degrees): measured 0.05 mm, with a clear minimum (score 0.87, the
    best turn more than 15 degrees away 1.57)."""
    turn, shift = rotation(40, (0.2, 1.0, 0.1)), np.array([12.0, -9.0, 6.0])
    fixed = _folded_spheroid(3.0, (0, 0, 0))
    moving = _folded_spheroid(3.0, shift, turn, shift)
    fit = fit_linear(fixed, moving, kind="affine")
    assert _error(fit, turn, shift, fixed) < 0.5, fit.log.get("turn_search")
    search = fit.log["turn_search"]
    assert abs(abs(np.asarray(search["axis"]) @ [0.0, 1.0, 0.0]) - 1) < 0.01  # the long axis
    assert search["score"] < 0.8 * search["runner_up"]


def test_the_turn_search_keeps_the_smallest_turn_where_the_labels_do_not_show_it():
    """Two nested balls: every turn about any axis fits alike; the search (the moments are those
    of a sphere) keeps the map as it is, turned by 0 degrees, and the fit stays the shift."""
    shift = np.array([3.0, -2.0, 1.0])
    balls = [Ellipsoid((14, 14, 14), (0, 0, 0)), Ellipsoid((8, 8, 8), (0, 0, 0))]

    def volume(centre, translation):
        grid = LabelVolume(np.zeros((24,) * 3, np.uint8), _around(centre, (24,) * 3, (1.5,) * 3), (1.5,) * 3, np.eye(3))
        p = grid.grid_points().reshape(-1, 3) - translation
        labels = np.where(balls[1].signed_distance(p) < 0, 2, np.where(balls[0].signed_distance(p) < 0, 1, 0))
        return grid.with_array(labels.astype(np.uint8).reshape(grid.shape))

    fit = fit_linear(volume((0, 0, 0), np.zeros(3)), volume(shift, shift), kind="rigid")
    assert fit.log["turn_search"]["degrees"] == 0.0
    assert fit.log["map"]["rotation_deg"] < 1.0
    assert np.allclose(fit.map.translation, shift, atol=0.3)


def test_no_turn_search_where_the_moments_show_the_turn():
    """Blobs whose centroids span the space, or one label of three different moments: no search."""
    fixed = _volume(BLOBS, (32, 32, 32), (1.5,) * 3, _around((0, 0, 0), (32,) * 3, (1.5,) * 3))
    assert "turn_search" not in fit_linear(fixed, fixed, kind="affine").log
    fixed, moving, _ = thick_slice_pair()
    assert "turn_search" not in fit_linear(fixed, moving, kind="affine").log
