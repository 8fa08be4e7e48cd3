"""Templates of label maps: `volreg template` against ANTs `build_template` on cohorts made from a known template.

Run:  PYTHON benchmarks/bench_template.py --quick     (4 phantom subjects, ANTs 2 iterations)
      PYTHON benchmarks/bench_template.py             (8 subjects of the phantom and of the frog)

The Python that runs the script needs volreg; ANTs runs in `--peer-python` (a Python with
antspyx, the bench extra; default this one). volreg runs as `--volreg-command` (default: the
repository's `.venv/bin/volreg`; e.g. `"env PYTHONPATH=SNAPSHOT .venv/bin/python -m volreg"` for a
source snapshot).

A cohort is made from a KNOWN template T by known maps whose mean is about the identity, so
that T is the cohort's mean shape and a template builder should find it (up to a global pose):

- templates (`--cohorts`): `phantom`, the folded grey / white cortex phantom of `bench_speed.py` at
  2 mm; `frog`, pyvista's frog tissues at 3 mm (block mode 3 x 3 x 2, as `volreg demo`);
- subjects (`--subjects`, even): subject i holds, at each voxel centre y, the label of T at
  psi_i^-1(y) (label-preserving `volreg.warp.resample.resample_labels`), psi_i = pose_i o bumps_i
  (template point -> subject point). The maps come in pairs: subject 2k is warped by smooth bumps
  of amplitude +a (`common.smooth_bumps`: 10 Gaussian bumps over the labels' box, scale 0.15 x its
  diagonal; `--amplitude`, default 7 mm) then posed by a small affine map P_k (:func:`pair_pose`:
  2-5 degrees about a random axis after a stretch of up to 3 %, a 2-5 mm shift, about the labels'
  centroid); subject 2k + 1 by the same bumps of amplitude -a, then P_k^-1. The bumps cancel
  exactly in the mean and the poses to first order. Every subject is on one grid of T's spacing
  covering all of them (ANTs builds its template on the first image's grid). Seeded (`--seed`).

Methods, each one fresh process timed from start to exit (`common.timed`), 2 threads:

- `volreg`: `volreg template MANIFEST -o OUT --workers 1 --quiet` (one Dask worker of 2 numba
  threads; `--protocol`, default `default`; its own iterations, at most 5). Its
  `OUT/subjects/ID/warp.nii.gz` is the pull-back field on the template grid: template point x is
  subject point x + u_i(x). An untimed `volreg register` of two subjects first compiles whatever
  volreg's numba cache lacks.
- `ants`: antspyx `ants.build_template(image_list=...)` on the subjects' label images read as
  float (SyN, `--ants-iterations`, default 3 as antspyx's), then the labels the way the ANTs
  maintainers make them: every subject registered to the built template (`ants.registration`,
  SyN), its labels warped to it (`ants.apply_transforms(..., interpolator="genericLabel")`) and the
  per-voxel majority vote (ties to the background, then to the lower label, as volreg's vote). The
  forward transforms of each subject's registration composed into one displacement field on the
  template grid (`ants.apply_transforms(..., compose=...)`, as `common.run_peer`) give the same
  correspondence as volreg's field. The wall time holds all of it.

Scores, the same code for both methods: the built template B is aligned to T by the affine map
F = `volreg.warp.linear.fit_linear(T, B, kind="affine")` (T point -> B point), which removes the
free global pose; G = F^-1. On T's grid, B read through F (label-preserving resampling) against T:
the mean Dice over T's labels, the worst label's Dice, the mean over the labels of the symmetric
mean surface distance (`volreg.evaluation.metrics.label_scores`, mm). Subject i's endpoint error
at T's labelled voxel centres x: |b + u_i(b) - psi_i(x)| with b = F(x), the field interpolated
trilinearly (B's template point b is T's point G(b) = x, which subject i holds at psi_i(x)); mean
and 95th percentile per subject, averaged over the subjects. Also the pose that F removes (mean
|F(x) - x| over T's labels) and the identity's endpoint error (|psi_i(x) - x|: the cohort's spread).
A reference row scores, the same way, the vote of the subjects read back onto T's grid through
their true maps: the Dice and boundary distance that the subjects' own voxels leave reachable.

Output: Markdown on stdout (a table per cohort and the ratios volreg / ANTs), and in `--out`
(default benchmarks/out/template) `templates.csv` / `templates.json` (a row per cohort and
method) and `subjects.csv` / `subjects.json` (a row per cohort, method and subject).
"""

