"""Reliability of files: headers whose data lie elsewhere, headers that disagree with their data or
declare more than the file holds, messages for unreadable and odd files, and batch folders.

Every hostile case ends in a correct result or a one-line error (exit status 2) naming the file
or argument and what was expected, with nothing written."""

from __future__ import annotations

import builtins
import gzip
import io
import json
import os
import re
import signal
import struct
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import pyvista as pv

from volreg.cli import main
from volreg.io import VolregIOError, read_labels, read_mesh, write_labels
from volreg.io.landmarks import read_landmarks
from volreg.warp.model import KernelWarp
from helpers import cube as _cube, write_nifti as _nifti

REPO = Path(__file__).resolve().parent.parent

#: A 4 x 4 x 4 MetaImage/NRRD payload: a 2 x 2 x 2 cube of label 1 (x fastest, as both formats store it).
CUBE = np.zeros((4, 4, 4), np.uint8)
CUBE[1:3, 1:3, 1:3] = 1
MHD = ("ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\nElementType = MET_UCHAR\nElementSpacing = 1 1 1\n"
       "ElementDataFile = {}\n")
NHDR = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\nspacings: 1 1 1\ndata file: {}\n"



def _patch_dim(path: Path, index: int, value: int) -> Path:
    """Overwrite dim[index] of a stored NIfTI-1 header (int16 at byte 40 + 2 index)."""
    gz = path.name.endswith(".gz")
    raw = bytearray(gzip.decompress(path.read_bytes()) if gz else path.read_bytes())
    raw[40 + 2 * index: 42 + 2 * index] = np.int16(value).tobytes()
    path.write_bytes(gzip.compress(bytes(raw)) if gz else bytes(raw))
    return path



def _npy_header(shape, descr="<f8") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def _vtp(points: int) -> str:
    return ('<?xml version="1.0"?>\n<VTKFile type="PolyData" version="0.1" byte_order="LittleEndian">\n<PolyData>\n'
            f'<Piece NumberOfPoints="{points}" NumberOfVerts="0" NumberOfLines="0" NumberOfStrips="0" '
            'NumberOfPolys="0">\n<Points><DataArray type="Float32" NumberOfComponents="3" format="ascii">0 0 0'
            '</DataArray></Points></Piece></PolyData></VTKFile>\n')


