"""``volreg surface``: boundary meshes and kernel implicit surfaces (paper Section 4) of a label volume's labels."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

from volreg.cli._common import PROG, _float_at_least, _label_list, _listing, _warn, output_path
from volreg.errors import UsageError
from volreg.settings import SurfaceSettings

if TYPE_CHECKING:  # the pipeline is imported when the command runs
    from volreg.grid import LabelVolume

__all__ = ["add_parser", "run"]

_DEFAULTS = SurfaceSettings()


def add_parser(commands) -> None:
    """Add ``surface`` to the ``volreg`` subcommands."""
    surface = commands.add_parser(
        "surface",
        help="meshes and implicit surfaces of the labels of a label volume",
        description="For each label: a boundary mesh with outward normals (OUTDIR/label_<id>.vtk, LPS mm; "
        "line segments for a 2-D image; with --gifti also OUTDIR/label_<id>.surf.gii, RAS mm) and the fitted kernel implicit surface sampled on the input "
        "grid as a float32 signed distance in mm, negative inside (OUTDIR/sdf_<id>.nii.gz), plus "
        "OUTDIR/surface.json summarising the run.",
    )
    surface.add_argument(
        "image", metavar="LABELS", type=Path,
        help="label volume: .nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd or .vti",
    )
    surface.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, required=True,
                         help="output directory (created if missing)")
    surface.add_argument("--labels", metavar="IDS", type=_label_list, default=None,
                         help="comma-separated labels to process, e.g. 1,3 (default: every non-zero label)")
    surface.add_argument("--skip-small", action="store_true",
                         help="warn about and skip labels that are absent or too small, instead of failing")
    surface.add_argument("--smoothing", metavar="VOXELS", type=_float_at_least(0.0, strict=False, upper=10.0),
                         default=_DEFAULTS.smoothing,
                         help="Gaussian blur (s.d.) of each mask before contouring, in units of the largest voxel spacing "
                         f"(default {_DEFAULTS.smoothing}; 0: none)")
    surface.add_argument("--min-width", metavar="VOXELS", type=_float_at_least(0.0, strict=True),
                         default=_DEFAULTS.min_width_voxels,
                         help="finest kernel width of the implicit surface, in units of the largest voxel spacing "
                         f"(default {_DEFAULTS.min_width_voxels:g})")
    surface.add_argument("--gifti", action="store_true",
                         help="also write each 3-D mesh as a GIFTI surface (label_<id>.surf.gii, scanner RAS mm)")
    surface.add_argument("--force", action="store_true", help="overwrite existing outputs")
    surface.add_argument("--quiet", action="store_true", help="no progress bars")
    surface.set_defaults(run=run)


def _select_labels(volume: LabelVolume, image: Path, requested: list[int] | None, skip: bool) -> list[int]:
    """The labels to process: ``requested`` (checked against the volume) or all present."""
    present = volume.labels().tolist()
    if not present:
        raise UsageError(f"Label image `{image}` holds no labels (every voxel is 0); expected a segmentation.")
    if requested is None:
        return present
    present_set = set(present)
    absent = [v for v in requested if v not in present_set]
    for v in absent:
        message = f"label {v} of --labels is absent from `{image}` (labels present: {_listing(present)})"
        if not skip:
            raise UsageError(message[0].upper() + message[1:] + "; pass --skip-small to skip it.")
        _warn("surface", f"skipping {message}.")
    labels = [v for v in requested if v not in absent]
    if not labels:
        raise UsageError(f"None of --labels {_listing(requested)} is present in `{image}`; nothing to do.")
    return labels


def _read_volume(image: Path) -> LabelVolume:
    """The label volume ``image``, once its header shows that the job fits in memory (nothing is
    decompressed before: :func:`volreg.pipeline.checks.surface_peak_bytes`)."""
    from volreg.io import read_labels
    from volreg.io.footprint import check_job_memory, image_footprint
    from volreg.pipeline.checks import surface_peak_bytes

    declared = image_footprint(image, "Label image")
    check_job_memory("surface", surface_peak_bytes(declared), declared)
    return read_labels(image)


def run(args: argparse.Namespace) -> int:
    """``volreg surface``: meshes, implicit surfaces and their signed distances for each label
    (:func:`volreg.outputs.surfaces.write_label_surfaces`)."""
    from volreg.outputs.surfaces import write_label_surfaces
    from volreg.progress import ProgressBars

    start = time.perf_counter()
    volume = _read_volume(args.image)
    labels = _select_labels(volume, args.image, args.labels, args.skip_small)
    if args.gifti and volume.ndim != 3:
        raise UsageError(f"--gifti: `{args.image}` is a {volume.ndim}-D image, whose outlines are line segments; "
                         "expected a 3-D label volume (GIFTI holds triangles).")
    with ProgressBars(quiet=args.quiet) as progress:
        written = write_label_surfaces(
            volume, labels, args.output, image_path=args.image, requested=args.labels, skip_small=args.skip_small,
            smoothing=args.smoothing, min_width_voxels=args.min_width, gifti=args.gifti, force=args.force,
            progress=progress, warn=lambda message: _warn("surface", message), started=start,
        )
    done = written.labels
    print(
        f"{PROG} surface: {len(done)} label{'s' if len(done) != 1 else ''} ({_listing(done)}) -> "
        f"{args.output}{os.sep} ({written.files} files) in {time.perf_counter() - start:.1f} s"
    )
    return 0
