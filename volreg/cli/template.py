"""``volreg template``: the unbiased template of a cohort's label maps (:func:`volreg.template.build_template`).

The command parses its arguments, builds the template and prints: news on stderr, one summary
line on stdout.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path

from volreg.cli._common import PROG, _float_at_least, _integer_at_least, _warn, output_path

__all__ = ["add_parser", "run"]


def add_parser(commands) -> None:
    """Add ``template`` to the ``volreg`` subcommands (Dask is imported only when it runs)."""
    p = commands.add_parser(
        "template",
        help="build the unbiased template of a cohort's label maps, with every subject's registration to it",
        description="Build the template of the label maps listed in MANIFEST (CSV with columns id,path, as for "
        "`volreg batch`): the subjects' mean affine pose first, then iterations of registering every subject to the "
        "template (one Dask task each, as `volreg batch --template`) and moving the template by the mean of their "
        "displacements, until that update's mean is at most --tolerance or stops falling. Writes OUTDIR/template.nii.gz, "
        "OUTDIR/probabilities.nii.gz (4-D, one frame per label; frames named in OUTDIR/labels.csv), "
        "OUTDIR/subjects/ID/ (each subject's `volreg register TEMPLATE SUBJECT` outputs), OUTDIR/report.json and "
        "OUTDIR/report.png. An unfinished OUTDIR is continued; a finished one needs --force.",
    )
    p.add_argument("manifest", metavar="MANIFEST", type=Path, help="CSV with columns id,path")
    p.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, required=True, help="output directory")
    p.add_argument("--iterations", type=_integer_at_least(1), default=5, help="at most this many rounds of registration (default 5)")
    p.add_argument("--tolerance", type=_float_at_least(0.0, strict=True), default=None, metavar="MM",
                   help="stop once the mean shape update is at most this (default: a quarter of the spacing)")
    p.add_argument("--spacing", type=_float_at_least(0.0, strict=True), default=None, metavar="MM",
                   help="template voxel size (default: the finest among the subjects)")
    p.add_argument("--linear", choices=("rigid", "similarity", "affine"), default="affine",
                   help="family of the subjects' mean pose (default affine)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None, help="connect to this Dask scheduler")
    p.add_argument("--workers", type=int, default=None, help="LocalCluster worker processes (default 2)")
    p.add_argument("--protocol", metavar="NAME|FILE", default="default", help="protocol for every registration")
    p.add_argument("--force", action="store_true", help="build again over a finished template in OUTDIR")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``volreg template MANIFEST -o OUTDIR``."""
    from volreg.errors import CohortInterrupted, SchedulerUnavailable
    from volreg.progress import ProgressBars
    from volreg.template import build_template

    start = time.perf_counter()
    outdir: Path = args.output
    notify = None if args.quiet else (lambda line: print(f"{PROG} template: {line}", file=sys.stderr))
    try:
        with ProgressBars(quiet=args.quiet) as progress:
            result = build_template(args.manifest, outdir, iterations=args.iterations, tolerance=args.tolerance,
                                    spacing=args.spacing, linear=args.linear, protocol=args.protocol,
                                    workers=args.workers, scheduler=args.scheduler, progress=progress, notify=notify,
                                    force=args.force, compile_helpers=getattr(args, "compile_helpers", None),
                                    warn=lambda line: _warn("template", line))
    except SchedulerUnavailable as exc:
        print(f"{PROG} template: error: {exc}", file=sys.stderr)
        return 1
    except CohortInterrupted as exc:
        print(f"{PROG} template: interrupted by {exc.signal_name}; the finished registrations are kept in "
              f"`{outdir / 'iterations'}` and a rerun continues from them; the template was not written.",
              file=sys.stderr)
        sys.unraisablehook = lambda unraisable: None
        return 130 if exc.signal_name == "SIGINT" else 128 + int(signal.SIGTERM)
    report = result.report
    if report["outliers"]:
        _warn("template", f"subjects far from the template: {', '.join(report['outliers'])} (see report.json "
                          "\"ranking\").")
    last = report["iterations"][-1]
    state = {"tolerance": "converged", "no progress": "stopped: the update no longer falls",
             "iterations": "stopped at --iterations"}.get(report["stopped"], "stopped")
    print(f"{PROG} template: {len(report['subjects'])} subjects, {len(report['iterations'])} iterations ({state}); "
          f"mean shape update {last['update_mean_mm']:.2f} mm, mean Dice to the template {last['mean_dice']:.3f}; "
          f"{outdir / 'template.nii.gz'} ({time.perf_counter() - start:.0f} s)")
    return 0
