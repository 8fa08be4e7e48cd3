"""Reliability of links: a data file that a header names is read only where it lies, once every link
is followed, inside the header's folder.

A MetaImage or NRRD header (``ElementDataFile``, ``data file``) and a GIFTI data array
(``ExternalFileName``) name another file, which the libraries open wherever it leads.  A name that
stays in the header's folder but is a symbolic link out of it (the file itself, or a folder on its
way) would put the bytes of a file elsewhere into the outputs.  Each case here would be read (exit
status 0) without the check: the files outside hold valid data.  Each command refuses it in one
line naming the header, exit status 2, nothing written; a link that stays inside the folder, and a
header reached through a linked folder, are read as before.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv

from volreg.io import read_labels, write_labels
from volreg.io.meshes import read_surface
from helpers import cube, run

#: A 4 x 4 x 4 payload: a 2 x 2 x 2 cube of label 1 (x fastest, as both formats store it).
CUBE = np.zeros((4, 4, 4), np.uint8)
CUBE[1:3, 1:3, 1:3] = 1
HEADERS = {
    "mhd": ("ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\nElementType = MET_UCHAR\nElementSpacing = 1 1 1\n"
            "ElementDataFile = {}\n"),
    "nhdr": "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\nspacings: 1 1 1\ndata file: {}\n",
}
IDENTITY_TFM = ("#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
                "Parameters: 1 0 0 0 1 0 0 0 1 0 0 0\nFixedParameters: 0 0 0\n")


def _outputs(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*")) if folder.exists() else []


def _refused(capfd, words=()) -> str:
    err = capfd.readouterr().err.strip()
    assert "\n" not in err and re.match(r"volreg [\w-]+: error: ", err), err
    for w in ("symbolic link", "outside the header's folder", "VOLREG_ALLOW_EXTERNAL_DATA=1", *words):
        assert w in err, (w, err)
    return err


# ----------------------------------------------------------------------------- label volumes


def _link_image(top: Path, fmt: str, kind: str) -> Path:
    """A header in ``top/in`` whose data file leads to ``top/elsewhere/data.raw`` by a link of ``kind``."""
    inside, outside = top / "in", top / "elsewhere"
    inside.mkdir(exist_ok=True)
    outside.mkdir(exist_ok=True)
    (outside / "data.raw").write_bytes(CUBE.tobytes())
    if kind == "file":  # in/f.raw -> ../elsewhere/data.raw
        os.symlink(outside / "data.raw", inside / f"{fmt}_file.raw")
        name = f"{fmt}_file.raw"
    elif kind == "folder":  # in/sub -> ../elsewhere, named sub/data.raw
        os.symlink(outside, inside / f"{fmt}_sub", target_is_directory=True)
        name = f"{fmt}_sub/data.raw"
    else:  # in/deep -> elsewhere/nested, named deep/../data.raw: ".." climbs from the link's target
        (outside / "nested").mkdir(exist_ok=True)
        os.symlink(outside / "nested", inside / f"{fmt}_deep", target_is_directory=True)
        name = f"{fmt}_deep/../data.raw"
    header = inside / f"{kind}.{fmt}"
    header.write_text(HEADERS[fmt].format(name))
    return header


@pytest.fixture(scope="module")
def volumes(tmp_path_factory):
    top = tmp_path_factory.mktemp("links")
    (top / "in").mkdir()
    write_labels(cube(shape=(4, 4, 4), lo=1, hi=3), top / "in" / "good.nii.gz")
    (top / "in" / "identity.tfm").write_text(IDENTITY_TFM)
    return top


#: (command, how it is given the hostile image ``{bad}``): each reads it through volreg.io's readers.
VOLUME_COMMANDS = {
    "surface": "surface {bad} -o {out}",
    "register": "register {good} {bad} -o {out}",
    "register (fixed)": "register {bad} {good} -o {out}",
    "apply": "apply {tfm} {bad} --reference {good} -o {out}/x.nii.gz",
    "apply --reference": "apply {tfm} {good} --reference {bad} -o {out}/x.nii.gz",
    "consistency": "consistency {good} {bad} -o {out}",
}


@pytest.mark.parametrize("command", sorted(VOLUME_COMMANDS))
@pytest.mark.parametrize("kind", ["file", "folder", "climb"])
@pytest.mark.parametrize("fmt", sorted(HEADERS))
def test_data_file_linked_out_of_the_folder_is_refused(volumes, tmp_path, capfd, fmt, kind, command):
    name = f"{fmt}_{kind}_{command.split()[0]}_{len(command)}"
    top = volumes / name
    top.mkdir()
    bad = _link_image(top, fmt, kind)
    out = tmp_path / "out"
    line = VOLUME_COMMANDS[command].format(bad=bad, good=volumes / "in" / "good.nii.gz", out=out,
                                           tfm=volumes / "in" / "identity.tfm")
    assert run(line.split()) == 2
    _refused(capfd, [bad.name])
    assert _outputs(out) == []


@pytest.mark.parametrize("kind", ["file", "folder", "climb"])
@pytest.mark.parametrize("fmt", sorted(HEADERS))
def test_linked_data_file_read_when_allowed(tmp_path, monkeypatch, fmt, kind):
    """With VOLREG_ALLOW_EXTERNAL_DATA=1 the same headers read the voxels the links lead to."""
    bad = _link_image(tmp_path, fmt, kind)
    monkeypatch.setenv("VOLREG_ALLOW_EXTERNAL_DATA", "1")
    assert np.array_equal(read_labels(bad).array, CUBE.T)


@pytest.mark.parametrize("fmt", sorted(HEADERS))
def test_links_that_stay_inside_are_read(tmp_path, fmt):
    """A data file linked to another in the folder, and a header reached through a linked folder
    (its data then lie in the folder the link leads to), are read as they were."""
    real = tmp_path / "real"
    (real / "sub").mkdir(parents=True)
    (real / "sub" / "data.raw").write_bytes(CUBE.tobytes())
    os.symlink(real / "sub" / "data.raw", real / "alias.raw")
    (real / "a.hdr.txt").write_text("")  # an unrelated file: the folder holds more than the pair
    (real / f"alias.{fmt}").write_text(HEADERS[fmt].format("alias.raw"))
    (real / f"sub.{fmt}").write_text(HEADERS[fmt].format("sub/data.raw"))
    os.symlink(real, tmp_path / "link", target_is_directory=True)
    for header in (real / f"alias.{fmt}", tmp_path / "link" / f"alias.{fmt}", tmp_path / "link" / f"sub.{fmt}"):
        assert np.array_equal(read_labels(header).array, CUBE.T), header


# ----------------------------------------------------------------------------- GIFTI


def _sphere() -> tuple[np.ndarray, np.ndarray]:
    sphere = pv.Sphere(radius=20.0, theta_resolution=8, phi_resolution=8)
    return np.asarray(sphere.points, np.float32), np.asarray(sphere.faces).reshape(-1, 4)[:, 1:]


def _gifti_surface(path: Path, name: str, encoding: str = "ExternalFileBinary", quote: str = '"') -> Path:
    """A GIFTI surface whose POINTSET lies in the external file ``name`` (float32, RAS) and whose
    triangles are inline."""
    points, faces = _sphere()
    q = quote
    path.write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<GIFTI Version="1.0" NumberOfDataArrays="2">\n'
        f'<DataArray Intent={q}NIFTI_INTENT_POINTSET{q} DataType={q}NIFTI_TYPE_FLOAT32{q} '
        f'ArrayIndexingOrder={q}RowMajorOrder{q} Dimensionality={q}2{q} Dim0={q}{len(points)}{q} Dim1={q}3{q} '
        f'Encoding={q}{encoding}{q} Endian={q}LittleEndian{q} ExternalFileName={q}{name}{q} '
        f'ExternalFileOffset={q}0{q}>\n<Data></Data>\n</DataArray>\n'
        '<DataArray Intent="NIFTI_INTENT_TRIANGLE" DataType="NIFTI_TYPE_INT32" ArrayIndexingOrder="RowMajorOrder" '
        f'Dimensionality="2" Dim0="{len(faces)}" Dim1="3" Encoding="ASCII" Endian="LittleEndian" '
        'ExternalFileName="" ExternalFileOffset="">\n'
        f'<Data>{" ".join(str(int(i)) for i in faces.ravel())}</Data>\n</DataArray>\n</GIFTI>\n')
    return path


def _gifti_data(path: Path, name: str, count: int) -> Path:
    """A GIFTI shape file of ``count`` float32 values in the external file ``name``."""
    path.write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<GIFTI Version="1.0" NumberOfDataArrays="1">\n'
        '<DataArray Intent="NIFTI_INTENT_SHAPE" DataType="NIFTI_TYPE_FLOAT32" ArrayIndexingOrder="RowMajorOrder" '
        f'Dimensionality="1" Dim0="{count}" Encoding="ExternalFileBinary" Endian="LittleEndian" '
        f'ExternalFileName="{name}" ExternalFileOffset="0">\n<Data></Data>\n</DataArray>\n</GIFTI>\n')
    return path


def _link_gifti(top: Path, kind: str, data: bool = False) -> Path:
    """A GIFTI file in ``top/in`` whose external file is ``top/elsewhere/points.bin``, reached by a link."""
    inside, outside = top / "in", top / "elsewhere"
    inside.mkdir(parents=True, exist_ok=True)
    outside.mkdir(exist_ok=True)
    points, _ = _sphere()
    values = np.linspace(0.0, 1.0, len(points), dtype=np.float32)
    (outside / "points.bin").write_bytes((values if data else points).tobytes())
    if kind == "file":
        os.symlink(outside / "points.bin", inside / "points.bin")
        name = "points.bin"
    else:
        os.symlink(outside, inside / "sub", target_is_directory=True)
        name = "sub/points.bin"
    if data:
        return _gifti_data(inside / "bad.thick.shape.gii", name, len(points))
    return _gifti_surface(inside / "bad.surf.gii", name)


@pytest.fixture(scope="module")
def surfaces(tmp_path_factory):
    top = tmp_path_factory.mktemp("gifti_links")
    points, faces = _sphere()
    (top / "points.bin").write_bytes(points.tobytes())
    _gifti_surface(top / "good.surf.gii", "points.bin")
    (top / "model").mkdir()  # never read: the inputs are refused first
    return top


#: (command, how it is given the hostile GIFTI surface ``{bad}`` or data file ``{bad_data}``).
GIFTI_COMMANDS = {
    "transfer": "transfer {bad} {good} --result {model} -o {out}/x.vtk",
    "transfer --target-data": "transfer {good} {good} --result {model} --target-data {bad_data} -o {out}/x.vtk",
    "morph": "morph {bad} {good} --from-result {model} -o {out}",
    "morph --source-data": "morph {good} {good} --from-result {model} --source-data {bad_data} -o {out}",
    "apply": "apply {model}/model.npz {bad} --from fixed -o {out}/x.surf.gii",
    "register-surfaces": "register-surfaces {bad} {good} -o {out}",
}


@pytest.mark.parametrize("command", sorted(GIFTI_COMMANDS))
@pytest.mark.parametrize("kind", ["file", "folder"])
def test_gifti_external_file_linked_out_of_the_folder_is_refused(surfaces, tmp_path, capfd, kind, command):
    top = tmp_path / "case"
    top.mkdir()
    bad = _link_gifti(top, kind)
    bad_data = _link_gifti(tmp_path / "data", kind, data=True) if "data" in command else None
    out = tmp_path / "out"
    if "x." in GIFTI_COMMANDS[command]:
        out.mkdir()  # the folder of a single output file
    line = GIFTI_COMMANDS[command].format(bad=bad, bad_data=bad_data, good=surfaces / "good.surf.gii",
                                          model=surfaces / "model", out=out)
    assert run(line.split()) == 2
    _refused(capfd, [(bad_data or bad).name])
    assert _outputs(out) == []


def test_gifti_external_file_read_when_inside_or_allowed(surfaces, tmp_path, monkeypatch):
    points, _ = _sphere()
    ras_to_lps = np.array([-1.0, -1.0, 1.0])
    assert np.allclose(read_surface(surfaces / "good.surf.gii").vertices, points * ras_to_lps)
    bad = _link_gifti(tmp_path, "folder")
    monkeypatch.setenv("VOLREG_ALLOW_EXTERNAL_DATA", "1")
    assert np.allclose(read_surface(bad).vertices, points * ras_to_lps)


@pytest.mark.parametrize("spelling", ["single quotes", "character references", "encoding External",
                                      "encoding GIFTI_ENCODING_EXTBIN"])
def test_gifti_external_file_is_read_as_nibabel_reads_it(tmp_path, capfd, spelling):
    """The attributes are read by nibabel's XML parser: quoting, escapes and synonyms do not hide a name."""
    (tmp_path / "in").mkdir()
    points, _ = _sphere()
    (tmp_path / "points.bin").write_bytes(points.tobytes())
    name, encoding, quote = "../points.bin", "ExternalFileBinary", '"'
    if spelling == "single quotes":
        quote = "'"
    elif spelling == "character references":
        name = "&#46;&#46;/points.bin"
    else:
        encoding = spelling.split()[1]
    bad = _gifti_surface(tmp_path / "in" / "bad.surf.gii", name, encoding=encoding, quote=quote)
    assert run(["register-surfaces", bad, bad, "-o", tmp_path / "out"]) == 2
    err = capfd.readouterr().err.strip()
    assert "\n" not in err and "climbs out of the header's folder" in err, err
