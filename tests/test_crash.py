"""Kill commands at random moments: every output folder holds a complete result or none, and a rerun completes.

``register``, ``register --force`` over an existing result (in a folder, and in a folder named
through a symbolic link, which is written in place), ``consistency`` and ``batch`` are
killed with SIGKILL and SIGTERM at moments drawn uniformly over a whole run's duration, on a
tiny 2-D pair.  "Complete" means every output of the command is there and reads back.  The
default run draws 1 moment per command and signal; ``VOLREG_CRASH_MOMENTS=20`` draws 20.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from volreg.outputs.consistency import CONSISTENCY_OUTPUTS
from volreg.grid import LabelVolume
from volreg.io import read_image, read_labels, write_labels
from volreg.io.fields import read_displacement, read_itk_linear
from volreg.outputs.registration import REGISTRATION_OUTPUTS
from volreg.warp.model import KernelWarp

REPO = Path(__file__).resolve().parents[1]
MOMENTS = int(os.environ.get("VOLREG_CRASH_MOMENTS", "1"))
PROTOCOL = '[protocol]\nname = "crash"\n[warp]\nmin_width = 8.0\npad = 6.0\nmax_iter = 30\n'


def _disc_pair(d: Path) -> None:
    ii, jj = np.meshgrid(np.arange(48), np.arange(48), indexing="ij")
    for name, cx in (("a", 22), ("b", 25)):
        arr = np.zeros((48, 48), np.uint8)
        arr[((ii - cx) / 12.0) ** 2 + ((jj - 24) / 9.0) ** 2 < 1] = 1
        arr[(ii - cx - 3) ** 2 + (jj - 22) ** 2 < 16] = 2
        write_labels(LabelVolume(arr, (0.0, 0.0), (1.0, 1.0), np.eye(2)), d / f"{name}.nii.gz")
    (d / "p.toml").write_text(PROTOCOL)
    (d / "manifest.csv").write_text("id,path\na,a.nii.gz\nb,b.nii.gz\n")


def _registration_complete(folder: Path) -> bool:
    """Every output of `register` is in ``folder`` and reads back."""
    if not all((folder / name).is_file() for name in REGISTRATION_OUTPUTS):
        return False
    u, grid = read_displacement(folder / "warp.nii.gz")
    assert u.shape == (*grid.shape, 2)
    read_displacement(folder / "inverse_warp.nii.gz")
    assert read_labels(folder / "warped.nii.gz").shape == grid.shape
    assert read_image(folder / "jacobian.nii.gz")[0].shape == grid.shape
    assert KernelWarp.load(folder / "model.npz").dim == 2
    read_itk_linear(folder / "linear.tfm", dim=2)
    assert json.loads((folder / "report.json").read_text())["mean_dice"]["after"] is not None
    assert (folder / "report.png").stat().st_size > 0
    return True


def _complete(command: str, folder: Path) -> bool:
    if command == "consistency":
        if not all((folder / name).is_file() for name in CONSISTENCY_OUTPUTS):
            return False
        json.loads((folder / "consistency.json").read_text())
        return _registration_complete(folder / "forward") and _registration_complete(folder / "backward")
    if command == "batch":
        pairs = folder / "pairs"
        done = [p for p in pairs.iterdir() if not p.name.startswith(".")] if pairs.is_dir() else []
        return all(_registration_complete(p) for p in done)  # each pair folder: complete or absent
    return _registration_complete(folder)


def _args(command: str, d: Path, out: Path) -> list[str]:
    if command == "batch":
        return ["batch", str(d / "manifest.csv"), "-o", str(out), "--protocol", str(d / "p.toml"), "--pairs",
                "consecutive", "--workers", "1", "--quiet"]
    force = ["--force"] if command.startswith("register-force") else []
    name = "consistency" if command == "consistency" else "register"
    return [name, str(d / "a.nii.gz"), str(d / "b.nii.gz"), "-o", str(out), "--protocol", str(d / "p.toml"),
            "--quiet", *force]


def _interrupted(err: str, command: str, name: str) -> bool:
    """Whether stderr ends in the one line of an interrupted run: the command's own, or (a signal
    within the imports, before the command is known) the starting program's."""
    last = err.strip().splitlines()[-1] if err.strip() else ""
    return last.startswith(f"volreg {command}: interrupted by {name}") or last == (
        f"volreg: interrupted by {name} while starting; nothing was written.")


