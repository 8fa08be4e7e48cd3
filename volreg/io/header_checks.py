"""Header checks for images: fields the libraries would misread, refused before they read them.

SimpleITK and nibabel each read an image's header their own way, and some headers they read
wrongly without a word: a word or ``nan`` taken for 0, a negative spacing turned into a flipped
axis, a NIfTI ``dim`` field that drops axes, qform and sform that describe two geometries, data
shorter or longer than the header says.  The functions here read the header themselves (as
text, or through nibabel) and refuse such a file with one :class:`VolregIOError` line naming
it, what it declares and what was expected.  :mod:`volreg.io.images` calls them before and
after SimpleITK reads; the checks on data files and declared sizes are in
:mod:`volreg.io._guards`.
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

from volreg.errors import VolregIOError, VolregWarning, exception_text, excerpt
from volreg.io._guards import max_image_bytes

# qform and sform affines may differ by float32 rounding; more than this (mm,
# per affine entry) means the header describes two different geometries.
_QS_TOL_MM = 1e-3

#: Voxel spacings a reader accepts, mm: a nanometre to a kilometre.  Beyond them a header is in
#: other units or corrupt, and the grid's arithmetic (distance maps, sampling) breaks down.
SPACING_RANGE_MM = (1e-6, 1e6)
#: Farthest an image's origin may lie from 0 along an axis, mm (a kilometre; ITK's NIfTI reader
#: already fails on an sform offset of 1e8 mm, calling its axes not orthogonal).
ORIGIN_LIMIT_MM = 1e6


def _first_line(exc: BaseException) -> str:
    """The first line of an exception's text (its type's name where it has none), what it quotes
    cut short (:func:`~volreg.errors.exception_text`)."""
    return exception_text(exc)


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
    shown = {key: excerpt(value, quote=False) for key, value in fields.items()}  # what messages quote
    ndims = _numbers(fields["NDims"])
    if ndims is None or len(ndims) != 1 or ndims[0] != int(ndims[0]) or not 1 <= ndims[0] <= 16:
        raise VolregIOError(f"{what} `{path}` has NDims = {shown['NDims']}; expected the number of axes (1 to 16).")
    n = int(ndims[0])

    def values(key: str, count: int, expected: str) -> list[float] | None:
        if key not in fields:
            return None
        found = _numbers(fields[key])
        if found is None or len(found) < count or not all(np.isfinite(found[:count])):
            raise VolregIOError(f"{what} `{path}` has {key} = {shown[key]}; expected {count} {expected}.")
        return found[:count]

    sizes = values("DimSize", n, "whole numbers of at least 1")
    if sizes is not None and any(v < 1 or v != int(v) for v in sizes):
        raise VolregIOError(f"{what} `{path}` has DimSize = {shown['DimSize']}; expected {n} whole numbers of at least 1.")
    key = "ElementSpacing" if "ElementSpacing" in fields else "ElementSize"  # MetaIO's fallback
    spacing = values(key, n, "positive finite numbers (voxel spacings in mm)")
    if spacing is not None:
        if any(v < 0 for v in spacing):
            raise VolregIOError(
                f"{what} `{path}` has negative spacing ({key} = {shown[key]}); expected positive voxel spacings (a "
                "flipped axis belongs in the direction matrix)."
            )
        if any(v == 0 for v in spacing):
            raise VolregIOError(
                f"{what} `{path}` has {key} = {shown[key]}; expected positive voxel spacings (a zero spacing puts "
                "an axis's voxels at one point)."
            )
        _implausible_spacing(path, what, f"{key} = {shown[key]}", spacing, sizes)
    for key in ("Offset", "Origin", "Position"):  # synonyms in MetaIO
        origin = values(key, n, "finite numbers (the origin in mm)")
        if origin is not None:
            _implausible_origin(path, what, f"{key} = {shown[key]}, an origin of", origin)
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
                f"{what} `{path}` has negative spacing (spacings = {excerpt(fields['spacings'], quote=False)}); "
                "expected positive voxel spacings (a flipped axis belongs in the direction matrix)."
            )
    sizes = _numbers(fields.get("sizes", "")) or []
    dimension = None
    if "space directions" in fields:
        text = excerpt(fields["space directions"], quote=False)  # as messages quote it
        vectors = [m.group(1) for m in _NRRD_VECTOR.finditer(fields["space directions"])]
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
        text = excerpt(fields["space origin"], quote=False)  # as messages quote it
        found = re.fullmatch(r"\(([^)]*)\)", fields["space origin"])
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
        # instead: two readings, neither the file's
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
