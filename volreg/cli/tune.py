"""``volreg tune``: score a grid of warp settings by consistency and hold-out, write the best as a protocol."""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
import time
from pathlib import Path

from volreg.cli._common import PROG, _label_list, _load_landmarks, output_path
from volreg.errors import ProtocolError, UsageError, excerpt

__all__ = ["add_parser", "parse_grid", "run"]

OUTPUTS = ("tune.csv", "tuned.toml")


def add_parser(commands) -> None:
    """Add ``tune`` to the ``volreg`` subcommands."""
    tune = commands.add_parser(
        "tune",
        help="choose warp settings by consistency and hold-out",
        description="Register A to B and B to A for every combination of the --grid values (replacing the "
        "protocol's [warp] settings), score each by the inverse-consistency error plus the hold-out surface "
        "distance (plus the landmark error with --landmarks), all in mm, and write OUTDIR/tune.csv (one row per "
        "setting) and OUTDIR/tuned.toml (the protocol with the best setting).",
    )
    tune.add_argument("a", metavar="A", type=Path, help="label volume A")
    tune.add_argument("b", metavar="B", type=Path, help="label volume B")
    tune.add_argument("-o", "--output", metavar="OUTDIR", type=output_path, required=True, help="output directory")
    tune.add_argument("--grid", metavar="KEY=V1,V2,...", action="append", required=True,
                      help="[warp] settings and their candidate values, e.g. lambda_loc=10,100,alpha=0,10 (repeatable)")
    tune.add_argument("--protocol", metavar="NAME|FILE", default="default",
                      help="protocol giving every other setting (default: default)")
    tune.add_argument("--drive-labels", metavar="IDS", type=_label_list, default=None,
                      help="labels that drive the warps (default: as `volreg register`)")
    tune.add_argument("--landmarks", metavar=("A_PTS", "B_PTS"), nargs=2, type=Path, default=None,
                      help="corresponding points of A and B (.csv x,y,z LPS mm, .fcsv, .mrk.json)")
    tune.add_argument("--force", action="store_true", help="write into an existing OUTDIR, replacing outputs")
    tune.add_argument("--quiet", action="store_true", help="no per-setting lines on stderr")
    tune.set_defaults(run=run)


def _not_a_number(key: str, token: str) -> UsageError:
    """The error for a --grid value that is not a number: where ``key`` is no numeric [warp] setting,
    the table it is a setting of (``kind`` of [linear]) or the known names."""
    import dataclasses

    from volreg import settings

    tables = {"warp": settings.WarpSettings, "linear": settings.LinearSettings, "surface": settings.SurfaceSettings,
              "review": settings.ReviewSettings, "outputs": settings.OutputSettings}
    known = [f.name for f in dataclasses.fields(settings.WarpSettings)]
    shown = excerpt(key, quote=False)
    if key not in known:
        owner = next((t for t, cls in tables.items() if key in {f.name for f in dataclasses.fields(cls)}), None)
        where = f"`{shown}` is a setting of [{owner}], not of [warp]" if owner else f"`{shown}` is no [warp] setting"
        return UsageError(f"--grid: {where}; --grid tunes the [warp] settings ({', '.join(known)}); "
                          + (f"set [{owner}] {shown} in the --protocol file." if owner else "expected one of them."))
    return UsageError(f"--grid: `{shown}` value {excerpt(token)} is not a number.")


def parse_grid(specs: list[str]) -> dict[str, list[float]]:
    """``["lambda_loc=10,100,alpha=0,10"]`` -> ``{"lambda_loc": [10.0, 100.0], "alpha": [0.0, 10.0]}``.

    A token ``key=value`` starts a key; bare tokens add values to the last key.
    ``--grid`` may be repeated.
    """
    grid: dict[str, list[float]] = {}
    key = None
    for spec in specs:
        for token in (t.strip() for t in spec.split(",")):
            if not token:
                continue
            if "=" in token:
                key, token = (s.strip() for s in token.split("=", 1))
                if not key or key in grid:
                    raise UsageError(f"--grid: {'a setting name is missing' if not key else f'`{excerpt(key, quote=False)}` is given twice'} "
                                     "in " + excerpt(spec) + "; expected KEY=V1,V2,... such as lambda_loc=10,100,alpha=0,10.")
                grid[key] = []
                if not token:  # "alpha=" alone: no value yet
                    continue
            if key is None:
                raise UsageError(f"--grid: expected KEY=V1,V2,... such as lambda_loc=10,100, got {excerpt(spec)}.")
            try:
                value = float(token)
            except ValueError:
                raise _not_a_number(key, token) from None
            if not math.isfinite(value):
                raise UsageError(f"--grid: `{excerpt(key, quote=False)}` value {excerpt(token)} is not finite.")
            if value in grid[key]:  # the same registration twice
                raise UsageError(f"--grid: `{excerpt(key, quote=False)}` value {excerpt(token)} is given twice; expected distinct values.")
            grid[key].append(int(value) if key == "max_iter" and value.is_integer() else value)
    if not grid or any(not values for values in grid.values()):
        raise UsageError("--grid: expected at least one value for every setting, such as lambda_loc=10,100.")
    return grid


