"""Tests for volreg.io: label/scalar images, meshes, atomic output."""

from __future__ import annotations

import gzip
import json
import os
import re
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import pyvista as pv
import SimpleITK as sitk

from volreg import LabelVolume
from volreg.grid import Grid
from volreg.io import (
    VolregIOError,
    atomic_output,
    check_writable,
    read_grid,
    read_image,
    read_labels,
    read_mesh,
    write_labels,
    write_mesh,
    write_scalar,
)
from volreg.io.fields import read_displacement, write_displacement, write_itk_composite
from helpers import write_nifti as _nifti

# NIfTI stores origin, spacing and the qform quaternion as float32: relative
# error ~6e-8, i.e. well under 1e-5 mm for coordinates of a few hundred mm.
GEOM_ATOL_MM = 1e-5

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def _rotation(axis, degrees: float) -> np.ndarray:
    """Rodrigues rotation matrix about ``axis`` by ``degrees``."""
    a = np.asarray(axis, dtype=float)
    a /= np.linalg.norm(a)
    t = np.deg2rad(degrees)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * (k @ k)


# (direction, spacing mm, origin mm)
ORIENTATIONS = {
    "identity": (np.eye(3), (1.0, 1.5, 2.0), (-10.0, 20.5, 3.25)),
    "flipped_xy": (np.diag([-1.0, -1.0, 1.0]), (1.0, 1.0, 1.0), (90.0, 126.0, -72.0)),
    "left_handed": (np.diag([1.0, -1.0, 1.0]), (0.5, 0.7, 1.2), (0.0, 0.0, 0.0)),
    "oblique_20deg": (_rotation((1.0, 2.0, 3.0), 20.0), (0.8, 0.8, 2.0), (-101.3, 12.7, 55.1)),
}
SUFFIXES = [".nii.gz", ".nii", ".nrrd", ".mha"]
DTYPES = [np.uint8, np.int16, np.uint16, np.int32]


def _volume(dtype, orientation: str, shape=(7, 6, 5), seed: int = 0) -> LabelVolume:
    rng = np.random.default_rng(seed)
    array = rng.integers(0, 5, size=shape).astype(dtype)
    info = np.iinfo(dtype)
    array.flat[0] = info.max  # extremes prove the dtype survives
    array.flat[-1] = info.min
    direction, spacing, origin = ORIENTATIONS[orientation]
    return LabelVolume(array, origin, spacing, direction)


def _assert_same(a: LabelVolume, b: LabelVolume) -> None:
    assert b.array.dtype == a.array.dtype
    assert b.shape == a.shape
    np.testing.assert_array_equal(b.array, a.array)
    np.testing.assert_allclose(b.origin, a.origin, atol=GEOM_ATOL_MM)
    np.testing.assert_allclose(b.spacing, a.spacing, atol=GEOM_ATOL_MM)
    np.testing.assert_allclose(b.direction, a.direction, atol=GEOM_ATOL_MM)


def _raises(path: Path, match: str):
    """Expect a one-line VolregIOError naming ``path`` and matching ``match``."""

    class _Ctx:
        def __enter__(self):
            self._cm = pytest.raises(VolregIOError, match=match)
            self.info = self._cm.__enter__()
            return self.info

        def __exit__(self, *exc):
            handled = self._cm.__exit__(*exc)
            msg = str(self.info.value)
            assert str(path) in msg, msg
            assert "\n" not in msg, msg
            return handled

    return _Ctx()


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("orientation", list(ORIENTATIONS))
@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: np.dtype(d).name)
@pytest.mark.parametrize("suffix", SUFFIXES)
def test_label_round_trip(tmp_path, suffix, dtype, orientation):
    vol = _volume(dtype, orientation)
    path = tmp_path / f"label_1{suffix}"
    write_labels(vol, path)
    back = read_labels(path)
    _assert_same(vol, back)
    assert back.array.flags.c_contiguous


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_label_round_trip_2d(tmp_path, suffix):
    rng = np.random.default_rng(1)
    array = rng.integers(0, 4, size=(9, 6)).astype(np.uint8)
    theta = np.deg2rad(30.0)
    direction = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    vol = LabelVolume(array, (3.5, -2.0), (0.5, 1.25), direction)
    path = tmp_path / f"slice{suffix}"
    write_labels(vol, path)
    back = read_labels(path)
    assert back.ndim == 2
    _assert_same(vol, back)


def test_bool_labels_written_as_uint8(tmp_path):
    mask = np.zeros((4, 5, 6), dtype=bool)
    mask[1:3, 2:4, 3:5] = True
    vol = LabelVolume(mask, (0, 0, 0), (1, 1, 1), np.eye(3))
    write_labels(vol, tmp_path / "mask.nrrd")
    back = read_labels(tmp_path / "mask.nrrd")
    assert back.array.dtype == np.uint8
    np.testing.assert_array_equal(back.array, mask.astype(np.uint8))


@pytest.mark.parametrize("orientation", list(ORIENTATIONS))
def test_nifti_qform_equals_sform_and_is_ras(tmp_path, orientation):
    vol = _volume(np.int16, orientation)
    path = tmp_path / "seg.nii.gz"
    write_labels(vol, path)
    img = nib.load(path)
    qform, qcode = img.get_qform(coded=True)
    sform, scode = img.get_sform(coded=True)
    assert qcode > 0 and scode > 0
    np.testing.assert_allclose(qform, sform, atol=GEOM_ATOL_MM)
    # nibabel's affine is RAS; volreg's is LPS: they differ by negating x and y.
    np.testing.assert_allclose(img.affine, LPS_TO_RAS @ vol.affine, atol=GEOM_ATOL_MM)
    # and nibabel's array is in the same (i, j, k) order as ours.
    np.testing.assert_array_equal(np.asarray(img.dataobj), vol.array)


def test_index_to_world_matches_simpleitk(tmp_path):
    vol = _volume(np.uint8, "oblique_20deg")
    path = tmp_path / "geom.nrrd"
    write_labels(vol, path)
    back = read_labels(path)
    img = sitk.ReadImage(str(path))
    indices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [6, 5, 4], [2.5, 3.25, 0.5]])
    ours = back.index_to_world(indices)
    theirs = np.array([img.TransformContinuousIndexToPhysicalPoint(tuple(map(float, ix))) for ix in indices])
    np.testing.assert_allclose(ours, theirs, atol=1e-9)
    # Voxel [i, j, k] of our array is SimpleITK's pixel at index (i, j, k).
    for ix in [(0, 0, 0), (6, 5, 4), (3, 1, 2)]:
        assert back.array[ix] == img.GetPixel(ix)


