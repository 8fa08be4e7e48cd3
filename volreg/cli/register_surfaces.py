"""``volreg register-surfaces``: register a surface mesh or point cloud to another and write the outputs."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from volreg.cli._common import PROG, _load_landmarks, output_path
from volreg.cli._surfaces import _add_data_options, _wants_gifti, _warn_findings

__all__ = ["add_parser", "run"]


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
    """``volreg register-surfaces SOURCE TARGET -o OUTDIR``
    (:func:`volreg.outputs.surfaces.write_surface_registration`)."""
    from volreg.io.protocol import load_protocol
    from volreg.outputs.surfaces import read_surface_with_data, write_surface_registration
    from volreg.progress import ProgressBars

    start = time.perf_counter()
    protocol = load_protocol(args.protocol)
    source = read_surface_with_data(args.source, "SOURCE", args.source_data)
    target = read_surface_with_data(args.target, "TARGET")
    landmarks = _load_landmarks(args)
    with ProgressBars(quiet=args.quiet) as progress:
        written = write_surface_registration(
            source, target, args.output, protocol=protocol, source_path=args.source, target_path=args.target,
            source_data=args.source_data, landmarks=landmarks, gifti=_wants_gifti(args, args.source), force=args.force,
            progress=progress, on_findings=lambda findings: _warn_findings("register-surfaces", findings), started=start,
        )
    print(_summary(written.report, written.files, args.output, landmarks is not None))
    return 0


def _summary(report: dict, files: int, outdir: Path, landmarks: bool) -> str:
    """The line ``volreg register-surfaces`` prints on stdout."""
    d = report["distance_to_target_mm"]
    to = "target" if d["measured"] == "source_to_target" else "target points (beyond half their spacing)"
    line = f"{PROG} register-surfaces: warped source to {to} mean {d['mean']:.3f} mm, p95 {d['p95']:.3f} mm"
    if landmarks:
        line += f", landmark error {report['landmark_error']['mean_mm']:.3f} mm"
    return line + f"; {files} files in {outdir} ({report['seconds']:.0f} s)"
