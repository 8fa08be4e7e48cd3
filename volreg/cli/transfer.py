"""``volreg transfer``: carry a per-vertex array from TARGET onto SOURCE through a saved registration."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from volreg.cli._common import PROG, output_path
from volreg.cli._surfaces import _add_data_options, _data_meta, _is_label, _load_model, _read, _warn_findings
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
    """``volreg transfer SOURCE TARGET --result OUTDIR [--array NAME] -o OUT``."""
    import numpy as np

    from volreg.evaluation.surface_review import (
        GAPS_MEASURED,
        diameter,
        review_surface_distance,
        review_surface_extents,
        review_surface_translation,
    )
    from volreg.io import check_writable, write_mesh
    from volreg.io.gifti import is_gifti, write_gifti_data
    from volreg.morph import surface_gaps, transfer_values

    start = time.perf_counter()
    source = _read(args.source, "SOURCE", args.source_data)
    target = _read(args.target, "TARGET", args.target_data)
    available = ", ".join(sorted(target.arrays)) or "none"
    name = args.array
    if name is None:
        if len(target.arrays) != 1:
            raise UsageError(f"--array is needed: TARGET `{args.target}` has {len(target.arrays)} per-vertex arrays "
                             f"({available}); expected exactly one without --array.")
        name = next(iter(target.arrays))
    elif name not in target.arrays:
        raise UsageError(f"--array `{name}` is not a per-vertex array of TARGET `{args.target}`; it has: {available}.")
    data = np.asarray(target.arrays[name])
    if data.dtype.kind not in "iubf":
        raise UsageError(f"Per-vertex array `{name}` of TARGET `{args.target}` holds {data.dtype} values; expected "
                         "numbers (scalars, vectors or integer labels).")
    if data.dtype.kind == "f" and not np.all(np.isfinite(data)):
        raise UsageError(f"Per-vertex array `{name}` of TARGET `{args.target}` holds "
                         f"{int(np.count_nonzero(~np.isfinite(data)))} NaN/Inf values; expected finite per-vertex "
                         "values (interpolation would spread them to their neighbours).")
    _check_output(args.output)
    check_writable([args.output], force=args.force)
    warp = _load_model(args.result, "--result")
    findings = review_surface_extents(source.vertices, target.vertices)
    warped = warp(source.vertices)
    gaps, measured = surface_gaps(warped, target.vertices, target.triangles)
    findings += review_surface_distance(
        gaps, diameter(target.vertices), measured=measured,
        hint="Check that SOURCE and TARGET are the surfaces registered in --result, read in the same frame.")
    findings += review_surface_translation(warp.linear.translation, diameter(source.vertices))
    _warn_findings("transfer", findings)
    label = _is_label(target, name)
    method = "nearest" if label else args.method
    values = transfer_values(warped, target.vertices, target.triangles, target.arrays[name], method=method)
    if is_gifti(args.output):
        structure = source.gifti.structure() if source.gifti is not None else None
        write_gifti_data(values, args.output, meta=_data_meta(target, name), structure=structure, force=args.force)
    else:
        arrays = dict(source.arrays)
        arrays[name] = values
        write_mesh(source.vertices, source.triangles, args.output, point_data=arrays, force=args.force,
                   allow_points=True)
    print(f"{PROG} transfer: `{name}` ({method}) from {args.target} onto {len(values)} vertices of "
          f"{args.source}, median {np.median(gaps):.3g} mm {GAPS_MEASURED[measured]} -> {args.output} "
          f"({time.perf_counter() - start:.1f} s)")
    return 0
