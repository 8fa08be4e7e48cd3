"""What ``volreg register-surfaces``, ``morph`` and ``transfer`` share: reading surfaces, registering them,
writing them (VTK in LPS, GIFTI in RAS), saved models and plausibility warnings."""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

from volreg.cli._common import _warn
from volreg.errors import UsageError

if TYPE_CHECKING:  # imported where used, so that the parsers load without numpy and the pipeline
    import numpy as np

    from volreg.evaluation.review import Finding
    from volreg.io.gifti import GiftiArrayMeta
    from volreg.io.meshes import SurfaceData
    from volreg.warp.model import KernelWarp

#: The frame of each kind of surface output, as the reports state it.
FRAMES = {".vtk": "LPS mm", ".gii": "RAS mm", ".csv": "LPS mm"}


def _add_data_options(parser, *roles: str) -> None:
    """``--source-data`` / ``--target-data FILE ...``: GIFTI per-vertex data files of SOURCE / TARGET."""
    for role in roles:
        parser.add_argument(f"--{role}-data", metavar="FILE", nargs="+", action="extend", type=Path, default=[],
                            help=f"GIFTI data files (.shape.gii .func.gii .label.gii) over the vertices of {role.upper()}; "
                            "each is an array named after its file (lh.thickness for lh.thickness.shape.gii)")


def _read(path: Path, role: str, data=()) -> SurfaceData:
    """The surface (mesh or point cloud) at ``path`` with the arrays of the GIFTI ``data`` files, with at
    least 10 vertices; ``role`` names it in errors."""
    from volreg.io.meshes import add_vertex_data, read_surface
    from volreg.pipeline.surface_inputs import MIN_VERTICES

    surface = read_surface(path)
    if len(surface.vertices) < MIN_VERTICES:
        raise UsageError(f"{role} `{path}` has {len(surface.vertices)} vertices; expected at least {MIN_VERTICES} to "
                         "fit a surface.")
    add_vertex_data(surface, data, f"{role} `{path}`")
    return surface


def _wants_gifti(args, source_path: Path) -> bool:
    """Whether to write GIFTI outputs: SOURCE is GIFTI, or ``--gifti`` was given."""
    from volreg.io.gifti import is_gifti

    return bool(getattr(args, "gifti", False)) or is_gifti(source_path)


def _register(source: SurfaceData, target: SurfaceData, protocol, landmarks, progress,
              names: tuple[object, object] = ("SOURCE", "TARGET")) -> KernelWarp:
    """The kernel warp of ``source`` onto ``target``, both checked first
    (:func:`volreg.pipeline.surfaces.register_surface_pair`)."""
    from volreg.pipeline.surfaces import register_surface_pair

    return register_surface_pair(source, target, protocol, landmarks, progress, names)


def _write_surface(path: Path, data: SurfaceData, vertices: np.ndarray, arrays: dict, force: bool) -> None:
    """``data``'s faces with moved ``vertices`` (LPS mm) and per-vertex ``arrays``: VTK/VTP in LPS."""
    from volreg.io import write_mesh

    write_mesh(vertices, data.triangles, path, point_data=arrays or None, force=force, allow_points=True)


def _write_gifti_surface(path: Path, data: SurfaceData, vertices: np.ndarray, force: bool) -> None:
    """``data``'s faces with moved ``vertices`` (LPS mm) as a GIFTI surface in RAS, with ``data``'s metadata."""
    from volreg.io.gifti import write_gifti

    write_gifti(vertices, data.triangles, path, meta=data.gifti, force=force)


def _is_label(surface: SurfaceData, name: str) -> bool:
    """Whether ``surface``'s array ``name`` holds labels: integers, or a GIFTI label array."""
    import numpy as np

    meta = surface.array_meta.get(name)
    return np.asarray(surface.arrays[name]).dtype.kind in "iub" or (meta is not None and meta.is_label)


def _data_meta(surface: SurfaceData, name: str) -> GiftiArrayMeta:
    """The GIFTI metadata of ``surface``'s array ``name`` (a bare one for arrays not read from GIFTI)."""
    from volreg.io.gifti import GiftiArrayMeta

    meta = surface.array_meta.get(name)
    if meta is not None:
        return meta
    return GiftiArrayMeta(kind="label" if _is_label(surface, name) else "shape")


def _data_file_name(stem: str, name: str, meta: GiftiArrayMeta) -> str:
    """``<stem>.<name>.<kind>.gii``, with characters unsafe in file names replaced by ``_``."""
    safe = re.sub(r"[^A-Za-z0-9._+-]", "_", name) or "array"
    return f"{stem}.{safe}.{meta.kind}.gii"


def _warn_findings(command: str, findings: list[Finding]) -> None:
    """One warning line on stderr per finding."""
    for finding in findings:
        _warn(command, finding.message)


def _check_result_kind(result: Path, option: str) -> None:
    """Refuse an OUTDIR whose report.json says another command than ``register-surfaces`` wrote it.

    A label-volume registration (``volreg register``) saves a 3-D ``model.npz`` too, of fixed
    points to moving points: taken for a surface registration it would carry values between
    unrelated surfaces without a word.  A folder without a report (a model copied alone), or
    with one that is not JSON, is left to the model's own checks.
    """
    import json

    from volreg.io.documents import parse_json

    report = result / "report.json"
    try:
        data = parse_json(report.read_text(encoding="utf-8"), f"{option} `{result}`: report.json", error=UsageError)
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return
    if not isinstance(data, dict):
        return
    command = data.get("command")
    inputs = data.get("inputs")
    labels = command == "register" or (command is None and isinstance(inputs, dict) and "fixed" in inputs)
    if labels:
        raise UsageError(f"{option} `{result}` is a label-volume registration (its report.json says `volreg "
                         "register`); expected a surface registration from `volreg register-surfaces`.")
    if isinstance(command, str) and command != "register-surfaces":
        raise UsageError(f"{option} `{result}` was written by `volreg {' '.join(command.split())[:40]}` (its "
                         "report.json says so); expected a surface registration from `volreg register-surfaces`.")


def _load_model(result: Path, option: str) -> KernelWarp:
    """The 3-D warp saved in a ``volreg register-surfaces`` OUTDIR (given as ``option``)."""
    from volreg.warp.model import KernelWarp

    model = result / "model.npz"
    if not model.is_file():
        raise UsageError(f"`{result}` has no model.npz; expected an OUTDIR written by `volreg register-surfaces`.")
    _check_result_kind(result, option)
    warp = KernelWarp.load(model)
    if warp.dim != 3:
        raise UsageError(f"`{model}` is a {warp.dim}-D warp; expected a 3-D surface registration.")
    return warp
