"""Label volume -> meshes: world placement, outward orientation, small labels, grids."""

import numpy as np
import pytest

from shapes import Disc2D, Ellipsoid, label_volume, rotation
from volreg.features.implicit import ImplicitSurface
from volreg.errors import SurfaceError
from volreg.features.label_surfaces import implicit_on_grid, label_surface, label_surfaces
from volreg.grid import LabelVolume

SPHERE = Ellipsoid((12, 12, 12), (0.31, 0.17, -0.23))

GEOMETRIES = {
    "identity": (np.eye(3), (1.0, 1.0, 1.0)),
    "lps-to-ras-flip": (np.diag([-1.0, -1.0, 1.0]), (1.0, 1.0, 1.0)),
    "mirrored": (np.diag([1.0, 1.0, -1.0]), (1.0, 1.0, 1.0)),
    "oblique-anisotropic": (rotation(30), (0.8, 0.8, 2.0)),
}


def _sphere_volume(direction, spacing):
    spacing = np.asarray(spacing)
    shape = tuple(int(np.ceil(34 / s)) for s in spacing)
    centre_index = (np.array(shape) - 1) / 2
    origin = -direction @ (centre_index * spacing)
    return label_volume(shape, spacing, direction, origin, SPHERE.signed_distance, label=7)


@pytest.mark.parametrize("name", list(GEOMETRIES))
def test_sphere_mesh_in_world_with_outward_normals(name):
    vol = _sphere_volume(*GEOMETRIES[name])
    surf = label_surface(vol, 7)
    radial = surf.vertices - SPHERE.centre
    radius = np.linalg.norm(radial, axis=1)
    # Vertices lie on the sphere to a fraction of the (largest) voxel.
    assert np.abs(radius - 12.0).mean() < 0.15 * vol.spacing.max()
    # Every normal points outward and is close to radial.
    cos = np.einsum("nd,nd->n", surf.normals, radial / radius[:, None])
    assert np.all(cos > 0.5) and cos.mean() > 0.99
    assert surf.enclosed_volume() == pytest.approx(4 / 3 * np.pi * 12**3, rel=0.03)
    assert surf.label == 7


@pytest.mark.parametrize("name", ["identity", "oblique-anisotropic"])
def test_a_mesh_on_every_second_voxel_lies_on_the_same_sphere_with_fewer_vertices(name):
    vol = _sphere_volume(*GEOMETRIES[name])
    fine, coarse = label_surface(vol, 7), label_surface(vol, 7, step=2)
    radius = np.linalg.norm(coarse.vertices - SPHERE.centre, axis=1)
    assert np.abs(radius - 12.0).mean() < 0.25 * vol.spacing.max()
    assert len(coarse.vertices) < 0.4 * len(fine.vertices)
    assert coarse.enclosed_volume() == pytest.approx(4 / 3 * np.pi * 12**3, rel=0.05)


def test_a_label_too_thin_for_every_second_voxel_is_meshed_on_every_voxel():
    array = np.zeros((20, 20, 20), np.uint8)
    # A sheet one voxel thick and one voxel beside it, none of them on every second voxel of the
    # label's box (which starts at (5, 5, 10)): that lattice holds no voxel of the label.
    array[5:15, 5:15, 11] = 3
    array[6, 6, 10] = 3
    vol = LabelVolume(array, np.zeros(3), np.ones(3), np.eye(3))
    surf = label_surface(vol, 3, smoothing=0, step=2)
    assert len(surf.vertices) == len(label_surface(vol, 3, smoothing=0).vertices) > 0


def test_unsmoothed_mesh_is_the_voxel_staircase():
    vol = _sphere_volume(*GEOMETRIES["identity"])
    raw = label_surface(vol, 7, smoothing=0)
    smooth = label_surface(vol, 7)
    angle = lambda s: np.degrees(np.arccos(np.einsum("nd,nd->n", s.normals, (s.vertices - SPHERE.centre)
                                                    / np.linalg.norm(s.vertices - SPHERE.centre, axis=1)[:, None]).clip(-1, 1))).mean()
    assert angle(raw) > 2 * angle(smooth)


