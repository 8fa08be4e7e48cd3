"""Reliability of memory: a job's size is judged from its images' headers before any voxel is read.

A compressed file of a kilobyte may declare a 2000^3 image (8 GB, under the per-file limit of half
the memory on most machines) that the readers would decompress and allocate, twice over, before
the command found out that it could not hold its grids' world points or signed distances.  Every
command that reads label volumes or images estimates its job from the headers first and refuses,
in one line naming the file, the estimate and the limit (exit status 2), with nothing decompressed:
here the readers of voxels are made to fail the test if they are reached at all.
"""

from __future__ import annotations

import gzip
import re
import subprocess
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk

from volreg.io import write_labels
from helpers import cube, run

REPO = Path(__file__).resolve().parent.parent
IDENTITY_TFM = ("#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
                "Parameters: 1 0 0 0 1 0 0 0 1 0 0 0\nFixedParameters: 0 0 0\n")


def _bomb(path: Path, shape=(2000, 2000, 2000), dtype=np.uint8, body: int = 1 << 16) -> Path:
    """A ``.nii.gz`` of a valid header declaring ``shape`` and a few bytes of zeros after it."""
    header = nib.Nifti1Header()
    header.set_data_shape(shape)
    header.set_data_dtype(dtype)
    header.set_qform(np.eye(4), 1)
    header.set_sform(np.eye(4), 1)
    header["vox_offset"] = 352
    path.write_bytes(gzip.compress(header.binaryblock + b"\0" * 4 + b"\0" * body))
    return path


def _zeros_bomb(path: Path, prefix: bytes, blocks: int, size: int = 1 << 24) -> Path:
    """A valid gzip file of ``prefix`` then ``blocks`` x ``size`` zero bytes, made without compressing them all:
    deflate blocks ended by a full flush stand alone, so one block of zeros is repeated."""
    import struct
    import zlib

    deflate = zlib.compressobj(9, zlib.DEFLATED, -zlib.MAX_WBITS)
    head = deflate.compress(prefix) + deflate.flush(zlib.Z_FULL_FLUSH)
    zeros = bytes(size)
    block = deflate.compress(zeros) + deflate.flush(zlib.Z_FULL_FLUSH)
    crc = zlib.crc32(prefix)
    for _ in range(blocks):
        crc = zlib.crc32(zeros, crc)
    total = len(prefix) + blocks * size
    path.write_bytes(b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x02\xff" + head + block * blocks + deflate.flush()
                     + struct.pack("<II", crc, total & 0xFFFFFFFF))
    return path


def test_zeros_bomb_is_a_valid_gzip_file(tmp_path):
    path = _zeros_bomb(tmp_path / "z.gz", b"header", 3, 1 << 16)
    assert gzip.decompress(path.read_bytes()) == b"header" + bytes(3 << 16)


@pytest.fixture()
def no_voxels(monkeypatch):
    """Fail the test if any image's voxels are read or decompressed."""
    import volreg.io.header_checks as header_checks

    def refuse(*args, **kwargs):
        raise AssertionError("voxels were read before the job's memory was checked")

    monkeypatch.setattr(sitk.ImageFileReader, "Execute", refuse)
    monkeypatch.setattr(sitk, "ReadImage", refuse)
    monkeypatch.setattr(header_checks, "_check_nifti_length", refuse)
    monkeypatch.setattr(nib.arrayproxy.ArrayProxy, "__array__", refuse)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("memory")
    header = nib.Nifti1Header()  # 2048^3 bytes (8 GiB) of zeros in an 8 MB file, the kind a download may hold
    header.set_data_shape((2048, 2048, 2048))
    header.set_data_dtype(np.uint8)
    header.set_qform(np.eye(4), 1)
    header.set_sform(np.eye(4), 1)
    header["vox_offset"] = 352
    _zeros_bomb(d / "zeros.nii.gz", header.binaryblock + b"\0" * 4, 512)
    write_labels(cube(), d / "good.nii.gz")
    (d / "identity.tfm").write_text(IDENTITY_TFM)
    _bomb(d / "bomb.nii.gz")
    write_labels(cube(shape=(40, 40, 40), lo=10, hi=30), d / "modest.nii.gz")
    (d / "p.toml").write_text("[protocol]\nname = \"t\"\n[warp]\nmin_width = 8.0\n")
    return d