def test_nifti_world_point_against_nibabel(tmp_path):
    vol = _volume(np.uint8, "oblique_20deg")
    path = tmp_path / "geom.nii.gz"
    write_labels(vol, path)
    back = read_labels(path)
    idx = np.array([[0, 0, 0], [6, 5, 4], [1.5, 2.0, 3.5]])
    ras = nib.affines.apply_affine(nib.load(path).affine, idx)
    lps = ras * np.array([-1.0, -1.0, 1.0])
    np.testing.assert_allclose(back.index_to_world(idx), lps, atol=GEOM_ATOL_MM)


@pytest.mark.parametrize("suffix", [".nii.gz", ".mha"])
def test_scalar_round_trip(tmp_path, suffix):
    like = _volume(np.uint8, "oblique_20deg")
    values = np.random.default_rng(2).normal(size=like.shape) * 10
    path = tmp_path / f"dist{suffix}"
    write_scalar(values, like, path)
    array, origin, spacing, direction = read_image(path)
    assert array.dtype == np.float32
    np.testing.assert_array_equal(array, values.astype(np.float32))
    np.testing.assert_allclose(origin, like.origin, atol=GEOM_ATOL_MM)
    np.testing.assert_allclose(spacing, like.spacing, atol=GEOM_ATOL_MM)
    np.testing.assert_allclose(direction, like.direction, atol=GEOM_ATOL_MM)


def test_read_image_of_labels_is_float(tmp_path):
    vol = _volume(np.int16, "identity")
    write_labels(vol, tmp_path / "l.nrrd")
    array, *_ = read_image(tmp_path / "l.nrrd")
    assert array.dtype == np.float32
    np.testing.assert_array_equal(array, vol.array.astype(np.float32))


def test_write_scalar_rejects_wrong_shape(tmp_path):
    like = _volume(np.uint8, "identity")
    with pytest.raises(VolregIOError, match="Expected `array` of shape"):
        write_scalar(np.zeros((2, 2, 2)), like, tmp_path / "x.nii.gz")
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- float and 4-D inputs



def test_float_integral_labels_accepted(tmp_path):
    data = np.random.default_rng(3).choice([0.0, 3.0, 7.0, 200.0], size=(5, 4, 3)).astype(np.float32)
    vol = read_labels(_nifti(tmp_path / "f.nii.gz", data))
    assert vol.array.dtype == np.uint8
    np.testing.assert_array_equal(vol.array, data.astype(np.uint8))
    data[0, 0, 0] = -1.0
    vol = read_labels(_nifti(tmp_path / "g.nii.gz", data))
    assert vol.array.dtype == np.int16
    np.testing.assert_array_equal(vol.array, data.astype(np.int16))


def test_4d_with_single_volume_is_squeezed(tmp_path):
    data = np.random.default_rng(4).integers(0, 3, size=(5, 4, 3, 1)).astype(np.int16)
    vol = read_labels(_nifti(tmp_path / "one.nii.gz", data))
    assert vol.shape == (5, 4, 3)
    np.testing.assert_array_equal(vol.array, data[..., 0])


def test_4d_with_single_volume_nrrd_is_squeezed(tmp_path):
    data = np.random.default_rng(4).integers(0, 3, size=(5, 4, 3, 1)).astype(np.uint8)
    img = sitk.GetImageFromArray(data.T.copy(), isVector=False)
    img.SetSpacing((0.5, 0.6, 0.7, 1.0))
    path = tmp_path / "one.nrrd"
    sitk.WriteImage(img, str(path))
    vol = read_labels(path)
    assert vol.shape == (5, 4, 3)
    np.testing.assert_allclose(vol.spacing, (0.5, 0.6, 0.7))
    np.testing.assert_array_equal(vol.array, data[..., 0])


# --------------------------------------------------------------------------- bad inputs


def test_missing_file(tmp_path):
    path = tmp_path / "nope.nii.gz"
    with _raises(path, "does not exist"):
        read_labels(path)
    with _raises(path, "does not exist"):
        read_image(path)


def test_random_bytes_nii_gz(tmp_path):
    path = tmp_path / "noise.nii.gz"
    path.write_bytes(np.random.default_rng(5).bytes(4096))
    with _raises(path, "not a readable NIfTI"):
        read_labels(path)


def test_text_file_named_nii(tmp_path):
    path = tmp_path / "notes.nii"
    path.write_text("this is not an image\n" * 30)
    with _raises(path, "not a readable NIfTI"):
        read_labels(path)


@pytest.mark.parametrize("suffix", [".nrrd", ".mha"])
def test_random_bytes_other_formats(tmp_path, suffix):
    path = tmp_path / f"noise{suffix}"
    path.write_bytes(np.random.default_rng(6).bytes(4096))
    with _raises(path, "could not be read as an image"):
        read_labels(path)


