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
:class:`~volreg.grid.Grid`) from the header.
"""

from __future__ import annotations

import contextlib
import gzip
import os
import re
import warnings
import zlib
from pathlib import Path

import nibabel as nib
import numpy as np
import SimpleITK as sitk

from volreg.errors import GeometryError, VolregIOError, VolregWarning
from volreg.grid import Grid, LabelVolume, as_grid
from volreg.io._atomic import atomic_output
from volreg.io._guards import check_image_data_files, check_readable, check_vti_size, max_image_bytes

__all__ = ["read_labels", "write_labels", "write_scalar", "read_image", "read_grid"]

#: Suffixes the readers accept (lower case).
READ_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd", ".vti")
#: Suffixes the writers accept: single-file formats only, so a write can be atomic.
WRITE_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".mha")

# qform and sform affines may differ by float32 rounding; more than this (mm,
# per affine entry) means the header describes two different geometries.
_QS_TOL_MM = 1e-3

# Tolerance for the direction block of a squeezed 4-D image (unitless).
_DIR_TOL = 1e-6

#: Voxel spacings a reader accepts, mm: a nanometre to a kilometre.  Beyond them a header is in
#: other units or corrupt, and the grid's arithmetic (distance maps, sampling) breaks down.
SPACING_RANGE_MM = (1e-6, 1e6)
#: Farthest an image's origin may lie from 0 along an axis, mm (a kilometre; ITK's NIfTI reader
#: already fails on an sform offset of 1e8 mm, calling its axes not orthogonal).
ORIGIN_LIMIT_MM = 1e6


def _check_size(path: Path, shape: tuple[int, ...], itemsize: int, what: str) -> None:
    """Refuse, before anything is allocated, an image larger than :func:`max_image_bytes`."""
    voxels = int(np.prod([max(int(n), 0) for n in shape], dtype=object))
    need = voxels * int(itemsize)
    limit = max_image_bytes()
    if need > limit:
        raise VolregIOError(
            f"{what} `{path}` has shape {tuple(int(n) for n in shape)} ({voxels:,} voxels, {need / 1024**3:.3g} GB in "
            f"memory); expected at most {limit / 1024**3:.3g} GB (set VOLREG_MAX_IMAGE_GB to change the limit)."
        )


def _raw_pixdim(path: Path, suffix: str) -> np.ndarray:
    """``pixdim[0:8]`` exactly as stored in a NIfTI-1 header (bytes 76-108), either byte order."""
    opener = gzip.open if suffix == ".nii.gz" else open
    with opener(path, "rb") as fh:
        block = fh.read(108)
    little = int.from_bytes(block[:4], "little") == 348
    return np.frombuffer(block[76:108], dtype="<f4" if little else ">f4").astype(float)


def _check_nifti_dims(path: Path, suffix: str, what: str) -> None:
    """Refuse a NIfTI header whose ``dim`` field is invalid or miscounts the axes, before either library reads it.

    ``dim[0]`` counts the axes (1 to 7) and ``dim[1..dim[0]]`` are their sizes (at least 1).
    nibabel and SimpleITK read a zero or negative size differently (0 or -3 against 1), and both
    silently drop the axes after ``dim[0]``: a ``dim[0]`` of 2 over 3-D data gives the first slice.
    """
    opener = gzip.open if suffix == ".nii.gz" else open
    try:
        with opener(path, "rb") as fh:
            block = fh.read(540)
    except (OSError, EOFError, zlib.error):
        return  # nibabel reports an unreadable or corrupt file
    if len(block) < 348:
        return
    for order in ("<", ">"):
        sizeof = int(np.frombuffer(block[:4], dtype=f"{order}i4")[0])
        if sizeof == 348:
            dim = np.frombuffer(block[40:56], dtype=f"{order}i2").astype(np.int64)
            break
        if sizeof == 540:
            raise VolregIOError(
                f"{what} `{path}` is NIfTI-2, which SimpleITK (volreg's reader) does not read; expected NIfTI-1 "
                "(convert it, e.g. with nibabel: nib.save(nib.Nifti1Image(np.asarray(img.dataobj), img.affine), "
                "'out.nii.gz'))."
            )
    else:
        return  # not NIfTI: nibabel reports it
    n = int(dim[0])
    if not 1 <= n <= 7:
        raise VolregIOError(
            f"{what} `{path}` has dim[0] = {n} in its NIfTI header; expected the number of axes, 1 to 7."
        )
    sizes = [int(v) for v in dim[1 : n + 1]]
    if any(v < 1 for v in sizes):
        raise VolregIOError(
            f"{what} `{path}` has axis sizes dim[1..{n}] = {sizes} in its NIfTI header; expected sizes of at least 1."
        )
    beyond = [(i, int(dim[i])) for i in range(n + 1, 8) if int(dim[i]) > 1]
    if beyond:
        i, v = beyond[0]
        raise VolregIOError(
            f"{what} `{path}` has dim[0] = {n} in its NIfTI header but dim[{i}] = {v}; expected dim[0] to count "
            f"every axis of the data (readers would drop axis {i} and read another shape)."
        )


def _implausible_spacing(path: Path, what: str, field: str, spacing, sizes=None) -> None:
    """Refuse a voxel spacing outside :data:`SPACING_RANGE_MM` (of an axis longer than 1 where
    ``sizes`` are given); ``field`` names the header field it came from ("" for none)."""
    lo, hi = SPACING_RANGE_MM
    for axis, value in enumerate(float(v) for v in spacing):
        if sizes is not None and axis < len(sizes) and int(sizes[axis]) <= 1:
            continue
        if not lo <= value <= hi:
            head = f"{field}: {value:g} mm" if field else f"a voxel spacing of {value:g} mm"
            raise VolregIOError(
                f"{what} `{path}` has {head} along axis {axis}; expected voxel spacings from {lo:g} to {hi:g} mm "
                "(check the header's units)."
            )


def _implausible_origin(path: Path, what: str, field: str, origin) -> None:
    """Refuse an origin farther than :data:`ORIGIN_LIMIT_MM` from 0 along any axis; ``field`` says
    where it came from (e.g. ``"an origin of"``)."""
    values = [float(v) for v in origin]
    if any(not abs(v) <= ORIGIN_LIMIT_MM for v in values):
        listed = ", ".join(f"{v:g}" for v in values)
        raise VolregIOError(
            f"{what} `{path}` has {field} [{listed}] mm; expected an origin within {ORIGIN_LIMIT_MM:g} mm (1 km) "
            "of 0 (check the header's units)."
        )


def _read_header_text(path: Path) -> bytes | None:
    try:
        with open(path, "rb") as fh:
            return fh.read(1 << 16)
    except OSError:
        return None  # SimpleITK reports unreadable files


def _numbers(text: str) -> list[float] | None:
    try:
        return [float(v) for v in text.split()]
    except ValueError:
        return None


def _check_metaimage_header(path: Path, what: str) -> None:
    """Refuse a MetaImage header whose geometry fields MetaIO would misread.

    MetaIO reads ``nan`` or a word as 0 and a missing value as 0 (``Offset = 5 5`` of a 3-D
    image is ``[5, 5, 0]``), or fails with lines of its own on stderr; ITK turns a negative
    spacing into a flipped axis.  Fields are matched as MetaIO matches them (case-sensitive,
    the last of a repeated field wins, up to ``ElementDataFile``); like MetaIO, values beyond
    the number of axes are ignored.
    """
    head = _read_header_text(path)
    if head is None:
        return
    fields: dict[str, str] = {}
    for raw in head.split(b"\n")[:200]:
        key, sep, value = raw.decode("latin-1").strip().partition("=")
        if not sep:
            continue
        key = key.strip()
        if key == "ElementDataFile":
            break
        fields[key] = value.strip()
    if "NDims" not in fields:
        return  # MetaIO reports a header without one
    ndims = _numbers(fields["NDims"])
    if ndims is None or len(ndims) != 1 or ndims[0] != int(ndims[0]) or not 1 <= ndims[0] <= 16:
        raise VolregIOError(f"{what} `{path}` has NDims = {fields['NDims']}; expected the number of axes (1 to 16).")
    n = int(ndims[0])

    def values(key: str, count: int, expected: str) -> list[float] | None:
        if key not in fields:
            return None
        found = _numbers(fields[key])
        if found is None or len(found) < count or not all(np.isfinite(found[:count])):
            raise VolregIOError(f"{what} `{path}` has {key} = {fields[key]}; expected {count} {expected}.")
        return found[:count]

    sizes = values("DimSize", n, "whole numbers of at least 1")
    if sizes is not None and any(v < 1 or v != int(v) for v in sizes):
        raise VolregIOError(f"{what} `{path}` has DimSize = {fields['DimSize']}; expected {n} whole numbers of at least 1.")
    key = "ElementSpacing" if "ElementSpacing" in fields else "ElementSize"  # MetaIO's fallback
    spacing = values(key, n, "positive finite numbers (voxel spacings in mm)")
    if spacing is not None:
        if any(v < 0 for v in spacing):
            raise VolregIOError(
                f"{what} `{path}` has negative spacing ({key} = {fields[key]}); expected positive voxel spacings (a "
                "flipped axis belongs in the direction matrix)."
            )
        if any(v == 0 for v in spacing):
            raise VolregIOError(
                f"{what} `{path}` has {key} = {fields[key]}; expected positive voxel spacings (a zero spacing puts "
                "an axis's voxels at one point)."
            )
        _implausible_spacing(path, what, f"{key} = {fields[key]}", spacing, sizes)
    for key in ("Offset", "Origin", "Position"):  # synonyms in MetaIO
        origin = values(key, n, "finite numbers (the origin in mm)")
        if origin is not None:
            _implausible_origin(path, what, f"{key} = {fields[key]}, an origin of", origin)
    for key in ("TransformMatrix", "Rotation", "Orientation"):  # synonyms in MetaIO
        values(key, n * n, "finite numbers (the direction matrix)")


_NRRD_VECTOR = re.compile(r"\(([^)]*)\)|none")


def _check_nrrd_header(path: Path, what: str) -> None:
    """Refuse a NRRD header whose space fields or spacings ITK would misread or reject with a cryptic line.

    ``spacings`` may not be negative (ITK makes a flipped axis of it); every vector of ``space
    directions`` and ``space origin`` must be finite numbers (teem takes a vector of NaNs for
    "no vector" and ITK then puts the identity there; one NaN among numbers fails with teem's
    own wording), and a direction's length, the axis's spacing, must be plausible.
    """
    head = _read_header_text(path)
    if head is None or not head.startswith(b"NRRD"):
        return
    fields: dict[str, str] = {}
    for raw in head.split(b"\n")[1:200]:
        line = raw.decode("latin-1").rstrip("\r")
        if not line.strip():
            break  # end of header
        if line.startswith("#") or ":=" in line:
            continue
        key, sep, value = line.partition(":")
        if sep:
            fields[key.strip().lower()] = value.strip()
    if "spacings" in fields:
        spacings = _numbers(fields["spacings"])
        if spacings is not None and any(v < 0 for v in spacings):
            raise VolregIOError(
                f"{what} `{path}` has negative spacing (spacings = {fields['spacings']}); expected positive "
                "voxel spacings (a flipped axis belongs in the direction matrix)."
            )
    sizes = _numbers(fields.get("sizes", "")) or []
    dimension = None
    if "space directions" in fields:
        text = fields["space directions"]
        vectors = [m.group(1) for m in _NRRD_VECTOR.finditer(text)]
        spatial = [(i, [_numbers(c) for c in v.split(",")]) for i, v in enumerate(vectors) if v is not None]
        parsed = [(i, [c[0] if c and len(c) == 1 else float("nan") for c in v]) for i, v in spatial]
        dimension = len(parsed[0][1]) if parsed else None
        if not parsed or any(len(v) != dimension or not all(np.isfinite(v)) for _, v in parsed):
            raise VolregIOError(
                f"{what} `{path}` has space directions: {text}; expected a vector of finite numbers per spatial "
                "axis, all of one length (or none for a non-spatial axis)."
            )
        lengths = [float(np.linalg.norm(v)) for _, v in parsed]
        axis_sizes = [sizes[i] if i < len(sizes) else 2 for i, _ in parsed]
        _implausible_spacing(path, what, f"space directions: {text}", lengths, axis_sizes)
    if "space origin" in fields:
        text = fields["space origin"]
        found = re.fullmatch(r"\(([^)]*)\)", text)
        parts = [_numbers(c) for c in found.group(1).split(",")] if found else []
        origin = [c[0] if c and len(c) == 1 else float("nan") for c in parts]
        if not origin or not all(np.isfinite(origin)) or (dimension is not None and len(origin) != dimension):
            count = f"{dimension} " if dimension is not None else ""
            raise VolregIOError(f"{what} `{path}` has space origin: {text}; expected a vector of {count}finite numbers.")
        _implausible_origin(path, what, f"space origin: {text}, an origin of", origin)


def _check_header_fields(path: Path, suffix: str, what: str) -> None:
    """Read a MetaImage or NRRD header as text and refuse geometry fields ITK would misread."""
    if suffix in (".mha", ".mhd"):
        _check_metaimage_header(path, what)
    elif suffix in (".nrrd", ".nhdr"):
        _check_nrrd_header(path, what)


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


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    line = text.splitlines()[0].strip() if text else ""
    return line or type(exc).__name__


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
    return reason.rstrip(".")


def _check_nifti_length(path: Path, suffix: str, what: str, offset: int, shape: tuple[int, ...], itemsize: int) -> None:
    """Refuse a NIfTI file whose data end before the header says (``offset`` + voxels x ``itemsize`` bytes)."""
    needed = offset + int(np.prod(shape, dtype=np.int64)) * itemsize
    if suffix == ".nii.gz":
        # SimpleITK silently zero-fills a truncated gzip stream, so decompress it
        # fully ourselves (this also verifies the gzip CRC).
        have = 0
        try:
            with gzip.open(path, "rb") as fh:
                while chunk := fh.read(1 << 22):
                    have += len(chunk)
        except EOFError as exc:
            raise VolregIOError(
                f"{what} `{path}` is truncated: its gzip stream ends before the {needed} bytes its header describes "
                "(an interrupted copy or download?)."
            ) from exc
        except (OSError, zlib.error) as exc:
            raise VolregIOError(f"{what} `{path}` is a corrupt gzip file: {_first_line(exc)}.") from exc
    else:
        have = os.path.getsize(path)
    if have < needed:
        raise VolregIOError(
            f"{what} `{path}` is truncated: header needs {needed} bytes (shape {shape}, "
            f"{itemsize}-byte voxels), file holds {have}."
        )
    # Data beyond the header's shape by a whole slice or more: the header's dim field describes
    # fewer or smaller axes than were written (both readers would silently read another shape).
    slice_bytes = int(np.prod(shape[:-1], dtype=np.int64)) * itemsize if len(shape) > 1 else itemsize
    if have - needed >= max(slice_bytes, 1):
        raise VolregIOError(
            f"{what} `{path}` holds {have - needed} bytes of data beyond the shape {shape} its header describes "
            f"({itemsize}-byte voxels); expected the header's dim field to describe all the data."
        )


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


@contextlib.contextmanager
def _nibabel_quiet():
    """nibabel's header checks log what they fix to stderr (through logging's last-resort handler
    when nothing is configured); the checks here report in one line of their own."""
    logger = nib.imageglobals.logger
    disabled, logger.disabled = logger.disabled, True
    try:
        yield
    finally:
        logger.disabled = disabled


#: Millimetres per unit of a NIfTI header's spatial unit (the low three bits of ``xyzt_units``:
#: 1 metre, 2 mm, 3 micrometre): ITK converts spacings and origins to millimetres, nibabel's affine
#: keeps the file's unit.  Other codes (0, unknown; 4-7) ITK reads as mm.
_NIFTI_UNIT_MM = {1: 1000.0, 2: 1.0, 3: 1e-3}


def _nifti_unit_mm(header) -> float:
    """Millimetres per unit of the header's spatial unit (see :data:`_NIFTI_UNIT_MM`).  Decoded from
    the space bits alone, as ITK does: nibabel's decoding fails on time bits it does not know."""
    try:
        return _NIFTI_UNIT_MM.get(int(header["xyzt_units"]) & 7, 1.0)
    except (KeyError, TypeError, ValueError):  # no such field: read as mm, as ITK does
        return 1.0


