"""A module imported at the first use of one of its attributes.

pyvista (with VTK) takes about a quarter of a second to import; ``volreg register`` on NIfTI
volumes never uses it, so the readers and writers of meshes and ``.vti`` images refer to it
through :class:`LazyModule` and pay the import only when they run.  (The standard library's
``importlib.util.LazyLoader`` would put a lazy module into ``sys.modules`` for every importer;
this stand-in affects only the modules that use it.)
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["LazyModule"]


class LazyModule:
    """Stands for the module ``name``; the first attribute looked up imports it.

    Parameters
    ----------
    name : str
        The module's import name, e.g. ``"pyvista"``.
    """

    def __init__(self, name: str) -> None:
        self._name = name

    def _module(self) -> ModuleType:
        return importlib.import_module(self._name)  # sys.modules after the first time

    def __getattr__(self, attr: str):
        return getattr(self._module(), attr)

    def __repr__(self) -> str:
        return f"<LazyModule {self._name!r}>"
