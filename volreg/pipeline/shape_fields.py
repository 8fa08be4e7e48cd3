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

__all__ = ["REGION_MARGIN", "fill_field", "interpolate_displacement", "labelled_region", "labels_of_displacement",
           "nearest_region_index", "sample_field"]


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


def interpolate_displacement(vertices: np.ndarray, displacement: np.ndarray, points: np.ndarray, *,
                             centres: int = 1500, seed: int = 0) -> np.ndarray:
    """Vertex displacements spread to other points by a thin plate spline.

    Parameters
    ----------
    vertices : (V, D) float array, mm
    displacement : (V, D) float array, mm
        At ``vertices``.
    points : (N, D) float array, mm
        Where the displacement is wanted.
    centres : int
        At most this many vertices carry the spline (a seeded random subset beyond): its cost is
        ``O(N * centres)``.
    seed : int

    Returns
    -------
    (N, D) float array, mm
    """
    v = np.asarray(vertices, float)
    if len(v) > centres:
        pick = np.sort(np.random.default_rng(seed).choice(len(v), centres, replace=False))
        v, displacement = v[pick], np.asarray(displacement, float)[pick]
    spline = RBFInterpolator(v, displacement, kernel="thin_plate_spline", smoothing=1e-3)
    points = np.asarray(points, float)
    out = np.empty((len(points), v.shape[1]))
    for s in range(0, len(points), 1 << 15):
        out[s:s + (1 << 15)] = spline(points[s:s + (1 << 15)])
    return out


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