from __future__ import annotations

import argparse
import csv
import json
import shlex
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO / "tests"))

from common import CHUNK, add_run_options, grid_text, last_line, print_header, run_env, smooth_bumps, timed

COHORTS = ("phantom", "frog")
METHODS = ("volreg", "ants")
QUICK_SUBJECTS = 4
QUICK_ANTS_ITERATIONS = 2
TEMPLATE_KEYS = ("cohort", "method", "subjects", "dice_mean", "dice_worst", "dice_worst_label", "boundary_mm",
                 "epe_mean", "epe_p95", "pose_removed_mm", "iterations", "seconds", "peak_rss_gb", "failed")
SUBJECT_KEYS = ("cohort", "method", "subject", "epe_mean", "epe_p95", "identity_epe_mean", "failed")


# ----------------------------------------------------------------------------- the cohorts


def known_template(name: str):
    """The known template of cohort ``name`` (one of COHORTS) and its title."""
    from bench_accuracy import class_volume

    if name == "phantom":
        return class_volume("phantom")
    if name == "frog":
        return class_volume("frog-3mm")
    raise ValueError(f"Expected a cohort in {COHORTS}, got {name!r}.")


def pair_pose(template, seed: int):
    """A small affine pose about the template labels' centroid: a rotation of 2-5 degrees about a
    random axis after a stretch of up to 3 % along three random orthogonal axes, then a 2-5 mm shift.

    Returns
    -------
    bench_pose.Pose
    """
    from bench_pose import Pose, unit
    from shapes import rotation

    rng = np.random.default_rng(seed)
    frame = rotation(rng.uniform(0, 180), rng.normal(size=3))
    stretch = frame @ np.diag(1.0 + rng.uniform(-0.03, 0.03, 3)) @ frame.T
    matrix = rotation(rng.uniform(2, 5), rng.normal(size=3)) @ stretch
    centre = template.grid_points()[template.array > 0].mean(axis=0)
    return Pose(matrix, centre, rng.uniform(2, 5) * unit(rng.normal(size=3)))


def inverse_pose(pose):
    """``pose``'s inverse as a Pose about the same centre: ``A^-1 (y - c) + c - A^-1 t``."""
    from bench_pose import Pose

    inv = np.linalg.inv(pose.matrix)
    return Pose(inv, pose.centre, -inv @ pose.shift)


@dataclass
class Cohort:
    """A generated cohort on disk: the known template, the subjects and their true maps."""

    name: str
    title: str
    known: object  # LabelVolume
    manifest: Path
    ids: list[str]
    truths: dict  # id -> bench_pose.Truth: template point -> subject point
    info: dict  # grid, identity EPE, the mean map's distance to the identity


def cohort_maps(known, subjects: int, amplitude: float, seed: int) -> dict:
    """The true maps of ``subjects`` subjects (ids s00, s01, ...), in pairs that average to about
    the identity: (P_k o bumps_k, P_k^-1 o (-bumps_k))."""
    from bench_pose import Truth

    from volreg.synthetic import GaussianBumps

    truths = {}
    for k in range(subjects // 2):
        bumps = smooth_bumps(known, amplitude, seed=1000 * seed + k)
        negated = GaussianBumps(bumps.centres, -bumps.amplitudes, bumps.scale)
        pose = pair_pose(known, 2000 + 1000 * seed + k)
        truths[f"s{2 * k:02d}"] = Truth(pose, bumps)
        truths[f"s{2 * k + 1:02d}"] = Truth(inverse_pose(pose), negated)
    return truths


def build_cohort(name: str, subjects: int, amplitude: float, seed: int, folder: Path) -> Cohort:
    """Cohort ``name`` in ``folder``: known.nii.gz, the subjects SID.nii.gz on one grid covering
    them all, manifest.csv."""
    from bench_pose import _box_grid, _sample

    from volreg.io import write_labels
    from volreg.warp.resample import resample_labels

    known, title = known_template(name)
    folder.mkdir(parents=True, exist_ok=True)
    write_labels(known, folder / "known.nii.gz", force=True)
    truths = cohort_maps(known, subjects, amplitude, seed)
    inside = known.grid_points()[known.array > 0]
    images = np.concatenate([t(inside) for t in truths.values()])
    grid = _box_grid(images, known.spacing, margin=6.0 + float(np.max(known.spacing)))
    del images
    rows = []
    for sid, truth in truths.items():
        subject = _sample(grid, lambda p: resample_labels(known, p), truth.inverse)
        write_labels(subject, folder / f"{sid}.nii.gz", force=True)
        rows.append((sid, f"{sid}.nii.gz"))
    manifest = folder / "manifest.csv"
    with open(manifest, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "path"])
        w.writerows(rows)
    mapped = np.stack([t(inside) for t in truths.values()])  # (S, N, 3)
    spread = np.linalg.norm(mapped - inside[None], axis=2)
    info = {"template_grid": grid_text(known), "subject_grid": grid_text(grid),
            "labels": [int(v) for v in known.labels() if v != 0],
            "identity_epe_mean": {sid: float(e.mean()) for sid, e in zip(truths, spread)},
            "mean_map_offset_mm": float(np.linalg.norm(mapped.mean(axis=0) - inside, axis=1).mean())}
    return Cohort(name, title, known, manifest, list(truths), truths, info)


