"""Helpers shared by the test modules: small label volumes, files of them, the command line in-process.

Analytic shapes with known signed distances live in ``shapes.py``; fixtures that several modules
use are in ``conftest.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import nibabel as nib
import numpy as np

from volreg import LabelVolume
from volreg.cli import main
from volreg.io import write_labels
from volreg.io.fields import write_displacement

#: The blob volumes' grid: 40^3 voxels of 1.5 mm.
SHAPE = (40, 40, 40)
SPACING = np.array([1.5, 1.5, 1.5])

#: A protocol with a coarse finest warp level (8 mm), so that a registration takes a few seconds.
TEST_PROTOCOL = """
[protocol]
name = "test"
[warp]
min_width = 8.0
pad = 6.0
"""


def blob_volume(direction=np.eye(3), origin=(-30.0, -30.0, -30.0), spacing=SPACING, shape=SHAPE) -> LabelVolume:
    """An outer ellipsoidal blob (label 1) around an inner sphere (label 2), in world mm
    (the shapes are defined in world space, so every grid orientation holds the same objects)."""
    tmp = LabelVolume(np.zeros(shape, np.uint8), origin, spacing, direction)
    x = tmp.grid_points()
    centre = tmp.index_to_world((np.array(shape)[None] - 1) / 2.0)[0]
    d = x - centre
    outer = ((d / [21.0, 17.0, 14.0]) ** 2).sum(-1) < 1
    inner = (((d - [4.0, 2.0, 0.0]) / 6.5) ** 2).sum(-1) < 1
    arr = np.zeros(shape, np.uint8)
    arr[outer] = 1
    arr[inner] = 2
    return tmp.with_array(arr)


def cube(shape=(16, 16, 16), lo=4, hi=12, label=1, origin=(0.0, 0.0, 0.0)) -> LabelVolume:
    """A cube of ``label`` from voxel ``lo`` to ``hi`` on every axis, 1 mm voxels."""
    arr = np.zeros(shape, np.uint8)
    arr[lo:hi, lo:hi, lo:hi] = label
    return LabelVolume(arr, origin, (1.0, 1.0, 1.0), np.eye(3))


def write_nifti(path: Path, data: np.ndarray, affine=None, **header) -> Path:
    """``data`` saved by nibabel as NIfTI at ``path`` (RAS ``affine``, default the identity), with
    the given header fields set; returns ``path``."""
    img = nib.Nifti1Image(data, np.eye(4) if affine is None else affine)
    for key, value in header.items():
        img.header[key] = value
    nib.save(img, str(path))
    return path


def run(args, protocol: bool = True) -> int:
    """``volreg ARGS`` in-process; ``register`` gets the test protocol unless one is given."""
    args = [str(a) for a in args]
    if protocol and args[0] == "register" and "--protocol" not in args:
        path = Path(args[args.index("-o") + 1]).parent / "test-protocol.toml"
        path.write_text(TEST_PROTOCOL)
        args += ["--protocol", str(path)]
    return main(args)


def write_template_folder(root, template, warps, subjects, ids):
    """A folder as ``volreg template`` writes it: template.nii.gz, report.json, subjects/<id>/warp.nii.gz."""
    out = root / "template"
    (out / "subjects").mkdir(parents=True)
    write_labels(template, out / "template.nii.gz")
    rows = []
    for sid, u, s in zip(ids, warps, subjects):
        (out / "subjects" / sid).mkdir()
        write_displacement(u, template, out / "subjects" / sid / "warp.nii.gz")
        write_labels(s, root / f"{sid}.nii.gz")
        rows.append({"id": sid, "path": str(root / f"{sid}.nii.gz")})
    (out / "report.json").write_text(json.dumps({"command": "template", "subjects": rows}))
    return out
