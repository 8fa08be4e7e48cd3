"""Checks made on a file before a library is handed it: what it points to, and what it declares.

Image and mesh readers (ITK's, VTK's, numpy's) allocate what a header declares before they
read the data, follow data-file names wherever they lead, and report a missing data file as a
bad header (printing their own text to stderr).  The functions here read the header text
themselves, cheaply, and refuse in one line naming the file:

- a data file named by a MetaImage, NRRD or GIFTI header that lies outside the header's folder
  (an absolute path, one that climbs out with ``..``, or one that a symbolic link, of the file or
  of a folder on its way, leads out of the header's resolved folder), unless
  ``VOLREG_ALLOW_EXTERNAL_DATA=1``;
- a data file that is missing, unreadable or shorter than the header declares;
- a header declaring more data than the file can hold (allowing for compression at the best
  ratio its codec can reach) or more than :func:`max_image_bytes` in memory.

Nothing here allocates in proportion to a declared size.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from zlib import error as zlib_error

import numpy as np

from volreg.errors import VolregIOError, exception_text, excerpt

__all__ = ["max_image_bytes", "external_data_allowed", "resolves_inside", "check_readable", "check_memory",
           "check_image_data_files", "check_mesh_sizes", "check_gifti_sizes", "check_vti_size", "declared_vti", "check_npz"]

#: Environment variable that allows data files outside a header's folder.
ALLOW_EXTERNAL = "VOLREG_ALLOW_EXTERNAL_DATA"

#: Largest ratio of inflated to deflated bytes that zlib/gzip can reach (about 1032:1), with a margin.
DEFLATE_RATIO = 1100
#: LZ4 cannot exceed about 255:1.
LZ4_RATIO = 260

# How much of a header is read (bytes); a header is text at the start of the file.
_HEAD = 1 << 20


def max_image_bytes() -> int:
    """Largest image, mesh or model (bytes in memory) a reader accepts.

    ``VOLREG_MAX_IMAGE_GB`` if set, else half the RAM.
    """
    value = os.environ.get("VOLREG_MAX_IMAGE_GB")
    if value:
        try:
            gb = float(value)
        except ValueError:
            raise VolregIOError(f"Environment variable VOLREG_MAX_IMAGE_GB={value!r} is not a number of GB.") from None
        return int(gb * 1024**3)
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 8 * 1024**3


def external_data_allowed() -> bool:
    """Whether ``VOLREG_ALLOW_EXTERNAL_DATA`` allows data files outside a header's folder (``1``, ``yes``, ``true``)."""
    value = os.environ.get(ALLOW_EXTERNAL, "").strip().lower()
    if value in ("", "0", "no", "false"):
        return False
    if value in ("1", "yes", "true"):
        return True
    raise VolregIOError(f"Environment variable {ALLOW_EXTERNAL}={value!r}; expected 1 (allow) or 0 (refuse).")


def check_readable(path: Path, what: str) -> None:
    """Refuse an existing file this process may not read (rather than calling it missing or invalid)."""
    try:
        with open(path, "rb") as fh:
            fh.read(1)
    except PermissionError:
        raise VolregIOError(f"{what} `{path}` is not readable (permission denied); expected a file you can read.") from None
    except IsADirectoryError:
        raise VolregIOError(f"{what} `{path}` is not a regular file.") from None
    except OSError as exc:
        raise VolregIOError(f"{what} `{path}` cannot be opened: {exc.strerror or exc}.") from None


def check_memory(path: Path, need: int, what: str, described: str) -> None:
    """Refuse a file whose declared contents need more than :func:`max_image_bytes` in memory."""
    limit = max_image_bytes()
    if need > limit:
        raise VolregIOError(
            f"{what} `{path}` declares {described} ({need / 1024**3:.3g} GB in memory); expected at most "
            f"{limit / 1024**3:.3g} GB (set VOLREG_MAX_IMAGE_GB to change the limit)."
        )


def _declared_too_much(path: Path, what: str, described: str, need: int, have: int, source: Path | None = None) -> None:
    where = "" if source is None or source == path else f" (data file `{source}`)"
    raise VolregIOError(
        f"{what} `{path}` declares {described}, at least {need:,} bytes of data, but the file{where} holds "
        f"{have:,}; expected a complete file (truncated, or a header that does not match its data?)."
    )


