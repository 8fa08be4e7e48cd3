"""GIFTI surfaces and data files through ``register-surfaces``, ``morph``, ``transfer`` and ``surface``.

The pair is an ellipsoid off the midline (like one hemisphere's structure) and its image under a
known smooth deformation, written with nibabel in RAS as FreeSurfer and Workbench write them, with a
``.shape.gii`` (a smooth scalar) and a ``.label.gii`` (two labels and a label table).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import pyvista as pv
from nibabel.gifti import GiftiDataArray, GiftiImage, GiftiLabel, GiftiLabelTable, GiftiMetaData

from volreg.cli import main
from volreg.io.meshes import read_surface
from volreg.synthetic import GaussianBumps

RAS = np.array([-1.0, -1.0, 1.0])  # LPS <-> RAS, per point
CENTRE_LPS = np.array([30.0, 10.0, 15.0])  # RAS (-30, -10, 15): left of the midline
RADII = np.array([16.0, 22.0, 18.0])
PROTOCOL = "[protocol]\nname = \"gifti-test\"\n[warp]\nmin_width = 8.0\n"
#: A smooth deformation in LPS mm, up to about 3 mm.
TRUTH = GaussianBumps(CENTRE_LPS + np.array([[12.0, 0, 8], [-8, 10, -4]]),
                      np.array([[3.0, 0.0, 1.0], [-1.0, 2.0, 0.0]]), 12.0)
FILE_META = {"AnatomicalStructurePrimary": "CortexLeft", "UserName": "volreg-test"}
POINTSET_META = {"AnatomicalStructurePrimary": "CortexLeft", "AnatomicalStructureSecondary": "GrayWhite",
                 "GeometricType": "Anatomical"}
TABLE = {0: ("???", (0.0, 0.0, 0.0, 0.0)), 3: ("lateral", (1.0, 0.0, 0.0, 1.0)), 10: ("medial", (0.0, 0.0, 1.0, 1.0))}
XFORM = np.array([[1.0, 0, 0, 2], [0, 1, 0, -3], [0, 0, 1, 4], [0, 0, 0, 1]])


def run(args) -> int:
    return main([str(a) for a in args])


def scalar(p_lps: np.ndarray) -> np.ndarray:
    """A smooth per-vertex quantity of a point (LPS mm), not symmetric about the ellipsoid's centre."""
    q = (p_lps - CENTRE_LPS) / RADII
    return 2.0 + q[:, 0] + 0.5 * q[:, 2] ** 2 + 0.3 * np.sin(2.0 * q[:, 1])


def labels(p_lps: np.ndarray) -> np.ndarray:
    """3 on the lateral half of the ellipsoid (LPS x beyond the centre), 10 on the medial half."""
    return np.where(p_lps[:, 0] > CENTRE_LPS[0], 3, 10).astype(np.int32)


def write_surface(path: Path, v_lps: np.ndarray, faces: np.ndarray) -> None:
    coordsys = nib.gifti.GiftiCoordSystem(1, 3, XFORM)
    darrays = [GiftiDataArray((v_lps * RAS).astype(np.float32), intent="NIFTI_INTENT_POINTSET",
                              datatype="NIFTI_TYPE_FLOAT32", coordsys=coordsys, meta=GiftiMetaData(POINTSET_META)),
               GiftiDataArray(faces.astype(np.int32),
                              intent="NIFTI_INTENT_TRIANGLE", datatype="NIFTI_TYPE_INT32",
                              meta=GiftiMetaData({"TopologicalType": "Closed"}))]
    nib.save(GiftiImage(meta=GiftiMetaData(FILE_META), darrays=darrays), str(path))


def write_shape(path: Path, values: np.ndarray) -> None:
    da = GiftiDataArray(values.astype(np.float32), intent="NIFTI_INTENT_SHAPE", datatype="NIFTI_TYPE_FLOAT32",
                        meta=GiftiMetaData({"Name": "thickness"}))
    nib.save(GiftiImage(meta=GiftiMetaData({"AnatomicalStructurePrimary": "CortexRight"}), darrays=[da]), str(path))


