"""``volreg protocols``: list the shipped protocol presets."""

from __future__ import annotations

import argparse

__all__ = ["add_parser", "run"]


def add_parser(commands) -> None:
    """Add ``protocols`` to the ``volreg`` subcommands."""
    protocols = commands.add_parser("protocols", help="list the shipped protocols",
                                    description="List the protocol presets, one line each.")
    protocols.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``volreg protocols``: one line per preset, its name and description."""
    from volreg.io.protocol import PROTOCOL_DIR, load_protocol

    for path in sorted(PROTOCOL_DIR.glob("*.toml")):
        p = load_protocol(path)
        print(f"{p.name:<10} {p.description}")
    return 0
