"""Tests for dtm_labeler.model.mixture (value object, eq. 6-7) and .mixture_em (eq. 8-11)."""
from __future__ import annotations

import io

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from dtm_labeler.model.mixture import GaussianMixture, params_per_component, stable_cholesky
from dtm_labeler.model.mixture_em import (FitResult, FixedKMixture, MDLMixture, SingleGaussian,
                                          make_estimator, message_length)

ESTIMATORS = {
    "single": lambda seed=0: SingleGaussian(random_state=seed),
    "fixed": lambda seed=0: FixedKMixture(3, random_state=seed),
    "mdl": lambda seed=0: MDLMixture(1, 8, random_state=seed),
}


# --------------------------------------------------------------------------- helpers
def random_mixture(rng, k: int, d: int, spread: float = 3.0, eig=(0.3, 2.0)) -> GaussianMixture:
    weights = rng.dirichlet(np.full(k, 3.0))
    means = rng.normal(scale=spread, size=(k, d))
    covs = np.empty((k, d, d))
    for i in range(k):
        q, _ = np.linalg.qr(rng.standard_normal((d, d)))
        covs[i] = (q * rng.uniform(*eig, size=d)) @ q.T
    return GaussianMixture(weights, means, 0.5 * (covs + covs.transpose(0, 2, 1)))


def reference_log_pdf(weights, means, covs, X) -> np.ndarray:
    comps = [np.log(w) + multivariate_normal(m, c).logpdf(X).reshape(-1)
             for w, m, c in zip(weights, means, covs)]
    return logsumexp(np.stack(comps, axis=1), axis=1)


@pytest.fixture(scope="module")
def three_cluster_data():
    """Well-separated 3-component mixture in 15-D (the triangle feature dimension)."""
    rng = np.random.default_rng(12345)
    d = 15
    directions = np.linalg.qr(rng.standard_normal((d, 3)))[0].T
    means = np.vstack([np.zeros(d), 12.0 * directions[0], 12.0 * directions[1]])
    covs = np.empty((3, d, d))
    for i in range(3):
        q, _ = np.linalg.qr(rng.standard_normal((d, d)))
        covs[i] = (q * rng.uniform(0.5, 2.0, size=d)) @ q.T
    truth = GaussianMixture(np.array([0.5, 0.3, 0.2]), means, 0.5 * (covs + covs.transpose(0, 2, 1)))
    return truth, truth.sample(3000, np.random.default_rng(7))


@pytest.fixture(scope="module")
def single_gaussian_data():
    rng = np.random.default_rng(99)
    d = 15
    a = rng.standard_normal((d, d))
    cov = a @ a.T / d + 0.5 * np.eye(d)
    return rng.multivariate_normal(rng.standard_normal(d), cov, size=3000)


@pytest.fixture(scope="module")
def small_data():
    rng = np.random.default_rng(5)
    return random_mixture(rng, 2, 4, spread=4.0).sample(600, rng)


