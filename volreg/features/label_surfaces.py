"""Label volume -> boundary meshes with outward normals, and their implicit surfaces.

Each label is a binary mask, lightly smoothed (a Gaussian about a voxel wide,
so that the mesh follows the object rather than the voxel staircase, with the
shrinkage that blurring causes on curved boundaries corrected) and
contoured at 1/2 by marching cubes (3-D, ``skimage.measure.marching_cubes``) or
marching squares (2-D, ``skimage.measure.find_contours``).  Vertices are mapped
to world (LPS, mm) through the volume's full geometry, oblique directions
included, and the cells are oriented so that normals point outward (a
direction matrix with negative determinant mirrors the mesh; this is detected
from the signed enclosed volume and undone).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable, Iterable, Literal, Sequence

import numpy as np
from scipy import ndimage
from skimage import measure

from volreg._threads import single_blas, thread_map
from volreg.features.implicit import ImplicitSurface
from volreg.grid import GridLike, LabelVolume, as_grid
from volreg.errors import SurfaceError
from volreg.settings import SurfaceSettings

__all__ = [
    "Surface",
    "SurfaceError",
    "label_surface",
    "label_surfaces",
    "surfaces_of_volumes",
    "implicit_surfaces",
    "implicit_on_grid",
    "voxel_size",
]


@dataclass(frozen=True, eq=False)
class Surface:
    """A boundary mesh in world coordinates.

    Attributes
    ----------
    vertices : (N, D) float ndarray, mm (LPS)
    cells : (F, D) int ndarray
        Triangles (D = 3) or line segments (D = 2), oriented outward.
    normals : (N, D) float ndarray
        Outward unit vertex normals.
    label : int
        The label value the surface bounds (0 if not from a label volume).
    smoothing : float, mm
        The Gaussian blur actually applied to the mask before contouring.
    """

    vertices: np.ndarray
    cells: np.ndarray
    normals: np.ndarray
    label: int = 0
    smoothing: float = 0.0

    @property
    def dim(self) -> int:
        """Spatial dimension ``D``."""
        return self.vertices.shape[1]

    def enclosed_volume(self) -> float:
        """Signed enclosed volume (D = 3, mm^3) or area (D = 2, mm^2); positive when outward."""
        return _signed_measure(self.vertices, self.cells)


def voxel_size(volume: LabelVolume) -> float:
    """A single voxel size for a possibly anisotropic grid: the largest spacing, mm."""
    return float(np.max(volume.spacing))


def _signed_measure(vertices: np.ndarray, cells: np.ndarray) -> float:
    v = [vertices[cells[:, i]] for i in range(cells.shape[1])]
    if cells.shape[1] == 3:
        return float(np.einsum("nd,nd->", v[0], np.cross(v[1], v[2])) / 6.0)
    return float(np.sum(v[0][:, 0] * v[1][:, 1] - v[1][:, 0] * v[0][:, 1]) / 2.0)


def _cell_normals(vertices: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Area-weighted cell normals (not normalised), (F, D)."""
    if cells.shape[1] == 3:
        a, b, c = (vertices[cells[:, i]] for i in range(3))
        return np.cross(b - a, c - a) / 2.0
    t = vertices[cells[:, 1]] - vertices[cells[:, 0]]
    return np.stack([t[:, 1], -t[:, 0]], axis=1)


