"""``volreg apply`` on landmarks and meshes, in either direction, from a model, a field or a linear transform."""

from __future__ import annotations

import json
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import pyvista as pv
import SimpleITK as sitk

from volreg.cli import main
from volreg.grid import Grid
from volreg.io.fields import write_displacement, write_itk_linear
from volreg.io.landmarks import read_landmarks
from volreg.linear_map import LinearMap
from volreg.warp.field import displacement_on_grid
from volreg.warp.inverse import InverseWarp
from volreg.warp.model import KernelWarp, WarpLevel
from volreg.warp.points import DisplacementField, transform_normals, transform_points

from shapes import rotation

FLIP = np.array([-1.0, -1.0, 1.0])


def known_warp() -> KernelWarp:
    """A smooth kernel warp on [0, 60]^3 mm (a few mm, det J > 0.5) after a rotation, scaling and shift."""
    rng = np.random.default_rng(7)
    levels = [WarpLevel(rng.uniform(0, 60, (80, 3)), rng.normal(0, amp, (80, 3)), width=width)
              for width, amp in ((30.0, 0.2), (15.0, 0.08))]
    linear = LinearMap(1.02 * rotation(5.0), np.array([2.0, -1.0, 1.5]))
    return KernelWarp(levels, dim=3, linear=linear)


FIXED = Grid((41, 41, 41), np.zeros(3), np.full(3, 1.5), np.eye(3))
MOVING = Grid((52, 52, 52), np.full(3, -8.0), np.full(3, 1.5), rotation(3.0, (0.1, 0.2, 1.0)))


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """model.npz, warp.nii.gz (fixed grid), inverse_warp.nii.gz (moving grid) and linear.tfm of ``known_warp``."""
    d = tmp_path_factory.mktemp("saved")
    warp = known_warp()
    warp.save(d / "model.npz")
    write_displacement(displacement_on_grid(warp, FIXED), FIXED, d / "warp.nii.gz")
    write_displacement(displacement_on_grid(InverseWarp(warp), MOVING), MOVING, d / "inverse_warp.nii.gz")
    write_itk_linear(d / "linear.tfm", warp.linear)
    return d, warp


def fixed_points(n: int = 30, seed: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).uniform(8, 52, (n, 3))


def write_csv(path: Path, points: np.ndarray) -> None:
    rows = ["label,x,y,z,t,comment"] + [f"p{i},{x},{y},{z},0,note {i}" for i, (x, y, z) in enumerate(points.tolist())]
    path.write_text("\n".join(rows) + "\n")


def apply(*args) -> int:
    return main(["apply", *[str(a) for a in args]])


# ----------------------------------------------------------------------------- the numerics


def test_displacement_field_maps_points_as_simpleitk(saved):
    """p + u(p), linear inside, the edge voxel's value within half a voxel of the edge, zero outside:
    SimpleITK's DisplacementFieldTransform.TransformPoint to 1e-6 mm, at points inside, at the edge and outside."""
    d, _ = saved
    img = sitk.ReadImage(str(d / "warp.nii.gz"), sitk.sitkVectorFloat64)
    u = sitk.GetArrayFromImage(img).transpose(2, 1, 0, 3)
    field = DisplacementField(u, FIXED)
    rng = np.random.default_rng(0)
    p = np.concatenate([rng.uniform(-2, 62, (3000, 3)),  # in, near the edge (-0.75 .. 60.75 mm) and out
                        [[-0.7, 30, 30], [60.7, 30.2, 29.9], [-0.8, 30, 30], [30, 61.0, 30]]])
    ref = np.array([sitk.DisplacementFieldTransform(sitk.Image(img)).TransformPoint(tuple(q)) for q in p])
    assert np.abs(field(p) - ref).max() <= 1e-6
    outside = ~field.inside(p)
    assert 0 < outside.sum() < len(p) and np.array_equal(field(p)[outside], p[outside])


