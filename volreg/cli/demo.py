"""``volreg demo``: register pyvista's frog to a copy deformed by a known warp."""

from __future__ import annotations

import argparse
from pathlib import Path

from volreg.cli._common import _fit_logger, _sha256, _summary_line, _warn_review, output_path

__all__ = ["DEMO_INPUTS", "add_parser", "run"]

#: The pair that `demo` writes beside the outputs of `volreg register`.
DEMO_INPUTS = ("fixed.nii.gz", "moving.nii.gz")


def add_parser(commands) -> None:
    """Add ``demo`` to the ``volreg`` subcommands."""
    demo = commands.add_parser(
        "demo",
        help="register pyvista's frog to a copy deformed by a known warp",
        description="The frog tissue labels shipped with pyvista, block-downsampled to 3 mm (or at their native "
        "1 x 1 x 1.5 mm with --full), registered to a copy deformed by a known smooth warp (up to 8 mm); prints "
        "Dice and the endpoint error against the truth and writes every output of `volreg register` to OUTDIR.",
    )
    demo.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, default=Path("volreg-demo"),
                      help="output directory (default ./volreg-demo)")
    demo.add_argument("--full", action="store_true", help="native resolution (slow)")
    demo.add_argument("--protocol", metavar="NAME|FILE", default="default", help="protocol preset or TOML file (default: default)")
    demo.add_argument("--force", action="store_true", help="overwrite existing outputs")
    demo.add_argument("--quiet", action="store_true", help="no progress bars")
    demo.add_argument("-v", "--verbose", action="store_true", help="log each stage and warp level to stderr")
    demo.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``volreg demo -o OUTDIR``: the frog pair, its inputs and every output of ``volreg register``."""
    from volreg.demo import frog_pair, frog_path
    from volreg.io import read_labels, write_labels
    from volreg.io._atomic import output_folder
    from volreg.io.protocol import load_protocol
    from volreg.progress import ProgressBars
    from volreg.outputs.registration import write_registration

    protocol = load_protocol(args.protocol)
    path = Path(frog_path())
    full = read_labels(path)
    fixed, moving, truth = frog_pair(full, factors=(1, 1, 1) if args.full else (3, 3, 2))
    inputs = {"fixed": {"path": str(path), "sha256": _sha256(path), "resampled": "block mode 3x3x2" if not args.full else "none"},
              "moving": {"known_deformation": "Gaussian bumps, max 8 mm, seed 0"}}
    # Leave nothing half-done: on failure the inputs written here go too.
    with output_folder(args.output, args.force, outputs=DEMO_INPUTS) as folder:
        for name, volume in zip(DEMO_INPUTS, (fixed, moving)):
            write_labels(volume, folder.path / name, force=args.force)
            folder.record(folder.path / name)
        with ProgressBars(quiet=args.quiet) as progress:
            report = write_registration(fixed, moving, args.output, protocol=protocol, force=True, inputs=inputs,
                                        truth=truth, progress=progress,
                                        on_fit=_fit_logger("demo") if args.verbose else None).to_json()
    _warn_review("demo", report)
    print(_summary_line("demo", report, args.output))
    return 0
