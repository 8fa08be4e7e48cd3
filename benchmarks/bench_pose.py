"""Pairs that differ in pose, size and resolution: the whole `volreg register` command beside ANTs and greedy.

Run:  .venv/bin/python benchmarks/bench_pose.py [--repeats 1] [--cases 1,3] [--methods volreg,ants,greedy]

The Python that runs the script needs volreg and the bench extra (antspyx, picsl_greedy:
`.venv/bin/pip install -e '.[bench]'`, or another environment with both); the peers run in it (or in
`--peer-python`). volreg runs as the repository's own command, `.venv/bin/volreg register FIXED MOVING
-o OUT` (`--volreg-command` names another, e.g. `"env PYTHONPATH=SNAPSHOT .venv/bin/python -m volreg"`
for a source snapshot).

Cases, generated with known answers (seeded):

1. pyvista's frog tissues at 3 mm (fixed: the 3 x 3 x 2 block mode of `volreg demo`) against a moving
   volume of 2 mm voxels, posed by 15 degrees and 20 mm and deformed by a smooth warp (10 Gaussian
   bumps, up to 8 mm; `volreg.synthetic.GaussianBumps`);
2. the same fixed frog against a moving volume of 3 mm voxels, posed by 45 degrees and 50 mm and scaled
   by 1.2 (a similarity), plus the smooth warp;
3. one label, an asymmetric blob (an ellipsoid of semi-axes 40 / 28 / 20 mm with two bumps), fixed at
   2 mm and moving at 1 mm, 30 degrees, 30 mm and an affine stretch of 0.85 / 1.0 / 1.15 along oblique
   axes;
4. an ellipsoidal "organ" (semi-axes 60 / 45 / 35 mm) split into 30 Voronoi labels, fixed at 1 mm and
   moving at 0.8 x 0.8 x 2.5 mm with an oblique direction matrix, 25 degrees and 30 mm, plus a smooth
   warp (up to 6 mm);
5. no motion: case 4's labels at 1 mm (fixed) and at 2 mm (moving); the answer is the identity;
6. no motion: case 4's labels at 1 mm (fixed) and at 0.8 x 0.8 x 2.5 mm on case 4's oblique grid
   (moving);
7. no motion: the folded two-label brain phantom of `bench_speed.py` (grey shell 2.5 mm thick around a
   white core) at 2 mm (fixed: every second voxel of the 1 mm labels, so the same label map) and at
   1 mm (moving);
8. no motion: a smaller ellipsoid (semi-axes 40 / 30 / 25 mm) split into 12 Voronoi labels, at 1 mm
   (fixed) and at 2 mm (moving), both grids centred on the ellipsoid, so that the 2 mm voxel centres lie
   half-way between 1 mm ones;
9. no motion: case 5 with one label (the ellipsoid's outline, its cells merged), a lone smooth organ;
10. thick slices: one ellipsoid (semi-axes 6 / 5 / 12 mm) on 64 x 64 x 8 voxels of 0.3 x 0.3 x 5 mm
    (about five slices through it), against the same grid holding it stretched to 6.5 mm along x and
    moved 0.6 mm (an affine truth);
11. the folded brain phantom of case 7 with an envelope of semi-axes 70 / 88 / 60 mm (a brain's
    proportions; case 7's 78 / 93 / 78 is a spheroid, whose turn about its long axis only the folds
    show) at 2 mm (fixed: every second voxel of its 1 mm labels) against a moving volume of 1 mm voxels,
    posed by 20 degrees and 31 mm, plus a smooth warp (up to 8 mm): the 1 mm labels are the source;
12. case 11 with case 7's spheroidal envelope: its moments do not show its turn about the long axis,
    only its folds do;
13. case 7's spheroidal phantom at 3 mm (every third voxel of its 1 mm labels) against its 1 mm labels
    read at 3 mm voxels, turned 40 degrees about (0.2, 1, 0.1) (mostly about its long axis), moved
    30 mm and deformed by a smooth warp (up to 6 mm);
14. no motion: case 7's phantom at 1 mm (fixed) against its 1 mm labels read by nearest neighbour at
    0.8 x 0.8 x 2.5 mm voxels on case 4's oblique grid (moving): the thick slices cut the 2.5 mm grey
    shell at every angle.

The true pull-back map is tau_true = L o beta: a fixed point x is first moved by the smooth warp beta
(x + the bumps' displacement, defined about the fixed object; the identity in cases 3 and 5-10), then by
the pose L(x) = A (x - c) + c + t (c: the centroid of the fixed labels; A = rotation [x scale / stretch];
t: the shift). The moving volume holds, at each voxel centre y of its grid, the label of the source
labels at tau_true^-1(y) = beta^-1(L^-1(y)) (beta inverted by fixed-point iteration), by nearest
neighbour: the source labels are the analytic label functions in cases 3-6 and the native frog
(1 x 1 x 1.5 mm, of which the 3 mm fixed volume is the block mode) in cases 1-2, the 1 mm phantom in
cases 11-14. The moving grid is the
box of the moving object plus a margin, in its own spacing and direction. Volumes are written as NIfTI.

Methods, each a fresh process timed from process start to exit (wall seconds; peak RSS of that process,
from `wait4` in a small launcher: a process started by the benchmark itself would report the
benchmark's own peak as its floor, since Linux carries the peak of the process that calls exec into the
program it starts), each writing a displacement field on the fixed grid (LPS mm, pull-back):

- `volreg`: the whole command `volreg register FIXED MOVING -o OUT --quiet` (every output written); its
  OUT/warp.nii.gz is read, and OUT/report.json's stages and (when present) its "linear" block are shown;
- `ants`: `ants.registration(type_of_transform="SyN")` on the label images as float (antspyx's default:
  centre-of-mass start, affine, then SyN, Mattes mutual information), its forward transforms composed
  into one displacement field (`ants.apply_transforms(..., compose=...)`); `ants-SyNRA` adds a rigid
  stage before the affine;
- `greedy`: picsl_greedy, affine (`-a -dof 12 -ia-image-centers`, SSD, 100x50x10) then deformable (SSD,
  100x50x20, smoothing 2 and 1 voxels) on top of it, composed by greedy itself (`-rc`); `greedy-moments`
  starts the affine from greedy's rigid alignment of the images' inertia tensors (`-moments 2 -det 1`)
  instead of the image centres;
- `identity` (no registration) and `truth` (tau_true itself), written and read back as the others: the
  first is the starting misalignment (and must score 0 mm in cases 5-9), the second checks the scoring (its
  endpoint error must be ~0 everywhere) and gives the Dice of the true map with these discretised
  volumes (not a ceiling: a map that bends boundaries onto the other volume's voxels can score higher).
  Neither is timed.

Peers get 2 threads (`ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS=2`, greedy `-threads 2`; ANTs seeded with
`ANTS_RANDOM_SEED=1`); volreg gets `NUMBA_NUM_THREADS=2`. The peers' results vary somewhat from run to
run even so (on case 3, picsl_greedy 1.4.0.3's endpoint error ranged from 0.95 to 2.17 mm over the
runs): use `--repeats`.

Scores per case and method: endpoint error |tau(x) - tau_true(x)| at the fixed voxel centres inside the
labels (mean and 95th percentile, mm); mean Dice over the fixed labels of at least 100 voxels, between
the fixed labels and the moving labels resampled through the method's field (volreg's label-preserving
resampling, the same for every method); wall seconds and peak RSS (GB). Medians of `--repeats` runs.
For volreg also its stages (seconds, from report.json) and its linear part, when its model holds one,
scored against the true pose L at the same voxels.

`--protocol NAME|FILE` is passed to `volreg register` (a preset or a TOML file: settings measured
against the defaults).

Output: Markdown on stdout: the command line, the cases, one table row per case and method, the volreg
stages. Work files go to a temporary folder (`--workdir` keeps them).
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from common import (
    CHUNK, LARGE, PEERS, add_run_options, grid_text, last_line, print_header, run_peer, score_field,
    smooth_bumps, timed,
)
from shapes import bumpy_ellipsoid, rotation

REFERENCES = ("identity", "truth")
#: Case 11's brain envelope, semi-axes (mm): three different axes, as a brain's.
BRAIN_11_AXES = (70.0, 88.0, 60.0)
DEFAULT_METHODS = "identity,truth,volreg,ants,greedy"


# ----------------------------------------------------------------------------- geometry of the cases


def unit(v) -> np.ndarray:
    """``v`` scaled to length 1."""
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


@dataclass(frozen=True)
class Pose:
    """``L(x) = A (x - c) + c + t`` (fixed point -> moving point, LPS mm)."""

    matrix: np.ndarray  # A, (3, 3)
    centre: np.ndarray  # c, (3,) mm
    shift: np.ndarray  # t, (3,) mm

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return (x - self.centre) @ self.matrix.T + self.centre + self.shift

    def inverse(self, y: np.ndarray) -> np.ndarray:
        return (y - self.centre - self.shift) @ np.linalg.inv(self.matrix).T + self.centre


@dataclass(frozen=True)
class Truth:
    """``tau_true = pose o bumps`` (bumps None: the identity)."""

    pose: Pose
    bumps: object | None  # volreg.synthetic.GaussianBumps

    def __call__(self, x: np.ndarray) -> np.ndarray:
        out = np.empty_like(x, dtype=float)
        for s in range(0, len(x), CHUNK):
            p = x[s : s + CHUNK]
            out[s : s + CHUNK] = self.pose(p if self.bumps is None else self.bumps(p))
        return out

    def inverse(self, y: np.ndarray) -> np.ndarray:
        out = np.empty_like(y, dtype=float)
        for s in range(0, len(y), CHUNK):
            p = self.pose.inverse(y[s : s + CHUNK])
            out[s : s + CHUNK] = p if self.bumps is None else self.bumps.inverse(p)
        return out


@dataclass
class Case:
    """A generated pair: fixed and moving label volumes and the true pull-back map."""

    number: int
    title: str
    fixed: object  # LabelVolume
    moving: object  # LabelVolume
    truth: Truth
    pose_text: str


def _box_grid(points: np.ndarray, spacing, direction=None, margin: float = 6.0):
    """The grid of ``spacing`` and ``direction`` (default: the identity) covering ``points`` (N, 3) mm
    plus ``margin`` mm."""
    from volreg.grid import Grid

    direction = np.eye(3) if direction is None else np.asarray(direction, float)
    spacing = np.asarray(spacing, float)
    q = points @ direction  # coordinates along the grid's axes
    lo, hi = q.min(axis=0) - margin, q.max(axis=0) + margin
    shape = tuple(int(n) for n in np.ceil((hi - lo) / spacing) + 1)
    return Grid(shape, direction @ lo, spacing, direction)


def _sample(grid, labels: Callable[[np.ndarray], np.ndarray], where: Callable[[np.ndarray], np.ndarray]):
    """The label volume on ``grid`` holding ``labels(where(y))`` at each voxel centre ``y``."""
    points = grid.grid_points().reshape(-1, 3)
    out = np.empty(len(points), dtype=np.uint8)
    for s in range(0, len(points), CHUNK):
        out[s : s + CHUNK] = labels(where(points[s : s + CHUNK]))
    return grid.with_array(out.reshape(grid.shape))


def _posed_moving(fixed, truth: Truth, labels, spacing, direction=None):
    """The moving volume: the source ``labels`` at ``tau_true^-1(y)``, on a grid of ``spacing`` and
    ``direction`` covering ``tau_true`` of the fixed labels' voxel centres (plus a margin)."""
    inside = fixed.grid_points()[fixed.array > 0]
    grid = _box_grid(truth(inside), spacing, direction, margin=6.0 + float(np.max(fixed.spacing)))
    return _sample(grid, labels, truth.inverse)