def _vti(n: int) -> str:
    ext = f"0 {n - 1} 0 {n - 1} 0 {n - 1}"
    return ('<?xml version="1.0"?>\n<VTKFile type="ImageData" version="0.1" byte_order="LittleEndian">\n'
            f'<ImageData WholeExtent="{ext}" Origin="0 0 0" Spacing="1 1 1">\n<Piece Extent="{ext}">'
            '<PointData Scalars="l"><DataArray type="UInt8" Name="l" format="ascii">0 1 0</DataArray></PointData>'
            '</Piece></ImageData></VTKFile>\n')


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A good volume and mesh, and one hostile file per case."""
    top = tmp_path_factory.mktemp("files")
    d = top / "in"
    d.mkdir()
    f = {"dir": d}
    write_labels(_cube(), d / "good.nii.gz")
    f["good"] = d / "good.nii.gz"
    # data files outside the header's folder
    (top / "outside.raw").write_bytes(CUBE.tobytes())
    (d / "inside.raw").write_bytes(CUBE.tobytes())
    (d / "abs.mhd").write_text(MHD.format(top / "outside.raw"))
    (d / "up.mhd").write_text(MHD.format("../outside.raw"))
    (d / "sneaky.mhd").write_text(MHD.format("sub/../../outside.raw"))
    (d / "abs.nhdr").write_text(NHDR.format(top / "outside.raw"))
    (d / "up.nhdr").write_text(NHDR.format("../outside.raw"))
    for k in range(4):  # one file per z slice, the last one outside
        (top if k == 3 else d).joinpath(f"slice{k}.raw").write_bytes(CUBE[k].tobytes())
    names = "slice0.raw\nslice1.raw\nslice2.raw\n../slice3.raw\n"
    (d / "list.mhd").write_text(MHD.format("LIST 2D") + names)
    (d / "list.nhdr").write_text(NHDR.format("LIST 2") + names)
    (d / "few.mhd").write_text(MHD.format("LIST 2D") + "slice0.raw\nslice1.raw\n")
    (d / "few.nhdr").write_text(NHDR.format("LIST") + "slice0.raw\nslice1.raw\nslice2.raw\n")
    for name in ("abs_mhd", "up_mhd", "sneaky_mhd", "abs_nhdr", "up_nhdr", "list_mhd", "list_nhdr", "few_mhd",
                 "few_nhdr"):
        stem, suffix = name.rsplit("_", 1)
        f[name] = d / f"{stem}.{suffix}"
    (top / "outside_warp.raw").write_bytes(np.zeros((4, 4, 4, 3), np.float32).tobytes())
    (d / "warp.mhd").write_text(MHD.replace("MET_UCHAR", "MET_FLOAT\nElementNumberOfChannels = 3")
                                .format("../outside_warp.raw"))
    f["warp_up"] = d / "warp.mhd"
    (d / "warp_short.mha").write_bytes(MHD.replace("MET_UCHAR", "MET_FLOAT\nElementNumberOfChannels = 3")
                                       .format("LOCAL").encode() + b"\0" * 500)
    f["warp_short"] = d / "warp_short.mha"
    # NIfTI dim fields
    f["dim0_2"] = _patch_dim(_nifti(d / "dim0_2.nii", _cube().array), 0, 2)
    f["dim0_0"] = _patch_dim(_nifti(d / "dim0_0.nii.gz", _cube().array), 0, 0)
    f["dim_zero"] = _patch_dim(_nifti(d / "dim_zero.nii", _cube().array), 2, 0)
    f["dim_negative"] = _patch_dim(_nifti(d / "dim_negative.nii.gz", _cube().array), 3, -3)
    f["dim_short"] = _patch_dim(_nifti(d / "dim_short.nii", _cube().array), 3, 4)
    # image headers declaring more than the file holds
    (d / "huge.mha").write_bytes(MHD.replace("4 4 4", "2000 2000 2000").format("LOCAL").encode() + b"\0" * 64)
    f["huge_mha"] = d / "huge.mha"
    (d / "huge.nrrd").write_bytes(NHDR.replace("4 4 4", "2000 2000 2000").replace("data file: {}\n", "\n").encode()
                                  + b"\0" * 64)
    f["huge_nrrd"] = d / "huge.nrrd"
    (d / "huge.vti").write_text(_vti(3000))
    f["huge_vti"] = d / "huge.vti"
    (d / "mid.vti").write_text(_vti(200))
    f["mid_vti"] = d / "mid.vti"
    # missing or truncated data files: ITK would print several lines and blame the header
    (d / "missing.mhd").write_text(MHD.format("nothere.raw"))
    f["missing_data"] = d / "missing.mhd"
    (d / "local_trunc.mha").write_bytes(MHD.format("LOCAL").encode() + CUBE.tobytes()[:10])
    f["truncated_mha"] = d / "local_trunc.mha"
    (d / "short.raw").write_bytes(CUBE.tobytes()[:40])
    (d / "short.nhdr").write_text(NHDR.format("short.raw"))
    f["truncated_nhdr"] = d / "short.nhdr"
    # saved models
    with zipfile.ZipFile(d / "shape.npz", "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("centres_0.npy", _npy_header((100_000_000_000, 3)) + b"\0" * 48)
    f["model_shape"] = d / "shape.npz"
    with zipfile.ZipFile(d / "lie.npz", "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("centres_0.npy", b"\0" * 100_000)
    raw = bytearray((d / "lie.npz").read_bytes())
    for signature, offset in ((b"PK\x03\x04", 22), (b"PK\x01\x02", 24)):  # uncompressed size, local and central
        at = raw.find(signature)
        raw[at + offset: at + offset + 4] = struct.pack("<I", 3_000_000_000)
    (d / "lie.npz").write_bytes(bytes(raw))
    f["model_inflates"] = d / "lie.npz"
    return f


def _outputs(outdir: Path) -> list[str]:
    return sorted(p.name for p in outdir.rglob("*")) if outdir.exists() else []


# (id, command line with {names} of `files` and {out}, words the one-line message must contain)
CASES = [
    ("MetaImage data at an absolute path", "surface {abs_mhd} -o {out}",
     ["abs.mhd", "outside.raw", "an absolute path", "VOLREG_ALLOW_EXTERNAL_DATA=1"]),
    ("MetaImage data up a folder", "surface {up_mhd} -o {out}", ["up.mhd", "climbs out", "VOLREG_ALLOW_EXTERNAL_DATA"]),
    ("MetaImage data up through a subfolder", "surface {sneaky_mhd} -o {out}", ["sneaky.mhd", "climbs out"]),
    ("NRRD data at an absolute path", "surface {abs_nhdr} -o {out}", ["abs.nhdr", "an absolute path"]),
    ("NRRD data up a folder", "register {up_nhdr} {good} -o {out}", ["up.nhdr", "climbs out"]),
    ("MetaImage LIST with a file outside", "surface {list_mhd} -o {out}", ["list.mhd", "../slice3.raw", "climbs out"]),
    ("NRRD LIST with a file outside", "surface {list_nhdr} -o {out}", ["list.nhdr", "../slice3.raw", "climbs out"]),
    ("MetaImage LIST of too few slices", "surface {few_mhd} -o {out}", ["few.mhd", "lists 2 data files", "expected 4"]),
    ("NRRD LIST of too few slices", "surface {few_nhdr} -o {out}", ["few.nhdr", "lists 3 data files", "expected 4"]),
    ("NIfTI dim[0] below the data's axes", "surface {dim0_2} -o {out}", ["dim0_2.nii", "dim[0] = 2", "dim[3] = 16"]),
    ("NIfTI dim[0] of 0", "register {dim0_0} {good} -o {out}", ["dim0_0.nii.gz", "dim[0] = 0", "1 to 7"]),
    ("NIfTI zero axis size", "surface {dim_zero} -o {out}", ["dim_zero.nii", "[16, 0, 16]", "at least 1"]),
    ("NIfTI negative axis size", "surface {dim_negative} -o {out}", ["dim_negative.nii.gz", "-3", "at least 1"]),
    ("NIfTI axis shorter than the data", "surface {dim_short} -o {out}",
     ["dim_short.nii", "beyond the shape (16, 16, 4)", "dim field"]),
    ("MetaImage declaring 2000^3 over 64 bytes", "surface {huge_mha} -o {out}",
     ["huge.mha", "2000 x 2000 x 2000", "holds 64"]),
    ("NRRD declaring 2000^3 over 64 bytes", "surface {huge_nrrd} -o {out}", ["huge.nrrd", "2000 x 2000 x 2000", "holds 64"]),
    (".vti extent of 3000^3", "surface {huge_vti} -o {out}", ["huge.vti", "3000 x 3000 x 3000", "GB in memory"]),
    (".vti extent of 200^3 in a few bytes", "surface {mid_vti} -o {out}", ["mid.vti", "200 x 200 x 200", "holds"]),
    ("MetaImage data file missing", "register {missing_data} {good} -o {out}",
     ["missing.mhd", "nothere.raw", "does not exist"]),
    ("MetaImage local data truncated", "surface {truncated_mha} -o {out}", ["local_trunc.mha", "at least 64 bytes", "holds 10"]),
    ("NRRD data file truncated", "surface {truncated_nhdr} -o {out}", ["short.nhdr", "short.raw", "holds 40"]),
    ("model member of shape (1e11, 3)", "apply {model_shape} {good} --reference {good} -o {out}/x.nii.gz",
     ["shape.npz", "centres_0.npy", "(100000000000, 3)"]),
    ("model member inflating 3 GB from bytes", "apply {model_inflates} {good} --reference {good} -o {out}/x.nii.gz",
     ["lie.npz", "centres_0.npy", "3,000,000,000 bytes"]),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_hostile_file_refused(files, tmp_path, capfd, case):
    """One line on stderr (nothing from ITK or VTK either), exit status 2, nothing written."""
    _, line, words = case
    out = tmp_path / "out"
    assert main(line.format(out=out, **files).split()) == 2
    err = capfd.readouterr().err.strip()
    assert "\n" not in err and re.match(r"volreg \w[\w-]*: error: ", err), err
    for w in words:
        assert w in err, (w, err)
    assert _outputs(out) == []


def test_external_data_read_when_allowed(files, monkeypatch):
    """With VOLREG_ALLOW_EXTERNAL_DATA=1 the same headers read the right voxels (x fastest on disk)."""
    monkeypatch.setenv("VOLREG_ALLOW_EXTERNAL_DATA", "1")
    for name in ("abs_mhd", "up_nhdr", "list_mhd", "list_nhdr"):
        vol = read_labels(files[name])
        assert vol.shape == (4, 4, 4) and np.array_equal(vol.array, CUBE.T), name
    monkeypatch.setenv("VOLREG_ALLOW_EXTERNAL_DATA", "maybe")
    with pytest.raises(VolregIOError, match="VOLREG_ALLOW_EXTERNAL_DATA='maybe'; expected 1"):
        read_labels(files["abs_mhd"])


def test_displacement_field_headers(files, monkeypatch):
    """``read_displacement`` (the API; `volreg apply` takes NIfTI warps only) applies the same checks."""
    from volreg.io.fields import read_displacement

    with pytest.raises(VolregIOError, match=r"warp.mhd` names data file `../outside_warp.raw`, a path that climbs"):
        read_displacement(files["warp_up"])
    with pytest.raises(VolregIOError, match=r"warp_short.mha` declares .* at least 768 bytes .* holds 500"):
        read_displacement(files["warp_short"])
    monkeypatch.setenv("VOLREG_ALLOW_EXTERNAL_DATA", "1")
    u, grid = read_displacement(files["warp_up"])
    assert u.shape == (4, 4, 4, 3) and grid.shape == (4, 4, 4) and not u.any()


def test_data_beside_the_header_is_read(tmp_path):
    """The guard refuses nothing legitimate: data in the header's folder or a subfolder, and images
    SimpleITK writes itself (detached, attached, compressed)."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "d.raw").write_bytes(CUBE.tobytes())
    (tmp_path / "a.mhd").write_text(MHD.format("sub/d.raw"))
    (tmp_path / "b.nhdr").write_text(NHDR.format("./sub/d.raw"))
    for name in ("a.mhd", "b.nhdr"):
        assert np.array_equal(read_labels(tmp_path / name).array, CUBE.T), name
    vol = _cube()
    for name in ("c.mhd", "c.nhdr", "c.mha", "c.nrrd"):
        import SimpleITK as sitk

        img = sitk.GetImageFromArray(vol.array.T.copy())
        sitk.WriteImage(img, str(tmp_path / name), name.endswith(("a", "d")))  # compress the single-file ones
        assert np.array_equal(read_labels(tmp_path / name).array, vol.array), name


