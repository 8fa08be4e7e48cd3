"""Protocols: named, validated presets of every setting, read from TOML.

A protocol file has the sections ``[protocol]`` (``name``, ``description``),
``[surface]`` (:class:`SurfaceSettings`) and ``[warp]``
(:class:`~volreg.pipeline.WarpSettings`).  Keys left out take their defaults;
an unknown section or key, or a value of the wrong type, is an error naming it.
Presets ship in the repository's ``protocols/`` folder; TOML is parsed with the
standard library's safe parser (``tomllib``; ``tomli`` before Python 3.11).
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

from .pipeline import WarpSettings

__all__ = [
    "Protocol",
    "ProtocolError",
    "SurfaceSettings",
    "load_protocol",
    "PROTOCOL_DIR",
    "replace_settings",
    "protocol_to_toml",
]

def _protocol_dir() -> Path:
    """The shipped presets: ``volreg/protocols`` in an installed wheel (package data,
    mapped from the repository's top-level ``protocols/`` by ``pyproject.toml``), else
    the repository's ``protocols/`` (source checkout, editable install)."""
    installed = Path(__file__).resolve().parent / "protocols"
    return installed if installed.is_dir() else Path(__file__).resolve().parent.parent / "protocols"


#: Where the shipped presets live.
PROTOCOL_DIR = _protocol_dir()


class ProtocolError(ValueError):
    """A protocol file that cannot be used: unreadable, unknown key, bad value."""


@dataclass(frozen=True)
class SurfaceSettings:
    """How label surfaces and their implicit surfaces are made.

    Attributes
    ----------
    smoothing : float, voxels
        Gaussian blur of each mask before contouring (largest spacing as unit).
    min_width_voxels : float, voxels
        Finest kernel width of the implicit surfaces.
    distance_weight : float
        Weight, relative to a label's implicit surface, of its voxel signed-distance
        feature (:class:`~volreg.distance_maps.VoxelDistance`, not in the paper) in the
        locational cost; it also covers labels too small or fragmented for a surface.
        0 = off (implicit surfaces only, as in the paper).
    distance_clip : float, voxels
        The voxel signed distances are clipped to +- this.
    distance_smoothing : float, voxels
        Gaussian blur of the clipped voxel signed distances.
    """

    smoothing: float = 1.0
    min_width_voxels: float = 4.0
    distance_weight: float = 2.0
    distance_clip: float = 3.0
    distance_smoothing: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.smoothing) and 0 <= self.smoothing <= 10):
            raise ValueError(f"Expected `smoothing` in [0, 10] voxels, got {self.smoothing}.")
        if not (math.isfinite(self.min_width_voxels) and self.min_width_voxels > 0):
            raise ValueError(f"Expected a positive `min_width_voxels`, got {self.min_width_voxels}.")
        if not (math.isfinite(self.distance_weight) and self.distance_weight >= 0):
            raise ValueError(f"Expected `distance_weight` >= 0, got {self.distance_weight}.")
        if not (math.isfinite(self.distance_clip) and self.distance_clip > 0):
            raise ValueError(f"Expected a positive `distance_clip` (voxels), got {self.distance_clip}.")
        if not (math.isfinite(self.distance_smoothing) and 0 <= self.distance_smoothing <= 10):
            raise ValueError(f"Expected `distance_smoothing` in [0, 10] voxels, got {self.distance_smoothing}.")


@dataclass(frozen=True)
class Protocol:
    """Every setting of a run, by section."""

    name: str = "default"
    description: str = ""
    surface: SurfaceSettings = field(default_factory=SurfaceSettings)
    warp: WarpSettings = field(default_factory=WarpSettings)

    def to_dict(self) -> dict[str, Any]:
        """Plain data (for reports and saved models)."""
        return dataclasses.asdict(self)


def _section(cls, values: Mapping[str, Any], where: str):
    """Build the dataclass ``cls`` from a TOML table, checking keys and types."""
    if not isinstance(values, Mapping):
        raise ProtocolError(f"Expected [{where}] to be a table, got {type(values).__name__}.")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in values.items():
        if key not in fields:
            raise ProtocolError(f"Unknown setting `{where}.{key}`; expected one of: {', '.join(sorted(fields))}.")
        want = fields[key].type if isinstance(fields[key].type, str) else fields[key].type.__name__
        if "int" in want and "float" not in want:
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif "float" in want:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            value = float(value) if ok else value
        else:
            ok = isinstance(value, str)
        if not ok:
            raise ProtocolError(f"Expected `{where}.{key}` to be {want.replace(' | None', '')}, got {value!r}.")
        kwargs[key] = value
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ProtocolError(f"In [{where}]: {exc}") from None


def load_protocol(name_or_path: str | os.PathLike[str] = "default") -> Protocol:
    """Read a protocol: a preset name (``protocols/<name>.toml``) or a path to a TOML file.

    Raises
    ------
    ProtocolError
        One line naming the file and the problem.
    """
    text = str(name_or_path)
    path = Path(text) if (text.endswith(".toml") or os.sep in text) else PROTOCOL_DIR / f"{text}.toml"
    if not path.is_file():
        presets = sorted(p.stem for p in PROTOCOL_DIR.glob("*.toml"))
        raise ProtocolError(f"Protocol `{text}` not found: expected a .toml file or a preset ({', '.join(presets)}).")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ProtocolError(f"Protocol `{path}` is not valid TOML: {exc}.") from None
    unknown = set(data) - {"protocol", "surface", "warp"}
    if unknown:
        raise ProtocolError(f"Unknown section [{sorted(unknown)[0]}] in `{path}`; expected [protocol], [surface], [warp].")
    head = data.get("protocol", {})
    if not isinstance(head, Mapping) or set(head) - {"name", "description"}:
        extra = sorted(set(head) - {"name", "description"}) if isinstance(head, Mapping) else ["?"]
        raise ProtocolError(f"Unknown setting `protocol.{extra[0]}` in `{path}`; expected name, description.")
    try:
        return Protocol(
            name=str(head.get("name", path.stem)),
            description=str(head.get("description", "")),
            surface=_section(SurfaceSettings, data.get("surface", {}), "surface"),
            warp=_section(WarpSettings, data.get("warp", {}), "warp"),
        )
    except ProtocolError as exc:
        raise ProtocolError(f"{exc} (in `{path}`)") from None


def replace_settings(protocol: Protocol, warp: Mapping[str, Any], *, name: str | None = None) -> Protocol:
    """A copy of ``protocol`` with some ``[warp]`` settings replaced, validated as a file's would be.

    Raises
    ------
    ProtocolError
        An unknown key or a bad value, named.
    """
    current = {k: v for k, v in dataclasses.asdict(protocol.warp).items() if v is not None}
    current.update(warp)
    return dataclasses.replace(protocol, name=protocol.name if name is None else name,
                               warp=_section(WarpSettings, current, "warp"))


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'


def protocol_to_toml(protocol: Protocol, *, comment: str = "") -> str:
    """The protocol as TOML text that :func:`load_protocol` reads back to an equal ``Protocol``.

    Settings that are ``None`` (derived from the data) are written as comments.
    """
    lines = [f"# {line}" for line in comment.splitlines()] if comment else []
    lines += ["[protocol]", f"name = {_toml_value(protocol.name)}", f"description = {_toml_value(protocol.description)}"]
    for section in ("surface", "warp"):
        lines += ["", f"[{section}]"]
        for key, value in dataclasses.asdict(getattr(protocol, section)).items():
            lines.append(f"# {key}: default (derived from the data)" if value is None else f"{key} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"