def _read_head(path: Path) -> bytes:
    with open(path, "rb") as fh:
        return fh.read(_HEAD)


# ----------------------------------------------------------------------------- MetaImage and NRRD

_MET_SIZES = {"MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4, "MET_UINT": 4,
              "MET_LONG": 4, "MET_ULONG": 4, "MET_LONG_LONG": 8, "MET_ULONG_LONG": 8, "MET_FLOAT": 4,
              "MET_DOUBLE": 8}

_NRRD_SIZES = {}
for _names, _size in (
    (("signed char", "int8", "int8_t", "uchar", "unsigned char", "uint8", "uint8_t"), 1),
    (("short", "short int", "signed short", "signed short int", "int16", "int16_t", "ushort", "unsigned short",
      "unsigned short int", "uint16", "uint16_t"), 2),
    (("int", "signed int", "int32", "int32_t", "uint", "unsigned int", "uint32", "uint32_t", "float"), 4),
    (("longlong", "long long", "long long int", "signed long long", "signed long long int", "int64", "int64_t",
      "ulonglong", "unsigned long long", "unsigned long long int", "uint64", "uint64_t", "double"), 8),
):
    for _n in _names:
        _NRRD_SIZES[_n] = _size


def _ints(text: str) -> list[int] | None:
    try:
        return [int(float(v)) for v in text.split()]
    except ValueError:
        return None


def resolves_inside(target: Path, folder: Path) -> bool:
    """Whether ``target``, every symbolic link on its way followed, lies inside ``folder`` (itself resolved).

    Both are resolved with :func:`os.path.realpath`, which follows links the way the system
    does when it opens the file (a ``..`` after a link climbs from the link's target); a target
    that does not exist is resolved as far as it goes.
    """
    real_folder = os.path.realpath(folder)
    real_target = os.path.realpath(target)
    return os.path.commonpath([real_folder, real_target]) == real_folder


def _data_file_location(header: Path, name: str, what: str) -> Path:
    """The data file ``name`` of ``header``: refused outside the header's folder unless allowed.

    Outside is judged twice: on the name as written (an absolute path, or one that climbs out
    with ``..``), and on where it leads once every symbolic link is followed
    (:func:`resolves_inside`): a data file, or a folder on its way, that is a link to a file
    elsewhere is outside too, though its name lies in the folder.
    """
    folder = header.parent
    target = Path(name)
    outside = ""
    if target.is_absolute():
        outside = "an absolute path"
    else:
        rel = os.path.normpath(name)
        if rel == ".." or rel.startswith(".." + os.sep) or rel.startswith("../"):
            outside = "a path that climbs out of the header's folder"
        target = folder / name
    if not outside and not resolves_inside(target, folder):
        outside = (f"which a symbolic link leads to `{excerpt(os.path.realpath(target), 80, quote=False)}`, outside the "
                   f"header's folder `{excerpt(os.path.realpath(folder), 80, quote=False)}`")
    if outside and not external_data_allowed():
        raise VolregIOError(
            f"{what} `{header}` names data file `{excerpt(name, 80, quote=False)}`, {outside}; expected a data file in "
            f"the header's folder (set {ALLOW_EXTERNAL}=1 to read data files elsewhere)."
        )
    return target


def _check_data_file(header: Path, target: Path, what: str) -> int:
    """Check that a data file exists and can be read; return its size in bytes."""
    if not target.exists():
        raise VolregIOError(f"{what} `{header}` names data file `{target}`, which does not exist; expected it beside the header.")
    if not target.is_file():
        raise VolregIOError(f"{what} `{header}` names data file `{target}`, which is not a regular file.")
    try:
        with open(target, "rb") as fh:
            fh.read(1)
    except PermissionError:
        raise VolregIOError(f"{what} `{header}` names data file `{target}`, which is not readable (permission "
                            "denied); expected a file you can read.") from None
    except OSError as exc:
        raise VolregIOError(f"{what} `{header}` names data file `{target}`, which cannot be opened: "
                            f"{exc.strerror or exc}.") from None
    return target.stat().st_size


