"""Kernel warps: ``tau(x) = A x + b + sum_l sum_j c_j k(|x - x_j| / sigma_l)`` (paper eq. 9).

Each component of the warp is ``tau_d(x) = x_d + <w_d, Phi(x)>`` (9); by the
representer theorem ``w_d`` is a finite kernel expansion over training points,
so ``tau(x) = x + sum_j c_j k(x, x_j)`` with one coefficient vector
``c_j in R^D`` (mm) per centre ``x_j``.  Fitting coarse to fine (Section 3.5)
adds one such expansion per kernel width, each fitting the residual of the
levels before it; the warp is their sum.  With the compactly supported Wu
kernel (13) every evaluation is a neighbour query (:func:`volreg.kernels.kernel_sum`)
and the Jacobian is analytic::

    J[n, a, b] = d tau_a / d x_b = A_ab + sum_l sum_j c_j[a] d k_l(x_n, x_j) / d x_b

A linear part ``x -> A x + b`` (:class:`~volreg.linear_map.LinearMap`, ``det A > 0``)
may precede the kernel expansion; it is the identity (``A = I``, ``b = 0``) unless
given, and then the evaluation is exactly that of ``x + sum ...``.  The kernel
sums are evaluated at ``x`` itself (fixed space), so the centres ``x_j`` are
fixed-space points whatever the linear part.  Outside the box of the kernels'
supports (:meth:`KernelWarp.bounds`) the warp is exactly its linear part.

The warp lives in continuous space: it is evaluated and differentiated at any
points, without a grid, and saved as its centres, coefficients and widths
(``.npz``, no pickle) together with the settings that produced it.

Conventions: points are ``(N, D)`` float arrays in world millimetres (ITK
physical space, LPS), D = 2 or 3.  A registration of FIXED to MOVING gives the
pull-back ``tau`` mapping a fixed-image point to its moving-image partner.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Callable, Union

import numpy as np

from volreg.errors import exception_text, excerpt
from volreg.kernels import CellGrid, check_points, kernel_sum, put_rows, spatial_order, take_rows
from volreg.linear_map import LinearMap

__all__ = [
    "WarpLevel",
    "KernelWarp",
    "ComposedWarp",
    "FORMAT",
    "FORMAT_VERSION",
    "DEFAULT_CHUNK",
    "jacobian_det",
    "linear_outside",
]

ProgressCallback = Callable[[str, int, int], None]

#: Value of the ``format`` entry of a saved warp.
FORMAT = "volreg-kernel-warp"
#: Version of the saved layout this module writes (it reads this one and every earlier one).
#: Version 2 added the linear part (``linear_matrix``, ``linear_translation``); a
#: version-1 file has none and loads with the identity.
FORMAT_VERSION = 2
#: Default number of points evaluated at once: the (N, D, D) Jacobian buffer of
#: a 3-D chunk is then 72 MB.
DEFAULT_CHUNK = 1_000_000


def jacobian_det(jac: np.ndarray) -> np.ndarray:
    """Determinants of a stack of 2 x 2 or 3 x 3 Jacobians, in closed form.

    The same values as ``np.linalg.det`` (to rounding) without its LU
    factorisation per matrix, which costs several times as long on stacks of
    small matrices.

    Parameters
    ----------
    jac : (..., D, D) float ndarray, D = 2 or 3

    Returns
    -------
    (...) float ndarray
    """
    a = np.asarray(jac, dtype=float)
    if a.ndim < 2 or a.shape[-1] != a.shape[-2] or a.shape[-1] not in (2, 3):
        raise ValueError(f"Expected `jac` of shape (..., D, D) with D = 2 or 3, got {a.shape}.")
    if a.shape[-1] == 2:
        return a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    return (a[..., 0, 0] * (a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1])
            - a[..., 0, 1] * (a[..., 1, 0] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 0])
            + a[..., 0, 2] * (a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0]))


def _as_level_array(name: str, value: Any) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"Expected real numbers in `{name}`, got dtype {arr.dtype}.")
    arr = np.array(arr, dtype=float)  # a private copy, made read-only below
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise ValueError(f"Expected `{name}` of shape (M, D) with D = 2 or 3, got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"Expected finite values in `{name}`, found NaN or Inf.")
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class WarpLevel:
    """One scale of a kernel warp: ``u_l(x) = sum_j c_j k(|x - x_j| / width)``.

    Parameters
    ----------
    centres : (M, D) float array_like, mm
        Kernel centres ``x_j`` (LPS), D = 2 or 3.  ``M = 0`` is allowed (a
        level that moves nothing).
    coeffs : (M, D) float array_like, mm
        Coefficient vectors ``c_j``; the displacement at a centre far from the
        others is ``k(0) c_j = 4 c_j``.
    width : float, mm
        Kernel width ``sigma_l`` (support radius): ``u_l`` vanishes farther
        than ``width`` from every centre.

    Notes
    -----
    The arrays are copied and made read-only, so a level (and every warp
    holding it) is immutable.  The neighbour grid of the centres
    (:attr:`grid`) is built on first use and reused by every evaluation.
    """

    centres: np.ndarray
    coeffs: np.ndarray
    width: float

    def __post_init__(self) -> None:
        centres = _as_level_array("centres", self.centres)
        coeffs = _as_level_array("coeffs", self.coeffs)
        if coeffs.shape != centres.shape:
            raise ValueError(
                f"Expected `coeffs` of the same shape as `centres` {centres.shape}, got {coeffs.shape}."
            )
        try:
            width = float(self.width)
        except (TypeError, ValueError):
            raise ValueError(f"Expected a positive finite `width` in mm, got {self.width!r}.") from None
        if not (np.isfinite(width) and width > 0):
            raise ValueError(f"Expected a positive finite `width` in mm, got {width}.")
        object.__setattr__(self, "centres", centres)
        object.__setattr__(self, "coeffs", coeffs)
        object.__setattr__(self, "width", width)

    @property
    def dim(self) -> int:
        """Number of spatial dimensions D."""
        return int(self.centres.shape[1])

    def __len__(self) -> int:
        """Number of centres M."""
        return int(self.centres.shape[0])

    @cached_property
    def grid(self) -> CellGrid:
        """The centres binned for radius-``width`` queries (built on first use)."""
        if len(self) == 0:
            raise ValueError("A level without centres has no `grid`.")
        return CellGrid.build(self.centres, self.width)

    @property
    def is_zero(self) -> bool:
        """Whether this level displaces no point (no centres or all ``coeffs`` zero)."""
        return not np.any(self.coeffs)

    def __repr__(self) -> str:
        return f"WarpLevel(width={self.width:g} mm, centres={len(self)}, dim={self.dim})"


def _check_chunk(chunk: int | None) -> int:
    if chunk is None:
        return DEFAULT_CHUNK
    if isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise ValueError(f"Expected a positive integer `chunk`, got {chunk!r}.")
    return int(chunk)


def _check_order(order: int) -> int:
    if order not in (0, 1):
        raise ValueError(f"Expected `order` in (0, 1), got {order!r}.")
    return int(order)


def _normalise_settings(settings: Mapping[str, Any] | None) -> str:
    """The JSON text of ``settings`` (a mapping; ``None`` means ``{}``)."""
    if settings is None:
        settings = {}
    if not isinstance(settings, Mapping):
        raise ValueError(f"Expected `settings` to be a dict, got {type(settings).__name__}.")
    try:
        return json.dumps(dict(settings), allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"Expected JSON-serialisable `settings`: {exc}.") from None


def _check_linear(linear: Any, dim: int) -> LinearMap:
    """``linear`` as a LinearMap of dimension ``dim`` (``None``: the identity)."""
    if linear is None:
        return LinearMap.identity(dim)
    if not isinstance(linear, LinearMap):
        raise ValueError(f"Expected a LinearMap as `linear`, got {type(linear).__name__}.")
    if linear.dim != dim:
        raise ValueError(f"Expected a `linear` map of dimension {dim}, got D={linear.dim}.")
    return linear


class _PointMap:
    """``__call__``, ``displacement`` and ``jacobian`` of a map, from its ``evaluate``."""

    def __call__(
        self, points: np.ndarray, *, chunk: int | None = None, progress: ProgressCallback | None = None
    ) -> np.ndarray:
        """The map at ``points``, (N, D) mm; see ``evaluate``."""
        return self.evaluate(points, order=0, chunk=chunk, progress=progress)[0]

    def displacement(
        self, points: np.ndarray, *, chunk: int | None = None, progress: ProgressCallback | None = None
    ) -> np.ndarray:
        """``u(points) = tau(points) - points``, (N, D) mm (LPS vectors)."""
        points = check_points("points", points, self.dim)
        return self.evaluate(points, order=0, chunk=chunk, progress=progress)[0] - points

    def jacobian(
        self, points: np.ndarray, *, chunk: int | None = None, progress: ProgressCallback | None = None
    ) -> np.ndarray:
        """Analytic Jacobian ``J[n, a, b] = d tau_a / d x_b``, (N, D, D) (chain rule for compositions)."""
        return self.evaluate(points, order=1, chunk=chunk, progress=progress)[1]


#: Warp evaluations of more points than this visit them in spatial order: a warp's kernel sums
#: then run in blocks of nearby queries (the SIMD loops) instead of one neighbour search per
#: query.  The inverse evaluates the warp at tens of thousands of scattered preimages at a time,
#: too few for :data:`~volreg.kernels.grid.SORT_ABOVE` and enough for the sort to pay (the
#: results differ by rounding only).
WARP_SORT_ABOVE = 2048


class KernelWarp(_PointMap):
    """A multi-scale kernel warp ``tau(x) = A x + b + sum_l u_l(x)`` (paper eq. 9).

    Immutable: :meth:`with_level` and :meth:`then` return new warps.  Calling
    the object evaluates ``tau``.

    Parameters
    ----------
    levels : sequence of WarpLevel
        The scales, coarse to fine by convention (the sum does not depend on
        the order).
    dim : {2, 3}
        Number of spatial dimensions D; every level must have it.
    settings : dict, optional
        JSON-serialisable description of how the warp was made (the
        protocol).  Stored as its JSON round trip (tuples become lists, keys
        strings) and saved with the model.
    linear : LinearMap, optional
        The linear part ``x -> A x + b`` (D x D, ``det A > 0``; ``b`` in mm),
        applied to ``x`` beside the kernel sums, which are evaluated at ``x``
        (fixed space).  Default: the identity, and then every result is bit
        for bit that of the warp without a linear part.

    Attributes
    ----------
    levels : tuple of WarpLevel
    dim : int
    linear : LinearMap

    Examples
    --------
    >>> import numpy as np
    >>> lev = WarpLevel(np.zeros((1, 3)), np.array([[0.5, 0.0, 0.0]]), width=10.0)
    >>> warp = KernelWarp([lev], dim=3)
    >>> warp(np.zeros((1, 3)))  # k(0) = 4
    array([[2., 0., 0.]])
    """

    def __init__(
        self,
        levels: Sequence[WarpLevel] = (),
        *,
        dim: int,
        settings: Mapping[str, Any] | None = None,
        linear: LinearMap | None = None,
    ) -> None:
        if isinstance(dim, bool) or not isinstance(dim, (int, np.integer)) or int(dim) not in (2, 3):
            raise ValueError(f"Expected `dim` 2 or 3, got {dim!r}.")
        dim = int(dim)
        levels = tuple(levels)
        for i, lev in enumerate(levels):
            if not isinstance(lev, WarpLevel):
                raise ValueError(f"Expected WarpLevel objects in `levels`, got {type(lev).__name__} at index {i}.")
            if lev.dim != dim:
                raise ValueError(f"Expected `levels` of dimension dim={dim}, level {i} has D={lev.dim}.")
        self._levels = levels
        self._dim = dim
        self._settings_json = _normalise_settings(settings)
        self._linear = _check_linear(linear, dim)

    @classmethod
    def _make(cls, levels: tuple[WarpLevel, ...], dim: int, settings_json: str, linear: LinearMap) -> "KernelWarp":
        """A warp from parts already checked (no validation, no copies)."""
        new = cls.__new__(cls)
        new._levels = levels
        new._dim = dim
        new._settings_json = settings_json
        new._linear = linear
        return new

    # ----------------------------------------------------------------------------------
    # Construction and description

    @classmethod
    def identity(cls, dim: int, *, settings: Mapping[str, Any] | None = None) -> "KernelWarp":
        """The identity warp ``tau(x) = x`` in ``dim`` dimensions (no levels)."""
        return cls((), dim=dim, settings=settings)

    def with_level(self, level: WarpLevel) -> "KernelWarp":
        """A new warp with ``level`` appended (same settings and linear part); ``self`` is unchanged."""
        if not isinstance(level, WarpLevel):
            raise ValueError(f"Expected a WarpLevel as `level`, got {type(level).__name__}.")
        if level.dim != self.dim:
            raise ValueError(f"Expected a `level` of dimension {self.dim}, got D={level.dim}.")
        return KernelWarp._make(self._levels + (level,), self._dim, self._settings_json, self._linear)

    def then(self, linear: LinearMap) -> "KernelWarp":
        """The warp ``x -> linear(self(x))``, as a kernel warp (same centres, widths and settings).

        With ``linear = (A_L, b_L)``: the linear part becomes ``A_L A``,
        ``A_L b + b_L``, and every coefficient ``c_j`` becomes ``A_L c_j``
        (the kernel sums are linear in the coefficients).

        Parameters
        ----------
        linear : LinearMap
            Of dimension :attr:`dim`.

        Returns
        -------
        KernelWarp
            ``self`` itself when ``linear`` is the identity.
        """
        linear = _check_linear(linear, self._dim)
        if linear.is_identity:
            return self
        a = linear.matrix
        levels = tuple(WarpLevel(lev.centres, lev.coeffs @ a.T, lev.width) for lev in self._levels)
        return KernelWarp._make(levels, self._dim, self._settings_json, self._linear.then(linear))

    @property
    def levels(self) -> tuple[WarpLevel, ...]:
        """The scales, in the order they were added."""
        return self._levels

    @property
    def dim(self) -> int:
        """Number of spatial dimensions D."""
        return self._dim

    @property
    def settings(self) -> dict[str, Any]:
        """The settings that produced the warp (a fresh copy on every access)."""
        return json.loads(self._settings_json)

    @property
    def widths(self) -> list[float]:
        """Kernel widths of the levels, mm."""
        return [lev.width for lev in self._levels]

    @property
    def linear(self) -> LinearMap:
        """The linear part ``x -> A x + b`` (the identity when none was given)."""
        return self._linear

    @property
    def is_identity(self) -> bool:
        """Whether ``tau(x) = x`` everywhere (identity linear part; no levels, or all coefficients zero)."""
        return self._linear.is_identity and all(lev.is_zero for lev in self._levels)

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Corners ``(lo, hi)``, each (D,) mm in fixed space, of a box outside which ``tau`` is linear.

        Outside the box ``tau(x) = A x + b`` exactly (:attr:`linear`; ``tau(x) = x``
        without a linear part): it holds every kernel's support, the balls of
        radius ``width`` around the centres.  ``None`` for a warp without centres:
        ``tau`` is then its linear part everywhere.
        """
        levels = [lev for lev in self._levels if len(lev)]
        if not levels:
            return None
        lo = np.min([lev.centres.min(axis=0) - lev.width for lev in levels], axis=0)
        hi = np.max([lev.centres.max(axis=0) + lev.width for lev in levels], axis=0)
        return lo, hi

    def __repr__(self) -> str:
        levels = ", ".join(f"{lev.width:g} mm: {len(lev)}" for lev in self._levels)
        linear = "" if self._linear.is_identity else ", linear"
        return f"KernelWarp(dim={self.dim}, levels=[{levels}]{linear})"

    # ----------------------------------------------------------------------------------
    # Evaluation

    def evaluate(
        self,
        points: np.ndarray,
        *,
        order: int = 1,
        chunk: int | None = None,
        progress: ProgressCallback | None = None,
    ) -> tuple[np.ndarray, ...]:
        """``tau = A x + b + sum_l u_l(x)`` and (if ``order == 1``) its Jacobian at ``points``.

        Parameters
        ----------
        points : (N, D) float ndarray, mm
            Where to evaluate (LPS).
        order : {0, 1}
            0: ``tau`` only; 1: ``tau`` and the Jacobian.
        chunk : int, optional
            Evaluate at most this many points at once (default
            :data:`DEFAULT_CHUNK`), so that temporary memory stays bounded.
            The result does not depend on it beyond rounding (chunks of more than
            :data:`WARP_SORT_ABOVE` points are summed in spatial blocks, ~1e-15 relative).
        progress : callable, optional
            ``progress("evaluate warp", done, total)`` after each chunk, in points.

        Returns
        -------
        tau : (N, D) float ndarray, mm
            ``tau(points)``.
        jacobian : (N, D, D) float ndarray, dimensionless (if ``order == 1``)
            ``jacobian[n, a, b] = d tau_a / d x_b`` at ``points[n]``: ``A`` plus
            the kernel sums' gradients.
        """
        order = _check_order(order)
        chunk = _check_chunk(chunk)
        points = check_points("points", points, self.dim)
        n, dim = points.shape
        # Without a linear part the points are added as they are (no product with I).
        affine = None if self._linear.is_identity else self._linear
        tau = np.empty((n, dim))
        jac = np.empty((n, dim, dim)) if order == 1 else None
        active = [lev for lev in self._levels if not lev.is_zero]
        finest = min((lev.width for lev in active), default=None)
        for s in range(0, n, chunk):
            q = points[s : s + chunk]
            m = len(q)
            perm = spatial_order(q, 0.5 * finest, above=WARP_SORT_ABOVE) if finest is not None else None
            qs = q if perm is None else take_rows(q, perm)
            outs = (np.zeros((m, dim)), np.zeros((m, dim, dim)))[: order + 1]
            for lev in active:
                kernel_sum(qs, lev.grid, lev.coeffs, lev.width, order=order, out=outs)
            if affine is None:
                outs[0][:] += qs
                if order == 1:
                    outs[1][:] += np.eye(dim)
            else:
                outs[0][:] += affine(qs)
                if order == 1:
                    outs[1][:] += affine.matrix
            for o, dest in zip(outs, (tau, jac)):
                if perm is None:
                    dest[s : s + m] = o
                else:
                    dest[s : s + m] = put_rows(o.reshape(m, -1), perm).reshape(o.shape)
            if progress is not None:
                progress("evaluate warp", s + m, n)
        return (tau,) if order == 0 else (tau, jac)

    def compose(self, other: "KernelWarp | ComposedWarp") -> "ComposedWarp":
        """The warp ``x -> other(self(x))``: ``self`` is applied first.

        With the pull-back convention, if ``self`` maps fixed to intermediate
        and ``other`` maps intermediate to moving, the result maps fixed to
        moving.  Its Jacobian is ``J_other(self(x)) @ J_self(x)``.
        """
        return ComposedWarp((self, other))

    # ----------------------------------------------------------------------------------
    # Serialisation

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays describing the model (for ``np.savez``; no pickle needed).

        Returns
        -------
        dict
            ``format`` (``"volreg-kernel-warp"``), ``format_version`` (int),
            ``volreg_version`` and ``settings_json`` (0-d unicode strings),
            ``dim`` (0-d int), ``widths`` ((L,) float, mm), per level ``i``
            ``centres_<i>`` and ``coeffs_<i>`` ((M_i, D) float, mm), and the
            linear part ``linear_matrix`` ((D, D) float) and
            ``linear_translation`` ((D,) float, mm).
        """
        from volreg import __version__

        out: dict[str, np.ndarray] = {
            "format": np.array(FORMAT),
            "format_version": np.array(FORMAT_VERSION, dtype=np.int64),
            "volreg_version": np.array(str(__version__)),
            "settings_json": np.array(self._settings_json),
            "dim": np.array(self.dim, dtype=np.int64),
            "widths": np.array(self.widths, dtype=float).reshape(-1),
            "linear_matrix": np.array(self._linear.matrix, dtype=float),
            "linear_translation": np.array(self._linear.translation, dtype=float),
        }
        for i, lev in enumerate(self._levels):
            out[f"centres_{i}"] = np.asarray(lev.centres)
            out[f"coeffs_{i}"] = np.asarray(lev.coeffs)
        return out

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> "KernelWarp":
        """Rebuild a warp from :meth:`to_arrays` output (or an opened ``.npz``).

        Arrays of format version 1 (no linear entries) give the identity linear part.

        Raises
        ------
        ValueError
            If the arrays do not describe a kernel warp of a format version
            this volreg reads; the message says what is wrong.
        """
        try:
            return _parse(arrays)
        except _FormatError as exc:
            raise ValueError(f"Expected the arrays of a volreg kernel warp: {exc}.") from None

    def save(self, path: str | os.PathLike[str], *, force: bool = False) -> None:
        """Write the model to ``path`` as a compressed ``.npz`` (no pickle).

        The file is written atomically (a temporary file renamed into place)
        and under exactly the given name (numpy's habit of appending ``.npz``
        does not apply); ``.npz`` is the conventional suffix.

        Parameters
        ----------
        path : path-like
        force : bool, default False
            Whether an existing ``path`` may be replaced.

        Raises
        ------
        volreg.io.VolregIOError
            If ``path`` exists and ``force`` is false, or cannot be written.
        """
        from volreg.io import atomic_output

        arrays = self.to_arrays()
        with atomic_output(path, force=force) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "KernelWarp":
        """Read a model written by :meth:`save`.

        Raises
        ------
        volreg.io.VolregIOError
            (a ``ValueError``) with one line naming the file and the problem,
            if it does not exist or is not a valid kernel warp.
        """
        from volreg.io import VolregIOError

        name = os.fspath(path)
        if not os.path.exists(name):
            raise VolregIOError(f"Warp model `{name}` does not exist.")
        if os.path.isdir(name):
            raise VolregIOError(f"Warp model `{name}` is a directory; expected a .npz file.")
        # Open the file here (not by name in np.load, which leaks the handle when
        # the archive is corrupt) so that it is closed on every path.
        try:
            fh = open(name, "rb")
        except PermissionError:
            raise VolregIOError(f"Warp model `{name}` is not readable (permission denied); expected a file you can read.") from None
        except OSError as exc:
            raise VolregIOError(f"Warp model `{name}` cannot be opened: {_one_line(exc)}.") from None
        with fh:
            from volreg.io._guards import check_npz

            check_npz(fh, name, "Warp model")
            try:
                data = np.load(fh, allow_pickle=False)
            except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
                # numpy falls back to unpickling non-zip bytes and, refused, suggests allow_pickle: never do that
                reason = "not a zip archive" if "pickle" in str(exc) else _one_line(exc)
                raise VolregIOError(
                    f"Warp model `{name}` is not a readable .npz file: {reason}."
                ) from None
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise VolregIOError(
                    f"Warp model `{name}` is not a volreg kernel warp: expected a .npz archive, found a single array."
                )
            with data:
                try:
                    return _parse(data)
                except _FormatError as exc:
                    raise VolregIOError(
                        f"Warp model `{name}` is not a valid volreg kernel warp: {exc}."
                    ) from None


def _one_line(exc: BaseException) -> str:
    return exception_text(exc).rstrip(".")


class _FormatError(Exception):
    """A saved warp's arrays are inconsistent; the message says how (one line, no full stop)."""


