"""``volreg transfer``: carry a per-vertex array from TARGET onto SOURCE through a saved registration."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from volreg.cli._common import PROG, output_path
from volreg.cli._surfaces import _add_data_options, _warn_findings
from volreg.errors import UsageError

__all__ = ["add_parser", "run"]

#: Suffixes OUT may have: a mesh with every array (LPS) or the transferred array alone as GIFTI data.
OUT_SUFFIXES = (".vtk", ".vtp", ".gii")


def add_parser(commands) -> None:
    """Add ``transfer`` to the ``volreg`` subcommands."""
    tr = commands.add_parser(
        "transfer",
        help="carry a per-vertex array from TARGET onto SOURCE through a registration",
        description="For every SOURCE vertex v, take the value of --array at the TARGET point nearest to tau(v) "
        "(interpolated in the nearest triangle, or the nearest vertex; labels always the nearest vertex) and write "
        "it to OUT: SOURCE with the array (.vtk, .vtp; LPS mm) or the array alone as a GIFTI data file (.shape.gii, "
        ".func.gii, .label.gii) with the metadata and label table of TARGET's data file. Warns when the warped "
        "SOURCE lies far from TARGET (frames or units that do not match).",
    )
    tr.add_argument("source", metavar="SOURCE", type=Path)
    tr.add_argument("target", metavar="TARGET", type=Path)
    tr.add_argument("--result", metavar="OUTDIR", type=Path, required=True, help="OUTDIR of `volreg register-surfaces`")
    tr.add_argument("--array", metavar="NAME", default=None,
                    help="per-vertex array of TARGET (may be left out when TARGET has exactly one)")
    _add_data_options(tr, "source", "target")
    tr.add_argument("-o", "--output", metavar="OUT", type=output_path, required=True,
                    help="output: mesh (.vtk, .vtp) or GIFTI data file (.shape.gii, .func.gii, .label.gii)")
    tr.add_argument("--method", choices=("nearest", "barycentric"), default="barycentric")
    tr.add_argument("--force", action="store_true", help="replace an existing OUT")
    tr.set_defaults(run=run)


def _check_output(out: Path) -> None:
    suffix = out.suffix.lower()
    if suffix not in OUT_SUFFIXES:
        raise UsageError(f"-o `{out}` has suffix {suffix!r}; expected .vtk, .vtp or a GIFTI data file "
                         "(.shape.gii, .func.gii, .label.gii).")
    if out.name.lower().endswith(".surf.gii"):
        raise UsageError(f"-o `{out}` names a GIFTI surface; expected a GIFTI data file (.shape.gii, .func.gii, "
                         ".label.gii) for the transferred values.")


def run(args: argparse.Namespace) -> int:
    """``volreg transfer SOURCE TARGET --result OUTDIR [--array NAME] -o OUT``
    (:func:`volreg.outputs.surfaces.write_transferred_array`)."""
    from volreg.evaluation.surface_review import GAPS_MEASURED
    from volreg.io import check_writable
    from volreg.outputs.surfaces import (load_surface_model, read_surface_with_data, select_vertex_array,
                                         write_transferred_array)

    start = time.perf_counter()
    source = read_surface_with_data(args.source, "SOURCE", args.source_data)
    target = read_surface_with_data(args.target, "TARGET", args.target_data)
    name = select_vertex_array(target, args.array, f"TARGET `{args.target}`")
    _check_output(args.output)
    check_writable([args.output], force=args.force)
    warp = load_surface_model(args.result)
    done = write_transferred_array(source, target, warp, name, args.output, method=args.method, force=args.force,
                                   on_findings=lambda findings: _warn_findings("transfer", findings))
    print(f"{PROG} transfer: `{name}` ({done.method}) from {args.target} onto {done.vertices} vertices of "
          f"{args.source}, median {done.median_gap_mm:.3g} mm {GAPS_MEASURED[done.measured]} -> {args.output} "
          f"({time.perf_counter() - start:.1f} s)")
    return 0
