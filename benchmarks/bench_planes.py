"""Voxel distance maps of planes at two resolutions: what a coarse grid's staircase leaves in the map.

Run:  .venv/bin/python benchmarks/bench_planes.py [--planes 16] [--seed 7]

A half-space of random orientation and offset is labelled at voxel centres on a 1 mm grid and on
a 2 mm grid (the 2 mm centres are every second 1 mm centre), and each mask becomes the voxel
distance map a registration uses (`volreg.features.distance_maps.VoxelDistance`: read through a
Gaussian of `scale`, then blurred by `smoothing`, cubic B-spline), clipped far enough (8 mm) that
the clip does not reach the points scored. At random points within 3 mm of the plane: the mean
|f - D| against the exact signed distance D, and the mean |f_2mm - f_1mm| between the two maps
(what a registration of the two grids with no motion sees as a difference), averaged over the
planes, with the worst plane's |f - D|. Rows: the 1 mm map and the 2 mm map with the settings a
registration of a 1 mm and a 2 mm volume uses (`distance_scale` 1 and `distance_smoothing` 0.8
coarse voxels: 2 mm and 1.6 mm), then wider Gaussians.

Output: Markdown on stdout.
"""

from __future__ import annotations

import argparse

import numpy as np

from volreg.features.distance_maps import VoxelDistance

#: (spacing, scale, smoothing) in mm, one row each.
ROWS = ((1.0, 2.0, 1.6), (2.0, 2.0, 1.6), (2.0, 3.0, 1.6), (2.0, 4.0, 1.6), (2.0, 5.0, 2.0))


def plane_map(h: float, normal: np.ndarray, offset: float, scale: float, smoothing: float,
              size: float = 44.0) -> VoxelDistance:
    """The distance map of the half-space ``x . normal < offset`` labelled on a cube of ``size`` mm
    with voxels of ``h`` mm (origin 0)."""
    k = int(size / h)
    centres = np.indices((k, k, k)).reshape(3, -1).T * h
    mask = (centres @ normal < offset).reshape(k, k, k)
    return VoxelDistance(mask, np.full(3, h), np.zeros(3), np.eye(3), clip=8.0, smoothing=smoothing, scale=scale)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--planes", type=int, default=16)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    scores: dict[tuple, list] = {row: [] for row in ROWS}
    for _ in range(args.planes):
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        offset = 22.0 * normal.sum() + rng.uniform(0.0, 2.0)
        x = 22.0 + rng.uniform(-6.0, 6.0, (6000, 3))
        d = x @ normal - offset
        x, d = x[np.abs(d) < 3.0], d[np.abs(d) < 3.0]
        for h, scale, smoothing in ROWS:
            fine = plane_map(1.0, normal, offset, scale, smoothing).evaluate(x)[0]
            f = plane_map(h, normal, offset, scale, smoothing).evaluate(x)[0]
            scores[(h, scale, smoothing)].append((np.mean(np.abs(f - d)), np.mean(np.abs(f - fine))))
    print(f"{args.planes} planes (seed {args.seed}), points within 3 mm of each\n")
    print("| grid (mm) | Gaussian scale, blur after (mm) | mean abs(f - D) (mm) | worst plane | "
          "mean abs(f - f at 1 mm) (mm) |")
    print("|---|---|---|---|---|")
    for (h, scale, smoothing), rows in scores.items():
        v = np.array(rows)
        print(f"| {h:g} | {scale:g}, {smoothing:g} | {v[:, 0].mean():.3f} | {v[:, 0].max():.3f} | {v[:, 1].mean():.3f} |")


if __name__ == "__main__":
    main()