def _get(arrays: Mapping[str, np.ndarray], key: str) -> np.ndarray:
    if key not in arrays:
        raise _FormatError(f"missing entry `{key}`")
    try:
        return np.asarray(arrays[key])
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:  # object arrays, damaged members
        raise _FormatError(f"entry `{key}` cannot be read ({_one_line(exc)})") from None


def _get_string(arrays: Mapping[str, np.ndarray], key: str) -> str:
    value = _get(arrays, key)
    if value.shape != () or value.dtype.kind != "U":
        raise _FormatError(f"entry `{key}` should be a 0-d unicode string, got dtype {value.dtype} shape {value.shape}")
    return str(value)


def _get_int(arrays: Mapping[str, np.ndarray], key: str) -> int:
    value = _get(arrays, key)
    if value.shape != () or value.dtype.kind not in "iu":
        raise _FormatError(f"entry `{key}` should be a 0-d integer, got dtype {value.dtype} shape {value.shape}")
    return int(value)


def _parse(arrays: Mapping[str, np.ndarray]) -> KernelWarp:
    """Validate :meth:`KernelWarp.to_arrays`-style arrays and build the warp."""
    from volreg.io.documents import parse_json  # volreg.io loads SimpleITK: only when a warp is read

    if "format" not in arrays:
        raise _FormatError("no `format` entry (not written by KernelWarp.save)")
    fmt = _get_string(arrays, "format")
    if fmt != FORMAT:
        raise _FormatError(f"`format` is {excerpt(fmt)}, expected {FORMAT!r}")
    version = _get_int(arrays, "format_version")
    if not 1 <= version <= FORMAT_VERSION:
        raise _FormatError(f"format_version {version} is not supported (this volreg reads 1 to {FORMAT_VERSION})")
    _get_string(arrays, "volreg_version")
    settings_text = _get_string(arrays, "settings_json")
    try:
        settings = parse_json(settings_text, "`settings_json`", error=lambda message: _FormatError(message.rstrip(".")))
    except ValueError as exc:
        raise _FormatError(f"`settings_json` is not valid JSON ({_one_line(exc)})") from None
    if not isinstance(settings, dict):
        raise _FormatError(f"`settings_json` should hold a JSON object, got {type(settings).__name__}")
    dim = _get_int(arrays, "dim")
    if dim not in (2, 3):
        raise _FormatError(f"`dim` is {dim}, expected 2 or 3")
    widths = _get(arrays, "widths")
    if widths.ndim != 1 or widths.dtype.kind not in "fiu":
        raise _FormatError(f"`widths` should be a 1-d float array, got dtype {widths.dtype} shape {widths.shape}")
    if not np.all(np.isfinite(widths) & (widths > 0)):
        raise _FormatError("`widths` should be positive and finite")
    levels = []
    for i, width in enumerate(widths):
        centres = _get(arrays, f"centres_{i}")
        coeffs = _get(arrays, f"coeffs_{i}")
        for key, arr in ((f"centres_{i}", centres), (f"coeffs_{i}", coeffs)):
            if arr.ndim != 2 or arr.shape[1] != dim or arr.dtype.kind not in "fiu":
                raise _FormatError(
                    f"`{key}` should be a float array of shape (M, {dim}), got dtype {arr.dtype} shape {arr.shape}"
                )
            if not np.all(np.isfinite(arr)):
                raise _FormatError(f"`{key}` holds NaN or Inf")
        if centres.shape != coeffs.shape:
            raise _FormatError(
                f"`centres_{i}` and `coeffs_{i}` should have the same shape, got {centres.shape} and {coeffs.shape}"
            )
        levels.append(WarpLevel(centres, coeffs, float(width)))
    extra = sorted(
        k for k in arrays if (k.startswith("centres_") or k.startswith("coeffs_"))
        and k not in {f"{p}_{i}" for p in ("centres", "coeffs") for i in range(len(widths))}
    )
    if extra:
        raise _FormatError(f"{len(widths)} widths but also entries {', '.join(extra)}")
    return KernelWarp(levels, dim=dim, settings=settings, linear=_parse_linear(arrays, version, dim))