# --------------------------------------------------------------- value object: density
@pytest.mark.parametrize("d", [1, 3, 15])
@pytest.mark.parametrize("k", [1, 4])
def test_log_pdf_matches_scipy(d, k):
    rng = np.random.default_rng(d * 10 + k)
    gm = random_mixture(rng, k, d)
    X = gm.sample(400, rng) + rng.normal(scale=0.5, size=(400, d))
    ref = reference_log_pdf(gm.weights, gm.means, gm.covariances, X)
    np.testing.assert_allclose(gm.log_pdf(X), ref, rtol=1e-8, atol=1e-10)
    comp = gm.component_log_pdf(X)
    assert comp.shape == (400, k)
    for j in range(k):
        np.testing.assert_allclose(
            comp[:, j], np.log(gm.weights[j]) + multivariate_normal(gm.means[j], gm.covariances[j]).logpdf(X),
            rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(gm.pdf(X), np.exp(ref), rtol=1e-7)
    np.testing.assert_allclose(gm.responsibilities(X).sum(axis=1), 1.0, rtol=1e-12)


def test_one_dimensional_input_is_one_row():
    gm = random_mixture(np.random.default_rng(0), 2, 3)
    x = np.array([0.1, -0.2, 0.3])
    assert gm.log_pdf(x).shape == (1,)
    assert gm.log_pdf(x)[0] == pytest.approx(gm.log_pdf(x[None])[0])
    with pytest.raises(ValueError):
        gm.log_pdf(np.zeros((4, 2)))


def test_far_points_stay_finite_in_log_space():
    gm = random_mixture(np.random.default_rng(1), 3, 15)
    X = np.full((3, 15), 1e3)
    lp = gm.log_pdf(X)
    assert np.all(np.isfinite(lp)) and np.all(lp < -1e4)   # exp() would underflow to 0
    ref = reference_log_pdf(gm.weights, gm.means, gm.covariances, X)
    np.testing.assert_allclose(lp, ref, rtol=1e-8)


def test_many_rows_batched():
    rng = np.random.default_rng(2)
    gm = random_mixture(rng, 8, 15)
    X = rng.normal(size=(20000, 15))   # several BLAS row blocks
    np.testing.assert_allclose(gm.log_pdf(X)[::997],
                               reference_log_pdf(gm.weights, gm.means, gm.covariances, X[::997]), rtol=1e-8)


def test_shape_properties():
    gm = random_mixture(np.random.default_rng(3), 3, 15)
    assert (gm.n_components, gm.dim) == (3, 15)
    assert params_per_component(15) == 15 + 120
    assert gm.n_parameters == 2 + 3 * 135
    assert "n_components=3" in repr(gm)
    with pytest.raises(ValueError):
        gm.weights[0] = 0.5   # read-only: the cached factors can never go stale


# ------------------------------------------------------- value object: linear maps
def test_linear_map_matches_analytic():
    rng = np.random.default_rng(4)
    gm = random_mixture(rng, 3, 5)
    A = rng.standard_normal((3, 5))
    b = rng.standard_normal(3)
    out = gm.linear_map(A, b)
    covs = np.einsum("ij,kjl,ml->kim", A, gm.covariances, A)
    np.testing.assert_allclose(out.means, gm.means @ A.T + b, rtol=1e-12)
    np.testing.assert_allclose(out.covariances, covs, rtol=1e-10)
    Y = rng.normal(scale=3.0, size=(200, 3))
    np.testing.assert_allclose(out.log_pdf(Y), reference_log_pdf(gm.weights, gm.means @ A.T + b, covs, Y),
                               rtol=1e-8)


def test_marginal_equals_identity_rows_map():
    rng = np.random.default_rng(5)
    gm = random_mixture(rng, 4, 15)
    dims = [9, 2, 14]
    X = rng.normal(scale=3.0, size=(300, 3))
    np.testing.assert_allclose(gm.marginal(dims).log_pdf(X), gm.linear_map(np.eye(15)[dims]).log_pdf(X),
                               rtol=1e-10)
    ref = reference_log_pdf(gm.weights, gm.means[:, dims], gm.covariances[:, dims][:, :, dims], X)
    np.testing.assert_allclose(gm.marginal(dims).log_pdf(X), ref, rtol=1e-8)
    assert gm.marginal(dims) is gm.marginal(tuple(dims))        # cached per dims
    with pytest.raises(ValueError):
        gm.marginal([1, 1])
    with pytest.raises(ValueError):
        gm.marginal([15])


def test_marginal_agrees_with_numerical_integration():
    """p(x0, x1) = integral of p(x0, x1, x2) dx2 for a 3-D mixture, at a few points."""
    rng = np.random.default_rng(6)
    gm = random_mixture(rng, 3, 3, spread=1.5)
    marg = gm.marginal([0, 1])
    for x01 in gm.sample(4, rng)[:, :2]:
        def integrand(x2, x01=x01):
            return gm.pdf(np.array([x01[0], x01[1], x2]))[0]
        val, err = integrate.quad(integrand, -np.inf, np.inf, epsabs=1e-13, epsrel=1e-10)
        assert marg.pdf(x01)[0] == pytest.approx(val, rel=1e-7)


def test_linear_map_agrees_with_monte_carlo():
    """Interval probabilities of y = a . x + b: sample frequency vs quadrature of the mapped density."""
    rng = np.random.default_rng(7)
    gm = random_mixture(rng, 3, 4, spread=2.0)
    A = rng.standard_normal((1, 4))
    b = np.array([0.7])
    mapped = gm.linear_map(A, b)
    y = (gm.sample(200_000, rng) @ A.T + b)[:, 0]
    lo, hi = np.quantile(y, [0.02, 0.98])
    edges = np.linspace(lo, hi, 7)
    for a, c in zip(edges[:-1], edges[1:]):
        p, _ = integrate.quad(lambda t: mapped.pdf(np.array([t]))[0], a, c)
        freq = np.mean((y >= a) & (y < c))
        assert abs(freq - p) < 5 * np.sqrt(p * (1 - p) / y.size) + 1e-4
    # first two moments of the mapped mixture vs the samples
    mean = mapped.weights @ mapped.means[:, 0]
    var = mapped.weights @ (mapped.covariances[:, 0, 0] + mapped.means[:, 0] ** 2) - mean ** 2
    assert np.mean(y) == pytest.approx(mean, abs=5 * np.sqrt(var / y.size))
    assert np.var(y) == pytest.approx(var, rel=0.02)


def test_empty_map_is_density_of_nothing():
    gm = random_mixture(np.random.default_rng(8), 3, 15)
    for empty in (gm.linear_map(np.zeros((0, 15))), gm.marginal([])):
        assert empty.dim == 0 and empty.n_components == 3
        np.testing.assert_array_equal(empty.log_pdf(np.zeros((7, 0))), np.zeros(7))
        np.testing.assert_allclose(logsumexp(empty.component_log_pdf(np.zeros((2, 0))), axis=1), 0.0,
                                   atol=1e-12)
        assert empty.sample(5, 0).shape == (5, 0)


def test_linear_map_rejects_bad_shapes_and_regularises_rank_deficiency():
    gm = random_mixture(np.random.default_rng(9), 2, 3)
    with pytest.raises(ValueError):
        gm.linear_map(np.ones((2, 4)))
    with pytest.raises(ValueError):
        gm.linear_map(np.ones((2, 3)), b=np.ones(3))
    degenerate = gm.linear_map(np.array([[1.0, 0, 0], [2.0, 0, 0]]))   # rank 1: jitter, no crash
    assert np.all(np.isfinite(degenerate.log_pdf(np.zeros((3, 2)))))


def test_stable_cholesky_escalates_jitter():
    singular = np.ones((4, 4))
    cov, chol = stable_cholesky(singular, 0.0)
    np.testing.assert_allclose(chol @ chol.T, cov, rtol=1e-12, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    with pytest.raises(ValueError):
        stable_cholesky(np.full((2, 2), np.nan))


def test_sample_moments_and_determinism():
    rng = np.random.default_rng(10)
    gm = random_mixture(rng, 3, 3)
    X = gm.sample(100_000, 3)
    np.testing.assert_array_equal(X, gm.sample(100_000, np.random.default_rng(3)))
    mean = gm.weights @ gm.means
    np.testing.assert_allclose(X.mean(axis=0), mean, atol=0.05)


# ----------------------------------------------------------- value object: model file
def test_arrays_round_trip_through_npz_without_pickle():
    gm = random_mixture(np.random.default_rng(11), 3, 15)
    buf = io.BytesIO()
    np.savez(buf, **gm.to_arrays(prefix="t0/"))
    buf.seek(0)
    with np.load(buf, allow_pickle=False) as f:
        back = GaussianMixture.from_arrays(f, prefix="t0/")
    for name in ("weights", "means", "covariances"):
        np.testing.assert_array_equal(getattr(back, name), getattr(gm, name))
    X = np.random.default_rng(0).normal(size=(10, 15))
    np.testing.assert_array_equal(back.log_pdf(X), gm.log_pdf(X))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 5), d=st.integers(1, 6))
