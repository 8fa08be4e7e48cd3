"""Whole commands on brain-size and atlas-size label maps: volreg's time beside greedy's and ANTs'.

Run:  PYTHON benchmarks/bench_speed.py [--repeats 3] [--once frog-full] [--growth] [--first-run]

The Python that runs the script needs volreg and the bench extra (antspyx, picsl_greedy); the peers
run in it (or in `--peer-python`). volreg runs as `--volreg-command` (default: the repository's
`.venv/bin/volreg`; e.g. `"env PYTHONPATH=SNAPSHOT .venv/bin/python -m volreg"` for a source snapshot).

Cases (same resolution, no pose: the deformable comparison), generated with known answers (seeded).
The moving volume is the fixed one deformed by a known smooth warp tau_true (10 Gaussian bumps over the
labels' box, scale 0.15 x its diagonal, up to 8 mm; `volreg.synthetic.GaussianBumps`), resampled
label-preservingly (`volreg.synthetic.deform_labels`, as `volreg demo` makes its pair):

- `phantom`: a folded, cortex-like two-label phantom at 1 mm on 169 x 199 x 169 voxels: a brain-sized
  ellipsoid (semi-axes 78 / 93 / 78 mm) whose surface is indented radially by sulci 12 mm deep along the
  zero set of a random sum of 10 plane waves of 18 mm wavelength (a labyrinth of gyri about 5-8 mm
  wide); grey matter (label 1) is the tissue within 2.5 mm of the outside, white matter (label 2) the
  core beneath it;
- `parcels`: the same phantom at 1.5 mm with its grey shell split into 99 Voronoi cells (seeds drawn
  among the shell's voxels) plus the white core: 100 labels;
- `frog`: pyvista's frog tissues at 3 mm, as `volreg demo` builds it (the 3 x 3 x 2 block mode);
- `frog-full`: the frog at its native 1 x 1 x 1.5 mm, as `volreg demo --full`;
- with `--growth` also `labels2` and `labels500`: the 1.5 mm phantom with its shell in 1 and in 499
  cells (2 and 500 labels), volreg only, for the table of how cost grows (with `parcels`, `frog` and
  `frog-full`).

Methods, each a fresh process timed from process start to exit (wall seconds; peak RSS of that process
from `wait4` in a small launcher, see `common.py`), 2 threads each:

- `volreg`: the whole command `volreg register FIXED MOVING -o OUT --quiet`, default protocol (affine
  linear stage, then the kernel warp), every output written; its report.json's stages are shown;
- `greedy`: picsl_greedy, affine then deformable (SSD, 100x50x20, smoothing 2 and 1 voxels), composed
  by greedy, as `bench_pose.py` runs it (`greedy-deformable`: the deformable stage alone, as
  `bench_labels.py` runs it);
- `ants`: antspyx `registration(type_of_transform="SyN")` (affine then SyN; `ants-SyNOnly`: SyN alone),
  the forward transforms composed into one field.

volreg's runs share one numba cache (NUMBA_CACHE_DIR in the work folder), filled by an untimed run on
`frog` first; a run that still compiled something (new files in the cache) is marked. With
`--first-run`, the volreg command on `frog` with an empty numba cache (a fresh folder each time) against
the same command right after it (cache warm), `--repeats` times; and the same for `volreg batch` of
the frog's two volumes registered both ways on 2 local workers.

Scores, from the field each method writes on the fixed grid (LPS mm): endpoint error |tau(x) -
tau_true(x)| at the fixed voxel centres inside the labels (mean, 95th percentile, mm); mean Dice over
the fixed labels of at least 100 voxels (moving labels resampled through the field by volreg's
label-preserving resampling, the same for every method); folded: the fraction of the grid where
det(I + du/dx) <= 0 by central differences (the same for every method). Medians of the runs.

Output: Markdown on stdout (the cases; per case and method time, memory and scores; the volreg/greedy
time ratio; volreg's stages; the growth table; the first-run figures); `--json FILE` also writes every
run's figures. Work files go to a temporary folder (`--workdir` keeps them).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from shapes import folded_blob_inside  # noqa: E402
from common import (
    CHUNK, LARGE, PEERS, add_run_options, grid_text, last_line, print_header, run_env, run_peer, score_field,
    smooth_bumps, timed,
)

CASES = ("frog", "parcels", "phantom", "frog-full")
GROWTH = ("labels2", "labels500")
DEFAULT_METHODS = "volreg,greedy,ants"

BRAIN_AXES = np.array([78.0, 93.0, 78.0])  # mm: semi-axes of the outer envelope
SULCUS_DEPTH = 12.0  # mm
FOLD_WAVELENGTH = 18.0  # mm
CORTEX = 2.5  # mm: grey-matter thickness
MARGIN = 6.0  # mm of background around the envelope


# ----------------------------------------------------------------------------- the cases


def cortex_phantom(spacing: float, *, seed: int = 7, axes=None):
    """The folded two-label phantom on an axis-aligned grid of ``spacing`` mm (origin at the centre).

    Brain is `tests/shapes.py`'s folded blob (:func:`folded_blob_inside`) with semi-axes ``axes``
    (mm; default BRAIN_AXES),
    sulci SULCUS_DEPTH deep along the zero set of a fold pattern of FOLD_WAVELENGTH. Brain within
    CORTEX mm of the outside (Euclidean distance transform) is grey (1), the rest white (2).

    Returns
    -------
    LabelVolume
        uint8 labels 0 (outside), 1 (grey), 2 (white).
    """
    from scipy import ndimage

    from volreg.grid import LabelVolume

    axes = BRAIN_AXES if axes is None else np.asarray(axes, float)
    half = axes + MARGIN
    shape = tuple(int(n) for n in np.floor(2 * half / spacing) + 1)
    origin = -(np.array(shape) - 1) * spacing / 2.0
    brain = np.zeros(shape, bool)
    ii, jj = np.meshgrid(np.arange(shape[1]), np.arange(shape[2]), indexing="ij")
    for i in range(shape[0]):  # slab by slab: 6 M points at 1 mm
        x = origin + spacing * np.stack([np.full(ii.shape, i), ii, jj], axis=-1).reshape(-1, 3)
        inside = folded_blob_inside(x, axes=axes, depth=SULCUS_DEPTH, wavelength=FOLD_WAVELENGTH, seed=seed)
        brain[i] = inside.reshape(ii.shape)
    depth = ndimage.distance_transform_edt(brain, sampling=spacing)
    labels = np.where(brain, np.where(depth <= CORTEX, 1, 2), 0).astype(np.uint8)
    return LabelVolume(labels, origin, np.full(3, float(spacing)), np.eye(3))


def parcellate(phantom, count: int, *, seed: int = 11):
    """The phantom with its grey shell split into ``count - 1`` Voronoi cells (labels 1..count-1,
    seeds drawn among the shell's voxel centres) and its white core as label ``count``.

    Parameters
    ----------
    phantom : LabelVolume
        From :func:`cortex_phantom`.
    count : int
        Labels in the result (2: the phantom itself).
    """
    from scipy.spatial import cKDTree

    shell = phantom.array == 1
    points = phantom.grid_points()[shell]
    seeds = points[np.random.default_rng(seed).choice(len(points), count - 1, replace=False)]
    out = np.zeros(phantom.shape, np.uint8 if count < 256 else np.uint16)
    out[shell] = cKDTree(seeds).query(points)[1] + 1
    out[phantom.array == 2] = count
    return phantom.with_array(out)


@dataclass
class Case:
    """A generated pair: fixed and moving label volumes and the true pull-back map."""

    name: str
    title: str
    fixed: object  # LabelVolume
    moving: object  # LabelVolume
    truth: object  # GaussianBumps: x -> tau_true(x)


def make_case(name: str) -> Case:
    """Build the case ``name`` (one of CASES + GROWTH)."""
    from volreg.synthetic import deform_labels

    if name in ("frog", "frog-full"):
        from volreg.demo import frog_pair, frog_path
        from volreg.io import read_labels

        fixed, moving, tau = frog_pair(read_labels(frog_path()), factors=(3, 3, 2) if name == "frog" else (1, 1, 1))
        return Case(name, "frog, 3 mm" if name == "frog" else "frog, 1 x 1 x 1.5 mm", fixed, moving, tau)
    if name == "phantom":
        fixed = cortex_phantom(1.0)
        title = "folded phantom, grey / white, 1 mm"
    elif name in ("parcels", "labels2", "labels500"):
        count = {"parcels": 100, "labels2": 2, "labels500": 500}[name]
        fixed = parcellate(cortex_phantom(1.5), count)
        title = f"phantom parcellated, {count} labels, 1.5 mm"
    else:
        raise ValueError(f"Expected a case in {CASES + GROWTH}, got {name!r}.")
    tau = smooth_bumps(fixed, 8.0, seed=0)
    return Case(name, title, fixed, deform_labels(fixed, tau), tau)


def boundary_area_cm2(volume) -> float:
    """Area of the faces between voxels of different labels (label boundaries, cm^2): a measure of
    the surface the features cover."""
    a, s = volume.array, np.asarray(volume.spacing, float)
    area = 0.0
    for axis in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        faces = np.count_nonzero(a[tuple(lo)] != a[tuple(hi)])
        area += faces * float(np.prod(np.delete(s, axis)))
    return area / 100.0


# ----------------------------------------------------------------------------- running


def _cache_files(folder: Path) -> int:
    """Files in numba's cache folder (index and data)."""
    return sum(len(files) for _, _, files in os.walk(folder)) if folder.exists() else 0


def run_volreg(case: Case, paths: dict, out: Path, args, cache: Path, *, score: bool = True) -> dict:
    """One timed `volreg register` run with numba's cache in ``cache``: wall seconds, peak RSS, the
    report's stages and total, whether numba compiled (new cache files), and the scores."""
    out.mkdir(parents=True)
    log = out.parent / f"{out.name}.log"
    command = shlex.split(args.volreg_command) + ["register", paths["fixed"], paths["moving"], "-o", str(out), "--quiet"]
    before = _cache_files(cache)
    rc, seconds, rss = timed(command, log, out, args.timeout, env=run_env(NUMBA_CACHE_DIR=str(cache)))
    if rc != 0 or not (out / "report.json").exists():
        return {"failed": last_line(log, rc, seconds)}
    report = json.loads((out / "report.json").read_text())
    result = {"seconds": seconds, "peak_rss_gb": rss, "compiled": _cache_files(cache) - before,
              "report_seconds": float(report.get("seconds", float("nan"))),
              "stages": [(s.get("stage"), float(s.get("seconds"))) for s in report.get("stages", [])]}
    if score:
        result.update(score_field(case.fixed, case.moving, case.truth, out / "warp.nii.gz", folding=True))
    return result


def run_volreg_batch(paths: dict, out: Path, args, cache: Path) -> dict:
    """One timed `volreg batch` of the case's two volumes registered both ways on 2 local workers,
    with numba's cache in ``cache``: wall seconds, peak RSS, new cache files."""
    out.mkdir(parents=True)
    manifest = out / "manifest.csv"
    manifest.write_text(f"id,path\nfixed,{paths['fixed']}\nmoving,{paths['moving']}\n")
    log = out.parent / f"{out.name}.log"
    command = shlex.split(args.volreg_command) + ["batch", str(manifest), "-o", str(out / "batch"), "--pairs", "all",
                                                  "--workers", "2", "--quiet"]
    before = _cache_files(cache)
    rc, seconds, rss = timed(command, log, out, args.timeout, env=run_env(NUMBA_CACHE_DIR=str(cache)))
    if rc != 0 or not (out / "batch" / "batch.csv").exists():
        return {"failed": last_line(log, rc, seconds)}
    return {"seconds": seconds, "peak_rss_gb": rss, "compiled": _cache_files(cache) - before}


def run_peer_timed(case: Case, method: str, paths: dict, out: Path, args) -> dict:
    """One timed peer run (this script with ``--peer`` in ``--peer-python``) and its scores."""
    out.mkdir(parents=True)
    log = out.parent / f"{out.name}.log"
    command = [args.peer_python, str(Path(__file__).resolve()), "--peer", method, paths["fixed"], paths["moving"],
               str(out)]
    rc, seconds, rss = timed(command, log, out, args.timeout)
    if rc != 0 or not (out / "warp.nii.gz").exists():
        return {"failed": last_line(log, rc, seconds)}
    result = {"seconds": seconds, "peak_rss_gb": rss}
    result.update(score_field(case.fixed, case.moving, case.truth, out / "warp.nii.gz", folding=True))
    return result


def _median(runs: list[dict], key: str) -> float:
    return float(np.median([r[key] for r in runs]))


def _median_run(runs: list[dict]) -> dict:
    """The run of median wall time (the lower middle one for an even count)."""
    order = sorted(runs, key=lambda r: r["seconds"])
    return order[(len(order) - 1) // 2]


def _stage_text(stages, top: int | None = None) -> str:
    items = sorted(stages, key=lambda s: -s[1])[:top] if top else stages
    return ", ".join(f"{n} {s:.1f}" for n, s in items)


# ----------------------------------------------------------------------------- main


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="runs per case and method (medians are shown)")
    parser.add_argument("--once", default="frog-full", help="cases run once whatever --repeats (comma-separated; `first-run`: that comparison)")
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma-separated subset of {','.join(CASES)}")
    parser.add_argument("--methods", default=DEFAULT_METHODS,
                        help=f"comma-separated subset of volreg,{','.join(PEERS)}")
    parser.add_argument("--skip", default="", help="CASE/METHOD pairs not run, e.g. frog-full/ants (comma-separated)")
    parser.add_argument("--growth", action="store_true",
                        help=f"also volreg on {' and '.join(GROWTH)}, and the table of how cost grows")
    parser.add_argument("--first-run", action="store_true", help="volreg on `frog` with an empty numba cache vs warm")
    add_run_options(parser)
    parser.add_argument("--json", type=Path, default=None, help="also write every run's figures to this file")
    args = parser.parse_args()
    if args.peer:
        run_peer(*args.peer)
        return
    cases = [c for c in args.cases.split(",") if c]
    methods = [m for m in args.methods.split(",") if m]
    once = set(args.once.split(","))
    skip = {p for p in args.skip.split(",") if p}
    for c in cases:
        if c not in CASES:
            parser.error(f"argument --cases: expected names from {','.join(CASES)}, got {c!r}")
    for m in methods:
        if m != "volreg" and m not in PEERS:
            parser.error(f"argument --methods: expected names from volreg,{','.join(PEERS)}, got {m!r}")
    if args.repeats < 1:
        parser.error(f"argument --repeats: expected a positive integer, got {args.repeats}")
    if args.workdir is not None and args.workdir.exists():
        parser.error(f"argument --workdir: expected a new folder, got an existing one: {args.workdir}")

    print_header("bench_speed.py")

    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_speed_"))
    work.mkdir(parents=True, exist_ok=args.workdir is None)
    cache = work / "numba-cache"
    record = {"argv": sys.argv[1:], "cases": {}, "runs": {}, "first_run": None}
    t_start = time.perf_counter()
    try:
        from volreg.io import write_labels

        wanted = cases + (["labels2", "labels500"] if args.growth else [])
        if args.growth or args.first_run:
            wanted += [c for c in ("frog",) if c not in wanted]
        built = {}
        print("| case | fixed grid | labels | label voxels (M) | boundary area (cm^2) | identity EPE mean / p95 (mm) "
              "| built in s |")
        print("|---|---|---|---|---|---|---|", flush=True)
        for name in wanted:
            t0 = time.perf_counter()
            case = make_case(name)
            paths = {k: str(work / f"{name}_{k}.nii.gz") for k in ("fixed", "moving")}
            write_labels(case.fixed, paths["fixed"])
            write_labels(case.moving, paths["moving"])
            x = case.fixed.grid_points()[case.fixed.array > 0]
            e0 = np.linalg.norm(np.concatenate([case.truth(x[s : s + CHUNK]) for s in range(0, len(x), CHUNK)]) - x,
                                axis=1)
            info = {"title": case.title, "grid": grid_text(case.fixed), "labels": len(case.fixed.labels()),
                    "label_voxels_m": len(x) / 1e6, "voxels_m": float(np.prod(case.fixed.shape)) / 1e6,
                    "area_cm2": boundary_area_cm2(case.fixed), "identity_epe": [float(e0.mean()),
                                                                                 float(np.percentile(e0, 95))]}
            del x, e0
            record["cases"][name] = info
            print(f"| {name}: {case.title} | {info['grid']} | {info['labels']} | {info['label_voxels_m']:.2f} "
                  f"| {info['area_cm2']:.0f} | {info['identity_epe'][0]:.2f} / {info['identity_epe'][1]:.2f} "
                  f"| {time.perf_counter() - t0:.0f} |", flush=True)
            built[name] = (case, paths)
        print()

        if "volreg" in methods or args.growth or args.first_run:  # numba's cache, filled untimed
            case, paths = built["frog"] if "frog" in built else next(iter(built.values()))
            warm = run_volreg(case, paths, work / "warmup", args, cache, score=False)
            print(f"Untimed warm-up of volreg's numba cache on `{case.name}`: "
                  f"{warm.get('failed') or format(warm['seconds'], '.1f') + ' s'}.\n", flush=True)

        def save() -> None:
            if args.json is not None:
                args.json.write_text(json.dumps(record, indent=1))

        def runs_of(name: str, method: str) -> list[dict]:
            case, paths = built[name]
            runs = []
            for r in range(1 if name in once else args.repeats):
                out = work / f"{name}_{method}_{r}"
                res = (run_volreg(case, paths, out, args, cache) if method == "volreg"
                       else run_peer_timed(case, method, paths, out, args))
                if "failed" in res:
                    runs = [res]
                    break
                runs.append(res)
            record["runs"][f"{name}/{method}"] = runs
            save()
            return runs

        if args.first_run:
            case, paths = built["frog"]
            cold, warm, batch_cold, batch_warm = [], [], [], []
            for r in range(1 if "first-run" in once else args.repeats):
                fresh = work / f"numba-cold-{r}"
                cold.append(run_volreg(case, paths, work / f"first_cold_{r}", args, fresh, score=False))
                warm.append(run_volreg(case, paths, work / f"first_warm_{r}", args, fresh, score=False))
                fresh = work / f"numba-cold-batch-{r}"
                batch_cold.append(run_volreg_batch(paths, work / f"first_batch_cold_{r}", args, fresh))
                batch_warm.append(run_volreg_batch(paths, work / f"first_batch_warm_{r}", args, fresh))
            record["first_run"] = {"cold": cold, "warm": warm, "batch_cold": batch_cold, "batch_warm": batch_warm}
            save()
            every = cold + warm + batch_cold + batch_warm
            if any("failed" in r for r in every):
                print("First run: failed: " + next(r["failed"] for r in every if "failed" in r))
            else:
                print("| volreg on `frog` | wall s, median (runs) | peak RSS GB | numba cache files written |")
                print("|---|---|---|---|")
                for title, runs in (("`register`, empty numba cache (first run)", cold),
                                    ("`register`, warm cache (the run after)", warm),
                                    ("`batch`, both ways on 2 workers, empty cache", batch_cold),
                                    ("`batch`, both ways on 2 workers, warm cache", batch_warm)):
                    print(f"| {title} | {_median(runs, 'seconds'):.1f} ("
                          + ", ".join(f"{r['seconds']:.1f}" for r in runs) + f") | {_median(runs, 'peak_rss_gb'):.2f} "
                          f"| {int(np.median([r['compiled'] for r in runs]))} |")
                print()
        print("| case | method | wall s, median (runs) | peak RSS GB | endpoint error mean / p95 (mm) "
              f"| mean Dice, labels >= {LARGE} voxels | folded | volreg / greedy time |")
        print("|---|---|---|---|---|---|---|---|", flush=True)
        stage_rows = []
        for name in cases:
            medians = {}
            for method in methods:
                if f"{name}/{method}" in skip:
                    print(f"| {name} | {method} | not run (--skip) | | | | | |", flush=True)
                    continue
                runs = runs_of(name, method)
                if "failed" in runs[0]:
                    print(f"| {name} | {method} | failed: {runs[0]['failed']} | | | | | |", flush=True)
                    continue
                med = {k: _median(runs, k) for k in ("seconds", "peak_rss_gb", "epe_mean", "epe_p95", "dice", "folded")}
                medians[method] = med
                ratio = ""
                if method == "volreg" and "greedy" in medians:
                    ratio = f"{med['seconds'] / medians['greedy']['seconds']:.2f}"
                if method == "greedy" and "volreg" in medians:
                    ratio = f"{medians['volreg']['seconds'] / med['seconds']:.2f}"
                mark = " *" if method == "volreg" and any(r["compiled"] for r in runs) else ""
                print(f"| {name} | {method} | {med['seconds']:.1f} ("
                      + ", ".join(f"{r['seconds']:.1f}" for r in runs) + f"){mark} | {med['peak_rss_gb']:.2f} "
                      f"| {med['epe_mean']:.2f} / {med['epe_p95']:.2f} | {med['dice']:.4f} | {med['folded']:.5f} "
                      f"| {ratio} |", flush=True)
                if method == "volreg":
                    run = _median_run(runs)
                    stage_rows.append((name, run))
        print("\n(* a run in which numba still compiled something: new files in its cache)\n")

        if stage_rows:
            print("| case | volreg wall s (median run) | start, imports, reading (s) | stages from report.json (s) |")
            print("|---|---|---|---|")
            for name, run in stage_rows:
                print(f"| {name} | {run['seconds']:.1f} | {run['seconds'] - run['report_seconds']:.1f} "
                      f"| {_stage_text(run['stages'])} |")
            print(flush=True)

        if args.growth:
            for name in GROWTH:
                runs_of(name, "volreg")
            print("| case | voxels (M) | labels | boundary area (cm^2) | volreg wall s, median (runs) | peak RSS GB "
                  "| largest stages (s, median run) |")
            print("|---|---|---|---|---|---|---|")
            for name in ("frog", "frog-full", "labels2", "parcels", "labels500", "phantom"):
                runs = record["runs"].get(f"{name}/volreg")
                info = record["cases"].get(name)
                if not runs or info is None:
                    continue
                head = f"| {name} | {info['voxels_m']:.2f} | {info['labels']} | {info['area_cm2']:.0f} "
                if "failed" in runs[0]:
                    print(head + f"| failed: {runs[0]['failed']} | | |")
                    continue
                run = _median_run(runs)
                mark = " *" if any(r["compiled"] for r in runs) else ""
                print(head + f"| {_median(runs, 'seconds'):.1f} (" + ", ".join(f"{r['seconds']:.1f}" for r in runs)
                      + f"){mark} | {_median(runs, 'peak_rss_gb'):.2f} | {_stage_text(run['stages'], top=3)} |")
            print(flush=True)

        print(f"Total {(time.perf_counter() - t_start) / 60:.0f} min.", flush=True)
    finally:
        if args.json is not None:
            args.json.write_text(json.dumps(record, indent=1))
        if args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