def _frog_source():
    """The native frog labels (1 x 1 x 1.5 mm) by nearest neighbour, and the 3 mm fixed volume."""
    from volreg.demo import block_mode, frog_path
    from volreg.io import read_labels
    from volreg.warp.resample import resample_labels

    native = read_labels(frog_path())
    fixed = block_mode(native, (3, 3, 2))
    return (lambda p: resample_labels(native, p, method="nearest")), fixed


def _centroid(volume) -> np.ndarray:
    """Mean of the labelled voxel centres, (3,) mm."""
    return volume.grid_points()[volume.array > 0].mean(axis=0)


def _blob_labels(p: np.ndarray) -> np.ndarray:
    """Label 1 inside the tests' ellipsoid with two bumps at twice its size (semi-axes 40 / 28 / 20 mm,
    bumps of 12 and 10 mm), at world points ``p`` (N, 3) mm."""
    return (bumpy_ellipsoid(2)(p / 2.0) < 0).astype(np.uint8)


ORGAN_AXES = np.array([60.0, 45.0, 35.0])
ORGAN_CENTRE = np.array([12.0, -25.0, 40.0])


def _organ_labels(count: int = 30, seed: int = 3):
    """An ellipsoid split into ``count`` Voronoi cells (labels 1..count), seeds uniform inside it."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (20 * count, 3))
    u = u[np.sum(u**2, axis=1) < 0.8][:count]  # away from the rim, so that each cell holds a real region
    tree = cKDTree(ORGAN_CENTRE + u * ORGAN_AXES)

    def labels(p: np.ndarray) -> np.ndarray:
        inside = np.sum(((p - ORGAN_CENTRE) / ORGAN_AXES) ** 2, axis=1) < 1.0
        out = np.zeros(len(p), np.uint8)
        out[inside] = tree.query(p[inside])[1] + 1
        return out

    return labels


def _organ_fixed(labels, spacing: float):
    """The organ's labels on an axis-aligned grid of ``spacing`` mm around the ellipsoid."""
    corners = ORGAN_CENTRE + np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T * ORGAN_AXES
    grid = _box_grid(corners, (spacing,) * 3, margin=5.0)
    return _sample(grid, labels, lambda p: p)