def test_truncated_nii_gz(tmp_path):
    # SimpleITK itself reads such a file without complaint, zero-filling the tail.
    vol = _volume(np.int16, "identity", shape=(30, 20, 10))
    path = tmp_path / "cut.nii.gz"
    write_labels(vol, path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with _raises(path, "truncated"):
        read_labels(path)


def test_truncated_nii(tmp_path):
    vol = _volume(np.int16, "identity", shape=(30, 20, 10))
    path = tmp_path / "cut.nii"
    write_labels(vol, path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with _raises(path, "truncated"):
        read_labels(path)


def test_corrupt_gzip_crc(tmp_path):
    vol = _volume(np.uint8, "identity", shape=(30, 20, 10))
    raw = tmp_path / "ok.nii"
    write_labels(vol, raw)
    blob = bytearray(gzip.compress(raw.read_bytes()))
    blob[-6] ^= 0xFF  # flip a CRC byte
    path = tmp_path / "crc.nii.gz"
    path.write_bytes(bytes(blob))
    with _raises(path, "corrupt gzip"):
        read_labels(path)


@pytest.mark.parametrize("suffix", [".nrrd", ".mha"])
def test_truncated_other_formats(tmp_path, suffix):
    vol = _volume(np.int16, "identity", shape=(30, 20, 10))
    path = tmp_path / f"cut{suffix}"
    write_labels(vol, path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with _raises(path, "could not be read as an image"):
        read_labels(path)


def test_4d_with_three_volumes(tmp_path):
    path = _nifti(tmp_path / "four.nii.gz", np.zeros((5, 4, 3, 3), dtype=np.int16))
    with _raises(path, r"4-D with size \(5, 4, 3, 3\)"):
        read_labels(path)


def test_vector_image(tmp_path):
    img = nib.Nifti1Image(np.zeros((5, 4, 3, 1, 3), dtype=np.float32), np.eye(4))
    img.header.set_intent("vector")
    path = tmp_path / "vec.nii.gz"
    nib.save(img, path)
    with _raises(path, "3 components per voxel"):
        read_labels(path)


def test_float_with_nan(tmp_path):
    data = np.ones((5, 4, 3), dtype=np.float32)
    data[1, 2, 0] = np.nan
    data[0, 0, 0] = np.inf
    path = _nifti(tmp_path / "nan.nii.gz", data)
    with _raises(path, "1 NaN and 1 Inf"):
        read_labels(path)


def test_float_non_integral(tmp_path):
    data = np.ones((5, 4, 3), dtype=np.float64)
    data[1, 2, 0] = 2.5
    path = _nifti(tmp_path / "half.nii.gz", data)
    with _raises(path, r"non-integral values \(e\.g\. 2\.5\)"):
        read_labels(path)


def test_float_labels_a_hair_from_whole_show_the_value_that_is_not(tmp_path):
    data = np.ones((5, 4, 3), dtype=np.float32)
    data[1, 2, 0] = np.float32(1.0000001)  # "1" in a six-digit message
    path = _nifti(tmp_path / "hair.nii.gz", data)
    with _raises(path, r"non-integral values \(e\.g\. 1\.00000011920928\d*\)"):
        read_labels(path)


@pytest.mark.parametrize("unit, per_mm", [("micron", 1000.0), ("meter", 1e-3), (3 | 64, 1000.0), (1 | 56, 1e-3)],
                         ids=["micron", "meter", "micron with unknown time bits", "meter with unknown time bits"])
def test_a_nifti_in_micrometres_or_metres_reads_in_millimetres(tmp_path, unit, per_mm):
    """A header whose spatial unit is micrometres or metres, its sform and pixdim in that unit:
    ITK converts to millimetres, nibabel's affine keeps the unit, and the cross-check of the two
    refused a consistent file as "pixdim disagrees with the sform/qform".  It reads as the same
    file in millimetres does."""
    data = np.zeros((6, 5, 4), np.uint8)
    data[2:4, 1:4, 1:3] = 3
    affine = np.array([[0.0, -1.5, 0.0, 10.0], [2.0, 0.0, 0.0, -20.0], [0.0, 0.0, 2.5, 5.0], [0, 0, 0, 1]])
    mm = nib.Nifti1Image(data, affine)
    mm.header.set_xyzt_units(xyz="mm")
    nib.save(mm, tmp_path / "mm.nii.gz")
    scaled = np.diag([per_mm, per_mm, per_mm, 1.0]) @ affine
    other = nib.Nifti1Image(data, scaled)
    other.set_sform(scaled, code=1)
    other.set_qform(scaled, code=1)
    if isinstance(unit, str):
        other.header.set_xyzt_units(xyz=unit)
    else:  # time bits nibabel cannot decode; ITK reads the space bits alone
        other.header["xyzt_units"] = unit
    nib.save(other, tmp_path / "other.nii.gz")
    a, b = read_labels(tmp_path / "mm.nii.gz"), read_labels(tmp_path / "other.nii.gz")
    assert np.array_equal(a.array, b.array)
    assert np.allclose(a.spacing, b.spacing) and np.allclose(a.origin, b.origin) and np.allclose(a.direction, b.direction)
    assert np.allclose(b.spacing, [2.0, 1.5, 2.5])


def test_a_single_file_nifti_with_its_voxels_inside_the_header_is_refused(tmp_path):
    """vox_offset 0 in a .nii: nibabel reads the header's bytes as voxels and ITK starts right after
    the header; neither is the file's reading (a pair read so was registered 4 mm off)."""
    path = _nifti(tmp_path / "ok.nii", np.ones((5, 4, 3), dtype=np.uint8))
    raw = bytearray(path.read_bytes())
    raw[108:112] = np.float32(0.0).tobytes()  # vox_offset
    (tmp_path / "vo0.nii").write_bytes(bytes(raw))
    with _raises(tmp_path / "vo0.nii", "vox_offset 0, inside its 348-byte header"):
        read_labels(tmp_path / "vo0.nii")


def test_qform_sform_disagree(tmp_path):
    img = nib.Nifti1Image(np.zeros((5, 4, 3), dtype=np.uint8), None)
    qform = np.diag([2.0, 2.0, 2.0, 1.0])
    sform = qform.copy()
    sform[:3, 3] = (5.0, 0.0, 0.0)  # 5 mm shift
    img.set_qform(qform, code=1)
    img.set_sform(sform, code=2)
    path = tmp_path / "conflict.nii.gz"
    nib.save(img, path)
    with _raises(path, "qform .* and sform .* disagree by up to 5 mm"):
        read_labels(path)


@pytest.mark.parametrize("which", ["qform", "sform"])
def test_only_one_of_qform_sform(tmp_path, which):
    img = nib.Nifti1Image(np.arange(60, dtype=np.int16).reshape(5, 4, 3), None)
    ras = np.array([[0.0, 0, 2, -10], [-1.5, 0, 0, 20], [0, 1, 0, 30], [0, 0, 0, 1]])
    getattr(img, f"set_{which}")(ras, code=1)
    getattr(img, f"set_{'sform' if which == 'qform' else 'qform'}")(None, code=0)
    img.header.set_zooms((1.5, 1.0, 2.0))  # pixdim consistent with the affine
    path = tmp_path / f"{which}.nii.gz"
    nib.save(img, path)
    vol = read_labels(path)
    np.testing.assert_allclose(vol.affine, LPS_TO_RAS @ ras, atol=GEOM_ATOL_MM)


def test_sform_pixdim_mismatch(tmp_path):
    # ITK takes voxel sizes from pixdim, nibabel from the sform: refuse rather than guess.
    img = nib.Nifti1Image(np.zeros((5, 4, 3), dtype=np.int16), None)
    img.set_sform(np.diag([2.0, 3.0, 4.0, 1.0]), code=1)
    img.set_qform(None, code=0)
    img.header.set_zooms((1.0, 1.0, 1.0))
    path = tmp_path / "pixdim.nii.gz"
    nib.save(img, path)
    with _raises(path, "pixdim disagrees with the sform/qform"):
        read_labels(path)


def test_read_image_keeps_nan_in_nifti(tmp_path):
    # SimpleITK's NIfTI reader turns NaN/Inf into 0; read_image must not.
    data = np.random.default_rng(8).normal(size=(5, 4, 3)).astype(np.float32)
    data[1, 2, 0] = np.nan
    data[0, 0, 0] = -np.inf
    path = _nifti(tmp_path / "nan.nii.gz", data)
    array, *_ = read_image(path)
    assert array.dtype == np.float32
    np.testing.assert_array_equal(array, data)


def test_unsupported_suffix(tmp_path):
    path = tmp_path / "labels.png"
    path.write_bytes(b"\x89PNG")
    with _raises(path, "unsupported suffix"):
        read_labels(path)
    with _raises(tmp_path / "out.nhdr", "unsupported suffix"):
        write_labels(_volume(np.uint8, "identity"), tmp_path / "out.nhdr")


# --------------------------------------------------------------------------- grids from headers


def _assert_grid(grid: Grid, shape, origin, spacing, direction) -> None:
    assert isinstance(grid, Grid)
    assert grid.shape == tuple(shape)
    np.testing.assert_allclose(grid.origin, origin, atol=GEOM_ATOL_MM)
    np.testing.assert_allclose(grid.spacing, spacing, atol=GEOM_ATOL_MM)
    np.testing.assert_allclose(grid.direction, direction, atol=GEOM_ATOL_MM)


@pytest.mark.parametrize("orientation", list(ORIENTATIONS))
@pytest.mark.parametrize("suffix", SUFFIXES)
def test_read_grid_is_the_geometry_read_image_gives(tmp_path, suffix, orientation):
    vol = _volume(np.int16, orientation)
    path = tmp_path / f"g{suffix}"
    write_labels(vol, path)
    array, origin, spacing, direction = read_image(path)
    grid = read_grid(path)
    assert grid.shape == array.shape
    # exactly the same numbers: the same header, read by the same code
    np.testing.assert_array_equal(grid.origin, origin)
    np.testing.assert_array_equal(grid.spacing, spacing)
    np.testing.assert_array_equal(grid.direction, direction)
    assert grid.same_geometry(read_labels(path))


def test_read_grid_2d_4d_and_vti(tmp_path):
    theta = np.deg2rad(30.0)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    flat = LabelVolume(np.zeros((9, 6), np.uint8), (3.5, -2.0), (0.5, 1.25), rot)
    write_labels(flat, tmp_path / "slice.nrrd")
    _assert_grid(read_grid(tmp_path / "slice.nrrd"), (9, 6), (3.5, -2.0), (0.5, 1.25), rot)

    data = np.zeros((5, 4, 3, 1), dtype=np.uint8).T.copy()
    img = sitk.GetImageFromArray(data, isVector=False)
    img.SetSpacing((0.5, 0.6, 0.7, 1.0))
    sitk.WriteImage(img, str(tmp_path / "one.nrrd"))
    _assert_grid(read_grid(tmp_path / "one.nrrd"), (5, 4, 3), (0, 0, 0), (0.5, 0.6, 0.7), np.eye(3))

    direction, spacing, origin = ORIENTATIONS["oblique_20deg"]
    _vti(tmp_path / "lab.vti", np.zeros(60, np.uint8), dims=(5, 4, 3), spacing=spacing, origin=origin,
         direction=direction)
    _assert_grid(read_grid(tmp_path / "lab.vti"), (5, 4, 3), origin, spacing, direction)


def test_read_grid_reads_only_the_header(tmp_path):
    # The voxels are not read: a file whose data are cut short still has a grid.
    vol = _volume(np.int16, "oblique_20deg", shape=(30, 20, 10))
    path = tmp_path / "cut.nii"
    write_labels(vol, path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    _assert_grid(read_grid(path), vol.shape, vol.origin, vol.spacing, vol.direction)
    with _raises(path, "truncated"):
        read_image(path)


def test_read_grid_refuses_what_the_header_shows(tmp_path):
    missing = tmp_path / "nope.nii.gz"
    with _raises(missing, "does not exist"):
        read_grid(missing)
    four = _nifti(tmp_path / "four.nii.gz", np.zeros((5, 4, 3, 3), dtype=np.int16))
    with _raises(four, r"4-D with size \(5, 4, 3, 3\)"):
        read_grid(four)
    img = nib.Nifti1Image(np.zeros((5, 4, 3, 1, 3), dtype=np.float32), np.eye(4))
    img.header.set_intent("vector")
    nib.save(img, tmp_path / "vec.nii.gz")
    with _raises(tmp_path / "vec.nii.gz", r"3 components per voxel \(vector of 32-bit float\)"):
        read_grid(tmp_path / "vec.nii.gz")
    img = nib.Nifti1Image(np.zeros((5, 4, 3), dtype=np.int16), None)
    img.set_sform(np.diag([2.0, 3.0, 4.0, 1.0]), code=1)
    img.set_qform(None, code=0)
    img.header.set_zooms((1.0, 1.0, 1.0))
    nib.save(img, tmp_path / "pixdim.nii.gz")
    with _raises(tmp_path / "pixdim.nii.gz", "pixdim disagrees with the sform/qform"):
        read_grid(tmp_path / "pixdim.nii.gz")


def test_write_scalar_on_a_grid_equals_on_the_volume(tmp_path):
    like = _volume(np.uint8, "oblique_20deg")
    values = np.random.default_rng(5).normal(size=like.shape)
    write_scalar(values, like, tmp_path / "a.nii.gz")
    write_scalar(values, like.grid, tmp_path / "b.nii.gz")
    assert (tmp_path / "a.nii.gz").read_bytes() == (tmp_path / "b.nii.gz").read_bytes()
    with pytest.raises(VolregIOError, match="Expected `like` to be a Grid or a LabelVolume, got tuple"):
        write_scalar(values, (like.shape, like.affine), tmp_path / "c.nii.gz")


# --------------------------------------------------------------------------- readers own their arrays


def _owns_memory(array: np.ndarray) -> bool:
    """True when ``array`` and every array it is a view of are numpy arrays, the last owning its data."""
    while True:
        if not isinstance(array, np.ndarray):
            return False  # e.g. a memoryview of a SimpleITK image, or a memory map
        if array.base is None:
            return array.flags.owndata
        array = array.base


@pytest.mark.parametrize("suffix", [*SUFFIXES, ".vti"])
def test_thin_image_read_twice_owns_its_memory(tmp_path, suffix):
    # With at most one axis longer than 1, a transposed view is already contiguous:
    # the array must still be a copy, not a view into the reader's (freed) buffer.
    values = np.arange(64, dtype=np.int16) * 3 - 50
    path = tmp_path / f"thin{suffix}"
    if suffix == ".vti":
        _vti(path, values, dims=(64, 1, 1), spacing=(1, 1, 1), origin=(0, 0, 0), direction=np.eye(3))
    else:
        write_labels(LabelVolume(values.reshape(64, 1, 1), (1, 2, 0), (1, 1, 1), np.eye(3)), path)
    shape = (64, 1)  # a single z slice is read as 2-D, whatever the format
    first = read_labels(path).array
    second = read_labels(path).array
    for array in (first, second):
        assert array.shape == shape and array.flags.c_contiguous
        assert array.flags.owndata and _owns_memory(array)
        np.testing.assert_array_equal(array.ravel(), values)
    image = read_image(path)[0]
    assert _owns_memory(image)
    np.testing.assert_array_equal(image.ravel(), values.astype(np.float32))


def test_thin_float_nifti_does_not_map_the_file(tmp_path):
    # Float NIfTI voxels come from nibabel, which may memory-map an uncompressed file.
    values = np.linspace(-1.0, 1.0, 64, dtype=np.float32)
    path = _nifti(tmp_path / "thin.nii", values.reshape(64, 1, 1))
    for _ in range(2):
        array = read_image(path)[0]
        assert array.flags.owndata and _owns_memory(array)
        np.testing.assert_array_equal(array.ravel(), values)


def test_thin_displacement_field_owns_its_memory(tmp_path):
    like = LabelVolume(np.zeros((64, 1, 2), np.uint8), (1, 2, 3), (1, 1, 1), np.eye(3))
    u = np.random.default_rng(6).normal(size=(64, 1, 2, 3))
    write_displacement(u, like, tmp_path / "warp.nii.gz")
    for _ in range(2):
        back, grid = read_displacement(tmp_path / "warp.nii.gz")
        assert back.flags.owndata and back.flags.c_contiguous and _owns_memory(back)
        np.testing.assert_array_equal(back, u.astype(np.float32))
        assert isinstance(grid, Grid) and grid.same_geometry(like)


@pytest.mark.parametrize("zero_fraction", [0.0, 0.9])
def test_displacement_field_stored_uncompressed_only_where_it_does_not_compress(tmp_path, zero_fraction):
    """A field of noise (non-zero at every voxel, as with an affine part) is stored in the gzip
    stream, about its raw size; one mostly zero (beyond the warp's support) is compressed. Both
    read back exactly, through nibabel and SimpleITK."""
    shape = (64, 60, 56)  # larger than the compression samples together
    like = Grid(shape, np.zeros(3), np.ones(3), np.eye(3))
    u = np.random.default_rng(4).normal(scale=4.0, size=(*shape, 3)).astype(np.float32).astype(float)
    u[: int(zero_fraction * shape[0])] = 0.0
    write_displacement(u, like, tmp_path / "warp.nii.gz")
    write_displacement(u, like, tmp_path / "warp.nii")
    packed, plain = (tmp_path / "warp.nii.gz").read_bytes(), (tmp_path / "warp.nii").read_bytes()
    assert gzip.decompress(packed) == plain
    if zero_fraction:
        assert len(packed) < 0.3 * len(plain)
    else:
        assert len(plain) < len(packed) < 1.01 * len(plain)  # stored: the bytes and gzip's framing
    back, _ = read_displacement(tmp_path / "warp.nii.gz")
    np.testing.assert_array_equal(back, u)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "warp.nii.gz"))),
                                  sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "warp.nii"))))


