"""The frames of a morph from one surface to another along the kernel warp, as ``volreg morph`` writes them.

:func:`write_morph` registers the pair (or takes a saved warp), moves the source's vertices
along v + t (tau(v) - v) (:func:`volreg.morph.morph_vertices`), carries the per-vertex arrays
both surfaces hold from one to the other (:func:`morph_arrays`), and writes each frame as a
mesh (and, on request, GIFTI), a PNG rendered off-screen, and the GIF of them all, in one output
transaction.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from volreg.evaluation.review import Finding
from volreg.evaluation.surface_review import diameter, review_surface_distance, review_surface_translation
from volreg.io import atomic_output
from volreg.io._atomic import output_folder
from volreg.io.gifti import write_gifti_data
from volreg.io.meshes import SurfaceData
from volreg.morph import morph_vertices, surface_gaps, transfer_values
from volreg.outputs.surfaces import (
    _issue_findings,
    data_file_name,
    is_label_array,
    vertex_array_meta,
    write_moved_gifti_surface,
    write_moved_surface,
)
from volreg.pipeline.surfaces import register_surface_pair
from volreg.settings import Protocol
from volreg.warp.model import KernelWarp

__all__ = ["MORPH_OUTPUTS", "morph_arrays", "render_frames", "shared_arrays", "write_morph"]

#: Every file :func:`write_morph` may write, whatever its options (an earlier run's that this one
#: does not write are removed with ``force``): frames as .vtk, .png and .surf.gii, their data
#: arrays, the animation.
MORPH_OUTPUTS = ("frame_[0-9][0-9][0-9].vtk", "frame_[0-9][0-9][0-9].png", "frame_[0-9][0-9][0-9].*.gii",
                 "morph.gif")

ProgressCallback = Callable[[str, int, int], None]


def shared_arrays(source: SurfaceData, target: SurfaceData) -> list[str]:
    """The per-vertex arrays a morph carries: those both surfaces hold, with the same shape per vertex.

    Returns
    -------
    list of str
        Their names, sorted.
    """
    shared = sorted(set(source.arrays) & set(target.arrays))
    return [name for name in shared if np.shape(source.arrays[name]) == (len(source.vertices),)
            + np.shape(target.arrays[name])[1:]]


def morph_arrays(source: SurfaceData, target: SurfaceData, warped: np.ndarray, names: Sequence[str],
                 frames: int) -> list[dict[str, np.ndarray]]:
    """Each frame's per-vertex arrays, from the source's at t = 0 to the target's at t = 1.

    Parameters
    ----------
    source, target : SurfaceData
    warped : (N, 3) float ndarray
        The source vertices moved by the warp, LPS mm (where the target's values are taken).
    names : sequence of str
        The arrays (:func:`shared_arrays`).
    frames : int
        How many frames, t evenly from 0 to 1.

    Returns
    -------
    list of dict of str to (N, ...) ndarray
        One per frame: values blended linearly in t; labels (:func:`~volreg.outputs.surfaces.is_label_array`)
        are not blended but switch from the source's to the target's at t = 0.5.
    """
    ts = np.linspace(0.0, 1.0, frames)
    per_frame: list[dict[str, np.ndarray]] = [dict() for _ in range(frames)]
    for name in names:
        label = is_label_array(source, name) or is_label_array(target, name)
        a = np.asarray(source.arrays[name])
        b = np.asarray(transfer_values(warped, target.vertices, target.triangles, target.arrays[name],
                                       method="nearest" if label else "barycentric"))
        for k, t in enumerate(ts):
            # labels are not blended: the source's up to half-way, the target's after
            per_frame[k][name] = (a if t < 0.5 else b) if label else (1 - t) * a.astype(float) + t * b.astype(float)
    return per_frame


def _frame_colours(per_frame: list[dict[str, np.ndarray]]) -> list[np.ndarray] | None:
    """The values that colour each frame: its first array (the length of a vector array), if any."""
    if not per_frame or not per_frame[0]:
        return None
    first = next(iter(per_frame[0]))
    return [np.asarray(arr[first], float) if np.ndim(arr[first]) == 1
            else np.linalg.norm(np.asarray(arr[first], float), axis=1) for arr in per_frame]


def render_frames(frames: list[np.ndarray], triangles: np.ndarray, colours: list[np.ndarray] | None,
                  png_paths: Sequence[str | os.PathLike[str]], force: bool,
                  record: Callable[[Path], object]) -> list[np.ndarray]:
    """One PNG per frame (matplotlib, off-screen) with the same axes for all.

    Parameters
    ----------
    frames : list of (N, 3) float ndarray
        The vertices of each frame, LPS mm.
    triangles : (F, 3) int ndarray
        The faces (none: the vertices are drawn as points).
    colours : list of (N,) float ndarray, optional
        Each frame's per-vertex values to colour it by (default: by z).
    png_paths : sequence of path-like
        Where each frame's PNG goes.
    force : bool
        Replace existing files.
    record : callable
        Called with each PNG's path once it is written.

    Returns
    -------
    list of (H, W, 3) uint8 ndarray
        The rendered frames, for the GIF.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

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


def _write_gif(images: list[np.ndarray], path: Path, force: bool) -> None:
    """The rendered frames as one looping GIF."""
    from PIL import Image

    pil = [Image.fromarray(im) for im in images]
    with atomic_output(path, force=force) as tmp:
        pil[0].save(tmp, format="GIF", save_all=True, append_images=pil[1:], duration=120, loop=0)


def _review_morph(warp: KernelWarp, source: SurfaceData, target: SurfaceData, warped: np.ndarray,
                  registered: bool) -> list[Finding]:
    """The checks of ``volreg register-surfaces`` on a warp fitted here; for a saved one, the distance
    alone (a saved warp of other surfaces would morph this source somewhere else, silently)."""
    gaps, measured = surface_gaps(warped, target.vertices, target.triangles)
    if registered:
        return review_surface_distance(
            gaps, diameter(target.vertices), measured=measured,
            hint="Check that SOURCE and TARGET are in the same frame and unit, and turned alike (surfaces are "
                 "aligned by their centroids only).") \
            + review_surface_translation(warp.linear.translation, diameter(source.vertices))
    return review_surface_distance(
        gaps, diameter(target.vertices), measured=measured,
        hint="Check that SOURCE and TARGET are the surfaces registered in --from-result, read in the same frame.")


def _output_names(frame_names: list[str], data_names: dict[str, dict[str, str]], gifti: bool) -> list[str]:
    """Every file the morph writes, to check up front."""
    names = [f"{n}.vtk" for n in frame_names] + [f"{n}.png" for n in frame_names] + ["morph.gif"]
    if gifti:
        names += [f"{n}.surf.gii" for n in frame_names]
        names += [file for files in data_names.values() for file in files.values()]
    return names


def write_morph(
    source: SurfaceData,
    target: SurfaceData,
    outdir: str | os.PathLike[str],
    *,
    frames: int,
    warp: KernelWarp | None = None,
    protocol: Protocol | None = None,
    names: tuple[object, object] = ("SOURCE", "TARGET"),
    gifti: bool = False,
    force: bool = False,
    progress: ProgressCallback | None = None,
    on_findings: Callable[[list[Finding]], None] | None = None,
) -> None:
    """Write the frames of the morph of ``source`` onto ``target`` into ``outdir``, all or nothing.

    Frame k (of ``frames``, t = k / (frames - 1)) is ``frame_<k>.vtk`` (LPS mm, the source's faces,
    with the per-vertex arrays both surfaces hold, :func:`morph_arrays`) and ``frame_<k>.png``;
    ``morph.gif`` holds them all; with ``gifti`` also ``frame_<k>.surf.gii`` (RAS mm) and each
    array as ``frame_<k>.<name>.<kind>.gii``.

    Parameters
    ----------
    source, target : SurfaceData
        LPS mm.
    outdir : path-like
        The output folder.
    frames : int
        At least 2 (the source and the warped source).
    warp : KernelWarp, optional
        A saved warp of ``source`` onto ``target``; default: registered here with ``protocol``.
    protocol : Protocol, optional
        The registration's settings (needed without ``warp``).
    names : pair of str
        How errors name the two surfaces (e.g. ``SOURCE `a.vtk```).
    gifti : bool, default False
        Also write GIFTI frames.
    force : bool, default False
        Write into a folder that is not empty, replacing outputs.
    progress : callable, optional
        ``progress(stage, done, total)`` for the registration.
    on_findings : callable, optional
        Called with the review's findings before the frames are written; default: each one a
        :class:`~volreg.errors.VolregWarning`.
    """
    outdir = Path(outdir)
    frame_names = [f"frame_{k:03d}" for k in range(frames)]
    shared = shared_arrays(source, target)
    data_names = {name: {n: data_file_name(n, name, vertex_array_meta(source, name)) for n in frame_names}
                  for name in shared}
    with output_folder(outdir, force, outputs=MORPH_OUTPUTS) as folder:
        folder.check_writable(_output_names(frame_names, data_names, gifti), force=force)
        outdir = folder.path  # written into the run's staging folder, swapped in at the end
        registered = warp is None
        if registered:
            warp = register_surface_pair(source, target, protocol, None, progress, names=names)
        warped = warp(source.vertices)
        (on_findings or _issue_findings)(_review_morph(warp, source, target, warped, registered))
        moved = morph_vertices(source.vertices, warped, frames, linear=warp.linear)
        per_frame = morph_arrays(source, target, warped, shared, frames)
        structure = source.gifti.structure() if source.gifti is not None else None
        for k, verts in enumerate(moved):
            write_moved_surface(outdir / f"{frame_names[k]}.vtk", source, verts, per_frame[k], force)
            folder.record(outdir / f"{frame_names[k]}.vtk")
            if gifti:
                write_moved_gifti_surface(outdir / f"{frame_names[k]}.surf.gii", source, verts, force)
                folder.record(outdir / f"{frame_names[k]}.surf.gii")
                for name in shared:
                    path = outdir / data_names[name][frame_names[k]]
                    write_gifti_data(per_frame[k][name], path, meta=vertex_array_meta(source, name),
                                     structure=structure, force=force)
                    folder.record(path)
        colours = _frame_colours(per_frame) if shared else None
        images = render_frames(moved, source.triangles, colours, [outdir / f"{n}.png" for n in frame_names], force,
                               folder.record)
        _write_gif(images, outdir / "morph.gif", force)
        folder.record(outdir / "morph.gif")
