"""Pieces shared by the whole-command benchmarks (`bench_pose.py`, `bench_speed.py`).

- :func:`timed`: run a command as a fresh process, timed from start to exit, with its own peak RSS
  (measured by ``wait4`` in a small launcher, see below);
- :func:`run_peer`: ANTs (antspyx) and greedy (picsl_greedy) as the benchmarks run them, each writing
  one displacement field on the fixed grid (LPS mm, pull-back) to ``OUT/warp.nii.gz``;
- :func:`score_field`: endpoint error against a known map, Dice over the labels of at least
  :data:`LARGE` voxels and (optionally) the folded fraction, for such a field;
- :func:`smooth_bumps`: the known smooth warps (10 Gaussian bumps over the labels' box).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

LARGE = 100  # voxels: Dice over the labels of at least this size
THREADS = 2
CHUNK = 1 << 18  # points per block when mapping many points
PEERS = ("ants", "ants-SyNOnly", "ants-SyNRA", "greedy", "greedy-moments", "greedy-deformable")


def smooth_bumps(fixed, max_displacement: float, seed: int):
    """Ten Gaussian bumps over the fixed labels' box, scale 0.15 x its diagonal (as `volreg demo`).

    Parameters
    ----------
    fixed : LabelVolume
    max_displacement : float, mm
    seed : int

    Returns
    -------
    volreg.synthetic.GaussianBumps
    """
    from volreg.synthetic import GaussianBumps

    points = fixed.grid_points()[fixed.array > 0]
    lo, hi = points.min(axis=0), points.max(axis=0)
    return GaussianBumps.random(lo, hi, max_displacement=max_displacement, scale=0.15 * float(np.linalg.norm(hi - lo)),
                                count=10, rng=np.random.default_rng(seed))


def run_env(**extra: str) -> dict:
    """The environment of every run: two threads, ANTs seeded, plus ``extra``; Python's bytecode
    cached as on a system where the packages are installed (pip compiles them at install), also
    where this machine's environment says not to write it (``PYTHONDONTWRITEBYTECODE``), which
    made every volreg run compile its own modules again (0.15 s)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    return dict(env, ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS=str(THREADS), ANTS_RANDOM_SEED="1",
                NUMBA_NUM_THREADS=str(THREADS), OMP_NUM_THREADS=str(THREADS), **extra)


# A process started by a large one would report that one's peak RSS as its own: Linux counts the
# memory of the process that called exec into the peak of the program it starts. So every run is
# started, timed and measured by this small launcher (a bare Python), itself started by the benchmark.
_LAUNCHER = """
import json, os, subprocess, sys, threading, time
command, log, cwd, timeout = json.loads(sys.argv[1])
with open(log, "w") as out:
    t0 = time.perf_counter()
    proc = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, cwd=cwd)
    timer = threading.Timer(timeout, proc.kill)
    timer.start()
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - t0
    timer.cancel()
print(json.dumps([os.waitstatus_to_exitcode(status), seconds, usage.ru_maxrss / 1024**2]))
"""


def timed(command: list[str], log: Path, cwd: Path, timeout: float, env: dict | None = None) -> tuple[int, float, float]:
    """Run ``command`` in ``cwd`` as a fresh process (stdout and stderr to ``log``).

    Returns
    -------
    exit status, wall seconds (start to exit), peak RSS (GB; Linux reports kB)
    """
    job = json.dumps([command, str(log), str(cwd), timeout])
    res = subprocess.run([sys.executable, "-c", _LAUNCHER, job], capture_output=True, text=True,
                         env=run_env() if env is None else env, check=True)
    rc, seconds, rss = json.loads(res.stdout)
    return int(rc), float(seconds), float(rss)


def last_line(log: Path, rc: int, seconds: float) -> str:
    """The last non-empty line of a failed run's ``log``, for a table cell."""
    lines = [s for s in log.read_text(errors="replace").splitlines() if s.strip()]
    return (lines[-1][:160] if lines else f"exit status {rc}") + f" (exit {rc}, {seconds:.0f} s)"


