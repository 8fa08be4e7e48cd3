"""Reliability of messages: an error quotes what it read from a file only as a short, printable excerpt.

A landmark file, a manifest, a protocol or a header may be another file than it claims (a link to a
key, a password file, a log): its lines must not reach the terminal, or a log a user shares.  Every
message that quotes a file's content goes through :func:`volreg.io.excerpt` (at most
:data:`~volreg.errors.EXCERPT_CHARS` characters, escaped), and what a library quotes of it
through :func:`~volreg.errors.exception_text`.
"""

from __future__ import annotations

import json
import os
import re
import zipfile
from pathlib import Path

import numpy as np
import pytest

from volreg.errors import EXCERPT_CHARS, VolregError, exception_text, excerpt
from volreg.io import write_labels
from helpers import cube, run

#: A line of another file, longer than an excerpt, with an escape sequence and a line break in it.
SECRET = "user=alice password=correct-horse-battery-staple \x1b[2J and-the-rest-of-the-line\nsecond line"
#: The same without the characters that cannot stand in a TOML string or a CSV field as they are.
PLAIN = "user=alice password=correct-horse-battery-staple and-the-rest-of-the-line-of-that-file"


def _leaks(message: str, secret: str = PLAIN) -> int:
    """The longest run of ``secret``'s characters that ``message`` holds."""
    longest = 0
    for size in range(1, len(secret) + 1):
        if not any(secret[i:i + size] in message for i in range(len(secret) - size + 1)):
            break
        longest = size
    return longest


def _check(message: str) -> None:
    """One line, nothing unprintable, at most an excerpt of the line (its middle left out)."""
    assert "\n" not in message and "\x1b" not in message, message
    assert _leaks(message) <= EXCERPT_CHARS and "battery" not in message, message


# ----------------------------------------------------------------------------- the helpers


def test_excerpt_quotes_short_text_as_repr_does():
    assert excerpt("ten") == repr("ten") and excerpt(2.5) == "2.5" and excerpt(["5", "5", "5"]) == "['5', '5', '5']"
    assert excerpt("warp.alpha", quote=False) == "warp.alpha"


def test_excerpt_cuts_and_escapes():
    text = excerpt(SECRET)
    assert text.startswith("'user=alice") and text.endswith("second line'") and "..." in text
    assert len(text) <= EXCERPT_CHARS + 2 and "\n" not in text and "\x1b" not in text
    assert excerpt("a\nb\x00c\u202ed") == r"'a\nb\x00c\u202ed'"  # a bidirectional override is escaped too
    assert excerpt("x" * 100, 10, quote=False) == "xxxx...xxx"
    assert excerpt("\n" * 30, 8) == r"'\n...\n'"  # an escape is not cut


def test_exception_text_cuts_what_a_library_quotes():
    assert exception_text(KeyError(PLAIN)).startswith("'user=alice") and _leaks(exception_text(KeyError(PLAIN))) <= 40
    text = exception_text(ValueError(f"could not convert string to float: {PLAIN!r}"))
    assert text.startswith("could not convert string to float: 'user") and _leaks(text) <= EXCERPT_CHARS
    assert exception_text(ValueError("")) == "ValueError" and exception_text(ValueError("one\ntwo")) == "one"
    assert exception_text(ValueError("a \x1b[2J b")) == r"a \x1b[2J b"


# ----------------------------------------------------------------------------- every reader that quotes a file


def _landmarks(path: Path):
    from volreg.io.landmarks import read_landmarks

    return read_landmarks(path)


def _protocol(path: Path):
    from volreg.io.protocol import load_protocol

    return load_protocol(path)


def _manifest(path: Path):
    from volreg.cohort import read_manifest

    return read_manifest(path)


def _labels(path: Path):
    from volreg.io import read_labels

    return read_labels(path)


def _mesh(path: Path):
    from volreg.io import read_mesh

    return read_mesh(path)


def _surface(path: Path):
    from volreg.io.meshes import read_surface

    return read_surface(path)


