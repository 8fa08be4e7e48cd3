"""Voxel signed-distance features (volreg.distance_maps): exact clipped distances, the known
signed distance of a sphere, analytic derivatives against finite differences, and their use in
label registration."""

import dataclasses

import numpy as np
import pytest
from scipy import ndimage
from shapes import ball_and_shifted_cube

from volreg.features import distance_maps
from volreg.features.distance_maps import (
    VoxelDistance, blurred_signed_distance, clipped_signed_distance, euclidean_distance,
)
from volreg.warp.resample import signed_distance_map


def _blobs(shape, seed=0):
    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.random(shape), 2) > 0.5


@pytest.mark.parametrize("clip", [0.9, 3.0, 4.5, 7.0])
@pytest.mark.parametrize("dim", [2, 3])
def test_clipped_distance_equals_clipped_distance_transform(dim, clip):
    mask = _blobs((40, 36, 30)[:dim])
    spacing = np.array([1.0, 1.2, 1.5])[:dim]
    expected = np.clip(signed_distance_map(mask, spacing), -clip, clip)
    got = clipped_signed_distance(mask, spacing, clip)
    assert got.dtype == np.float32 and got.shape == mask.shape
    np.testing.assert_array_equal(got, expected)


def test_clipped_distance_without_boundary():
    spacing = np.array([1.0, 1.0, 2.0])
    assert np.all(clipped_signed_distance(np.ones((5, 6, 7), bool), spacing, 3.0) == -3.0)
    assert np.all(clipped_signed_distance(np.zeros((5, 6, 7), bool), spacing, 3.0) == 3.0)


def _oblique_sphere(radius=12.0, t=0.3):
    spacing = np.array([1.0, 1.2, 1.5])
    origin = np.array([-10.0, 5.0, 3.0])
    direction = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    shape = (50, 44, 36)
    index = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    world = origin + (index * spacing) @ direction.T
    centre = origin + (np.array(shape) / 2 * spacing) @ direction.T
    mask = np.linalg.norm(world - centre, axis=-1) < radius
    return mask, spacing, origin, direction, centre


def test_sphere_signed_distance_on_an_oblique_grid():
    """The zero level is the sphere to within half a voxel; the map grows like the distance."""
    mask, spacing, origin, direction, centre = _oblique_sphere()
    f = VoxelDistance(mask, spacing, origin, direction, clip=6.0)
    rng = np.random.default_rng(1)
    points = centre + rng.normal(size=(3000, 3)) * 8
    true = np.linalg.norm(points - centre, axis=1) - 12.0
    value = f.evaluate(points)[0]
    near = np.abs(true) < 4.0
    assert np.max(np.abs(value - true)[near]) <= 0.5 * spacing.max() + 1.0  # half a voxel plus the step
    clear = near & (np.abs(true) > 0.5 * spacing.max())
    np.testing.assert_array_equal(np.sign(value[clear]), np.sign(true[clear]))
    # Beyond the clip the map is flat (up to the interpolating spline's ringing, decaying from the kink).
    far = np.linalg.norm(points - centre, axis=1) > 12.0 + 6.0 + 4 * spacing.max()
    assert far.sum() > 20
    np.testing.assert_allclose(value[far], 6.0, atol=1e-3)