def run_peer(method: str, fixed: str, moving: str, out: str) -> None:
    """Register ``moving`` to ``fixed`` (NIfTI label images, read as float) with a peer and write
    its displacement field on the fixed grid to ``out``/warp.nii.gz (LPS mm, pull-back).

    ``ants``: antspyx ``registration(type_of_transform="SyN")`` (centre-of-mass start, affine, SyN,
    Mattes mutual information); ``ants-NAME``: ``type_of_transform=NAME`` (``SyNOnly``, ``SyNRA``);
    the forward transforms composed into one field. ``greedy``: picsl_greedy, affine (``-a -dof 12
    -ia-image-centers``, SSD, 100x50x10) then deformable (SSD, 100x50x20, smoothing 2 and 1 voxels),
    composed by greedy (``-rc``); ``greedy-moments`` starts the affine from the images' inertia
    tensors (``-moments 2 -det 1``); ``greedy-deformable`` is the deformable stage alone.
    """
    out_dir = Path(out)
    if method == "ants" or method.startswith("ants-"):
        import ants

        f = ants.image_read(fixed, pixeltype="float")
        m = ants.image_read(moving, pixeltype="float")
        reg = ants.registration(f, m, type_of_transform="SyN" if method == "ants" else method.split("-", 1)[1],
                                outprefix=str(out_dir / "ants_"))
        # the forward transforms (warp, then affine) composed into one field on the fixed grid
        composed = ants.apply_transforms(f, m, reg["fwdtransforms"], compose=str(out_dir / "composed"))
        shutil.move(composed, out_dir / "warp.nii.gz")
    elif method in ("greedy", "greedy-moments", "greedy-deformable"):
        from picsl_greedy import Greedy3D

        g = Greedy3D()
        deform = "-n 100x50x20 -m SSD -s 2vox 1vox"
        if method == "greedy-deformable":
            g.execute(f"-d 3 -threads {THREADS} -i {fixed} {moving} -o {out_dir}/warp.nii.gz {deform}")
            return
        start = "-ia-image-centers"
        if method == "greedy-moments":  # a rigid start from the images' inertia tensors
            g.execute(f"-d 3 -threads {THREADS} -moments 2 -det 1 -i {fixed} {moving} -o {out_dir}/moments.mat")
            start = f"-ia {out_dir}/moments.mat"
        g.execute(f"-d 3 -threads {THREADS} -a -dof 12 {start} -i {fixed} {moving} -o {out_dir}/affine.mat "
                  "-n 100x50x10 -m SSD")
        g.execute(f"-d 3 -threads {THREADS} -i {fixed} {moving} -it {out_dir}/affine.mat -o {out_dir}/deform.nii.gz "
                  f"{deform}")
        g.execute(f"-d 3 -threads {THREADS} -rf {fixed} -r {out_dir}/deform.nii.gz {out_dir}/affine.mat "
                  f"-rc {out_dir}/warp.nii.gz")
    else:
        raise ValueError(f"Expected a peer `method` in {PEERS}, got {method!r}.")


def folded_fraction_of_field(u: np.ndarray, grid, slab: int = 32) -> float:
    """Fraction of the grid's voxels where ``det(I + du/dx) <= 0``, by central differences
    (one-sided at the edges), slab by slab along the first axis to bound memory.

    Parameters
    ----------
    u : (X, Y, Z, 3) float ndarray, LPS mm
        Displacement on ``grid``.
    grid : Grid or LabelVolume
        Its geometry (any direction).
    """
    # x = origin + D diag(s) i, so du/dx = du/di diag(1/s) D^T
    to_world = np.diag(1.0 / np.asarray(grid.spacing, float)) @ np.asarray(grid.direction, float).T
    n = u.shape[0]
    folded = 0
    for a in range(0, n, slab):
        lo, hi = max(a - 1, 0), min(a + slab + 1, n)
        block = np.asarray(u[lo:hi], np.float64)
        grads = np.stack([np.stack(np.gradient(block[..., c]), axis=-1) for c in range(3)], axis=-2)  # [..., c, i]
        keep = grads[a - lo : a - lo + min(slab, n - a)]
        det = np.linalg.det(keep @ to_world + np.eye(3))
        folded += int(np.count_nonzero(det <= 0))
    return folded / float(np.prod(u.shape[:3]))