def _file_list(header: Path, head: bytes, start: int, what: str) -> list[str]:
    """The file names listed one per line after a ``LIST`` data-file entry (from byte ``start``)."""
    if len(head) >= _HEAD:
        raise VolregIOError(f"{what} `{header}` has a header longer than {_HEAD} bytes; expected a short text header.")
    return [line.strip() for line in head[start:].decode("latin-1").splitlines() if line.strip()]


def _check_list_count(path: Path, what: str, files: list[str], dims: list[int] | None, subdim: int | None) -> None:
    """Refuse a ``LIST`` of data files that does not give one file per slice (readers leave the rest unset)."""
    if not dims or subdim is None or not 1 <= subdim <= len(dims):
        return
    expected = int(np.prod(dims[subdim:], dtype=object)) if subdim < len(dims) else 1
    if len(files) != expected:
        raise VolregIOError(
            f"{what} `{path}` lists {len(files)} data files for {subdim}-D slices of a "
            f"{' x '.join(map(str, dims))} image; expected {expected}, one per slice."
        )


def _pattern_files(spec: list[str]) -> list[str] | None:
    """The names of a printf-style data-file pattern ``fmt min max step [subdim]``, or None if not one."""
    if len(spec) < 4 or "%" not in spec[0]:
        return None
    bounds = _ints(" ".join(spec[1:4]))
    if bounds is None or bounds[2] == 0:
        return None
    lo, hi, step = bounds
    count = (hi - lo) // step + 1
    if count <= 0 or count > 100_000:
        return None
    try:
        return [spec[0] % i for i in range(lo, hi + 1 if step > 0 else hi - 1, step)]
    except (TypeError, ValueError):
        return None


def _check_payload(header: Path, what: str, described: str, need: int, have: int, encoding: str,
                   source: Path | None) -> None:
    """Compare the bytes a header needs (``need``, uncompressed) with those the data hold (``have``)."""
    if encoding == "raw":
        minimum = need
    elif encoding == "ascii":
        minimum = need  # at least one character and one separator per value: ``need`` counts values x 2 - 1
    elif encoding == "hex":
        minimum = 2 * need
    elif encoding == "deflate":
        minimum = need // DEFLATE_RATIO
    else:  # bzip2 and others: only the memory guard applies
        return
    if have < minimum:
        _declared_too_much(header, what, described, minimum, have, source)


def _metaimage(path: Path, head: bytes, what: str) -> None:
    fields: dict[str, str] = {}
    offset = 0
    data_spec = None
    for raw in head.splitlines(keepends=True):
        offset += len(raw)
        line = raw.decode("latin-1").strip()
        key, sep, value = line.partition("=")
        if not sep:
            continue
        key = key.strip().lower()
        fields[key] = value.strip()
        if key == "elementdatafile":
            data_spec = value.strip()
            break
    if data_spec is None:
        return  # not a MetaImage header this reader understands; SimpleITK reports it
    dims = _ints(fields.get("dimsize", ""))
    size = _MET_SIZES.get(fields.get("elementtype", "").upper())
    channels = _ints(fields.get("elementnumberofchannels", "1")) or [1]
    compressed = fields.get("compresseddata", "false").lower() in ("true", "1")
    need = None
    if dims and size and all(n > 0 for n in dims):
        need = int(np.prod(dims, dtype=object)) * size * max(channels[0], 1)
        described = f"a {' x '.join(map(str, dims))} image of {size}-byte voxels"
        check_memory(path, need, what, described)
    spec = data_spec.split()
    encoding = "deflate" if compressed else "raw"
    if spec and spec[0].upper() == "LOCAL":
        files, have = [], path.stat().st_size - offset
    elif spec and spec[0].upper() == "LIST":
        files = _file_list(path, head, offset, what)
        sub = _ints(spec[1].upper().rstrip("D")) if len(spec) > 1 else None
        _check_list_count(path, what, files, dims, sub[0] if sub else (len(dims) - 1 if dims else None))
    else:
        files = _pattern_files(spec) or [data_spec]
    if files:
        have = 0
        for name in files:
            have += _check_data_file(path, _data_file_location(path, name, what), what)
    header_size = _ints(fields.get("headersize", "0")) or [0]
    if need is not None and header_size[0] >= 0:
        have -= header_size[0] if files else 0
        source = _data_file_location(path, files[0], what) if len(files) == 1 else None
        _check_payload(path, what, described, need, have, encoding, source)


