"""``volreg register`` / ``apply`` / ``protocols`` end to end on generated label volumes."""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk

from volreg.cli import main
from volreg.io import read_labels, write_labels
from volreg.io.fields import read_displacement
from volreg.evaluation.metrics import dice
from volreg.synthetic import GaussianBumps, deform_labels
from volreg.warp.model import KernelWarp

from shapes import rotation

from helpers import SHAPE, SPACING, TEST_PROTOCOL, blob_volume, run


@pytest.fixture(scope="module")
def known_pair(tmp_path_factory):
    """A blob pair related by a known smooth warp (max 4.5 mm = 3 voxels), registered once."""
    d = tmp_path_factory.mktemp("known")
    fixed = blob_volume()
    inside = fixed.grid_points().reshape(-1, 3)[fixed.array.ravel() > 0]
    truth = GaussianBumps.random(inside.min(0), inside.max(0), max_displacement=4.5, scale=14.0, count=5,
                                 rng=np.random.default_rng(3))
    moving = deform_labels(fixed, truth)
    write_labels(fixed, d / "fixed.nii.gz")
    write_labels(moving, d / "moving.nii.gz")
    assert run(["register", d / "fixed.nii.gz", d / "moving.nii.gz", "-o", d / "out", "--quiet"]) == 0
    return d, fixed, moving, truth


def test_outputs_written(known_pair):
    d, *_ = known_pair
    names = sorted(p.name for p in (d / "out").iterdir())
    assert names == sorted(["warp.nii.gz", "inverse_warp.nii.gz", "warped.nii.gz", "model.npz", "linear.tfm",
                            "jacobian.nii.gz", "report.json", "report.png", "warp.h5", "inverse_warp.h5"])


def test_inverse_warp_file(known_pair):
    """inverse_warp.nii.gz (moving grid, ANTs InverseWarp convention): y + v(y) = tau^-1(y) to 1e-3 of the
    smallest voxel spacing at every voxel (float32 storage aside), as the report states, and SimpleITK
    pulls the fixed labels onto the moving grid with it."""
    d, fixed, moving, _ = known_pair
    v, grid = read_displacement(d / "out" / "inverse_warp.nii.gz")
    assert grid.same_geometry(moving)
    y = moving.grid_points().reshape(-1, 3)
    tau = KernelWarp.load(d / "out" / "model.npz")
    report = json.loads((d / "out" / "report.json").read_text())
    tol = report["inverse"]["tolerance_mm"]
    assert tol == pytest.approx(1e-3 * SPACING.min())
    assert report["inverse"]["max_residual_mm"] <= tol and report["inverse"]["unconverged_voxels"] == 0
    residual = np.linalg.norm(tau(y + v.reshape(-1, 3)) - y, axis=1)
    assert residual.max() <= tol + 1e-5  # float32 rounds a displacement of 20 mm by 1e-6 mm
    field = sitk.ReadImage(str(d / "out" / "inverse_warp.nii.gz"), sitk.sitkVectorFloat64)
    res = sitk.GetArrayFromImage(sitk.Resample(sitk.ReadImage(str(d / "fixed.nii.gz")), sitk.ReadImage(str(d / "moving.nii.gz")),
                                               sitk.DisplacementFieldTransform(field), sitk.sitkNearestNeighbor, 0)).T
    for label in (1, 2):
        before = dice(fixed.array == label, moving.array == label)
        assert dice(res == label, moving.array == label) > max(0.9, before)


def test_known_deformation_recovered(known_pair):
    """Mean endpoint error inside the labels <= 1.0 mm (2/3 voxel) and under a third of the
    identity's (measured: 0.77 mm against 2.93 mm)."""
    d, fixed, moving, truth = known_pair
    u, grid = read_displacement(d / "out" / "warp.nii.gz")
    assert grid.same_geometry(fixed)
    x = fixed.grid_points()
    inside = fixed.array > 0
    err = np.linalg.norm((x + u)[inside] - truth(x[inside]), axis=1)
    err0 = np.linalg.norm(truth(x[inside]) - x[inside], axis=1)
    assert err.mean() <= 1.0, (err.mean(), err0.mean())
    assert err.mean() < err0.mean() / 3