def test_round_trip_and_permuted_marginal_property(seed, k, d):
    rng = np.random.default_rng(seed)
    gm = random_mixture(rng, k, d)
    back = GaussianMixture.from_arrays(gm.to_arrays())
    X = rng.normal(size=(5, d))
    np.testing.assert_array_equal(back.log_pdf(X), gm.log_pdf(X))
    perm = rng.permutation(d)
    np.testing.assert_allclose(gm.marginal(perm).log_pdf(X[:, perm]), gm.log_pdf(X), rtol=1e-9)


def _corrupt(arrays, key, fn):
    out = {k: np.array(v) for k, v in arrays.items()}
    out[key] = fn(out[key])
    return out


def _set(idx, value):
    def fn(a):
        a[idx] = value
        return a
    return fn


def _not_pd(c):
    c[0] = np.diag(np.r_[-1.0, np.ones(c.shape[1] - 1)])
    return c


def _asym(c):
    c[1, 0, 2] += 0.1
    return c


@pytest.mark.parametrize("key, fn, match", [
    ("weights", lambda w: w[:2], "means must have shape"),
    ("weights", lambda w: w[None], "1-D"),
    ("means", lambda m: m[:, :4], "covariances must have shape"),
    ("covariances", lambda c: c[:, :4, :4], "covariances must have shape"),
    ("means", _set((0, 0), np.nan), "NaN"),
    ("covariances", _set((1, 1, 1), np.inf), "NaN"),
    ("weights", lambda w: w * 0.9, "sum to 1"),
    ("weights", lambda w: np.r_[1.2, -0.1, w[2] - 0.1], "positive"),
    ("covariances", _not_pd, "positive definite"),
    ("covariances", _asym, "symmetric"),
    ("weights", lambda w: w.astype(str), "numeric"),
])
def test_from_arrays_rejects_corrupt_arrays(key, fn, match):
    arrays = random_mixture(np.random.default_rng(12), 3, 5).to_arrays()
    with pytest.raises(ValueError, match=match):
        GaussianMixture.from_arrays(_corrupt(arrays, key, fn))


