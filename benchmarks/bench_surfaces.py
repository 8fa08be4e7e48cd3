"""Surface-to-surface registration: volreg against coherent point drift (pycpd, probreg), side by side.

Run:  python benchmarks/bench_surfaces.py [--sizes 10000,25000,50000,100000] [--repeats 3]
      [--cpd-repeats 1] [--cpd-timeout 600] [--cpd-memory-gb 16]

Needs the `bench` extra (pycpd) and probreg (`pip install probreg`; its open3d needs
`apt-get install libusb-1.0-0` on Debian).

Pairs: pyvista's shipped ant mesh (ant.ply, scaled by 5: diameter 246 mm), Loop-subdivided 4 times
(117k vertices) and decimated to each size, and a copy deformed by a known smooth warp (6 Gaussian
bumps, scale 15 % of the diameter, displacement up to 5 % of it; `volreg.synthetic.GaussianBumps`,
seed 1).  Every method gets the source and target vertices (volreg also the mesh normals), never the
correspondence.  Reported: mean vertex error |tau(v) - truth(v)| as % of the diameter, wall time and
peak RSS of the process; medians of the repeats, each run its own process.  Both CPDs run non-rigid
with beta = 2, lambda = 2 in units of a tenth of the diameter; each CPD run is limited to
--cpd-memory-gb of address space and --cpd-timeout seconds, and a run that hits a limit is reported
as such (both keep dense M x M and M x N matrices: 8 M^2 bytes each).
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


def _pair(size: int):
    import pyvista as pv
    from pyvista import examples

    from volreg.synthetic import GaussianBumps

    mesh = pv.read(os.path.join(os.path.dirname(examples.__file__), "ant.ply")).triangulate().clean()
    mesh.points = np.asarray(mesh.points) * 5.0
    mesh = mesh.subdivide(4, subfilter="loop")
    if size < mesh.n_points:
        mesh = mesh.decimate(1.0 - size / mesh.n_points).triangulate().clean()
    v = np.asarray(mesh.points, float)
    diameter = float(np.linalg.norm(np.ptp(v, axis=0)))
    truth = GaussianBumps.random(v.min(0), v.max(0), max_displacement=0.05 * diameter, scale=0.15 * diameter,
                                 count=6, rng=np.random.default_rng(1))
    faces = np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]
    return v, faces, truth, diameter


def run_one(method: str, size: int) -> dict:
    v, faces, truth, diameter = _pair(size)
    target = truth(v)
    t0 = time.perf_counter()
    if method == "volreg":
        from volreg.settings import WarpSettings
        from volreg.pipeline.surfaces import register_surfaces
        from volreg.morph import surface_normals

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
    elif method == "probreg":
        from probreg import cpd

        scale = diameter / 10.0
        res = cpd.registration_cpd(v / scale, target / scale, tf_type_name="nonrigid", beta=2.0, lmd=2.0,
                                   maxiter=100)
        moved = np.asarray(res.transformation.transform(v / scale)) * scale
    else:
        raise SystemExit(f"unknown method {method}")
    seconds = time.perf_counter() - t0
    from scipy.spatial import cKDTree

    err = np.linalg.norm(moved - target, axis=1)
    on_surface = cKDTree(target).query(moved)[0]  # distance to the nearest target vertex
    return {"vertices": len(v), "error_percent": float(100 * err.mean() / diameter),
            "surface_percent": float(100 * on_surface.mean() / diameter),
            "identity_percent": float(100 * np.linalg.norm(target - v, axis=1).mean() / diameter),
            "seconds": seconds, "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2}


def _limits(memory_gb: float):
    def apply() -> None:
        limit = int(memory_gb * 1024**3)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    return apply


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=3, help="runs of volreg per size (median reported)")
    parser.add_argument("--cpd-repeats", type=int, default=1, help="runs of each CPD per size")
    parser.add_argument("--sizes", default="10000,25000,50000,100000")
    parser.add_argument("--methods", default="volreg,pycpd,probreg")
    parser.add_argument("--cpd-timeout", type=float, default=600.0)
    parser.add_argument("--cpd-memory-gb", type=float, default=16.0)
    parser.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(args.one[0], int(args.one[1]))))
        return
    print("| vertices | method | mean vertex error, % of diameter (identity) | distance to nearest target vertex, % "
          "| wall s (runs) | peak RSS GB |")
    print("|---|---|---|---|---|---|", flush=True)
    gave_up: dict[str, str] = {}
    for size in (int(x) for x in args.sizes.split(",")):
        n = len(_pair(size)[0])
        for method in args.methods.split(","):
            cpd = method != "volreg"
            if method in gave_up:
                print(f"| {n} | {method} | not run: {gave_up[method]} at a smaller size | - | - | - |", flush=True)
                continue
            runs = []
            for _ in range(args.cpd_repeats if cpd else args.repeats):
                cmd = [sys.executable, __file__, "--one", method, str(size)]
                try:
                    res = subprocess.run(cmd, capture_output=True, text=True,
                                         timeout=args.cpd_timeout if cpd else None,
                                         preexec_fn=_limits(args.cpd_memory_gb) if cpd else None)
                except subprocess.TimeoutExpired:
                    gave_up[method] = f"over {args.cpd_timeout:.0f} s"
                    print(f"| {n} | {method} | stopped after {args.cpd_timeout:.0f} s | - | > {args.cpd_timeout:.0f} | - |",
                          flush=True)
                    break
                if res.returncode != 0:
                    lines = res.stderr.strip().splitlines()
                    tail = lines[-1] if lines else f"exit {res.returncode}"
                    if "MemoryError" in tail or "Unable to allocate" in tail:
                        gave_up[method] = f"out of memory ({args.cpd_memory_gb:g} GB limit)"
                        tail = f"out of memory ({args.cpd_memory_gb:g} GB limit): {tail[:120]}"
                    print(f"| {n} | {method} | failed: {tail} | - | - | - |", flush=True)
                    break
                runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
            if not runs:
                continue
            med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
            times = ", ".join(f"{r['seconds']:.2f}" for r in runs)
            print(f"| {n} | {method} | {med['error_percent']:.2f} ({med['identity_percent']:.2f}) "
                  f"| {med['surface_percent']:.3f} | {med['seconds']:.2f} "
                  f"({times}) | {med['peak_rss_gb']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
