"""``volreg apply``: carry an image, landmarks or a mesh through a saved warp."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from volreg.cli._common import PROG, _warn, output_path
from volreg.errors import UsageError

__all__ = ["add_parser", "run"]

#: What ``--from`` says about INPUT's points, and where they go.
_DIRECTIONS = {"fixed": "fixed -> moving space", "moving": "moving -> fixed space"}


def add_parser(commands) -> None:
    """Add ``apply`` to the ``volreg`` subcommands."""
    apply = commands.add_parser(
        "apply",
        help="carry an image, landmarks or a mesh through a saved result",
        description="Carry INPUT through a saved warp: a model.npz or displacement field (warp.nii.gz, "
        "inverse_warp.nii.gz) from `volreg register`, or an ITK linear transform (.tfm, .txt, .mat). "
        "An image (in moving space) is resampled onto the grid of --reference (fixed space). Landmarks "
        "(.csv, .fcsv, .mrk.json) and meshes (.vtk, .vtp, .ply, .stl, .obj, .gii) are moved point by point; "
        "--from names the space they are in: fixed (carried to moving space by tau: model.npz, warp.nii.gz or "
        "the linear transform) or moving (carried to fixed space by the inverse: model.npz, inverse_warp.nii.gz "
        "or the linear transform). A displacement field is applied as it is, p + u(p): give the field of the "
        "direction you want.",
    )
    apply.add_argument("warp", metavar="MODEL_OR_WARP", type=Path,
                       help="model.npz, a displacement field (warp.nii.gz or warp.h5: fixed -> moving; "
                       "inverse_warp.nii.gz or inverse_warp.h5: moving -> fixed) or an ITK linear transform "
                       "(.tfm, .txt, .mat)")
    apply.add_argument("image", metavar="INPUT", type=Path,
                       help="image in moving space, or landmarks / mesh in the space --from names")
    apply.add_argument("--from", dest="space", choices=tuple(_DIRECTIONS), default=None,
                       help="landmarks and meshes only (required for them): the space INPUT's points are in; they are "
                       "written in the other one")
    apply.add_argument("--reference", metavar="REF", type=Path, default=None,
                       help="images only (required for them): image whose grid the output takes (fixed space)")
    apply.add_argument("-o", "--output", metavar="OUT", type=output_path, required=True,
                       help="output: an image (.nii.gz, .nii, .nrrd, .mha), or points / mesh in INPUT's format")
    apply.add_argument("--interpolation", choices=("label", "nearest", "gaussian", "linear", "bspline"), default=None,
                       help="images only: label: label-preserving (per-label signed distances, default); nearest; "
                       "gaussian: label-preserving, Gaussian-smoothed indicators (0.8 x the geometric-mean spacing); "
                       "linear or bspline for intensity images (written as float32)")
    apply.add_argument("--force", action="store_true", help="overwrite an existing output")
    apply.add_argument("--quiet", action="store_true", help="no progress bars")
    apply.set_defaults(run=run)


def _kind(path: Path) -> str:
    """``"points"``, ``"mesh"`` or ``"image"`` by INPUT's suffix; a one-line error for any other."""
    from volreg.io.images import READ_SUFFIXES
    from volreg.io.pointsets import MESH_FORMATS, POINT_SUFFIXES, point_set_kind

    kind = point_set_kind(path)
    if kind in ("csv", "fcsv", "mrk.json"):
        return "points"
    if kind is not None:
        return "mesh"
    if path.name.lower().endswith(READ_SUFFIXES):
        return "image"
    raise UsageError(f"INPUT `{path}` has an unsupported suffix; expected an image ({', '.join(READ_SUFFIXES)}), "
                     f"points ({', '.join(POINT_SUFFIXES)}) or a mesh ({', '.join(MESH_FORMATS)}).")


def run(args: argparse.Namespace) -> int:
    """``volreg apply MODEL_OR_WARP INPUT (--reference REF | --from fixed|moving) -o OUT``."""
    kind = _kind(args.image)
    if kind == "image":
        if args.space is not None:
            raise UsageError(f"--from is for landmarks and meshes; an image (`{args.image}`) is always resampled from "
                             "moving space onto the grid of --reference (fixed space): drop --from.")
        if args.reference is None:
            raise UsageError(f"--reference is required for an image (`{args.image}`); expected the fixed image whose "
                             "grid the output takes.")
        return _run_image(args)
    if args.space is None:
        raise UsageError(f"--from is required for {kind} `{args.image}`; expected --from fixed (its points are in the "
                         "fixed image's space, carried to moving space) or --from moving (carried to fixed space).")
    if args.reference is not None:
        raise UsageError(f"--reference is for images; {kind} `{args.image}` is carried point by point without a grid: "
                         "drop --reference.")
    if args.interpolation is not None:
        raise UsageError(f"--interpolation is for images; {kind} `{args.image}` is carried point by point: "
                         "drop --interpolation.")
    return _run_points(args)


def _run_points(args: argparse.Namespace) -> int:
    """Landmarks or a mesh, carried point by point (:func:`volreg.outputs.apply.write_moved_point_set`)."""
    from volreg.outputs.apply import write_moved_point_set

    start = time.perf_counter()
    moved = write_moved_point_set(args.warp, args.image, args.output, space=args.space, force=args.force,
                                  warn=lambda message: _warn("apply", message))
    print(f"{PROG} apply: {args.image} ({moved.points} {moved.what}, {_DIRECTIONS[args.space]}) -> {args.output} "
          f"in {time.perf_counter() - start:.1f} s")
    return 0


def _run_image(args: argparse.Namespace) -> int:
    """An image in moving space, resampled onto the grid of --reference
    (:func:`volreg.outputs.apply.write_resampled_image`)."""
    from volreg.io.footprint import check_job_memory, image_footprint
    from volreg.outputs.apply import write_resampled_image
    from volreg.pipeline.checks import apply_peak_bytes
    from volreg.progress import ProgressBars

    interpolation = args.interpolation or "label"
    start = time.perf_counter()
    # the job's size from the headers, before any voxel is decompressed
    declared_reference = image_footprint(args.reference)
    declared = image_footprint(args.image, "Label image" if interpolation in ("label", "gaussian") else "Image")
    name = args.warp.name.lower()
    field = image_footprint(args.warp, "Displacement field") if name.endswith((".nii", ".nii.gz")) else None
    largest = max((declared, declared_reference, field), key=lambda f: 0 if f is None else f.voxels)
    check_job_memory("apply", apply_peak_bytes(declared, declared_reference, field), largest)
    with ProgressBars(quiet=args.quiet) as progress:
        write_resampled_image(args.warp, args.image, args.reference, args.output, interpolation=interpolation,
                              force=args.force, progress=progress, warn=lambda message: _warn("apply", message))
    print(f"{PROG} apply: {args.image} -> {args.output} ({interpolation}) in {time.perf_counter() - start:.1f} s")
    return 0
