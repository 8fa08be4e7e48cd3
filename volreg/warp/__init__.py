"""The warp tau(x) = A x + b + sum_j c_j k(x, x_j) (paper eq. 9 after a linear map) and what fits and uses it.

Modules
-------
linear
    :func:`~volreg.warp.linear.fit_linear`, the rigid/similarity/affine stage fitted to label moments and
    distance maps before the kernel warp; its map is a :class:`~volreg.linear_map.LinearMap` (A x + b).
linear_labels, linear_starts, linear_cost, linear_refine
    The linear stage's parts: the labels' moments, boundary samples and distance maps; the candidate
    starts and their scoring; the cost and one least-squares solve; the coarse-to-fine refinement.
model
    :class:`~volreg.warp.model.KernelWarp` (evaluate, Jacobian, compose) and its ``.npz`` file format.
sampling
    Octree sampling of the warp volume X (paper Section 3.5).
objective
    The per-level objective (11): regulariser, locational cost (3)-(6), landmarks (8), fold barrier.
fit
    The coarse-to-fine driver and the per-level solver (Sections 3.4-3.5).
inverse
    :class:`~volreg.warp.inverse.InverseWarp`: Newton inversion with the analytic Jacobian.
field
    A warp sampled on a voxel grid: displacement fields and Jacobian determinants.
resample
    Label-preserving and intensity resampling of images at warped points.
points
    Landmarks and mesh vertices carried through a warp, a linear map or a displacement field, either way.
"""
