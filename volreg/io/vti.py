"""VTK XML image data (``.vti``) via VTK's reader, as shipped with pyvista.

VTK stores image data x-fastest: point ``(i, j, k)`` of a grid of
``dimensions = (nx, ny, nz)`` is entry ``i + nx * (j + ny * k)`` of a point
array, so the flat array reshapes to ``(nz, ny, nx)`` and is transposed to
ITK index order ``[i, j, k]``.  The world point of index ``(i, j, k)`` is
``origin + direction @ (spacing * (extent_lo + (i, j, k)))``.

VTK image data carry no anatomical frame.  volreg takes VTK world
coordinates to be ITK physical coordinates (LPS, mm) unchanged, as ITK's
own VTK image IO does: no axis is flipped.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pyvista as pv
from vtkmodules.vtkCommonCore import vtkOutputWindow, vtkStringOutputWindow
from vtkmodules.vtkIOXML import vtkXMLImageDataReader

from volreg.errors import VolregIOError, excerpt

__all__ = ["read_vti"]

# Tolerance for the off-diagonal direction block of a single-slice image (unitless).
_DIR_TOL = 1e-6


def _vtk_reason(text: str) -> str:
    """The first VTK error message in an output-window transcript, without file/line noise."""
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith(("ERROR:", "Warning:", "WARNING:")):
            continue
        # "vtkXMLDataParser (0x55...): Error parsing XML ..." -> "Error parsing XML ..."
        head, sep, tail = line.partition("): ")
        return (tail if sep and head.startswith("vtk") else line).rstrip(".")
    return "VTK could not parse it"


def _run_reader(path: Path, what: str) -> pv.ImageData:
    """Run VTK's XML image reader with its messages captured instead of printed."""
    reader = vtkXMLImageDataReader()
    reader.SetFileName(str(path))
    window = vtkStringOutputWindow()
    previous = vtkOutputWindow.GetInstance()
    vtkOutputWindow.SetInstance(window)
    # VTK's logger prints to stderr separately from the output window.
    quiet = pv.vtk_verbosity("off") if hasattr(pv, "vtk_verbosity") else None
    try:
        if quiet is not None:
            with quiet:
                ok = reader.CanReadFile(str(path))
                if ok:
                    reader.Update()
        else:  # pragma: no cover - pyvista < 0.45
            ok = reader.CanReadFile(str(path))
            if ok:
                reader.Update()
    finally:
        vtkOutputWindow.SetInstance(previous)
    messages = window.GetOutput() or ""
    if not ok:
        reason = f": {_vtk_reason(messages)}" if messages.strip() else ""
        raise VolregIOError(f"{what} `{path}` is not a VTK XML image data file{reason}.")
    if "ERROR" in messages:
        raise VolregIOError(f"{what} `{path}` could not be read as VTK image data: {_vtk_reason(messages)}.")
    return pv.wrap(reader.GetOutput())


def _scalar_array(image: pv.ImageData, path: Path, what: str) -> np.ndarray:
    """The one scalar point array of ``image`` (the active one if several)."""
    names = list(image.point_data.keys())
    if not names:
        cells = list(image.cell_data.keys())
        extra = f" (it has cell data {excerpt(cells)}; expected values at the points)" if cells else ""
        raise VolregIOError(f"{what} `{path}` holds no point data array{extra}.")
    active = image.point_data.active_scalars_name
    if active is None:
        if len(names) > 1:
            raise VolregIOError(
                f"{what} `{path}` holds point arrays {excerpt(names)} and none is marked active; expected one label array."
            )
        active = names[0]
    values = np.asarray(image.point_data[active])
    if values.ndim != 1:
        raise VolregIOError(
            f"{what} `{path}`: point array {excerpt(active)} has {values.shape[1]} components per voxel; "
            "expected a scalar image."
        )
    if values.dtype.kind not in "iubf":
        raise VolregIOError(f"{what} `{path}`: point array {excerpt(active)} has {values.dtype} values; expected numbers.")
    return values


def _check_header_numbers(path: Path, what: str) -> None:
    """Refuse an ``ImageData`` element whose Origin, Spacing or Direction is not finite numbers
    (VTK's parser reads ``nan`` or ``inf`` there as 0 without a word)."""
    with open(path, "rb") as fh:
        head = fh.read(65536).decode("latin-1")
    element = re.search(r"<ImageData\b[^>]*>", head)
    if element is None:
        return
    for name in ("Origin", "Spacing", "Direction"):
        found = re.search(rf'\b{name}\s*=\s*"([^"]*)"', element.group(0))
        if found is None:
            continue
        try:
            values = [float(v) for v in found.group(1).split()]
        except ValueError:
            values = [float("nan")]
        if not all(math.isfinite(v) for v in values):
            raise VolregIOError(f"{what} `{path}` has {name}=\"{excerpt(found.group(1), quote=False)}\"; expected finite numbers.")


# Bytes read at a time while looking for the ``<Piece>`` elements of a file with inline data.
_SCAN_CHUNK = 1 << 20
_TAG = re.compile(rb"<(ImageData|Piece)\b[^>]*>")


