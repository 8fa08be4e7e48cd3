"""Output folders under hostile conditions, for every command that writes one.

An OUTDIR that cannot be swapped as a whole (a symbolic link, the working directory, a mount
point, bind mounts included, a folder in a parent that cannot be written) is written through a
staging folder inside it; a ``--force`` rerun that fails or is interrupted leaves the previous
result whole and says so; two runs into one OUTDIR: one writes it, the other refuses at once; a
rerun leaves no output of an earlier run that it does not write; an OUTDIR that cannot be
written is refused before the work, in one line.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

import volreg.io._atomic as atomic
import volreg.io._folder_parts as parts
from volreg.cli import main
from volreg.errors import VolregIOError
from volreg.grid import LabelVolume
from volreg.io import write_labels
from volreg.io._atomic import OutputFolder, kept_results, output_folder, recover_folder
from volreg.io._folder_parts import STALE_LIST, FolderLock, is_mount_point

REPO = Path(__file__).resolve().parents[1]
SMALL = '[protocol]\nname = "t"\n[warp]\nmin_width = 8.0\npad = 6.0\nmax_iter = 30\n'
NO_H5 = SMALL + "[outputs]\nitk_h5 = false\n"
SURFACES = '[protocol]\nname = "s"\n[warp]\nmin_width = 10.0\nmax_iter = 20\n'

#: Every command that writes an output folder.
COMMANDS = ["register", "consistency", "demo", "surface", "register-surfaces", "morph", "tune"]

#: Per command: the options of the earlier run, and those of a rerun that writes fewer files,
#: with the earlier run's files that the rerun must not keep.
FEWER = {
    "register": ([], ["--protocol", "{d}/noh5.toml"], ["warp.h5", "inverse_warp.h5"]),
    "demo": ([], ["--protocol", "{d}/noh5.toml"], ["warp.h5", "inverse_warp.h5"]),
    "consistency": ([], ["--protocol", "{d}/noh5.toml"], ["forward/warp.h5", "backward/inverse_warp.h5"]),
    "surface": ([], ["--labels", "1"], ["label_2.vtk", "sdf_2.nii.gz"]),
    "register-surfaces": (["--gifti"], [], ["warped.surf.gii"]),
    "morph": (["--frames", "4", "--gifti"], ["--frames", "3"], ["frame_003.vtk", "frame_003.png", "frame_000.surf.gii"]),
}


def _disc_pair(d: Path) -> None:
    """Two 2-D label images: an ellipse with a disc inside, the second shifted 3 voxels."""
    ii, jj = np.meshgrid(np.arange(48), np.arange(48), indexing="ij")
    for name, cx in (("a", 22), ("b", 25)):
        arr = np.zeros((48, 48), np.uint8)
        arr[((ii - cx) / 12.0) ** 2 + ((jj - 24) / 9.0) ** 2 < 1] = 1
        arr[(ii - cx - 3) ** 2 + (jj - 22) ** 2 < 16] = 2
        write_labels(LabelVolume(arr, (0.0, 0.0), (1.0, 1.0), np.eye(2)), d / f"{name}.nii.gz")


def _two_boxes(d: Path) -> None:
    """A 3-D label volume of two boxes (labels 1 and 2), for `surface`."""
    arr = np.zeros((20, 16, 16), np.uint8)
    arr[3:9, 4:12, 4:12] = 1
    arr[11:17, 4:12, 4:12] = 2
    write_labels(LabelVolume(arr, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(3)), d / "boxes.nii.gz")


def _spheres(d: Path) -> None:
    import pyvista as pv

    src = pv.Sphere(radius=20.0, theta_resolution=16, phi_resolution=16)
    tgt = src.copy()
    tgt.points = np.array(src.points) * [1.05, 1.0, 0.97]
    src.save(d / "src.vtk")
    tgt.save(d / "tgt.vtk")


def _small_frog(d: Path):
    """``volreg.demo``'s frog pair, replaced by the small 2-D pair (the demo's outputs are those of a registration)."""
    from volreg.io import read_labels
    from volreg.synthetic import GaussianBumps

    def frog_pair(full, factors=None):
        return full, read_labels(d / "b.nii.gz"), GaussianBumps(np.zeros((1, 2)), np.array([[3.0, 0.0]]), 20.0)

    return {"volreg.demo.frog_path": lambda: str(d / "a.nii.gz"), "volreg.demo.frog_pair": frog_pair}


def _args(command: str, d: Path, out: Path, extra=()) -> list[str]:
    extra = [e.format(d=d) for e in extra]
    protocol = [] if "--protocol" in extra else ["--protocol", str(d / "p.toml")]
    pair = [str(d / "a.nii.gz"), str(d / "b.nii.gz")]
    surfaces = [str(d / "src.vtk"), str(d / "tgt.vtk")]
    head = {
        "register": ["register", *pair, *protocol],
        "consistency": ["consistency", *pair, *protocol],
        "demo": ["demo", *protocol],
        "surface": ["surface", str(d / "boxes.nii.gz")],
        "register-surfaces": ["register-surfaces", *surfaces, "--protocol", str(d / "s.toml")],
        "morph": ["morph", *surfaces, "--from-result", str(d / "surface-result")],
        "tune": ["tune", *pair, *protocol, "--grid", "lambda_loc=0,100"],
    }[command]
    return [*head, "-o", str(out), "--quiet", *extra]


@pytest.fixture(autouse=True)
def small_frog(monkeypatch, inputs):
    for name, value in _small_frog(inputs).items():
        monkeypatch.setattr(name, value)
    kept_results().clear()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    _disc_pair(d)
    _two_boxes(d)
    _spheres(d)
    (d / "p.toml").write_text(SMALL)
    (d / "noh5.toml").write_text(NO_H5)
    (d / "s.toml").write_text(SURFACES)
    assert main(_args("register-surfaces", d, d / "surface-result")) == 0
    return d


@pytest.fixture(scope="module")
def earlier(inputs, tmp_path_factory):
    """Each command's complete result, with the options of FEWER's earlier run: ``{command: folder}``."""
    d, results = inputs, {}
    root = tmp_path_factory.mktemp("earlier")
    with pytest.MonkeyPatch.context() as mp:
        for name, value in _small_frog(d).items():
            mp.setattr(name, value)
        for command in COMMANDS:
            out = root / command
            assert main(_args(command, d, out, FEWER.get(command, ([], [], []))[0])) == 0, command
            results[command] = out
    return results


def _contents(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _working_entries(*folders: Path) -> list[str]:
    """volreg's hidden working entries (staging folders, locks) in ``folders``."""
    return sorted(p.name for f in folders for p in f.iterdir() if ".volreg-" in p.name)


