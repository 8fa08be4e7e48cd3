"""Accuracy over many generated pairs: the distribution of volreg's errors beside greedy's and ANTs'.

Run:  PYTHON benchmarks/bench_accuracy.py --quick                        (volreg default, a few minutes)
      PYTHON benchmarks/bench_accuracy.py --methods volreg,volreg-accurate,greedy,ants   (every pair)

The Python that runs the script needs volreg and, for the peers, the bench extra (antspyx,
picsl_greedy); the peers run in it (or in `--peer-python`). volreg runs as `--volreg-command`
(default: the repository's `.venv/bin/volreg`; e.g. `"env PYTHONPATH=SNAPSHOT .venv/bin/python -m
volreg"` for a source snapshot).

A yardstick to run before and after every change to the numerics: a few pairs per benchmark hide
losses on some shapes (small organs, thin structures), so here every method meets the same many
pairs and the table shows the median and the worst pair of each class.

Classes of label maps (the fixed volume of every pair of a class):

- `frog-3mm`: pyvista's frog tissues block-downsampled 3 x 3 x 2 (3 mm), as `volreg demo` builds it;
- `frog-1.5mm`: the same tissues at 2 x 2 x 1.5 mm (block mode 2 x 2 x 1, the native slices kept);
- `phantom`: the folded two-label cortex phantom of `bench_speed.py` (grey shell, white core) at 2 mm;
- `parcels`: that phantom at 2 mm with its grey shell split into 99 Voronoi cells: 100 labels;
- `thin`: generated thin structures at 1 mm (:func:`thin_structures`): three spherical shells 2 mm
  thick and six winding tubes 2 to 4 mm across.

Pairs: per class, seeds 0 .. `--seeds` - 1; seed k warps by a smooth random map of amplitude
AMPLITUDES[k % 3] mm (4, 8, 12) and, for odd k, also poses the moving volume by a small affine map
(:func:`small_pose`: 5-12 degrees about a random axis, a 5-12 mm shift, a stretch of up to 5 % along
random axes, about the labels' centroid). Seeds 0-5 of every twelve warp by a smooth map
(`common.smooth_bumps`: 10 Gaussian bumps over the labels' box, scale 0.15 x its diagonal, as
`volreg demo`), seeds 6-11 by a local one (:func:`local_bumps`: 30 bumps, scale 0.07 x the diagonal
but at least 2.5 x the amplitude), which moves neighbouring small structures apart. So twelve seeds
(the default) cover every amplitude, with and without a pose, smooth and local: four per amplitude.

The true pull-back map is tau_true = pose o bumps (`bench_pose.Truth`). The moving volume holds, at
each voxel centre y, the labels at tau_true^-1(y), on the fixed grid without a pose and on a grid of
the fixed spacing covering the posed labels otherwise (`bench_pose`'s moving grid). The frogs read
those labels from the native 1 x 1 x 1.5 mm tissues (nearest neighbour) and the thin structures from
their exact description (:func:`class_source`), so each volume of a pair has its own staircase, as
two subjects' scans do; the phantoms read them from the fixed labels (label-preserving
`volreg.warp.resample.resample_labels`). Everything is seeded; the pairs are
cached under `--work` and built again only when their description changes.

Methods, each a fresh process timed from start to exit with 2 threads (`common.timed`):

- `volreg`: `volreg register FIXED MOVING -o OUT --quiet`; `volreg-accurate`: the same with
  `--protocol accurate`; `volreg@P`: with `--protocol P` (a shipped name or a protocol file), to
  compare settings on the same pairs;
- `greedy`: picsl_greedy, affine (image centres start) then deformable; `ants`: antspyx SyN (centre of
  mass, affine, SyN): both with an affine stage, as the posed pairs need (`common.run_peer`); any other
  name of `common.PEERS` is accepted too.

volreg's numba cache is its own; one untimed volreg run per protocol on the smallest pair first
compiles whatever it lacks.

Scores per pair (`common.score_field`, on each method's field on the fixed grid): endpoint error
|tau(x) - tau_true(x)| at the fixed labels' voxel centres (mean, 95th percentile, mm); mean Dice over
the fixed labels of at least 100 voxels; that Dice minus the true map's (the fixed labels against the
moving labels read through tau_true, scored the same way: the moving volume's resampling loses a
little, so 0 is no loss against the truth and a positive value fits the voxels past it); the folded
fraction; wall seconds. The table: per method and class, the median and the worst pair of each
(largest error, smallest Dice difference) with the worst pair's seed, and the median time.

Output: Markdown on stdout, a compact summary (one line per method and class, for a commit
message), and every pair's row in `--out` (pairs.csv, pairs.json).
"""