def _nrrd(path: Path, head: bytes, what: str, detached: bool) -> None:
    if not head.startswith(b"NRRD"):
        return  # SimpleITK reports it
    fields: dict[str, str] = {}
    offset = 0
    data_spec = None
    lines = head.splitlines(keepends=True)
    for raw in lines[1:]:
        offset_before = offset
        offset += len(raw)
        line = raw.decode("latin-1").rstrip("\r\n")
        if not line.strip():
            break  # end of header: attached data follow
        if line.startswith("#") or ":=" in line:
            continue
        key, sep, value = line.partition(":")
        if not sep:
            continue
        key = key.strip().lower()
        fields[key] = value.strip()
        if key in ("data file", "datafile"):
            data_spec = value.strip()
            if data_spec.split() and data_spec.split()[0].upper() == "LIST":
                offset = offset_before + len(raw)
                break
    offset += len(lines[0])
    dims = _ints(fields.get("sizes", ""))
    size = _NRRD_SIZES.get(fields.get("type", "").lower())
    encoding = fields.get("encoding", "raw").lower()
    encoding = {"raw": "raw", "txt": "ascii", "text": "ascii", "ascii": "ascii", "hex": "hex",
                "gz": "deflate", "gzip": "deflate"}.get(encoding, encoding)
    need = None
    if dims and size and all(n > 0 for n in dims):
        count = int(np.prod(dims, dtype=object))
        need = count * size
        described = f"a {' x '.join(map(str, dims))} image of {size}-byte voxels"
        check_memory(path, need, what, described)
        if encoding == "ascii":
            need = 2 * count - 1
    skip = (_ints(fields.get("byte skip", fields.get("byteskip", "0"))) or [0])[0]
    if data_spec is None:
        if detached:
            return  # SimpleITK reports a detached header without a data file
        files, have = [], path.stat().st_size - offset
    else:
        spec = data_spec.split()
        if spec and spec[0].upper() == "LIST":
            files = _file_list(path, head, offset, what)
            sub = _ints(spec[1]) if len(spec) > 1 else None
            _check_list_count(path, what, files, dims, sub[0] if sub else (len(dims) - 1 if dims else None))
        else:
            files = _pattern_files(spec) or [data_spec]
        have = sum(_check_data_file(path, _data_file_location(path, name, what), what) for name in files)
    if need is not None and skip >= 0 and fields.get("line skip", fields.get("lineskip", "0")) in ("0", ""):
        have -= skip * max(len(files), 1)
        source = _data_file_location(path, files[0], what) if len(files) == 1 else None
        _check_payload(path, what, described, need, have, encoding, source)


def check_image_data_files(path: Path, suffix: str, what: str) -> None:
    """Check a MetaImage (``.mha``/``.mhd``) or NRRD (``.nrrd``/``.nhdr``) header against its data.

    Parameters
    ----------
    path : pathlib.Path
        The header (or single) file; it exists.
    suffix : str
        Its lower-case suffix.
    what : str
        What the file is, for messages (``"Label image"``).

    Raises
    ------
    VolregIOError
        A data file outside the header's folder (without ``VOLREG_ALLOW_EXTERNAL_DATA=1``), a
        missing or unreadable data file, data shorter than declared, or a declared image
        larger than :func:`max_image_bytes`.
    """
    check_readable(path, what)
    head = _read_head(path)
    if suffix in (".mha", ".mhd"):
        _metaimage(path, head, what)
    else:
        _nrrd(path, head, what, detached=suffix == ".nhdr")


# ----------------------------------------------------------------------------- meshes and VTK XML

# The least bytes one declared item can take in a file, uncompressed: a point is three numbers
# (binary: 3 x 4 bytes; ASCII: a digit and a separator each), a cell at least two (a count and an index).
_POINT_BYTES_ASCII = 6
_CELL_BYTES_ASCII = 4
# In memory: a point is three doubles; a cell (VTK's offsets and connectivity) at least 3 x 8 bytes.
_POINT_MEMORY = 24
_CELL_MEMORY = 24

