"""``volreg tune``: grid of warp settings scored by consistency and hold-out."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from volreg.errors import UsageError
from volreg.cli.tune import parse_grid
from volreg.io import write_labels
from volreg.errors import ProtocolError
from volreg.io.protocol import load_protocol, protocol_to_toml
from volreg.settings import replace_settings
from volreg.synthetic import GaussianBumps, deform_labels

from helpers import TEST_PROTOCOL, blob_volume, run


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("tune")
    a = blob_volume()
    inside = a.grid_points().reshape(-1, 3)[a.array.ravel() > 0]
    truth = GaussianBumps.random(inside.min(0), inside.max(0), max_displacement=4.5, scale=14.0, count=5,
                                 rng=np.random.default_rng(3))
    write_labels(a, d / "a.nii.gz")
    write_labels(deform_labels(a, truth), d / "b.nii.gz")
    # Without the linear stage: lambda_loc = 0 then leaves the identity both ways.
    (d / "p.toml").write_text(TEST_PROTOCOL + '\n[linear]\nkind = "none"\n')
    return d


def test_tune_prefers_a_registration_over_the_consistent_identity(pair, tmp_path, capsys):
    """lambda_loc = 0 gives the identity (perfectly consistent, far from the other surface); the
    hold-out distance makes tune choose lambda_loc = 100, and tuned.toml loads back with it."""
    assert run(["tune", pair / "a.nii.gz", pair / "b.nii.gz", "-o", tmp_path / "out", "--protocol", pair / "p.toml",
                "--grid", "lambda_loc=0,100"]) == 0
    out = capsys.readouterr()
    assert "[2/2] lambda_loc=100" in out.err
    # the last line names the file where it now is, not the staging folder it was written in
    assert f"{tmp_path / 'out' / 'tuned.toml'} (" in out.out.strip().splitlines()[-1], out.out
    rows = list(csv.DictReader((tmp_path / "out" / "tune.csv").read_text().splitlines()))
    assert [float(r["lambda_loc"]) for r in rows] == [0.0, 100.0]
    identity, registered = rows
    assert float(identity["consistency_mm"]) == 0.0  # both warps are the identity
    assert float(registered["holdout_mm"]) < 0.5 * float(identity["holdout_mm"])
    for r in rows:
        assert float(r["score_mm"]) == pytest.approx(float(r["consistency_mm"]) + float(r["holdout_mm"]))
    assert (identity["chosen"], registered["chosen"]) == ("0", "1")
    tuned = load_protocol(tmp_path / "out" / "tuned.toml")
    assert tuned.warp.lambda_loc == 100.0 and tuned.name == "test-tuned" and tuned.linear.kind == "none"
    assert tuned.warp == replace_settings(load_protocol(pair / "p.toml"), {"lambda_loc": 100.0}).warp


def test_parse_grid():
    assert parse_grid(["lambda_loc=10,100,alpha=0,10"]) == {"lambda_loc": [10.0, 100.0], "alpha": [0.0, 10.0]}
    assert parse_grid(["alpha=1", "max_iter=20,40"]) == {"alpha": [1.0], "max_iter": [20, 40]}
    for bad, words in (("10,100", "KEY=V1"), ("alpha=", "at least one value"), ("alpha=x", "not a number"),
                       ("alpha=1,alpha=2", "given twice"), ("alpha=inf", "not finite")):
        with pytest.raises(UsageError, match=words):
            parse_grid([bad])


def test_protocol_round_trips_through_toml(tmp_path):
    p = replace_settings(load_protocol("fast"), {"lambda_loc": 7.5, "max_iter": 12}, name="x")
    (tmp_path / "x.toml").write_text(protocol_to_toml(p, comment="a\nb"))
    assert load_protocol(tmp_path / "x.toml") == p
    with pytest.raises(ProtocolError, match="lambda_loc"):
        replace_settings(p, {"lambda_loc": -1.0})


def test_a_pair_without_a_surface_to_score_on_is_refused(tmp_path):
    """Labels of 6 voxels (under min_voxels) have no surface: the hold-out distance, and every
    setting's score, was NaN, and tune picked one at random with exit 0."""
    from volreg.errors import RegistrationInputError
    from volreg.evaluation.tune import tune_settings
    from volreg.grid import LabelVolume

    arr = np.zeros((12, 12, 12), np.uint8)
    arr[3:9, 5, 5] = 1
    thin = LabelVolume(arr, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(3))
    with pytest.warns(Warning), pytest.raises(RegistrationInputError, match="No label has a surface in both"):
        tune_settings(thin, thin, load_protocol("fast"), {"alpha": [0.0, 1.0]})


@pytest.mark.parametrize("grid, words", [("bogus=1,2", "Unknown setting `warp.bogus`"),
                                         ("lambda_loc=-5", "lambda_loc"), ("max_iter=2.5", "max_iter"),
                                         ("lambda_loc=10,10.0", "given twice")])
def test_bad_grid_refused_before_registering(pair, tmp_path, capsys, grid, words):
    assert run(["tune", pair / "a.nii.gz", pair / "b.nii.gz", "-o", tmp_path / "out", "--grid", grid]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("volreg tune: error: --grid") and "\n" not in err and words in err
    assert not (tmp_path / "out").exists()


def test_scored_settings_are_printed_as_they_are_set(capsys):
    """`min_det=0.99999999` was printed `min_det=1` (six significant digits), a value out of range."""
    from volreg.cli.tune import _print_score

    _print_score(0, 2, {"min_det": 0.99999999, "alpha": 10.0},
                 {"consistency_mm": 0.1, "holdout_mm": 0.2, "score_mm": 0.3, "seconds": 1.0})
    assert "min_det=0.99999999, alpha=10:" in capsys.readouterr().err
