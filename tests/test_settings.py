"""Settings have one home: the dataclasses of volreg.settings hold every default.

``protocols/default.toml`` states exactly those defaults, every shipped preset loads and
says truthfully how it differs from the default, a protocol survives a round trip through
TOML, and library functions that take a setting as an argument default to the setting's value.
"""

import dataclasses
import inspect
import re
import sys

import numpy as np
import pytest

from volreg.io.protocol import PROTOCOL_DIR, load_protocol, protocol_to_toml
from volreg.settings import Protocol, SurfaceSettings, WarpSettings

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

SECTIONS = {"surface": SurfaceSettings, "warp": WarpSettings}
PRESETS = sorted(p.stem for p in PROTOCOL_DIR.glob("*.toml"))


def _live_keys(text: str, section: str) -> set[str]:
    """Keys set (not commented) in ``[section]`` of a TOML text."""
    return set(tomllib.loads(text).get(section, {}))


def _commented_keys(text: str) -> set[str]:
    """Keys that appear only as ``# key = ...`` comments."""
    return set(re.findall(r"^#\s*(\w+)\s*=", text, flags=re.MULTILINE))


def test_presets_are_shipped():
    assert "default" in PRESETS and len(PRESETS) >= 2


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_default_toml_states_exactly_the_dataclass_defaults(section):
    """Every field with a value is set to exactly its default (same type); every field whose
    default is None (derived from the data) is present only as a comment."""
    text = (PROTOCOL_DIR / "default.toml").read_text(encoding="utf-8")
    table = tomllib.loads(text)[section]
    fields = dataclasses.fields(SECTIONS[section])
    derived = {f.name for f in fields if f.default is None}
    valued = {f.name: f.default for f in fields if f.default is not None}
    assert set(table) == set(valued), f"[{section}] keys differ from the fields with a default"
    for name, default in valued.items():
        value = table[name]
        assert type(value) is type(default) and value == default, f"{section}.{name} = {value!r}, default {default!r}"
    assert derived <= _commented_keys(text), f"[{section}] lacks comments for {sorted(derived - _commented_keys(text))}"
    assert not derived & set(table)


def test_default_toml_loads_to_the_defaults():
    p = load_protocol("default")
    assert p.surface == SurfaceSettings() and p.warp == WarpSettings()
    assert p == Protocol(name="default", description=p.description)


@pytest.mark.parametrize("name", PRESETS)
def test_every_preset_loads_and_names_every_setting(name):
    p = load_protocol(name)
    assert p.name == name and p.description
    text = (PROTOCOL_DIR / f"{name}.toml").read_text(encoding="utf-8")
    for section, cls in SECTIONS.items():
        named = _live_keys(text, section) | _commented_keys(text)
        missing = {f.name for f in dataclasses.fields(cls)} - named
        assert not missing, f"{name}.toml does not name [{section}] {sorted(missing)}"


@pytest.mark.parametrize("name", [n for n in PRESETS if n != "default"])
def test_every_preset_says_how_it_differs_from_the_default(name):
    """The first line lists exactly the settings that differ from the default."""
    first = (PROTOCOL_DIR / f"{name}.toml").read_text(encoding="utf-8").splitlines()[0]
    claim = re.search(r'differs from "default" in (.+?)\.?$', first)
    assert claim, f"{name}.toml: first line should say how it differs from the default: {first!r}"
    said = set(re.split(r",\s*|\s+and\s+", claim.group(1)))
    p, default = load_protocol(name), load_protocol("default")
    differ = {key for section in SECTIONS for key, value in dataclasses.asdict(getattr(p, section)).items()
              if value != getattr(getattr(default, section), key)}
    assert said == differ


