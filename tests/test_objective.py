"""Objective (11): analytic gradient against finite differences, terms behave as defined."""

import numpy as np
import pytest

from volreg.kernels import kernel_gradient_matrices, kernel_matrix, kernel_sum
from volreg.warp.objective import FeaturePair, LevelObjective, simplex_vertices


class SphereSDF:
    """Exact signed distance of a sphere, with gradient and Hessian."""

    def __init__(self, centre, radius):
        self.centre, self.radius = np.asarray(centre, float), float(radius)

    def evaluate(self, x, order=1):
        d = x - self.centre
        n = np.linalg.norm(d, axis=1)
        out = [n - self.radius]
        if order >= 1:
            u = d / n[:, None]
            out.append(u)
        if order >= 2:
            dim = x.shape[1]
            out.append((np.eye(dim)[None] - u[:, :, None] * u[:, None, :]) / n[:, None, None])
        return tuple(out)


def _objective(dim, rng, **kw):
    samples = rng.uniform(-6, 6, (150, dim))
    centres = samples[::3]
    sigma = 5.0
    feats = [FeaturePair(SphereSDF(np.zeros(dim), 4.0), SphereSDF(np.full(dim, 0.7), 4.5)),
             FeaturePair(SphereSDF(np.full(dim, 2.0), 2.0), SphereSDF(np.full(dim, 2.5), 2.2), weight=0.5)]
    base = samples + 0.1 * np.sin(samples)
    lm = rng.uniform(-4, 4, (5, dim))
    return LevelObjective(
        kernel=kernel_matrix(samples, centres, sigma),
        kernel_centres=kernel_matrix(centres, centres, sigma),
        base=base, samples=samples, features=feats,
        landmark_kernel=kernel_matrix(lm, centres, sigma), landmark_base=lm + 0.05,
        landmark_targets=lm + 0.5, **kw,
    )


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize(
    "kw",
    [dict(lambda_loc=3.0, alpha=0.0), dict(lambda_loc=3.0, alpha=2.0, lambda_p=0.7),
     dict(lambda_loc=1.0, alpha=1.0, neighbourhood=simplex_vertices(2, 0.5)),
     dict(lambda_loc=2.0, alpha=1.0, lambda_target=5.0), dict(lambda_loc=3.0, alpha=1.0, robust=0.3)],
    ids=["distance-only", "distance+gradient+landmarks", "neighbourhood", "consistency", "robust"],
)
def test_gradient_matches_finite_differences(dim, kw):
    rng = np.random.default_rng(20 + dim)
    if "neighbourhood" in kw:
        kw = dict(kw, neighbourhood=simplex_vertices(dim, 0.5))
    if "lambda_target" in kw:
        kw = dict(kw, sample_targets=rng.uniform(-6, 6, (150, dim)))
    obj = _objective(dim, rng, **kw)
    c = rng.normal(0, 0.05, obj.n_centres * dim)
    value, grad = obj(c)
    if "lambda_target" in kw:
        resid = obj.warp_samples(c.reshape(-1, dim)) - kw["sample_targets"]
        assert obj.last_terms["consistency"] == pytest.approx(kw["lambda_target"] * np.mean(np.sum(resid**2, axis=1)))
    h = 1e-6
    idx = rng.choice(len(c), 25, replace=False)
    fd = np.array([(obj(c + h * np.eye(len(c))[i])[0] - obj(c - h * np.eye(len(c))[i])[0]) / (2 * h) for i in idx])
    np.testing.assert_allclose(grad[idx], fd, rtol=1e-5, atol=1e-7 * np.abs(grad).max())


@pytest.mark.parametrize("dim", [2, 3])
def test_fold_barrier_gradient_matches_finite_differences(dim):
    rng = np.random.default_rng(30 + dim)
    samples = rng.uniform(-6, 6, (120, dim))
    centres = samples[::2]
    check = rng.uniform(-6, 6, (200, dim))
    f = SphereSDF(np.zeros(dim), 4.0)
    obj = LevelObjective(
        kernel=kernel_matrix(samples, centres, 5.0), kernel_centres=kernel_matrix(centres, centres, 5.0),
        base=samples.copy(), samples=samples, features=[FeaturePair(f, f)], lambda_loc=0.0,
        fold_gradients=kernel_gradient_matrices(check, centres, 5.0),
        fold_base=np.repeat(np.eye(dim)[None], len(check), axis=0), lambda_fold=50.0, fold_margin=0.9,
    )
    c = rng.normal(0, 0.4, obj.n_centres * dim)  # large enough that det J < 0.9 somewhere
    value, grad = obj(c)
    assert obj.last_terms["folding"] > 0
    h = 1e-6
    idx = rng.choice(len(c), 25, replace=False)
    fd = np.array([(obj(c + h * np.eye(len(c))[i])[0] - obj(c - h * np.eye(len(c))[i])[0]) / (2 * h) for i in idx])
    np.testing.assert_allclose(grad[idx], fd, rtol=1e-5, atol=1e-7 * np.abs(grad).max())


