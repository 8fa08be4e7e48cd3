"""Writing a registration's outputs from the library: the output transaction, the pair checks,
:func:`volreg.outputs.registration.write_registration`, :func:`volreg.outputs.consistency.write_both_ways` and the
consistency test's entry points, without the command line."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest

from volreg.cli._common import _summary_line
from volreg.errors import RegistrationInputError, UsageError, VolregError
from volreg.evaluation.consistency import consistency_test, warp_pad
from volreg.outputs.consistency import CONSISTENCY_OUTPUTS, write_both_ways, write_consistency_test
from volreg.grid import LabelVolume
from volreg.io._atomic import output_folder
from volreg.io.protocol import load_protocol
from volreg.outputs.registration import ITK_H5_OUTPUTS, REGISTRATION_OUTPUTS, registration_outputs, write_registration
from volreg.pipeline.checks import check_pair
from volreg.pipeline.labels import LabelRegistration
from volreg.settings import OutputSettings
from volreg.synthetic import GaussianBumps, deform_labels
from volreg.warp.model import KernelWarp

from helpers import blob_volume

#: Two warp levels (32 and 16 mm) on 24^3 volumes of 2.5 mm voxels: a few seconds per registration.
SMALL_PROTOCOL = "[protocol]\nname = \"small\"\n[warp]\nmin_width = 12.0\npad = 6.0\nmax_iter = 40\n"


@pytest.fixture(scope="module")
def small_pair(tmp_path_factory):
    """A blob and a copy shifted by a smooth bump (up to about 2 mm), and a protocol for them."""
    d = tmp_path_factory.mktemp("small")
    a = blob_volume(shape=(24, 24, 24), spacing=np.array([2.5, 2.5, 2.5]))
    bump = GaussianBumps(np.array([[0.0, 0.0, 0.0]]), np.array([[2.0, 1.0, 0.5]]), 30.0)
    (d / "p.toml").write_text(SMALL_PROTOCOL)
    return a, deform_labels(a, bump), load_protocol(d / "p.toml")


# ----------------------------------------------------------------------------- the output transaction


def test_output_folder_creates_parents_and_keeps_what_completes(tmp_path):
    out = tmp_path / "a" / "b"
    with output_folder(out) as folder:
        assert not out.exists() and folder.path.parent == tmp_path / "a"  # written beside, swapped in at the end
        (folder.path / "x.txt").write_text("x")
        folder.record(folder.path / "x.txt")
    assert (out / "x.txt").read_text() == "x" and folder.final == out
    assert [p.name for p in (tmp_path / "a").iterdir()] == ["b"] and folder.created == [tmp_path / "a"]


@pytest.mark.parametrize("error", [RuntimeError("a bug"), KeyboardInterrupt("SIGINT")], ids=["error", "interrupt"])
def test_output_folder_removes_what_the_run_wrote_and_created(tmp_path, error):
    out = tmp_path / "a" / "b"
    with pytest.raises(type(error)):
        with output_folder(out) as folder:
            (folder.path / "x.txt").write_text("x")
            folder.record(folder.path / "x.txt")
            raise error
    assert list(tmp_path.iterdir()) == []


def test_output_folder_refuses_a_non_empty_folder_without_force(tmp_path):
    (tmp_path / "keep.txt").write_text("keep")
    with pytest.raises(UsageError, match=r"Output directory `.*` exists and is not empty; pass --force to write into it\."):
        with output_folder(tmp_path):
            pass
    with output_folder(tmp_path, require_empty=False):  # each output is checked on its own instead
        pass
    # with force: a failure removes what the run wrote, never what was there before
    with pytest.raises(ValueError):
        with output_folder(tmp_path, force=True) as folder:
            (folder.path / "new.txt").write_text("new")
            folder.record(folder.path / "new.txt")
            raise ValueError("late failure")
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]


def test_output_folder_refuses_a_file(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(UsageError, match="exists and is not a directory"):
        with output_folder(tmp_path / "file"):
            pass


def test_inner_transaction_writes_into_the_outer_one_and_completes_with_it(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with output_folder(out) as outer:
            with output_folder(out / "forward") as inner:
                assert inner.path == outer.path / "forward" and inner.final == out / "forward"
                (inner.path / "model.npz").write_text("m")
                inner.record(inner.path / "model.npz")
            assert (outer.path / "forward" / "model.npz").is_file() and not out.exists()
            assert outer.written == [outer.path / "forward" / "model.npz"]
            raise RuntimeError("a later step fails")
    assert list(tmp_path.iterdir()) == []
    # an inner failure removes the inner run's files only; the outer run decides about its own
    with output_folder(out) as outer:
        (outer.path / "a.txt").write_text("a")
        outer.record(outer.path / "a.txt")
        with pytest.raises(RuntimeError):
            with output_folder(out / "backward") as inner:
                (inner.path / "b.txt").write_text("b")
                inner.record(inner.path / "b.txt")
                raise RuntimeError("inner failure")
    assert [p.name for p in out.iterdir()] == ["a.txt"] and outer.written == [outer.path / "a.txt"]


# ----------------------------------------------------------------------------- pair checks


def test_check_pair_refuses_pairs_that_cannot_be_registered():
    a = blob_volume(shape=(24, 24, 24), spacing=np.array([2.5, 2.5, 2.5]))
    flat = LabelVolume(np.ones((5, 5), np.uint8), (0.0, 0.0), (1.0, 1.0), np.eye(2))
    with pytest.raises(RegistrationInputError, match=r"`a.nii` is 3-D and `b.nii` 2-D; expected two volumes of one dimension"):
        check_pair(a, flat, "a.nii", "b.nii")
    far = LabelVolume(a.array, (1000.0, 0.0, 0.0), a.spacing, a.direction)
    with pytest.raises(RegistrationInputError, match=r"The grids of `fixed` and `moving` do not overlap.*no linear"):
        check_pair(a, far)
    check_pair(a, far, linear="rigid")  # a linear stage brings them together
    assert issubclass(RegistrationInputError, VolregError) and issubclass(RegistrationInputError, ValueError)
    check_pair(a, a)


def test_warp_pad_is_the_recorded_pad_or_a_tenth_of_the_extent():
    a = blob_volume(shape=(24, 24, 24), spacing=np.array([2.5, 2.5, 2.5]))
    assert warp_pad(KernelWarp.identity(3, settings={"pad": 6.0}), a) == 6.0
    assert warp_pad(KernelWarp.identity(3), a) == pytest.approx(0.1 * 24 * 2.5)


# ----------------------------------------------------------------------------- library entry points


def test_write_registration_writes_every_output_and_prints_nothing(small_pair, tmp_path, capsys):
    a, b, protocol = small_pair
    fitted = []
    report = write_registration(a, b, tmp_path / "out", protocol=protocol, inputs={"fixed": "a", "moving": "b"},
                                on_fit=fitted.append)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(REGISTRATION_OUTPUTS)
    assert json.loads((tmp_path / "out" / "report.json").read_text()) == report.to_json()
    assert report.inputs == {"fixed": "a", "moving": "b"} and report.mean_dice["after"] > report.mean_dice["before"]
    assert [s["stage"] for s in report.stages][-4:] == ["resample", "inverse", "metrics", "write"]
    assert len(fitted) == 1 and isinstance(fitted[0], LabelRegistration)
    assert report.levels == fitted[0].log
    # The report's |u| figures are those of the field written (float32 there).
    from volreg.io.fields import read_displacement

    u, _ = read_displacement(tmp_path / "out" / "warp.nii.gz")
    size = np.linalg.norm(u, axis=-1)
    assert report.displacement_mm["max"] == pytest.approx(size.max(), abs=1e-4) and size.max() > 0
    assert report.displacement_mm["mean_in_labels"] == pytest.approx(size[a.array != 0].mean(), abs=1e-4)
    assert capsys.readouterr() == ("", "")


def test_itk_h5_outputs_follow_the_protocol(small_pair, tmp_path):
    """`[outputs] itk_h5 = false`: the NIfTI fields only, and the summary line counts what was written."""
    a, b, protocol = small_pair
    assert set(ITK_H5_OUTPUTS) <= set(registration_outputs(protocol)) == set(REGISTRATION_OUTPUTS)
    no_h5 = dataclasses.replace(protocol, outputs=OutputSettings(itk_h5=False))
    report = write_registration(a, b, tmp_path / "out", protocol=no_h5)
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == sorted(registration_outputs(no_h5)) == sorted(set(REGISTRATION_OUTPUTS) - set(ITK_H5_OUTPUTS))
    assert report.protocol["outputs"] == {"itk_h5": False}
    assert _summary_line("register", report.to_json(), tmp_path / "out").endswith(f"; {len(names)} files in "
                                                                       f"{tmp_path / 'out'}{os.sep} ({report.seconds:.0f} s)")


def test_write_registration_leaves_nothing_when_a_write_fails(small_pair, tmp_path, monkeypatch):
    import volreg.io

    def disk_full(*args, **kwargs):
        raise volreg.io.VolregIOError("Image `jacobian.nii.gz` could not be written: disk full.")

    monkeypatch.setattr(volreg.io, "write_scalar", disk_full)  # after the model and both fields
    a, b, protocol = small_pair
    with pytest.raises(volreg.io.VolregIOError, match="disk full"):
        write_registration(a, b, tmp_path / "deep" / "out", protocol=protocol)
    assert list(tmp_path.iterdir()) == []


def test_write_registration_leaves_nothing_when_a_stage_fails_during_the_writes(small_pair, tmp_path, monkeypatch):
    """The fixed grid's fields are written in the background while the inverse is computed; an
    error there waits for the writes that started and removes them with the rest."""
    import volreg.outputs.registration as reg

    started = []

    def failing_inverse(*args, **kwargs):
        started.append(True)
        raise MemoryError("Unable to allocate the inverse's grid.")

    monkeypatch.setattr(reg, "inverse_on_moving_grid", failing_inverse)
    a, b, protocol = small_pair
    with pytest.raises(MemoryError, match="inverse"):
        write_registration(a, b, tmp_path / "deep" / "out", protocol=protocol)
    assert started
    assert list(tmp_path.iterdir()) == []


def test_both_ways_and_the_consistency_test(small_pair, tmp_path):
    a, b, protocol = small_pair
    both = write_both_ways(a, b, tmp_path / "out", protocol=protocol, inputs={"A": {"path": "a"}, "B": {"path": "b"}})
    assert set(both.reports) == {"forward", "backward"}
    assert both.reports["backward"].inputs == {"fixed": {"path": "b"}, "moving": {"path": "a"}}
    # the warps in memory are those written
    x = a.grid_points().reshape(-1, 3)[::11]
    for name in ("forward", "backward"):
        saved = KernelWarp.load(tmp_path / "out" / name / "model.npz")
        assert np.array_equal(saved(x), getattr(both, name).warp(x))
    report, error = consistency_test(a, b, both.forward.warp, both.backward.warp)
    assert report["pad_mm"] == 6.0 and error.shape == a.shape
    assert 0.0 < report["region"]["mean_mm"] < 1.25  # well under half a voxel (2.5 mm)
    # the same test from the saved warps, written all or nothing
    written = write_consistency_test(a, b, tmp_path / "test", forward=both.forward.warp, backward=both.backward.warp,
                                     directions={"forward": {"outdir": "f"}, "backward": {"outdir": "b"}})
    assert sorted(p.name for p in (tmp_path / "test").iterdir()) == sorted(CONSISTENCY_OUTPUTS)
    assert written["region"] == report["region"] and written["directions"]["forward"] == {"outdir": "f"}
    with pytest.raises(ValueError, match="`forward` and `backward`"):
        write_consistency_test(a, b, tmp_path / "half", forward=both.forward.warp)
    assert not (tmp_path / "half").exists()


def test_signals_held_for_a_swap_while_other_threads_run():
    """A SIGTERM sent to the process during a swap is handled once the swap's renames are done,
    also when other threads run (the kernel then delivers it to one of them, and Python runs
    the handler in the main thread all the same: a mask on the main thread did not hold it)."""
    import os
    import signal
    import threading
    import time

    from volreg._signals import SignalsHeld

    class Stop(Exception):
        pass

    def raise_stop(signum, frame):
        raise Stop(signum)

    previous = signal.signal(signal.SIGTERM, raise_stop)
    release = threading.Event()
    others = [threading.Thread(target=release.wait, args=(20,)) for _ in range(3)]
    for t in others:
        t.start()
    steps = []
    try:
        with pytest.raises(Stop):
            with SignalsHeld():
                os.kill(os.getpid(), signal.SIGTERM)
                for _ in range(50):  # Python checks for signals between these steps
                    time.sleep(0.002)
                    steps.append(1)
        assert len(steps) == 50  # the block ran to its end, then the handler
        assert signal.getsignal(signal.SIGTERM) is raise_stop  # restored
    finally:
        release.set()
        for t in others:
            t.join()
        signal.signal(signal.SIGTERM, previous)


@pytest.mark.parametrize("between", ["the swaps", "the restores"])
def test_a_signal_between_two_handler_swaps_leaves_no_handler_replaced(monkeypatch, between):
    """``signal.signal`` runs the handlers of signals that came meanwhile before it swaps, and
    makes no swap when one of them raises: a signal between the hold's two swaps (or its two
    restores) left the other signal's handler replaced by the hold's for the rest of the run,
    and a later Ctrl-C or SIGTERM was swallowed.  Every handler is back, and the signal raised."""
    import os
    import signal

    from volreg._signals import SignalsHeld

    class Stop(Exception):
        pass

    def raise_stop(signum, frame):
        raise Stop(signum)

    swap = signal.signal
    calls = []

    def swap_then_signal(signum, handler):
        old = swap(signum, handler)
        calls.append(signum)
        # right after the entry's first swap (SIGINT's), SIGTERM, whose handler is not swapped yet;
        # right after the exit's first restore (SIGINT's), SIGINT, whose handler is back
        if len(calls) == (1 if between == "the swaps" else 3):
            os.kill(os.getpid(), signal.SIGTERM if between == "the swaps" else signal.SIGINT)
        return old

    previous = {s: swap(s, raise_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        monkeypatch.setattr(signal, "signal", swap_then_signal)
        with pytest.raises(Stop):
            with SignalsHeld():
                pass
        monkeypatch.undo()
        assert signal.getsignal(signal.SIGINT) is raise_stop and signal.getsignal(signal.SIGTERM) is raise_stop
    finally:
        monkeypatch.undo()
        for s, handler in previous.items():
            swap(s, handler)


@pytest.mark.parametrize("made_by_another", ["folder", "file"])
def test_a_parent_folder_made_meanwhile_by_another_process(tmp_path, monkeypatch, made_by_another):
    """Batch workers create the same parent folder: where another process makes it between the
    check and `mkdir`, the folder is used, and only the folders this call made are reported; where
    a file took its place, the error names it."""
    from pathlib import Path

    from volreg.errors import VolregIOError
    from volreg.io._atomic import make_directory

    shared = tmp_path / "out" / "pairs"
    real_mkdir = Path.mkdir

    def racing(self, *args, **kwargs):
        if self == shared:
            if made_by_another == "folder":
                os.mkdir(self)
            else:
                self.write_text("")
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", racing)
    if made_by_another == "folder":
        assert make_directory(shared / "s0") == [tmp_path / "out", shared / "s0"]
        assert (shared / "s0").is_dir()
    else:
        with pytest.raises(VolregIOError, match="pairs. could not be created: File exists"):
            make_directory(shared / "s0")
        assert shared.is_file()