def _small_organ(shape, spacing: float):
    """Case 8's 12 Voronoi cells of an ellipsoid of semi-axes 40 / 30 / 25 mm centred at 0, on the grid
    of ``shape`` voxels of ``spacing`` mm centred at 0."""
    from scipy.spatial import cKDTree

    from volreg.grid import LabelVolume

    rng = np.random.default_rng(2)
    axes = np.array([40.0, 30.0, 25.0])
    u = rng.uniform(-1, 1, (480, 3))
    tree = cKDTree(u[np.sum(u**2, axis=1) < 0.7][:12] * axes)
    origin = -0.5 * (np.array(shape) - 1) * spacing
    grid = LabelVolume(np.zeros(shape, np.uint8), origin, (spacing,) * 3, np.eye(3))

    def labels(p: np.ndarray) -> np.ndarray:
        inside = np.sum((p / axes) ** 2, axis=1) < 1.0
        out = np.zeros(len(p), np.uint8)
        out[inside] = tree.query(p[inside])[1] + 1
        return out

    return _sample(grid, labels, lambda p: p)


def make_case(number: int) -> Case:
    """Build case ``number`` (1-14): fixed and moving volumes, the true map and a description."""
    from volreg.grid import Grid

    if number in (1, 2):
        source, fixed = _frog_source()
        c = _centroid(fixed)
        bumps = smooth_bumps(fixed, 8.0, seed=0)
        if number == 1:
            pose = Pose(rotation(15, (0.2, 0.3, 1.0)), c, 20.0 * unit((1.0, -0.5, 0.3)))
            moving = _posed_moving(fixed, Truth(pose, bumps), source, (2.0, 2.0, 2.0))
            text = "15 deg about (0.2, 0.3, 1), 20 mm, bumps up to 8 mm"
            title = "frog 3 mm vs 2 mm"
        else:
            pose = Pose(1.2 * rotation(45, (0.3, 0.5, 0.8)), c, 50.0 * unit((-0.4, 0.8, 0.45)))
            moving = _posed_moving(fixed, Truth(pose, bumps), source, (3.0, 3.0, 3.0))
            text = "45 deg about (0.3, 0.5, 0.8), 50 mm, scale 1.2, bumps up to 8 mm"
            title = "frog 3 mm vs 3 mm"
        return Case(number, title, fixed, moving, Truth(pose, bumps), text)
    if number == 3:
        grid = _box_grid(np.array([[-48.0, -36, -30], [48, 36, 30]]), (2.0, 2.0, 2.0), margin=4.0)
        fixed = _sample(Grid(grid.shape, grid.origin + (3.1, -1.7, 0.9), grid.spacing, grid.direction),
                        _blob_labels, lambda p: p)
        q = rotation(35, (1.0, 0.2, -0.4))
        a = rotation(30, (-0.5, 0.4, 0.75)) @ q @ np.diag([0.85, 1.0, 1.15]) @ q.T
        pose = Pose(a, _centroid(fixed), 30.0 * unit((0.6, 0.7, -0.4)))
        truth = Truth(pose, None)
        moving = _posed_moving(fixed, truth, _blob_labels, (1.0, 1.0, 1.0))
        return Case(3, "one blob 2 mm vs 1 mm", fixed, moving, truth,
                    "30 deg about (-0.5, 0.4, 0.75), 30 mm, stretch 0.85 / 1 / 1.15 along oblique axes")
    if number == 10:
        from volreg.grid import LabelVolume

        spacing = np.array([0.3, 0.3, 5.0])
        grid = LabelVolume(np.zeros((64, 64, 8), np.uint8), (0.0, 0.0, 0.0), spacing, np.eye(3))
        centre = np.array([9.6, 9.6, 20.0])
        axes = np.array([6.0, 5.0, 12.0])
        pose = Pose(np.diag([6.5 / 6.0, 1.0, 1.0]), centre, np.array([0.6, 0.0, 0.0]))

        def ellipsoid(p: np.ndarray) -> np.ndarray:
            return (np.sum(((p - centre) / axes) ** 2, axis=1) <= 1.0).astype(np.uint8)

        truth = Truth(pose, None)
        return Case(10, "one label over 5 mm slices, stretched", _sample(grid, ellipsoid, lambda p: p),
                    _sample(grid, ellipsoid, pose.inverse), truth, "stretch 6.5 / 6 along x, 0.6 mm")
    if number == 8:
        fixed, moving = _small_organ((90, 70, 60), 1.0), _small_organ((45, 35, 30), 2.0)
        truth = Truth(Pose(np.eye(3), _centroid(fixed), np.zeros(3)), None)
        return Case(8, "12 labels 1 mm vs 2 mm, half a voxel apart, no motion", fixed, moving, truth,
                    "none (identity)")
    labels = _organ_labels()
    fixed = _organ_fixed(labels, 1.0)
    if number == 4:
        pose = Pose(rotation(25, (0.7, -0.3, 0.6)), _centroid(fixed), 30.0 * unit((-0.5, -0.6, 0.6)))
        truth = Truth(pose, smooth_bumps(fixed, 6.0, seed=4))
        moving = _posed_moving(fixed, truth, labels, (0.8, 0.8, 2.5), direction=rotation(20, (1.0, 0.3, 0.2)))
        return Case(4, "30 labels 1 mm vs 0.8 x 0.8 x 2.5 mm oblique", fixed, moving, truth,
                    "25 deg about (0.7, -0.3, 0.6), 30 mm, bumps up to 6 mm; moving direction 20 deg oblique")
    if number == 5:
        truth = Truth(Pose(np.eye(3), _centroid(fixed), np.zeros(3)), None)
        moving = _organ_fixed(labels, 2.0)
        return Case(5, "30 labels 1 mm vs 2 mm, no motion", fixed, moving, truth, "none (identity)")
    if number == 9:
        truth = Truth(Pose(np.eye(3), _centroid(fixed), np.zeros(3)), None)
        moving = _organ_fixed(labels, 2.0)
        lone = [v.with_array((v.array > 0).astype(np.uint8)) for v in (fixed, moving)]
        return Case(9, "one smooth label 1 mm vs 2 mm, no motion", *lone, truth, "none (identity)")
    if number == 6:
        truth = Truth(Pose(np.eye(3), _centroid(fixed), np.zeros(3)), None)
        moving = _posed_moving(fixed, truth, labels, (0.8, 0.8, 2.5), direction=rotation(20, (1.0, 0.3, 0.2)))
        return Case(6, "30 labels 1 mm vs 0.8 x 0.8 x 2.5 mm oblique, no motion", fixed, moving, truth,
                    "none (identity); moving direction 20 deg oblique")
    if number == 13:
        from bench_speed import cortex_phantom
        from volreg.grid import LabelVolume
        from volreg.warp.resample import resample_labels

        native = cortex_phantom(1.0)
        fixed = LabelVolume(native.array[1::3, 1::3, 1::3].copy(), native.origin + native.spacing, 3 * native.spacing,
                            native.direction)
        pose = Pose(rotation(40, (0.2, 1.0, 0.1)), _centroid(fixed), 30.0 * unit((-0.4, 0.8, 0.45)))
        truth = Truth(pose, smooth_bumps(fixed, 6.0, seed=4))
        moving = _posed_moving(fixed, truth, lambda p: resample_labels(native, p, method="nearest"), (3.0, 3.0, 3.0))
        return Case(13, "spheroidal brain phantom 3 mm, turned about its long axis", fixed, moving, truth,
                    "40 deg about (0.2, 1, 0.1), 30 mm, bumps up to 6 mm")
    if number in (11, 12):
        from bench_speed import cortex_phantom
        from volreg.grid import LabelVolume
        from volreg.warp.resample import resample_labels

        native = cortex_phantom(1.0, axes=BRAIN_11_AXES if number == 11 else None)
        fixed = LabelVolume(native.array[::2, ::2, ::2].copy(), native.origin, 2 * native.spacing, native.direction)
        pose = Pose(rotation(20, (0.4, -0.2, 1.0)), _centroid(fixed), 31.0 * unit((0.5, 0.7, -0.3)))
        truth = Truth(pose, smooth_bumps(fixed, 8.0, seed=1))
        moving = _posed_moving(fixed, truth, lambda p: resample_labels(native, p, method="nearest"), (1.0, 1.0, 1.0))
        title = "brain phantom 2 mm vs 1 mm" if number == 11 else "spheroidal brain phantom 2 mm vs 1 mm"
        return Case(number, title, fixed, moving, truth, "20 deg about (0.4, -0.2, 1), 31 mm, bumps up to 8 mm")
    if number == 14:
        from bench_speed import cortex_phantom
        from volreg.warp.resample import resample_labels

        fine = cortex_phantom(1.0)
        truth = Truth(Pose(np.eye(3), _centroid(fine), np.zeros(3)), None)
        moving = _posed_moving(fine, truth, lambda p: resample_labels(fine, p, method="nearest"), (0.8, 0.8, 2.5),
                               direction=rotation(20, (1.0, 0.3, 0.2)))
        return Case(14, "brain phantom 1 mm vs 0.8 x 0.8 x 2.5 mm oblique, no motion", fine, moving, truth,
                    "none (identity); moving direction 20 deg oblique")
    if number == 7:
        from bench_speed import cortex_phantom
        from volreg.grid import LabelVolume

        fine = cortex_phantom(1.0)
        coarse = LabelVolume(fine.array[::2, ::2, ::2].copy(), fine.origin, 2 * fine.spacing, fine.direction)
        truth = Truth(Pose(np.eye(3), _centroid(coarse), np.zeros(3)), None)
        return Case(7, "brain phantom 2 mm vs 1 mm, no motion", coarse, fine, truth, "none (identity)")
    raise ValueError(f"Expected a `case` from 1 to 14, got {number!r}.")


