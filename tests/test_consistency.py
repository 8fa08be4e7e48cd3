"""``volreg consistency`` and the functions of volreg.evaluation.consistency."""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest

from volreg import LabelVolume
from volreg.evaluation.consistency import error_on_grid, error_summary, padded_region, round_trip_error, round_trip_labels
from volreg.warp.inverse import InverseWarp
from volreg.io import write_labels
from volreg.io.fields import write_displacement
from volreg.synthetic import GaussianBumps, deform_labels
from volreg.warp.model import KernelWarp, WarpLevel

from test_inverse import smooth_warp
from helpers import TEST_PROTOCOL, blob_volume, run

OUTPUTS = {"consistency.json", "consistency_error.nii.gz", "consistency.png", "forward", "backward"}


@pytest.fixture(scope="module")
def both_ways(tmp_path_factory):
    """The blob pair of test_register (known warp, max 4.5 mm = 3 voxels) through `volreg consistency`."""
    d = tmp_path_factory.mktemp("consistency")
    a = blob_volume()
    inside = a.grid_points().reshape(-1, 3)[a.array.ravel() > 0]
    truth = GaussianBumps.random(inside.min(0), inside.max(0), max_displacement=4.5, scale=14.0, count=5,
                                 rng=np.random.default_rng(3))
    b = deform_labels(a, truth)
    write_labels(a, d / "a.nii.gz")
    write_labels(b, d / "b.nii.gz")
    (d / "p.toml").write_text(TEST_PROTOCOL)
    assert run(["consistency", d / "a.nii.gz", d / "b.nii.gz", "-o", d / "out", "--protocol", d / "p.toml", "--quiet"]) == 0
    return d, a, b, truth


def test_outputs_and_error_below_half_a_voxel(both_ways):
    d, a, _, truth = both_ways
    assert {p.name for p in (d / "out").iterdir()} == OUTPUTS
    report = json.loads((d / "out" / "consistency.json").read_text())
    region = report["region"]
    assert region["count"] > (a.array > 0).sum()  # the padded neighbourhood is larger than the labels
    assert region["mean_voxels"] <= 0.5  # under half a voxel (this pair gives about 0.16)
    assert region["mean_voxels"] == pytest.approx(region["mean_mm"] / 1.5)
    assert report["surface_vertices"]["count"] > 1000 and report["surface_vertices"]["mean_voxels"] <= 0.5
    assert set(report["labels"]) == {"1", "2"} and report["mean_round_trip_dice"] >= 0.97
    # consistent *and* useful: the forward warp recovers much of the known deformation (identity is consistent too)
    forward = KernelWarp.load(d / "out" / "forward" / "model.npz")
    x = a.grid_points().reshape(-1, 3)[a.array.ravel() > 0]
    assert np.linalg.norm(forward(x) - truth(x), axis=1).mean() < 0.5 * np.linalg.norm(truth(x) - x, axis=1).mean()
    error = nib.load(d / "out" / "consistency_error.nii.gz").get_fdata()
    assert error.shape == a.shape and error.min() >= 0
    assert region["max_mm"] - 1e-4 <= error.max()  # the map covers the region (float32) and beyond


def test_saved_results_give_the_same_report(both_ways, tmp_path):
    d, *_ = both_ways
    assert run(["consistency", d / "a.nii.gz", d / "b.nii.gz", "-o", tmp_path / "again", "--quiet",
                "--forward", d / "out" / "forward", "--backward", d / "out" / "backward"]) == 0
    first = json.loads((d / "out" / "consistency.json").read_text())
    second = json.loads((tmp_path / "again" / "consistency.json").read_text())
    for key in ("region", "surface_vertices", "labels", "mean_round_trip_dice", "pad_mm"):
        assert first[key] == second[key]
    assert np.array_equal(nib.load(d / "out" / "consistency_error.nii.gz").get_fdata(),
                          nib.load(tmp_path / "again" / "consistency_error.nii.gz").get_fdata())
    assert {p.name for p in (tmp_path / "again").iterdir()} == OUTPUTS - {"forward", "backward"}


def _fake_result(path, warp: KernelWarp, grid: LabelVolume) -> None:
    path.mkdir()
    warp.save(path / "model.npz")
    write_displacement(np.zeros((*grid.shape, 3)), grid, path / "warp.nii.gz")


def test_bad_inputs(both_ways, tmp_path, capsys):
    d, a, _, _ = both_ways
    args = ["consistency", d / "a.nii.gz", d / "b.nii.gz", "--quiet"]

    def refused(extra, *words):
        out = tmp_path / "out"
        assert run(args + ["-o", out] + extra) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and err.startswith("volreg consistency: error:")
        for w in words:
            assert w in err
        assert not out.exists()

    refused(["--forward", d / "out" / "forward"], "--forward", "without --backward")
    refused(["--backward", d / "out" / "backward"], "--backward", "without --forward")
    refused(["--forward", d / "out" / "forward", "--backward", d / "out" / "backward", "--protocol", "fast"], "--protocol")
    refused(["--forward", tmp_path, "--backward", d / "out" / "backward"], "model.npz")
    other = LabelVolume(np.zeros((30, 30, 30), np.uint8), (-30.0, -30.0, -30.0), (2.0, 2.0, 2.0), np.eye(3))
    _fake_result(tmp_path / "wrong-grid", KernelWarp.identity(3), other)
    refused(["--forward", tmp_path / "wrong-grid", "--backward", d / "out" / "backward"], "--forward", "not on the grid of A")
    refused(["--forward", d / "out" / "forward", "--backward", tmp_path / "wrong-grid"], "--backward", "not on the grid of B")
    # an existing, non-empty OUTDIR is left alone without --force
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("keep")
    assert run(args + ["-o", tmp_path / "full", "--forward", d / "out" / "forward", "--backward", d / "out" / "backward"]) == 2
    assert "--force" in capsys.readouterr().err
    assert [p.name for p in (tmp_path / "full").iterdir()] == ["keep.txt"]


