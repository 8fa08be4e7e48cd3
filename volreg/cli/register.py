"""``volreg register``: register two label volumes and write every output."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from volreg.cli._common import (
    output_path,
    _fit_logger,
    _label_list,
    _load_landmarks,
    _sha256,
    _strict_status,
    _summary_line,
    _warn_review,
)
from volreg.settings import LINEAR_KINDS

__all__ = ["add_parser", "run"]


def add_parser(commands) -> None:
    """Add ``register`` to the ``volreg`` subcommands."""
    register = commands.add_parser(
        "register",
        help="register two label volumes (the main job)",
        description="Register the MOVING label volume to the FIXED one with a kernel warp driven by the "
        "labels' surfaces, after a linear stage (affine by default), and write into OUTDIR: warp.nii.gz "
        "(ANTs/ITK displacement field on the fixed grid, LPS mm, pull-back, the whole map), inverse_warp.nii.gz "
        "(its inverse on the moving grid), warp.h5 and inverse_warp.h5 (the same fields as ITK composite "
        "transforms, unless the protocol says [outputs] itk_h5 = false), warped.nii.gz "
        "(moving labels on the fixed grid), model.npz (the warp), "
        "jacobian.nii.gz (det of its analytic Jacobian), linear.tfm (the linear part alone, ITK transform), "
        "report.json and report.png. Implausible results are named in one warning line each on stderr.",
    )
    register.add_argument("fixed", metavar="FIXED", type=Path, help="fixed label volume (defines the output grid)")
    register.add_argument("moving", metavar="MOVING", type=Path, help="moving label volume")
    register.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, required=True, help="output directory")
    register.add_argument("--protocol", metavar="NAME|FILE", default="default",
                          help="protocol preset (see `volreg protocols`) or TOML file (default: default)")
    register.add_argument("--linear", choices=LINEAR_KINDS, default=None,
                          help="linear stage before the kernel warp (default: the protocol's [linear] kind, "
                          "affine in the presets)")
    register.add_argument("--drive-labels", metavar="IDS", type=_label_list, default=None,
                          help="labels that drive the warp, e.g. 1,4,7 (default: every label in both volumes); "
                          "every label is warped")
    register.add_argument("--landmarks", metavar=("FIXED_PTS", "MOVING_PTS"), nargs=2, type=Path, default=None,
                          help="corresponding points (.csv x,y,z LPS mm, Slicer .fcsv or .mrk.json)")
    register.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    register.add_argument("--quiet", action="store_true", help="no progress bars")
    register.add_argument("-v", "--verbose", action="store_true", help="log each stage and warp level to stderr")
    register.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``volreg register FIXED MOVING -o OUTDIR``."""
    from volreg.io import read_labels
    from volreg.io.protocol import load_protocol
    from volreg.progress import ProgressBars
    from volreg.outputs.registration import write_registration
    from volreg.pipeline.checks import check_pair, check_pair_headers
    from volreg.settings import LinearSettings

    protocol = load_protocol(args.protocol)
    if args.linear is not None:
        protocol = dataclasses.replace(protocol, linear=LinearSettings(kind=args.linear))
    check_pair_headers(args.fixed, args.moving)  # before any voxel is decompressed
    fixed = read_labels(args.fixed)
    moving = read_labels(args.moving)
    check_pair(fixed, moving, args.fixed, args.moving, linear=protocol.linear.kind)
    landmarks = _load_landmarks(args, fixed, moving)
    inputs = {
        "fixed": {"path": str(args.fixed), "sha256": _sha256(args.fixed)},
        "moving": {"path": str(args.moving), "sha256": _sha256(args.moving)},
    }
    if landmarks is not None:
        inputs["landmarks"] = [{"path": str(p), "sha256": _sha256(p)} for p in args.landmarks]
    with ProgressBars(quiet=args.quiet) as progress:
        report = write_registration(fixed, moving, args.output, protocol=protocol, drive_labels=args.drive_labels,
                                    landmarks=landmarks, force=args.force, inputs=inputs, progress=progress,
                                    on_fit=_fit_logger("register") if args.verbose else None).to_json()
    _warn_review("register", report)
    print(_summary_line("register", report, args.output))
    return _strict_status("register", protocol, [report["review"]])
