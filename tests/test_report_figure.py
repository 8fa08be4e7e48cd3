"""Tests for volreg.io.report_figure: the PNG registration report."""

from __future__ import annotations

from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from PIL import Image

from volreg.io import VolregIOError
from volreg.io.report_figure import _PALETTE, _label_rgb, write_report_figure

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
SHAPE = (20, 18, 16)


def _case(ndim: int = 3, moved: bool = False) -> dict:
    """Two box labels; warped = fixed shifted by one voxel; zero or smooth displacement."""
    fixed = np.zeros(SHAPE, dtype=np.uint8)
    fixed[3:12, 4:14, 2:12] = 1
    fixed[12:18, 5:15, 4:14] = 2
    moving = np.zeros((22, 20, 14), dtype=np.int16)
    moving[4:13, 5:15, 2:11] = 1
    moving[13:19, 6:16, 3:12] = 2
    warped = np.roll(fixed, 1, axis=0)
    disp = np.zeros(SHAPE + (3,))
    if moved:
        idx = np.indices(SHAPE).astype(float)
        disp[..., 0] = 1.5 * np.sin(idx[1] / 3.0)
        disp[..., 1] = np.cos(idx[0] / 4.0)
        disp[..., 2] = 0.5 * np.sin(idx[2] / 3.0)
    if ndim == 2:
        return dict(
            fixed=fixed[:, :, 8],
            moving=moving[:, :, 6],
            warped=warped[:, :, 8],
            displacement=disp[:, :, 8, :2],
            fixed_spacing=(1.0, 1.2),
            moving_spacing=(1.0, 1.0),
        )
    return dict(
        fixed=fixed,
        moving=moving,
        warped=warped,
        displacement=disp,
        fixed_spacing=(1.0, 1.2, 2.5),
        moving_spacing=(1.0, 1.0, 2.0),
    )


def _write(path: Path, case: dict, **kwargs) -> None:
    write_report_figure(
        path,
        case["fixed"],
        case["moving"],
        case["warped"],
        case["displacement"],
        fixed_spacing=case["fixed_spacing"],
        moving_spacing=case["moving_spacing"],
        **kwargs,
    )


def _read_png(path: Path) -> np.ndarray:
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    image = mpimg.imread(path)
    assert image.ndim == 3 and image.shape[2] in (3, 4)
    assert image.shape[1] <= 1600
    return image[..., :3]


def _has_label_colour(image: np.ndarray, label: int) -> bool:
    colour = _label_rgb(np.array([label]))[0]
    return bool(np.any(np.all(np.abs(image - colour) < 2.5 / 255, axis=-1)))


def _only(directory: Path, *names: str) -> None:
    assert sorted(p.name for p in directory.iterdir()) == sorted(names)


@pytest.mark.parametrize("moved", [False, True], ids=["zero_displacement", "displacement"])
def test_writes_png_3d(tmp_path, moved):
    out = tmp_path / "report.png"
    _write(out, _case(moved=moved), title="fixed vs moving")
    image = _read_png(out)
    assert np.any(image.max(axis=-1) > 0.1)  # not all black
    assert _has_label_colour(image, 1) and _has_label_colour(image, 2)
    _only(tmp_path, "report.png")


def test_displacement_changes_grid_panel(tmp_path):
    _write(tmp_path / "zero.png", _case(moved=False))
    _write(tmp_path / "moved.png", _case(moved=True))
    zero, moved = _read_png(tmp_path / "zero.png"), _read_png(tmp_path / "moved.png")
    assert zero.shape == moved.shape
    width = zero.shape[1]
    differs = np.any(np.abs(zero - moved) > 1e-3, axis=(0, 2))
    # Only the last column (the warped grid) depends on the displacement.
    assert differs[3 * width // 4 :].any()
    assert not differs[: 7 * width // 10].any()


def test_writes_png_2d(tmp_path):
    out = tmp_path / "slice.png"
    _write(out, _case(ndim=2, moved=True))
    image = _read_png(out)
    assert _has_label_colour(image, 1) and _has_label_colour(image, 2)
    assert image.shape[0] < image.shape[1]  # one row of four panels
    _only(tmp_path, "slice.png")


def test_palette_is_matplotlibs_tab20():
    from matplotlib import colormaps

    tab20 = np.asarray(colormaps["tab20"].colors, dtype=float)[:, :3]
    assert np.allclose(_PALETTE, np.concatenate([tab20[0::2], tab20[1::2]]), atol=1e-12)


def test_label_colours_are_fixed_per_value():
    rgb = _label_rgb(np.array([[0, 1, 2], [21, 1, 0]], dtype=np.int32))
    assert np.array_equal(rgb[0, 0], [0.0, 0.0, 0.0])
    assert np.array_equal(rgb[0, 1], rgb[1, 1])
    assert np.array_equal(rgb[1, 0], rgb[0, 1])  # the palette repeats every 20 labels
    assert not np.array_equal(rgb[0, 1], rgb[0, 2])
    assert np.all(_PALETTE.sum(axis=1) > 0.3)  # no label is drawn black


@pytest.mark.parametrize("name", ["report.jpg", "report", "report.png.txt"])
def test_wrong_suffix(tmp_path, name):
    with pytest.raises(VolregIOError, match=r"Expected `path` ending in `\.png`"):
        _write(tmp_path / name, _case())
    _only(tmp_path)


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("warped", np.zeros((20, 18, 15), np.uint8), r"Expected `warped` of shape \(X, Y, Z\) = \(20, 18, 16\), got \(20, 18, 15\)"),
        ("displacement", np.zeros((20, 18, 16, 2)), r"Expected `displacement` of shape \(X, Y, Z, 3\) = \(20, 18, 16, 3\), got"),
        ("displacement", np.zeros((20, 18, 15, 3)), r"Expected `displacement` of shape"),
        ("moving", np.zeros((22, 20), np.int16), r"Expected `moving` of shape \(X', Y', Z'\) \(3-D like `fixed`\), got \(22, 20\)"),
        ("fixed", np.zeros((20, 18, 16), np.float32), r"Expected `fixed` of integer dtype"),
        ("fixed", np.zeros((20,), np.uint8), r"Expected `fixed` of shape"),
        ("fixed_spacing", (1.0, 1.0), r"Expected `fixed_spacing` of 3 positive finite voxel sizes"),
        ("moving_spacing", (1.0, 0.0, 1.0), r"Expected `moving_spacing` of 3 positive finite voxel sizes"),
    ],
)
def test_bad_inputs(tmp_path, key, value, message):
    case = _case()
    case[key] = value
    with pytest.raises(VolregIOError, match=message):
        _write(tmp_path / "report.png", case)
    _only(tmp_path)


