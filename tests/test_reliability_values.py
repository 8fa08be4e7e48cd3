"""Hostile inputs, second round: shapes, limits, values and interrupted runs.

Each ends in a correct result (checked against a known answer) or a one-line error
naming the file or setting and what was expected.
"""

from __future__ import annotations

import json
import os
import re

import nibabel as nib
import numpy as np
import pytest
import pyvista as pv
import SimpleITK as sitk

from volreg.cli import main
from volreg.errors import VolregIOError
from volreg.grid import Grid, LabelVolume
from volreg.io import read_grid, read_image, read_labels, write_labels
from volreg.io._atomic import output_folder, recover_folder
from volreg.io.landmarks import read_landmarks
from volreg.io.meshes import read_surface
from volreg.io.protocol import load_protocol
from volreg.morph import NormalsCheck, checked_normals
from volreg.settings import WarpSettings
from volreg.warp.fit import check_sample_memory, estimated_samples
from volreg.warp.resample import resample_image

SMALL = '[protocol]\nname = "t"\n[warp]\nmin_width = 8.0\npad = 6.0\nmax_iter = 30\n'


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def _disc_slices(d, shape=(48, 48, 1), shift=3):
    """Two single-slice volumes stored as 3-D: an ellipse and a disc, the second shifted by ``shift`` voxels in i."""
    ii, jj = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    for name, cx in (("a", 22), ("b", 22 + shift)):
        arr = np.zeros(shape, np.uint8)
        arr[..., 0][((ii - cx) / 12.0) ** 2 + ((jj - 24) / 9.0) ** 2 < 1] = 1
        arr[..., 0][(ii - cx - 3) ** 2 + (jj - 22) ** 2 < 16] = 2
        nib.save(nib.Nifti1Image(arr, np.eye(4)), d / f"{name}.nii.gz")
    (d / "p.toml").write_text(SMALL)


# ----------------------------------------------------------------------------- 2-D stored as 3-D


@pytest.mark.parametrize("suffix", [".nii.gz", ".nrrd"])
def test_a_single_slice_stored_as_3d_is_read_as_2d(tmp_path, suffix):
    arr = np.zeros((20, 16, 1), np.uint8)
    arr[3:9, 4:7, 0] = 5
    img = sitk.GetImageFromArray(arr.transpose(2, 1, 0))
    img.SetSpacing((0.5, 0.75, 2.0))
    sitk.WriteImage(img, str(tmp_path / f"s{suffix}"))
    vol = read_labels(tmp_path / f"s{suffix}")
    assert vol.shape == (20, 16) and np.array_equal(vol.array, arr[..., 0])
    assert np.allclose(vol.spacing, [0.5, 0.75])
    assert read_grid(tmp_path / f"s{suffix}").shape == (20, 16) and read_image(tmp_path / f"s{suffix}")[0].shape == (20, 16)


def test_an_oblique_single_slice_stays_3d(tmp_path):
    img = sitk.GetImageFromArray(np.ones((1, 8, 8), np.uint8))
    c, s = np.cos(0.3), np.sin(0.3)
    img.SetDirection((1, 0, 0, 0, c, -s, 0, s, c))
    sitk.WriteImage(img, str(tmp_path / "o.nii.gz"))
    assert read_labels(tmp_path / "o.nii.gz").shape == (8, 8, 1)


def test_a_single_slice_off_z0_warns_that_its_position_is_dropped(tmp_path):
    img = sitk.GetImageFromArray(np.ones((1, 8, 8), np.uint8))
    img.SetOrigin((0.0, 0.0, 37.5))
    sitk.WriteImage(img, str(tmp_path / "z.nii.gz"))
    with pytest.warns(UserWarning, match=r"single slice \(8x8x1\) and is read as 2-D; its position z = 37.5 mm"):
        assert read_labels(tmp_path / "z.nii.gz").shape == (8, 8)


def test_a_shift_between_single_slices_is_recovered_and_the_warp_reads_back_as_2d(tmp_path, capsys):
    _disc_slices(tmp_path)
    out = tmp_path / "out"
    assert main(["register", str(tmp_path / "a.nii.gz"), str(tmp_path / "b.nii.gz"), "-o", str(out),
                 "--protocol", str(tmp_path / "p.toml"), "--quiet"]) == 0
    warp = sitk.ReadImage(str(out / "warp.nii.gz"))
    assert warp.GetDimension() == 2 and warp.GetNumberOfComponentsPerPixel() == 2
    u = sitk.GetArrayFromImage(warp).transpose(1, 0, 2)  # (i, j, 2), LPS mm
    inside = read_labels(tmp_path / "a.nii.gz").array > 0
    # a shift of 3 voxels (1 mm each) along +i, which is -x in LPS for this RAS-identity affine
    assert np.allclose(u[inside].mean(axis=0), [-3.0, 0.0], atol=0.25)
    assert json.loads((out / "report.json").read_text())["mean_dice"]["after"] > 0.95
    # `apply` takes the single slice and the 2-D warp together
    assert main(["apply", str(out / "warp.nii.gz"), str(tmp_path / "b.nii.gz"), "--reference", str(tmp_path / "a.nii.gz"),
                 "-o", str(tmp_path / "w.nii.gz"), "--interpolation", "label"]) == 0
    warped = read_labels(tmp_path / "w.nii.gz").array
    assert np.mean(warped[inside] == read_labels(tmp_path / "a.nii.gz").array[inside]) > 0.95


# ----------------------------------------------------------------------------- unreadable files, long paths


def _unreadable(path):
    path.write_text("x,y,z\n1,2,3\n")
    path.chmod(0)
    if os.access(path, os.R_OK):  # root reads anything
        pytest.skip("the test runs as a user who can read any file")


