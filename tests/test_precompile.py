"""The helper process that compiles a first run's loops alongside the command (``volreg.precompile``)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import numba
import pytest

from volreg import precompile as _precompile
from volreg.precompile import LOOPS, argument_types
from volreg.io import write_labels
from volreg.synthetic import GaussianBumps, deform_labels

from helpers import blob_volume

#: Run in a fresh interpreter: register a small pair with the default protocol, then print every
#: signature that any of volreg's compiled loops holds (the cache is warm or not: loaded
#: signatures count as well as compiled ones).  A large mask's distances stand for the linear
#: stage's on larger volumes.
_CALLED = """
import json, sys
import numpy as np
from numba.core.registry import CPUDispatcher
from volreg.cli import main
status = main(["register", sys.argv[1], sys.argv[2], "-o", sys.argv[3], "--quiet"])
# The linear stage's distances of a mask as large as the frog's take separable passes.
from volreg.features.distance_maps import SEPARABLE_CELLS, euclidean_distance
mask = np.ones((SEPARABLE_CELLS // 16384 + 1, 128, 128), bool)
mask[0] = False
euclidean_distance(mask, (1.0, 1.0, 1.0))
called = []
for name, module in sorted(sys.modules.items()):
    if name.startswith("volreg"):
        for attr, obj in sorted(vars(module).items()):
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == name:
                called += [[name, attr, [str(t) for t in sig]] for sig in obj.signatures]
print(json.dumps({"status": status, "called": called}))
"""


def _env(**extra) -> dict:
    env = dict(os.environ)
    env.update(extra)
    return env


def test_loops_are_exactly_those_a_registration_calls(tmp_path):
    fixed = blob_volume()
    inside = fixed.grid_points().reshape(-1, 3)[fixed.array.ravel() > 0]
    truth = GaussianBumps.random(inside.min(0), inside.max(0), max_displacement=4.5, scale=14.0, count=5,
                                 rng=np.random.default_rng(3))
    moving = deform_labels(fixed, truth)
    write_labels(fixed, tmp_path / "fixed.nii.gz")
    write_labels(moving, tmp_path / "moving.nii.gz")
    # Twice: a loop compiled (not loaded from the cache) also compiles the loops it calls, which
    # then hold signatures of their own; the second run loads the first's from the cache.
    for run in ("warm-up", "listed"):
        proc = subprocess.run([sys.executable, "-c", _CALLED, str(tmp_path / "fixed.nii.gz"),
                               str(tmp_path / "moving.nii.gz"), str(tmp_path / run)],
                              capture_output=True, text=True, timeout=600, env=_env(VOLREG_COMPILE_AHEAD="0"))
        assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["status"] == 0
    called = {(m, f, tuple(sig)) for m, f, sig in result["called"]}
    listed = {(m, f, tuple(str(t) for t in argument_types(spec))) for m, f, spec in LOOPS}
    assert listed == called
    assert len(listed) == len(LOOPS)  # no entry twice


def test_helper_compiles_the_later_stages_first_then_the_earlier_from_the_last_back():
    k = _precompile.HELPER_FROM
    assert 0 < k < len(LOOPS) - 1
    cold = list(range(len(LOOPS)))
    order = _precompile.helper_order(cold[::-1])
    assert sorted(order) == cold  # each once
    assert order == list(range(k, len(LOOPS))) + list(range(k - 1, -1, -1))
    assert _precompile.helper_order([k - 2, k + 3, k - 1, k]) == [k, k + 3, k - 1, k - 2]
    assert _precompile.helper_order([]) == []


def test_argument_types_are_those_numba_infers():
    a = np.zeros((3, 4))
    readonly = np.zeros((2, 2), np.float32)
    readonly.flags.writeable = False
    types = argument_types("float64[2] ro:float32[2] int64 float64 bool[3] int32[1]")
    assert types == (numba.typeof(a), numba.typeof(readonly), numba.typeof(np.int64(1)), numba.typeof(1.0),
                     numba.typeof(np.zeros((1, 1, 1), bool)), numba.typeof(np.zeros(2, np.int32)))
    for bad in ("float16[2]", "ro:int64", "float64[5]", "float64 [2]x"):
        with pytest.raises(ValueError, match="argument type"):
            argument_types(bad)


def _cold_in(cache: Path) -> list[int]:
    code = "import json; from volreg import precompile; print(json.dumps(precompile.cold_loops()))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env=_env(NUMBA_CACHE_DIR=str(cache)))
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def _index(module: str, name: str) -> int:
    return next(i for i, (m, f, _) in enumerate(LOOPS) if (m, f) == (module, name))


def test_helper_compiles_into_the_cache_that_the_next_process_reads(tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir()
    assert _cold_in(cache) == list(range(len(LOOPS)))
    chosen = [_index("volreg.kernels._compiled", "_take_rows"), _index("volreg.kernels._compiled", "_put_rows")]
    proc = subprocess.run([sys.executable, "-m", "volreg.precompile", *map(str, chosen)], timeout=300,
                          env=_env(NUMBA_CACHE_DIR=str(cache)))
    assert proc.returncode == 0
    assert _cold_in(cache) == [i for i in range(len(LOOPS)) if i not in chosen]


@pytest.mark.parametrize("held", [False, True], ids=["signals as they are", "started with SIGTERM blocked"])
def test_stopped_helper_ends_promptly_and_leaves_no_partial_file(tmp_path, held):
    """Stopped while compiling, the helper ends with status 0, says nothing, leaves no temporary
    file and has not compiled every loop; also when started, as the command starts it, while
    the command holds SIGINT and SIGTERM blocked (a blocked mask is inherited)."""
    cache = tmp_path / "cache"
    cache.mkdir()
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM}) if held else None
    try:
        helper = subprocess.Popen([sys.executable, "-m", "volreg.precompile", *map(str, range(len(LOOPS)))],
                                  env=_env(NUMBA_CACHE_DIR=str(cache)), stderr=subprocess.PIPE)
    finally:
        if held:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)
    time.sleep(4.0)  # imported, and compiling
    assert helper.poll() is None
    t0 = time.perf_counter()
    _precompile.stop([helper])
    assert time.perf_counter() - t0 < 10.0
    assert helper.returncode == 0
    with helper.stderr:
        assert helper.stderr.read() == b""
    assert not [p for p in cache.rglob("*") if ".tmp." in p.name]
    assert _cold_in(cache)  # stopped before the end, not run to it


#: Run in a fresh interpreter as the helper runs: SIGTERM arrives in the middle of a cache
#: file's write; the process must finish that write (renamed into place, no temporary file)
#: and end at once after it with status 0, before the next statement.
_WRITE_INTERRUPTED = """
import os, signal, sys
from numba.core import caching
from volreg import precompile as _precompile
_precompile._hook_cache_writes()
signal.signal(signal.SIGTERM, _precompile._on_sigterm)
target = sys.argv[1]
with caching.IndexDataCacheFile._open_for_write(None, target) as f:
    f.write(b"first half ")
    os.kill(os.getpid(), signal.SIGTERM)
    f.write(b"second half")
print("went on after the write")
"""


def test_sigterm_during_a_cache_write_ends_the_helper_after_it(tmp_path):
    from numba.core import caching

    if not hasattr(getattr(caching, "IndexDataCacheFile", None), "_open_for_write"):
        pytest.skip("this numba writes its cache otherwise; the helper then stops as before")
    target = tmp_path / "loop.nbc"
    proc = subprocess.run([sys.executable, "-c", _WRITE_INTERRUPTED, str(target)], capture_output=True,
                          timeout=120, env=_env())
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == b""
    assert target.read_bytes() == b"first half second half"
    assert [p.name for p in tmp_path.iterdir()] == ["loop.nbc"]


def test_no_helper_when_turned_off_or_warm(monkeypatch):
    monkeypatch.setenv("VOLREG_COMPILE_AHEAD", "0")
    assert _precompile.start() == []
    monkeypatch.delenv("VOLREG_COMPILE_AHEAD")
    for i, (_, _, spec) in enumerate(LOOPS):  # this process's cache now holds them all
        _precompile._dispatcher(i).compile(argument_types(spec))
    assert _precompile.cold_loops() == []
    assert _precompile.start() == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc to tell an ended process")
def test_helper_ends_soon_after_its_command_is_killed(tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir()
    command = ("import subprocess, sys; h = subprocess.Popen([sys.executable, '-m', 'volreg.precompile', "
               f"*map(str, range({len(LOOPS)}))]); print(h.pid, flush=True); h.wait()")
    parent = subprocess.Popen([sys.executable, "-c", command], stdout=subprocess.PIPE, text=True,
                              env=_env(NUMBA_CACHE_DIR=str(cache)))
    helper = int(parent.stdout.readline())

    def compiled() -> list:
        # the loops' own index files: the functions they call are cached beside them
        return [(m, f) for m, f, _ in LOOPS if any(cache.rglob(f"{m.rsplit('.', 1)[1]}.{f}-*.nbi"))]

    # Killed once the helper has compiled its first loop (not after a fixed time, which a fast
    # machine spends compiling most of them).
    started = time.monotonic() + 120.0
    while not compiled() and time.monotonic() < started:
        time.sleep(0.05)
    parent.kill()  # SIGKILL: the command cannot stop its helper
    parent.wait()
    parent.stdout.close()
    deadline = time.monotonic() + 30.0  # the loop being compiled is finished first
    while time.monotonic() < deadline:
        try:
            os.kill(helper, 0)
        except ProcessLookupError:
            break
        if Path(f"/proc/{helper}/stat").exists() and Path(f"/proc/{helper}/stat").read_text().split()[2] == "Z":
            break  # ended; a zombie until init reaps it
        time.sleep(0.2)
    else:
        pytest.fail("the helper outlived its killed command by 30 s")
    # It stopped long before compiling them all.
    assert 0 < len(compiled()) < len(LOOPS) // 2


def test_first_index_is_looked_up_where_numba_would_write_it(tmp_path, monkeypatch):
    from numba.core.caching import _CacheLocator

    import volreg

    package = tmp_path / "site" / "volreg"
    (package / "warp").mkdir(parents=True)
    monkeypatch.setattr(volreg, "__file__", str(package / "__init__.py"))
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "home-cache"))
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path / "tmp"))
    assert not _precompile._first_index_seen()
    # numba's own name for the folder of a source file's cache under NUMBA_CACHE_DIR
    sub = _CacheLocator.get_suitable_cache_subpath(str(package / "warp" / "inverse.py"))
    (tmp_path / "cache" / sub).mkdir(parents=True)
    (tmp_path / "cache" / sub / "inverse._grid_fixed_point-123.py311.nbi").write_bytes(b"")
    assert _precompile._first_index_seen()
    # Without NUMBA_CACHE_DIR: beside the source (numba's default), and volreg's fallback folder.
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert not _precompile._first_index_seen()
    (package / "warp" / "__pycache__").mkdir()
    (package / "warp" / "__pycache__" / "inverse._grid_fixed_point-9.py311.nbi").write_bytes(b"")
    assert _precompile._first_index_seen()
    (package / "warp" / "__pycache__" / "inverse._grid_fixed_point-9.py311.nbi").unlink()
    fallback = tmp_path / "tmp" / f"volreg-numba-cache-{os.getuid()}" / sub
    fallback.mkdir(parents=True)
    (fallback / "inverse._grid_fixed_point-9.py311.nbi").write_bytes(b"")
    assert _precompile._first_index_seen()


def test_helpers_started_for_a_fresh_cache_compile_their_shares_of_every_cold_loop(tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir()
    order = _precompile.helper_order(list(range(len(LOOPS))))
    proc = subprocess.run([sys.executable, "-m", "volreg.precompile", "cold", "1/2"], timeout=600,
                          env=_env(NUMBA_CACHE_DIR=str(cache)))
    assert proc.returncode == 0
    assert _cold_in(cache) == sorted(_precompile.shares_of(order, 2)[0])  # the other share's
    proc = subprocess.run([sys.executable, "-m", "volreg.precompile", "cold"], timeout=600,
                          env=_env(NUMBA_CACHE_DIR=str(cache)))
    assert proc.returncode == 0
    assert _cold_in(cache) == []


class _Started:
    """Stands for subprocess.Popen: records the command lines of the helpers started."""

    commands: list = []

    def __init__(self, command, **kwargs) -> None:
        self.commands.append(command[command.index("volreg.precompile") + 1:])


def test_helpers_for_a_batch_share_the_cold_loops_between_them(monkeypatch):
    monkeypatch.setenv("VOLREG_COMPILE_AHEAD", "1")
    monkeypatch.setattr(_precompile.subprocess, "Popen", _Started)
    # a fresh install: each helper finds the cold loops and takes its share
    monkeypatch.setattr(_precompile, "_first_index_seen", lambda: False)
    _Started.commands = []
    assert len(_precompile.start(3)) == 3
    assert _Started.commands == [["cold", "0/3"], ["cold", "1/3"], ["cold", "2/3"]]
    # a cache that holds some loops: this process splits those it lacks
    monkeypatch.setattr(_precompile, "_first_index_seen", lambda: True)
    pairs = next(i for i, (_, name, _) in enumerate(LOOPS) if name == "_grid_pairs")
    cold = sorted({0, 2, pairs, _precompile.HELPER_FROM, len(LOOPS) - 1})
    monkeypatch.setattr(_precompile, "cold_loops", lambda: cold)
    _Started.commands = []
    assert len(_precompile.start(2)) == 2
    order = [str(i) for i in _precompile.helper_order(cold)]
    # _grid_pairs and the others that share compiled callees with it on one helper; the others
    # dealt to the rest
    shared = [w for w in order if LOOPS[int(w)][1] in _precompile.SHARED_CALLEES]
    assert str(pairs) in shared and len(shared) < len(order)
    assert _Started.commands == [shared, [w for w in order if w not in shared]]
    _Started.commands = []
    assert len(_precompile.start(9)) == len(cold) - len(shared) + 1  # no helper without a loop
    assert sorted(sum(_Started.commands, [])) == sorted(order)
    monkeypatch.setattr(_precompile, "cold_loops", lambda: [3])  # one loop: compiled where needed
    assert _precompile.start(2) == []


def test_loops_that_share_compiled_callees_go_to_one_helper():
    """The kernel sums together on the first helper, the other loops dealt to the others, every
    loop once and each share in the order given; one helper, or none of those loops: dealt in turn."""
    names = [name for _, name, _ in LOOPS]
    assert set(_precompile.SHARED_CALLEES) <= set(names)
    order = _precompile.helper_order(list(range(len(LOOPS))))
    together = [i for i in order if names[i] in _precompile.SHARED_CALLEES]
    for n in (2, 3):
        shares = _precompile.shares_of(order, n)
        assert len(shares) == n and shares[0] == together
        assert sorted(sum(shares, [])) == sorted(order)
        for share in shares:
            assert share == [i for i in order if i in share]
    assert _precompile.shares_of(order, 1) == [order]
    others = [i for i in order if i not in together]
    assert _precompile.shares_of(others, 2) == [others[0::2], others[1::2]]
    assert _precompile.shares_of([], 3) == [[], [], []]


def test_waiting_for_helpers_ends_with_them_or_at_the_timeout():
    quick = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(0.5)"])
    t0 = time.perf_counter()
    _precompile.wait([quick])
    assert quick.returncode == 0 and time.perf_counter() - t0 < 10.0
    slow = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    t0 = time.perf_counter()
    _precompile.wait([slow], timeout=0.5)
    assert slow.poll() is None and time.perf_counter() - t0 < 5.0
    _precompile.stop([slow])
    assert slow.returncode is not None


def test_an_interrupt_while_a_loop_compiles_is_raised_once_it_is_ready():
    """SIGTERM (or Ctrl-C) while numba compiles a loop or loads it from the cache is held until
    the loop is ready, then raised: raised inside numba's compiler or LLVM's callbacks, it left
    LLVM's objects half-built, and the command crashed by a segmentation fault after its report."""
    from volreg._jit import _compiled_with_signals_held, njit

    class Stop(Exception):
        pass

    def raise_stop(signum, frame):
        raise Stop(signum)

    steps = []

    class Dispatcher:
        def compile(self, sig):
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(50):  # Python checks for signals between these steps
                time.sleep(0.002)
                steps.append(sig)
            return "compiled"

    loop = _compiled_with_signals_held(Dispatcher())
    previous = signal.signal(signal.SIGTERM, raise_stop)
    try:
        with pytest.raises(Stop):
            loop.compile("float64")
        assert steps == ["float64"] * 50  # the compilation ran to its end, then the handler
        assert signal.getsignal(signal.SIGTERM) is raise_stop
        assert loop.compile.__wrapped__.__func__ is Dispatcher.compile  # unheld, as the helper calls it
    finally:
        signal.signal(signal.SIGTERM, previous)

    @njit(cache=False)
    def add_one(x):
        return x + 1

    assert add_one(1) == 2 and add_one(1.5) == 2.5  # every volreg loop compiles through the held method
    assert hasattr(add_one.compile, "__wrapped__") and len(add_one.signatures) == 2