def test_a_repeated_point_is_evaluated_once_until_the_barrier_changes(monkeypatch):
    """The same coefficients twice give the same value, gradient and terms from one evaluation
    (a caller changing the returned gradient changes nothing kept); new coefficients, or new
    fold-barrier rows, evaluate again."""
    rng = np.random.default_rng(8)
    obj = _objective(3, rng, lambda_loc=3.0, alpha=1.0, lambda_fold=10.0, fold_margin=0.9,
                     fold_gradients=kernel_gradient_matrices(rng.uniform(-6, 6, (40, 3)),
                                                             rng.uniform(-6, 6, (50, 3)), 5.0),
                     fold_base=np.repeat(np.eye(3)[None], 40, axis=0))
    calls = []
    evaluate = obj._evaluate
    monkeypatch.setattr(obj, "_evaluate", lambda flat, blocks: calls.append(1) or evaluate(flat, blocks))
    c = rng.normal(0, 0.05, obj.n_centres * 3)
    value, grad = obj(c)
    terms = dict(obj.last_terms)
    grad[:] = 0.0
    again, grad2 = obj(c.copy())
    assert len(calls) == 1 and again == value and np.any(grad2 != 0) and obj.last_terms == terms
    obj(c + 1e-3)
    assert len(calls) == 2 and obj.last_terms != terms
    assert obj(c)[0] == value and obj(c)[0] == value and len(calls) == 3 and obj.last_terms == terms
    obj.set_fold(obj._fold, obj.fold_base)
    obj(c)
    assert len(calls) == 4


@pytest.mark.parametrize("batched", [True, False])
def test_objectives_on_shared_samples_evaluate_the_fixed_features_once(batched):
    """A second objective on the same samples and features (another level: other centres)
    reuses the first's fixed features at the samples and equals one made on its own."""
    rng = np.random.default_rng(9)
    samples = rng.uniform(-6, 6, (150, 3))
    calls = []

    class Counted(SphereSDF):
        def evaluate(self, x, *, order=1):
            calls.append(len(x))
            return super().evaluate(x, order=order)

    feats = [FeaturePair(Counted(np.zeros(3), 4.0), SphereSDF(np.full(3, 0.7), 4.5))]
    shared = {}

    def objective(centres, sigma, shared):
        return LevelObjective(kernel=kernel_matrix(samples, centres, sigma),
                              kernel_centres=kernel_matrix(centres, centres, sigma), base=samples + 0.1,
                              samples=samples, features=feats, lambda_loc=2.0, alpha=1.0, batched=batched,
                              shared=shared)

    objective(samples[::3], 5.0, shared)
    assert len(calls) == 1
    second = objective(samples[::5], 3.0, shared)
    assert len(calls) == 1
    alone = objective(samples[::5], 3.0, None)
    assert len(calls) == 2
    c = rng.normal(0, 0.1, second.n_centres * 3)
    assert second(c)[0] == alone(c)[0] and np.array_equal(second(c)[1], alone(c)[1])


def test_kernel_gradient_matrices_give_the_warp_jacobian():
    rng = np.random.default_rng(5)
    centres = rng.uniform(0, 5, (60, 3))
    coeffs = rng.normal(size=(60, 3))
    x = rng.uniform(0, 5, (40, 3))
    jac = np.stack([g @ coeffs for g in kernel_gradient_matrices(x, centres, 2.0)], axis=2) + np.eye(3)
    _, grad = kernel_sum(x, centres, coeffs, 2.0, order=1)
    np.testing.assert_allclose(jac, np.eye(3) + grad, atol=1e-12)


