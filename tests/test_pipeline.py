"""Coarse-to-fine kernel warps between surfaces (2-D).

Paper Figure 2: a square with a triangular protrusion; in the target the
protrusion is shifted 8 mm along the outline.  The distance-only cost (3)
cannot tell the protrusion's sides apart; with the gradient term (4) the sides
land on their partners.
"""

import numpy as np
import pytest

from volreg.features.implicit import ImplicitSurface
from volreg.settings import WarpSettings
from volreg.pipeline.surfaces import register_surfaces
from volreg.features.label_surfaces import label_surface
from volreg.grid import LabelVolume

# Protrusion: base on x = 20 from y = s - 8 to s + 8, tip at (30, s).
TOP_MID, BOTTOM_MID, TIP = np.array([25.0, 4.0]), np.array([25.0, -4.0]), np.array([30.0, 0.0])
SHIFT = np.array([0.0, 8.0])


def _outline(shift: float) -> ImplicitSurface:
    geom = LabelVolume(np.zeros((100, 100), np.uint8), (-49.5, -49.5), (1.0, 1.0), np.eye(2))
    x, y = geom.grid_points().reshape(-1, 2).T
    square = (np.abs(x) <= 20) & (np.abs(y) <= 20)
    tri = (x >= 20) & (x <= 30) & (np.abs(y - shift) <= 8 * (30 - x) / 10)
    vol = geom.with_array((square | tri).reshape(100, 100).astype(np.uint8))
    surf = label_surface(vol, 1)
    return surf, ImplicitSurface(surf.vertices, surf.normals, min_width=4.0)


@pytest.fixture(scope="module")
def shapes():
    return _outline(0.0), _outline(8.0)


@pytest.fixture(scope="module")
def warps(shapes):
    (_, f1), (_, f2) = shapes
    return {alpha: register_surfaces(f1, f2, settings=WarpSettings(alpha=alpha)) for alpha in (0.0, 10.0)}


def _errors(warp):
    probe = np.array([TOP_MID, BOTTOM_MID, TIP])
    return np.linalg.norm(warp(probe) - (probe + SHIFT), axis=1)


def test_gradient_term_puts_the_protrusion_sides_on_their_partners(warps):
    # Measured: top 0.12, bottom 0.16, tip 0.10 mm (1 mm pixels).
    assert np.all(_errors(warps[10.0].warp) <= 1.5)


def test_distance_only_cost_is_worse(warps):
    # Measured: top 0.92, bottom 0.79, tip 0.59 mm with alpha = 0, against 0.1-0.2 mm with the
    # gradient term.  (When each level was sampled only at its own octree boxes, alpha = 0 left
    # them 9-12 mm off, the paper's failure mode; sampling the locational cost at the finest
    # boxes on every level, within a band around the surface, removes most of that failure.)
    assert np.all(_errors(warps[10.0].warp) < _errors(warps[0.0].warp))


def test_half_way_morph_keeps_a_single_protrusion(shapes, warps):
    (surf, _), _ = shapes
    v = surf.vertices
    morph = v + 0.5 * (warps[10.0].warp(v) - v)
    out = morph[morph[:, 0] > 21.0]
    ys = np.sort(out[:, 1])
    assert np.diff(ys).max() < 2.0  # one contiguous bump, no ghost
    tip = out[np.argmax(out[:, 0])]
    assert tip[0] > 28.0 and 2.0 <= tip[1] <= 6.0  # the tip half way, at y = 4


def test_no_folding_at_the_samples(warps):
    for result in warps.values():
        samples = np.concatenate([level.centres for level in result.warp.levels])
        assert np.linalg.det(result.warp.jacobian(samples)).min() > 0
    # With the gradient cost the whole neighbourhood stays unfolded (measured min det 0.28).
    pts = np.random.default_rng(0).uniform([-35.0, -35.0], [40.0, 35.0], (20000, 2))
    assert np.linalg.det(warps[10.0].warp.jacobian(pts)).min() > 0


def test_log_records_every_level(warps):
    log = warps[10.0].log
    widths = [entry["width"] for entry in log]
    np.testing.assert_allclose(np.array(widths[1:]) / widths[:-1], 0.5)
    for entry in log:
        assert entry["samples"] > 0 and entry["seconds"] > 0
        assert entry["objective"] <= entry["objective_start"]
        assert set(entry["terms"]) == {"regulariser", "landmarks", "distance", "gradient", "folding", "consistency"}


def test_finer_samples_only_at_the_levels_narrower_than_four_finest_widths(shapes, warps):
    """sample_scale 0.5: the levels of width >= 4 min_width keep the default samples (the
    finest width's boxes); the finer levels get the denser set, and the fit stays as good."""
    (_, f1), (_, f2) = shapes
    dense = register_surfaces(f1, f2, settings=WarpSettings(alpha=10.0, sample_scale=0.5))
    plain = warps[10.0].log
    min_width = plain[-1]["width"]
    assert len(dense.log) == len(plain) >= 3
    for d, p in zip(dense.log, plain):
        if d["width"] >= 4 * min_width * (1 - 1e-9):
            assert d["samples"] == p["samples"]
        else:
            assert d["samples"] > 2 * p["samples"]
    assert any(d["samples"] > p["samples"] for d, p in zip(dense.log, plain))
    assert np.all(_errors(dense.warp) <= 1.5)