def test_report_contents(known_pair):
    d, fixed, *_ = known_pair
    report = json.loads((d / "out" / "report.json").read_text())
    assert set(report["labels"]) == {"1", "2"}
    for v in ("1", "2"):
        assert report["labels"][v]["after"]["dice"] > report["labels"][v]["before"]["dice"]
        assert report["labels"][v]["after"]["hd95_mm"] >= 0
    assert report["jacobian"]["folded_fraction"] == 0.0
    assert report["protocol"]["name"] == "test"
    assert len(report["inputs"]["fixed"]["sha256"]) == 64
    assert {s["stage"] for s in report["stages"]} >= {"surfaces", "fit warp", "resample", "write"}
    assert all(s["peak_rss_gb"] > 0 for s in report["stages"])


def test_gaussian_label_interpolation_agrees_with_itks(known_pair, tmp_path):
    """`apply --interpolation gaussian` keeps the moving labels and their dtype, and agrees with
    SimpleITK's label-Gaussian interpolator through the same field (its blur: 1 mm, 0.67 voxel
    here) to Dice >= 0.97 per label, and more closely than the default (linear) label
    interpolation of warped.nii.gz does (measured 0.989 and 0.973 on the 5765- and 328-voxel
    labels, against 0.988 and 0.960)."""
    d, fixed, moving, _ = known_pair
    assert run(["apply", d / "out" / "warp.nii.gz", d / "moving.nii.gz", "--reference", d / "fixed.nii.gz",
                "-o", tmp_path / "g.nii.gz", "--interpolation", "gaussian"]) == 0
    ours = read_labels(tmp_path / "g.nii.gz")
    assert ours.same_geometry(fixed) and ours.array.dtype == moving.array.dtype
    assert set(np.unique(ours.array)) <= {0, 1, 2}
    field = sitk.ReadImage(str(d / "out" / "warp.nii.gz"), sitk.sitkVectorFloat64)
    res = sitk.GetArrayFromImage(sitk.Resample(sitk.ReadImage(str(d / "moving.nii.gz")),
                                               sitk.ReadImage(str(d / "fixed.nii.gz")),
                                               sitk.DisplacementFieldTransform(field), sitk.sitkLabelGaussian, 0)).T
    linear = read_labels(d / "out" / "warped.nii.gz").array
    for v in (1, 2):
        assert dice(ours.array == v, res == v) >= max(0.97, dice(linear == v, res == v)), v


def test_warped_labels_and_dtype(known_pair):
    d, fixed, moving, _ = known_pair
    warped = read_labels(d / "out" / "warped.nii.gz")
    assert warped.same_geometry(fixed)
    assert warped.array.dtype == moving.array.dtype
    assert set(np.unique(warped.array)) <= {0, 1, 2}


def test_simpleitk_reproduces_warped(known_pair, tmp_path):
    """sitk.DisplacementFieldTransform with warp.nii.gz gives volreg's nearest-neighbour resampling
    exactly, and agrees with the label-interpolated warped.nii.gz to Dice >= 0.97."""
    d, fixed, moving, _ = known_pair
    field = sitk.ReadImage(str(d / "out" / "warp.nii.gz"), sitk.sitkVectorFloat64)
    transform = sitk.DisplacementFieldTransform(field)
    mov = sitk.ReadImage(str(d / "moving.nii.gz"))
    ref = sitk.ReadImage(str(d / "fixed.nii.gz"))
    res = sitk.GetArrayFromImage(sitk.Resample(mov, ref, transform, sitk.sitkNearestNeighbor, 0)).T
    assert run(["apply", d / "out" / "warp.nii.gz", d / "moving.nii.gz", "--reference", d / "fixed.nii.gz",
                "-o", tmp_path / "nn.nii.gz", "--interpolation", "nearest"]) == 0
    ours = read_labels(tmp_path / "nn.nii.gz").array
    assert np.count_nonzero(ours != res) <= 2  # float32 field: ties at exactly half a voxel may differ
    warped = read_labels(d / "out" / "warped.nii.gz").array
    for v in (1, 2):
        assert dice(warped == v, res == v) >= 0.97