def test_terms_add_up_and_vanish_where_expected():
    rng = np.random.default_rng(3)
    obj = _objective(3, rng, lambda_loc=2.0, alpha=1.5, lambda_p=1.0)
    value, _ = obj(np.zeros(obj.n_centres * 3))
    t = obj.last_terms
    assert t["regulariser"] == 0.0  # zero coefficients
    assert t["folding"] == 0.0
    assert value == pytest.approx(t["regulariser"] + t["landmarks"] + t["distance"] + t["gradient"])
    # landmark residual is 0.45 in each coordinate at C = 0
    assert t["landmarks"] == pytest.approx(1.0 * 5 * 3 * 0.45**2)


def test_identical_objects_at_identity_cost_nothing():
    rng = np.random.default_rng(4)
    samples = rng.uniform(-5, 5, (80, 3))
    f = SphereSDF(np.zeros(3), 3.0)
    obj = LevelObjective(kernel=kernel_matrix(samples, samples, 4.0), kernel_centres=kernel_matrix(samples, samples, 4.0),
                         base=samples.copy(), samples=samples, features=[FeaturePair(f, f)], lambda_loc=5.0, alpha=2.0)
    value, grad = obj(np.zeros(80 * 3))
    assert value == 0.0 and np.all(grad == 0.0)


def test_simplex_vertices_are_regular():
    for dim in (2, 3):
        v = simplex_vertices(dim, 2.0)
        assert v.shape == (dim + 1, dim)
        np.testing.assert_allclose(v.sum(axis=0), 0, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), 2.0)
        d = np.linalg.norm(v[:, None] - v[None], axis=2)[np.triu_indices(dim + 1, 1)]
        np.testing.assert_allclose(d, d[0])


def test_robust_loss_is_pseudo_huber_of_the_residual():
    """Distance term with ``robust = d``: ``2 d^2 (sqrt(1 + (r/d)^2) - 1)`` per sample, which is
    ``r^2`` for small residuals and grows linearly for large ones."""
    samples = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 4.01], [0.0, 0.0, 30.0]])
    f1, f2 = SphereSDF(np.zeros(3), 4.0), SphereSDF(np.zeros(3), 4.0)
    moved = samples + np.array([0.0, 0.0, 0.5])  # residual f1(x) - f2(tau(x)) = -0.5 at every sample
    k = kernel_matrix(samples, samples, 1.0)

    def distance(robust):
        obj = LevelObjective(kernel=k, kernel_centres=k, base=moved, samples=samples,
                             features=[FeaturePair(f1, f2)], lambda_loc=3.0, robust=robust)
        obj(np.zeros(9))
        return obj.last_terms["distance"]

    d = 0.2
    assert distance(0.0) == pytest.approx(3.0 * 0.25)
    assert distance(d) == pytest.approx(3.0 * 2 * d**2 * (np.sqrt(1 + (0.5 / d) ** 2) - 1))
    assert distance(1e4) == pytest.approx(distance(0.0), rel=1e-6)
    with pytest.raises(ValueError, match="robust"):
        LevelObjective(kernel=k, kernel_centres=k, base=moved, samples=samples,
                       features=[FeaturePair(f1, f2)], lambda_loc=3.0, robust=-1.0)