@pytest.mark.parametrize(
    "protocol",
    [load_protocol(n) for n in PRESETS]
    + [Protocol(name="mine", description='quotes " and \\ backslashes',
                surface=SurfaceSettings(smoothing=0.0, implicit_weight=0.5, distance_weight=0.0),
                warp=WarpSettings(pad=7.5, min_width=3.0, band=2.5, sample_spacing=1.25, max_iter=7,
                                  tolerance=1e-9, lambda_fold=0.0, robust=0.0)),
       # control characters (a description over several lines, a bell in the name) made a file TOML refuses
       Protocol(name="bell\x07-tuned", description="first line\nsecond\tline\r\x7f")],
    ids=PRESETS + ["every-optional-set", "control-characters"],
)
def test_protocol_round_trips_through_toml(tmp_path, protocol):
    path = tmp_path / "round_trip.toml"
    path.write_text(protocol_to_toml(protocol, comment="written by a test\nsecond line with a \x07"), encoding="utf-8")
    assert load_protocol(path) == protocol
    assert load_protocol(path).to_dict() == protocol.to_dict()


def test_resolved_fills_in_only_the_data_derived_defaults():
    """``pad`` defaults to 10 % of the source diameter and ``min_width`` to 1/16 (the paper's
    cascade 1/2, 1/4, 1/8, 1/16 of the diameter); values already set stay."""
    r = WarpSettings().resolved(80.0)
    assert (r.pad, r.min_width) == (pytest.approx(8.0), 5.0)
    assert dataclasses.replace(r, pad=None, min_width=None) == WarpSettings()
    kept = WarpSettings(pad=3.0, min_width=2.0, alpha=0.0).resolved(80.0)
    assert kept == WarpSettings(pad=3.0, min_width=2.0, alpha=0.0)
    with pytest.raises(ValueError, match="`pad`"):
        WarpSettings().resolved(0.0)


def test_a_fitted_warp_records_its_resolved_settings():
    from volreg.warp.fit import fit_warp
    from volreg.warp.objective import FeaturePair

    class Circle:
        """Signed distance of a circle of radius 10 mm, the same on both sides (identity warp)."""

        def evaluate(self, x, order=1):
            n = np.linalg.norm(x, axis=1)
            out = [n - 10.0, x / n[:, None]]
            if order >= 2:
                u = out[1]
                out.append((np.eye(2)[None] - u[:, :, None] * u[:, None, :]) / n[:, None, None])
            return tuple(out[: order + 1])

    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    points = 10.0 * np.column_stack([np.cos(t), np.sin(t)])
    diameter = 20.0 * np.sqrt(2.0)  # the diagonal of the points' bounding box
    settings = WarpSettings(max_iter=3)
    result = fit_warp([FeaturePair(Circle(), Circle())], points, settings=settings)
    assert result.warp.settings == dataclasses.asdict(settings.resolved(diameter))
    assert [e["width"] for e in result.log] == pytest.approx([diameter / 2, diameter / 4, diameter / 8, diameter / 16])


def test_library_defaults_agree_with_the_settings():
    """Functions that take a setting as an argument default to the setting's value, so that
    the library and a protocol left at its defaults do the same."""
    from volreg.features.label_surfaces import implicit_surfaces, label_surface, label_surfaces
    from volreg.warp.sampling import octree_sample

    def default(func, name):
        return inspect.signature(func).parameters[name].default

    assert default(octree_sample, "fraction") == WarpSettings().fraction
    assert default(label_surface, "smoothing") == SurfaceSettings().smoothing
    assert default(label_surfaces, "smoothing") == SurfaceSettings().smoothing
    assert default(implicit_surfaces, "min_width_voxels") == SurfaceSettings().min_width_voxels


@pytest.mark.parametrize("section, name", [("warp", "lambda_loc"), ("warp", "lambda_fold"), ("warp", "robust"),
                                           ("surface", "distance_clip"), ("surface", "min_distance_clip")])
def test_settings_beyond_double_precision_are_refused(section, name):
    """1e200 as a weight (1e160 as `robust`, 1e308 as a clip) ended in a traceback from inside the
    fit ("Expected finite values in points", an OverflowError, an empty mask); refused as settings."""
    from volreg.settings import MAX_SETTING

    kind = WarpSettings if section == "warp" else SurfaceSettings
    kind(**{name: MAX_SETTING})
    with pytest.raises(ValueError, match=f"`{name}`.*at most 1e\\+12"):
        kind(**{name: 1e200})
