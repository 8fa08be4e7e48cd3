"""Both directions of a pair, as the consistency test (paper Section 5) needs.

:func:`register_both_ways` registers A to B, then B to A; with the symmetric option
(``warp.lambda_consistency`` > 0) the backward fit is pulled towards the inverse of the
forward warp.  How each direction is registered is the caller's (``register``): the
outputs layer passes one that also writes each direction's files.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol as Signature, Sequence

import numpy as np

from volreg.grid import LabelVolume
from volreg.pipeline.arguments import (
    callable_argument,
    drive_labels_argument,
    label_volume_argument,
    landmarks_argument,
    protocol_argument,
)
from volreg.pipeline.labels import LabelRegistration, register_labels
from volreg.settings import Protocol
from volreg.warp.inverse import InverseWarp

__all__ = ["DirectionRegistrar", "TwoWayRegistration", "register_both_ways"]

ProgressCallback = Callable[[str, int, int], None]
Landmarks = tuple[np.ndarray, np.ndarray]


class DirectionRegistrar(Signature):
    """How one direction is registered: ``register(name, fixed, moving, landmarks, prior)``.

    ``name`` is ``"forward"`` (fixed A, moving B) or ``"backward"`` (fixed B, moving A);
    ``landmarks`` the fixed volume's points and their moving partners (or ``None``); ``prior``
    the symmetric option's target map (or ``None``).  Returns the direction's
    :class:`~volreg.pipeline.labels.LabelRegistration`.
    """

    def __call__(self, name: str, fixed: LabelVolume, moving: LabelVolume, landmarks: Landmarks | None,
                 prior: Callable[[np.ndarray], np.ndarray] | None) -> LabelRegistration: ...


@dataclass
class TwoWayRegistration:
    """Registrations of A to B and of B to A.

    Attributes
    ----------
    forward : LabelRegistration
        ``forward.warp`` maps A points to their B partners (the pull-back of registering B to A's grid).
    backward : LabelRegistration
        ``backward.warp`` maps B points to their A partners.
    """

    forward: LabelRegistration
    backward: LabelRegistration


def register_both_ways(
    a: LabelVolume,
    b: LabelVolume,
    *,
    protocol: Protocol | None = None,
    drive_labels: Sequence[int] | None = None,
    landmarks: Landmarks | None = None,
    progress: ProgressCallback | None = None,
    on_fit: Callable[[LabelRegistration], None] | None = None,
    register: DirectionRegistrar | None = None,
) -> TwoWayRegistration:
    """Register A to B, then B to A, as the consistency test (paper Section 5) needs.

    With the protocol's ``warp.lambda_consistency`` > 0 (the symmetric option) the
    backward fit is pulled towards the inverse of the forward warp
    (:class:`~volreg.warp.inverse.InverseWarp`, the ``prior`` of
    :func:`~volreg.pipeline.labels.register_labels`); otherwise the two registrations are independent.

    Parameters
    ----------
    a, b : LabelVolume or path-like
        The volumes, or the paths of label images (:func:`volreg.io.read_labels`).
    protocol : Protocol, str or path-like, optional
        For both registrations: a protocol, or a preset name or protocol file; default
        :func:`volreg.io.protocol.load_protocol` ``("default")``.
    drive_labels : sequence of int, optional
        As :func:`~volreg.pipeline.labels.register_labels`, for both.
    landmarks : pair of (L, D) float ndarrays, optional
        A's points and their B partners, LPS mm (swapped for the backward registration).
    progress : callable, optional
        ``progress(stage, done, total)``.
    on_fit : callable, optional
        Called with each direction's registration once it is fitted (default ``register`` only).
    register : DirectionRegistrar, optional
        How each direction is registered; default :func:`~volreg.pipeline.labels.register_labels`
        with the settings above (e.g. :func:`volreg.outputs.consistency.write_both_ways` passes one
        that writes each direction's outputs as well).

    Returns
    -------
    TwoWayRegistration

    Raises
    ------
    ArgumentTypeError, RegistrationInputError
        An argument of the wrong kind or value, named, before any work (as
        :func:`~volreg.pipeline.labels.register_labels`).
    """
    a, b = label_volume_argument(a, "a"), label_volume_argument(b, "b")
    protocol = protocol_argument(protocol)
    drive_labels = drive_labels_argument(drive_labels)
    landmarks = landmarks_argument(landmarks, a.ndim)
    progress = callable_argument(progress, "progress", "progress(stage, done, total)")
    on_fit = callable_argument(on_fit, "on_fit", "of a LabelRegistration")
    register = callable_argument(register, "register", "register(name, fixed, moving, landmarks, prior)")
    reverse = None if landmarks is None else (landmarks[1], landmarks[0])

    def fit_only(name, fixed, moving, points, prior) -> LabelRegistration:
        result = register_labels(fixed, moving, protocol=protocol, drive_labels=drive_labels, landmarks=points,
                                 prior=prior, progress=progress)
        if on_fit is not None:
            on_fit(result)
        return result

    register = fit_only if register is None else register
    forward = register("forward", a, b, landmarks, None)
    # the symmetric option: the backward fit is pulled towards the forward warp's inverse
    prior = InverseWarp(forward.warp) if protocol.warp.lambda_consistency > 0 else None
    backward = register("backward", b, a, reverse, prior)
    return TwoWayRegistration(forward, backward)