@pytest.mark.parametrize("dim", [2, 3])
def test_compressed_displacement_field_is_the_plain_file_gzipped(tmp_path, dim):
    """warp.nii.gz decompresses to the bytes of warp.nii (the same header and data), and
    SimpleITK reads the same vectors from both; a run of zeros (the field beyond the warp's
    support) still compresses."""
    shape = (9, 8, 7)[:dim]
    like = LabelVolume(np.zeros(shape, np.uint8), (1.0, -2.0, 3.0)[:dim], (0.8, 1.0, 1.5)[:dim], np.eye(dim))
    u = np.random.default_rng(3).normal(size=(*shape, dim))
    u[: shape[0] // 2] = 0.0
    write_displacement(u, like, tmp_path / "warp.nii.gz")
    write_displacement(u, like, tmp_path / "warp.nii")
    packed = (tmp_path / "warp.nii.gz").read_bytes()
    plain = (tmp_path / "warp.nii").read_bytes()
    assert gzip.decompress(packed) == plain
    assert len(packed) < 0.8 * len(plain)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "warp.nii.gz"))),
                                  sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "warp.nii"))))


@pytest.mark.parametrize("dim", [2, 3])
def test_composite_h5_holds_the_nifti_field(tmp_path, dim):
    """warp.h5 (ITK composite transform) and warp.nii.gz of one field, on an oblique flipped grid:
    SimpleITK maps every point alike through both (1e-4 mm: the NIfTI header keeps the geometry in
    float32), and each voxel centre x to x + u(x) with u rounded to float32."""
    shape = (7, 6, 5)[:dim]
    flip = np.diag([1.0, -1.0, 1.0][:dim])
    direction = (_rotation((0.2, 0.4, 0.9), 25.0)[:dim, :dim] if dim == 3 else
                 np.array([[np.cos(0.4), -np.sin(0.4)], [np.sin(0.4), np.cos(0.4)]])) @ flip
    like = Grid(shape, np.array([12.0, -30.0, 7.5][:dim]), np.array([1.5, 2.0, 2.5][:dim]), direction)
    u = np.random.default_rng(11).normal(scale=3.0, size=(*shape, dim))
    write_itk_composite(u, like, tmp_path / "warp.h5")
    write_displacement(u, like, tmp_path / "warp.nii.gz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["warp.h5", "warp.nii.gz"]  # no temporary left
    composite = sitk.ReadTransform(str(tmp_path / "warp.h5"))
    assert composite.GetName() == "CompositeTransform" and composite.GetNumberOfTransforms() == 1
    assert composite.GetNthTransform(0).GetName() == "DisplacementFieldTransform"
    field = sitk.DisplacementFieldTransform(sitk.ReadImage(str(tmp_path / "warp.nii.gz"), sitk.sitkVectorFloat64))
    centres = like.grid_points().reshape(-1, dim)
    inside = like.index_to_world(np.random.default_rng(12).uniform(0, np.array(shape) - 1, (300, dim)))
    for points in (inside, centres):
        by_h5 = np.array([composite.TransformPoint(tuple(map(float, p))) for p in points])
        by_nifti = np.array([field.TransformPoint(tuple(map(float, p))) for p in points])
        np.testing.assert_allclose(by_h5, by_nifti, rtol=0, atol=1e-4)
    np.testing.assert_allclose(by_h5, centres + u.astype(np.float32).reshape(-1, dim), rtol=0, atol=1e-9)


def test_composite_h5_refuses_bad_input_and_keeps_existing_files(tmp_path):
    like = Grid((4, 3, 2), np.zeros(3), np.ones(3), np.eye(3))
    u = np.zeros((4, 3, 2, 3))
    with pytest.raises(VolregIOError, match=r"Composite transform `.*warp.nii.gz` must be named .h5 or .hdf5"):
        write_itk_composite(u, like, tmp_path / "warp.nii.gz")
    with pytest.raises(VolregIOError, match=r"Expected `displacement` of shape \(4, 3, 2, 3\).*got \(4, 3, 3\)"):
        write_itk_composite(u[..., 0, :], like, tmp_path / "warp.h5")
    bad = u.copy()
    bad[1, 1, 1, 0] = np.nan
    with pytest.raises(VolregIOError, match="Expected a finite `displacement`"):
        write_itk_composite(bad, like, tmp_path / "warp.h5")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "warp.h5").write_bytes(b"keep")
    with pytest.raises(VolregIOError, match=r"exists; pass --force to overwrite"):
        write_itk_composite(u, like, tmp_path / "warp.h5")
    assert (tmp_path / "warp.h5").read_bytes() == b"keep"
    write_itk_composite(u + 1.0, like, tmp_path / "warp.h5", force=True)
    moved = sitk.ReadTransform(str(tmp_path / "warp.h5")).TransformPoint((1.0, 1.0, 1.0))
    assert moved == (2.0, 2.0, 2.0) and [p.name for p in tmp_path.iterdir()] == ["warp.h5"]