@pytest.mark.parametrize("smoothing", [0.0, 0.4, 1.5])
@pytest.mark.parametrize("angle", [0.3, 0.0], ids=["oblique", "axis-aligned"])
def test_derivatives_match_finite_differences(smoothing, angle):
    """Gradient and Hessian are the interpolant's exact derivatives (both the prefiltered and
    the blurred-coefficient paths), in world axes on an oblique grid and on an axis-aligned
    one (whose Hessian takes the diagonal shortcut)."""
    mask, spacing, origin, direction, centre = _oblique_sphere(t=angle)
    diagonal_shortcut = VoxelDistance(mask, spacing, origin, direction, clip=6.0)._step_outer is not None
    assert diagonal_shortcut == (angle == 0.0)
    f = VoxelDistance(mask, spacing, origin, direction, clip=6.0, smoothing=smoothing)
    rng = np.random.default_rng(2)
    points = centre + rng.normal(size=(500, 3)) * 9
    value, grad, hess = f.evaluate(points, order=2)
    assert value.shape == (500,) and grad.shape == (500, 3) and hess.shape == (500, 3, 3)
    np.testing.assert_allclose(f.evaluate(points, order=0)[0], value, atol=1e-12)
    np.testing.assert_allclose(f.evaluate(points, order=1)[1], grad, atol=1e-12)
    eps = 1e-4
    for a in range(3):
        step = np.zeros(3)
        step[a] = eps
        fd = (f.evaluate(points + step)[0] - f.evaluate(points - step)[0]) / (2 * eps)
        np.testing.assert_allclose(grad[:, a], fd, atol=1e-5)
        fd2 = (f.evaluate(points + step, order=1)[1] - f.evaluate(points - step, order=1)[1]) / (2 * eps)
        np.testing.assert_allclose(hess[:, :, a], fd2, atol=1e-4)
    np.testing.assert_allclose(hess, np.transpose(hess, (0, 2, 1)))
    # Near the surface the gradient of a distance points outwards with about unit length.
    on = np.abs(np.linalg.norm(points - centre, axis=1) - 12.0) < 1.0
    radial = (points - centre) / np.linalg.norm(points - centre, axis=1, keepdims=True)
    assert np.median(np.einsum("nd,nd->n", grad[on], radial[on])) > 0.8


def test_two_dimensional_and_far_away():
    mask3, spacing, origin, direction, centre = _oblique_sphere()
    mask = mask3[:, :, 18]
    f = VoxelDistance(mask, spacing[:2], origin[:2], direction[:2, :2], clip=5.0, smoothing=1.5)
    value, grad, hess = f.evaluate(np.array([[1000.0, 1000.0], centre[:2]]), order=2)
    assert grad.shape == (2, 2) and hess.shape == (2, 2, 2)
    np.testing.assert_allclose(value[0], 5.0, atol=1e-5)
    np.testing.assert_array_equal(grad[0], 0.0)
    np.testing.assert_array_equal(hess[0], 0.0)
    assert value[1] < -4.0  # the circle's centre is deep inside
    lo, hi = f.bounds()
    assert np.all(lo <= centre[:2]) and np.all(hi >= centre[:2])
    assert f.band < 5.0


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(mask=np.zeros((4, 4, 4), bool)), "empty"),
        (dict(clip=0.0), "clip"),
        (dict(smoothing=-1.0), "smoothing"),
        (dict(mask=np.ones(5, bool)), "2-D or 3-D"),
    ],
)
def test_bad_arguments(kwargs, message):
    args = dict(mask=np.ones((4, 4, 4), bool), spacing=np.ones(3), origin=np.zeros(3), direction=np.eye(3),
                clip=2.0, smoothing=0.0)
    args.update(kwargs)
    if args["mask"].ndim != 3:
        args.update(spacing=np.ones(args["mask"].ndim), origin=np.zeros(args["mask"].ndim),
                    direction=np.eye(args["mask"].ndim))
    with pytest.raises(ValueError, match=message):
        VoxelDistance(args.pop("mask"), args.pop("spacing"), args.pop("origin"), args.pop("direction"), **args)


