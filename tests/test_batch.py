"""``volreg batch`` on a Dask LocalCluster of 2 workers: small generated subjects."""

from __future__ import annotations

import json

import csv
import os
import signal
import threading

import nibabel as nib
import numpy as np
import pytest

from volreg.cli import main
from volreg.io import write_labels
from volreg.synthetic import GaussianBumps, deform_labels

from helpers import blob_volume

distributed = pytest.importorskip("dask.distributed")

#: Two warp levels (32 and 16 mm) on these 24^3 volumes of 2.5 mm voxels: a few seconds per pair.
PROTOCOL = "[protocol]\nname = \"batch-test\"\n[warp]\nmin_width = 12.0\npad = 6.0\nmax_iter = 40\n"


def _rows(path):
    return list(csv.DictReader(path.read_text().splitlines()))


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    d = tmp_path_factory.mktemp("cohort")
    base = blob_volume(shape=(24, 24, 24), spacing=np.array([2.5, 2.5, 2.5]))
    write_labels(base, d / "template.nii.gz")
    lines = ["id,path"]
    for i in range(6):
        bump = GaussianBumps(np.array([[0.0, 0.0, 0.0]]), np.array([[0.8 * i - 2.0, 1.0, 0.5 * (i % 2)]]), 30.0)
        write_labels(deform_labels(base, bump), d / f"s{i}.nii.gz")
        lines.append(f"s{i},s{i}.nii.gz")
    (d / "corrupt.nii.gz").write_bytes(b"\x1f\x8b" + os.urandom(300))
    lines.append("bad,corrupt.nii.gz")
    (d / "manifest.csv").write_text("\n".join(lines) + "\n")
    (d / "p.toml").write_text(PROTOCOL)
    args = ["batch", str(d / "manifest.csv"), "-o", str(d / "out"), "--template", str(d / "template.nii.gz"),
            "--protocol", str(d / "p.toml"), "--workers", "2", "--quiet"]
    assert main(args) == 1  # one pair failed
    return d, args


def test_all_pairs_complete_and_the_corrupt_one_fails_alone(cohort):
    d, _ = cohort
    rows = _rows(d / "out" / "batch.csv")
    assert [(r["fixed_id"], r["moving_id"]) for r in rows] == [("template", f"s{i}") for i in range(6)] + [("template", "bad")]
    assert [r["status"] for r in rows] == ["done"] * 6 + ["failed"], [(r["moving_id"], r["error"]) for r in rows]
    assert "corrupt.nii.gz" in rows[-1]["error"] and "\n" not in rows[-1]["error"]
    for r in rows[:6]:
        assert float(r["mean_dice_after"]) >= float(r["mean_dice_before"]) - 1e-9
        assert (d / "out" / "pairs" / f"template__{r['moving_id']}" / "warp.nii.gz").is_file()
    assert (d / "out" / "batch.png").read_bytes()[:4] == b"\x89PNG"


def test_rerun_recomputes_nothing(cohort, capsys):
    d, args = cohort
    warp = d / "out" / "pairs" / "template__s3" / "warp.nii.gz"
    before = warp.stat().st_mtime_ns
    assert main(args) == 1
    out = capsys.readouterr()
    assert "(6 already done, skipped), 1 failed" in out.out
    assert warp.stat().st_mtime_ns == before
    # the failed pair is named on stderr, with its reason
    (line,) = [x for x in out.err.splitlines() if "failed" in x]
    assert line.startswith("volreg batch: warning: pair template <- bad failed:") and "corrupt.nii.gz" in line