# ----------------------------------------------------------------------------- running the methods


def _reference_field(case: Case, method: str, out: Path) -> None:
    """The identity's or the true map's displacement field, written as a method's would be."""
    from volreg.io.fields import write_displacement

    x = case.fixed.grid_points().reshape(-1, 3)
    u = np.zeros_like(x) if method == "identity" else case.truth(x) - x
    write_displacement(u.reshape(*case.fixed.shape, 3), case.fixed, out / "warp.nii.gz")


def _linear_error(case: Case, model: Path) -> dict | None:
    """The linear part saved in volreg's model against the true pose, at the fixed label voxels (mm)."""
    if not model.exists():
        return None
    with np.load(model, allow_pickle=False) as z:
        if "linear_matrix" not in z.files:
            return None
        a, b = np.asarray(z["linear_matrix"], float), np.asarray(z["linear_translation"], float)
    x = case.fixed.grid_points()[case.fixed.array > 0]
    err = np.linalg.norm(x @ a.T + b - case.truth.pose(x), axis=1)
    return {"mean": float(err.mean()), "p95": float(np.percentile(err, 95))}


def run_method(case: Case, method: str, paths: dict, out: Path, args) -> dict:
    """One run of ``method`` on ``case``: scores, wall seconds, peak RSS; for volreg also its report."""
    out.mkdir(parents=True)
    log = out.parent / f"{out.name}.log"
    if method in REFERENCES:
        _reference_field(case, method, out)
        result = {"seconds": float("nan"), "peak_rss_gb": float("nan")}
    else:
        if method == "volreg":
            command = shlex.split(args.volreg_command) + ["register", paths["fixed"], paths["moving"], "-o", str(out),
                                                          "--force", "--quiet"]
            if args.protocol:
                command += ["--protocol", args.protocol]
        elif method in PEERS:
            command = [args.peer_python, str(Path(__file__).resolve()), "--peer", method, paths["fixed"],
                       paths["moving"], str(out)]
        else:
            raise ValueError(f"Expected a method in {REFERENCES + ('volreg',) + PEERS}, got {method!r}.")
        rc, seconds, rss = timed(command, log, out, args.timeout)
        if rc != 0 or not (out / "warp.nii.gz").exists():
            return {"failed": last_line(log, rc, seconds)}
        result = {"seconds": seconds, "peak_rss_gb": rss}
    result.update(score_field(case.fixed, case.moving, case.truth, out / "warp.nii.gz"))
    if method == "volreg":
        report = json.loads((out / "report.json").read_text()) if (out / "report.json").exists() else {}
        result["stages"] = [(s.get("stage"), s.get("seconds")) for s in report.get("stages", [])]
        result["linear"] = report.get("linear")
        result["linear_error"] = _linear_error(case, out / "model.npz")
    return result