def _run(args: list[str], d: Path, kill_after: float | None = None, sig: int = signal.SIGKILL):
    """Run ``volreg ARGS`` in its own process group; with ``kill_after``, send ``sig`` then."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "volreg", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, cwd=d, start_new_session=True)
    if kill_after is not None:
        try:
            proc.wait(timeout=kill_after)
        except subprocess.TimeoutExpired:
            proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=300)
    finally:
        try:  # what the command started (Dask workers) goes with it, as under a job scheduler
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return proc.returncode, err


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("crash")
    _disc_pair(d)
    return d


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
@pytest.mark.parametrize("command", ["register", "register-force", "register-force-in-place", "consistency", "batch"])
def test_killed_runs_leave_complete_results_and_a_rerun_completes(inputs, tmp_path, command, sig):
    rng = np.random.default_rng(abs(hash((command, int(sig)))) % 2**32)
    d = inputs
    # one whole run: its duration bounds the moments, and it is the previous result for --force
    out = tmp_path / "out"
    if command == "register-force-in-place":  # a symbolic link cannot be swapped: written in place
        (tmp_path / "real").mkdir()
        out.symlink_to(tmp_path / "real", target_is_directory=True)
    t0 = time.perf_counter()
    rc, err = _run(_args(command, d, out), d)
    duration = time.perf_counter() - t0
    assert rc == 0, err
    assert _complete(command, out)
    forced = command.startswith("register-force")
    previous = (out / "report.json").read_text() if forced else None
    outcomes = {"killed": 0, "finished": 0}
    for k in range(MOMENTS):
        target = out if forced or command == "batch" else tmp_path / f"out{k}"
        moment = float(rng.uniform(0.0, duration))
        rc, err = _run(_args(command, d, target), d, kill_after=moment, sig=sig)
        outcomes["finished" if rc == 0 else "killed"] += 1
        assert rc in (0, 143, -signal.SIGTERM, -signal.SIGKILL), err
        if sig == signal.SIGTERM and rc == 143:  # (-15: the signal came before Python had started volreg)
            assert _interrupted(err, _args(command, d, target)[0], "SIGTERM"), err
        # complete old or complete new, or (a fresh folder) nothing
        if command in ("register", "consistency") and not target.exists():
            pass
        else:
            assert _complete(command, target), (command, moment, err)
        if forced:
            now = (target / "report.json").read_text()
            assert now == previous or json.loads(now)["mean_dice"]["after"] is not None
        # a rerun completes and leaves no hidden sibling behind
        rc, err = _run([*_args(command, d, target), *(["--force"] if command == "consistency" else [])], d)
        if command == "register":
            rc, err = (rc, err) if rc == 0 else _run([*_args(command, d, target), "--force"], d)
        assert rc == 0, err
        assert _complete(command, target)
        assert not [p for p in target.parent.iterdir() if ".volreg-" in p.name]
        assert not [p for p in target.iterdir() if ".volreg-" in p.name]
    assert sum(outcomes.values()) == MOMENTS
    print(f"{command} {sig.name}: {outcomes}")


@pytest.mark.parametrize("name, status", [("SIGTERM", 143), ("SIGINT", 130)])
def test_an_interrupt_inside_python_code_an_extension_runs_keeps_the_exit_status(tmp_path, name, status):
    """An interrupt that lands in Python code which an extension runs through CPython's PyRun_*
    functions marks the interpreter, which then used to end the process by SIGINT at exit, after
    the one-line report (exit -2 instead of 143; seen once in about 20 SIGTERMs of `python -m volreg
    register` 1.2 s after its start).  The command's exit status is kept."""
    script = tmp_path / "interrupted_run.py"
    script.write_text(
        "import ctypes, sys\n"
        "import volreg.cli.protocols as command\n"
        "from volreg.cli import main\n"
        "def run(args):\n"
        "    # the interrupt, raised inside code run through PyRun_*, then on its way up\n"
        f"    ctypes.pythonapi.PyRun_SimpleString(b\"raise KeyboardInterrupt({name!r})\")\n"
        f"    raise KeyboardInterrupt({name!r})\n"
        "command.run = run\n"
        "raise SystemExit(main(['protocols']))\n")
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    # run as a module, as `python -m volreg` is: CPython checks the mark after such a run
    proc = subprocess.run([sys.executable, "-m", script.stem], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=120)
    assert proc.returncode == status, (proc.returncode, proc.stderr)
    assert f"volreg protocols: interrupted by {name}" in proc.stderr


