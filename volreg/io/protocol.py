"""Protocols: named, validated presets of every setting, read from TOML.

A protocol file has the sections ``[protocol]`` (``name``, ``description``),
``[surface]`` (:class:`~volreg.settings.SurfaceSettings`), ``[warp]``
(:class:`~volreg.settings.WarpSettings`), ``[linear]``
(:class:`~volreg.settings.LinearSettings`), ``[review]``
(:class:`~volreg.settings.ReviewSettings`) and ``[outputs]``
(:class:`~volreg.settings.OutputSettings`).  Keys left out take their defaults;
an unknown section or key, or a value of the wrong type, is an error naming it.
Presets ship in the repository's ``protocols/`` folder; TOML is parsed with the
standard library's safe parser (``tomllib``; ``tomli`` before Python 3.11).
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import Any, Mapping

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

from volreg.settings import (
    LinearSettings,
    OutputSettings,
    Protocol,
    ReviewSettings,
    SurfaceSettings,
    WarpSettings,
    settings_from_mapping,
)
from volreg.errors import ProtocolError, exception_text, excerpt
from volreg.io.documents import parse_toml

__all__ = ["PROTOCOL_DIR", "load_protocol", "protocol_to_toml"]


def _protocol_dir() -> Path:
    """The shipped presets: ``volreg/protocols`` in an installed wheel (package data,
    mapped from the repository's top-level ``protocols/`` by ``pyproject.toml``), else
    the repository's ``protocols/`` (source checkout, editable install)."""
    package = Path(__file__).resolve().parent.parent  # volreg/
    installed = package / "protocols"
    return installed if installed.is_dir() else package.parent / "protocols"


#: Where the shipped presets live.
PROTOCOL_DIR = _protocol_dir()

#: The settings sections of a protocol file, after ``[protocol]``: fields of :class:`~volreg.settings.Protocol`.
_SECTIONS = ("surface", "warp", "linear", "review", "outputs")
_SECTION_CLASSES = {"surface": SurfaceSettings, "warp": WarpSettings, "linear": LinearSettings,
                    "review": ReviewSettings, "outputs": OutputSettings, "protocol": None}


def load_protocol(name_or_path: str | os.PathLike[str] = "default") -> Protocol:
    """Read a protocol: a preset name (``protocols/<name>.toml``) or a path to a TOML file.

    Raises
    ------
    ProtocolError
        One line naming the file and the problem.
    """
    text = os.fsdecode(name_or_path)
    # A path (a PathLike, a folder in it, any suffix in any case: proto.TOML, proto.cfg) is a
    # file; a bare name a preset, or a file of that name where no preset has it.
    preset = PROTOCOL_DIR / f"{text}.toml"
    as_file = isinstance(name_or_path, os.PathLike) or os.sep in text or (os.altsep or os.sep) in text \
        or bool(Path(text).suffix) or text in (".", "..")
    try:
        as_file = as_file or (not preset.is_file() and Path(text).is_file())
    except OSError:  # e.g. a name longer than the system allows: reported below
        pass
    path = Path(text) if as_file else preset
    try:
        is_file, exists = path.is_file(), path.exists()
    except OSError as exc:  # e.g. a name longer than the system allows
        raise ProtocolError(f"Protocol `{excerpt(text, 80, quote=False)}` cannot be looked up: {exc.strerror or exc}.") from None
    if exists and not is_file:
        raise ProtocolError(f"Protocol `{path}` is a directory; expected a .toml file.")
    if not is_file:
        presets = sorted(p.stem for p in PROTOCOL_DIR.glob("*.toml"))
        raise ProtocolError(f"Protocol `{excerpt(text, 80, quote=False)}` is no such preset or file: "
                            f"expected a TOML file or a preset ({', '.join(presets)}).")
    try:
        raw = path.read_text(encoding="utf-8-sig")  # a byte-order mark (Windows editors) is not TOML
    except OSError as exc:
        raise ProtocolError(f"Protocol `{path}` could not be read: {exc.strerror or exc}.") from None
    except UnicodeDecodeError:
        raise ProtocolError(f"Protocol `{path}` is not UTF-8 text; expected a TOML file.") from None
    try:
        data = parse_toml(raw, f"Protocol `{path}`")
    except tomllib.TOMLDecodeError as exc:
        raise ProtocolError(f"Protocol `{path}` is not valid TOML: {exception_text(exc)}.") from None
    loose = sorted(k for k, v in data.items() if not isinstance(v, Mapping))
    if loose:
        owners = [s for s, cls in _SECTION_CLASSES.items()
                  if (loose[0] in ("name", "description") if cls is None else
                      loose[0] in {f.name for f in dataclasses.fields(cls)})]
        where = f"under [{owners[0]}]" if owners else "under a section"
        raise ProtocolError(f"Setting `{excerpt(loose[0], quote=False)}` in `{path}` lies outside any section; expected it {where} "
                            "(a [section] line above it).")
    unknown = set(data) - {"protocol", *_SECTIONS}
    if unknown:
        raise ProtocolError(f"Unknown section [{excerpt(sorted(unknown)[0], quote=False)}] in `{path}`; "
                            f"expected [protocol], {', '.join(f'[{s}]' for s in _SECTIONS)}.")
    head = data.get("protocol", {})
    if not isinstance(head, Mapping) or set(head) - {"name", "description"}:
        extra = sorted(set(head) - {"name", "description"}) if isinstance(head, Mapping) else ["?"]
        raise ProtocolError(f"Unknown setting `protocol.{excerpt(extra[0], quote=False)}` in `{path}`; expected name, description.")
    for key in ("name", "description"):
        if key in head and not isinstance(head[key], str):
            raise ProtocolError(f"Expected `protocol.{key}` to be a string (in quotes), got {excerpt(head[key])} (in `{path}`).")
    try:
        return Protocol(
            name=str(head.get("name", path.stem)),
            description=str(head.get("description", "")),
            surface=settings_from_mapping(SurfaceSettings, data.get("surface", {}), "surface"),
            warp=settings_from_mapping(WarpSettings, data.get("warp", {}), "warp"),
            linear=settings_from_mapping(LinearSettings, data.get("linear", {}), "linear"),
            review=settings_from_mapping(ReviewSettings, data.get("review", {}), "review"),
            outputs=settings_from_mapping(OutputSettings, data.get("outputs", {}), "outputs"),
        )
    except ProtocolError as exc:
        raise ProtocolError(f"{exc} (in `{path}`)") from None


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    return '"' + "".join(_TOML_ESCAPES.get(c, c if c >= " " and c != "\x7f" else f"\\u{ord(c):04x}")
                         for c in str(value)) + '"'


#: Characters a TOML basic string must escape (other control characters as ``\\uXXXX``).
_TOML_ESCAPES = {"\\": "\\\\", '"': '\\"', "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def protocol_to_toml(protocol: Protocol, *, comment: str = "") -> str:
    """The protocol as TOML text that :func:`load_protocol` reads back to an equal ``Protocol``.

    Settings that are ``None`` (derived from the data) are written as comments.
    """
    # a comment line ends at the line's end; control characters (other than tab) may not stand in it
    lines = [f"# {''.join(c if c >= ' ' or c == chr(9) else '?' for c in line)}" for line in comment.splitlines()] \
        if comment else []
    lines += ["[protocol]", f"name = {_toml_value(protocol.name)}", f"description = {_toml_value(protocol.description)}"]
    for section in _SECTIONS:
        lines += ["", f"[{section}]"]
        for key, value in dataclasses.asdict(getattr(protocol, section)).items():
            lines.append(f"# {key}: default (derived from the data)" if value is None else f"{key} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"
