"""Foundation benchmarks: implicit-surface fit and evaluation on pyvista's frog.

Run:  .venv/bin/python benchmarks/bench_foundation.py [--repeats 3] [--quick]

Each measurement runs in a fresh subprocess (so peak memory is that run's own)
and is repeated; the median is reported.  Results go to stdout as Markdown, to
be pasted into BENCHMARKS.md with the command line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def frog_body():
    """The frog's body outline (all tissue labels merged) as a LabelVolume."""
    from pyvista import examples

    from volreg.io import read_labels
    from volreg.grid import LabelVolume

    vol = read_labels(os.path.join(os.path.dirname(examples.__file__), "frog_tissues.vti"))
    return LabelVolume((vol.array > 0).astype(np.uint8), vol.origin, vol.spacing, vol.direction)


def _child(task: str, arg: float) -> dict:
    import resource

    from volreg.features.implicit import ImplicitSurface
    from volreg.kernels import kernel_sum, kernel_sum_reference
    from volreg.features.label_surfaces import label_surface, voxel_size

    cache = os.path.join(HERE, "out", "frog_body_surface.npz")
    if not os.path.exists(cache):
        os.makedirs(os.path.dirname(cache), exist_ok=True)
        vol = frog_body()
        t0 = time.perf_counter()
        s = label_surface(vol, 1)
        np.savez(cache, vertices=s.vertices, normals=s.normals, voxel=voxel_size(vol),
                 mesh_seconds=time.perf_counter() - t0)
    data = np.load(cache)
    verts, normals, voxel = data["vertices"], data["normals"], float(data["voxel"])
    rng = np.random.default_rng(0)
    out: dict = {}
    if task == "mesh":
        vol = frog_body()
        t0 = time.perf_counter()
        from volreg.features.label_surfaces import label_surface as ls

        s = ls(vol, 1)
        out = dict(seconds=time.perf_counter() - t0, vertices=len(s.vertices))
    elif task == "fit":
        # Vertex subsets of the body outline, finest width fixed at 4 voxels.
        n = int(arg)
        idx = rng.choice(len(verts), size=min(n, len(verts)), replace=False)
        t0 = time.perf_counter()
        f = ImplicitSurface(verts[idx], normals[idx], min_width=4 * voxel)
        out = dict(seconds=time.perf_counter() - t0, vertices=len(idx), levels=len(f.levels),
                   finest_training=f.log[-1]["training_points"], min_width=f.widths[-1])
    elif task == "fit-width":
        # All vertices; the finest width (hence the training points per level) varies.
        diameter = float(np.linalg.norm(verts.max(axis=0) - verts.min(axis=0)))
        t0 = time.perf_counter()
        f = ImplicitSurface(verts, normals, min_width=arg, max_width=diameter / 2 * _top_scale(arg, diameter))
        out = dict(seconds=time.perf_counter() - t0, vertices=len(verts), levels=len(f.levels),
                   finest_training=f.log[-1]["training_points"], min_width=f.widths[-1],
                   training=sum(e["training_points"] for e in f.log))
    elif task == "fit-voxel":
        t0 = time.perf_counter()
        f = ImplicitSurface(verts, normals, min_width=4 * voxel)
        out = dict(seconds=time.perf_counter() - t0, vertices=len(verts), levels=len(f.levels),
                   finest_training=f.log[-1]["training_points"], min_width=f.widths[-1])
    elif task in ("eval-near", "eval-box"):
        f = ImplicitSurface(verts, normals, min_width=4 * voxel)
        n = int(arg)
        if task == "eval-near":
            q = verts[rng.integers(0, len(verts), n)] + rng.normal(0, 2 * voxel, (n, 3))
        else:
            lo, hi = verts.min(axis=0), verts.max(axis=0)
            q = rng.uniform(lo, hi, (n, 3))
        f.evaluate(q[:1000], order=1)
        t0 = time.perf_counter()
        f.evaluate(q, order=1)
        out = dict(seconds=time.perf_counter() - t0, points=n)
    elif task in ("sum-numba", "sum-scipy"):
        f = ImplicitSurface(verts, normals, min_width=4 * voxel)
        lev = f.levels[-1]
        n = int(arg)
        q = verts[rng.integers(0, len(verts), n)] + rng.normal(0, voxel, (n, 3))
        fn = kernel_sum if task == "sum-numba" else kernel_sum_reference
        fn(q[:100], lev.centres, lev.alpha, lev.width, order=1)
        t0 = time.perf_counter()
        fn(q, lev.centres, lev.alpha, lev.width, order=1)
        out = dict(seconds=time.perf_counter() - t0, points=n, centres=len(lev.centres))
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    return out