def _model(path: Path):
    from volreg.warp.model import KernelWarp

    return KernelWarp.load(path)


def _json(**markup) -> str:
    return json.dumps({"markups": [{"controlPoints": [{"position": [1.0, 2.0, 3.0]}], **markup}]})


MHD = "ObjectType = Image\nNDims = {ndims}\nDimSize = 4 4 4\nElementType = MET_UCHAR\nElementSpacing = {spacing}\n" \
      "ElementDataFile = LOCAL\n"
NRRD = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\n{field}\n\n"
GIFTI = ('<?xml version="1.0" encoding="UTF-8"?>\n<GIFTI Version="1.0" NumberOfDataArrays="1">\n'
         '<DataArray Intent="NIFTI_INTENT_POINTSET" DataType="{type}" ArrayIndexingOrder="RowMajorOrder" '
         'Dimensionality="2" Dim0="1" Dim1="3" Encoding="ASCII" Endian="LittleEndian" ExternalFileName="" '
         'ExternalFileOffset="">\n<Data>0 0 0</Data>\n</DataArray>\n</GIFTI>\n')

#: (case, file name, its text, the reader): each message would quote ``PLAIN`` (or ``SECRET``).
READERS = [
    ("landmark CSV header", "l.csv", f"{SECRET}\n1,2,3\n", _landmarks),
    ("landmark CSV value", "l.csv", f"x,y,z\n\"{PLAIN}\",1,2\n", _landmarks),
    ("landmark fcsv coordinate system", "l.fcsv", f"# CoordinateSystem = {PLAIN}\nid,1,2,3\n", _landmarks),
    ("landmark fcsv value", "l.fcsv", f"# CoordinateSystem = LPS\nid,\"{PLAIN}\",2,3\n", _landmarks),
    ("mrk.json coordinate system", "l.mrk.json", _json(coordinateSystem=SECRET), _landmarks),
    ("mrk.json units", "l.mrk.json", _json(coordinateUnits=SECRET), _landmarks),
    ("mrk.json position of words", "l.mrk.json",
     json.dumps({"markups": [{"controlPoints": [{"position": [SECRET, 1, 2]}]}]}), _landmarks),
    ("mrk.json NaN position and status", "l.mrk.json",
     json.dumps({"markups": [{"controlPoints": [{"position": [float("nan")] * 3, "positionStatus": SECRET}]}]}),
     _landmarks),
    ("manifest header", "m.csv", f"{PLAIN}\nid,path\n", _manifest),
    ("manifest row", "m.csv", f"id,path\n\"{PLAIN}\",\n", _manifest),
    ("manifest id with a line break", "m.csv", f"id,path\n\"{SECRET}\",a.nii.gz\n", _manifest),
    ("manifest id listed twice", "m.csv", f"id,path\n\"{SECRET}\",a.nii.gz\n\"{SECRET}\",b.nii.gz\n", _manifest),
    ("manifest path with NUL", "m.csv", f"id,path\na,\"{PLAIN}\x00\"\n", _manifest),
    ("protocol section", "p.toml", f'["{PLAIN}"]\n', _protocol),
    ("protocol key", "p.toml", f'[warp]\n"{PLAIN}" = 1\n', _protocol),
    ("protocol key with a line break", "p.toml", '[warp]\n"' + SECRET.replace("\n", "\\n").replace("\x1b", "\\u001b")
     + '" = 1\n', _protocol),
    ("protocol loose key", "p.toml", f'"{PLAIN}" = 1\n', _protocol),
    ("protocol value", "p.toml", f'[warp]\nalpha = "{PLAIN}"\n', _protocol),
    ("protocol linear kind", "p.toml", f'[linear]\nkind = "{PLAIN}"\n', _protocol),
    ("protocol name", "p.toml", f'[protocol]\nname = ["{PLAIN}"]\n', _protocol),
    ("protocol unknown head key", "p.toml", f'[protocol]\n"{PLAIN}" = 1\n', _protocol),
    ("MetaImage NDims", "m.mha", MHD.format(ndims=PLAIN, spacing="1 1 1"), _labels),
    ("MetaImage spacing", "m.mha", MHD.format(ndims=3, spacing=PLAIN), _labels),
    ("NRRD space origin", "n.nrrd", NRRD.format(field=f"space origin: {PLAIN}"), _labels),
    ("NRRD space directions", "n.nrrd", NRRD.format(field=f"space directions: {PLAIN}"), _labels),
    ("PLY element count", "m.ply", f"ply\nformat ascii 1.0\nelement vertex {PLAIN.replace(' ', '_')}\nend_header\n", _mesh),
    ("PLY element name", "m.ply", f"ply\nformat ascii 1.0\nelement {PLAIN.replace(' ', '_')} x\nend_header\n", _mesh),
    ("GIFTI data type (nibabel's KeyError)", "s.surf.gii", GIFTI.format(type=PLAIN), _surface),
]


