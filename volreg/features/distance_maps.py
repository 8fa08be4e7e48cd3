"""Voxel signed-distance features: each label's distance map as a feature function (6).

The implicit surfaces (Section 4 of the paper) describe each label by a kernel
fit to its marching-cubes surface; labels too small or too fragmented for a
surface (thin bones broken into dozens of pieces by the voxel grid, tissues of
a few voxels) then only ride along with the warp.  A :class:`VoxelDistance` is
a second kind of feature function for the locational cost (3)-(4), one per
label and volume: the signed distance to the label's boundary (mm, negative
inside), clipped to ``+-clip`` mm so that only the neighbourhood of the label
counts, smoothed by a Gaussian, and interpolated by a cubic B-spline -- so that
its gradient and Hessian, which the objective's gradient needs, are exact
derivatives of the interpolant.  The distance is read from the label's
indicator blurred by a Gaussian of a scale in mm (:func:`blurred_signed_distance`),
exact for a plane whatever the grid, so that the same object sampled at two
resolutions gets the same map; or, with no scale, measured between voxel
centres to the boundary half-way between them (:func:`clipped_signed_distance`).

Everything here is a pure function of arrays (no I/O).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage, special

from volreg._jit import njit
from volreg._threads import part_range, run_parts

__all__ = ["VoxelDistance", "blurred_signed_distance", "clipped_signed_distance", "euclidean_distance"]


@njit
def _mirror(i: int, n: int) -> int:
    """Index ``i`` reflected into ``[0, n)`` (scipy.ndimage's ``mirror`` mode)."""
    if n == 1:
        return 0
    period = 2 * (n - 1)
    i = i % period
    if i < 0:
        i += period
    return i if i < n else period - i


@njit
def _axis(x: float, n: int, idx, w, d, s) -> None:
    """Stencil of the cubic B-spline on one axis at continuous index ``x``: the four
    indices ``idx``, weights ``w`` and their first and second derivatives ``d``, ``s``.
    Outside ``[0, n - 1]`` the spline is continued as a constant (derivatives 0)."""
    clamped = False
    if x < 0.0:
        x, clamped = 0.0, True
    elif x > n - 1:
        x, clamped = float(n - 1), True
    base = int(np.floor(x))
    if base > n - 2:
        base = max(n - 2, 0)
    t = x - base
    t2 = t * t
    t3 = t2 * t
    u = 1.0 - t
    w[0] = u * u * u / 6.0
    w[1] = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0
    w[2] = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
    w[3] = t3 / 6.0
    if clamped or n == 1:
        for k in range(4):
            d[k] = 0.0
            s[k] = 0.0
    else:
        d[0] = -0.5 * u * u
        d[1] = 1.5 * t2 - 2.0 * t
        d[2] = -1.5 * t2 + t + 0.5
        d[3] = 0.5 * t2
        s[0] = u
        s[1] = 3.0 * t - 2.0
        s[2] = 1.0 - 3.0 * t
        s[3] = t
    for k in range(4):
        idx[k] = _mirror(base - 1 + k, n)


@njit(fastmath=True)
def _bspline3_at(coef, i0, i1, i2, order, p, f, g, h, index, weight):  # pragma: no cover - compiled
    """The cubic B-spline of ``coef`` (nx, ny, nz) at one continuous index ``(i0, i1, i2)``, written to row ``p``;
    ``index`` (3, 4) int and ``weight`` (9, 4) float are scratch."""
    nx, ny, nz = coef.shape
    ix, iy, iz = index[0], index[1], index[2]
    wx, wy, wz, dx, dy, dz, sx, sy, sz = (weight[0], weight[1], weight[2], weight[3], weight[4], weight[5],
                                          weight[6], weight[7], weight[8])
    _axis(i0, nx, ix, wx, dx, sx)
    _axis(i1, ny, iy, wy, dy, sy)
    _axis(i2, nz, iz, wz, dz, sz)
    # Separably, axis by axis (z, then y, then x): the 64 coefficients are read once and each
    # derivative is a sum over the x weights of sums over y of sums over z, 3 x 64 + 6 x 16 + 10 x 4
    # products instead of up to 10 x 64, and less code to compile.
    v = 0.0
    gx = 0.0
    gy = 0.0
    gz = 0.0
    hxx = 0.0
    hyy = 0.0
    hzz = 0.0
    hxy = 0.0
    hxz = 0.0
    hyz = 0.0
    for a in range(4):
        y00 = 0.0  # sum over y and z of w w q
        y10 = 0.0  # dy w
        y01 = 0.0  # w dz
        y20 = 0.0  # sy w
        y11 = 0.0  # dy dz
        y02 = 0.0  # w sz
        for b in range(4):
            z0 = 0.0
            z1 = 0.0
            z2 = 0.0
            for c in range(4):
                q = coef[ix[a], iy[b], iz[c]]
                z0 += wz[c] * q
                z1 += dz[c] * q
                z2 += sz[c] * q
            y00 += wy[b] * z0
            y10 += dy[b] * z0
            y01 += wy[b] * z1
            y20 += sy[b] * z0
            y11 += dy[b] * z1
            y02 += wy[b] * z2
        v += wx[a] * y00
        gx += dx[a] * y00
        gy += wx[a] * y10
        gz += wx[a] * y01
        hxx += sx[a] * y00
        hyy += wx[a] * y20
        hzz += wx[a] * y02
        hxy += dx[a] * y10
        hxz += dx[a] * y01
        hyz += wx[a] * y11
    f[p] = v
    if order >= 1:
        g[p, 0] = gx
        g[p, 1] = gy
        g[p, 2] = gz
    if order >= 2:
        h[p, 0, 0] = hxx
        h[p, 1, 1] = hyy
        h[p, 2, 2] = hzz
        h[p, 0, 1] = hxy
        h[p, 1, 0] = hxy
        h[p, 0, 2] = hxz
        h[p, 2, 0] = hxz
        h[p, 1, 2] = hyz
        h[p, 2, 1] = hyz


@njit(nogil=True, fastmath=True)
def _bspline3_segments(part, parts, coef, coff, shapes, rstart, index, order, f, g, h):  # pragma: no cover - compiled
    """Cubic B-splines of several coefficient volumes, each at its own segment of ``index``.

    Volume ``k`` is ``coef[coff[k]:coff[k + 1]]`` (flat, C order) of shape ``shapes[k]``
    (3,) and is evaluated at the continuous indices of rows ``rstart[k]:rstart[k + 1]`` of
    ``index`` (N, 3): value ``f`` (N,), and for ``order`` >= 1 the gradient ``g`` (N, 3)
    and for ``order`` >= 2 the Hessian ``h`` (N, 3, 3), per index unit.  The rows in
    parallel, ``part_range(N, part, parts)`` of them per part, whichever volumes they fall
    in.  One volume is one segment (:meth:`VoxelDistance.evaluate`): no loop of its own for
    that case, so a first run compiles one loop instead of two.
    """
    first, stop = part_range(rstart[rstart.shape[0] - 1], part, parts)
    stencil = np.empty((3, 4), np.int64)
    weight = np.empty((9, 4))
    nk = rstart.shape[0] - 1
    k = 0
    while k < nk and rstart[k + 1] <= first:  # the volume holding the part's first row
        k += 1
    for k in range(k, nk):
        if rstart[k] >= stop:
            break
        volume = coef[coff[k]:coff[k + 1]].reshape((shapes[k, 0], shapes[k, 1], shapes[k, 2]))
        for p in range(max(rstart[k], first), min(rstart[k + 1], stop)):
            _bspline3_at(volume, index[p, 0], index[p, 1], index[p, 2], order, p, f, g, h, stencil, weight)


@njit(nogil=True)
def _clipped_sdf_band(part, parts, mask, band, offsets, lengths, clip, out):  # pragma: no cover - compiled
    """Signed distance of each voxel of ``band`` to the nearest voxel of the other kind
    (inside/outside ``mask``), scanning ``offsets`` (K, 3) in order of their ``lengths``
    (mm); ``+-clip`` where none lies within ``clip`` and everywhere outside ``band``."""
    nx, ny, nz = mask.shape
    first, stop = part_range(nx, part, parts)
    for i in range(first, stop):
        for j in range(ny):
            for k in range(nz):
                inside = mask[i, j, k]
                value = clip
                if band[i, j, k]:
                    for q in range(offsets.shape[0]):
                        a = i + offsets[q, 0]
                        b = j + offsets[q, 1]
                        c = k + offsets[q, 2]
                        if a < 0 or b < 0 or c < 0 or a >= nx or b >= ny or c >= nz:
                            continue
                        if mask[a, b, c] != inside:
                            value = lengths[q]
                            break
                out[i, j, k] = -value if inside else value


#: Fewest points per part of a B-spline evaluation (:func:`volreg._threads.run_parts`).
_POINTS = 1024

#: Masks from this many voxels on get :func:`euclidean_distance`'s own separable passes: below
#: it scipy's transform is as fast.
SEPARABLE_CELLS = 1 << 15


@njit(nogil=True)
def _squared_distance_lines(part, parts, g, axis, s2):  # pragma: no cover - compiled
    """Exact 1-D squared distance transform of every line of ``g`` (3-D, float64, in place)
    along ``axis``: ``g[q] <- min_p s2 (q - p)^2 + g[p]`` over the line's finite entries
    (the lower envelope of parabolas, Felzenszwalb & Huttenlocher 2012), lines in parallel."""
    n = g.shape[axis]
    na = g.shape[1] if axis == 0 else g.shape[0]
    nb = g.shape[1] if axis == 2 else g.shape[2]
    first, stop = part_range(na, part, parts)
    for a in range(first, stop):
        f = np.empty(n)
        v = np.empty(n, dtype=np.int64)
        z = np.empty(n + 1)
        for b in range(nb):
            for i in range(n):
                if axis == 0:
                    f[i] = g[i, a, b]
                elif axis == 1:
                    f[i] = g[a, i, b]
                else:
                    f[i] = g[a, b, i]
            k = -1
            for q in range(n):
                fq = f[q]
                if fq == np.inf:
                    continue
                cross = 0.0
                while k >= 0:
                    p = v[k]
                    cross = ((fq + s2 * q * q) - (f[p] + s2 * p * p)) / (2.0 * s2 * (q - p))
                    if cross <= z[k]:
                        k -= 1
                    else:
                        break
                k += 1
                v[k] = q
                z[k] = -np.inf if k == 0 else cross
                z[k + 1] = np.inf
            if k < 0:
                continue  # no finite entry: the line stays infinite
            j = 0
            for q in range(n):
                while z[j + 1] < q:
                    j += 1
                p = v[j]
                value = s2 * (q - p) * (q - p) + f[p]
                if axis == 0:
                    g[q, a, b] = value
                elif axis == 1:
                    g[a, q, b] = value
                else:
                    g[a, b, q] = value


def euclidean_distance(mask: np.ndarray, spacing) -> np.ndarray:
    """Euclidean distance (mm) of each ``True`` voxel centre to the nearest ``False`` one; 0 on ``False`` voxels.

    The values of ``scipy.ndimage.distance_transform_edt(mask, sampling=spacing)`` (exact,
    to rounding).  Masks of :data:`SEPARABLE_CELLS` voxels or more are computed by three
    separable 1-D passes of squared distances, lines in parallel (scipy's transform runs on
    one thread), the same values.  Smaller ones go to scipy, which is as fast there.

    Parameters
    ----------
    mask : (X, Y, Z) or (X, Y) bool ndarray
        At least one ``False`` voxel (else every distance is infinite).
    spacing : (D,) float, mm

    Returns
    -------
    (X, Y, Z) or (X, Y) float64 ndarray, mm
    """
    mask = np.asarray(mask, dtype=bool)
    spacing = np.asarray(spacing, dtype=float)
    if mask.ndim not in (2, 3) or spacing.shape != (mask.ndim,):
        raise ValueError(f"Expected a 2-D or 3-D mask and one spacing per axis, got {mask.shape} and {spacing.shape}.")
    if mask.size < SEPARABLE_CELLS:
        return ndimage.distance_transform_edt(mask, sampling=spacing)
    g = np.where(mask, np.inf, 0.0)
    if mask.ndim == 2:
        g, spacing = g[None], np.concatenate([[1.0], spacing])
    for axis in range(3):
        if g.shape[axis] > 1:
            run_parts(_squared_distance_lines, g.shape[1] if axis == 0 else g.shape[0], g, axis,
                      float(spacing[axis]) ** 2)
    return np.sqrt(g, out=g).reshape(mask.shape)


def clipped_signed_distance(mask: np.ndarray, spacing: np.ndarray, clip: float, *, midway: bool = False) -> np.ndarray:
    """:func:`volreg.warp.resample.signed_distance_map` clipped to ``[-clip, clip]``, computed only
    near the boundary.

    Equal to ``np.clip(signed_distance_map(mask, spacing), -clip, clip)`` (the same Euclidean
    distances between voxel centres), but each voxel looks only at the voxels within
    ``clip`` mm of it, and only voxels within that reach of the boundary look at all:
    on a thin label spread over a large box (a skeleton in a whole-body volume) this is
    much less work than two full distance transforms.

    With ``midway``, distances are measured to the boundary half-way between the voxel
    centres of the two kinds (where marching cubes puts the surface) instead of to the
    nearest centre of the other kind, to first order: every distance is shortened by a
    third of the mean voxel spacing (at most half the finest spacing).  The distances
    between centres are too long by 0.25-0.6 voxel, depending on the boundary's
    orientation and the distance to it: 0.38-0.44 voxel on average within 3 voxels of
    spheres of radius 12 and 25 mm at 1, 2 and 3 mm, so that the same object at two
    resolutions gets two different maps (0.4 mm apart at 1 and 2 mm).  Shortened, the
    mean error there is 0.05-0.11 voxel, and within 0.04 mm at 0.8 x 0.8 x 2.5 and
    1 x 1 x 1.5 mm.  (A shortening that depends on the direction to
    the nearest centre of the other kind is less biased on the sphere, but makes the map
    rough where neighbouring voxels find their nearest centres along different axes, and
    the warps fitted to it were less accurate.)

    Parameters
    ----------
    mask : (n_i, n_j[, n_k]) bool ndarray
    spacing : (D,) float ndarray, mm
    clip : float, mm
    midway : bool
        Distances to the boundary half-way between the centres (see above), not to the
        centres.

    Returns
    -------
    float32 ndarray of ``mask.shape``, mm (negative inside)
    """
    mask = np.asarray(mask, dtype=bool)
    spacing = np.asarray(spacing, dtype=float)
    # Midway: every distance less a third of the mean spacing (see above), never more than
    # half the finest one (so that no distance reaches 0).
    shorten = min(float(np.mean(spacing)) / 3.0, 0.5 * float(spacing.min())) if midway else 0.0
    reach = np.floor((clip + shorten) / spacing + 1e-9).astype(int)
    grids = np.meshgrid(*[np.arange(-r, r + 1) for r in reach], indexing="ij")
    offsets = np.stack([g.ravel() for g in grids], axis=1)
    lengths = np.linalg.norm(offsets * spacing, axis=1) - shorten
    keep = (np.any(offsets != 0, axis=1)) & (lengths <= clip)
    order = np.argsort(lengths[keep], kind="stable")
    offsets, lengths = offsets[keep][order], lengths[keep][order]
    # Voxels with a voxel of the other kind within `reach` (per axis): the only ones that can
    # be nearer than `clip` to the boundary.
    # (Separable running max / min over boxes of that reach; outside the array counts as
    # neither, as in the distance transform.)
    size = tuple(2 * reach + 1)
    as_u8 = mask.view(np.uint8)
    near_in = ndimage.maximum_filter(as_u8, size=size, mode="constant", cval=0)
    near_out = ndimage.minimum_filter(as_u8, size=size, mode="constant", cval=1) == 0
    band = (near_in > 0) & near_out
    if mask.ndim == 2:
        mask3, band3 = mask[:, :, None], band[:, :, None]
        offsets = np.concatenate([offsets, np.zeros((len(offsets), 1), dtype=offsets.dtype)], axis=1)
    else:
        mask3, band3 = mask, band
    out = np.empty(mask3.shape, dtype=np.float32)
    run_parts(_clipped_sdf_band, mask3.shape[0], np.ascontiguousarray(mask3), np.ascontiguousarray(band3),
              np.ascontiguousarray(offsets, dtype=np.int64), lengths.astype(np.float32), np.float32(clip), out)
    return out.reshape(mask.shape)


def blurred_signed_distance(mask: np.ndarray, spacing: np.ndarray, scale: float, clip: float) -> np.ndarray:
    """Signed distance to the boundary of ``mask`` read from its indicator blurred by a Gaussian,
    clipped to ``[-clip, clip]``.

    ``d = -scale * Phi^-1((G_scale * 1_mask)(x))``, with ``G_scale`` the isotropic Gaussian of
    standard deviation ``scale`` mm and ``Phi`` the standard normal distribution function.  For
    a half-space whose boundary plane lies at signed distance ``D`` from ``x`` (positive
    outside) the blurred indicator is ``Phi(-D / scale)``, so ``d = D`` exactly, at any
    orientation; a boundary of radius of curvature ``R`` is moved by about ``scale^2 / R``
    (towards its concave side), the same on any grid.  Where ``scale`` is at least the voxel
    spacing the blur of the voxels' indicator is that of the object itself up to the voxels'
    discretisation, which the blur averages out, so the same object sampled at two resolutions
    gets the same distances: the labels of a folded brain-like phantom at 1 mm and at 2 mm (every
    second voxel), blurred as a registration does (2 mm), 1-3 mm from their boundaries differ by
    at most 0.007 mm on average, where distances between voxel centres
    (:func:`clipped_signed_distance`, ``midway``) differ by 0.1-0.16 mm.

    Parameters
    ----------
    mask : (n_i, n_j[, n_k]) bool ndarray
        Beyond its faces the mask is continued by its edge voxels (a label cut by the edge of
        an image is not closed there).
    spacing : (D,) float ndarray, mm
    scale : float, mm
        Standard deviation of the Gaussian, positive.
    clip : float, mm
        Positive.

    Returns
    -------
    float32 ndarray of ``mask.shape``, mm (negative inside)
    """
    mask = np.asarray(mask, dtype=bool)
    spacing = np.asarray(spacing, dtype=float)
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"Expected a positive `scale` (mm), got {scale}.")
    if not (np.isfinite(clip) and clip > 0):
        raise ValueError(f"Expected a positive `clip` (mm), got {clip}.")
    blurred = ndimage.gaussian_filter(mask.astype(np.float64), float(scale) / spacing, mode="nearest")
    # Beyond the clip the distance is the clip: Phi^-1 is evaluated only where it is less.
    tail = 0.5 * math.erfc(float(clip) / float(scale) / math.sqrt(2.0))
    out = np.where(blurred >= 0.5, np.float32(-clip), np.float32(clip))
    band = (blurred > tail) & (blurred < 1.0 - tail)
    out[band] = np.clip(-float(scale) * special.ndtri(blurred[band]), -clip, clip)
    return out


