"""The outputs of `volreg register` as nibabel, SimpleITK and ANTs (antspyx) read them.

One pair, registered once for the module: a blob on an oblique grid whose direction matrix is a
rotation times a reflection (determinant -1, as a flipped scanner axis gives), and the same blob,
moved by a smooth bump of up to about 2 mm, on another oblique, flipped grid of other spacing.
Every output must then be the same map, on the same grid, in each reader: nibabel (RAS affines),
SimpleITK and ANTs (LPS physical space).  The ANTs tests are skipped when antspyx is absent.
"""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
from shapes import grid_around, rotation

import volreg
from volreg.cli import main
from volreg.synthetic import GaussianBumps, deform_labels

from test_outputs_library import SMALL_PROTOCOL
from helpers import blob_volume

#: Oblique and flipped (determinant -1) grids of the two volumes.
FIXED_DIRECTION = rotation(25.0, (0.3, 0.5, 0.8)) @ np.diag([1.0, -1.0, 1.0])
MOVING_DIRECTION = rotation(-20.0, (0.7, -0.2, 0.4)) @ np.diag([-1.0, 1.0, 1.0])
FIXED_SHAPE, FIXED_SPACING = (24, 24, 24), np.array([2.5, 2.5, 2.5])
MOVING_SHAPE, MOVING_SPACING = (28, 28, 28), np.array([2.2, 2.2, 2.2])

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
#: NIfTI keeps origin, spacing and direction in float32: under 1e-5 mm at tens of mm.
GEOMETRY_ATOL_MM = 1e-5
#: Two readers of one field at one point: the NIfTI header's float32 geometry against the .h5's
#: float64 geometry moves a point by about 1e-7 mm (measured: 2.4e-7 mm).
SAME_FIELD_ATOL_MM = 1e-4


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    """The folder holding fixed.nii.gz, moving.nii.gz and out/ (`volreg register` of the pair)."""
    d = tmp_path_factory.mktemp("interop")
    fixed = blob_volume(direction=FIXED_DIRECTION, spacing=FIXED_SPACING, shape=FIXED_SHAPE,
                        origin=grid_around((0.0, 0.0, 0.0), FIXED_SHAPE, FIXED_SPACING, FIXED_DIRECTION))
    moving_grid = blob_volume(direction=MOVING_DIRECTION, spacing=MOVING_SPACING, shape=MOVING_SHAPE,
                              origin=grid_around((0.0, 0.0, 0.0), MOVING_SHAPE, MOVING_SPACING, MOVING_DIRECTION))
    bump = GaussianBumps(np.array([[0.0, 0.0, 0.0]]), np.array([[2.0, 1.0, 0.5]]), 30.0)
    volreg.write_labels(fixed, d / "fixed.nii.gz")
    volreg.write_labels(deform_labels(moving_grid, bump), d / "moving.nii.gz")
    (d / "p.toml").write_text(SMALL_PROTOCOL)
    assert main(["register", str(d / "fixed.nii.gz"), str(d / "moving.nii.gz"), "-o", str(d / "out"),
                 "--protocol", str(d / "p.toml"), "--quiet"]) == 0
    return d


def _map(transform: sitk.Transform, points: np.ndarray) -> np.ndarray:
    """``transform`` (SimpleITK) at each of ``points`` (N, 3), LPS mm."""
    return np.array([transform.TransformPoint(tuple(float(v) for v in p)) for p in points])


def _field(path) -> sitk.DisplacementFieldTransform:
    return sitk.DisplacementFieldTransform(sitk.ReadImage(str(path), sitk.sitkVectorFloat64))


def _lps_affine(image: sitk.Image) -> np.ndarray:
    """4x4 index -> LPS mm map of a SimpleITK image."""
    affine = np.eye(4)
    affine[:3, :3] = np.array(image.GetDirection()).reshape(3, 3) * np.array(image.GetSpacing())
    affine[:3, 3] = image.GetOrigin()
    return affine


def _random_points(volume, count: int, seed: int) -> np.ndarray:
    """``count`` points (LPS mm) at random places between the voxel centres of ``volume``."""
    index = np.random.default_rng(seed).uniform(0, np.array(volume.shape) - 1, (count, 3))
    return volume.index_to_world(index)


def _interpolation_bound(u: np.ndarray) -> float:
    """Largest error of linear interpolation of the field ``u`` (X, Y, Z, 3), mm, between voxel
    centres: sum over grid axes i of h_i^2 max|d^2 u / dx_i^2| / 8, the second derivatives taken
    as second differences of ``u``."""
    return sum(np.linalg.norm(np.diff(u, 2, axis=i), axis=-1).max() for i in range(3)) / 8


