"""Carry an interior structure that did not drive the warp (`--drive-labels`).

Usage: python examples/carry_interior_label.py [OUTDIR]

Only the outer blob's surface (label 1) drives the warp; the inner sphere (label 2) moves 3
voxels with it and is carried across by the dense warp.  Runs the command line in-process.
"""

import json
import sys
from pathlib import Path

import numpy as np

from volreg.cli import main as volreg
from volreg.io import read_labels, write_labels
from volreg.evaluation.metrics import dice
from volreg.synthetic import GaussianBumps, deform_labels

sys.path.insert(0, str(Path(__file__).parent))
from register_two_volumes import blob  # noqa: E402


def main(outdir: Path) -> None:
    outdir.mkdir(parents=True, exist_ok=True)
    fixed = blob()
    moving = deform_labels(fixed, GaussianBumps(np.zeros((1, 3)), np.array([[4.5, 0.0, 0.0]]), 60.0))
    write_labels(fixed, outdir / "fixed.nii.gz", force=True)
    write_labels(moving, outdir / "moving.nii.gz", force=True)
    volreg(["register", str(outdir / "fixed.nii.gz"), str(outdir / "moving.nii.gz"), "-o", str(outdir / "result"),
            "--drive-labels", "1", "--force", "--quiet"])
    warped = read_labels(outdir / "result" / "warped.nii.gz").array
    report = json.loads((outdir / "result" / "report.json").read_text())
    print(f"driving labels: {report['drive_labels']}; inner sphere (label 2) Dice "
          f"{dice(fixed.array == 2, moving.array == 2):.3f} before -> {dice(fixed.array == 2, warped == 2):.3f} after")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "example-output-interior"))
