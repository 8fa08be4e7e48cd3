"""What every ``volreg`` command shares: argument types, messages, landmarks, checksums, log lines."""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from volreg.errors import VolregError

if TYPE_CHECKING:  # the command modules import numpy and the pipeline only when a command runs
    from volreg.grid import LabelVolume
    from volreg.pipeline.labels import LabelRegistration

PROG = "volreg"


#: Errors that are the user's input, not volreg's bug: reported in one line, exit status 2.
EXPECTED_ERRORS = (VolregError,)


#: How many label values an error message lists before eliding the rest.
_MAX_LISTED = 30


def _label_list(text: str) -> list[int]:
    """``"1,3"`` -> ``[1, 3]``; for ``--labels``."""
    expected = "expected comma-separated non-zero integer labels such as 1,3"
    items = [t.strip() for t in text.split(",")]
    try:
        labels = [int(t) for t in items]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{expected}, got {text!r}") from None
    if 0 in labels:
        raise argparse.ArgumentTypeError(f"{expected}, got {text!r} (0 is the background)")
    duplicates = sorted({v for v in labels if labels.count(v) > 1})
    if duplicates:
        raise argparse.ArgumentTypeError(f"{expected}, got {text!r} (label {duplicates[0]} is listed twice)")
    return labels


def _integer_at_least(least: int):
    """An argparse type: an integer of at least ``least`` ("a positive integer" for 1)."""
    wanted = "a positive integer" if least == 1 else f"an integer of at least {least}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text[:40]!r}") from None
        if value < least:
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text[:40]!r}")
        return value

    return parse


def _float_at_least(lower: float, *, strict: bool, upper: float = math.inf):
    """An argparse type for a finite float ``> lower`` (``strict``) or ``>= lower``, and ``<= upper``."""
    relation = ">" if strict else ">="
    expected = f"a number {relation} {lower:g}" + (f" and <= {upper:g}" if upper < math.inf else "")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not math.isfinite(value) or (value <= lower if strict else value < lower) or value > upper:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value

    return parse


def _listing(values: Sequence[int]) -> str:
    shown = ", ".join(str(v) for v in values[:_MAX_LISTED])
    return shown + (f", ... ({len(values)} in all)" if len(values) > _MAX_LISTED else "")


def output_path(text: str) -> Path:
    """The argparse type of ``-o``: a path, not an empty string (which would name the working folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a file or folder name, got an empty string")
    return Path(text)


def _warn(command: str, message: str) -> None:
    print(f"{PROG} {command}: warning: {message}", file=sys.stderr)


def _warn_review(command: str, report: dict) -> None:
    """One warning line on stderr per finding of the report's plausibility review, and a note
    naming the labels that only one volume holds (they have nothing to align to and are not judged)."""
    for finding in report.get("review", {}).get("findings", []):
        _warn(command, finding["message"])
    alone = report.get("labels_in_one_volume", {})
    parts = [f"labels {alone[side][:20]}{' ...' * (len(alone[side]) > 20)} only in the {side} volume"
             for side in ("fixed", "moving") if alone.get(side)]
    if parts:  # a note, not a finding: one subject may lack a structure, or a field of view miss it
        print(f"{PROG} {command}: note: {' and '.join(parts)}: nothing to align them to, so they neither drive the "
              "warp nor are judged; check that both volumes number their structures alike.", file=sys.stderr)


def _strict_status(command: str, protocol, reviews: list[dict]) -> int:
    """The exit status after plausibility reviews: 3 (with one error line) when the protocol's
    ``[review] strict`` is set and a review found something, else 0."""
    count = sum(len(review.get("findings", [])) for review in reviews)
    if not (protocol.review.strict and count):
        return 0
    print(f"{PROG} {command}: error: the result is implausible ({count} finding{'s' * (count != 1)}, above and in "
          "the report) and the protocol's [review] strict is true; the outputs are written, for a look.",
          file=sys.stderr)
    return 3


def _sha256(path: Path) -> str:
    """The SHA-256 checksum of a file, as the reports record inputs (numpy is loaded only now)."""
    from volreg.io.summary import file_sha256

    return file_sha256(path)


def _fit_logger(command: str) -> Callable[[LabelRegistration], None]:
    """An ``on_fit`` callback for :func:`volreg.outputs.registration.write_registration` that logs, one line each
    on stderr, the driving labels, the labels left out, the fit's stages and its warp levels."""

    def log(text: str) -> None:
        print(f"{PROG} {command}: {text}", file=sys.stderr)

    def log_fit(result: LabelRegistration) -> None:
        if result.linear is not None:
            d = result.linear.map.describe()
            log(f"linear part: rotation {d['rotation_deg']:.1f} deg, scales "
                f"{', '.join(f'{v:.3f}' for v in d['scales'])}, translation "
                f"{', '.join(f'{v:.1f}' for v in d['translation'])} mm")
        log(f"driving labels {result.distance_labels} (voxel distance maps)"
            + (f", {result.labels} (implicit surfaces)" if result.labels else ""))
        for note in result.skipped:
            log(note)
        for st in result.stages:
            log(f"{st.stage}: {st.seconds:.1f} s")
        for lev in result.log:
            log(f"level {lev['level']}: width {lev['width']:.1f} mm, {lev['centres']} centres, "
                f"{lev['samples']} samples, {lev['iterations']} iterations, objective "
                f"{lev['objective_start']:.4g} -> {lev['objective']:.4g}, fold scale {lev['fold_scale']:.2f}, "
                f"{lev['seconds']:.1f} s")

    return log_fit