# ----------------------------------------------------------------------------- ANTs (the peer)


def ants_template(manifest: str, out: str, iterations: str) -> None:
    """ANTs' template of the manifest's label maps into ``out`` (runs in the peer Python: antspyx
    and numpy only): ``template_float.nii.gz`` (``ants.build_template`` of the label images read as
    float), ``template.nii.gz`` (the majority vote of the subjects' labels warped to it with
    ``genericLabel``) and ``subjects/ID/warp.nii.gz`` (each subject's forward transforms to the
    template composed into one pull-back field on its grid)."""
    import ants

    out_dir = Path(out)
    with open(manifest, newline="") as f:
        rows = [(r["id"], Path(manifest).parent / r["path"]) for r in csv.DictReader(f)]
    images = [ants.image_read(str(p), pixeltype="float") for _, p in rows]
    template = ants.build_template(image_list=images, iterations=int(iterations), output_dir=str(out_dir / "build"))
    ants.image_write(template, str(out_dir / "template_float.nii.gz"))
    warped = []
    for (sid, _), image in zip(rows, images):
        folder = out_dir / "subjects" / sid
        folder.mkdir(parents=True, exist_ok=True)
        reg = ants.registration(template, image, type_of_transform="SyN", outprefix=str(folder / "ants_"))
        labels = ants.apply_transforms(template, image, reg["fwdtransforms"], interpolator="genericLabel")
        warped.append(np.rint(labels.numpy()).astype(np.int64))
        composed = ants.apply_transforms(template, image, reg["fwdtransforms"], compose=str(folder / "composed"))
        shutil.move(composed, folder / "warp.nii.gz")
    values = sorted({int(v) for w in warped for v in np.unique(w) if v != 0})
    counts = np.stack([sum((w == v).astype(np.int32) for w in warped) for v in values])
    background = len(warped) - counts.sum(axis=0)
    best = counts.argmax(axis=0)
    vote = np.asarray(values)[best]
    vote[np.take_along_axis(counts, best[None], axis=0)[0] <= background] = 0
    dtype = np.uint8 if max(values, default=0) < 256 else np.uint32
    image = ants.from_numpy(vote.astype(dtype), origin=template.origin, spacing=template.spacing,
                            direction=template.direction)
    ants.image_write(image, str(out_dir / "template.nii.gz"))
    shutil.rmtree(out_dir / "build", ignore_errors=True)


# ----------------------------------------------------------------------------- running and scoring


def method_command(method: str, cohort: Cohort, out: Path, args) -> list[str]:
    """The command line of ``method`` building ``cohort``'s template into ``out``."""
    if method == "volreg":
        return shlex.split(args.volreg_command) + ["template", str(cohort.manifest), "-o", str(out), "--workers", "1",
                                                   "--protocol", args.protocol, "--quiet"]
    return [args.peer_python, str(Path(__file__).resolve()), "--ants-template", str(cohort.manifest), str(out),
            str(args.ants_iterations)]