def test_fold_barrier_needs_its_margin():
    """``fold_margin`` has no default of its own (``WarpSettings.fold_margin`` is the one):
    a barrier without it is refused by name."""
    rng = np.random.default_rng(6)
    samples = rng.uniform(-6, 6, (40, 3))
    check = rng.uniform(-6, 6, (30, 3))
    f = SphereSDF(np.zeros(3), 4.0)
    k = kernel_matrix(samples, samples, 5.0)
    fold = dict(fold_gradients=kernel_gradient_matrices(check, samples, 5.0),
                fold_base=np.repeat(np.eye(3)[None], len(check), axis=0), lambda_fold=50.0)
    with pytest.raises(ValueError, match="`fold_margin`"):
        LevelObjective(kernel=k, kernel_centres=k, base=samples.copy(), samples=samples,
                       features=[FeaturePair(f, f)], lambda_loc=1.0, **fold)
    obj = LevelObjective(kernel=k, kernel_centres=k, base=samples.copy(), samples=samples,
                         features=[FeaturePair(f, f)], lambda_loc=1.0, fold_margin=0.3, **fold)
    assert obj(np.zeros(40 * 3))[0] == 0.0  # identity: det J = 1 above the margin


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize(
    "kw",
    [dict(lambda_loc=3.0, alpha=0.0), dict(lambda_loc=3.0, alpha=2.0, lambda_p=0.7),
     dict(lambda_loc=2.0, alpha=1.0, lambda_target=5.0), dict(lambda_loc=3.0, alpha=1.0, robust=0.3)],
    ids=["distance-only", "distance+gradient+landmarks", "consistency", "robust"],
)
def test_gauss_newton_model_is_the_hessian_where_the_residuals_vanish(dim, kw):
    # f1 = f2 and tau_prev = identity: at C = 0 every feature residual is 0, where the
    # Gauss-Newton model (the pseudo-Huber's reweighting included) is the exact Hessian.
    rng = np.random.default_rng(40 + dim)
    samples = rng.uniform(-6, 6, (150, dim))
    centres = samples[::3]
    sphere = SphereSDF(np.zeros(dim), 4.0)
    small = SphereSDF(np.full(dim, 2.0), 2.0)
    lm = rng.uniform(-4, 4, (5, dim))
    extra = dict(sample_targets=samples.copy()) if "lambda_target" in kw else {}
    obj = LevelObjective(
        kernel=kernel_matrix(samples, centres, 5.0), kernel_centres=kernel_matrix(centres, centres, 5.0),
        base=samples.copy(), samples=samples,
        features=[FeaturePair(sphere, sphere), FeaturePair(small, small, weight=0.5)],
        landmark_kernel=kernel_matrix(lm, centres, 5.0), landmark_base=lm.copy(), landmark_targets=lm.copy(),
        **kw, **extra,
    )
    c = np.zeros(obj.n_centres * dim)
    value, grad, blocks = obj.gauss_newton(c)
    assert (value, grad.tolist()) == (obj(c)[0], obj(c)[1].tolist())
    hess = obj.gauss_newton_matrix(blocks)
    h = 1e-5
    idx = rng.choice(len(c), 12, replace=False)
    fd = np.array([(obj(c + h * np.eye(len(c))[i])[1] - obj(c - h * np.eye(len(c))[i])[1]) / (2 * h) for i in idx])
    np.testing.assert_allclose(hess[idx], fd, rtol=1e-5, atol=1e-6 * np.abs(hess).max())
    np.testing.assert_allclose(hess, hess.T, atol=1e-12 * np.abs(hess).max())


def test_gauss_newton_refuses_active_fold_rows():
    rng = np.random.default_rng(7)
    samples = rng.uniform(-6, 6, (60, 3))
    centres = samples[::2]
    check = rng.uniform(-6, 6, (30, 3))
    f = SphereSDF(np.zeros(3), 4.0)
    obj = LevelObjective(
        kernel=kernel_matrix(samples, centres, 5.0), kernel_centres=kernel_matrix(centres, centres, 5.0),
        base=samples.copy(), samples=samples, features=[FeaturePair(f, f)], lambda_loc=1.0,
        fold_gradients=kernel_gradient_matrices(check, centres, 5.0),
        fold_base=np.repeat(np.eye(3)[None], len(check), axis=0), lambda_fold=50.0, fold_margin=0.9,
    )
    assert not obj.gauss_newton_ready
    with pytest.raises(ValueError, match="fold"):
        obj.gauss_newton(np.zeros(obj.n_centres * 3))


@pytest.mark.parametrize("kw", [dict(lambda_loc=3.0, alpha=2.0, lambda_p=0.7), dict(lambda_loc=3.0, alpha=1.0, robust=0.3)],
                         ids=["gradient+landmarks", "robust"])
def test_gauss_newton_reaches_the_minimum_that_lbfgs_finds(kw):
    import scipy.optimize

    from volreg.warp.fit import _gauss_newton

    obj = _objective(3, np.random.default_rng(50), **kw)
    start = np.zeros((obj.n_centres, 3))
    ref = scipy.optimize.minimize(obj, start.ravel(), jac=True, method="L-BFGS-B",
                                  options=dict(maxiter=5000, ftol=1e-15, gtol=1e-12))
    res = _gauss_newton(obj, start, max_iter=200, ftol=1e-10)
    assert res.success and res.nit < 25
    assert obj(start.ravel())[0] > ref.fun + 0.1  # a way from the start
    assert res.fun <= ref.fun * (1 + 1e-8)
    # The warp at the samples agrees within a thousandth of a mm.
    moved = np.abs(obj.warp_samples(ref.x.reshape(-1, 3)) - obj.base).max()
    assert moved > 0.1
    assert np.abs(obj.warp_samples(res.x.reshape(-1, 3)) - obj.warp_samples(ref.x.reshape(-1, 3))).max() < 1e-3
