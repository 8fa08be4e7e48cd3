"""Kernel warps (paper eq. 9): exact properties, analytic Jacobian, serialisation, composition.

Finite differences use a step of 1e-4 mm on warps whose kernel widths are
tens of mm: the central-difference truncation error (about h^2 |c| k''' / sigma^3)
is below 1e-9 and the rounding error (about 1e-16 * 100 mm / h) below 1e-10,
so agreement to 1e-6 relative (1e-8 absolute on near-zero entries) tests the
analytic Jacobian, not the difference scheme.
"""

import json
import zipfile

import numpy as np
import pytest

from volreg.io import VolregIOError
from volreg.warp.model import FORMAT, ComposedWarp, KernelWarp, WarpLevel, jacobian_det

FD_STEP = 1e-4  # mm


def random_warp(rng, dim, widths=(40.0, 20.0, 10.0), centres=(6, 15, 40), scale=1.0, settings=None):
    """A multi-level warp with centres in [-30, 30]^D mm and coefficients of about `scale` mm."""
    levels = [
        WarpLevel(rng.uniform(-30, 30, (m, dim)), scale * rng.normal(size=(m, dim)) * w / 40.0, w)
        for w, m in zip(widths, centres)
    ]
    return KernelWarp(levels, dim=dim, settings=settings)


def fd_jacobian(f, x, h=FD_STEP):
    """Central differences: J[n, a, b] = (f(x + h e_b) - f(x - h e_b))_a / 2h."""
    n, dim = x.shape
    jac = np.empty((n, dim, dim))
    for b in range(dim):
        e = np.zeros(dim)
        e[b] = h
        jac[:, :, b] = (f(x + e) - f(x - e)) / (2 * h)
    return jac