def field_at(u: np.ndarray, grid, points: np.ndarray) -> np.ndarray:
    """The displacement ``u`` on ``grid`` at world ``points`` (N, 3) mm, trilinear (the edge value
    beyond the grid), (N, 3) mm."""
    from scipy import ndimage

    index = grid.world_to_index(points).T
    return np.stack([ndimage.map_coordinates(u[..., c], index, order=1, mode="nearest") for c in range(3)], axis=1)


def score_template(cohort: Cohort, out: Path) -> tuple[dict, list[dict]]:
    """The scores of the template in ``out`` (``template.nii.gz`` and ``subjects/ID/warp.nii.gz``)
    against the known one (the module notes): the template's row and one row per subject."""
    from volreg.evaluation.metrics import label_scores
    from volreg.io import read_labels
    from volreg.io.fields import read_displacement
    from volreg.warp.linear import fit_linear
    from volreg.warp.resample import resample_labels

    known = cohort.known
    built = read_labels(out / "template.nii.gz")
    to_built = fit_linear(known, built, kind="affine").map
    x = known.grid_points().reshape(-1, 3)
    aligned = resample_labels(built, to_built(x)).reshape(known.shape)
    labels = cohort.info["labels"]
    per_label = label_scores(known.array, aligned, labels, known.spacing)
    dices = {v: s["dice"] for v, s in per_label.items()}
    worst = min(dices, key=dices.get)
    inside = x[known.array.ravel() > 0]
    del x
    b = to_built(inside)
    row = {"dice_mean": float(np.mean(list(dices.values()))), "dice_worst": dices[worst], "dice_worst_label": worst,
           "boundary_mm": float(np.nanmean([s["mean_surface_distance_mm"] for s in per_label.values()])),
           "pose_removed_mm": float(np.linalg.norm(b - inside, axis=1).mean())}
    subjects = []
    for sid in cohort.ids:
        path = out / "subjects" / sid / "warp.nii.gz"
        if not path.is_file():
            subjects.append({"subject": sid, "failed": "no warp.nii.gz"})
            continue
        u, grid = read_displacement(path)
        err = np.empty(len(b))
        for s in range(0, len(b), CHUNK):
            p = b[s : s + CHUNK]
            err[s : s + CHUNK] = np.linalg.norm(p + field_at(u, grid, p) - cohort.truths[sid](inside[s : s + CHUNK]),
                                                axis=1)
        subjects.append({"subject": sid, "epe_mean": float(err.mean()), "epe_p95": float(np.percentile(err, 95)),
                         "identity_epe_mean": cohort.info["identity_epe_mean"][sid]})
    scored = [s for s in subjects if "failed" not in s]
    if scored:
        row["epe_mean"] = float(np.mean([s["epe_mean"] for s in scored]))
        row["epe_p95"] = float(np.mean([s["epe_p95"] for s in scored]))
    return row, subjects


def known_maps_row(cohort: Cohort) -> dict:
    """The reference row: the subjects read back onto the known template's grid through their true
    maps (label-preserving resampling at psi_i(x)) and voted, scored as a built template is (no
    pose to remove, no endpoint error): what the subjects' own voxels let a template reach."""
    from volreg.evaluation.metrics import label_scores
    from volreg.io import read_labels
    from volreg.pipeline.template_shape import vote
    from volreg.warp.resample import resample_labels

    known = cohort.known
    labels = cohort.info["labels"]
    x = known.grid_points().reshape(-1, 3)
    counts = np.zeros((len(labels), *known.shape), np.uint16)
    for sid in cohort.ids:
        subject = read_labels(cohort.manifest.parent / f"{sid}.nii.gz")
        back = resample_labels(subject, cohort.truths[sid](x)).reshape(known.shape)
        for k, v in enumerate(labels):
            counts[k] += back == v
    voted = vote(counts, len(cohort.ids), np.array(labels))
    per_label = label_scores(known.array, voted, labels, known.spacing)
    dices = {v: s["dice"] for v, s in per_label.items()}
    worst = min(dices, key=dices.get)
    return {"cohort": cohort.name, "method": "known-maps", "subjects": len(cohort.ids),
            "dice_mean": float(np.mean(list(dices.values()))), "dice_worst": dices[worst], "dice_worst_label": worst,
            "boundary_mm": float(np.nanmean([s["mean_surface_distance_mm"] for s in per_label.values()]))}


