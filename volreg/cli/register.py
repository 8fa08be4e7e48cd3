"""``volreg register``, ``apply``, ``protocols`` and ``demo``: parse -> io -> pipeline -> io.

Kept apart from :mod:`volreg.cli` (which wires the parser) so that each
command reads top to bottom.  Every output goes to a temporary name and is
renamed when complete; on any failure the files this run wrote are removed.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
import numpy as np
from volreg import __version__
from volreg.cli._common import PROG, _check_pair, _json_safe, _load_landmarks, _peak_rss_gb, _prepare_outdir, _remove_directories, _sha256, _versions
from volreg.errors import UsageError
from volreg.warp.field import displacement_on_grid, fields_on_grid
from volreg.warp.inverse import InverseWarp
from volreg.io import check_writable, read_image, read_labels, write_json, write_labels, write_scalar
from volreg.io.fields import read_displacement, write_displacement
from volreg.io.report_figure import write_report_figure
from volreg.evaluation.metrics import folded_fraction, label_scores
from volreg.warp.fit import check_folding
from volreg.register import register_labels
from volreg.progress import ProgressBars
from volreg.io.protocol import PROTOCOL_DIR, load_protocol
from volreg.settings import Protocol
from volreg.warp.resample import resample_image, resample_labels
from volreg.grid import LabelVolume
from volreg.warp.model import KernelWarp


OUTPUTS = (
    "warp.nii.gz", "inverse_warp.nii.gz", "warped.nii.gz", "model.npz", "jacobian.nii.gz", "report.json", "report.png",
)


def run_registration(
    fixed: LabelVolume,
    moving: LabelVolume,
    outdir: Path,
    *,
    protocol: Protocol,
    drive_labels=None,
    landmarks=None,
    force: bool,
    quiet: bool,
    inputs: dict,
    truth=None,
    verbose: bool = False,
    command: str = "register",
    prior=None,
) -> dict:
    """Register, write every output atomically into ``outdir`` (created), return the report."""
    created = _prepare_outdir(outdir, force)
    paths = {name: outdir / name for name in OUTPUTS}
    written: list[Path] = []
    stages = []
    try:
        check_writable(paths.values(), force=force)
        with ProgressBars(quiet=quiet) as progress:
            t_all = time.perf_counter()
            result = register_labels(fixed, moving, drive_labels=drive_labels, landmarks=landmarks,
                                     protocol=protocol, prior=prior, progress=progress)
            for st in result.stages:
                stages.append(dict(st, peak_rss_gb=round(_peak_rss_gb(), 3)))
            if verbose:
                def log(text: str) -> None:
                    print(f"{PROG} {command}: {text}", file=sys.stderr)

                log(f"driving labels {result.labels} (surfaces), {result.distance_labels} (voxel distance maps)")
                for note in result.skipped:
                    log(note)
                for st in result.stages:
                    log(f"{st['stage']}: {st['seconds']:.1f} s")
                for lev in result.log:
                    log(f"level {lev['level']}: width {lev['width']:.1f} mm, {lev['centres']} centres, "
                        f"{lev['samples']} samples, {lev['iterations']} iterations, objective "
                        f"{lev['objective_start']:.4g} -> {lev['objective']:.4g}, fold scale {lev['fold_scale']:.2f}, "
                        f"{lev['seconds']:.1f} s")

            t0 = time.perf_counter()
            grid = fixed.grid_points()  # (X, Y, Z, 3) mm, used below for every comparison
            u, jac = fields_on_grid(result.warp, fixed, progress=progress)
            points = grid + u
            check_folding(result.warp, fixed, jac, protocol.warp.max_folded_fraction)  # before more work
            warped_array = resample_labels(moving, points, method="label", progress=progress)
            stages.append(dict(stage="resample", seconds=time.perf_counter() - t0, peak_rss_gb=round(_peak_rss_gb(), 3)))

            t0 = time.perf_counter()
            inverse = InverseWarp(result.warp)
            u_inverse = displacement_on_grid(inverse, moving, progress=progress, stage="invert warp")
            stages.append(dict(stage="inverse", seconds=time.perf_counter() - t0, peak_rss_gb=round(_peak_rss_gb(), 3)))

            t0 = time.perf_counter()
            before = resample_labels(moving, grid, method="nearest")
            labels = sorted(set(fixed.labels().tolist()) | set(moving.labels().tolist()))
            scores_before = label_scores(fixed.array, before, labels, fixed.spacing)
            scores_after = label_scores(fixed.array, warped_array, labels, fixed.spacing)
            inside = fixed.array != 0
            report = {
                "volreg_version": __version__,
                "command": "register",
                "inputs": inputs,
                "direction": "pull-back: fixed point x corresponds to moving point x + u(x) (LPS mm)",
                "drive_labels": result.labels,
                "distance_map_labels": result.distance_labels,
                "skipped_labels": result.skipped,
                "labels": {
                    str(v): {"before": scores_before[v], "after": scores_after[v]} for v in labels
                },
                "mean_dice": {
                    "before": float(np.mean([scores_before[v]["dice"] for v in labels])),
                    "after": float(np.mean([scores_after[v]["dice"] for v in labels])),
                },
                "jacobian": {
                    "min": float(jac.min()),
                    "max": float(jac.max()),
                    "folded_fraction": folded_fraction(jac),
                    "folded_fraction_in_labels": folded_fraction(jac, inside),
                },
                "displacement_mm": {
                    "max": float(np.linalg.norm(u, axis=-1).max()),
                    "mean_in_labels": float(np.linalg.norm(u[inside], axis=-1).mean()) if inside.any() else 0.0,
                },
                "inverse": {
                    "method": "Newton iteration with the analytic Jacobian, on the moving grid",
                    "tolerance_mm": inverse.tol,
                    "max_residual_mm": inverse.max_residual,
                    "unconverged_voxels": inverse.unconverged,
                },
                "levels": result.log,
                "protocol": protocol.to_dict(),
                "versions": _versions(),
            }
            if truth is not None:
                gp = grid[inside]
                err = np.linalg.norm(points[inside] - truth(gp), axis=1)
                err0 = np.linalg.norm(truth(gp) - gp, axis=1)
                report["endpoint_error_mm"] = {
                    "mean": float(err.mean()), "p95": float(np.percentile(err, 95)), "max": float(err.max()),
                    "identity_mean": float(err0.mean()), "identity_p95": float(np.percentile(err0, 95)),
                }
            stages.append(dict(stage="metrics", seconds=time.perf_counter() - t0, peak_rss_gb=round(_peak_rss_gb(), 3)))

            t0 = time.perf_counter()
            result.warp.save(paths["model.npz"], force=force)
            written.append(paths["model.npz"])
            write_displacement(u, fixed, paths["warp.nii.gz"], force=force)
            written.append(paths["warp.nii.gz"])
            write_displacement(u_inverse, moving, paths["inverse_warp.nii.gz"], force=force)
            written.append(paths["inverse_warp.nii.gz"])
            write_labels(fixed.with_array(warped_array.astype(moving.array.dtype, copy=False)), paths["warped.nii.gz"], force=force)
            written.append(paths["warped.nii.gz"])
            write_scalar(jac, fixed, paths["jacobian.nii.gz"], force=force)
            written.append(paths["jacobian.nii.gz"])
            u_index = (u @ fixed.direction) / fixed.spacing  # LPS mm -> index units of the fixed grid
            write_report_figure(paths["report.png"], fixed.array, moving.array, warped_array, u_index,
                                fixed_spacing=fixed.spacing, moving_spacing=moving.spacing, force=force,
                                title=f"volreg register: mean Dice {report['mean_dice']['before']:.3f} -> "
                                f"{report['mean_dice']['after']:.3f}")
            written.append(paths["report.png"])
            stages.append(dict(stage="write", seconds=time.perf_counter() - t0, peak_rss_gb=round(_peak_rss_gb(), 3)))
            report["stages"] = stages
            report["seconds"] = time.perf_counter() - t_all
            report["peak_rss_gb"] = round(_peak_rss_gb(), 3)
            report = _json_safe(report)
            write_json(report, paths["report.json"], force=force)
            written.append(paths["report.json"])
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        _remove_directories(created)
        raise
    return report


def _summary_line(command: str, report: dict, outdir: Path) -> str:
    d = report["mean_dice"]
    line = (f"{PROG} {command}: mean Dice {d['before']:.3f} -> {d['after']:.3f} over {len(report['labels'])} labels, "
            f"folded {100 * report['jacobian']['folded_fraction']:.3f} %")
    if "endpoint_error_mm" in report:
        e = report["endpoint_error_mm"]
        line += (f", endpoint error mean {e['mean']:.2f} mm / p95 {e['p95']:.2f} mm "
                 f"(identity {e['identity_mean']:.2f} / {e['identity_p95']:.2f})")
    return line + f"; {len(OUTPUTS)} files in {outdir}{os.sep} ({report['seconds']:.0f} s)"


def _register(args: argparse.Namespace) -> int:
    protocol = load_protocol(args.protocol)
    fixed = read_labels(args.fixed)
    moving = read_labels(args.moving)
    _check_pair(fixed, moving, args.fixed, args.moving)
    landmarks = _load_landmarks(args, fixed, moving)
    inputs = {
        "fixed": {"path": str(args.fixed), "sha256": _sha256(args.fixed)},
        "moving": {"path": str(args.moving), "sha256": _sha256(args.moving)},
    }
    if landmarks is not None:
        inputs["landmarks"] = [{"path": str(p), "sha256": _sha256(p)} for p in args.landmarks]
    report = run_registration(fixed, moving, args.output, protocol=protocol, drive_labels=args.drive_labels,
                              landmarks=landmarks, force=args.force, quiet=args.quiet, inputs=inputs,
                              verbose=args.verbose)
    print(_summary_line("register", report, args.output))
    return 0


def _apply(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    reference = _reference_grid(args.reference)
    at = reference.grid_points()  # (X, Y, Z, 3) mm
    name = args.warp.name.lower()
    with ProgressBars(quiet=args.quiet) as progress:
        if name.endswith(".npz"):
            warp = KernelWarp.load(args.warp)
            if warp.dim != reference.ndim:
                raise UsageError(f"Model `{args.warp}` is {warp.dim}-D but --reference `{args.reference}` is {reference.ndim}-D.")
            u = displacement_on_grid(warp, reference, progress=progress)
        elif name.endswith(".nii") or name.endswith(".nii.gz"):
            u_field, grid = read_displacement(args.warp)
            if grid.ndim != reference.ndim:
                raise UsageError(f"Warp `{args.warp}` is {grid.ndim}-D but --reference `{args.reference}` is {reference.ndim}-D.")
            if grid.same_geometry(reference):
                u = u_field
            else:  # as ITK: the field is interpolated linearly at the reference voxels, zero outside it
                u = np.stack([resample_image(u_field[..., d], grid, at, order=1) for d in range(grid.ndim)], axis=-1)
        else:
            raise UsageError(f"MODEL_OR_WARP `{args.warp}` must be a model.npz or a displacement field .nii/.nii.gz.")
        points = at + u
        if args.interpolation in ("label", "nearest"):
            image = read_labels(args.image)
            out = resample_labels(image, points, method=args.interpolation, progress=progress)
            write_labels(reference.with_array(out.astype(image.array.dtype, copy=False)), args.output, force=args.force)
        else:
            array, origin, spacing, direction = read_image(args.image)
            geometry = LabelVolume(np.zeros(array.shape, np.uint8), origin, spacing, direction)
            values = resample_image(array, geometry, points, order=1 if args.interpolation == "linear" else 3)
            write_scalar(values, reference, args.output, force=args.force)
    print(f"{PROG} apply: {args.image} -> {args.output} ({args.interpolation}) in {time.perf_counter() - start:.1f} s")
    return 0


def _reference_grid(path: Path) -> LabelVolume:
    """The grid of any readable image (its values are not kept)."""
    array, origin, spacing, direction = read_image(path)
    return LabelVolume(np.zeros(array.shape, np.uint8), origin, spacing, direction)


def _protocols(args: argparse.Namespace) -> int:
    for path in sorted(PROTOCOL_DIR.glob("*.toml")):
        p = load_protocol(path)
        print(f"{p.name:<10} {p.description}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    from volreg.demo import frog_pair, frog_path

    protocol = load_protocol(args.protocol)
    path = Path(frog_path())
    full = read_labels(path)
    fixed, moving, truth = frog_pair(full, factors=(1, 1, 1) if args.full else (3, 3, 2))
    inputs = {"fixed": {"path": str(path), "sha256": _sha256(path), "resampled": "block mode 3x3x2" if not args.full else "none"},
              "moving": {"known_deformation": "Gaussian bumps, max 8 mm, seed 0"}}
    created = _prepare_outdir(args.output, args.force)
    try:
        write_labels(fixed, args.output / "fixed.nii.gz", force=args.force)
        write_labels(moving, args.output / "moving.nii.gz", force=args.force)
        report = run_registration(fixed, moving, args.output, protocol=protocol, force=True, quiet=args.quiet,
                                  inputs=inputs, truth=truth, verbose=args.verbose, command="demo")
    except BaseException:  # leave nothing half-done: the inputs written above go too
        for name in ("fixed.nii.gz", "moving.nii.gz"):
            (args.output / name).unlink(missing_ok=True)
        _remove_directories(created)
        raise
    print(_summary_line("demo", report, args.output))
    return 0