def test_registering_a_surface_to_itself_is_the_identity(shapes):
    (_, f1), _ = shapes
    result = register_surfaces(f1, f1)
    pts = np.random.default_rng(1).uniform(-35, 35, (2000, 2))
    assert np.abs(result.warp(pts) - pts).max() <= 0.01  # 0.01 pixel


def test_landmarks_are_hit_and_help_held_out_points(shapes):
    (_, f1), (_, f2) = shapes
    side = lambda t, sgn: np.array([20 + 10 * t, sgn * 8 * (1 - t)])  # noqa: E731
    train_src = np.array([side(t, s) for t in (0.2, 0.5, 0.8) for s in (1, -1)]
                         + [[30.0, 0.0], [-20.0, 10.0], [-20.0, -10.0], [0.0, -20.0]])
    train_dst = train_src + np.where(train_src[:, :1] > 20.5, SHIFT, 0.0)
    held = np.array([side(t, s) for t in (0.35, 0.65) for s in (1, -1)])
    held_dst = held + SHIFT
    settings = WarpSettings(alpha=0.0, lambda_p=1e6)
    with_lm = register_surfaces(f1, f2, landmarks=(train_src, train_dst), settings=settings).warp
    without = register_surfaces(f1, f2, settings=WarpSettings(alpha=0.0)).warp
    diameter = f1.diameter
    train_err = np.linalg.norm(with_lm(train_src) - train_dst, axis=1)
    assert train_err.max() <= 0.0005 * diameter
    err_with = np.linalg.norm(with_lm(held) - held_dst, axis=1).mean()
    # Landmarks are kernel centres too, so one far outside the warp volume is fitted as well.
    far_src, far_dst = np.array([[-40.0, 0.0]]), np.array([[-40.0, 3.0]])
    far = register_surfaces(f1, f2, landmarks=(np.concatenate([train_src, far_src]),
                                               np.concatenate([train_dst, far_dst])), settings=settings).warp
    assert np.linalg.norm(far(far_src) - far_dst) <= 0.0005 * diameter
    err_without = np.linalg.norm(without(held) - held_dst, axis=1).mean()
    assert err_with < 0.5 * err_without


def test_bad_inputs():
    pts = np.random.default_rng(2).normal(size=(50, 2))
    with pytest.raises(ValueError, match="`alpha`"):
        WarpSettings(alpha=-1.0)
    with pytest.raises(ValueError, match="`pad`"):
        WarpSettings(pad=0.0)
    with pytest.raises(TypeError, match="`source`/`target`"):
        register_surfaces(pts, pts)
    f = ImplicitSurface(pts * 10, min_width=5.0)
    with pytest.raises(ValueError, match="`lambda_p` > 0"):
        register_surfaces(f, f, landmarks=(pts[:3], pts[:3]), settings=WarpSettings(lambda_p=0.0))
    with pytest.raises(ValueError, match="as many `target`"):
        f = ImplicitSurface(pts * 10, min_width=5.0)
        register_surfaces([f, f], [f])


def test_fold_barrier_on_its_active_set_fits_as_the_barrier_on_every_point(shapes, monkeypatch):
    """The fold barrier is carried only by check points near fold_margin (plus those that
    cross it, in further rounds); the fit must be that of the barrier on every point."""
    from volreg.warp import fit

    (_, f1), _ = shapes
    src = np.array([[20.0, -3.0], [20.0, 3.0]])  # two outline points that swap places: the warp must fold
    settings = WarpSettings(lambda_p=10.0, min_width=7.0, max_iter=100)
    subset = register_surfaces(f1, f1, landmarks=(src, src[::-1].copy()), settings=settings).log
    monkeypatch.setattr(fit, "FOLD_SLACK", np.inf)  # every check point carries the barrier
    full = register_surfaces(f1, f1, landmarks=(src, src[::-1].copy()), settings=settings).log
    checks = 5 * full[0]["samples"]  # the samples and their 4 octree children in 2-D
    assert all(e["fold_points"] == checks for e in full)
    assert all(e["fold_points"] < checks for e in subset)
    assert max(e["terms"]["folding"] for e in subset) > 1.0  # the barrier acted (measured 5.3 and 10.6)
    for a, b in zip(subset, full):
        # Measured: 381.405 / 381.405, 315.373 / 315.374, 309.208 / 309.266.
        assert a["objective"] == pytest.approx(b["objective"], rel=0.01)