@pytest.mark.parametrize("variant", ["no permission", "binary"])
def test_landmark_file_that_cannot_be_read(tmp_path, variant):
    path = tmp_path / "l.csv"
    if variant == "no permission":
        _unreadable(path)
        match = r"Landmark file `.*l\.csv` could not be read: Permission denied\."
    else:
        path.write_bytes(b"\xff\xfe\x00\x81" * 50)
        match = r"Landmark file `.*l\.csv` is not UTF-8 text"
    with pytest.raises(VolregIOError, match=match):
        read_landmarks(path)


@pytest.mark.parametrize("variant", ["no permission", "a directory", "binary"])
def test_protocol_file_that_cannot_be_read(tmp_path, capsys, variant):
    path = tmp_path / "p.toml"
    if variant == "no permission":
        _unreadable(path)
        match = "could not be read: Permission denied."
    elif variant == "a directory":
        path.mkdir()
        match = "is a directory; expected a .toml file."
    else:
        path.write_bytes(b"\x00\xff\xfe" * 40)
        match = "is not UTF-8 text; expected a TOML file."
    assert main(["register", "a.nii.gz", "b.nii.gz", "-o", str(tmp_path / "o"), "--protocol", str(path)]) == 2
    assert _error(capsys).endswith(match)


@pytest.mark.parametrize("where", ["input", "output"])
def test_a_path_over_the_name_limit_is_one_line(tmp_path, capsys, where):
    long = "n" * 300
    write_labels(LabelVolume(np.ones((4, 4), np.uint8), (0, 0), (1, 1), np.eye(2)), tmp_path / "a.nii.gz")
    args = (["register", str(tmp_path / f"{long}.nii.gz"), str(tmp_path / "a.nii.gz"), "-o", str(tmp_path / "o")]
            if where == "input" else
            ["register", str(tmp_path / "a.nii.gz"), str(tmp_path / "a.nii.gz"), "-o", str(tmp_path / long / "o")])
    assert main(args) == 2
    line = _error(capsys)
    assert long in line and "File name too long" in line and "expected a path within the system's limits" in line


# ----------------------------------------------------------------------------- settings that cannot fit in memory


@pytest.mark.parametrize("setting", [{"min_width": 0.05}, {"pad": 1e5}, {"fraction": 1e-6}])
def test_warp_settings_that_cannot_fit_are_refused_up_front(tmp_path, capsys, setting):
    write_labels(read_labels_like_blob(), tmp_path / "a.nii.gz")
    key, value = next(iter(setting.items()))
    (tmp_path / "p.toml").write_text(f'[protocol]\nname = "big"\n[warp]\n{key} = {value}\n')
    assert main(["register", str(tmp_path / "a.nii.gz"), str(tmp_path / "a.nii.gz"), "-o", str(tmp_path / "o"),
                 "--protocol", str(tmp_path / "p.toml"), "--quiet"]) == 2
    line = _error(capsys)
    assert f"{key} {value:g}" in line and "would sample about" in line and "GB is available" in line
    assert not (tmp_path / "o").exists()


def read_labels_like_blob() -> LabelVolume:
    """An ellipsoid of 40 x 30 x 24 mm on a 1.5 mm grid."""
    g = LabelVolume(np.zeros((36, 30, 24), np.uint8), (0, 0, 0), (1.5, 1.5, 1.5), np.eye(3))
    d = g.grid_points() - g.index_to_world((np.array(g.shape)[None] - 1) / 2)[0]
    return g.with_array((((d / [20.0, 15.0, 12.0]) ** 2).sum(-1) < 1).astype(np.uint8))


def test_sample_estimate_is_the_padded_box_over_the_box_size():
    pts = np.array([[0.0, 0.0, 0.0], [10.0, 20.0, 30.0]])
    s = WarpSettings(pad=5.0, min_width=4.0, fraction=0.5)
    # (10 + 10) * (20 + 10) * (30 + 10) mm^3 / (0.5 * 4 mm)^3
    assert estimated_samples(pts, s, 4.0) == pytest.approx(20 * 30 * 40 / 8.0)
    check_sample_memory(pts, s, 4.0)  # 3,000 samples: fine


# ----------------------------------------------------------------------------- meshes and point clouds


def _sphere(d, scale=1.0, name="target.vtk"):
    s = pv.Sphere(radius=20, theta_resolution=14, phi_resolution=14)
    s.points = s.points * scale
    s.save(d / name)
    return d / name


def _surfaces(tmp_path, source, capsys):
    target = _sphere(tmp_path)
    (tmp_path / "p.toml").write_text('[protocol]\nname = "s"\n[warp]\nmin_width = 10.0\npad = 6.0\nmax_iter = 20\n')
    rc = main(["register-surfaces", str(source), str(target), "-o", str(tmp_path / "out"), "--protocol",
               str(tmp_path / "p.toml"), "--quiet"])
    return rc, capsys.readouterr()


