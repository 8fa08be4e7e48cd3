"""Displacement fields and linear transforms as ANTs and ITK read and write them.

Displacement fields: NIfTI-1, 5-D, intent vector; or the same field as an ITK
composite transform in HDF5 (``.h5``).  Linear transforms: ITK's
"Insight Transform File V1.0" text format (``.tfm`` or ``.txt``).

Convention (docs/conventions.md): a displacement field lives on the fixed
(reference) grid; voxel ``x`` holds ``u(x) = tau(x) - x`` in ITK physical
space (LPS, mm), so that a moving image is pulled back as
``moving(x + u(x))``.  On disk: NIfTI-1, float32, shape ``(X, Y, Z, 1, 3)``
(``(X, Y, 1, 1, 2)`` in 2-D), intent code 1007 (vector), identical qform and
sform (code 1) holding the RAS form of the LPS grid.  The vector components
are *not* flipped to RAS: ITK (and so ANTs, SimpleITK, Slicer) store them as
LPS, and read them back as such.

A linear transform ``x -> A x + b`` (:class:`~volreg.linear_map.LinearMap`) is
written as ITK's ``AffineTransform_double_3_3`` (``_2_2`` in 2-D): ``Parameters``
are ``A`` row by row, then ``b``; ``FixedParameters`` the centre, zero.  ITK's
transforms map points of the output (fixed) space to the input (moving) space,
in LPS mm -- the direction and frame of volreg's pull-back ``tau`` -- so no
flips are needed; ITK, SimpleITK, ANTs and 3D Slicer read the file as it is.

An ITK composite transform file (``.h5``, ITK's HDF5 transform format) holds a
``CompositeTransform`` of one ``DisplacementFieldTransform_double_D_D`` whose
field is the NIfTI field's: same grid, same LPS vectors, the values rounded to
float32 as the NIfTI file stores them, so both files are the same map.  ANTs
(``antsApplyTransforms -t warp.h5``, ``ants.apply_transforms``), SimpleITK
(``sitk.ReadTransform``) and 3D Slicer load it as a transform without being
told what the file is.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import SimpleITK as sitk

from volreg.grid import Grid, GridLike, LabelVolume, as_grid
from volreg.errors import VolregIOError, exception_text, excerpt
from volreg.io._atomic import atomic_output
from volreg.io._guards import check_image_data_files, check_readable
from volreg.io.images import (_check_header_fields, _check_input, _check_nifti, _itk_quiet, _nifti_float_voxels,
                              _sitk_reason)
from volreg.linear_map import LinearMap

__all__ = [
    "write_displacement",
    "read_displacement",
    "write_itk_composite",
    "read_itk_composite",
    "write_itk_linear",
    "read_itk_linear",
]

_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def _nifti_suffix(path: Path, what: str) -> None:
    name = path.name.lower()
    if not (name.endswith(".nii") or name.endswith(".nii.gz")):
        raise VolregIOError(f"{what} `{path}` must be NIfTI (.nii or .nii.gz), the format ANTs and ITK read fields from.")


def _ras_affine(like: Grid) -> np.ndarray:
    """4x4 RAS affine of a 2-D or 3-D LPS grid (2-D grids get a unit third axis)."""
    a = np.eye(4)
    d = like.ndim
    a[:d, :d] = like.direction * like.spacing[None, :]
    a[:d, 3] = like.origin
    return _LPS_TO_RAS @ a


def _checked_displacement(displacement, like: Grid) -> np.ndarray:
    """``displacement`` as an array of shape ``(*like.shape, D)``, finite; else a VolregIOError."""
    u = np.asarray(displacement)
    want = (*like.shape, like.ndim)
    if u.shape != want:
        raise VolregIOError(f"Expected `displacement` of shape {want} (grid of `like`, then D), got {u.shape}.")
    if not np.all(np.isfinite(u)):
        raise VolregIOError("Expected a finite `displacement`; it holds NaN or Inf.")
    return u


def write_displacement(
    displacement: np.ndarray, like: GridLike, path: str | os.PathLike[str], *, force: bool = False
) -> None:
    """Write a displacement field in the ANTs/ITK convention, atomically.

    Parameters
    ----------
    displacement : (*like.shape, D) float ndarray, LPS mm
        ``u(x) = tau(x) - x`` at the voxel centres of ``like``.
    like : Grid, LabelVolume or (shape, affine)
        The reference (fixed) grid: origin, spacing, direction (a volume's array is not used).
    path : path-like
        ``.nii.gz`` (or ``.nii``).
    force : bool
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        On a shape mismatch, a non-finite value, a non-NIfTI path, or an
        existing ``path`` without ``force``.
    """
    like = as_grid(like, "like")
    p = Path(path)
    _nifti_suffix(p, "Displacement field")
    u = _checked_displacement(displacement, like)
    # A grid whose last axis has one voxel (a sagittal or oblique slice, a line): ITK drops that
    # axis when it reads a vector NIfTI, and the field's direction is then singular or its D
    # components do not fit D - 1 axes, so no tool could apply it.  The same voxels with the
    # single-voxel axes stored first read with all D axes (axis_order_of finds the grid's order).
    order = stored_axis_order(like.shape)
    data = np.transpose(u.astype(np.float32), order + (like.ndim,))
    data = data[:, :, None, None, :] if like.ndim == 2 else data[:, :, :, None, :]
    affine = _ras_affine(like)[:, list(order) + list(range(like.ndim, 4))]  # 4 x 4, also for a 2-D grid
    img = nib.Nifti1Image(data, affine)
    img.header.set_intent("vector")
    img.header.set_qform(affine, code=1)
    img.header.set_sform(affine, code=1)
    img.header.set_xyzt_units("mm", "sec")
    with atomic_output(p, force=force) as tmp:
        if p.name.lower().endswith(".gz"):
            _save_nifti_gz(img, tmp)
        else:
            nib.save(img, str(tmp))


#: A field whose samples deflate to more than this fraction of their size is stored in the gzip
#: stream without compression (:func:`_save_nifti_gz`).
_STORE_ABOVE = 0.85

#: Samples of a field tried for compression: this many, evenly spread, of ``_SAMPLE_BYTES`` each.
_SAMPLES, _SAMPLE_BYTES = 8, 1 << 17


def _gzip_level(data: np.ndarray) -> int:
    """zlib level for a field: 1 (run-length strategy) where samples of its bytes compress,
    0 (stored) where they deflate to more than :data:`_STORE_ABOVE` of their size."""
    import zlib

    raw = np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    if raw.size <= _SAMPLES * _SAMPLE_BYTES:
        starts = [0]
        size = raw.size
    else:
        starts = np.linspace(0, raw.size - _SAMPLE_BYTES, _SAMPLES).astype(np.int64)
        size = _SAMPLE_BYTES
    packed = total = 0
    for s in starts:
        chunk = raw[s : s + size].tobytes()
        c = zlib.compressobj(1, zlib.DEFLATED, -zlib.MAX_WBITS, zlib.DEF_MEM_LEVEL, zlib.Z_RLE)
        packed += len(c.compress(chunk)) + len(c.flush())
        total += len(chunk)
    return 0 if total and packed > _STORE_ABOVE * total else 1


def _save_nifti_gz(img: nib.Nifti1Image, path: Path) -> None:
    """``nib.save`` into a gzip stream compressed with zlib's run-length strategy, or stored.

    Deflate's usual string matching finds almost nothing to match in a field of float32
    displacements: the run-length strategy (matches at distance one only, which still
    shrinks runs of zeros) wrote the full frog's 384 MB field at about 100 MB/s instead
    of 38 MB/s, and 0.4 % smaller.  Where the field is non-zero almost everywhere (an affine
    part moves every voxel) even that saves only a tenth (the 1 mm phantom's 68 MB field:
    61 MB in 0.66 s), and the stream stores the bytes instead (68 MB in 0.09 s), as samples of
    the field tell (:func:`_gzip_level`).  The file is ordinary gzip; every reader opens it.
    """
    import gzip
    import zlib

    level = _gzip_level(np.asanyarray(img.dataobj))
    with open(path, "wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw, compresslevel=1, mtime=0) as gz:
        if hasattr(gz, "compress"):  # CPython's GzipFile keeps its compressor here; else its own is used
            gz.compress = zlib.compressobj(level, zlib.DEFLATED, -zlib.MAX_WBITS, zlib.DEF_MEM_LEVEL,
                                           zlib.Z_RLE if level else zlib.Z_DEFAULT_STRATEGY)
        img.to_file_map({"image": nib.FileHolder(fileobj=gz)})


#: Suffixes ITK's HDF5 transform reader and writer take (ANTs writes ``.h5``).
_ITK_H5_SUFFIXES = (".h5", ".hdf5")


def _itk_pixel_order(u: np.ndarray) -> np.ndarray:
    """``u`` (i, j[, k], D) rounded to float32, as a new float64 array in ITK's pixel order
    (the axes reversed, the components last).

    In 3-D slab by slab along j: one transposing copy through a float32 temporary of a whole
    field is several times slower.
    """
    d = u.ndim - 1
    if d != 3:
        return np.ascontiguousarray(u.astype(np.float32).transpose(*range(d - 1, -1, -1), d), dtype=np.float64)
    out = np.empty((u.shape[2], u.shape[1], u.shape[0], d))
    for j in range(u.shape[1]):
        out[:, j] = u[:, j].astype(np.float32).transpose(1, 0, 2)
    return out


def write_itk_composite(
    displacement: np.ndarray, like: GridLike, path: str | os.PathLike[str], *, force: bool = False
) -> None:
    """Write a displacement field as an ITK composite transform file (HDF5), atomically.

    The file holds a ``CompositeTransform`` of one ``DisplacementFieldTransform``
    whose field is ``displacement`` on the grid of ``like``: the map
    ``x -> x + u(x)`` (fixed point to moving point, LPS mm, linear interpolation
    between voxel centres), as :func:`write_displacement` writes it to NIfTI.  The
    values are rounded to float32 first, as the NIfTI file stores them, so that
    the two files hold the same field (ITK keeps it as float64 here, and SimpleITK
    writes HDF5 transforms uncompressed: the file is twice an uncompressed float32
    NIfTI, and about 2.7 times the ``.nii.gz`` of a registration's warp).

    Parameters
    ----------
    displacement : (*like.shape, D) float ndarray, LPS mm
        ``u(x) = tau(x) - x`` at the voxel centres of ``like``; D = 2 or 3.
    like : Grid, LabelVolume or (shape, affine)
        The reference (fixed) grid: origin, spacing, direction.
    path : path-like
        ``.h5`` (or ``.hdf5``), the suffixes ITK reads as HDF5 transforms.
    force : bool
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        On a shape mismatch, a non-finite value, another suffix, or an existing
        ``path`` without ``force``.
    """
    like = as_grid(like, "like")
    p = Path(path)
    if not p.name.lower().endswith(_ITK_H5_SUFFIXES):
        raise VolregIOError(f"Composite transform `{p}` must be named .h5 or .hdf5, the suffixes ITK reads as HDF5 "
                            "transforms.")
    u = _checked_displacement(displacement, like)
    d = like.ndim
    values = _itk_pixel_order(u)
    field = sitk.GetImageFromArray(values, isVector=True)  # a copy
    del values
    field.SetOrigin(tuple(float(v) for v in like.origin))
    field.SetSpacing(tuple(float(v) for v in like.spacing))
    field.SetDirection(tuple(float(v) for v in like.direction.ravel()))
    composite = sitk.CompositeTransform(d)
    composite.AddTransform(sitk.DisplacementFieldTransform(field))  # takes the field's pixels over
    with atomic_output(p, force=force) as tmp:
        # On a full disk HDF5 prints its error stack (a hundred lines on stderr) before ITK raises
        # with "H5Dwrite failed": a disk without room for the field is reported before writing.
        if shutil.disk_usage(Path(tmp).parent).free < u.nbytes + (1 << 20):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(p))
        try:
            sitk.WriteTransform(composite, str(tmp))
        except RuntimeError as exc:
            if shutil.disk_usage(Path(tmp).parent).free < u.nbytes:  # HDF5 says only "H5Dwrite failed"
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(p)) from None
            raise VolregIOError(f"Composite transform `{p}` could not be written: {_sitk_reason(exc)}.") from None


def _check_hdf5_length(p: Path) -> None:
    """Refuse an HDF5 file shorter than its superblock's end-of-file address (a copy cut short).

    HDF5 prints a diagnostic stack of some 25 lines from C on such a file before ITK raises; the
    superblock (versions 0-3) records the file's length, so a short file is found from its
    first 64 bytes."""
    with open(p, "rb") as fh:
        head = fh.read(64)
    size = p.stat().st_size
    version = head[8] if len(head) > 8 else -1
    if version in (0, 1):
        width = head[13] if len(head) > 13 else 0
        start = 24 if version == 0 else 28
    elif version in (2, 3):
        width = head[9] if len(head) > 9 else 0
        start = 12
    else:
        width, start = 0, 0
    end = start + 3 * width
    if width not in (2, 4, 8) or len(head) < end:
        raise VolregIOError(f"Transform `{p}` is truncated or not a valid HDF5 file (its superblock is incomplete); "
                            "expected an ITK HDF5 transform (.h5), as register writes warp.h5.")
    base = int.from_bytes(head[start:start + width], "little")
    eof = int.from_bytes(head[start + 2 * width:end], "little")
    if base + eof > size:
        raise VolregIOError(f"Transform `{p}` is truncated or not a valid HDF5 file: {size} bytes where its header "
                            f"says {base + eof}; expected the complete file, as register writes warp.h5.")


@contextlib.contextmanager
def _c_stderr_silenced():
    """Descriptor 2 sent to the null device while C code (HDF5 through ITK) reads a file: HDF5 prints
    its diagnostic stack there, not through Python, on any file it cannot read, and the reader's
    one-line error says what matters."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no descriptor 2 to save: nothing to silence
        yield
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(null)


def read_itk_composite(path: str | os.PathLike[str]) -> tuple[np.ndarray, Grid]:
    """Read the displacement field of an ITK HDF5 transform file holding one, as
    :func:`write_itk_composite` writes it (``warp.h5``, ``inverse_warp.h5``).

    Returns
    -------
    displacement : (*shape, D) float64 ndarray, LPS mm
    grid : Grid
        The field's grid.

    Raises
    ------
    VolregIOError
        One line naming the file: missing, unreadable, or holding anything but one displacement
        field (ANTs' composite files of an affine map and a warp: apply those with ANTs, or pass
        the NIfTI field).
    """
    p = Path(path)
    if not p.exists():
        raise VolregIOError(f"Transform `{p}` does not exist.")
    if not p.is_file():
        raise VolregIOError(f"Transform `{p}` is not a regular file.")
    check_readable(p, "Transform")
    try:
        with open(p, "rb") as fh:
            signature = fh.read(8)
    except OSError as exc:
        raise VolregIOError(f"Transform `{p}` cannot be read: {exc.strerror}.") from None
    if signature != b"\x89HDF\r\n\x1a\n":  # HDF5 would print its error stack on anything else
        raise VolregIOError(f"Transform `{p}` is not an HDF5 file; expected an ITK HDF5 transform (.h5), as "
                            "register writes warp.h5.")
    _check_hdf5_length(p)
    try:
        with _c_stderr_silenced():
            transform = sitk.ReadTransform(str(p))
    except RuntimeError as exc:
        raise VolregIOError(f"Transform `{p}` could not be read as an ITK HDF5 transform: {_sitk_reason(exc)}.") from None
    parts = [transform]
    if type(transform).__name__ == "CompositeTransform":
        parts = [transform.GetNthTransform(i).Downcast() for i in range(transform.GetNumberOfTransforms())]
    if len(parts) != 1 or type(parts[0]).__name__ != "DisplacementFieldTransform":
        kinds = ", ".join(t.GetName() for t in parts) or "no transform"
        raise VolregIOError(f"Transform `{p}` holds {kinds}; expected one displacement field, as volreg writes "
                            "warp.h5 (pass the NIfTI field, warp.nii.gz, or apply this file with antsApplyTransforms).")
    u, grid = _field_of_image(parts[0].GetDisplacementField())
    if not np.all(np.isfinite(u)):
        raise VolregIOError(f"Transform `{p}` holds NaN or Inf; expected finite displacements.")
    return u, grid


def _field_of_image(img: sitk.Image) -> tuple[np.ndarray, Grid]:
    """A SimpleITK vector image of D components on a D-D grid as ``(u, grid)``: ``u`` (i, j[, k], D)
    float64, C order, owning its memory (the image's (k, j, i, D) array in one more copy)."""
    dim = img.GetDimension()
    array = sitk.GetArrayFromImage(img)  # (k, j, i, D), a copy
    u = np.array(array.transpose(*range(dim - 1, -1, -1), dim), dtype=np.float64, order="C")
    grid = Grid(u.shape[:-1], np.array(img.GetOrigin()), np.array(img.GetSpacing()),
                np.array(img.GetDirection()).reshape(dim, dim))
    return u, grid


def stored_axis_order(shape: tuple[int, ...]) -> tuple[int, ...]:
    """The order in which :func:`write_displacement` stores a grid's axes: as they are, unless the
    last has one voxel (and some other more): then the single-voxel axes first, the others after,
    each group in its order, so that ITK reads the field with all of its axes.

    Parameters
    ----------
    shape : tuple of D ints

    Returns
    -------
    tuple of D ints
        Stored axis ``t`` is the grid's axis ``order[t]``.
    """
    d = len(shape)
    if shape[-1] != 1 or max(shape) == 1:
        return tuple(range(d))
    return tuple([a for a in range(d) if shape[a] == 1] + [a for a in range(d) if shape[a] > 1])


def axis_order_of(grid: Grid, reference: Grid | LabelVolume, atol: float = 1e-6) -> tuple[int, ...] | None:
    """The order of ``grid``'s axes that gives ``reference``'s grid, if one does.

    A field read from a file is on the grid it was stored on; :func:`write_displacement` stores a
    grid whose last axis has one voxel with its axes reordered (:func:`stored_axis_order`): the
    same voxels.  ``np.transpose(u, order + (D,))`` gives the field in ``reference``'s order.

    Parameters
    ----------
    grid : Grid
        A field's grid, as :func:`read_displacement` returns it.
    reference : Grid or LabelVolume
    atol : float
        Tolerance of :meth:`Grid.same_geometry`, mm.

    Returns
    -------
    tuple of D ints, or None
        The identity where the grids are the same as they are; None where no order matches.
    """
    from itertools import permutations

    if grid.ndim != reference.ndim:
        return None
    for order in permutations(range(grid.ndim)):
        axes = list(order)
        candidate = Grid(tuple(grid.shape[a] for a in axes), grid.origin, np.asarray(grid.spacing)[axes],
                         np.asarray(grid.direction)[:, axes])
        if candidate.same_geometry(reference, atol=atol):
            return tuple(order)
    return None


def read_displacement(path: str | os.PathLike[str]) -> tuple[np.ndarray, Grid]:
    """Read an ANTs/ITK displacement field.

    Returns
    -------
    displacement : (*shape, D) float64 ndarray, LPS mm
        A new C-order array that owns its memory.
    grid : Grid
        The field's grid: shape, origin, spacing, direction.

    Raises
    ------
    VolregIOError
        If the file is unreadable or not a vector image with D components on a D-D grid.
    """
    p = Path(path)
    suffix = _check_input(p, "Displacement field")
    nimg = None
    if suffix in (".nii", ".nii.gz"):
        # SimpleITK zero-fills a truncated file: a warp that silently becomes the identity there.
        nimg = _check_nifti(p, suffix, "Displacement field")
    elif suffix in (".mha", ".mhd", ".nrrd", ".nhdr"):
        _check_header_fields(p, suffix, "Displacement field")  # NaN or missing geometry values
        check_image_data_files(p, suffix, "Displacement field")  # data elsewhere, missing or short
    try:
        with _itk_quiet():
            img = sitk.ReadImage(str(p))
    except RuntimeError as exc:
        raise VolregIOError(f"Displacement field `{p}` could not be read: {_sitk_reason(exc)}.") from exc
    dim = img.GetDimension()
    if img.GetNumberOfComponentsPerPixel() != dim or dim not in (2, 3):
        raise VolregIOError(
            f"Displacement field `{p}` has {img.GetNumberOfComponentsPerPixel()} components on a {dim}-D grid; "
            "expected a 2-D or 3-D vector image with one component per axis (ANTs/ITK warp)."
        )
    u, grid = _field_of_image(img)
    if nimg is not None:
        # SimpleITK reads NaN and Inf in float NIfTI data as 0 (zero displacement there, silently):
        # the voxels as nibabel reads them, in the same (i, j, k, D) order once the NIfTI's
        # singleton time axis is dropped.
        u = _nifti_float_voxels(nimg, u, p, "Displacement field")
    if not np.all(np.isfinite(u)):
        raise VolregIOError(f"Displacement field `{p}` holds NaN or Inf; expected finite displacements in mm.")
    return u, grid


#: First line of ITK's text transform files.
_ITK_HEADER = "#Insight Transform File V1.0"
#: Suffixes ITK's transform reader takes as its text format.
_ITK_TEXT_SUFFIXES = (".tfm", ".txt")
#: Transforms whose parameters are the matrix row by row, then the translation; fixed: the centre.
_MATRIX_OFFSET = re.compile(r"^(AffineTransform|MatrixOffsetTransformBase)_(double|float)_(\d+)_(\d+)$")
#: SimpleITK transform classes that are ``x -> A (x - c) + t + c`` (GetMatrix, GetTranslation, GetCenter).
_SITK_LINEAR = (
    "AffineTransform",
    "Euler2DTransform",
    "Euler3DTransform",
    "Similarity2DTransform",
    "Similarity3DTransform",
    "VersorTransform",
    "VersorRigid3DTransform",
    "ScaleVersor3DTransform",
    "ScaleSkewVersor3DTransform",
    "ComposeScaleSkewVersor3DTransform",
)


def _number(value: float) -> str:
    """A float as the shortest text that reads back as the same double."""
    text = repr(float(value))
    return "0" if text in ("0.0", "-0.0") else text


def write_itk_linear(path: str | os.PathLike[str], linear: LinearMap, *, force: bool = False) -> None:
    """Write a linear map as an ITK text transform file ("Insight Transform File V1.0"), atomically.

    Parameters
    ----------
    path : path-like
        ``.tfm`` (or ``.txt``): the suffixes ITK reads as text transforms.
    linear : LinearMap
        ``x -> A x + b``, D = 2 or 3, mapping fixed points to moving points (LPS mm),
        as ITK's transforms do.  Written as ``AffineTransform_double_D_D`` with
        ``Parameters`` = ``A`` row-major then ``b`` (mm) and ``FixedParameters`` =
        the centre, zero; numbers are written to full double precision.
    force : bool
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        On another suffix, or an existing ``path`` without ``force``.
    ValueError
        If ``linear`` is not a :class:`~volreg.linear_map.LinearMap`.
    """
    p = Path(path)
    if not p.name.lower().endswith(_ITK_TEXT_SUFFIXES):
        raise VolregIOError(f"Linear transform `{p}` must be named .tfm or .txt, the suffixes ITK reads as text transforms.")
    if not isinstance(linear, LinearMap):
        raise ValueError(f"Expected a LinearMap as `linear`, got {type(linear).__name__}.")
    d = linear.dim
    params = [*np.asarray(linear.matrix, float).ravel(), *np.asarray(linear.translation, float)]
    text = (
        f"{_ITK_HEADER}\n"
        "#Transform 0\n"
        f"Transform: AffineTransform_double_{d}_{d}\n"
        f"Parameters: {' '.join(_number(v) for v in params)}\n"
        f"FixedParameters: {' '.join('0' for _ in range(d))}\n"
    )
    with atomic_output(p, force=force) as tmp:
        with open(tmp, "w", encoding="ascii", newline="\n") as fh:
            fh.write(text)


def _linear_map(path: Path, kind: str, matrix, translation, centre, dim: int | None) -> LinearMap:
    """``x -> A (x - c) + t + c`` as a LinearMap, checked; errors name the file."""
    a = np.asarray(matrix, dtype=float)
    d = a.shape[0]
    if dim is not None and d != dim:
        raise VolregIOError(f"Linear transform `{path}` is {d}-D ({kind}); expected a {dim}-D transform.")
    t = np.asarray(translation, dtype=float)
    c = np.asarray(centre, dtype=float)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(t)) and np.all(np.isfinite(c))):
        raise VolregIOError(f"Linear transform `{path}` holds NaN or Inf; expected finite parameters.")
    det = float(np.linalg.det(a))
    if not det > 0:
        raise VolregIOError(
            f"Linear transform `{path}` has a matrix of determinant {det:.3g}; expected a positive determinant "
            "(no reflection, no collapse)."
        )
    return LinearMap(a, t + c - a @ c)


