"""``volreg shape-model``: statistical shape and deformation models of a template's cohort
(:func:`volreg.shape_models.build_shape_models`), and shapes drawn from a saved model.

The command parses its arguments, calls the library and prints: news on stderr, one summary
line on stdout.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from volreg.cli._common import PROG, _integer_at_least, _warn, output_path
from volreg.errors import UsageError

__all__ = ["add_parser", "run"]


def _coefficients(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers (standard deviations of the leading "
                                         f"modes), got {text[:60]!r}") from None
    if not values or not all(abs(v) < float("inf") for v in values):
        raise argparse.ArgumentTypeError(f"expected finite numbers, got {text[:60]!r}")
    return values


def add_parser(commands) -> None:
    """Add ``shape-model`` to the ``volreg`` subcommands."""
    p = commands.add_parser(
        "shape-model",
        help="statistical shape and deformation models of a template's cohort; shapes drawn from a model",
        usage="volreg shape-model TEMPLATE_OUT -o OUTDIR [--align none|rigid|similarity] [--modes N] [--samples N]\n"
              "                          [--seed N] [--force] [--quiet]\n"
              "       volreg shape-model sample MODEL --coefficients B1,B2,... -o OUTDIR [--force]",
        description="`volreg shape-model TEMPLATE_OUT -o OUTDIR`: from the folder `volreg template` wrote, a surface "
        "model (the template's label meshes carried into every subject by its warp) and a deformation model (the "
        "subjects' displacements over the template's labelled region), each aligned by generalised Procrustes "
        "(--align) and modelled by PCA. Writes OUTDIR/surface/ and OUTDIR/deformation/ (model.npz, modes.csv, "
        "scores.csv, quality.json and quality.png: compactness, generalization, specificity, correspondence both "
        "ways; mean meshes; the leading modes' -2/+2 sd label maps and meshes; one GIF per leading mode) and "
        "OUTDIR/report.json. `volreg shape-model sample MODEL --coefficients 2,-1,0.5 -o OUTDIR`: the label map "
        "(shape.nii.gz) and meshes (shape_label<L>.vtk) of that shape of a saved model.npz (a first value below zero "
        "may follow --coefficients as it is: --coefficients -2,1).",
    )
    p.add_argument("inputs", nargs="+", metavar="TEMPLATE_OUT",
                   help="the template folder, or `sample` and a saved model.npz")
    p.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, required=True, help="output directory")
    p.add_argument("--align", choices=("none", "rigid", "similarity"), default="rigid",
                   help="generalised Procrustes alignment of the subjects before the PCA (default rigid)")
    p.add_argument("--modes", type=_integer_at_least(1), default=10, help="at most this many modes per model (default 10)")
    p.add_argument("--samples", type=_integer_at_least(1), default=100,
                   help="shapes drawn to measure the specificity (default 100)")
    p.add_argument("--seed", type=_integer_at_least(0), default=0, help="seed of the specificity's draws (default 0)")
    p.add_argument("--coefficients", type=_coefficients, default=None, metavar="B1,B2,...",
                   help="with `sample`: the shape's coefficients, standard deviations of the leading modes")
    p.add_argument("--force", action="store_true", help="replace the outputs in OUTDIR")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=run)


def _sample(args: argparse.Namespace, model: Path) -> int:
    from volreg.outputs.shape_model import write_shape_sample
    from volreg.shape_models import LabelShapeModel

    if args.coefficients is None:
        raise UsageError("--coefficients: expected the shape's coefficients with `sample` (e.g. --coefficients 2,-1).")
    lsm = LabelShapeModel.load(model, option="MODEL")
    names = write_shape_sample(lsm, args.coefficients, args.output, force=args.force)
    print(f"{PROG} shape-model sample: {lsm.kind} model, coefficients {','.join(f'{v:g}' for v in args.coefficients)}; "
          f"{len(names)} files in {args.output}")
    return 0


def run(args: argparse.Namespace) -> int:
    """``volreg shape-model TEMPLATE_OUT -o OUTDIR`` or ``volreg shape-model sample MODEL --coefficients ... -o OUTDIR``."""
    words = args.inputs
    if words[0] == "sample":
        if len(words) != 2:
            raise UsageError("MODEL: expected `volreg shape-model sample MODEL --coefficients B1,B2,... -o OUTDIR` "
                             "with one model.npz.")
        return _sample(args, Path(words[1]))
    if len(words) != 1:
        raise UsageError("TEMPLATE_OUT: expected one folder (`volreg shape-model TEMPLATE_OUT -o OUTDIR`), or "
                         "`sample MODEL`.")
    if args.coefficients is not None:
        raise UsageError("--coefficients: only with `volreg shape-model sample MODEL`.")
    from volreg.outputs.shape_model import build_and_write_shape_models
    from volreg.progress import ProgressBars

    start = time.perf_counter()
    outdir: Path = args.output
    with ProgressBars(quiet=args.quiet) as progress:
        _, report = build_and_write_shape_models(
            Path(words[0]), outdir, force=args.force, progress=progress, align=args.align, modes=args.modes,
            samples=args.samples, seed=args.seed, warn=lambda line: _warn("shape-model", line))
    parts = []
    for kind, m in report["models"].items():
        parts.append(f"{kind}: {m['modes']} modes, the leading {m['leading']} hold {100 * (m['compactness_leading'] or 0):.0f} %, "
                     f"generalization {m['generalization_leading_mm'] or 0:.2f} mm")
    print(f"{PROG} shape-model: {len(report['subjects'])} subjects; {'; '.join(parts)}; {outdir} "
          f"({time.perf_counter() - start:.0f} s)", file=sys.stdout)
    return 0