def test_transform_points_and_normals_follow_the_jacobian(saved):
    _, warp = saved
    x = fixed_points(200)
    y = transform_points(warp, x).points
    assert np.abs(y - warp(x)).max() == 0
    back = transform_points(warp, y, inverse=True)
    assert back.converged.all() and np.abs(back.points - x).max() <= 1e-6
    lin = transform_points(warp.linear, x)
    assert np.abs(lin.points - warp.linear(x)).max() <= 1e-12
    assert np.abs(transform_points(warp.linear, lin.points, inverse=True).points - x).max() <= 1e-9
    # a normal stays perpendicular to every tangent carried by J
    rng = np.random.default_rng(1)
    n = rng.normal(size=(200, 3))
    t = np.cross(n, rng.normal(size=(200, 3)))
    jac = warp.jacobian(x)
    for inverse, at, j in ((False, x, jac), (True, y, np.linalg.inv(jac))):
        m = transform_normals(warp, at, n, inverse=inverse, mapped=x if inverse else None)
        tangent = np.einsum("nab,nb->na", j, t)
        assert np.abs(np.einsum("na,na->n", m, tangent)).max() <= 1e-9 * np.abs(tangent).max()
        assert np.allclose(np.linalg.norm(m, axis=1), np.linalg.norm(n, axis=1))
    with pytest.raises(ValueError, match="one direction only"):
        transform_points(DisplacementField(np.zeros((*FIXED.shape, 3)), FIXED), x, inverse=True)


# ----------------------------------------------------------------------------- points through the command


def test_csv_from_fixed_through_the_model_is_tau_exactly(saved, tmp_path, capsys):
    d, warp = saved
    x = fixed_points()
    write_csv(tmp_path / "in.csv", x)
    assert apply(d / "model.npz", tmp_path / "in.csv", "--from", "fixed", "-o", tmp_path / "out.csv") == 0
    assert "30 points, fixed -> moving space" in capsys.readouterr().out
    assert np.abs(read_landmarks(tmp_path / "out.csv") - warp(x)).max() <= 1e-6
    rows_in = (tmp_path / "in.csv").read_text().splitlines()
    rows_out = (tmp_path / "out.csv").read_text().splitlines()
    assert rows_out[0] == rows_in[0] and len(rows_out) == len(rows_in)
    for a, b in zip(rows_in[1:], rows_out[1:]):  # label, t and comment columns kept as they were
        a, b = a.split(","), b.split(",")
        assert [a[0], *a[4:]] == [b[0], *b[4:]]


def test_csv_from_fixed_through_the_field_within_interpolation(saved, tmp_path):
    """warp.nii.gz is u sampled every 1.5 mm (kernels 15 mm wide and more, |u| up to 6 mm): linear
    interpolation of it is within 0.05 mm of tau (0.03 mm measured at 2000 points)."""
    d, warp = saved
    x = fixed_points()
    write_csv(tmp_path / "in.csv", x)
    assert apply(d / "warp.nii.gz", tmp_path / "in.csv", "--from", "fixed", "-o", tmp_path / "out.csv") == 0
    err = np.abs(read_landmarks(tmp_path / "out.csv") - warp(x)).max()
    assert err <= 0.05, err


@pytest.mark.parametrize("there, back", [("model.npz", "model.npz"), ("linear.tfm", "linear.tfm"),
                                          ("inverse_warp.nii.gz", "warp.nii.gz")])
def test_moving_to_fixed_and_back_returns_the_start(saved, tmp_path, there, back):
    d, warp = saved
    y = (warp.linear if there == "linear.tfm" else warp)(fixed_points())  # moving-space points
    write_csv(tmp_path / "y.csv", y)
    assert apply(d / there, tmp_path / "y.csv", "--from", "moving", "-o", tmp_path / "x.csv") == 0
    assert apply(d / back, tmp_path / "x.csv", "--from", "fixed", "-o", tmp_path / "y2.csv") == 0
    tol = 0.05 if there.endswith(".nii.gz") else 1e-3  # fields: interpolated twice
    assert np.abs(read_landmarks(tmp_path / "y2.csv") - y).max() <= tol
    if there == "model.npz":  # tau^-1 itself, to the solver's tolerance
        assert np.abs(warp(read_landmarks(tmp_path / "x.csv")) - y).max() <= 1e-5


def test_linear_transform_from_fixed_is_exact(saved, tmp_path):
    d, warp = saved
    x = fixed_points()
    write_csv(tmp_path / "in.csv", x)
    assert apply(d / "linear.tfm", tmp_path / "in.csv", "--from", "fixed", "-o", tmp_path / "out.csv") == 0
    assert np.abs(read_landmarks(tmp_path / "out.csv") - warp.linear(x)).max() <= 1e-9