def _print_score(i: int, n: int, values: dict, row: dict) -> None:
    """The line on stderr for the ``i``-th of ``n`` settings scored."""
    settings = ", ".join(f"{k}={v:.12g}" for k, v in values.items())
    print(f"{PROG} tune: [{i + 1}/{n}] {settings}: consistency {row['consistency_mm']:.3f} mm, "
          f"hold-out {row['holdout_mm']:.3f} mm, score {row['score_mm']:.3f} mm ({row['seconds']:.0f} s)",
          file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    """``volreg tune A B -o OUTDIR --grid KEY=V1,V2,...``."""
    from volreg.evaluation.tune import grid_settings, tune_settings
    from volreg.io import read_labels, write_text
    from volreg.io._atomic import output_folder
    from volreg.io.protocol import load_protocol, protocol_to_toml
    from volreg.pipeline.checks import check_pair, check_pair_headers
    from volreg.settings import replace_settings

    start = time.perf_counter()
    protocol = load_protocol(args.protocol)
    grid = parse_grid(args.grid)
    combos = grid_settings(grid)
    for values in combos:  # validate every candidate before registering anything
        try:
            replace_settings(protocol, values)
        except ProtocolError as exc:
            raise UsageError(f"--grid: {exc}") from None
    check_pair_headers(args.a, args.b)  # before any voxel is decompressed
    a = read_labels(args.a)
    b = read_labels(args.b)
    check_pair(a, b, args.a, args.b, linear=protocol.linear.kind)
    landmarks = _load_landmarks(args, a, b)
    outdir: Path = args.output
    paths = {name: outdir / name for name in OUTPUTS}
    with output_folder(outdir, args.force, outputs=OUTPUTS) as folder:
        paths = folder.check_writable(OUTPUTS, force=args.force)  # in staging, swapped into outdir at the end
        rows, best = tune_settings(a, b, protocol, grid, drive_labels=args.drive_labels, landmarks=landmarks,
                                   on_score=None if args.quiet else _print_score)
        table = io.StringIO()
        writer = csv.DictWriter(table, fieldnames=[*grid, "consistency_mm", "consistency_p95_mm", "holdout_mm",
                                                   "landmark_mm", "score_mm", "seconds", "chosen"], lineterminator="\n")
        writer.writeheader()
        for i, row in enumerate(rows):
            writer.writerow({**{k: ("" if v is None else v) for k, v in row.items()}, "chosen": int(i == best)})
        write_text(table.getvalue(), paths["tune.csv"], force=args.force)
        folder.record(paths["tune.csv"])
        chosen = replace_settings(protocol, combos[best], name=f"{protocol.name}-tuned")
        settings = ", ".join(f"{k}={v:.12g}" for k, v in combos[best].items())
        comment = (f"written by `volreg tune` from protocol `{protocol.name}`: {settings} scored best of {len(combos)} "
                   f"(score {rows[best]['score_mm']:.4f} mm = consistency + hold-out surface distance"
                   f"{' + landmark error' if landmarks is not None else ''}; see tune.csv)")
        write_text(protocol_to_toml(chosen, comment=comment), paths["tuned.toml"], force=args.force)
        folder.record(paths["tuned.toml"])
    print(f"{PROG} tune: best of {len(combos)} settings: {settings} (score {rows[best]['score_mm']:.3f} mm); "
          f"{outdir / 'tuned.toml'} ({time.perf_counter() - start:.0f} s)")
    return 0
