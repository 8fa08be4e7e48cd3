"""Surfaces checked before they are fitted, from Python as on the command line."""

from __future__ import annotations

import numpy as np
import pytest

import volreg
from volreg.errors import SurfaceError
from volreg.pipeline.surface_inputs import MAX_SIZE_RATIO, check_point_extent, check_size_ratio


def _sphere(radius: float, n: int = 200, rng=None) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points on a sphere of ``radius`` mm and their outward normals."""
    rng = np.random.default_rng(0) if rng is None else rng
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return radius * normals, normals


@pytest.mark.parametrize("points, message", [
    (np.zeros((20, 3)), "at one point"),
    (np.outer(np.linspace(0, 10, 20), [1.0, 2.0, 3.0]), "on a line"),
    (np.c_[np.random.default_rng(1).uniform(-5, 5, (40, 2)), np.zeros(40)], "point cloud lying in a plane"),
])
def test_register_surfaces_refuses_points_that_bound_no_volume(points, message):
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    with pytest.raises(SurfaceError, match=message):
        volreg.register_surfaces((points, normals), _sphere(10.0))
    with pytest.raises(SurfaceError, match=message):  # the target as well
        volreg.register_surfaces(_sphere(10.0), (points, normals))


def test_a_planar_mesh_is_a_surface_but_a_planar_cloud_is_not():
    plane = np.c_[np.random.default_rng(2).uniform(-5, 5, (40, 2)), np.zeros(40)]
    check_point_extent(plane, "a sheet", cloud=False)
    with pytest.raises(SurfaceError, match="a sheet is a point cloud lying in a plane"):
        check_point_extent(plane, "a sheet", cloud=True)


def test_register_surfaces_refuses_surfaces_in_two_units():
    """A sphere 20 mm across against one 20 m across (metres read as millimetres by a factor 1000)."""
    with pytest.raises(SurfaceError, match=r"`source` is 3\d\.\d+ mm across .* expected two surfaces in one unit"):
        volreg.register_surfaces(_sphere(10.0), _sphere(10_000.0))
    small, large = _sphere(10.0)[0], _sphere(10.0 * MAX_SIZE_RATIO * 0.99)[0]
    check_size_ratio(small, large)  # within the ratio: accepted
    with pytest.raises(SurfaceError, match="times the size"):
        check_size_ratio(small, 1.02 * MAX_SIZE_RATIO * small)


def test_the_command_refuses_what_the_library_refuses(tmp_path, capsys):
    """The same check and message on both paths: a point cloud in a plane as SOURCE."""
    from volreg.cli import main

    plane = np.c_[np.random.default_rng(3).uniform(-5, 5, (40, 2)), np.zeros(40)]
    none = np.zeros((0, 3), int)
    volreg.write_mesh(plane, none, tmp_path / "plane.vtk", allow_points=True)
    volreg.write_mesh(_sphere(6.0)[0], none, tmp_path / "sphere.vtk", allow_points=True)
    status = main(["register-surfaces", str(tmp_path / "plane.vtk"), str(tmp_path / "sphere.vtk"), "-o",
                   str(tmp_path / "out"), "--quiet"])
    assert status == 2
    err = capsys.readouterr().err
    assert "is a point cloud lying in a plane" in err and not (tmp_path / "out").exists()
