"""The ``volreg`` command line: parse, call the library, print.

One module per command (``surface``, ``register``, ``apply``, ``protocols``, ``demo``,
``consistency``, ``tune``, ``register-surfaces``, ``morph``, ``transfer``, ``batch``, ``template``),
each with ``add_parser(commands)`` and ``run(args)``; ``volreg --help`` lists them.

Exit status is 0 on success, 2 for any invalid input (a file that cannot
be read or written, a bad argument, a label that cannot give a surface) and 1
for a full disk (whichever library met it); the error is then one line on
stderr, ``volreg <command>: error: <message>``, and no output file is left behind.  Any other exception is a bug and propagates
with its traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import signal
import sys
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path

from volreg import __version__
from volreg.cli import (apply, batch, consistency, demo, morph, protocols, register, register_surfaces, shape_model,
                        surface, template, transfer, tune)
from volreg.cli._common import EXPECTED_ERRORS, PROG, _warn
from volreg.errors import FULL_DISK_ERRNOS, UsageError, VolregWarning, full_disk

__all__ = ["main", "run", "build_parser", "UsageError"]

#: The commands, in the order ``volreg --help`` lists them: each module's ``add_parser(commands)``
#: adds its subparser, whose ``run(args)`` carries the command out.
COMMANDS = (surface, register, apply, protocols, demo, consistency, tune, register_surfaces, morph, transfer, batch,
            template, shape_model)


#: What every command but ``protocols`` loads, loaded before the command runs with SIGINT and
#: SIGTERM held back (they are acted on once it is loaded and the handlers are in place).  A
#: signal that lands inside a C extension's import can crash the interpreter (a segmentation
#: fault), or end it by SIGINT after the interrupt was reported, instead of the clean exit
#: status 130 or 143.
PRELOAD = ("numpy", "scipy.ndimage", "scipy.optimize", "scipy.sparse", "numba", "SimpleITK", "nibabel",
           "skimage.measure", "volreg.io", "volreg.io.report_figure", "volreg.io.protocol",
           "volreg.progress", "volreg.outputs.registration")

#: pyvista (and VTK) are loaded too, in the same way, except for these commands when no argument
#: names a VTK file (:data:`VTK_SUFFIXES`): they do not use it, and importing it is a noticeable
#: part of a short command's start.
WITHOUT_PYVISTA = ("register", "consistency", "tune", "template")

#: File suffixes that volreg reads or writes through pyvista and VTK (meshes, point sets, ``.vti``).
VTK_SUFFIXES = (".vti", ".vtk", ".vtp", ".ply", ".stl", ".obj")


#: The commands that register label volumes: on a first run a helper process compiles their loops
#: alongside the command (:mod:`volreg.precompile`); for ``batch``, one per local worker while the
#: cluster starts, its tasks waiting for them (not beside a remote ``--scheduler``, whose workers
#: have caches of their own).
COMPILE_AHEAD = ("register", "consistency", "tune", "demo", "batch", "template")


def _hold_signals():
    """Block SIGINT and SIGTERM (main thread); return the previous mask, or None where nothing was held."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        return None
    return signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})


def _release_signals(mask) -> None:
    """Restore the mask that :func:`_hold_signals` returned: a signal that came meanwhile is acted on now."""
    if mask is not None:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def _preload(command: str, words: Sequence[str] = ()) -> None:
    """Import :data:`PRELOAD`, unless ``command`` is ``protocols``; pyvista unless the command is one
    of :data:`WITHOUT_PYVISTA` and none of its argument ``words`` ends in a :data:`VTK_SUFFIXES`
    suffix; for ``batch`` also Dask, where it is installed (the command says what to install where
    it is not)."""
    if command == "protocols":
        return
    import importlib

    vtk_file = any(str(w).lower().endswith(VTK_SUFFIXES) for w in words)
    for name in PRELOAD + (() if command in WITHOUT_PYVISTA and not vtk_file else ("pyvista",)):
        importlib.import_module(name)
    if command in ("batch", "template"):
        try:
            importlib.import_module("dask.distributed")
        except ImportError:
            pass


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``volreg`` command, with its subcommands."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Kernel registration of label volumes (Schölkopf, Steinke & Blanz, ICML 2005). "
        "World coordinates are ITK physical space: LPS, millimetres.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS:
        command.add_parser(commands)
    return parser


#: The signals this run's handler turned into KeyboardInterrupt: a library that calls back into
#: Python (matplotlib's renderer) may turn the KeyboardInterrupt into an error of its own.
_signalled: list[str] = []


