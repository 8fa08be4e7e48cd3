"""What ``volreg register-surfaces``, ``morph`` and ``transfer`` share: reading surfaces, registering them, saved models."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from volreg.errors import UsageError
from volreg.io import write_mesh
from volreg.io.meshes import SurfaceData, read_surface
from volreg.morph import surface_normals
from volreg.register import register_surfaces
from volreg.warp.model import KernelWarp


def _read(path: Path, role: str) -> SurfaceData:
    """The surface (mesh or point cloud) at ``path``, with at least 10 vertices; ``role`` names it in errors."""
    data = read_surface(path)
    if len(data.vertices) < 10:
        raise UsageError(f"{role} `{path}` has {len(data.vertices)} vertices; expected at least 10 to fit a surface.")
    return data


def _register(source: SurfaceData, target: SurfaceData, protocol, landmarks, progress) -> KernelWarp:
    """The kernel warp of ``source`` onto ``target`` (:func:`volreg.register.register_surfaces`)."""
    src = (source.vertices, surface_normals(source.vertices, source.triangles, source.normals))
    tgt = (target.vertices, surface_normals(target.vertices, target.triangles, target.normals))
    return register_surfaces(src, tgt, landmarks=landmarks, settings=protocol.warp, progress=progress).warp


def _write_surface(path: Path, data: SurfaceData, vertices: np.ndarray, arrays: dict, force: bool) -> None:
    """``data``'s faces with moved ``vertices`` and per-vertex ``arrays``, written to ``path``."""
    write_mesh(vertices, data.triangles, path, point_data=arrays or None, force=force, allow_points=True)


def _load_model(result: Path) -> KernelWarp:
    """The 3-D warp saved in a ``volreg register-surfaces`` OUTDIR."""
    model = result / "model.npz"
    if not model.is_file():
        raise UsageError(f"`{result}` has no model.npz; expected an OUTDIR written by `volreg register-surfaces`.")
    warp = KernelWarp.load(model)
    if warp.dim != 3:
        raise UsageError(f"`{model}` is a {warp.dim}-D warp; expected a 3-D surface registration.")
    return warp