@pytest.mark.parametrize(
    "settings, widths, steps",
    [
        (WarpSettings(min_width=4.0), [32, 16, 8, 4], [4, 4, 4, 4]),
        (WarpSettings(min_width=5.0), [32, 16, 8], [5, 5, 5]),  # stops above min_width, never below
        (WarpSettings(min_width=4.0, sample_scale=0.5), [32, 16, 8, 4], [4, 4, 2, 2]),
        (WarpSettings(min_width=4.0, sample_scale=2.0), [32, 16, 8, 4], [8, 8, 8, 8]),
        (WarpSettings(min_width=4.0, sample_spacing=1.0), [32, 16, 8, 4], [4, 4, 2, 1]),
        (WarpSettings(), [32, 16, 8, 4], [4, 4, 4, 4]),  # min_width: 1/16 of the diameter
        # min_width wider than the coarsest level: that level alone, sampled at its own width
        (WarpSettings(min_width=60.0), [32], [32]),
        (WarpSettings(min_width=60.0, sample_scale=0.5), [32], [16]),
    ],
)
def test_level_schedule(settings, widths, steps):
    """Widths 1/2, 1/4, ... of the diameter down to min_width (paper Section 3.5); samples at
    max(spacing, min(width / 4, min_width)) with spacing = sample_spacing or sample_scale * min_width."""
    from volreg.warp.fit import _level_schedule

    got_widths, got_steps = _level_schedule(64.0, settings.resolved(64.0))
    assert got_widths == widths and got_steps == steps


def test_a_min_width_wider_than_the_object_fits_one_level_and_no_samples_are_refused():
    """min_width 60 mm on a 20 mm circle: one level of half the diameter, fitted (octree boxes
    of 60 mm held no sample, and the objective divided by their count); a sample spacing that
    leaves no sample is refused naming it."""
    from volreg.errors import ProtocolError
    from volreg.features.implicit import ImplicitSurface
    from volreg.warp.fit import fit_warp
    from volreg.warp.objective import FeaturePair

    t = np.linspace(0, 2 * np.pi, 80, endpoint=False)
    normals = np.c_[np.cos(t), np.sin(t)]
    f1 = ImplicitSurface(10.0 * normals, normals)
    f2 = ImplicitSurface(10.5 * normals + [1.0, 0.0], normals)
    result = fit_warp([FeaturePair(f1, f2)], 10.0 * normals, settings=WarpSettings(min_width=60.0))
    assert len(result.log) == 1 and result.log[0]["samples"] > 0
    moved = result.warp(10.0 * normals) - 10.0 * normals
    assert np.all(np.isfinite(moved)) and moved[:, 0].mean() > 0.1  # towards the shifted circle
    with pytest.raises(ProtocolError, match="sample_spacing"):
        fit_warp([FeaturePair(f1, f2)], 10.0 * normals, settings=WarpSettings(min_width=4.0, sample_spacing=500.0))


def test_fold_guard_shrinks_a_folding_level_by_powers_of_0_7():
    from volreg.warp.fit import _fold_guard
    from volreg.warp.model import jacobian_det

    base = np.repeat(np.eye(2)[None], 3, axis=0)
    level = np.zeros((3, 2, 2))
    level[:, 0, 0] = [-0.95, -0.5, 0.0]  # det(I + s level) = 1 - 0.95 s at the first point
    assert _fold_guard(base, level, jacobian_det(base + level), min_det=0.1) == 0.7
    assert _fold_guard(base, 0.1 * level, jacobian_det(base + 0.1 * level), min_det=0.1) == 1.0
    hopeless = np.zeros((1, 2, 2))
    hopeless[0, 0, 0] = -1e6
    assert _fold_guard(base[:1], hopeless, jacobian_det(base[:1] + hopeless), min_det=0.1) == 0.0
    # Where the coarser levels already fold, the level only must not make it worse.
    folded = np.array([[[0.05, 0.0], [0.0, 1.0]]])
    assert _fold_guard(folded, np.zeros((1, 2, 2)), jacobian_det(folded), min_det=0.1) == 1.0


def test_fit_warp_refuses_source_points_without_extent():
    from volreg.warp.fit import fit_warp

    with pytest.raises(ValueError, match="`source_points` of positive extent"):
        fit_warp([], np.ones((5, 2)))


def test_despeckle_removes_pieces_under_the_speck_fraction_and_judges_at_another():
    from volreg.pipeline.label_features import SPECK_FRACTION, despeckle

    a = np.zeros((30, 30, 30), np.uint8)
    a[2:12, 2:12, 2:12] = 3  # 1000 voxels
    a[20:23, 20:23, 20:23] = 3  # 27 voxels: 2.6 % of the label, over SPECK_FRACTION, under 5 %
    a[27, 27, 27] = 3  # 1 voxel: 0.1 %
    vol = LabelVolume(a, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(3))
    assert SPECK_FRACTION < 27 / 1028
    cleaned, kept = despeckle(vol, [3], piece=SPECK_FRACTION, judge=0.05)
    assert np.count_nonzero(cleaned.array == 3) == 1027 and cleaned.array[27, 27, 27] == 0
    assert kept[3] == pytest.approx(1000 / 1028)
    cleaned5, kept5 = despeckle(vol, [3])
    assert np.count_nonzero(cleaned5.array == 3) == 1000 and kept5[3] == kept[3]
    assert np.array_equal(vol.array, a)  # input untouched
