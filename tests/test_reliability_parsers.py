"""Reliability of what volreg parses and what it takes back: documents nested beyond reason, point
files with quoted line breaks or true/false coordinates, a result folder of the wrong kind, and
outputs named as another kind of file.

Every hostile case ends in a correct result or a one-line error (exit status 2) naming the file or
argument and what was expected, with nothing written."""

from __future__ import annotations

import json
import re
import shutil
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import pyvista as pv

from volreg.errors import ProtocolError, VolregIOError
from volreg.io import read_mesh, write_labels
from volreg.io.documents import MAX_NESTING, nesting_depth, parse_json, parse_toml
from volreg.io.gifti import write_gifti, write_gifti_data
from volreg.io.landmarks import read_landmarks
from volreg.io.pointsets import read_point_set, write_point_set
from volreg.io.protocol import load_protocol
from volreg.warp.model import KernelWarp

from helpers import cube, run

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: Deep enough to end Python's readers in a RecursionError (their descent takes a frame a level).
DEEP = 100_000
#: Within Python's recursion limit but beyond :data:`MAX_NESTING`: read, then refused.
SHALLOW = 3 * MAX_NESTING


def _json_list(depth: int, inner: str = "1") -> str:
    return "[" * depth + inner + "]" * depth


def _refused(args, capsys, *words) -> str:
    """Run ``volreg ARGS``: exit status 2, one line on stderr naming ``words``, no traceback."""
    assert run(args) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and re.match(r"volreg [\w-]+: error: ", err), err
    assert "Traceback" not in err and "RecursionError" not in err
    for w in words:
        assert w in err, (w, err)
    return err


@pytest.fixture(scope="module")
def volumes(tmp_path_factory):
    """Two cubes, a label registration of them (``volreg register``) and landmark files."""
    d = tmp_path_factory.mktemp("parsers")
    write_labels(cube(), d / "a.nii.gz")
    write_labels(cube(lo=5, hi=12), d / "b.nii.gz")
    (d / "l.csv").write_text("x,y,z\n5,5,5\n6,6,6\n7,7,7\n")
    assert run(["register", d / "a.nii.gz", d / "b.nii.gz", "-o", d / "reg", "--quiet"]) == 0
    return d


@pytest.fixture(scope="module")
def spheres(tmp_path_factory):
    """A source and target sphere (with a per-vertex array) and a GIFTI surface."""
    d = tmp_path_factory.mktemp("spheres")
    src = pv.Sphere(radius=20.0, theta_resolution=16, phi_resolution=16)
    src.point_data["t"] = np.asarray(src.points[:, 2], float)
    src.save(d / "src.vtk")
    src.save(d / "tgt.vtk")
    write_gifti(np.asarray(src.points, float), np.asarray(src.faces.reshape(-1, 4)[:, 1:]), d / "s.surf.gii")
    return d


# ----------------------------------------------------------------------------- nesting: the readers

@pytest.mark.parametrize("depth", [0, 1, 5, MAX_NESTING])
def test_documents_within_the_limit_read_as_the_standard_readers_do(depth):
    text = _json_list(depth) if depth else "1"
    assert parse_json(text, "doc") == json.loads(text)
    assert nesting_depth(json.loads(text)) == depth
    toml = f"a = {_json_list(depth - 1) if depth > 1 else 1}" if depth else ""
    assert parse_toml(toml, "doc") == tomllib.loads(toml)


@pytest.mark.parametrize("depth", [MAX_NESTING + 1, SHALLOW, DEEP])
@pytest.mark.parametrize("container", ["list", "object"])
def test_json_nested_beyond_the_limit_is_one_line_naming_it(depth, container):
    text = _json_list(depth) if container == "list" else '{"a": ' * depth + "1" + "}" * depth
    with pytest.raises(VolregIOError, match=rf"^Landmark file `x.json` nests its JSON data more than {MAX_NESTING} "):
        parse_json(text, "Landmark file `x.json`")


