"""What ``volreg register-surfaces``, ``morph`` and ``transfer`` share on the command line: the data
options, the choice of GIFTI outputs and the plausibility warnings.  Reading, registering and writing
surfaces is the library's (:mod:`volreg.outputs.surfaces`)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from volreg.cli._common import _warn

if TYPE_CHECKING:  # imported where used, so that the parsers load without numpy and the pipeline
    from volreg.evaluation.review import Finding


def _add_data_options(parser, *roles: str) -> None:
    """``--source-data`` / ``--target-data FILE ...``: GIFTI per-vertex data files of SOURCE / TARGET."""
    for role in roles:
        parser.add_argument(f"--{role}-data", metavar="FILE", nargs="+", action="extend", type=Path, default=[],
                            help=f"GIFTI data files (.shape.gii .func.gii .label.gii) over the vertices of {role.upper()}; "
                            "each is an array named after its file (lh.thickness for lh.thickness.shape.gii)")


def _wants_gifti(args, source_path: Path) -> bool:
    """Whether to write GIFTI outputs: SOURCE is GIFTI, or ``--gifti`` was given."""
    from volreg.io.gifti import is_gifti

    return bool(getattr(args, "gifti", False)) or is_gifti(source_path)


def _warn_findings(command: str, findings: list[Finding]) -> None:
    """One warning line on stderr per finding."""
    for finding in findings:
        _warn(command, finding.message)
