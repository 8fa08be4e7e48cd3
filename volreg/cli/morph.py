"""``volreg morph``: frames of the morph from SOURCE to TARGET along the kernel warp."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING

from volreg.cli._common import PROG, output_path
from volreg.cli._surfaces import (_add_data_options, _data_file_name, _data_meta, _is_label, _load_model, _read,
                                  _register, _wants_gifti, _warn_findings, _write_gifti_surface, _write_surface)
from volreg.errors import UsageError

if TYPE_CHECKING:  # numpy and the pipeline are imported when the command runs
    import numpy as np

__all__ = ["add_parser", "run"]


#: The most frames a morph writes (each is a mesh file and a PNG, and all are held for the GIF).
MAX_FRAMES = 1000


def add_parser(commands) -> None:
    """Add ``morph`` to the ``volreg`` subcommands."""
    morph = commands.add_parser(
        "morph",
        help="frames of the morph from SOURCE to TARGET",
        description="Meshes along v + t (tau(v) - v) for t from 0 to 1 (frame_000.vtk ..., LPS mm), with per-vertex "
        "arrays that both surfaces carry interpolated (labels switch at t = 0.5), rendered off-screen to "
        "frame_000.png ... and morph.gif; when SOURCE is GIFTI or with --gifti also frame_000.surf.gii ... (RAS mm) "
        "and the arrays as frame_000.<name>.<kind>.gii.",
    )
    morph.add_argument("source", metavar="SOURCE", type=Path)
    morph.add_argument("target", metavar="TARGET", type=Path)
    morph.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, required=True, help="output directory")
    morph.add_argument("--frames", type=int, default=10, help="number of frames, 2 to 1000 (default 10)")
    morph.add_argument("--from-result", metavar="OUTDIR", type=Path, default=None,
                       help="use the model.npz of a `volreg register-surfaces` OUTDIR instead of registering")
    morph.add_argument("--protocol", metavar="NAME|FILE", default="default", help="protocol when registering")
    _add_data_options(morph, "source", "target")
    morph.add_argument("--gifti", action="store_true", help="also write GIFTI frames (RAS) when SOURCE is not GIFTI")
    morph.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    morph.add_argument("--quiet", action="store_true", help="no progress bars")
    morph.set_defaults(run=run)


def _render(frames: list[np.ndarray], triangles: np.ndarray, colours: list[np.ndarray] | None, png_paths, force: bool,
            record) -> list[np.ndarray]:
    """One PNG per frame (matplotlib, off-screen) with fixed axes, each passed to ``record`` once written,
    and the frames for the GIF."""
    import numpy as np
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
        record(path)
    return images


def run(args: argparse.Namespace) -> int:
    """``volreg morph SOURCE TARGET -o OUTDIR``."""
    import numpy as np

    from volreg.io._atomic import output_folder
    from volreg.io.gifti import write_gifti_data
    from volreg.io.protocol import load_protocol
    from volreg.evaluation.surface_review import diameter, review_surface_distance, review_surface_translation
    from volreg.morph import morph_vertices, surface_gaps, transfer_values
    from volreg.progress import ProgressBars

    start = time.perf_counter()
    if not 2 <= args.frames <= MAX_FRAMES:
        raise UsageError(f"--frames {args.frames}: expected 2 to {MAX_FRAMES} frames (the source, the warped source "
                         "and the steps between).")
    source = _read(args.source, "SOURCE", args.source_data)
    target = _read(args.target, "TARGET", args.target_data)
    warp = _load_model(args.from_result, "--from-result") if args.from_result is not None else None
    protocol = load_protocol(args.protocol) if warp is None else None
    outdir: Path = args.output
    names = [f"frame_{k:03d}" for k in range(args.frames)]
    gifti = _wants_gifti(args, args.source)
    shared = sorted(set(source.arrays) & set(target.arrays))
    shared = [name for name in shared if np.shape(source.arrays[name]) == (len(source.vertices),)
              + np.shape(target.arrays[name])[1:]]
    data_names = {name: {n: _data_file_name(n, name, _data_meta(source, name)) for n in names} for name in shared}
    paths = [outdir / f"{n}.vtk" for n in names] + [outdir / f"{n}.png" for n in names] + [outdir / "morph.gif"]
    if gifti:
        paths += [outdir / f"{n}.surf.gii" for n in names]
        paths += [outdir / file for files in data_names.values() for file in files.values()]
    with output_folder(outdir, args.force) as folder:
        folder.check_writable([p.name for p in paths], force=args.force)
        final, outdir = outdir, folder.path  # written into the run's staging folder, swapped in at the end
        registered = warp is None
        if registered:
            with ProgressBars(quiet=args.quiet) as progress:
                warp = _register(source, target, protocol, None, progress,
                                 names=(f"SOURCE `{args.source}`", f"TARGET `{args.target}`"))
        warped = warp(source.vertices)
        if registered:  # the checks of register-surfaces, on the registration made here
            gaps, measured = surface_gaps(warped, target.vertices, target.triangles)
            _warn_findings("morph", review_surface_distance(
                gaps, diameter(target.vertices), measured=measured,
                hint="Check that SOURCE and TARGET are in the same frame and unit, and turned alike (surfaces are "
                     "aligned by their centroids only).")
                + review_surface_translation(warp.linear.translation, diameter(source.vertices)))
        if args.from_result is not None:
            # a saved warp of other surfaces would morph this SOURCE somewhere else, silently
            gaps, measured = surface_gaps(warped, target.vertices, target.triangles)
            _warn_findings("morph", review_surface_distance(
                gaps, diameter(target.vertices), measured=measured,
                hint="Check that SOURCE and TARGET are the surfaces registered in --from-result, read in the same frame."))
        frames = morph_vertices(source.vertices, warped, args.frames, linear=warp.linear)
        ts = np.linspace(0.0, 1.0, args.frames)
        colours = None
        per_frame_arrays = [dict() for _ in frames]
        for name in shared:
            label = _is_label(source, name) or _is_label(target, name)
            a = np.asarray(source.arrays[name])
            b = np.asarray(transfer_values(warped, target.vertices, target.triangles, target.arrays[name],
                                           method="nearest" if label else "barycentric"))
            for k, t in enumerate(ts):
                # labels are not blended: the source's up to half-way, the target's after
                per_frame_arrays[k][name] = (a if t < 0.5 else b) if label else (1 - t) * a.astype(float) + t * b.astype(float)
        if shared and per_frame_arrays[0]:
            first = next(iter(per_frame_arrays[0]))
            colours = [np.asarray(arr[first], float) if np.ndim(arr[first]) == 1
                       else np.linalg.norm(np.asarray(arr[first], float), axis=1) for arr in per_frame_arrays]
        structure = source.gifti.structure() if source.gifti is not None else None
        for k, verts in enumerate(frames):
            _write_surface(outdir / f"{names[k]}.vtk", source, verts, per_frame_arrays[k], args.force)
            folder.record(outdir / f"{names[k]}.vtk")
            if gifti:
                _write_gifti_surface(outdir / f"{names[k]}.surf.gii", source, verts, args.force)
                folder.record(outdir / f"{names[k]}.surf.gii")
                for name in shared:
                    path = outdir / data_names[name][names[k]]
                    write_gifti_data(per_frame_arrays[k][name], path, meta=_data_meta(source, name),
                                     structure=structure, force=args.force)
                    folder.record(path)
        images = _render(frames, source.triangles, colours, [outdir / f"{n}.png" for n in names], args.force,
                         folder.record)
        from PIL import Image

        from volreg.io import atomic_output

        pil = [Image.fromarray(im) for im in images]
        with atomic_output(outdir / "morph.gif", force=args.force) as tmp:
            pil[0].save(tmp, format="GIF", save_all=True, append_images=pil[1:], duration=120, loop=0)
        folder.record(outdir / "morph.gif")
    kinds = ".vtk, .surf.gii, .png" if gifti else ".vtk, .png"
    print(f"{PROG} morph: {args.frames} frames ({kinds}) and morph.gif in {final} "
          f"({time.perf_counter() - start:.0f} s)")
    return 0