def test_two_dimensional_outline_is_oriented_outward():
    disc = Disc2D((15, 9), (0.2, 0.1))
    for direction in (np.eye(2), np.diag([-1.0, 1.0])):
        vol = label_volume((50, 50), (1.0, 1.0), direction, direction @ np.array([-24.5, -24.5]), disc.signed_distance)
        surf = label_surface(vol, 1)
        assert surf.cells.shape[1] == 2
        assert surf.enclosed_volume() == pytest.approx(np.pi * 15 * 9, rel=0.03)
        assert np.einsum("nd,nd->n", surf.normals, surf.vertices - disc.centre).min() > 0


def test_absent_and_small_labels():
    vol = _sphere_volume(*GEOMETRIES["identity"])
    array = vol.array.copy()
    array[0, 0, 0] = 3  # a one-voxel label
    vol = vol.with_array(array)
    with pytest.raises(SurfaceError, match="Label 5 is absent"):
        label_surface(vol, 5)
    with pytest.raises(SurfaceError, match="Label 3 has 1 voxels"):
        label_surfaces(vol)
    with pytest.warns(UserWarning, match="Skipping label 3"):
        out = label_surfaces(vol, on_small="warn")
    assert list(out) == [7]
    with pytest.raises(ValueError, match="`on_small`"):
        label_surfaces(vol, on_small="ignore")


