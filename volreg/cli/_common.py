"""What every ``volreg`` command shares: argument types, output folders, input checks, reports."""

from __future__ import annotations

import argparse
import hashlib
import importlib.metadata
import math
import resource
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from volreg import __version__
from volreg.errors import UsageError, VolregError, VolregIOError
from volreg.grid import LabelVolume
from volreg.io.landmarks import read_landmarks

PROG = "volreg"


#: Errors that are the user's input, not volreg's bug: reported in one line, exit status 2.
EXPECTED_ERRORS = (VolregError,)


#: How many label values an error message lists before eliding the rest.
_MAX_LISTED = 30


def _label_list(text: str) -> list[int]:
    """``"1,3"`` -> ``[1, 3]``; for ``--labels``."""
    expected = "expected comma-separated non-zero integer labels such as 1,3"
    items = [t.strip() for t in text.split(",")]
    try:
        labels = [int(t) for t in items]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{expected}, got {text!r}") from None
    if 0 in labels:
        raise argparse.ArgumentTypeError(f"{expected}, got {text!r} (0 is the background)")
    duplicates = sorted({v for v in labels if labels.count(v) > 1})
    if duplicates:
        raise argparse.ArgumentTypeError(f"{expected}, got {text!r} (label {duplicates[0]} is listed twice)")
    return labels


def _float_at_least(lower: float, *, strict: bool, upper: float = math.inf):
    """An argparse type for a finite float ``> lower`` (``strict``) or ``>= lower``, and ``<= upper``."""
    relation = ">" if strict else ">="
    expected = f"a number {relation} {lower:g}" + (f" and <= {upper:g}" if upper < math.inf else "")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not math.isfinite(value) or (value <= lower if strict else value < lower) or value > upper:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value

    return parse


def _listing(values: Sequence[int]) -> str:
    shown = ", ".join(str(v) for v in values[:_MAX_LISTED])
    return shown + (f", ... ({len(values)} in all)" if len(values) > _MAX_LISTED else "")


def _warn(command: str, message: str) -> None:
    print(f"{PROG} {command}: warning: {message}", file=sys.stderr)


def _make_directory(path: Path) -> list[Path]:
    """Create ``path`` and any missing parents; return the directories created, outermost first."""
    if path.exists() and not path.is_dir():
        raise UsageError(f"Output directory `{path}` exists and is not a directory; expected a directory for -o.")
    missing = []
    p = path
    while not p.exists():
        missing.append(p)
        if p.parent == p:
            break
        p = p.parent
    created: list[Path] = []
    for d in reversed(missing):
        try:
            d.mkdir()
        except OSError as exc:
            _remove_directories(created)
            raise VolregIOError(f"Output directory `{d}` could not be created: {exc.strerror}.") from exc
        created.append(d)
    return created


def _remove_directories(created: list[Path]) -> None:
    """Remove directories this run created, innermost first, if they are empty."""
    for d in reversed(created):
        try:
            d.rmdir()
        except OSError:
            return


def _peak_rss_gb() -> float:
    """Peak resident memory of this process so far, GB (Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _versions() -> dict[str, str]:
    out = {"volreg": __version__, "python": sys.version.split()[0]}
    for name in ("numpy", "scipy", "SimpleITK", "nibabel", "scikit-image", "pyvista", "numba"):
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:  # pragma: no cover
            out[name] = "unknown"
    return out


def _world_box(volume: LabelVolume) -> tuple[np.ndarray, np.ndarray]:
    """LPS bounding box (mm) of the voxel domain of ``volume``."""
    corners = np.array(list(np.ndindex(*([2] * volume.ndim))), dtype=float)
    pts = volume.index_to_world(corners * (np.array(volume.shape) - 1)[None] + (corners - 0.5))
    return pts.min(axis=0), pts.max(axis=0)


#: Peak memory of a registration, estimated before it starts: a base plus bytes per voxel of the
#: two grids (measured on the frog demo: 1.71 GB peak for two grids of 1.76 M voxels).
_BASE_GB = 0.4


_BYTES_PER_VOXEL = 400


def _available_bytes() -> int | None:
    """MemAvailable from /proc/meminfo (Linux), else None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover - not Linux
        return None
    return None