_LINEAR_KEYS = ("linear_matrix", "linear_translation")


def _parse_linear(arrays: Mapping[str, np.ndarray], version: int, dim: int) -> LinearMap | None:
    """The linear part of saved arrays: required from format version 2, absent before."""
    if version < 2:
        present = [k for k in _LINEAR_KEYS if k in arrays]
        if present:
            raise _FormatError(f"format_version {version} has no linear part, but the file holds `{present[0]}`")
        return None
    matrix = _get(arrays, "linear_matrix")
    translation = _get(arrays, "linear_translation")
    for key, arr, shape in (("linear_matrix", matrix, (dim, dim)), ("linear_translation", translation, (dim,))):
        if arr.shape != shape or arr.dtype.kind not in "fiu":
            raise _FormatError(
                f"`{key}` should be a float array of shape {shape}, got dtype {arr.dtype} shape {arr.shape}"
            )
        if not np.all(np.isfinite(arr)):
            raise _FormatError(f"`{key}` holds NaN or Inf")
    det = float(np.linalg.det(matrix.astype(float)))
    if not det > 0:
        raise _FormatError(f"`linear_matrix` should have a positive determinant, got {det:.3g}")
    try:
        return LinearMap(matrix, translation)
    except ValueError as exc:
        raise _FormatError(f"`linear_matrix` and `linear_translation` are not a linear map ({_one_line(exc)})") from None


