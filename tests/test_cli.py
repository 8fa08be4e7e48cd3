"""Tests for the ``volreg`` command line: ``main([...])`` in-process, and once through ``python -m volreg``."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv
import SimpleITK as sitk

import volreg
from volreg import LabelVolume
from volreg.cli import main
from volreg.io import VolregIOError, write_labels
from volreg.settings import SurfaceSettings

from shapes import rotation
from helpers import write_nifti as _nifti

# Geometry of the 3-D test volume: oblique, anisotropic, off-centre shapes, so that
# a flipped or transposed axis anywhere between input and outputs shows.
DIRECTION = rotation(25.0)
SPACING = np.array([1.0, 1.1, 0.9])
ORIGIN = np.array([-12.0, 4.0, 30.0])
SHAPE = (30, 30, 30)
SPHERE_INDEX = np.array([10.0, 15.0, 14.0])  # sphere centre in continuous voxel indices
SPHERE_RADIUS = 7.0  # mm
BLOB_INDEX = np.array([23.0, 14.0, 15.0])
BLOB_AXES = (3.0, 4.0, 3.5)  # mm; the ellipsoid is axis-aligned in world space

# Square pixels: a mask sampled at pixel centres already misplaces a circle by up to half a
# pixel where the outline grazes a row of centres, and the outline is checked to half a pixel.
DISC_SPACING = np.array([0.8, 0.8])
DISC_CENTRE = np.array([17.0, 14.0])  # mm (origin 0, identity direction; off-centre on a 44x40 grid)
DISC_RADIUS = 10.0  # mm

# Half a voxel, a voxel being the largest spacing (volreg's convention, surfaces.voxel_size):
# a mask sampled at voxel centres already places the boundary only to within half a voxel
# along an axis, and the smoothed, shrinkage-corrected mesh should not add to that.
MESH_TOL_MM = 0.5 * SPACING.max()

OUTPUTS_3D = {"label_3.vtk", "label_5.vtk", "sdf_3.nii.gz", "sdf_5.nii.gz", "surface.json"}


def _world(index) -> np.ndarray:
    return ORIGIN + DIRECTION @ (SPACING * np.asarray(index, float))


@pytest.fixture(scope="module")
def volume3d() -> LabelVolume:
    """Label 3: a sphere; label 5: an ellipsoid; uint16 to check that nothing assumes uint8."""
    geom = LabelVolume(np.zeros(SHAPE, np.uint16), ORIGIN, SPACING, DIRECTION)
    pts = geom.grid_points().reshape(-1, 3)
    sphere = np.linalg.norm(pts - _world(SPHERE_INDEX), axis=1) < SPHERE_RADIUS
    blob = np.sum(((pts - _world(BLOB_INDEX)) / BLOB_AXES) ** 2, axis=1) < 1.0
    array = np.where(sphere, 3, np.where(blob, 5, 0)).astype(np.uint16).reshape(SHAPE)
    return geom.with_array(array)


@pytest.fixture(scope="module")
def labels3d(volume3d, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("in") / "labels.nii.gz"
    write_labels(volume3d, path)
    return path


@pytest.fixture(scope="module")
def disc2d(tmp_path_factory) -> Path:
    geom = LabelVolume(np.zeros((44, 40), np.uint8), (0.0, 0.0), DISC_SPACING, np.eye(2))
    pts = geom.grid_points().reshape(-1, 2)
    inside = np.linalg.norm(pts - DISC_CENTRE, axis=1) < DISC_RADIUS
    path = tmp_path_factory.mktemp("in") / "disc.nii.gz"
    write_labels(geom.with_array(inside.reshape(geom.shape).astype(np.uint8)), path)
    return path


@pytest.fixture(scope="module")
def run3d(labels3d, tmp_path_factory):
    """One full run on the 3-D volume, shared by the tests that inspect its outputs."""
    out = tmp_path_factory.mktemp("run3d") / "out"
    rc = main(["surface", str(labels3d), "-o", str(out), "--quiet"])
    assert rc == 0
    return out


def _files(directory: Path) -> set[str]:
    return {p.name for p in directory.iterdir()} if directory.exists() else set()


def _sitk_array(path: Path) -> tuple[np.ndarray, sitk.Image]:
    img = sitk.ReadImage(str(path))
    return sitk.GetArrayFromImage(img).T, img


# --------------------------------------------------------------------------- successful runs


def test_3d_outputs_exist_and_summary_line(labels3d, tmp_path, capsys):
    out = tmp_path / "new" / "out"  # missing parents are created
    assert main(["surface", str(labels3d), "-o", str(out), "--quiet"]) == 0
    assert _files(out) == OUTPUTS_3D
    captured = capsys.readouterr()
    lines = captured.out.strip().splitlines()
    assert len(lines) == 1 and "2 labels (3, 5)" in lines[0] and str(out) in lines[0]
    assert captured.err == ""


def test_3d_mesh_on_analytic_sphere(run3d):
    mesh = pv.read(run3d / "label_3.vtk")
    assert mesh.n_cells > 0 and mesh.is_all_triangles
    centre = _world(SPHERE_INDEX)
    offset = np.asarray(mesh.points, float) - centre
    radius = np.linalg.norm(offset, axis=1)
    assert np.abs(radius - SPHERE_RADIUS).max() < MESH_TOL_MM
    normals = np.asarray(mesh.point_data["Normals"], float)
    assert np.min(np.einsum("nd,nd->n", normals, offset / radius[:, None])) > 0.9  # outward


def test_3d_sdf_geometry_and_sign(run3d, labels3d):
    sdf, img = _sitk_array(run3d / "sdf_3.nii.gz")
    ref = sitk.ReadImage(str(labels3d))
    assert img.GetPixelID() == sitk.sitkFloat32
    assert sdf.shape == SHAPE
    np.testing.assert_allclose(img.GetOrigin(), ref.GetOrigin(), atol=1e-5)
    np.testing.assert_allclose(img.GetSpacing(), ref.GetSpacing(), atol=1e-6)
    np.testing.assert_allclose(img.GetDirection(), ref.GetDirection(), atol=1e-6)
    centre = tuple(int(v) for v in SPHERE_INDEX)
    assert sdf[centre] < 0
    assert sdf[0, 0, 0] > 0 and sdf[-1, -1, -1] > 0
    # Sign agrees with the analytic sphere wherever a voxel is more than a voxel from the
    # boundary (the fit is only required to be accurate near the surface).
    pts = np.array([img.TransformIndexToPhysicalPoint(tuple(int(v) for v in ijk)) for ijk in np.ndindex(SHAPE)])
    true = np.linalg.norm(pts - _world(SPHERE_INDEX), axis=1) - SPHERE_RADIUS
    # Only near the sphere: label 5 is elsewhere, and far away f is just its offset.
    near = (np.abs(true) > SPACING.max()) & (true < 3.0)
    assert np.all(np.sign(sdf.reshape(-1)[near]) == np.sign(true[near]))


def test_3d_summary_json(run3d):
    summary = json.loads((run3d / "surface.json").read_text())
    assert summary["volreg_version"] == volreg.__version__
    assert summary["grid"]["shape"] == list(SHAPE)
    assert [r["label"] for r in summary["labels"]] == [3, 5]
    for record in summary["labels"]:
        mesh = pv.read(run3d / record["mesh"])
        assert record["vertices"] == mesh.n_points
        assert len(record["levels"]) >= 1 and record["levels"] == sorted(record["levels"], reverse=True)
        assert record["fit_seconds"] >= 0
    assert summary["skipped"] == []


def test_2d_disc_outline(disc2d, tmp_path):
    out = tmp_path / "out"
    assert main(["surface", str(disc2d), "-o", str(out), "--quiet"]) == 0
    assert _files(out) == {"label_1.vtk", "sdf_1.nii.gz", "surface.json"}
    mesh = pv.read(out / "label_1.vtk")
    assert mesh.n_lines > 0 and mesh.faces.size == 0
    pts = np.asarray(mesh.points, float)
    np.testing.assert_array_equal(pts[:, 2], 0.0)
    radius = np.linalg.norm(pts[:, :2] - DISC_CENTRE, axis=1)
    assert np.abs(radius - DISC_RADIUS).max() < 0.5 * DISC_SPACING.min()
    sdf, img = _sitk_array(out / "sdf_1.nii.gz")
    assert img.GetDimension() == 2 and sdf.shape == (44, 40)
    np.testing.assert_allclose(img.GetSpacing(), DISC_SPACING, atol=1e-6)
    inside = tuple(np.round(DISC_CENTRE / DISC_SPACING).astype(int))
    assert sdf[inside] < 0 and sdf[0, 0] > 0


def test_labels_subset_writes_only_those(labels3d, tmp_path):
    out = tmp_path / "out"
    assert main(["surface", str(labels3d), "-o", str(out), "--labels", "5", "--quiet"]) == 0
    assert _files(out) == {"label_5.vtk", "sdf_5.nii.gz", "surface.json"}
    assert [r["label"] for r in json.loads((out / "surface.json").read_text())["labels"]] == [5]


def test_skip_small_warns_and_skips(labels3d, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["surface", str(labels3d), "-o", str(out), "--labels", "7,3", "--skip-small", "--quiet"]) == 0
    assert _files(out) == {"label_3.vtk", "sdf_3.nii.gz", "surface.json"}
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.match(r"volreg surface: warning: skipping label 7 .*absent", err[0]), err
    assert json.loads((out / "surface.json").read_text())["skipped"] == [7]


def test_too_small_label(tmp_path, capsys):
    array = np.zeros((20, 20, 20), np.uint8)
    array[4:14, 4:14, 4:14] = 1
    array[17, 17, 17:19] = 2  # two voxels: fewer than min_voxels
    path = tmp_path / "small.nii.gz"
    write_labels(LabelVolume(array, (0, 0, 0), (1, 1, 1), np.eye(3)), path)
    out = tmp_path / "out"
    assert main(["surface", str(path), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert re.fullmatch(r"volreg surface: error: Label 2 has 2 voxels, fewer than min_voxels=8 in `.*small\.nii\.gz`, "
                        r"too few for a surface; pass --skip-small to skip such labels, or --labels .*\n", err), err
    assert _files(out) == set()
    assert main(["surface", str(path), "-o", str(out), "--quiet", "--skip-small"]) == 0
    assert "warning: Skipping label 2" in capsys.readouterr().err
    assert _files(out) == {"label_1.vtk", "sdf_1.nii.gz", "surface.json"}


def test_vti_input(tmp_path):
    array = np.zeros((16, 14, 12), np.uint8)
    array[3:12, 4:11, 2:10] = 4
    img = pv.ImageData(dimensions=array.shape, spacing=(1.0, 1.2, 1.5), origin=(5.0, -3.0, 2.0))
    img.point_data["labels"] = array.ravel(order="F")  # x fastest
    img.save(tmp_path / "box.vti")
    out = tmp_path / "out"
    assert main(["surface", str(tmp_path / "box.vti"), "-o", str(out), "--quiet"]) == 0
    sdf, sdf_img = _sitk_array(out / "sdf_4.nii.gz")
    np.testing.assert_allclose(sdf_img.GetOrigin(), (5.0, -3.0, 2.0), atol=1e-6)
    np.testing.assert_allclose(sdf_img.GetSpacing(), (1.0, 1.2, 1.5), atol=1e-6)
    assert sdf[7, 7, 6] < 0 and sdf[0, 0, 0] > 0
    bounds = np.asarray(pv.read(out / "label_4.vtk").bounds).reshape(3, 2)
    # The box spans indices 3..11, 4..10, 2..9: its boundary lies half a voxel beyond.
    expected = np.array([[2.5, 11.5], [3.5, 10.5], [1.5, 9.5]]) * np.array([[1.0], [1.2], [1.5]])
    expected += np.array([[5.0], [-3.0], [2.0]])
    np.testing.assert_allclose(bounds, expected, atol=0.5 * 1.5)


# --------------------------------------------------------------------------- refusals



def _bad_text(tmp: Path) -> Path:
    path = tmp / "notes.txt"
    path.write_text("not an image\n")
    return path


def _bad_text_named_nii(tmp: Path) -> Path:
    path = tmp / "notes.nii.gz"
    path.write_text("not an image\n" * 20)
    return path


def _bad_truncated(tmp: Path) -> Path:
    path = tmp / "cut.nii.gz"
    write_labels(LabelVolume(np.arange(24000, dtype=np.int16).reshape(30, 40, 20), (0, 0, 0), (1, 1, 1), np.eye(3)),
                 path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _bad_4d(tmp: Path) -> Path:
    return _nifti(tmp / "four.nii.gz", np.ones((6, 5, 4, 3), np.int16))


def _bad_nan(tmp: Path) -> Path:
    data = np.zeros((6, 5, 4), np.float32)
    data[1:4, 1:4, 1:3] = 1.0
    data[0, 0, 0] = np.nan
    return _nifti(tmp / "nan.nii.gz", data)


def _bad_missing(tmp: Path) -> Path:
    return tmp / "nowhere.nii.gz"


def _bad_empty(tmp: Path) -> Path:
    return _nifti(tmp / "empty.nii.gz", np.zeros((6, 5, 4), np.uint8))


BAD_INPUTS = {
    "text file": (_bad_text, r"unsupported suffix '\.txt'"),
    "text named .nii.gz": (_bad_text_named_nii, r"not a readable NIfTI"),
    "truncated .nii.gz": (_bad_truncated, r"is truncated"),
    "4-D image": (_bad_4d, r"is 4-D with size \(6, 5, 4, 3\)"),
    "float with NaN": (_bad_nan, r"1 NaN and 0 Inf"),
    "missing file": (_bad_missing, r"does not exist"),
    "no labels": (_bad_empty, r"holds no labels"),
}


def _assert_one_error_line(err: str, pattern: str) -> None:
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("volreg surface: error: "), err
    assert re.search(pattern, lines[0]), err


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_exit_2_one_line_no_files(case, tmp_path, capsys):
    make, pattern = BAD_INPUTS[case]
    path = make(tmp_path)
    out = tmp_path / "out" / "nested"
    assert main(["surface", str(path), "-o", str(out)]) == 2
    captured = capsys.readouterr()
    _assert_one_error_line(captured.err, pattern)
    assert str(path) in captured.err  # the message names the file
    assert captured.out == ""
    assert not (tmp_path / "out").exists()  # directories it would have created are not left either


def test_absent_label_is_an_error(labels3d, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    assert main(["surface", str(labels3d), "-o", str(out), "--labels", "3,7"]) == 2
    _assert_one_error_line(capsys.readouterr().err, r"Label 7 of --labels is absent from .*labels present: 3, 5")
    assert _files(out) == set()
    assert out.is_dir()  # an existing directory is kept


def test_existing_outputs_need_force(labels3d, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["surface", str(labels3d), "-o", str(out), "--labels", "5", "--quiet"]) == 0
    before = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in out.iterdir()}
    capsys.readouterr()
    assert main(["surface", str(labels3d), "-o", str(out), "--labels", "5", "--quiet"]) == 2
    _assert_one_error_line(capsys.readouterr().err, r"Output `.*label_5\.vtk` exists; pass --force to overwrite")
    assert {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in out.iterdir()} == before
    assert main(["surface", str(labels3d), "-o", str(out), "--labels", "5", "--quiet", "--force"]) == 0
    assert _files(out) == set(before)


def test_any_existing_output_refuses_before_computing(labels3d, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "surface.json").write_text("{}")  # the last output written
    monkeypatch.setattr("volreg.features.label_surfaces.label_surfaces", _must_not_run)
    assert main(["surface", str(labels3d), "-o", str(out)]) == 2
    _assert_one_error_line(capsys.readouterr().err, r"surface\.json` exists")
    assert _files(out) == {"surface.json"}
    assert (out / "surface.json").read_text() == "{}"


def _must_not_run(*args, **kwargs):
    raise AssertionError("computation started before the outputs were checked")


def _failing_second_write(monkeypatch, error: Exception) -> None:
    calls = []
    real = volreg.io.write_scalar

    def write_scalar(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise error
        return real(*args, **kwargs)

    monkeypatch.setattr("volreg.io.write_scalar", write_scalar)


def test_failed_write_midway_removes_what_was_written(labels3d, tmp_path, capsys, monkeypatch):
    _failing_second_write(monkeypatch, VolregIOError("Image `sdf_5.nii.gz` could not be written: disk full."))
    out = tmp_path / "out"
    assert main(["surface", str(labels3d), "-o", str(out), "--quiet"]) == 2
    _assert_one_error_line(capsys.readouterr().err, "disk full")
    assert not out.exists()


def test_bug_propagates_with_traceback_and_cleans_up(labels3d, tmp_path, monkeypatch):
    _failing_second_write(monkeypatch, ZeroDivisionError("a bug"))
    out = tmp_path / "out"
    with pytest.raises(ZeroDivisionError, match="a bug"):
        main(["surface", str(labels3d), "-o", str(out), "--quiet"])
    assert not out.exists()


@pytest.mark.parametrize(
    "argv, pattern",
    [
        (["surface", "x.nii.gz", "-o", "o", "--labels", "1,x"], r"argument --labels: expected comma-separated"),
        (["surface", "x.nii.gz", "-o", "o", "--labels", "0"], r"0 is the background"),
        (["surface", "x.nii.gz", "-o", "o", "--labels", "2,2"], r"label 2 is listed twice"),
        (["surface", "x.nii.gz", "-o", "o", "--min-width", "0"], r"argument --min-width: expected a number > 0"),
        (["surface", "x.nii.gz", "-o", "o", "--smoothing", "nan"], r"argument --smoothing: expected a number >= 0"),
        (["surface", "x.nii.gz"], r"required: -o/--output"),
        ([], r"required: COMMAND"),
    ],
)
def test_usage_errors(argv, pattern, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: volreg"), err
    assert re.search(pattern, err.strip().splitlines()[-1]), err


def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"volreg {volreg.__version__}"


#: Modules that take most of a second to import: the command line loads them only when a command runs.
HEAVY_MODULES = ("numpy", "numba", "scipy", "SimpleITK", "nibabel", "pyvista", "matplotlib", "dask")


@pytest.mark.parametrize(
    "argv, status, stream, pattern",
    [
        (["--version"], 0, "stdout", rf"volreg {re.escape(volreg.__version__)}"),
        (["register", "--help"], 0, "stdout", r"usage: volreg register .* FIXED MOVING .* --linear \{none,rigid,similarity,affine\} .*"),
        (["surface", "--help"], 0, "stdout", rf"usage: volreg surface .* \(default {SurfaceSettings().smoothing}; 0: none\) .*"),
        (["register", "fixed.nii.gz"], 2, "stderr",
         r"usage: volreg register .* volreg register: error: the following arguments are required: MOVING, -o/--output"),
    ],
)
@pytest.mark.system
def test_parser_imports_no_heavy_module(argv, status, stream, pattern):
    """--version, --help and usage errors answer without importing numpy, numba, SimpleITK, pyvista, ..."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "volreg", *argv],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == status, proc.stderr
    timings = [line for line in proc.stderr.splitlines() if line.startswith("import time:")]
    imported = {line.rsplit("|", 1)[1].strip() for line in timings}
    assert "volreg.cli" in imported  # -X importtime did report the imports
    heavy = sorted(m for m in imported if m.split(".")[0] in HEAVY_MODULES)
    assert not heavy, heavy
    output = proc.stdout if stream == "stdout" else "\n".join(
        line for line in proc.stderr.splitlines() if not line.startswith("import time:"))
    assert re.fullmatch(pattern, " ".join(output.split())), output


