"""The public API's arguments: what is natural is taken (a path for a volume, a preset name for a
protocol), anything else is refused where it comes in, in one line naming the argument, as a
VolregError (a TypeError for the wrong kind of argument, a ValueError for a wrong value), before
any work or any file."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import volreg
from volreg.errors import ArgumentTypeError, ProtocolError, RegistrationInputError, UsageError, VolregError
from volreg.io.protocol import load_protocol
from volreg.pipeline.arguments import drive_labels_argument, protocol_argument, warp_settings_argument
from volreg.settings import (LinearSettings, OutputSettings, Protocol, ReviewSettings, SurfaceSettings, WarpSettings,
                             settings_from_mapping)

from helpers import TEST_PROTOCOL, cube


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("api")
    fixed, moving = cube(), cube(lo=5, hi=12)
    volreg.write_labels(fixed, d / "fixed.nii.gz")
    volreg.write_labels(moving, d / "moving.nii.gz")
    (d / "test.toml").write_text(TEST_PROTOCOL)
    return d, fixed, moving


def _register_labels(fixed, moving, outdir, **kw):
    return volreg.register_labels(fixed, moving, **kw)


def _register_both_ways(fixed, moving, outdir, **kw):
    return volreg.register_both_ways(fixed, moving, **kw)


def _write_registration(fixed, moving, outdir, **kw):
    return volreg.write_registration(fixed, moving, outdir, **kw)


#: The label registration functions, called alike: (fixed, moving, outdir, **keywords).
LABEL_FUNCTIONS = {"register_labels": _register_labels, "register_both_ways": _register_both_ways,
                   "write_registration": _write_registration}

#: (id, keywords replacing the good ones, error class, words of the message, functions that take it).
BAD_ARGUMENTS = [
    ("volume as list", {"fixed": [[1, 2], [3, 4]]}, ArgumentTypeError, ["list", "LabelVolume"], None),
    ("volume as array", {"moving": np.zeros((4, 4, 4), np.uint8)}, ArgumentTypeError,
     ["ndarray of shape (4, 4, 4)", "LabelVolume(array, origin, spacing, direction)"], None),
    ("volume None", {"fixed": None}, ArgumentTypeError, ["LabelVolume", "got None"], None),
    ("volume a number", {"moving": 3}, ArgumentTypeError, ["LabelVolume", "int 3"], None),
    ("missing volume file", {"fixed": "nope.nii.gz"}, volreg.VolregIOError, ["nope.nii.gz", "does not exist"], None),
    ("protocol dict", {"protocol": {"warp": {}}}, ArgumentTypeError, ["`protocol`", "dict"], None),
    ("protocol section", {"protocol": WarpSettings()}, ArgumentTypeError, ["`protocol`", "dataclasses.replace"], None),
    ("protocol a number", {"protocol": 5}, ArgumentTypeError, ["`protocol`", "int 5"], None),
    ("unknown preset", {"protocol": "fastest"}, ProtocolError, ["fastest", "no such preset or file"], None),
    ("fractional label", {"drive_labels": [1.5]}, RegistrationInputError, ["`drive_labels`", "1.5", "not rounded"], None),
    ("label a number", {"drive_labels": 1}, ArgumentTypeError, ["`drive_labels`", "sequence", "int 1"], None),
    ("label text", {"drive_labels": "1"}, ArgumentTypeError, ["`drive_labels`", "str '1'"], None),
    ("label boolean", {"drive_labels": [True]}, ArgumentTypeError, ["`drive_labels`", "bool True"], None),
    ("label None", {"drive_labels": [None]}, ArgumentTypeError, ["`drive_labels`", "None"], None),
    ("label NaN", {"drive_labels": [float("nan")]}, RegistrationInputError, ["`drive_labels`", "nan"], None),
    ("landmarks path", {"landmarks": "l.csv"}, ArgumentTypeError, ["`landmarks`", "pair"], None),
    ("landmark paths", {"landmarks": ("a.csv", "b.csv")}, ArgumentTypeError, ["`landmarks`", "read_landmarks"], None),
    ("landmarks 2-D for 3-D", {"landmarks": ([[1.0, 2.0]], [[1.0, 2.0]])}, RegistrationInputError,
     ["`landmarks`", "(L, 3)", "(1, 2)"], None),
    ("landmark counts", {"landmarks": (np.ones((2, 3)), np.ones((3, 3)))}, RegistrationInputError,
     ["`landmarks`", "(2, 3) and (3, 3)"], None),
    ("landmark NaN", {"landmarks": (np.ones((1, 3)), np.full((1, 3), np.nan))}, RegistrationInputError,
     ["`landmarks`", "NaN"], None),
    ("landmark text", {"landmarks": (np.array([["a", "b", "c"]]), np.ones((1, 3)))}, ArgumentTypeError,
     ["`landmarks`", "numbers"], None),
    ("progress a number", {"progress": 5}, ArgumentTypeError, ["`progress`", "callable", "int 5"], None),
    ("prior a number", {"prior": 5}, ArgumentTypeError, ["`prior`", "callable"], ("register_labels", "write_registration")),
    ("on_fit a string", {"on_fit": "print"}, ArgumentTypeError, ["`on_fit`", "callable"],
     ("register_both_ways", "write_registration")),
    ("register a number", {"register": 1}, ArgumentTypeError, ["`register`", "callable"], ("register_both_ways",)),
    ("outdir a number", {"outdir": 5}, ArgumentTypeError, ["`outdir`", "path"], ("write_registration",)),
    ("force a string", {"force": "no"}, ArgumentTypeError, ["`force`", "True or False"], ("write_registration",)),
    ("inputs a list", {"inputs": ["a"]}, ArgumentTypeError, ["`inputs`", "mapping"], ("write_registration",)),
    ("truth a number", {"truth": 1.0}, ArgumentTypeError, ["`truth`", "callable"], ("write_registration",)),
]

_CASES = [(f, case) for f in LABEL_FUNCTIONS for case in BAD_ARGUMENTS if case[4] is None or f in case[4]]


@pytest.mark.parametrize("function, case", _CASES, ids=[f"{f}-{c[0]}" for f, c in _CASES])
def test_bad_argument_refused_at_the_door(pair, tmp_path, monkeypatch, function, case):
    d, fixed, moving = pair
    _, changes, error, words, _ = case
    monkeypatch.chdir(tmp_path)  # relative names (a missing file) are looked up here
    args = {"fixed": fixed, "moving": moving, "outdir": tmp_path / "out", "protocol": load_protocol(d / "test.toml")}
    args.update(changes)
    if function == "register_both_ways":  # its volumes are a and b; it registers both directions
        args = {("a" if k == "fixed" else "b" if k == "moving" else k): v for k, v in args.items()}
        words = [w.replace("`fixed`", "`a`").replace("`moving`", "`b`") for w in words]
    positional = [args.pop(k) for k in (("a", "b") if function == "register_both_ways" else ("fixed", "moving"))]
    outdir = args.pop("outdir")
    with pytest.raises(error) as caught:
        LABEL_FUNCTIONS[function](*positional, outdir, **args)
    assert isinstance(caught.value, VolregError)
    message = str(caught.value)
    assert "\n" not in message
    for w in words:
        assert w in message, (w, message)
    assert not (tmp_path / "out").exists() and list(tmp_path.iterdir()) == []


def test_paths_and_a_protocol_file_taken_as_the_objects_they_name(pair):
    """A volume's path is read (volreg.read_labels), a protocol's file or preset name loaded
    (volreg.load_protocol), labels of an array of floats with whole values taken: the same warp."""
    d, fixed, moving = pair
    by_objects = volreg.register_labels(fixed, moving, protocol=load_protocol(d / "test.toml"), drive_labels=[1])
    by_names = volreg.register_labels(str(d / "fixed.nii.gz"), d / "moving.nii.gz", protocol=str(d / "test.toml"),
                                      drive_labels=np.array([1.0]))
    points = fixed.grid_points().reshape(-1, 3)[::37]
    np.testing.assert_allclose(by_names.warp(points), by_objects.warp(points), atol=1e-9)
    assert by_names.distance_labels == by_objects.distance_labels == [1]


def test_preset_names_are_protocols():
    assert protocol_argument("fast") == load_protocol("fast")
    assert protocol_argument(None) == load_protocol("default")
    assert warp_settings_argument("fast") == load_protocol("fast").warp
    assert warp_settings_argument(load_protocol("accurate")) == load_protocol("accurate").warp


@pytest.mark.parametrize("labels, expected", [([1, 2], [1, 2]), (np.array([3, 4], np.int16), [3, 4]),
                                              ((2.0,), [2]), (np.array([5.0]), [5]), (None, None), ([], [])])
def test_natural_labels_taken(labels, expected):
    assert drive_labels_argument(labels) == expected


# ----------------------------------------------------------------------------- surfaces

@pytest.mark.parametrize("changes, error, words", [
    ({"source": "src.vtk"}, ArgumentTypeError, ["`source`/`target`", "pyvista.read"]),
    ({"target": None}, ArgumentTypeError, ["`source`/`target`", "NoneType"]),
    ({"source": [], "target": []}, ArgumentTypeError, ["at least one"]),
    ({"source": (np.array([["a", "b", "c"]]), np.ones((1, 3)))}, ArgumentTypeError, ["arrays of numbers"]),
    ({"settings": 5}, ArgumentTypeError, ["`settings`", "WarpSettings"]),
    ({"settings": "fastest"}, ProtocolError, ["fastest", "no such preset or file"]),
    ({"progress": 1}, ArgumentTypeError, ["`progress`", "callable"]),
    ({"align_centroids": "no"}, ArgumentTypeError, ["`align_centroids`", "True or False"]),
    ({"landmarks": (np.ones((2, 2)), np.ones((2, 2)))}, RegistrationInputError, ["`landmarks`", "(L, 3)"]),
], ids=["path", "None", "empty lists", "text points", "settings number", "unknown preset", "progress", "align",
        "landmarks"])
def test_register_surfaces_refuses_bad_arguments(changes, error, words):
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    args = {"source": (points * 10, points), "target": (points * 10, points)}
    args.update(changes)
    with pytest.raises(error) as caught:
        volreg.register_surfaces(args.pop("source"), args.pop("target"), **args)
    assert isinstance(caught.value, VolregError)
    for w in words:
        assert w in str(caught.value), (w, str(caught.value))


# ----------------------------------------------------------------------------- cohorts

@pytest.mark.parametrize("changes, error, words", [
    ({"manifest": 5}, ArgumentTypeError, ["`manifest`", "path"]),
    ({"outdir": None}, ArgumentTypeError, ["`outdir`", "path"]),
    ({"template": 3}, ArgumentTypeError, ["`template`"]),
    ({"pairs": "every"}, UsageError, ["`pairs`", "all, consecutive", "'every'"]),
    ({"pairs": None}, ArgumentTypeError, ["`pairs`"]),
    ({"consistency": "yes"}, ArgumentTypeError, ["`consistency`", "True or False"]),
    ({"protocol": Protocol()}, ArgumentTypeError, ["`protocol`", "preset name", "each worker reads it"]),
    ({"workers": 1.5}, ArgumentTypeError, ["`workers`", "whole number", "1.5"]),
    ({"workers": True}, ArgumentTypeError, ["`workers`"]),
    ({"scheduler": 8786}, ArgumentTypeError, ["`scheduler`", "address"]),
    ({"progress": 2}, ArgumentTypeError, ["`progress`", "callable"]),
    ({"notify": "x"}, ArgumentTypeError, ["`notify`", "callable"]),
], ids=["manifest", "outdir", "template", "pairs", "pairs None", "consistency", "protocol object", "workers float",
        "workers bool", "scheduler", "progress", "notify"])
def test_register_cohort_refuses_bad_arguments(pair, tmp_path, changes, error, words):
    d, _, _ = pair
    (tmp_path / "m.csv").write_text(f"id,path\na,{d / 'fixed.nii.gz'}\nb,{d / 'moving.nii.gz'}\n")
    args = {"manifest": str(tmp_path / "m.csv"), "outdir": tmp_path / "out"}
    args.update(changes)
    with pytest.raises(error) as caught:
        volreg.register_cohort(args.pop("manifest"), args.pop("outdir"), **args)
    for w in words:
        assert w in str(caught.value), (w, str(caught.value))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]


# ----------------------------------------------------------------------------- settings

SETTINGS = (SurfaceSettings, WarpSettings, LinearSettings, ReviewSettings, OutputSettings)


def _wrong_values(annotation: str) -> list:
    """Values of another type than a field of this annotation takes."""
    base = annotation.replace(" | None", "")
    return {"float": [True, False, "1.0", np.bool_(True)], "int": [True, 2.5, "2"], "bool": [1, 0, "true", None],
            "str": [3, True, None]}[base] + ([] if "None" in annotation or base in ("bool", "str") else [None])


_SETTING_CASES = [(cls, f.name, value) for cls in SETTINGS for f in dataclasses.fields(cls)
                  for value in _wrong_values(f.type)]


@pytest.mark.parametrize("cls, name, value", _SETTING_CASES,
                         ids=[f"{c.__name__}.{n}={v!r}" for c, n, v in _SETTING_CASES])
def test_settings_refuse_values_the_protocol_reader_refuses(cls, name, value):
    with pytest.raises(ArgumentTypeError, match=rf"^Expected `{name}` of {cls.__name__} to be "):
        cls(**{name: value})
    if value is not None and not isinstance(value, np.bool_):  # what a TOML file can hold
        with pytest.raises(ProtocolError, match=rf"`section.{name}`"):
            settings_from_mapping(cls, {name: value}, "section")


def test_settings_take_numbers_of_any_kind_as_python_numbers():
    """numpy's numbers are kept as the Python numbers they hold, so that the protocol writes back as TOML."""
    from volreg.io.protocol import protocol_to_toml

    warp = WarpSettings(alpha=np.float32(2.0), max_iter=np.int64(3), pad=4)
    assert (type(warp.alpha), type(warp.max_iter), warp.pad) == (float, int, 4)
    protocol = dataclasses.replace(Protocol(), warp=warp)
    assert volreg.io.protocol.tomllib.loads(protocol_to_toml(protocol))["warp"]["alpha"] == 2.0
    with pytest.raises(ArgumentTypeError, match="`strict` of ReviewSettings to be true or false"):
        ReviewSettings(strict=np.bool_(True))


def test_protocol_refuses_sections_of_another_kind():
    with pytest.raises(ArgumentTypeError, match=r"`warp` of Protocol to be a WarpSettings, got dict"):
        Protocol(warp={"alpha": 1.0})
    with pytest.raises(ArgumentTypeError, match=r"`name` of Protocol to be a string"):
        Protocol(name=3)
    with pytest.raises(ArgumentTypeError, match=r"`surface` of Protocol to be a SurfaceSettings, got WarpSettings"):
        Protocol(surface=WarpSettings())
