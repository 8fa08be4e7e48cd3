"""Every setting of a registration, with its default, in one place.

A :class:`Protocol` holds one :class:`SurfaceSettings` (how label surfaces and their
implicit surfaces are made) and one :class:`WarpSettings` (the warp fit).  The
presets in ``protocols/*.toml`` are data read into these classes
(:func:`volreg.io.protocol.load_protocol`); a test checks that ``default.toml``
states exactly these defaults.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from typing import Any, Mapping

from volreg.errors import ArgumentTypeError, ProtocolError, excerpt

__all__ = ["LINEAR_KINDS", "LinearSettings", "OutputSettings", "Protocol", "ReviewSettings", "SurfaceSettings", "WarpSettings", "replace_settings", "settings_from_mapping"]


#: The largest weight or length (mm, voxels) a setting may take: far beyond any useful value
#: (the defaults are 100 and 1e5 for the weights, a few mm for the lengths), and far enough
#: below double precision's range that the cost's sums and squares stay finite.
MAX_SETTING = 1e12


def _kind_expected(annotation: str) -> str:
    """How a message names the values a field of this annotation takes."""
    base = annotation.replace(" | None", "")
    kind = {"bool": "true or false", "int": "an integer", "float": "a number", "str": "a string"}.get(base, base)
    return f"{kind} (or None)" if "None" in annotation else kind


def _check_types(settings) -> None:
    """Refuse a field of a settings dataclass whose value is not of the field's type, as the
    protocol files' reader refuses it (:func:`settings_from_mapping`): true and false are not
    numbers here (Python counts them as 1 and 0), nor are numbers true or false.  A numpy number
    is kept as the Python number it holds (so that the settings write back as TOML and JSON).

    Raises
    ------
    ArgumentTypeError
        Naming the field, the kind of value it takes and the value given.
    """
    for f in dataclasses.fields(settings):
        annotation = f.type if isinstance(f.type, str) else f.type.__name__
        value = getattr(settings, f.name)
        base = annotation.replace(" | None", "")
        if value is None:
            ok = "None" in annotation
        elif type(value).__name__ == "bool_":  # numpy's: neither a number nor (for the TOML writer) a bool
            ok = False
        elif isinstance(value, bool):
            ok = base == "bool"
        elif base == "int":
            ok = isinstance(value, numbers.Integral)
        elif base == "float":
            ok = isinstance(value, numbers.Real)
        elif base == "str":
            ok = isinstance(value, str)
        elif base == "bool":
            ok = False  # a number, a string: not true or false
        else:
            continue  # a section of a Protocol: checked by its own class
        if not ok:
            raise ArgumentTypeError(f"Expected `{f.name}` of {type(settings).__name__} to be "
                                    f"{_kind_expected(annotation)}, got {excerpt(value)}.")
        if isinstance(value, numbers.Number) and hasattr(value, "item") and not isinstance(value, (int, float)):
            object.__setattr__(settings, f.name, value.item())  # numpy's float32, int64, ...


@dataclass(frozen=True)
class WarpSettings:
    """Settings of the warp fit (the protocol's warp section).

    Attributes
    ----------
    pad : float, mm, optional
        Padding of the warp volume X around the source surfaces; default 10 % of
        the source diameter.  A wider pad puts signed distances further from the
        surface into the cost (11), which carry more of the shape around each point and
        pin sliding along a bumpy surface; on a smooth one it does not help.
        Resolved by :meth:`resolved`.
    min_width : float, mm, optional
        Finest kernel width; default 1/16 of the source diameter (:meth:`resolved`).
    lambda_loc : float
        Weight of the locational cost (11), per unit of mean cost.
    alpha : float, mm^2
        Weight of the gradient term (4); 0 gives the distance-only cost (3).
    lambda_p : float
        Landmark weight (8).
    neighbourhood : float, mm
        If > 0, the neighbourhood cost (5) over a regular simplex of this radius.
    fraction : float
        Octree boxes stop below ``fraction * width`` (paper: 1/2).
    max_iter : int
        L-BFGS iterations per level.
    tolerance : float
        L-BFGS stops a level when an iteration lowers the objective by less than this
        fraction of it (scipy's ``ftol``).  On the frog demo 1e-6 gave the same endpoint
        error as scipy's default 2.2e-9 (0.611 mm mean, 1.47 mm p95) in 80 instead of 173
        iterations over the 4 levels; 1e-5: 0.611 / 1.47 mm in 55; 1e-4: 0.612 / 1.47 mm in 37.
    lambda_fold : float
        Weight of the fold barrier (not in the paper): ``lambda_fold mean
        max(0, fold_margin - det d tau/dx)^2`` over the samples and their
        octree children, so that L-BFGS keeps the warp orientation-preserving.
        During a level's fit only the points with ``det < fold_margin + FOLD_SLACK``
        carry it; points that end below ``fold_margin`` join them for another fit
        (up to ``FOLD_ROUNDS``), so the result is the barrier's over every point.
    fold_margin : float
        Determinant below which the barrier acts.
    sample_spacing : float, mm, optional
        The locational cost is sampled at the centres of octree boxes of X
        smaller than ``fraction * s``, with ``s = max(sample_spacing,
        min(width / 4, min_width))`` at a level of kernel width ``width``:
        ``sample_spacing`` at every level when it is ``min_width`` or more, and
        where it is finer, only at the levels whose width is below
        ``4 * min_width``; default ``sample_scale * min_width`` (1: the
        finest level's boxes at every level).
    sample_scale : float
        See ``sample_spacing``; cost grows about as ``sample_scale^-2``
        (samples crowd the surfaces).
    band : float, mm, optional
        The locational cost of a feature counts only at samples within this
        distance of its source surface; default half the finest kernel width
        of that feature's ``f1`` (see ``_feature_samples``).
    lambda_consistency : float
        Symmetric option (not in the paper): weight of ``mean_x |tau(x) - t(x)|^2`` over
        the locational-cost samples, where ``t`` is the inverse of a registration in the
        opposite direction (``fit_warp(prior=...)``; ``volreg consistency`` passes the
        forward warp's Newton inverse to the backward fit).  0 = off; ignored when no
        ``prior`` is given.
    robust : float, mm
        If > 0, the distance term uses a pseudo-Huber loss of this scale (not in the
        paper; see :class:`~volreg.warp.objective.LevelObjective`); 0 = squared residuals,
        as in (3).  Implicit surfaces of resampled labels disagree by tens of mm at a
        few samples (seen on thin, fragmented labels), which the squared loss
        lets dominate: on the frog demo (``fast``) the true warp's squared distance
        cost was 14x the fitted warp's, 90 % of it from one label.  Measured there
        (endpoint error, mean mm): 0 -> 2.15, 1 -> 1.37, 0.5 -> 1.28, 0.25 -> 1.24.
    max_folded_fraction : float
        Health check on the output grid (:func:`~volreg.warp.fit.check_folding`): if the warp folds space
        (``det d tau / dx <= 0``) at more than this fraction of the fixed grid's voxels,
        the registration stops with :class:`~volreg.errors.RegistrationDiverged` naming the first level
        that crossed it, instead of writing a folded warp.
    min_det : float
        Last-resort fold guard: after each level, its coefficients are shrunk (by 0.7 at a
        time) until ``det d tau / dx >= min_det`` at every sample point (or, where
        the coarser levels are already below that, until the level makes the
        minimum no worse).
    """

    pad: float | None = None
    min_width: float | None = None
    lambda_loc: float = 100.0
    alpha: float = 10.0
    lambda_p: float = 100.0
    neighbourhood: float = 0.0
    fraction: float = 0.5
    max_iter: int = 200
    tolerance: float = 1e-6
    lambda_fold: float = 1e5
    fold_margin: float = 0.3
    min_det: float = 0.1
    band: float | None = None
    sample_spacing: float | None = None
    sample_scale: float = 1.0
    lambda_consistency: float = 0.0
    max_folded_fraction: float = 0.01
    robust: float = 0.5

    def __post_init__(self) -> None:
        _check_types(self)
        for name in ("lambda_loc", "alpha", "lambda_p", "neighbourhood", "lambda_fold", "fold_margin", "min_det",
                     "lambda_consistency", "robust"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ProtocolError(f"Expected `{name}` >= 0, got {value}.")
            if value > MAX_SETTING:
                raise ProtocolError(f"Expected `{name}` of at most {MAX_SETTING:g}, got {value:g}: beyond, the cost's "
                                 "terms leave double precision (weights of 1e200 gave infinite samples).")
        for name in ("fold_margin", "min_det"):
            if getattr(self, name) >= 1:
                raise ProtocolError(f"Expected `{name}` in [0, 1) (a Jacobian determinant below which the fold guards "
                                 f"act; at 1 or more they would undo every warp that compresses space), got "
                                 f"{getattr(self, name)}.")
        for name in ("pad", "min_width", "band", "sample_spacing"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ProtocolError(f"Expected a positive `{name}` (mm), got {value}.")
        if not (math.isfinite(self.sample_scale) and 0 < self.sample_scale <= 16):
            raise ProtocolError(f"Expected `sample_scale` in (0, 16], got {self.sample_scale}.")
        if not (math.isfinite(self.max_folded_fraction) and 0 <= self.max_folded_fraction <= 1):
            raise ProtocolError(f"Expected `max_folded_fraction` in [0, 1], got {self.max_folded_fraction}.")
        if not 0 < self.fraction <= 1:
            raise ProtocolError(f"Expected `fraction` in (0, 1], got {self.fraction}.")
        if not (math.isfinite(self.tolerance) and 0 < self.tolerance < 1):
            raise ProtocolError(f"Expected `tolerance` in (0, 1), got {self.tolerance}.")
        if self.max_iter < 0:
            raise ProtocolError(f"Expected `max_iter` >= 0, got {self.max_iter}.")

    def resolved(self, diameter: float) -> WarpSettings:
        """These settings with the defaults that depend on the source filled in.

        Parameters
        ----------
        diameter : float, mm
            Diagonal of the bounding box of the source surface points, positive.

        Returns
        -------
        WarpSettings
            ``pad`` defaults to 10 % of ``diameter`` and ``min_width`` to 1/16 of it
            (kernel widths 1/2, 1/4, 1/8, 1/16 of the diameter, paper Section 3.5);
            values already set are kept.
        """
        pad = 0.1 * diameter if self.pad is None else self.pad
        min_width = diameter / 16 if self.min_width is None else self.min_width
        return dataclasses.replace(self, pad=pad, min_width=min_width)


@dataclass(frozen=True)
class SurfaceSettings:
    """How each label's features are made: boundary mesh, kernel implicit surface, voxel distance map.

    Attributes
    ----------
    smoothing : float, voxels
        Gaussian blur of each mask before contouring (largest spacing as unit).
    min_width_voxels : float, voxels
        Finest kernel width of the implicit surfaces.
    implicit_weight : float
        Weight in the locational cost of each label's pair of kernel implicit surfaces (paper
        Section 4, fitted to the boundary meshes); 0 = not fitted.  0 by default: with the voxel
        distance maps alone the whole command is faster, and its endpoint error lower or the
        same on most label pairs (docs/method.md, "Measured and not kept").
    distance_weight : float
        Weight in the locational cost of each label's pair of voxel signed-distance maps
        (:class:`~volreg.features.distance_maps.VoxelDistance`: the paper's signed distance
        function (3)-(4) read from the label's voxels), which also covers labels too small or
        fragmented for a surface.  0 = off (with ``implicit_weight`` 1: the paper's features alone).
    distance_clip : float, voxels
        The voxel signed distances are clipped to +- this, or to ``min_distance_clip`` where
        that is more (:meth:`clip_mm`).
    min_distance_clip : float, mm
        The clip's least value: the features' reach must cover what is left after the
        linear stage, whatever the voxel size.
    distance_scale : float, voxels
        The voxel signed distances are read from each label's mask blurred by a Gaussian of
        this scale (:func:`~volreg.features.distance_maps.blurred_signed_distance`): exact for
        a plane at any orientation, and the same on any grid at least this fine, so that the
        same labels at two resolutions give the same maps.  0 = distances between the voxel
        centres, to the boundary half-way between them (first order; each grid's own bias).
    distance_smoothing : float, voxels
        Gaussian blur of the clipped voxel signed distances.
    resample_finer : bool
        Where every spacing of one volume's grid is larger than every spacing of the other's, read the finer
        volume's distance maps from its labels resampled onto the coarser grid (through the
        linear stage's map; label-preserving, Gaussian-smoothed indicators): both maps then
        come from the same staircase, which a warp would otherwise follow.  The same 30
        labels at 1 mm and 2 mm with no motion moved 0.11 mm on average without it.
    """

    smoothing: float = 1.0
    min_width_voxels: float = 4.0
    implicit_weight: float = 0.0
    distance_weight: float = 3.0
    distance_clip: float = 2.0
    min_distance_clip: float = 4.0
    distance_scale: float = 1.0
    distance_smoothing: float = 0.8
    resample_finer: bool = True

    def __post_init__(self) -> None:
        _check_types(self)
        if not (math.isfinite(self.smoothing) and 0 <= self.smoothing <= 10):
            raise ProtocolError(f"Expected `smoothing` in [0, 10] voxels, got {self.smoothing}.")
        if not (math.isfinite(self.min_width_voxels) and self.min_width_voxels > 0):
            raise ProtocolError(f"Expected a positive `min_width_voxels`, got {self.min_width_voxels}.")
        if not (math.isfinite(self.implicit_weight) and self.implicit_weight >= 0):
            raise ProtocolError(f"Expected `implicit_weight` >= 0, got {self.implicit_weight}.")
        if not (math.isfinite(self.distance_weight) and self.distance_weight >= 0):
            raise ProtocolError(f"Expected `distance_weight` >= 0, got {self.distance_weight}.")
        if self.implicit_weight == 0 and self.distance_weight == 0:
            raise ProtocolError("Expected `implicit_weight` or `distance_weight` > 0, got both 0: no feature would "
                             "drive the warp.")
        if not (math.isfinite(self.distance_clip) and 0 < self.distance_clip <= MAX_SETTING):
            raise ProtocolError(f"Expected a positive `distance_clip` (voxels) of at most {MAX_SETTING:g}, got "
                             f"{self.distance_clip:g}.")
        if not (math.isfinite(self.min_distance_clip) and 0 <= self.min_distance_clip <= MAX_SETTING):
            raise ProtocolError(f"Expected `min_distance_clip` >= 0 (mm) and at most {MAX_SETTING:g}, got "
                             f"{self.min_distance_clip:g}.")
        if not (math.isfinite(self.distance_scale) and 0 <= self.distance_scale <= 10):
            raise ProtocolError(f"Expected `distance_scale` in [0, 10] voxels, got {self.distance_scale}.")
        if not (math.isfinite(self.distance_smoothing) and 0 <= self.distance_smoothing <= 10):
            raise ProtocolError(f"Expected `distance_smoothing` in [0, 10] voxels, got {self.distance_smoothing}.")

    def clip_mm(self, unit: float) -> float:
        """The voxel distance maps' clip, mm: ``distance_clip`` voxels of ``unit`` mm, at least
        ``min_distance_clip``.

        2 voxels and 4 mm: on the label pairs of ``bench_speed.py`` and ``bench_pose.py`` (grids of
        1-3 mm) 3 voxels and 2 voxels each did worse where the clip came out further from 4-6 mm
        (docs/method.md, the voxel signed-distance maps).
        """
        return max(self.distance_clip * unit, self.min_distance_clip)


#: The kinds of linear stage a protocol may ask for, from none to the most general.
LINEAR_KINDS = ("none", "rigid", "similarity", "affine")


@dataclass(frozen=True)
class LinearSettings:
    """The linear stage before the kernel warp (the protocol's linear section).

    Attributes
    ----------
    kind : {"none", "rigid", "similarity", "affine"}
        The linear map found first: ``"affine"`` (the default) as ANTs' SyN and
        greedy's users run before a deformable stage, since two subjects differ in
        pose, size and proportions; ``"rigid"`` for the same subject in two sessions;
        ``"none"`` for pairs already aligned (the kernel warp alone).
    """

    kind: str = "affine"

    def __post_init__(self) -> None:
        _check_types(self)
        if self.kind not in LINEAR_KINDS:
            raise ProtocolError(f"Expected `kind` in {LINEAR_KINDS}, got {excerpt(self.kind)}.")


@dataclass(frozen=True)
class ReviewSettings:
    """What the plausibility review of a registration does with its findings (the protocol's
    review section; the checks and their limits: :class:`~volreg.evaluation.review.ReviewLimits`).

    Attributes
    ----------
    strict : bool
        ``False`` (the default): findings are warnings (stderr and ``report.json``) and the
        exit status stays 0.  ``True``: an implausible result also makes ``register`` and
        ``consistency`` exit with status 3 (its outputs are still written, to be looked at).
    """

    strict: bool = False

    def __post_init__(self) -> None:
        _check_types(self)


@dataclass(frozen=True)
class OutputSettings:
    """Which optional files a registration writes (the protocol's outputs section).

    Attributes
    ----------
    itk_h5 : bool
        ``True`` (the default): also write ``warp.h5`` and ``inverse_warp.h5``, the
        displacement fields as ITK composite transforms (HDF5), the one-file form ANTs,
        SimpleITK and 3D Slicer load as a transform.  They hold the same maps as
        ``warp.nii.gz`` and ``inverse_warp.nii.gz`` but uncompressed in float64: about
        140 MB each on a 170 x 200 x 170 grid (the ``.nii.gz`` about 50 MB) and half a
        second each to write.  ``False`` leaves them out (e.g. for a batch of many pairs).
    """

    itk_h5: bool = True

    def __post_init__(self) -> None:
        _check_types(self)


@dataclass(frozen=True)
class Protocol:
    """Every setting of a run, by section."""

    name: str = "default"
    description: str = ""
    surface: SurfaceSettings = field(default_factory=SurfaceSettings)
    warp: WarpSettings = field(default_factory=WarpSettings)
    linear: LinearSettings = field(default_factory=LinearSettings)
    review: ReviewSettings = field(default_factory=ReviewSettings)
    outputs: OutputSettings = field(default_factory=OutputSettings)

    def __post_init__(self) -> None:
        _check_types(self)  # name and description
        for name, cls in (("surface", SurfaceSettings), ("warp", WarpSettings), ("linear", LinearSettings),
                          ("review", ReviewSettings), ("outputs", OutputSettings)):
            value = getattr(self, name)
            if not isinstance(value, cls):
                raise ArgumentTypeError(f"Expected `{name}` of Protocol to be a {cls.__name__}, got "
                                        f"{type(value).__name__} {value!r:.80}.")

    def to_dict(self) -> dict[str, Any]:
        """Plain data (for reports and saved models)."""
        return dataclasses.asdict(self)


def settings_from_mapping(cls, values: Mapping[str, Any], where: str):
    """Build the dataclass ``cls`` from a TOML table, checking keys and types."""
    if not isinstance(values, Mapping):
        raise ProtocolError(f"Expected [{where}] to be a table, got {type(values).__name__}.")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in values.items():
        if key not in fields:
            raise ProtocolError(f"Unknown setting `{where}.{excerpt(key, quote=False)}`; expected one of: {', '.join(sorted(fields))}.")
        want = fields[key].type if isinstance(fields[key].type, str) else fields[key].type.__name__
        if want == "bool":
            ok = isinstance(value, bool)
        elif "int" in want and "float" not in want:
            ok = isinstance(value, int) and not isinstance(value, bool)
            if ok and not -(2**63) <= value < 2**63:  # TOML integers are 64-bit; Python's reader takes any
                raise ProtocolError(f"Expected `{where}.{key}` to be an integer of at most 64 bits, got {excerpt(value)}.")
        elif "float" in want:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            try:
                value = float(value) if ok else value
            except OverflowError:  # an integer of hundreds of digits (Python's TOML reader takes any size)
                raise ProtocolError(f"Expected `{where}.{key}` to be a finite number, got an integer of "
                                    f"{len(str(abs(value)))} digits.") from None
        else:
            ok = isinstance(value, str)
        if not ok:
            raise ProtocolError(f"Expected `{where}.{key}` to be {want.replace(' | None', '')}, got {excerpt(value)}.")
        kwargs[key] = value
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ProtocolError(f"In [{where}]: {exc}") from None


def replace_settings(protocol: Protocol, warp: Mapping[str, Any], *, name: str | None = None) -> Protocol:
    """A copy of ``protocol`` with some ``[warp]`` settings replaced, validated as a file's would be.

    Raises
    ------
    ProtocolError
        An unknown key or a bad value, named.
    """
    current = {k: v for k, v in dataclasses.asdict(protocol.warp).items() if v is not None}
    current.update(warp)
    return dataclasses.replace(protocol, name=protocol.name if name is None else name,
                               warp=settings_from_mapping(WarpSettings, current, "warp"))