# ----------------------------------------------------------------------------- meshes


def _mesh_cases(d: Path) -> dict[str, Path]:
    m = {}
    (d / "big.ply").write_text("ply\nformat ascii 1.0\nelement vertex 10000000\nproperty float x\nproperty float y\n"
                               "property float z\nend_header\n0 0 0\n")
    m["ply ascii"] = d / "big.ply"
    (d / "bigb.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10000000\nproperty float x\n"
                                 b"property float y\nproperty float z\nend_header\n" + b"\0" * 30)
    m["ply binary"] = d / "bigb.ply"
    (d / "big.vtk").write_text("# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\nPOINTS 1000000000 float\n0 0 0\n")
    m["vtk 1e9 points"] = d / "big.vtk"
    (d / "bigbin.vtk").write_bytes(b"# vtk DataFile Version 3.0\nx\nBINARY\nDATASET POLYDATA\nPOINTS 3000000 float\n"
                                   + b"\0" * 40)
    m["vtk binary"] = d / "bigbin.vtk"
    (d / "big.stl").write_bytes(b"\0" * 80 + struct.pack("<I", 10_000_000) + b"\0" * 50)
    m["stl"] = d / "big.stl"
    (d / "big.vtp").write_text(_vtp(100_000_000))
    m["vtp"] = d / "big.vtp"
    (d / "big.gii").write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<GIFTI Version="1.0" NumberOfDataArrays="1">\n'
        '<DataArray Intent="NIFTI_INTENT_POINTSET" DataType="NIFTI_TYPE_FLOAT32" ArrayIndexingOrder="RowMajorOrder" '
        'Dimensionality="2" Dim0="100000000" Dim1="3" Encoding="ASCII" Endian="LittleEndian" ExternalFileName="" '
        'ExternalFileOffset=""><Data>0 0 0</Data></DataArray></GIFTI>\n')
    m["gifti"] = d / "big.gii"
    return m