def _parse_itk_text(path: Path, text: str, dim: int | None) -> LinearMap | None:
    """The linear map of an ITK text file whose one transform is an affine / matrix-offset one.

    ``None`` when the file holds one transform of another kind (left to SimpleITK).
    """
    kinds, fields = [], []
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("Transform:"):
            kinds.append(line.partition(":")[2].strip())
            fields.append({})
        elif fields and line.startswith(("Parameters:", "FixedParameters:")):
            key, _, values = line.partition(":")
            fields[-1][key] = values.split()
    if not kinds:
        raise VolregIOError(f"Linear transform `{path}` names no transform; expected an ITK transform file.")
    if kinds[0].startswith("CompositeTransform"):  # a composite of one transform is that transform
        kinds, fields = kinds[1:], fields[1:]
    if len(kinds) != 1:
        raise VolregIOError(
            f"Linear transform `{path}` holds {len(kinds)} transforms; expected a single linear transform."
        )
    kind = kinds[0]
    match = _MATRIX_OFFSET.match(kind)
    if match is None:
        return None
    d, d2 = int(match.group(3)), int(match.group(4))
    if d != d2 or d not in (2, 3):
        raise VolregIOError(f"Linear transform `{path}` is a {excerpt(kind, quote=False)}; expected a 2-D or 3-D transform "
                             "(_2_2 or _3_3).")
    try:
        params = np.array([float(v) for v in fields[0].get("Parameters", [])])
        fixed = np.array([float(v) for v in fields[0].get("FixedParameters", [])])
    except ValueError:
        raise VolregIOError(f"Linear transform `{path}` has parameters that are not numbers.") from None
    if params.size != d * d + d or fixed.size != d:
        raise VolregIOError(
            f"Linear transform `{path}` ({kind}) has {params.size} parameters and {fixed.size} fixed parameters; "
            f"expected {d * d + d} and {d}."
        )
    return _linear_map(path, kind, params[: d * d].reshape(d, d), params[d * d :], fixed, dim)


