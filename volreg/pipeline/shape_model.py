"""A linear statistical model of shapes in correspondence: generalised Procrustes and PCA.

Every shape is the same ``P`` points in ``D`` dimensions (template boundary vertices carried into
each subject, or template voxel centres carried by each subject's warp), so shape ``i`` is a
vector ``x_i`` of ``P * D`` coordinates (mm).  The model is

    x = mean + sum_k  b_k * sqrt(variance_k) * mode_k,

with unit-length ``mode_k`` (over all ``P * D`` coordinates), ``variance_k`` the variance of the
training shapes along it (mm^2, denominator ``N - 1``) and ``b_k`` the coefficient in standard
deviations: the training shapes' coefficients (``scores``) have unit variance.

The PCA goes through the ``N x N`` Gram matrix of the centred shapes (its eigenvectors ``v_k`` and
eigenvalues ``w_k`` give ``mode_k = X_c^T v_k / sqrt(w_k)``), so its cost is ``O(N^2 P D)`` and its
memory the data itself (``4 N P D`` bytes in float32) plus ``8 K P D`` for ``K`` modes: a model
of hundreds of subjects never forms the ``PD x PD`` covariance.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field

import numpy as np

from volreg.errors import UsageError

__all__ = ["ALIGNMENTS", "POINT_MODEL_FORMAT", "ShapeModel", "fit_similarity", "procrustes", "gram_matrix"]

#: The alignments :func:`procrustes` knows: none, rotation and translation, and with a scale.
ALIGNMENTS = ("none", "rigid", "similarity")
#: The ``format`` member of a saved :class:`ShapeModel`.
POINT_MODEL_FORMAT = "volreg-point-shape-model-1"
#: Columns of the data matrix processed at a time (bounds the float64 working copy).
_CHUNK = 1 << 18


def fit_similarity(source: np.ndarray, target: np.ndarray, kind: str) -> np.ndarray:
    """The least-squares map of ``kind`` taking ``source`` onto ``target`` (Kabsch / Umeyama).

    Parameters
    ----------
    source, target : (P, D) float arrays, mm
        Corresponding points.
    kind : {"none", "rigid", "similarity"}
        ``"rigid"``: rotation (never a reflection) and translation; ``"similarity"``: with a
        uniform scale as well; ``"none"``: the identity.

    Returns
    -------
    (D + 1, D + 1) float array
        Homogeneous matrix ``T`` with ``target ~ source @ T[:D, :D].T + T[:D, D]``.
    """
    d = source.shape[1]
    out = np.eye(d + 1)
    if kind == "none":
        return out
    a = np.asarray(source, float)
    b = np.asarray(target, float)
    ca, cb = a.mean(0), b.mean(0)
    a0, b0 = a - ca, b - cb
    u, s, vt = np.linalg.svd(a0.T @ b0)
    flip = np.ones(d)
    flip[-1] = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = (vt.T * flip) @ u.T
    scale = 1.0
    if kind == "similarity":
        norm = float((a0**2).sum())
        scale = float((s * flip).sum()) / norm if norm > 0 else 1.0
    out[:d, :d] = scale * rotation
    out[:d, d] = cb - out[:d, :d] @ ca
    return out


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    d = points.shape[-1]
    return points @ matrix[:d, :d].T + matrix[:d, d]


def procrustes(shapes: np.ndarray, kind: str, reference: np.ndarray | None = None, *, iterations: int = 20,
               tol: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Generalised Procrustes analysis: every shape aligned onto the shapes' mean, in ``reference``'s frame.

    Each round aligns every shape onto the current mean (:func:`fit_similarity`), averages them,
    and aligns that average onto ``reference`` (so the model keeps the reference's position,
    orientation and, with ``"similarity"``, size), until the mean moves by less than ``tol``
    (mm, RMS) or after ``iterations`` rounds.

    Parameters
    ----------
    shapes : (N, P, D) float array, mm
    kind : {"none", "rigid", "similarity"}
    reference : (P, D) float array, optional, mm
        The frame of the result (default: the first mean, the unaligned shapes' average).

    Returns
    -------
    aligned : (N, P, D) float array, mm
        In the dtype of ``shapes`` (float32 stays float32).
    transforms : (N, D + 1, D + 1) float array
        ``aligned[i] = shapes[i] @ T[:D, :D].T + T[:D, D]`` with ``T = transforms[i]``.
    """
    if kind not in ALIGNMENTS:
        raise UsageError(f"--align {kind!r}: expected one of {', '.join(ALIGNMENTS)}.")
    shapes = np.asarray(shapes)
    n, _, d = shapes.shape
    transforms = np.repeat(np.eye(d + 1)[None], n, axis=0)
    if kind == "none":
        return shapes, transforms
    frame = np.asarray(shapes.mean(0), float) if reference is None else np.asarray(reference, float)
    mean = frame
    for _ in range(iterations):  # a running sum: no aligned copy of the cohort until the end
        average = np.zeros_like(frame)
        for s in shapes:
            average += _apply(fit_similarity(s, mean, kind), s)
        average /= n
        back = fit_similarity(average, frame, kind)  # the average in the frame of the reference
        new = _apply(back, average)
        moved = float(np.sqrt(((new - mean) ** 2).sum(1).mean()))
        mean = new
        if moved < tol:
            break
    transforms = np.stack([fit_similarity(s, mean, kind) for s in shapes])
    aligned = np.empty_like(shapes)
    for i, (t, s) in enumerate(zip(transforms, shapes)):
        aligned[i] = _apply(t, s)
    return aligned, transforms


