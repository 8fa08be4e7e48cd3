"""``volreg consistency``: register both ways (or load both results), compose, report.

Thin: reading and validating inputs, calling :mod:`volreg.consistency` and
:func:`volreg._register_cli.run_registration`, writing outputs atomically.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from volreg import __version__
from volreg.cli._common import PROG, _remove_directories
from volreg.errors import UsageError
from volreg.evaluation.consistency import error_on_grid, error_summary, padded_region, round_trip_dice, round_trip_labels
from volreg.io import check_writable, read_labels, write_json, write_scalar
from volreg.io.fields import read_displacement
from volreg.warp.inverse import InverseWarp
from volreg.io.report_figure import write_error_figure
from volreg.progress import ProgressBars
from volreg.io.protocol import load_protocol
from volreg.features.label_surfaces import label_surfaces
from volreg.grid import LabelVolume
from volreg.warp.model import KernelWarp
from volreg.cli.register import OUTPUTS as REGISTER_OUTPUTS
from volreg.cli._common import _check_pair, _json_safe, _prepare_outdir, _sha256, _versions
from volreg.cli.register import run_registration

__all__ = ["run_consistency"]

OUTPUTS = ("consistency.json", "consistency_error.nii.gz", "consistency.png")


def _load_result(result: Path, grid: LabelVolume, option: str, grid_path: Path, role: str) -> KernelWarp:
    """The warp of a saved ``volreg register`` OUTDIR whose fixed grid must be ``grid``."""
    model = result / "model.npz"
    field = result / "warp.nii.gz"
    for p in (model, field):
        if not p.is_file():
            raise UsageError(f"{option} `{result}` has no `{p.name}`; expected an OUTDIR written by `volreg register`.")
    _, field_grid = read_displacement(field)
    if not field_grid.same_geometry(grid, atol=1e-3):
        raise UsageError(
            f"{option} `{result}` was registered on a grid of shape {field_grid.shape} (origin "
            f"{np.round(field_grid.origin, 3).tolist()} mm), not on the grid of {role} `{grid_path}` (shape "
            f"{grid.shape}, origin {np.round(grid.origin, 3).tolist()} mm); expected the result of "
            f"`volreg register {'A B' if role == 'A' else 'B A'}`."
        )
    warp = KernelWarp.load(model)
    if warp.dim != grid.ndim:
        raise UsageError(f"{option} `{model}` is a {warp.dim}-D warp but {role} `{grid_path}` is {grid.ndim}-D.")
    return warp


def _pad_of(warp: KernelWarp, volume: LabelVolume) -> float:
    """The padding (mm) the warp was fitted with; 10 % of the volume's extent if not recorded."""
    pad = warp.settings.get("pad")
    if isinstance(pad, (int, float)) and pad >= 0:
        return float(pad)
    return 0.1 * float(np.max(np.array(volume.shape) * volume.spacing))


def consistency_report(a: LabelVolume, b: LabelVolume, forward, backward, *, progress=None):
    """Figures of the consistency test and the error map on A's grid.

    Returns
    -------
    report : dict
        ``region`` (A's objects padded by the warp's ``pad``), ``labels`` (per
        label of A: the error over its voxels and at its surface vertices, and
        the round-trip Dice), ``surface_vertices`` (all labels together).
    error : (*a.shape) float ndarray, mm
    """
    voxel = float(np.mean(a.spacing))
    pad = _pad_of(forward, a)
    error = error_on_grid(forward, backward, a, progress=progress)
    region = padded_region(a, pad)
    labels = [int(v) for v in a.labels()]
    meshes = label_surfaces(a, labels, on_small="warn")
    _, back = round_trip_labels(a, b, forward, backward, progress=progress)
    dice = round_trip_dice(a.array, back, labels)
    per_label = {}
    all_vertex_errors = []
    for v in labels:
        entry = {"voxels": error_summary(error[a.array == v], voxel), "round_trip_dice": dice[v]}
        if v in meshes:
            vertex_error = np.linalg.norm(backward(forward(meshes[v].vertices)) - meshes[v].vertices, axis=1)
            entry["surface_vertices"] = error_summary(vertex_error, voxel)
            all_vertex_errors.append(vertex_error)
        per_label[str(v)] = entry
    report = {
        "definition": "|tau_BA(tau_AB(x)) - x| for x in A's world frame (LPS mm); voxels = mm / mean spacing of A",
        "voxel_mm": voxel,
        "pad_mm": pad,
        "region": error_summary(error[region], voxel),
        "surface_vertices": error_summary(np.concatenate(all_vertex_errors) if all_vertex_errors else [], voxel),
        "mean_round_trip_dice": float(np.mean(list(dice.values()))) if dice else None,
        "labels": per_label,
    }
    return report, error