def assert_jacobian_close(jac, ref):
    np.testing.assert_allclose(jac, ref, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("dim", [2, 3])
def test_identity_is_exact(dim):
    rng = np.random.default_rng(0)
    x = rng.uniform(-100, 100, (50, dim))
    warp = KernelWarp.identity(dim)
    assert warp.is_identity and warp.levels == ()
    np.testing.assert_array_equal(warp(x), x)
    np.testing.assert_array_equal(warp.displacement(x), 0.0)
    np.testing.assert_array_equal(warp.jacobian(x), np.broadcast_to(np.eye(dim), (50, dim, dim)))
    # A level of zero coefficients is still the identity, exactly.
    zero = warp.with_level(WarpLevel(rng.uniform(-10, 10, (5, dim)), np.zeros((5, dim)), 30.0))
    assert zero.is_identity and len(zero.levels) == 1 and len(warp.levels) == 0
    np.testing.assert_array_equal(zero(x), x)
    np.testing.assert_array_equal(zero.jacobian(x), warp.jacobian(x))


@pytest.mark.parametrize("dim", [2, 3])
def test_one_centre_moves_its_centre_by_k0_c(dim):
    rng = np.random.default_rng(1)
    centre = rng.uniform(-5, 5, (1, dim))
    c = rng.normal(size=(1, dim))
    width = 2.0
    warp = KernelWarp([WarpLevel(centre, c, width)], dim=dim)
    assert not warp.is_identity
    np.testing.assert_array_equal(warp(centre), centre + 4.0 * c)  # k(0) = 4
    # Zero displacement at distance >= width: exactly width along the axes (r = 1
    # exactly in floating point), and a hair beyond it in random directions.
    on_axes = np.zeros((2 * dim, dim))
    on_axes[np.arange(dim), np.arange(dim)] = width
    on_axes[dim + np.arange(dim), np.arange(dim)] = -width
    warp0 = KernelWarp([WarpLevel(np.zeros((1, dim)), c, width)], dim=dim)
    np.testing.assert_array_equal(warp0.displacement(on_axes), 0.0)
    u = rng.normal(size=(200, dim))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    dist = width * rng.uniform(1 + 1e-9, 3, (200, 1))
    far = centre + dist * u
    np.testing.assert_array_equal(warp(far), far)
    np.testing.assert_array_equal(warp.jacobian(far), np.broadcast_to(np.eye(dim), (200, dim, dim)))
    # ... and non-zero just inside.
    near = centre + width * 0.99 * u
    assert np.all(np.abs(warp.displacement(near)).max(axis=1) > 0)


@pytest.mark.parametrize("dim", [2, 3])
def test_jacobian_matches_finite_differences(dim):
    rng = np.random.default_rng(2 + dim)
    warp = random_warp(rng, dim)
    x = rng.uniform(-35, 35, (60, dim))
    tau, jac = warp.evaluate(x, order=1)
    # The value alone and with the Jacobian are summed by two variants of one SIMD loop.
    np.testing.assert_allclose(tau, warp(x), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(jac, warp.jacobian(x))
    assert np.abs(jac - np.eye(dim)).max() > 0.1  # the test has teeth: a real deformation
    assert_jacobian_close(jac, fd_jacobian(warp, x))


@pytest.mark.parametrize("dim", [2, 3])
def test_displacement_is_sum_of_levels(dim):
    rng = np.random.default_rng(10 + dim)
    warp = random_warp(rng, dim)
    x = rng.uniform(-35, 35, (40, dim))
    parts = [KernelWarp([lev], dim=dim).displacement(x) for lev in warp.levels]
    np.testing.assert_allclose(warp.displacement(x), np.sum(parts, axis=0), rtol=0, atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_save_load_round_trip(tmp_path, dim):
    rng = np.random.default_rng(20 + dim)
    settings = {"protocol": "test", "widths": [40.0, 20.0], "alpha": 10.0, "nested": {"seed": 3}}
    warp = random_warp(rng, dim, settings=settings)
    path = tmp_path / "warp.npz"
    warp.save(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["warp.npz"]  # no temporary left over
    loaded = KernelWarp.load(path)
    x = rng.uniform(-40, 40, (100, dim))
    np.testing.assert_array_equal(loaded(x), warp(x))
    np.testing.assert_array_equal(loaded.jacobian(x), warp.jacobian(x))
    assert loaded.settings == settings and loaded.dim == dim and loaded.widths == warp.widths
    with np.load(path, allow_pickle=False) as data:
        assert str(data["format"]) == FORMAT and int(data["format_version"]) == 2
        assert data["format"].shape == () and data["format"].dtype.kind == "U"
        assert json.loads(str(data["settings_json"])) == settings
        assert int(data["dim"]) == dim and data["centres_0"].shape == (6, dim)
    # A name without .npz is kept as given.
    other = tmp_path / "model.warp"
    KernelWarp.identity(dim).save(other)
    assert other.exists() and KernelWarp.load(other).is_identity
    # Arrays round trip without a file.
    again = KernelWarp.from_arrays(warp.to_arrays())
    np.testing.assert_array_equal(again(x), warp(x))


def test_save_refuses_to_overwrite(tmp_path):
    path = tmp_path / "warp.npz"
    warp = random_warp(np.random.default_rng(30), 3)
    warp.save(path)
    before = path.read_bytes()
    with pytest.raises(VolregIOError, match="exists"):
        KernelWarp.identity(3).save(path)
    assert path.read_bytes() == before
    KernelWarp.identity(3).save(path, force=True)
    assert KernelWarp.load(path).is_identity


def _write_npz(path, arrays):
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def test_load_rejects_bad_files(tmp_path):
    good = random_warp(np.random.default_rng(31), 2).to_arrays()

    def check(name, arrays, match):
        path = tmp_path / name
        _write_npz(path, arrays)
        with pytest.raises(ValueError, match=match) as info:
            KernelWarp.load(path)
        assert name in str(info.value) and "\n" not in str(info.value)
        assert isinstance(info.value, VolregIOError)

    check("wrong_format.npz", {**good, "format": np.array("something-else")}, "format")
    check("no_format.npz", {k: v for k, v in good.items() if k != "format"}, "format")
    check("newer.npz", {**good, "format_version": np.array(3)}, "format_version 3")
    check("missing_key.npz", {k: v for k, v in good.items() if k != "coeffs_1"}, "coeffs_1")
    check("missing_settings.npz", {k: v for k, v in good.items() if k != "settings_json"}, "settings_json")
    check("bad_shape.npz", {**good, "coeffs_0": good["coeffs_0"][:-1]}, "same shape")
    check("wrong_dim.npz", {**good, "centres_0": np.zeros((6, 3))}, "centres_0")
    check("nan.npz", {**good, "coeffs_2": np.full_like(good["coeffs_2"], np.nan)}, "NaN")
    check("bad_width.npz", {**good, "widths": np.array([40.0, -1.0, 10.0])}, "widths")
    check("extra_level.npz", {**good, "centres_3": np.zeros((1, 2)), "coeffs_3": np.zeros((1, 2))}, "centres_3")
    check("bad_json.npz", {**good, "settings_json": np.array("{not json")}, "settings_json")
    check("object.npz", {**good, "centres_0": np.array([None, 1], dtype=object)}, "centres_0")

    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"this is not a zip archive")
    with pytest.raises(VolregIOError, match="corrupt.npz"):
        KernelWarp.load(corrupt)
    truncated = tmp_path / "truncated.npz"
    blob = (tmp_path / "wrong_format.npz").read_bytes()
    truncated.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(VolregIOError, match="truncated.npz"):
        KernelWarp.load(truncated)
    # A compressed archive whose directory is intact but whose members are damaged.
    damaged = tmp_path / "damaged.npz"
    random_warp(np.random.default_rng(32), 2).save(damaged)
    blob = bytearray(damaged.read_bytes())
    with zipfile.ZipFile(damaged) as zf:
        info = zf.getinfo("centres_2.npy")
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 60
    blob[start : start + 64] = bytes(64)
    damaged.write_bytes(bytes(blob))
    with pytest.raises(VolregIOError, match="damaged.npz.*centres_2"):
        KernelWarp.load(damaged)
    single = tmp_path / "single.npy"
    np.save(single, np.zeros(3))
    with pytest.raises(VolregIOError, match="single.npy"):
        KernelWarp.load(single)
    with pytest.raises(VolregIOError, match="does not exist"):
        KernelWarp.load(tmp_path / "absent.npz")
    assert zipfile.is_zipfile(tmp_path / "wrong_format.npz")
    with pytest.raises(ValueError, match="format"):
        KernelWarp.from_arrays({**good, "format": np.array("x")})


@pytest.mark.parametrize("dim", [2, 3])
def test_compose(dim):
    rng = np.random.default_rng(40 + dim)
    a = random_warp(rng, dim)
    b = random_warp(rng, dim, widths=(30.0, 15.0), centres=(8, 20))
    c = random_warp(rng, dim, widths=(25.0,), centres=(10,))
    x = rng.uniform(-35, 35, (50, dim))
    ab = a.compose(b)
    assert isinstance(ab, ComposedWarp) and ab.warps == (a, b)
    np.testing.assert_array_equal(ab(x), b(a(x)))
    np.testing.assert_array_equal(ab.displacement(x), b(a(x)) - x)
    assert not np.allclose(ab(x), a(b(x)))  # the order matters, and is a first
    jac = ab.jacobian(x)
    np.testing.assert_allclose(jac, b.jacobian(a(x)) @ a.jacobian(x), rtol=0, atol=1e-14)
    assert_jacobian_close(jac, fd_jacobian(ab, x))
    abc = ab.compose(c)
    assert abc.warps == (a, b, c)
    np.testing.assert_array_equal(abc(x), c(b(a(x))))
    assert_jacobian_close(abc.jacobian(x), fd_jacobian(abc, x))
    assert a.compose(KernelWarp.identity(dim)).compose(KernelWarp.identity(dim))(x).tolist() == a(x).tolist()
    assert KernelWarp.identity(dim).compose(KernelWarp.identity(dim)).is_identity
    with pytest.raises(ValueError, match="dimension"):
        a.compose(KernelWarp.identity(5 - dim))


def test_chunking_does_not_change_results():
    rng = np.random.default_rng(50)
    warp = random_warp(rng, 3)
    x = rng.uniform(-35, 35, (101, 3))
    calls = []
    tau7, jac7 = warp.evaluate(x, chunk=7, progress=lambda *a: calls.append(a))
    tau, jac = warp.evaluate(x)
    # Chunks group the points into other blocks of the kernel sums, whose SIMD reductions
    # group the terms differently: the results change by rounding only.
    np.testing.assert_allclose(tau7, tau, rtol=0, atol=1e-12)
    np.testing.assert_allclose(jac7, jac, rtol=0, atol=1e-13)
    np.testing.assert_allclose(warp.displacement(x, chunk=7), warp.displacement(x), rtol=0, atol=1e-12)
    assert len(calls) == 15 and calls[-1] == ("evaluate warp", 101, 101)
    assert [c[1] for c in calls] == sorted(c[1] for c in calls)
    composed = warp.compose(random_warp(rng, 3))
    np.testing.assert_allclose(composed.jacobian(x, chunk=7), composed.jacobian(x), rtol=0, atol=1e-13)
    big = rng.uniform(-35, 35, (60_000, 3))
    np.testing.assert_allclose(warp.jacobian(big), warp.jacobian(big, chunk=20_000), rtol=0, atol=1e-13)
    np.testing.assert_array_equal(warp.jacobian(big), warp.jacobian(big))
    assert warp(np.zeros((0, 3))).shape == (0, 3) and warp.jacobian(np.zeros((0, 3))).shape == (0, 3, 3)


def test_warps_are_immutable():
    rng = np.random.default_rng(60)
    centres, coeffs = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    lev = WarpLevel(centres, coeffs, 5.0)
    coeffs[:] = 0  # the level holds its own copy
    assert lev.coeffs.any()
    with pytest.raises(ValueError):
        lev.coeffs[0, 0] = 1.0  # read-only
    with pytest.raises(AttributeError):
        lev.width = 3.0
    warp = KernelWarp([lev], dim=3, settings={"a": [1, 2]})
    s = warp.settings
    s["a"].append(3)
    assert warp.settings == {"a": [1, 2]}


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: WarpLevel(np.zeros((3, 3)), np.zeros((2, 3)), 1.0), "`coeffs`"),
        (lambda: WarpLevel(np.zeros((3, 3)), np.zeros((3, 2)), 1.0), "`coeffs`"),
        (lambda: WarpLevel(np.zeros((3, 4)), np.zeros((3, 4)), 1.0), "`centres`"),
        (lambda: WarpLevel(np.zeros(3), np.zeros(3), 1.0), "`centres`"),
        (lambda: WarpLevel(np.full((1, 2), np.nan), np.zeros((1, 2)), 1.0), "`centres`"),
        (lambda: WarpLevel(np.zeros((1, 2)), np.full((1, 2), np.inf), 1.0), "`coeffs`"),
        (lambda: WarpLevel(np.zeros((1, 2)), np.zeros((1, 2)), 0.0), "`width`"),
        (lambda: WarpLevel(np.zeros((1, 2)), np.zeros((1, 2)), np.nan), "`width`"),
        (lambda: KernelWarp(dim=4), "`dim`"),
        (lambda: KernelWarp([WarpLevel(np.zeros((1, 2)), np.zeros((1, 2)), 1.0)], dim=3), "`levels`"),
        (lambda: KernelWarp(dim=3, settings={"x": object()}), "`settings`"),
        (lambda: KernelWarp(dim=3, settings={"x": float("nan")}), "`settings`"),
        (lambda: KernelWarp.identity(3).with_level(WarpLevel(np.zeros((1, 2)), np.zeros((1, 2)), 1.0)), "`level`"),
    ],
)
def test_bad_construction(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_bad_points():
    warp = random_warp(np.random.default_rng(70), 3)
    with pytest.raises(ValueError, match=r"`points` of shape \(N, 3\)"):
        warp(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="`points`"):
        warp.jacobian(np.zeros(3))
    bad = np.zeros((4, 3))
    bad[2, 1] = np.nan
    for f in (warp, warp.jacobian, warp.displacement, warp.compose(warp)):
        with pytest.raises(ValueError, match="finite values in `points`"):
            f(bad)
    with pytest.raises(ValueError, match="`chunk`"):
        warp(np.zeros((4, 3)), chunk=0)
    with pytest.raises(ValueError, match="`order`"):
        warp.evaluate(np.zeros((4, 3)), order=2)


@pytest.mark.parametrize("dim", [2, 3])
def test_jacobian_det_matches_numpy(dim):
    """Closed-form determinants equal np.linalg.det's on random stacks (also with leading axes);
    a rotation gives 1, a reflection -1."""
    rng = np.random.default_rng(dim)
    jac = rng.normal(size=(4, 50, dim, dim))
    np.testing.assert_allclose(jacobian_det(jac), np.linalg.det(jac), rtol=1e-12, atol=1e-12)
    t = 0.7
    rot = np.eye(dim)
    rot[:2, :2] = [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]
    flip = np.diag([-1.0] + [1.0] * (dim - 1))
    np.testing.assert_allclose(jacobian_det(np.stack([rot, flip])), [1.0, -1.0], atol=1e-14)


@pytest.mark.parametrize("shape", [(5, 4, 4), (5, 3), (3,), (5, 2, 3)])
def test_jacobian_det_rejects_other_shapes(shape):
    with pytest.raises(ValueError, match="jac"):
        jacobian_det(np.zeros(shape))