def _outdir(tmp_path: Path, mode: str, previous: Path | None = None) -> tuple[Path, Path]:
    """``(OUTDIR as named, the real folder)``: a folder beside its siblings, or a symbolic link to one
    (which cannot be swapped as a whole); holding a copy of ``previous``."""
    real = tmp_path / "real"
    if previous is not None:
        shutil.copytree(previous, real)
    else:
        real.mkdir()
    if mode == "beside":
        return real, real
    link = tmp_path / "link"
    link.symlink_to(real, target_is_directory=True)
    return link, real


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


# ----------------------------------------------------------------------------- failed and interrupted reruns


def _fail_at_first_output(monkeypatch, failure: str) -> None:
    """Make the run fail once its first output is complete: a full disk, or SIGTERM."""
    def record(self, path):
        if failure == "SIGTERM":
            raise KeyboardInterrupt("SIGTERM")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(OutputFolder, "record", record)


@pytest.mark.parametrize("failure", ["disk full", "SIGTERM"])
@pytest.mark.parametrize("mode", ["beside", "in place"])
@pytest.mark.parametrize("command", COMMANDS)
def test_a_failed_force_rerun_keeps_the_previous_result_whole_and_says_so(inputs, earlier, tmp_path, capsys,
                                                                         monkeypatch, command, mode, failure):
    out, real = _outdir(tmp_path, mode, earlier[command])
    before = _contents(real)
    _fail_at_first_output(monkeypatch, failure)
    capsys.readouterr()
    status = main(_args(command, inputs, out, ["--force"]))
    line = _one_line(capsys)
    assert status == (143 if failure == "SIGTERM" else 1), line
    assert line.startswith(f"volreg {command}: ")
    assert f"were removed (the previous result in `{out}` was kept)" in line, line
    if failure == "disk full":  # naming the output where the user looks for it, not in the staging folder
        assert f" writing `{out}{os.sep}" in line and ".volreg-" not in line, line
    assert _contents(real) == before
    assert _working_entries(real, tmp_path) == []
    assert out.is_symlink() == (mode == "in place")


