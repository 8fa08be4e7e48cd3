"""Reliability of messages: a full disk, a truncated field, retries, protocol files, long values, early signals.

Each case ends in one line on stderr (``volreg COMMAND: error: …`` or an interrupt's report) with the
documented exit status: 1 for a full disk, 2 for invalid input, 130 / 143 for SIGINT / SIGTERM.
"""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from volreg.cli import main
from volreg.io import write_labels
from helpers import TEST_PROTOCOL, cube

# ----------------------------------------------------------------------------- a full disk


def _inputs(tmp_path: Path) -> dict[str, Path]:
    """Two label volumes, a mesh of each, an identity transform and a protocol file."""
    from volreg.io.fields import write_itk_linear
    from volreg.linear_map import LinearMap

    write_labels(cube(), tmp_path / "a.nii.gz")
    write_labels(cube(lo=5, hi=12), tmp_path / "b.nii.gz")
    (tmp_path / "p.toml").write_text(TEST_PROTOCOL)
    for name in ("a", "b"):
        assert main(["surface", str(tmp_path / f"{name}.nii.gz"), "-o", str(tmp_path / f"s{name}"), "--quiet"]) == 0
    write_itk_linear(tmp_path / "id.tfm", LinearMap.identity(3))
    return {"a": tmp_path / "a.nii.gz", "b": tmp_path / "b.nii.gz", "p": tmp_path / "p.toml",
            "ma": next((tmp_path / "sa").glob("*.vtk")), "mb": next((tmp_path / "sb").glob("*.vtk")),
            "tfm": tmp_path / "id.tfm"}


#: Each command with a full disk: its arguments (from :func:`_inputs`) and its output's name.
FULL_DISK = {
    "surface": lambda f, o: ["surface", f["a"], "-o", o],
    "morph": lambda f, o: ["morph", f["ma"], f["mb"], "-o", o, "--frames", "3"],
    "register-surfaces": lambda f, o: ["register-surfaces", f["ma"], f["mb"], "-o", o],
    "apply": lambda f, o: ["apply", f["tfm"], f["a"], "--reference", f["b"], "-o", o / "moved.nii.gz"],
    "consistency": lambda f, o: ["consistency", f["a"], f["b"], "-o", o, "--protocol", f["p"]],
}


@pytest.fixture(scope="module")
def disk_inputs(tmp_path_factory):
    return _inputs(tmp_path_factory.mktemp("inputs"))


@pytest.mark.parametrize("how", ["os.replace", "library"])
@pytest.mark.parametrize("command", list(FULL_DISK))
def test_a_full_disk_ends_in_one_line_naming_the_output(disk_inputs, tmp_path, capfd, monkeypatch, command, how):
    """Every write ends in a rename (os.replace); a full disk there, or inside a library that
    turns it into an error of its own (ITK's RuntimeError, VTK's), names the user's output."""
    real_replace = os.replace
    out = tmp_path / "out"

    def full(src, dst, *args, **kwargs):
        if str(tmp_path) not in os.fspath(dst):  # numba writes its cache the same way
            return real_replace(src, dst, *args, **kwargs)
        if how == "os.replace":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), os.fspath(src))
        raise RuntimeError(f"ITK ERROR: ImageFileWriter(0x55d0): Could not write {os.fspath(src)}\n"
                           f"  error: No space left on device\n" + "dump line\n" * 30)

    monkeypatch.setattr(os, "replace", full)
    (out if command == "apply" else out.parent).mkdir(exist_ok=True)
    args = [str(a) for a in FULL_DISK[command](disk_inputs, out)] + ["--quiet"]
    capfd.readouterr()
    rc = main(args)
    monkeypatch.setattr(os, "replace", real_replace)
    err = capfd.readouterr().err.strip()
    assert rc == 1, err
    assert "\n" not in err and "Traceback" not in err, err
    assert "No space left on device writing `" in err, err
    assert ".volreg-new" not in err and ".tmp-" not in err, err
    assert str(out) in err, err


# ----------------------------------------------------------------------------- a truncated field


