"""Shape models of cohorts with known modes: `volreg template` + `volreg shape-model` against a CPD-correspondence baseline.

Run:  PYTHON benchmarks/bench_shape_model.py --quick     (one cohort of 8 subjects)
      PYTHON benchmarks/bench_shape_model.py             (two cohorts of 16 subjects, seeds 0 and 1)

The Python that runs the script needs volreg and, for the baseline, pycpd (the bench extra).
volreg runs as `--volreg-command` (default: the repository's `.venv/bin/volreg`).

A cohort: a KNOWN template T (an ellipsoidal organ holding three inner structures, one small,
at 2 mm) and subjects warped by x + sum_m b_im e_m(x), with three known modes e_m (Gaussian bumps in
opposite pairs that neither move nor turn the organ, pushing along x, y and z; `--modes`: `large`,
peaks 6, 4 and 3 mm at 1 sd, scale 15 mm; `small`, peaks 4, 2.5 and 1.5 mm, scale 10 mm, a shape
variation of about a third of a voxel's RMS, near the registrations' own error) and whitened known
coefficients b (`volreg.synthetic.KnownModes`: the cohort's variance along each mode is
exactly its own), label-preservingly resampled on T's grid. The cohort's mean shape is T.

Methods, each timed as a user runs it:

- `volreg`: `volreg template MANIFEST -o TEMPLATE --workers 1 --quiet` (timed on its own, not
  part of the model's time), then `volreg shape-model TEMPLATE -o MODEL --align rigid --quiet`
  (a fresh process, start to exit): its surface and deformation models.
- `cpd`: the correspondence users make without a volume model: the same built template's label
  meshes (marching cubes, `volreg.features.label_surfaces`), each label's vertices subsampled to
  at most 1000 (seeded), registered to each subject's own label meshes by pycpd's
  `DeformableRegistration` (beta 10 mm, alpha 2, 60 iterations; in-process, timed); then the
  same rigid Procrustes, PCA and quality code as volreg (`volreg.ShapeModel`,
  `volreg.model_quality`).
- `known`: the models of the known warps on T itself (the best any correspondence can do).

Scores, the same code for every model: the largest principal angle between the span of the
leading three modes and the known modes' span at the model's points (degrees; all three principal
angles, smallest first), and for surface models the same of the modes' normal components alone
(motion along a smooth boundary is not seen in label maps, by any method); the leading
three variances over the known ones (the eigenvalues of the known modes' covariance at those
points); compactness, generalization and specificity with 3 modes (mm, with their standard
errors); correspondence both ways (the model's points in each subject against its own label
boundary, mm: to / from); time.

Output: Markdown on stdout and `shape_models.csv` / `.json` in `--out` (default benchmarks/out/shape_model).
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
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from common import last_line, print_header, run_env, timed  # noqa: E402

KEYS = ("cohort", "method", "model", "subjects", "angle_deg", "angles_deg", "normal_angles_deg", "variance_ratio", "compactness_3", "generalization_3_mm",
        "generalization_3_se_mm", "specificity_3_mm", "to_boundary_mm", "from_boundary_mm", "seconds",
        "template_seconds", "failed")
CPD_POINTS = 1000


def known_template(n: int = 44, spacing: float = 2.0):
    from volreg.grid import LabelVolume

    x = np.indices((n, n, n)).reshape(3, -1).T * spacing - (n - 1) * spacing / 2
    a = np.zeros(len(x), np.uint8)
    a[((x / [34, 25, 19]) ** 2).sum(1) <= 1] = 1
    a[(((x - [10, 0, 0]) / [13, 10, 9]) ** 2).sum(1) <= 1] = 2
    a[(((x + [15, -4, 0]) / [9, 8, 7]) ** 2).sum(1) <= 1] = 3
    a[(((x - [-4, -12, 6]) / [5, 4, 4]) ** 2).sum(1) <= 1] = 4
    return LabelVolume(a.reshape(n, n, n), np.full(3, -(n - 1) * spacing / 2), np.full(3, spacing), np.eye(3))


#: The known modes' peak displacements at 1 sd (mm) and bump scale (mm), by name (``--modes``).
MODE_SETS = {"large": ((6.0, 4.0, 3.0), 15.0), "small": ((4.0, 2.5, 1.5), 10.0)}


def known_modes(name: str = "large"):
    from volreg.synthetic import KnownModes

    sd, scale = MODE_SETS[name]
    return KnownModes(np.array([[16.0, 0, 0], [-8.0, 12, 0], [6.0, 0, 10]]), np.eye(3), np.array(sd), scale)


def build_cohort(subjects: int, seed: int, folder: Path, modes_name: str) -> dict:
    """The subjects' label maps, manifest and known coefficients in ``folder``."""
    from volreg.io import write_labels
    from volreg.synthetic import deform_labels

    template, modes = known_template(), known_modes(modes_name)
    b = modes.coefficients(subjects, seed=seed)
    folder.mkdir(parents=True, exist_ok=True)
    ids = [f"s{i:02d}" for i in range(subjects)]
    rows = ["id,path"]
    for sid, bi in zip(ids, b):
        write_labels(deform_labels(template, modes.warp(bi)), folder / f"{sid}.nii.gz")
        rows.append(f"{sid},{sid}.nii.gz")
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n")
    return {"template": template, "modes": modes, "b": b, "ids": ids, "folder": folder}