def test_fcsv_keeps_its_frame_and_fields(saved, tmp_path):
    d, warp = saved
    x = fixed_points(4)
    ras = x * FLIP
    head = "# Markups fiducial file version = 4.10\n# CoordinateSystem = 0\n# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
    lines = [f"vtkMRMLMarkupsFiducialNode_{i},{p[0]},{p[1]},{p[2]},0,0,0,1,1,1,0,F-{i},desc {i},vtkMRMLScalarVolumeNode1"
             for i, p in enumerate(ras.tolist())]
    (tmp_path / "in.fcsv").write_text(head + "\n".join(lines) + "\n")
    assert apply(d / "model.npz", tmp_path / "in.fcsv", "--from", "fixed", "-o", tmp_path / "out.fcsv") == 0
    text = (tmp_path / "out.fcsv").read_text()
    assert text.startswith(head)
    rows = [r.split(",") for r in text.splitlines()[3:]]
    assert [r[4:] for r in rows] == [line.split(",")[4:] for line in lines]
    stored = np.array([[float(v) for v in r[1:4]] for r in rows])
    assert np.abs(stored - warp(x) * FLIP).max() <= 1e-6  # still RAS
    assert np.abs(read_landmarks(tmp_path / "out.fcsv") - warp(x)).max() <= 1e-6


def test_mrk_json_keeps_frames_and_unplaced_points(saved, tmp_path):
    d, warp = saved
    x = fixed_points(3)
    data = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
            "Schema/markups-schema-v1.0.3.json#",
            "markups": [
                {"type": "Fiducial", "coordinateSystem": "RAS", "display": {"color": [1, 0, 0]},
                 "controlPoints": [{"id": "1", "label": "a", "position": list(x[0] * FLIP), "positionStatus": "defined"},
                                   {"id": "2", "label": "b", "position": [0, 0, 0], "positionStatus": "undefined"}]},
                {"type": "Fiducial", "coordinateSystem": "LPS",
                 "controlPoints": [{"id": "3", "label": "c", "position": list(x[1])},
                                   {"id": "4", "label": "d", "position": list(x[2])}]}]}
    (tmp_path / "in.mrk.json").write_text(json.dumps(data))
    assert apply(d / "model.npz", tmp_path / "in.mrk.json", "--from", "fixed", "-o", tmp_path / "out.mrk.json") == 0
    out = json.loads((tmp_path / "out.mrk.json").read_text())
    y = warp(x)
    first, second = out["markups"]
    assert first["coordinateSystem"] == "RAS" and second["coordinateSystem"] == "LPS"
    assert first["display"] == {"color": [1, 0, 0]} and out["@schema"] == data["@schema"]
    assert np.abs(np.array(first["controlPoints"][0]["position"]) - y[0] * FLIP).max() <= 1e-6
    assert first["controlPoints"][1] == data["markups"][0]["controlPoints"][1]  # never placed: as it was
    assert np.abs(np.array([cp["position"] for cp in second["controlPoints"]]) - y[1:]).max() <= 1e-6
    assert [cp["label"] for m in out["markups"] for cp in m["controlPoints"]] == ["a", "b", "c", "d"]


@pytest.mark.parametrize("unit, per_mm", [("cm", 0.1), ("um", 1000.0), ("m", 1e-3)])
def test_mrk_json_in_other_units_is_written_back_in_its_unit(saved, tmp_path, unit, per_mm):
    """A markup in cm (um, m) is read in mm; its moved points were written as mm under the
    file's "cm", ten times too far out, with exit 0.  They are written in the file's unit."""
    d, warp = saved
    x = fixed_points(2)
    data = {"markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": unit,
                         "controlPoints": [{"id": str(i), "position": list(p * per_mm)} for i, p in enumerate(x)]}]}
    (tmp_path / "in.mrk.json").write_text(json.dumps(data))
    assert apply(d / "model.npz", tmp_path / "in.mrk.json", "--from", "fixed", "-o", tmp_path / "out.mrk.json") == 0
    out = json.loads((tmp_path / "out.mrk.json").read_text())["markups"][0]
    assert out["coordinateUnits"] == unit
    moved = np.array([cp["position"] for cp in out["controlPoints"]]) / per_mm
    assert np.abs(moved - warp(x)).max() <= 1e-6
    assert np.allclose(read_landmarks(tmp_path / "out.mrk.json"), warp(x), atol=1e-6)


