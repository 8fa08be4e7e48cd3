"""Protocols: presets load to the documented defaults; bad files are refused by name."""

import pytest

from volreg.errors import ProtocolError
from volreg.io.protocol import PROTOCOL_DIR, load_protocol
from volreg.io.protocol import protocol_to_toml
from volreg.settings import LinearSettings, OutputSettings, Protocol, ReviewSettings, SurfaceSettings, WarpSettings


def test_default_preset_names_every_default():
    p = load_protocol("default")
    assert p.name == "default"
    assert p.warp == WarpSettings() and p.surface == SurfaceSettings()
    assert p.linear == LinearSettings("affine") and p.review == ReviewSettings(strict=False)
    assert p.outputs == OutputSettings(itk_h5=True)
    assert p == Protocol(name="default", description=p.description)
    text = (PROTOCOL_DIR / "default.toml").read_text()
    for section in (p.warp, p.surface, p.linear, p.review, p.outputs):  # every setting is named in the file (some commented: optional)
        for name in section.__dataclass_fields__:
            assert f"{name} =" in text, name


def test_a_file_overrides_and_keeps_the_rest(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text('[warp]\nalpha = 0\npad = 7.5\nmax_iter = 50\n[surface]\nsmoothing = 0.5\n')
    p = load_protocol(f)
    assert (p.warp.alpha, p.warp.pad, p.warp.max_iter, p.surface.smoothing) == (0.0, 7.5, 50, 0.5)
    assert p.warp.lambda_loc == WarpSettings().lambda_loc and p.name == "mine"


@pytest.mark.parametrize(
    "body, message",
    [
        ("[warp]\nalpah = 1.0\n", "Unknown setting `warp.alpah`"),
        ("[wrap]\n", r"Unknown section \[wrap\]"),
        ("[warp]\nalpha = -1.0\n", "`alpha` >= 0"),
        ("[warp]\nmax_iter = 2.5\n", "`warp.max_iter` to be int"),
        ("[warp]\nalpha = true\n", "`warp.alpha` to be float"),
        ("[surface]\nsmoothing = 50\n", "`smoothing` in \\[0, 10\\]"),
        ("[protocol]\nnam = 'x'\n", "Unknown setting `protocol.nam`"),
        ("[warp\n", "not valid TOML"),
        ("[linear]\nkind = 'rotation'\n", "`kind` in"),
        ("[linear]\nkind = 2\n", "`linear.kind` to be str"),
        ("[review]\nstrict = 'yes'\n", "`review.strict` to be bool"),
        ("[review]\nstrict = 1\n", "`review.strict` to be bool"),
        ("[outputs]\nitk_h5 = 'no'\n", "`outputs.itk_h5` to be bool"),
        ("[outputs]\nnifti = false\n", "Unknown setting `outputs.nifti`"),
        ("[warp]\nmax_iter = 99999999999999999999\n", "`warp.max_iter` to be an integer of at most 64 bits"),
        ("[warp]\nlambda_loc = 1" + "0" * 400 + "\n", "`warp.lambda_loc` to be a finite number"),
        ("[protocol]\nname = 5\n", "`protocol.name` to be a string"),
        ("alpha = 3.0\n[warp]\npad = 5.0\n", r"Setting `alpha` .* lies outside any section; expected it under \[warp\]"),
        ("name = 'x'\n", r"Setting `name` .* expected it under \[protocol\]"),
    ],
)
def test_bad_files_are_refused_by_name(tmp_path, body, message):
    f = tmp_path / "bad.toml"
    f.write_text(body)
    with pytest.raises(ProtocolError, match=message):
        load_protocol(f)


def test_unknown_preset():
    with pytest.raises(ProtocolError, match="Protocol `nope` is no such preset or file.*default"):
        load_protocol("nope")


def test_linear_review_and_outputs_sections_round_trip(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text('[linear]\nkind = "rigid"\n[review]\nstrict = true\n[outputs]\nitk_h5 = false\n')
    p = load_protocol(f)
    assert p.linear.kind == "rigid" and p.review.strict is True and p.warp == WarpSettings()
    assert p.outputs.itk_h5 is False
    (tmp_path / "again.toml").write_text(protocol_to_toml(p))
    assert load_protocol(tmp_path / "again.toml") == p