# ----------------------------------------------------------------------------- nibabel


@pytest.mark.parametrize("name, reference, shape, intent", [
    ("warp.nii.gz", "fixed.nii.gz", (*FIXED_SHAPE, 1, 3), "vector"),
    ("inverse_warp.nii.gz", "moving.nii.gz", (*MOVING_SHAPE, 1, 3), "vector"),
    ("warped.nii.gz", "fixed.nii.gz", FIXED_SHAPE, "none"),
    ("jacobian.nii.gz", "fixed.nii.gz", FIXED_SHAPE, "none"),
])
def test_nibabel_reads_each_nifti_output_on_its_grid(result, name, reference, shape, intent):
    """nibabel's (RAS) affine of every NIfTI output is SimpleITK's (LPS) geometry with x and y negated,
    and that of its reference volume: the flip (determinant < 0) and the obliquity survive."""
    img = nib.load(result / "out" / name)
    assert img.shape == shape and img.header.get_intent()[0] == intent
    assert int(img.header["qform_code"]) == int(img.header["sform_code"]) == 1
    np.testing.assert_allclose(img.header.get_qform(), img.header.get_sform(), rtol=0, atol=GEOMETRY_ATOL_MM)
    np.testing.assert_allclose(img.affine, LPS_TO_RAS @ _lps_affine(sitk.ReadImage(str(result / "out" / name))),
                               rtol=0, atol=GEOMETRY_ATOL_MM)
    np.testing.assert_allclose(img.affine, nib.load(result / reference).affine, rtol=0, atol=GEOMETRY_ATOL_MM)
    assert np.linalg.det(img.affine[:3, :3]) < 0


@pytest.mark.parametrize("name", ["warp.nii.gz", "inverse_warp.nii.gz"])
def test_nibabel_reads_the_vectors_in_lps_as_itk_does(result, name):
    """The displacement vectors are stored in LPS mm (not flipped to RAS): nibabel's array is
    SimpleITK's, axis for axis, and volreg reads back the same numbers."""
    by_nibabel = np.asarray(nib.load(result / "out" / name).dataobj)[:, :, :, 0, :]
    by_itk = sitk.GetArrayFromImage(sitk.ReadImage(str(result / "out" / name))).transpose(2, 1, 0, 3)
    np.testing.assert_array_equal(by_nibabel, by_itk)
    np.testing.assert_array_equal(volreg.read_displacement(result / "out" / name)[0], by_nibabel)


# ----------------------------------------------------------------------------- SimpleITK


def test_simpleitk_field_reproduces_warped(result):
    """SimpleITK resampling the moving labels through warp.nii.gz: with its label interpolator
    (one-hot linear, closest to volreg's per-label distance interpolation) it gives warped.nii.gz
    on >= 99.9 % of the voxels (measured: 3 of 13824 differ); nearest neighbour differs only on
    label boundaries (measured: 80 voxels, 0.6 % of this small grid)."""
    fixed, moving = (sitk.ReadImage(str(result / n)) for n in ("fixed.nii.gz", "moving.nii.gz"))
    warped = sitk.GetArrayFromImage(sitk.ReadImage(str(result / "out" / "warped.nii.gz")))
    field = _field(result / "out" / "warp.nii.gz")
    label = sitk.GetArrayFromImage(sitk.Resample(moving, fixed, field, sitk.sitkLabelLinear, 0))
    assert np.mean(label == warped) >= 0.999
    nearest = sitk.GetArrayFromImage(sitk.Resample(moving, fixed, field, sitk.sitkNearestNeighbor, 0))
    assert np.mean(nearest == warped) >= 0.99
    for k, j, i in np.argwhere(nearest != warped):  # each label it gives is one warped.nii.gz has next door
        assert nearest[k, j, i] in warped[max(k - 1, 0):k + 2, max(j - 1, 0):j + 2, max(i - 1, 0):i + 2]


def test_simpleitk_reads_linear_tfm_as_the_models_linear_part(result):
    transform = sitk.ReadTransform(str(result / "out" / "linear.tfm"))
    model = volreg.KernelWarp.load(result / "out" / "model.npz")
    x = _random_points(volreg.read_labels(result / "fixed.nii.gz"), 200, seed=1)
    np.testing.assert_allclose(_map(transform, x), model.linear(x), rtol=0, atol=1e-9)


