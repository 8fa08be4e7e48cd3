"""``volreg register-surfaces``: register a surface mesh or point cloud to another and write the outputs."""

from __future__ import annotations

import argparse
import csv
import io
import time
from dataclasses import asdict
from pathlib import Path

from volreg import __version__
from volreg.cli._common import PROG, _load_landmarks, _sha256, output_path
from volreg.cli._surfaces import (FRAMES, _add_data_options, _read, _register, _wants_gifti, _warn_findings,
                                  _write_gifti_surface, _write_surface)

__all__ = ["add_parser", "run"]

OUTPUTS = ("warped.vtk", "correspondence.csv", "model.npz", "report.json")
#: Written besides OUTPUTS when SOURCE is GIFTI or with --gifti.
GIFTI_OUTPUT = "warped.surf.gii"


def add_parser(commands) -> None:
    """Add ``register-surfaces`` to the ``volreg`` subcommands."""
    reg = commands.add_parser(
        "register-surfaces",
        help="register a surface mesh or point cloud to another",
        description="Fit kernel implicit surfaces to SOURCE and TARGET (meshes: .vtk .vtp .ply .stl .obj .gii, or point "
        "clouds with or without normals) and the kernel warp tau of SOURCE onto TARGET; write into OUTDIR "
        "warped.vtk (LPS mm: every source vertex moved by tau, same order and faces), correspondence.csv (LPS mm), "
        "model.npz and report.json, and warped.surf.gii (RAS mm, the source's metadata) when SOURCE is GIFTI "
        "or with --gifti.",
    )
    reg.add_argument("source", metavar="SOURCE", type=Path)
    reg.add_argument("target", metavar="TARGET", type=Path)
    reg.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, required=True, help="output directory")
    reg.add_argument("--landmarks", metavar=("SRC_PTS", "TGT_PTS"), nargs=2, type=Path, default=None,
                     help="corresponding points (.csv x,y,z LPS mm, Slicer .fcsv or .mrk.json)")
    reg.add_argument("--protocol", metavar="NAME|FILE", default="default", help="protocol preset or TOML file")
    _add_data_options(reg, "source")
    reg.add_argument("--gifti", action="store_true", help="also write warped.surf.gii (RAS) when SOURCE is not GIFTI")
    reg.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    reg.add_argument("--quiet", action="store_true", help="no progress bars")
    reg.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``volreg register-surfaces SOURCE TARGET -o OUTDIR``."""
    import numpy as np

    from volreg.evaluation.surface_review import (
        SurfaceReviewLimits,
        diameter,
        review_landmarks,
        review_surface_distance,
        review_surface_translation,
    )
    from volreg.io import write_json, write_text
    from volreg.io._atomic import output_folder
    from volreg.io.protocol import load_protocol
    from volreg.io.summary import json_safe, package_versions
    from volreg.morph import closest_points, surface_gaps
    from volreg.progress import ProgressBars

    start = time.perf_counter()
    protocol = load_protocol(args.protocol)
    source = _read(args.source, "SOURCE", args.source_data)
    target = _read(args.target, "TARGET")
    landmarks = _load_landmarks(args)
    outdir: Path = args.output
    names = OUTPUTS + ((GIFTI_OUTPUT,) if _wants_gifti(args, args.source) else ())
    limits = SurfaceReviewLimits()
    with output_folder(outdir, args.force, outputs=(*OUTPUTS, GIFTI_OUTPUT)) as folder:
        paths = folder.check_writable(names, force=args.force)  # in staging, swapped into outdir at the end
        findings = []  # surfaces of other sizes (units) were refused by _register
        with ProgressBars(quiet=args.quiet) as progress:
            warp = _register(source, target, protocol, landmarks, progress,
                             names=(f"SOURCE `{args.source}`", f"TARGET `{args.target}`"))
        warped, jac = warp.evaluate(source.vertices, order=1)
        closest, distance, _ = closest_points(warped, target.vertices, target.triangles)  # per vertex, for the table
        # a point cloud TARGET is a sample of its surface: the review allows for the samples' spacing
        gaps, measured = (distance, "source_to_target") if len(target.triangles) else \
            surface_gaps(warped, target.vertices, target.triangles)
        target_diameter = diameter(target.vertices)
        late = review_surface_distance(gaps, target_diameter, limits, measured=measured,
                                       hint="Check that SOURCE and TARGET are in the same frame and unit, and turned alike "
                                            "(surfaces are aligned by their centroids only).")
        late += review_surface_translation(warp.linear.translation, diameter(source.vertices), limits)
        landmark_error = None
        if landmarks is not None:
            landmark_error = np.linalg.norm(warp(landmarks[0]) - landmarks[1], axis=1)
            off = np.maximum(closest_points(landmarks[0], source.vertices, source.triangles)[1],
                             closest_points(landmarks[1], target.vertices, target.triangles)[1])
            late += review_landmarks(landmark_error, target_diameter, limits, off_surface=off)
        _warn_findings("register-surfaces", late)
        findings += late
        report = {
            "volreg_version": __version__,
            "command": "register-surfaces",
            "inputs": {"source": {"path": str(args.source), "sha256": _sha256(args.source), "vertices": len(source.vertices),
                                  "triangles": len(source.triangles),
                                  "data": [{"path": str(p), "sha256": _sha256(p)} for p in args.source_data]},
                       "target": {"path": str(args.target), "sha256": _sha256(args.target), "vertices": len(target.vertices),
                                  "triangles": len(target.triangles)}},
            "direction": "source vertex v corresponds to target point tau(v) (LPS mm)",
            "frames": {name: FRAMES[Path(name).suffix] for name in names if Path(name).suffix in FRAMES},
            "distance_to_target_mm": {"mean": float(gaps.mean()), "median": float(np.median(gaps)),
                                      "p95": float(np.percentile(gaps, 95)), "max": float(gaps.max()),
                                      "measured": measured},
            "target_diameter_mm": target_diameter,
            # the centroids' translation the warp starts from (register_surfaces' align_centroids), or zeros
            "translation_mm": [float(v) for v in warp.linear.translation],
            "source_diameter_mm": diameter(source.vertices),
            "review": {"plausible": not findings, "findings": [f.to_dict() for f in findings],
                       "limits": asdict(limits)},
            "folded_fraction_at_vertices": float(np.mean(np.linalg.det(jac) <= 0)),
            "protocol": protocol.to_dict(),
            "versions": package_versions(),
        }
        if landmark_error is not None:
            err = landmark_error
            report["landmark_error"] = {"mean_mm": float(err.mean()), "max_mm": float(err.max()),
                                        "mean_percent_of_diameter": float(100 * err.mean() / target_diameter)}
        warp.save(paths["model.npz"], force=args.force)
        folder.record(paths["model.npz"])
        _write_surface(paths["warped.vtk"], source, warped, source.arrays, args.force)
        folder.record(paths["warped.vtk"])
        if GIFTI_OUTPUT in paths:
            _write_gifti_surface(paths[GIFTI_OUTPUT], source, warped, args.force)
            folder.record(paths[GIFTI_OUTPUT])
        table = io.StringIO()
        w = csv.writer(table, lineterminator="\n")
        w.writerow(["vertex", "x", "y", "z", "tau_x", "tau_y", "tau_z", "target_x", "target_y", "target_z", "distance_mm"])
        for i in range(len(warped)):
            # shortest round-trip text of each float: six digits would round coordinates far from
            # the origin (1e6 mm) to several millimetres
            w.writerow([i, *map(float, source.vertices[i]), *map(float, warped[i]), *map(float, closest[i]),
                        float(distance[i])])
        write_text(table.getvalue(), paths["correspondence.csv"], force=args.force)
        folder.record(paths["correspondence.csv"])
        report["seconds"] = time.perf_counter() - start
        write_json(json_safe(report), paths["report.json"], force=args.force)
        folder.record(paths["report.json"])
    d = report["distance_to_target_mm"]
    to = "target" if measured == "source_to_target" else "target points (beyond half their spacing)"
    line = f"{PROG} register-surfaces: warped source to {to} mean {d['mean']:.3f} mm, p95 {d['p95']:.3f} mm"
    if landmarks is not None:
        line += f", landmark error {report['landmark_error']['mean_mm']:.3f} mm"
    print(line + f"; {len(folder.written)} files in {outdir} ({report['seconds']:.0f} s)")
    return 0