# ----------------------------------------------------------------------------- scores


def mode_scores(model, points: np.ndarray, to_known, modes, normals: np.ndarray | None = None) -> dict:
    """Principal angles (degrees) and variance ratios of the leading three modes against the known
    ``modes`` at ``points``; with the points' unit ``normals`` (surfaces), also the angles of the
    modes' normal components alone (what a boundary determines: motion along a smooth boundary
    is not seen in a label map)."""
    from scipy.linalg import subspace_angles

    fields = modes.fields(to_known(points))  # (3, P, D)
    known = fields.reshape(3, -1)
    k = min(3, model.n_modes)
    angles = np.sort(np.degrees(subspace_angles(model.modes[:k].reshape(k, -1).T, known.T)))
    expected = np.sort(np.linalg.eigvalsh(known @ known.T))[::-1][:k]
    out = {"angle_deg": float(angles[-1]), "angles_deg": "/".join(f"{a:.1f}" for a in angles),
           "variance_ratio": "/".join(f"{r:.2f}" for r in model.variances[:k] / expected)}
    if normals is not None:
        along = (fields * normals).sum(-1)  # (3, P)
        mine = (model.modes[:k] * normals).sum(-1)
        normal = np.sort(np.degrees(subspace_angles(mine.T, along.T)))
        out["normal_angles_deg"] = "/".join(f"{a:.1f}" for a in normal)
    return out


def mesh_normals(lsm) -> np.ndarray:
    """Unit vertex normals of a LabelShapeModel's template meshes, label after label."""
    from volreg.features.label_surfaces import vertex_normals

    return np.concatenate([vertex_normals(lsm.vertices[lsm.offsets[j]:lsm.offsets[j + 1]], lsm.faces[j])
                           for j in range(len(lsm.labels))])


def quality_row(q: dict) -> dict:
    return {"compactness_3": q["compactness"][2], "generalization_3_mm": q["generalization_mm"][2],
            "generalization_3_se_mm": q["generalization_se_mm"][2], "specificity_3_mm": q["specificity_mm"][2]}


def to_known_map(template_path: Path, known):
    """Built template point -> known template point (the affine map that removes the free global pose)."""
    from volreg.io import read_labels
    from volreg.warp.linear import fit_linear

    built = read_labels(template_path)
    return fit_linear(known, built, kind="affine").map.inverse()


def score_volreg(cohort: dict, template_dir: Path, model_dir: Path) -> list[dict]:
    from volreg.shape_models import LabelShapeModel

    to_known = to_known_map(template_dir / "template.nii.gz", cohort["template"])
    rows = []
    for kind in ("surface", "deformation"):
        lsm = LabelShapeModel.load(model_dir / kind / "model.npz")
        q = json.loads((model_dir / kind / "quality.json").read_text())
        points = lsm.vertices if kind == "surface" else lsm.template.grid_points()[lsm.region]
        normals = mesh_normals(lsm) if kind == "surface" else None
        rows.append({"model": kind, **mode_scores(lsm.model, points, to_known, cohort["modes"], normals), **quality_row(q),
                     "to_boundary_mm": q["correspondence"]["to_boundary_mm"],
                     "from_boundary_mm": q["correspondence"]["from_boundary_mm"]})
    return rows