@pytest.mark.parametrize("name, reference", [("warp", "fixed.nii.gz"), ("inverse_warp", "moving.nii.gz")])
def test_h5_is_the_nifti_field_and_the_model(result, name, reference):
    """NAME.h5 (a composite of one DisplacementFieldTransform) maps points as NAME.nii.gz does
    (<= 1e-4 mm), and as the model (tau, or its inverse) does: at the voxel centres to float32
    precision, between them within the error bound of linear interpolation of the field."""
    volume = volreg.read_labels(result / reference)
    composite = sitk.ReadTransform(str(result / "out" / f"{name}.h5"))
    assert composite.GetName() == "CompositeTransform" and composite.GetNumberOfTransforms() == 1
    assert composite.GetNthTransform(0).GetName() == "DisplacementFieldTransform"
    field = _field(result / "out" / f"{name}.nii.gz")
    model = volreg.KernelWarp.load(result / "out" / "model.npz")
    exact = model if name == "warp" else volreg.InverseWarp(model)
    centres = volume.grid_points()[volume.array > 0]
    between = _random_points(volume, 500, seed=2)
    for x in (centres, between):
        np.testing.assert_allclose(_map(composite, x), _map(field, x), rtol=0, atol=SAME_FIELD_ATOL_MM)
    # float32 storage of displacements of a few mm: < 1e-6 mm.  The model's inverse is solved to
    # 1e-6 mm, the grid's to the report's tolerance (1e-3 voxel) in |tau(x) - y|, which moves the
    # preimage by at most that times the largest singular value of J^-1.
    if name == "warp":
        bound = 1e-5
    else:
        tol = json.loads((result / "out" / "report.json").read_text())["inverse"]["tolerance_mm"]
        bound = tol * np.linalg.norm(exact.evaluate(centres, order=1)[1], 2, axis=(1, 2)).max() + 1e-5
    assert np.abs(_map(composite, centres) - exact(centres)).max() < bound
    u, _ = volreg.read_displacement(result / "out" / f"{name}.nii.gz")
    error = np.linalg.norm(_map(composite, between) - exact(between), axis=1)
    assert error.max() <= _interpolation_bound(u), (error.max(), _interpolation_bound(u))  # measured 0.095 / 0.17 mm


@pytest.mark.parametrize("name, reference, source", [
    ("warp", "fixed.nii.gz", "moving.nii.gz"),
    ("inverse_warp", "moving.nii.gz", "fixed.nii.gz"),
])
def test_resampling_through_h5_equals_resampling_through_nifti(result, name, reference, source):
    """sitk.Resample of labels through NAME.h5 and through NAME.nii.gz: the same volume, voxel for voxel."""
    grid, labels = (sitk.ReadImage(str(result / n)) for n in (reference, source))
    through_h5 = sitk.Resample(labels, grid, sitk.ReadTransform(str(result / "out" / f"{name}.h5")),
                               sitk.sitkNearestNeighbor, 0)
    through_nifti = sitk.Resample(labels, grid, _field(result / "out" / f"{name}.nii.gz"), sitk.sitkNearestNeighbor, 0)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(through_h5), sitk.GetArrayFromImage(through_nifti))
    assert len(np.unique(sitk.GetArrayFromImage(through_h5))) == 3  # both labels are there


# ----------------------------------------------------------------------------- ANTs


@pytest.mark.parametrize("name", ["warp.nii.gz", "warp.h5"])
def test_ants_apply_transforms_reproduces_warped(result, name):
    """ants.apply_transforms with warp.nii.gz or warp.h5: nearest neighbour gives exactly
    SimpleITK's nearest-neighbour resampling (the same field, the same sense), and ANTs' label
    interpolator warped.nii.gz on >= 99.9 % of the voxels (measured: 3 of 13824 differ)."""
    ants = pytest.importorskip("ants")
    fixed, moving = (ants.image_read(str(result / n)) for n in ("fixed.nii.gz", "moving.nii.gz"))
    transform = [str(result / "out" / name)]
    nearest = ants.apply_transforms(fixed, moving, transformlist=transform, interpolator="nearestNeighbor").numpy()
    field = _field(result / "out" / "warp.nii.gz")
    by_itk = sitk.Resample(*(sitk.ReadImage(str(result / n)) for n in ("moving.nii.gz", "fixed.nii.gz")),
                           field, sitk.sitkNearestNeighbor, 0)
    np.testing.assert_array_equal(nearest, sitk.GetArrayFromImage(by_itk).transpose(2, 1, 0))
    label = ants.apply_transforms(fixed, moving, transformlist=transform, interpolator="genericLabel").numpy()
    warped = ants.image_read(str(result / "out" / "warped.nii.gz")).numpy()
    assert np.mean(label == warped) >= 0.999