_PLY_TYPES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _ply(path: Path, head: bytes, size: int, what: str) -> None:
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return  # VTK reports it
    lines = head[:end].decode("latin-1").splitlines()
    binary = any(line.split()[:2] in (["format", "binary_little_endian"], ["format", "binary_big_endian"])
                 for line in lines if line.strip())
    elements: list[list] = []  # [name, count, bytes per row (binary, lower bound)]
    for line in lines:
        words = line.split()
        if words[:1] == ["element"] and len(words) >= 3:
            count = _ints(words[2])
            if count is None or count[0] < 0:
                raise VolregIOError(f"Mesh `{path}` declares element {excerpt(words[1], quote=False)} with count "
                                    f"{excerpt(words[2])}; expected a count.")
            elements.append([words[1], count[0], 0])
        elif words[:1] == ["property"] and elements:
            if words[1:2] == ["list"] and len(words) >= 3:
                elements[-1][2] += _PLY_TYPES.get(words[2], 1)  # the list's length, at least
            elif len(words) >= 2:
                elements[-1][2] += _PLY_TYPES.get(words[1], 1)
    data = size - (end + len(b"end_header\n"))
    need = 0
    memory = 0
    for name, count, row in elements:
        need += count * (row if binary else 2)  # ASCII: at least a digit and a line end per row
        memory += count * (_POINT_MEMORY if name == "vertex" else _CELL_MEMORY)
    described = ", ".join(f"{count:,} {name} elements" for name, count, _ in elements) or "no elements"
    check_memory(path, memory, what, described)
    if need > data:
        _declared_too_much(path, what, described, need, max(data, 0))


_LEGACY_SECTION = re.compile(rb"^(POINTS|VERTICES|LINES|POLYGONS|TRIANGLE_STRIPS|CELLS|CELL_TYPES|POINT_DATA|CELL_DATA)"
                             rb"[ \t]+(\d+)", re.MULTILINE)
_VTK_TYPES = {b"bit": 1, b"unsigned_char": 1, b"char": 1, b"short": 2, b"unsigned_short": 2, b"int": 4,
              b"unsigned_int": 4, b"long": 8, b"unsigned_long": 8, b"vtktypeint64": 8, b"vtktypeuint64": 8,
              b"float": 4, b"double": 8}


def _legacy_vtk(path: Path, head: bytes, size: int, what: str) -> None:
    lines = head.split(b"\n", 4)
    if len(lines) < 4 or not lines[0].startswith(b"# vtk DataFile"):
        return  # VTK reports it
    binary = lines[2].strip().upper() == b"BINARY"
    need = 0
    memory = 0
    parts = []
    for match in _LEGACY_SECTION.finditer(head):
        keyword, count = match.group(1), int(match.group(2))
        if keyword == b"POINTS":
            rest = head[match.end():match.end() + 40].split(b"\n", 1)[0].split()
            item = _VTK_TYPES.get(rest[0].lower(), 4) if rest else 4
            need += count * (3 * item if binary else _POINT_BYTES_ASCII)
            memory += count * _POINT_MEMORY
            parts.append(f"{count:,} points")
        elif keyword in (b"POINT_DATA", b"CELL_DATA"):
            continue  # counts of points or cells already declared
        else:
            # a cell: at least one index (4 bytes binary; a digit and a separator in ASCII)
            need += count * (4 if binary else 2)
            memory += count * _CELL_MEMORY
            parts.append(f"{count:,} {keyword.decode().lower()}")
    if not parts:
        return
    described = ", ".join(parts)
    check_memory(path, memory, what, described)
    if need > size:
        _declared_too_much(path, what, described, need, size)


_XML_ATTR = re.compile(rb'\b(NumberOfPoints|NumberOfVerts|NumberOfLines|NumberOfStrips|NumberOfPolys|NumberOfCells|'
                       rb'WholeExtent|Extent|compressor|format)\s*=\s*"([^"]*)"')