def score_field(fixed, moving, truth, field_path: Path, *, folding: bool = False) -> dict:
    """Scores of the displacement field at ``field_path`` (on the fixed grid).

    Parameters
    ----------
    fixed, moving : LabelVolume
    truth : callable
        The true pull-back map, (N, 3) -> (N, 3) LPS mm.
    field_path : Path
    folding : bool
        Also the folded fraction of the grid (:func:`folded_fraction_of_field`).

    Returns
    -------
    dict
        ``epe_mean``, ``epe_p95`` (mm): |tau(x) - tau_true(x)| at the fixed voxel centres inside the
        labels; ``dice``: mean over the fixed labels of at least LARGE voxels, between the fixed labels
        and the moving labels resampled through the field (volreg's label-preserving resampling, the
        same for every method); with ``folding``, ``folded``.
    """
    from volreg.evaluation.metrics import dice
    from volreg.io.fields import read_displacement
    from volreg.warp.resample import resample_labels

    u, grid = read_displacement(field_path)
    if not grid.same_geometry(fixed, atol=1e-3):
        raise ValueError(f"Expected the field `{field_path}` on the fixed grid, got {grid}.")
    x = fixed.grid_points()
    positions = x + u
    inside = fixed.array > 0
    xi, pi = x[inside], positions[inside]
    err = np.concatenate([np.linalg.norm(pi[s : s + CHUNK] - truth(xi[s : s + CHUNK]), axis=1)
                          for s in range(0, len(xi), CHUNK)])
    del x, xi, pi
    warped = resample_labels(moving, positions)
    del positions
    values, counts = np.unique(fixed.array[inside], return_counts=True)
    d = [dice(fixed.array == v, warped == v) for v, c in zip(values, counts) if c >= LARGE]
    out = {"epe_mean": float(err.mean()), "epe_p95": float(np.percentile(err, 95)), "dice": float(np.mean(d))}
    if folding:
        out["folded"] = folded_fraction_of_field(u, grid)
    return out


def add_run_options(parser: argparse.ArgumentParser) -> None:
    """The options of every whole-command benchmark: ``--volreg-command``, ``--peer-python``,
    ``--timeout``, ``--workdir`` and the hidden ``--peer METHOD FIXED MOVING OUT`` (one peer run)."""
    repo = Path(__file__).resolve().parents[1]
    parser.add_argument("--volreg-command", default=str(repo / ".venv" / "bin" / "volreg"),
                        help="the volreg command line (default: the repository's .venv/bin/volreg)")
    parser.add_argument("--peer-python", default=sys.executable, help="Python with the bench extra (default: this one)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds before a run is stopped")
    parser.add_argument("--workdir", type=Path, default=None, help="keep the volumes and outputs in this new folder")
    parser.add_argument("--peer", nargs=4, metavar=("METHOD", "FIXED", "MOVING", "OUT"), help=argparse.SUPPRESS)


def print_header(script: str) -> None:
    """The command line that runs ``script`` (``PYTHON`` for the interpreter) and the machine's load."""
    print(f"```\nPYTHON benchmarks/{script} " + " ".join(shlex.quote(a) for a in sys.argv[1:]) + "\n```\n")
    load = os.getloadavg()
    print(f"{os.cpu_count()} CPU cores; load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} at the start "
          f"(1 / 5 / 15 min); every method with {THREADS} threads.\n", flush=True)


def grid_text(v) -> str:
    """``X x Y x Z of sx x sy x sz mm[, oblique] (N M voxels)`` for a volume or grid."""
    oblique = "" if np.allclose(v.direction, np.eye(3)) else ", oblique"
    return (f"{' x '.join(map(str, v.shape))} of {' x '.join(f'{s:g}' for s in v.spacing)} mm{oblique} "
            f"({np.prod(v.shape) / 1e6:.2f} M voxels)")
