"""``volreg apply``: resample an image onto a reference grid through a saved warp."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from volreg.cli._common import PROG
from volreg.errors import UsageError
from volreg.grid import Grid
from volreg.io import read_grid, read_image, read_labels, write_labels, write_scalar
from volreg.io.fields import read_displacement, read_itk_linear
from volreg.progress import ProgressBars
from volreg.warp.field import displacement_on_grid, linear_displacement_on_grid
from volreg.warp.model import KernelWarp
from volreg.warp.resample import resample_image, resample_labels

__all__ = ["add_parser", "run"]


def add_parser(commands) -> None:
    """Add ``apply`` to the ``volreg`` subcommands."""
    apply = commands.add_parser(
        "apply",
        help="warp an image with a saved result",
        description="Resample IMAGE (labels or intensities) onto the grid of REF through a saved warp: "
        "a model.npz or an ANTs/ITK displacement field (warp.nii.gz) from `volreg register`, or an ITK "
        "linear transform (.tfm, .txt, .mat).",
    )
    apply.add_argument("warp", metavar="MODEL_OR_WARP", type=Path,
                       help="model.npz, warp.nii.gz or an ITK linear transform (.tfm, .txt, .mat)")
    apply.add_argument("image", metavar="IMAGE", type=Path, help="image in moving space")
    apply.add_argument("--reference", metavar="REF", type=Path, required=True, help="image whose grid the output takes (fixed space)")
    apply.add_argument("-o", "--output", metavar="OUT", type=Path, required=True, help="output image (.nii.gz, .nii, .nrrd, .mha)")
    apply.add_argument("--interpolation", choices=("label", "nearest", "linear", "bspline"), default="label",
                       help="label: label-preserving (per-label signed distances, default); nearest; linear or bspline "
                       "for intensity images (written as float32)")
    apply.add_argument("--force", action="store_true", help="overwrite an existing output")
    apply.add_argument("--quiet", action="store_true", help="no progress bars")
    apply.set_defaults(run=run)


def _check_overlap(field, reference, warp_path, reference_path) -> None:
    """Refuse a displacement field whose grid misses the reference grid: it would act as the identity there."""
    from volreg.register import world_box

    lo1, hi1 = world_box(field)
    lo2, hi2 = world_box(reference)
    if np.any(hi1 < lo2) or np.any(hi2 < lo1):
        raise UsageError(
            f"Warp `{warp_path}` covers {np.round(lo1, 1).tolist()}..{np.round(hi1, 1).tolist()} mm (LPS) and "
            f"--reference `{reference_path}` {np.round(lo2, 1).tolist()}..{np.round(hi2, 1).tolist()} mm: they do not "
            "overlap, so the warp would leave every reference voxel where it is; expected a warp on (or around) the "
            "reference's grid (check the origins, or the pairing of the warp and the reference)."
        )


def run(args: argparse.Namespace) -> int:
    """``volreg apply MODEL_OR_WARP IMAGE --reference REF -o OUT``."""
    start = time.perf_counter()
    reference = read_grid(args.reference)
    at = reference.grid_points()  # (X, Y, Z, 3) mm
    name = args.warp.name.lower()
    with ProgressBars(quiet=args.quiet) as progress:
        if name.endswith(".npz"):
            warp = KernelWarp.load(args.warp)
            if warp.dim != reference.ndim:
                raise UsageError(f"Model `{args.warp}` is {warp.dim}-D but --reference `{args.reference}` is {reference.ndim}-D.")
            # the model's linear part included: outside the kernels' support u = (A - I) x + b
            u = displacement_on_grid(warp, reference, progress=progress)
        elif name.endswith((".tfm", ".txt", ".mat")):
            linear = read_itk_linear(args.warp, dim=reference.ndim)
            u = linear_displacement_on_grid(linear, reference)
        elif name.endswith(".nii") or name.endswith(".nii.gz"):
            u_field, grid = read_displacement(args.warp)
            if grid.ndim != reference.ndim:
                raise UsageError(f"Warp `{args.warp}` is {grid.ndim}-D but --reference `{args.reference}` is {reference.ndim}-D.")
            if grid.same_geometry(reference):
                u = u_field
            else:
                _check_overlap(grid, reference, args.warp, args.reference)  # as ITK: the field is interpolated linearly at the reference voxels, zero outside it
                u = np.stack([resample_image(u_field[..., d], grid, at, order=1) for d in range(grid.ndim)], axis=-1)
        else:
            raise UsageError(f"MODEL_OR_WARP `{args.warp}` must be a model.npz, a displacement field .nii/.nii.gz "
                             "or an ITK linear transform .tfm/.txt/.mat.")
        points = at + u
        if args.interpolation in ("label", "nearest"):
            image = read_labels(args.image)
            out = resample_labels(image, points, method=args.interpolation, progress=progress)
            write_labels(reference.with_array(out.astype(image.array.dtype, copy=False)), args.output, force=args.force)
        else:
            array, origin, spacing, direction = read_image(args.image)
            values = resample_image(array, Grid(array.shape, origin, spacing, direction), points, order=1 if args.interpolation == "linear" else 3)
            write_scalar(values, reference, args.output, force=args.force)
    print(f"{PROG} apply: {args.image} -> {args.output} ({args.interpolation}) in {time.perf_counter() - start:.1f} s")
    return 0