@pytest.mark.parametrize("kind,match", [
    ("coincident", "has all its 20 vertices at one point; expected a surface."),
    ("collinear", "has all its vertices on a line; expected a surface."),
    ("planar", "is a point cloud lying in a plane: its inside and outside are undefined"),
    ("metres", "times the size); expected two surfaces in one unit, millimetres"),
    ("centimetres", "times the size); expected two surfaces in one unit, millimetres"),
])
def test_degenerate_or_mis_scaled_surfaces_are_refused(tmp_path, capsys, kind, match):
    path = tmp_path / f"{kind}.vtk"
    if kind == "coincident":
        pv.PolyData(np.full((20, 3), 3.0)).save(path)
    elif kind == "collinear":
        pv.PolyData(np.c_[np.linspace(0, 40, 30), np.zeros(30), np.zeros(30)]).save(path)
    elif kind == "planar":
        g = np.mgrid[0:40:5, 0:40:5].reshape(2, -1).T.astype(float)
        pv.PolyData(np.c_[g, np.zeros(len(g))]).save(path)
    else:
        _sphere(tmp_path, 1e-3 if kind == "metres" else 0.1, path.name)
    rc, cap = _surfaces(tmp_path, path, capsys)
    assert rc == 2
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"volreg register-surfaces: error: SOURCE `{path}`") and match in lines[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("extra", ["unreferenced", "duplicated"])
def test_vertices_on_no_triangle_are_warped_but_not_fitted(tmp_path, capsys, extra):
    s = pv.Sphere(radius=20, theta_resolution=14, phi_resolution=14)
    more = np.array([[60.0, 0.0, 0.0]]) if extra == "unreferenced" else s.points[:5]
    pv.PolyData(np.vstack([s.points, more]), s.faces).save(tmp_path / "src.vtk")
    rc, cap = _surfaces(tmp_path, tmp_path / "src.vtk", capsys)
    assert rc == 0, cap.err
    assert f"has {len(more)} of {s.n_points + len(more)} vertices on no triangle" in cap.err
    warped = pv.read(tmp_path / "out" / "warped.vtk")
    assert warped.n_points == s.n_points + len(more)
    # the source is the target: every vertex stays within a millimetre
    assert np.abs(np.asarray(warped.points) - np.vstack([s.points, more])).max() < 1.0


@pytest.mark.parametrize("kind", ["one triangle", "one triangle with normals"])
def test_a_mesh_with_too_few_vertices_on_triangles_is_refused(tmp_path, capsys, kind):
    """13 vertices, 3 on the one triangle: the 10 others are not fitted, so 3 are left to fit."""
    pts = np.vstack([[[0, 0, 20], [15, 0, 13], [0, 15, 13]], np.random.default_rng(0).normal(size=(10, 3)) * 20])
    mesh = pv.PolyData(pts, faces=[3, 0, 1, 2])
    if kind.endswith("normals"):  # zero normals away from the triangle: those vertices are not fitted either
        normals = np.zeros_like(pts)
        normals[:3] = [0.0, 0.0, 1.0]
        mesh.point_data["Normals"] = normals
    mesh.save(tmp_path / "src.vtk")
    rc, cap = _surfaces(tmp_path, tmp_path / "src.vtk", capsys)
    assert rc == 2, cap.err
    line = cap.err.strip().splitlines()[-1]
    assert line.startswith(f"volreg register-surfaces: error: SOURCE `{tmp_path / 'src.vtk'}` has 3 of 13 vertices")
    assert "expected at least 10" in line and "Traceback" not in cap.err
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- vertex normals read from a file


def _sphere_arrays(radius=20.0, center=(0.0, 0.0, 0.0)):
    s = pv.Sphere(radius=radius, center=center, theta_resolution=14, phi_resolution=14)
    radial = (np.array(s.points, float) - center) / radius
    return np.array(s.points, float), np.asarray(s.faces).reshape(-1, 4)[:, 1:], radial


def test_outward_file_normals_are_kept_as_they_are():
    v, f, radial = _sphere_arrays()
    given = radial + np.random.default_rng(1).normal(0, 0.2, radial.shape)  # outward, not the triangles' own
    normals, check = checked_normals(v, f, given)
    assert np.allclose(normals, given / np.linalg.norm(given, axis=1, keepdims=True))
    assert check == NormalsCheck(compared=len(v))


def test_inward_file_normals_of_a_closed_mesh_are_flipped():
    v, f, radial = _sphere_arrays()
    normals, check = checked_normals(v, f, -radial)
    assert check.flipped and check.inward == check.compared == len(v) and not check.replaced
    assert np.allclose(normals, radial)


def test_file_normals_of_random_sign_are_replaced_by_the_triangles_normals():
    v, f, radial = _sphere_arrays()
    signs = np.random.default_rng(2).choice([-1.0, 1.0], len(v))
    normals, check = checked_normals(v, f, radial * signs[:, None])
    assert check.replaced == len(v) and not check.flipped
    assert np.einsum("nd,nd->n", normals, radial).min() > 0.95  # outward: the triangles' normals


def test_a_hollow_shell_keeps_inner_normals_pointing_into_its_cavity():
    """A solid between radii 10 and 20 mm: outward from the solid is towards the centre on the inner sphere,
    against the triangles' own orientation of that piece; the enclosed volume (outer minus inner) decides."""
    vo, fo, ro = _sphere_arrays(20.0)
    vi, fi, ri = _sphere_arrays(10.0)
    v, f, right = np.vstack([vo, vi]), np.vstack([fo, fi + len(vo)]), np.vstack([ro, -ri])
    normals, check = checked_normals(v, f, right)
    assert np.allclose(normals, right) and check == NormalsCheck(compared=len(v))
    normals, check = checked_normals(v, f, -right)
    assert check.flipped and np.allclose(normals, right)


def test_an_open_mesh_keeps_the_orientation_of_its_file_normals():
    """A cap bounds no volume: normals pointing either way are both possible; they are kept."""
    cap = pv.Sphere(radius=20, theta_resolution=14, phi_resolution=14).clip(normal="z", origin=(0, 0, 8), invert=False)
    cap = cap.triangulate()
    cap = cap.triangulate()
    v, f = np.array(cap.points, float), np.asarray(cap.faces).reshape(-1, 4)[:, 1:]
    inward = -v / np.linalg.norm(v, axis=1, keepdims=True)
    normals, check = checked_normals(v, f, inward)
    assert np.allclose(normals, inward) and check == NormalsCheck()  # nothing closed to compare with


def test_zero_or_non_finite_file_normals_are_computed_again():
    v, f, radial = _sphere_arrays()
    given = radial.copy()
    given[:40] = 0.0
    given[40] = np.nan
    normals, check = checked_normals(v, f, given)
    assert check.absent == 41 and not check.flipped and not check.replaced
    assert np.allclose(normals[41:], radial[41:]) and np.einsum("nd,nd->n", normals, radial).min() > 0.95
    for triangles in (f, np.zeros((0, 3), int)):  # all zero: from the triangles, or a point cloud's neighbours
        normals, check = checked_normals(v, triangles, np.zeros_like(v))
        assert check.absent == len(v) and np.einsum("nd,nd->n", normals, radial).min() > 0.9


def _known_pair(tmp_path, normals):
    """A sphere and its image under a known affine map (as target); the source's point array Normals set."""
    s = pv.Sphere(radius=20, theta_resolution=14, phi_resolution=14)
    truth = np.array(s.points) * [1.1, 0.95, 1.0] + [1.0, 0.0, 0.0]
    t = s.copy()
    t.points = truth
    t.save(tmp_path / "target.vtk")
    s.point_data["Normals"] = normals(np.array(s.point_data["Normals"]))
    s.save(tmp_path / "src.vtk")
    (tmp_path / "p.toml").write_text('[protocol]\nname = "s"\n[warp]\nmin_width = 10.0\npad = 6.0\nmax_iter = 20\n')
    return truth


def _register_known(tmp_path, capsys):
    rc = main(["register-surfaces", str(tmp_path / "src.vtk"), str(tmp_path / "target.vtk"), "-o", str(tmp_path / "out"),
               "--protocol", str(tmp_path / "p.toml"), "--quiet"])
    return rc, capsys.readouterr(), pv.read(tmp_path / "out" / "warped.vtk").points if rc == 0 else None


@pytest.mark.parametrize("kind, words", [
    ("inward", ["point inward", "flipped"]),
    ("random", ["at random", "replaced"]),
    ("some zero", ["40 of", "zero length", "computed from the triangles"]),
    ("all zero", ["zero length", "computed from the triangles"]),
])
def test_register_surfaces_mends_file_normals_with_one_warning(tmp_path, capsys, kind, words):
    """The warped source lands on its true partners as with outward normals: measured 0.39 mm mean
    with outward, inward (flipped), random-sign and zero normals alike; 6.1 mm when inward ones were trusted."""
    rng = np.random.default_rng(3)

    def normals(n):
        if kind == "inward":
            return -n
        if kind == "random":
            return n * rng.choice([-1.0, 1.0], len(n))[:, None]
        n[: 40 if kind == "some zero" else len(n)] = 0.0
        return n

    truth = _known_pair(tmp_path, normals)
    rc, cap, warped = _register_known(tmp_path, capsys)
    assert rc == 0, cap.err
    lines = [line for line in cap.err.strip().splitlines() if "warning" in line]
    assert len(lines) == 1 and f"SOURCE `{tmp_path / 'src.vtk'}`" in lines[0], lines
    assert all(w in lines[0] for w in words), lines[0]
    assert np.linalg.norm(warped - truth, axis=1).mean() < 0.6  # mm: 0.39 measured, 6.1 with inward normals trusted


def test_register_surfaces_with_outward_file_normals_warns_nothing(tmp_path, capsys):
    truth = _known_pair(tmp_path, lambda n: n)
    rc, cap, warped = _register_known(tmp_path, capsys)
    assert rc == 0 and "warning" not in cap.err, cap.err
    assert np.linalg.norm(warped - truth, axis=1).mean() < 0.6  # mm: 0.39 measured


def test_a_point_cloud_with_zero_normals_is_registered_with_one_warning(tmp_path, capsys):
    s = pv.Sphere(radius=20, theta_resolution=14, phi_resolution=14)
    cloud = pv.PolyData(np.array(s.points))
    cloud.point_data["Normals"] = np.zeros((s.n_points, 3))
    cloud.save(tmp_path / "cloud.vtk")
    rc, cap = _surfaces(tmp_path, tmp_path / "cloud.vtk", capsys)
    assert rc == 0, cap.err
    lines = [line for line in cap.err.strip().splitlines() if "warning" in line]
    assert len(lines) == 1 and "zero length" in lines[0] and "neighbouring points" in lines[0], lines
    # the source is the target: every vertex stays within a millimetre
    assert np.abs(np.asarray(pv.read(tmp_path / "out" / "warped.vtk").points) - s.points).max() < 1.0


def test_gifti_quads_are_split_into_triangles(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    quads = np.array([[0, 1, 2, 3]], np.int32)
    img = nib.gifti.GiftiImage(darrays=[
        nib.gifti.GiftiDataArray(v, intent="NIFTI_INTENT_POINTSET", datatype="NIFTI_TYPE_FLOAT32"),
        nib.gifti.GiftiDataArray(quads, intent="NIFTI_INTENT_TRIANGLE", datatype="NIFTI_TYPE_INT32")])
    nib.save(img, tmp_path / "q.surf.gii")
    surf = read_surface(tmp_path / "q.surf.gii")
    assert surf.triangles.tolist() == [[0, 1, 2], [0, 2, 3]]


@pytest.mark.parametrize("shape", [(30, 2), (30, 4)])
def test_gifti_point_set_without_three_columns_is_refused(tmp_path, shape):
    pts = np.random.default_rng(0).random(shape).astype(np.float32)
    img = nib.gifti.GiftiImage(darrays=[
        nib.gifti.GiftiDataArray(pts, intent="NIFTI_INTENT_POINTSET", datatype="NIFTI_TYPE_FLOAT32")])
    nib.save(img, tmp_path / "p.surf.gii")
    with pytest.raises(VolregIOError, match=rf"has a POINTSET of shape \({shape[0]}, {shape[1]}\); expected \(N, 3\)"):
        read_surface(tmp_path / "p.surf.gii")


# ----------------------------------------------------------------------------- values


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_bspline_keeps_a_non_finite_voxel_where_it_was(bad):
    i, j, k = np.meshgrid(*[np.arange(16.0)] * 3, indexing="ij")
    array = np.sin(i / 4) + j / 8 + 0.1 * k
    array[8, 8, 8] = bad
    grid = Grid(array.shape, np.zeros(3), np.ones(3), np.eye(3))
    points = grid.grid_points() + 0.25
    cubic = resample_image(array, grid, points, order=3)
    linear = resample_image(array, grid, points, order=1)
    assert np.array_equal(~np.isfinite(cubic), ~np.isfinite(linear))
    assert (~np.isfinite(cubic)).sum() == 8  # the 8 sample points next to the voxel, not 91 % of the image
    far = np.linalg.norm(points - 8.0, axis=-1) > 4  # away from it: the smooth image's values
    exact = np.sin((i + 0.25) / 4) + (j + 0.25) / 8 + 0.1 * (k + 0.25)
    inner = far & (points.min(axis=-1) > 2) & (points.max(axis=-1) < 13)
    assert np.abs(cubic - exact)[inner].max() < 0.01


@pytest.mark.parametrize("offset", [1000.0, -500.0])
def test_apply_refuses_a_warp_whose_grid_misses_the_reference(tmp_path, capsys, offset):
    ref = LabelVolume(np.ones((8, 8, 8), np.uint8), (0, 0, 0), (1, 1, 1), np.eye(3))
    write_labels(ref, tmp_path / "ref.nii.gz")
    img = sitk.Image([8, 8, 8], sitk.sitkVectorFloat32, 3)
    img.SetOrigin((offset, 0.0, 0.0))
    sitk.WriteImage(img, str(tmp_path / "w.nii.gz"))
    assert main(["apply", str(tmp_path / "w.nii.gz"), str(tmp_path / "ref.nii.gz"), "--reference",
                 str(tmp_path / "ref.nii.gz"), "-o", str(tmp_path / "o.nii.gz")]) == 2
    line = _error(capsys)
    assert "do not overlap, so the warp would leave every reference voxel where it is" in line
    assert not (tmp_path / "o.nii.gz").exists()


@pytest.mark.parametrize("units,scale", [("mm", 1.0), ("um", 1e-3), ("m", 1e3), ("cm", 10.0)])
def test_mrk_json_coordinate_units_are_honoured(tmp_path, units, scale):
    doc = {"markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": units,
                        "controlPoints": [{"position": [1.0, 2.0, 3.0]}]}]}
    (tmp_path / "l.mrk.json").write_text(json.dumps(doc))
    assert np.allclose(read_landmarks(tmp_path / "l.mrk.json"), [[1.0 * scale, 2.0 * scale, 3.0 * scale]])