# --------------------------------------------------------------------------- atomic output


def test_existing_output_refused_and_untouched(tmp_path):
    path = tmp_path / "label_1.nii.gz"
    path.write_bytes(b"precious")
    expected = f"Output `{path}` exists; pass --force to overwrite."
    with pytest.raises(VolregIOError, match=re.escape(expected)):
        with atomic_output(path):
            raise AssertionError("body must not run")  # pragma: no cover
    with pytest.raises(VolregIOError, match=re.escape(expected)):
        write_labels(_volume(np.uint8, "identity"), path)
    assert path.read_bytes() == b"precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["label_1.nii.gz"]

    write_labels(_volume(np.uint8, "identity"), path, force=True)
    _assert_same(_volume(np.uint8, "identity"), read_labels(path))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["label_1.nii.gz"]


def test_exception_inside_context_leaves_nothing(tmp_path):
    path = tmp_path / "label_1.nii.gz"
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_output(path) as tmp:
            assert tmp.parent == tmp_path
            assert tmp.name.startswith(".tmp-") and tmp.name.endswith("-label_1.nii.gz")
            tmp.write_bytes(b"partial")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_output_success_and_permissions(tmp_path):
    path = tmp_path / "out.txt"
    with atomic_output(path) as tmp:
        tmp.write_text("done")
        assert not path.exists()
    assert path.read_text() == "done"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_check_writable(tmp_path):
    existing = tmp_path / "a.nii.gz"
    existing.write_bytes(b"x")
    fresh = tmp_path / "b.vtk"
    check_writable([fresh], force=False)
    check_writable([existing, fresh], force=True)
    with pytest.raises(VolregIOError, match=re.escape(f"Output `{existing}` exists; pass --force")):
        check_writable([fresh, existing], force=False)
    with pytest.raises(VolregIOError, match="does not exist"):
        check_writable([tmp_path / "missing_dir" / "c.nii.gz"], force=True)
    with pytest.raises(VolregIOError, match="more than once"):
        check_writable([fresh, fresh], force=False)
    with pytest.raises(VolregIOError, match="is a directory"):
        check_writable([tmp_path], force=True)


