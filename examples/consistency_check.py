"""The consistency test from Python: register both ways, compose, and compare with the exact inverse.

Usage: python examples/consistency_check.py

Registers a blob pair (known smooth warp, up to 3 voxels) A->B and B->A, reports the
inverse-consistency error |tau_BA(tau_AB(x)) - x| over A's labels, then the same with the
symmetric option (the B->A fit pulled towards the Newton inverse of A->B), and the residual
of the Newton inverse itself.
"""

import dataclasses
import sys
from pathlib import Path

import numpy as np

import volreg
from volreg.synthetic import GaussianBumps, deform_labels

sys.path.insert(0, str(Path(__file__).parent))
from register_two_volumes import blob  # noqa: E402


def main() -> None:
    a = blob()
    x = a.grid_points()[a.array > 0]  # (N, 3) LPS mm: A's labelled voxels
    truth = GaussianBumps.random(x.min(0), x.max(0), max_displacement=4.5, scale=14.0, count=5,
                                 rng=np.random.default_rng(3))
    b = deform_labels(a, truth)
    protocol = volreg.load_protocol("fast")

    ab = volreg.register_labels(a, b, protocol=protocol).warp   # A point -> its B partner
    ba = volreg.register_labels(b, a, protocol=protocol).warp   # B point -> its A partner
    error = np.linalg.norm(ba(ab(x)) - x, axis=1)
    print(f"two registrations: consistency error mean {error.mean():.3f} mm, p95 {np.percentile(error, 95):.3f} mm")

    symmetric = dataclasses.replace(protocol, warp=dataclasses.replace(protocol.warp, lambda_consistency=1000.0))
    ba_sym = volreg.register_labels(b, a, protocol=symmetric, prior=volreg.InverseWarp(ab)).warp
    error = np.linalg.norm(ba_sym(ab(x)) - x, axis=1)
    print(f"symmetric option:  consistency error mean {error.mean():.3f} mm, p95 {np.percentile(error, 95):.3f} mm")

    inverse = volreg.InverseWarp(ab)  # tau_AB^-1 by Newton's method, with its residual
    back = inverse(ab(x))
    print(f"Newton inverse: max |x - tau^-1(tau(x))| {np.abs(back - x).max():.2e} mm, "
          f"max residual |tau(x') - y| {inverse.max_residual:.2e} mm, {inverse.unconverged} points unconverged")


if __name__ == "__main__":
    main()
