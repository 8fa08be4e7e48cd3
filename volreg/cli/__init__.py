"""The ``volreg`` command line: parse -> io -> numerics -> io.

Commands
--------
``volreg surface LABELS -o OUTDIR``
    Boundary meshes and kernel implicit surfaces (paper Section 4) of the
    labels of a label volume.

Exit status is 0 on success and 2 for any invalid input (a file that cannot
be read or written, a bad argument, a label that cannot give a surface); the
error is then one line on stderr, ``volreg <command>: error: <message>``, and
no output file is left behind.  Any other exception is a bug and propagates
with its traceback.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path

from volreg import __version__
from volreg.cli._common import EXPECTED_ERRORS, PROG, UsageError, _float_at_least, _label_list, _warn
from volreg.cli.consistency import run_consistency as _consistency
from volreg.cli.register import _apply, _demo, _protocols, _register
from volreg.cli.register_surfaces import add_surface_commands
from volreg.cli.surface import _surface
from volreg.cli.tune import run_tune as _tune
from volreg.errors import VolregWarning
from volreg.progress import clear_interrupt, note_interrupt

__all__ = ["main", "build_parser", "UsageError"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``volreg`` command, with its subcommands."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Kernel registration of label volumes (Schölkopf, Steinke & Blanz, ICML 2005). "
        "World coordinates are ITK physical space: LPS, millimetres.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    surface = commands.add_parser(
        "surface",
        help="meshes and implicit surfaces of the labels of a label volume",
        description="For each label: a boundary mesh with outward normals (OUTDIR/label_<id>.vtk; "
        "line segments for a 2-D image) and the fitted kernel implicit surface sampled on the input "
        "grid as a float32 signed distance in mm, negative inside (OUTDIR/sdf_<id>.nii.gz), plus "
        "OUTDIR/surface.json summarising the run.",
    )
    surface.add_argument(
        "image", metavar="LABELS", type=Path,
        help="label volume: .nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd or .vti",
    )
    surface.add_argument("-o", "--output", metavar="OUTDIR", type=Path, required=True,
                         help="output directory (created if missing)")
    surface.add_argument("--labels", metavar="IDS", type=_label_list, default=None,
                         help="comma-separated labels to process, e.g. 1,3 (default: every non-zero label)")
    surface.add_argument("--skip-small", action="store_true",
                         help="warn about and skip labels that are absent or too small, instead of failing")
    surface.add_argument("--smoothing", metavar="VOXELS", type=_float_at_least(0.0, strict=False, upper=10.0), default=1.0,
                         help="Gaussian blur (s.d.) of each mask before contouring, in units of the largest voxel spacing "
                         "(default 1.0; 0: none)")
    surface.add_argument("--min-width", metavar="VOXELS", type=_float_at_least(0.0, strict=True), default=4.0,
                         help="finest kernel width of the implicit surface, in units of the largest voxel spacing (default 4)")
    surface.add_argument("--force", action="store_true", help="overwrite existing outputs")
    surface.add_argument("--quiet", action="store_true", help="no progress bars")
    surface.set_defaults(run=_surface)

    register = commands.add_parser(
        "register",
        help="register two label volumes (the main job)",
        description="Register the MOVING label volume to the FIXED one with a kernel warp driven by the "
        "labels' surfaces, and write into OUTDIR: warp.nii.gz (ANTs/ITK displacement field on the fixed grid, "
        "LPS mm, pull-back), warped.nii.gz (moving labels on the fixed grid), model.npz (the kernel warp), "
        "jacobian.nii.gz (det of its analytic Jacobian), report.json and report.png.",
    )
    register.add_argument("fixed", metavar="FIXED", type=Path, help="fixed label volume (defines the output grid)")
    register.add_argument("moving", metavar="MOVING", type=Path, help="moving label volume")
    _common_register_options(register)
    register.set_defaults(run=_register)

    apply = commands.add_parser(
        "apply",
        help="warp an image with a saved result",
        description="Resample IMAGE (labels or intensities) onto the grid of REF through a saved warp: "
        "a model.npz or an ANTs/ITK displacement field (warp.nii.gz) from `volreg register`.",
    )
    apply.add_argument("warp", metavar="MODEL_OR_WARP", type=Path, help="model.npz or warp.nii.gz")
    apply.add_argument("image", metavar="IMAGE", type=Path, help="image in moving space")
    apply.add_argument("--reference", metavar="REF", type=Path, required=True, help="image whose grid the output takes (fixed space)")
    apply.add_argument("-o", "--output", metavar="OUT", type=Path, required=True, help="output image (.nii.gz, .nii, .nrrd, .mha)")
    apply.add_argument("--interpolation", choices=("label", "nearest", "linear", "bspline"), default="label",
                       help="label: label-preserving (per-label signed distances, default); nearest; linear or bspline "
                       "for intensity images (written as float32)")
    apply.add_argument("--force", action="store_true", help="overwrite an existing output")
    apply.add_argument("--quiet", action="store_true", help="no progress bars")
    apply.set_defaults(run=_apply)

    protocols = commands.add_parser("protocols", help="list the shipped protocols",
                                    description="List the protocol presets, one line each.")
    protocols.set_defaults(run=_protocols)

    demo = commands.add_parser(
        "demo",
        help="register pyvista's frog to a copy deformed by a known warp",
        description="The frog tissue labels shipped with pyvista, block-downsampled to 3 mm (or at their native "
        "1 x 1 x 1.5 mm with --full), registered to a copy deformed by a known smooth warp (up to 8 mm); prints "
        "Dice and the endpoint error against the truth and writes every output of `volreg register` to OUTDIR.",
    )
    demo.add_argument("-o", "--output", metavar="OUTDIR", type=Path, default=Path("volreg-demo"),
                      help="output directory (default ./volreg-demo)")
    demo.add_argument("--full", action="store_true", help="native resolution (slow)")
    demo.add_argument("--protocol", metavar="NAME|FILE", default="default", help="protocol preset or TOML file (default: default)")
    demo.add_argument("--force", action="store_true", help="overwrite existing outputs")
    demo.add_argument("--quiet", action="store_true", help="no progress bars")
    demo.add_argument("-v", "--verbose", action="store_true", help="log each stage and warp level to stderr")
    demo.set_defaults(run=_demo)

    consistency = commands.add_parser(
        "consistency",
        help="the consistency test: register A->B and B->A, compose, report the error",
        description="Register A to B and B to A (into OUTDIR/forward and OUTDIR/backward), or load both "
        "directions saved by `volreg register` (--forward, --backward), compose tau_BA(tau_AB(x)) at every voxel "
        "of A's padded labels and at A's surface vertices, and write consistency.json (inverse-consistency error "
        "in mm and voxels: mean, median, p95, max; round-trip Dice per label), consistency_error.nii.gz (the error "
        "on A's grid) and consistency.png.",
    )
    consistency.add_argument("a", metavar="A", type=Path, help="label volume A")
    consistency.add_argument("b", metavar="B", type=Path, help="label volume B")
    consistency.add_argument("-o", "--output", metavar="OUTDIR", type=Path, required=True, help="output directory")
    consistency.add_argument("--forward", metavar="RESULT_AB", type=Path, default=None,
                             help="OUTDIR of `volreg register A B` (skip registering; needs --backward)")
    consistency.add_argument("--backward", metavar="RESULT_BA", type=Path, default=None,
                             help="OUTDIR of `volreg register B A` (needs --forward)")
    consistency.add_argument("--protocol", metavar="NAME|FILE", default=None,
                             help="protocol preset or TOML file for both registrations (default: default)")
    consistency.add_argument("--drive-labels", metavar="IDS", type=_label_list, default=None,
                             help="labels whose surfaces drive both warps (default: as `volreg register`)")
    consistency.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    consistency.add_argument("--quiet", action="store_true", help="no progress bars")
    consistency.add_argument("-v", "--verbose", action="store_true", help="log each stage and warp level to stderr")
    consistency.set_defaults(run=_consistency)

    tune = commands.add_parser(
        "tune",
        help="choose warp settings by consistency and hold-out",
        description="Register A to B and B to A for every combination of the --grid values (replacing the "
        "protocol's [warp] settings), score each by the inverse-consistency error plus the hold-out surface "
        "distance (plus the landmark error with --landmarks), all in mm, and write OUTDIR/tune.csv (one row per "
        "setting) and OUTDIR/tuned.toml (the protocol with the best setting).",
    )
    tune.add_argument("a", metavar="A", type=Path, help="label volume A")
    tune.add_argument("b", metavar="B", type=Path, help="label volume B")
    tune.add_argument("-o", "--output", metavar="OUTDIR", type=Path, required=True, help="output directory")
    tune.add_argument("--grid", metavar="KEY=V1,V2,...", action="append", required=True,
                      help="[warp] settings and their candidate values, e.g. lambda_loc=10,100,alpha=0,10 (repeatable)")
    tune.add_argument("--protocol", metavar="NAME|FILE", default="default",
                      help="protocol giving every other setting (default: default)")
    tune.add_argument("--drive-labels", metavar="IDS", type=_label_list, default=None,
                      help="labels whose surfaces drive the warps (default: as `volreg register`)")
    tune.add_argument("--landmarks", metavar=("A_PTS", "B_PTS"), nargs=2, type=Path, default=None,
                      help="corresponding points of A and B (.csv x,y,z LPS mm, .fcsv, .mrk.json)")
    tune.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    tune.add_argument("--quiet", action="store_true", help="no per-setting lines on stderr")
    tune.set_defaults(run=_tune)

    add_surface_commands(commands)

    batch = commands.add_parser(
        "batch",
        help="register a cohort, one Dask task per pair, on this machine or a cluster",
        description="Register the label volumes listed in MANIFEST (CSV with columns id,path) to --template, or in "
        "pairs (all ordered pairs, or consecutive ones), one Dask task per registration: on a LocalCluster of "
        "--workers processes, or on the cluster at --scheduler. Every pair gets a full `volreg register` (or, with "
        "--consistency, `volreg consistency`) OUTDIR under OUTDIR/pairs/FIXED__MOVING; a rerun skips pairs that are "
        "complete with unchanged inputs. Writes OUTDIR/batch.csv (one row per pair, failures with their error) and "
        "OUTDIR/batch.png. Exit status 1 if any pair failed.",
    )
    batch.add_argument("manifest", metavar="MANIFEST", type=Path, help="CSV with columns id,path")
    batch.add_argument("-o", "--output", metavar="OUTDIR", type=Path, required=True, help="output directory")
    batch.add_argument("--template", metavar="T", type=Path, default=None, help="register every subject to this volume")
    batch.add_argument("--pairs", choices=("all", "consecutive"), default="all",
                       help="without --template: every ordered pair (default) or consecutive subjects")
    batch.add_argument("--consistency", action="store_true", help="register both ways and report consistency")
    batch.add_argument("--scheduler", metavar="ADDRESS", default=None, help="connect to this Dask scheduler")
    batch.add_argument("--workers", type=int, default=None, help="LocalCluster worker processes (default 2)")
    batch.add_argument("--protocol", metavar="NAME|FILE", default="default", help="protocol for every registration")
    batch.add_argument("--quiet", action="store_true", help="no progress bar")
    batch.set_defaults(run=_batch)
    return parser


def _common_register_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-o", "--output", metavar="OUTDIR", type=Path, required=True, help="output directory")
    parser.add_argument("--protocol", metavar="NAME|FILE", default="default",
                        help="protocol preset (see `volreg protocols`) or TOML file (default: default)")
    parser.add_argument("--drive-labels", metavar="IDS", type=_label_list, default=None,
                        help="labels whose surfaces drive the warp, e.g. 1,4,7 (default: every label in both "
                        "volumes that is compact enough); every label is warped")
    parser.add_argument("--landmarks", metavar=("FIXED_PTS", "MOVING_PTS"), nargs=2, type=Path, default=None,
                        help="corresponding points (.csv x,y,z LPS mm, Slicer .fcsv or .mrk.json)")
    parser.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("-v", "--verbose", action="store_true", help="log each stage and warp level to stderr")


def _batch(args: argparse.Namespace) -> int:
    # Imported when run: Dask and its workers are needed only here.
    from volreg.cli.batch import run_batch

    return run_batch(args)


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def _install_sigterm():
    """Make SIGTERM raise KeyboardInterrupt("SIGTERM"); return the previous handler (None off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_interrupt)


