"""PNG figures of one registration: labels, warped labels and the deformed grid; error maps.

The registration's report figure (:func:`write_report_figure`) is drawn straight into an
RGB array and encoded by Pillow: a registration writes one with every run, and drawing it
with matplotlib (and importing matplotlib) would take a noticeable share of the command's
time.  The consistency test's error maps
(:func:`write_error_figure`), which need a colour bar, are drawn with matplotlib's Agg
canvas (no pyplot, no GUI backend), imported only then.  Both are written atomically like
every other output of :mod:`volreg.io`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import numpy.typing as npt

from volreg.errors import VolregIOError
from volreg.io._atomic import atomic_output

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes

__all__ = ["write_report_figure", "write_error_figure"]

#: Width of the report figure (px); text and margins are sized as at 100 dots per inch.
_WIDTH_PX = 1400
#: Nominal spacing of the deformed grid's lines, in fixed-grid voxels.
_GRID_STEP = 8
#: matplotlib's figure resolution for the error figure (dots per inch).
_DPI = 100

_COLUMNS = ("fixed", "moving", "warped moving (contours: fixed)", "warped grid")

#: matplotlib's ``tab20`` colours (the qualitative palette of Vega), as hex RGB.
_TAB20 = ("1f77b4 aec7e8 ff7f0e ffbb78 2ca02c 98df8a d62728 ff9896 9467bd c5b0d5 "
          "8c564b c49c94 e377c2 f7b6d2 7f7f7f c7c7c7 bcbd22 dbdb8d 17becf 9edae5").split()


def _palette() -> np.ndarray:
    """20 qualitative RGB colours (``tab20``, the saturated half first), shape (20, 3)."""
    colours = np.array([[int(h[i:i + 2], 16) / 255.0 for i in (0, 2, 4)] for h in _TAB20])
    return np.concatenate([colours[0::2], colours[1::2]])


_PALETTE = _palette()


def _label_rgb(labels: np.ndarray) -> np.ndarray:
    """Colour a label array: shape ``labels.shape + (3,)``, floats in [0, 1].

    Label 0 is black; label ``v != 0`` gets ``_PALETTE[(v - 1) % 20]``, so a
    value has the same colour in every panel and every figure.
    """
    lab = np.asarray(labels).astype(np.int64, copy=False)
    rgb = _PALETTE[np.mod(lab - 1, len(_PALETTE))]
    rgb[lab == 0] = 0.0
    return rgb


def _boundary_segments(labels: np.ndarray) -> np.ndarray:
    """Voxel edges between differing labels of a 2-D slice, as line segments.

    ``labels`` has shape (H, V) (first axis horizontal in the panel); voxel
    ``(a, b)`` is centred at ``(a, b)``.  Returns shape (S, 2, 2): S segments
    of two (x, y) points each, in voxel units.
    """
    lab = np.asarray(labels)
    # Edges between horizontal neighbours: vertical segments at x = a + 1/2.
    a, b = np.nonzero(lab[1:, :] != lab[:-1, :])
    vertical = np.stack(
        [np.stack([a + 0.5, b - 0.5], axis=-1), np.stack([a + 0.5, b + 0.5], axis=-1)], axis=1
    )
    # Edges between vertical neighbours: horizontal segments at y = b + 1/2.
    a, b = np.nonzero(lab[:, 1:] != lab[:, :-1])
    horizontal = np.stack(
        [np.stack([a - 0.5, b + 0.5], axis=-1), np.stack([a + 0.5, b + 0.5], axis=-1)], axis=1
    )
    return np.concatenate([vertical, horizontal]).astype(float).reshape(-1, 2, 2)


def _bbox_centre(labels: np.ndarray) -> tuple[int, ...]:
    """Integer centre of the bounding box of the non-zero voxels (array centre if none)."""
    nonzero = labels != 0
    centre = []
    for axis, n in enumerate(labels.shape):
        others = tuple(a for a in range(labels.ndim) if a != axis)
        hit = np.flatnonzero(np.any(nonzero, axis=others)) if others else np.flatnonzero(nonzero)
        centre.append(int((hit[0] + hit[-1]) // 2) if hit.size else (n - 1) // 2)
    return tuple(centre)


#: A plane of the figure: its name, the axis its slices are taken across (None for a 2-D image)
#: and its in-plane axes (horizontal, vertical), in ITK index order i, j, k.
_Plane = tuple[str, int | None, tuple[int, int]]
_PLANES_3D: tuple[_Plane, ...] = (("axial", 2, (0, 1)), ("coronal", 1, (0, 2)), ("sagittal", 0, (1, 2)))
_AXIS_NAMES = "ijk"


def _take(array: np.ndarray, axis: int | None, index: int) -> np.ndarray:
    """The slice of ``array`` at ``index`` along ``axis`` (``array`` itself if ``axis`` is None)."""
    return array if axis is None else np.take(array, index, axis=axis)


def _style(ax: Axes, shape: tuple[int, ...], aspect: float) -> None:
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_xlim(-0.5, shape[0] - 0.5)
    ax.set_ylim(-0.5, shape[1] - 0.5)
    ax.set_aspect(aspect)
    ax.set_anchor("N")  # top-align the panels of a row so the column titles line up


@lru_cache(maxsize=None)
def _font(size_px: int):
    """Pillow's default font (scalable where Pillow has FreeType, else its bitmap font)."""
    from PIL import ImageFont

    return ImageFont.load_default(size=size_px)


