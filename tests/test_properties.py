"""Property-based tests (hypothesis) of warps and label resampling."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volreg import LabelVolume
from volreg.warp.inverse import invert_points
from volreg.warp.resample import resample_labels
from volreg.warp.model import KernelWarp, WarpLevel

FAST = settings(max_examples=25, deadline=None)


@st.composite
def label_volumes(draw):
    """Small 3-D label volumes with a few to a dozen arbitrary label values (0 = background) on a
    random grid (label resampling takes another path beyond 8 labels)."""
    shape = tuple(draw(st.integers(3, 9)) for _ in range(3))
    values = draw(st.lists(st.integers(1, 60000), min_size=1, max_size=12, unique=True))
    dtype = np.uint16
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    arr = rng.choice(np.array([0, *values], dtype=dtype), size=shape)
    spacing = tuple(draw(st.floats(0.5, 3.0)) for _ in range(3))
    origin = tuple(draw(st.floats(-50, 50)) for _ in range(3))
    return LabelVolume(arr, origin, spacing, np.eye(3))


@st.composite
def smooth_warps(draw, invertible: bool = True):
    """Kernel warps with a few centres; coefficients small enough (|c| k'(0) < 1) to stay invertible."""
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    width = draw(st.floats(5.0, 30.0))
    n = draw(st.integers(1, 6))
    centres = rng.uniform(-20, 20, (n, 3))
    # the Wu kernel's gradient is at most ~ 6 / width; keep sum |c| * that below 1/2
    scale = 0.5 * width / (6.0 * n) if invertible else width
    coeffs = rng.uniform(-1, 1, (n, 3)) * scale
    return KernelWarp([WarpLevel(centres, coeffs, width=width)], dim=3)


@FAST
@given(label_volumes())
def test_identity_in_identity_out(volume):
    """A warp with zero coefficients maps every point to itself and reproduces the labels exactly."""
    warp = KernelWarp([WarpLevel(np.zeros((2, 3)), np.zeros((2, 3)), width=10.0)], dim=3)
    points = volume.grid_points().reshape(-1, 3)
    assert np.array_equal(warp(points), points)
    for method in ("label", "gaussian"):
        assert np.array_equal(resample_labels(volume, points.reshape(*volume.shape, 3), method=method), volume.array)


@FAST
@given(label_volumes(), smooth_warps(invertible=False))
def test_warping_preserves_the_label_set(volume, warp):
    """Label resampling through any warp yields only labels of the input, in its dtype."""
    points = warp(volume.grid_points().reshape(-1, 3)).reshape(*volume.shape, 3)
    for method in ("label", "nearest", "gaussian"):
        out = resample_labels(volume, points, method=method)
        assert set(np.unique(out).tolist()) <= set(np.unique(volume.array).tolist()) | {0}
        assert out.dtype == volume.array.dtype or np.can_cast(out.dtype, volume.array.dtype)


def _blocks_and_points(volume, block: int, seed: int):
    """``volume`` with each voxel repeated ``block`` times along every axis, and continuous
    indices (N, 3) to sample it at: anywhere inside, at voxel centres, and some outside."""
    array = volume.array
    for axis in range(3):
        array = np.repeat(array, block, axis=axis)
    rng = np.random.default_rng(seed)
    size = np.array(array.shape)
    index = np.concatenate([rng.uniform(-0.5, size - 0.5, (3000, 3)),  # inside, anywhere
                            rng.integers(0, size, (100, 3)).astype(float),  # voxel centres
                            rng.uniform(-3, size + 2, (100, 3))])  # some outside
    return LabelVolume(array, volume.origin, volume.spacing, np.eye(3)), index


@FAST
@given(label_volumes(), st.integers(1, 3), st.integers(0, 2**31 - 1))
def test_label_resampling_follows_its_definition(volume, block, seed):
    """At any point inside the image, the label whose linearly interpolated signed distance map
    (the whole volume's, clamped at its edges) is the most negative, the first such label on ties,
    or 0 where none is negative; outside the image, 0.  Blocks of ``block`` voxels of one label
    give points whose interpolation voxels all hold one label, and points near boundaries."""
    from scipy import ndimage

    from volreg.warp.resample import signed_distance_map

    volume, index = _blocks_and_points(volume, block, seed)
    array, size = volume.array, np.array(volume.shape)
    points = volume.index_to_world(index)

    out = resample_labels(volume, points)

    best = np.zeros(len(index))
    expected = np.zeros(len(index), dtype=array.dtype)
    for value in volume.labels():
        d = ndimage.map_coordinates(signed_distance_map(array == value, volume.spacing), index.T, order=1,
                                    mode="nearest")
        win = d < best
        best[win], expected[win] = d[win], value
    inside = np.all((index >= -0.5) & (index <= size - 0.5), axis=1)
    expected[~inside] = 0
    assert np.array_equal(out, expected)


@FAST
@given(label_volumes(), st.integers(1, 3), st.integers(0, 2**31 - 1))
@pytest.mark.system
def test_gaussian_label_resampling_follows_its_definition(volume, block, seed):
    """``"gaussian"``: a point whose linear stencil holds one value takes it, a point at a voxel
    centre that voxel's value; any other point inside the image the value (the background
    included) whose indicator, blurred by a Gaussian of GAUSSIAN_SIGMA geometric-mean voxels over
    the whole volume (clamped at its edges) and read by cubic B-spline, is the largest, wherever
    the largest leads the next by more than 1e-4 (each label's blur is made on its box, padded);
    outside the image, 0."""
    from itertools import product

    from scipy import ndimage

    from volreg.warp.resample import GAUSSIAN_SIGMA

    volume, index = _blocks_and_points(volume, block, seed)
    array, size = volume.array, np.array(volume.shape)
    out = resample_labels(volume, volume.index_to_world(index), method="gaussian")

    sigma = GAUSSIAN_SIGMA * np.exp(np.mean(np.log(volume.spacing))) / volume.spacing
    values = np.unique(array)
    blurred = np.stack([ndimage.map_coordinates(ndimage.gaussian_filter((array == v).astype(float), sigma,
                                                                        mode="nearest"),
                                                index.T, order=3, mode="nearest") for v in values])
    order = np.sort(blurred, axis=0)
    clear = order[-1] - order[-2] > 1e-4
    expected = values[np.argmax(blurred, axis=0)]
    low = np.floor(index).astype(int)
    for r in range(len(index)):
        corners = {int(array[tuple(np.clip(low[r] + np.array(c), 0, size - 1))]) for c in product((0, 1), repeat=3)}
        if len(corners) == 1:
            expected[r], clear[r] = corners.pop(), True
        elif np.all(np.abs(index[r] - np.round(index[r])) < 1e-6):
            expected[r], clear[r] = array[tuple(np.round(index[r]).astype(int))], True
    inside = np.all((index >= -0.5) & (index <= size - 0.5), axis=1)
    expected[~inside], clear[~inside] = 0, True
    assert np.array_equal(out[clear], expected[clear])


@pytest.mark.parametrize("shape", [(7, 5), (6, 5, 4)])
def test_single_valued_stencils_are_those_whose_corners_agree(shape):
    """A point's linear stencil (its 2^D voxels, clamped at the image's edges) holds one value
    exactly when every corner does; those points get it, the others are returned in order."""
    from itertools import product

    from volreg.warp.resample import _mixed_stencils

    rng = np.random.default_rng(len(shape))
    array = rng.integers(0, 2, shape).astype(np.int16) * rng.integers(1, 3, shape).astype(np.int16)
    array[: shape[0] // 2] = 1  # a block of one value: single-valued stencils
    index = rng.uniform(-0.5, np.array(shape) - 0.5, (4000, len(shape)))
    rows = np.arange(0, 4000, 2)
    out = np.zeros(4000, np.int16)
    mixed = _mixed_stencils(array, index, rows, out, chunk=700)
    expected_mixed = []
    for r in rows:
        low = np.floor(index[r]).astype(int)
        corners = {int(array[tuple(np.clip(low + np.array(c), 0, np.array(shape) - 1))])
                   for c in product((0, 1), repeat=len(shape))}
        if len(corners) > 1:
            expected_mixed.append(r)
        else:
            assert out[r] == corners.pop()
    assert np.array_equal(mixed, expected_mixed) and 0 < len(mixed) < len(rows)
    assert not out[1::2].any()


@FAST
@given(smooth_warps())
def test_composition_with_the_inverse_is_near_identity(warp):
    """tau(tau^-1(y)) = y and tau^-1(tau(x)) = x to 1e-5 mm wherever tau does not fold."""
    pts = np.random.default_rng(0).uniform(-40, 40, (500, 3))
    assert np.linalg.det(warp.jacobian(pts)).min() > 0
    sol = invert_points(warp, pts)
    assert sol.converged.all()
    assert np.abs(warp(sol.points) - pts).max() <= 1e-5
    assert np.abs(invert_points(warp, warp(pts)).points - pts).max() <= 1e-5


def test_a_label_filling_the_whole_volume_is_kept():
    """A label with no boundary in the array (every voxel the label) survives label resampling.

    Its signed distance is -inf everywhere; linear interpolation of infinities gives NaN, which
    used to make every voxel background.
    """
    for array in (np.full((5, 6, 7), 7, np.uint8), np.pad(np.full((5, 6, 7), 3, np.int16), 1)[1:, 1:, 1:]):
        volume = LabelVolume(array, (0, 0, 0), (1.0, 2.0, 0.5), np.eye(3))
        for shift in (0.0, 0.1):  # on the voxel centres and between them
            assert np.array_equal(resample_labels(volume, volume.grid_points() + shift), array)


@FAST
@given(st.sampled_from(["bool", "uint8", "int16", "uint32", "int64"]), st.integers(0, 2**31 - 1))
def test_label_boxes_are_the_tight_boxes_of_every_label(dtype, seed):
    """``LabelVolume.label_boxes``: for every non-zero label, the tightest index box holding it
    (also negative values and values of 2^30, which take the per-label path)."""
    rng = np.random.default_rng(seed)
    values = {"bool": [True], "uint8": [3, 255], "int16": [-7, 2, 30000], "uint32": [5, 2**30],
              "int64": [-(2**40), 1, 2**40]}[dtype]
    arr = np.zeros((6, 5, 4), dtype=dtype)
    for v in values:
        arr[tuple(rng.integers(0, n, 2) for n in arr.shape)] = v
    vol = LabelVolume(arr, (0, 0, 0), (1, 1, 1), np.eye(3))
    boxes = vol.label_boxes()
    assert sorted(boxes) == [int(v) for v in vol.labels()]
    for v, box in boxes.items():
        where = np.argwhere(arr == v)
        assert box == tuple(slice(int(a), int(b) + 1) for a, b in zip(where.min(0), where.max(0)))


def test_many_labels_shifted_by_one_voxel_move_by_one_voxel():
    """Forty block labels sampled one voxel further along each axis in turn: the label map moves by
    exactly one voxel (the many-label path of label resampling)."""
    blocks = np.arange(40, dtype=np.int16).reshape(2, 4, 5) + 1
    array = np.kron(blocks, np.ones((6, 5, 4), dtype=np.int16))  # 12 x 20 x 20 voxels
    volume = LabelVolume(array, (0, 0, 0), (1.0, 0.8, 1.5), np.eye(3))
    for axis in range(3):
        shift = np.zeros(3)
        shift[axis] = volume.spacing[axis]
        out = resample_labels(volume, volume.grid_points() + shift)
        inner = [slice(None)] * 3
        inner[axis] = slice(0, -1)
        assert np.array_equal(out[tuple(inner)], np.roll(array, -1, axis=axis)[tuple(inner)])


def test_label_scores_within_label_boxes_equal_the_whole_arrays():
    """Per-label Dice and surface distances computed within each label's boxes equal those of
    the whole arrays: for labels in both, in one only, in neither, and the background."""
    from volreg.evaluation.metrics import dice, label_scores, surface_distances

    rng = np.random.default_rng(5)
    reference = np.zeros((30, 24, 20), dtype=np.int32)
    other = np.zeros_like(reference)
    for value in range(1, 9):
        lo = rng.integers(0, 16, 3)
        reference[lo[0]:lo[0] + 10, lo[1]:lo[1] + 6, lo[2]:lo[2] + 5] = value
        lo = np.minimum(lo + rng.integers(-2, 3, 3), [20, 18, 15]).clip(0)
        if value != 8:  # label 8 only in the reference
            other[lo[0]:lo[0] + 10, lo[1]:lo[1] + 6, lo[2]:lo[2] + 5] = value
    other[0:3, 0:3, 0:3] = 9  # label 9 only in the other
    spacing = np.array([0.8, 1.0, 1.5])
    labels = [0, *range(1, 11)]  # 10 is in neither
    scores = label_scores(reference, other, labels, spacing)
    for v in labels:
        a, b = reference == v, other == v
        mean, hd95 = surface_distances(a, b, spacing)
        assert scores[v]["dice"] == dice(a, b)
        np.testing.assert_array_equal([scores[v]["mean_surface_distance_mm"], scores[v]["hd95_mm"]], [mean, hd95])


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.8, 1.5, 2.5)])
def test_boundary_distances_by_trees_equal_those_by_distance_transforms(spacing):
    from volreg.evaluation.metrics import _boundary, _boundary_distances

    rng = np.random.default_rng(3)
    a = np.zeros((40, 36, 30), dtype=bool)
    b = np.zeros_like(a)
    a[5:25, 6:30, 4:20] = True
    b[8:30, 4:26, 9:27] = True
    b &= rng.random(b.shape) > 0.05  # ragged, with holes
    c = a.copy()  # a's shape with a dent: most of its boundary is a's
    c[10:16, 12:20, 4:8] = False
    spacing = np.array(spacing)
    for x, y, shared in ((a, b, False), (a, c, True)):
        ba, bb = _boundary(x), _boundary(y)
        by_edt = _boundary_distances(ba, bb, spacing, tree=False)
        by_tree = _boundary_distances(ba, bb, spacing, tree=True)
        for e, t in zip(by_edt, by_tree):
            assert len(e) == len(t) > 100 and e.max() >= 2 * spacing.min()
            assert np.count_nonzero(e == 0) > (len(e) // 2 if shared else 0)
            # The same distances, the voxels on both boundaries (distance 0) grouped first by the trees
            np.testing.assert_allclose(np.sort(t), np.sort(e), rtol=1e-12, atol=1e-12)
