"""Surface-to-surface registration: volreg against coherent point drift (pycpd), side by side.

Run:  python benchmarks/bench_surfaces.py [--repeats 3] [--levels 2,3,4] [--cpd-max 10000]

Pairs: pyvista's shipped ant mesh (ant.ply, scaled by 5: diameter 246 mm), Loop-subdivided 2, 3 and 4 times
(7.3k, 29k and 117k vertices after cleaning), and a copy deformed by a known smooth warp (6 Gaussian bumps, scale 15 %
of the diameter, displacement up to 5 % of it; `volreg.synthetic.GaussianBumps`, seed 1).  Every method
gets the source and target vertices (volreg also the mesh normals), never the correspondence.
Reported: mean vertex error |tau(v) - truth(v)| as % of the diameter, wall time and peak RSS of the
process; medians of the repeats, each run its own process.  pycpd's DeformableRegistration (default
alpha = 2, beta = 2 in units of the data, here scaled by the diameter) keeps dense N x M matrices, so it
is run only up to --cpd-max vertices.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np


def _pair(level: int):
    import pyvista as pv
    from pyvista import examples

    from volreg.synthetic import GaussianBumps

    mesh = pv.read(os.path.join(os.path.dirname(examples.__file__), "ant.ply")).triangulate().clean()
    mesh.points = np.asarray(mesh.points) * 5.0
    mesh = mesh.subdivide(level, subfilter="loop") if level > 0 else mesh
    v = np.asarray(mesh.points, float)
    diameter = float(np.linalg.norm(np.ptp(v, axis=0)))
    truth = GaussianBumps.random(v.min(0), v.max(0), max_displacement=0.05 * diameter, scale=0.15 * diameter,
                                 count=6, rng=np.random.default_rng(1))
    faces = np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]
    return v, faces, truth, diameter


def run_one(method: str, level: int) -> dict:
    v, faces, truth, diameter = _pair(level)
    target = truth(v)
    t0 = time.perf_counter()
    if method == "volreg":
        from volreg.pipeline import WarpSettings, register_surfaces
        from volreg.surface_registration import surface_normals

        src = (v, surface_normals(v, faces))
        tgt = (target, surface_normals(target, faces))
        warp = register_surfaces(src, tgt, settings=WarpSettings()).warp
        moved = warp(v)
    elif method == "pycpd":
        from pycpd import DeformableRegistration

        scale = diameter / 10.0  # CPD's beta is in data units: work in units of a tenth of the diameter
        reg = DeformableRegistration(X=target / scale, Y=v / scale, alpha=2.0, beta=2.0, max_iterations=100)
        moved, _ = reg.register()
        moved = moved * scale
    else:
        raise SystemExit(f"unknown method {method}")
    seconds = time.perf_counter() - t0
    err = np.linalg.norm(moved - target, axis=1)
    return {"vertices": len(v), "error_percent": float(100 * err.mean() / diameter),
            "identity_percent": float(100 * np.linalg.norm(target - v, axis=1).mean() / diameter),
            "seconds": seconds, "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--levels", default="2,3,4")
    parser.add_argument("--cpd-max", type=int, default=10000)
    parser.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(args.one[0], int(args.one[1]))))
        return
    print("| vertices | method | mean vertex error, % of diameter (identity) | wall s (runs) | peak RSS GB |")
    print("|---|---|---|---|---|")
    for level in (int(x) for x in args.levels.split(",")):
        n = len(_pair(level)[0])
        for method in ("volreg", "pycpd"):
            if method == "pycpd" and n > args.cpd_max:
                print(f"| {n} | pycpd | not run: dense {n} x {n} matrices ({8 * n * n / 1024**3:.0f} GB each) | - | - |",
                      flush=True)
                continue
            runs = []
            for _ in range(args.repeats):
                res = subprocess.run([sys.executable, __file__, "--one", method, str(level)], capture_output=True, text=True)
                if res.returncode != 0:
                    tail = res.stderr.strip().splitlines()[-1] if res.stderr.strip() else res.returncode
                    print(f"| {n} | {method} | failed: {tail} | - | - |", flush=True)
                    break
                runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
            if not runs:
                continue
            med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
            times = ", ".join(f"{r['seconds']:.0f}" for r in runs)
            print(f"| {n} | {method} | {med['error_percent']:.2f} ({med['identity_percent']:.2f}) | {med['seconds']:.0f} "
                  f"({times}) | {med['peak_rss_gb']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