from __future__ import annotations

import argparse
import csv
import json
import re
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

from common import (
    LARGE, PEERS, add_run_options, last_line, print_header, run_env, run_peer, score_field, smooth_bumps, timed,
)

CLASSES = ("frog-3mm", "frog-1.5mm", "phantom", "parcels", "thin")
AMPLITUDES = (4.0, 8.0, 12.0)  # mm: seed k warps by AMPLITUDES[k % 3]
VOLREG_METHODS = {"volreg": (), "volreg-accurate": ("--protocol", "accurate")}
METHODS = tuple(VOLREG_METHODS) + PEERS
#: ``--quick``: per class, the seeds run (a posed 8 mm pair everywhere, and the unposed 12 mm pair
#: of the classes that are quick to register); the finer frog is left out.
QUICK = {"frog-3mm": (1, 2, 7), "phantom": (1, 2), "parcels": (1,), "thin": (1, 8)}
#: The description of how the pairs are made: a change here builds the cached pairs again.
PAIR_VERSION = 2
#: Seeds k with (k // 6) % 2 == 1 warp by :func:`local_bumps`.
LOCAL_SCALE, LOCAL_COUNT, LOCAL_MIN_RATIO = 0.07, 30, 2.5
SCORES = ("epe_mean", "epe_p95", "dice_gap")


# ----------------------------------------------------------------------------- the label maps