MESH_CASES = ["ply ascii", "ply binary", "vtk 1e9 points", "vtk binary", "stl", "vtp", "gifti"]


@pytest.mark.parametrize("name", MESH_CASES)
def test_mesh_declaring_more_than_it_holds(tmp_path, capfd, name):
    """Refused from the header, at once (no allocation, no minutes of reading), in one line."""
    path = _mesh_cases(tmp_path)[name]
    pv.Sphere().save(str(tmp_path / "good.vtk"))
    out = tmp_path / "out"
    start = time.perf_counter()
    assert main(["register-surfaces", str(path), str(tmp_path / "good.vtk"), "-o", str(out)]) == 2
    assert time.perf_counter() - start < 20
    err = capfd.readouterr().err.strip()
    assert "\n" not in err and err.startswith("volreg register-surfaces: error: Surface ") and path.name in err, err
    assert "declares" in err and ("holds" in err or "GB in memory" in err), err
    assert _outputs(out) == []
    if path.suffix != ".gii":
        with pytest.raises(VolregIOError, match="declares"):
            read_mesh(path)


def test_meshes_pyvista_writes_are_read(tmp_path):
    """Every format the guard parses, as VTK writes it (binary and ASCII): read, same vertices."""
    sphere = pv.Sphere(theta_resolution=10, phi_resolution=10)
    for name, binary in (("a.vtk", True), ("b.vtk", False), ("a.ply", True), ("b.ply", False), ("a.stl", True),
                         ("a.vtp", True), ("b.vtp", False)):
        sphere.save(str(tmp_path / name), binary=binary)
        vertices, triangles, _ = read_mesh(tmp_path / name)
        assert len(triangles) == sphere.n_cells, name
        np.testing.assert_allclose(np.sort(vertices, axis=0), np.sort(np.asarray(sphere.points), axis=0), atol=1e-6)