def test_results_equal_volreg_register(cohort, tmp_path):
    d, _ = cohort
    assert main(["register", str(d / "template.nii.gz"), str(d / "s4.nii.gz"), "-o", str(tmp_path / "one"),
                 "--protocol", str(d / "p.toml"), "--quiet"]) == 0
    one, batch = tmp_path / "one", d / "out" / "pairs" / "template__s4"
    # The same computation in a Dask worker: equal up to floating-point rounding (numba's
    # fastmath sums may be compiled differently in another process), labels exactly.
    assert np.array_equal(nib.load(one / "warped.nii.gz").get_fdata(), nib.load(batch / "warped.nii.gz").get_fdata())
    np.testing.assert_allclose(nib.load(one / "warp.nii.gz").get_fdata(), nib.load(batch / "warp.nii.gz").get_fdata(),
                               rtol=0, atol=1e-6)
    with np.load(one / "model.npz") as a, np.load(batch / "model.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            if a[key].dtype.kind == "f":
                np.testing.assert_allclose(a[key], b[key], rtol=0, atol=1e-6)
            else:
                assert np.array_equal(a[key], b[key]), key


def test_killed_worker_is_retried(cohort, tmp_path):
    """A worker process killed mid-run: Dask restarts it and reruns its task; every pair completes."""
    d, _ = cohort
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0")
    killed = []

    def kill_one():
        for nanny in list(cluster.workers.values()):
            pid = getattr(getattr(nanny, "process", None), "pid", None)
            if pid:
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                return

    try:
        timer = threading.Timer(2.0, kill_one)
        timer.start()
        rc = main(["batch", str(d / "manifest.csv"), "-o", str(tmp_path / "out"), "--pairs", "consecutive",
                   "--protocol", str(d / "p.toml"), "--scheduler", cluster.scheduler_address, "--quiet"])
        timer.join()
    finally:
        cluster.close()
    assert killed, "no worker was killed"
    rows = _rows(tmp_path / "out" / "batch.csv")
    assert [r["status"] for r in rows] == ["done"] * 5 + ["failed"] and rc == 1  # s5 -> bad fails as it should


@pytest.mark.parametrize("content, words", [
    ("id,file\ns0,a.nii.gz\n", "columns id,path"),
    ("id,path\ns0,s0.nii.gz\ns0,s1.nii.gz\n", "listed twice"),
    ("id,path\ns0,s0.nii.gz\n", "no pair"),
    ("id,path\ns0,s0.nii.gz\ns1,s1.nii.gz,extra\n", "line 3: 3 fields where the header names 2"),
])
def test_bad_manifest(cohort, tmp_path, capsys, content, words):
    d, _ = cohort
    (d / "m.csv").write_text(content)
    assert main(["batch", str(d / "m.csv"), "-o", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and words in err


def test_consistency_pairs(cohort, tmp_path):
    """--consistency runs `volreg consistency` per pair; its error figures land in batch.csv."""
    d, _ = cohort
    (d / "two.csv").write_text("id,path\ns1,s1.nii.gz\ns5,s5.nii.gz\n")
    assert main(["batch", str(d / "two.csv"), "-o", str(tmp_path / "out"), "--pairs", "consecutive", "--consistency",
                 "--protocol", str(d / "p.toml"), "--workers", "1", "--quiet"]) == 0
    (row,) = _rows(tmp_path / "out" / "batch.csv")
    assert (row["fixed_id"], row["moving_id"], row["status"]) == ("s1", "s5", "done")
    pair = tmp_path / "out" / "pairs" / "s1__s5"
    assert (pair / "consistency.json").is_file() and (pair / "forward" / "warp.nii.gz").is_file()
    # the blobs differ by a few mm: the two registrations agree to well under a voxel (2.5 mm)
    assert 0.0 < float(row["consistency_mean_mm"]) < 1.25
    assert float(row["consistency_p95_mm"]) >= float(row["consistency_mean_mm"])
    # both directions' plausibility reviews: the cell is "ok" exactly when neither found anything
    reviews = [d["review"] for d in json.loads((pair / "consistency.json").read_text())["directions"].values()]
    assert len(reviews) == 2
    assert (row["review"] == "ok") == all(r["plausible"] for r in reviews)
    # the larger of the two directions' folded fractions
    folded = [d["folded_fraction"] for d in json.loads((pair / "consistency.json").read_text())["directions"].values()]
    assert float(row["folded_fraction"]) == pytest.approx(max(folded))


def test_the_review_cell_names_the_direction_of_each_finding():
    from volreg.cohort import _review_cell

    found = {"findings": [{"message": "mean Dice 0.00"}]}
    assert _review_cell({"forward": {"findings": []}, "backward": found}) == "backward: mean Dice 0.00"
    assert _review_cell({"": found}) == "mean Dice 0.00"
    assert _review_cell({"forward": {"findings": []}, "backward": {"findings": []}}) == "ok"


def test_an_interrupt_waits_for_worker_processes_being_launched(monkeypatch):
    """A worker process whose launch an interrupt catches is let receive its start-up data before
    the report: a parent exiting mid-launch made it print ``EOFError``."""
    import multiprocessing
    import multiprocessing.popen_spawn_posix as popen
    import time

    from volreg import cohort as batch

    launched, release = threading.Event(), threading.Event()
    spawn = popen.util.spawnv_passfds

    def held_spawn(*args, **kwargs):
        launched.set()
        release.wait(30)
        return spawn(*args, **kwargs)

    monkeypatch.setattr(popen.util, "spawnv_passfds", held_spawn)
    assert not batch._launching_a_process()
    child = multiprocessing.get_context("spawn").Process(target=time.sleep, args=(60,))
    starter = threading.Thread(target=child.start)
    starter.start()
    assert launched.wait(30)
    assert batch._launching_a_process()  # the thread is inside multiprocessing's launch
    threading.Timer(0.5, release.set).start()
    t0 = time.monotonic()
    batch._await_worker_launches(wait_s=30)
    waited = time.monotonic() - t0
    assert not batch._launching_a_process() and 0.4 < waited < 25
    starter.join()
    assert child.is_alive()  # launched, with its data
    child.terminate()
    child.join(30)
    assert child.exitcode == -signal.SIGTERM


def test_a_first_run_submits_its_tasks_once_the_compiling_helpers_have_ended(cohort, tmp_path, monkeypatch, capsys):
    # Stand-in helpers (the cache here is warm): one process that ends 1.5 s later.
    import subprocess
    import sys
    import time

    from volreg import precompile as _precompile

    d, _ = cohort
    shares, events = [], []
    helpers = []

    def start(n=1):
        shares.append(n)
        helpers.append(subprocess.Popen([sys.executable, "-c", "import time; time.sleep(1.5)"]))
        return list(helpers)

    submit = distributed.Client.submit

    def recorded_submit(self, *args, **kwargs):
        events.append(("submit", time.monotonic(), all(h.poll() is not None for h in helpers)))
        return submit(self, *args, **kwargs)

    monkeypatch.setattr(_precompile, "start", start)
    monkeypatch.setattr(distributed.Client, "submit", recorded_submit)
    (d / "two.csv").write_text("id,path\ns1,s1.nii.gz\ns5,s5.nii.gz\n")
    assert main(["batch", str(d / "two.csv"), "-o", str(tmp_path / "out"), "--pairs", "consecutive",
                 "--protocol", str(d / "p.toml"), "--workers", "2"]) == 0
    assert shares == [min(2, os.cpu_count() or 1)]  # one helper per local worker
    assert "compiling the registration's loops once for the workers" in capsys.readouterr().err
    assert events and all(ended for _, _, ended in events)  # every task submitted after the helpers ended
    assert (tmp_path / "out" / "pairs" / "s1__s5" / "warp.nii.gz").is_file()


def test_a_pair_redone_another_way_keeps_no_earlier_result(cohort, tmp_path):
    """A consistency test, then a plain registration of the same pair into the same OUTDIR: the
    pair's folder holds the registration alone, not the earlier test's files beside it."""
    d, _ = cohort
    (d / "two.csv").write_text("id,path\ns1,s1.nii.gz\ns5,s5.nii.gz\n")
    common = ["-o", str(tmp_path / "out"), "--pairs", "consecutive", "--protocol", str(d / "p.toml"), "--workers", "1",
              "--quiet"]
    assert main(["batch", str(d / "two.csv"), "--consistency", *common]) == 0
    pair = tmp_path / "out" / "pairs" / "s1__s5"
    assert (pair / "consistency.json").is_file() and (pair / "forward").is_dir()
    assert main(["batch", str(d / "two.csv"), *common]) == 0
    assert (pair / "warp.nii.gz").is_file() and (pair / "batch_row.json").is_file()
    assert not (pair / "consistency.json").exists() and not (pair / "forward").exists()
    assert not (pair / "backward").exists()


@pytest.mark.parametrize("address", ["scheduler-host", "tcp://scheduler-host", "tcp://:8786", "tcp://host:99999",
                                     "http://host:8786"])
def test_a_scheduler_address_without_host_or_port_is_refused_before_any_folder(tmp_path, capsys, address):
    (tmp_path / "m.csv").write_text("id,path\na,a.nii.gz\nb,b.nii.gz\n")
    for name in ("a", "b"):
        write_labels(blob_volume(shape=(8, 8, 8)), tmp_path / f"{name}.nii.gz")
    out = tmp_path / "new" / "out"
    assert main(["batch", str(tmp_path / "m.csv"), "-o", str(out), "--scheduler", address, "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"--scheduler `{address}`" in err and "tcp://HOST:8786" in err
    assert not (tmp_path / "new").exists()


def test_an_unreachable_scheduler_is_one_line_and_leaves_no_folder(tmp_path, capsys, monkeypatch):
    import socket

    from volreg import cohort as batch

    monkeypatch.setattr(batch, "SCHEDULER_TIMEOUT_S", 2.0)
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (tmp_path / "m.csv").write_text("id,path\na,a.nii.gz\nb,b.nii.gz\n")
    for name in ("a", "b"):
        write_labels(blob_volume(shape=(8, 8, 8)), tmp_path / f"{name}.nii.gz")
    out = tmp_path / "new" / "out"
    assert main(["batch", str(tmp_path / "m.csv"), "-o", str(out), "--scheduler", f"tcp://127.0.0.1:{port}",
                 "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no Dask scheduler answered within 2 s" in err
    assert not (tmp_path / "new").exists()
