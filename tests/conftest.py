"""Test tiers and shared fixtures.

Every test has exactly one tier, a pytest marker:

- ``unit``: one function or class on small arrays, well under a second;
- ``integration``: several modules together on small data (a registration of small volumes in
  process, a command run in process);
- ``system``: a whole command in a fresh interpreter, a cold compilation of the numba loops,
  signals sent to a running process, or anything else of several seconds.

A test module names its tier in :data:`MODULE_TIERS` below (one line per module, so a new module
must be placed: collection fails until it is); a test that differs from its module's tier says so
itself with ``@pytest.mark.system`` (or ``unit`` / ``integration``), which wins.  ``make test`` runs
every tier, ``make test-quick`` all but ``system`` (``pytest -m "not system"``).

Helpers that several modules share live in ``helpers.py`` (small label volumes, NIfTI files, the
command line in process) and ``shapes.py`` (analytic shapes with known signed distances).
"""

import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, os.path.dirname(__file__))

from helpers import TEST_PROTOCOL  # noqa: E402 (after the path)

TIERS = ("unit", "integration", "system")

#: Each test module's tier (a test's own tier marker wins over its module's).
MODULE_TIERS = {
    "test_api_arguments.py": "integration",
    "test_apply_points.py": "integration",
    "test_batch.py": "system",
    "test_cli.py": "integration",
    "test_cli_thin.py": "unit",
    "test_consistency.py": "integration",
    "test_crash.py": "system",
    "test_demo_data.py": "unit",
    "test_distance_maps.py": "integration",
    "test_examples.py": "system",
    "test_feature_batch.py": "unit",
    "test_fit_valid.py": "unit",
    "test_gifti.py": "integration",
    "test_grid.py": "unit",
    "test_implicit.py": "unit",
    "test_interop.py": "integration",
    "test_inverse.py": "unit",
    "test_io.py": "unit",
    "test_kernels.py": "unit",
    "test_known_deformation.py": "system",
    "test_label_interpolation.py": "integration",
    "test_layout.py": "unit",
    "test_linear_fit.py": "integration",
    "test_linear_least_rotation.py": "integration",
    "test_linear_model.py": "integration",
    "test_objective.py": "unit",
    "test_output_folders.py": "integration",
    "test_outputs_library.py": "integration",
    "test_pipeline.py": "integration",
    "test_precompile.py": "system",
    "test_properties.py": "unit",
    "test_protocol.py": "unit",
    "test_readme.py": "integration",
    "test_readonly_install.py": "system",
    "test_register.py": "integration",
    "test_register_pose.py": "system",
    "test_reliability.py": "integration",
    "test_reliability_files.py": "integration",
    "test_reliability_links.py": "integration",
    "test_reliability_memory.py": "integration",
    "test_reliability_messages.py": "integration",
    "test_reliability_notices.py": "integration",
    "test_reliability_pairs.py": "integration",
    "test_reliability_parsers.py": "integration",
    "test_reliability_values.py": "integration",
    "test_report_figure.py": "unit",
    "test_review.py": "unit",
    "test_sampling.py": "unit",
    "test_settings.py": "unit",
    "test_surface_cli.py": "integration",
    "test_surface_inputs.py": "unit",
    "test_surfaces.py": "unit",
    "test_template.py": "system",
    "test_template_shape.py": "unit",
    "test_shape_model.py": "integration",
    "test_threads.py": "integration",
    "test_tune.py": "integration",
    "test_warp.py": "unit",
}


def pytest_collection_modifyitems(config, items):
    """Give each test without a tier marker of its own its module's tier."""
    unplaced, doubled = set(), []
    for item in items:
        own = {m.name for m in item.iter_markers() if m.name in TIERS}
        if len(own) > 1:
            doubled.append(item.nodeid)
        if own:
            continue
        name = Path(str(item.fspath)).name
        tier = MODULE_TIERS.get(name)
        if tier is None:
            unplaced.add(name)
            continue
        item.add_marker(getattr(pytest.mark, tier))
    if doubled:
        raise pytest.UsageError(f"tests with more than one tier marker: {doubled[:5]}")
    if unplaced:
        raise pytest.UsageError(f"test modules without a tier in tests/conftest.py MODULE_TIERS: {sorted(unplaced)}")


@pytest.fixture
def test_protocol_file(tmp_path) -> Path:
    """A protocol file with a coarse finest warp level (helpers.TEST_PROTOCOL): registrations in seconds."""
    path = tmp_path / "p.toml"
    path.write_text(TEST_PROTOCOL)
    return path