@pytest.mark.parametrize("mode", ["beside", "in place"])
def test_a_failure_while_the_result_is_put_in_place_keeps_the_previous_one_and_says_so(tmp_path, monkeypatch, mode):
    out, real = _outdir(tmp_path, mode)
    (real / "a.txt").write_text("old")

    def full(*args):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(real / "a.txt"))

    monkeypatch.setattr(atomic, "_stale", full)  # the first step of putting the result in place
    with pytest.raises(OSError):
        with output_folder(out, force=True, outputs=["*.txt"]) as folder:
            (folder.path / ".tmp-a.txt").write_text("new")  # replaced, as volreg's writers do (never in place)
            os.replace(folder.path / ".tmp-a.txt", folder.path / "a.txt")
            folder.record(folder.path / "a.txt")
    assert _contents(real) == {"a.txt": b"old"} and kept_results() == [out]
    assert _working_entries(real, tmp_path) == []


@pytest.mark.parametrize("command", COMMANDS)
def test_a_completed_force_rerun_in_place_replaces_the_result(inputs, earlier, tmp_path, command):
    out, real = _outdir(tmp_path, "in place", earlier[command])
    (real / "mine.txt").write_text("not volreg's")
    before = {p.name: p.stat().st_ino for p in real.iterdir()}
    assert main(_args(command, inputs, out, [*FEWER.get(command, ([], [], []))[0], "--force"])) == 0
    after = {p.name: p.stat().st_ino for p in real.iterdir()}
    assert after.keys() == before.keys() and out.is_symlink()
    assert after["mine.txt"] == before["mine.txt"] and (real / "mine.txt").read_text() == "not volreg's"
    assert all(after[name] != before[name] for name in after if name != "mine.txt" and (real / name).is_file())
    assert _working_entries(real, tmp_path) == []


def test_a_failed_rerun_into_the_working_directory_keeps_its_files(inputs, earlier, tmp_path, capsys, monkeypatch):
    work = tmp_path / "work"
    shutil.copytree(earlier["register"], work)
    (work / "notes.txt").write_text("mine")
    before = _contents(work)
    monkeypatch.chdir(work)
    _fail_at_first_output(monkeypatch, "disk full")
    assert main(_args("register", inputs, Path("."), ["--force"])) == 1
    assert "(the previous result in `.` was kept)" in _one_line(capsys)
    assert _contents(work) == before and _working_entries(work) == []


# ----------------------------------------------------------------------------- stale outputs


@pytest.mark.parametrize("mode", ["beside", "in place"])
@pytest.mark.parametrize("command", sorted(FEWER))
def test_a_force_rerun_keeps_no_output_of_the_earlier_run_that_it_does_not_write(inputs, earlier, tmp_path, capsys,
                                                                                 command, mode):
    _, fewer, stale = FEWER[command]
    out, real = _outdir(tmp_path, mode, earlier[command])
    (real / "mine.txt").write_text("not volreg's")
    assert all((real / name).is_file() for name in stale)
    fresh = tmp_path / "fresh"
    capsys.readouterr()
    assert main(_args(command, inputs, fresh, fewer)) == 0
    assert main(_args(command, inputs, out, [*fewer, "--force"])) == 0
    summary = capsys.readouterr().out.strip().splitlines()
    assert sorted(_contents(real)) == sorted([*_contents(fresh), "mine.txt"])
    assert not any((real / name).exists() for name in stale)
    assert _working_entries(real, tmp_path) == []
    if command in ("register", "demo"):  # the summary counts the files there
        count = int(re.search(r"; (\d+) files in ", summary[-1]).group(1))
        assert count == len(_contents(real)) - 1 - (2 if command == "demo" else 0)


def test_every_output_folder_names_every_output_its_command_may_write():
    """A command that opened its output folder without ``outputs`` would keep an earlier run's files."""
    calls = []
    for path in (REPO / "volreg").rglob("*.py"):
        if path.name == "_atomic.py":
            continue
        text = path.read_text()
        for match in re.finditer(r"\boutput_folder\(", text):
            call = text[match.end():text.index(")", match.end()) + 1]
            calls.append((path.name, "outputs=" in call))
    assert len(calls) >= 8 and all(ok for _, ok in calls), calls