def cpd_model(cohort: dict, template_dir: Path, seed: int) -> tuple[dict, float]:
    """The CPD baseline (module notes): its row and its seconds."""
    from pycpd import DeformableRegistration
    from scipy.spatial import cKDTree

    from volreg import ShapeModel, model_quality
    from volreg.features.label_surfaces import label_surfaces
    from volreg.io import read_labels

    t0 = time.perf_counter()
    built = read_labels(template_dir / "template.nii.gz")
    meshes = label_surfaces(built)
    rng = np.random.default_rng(seed)
    picks = {v: np.sort(rng.choice(len(m.vertices), min(CPD_POINTS, len(m.vertices)), replace=False))
             for v, m in meshes.items()}
    source = {v: meshes[v].vertices[picks[v]] for v in meshes}
    normals = np.concatenate([meshes[v].normals[picks[v]] for v in meshes])
    shapes, boundaries = [], []
    for sid in cohort["ids"]:
        own = label_surfaces(read_labels(cohort["folder"] / f"{sid}.nii.gz"), list(meshes))
        moved = []
        for v in meshes:
            target = own[v].vertices
            sub = target[np.sort(rng.choice(len(target), min(3 * CPD_POINTS, len(target)), replace=False))]
            reg = DeformableRegistration(X=sub, Y=source[v], alpha=2.0, beta=10.0, max_iterations=60)
            ty, _ = reg.register()
            moved.append(ty)
        shapes.append(np.concatenate(moved))
        boundaries.append({v: own[v].vertices for v in meshes})
    shapes = np.stack(shapes)
    reference = np.concatenate([source[v] for v in meshes])
    model = ShapeModel.fit(shapes, ids=cohort["ids"], align="rigid", modes=10, reference=reference)
    aligned = np.stack([s @ t[:3, :3].T + t[:3, 3] for s, t in zip(shapes, model.transforms)])
    q = model_quality(model, aligned, samples=100, seed=0)
    seconds = time.perf_counter() - t0
    to_b, from_b = [], []
    offsets = np.cumsum([0] + [len(source[v]) for v in meshes])
    for i in range(len(shapes)):
        for j, v in enumerate(meshes):
            mine = shapes[i][offsets[j]:offsets[j + 1]]
            to_b.append(cKDTree(boundaries[i][v]).query(mine)[0].mean())
            from_b.append(cKDTree(mine).query(boundaries[i][v])[0].mean())
    to_known = to_known_map(template_dir / "template.nii.gz", cohort["template"])
    row = {"model": "surface", **mode_scores(model, reference, to_known, cohort["modes"], normals), **quality_row(q),
           "to_boundary_mm": float(np.mean(to_b)), "from_boundary_mm": float(np.mean(from_b))}
    return row, seconds


def known_rows(cohort: dict, work: Path) -> list[dict]:
    """The models of the known warps on T (the module notes), through the library."""
    sys.path.insert(0, str(REPO / "tests"))
    from helpers import write_template_folder

    from volreg.shape_models import build_shape_models
    from volreg.synthetic import deform_labels

    template, modes = cohort["template"], cohort["modes"]
    x = template.grid_points().reshape(-1, 3)
    warps = [modes.warp(bi).displacement(x).reshape(template.shape + (3,)) for bi in cohort["b"]]
    subjects = [deform_labels(template, modes.warp(bi)) for bi in cohort["b"]]
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    result = build_shape_models(write_template_folder(work, template, warps, subjects, cohort["ids"]), align="rigid")
    rows = []
    for kind, lsm in result.models.items():
        q = result.quality[kind]
        points = lsm.vertices if kind == "surface" else template.grid_points()[lsm.region]
        normals = mesh_normals(lsm) if kind == "surface" else None
        rows.append({"model": kind, **mode_scores(lsm.model, points, lambda p: p, modes, normals), **quality_row(q),
                     "to_boundary_mm": q["correspondence"]["to_boundary_mm"],
                     "from_boundary_mm": q["correspondence"]["from_boundary_mm"]})
    return rows


def scaling_rows(sizes, points: int) -> list[dict]:
    """Large cohorts without registration: ``ShapeModel.fit`` (rigid Procrustes, 10 modes) and
    ``model_quality`` on N float32 shapes of ``points`` points (5 true modes plus noise), timed, and
    the data's and modes' bytes."""
    from volreg import ShapeModel, model_quality

    rows = []
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(points, 3)) * 30
    basis = rng.normal(size=(5, points, 3))
    for n in sizes:
        b = rng.normal(size=(n, 5)) * [5, 4, 3, 2, 1]
        shapes = (mean + np.tensordot(b, basis, axes=1) + rng.normal(size=(n, points, 3)) * 0.1).astype(np.float32)
        t0 = time.perf_counter()
        model = ShapeModel.fit(shapes, align="rigid", modes=10)
        fit = time.perf_counter() - t0
        aligned = np.stack([s @ t[:3, :3].T + t[:3, 3] for s, t in zip(shapes, model.transforms)]).astype(np.float32)
        t0 = time.perf_counter()
        q = model_quality(model, aligned, samples=100)
        rows.append({"subjects": n, "points": points, "fit_seconds": fit, "quality_seconds": time.perf_counter() - t0,
                     "data_mb": shapes.nbytes / 1e6, "modes_mb": model.modes.nbytes / 1e6,
                     "compactness_5": q["compactness"][4], "generalization_5_mm": q["generalization_mm"][4]})
    return rows