def write_label(path: Path, values: np.ndarray) -> None:
    table = GiftiLabelTable()
    for key, (name, rgba) in TABLE.items():
        lab = GiftiLabel(key, *rgba)
        lab.label = name
        table.labels.append(lab)
    da = GiftiDataArray(values.astype(np.int32), intent="NIFTI_INTENT_LABEL", datatype="NIFTI_TYPE_INT32",
                        meta=GiftiMetaData({"Name": "halves"}))
    nib.save(GiftiImage(meta=GiftiMetaData({"AnatomicalStructurePrimary": "CortexRight"}), labeltable=table,
                        darrays=[da]), str(path))


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """SOURCE (src.surf.gii) and TARGET = TRUTH(SOURCE) (tgt.surf.gii) in RAS, data files, one registration."""
    d = tmp_path_factory.mktemp("gifti")
    sphere = pv.Sphere(radius=1.0, theta_resolution=36, phi_resolution=36)
    v = np.array(sphere.points, float) * RADII + CENTRE_LPS
    faces = np.asarray(sphere.faces).reshape(-1, 4)[:, 1:]
    t = TRUTH(v)
    write_surface(d / "src.surf.gii", v, faces)
    write_surface(d / "tgt.surf.gii", t, faces)
    write_shape(d / "tgt.thick.shape.gii", scalar(t))
    write_shape(d / "src.thick.shape.gii", scalar(v))
    write_label(d / "tgt.halves.label.gii", labels(t))
    (d / "p.toml").write_text(PROTOCOL)
    assert run(["register-surfaces", d / "src.surf.gii", d / "tgt.surf.gii", "-o", d / "out", "--protocol", d / "p.toml",
                "--source-data", d / "src.thick.shape.gii", "--quiet"]) == 0
    return d, v, t, faces


def test_register_surfaces_writes_gifti_in_ras(pair):
    d, v, _, faces = pair
    assert sorted(p.name for p in (d / "out").iterdir()) == ["correspondence.csv", "model.npz", "report.json",
                                                           "warped.surf.gii", "warped.vtk"]
    vtk = pv.read(d / "out" / "warped.vtk")
    gii = nib.load(str(d / "out" / "warped.surf.gii"))
    ras = gii.agg_data("pointset")
    # the same points: RAS is LPS with x and y negated (exactly, in float32)
    assert ras.dtype == np.float32 and np.array_equal(ras, (np.array(vtk.points, float) * RAS).astype(np.float32))
    assert np.array_equal(gii.agg_data("triangle"), faces)
    # the warp moved the points (they are not the source's)
    assert np.abs(ras - (v * RAS).astype(np.float32)).max() > 1.0
    # metadata and coordinate system kept
    assert dict(gii.meta) == FILE_META
    pointset = gii.darrays[0]
    assert dict(pointset.meta) == POINTSET_META
    assert (pointset.coordsys.dataspace, pointset.coordsys.xformspace) == (1, 3)
    assert np.array_equal(pointset.coordsys.xform, XFORM)
    assert dict(gii.darrays[1].meta) == {"TopologicalType": "Closed"}
    # the source's data file is carried into the VTK output as a point array
    assert np.allclose(vtk.point_data["src.thick"], scalar(v), atol=1e-5)
    report = json.loads((d / "out" / "report.json").read_text())
    assert report["frames"] == {"warped.vtk": "LPS mm", "correspondence.csv": "LPS mm", "warped.surf.gii": "RAS mm"}
    assert report["review"]["plausible"] and report["distance_to_target_mm"]["median"] < 0.2


def test_read_surface_converts_ras_to_lps(pair):
    d, v, _, faces = pair
    back = read_surface(d / "src.surf.gii")
    assert np.allclose(back.vertices, v, atol=1e-5) and np.array_equal(back.triangles, faces)
    assert back.gifti.structure() == {"AnatomicalStructurePrimary": "CortexLeft",
                                      "AnatomicalStructureSecondary": "GrayWhite"}


