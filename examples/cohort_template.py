"""A cohort's template of label maps from Python: four subjects made from one shape by opposite
local bumps, so that their mean shape is that shape, which none of them is; then the cohort's
shape and deformation models from the template's correspondences.

Usage: python examples/cohort_template.py [OUTDIR]   (needs Dask: pip install 'volreg[batch]')

Builds the template (volreg.build_template, as `volreg template`), then prints each round's shape
update, the subjects ranked by their distance to the template, and how close the template and
each subject come to the shape they were made from (mean Dice over its labels); then builds the
shape models (volreg.build_shape_models, as `volreg shape-model`), prints the share of the
variance in each leading mode (two bumps: two modes hold most of it) and writes the label map at
+2 standard deviations of the leading deformation mode.
"""

import sys
import tempfile

import numpy as np

import volreg
from volreg.synthetic import GaussianBumps, deform_labels


def base_shape(n: int = 36, spacing: float = 2.0) -> volreg.LabelVolume:
    """An ellipsoid (label 1) holding three smaller ones (labels 2-4), 2 mm voxels."""
    x = np.indices((n, n, n)).reshape(3, -1).T * spacing - (n - 1) * spacing / 2
    labels = np.zeros(len(x), np.uint8)
    for value, centre, radii in ((1, [0, 0, 0], [28, 20, 15]), (2, [8, 0, 0], [11, 8, 7]),
                                 (3, [-13, 0, 0], [7, 7, 6]), (4, [-2, 10, 5], [6, 5, 5])):
        labels[(((x - centre) / radii) ** 2).sum(1) <= 1] = value
    return volreg.LabelVolume(labels.reshape(n, n, n), np.full(3, -(n - 1) * spacing / 2), np.full(3, spacing),
                              np.eye(3))


def mean_dice(reference: volreg.LabelVolume, other: volreg.LabelVolume) -> float:
    """Mean Dice over the reference's labels, ``other`` read at the reference's voxel centres."""
    index = np.rint(other.world_to_index(reference.grid_points().reshape(-1, 3))).astype(int)
    inside = np.all((index >= 0) & (index < other.shape), axis=1)
    values = np.zeros(len(index), other.array.dtype)
    values[inside] = other.array[tuple(index[inside].T)]
    values = values.reshape(reference.shape)
    return float(np.mean([2 * np.sum((reference.array == v) & (values == v))
                          / (np.sum(reference.array == v) + np.sum(values == v)) for v in (1, 2, 3, 4)]))


def main() -> None:
    outdir = sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="volreg-template-")
    base = base_shape()
    subjects = {}
    for j, (centre, amplitude) in enumerate((([9, 0, 0], [0, 0, 5]), ([-11, 6, 0], [0, 5, 0]))):
        for sign, tag in ((1, "plus"), (-1, "minus")):
            bump = GaussianBumps(np.array([centre], float), sign * np.array([amplitude], float), 11.0)
            subjects[f"bump{j}-{tag}"] = deform_labels(base, bump)
    result = volreg.build_template(subjects, outdir, iterations=3, workers=2, protocol="fast", force=True)
    for it in result.report["iterations"]:
        print(f"iteration {it['iteration']}: shape update mean {it['update_mean_mm']:.2f} mm, "
              f"max {it['update_max_mm']:.2f} mm; subjects' mean Dice to the template {it['mean_dice']:.3f}")
    print("subjects by distance to the template:",
          ", ".join(f"{r['id']} {r['distance_mm']:.2f} mm" for r in result.report["ranking"]))
    print(f"mean Dice to the shape they were made from: template {mean_dice(base, result.template):.3f}; subjects "
          + ", ".join(f"{mean_dice(base, s):.3f}" for s in subjects.values()))
    models = volreg.build_shape_models(outdir, align="rigid", samples=20)
    for kind, model in models.models.items():
        print(f"{kind} model: share of the variance in the leading modes "
              + ", ".join(f"{f:.2f}" for f in model.model.fractions()[:3]))
    volreg.write_labels(models.models["deformation"].label_map([2.0]), f"{outdir}/mode1_plus2sd.nii.gz", force=True)
    print(f"outputs in {outdir}")


if __name__ == "__main__":
    main()
