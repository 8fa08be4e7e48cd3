"""The documentation stays true: the README's Python example runs and does what it says, the README
stays short, every relative link points to a file (and heading), the public API is documented, and
BENCHMARKS.md covers every benchmark script with commands that exist."""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

import numpy as np
import pytest

import volreg
from volreg.synthetic import GaussianBumps, deform_labels

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
BENCHMARKS = REPO / "BENCHMARKS.md"
DOCS = sorted((REPO / "docs").glob("*.md"))

#: The README's limit, characters: an overview, with the details in docs/.
README_MAX_CHARS = 12_500

#: The names the README's Python example needs from the public API.
SNIPPET_NAMES = ("read_labels", "load_protocol", "register_labels", "resample_labels", "KernelWarp", "InverseWarp",
                 "write_outputs")


def _without_code(text: str) -> str:
    """Markdown text with fenced code blocks removed (links and headings inside them do not count)."""
    return re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)


def _python_snippet() -> str:
    """The first ```python block under the README's "## Python" heading."""
    text = README.read_text(encoding="utf-8")
    section = re.search(r"^## Python\s*$(.*?)(?=^## |\Z)", text, flags=re.S | re.M)
    assert section, "README.md has no '## Python' section"
    block = re.search(r"^```python\n(.*?)^```", section.group(1), flags=re.S | re.M)
    assert block, "README.md's Python section has no ```python block"
    return block.group(1)


def _pair(folder: Path) -> tuple[volreg.LabelVolume, volreg.LabelVolume]:
    """fixed.nii.gz: an ellipsoid (label 1) around a sphere (label 2), 40^3 voxels of 2 mm;
    moving.nii.gz: the same deformed by a known smooth warp of up to 4 mm."""
    shape, spacing = (40, 40, 40), 2.0
    grid = volreg.LabelVolume(np.zeros(shape, np.uint8), (-39.0, -39.0, -39.0), (spacing,) * 3, np.eye(3))
    d = grid.grid_points()  # (40, 40, 40, 3) mm, centred on the origin
    array = np.zeros(shape, np.uint8)
    array[((d / [28.0, 22.0, 18.0]) ** 2).sum(-1) < 1] = 1
    array[(((d - [5.0, 3.0, 0.0]) / 9.0) ** 2).sum(-1) < 1] = 2
    fixed = grid.with_array(array)
    inside = d[array > 0]
    truth = GaussianBumps.random(inside.min(0), inside.max(0), max_displacement=4.0, scale=16.0, count=4,
                                 rng=np.random.default_rng(7))
    moving = deform_labels(fixed, truth)
    volreg.write_labels(fixed, folder / "fixed.nii.gz")
    volreg.write_labels(moving, folder / "moving.nii.gz")
    return fixed, moving


def test_readme_python_example_runs_and_registers(tmp_path, monkeypatch):
    missing = [name for name in SNIPPET_NAMES if name not in volreg._API]
    if missing:
        pytest.skip(f"the README's Python example needs {', '.join(missing)} in the public API (volreg._API)")
    fixed, moving = _pair(tmp_path)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(_python_snippet(), str(README) + " (Python example)", "exec"), namespace)

    result, report = namespace["result"], namespace["report"]
    tau = result.warp
    assert isinstance(tau, volreg.KernelWarp) and tau.levels
    # The warp brings the moving labels onto the fixed ones.
    warped = volreg.read_labels(tmp_path / "out" / "warped.nii.gz")
    assert warped.same_geometry(fixed) and warped.array.dtype == moving.array.dtype
    assert set(np.unique(warped.array)) <= {0, 1, 2}
    scores_before = volreg.label_scores(fixed.array, moving.array, [1, 2], fixed.spacing)
    scores_after = volreg.label_scores(fixed.array, warped.array, [1, 2], fixed.spacing)
    for v in (1, 2):
        assert scores_after[v]["dice"] > scores_before[v]["dice"]
    # The saved model is the warp registered once (the outputs are written from it); the inverse undoes it.
    x = fixed.grid_points().reshape(-1, 3)[::97]
    assert np.array_equal(volreg.KernelWarp.load(tmp_path / "out" / "model.npz")(x), tau(x))
    assert np.abs(namespace["back"](tau(x)) - x).max() < 1e-3
    # write_outputs wrote every output of `volreg register` and reports an improvement.
    for name in ("warp.nii.gz", "inverse_warp.nii.gz", "warped.nii.gz", "model.npz", "jacobian.nii.gz",
                 "report.json", "report.png", "warp.h5", "inverse_warp.h5"):
        assert (tmp_path / "out" / name).is_file(), name
    assert report.mean_dice["after"] > report.mean_dice["before"]
    assert namespace["warped"].shape == fixed.shape