def test_transfer_shape_and_label_files(pair, tmp_path, capsys):
    d, v, t, _ = pair
    out = tmp_path / "src.thick.shape.gii"
    assert run(["transfer", d / "src.surf.gii", d / "tgt.surf.gii", "--result", d / "out",
                "--target-data", d / "tgt.thick.shape.gii", "-o", out]) == 0
    assert "warning" not in capsys.readouterr().err
    img = nib.load(str(out))
    got = img.agg_data()
    truth = scalar(t)  # the target's value at each source vertex's true partner
    assert got.shape == (len(v),) and np.corrcoef(got, truth)[0, 1] > 0.9  # measured 0.999
    assert np.abs(got - truth).mean() < 0.05 * np.ptp(truth)
    # the data array's metadata is kept; the file's structure is now the source surface's
    assert dict(img.darrays[0].meta) == {"Name": "thickness"}
    assert img.darrays[0].intent == nib.nifti1.intent_codes["NIFTI_INTENT_SHAPE"]
    assert dict(img.meta) == {"AnatomicalStructurePrimary": "CortexLeft",
                              "AnatomicalStructureSecondary": "GrayWhite"}

    lab = tmp_path / "src.halves.label.gii"
    assert run(["transfer", d / "src.surf.gii", d / "tgt.surf.gii", "--result", d / "out", "--target-data",
                d / "tgt.halves.label.gii", d / "tgt.thick.shape.gii", "--array", "tgt.halves", "-o", lab]) == 0
    assert "(nearest)" in capsys.readouterr().out  # labels: the nearest vertex, whatever --method says
    img = nib.load(str(lab))
    keys = img.agg_data()
    assert keys.dtype.kind == "i" and set(np.unique(keys).tolist()) <= set(TABLE)
    assert {lab.key: lab.label for lab in img.labeltable.labels} == {k: name for k, (name, _) in TABLE.items()}
    assert np.mean(keys == labels(t)) > 0.97  # the labels of the true partners
    assert img.darrays[0].intent == nib.nifti1.intent_codes["NIFTI_INTENT_LABEL"]

    vtk = tmp_path / "src.vtk"  # the mesh output holds every source array and the transferred one (LPS)
    assert run(["transfer", d / "src.surf.gii", d / "tgt.surf.gii", "--result", d / "out", "--target-data",
                d / "tgt.thick.shape.gii", "--source-data", d / "src.thick.shape.gii", "-o", vtk]) == 0
    mesh = pv.read(vtk)
    assert set(mesh.point_data.keys()) >= {"tgt.thick", "src.thick"}
    assert np.allclose(np.array(mesh.points), v, atol=1e-5)


