"""Throughput of ``volreg batch``: 1 against 2 LocalCluster workers, and the Dask overhead per task.

Run:  .venv/bin/python benchmarks/bench_batch.py [--subjects 8] [--repeats 3] [--protocol fast]

The cohort is generated: an ellipsoidal blob (label 1) around a sphere (label 2) on a 40^3 grid
of 1.5 mm voxels, and N subjects that are copies deformed by a known smooth warp (a Gaussian bump
of up to ~4 mm, different for each), all registered to the undeformed template.  For each repeat
and worker count a fresh ``volreg batch`` process runs on a fresh output folder, and we time
  * the whole command (start of the process to exit: cluster start-up, all tasks, summary files);
  * the sum of the per-task seconds it records in ``batch.csv`` (the registrations themselves);
and also, for reference, the same registrations run one after another in one process without
Dask (``volreg.register_labels`` and every output through ``volreg.write_registration``).
Throughput is registrations per minute of wall time.  The scheduler overhead per task is measured
separately on a running 1-worker LocalCluster: the round trip of 200 trivial tasks submitted one at
a time, per task.  Medians over the repeats; printed as a Markdown table.
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def make_cohort(folder: Path, n: int) -> Path:
    from volreg import LabelVolume
    from volreg.io import write_labels
    from volreg.synthetic import GaussianBumps, deform_labels

    shape, spacing = (40, 40, 40), np.array([1.5, 1.5, 1.5])
    tmp = LabelVolume(np.zeros(shape, np.uint8), (-30.0, -30.0, -30.0), spacing, np.eye(3))
    d = tmp.grid_points() - tmp.index_to_world((np.array(shape)[None] - 1) / 2.0)[0]
    arr = np.zeros(shape, np.uint8)
    arr[((d / [21.0, 17.0, 14.0]) ** 2).sum(-1) < 1] = 1
    arr[(((d - [4.0, 2.0, 0.0]) / 6.5) ** 2).sum(-1) < 1] = 2
    base = tmp.with_array(arr)
    write_labels(base, folder / "template.nii.gz")
    rng = np.random.default_rng(0)
    lines = ["id,path"]
    for i in range(n):
        bump = GaussianBumps(rng.uniform(-8, 8, (1, 3)), rng.uniform(-3, 3, (1, 3)), 25.0)
        write_labels(deform_labels(base, bump), folder / f"s{i}.nii.gz")
        lines.append(f"s{i},s{i}.nii.gz")
    (folder / "manifest.csv").write_text("\n".join(lines) + "\n")
    return folder / "manifest.csv"


def run_batch(manifest: Path, out: Path, workers: int, protocol: str) -> tuple[float, float]:
    volreg = Path(sys.executable).with_name("volreg")
    t0 = time.perf_counter()
    proc = subprocess.run([str(volreg), "batch", str(manifest), "-o", str(out), "--template",
                           str(manifest.parent / "template.nii.gz"), "--workers", str(workers), "--protocol", protocol,
                           "--quiet"], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"volreg batch failed: {proc.stderr.strip()[-2000:]}")
    rows = list(csv.DictReader((out / "batch.csv").read_text().splitlines()))
    return wall, sum(float(r["seconds"]) for r in rows)


def run_serial(manifest: Path, out: Path, protocol: str) -> float:
    """The same registrations, one after another in a fresh process, without Dask."""
    code = (
        "import sys, csv; from pathlib import Path; from volreg.cohort import read_manifest, run_pair\n"
        f"m = Path({str(manifest)!r}); t = m.parent / 'template.nii.gz'\n"
        "for sid, p in read_manifest(m):\n"
        f"    r = run_pair('template', str(t), sid, str(p), str(Path({str(out)!r}) / sid), {protocol!r})\n"
        "    assert r['status'] == 'done', r\n"
    )
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True)
    return time.perf_counter() - t0


def scheduler_overhead(n: int = 200) -> float:
    """Seconds per trivial task, submitted and awaited one at a time on a 1-worker LocalCluster."""
    from dask.distributed import Client, LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        client.submit(abs, -1, pure=False).result()  # warm up
        t0 = time.perf_counter()
        for i in range(n):
            client.submit(abs, -i, pure=False).result()
        return (time.perf_counter() - t0) / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subjects", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--protocol", default="fast")
    args = parser.parse_args()
    results: dict[str, list[tuple[float, float]]] = {"serial (no Dask)": [], "batch, 1 worker": [], "batch, 2 workers": []}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        manifest = make_cohort(folder, args.subjects)
        for r in range(args.repeats):
            results["serial (no Dask)"].append((run_serial(manifest, folder / f"serial{r}", args.protocol), float("nan")))
            for w in (1, 2):
                results[f"batch, {w} worker{'s' if w > 1 else ''}"].append(
                    run_batch(manifest, folder / f"w{w}r{r}", w, args.protocol))
            print(f"repeat {r + 1}: " + ", ".join(f"{k} {v[-1][0]:.1f} s" for k, v in results.items()), file=sys.stderr)
    overhead = statistics.median(scheduler_overhead() for _ in range(args.repeats))
    n = args.subjects
    base = statistics.median(w for w, _ in results["batch, 1 worker"])
    print(f"{n} registrations (40^3 blobs at 1.5 mm, protocol `{args.protocol}`), medians of {args.repeats} runs, "
          f"{os.cpu_count()} cores\n")
    print("| run | wall s | registrations / min | speed-up vs 1 worker | sum of task s |")
    print("|---|---|---|---|---|")
    for name, runs in results.items():
        wall = statistics.median(w for w, _ in runs)
        tasks = statistics.median(t for _, t in runs)
        print(f"| {name} | {wall:.1f} | {60 * n / wall:.1f} | {base / wall:.2f} | "
              f"{'' if np.isnan(tasks) else f'{tasks:.1f}'} |")
    print(f"\nDask round trip per trivial task (1-worker LocalCluster, 200 tasks one at a time): {1000 * overhead:.1f} ms")


if __name__ == "__main__":
    main()
