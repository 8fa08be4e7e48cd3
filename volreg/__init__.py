"""volreg: kernel registration of labelled volumes and surfaces.

Implements Schölkopf, Steinke & Blanz, "Object Correspondence as a Machine
Learning Problem" (ICML 2005).  World coordinates are ITK physical space (LPS, mm).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("volreg")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

from .volume import LabelVolume  # noqa: E402

__all__ = ["LabelVolume", "__version__"]