def read_itk_linear(path: str | os.PathLike[str], *, dim: int | None = None) -> LinearMap:
    """Read a linear transform from an ITK transform file as ``x -> A x + b``.

    Reads ITK's text format (``AffineTransform_*`` and
    ``MatrixOffsetTransformBase_*``, double or float, with any centre ``c``: the
    map is ``A (x - c) + t + c``, so ``b = t + c - A c``) and, through SimpleITK,
    the other linear kinds it reads and writes (Euler, Similarity, Versor,
    VersorRigid3D, ScaleVersor3D, ScaleSkewVersor3D) in text or MATLAB ``.mat``
    files (as ANTs writes them).  The transform maps fixed points to moving points
    in LPS mm, as volreg's ``tau``.

    Parameters
    ----------
    path : path-like
    dim : {2, 3}, optional
        The dimension the transform must have.

    Returns
    -------
    LinearMap

    Raises
    ------
    VolregIOError
        One line naming the file: missing or unreadable, not a transform file, a
        composite or non-linear transform (displacement field, B-spline), another
        dimension than ``dim``, non-finite parameters, or a matrix whose
        determinant is not positive (a reflection).
    """
    p = Path(path)
    if not p.exists():
        raise VolregIOError(f"Linear transform `{p}` does not exist.")
    if p.is_dir():
        raise VolregIOError(f"Linear transform `{p}` is a directory; expected an ITK transform file (.tfm, .txt, .mat).")
    try:
        with open(p, "rb") as fh:
            head = fh.read(len(_ITK_HEADER) + 64)
    except OSError as exc:
        raise VolregIOError(f"Linear transform `{p}` cannot be read: {exc.strerror}.") from None
    if head.lstrip().startswith(_ITK_HEADER.encode()):
        try:
            text = p.read_text(encoding="ascii")
        except (OSError, UnicodeDecodeError) as exc:
            raise VolregIOError(f"Linear transform `{p}` is not a readable text transform file: {exception_text(exc)}.") from None
        linear = _parse_itk_text(p, text, dim)
        if linear is not None:
            return linear
    try:
        transform = sitk.ReadTransform(str(p))
    except RuntimeError as exc:
        raise VolregIOError(f"Linear transform `{p}` could not be read as an ITK transform: {_sitk_reason(exc)}.") from None
    if type(transform).__name__ == "CompositeTransform" and transform.GetNumberOfTransforms() == 1:
        transform = transform.GetNthTransform(0).Downcast()
    kind = type(transform).__name__
    if kind == "TranslationTransform":
        offset = np.array(transform.GetOffset(), dtype=float)
        return _linear_map(p, kind, np.eye(len(offset)), offset, np.zeros(len(offset)), dim)
    if kind not in _SITK_LINEAR:
        raise VolregIOError(
            f"Linear transform `{p}` holds a {transform.GetName()}; expected one linear transform "
            "(affine, rigid or similarity)."
        )
    d = transform.GetDimension()
    return _linear_map(p, kind, np.array(transform.GetMatrix(), dtype=float).reshape(d, d),
                       transform.GetTranslation(), transform.GetCenter(), dim)
