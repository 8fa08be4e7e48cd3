"""A saved warp applied to files, as ``volreg apply`` does: points and meshes moved, images resampled.

The warp is a ``model.npz`` (:class:`~volreg.warp.model.KernelWarp`), a displacement field
(``.nii.gz`` or an ITK composite ``.h5``) or an ITK linear transform (``.tfm``, ``.txt``,
``.mat``).  :func:`write_moved_point_set` carries landmarks or a mesh point by point, in
either direction (:func:`read_point_map`); :func:`write_resampled_image` resamples an image of
the moving space onto a reference grid of the fixed space.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from volreg import io
from volreg.errors import UsageError, VolregWarning
from volreg.grid import Grid, world_box
from volreg.io.fields import axis_order_of, read_displacement, read_itk_composite, read_itk_linear
from volreg.io.pointsets import check_same_format, point_set_kind, read_point_set, write_point_set
from volreg.linear_map import LinearMap
from volreg.warp.field import displacement_on_grid, linear_displacement_on_grid
from volreg.warp.model import KernelWarp
from volreg.warp.points import DisplacementField, transform_normals, transform_points
from volreg.warp.resample import resample_image, resample_labels

__all__ = ["LANDS_INSIDE_WARN", "MovedPointSet", "read_point_map", "write_moved_point_set", "write_resampled_image"]

ProgressCallback = Callable[[str, int, int], None]

#: Below this share of the reference voxels sent into the input image, :func:`write_resampled_image` warns.
LANDS_INSIDE_WARN = 0.5

#: The suffixes of the warps that :func:`read_point_map` and :func:`write_resampled_image` read.
_MODEL = (".npz",)
_LINEAR = (".tfm", ".txt", ".mat")
_FIELD = (".nii", ".nii.gz", ".h5", ".hdf5")
_ITK_COMPOSITE = (".h5", ".hdf5")


def _issue(message: str) -> None:
    """Where the caller passed no ``warn``: the message as a :class:`~volreg.errors.VolregWarning`."""
    warnings.warn(message, VolregWarning, stacklevel=3)


def read_point_map(path: str | os.PathLike[str], space: str, warn: Callable[[str], None] | None = None) \
        -> tuple[KernelWarp | LinearMap | DisplacementField, bool]:
    """The map that carries points out of ``space``, and whether to apply its inverse.

    Parameters
    ----------
    path : path-like
        ``model.npz``, an ITK linear transform (``.tfm``, ``.txt``, ``.mat``) or a displacement
        field (``.nii``, ``.nii.gz``, ``.h5``), which is applied as it is (p + u(p)).
    space : {"fixed", "moving"}
        The space the points are in: a model or a linear transform is applied forwards from
        ``"fixed"``, inverted from ``"moving"``.
    warn : callable, optional
        ``warn(message)`` where a field's name suggests the other direction; default: a
        :class:`~volreg.errors.VolregWarning`.

    Returns
    -------
    map : KernelWarp, LinearMap or DisplacementField
    inverse : bool

    Raises
    ------
    UsageError
        Another suffix.
    """
    warn = warn or _issue
    path = Path(path)
    name = path.name.lower()
    if name.endswith(_MODEL):
        return KernelWarp.load(path), space == "moving"
    if name.endswith(_LINEAR):
        return read_itk_linear(path), space == "moving"
    if name.endswith(_FIELD):
        u, grid = read_itk_composite(path) if name.endswith(_ITK_COMPOSITE) else read_displacement(path)
        inverse_name = "inverse" in name
        if space == "fixed" and inverse_name:
            warn(f"`{path}` is applied as it is (p + u(p)); with --from fixed it must be the fixed -> moving "
                 "field on the fixed grid (warp.nii.gz), but its name suggests the inverse field.")
        elif space == "moving" and not inverse_name:
            warn(f"`{path}` is applied as it is (p + u(p)); with --from moving it must be the moving -> fixed "
                 "field on the moving grid (inverse_warp.nii.gz, ANTs' *InverseWarp.nii.gz), but its name does not "
                 "say inverse.")
        return DisplacementField(u, grid), False
    raise UsageError(f"MODEL_OR_WARP `{path}` must be a model.npz, a displacement field .nii/.nii.gz or .h5 "
                     "or an ITK linear transform .tfm/.txt/.mat.")


@dataclass
class MovedPointSet:
    """What :func:`write_moved_point_set` wrote.

    Attributes
    ----------
    points : int
        How many points were moved (placed landmarks, or a mesh's vertices).
    what : {"points", "vertices"}
        Landmarks or a mesh.
    """

    points: int
    what: str


def _moved_normals(warp, at: np.ndarray, normals: np.ndarray, placed: np.ndarray, dim: int, inverse: bool,
                   mapped: np.ndarray) -> np.ndarray:
    """The normals at the placed points carried by the warp's Jacobian, each keeping its length."""
    nv = normals[placed]
    moved = transform_normals(warp, at, nv[:, :dim], inverse=inverse, mapped=mapped, keep_length=False)
    out = nv.copy()
    out[:, :dim] = moved
    length, new = np.linalg.norm(nv, axis=1), np.linalg.norm(out, axis=1)
    out *= np.divide(length, new, out=np.zeros_like(length), where=new > 0)[:, None]
    return out


def write_moved_point_set(warp_path: str | os.PathLike[str], input_path: str | os.PathLike[str],
                          output: str | os.PathLike[str], *, space: str, force: bool = False,
                          warn: Callable[[str], None] | None = None) -> MovedPointSet:
    """Carry landmarks or a mesh through a saved warp, point by point, and write them in the input's format.

    Parameters
    ----------
    warp_path : path-like
        The warp (:func:`read_point_map`).
    input_path : path-like
        Landmarks (``.csv``, ``.fcsv``, ``.mrk.json``) or a mesh (``.vtk``, ``.vtp``, ``.ply``,
        ``.stl``, ``.obj``, ``.gii``).
    output : path-like
        Of the same format.
    space : {"fixed", "moving"}
        The space the input's points are in; they are written in the other one.
    force : bool, default False
        Replace an existing output.
    warn : callable, optional
        ``warn(message)`` for points outside a field's grid, an inverse that did not converge, and
        what of the input the output cannot hold; default: a :class:`~volreg.errors.VolregWarning`.

    Returns
    -------
    MovedPointSet
    """
    warn = warn or _issue
    input_path, output = Path(input_path), Path(output)
    check_same_format(input_path, output)
    io.check_writable([output], force=force)
    data = read_point_set(input_path)
    warp, inverse = read_point_map(warp_path, space, warn)
    dim = warp.dim
    placed = np.flatnonzero(~np.all(np.isnan(data.points), axis=1))
    at = data.points[placed][:, :dim]
    mapped = transform_points(warp, at, inverse=inverse)
    out = data.points.copy()
    out[placed, :dim] = mapped.points
    what = "points" if point_set_kind(input_path) in ("csv", "fcsv", "mrk.json") else "vertices"
    n_out = int(np.count_nonzero(mapped.outside))
    if n_out:
        warn(f"{n_out} of {len(at)} {what} lie outside the grid of `{warp_path}`; they are left where they "
             "are (zero displacement there, as ITK does).")
    n_bad = int(np.count_nonzero(~mapped.converged))
    if n_bad:
        warn(f"the inverse of `{warp_path}` did not converge at {n_bad} of {len(at)} {what} (largest "
             f"residual {float(mapped.residual.max()):.3g} mm); the warp may fold there.")
    normals = None
    if data.normals is not None:
        normals = _moved_normals(warp, at, data.normals, placed, dim, inverse, mapped.points)
    for item in data.dropped:
        warn(f"{item} of `{input_path}` are not written (they would no longer fit the moved mesh).")
    if data.unwritable:
        warn(f"{', '.join(data.unwritable)} of `{input_path}` left out of `{output}`: a "
             f"{output.suffix.lower()} file holds normals, texture coordinates and one colour array only "
             "(.vtk and .vtp keep every array).")
    write_point_set(data, out, output, normals=normals, force=force)
    return MovedPointSet(points=len(placed), what=what)


def _check_overlap(field, reference, warp_path, reference_path) -> None:
    """Refuse a displacement field whose grid misses the reference grid: it would act as the identity there."""
    lo1, hi1 = world_box(field)
    lo2, hi2 = world_box(reference)
    if np.any(hi1 < lo2) or np.any(hi2 < lo1):
        raise UsageError(
            f"Warp `{warp_path}` covers {np.round(lo1, 1).tolist()}..{np.round(hi1, 1).tolist()} mm (LPS) and "
            f"--reference `{reference_path}` {np.round(lo2, 1).tolist()}..{np.round(hi2, 1).tolist()} mm: they do not "
            "overlap, so the warp would leave every reference voxel where it is; expected a warp on (or around) the "
            "reference's grid (check the origins, or the pairing of the warp and the reference)."
        )


def _warn_partial_cover(field, points, warp_path, reference_path, warn) -> None:
    """One warning where some reference voxels lie outside the field's grid (voxel centres to half a
    voxel beyond): the displacement there is 0, as ITK reads a field, so they are not warped."""
    index = field.world_to_index(points.reshape(-1, field.ndim))
    inside = np.all((index >= -0.5) & (index <= np.array(field.shape) - 0.5), axis=1)
    share = float(inside.mean())
    if share < 1.0:
        warn(f"warp `{warp_path}` covers {100 * share:.1f} % of the voxels of --reference `{reference_path}`; "
             "outside it the displacement is 0 (as ITK reads a field), so those voxels are not warped (apply the "
             "model.npz of the registration, which holds the whole map, or a warp written on the reference's grid).")


def _check_lands_inside(source, points, warp_path, image_path, reference_path, warn) -> None:
    """Refuse a warp that sends every reference voxel outside the input (the output would be all
    background), and warn where it sends under :data:`LANDS_INSIDE_WARN` of them inside."""
    index = source.world_to_index(points.reshape(-1, source.ndim))
    inside = np.all((index >= -0.5) & (index <= np.array(source.shape) - 0.5), axis=1)
    share = float(inside.mean()) if inside.size else 0.0
    if share == 0.0:
        lo, hi = world_box(source)
        flat = points.reshape(-1, source.ndim)
        raise UsageError(
            f"Warp `{warp_path}` sends every voxel of --reference `{reference_path}` outside INPUT `{image_path}` "
            f"(INPUT covers {np.round(lo, 1).tolist()}..{np.round(hi, 1).tolist()} mm, LPS; the warped voxels lie in "
            f"{np.round(flat.min(axis=0), 1).tolist()}..{np.round(flat.max(axis=0), 1).tolist()} mm), so the output "
            "would be empty; expected INPUT in the warp's moving space (check the pairing of the warp, the image and "
            "--reference, or their origins)."
        )
    if share < LANDS_INSIDE_WARN:
        warn(f"warp `{warp_path}` sends only {100 * share:.1f} % of the voxels of --reference "
             f"`{reference_path}` into INPUT `{image_path}`; the rest are background (0) in the output (check the "
             "pairing of the warp and the image, or their origins).")


def _displacement_on_reference(warp_path: Path, reference, reference_path, at: np.ndarray,
                               progress: ProgressCallback | None, warn) -> np.ndarray:
    """The warp's displacement at every voxel of ``reference`` (``at``: their centres), (X, Y, Z, 3) mm."""
    name = warp_path.name.lower()
    if name.endswith(_MODEL):
        warp = KernelWarp.load(warp_path)
        if warp.dim != reference.ndim:
            raise UsageError(f"Model `{warp_path}` is {warp.dim}-D but --reference `{reference_path}` is {reference.ndim}-D.")
        # the model's linear part included: outside the kernels' support u = (A - I) x + b
        return displacement_on_grid(warp, reference, progress=progress)
    if name.endswith(_LINEAR):
        linear = read_itk_linear(warp_path, dim=reference.ndim)
        return linear_displacement_on_grid(linear, reference)
    if name.endswith(_FIELD):
        u_field, grid = read_itk_composite(warp_path) if name.endswith(_ITK_COMPOSITE) else read_displacement(warp_path)
        if grid.ndim != reference.ndim:
            raise UsageError(f"Warp `{warp_path}` is {grid.ndim}-D but --reference `{reference_path}` is {reference.ndim}-D.")
        order = axis_order_of(grid, reference)  # a single-voxel axis is stored first (write_displacement)
        if order is not None:
            return np.transpose(u_field, order + (grid.ndim,))
        # as ITK: the field is interpolated linearly at the reference voxels, zero outside it
        _check_overlap(grid, reference, warp_path, reference_path)
        _warn_partial_cover(grid, at, warp_path, reference_path, warn)
        return np.stack([resample_image(u_field[..., d], grid, at, order=1) for d in range(grid.ndim)], axis=-1)
    raise UsageError(f"MODEL_OR_WARP `{warp_path}` must be a model.npz, a displacement field .nii/.nii.gz "
                     "or .h5, or an ITK linear transform .tfm/.txt/.mat.")


def write_resampled_image(warp_path: str | os.PathLike[str], image_path: str | os.PathLike[str],
                          reference_path: str | os.PathLike[str], output: str | os.PathLike[str], *,
                          interpolation: str = "label", force: bool = False, progress: ProgressCallback | None = None,
                          warn: Callable[[str], None] | None = None) -> None:
    """Resample an image of the moving space onto the grid of a reference image through a saved warp.

    Parameters
    ----------
    warp_path : path-like
        ``model.npz``, a displacement field on (or around) the reference grid (``warp.nii.gz``,
        ``warp.h5``: fixed -> moving) or an ITK linear transform.
    image_path : path-like
        The image, in moving space.
    reference_path : path-like
        The image whose grid the output takes (fixed space).
    output : path-like
        The resampled image (``.nii.gz``, ``.nii``, ``.nrrd``, ``.mha``).
    interpolation : {"label", "nearest", "gaussian", "linear", "bspline"}
        ``label`` (per-label signed distances) and ``gaussian`` (Gaussian-smoothed indicators)
        preserve labels; ``nearest`` keeps labels, or intensities that are not integers, as they
        are; ``linear`` and ``bspline`` resample intensities (written as float32).
    force : bool, default False
        Replace an existing output.
    progress : callable, optional
        ``progress(stage, done, total)``.
    warn : callable, optional
        ``warn(message)`` where a field misses part of the reference, or few reference voxels
        land inside the image; default: a :class:`~volreg.errors.VolregWarning`.

    Raises
    ------
    UsageError
        Images of other dimensions, a warp of another dimension or suffix, a field whose grid
        misses the reference, or a warp that sends every reference voxel outside the image.
    """
    warn = warn or _issue
    warp_path = Path(warp_path)
    reference = io.read_grid(reference_path)
    as_labels = interpolation in ("label", "nearest", "gaussian")
    if interpolation == "nearest":  # labels, or intensities (NaN, fractions) read as they are
        array, origin, spacing, direction = io.read_image(image_path)
        as_labels = bool(np.all(np.isfinite(array)) and np.all(array == np.round(array)))
    if as_labels:
        image = io.read_labels(image_path)
        source = image
    else:
        if interpolation != "nearest":
            array, origin, spacing, direction = io.read_image(image_path)
        source = Grid(array.shape[: len(spacing)], origin, spacing, direction)
    if source.ndim != reference.ndim:
        raise UsageError(f"INPUT `{image_path}` is {source.ndim}-D but --reference `{reference_path}` is "
                         f"{reference.ndim}-D; expected an image of the warp's moving space, as many axes as the reference.")
    at = reference.grid_points()  # (X, Y, Z, 3) mm
    points = at + _displacement_on_reference(warp_path, reference, reference_path, at, progress, warn)
    _check_lands_inside(source, points, warp_path, image_path, reference_path, warn)
    if as_labels:
        out = resample_labels(image, points, method=interpolation, progress=progress)
        io.write_labels(reference.with_array(out.astype(image.array.dtype, copy=False)), output, force=force)
    else:
        order = {"nearest": 0, "linear": 1}.get(interpolation, 3)
        values = resample_image(array, Grid(array.shape, origin, spacing, direction), points, order=order)
        io.write_scalar(values, reference, output, force=force)