def test_many_labels_give_the_surfaces_of_one_label_at_a_time():
    """label_surfaces finds every label's box in one pass; each mesh is the one label_surface
    makes from the whole volume, vertex for vertex."""
    vol = _sphere_volume(*GEOMETRIES["identity"])
    array = vol.array.copy()
    array[array.shape[0] // 2:][array[array.shape[0] // 2:] == 7] = 2  # cut the ball into labels 7 and 2
    array[1:4, 2:6, 1:3] = 9  # and a small box near a corner
    vol = vol.with_array(array)
    many = label_surfaces(vol)
    assert list(many) == [2, 7, 9]
    for lab, surf in many.items():
        one = label_surface(vol, lab)
        np.testing.assert_array_equal(surf.vertices, one.vertices)
        np.testing.assert_array_equal(surf.cells, one.cells)
    assert label_surfaces(vol, [9, 2]).keys() == {9, 2}


def test_progress_callback_counts_labels():
    vol = _sphere_volume(*GEOMETRIES["identity"])
    calls = []
    label_surfaces(vol, progress=lambda stage, done, total: calls.append((stage, done, total)))
    assert calls == [("extract surfaces", 1, 1)]


@pytest.mark.parametrize("size_mm", [34, 120])
def test_implicit_on_grid_matches_pointwise_evaluation(size_mm):
    # 120 mm is wider than the surface's bounds: the voxels beyond them take the offset unevaluated.
    direction, spacing = rotation(30), np.array([2.0, 2.0, 2.5])
    shape = tuple(int(np.ceil(size_mm / s)) for s in spacing)
    origin = -direction @ ((np.array(shape) - 1) / 2 * spacing)
    vol = label_volume(shape, spacing, direction, origin, SPHERE.signed_distance, label=7)
    surf = label_surface(vol, 7)
    f = ImplicitSurface(surf.vertices, surf.normals, min_width=8.0)
    grid = implicit_on_grid(f, vol, chunk=1000)
    assert grid.shape == vol.shape and grid.dtype == np.float32
    np.testing.assert_array_equal(implicit_on_grid(f, vol.grid, chunk=1000), grid)  # the grid alone suffices
    direct = f(vol.grid_points().reshape(-1, 3)).reshape(vol.shape)
    np.testing.assert_allclose(grid, direct, rtol=1e-6, atol=1e-5)
    lo, hi = f.bounds()
    beyond = np.any((vol.grid_points() < lo) | (vol.grid_points() > hi), axis=-1)
    assert beyond.any() == (size_mm == 120)
    assert np.all(grid[beyond] == np.float32(f.offset))


@pytest.mark.parametrize("dim", [2, 3])
def test_vertex_normals_are_the_area_weighted_mean_of_the_cell_normals(dim):
    """Each vertex's normal is the normalised sum of its cells' area-weighted normals (a loop over
    the cells as the reference), unit length, and radial on a sphere's label surface."""
    from volreg.features.label_surfaces import _cell_normals, vertex_normals

    rng = np.random.default_rng(dim)
    vertices = rng.normal(size=(40, dim))
    cells = np.array([rng.choice(40, dim, replace=False) for _ in range(150)])
    expected = np.zeros_like(vertices)
    for cell, normal in zip(cells, _cell_normals(vertices, cells)):
        for v in cell:
            expected[v] += normal
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    normals = vertex_normals(vertices, cells)
    np.testing.assert_allclose(normals, expected, atol=1e-12)
    if dim == 3:
        surf = label_surface(label_volume((40,) * 3, (1, 1, 1), np.eye(3), (-19.5,) * 3,
                                          lambda p: np.linalg.norm(p, axis=1) - 12.0), 1)
        radial = surf.vertices / np.linalg.norm(surf.vertices, axis=1, keepdims=True)
        cosine = np.einsum("ni,ni->n", vertex_normals(surf.vertices, surf.cells), radial)
        assert cosine.min() > 0.9 and cosine.mean() > 0.99  # outward; within the mesh's facets of radial


@pytest.mark.parametrize("dim", [2, 3])
def test_edge_sampler_interpolates_as_map_coordinates(dim):
    from scipy import ndimage
    from skimage import measure

    from volreg.features.label_surfaces import _edge_sampler

    rng = np.random.default_rng(dim)
    field = ndimage.gaussian_filter(rng.random((24,) * dim).astype(np.float32), 1.5)
    level = float(np.median(field))
    if dim == 3:
        at = measure.marching_cubes(field, level=level)[0]  # some of Lewiner's vertices lie inside cubes
    else:
        at = np.concatenate(measure.find_contours(field, level))
    at = np.concatenate([at, [[0.5] + [0.0] * (dim - 1)]])  # on the array's edge: interpolated the general way
    sample = _edge_sampler(field, at)
    for offset in np.array(list(np.ndindex(*([3] * dim)))) - 1:
        ref = ndimage.map_coordinates(field, (at + offset).T, order=1, mode="nearest")
        np.testing.assert_array_equal(sample(offset.astype(float)), ref)


def test_surfaces_of_several_volumes_at_once_equal_each_volume_alone():
    """Both volumes' meshes made on the threads together, largest label box first: the same
    meshes as each volume's own, and per volume the labels without one, in the labels' order."""
    from volreg.features.label_surfaces import surfaces_of_volumes

    big = Ellipsoid((14, 11, 9), (0, 0, 0))
    small = Ellipsoid((4, 5, 3), (8, 6, 0))
    a = label_volume((40, 36, 30), (1.0, 1.0, 1.0), np.eye(3), (-20, -18, -15), big.signed_distance, label=2)
    arr = a.array.copy()
    grid = a.grid_points().reshape(-1, 3)
    arr[(small.signed_distance(grid) < 0).reshape(arr.shape)] = 5
    a = a.with_array(arr)
    b = label_volume((27, 24, 20), (1.5, 1.5, 1.5), rotation(20), (-19, -17, -14), big.signed_distance, label=2)
    found = surfaces_of_volumes([a, b], iter([5, 2, 9]), smoothing=[1.0, 0.7])  # an iterator, read once
    assert [sorted(m) for m, _ in found] == [[2, 5], [2]]
    assert [list(e) for _, e in found] == [[9], [5, 9]]  # labels in the order asked for
    assert all(isinstance(err, SurfaceError) for _, e in found for err in e.values())
    for (meshes, _), volume, s in zip(found, (a, b), (1.0, 0.7)):
        for lab, mesh in meshes.items():
            alone = label_surface(volume, lab, smoothing=s)
            np.testing.assert_array_equal(mesh.vertices, alone.vertices)
            np.testing.assert_array_equal(mesh.cells, alone.cells)