def test_from_arrays_missing_key():
    arrays = random_mixture(np.random.default_rng(13), 2, 2).to_arrays()
    del arrays["means"]
    with pytest.raises(ValueError, match="lack key"):
        GaussianMixture.from_arrays(arrays)


# --------------------------------------------------------------------- estimators
@pytest.mark.parametrize("kind", sorted(ESTIMATORS))
def test_fit_result_is_consistent(kind, small_data):
    res = ESTIMATORS[kind]().fit(small_data)
    assert isinstance(res, FitResult)
    gm = res.mixture
    assert gm.dim == small_data.shape[1]
    assert res.log_likelihood == pytest.approx(gm.log_pdf(small_data).sum(), rel=1e-12)
    assert res.message_length == pytest.approx(
        message_length(res.log_likelihood, gm.weights, len(small_data), gm.dim), rel=1e-12)
    assert res.n_iter >= 1 and res.converged
    assert res.history and res.history[-1][0] >= 1
    assert gm.weights.sum() == pytest.approx(1.0)
    assert all(np.all(np.linalg.eigvalsh(c) > 0) for c in gm.covariances)


@pytest.mark.parametrize("kind", sorted(ESTIMATORS))
def test_same_seed_same_result(kind, small_data):
    a = ESTIMATORS[kind](seed=3).fit(small_data).mixture
    b = ESTIMATORS[kind](seed=3).fit(small_data).mixture
    for name in ("weights", "means", "covariances"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


@pytest.mark.parametrize("kind", sorted(ESTIMATORS))
def test_degenerate_data_stays_finite(kind):
    """Duplicate rows and a constant dimension: reg_covar keeps every covariance PD."""
    rng = np.random.default_rng(14)
    X = rng.normal(size=(1500, 15))
    X[:, 4] = 0.25                    # constant feature (rank 14)
    X[700:] = X[0]                    # half the rows are one repeated point
    res = ESTIMATORS[kind]().fit(X)
    lp = res.mixture.log_pdf(X)
    assert np.all(np.isfinite(lp)) and np.isfinite(res.log_likelihood) and np.isfinite(res.message_length)
    assert all(np.all(np.linalg.eigvalsh(c) > 0) for c in res.mixture.covariances)


@pytest.mark.parametrize("kind", sorted(ESTIMATORS))
def test_input_validation(kind):
    est = ESTIMATORS[kind]()
    with pytest.raises(ValueError):
        est.fit(np.array([[0.0, np.nan]] * 10))
    with pytest.raises(ValueError):
        est.fit(np.zeros(10))
    with pytest.raises(ValueError):
        est.fit(np.zeros((10, 2)), sample_weight=-np.ones(10))


def test_single_gaussian_is_sample_mean_and_ml_covariance(single_gaussian_data):
    X = single_gaussian_data
    res = SingleGaussian(reg_covar=1e-6).fit(X)
    np.testing.assert_allclose(res.mixture.means[0], X.mean(axis=0), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(res.mixture.covariances[0], np.cov(X.T, bias=True) + 1e-6 * np.eye(15),
                               rtol=1e-10, atol=1e-13)
    assert res.n_components == 1


def test_single_gaussian_frequency_weights_equal_repeated_rows():
    rng = np.random.default_rng(15)
    X = rng.normal(size=(50, 3))
    counts = rng.integers(0, 4, size=50)
    a = SingleGaussian().fit(X, sample_weight=counts).mixture
    b = SingleGaussian().fit(np.repeat(X, counts, axis=0)).mixture
    np.testing.assert_allclose(a.means, b.means, rtol=1e-12)
    np.testing.assert_allclose(a.covariances, b.covariances, rtol=1e-10)


@pytest.mark.parametrize("kind", ["fixed", "mdl"])
def test_sample_weights_are_used(kind, small_data):
    w = np.ones(len(small_data))
    w[small_data[:, 0] > np.median(small_data[:, 0])] = 0.0
    res = ESTIMATORS[kind]().fit(small_data, sample_weight=w)
    assert res.n_samples == w.sum()
    assert np.all(np.isfinite(res.mixture.log_pdf(small_data)))


@pytest.mark.parametrize("reg_covar, slack", [(0.0, 1e-9), (1e-6, 1e-6)])
def test_fixed_k_log_likelihood_non_decreasing(three_cluster_data, reg_covar, slack):
    truth, X = three_cluster_data
    res = FixedKMixture(4, reg_covar=reg_covar, tol=0.0, max_iter=40, random_state=1).fit(X)
    trace = np.asarray(res.loglik_trace)
    assert len(trace) == 40
    assert np.all(np.diff(trace) >= -slack * np.abs(trace[1:]))


def test_fixed_k_recovers_separated_clusters(three_cluster_data):
    truth, X = three_cluster_data
    res = FixedKMixture(3, n_init=2, random_state=0).fit(X)
    order = [int(np.argmin(np.linalg.norm(res.mixture.means - m, axis=1))) for m in truth.means]
    assert sorted(order) == [0, 1, 2]
    np.testing.assert_allclose(res.mixture.weights[order], truth.weights, atol=0.05)
    with pytest.raises(ValueError):
        FixedKMixture(5).fit(X[:3])


def test_mdl_recovers_three_components(three_cluster_data):
    truth, X = three_cluster_data
    res = MDLMixture(k_min=1, k_max=8, random_state=0).fit(X)
    assert res.n_components == 3, res.history
    order = [int(np.argmin(np.linalg.norm(res.mixture.means - m, axis=1))) for m in truth.means]
    assert sorted(order) == [0, 1, 2]
    np.testing.assert_allclose(res.mixture.weights[order], truth.weights, atol=0.05)
    for j, m in zip(order, truth.means):
        assert np.linalg.norm(res.mixture.means[j] - m) < 0.5
    # MDL keeps the stage with the shortest message length; stages go down to k_min
    ks = [k for k, _ in res.history]
    assert ks == sorted(ks, reverse=True) and ks[-1] == 1
    assert res.message_length == pytest.approx(min(ml for _, ml in res.history), rel=1e-9)
    # and the selected model beats the fixed single-Gaussian and 3-component fits on MDL
    assert res.message_length <= SingleGaussian().fit(X).message_length


def test_mdl_picks_one_component_for_gaussian_data(single_gaussian_data):
    res = MDLMixture(1, 8, random_state=0).fit(single_gaussian_data)
    assert res.n_components == 1, res.history


def test_mdl_falls_back_when_data_are_too_few():
    rng = np.random.default_rng(16)
    tiny = MDLMixture(random_state=0).fit(rng.normal(size=(50, 15)))     # 50 <= N/2 = 67.5
    assert tiny.n_components == 1 and any("single Gaussian" in n for n in tiny.notes)
    few = MDLMixture(random_state=0).fit(rng.normal(size=(400, 15)))     # supports ~3 components
    assert few.history[0][0] <= 2 and any("k_max lowered" in n for n in few.notes)
    assert np.all(np.isfinite(few.mixture.log_pdf(rng.normal(size=(5, 15)))))


def test_mdl_respects_k_min(single_gaussian_data):
    res = MDLMixture(k_min=2, k_max=3, random_state=0).fit(single_gaussian_data)
    assert res.n_components >= 2
    assert all(k >= 2 for k, _ in res.history)


def test_message_length_formula():
    n, d = 1000.0, 15
    npar = params_per_component(d)
    w = np.array([0.25, 0.75])
    expected = (npar / 2 * np.log(n * w / 12).sum() + 2 / 2 * np.log(n / 12) + 2 * (npar + 1) / 2 - (-123.0))
    assert message_length(-123.0, w, n, d) == pytest.approx(expected)


def test_make_estimator():
    est = make_estimator("fixed", k_fixed=5, k_min=2, k_max=4, reg_covar=1e-5, max_iter=7, tol=1e-3,
                         random_state=4)
    assert isinstance(est, FixedKMixture) and est.k == 5
    assert (est.reg_covar, est.max_iter, est.tol, est.random_state) == (1e-5, 7, 1e-3, 4)
    mdl = make_estimator("mdl", k_fixed=3, k_min=2, k_max=6, random_state=None)
    assert isinstance(mdl, MDLMixture) and (mdl.k_min, mdl.k_max) == (2, 6)
    assert isinstance(make_estimator("single", k_max=8), SingleGaussian)
    with pytest.raises(ValueError):
        make_estimator("kmeans")
    with pytest.raises(TypeError):
        make_estimator("mdl", n_components=3)
    with pytest.raises(ValueError):
        make_estimator("mdl", k_min=5, k_max=2)


def test_mdl_least_loss_removal_keeps_a_small_real_cluster():
    """F&J drop the least probable component between stages; with a small genuine cluster and
    a split big one that deletes the real cluster. ``removal='least_loss'`` keeps it."""
    rng = np.random.default_rng(21)
    d = 15
    means = np.linalg.qr(rng.standard_normal((d, 3)))[0].T * 20.0
    covs = np.stack([np.eye(d) * s for s in (1.0, 1.5, 0.7)])
    truth = GaussianMixture(np.array([0.47, 0.45, 0.08]), means, covs)
    X = truth.sample(3000, rng)
    for seed in (0, 1):
        res = MDLMixture(random_state=seed, removal="least_loss").fit(X)
        assert res.n_components == 3, res.history
        assert np.sort(res.mixture.weights)[0] == pytest.approx(0.08, abs=0.03)
    assert isinstance(make_estimator("mdl", removal="least_loss"), MDLMixture)
    with pytest.raises(ValueError):
        MDLMixture(removal="random")