def _xml_ratio(head: bytes) -> int | None:
    """The best compression ratio the file's compressor can reach (1: none), or None for LZMA (unbounded)."""
    match = re.search(rb'compressor\s*=\s*"([^"]*)"', head)
    if not match:
        return 1
    name = match.group(1).lower()
    if b"zlib" in name:
        return DEFLATE_RATIO
    if b"lz4" in name:
        return LZ4_RATIO
    return None


def _xml_counts(head: bytes) -> tuple[int, int, tuple[int, ...] | None]:
    """Total points and cells declared by ``<Piece>`` elements, and the image extent's point counts."""
    points = cells = 0
    dims = None
    for piece in re.finditer(rb"<(Piece|ImageData)\b[^>]*>", head):
        for match in _XML_ATTR.finditer(piece.group(0)):
            key, value = match.group(1), match.group(2)
            if key in (b"WholeExtent", b"Extent"):
                ext = _ints(value.decode("latin-1"))
                if ext is not None and len(ext) == 6 and (key == b"WholeExtent" or dims is None):
                    dims = tuple(max(ext[2 * a + 1] - ext[2 * a] + 1, 0) for a in range(3))
            elif key == b"NumberOfPoints":
                points += int(value) if value.isdigit() else 0
            elif key.startswith(b"NumberOf"):
                cells += int(value) if value.isdigit() else 0
    return points, cells, dims


def _vtk_xml(path: Path, head: bytes, size: int, what: str) -> None:
    if b"<VTKFile" not in head[:4096]:
        return  # VTK reports it
    points, cells, _ = _xml_counts(head)
    described = f"{points:,} points and {cells:,} cells"
    check_memory(path, points * _POINT_MEMORY + cells * _CELL_MEMORY, what, described)
    ratio = _xml_ratio(head)
    if ratio is None:
        return
    need = (points * _POINT_BYTES_ASCII + cells * 2) // ratio
    if need > size:
        _declared_too_much(path, what, described, need, size)


def _stl(path: Path, head: bytes, size: int, what: str) -> None:
    if size < 84:
        return  # VTK reports it
    count = int.from_bytes(head[80:84], "little")
    ascii_stl = head[:5].lower() == b"solid" and size != 84 + 50 * count
    if ascii_stl:
        return  # ASCII STL: no declared count; VTK's memory grows with the file
    check_memory(path, count * (_CELL_MEMORY + 3 * _POINT_MEMORY), what, f"{count:,} triangles")
    if 84 + 50 * count > size:
        _declared_too_much(path, what, f"{count:,} triangles (binary STL)", 84 + 50 * count, size)


def check_mesh_sizes(path: Path, what: str) -> None:
    """Refuse a mesh whose header declares more points or cells than the file holds, or memory allows.

    Parameters
    ----------
    path : pathlib.Path
        An existing ``.vtk``, ``.vtp``, ``.ply`` or ``.stl`` file (other suffixes: nothing declared,
        nothing checked).
    what : str
        What the file is, for messages (``"Mesh"``, ``"Surface"``).

    Raises
    ------
    VolregIOError
        One line naming the file, what it declares and what it holds.
    """
    check_readable(path, what)
    suffix = path.suffix.lower()
    size = path.stat().st_size
    head = _read_head(path)
    if suffix == ".ply":
        _ply(path, head, size, what)
    elif suffix == ".vtk":
        _legacy_vtk(path, head, size, what)
    elif suffix in (".vtp", ".vtu"):
        _vtk_xml(path, head, size, what)
    elif suffix == ".stl":
        _stl(path, head, size, what)


def check_vti_size(path: Path, what: str) -> None:
    """Refuse a ``.vti`` file whose extent declares more voxels than the file holds or memory allows.

    Each voxel takes at least one byte (more when its arrays are wider); compressed data at
    most the best ratio of the file's compressor less.

    Raises
    ------
    VolregIOError
        One line naming the file, the extent's size and the bytes it holds.
    """
    check_readable(path, what)
    size = path.stat().st_size
    head = _read_head(path)
    if b"<VTKFile" not in head[:4096]:
        return  # VTK reports it
    _, _, dims = _xml_counts(head)
    if dims is None:
        return
    voxels = int(np.prod(dims, dtype=object))
    described = f"an extent of {' x '.join(map(str, dims))} points"
    check_memory(path, voxels, what, described)
    ratio = _xml_ratio(head)
    if ratio is None:
        return
    need = voxels // ratio
    if need > size:
        _declared_too_much(path, what, described, need, size)