def _image_tags(path: Path) -> tuple[bytes | None, list[bytes]]:
    """The ``<ImageData>`` element and every ``<Piece>`` element of a ``.vti`` file.

    Reads up to ``</ImageData>`` or ``<AppendedData`` (after which raw bytes follow), so a file
    with appended data costs one read of its head; inline data are scanned in chunks.
    """
    image, pieces = None, []
    carry = b""
    with open(path, "rb") as fh:
        while True:
            chunk = fh.read(_SCAN_CHUNK)
            if not chunk:
                break
            text = carry + chunk
            ends = [i for i in (text.find(b"</ImageData>"), text.find(b"<AppendedData")) if i >= 0]
            stop = min(ends) if ends else len(text)
            last = 0
            for match in _TAG.finditer(text, 0, stop):
                if match.group(1) == b"ImageData":
                    image = image or match.group(0)
                else:
                    pieces.append(match.group(0))
                last = match.end()
            if ends:
                break
            carry = text[max(last, len(text) - 4096):]  # a tag cut by the chunk's end is found next time
    return image, pieces


def _extent(element: bytes, name: str) -> tuple[str, list[int]] | None:
    """The text and the six integers of attribute ``name`` of an XML element, or None."""
    found = re.search(rb"\b" + name.encode() + rb'\s*=\s*"([^"]*)"', element)
    if found is None:
        return None
    text = " ".join(found.group(1).decode("latin-1").split())
    try:
        values = [int(v) for v in text.split()]
    except ValueError:
        return None
    return (text, values) if len(values) == 6 else None


def _check_pieces(path: Path, what: str) -> None:
    """Refuse a ``.vti`` whose ``<Piece>`` extents leave part of its ``WholeExtent`` without data.

    VTK allocates the whole extent and fills it from the pieces only: the points no piece covers
    keep whatever the memory held, which would be read as labels.
    """
    image, pieces = _image_tags(path)
    whole = _extent(image, "WholeExtent") if image is not None else None
    extents = [_extent(piece, "Extent") for piece in pieces]
    if whole is None or not extents or any(e is None for e in extents):
        return  # VTK reports a malformed file
    lo, hi = np.array(whole[1][0::2]), np.array(whole[1][1::2]) + 1  # point ranges [lo, hi)
    if np.any(hi <= lo):
        return  # an empty extent: reported after reading
    boxes = [(np.maximum(np.array(e[1][0::2]), lo), np.minimum(np.array(e[1][1::2]) + 1, hi)) for e in extents]
    boxes = [(a, b) for a, b in boxes if np.all(b > a)]
    # Cover the whole extent with the cells between the pieces' boundaries along each axis.
    cuts = [np.unique([lo[a], hi[a], *[v for box in boxes for v in (box[0][a], box[1][a])]]) for a in range(3)]
    if np.prod([len(c) - 1 for c in cuts], dtype=float) > 1e7:
        return  # too many pieces to check cheaply
    covered = np.zeros([len(c) - 1 for c in cuts], bool)
    for a, b in boxes:
        covered[tuple(slice(np.searchsorted(cuts[x], a[x]), np.searchsorted(cuts[x], b[x])) for x in range(3))] = True
    if not covered.all():
        listed = ", ".join(f'Extent="{e[0]}"' for e in extents)
        raise VolregIOError(
            f'{what} `{path}` has WholeExtent="{whole[0]}" but its data cover only {listed}; expected pieces that '
            "cover the whole extent (VTK would fill the rest with whatever its memory held)."
        )


def read_vti(path: Path, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read a scalar ``.vti`` image; return ``(array[i, j, k], origin, spacing, direction)``.

    Parameters
    ----------
    path : pathlib.Path
        An existing ``.vti`` file.
    what : str
        What the file is, for error messages (e.g. ``"Label image"``).

    Returns
    -------
    array : (n_i, n_j[, n_k]) ndarray
        Point values in ITK index order, dtype as stored, in a new C-order
        array that owns its memory.  A grid with a
        single slice along ``z`` whose direction keeps ``z`` separate is
        returned as a 2-D image.
    origin : (D,) float ndarray, mm
        World point of index ``0`` (the first point of the extent).
    spacing : (D,) float ndarray, mm
    direction : (D, D) float ndarray
        The image's direction matrix; world coordinates are taken as LPS.

    Raises
    ------
    VolregIOError
        If the file is not VTK image data, fails to parse (e.g. truncated),
        is empty, holds no point array, several arrays none of them active,
        or a vector array, or if its pieces leave part of its ``WholeExtent``
        without data.
    """
    _check_header_numbers(path, what)
    _check_pieces(path, what)
    image = _run_reader(path, what)
    dims = tuple(int(n) for n in image.dimensions)
    if image.n_points == 0 or min(dims) < 1:
        raise VolregIOError(f"{what} `{path}` holds an empty image (dimensions {dims}); expected voxels.")
    values = _scalar_array(image, path, what)
    if values.size != int(np.prod(dims)):
        raise VolregIOError(
            f"{what} `{path}` has {values.size} values for dimensions {dims}; expected {int(np.prod(dims))}."
        )
    view = values.reshape(dims[::-1]).T  # (nz, ny, nx) -> [i, j, k], still VTK's memory
    spacing = np.asarray(image.spacing, dtype=float)
    direction = np.asarray(image.direction_matrix, dtype=float)
    extent_lo = np.asarray(image.extent, dtype=float)[0::2]
    origin = np.asarray(image.origin, dtype=float) + direction @ (spacing * extent_lo)
    separable = np.all(np.abs(direction[:2, 2]) < _DIR_TOL) and np.all(np.abs(direction[2, :2]) < _DIR_TOL)
    if dims[2] == 1 and separable:
        view = view[:, :, 0]
        origin, spacing, direction = origin[:2], spacing[:2], direction[:2, :2]
    # One copy, in C order, that owns its memory (never a view into the VTK array).
    return np.array(view, order="C"), origin, spacing, direction