@pytest.mark.parametrize("text", [
    "a = " + _json_list(5000),  # inline arrays: a RecursionError in the reader
    "a = " + "{b = " * 5000 + "1" + "}" * 5000,  # inline tables: a RecursionError too
    "a = " + _json_list(SHALLOW),  # read, then refused
    "[" + ".".join(["t"] * SHALLOW) + "]\nb = 1\n",  # a table header's dotted names
    "[warp]\n" + ".".join(["k"] * SHALLOW) + " = 1\n",  # dotted keys
], ids=["inline arrays", "inline tables", "shallow arrays", "table header", "dotted keys"])
def test_toml_nested_beyond_the_limit_is_one_line_naming_it(text):
    with pytest.raises(ProtocolError, match=r"^Protocol `p.toml` nests its TOML data more than 64 levels deep"):
        parse_toml(text, "Protocol `p.toml`")


def test_depth_is_measured_without_recursion():
    value: list = []
    for _ in range(DEEP):
        value = [value]
    assert nesting_depth(value) == DEEP + 1
    assert nesting_depth(value, limit=10) == 11


# ----------------------------------------------------------------------------- nesting: every user file

def _deep_markups(kind: str) -> str:
    point = '{"position": [5, 5, 5]}'
    if kind == "whole file":
        return _json_list(DEEP)
    if kind == "position":
        return '{"markups": [{"controlPoints": [{"position": ' + _json_list(DEEP, "5") + "}]}]}"
    # beside the points, within the recursion limit: read, then refused before the points are taken
    return '{"markups": [{"display": ' + _json_list(SHALLOW) + ', "controlPoints": [' + point + "]}]}"


MARKUP_NESTINGS = ["whole file", "position", "beside the points"]


@pytest.mark.parametrize("kind", MARKUP_NESTINGS)
def test_deep_markups_refused_by_the_readers(tmp_path, kind):
    path = tmp_path / "deep.mrk.json"
    path.write_text(_deep_markups(kind))
    for read in (read_landmarks, read_point_set):
        with pytest.raises(VolregIOError, match=r"Landmark file `.*deep.mrk.json` nests its JSON data more than 64"):
            read(path)


@pytest.mark.parametrize("kind", MARKUP_NESTINGS)
@pytest.mark.parametrize("command", ["register", "apply"])
def test_deep_markups_refused_by_the_commands(volumes, tmp_path, capsys, kind, command):
    path = tmp_path / "deep.mrk.json"
    path.write_text(_deep_markups(kind))
    out = tmp_path / "out"
    if command == "register":
        args = ["register", volumes / "a.nii.gz", volumes / "b.nii.gz", "-o", out, "--landmarks", path,
                volumes / "l.csv"]
    else:
        out = tmp_path / "moved.mrk.json"
        args = ["apply", volumes / "reg" / "model.npz", path, "--from", "fixed", "-o", out]
    _refused(args, capsys, "deep.mrk.json", "nests its JSON data more than 64 levels deep")
    assert not out.exists()


PROTOCOL_NESTINGS = {
    "inline arrays": "[warp]\nalpha = " + _json_list(5000, "1.0") + "\n",
    "inline tables": "[warp]\nalpha = " + "{a = " * 5000 + "1" + "}" * 5000 + "\n",
    "table header": "[" + ".".join(["warp"] * SHALLOW) + "]\nalpha = 1.0\n",
}


@pytest.mark.parametrize("kind", sorted(PROTOCOL_NESTINGS))
@pytest.mark.parametrize("command", ["register", "consistency", "register-surfaces", "load_protocol"])
def test_deep_protocol_refused(volumes, spheres, tmp_path, capsys, kind, command):
    path = tmp_path / "deep.toml"
    path.write_text(PROTOCOL_NESTINGS[kind])
    if command == "load_protocol":
        with pytest.raises(ProtocolError, match=r"^Protocol `.*deep.toml` nests its TOML data more than 64"):
            load_protocol(path)
        return
    inputs = ([spheres / "src.vtk", spheres / "tgt.vtk"] if command == "register-surfaces"
              else [volumes / "a.nii.gz", volumes / "b.nii.gz"])
    out = tmp_path / "out"
    _refused([command, *inputs, "-o", out, "--protocol", path], capsys, "deep.toml", "nests its TOML data")
    assert not out.exists()