def run_method(method: str, cohort: Cohort, out: Path, args) -> tuple[dict, list[dict]]:
    """One timed run of ``method`` on ``cohort`` in ``out`` (its log beside it), scored."""
    shutil.rmtree(out, ignore_errors=True)  # a run stopped before its cleanup
    out.mkdir(parents=True)
    log = out.parent / f"{out.name}.log"
    rc, seconds, rss = timed(method_command(method, cohort, out, args), log, out, args.timeout, env=run_env())
    row = {"cohort": cohort.name, "method": method, "subjects": len(cohort.ids), "seconds": seconds,
           "peak_rss_gb": rss}
    if rc != 0 or not (out / "template.nii.gz").is_file():
        row["failed"] = last_line(log, rc, seconds)
        return row, []
    if method == "volreg":
        report = json.loads((out / "report.json").read_text())
        row["iterations"] = f"{len(report['iterations'])} ({report['stopped']})"
    else:
        row["iterations"] = str(args.ants_iterations)
    scores, subjects = score_template(cohort, out)
    row.update(scores)
    return row, [{"cohort": cohort.name, "method": method, **s} for s in subjects]


def warm_up(cohort: Cohort, work: Path, args) -> str:
    """An untimed ``volreg register`` of the first two subjects (numba compiles what its cache
    lacks); its time or its failure."""
    out = work / "warmup"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    a, b = (str(cohort.manifest.parent / f"{sid}.nii.gz") for sid in cohort.ids[:2])
    command = shlex.split(args.volreg_command) + ["register", a, b, "-o", str(out), "--quiet",
                                                  "--protocol", args.protocol]
    rc, seconds, _ = timed(command, work / "warmup.log", out, args.timeout, env=run_env())
    shutil.rmtree(out, ignore_errors=True)
    return f"{seconds:.1f} s" if rc == 0 else last_line(work / "warmup.log", rc, seconds)


# ----------------------------------------------------------------------------- the tables


def method_name(method: str, args) -> str:
    """The table's name of ``method``."""
    if method == "known-maps":
        return "(reference: the subjects read back through their true maps, voted)"
    if method == "volreg":
        return "volreg template" + ("" if args.protocol == "default" else f" ({args.protocol})")
    return "ANTs build_template + genericLabel vote"