_VTK_XML_TYPES = {b"int8": 1, b"uint8": 1, b"int16": 2, b"uint16": 2, b"int32": 4, b"uint32": 4, b"int64": 8,
                  b"uint64": 8, b"float32": 4, b"float64": 8}


def declared_vti(path: Path) -> tuple[tuple[int, int, int], int, int]:
    """What a ``.vti`` file's header declares: the points along each axis, the components of its
    first point array and the bytes of one of them (1 where the header does not say).

    Reads the start of the file only (:func:`check_vti_size` has refused what it cannot hold).
    """
    head = _read_head(path)
    _, _, dims = _xml_counts(head)
    array = re.search(rb"<PointData\b[^>]*>\s*<DataArray\b([^>]*)>", head)
    itemsize, components = 1, 1
    if array is not None:
        kind = re.search(rb'\btype\s*=\s*"([^"]*)"', array.group(1))
        count = re.search(rb'\bNumberOfComponents\s*=\s*"(\d+)"', array.group(1))
        itemsize = _VTK_XML_TYPES.get(kind.group(1).lower(), 1) if kind else 1
        components = max(int(count.group(1)), 1) if count else 1
    return (dims or (0, 0, 0)), components, itemsize


_GIFTI_TYPES = {"NIFTI_TYPE_UINT8": 1, "NIFTI_TYPE_INT8": 1, "NIFTI_TYPE_INT16": 2, "NIFTI_TYPE_UINT16": 2,
                "NIFTI_TYPE_INT32": 4, "NIFTI_TYPE_UINT32": 4, "NIFTI_TYPE_FLOAT32": 4, "NIFTI_TYPE_INT64": 8,
                "NIFTI_TYPE_UINT64": 8, "NIFTI_TYPE_FLOAT64": 8}
#: GIFTI's encodings under each of the names nibabel takes for them (in lower case).
_GIFTI_ENCODINGS = {
    **dict.fromkeys(("ascii", "gifti_encoding_ascii"), "ascii"),
    **dict.fromkeys(("b64bin", "gifti_encoding_b64bin", "base64binary"), "base64"),
    **dict.fromkeys(("b64gz", "gifti_encoding_b64gz", "gzipbase64binary"), "gzip"),
    **dict.fromkeys(("external", "gifti_encoding_extbin", "externalfilebinary"), "external"),
}


def _gifti_arrays(text: bytes) -> list[dict[str, str]]:
    """The attributes of each ``<DataArray>`` of a GIFTI file (names in lower case), as nibabel reads them.

    Parsed by expat, nibabel's own parser, so that what is checked is what nibabel will act on:
    attributes in single quotes, character references (``&#46;&#46;/``) and entities are read
    alike.  A file that is not well-formed gives the arrays before the fault (nibabel then fails
    there too, but may have read those arrays' data).
    """
    from xml.parsers import expat

    arrays: list[dict[str, str]] = []

    def start(name: str, attrs: dict[str, str]) -> None:
        if name.lower() == "dataarray":
            arrays.append({k.lower(): v for k, v in attrs.items()})

    parser = expat.ParserCreate()
    parser.StartElementHandler = start
    try:
        parser.Parse(text, True)
    except expat.ExpatError:
        pass  # nibabel reports it
    return arrays