def _raise_interrupt(signum, frame) -> None:
    name = signal.Signals(signum).name
    _signalled.append(name)
    raise KeyboardInterrupt(name)


def _forget_unhandled_interrupt() -> None:
    """Keep the exit status that :func:`_interrupted` returns.

    CPython remembers a KeyboardInterrupt that left Python code run through its ``PyRun_*``
    functions (which some extensions call) as "unhandled", and at exit then ends the process by
    SIGINT whatever its exit status; so an interrupt that landed there made the run end by
    SIGINT after its one-line report.  One empty statement run that way clears the mark.
    """
    try:
        import ctypes

        ctypes.pythonapi.PyRun_SimpleString(b"pass")
    except (ImportError, AttributeError, OSError):  # not CPython: no such mark
        pass


def _interrupted(command: str, name: str) -> int:
    """Report an interrupt in one line; return the exit status (130 for SIGINT, 143 for SIGTERM)."""
    _forget_unhandled_interrupt()
    print(f"{PROG} {command}: interrupted by {name}; the outputs of this run were removed{_kept_note()}.",
          file=sys.stderr)
    # An object the interrupt left half-built (llvmlite's, while numba loads) can fail in its
    # destructor on the way out ("Exception ignored in ..."): the report stays the last line.
    sys.unraisablehook = _ignore_unraisable
    return 130 if name == "SIGINT" else 128 + int(signal.SIGTERM)


def _kept_note() -> str:
    """`` (the previous result in `OUTDIR` was kept)`` after a failed run that left one, else ``""``."""
    from volreg.io._atomic import kept_results

    return "".join(f" (the previous result in `{p}` was kept)" for p in kept_results()[:1])


def _ignore_unraisable(unraisable) -> None:
    """A ``sys.unraisablehook`` that prints nothing."""