def _summary_line(command: str, report: dict, outdir: Path) -> str:
    """The one line ``volreg register`` and ``volreg demo`` print on stdout."""
    from volreg.outputs.registration import ITK_H5_OUTPUTS, REGISTRATION_OUTPUTS

    d = report["mean_dice"]
    shared = len(d.get("labels", report["labels"]))
    alone = len(report["labels"]) - shared
    over = f"{shared} labels" + (f" in both volumes ({alone} in one only)" if alone else "")
    line = (f"{PROG} {command}: mean Dice {d['before']:.3f} -> {d['after']:.3f} over {over}, "
            f"folded {100 * report['jacobian']['folded_fraction']:.3f} %")
    if "endpoint_error_mm" in report:
        e = report["endpoint_error_mm"]
        line += (f", endpoint error mean {e['mean']:.2f} mm / p95 {e['p95']:.2f} mm "
                 f"(identity {e['identity_mean']:.2f} / {e['identity_p95']:.2f})")
    if report.get("landmarks"):
        m = report["landmarks"]
        line += f", landmark error mean {m['mean_mm']:.2f} mm / max {m['max_mm']:.2f} mm (identity {m['identity_mean_mm']:.2f})"
    files = len(REGISTRATION_OUTPUTS) - (0 if report["protocol"]["outputs"]["itk_h5"] else len(ITK_H5_OUTPUTS))
    return line + f"; {files} files in {outdir}{os.sep} ({report['seconds']:.0f} s)"


def _load_landmarks(args, fixed: LabelVolume | None = None, moving: LabelVolume | None = None):
    """The ``--landmarks`` pair, checked for equal counts and (given the volumes) to lie in their images
    (:func:`volreg.pipeline.landmark_pairs.check_landmark_pairs`); pairs left out are named in a warning."""
    from volreg.io.landmarks import read_landmarks
    from volreg.pipeline.landmark_pairs import check_landmark_pairs

    if args.landmarks is None:
        return None
    a = read_landmarks(args.landmarks[0], keep_unplaced=True)
    b = read_landmarks(args.landmarks[1], keep_unplaced=True)
    return check_landmark_pairs(a, b, (args.landmarks[0], args.landmarks[1]), fixed, moving,
                                note=lambda message: _warn(args.command, message))
