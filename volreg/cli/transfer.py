"""``volreg transfer``: carry a per-vertex array from TARGET onto SOURCE through a saved registration."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from volreg.cli._common import PROG
from volreg.cli._surfaces import _load_model, _read
from volreg.errors import UsageError
from volreg.io import write_mesh
from volreg.morph import transfer_values

__all__ = ["add_parser", "run"]


def add_parser(commands) -> None:
    """Add ``transfer`` to the ``volreg`` subcommands."""
    tr = commands.add_parser(
        "transfer",
        help="carry a per-vertex array from TARGET onto SOURCE through a registration",
        description="For every SOURCE vertex v, take the value of --array at the TARGET point nearest to tau(v) "
        "(nearest vertex, or interpolated in the nearest triangle; integer arrays stay labels) and write SOURCE "
        "with the array to OUT.",
    )
    tr.add_argument("source", metavar="SOURCE", type=Path)
    tr.add_argument("target", metavar="TARGET", type=Path)
    tr.add_argument("--result", metavar="OUTDIR", type=Path, required=True, help="OUTDIR of `volreg register-surfaces`")
    tr.add_argument("--array", metavar="NAME", required=True, help="per-vertex array of TARGET")
    tr.add_argument("-o", "--output", metavar="OUT", type=Path, required=True, help="output mesh (.vtk or .vtp)")
    tr.add_argument("--method", choices=("nearest", "barycentric"), default="barycentric")
    tr.add_argument("--force", action="store_true", help="replace an existing OUT")
    tr.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``volreg transfer SOURCE TARGET --result OUTDIR --array NAME -o OUT``."""
    start = time.perf_counter()
    source = _read(args.source, "SOURCE")
    target = _read(args.target, "TARGET")
    if args.array not in target.arrays:
        available = ", ".join(sorted(target.arrays)) or "none"
        raise UsageError(f"--array `{args.array}` is not a per-vertex array of TARGET `{args.target}`; it has: {available}.")
    warp = _load_model(args.result)
    values = transfer_values(warp(source.vertices), target.vertices, target.triangles, target.arrays[args.array],
                             method=args.method)
    arrays = dict(source.arrays)
    arrays[args.array] = values
    write_mesh(source.vertices, source.triangles, args.output, point_data=arrays, force=args.force, allow_points=True)
    print(f"{PROG} transfer: `{args.array}` ({args.method}) from {args.target} onto {len(values)} vertices of "
          f"{args.source} -> {args.output} ({time.perf_counter() - start:.1f} s)")
    return 0
