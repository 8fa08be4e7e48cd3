"""FeatureBatch: many features, each at its own points, equal to their own ``evaluate``;
the objective with the batch equals the objective evaluating one feature at a time."""

import numpy as np
import pytest

from volreg.features.batch import FeatureBatch
from volreg.features.distance_maps import VoxelDistance
from volreg.features.implicit import ImplicitSurface
from volreg.features.mapped import LinearlyMapped
from volreg.kernels import kernel_matrix
from volreg.linear_map import LinearMap
from volreg.warp.objective import FeaturePair, LevelObjective


def _sphere_points(centre, radius, count, rng):
    u = rng.normal(size=(count, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return centre + radius * u, u


def _features(rng, shift=0.0):
    """Two implicit surfaces (a sphere, an ellipsoid) and two voxel distance maps (an axis-aligned
    and an oblique grid), mm."""
    out = []
    for centre, axes in (((0.0, 0.0, 0.0), (9.0, 9.0, 9.0)), ((14.0, 3.0, -2.0), (6.0, 8.0, 5.0))):
        pts, u = _sphere_points(np.zeros(3), 1.0, 1500, rng)
        pts = np.asarray(centre) + shift + pts * axes
        normals = u / np.asarray(axes)
        out.append(ImplicitSurface(pts, normals / np.linalg.norm(normals, axis=1, keepdims=True), min_width=4.0))
    t = np.deg2rad(20.0)
    oblique = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    for direction, spacing in ((np.eye(3), np.array([1.0, 1.2, 1.5])), (oblique, np.array([1.1, 1.0, 1.3]))):
        shape = (30, 28, 24)
        origin = np.array([-15.0, -14.0, -12.0]) + shift
        index = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
        world = origin + (index * spacing) @ direction.T
        mask = np.linalg.norm(world - (origin + (np.array(shape) / 2 * spacing) @ direction.T), axis=-1) < 8.0
        out.append(VoxelDistance(mask, spacing, origin, direction, clip=5.0, smoothing=1.0))
    return out


@pytest.mark.parametrize("mapped", [False, True], ids=["plain", "linearly-mapped"])
@pytest.mark.parametrize("order", [0, 1, 2])
def test_batch_equals_each_features_own_evaluation(mapped, order):
    rng = np.random.default_rng(5)
    features = _features(rng)
    if mapped:
        linear = LinearMap(np.array([[1.05, 0.04, 0.0], [-0.03, 0.97, 0.02], [0.01, 0.0, 1.02]]),
                           np.array([0.5, -0.3, 0.2]))
        features = [LinearlyMapped(f, linear) for f in features]
    batch = FeatureBatch.build(features)
    assert batch is not None
    counts = [40, 0, 25, 70]  # an empty segment too
    segments = [rng.uniform(-16, 16, (c, 3)) for c in counts]
    out = batch.evaluate(np.concatenate(segments), np.cumsum([0] + counts), order=order)
    assert len(out) == order + 1
    for k in range(order + 1):
        ref = np.concatenate([f.evaluate(s, order=order)[k] for f, s in zip(features, segments)])
        # Same sums, possibly reassociated: rounding only (values are tens of mm at most).
        np.testing.assert_allclose(out[k], ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", ["implicit", "voxel"])
@pytest.mark.parametrize("order", [0, 1, 2])
def test_batch_of_one_kind_equals_each_features_own_evaluation(kind, order):
    """Features of one kind only; the voxel maps cropped from one volume (its grid's axes and
    spacing, each map its own origin), as a label volume's maps are."""
    rng = np.random.default_rng(7)
    if kind == "implicit":
        features = _features(rng)[:2]
    else:
        spacing, direction = np.array([1.0, 1.2, 1.5]), np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        features = []
        for origin, radius in (((-15.0, -14.0, -12.0), 8.0), ((-11.0, -16.0, -9.0), 6.0)):
            shape = (30, 28, 24)
            index = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
            world = np.asarray(origin) + (index * spacing) @ direction.T
            centre = np.asarray(origin) + (np.array(shape) / 2 * spacing) @ direction.T
            mask = np.linalg.norm(world - centre, axis=-1) < radius
            features.append(VoxelDistance(mask, spacing, np.asarray(origin), direction, clip=5.0, smoothing=1.0))
    batch = FeatureBatch.build(features)
    counts = [35, 50]
    centre = np.array([-30.0, 0.0, 7.0])  # about where the maps lie
    segments = [centre + rng.uniform(-12, 12, (c, 3)) for c in counts]
    out = batch.evaluate(np.concatenate(segments), np.cumsum([0] + counts), order=order)
    for k in range(order + 1):
        ref = np.concatenate([f.evaluate(s, order=order)[k] for f, s in zip(features, segments)])
        np.testing.assert_allclose(out[k], ref, rtol=1e-12, atol=1e-12)


def test_build_refuses_unsupported_or_mixed_features():
    rng = np.random.default_rng(6)
    features = _features(rng)
    other = LinearMap(np.eye(3), np.array([1.0, 0.0, 0.0]))
    assert FeatureBatch.build([object()]) is None
    assert FeatureBatch.build([features[0], LinearlyMapped(features[1], other)]) is None
    assert FeatureBatch.build([LinearlyMapped(features[0], LinearMap(np.eye(3), np.zeros(3))),
                               LinearlyMapped(features[1], other)]) is None
    batch = FeatureBatch.build(features)
    with pytest.raises(ValueError, match="`starts`"):
        batch.evaluate(np.zeros((5, 3)), np.array([0, 1, 2, 3, 4]))


@pytest.mark.parametrize("kw", [dict(alpha=0.0), dict(alpha=2.0), dict(alpha=1.0, robust=0.4)],
                         ids=["distance-only", "gradient", "robust"])
def test_objective_with_the_batch_equals_one_feature_at_a_time(kw):
    rng = np.random.default_rng(7)
    fixed, moving = _features(rng), _features(np.random.default_rng(7), shift=0.8)
    pairs = [FeaturePair(f1, f2, weight=w) for f1, f2, w in zip(fixed, moving, (1.0, 0.5, 2.0, 1.0))]
    samples = rng.uniform(-16, 16, (600, 3))
    centres = samples[::4]
    subsets = [np.flatnonzero(np.abs(p.f1.evaluate(samples, order=0)[0]) < 4.0) for p in pairs]
    subsets[1] = None  # one feature at every sample
    common = dict(kernel=kernel_matrix(samples, centres, 12.0), kernel_centres=kernel_matrix(centres, centres, 12.0),
                  base=samples + 0.1, samples=samples, features=pairs, lambda_loc=5.0, feature_samples=subsets, **kw)
    batched, single = LevelObjective(**common), LevelObjective(**common, batched=False)
    assert batched._batch is not None and single._batch is None
    for scale in (0.0, 0.3):
        c = rng.normal(0, scale, len(centres) * 3)
        (e1, g1), (e2, g2) = batched(c), single(c)
        assert e1 == pytest.approx(e2, rel=1e-10)
        np.testing.assert_allclose(g1, g2, rtol=1e-10, atol=1e-10 * np.abs(g2).max())
        for name in ("distance", "gradient"):
            assert batched.last_terms[name] == pytest.approx(single.last_terms[name], rel=1e-10, abs=1e-300)
        # The Gauss-Newton blocks too, and with them the same value and gradient.
        (e3, g3, b1), (_, _, b2) = batched.gauss_newton(c), single.gauss_newton(c)
        assert (e3, g3.tolist()) == (e1, g1.tolist())
        assert np.abs(b2).max() > 0
        np.testing.assert_allclose(b1, b2, rtol=1e-10, atol=1e-10 * np.abs(b2).max())


@pytest.mark.parametrize("order", [0, 1, 2])
@pytest.mark.parametrize("parts", [2, 3, 8, 50])
def test_parts_of_equal_points_cut_through_features_and_equal_one_part_to_the_bit(order, parts, monkeypatch):
    """The batch's loops split the points, not the features, between their parts: a feature
    holding most of the points (a large label among small ones) is shared out. Every part run
    in turn gives each point exactly what one part alone gives it."""
    import volreg.features.batch as batch_module

    rng = np.random.default_rng(11)
    features = _features(rng)
    counts = [5, 0, 300]  # one feature with most of the points, an empty one
    starts = np.cumsum([0] + counts).astype(np.int64)
    points = rng.uniform(-16, 16, (int(starts[-1]), 3))
    groups = [(batch_module._Implicit(features[:2] + features[:1], 3), starts),
              (batch_module._Voxel(features[2:] + features[2:3], 3), starts)]
    for group, seg in groups:
        ref = group.evaluate(points, seg, order)
        calls = []

        def every_part(loop, n, *args, grain=1):
            calls.append(n)
            for part in range(parts):  # one after another, whatever the thread count
                loop(part, parts, *args)

        monkeypatch.setattr(batch_module, "run_parts", every_part)
        split = group.evaluate(points, seg, order)
        monkeypatch.undo()
        assert calls == [len(points)]  # parts over the points
        for a, b in zip(split, ref):
            np.testing.assert_array_equal(a, b)
        assert np.all(split[0] != 0)  # every point got its sums