# --------------------------------------------------------------------------- meshes


def _octahedron():
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float)
    tri = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    scale = np.array([12.5, 7.25, 3.125])  # mm; exactly representable in float32
    return v * scale + np.array([-30.0, 40.5, 2.0]), tri, v.copy()


def _corner_sets(vertices, triangles):
    """Orientation-preserving canonical form of a triangle soup, independent of vertex order."""
    corners = vertices[triangles]  # (F, 3, 3)
    canon = []
    for tri in corners:
        rolls = [np.roll(tri, -r, axis=0) for r in range(3)]
        canon.append(min(rolls, key=lambda t: tuple(t.ravel())).ravel())
    canon = np.array(canon)
    return canon[np.lexsort(canon.T[::-1])]


@pytest.mark.parametrize("suffix", [".vtk", ".vtp", ".ply", ".obj"])
def test_mesh_round_trip(tmp_path, suffix):
    v, tri, normals = _octahedron()
    path = tmp_path / f"surf{suffix}"
    write_mesh(v, tri, path, normals=normals)
    v2, tri2, n2 = read_mesh(path)
    np.testing.assert_allclose(v2, v, atol=1e-6)
    np.testing.assert_array_equal(tri2, tri)
    assert n2 is not None
    np.testing.assert_allclose(n2, normals, atol=1e-6)


def test_mesh_round_trip_stl(tmp_path):
    v, tri, _ = _octahedron()
    path = tmp_path / "surf.stl"
    write_mesh(v, tri, path)
    v2, tri2, n2 = read_mesh(path)
    assert n2 is None
    assert v2.shape == v.shape and tri2.shape == tri.shape
    np.testing.assert_allclose(_corner_sets(v2, tri2), _corner_sets(v, tri), atol=1e-6)


@pytest.mark.parametrize("suffix", [".vtk", ".vtp"])
def test_mesh_point_data(tmp_path, suffix):
    v, tri, _ = _octahedron()
    labels = np.arange(len(v), dtype=np.int32)
    path = tmp_path / f"surf{suffix}"
    write_mesh(v, tri, path, point_data={"label": labels})
    np.testing.assert_array_equal(pv.read(path).point_data["label"], labels)
    assert read_mesh(path)[2] is None


@pytest.mark.parametrize("suffix", [".vtk", ".vtp"])
def test_segments_2d(tmp_path, suffix):
    square = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.5], [0.0, 1.5]])
    segments = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    outward = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) / np.sqrt(2)
    path = tmp_path / f"outline{suffix}"
    write_mesh(square, segments, path, normals=outward)
    mesh = pv.read(path)
    assert mesh.n_lines == 4 and mesh.n_cells == 4 and mesh.faces.size == 0
    np.testing.assert_allclose(mesh.points, np.column_stack([square, np.zeros(4)]))
    np.testing.assert_array_equal(mesh.lines.reshape(-1, 3)[:, 1:], segments)
    with _raises(path, "no triangles"):
        read_mesh(path)


def test_quads_are_triangulated(tmp_path):
    path = tmp_path / "cube.vtk"
    pv.Cube().save(path)
    v, tri, _ = read_mesh(path)
    assert tri.shape == (12, 3)
    assert tri.max() < len(v)


def test_mesh_bad_inputs(tmp_path):
    v, tri, normals = _octahedron()
    with _raises(tmp_path / "s.stl", "cannot hold line segments"):
        write_mesh(v, tri[:, :2], tmp_path / "s.stl")
    with _raises(tmp_path / "s.stl", "cannot hold vertex normals"):
        write_mesh(v, tri, tmp_path / "s.stl", normals=normals)
    with _raises(tmp_path / "s.ply", "cannot hold `point_data`"):
        write_mesh(v, tri, tmp_path / "s.ply", point_data={"a": np.zeros(len(v))})
    with pytest.raises(VolregIOError, match=r"Expected `cells` to index vertices in \[0, 6\)"):
        write_mesh(v, tri + 1, tmp_path / "s.vtk")
    with pytest.raises(VolregIOError, match=r"Expected `vertices` of shape \(N, 3\) or \(N, 2\)"):
        write_mesh(v[:, :1], tri, tmp_path / "s.vtk")
    bad = v.copy()
    bad[0, 0] = np.nan
    with pytest.raises(VolregIOError, match="Expected finite `vertices`"):
        write_mesh(bad, tri, tmp_path / "s.vtk")
    assert list(tmp_path.iterdir()) == []