def test_model_inflating_beyond_the_memory_limit(tmp_path, monkeypatch, capsys):
    """A genuine archive whose members inflate past VOLREG_MAX_IMAGE_GB is refused before inflating."""
    with zipfile.ZipFile(tmp_path / "zeros.npz", "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("centres_0.npy", _npy_header((1_000_000, 3)) + b"\0" * 24_000_000)
    assert (tmp_path / "zeros.npz").stat().st_size < 100_000
    monkeypatch.setenv("VOLREG_MAX_IMAGE_GB", "0.01")
    with pytest.raises(VolregIOError, match=r"zeros.npz` declares 1 members inflating to 24,000,128 bytes"):
        KernelWarp.load(tmp_path / "zeros.npz")


# ----------------------------------------------------------------------------- messages


@pytest.fixture
def unreadable(monkeypatch):
    """Make files unreadable to this process: chmod 000, or (as root, who reads everything) an
    ``open`` that answers them as the kernel would (PermissionError, errno 13)."""
    targets: set[str] = set()
    real_open = builtins.open

    def guarded_open(file, *args, **kwargs):
        if isinstance(file, (str, os.PathLike)) and os.path.abspath(os.fspath(file)) in targets:
            raise PermissionError(13, "Permission denied", os.fspath(file))
        return real_open(file, *args, **kwargs)

    def make(path: Path) -> Path:
        if os.geteuid() != 0:
            path.chmod(0)
        else:
            targets.add(os.path.abspath(path))
            monkeypatch.setattr(builtins, "open", guarded_open)
            monkeypatch.setattr(io, "open", guarded_open)
        return path

    return make


def test_unreadable_files_are_not_called_missing(tmp_path, unreadable, capsys):
    write_labels(_cube(), tmp_path / "good.nii.gz")
    write_labels(_cube(), tmp_path / "locked.nii.gz")
    pv.Sphere().save(str(tmp_path / "locked.vtk"))
    pv.Sphere().save(str(tmp_path / "good.vtk"))
    (tmp_path / "locked.csv").write_text("id,path\na,good.nii.gz\nb,good.nii.gz\n")
    cases = [
        (["surface", tmp_path / "locked.nii.gz", "-o", tmp_path / "o1"], "locked.nii.gz"),
        (["register-surfaces", tmp_path / "locked.vtk", tmp_path / "good.vtk", "-o", tmp_path / "o2"], "locked.vtk"),
    ]
    for path in (tmp_path / "locked.nii.gz", tmp_path / "locked.vtk", tmp_path / "locked.csv"):
        unreadable(path)
    for args, name in cases:
        assert main([str(a) for a in args]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and name in err and "not readable (permission denied)" in err, err
        assert "does not exist" not in err
    from volreg.cohort import read_manifest
    from volreg.errors import UsageError

    with pytest.raises(UsageError, match="locked.csv` is not readable"):
        read_manifest(tmp_path / "locked.csv")


def test_byte_order_mark_in_csv_headers(tmp_path):
    """Spreadsheet programs start UTF-8 CSV files with a byte-order mark: read as if it were not there."""
    from volreg.cohort import read_manifest

    bom = "\ufeff"
    (tmp_path / "m.csv").write_text(bom + "id,path\ns1,a.nii.gz\ns2,/abs/b.nii.gz\n", encoding="utf-8")
    assert read_manifest(tmp_path / "m.csv") == [("s1", tmp_path / "a.nii.gz"), ("s2", Path("/abs/b.nii.gz"))]
    (tmp_path / "l.csv").write_text(bom + "x,y,z\n1,2,3\n4.5,5,6\n", encoding="utf-8")
    np.testing.assert_array_equal(read_landmarks(tmp_path / "l.csv"), [[1, 2, 3], [4.5, 5, 6]])
    (tmp_path / "l.fcsv").write_text(bom + "# CoordinateSystem = LPS\nF-1,1,2,3\n", encoding="utf-8")
    np.testing.assert_array_equal(read_landmarks(tmp_path / "l.fcsv"), [[1, 2, 3]])
    doc = {"markups": [{"coordinateSystem": "RAS", "controlPoints": [{"position": [1, 2, 3]}]}]}
    (tmp_path / "l.mrk.json").write_text(bom + json.dumps(doc), encoding="utf-8")
    np.testing.assert_array_equal(read_landmarks(tmp_path / "l.mrk.json"), [[-1, -2, 3]])


def test_manifest_rows_as_users_write_them(tmp_path):
    """Line numbers count the blank lines a manifest holds; a quoted field may hold a line break
    (an id with one is refused: it names a folder, as one with a NUL byte), and a value holding
    U+2028 is one value (str.splitlines split the row there); `..` is named as a special folder
    and a header with spaces shows what was read."""
    from volreg.cohort import read_manifest
    from volreg.errors import UsageError

    def refused(text: str, words: str) -> None:
        (tmp_path / "m.csv").write_text(text, encoding="utf-8")
        with pytest.raises(UsageError, match=words):
            read_manifest(tmp_path / "m.csv")

    refused("id,path\ns1,a.nii.gz\n\n\n,\n", "line 5: expected an id and a path")
    refused('id,path\n"s\n1",a.nii.gz\ns2,b.nii.gz\n', r"line 3: id 's\\n1' must not contain .*control characters")
    refused("id,path\ns\x001,a.nii.gz\ns2,b.nii.gz\n", "control characters")
    refused("id,path\n..,a.nii.gz\ns2,b.nii.gz\n", "names a special folder")
    refused("id, path\ns1,a.nii.gz\n", r"\(read: id, path\).*without spaces")
    (tmp_path / "m.csv").write_text('id,path\ns\u20281,"a, b.nii.gz"\ns2,b.nii.gz\n', encoding="utf-8")
    assert read_manifest(tmp_path / "m.csv") == [("s\u20281", tmp_path / "a, b.nii.gz"), ("s2", tmp_path / "b.nii.gz")]


def test_nifti_dims_both_readers_agree_on_valid_files(tmp_path):
    """The dim checks pass 2-D, 3-D, 4-D with a size-1 axis, and big-endian files."""
    cube = _cube().array
    assert read_labels(_nifti(tmp_path / "a.nii", cube)).shape == (16, 16, 16)
    single = read_labels(_nifti(tmp_path / "b.nii.gz", cube[:, :, 4:5]))  # one axial slice: read as 2-D
    assert single.shape == (16, 16) and np.array_equal(single.array, cube[:, :, 4])
    assert read_labels(_nifti(tmp_path / "b2.nii", cube[:, :, 4])).shape == (16, 16)
    assert read_labels(_nifti(tmp_path / "c.nii.gz", cube[..., None])).shape == (16, 16, 16)
    big = nib.Nifti1Image(cube.astype(">i2"), np.eye(4))
    nib.save(big, str(tmp_path / "d.nii"))
    assert np.array_equal(read_labels(tmp_path / "d.nii").array, cube)



def test_nifti2_is_refused_as_such(tmp_path, capsys):
    """A NIfTI-2 file (which SimpleITK does not read) is named as NIfTI-2, not as a header with
    zero voxel sizes (its pixdim lies elsewhere than NIfTI-1's)."""
    cube = _cube().array
    nib.save(nib.Nifti2Image(cube, np.diag([2.0, 2.0, 2.0, 1.0])), str(tmp_path / "n2.nii"))
    with pytest.raises(VolregIOError, match=r"is NIfTI-2, .* expected NIfTI-1"):
        read_labels(tmp_path / "n2.nii")
    write_labels(_cube(), tmp_path / "f.nii.gz")
    assert main(["register", str(tmp_path / "f.nii.gz"), str(tmp_path / "n2.nii"), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "NIfTI-2" in err and "pixdim" not in err, err
    assert not (tmp_path / "o").exists()



def test_labels_scaled_into_fractions_by_the_header_are_named_so(tmp_path):
    """uint8 labels with scl_slope 0.5 read as halves: the error names the scaling, not float32
    voxels the file does not hold; a slope of 2 gives whole numbers, read as labels."""
    cube = _cube().array
    for slope in (0.5, 2.0):
        img = nib.Nifti1Image(cube, np.eye(4))
        img.header.set_slope_inter(slope, 0.0)
        nib.save(img, str(tmp_path / f"s{slope}.nii.gz"))
    with pytest.raises(VolregIOError, match=r"stores uint8 voxels that its header scales by scl_slope 0.5 and "
                                            r"scl_inter 0 into non-integral values \(e.g. 0.5\)"):
        read_labels(tmp_path / "s0.5.nii.gz")
    assert set(np.unique(read_labels(tmp_path / "s2.0.nii.gz").array)) == {0, 2 * int(cube.max())}

def test_files_an_image_writer_makes_under_other_names_are_removed(tmp_path):
    """The temporary output's unique prefix finds what a writer wrote beside it under a name of
    its own (ITK's NIfTI writer drops an ending it takes for the suffix); other files stay."""
    from volreg.io.images import _remove_written_beside

    tmp = tmp_path / ".tmp-0a1b2c3d-out.nia.nii.gz"
    for name in (tmp.name, ".tmp-0a1b2c3d-out.nia.gz", ".tmp-99999999-other.nii.gz", "out.nii.gz"):
        (tmp_path / name).write_bytes(b"x")
    _remove_written_beside(tmp)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".tmp-0a1b2c3d-out.nia.nii.gz", ".tmp-99999999-other.nii.gz",
                                                          "out.nii.gz"]


def test_a_disk_without_room_for_the_hdf5_field_is_reported_before_writing(tmp_path, monkeypatch):
    """HDF5 prints a hundred lines of its error stack when the disk fills under it: the room is
    checked first, and a lack of it raised as the system's ENOSPC, nothing written."""
    import errno
    import shutil

    from volreg.io.fields import write_itk_composite

    grid = _cube()
    u = np.zeros(grid.shape + (3,))
    monkeypatch.setattr(shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(100, 100, 0))
    with pytest.raises(OSError) as info:
        write_itk_composite(u, grid, tmp_path / "warp.h5")
    assert info.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []

def test_a_full_disk_is_reported_in_one_line(tmp_path, capsys, monkeypatch):
    """No space left while the outputs are written: one line, exit status 1, nothing left."""
    import errno

    import volreg.io

    write_labels(_cube(), tmp_path / "f.nii.gz")

    def full(obj, path, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(volreg.io, "write_json", full)
    out = tmp_path / "o"
    assert main(["register", str(tmp_path / "f.nii.gz"), str(tmp_path / "f.nii.gz"), "-o", str(out), "--quiet",
                 "--protocol", "fast"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "No space left on device writing" in err and "outputs were removed" in err, err
    assert not out.exists()



# ----------------------------------------------------------------------------- batch

BATCH_PROTOCOL = "[protocol]\nname = \"{name}\"\n[warp]\nmin_width = 12.0\npad = 6.0\nmax_iter = {iters}\n"


@pytest.mark.parametrize("pairs, ids", [("all", ["a", "b__c", "a__b", "c"]), ("consecutive", ["x__y", "z", "x", "y__z"])])
def test_batch_refuses_ids_sharing_a_folder(tmp_path, capsys, pairs, ids):
    pytest.importorskip("dask.distributed")
    write_labels(_cube(), tmp_path / "v.nii.gz")
    (tmp_path / "m.csv").write_text("id,path\n" + "".join(f"{i},v.nii.gz\n" for i in ids))
    out = tmp_path / "out"
    assert main(["batch", str(tmp_path / "m.csv"), "-o", str(out), "--pairs", pairs, "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "would share the folder" in err, err
    folder = "a__b__c" if pairs == "all" else "x__y__z"
    assert f"pairs/{folder}" in err and err.count("(") >= 2
    assert not out.exists()


@pytest.fixture(scope="module")
def blobs(tmp_path_factory):
    from volreg.synthetic import GaussianBumps, deform_labels
    from helpers import blob_volume

    d = tmp_path_factory.mktemp("blobs")
    base = blob_volume(shape=(24, 24, 24), spacing=np.array([2.5, 2.5, 2.5]))
    write_labels(base, d / "a.nii.gz")
    bump = GaussianBumps(np.zeros((1, 3)), np.array([[2.0, 1.0, 0.0]]), 30.0)
    write_labels(deform_labels(base, bump), d / "b.nii.gz")
    (d / "p1.toml").write_text(BATCH_PROTOCOL.format(name="one", iters=15))
    (d / "p2.toml").write_text(BATCH_PROTOCOL.format(name="two", iters=16))
    (d / "p1_renamed.toml").write_text(BATCH_PROTOCOL.format(name="renamed", iters=15))
    return d


def test_batch_pair_redone_when_settings_change_and_temporaries_cleaned(blobs, tmp_path):
    """A finished pair is skipped only with the settings it was made with; a pair (re)started loses
    the temporary files a killed worker left; a protocol's name alone changes nothing."""
    from volreg.cohort import run_pair

    d = blobs
    out = tmp_path / "pair"
    args = ("a", str(d / "a.nii.gz"), "b", str(d / "b.nii.gz"), str(out))
    first = run_pair(*args, str(d / "p1.toml"))
    assert first["status"] == "done" and not first.get("skipped"), first
    warp = out / "warp.nii.gz"
    made = warp.stat().st_mtime_ns
    assert run_pair(*args, str(d / "p1.toml")).get("skipped") is True
    assert run_pair(*args, str(d / "p1_renamed.toml")).get("skipped") is True
    assert warp.stat().st_mtime_ns == made
    stale = [out / ".tmp-0123abcd-warp.nii.gz", out / ".tmp-89abcdef-report.json"]
    for p in stale:
        p.write_bytes(b"half")
    second = run_pair(*args, str(d / "p2.toml"))
    assert second["status"] == "done" and not second.get("skipped") and second.get("redone") is True, second
    assert warp.stat().st_mtime_ns != made
    assert not any(p.exists() for p in stale)
    saved = json.loads((out / "batch_row.json").read_text())
    assert saved["settings_sha256"] == second["settings_sha256"] != first["settings_sha256"]
    assert "redone" not in saved


@pytest.mark.system
def test_batch_interrupt_says_what_remains(blobs, tmp_path):
    """SIGTERM during a batch: exit 143 and one line saying how many pairs finished (kept) and how
    many did not; the finished pairs' results are complete."""
    pytest.importorskip("dask.distributed")
    d = blobs
    lines = ["id,path"] + [f"s{i},{d / ('a.nii.gz' if i % 2 else 'b.nii.gz')}" for i in range(5)]
    (tmp_path / "m.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "volreg", "batch", str(tmp_path / "m.csv"), "-o", str(out),
                             "--protocol", str(d / "p1.toml"), "--workers", "1", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None and not list(out.glob("pairs/*/batch_row.json")):
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    line = [ln for ln in err.splitlines() if "interrupted" in ln]
    assert len(line) == 1, err
    match = re.search(r"interrupted by SIGTERM; (\d+) of 20 pairs finished and are kept in .*; the (\d+) others are "
                      r"unfinished and a rerun redoes them; `.*batch\.csv` was not written\.", line[0])
    assert match, line[0]
    finished = [p.parent for p in out.glob("pairs/*/batch_row.json")]
    # counted on disk once the workers stopped: a pair that ended while the signal was on its way counts
    assert int(match.group(1)) == len(finished) >= 1 and int(match.group(1)) + int(match.group(2)) == 20
    for pair in finished:
        assert all((pair / n).is_file() for n in ("warp.nii.gz", "warped.nii.gz", "model.npz", "report.json"))
    assert not (out / "batch.csv").exists()


def test_at_least_twenty_five_file_cases():
    assert len(CASES) + len(MESH_CASES) >= 25