def test_mrk_json_unknown_units_are_refused(tmp_path):
    doc = {"markups": [{"coordinateUnits": "inch", "controlPoints": [{"position": [1.0, 2.0, 3.0]}]}]}
    (tmp_path / "l.mrk.json").write_text(json.dumps(doc))
    with pytest.raises(VolregIOError, match=r"coordinateUnits 'inch'; expected one of mm, um, cm, m"):
        read_landmarks(tmp_path / "l.mrk.json")


@pytest.mark.parametrize("attribute,value", [("Origin", "nan 0 0"), ("Spacing", "1 inf 1"), ("Origin", "0 zero 0")])
def test_vti_geometry_must_be_finite(tmp_path, attribute, value):
    import re

    g = pv.ImageData(dimensions=(5, 5, 5))
    g.point_data["labels"] = np.ones(125, np.uint8)
    g.save(tmp_path / "v.vti", binary=False)
    text = (tmp_path / "v.vti").read_text()
    (tmp_path / "v.vti").write_text(re.sub(rf'{attribute}="[^"]*"', f'{attribute}="{value}"', text, count=1))
    with pytest.raises(VolregIOError, match=rf'has {attribute}="{value}"; expected finite numbers'):
        read_labels(tmp_path / "v.vti")


# ----------------------------------------------------------------------------- image headers: geometry


