"""Cohorts of registrations as Dask tasks, on this machine or on a cluster (what ``volreg batch`` runs).

Each registration is one task that reads its two label volumes from their paths (nothing large
goes through the scheduler) and writes a complete ``volreg register`` (or ``consistency``) folder
under ``OUTDIR/pairs/``.  A pair whose outputs are complete and whose inputs' checksums and settings
(protocol, mode and volreg version) are those recorded when it finished is skipped on a rerun
(:func:`pair_result_done`); any other pair is (re)done, after removing temporary files a killed
worker left in its folder.  A failing pair is recorded with its error and does not stop the others;
Dask retries the task of a worker that dies.

:func:`register_cohort` runs a whole cohort; its parts (:func:`read_manifest`, :func:`plan_pairs`,
:func:`pair_folders`, :func:`settings_fingerprint`, :func:`pair_result_done`, :func:`run_pair`) serve
other cohort jobs too.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import logging
import numbers
import os
import re
import shutil
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from volreg.errors import ArgumentTypeError, CohortInterrupted, SchedulerUnavailable, UsageError, VolregError, exception_text, excerpt, full_disk
from volreg.io import atomic_output, read_labels, user_path, write_json, write_text
from volreg.io._atomic import make_directory
from volreg.io.documents import parse_json
from volreg.io.protocol import load_protocol
from volreg.io.summary import file_sha256
from volreg.outputs.consistency import CONSISTENCY_OUTPUTS, write_consistency_test
from volreg.outputs.registration import REGISTRATION_OUTPUTS, registration_outputs, write_registration
from volreg.pipeline.arguments import bool_argument, callable_argument, path_argument
from volreg.pipeline.checks import check_pair, check_pair_headers
from volreg.progress import ProgressBars

__all__ = ["COLUMNS", "PAIR_MODES", "CohortSummary", "pair_folders", "pair_outputs", "pair_result_done", "plan_pairs", "read_manifest",
           "register_cohort", "run_pair", "settings_fingerprint", "write_cohort_plot", "write_cohort_table"]

#: The columns of ``batch.csv``.
COLUMNS = ["fixed_id", "moving_id", "status", "error", "mean_dice_before", "mean_dice_after", "consistency_mean_mm",
           "consistency_p95_mm", "folded_fraction", "review", "seconds", "outdir"]

ProgressCallback = Callable[[str, int, int], None]


#: The longest id (in bytes) of a manifest: a pair's folder ``A__B``, with the hidden prefix and
#: suffix of its working folder, stays within the usual 255-byte name limit.
MAX_ID_BYTES = 100


def read_manifest(path: Path) -> list[tuple[str, Path]]:
    """The subjects of a cohort's manifest: ``id,path`` rows (header required; relative paths are
    relative to the manifest).

    Returns
    -------
    list of (str, Path)
        Each subject's id and file, in the manifest's order.

    Raises
    ------
    UsageError
        A missing, unreadable or malformed manifest, naming its line.
    """
    if not path.is_file():
        raise UsageError(f"MANIFEST `{path}` does not exist or is not a file.")
    try:
        # utf-8-sig: a byte-order mark (as spreadsheet programs write) is not part of the first column's name;
        # the csv module splits the lines itself (a quoted field may hold a line break, and str.splitlines
        # would also split at U+2028 and other separators inside a value)
        with path.open(encoding="utf-8-sig", newline="") as fh:
            reader = csv.DictReader(fh)
            rows, lines = [], []
            for row in reader:
                rows.append(row)
                lines.append(reader.line_num)  # the file line the row ends on (blank lines are skipped)
    except PermissionError:
        raise UsageError(f"MANIFEST `{path}` is not readable (permission denied); expected a file you can read.") from None
    except OSError as exc:
        raise UsageError(f"MANIFEST `{path}` cannot be read: {exc.strerror or exc}.") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise UsageError(f"MANIFEST `{path}` is not a CSV file: {exception_text(exc)}.") from None
    if not rows or not {"id", "path"} <= set(rows[0]):
        read = f" (read: {excerpt(','.join(str(c) for c in rows[0] if c is not None), quote=False)})" if rows else ""
        raise UsageError(f"MANIFEST `{path}` needs a header with the columns id,path{read} and at least one row; "
                         "expected exactly those names, without spaces around them.")
    subjects, seen = [], set()
    for i, row in zip(lines, rows):
        sid, p = (row.get("id") or "").strip(), (row.get("path") or "").strip()
        if not sid or not p:
            raise UsageError(f"MANIFEST `{path}` line {i}: expected an id and a path, got {excerpt(row)}.")
        if None in row:
            raise UsageError(f"MANIFEST `{path}` line {i}: {len(row) - 1 + len(row[None])} fields where the header "
                             f"names {len(row) - 1}; expected one value per column (quote a path holding a comma).")
        if sid in seen:
            raise UsageError(f"MANIFEST `{path}` line {i}: id `{excerpt(sid, quote=False)}` is listed twice; expected unique ids.")
        if any(c in sid for c in "/\\") or any(c < " " or c == "\x7f" for c in sid):
            raise UsageError(f"MANIFEST `{path}` line {i}: id {excerpt(sid)} must not contain path separators or control "
                             "characters; expected a name for its results' folder.")
        if len(os.fsencode(sid)) > MAX_ID_BYTES:
            raise UsageError(f"MANIFEST `{path}` line {i}: id `{excerpt(sid, quote=False)}` is {len(os.fsencode(sid))} "
                             f"bytes long; expected at most {MAX_ID_BYTES}, so that a pair's folder (A__B) is a "
                             "name the system allows.")
        if sid in (".", ".."):
            raise UsageError(f"MANIFEST `{path}` line {i}: id `{excerpt(sid, quote=False)}` names a special folder; expected a name for its "
                             "results' folder.")
        if sid.startswith(".") or ".volreg-" in sid:
            # a pair's folder of such a name could be taken for another pair's hidden working folder
            # (``.A__B.volreg-old-PID-HEX``), which recovery after a killed run renames or removes
            raise UsageError(f"MANIFEST `{path}` line {i}: id `{excerpt(sid, quote=False)}` could name one of volreg's hidden working "
                             "folders (it starts with '.' or holds '.volreg-'); expected an id without either.")
        if "\x00" in p:
            raise UsageError(f"MANIFEST `{path}` line {i}: path {excerpt(p)} holds a NUL byte; expected a file path.")
        seen.add(sid)
        q = Path(p)
        subjects.append((sid, q if q.is_absolute() else path.parent / q))
    return subjects


def plan_pairs(subjects, template: tuple[str, Path] | None, mode: str) -> list[tuple[tuple[str, Path], tuple[str, Path]]]:
    """(fixed, moving) pairs: every subject to the template, or all ordered pairs, or consecutive ones."""
    if template is not None:
        return [(template, s) for s in subjects]
    if mode == "consecutive":
        return [(subjects[i], subjects[i + 1]) for i in range(len(subjects) - 1)]
    return [(a, b) for a in subjects for b in subjects if a[0] != b[0]]


def pair_folders(pairs, manifest: Path) -> list[str]:
    """The folder name ``FIXED__MOVING`` of each pair; refuse two pairs that would share one.

    Ids are joined with ``__``, so ``a`` + ``b__c`` and ``a__b`` + ``c`` would both give
    ``a__b__c`` (and one pair would silently overwrite, or be skipped for, the other).

    Raises
    ------
    UsageError
        Naming both pairs and the folder they would share.
    """
    names: list[str] = []
    owner: dict[str, tuple[str, str]] = {}
    for (fid, _), (mid, _) in pairs:
        name = f"{fid}__{mid}"
        if name in owner:
            other = owner[name]
            raise UsageError(
                f"MANIFEST `{manifest}`: pairs ({other[0]}, {other[1]}) and ({fid}, {mid}) would share the folder "
                f"pairs/{name}; expected ids that stay distinct when joined with '__' (rename one, e.g. without '__')."
            )
        owner[name] = (fid, mid)
        names.append(name)
    return names


def settings_fingerprint(protocol, consistency: bool) -> str:
    """SHA-256 of what decides a pair's result besides its inputs: the protocol's settings, the mode
    (``register`` or ``consistency``) and the volreg version (the protocol's name and description aside)."""
    from volreg import __version__

    settings = {k: v for k, v in protocol.to_dict().items() if k not in ("name", "description")}
    text = json.dumps({"settings": settings, "mode": "consistency" if consistency else "register",
                       "volreg": str(__version__)}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


#: Temporary files of :func:`volreg.io.atomic_output` (``.tmp-1a2b3c4d-NAME``).
_TEMPORARY = re.compile(r"^\.tmp-[0-9a-f]{8}-")


def _remove_temporaries(outdir: Path) -> int:
    """Remove temporary files left in a pair folder by a worker that was killed; return how many."""
    removed = 0
    if outdir.is_dir():
        for p in outdir.rglob(".tmp-*"):
            if _TEMPORARY.match(p.name) and (p.is_file() or p.is_symlink()):
                p.unlink(missing_ok=True)
                removed += 1
    return removed


def pair_outputs(protocol=None, consistency: bool = False) -> tuple[str, ...]:
    """Every file a pair's folder holds once done with ``protocol`` (default: the default protocol),
    relative to it: a registration's outputs (:func:`~volreg.outputs.registration.registration_outputs`),
    or with ``consistency`` the consistency test's and both directions' in ``forward/`` and ``backward/``."""
    registration = registration_outputs(protocol)
    if not consistency:
        return registration
    return (*CONSISTENCY_OUTPUTS, *(f"{way}/{name}" for way in ("forward", "backward") for name in registration))


def _output_checksums(outdir: Path, names) -> dict[str, str]:
    """SHA-256 of each of the files ``names`` in ``outdir``."""
    return {name: file_sha256(outdir / name) for name in names}


def pair_result_done(outdir: Path, sha: tuple[str, str], consistency: bool, fingerprint: str | None = None,
                     protocol=None) -> dict | None:
    """The saved row of a complete pair whose inputs still have the checksums ``sha`` and whose
    settings had the fingerprint ``fingerprint`` (see :func:`settings_fingerprint`), else None.

    Complete: every output that ``protocol`` writes (:func:`pair_outputs`) is there, and, where the
    row records their checksums (``outputs``), each still has its checksum.
    """
    row_file = outdir / "batch_row.json"
    if not row_file.is_file():
        return None
    try:
        row = parse_json(row_file.read_text(), f"Pair row `{row_file}`")
    except (OSError, ValueError):  # unreadable, not JSON or nested beyond reason: the pair is done again
        return None
    if not isinstance(row, dict) or row.get("status") != "done" or (row.get("fixed_sha256"), row.get("moving_sha256")) != sha:
        return None
    if fingerprint is not None and row.get("settings_sha256") != fingerprint:
        return None
    needed = pair_outputs(protocol, consistency)
    if not all((outdir / n).is_file() for n in needed):
        return None
    recorded = row.get("outputs")
    if recorded is not None:
        try:
            if not isinstance(recorded, dict) or any(recorded.get(n) != file_sha256(outdir / n) for n in needed):
                return None
        except OSError:
            return None
    return row


def _remove_earlier_results(outdir: Path) -> None:
    """Remove what an earlier run of a pair wrote (its row first, so that an interruption leaves
    the pair not done): a result redone with other inputs, or the other kind (a registration
    after a consistency test, or the reverse), would otherwise lie beside the new one."""
    (outdir / "batch_row.json").unlink(missing_ok=True)
    for name in (*REGISTRATION_OUTPUTS, *CONSISTENCY_OUTPUTS, "forward", "backward"):
        path = outdir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


def run_pair(fixed_id: str, fixed: str, moving_id: str, moving: str, outdir: str, protocol: str,
             consistency: bool = False) -> dict:
    """One task: register MOVING to FIXED (or both ways with ``consistency``) into ``outdir``; return its row.

    Runs on a worker; reads its inputs from their paths.  Input errors and a full disk
    (errors that recur on every try) become a ``failed`` row with the one-line message,
    not an exception, which Dask would retry; anything else propagates (a bug, or an
    error that may not recur).  A lost worker's task is run again by Dask whatever this
    returns.
    """
    start = time.perf_counter()
    out, fpath, mpath = Path(outdir), Path(fixed), Path(moving)
    row = {"fixed_id": fixed_id, "moving_id": moving_id, "outdir": str(out)}
    try:
        check_pair_headers(fpath, mpath)  # before any voxel is decompressed
        a, b = read_labels(fpath), read_labels(mpath)  # validates both; a clear error for a missing file
        sha = (file_sha256(fpath), file_sha256(mpath))
        proto = load_protocol(protocol)
        fingerprint = settings_fingerprint(proto, consistency)
        saved = pair_result_done(out, sha, consistency, fingerprint, protocol=proto)
        if saved is not None:
            return dict(saved, skipped=True)
        if (out / "batch_row.json").is_file():
            row["redone"] = True  # finished before, with other inputs or settings
        _remove_temporaries(out)
        _remove_earlier_results(out)
        check_pair(a, b, fpath, mpath, linear=proto.linear.kind)
        with ProgressBars(quiet=True) as progress:
            if consistency:
                inputs = {"A": {"path": str(fpath), "sha256": sha[0]}, "B": {"path": str(mpath), "sha256": sha[1]}}
                rep = write_consistency_test(a, b, out, protocol=proto, force=True, inputs=inputs, progress=progress)
                fwd = rep["directions"]["forward"]["mean_dice"]
                directions = rep["directions"]
                row.update(mean_dice_before=fwd["before"], mean_dice_after=fwd["after"],
                           consistency_mean_mm=rep["region"]["mean_mm"], consistency_p95_mm=rep["region"]["p95_mm"],
                           folded_fraction=max(d["folded_fraction"] for d in directions.values()),
                           review=_review_cell({name: d["review"] for name, d in directions.items()}))
            else:
                inputs = {"fixed": {"path": str(fpath), "sha256": sha[0]}, "moving": {"path": str(mpath), "sha256": sha[1]}}
                rep = write_registration(a, b, out, protocol=proto, force=True, inputs=inputs, progress=progress).to_json()
                row.update(mean_dice_before=rep["mean_dice"]["before"], mean_dice_after=rep["mean_dice"]["after"],
                           folded_fraction=rep["jacobian"]["folded_fraction"], review=_review_cell({"": rep["review"]}))
        row.update(status="done", error="", seconds=time.perf_counter() - start, fixed_sha256=sha[0], moving_sha256=sha[1],
                   settings_sha256=fingerprint, outputs=_output_checksums(out, pair_outputs(proto, consistency)))
        write_json({k: v for k, v in row.items() if k != "redone"}, out / "batch_row.json", force=True)
    except VolregError as exc:
        row.update(status="failed", error=" ".join(str(exc).split()), seconds=time.perf_counter() - start)
    except Exception as exc:
        full = full_disk(exc)
        if full is None:
            raise  # a bug, or an error that may not recur (Dask retries the task)
        # A full disk fails the same way on every try: a row, which Dask does not retry.
        name = full.filename if full.filename is not None else out
        row.update(status="failed", seconds=time.perf_counter() - start,
                   error=f"{full.strerror or os.strerror(full.errno)} writing `{user_path(name)}`")
    return row


def _review_cell(reviews: dict[str, dict]) -> str:
    """The batch.csv cell of a pair's plausibility reviews (by direction: "forward", "backward";
    one, unnamed, for a registration): "ok", or their findings' messages joined by " | ", each
    after its direction's name where there are two."""
    named = len(reviews) > 1
    messages = [f"{name}: {f['message']}" if named else f["message"]
                for name, review in reviews.items() for f in review.get("findings", [])]
    return " | ".join(messages) if messages else "ok"


def write_cohort_table(rows: list[dict], path: Path) -> None:
    """``batch.csv``: one row per pair (:data:`COLUMNS`), failures with their error."""
    table = io.StringIO()
    writer = csv.DictWriter(table, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if row.get(k) is None else row.get(k, "")) for k in COLUMNS})
    write_text(table.getvalue(), path, force=True)


