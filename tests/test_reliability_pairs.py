"""Hostile inputs, third round: labels a few voxels across, repeated landmarks, saved results of
another pair, displacement fields that cannot be trusted, and files whose rows or headers are broken.

Each ends in a correct result (checked against a known answer) or a one-line error naming the
argument and what was expected.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

import volreg
from volreg.grid import LabelVolume


def _ball(centre, radius: float, n: int = 32) -> LabelVolume:
    """A ball of ``radius`` voxels (label 1) on an ``n``^3 grid of 1 mm voxels at the origin."""
    g = np.indices((n,) * 3)
    inside = np.sum((g - np.asarray(centre, float)[:, None, None, None]) ** 2, axis=0) <= radius**2
    return LabelVolume(inside.astype(np.uint8), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(3))


@pytest.mark.parametrize("radius", [1.5, 2.5, 3.0])
def test_a_label_a_few_voxels_across_is_registered(radius):
    """A ball a few voxels across (its warp volume, 10 % of its diameter around its surface, is
    thinner than the coarsest level's boxes) moved by one voxel: the shift comes back within
    0.25 mm at its voxels."""
    fixed, moving = _ball((16, 16, 16), radius), _ball((17, 16, 16), radius)
    result = volreg.register_labels(fixed, moving)
    x = fixed.grid_points()[fixed.array > 0]
    error = np.linalg.norm(result.warp(x) - (x + [1.0, 0.0, 0.0]), axis=1)
    assert error.max() < 0.25, error.max()


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """Two balls of radius 8 voxels two voxels apart (A, B), a third ball (C) on the same grid, and
    the two saved registrations ``register A B`` (ab) and ``register B A`` (ba)."""
    from volreg.cli import main
    from volreg.io import write_labels

    d = tmp_path_factory.mktemp("pair")
    for name, centre, radius in (("A", (16, 16, 16), 8), ("B", (18, 16, 16), 8), ("C", (13, 15, 16), 7)):
        write_labels(_ball(centre, radius), d / f"{name}.nii.gz")
    assert main(["register", str(d / "A.nii.gz"), str(d / "B.nii.gz"), "-o", str(d / "ab"), "--quiet"]) == 0
    assert main(["register", str(d / "B.nii.gz"), str(d / "A.nii.gz"), "-o", str(d / "ba"), "--quiet"]) == 0
    return d


@pytest.mark.parametrize("command", ["register", "register-surfaces"])
def test_repeated_landmarks_are_refused_in_one_line(request, tmp_path, capsys, command):
    """Two pairs at one fixed (source) point, here sent to two places, make the landmark start's
    kernel system singular: refused, naming the points, before anything is written."""
    from volreg.cli import main

    if command == "register":
        d, inputs, point, role = request.getfixturevalue("pair"), ("A.nii.gz", "B.nii.gz"), (16, 16, 16), "fixed"
    else:
        d, inputs, point, role = request.getfixturevalue("spheres"), ("a.vtk", "b.vtk"), (20, 0, 0), "source"
    x, y, z = point
    (tmp_path / "f.csv").write_text(f"x,y,z\n{x},{y},{z}\n{x},{y},{z}\n")
    (tmp_path / "m.csv").write_text(f"x,y,z\n{x + 1},{y},{z}\n{x + 2},{y},{z}\n")
    capsys.readouterr()
    assert main([command, *(str(d / name) for name in inputs), "-o", str(tmp_path / "out"),
                 "--landmarks", str(tmp_path / "f.csv"), str(tmp_path / "m.csv")]) == 2
    line = _error(capsys)
    assert "--landmarks: points 1 and 2 of" in line and f"expected distinct {role} landmarks" in line, line
    assert not (tmp_path / "out").exists()


def test_repeated_source_landmarks_are_refused_by_the_library():
    fixed, moving = _ball((16, 16, 16), 8), _ball((18, 16, 16), 8)
    p = np.array([[10.0, 16.0, 16.0], [10.0, 16.0, 16.0]])
    with pytest.raises(ValueError, match="Expected distinct source `landmarks`"):
        volreg.register_labels(fixed, moving, landmarks=(p, p + [2.0, 0.0, 0.0]))


def test_consistency_refuses_saved_results_registered_the_other_way_round(pair, tmp_path, capsys):
    from volreg.cli import main

    capsys.readouterr()
    assert main(["consistency", str(pair / "A.nii.gz"), str(pair / "B.nii.gz"), "--forward", str(pair / "ba"),
                 "--backward", str(pair / "ab"), "-o", str(tmp_path / "out")]) == 2
    line = _error(capsys)
    assert "--forward" in line and "registered the other way round" in line, line
    assert not (tmp_path / "out").exists()


def test_consistency_warns_when_saved_results_come_from_other_files(pair, tmp_path, capsys):
    """C is on A's grid but is not A: the test runs (the same labels saved again differ in their
    bytes as well), and a warning line says the saved registration is of another file."""
    from volreg.cli import main

    capsys.readouterr()
    assert main(["consistency", str(pair / "C.nii.gz"), str(pair / "B.nii.gz"), "--forward", str(pair / "ab"),
                 "--backward", str(pair / "ba"), "-o", str(tmp_path / "out"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "--forward" in err and "registered from other files" in err and "differs from A's" in err, err
    assert main(["consistency", str(pair / "A.nii.gz"), str(pair / "B.nii.gz"), "--forward", str(pair / "ab"),
                 "--backward", str(pair / "ba"), "-o", str(tmp_path / "out2"), "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_apply_refuses_a_field_holding_nan(pair, tmp_path, capsys):
    """SimpleITK reads NaN in a float NIfTI file as 0: the field is checked as nibabel reads it."""
    import nibabel as nib

    from volreg.cli import main

    w = nib.load(pair / "ab" / "warp.nii.gz")
    data = np.asarray(w.dataobj).copy()
    data[8:25, 8:25, 16, 0, 0] = np.nan
    nib.save(nib.Nifti1Image(data, w.affine, w.header), tmp_path / "nan.nii.gz")
    capsys.readouterr()
    assert main(["apply", str(tmp_path / "nan.nii.gz"), str(pair / "B.nii.gz"), "--reference", str(pair / "A.nii.gz"),
                 "-o", str(tmp_path / "o.nii.gz")]) == 2
    assert "holds NaN or Inf; expected finite displacements" in _error(capsys)
    assert not (tmp_path / "o.nii.gz").exists()


def test_apply_warns_when_the_field_covers_part_of_the_reference(pair, tmp_path, capsys):
    """A reference 28 mm along from the field's grid: 4 of its 32 columns lie on the field, and
    the rest is not warped (zero displacement, as ITK reads a field), which one line says."""
    from volreg.cli import main
    from volreg.io import read_labels, write_labels

    b = read_labels(pair / "B.nii.gz")
    shifted = LabelVolume(b.array, b.origin + [28.0, 0.0, 0.0], b.spacing, b.direction)
    write_labels(shifted, tmp_path / "ref.nii.gz")
    capsys.readouterr()
    assert main(["apply", str(pair / "ab" / "warp.nii.gz"), str(tmp_path / "ref.nii.gz"), "--reference",
                 str(tmp_path / "ref.nii.gz"), "-o", str(tmp_path / "o.nii.gz"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "covers 12.5 % of the voxels of --reference" in err and "not warped" in err, err


@pytest.mark.parametrize("warp", ["model.npz", "warp.nii.gz"])
def test_apply_refuses_an_image_the_warp_does_not_reach(pair, tmp_path, capsys, warp):
    """INPUT 500 mm from where the warp sends the reference voxels: the output would be all
    background, which one line refuses; INPUT 20 mm along (14 of its 32 columns are reached) is
    resampled, with a warning."""
    from volreg.cli import main
    from volreg.io import read_labels, write_labels

    b = read_labels(pair / "B.nii.gz")
    for shift, code in ((500.0, 2), (20.0, 0)):
        moving = tmp_path / f"m{int(shift)}.nii.gz"
        write_labels(LabelVolume(b.array, b.origin + [shift, 0.0, 0.0], b.spacing, b.direction), moving)
        out = tmp_path / f"o{int(shift)}.nii.gz"
        capsys.readouterr()
        assert main(["apply", str(pair / "ab" / warp), str(moving), "--reference", str(pair / "A.nii.gz"),
                     "-o", str(out), "--quiet"]) == code
        err = _error(capsys)
        if code:
            assert "sends every voxel of --reference" in err and "outside INPUT" in err, err
            assert not out.exists()
        else:
            assert re.search(r"warning: warp .* sends only 43\.8 % of the voxels of --reference", err), err
            assert read_labels(out).array.any()


def test_apply_refuses_an_image_of_other_dimension(pair, tmp_path, capsys):
    """A 2-D image through a 3-D registration: one line, not a traceback."""
    from volreg.cli import main
    from volreg.io import read_labels, write_labels

    b = read_labels(pair / "B.nii.gz")
    write_labels(LabelVolume(b.array[:, :, 16].copy(), b.origin[:2], b.spacing[:2], np.eye(2)), tmp_path / "m2.nii.gz")
    for warp in ("model.npz", "warp.nii.gz", "linear.tfm"):
        capsys.readouterr()
        assert main(["apply", str(pair / "ab" / warp), str(tmp_path / "m2.nii.gz"), "--reference", str(pair / "A.nii.gz"),
                     "-o", str(tmp_path / "o.nii.gz")]) == 2
        err = _error(capsys)
        assert re.search(r"INPUT `.*m2\.nii\.gz` is 2-D but --reference `.*A\.nii\.gz` is 3-D", err), err
        assert not (tmp_path / "o.nii.gz").exists()


def test_apply_takes_the_h5_fields_register_writes(pair, tmp_path, capsys):
    """warp.h5 and inverse_warp.h5 (ITK HDF5 composite transforms holding one field) apply as
    their NIfTI twins do; an HDF5 transform holding anything else is refused in one line."""
    import SimpleITK as sitk

    from volreg.cli import main
    from volreg.io import read_labels

    for warp, out in (("warp.nii.gz", "by_nifti.nii.gz"), ("warp.h5", "by_h5.nii.gz")):
        assert main(["apply", str(pair / "ab" / warp), str(pair / "B.nii.gz"), "--reference", str(pair / "A.nii.gz"),
                     "-o", str(tmp_path / out), "--quiet"]) == 0
    assert np.array_equal(read_labels(tmp_path / "by_h5.nii.gz").array, read_labels(tmp_path / "by_nifti.nii.gz").array)
    points = np.array([[14.0, 16.0, 16.0], [20.0, 15.0, 17.0]])
    np.savetxt(tmp_path / "p.csv", points, delimiter=",", header="x,y,z", comments="")
    for warp in ("inverse_warp.nii.gz", "inverse_warp.h5"):
        assert main(["apply", str(pair / "ab" / warp), str(tmp_path / "p.csv"), "--from", "moving",
                     "-o", str(tmp_path / f"{warp.replace('.', '_')}.csv")]) == 0
    a, b = (np.loadtxt(tmp_path / f"{w}.csv", delimiter=",", skiprows=1, usecols=(0, 1, 2))
            for w in ("inverse_warp_nii_gz", "inverse_warp_h5"))
    np.testing.assert_allclose(a, b, atol=1e-4)  # the NIfTI field holds float32, the HDF5 one float64
    sitk.WriteTransform(sitk.AffineTransform(3), str(tmp_path / "affine.h5"))
    capsys.readouterr()
    assert main(["apply", str(tmp_path / "affine.h5"), str(pair / "B.nii.gz"), "--reference", str(pair / "A.nii.gz"),
                 "-o", str(tmp_path / "o.nii.gz")]) == 2
    assert "holds AffineTransform; expected one displacement field" in _error(capsys)
    (tmp_path / "text.h5").write_text("not HDF5\n")
    assert main(["apply", str(tmp_path / "text.h5"), str(pair / "B.nii.gz"), "--reference", str(pair / "A.nii.gz"),
                 "-o", str(tmp_path / "o.nii.gz")]) == 2
    assert "is not an HDF5 file" in _error(capsys)
    assert not (tmp_path / "o.nii.gz").exists()


@pytest.mark.parametrize("name", ["o.nii.gz.nii.gz", "o.img.nii", "o.NII.nii.gz", "o.nia.nii.gz"])
def test_an_output_name_the_nifti_writer_would_change_is_refused(pair, tmp_path, capsys, name):
    """ITK's NIfTI writer writes o.nii.gz for o.nii.gz.nii.gz (and an Analyze pair for o.img.nii),
    leaving the named file empty: such names are refused, and nothing is written."""
    from volreg.cli import main

    assert main(["apply", str(pair / "ab" / "model.npz"), str(pair / "B.nii.gz"), "--reference", str(pair / "A.nii.gz"),
                 "-o", str(tmp_path / name)]) == 2
    assert "ends in two image suffixes; expected one, such as `o.nii" in _error(capsys)
    assert list(tmp_path.iterdir()) == []

def test_an_empty_output_name_is_refused(pair, tmp_path, capsys, monkeypatch):
    """`-o ""` would name the working folder."""
    from volreg.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["register", str(pair / "A.nii.gz"), str(pair / "B.nii.gz"), "-o", "", "--force"]) == 2
    assert "argument -o/--output: expected a file or folder name, got an empty string" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name, text, words", [
    ("short.csv", "x,y,z\n1,2,3\n4,5\n", "row 3 has 2 fields; expected x, y and z"),
    ("word.csv", "x,y,z\n1,2,3\n4,abc,5\n", "row 3 holds 'abc'; expected a number"),
    ("short.fcsv", "# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\nF-1,1,2\n",
     "line 3 has 3 fields; expected Slicer's id,x,y,z"),
    ("flat.mrk.json", '{"markups": [{"controlPoints": [{"position": [1, 2]}]}]}',
     "control point 1 has position [1, 2]; expected three coordinates"),
])
def test_a_landmark_row_that_cannot_be_read_is_named(tmp_path, name, text, words):
    from volreg.errors import VolregIOError
    from volreg.io.landmarks import read_landmarks

    (tmp_path / name).write_text(text)
    with pytest.raises(VolregIOError, match=re.escape(words)):
        read_landmarks(tmp_path / name)


def test_a_protocol_file_with_a_byte_order_mark_is_read(tmp_path):
    from volreg.io.protocol import load_protocol

    (tmp_path / "p.toml").write_bytes(b"\xef\xbb\xbf[warp]\nlambda_loc = 50.0\n")
    assert load_protocol(tmp_path / "p.toml").warp.lambda_loc == 50.0


@pytest.mark.parametrize("setting", ["min_det", "fold_margin"])
def test_a_fold_guard_at_or_above_one_is_refused(tmp_path, setting):
    """At det 1 or more the guard would drop every level that compresses space."""
    from volreg.errors import ProtocolError
    from volreg.io.protocol import load_protocol

    (tmp_path / "p.toml").write_text(f"[warp]\n{setting} = 2.0\n")
    with pytest.raises(ProtocolError, match=rf"Expected `{setting}` in \[0, 1\)"):
        load_protocol(tmp_path / "p.toml")


@pytest.mark.parametrize("header", ["zero pixdim", "NaN sform"])
@pytest.mark.system
def test_a_broken_nifti_header_gives_one_line_and_nothing_else(tmp_path, capfd, header):
    """The libraries' own diagnostics (nibabel's log of a pixdim it fixes, ITK's linear-algebra
    dump for a NaN sform) do not reach the terminal before volreg's one-line error."""
    import subprocess
    import sys

    import nibabel as nib

    a = np.zeros((10, 10, 10), np.uint8)
    a[3:6, 3:6, 3:6] = 1
    img = nib.Nifti1Image(a, np.eye(4))
    if header == "zero pixdim":
        img.header["pixdim"][2] = 0
    else:
        s = np.eye(4)
        s[0, 3] = np.nan
        img.set_sform(s, 1)
        img.set_qform(np.eye(4), 0)
    nib.save(img, tmp_path / "a.nii.gz")
    run = subprocess.run([sys.executable, "-m", "volreg", "register", "a.nii.gz", "a.nii.gz", "-o", "out"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("volreg register: error: Label image `a.nii.gz` has"), run.stderr


@pytest.fixture(scope="module")
def spheres(tmp_path_factory):
    """Two spheres of radius 20 mm 3 mm apart, and `register-surfaces` of the first to the second."""
    import pyvista as pv

    from volreg.cli import main

    d = tmp_path_factory.mktemp("spheres")
    pv.Sphere(radius=20, theta_resolution=24, phi_resolution=24).save(d / "a.vtk")
    pv.Sphere(radius=20, center=(3, 0, 0), theta_resolution=24, phi_resolution=24).save(d / "b.vtk")
    assert main(["register-surfaces", str(d / "a.vtk"), str(d / "b.vtk"), "-o", str(d / "r"), "--quiet"]) == 0
    return d


@pytest.mark.parametrize("kind, words", [("text", "holds <U1 values; expected numbers"),
                                         ("nan", "NaN/Inf values; expected finite per-vertex values")])
def test_transfer_refuses_an_array_it_cannot_interpolate(spheres, tmp_path, capsys, kind, words):
    import pyvista as pv

    from volreg.cli import main

    target = pv.read(spheres / "b.vtk")
    target.point_data.clear()
    n = target.n_points
    target.point_data["v"] = np.array(["a"] * n) if kind == "text" else np.where(np.arange(n) % 7 == 0, np.nan, 1.0)
    target.save(tmp_path / "t.vtk")
    capsys.readouterr()
    assert main(["transfer", str(spheres / "a.vtk"), str(tmp_path / "t.vtk"), "--result", str(spheres / "r"),
                 "-o", str(tmp_path / "o.vtk")]) == 2
    assert words in _error(capsys)
    assert not (tmp_path / "o.vtk").exists()


def test_correspondence_table_keeps_full_precision_far_from_the_origin(tmp_path):
    """Coordinates of 1e6 mm: six significant digits would round them to 10 mm."""
    import csv

    import pyvista as pv

    from volreg.cli import main

    for name, centre in (("a", (1e6, 1e6, 1e6)), ("b", (1e6 + 3, 1e6, 1e6))):
        mesh = pv.Sphere(radius=20, center=centre, theta_resolution=20, phi_resolution=20)
        mesh.points = mesh.points.astype(np.float64)
        mesh.points = np.asarray(mesh.points) - np.asarray(mesh.center) + np.asarray(centre)  # float64 about it
        mesh.save(tmp_path / f"{name}.vtk")
    assert main(["register-surfaces", str(tmp_path / "a.vtk"), str(tmp_path / "b.vtk"), "-o", str(tmp_path / "r"),
                 "--quiet"]) == 0
    rows = list(csv.DictReader((tmp_path / "r" / "correspondence.csv").read_text().splitlines()))
    source = pv.read(tmp_path / "a.vtk").points
    table = np.array([[float(r[k]) for k in ("x", "y", "z")] for r in rows])
    assert np.abs(table - source).max() < 1e-6


def test_morph_refuses_more_frames_than_it_can_write(spheres, tmp_path, capsys):
    from volreg.cli import main

    capsys.readouterr()
    assert main(["morph", str(spheres / "a.vtk"), str(spheres / "b.vtk"), "--from-result", str(spheres / "r"),
                 "--frames", "100000000", "-o", str(tmp_path / "m")]) == 2
    assert "--frames 100000000: expected 2 to 1000 frames" in _error(capsys)
    assert not (tmp_path / "m").exists()


def test_morph_from_a_result_of_other_surfaces_says_so(spheres, tmp_path, capsys):
    """A saved warp applied to a SOURCE it was not fitted to lands away from TARGET: one warning line."""
    import pyvista as pv

    from volreg.cli import main

    (pv.Sphere(radius=12, center=(-25, 0, 0)) + pv.Sphere(radius=12, center=(25, 0, 0))).save(tmp_path / "two.vtk")
    capsys.readouterr()
    assert main(["morph", str(tmp_path / "two.vtk"), str(spheres / "b.vtk"), "--from-result", str(spheres / "r"),
                 "--frames", "3", "-o", str(tmp_path / "m"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "volreg morph: warning: the warped SOURCE vertices lie a median" in err and "--from-result" in err, err


def test_triangles_repeating_a_vertex_are_not_counted_as_non_manifold_edges(tmp_path, recwarn):
    import pyvista as pv

    from volreg.io.meshes import read_surface

    sphere = pv.Sphere(radius=20, theta_resolution=16, phi_resolution=16)
    faces = np.concatenate([np.asarray(sphere.faces), [3, 0, 0, 1, 3, 2, 2, 2]])
    pv.PolyData(np.asarray(sphere.points), faces).save(tmp_path / "degenerate.vtk")
    read_surface(tmp_path / "degenerate.vtk")
    assert not [w for w in recwarn if "non-manifold" in str(w.message)]