def test_apply_model_equals_warp_field(known_pair, tmp_path):
    d, *_ = known_pair
    for src, name in ((d / "out" / "model.npz", "a.nii.gz"), (d / "out" / "warp.nii.gz", "b.nii.gz")):
        assert run(["apply", src, d / "moving.nii.gz", "--reference", d / "fixed.nii.gz", "-o", tmp_path / name,
                    "--quiet"]) == 0
    a = read_labels(tmp_path / "a.nii.gz").array
    b = read_labels(tmp_path / "b.nii.gz").array
    warped = read_labels(d / "out" / "warped.nii.gz").array
    assert np.array_equal(a, warped)
    assert np.count_nonzero(a != b) <= 0.001 * a.size  # the field is stored as float32


def test_apply_linear_intensity(known_pair, tmp_path):
    d, fixed, moving, _ = known_pair
    image = tmp_path / "intensity.nii.gz"
    sitk_img = sitk.GetImageFromArray((moving.array.T * 100.0).astype(np.float32).copy())
    sitk_img.SetSpacing(tuple(moving.spacing))
    sitk_img.SetOrigin(tuple(moving.origin))
    sitk.WriteImage(sitk_img, str(image))
    assert run(["apply", d / "out" / "model.npz", image, "--reference", d / "fixed.nii.gz", "-o",
                tmp_path / "lin.nii.gz", "--interpolation", "linear"]) == 0
    out = nib.load(tmp_path / "lin.nii.gz").get_fdata()
    assert out.shape == fixed.shape
    assert 0 <= out.min() and out.max() <= 200.0 + 1e-3


def test_apply_nearest_to_an_intensity_image(known_pair, tmp_path):
    """`--interpolation nearest` on an intensity image (fractions, NaN): every output voxel holds
    one of the input's values (NaN where the nearest voxel is NaN, 0 outside the image), written as
    float32, and follows the labels' own resampling."""
    d, fixed, moving, _ = known_pair
    values = moving.array.T * 0.37 + 0.5
    values[0, 0, 0] = np.nan
    sitk_img = sitk.GetImageFromArray(values.astype(np.float32).copy())
    sitk_img.SetSpacing(tuple(moving.spacing))
    sitk_img.SetOrigin(tuple(moving.origin))
    sitk.WriteImage(sitk_img, str(tmp_path / "intensity.nii.gz"))
    assert run(["apply", d / "out" / "model.npz", tmp_path / "intensity.nii.gz", "--reference", d / "fixed.nii.gz",
                "-o", tmp_path / "nn.nii.gz", "--interpolation", "nearest"]) == 0
    img = nib.load(tmp_path / "nn.nii.gz")
    out = np.asarray(img.dataobj)
    assert out.dtype == np.float32 and out.shape == fixed.shape
    allowed = np.append(np.unique(values[np.isfinite(values)].astype(np.float32)), 0.0)  # 0 outside the image
    assert np.all(np.isin(out[np.isfinite(out)], allowed))
    labels = read_labels(d / "out" / "warped.nii.gz").array  # the same map, by nearest neighbour here
    inside = np.isfinite(out) & (out != 0)
    assert inside.mean() > 0.5
    assert np.mean(np.isclose(out[inside], labels[inside] * np.float32(0.37) + np.float32(0.5))) > 0.97

def test_identity_registration(tmp_path, capsys):
    """Registering a volume to itself: labels bit-identical, |u| <= 0.01 voxel."""
    vol = blob_volume()
    write_labels(vol, tmp_path / "a.nii.gz")
    assert run(["register", tmp_path / "a.nii.gz", tmp_path / "a.nii.gz", "-o", tmp_path / "out", "--quiet", "-v"]) == 0
    assert "level 0: width" in capsys.readouterr().err  # -v logs each warp level
    warped = read_labels(tmp_path / "out" / "warped.nii.gz")
    assert np.array_equal(warped.array, vol.array)
    u, _ = read_displacement(tmp_path / "out" / "warp.nii.gz")
    assert np.abs(u).max() <= 0.01 * SPACING.min()
    assert np.allclose(nib.load(tmp_path / "out" / "jacobian.nii.gz").get_fdata(), 1.0)