def test_landmark_files_with_a_byte_order_mark_are_moved(saved, tmp_path):
    """A CSV or .mrk.json starting with a byte-order mark (as spreadsheet programs and some
    editors write) was read for its points but written back from the raw text: a traceback."""
    d, warp = saved
    x = fixed_points(2)
    write_csv(tmp_path / "in.csv", x)
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + (tmp_path / "in.csv").read_bytes())
    marks = {"markups": [{"coordinateSystem": "LPS", "controlPoints": [{"position": list(p)} for p in x]}]}
    (tmp_path / "bom.mrk.json").write_bytes(b"\xef\xbb\xbf" + json.dumps(marks).encode())
    for name in ("bom.csv", "bom.mrk.json"):
        assert apply(d / "model.npz", tmp_path / name, "--from", "fixed", "-o", tmp_path / f"out-{name}") == 0
        assert np.allclose(read_landmarks(tmp_path / f"out-{name}"), warp(x), atol=1e-6), name


def test_slicer_files_read_as_users_write_them(tmp_path):
    """`# CoordinateSystem: RAS` (a colon) in a .fcsv gave "list index out of range"; a .mrk.json
    point marked placed at NaN was read as never placed, and written back as NaN."""
    (tmp_path / "colon.fcsv").write_text("# Markups fiducial file version = 4.11\n# CoordinateSystem: RAS\n"
                                         "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                                         "1,10,20,30,0,0,0,1,1,1,0,F-1,,\n")
    assert np.allclose(read_landmarks(tmp_path / "colon.fcsv"), [[-10.0, -20.0, 30.0]])
    nan = {"markups": [{"controlPoints": [{"position": [1.0, 2.0, 3.0]},
                                          {"position": [float("nan")] * 3, "positionStatus": "defined"}]}]}
    (tmp_path / "nan.mrk.json").write_text(json.dumps(nan))
    with pytest.raises(Exception, match="control point 2 is placed"):
        read_landmarks(tmp_path / "nan.mrk.json")


def test_points_outside_the_field_grid_are_counted(saved, tmp_path, capsys):
    d, _ = saved
    x = np.concatenate([fixed_points(5), [[200.0, 0, 0], [-50.0, 10, 10]]])
    write_csv(tmp_path / "in.csv", x)
    assert apply(d / "warp.nii.gz", tmp_path / "in.csv", "--from", "fixed", "-o", tmp_path / "out.csv") == 0
    assert "2 of 7 points lie outside the grid" in capsys.readouterr().err
    assert np.array_equal(read_landmarks(tmp_path / "out.csv")[5:], x[5:])


def test_field_named_for_the_other_direction_is_warned_about(saved, tmp_path, capsys):
    d, _ = saved
    write_csv(tmp_path / "in.csv", fixed_points(3))
    assert apply(d / "warp.nii.gz", tmp_path / "in.csv", "--from", "moving", "-o", tmp_path / "out.csv") == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "inverse_warp.nii.gz" in err


# ----------------------------------------------------------------------------- meshes


def smooth_sphere() -> pv.PolyData:
    mesh = pv.Sphere(radius=15.0, center=(30.0, 28.0, 31.0), theta_resolution=24, phi_resolution=24)
    mesh.point_data["thickness"] = np.arange(mesh.n_points, dtype=np.float32)
    return mesh


@pytest.mark.parametrize("suffix", [".vtk", ".vtp", ".ply", ".stl", ".obj"])
def test_mesh_moves_its_vertices_and_keeps_its_faces(saved, tmp_path, suffix):
    d, warp = saved
    smooth_sphere().save(str(tmp_path / f"in{suffix}"))
    source = pv.read(str(tmp_path / f"in{suffix}"))
    assert apply(d / "model.npz", tmp_path / f"in{suffix}", "--from", "fixed", "-o", tmp_path / f"out{suffix}") == 0
    out = pv.read(str(tmp_path / f"out{suffix}"))
    assert np.array_equal(np.asarray(out.faces), np.asarray(source.faces))
    assert np.abs(np.asarray(out.points) - warp(np.asarray(source.points, float))).max() <= 1e-4  # float32 storage
    if suffix in (".vtk", ".vtp"):
        assert np.array_equal(out.point_data["thickness"], source.point_data["thickness"])
    if "Normals" in source.point_data:  # carried normals agree with the moved surface's own within 1 degree
        own = out.compute_normals(point_normals=True, cell_normals=False, split_vertices=False,
                                  consistent_normals=False).point_data["Normals"]
        cos = np.einsum("na,na->n", own, np.asarray(out.point_data["Normals"]))
        assert cos.min() >= np.cos(np.radians(1.0)), cos.min()
        stale = np.einsum("na,na->n", own, np.asarray(source.point_data["Normals"]))
        assert stale.min() < np.cos(np.radians(5.0))  # the warp turns the surface by more than that


def test_ply_keeps_its_vertex_colours_and_texture_coordinates(saved, tmp_path, capsys):
    d, warp = saved
    sphere = smooth_sphere()
    colours = np.random.default_rng(5).integers(0, 256, (sphere.n_points, 3)).astype(np.uint8)
    sphere.point_data["RGB"] = colours
    sphere.active_texture_coordinates = np.asarray(sphere.points[:, :2] / 60.0, np.float32)
    sphere.save(str(tmp_path / "in.ply"), texture="RGB")
    source = pv.read(str(tmp_path / "in.ply"))
    assert {"RGB", "TCoords"} <= set(source.point_data.keys())  # what a coloured PLY reads as
    assert apply(d / "model.npz", tmp_path / "in.ply", "--from", "fixed", "-o", tmp_path / "out.ply") == 0
    assert "warning" not in capsys.readouterr().err
    out = pv.read(str(tmp_path / "out.ply"))
    assert np.array_equal(np.asarray(out.point_data["RGB"]), colours)
    assert np.array_equal(np.asarray(out.point_data["TCoords"]), np.asarray(source.point_data["TCoords"]))
    assert np.abs(np.asarray(out.points) - warp(np.asarray(source.points, float))).max() <= 1e-4


def test_ply_colours_it_cannot_hold_are_named_in_a_warning(saved, tmp_path, capsys):
    """Vertex colours with alpha and face colours without: a PLY writer holds one colour array by name."""
    d, _ = saved
    points = [[20, 20, 20], [40, 20, 20], [20, 40, 20], [20, 20, 40]]
    rows = [f"{x} {y} {z} 10 20 30 40" for x, y, z in points]
    (tmp_path / "in.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n"
        "element face 2\nproperty list uchar int vertex_indices\nproperty uchar red\nproperty uchar green\n"
        "property uchar blue\nend_header\n" + "\n".join(rows) + "\n3 0 1 2 200 0 0\n3 0 1 3 0 200 0\n")
    source = pv.read(str(tmp_path / "in.ply"))
    assert "RGBA" in source.point_data.keys() and "RGB" in source.cell_data.keys()
    assert apply(d / "model.npz", tmp_path / "in.ply", "--from", "fixed", "-o", tmp_path / "out.ply") == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(lines) == 1 and "cell array `RGB`" in lines[0] and "in.ply" in lines[0], lines
    out = pv.read(str(tmp_path / "out.ply"))
    assert np.array_equal(np.asarray(out.point_data["RGBA"]), np.tile([10, 20, 30, 40], (4, 1)))


def test_quad_mesh_keeps_quads(saved, tmp_path):
    d, warp = saved
    pv.Plane(center=(30, 30, 30), i_resolution=5, j_resolution=4, i_size=20, j_size=20).save(str(tmp_path / "q.vtk"))
    source = pv.read(str(tmp_path / "q.vtk"))
    assert apply(d / "model.npz", tmp_path / "q.vtk", "--from", "fixed", "-o", tmp_path / "o.vtk") == 0
    out = pv.read(str(tmp_path / "o.vtk"))
    assert np.array_equal(np.asarray(out.faces), np.asarray(source.faces)) and out.n_cells == 20
    assert np.abs(np.asarray(out.points) - warp(np.asarray(source.points, float))).max() <= 1e-4


def test_gifti_surface_from_moving(saved, tmp_path):
    """Stored RAS, read as LPS, carried to fixed space by the model's inverse, written RAS with its metadata."""
    d, warp = saved
    sphere = smooth_sphere()
    lps = np.asarray(sphere.points, float)
    tri = np.asarray(sphere.faces).reshape(-1, 4)[:, 1:]
    img = nib.gifti.GiftiImage(darrays=[
        nib.gifti.GiftiDataArray((lps * FLIP).astype(np.float32), intent="NIFTI_INTENT_POINTSET",
                                 datatype="NIFTI_TYPE_FLOAT32", meta={"AnatomicalStructurePrimary": "CortexLeft"}),
        nib.gifti.GiftiDataArray(tri.astype(np.int32), intent="NIFTI_INTENT_TRIANGLE", datatype="NIFTI_TYPE_INT32")])
    nib.save(img, str(tmp_path / "in.surf.gii"))
    assert apply(d / "model.npz", tmp_path / "in.surf.gii", "--from", "moving", "-o", tmp_path / "out.surf.gii") == 0
    out = nib.load(str(tmp_path / "out.surf.gii"))
    assert np.array_equal(out.agg_data("triangle"), tri)
    assert out.darrays[0].meta["AnatomicalStructurePrimary"] == "CortexLeft"
    x = out.agg_data("pointset").astype(float) * FLIP
    stored = np.asarray(img.darrays[0].data, float) * FLIP
    assert np.abs(warp(x) - stored).max() <= 1e-4


# ----------------------------------------------------------------------------- refusals


@pytest.mark.parametrize("case, words", [
    ("points without --from", ["--from is required", "--from fixed", "--from moving"]),
    ("image with --from", ["--from is for landmarks and meshes", "drop --from"]),
    ("points with --reference", ["--reference is for images"]),
    ("unsupported suffix", ["points.xyz", "unsupported suffix", ".csv", ".vtk"]),
    ("image without --reference", ["--reference is required"]),
    ("output in another format", ["out.fcsv", "suffix of `in.csv`"]),
])
def test_refusals_are_one_line_with_status_2(saved, tmp_path, capsys, case, words):
    d, _ = saved
    write_csv(tmp_path / "in.csv", fixed_points(3))
    (tmp_path / "points.xyz").write_text("1 2 3\n")
    image = tmp_path / "image.nii.gz"
    sitk.WriteImage(sitk.Image(4, 4, 4, sitk.sitkUInt8), str(image))
    t = str(tmp_path)
    args = {
        "points without --from": [f"{t}/in.csv", "-o", f"{t}/out.csv"],
        "image with --from": [f"{t}/image.nii.gz", "--reference", f"{t}/image.nii.gz", "--from", "fixed",
                              "-o", f"{t}/out.nii.gz"],
        "points with --reference": [f"{t}/in.csv", "--from", "fixed", "--reference", f"{t}/image.nii.gz",
                                    "-o", f"{t}/out.csv"],
        "unsupported suffix": [f"{t}/points.xyz", "--from", "fixed", "-o", f"{t}/out.xyz"],
        "image without --reference": [f"{t}/image.nii.gz", "-o", f"{t}/out.nii.gz"],
        "output in another format": [f"{t}/in.csv", "--from", "fixed", "-o", f"{t}/out.fcsv"],
    }[case]
    before = sorted(p.name for p in tmp_path.iterdir())
    assert apply(d / "model.npz", *args) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("volreg apply: error: "), err
    for w in words:
        assert w in err, (w, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_existing_output_is_kept_without_force(saved, tmp_path, capsys):
    d, warp = saved
    write_csv(tmp_path / "in.csv", fixed_points(3))
    (tmp_path / "out.csv").write_text("keep")
    assert apply(d / "model.npz", tmp_path / "in.csv", "--from", "fixed", "-o", tmp_path / "out.csv") == 2
    assert "--force" in capsys.readouterr().err and (tmp_path / "out.csv").read_text() == "keep"
    assert apply(d / "model.npz", tmp_path / "in.csv", "--from", "fixed", "-o", tmp_path / "out.csv", "--force") == 0
    assert np.abs(read_landmarks(tmp_path / "out.csv") - warp(fixed_points(3))).max() <= 1e-6


# ----------------------------------------------------------------------------- agreement with ANTs


def test_agrees_with_ants_apply_transforms_to_points(saved, tmp_path):
    """ANTs maps points with a transform in the sense it maps images' sample points: `-t warp.nii.gz`
    (whichtoinvert False) takes fixed points to moving space, as `--from fixed` with warp.nii.gz, and
    `-t inverse_warp.nii.gz` moving points to fixed space, as `--from moving` with it; LPS mm both."""
    ants = pytest.importorskip("ants")
    pd = pytest.importorskip("pandas")
    d, warp = saved
    x = fixed_points(40)
    for field, space, pts in (("warp.nii.gz", "fixed", x), ("inverse_warp.nii.gz", "moving", warp(x))):
        write_csv(tmp_path / "in.csv", pts)
        assert apply(d / field, tmp_path / "in.csv", "--from", space, "-o", tmp_path / f"{space}.csv") == 0
        ours = read_landmarks(tmp_path / f"{space}.csv")
        frame = pd.DataFrame({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]})
        theirs = ants.apply_transforms_to_points(3, frame, [str(d / field)], whichtoinvert=[False])
        theirs = theirs[["x", "y", "z"]].to_numpy(float)
        assert np.abs(ours - theirs).max() <= 0.01, (field, np.abs(ours - theirs).max())
        assert np.abs(ours - pts).max() > 1.0  # the points did move