def test_a_move_in_place_killed_midway_is_finished_by_the_next_run(tmp_path):
    """SIGKILL while a complete result was being moved in file by file: the next run moves the rest
    and removes the earlier run's outputs that the result does not hold."""
    out = tmp_path / "out"
    out.mkdir()
    for name in ("a.txt", "b.txt", "old.h5", "mine.txt"):
        (out / name).write_text("old")
    ready = out / ".volreg-ready-999999999-0badc0de"  # a run no longer alive
    (ready / "sub").mkdir(parents=True)
    (ready / "b.txt").write_text("new")  # a.txt was moved in already
    (ready / "sub" / "c.txt").write_text("new")
    (ready / STALE_LIST).write_text('["old.h5"]')
    (out / "a.txt").write_text("new")
    partial = out / ".volreg-new-999999999-00000000"
    partial.mkdir()
    (partial / "a.txt").write_text("partial")
    assert recover_folder(out) == "new"
    assert _contents(out) == {"a.txt": b"new", "b.txt": b"new", "mine.txt": b"old", "sub/c.txt": b"new"}


def test_only_working_folders_of_the_exact_form_are_recovered(tmp_path):
    """Folders that merely start like a working folder's name are left alone."""
    out = tmp_path / "out"
    lookalikes = [tmp_path / ".out.volreg-old-999999999-0badc0de-mine", tmp_path / ".out.volreg-old-x-0badc0de",
                  tmp_path / ".out.volreg-oldest-999999999-0badc0de"]
    for folder in lookalikes:
        folder.mkdir()
    assert recover_folder(out) is None and not out.exists() and all(f.is_dir() for f in lookalikes)


# ----------------------------------------------------------------------------- two runs into one folder


@pytest.mark.parametrize("mode", ["beside", "in place"])
@pytest.mark.parametrize("command", COMMANDS)
def test_a_run_into_a_folder_another_run_writes_refuses_at_once(inputs, tmp_path, capsys, command, mode):
    out, real = _outdir(tmp_path, mode)
    lock = FolderLock(real, atomic._stage_prefix)  # the other run, writing the folder by its real name
    try:
        capsys.readouterr()
        assert main(_args(command, inputs, out, ["--force"])) == 2
        line = _one_line(capsys)
    finally:
        lock.release()
    assert line == (f"volreg {command}: error: Output directory `{out}` is being written by another volreg run "
                    f"(process {os.getpid()}); expected one run per output folder (wait for it to end, or choose "
                    "another -o).")
    assert list(real.iterdir()) == [] and _working_entries(tmp_path) == []


def test_two_threads_entering_one_fresh_folder_one_writes_the_other_refuses(tmp_path):
    out = tmp_path / "out"
    entered, release = threading.Event(), threading.Event()
    outcomes = {}

    def first():
        with output_folder(out) as folder:
            (folder.path / "a.txt").write_text("first")
            folder.record(folder.path / "a.txt")
            entered.set()
            release.wait(30)
        outcomes["first"] = "done"

    thread = threading.Thread(target=first)
    thread.start()
    assert entered.wait(30)
    with pytest.raises(VolregIOError, match="is being written by another volreg run"):
        with output_folder(out) as folder:
            (folder.path / "a.txt").write_text("second")
    release.set()
    thread.join(30)
    assert outcomes == {"first": "done"} and _contents(out) == {"a.txt": b"first"}
    assert _working_entries(tmp_path) == []
    with output_folder(out, force=True):  # the lock went with the run
        pass