def test_an_interrupted_run_ends_with_its_one_line_report(tmp_path):
    """An object the interrupt left half-built (seen: llvmlite's, while numba loads) whose
    destructor fails on the way out printed "Exception ignored in ..." and a traceback after the
    report; the report stays the last line, and the exit status is kept."""
    script = tmp_path / "half_built.py"
    script.write_text(
        "import volreg.cli.protocols as command\n"
        "from volreg.cli import main\n"
        "class HalfBuilt:\n"
        "    def __del__(self):\n"
        "        raise AttributeError('no attribute _ptr')\n"
        "def run(args):\n"
        "    half = HalfBuilt()  # freed with the interrupt's traceback\n"
        "    raise KeyboardInterrupt('SIGTERM')\n"
        "command.run = run\n"
        "raise SystemExit(main(['protocols']))\n")
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-m", script.stem], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=120)
    assert proc.returncode == 143, (proc.returncode, proc.stderr)
    assert proc.stderr.strip().splitlines() == ["volreg protocols: interrupted by SIGTERM; the outputs of this run "
                                                "were removed."], proc.stderr


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_while_the_libraries_load_exits_cleanly(inputs, tmp_path, sig):
    """Signals 0.3-1.2 s after the start land while Python loads numpy, numba, SimpleITK, ...;
    held back until the handlers are in place, each ends the run with 143 (130 for SIGINT) and
    one line, or (before Python had started volreg) by the signal itself, and leaves nothing.
    Acted on inside a C extension's import, they ended it by SIGINT or a segmentation fault."""
    clean = {signal.SIGTERM: 143, signal.SIGINT: 130}[sig]
    for k, moment in enumerate(np.linspace(0.3, 1.2, 10)):
        target = tmp_path / f"out{k}"
        rc, err = _run(_args("register", inputs, target), inputs, kill_after=float(moment), sig=sig)
        assert rc in (0, clean, -sig), (moment, rc, err)
        if rc == clean:
            assert _interrupted(err, "register", sig.name), err
            assert not target.exists()
        assert not [p for p in tmp_path.iterdir() if ".volreg-" in p.name]


def test_a_signal_while_the_batch_cluster_starts_exits_cleanly(inputs, tmp_path):
    """SIGTERM 0.5-3 s after the start of a batch lands while Dask is loaded and its local cluster
    starts: each run ends with 143 and the batch's one line last on stderr (before, Dask's exit
    hook added a traceback after it, or Python ended by SIGINT), or by the signal itself."""
    for k, moment in enumerate(np.linspace(0.5, 3.0, 10)):
        target = tmp_path / f"out{k}"
        rc, err = _run(_args("batch", inputs, target), inputs, kill_after=float(moment), sig=signal.SIGTERM)
        assert rc in (0, 143, -signal.SIGTERM), (moment, rc, err)
        if rc == 143:
            assert _interrupted(err, "batch", "SIGTERM"), (moment, err)
