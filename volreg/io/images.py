"""Label volumes and scalar images: NIfTI, NRRD and MetaImage via SimpleITK; VTK ``.vti``.

Arrays are returned in ITK index order ``[i, j, k]`` (SimpleITK's
``GetArrayFromImage`` gives ``[k, j, i]``; we transpose), and geometry is
SimpleITK's: origin, spacing and direction in ITK physical space (LPS, mm).
For NIfTI files, whose affines are RAS, this means ``LPS = diag(-1, -1, 1) @ RAS``
(SimpleITK does the conversion).  VTK image data (``.vti``, read-only) have no
anatomical frame; their world coordinates are taken as LPS unchanged, as ITK's
VTK image IO does (see :mod:`volreg.io.vti`).

Readers validate aggressively, because a silently wrong label volume is worse
than a refusal: every problem raises :class:`VolregIOError` with one line
naming the file and what was expected.  The arrays they return are new and
own their memory (never views into a SimpleITK image, a VTK array or a
memory-mapped file).  :func:`read_grid` reads only the geometry (a
:class:`~volreg.grid.Grid`) from the header.  The checks on header fields
are in :mod:`volreg.io.header_checks`.
"""

from __future__ import annotations

import contextlib
import os
import re
import warnings
from pathlib import Path

import nibabel as nib
import numpy as np
import SimpleITK as sitk

from volreg.errors import GeometryError, VolregIOError, VolregWarning, exception_text
from volreg.grid import Grid, LabelVolume, as_grid
from volreg.io._atomic import atomic_output
from volreg.io._guards import check_image_data_files, check_readable, check_vti_size, declared_vti
from volreg.io.header_checks import ORIGIN_LIMIT_MM, SPACING_RANGE_MM  # noqa: F401 - the readers' limits
from volreg.io.header_checks import (_check_header_fields, _check_nifti, _check_nifti_geometry, _check_nifti_shape,
                                     _check_size, _first_line, _implausible_origin, _implausible_spacing,
                                     _nibabel_quiet)

__all__ = ["read_labels", "write_labels", "write_scalar", "read_image", "read_grid", "image_header"]

#: Suffixes the readers accept (lower case).
READ_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd", ".vti")
#: Suffixes the writers accept: single-file formats only, so a write can be atomic.
WRITE_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".mha")

# Tolerance for the direction block of a squeezed 4-D image (unitless).
_DIR_TOL = 1e-6


def _suffix(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".nii.gz"):
        return ".nii.gz"
    return path.suffix.lower()


def _check_input(path: Path, what: str) -> str:
    """Check that ``path`` is an existing file with a supported suffix; return the suffix."""
    if not path.exists():
        raise VolregIOError(f"{what} `{path}` does not exist.")
    if not path.is_file():
        raise VolregIOError(f"{what} `{path}` is not a regular file.")
    suffix = _suffix(path)
    if suffix not in READ_SUFFIXES:
        raise VolregIOError(
            f"{what} `{path}` has unsupported suffix {suffix!r}; expected one of {', '.join(READ_SUFFIXES)}."
        )
    check_readable(path, what)
    return suffix


def _sitk_reason(exc: BaseException) -> str:
    """Condense SimpleITK's multi-line exception text to its most specific line."""
    lines = str(exc).splitlines()[1:]  # the first line is "Exception thrown in ...: file.cxx:NN:"
    prefix = re.compile(r"^\s*(sitk::ERROR:|ITK ERROR:( \w+\(0x[0-9a-fA-F]+\):)?|\[\w+\] \w+:)\s*")
    candidates = []
    flagged = []  # lines that carry an "ITK ERROR:" / "sitk::ERROR:" prefix: the message proper
    for line in lines:
        is_error = bool(prefix.match(line))
        line = prefix.sub("", line).strip()
        # MetaIO appends the C errno ("Reason: No such file or directory"), which is misleading.
        if not line or line.startswith("Reason:") or line.rstrip(":") in {"trouble", ""}:
            continue
        candidates.append(line)
        if is_error:
            flagged.append(line)
    if not candidates:
        return _first_line(exc)
    reason = flagged[-1] if flagged else candidates[-1]
    if "Unable to determine ImageIO reader" in reason:
        return "unrecognised file format"
    if "orthonormal direction cosines" in reason:
        return "its axes are not orthogonal (a sheared affine; ITK supports only orthonormal directions)"
    if "Bad direction, determinant is 0" in reason:
        return "its direction matrix is singular (determinant 0); expected independent axis directions"
    return exception_text(reason).rstrip(".")  # what ITK quotes of the file, cut short