#: Every command that reads label volumes or images, with the file ``{big}`` in each place it can take.
COMMANDS = {
    "surface": "surface {big} -o {out}",
    "register (fixed)": "register {big} {good} -o {out} --protocol {p}",
    "register (moving)": "register {good} {big} -o {out} --protocol {p}",
    "apply (input)": "apply {tfm} {big} --reference {good} -o {out}/x.nii.gz",
    "apply (input, linear)": "apply {tfm} {big} --reference {good} --interpolation linear -o {out}/x.nii.gz",
    "apply (--reference)": "apply {tfm} {good} --reference {big} -o {out}/x.nii.gz",
    "apply (field)": "apply {big_field} {good} --reference {good} -o {out}/x.nii.gz",
    "consistency": "consistency {good} {big} -o {out} --protocol {p}",
    "tune": "tune {big} {good} -o {out} --grid lambda_loc=1,10 --protocol {p}",
}


def _line(command: str, files: Path, big: Path, tmp_path: Path) -> list[str]:
    return COMMANDS[command].format(big=big, good=files / "good.nii.gz", tfm=files / "identity.tfm", p=files / "p.toml",
                                    big_field=tmp_path / "warp.nii.gz", out=tmp_path / "out").split()


def _field(path: Path, shape) -> Path:
    """A displacement field's header (X, Y, Z, 1, 3 float32, intent vector) over a few bytes."""
    header = nib.Nifti1Header()
    header.set_data_shape((*shape, 1, 3))
    header.set_data_dtype(np.float32)
    header.set_intent("vector")
    header.set_qform(np.eye(4), 1)
    header.set_sform(np.eye(4), 1)
    header["vox_offset"] = 352
    path.write_bytes(gzip.compress(header.binaryblock + b"\0" * 4 + b"\0" * 4096))
    return path


def _refused(capfd, name: str, limit: str) -> str:
    err = capfd.readouterr().err.strip()
    assert "\n" not in err and re.match(r"volreg [\w-]+: error: ", err), err
    assert f"{name}`" in err and "would need" in err and f"GB is {limit}" in err and "VOLREG_MAX_MEMORY_GB" in err, err
    return err


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_header_bomb_refused_before_reading(files, tmp_path, capfd, monkeypatch, no_voxels, command):
    """2000^3 declared in a kilobyte (a field of 1000^3): under a per-file limit of 64 GB, a job limit of 8 GB."""
    monkeypatch.setenv("VOLREG_MAX_IMAGE_GB", "64")
    monkeypatch.setenv("VOLREG_MAX_MEMORY_GB", "8")
    _field(tmp_path / "warp.nii.gz", (1000, 1000, 1000))  # 12 GB of float32
    assert run(_line(command, files, files / "bomb.nii.gz", tmp_path), protocol=False) == 2
    err = _refused(capfd, "warp.nii.gz" if "field" in command else "bomb.nii.gz", "allowed (VOLREG_MAX_MEMORY_GB)")
    assert ("1000, 1000, 1000" if "field" in command else "2000, 2000, 2000") in err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_lowered_limit_refuses_a_modest_volume_before_reading(files, tmp_path, capfd, monkeypatch, no_voxels,
                                                               command):
    """40^3 voxels against VOLREG_MAX_MEMORY_GB=0.0001 (107 kB): the same refusal, from the header."""
    monkeypatch.setenv("VOLREG_MAX_MEMORY_GB", "0.0001")
    _field(tmp_path / "warp.nii.gz", (40, 40, 40))
    assert run(_line(command, files, files / "modest.nii.gz", tmp_path), protocol=False) == 2
    _refused(capfd, "warp.nii.gz" if "field" in command else "modest.nii.gz", "allowed (VOLREG_MAX_MEMORY_GB)")