def write_cohort_plot(rows: list[dict], path: Path) -> None:
    """``batch.png``: the pairs' mean Dice before and after, and their seconds."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    done = [r for r in rows if r.get("status") == "done"]
    fig = Figure(figsize=(9, 4), dpi=90, facecolor="white")
    canvas = FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(1, 2)
    before = [r["mean_dice_before"] for r in done]
    after = [r["mean_dice_after"] for r in done]
    if done:
        ax1.boxplot([before, after])
        ax1.set_xticks([1, 2], ["before", "after"])
    ax1.set_title(f"mean Dice per pair ({len(done)} done, {len(rows) - len(done)} failed)")
    secs = [r["seconds"] for r in done]
    if secs:
        ax2.hist(secs, bins=min(10, len(secs)))
    ax2.set_title("seconds per registration")
    with atomic_output(path, force=True) as tmp:
        canvas.print_png(str(tmp))


def _close(client, cluster) -> None:
    """Close the Dask client and the local cluster, if any; one interrupted while starting may not
    close cleanly, and that is not worth a traceback."""
    for part in (client, cluster):
        if part is not None:
            try:
                part.close()
            except Exception:
                pass


def _close_started_clusters() -> None:
    """Close the local clusters an interrupt caught while they started (the ``LocalCluster``
    call had not returned, so there is no object to close), quietly.  Left to Dask's exit hook,
    their workers, still starting, fail its check of their status and it prints a traceback
    after the one-line report."""
    import atexit

    from distributed.deploy import spec

    for started in list(spec.SpecCluster._instances):
        try:
            started.close(timeout=10)
        except Exception:
            pass
    atexit.unregister(spec.close_clusters)


def _launching_a_process() -> bool:
    """Whether another thread is inside multiprocessing's spawn of a child (Dask starts its
    workers' processes on threads of its own), found from the threads' current frames."""
    me = threading.get_ident()
    for ident, frame in sys._current_frames().items():
        while ident != me and frame is not None:
            code = frame.f_code
            if code.co_name == "_launch" and "popen_" in Path(code.co_filename).name:
                return True
            frame = frame.f_back
    return False


def _await_worker_launches(wait_s: float = 5.0) -> None:
    """Wait (at most ``wait_s``) until no thread is inside multiprocessing's launch of a child.

    Dask launches its workers' processes on threads of its own.  A child whose parent exits while
    it still waits for its start-up data prints ``EOFError: Ran out of input`` after the one-line
    report; one that has its data starts, finds its parent gone and exits silently.  (Ending the
    children instead left the resource tracker warning about their semaphores after the report.)
    """
    end = time.monotonic() + wait_s
    while _launching_a_process() and time.monotonic() < end:
        time.sleep(0.02)


#: Seconds to wait for the Dask scheduler named by ``--scheduler`` to answer.
SCHEDULER_TIMEOUT_S = 30.0


def _check_scheduler_address(address: str) -> None:
    """Refuse a ``--scheduler`` that is not a Dask address (``tcp://HOST:PORT``, ``HOST:PORT``,
    ``tls://...``, ``inproc://...``) before any folder is made.

    Raises
    ------
    UsageError
        Naming the address and the form expected.
    """
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import backends

    try:
        scheme, location = parse_address(address, strict=False)
        if scheme not in backends:
            raise ValueError(f"unknown scheme {scheme!r} (Dask knows {', '.join(sorted(backends))})")
        if scheme in ("tcp", "tls"):
            host, port = parse_host_port(location)
            if not host or not 0 < int(port) < 65536:
                raise ValueError("no host or port out of range")
    except (ValueError, TypeError) as exc:
        raise UsageError(f"--scheduler `{address}`: {' '.join(str(exc).split())}; expected a Dask scheduler address "
                         "such as tcp://HOST:8786.") from None


@dataclass
class CohortSummary:
    """What :func:`register_cohort` did.

    Attributes
    ----------
    rows : list of dict
        One per pair, in the planned order (:data:`COLUMNS` and more): ``status`` ``"done"`` or
        ``"failed"`` (with ``error``), ``skipped`` (already done), ``redone``.
    table : Path
        ``batch.csv``.
    seconds : float
    """

    rows: list[dict] = field(default_factory=list)
    table: Path | None = None
    seconds: float = 0.0

    @property
    def failed(self) -> list[dict]:
        """The rows of the pairs that failed."""
        return [r for r in self.rows if r.get("status") != "done"]

    @property
    def skipped(self) -> int:
        """Pairs already done with the same inputs and settings."""
        return sum(1 for r in self.rows if r.get("skipped"))

    @property
    def redone(self) -> int:
        """Pairs done before with other inputs or settings, done again."""
        return sum(1 for r in self.rows if r.get("redone"))


def _start_client(scheduler: str | None, workers: int | None, created: list[Path]):
    """A Dask client of the scheduler at ``scheduler``, or of a new local cluster of ``workers``
    processes; ``(client, cluster)``."""
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, timeout=SCHEDULER_TIMEOUT_S), None
        except (OSError, ValueError) as exc:  # refused, unreachable, timed out, or no such address
            for folder in reversed(created):  # nothing was written: the folders made for it go
                with contextlib.suppress(OSError):
                    folder.rmdir()
            reason = " ".join(str(exc).split()) or type(exc).__name__
            raise SchedulerUnavailable(
                f"--scheduler `{scheduler}`: no Dask scheduler answered within {SCHEDULER_TIMEOUT_S:g} s "
                f"({reason[:200]}); expected the address of a running scheduler.") from None
    cluster = LocalCluster(n_workers=workers or 2, threads_per_worker=1, processes=True, dashboard_address=":0")
    return Client(cluster), cluster


def _stop_after_interrupt(client, cluster) -> None:
    """Stop the workers quietly after an interrupt, before the one line that reports it."""
    # what Dask's threads still say while the process ends (a nanny that failed to start, through
    # asyncio's or tornado's loggers or an exception ending a thread) adds nothing to that line
    for logger in ("distributed", "asyncio", "tornado"):
        logging.getLogger(logger).setLevel(logging.CRITICAL)
    threading.excepthook = lambda hooked: None
    _close(client, cluster)
    _close_started_clusters()
    _await_worker_launches()


def _check_request(manifest: Path, template: Path | None, mode: str, protocol: str, workers: int | None):
    """The pairs of a cohort request and their folders, checked before any folder or cluster."""
    load_protocol(protocol)  # validate before starting a cluster
    if workers is not None and workers < 1:
        raise UsageError(f"--workers {workers}: expected at least 1.")
    subjects = read_manifest(manifest)
    if template is not None:
        if not template.is_file():
            raise UsageError(f"--template `{template}` does not exist or is not a file.")
        template = ("template", template)
    pairs = plan_pairs(subjects, template, mode)
    if not pairs:
        raise UsageError(f"MANIFEST `{manifest}` gives no pair to register; expected at least two subjects "
                         "(or --template).")
    return pairs, pair_folders(pairs, manifest)


#: How :func:`register_cohort` may pair a cohort's subjects (:func:`plan_pairs`).
PAIR_MODES = ("all", "consecutive")


def _checked_arguments(manifest, outdir, template, pairs, consistency, protocol, workers, scheduler, progress,
                       notify) -> tuple:
    """:func:`register_cohort`'s arguments, checked before anything starts: paths as Paths, the pairing
    one of :data:`PAIR_MODES`, a protocol by its name or file (each worker reads it), a whole number of
    workers, the scheduler's address as text, callables."""
    manifest, outdir = path_argument(manifest, "manifest"), path_argument(outdir, "outdir")
    template = path_argument(template, "template", optional=True)
    if not isinstance(pairs, str):
        raise ArgumentTypeError(f"Expected `pairs` to be one of {', '.join(PAIR_MODES)}, got {type(pairs).__name__} "
                                f"{pairs!r:.60}.")
    if pairs not in PAIR_MODES:
        raise UsageError(f"Expected `pairs` to be one of {', '.join(PAIR_MODES)}, got {pairs!r:.60}.")
    if not isinstance(protocol, (str, os.PathLike)):
        raise ArgumentTypeError(f"Expected `protocol` to be a preset name or the path of a protocol file (each worker "
                                f"reads it), got {type(protocol).__name__}.")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, numbers.Integral)):
        raise ArgumentTypeError(f"Expected `workers` to be None or a whole number, got {type(workers).__name__} "
                                f"{workers!r:.60}.")
    if scheduler is not None and not isinstance(scheduler, str):
        raise ArgumentTypeError(f"Expected `scheduler` to be None or an address (str), got {type(scheduler).__name__}.")
    return (manifest, outdir, template, pairs, bool_argument(consistency, "consistency"), protocol,
            None if workers is None else int(workers), scheduler,
            callable_argument(progress, "progress", "progress(stage, done, total)"),
            callable_argument(notify, "notify", "of a line of news"))