@pytest.mark.system
def test_python_m_volreg(disc2d, tmp_path):
    out = tmp_path / "out"
    ok = subprocess.run(
        [sys.executable, "-m", "volreg", "surface", str(disc2d), "-o", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert ok.returncode == 0, ok.stderr
    assert re.fullmatch(r"volreg surface: 1 label \(1\) -> .* \(3 files\) in [0-9.]+ s\n", ok.stdout), ok.stdout
    assert _files(out) == {"label_1.vtk", "sdf_1.nii.gz", "surface.json"}
    # Again, without --force: refused with one line and no traceback.
    again = subprocess.run(
        [sys.executable, "-m", "volreg", "surface", str(disc2d), "-o", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert again.returncode == 2
    _assert_one_error_line(again.stderr, "exists; pass --force")


def test_thin_label_is_contoured_with_less_smoothing(tmp_path):
    array = np.zeros((20, 20, 20), np.uint8)
    array[4:14, 4:14, 4:14] = 1
    array[17, 2:14, 17] = 2  # a one-voxel-thick line of 12 voxels: blurred by a voxel, it never reaches 1/2
    path = tmp_path / "thin.nii.gz"
    write_labels(LabelVolume(array, (0, 0, 0), (1, 1, 1), np.eye(3)), path)
    out = tmp_path / "out"
    assert main(["surface", str(path), "-o", str(out), "--quiet"]) == 0
    assert _files(out) == {"label_1.vtk", "label_2.vtk", "sdf_1.nii.gz", "sdf_2.nii.gz", "surface.json"}
    mesh = pv.read(out / "label_2.vtk")
    lo, hi = np.asarray(mesh.bounds).reshape(3, 2).T
    # The line's mesh encloses its voxel centres and stays within a voxel of them.
    assert np.all(lo <= [17, 2, 17]) and np.all(hi >= [17, 13, 17])
    assert np.all(lo >= [16, 1, 16]) and np.all(hi <= [18, 14, 18])


@pytest.mark.system
def test_closed_stdout_pipe_exits_quietly():
    """`volreg protocols | head -c 1`: the reader goes away; no traceback, the SIGPIPE status."""
    read_end, write_end = os.pipe()
    os.close(read_end)  # nobody reads: the child's first write fails with EPIPE
    try:
        proc = subprocess.run([sys.executable, "-m", "volreg", "protocols"], stdout=write_end,
                              stderr=subprocess.PIPE, timeout=60)
    finally:
        os.close(write_end)
    stderr = proc.stderr.decode()
    assert "Traceback" not in stderr and "BrokenPipe" not in stderr, stderr
    assert proc.returncode == 141


@pytest.mark.parametrize("command, words, loaded", [
    ("register", ["a.nii.gz", "b.nii.gz", "-o", "out"], False),
    ("register", ["a.nii.gz", "b.nii.gz", "--landmarks", "a.vtk", "b.vtk"], True),
    ("register", ["a.VTI", "b.nii.gz"], True),
    ("surface", ["a.nii.gz"], True),
])
@pytest.mark.system
def test_pyvista_is_loaded_before_a_command_only_where_it_may_be_used(command, words, loaded):
    """Imports happen with the signals held back (a signal inside a C extension's import can crash
    the interpreter), so a command that may touch VTK loads pyvista then; NIfTI registration does not."""
    code = ("import sys; from volreg.cli import _preload; _preload(sys.argv[1], sys.argv[2:]); "
            "print('pyvista' in sys.modules, 'volreg.outputs.registration' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", code, command, *words], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == [str(loaded), "True"]


@pytest.mark.parametrize("words, status, shown", [
    (["--version"], 0, f"volreg {volreg.__version__}"),
    (["protocols"], 0, "default"),
    (["register", "missing.nii.gz", "also-missing.nii.gz", "-o", "out"], 2, "does not exist"),
])
@pytest.mark.system
def test_console_command_ends_quickly_with_mains_status_output_and_exit_handlers(tmp_path, words, status, shown):
    """The console command ends by os._exit after main: the status is main's, everything printed
    reaches the pipe, and atexit handlers (a library's clean-up) still run, after main."""
    code = ("import atexit, sys; atexit.register(lambda: print('exit handler ran', flush=True)); "
            "from volreg.cli import run; sys.argv = ['volreg', *sys.argv[1:]]; run()")
    proc = subprocess.run([sys.executable, "-c", code, *words], capture_output=True, text=True, timeout=300,
                          cwd=tmp_path)
    assert proc.returncode == status, proc.stderr
    assert shown in proc.stdout + proc.stderr
    assert proc.stdout.rstrip().endswith("exit handler ran")


def test_vtk_suffixes_cover_every_format_read_through_pyvista():
    from volreg.cli import VTK_SUFFIXES
    from volreg.io.images import READ_SUFFIXES
    from volreg.io.meshes import MESH_SUFFIXES
    from volreg.io.pointsets import MESH_FORMATS

    through_pyvista = set(MESH_SUFFIXES) | {s for s in MESH_FORMATS if s != ".gii"} | {".vti"} & set(READ_SUFFIXES)
    assert through_pyvista <= set(VTK_SUFFIXES)


@pytest.mark.parametrize("closed", [(2,), (1, 2), (0, 1, 2)])
@pytest.mark.system
def test_register_with_its_output_streams_closed_writes_every_output(disc2d, tmp_path, closed):
    """`volreg register A B -o OUT 2>&-` (and `>&- 2>&-`): Python starts with no stream there, and
    the first progress line ended the command with exit status 1 and no output."""
    out = tmp_path / "out"

    def close():
        for fd in closed:
            os.close(fd)

    proc = subprocess.run([sys.executable, "-m", "volreg", "register", str(disc2d), str(disc2d), "-o", str(out),
                           "--protocol", "fast"], preexec_fn=close, cwd=tmp_path, timeout=300,
                          **({} if 1 in closed else {"stdout": subprocess.PIPE}))
    assert proc.returncode == 0
    assert {"warp.nii.gz", "inverse_warp.nii.gz", "report.json", "model.npz"} <= _files(out)
    if 1 not in closed:
        assert b"mean Dice" in proc.stdout