def test_read_mesh_errors(tmp_path):
    missing = tmp_path / "none.vtk"
    with _raises(missing, "does not exist"):
        read_mesh(missing)

    empty = tmp_path / "empty.vtk"
    pv.PolyData().save(empty)
    with _raises(empty, "empty"):
        read_mesh(empty)

    v, tri, _ = _octahedron()
    v[2] = np.nan
    nan_path = tmp_path / "nan.vtk"
    pv.PolyData(v, faces=np.column_stack([np.full(len(tri), 3), tri]).ravel()).save(nan_path)
    with _raises(nan_path, "NaN/Inf"):
        read_mesh(nan_path)

    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(np.random.default_rng(7).bytes(512))
    with _raises(garbage, "could not be read"):
        read_mesh(garbage)


# --------------------------------------------------------------------------- VTK image data (.vti)


def _vti(path: Path, values: np.ndarray, *, dims, spacing, origin, direction, extent_lo=(0, 0, 0)) -> pv.ImageData:
    """Save a pyvista ImageData holding ``values`` (flat, VTK x-fastest order) and return it."""
    img = pv.ImageData(dimensions=dims, spacing=spacing, origin=origin, direction_matrix=direction)
    img.extent = tuple(v for lo, n in zip(extent_lo, dims) for v in (lo, lo + n - 1))
    img.point_data["labels"] = values
    img.save(path)
    return img


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.uint16, np.int32], ids=lambda d: np.dtype(d).name)
@pytest.mark.parametrize("orientation", ["identity", "oblique_20deg", "left_handed"])
def test_vti_matches_pyvista(tmp_path, dtype, orientation):
    direction, spacing, origin = ORIENTATIONS[orientation]
    dims = (5, 4, 3)
    rng = np.random.default_rng(11)
    values = rng.integers(0, 7, size=int(np.prod(dims))).astype(dtype)
    values[0] = np.iinfo(dtype).max  # an extreme value proves the dtype survives
    # A non-zero extent start moves index 0 away from the ImageData origin.
    img = _vti(tmp_path / "lab.vti", values, dims=dims, spacing=spacing, origin=origin, direction=direction,
               extent_lo=(2, -1, 3))
    vol = read_labels(tmp_path / "lab.vti")
    assert vol.shape == dims
    assert vol.array.dtype == np.dtype(dtype)
    points = np.asarray(img.points)  # VTK's world points, x fastest
    for ijk in [(0, 0, 0), (4, 0, 0), (1, 2, 0), (0, 3, 2), (4, 3, 2), (2, 1, 1)]:
        flat = ijk[0] + dims[0] * (ijk[1] + dims[1] * ijk[2])
        assert vol.array[ijk] == values[flat]
        np.testing.assert_allclose(vol.index_to_world(np.array([ijk]))[0], points[flat], atol=1e-9)
    np.testing.assert_allclose(vol.spacing, spacing)
    np.testing.assert_allclose(vol.direction, direction, atol=1e-12)


def test_vti_single_slice_is_2d(tmp_path):
    dims = (6, 4, 1)
    values = np.arange(24, dtype=np.int16)
    _vti(tmp_path / "slice.vti", values, dims=dims, spacing=(0.5, 2.0, 1.0), origin=(1.0, 2.0, 0.0),
         direction=np.eye(3))
    vol = read_labels(tmp_path / "slice.vti")
    assert vol.shape == (6, 4)
    assert vol.array[5, 3] == values[5 + 6 * 3]
    np.testing.assert_allclose(vol.index_to_world(np.array([[5.0, 3.0]])), [[3.5, 8.0]])


def test_vti_float_image(tmp_path):
    values = np.linspace(-1.0, 1.0, 24).astype(np.float32)
    _vti(tmp_path / "f.vti", values, dims=(4, 3, 2), spacing=(1, 1, 1), origin=(0, 0, 0), direction=np.eye(3))
    array, origin, spacing, direction = read_image(tmp_path / "f.vti")
    assert array.dtype == np.float32
    np.testing.assert_array_equal(array[3, 2, 1], values[-1])
    with _raises(tmp_path / "f.vti", "non-integral values"):
        read_labels(tmp_path / "f.vti")


def test_vti_frog_tissues_shipped_with_pyvista():
    from pyvista import examples

    path = Path(examples.__file__).parent / "frog_tissues.vti"
    vol = read_labels(path)
    assert vol.shape == (500, 470, 136)
    assert vol.array.dtype == np.uint8
    np.testing.assert_allclose(vol.spacing, [1.0, 1.0, 1.5])
    assert len(vol.labels()) == 25  # 26 values including background 0


def test_vti_truncated(tmp_path):
    path = tmp_path / "cut.vti"
    _vti(path, np.arange(60, dtype=np.int16), dims=(5, 4, 3), spacing=(1, 1, 1), origin=(0, 0, 0),
         direction=np.eye(3))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with _raises(path, "could not be read as VTK image data"):
        read_labels(path)


def test_vti_not_image_data(tmp_path):
    text = tmp_path / "notes.vti"
    text.write_text("this is not an image\n" * 30)
    with _raises(text, "not a VTK XML image data file"):
        read_labels(text)
    poly = tmp_path / "poly.vti"
    pv.Sphere().save(tmp_path / "poly.vtp")
    os.replace(tmp_path / "poly.vtp", poly)
    with _raises(poly, "not a VTK XML image data file"):
        read_labels(poly)


def test_vti_vector_and_ambiguous_arrays(tmp_path):
    img = pv.ImageData(dimensions=(3, 3, 3))
    img.point_data["vec"] = np.zeros((27, 3), dtype=np.float32)
    img.save(tmp_path / "vec.vti")
    with _raises(tmp_path / "vec.vti", "3 components per voxel"):
        read_labels(tmp_path / "vec.vti")
    img = pv.ImageData(dimensions=(3, 3, 3))
    img.point_data.set_array(np.zeros(27, dtype=np.uint8), "a")
    img.point_data.set_array(np.ones(27, dtype=np.uint8), "b")
    img.save(tmp_path / "two.vti")
    with _raises(tmp_path / "two.vti", "none is marked active"):
        read_labels(tmp_path / "two.vti")
    cells = pv.ImageData(dimensions=(3, 3, 3))
    cells.cell_data["labels"] = np.ones(8, dtype=np.uint8)
    cells.save(tmp_path / "cells.vti")
    with _raises(tmp_path / "cells.vti", "no point data array"):
        read_labels(tmp_path / "cells.vti")