def _check_nifti(path: Path, suffix: str, what: str, *, voxels: bool = True) -> nib.Nifti1Image:
    """Checks SimpleITK does not do for NIfTI: truncated data and qform/sform conflicts.

    With ``voxels=False`` (the header alone is wanted) the data are not
    checked for truncation, which for ``.nii.gz`` means decompressing them.
    Returns the (lazily loaded) nibabel image for the checks after reading.
    """
    _check_nifti_dims(path, suffix, what)
    try:
        with warnings.catch_warnings(), _nibabel_quiet():
            # nibabel warns (and logs, e.g. a zero pixdim it "fixes") about odd headers; we only
            # need the fields below, and check them ourselves.
            warnings.simplefilter("ignore")
            img = nib.load(str(path))
            header = img.header
            # The offset the data are read from (the loaded header's own field may read 0).
            offset = int(getattr(img.dataobj, "offset", header.get_data_offset()))
            shape = tuple(int(n) for n in header.get_data_shape())
            itemsize = np.dtype(header.get_data_dtype()).itemsize
            qform, qcode = img.get_qform(coded=True)
            sform, scode = img.get_sform(coded=True)
            unit = _nifti_unit_mm(header)  # forms in micrometres or metres: checked in mm, as ITK reads them
            qform = None if qform is None else np.diag([unit, unit, unit, 1.0]) @ qform
            sform = None if sform is None else np.diag([unit, unit, unit, 1.0]) @ sform
    except Exception as exc:  # nibabel raises many types for garbage input
        raise VolregIOError(f"{what} `{path}` is not a readable NIfTI file: {_first_line(exc)}.") from exc

    _check_size(path, shape, itemsize, what)  # before decompressing: a header may claim terabytes
    if suffix in (".nii", ".nii.gz") and offset < int(header.sizeof_hdr):
        # nibabel then reads the header's own bytes as voxels, and ITK starts after the header
        # instead: two readings, neither the file's (a pair read so was registered 4 mm off)
        raise VolregIOError(
            f"{what} `{path}` has vox_offset {offset}, inside its {int(header.sizeof_hdr)}-byte header; expected the "
            f"voxels after the header (vox_offset {int(header.sizeof_hdr) + 4} or more in a single-file NIfTI): the "
            "header is malformed, and readers disagree on where the voxels start (rewrite it with the tool that "
            "made it, or set vox_offset)."
        )
    # Spatial axes only (a displacement field's 4th and 5th axes are time and vector components).
    pixdim = _raw_pixdim(path, suffix)[1 : min(len(shape), 3) + 1] * unit  # nibabel's loader makes them positive
    spatial = np.asarray(shape[: len(pixdim)]) > 1  # a singleton axis may carry pixdim 0
    if np.any(~np.isfinite(pixdim)) or np.any((pixdim <= 0) & spatial):
        raise VolregIOError(
            f"{what} `{path}` has voxel sizes (pixdim) {pixdim.tolist()}; expected positive, finite spacings."
        )
    listed = ", ".join(f"{float(v):g}" for v in pixdim)
    _implausible_spacing(path, what, f"voxel sizes (pixdim) [{listed}]", pixdim, shape[: len(pixdim)])
    if voxels:
        _check_nifti_length(path, suffix, what, offset, shape, itemsize)

    for name, form, code in (("qform", qform, qcode), ("sform", sform, scode)):
        if form is not None and not np.all(np.isfinite(form)):
            # SimpleITK would print pages of linear-algebra diagnostics before failing on it.
            raise VolregIOError(f"{what} `{path}` has a {name} (code {int(code)}) with NaN or Inf entries; expected "
                                "a finite geometry (fix the header or clear that form).")
        if form is not None:
            article = "a" if name == "qform" else "an"
            _check_nifti_form(np.asarray(form, dtype=float), f"{article} {name} (code {int(code)})", path, what)
    if qform is None and sform is None:
        warnings.warn(
            f"{what} `{path}` has no orientation in its header (qform_code = sform_code = 0): read as ITK does "
            "(identity direction, origin 0; nibabel would give a flipped, centred affine); set an sform or qform "
            "to make it unambiguous.",
            VolregWarning,
            stacklevel=3,
        )
    if qform is not None and sform is not None:
        diff = float(np.max(np.abs(np.asarray(qform) - np.asarray(sform))))
        if diff > _QS_TOL_MM:
            raise VolregIOError(
                f"{what} `{path}` has qform (code {int(qcode)}) and sform (code {int(scode)}) that disagree "
                f"by up to {diff:.4g} mm; expected one geometry (fix the header or clear one of them)."
            )
    return img