def _labels_3d() -> np.ndarray:
    arr = np.zeros((12, 10, 8), np.uint8)
    arr[3:9, 2:8, 2:6] = 1
    arr[5:7, 4:6, 3:5] = 2
    return arr


def _edited_mha(path, old: str, new: str):
    """A MetaImage written by SimpleITK with one header line replaced (``old`` must be in it)."""
    sitk.WriteImage(sitk.GetImageFromArray(_labels_3d().transpose(2, 1, 0).copy()), str(path))
    raw = path.read_bytes()
    assert old.encode() in raw, raw[:300]
    path.write_bytes(raw.replace(old.encode(), new.encode(), 1))
    return path


def _nrrd(path, directions="(1,0,0) (0,1,0) (0,0,1)", origin="(0,0,0)"):
    arr = _labels_3d()
    header = ("NRRD0004\ntype: uint8\ndimension: 3\nspace: left-posterior-superior\n"
              f"sizes: {' '.join(map(str, arr.shape))}\nspace directions: {directions}\nkinds: domain domain domain\n"
              f"encoding: raw\nspace origin: {origin}\n\n")
    path.write_bytes(header.encode() + arr.tobytes(order="F"))
    return path


def _nifti_header(path, *, pixdim=1.0, sform=None):
    """A NIfTI file with an sform alone (qform code 0) and the given pixdim, fields as stored."""
    arr = _labels_3d()
    header = nib.Nifti1Header()
    header.set_data_dtype(arr.dtype)
    header.set_data_shape(arr.shape)
    header["pixdim"][1:4] = pixdim
    header["qform_code"], header["sform_code"] = 0, 1
    rows = np.diag([pixdim, pixdim, pixdim, 1.0]) if sform is None else np.asarray(sform, float)
    header["srow_x"], header["srow_y"], header["srow_z"] = rows[0], rows[1], rows[2]
    nib.save(nib.Nifti1Image(arr, None, header=header), str(path))
    return path


