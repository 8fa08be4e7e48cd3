"""Tangential sliding on smooth surfaces: correspondence error on known warps, remeshed targets.

Run:  python benchmarks/bench_sliding.py [--seeds 0,1,2,3] [--shapes 0,4,8,ant,cortex] [--shear]
      [--settings '{"alpha": 3}'] [--pre none|translation|affine] [--affine-penalty 0.014]
      [--methods volreg,moments,pycpd] [--cpd-points 2000] [--min-width MM] [--diagnose]

Pairs (``--shapes``): the ellipsoid of `tests/shapes.py` (semi-axes 20 / 14 / 10 mm) with 0, 4 or 8 bumps,
labelled on a 1 mm grid; the target is the same solid moved by a known smooth warp and labelled
again on another 1 mm grid (offset by a fraction of a voxel), so its marching-cubes vertices do
not coincide with the source's images.  Warps: 6 random Gaussian bumps of 15 mm scaled to a
maximum displacement of 15 % of the diameter (`GaussianBumps.random`, one per seed), and a
near-linear shear (``--shear``: u = 0.15 d (sin(y/15), 0.8 sin(z/15), 0.8 sin(x/15)), d the
diameter).  ``ant``: pyvista's ant and its image under 6 Gaussian bumps of up to 5 % of the
diameter, the two meshes decimated separately (:func:`_ant_pair`).  ``cortex``: a folded,
cortex-like blob (110 mm across, sulci 7 mm apart) at 10k vertices against its image under 6
Gaussian bumps of up to 5 % of the diameter at 12k (:func:`_cortex_pair`).  Every method sees the
two surfaces (vertices and normals), never the correspondence.

Reported per pair: mean |tau(v) - truth(v)| over the source vertices as % of the diameter, the
identity's, the mean distance of tau(v) to the target surface (mm, through the target's implicit
surface), and the seconds of the method (volreg's with both implicit-surface fits).

Methods:
- ``volreg``: `register_surfaces`' kernel warp on the two implicit surfaces (minimum width 4 mm; the
  ant and the cortex as `register_surfaces` fits meshes, `mesh_min_width`; ``--min-width`` sets it
  for both),
  with ``--settings`` as further `WarpSettings`.  ``--pre`` first fits a linear map of the target
  by the same locational cost (least squares over the finest level's samples): ``translation``,
  or ``affine`` with ``--affine-penalty`` x (d/2)^2 x |A - I|^2 per sample (d the diameter);
  the kernel warp then works on the target seen through it.  ``--coarse-features K:W`` adds a
  further feature pair (paper eq. 6): both implicit surfaces summed over their K coarsest levels
  only, with weight W.  ``--landmarks N`` gives N random source vertices with their true images.
- ``moments``: a map that uses only the shapes, not the correspondence: the affine map taking the
  source vertices' centroid and covariance to the target's (symmetric square roots).  It is not a
  registration method; it shows how far from the truth a map that puts the source onto the target
  can be (its distance to the target surface is printed too).
- ``pycpd``: non-rigid coherent point drift (beta = 2, lambda = 2 in tenths of the diameter, at
  most 100 iterations) on ``--cpd-points`` random source and target vertices; its error is
  measured on those source vertices.  ``probreg-cpd``: probreg's non-rigid CPD, the same
  parameters; ``probreg-bcpd``: probreg's Bayesian CPD (rigid and non-rigid together; lambda 2,
  its default kernel, at most 50 iterations); both on the same vertices (need ``pip install
  probreg``, whose open3d needs libusb-1.0-0 on Debian).

``--diagnose`` also prints, for volreg, the locational cost's terms at the fitted warp and at the
true map (see :func:`diagnose`): where the truth costs more than the fitted warp, the cost itself
prefers the sliding answer, and no optimiser can recover the truth from it.  And two properties of
each map over the warp volume's samples: its bending energy (mean squared second derivative) and
its mean displacement.

``--regulariser-power P`` (a candidate measured, not in the library): each level's regulariser
(10) weighted by ``(W / w)^P`` (w the level's kernel width, W the coarsest's; ``P:REF`` sets W to
REF mm instead), so that finer levels cost more for the same coefficients.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

from shapes import bumpy_ellipsoid_parts, decimated_surface, folded_blob_inside  # noqa: E402
from volreg.features.implicit import ImplicitSurface  # noqa: E402
from volreg.pipeline.surfaces import mesh_min_width  # noqa: E402
from volreg.features.label_surfaces import label_surface  # noqa: E402
from volreg.grid import LabelVolume  # noqa: E402
from volreg.settings import WarpSettings  # noqa: E402
from volreg.synthetic import GaussianBumps  # noqa: E402


class Shear:
    """The near-linear shear ``x + 0.15 d (sin(y/15), 0.8 sin(z/15), 0.8 sin(x/15))`` (mm)."""

    def __init__(self, diameter: float) -> None:
        self.amplitude = 0.15 * diameter

    def displacement(self, x: np.ndarray) -> np.ndarray:
        return self.amplitude * np.stack([np.sin(x[:, 1] / 15), 0.8 * np.sin(x[:, 2] / 15),
                                          0.8 * np.sin(x[:, 0] / 15)], axis=1)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return x + self.displacement(x)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        jac = np.broadcast_to(np.eye(3), (len(x), 3, 3)).copy()
        jac[:, 0, 1] += self.amplitude * np.cos(x[:, 1] / 15) / 15
        jac[:, 1, 2] += 0.8 * self.amplitude * np.cos(x[:, 2] / 15) / 15
        jac[:, 2, 0] += 0.8 * self.amplitude * np.cos(x[:, 0] / 15) / 15
        return jac

    def inverse(self, y: np.ndarray, iterations: int = 200) -> np.ndarray:
        x = y.copy()
        for _ in range(iterations):  # a contraction: max |grad u| = 0.53 here
            x = y - self.displacement(x)
        return x


def _inside(bumps: int):
    """Inside test of `bumpy_ellipsoid(bumps)` (the sign of its distance, without the distance)."""
    parts = bumpy_ellipsoid_parts(bumps)

    def inside(p: np.ndarray) -> np.ndarray:
        return np.any([np.sum(((p - e.centre) / e.axes) ** 2, axis=1) < 1.0 for e in parts], axis=0)

    return inside


def _surface(shape, origin, inside, spacing: float = 1.0):
    geom = LabelVolume(np.zeros(shape, np.uint8), origin, (spacing,) * 3, np.eye(3))
    mask = inside(geom.grid_points().reshape(-1, 3)).reshape(shape)
    return label_surface(geom.with_array(mask.astype(np.uint8)), 1)


def _ant_pair(seed: int):
    """pyvista's ant (scaled to a 246 mm diameter, Loop-subdivided to 117k vertices) decimated to 10k
    vertices, and its image under 6 Gaussian bumps (scale 15 %, up to 5 % of the diameter, as in
    `bench_surfaces.py`) decimated to 12k, so that no target vertex is the image of a source vertex."""
    from types import SimpleNamespace

    import pyvista as pv
    from pyvista import examples

    from volreg.morph import surface_normals

    mesh = pv.read(os.path.join(os.path.dirname(examples.__file__), "ant.ply")).triangulate().clean()
    mesh.points = np.asarray(mesh.points) * 5.0
    mesh = mesh.subdivide(4, subfilter="loop")
    v = np.asarray(mesh.points, float)
    diameter = float(np.linalg.norm(np.ptp(v, axis=0)))
    truth = GaussianBumps.random(v.min(0), v.max(0), max_displacement=0.05 * diameter, scale=0.15 * diameter,
                                 count=6, rng=np.random.default_rng(seed))
    moved = mesh.copy()
    moved.points = truth(v)
    out = []
    for m, size in ((mesh, 10000), (moved, 12000)):
        m = m.decimate(1.0 - size / m.n_points).triangulate().clean()
        pts = np.asarray(m.points, float)
        faces = np.asarray(m.faces).reshape(-1, 4)[:, 1:]
        out.append(SimpleNamespace(vertices=pts, normals=surface_normals(pts, faces)))
    return out[0], out[1], truth, diameter


def _cortex_pair(seed: int):
    """The folded blob of `tests/shapes.py` (semi-axes 30 / 36 / 30 mm, sulci 8 mm deep and about 7 mm
    apart; diameter about 110 mm, surface 1.6 x its envelope's) labelled at 0.75 mm and
    decimated to 10k vertices, and its image under 6 Gaussian bumps (scale 15 %, up to 5 % of the
    diameter, as the ant) labelled on a grid offset by a fraction of a voxel and decimated to 12k."""
    spacing = 0.75
    shape = tuple(int(n) for n in np.floor(2 * (np.array([30.0, 36.0, 30.0]) + 10) / spacing) + 1)
    origin = -(np.array(shape) - 1) * spacing / 2
    full = _surface(shape, origin, folded_blob_inside, spacing)
    v = full.vertices
    diameter = float(np.linalg.norm(np.ptp(v, axis=0)))
    truth = GaussianBumps.random(v.min(0), v.max(0), max_displacement=0.05 * diameter, scale=0.15 * diameter,
                                 count=6, rng=np.random.default_rng(seed))
    moved = _surface(shape, origin + np.array([0.31, 0.17, 0.43]) * spacing,
                     lambda p: folded_blob_inside(truth.inverse(p)), spacing)
    return decimated_surface(full, 10000), decimated_surface(moved, 12000), truth, diameter


def make_pair(bumps: int | str, seed: int | None):
    """Source surface, target surface, the true map and the diameter (mm) of one pair."""
    if bumps == "ant":
        return _ant_pair(seed)
    if bumps == "cortex":
        return _cortex_pair(seed)
    inside = _inside(bumps)
    source = _surface((60,) * 3, (-29.5,) * 3, inside)
    diameter = float(np.linalg.norm(np.ptp(source.vertices, axis=0)))
    if seed is None:
        truth = Shear(diameter)
    else:
        truth = GaussianBumps.random((-30,) * 3, (30,) * 3, max_displacement=0.15 * diameter, scale=15.0, count=6,
                                     rng=np.random.default_rng(seed))
    target = _surface((80,) * 3, (-39.3, -39.6, -39.8), lambda p: inside(truth.inverse(p)))
    return source, target, truth, diameter


def _pre_stage(f1, f2, diameter: float, settings, kind: str, penalty: float):
    """A linear map fitted by the locational cost before the kernel warp (see the module docstring)."""
    from scipy.optimize import least_squares

    from volreg.features.mapped import LinearlyMapped
    from volreg.linear_map import LinearMap
    from volreg.warp.sampling import octree_sample

    st = settings.resolved(diameter)
    x = octree_sample(f1.points, st.pad, st.min_width, fraction=st.fraction)
    a, ga = f1.evaluate(x)
    weight = np.sqrt(st.alpha)
    pen = np.sqrt(penalty * (diameter / 2) ** 2 * len(x))

    def linear(p):
        if kind == "translation":
            return LinearMap(np.eye(3), p)
        return LinearMap(np.eye(3) + p[:9].reshape(3, 3), p[9:])

    def residual(p):
        b, gb = LinearlyMapped(f2, linear(p)).evaluate(x)
        extra = pen * p[:9] if kind == "affine" else []
        return np.concatenate([a - b, weight * (ga - gb).ravel(), extra])

    n = 3 if kind == "translation" else 12
    scale = np.ones(n) if kind == "translation" else np.r_[[0.1] * 9, [1.0] * 3]
    return linear(least_squares(residual, np.zeros(n), x_scale=scale, max_nfev=200).x)


def _coarse(f, keep: int):
    """The implicit surface ``f`` summed over its ``keep`` coarsest levels only (a smoother shape)."""
    arrays = f.to_arrays()
    arrays["widths"] = arrays["widths"][:keep]
    return ImplicitSurface.from_arrays(arrays)


def _mean_curvature(f, x: np.ndarray) -> np.ndarray:
    """Mean curvature (1/mm) of the level set of ``f`` through each point of ``x``."""
    _, g, h = f.evaluate(x, order=2)
    norm = np.linalg.norm(g, axis=1)
    n = g / norm[:, None]
    return (np.trace(h, axis1=1, axis2=2) - np.einsum("ni,nij,nj->n", n, h, n)) / (2 * norm)


def _bending(warp, x: np.ndarray, step: float = 0.5) -> float:
    """Mean over ``x`` of the squared second derivatives of a map, ``sum_ijk (d^2 tau_i / dx_j dx_k)^2``
    (1/mm^2), by central differences of its Jacobian (``step`` mm)."""
    total = 0.0
    for k in range(x.shape[1]):
        d = np.zeros(x.shape[1])
        d[k] = step
        total += np.mean(np.sum((warp.jacobian(x + d) - warp.jacobian(x - d)) ** 2, axis=(1, 2))) / (2 * step) ** 2
    return float(total)


def level_weighted_regulariser(power: float, reference: float | None) -> None:
    """Weight each level's regulariser Gram matrix by ``(reference / width)^power`` (reference:
    the coarsest level's width when None): ``--regulariser-power``, measured, not kept."""
    import volreg.warp.fit as fit

    original = fit._level_objective

    def weighted(width, centres, grid, samples, fold, warp, inputs):
        ref = reference or fit._level_schedule(inputs.diameter, inputs.settings)[0][0]
        plain = fit.kernel_matrix
        first = []

        def kernel_matrix(points, grid, w):
            m = plain(points, grid, w)
            if not first:  # the first call is the centres' Gram matrix K_cc
                first.append(True)
                return m * (ref / width) ** power
            return m

        fit.kernel_matrix = kernel_matrix
        try:
            return original(width, centres, grid, samples, fold, warp, inputs)
        finally:
            fit.kernel_matrix = plain

    fit._level_objective = weighted


def diagnose(f1, f2, warp, truth, vertices: np.ndarray, settings, diameter: float) -> dict:
    """The locational cost's terms and a curvature mismatch, at the fitted warp and at the truth.

    Over the finest level's samples within the band (as the cost counts them): mean squared
    distance residual (3), mean squared gradient residual (4), the same with the target's
    gradient pulled back through the map's Jacobian (J^T grad f2(tau), the rotation-aware
    term); at the source vertices: the rms difference of the mean curvatures of f1 and f2; over
    all the warp volume's samples, the map's bending energy (:func:`_bending`) and mean |tau(x) - x|.
    """
    from scipy.spatial import cKDTree

    from volreg.warp.sampling import octree_sample

    st = settings.resolved(diameter)
    x = octree_sample(f1.points, st.pad, st.min_width, fraction=st.fraction)
    volume = x
    band = 0.5 * min(f1.widths) if st.band is None else st.band
    x = x[np.isfinite(cKDTree(f1.points).query(x, distance_upper_bound=band)[0])]
    a, ga = f1.evaluate(x)
    k1 = _mean_curvature(f1, vertices)
    out = {}
    for name, tau_map in (("fitted", warp), ("truth", truth)):
        tau, jac, tv = tau_map(x), tau_map.jacobian(x), tau_map(vertices)
        b, gb = f2.evaluate(tau)
        out[name] = (np.mean((a - b) ** 2), np.mean(np.sum((ga - gb) ** 2, axis=1)),
                     np.mean(np.sum((ga - np.einsum("nji,nj->ni", jac, gb)) ** 2, axis=1)),
                     float(np.sqrt(np.mean((k1 - _mean_curvature(f2, tv)) ** 2))),
                     _bending(tau_map, volume), float(np.mean(np.linalg.norm(tau_map(volume) - volume, axis=1))))
    return out


def run(method: str, bumps: int | str, pair, args) -> dict:
    """One method on one pair (:func:`make_pair`'s result for the shape ``bumps``)."""
    source, target, truth, diameter = pair
    v = source.vertices
    settings = WarpSettings(**json.loads(args.settings))
    if args.min_width:
        widths = (args.min_width, args.min_width)
    elif bumps in ("ant", "cortex"):  # as register_surfaces fits meshes
        finest = settings.resolved(float(np.linalg.norm(np.ptp(source.vertices, axis=0)))).min_width / np.sqrt(2)
        widths = tuple(mesh_min_width(s.vertices, finest) for s in (source, target))
    else:
        widths = (4.0, 4.0)
    t0 = time.perf_counter()
    f2 = ImplicitSurface(target.vertices, target.normals, min_width=widths[1])
    fit_f2 = time.perf_counter() - t0  # counted in volreg's time; the others use f2 only to score
    t0 = time.perf_counter()
    if method == "volreg":
        from volreg.features.mapped import LinearlyMapped
        from volreg.warp.fit import fit_warp
        from volreg.warp.objective import FeaturePair

        f1 = ImplicitSurface(v, source.normals, min_width=widths[0])
        target_feature, pre = f2, None
        if args.pre != "none":
            pre = _pre_stage(f1, f2, diameter, settings, args.pre, args.affine_penalty)
            target_feature = LinearlyMapped(f2, pre)
        pairs = [FeaturePair(f1, target_feature)]
        if args.coarse_features:
            keep, weight = (float(x) for x in args.coarse_features.split(":"))
            pairs.append(FeaturePair(_coarse(f1, int(keep)), LinearlyMapped(_coarse(f2, int(keep)), pre) if pre
                                     else _coarse(f2, int(keep)), weight=weight))
        landmarks = None
        if args.landmarks:
            pick = np.random.default_rng(0).choice(len(v), args.landmarks, replace=False)
            landmarks = (v[pick], truth(v[pick]) if pre is None else pre.inverse()(truth(v[pick])))
        prior = None
        if args.symmetric:  # the backward registration first; the forward one pulled to its inverse
            from dataclasses import replace

            from volreg.warp.inverse import InverseWarp

            back = fit_warp([FeaturePair(f2, f1)], target.vertices, settings=settings).warp
            prior = InverseWarp(back)
            settings = replace(settings, lambda_consistency=args.symmetric)
        warp = fit_warp(pairs, v, landmarks=landmarks, settings=settings, prior=prior).warp  # as register_surfaces
        if pre is not None:
            warp = warp.then(pre)
        moved = warp(v)
        terms = diagnose(f1, f2, warp, truth, v, settings, diameter) if args.diagnose else None
    elif method == "moments":
        from scipy.linalg import sqrtm

        def moments(p):
            return p.mean(axis=0), np.real(sqrtm(np.cov(p.T)))

        c1, t1 = moments(v)
        c2, t2 = moments(target.vertices)
        moved = (v - c1) @ (t2 @ np.linalg.inv(t1)).T + c2
    elif method in ("pycpd", "probreg-cpd", "probreg-bcpd"):
        rng = np.random.default_rng(0)
        pick = rng.choice(len(v), min(args.cpd_points, len(v)), replace=False)
        tpick = rng.choice(len(target.vertices), min(args.cpd_points, len(target.vertices)), replace=False)
        v = v[pick]
        scale = diameter / 10.0  # beta and lambda in tenths of the diameter
        y, x = v / scale, target.vertices[tpick] / scale
        if method == "pycpd":
            from pycpd import DeformableRegistration

            moved = DeformableRegistration(X=x, Y=y, alpha=2.0, beta=2.0, max_iterations=100).register()[0]
        elif method == "probreg-cpd":
            from probreg import cpd

            res = cpd.registration_cpd(y, x, tf_type_name="nonrigid", beta=2.0, lmd=2.0, maxiter=100)
            moved = np.asarray(res.transformation.transform(y))
        else:
            from probreg import bcpd

            moved = np.asarray(bcpd.registration_bcpd(y, x, lmd=2.0, maxiter=50).transform(y))
        moved = moved * scale
    else:
        raise SystemExit(f"unknown method {method}")
    seconds = time.perf_counter() - t0 + (fit_f2 if method == "volreg" else 0.0)
    if method != "volreg":
        terms = None
    err = np.linalg.norm(moved - truth(v), axis=1)
    return {"error": 100 * err.mean() / diameter,
            "identity": 100 * np.linalg.norm(truth(v) - v, axis=1).mean() / diameter,
            "distance": float(np.abs(f2(moved)).mean()), "seconds": seconds, "diameter": diameter, "terms": terms}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--shapes", default="0,4,8", help="bumps on the ellipsoid (any of 0, 4, 8), ant or cortex")
    parser.add_argument("--seeds", default="0,1,2,3", help="Gaussian-bump warps (one pair per seed)")
    parser.add_argument("--shear", action="store_true", help="also the bare ellipsoid under the shear")
    parser.add_argument("--methods", default="volreg,moments")
    parser.add_argument("--settings", default="{}", help="further WarpSettings for volreg, as JSON")
    parser.add_argument("--pre", default="none", choices=("none", "translation", "affine"))
    parser.add_argument("--affine-penalty", type=float, default=0.0)
    parser.add_argument("--cpd-points", type=int, default=2000)
    parser.add_argument("--coarse-features", default="",
                        help="K:W, a further feature pair: both implicit surfaces summed over their K coarsest "
                             "levels, weight W (paper eq. 6)")
    parser.add_argument("--landmarks", type=int, default=0,
                        help="volreg: this many random source vertices given with their true images")
    parser.add_argument("--symmetric", type=float, default=0.0,
                        help="volreg: fit the target onto the source first, then the source onto the target "
                             "pulled towards that warp's inverse with this lambda_consistency (mm^-2)")
    parser.add_argument("--min-width", type=float, default=0.0,
                        help="finest implicit-surface width (mm) for both surfaces, instead of the shape's default")
    parser.add_argument("--diagnose", action="store_true",
                        help="also print the cost terms and curvature mismatch at the fitted warp and the truth")
    parser.add_argument("--regulariser-power", default="",
                        help="P or P:REF: each level's regulariser weighted by (REF / width)^P (REF: the coarsest "
                             "width); a candidate measured, not in the library")
    args = parser.parse_args()
    if args.regulariser_power:
        power, _, ref = args.regulariser_power.partition(":")
        level_weighted_regulariser(float(power), float(ref) if ref else None)
    if args.symmetric and (args.pre != "none" or args.landmarks or args.coarse_features):
        parser.error("--symmetric fits the plain pair both ways; it does not combine with --pre, --landmarks "
                     "or --coarse-features")
    pairs = [(b if b in ("ant", "cortex") else int(b), int(s)) for b in args.shapes.split(",") for s in args.seeds.split(",")
             if s != ""]
    if args.shear:
        pairs.append((0, None))
    print("| shape | warp | method | error, % of diameter (identity) | distance to target (mm) | seconds |")
    print("|---|---|---|---|---|---|", flush=True)
    summary: dict[tuple[str, str], list[float]] = {}
    diagnosed = []
    for bumps, seed in pairs:
        shape = bumps if bumps in ("ant", "cortex") else f"ellipsoid + {bumps} bumps" if bumps else "ellipsoid"
        warp = "shear" if seed is None else f"bumps, seed {seed}"
        pair = make_pair(bumps, seed)
        for method in args.methods.split(","):
            r = run(method, bumps, pair, args)
            summary.setdefault((f"{shape}, {'shear' if seed is None else 'bumps'}", method), []).append(r["error"])
            print(f"| {shape} | {warp} | {method} | {r['error']:.2f} ({r['identity']:.2f}) | {r['distance']:.3f} "
                  f"| {r['seconds']:.1f} |", flush=True)
            if r["terms"]:
                diagnosed.append((f"{shape}, {warp}", r["terms"]))
    print("\n| pairs | method | mean error, % of diameter (per pair) |\n|---|---|---|")
    for (name, method), errs in summary.items():
        print(f"| {name} | {method} | {np.mean(errs):.2f} ({', '.join(f'{e:.2f}' for e in errs)}) |")
    if diagnosed:
        print("\n| pair | distance term (mm^2), fitted / truth | gradient term, fitted / truth "
              "| rotation-aware gradient term, fitted / truth | mean-curvature mismatch (1/mm), fitted / truth "
              "| bending energy (1/mm^2), fitted / truth | mean displacement (mm), fitted / truth |")
        print("|---|---|---|---|---|---|---|")
        for name, t in diagnosed:
            f, g = t["fitted"], t["truth"]
            print(f"| {name} | {f[0]:.4f} / {g[0]:.4f} | {f[1]:.4f} / {g[1]:.4f} | {f[2]:.4f} / {g[2]:.4f} "
                  f"| {f[3]:.4f} / {g[3]:.4f} | {f[4]:.5f} / {g[4]:.5f} | {f[5]:.2f} / {g[5]:.2f} |")


if __name__ == "__main__":
    main()