def _volreg(*args, timeout: float = 120) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    return subprocess.run([sys.executable, "-m", "volreg", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=timeout)


@pytest.mark.parametrize("cut", ["half", "superblock", "signature", "scrambled", "nifti"])
def test_a_truncated_field_is_named_in_one_line(tmp_path, cut):
    """HDF5 prints its diagnostic stack from C (not through Python): the subprocess's own stderr
    must hold only volreg's line."""
    from volreg.io.fields import write_displacement, write_itk_composite

    volume = cube()
    write_labels(volume, tmp_path / "a.nii.gz")
    u = np.zeros(volume.grid.shape + (3,))
    name = "warp.nii.gz" if cut == "nifti" else "warp.h5"
    (write_displacement if cut == "nifti" else write_itk_composite)(u, volume.grid, tmp_path / name)
    data = (tmp_path / name).read_bytes()
    cuts = {"half": data[:len(data) // 2], "superblock": data[:40], "signature": data[:8], "nifti": data[:len(data) // 2],
            "scrambled": data[:48] + bytes(len(data) - 48)}
    (tmp_path / name).write_bytes(cuts[cut])
    done = _volreg("apply", tmp_path / name, tmp_path / "a.nii.gz", "--reference", tmp_path / "a.nii.gz",
                   "-o", tmp_path / "moved.nii.gz", "--quiet")
    err = done.stderr.strip()
    assert done.returncode == 2, err
    assert "\n" not in err and "HDF5-DIAG" not in err and "Traceback" not in err, err
    assert name in err and ("truncated" in err or cut == "scrambled"), err
    assert not (tmp_path / "moved.nii.gz").exists()


# ----------------------------------------------------------------------------- batch retries


@pytest.mark.parametrize("failure", ["ENOSPC", "EDQUOT", "library", "input"])
def test_a_pair_that_fails_for_good_is_tried_once(tmp_path, monkeypatch, failure):
    """A task that raises is retried by Dask (``retries``); a failure that recurs on every try is a
    row instead, returned from the one attempt."""
    import volreg.cohort as cohort
    from volreg.errors import RegistrationInputError

    write_labels(cube(), tmp_path / "a.nii.gz")
    (tmp_path / "p.toml").write_text(TEST_PROTOCOL)
    calls = []

    def fails(*args, **kwargs):
        calls.append(1)
        staged = tmp_path / ".out.volreg-new-1-0a1b2c3d" / ".tmp-0a1b2c3d-warp.h5"
        if failure == "input":
            raise RegistrationInputError("the pair shares no label")
        if failure == "library":
            raise RuntimeError(f"HDF5-DIAG: H5Dwrite failed\nerrno = 28, error message = 'No space left on device' "
                               f"{staged}")
        code = getattr(errno, failure)
        raise OSError(code, os.strerror(code), str(staged))

    monkeypatch.setattr(cohort, "write_registration", fails)
    row = cohort.run_pair("a", str(tmp_path / "a.nii.gz"), "b", str(tmp_path / "a.nii.gz"), str(tmp_path / "out"),
                          str(tmp_path / "p.toml"))
    assert calls == [1] and row["status"] == "failed", row
    assert ".volreg-new" not in row["error"] and ".tmp-" not in row["error"], row
    if failure != "input":
        assert row["error"].startswith(("No space left on device", "Disk quota exceeded")), row


def test_a_bug_in_a_pair_is_left_to_dask(tmp_path, monkeypatch):
    import volreg.cohort as cohort

    write_labels(cube(), tmp_path / "a.nii.gz")
    (tmp_path / "p.toml").write_text(TEST_PROTOCOL)
    monkeypatch.setattr(cohort, "write_registration", lambda *a, **k: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        cohort.run_pair("a", str(tmp_path / "a.nii.gz"), "b", str(tmp_path / "a.nii.gz"), str(tmp_path / "out"),
                        str(tmp_path / "p.toml"))


# ----------------------------------------------------------------------------- protocol files


@pytest.mark.parametrize("name", ["proto.TOML", "proto.Toml", "proto.cfg", "proto"])
def test_a_protocol_file_of_any_suffix_is_read_as_a_file(tmp_path, monkeypatch, name):
    from volreg.io.protocol import load_protocol

    monkeypatch.chdir(tmp_path)
    Path(name).write_text(TEST_PROTOCOL)
    assert load_protocol(name).name == "test"
    assert load_protocol(tmp_path / name).name == "test"


@pytest.mark.parametrize("name", ["fastest", "x" * 100_000, "nothere.TOML"])
def test_neither_preset_nor_file_lists_the_presets(tmp_path, monkeypatch, capsys, name):
    monkeypatch.chdir(tmp_path)
    write_labels(cube(), tmp_path / "a.nii.gz")
    assert main(["register", "a.nii.gz", "a.nii.gz", "-o", "out", "--protocol", name, "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and len(err) < 400, err[:400]
    if len(name) > 255:  # over the system's name limit: no file can have it
        assert "cannot be looked up: File name too long" in err, err
    else:
        assert "is no such preset or file" in err and "fast" in err and "default" in err, err


# ----------------------------------------------------------------------------- long values, settings' tables

LONG = "k" * 100_000


@pytest.mark.parametrize("case", ["protocol key", "protocol section", "protocol value", "grid name", "grid value",
                                  "grid table", "manifest id"])
def test_a_long_user_value_is_never_echoed_whole(tmp_path, monkeypatch, capsys, case):
    monkeypatch.chdir(tmp_path)
    write_labels(cube(), tmp_path / "a.nii.gz")
    texts = {"protocol key": f"[warp]\n{LONG} = 1\n", "protocol section": f"[{LONG}]\na = 1\n",
             "protocol value": f"[warp]\nmin_width = \"{LONG}\"\n"}
    if case.startswith("protocol"):
        Path("p.toml").write_text(texts[case])
        args = ["register", "a.nii.gz", "a.nii.gz", "-o", "out", "--protocol", "p.toml"]
    elif case.startswith("grid"):
        grid = {"grid name": f"{LONG}=1,2", "grid value": f"alpha=1,{LONG}", "grid table": f"{LONG}=a"}[case]
        args = ["tune", "a.nii.gz", "a.nii.gz", "-o", "out", "--grid", grid]
    else:
        Path("m.csv").write_text(f"id,path\n{LONG},a.nii.gz\nb,a.nii.gz\n")
        args = ["batch", "m.csv", "-o", "out"]
    assert main(args + ["--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and len(err) < 400, err[:600]


@pytest.mark.parametrize("grid, words", [
    ("kind=rigid,affine", ["`kind` is a setting of [linear]", "set [linear] kind in the --protocol file"]),
    ("smoothing=x", ["`smoothing` is a setting of [surface]"]),
    ("colour=red", ["`colour` is no [warp] setting", "lambda_loc", "alpha"]),
])
def test_a_grid_setting_of_another_table_is_named(tmp_path, capsys, grid, words):
    write_labels(cube(), tmp_path / "a.nii.gz")
    assert main(["tune", str(tmp_path / "a.nii.gz"), str(tmp_path / "a.nii.gz"), "-o", str(tmp_path / "o"),
                 "--grid", grid, "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "not a number" not in err and all(w in err for w in words), err


# ----------------------------------------------------------------------------- signals while starting


@pytest.mark.parametrize("delay_ms", [100, 200, 500])  # after the interpreter starts, during the imports
@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_a_signal_while_the_command_starts_ends_in_one_line(tmp_path, signame, delay_ms):
    """During Python's imports a SIGINT gave a KeyboardInterrupt traceback and a SIGTERM a silent
    status -15. (A signal before the interpreter runs any code, 0 ms, takes the system's default
    action: nothing in Python can handle it.)"""
    import signal
    import subprocess
    import sys
    import time

    write_labels(cube(), tmp_path / "a.nii.gz")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen([sys.executable, "-m", "volreg", "register", "a.nii.gz", "a.nii.gz", "-o", "out", "--quiet"],
                            stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
    time.sleep(delay_ms / 1000)
    proc.send_signal(getattr(signal, signame))
    err = proc.communicate(timeout=120)[1].strip()
    if proc.returncode == 0:  # finished before the signal came: nothing to check
        pytest.skip("the run ended before the signal")
    assert proc.returncode == (130 if signame == "SIGINT" else 143), err
    assert "Traceback" not in err and len(err.splitlines()) == 1 and "interrupted by " + signame in err, err
    assert not (tmp_path / "out").exists()