def test_identity_results_are_exactly_consistent(tmp_path):
    a = blob_volume()
    write_labels(a, tmp_path / "a.nii.gz")
    for name in ("f", "b"):
        _fake_result(tmp_path / name, KernelWarp.identity(3), a)
    assert run(["consistency", tmp_path / "a.nii.gz", tmp_path / "a.nii.gz", "-o", tmp_path / "out", "--quiet",
                "--forward", tmp_path / "f", "--backward", tmp_path / "b"]) == 0
    report = json.loads((tmp_path / "out" / "consistency.json").read_text())
    assert report["region"]["max_mm"] == 0.0 and report["mean_round_trip_dice"] == 1.0


# ------------------------------------------------------------------------------- functions


def test_padded_region_counts_voxels_within_pad():
    arr = np.zeros((11, 11, 11), np.uint8)
    arr[5, 5, 5] = 3
    vol = LabelVolume(arr, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(3))
    # lattice points within distance 2 of the origin: 1 + 6 + 12 + 8 + 6 = 33
    assert padded_region(vol, 2.0).sum() == 33
    assert padded_region(vol, 0.0).sum() == 1
    assert not padded_region(vol.with_array(np.zeros_like(arr)), 5.0).any()
    with pytest.raises(ValueError, match="pad"):
        padded_region(vol, -1.0)


def test_error_summary():
    s = error_summary(np.array([0.0, 1.0, 2.0, 3.0, 4.0]), voxel=2.0)
    assert (s["count"], s["mean_mm"], s["median_mm"], s["max_mm"], s["mean_voxels"]) == (5, 2.0, 2.0, 4.0, 1.0)
    assert s["p95_mm"] == pytest.approx(3.8)
    assert error_summary(np.array([]))["mean_mm"] is None


def test_warp_and_its_inverse_are_consistent_on_a_grid():
    warp = smooth_warp(3, seed=7)
    grid = LabelVolume(np.zeros((25, 25, 25), np.uint8), (0.0, 0.0, 0.0), (4.0, 4.0, 4.0), np.eye(3))
    inv = InverseWarp(warp)
    error = error_on_grid(warp, inv, grid, chunk=5000)  # several chunks
    assert error.max() <= 1e-5
    # a warp composed with itself is not consistent: the error map equals brute force at every voxel
    pts = grid.grid_points().reshape(-1, 3)
    brute = round_trip_error(warp, warp, pts).reshape(grid.shape)
    assert np.allclose(error_on_grid(warp, warp, grid, chunk=5000), brute) and brute.max() > 1.0


def test_round_trip_labels_through_exact_inverse():
    """A's labels through a warp (up to 3 mm) and its exact inverse come back up to boundary voxels."""
    a = blob_volume()
    warp = KernelWarp([WarpLevel(np.zeros((1, 3)), np.array([[0.75, 0.0, 0.0]]), width=60.0)], dim=3)
    on_b, back = round_trip_labels(a, a, warp, InverseWarp(warp))
    assert set(np.unique(back)) <= {0, 1, 2} and not np.array_equal(on_b, a.array)
    assert (back != a.array).mean() < 0.002


def test_symmetric_option_lowers_the_error(both_ways, tmp_path):
    """lambda_consistency > 0 pulls the backward fit towards the forward warp's inverse: the error at
    least halves (measured 0.155 -> 0.038 voxel mean at 1000) and the backward Dice does not drop."""
    d, *_ = both_ways
    (tmp_path / "sym.toml").write_text(TEST_PROTOCOL + "lambda_consistency = 1000.0\n")
    assert run(["consistency", d / "a.nii.gz", d / "b.nii.gz", "-o", tmp_path / "sym", "--protocol",
                tmp_path / "sym.toml", "--quiet"]) == 0
    plain = json.loads((d / "out" / "consistency.json").read_text())
    sym = json.loads((tmp_path / "sym" / "consistency.json").read_text())
    assert (plain["lambda_consistency"], sym["lambda_consistency"]) == (0.0, 1000.0)
    assert sym["region"]["mean_mm"] <= 0.5 * plain["region"]["mean_mm"]
    assert sym["region"]["p95_mm"] <= 0.5 * plain["region"]["p95_mm"]
    back_plain = plain["directions"]["backward"]["mean_dice"]["after"]
    assert sym["directions"]["backward"]["mean_dice"]["after"] >= back_plain - 0.005
    # the forward direction is registered exactly as without the option
    assert sym["directions"]["forward"]["mean_dice"] == plain["directions"]["forward"]["mean_dice"]
    # each direction carries its registration's plausibility review, as register's report.json does
    for name in ("forward", "backward"):
        review = sym["directions"][name]["review"]
        saved = json.loads((tmp_path / "sym" / name / "report.json").read_text())["review"]
        assert review == saved and review["plausible"] == (not review["findings"])