@pytest.mark.parametrize("name", ["warp", "inverse_warp"])
@pytest.mark.parametrize("suffix", [".nii.gz", ".h5"])
def test_ants_maps_points_as_the_model(result, name, suffix):
    """ants.apply_transforms_to_points maps points in the sense opposite to images: the warp that
    brings the moving image onto the fixed grid (warp.*) takes fixed points to their moving
    partners, tau(x); inverse_warp.* takes moving points to fixed ones, tau^-1(y).  At the voxel
    centres of the labels both agree with model.npz to 0.01 mm (measured: 2e-6 mm), and between
    them with SimpleITK's reading of the same file to 1e-4 mm."""
    ants = pytest.importorskip("ants")
    import pandas as pd

    model = volreg.KernelWarp.load(result / "out" / "model.npz")
    volume = volreg.read_labels(result / ("fixed.nii.gz" if name == "warp" else "moving.nii.gz"))
    exact = model if name == "warp" else volreg.InverseWarp(model)
    path = str(result / "out" / f"{name}{suffix}")

    def by_ants(points):
        table = pd.DataFrame(points, columns=["x", "y", "z"])
        return ants.apply_transforms_to_points(3, table, [path])[["x", "y", "z"]].to_numpy()

    centres = volume.grid_points()[volume.array > 0]
    assert np.linalg.norm(by_ants(centres) - exact(centres), axis=1).max() <= 0.01
    between = _random_points(volume, 300, seed=3)
    by_itk = _map(_field(path) if suffix == ".nii.gz" else sitk.ReadTransform(path), between)
    np.testing.assert_allclose(by_ants(between), by_itk, rtol=0, atol=SAME_FIELD_ATOL_MM)


def test_ants_jacobian_matches_jacobian_nii(result):
    """ants.create_jacobian_determinant_image of warp.nii.gz (finite differences of the field) against
    jacobian.nii.gz (the model's analytic Jacobian): within 0.015 away from the grid's faces, where
    ANTs' differences are one-sided (measured on this 2.5 mm grid: largest 0.0073, mean 0.001)."""
    ants = pytest.importorskip("ants")
    fixed = ants.image_read(str(result / "fixed.nii.gz"))
    by_ants = ants.create_jacobian_determinant_image(fixed, str(result / "out" / "warp.nii.gz"), do_log=False).numpy()
    ours = ants.image_read(str(result / "out" / "jacobian.nii.gz")).numpy()
    inner = (slice(2, -2),) * 3
    difference = np.abs(by_ants - ours)[inner]
    assert difference.max() <= 0.015 and difference.mean() <= 0.002
    assert ours.min() < 0.9 and ours.max() > 1.1  # the warp does change volumes: the comparison means something


def test_a_single_sagittal_slice_gives_fields_that_apply_and_consistency_read(tmp_path):
    """A pair of single sagittal slices (40 x 40 x 1, the slice axis along world x), the moving
    one's disc 3 mm off: warp.nii.gz applied by `volreg apply` gives warped.nii.gz again, ITK
    reads it as a 3-D field, and `consistency` takes the two saved results (before, ITK read
    both fields as 2-D with a singular direction, and both commands refused them)."""
    direction = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # i -> y, j -> z, k -> x
    ii, jj = np.meshgrid(np.arange(40), np.arange(40), indexing="ij")
    for name, cy in (("a", 20.0), ("b", 23.0)):
        disc = (((ii - cy) / 9.0) ** 2 + ((jj - 20.0) / 7.0) ** 2 < 1).astype(np.uint8)
        volreg.write_labels(volreg.LabelVolume(disc[:, :, None], (0.0, -20.0, -20.0), (1.0, 1.0, 1.0), direction),
                            tmp_path / f"{name}.nii.gz")
    (tmp_path / "p.toml").write_text(SMALL_PROTOCOL)
    a, b = str(tmp_path / "a.nii.gz"), str(tmp_path / "b.nii.gz")
    for fixed, moving, out in ((a, b, "ab"), (b, a, "ba")):
        assert main(["register", fixed, moving, "-o", str(tmp_path / out), "--protocol", str(tmp_path / "p.toml"),
                     "--quiet"]) == 0
    field = sitk.ReadImage(str(tmp_path / "ab" / "warp.nii.gz"), sitk.sitkVectorFloat64)
    assert field.GetDimension() == 3
    sitk.DisplacementFieldTransform(field)
    assert main(["apply", str(tmp_path / "ab" / "warp.nii.gz"), b, "--reference", a, "-o",
                 str(tmp_path / "applied.nii.gz"), "--quiet"]) == 0
    applied = volreg.read_labels(tmp_path / "applied.nii.gz").array
    assert np.array_equal(applied, volreg.read_labels(tmp_path / "ab" / "warped.nii.gz").array)
    assert main(["consistency", a, b, "--forward", str(tmp_path / "ab"), "--backward", str(tmp_path / "ba"), "-o",
                 str(tmp_path / "c"), "--quiet"]) == 0
