"""One surface registration at 20k-200k finest-level training points: time, memory, where the time goes.

Run:  .venv/bin/python benchmarks/bench_scaling.py [--repeats 3] [--pads 0.006,0.0125,0.025,0.045]

Pair: pyvista's ant mesh (scaled by 5: diameter 246 mm) Loop-subdivided 4 times (117k vertices) and
its copy deformed by the known smooth warp of `bench_surfaces.py` (6 Gaussian bumps, up to 5 % of the
diameter).  The full pipeline of `register_surfaces` runs: both implicit-surface fits and every warp
level, coarse to fine.  The finest kernel width is fixed at 1/64 of the diameter (3.85 mm); the
padding of the warp volume X (as a fraction of the diameter) sets how many training points (octree
box centres, Section 3.5) the finest level has.  Each run is its own process, profiled with
cProfile; the time is split into: implicit-surface fits, neighbour search and sparse kernel-matrix
assembly (`kernel_matrix`, `kernel_gradient_matrices`, octree sampling), evaluating f2 and its
derivatives at moved points (`ImplicitSurface.evaluate`), sparse matrix products (scipy's
`csr_matvec(s)` and volreg's `_csr_matmul_shared*`), and the rest (L-BFGS, the warp evaluated at samples, fold checks).
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

HERE = os.path.dirname(os.path.abspath(__file__))

#: cProfile categories: (name, substrings of "file:function", files of the callers that count).
#: Calls are counted with their cumulative time as called from those files only, so that the
#: kernel matrices built inside the implicit-surface fits are not counted twice.
CATEGORIES = (  # (name, (path fragment, function) callees, caller files)
    ("fit implicit surfaces", (("features/implicit.py", "__init__"),), ("register.py", "fit.py")),
    ("neighbour search + assembly", (("kernels/", "kernel_matrix"), ("kernels/", "kernel_gradient_matrices"),
                                     ("warp/sampling.py", "octree_sample"), ("kernels/", "build")),
     ("register.py", "fit.py")),
    ("f2 evaluation", (("features/implicit.py", "evaluate"), ("features/implicit.py", "__call__")),
     ("objective.py", "register.py", "fit.py")),
)


def run_one(pad_fraction: float) -> dict:
    import cProfile
    import pstats

    sys.path.insert(0, HERE)
    from bench_surfaces import _pair

    from volreg.settings import WarpSettings
    from volreg.pipeline.surfaces import register_surfaces
    from volreg.morph import surface_normals

    v, faces, truth, diameter = _pair(10**9)  # all 117k vertices
    target = truth(v)
    settings = WarpSettings(min_width=diameter / 64, pad=pad_fraction * diameter)
    src = (v, surface_normals(v, faces))
    tgt = (target, surface_normals(target, faces))
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    res = register_surfaces(src, tgt, settings=settings)
    prof.disable()
    seconds = time.perf_counter() - t0
    stats = pstats.Stats(prof).stats  # {(file, line, func): (cc, nc, tottime, cumtime, callers)}
    split = {}
    for name, keys, caller_files in CATEGORIES:
        total = 0.0
        for (file, _, func), (_, _, _, _, callers) in stats.items():
            if any(fragment in file.replace(os.sep, "/") and func == name_ for fragment, name_ in keys):
                total += sum(c[3] for caller, c in callers.items() if os.path.basename(caller[0]) in caller_files)
        split[name] = total
    split["sparse matvecs"] = sum(tot for (file, _, func), (_, _, tot, _, _) in stats.items()
                                  if "csr_matvec" in func or "_csr_matmul_shared" in func)
    split["other"] = seconds - sum(split.values())
    err = np.linalg.norm(res.warp(v) - target, axis=1)
    return {"finest_samples": res.log[-1]["samples"], "finest_centres": res.log[-1]["centres"],
            "levels": len(res.log), "seconds": seconds, "split": split,
            "error_percent": float(100 * err.mean() / diameter),
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--pads", default="0.006,0.0125,0.025,0.045", help="padding of X, fractions of the diameter")
    parser.add_argument("--one", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(run_one(args.one)))
        return
    names = [c[0] for c in CATEGORIES] + ["sparse matvecs", "other"]
    print("| pad (% of diameter) | finest-level training points | levels | wall s, median (runs) | "
          + " | ".join(f"{n} s" for n in names) + " | peak RSS GB | mean vertex error, % of diameter |")
    print("|---" * (7 + len(names)) + "|", flush=True)
    for pad in (float(p) for p in args.pads.split(",")):
        runs = []
        for _ in range(args.repeats):
            out = subprocess.run([sys.executable, __file__, "--one", str(pad)], capture_output=True, text=True)
            if out.returncode != 0:
                raise SystemExit(out.stderr.strip().splitlines()[-1])
            runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        med = sorted(runs, key=lambda r: r["seconds"])[len(runs) // 2]  # the median run, with its split
        times = ", ".join(f"{r['seconds']:.1f}" for r in runs)
        print(f"| {100 * pad:.2f} | {med['finest_samples']} | {med['levels']} | {med['seconds']:.1f} ({times}) | "
              + " | ".join(f"{med['split'][n]:.1f}" for n in names)
              + f" | {max(r['peak_rss_gb'] for r in runs):.2f} | {med['error_percent']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