def vertex_normals(vertices: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Unit vertex normals: area-weighted mean of the incident cell normals, (N, D)."""
    fn = _cell_normals(vertices, cells)
    # Each cell's normal added to its corners' sums: bincount over the flattened corners, one
    # column at a time (np.add.at's unbuffered adds are slower).
    corners = cells.ravel()
    n = len(vertices)
    vn = np.stack([np.bincount(corners, weights=np.repeat(fn[:, d], cells.shape[1]), minlength=n)
                   for d in range(vertices.shape[1])], axis=1)
    length = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.where(length > 0, length, 1.0)


def _contour(mask: np.ndarray, level: float, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Iso-contour of a padded float mask in its index space: (vertices, cells); in 3-D on every
    ``step``-th voxel along each axis."""
    if mask.ndim == 3:
        verts, faces, _, _ = measure.marching_cubes(mask, level=level, step_size=step)
        return verts, faces.astype(np.int64)
    verts, cells = [], []
    base = 0
    for c in measure.find_contours(mask, level):
        closed = len(c) > 2 and np.allclose(c[0], c[-1])
        pts = c[:-1] if closed else c
        k = len(pts)
        if k < 2:
            continue
        idx = np.arange(k)
        seg = np.stack([idx, (idx + 1) % k], axis=1) if closed else np.stack([idx[:-1], idx[1:]], axis=1)
        verts.append(pts)
        cells.append(seg + base)
        base += k
    if not verts:
        return np.zeros((0, 2)), np.zeros((0, 2), dtype=np.int64)
    return np.concatenate(verts), np.concatenate(cells)


def _mean_curvature(field: np.ndarray, spacing: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Sum of principal curvatures (1/mm) of the level sets of a field that is high inside.

    ``H = div(n)`` with the outward unit normal ``n = -grad u / |grad u|``, i.e.
    ``H = -(lap u - m^T hess(u) m) / |grad u|`` with ``m = grad u / |grad u|``.
    Derivatives are central differences with a one-voxel step, on values
    interpolated linearly at a stencil around each point (only where needed,
    not on the whole grid; cubic interpolation measured no better); the grid axes are orthogonal, so index-space
    derivatives divided by the spacing are physical ones.

    Parameters
    ----------
    field : (n_0, ..., n_{D-1}) float ndarray
    spacing : (D,) float ndarray, mm
    at : (N, D) float ndarray
        Continuous indices.

    Returns
    -------
    (N,) float ndarray, 1/mm
    """
    dim = field.ndim
    eye = np.eye(dim)
    sample = _edge_sampler(field, at)

    centre = sample(np.zeros(dim))
    grad = np.empty((len(at), dim))
    hess = np.empty((len(at), dim, dim))
    for a in range(dim):
        up, down = sample(eye[a]), sample(-eye[a])
        grad[:, a] = (up - down) / (2 * spacing[a])
        hess[:, a, a] = (up - 2 * centre + down) / spacing[a] ** 2
        for b in range(a + 1, dim):
            cross = sample(eye[a] + eye[b]) - sample(eye[a] - eye[b]) - sample(eye[b] - eye[a]) + sample(-eye[a] - eye[b])
            hess[:, a, b] = hess[:, b, a] = cross / (4 * spacing[a] * spacing[b])
    norm = np.linalg.norm(grad, axis=1) + 1e-12
    m = grad / norm[:, None]
    lap = np.trace(hess, axis1=1, axis2=2)
    return -(lap - np.einsum("na,nab,nb->n", m, hess, m)) / norm


def _edge_sampler(field: np.ndarray, at: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Linear interpolation of ``field`` at ``at + offset`` for integer offsets (within one voxel):
    the values of ``ndimage.map_coordinates(order=1, mode="nearest")``.

    Marching cubes and marching squares put almost every vertex on a grid edge (at most one
    non-integer index): there the interpolation is two gathers per offset, and only the other
    points (Lewiner's vertices inside ambiguous cubes, points near the array's edge) go through
    ``map_coordinates``, which costs far more per point.
    """
    base = np.floor(at)
    t = at - base
    base = base.astype(np.int64)
    fast = (np.count_nonzero(t, axis=1) <= 1) & np.all(base >= 1, axis=1) & \
        np.all(base <= np.array(field.shape) - 3, axis=1)
    slow = np.flatnonzero(~fast)
    fast = np.flatnonzero(fast)
    axis = np.argmax(t[fast], axis=1)
    w = t[fast, axis].astype(np.float64)
    strides = np.array([int(np.prod(field.shape[a + 1:])) for a in range(field.ndim)], dtype=np.int64)
    flat = np.ascontiguousarray(field).ravel()
    first = base[fast] @ strides
    along = strides[axis]

    def sample(offset: np.ndarray) -> np.ndarray:
        out = np.empty(len(at), dtype=field.dtype)
        index = first + int(np.asarray(offset, dtype=np.int64) @ strides)
        out[fast] = (1.0 - w) * flat[index] + w * flat[index + along]
        if len(slow):
            out[slow] = ndimage.map_coordinates(field, (at[slow] + offset).T, order=1, mode="nearest")
        return out

    return sample


def label_surface(
    volume: LabelVolume,
    label: int,
    *,
    smoothing: float = SurfaceSettings.smoothing,
    min_voxels: int = 8,
    box: tuple[slice, ...] | None = None,
    step: int = 1,
) -> Surface:
    """Boundary mesh of one label, in world mm with outward normals.

    Parameters
    ----------
    volume : LabelVolume
    label : int
        Label value (non-zero).
    smoothing : float
        Standard deviation of the Gaussian applied to the binary mask before
        contouring, in units of the largest voxel spacing (isotropic in mm).
        0 contours the raw mask: a voxel staircase whose normals are off by
        13-20 degrees.  A label too thin to survive the blur (its blurred mask
        stays below 1/2) is contoured with half, a quarter, then none of it;
        ``Surface.smoothing`` records what was used.  Blurring moves a curved boundary inward by ``H s^2 / 2``
        (``H`` the sum of principal curvatures, ``s`` the blur in mm); that
        shift is undone using ``H`` measured on the blurred mask.
    min_voxels : int
        Labels with fewer voxels raise :class:`SurfaceError`.
    box : tuple of slices, optional
        The label's bounding box in index space, as :meth:`LabelVolume.label_boxes`
        gives it (one pass over the volume for all labels); default: found here,
        with a pass over the whole volume.  The result is the same.
    step : int
        In 3-D, marching cubes on every ``step``-th voxel of the blurred mask along each axis:
        a coarser mesh of the same surface (about ``step^2`` times fewer vertices), for uses
        that need only where the surface lies.  Where that gives no contour (a label a few
        voxels thick), every voxel is used.

    Returns
    -------
    Surface

    Raises
    ------
    SurfaceError
        If the label is absent or has fewer than ``min_voxels`` voxels.
    """
    if box is None:
        found = ndimage.find_objects((volume.array == label).view(np.uint8))
        box = found[0] if found else None
    crop = None if box is None else volume.array[box] == label
    count = 0 if crop is None else int(crop.sum())
    if count == 0:
        raise SurfaceError(f"Label {label} is absent from the volume (labels present: {volume.labels().tolist()}).")
    if count < min_voxels:
        raise SurfaceError(f"Label {label} has {count} voxels, fewer than min_voxels={min_voxels}.")
    sigma_mm = float(smoothing) * voxel_size(volume)
    sigma_vox = sigma_mm / volume.spacing
    margin = 2 + int(np.ceil(3 * sigma_vox.max()))
    lo = np.array([b.start for b in box])
    crop = crop.astype(np.float32)
    padded = np.pad(crop, margin)
    # A structure thinner than about two blur widths never reaches 1/2 once
    # blurred; halve the blur until it does (down to the raw mask).
    for blur in (sigma_mm, sigma_mm / 2, sigma_mm / 4, 0.0):
        field = ndimage.gaussian_filter(padded, blur / volume.spacing, mode="constant") if blur > 0 else padded
        if field.max() >= 0.55:
            break
    sigma_mm = blur
    try:
        verts, cells = _contour(field, 0.5, step)
    except RuntimeError:  # scikit-image found no contour: none on that lattice
        verts, cells = np.zeros((0, field.ndim)), np.zeros((0, field.ndim), dtype=np.int64)
    if len(cells) == 0 and step > 1:
        verts, cells = _contour(field, 0.5)
    if len(cells) == 0:
        raise SurfaceError(f"Label {label} gave an empty contour (object thinner than the smoothing).")
    world = volume.index_to_world(verts + (lo - margin))
    if _signed_measure(world, cells) < 0:
        cells = cells[:, ::-1].copy()
    normals = vertex_normals(world, cells)
    if sigma_mm > 0:
        # Blurring a curved boundary moves its 1/2 level inward by H sigma^2 / 2
        # (H: sum of principal curvatures, positive where convex); move it back.
        shift = 0.5 * sigma_mm**2 * _mean_curvature(field, volume.spacing, verts)
        world = world + np.clip(shift, -sigma_mm, sigma_mm)[:, None] * normals
        normals = vertex_normals(world, cells)
    return Surface(world, cells, normals, int(label), smoothing=sigma_mm)


def label_surfaces(
    volume: LabelVolume,
    labels: Iterable[int] | None = None,
    *,
    on_small: Literal["error", "warn"] = "error",
    smoothing: float = SurfaceSettings.smoothing,
    min_voxels: int = 8,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[int, Surface]:
    """Boundary meshes of several labels.

    Parameters
    ----------
    volume : LabelVolume
    labels : iterable of int, optional
        Labels to extract; default every non-zero label present.
    on_small : {"error", "warn"}
        For an absent or too-small label: raise :class:`SurfaceError`, or warn
        and skip it.
    smoothing, min_voxels
        As in :func:`label_surface`.
    progress : callable, optional
        ``progress(stage, done, total)`` after each label.

    Returns
    -------
    dict of int to Surface
    """
    if on_small not in ("error", "warn"):
        raise ValueError(f"Expected `on_small` in ('error', 'warn'), got {on_small!r}.")
    labels = None if labels is None else [int(v) for v in labels]
    [(out, errors)] = surfaces_of_volumes([volume], labels, smoothing=[smoothing], min_voxels=min_voxels,
                                          progress=progress)
    for lab, err in errors.items():  # in the labels' order
        if on_small == "error":
            raise err
        warnings.warn(f"Skipping label {lab}: {err}", stacklevel=2)
    return out


def surfaces_of_volumes(
    volumes: Sequence[LabelVolume],
    labels: Iterable[int] | None = None,
    *,
    smoothing: Sequence[float],
    min_voxels: int = 8,
    step: int = 1,
    progress: Callable[[str, int, int], None] | None = None,
) -> list[tuple[dict[int, Surface], dict[int, SurfaceError]]]:
    """Boundary meshes of the same labels in several volumes, all on volreg's threads at once.

    The (volume, label) meshes are independent: they are made on :func:`thread_map`'s
    threads, largest label box first, so that one large label in each volume does not leave
    a thread idle at the end of each volume (the 1 mm phantom's grey shell takes three times
    its white core).

    Parameters
    ----------
    volumes : sequence of LabelVolume
    labels : iterable of int, optional
        Labels to extract from each volume; default every non-zero label present in it.
    smoothing : sequence of float
        :func:`label_surface`'s ``smoothing`` for each volume.
    min_voxels, step : int
        As in :func:`label_surface`.
    progress : callable, optional
        ``progress(stage, done, total)`` after each mesh.

    Returns
    -------
    list of (dict of int to Surface, dict of int to SurfaceError)
        Per volume, the meshes of its labels and the errors of those without one (absent or
        too small), each in the labels' order.
    """
    labels = None if labels is None else [int(v) for v in labels]  # once: an iterator is read for every volume
    jobs = []
    for k, volume in enumerate(volumes):
        boxes = volume.label_boxes()
        for lab in (sorted(boxes) if labels is None else labels):
            box = boxes.get(lab)
            size = 0 if box is None else int(np.prod([s.stop - s.start for s in box]))
            jobs.append((k, lab, box, size))
    order = sorted(range(len(jobs)), key=lambda i: -jobs[i][3])  # largest first (stable for ties)

    def extract(i: int) -> Surface | SurfaceError:
        k, lab, box, _ = jobs[i]
        try:
            return label_surface(volumes[k], lab, smoothing=smoothing[k], min_voxels=min_voxels, box=box, step=step)
        except SurfaceError as err:
            return err

    # The blur, marching cubes and the curvature's interpolation release the GIL.
    done: dict[int, Surface | SurfaceError] = {}
    results = thread_map(extract, order)
    try:
        for i, result in zip(order, results):
            done[i] = result
            if progress is not None:
                progress("extract surfaces", len(done), len(jobs))
    finally:
        results.close()  # joins the threads, also on an error or an interrupt
    out = [({}, {}) for _ in volumes]
    for i, (k, lab, _, _) in enumerate(jobs):
        out[k][1 if isinstance(done[i], SurfaceError) else 0][lab] = done[i]
    return out


@single_blas
def implicit_surfaces(
    volume: LabelVolume,
    surfaces: dict[int, Surface],
    *,
    min_width_voxels: float = SurfaceSettings.min_width_voxels,
    progress: Callable[[str, int, int], None] | None = None,
    **kwargs,
) -> dict[int, ImplicitSurface]:
    """Fit an :class:`ImplicitSurface` to each surface of a label volume.

    Parameters
    ----------
    volume : LabelVolume
        The volume the surfaces came from (for the voxel size).
    surfaces : dict of int to Surface
    min_width_voxels : float
        Finest kernel width in voxels (largest spacing).
    progress : callable, optional
        ``progress(stage, done, total)`` after each label.
    **kwargs
        Passed to :class:`ImplicitSurface`.
    """
    min_width = min_width_voxels * voxel_size(volume)

    def fit(surf: Surface) -> ImplicitSurface:
        return ImplicitSurface(surf.vertices, surf.normals, min_width=min_width, **kwargs)

    out = {}
    fits = thread_map(fit, list(surfaces.values()))  # independent fits, on volreg's threads
    try:
        for i, (lab, f) in enumerate(zip(surfaces, fits)):
            out[lab] = f
            if progress is not None:
                progress("fit implicit surfaces", i + 1, len(surfaces))
    finally:
        fits.close()  # joins the threads, also when progress raises (an interrupt)
    return out


def implicit_on_grid(surface: ImplicitSurface, volume: GridLike, *, chunk: int = 1 << 20) -> np.ndarray:
    """Sample an implicit surface at every voxel centre of a grid.

    Only the voxels inside the surface's :meth:`~ImplicitSurface.bounds` are
    evaluated (in chunks of ``chunk`` points, :meth:`~volreg.grid.Grid.chunks`);
    elsewhere ``f`` equals its offset exactly and is filled in without
    evaluation.

    Parameters
    ----------
    surface : ImplicitSurface
    volume : Grid, LabelVolume or (shape, affine)
        The grid whose voxel centres are sampled (a volume's array is not used).
    chunk : int
        Points evaluated at a time.

    Returns
    -------
    ndarray of float32, shape ``volume.shape``, mm
    """
    grid = as_grid(volume, "volume")
    out = np.full(grid.shape, surface.offset, dtype=np.float32)
    window = grid.index_window(*surface.bounds())
    if window is None:
        return out
    flat_out = out.reshape(-1)  # a view: ``out`` is C-contiguous
    for part in grid.chunks(chunk, window):
        flat_out[part.flat] = surface(part.points)
    return out