def run_consistency(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    if (args.forward is None) != (args.backward is None):
        given, missing = ("--forward", "--backward") if args.backward is None else ("--backward", "--forward")
        raise UsageError(f"{given} was given without {missing}; expected both saved directions, or neither to register.")
    saved = args.forward is not None
    if saved and (args.protocol is not None or args.drive_labels is not None):
        raise UsageError("--protocol and --drive-labels apply only when registering; drop them with --forward/--backward.")
    a = read_labels(args.a)
    b = read_labels(args.b)
    _check_pair(a, b, args.a, args.b)
    if saved:
        forward = _load_result(args.forward, a, "--forward", args.a, "A")
        backward = _load_result(args.backward, b, "--backward", args.b, "B")
        if forward.dim != backward.dim:
            raise UsageError("--forward and --backward hold warps of different dimension.")
    protocol = None if saved else load_protocol(args.protocol or "default")

    outdir: Path = args.output
    created = _prepare_outdir(outdir, args.force)
    paths = {name: outdir / name for name in OUTPUTS}
    written: list[Path] = []
    registered: list[Path] = []
    try:
        check_writable(paths.values(), force=args.force)
        inputs = {"A": {"path": str(args.a), "sha256": _sha256(args.a)}, "B": {"path": str(args.b), "sha256": _sha256(args.b)}}
        if not saved:
            directions = {}
            symmetric = protocol.warp.lambda_consistency > 0
            for name, fixed, moving, fixed_key, moving_key in (("forward", a, b, "A", "B"), ("backward", b, a, "B", "A")):
                sub = outdir / name
                # symmetric option: the backward fit is pulled towards the forward warp's inverse
                prior = InverseWarp(KernelWarp.load(outdir / "forward" / "model.npz")) if symmetric and name == "backward" else None
                rep = run_registration(
                    fixed, moving, sub, protocol=protocol, drive_labels=args.drive_labels, force=args.force,
                    quiet=args.quiet, verbose=args.verbose, command="consistency",
                    inputs={"fixed": inputs[fixed_key], "moving": inputs[moving_key]}, prior=prior,
                )
                registered.append(sub)  # complete: removed again if a later step fails
                directions[name] = {"outdir": str(sub), "mean_dice": rep["mean_dice"], "seconds": rep["seconds"]}
            forward = KernelWarp.load(outdir / "forward" / "model.npz")
            backward = KernelWarp.load(outdir / "backward" / "model.npz")
        else:
            directions = {"forward": {"outdir": str(args.forward)}, "backward": {"outdir": str(args.backward)}}
        with ProgressBars(quiet=args.quiet) as progress:
            figures, error = consistency_report(a, b, forward, backward, progress=progress)
        report = {
            "volreg_version": __version__,
            "command": "consistency",
            "inputs": inputs,
            "directions": directions,
            # the symmetric option's weight, as recorded in the backward warp's settings
            "lambda_consistency": backward.settings.get("lambda_consistency", 0.0),
            **figures,
            "seconds": time.perf_counter() - start,
            "versions": _versions(),
        }
        write_scalar(error, a, paths["consistency_error.nii.gz"], force=args.force)
        written.append(paths["consistency_error.nii.gz"])
        r = figures["region"]
        write_error_figure(paths["consistency.png"], a.array, error, spacing=a.spacing, force=args.force,
                           title=f"volreg consistency: |tau_BA(tau_AB(x)) - x|, mean {r['mean_mm'] or 0:.3g} mm, "
                           f"p95 {r['p95_mm'] or 0:.3g} mm over A's padded labels")
        written.append(paths["consistency.png"])
        write_json(_json_safe(report), paths["consistency.json"], force=args.force)
        written.append(paths["consistency.json"])
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        for sub in registered:
            for name in REGISTER_OUTPUTS:
                (sub / name).unlink(missing_ok=True)
            if not any(sub.iterdir()):
                sub.rmdir()
        _remove_directories(created)
        raise
    r = report["region"]
    print(f"{PROG} consistency: inverse-consistency error over A's padded labels mean {r['mean_mm']:.4f} mm "
          f"({r['mean_voxels']:.4f} voxel), p95 {r['p95_mm']:.4f} mm, max {r['max_mm']:.4f} mm; round-trip Dice "
          f"{report['mean_round_trip_dice']:.3f}; {outdir} ({report['seconds']:.0f} s)")
    return 0
