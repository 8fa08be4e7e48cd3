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


def _check_overlap(field, reference, warp_path, reference_path) -> None:
    """Refuse a displacement field whose grid misses the reference grid: it would act as the identity there."""
    import numpy as np

    from volreg.grid import world_box

    lo1, hi1 = world_box(field)
    lo2, hi2 = world_box(reference)
    if np.any(hi1 < lo2) or np.any(hi2 < lo1):
        raise UsageError(
            f"Warp `{warp_path}` covers {np.round(lo1, 1).tolist()}..{np.round(hi1, 1).tolist()} mm (LPS) and "
            f"--reference `{reference_path}` {np.round(lo2, 1).tolist()}..{np.round(hi2, 1).tolist()} mm: they do not "
            "overlap, so the warp would leave every reference voxel where it is; expected a warp on (or around) the "
            "reference's grid (check the origins, or the pairing of the warp and the reference)."
        )


def _warn_partial_cover(field, points, warp_path, reference_path) -> None:
    """One warning line where some reference voxels lie outside the field's grid (voxel centres
    to half a voxel beyond): the displacement there is 0, as ITK reads a field, so they are not warped."""
    import numpy as np

    index = field.world_to_index(points.reshape(-1, field.ndim))
    inside = np.all((index >= -0.5) & (index <= np.array(field.shape) - 0.5), axis=1)
    share = float(inside.mean())
    if share < 1.0:
        _warn("apply", f"warp `{warp_path}` covers {100 * share:.1f} % of the voxels of --reference `{reference_path}`; "
              "outside it the displacement is 0 (as ITK reads a field), so those voxels are not warped (apply the "
              "model.npz of the registration, which holds the whole map, or a warp written on the reference's grid).")


#: Below this share of the reference voxels sent into INPUT, ``apply`` warns.
LANDS_INSIDE_WARN = 0.5


def _check_lands_inside(source, points, args) -> None:
    """Refuse a warp that sends every reference voxel outside INPUT (the output would be all
    background), and warn where it sends under :data:`LANDS_INSIDE_WARN` of them inside."""
    import numpy as np

    from volreg.grid import world_box

    index = source.world_to_index(points.reshape(-1, source.ndim))
    inside = np.all((index >= -0.5) & (index <= np.array(source.shape) - 0.5), axis=1)
    share = float(inside.mean()) if inside.size else 0.0
    if share == 0.0:
        lo, hi = world_box(source)
        flat = points.reshape(-1, source.ndim)
        raise UsageError(
            f"Warp `{args.warp}` sends every voxel of --reference `{args.reference}` outside INPUT `{args.image}` "
            f"(INPUT covers {np.round(lo, 1).tolist()}..{np.round(hi, 1).tolist()} mm, LPS; the warped voxels lie in "
            f"{np.round(flat.min(axis=0), 1).tolist()}..{np.round(flat.max(axis=0), 1).tolist()} mm), so the output "
            "would be empty; expected INPUT in the warp's moving space (check the pairing of the warp, the image and "
            "--reference, or their origins)."
        )
    if share < LANDS_INSIDE_WARN:
        _warn("apply", f"warp `{args.warp}` sends only {100 * share:.1f} % of the voxels of --reference "
              f"`{args.reference}` into INPUT `{args.image}`; the rest are background (0) in the output (check the "
              "pairing of the warp and the image, or their origins).")


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
    return _run_points(args, kind)


def _read_warp(path: Path, space: str):
    """The map to apply and whether to invert it: (KernelWarp | LinearMap | DisplacementField, inverse)."""
    from volreg.io.fields import read_displacement, read_itk_composite, read_itk_linear
    from volreg.warp.model import KernelWarp
    from volreg.warp.points import DisplacementField

    name = path.name.lower()
    if name.endswith(".npz"):
        return KernelWarp.load(path), space == "moving"
    if name.endswith((".tfm", ".txt", ".mat")):
        return read_itk_linear(path), space == "moving"
    if name.endswith((".nii", ".nii.gz", ".h5", ".hdf5")):
        u, grid = read_itk_composite(path) if name.endswith((".h5", ".hdf5")) else read_displacement(path)
        inverse_name = "inverse" in name
        if space == "fixed" and inverse_name:
            _warn("apply", f"`{path}` is applied as it is (p + u(p)); with --from fixed it must be the fixed -> moving "
                  "field on the fixed grid (warp.nii.gz), but its name suggests the inverse field.")
        elif space == "moving" and not inverse_name:
            _warn("apply", f"`{path}` is applied as it is (p + u(p)); with --from moving it must be the moving -> fixed "
                  "field on the moving grid (inverse_warp.nii.gz, ANTs' *InverseWarp.nii.gz), but its name does not "
                  "say inverse.")
        return DisplacementField(u, grid), False
    raise UsageError(f"MODEL_OR_WARP `{path}` must be a model.npz, a displacement field .nii/.nii.gz or .h5 "
                     "or an ITK linear transform .tfm/.txt/.mat.")


