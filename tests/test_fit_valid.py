"""Locational-cost samples restricted by a mask (``fit_warp(valid=...)``), 2-D.

Two ellipses 60 mm apart (semi-axes 8 x 6 mm, centres at x = -30 and x = +30),
each a feature of its own; in the target both are shifted 3 mm along y.  A mask
that drops the half-space x > 0 leaves the right ellipse without any locational
cost: the warp must then leave it in place, as it must where a target image does
not see an object.
"""

import numpy as np
import pytest

from shapes import Disc2D
from volreg.features.implicit import ImplicitSurface
from volreg.settings import WarpSettings
from volreg.warp.fit import fit_warp
from volreg.warp.objective import FeaturePair

SHIFT = np.array([0.0, 3.0])  # mm
SETTINGS = WarpSettings(alpha=10.0)


@pytest.fixture(scope="module")
def problem():
    rng = np.random.default_rng(7)
    pairs, points = [], []
    for cx in (-30.0, 30.0):
        p1, n1 = Disc2D((8.0, 6.0), (cx, 0.0)).surface_points(400, rng)
        p2, n2 = Disc2D((8.0, 6.0), np.array([cx, 0.0]) + SHIFT).surface_points(400, rng)
        pairs.append(FeaturePair(ImplicitSurface(p1, n1, min_width=4.0), ImplicitSurface(p2, n2, min_width=4.0)))
        points.append(p1)
    return pairs, np.concatenate(points)


@pytest.fixture(scope="module")
def unmasked(problem):
    pairs, points = problem
    return fit_warp(pairs, points, settings=SETTINGS)


def _same_warp(a, b):
    assert len(a.levels) == len(b.levels) >= 3
    for la, lb in zip(a.levels, b.levels):
        assert la.width == lb.width
        np.testing.assert_array_equal(la.centres, lb.centres)
        np.testing.assert_array_equal(la.coeffs, lb.coeffs)


def test_a_mask_keeping_every_sample_gives_the_same_warp(problem, unmasked):
    pairs, points = problem
    kept = fit_warp(pairs, points, settings=SETTINGS, valid=lambda x: np.ones(len(x), dtype=bool))
    _same_warp(kept.warp, unmasked.warp)  # bit for bit
    for a, b in zip(kept.log, unmasked.log):
        assert a["valid_samples"] == a["samples"] == b["samples"]
        assert a["terms"] == b["terms"] and a["iterations"] == b["iterations"]
    assert all("valid_samples" not in entry for entry in unmasked.log)


def test_masked_half_space_pulls_nothing(problem, unmasked):
    pairs, points = problem
    calls = []

    def left_half(x):
        calls.append(x.shape)
        return x[:, 0] < 0.0

    masked = fit_warp(pairs, points, settings=SETTINGS, valid=left_half)
    # Called with the (N, D) samples, once per sample set (here one set for every level).
    assert calls and all(len(c) == 2 and c[1] == 2 for c in calls)
    for entry in masked.log:
        assert 0 < entry["valid_samples"] < entry["samples"]
    left, right = points[points[:, 0] < 0], points[points[:, 0] > 0]
    u_right = np.linalg.norm(masked.warp(right) - right, axis=1)
    u_right_ref = np.linalg.norm(unmasked.warp(right) - right, axis=1)
    # Unmasked, the right ellipse follows its 3 mm shift (the implicit surfaces fit to about
    # 0.1 mm; measured mean 3.007 mm).  Masked, nothing pulls it: its nearest kept samples lie
    # more than one coarsest kernel width (38 mm) away, so only the regulariser's coupling
    # reaches it (measured max 0.0004 mm).
    assert u_right_ref.min() > 2.5
    assert u_right.max() < 0.05
    assert u_right.max() < 0.02 * u_right_ref.min()
    # The kept half is fitted as without the mask (measured mean error 0.02 mm both ways).
    err_left = np.linalg.norm(masked.warp(left) - (left + SHIFT), axis=1)
    assert err_left.mean() < 0.3
    np.testing.assert_allclose(masked.warp(left), unmasked.warp(left), atol=0.1)  # mm


def test_a_mask_dropping_every_sample_leaves_the_identity(problem):
    pairs, points = problem
    # No locational cost, no landmarks: the regulariser alone is minimal at zero coefficients.
    none = fit_warp(pairs, points, settings=SETTINGS, valid=lambda x: np.zeros(len(x), dtype=bool))
    np.testing.assert_array_equal(none.warp(points), points)
    assert all(entry["valid_samples"] == 0 and entry["terms"]["distance"] == 0.0 for entry in none.log)


@pytest.mark.parametrize("valid, match", [
    (lambda x: np.ones(len(x) + 1, dtype=bool), r"`valid` to return a bool array of shape \(\d+,\)"),
    (lambda x: np.ones((len(x), 1), dtype=bool), r"`valid` to return a bool array"),
    (lambda x: x[:, 0], r"`valid` to return a bool array .* got float64"),
    (np.ones(5, dtype=bool), r"`valid` as a callable"),
])
def test_bad_valid(problem, valid, match):
    pairs, points = problem
    with pytest.raises(ValueError, match=match):
        fit_warp(pairs, points, settings=SETTINGS, valid=valid)


@pytest.mark.parametrize("band, reach", [(None, 0.0), (2.5, 1.5)])
def test_feature_samples_are_those_within_band_of_the_feature_points(problem, band, reach):
    """Per feature, the samples whose nearest source surface point is nearer than the band (half
    the finest implicit width by default) plus the neighbourhood's reach, and no other: the same
    as a brute-force search over every sample, also for samples near the other feature only."""
    from volreg.warp.fit import _feature_samples

    pairs, _ = problem
    rng = np.random.default_rng(3)
    samples = np.concatenate([rng.uniform([-50.0, -20.0], [50.0, 20.0], (3000, 2)),
                              pairs[0].f1.points[:200] + rng.normal(0.0, 2.0, (200, 2))])
    subsets = _feature_samples(pairs, samples, band, reach)
    assert len(subsets) == len(pairs)
    for pair, idx in zip(pairs, subsets):
        limit = (0.5 * min(pair.f1.widths) if band is None else band) + reach
        nearest = np.min(np.linalg.norm(samples[:, None, :] - pair.f1.points[None], axis=2), axis=1)
        assert np.array_equal(idx, np.flatnonzero(nearest < limit))
        assert 50 < len(idx) < len(samples) // 2


@pytest.mark.parametrize("after", [1, 2])
def test_stop_ends_the_fit_after_the_level_it_answers_true(problem, unmasked, after):
    """`stop(warp)` is asked after each level but the last with the warp so far; where it says
    True the finer levels are not fitted, and the levels fitted are those of the whole fit."""
    pairs, points = problem
    seen = []

    def stop(warp):
        seen.append(len(warp.levels))
        return len(warp.levels) == after

    early = fit_warp(pairs, points, settings=SETTINGS, stop=stop)
    assert seen == list(range(1, after + 1))
    assert len(early.log) == len(early.warp.levels) == after < len(unmasked.warp.levels)
    for la, lb in zip(early.warp.levels, unmasked.warp.levels):
        np.testing.assert_array_equal(la.coeffs, lb.coeffs)
    asked = []
    whole = fit_warp(pairs, points, settings=SETTINGS, stop=lambda warp: asked.append(len(warp.levels)) or False)
    assert asked == list(range(1, len(unmasked.warp.levels)))  # not after the last level
    _same_warp(whole.warp, unmasked.warp)