def _top_scale(min_width: float, diameter: float) -> float:
    """Scale of the coarsest width so that halving lands exactly on ``min_width``."""
    top = diameter / 2
    k = np.floor(np.log2(top / min_width))
    return float(min_width * 2**k / top)


def run(task: str, arg: float, repeats: int) -> dict:
    runs = []
    for _ in range(repeats):
        res = subprocess.run([sys.executable, __file__, "--child", task, str(arg)],
                             check=True, capture_output=True, text=True)
        runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
    best = dict(runs[0])
    best["seconds"] = statistics.median(r["seconds"] for r in runs)
    best["seconds_all"] = [round(r["seconds"], 2) for r in runs]
    best["peak_rss_gb"] = max(r["peak_rss_gb"] for r in runs)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="smaller sizes, one repeat")
    ap.add_argument("--only", choices=("all", "eval"), default="all",
                    help="'eval': only the evaluation and kernel-sum rows")
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_child(args.child[0], float(args.child[1]))))
        return
    reps = 1 if args.quick else args.repeats
    # Build the cached surface and compile the numba kernels once, in a child
    # process: a child started from a large parent would inherit its peak RSS.
    subprocess.run([sys.executable, __file__, "--child", "warm", "0"], check=True, capture_output=True)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"median of {reps} runs, each in a fresh process\n")
    print("| task | size | median s | runs (s) | peak RSS GB | notes |\n|---|---|---|---|---|---|")
    if args.only == "eval":
        _eval_rows(args, reps)
        return
    r = run("mesh", 0, reps)
    print(f"| frog body outline: smoothing + marching cubes + curvature correction | {r['vertices']} vertices "
          f"| {r['seconds']:.2f} | {r['seconds_all']} | {r['peak_rss_gb']:.2f} | 500x470x136 grid |")
    sizes = [25_000, 50_000] if args.quick else [25_000, 50_000, 100_000, 200_000]
    for n in sizes:
        r = run("fit", n, reps)
        print(f"| fit a vertex subset, finest width 4 voxels | {r['vertices']} vertices | {r['seconds']:.2f} "
              f"| {r['seconds_all']} | {r['peak_rss_gb']:.2f} | {r['levels']} levels, finest width "
              f"{r['min_width']:.1f} mm, {r['finest_training']} finest training points |")
    widths = [20.0, 14.0] if args.quick else [20.0, 14.0, 10.0, 7.0, 5.0]
    for w in widths:
        r = run("fit-width", w, reps)
        print(f"| fit all vertices, finest width {r['min_width']:.1f} mm | {r['training']} training points "
              f"(all levels) | {r['seconds']:.2f} | {r['seconds_all']} | {r['peak_rss_gb']:.2f} | {r['levels']} levels, "
              f"{r['finest_training']} at the finest |")
    r = run("fit-voxel", 0, reps)
    print(f"| fit, min width 4 voxels (as `volreg surface`) | {r['vertices']} vertices | {r['seconds']:.2f} "
          f"| {r['seconds_all']} | {r['peak_rss_gb']:.2f} | {r['levels']} levels, finest width "
          f"{r['min_width']:.1f} mm, {r['finest_training']} finest training points |")
    _eval_rows(args, reps)


def _eval_rows(args: argparse.Namespace, reps: int) -> None:
    n_eval = 1_000_000 if args.quick else 10_000_000
    for task, what in (("eval-near", "within ~2 voxels of the surface"), ("eval-box", "uniform in the bounding box")):
        r = run(task, n_eval, reps)
        print(f"| evaluate f and grad f, {what} | {n_eval} points | {r['seconds']:.2f} | {r['seconds_all']} "
              f"| {r['peak_rss_gb']:.2f} | model of the row above |")
    n_sum = 200_000
    rn = run("sum-numba", n_sum, reps)
    rs = run("sum-scipy", n_sum, reps)
    print(f"| kernel sum + gradient, finest level, numba cell grid | {n_sum} points | {rn['seconds']:.3f} "
          f"| {rn['seconds_all']} | {rn['peak_rss_gb']:.2f} | {rn['centres']} centres |")
    print(f"| same, scipy cKDTree + bincount (reference) | {n_sum} points | {rs['seconds']:.3f} "
          f"| {rs['seconds_all']} | {rs['peak_rss_gb']:.2f} | ratio scipy/numba = "
          f"{rs['seconds'] / rn['seconds']:.1f} |")


if __name__ == "__main__":
    main()