def test_batch_pair_refused_before_reading(files, tmp_path, monkeypatch, no_voxels):
    """A batch's pair is refused on its worker from the headers too (a failed row, the others go on)."""
    from volreg.cohort import run_pair

    monkeypatch.setenv("VOLREG_MAX_IMAGE_GB", "64")
    monkeypatch.setenv("VOLREG_MAX_MEMORY_GB", "8")
    row = run_pair("a", str(files / "good.nii.gz"), "b", str(files / "bomb.nii.gz"), str(tmp_path / "pair"),
                   str(files / "p.toml"))
    assert row["status"] == "failed" and "bomb.nii.gz" in row["error"] and "would need about" in row["error"], row


def test_the_memory_available_is_the_default_limit(files, tmp_path, capfd, monkeypatch, no_voxels):
    """Without VOLREG_MAX_MEMORY_GB the limit is the memory available now."""
    import volreg._memory

    monkeypatch.setenv("VOLREG_MAX_IMAGE_GB", "64")
    monkeypatch.setattr(volreg._memory, "available_bytes", lambda: 4 * 1024**3)
    assert run(["surface", files / "bomb.nii.gz", "-o", tmp_path / "out"]) == 2
    err = _refused(capfd, "bomb.nii.gz", "available")
    assert "would need at least 96.9 GB of memory and 4 GB is available" in err, err


@pytest.mark.parametrize("value", ["x", "0", "-1", "inf"])
def test_the_limit_must_be_a_positive_number(files, tmp_path, capfd, monkeypatch, value):
    monkeypatch.setenv("VOLREG_MAX_MEMORY_GB", value)
    assert run(["surface", files / "good.nii.gz", "-o", tmp_path / "out"]) == 2
    assert "VOLREG_MAX_MEMORY_GB" in capfd.readouterr().err


def test_jobs_within_the_limit_run(files, tmp_path, monkeypatch):
    monkeypatch.setenv("VOLREG_MAX_MEMORY_GB", "4")
    assert run(["surface", files / "good.nii.gz", "-o", tmp_path / "s", "--quiet"]) == 0
    assert run(["apply", files / "identity.tfm", files / "good.nii.gz", "--reference", files / "good.nii.gz", "-o",
                tmp_path / "x.nii.gz", "--quiet"]) == 0


#: The command's peak resident memory, MB: VmHWM of its own address space (ru_maxrss would keep the
#: high-water mark of the forking test process across exec, the whole suite's size by then).
_PEAK = """
import re, sys
from volreg.cli import main
status = main(sys.argv[1:])
with open("/proc/self/status") as f:
    print(int(re.search(r"VmHWM:\\s+(\\d+) kB", f.read()).group(1)) // 1024, status)
"""


@pytest.mark.parametrize("command", ["surface", "register (moving)", "apply (--reference)"])
def test_peak_memory_stays_small(files, tmp_path, command):
    """An 8 MB file that inflates to 8 GiB of valid voxels, under a per-file limit of 64 GB: in a fresh
    interpreter the command ends in one line, its resident memory never near what the file holds."""
    line = _line(command, files, files / "zeros.nii.gz", tmp_path)
    env = {"PYTHONPATH": str(REPO), "VOLREG_MAX_IMAGE_GB": "64", "VOLREG_MAX_MEMORY_GB": "8",
           "VOLREG_COMPILE_AHEAD": "0", "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-c", _PEAK, *line], capture_output=True, text=True, env=env, timeout=300)
    peak_mb, status = (int(v) for v in done.stdout.split()[-2:])
    assert status == 2 and done.stderr.count("\n") == 1 and "2048, 2048, 2048" in done.stderr, done.stderr
    assert peak_mb < 1500, (peak_mb, done.stderr)