def _install_sigterm():
    """Make SIGTERM raise KeyboardInterrupt("SIGTERM"); return the previous handler (None off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_interrupt)


def _unraisable_hook(previous):
    """A ``sys.unraisablehook`` that keeps a KeyboardInterrupt raised where it could not propagate.

    Ctrl-C or SIGTERM during numba's first compilation of a kernel lands in an llvmlite
    ctypes callback; Python reports it there as "Exception ignored" and the run went on to
    finish (exit 0).  Recorded instead, it is raised again at the next progress report.
    """
    from volreg.progress import note_interrupt

    def hook(unraisable) -> None:
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            note_interrupt(str(unraisable.exc_value or "") or "SIGINT")
            return
        previous(unraisable)

    return hook


def _open_closed_streams() -> None:
    """Standard streams closed when the command started (``2>&-``): Python then has no stream
    there, and the first progress line or warning would end the command.  Each closed one of
    descriptors 0-2 is opened on the null device, in place (so that the next file opened, an
    output, does not take it and receive what libraries write to 2 directly), and Python's
    stream there writes to it."""
    for fd, name, mode in ((0, "stdin", "r"), (1, "stdout", "w"), (2, "stderr", "w")):
        try:
            os.fstat(fd)
            continue
        except OSError:
            pass
        null = os.open(os.devnull, os.O_RDONLY if mode == "r" else os.O_WRONLY)
        if null != fd:
            os.dup2(null, fd)
            os.close(null)
        if getattr(sys, name) is None:
            setattr(sys, name, open(fd, mode, encoding="utf-8", closefd=False))  # noqa: SIM115 (lives with the process)


#: Options whose value may start with a minus sign (``--coefficients -2,1``), which argparse would
#: take for an option of its own.
NEGATIVE_VALUE_OPTIONS = ("--coefficients",)


def _joined_negative_values(words: list[str]) -> list[str]:
    """``--coefficients -2,1`` as ``--coefficients=-2,1`` (for :data:`NEGATIVE_VALUE_OPTIONS`)."""
    out, i = [], 0
    while i < len(words):
        value = words[i + 1] if i + 1 < len(words) else ""
        if words[i] in NEGATIVE_VALUE_OPTIONS and value[:1] == "-" and (value[1:2].isdigit() or value[1:2] == "."):
            out.append(f"{words[i]}={value}")
            i += 2
        else:
            out.append(words[i])
            i += 1
    return out


def _parse(argv: Sequence[str] | None) -> argparse.Namespace | int:
    """The parsed arguments, or the exit status where argparse ended the run (``--help`` and
    ``--version``: 0; a usage error: 2, its message printed)."""
    parser = build_parser()
    words = _joined_negative_values(sys.argv[1:] if argv is None else list(argv))
    try:
        return parser.parse_args(words)
    except SystemExit as exc:  # argparse exits for --help, --version and usage errors
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)


def _start_helpers_and_preload(args: argparse.Namespace, words: Sequence[str], held) -> list:
    """Start the compiling helpers the command wants (:data:`COMPILE_AHEAD`), then load what it uses
    (:func:`_preload`), with SIGINT and SIGTERM held (``held``, from :func:`_hold_signals`); return
    the helpers.  On any failure the helpers are stopped and the signals released."""
    helpers: list = []
    try:
        # The helpers first: on a first run they compile while this process imports. One beside
        # a command; for batch, one per local worker, which wait for them (see volreg.cli.batch).
        if args.command in COMPILE_AHEAD and not getattr(args, "scheduler", None):
            from volreg import precompile as _precompile

            workers = getattr(args, "workers", None) or 2
            cohort = args.command in ("batch", "template")
            helpers = _precompile.start(min(workers, os.cpu_count() or 1) if cohort else 1)
            args.compile_helpers = helpers
        _preload(args.command, words)
        # what the handlers use, loaded while the signals are held too
        import volreg.io._atomic  # noqa: F401
        import volreg.progress  # noqa: F401
    except BaseException:
        if helpers:
            from volreg import precompile as _precompile

            _precompile.stop(helpers)
        _release_signals(held)
        raise
    return helpers


@contextlib.contextmanager
def _interrupts_unwind():
    """SIGTERM (a scheduler or `kill` stopping the job) unwinds like Ctrl-C, so every command's
    clean-up runs: outputs written so far are removed and temporary files deleted.  A
    KeyboardInterrupt that a library could not pass on is kept (:func:`_unraisable_hook`).
    Everything is restored on the way out."""
    from volreg.io._atomic import kept_results
    from volreg.progress import clear_interrupt

    previous = _install_sigterm()
    # SIGINT too, so that it is recorded when a library turns the KeyboardInterrupt into an error
    # of its own (numba's dispatcher: "SystemError: ... returned a result with an exception set").
    # (Not where SIGINT is ignored, as for a job started in the background by a shell.)
    previous_int = signal.signal(signal.SIGINT, _raise_interrupt) \
        if previous is not None and signal.getsignal(signal.SIGINT) not in (signal.SIG_IGN, None) else None
    unraisable = sys.unraisablehook
    if previous is not None:  # the main thread: signals are delivered here
        clear_interrupt()
        kept_results().clear()
        _signalled.clear()
        sys.unraisablehook = _unraisable_hook(unraisable)
    try:
        yield
    finally:
        sys.unraisablehook = unraisable  # also where an interrupt's report replaced it
        if previous is not None:
            clear_interrupt()
            signal.signal(signal.SIGTERM, previous)
            if previous_int is not None:
                signal.signal(signal.SIGINT, previous_int)


@contextlib.contextmanager
def _one_line_warnings(command: str):
    """Warnings shown as one line each on stderr (``volreg COMMAND: warning: ...``), volreg's always."""
    show = warnings.showwarning

    def one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
        _warn(command, " ".join(str(message).split()))

    warnings.showwarning = one_line_warning
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", VolregWarning)  # shown (one line each) whatever the global filters say
            yield
    finally:
        warnings.showwarning = show