def test_distance_maps_carry_a_label_without_a_surface():
    """A label of a few voxels (no surface: too small) drives the warp through its distance map:
    a cube of 2 x 2 x 2 voxels less one 10 voxels from a sphere, shifted by 2 voxels in the moving volume, comes
    back in place (Dice 1) with the maps and is missed with the implicit surfaces alone (no linear
    stage, which would move it by its own distance maps)."""
    from volreg.evaluation.metrics import dice
    from volreg.io.protocol import load_protocol
    from volreg.pipeline.labels import register_labels
    from volreg.warp.field import fields_on_grid
    from volreg.warp.resample import resample_labels
    from volreg.grid import LabelVolume
    from volreg.settings import LinearSettings

    fixed_a, moving_a = ball_and_shifted_cube(whole_cube=False)  # 7 voxels: too few for a surface
    geometry = dict(spacing=np.full(3, 1.5), origin=np.zeros(3), direction=np.eye(3))
    fixed, moving = LabelVolume(fixed_a, **geometry), LabelVolume(moving_a, **geometry)
    out = {}
    for weight in (0.0, 2.0):
        protocol = load_protocol("default")
        surface = dataclasses.replace(protocol.surface, implicit_weight=1.0, distance_weight=weight)
        protocol = dataclasses.replace(protocol, surface=surface, linear=LinearSettings("none"))
        result = register_labels(fixed, moving, protocol=protocol)
        assert result.labels == [1]  # label 2 has no surface either way
        assert result.distance_labels == ([1, 2] if weight else [])
        u, _ = fields_on_grid(result.warp, fixed)
        warped = resample_labels(moving, fixed.grid_points() + u)
        out[weight] = (dice(fixed_a == 2, warped == 2), np.linalg.norm(u[fixed_a == 2], axis=-1).mean(),
                       np.linalg.norm(u[fixed_a == 1], axis=-1).max())
    assert out[0.0][0] == 0.0
    assert out[2.0][0] == 1.0, out
    assert abs(out[2.0][1] - 3.0) < 0.2, out  # the cube moved 3 mm (measured: 3.00-3.06 mm)
    assert out[2.0][2] < 0.05, out  # and the sphere stayed (measured: 0.0015 mm)


def test_distance_maps_alone_drive_when_no_label_gives_a_surface():
    """Three labels of 7 voxels each (none gives a surface), shifted 3 mm along i in the moving
    volume: the distance maps register them (Dice 1, measured shifts 2.98-3.00 mm; by default, and
    beside implicit surfaces, which then note the labels they leave out); with the implicit surfaces
    alone nothing drives and the registration stops with a clear error."""
    from volreg.evaluation.metrics import dice
    from volreg.errors import RegistrationInputError
    from volreg.pipeline.labels import register_labels
    from volreg.io.protocol import load_protocol
    from volreg.warp.field import fields_on_grid
    from volreg.warp.resample import resample_labels
    from volreg.grid import LabelVolume

    fixed_a = np.zeros((40, 40, 40), np.uint8)
    moving_a = fixed_a.copy()
    for label, (i, j, k) in ((1, (8, 10, 10)), (2, (30, 28, 12)), (3, (12, 30, 28))):
        fixed_a[i:i + 2, j:j + 2, k:k + 2] = label
        moving_a[i + 2:i + 4, j:j + 2, k:k + 2] = label
        fixed_a[i, j, k] = moving_a[i + 2, j, k] = 0
    geometry = dict(spacing=np.full(3, 1.5), origin=np.zeros(3), direction=np.eye(3))
    fixed, moving = LabelVolume(fixed_a, **geometry), LabelVolume(moving_a, **geometry)
    default = load_protocol("default")
    with_implicit = dataclasses.replace(default, surface=dataclasses.replace(default.surface, implicit_weight=1.0))
    for protocol in (default, with_implicit):
        result = register_labels(fixed, moving, protocol=protocol)
        assert result.labels == [] and result.distance_labels == [1, 2, 3]
        if protocol is default:
            assert result.skipped == []  # no surface drives, so none is left out
        else:
            assert result.skipped[0] == ("fixed volume: Skipping label 1: Label 1 has 7 voxels, fewer than "
                                         "min_voxels=8; its voxel distance map drives instead.")
            assert result.skipped[5].startswith("moving volume: Skipping label 3:")
        u, _ = fields_on_grid(result.warp, fixed)
        warped = resample_labels(moving, fixed.grid_points() + u)
        for label in (1, 2, 3):
            assert dice(fixed_a == label, warped == label) == 1.0
            assert np.allclose(u[fixed_a == label], [3.0, 0.0, 0.0], atol=0.1)
    protocol = dataclasses.replace(default, surface=dataclasses.replace(default.surface, implicit_weight=1.0,
                                                                         distance_weight=0.0))
    with pytest.raises(RegistrationInputError, match="distance_weight is 0; nothing drives the warp"):
        register_labels(fixed, moving, protocol=protocol)
    with pytest.raises(ValueError, match="`implicit_weight` or `distance_weight` > 0"):
        dataclasses.replace(default.surface, distance_weight=0.0)