def _copy_with(folder: Path, tmp_path: Path, name: str, text: str) -> Path:
    copy = tmp_path / folder.name
    shutil.copytree(folder, copy)
    (copy / name).write_text(text)
    return copy


@pytest.mark.parametrize("depth", [SHALLOW, DEEP])
def test_deep_report_refused_by_consistency(volumes, tmp_path, capsys, depth):
    saved = _copy_with(volumes / "reg", tmp_path, "report.json", '{"inputs": ' + _json_list(depth) + "}")
    out = tmp_path / "out"
    _refused(["consistency", volumes / "a.nii.gz", volumes / "b.nii.gz", "-o", out, "--forward", saved,
              "--backward", saved], capsys, "report.json", "nests its JSON data more than 64")
    assert not out.exists()


@pytest.mark.parametrize("depth", [SHALLOW, DEEP])
def test_deep_model_settings_refused(volumes, tmp_path, capsys, depth):
    with np.load(volumes / "reg" / "model.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays["settings_json"] = np.array('{"a": ' + _json_list(depth) + "}")
    np.savez(tmp_path / "deep.npz", **arrays)
    with pytest.raises(VolregIOError, match=r"`settings_json` nests its JSON data more than 64 levels deep"):
        KernelWarp.load(tmp_path / "deep.npz")
    _refused(["apply", tmp_path / "deep.npz", volumes / "l.csv", "--from", "fixed", "-o", tmp_path / "o.csv"],
             capsys, "deep.npz", "settings_json", "nests")


def test_deep_pair_row_is_a_pair_to_do_again(tmp_path):
    from volreg.cohort import pair_result_done

    (tmp_path / "batch_row.json").write_text(_json_list(DEEP))
    assert pair_result_done(tmp_path, ("a", "b"), consistency=False) is None


def test_gifti_with_deeply_nested_xml_reads_as_without_it(spheres, tmp_path):
    """GIFTI's XML is read by expat's callbacks, which do not descend: nested elements that GIFTI
    does not know are passed over."""
    text = (spheres / "s.surf.gii").read_text()
    at = text.index("<DataArray")
    (tmp_path / "deep.surf.gii").write_text(text[:at] + "<x>" * DEEP + "</x>" * DEEP + text[at:])
    for got, want in zip(read_mesh(tmp_path / "deep.surf.gii"), read_mesh(spheres / "s.surf.gii")):
        np.testing.assert_array_equal(got, want)


# ----------------------------------------------------------------------------- point files