# ----------------------------------------------------------------------------- output


def _summary(block, limit: int = 400) -> str:
    """A short one-line rendering of a JSON block: its scalar leaves and short numeric lists."""
    items = []

    def walk(prefix, value):
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            items.append(f"{prefix}={value:.4g}")
        elif isinstance(value, (str, bool)) or value is None:
            items.append(f"{prefix}={value}")
        elif isinstance(value, list) and len(value) <= 3 and all(isinstance(v, (int, float)) for v in value):
            items.append(f"{prefix}=[{', '.join(f'{v:.3g}' for v in value)}]")
        elif isinstance(value, list):
            items.append(f"{prefix}=[{len(value)} items]")

    walk("", block)
    text = "; ".join(items)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=1, help="runs per case and method (medians are shown)")
    parser.add_argument("--cases", default="1,2,3,4,5", help="comma-separated subset of 1-14")
    parser.add_argument("--protocol", default=None, help="passed to `volreg register --protocol` (a preset or a TOML file)")
    parser.add_argument("--methods", default=DEFAULT_METHODS,
                        help=f"comma-separated subset of {','.join(REFERENCES + ('volreg',) + PEERS)}")
    add_run_options(parser)
    args = parser.parse_args()
    if args.peer:
        run_peer(*args.peer)
        return
    cases = [int(c) for c in args.cases.split(",")]
    methods = args.methods.split(",")
    for m in methods:
        if m not in REFERENCES + ("volreg",) + PEERS:
            parser.error(f"unknown method {m!r}")

    print_header("bench_pose.py")

    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_pose_"))
    work.mkdir(parents=True, exist_ok=args.workdir is None)
    stage_rows, case_rows = [], []
    try:
        from volreg.io import write_labels

        built = []
        for number in cases:
            t0 = time.perf_counter()
            case = make_case(number)
            paths = {k: str(work / f"case{number}_{k}.nii.gz") for k in ("fixed", "moving")}
            write_labels(case.fixed, paths["fixed"])
            write_labels(case.moving, paths["moving"])
            case_rows.append(f"| {number} | {case.title} | {grid_text(case.fixed)}, {len(case.fixed.labels())} labels "
                             f"| {grid_text(case.moving)}, {len(case.moving.labels())} labels | {case.pose_text} "
                             f"| {time.perf_counter() - t0:.0f} |")
            built.append((case, paths))
        print("| case | pair | fixed | moving | tau_true (pose L after the smooth warp) | built in s |")
        print("|---|---|---|---|---|---|")
        print("\n".join(case_rows) + "\n", flush=True)

        print(f"| case | method | endpoint error mean / p95 (mm) | mean Dice, labels >= {LARGE} voxels | wall s (runs) "
              "| peak RSS GB |")
        print("|---|---|---|---|---|---|", flush=True)
        for case, paths in built:
            for method in methods:
                runs = []
                for r in range(args.repeats if method not in REFERENCES else 1):
                    res = run_method(case, method, paths, work / f"case{case.number}_{method}_{r}", args)
                    if "failed" in res:
                        runs = [res]
                        break
                    runs.append(res)
                if "failed" in runs[0]:
                    row = f"| {case.number} | {method} | failed: {runs[0]['failed']} | | | |"
                else:
                    med = {k: float(np.median([r[k] for r in runs]))
                           for k in ("epe_mean", "epe_p95", "dice", "seconds", "peak_rss_gb")}
                    timing = "-" if method in REFERENCES else (
                        f"{med['seconds']:.1f} (" + ", ".join(f"{r['seconds']:.1f}" for r in runs) + ")")
                    rss = "-" if method in REFERENCES else f"{med['peak_rss_gb']:.2f}"
                    row = (f"| {case.number} | {method} | {med['epe_mean']:.2f} / {med['epe_p95']:.2f} "
                           f"| {med['dice']:.4f} | {timing} | {rss} |")
                    if method == "volreg":
                        last = runs[-1]
                        stages = ", ".join(f"{n} {s:.1f}" for n, s in last["stages"]) or "-"
                        lin_err = last["linear_error"]
                        lin = "-" if last["linear"] is None else _summary(last["linear"])
                        err_text = "-" if lin_err is None else f"{lin_err['mean']:.2f} / {lin_err['p95']:.2f}"
                        stage_rows.append(f"| {case.number} | {stages} | {err_text} | {lin} |")
                print(row, flush=True)
        if stage_rows:
            print("\n| case | volreg stages (s, last run) | its linear part vs the true pose, mean / p95 (mm) "
                  "| report.json \"linear\" |")
            print("|---|---|---|---|")
            print("\n".join(stage_rows))
    finally:
        if args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
