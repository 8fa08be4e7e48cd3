"""Surface registration: the paper's Figure 2 (2-D) and known 3-D deformations.

Run:  .venv/bin/python benchmarks/bench_register.py

Prints a Markdown table: correspondence error against the known answer, the
distance of the warped source to the target surface, the smallest Jacobian
determinant, the samples of the finest level and the time.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

from shapes import bumpy_ellipsoid, label_volume  # noqa: E402
from volreg.features.implicit import ImplicitSurface  # noqa: E402
from volreg.settings import WarpSettings  # noqa: E402
from volreg.pipeline.surfaces import register_surfaces  # noqa: E402
from volreg.features.label_surfaces import label_surface, vertex_normals  # noqa: E402
from volreg.synthetic import GaussianBumps  # noqa: E402
from volreg.grid import LabelVolume  # noqa: E402


def figure2(alpha: float) -> str:
    def outline(shift):
        geom = LabelVolume(np.zeros((100, 100), np.uint8), (-49.5, -49.5), (1.0, 1.0), np.eye(2))
        x, y = geom.grid_points().reshape(-1, 2).T
        inside = ((np.abs(x) <= 20) & (np.abs(y) <= 20)) | (
            (x >= 20) & (x <= 30) & (np.abs(y - shift) <= 8 * (30 - x) / 10))
        s = label_surface(geom.with_array(inside.reshape(100, 100).astype(np.uint8)), 1)
        return ImplicitSurface(s.vertices, s.normals, min_width=4.0)

    f1, f2 = outline(0.0), outline(8.0)
    t0 = time.perf_counter()
    res = register_surfaces(f1, f2, settings=WarpSettings(alpha=alpha))
    dt = time.perf_counter() - t0
    probe = np.array([[25.0, 4.0], [25.0, -4.0], [30.0, 0.0]])
    err = np.linalg.norm(res.warp(probe) - (probe + [0.0, 8.0]), axis=1)
    pts = np.random.default_rng(0).uniform([-35, -35], [40, 35], (20000, 2))
    det = np.linalg.det(res.warp.jacobian(pts)).min()
    surf = np.abs(f2(res.warp(f1.points))).mean()
    return (f"| Figure 2 (2-D), alpha = {alpha:g} mm^2 | sides {err[0]:.2f} / {err[1]:.2f}, tip {err[2]:.2f} mm "
            f"| {surf:.3f} | {det:.2f} | {res.log[-1]['samples']} | {dt:.1f} |")


def blob(bumps: int, alpha: float, seed: int | None = None, **settings) -> str:
    """An ellipsoid with 0, 2, 4 or 8 bumps under a known warp: the near-linear shear
    below (``seed`` None) or 6 random Gaussian bumps of 15 mm (``seed``), max |u| = 15 % of
    the diameter over the box.  ``settings``: further `WarpSettings` (e.g. a wider ``pad``)."""
    sdf = bumpy_ellipsoid(bumps)
    vol = label_volume((60,) * 3, (1, 1, 1), np.eye(3), (-29.5,) * 3, sdf)
    s = label_surface(vol, 1)
    diameter = float(np.linalg.norm(s.vertices.max(0) - s.vertices.min(0)))

    def phi(x):  # odd in every coordinate: no net translation; max |u| = 0.15 diameter
        u = np.stack([np.sin(x[:, 1] / 15), 0.8 * np.sin(x[:, 2] / 15), 0.8 * np.sin(x[:, 0] / 15)], 1)
        return x + 0.15 * diameter * u

    if seed is not None:
        phi = GaussianBumps.random((-30,) * 3, (30,) * 3, max_displacement=0.15 * diameter, scale=15.0,
                                   count=6, rng=np.random.default_rng(seed))
    v2 = phi(s.vertices)
    f1 = ImplicitSurface(s.vertices, s.normals, min_width=4.0)
    f2 = ImplicitSurface(v2, vertex_normals(v2, s.cells), min_width=4.0)
    t0 = time.perf_counter()
    res = register_surfaces(f1, f2, settings=WarpSettings(alpha=alpha, **settings))
    dt = time.perf_counter() - t0
    err = np.linalg.norm(res.warp(s.vertices) - v2, axis=1)
    centres = np.concatenate([lev.centres for lev in res.warp.levels])
    det = np.linalg.det(res.warp.jacobian(centres)).min()
    surf = np.abs(f2(res.warp(s.vertices))).mean()
    name = f"ellipsoid + {bumps} bumps" if bumps else "ellipsoid"
    name += ", shear" if seed is None else f", Gaussian bumps (seed {seed})"
    if settings:
        name += ", " + ", ".join(f"{k} = {v:g}" for k, v in settings.items())
    return (f"| 3-D {name}, known deformation (max {np.linalg.norm(v2 - s.vertices, axis=1).max():.1f} mm, "
            f"diameter {diameter:.1f} mm), alpha = {alpha:g} | mean {err.mean():.2f} mm "
            f"({100 * err.mean() / diameter:.2f} % of diameter) | {surf:.3f} | {det:.2f} "
            f"| {res.log[-1]['samples']} | {dt:.1f} |")


def main() -> None:
    print("| case | correspondence error | mean distance to target surface (mm) | min det J "
          "| finest-level samples | seconds |\n|---|---|---|---|---|---|")
    for alpha in (0.0, 10.0):
        print(figure2(alpha), flush=True)
    for bumps in (0, 2):
        for alpha in (0.0, 10.0):
            print(blob(bumps, alpha), flush=True)
    for bumps in (0, 4, 8):
        for seed in range(4):
            print(blob(bumps, 10.0, seed), flush=True)
    # A wider warp volume (pad 15 mm, 24-28 % of the diameter; samples twice as coarse to pay for it):
    # the setting of the 1 % acceptance test in tests/test_known_deformation.py.
    for bumps in (0, 4, 8):
        for seed in range(4):
            print(blob(bumps, 10.0, seed, pad=15.0, sample_scale=2.0), flush=True)


if __name__ == "__main__":
    main()