def _unraisable_hook(previous):
    """A ``sys.unraisablehook`` that keeps a KeyboardInterrupt raised where it could not propagate.

    Ctrl-C or SIGTERM during numba's first compilation of a kernel lands in an llvmlite
    ctypes callback; Python reports it there as "Exception ignored" and the run went on to
    finish (exit 0).  Recorded instead, it is raised again at the next progress report.
    """

    def hook(unraisable) -> None:
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            note_interrupt(str(unraisable.exc_value or "") or "SIGINT")
            return
        previous(unraisable)

    return hook


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``volreg`` command line.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        Exit status: 0 on success, 2 for a usage error or invalid input
        (reported as one line on stderr), 130 after Ctrl-C (SIGINT) and 143
        after SIGTERM (the run's outputs removed).  ``--help`` and
        ``--version`` return 0.

    Raises
    ------
    Exception
        Anything other than volreg's input errors (:class:`~volreg.io.VolregIOError`,
        :class:`~volreg.surfaces.SurfaceError`, :class:`~volreg.volume.GeometryError`,
        :class:`UsageError`) is a bug and propagates with its traceback.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as exc:  # argparse exits for --help, --version and usage errors
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    # SIGTERM (a scheduler or `kill` stopping the job) unwinds like Ctrl-C, so every command's
    # clean-up runs: outputs written so far are removed and temporary files deleted.
    previous = _install_sigterm()
    unraisable = sys.unraisablehook
    if previous is not None:  # the main thread: signals are delivered here
        clear_interrupt()
        sys.unraisablehook = _unraisable_hook(unraisable)
    show = warnings.showwarning

    def one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
        _warn(args.command, " ".join(str(message).split()))

    warnings.showwarning = one_line_warning
    filters = warnings.catch_warnings()
    filters.__enter__()
    warnings.simplefilter("always", VolregWarning)  # shown (one line each) whatever the global filters say
    try:
        output = getattr(args, "output", None)
        if output is not None and ".." in Path(output).parts:
            raise UsageError(
                f"-o `{output}` contains '..'; expected an output path without '..' components "
                f"(e.g. `{Path(os.path.normpath(os.path.abspath(output)))}`), so outputs stay where they are named."
            )
        return args.run(args)
    except EXPECTED_ERRORS as exc:
        message = " ".join(str(exc).split("\n")).strip() or type(exc).__name__
        print(f"{PROG} {args.command}: error: {message}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader of stdout went away (`volreg protocols | head -1`): stop quietly, as
        # command-line tools killed by SIGPIPE do, and keep Python's exit-time flush from
        # raising again on the closed pipe.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return 128 + int(signal.SIGPIPE)
    except KeyboardInterrupt as exc:
        name = str(exc) or "SIGINT"
        print(f"{PROG} {args.command}: interrupted by {name}; the outputs of this run were removed.", file=sys.stderr)
        return 130 if name == "SIGINT" else 128 + int(signal.SIGTERM)
    finally:
        filters.__exit__(None, None, None)
        warnings.showwarning = show
        if previous is not None:
            sys.unraisablehook = unraisable
            clear_interrupt()
            signal.signal(signal.SIGTERM, previous)