@contextlib.contextmanager
def _helpers_stopped(helpers: list):
    """Stop the compiling helpers on the way out (what they compiled stays cached)."""
    try:
        yield
    finally:
        if helpers:
            from volreg import precompile as _precompile

            _precompile.stop(helpers)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``volreg`` command line.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        Exit status: 0 on success, 2 for a usage error or invalid input
        (reported as one line on stderr), 1 for a full disk or quota (one line
        naming the output as given, never a staging path), 130 after Ctrl-C (SIGINT) and 143
        after SIGTERM (the run's outputs removed; an output folder keeps
        its previous complete result).  ``--help`` and
        ``--version`` return 0.

    Raises
    ------
    Exception
        Anything other than volreg's input errors (:class:`~volreg.errors.VolregError` and
        its subclasses) is a bug and propagates with its traceback.
    """
    _open_closed_streams()
    args = _parse(argv)
    if isinstance(args, int):
        return args
    # Imported once a command runs, so that --help, --version and usage errors stay quick; with
    # SIGINT and SIGTERM held until the handlers are in place (see PRELOAD).
    held = _hold_signals()
    helpers = _start_helpers_and_preload(args, sys.argv[1:] if argv is None else list(argv), held)
    with _interrupts_unwind(), _one_line_warnings(args.command), _helpers_stopped(helpers):
        return _run_command(args, held)


def _run_command(args: argparse.Namespace, held) -> int:
    """Release the signals ``held`` (one that came meanwhile is acted on now, inside the handlers), run
    the parsed command and return its exit status, input errors and interrupts reported in one line."""
    output = getattr(args, "output", None)
    try:
        _release_signals(held)
        if output is not None and ".." in Path(output).parts:
            raise UsageError(
                f"-o `{output}` contains '..'; expected an output path without '..' components "
                f"(e.g. `{Path(os.path.normpath(os.path.abspath(output)))}`), so outputs stay where they are named."
            )
        return args.run(args)
    except EXPECTED_ERRORS as exc:
        if _signalled:  # the interrupt, turned into another error on its way up
            return _interrupted(args.command, _signalled[0])
        if full_disk(exc) is not None:  # a full disk, which a library reported in words of its own
            return _os_error(args.command, full_disk(exc), output)
        message = " ".join(str(exc).split("\n")).strip() or type(exc).__name__
        print(f"{PROG} {args.command}: error: {message}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader of stdout went away (`volreg protocols | head -1`): stop quietly, as
        # command-line tools killed by SIGPIPE do, and keep Python's exit-time flush from
        # raising again on the closed pipe.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return 128 + int(signal.SIGPIPE)
    except OSError as exc:
        if _signalled:
            return _interrupted(args.command, _signalled[0])
        if exc.errno in (errno.ENAMETOOLONG, errno.ELOOP):
            return _os_error(args.command, exc, output)
        if full_disk(exc) is None:
            raise
        return _os_error(args.command, full_disk(exc), output)
    except KeyboardInterrupt as exc:
        return _interrupted(args.command, str(exc) or "SIGINT")
    except Exception as exc:
        if _signalled:  # the interrupt, turned into another error on its way up (outputs already removed)
            return _interrupted(args.command, _signalled[0])
        if full_disk(exc) is not None:  # ITK's RuntimeError, VTK's, HDF5's, a Dask task's, around a full disk
            return _os_error(args.command, full_disk(exc), output)
        raise


def _os_error(command: str, exc: OSError, output=None) -> int:
    """Report in one line a full device (exit status 1) or a path over the system's limits (``ENAMETOOLONG``,
    ``ELOOP``: 2).  A full device names the file as the user named it (never a staging path), or the
    command's ``output`` where the error named no file."""
    from volreg.io import user_path

    if exc.errno in FULL_DISK_ERRNOS:
        name = exc.filename if exc.filename is not None else output
        where = f" writing `{user_path(name)}`" if name is not None else ""
        print(f"{PROG} {command}: error: {exc.strerror or os.strerror(exc.errno)}{where}; the outputs "
              f"were removed{_kept_note()}; expected room for them on the output's device (free some, or write "
              "elsewhere).", file=sys.stderr)
        return 1
    # a path over the system's limits (NAME_MAX per component, PATH_MAX in all), wherever it is met
    name = exc.filename if exc.filename is not None else "a path"
    print(f"{PROG} {command}: error: `{name}`: {exc.strerror}; expected a path within the system's limits "
          f"({os.pathconf('/', 'PC_NAME_MAX')} bytes per name, {os.pathconf('/', 'PC_PATH_MAX')} in all).",
          file=sys.stderr)
    return 2


def run() -> None:
    """The ``volreg`` console command (and ``python -m volreg``): :func:`main`, then a quick exit.

    When :func:`main` returns, every output is complete and closed.  What remains of a normal
    interpreter shutdown is freeing the objects of every loaded module, a noticeable part of a
    short command with numba, scipy and matplotlib loaded.  So the ``atexit`` handlers run, the standard
    streams are flushed, and the process ends with ``os._exit`` and :func:`main`'s status.
    Errors that escape :func:`main` (bugs) take the normal way out, with their traceback.
    """
    import atexit

    status = main()
    if status in (130, 128 + int(signal.SIGTERM)):  # interrupted: the report stays the last line
        sys.unraisablehook = _ignore_unraisable
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed pipe or stream: the normal exit reports it
        raise SystemExit(status)
    atexit._run_exitfuncs()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    os._exit(status if isinstance(status, int) else 1)