def test_readme_is_an_overview():
    size = len(README.read_text(encoding="utf-8"))
    assert size <= README_MAX_CHARS, f"README.md has {size} characters; expected at most {README_MAX_CHARS} (details go to docs/)"


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = heading.strip().lower()
    text = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    headings = re.findall(r"^#{1,6}\s+(.*?)\s*#*\s*$", _without_code(path.read_text(encoding="utf-8")), flags=re.M)
    return {_slug(h) for h in headings}


@pytest.mark.parametrize("path", [README, BENCHMARKS, *DOCS], ids=lambda p: p.relative_to(REPO).as_posix())
def test_relative_links_point_to_files_and_headings(path):
    text = _without_code(path.read_text(encoding="utf-8"))
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        linked = (path.parent / file_part).resolve() if file_part else path
        if not linked.exists():
            broken.append(f"{target} (no such file)")
        elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
            broken.append(f"{target} (no such heading)")
    assert not broken, f"{path.name}: " + "; ".join(broken)


def test_docs_exist_and_every_public_name_is_documented():
    names = {p.name for p in DOCS}
    assert {"commands.md", "python-api.md", "conventions.md", "reliability.md", "method.md", "design.md"} <= names
    api = (REPO / "docs" / "python-api.md").read_text(encoding="utf-8")
    undocumented = [name for name in volreg._API if not re.search(rf"`{re.escape(name)}\b", api)]
    assert not undocumented, f"docs/python-api.md does not mention {undocumented}"


def test_every_command_is_documented():
    from volreg.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices
    text = (REPO / "docs" / "commands.md").read_text(encoding="utf-8")
    anchors = _anchors(REPO / "docs" / "commands.md")
    missing = [c for c in commands if c not in anchors]
    assert not missing, f"docs/commands.md has no section for {missing}"
    for name, sub in commands.items():
        options = [s for a in sub._actions for s in a.option_strings if s.startswith("--") and s != "--help"]
        absent = [o for o in options if o not in text]
        assert not absent, f"docs/commands.md does not mention {absent} of `volreg {name}`"


def test_benchmarks_cover_every_script_with_commands_that_exist():
    text = BENCHMARKS.read_text(encoding="utf-8")
    scripts = sorted(p.name for p in (REPO / "benchmarks").glob("bench_*.py"))
    headings = re.findall(r"^## .*$", text, flags=re.M)
    for script in scripts:
        assert any(script in h for h in headings), f"BENCHMARKS.md has no section for {script}"
    commands = re.findall(r"^\S*python\S* (\S+\.py)", text, flags=re.M)
    assert commands, "BENCHMARKS.md shows no command"
    for command in commands:
        assert (REPO / command).is_file(), f"BENCHMARKS.md runs {command}, which is not in the repository"
    assert not re.findall(r"^(?!\.venv/bin/python )\S*python\S* \S+\.py", text, flags=re.M), \
        "BENCHMARKS.md commands should run .venv/bin/python from the repository root"


@pytest.mark.parametrize("path", [README, BENCHMARKS, *DOCS], ids=lambda p: p.relative_to(REPO).as_posix())
def test_no_machine_paths_or_development_notes(path):
    text = path.read_text(encoding="utf-8")
    for pattern in (r"\bsessions?\b", r"\bissues? #?\d", r"/tmp/", r"/work/", r"/home/", r"~/"):
        assert not re.search(pattern, text, flags=re.I), f"{path.name} contains {pattern!r}"