def gram_matrix(data: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """``(X - mean)(X - mean)^T`` of an ``(N, F)`` data matrix, in float64, a block of columns at a time.

    Returns
    -------
    (N, N) float64 array, mm^2
    """
    n, f = data.shape
    gram = np.zeros((n, n))
    for s in range(0, f, _CHUNK):
        block = np.asarray(data[:, s:s + _CHUNK], float) - mean[s:s + _CHUNK]
        gram += block @ block.T
    return gram


def _principal(gram: np.ndarray, cap: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The Gram matrix's eigenvalues (descending, positive ones only, at most ``cap``) and eigenvectors."""
    w, v = np.linalg.eigh(gram)
    order = np.argsort(w)[::-1]
    w, v = w[order], v[:, order]
    keep = w > max(float(w[0]), 0.0) * 1e-10 if len(w) else np.zeros(0, bool)
    k = int(keep.sum()) if cap is None else min(int(keep.sum()), cap)
    return w[:k], v[:, :k]


@dataclass
class ShapeModel:
    """A PCA model of ``N`` shapes of ``P`` corresponding points in ``D`` dimensions (the module notes).

    Attributes
    ----------
    mean : (P, D) float array, mm
    modes : (K, P, D) float array
        Unit-length principal directions, leading first.
    variances : (K,) float array, mm^2
        The training shapes' variance along each mode (denominator ``N - 1``).
    scores : (N, K) float array
        Each training shape's coefficients, in standard deviations of its mode.
    ids : list of str
        The training shapes' names, in the rows' order.
    total_variance : float, mm^2
        The training shapes' whole variance (the sum over every mode, kept or not).
    align : str
        The Procrustes alignment the shapes had before the PCA.
    transforms : (N, D + 1, D + 1) float array
        Each training shape's alignment onto the model's frame (identity for ``"none"``).
    aligned : (N, P, D) array, optional
        After :meth:`fit`, the training shapes in the model's frame, in their dtype (not saved).
    """

    mean: np.ndarray
    modes: np.ndarray
    variances: np.ndarray
    scores: np.ndarray
    ids: list[str]
    total_variance: float
    align: str = "none"
    transforms: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))
    aligned: np.ndarray | None = field(default=None, repr=False)

    @classmethod
    def fit(cls, shapes: np.ndarray, *, ids=None, align: str = "none", modes: int | None = None,
            reference: np.ndarray | None = None) -> "ShapeModel":
        """Fit the model to shapes in correspondence.

        Parameters
        ----------
        shapes : (N, P, D) float array, mm
            ``N >= 2`` shapes; float32 is kept as it is (half the memory).
        ids : sequence of str, optional
            Default ``"0", "1", ...``.
        align : {"none", "rigid", "similarity"}
            Generalised Procrustes alignment first (:func:`procrustes`).
        modes : int, optional
            At most this many modes (default ``N - 1``, the most ``N`` shapes have).
        reference : (P, D) float array, optional, mm
            The frame the aligned shapes are put in (e.g. the template's own points).

        Returns
        -------
        ShapeModel
        """
        shapes = np.asarray(shapes)
        if shapes.ndim != 3 or shapes.shape[0] < 2 or shapes.shape[1] < 1:
            raise UsageError(f"Expected `shapes` as an (N, P, D) array of N >= 2 shapes, got shape {shapes.shape}.")
        if modes is not None and (not isinstance(modes, numbers.Integral) or isinstance(modes, bool) or modes < 1):
            raise UsageError(f"--modes {modes!r}: expected a positive integer.")
        modes = None if modes is None else int(modes)
        n, p, d = shapes.shape
        ids = [str(i) for i in range(n)] if ids is None else [str(i) for i in ids]
        if len(ids) != n:
            raise UsageError(f"Expected {n} `ids`, one per shape, got {len(ids)}.")
        aligned, transforms = procrustes(shapes, align, reference)
        data = aligned.reshape(n, p * d)
        mean = data.mean(0, dtype=float)
        gram = gram_matrix(data, mean)
        w, v = _principal(gram, n - 1 if modes is None else min(modes, n - 1))
        vectors = np.zeros((len(w), p * d))
        for s in range(0, p * d, _CHUNK):
            vectors[:, s:s + _CHUNK] = v.T @ (np.asarray(data[:, s:s + _CHUNK], float) - mean[s:s + _CHUNK])
        vectors /= np.sqrt(w)[:, None]
        scores = v * np.sqrt(n - 1)
        # a sign that does not depend on the eigensolver: each mode's largest coordinate positive
        sign = np.sign(vectors[np.arange(len(w)), np.abs(vectors).argmax(1)]) if len(w) else np.ones(0)
        sign[sign == 0] = 1.0
        vectors *= sign[:, None]
        scores = scores * sign
        model = cls(mean.reshape(p, d), vectors.reshape(len(w), p, d), w / (n - 1), scores, ids,
                    float(np.trace(gram)) / (n - 1), align, transforms)
        model.aligned = aligned
        return model

    # ----------------------------------------------------------------------------- using it

    @property
    def n_modes(self) -> int:
        """``K``, the number of modes kept."""
        return len(self.variances)

    def check_coefficients(self, coefficients) -> np.ndarray:
        """``coefficients`` as an (M,) float array, M <= K; a bad one refused (``UsageError`` naming --coefficients)."""
        b = np.atleast_1d(np.asarray(coefficients, float))
        if b.ndim != 1 or len(b) > self.n_modes or not np.isfinite(b).all():
            raise UsageError(f"--coefficients {np.asarray(coefficients).tolist()!r}: expected at most {self.n_modes} "
                             "finite numbers (standard deviations of the leading modes).")
        return b

    def sample(self, coefficients) -> np.ndarray:
        """The shape ``mean + sum_k b_k sqrt(variance_k) mode_k``.

        Parameters
        ----------
        coefficients : (M,) array-like, standard deviations
            For the leading ``M <= K`` modes; the others are 0.

        Returns
        -------
        (P, D) float array, mm
        """
        b = self.check_coefficients(coefficients)
        m = len(b)
        return self.mean + np.tensordot(b * np.sqrt(self.variances[:m]), self.modes[:m], axes=1)

    def project(self, shape: np.ndarray, modes: int | None = None) -> np.ndarray:
        """A shape's coefficients (standard deviations) on the leading ``modes`` (default all).

        ``shape`` is taken in the model's frame (already aligned).

        Returns
        -------
        (M,) float array
        """
        m = self.n_modes if modes is None else min(int(modes), self.n_modes)
        offset = (np.asarray(shape, float) - self.mean).reshape(-1)
        return self.modes[:m].reshape(m, -1) @ offset / np.sqrt(self.variances[:m])

    def reconstruct(self, shape: np.ndarray, modes: int | None = None) -> np.ndarray:
        """``shape`` (in the model's frame) projected onto the leading ``modes``: (P, D) mm."""
        return self.sample(self.project(shape, modes))

    # ----------------------------------------------------------------------------- files

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The model's arrays (ids as a fixed-width string array, the unit-length modes in float32):
        what :meth:`save` writes."""
        return {"mean": self.mean, "modes": self.modes.astype(np.float32), "variances": self.variances, "scores": self.scores,
                "ids": np.array(self.ids, dtype=str), "total_variance": np.array(self.total_variance),
                "align": np.array(self.align), "transforms": self.transforms}

    @classmethod
    def from_arrays(cls, arrays) -> "ShapeModel":
        """The model of :meth:`to_arrays`' arrays; ``ValueError`` where they do not agree in size."""
        mean = np.asarray(arrays["mean"], float)
        modes = np.asarray(arrays["modes"], float)
        variances = np.asarray(arrays["variances"], float)
        scores = np.asarray(arrays["scores"], float)
        ids = [str(i) for i in np.asarray(arrays["ids"]).reshape(-1)]
        if mean.ndim != 2 or modes.shape[1:] != mean.shape or variances.shape != (len(modes),) \
                or scores.shape != (len(ids), len(modes)):
            raise ValueError("the mean, modes, variances, scores and ids do not agree in size")
        return cls(mean, modes, variances, scores, ids, float(arrays["total_variance"]), str(arrays["align"]),
                   np.asarray(arrays["transforms"], float))

    def save(self, path, *, force: bool = False) -> None:
        """Write the model to ``path`` (``.npz`` with format ``volreg-point-shape-model-1``, no pickle), atomically."""
        from volreg.io.archives import write_arrays

        write_arrays(self.to_arrays(), path, format=POINT_MODEL_FORMAT, force=force)

    @classmethod
    def load(cls, path) -> "ShapeModel":
        """Read a model :meth:`save` wrote (``VolregIOError`` in one line if it is not one)."""
        from volreg.errors import VolregIOError
        from volreg.io.archives import read_arrays

        arrays = read_arrays(path, "Shape model", POINT_MODEL_FORMAT)
        try:
            return cls.from_arrays(arrays)
        except (KeyError, ValueError, TypeError) as exc:
            raise VolregIOError(f"Shape model `{path}` is not a complete shape model: {str(exc)[:80]}.") from None

    def fractions(self) -> np.ndarray:
        """Each mode's share of the training shapes' whole variance: (K,)."""
        return self.variances / self.total_variance if self.total_variance > 0 else np.zeros(self.n_modes)