class VoxelDistance:
    """One label's clipped, smoothed signed distance map as a feature function.

    ``f(x)`` (mm) is the cubic B-spline interpolant of the signed distance of
    the voxel centres to the boundary of ``mask`` (negative inside): read from
    the mask blurred by a Gaussian of ``scale`` mm (:func:`blurred_signed_distance`),
    or with ``scale`` 0 measured to the boundary half-way between its centres
    and those outside (:func:`clipped_signed_distance` with ``midway``), clipped
    to ``[-clip, clip]`` and blurred by a Gaussian of ``smoothing`` mm; beyond
    the mask's bounding box padded by ``clip`` it is the constant ``clip``.  Exposes the interface
    of :class:`~volreg.features.implicit.ImplicitSurface` that the warp objective uses:
    :meth:`evaluate`, :meth:`bounds` and ``band``.

    Parameters
    ----------
    mask : (n_i, n_j[, n_k]) bool ndarray
        The label's voxels, ITK index order.
    spacing : (D,) float ndarray, mm
    origin : (D,) float ndarray, mm (LPS)
    direction : (D, D) float ndarray
        World point of index ``i``: ``origin + direction @ (spacing * i)``.
    clip : float, mm
        Distances are clipped to ``+-clip``.
    smoothing : float, mm
        Standard deviation of the blur (0 = none: the spline interpolates the
        clipped distances).  Where it is at least ``spacing / sqrt(3)`` on every
        axis, the spline's own blur is part of it (the samples blurred by the
        rest are the spline's coefficients); otherwise the samples are blurred
        by a Gaussian of ``smoothing`` and interpolated.
    scale : float, mm
        Scale of the Gaussian through which the distances are read (0: distances between
        voxel centres); at least the largest voxel spacing for distances that do not depend
        on the grid.

    Attributes
    ----------
    band : float, mm
        Where the feature is informative: ``|f| < clip`` (samples farther from
        the fixed label are left out of its locational cost, as the band of
        the implicit surfaces).
    """

    def __init__(self, mask, spacing, origin, direction, *, clip: float, smoothing: float = 0.0, scale: float = 0.0):
        mask = np.asarray(mask, dtype=bool)
        self.dim = mask.ndim
        if self.dim not in (2, 3):
            raise ValueError(f"Expected a 2-D or 3-D `mask`, got {mask.ndim}-D.")
        if not mask.any():
            raise ValueError("Expected a `mask` with at least one voxel, got an empty mask.")
        if not (np.isfinite(clip) and clip > 0):
            raise ValueError(f"Expected a positive `clip` (mm), got {clip}.")
        if not (np.isfinite(smoothing) and smoothing >= 0):
            raise ValueError(f"Expected `smoothing` >= 0 (mm), got {smoothing}.")
        if not (np.isfinite(scale) and scale >= 0):
            raise ValueError(f"Expected `scale` >= 0 (mm), got {scale}.")
        spacing = np.asarray(spacing, dtype=float)
        self.spacing = spacing
        self.origin = np.asarray(origin, dtype=float)
        self.direction = np.asarray(direction, dtype=float)
        self.clip = float(clip)
        # Strictly inside the clip: far from the label, where f is the constant `clip` up to
        # rounding, samples carry no information.
        self.band = float(clip) * (1 - 1e-3)
        # Crop: the bounding box padded by the clip distance, the blur's reach and the
        # spline's stencil, so that the map is the constant `clip` at the crop's faces.
        box = ndimage.find_objects(mask.astype(np.int8))[0]
        pad = np.ceil((clip + 3 * smoothing + 4 * scale) / spacing).astype(int) + 2
        self.lo = np.array([max(b.start - p, 0) for b, p in zip(box, pad)])
        hi = np.array([min(b.stop + p, n) for b, p, n in zip(box, pad, mask.shape)])
        crop = mask[tuple(slice(a, b) for a, b in zip(self.lo, hi))]
        if scale > 0:
            sdf = blurred_signed_distance(crop, spacing, scale, clip)
        else:
            sdf = clipped_signed_distance(crop, spacing, clip, midway=True)
        # A cubic B-spline whose coefficients are the samples themselves blurs them by its
        # own kernel, of variance 1/3 voxel^2 per axis: where the asked-for blur is at least
        # that, the Gaussian makes up the rest and no prefilter is needed (the prefilter and
        # a full Gaussian were most of the cost of a thin label in a large volume).
        sigma = smoothing / spacing  # voxels, per axis
        if np.all(sigma**2 >= 1 / 3):
            coef = ndimage.gaussian_filter(sdf, np.sqrt(sigma**2 - 1 / 3), mode="nearest")
        else:
            if smoothing > 0:
                sdf = ndimage.gaussian_filter(sdf, sigma, mode="nearest")
            coef = ndimage.spline_filter(sdf, order=3, mode="mirror")
        coef = coef.astype(np.float32, copy=False)
        self._coef = np.ascontiguousarray(coef if self.dim == 3 else coef[:, :, None])
        self._step = self.direction / spacing[None, :]  # d world-gradient = step @ d index-gradient
        # Axis-aligned grids (a diagonal step): the Hessian's change of variables is a product
        # with the outer product of the diagonal, not two matrix products per point.
        diagonal = not np.any(self._step - np.diag(np.diag(self._step)))
        self._step_outer = np.outer(np.diag(self._step), np.diag(self._step)) if diagonal else None
        self._to_index = np.linalg.inv(self.direction * spacing[None, :]).T  # index = (x - origin) @ this
        corners = np.array(np.meshgrid(*[[a, b - 1] for a, b in zip(self.lo, hi)], indexing="ij")).reshape(self.dim, -1).T
        world = self.origin + (corners * spacing) @ self.direction.T
        self._bounds = (world.min(axis=0), world.max(axis=0))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World bounding box (LPS mm) outside which ``f`` is the constant ``clip``."""
        return self._bounds

    def evaluate(self, points: np.ndarray, order: int = 0) -> tuple:
        """``f`` (mm) and for ``order`` >= 1 its gradient, for ``order`` >= 2 its Hessian.

        Parameters
        ----------
        points : (N, D) float ndarray, LPS mm
        order : {0, 1, 2}

        Returns
        -------
        tuple of (N,), (N, D), (N, D, D) float ndarrays (as many as ``order + 1``)
        """
        points = np.asarray(points, dtype=float).reshape(-1, self.dim)
        index = (points - self.origin) @ self._to_index - self.lo
        if self.dim == 2:
            index = np.concatenate([index, np.zeros((len(index), 1))], axis=1)
        n = len(index)
        f = np.empty(n)
        g = np.empty((n, 3)) if order >= 1 else np.empty((0, 3))
        h = np.empty((n, 3, 3)) if order >= 2 else np.empty((0, 3, 3))
        coef = self._coef.reshape(-1)  # one volume, one segment
        run_parts(_bspline3_segments, n, coef, np.array([0, coef.size], np.int64),
                  np.array([self._coef.shape], np.int64), np.array([0, n], np.int64), np.ascontiguousarray(index),
                  int(order), f, g, h, grain=_POINTS)
        out = [f]
        d = self.dim
        if order >= 1:
            out.append(g[:, :d] @ self._step.T)
        if order >= 2:
            if self._step_outer is not None:
                out.append(h[:, :d, :d] * self._step_outer)
            else:
                out.append(self._step @ h[:, :d, :d] @ self._step.T)
        return tuple(out)