QUOTED_BREAKS = {
    "csv": ("q.csv", 'x,y,z,comment\n1,2,3,"two\nlines"\n4,5,6,plain\n'),
    "fcsv": ("q.fcsv", "# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n"
                       "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                       'p0,1,2,3,0,0,0,1,1,1,0,F-1,"two\nlines",\np1,4,5,6,0,0,0,1,1,1,0,F-2,plain,\n'),
    "mrk.json": ("q.mrk.json", json.dumps({"markups": [{"controlPoints": [
        {"label": "two\nlines", "position": [1, 2, 3]}, {"label": "plain", "position": [4, 5, 6]}]}]})),
}


@pytest.mark.parametrize("kind", sorted(QUOTED_BREAKS))
def test_quoted_line_break_kept_through_apply(tmp_path, kind):
    name, text = QUOTED_BREAKS[kind]
    (tmp_path / name).write_text(text, newline="")
    points = read_landmarks(tmp_path / name)
    np.testing.assert_array_equal(points, [[1, 2, 3], [4, 5, 6]])
    data = read_point_set(tmp_path / name)
    write_point_set(data, data.points + 1, tmp_path / f"out.{name}")
    written = (tmp_path / f"out.{name}").read_text()
    assert "two\nlines" in written or "two\\nlines" in written, written
    np.testing.assert_array_equal(read_landmarks(tmp_path / f"out.{name}"), points + 1)
    again = read_point_set(tmp_path / f"out.{name}")
    write_point_set(again, again.points - 1, tmp_path / f"back.{name}")
    if kind != "mrk.json":  # the JSON is written indented
        assert (tmp_path / f"back.{name}").read_text().replace(".0", "") == text


BAD_POSITIONS = [([True, False, True], "true or false"), ([1, "2", 3], "text"), ([True, 2.0, 3.0], "true or false")]


@pytest.mark.parametrize("position, what", BAD_POSITIONS, ids=["booleans", "text", "one boolean"])
def test_markup_position_of_booleans_or_text_refused(volumes, tmp_path, capsys, position, what):
    path = tmp_path / "b.mrk.json"
    path.write_text(json.dumps({"markups": [{"controlPoints": [{"position": [5, 5, 5]}, {"position": position}]}]}))
    message = rf"control point 2 has position {re.escape(json.dumps(position))}; expected three numbers"
    for read in (read_landmarks, read_point_set):
        with pytest.raises(VolregIOError, match=message):
            read(path)
    _refused(["apply", volumes / "reg" / "model.npz", path, "--from", "fixed", "-o", tmp_path / "o.mrk.json"],
             capsys, "b.mrk.json", f"not {what}")


# ----------------------------------------------------------------------------- results and outputs of the wrong kind

@pytest.mark.parametrize("command", ["transfer", "morph"])
def test_label_registration_refused_as_a_surface_registration(volumes, spheres, tmp_path, capsys, command):
    option = "--result" if command == "transfer" else "--from-result"
    out = tmp_path / ("o.vtk" if command == "transfer" else "o")
    args = [command, spheres / "src.vtk", spheres / "tgt.vtk", option, volumes / "reg", "-o", out]
    _refused(args + (["--array", "t"] if command == "transfer" else []), capsys,
             f"{option} `{volumes / 'reg'}` is a label-volume registration",
             "expected a surface registration from `volreg register-surfaces`")
    assert not out.exists()


@pytest.mark.parametrize("command", ["transfer", "morph"])
def test_other_command_result_refused(volumes, spheres, tmp_path, capsys, command):
    saved = _copy_with(volumes / "reg", tmp_path, "report.json", json.dumps({"command": "consistency"}))
    option = "--result" if command == "transfer" else "--from-result"
    args = [command, spheres / "src.vtk", spheres / "tgt.vtk", option, saved, "-o", tmp_path / "o.vtk"]
    _refused(args + (["--array", "t"] if command == "transfer" else []), capsys, "written by `volreg consistency`")


@pytest.mark.parametrize("suffix", [".shape.gii", ".func.gii", ".label.gii"])
def test_surface_not_written_under_a_data_file_suffix(volumes, spheres, tmp_path, capsys, suffix):
    out = tmp_path / f"moved{suffix}"
    _refused(["apply", volumes / "reg" / "model.npz", spheres / "s.surf.gii", "--from", "fixed", "-o", out],
             capsys, f"moved{suffix}", "GIFTI data file", "moved.surf.gii")
    assert not out.exists()
    vertices, triangles, _ = read_mesh(spheres / "s.surf.gii")
    with pytest.raises(VolregIOError, match="suffix of a GIFTI data file"):
        write_gifti(vertices, triangles, out)
    with pytest.raises(VolregIOError, match="suffix of a GIFTI data file"):
        data = read_point_set(spheres / "s.surf.gii")
        write_point_set(data, data.points, out)
    with pytest.raises(VolregIOError, match="suffix of a GIFTI surface"):
        write_gifti_data(np.zeros(len(vertices)), tmp_path / "values.surf.gii")
    assert list(tmp_path.iterdir()) == []


def test_surface_written_under_a_surface_name(volumes, spheres, tmp_path):
    out = tmp_path / "moved.surf.gii"
    assert run(["apply", volumes / "reg" / "model.npz", spheres / "s.surf.gii", "--from", "fixed", "-o", out]) == 0
    assert nib.load(str(out)).darrays[0].intent == nib.nifti1.intent_codes["NIFTI_INTENT_POINTSET"]
