"""``volreg register-surfaces``, ``morph`` and ``transfer`` end to end on pyvista spheres."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import pyvista as pv

from volreg.cli import main
from volreg.io.meshes import read_surface, write_gifti
from volreg.synthetic import GaussianBumps
from volreg.warp.model import KernelWarp

DIAMETER = 40.0
PROTOCOL = "[protocol]\nname = \"surface-test\"\n[warp]\nmin_width = 8.0\n"
#: A smooth deformation with normal and tangential parts, up to ~3 mm (7.5 % of the diameter).
TRUTH = GaussianBumps(np.array([[15.0, 0, 10], [-10, 10, -5]]), np.array([[3.0, 0.0, 1.0], [-1.0, 2.0, 0.0]]), 12.0)


def run(args) -> int:
    return main([str(a) for a in args])


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("surfaces")
    src = pv.Sphere(radius=DIAMETER / 2, theta_resolution=40, phi_resolution=40)
    src.point_data["height"] = np.array(src.points[:, 2])
    src.point_data["side"] = (np.array(src.points[:, 0]) > 0).astype(np.int32) * 7 + 3  # labels {3, 10}
    tgt = src.copy()
    tgt.points = TRUTH(np.array(src.points))
    src.save(d / "src.vtk")
    tgt.save(d / "tgt.vtk")
    (d / "p.toml").write_text(PROTOCOL)
    assert run(["register-surfaces", d / "src.vtk", d / "tgt.vtk", "-o", d / "out", "--protocol", d / "p.toml", "--quiet"]) == 0
    return d, np.array(src.points), np.asarray(src.faces).reshape(-1, 4)[:, 1:]


def test_known_deformation_recovered(pair):
    """Mean vertex error against the known partner <= 1 % of the diameter (measured 0.92 %; identity 2.3 %)."""
    d, v, _ = pair
    warp = KernelWarp.load(d / "out" / "model.npz")
    err = np.linalg.norm(warp(v) - TRUTH(v), axis=1)
    moved = np.linalg.norm(TRUTH(v) - v, axis=1)
    assert err.mean() <= 0.01 * DIAMETER
    assert err.mean() < 0.5 * moved.mean()


def test_outputs(pair):
    d, v, faces = pair
    assert sorted(p.name for p in (d / "out").iterdir()) == ["correspondence.csv", "model.npz", "report.json", "warped.vtk"]
    warped = read_surface(d / "out" / "warped.vtk")
    warp = KernelWarp.load(d / "out" / "model.npz")
    assert np.allclose(warped.vertices, warp(v), atol=1e-4) and np.array_equal(warped.triangles, faces)
    assert set(warped.arrays) >= {"height", "side"}
    rows = list(csv.DictReader((d / "out" / "correspondence.csv").read_text().splitlines()))
    assert len(rows) == len(v) and float(rows[5]["tau_x"]) == pytest.approx(warp(v[5:6])[0, 0], abs=1e-3)
    report = json.loads((d / "out" / "report.json").read_text())
    assert report["distance_to_target_mm"]["mean"] < 0.2 and report["folded_fraction_at_vertices"] == 0.0
    assert report["target_diameter_mm"] == pytest.approx(np.linalg.norm(np.ptp(TRUTH(v), axis=0)), rel=1e-6)


def test_a_shifted_target_is_reached_through_the_centroids(pair, tmp_path):
    """The target moved 12 mm (30 % of the diameter) on top of the known warp: the warp starts
    from the centroids' translation (report.json `translation_mm`) and finds the known partners
    as without the shift, within 1 % of the diameter. A cap cut from the source, lying in place
    on the target, is not moved to the target's centroid (one surface a part of the other)."""
    d, v, faces = pair
    shift = np.array([12.0, 0.0, 0.0])
    tgt = pv.read(d / "tgt.vtk")
    tgt.points = np.array(tgt.points) + shift
    tgt.save(tmp_path / "shifted.vtk")
    assert run(["register-surfaces", d / "src.vtk", tmp_path / "shifted.vtk", "-o", tmp_path / "out", "--protocol",
                d / "p.toml", "--quiet"]) == 0
    warp = KernelWarp.load(tmp_path / "out" / "model.npz")
    err = np.linalg.norm(warp(v) - (TRUTH(v) + shift), axis=1)
    assert err.mean() <= 0.01 * DIAMETER, err.mean()
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["translation_mm"] == pytest.approx(list(warp.linear.translation))
    assert abs(report["translation_mm"][0] - 12.0) < 1.5
    cap = pv.read(d / "src.vtk").clip(normal="z", origin=(0.0, 0.0, 8.0), invert=False)  # z >= 8 mm
    assert 0 < cap.n_points < 0.5 * len(v)
    cap.save(tmp_path / "cap.vtk")
    assert run(["register-surfaces", tmp_path / "cap.vtk", d / "tgt.vtk", "-o", tmp_path / "cap_out", "--protocol",
                d / "p.toml", "--quiet"]) == 0
    assert json.loads((tmp_path / "cap_out" / "report.json").read_text())["translation_mm"] == [0.0, 0.0, 0.0]

