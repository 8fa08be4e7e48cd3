"""``volreg register-surfaces``, ``morph`` and ``transfer``: surface-to-surface commands (thin)."""

from __future__ import annotations

import argparse
import csv
import io
import time
from pathlib import Path

import numpy as np

from volreg import __version__
from volreg.cli._common import PROG, _remove_directories
from volreg.errors import UsageError
from volreg.io import check_writable, write_json, write_mesh, write_text
from volreg.io.landmarks import read_landmarks
from volreg.io.meshes import SurfaceData, read_surface
from volreg.register import register_surfaces
from volreg.progress import ProgressBars
from volreg.io.protocol import load_protocol
from volreg.morph import closest_points, morph_vertices, surface_normals, transfer_values
from volreg.warp.model import KernelWarp
from volreg.cli._common import _json_safe, _prepare_outdir, _sha256, _versions

__all__ = ["add_surface_commands"]

REGISTER_OUTPUTS = ("warped.vtk", "correspondence.csv", "model.npz", "report.json")


def _diameter(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def _read(path: Path, role: str) -> SurfaceData:
    data = read_surface(path)
    if len(data.vertices) < 10:
        raise UsageError(f"{role} `{path}` has {len(data.vertices)} vertices; expected at least 10 to fit a surface.")
    return data


def _landmarks(args) -> tuple[np.ndarray, np.ndarray] | None:
    if args.landmarks is None:
        return None
    a, b = (read_landmarks(p) for p in args.landmarks)
    if len(a) != len(b):
        raise UsageError(f"--landmarks: `{args.landmarks[0]}` has {len(a)} points and `{args.landmarks[1]}` {len(b)}; "
                         "expected the same number, in corresponding order.")
    return a, b


def _register(source: SurfaceData, target: SurfaceData, protocol, landmarks, progress) -> KernelWarp:
    src = (source.vertices, surface_normals(source.vertices, source.triangles, source.normals))
    tgt = (target.vertices, surface_normals(target.vertices, target.triangles, target.normals))
    return register_surfaces(src, tgt, landmarks=landmarks, settings=protocol.warp, progress=progress).warp


def _write_surface(path: Path, data: SurfaceData, vertices: np.ndarray, arrays: dict, force: bool) -> None:
    write_mesh(vertices, data.triangles, path, point_data=arrays or None, force=force, allow_points=True)


def _run_register_surfaces(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    protocol = load_protocol(args.protocol)
    source = _read(args.source, "SOURCE")
    target = _read(args.target, "TARGET")
    landmarks = _landmarks(args)
    outdir: Path = args.output
    created = _prepare_outdir(outdir, args.force)
    paths = {name: outdir / name for name in REGISTER_OUTPUTS}
    written: list[Path] = []
    try:
        check_writable(paths.values(), force=args.force)
        with ProgressBars(quiet=args.quiet) as progress:
            warp = _register(source, target, protocol, landmarks, progress)
        warped, jac = warp.evaluate(source.vertices, order=1)
        closest, distance, _ = closest_points(warped, target.vertices, target.triangles)
        diameter = _diameter(target.vertices)
        report = {
            "volreg_version": __version__,
            "command": "register-surfaces",
            "inputs": {"source": {"path": str(args.source), "sha256": _sha256(args.source), "vertices": len(source.vertices),
                                  "triangles": len(source.triangles)},
                       "target": {"path": str(args.target), "sha256": _sha256(args.target), "vertices": len(target.vertices),
                                  "triangles": len(target.triangles)}},
            "direction": "source vertex v corresponds to target point tau(v) (LPS mm)",
            "distance_to_target_mm": {"mean": float(distance.mean()), "p95": float(np.percentile(distance, 95)),
                                      "max": float(distance.max())},
            "target_diameter_mm": diameter,
            "folded_fraction_at_vertices": float(np.mean(np.linalg.det(jac) <= 0)),
            "protocol": protocol.to_dict(),
            "versions": _versions(),
        }
        if landmarks is not None:
            err = np.linalg.norm(warp(landmarks[0]) - landmarks[1], axis=1)
            report["landmark_error"] = {"mean_mm": float(err.mean()), "max_mm": float(err.max()),
                                        "mean_percent_of_diameter": float(100 * err.mean() / diameter)}
        warp.save(paths["model.npz"], force=args.force)
        written.append(paths["model.npz"])
        _write_surface(paths["warped.vtk"], source, warped, source.arrays, args.force)
        written.append(paths["warped.vtk"])
        table = io.StringIO()
        w = csv.writer(table, lineterminator="\n")
        w.writerow(["vertex", "x", "y", "z", "tau_x", "tau_y", "tau_z", "target_x", "target_y", "target_z", "distance_mm"])
        for i in range(len(warped)):
            w.writerow([i, *(f"{v:.6g}" for v in source.vertices[i]), *(f"{v:.6g}" for v in warped[i]),
                        *(f"{v:.6g}" for v in closest[i]), f"{distance[i]:.6g}"])
        write_text(table.getvalue(), paths["correspondence.csv"], force=args.force)
        written.append(paths["correspondence.csv"])
        report["seconds"] = time.perf_counter() - start
        write_json(_json_safe(report), paths["report.json"], force=args.force)
        written.append(paths["report.json"])
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        _remove_directories(created)
        raise
    d = report["distance_to_target_mm"]
    line = f"{PROG} register-surfaces: warped source to target mean {d['mean']:.3f} mm, p95 {d['p95']:.3f} mm"
    if landmarks is not None:
        line += f", landmark error {report['landmark_error']['mean_mm']:.3f} mm"
    print(line + f"; {len(written)} files in {outdir} ({report['seconds']:.0f} s)")
    return 0


def _load_model(result: Path) -> KernelWarp:
    model = result / "model.npz"
    if not model.is_file():
        raise UsageError(f"`{result}` has no model.npz; expected an OUTDIR written by `volreg register-surfaces`.")
    warp = KernelWarp.load(model)
    if warp.dim != 3:
        raise UsageError(f"`{model}` is a {warp.dim}-D warp; expected a 3-D surface registration.")
    return warp


def _render(frames: list[np.ndarray], triangles: np.ndarray, colours: list[np.ndarray] | None, png_paths, force: bool):
    """One PNG per frame (matplotlib, off-screen) with fixed axes, and the frames for the GIF."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from volreg.io import atomic_output

    allpts = np.concatenate(frames)
    lo, hi = allpts.min(axis=0), allpts.max(axis=0)
    images = []
    for k, (verts, path) in enumerate(zip(frames, png_paths)):
        fig = Figure(figsize=(5, 5), dpi=80, facecolor="white")
        canvas = FigureCanvasAgg(fig)
        ax = fig.add_subplot(projection="3d")
        c = None if colours is None else colours[k]
        if len(triangles):
            surf = ax.plot_trisurf(verts[:, 0], verts[:, 1], verts[:, 2], triangles=triangles, cmap="viridis",
                                   linewidth=0.0, antialiased=False)
            if c is not None:
                surf.set_array(np.asarray(c, float)[triangles].mean(axis=1))
        else:
            ax.scatter(verts[:, 0], verts[:, 1], verts[:, 2], s=2, c=c if c is not None else verts[:, 2], cmap="viridis")
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_title(f"t = {k / (len(frames) - 1):.2f}")
        ax.set_axis_off()
        canvas.draw()
        images.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
        with atomic_output(path, force=force) as tmp:
            canvas.print_png(str(tmp))
    return images


def _run_morph(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    if args.frames < 2:
        raise UsageError(f"--frames {args.frames}: expected at least 2 frames (the source and the warped source).")
    source = _read(args.source, "SOURCE")
    target = _read(args.target, "TARGET")
    warp = _load_model(args.from_result) if args.from_result is not None else None
    protocol = load_protocol(args.protocol) if warp is None else None
    outdir: Path = args.output
    names = [f"frame_{k:03d}" for k in range(args.frames)]
    paths = [outdir / f"{n}.vtk" for n in names] + [outdir / f"{n}.png" for n in names] + [outdir / "morph.gif"]
    created = _prepare_outdir(outdir, args.force)
    written: list[Path] = []
    try:
        check_writable(paths, force=args.force)
        if warp is None:
            with ProgressBars(quiet=args.quiet) as progress:
                warp = _register(source, target, protocol, None, progress)
        warped = warp(source.vertices)
        frames = morph_vertices(source.vertices, warped, args.frames)
        shared = sorted(set(source.arrays) & set(target.arrays))
        ts = np.linspace(0.0, 1.0, args.frames)
        colours = None
        per_frame_arrays = [dict() for _ in frames]
        for name in shared:
            a = np.asarray(source.arrays[name], float)
            b = np.asarray(transfer_values(warped, target.vertices, target.triangles, target.arrays[name]), float)
            if a.shape != b.shape:
                continue
            for k, t in enumerate(ts):
                per_frame_arrays[k][name] = (1 - t) * a + t * b
        if shared and per_frame_arrays[0]:
            first = next(iter(per_frame_arrays[0]))
            colours = [arr[first] if arr[first].ndim == 1 else np.linalg.norm(arr[first], axis=1) for arr in per_frame_arrays]
        for k, verts in enumerate(frames):
            _write_surface(outdir / f"{names[k]}.vtk", source, verts, per_frame_arrays[k], args.force)
            written.append(outdir / f"{names[k]}.vtk")
        images = _render(frames, source.triangles, colours, [outdir / f"{n}.png" for n in names], args.force)
        written += [outdir / f"{n}.png" for n in names]
        from PIL import Image

        from volreg.io import atomic_output

        pil = [Image.fromarray(im) for im in images]
        with atomic_output(outdir / "morph.gif", force=args.force) as tmp:
            pil[0].save(tmp, format="GIF", save_all=True, append_images=pil[1:], duration=120, loop=0)
        written.append(outdir / "morph.gif")
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        _remove_directories(created)
        raise
    print(f"{PROG} morph: {args.frames} frames (.vtk, .png) and morph.gif in {outdir} "
          f"({time.perf_counter() - start:.0f} s)")
    return 0


def _run_transfer(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    source = _read(args.source, "SOURCE")
    target = _read(args.target, "TARGET")
    if args.array not in target.arrays:
        available = ", ".join(sorted(target.arrays)) or "none"
        raise UsageError(f"--array `{args.array}` is not a per-vertex array of TARGET `{args.target}`; it has: {available}.")
    warp = _load_model(args.result)
    values = transfer_values(warp(source.vertices), target.vertices, target.triangles, target.arrays[args.array],
                             method=args.method)
    arrays = dict(source.arrays)
    arrays[args.array] = values
    write_mesh(source.vertices, source.triangles, args.output, point_data=arrays, force=args.force, allow_points=True)
    print(f"{PROG} transfer: `{args.array}` ({args.method}) from {args.target} onto {len(values)} vertices of "
          f"{args.source} -> {args.output} ({time.perf_counter() - start:.1f} s)")
    return 0


def add_surface_commands(commands) -> None:
    """Add ``register-surfaces``, ``morph`` and ``transfer`` to the ``volreg`` subcommands."""
    reg = commands.add_parser(
        "register-surfaces",
        help="register a surface mesh or point cloud to another",
        description="Fit kernel implicit surfaces to SOURCE and TARGET (meshes: .vtk .vtp .ply .stl .obj .gii, or point "
        "clouds with or without normals) and the kernel warp tau of SOURCE onto TARGET; write into OUTDIR "
        "warped.vtk (every source vertex moved by tau, same order and faces), correspondence.csv, model.npz and "
        "report.json.",
    )
    reg.add_argument("source", metavar="SOURCE", type=Path)
    reg.add_argument("target", metavar="TARGET", type=Path)
    reg.add_argument("-o", "--output", metavar="OUTDIR", type=Path, required=True, help="output directory")
    reg.add_argument("--landmarks", metavar=("SRC_PTS", "TGT_PTS"), nargs=2, type=Path, default=None,
                     help="corresponding points (.csv x,y,z LPS mm, Slicer .fcsv or .mrk.json)")
    reg.add_argument("--protocol", metavar="NAME|FILE", default="default", help="protocol preset or TOML file")
    reg.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    reg.add_argument("--quiet", action="store_true", help="no progress bars")
    reg.set_defaults(run=_run_register_surfaces)

    morph = commands.add_parser(
        "morph",
        help="frames of the morph from SOURCE to TARGET",
        description="Meshes along v + t (tau(v) - v) for t from 0 to 1 (frame_000.vtk ...), with per-vertex arrays "
        "that both surfaces carry interpolated, rendered off-screen to frame_000.png ... and morph.gif.",
    )
    morph.add_argument("source", metavar="SOURCE", type=Path)
    morph.add_argument("target", metavar="TARGET", type=Path)
    morph.add_argument("-o", "--output", metavar="OUTDIR", type=Path, required=True, help="output directory")
    morph.add_argument("--frames", type=int, default=10, help="number of frames, >= 2 (default 10)")
    morph.add_argument("--from-result", metavar="OUTDIR", type=Path, default=None,
                       help="use the model.npz of a `volreg register-surfaces` OUTDIR instead of registering")
    morph.add_argument("--protocol", metavar="NAME|FILE", default="default", help="protocol when registering")
    morph.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    morph.add_argument("--quiet", action="store_true", help="no progress bars")
    morph.set_defaults(run=_run_morph)

    tr = commands.add_parser(
        "transfer",
        help="carry a per-vertex array from TARGET onto SOURCE through a registration",
        description="For every SOURCE vertex v, take the value of --array at the TARGET point nearest to tau(v) "
        "(nearest vertex, or interpolated in the nearest triangle; integer arrays stay labels) and write SOURCE "
        "with the array to OUT.",
    )
    tr.add_argument("source", metavar="SOURCE", type=Path)
    tr.add_argument("target", metavar="TARGET", type=Path)
    tr.add_argument("--result", metavar="OUTDIR", type=Path, required=True, help="OUTDIR of `volreg register-surfaces`")
    tr.add_argument("--array", metavar="NAME", required=True, help="per-vertex array of TARGET")
    tr.add_argument("-o", "--output", metavar="OUT", type=Path, required=True, help="output mesh (.vtk or .vtp)")
    tr.add_argument("--method", choices=("nearest", "barycentric"), default="barycentric")
    tr.add_argument("--force", action="store_true", help="replace an existing OUT")
    tr.set_defaults(run=_run_transfer)
