"""Inverse consistency on the frog demo pair: volreg against ANTs SyN, side by side.

Run:  .venv/bin/python benchmarks/bench_consistency.py [--repeats 3] [--peers]
          [--methods volreg-default,volreg-default-symmetric,volreg-fast,ants-SyNOnly]

The pair is `volreg demo`'s (pyvista's frog tissues block-downsampled to 3 mm = A, a copy deformed
by a known smooth warp of up to 8 mm = B).  For every method, A is registered to B (pull-back
tau_AB: an A point to its B partner) and B to A, and at every voxel x of A's labels we measure
  * the consistency error of the two registrations, |tau_BA(tau_AB(x)) - x|;
  * for ANTs also the forward warp composed with ANTs' own inverse (SyN's InverseWarp);
  * for volreg also the forward warp composed with its Newton inverse (volreg.InverseWarp);
  * volreg-<protocol>-symmetric[=W]: the symmetric option (lambda_consistency = W, default 1000: the B->A fit is
    pulled towards the A->B warp's inverse);
  * the endpoint error of tau_AB against the known warp (an identity warp is perfectly
    consistent and useless, so the two are read together).
Errors in mm and in voxels (mean spacing of A); ANTs fields are interpolated linearly.  Each run
is a fresh process; medians of the repeats.  --peers adds ANTs SyNOnly (antspyx, label images as
float, 2 threads) and greedy (picsl_greedy, SSD on the label images, -n 100x50x20, -s 2vox 1vox,
its own inverse from -oinv, 2 threads).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_labels import _pair  # noqa: E402


def _stats(err: np.ndarray, voxel: float) -> dict:
    return {"mean": float(err.mean()), "p95": float(np.percentile(err, 95)), "mean_vox": float(err.mean() / voxel),
            "p95_vox": float(np.percentile(err, 95) / voxel)}


def run_one(method: str) -> dict:
    a, b, truth = _pair()
    inside = a.array > 0
    x = a.grid_points()[inside]
    voxel = float(np.mean(a.spacing))
    out: dict = {}
    t0 = time.perf_counter()
    if method.startswith("volreg"):
        from volreg.warp.inverse import InverseWarp
        from volreg.pipeline.labels import register_labels
        from volreg.io.protocol import load_protocol

        name = method.split("-")[1]
        protocol = load_protocol(name)
        if "-symmetric" in method:  # the symmetric option, weight 1000 or as given (-symmetric=W)
            weight = float(method.split("=")[1]) if "=" in method else 1000.0
            protocol = dataclasses.replace(protocol, warp=dataclasses.replace(protocol.warp, lambda_consistency=weight))
        ab = register_labels(a, b, protocol=protocol).warp
        ba = register_labels(b, a, protocol=protocol, prior=InverseWarp(ab)).warp
        out["seconds"] = time.perf_counter() - t0
        y = ab(x)
        out["two_registrations"] = _stats(np.linalg.norm(ba(y) - x, axis=1), voxel)
        t1 = time.perf_counter()
        inv = InverseWarp(ab)
        out["own_inverse"] = _stats(np.linalg.norm(inv(y) - x, axis=1), voxel)
        out["inverse_seconds"] = time.perf_counter() - t1
    elif method == "ants-SyNOnly":
        import ants

        from volreg.io import write_labels
        from volreg.io.fields import read_displacement
        from volreg.warp.resample import resample_image

        def field_at(field, grid, points):
            return np.stack([resample_image(field[..., d], grid, points, order=1) for d in range(3)], axis=-1)

        with tempfile.TemporaryDirectory() as d:
            write_labels(a, os.path.join(d, "a.nii.gz"))
            write_labels(b, os.path.join(d, "b.nii.gz"))
            ia = ants.image_read(os.path.join(d, "a.nii.gz"), pixeltype="float")
            ib = ants.image_read(os.path.join(d, "b.nii.gz"), pixeltype="float")
            reg_ab = ants.registration(ia, ib, type_of_transform="SyNOnly", outprefix=os.path.join(d, "ab_"))
            reg_ba = ants.registration(ib, ia, type_of_transform="SyNOnly", outprefix=os.path.join(d, "ba_"))
            out["seconds"] = time.perf_counter() - t0
            u_ab, grid_a = read_displacement(reg_ab["fwdtransforms"][0])
            inverse = [t for t in reg_ab["invtransforms"] if t.endswith("InverseWarp.nii.gz")]
            v_ab, grid_a2 = read_displacement(inverse[0])  # SyN's InverseWarp, on A's grid too
            u_ba, grid_b = read_displacement(reg_ba["fwdtransforms"][0])
        y = x + u_ab[inside]
        out["two_registrations"] = _stats(np.linalg.norm(y + field_at(u_ba, grid_b, y) - x, axis=1), voxel)
        out["own_inverse"] = _stats(np.linalg.norm(y + field_at(v_ab, grid_a2, y) - x, axis=1), voxel)
    elif method == "greedy":
        from picsl_greedy import Greedy3D

        from volreg.io import write_labels
        from volreg.io.fields import read_displacement
        from volreg.warp.resample import resample_image

        def field_at(field, grid, points):
            return np.stack([resample_image(field[..., d], grid, points, order=1) for d in range(3)], axis=-1)

        with tempfile.TemporaryDirectory() as d:
            write_labels(a, os.path.join(d, "a.nii.gz"))
            write_labels(b, os.path.join(d, "b.nii.gz"))
            for f, m, name in (("a", "b", "ab"), ("b", "a", "ba")):
                Greedy3D().execute(f"-d 3 -threads 2 -i {d}/{f}.nii.gz {d}/{m}.nii.gz -o {d}/{name}.nii.gz "
                                   f"-oinv {d}/{name}_inv.nii.gz -n 100x50x20 -m SSD -s 2vox 1vox")
            out["seconds"] = time.perf_counter() - t0
            u_ab, grid_a = read_displacement(f"{d}/ab.nii.gz")
            v_ab, grid_a2 = read_displacement(f"{d}/ab_inv.nii.gz")
            u_ba, grid_b = read_displacement(f"{d}/ba.nii.gz")
        y = x + u_ab[inside]
        out["two_registrations"] = _stats(np.linalg.norm(y + field_at(u_ba, grid_b, y) - x, axis=1), voxel)
        out["own_inverse"] = _stats(np.linalg.norm(y + field_at(v_ab, grid_a2, y) - x, axis=1), voxel)
    else:
        raise SystemExit(f"unknown method {method}")
    err = np.linalg.norm(y - truth(x), axis=1)
    out["endpoint"] = {"mean": float(err.mean()), "p95": float(np.percentile(err, 95))}
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--peers", action="store_true")
    parser.add_argument("--methods", default=None, help="comma-separated subset, e.g. ants-SyNOnly,volreg-fast")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(args.one)))
        return
    methods = ["volreg-default", "volreg-default-symmetric"] + (["ants-SyNOnly", "greedy"] if args.peers else [])
    if args.methods:
        methods = args.methods.split(",")
    print("| method | A->B then B->A: mean / p95 mm (voxel) | A->B then own inverse: mean / p95 mm (voxel) "
          "| endpoint error A->B mean / p95 mm | wall s, both registrations (runs) |")
    print("|---|---|---|---|---|")
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

        def med(*keys):
            vals = []
            for r in runs:
                for k in keys:
                    r = r[k]
                vals.append(r)
            return float(np.median(vals))

        cells = []
        for key in ("two_registrations", "own_inverse"):
            cells.append(f"{med(key, 'mean'):.3f} / {med(key, 'p95'):.3f} ({med(key, 'mean_vox'):.4f} / {med(key, 'p95_vox'):.4f})")
        times = ", ".join(f"{r['seconds']:.0f}" for r in runs)
        print(f"| {method} | {cells[0]} | {cells[1]} | {med('endpoint', 'mean'):.2f} / {med('endpoint', 'p95'):.2f} "
              f"| {med('seconds'):.0f} ({times}) |", flush=True)
    a, _, truth = _pair()
    x = a.grid_points()[a.array > 0]
    err0 = np.linalg.norm(truth(x) - x, axis=1)
    print(f"| identity (no registration) | 0 / 0 | 0 / 0 | {err0.mean():.2f} / {np.percentile(err0, 95):.2f} | - |")


if __name__ == "__main__":
    main()
