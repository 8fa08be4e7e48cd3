"""The demo's inputs: block-mode downsampling and the known smooth warp (``volreg.demo``, ``volreg.synthetic``)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from volreg.demo import block_mode
from volreg.grid import LabelVolume
from volreg.synthetic import GaussianBumps


def _mode_by_block(array: np.ndarray, factors) -> np.ndarray:
    """Each block's most frequent value, the smallest on a tie, one block at a time."""
    shape = tuple(n // k for n, k in zip(array.shape, factors))
    out = np.zeros(shape, array.dtype)
    for index in itertools.product(*map(range, shape)):
        block = array[tuple(slice(i * k, (i + 1) * k) for i, k in zip(index, factors))]
        values, counts = np.unique(block, return_counts=True)
        out[index] = values[np.argmax(counts)]  # unique sorts: the first maximum is the smallest value
    return out


@pytest.mark.parametrize("shape, factors, dtype", [((13, 11, 9), (3, 3, 2), np.uint8), ((12, 10, 7), (2, 1, 3), np.int16),
                                                   ((9, 14), (2, 3), np.int32), ((8, 8, 8), (1, 1, 1), np.uint8)])
def test_block_mode_is_each_blocks_most_frequent_label(shape, factors, dtype):
    rng = np.random.default_rng(7)
    array = rng.integers(0, 3, shape).astype(dtype)  # three values in small blocks: many ties
    ndim = len(shape)
    volume = LabelVolume(array, np.full(ndim, -5.0), np.linspace(0.5, 1.5, ndim), np.eye(ndim))
    down = block_mode(volume, factors)
    np.testing.assert_array_equal(down.array, _mode_by_block(array, factors))
    assert down.array.dtype == array.dtype
    np.testing.assert_allclose(down.spacing, volume.spacing * np.array(factors))
    # the origin is the centre of the first block
    np.testing.assert_allclose(down.origin, volume.index_to_world(((np.array(factors) - 1) / 2.0)[None])[0])


def test_gaussian_bumps_displacement_and_inverse():
    rng = np.random.default_rng(2)
    tau = GaussianBumps.random(np.zeros(3), np.full(3, 60.0), max_displacement=6.0, scale=15.0, count=4, rng=rng)
    x = rng.uniform(-10.0, 70.0, (500, 3))
    by_bump = sum(np.exp(-np.sum((x - c) ** 2, axis=1) / (2 * tau.scale**2))[:, None] * a
                  for c, a in zip(tau.centres, tau.amplitudes))
    np.testing.assert_allclose(tau.displacement(x), by_bump, rtol=0, atol=1e-12)
    assert np.abs(by_bump).max() > 1.0  # it moves points by millimetres
    np.testing.assert_allclose(tau.inverse(tau(x)), x, rtol=0, atol=1e-8)