def _mrk(path, positions, statuses):
    """A Slicer .mrk.json (LPS) with one control point per position and status."""
    points = [{"position": list(p), "positionStatus": s} for p, s in zip(positions, statuses)]
    path.write_text(json.dumps({"markups": [{"coordinateSystem": "LPS", "controlPoints": points}]}))
    return path


def test_unplaced_slicer_control_points_are_not_landmarks(tmp_path):
    from volreg.io.landmarks import read_landmarks

    f = _mrk(tmp_path / "f.mrk.json", [(1, 2, 3), (0, 0, 0), (4, 5, 6)], ["defined", "undefined", "preview"])
    np.testing.assert_array_equal(read_landmarks(f), [[1, 2, 3], [4, 5, 6]])
    kept = read_landmarks(f, keep_unplaced=True)
    assert kept.shape == (3, 3) and np.isnan(kept[1]).all() and np.array_equal(kept[[0, 2]], [[1, 2, 3], [4, 5, 6]])
    none = _mrk(tmp_path / "none.mrk.json", [(0, 0, 0), (0, 0, 0)], ["undefined", "undefined"])
    with pytest.raises(VolregIOError, match=r"none.mrk.json.*no placed points \(2 not placed\)"):
        read_landmarks(none)


@pytest.mark.parametrize("content, part", [
    ([[-16, -16, 16]], "holds list data at the top"),
    ({"markups": {"controlPoints": []}}, "has a `markups` dict, not a list"),
    ({"markups": [[-16, -16, 16]]}, "markup 1 is not an object"),
    ({"markups": [{"controlPoints": {"position": [1, 2, 3]}}]}, "markup 1 is not an object"),
    ({"markups": [{"controlPoints": [{"position": [1, 2, 3]}, [-16, -16, 16]]}]}, "control point 2 is not an object"),
    ({"markups": [{"controlPoints": [{"label": "F-1"}]}]}, "control point 1 is not an object with a `position`"),
])
def test_markups_of_the_wrong_shape_are_refused_in_one_line(tmp_path, content, part):
    """Valid JSON that is not a Slicer markups file: a line naming the file and the part."""
    from volreg.io.landmarks import read_landmarks

    path = tmp_path / "bad.mrk.json"
    path.write_text(json.dumps(content))
    with pytest.raises(VolregIOError, match=r"bad\.mrk\.json") as info:
        read_landmarks(path)
    assert part in str(info.value) and "\n" not in str(info.value)


def test_landmark_pairs_with_an_unplaced_point_are_left_out(tmp_path, capsys):
    import argparse

    from volreg.cli._common import _load_landmarks
    from volreg.errors import UsageError

    f = _mrk(tmp_path / "f.mrk.json", [(1, 2, 3), (0, 0, 0), (4, 5, 6)], ["defined", "undefined", "defined"])
    m = tmp_path / "m.csv"
    m.write_text("x,y,z\n1.5,2,3\n9,9,9\n4.5,5,6\n")
    a, b = _load_landmarks(argparse.Namespace(landmarks=[f, m], command="register"))
    np.testing.assert_array_equal(a, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(b, [[1.5, 2, 3], [4.5, 5, 6]])  # the partner of the unplaced point goes too
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "volreg register: warning: --landmarks: left out 1 pair" in err and ": 2." in err
    none = _mrk(tmp_path / "none.mrk.json", [(0, 0, 0)] * 3, ["undefined"] * 3)
    only = _mrk(tmp_path / "only.mrk.json", [(1, 1, 1), (0, 0, 0), (0, 0, 0)], ["defined", "undefined", "undefined"])
    other = _mrk(tmp_path / "other.mrk.json", [(0, 0, 0), (1, 1, 1), (2, 2, 2)], ["undefined", "defined", "defined"])
    with pytest.raises(VolregIOError, match="no placed points"):
        _load_landmarks(argparse.Namespace(landmarks=[none, m], command="register"))
    with pytest.raises(UsageError, match="no pair has both points placed"):
        _load_landmarks(argparse.Namespace(landmarks=[only, other], command="register"))


@pytest.mark.parametrize("shape, tilt", [((40, 30, 1), 0.0), ((40, 30, 1), 10.0), ((40, 1, 1), 10.0),
                                         ((1, 40, 1), 10.0), ((40, 1), 10.0)],
                         ids=["sagittal slice", "oblique slice", "line", "line along j", "2-D line"])
def test_a_field_whose_last_axis_has_one_voxel_reads_in_itk_with_all_its_axes(tmp_path, shape, tilt):
    """A field on a grid whose last axis has one voxel (a single sagittal or oblique slice, a line):
    written in that order, ITK dropped the axis and read a field of D components on D - 1 axes, or a
    singular direction, so no tool, volreg included, could apply it.  Stored single-voxel axes
    first, it reads with all D axes and maps every voxel centre as the field says;
    `axis_order_of` gives back the order of the grid it was computed on."""
    from scipy.spatial.transform import Rotation

    from volreg.io.fields import axis_order_of

    d = len(shape)
    if d == 3:  # index axes: i -> world y, j -> world z, k -> world x; tilted about y
        turn = Rotation.from_euler("y", tilt, degrees=True).as_matrix()
        direction = turn @ np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    else:
        c, s_ = np.cos(np.radians(tilt)), np.sin(np.radians(tilt))
        direction = np.array([[c, -s_], [s_, c]])
    grid = Grid(shape, np.array([5.0, -20.0, 10.0][:d]), np.array([0.8, 1.2, 3.0][:d]), direction)
    u = np.random.default_rng(0).normal(size=shape + (d,))
    write_displacement(u, grid, tmp_path / "warp.nii.gz")
    image = sitk.ReadImage(str(tmp_path / "warp.nii.gz"), sitk.sitkVectorFloat64)
    assert image.GetDimension() == d and sorted(image.GetSize()) == sorted(shape)
    field = sitk.DisplacementFieldTransform(image)
    centres = grid.grid_points().reshape(-1, d)
    mapped = np.array([field.TransformPoint(tuple(p)) for p in centres])
    assert np.allclose(mapped, centres + u.reshape(-1, d), atol=1e-5)
    back, stored = read_displacement(tmp_path / "warp.nii.gz")
    order = axis_order_of(stored, grid)
    assert order is not None and np.allclose(np.transpose(back, order + (d,)), u, atol=1e-6)
    assert axis_order_of(grid, grid) == tuple(range(d))