AnyWarp = Union[KernelWarp, "ComposedWarp"]

Box = tuple[np.ndarray, np.ndarray]


def _box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The 2^D corners of the box ``[lo, hi]``, (2^D, D)."""
    dim = len(lo)
    pick = np.array(list(np.ndindex(*([2] * dim))), dtype=bool)
    return np.where(pick, hi, lo)


def _box_through(box: Box, linear: LinearMap) -> Box:
    """The bounding box of ``linear`` applied to the box ``[lo, hi]`` (an infinite box stays infinite)."""
    lo, hi = (np.asarray(c, dtype=float) for c in box)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return np.full(len(lo), -np.inf), np.full(len(lo), np.inf)
    corners = linear(_box_corners(lo, hi))
    return corners.min(axis=0), corners.max(axis=0)


def linear_outside(warps: Sequence[Any], *, dim: int | None = None) -> tuple[Box | None, LinearMap]:
    """Where the chain ``x -> w_k(... w_2(w_1(x)))`` is linear, and that linear map.

    Each map ``w_i`` is linear outside its box ``B_i`` (``w_i.bounds()``) and equals
    its linear part ``L_i`` there (``w_i.linear``; the identity for a map without
    one).  A point ``x`` outside ``B_1`` goes to ``L_1 x``; outside the preimage of
    ``B_2`` under ``L_1`` as well, on to ``L_2 L_1 x``; and so on.  So the chain is
    ``L_k ... L_1`` outside the union of the bounding boxes of
    ``(L_{i-1} ... L_1)^-1 (B_i)``.  Without linear parts this is the union of the
    boxes themselves, exactly.

    Parameters
    ----------
    warps : sequence of maps
        In the order they are applied: KernelWarp, ComposedWarp, InverseWarp, or
        any map; a ``bounds()`` returning ``None`` means linear everywhere, a map
        without ``bounds`` is taken to be non-linear everywhere.
    dim : int, optional
        Number of spatial dimensions D; default the first map's ``dim``.

    Returns
    -------
    box : ((D,), (D,)) float ndarrays, mm, or None
        Corners ``(lo, hi)`` in the space of ``w_1``'s inputs, infinite when some map
        has no ``bounds``; ``None`` when the chain is linear everywhere.
    linear : LinearMap
        ``L_k ... L_1``, what the chain is outside ``box``.
    """
    warps = list(warps)
    if not warps:
        raise ValueError("Expected at least one map in `warps`.")
    dim = int(warps[0].dim if dim is None else dim)
    before = LinearMap.identity(dim)  # L_{i-1} ... L_1
    boxes: list[Box] = []
    for w in warps:
        if not hasattr(w, "bounds"):
            boxes.append((np.full(dim, -np.inf), np.full(dim, np.inf)))
        else:
            box = w.bounds()
            if box is not None:
                boxes.append(box if before.is_identity else _box_through(box, before.inverse()))
        linear = getattr(w, "linear", None)
        if linear is not None and not linear.is_identity:
            before = linear if before.is_identity else before.then(linear)
    if not boxes:
        return None, before
    return (np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)), before


class ComposedWarp(_PointMap):
    """A chain of warps applied one after another: ``x -> w_k(... w_2(w_1(x)))``.

    Made by :meth:`KernelWarp.compose`: ``a.compose(b)`` is ``x -> b(a(x))``
    (``a`` first).  Nested compositions are flattened.

    Parameters
    ----------
    warps : sequence of KernelWarp or ComposedWarp
        In the order they are applied; all of the same dimension.
    """

    def __init__(self, warps: Sequence[AnyWarp]) -> None:
        flat: list[KernelWarp] = []
        for i, w in enumerate(warps):
            if isinstance(w, ComposedWarp):
                flat.extend(w.warps)
            elif isinstance(w, KernelWarp):
                flat.append(w)
            else:
                raise ValueError(
                    f"Expected KernelWarp or ComposedWarp objects in `warps`, got {type(w).__name__} at index {i}."
                )
        if not flat:
            raise ValueError("Expected at least one warp in `warps`.")
        dims = {w.dim for w in flat}
        if len(dims) != 1:
            raise ValueError(f"Expected `warps` of one dimension, got dimensions {sorted(dims)}.")
        self._warps = tuple(flat)
        self._dim = flat[0].dim

    @property
    def warps(self) -> tuple[KernelWarp, ...]:
        """The kernel warps, in the order they are applied."""
        return self._warps

    @property
    def dim(self) -> int:
        """Number of spatial dimensions D."""
        return self._dim

    @property
    def is_identity(self) -> bool:
        """Whether every warp in the chain is the identity."""
        return all(w.is_identity for w in self._warps)

    @property
    def linear(self) -> LinearMap:
        """The composition of the warps' linear parts: the chain outside :meth:`bounds`."""
        return linear_outside(self._warps)[1]

    def bounds(self) -> Box | None:
        """Corners ``(lo, hi)``, each (D,) mm, of a box outside which the chain is :attr:`linear`.

        See :func:`linear_outside`; ``None`` when no warp has centres.
        """
        return linear_outside(self._warps)[0]

    def __repr__(self) -> str:
        return f"ComposedWarp({', '.join(map(repr, self._warps))})"

    def evaluate(
        self,
        points: np.ndarray,
        *,
        order: int = 1,
        chunk: int | None = None,
        progress: ProgressCallback | None = None,
    ) -> tuple[np.ndarray, ...]:
        """The composed map and (if ``order == 1``) its Jacobian by the chain rule.

        ``J = J_k(x_{k-1}) @ ... @ J_2(x_1) @ J_1(x)`` with ``x_i`` the point
        after the first ``i`` warps.  Parameters and returns as in
        :meth:`KernelWarp.evaluate`.
        """
        order = _check_order(order)
        chunk = _check_chunk(chunk)
        points = check_points("points", points, self.dim)
        n, dim = points.shape
        out = np.empty((n, dim))
        jac = np.empty((n, dim, dim)) if order == 1 else None
        for s in range(0, n, chunk):
            x = points[s : s + chunk]
            j = None
            for w in self._warps:
                res = w.evaluate(x, order=order, chunk=chunk)
                x = res[0]
                if order == 1:
                    j = res[1] if j is None else np.matmul(res[1], j)
            out[s : s + len(x)] = x
            if order == 1:
                jac[s : s + len(x)] = j
            if progress is not None:
                progress("evaluate warp", s + len(x), n)
        return (out,) if order == 0 else (out, jac)

    def compose(self, other: AnyWarp) -> "ComposedWarp":
        """``x -> other(self(x))`` (``self`` first), flattened."""
        return ComposedWarp((self, other))
