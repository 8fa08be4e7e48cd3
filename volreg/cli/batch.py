"""``volreg batch``: a cohort of registrations as Dask tasks (:func:`volreg.cohort.register_cohort`).

The command parses its arguments, runs the cohort and prints: news and failed pairs on stderr,
one summary line on stdout, and one line naming what was kept when it is interrupted.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path

from volreg.cli._common import PROG, _warn, output_path

__all__ = ["add_parser", "run"]


def add_parser(commands) -> None:
    """Add ``batch`` to the ``volreg`` subcommands (Dask is imported only when it runs)."""
    batch = commands.add_parser(
        "batch",
        help="register a cohort, one Dask task per pair, on this machine or a cluster",
        description="Register the label volumes listed in MANIFEST (CSV with columns id,path) to --template, or in "
        "pairs (all ordered pairs, or consecutive ones), one Dask task per registration: on a LocalCluster of "
        "--workers processes, or on the cluster at --scheduler. Every pair gets a full `volreg register` (or, with "
        "--consistency, `volreg consistency`) OUTDIR under OUTDIR/pairs/FIXED__MOVING; a rerun skips pairs that are "
        "complete with unchanged inputs and settings (protocol, --consistency, volreg version) and redoes the others. "
        "Writes OUTDIR/batch.csv (one row per pair, failures with their error) and "
        "OUTDIR/batch.png. Exit status 1 if any pair failed.",
    )
    batch.add_argument("manifest", metavar="MANIFEST", type=Path, help="CSV with columns id,path")
    batch.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, required=True, help="output directory")
    batch.add_argument("--template", metavar="T", type=Path, default=None, help="register every subject to this volume")
    batch.add_argument("--pairs", choices=("all", "consecutive"), default="all",
                       help="without --template: every ordered pair (default) or consecutive subjects")
    batch.add_argument("--consistency", action="store_true", help="register both ways and report consistency")
    batch.add_argument("--scheduler", metavar="ADDRESS", default=None, help="connect to this Dask scheduler")
    batch.add_argument("--workers", type=int, default=None, help="LocalCluster worker processes (default 2)")
    batch.add_argument("--protocol", metavar="NAME|FILE", default="default", help="protocol for every registration")
    batch.add_argument("--quiet", action="store_true", help="no progress bar")
    batch.set_defaults(run=run)


#: Failed pairs named one per line on stderr at most (the rest are counted; batch.csv has all).
_FAILED_LINES = 20


def run(args: argparse.Namespace) -> int:
    """``volreg batch MANIFEST -o OUTDIR``: every pair as a Dask task; exit status 1 if any failed."""
    from volreg.cohort import register_cohort
    from volreg.errors import CohortInterrupted, SchedulerUnavailable
    from volreg.progress import ProgressBars

    start = time.perf_counter()
    outdir: Path = args.output
    notify = None if args.quiet else (lambda line: print(f"{PROG} batch: {line}", file=sys.stderr))
    try:
        with ProgressBars(quiet=args.quiet) as progress:
            summary = register_cohort(args.manifest, outdir, template=args.template, pairs=args.pairs,
                                      consistency=args.consistency, protocol=args.protocol, workers=args.workers,
                                      scheduler=args.scheduler, progress=progress, notify=notify,
                                      compile_helpers=getattr(args, "compile_helpers", None))
    except SchedulerUnavailable as exc:
        print(f"{PROG} batch: error: {exc}", file=sys.stderr)
        return 1
    except CohortInterrupted as exc:
        # Finished pairs are complete results and stay; say so rather than "outputs removed".
        print(f"{PROG} batch: interrupted by {exc.signal_name}; {exc.finished} of {exc.total} pairs finished and are "
              f"kept in `{outdir / 'pairs'}` (a rerun skips them); the {exc.total - exc.finished} others are "
              f"unfinished and a rerun redoes them; `{outdir / 'batch.csv'}` was not written.", file=sys.stderr)
        # a cluster interrupted while starting complains when it is collected; the line above says it all
        sys.unraisablehook = lambda unraisable: None
        return 130 if exc.signal_name == "SIGINT" else 128 + int(signal.SIGTERM)
    rows, failed = summary.rows, summary.failed
    again = f", {summary.redone} redone (inputs, protocol or volreg version changed)" if summary.redone else ""
    for r in failed[:_FAILED_LINES]:
        _warn("batch", f"pair {r['fixed_id']} <- {r['moving_id']} failed: {r.get('error') or 'no message'}")
    if len(failed) > _FAILED_LINES:
        _warn("batch", f"{len(failed) - _FAILED_LINES} more pairs failed; see batch.csv.")
    print(f"{PROG} batch: {len(rows) - len(failed)} of {len(rows)} pairs done ({summary.skipped} already done, "
          f"skipped{again}), {len(failed)} failed; {outdir / 'batch.csv'} ({time.perf_counter() - start:.0f} s)")
    return 1 if failed else 0