def _sphere_on_grid(spacing, radius=25.0, centre=(45.3, 44.6, 45.1), size=90.0):
    """A ball's mask on an axis-aligned grid of ``spacing`` mm and the true signed distance
    (mm, negative inside) of its voxel centres."""
    spacing = np.asarray(spacing, dtype=float)
    axes = [np.arange(n) * h for n, h in zip(np.ceil(size / spacing).astype(int), spacing)]
    world = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    true = np.linalg.norm(world - np.asarray(centre), axis=-1) - radius
    return true < 0, true


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (2.0, 2.0, 2.0), (1.0, 1.0, 1.5), (0.8, 0.8, 2.5)])
def test_midway_distances_measure_to_the_boundary_not_to_the_next_voxel(spacing):
    """Within 3 voxels of a ball's boundary, distances between voxel centres are too long by
    about 0.4 voxel on both sides (measured 0.39, 0.80, 0.40 and 0.40 mm); measured to the
    boundary half-way between the centres, the bias on each side is below a tenth of the largest
    voxel spacing (measured at most 0.06, 0.14, 0.01 and 0.03 mm), and every sign is kept."""
    mask, true = _sphere_on_grid(spacing)
    spacing = np.asarray(spacing)
    band = np.abs(true) < 3 * spacing.max()
    for midway in (False, True):
        d = clipped_signed_distance(mask, spacing, 3 * spacing.max() + 1.0, midway=midway)
        too_long_in = float(np.mean(true[band & mask] - d[band & mask]))
        too_long_out = float(np.mean(d[band & ~mask] - true[band & ~mask]))
        if midway:
            assert max(abs(too_long_in), abs(too_long_out)) < 0.1 * spacing.max(), (too_long_in, too_long_out)
            np.testing.assert_array_equal(np.sign(d), np.where(mask, -1.0, 1.0))
        else:
            assert min(too_long_in, too_long_out) > 0.3 * spacing.min(), (too_long_in, too_long_out)