def test_mean_dice_is_over_the_labels_both_volumes_hold(tmp_path, capsys):
    """A one-voxel label that only the moving volume holds has Dice 0 whatever the warp: it is
    scored on its own but left out of the mean Dice, and the summary line says so."""
    vol = blob_volume()
    speck = vol.array.copy()
    speck[1, 1, 1] = 7
    write_labels(vol, tmp_path / "a.nii.gz")
    write_labels(vol.with_array(speck), tmp_path / "b.nii.gz")
    assert run(["register", tmp_path / "a.nii.gz", tmp_path / "b.nii.gz", "-o", tmp_path / "out"]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["labels"]["7"]["after"]["dice"] == 0.0 and report["mean_dice"]["labels"] == [1, 2]
    for when in ("before", "after"):
        both = np.mean([report["labels"][v][when]["dice"] for v in ("1", "2")])
        assert report["mean_dice"][when] == pytest.approx(both) and report["mean_dice"][when] > 0.95
    assert "over 2 labels in both volumes (1 in one only)" in capsys.readouterr().out


def test_interior_label_carried(tmp_path):
    """Only the outer blob drives the warp; the inner sphere, moved 3 voxels with it, is carried (Dice >= 0.9)."""
    fixed = blob_volume()
    shift = GaussianBumps(np.array([[0.0, 0.0, 0.0]]), np.array([[4.5, 0.0, 0.0]]), 60.0)  # ~3 voxels near the centre
    moving = deform_labels(fixed, shift)
    write_labels(fixed, tmp_path / "f.nii.gz")
    write_labels(moving, tmp_path / "m.nii.gz")
    assert run(["register", tmp_path / "f.nii.gz", tmp_path / "m.nii.gz", "-o", tmp_path / "out",
                "--drive-labels", "1", "--quiet"]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["drive_labels"] == report["distance_map_labels"] == [1]  # the chosen labels' maps only
    assert report["implicit_surface_labels"] == []  # none by default
    warped = read_labels(tmp_path / "out" / "warped.nii.gz").array
    assert dice(moving.array == 2, fixed.array == 2) < 0.8  # it did move
    assert dice(warped == 2, fixed.array == 2) >= 0.9


@pytest.mark.parametrize("frame", ["LPS", "RAS", "LAS", "oblique"])
def test_orientations_agree(frame, tmp_path):
    """The same objects on grids of different orientation give the same warp in world space."""
    directions = {"LPS": np.eye(3), "RAS": np.diag([-1.0, -1.0, 1.0]), "LAS": np.diag([-1.0, 1.0, 1.0]),
                  "oblique": rotation(20.0)}
    direction = directions[frame]
    centre = np.zeros(3)
    origin = centre - direction @ ((np.array(SHAPE) - 1) / 2.0 * SPACING)
    fixed = blob_volume(direction, origin)
    shift = GaussianBumps(np.array([[0.0, 0.0, 0.0]]), np.array([[3.0, -1.5, 1.0]]), 40.0)
    moving = deform_labels(fixed, shift)
    write_labels(fixed, tmp_path / "f.nii.gz")
    write_labels(moving, tmp_path / "m.nii.gz")
    assert run(["register", tmp_path / "f.nii.gz", tmp_path / "m.nii.gz", "-o", tmp_path / "out", "--quiet"]) == 0
    warp = KernelWarp.load(tmp_path / "out" / "model.npz")
    probe = np.array([[0.0, 0.0, 0.0], [10.0, 5.0, -4.0], [-12.0, 3.0, 6.0]])
    # Within one voxel of the known warp at world points inside the objects, whatever the grid's
    # orientation (a rotated grid voxelises the same objects differently, by up to a voxel;
    # a flipped axis would put the error at twice the displacement, 2-8 mm).
    assert np.abs(warp(probe) - shift(probe)).max() <= SPACING[0]


def test_protocols_listed(capsys):
    assert main(["protocols"]) == 0
    out = capsys.readouterr().out
    names = [line.split()[0] for line in out.splitlines()]
    assert {"default", "fast", "accurate"} <= set(names)


# ------------------------------------------------------------------------- bad input


@pytest.fixture()
def pair_files(tmp_path):
    vol = blob_volume()
    write_labels(vol, tmp_path / "f.nii.gz")
    write_labels(vol, tmp_path / "m.nii.gz")
    return tmp_path


def _fails(args, capsys, match: str) -> str:
    assert run(args) == 2
    err = capsys.readouterr().err.strip()
    last = err.splitlines()[-1]
    # one error line (argparse puts its usage before it)
    assert last.startswith("volreg register: error:") and match in last, err
    assert all(line.startswith(("usage:", " ")) for line in err.splitlines()[:-1]), err
    return last


def test_bad_grids_do_not_overlap(pair_files, capsys):
    far = blob_volume(origin=(1000.0, 0.0, 0.0))
    write_labels(far, pair_files / "far.nii.gz")
    _fails(["register", pair_files / "f.nii.gz", pair_files / "far.nii.gz", "-o", pair_files / "out", "--linear", "none"],
           capsys, "and the protocol has no linear stage")
    assert not (pair_files / "out").exists()


def test_bad_no_common_label(pair_files, capsys):
    vol = blob_volume()
    write_labels(vol.with_array(vol.array * 5), pair_files / "other.nii.gz")
    _fails(["register", pair_files / "f.nii.gz", pair_files / "other.nii.gz", "-o", pair_files / "out"], capsys,
           "no label in common")
    assert not (pair_files / "out").exists()


def test_bad_empty_drive_labels(pair_files, capsys):
    _fails(["register", pair_files / "f.nii.gz", pair_files / "m.nii.gz", "-o", pair_files / "out",
            "--drive-labels", ""], capsys, "--drive-labels")
    assert not (pair_files / "out").exists()


def test_bad_drive_label_absent(pair_files, capsys):
    _fails(["register", pair_files / "f.nii.gz", pair_files / "m.nii.gz", "-o", pair_files / "out",
            "--drive-labels", "7"], capsys, "Drive label 7")
    assert not (pair_files / "out").exists()


def test_bad_landmark_lengths(pair_files, capsys):
    (pair_files / "a.csv").write_text("x,y,z\n0,0,0\n1,1,1\n")
    (pair_files / "b.csv").write_text("x,y,z\n0,0,0\n")
    _fails(["register", pair_files / "f.nii.gz", pair_files / "m.nii.gz", "-o", pair_files / "out",
            "--landmarks", pair_files / "a.csv", pair_files / "b.csv"], capsys, "same number")
    assert not (pair_files / "out").exists()


def test_bad_protocol_typo(pair_files, capsys):
    (pair_files / "p.toml").write_text("[warp]\nlamda_loc = 3.0\n")
    _fails(["register", pair_files / "f.nii.gz", pair_files / "m.nii.gz", "-o", pair_files / "out",
            "--protocol", pair_files / "p.toml"], capsys, "lamda_loc")
    _fails(["register", pair_files / "f.nii.gz", pair_files / "m.nii.gz", "-o", pair_files / "out",
            "--protocol", "fastest"], capsys, "fastest")
    assert not (pair_files / "out").exists()


def test_bad_existing_outdir(pair_files, capsys):
    out = pair_files / "out"
    out.mkdir()
    (out / "warp.nii.gz").write_bytes(b"keep")
    _fails(["register", pair_files / "f.nii.gz", pair_files / "m.nii.gz", "-o", out], capsys, "--force")
    assert sorted(p.name for p in out.iterdir()) == ["warp.nii.gz"]
    assert (out / "warp.nii.gz").read_bytes() == b"keep"


def test_demo_command(tmp_path, monkeypatch, capsys):
    """`volreg demo` on a small stand-in pair (the frog takes a minute): all outputs, the inputs
    it made, and the endpoint error against the known warp, below the identity's."""
    import volreg.demo

    fixed = blob_volume()
    inside = fixed.grid_points()[fixed.array > 0]
    truth = GaussianBumps.random(inside.min(0), inside.max(0), max_displacement=4.5, scale=14.0, count=5,
                                 rng=np.random.default_rng(3))
    monkeypatch.setattr(volreg.demo, "frog_pair", lambda full, **kw: (fixed, deform_labels(fixed, truth), truth))
    (tmp_path / "p.toml").write_text(TEST_PROTOCOL)
    assert main(["demo", "-o", str(tmp_path / "demo"), "--quiet", "--protocol", str(tmp_path / "p.toml")]) == 0
    assert "endpoint error mean" in capsys.readouterr().out
    names = {p.name for p in (tmp_path / "demo").iterdir()}
    assert names == {"fixed.nii.gz", "moving.nii.gz", "warp.nii.gz", "inverse_warp.nii.gz", "warped.nii.gz",
                     "model.npz", "linear.tfm", "jacobian.nii.gz", "report.json", "report.png", "warp.h5",
                     "inverse_warp.h5"}
    report = json.loads((tmp_path / "demo" / "report.json").read_text())
    assert report["endpoint_error_mm"]["mean"] < report["endpoint_error_mm"]["identity_mean"] / 3
