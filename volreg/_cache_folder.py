"""Where volreg has numba cache its compiled loops when no usual folder can be written.

Kept apart from :mod:`volreg._jit` (which imports numba) so that :mod:`volreg.precompile` can
look there without importing numba.
"""

from __future__ import annotations

import os
import tempfile

__all__ = ["fallback_cache_folder"]


def fallback_cache_folder() -> str:
    """The per-user folder under the system's temporary directory where :mod:`volreg._jit` has
    numba cache when neither the package's folder nor the user's cache folder can be written."""
    try:
        uid = os.getuid()
    except AttributeError:  # pragma: no cover - not on POSIX
        uid = "user"
    return os.path.join(tempfile.gettempdir(), f"volreg-numba-cache-{uid}")