# ----------------------------------------------------------------------------- running


def run_cohort(name: str, subjects: int, seed: int, modes_name: str, work: Path, args) -> list[dict]:
    cohort = build_cohort(subjects, seed, work / name, modes_name)
    base = {"cohort": name, "subjects": subjects}
    rows = [{**base, "method": "known", **r} for r in known_rows(cohort, work / f"{name}-known")]
    volreg = shlex.split(args.volreg_command)
    template_dir, model_dir = work / f"{name}-template", work / f"{name}-model"
    shutil.rmtree(template_dir, ignore_errors=True)
    shutil.rmtree(model_dir, ignore_errors=True)
    rc, t_seconds, _ = timed(volreg + ["template", str(cohort["folder"] / "manifest.csv"), "-o", str(template_dir),
                                       "--workers", "1", "--quiet"], work / f"{name}-template.log", work,
                             args.timeout, env=run_env())
    if rc != 0:
        return rows + [{**base, "method": "volreg", "failed": last_line(work / f"{name}-template.log", rc, t_seconds)}]
    rc, m_seconds, _ = timed(volreg + ["shape-model", str(template_dir), "-o", str(model_dir), "--align", "rigid",
                                       "--quiet"], work / f"{name}-model.log", work, args.timeout, env=run_env())
    if rc != 0:
        rows.append({**base, "method": "volreg", "failed": last_line(work / f"{name}-model.log", rc, m_seconds)})
    else:
        rows += [{**base, "method": "volreg", **r, "seconds": m_seconds, "template_seconds": t_seconds}
                 for r in score_volreg(cohort, template_dir, model_dir)]
    if not args.no_cpd:
        try:
            row, seconds = cpd_model(cohort, template_dir, seed)
            rows.append({**base, "method": "cpd", **row, "seconds": seconds, "template_seconds": t_seconds})
        except ImportError as exc:
            rows.append({**base, "method": "cpd", "failed": f"pycpd not importable: {exc}"})
    return rows


def fmt(v) -> str:
    if v is None or v == "":
        return ""
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def markdown(rows: list[dict]) -> str:
    cols = ("cohort", "method", "model", "angles_deg", "normal_angles_deg", "variance_ratio", "compactness_3", "generalization_3_mm",
            "specificity_3_mm", "to_boundary_mm", "from_boundary_mm", "seconds", "template_seconds")
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        if r.get("failed"):
            out.append(f"| {r['cohort']} | {r['method']} | failed: {r['failed']} |" + " |" * (len(cols) - 3))
        else:
            out.append("| " + " | ".join(fmt(r.get(c)) for c in cols) + " |")
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one cohort of 8 subjects")
    parser.add_argument("--subjects", type=int, default=16, help="subjects per cohort (default 16)")
    parser.add_argument("--seeds", default="0,1", help="one cohort per seed (default 0,1)")
    parser.add_argument("--modes", default="large,small",
                        help="known mode sets: large (6, 4, 3 mm at 1 sd, scale 15 mm), small (4, 2.5, 1.5 mm, scale 10)")
    parser.add_argument("--no-cpd", action="store_true", help="leave the CPD baseline out")
    parser.add_argument("--scaling", default="", help="also time the PCA alone on cohorts of these sizes (e.g. 100,400)")
    parser.add_argument("--volreg-command", default=str(REPO / ".venv" / "bin" / "volreg"))
    parser.add_argument("--timeout", type=float, default=3600.0)
    parser.add_argument("--workdir", type=Path, default=None, help="keep the volumes and outputs in this new folder")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out" / "shape_model")
    args = parser.parse_args()
    subjects, seeds = (8, [0]) if args.quick else (args.subjects, [int(s) for s in args.seeds.split(",")])
    mode_sets = ["large"] if args.quick else args.modes.split(",")
    print_header("bench_shape_model.py")
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_shape_model_"))
    rows = []
    for name in mode_sets:
        for seed in seeds:
            rows += run_cohort(f"{name}-{subjects}-seed{seed}", subjects, seed, name, work, args)
            print(markdown(rows[-5:]), flush=True)
    print("\n" + markdown(rows))
    if args.scaling:
        big = scaling_rows([int(v) for v in args.scaling.split(",")], 30000)
        keys = list(big[0])
        print("\n| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
        for r in big:
            print("| " + " | ".join(fmt(r[k]) for k in keys) + " |")
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "shape_models.csv", "w", newline="") as f:
        w = csv.DictWriter(f, KEYS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    (args.out / "shape_models.json").write_text(json.dumps(rows, indent=1))
    if args.workdir is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