def _pixel_voxels(n: int, size: int) -> np.ndarray:
    """The voxel (of ``n``) under each of ``size`` pixels spanning them, shape (size,)."""
    return np.minimum(((np.arange(size) + 0.5) * (n / size)).astype(np.int64), n - 1)


def _edges(image: np.ndarray) -> np.ndarray:
    """Pixels of a (H, W) label image whose right or lower neighbour holds another label."""
    edge = np.zeros(image.shape, dtype=bool)
    edge[:, :-1] |= image[:, 1:] != image[:, :-1]
    edge[:-1, :] |= image[1:, :] != image[:-1, :]
    return edge


def _label_image(labels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A (H, V) label slice as a (h, w) image of ``size = (w, h)`` px, origin lower left
    (first axis horizontal), nearest neighbour."""
    w, h = size
    return labels[_pixel_voxels(labels.shape[0], w)][:, _pixel_voxels(labels.shape[1], h)[::-1]].T


def _rgb8(rgb: np.ndarray) -> np.ndarray:
    return np.round(255.0 * rgb).astype(np.uint8)


def _labels_panel(labels: np.ndarray, size: tuple[int, int], contours: np.ndarray | None = None) -> np.ndarray:
    """Label colours with their boundaries in black, and (``contours``, another slice of the
    same shape) that slice's boundaries in white: a (h, w, 3) uint8 image of ``size = (w, h)``."""
    image = _label_image(labels, size)
    rgb = _rgb8(_label_rgb(image))
    rgb[_edges(image)] = 0
    if contours is not None:
        rgb[_edges(_label_image(contours, size))] = 255
    return rgb


def _grid_panel(labels: np.ndarray, disp: np.ndarray, size: tuple[int, int]):
    """Faint labels and a regular grid moved by the in-plane displacement; returns the
    Pillow image (``size = (w, h)`` px) and the grid's step (voxels).

    ``disp`` has shape ``labels.shape + (2,)``: the (horizontal, vertical) displacement in
    voxels.  Grid point ``p`` is drawn at ``p + disp[p]``.
    """
    from PIL import Image, ImageDraw

    w, h = size
    image = _label_image(labels, size)
    faint = _rgb8(0.6 + 0.4 * _label_rgb(image))
    faint[image == 0] = 255
    panel = Image.fromarray(faint, "RGB")
    draw = ImageDraw.Draw(panel)
    nh, nv = labels.shape
    step = max(2, min(_GRID_STEP, min(nh, nv) // 4))
    disp = np.nan_to_num(np.asarray(disp, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)

    def pixels(x: np.ndarray, y: np.ndarray) -> list:
        px = np.clip((x + 0.5) * (w / nh), -4.0 * w, 5.0 * w)
        py = np.clip(h - (y + 0.5) * (h / nv), -4.0 * h, 5.0 * h)
        return np.stack([px, py], axis=-1).ravel().tolist()

    ink = (0x1A, 0x1A, 0x66)
    across = np.arange(nh, dtype=float)
    for v0 in range(0, nv, step):
        draw.line(pixels(across + disp[:, v0, 0], v0 + disp[:, v0, 1]), fill=ink, width=1)
    up = np.arange(nv, dtype=float)
    for h0 in range(0, nh, step):
        draw.line(pixels(h0 + disp[h0, :, 0], up + disp[h0, :, 1]), fill=ink, width=1)
    return panel, step


def _fit(shape: tuple[int, ...], aspect: float, box: tuple[float, float]) -> tuple[int, int]:
    """Pixel size (w, h) of a (H, V) slice of physical aspect ``aspect`` (vertical / horizontal
    voxel size) fitted into ``box = (w, h)`` px."""
    width, height = float(shape[0]), float(shape[1]) * aspect
    scale = min(box[0] / width, box[1] / height)
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))


def _text(draw, xy: tuple[float, float], text: str, size_px: int, anchor: str) -> None:
    """``text`` at ``xy`` placed by Pillow's two-letter ``anchor`` (e.g. ``"mt"``: middle, top)."""
    font = _font(size_px)
    try:
        draw.text(xy, text, fill=(0, 0, 0), font=font, anchor=anchor)
    except ValueError:  # a Pillow without FreeType: its bitmap font takes no anchor
        left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
        dx = {"l": 0.0, "m": 0.5, "r": 1.0}[anchor[0]] * (right - left)
        dy = {"a": 0.0, "t": 0.0, "m": 0.5, "b": 1.0}.get(anchor[1], 0.0) * (bottom - top)
        draw.text((xy[0] - dx, xy[1] - dy), text, fill=(0, 0, 0), font=font)


def _shape_str(shape: tuple[int, ...]) -> str:
    return "(" + ", ".join(str(n) for n in shape) + ")"


def _labels_array(name: str, value: npt.ArrayLike, dims: str) -> np.ndarray:
    array = np.asarray(value)
    if array.dtype.kind not in "iub":
        raise VolregIOError(f"Expected `{name}` of integer dtype (labels), got {array.dtype}.")
    if array.ndim not in (2, 3) or 0 in array.shape:
        raise VolregIOError(
            f"Expected `{name}` of shape {dims} or its 2-D form, non-empty, got {_shape_str(array.shape)}."
        )
    return array


def _spacing(name: str, value: Sequence[float] | npt.ArrayLike, ndim: int) -> np.ndarray:
    try:
        sp = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        sp = np.array([np.nan])
    if sp.shape != (ndim,) or not np.all(np.isfinite(sp)) or not np.all(sp > 0):
        raise VolregIOError(f"Expected `{name}` of {ndim} positive finite voxel sizes (mm), got {value!r}.")
    return sp


class _ReportInputs(NamedTuple):
    """The checked inputs of :func:`write_report_figure`."""

    fix: np.ndarray  #: fixed labels, (X, Y[, Z])
    mov: np.ndarray  #: moving labels, (X', Y'[, Z'])
    war: np.ndarray  #: warped moving labels, (X, Y[, Z])
    disp: np.ndarray  #: displacement, (X, Y[, Z], D), in fixed-grid voxels or turned into them by ``to_voxels``
    to_voxels: np.ndarray | None  #: (D, D) float, or None
    fsp: np.ndarray  #: fixed voxel sizes, (D,) mm
    msp: np.ndarray  #: moving voxel sizes, (D,) mm


def _report_inputs(fixed, moving, warped, displacement, fixed_spacing, moving_spacing, title,
                   to_voxels) -> _ReportInputs:
    """Check the arrays, spacings and title of :func:`write_report_figure` (in that order) and
    return them as arrays; raise :class:`VolregIOError` naming the first that does not fit."""
    fix = _labels_array("fixed", fixed, "(X, Y, Z)")
    ndim = fix.ndim
    dims = "(X, Y, Z)" if ndim == 3 else "(X, Y)"
    mov = _labels_array("moving", moving, "(X', Y', Z')")
    if mov.ndim != ndim:
        primes = "(X', Y', Z')" if ndim == 3 else "(X', Y')"
        raise VolregIOError(
            f"Expected `moving` of shape {primes} ({ndim}-D like `fixed`), got {_shape_str(mov.shape)}."
        )
    war = _labels_array("warped", warped, dims)
    if war.shape != fix.shape:
        raise VolregIOError(
            f"Expected `warped` of shape {dims} = {_shape_str(fix.shape)}, got {_shape_str(war.shape)}."
        )
    disp = np.asarray(displacement)
    want = fix.shape + (ndim,)
    disp_dims = dims[:-1] + f", {ndim})"
    if disp.shape != want:
        raise VolregIOError(
            f"Expected `displacement` of shape {disp_dims} = {_shape_str(want)}, got {_shape_str(disp.shape)}."
        )
    if disp.dtype.kind not in "fiu":
        raise VolregIOError(f"Expected `displacement` of real dtype (voxels), got {disp.dtype}.")
    if to_voxels is not None:
        to_voxels = np.asarray(to_voxels, dtype=float)
        if to_voxels.shape != (ndim, ndim) or not np.all(np.isfinite(to_voxels)):
            raise VolregIOError(f"Expected `to_voxels` of shape ({ndim}, {ndim}), finite, got shape {to_voxels.shape}.")
    fsp = _spacing("fixed_spacing", fixed_spacing, ndim)
    msp = _spacing("moving_spacing", moving_spacing, ndim)
    if title is not None and not isinstance(title, str):
        raise VolregIOError(f"Expected `title` to be a string or None, got {type(title).__name__}.")
    return _ReportInputs(fix, mov, war, disp, to_voxels, fsp, msp)


# Layout of the report figure, in pixels at 100 dots per inch: the margins left and right of the
# panels, the gap between columns, the margin below the last row and the gap between rows.
_LEFT, _RIGHT, _GAP_W = 49, 7, 16
_BOTTOM, _GAP_H = 15, 40


def _row_heights(inputs: _ReportInputs, planes: tuple[_Plane, ...], panel_w: float) -> list[int]:
    """Each row's height (px): the taller of its fixed and moving panels (physical height over
    width, kept within 0.3 to 2) at width ``panel_w`` px."""
    fix, mov, fsp, msp = inputs.fix, inputs.mov, inputs.fsp, inputs.msp
    row_h = []
    for _, _, (ah, av) in planes:
        ratio = max(
            fix.shape[av] * fsp[av] / (fix.shape[ah] * fsp[ah]),
            mov.shape[av] * msp[av] / (mov.shape[ah] * msp[ah]),
        )
        row_h.append(int(round(panel_w * float(np.clip(ratio, 0.3, 2.0)))))
    return row_h


def _row_panels(inputs: _ReportInputs, plane: _Plane, fc: tuple[int, ...], mc: tuple[int, ...],
                box: tuple[float, float]) -> tuple[list, list[str | None]]:
    """The four panels of one plane's row (Pillow images fitted into ``box = (w, h)`` px), through
    the fixed centre ``fc`` (the moving panel: ``mc``), and the note under each (or None)."""
    from PIL import Image

    _, axis, (ah, av) = plane
    fix_aspect = float(inputs.fsp[av] / inputs.fsp[ah])
    mov_aspect = float(inputs.msp[av] / inputs.msp[ah])
    fix_sl = _take(inputs.fix, axis, fc[axis] if axis is not None else 0)
    mov_sl = _take(inputs.mov, axis, mc[axis] if axis is not None else 0)
    war_sl = _take(inputs.war, axis, fc[axis] if axis is not None else 0)
    disp_sl = _take(inputs.disp, axis, fc[axis] if axis is not None else 0).astype(float, copy=False)
    if inputs.to_voxels is not None:
        disp_sl = disp_sl @ inputs.to_voxels
    disp_sl = disp_sl[..., [ah, av]]
    fix_size, mov_size = _fit(fix_sl.shape, fix_aspect, box), _fit(mov_sl.shape, mov_aspect, box)
    grid, step = _grid_panel(fix_sl, disp_sl, fix_size)
    panels = [
        Image.fromarray(_labels_panel(fix_sl, fix_size), "RGB"),
        Image.fromarray(_labels_panel(mov_sl, mov_size), "RGB"),
        Image.fromarray(_labels_panel(war_sl, fix_size, contours=fix_sl), "RGB"),
        grid,
    ]
    notes = [None, None if axis is None else f"moving {_AXIS_NAMES[axis]}={mc[axis]}", None,
             f"grid every {step} voxels ({_AXIS_NAMES[ah]} to the right, {_AXIS_NAMES[av]} up)"]
    return panels, notes


def _paste_row(canvas, draw, panels: list, notes: list[str | None], y0: int, panel_w: float, *,
               column_titles: bool, row_title: str) -> None:
    """Paste one row's panels at height ``y0`` px, centred in their columns and framed, with the
    notes under them, the column titles above them (``column_titles``) and ``row_title`` rotated
    at their left."""
    from PIL import Image, ImageDraw

    for col, (panel, note) in enumerate(zip(panels, notes)):
        x0 = int(round(_LEFT + col * (panel_w + _GAP_W) + (panel_w - panel.width) / 2))
        canvas.paste(panel, (x0, y0))
        draw.rectangle((x0 - 1, y0 - 1, x0 + panel.width, y0 + panel.height), outline=(0, 0, 0))
        centre = x0 + panel.width / 2
        if column_titles:
            _text(draw, (centre, y0 - 6), _COLUMNS[col], 15, "mb")
        if note is not None:
            _text(draw, (centre, y0 + panel.height + 3), note, 12, "mt")
        if col == 0:
            size = draw.textbbox((0, 0), row_title, font=_font(15))
            label = Image.new("RGB", (size[2] + 2, size[3] + 2), (255, 255, 255))
            _text(ImageDraw.Draw(label), (1, 1), row_title, 15, "la")
            label = label.rotate(90, expand=True)
            canvas.paste(label, (max(0, x0 - 6 - label.width), int(y0 + (panel.height - label.height) / 2)))


def write_report_figure(
    path: str | os.PathLike[str],
    fixed: npt.ArrayLike,
    moving: npt.ArrayLike,
    warped: npt.ArrayLike,
    displacement: npt.ArrayLike,
    *,
    fixed_spacing: Sequence[float] | npt.ArrayLike,
    moving_spacing: Sequence[float] | npt.ArrayLike,
    force: bool = False,
    title: str | None = None,
    to_voxels: npt.ArrayLike | None = None,
) -> None:
    """Write a PNG showing the labels, the warped moving labels and the deformed grid.

    One row per orthogonal plane (axial ``k``, coronal ``j``, sagittal ``i``)
    through the centre of the bounding box of the non-zero fixed labels (the
    moving panel uses the centre of its own labels' bounding box); 2-D inputs
    give a single row.  Four columns: the fixed labels, the moving labels, the
    warped moving labels with the fixed labels' boundaries overlaid in white,
    and a regular grid (lines every ~8 voxels) on the fixed slice moved by the
    in-plane displacement over the faint fixed labels.  Each label value has
    one colour in every panel (label 0 black); label boundaries are drawn
    along voxel edges.  Panels have physical aspect (from the spacings),
    origin lower left (first index axis horizontal), no ticks.  The figure is
    1400 px wide.

    Parameters
    ----------
    path : path-like
        Output file; must end in ``.png``.
    fixed : array_like of int, shape (X, Y, Z) or (X, Y)
        Fixed labels, ITK index order ``[i, j, k]``.
    moving : array_like of int, shape (X', Y', Z') or (X', Y')
        Moving labels on their own grid (same number of dimensions as ``fixed``).
    warped : array_like of int, shape (X, Y, Z) or (X, Y)
        Moving labels resampled onto the fixed grid.
    displacement : array_like of float, shape (X, Y, Z, 3) or (X, Y, 2)
        Displacement ``u(x)`` at each fixed voxel, in fixed-grid voxels along
        ``i, j, k``: voxel ``x`` maps to ``x + u(x)``; or in other units, with
        ``to_voxels``.
    fixed_spacing, moving_spacing : sequence of float, length 3 (or 2)
        Voxel sizes (mm) of the fixed and moving grids, used for each panel's
        aspect ratio.
    force : bool, default False
        Overwrite an existing ``path``.
    title : str, optional
        Figure title.
    to_voxels : array_like of float, shape (3, 3) or (2, 2), optional
        The matrix ``M`` that turns ``displacement`` into fixed-grid voxels,
        ``u M`` (for a displacement in LPS mm, the fixed grid's direction with
        each column divided by its spacing).  Applied to the drawn slices only.

    Raises
    ------
    VolregIOError
        If ``path`` does not end in ``.png``, the shapes, dtypes or spacings
        do not match the above, ``path`` exists and ``force`` is false, or the
        write fails; nothing is left behind on failure.
    """
    p = Path(path)
    if not p.name.lower().endswith(".png") or p.name.lower() == ".png":
        raise VolregIOError(f"Expected `path` ending in `.png` (a PNG file name), got `{p}`.")
    inputs = _report_inputs(fixed, moving, warped, displacement, fixed_spacing, moving_spacing, title, to_voxels)
    fc = _bbox_centre(inputs.fix)
    mc = _bbox_centre(inputs.mov)
    if inputs.fix.ndim == 3:
        planes: tuple[_Plane, ...] = _PLANES_3D
    else:
        planes = (("slice", None, (0, 1)),)

    panel_w = (_WIDTH_PX - _LEFT - _RIGHT - 3 * _GAP_W) / 4
    row_h = _row_heights(inputs, planes, panel_w)
    top = 95 if title else 45
    height = top + _BOTTOM + sum(row_h) + _GAP_H * (len(planes) - 1)

    from PIL import Image, ImageDraw

    canvas = Image.new("RGB", (_WIDTH_PX, height), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    if title:
        _text(draw, (_WIDTH_PX / 2, 15), title, 19, "mt")
    y0 = top
    for row, plane in enumerate(planes):
        name, axis, _ = plane
        panels, notes = _row_panels(inputs, plane, fc, mc, (panel_w, float(row_h[row])))
        where = "" if axis is None else f" {_AXIS_NAMES[axis]}={fc[axis]}"
        _paste_row(canvas, draw, panels, notes, y0, panel_w, column_titles=row == 0, row_title=f"{name}{where}")
        y0 += row_h[row] + _GAP_H

    with atomic_output(p, force=force) as tmp:
        try:
            canvas.save(str(tmp), format="PNG")
        except OSError as exc:
            raise VolregIOError(f"Figure `{p}` could not be written: {exc.strerror}.") from exc


def write_error_figure(
    path: str | os.PathLike[str],
    labels: npt.ArrayLike,
    error: npt.ArrayLike,
    *,
    spacing: Sequence[float] | npt.ArrayLike,
    force: bool = False,
    title: str | None = None,
) -> None:
    """Slices of an error map (mm) with label boundaries: the consistency test's picture.

    Parameters
    ----------
    path : path-like
        Output ``.png``, written atomically.
    labels : (n_i, n_j[, n_k]) integer array_like
        Label volume whose boundaries are drawn (black), ITK index order.
    error : array_like, same shape as ``labels``
        Error magnitude per voxel, mm (e.g. ``|tau_BA(tau_AB(x)) - x|``).
    spacing : (D,) float, mm
        Voxel spacing (sets the panels' aspect ratios).
    force : bool
        Whether an existing ``path`` may be replaced.
    title : str, optional
        Figure title.

    Notes
    -----
    One panel per plane (one for 2-D) through the centre of the labels'
    bounding box; the colour scale runs from 0 to the 99th percentile of the
    error inside the labels (or everywhere, if there are none), shown by a
    colour bar.
    """
    p = Path(path)
    if p.suffix.lower() != ".png":
        raise VolregIOError(f"Expected a `.png` path for the figure, got `{p}`.")
    lab = _labels_array("labels", labels, "2-D or 3-D")
    err = np.asarray(error)
    if err.shape != lab.shape or err.dtype.kind not in "fiu":
        raise VolregIOError(f"Expected a real `error` of shape {_shape_str(lab.shape)}, got {err.dtype} {_shape_str(err.shape)}.")
    err = err.astype(float, copy=False)
    sp = _spacing("spacing", spacing, lab.ndim)
    inside = err[lab != 0] if np.any(lab != 0) else err.ravel()
    vmax = float(np.percentile(inside, 99)) if inside.size else 1.0
    vmax = vmax if vmax > 0 else 1.0
    centre = _bbox_centre(lab)
    planes = _PLANES_3D if lab.ndim == 3 else (("slice", None, (0, 1)),)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure

    with atomic_output(p, force=force) as tmp:
        fig = Figure(figsize=(4.2 * len(planes) + 1.0, 4.6), dpi=_DPI, facecolor="white")
        canvas = FigureCanvasAgg(fig)
        axes = fig.subplots(1, len(planes), squeeze=False)[0]
        image = None
        for ax, (name, axis, (ah, av)) in zip(axes, planes):
            index = centre[axis] if axis is not None else 0
            lab_sl = _take(lab, axis, index)
            err_sl = _take(err, axis, index)
            aspect = float(sp[av] / sp[ah])
            image = ax.imshow(err_sl.T, origin="lower", interpolation="nearest", aspect=aspect,
                              cmap="magma", vmin=0.0, vmax=vmax)
            ax.add_collection(LineCollection(_boundary_segments(lab_sl), colors="#33cc33", linewidths=0.6))
            _style(ax, lab_sl.shape, aspect)
            ax.set_title(name if axis is None else f"{name} {_AXIS_NAMES[axis]}={index}", fontsize=11)
        fig.colorbar(image, ax=list(axes), shrink=0.8, label="error (mm)")
        if title:
            fig.suptitle(title, fontsize=12)
        try:
            canvas.print_png(str(tmp))
        except OSError as exc:
            raise VolregIOError(f"Figure `{p}` could not be written: {exc.strerror}.") from exc