@contextlib.contextmanager
def _itk_quiet():
    """ITK prints warnings of its own to stderr (e.g. "unexpected scales in sform", once per header
    read); the checks here report what matters in one line, so they are silenced while reading."""
    previous = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        yield
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(previous)


def _nifti_float_voxels(nimg: nib.Nifti1Image, array: np.ndarray, path: Path, what: str) -> np.ndarray:
    """Float voxels of a NIfTI file as nibabel reads them, in ``array``'s shape and dtype (a new array).

    SimpleITK (niftilib) silently replaces NaN and Inf voxels by 0 in float
    NIfTI files, so float data are taken from nibabel instead (same
    ``[i, j, k]`` order, same shape once trailing size-1 axes are dropped).
    Other data are returned unchanged.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if np.dtype(nimg.header.get_data_dtype()).kind != "f":
            return array
        try:
            data = np.asarray(nimg.dataobj)
        except Exception as exc:  # already checked for truncation; be safe anyway
            raise VolregIOError(f"{what} `{path}` could not be read: {_first_line(exc)}.") from exc
        # A copy in C order: nibabel may hand out a memory map of the file.
        return np.array(data.reshape(array.shape), dtype=array.dtype, order="C")


def _pixel_dtype(reader: sitk.ImageFileReader) -> np.dtype:
    """The numpy dtype of one component of the pixels of the file ``reader`` has read the header of."""
    probe = sitk.Image([1] * reader.GetDimension(), reader.GetPixelID())
    return sitk.GetArrayFromImage(probe).dtype


def _spatial_geometry(
    source: sitk.Image | sitk.ImageFileReader, ncomp: int, pixel_type: str, dtype: np.dtype, path: Path, what: str
) -> tuple[tuple[int, ...], np.ndarray, np.ndarray, np.ndarray]:
    """Check that an image (or a header) is scalar, real and 2-D/3-D; return its spatial geometry.

    Returns
    -------
    shape : tuple of D ints
        Grid size in ITK index order (trailing axes of size 1 dropped).
    origin : (D,) float ndarray, mm
    spacing : (D,) float ndarray, mm
    direction : (D, D) float ndarray
    """
    if ncomp != 1:
        raise VolregIOError(
            f"{what} `{path}` has {ncomp} components per voxel ({pixel_type}); expected a scalar image."
        )
    dim = source.GetDimension()
    size = tuple(source.GetSize())
    if dim < 2 or (dim > 3 and any(n != 1 for n in size[3:])):
        raise VolregIOError(
            f"{what} `{path}` is {dim}-D with size {size}; expected a 2-D or 3-D image "
            "(extra axes of size 1 are allowed)."
        )
    if np.dtype(dtype).kind == "c":
        raise VolregIOError(f"{what} `{path}` has complex voxels ({dtype}); expected a real scalar image.")
    origin = np.asarray(source.GetOrigin(), dtype=float)
    spacing = np.asarray(source.GetSpacing(), dtype=float)
    direction = np.asarray(source.GetDirection(), dtype=float).reshape(dim, dim)
    if dim > 3:
        off_block = np.concatenate([direction[:3, 3:].ravel(), direction[3:, :3].ravel()])
        if np.any(np.abs(off_block) > _DIR_TOL):
            raise VolregIOError(
                f"{what} `{path}` is {dim}-D with a direction matrix that mixes its extra axes with space; "
                "expected a spatial 3-D block."
            )
        origin, spacing, direction = origin[:3], spacing[:3], direction[:3, :3]
    return size[:3], origin, spacing, direction


def _single_slice_as_2d(shape: tuple[int, ...], origin: np.ndarray, spacing: np.ndarray, direction: np.ndarray,
                        path: Path, what: str) -> tuple[tuple[int, ...], np.ndarray, np.ndarray, np.ndarray] | None:
    """The 2-D geometry of a 3-D grid of one slice (``(n_i, n_j, 1)``), or None.

    A slice stored as 3-D is a 2-D image: registered in 3-D its labels have no
    thickness to fit, and ITK reads a displacement field of shape ``(n_i, n_j, 1)``
    back as 2-D.  It is read as 2-D when its direction keeps the third axis apart
    from the first two (the slice lies in a plane of constant LPS ``z``); its
    position along ``z`` is then dropped, with a warning when it is not 0.
    """
    if len(shape) != 3 or shape[2] != 1 or (shape[0] == 1 and shape[1] == 1):
        return None
    if np.any(np.abs(direction[:2, 2]) > _DIR_TOL) or np.any(np.abs(direction[2, :2]) > _DIR_TOL):
        return None  # an oblique slice: no 2-D frame in LPS space
    if origin[2] != 0:
        warnings.warn(
            f"{what} `{path}` is a single slice ({shape[0]}x{shape[1]}x1) and is read as 2-D; its position "
            f"z = {origin[2]:g} mm is not kept in 2-D outputs.", VolregWarning, stacklevel=4,
        )
    return shape[:2], origin[:2].copy(), spacing[:2].copy(), direction[:2, :2].copy()


def _header_reader(p: Path, suffix: str, what: str, *, voxels: bool) -> tuple[sitk.ImageFileReader,
                                                                              nib.Nifti1Image | None, np.dtype]:
    """Check a NIfTI, NRRD or MetaImage file and read its header with SimpleITK, no voxels.

    Returns SimpleITK's reader (its image information read), the lazily loaded nibabel image of
    a NIfTI file (None for others) and the dtype of one component of a voxel.  Every check that
    needs only the header is made, the declared size against :func:`max_image_bytes` among them;
    with ``voxels`` a NIfTI file's data are checked for truncation too (which decompresses them).
    """
    nimg = _check_nifti(p, suffix, what, voxels=voxels) if suffix in (".nii", ".nii.gz") else None
    if suffix in (".mha", ".mhd", ".nrrd", ".nhdr"):
        _check_header_fields(p, suffix, what)
        check_image_data_files(p, suffix, what)
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(p))
    try:
        with _itk_quiet():
            reader.ReadImageInformation()
            pixel = _pixel_dtype(reader)
            _check_size(p, reader.GetSize(), pixel.itemsize * reader.GetNumberOfComponents(), what)
            # Before the voxels are read; the spatial axes only (a 4-D image's fourth is time).
            _implausible_spacing(p, what, "", reader.GetSpacing()[:3], reader.GetSize()[:3])
            _implausible_origin(p, what, "an origin of", reader.GetOrigin()[:3])
    except RuntimeError as exc:
        raise VolregIOError(f"{what} `{p}` could not be read as an image: {_sitk_reason(exc)}.") from exc
    return reader, nimg, pixel


def image_header(path: str | os.PathLike[str], what: str = "Image") -> tuple[tuple[int, ...], int, int]:
    """What an image file declares it holds, from its header alone: no voxel is read or decompressed.

    Parameters
    ----------
    path : path-like
        As for :func:`read_image` (a scalar or a vector image).
    what : str
        What the file is, for messages (``"Label image"``).

    Returns
    -------
    size : tuple of ints
        Voxels along every axis, in ITK index order (extra axes of size 1 included).
    components : int
        Values per voxel (1 for a scalar image, D for a displacement field).
    itemsize : int
        Bytes of one value as the file stores it, and as the readers hold it.

    Raises
    ------
    VolregIOError
        As the readers do, for everything the header shows (a missing or unrecognised file, a data
        file outside the header's folder, a declared size beyond :func:`max_image_bytes`, ...).
    """
    p = Path(path)
    suffix = _check_input(p, what)
    if suffix == ".vti":
        check_vti_size(p, what)
        return declared_vti(p)
    with warnings.catch_warnings():
        # a header read ahead of the voxels: the reader that reads them gives its warnings once
        warnings.simplefilter("ignore", VolregWarning)
        reader, _, pixel = _header_reader(p, suffix, what, voxels=False)
    return tuple(int(n) for n in reader.GetSize()), int(reader.GetNumberOfComponents()), int(pixel.itemsize)


def _read_sitk(
    path: str | os.PathLike[str], what: str, *, voxels: bool = True
) -> tuple[np.ndarray | tuple[int, ...], np.ndarray, np.ndarray, np.ndarray]:
    """Read and validate a scalar 2-D/3-D image; return ``(array[i,j,k], origin, spacing, direction)``.

    ``.vti`` files go to :func:`volreg.io.vti.read_vti`; everything else to
    SimpleITK.  The array owns its memory (it is never a view into a
    SimpleITK image or a memory-mapped file).  With ``voxels=False`` only the
    header is read and validated, and the first item is the grid's shape
    ``(n_i, n_j[, n_k])`` instead of an array (a ``.vti`` file is read whole).
    """
    p = Path(path)
    suffix = _check_input(p, what)
    if suffix == ".vti":
        from volreg.io.vti import read_vti  # pyvista and VTK, imported only for .vti files

        check_vti_size(p, what)
        array, origin, spacing, direction = read_vti(p, what)
        _implausible_spacing(p, what, "", spacing, array.shape)
        _implausible_origin(p, what, "an origin of", origin)
        return (array if voxels else array.shape), origin, spacing, direction
    reader, nimg, pixel = _header_reader(p, suffix, what, voxels=voxels)
    try:
        with _itk_quiet():
            img = reader.Execute() if voxels else None
    except RuntimeError as exc:
        raise VolregIOError(f"{what} `{p}` could not be read as an image: {_sitk_reason(exc)}.") from exc

    if not voxels:
        shape, origin, spacing, direction = _spatial_geometry(
            reader, reader.GetNumberOfComponents(), sitk.GetPixelIDValueAsString(reader.GetPixelID()), pixel, p, what
        )
        if nimg is not None:
            _check_nifti_shape(nimg, shape, p, what)
            _check_nifti_geometry(nimg, origin, spacing, direction, p, what)
        flat = _single_slice_as_2d(shape, origin, spacing, direction, p, what)
        return (shape, origin, spacing, direction) if flat is None else flat

    view = sitk.GetArrayViewFromImage(img)  # (..., k, j, i): valid only while `img` lives
    shape, origin, spacing, direction = _spatial_geometry(
        img, img.GetNumberOfComponentsPerPixel(), img.GetPixelIDTypeAsString(), view.dtype, p, what
    )
    # One copy, in C order, that owns its memory: ``np.ascontiguousarray`` would return the
    # view itself when at most one axis is longer than 1, and the view dies with `img`.
    array = np.array(view.reshape(shape[::-1]).T, order="C")
    del view, img
    if nimg is not None:
        _check_nifti_shape(nimg, shape, p, what)
        array = _nifti_float_voxels(nimg, array, p, what)
        _check_nifti_geometry(nimg, origin, spacing, direction, p, what)
    flat = _single_slice_as_2d(array.shape, origin, spacing, direction, p, what)
    if flat is not None:
        shape, origin, spacing, direction = flat
        array = array[:, :, 0].copy(order="C")  # a new array that owns its memory
    return array, origin, spacing, direction


def _nifti_scaling(path: Path) -> tuple[str, float, float] | None:
    """How a NIfTI file scales its stored values: (stored dtype, ``scl_slope``, ``scl_inter``) where
    those are not 1 and 0; ``None`` for other files or none."""
    if _suffix(path) not in (".nii", ".nii.gz"):
        return None
    try:
        with warnings.catch_warnings(), _nibabel_quiet():
            warnings.simplefilter("ignore")
            img = nib.load(str(path))  # the loaded header's own fields are reset: the proxy holds them
        header = img.header
        slope, inter = float(getattr(img.dataobj, "slope", np.nan)), float(getattr(img.dataobj, "inter", np.nan))
    except Exception:  # the scaling is a hint only
        return None
    if (np.isnan(slope) or slope in (0.0, 1.0)) and (np.isnan(inter) or inter == 0.0):
        return None
    return str(header.get_data_dtype()), slope, 0.0 if np.isnan(inter) else inter


def _as_integer_labels(array: np.ndarray, path: Path, what: str) -> np.ndarray:
    """Cast a float array holding whole numbers to the smallest integer dtype holding them."""
    finite = np.isfinite(array)
    if not finite.all():
        n_nan = int(np.isnan(array).sum())
        n_inf = int(array.size - finite.sum()) - n_nan
        raise VolregIOError(
            f"{what} `{path}` has {array.dtype} voxels with {n_nan} NaN and {n_inf} Inf values; "
            "expected integer labels."
        )
    nonint = array != np.round(array)
    if nonint.any():
        example = float(array[nonint].flat[0])
        raise VolregIOError(
            f"{what} `{path}` has {array.dtype} voxels with {int(nonint.sum())} non-integral values "
            f"(e.g. {example!r}); expected integer labels."
        )
    lo, hi = int(array.min()), int(array.max())
    dtype = np.promote_types(np.min_scalar_type(lo), np.min_scalar_type(hi))
    if dtype.kind not in "iu":
        raise VolregIOError(
            f"{what} `{path}` has label values in [{lo}, {hi}], beyond any integer dtype; expected integer labels."
        )
    return array.astype(dtype)


def read_labels(path: str | os.PathLike[str]) -> LabelVolume:
    """Read a label volume from NIfTI, NRRD, MetaImage or VTK image data.

    Parameters
    ----------
    path : path-like
        ``.nii``, ``.nii.gz``, ``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd`` or
        ``.vti`` file holding a 2-D or 3-D scalar image.  For ``.vti`` the
        active (or only) point array is read, and VTK world coordinates
        (origin, spacing, ``direction_matrix``) are taken as LPS mm unchanged,
        as ITK's VTK image IO does; a single-slice ``.vti`` is read as 2-D.

    Returns
    -------
    LabelVolume
        ``array`` is ``(n_i, n_j[, n_k])`` in ITK index order, with the
        on-disk integer dtype kept exactly; origin and spacing in mm and the
        direction matrix in ITK physical space (LPS).

    Raises
    ------
    VolregIOError
        If the file is missing, not an image, truncated (including a
        truncated ``.nii.gz``, which SimpleITK would read as zero-filled;
        a ``.vti`` that fails to parse),
        4-D or more (a trailing axis of size 1 is squeezed), vector-valued,
        a float image with NaN, Inf or non-integral values, or a NIfTI whose
        qform and sform are both set and disagree by more than 1e-3 mm.

    Notes
    -----
    A float image whose values are all whole numbers is accepted and cast
    to the smallest integer dtype that holds its range (e.g. ``uint8`` for
    labels 0..255).
    """
    what = "Label image"
    p = Path(path)
    array, origin, spacing, direction = _read_sitk(p, what)
    if array.dtype.kind == "f":
        try:
            array = _as_integer_labels(array, p, what)
        except VolregIOError:
            scaling = _nifti_scaling(p)
            finite = array[np.isfinite(array)]
            odd = finite[finite != np.round(finite)]
            if scaling is None or not odd.size:
                raise
            stored, slope, inter = scaling
            raise VolregIOError(f"{what} `{p}` stores {stored} voxels that its header scales by scl_slope {slope:g} "
                                f"and scl_inter {inter:g} into non-integral values (e.g. {float(odd[0]):g}); expected "
                                "integer labels, stored unscaled (scl_slope 1, scl_inter 0).") from None
    elif array.dtype.kind not in "iub":
        raise VolregIOError(f"{what} `{p}` has {array.dtype} voxels; expected integer labels.")
    try:
        return LabelVolume(array, origin, spacing, direction)
    except GeometryError as exc:
        raise VolregIOError(f"{what} `{p}` has invalid geometry: {exc}") from exc


def read_image(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read a scalar (e.g. intensity) image as floats.

    Parameters
    ----------
    path : path-like
        As for :func:`read_labels`.

    Returns
    -------
    array : (n_i, n_j[, n_k]) float ndarray
        Voxel values in ITK index order; ``float64`` for ``float64`` and 32-/64-bit
        integer files (to keep them exact), ``float32`` otherwise.  NaN and Inf
        are passed through.
    origin : (D,) float ndarray, mm
    spacing : (D,) float ndarray, mm
    direction : (D, D) float ndarray
        Columns are the LPS directions of the index axes.

    Raises
    ------
    VolregIOError
        As for :func:`read_labels`, except that float values are not checked.
    """
    array, origin, spacing, direction = _read_sitk(path, "Image")
    wide = array.dtype == np.float64 or (array.dtype.kind in "iu" and array.dtype.itemsize >= 4)
    array = array.astype(np.float64 if wide else np.float32, copy=False)
    return array, origin, spacing, direction


def read_grid(path: str | os.PathLike[str]) -> Grid:
    """Read the grid of an image (shape, origin, spacing, direction), not its voxels.

    Parameters
    ----------
    path : path-like
        As for :func:`read_image`.  Only the header is read where SimpleITK
        allows (NIfTI, NRRD, MetaImage); a ``.vti`` file is read whole.

    Returns
    -------
    Grid
        Shape ``(n_i, n_j[, n_k])`` in ITK index order; origin and spacing in
        mm, direction in ITK physical space (LPS); the same geometry as
        :func:`read_image` gives.

    Raises
    ------
    VolregIOError
        As for :func:`read_image`, for everything the header shows (missing
        or unrecognised file, vector or complex voxels, more than 3-D, an
        inconsistent NIfTI header, invalid geometry).  The voxel data are not
        read, so truncated or corrupt data are not detected.
    """
    p = Path(path)
    shape, origin, spacing, direction = _read_sitk(p, "Image", voxels=False)
    try:
        return Grid(shape, origin, spacing, direction)
    except GeometryError as exc:
        raise VolregIOError(f"Image `{p}` has invalid geometry: {exc}") from exc


#: Name endings before ``.nii`` / ``.nii.gz`` that ITK's NIfTI writer takes as the suffix: it writes
#: ``x.nii.gz`` for ``x.nii.gz.nii.gz`` and an Analyze pair for ``x.img.nii``, and leaves the named
#: file as it was.
_NIFTI_MANGLED_STEMS = (".nii", ".nii.gz", ".nia", ".nia.gz", ".hdr", ".img", ".hdr.gz", ".img.gz")


def _unmangled(stem: str) -> str:
    """``stem`` without the longest of :data:`_NIFTI_MANGLED_STEMS` it ends with."""
    for ending in sorted(_NIFTI_MANGLED_STEMS, key=len, reverse=True):
        if stem.lower().endswith(ending):
            return stem[: len(stem) - len(ending)]
    return stem


def _check_output_suffix(path: Path, what: str) -> str:
    suffix = _suffix(path)
    if suffix not in WRITE_SUFFIXES:
        raise VolregIOError(
            f"{what} `{path}` has unsupported suffix {suffix!r}; expected one of {', '.join(WRITE_SUFFIXES)} "
            "(detached-header .nhdr/.mhd are read-only)."
        )
    stem = path.name[: len(path.name) - len(suffix)]
    if suffix in (".nii", ".nii.gz") and stem.lower().endswith(_NIFTI_MANGLED_STEMS):
        raise VolregIOError(
            f"{what} `{path}` ends in two image suffixes; expected one, such as `{_unmangled(stem)}{suffix}` "
            "(ITK's NIfTI writer would write a file of another name)."
        )
    return suffix


def _remove_written_beside(tmp: Path) -> None:
    """Remove the files a writer made beside the temporary output ``tmp`` under names of its own
    (ITK's NIfTI writer drops an ending it takes for the suffix): those starting with ``tmp``'s
    unique prefix (``.tmp-<token>-``, :func:`~volreg.io._atomic.atomic_output`)."""
    parts = tmp.name.split("-", 2)
    if len(parts) < 3 or parts[0] != ".tmp":
        return
    prefix = f"{parts[0]}-{parts[1]}-"
    for other in tmp.parent.iterdir():
        if other.name.startswith(prefix) and other != tmp and other.is_file():
            other.unlink(missing_ok=True)


def _write_sitk(array: np.ndarray, like: Grid | LabelVolume, path: Path, suffix: str, force: bool, what: str) -> None:
    img = sitk.GetImageFromArray(np.ascontiguousarray(array.T), isVector=False)
    img.SetOrigin(tuple(float(v) for v in like.origin))
    img.SetSpacing(tuple(float(v) for v in like.spacing))
    img.SetDirection(tuple(float(v) for v in like.direction.ravel()))
    with atomic_output(path, force=force) as tmp:
        writer = sitk.ImageFileWriter()
        writer.SetFileName(str(tmp))
        writer.SetUseCompression(suffix != ".nii")
        try:
            writer.Execute(img)
        except RuntimeError as exc:
            raise VolregIOError(f"{what} `{path}` could not be written: {_sitk_reason(exc)}.") from exc
        if os.path.getsize(tmp) == 0:  # the writer wrote another file than the one named
            _remove_written_beside(Path(tmp))
            raise VolregIOError(f"{what} `{path}` could not be written: the image writer left it empty.")


def write_labels(volume: LabelVolume, path: str | os.PathLike[str], *, force: bool = False) -> None:
    """Write a label volume with its geometry and dtype, atomically.

    Parameters
    ----------
    volume : LabelVolume
        Labels in ITK index order with LPS geometry (mm).  A boolean array is
        written as ``uint8``; every other integer dtype is kept.
    path : path-like
        ``.nii``, ``.nii.gz``, ``.nrrd`` or ``.mha``.  NRRD, MetaImage and
        ``.nii.gz`` are compressed.  NIfTI files get identical qform and sform
        (code 1, scanner), both the RAS form of the LPS geometry.
    force : bool, default False
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        If ``path`` exists and ``force`` is false, has an unsupported suffix,
        or the write fails; nothing is left behind on failure.
    """
    if not isinstance(volume, LabelVolume):
        raise VolregIOError(f"Expected `volume` to be a LabelVolume, got {type(volume).__name__}.")
    p = Path(path)
    suffix = _check_output_suffix(p, "Label image")
    array = volume.array
    if array.dtype == np.bool_:
        array = array.astype(np.uint8)
    _write_sitk(array, volume, p, suffix, force, "Label image")


def write_scalar(
    array: np.ndarray, like: Grid | LabelVolume, path: str | os.PathLike[str], *, force: bool = False
) -> None:
    """Write a float32 scalar image on a grid (or the grid of a label volume), atomically.

    Parameters
    ----------
    array : (n_i, n_j[, n_k]) real ndarray
        Values in ITK index order; cast to ``float32``.  Shape must equal
        ``like.shape``.
    like : Grid or LabelVolume
        Supplies origin, spacing and direction (LPS, mm); a volume's array is not used.
    path : path-like
        ``.nii``, ``.nii.gz``, ``.nrrd`` or ``.mha``.
    force : bool, default False
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        On a shape mismatch, an unsupported suffix, an existing ``path``
        without ``force``, or a failed write.
    """
    if not isinstance(like, (Grid, LabelVolume)):
        raise VolregIOError(f"Expected `like` to be a Grid or a LabelVolume, got {type(like).__name__}.")
    like = as_grid(like)
    array = np.asarray(array)
    if array.shape != like.shape:
        raise VolregIOError(f"Expected `array` of shape {like.shape} (the grid of `like`), got {array.shape}.")
    if np.iscomplexobj(array) or not (np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_):
        raise VolregIOError(f"Expected `array` to hold real numbers, got dtype {array.dtype}.")
    p = Path(path)
    suffix = _check_output_suffix(p, "Image")
    _write_sitk(array.astype(np.float32, copy=False), like, p, suffix, force, "Image")
