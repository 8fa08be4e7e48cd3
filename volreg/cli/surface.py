"""``volreg surface``: boundary meshes and kernel implicit surfaces (paper Section 4) of a label volume's labels."""

from __future__ import annotations

import argparse
import os
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

from volreg import __version__
from volreg.cli._common import PROG, _float_at_least, _label_list, _listing, _warn, output_path
from volreg.errors import SurfaceError, UsageError
from volreg.settings import SurfaceSettings

if TYPE_CHECKING:  # the pipeline is imported when the command runs
    from volreg.grid import LabelVolume

__all__ = ["OUTPUT_PATTERNS", "add_parser", "run"]

#: Every file `surface` may write, whatever its labels (an earlier run's that this one does not
#: write are removed with --force): each label's mesh, GIFTI surface and signed distance, the summary.
OUTPUT_PATTERNS = ("label_*.vtk", "label_*.surf.gii", "sdf_*.nii.gz", "surface.json")

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


def run(args: argparse.Namespace) -> int:
    """``volreg surface``: meshes, implicit surfaces and their signed distances for each label."""
    from volreg.features.label_surfaces import implicit_on_grid, implicit_surfaces, label_surfaces
    from volreg.io import read_labels, write_json, write_mesh, write_scalar
    from volreg.io._atomic import output_folder
    from volreg.io.gifti import GiftiSurfaceMeta, write_gifti
    from volreg.progress import ProgressBars

    # GIFTI POINTSETs of label meshes: in the world of the label volume, which NIfTI calls scanner RAS (code 1).
    scanner_ras = GiftiSurfaceMeta(dataspace=1, xformspace=1)
    start = time.perf_counter()
    volume = read_labels(args.image)
    labels = _select_labels(volume, args.image, args.labels, args.skip_small)
    if args.gifti and volume.ndim != 3:
        raise UsageError(f"--gifti: `{args.image}` is a {volume.ndim}-D image, whose outlines are line segments; "
                         "expected a 3-D label volume (GIFTI holds triangles).")

    outdir: Path = args.output
    meshes = {v: outdir / f"label_{v}.vtk" for v in labels}
    giftis = {v: outdir / f"label_{v}.surf.gii" for v in labels} if args.gifti else {}
    sdfs = {v: outdir / f"sdf_{v}.nii.gz" for v in labels}
    summary_path = outdir / "surface.json"
    # Existing outputs are refused one by one (check_writable), not the folder as a whole.
    with output_folder(outdir, args.force, require_empty=False, outputs=OUTPUT_PATTERNS) as folder:
        # written into the run's staging folder, swapped into outdir at the end
        folder.check_writable([p.name for p in (*meshes.values(), *giftis.values(), *sdfs.values(), summary_path)],
                              force=args.force)
        meshes = {v: folder.path / p.name for v, p in meshes.items()}
        giftis = {v: folder.path / p.name for v, p in giftis.items()}
        sdfs = {v: folder.path / p.name for v, p in sdfs.items()}
        summary_path = folder.path / summary_path.name
        with ProgressBars(quiet=args.quiet) as progress:
            with warnings.catch_warnings(record=True) as caught:
                # label_surfaces warns for each label it skips (on_small="warn").
                warnings.simplefilter("always")
                try:
                    surfaces = label_surfaces(
                        volume,
                        labels,
                        on_small="warn" if args.skip_small else "error",
                        smoothing=args.smoothing,
                        progress=progress,
                    )
                except SurfaceError as exc:
                    if "min_voxels" not in str(exc):
                        raise
                    # a stray speck of a label, common in segmentations
                    raise UsageError(f"{str(exc).rstrip('.')} in `{args.image}`, too few for a surface; pass "
                                     "--skip-small to skip such labels, or --labels to choose the labels.") from exc
            for w in caught:
                _warn("surface", str(w.message))
            if not surfaces:
                raise UsageError(f"No label of `{args.image}` gave a surface; nothing to write.")

            records = []
            implicit = {}
            for i, (label, surf) in enumerate(surfaces.items()):
                t0 = time.perf_counter()
                implicit[label] = implicit_surfaces(volume, {label: surf}, min_width_voxels=args.min_width)[label]
                fit_seconds = time.perf_counter() - t0
                model = implicit[label]
                records.append(
                    {
                        "label": int(label),
                        "mesh": meshes[label].name,
                        **({"gifti": giftis[label].name} if giftis else {}),
                        "sdf": sdfs[label].name,
                        "vertices": int(len(surf.vertices)),
                        "cells": int(len(surf.cells)),
                        "smoothing_mm": float(surf.smoothing),
                        "levels": [float(w) for w in model.widths],
                        "centres": int(sum(len(level.centres) for level in model.levels)),
                        "fit_seconds": round(fit_seconds, 3),
                    }
                )
                progress("fit implicit surfaces", i + 1, len(surfaces))

            for i, (label, surf) in enumerate(surfaces.items()):
                write_mesh(surf.vertices, surf.cells, meshes[label], normals=surf.normals, force=args.force)
                folder.record(meshes[label])
                if giftis:
                    write_gifti(surf.vertices, surf.cells, giftis[label], meta=scanner_ras, force=args.force)
                    folder.record(giftis[label])
                sdf = implicit_on_grid(implicit[label], volume)
                write_scalar(sdf, volume, sdfs[label], force=args.force)
                folder.record(sdfs[label])
                progress("sample and write", i + 1, len(surfaces))

            summary = {
                "volreg_version": __version__,
                "command": "surface",
                "input": str(args.image),
                "grid": {
                    "shape": [int(n) for n in volume.shape],
                    "origin_mm": volume.origin.tolist(),
                    "spacing_mm": volume.spacing.tolist(),
                    "direction": volume.direction.tolist(),
                    "frame": "LPS",
                },
                "parameters": {
                    "smoothing_voxels": args.smoothing,
                    "min_width_voxels": args.min_width,
                    "skip_small": bool(args.skip_small),
                },
                "labels": records,
                "skipped": [int(v) for v in (args.labels or labels) if v not in surfaces],
                "seconds": round(time.perf_counter() - start, 3),
            }
            write_json(summary, summary_path, force=args.force)
            folder.record(summary_path)

    done = sorted(surfaces)
    print(
        f"{PROG} surface: {len(done)} label{'s' if len(done) != 1 else ''} ({_listing(done)}) -> "
        f"{outdir}{os.sep} ({len(folder.written)} files) in {time.perf_counter() - start:.1f} s"
    )
    return 0
