"""The arguments of the public registration functions, checked where they come in.

Each function here takes what a caller naturally passes for one argument, returns it in the form
the pipeline works with (a path becomes the label volume it holds, a preset name the protocol),
and refuses anything else in one line naming the argument and what it takes, before any work
starts: an argument of the wrong kind as :class:`~volreg.errors.ArgumentTypeError` (a
``TypeError``), a value out of reach as :class:`~volreg.errors.RegistrationInputError` (a
``ValueError``).  Without them, a list given for a volume ended in ``AttributeError: 'list'
object has no attribute 'ndim'`` somewhere inside, and a label 1.5 was taken as 1.
"""

from __future__ import annotations

import numbers
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Callable

import numpy as np

from volreg.errors import ArgumentTypeError, RegistrationInputError
from volreg.grid import LabelVolume
from volreg.io.protocol import load_protocol
from volreg.settings import Protocol, WarpSettings

__all__ = ["bool_argument", "callable_argument", "drive_labels_argument", "label_volume_argument",
           "landmarks_argument", "mapping_argument", "path_argument", "protocol_argument", "warp_settings_argument"]


def _described(value: Any) -> str:
    """A value as a message names it: its type, and an array's shape or a short repr."""
    if value is None:
        return "None"
    if isinstance(value, np.ndarray):
        return f"ndarray of shape {value.shape}"
    text = repr(value)
    return f"{type(value).__name__} {text if len(text) <= 60 else text[:57] + '...'}"


def _is_path(value: Any) -> bool:
    return isinstance(value, (str, os.PathLike))


def label_volume_argument(value: Any, name: str) -> LabelVolume:
    """A label volume, or the path of a label image (read with :func:`volreg.io.read_labels`).

    Raises
    ------
    ArgumentTypeError
        Anything else (an array without its geometry, a list, ``None``).
    VolregIOError
        A path that does not hold a readable label image.
    """
    if isinstance(value, LabelVolume):
        return value
    if _is_path(value):
        from volreg.io import read_labels  # SimpleITK and nibabel: only when a file is to be read

        return read_labels(value)
    hint = (" (an array has no geometry: wrap it as volreg.LabelVolume(array, origin, spacing, direction))"
            if isinstance(value, (np.ndarray, list, tuple)) else "")
    raise ArgumentTypeError(f"Expected `{name}` to be a LabelVolume or the path of a label image, got "
                            f"{_described(value)}{hint}.")


def protocol_argument(value: Any, name: str = "protocol") -> Protocol:
    """A protocol: ``None`` (the default preset), a :class:`~volreg.settings.Protocol`, or a preset
    name or TOML path (read with :func:`volreg.io.protocol.load_protocol`).

    Raises
    ------
    ArgumentTypeError
        Anything else (a section's settings alone, a dict).
    ProtocolError
        A name that is no preset, or a file that is no valid protocol.
    """
    if value is None:
        return load_protocol("default")
    if isinstance(value, Protocol):
        return value
    if _is_path(value):
        return load_protocol(value)
    hint = (" (a section's settings go into a Protocol: dataclasses.replace(volreg.load_protocol(), "
            f"{_section_of(value)}=...))" if _section_of(value) else "")
    raise ArgumentTypeError(f"Expected `{name}` to be a Protocol, a preset name or the path of a protocol file, "
                            f"got {_described(value)}{hint}.")


def _section_of(value: Any) -> str | None:
    """The Protocol field that holds settings of ``value``'s class, if any."""
    from volreg.settings import LinearSettings, OutputSettings, ReviewSettings, SurfaceSettings

    sections = {SurfaceSettings: "surface", WarpSettings: "warp", LinearSettings: "linear",
                ReviewSettings: "review", OutputSettings: "outputs"}
    return sections.get(type(value))


def warp_settings_argument(value: Any, name: str = "settings") -> WarpSettings:
    """The warp settings: a :class:`~volreg.settings.WarpSettings`, or a protocol (its ``warp``
    section) as :func:`protocol_argument` takes one.

    Raises
    ------
    ArgumentTypeError, ProtocolError
        As :func:`protocol_argument`.
    """
    if isinstance(value, WarpSettings):
        return value
    if value is None or isinstance(value, Protocol) or _is_path(value):
        return protocol_argument(value, name).warp
    raise ArgumentTypeError(f"Expected `{name}` to be WarpSettings, a Protocol or a preset name, got "
                            f"{_described(value)}.")