def check_gifti_sizes(path: Path, what: str) -> None:
    """Refuse a GIFTI file whose data arrays declare more than it holds, or than memory allows,
    or whose external data file lies outside its folder (without ``VOLREG_ALLOW_EXTERNAL_DATA=1``).

    Raises
    ------
    VolregIOError
        One line naming the file and what it declares.
    """
    check_readable(path, what)
    size = path.stat().st_size
    with open(path, "rb") as fh:
        text = fh.read()  # GIFTI is XML read whole by nibabel anyway; this is the file's own size
    need = memory = 0
    parts = []
    for attrs in _gifti_arrays(text):
        encoding = _GIFTI_ENCODINGS.get(attrs.get("encoding", "").strip().lower(), "ascii")
        source = None
        if encoding == "external":
            # before anything else about the array: nibabel reads the file wherever the name leads
            source = _data_file_location(path, attrs.get("externalfilename", ""), what)
        dims = [int(attrs[k]) for k in ("dim0", "dim1", "dim2") if k in attrs and attrs[k].strip().lstrip("-").isdigit()]
        if not dims:
            continue
        if any(n < 0 for n in dims):
            raise VolregIOError(f"{what} `{path}` has a data array of dimensions {dims}; expected sizes of at least 0.")
        item = _GIFTI_TYPES.get(attrs.get("datatype", "").upper(), 4)
        nbytes = int(np.prod(dims, dtype=object)) * item
        memory += nbytes
        parts.append(" x ".join(map(str, dims)))
        if encoding == "external":
            offset = _ints(attrs.get("externalfileoffset", "") or "0") or [0]
            have = _check_data_file(path, source, what) - offset[0]
            if have < nbytes:
                _declared_too_much(path, what, f"a data array of {parts[-1]}", nbytes, max(have, 0), source)
        elif encoding == "gzip":
            need += nbytes // DEFLATE_RATIO
        elif encoding == "base64":
            need += nbytes
        else:  # ASCII: a digit and a separator per value
            need += 2 * (nbytes // item)
    described = "data arrays of " + ", ".join(parts) if parts else "no data arrays"
    check_memory(path, memory, what, described)
    if need > size:
        _declared_too_much(path, what, described, need, size)


# ----------------------------------------------------------------------------- .npz archives


def check_npz(fh, path: Path | str, what: str) -> None:
    """Refuse an ``.npz`` archive whose members would inflate or allocate more than they hold.

    Reads only the zip directory and each member's ``.npy`` header: a member's declared shape
    and dtype must fill exactly the bytes the directory says it inflates to, those must be within
    the best ratio deflate can reach of its compressed bytes, and all members together within
    :func:`max_image_bytes`.  Archives that are not zip files are left to the caller's reader.

    Parameters
    ----------
    fh : binary file object
        The open archive (its position is restored).
    path : path-like
        Its name, for messages.
    what : str
        What the file is (``"Warp model"``).

    Raises
    ------
    VolregIOError
        One line naming the file and the offending member.
    """
    import zipfile

    start = fh.tell()
    try:
        try:
            archive = zipfile.ZipFile(fh)
        except (zipfile.BadZipFile, OSError, ValueError, EOFError):
            return  # not a zip archive: the reader says so
        with archive:
            infos = archive.infolist()
            total = sum(info.file_size for info in infos)
            check_memory(Path(path), total, what, f"{len(infos)} members inflating to {total:,} bytes")
            for info in infos:
                member = info.filename
                if info.file_size > max(info.compress_size, 1) * DEFLATE_RATIO + 1024:
                    raise VolregIOError(
                        f"{what} `{path}` member `{member}` declares {info.file_size:,} bytes from "
                        f"{info.compress_size:,} compressed; expected at most {DEFLATE_RATIO}:1 (a damaged or "
                        "crafted archive)."
                    )
                if not member.endswith(".npy"):
                    continue
                try:
                    with archive.open(info) as member_fh:
                        version = np.lib.format.read_magic(member_fh)
                        if version == (1, 0):
                            shape, _, dtype = np.lib.format.read_array_header_1_0(member_fh)
                        else:
                            shape, _, dtype = np.lib.format.read_array_header_2_0(member_fh)
                        header_end = member_fh.tell()
                except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib_error) as exc:
                    raise VolregIOError(
                        f"{what} `{path}` member `{member}` has no valid .npy header: "
                        f"{exception_text(exc)}."
                    ) from None
                if dtype.hasobject:
                    continue  # refused by the reader (no pickle)
                nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
                if nbytes > info.file_size - header_end:
                    raise VolregIOError(
                        f"{what} `{path}` member `{member}` declares shape {tuple(shape)} of {dtype} "
                        f"({nbytes:,} bytes) but holds {max(info.file_size - header_end, 0):,}; expected an "
                        "array that fills its member."
                    )
    finally:
        fh.seek(start)
