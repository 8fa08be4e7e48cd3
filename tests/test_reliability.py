"""Reliability: hostile inputs refused in one line with exit status 2 and nothing written;
interrupted runs leave no partial output; runs are reproducible; no unsafe loaders."""

from __future__ import annotations

import gzip
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import pyvista as pv
import SimpleITK as sitk

from volreg import LabelVolume
from volreg.cli import main
from volreg.io import VolregIOError, read_mesh, write_labels
from volreg.errors import RegistrationDiverged
from volreg.warp.fit import fit_warp
from volreg.warp.model import KernelWarp
from volreg.warp.objective import FeaturePair

from helpers import TEST_PROTOCOL, cube as _cube, write_nifti as _nifti

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
REPO = Path(__file__).resolve().parent.parent




def _mha(path: Path, *, spacing="1 1 1", matrix="1 0 0 0 1 0 0 0 1", dims=(4, 4, 4)) -> Path:
    """A MetaImage written by hand, so spacing and direction can be anything."""
    data = np.zeros(dims[::-1], np.uint8)
    data[1:3, 1:3, 1:3] = 1
    header = (f"ObjectType = Image\nNDims = 3\nDimSize = {' '.join(map(str, dims))}\nElementType = MET_UCHAR\n"
              f"ElementSpacing = {spacing}\nTransformMatrix = {matrix}\nOffset = 0 0 0\nElementDataFile = LOCAL\n")
    path.write_bytes(header.encode() + data.tobytes())
    return path


def _patch_pixdim(path: Path, index: int, value: float) -> Path:
    """Overwrite pixdim[index] in the stored header (nibabel would fix it on save)."""
    gz = path.name.endswith(".gz")
    raw = bytearray(gzip.decompress(path.read_bytes()) if gz else path.read_bytes())
    raw[76 + 4 * index: 80 + 4 * index] = np.float32(value).tobytes()
    path.write_bytes(gzip.compress(bytes(raw)) if gz else bytes(raw))
    return path