@pytest.mark.parametrize("case", READERS, ids=[c[0] for c in READERS])
def test_messages_quote_an_excerpt(tmp_path, case):
    _, name, text, reader = case
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8"))
    with pytest.raises(VolregError) as info:
        reader(path)
    message = str(info.value)
    _check(message)
    assert f"`{path}`" in message or str(path) in message, message


def test_model_format_is_quoted_as_an_excerpt(tmp_path):
    path = tmp_path / "m.npz"
    with zipfile.ZipFile(path, "w") as z, z.open("format.npy", "w") as fh:
        np.save(fh, np.array(PLAIN))
    with pytest.raises(VolregError) as info:
        _model(path)
    _check(str(info.value))


# ----------------------------------------------------------------------------- commands, through a link


@pytest.fixture()
def secret_file(tmp_path) -> Path:
    """A file elsewhere, whose first line is ``PLAIN``."""
    (tmp_path / "elsewhere").mkdir()
    path = tmp_path / "elsewhere" / "notes.txt"
    path.write_text(f"{PLAIN}\nmore: {PLAIN}\n")
    return path


def test_landmark_file_linked_to_another_file(tmp_path, secret_file, capfd):
    write_labels(cube(), tmp_path / "a.nii.gz")
    good = tmp_path / "good.csv"
    good.write_text("x,y,z\n8,8,8\n")
    os.symlink(secret_file, tmp_path / "l.csv")
    assert run(["register", tmp_path / "a.nii.gz", tmp_path / "a.nii.gz", "-o", tmp_path / "out", "--landmarks",
                good, tmp_path / "l.csv"]) == 2
    err = capfd.readouterr().err.strip()
    assert re.match(r"volreg register: error: Landmark file `.*l\.csv` has header", err), err
    _check(err)
    assert run(["apply", tmp_path / "w.tfm", tmp_path / "l.csv", "--from", "fixed", "-o", tmp_path / "o.csv"]) == 2
    _check(capfd.readouterr().err.strip())


def test_manifest_linked_to_another_file(tmp_path, secret_file, capfd):
    os.symlink(secret_file, tmp_path / "m.csv")
    assert run(["batch", tmp_path / "m.csv", "-o", tmp_path / "out", "--workers", "1"]) == 2
    err = capfd.readouterr().err.strip()
    assert re.match(r"volreg batch: error: MANIFEST `.*m\.csv` needs a header", err), err
    _check(err)


def test_protocol_linked_to_another_file(tmp_path, capfd):
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "config.toml").write_text(f'"{PLAIN}" = "{PLAIN}"\n')
    os.symlink(tmp_path / "elsewhere" / "config.toml", tmp_path / "p.toml")
    write_labels(cube(), tmp_path / "a.nii.gz")
    assert run(["register", tmp_path / "a.nii.gz", tmp_path / "a.nii.gz", "-o", tmp_path / "out", "--protocol",
                tmp_path / "p.toml"]) == 2
    _check(capfd.readouterr().err.strip())
