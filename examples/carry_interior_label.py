"""Carry an interior structure that did not drive the warp (`drive_labels`, `--drive-labels`).

Usage: python examples/carry_interior_label.py [OUTDIR]

Only the outer blob (label 1) drives the warp; the inner sphere (label 2) moves 3 voxels with it
and is carried across by the dense warp.  Writes the pair, the warped labels and the model
(OUTDIR/result/model.npz, which examples/apply_to_intensity.py can apply).  The same from the
command line: `volreg register fixed.nii.gz moving.nii.gz -o result --drive-labels 1`.
"""

import sys
from pathlib import Path

import numpy as np

import volreg
from volreg.synthetic import GaussianBumps, deform_labels

sys.path.insert(0, str(Path(__file__).parent))
from register_two_volumes import blob  # noqa: E402


def main(outdir: Path) -> None:
    (outdir / "result").mkdir(parents=True, exist_ok=True)
    fixed = blob()
    moving = deform_labels(fixed, GaussianBumps(np.zeros((1, 3)), np.array([[4.5, 0.0, 0.0]]), 60.0))
    volreg.write_labels(fixed, outdir / "fixed.nii.gz", force=True)
    volreg.write_labels(moving, outdir / "moving.nii.gz", force=True)

    result = volreg.register_labels(fixed, moving, drive_labels=[1])   # label 2 does not drive
    x = fixed.grid_points().reshape(-1, 3)
    warped = volreg.resample_labels(moving, result.warp(x)).reshape(fixed.shape)
    volreg.write_labels(fixed.with_array(warped), outdir / "result" / "warped.nii.gz", force=True)
    result.warp.save(outdir / "result" / "model.npz", force=True)

    before = volreg.label_scores(fixed.array, moving.array, [2], fixed.spacing)[2]["dice"]
    after = volreg.label_scores(fixed.array, warped, [2], fixed.spacing)[2]["dice"]
    print(f"driving labels: {result.labels}; inner sphere (label 2) Dice {before:.3f} before -> {after:.3f} after")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "example-output-interior"))
