"""``volreg tune``: score a grid of warp settings by consistency and hold-out, write the best as a protocol."""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
import time
from pathlib import Path

from volreg.cli._common import PROG, _remove_directories
from volreg.errors import UsageError
from volreg.io import check_writable, read_labels, write_text
from volreg.errors import ProtocolError
from volreg.io.protocol import load_protocol, protocol_to_toml
from volreg.settings import replace_settings
from volreg.features.label_surfaces import label_surfaces
from volreg.evaluation.tune import grid_settings, score_setting
from volreg.cli._common import _check_pair, _load_landmarks, _prepare_outdir

__all__ = ["run_tune", "parse_grid"]

OUTPUTS = ("tune.csv", "tuned.toml")


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
                    raise UsageError(f"--grid: {'a setting name is missing' if not key else f'`{key}` is given twice'} "
                                     "in " + repr(spec) + "; expected KEY=V1,V2,... such as lambda_loc=10,100,alpha=0,10.")
                grid[key] = []
                if not token:  # "alpha=" alone: no value yet
                    continue
            if key is None:
                raise UsageError(f"--grid: expected KEY=V1,V2,... such as lambda_loc=10,100, got {spec!r}.")
            try:
                value = float(token)
            except ValueError:
                raise UsageError(f"--grid: `{key}` value {token!r} is not a number.") from None
            if not math.isfinite(value):
                raise UsageError(f"--grid: `{key}` value {token!r} is not finite.")
            grid[key].append(int(value) if key == "max_iter" and value.is_integer() else value)
    if not grid or any(not values for values in grid.values()):
        raise UsageError("--grid: expected at least one value for every setting, such as lambda_loc=10,100.")
    return grid


def run_tune(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    protocol = load_protocol(args.protocol)
    grid = parse_grid(args.grid)
    combos = grid_settings(grid)
    for values in combos:  # validate every candidate before registering anything
        try:
            replace_settings(protocol, values)
        except ProtocolError as exc:
            raise UsageError(f"--grid: {exc}") from None
    a = read_labels(args.a)
    b = read_labels(args.b)
    _check_pair(a, b, args.a, args.b)
    landmarks = _load_landmarks(args, a, b)
    outdir: Path = args.output
    created = _prepare_outdir(outdir, args.force)
    paths = {name: outdir / name for name in OUTPUTS}
    written: list[Path] = []
    try:
        check_writable(paths.values(), force=args.force)
        a_surfaces = label_surfaces(a, on_small="warn", smoothing=protocol.surface.smoothing)
        b_surfaces = label_surfaces(b, on_small="warn", smoothing=protocol.surface.smoothing)
        rows = []
        for i, values in enumerate(combos):
            row = score_setting(a, b, protocol, values, a_surfaces=a_surfaces, b_surfaces=b_surfaces,
                                drive_labels=args.drive_labels, landmarks=landmarks)
            rows.append(row)
            if not args.quiet:
                settings = ", ".join(f"{k}={v:g}" for k, v in values.items())
                print(f"{PROG} tune: [{i + 1}/{len(combos)}] {settings}: consistency {row['consistency_mm']:.3f} mm, "
                      f"hold-out {row['holdout_mm']:.3f} mm, score {row['score_mm']:.3f} mm ({row['seconds']:.0f} s)",
                      file=sys.stderr)
        best = min(range(len(rows)), key=lambda i: rows[i]["score_mm"])
        table = io.StringIO()
        writer = csv.DictWriter(table, fieldnames=[*grid, "consistency_mm", "consistency_p95_mm", "holdout_mm",
                                                   "landmark_mm", "score_mm", "seconds", "chosen"], lineterminator="\n")
        writer.writeheader()
        for i, row in enumerate(rows):
            writer.writerow({**{k: ("" if v is None else v) for k, v in row.items()}, "chosen": int(i == best)})
        write_text(table.getvalue(), paths["tune.csv"], force=args.force)
        written.append(paths["tune.csv"])
        chosen = replace_settings(protocol, combos[best], name=f"{protocol.name}-tuned")
        settings = ", ".join(f"{k}={v:g}" for k, v in combos[best].items())
        comment = (f"written by `volreg tune` from protocol `{protocol.name}`: {settings} scored best of {len(combos)} "
                   f"(score {rows[best]['score_mm']:.4f} mm = consistency + hold-out surface distance"
                   f"{' + landmark error' if landmarks is not None else ''}; see tune.csv)")
        write_text(protocol_to_toml(chosen, comment=comment), paths["tuned.toml"], force=args.force)
        written.append(paths["tuned.toml"])
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        _remove_directories(created)
        raise
    print(f"{PROG} tune: best of {len(combos)} settings: {settings} (score {rows[best]['score_mm']:.3f} mm); "
          f"{paths['tuned.toml']} ({time.perf_counter() - start:.0f} s)")
    return 0