def _vti_pieces(path, whole: str, pieces: list[str], values=None):
    """An ASCII ``.vti`` of a 4 x 3 x 4 grid (x fastest) whose data come in ``pieces`` (extents)."""
    full = np.arange(48, dtype=np.uint8).reshape(4, 3, 4) if values is None else values  # [k, j, i]
    body = []
    for extent in pieces:
        lo = [int(v) for v in extent.split()][0::2]
        hi = [int(v) for v in extent.split()][1::2]
        block = full[lo[2]:hi[2] + 1, lo[1]:hi[1] + 1, lo[0]:hi[0] + 1]
        body.append(f'<Piece Extent="{extent}"><PointData Scalars="l"><DataArray type="UInt8" Name="l" '
                    f'format="ascii">{" ".join(map(str, block.ravel()))}</DataArray></PointData></Piece>')
    path.write_text('<?xml version="1.0"?>\n<VTKFile type="ImageData" version="0.1" byte_order="LittleEndian">\n'
                    f'<ImageData WholeExtent="{whole}" Origin="0 0 0" Spacing="1 1 1">\n' + "\n".join(body)
                    + '\n</ImageData></VTKFile>\n')
    return path, full


def test_vti_whole_extent_beyond_its_piece_is_refused(tmp_path, capfd):
    """VTK fills the part of WholeExtent that no piece covers with whatever memory held."""
    g = pv.ImageData(dimensions=(8, 8, 4))
    g.point_data["labels"] = np.ones(256, np.uint8)
    g.save(tmp_path / "v.vti")
    raw = (tmp_path / "v.vti").read_bytes()
    assert b'WholeExtent="0 7 0 7 0 3"' in raw
    (tmp_path / "v.vti").write_bytes(raw.replace(b'WholeExtent="0 7 0 7 0 3"', b'WholeExtent="0 7 0 7 0 7"', 1))
    with pytest.raises(VolregIOError, match=r'v.vti` has WholeExtent="0 7 0 7 0 7" but its data cover only '
                                            r'Extent="0 7 0 7 0 3"; expected'):
        read_labels(tmp_path / "v.vti")
    assert main(["surface", str(tmp_path / "v.vti"), "-o", str(tmp_path / "out")]) == 2
    err = capfd.readouterr().err.strip()
    assert "\n" not in err and err.startswith("volreg surface: error: ") and "WholeExtent" in err, err
    assert not (tmp_path / "out").exists()


def test_vti_pieces_that_together_cover_the_extent_are_read(tmp_path):
    path, full = _vti_pieces(tmp_path / "two.vti", "0 3 0 2 0 3", ["0 3 0 2 0 1", "0 3 0 2 2 3"])
    assert np.array_equal(read_labels(path).array, full.transpose(2, 1, 0))
    path, _ = _vti_pieces(tmp_path / "gap.vti", "0 3 0 2 0 3", ["0 3 0 2 0 0", "0 3 0 2 2 3"])
    with pytest.raises(VolregIOError, match=r'gap.vti` has WholeExtent="0 3 0 2 0 3" but its data cover only '
                                            r'Extent="0 3 0 2 0 0", Extent="0 3 0 2 2 3"'):
        read_labels(path)


MHA_CASES = [
    # (line SimpleITK writes, line written instead, what the message must say)
    ("Offset = 0 0 0", "Offset = nan 0 0", "has Offset = nan 0 0; expected 3 finite numbers"),
    ("Offset = 0 0 0", "Offset = x 0 0", "has Offset = x 0 0; expected 3 finite numbers"),
    ("Offset = 0 0 0", "Offset = 5 5", "has Offset = 5 5; expected 3 finite numbers"),
    ("Offset = 0 0 0", "Origin = 0 inf 0", "has Origin = 0 inf 0; expected 3 finite numbers"),
    ("Offset = 0 0 0", "Position = 1 2", "has Position = 1 2; expected 3 finite numbers"),
    ("ElementSpacing = 1 1 1", "ElementSpacing = 1 1", "has ElementSpacing = 1 1; expected 3 positive finite numbers"),
    ("ElementSpacing = 1 1 1", "ElementSpacing = nan 1 1",
     "has ElementSpacing = nan 1 1; expected 3 positive finite numbers"),
    ("ElementSpacing = 1 1 1", "ElementSpacing = inf 1 1",
     "has ElementSpacing = inf 1 1; expected 3 positive finite numbers"),
    ("ElementSpacing = 1 1 1", "ElementSpacing = a b c", "has ElementSpacing = a b c; expected 3 positive finite numbers"),
    ("ElementSpacing = 1 1 1", "ElementSpacing = -0 1 1", "has ElementSpacing = -0 1 1; expected positive voxel spacings"),
    ("ElementSpacing = 1 1 1", "ElementSpacing = 1 0 1", "has ElementSpacing = 1 0 1; expected positive voxel spacings"),
    ("TransformMatrix = 1 0 0 0 1 0 0 0 1", "TransformMatrix = 1 0 0 0 1 0 0 0",
     "has TransformMatrix = 1 0 0 0 1 0 0 0; expected 9 finite numbers"),
    ("TransformMatrix = 1 0 0 0 1 0 0 0 1", "Rotation = 1 0 0 0 nan 0 0 0 1",
     "has Rotation = 1 0 0 0 nan 0 0 0 1; expected 9 finite numbers"),
    ("TransformMatrix = 1 0 0 0 1 0 0 0 1", "Orientation = 1 0 0 0 1 0 0 0 x",
     "has Orientation = 1 0 0 0 1 0 0 0 x; expected 9 finite numbers"),
    ("DimSize = 12 10 8", "DimSize = 12 10", "has DimSize = 12 10; expected 3 whole numbers of at least 1"),
    ("DimSize = 12 10 8", "DimSize = 12 nan 8", "has DimSize = 12 nan 8; expected 3 whole numbers of at least 1"),
]


@pytest.mark.parametrize("old,new,message", MHA_CASES, ids=[c[1] for c in MHA_CASES])
def test_metaimage_geometry_fields_must_be_numbers(tmp_path, capfd, old, new, message):
    """MetaIO reads NaN, words or missing values as 0 (or fails with lines of its own): refuse in one line."""
    path = _edited_mha(tmp_path / "m.mha", old, new)
    with pytest.raises(VolregIOError, match=re.escape(f"m.mha` {message}")):
        read_labels(path)
    capfd.readouterr()
    assert main(["surface", str(path), "-o", str(tmp_path / "out")]) == 2
    err = capfd.readouterr().err.strip()
    assert "\n" not in err and err.startswith("volreg surface: error: ") and message in err, err