def thin_labels(*, seed: int = 5, size: int = 96, spacing: float = 1.0, shells: int = 3, tubes: int = 6):
    """Thin and small structures as a function of position: ``shells`` spherical shells 2 x
    ``spacing`` thick (labels 1..shells), then ``tubes`` winding tubes 2-4 x ``spacing`` across
    (labels shells+1 .. shells+tubes, drawn over the shells), in a cube of ``size`` x ``spacing`` mm
    centred at the origin.

    A tube follows ``a + t (b - a) + sum_k c_k sin(pi k t)`` (``t`` in [0, 1], ``k`` = 1, 2) between
    two random points near opposite faces, with random bends ``c_k`` up to 0.15 x the cube's side; a
    shell has its radius between 0.12 and 0.22 x the side.

    Parameters
    ----------
    seed : int
        Of ``numpy.random.default_rng``: the same seed, the same structures.
    size : int
    spacing : float, mm
    shells, tubes : int

    Returns
    -------
    callable
        ``labels(points)``: (N, 3) mm -> (N,) uint8, 0 outside every structure.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    side = size * spacing
    spheres = []
    for _ in range(shells):
        radius = side * rng.uniform(0.12, 0.22)
        spheres.append((rng.uniform(-1, 1, 3) * (side / 2 - radius - 3 * spacing), radius))
    t = np.linspace(0.0, 1.0, int(4 * side / spacing))[:, None]
    curves = []
    for _ in range(tubes):
        axis = rng.integers(3)
        a, b = rng.uniform(-0.35, 0.35, (2, 3)) * side
        a[axis], b[axis] = -0.42 * side, 0.42 * side
        bends = rng.uniform(-0.15, 0.15, (2, 3)) * side
        curve = a + t * (b - a) + np.sin(np.pi * t) * bends[0] + np.sin(2 * np.pi * t) * bends[1]
        curves.append((cKDTree(curve), spacing * rng.uniform(1.0, 2.0)))  # 2-4 voxels across

    def labels(points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, float)
        out = np.zeros(len(points), np.uint8)
        for k, (centre, radius) in enumerate(spheres):
            out[np.abs(np.linalg.norm(points - centre, axis=1) - radius) < spacing] = k + 1
        for k, (tree, radius) in enumerate(curves):
            out[np.isfinite(tree.query(points, distance_upper_bound=radius)[0])] = shells + k + 1
        return out

    return labels


def thin_structures(*, seed: int = 5, size: int = 96, spacing: float = 1.0, shells: int = 3, tubes: int = 6):
    """:func:`thin_labels` at the voxel centres of a cube of ``size`` voxels of ``spacing`` mm
    centred at the origin.

    Returns
    -------
    LabelVolume
        uint8 labels 0 (background) to ``shells + tubes``.
    """
    from volreg.grid import LabelVolume

    origin = np.full(3, -(size - 1) * spacing / 2.0)
    volume = LabelVolume(np.zeros((size,) * 3, np.uint8), origin, np.full(3, spacing), np.eye(3))
    labels = thin_labels(seed=seed, size=size, spacing=spacing, shells=shells, tubes=tubes)
    return volume.with_array(labels(volume.grid_points().reshape(-1, 3)).reshape(volume.shape))


def _frog(factors):
    from volreg.demo import block_mode, frog_path
    from volreg.io import read_labels

    return block_mode(read_labels(frog_path()), factors)


def class_volume(name: str):
    """The fixed label volume of class ``name`` (one of CLASSES) and its title."""
    if name == "frog-3mm":
        return _frog((3, 3, 2)), "frog tissues, 3 mm (block mode 3 x 3 x 2, as `volreg demo`)"
    if name == "frog-1.5mm":
        return _frog((2, 2, 1)), "frog tissues, 2 x 2 x 1.5 mm (block mode 2 x 2 x 1)"
    if name in ("phantom", "parcels"):
        from bench_speed import cortex_phantom, parcellate

        phantom = cortex_phantom(2.0)
        if name == "phantom":
            return phantom, "cortex phantom, grey / white, 2 mm"
        return parcellate(phantom, 100), "cortex phantom parcellated, 100 labels, 2 mm"
    if name == "thin":
        return thin_structures(), "thin structures: 3 shells 2 mm thick, 6 tubes 2-4 mm across, 1 mm"
    raise ValueError(f"Expected a class in {CLASSES}, got {name!r}.")


def class_source(name: str):
    """Where the moving volumes of class ``name`` read their labels: ``labels(points)`` ((N, 3) mm ->
    (N,) labels) from a finer or exact description of the same structures, so that the moving
    volume's staircase is its own, not the fixed one's resampled (as two subjects' are); None where the
    class has none (the moving labels are then the fixed ones read through the true map)."""
    if name in ("frog-3mm", "frog-1.5mm"):
        from volreg.demo import frog_path
        from volreg.io import read_labels
        from volreg.warp.resample import resample_labels

        native = read_labels(frog_path())  # 1 x 1 x 1.5 mm
        return lambda p: resample_labels(native, p, method="nearest")
    if name == "thin":
        return thin_labels()
    return None


# ----------------------------------------------------------------------------- the pairs


def local_bumps(fixed, max_displacement: float, seed: int):
    """A local random warp: LOCAL_COUNT Gaussian bumps over the fixed labels' box, of scale
    LOCAL_SCALE x its diagonal but at least LOCAL_MIN_RATIO x ``max_displacement`` (so that it stays
    invertible), rescaled to ``max_displacement`` mm.

    Returns
    -------
    volreg.synthetic.GaussianBumps
    """
    from volreg.synthetic import GaussianBumps

    points = fixed.grid_points()[fixed.array > 0]
    lo, hi = points.min(axis=0), points.max(axis=0)
    scale = max(LOCAL_SCALE * float(np.linalg.norm(hi - lo)), LOCAL_MIN_RATIO * max_displacement)
    return GaussianBumps.random(lo, hi, max_displacement=max_displacement, scale=scale, count=LOCAL_COUNT,
                                rng=np.random.default_rng(seed))


def small_pose(fixed, seed: int):
    """A small affine pose about the fixed labels' centroid: a rotation of 5-12 degrees about a random
    axis after a stretch of up to 5 % along three random orthogonal axes, then a 5-12 mm shift.

    Returns
    -------
    bench_pose.Pose
    """
    from bench_pose import Pose, unit
    from shapes import rotation

    rng = np.random.default_rng(1000 + seed)
    frame = rotation(rng.uniform(0, 180), rng.normal(size=3))
    stretch = frame @ np.diag(1.0 + rng.uniform(-0.05, 0.05, 3)) @ frame.T
    matrix = rotation(rng.uniform(5, 12), rng.normal(size=3)) @ stretch
    centre = fixed.grid_points()[fixed.array > 0].mean(axis=0)
    return Pose(matrix, centre, rng.uniform(5, 12) * unit(rng.normal(size=3)))


@dataclass
class Pair:
    """A generated pair on disk: its files, its true map and what describes it."""

    name: str  # CLASS/sSEED
    cls: str
    seed: int
    amplitude: float  # mm
    posed: bool
    fixed_path: Path
    moving_path: Path
    truth: object  # bench_pose.Truth: fixed point -> moving point
    info: dict  # identity_epe, truth scores, grid sizes


def pair_spec(cls: str, seed: int) -> dict:
    """What describes the pair ``cls``/``seed``: a cached pair is reused only while it is the same."""
    return {"version": PAIR_VERSION, "class": cls, "seed": seed, "amplitude": AMPLITUDES[seed % 3],
            "posed": bool(seed % 2), "local": bool((seed // 6) % 2)}


def _truth_of(z):
    from bench_pose import Pose, Truth

    from volreg.synthetic import GaussianBumps

    bumps = GaussianBumps(z["centres"], z["amplitudes"], float(z["scale"]))
    return Truth(Pose(z["matrix"], z["centre"], z["shift"]), bumps)


def build_pair(cls: str, seed: int, fixed, fixed_path: Path, folder: Path) -> Pair:
    """The pair ``cls``/``seed`` in ``folder``: read from there when its spec matches, else made
    (moving volume, true map, the true map's field and scores) and written there."""
    from bench_pose import Pose, Truth, _posed_moving, _sample

    from volreg.io import read_labels, write_labels
    from volreg.io.fields import write_displacement
    from volreg.synthetic import deform_labels
    from volreg.warp.resample import resample_labels

    spec = pair_spec(cls, seed)
    meta_path, moving_path, truth_path = folder / "pair.json", folder / "moving.nii.gz", folder / "truth.npz"
    if meta_path.exists() and moving_path.exists() and truth_path.exists():
        meta = json.loads(meta_path.read_text())
        if meta.get("spec") == spec:
            with np.load(truth_path) as z:
                truth = _truth_of(z)
            return Pair(f"{cls}/s{seed}", cls, seed, spec["amplitude"], spec["posed"], fixed_path, moving_path, truth,
                        meta["info"])
    folder.mkdir(parents=True, exist_ok=True)
    bumps = (local_bumps if spec["local"] else smooth_bumps)(fixed, spec["amplitude"], seed=seed)
    pose = small_pose(fixed, seed) if spec["posed"] else Pose(np.eye(3), np.zeros(3), np.zeros(3))
    truth = Truth(pose, bumps)
    source = class_source(cls)
    if spec["posed"]:
        moving = _posed_moving(fixed, truth, source or (lambda p: resample_labels(fixed, p)), fixed.spacing)
    elif source is not None:
        moving = _sample(fixed, source, truth.inverse)
    else:
        moving = deform_labels(fixed, bumps)
    write_labels(moving, moving_path, force=True)
    np.savez(truth_path, centres=bumps.centres, amplitudes=bumps.amplitudes, scale=bumps.scale, matrix=pose.matrix,
             centre=pose.centre, shift=pose.shift)
    # the true map's field, written and read back as a method's is, and scored the same way
    x = fixed.grid_points().reshape(-1, 3)
    field = folder / "truth_warp.nii.gz"
    write_displacement((truth(x) - x).reshape(*fixed.shape, 3), fixed, field, force=True)
    moving = read_labels(str(moving_path))
    scores = score_field(fixed, moving, truth, field)
    inside = x[fixed.array.ravel() > 0]
    e0 = np.linalg.norm(truth(inside) - inside, axis=1)
    info = {"identity_epe_mean": float(e0.mean()), "identity_epe_p95": float(np.percentile(e0, 95)),
            "truth_dice": scores["dice"], "truth_epe_p95": scores["epe_p95"], "moving_shape": list(moving.shape)}
    field.unlink()
    meta_path.write_text(json.dumps({"spec": spec, "info": info}, indent=1))
    return Pair(f"{cls}/s{seed}", cls, seed, spec["amplitude"], spec["posed"], fixed_path, moving_path, truth, info)


def build_class(cls: str, seeds, work: Path) -> tuple[object, list[Pair], str]:
    """The fixed volume of ``cls`` (cached in ``work``/pairs/CLS/fixed.nii.gz with its description)
    and its pairs of ``seeds``."""
    from volreg.io import read_labels, write_labels

    folder = work / "pairs" / cls
    fixed_path, meta_path = folder / "fixed.nii.gz", folder / "fixed.json"
    spec = {"version": PAIR_VERSION, "class": cls}
    if fixed_path.exists() and meta_path.exists() and json.loads(meta_path.read_text()).get("spec") == spec:
        title = json.loads(meta_path.read_text())["title"]
    else:
        folder.mkdir(parents=True, exist_ok=True)
        volume, title = class_volume(cls)
        write_labels(volume, fixed_path, force=True)
        meta_path.write_text(json.dumps({"spec": spec, "title": title}))
        for stale in folder.glob("s*/pair.json"):  # pairs of another fixed volume
            stale.unlink()
    fixed = read_labels(str(fixed_path))
    return fixed, [build_pair(cls, s, fixed, fixed_path, folder / f"s{s}") for s in seeds], title


# ----------------------------------------------------------------------------- running


def is_volreg(method: str) -> bool:
    """Whether ``method`` is a volreg run (``volreg``, ``volreg-accurate`` or ``volreg@PROTOCOL``)."""
    return method in VOLREG_METHODS or method.startswith("volreg@")


def volreg_options(method: str) -> tuple[str, ...]:
    """The options a volreg method adds to ``volreg register``."""
    if method.startswith("volreg@"):
        return ("--protocol", method[len("volreg@"):])
    return VOLREG_METHODS[method]


def folder_name(method: str) -> str:
    """``method`` as one folder name (a protocol file's path has separators)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", method)


def run_method(method: str, pair: Pair, fixed, moving, out: Path, args) -> dict:
    """One timed run of ``method`` on ``pair`` in ``out`` (removed after scoring, its log kept beside
    it): wall seconds, peak RSS and the scores, or ``failed``."""
    shutil.rmtree(out, ignore_errors=True)  # a run stopped before its cleanup
    out.mkdir(parents=True)
    log = out.parent / f"{out.name}.log"
    if is_volreg(method):
        command = shlex.split(args.volreg_command) + ["register", str(pair.fixed_path), str(pair.moving_path), "-o",
                                                      str(out), "--quiet", *volreg_options(method)]
    else:
        command = [args.peer_python, str(Path(__file__).resolve()), "--peer", method, str(pair.fixed_path),
                   str(pair.moving_path), str(out)]
    try:
        rc, seconds, rss = timed(command, log, out, args.timeout, env=run_env())
        if rc != 0 or not (out / "warp.nii.gz").exists():
            return {"failed": last_line(log, rc, seconds)}
        result = {"seconds": seconds, "peak_rss_gb": rss}
        result.update(score_field(fixed, moving, pair.truth, out / "warp.nii.gz", folding=True))
    finally:
        shutil.rmtree(out, ignore_errors=True)
    result["dice_gap"] = result["dice"] - pair.info["truth_dice"]
    return result


def summarise(rows: list[dict], methods, classes) -> list[dict]:
    """Per method and class (and over all classes): pairs, medians and worst pairs of SCORES, the
    median time and the largest folded fraction; failed runs counted."""
    out = []
    for method in methods:
        for cls in list(classes) + ["all"]:
            mine = [r for r in rows if r["method"] == method and (cls == "all" or r["class"] == cls)]
            ok = [r for r in mine if not r.get("failed")]
            if not mine:
                continue
            s = {"method": method, "class": cls, "pairs": len(ok), "failed": len(mine) - len(ok)}
            if ok:
                for key in SCORES:
                    values = np.array([r[key] for r in ok])
                    worst = int(np.argmin(values) if key == "dice_gap" else np.argmax(values))
                    s[f"{key}_median"] = float(np.median(values))
                    s[f"{key}_worst"] = float(values[worst])
                    s[f"{key}_worst_pair"] = ok[worst]["pair"]
                s["folded_max"] = float(max(r["folded"] for r in ok))
                s["seconds_median"] = float(np.median([r["seconds"] for r in ok]))
            out.append(s)
    return out


def markdown_table(summary: list[dict]) -> str:
    """The summary as a Markdown table: median / worst (worst pair) per score."""
    lines = [("| method | class | pairs | EPE mean, median / worst (mm) | EPE p95, median / worst (mm) "
              "| Dice - truth's, median / worst | folded, max | wall s, median |"), "|---|---|---|---|---|---|---|---|"]
    for s in summary:
        pairs = f"{s['pairs']}" + (f" ({s['failed']} failed)" if s["failed"] else "")
        if not s["pairs"]:
            lines.append(f"| {s['method']} | {s['class']} | {pairs} | | | | | |")
            continue
        cells = []
        for key, fmt in (("epe_mean", ".2f"), ("epe_p95", ".2f"), ("dice_gap", "+.4f")):
            cells.append(f"{s[f'{key}_median']:{fmt}} / {s[f'{key}_worst']:{fmt}} ({s[f'{key}_worst_pair']})")
        name = f"**{s['class']}**" if s["class"] == "all" else s["class"]
        lines.append(f"| {s['method']} | {name} | {pairs} | " + " | ".join(cells)
                     + f" | {s['folded_max']:.5f} | {s['seconds_median']:.1f} |")
    return "\n".join(lines)


def compact_lines(summary: list[dict]) -> str:
    """One line per method and class: medians / worst of EPE mean, EPE p95 and Dice - truth's, median
    time (for a commit message)."""
    lines = []
    for s in summary:
        if not s["pairs"]:
            lines.append(f"{s['method']:<16} {s['class']:<11} all {s['failed']} failed")
            continue
        fail = f" ({s['failed']} failed)" if s["failed"] else ""
        lines.append(f"{s['method']:<16} {s['class']:<11} n={s['pairs']:<3} epe {s['epe_mean_median']:.2f}/"
                     f"{s['epe_mean_worst']:.2f} p95 {s['epe_p95_median']:.2f}/{s['epe_p95_worst']:.2f} "
                     f"dDice {s['dice_gap_median']:+.4f}/{s['dice_gap_worst']:+.4f} "
                     f"t {s['seconds_median']:.1f}s{fail}")
    return "\n".join(lines)


def write_rows(rows: list[dict], out: Path) -> None:
    """Every pair's row as ``out``/pairs.csv and ``out``/pairs.json."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "pairs.json").write_text(json.dumps(rows, indent=1))
    keys = ["pair", "class", "seed", "amplitude", "posed", "method", "epe_mean", "epe_p95", "dice", "truth_dice",
            "dice_gap", "folded", "seconds", "peak_rss_gb", "identity_epe_mean", "failed"]
    with open(out / "pairs.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


# ----------------------------------------------------------------------------- main


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="the quick subset: " + ", ".join(f"{c} seeds {','.join(map(str, s))}"
                                                             for c, s in QUICK.items()))
    parser.add_argument("--methods", default=None,
                        help=f"comma-separated subset of {','.join(METHODS)}, or volreg@PROTOCOL (default: volreg with --quick, "
                             "else volreg,volreg-accurate,greedy,ants)")
    parser.add_argument("--classes", default=",".join(CLASSES), help=f"comma-separated subset of {','.join(CLASSES)}")
    parser.add_argument("--seeds", type=int, default=12, help="pairs per class (seeds 0 .. N-1); not with --quick")
    parser.add_argument("--work", type=Path, default=None,
                        help="folder of the cached pairs and the runs (default: a temporary folder, removed)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out" / "accuracy",
                        help="folder for pairs.csv and pairs.json (default: benchmarks/out/accuracy)")
    add_run_options(parser)
    args = parser.parse_args()
    if args.peer:
        run_peer(*args.peer)
        return
    methods = [m for m in (args.methods or ("volreg" if args.quick else "volreg,volreg-accurate,greedy,ants"))
               .split(",") if m]
    for m in methods:
        if m not in METHODS and not (m.startswith("volreg@") and len(m) > len("volreg@")):
            parser.error(f"argument --methods: expected names from {','.join(METHODS)}, got {m!r}")
    classes = [c for c in args.classes.split(",") if c]
    for c in classes:
        if c not in CLASSES:
            parser.error(f"argument --classes: expected names from {','.join(CLASSES)}, got {c!r}")
    if args.seeds < 1:
        parser.error(f"argument --seeds: expected a positive integer, got {args.seeds}")
    plan = {c: (QUICK.get(c, ()) if args.quick else tuple(range(args.seeds))) for c in classes}
    plan = {c: s for c, s in plan.items() if s}

    print_header("bench_accuracy.py")
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_accuracy_"))
    work.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    rows: list[dict] = []
    try:
        from volreg.io import read_labels

        print("| class | fixed grid | labels | pairs (seed: amplitude mm, posed) | true map's Dice, min / median "
              "| identity EPE mean, median (mm) | built or read in s |")
        print("|---|---|---|---|---|---|---|", flush=True)
        built = []
        for cls, seeds in plan.items():
            t0 = time.perf_counter()
            fixed, pairs, title = build_class(cls, seeds, work)
            built.append((cls, fixed, pairs))
            td = [p.info["truth_dice"] for p in pairs]
            text = ", ".join(f"{p.seed}: {p.amplitude:g}{' P' if p.posed else ''}" for p in pairs)
            print(f"| {cls}: {title} | {' x '.join(map(str, fixed.shape))} of "
                  f"{' x '.join(f'{s:g}' for s in fixed.spacing)} mm | {len(fixed.labels())} | {text} "
                  f"| {min(td):.4f} / {np.median(td):.4f} "
                  f"| {np.median([p.info['identity_epe_mean'] for p in pairs]):.2f} "
                  f"| {time.perf_counter() - t0:.0f} |", flush=True)
        print(f"\n{sum(len(p) for _, _, p in built)} pairs (P: posed); methods {', '.join(methods)}.\n", flush=True)

        smallest = min(built, key=lambda b: int(np.prod(b[1].shape)))
        for method in methods:
            if is_volreg(method):  # untimed: numba compiles what its cache lacks
                pair = smallest[2][0]
                warm = run_method(method, pair, smallest[1], read_labels(str(pair.moving_path)),
                                  work / "runs" / f"warmup-{folder_name(method)}", args)
                print(f"Untimed warm-up of `{method}` on {pair.name}: "
                      f"{warm.get('failed') or format(warm['seconds'], '.1f') + ' s'}.", flush=True)
        print("\n| pair | amplitude mm | posed | method | EPE mean / p95 (mm) | Dice (truth's) | folded | wall s |")
        print("|---|---|---|---|---|---|---|---|", flush=True)
        for cls, fixed, pairs in built:
            for pair in pairs:
                moving = read_labels(str(pair.moving_path))
                for method in methods:
                    res = run_method(method, pair, fixed, moving,
                                     work / "runs" / f"{cls}-s{pair.seed}-{folder_name(method)}", args)
                    row = {"pair": pair.name, "class": cls, "seed": pair.seed, "amplitude": pair.amplitude,
                           "posed": pair.posed, "method": method, "truth_dice": pair.info["truth_dice"],
                           "identity_epe_mean": pair.info["identity_epe_mean"], **res}
                    rows.append(row)
                    head = f"| {pair.name} | {pair.amplitude:g} | {'yes' if pair.posed else 'no'} | {method} "
                    if "failed" in res:
                        print(head + f"| failed: {res['failed']} | | | |", flush=True)
                    else:
                        print(head + f"| {res['epe_mean']:.2f} / {res['epe_p95']:.2f} | {res['dice']:.4f} "
                              f"({pair.info['truth_dice']:.4f}) | {res['folded']:.5f} | {res['seconds']:.1f} |",
                              flush=True)
                    write_rows(rows, args.out)
        summary = summarise(rows, methods, [c for c, _, _ in built])
        print(f"\nPer method and class: median / worst pair (CLASS/sSEED); Dice over the fixed labels of at "
              f"least {LARGE} voxels, minus the true map's.\n")
        print(markdown_table(summary))
        print("\n```\n" + compact_lines(summary) + "\n```\n")
        (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
        print(f"Rows in {args.out}; total {(time.perf_counter() - t_start) / 60:.1f} min.", flush=True)
    finally:
        if rows:
            write_rows(rows, args.out)
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