def test_2d_shape_mismatch(tmp_path):
    case = _case(ndim=2)
    case["displacement"] = np.zeros(SHAPE[:2] + (3,))
    with pytest.raises(VolregIOError, match=r"Expected `displacement` of shape \(X, Y, 2\) = \(20, 18, 2\)"):
        _write(tmp_path / "report.png", case)
    _only(tmp_path)


def test_existing_file_needs_force(tmp_path):
    out = tmp_path / "report.png"
    out.write_bytes(b"old bytes")
    with pytest.raises(VolregIOError, match="exists; pass --force"):
        _write(out, _case(ndim=2))
    assert out.read_bytes() == b"old bytes"
    _only(tmp_path, "report.png")
    _write(out, _case(ndim=2), force=True)
    _read_png(out)
    _only(tmp_path, "report.png")


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
    def broken(self, filename, *args, **kwargs):
        Path(filename).write_bytes(b"partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Image.Image, "save", broken)
    with pytest.raises(OSError, match=r"No space left on device.*report.png"):
        _write(tmp_path / "report.png", _case(ndim=2))
    _only(tmp_path)


def test_a_displacement_in_mm_with_its_matrix_draws_as_the_same_in_voxels(tmp_path):
    """``to_voxels`` turns a displacement in LPS mm into voxels on the drawn slices: the figure
    equals the one drawn from the displacement converted beforehand."""
    case = _case(moved=True)
    direction = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    spacing = np.array(case["fixed_spacing"])
    to_voxels = direction / spacing
    mm = case["displacement"] @ np.linalg.inv(to_voxels)
    _write(tmp_path / "voxels.png", case)
    _write(tmp_path / "mm.png", dict(case, displacement=mm), to_voxels=to_voxels)
    _write(tmp_path / "raw.png", dict(case, displacement=mm))
    voxels, converted, raw = (_read_png(tmp_path / n) for n in ("voxels.png", "mm.png", "raw.png"))
    assert np.array_equal(voxels, converted) and not np.array_equal(voxels, raw)
    with pytest.raises(VolregIOError, match="to_voxels"):
        _write(tmp_path / "bad.png", case, to_voxels=np.eye(2))


def test_the_report_figure_is_drawn_without_importing_matplotlib(tmp_path):
    """Every registration writes the report figure: it is drawn with Pillow alone (importing
    matplotlib costs a registration a quarter of a second)."""
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from volreg.io.report_figure import write_report_figure\n"
        "a = np.zeros((12, 10), np.uint8); a[3:8, 2:7] = 1\n"
        f"write_report_figure({str(tmp_path / 'r.png')!r}, a, a, a, np.zeros((12, 10, 2)),"
        " fixed_spacing=(1, 1), moving_spacing=(1, 1))\n"
        "print('matplotlib' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "False"
    assert (tmp_path / "r.png").read_bytes()[:8] == PNG_SIGNATURE


def test_a_pillow_whose_font_takes_no_anchor_still_draws_the_text(tmp_path, monkeypatch):
    """Older Pillows refuse a text anchor for their bitmap font (where built without FreeType)."""
    from PIL import ImageDraw

    text = ImageDraw.ImageDraw.text

    def no_anchor(self, xy, message, *args, **kwargs):
        if kwargs.get("anchor") is not None:
            raise ValueError("anchor not supported for non-TrueType fonts")
        return text(self, xy, message, *args, **kwargs)

    monkeypatch.setattr(ImageDraw.ImageDraw, "text", no_anchor)
    _write(tmp_path / "report.png", _case(moved=True), title="fixed vs moving")
    image = _read_png(tmp_path / "report.png")
    assert _has_label_colour(image, 1) and _has_label_colour(image, 2)
    assert np.any(image[:30].min(axis=-1) < 0.5)  # the title's dark pixels at the top