def _run_points(args: argparse.Namespace, kind: str) -> int:
    """Landmarks or a mesh, carried point by point."""
    import numpy as np

    from volreg.io import check_writable
    from volreg.io.pointsets import check_same_format, read_point_set, write_point_set
    from volreg.warp.points import transform_normals, transform_points

    start = time.perf_counter()
    check_same_format(args.image, args.output)
    check_writable([args.output], force=args.force)
    data = read_point_set(args.image)
    warp, inverse = _read_warp(args.warp, args.space)
    dim = warp.dim
    placed = np.flatnonzero(~np.all(np.isnan(data.points), axis=1))
    at = data.points[placed][:, :dim]
    mapped = transform_points(warp, at, inverse=inverse)
    out = data.points.copy()
    out[placed, :dim] = mapped.points
    what = "points" if kind == "points" else "vertices"
    n_out = int(np.count_nonzero(mapped.outside))
    if n_out:
        _warn("apply", f"{n_out} of {len(at)} {what} lie outside the grid of `{args.warp}`; they are left where they "
              "are (zero displacement there, as ITK does).")
    n_bad = int(np.count_nonzero(~mapped.converged))
    if n_bad:
        _warn("apply", f"the inverse of `{args.warp}` did not converge at {n_bad} of {len(at)} {what} (largest "
              f"residual {float(mapped.residual.max()):.3g} mm); the warp may fold there.")
    normals = None
    if data.normals is not None:
        nv = data.normals[placed]
        moved = transform_normals(warp, at, nv[:, :dim], inverse=inverse, mapped=mapped.points, keep_length=False)
        normals = nv.copy()
        normals[:, :dim] = moved
        length, new = np.linalg.norm(nv, axis=1), np.linalg.norm(normals, axis=1)
        normals *= np.divide(length, new, out=np.zeros_like(length), where=new > 0)[:, None]
    for item in data.dropped:
        _warn("apply", f"{item} of `{args.image}` are not written (they would no longer fit the moved mesh).")
    if data.unwritable:
        _warn("apply", f"{', '.join(data.unwritable)} of `{args.image}` left out of `{args.output}`: a "
              f"{args.output.suffix.lower()} file holds normals, texture coordinates and one colour array only "
              "(.vtk and .vtp keep every array).")
    write_point_set(data, out, args.output, normals=normals, force=args.force)
    print(f"{PROG} apply: {args.image} ({len(placed)} {what}, {_DIRECTIONS[args.space]}) -> {args.output} "
          f"in {time.perf_counter() - start:.1f} s")
    return 0


def _run_image(args: argparse.Namespace) -> int:
    """An image in moving space, resampled onto the grid of --reference."""
    import numpy as np

    from volreg.grid import Grid
    from volreg.io import read_grid, read_image, read_labels, write_labels, write_scalar
    from volreg.io.footprint import check_job_memory, image_footprint
    from volreg.pipeline.checks import apply_peak_bytes
    from volreg.io.fields import axis_order_of, read_displacement, read_itk_composite, read_itk_linear
    from volreg.progress import ProgressBars
    from volreg.warp.field import displacement_on_grid, linear_displacement_on_grid
    from volreg.warp.model import KernelWarp
    from volreg.warp.resample import resample_image, resample_labels

    interpolation = args.interpolation or "label"
    start = time.perf_counter()
    # the job's size from the headers, before any voxel is decompressed
    declared_reference = image_footprint(args.reference)
    declared = image_footprint(args.image, "Label image" if interpolation in ("label", "gaussian") else "Image")
    name = args.warp.name.lower()
    field = image_footprint(args.warp, "Displacement field") if name.endswith((".nii", ".nii.gz")) else None
    largest = max((declared, declared_reference, field), key=lambda f: 0 if f is None else f.voxels)
    check_job_memory("apply", apply_peak_bytes(declared, declared_reference, field), largest)
    reference = read_grid(args.reference)
    as_labels = interpolation in ("label", "nearest", "gaussian")
    if interpolation == "nearest":  # labels, or intensities (NaN, fractions) read as they are
        array, origin, spacing, direction = read_image(args.image)
        as_labels = bool(np.all(np.isfinite(array)) and np.all(array == np.round(array)))
    if as_labels:
        image = read_labels(args.image)
        source = image
    else:
        if interpolation != "nearest":
            array, origin, spacing, direction = read_image(args.image)
        source = Grid(array.shape[: len(spacing)], origin, spacing, direction)
    if source.ndim != reference.ndim:
        raise UsageError(f"INPUT `{args.image}` is {source.ndim}-D but --reference `{args.reference}` is "
                         f"{reference.ndim}-D; expected an image of the warp's moving space, as many axes as the reference.")
    at = reference.grid_points()  # (X, Y, Z, 3) mm
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
        elif name.endswith((".nii", ".nii.gz", ".h5", ".hdf5")):
            u_field, grid = (read_itk_composite(args.warp) if name.endswith((".h5", ".hdf5"))
                             else read_displacement(args.warp))
            if grid.ndim != reference.ndim:
                raise UsageError(f"Warp `{args.warp}` is {grid.ndim}-D but --reference `{args.reference}` is {reference.ndim}-D.")
            order = axis_order_of(grid, reference)  # a single-voxel axis is stored first (write_displacement)
            if order is not None:
                u = np.transpose(u_field, order + (grid.ndim,))
            else:
                _check_overlap(grid, reference, args.warp, args.reference)  # as ITK: the field is interpolated linearly at the reference voxels, zero outside it
                _warn_partial_cover(grid, at, args.warp, args.reference)
                u = np.stack([resample_image(u_field[..., d], grid, at, order=1) for d in range(grid.ndim)], axis=-1)
        else:
            raise UsageError(f"MODEL_OR_WARP `{args.warp}` must be a model.npz, a displacement field .nii/.nii.gz "
                             "or .h5, or an ITK linear transform .tfm/.txt/.mat.")
        points = at + u
        _check_lands_inside(source, points, args)
        if as_labels:
            out = resample_labels(image, points, method=interpolation, progress=progress)
            write_labels(reference.with_array(out.astype(image.array.dtype, copy=False)), args.output, force=args.force)
        else:
            order = {"nearest": 0, "linear": 1}.get(interpolation, 3)
            values = resample_image(array, Grid(array.shape, origin, spacing, direction), points, order=order)
            write_scalar(values, reference, args.output, force=args.force)
    print(f"{PROG} apply: {args.image} -> {args.output} ({interpolation}) in {time.perf_counter() - start:.1f} s")
    return 0