def markdown_table(rows: list[dict], args) -> str:
    """A cohort's rows as a Markdown table."""
    lines = [("| method | template Dice, mean / worst label | boundary distance (mm) | subjects' EPE mean / p95 (mm) "
              "| pose removed (mm) | iterations | wall s | peak RSS GB |"), "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        name = method_name(r["method"], args)
        if "failed" in r:
            lines.append(f"| {name} | failed: {r['failed']} | | | | | {r['seconds']:.0f} | |")
            continue
        head = (f"| {name} | {r['dice_mean']:.4f} / {r['dice_worst']:.4f} (label {r['dice_worst_label']}) "
                f"| {r['boundary_mm']:.2f} ")
        if r["method"] == "known-maps":
            lines.append(head + "| 0 | 0 | | | |")
            continue
        epe = f"{r['epe_mean']:.2f} / {r['epe_p95']:.2f}" if "epe_mean" in r else "no subject scored"
        lines.append(head + f"| {epe} | {r['pose_removed_mm']:.2f} | {r['iterations']} | {r['seconds']:.0f} "
                     f"| {r['peak_rss_gb']:.2f} |")
    return "\n".join(lines)


def ratios(rows: list[dict]) -> str:
    """The line of volreg / ANTs ratios of a cohort's scores, or why there is none."""
    by = {r["method"]: r for r in rows}
    if not all(m in by and "failed" not in by[m] and "epe_mean" in by[m] for m in METHODS):
        return "No ratios: a method failed."
    v, a = by["volreg"], by["ants"]
    parts = [f"{label} {v[key] / a[key]:.2f}" for label, key in
             (("Dice mean", "dice_mean"), ("worst label's Dice", "dice_worst"), ("boundary distance", "boundary_mm"),
              ("EPE mean", "epe_mean"), ("EPE p95", "epe_p95"), ("wall time", "seconds"))]
    return "volreg / ANTs: " + ", ".join(parts) + "."


def write_rows(rows: list[dict], keys, out: Path, name: str) -> None:
    """``rows`` as ``out``/NAME.csv and ``out``/NAME.json."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(rows, indent=1))
    with open(out / f"{name}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(keys), extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


# ----------------------------------------------------------------------------- main


def parse_args() -> argparse.Namespace:
    """The command line (``--quick`` sets the subjects, the cohorts and ANTs' iterations)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help=f"{QUICK_SUBJECTS} subjects of the phantom only, ANTs with {QUICK_ANTS_ITERATIONS} "
                             "iterations")
    parser.add_argument("--cohorts", default=",".join(COHORTS), help=f"comma-separated subset of {','.join(COHORTS)}")
    parser.add_argument("--subjects", type=int, default=8, help="subjects per cohort, even (default 8)")
    parser.add_argument("--amplitude", type=float, default=7.0,
                        help="largest displacement of the bumps, mm (default 7)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the maps (default 0)")
    parser.add_argument("--protocol", default="default", help="volreg's protocol (a preset name or a file)")
    parser.add_argument("--ants-iterations", type=int, default=None,
                        help=f"iterations of ants.build_template (default 3; {QUICK_ANTS_ITERATIONS} with --quick)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out" / "template",
                        help="folder for templates.csv/.json and subjects.csv/.json (default: benchmarks/out/template)")
    parser.add_argument("--ants-template", nargs=3, metavar=("MANIFEST", "OUT", "ITERATIONS"), help=argparse.SUPPRESS)
    add_run_options(parser)
    args = parser.parse_args()
    if args.ants_template:
        return args
    if args.quick:
        args.subjects, args.cohorts = QUICK_SUBJECTS, "phantom"
    if args.ants_iterations is None:
        args.ants_iterations = QUICK_ANTS_ITERATIONS if args.quick else 3
    args.cohorts = [c for c in args.cohorts.split(",") if c]
    for c in args.cohorts:
        if c not in COHORTS:
            parser.error(f"argument --cohorts: expected names from {','.join(COHORTS)}, got {c!r}")
    if args.subjects < 2 or args.subjects % 2:
        parser.error(f"argument --subjects: expected an even number of at least 2, got {args.subjects}")
    if args.ants_iterations < 1:
        parser.error(f"argument --ants-iterations: expected a positive integer, got {args.ants_iterations}")
    if not args.amplitude > 0:
        parser.error(f"argument --amplitude: expected a positive number of mm, got {args.amplitude}")
    return args


def main() -> None:
    args = parse_args()
    if args.ants_template:
        ants_template(*args.ants_template)
        return
    print_header("bench_template.py")
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_template_"))
    work.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    templates: list[dict] = []
    subjects: list[dict] = []
    try:
        warmed = False
        for name in args.cohorts:
            t0 = time.perf_counter()
            cohort = build_cohort(name, args.subjects, args.amplitude, args.seed, work / name / "cohort")
            spread = list(cohort.info["identity_epe_mean"].values())
            print(f"### {name}: {cohort.title}\n\nKnown template {cohort.info['template_grid']}, "
                  f"{len(cohort.info['labels'])} labels; {len(cohort.ids)} subjects on {cohort.info['subject_grid']} "
                  f"(built in {time.perf_counter() - t0:.0f} s), warped by bumps of +/- {args.amplitude:g} mm and "
                  f"posed; their maps' distance to the identity (the identity's EPE) {np.mean(spread):.2f} mm on "
                  f"average, the mean map's {cohort.info['mean_map_offset_mm']:.2f} mm.\n", flush=True)
            if not warmed:
                print(f"Untimed volreg warm-up (register s00 s01): {warm_up(cohort, work, args)}.\n", flush=True)
                warmed = True
            rows = [known_maps_row(cohort)]
            templates.append(rows[0])
            for method in METHODS:
                row, scored = run_method(method, cohort, work / name / method, args)
                rows.append(row)
                templates.append(row)
                subjects.extend(scored)
                write_rows(templates, TEMPLATE_KEYS, args.out, "templates")
                write_rows(subjects, SUBJECT_KEYS, args.out, "subjects")
                print(f"- {method}: {row.get('failed') or format(row['seconds'], '.0f') + ' s'}", flush=True)
            print("\n" + markdown_table(rows, args) + "\n\n" + ratios(rows) + "\n", flush=True)
        print(f"Rows in {args.out}; total {(time.perf_counter() - t_start) / 60:.1f} min.", flush=True)
    finally:
        if args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