def _bomb(path: Path) -> Path:
    """A .nii.gz whose header claims 30000^3 int16 voxels (54 TB) over a few bytes of data."""
    hdr = nib.Nifti1Header()
    hdr.set_data_shape((30000, 30000, 30000))
    hdr.set_data_dtype(np.int16)
    hdr["vox_offset"] = 352
    raw = hdr.binaryblock + b"\0" * (352 - len(hdr.binaryblock)) + b"\0" * 64
    path.write_bytes(gzip.compress(raw))
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A valid pair, and one hostile file per case."""
    d = tmp_path_factory.mktemp("hostile")
    good = _cube()
    write_labels(good, d / "good.nii.gz")
    write_labels(_cube(lo=5, hi=12), d / "good2.nii.gz")
    f = {"good": d / "good.nii.gz", "good2": d / "good2.nii.gz", "dir": d}
    (d / "garbage.nii.gz").write_bytes(os.urandom(2000))
    f["garbage"] = d / "garbage.nii.gz"
    (d / "text.nii").write_text("this is not an image\n" * 40)
    f["text"] = d / "text.nii"
    noisy = np.random.default_rng(0).integers(0, 9, (48, 48, 48)).astype(np.uint8)  # compresses poorly
    _nifti(d / "noisy.nii.gz", noisy)
    whole = (d / "noisy.nii.gz").read_bytes()
    (d / "truncated.nii.gz").write_bytes(whole[: len(whole) // 2])
    f["truncated_gz"] = d / "truncated.nii.gz"
    _nifti(d / "full.nii", good.array)
    (d / "truncated.nii").write_bytes((d / "full.nii").read_bytes()[:-500])
    f["truncated_nii"] = d / "truncated.nii"
    from volreg.io.fields import write_displacement

    u = np.random.default_rng(1).normal(0, 1, (*good.shape, 3))  # compresses poorly
    write_displacement(u, good, d / "warp.nii.gz")
    whole = (d / "warp.nii.gz").read_bytes()
    (d / "truncated_warp.nii.gz").write_bytes(whole[: len(whole) // 2])
    f["truncated_warp"] = d / "truncated_warp.nii.gz"
    f["bomb"] = _bomb(d / "bomb.nii.gz")
    f["4d"] = _nifti(d / "4d.nii.gz", np.zeros((8, 8, 8, 3), np.uint8))
    twod = LabelVolume(np.pad(np.ones((6, 6), np.uint8), 5), (0.0, 0.0), (1.0, 1.0), np.eye(2))
    write_labels(twod, d / "2d.nii.gz")
    f["2d"] = d / "2d.nii.gz"
    nan = good.array.astype(np.float32)
    nan[0, 0, 0] = np.nan
    f["nan"] = _nifti(d / "nan.nii.gz", nan)
    inf = good.array.astype(np.float32)
    inf[0, 0, 0] = np.inf
    f["inf"] = _nifti(d / "inf.nii.gz", inf)
    f["float_labels"] = _nifti(d / "float.nii.gz", good.array.astype(np.float32) * 0.5)
    f["zero_spacing"] = _mha(d / "zero.mha", spacing="0 1 1")
    f["nifti_zero_pixdim"] = _patch_pixdim(_nifti(d / "zero_pixdim.nii.gz", good.array), 2, 0.0)
    f["nifti_negative_pixdim"] = _patch_pixdim(_nifti(d / "neg_pixdim.nii", good.array), 1, -2.0)
    f["negative_spacing"] = _mha(d / "negative.mha", spacing="-1 1 1")
    f["singular_direction"] = _mha(d / "singular.mha", matrix="1 0 0 0 0 0 0 0 1")
    qs = nib.Nifti1Image(good.array, np.eye(4))
    qs.set_qform(np.eye(4), code=1)
    shifted = np.eye(4)
    shifted[:3, 3] = [5.0, 0.0, 0.0]
    qs.set_sform(shifted, code=1)
    nib.save(qs, str(d / "qs.nii.gz"))
    f["qform_sform"] = d / "qs.nii.gz"
    sheared = np.eye(4)
    sheared[0, 1] = 0.3
    sh = nib.Nifti1Image(good.array, sheared)
    sh.set_qform(None, code=0)
    sh.set_sform(sheared, code=1)
    nib.save(sh, str(d / "sheared.nii.gz"))
    f["sheared"] = d / "sheared.nii.gz"
    rgb = sitk.Image([6, 6, 6], sitk.sitkVectorUInt8, 3)
    sitk.WriteImage(rgb, str(d / "rgb.mha"))
    f["vector"] = d / "rgb.mha"
    (d / "image.png").write_bytes(b"\x89PNG\r\n")
    f["png"] = d / "image.png"
    write_labels(_cube(lo=7, hi=8), d / "dot.nii.gz")  # a single voxel of label 1
    f["dot"] = d / "dot.nii.gz"
    write_labels(_cube(lo=8, hi=9), d / "dot2.nii.gz")
    f["dot2"] = d / "dot2.nii.gz"
    write_labels(_cube(label=2), d / "other_label.nii.gz")
    f["other_label"] = d / "other_label.nii.gz"
    write_labels(_cube(origin=(500.0, 0.0, 0.0)), d / "far.nii.gz")
    f["far"] = d / "far.nii.gz"
    write_labels(_cube().with_array(np.zeros((16, 16, 16), np.uint8)), d / "empty.nii.gz")
    f["empty"] = d / "empty.nii.gz"
    # landmarks (LPS mm; the cube spans 0..15 mm)
    (d / "l3.csv").write_text("x,y,z\n5,5,5\n6,6,6\n7,7,7\n")
    (d / "l2.csv").write_text("x,y,z\n5,5,5\n6,6,6\n")
    (d / "lnan.csv").write_text("x,y,z\n5,5,5\nnan,6,6\n7,7,7\n")
    (d / "lnohead.csv").write_text("5,5,5\n6,6,6\n7,7,7\n")
    (d / "lfar.csv").write_text("x,y,z\n5,5,5\n6,6,6\n700,7,7\n")
    (d / "lbad.mrk.json").write_text('{"markups": [{"coordinateSystem": "XYZ", "controlPoints": []}]}')
    (d / "l2col.csv").write_text("x,y\n5,5\n6,6\n7,7\n")
    for name in ("l3", "l2", "lnan", "lnohead", "lfar", "l2col"):
        f[name] = d / f"{name}.csv"
    f["lbad"] = d / "lbad.mrk.json"
    # protocols
    (d / "unknown_key.toml").write_text('[warp]\nlambda_lco = 1.0\n')
    (d / "wrong_type.toml").write_text('[warp]\nalpha = "ten"\n')
    (d / "out_of_range.toml").write_text('[warp]\nlambda_loc = -1.0\n')
    (d / "not_toml.toml").write_text('[warp\nalpha = = 1\n')
    (d / "unknown_section.toml").write_text('[wrap]\nalpha = 1.0\n')
    (d / "bad_int.toml").write_text('[warp]\nmax_iter = 2.5\n')
    for name in ("unknown_key", "wrong_type", "out_of_range", "not_toml", "unknown_section", "bad_int"):
        f[name] = d / f"{name}.toml"
    # saved models
    np.savez(d / "pickled.npz", obj=np.array([{"a": 1}], dtype=object))
    f["pickled_model"] = d / "pickled.npz"
    (d / "garbage.npz").write_bytes(os.urandom(500))
    f["garbage_model"] = d / "garbage.npz"
    return f


def _outputs(outdir: Path) -> list[str]:
    return sorted(p.name for p in outdir.rglob("*")) if outdir.exists() else []


# (id, command line with {names} of `files` and {out}, words the one-line message must contain)
CASES = [
    ("non-image bytes", "surface {garbage} -o {out}", ["garbage.nii.gz", "not a readable NIfTI"]),
    ("text as .nii", "surface {text} -o {out}", ["text.nii", "NIfTI"]),
    ("truncated gzip", "surface {truncated_gz} -o {out}", ["truncated.nii.gz", "is truncated", "gzip stream ends before"]),
    ("truncated nii", "surface {truncated_nii} -o {out}", ["truncated"]),
    ("gzip bomb header", "surface {bomb} -o {out}", ["bomb.nii.gz", "GB in memory", "VOLREG_MAX_IMAGE_GB"]),
    ("4-D image", "register {4d} {good} -o {out}", ["4d.nii.gz", "expected a 2-D or 3-D image"]),
    ("2-D with 3-D", "register {2d} {good} -o {out}", ["2-D", "3-D", "expected two volumes of one dimension"]),
    ("NaN voxels", "register {nan} {good} -o {out}", ["nan.nii.gz", "NaN", "expected integer labels"]),
    ("Inf voxels", "register {good} {inf} -o {out}", ["inf.nii.gz", "Inf", "expected integer labels"]),
    ("float labels", "surface {float_labels} -o {out}", ["non-integral", "expected integer labels"]),
    ("zero spacing", "surface {zero_spacing} -o {out}", ["zero.mha", "spacing"]),
    ("negative spacing", "surface {negative_spacing} -o {out}", ["negative.mha", "negative spacing"]),
    ("NIfTI zero pixdim", "surface {nifti_zero_pixdim} -o {out}", ["zero_pixdim.nii.gz", "pixdim", "positive"]),
    ("NIfTI negative pixdim", "surface {nifti_negative_pixdim} -o {out}", ["neg_pixdim.nii", "pixdim", "positive"]),
    ("singular direction", "surface {singular_direction} -o {out}", ["singular.mha", "direction matrix is singular"]),
    ("qform != sform", "register {qform_sform} {good} -o {out}", ["qs.nii.gz", "qform", "sform", "disagree"]),
    ("sheared affine", "surface {sheared} -o {out}", ["sheared.nii.gz", "not orthogonal"]),
    ("vector image", "surface {vector} -o {out}", ["rgb.mha", "expected a scalar image"]),
    ("missing file", "register {dir}/nope.nii.gz {good} -o {out}", ["nope.nii.gz", "does not exist"]),
    ("directory as image", "surface {dir} -o {out}", ["not a regular file"]),
    ("unsupported suffix", "surface {png} -o {out}", ["image.png", "unsupported suffix"]),
    ("no common label", "register {good} {other_label} -o {out}", ["label"]),
    ("grids far apart, no linear stage", "register {good} {far} -o {out} --linear none", ["do not overlap", "no linear stage"]),
    ("empty volume", "register {empty} {good} -o {out}", ["label"]),
    ("one-voxel label only", "register {dot} {dot2} -o {out}", ["[1]", "single voxel"]),
    ("landmark counts differ", "register {good} {good2} -o {out} --landmarks {l3} {l2}", ["--landmarks", "3 points", "same number"]),
    ("landmark NaN", "register {good} {good2} -o {out} --landmarks {lnan} {l3}", ["lnan.csv"]),
    ("landmark without header", "register {good} {good2} -o {out} --landmarks {lnohead} {l3}", ["lnohead.csv"]),
    ("landmark outside image", "register {good} {good2} -o {out} --landmarks {l3} {lfar}", ["point 3", "outside", "extent"]),
    ("landmark coordinate system", "register {good} {good2} -o {out} --landmarks {lbad} {l3}", ["XYZ", "LPS or RAS"]),
    ("landmark 2 columns", "register {good} {good2} -o {out} --landmarks {l2col} {l3}", ["l2col.csv"]),
    ("protocol unknown key", "register {good} {good2} -o {out} --protocol {unknown_key}", ["warp.lambda_lco", "expected one of"]),
    ("protocol wrong type", "register {good} {good2} -o {out} --protocol {wrong_type}", ["warp.alpha", "float"]),
    ("protocol out of range", "register {good} {good2} -o {out} --protocol {out_of_range}", ["lambda_loc", ">= 0"]),
    ("protocol not TOML", "register {good} {good2} -o {out} --protocol {not_toml}", ["not valid TOML"]),
    ("protocol unknown section", "register {good} {good2} -o {out} --protocol {unknown_section}", ["[wrap]"]),
    ("protocol float for int", "register {good} {good2} -o {out} --protocol {bad_int}", ["max_iter", "int"]),
    ("protocol unknown preset", "register {good} {good2} -o {out} --protocol fastest", ["fastest", "no such preset or file"]),
    ("pickled model", "apply {pickled_model} {good} --reference {good} -o {out}/x.nii.gz",
     ["pickled.npz", "not a valid volreg kernel warp"]),
    ("truncated warp", "apply {truncated_warp} {good} --reference {good} -o {out}/x.nii.gz",
     ["truncated_warp.nii.gz", "is truncated"]),
    ("garbage model", "apply {garbage_model} {good} --reference {good} -o {out}/x.nii.gz",
     ["garbage.npz", "not a zip archive"]),
    ("output path with ..", "register {good} {good2} -o {out}/../escape", ["..", "expected an output path"]),
    ("tune grid key", "tune {good} {good2} -o {out} --grid lambda_lco=1", ["--grid", "warp.lambda_lco"]),
    ("consistency one direction", "consistency {good} {good2} -o {out} --forward {dir}", ["--forward", "without --backward"]),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_hostile_input_refused(files, tmp_path, capsys, case):
    _, line, words = case
    out = tmp_path / "out"
    args = line.format(out=out, **files).split()
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and re.match(r"volreg \w[\w-]*: error: ", err), err
    assert "Traceback" not in err
    for w in words:
        assert w in err, (w, err)
    assert _outputs(out) == [] and not (tmp_path / "escape").exists()


def test_at_least_thirty_cases_and_mesh_cases_counted():
    assert len(CASES) + len(MESH_CASES) >= 30


def test_existing_outputs_are_not_overwritten(files, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("keep")
    assert main(["register", str(files["good"]), str(files["good2"]), "-o", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert _outputs(out) == ["keep.txt"]
    (tmp_path / "file").write_text("x")
    assert main(["register", str(files["good"]), str(files["good2"]), "-o", str(tmp_path / "file")]) == 2
    assert "file" in capsys.readouterr().err and (tmp_path / "file").read_text() == "x"
    target = tmp_path / "exists.nii.gz"
    target.write_bytes(b"keep")
    assert main(["apply", str(files["good"]), str(files["good"]), "--reference", str(files["good"]), "-o", str(target)]) == 2
    assert target.read_bytes() == b"keep"


# ----------------------------------------------------------------------------- meshes (API)


def _mesh_file(d: Path, name: str) -> Path:
    if name == "empty":
        pv.PolyData().save(str(d / "empty.vtk"))
        return d / "empty.vtk"
    if name == "nan":
        mesh = pv.Sphere(theta_resolution=8, phi_resolution=8)
        pts = np.array(mesh.points)
        pts[3] = np.nan
        mesh.points = pts
        mesh.save(str(d / "nan.vtk"))
        return d / "nan.vtk"
    if name == "garbage":
        (d / "garbage.vtk").write_bytes(os.urandom(300))
        return d / "garbage.vtk"
    if name == "suffix":
        (d / "mesh.xyz").write_text("1 2 3\n")
        return d / "mesh.xyz"
    return d / "absent.vtk"


MESH_CASES = [("empty mesh", "empty", "empty"), ("NaN vertices", "nan", "NaN"),
              ("non-mesh bytes", "garbage", "could not be read"), ("mesh suffix", "suffix", "suffix"),
              ("missing mesh", "absent", "does not exist")]


@pytest.mark.parametrize("case", MESH_CASES, ids=[c[0] for c in MESH_CASES])
def test_hostile_mesh_refused(tmp_path, capsys, case):
    """Through `volreg register-surfaces` (exit 2, one line, nothing written) and `read_mesh`."""
    _, name, word = case
    path = _mesh_file(tmp_path, name)
    pv.Sphere().save(str(tmp_path / "good.vtk"))
    out = tmp_path / "out"
    assert main(["register-surfaces", str(path), str(tmp_path / "good.vtk"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("volreg register-surfaces: error: ") and path.name in err and word in err, err
    assert _outputs(out) == []
    with pytest.raises(VolregIOError) as info:
        read_mesh(path)
    message = str(info.value)
    assert "\n" not in message and path.name in message and word in message, message


# ----------------------------------------------------------------------------- interrupts


def _start(args, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    # SIGINT as from a terminal: an earlier test (Dask) may leave it ignored in this process,
    # and an ignored signal stays ignored in children (Python then installs no handler for it).
    return subprocess.Popen([sys.executable, "-m", "volreg", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
@pytest.mark.system
def test_interrupted_registration_leaves_nothing(tmp_path, sig):
    """Kill `volreg register` mid-run: a clean one-line message, non-zero exit, OUTDIR gone."""
    from volreg.synthetic import GaussianBumps, deform_labels
    from helpers import blob_volume

    a = blob_volume()
    write_labels(a, tmp_path / "a.nii.gz")
    write_labels(deform_labels(a, GaussianBumps(np.zeros((1, 3)), np.array([[3.0, 0, 0]]), 40.0)), tmp_path / "b.nii.gz")
    (tmp_path / "p.toml").write_text(TEST_PROTOCOL)
    out = tmp_path / "out"
    # One whole run first, so that numba's kernels are compiled and cached: the interrupted run
    # then is the usual one (an interrupt during compilation: the ctypes-callback test below).
    warm = _start(["register", tmp_path / "a.nii.gz", tmp_path / "b.nii.gz", "-o", tmp_path / "warm",
                   "--protocol", tmp_path / "p.toml", "--quiet"], tmp_path)
    warm_err = warm.communicate(timeout=300)[1]
    assert warm.returncode == 0, warm_err
    proc = _start(["register", tmp_path / "a.nii.gz", tmp_path / "b.nii.gz", "-o", out, "--protocol",
                   tmp_path / "p.toml", "-v"], tmp_path)
    # wait until the warp fit has started (stderr logs stages once they finish; poll for the directory)
    deadline = time.time() + 120
    # (the run writes into a hidden sibling of `out`, renamed to `out` once complete)
    while not list(tmp_path.glob(".out.volreg-new-*")) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    # The directory appears about 1 s into a run of about 2 s; waiting 1 s here can let the run
    # finish (restoring the default SIGTERM action) before the signal is sent.
    time.sleep(0.3)
    assert proc.poll() is None, "the registration finished before it could be interrupted"
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == (130 if sig == signal.SIGINT else 143), err
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("volreg register: ") or "interrupted" in ln]
    assert lines == [f"volreg register: interrupted by {sig.name}; the outputs of this run were removed."], err
    assert not out.exists() and not list(tmp_path.glob("**/*.tmp*")) and not list(tmp_path.glob(".out.volreg-*"))


def test_interrupt_lost_in_a_ctypes_callback_still_stops_the_run(tmp_path, monkeypatch, capsys):
    """Ctrl-C during numba's first compilation of a kernel lands in an llvmlite ctypes callback,
    where Python only reports it ("Exception ignored"), and the run would go on to finish with
    exit 0. The next progress report must raise it again: exit 130, one line, OUTDIR gone."""
    import ctypes

    import volreg.outputs.registration as registration
    from helpers import blob_volume

    def raise_sigint() -> None:
        raise KeyboardInterrupt("SIGINT")

    def register_labels(*args, progress=None, **kwargs):
        ctypes.CFUNCTYPE(None)(raise_sigint)()  # swallowed by ctypes: reaches sys.unraisablehook
        progress("fit warp", 1, 4)
        raise AssertionError("the interrupt was not raised again")

    monkeypatch.setattr(registration, "register_labels", register_labels)
    vol = blob_volume()
    write_labels(vol, tmp_path / "a.nii.gz")
    write_labels(vol, tmp_path / "b.nii.gz")
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["register", str(tmp_path / "a.nii.gz"), str(tmp_path / "b.nii.gz"), "-o", str(out), "--quiet"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["volreg register: interrupted by SIGINT; the outputs of this run were removed."]
    assert not out.exists()


# ----------------------------------------------------------------------------- determinism


@pytest.mark.system
def test_registration_is_deterministic_across_runs_and_threads(tmp_path):
    """Two runs give byte-identical outputs; 1 and 2 threads give the same warp (within 1e-6 mm)."""
    from volreg.synthetic import GaussianBumps, deform_labels
    from volreg.warp.model import KernelWarp
    from helpers import blob_volume

    a = blob_volume()
    write_labels(a, tmp_path / "a.nii.gz")
    truth = GaussianBumps(np.array([[0.0, 0.0, 0.0], [10.0, 5.0, 0.0]]), np.array([[3.0, 0, 0], [0, -2.0, 1.0]]), 15.0)
    write_labels(deform_labels(a, truth), tmp_path / "b.nii.gz")
    (tmp_path / "p.toml").write_text(TEST_PROTOCOL)
    outs = []
    for i, threads in enumerate(("2", "2", "1")):
        env_threads = {k: threads for k in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
        proc = subprocess.run([sys.executable, "-m", "volreg", "register", "a.nii.gz", "b.nii.gz", "-o", f"out{i}",
                               "--protocol", "p.toml", "--quiet"], cwd=tmp_path, capture_output=True, text=True,
                              env=dict(os.environ, PYTHONPATH=str(REPO), **env_threads))
        assert proc.returncode == 0, proc.stderr
        outs.append(tmp_path / f"out{i}")
    for name in ("warp.nii.gz", "inverse_warp.nii.gz", "warped.nii.gz", "model.npz", "jacobian.nii.gz"):
        assert (outs[0] / name).read_bytes() == (outs[1] / name).read_bytes(), name
    x = a.grid_points().reshape(-1, 3)[::7]
    two, one = (KernelWarp.load(o / "model.npz") for o in (outs[0], outs[2]))
    assert np.abs(two(x) - one(x)).max() <= 1e-6


# ----------------------------------------------------------------------------- divergence


class _NaNFeature:
    """A feature function that returns NaN (e.g. a corrupted implicit surface)."""

    def evaluate(self, points, order=1):
        n, d = points.shape
        out = [np.full(n, np.nan), np.full((n, d), np.nan), np.full((n, d, d), np.nan)]
        return tuple(out[: order + 1])


def test_divergence_stops_with_the_level_named():
    from volreg.settings import WarpSettings

    pts = np.random.default_rng(0).uniform(-10, 10, (200, 3))
    with pytest.raises(RegistrationDiverged, match=r"Warp level 0 \(kernel width .* mm\) diverged.*protocol"):
        fit_warp([FeaturePair(_NaNFeature(), _NaNFeature())], pts, settings=WarpSettings(min_width=8.0, max_iter=5))


def _folding_warp(volume: LabelVolume) -> KernelWarp:
    """Level 0: a gentle 1 mm shift bump; level 1: a 6 mm-wide bump of 10 mm that folds around the centre."""
    from volreg.warp.model import WarpLevel

    centre = volume.index_to_world((np.array(volume.shape)[None] - 1) / 2.0)
    gentle = WarpLevel(centre, np.array([[1.0, 0.0, 0.0]]), width=40.0)
    folding = WarpLevel(centre, np.array([[10.0, 0.0, 0.0]]), width=6.0)
    return KernelWarp([gentle, folding], dim=3)


def test_a_warp_folding_the_grid_stops_with_the_level_named():
    from volreg.warp.field import jacobian_determinant_on_grid
    from volreg.warp.fit import check_folding

    volume = _cube()
    warp = _folding_warp(volume)
    det = jacobian_determinant_on_grid(warp, volume)
    assert 0.0 < np.mean(det <= 0) < 0.5  # it folds, locally
    with pytest.raises(RegistrationDiverged, match=r"Warp level 1 \(kernel width 6 mm\) folds space.*min_width"):
        check_folding(warp, volume, det, 0.001)
    check_folding(warp, volume, det, 0.5)  # tolerated above its folded fraction
    gentle = KernelWarp(warp.levels[:1], dim=3)
    check_folding(gentle, volume, jacobian_determinant_on_grid(gentle, volume), 0.0)


def test_register_writes_nothing_when_the_warp_folds(files, tmp_path, capsys, monkeypatch):
    import volreg.outputs.registration as registration

    real = registration.register_labels

    def folding(fixed, moving, **kwargs):
        result = real(fixed, moving, **kwargs)
        result.warp = _folding_warp(fixed)
        return result

    monkeypatch.setattr(registration, "register_labels", folding)
    (tmp_path / "p.toml").write_text(TEST_PROTOCOL)
    out = tmp_path / "out"
    assert main(["register", str(files["good"]), str(files["good2"]), "-o", str(out), "--protocol",
                 str(tmp_path / "p.toml"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "folds space" in err and "max_folded_fraction" in err
    assert _outputs(out) == []


# ----------------------------------------------------------------------------- safe loading


def test_no_unsafe_loaders_in_the_package():
    pattern = re.compile(r"\bimport pickle\b|allow_pickle\s*=\s*True|yaml\.load\(|\beval\(|\bexec\(|marshal\.loads")
    hits = [f"{p.name}:{i}" for p in (REPO / "volreg").rglob("*.py")
            for i, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]
    assert hits == []
    loads = [p.name for p in (REPO / "volreg").rglob("*.py") if "np.load(" in p.read_text()]
    for name in loads:
        text = next((REPO / "volreg").rglob(name)).read_text()
        assert text.count("np.load(") == text.count("allow_pickle=False"), name


def test_header_without_orientation_is_reported(tmp_path, capsys):
    """qform_code = sform_code = 0: SimpleITK and nibabel disagree on the geometry; volreg reads it as
    ITK does and says so in one warning line."""
    img = nib.Nifti1Image(_cube().array, np.diag([2.0, 3.0, 4.0, 1.0]))
    img.set_qform(None, code=0)
    img.set_sform(None, code=0)
    nib.save(img, str(tmp_path / "nocode.nii.gz"))
    assert main(["surface", str(tmp_path / "nocode.nii.gz"), "-o", str(tmp_path / "out"), "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("volreg surface: warning: ") and "sform_code = 0" in err[0]


def test_fields_on_grid_is_displacement_and_jacobian_determinant_in_one_pass():
    from volreg.warp.field import displacement_on_grid, fields_on_grid, jacobian_determinant_on_grid

    volume = _cube()
    warp = _folding_warp(volume)
    u, det = fields_on_grid(warp, volume, chunk=1000)  # several chunks
    np.testing.assert_allclose(u, displacement_on_grid(warp, volume), rtol=0, atol=1e-12)
    np.testing.assert_allclose(det, jacobian_determinant_on_grid(warp, volume), rtol=0, atol=1e-12)
    assert np.mean(det <= 0) > 0 and np.abs(u).max() > 1.0  # a warp that moves and folds