def _check_nifti_form(form: np.ndarray, name: str, path: Path, what: str) -> None:
    """Refuse a coded NIfTI affine (RAS, mm; ``name`` e.g. "an sform (code 1)") that is singular or
    lies implausibly far away.

    ITK calls both "not orthogonal": it checks that the sform is a rotation times scales in single
    precision, offset included, which a zero row fails and so does an offset of 1e8 mm or more.
    """
    block = form[:3, :3]
    lengths = np.linalg.norm(block, axis=0)
    det = float(np.linalg.det(block))
    if np.any(lengths == 0) or abs(det) <= 1e-9 * float(np.prod(lengths)):
        raise VolregIOError(
            f"{what} `{path}` has {name} whose direction matrix is singular (determinant {det:.3g}); expected "
            "independent axis directions (fix the header or clear that form)."
        )
    _implausible_origin(path, what, f"{name} offset of", form[:3, 3])


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


def _check_nifti_geometry(
    nimg: nib.Nifti1Image,
    origin: np.ndarray,
    spacing: np.ndarray,
    direction: np.ndarray,
    path: Path,
    what: str,
) -> None:
    """Cross-check SimpleITK's geometry of a NIfTI file against the header's coded affine.

    ITK takes voxel sizes from ``pixdim`` even when the sform says otherwise,
    and cannot represent a sheared affine; so SimpleITK's geometry, converted
    to RAS, must equal the header's coded affine.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        header = nimg.header
        coded = int(header["sform_code"]) > 0 or int(header["qform_code"]) > 0
        unit = _nifti_unit_mm(header)  # ITK's geometry is in mm, nibabel's affine in the file's unit
        header_affine = np.diag([unit, unit, unit, 1.0]) @ np.asarray(nimg.affine, dtype=float)
    if coded:
        d = len(origin)
        flip = np.array([-1.0, -1.0, 1.0])[:d]
        ours = flip[:, None] * (direction * spacing[None, :])  # RAS columns per index axis
        diff = max(
            float(np.max(np.abs(ours - header_affine[:d, :d]))),
            float(np.max(np.abs(flip * origin - header_affine[:d, 3]))),
        )
        if diff > _QS_TOL_MM:
            raise VolregIOError(
                f"{what} `{path}` has a header affine that SimpleITK cannot reproduce (off by up to {diff:.4g} mm): "
                "pixdim disagrees with the sform/qform, or the affine is sheared; expected a consistent header."
            )


def _check_nifti_shape(nimg: nib.Nifti1Image, size: tuple[int, ...], path: Path, what: str) -> None:
    """Refuse a NIfTI file that nibabel and SimpleITK read as two different shapes (trailing 1s aside)."""

    def trim(shape):
        shape = [int(n) for n in shape]
        while len(shape) > 1 and shape[-1] == 1:
            shape.pop()
        return tuple(shape)

    ours, theirs = trim(size), trim(nimg.shape)
    if ours != theirs:
        raise VolregIOError(
            f"{what} `{path}` reads as shape {theirs} with nibabel but {ours} with SimpleITK; expected a NIfTI "
            "header both read alike (check its dim field)."
        )


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