def test_the_same_ball_at_two_resolutions_gives_the_same_feature():
    """The distance feature of one ball sampled at 1 mm and at 2 mm, as a registration makes it
    (counted in 2 mm voxels): the two maps agree within 0.1 mm on average near the boundary and
    the 2 mm map is not larger or smaller overall (measured 0.083 mm, 0.013 mm signed; distances
    between voxel centres, blurred 2 mm as before: 0.113 and 0.031 mm)."""
    rng = np.random.default_rng(3)
    direction = rng.normal(size=(4000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = np.array([45.3, 44.6, 45.1]) + direction * rng.uniform(22.0, 28.0, (4000, 1))
    gaps = {}
    for scale, smoothing in ((2.0, 1.6), (0.0, 2.0)):
        features = {}
        for h in (1.0, 2.0):
            mask, _ = _sphere_on_grid((h,) * 3)
            features[h] = VoxelDistance(mask, np.full(3, h), np.zeros(3), np.eye(3), clip=6.0, smoothing=smoothing,
                                        scale=scale)
        gaps[scale] = features[2.0].evaluate(points)[0] - features[1.0].evaluate(points)[0]
    assert np.abs(gaps[2.0]).mean() < 0.1 and abs(gaps[2.0].mean()) < 0.02, (np.abs(gaps[2.0]).mean(), gaps[2.0].mean())
    assert np.abs(gaps[2.0]).mean() < np.abs(gaps[0.0]).mean()


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (2.0, 2.0, 2.0), (0.8, 0.8, 2.5)])
def test_blurred_distance_of_a_plane_is_its_signed_distance_at_any_orientation(spacing):
    """A half-space at oblique orientations and sub-voxel offsets: -s Phi^-1 of its voxels blurred
    by a Gaussian of s (the largest spacing) is the signed distance to the plane, within a tenth
    of s on average over the voxels within the clip (measured at most 0.06 at 1 and 2 mm, 0.03 at
    0.8 x 0.8 x 2.5 mm) and with no bias (at most 0.01), closer than the distances between voxel
    centres (at least 0.2 and 0.05); beyond the clip, the clip."""
    spacing = np.asarray(spacing)
    s = float(spacing.max())
    clip = 2 * s
    rng = np.random.default_rng(5)
    shape = tuple(int(v) for v in np.ceil(48.0 / spacing))
    index = np.stack(np.meshgrid(*[np.arange(k) for k in shape], indexing="ij"), axis=-1)
    x = index * spacing - 24.0
    inner = np.all((index * spacing > 4 * s + 1) & (index * spacing < 48 - 4 * s - 1), axis=-1)  # away from the faces
    worst = {"blurred": 0.0, "between centres": np.inf}
    for _ in range(4):
        n = rng.normal(size=3)
        while np.abs(n / np.linalg.norm(n)).min() < 0.3:  # oblique: the staircase averages out within s
            n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        true = x @ n - rng.uniform(-0.5, 0.5) * s
        mask = true < 0
        near = inner & (np.abs(true) < clip - 0.5 * s)
        d = blurred_signed_distance(mask, spacing, s, clip)
        assert d.dtype == np.float32 and d.shape == mask.shape
        err = (d - true)[near]
        assert abs(err.mean()) < 0.02 * s, err.mean()
        worst["blurred"] = max(worst["blurred"], float(np.abs(err).mean()) / s)
        midway = clipped_signed_distance(mask, spacing, clip, midway=True)
        worst["between centres"] = min(worst["between centres"], float(np.abs(midway - true)[near].mean()) / s)
        far = inner & (np.abs(true) > clip + 0.5 * s)
        np.testing.assert_array_equal(d[far], np.where(mask[far], -clip, clip).astype(np.float32))
    assert worst["blurred"] < 0.1 and worst["blurred"] < 0.75 * worst["between centres"], worst


def test_blurred_distance_rejects_bad_scale_and_clip():
    with pytest.raises(ValueError, match="scale"):
        blurred_signed_distance(np.ones((4, 4, 4), bool), np.ones(3), 0.0, 2.0)
    with pytest.raises(ValueError, match="clip"):
        blurred_signed_distance(np.ones((4, 4, 4), bool), np.ones(3), 1.0, -1.0)
    with pytest.raises(ValueError, match="scale"):
        VoxelDistance(np.ones((4, 4, 4), bool), np.ones(3), np.zeros(3), np.eye(3), clip=2.0, scale=-1.0)


@pytest.mark.parametrize("shape, spacing", [((23, 31, 17), (1.5, 1.0, 2.5)), ((40, 29), (0.9375, 1.2)),
                                            ((9, 1, 30), (1.0, 2.0, 0.5)), ((12, 12, 12), (0.8, 0.8, 0.8))])
def test_separable_distance_equals_scipys(shape, spacing, monkeypatch):
    monkeypatch.setattr(distance_maps, "SEPARABLE_CELLS", 0)  # the separable passes whatever the size
    rng = np.random.default_rng(len(shape) * 7 + shape[0])
    masks = [rng.random(shape) < 0.9,  # scattered zeros: many lines without one
             np.ones(shape, bool)]
    masks[1][(0,) * len(shape)] = False  # one zero in a corner: distances across the whole box
    for mask in masks:
        expected = ndimage.distance_transform_edt(mask, sampling=spacing)
        found = euclidean_distance(mask, spacing)
        assert found.shape == mask.shape and found.dtype == np.float64
        np.testing.assert_allclose(found, expected, rtol=1e-14, atol=0)
    assert np.array_equal(euclidean_distance(masks[0], (1.0,) * len(shape)),
                          ndimage.distance_transform_edt(masks[0]))  # integer squared sums: the same bits
    with pytest.raises(ValueError, match="one spacing per axis"):
        euclidean_distance(masks[0], (1.0,))