def estimated_peak_gb(fixed: LabelVolume, moving: LabelVolume) -> float:
    """Rough peak memory (GB) of registering ``moving`` to ``fixed``."""
    voxels = int(np.prod(fixed.shape)) + int(np.prod(moving.shape))
    return _BASE_GB + _BYTES_PER_VOXEL * voxels / 1024**3


def _check_memory(fixed: LabelVolume, moving: LabelVolume, fixed_path, moving_path) -> None:
    """Refuse a job that would not fit in the memory available now, before it starts."""
    need = estimated_peak_gb(fixed, moving)
    available = _available_bytes()
    if available is not None and need * 1024**3 > available:
        raise UsageError(
            f"Registering `{moving_path}` ({moving.shape}) to `{fixed_path}` ({fixed.shape}) would need about "
            f"{need:.1f} GB of memory and {available / 1024**3:.1f} GB is available; expected smaller grids "
            "(downsample the label volumes) or more free memory."
        )


def _check_pair(fixed: LabelVolume, moving: LabelVolume, fixed_path, moving_path) -> None:
    if fixed.ndim != moving.ndim:
        raise UsageError(f"`{fixed_path}` is {fixed.ndim}-D and `{moving_path}` {moving.ndim}-D; expected two volumes of one dimension.")
    lo1, hi1 = _world_box(fixed)
    lo2, hi2 = _world_box(moving)
    if np.any(hi1 < lo2) or np.any(hi2 < lo1):
        raise UsageError(
            f"The grids of `{fixed_path}` and `{moving_path}` do not overlap in world (LPS) space "
            f"(fixed {np.round(lo1, 1).tolist()}..{np.round(hi1, 1).tolist()} mm, moving "
            f"{np.round(lo2, 1).tolist()}..{np.round(hi2, 1).tolist()} mm); check their origins and orientations."
        )
    _check_memory(fixed, moving, fixed_path, moving_path)


def _json_safe(value):
    """NaN and Inf -> None (JSON null), recursively; numpy scalars -> Python numbers."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def _prepare_outdir(outdir: Path, force: bool) -> list[Path]:
    """Create OUTDIR; refuse a non-empty one without ``force``."""
    if outdir.is_dir() and any(outdir.iterdir()) and not force:
        raise UsageError(f"Output directory `{outdir}` exists and is not empty; pass --force to write into it.")
    return _make_directory(outdir)


def _load_landmarks(args, fixed: LabelVolume | None = None, moving: LabelVolume | None = None):
    """The ``--landmarks`` pair, checked for equal counts and (given the volumes) to lie in their images."""
    if args.landmarks is None:
        return None
    a = read_landmarks(args.landmarks[0])
    b = read_landmarks(args.landmarks[1])
    if len(a) != len(b):
        raise UsageError(
            f"--landmarks: `{args.landmarks[0]}` has {len(a)} points and `{args.landmarks[1]}` {len(b)}; "
            "expected the same number, in corresponding order."
        )
    for points, volume, path, role in ((a, fixed, args.landmarks[0], "first"), (b, moving, args.landmarks[1], "second")):
        if volume is None:
            continue
        if points.shape[1] != volume.ndim:
            raise UsageError(f"--landmarks: `{path}` holds {points.shape[1]}-D points for a {volume.ndim}-D image.")
        lo, hi = _world_box(volume)
        outside = np.flatnonzero(np.any((points < lo) | (points > hi), axis=1))
        if outside.size:
            i = int(outside[0])
            raise UsageError(
                f"--landmarks: point {i + 1} of `{path}` ({', '.join(f'{v:.1f}' for v in points[i])} mm) lies outside the "
                f"{role} image's extent ({np.round(lo, 1).tolist()}..{np.round(hi, 1).tolist()} mm LPS); expected "
                "points inside it (check the file's coordinate system: LPS or RAS)."
            )
    return a, b