def test_a_folder_made_by_another_program_during_the_run_is_not_replaced(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(VolregIOError, match="was made by another program while this run wrote its outputs"):
        with output_folder(out) as folder:
            (folder.path / "a.txt").write_text("ours")
            folder.record(folder.path / "a.txt")
            out.mkdir()
            (out / "theirs.txt").write_text("theirs")
    assert _contents(out) == {"theirs.txt": b"theirs"} and _working_entries(tmp_path) == []


@pytest.mark.system
def test_two_register_runs_started_together_into_one_folder(inputs, tmp_path):
    """Exactly one writes OUTDIR; the other exits 2 in one line saying why, and nothing is replaced."""
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    procs = [subprocess.Popen([sys.executable, "-m", "volreg", *_args("register", inputs, out)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=env) for _ in range(2)]
    results = [(p.wait(300), p.communicate()[1]) for p in procs]
    assert sorted(rc for rc, _ in results) == [0, 2], results
    err = next(err for rc, err in results if rc == 2).strip().splitlines()
    assert len(err) == 1 and ("is being written by another volreg run" in err[0] or "is not empty" in err[0]), err
    assert _working_entries(tmp_path) == [] and len(list(out.iterdir())) == 10


# ----------------------------------------------------------------------------- folders that cannot be written


@pytest.mark.parametrize("command", COMMANDS)
def test_an_outdir_that_cannot_be_written_is_refused_before_the_work(inputs, tmp_path, capsys, monkeypatch, command):
    out = tmp_path / "out"
    out.mkdir()
    # as a read-only folder is for a user (os.access is true for root whatever the mode)
    monkeypatch.setattr(atomic, "writable", lambda p: Path(p) != out)
    capsys.readouterr()
    assert main(_args(command, inputs, out)) == 2
    assert _one_line(capsys) == (f"volreg {command}: error: Output directory `{out}` is not writable; expected a "
                                 "folder you can write into for -o.")
    missing = tmp_path / "new" / "out"
    monkeypatch.setattr(atomic, "writable", lambda p: Path(p) != tmp_path)
    assert main(_args(command, inputs, missing)) == 2
    assert _one_line(capsys) == (f"volreg {command}: error: Output directory `{missing}` cannot be created: "
                                 f"`{tmp_path}` is not writable; expected a folder you can write into for -o.")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_folder_in_a_parent_that_cannot_be_written_is_staged_inside_it(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old")
    monkeypatch.setattr(atomic, "writable", lambda p: Path(p) != tmp_path)
    monkeypatch.setattr(parts, "writable", lambda p: Path(p) != tmp_path)
    with pytest.raises(KeyboardInterrupt):
        with output_folder(out, force=True) as folder:
            assert folder.path.parent == out
            assert (out / ".volreg-lock").is_file()  # no lock beside a folder in a parent that cannot be written
            (folder.path / "a.txt").write_text("new")
            folder.record(folder.path / "a.txt")
            raise KeyboardInterrupt("SIGTERM")
    assert _contents(out) == {"a.txt": b"old"} and kept_results() == [out]
    with output_folder(out, force=True) as folder:
        (folder.path / "a.txt").write_text("new")
        folder.record(folder.path / "a.txt")
    assert _contents(out) == {"a.txt": b"new"} and sorted(p.name for p in out.iterdir()) == ["a.txt"]


# ----------------------------------------------------------------------------- mount points


def _in_mount_namespace(script: str, tmp_path: Path):
    """Run ``script`` (bash) in a mount namespace of its own, where it may bind-mount; skip where that cannot be."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare(1)")
    probe = subprocess.run(["unshare", "-rm", "true"], capture_output=True, check=False)
    if probe.returncode != 0:
        pytest.skip("no mount namespaces here")
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run(["unshare", "-rm", "bash", "-c", script], capture_output=True, text=True, env=env, check=False,
                          cwd=tmp_path, timeout=300)


def test_a_bind_mount_is_a_mount_point_and_is_written_in_place(tmp_path):
    """A bind mount of a folder of the same file system, which ``os.path.ismount`` misses: without
    seeing it, a --force run registered and then failed to rename it ("Device or resource busy")."""
    (tmp_path / "source").mkdir()
    (tmp_path / "out").mkdir()
    script = textwrap.dedent(f"""\
        set -e
        mount --bind source out
        {sys.executable} - <<'EOF'
        import os
        from pathlib import Path
        from volreg.io._atomic import output_folder
        from volreg.io._folder_parts import is_mount_point
        out = Path("out")
        assert not os.path.ismount(out) and is_mount_point(out)
        for text in ("old", "new"):
            with output_folder(out, force=True) as folder:
                assert folder.path.parent == out
                (folder.path / "a.txt").write_text(text)
                folder.record(folder.path / "a.txt")
        assert (out / "a.txt").read_text() == "new" and sorted(os.listdir(out)) == ["a.txt"]
        print("ok")
        EOF
        """)
    done = _in_mount_namespace(script, tmp_path)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
    assert not is_mount_point(tmp_path / "out") and (tmp_path / "source" / "a.txt").read_text() == "new"


@pytest.mark.system
def test_register_force_into_a_bind_mount_and_into_a_read_only_one(inputs, tmp_path):
    (tmp_path / "source").mkdir()
    (tmp_path / "out").mkdir()
    (tmp_path / "ro").mkdir()
    register = " ".join(f"'{a}'" for a in _args("register", inputs, Path("out"), ["--force"])[:-4])
    script = textwrap.dedent(f"""\
        mount --bind source out || exit 99
        mount --bind source ro && mount -o remount,bind,ro ro || exit 99
        {sys.executable} -m volreg {register} -o out --quiet --force || exit 1
        {sys.executable} -m volreg {register} -o out --quiet --force || exit 1
        {sys.executable} -m volreg {register} -o ro --quiet --force 2>ro.err
        echo "read-only: $?"
        """)
    done = _in_mount_namespace(script, tmp_path)
    if done.returncode == 99:
        pytest.skip("bind mounts cannot be made here")
    assert done.returncode == 0 and done.stdout.strip().endswith("read-only: 2"), (done.stdout, done.stderr)
    assert len(list((tmp_path / "source").iterdir())) == 10 and not _working_entries(tmp_path / "source")
    assert (tmp_path / "ro.err").read_text().strip() == (
        "volreg register: error: Output directory `ro` is not writable; expected a folder you can write into for -o.")


def test_signals_are_held_while_a_result_is_moved_in(tmp_path, monkeypatch):
    """SIGTERM while the files of a result written in place are moved in: the move completes first."""
    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.chdir(out)
    moved = []
    real_replace = os.replace

    def replace(src, dst):
        if not moved:
            os.kill(os.getpid(), signal.SIGTERM)
        moved.append(dst)
        real_replace(src, dst)

    previous = signal.signal(signal.SIGTERM, lambda *a: (_ for _ in ()).throw(KeyboardInterrupt("SIGTERM")))
    try:
        monkeypatch.setattr(parts.os, "replace", replace)
        with pytest.raises(KeyboardInterrupt):
            with output_folder(out, require_empty=False) as folder:
                for name in ("a.txt", "b.txt", "c.txt"):
                    (folder.path / name).write_text("new")
                    folder.record(folder.path / name)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert len(moved) == 3 and _contents(out) == {n: b"new" for n in ("a.txt", "b.txt", "c.txt")}
    assert _working_entries(out) == []


# ----------------------------------------------------------------------------- batch ids and resumed pairs


@pytest.mark.parametrize("sid", [".x", "y.volreg-old-999999999-0badc0de", "a.volreg-new-2-00000000", ".out.volreg-lock"])
def test_a_batch_id_that_could_name_a_working_folder_is_refused(tmp_path, sid):
    from volreg.cohort import read_manifest
    from volreg.errors import UsageError

    manifest = tmp_path / "m.csv"
    manifest.write_text(f"id,path\nok,a.nii.gz\n{sid},b.nii.gz\n")
    with pytest.raises(UsageError) as info:
        read_manifest(manifest)
    assert str(info.value) == (f"MANIFEST `{manifest}` line 3: id `{sid}` could name one of volreg's hidden working "
                               "folders (it starts with '.' or holds '.volreg-'); expected an id without either.")


@pytest.mark.parametrize("consistency", [False, True], ids=["register", "consistency"])
def test_a_pair_missing_or_altering_an_output_is_not_done(inputs, tmp_path, consistency):
    import json

    from volreg.cohort import pair_outputs, run_pair

    d, out = inputs, tmp_path / "pair"
    args = ("a", str(d / "a.nii.gz"), "b", str(d / "b.nii.gz"), str(out), str(d / "p.toml"), consistency)
    assert run_pair(*args)["status"] == "done"
    names = pair_outputs(None, consistency)
    recorded = json.loads((out / "batch_row.json").read_text())["outputs"]
    assert sorted(recorded) == sorted(names) and all((out / n).is_file() for n in names)
    assert run_pair(*args).get("skipped") is True
    h5 = "forward/warp.h5" if consistency else "warp.h5"
    (out / h5).unlink()
    again = run_pair(*args)
    assert again["status"] == "done" and not again.get("skipped") and (out / h5).is_file()
    field = out / ("backward/inverse_warp.nii.gz" if consistency else "inverse_warp.nii.gz")
    field.write_bytes(field.read_bytes()[:-10])  # truncated after it finished
    again = run_pair(*args)
    assert not again.get("skipped") and json.loads((out / "batch_row.json").read_text())["outputs"] != recorded


def test_a_pair_done_without_the_outputs_its_protocol_leaves_out_is_skipped(inputs, tmp_path):
    import json

    from volreg.cohort import run_pair

    d, out = inputs, tmp_path / "pair"
    args = ("a", str(d / "a.nii.gz"), "b", str(d / "b.nii.gz"), str(out), str(d / "noh5.toml"))
    assert run_pair(*args)["status"] == "done" and not (out / "warp.h5").exists()
    assert run_pair(*args).get("skipped") is True
    row = json.loads((out / "batch_row.json").read_text())
    del row["outputs"]  # a row that records no checksums: every output there is enough
    (out / "batch_row.json").write_text(json.dumps(row))
    assert run_pair(*args).get("skipped") is True
