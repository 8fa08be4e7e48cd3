"""Feature functions of an object, the f of the locational cost (paper eqs. 3-6).

Modules
-------
label_surfaces
    Boundary meshes of the labels of a label volume (marching cubes) and their implicit surfaces.
implicit
    :class:`~volreg.features.implicit.ImplicitSurface`: the multi-scale kernel SV-regression fit of a
    signed distance (paper Section 4).
distance_maps
    :class:`~volreg.features.distance_maps.VoxelDistance`: a label's clipped, smoothed voxel signed
    distance (not in the paper), for labels too small or fragmented for a surface.

Every feature offers ``evaluate(points, order) -> (value, gradient[, hessian])`` in mm;
:class:`~volreg.warp.objective.FeaturePair` pairs the fixed object's feature with the moving one's.
"""
