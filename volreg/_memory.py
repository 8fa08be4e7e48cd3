"""The memory this machine has free, for refusing jobs up front that could not finish."""

from __future__ import annotations

import os

from volreg.errors import UsageError

__all__ = ["MAX_MEMORY", "available_bytes", "memory_limit"]

#: Environment variable that sets the memory a job may plan to use, GB (instead of what is free).
MAX_MEMORY = "VOLREG_MAX_MEMORY_GB"


def available_bytes() -> int | None:
    """MemAvailable from /proc/meminfo (Linux), else None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover - not Linux
        return None
    return None


def memory_limit() -> tuple[int | None, str]:
    """The memory a job may plan to use (bytes), and how messages name it.

    ``VOLREG_MAX_MEMORY_GB`` where set ("allowed (VOLREG_MAX_MEMORY_GB)"), else the memory
    available now (:func:`available_bytes`, "available"); ``None`` where neither is known.

    Raises
    ------
    UsageError
        ``VOLREG_MAX_MEMORY_GB`` that is not a positive number.
    """
    value = os.environ.get(MAX_MEMORY, "").strip()
    if not value:
        return available_bytes(), "available"
    try:
        gb = float(value)
    except ValueError:
        gb = float("nan")
    if not gb > 0 or gb == float("inf"):
        raise UsageError(f"Environment variable {MAX_MEMORY}={value!r} is not a positive number of GB.")
    return int(gb * 1024**3), f"allowed ({MAX_MEMORY})"