def test_transfer_warns_on_a_mirrored_source(pair, tmp_path, capsys):
    """The RAS coordinates of the GIFTI source in a VTK file (read as LPS): mirrored, far from the target."""
    d, v, t, faces = pair
    mirrored = pv.PolyData((v * RAS).astype(np.float32), faces=np.column_stack([np.full(len(faces), 3), faces]).ravel())
    mirrored.save(tmp_path / "src_ras.vtk")
    out = tmp_path / "bad.shape.gii"
    assert run(["transfer", tmp_path / "src_ras.vtk", d / "tgt.surf.gii", "--result", d / "out",
                "--target-data", d / "tgt.thick.shape.gii", "-o", out]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("volreg transfer: warning: ") and "different frames" in err[0]
    assert np.corrcoef(nib.load(str(out)).agg_data(), scalar(t))[0, 1] < 0.9  # the values are indeed wrong


def test_register_surfaces_warns_on_a_mirrored_source_the_centroids_carry_onto_the_target(pair, tmp_path, capsys):
    """The RAS coordinates of the GIFTI source in a VTK file (read as LPS): the centroids'
    translation (98 % of its diameter) puts the mirrored surface on the target, where no distance
    shows it (a median 0.03 mm) while its points are 26 mm from their partners.  The translation
    is the sign: register-surfaces and a transfer through its result warn, naming the frames."""
    d, v, t, faces = pair
    mirrored = pv.PolyData((v * RAS).astype(np.float32), faces=np.column_stack([np.full(len(faces), 3), faces]).ravel())
    mirrored.save(tmp_path / "src_ras.vtk")
    assert run(["register-surfaces", tmp_path / "src_ras.vtk", d / "tgt.surf.gii", "-o", tmp_path / "out",
                "--protocol", d / "p.toml", "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("volreg register-surfaces: warning: ") and "RAS against LPS" in err[0]
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert [f["figure"] for f in report["review"]["findings"]] == ["translation_fraction"]
    assert report["review"]["findings"][0]["value"] > 0.9
    assert run(["transfer", tmp_path / "src_ras.vtk", d / "tgt.surf.gii", "--result", tmp_path / "out",
                "--target-data", d / "tgt.thick.shape.gii", "-o", tmp_path / "bad.shape.gii"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("volreg transfer: warning: ") and "RAS against LPS" in err[0]


def test_transfer_warns_on_metres(pair, tmp_path, capsys):
    d, v, t, faces = pair
    write_surface(tmp_path / "src_m.surf.gii", v / 1000.0, faces)
    assert run(["transfer", tmp_path / "src_m.surf.gii", d / "tgt.surf.gii", "--result", d / "out",
                "--target-data", d / "tgt.thick.shape.gii", "-o", tmp_path / "m.shape.gii"]) == 0
    err = capsys.readouterr().err
    ratio = float(re.search(r"a ratio of ([0-9.e+]+)", err).group(1))
    expected = np.linalg.norm(np.ptp(t, axis=0)) / np.linalg.norm(np.ptp(v / 1000.0, axis=0))  # about 1000
    assert "millimetres" in err and ratio == pytest.approx(expected, rel=0.01)


def test_morph_writes_gifti_frames(pair, tmp_path):
    d, v, _, _ = pair
    assert run(["morph", d / "src.surf.gii", d / "tgt.surf.gii", "-o", tmp_path / "m", "--frames", "3", "--from-result",
                d / "out", "--source-data", d / "src.thick.shape.gii", "--target-data", d / "tgt.thick.shape.gii",
                "--quiet"]) == 0
    # the arrays are matched by name: "src.thick" and "tgt.thick" differ, so none is carried
    names = sorted(p.name for p in (tmp_path / "m").iterdir())
    assert names == sorted([f"frame_{k:03d}.{e}" for k in range(3) for e in ("vtk", "png", "surf.gii")] + ["morph.gif"])
    for k in range(3):
        vtk = pv.read(tmp_path / "m" / f"frame_{k:03d}.vtk")
        gii = nib.load(str(tmp_path / "m" / f"frame_{k:03d}.surf.gii"))
        assert np.array_equal(gii.agg_data("pointset"), (np.array(vtk.points, float) * RAS).astype(np.float32))
        assert dict(gii.darrays[0].meta) == POINTSET_META
    assert np.allclose(nib.load(str(tmp_path / "m" / "frame_000.surf.gii")).agg_data("pointset"), v * RAS, atol=1e-4)


def test_morph_gifti_label_frames(pair, tmp_path):
    """An array both carry under one name: labels switch half-way and keep their table."""
    d, v, t, _ = pair
    (tmp_path / "s").mkdir()
    (tmp_path / "t").mkdir()
    write_label(tmp_path / "s" / "halves.label.gii", labels(v))
    write_label(tmp_path / "t" / "halves.label.gii", labels(t))
    assert run(["morph", d / "src.surf.gii", d / "tgt.surf.gii", "-o", tmp_path / "m", "--frames", "3", "--from-result",
                d / "out", "--source-data", tmp_path / "s" / "halves.label.gii", "--target-data",
                tmp_path / "t" / "halves.label.gii", "--quiet"]) == 0
    for k in range(3):
        img = nib.load(str(tmp_path / "m" / f"frame_{k:03d}.halves.label.gii"))
        assert set(np.unique(img.agg_data()).tolist()) <= set(TABLE) and len(img.labeltable.labels) == len(TABLE)
    assert np.array_equal(nib.load(str(tmp_path / "m" / "frame_000.halves.label.gii")).agg_data(), labels(v))


def test_gifti_on_request(pair, tmp_path):
    """--gifti writes warped.surf.gii for a VTK source: RAS, no metadata."""
    d, v, _, faces = pair
    pv.PolyData(v, faces=np.column_stack([np.full(len(faces), 3), faces]).ravel()).save(tmp_path / "src.vtk")
    assert run(["morph", tmp_path / "src.vtk", d / "tgt.surf.gii", "-o", tmp_path / "m", "--frames", "2",
                "--from-result", d / "out", "--gifti", "--quiet"]) == 0
    gii = nib.load(str(tmp_path / "m" / "frame_000.surf.gii"))
    assert np.allclose(gii.agg_data("pointset"), v * RAS, atol=1e-4) and dict(gii.meta) == {}


def test_surface_command_gifti(tmp_path):
    from volreg.io import write_labels
    from volreg.grid import LabelVolume

    arr = np.zeros((20, 18, 16), np.uint8)
    arr[5:14, 4:12, 5:11] = 2
    direction = np.diag([-1.0, 1.0, 1.0])  # a flipped axis: the NIfTI affine is then not diagonal-positive
    write_labels(LabelVolume(arr, np.array([-10.0, 5.0, 2.0]), np.array([1.0, 1.5, 2.0]), direction),
                 tmp_path / "lab.nii.gz")
    assert run(["surface", tmp_path / "lab.nii.gz", "-o", tmp_path / "s", "--gifti", "--quiet"]) == 0
    vtk = pv.read(tmp_path / "s" / "label_2.vtk")
    gii = nib.load(str(tmp_path / "s" / "label_2.surf.gii"))
    assert np.array_equal(gii.agg_data("pointset"), (np.array(vtk.points, float) * RAS).astype(np.float32))
    assert np.array_equal(gii.agg_data("triangle"), np.asarray(vtk.faces).reshape(-1, 4)[:, 1:])
    # the label box in RAS from the NIfTI affine: the mesh lies around it
    affine = nib.load(str(tmp_path / "lab.nii.gz")).affine
    box = nib.affines.apply_affine(affine, np.argwhere(arr == 2))
    ras = gii.agg_data("pointset")
    assert np.all(ras.min(axis=0) >= box.min(axis=0) - 2.0) and np.all(ras.max(axis=0) <= box.max(axis=0) + 2.0)


def test_refusals(pair, tmp_path, capsys):
    d, v, _, faces = pair
    write_shape(tmp_path / "short.shape.gii", np.zeros(len(v) - 5))

    def refused(args, *words):
        out = tmp_path / "out"
        assert run(args + ["-o", out]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "error:" in err and all(w in err for w in words), err
        assert not out.exists()

    refused(["register-surfaces", d / "src.surf.gii", d / "tgt.surf.gii", "--source-data", tmp_path / "short.shape.gii"],
            "short.shape.gii", f"expected {len(v)} values")
    refused(["register-surfaces", d / "tgt.thick.shape.gii", d / "tgt.surf.gii"], "tgt.thick.shape.gii", "no POINTSET")
    refused(["morph", d / "src.surf.gii", d / "tgt.surf.gii", "--target-data", d / "tgt.surf.gii"],
            "tgt.surf.gii", "is a GIFTI surface")
    refused(["transfer", d / "src.surf.gii", d / "tgt.surf.gii", "--result", d / "out", "--target-data",
             d / "tgt.thick.shape.gii", d / "tgt.halves.label.gii"], "--array", "tgt.halves, tgt.thick")
    assert run(["transfer", d / "src.surf.gii", d / "tgt.surf.gii", "--result", d / "out", "--target-data",
                d / "tgt.thick.shape.gii", "-o", tmp_path / "x.surf.gii"]) == 2
    assert "GIFTI surface" in capsys.readouterr().err and not (tmp_path / "x.surf.gii").exists()
