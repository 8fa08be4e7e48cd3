"""Apply a saved warp to an intensity image (`volreg apply ... --interpolation linear`).

Usage: python examples/apply_to_intensity.py RESULT_DIR MOVING_LABELS FIXED_LABELS

RESULT_DIR is the output of `volreg register` (or of carry_interior_label.py's `result/`).  A
synthetic intensity image is made in moving space (a smooth ramp plus 100 x labels) and warped
onto the fixed grid with the saved model through the command line's `apply`; nothing is
re-registered.
"""

import sys
from pathlib import Path

import numpy as np
import SimpleITK as sitk

import volreg
from volreg.cli import main as volreg_command


def main(result: Path, moving_path: Path, fixed_path: Path) -> None:
    moving = volreg.read_labels(moving_path)
    ramp = moving.grid_points()[..., 0]
    image = sitk.GetImageFromArray(np.ascontiguousarray((100.0 * moving.array + ramp).T.astype(np.float32)))
    image.SetOrigin(tuple(moving.origin))
    image.SetSpacing(tuple(moving.spacing))
    image.SetDirection(tuple(moving.direction.ravel()))
    sitk.WriteImage(image, str(result / "intensity_moving.nii.gz"))
    volreg_command(["apply", str(result / "model.npz"), str(result / "intensity_moving.nii.gz"), "--reference",
                    str(fixed_path), "-o", str(result / "intensity_warped.nii.gz"), "--interpolation", "linear",
                    "--force"])


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]))