def drive_labels_argument(value: Any, name: str = "drive_labels") -> list[int] | None:
    """Integer labels: ``None``, or a sequence (or 1-D array) of integers (or of floats with
    integral values, as an array of labels read as floats holds them).

    Raises
    ------
    ArgumentTypeError
        A single number, a string, a mapping, or items that are not numbers (true/false included).
    RegistrationInputError
        A label that is not a whole number (1.5) or not finite.
    """
    if value is None:
        return None
    if isinstance(value, (str, bytes, Mapping, numbers.Number)) or not hasattr(value, "__iter__"):
        raise ArgumentTypeError(f"Expected `{name}` to be a sequence of integer labels (e.g. [1, 3]), got "
                                f"{_described(value)}.")
    if isinstance(value, np.ndarray) and value.ndim != 1:
        raise ArgumentTypeError(f"Expected `{name}` to be a 1-D sequence of integer labels, got {_described(value)}.")
    labels = []
    for item in value:
        if isinstance(item, (bool, np.bool_)) or not isinstance(item, numbers.Real):
            raise ArgumentTypeError(f"Expected `{name}` to hold integer labels, got {_described(item)}.")
        if isinstance(item, numbers.Integral):
            labels.append(int(item))
            continue
        number = float(item)
        if not (np.isfinite(number) and number.is_integer()):
            raise RegistrationInputError(f"Expected `{name}` to hold integer labels, got {number!r} (a label is a "
                                         "whole number; it is not rounded).")
        labels.append(int(number))
    return labels


def landmarks_argument(value: Any, dim: int, name: str = "landmarks") -> tuple[np.ndarray, np.ndarray] | None:
    """Corresponding points: ``None``, or a pair of (L, ``dim``) arrays of finite coordinates, mm.

    Raises
    ------
    ArgumentTypeError
        Not a pair, or a pair of something else than numbers (paths: read them with
        :func:`volreg.io.landmarks.read_landmarks` first).
    RegistrationInputError
        Arrays of another shape, of different lengths, empty, or with NaN or Inf.
    """
    if value is None:
        return None
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise ArgumentTypeError(f"Expected `{name}` as a pair (points, partners) of (L, {dim}) arrays, got "
                                f"{_described(value)}.")
    arrays = []
    for item in value:
        if _is_path(item):
            raise ArgumentTypeError(f"Expected `{name}` as a pair of (L, {dim}) arrays, got the path {str(item)!r} "
                                    "(read a landmark file with volreg.read_landmarks).")
        array = np.asarray(item)
        if array.dtype.kind not in "iuf":
            raise ArgumentTypeError(f"Expected `{name}` as a pair of (L, {dim}) arrays of numbers, got an array of "
                                    f"dtype {array.dtype}.")
        arrays.append(array.astype(float))
    a, b = arrays
    if a.ndim != 2 or a.shape[1] != dim or a.shape != b.shape or len(a) == 0:
        raise RegistrationInputError(f"Expected `{name}` as two arrays of one shape (L, {dim}) with L >= 1 (for "
                                     f"{dim}-D volumes), got {a.shape} and {b.shape}.")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise RegistrationInputError(f"Expected finite `{name}` (mm), got NaN or Inf coordinates.")
    return a, b


def callable_argument(value: Any, name: str, what: str) -> Callable | None:
    """``None`` or a callable (``what`` says how it is called, for the message).

    Raises
    ------
    ArgumentTypeError
        Anything else.
    """
    if value is None or callable(value):
        return value
    raise ArgumentTypeError(f"Expected `{name}` to be None or a callable {what}, got {_described(value)}.")


def bool_argument(value: Any, name: str) -> bool:
    """``True`` or ``False`` (numpy's booleans too).

    Raises
    ------
    ArgumentTypeError
        Anything else (a number, a string: ``"no"`` would count as true).
    """
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise ArgumentTypeError(f"Expected `{name}` to be True or False, got {_described(value)}.")


def path_argument(value: Any, name: str, *, optional: bool = False) -> Path | None:
    """A path (``str`` or path-like) as a :class:`~pathlib.Path`; ``None`` where ``optional``.

    Raises
    ------
    ArgumentTypeError
        Anything else.
    """
    if value is None and optional:
        return None
    if _is_path(value):
        return Path(value)
    raise ArgumentTypeError(f"Expected `{name}` to be a path (str or pathlib.Path){' or None' if optional else ''}, "
                            f"got {_described(value)}.")


def mapping_argument(value: Any, name: str) -> Mapping | None:
    """``None`` or a mapping (a dict).

    Raises
    ------
    ArgumentTypeError
        Anything else.
    """
    if value is None or isinstance(value, Mapping):
        return value
    raise ArgumentTypeError(f"Expected `{name}` to be None or a mapping (a dict), got {_described(value)}.")