def test_metaimage_fields_metaio_reads_are_read_as_it_does(tmp_path):
    """Synonyms, and more values than axes (MetaIO takes the first ones), are read as before."""
    vol = read_labels(_edited_mha(tmp_path / "p.mha", "Offset = 0 0 0", "Position = 1 2 3"))
    assert vol.origin.tolist() == [1.0, 2.0, 3.0]
    vol = read_labels(_edited_mha(tmp_path / "s.mha", "ElementSpacing = 1 1 1", "ElementSpacing = 0.5 0.25 2 7"))
    assert vol.spacing.tolist() == [0.5, 0.25, 2.0]


@pytest.mark.parametrize("field,directions,origin", [
    ("space directions", "(nan,0,0) (0,1,0) (0,0,1)", "(0,0,0)"),
    ("space directions", "(nan,nan,nan) (0,1,0) (0,0,1)", "(0,0,0)"),
    ("space directions", "(1,0,0) (0,inf,0) (0,0,1)", "(0,0,0)"),
    ("space origin", "(1,0,0) (0,1,0) (0,0,1)", "(nan,0,0)"),
    ("space origin", "(1,0,0) (0,1,0) (0,0,1)", "(0,0)"),
    ("space origin", "(1,0,0) (0,1,0) (0,0,1)", "(x,0,0)"),
])
def test_nrrd_space_fields_must_be_finite(tmp_path, capfd, field, directions, origin):
    path = _nrrd(tmp_path / "n.nrrd", directions, origin)
    value = directions if field == "space directions" else origin
    with pytest.raises(VolregIOError, match=re.escape(f"n.nrrd` has {field}: {value}; expected")):
        read_labels(path)
    capfd.readouterr()
    assert main(["surface", str(path), "-o", str(tmp_path / "out")]) == 2
    err = capfd.readouterr().err.strip()
    assert "\n" not in err and f"{field}: {value}" in err, err


def test_nrrd_with_valid_space_fields_is_still_read(tmp_path):
    vol = read_labels(_nrrd(tmp_path / "ok.nrrd", "(0,2,0) (1.5,0,0) (0,0,1)", "(1,2,3)"))
    assert vol.spacing.tolist() == [2.0, 1.5, 1.0] and vol.origin.tolist() == [1.0, 2.0, 3.0]


def test_nifti_sform_scaled_beyond_pixdim_gives_one_line(tmp_path, capfd):
    """ITK prints 'unexpected scales in sform' warnings of its own before volreg's line: not any more."""
    path = _nifti_header(tmp_path / "scaled.nii.gz", sform=np.diag([2.0, 2.0, 2.0, 1.0]))
    assert main(["surface", str(path), "-o", str(tmp_path / "out")]) == 2
    err = capfd.readouterr().err.strip()
    assert "\n" not in err and "WARNING" not in err and "pixdim disagrees with the sform" in err, err


def test_nifti_singular_sform_is_called_singular(tmp_path):
    sform = np.eye(4)
    sform[2] = 0.0
    with pytest.raises(VolregIOError, match=r"singular.nii.gz` has an sform \(code 1\) whose direction matrix is "
                                            r"singular \(determinant 0\); expected independent axis directions"):
        read_labels(_nifti_header(tmp_path / "singular.nii.gz", sform=sform))


def test_nifti_sform_offset_a_million_kilometres_away_is_named(tmp_path):
    """ITK checks the sform in single precision, offset included: at 1e8 mm it calls the axes sheared."""
    sform = np.eye(4)
    sform[0, 3] = 1e9
    with pytest.raises(VolregIOError, match=r"far.nii.gz` has an sform \(code 1\) offset of \[1e\+09, 0, 0\] mm; "
                                            r"expected an origin within 1e\+06 mm"):
        read_labels(_nifti_header(tmp_path / "far.nii.gz", sform=sform))


@pytest.mark.parametrize("kind,value", [("nifti", 1e-20), ("nifti", 1e-7), ("nifti", 1e7), ("mha", 1e-30),
                                        ("mha", 1e9), ("nrrd", 1e-9), ("vti", 1e-8)])
def test_implausible_voxel_spacing_is_refused_when_read(tmp_path, capfd, kind, value):
    """A spacing of 1e-20 mm ends in a traceback deep in `register`; refuse it with the axis and value."""
    if kind == "nifti":
        path = _nifti_header(tmp_path / "s.nii.gz", pixdim=value)
        field = "pixdim"
    elif kind == "mha":
        path = _edited_mha(tmp_path / "s.mha", "ElementSpacing = 1 1 1", f"ElementSpacing = {value:g} 1 1")
        field = "ElementSpacing"
    elif kind == "nrrd":
        path = _nrrd(tmp_path / "s.nrrd", f"({value:g},0,0) (0,1,0) (0,0,1)")
        field = "space directions"
    else:
        g = pv.ImageData(dimensions=(5, 5, 5), spacing=(value, 1.0, 1.0))
        g.point_data["labels"] = np.ones(125, np.uint8)
        g.save(tmp_path / "s.vti")
        path, field = tmp_path / "s.vti", "voxel spacing"
    pattern = (rf"{re.escape(path.name)}` has .*{field}.*{re.escape(f'{value:g}')} mm along axis 0; expected voxel "
               r"spacings from 1e-06 to 1e\+06 mm")
    with pytest.raises(VolregIOError, match=pattern):
        read_labels(path)
    assert main(["surface", str(path), "-o", str(tmp_path / "out")]) == 2
    err = capfd.readouterr().err.strip()
    assert "\n" not in err and re.search(pattern, err), err


