"""From a shape model's points to the fields and label maps of a template grid.

A deformation model describes a displacement ``d`` at the voxel centres ``x`` of the template's
labelled region (dilated by :data:`REGION_MARGIN` voxels), a surface model at the template's
boundary vertices.  To draw the label map of a shape ``x -> x + d(x)`` the displacement is
needed at every template voxel:

- :func:`fill_field` extends the region's values to the whole grid by each voxel's nearest
  region voxel (the region holds every label with a margin, so a label's own motion is never
  extrapolated);
- :func:`interpolate_displacement` spreads vertex displacements over the grid points by a thin
  plate spline (``scipy.interpolate.RBFInterpolator``) through a seeded subset of the vertices;
- :func:`labels_of_displacement` draws the template's labels where the map sends them: the
  label at ``y`` is the template's at ``phi^-1(y)`` (fixed-point inversion on the grid,
  :func:`~volreg.pipeline.template_shape.invert_displacement`), nearest neighbour.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.interpolate import RBFInterpolator

from volreg.grid import Grid, LabelVolume
from volreg.pipeline.template_shape import _sample_field, invert_displacement
from volreg.warp.resample import resample_labels

__all__ = ["REGION_MARGIN", "fill_field", "interpolate_displacement", "labelled_region", "labels_at",
           "labels_of_displacement", "nearest_region_index", "sample_field", "vertex_spline"]


def sample_field(field: np.ndarray, grid: Grid, points: np.ndarray) -> np.ndarray:
    """Trilinear samples of a ``(*shape, D)`` field at world points (N, D) mm; the nearest edge value outside."""
    return _sample_field(field, grid, np.asarray(points, float))

#: Voxels by which the labelled region is dilated: trilinear samples at a boundary vertex
#: read region voxels only.
REGION_MARGIN = 2


def labelled_region(labels: np.ndarray, margin: int = REGION_MARGIN) -> np.ndarray:
    """The template's non-zero labels dilated by ``margin`` voxels (a box-shaped structuring element).

    Returns
    -------
    bool array, the shape of ``labels``
    """
    mask = np.asarray(labels) != 0
    return ndimage.binary_dilation(mask, np.ones((3,) * mask.ndim, bool), iterations=margin) if margin else mask


def nearest_region_index(region: np.ndarray) -> np.ndarray:
    """For every grid voxel, the flat index among ``region``'s voxels (C order) of its nearest one.

    Returns
    -------
    int array, the shape of ``region``
    """
    order = np.full(region.shape, -1, np.int64)
    order[region] = np.arange(int(region.sum()))
    index = ndimage.distance_transform_edt(~region, return_distances=False, return_indices=True)
    return order[tuple(index)]


def fill_field(values: np.ndarray, nearest: np.ndarray) -> np.ndarray:
    """Region values (P, D) spread over the grid: ``(*shape, D)``, each voxel its nearest region voxel's."""
    return np.asarray(values, float)[nearest]


def vertex_spline(vertices: np.ndarray, displacement: np.ndarray, *, centres: int = 1500, seed: int = 0):
    """A thin plate spline through vertex displacements: a function of points (N, D) -> (N, D) mm.

    Parameters
    ----------
    vertices : (V, D) float array, mm
    displacement : (V, C) float array, mm
        At ``vertices`` (``C = D``, or several displacements side by side: the spline is linear
        in them, so one evaluation serves them all).
    centres : int
        At most this many vertices carry the spline (a seeded random subset beyond): its cost is
        ``O(N * centres)`` per evaluation.
    seed : int
    """
    v = np.asarray(vertices, float)
    displacement = np.asarray(displacement, float)
    if len(v) > centres:
        pick = np.sort(np.random.default_rng(seed).choice(len(v), centres, replace=False))
        v, displacement = v[pick], displacement[pick]
    spline = RBFInterpolator(v, displacement, kernel="thin_plate_spline", smoothing=1e-3)

    def evaluate(points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, float)
        out = np.empty((len(points), displacement.shape[1]))
        for s in range(0, len(points), 4096):
            out[s:s + 4096] = spline(points[s:s + 4096])
        return out

    return evaluate


def interpolate_displacement(vertices: np.ndarray, displacement: np.ndarray, points: np.ndarray, *,
                             centres: int = 1500, seed: int = 0) -> np.ndarray:
    """Vertex displacements spread to ``points`` (N, D) by :func:`vertex_spline`: (N, D) mm."""
    return vertex_spline(vertices, displacement, centres=centres, seed=seed)(points)


def labels_at(template: LabelVolume, displacement, points: np.ndarray, *, iterations: int = 30,
              tol: float = 1e-3) -> np.ndarray:
    """The template's labels moved by ``phi(x) = x + d(x)``, at ``points``: ``template(phi^-1(y))``.

    Parameters
    ----------
    template : LabelVolume
    displacement : callable
        ``d``: points (N, D) mm -> (N, D) mm.
    points : (N, D) float array, mm
    iterations, tol
        The fixed-point iteration ``v <- -d(y + v)`` (mm), as
        :func:`~volreg.pipeline.template_shape.invert_displacement`.

    Returns
    -------
    (N,) array of the template's dtype
    """
    y = np.asarray(points, float)
    v = -displacement(y)
    for _ in range(iterations):
        new = -displacement(y + v)
        step = np.abs(new - v).max(initial=0.0)
        v = new
        if step < tol:
            break
    return resample_labels(template, y + v, method="nearest").astype(template.array.dtype, copy=False)


def labels_of_displacement(template: LabelVolume, field: np.ndarray) -> LabelVolume:
    """The template's labels moved by ``phi(x) = x + field(x)``: ``template(phi^-1(y))`` on the template grid.

    Parameters
    ----------
    template : LabelVolume
    field : (*shape, D) float array, mm
        On the template's grid.

    Returns
    -------
    LabelVolume
        On the template's grid, the template's dtype.
    """
    grid = template.grid
    inverse = invert_displacement(np.asarray(field, float), grid)
    points = grid.grid_points().reshape(-1, grid.ndim) + inverse.reshape(-1, grid.ndim)
    moved = resample_labels(template, points, method="nearest").reshape(grid.shape)
    return template.with_array(moved.astype(template.array.dtype, copy=False))