def test_landmarks_are_hit(pair, tmp_path):
    """With landmarks (lambda_p = 1e6) the training landmarks land within 0.05 % of the diameter."""
    d, v, _ = pair
    idx = [0, 100, 400, 800, 1200]
    np.savetxt(tmp_path / "s.csv", v[idx], delimiter=",", header="x,y,z", comments="")
    np.savetxt(tmp_path / "t.csv", TRUTH(v[idx]), delimiter=",", header="x,y,z", comments="")
    (tmp_path / "p.toml").write_text(PROTOCOL + "lambda_p = 1e6\n")
    assert run(["register-surfaces", d / "src.vtk", d / "tgt.vtk", "-o", tmp_path / "out", "--protocol", tmp_path / "p.toml",
                "--landmarks", tmp_path / "s.csv", tmp_path / "t.csv", "--quiet"]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["landmark_error"]["mean_percent_of_diameter"] <= 0.05


def test_point_cloud_without_normals(pair, tmp_path):
    d, v, _ = pair
    pv.PolyData(v.copy()).save(tmp_path / "cloud.vtk")  # the vertices alone: normals are estimated (PCA)
    assert read_surface(tmp_path / "cloud.vtk").normals is None and len(read_surface(tmp_path / "cloud.vtk").triangles) == 0
    assert run(["register-surfaces", tmp_path / "cloud.vtk", d / "tgt.vtk", "-o", tmp_path / "out", "--protocol", d / "p.toml",
                "--quiet"]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["distance_to_target_mm"]["mean"] < 0.2  # measured 0.052 mm
    warp = KernelWarp.load(tmp_path / "out" / "model.npz")
    assert np.linalg.norm(warp(v) - TRUTH(v), axis=1).mean() <= 0.01 * DIAMETER  # measured 0.92 %


def test_morph_first_and_last_frames(pair, tmp_path):
    d, v, _ = pair
    assert run(["morph", d / "src.vtk", d / "tgt.vtk", "-o", tmp_path / "m", "--frames", "4", "--from-result", d / "out",
                "--quiet"]) == 0
    names = sorted(p.name for p in (tmp_path / "m").iterdir())
    assert names == sorted([f"frame_{k:03d}.{e}" for k in range(4) for e in ("vtk", "png")] + ["morph.gif"])
    first, last = read_surface(tmp_path / "m" / "frame_000.vtk"), read_surface(tmp_path / "m" / "frame_003.vtk")
    warped = read_surface(d / "out" / "warped.vtk")
    assert np.allclose(first.vertices, v, atol=1e-5) and np.allclose(last.vertices, warped.vertices, atol=1e-5)
    # both surfaces carry "height": the first frame has the source's, the last the target's through the correspondence
    assert np.allclose(first.arrays["height"], v[:, 2], atol=1e-4)
    assert (tmp_path / "m" / "morph.gif").read_bytes()[:6] == b"GIF89a"


def test_transfer_constant_and_labels(pair, tmp_path):
    d, v, _ = pair
    tgt = pv.read(d / "tgt.vtk")
    tgt.point_data["const"] = np.full(tgt.n_points, 2.5)
    tgt.save(tmp_path / "tgt.vtk")
    for method in ("nearest", "barycentric"):
        out = tmp_path / f"{method}.vtk"
        assert run(["transfer", d / "src.vtk", tmp_path / "tgt.vtk", "--result", d / "out", "--array", "const", "-o", out,
                    "--method", method]) == 0
        assert np.all(read_surface(out).arrays["const"] == 2.5)
        assert run(["transfer", d / "src.vtk", tmp_path / "tgt.vtk", "--result", d / "out", "--array", "side", "-o",
                    tmp_path / f"side-{method}.vtk", "--method", method]) == 0
        side = read_surface(tmp_path / f"side-{method}.vtk").arrays["side"]
        assert set(np.unique(side).tolist()) == {3, 10} and side.dtype.kind == "i"
        assert np.mean(side == np.where(v[:, 0] > 0, 10, 3)) > 0.97  # the correspondence keeps sides


def test_gifti_round_trip(pair, tmp_path):
    _, v, faces = pair
    write_gifti(v, faces, tmp_path / "s.surf.gii")
    back = read_surface(tmp_path / "s.surf.gii")
    assert np.allclose(back.vertices, v, atol=1e-4) and np.array_equal(back.triangles, faces)


def test_bad_inputs(pair, tmp_path, capsys):
    d, v, _ = pair
    pv.PolyData().save(tmp_path / "empty.vtk")
    nan = pv.Sphere()
    pts = np.array(nan.points)
    pts[0] = np.nan
    nan.points = pts
    nan.save(tmp_path / "nan.vtk")
    np.savetxt(tmp_path / "a.csv", v[:3], delimiter=",", header="x,y,z", comments="")
    np.savetxt(tmp_path / "b.csv", v[:2], delimiter=",", header="x,y,z", comments="")

    def refused(args, *words):
        out = tmp_path / "out"
        assert run(args + ["-o", out]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "error:" in err and all(w in err for w in words), err
        assert not out.exists()

    refused(["register-surfaces", tmp_path / "empty.vtk", d / "tgt.vtk"], "empty.vtk", "empty")
    refused(["register-surfaces", tmp_path / "nan.vtk", d / "tgt.vtk"], "nan.vtk", "NaN")
    refused(["register-surfaces", d / "src.vtk", d / "tgt.vtk", "--landmarks", tmp_path / "a.csv", tmp_path / "b.csv"],
            "same number")
    refused(["morph", d / "src.vtk", d / "tgt.vtk", "--frames", "1"], "--frames")
    refused(["transfer", d / "src.vtk", d / "tgt.vtk", "--result", d / "out", "--array", "nope"], "nope", "height")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep").write_text("k")
    assert run(["register-surfaces", d / "src.vtk", d / "tgt.vtk", "-o", tmp_path / "full"]) == 2
    assert [p.name for p in (tmp_path / "full").iterdir()] == ["keep"]


def test_non_manifold_mesh_is_reported(pair, tmp_path, capsys):
    """Three triangles on one edge: read with a one-line warning (the registration still runs)."""
    import warnings

    from volreg.io import VolregWarning

    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    fan = pv.PolyData(pts, faces=np.array([3, 0, 1, 2, 3, 0, 1, 3, 3, 0, 1, 4]))
    fan.save(tmp_path / "fan.vtk")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_surface(tmp_path / "fan.vtk")
    assert [w.category for w in caught] == [VolregWarning] and "1 non-manifold edges" in str(caught[0].message)
    assert run(["transfer", tmp_path / "fan.vtk", pair[0] / "tgt.vtk", "--result", pair[0] / "out", "--array", "height",
                "-o", tmp_path / "t.vtk"]) == 2  # too few vertices to be a surface: refused after the warning
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("volreg transfer: warning: ") and "non-manifold" in err[0]


def test_a_partial_target_is_named_though_the_median_distance_is_small(pair, tmp_path, capsys):
    """The target is the cap z >= -4 mm of the warped sphere (about 60 % of it): the source's other
    part has no counterpart and is squeezed towards the cut, far from the target (16 % of its
    vertices beyond 5 % of the diameter), while the median distance over all vertices stays
    small (0.14 mm).  The 90th percentile names it."""
    d, v, _ = pair
    cap = pv.read(d / "tgt.vtk").clip(normal="z", origin=(0.0, 0.0, -4.0), invert=False)
    cap.save(tmp_path / "cap.vtk")
    assert run(["register-surfaces", d / "src.vtk", tmp_path / "cap.vtk", "-o", tmp_path / "out", "--protocol",
                d / "p.toml", "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no counterpart in TARGET (a partial surface)" in err[0], err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert [f["figure"] for f in report["review"]["findings"]] == ["p90_distance_fraction"]
    assert report["distance_to_target_mm"]["median"] < 0.05 * report["target_diameter_mm"]


def test_the_centroids_weigh_points_by_the_surface_they_stand_for():
    """A sphere meshed four times as densely on one half: its vertices' mean lies 4 mm off the
    centre (radius 20 mm), the area-weighted centroid within 0.6 mm; 50 points of debris 300 mm
    away move the plain mean 4 mm, the weighted one under 1 mm."""
    from volreg.pipeline.surfaces import _area_centroid

    sphere = pv.Sphere(radius=20.0, theta_resolution=60, phi_resolution=60)
    points = np.array(sphere.points, float)
    dense = np.array(pv.Sphere(radius=20.0, theta_resolution=120, phi_resolution=120).points, float)
    mixed = np.concatenate([points[points[:, 0] < 0], dense[dense[:, 0] >= 0]])
    assert np.linalg.norm(mixed.mean(axis=0)) > 3.0
    assert np.linalg.norm(_area_centroid(mixed)) < 0.6, _area_centroid(mixed)
    debris = np.array([300.0, 0.0, 0.0]) + np.random.default_rng(0).normal(scale=0.5, size=(50, 3))
    with_debris = np.concatenate([points, debris])
    assert np.linalg.norm(with_debris.mean(axis=0)) > 4.0
    assert np.linalg.norm(_area_centroid(with_debris)) < 1.0, _area_centroid(with_debris)
    # a one-voxel speck (marching cubes' octahedron) 70 mm away, and the surface's points repeated
    speck = np.array([70.0, 0.0, 0.0]) + 0.5 * np.vstack([np.eye(3), -np.eye(3)])
    assert np.linalg.norm(_area_centroid(np.concatenate([points, speck]))) < 1.0  # 21.5 mm uncapped
    assert np.linalg.norm(_area_centroid(np.concatenate([points] + [points[points[:, 0] > 0]] * 7))) < 0.6


def test_morph_that_registers_runs_the_checks_of_register_surfaces(pair, tmp_path, capsys):
    """The target moved 50 mm, 72 % of the source's diameter (its bounding-box diagonal), as a
    surface mirrored between RAS and LPS moves: register-surfaces warns of the translation, and so
    does morph registering the pair itself (it used to check only a result given with
    --from-result)."""
    d, _, _ = pair
    far = pv.read(d / "tgt.vtk")
    far.points = np.array(far.points) + [50.0, 0.0, 0.0]
    far.save(tmp_path / "far.vtk")
    assert run(["morph", d / "src.vtk", tmp_path / "far.vtk", "-o", tmp_path / "m", "--frames", "2", "--protocol",
                d / "p.toml", "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("volreg morph: warning: ") and "centroids' translation" in err[0], err


@pytest.mark.system
def test_landmarks_in_another_order_are_named(pair, tmp_path, capsys):
    d, v, _ = pair
    idx = [0, 100, 400, 800, 1200]
    np.savetxt(tmp_path / "s.csv", v[idx], delimiter=",", header="x,y,z", comments="")
    np.savetxt(tmp_path / "t.csv", TRUTH(v[idx[::-1]]), delimiter=",", header="x,y,z", comments="")
    assert run(["register-surfaces", d / "src.vtk", d / "tgt.vtk", "-o", tmp_path / "out", "--protocol",
                d / "p.toml", "--landmarks", tmp_path / "s.csv", tmp_path / "t.csv", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "landmark files probably list their points in another order" in err, err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert "landmark_fraction" in [f["figure"] for f in report["review"]["findings"]]


def _fibonacci_sphere(n: int, radius: float) -> np.ndarray:
    """``n`` points spread evenly over a sphere of ``radius`` mm about the origin, (n, 3)."""
    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    return radius * np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1)


def test_gaps_to_a_point_cloud_allow_for_the_spacing_of_its_points():
    """The vertices of a sphere 40 mm across lie a median 4.5 mm from the nearest of 40 points of the
    same sphere (6.7 % of their diameter, over the 5 % limit); less half the points' spacing, a
    median 0 and a 90th percentile of 1.6 %.  Listing each point twice changes nothing; half the
    points leave the other half of the sphere far (90th percentile 30 %); a sphere of twice the
    radius is off by 10 mm."""
    from volreg.evaluation.surface_review import diameter, review_surface_distance
    from volreg.morph import closest_points, surface_gaps

    sphere = pv.Sphere(radius=20.0, theta_resolution=40, phi_resolution=40)
    vertices, triangles = np.array(sphere.points, float), np.asarray(sphere.faces).reshape(-1, 4)[:, 1:]
    cloud, none = _fibonacci_sphere(40, 20.0), np.zeros((0, 3), int)
    size = diameter(cloud)
    assert np.median(closest_points(vertices, cloud, none)[1]) > 0.06 * size  # what the nearest point gave
    gaps, measured = surface_gaps(vertices, cloud, none)
    assert measured == "source_to_target_points" and gaps.shape == (len(vertices),)
    assert np.median(gaps) == 0.0 and np.percentile(gaps, 90) < 0.02 * size, np.percentile(gaps, 90)
    assert review_surface_distance(gaps, size, measured=measured) == []
    assert np.array_equal(surface_gaps(vertices, np.concatenate([cloud, cloud[::-1]]), none)[0], gaps)
    half, _ = surface_gaps(vertices, cloud[cloud[:, 2] > 0], none)
    findings = review_surface_distance(half, size, measured=measured)
    assert [f.figure for f in findings] == ["p90_distance_fraction"] and findings[0].value > 0.25, findings
    assert "from TARGET's points (beyond half their spacing)" in findings[0].message
    far, _ = surface_gaps(vertices, _fibonacci_sphere(40, 40.0), none)
    assert 9.0 < np.median(far) < 12.0, np.median(far)
    gaps, measured = surface_gaps(vertices, vertices, triangles)  # a mesh: to its triangles
    assert measured == "source_to_target" and gaps.max() < 1e-6


def test_a_sparse_point_cloud_target_is_not_taken_for_another_frame(pair, tmp_path, capsys):
    """40 points of the warped sphere as TARGET: the warped source lies on their surface, but a
    median 4.5 mm (7 % of the diameter) from the nearest of them, which was warned about as
    surfaces in different frames.  Beyond half the points' spacing it is under 1 mm, and the
    target moved 50 mm (as a surface read in another frame) is still named."""
    d, _, _ = pair
    pv.PolyData(TRUTH(_fibonacci_sphere(40, DIAMETER / 2))).save(tmp_path / "cloud.vtk")
    assert run(["register-surfaces", d / "src.vtk", tmp_path / "cloud.vtk", "-o", tmp_path / "out", "--protocol",
                d / "p.toml", "--quiet"]) == 0
    assert capsys.readouterr().err == ""
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["review"]["plausible"] and report["distance_to_target_mm"]["median"] < 1.0, report
    assert report["distance_to_target_mm"]["measured"] == "source_to_target_points"
    pv.PolyData(TRUTH(_fibonacci_sphere(40, DIAMETER / 2)) + [0.0, 50.0, 0.0]).save(tmp_path / "moved.vtk")
    assert run(["morph", d / "src.vtk", tmp_path / "moved.vtk", "-o", tmp_path / "m", "--frames", "2", "--protocol",
                d / "p.toml", "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "centroids' translation" in err[0], err
    # transfer from a cloud of the target's upper half: the lower half of SOURCE has no counterpart
    points = np.array(pv.read(d / "tgt.vtk").points)
    half = pv.PolyData(points[points[:, 2] > 0])
    half.point_data["height"] = points[points[:, 2] > 0, 2]
    half.save(tmp_path / "half.vtk")
    assert run(["transfer", d / "src.vtk", tmp_path / "half.vtk", "--result", d / "out", "--array", "height", "-o",
                tmp_path / "t.vtk"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "part of SOURCE has no counterpart in TARGET" in err[0], err
