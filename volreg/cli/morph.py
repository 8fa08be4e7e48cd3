"""``volreg morph``: frames of the morph from SOURCE to TARGET along the kernel warp."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from volreg.cli._common import PROG, output_path
from volreg.cli._surfaces import _add_data_options, _wants_gifti, _warn_findings
from volreg.errors import UsageError

__all__ = ["add_parser", "run"]


#: The most frames a morph writes (each is a mesh file and a PNG, and all are held for the GIF).
MAX_FRAMES = 1000


def add_parser(commands) -> None:
    """Add ``morph`` to the ``volreg`` subcommands."""
    morph = commands.add_parser(
        "morph",
        help="frames of the morph from SOURCE to TARGET",
        description="Meshes along v + t (tau(v) - v) for t from 0 to 1 (frame_000.vtk ..., LPS mm), with per-vertex "
        "arrays that both surfaces carry interpolated (labels switch at t = 0.5), rendered off-screen to "
        "frame_000.png ... and morph.gif; when SOURCE is GIFTI or with --gifti also frame_000.surf.gii ... (RAS mm) "
        "and the arrays as frame_000.<name>.<kind>.gii.",
    )
    morph.add_argument("source", metavar="SOURCE", type=Path)
    morph.add_argument("target", metavar="TARGET", type=Path)
    morph.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, required=True, help="output directory")
    morph.add_argument("--frames", type=int, default=10, help="number of frames, 2 to 1000 (default 10)")
    morph.add_argument("--from-result", metavar="OUTDIR", type=Path, default=None,
                       help="use the model.npz of a `volreg register-surfaces` OUTDIR instead of registering")
    morph.add_argument("--protocol", metavar="NAME|FILE", default="default", help="protocol when registering")
    _add_data_options(morph, "source", "target")
    morph.add_argument("--gifti", action="store_true", help="also write GIFTI frames (RAS) when SOURCE is not GIFTI")
    morph.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    morph.add_argument("--quiet", action="store_true", help="no progress bars")
    morph.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``volreg morph SOURCE TARGET -o OUTDIR`` (:func:`volreg.outputs.morph.write_morph`)."""
    from volreg.io.protocol import load_protocol
    from volreg.outputs.morph import write_morph
    from volreg.outputs.surfaces import load_surface_model, read_surface_with_data
    from volreg.progress import ProgressBars

    start = time.perf_counter()
    if not 2 <= args.frames <= MAX_FRAMES:
        raise UsageError(f"--frames {args.frames}: expected 2 to {MAX_FRAMES} frames (the source, the warped source "
                         "and the steps between).")
    source = read_surface_with_data(args.source, "SOURCE", args.source_data)
    target = read_surface_with_data(args.target, "TARGET", args.target_data)
    warp = load_surface_model(args.from_result, "--from-result") if args.from_result is not None else None
    protocol = load_protocol(args.protocol) if warp is None else None
    gifti = _wants_gifti(args, args.source)
    with ProgressBars(quiet=args.quiet) as progress:
        write_morph(source, target, args.output, frames=args.frames, warp=warp, protocol=protocol,
                    names=(f"SOURCE `{args.source}`", f"TARGET `{args.target}`"), gifti=gifti, force=args.force,
                    progress=progress, on_findings=lambda findings: _warn_findings("morph", findings))
    kinds = ".vtk, .surf.gii, .png" if gifti else ".vtk, .png"
    print(f"{PROG} morph: {args.frames} frames ({kinds}) and morph.gif in {args.output} "
          f"({time.perf_counter() - start:.0f} s)")
    return 0
