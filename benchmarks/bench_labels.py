"""Label-volume registration on the frog demo pair: volreg against ANTs SyN, side by side.

Run:  .venv/bin/python benchmarks/bench_labels.py [--repeats 3] [--peers] [--full]

The pair is `volreg demo`'s: pyvista's frog tissues block-downsampled to 3 mm (fixed; with --full
the native 1 x 1 x 1.5 mm grid, as `volreg demo --full`) and a copy deformed by a known smooth warp
of up to 8 mm (moving). Every method gets the same two label volumes; each run is a fresh process
(its own peak RSS). Reported per method: mean Dice over the labels (and over the labels of at least
100 voxels), endpoint error against the known warp at the fixed voxels inside the labels (mean, 95th
percentile, mm), folded fraction (det <= 0 over the grid), wall time and peak RSS; medians of the
repeats; below them the true warp's Dice (the moving volume is the fixed one resampled through it,
so labels of a few voxels do not come back whole even through the truth). With --peers the peers run
too, each on the label images as float with 2 threads: ANTs SyNOnly and SyN (affine + SyN; antspyx),
greedy (picsl_greedy: SSD, 100x50x20 iterations, smoothing 2 and 1 voxels) and elastix B-spline
(itk-elastix: its default 4-resolution B-spline map with a 12 mm final grid; `elastix-bspline-ms`
with mean squares, `elastix-bspline` with the map's mutual information). Peers' folded fractions
come from central differences of their displacement fields (ANTs SyNOnly: ANTs' own Jacobian).

Also measured once: label interpolation by per-label signed distances against nearest neighbour,
both through the *true* warp (so the only error is the interpolation), as Dice with the fixed labels.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np


LARGE = 100  # voxels: the "labels >= 100 voxels" Dice


def _pair():
    from volreg.demo import frog_pair, frog_path
    from volreg.io import read_labels

    full = os.environ.get("VOLREG_BENCH_FULL") == "1"  # set by --full for the child processes
    return frog_pair(read_labels(frog_path()), factors=(1, 1, 1) if full else (3, 3, 2))


def _scores(fixed, moving, positions, truth, det):
    from volreg.warp.resample import resample_labels

    warped = resample_labels(moving, positions)
    inside = fixed.array > 0
    x = fixed.grid_points()[inside]
    err = np.linalg.norm(positions[inside] - truth(x), axis=1)
    out = dict(epe_mean=float(err.mean()), epe_p95=float(np.percentile(err, 95)), folded=float(np.mean(det <= 0)))
    return out | _dice(fixed, warped)


def _dice(fixed, warped: np.ndarray) -> dict:
    """Mean Dice over the fixed labels, and over those of at least LARGE voxels: a generated
    moving volume keeps labels of a few dozen voxels only approximately (resampled once), so
    that even the true warp brings some back with Dice 0 (see BENCHMARKS.md)."""
    from volreg.evaluation.metrics import dice

    scores = {v: dice(fixed.array == v, warped == v) for v in fixed.labels()}
    large = [d for v, d in scores.items() if np.count_nonzero(fixed.array == v) >= LARGE]
    return dict(dice=float(np.mean(list(scores.values()))), dice_large=float(np.mean(large)))


def _read_field(path) -> np.ndarray:
    from volreg.io.fields import read_displacement

    return read_displacement(path)[0]


def _det_from_field(u: np.ndarray, grid) -> np.ndarray:
    """det(I + du/dx) by central differences on an axis-aligned grid (the frog's), for peers
    that return only a displacement field."""
    if not np.allclose(grid.direction, np.eye(3)):
        raise SystemExit("expected an axis-aligned grid")
    jac = np.stack([np.stack(np.gradient(u[..., a], *grid.spacing), axis=-1) for a in range(3)], axis=-2)
    return np.linalg.det(jac + np.eye(3))


def _peer(method: str, fixed, moving, d: str):
    """Run a peer on the pair written as float NIfTI into folder ``d``: its displacement field
    on the fixed grid (LPS mm, pull-back) and det of its Jacobian there."""
    from volreg.io import write_labels

    f_path, m_path = os.path.join(d, "f.nii.gz"), os.path.join(d, "m.nii.gz")
    write_labels(fixed, f_path)
    write_labels(moving, m_path)
    if method in ("ants-SyNOnly", "ants-SyN"):  # SyN: affine then SyN, ANTs' default for a pair
        import ants

        f = ants.image_read(f_path, pixeltype="float")
        m = ants.image_read(m_path, pixeltype="float")
        reg = ants.registration(f, m, type_of_transform=method.split("-")[1], outprefix=os.path.join(d, "ants_"))
        if method == "ants-SyNOnly":
            return _read_field(reg["fwdtransforms"][0]), ants.create_jacobian_determinant_image(
                f, reg["fwdtransforms"][0]).numpy()
        # the composite (warp, then affine) as one displacement field on the fixed grid
        u = _read_field(ants.apply_transforms(f, m, reg["fwdtransforms"], compose=os.path.join(d, "comp")))
    elif method == "greedy":
        from picsl_greedy import Greedy3D

        Greedy3D().execute(f"-d 3 -threads 2 -i {f_path} {m_path} -o {d}/w.nii.gz -n 100x50x20 -m SSD -s 2vox 1vox")
        u = _read_field(f"{d}/w.nii.gz")
    elif method in ("elastix-bspline", "elastix-bspline-ms"):
        import itk

        f = itk.imread(f_path, itk.F)
        m = itk.imread(m_path, itk.F)
        params = itk.ParameterObject.New()
        pm = params.GetDefaultParameterMap("bspline", 4)  # 4 resolutions
        if method == "elastix-bspline-ms":
            pm["Metric"] = ["AdvancedMeanSquares"]  # same label values in both images
        pm["FinalGridSpacingInPhysicalUnits"] = ["12"]  # 4 voxels of 3 mm
        params.AddParameterMap(pm)
        # threads from ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS (main sets 2): number_of_threads=2
        # crashed itk-elastix 0.25.4 (ITK 5.4.7) on this pair (segmentation fault)
        _, tp = itk.elastix_registration_method(f, m, parameter_object=params, log_to_console=False)
        with contextlib.chdir(d):  # transformix also writes deformationField.nii into the working directory
            field = itk.transformix_deformation_field(m, tp)  # on the fixed grid, LPS mm, fixed -> moving
        u = np.ascontiguousarray(np.transpose(itk.array_from_image(field), (2, 1, 0, 3)), dtype=float)
    else:
        raise SystemExit(f"unknown method {method}")
    return u, _det_from_field(u, fixed)


def run_one(method: str) -> dict:
    fixed, moving, truth = _pair()
    t0 = time.perf_counter()
    if method.startswith("volreg"):
        from volreg.warp.field import fields_on_grid
        from volreg.pipeline.labels import register_labels
        from volreg.io.protocol import load_protocol

        import dataclasses

        # volreg-NAME[+key=value...]: a preset with settings overridden, e.g. volreg-default+alpha=20
        # (a [warp] key) or volreg-accurate+distance_smoothing=0.5 (a [surface] key).
        name, *overrides = method.split("-", 1)[1].split("+")
        protocol = load_protocol(name)
        for key, value in (o.split("=") for o in overrides):
            section = "surface" if key in {f.name for f in dataclasses.fields(protocol.surface)} else "warp"
            part = dataclasses.replace(getattr(protocol, section), **{key: float(value)})
            protocol = dataclasses.replace(protocol, **{section: part})
        result = register_labels(fixed, moving, protocol=protocol)
        u, det = fields_on_grid(result.warp, fixed)
    else:
        with tempfile.TemporaryDirectory() as d:
            u, det = _peer(method, fixed, moving, d)
    seconds = time.perf_counter() - t0
    out = _scores(fixed, moving, fixed.grid_points() + u, truth, det)
    out.update(seconds=seconds, peak_rss_gb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2)
    return out


def interpolation_check() -> str:
    from volreg.evaluation.metrics import dice
    from volreg.warp.resample import resample_labels

    fixed, moving, truth = _pair()
    positions = truth(fixed.grid_points().reshape(-1, 3)).reshape(*fixed.shape, 3)
    rows = []
    for method in ("label", "nearest"):
        warped = resample_labels(moving, positions, method=method)
        big = [v for v in fixed.labels() if np.count_nonzero(fixed.array == v) >= LARGE]
        rows.append(f"| {method} | {np.mean([dice(fixed.array == v, warped == v) for v in fixed.labels()]):.3f} "
                    f"| {np.mean([dice(fixed.array == v, warped == v) for v in big]):.3f} |")
    return f"| interpolation through the true warp | mean Dice, all labels | labels >= {LARGE} voxels |\n|---|---|---|\n" + "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--peers", action="store_true")
    parser.add_argument("--methods", default=None,
                        help="comma-separated subset, e.g. ants-SyNOnly,volreg-fast,volreg-default+alpha=20"
                             ",volreg-accurate+distance_smoothing=0.5")
    parser.add_argument("--no-interpolation", action="store_true", help="skip the interpolation table")
    parser.add_argument("--full", action="store_true", help="the frog at its native 1 x 1 x 1.5 mm (default 3 mm)")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.full:
        os.environ["VOLREG_BENCH_FULL"] = "1"
    if args.one:
        print(json.dumps(run_one(args.one)))
        return
    methods = ["volreg-fast", "volreg-default"] + (
        ["ants-SyNOnly", "ants-SyN", "greedy", "elastix-bspline-ms"] if args.peers else [])
    if args.methods:
        methods = args.methods.split(",")
    if not args.no_interpolation:
        print(interpolation_check())
        print()
    print(f"| method | mean Dice | mean Dice, labels >= {LARGE} voxels | endpoint error mean / p95 (mm) | folded "
          "| wall s (runs) | peak RSS GB |")
    print("|---|---|---|---|---|---|---|")
    for method in methods:
        runs = []
        for _ in range(args.repeats):
            res = subprocess.run([sys.executable, __file__, "--one", method], capture_output=True, text=True,
                                 env=dict(os.environ, ANTS_RANDOM_SEED="1", ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS="2"))
            if res.returncode != 0:
                print(f"| {method} | failed: {res.stderr.strip().splitlines()[-1] if res.stderr.strip() else res.returncode} |")
                break
            runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
        if not runs:
            continue
        med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
        times = ", ".join(f"{r['seconds']:.1f}" for r in runs)
        print(f"| {method} | {med['dice']:.4f} | {med['dice_large']:.4f} | {med['epe_mean']:.2f} / {med['epe_p95']:.2f} "
              f"| {med['folded']:.4f} | {med['seconds']:.1f} ({times}) | {med['peak_rss_gb']:.2f} |", flush=True)
    from volreg.warp.resample import resample_labels

    fixed, moving, truth = _pair()
    x = fixed.grid_points()[fixed.array > 0]
    err0 = np.linalg.norm(truth(x) - x, axis=1)
    d0 = _dice(fixed, moving.array)
    print(f"| identity (no registration) | {d0['dice']:.4f} | {d0['dice_large']:.4f} "
          f"| {err0.mean():.2f} / {np.percentile(err0, 95):.2f} | 0 | - | - |")
    positions = truth(fixed.grid_points().reshape(-1, 3)).reshape(*fixed.shape, 3)
    dt = _dice(fixed, resample_labels(moving, positions))
    print(f"| the true warp | {dt['dice']:.4f} | {dt['dice_large']:.4f} | 0 / 0 | 0 | - | - |")


if __name__ == "__main__":
    main()
