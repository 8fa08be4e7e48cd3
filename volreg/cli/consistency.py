"""``volreg consistency``: register both ways (or load both results), compose, report.

Reads and checks the inputs, calls :func:`volreg.outputs.consistency.write_consistency_test`
and prints its one-line summary.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from volreg.cli._common import PROG, _fit_logger, _label_list, _sha256, _strict_status, _warn, output_path
from volreg.errors import UsageError

__all__ = ["add_parser", "run"]


def add_parser(commands) -> None:
    """Add ``consistency`` to the ``volreg`` subcommands."""
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
    consistency.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, required=True, help="output directory")
    consistency.add_argument("--forward", metavar="RESULT_AB", type=Path, default=None,
                             help="OUTDIR of `volreg register A B` (skip registering; needs --backward)")
    consistency.add_argument("--backward", metavar="RESULT_BA", type=Path, default=None,
                             help="OUTDIR of `volreg register B A` (needs --forward)")
    consistency.add_argument("--protocol", metavar="NAME|FILE", default=None,
                             help="protocol preset or TOML file for both registrations (default: default)")
    consistency.add_argument("--drive-labels", metavar="IDS", type=_label_list, default=None,
                             help="labels that drive both warps (default: as `volreg register`)")
    consistency.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    consistency.add_argument("--quiet", action="store_true", help="no progress bars")
    consistency.add_argument("-v", "--verbose", action="store_true", help="log each stage and warp level to stderr")
    consistency.set_defaults(run=run)


def _saved_inputs(result: Path) -> tuple[str | None, str | None]:
    """The checksums of the fixed and moving files a saved ``volreg register`` OUTDIR was made from
    (its report.json), or ``None`` where it does not say (no report, or not JSON); a report nested
    beyond reason is refused (:func:`~volreg.io.documents.parse_json`)."""
    import json

    from volreg.io.documents import parse_json

    report = result / "report.json"
    try:
        inputs = parse_json(report.read_text(encoding="utf-8"), f"Report `{report}`").get("inputs", {})
        return inputs.get("fixed", {}).get("sha256"), inputs.get("moving", {}).get("sha256")
    except (OSError, json.JSONDecodeError, UnicodeDecodeError, AttributeError):
        return None, None


def _check_saved_inputs(args: argparse.Namespace, sha_a: str, sha_b: str) -> None:
    """Refuse saved results registered the other way round; warn where they were made from other
    files than A and B (the same labels saved again differ in their bytes too)."""
    for option, result, want in (("--forward", args.forward, (sha_a, sha_b)),
                                 ("--backward", args.backward, (sha_b, sha_a))):
        got = _saved_inputs(result)
        if None in got or got == want:
            continue
        command = "volreg register A B" if option == "--forward" else "volreg register B A"
        if got == want[::-1] and want[0] != want[1]:
            raise UsageError(f"{option} `{result}` registered the other way round ({'B to A' if option == '--forward' else 'A to B'}, "
                             f"by its report.json's input checksums); expected the result of `{command}`.")
        names = ("A", "B") if option == "--forward" else ("B", "A")  # its fixed and moving files
        differ = [f"{role} checksum differs from {name}'s"
                  for role, name, g, w in zip(("fixed", "moving"), names, got, want) if g != w]
        _warn("consistency", f"{option} `{result}` was registered from other files than `{command}` names "
              f"(its report.json's {' and '.join(differ)}); the test is of that registration, not of A and B.")


def run(args: argparse.Namespace) -> int:
    """``volreg consistency A B -o OUTDIR [--forward RESULT_AB --backward RESULT_BA]``."""
    from volreg.outputs.consistency import load_saved_warp, write_consistency_test
    from volreg.io import read_labels
    from volreg.io.protocol import load_protocol
    from volreg.progress import ProgressBars
    from volreg.pipeline.checks import check_pair, check_pair_headers

    start = time.perf_counter()
    if (args.forward is None) != (args.backward is None):
        given, missing = ("--forward", "--backward") if args.backward is None else ("--backward", "--forward")
        raise UsageError(f"{given} was given without {missing}; expected both saved directions, or neither to register.")
    saved = args.forward is not None
    if saved and (args.protocol is not None or args.drive_labels is not None):
        raise UsageError("--protocol and --drive-labels apply only when registering; drop them with --forward/--backward.")
    check_pair_headers(args.a, args.b)  # before any voxel is decompressed
    a = read_labels(args.a)
    b = read_labels(args.b)
    protocol = None if saved else load_protocol(args.protocol or "default")
    forward = backward = directions = None
    if saved:
        forward = load_saved_warp(args.forward, a, option="--forward", grid_path=args.a, role="A")
        backward = load_saved_warp(args.backward, b, option="--backward", grid_path=args.b, role="B")
        if forward.dim != backward.dim:
            raise UsageError("--forward and --backward hold warps of different dimension.")
        directions = {"forward": {"outdir": str(args.forward)}, "backward": {"outdir": str(args.backward)}}
        # The saved warps' own linear parts, if any, bring far-apart grids together.
        linear = "none" if forward.linear.is_identity and backward.linear.is_identity else "affine"
    else:
        linear = protocol.linear.kind
    check_pair(a, b, args.a, args.b, linear=linear)
    inputs = {"A": {"path": str(args.a), "sha256": _sha256(args.a)}, "B": {"path": str(args.b), "sha256": _sha256(args.b)}}
    if saved:
        _check_saved_inputs(args, inputs["A"]["sha256"], inputs["B"]["sha256"])
    with ProgressBars(quiet=args.quiet) as progress:
        report = write_consistency_test(
            a, b, args.output, forward=forward, backward=backward, directions=directions, protocol=protocol,
            drive_labels=args.drive_labels, force=args.force, inputs=inputs, progress=progress,
            on_fit=_fit_logger("consistency") if args.verbose else None,
        )
    for name, direction in report["directions"].items():
        for finding in direction.get("review", {}).get("findings", []):
            _warn("consistency", f"{name} registration: {finding['message']}")
    r = report["region"]
    print(f"{PROG} consistency: inverse-consistency error over A's padded labels mean {r['mean_mm']:.4f} mm "
          f"({r['mean_voxels']:.4f} voxel), p95 {r['p95_mm']:.4f} mm, max {r['max_mm']:.4f} mm; round-trip Dice "
          f"{report['mean_round_trip_dice']:.3f}; {args.output} ({time.perf_counter() - start:.0f} s)")
    if protocol is None:  # saved results: nothing registered here, nothing reviewed
        return 0
    return _strict_status("consistency", protocol, [d.get("review", {}) for d in report["directions"].values()])