def register_cohort(
    manifest: Path,
    outdir: Path,
    *,
    template: Path | None = None,
    pairs: str = "all",
    consistency: bool = False,
    protocol: str = "default",
    workers: int | None = None,
    scheduler: str | None = None,
    progress: ProgressCallback | None = None,
    notify: Callable[[str], None] | None = None,
    compile_helpers: list | None = None,
) -> CohortSummary:
    """Register a cohort's pairs as Dask tasks and write ``OUTDIR/pairs/FIXED__MOVING/``,
    ``OUTDIR/batch.csv`` and ``OUTDIR/batch.png``.

    Parameters
    ----------
    manifest : path-like
        CSV with the columns ``id,path`` (:func:`read_manifest`).
    outdir : path-like
        Created with missing parents; finished pairs in it are kept and skipped on a rerun.
    template : path-like, optional
        Register every subject to this volume; without it, ``pairs``.
    pairs : {"all", "consecutive"}
        Every ordered pair of subjects, or consecutive ones (:func:`plan_pairs`).
    consistency : bool
        Register both ways and run the consistency test per pair.
    protocol : str or path-like
        A preset name or a protocol file, for every registration.
    workers : int, optional
        Worker processes of a local cluster (default 2).
    scheduler : str, optional
        The address of a running Dask scheduler instead of a local cluster.
    progress : callable, optional
        ``progress("registrations", done, total)`` as pairs finish.
    notify : callable, optional
        Called with a line of news (the dashboard's address, a first run's compilation).
    compile_helpers : list, optional
        Processes compiling the registration's loops (:func:`volreg.precompile.start`); a local
        cluster's workers wait for them.

    Returns
    -------
    CohortSummary

    Raises
    ------
    ArgumentTypeError
        An argument of the wrong kind (a Protocol object for ``protocol``, a float for ``workers``), named.
    UsageError
        A bad manifest, template, pairing, protocol, worker count or scheduler address, before any work.
    SchedulerUnavailable
        No scheduler answered at ``scheduler``; the folders made for the run are removed.
    CohortInterrupted
        SIGINT or SIGTERM: the workers are stopped, finished pairs kept, ``batch.csv`` not written.
    """
    try:
        from dask.distributed import as_completed
    except ImportError:
        raise UsageError("volreg batch needs Dask: pip install 'dask[distributed]' (or volreg[batch]).") from None
    from volreg import precompile

    manifest, outdir, template, pairs, consistency, protocol, workers, scheduler, progress, notify = (
        _checked_arguments(manifest, outdir, template, pairs, consistency, protocol, workers, scheduler, progress,
                           notify))
    start = time.perf_counter()
    planned, folders = _check_request(manifest, template, pairs, protocol, workers)
    if scheduler:
        _check_scheduler_address(scheduler)
    created = make_directory(outdir)
    rows: list[dict] = []
    client = cluster = None
    try:
        # inside the try: an interrupt while the cluster starts is reported like any other
        client, cluster = _start_client(scheduler, workers, created)
        if client.dashboard_link and notify is not None:
            notify(f"Dask dashboard {client.dashboard_link}")
        if compile_helpers and cluster is not None:
            # A first run: rather than every worker compiling the same loops, the workers load
            # what the helpers (one per worker, started with this command) compile meanwhile.
            if notify is not None:
                notify("compiling the registration's loops once for the workers (a first run)")
            precompile.wait(compile_helpers)
        futures = {}
        for ((fid, fpath), (mid, mpath)), folder in zip(planned, folders):
            pair_dir = outdir / "pairs" / folder
            fut = client.submit(run_pair, fid, str(fpath.resolve()), mid, str(mpath.resolve()), str(pair_dir.resolve()),
                                str(protocol), consistency, key=f"volreg-{folder}", pure=False, retries=2)
            futures[fut] = (fid, mid)
        for n, fut in enumerate(as_completed(futures), start=1):
            fid, mid = futures[fut]
            try:
                rows.append(fut.result())
            except Exception as exc:  # a bug or a worker lost more often than the retries allow
                rows.append({"fixed_id": fid, "moving_id": mid, "status": "failed",
                             "error": f"{type(exc).__name__}: {' '.join(str(exc).split())}"})
            if progress is not None:
                progress("registrations", n, len(futures))
    except KeyboardInterrupt as exc:
        name = str(exc) or "SIGINT"
        _stop_after_interrupt(client, cluster)
        client = cluster = None
        # Counted on disk, the workers stopped: a pair's row is written once its outputs are, and
        # pairs that ended while the interrupt was on its way were never collected here.
        finished = sum(1 for folder in folders if (outdir / "pairs" / folder / "batch_row.json").is_file())
        raise CohortInterrupted(name, finished, len(planned)) from None
    finally:
        _close(client, cluster)
    order = {(f[0], m[0]): i for i, (f, m) in enumerate(planned)}
    rows.sort(key=lambda r: order[(r["fixed_id"], r["moving_id"])])
    write_cohort_table(rows, outdir / "batch.csv")
    write_cohort_plot(rows, outdir / "batch.png")
    return CohortSummary(rows, outdir / "batch.csv", time.perf_counter() - start)