@pytest.mark.parametrize("spacing", [1e-3, 1e-5, 5e4])
def test_spacings_of_microscopy_and_large_scale_images_are_read(tmp_path, spacing):
    for name in ("m.nii.gz", "m.mha", "m.nrrd"):
        write_labels(LabelVolume(_labels_3d(), (0.0, 0.0, 0.0), (spacing, 1.0, 1.0), np.eye(3)), tmp_path / name)
        np.testing.assert_allclose(read_labels(tmp_path / name).spacing, [spacing, 1.0, 1.0], rtol=1e-6)


# ----------------------------------------------------------------------------- all-or-nothing output folders


def _write(path, text):
    """Write as volreg's writers do: a new file renamed onto the name (the staging folder's
    files are hard links to the previous result's until replaced)."""
    tmp = path.with_name(f".tmp-{path.name}")
    tmp.write_text(text)
    os.replace(tmp, path)


def _result(folder, text):
    for name in ("a.txt", "b.txt"):
        _write(folder / name, text)


@pytest.mark.parametrize("error", [KeyboardInterrupt("SIGTERM"), RuntimeError("disk full")], ids=["interrupt", "error"])
def test_a_failed_force_rerun_keeps_the_whole_previous_result(tmp_path, error):
    out = tmp_path / "out"
    with output_folder(out) as folder:
        _result(folder.path, "old")
        (folder.path / "mine.txt").write_text("kept")
    with pytest.raises(type(error)):
        with output_folder(out, force=True) as folder:
            assert (folder.path / "mine.txt").read_text() == "kept"  # the folder's other files come along
            _write(folder.path / "a.txt", "new")  # one output replaced, the other not yet
            raise error
    assert sorted(p.name for p in out.iterdir()) == ["a.txt", "b.txt", "mine.txt"]
    assert (out / "a.txt").read_text() == (out / "b.txt").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_completed_force_rerun_replaces_the_result_and_keeps_other_files(tmp_path):
    out = tmp_path / "out"
    with output_folder(out) as folder:
        _result(folder.path, "old")
        (folder.path / "mine.txt").write_text("kept")
    with output_folder(out, force=True) as folder:
        _result(folder.path, "new")
    assert (out / "a.txt").read_text() == (out / "b.txt").read_text() == "new"
    assert (out / "mine.txt").read_text() == "kept" and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.parametrize("left", ["ready", "old"])
def test_a_swap_killed_between_its_renames_is_recovered(tmp_path, left):
    """SIGKILL after the old result was set aside and before the new one was renamed in."""
    out = tmp_path / "out"
    aside = tmp_path / f".out.volreg-{left}-999999999-0badc0de"  # a pid that is not running
    aside.mkdir()
    _result(aside, left)
    stale = tmp_path / ".out.volreg-new-999999999-00000000"
    stale.mkdir()
    (stale / "a.txt").write_text("partial")
    assert recover_folder(out) == ("new" if left == "ready" else "old")
    assert (out / "a.txt").read_text() == (out / "b.txt").read_text() == left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_the_working_directory_is_written_in_place(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with output_folder(tmp_path, require_empty=False) as folder:
        # never renamed away under the user's shell: staged inside it, moved in file by file
        assert folder.path.parent == tmp_path and folder.path.name.startswith(".volreg-new-")
        (folder.path / "a.txt").write_text("x")
        folder.record(folder.path / "a.txt")
    assert (tmp_path / "a.txt").read_text() == "x" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_an_interrupted_force_rerun_says_the_previous_result_was_kept(tmp_path, capsys, monkeypatch):
    _disc_slices(tmp_path)
    out = tmp_path / "out"
    args = ["register", str(tmp_path / "a.nii.gz"), str(tmp_path / "b.nii.gz"), "-o", str(out), "--protocol",
            str(tmp_path / "p.toml"), "--quiet"]
    assert main(args) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()

    def interrupted(*a, **k):
        raise KeyboardInterrupt("SIGTERM")

    # after six of the eight outputs are written
    monkeypatch.setattr("volreg.io.report_figure.write_report_figure", interrupted)
    assert main([*args, "--force"]) == 143
    assert _error(capsys) == (f"volreg register: interrupted by SIGTERM; the outputs of this run were removed "
                              f"(the previous result in `{out}` was kept).")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir() if "volreg" in p.name) == []
    assert load_protocol(tmp_path / "p.toml").warp.min_width == 8.0


@pytest.mark.parametrize("name, status", [("SIGTERM", 143), ("SIGINT", 130)])
def test_an_interrupt_that_a_library_turns_into_another_error_is_still_an_interrupt(tmp_path, capsys, monkeypatch,
                                                                                   name, status):
    """SIGTERM or SIGINT while matplotlib draws: its renderer turns the KeyboardInterrupt into a
    ValueError (numba's dispatcher likewise turns it into a SystemError)."""
    import signal
    import time

    _disc_slices(tmp_path)
    out = tmp_path / "out"

    def drawing(*a, **k):
        try:
            os.kill(os.getpid(), getattr(signal, name))
            time.sleep(5)
        except KeyboardInterrupt:
            raise ValueError("Invalid affine transformation matrix") from None

    monkeypatch.setattr("volreg.io.report_figure.write_report_figure", drawing)
    # Python's own SIGINT handler, as when the command starts (a library loaded by another test
    # may have installed its own)
    previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    # On one thread the figure is drawn by the main thread, which the signal interrupts (on
    # more, the outputs are written on worker threads and the interrupt meets the main one
    # waiting for them).
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        code = main(["register", str(tmp_path / "a.nii.gz"), str(tmp_path / "b.nii.gz"), "-o", str(out),
                     "--protocol", str(tmp_path / "p.toml"), "--quiet"])
    finally:
        numba.set_num_threads(threads)
        signal.signal(signal.SIGINT, previous_int)
    assert code == status
    assert _error(capsys) == f"volreg register: interrupted by {name}; the outputs of this run were removed."
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.nii.gz", "b.nii.gz", "p.toml"]
