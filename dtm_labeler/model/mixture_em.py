"""Estimators for the triangle mixtures of Hu & Wong sec. III (eq. 8-11).

Three estimators share one EM skeleton (template methods, as in scikit-learn's
``BaseMixture``): :meth:`MixtureEstimator._initialize`, :meth:`~MixtureEstimator._e_step`,
:meth:`~MixtureEstimator._m_step`, :meth:`~MixtureEstimator._objective` and the shared
loop :meth:`~MixtureEstimator._run_em` with its convergence test::

    SingleGaussian      K = 1, closed form (the paper's "joint Gaussian", JG)
    FixedKMixture(k)    standard EM, k-means++ initialisation (JMG; the paper uses k = 3)
    MDLMixture(1, 8)    Figueiredo & Jain (2002) component-annihilating EM (JMGW)

The paper's algorithm (eq. 8-11) is a garbled transcription of Figueiredo & Jain,
"Unsupervised learning of finite mixture models", IEEE TPAMI 24(3), 2002; this module
implements F&J's CEM^2 with ``N = d + d(d+1)/2`` parameters per component:

* eq. 8 (E-step): responsibilities ``alpha_m(x_i) = w_m N_m(x_i) / sum_j w_j N_j(x_i)``,
  recomputed before each component's update (component-wise EM, CEM^2);
* eq. 9 (weight rule): ``w_m = max(0, sum_i alpha_m(x_i) - N/2) /
  sum_j max(0, sum_i alpha_j(x_i) - N/2)``, then the weights are renormalised; a component
  whose weight becomes 0 is annihilated;
* eq. 10 (M-step): mean and covariance of a surviving component maximise the expected
  complete log-likelihood ``Q`` (weighted sample mean and ML covariance, plus ``reg_covar``);
* eq. 11 (MDL): the paper prints ``-log P(x | theta) + (k/2) log N``; we read it as F&J's
  message length, the mathematically sound form (a penalty per *parameter*, ``N`` per
  component, and ``n`` samples, not the constant ``log N``)::

      L(theta) = (N/2) sum_m log(n w_m / 12) + (k/2) log(n / 12) + k (N + 1)/2 - log p(X | theta)

  Sweeps run until the relative change of ``L`` is below ``tol``; ``L`` is recorded, the
  least probable component is removed, and the loop continues while ``k > k_min``. The
  parameters with the shortest message length are returned.

Everything runs in log space (log-sum-exp), densities use Cholesky factors, covariances
get ``reg_covar`` on the diagonal (more if a factorisation still fails), loops run over
components only (never samples), iteration counts are bounded by ``max_iter`` and all
randomness comes from ``numpy.random.default_rng(random_state)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .mixture import (GaussianMixture, inv_lower, log_gaussian_all, log_gaussian_one,
                      params_per_component, rows_matmul, stable_cholesky, weighted_gram)

__all__ = ["FitResult", "MixtureEstimator", "SingleGaussian", "FixedKMixture", "MDLMixture",
           "make_estimator", "message_length"]

_EPS = 10.0 * np.finfo(np.float64).eps


def message_length(log_likelihood: float, weights: np.ndarray, n: float, dim: int) -> float:
    """F&J message length (our reading of eq. 11) of a mixture with ``weights`` on ``n`` samples.

    ``L = (N/2) sum_m log(n w_m / 12) + (k/2) log(n/12) + k (N+1)/2 - log p(X | theta)``,
    ``N = d + d(d+1)/2``. Natural logs, so ``L`` is in nats.
    """
    w = np.asarray(weights, dtype=np.float64)
    k = w.shape[0]
    npar = params_per_component(dim)
    return float(0.5 * npar * np.sum(np.log(n * w / 12.0)) + 0.5 * k * math.log(n / 12.0)
                 + 0.5 * k * (npar + 1) - log_likelihood)


@dataclass
class FitResult:
    """What an estimator returns.

    ``log_likelihood`` is the total (sample-weighted) natural-log likelihood of the
    training data under ``mixture``; ``message_length`` is :func:`message_length` for it
    (the MDL criterion; computed for every estimator so they can be compared).
    ``n_iter`` counts EM iterations (for MDL: CEM^2 sweeps over all stages),
    ``converged`` refers to the run (MDL: the stage that produced ``mixture``).
    ``history`` is MDL's ``[(k, message_length), ...]`` per stage (one entry otherwise);
    ``loglik_trace`` the log-likelihood after every iteration (non-decreasing for plain
    EM up to the ``reg_covar`` perturbation); ``notes`` explains any fallback taken.
    """

    mixture: GaussianMixture
    log_likelihood: float
    message_length: float
    n_iter: int
    converged: bool
    history: list = field(default_factory=list)
    loglik_trace: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    n_samples: float = 0.0

    @property
    def n_components(self) -> int:
        return self.mixture.n_components


class _State:
    """Mutable EM parameters plus the cache ``log_dens[k, i] = log N_k(x_i)``, stored ``(K, n)``
    so per-component rows are contiguous and reductions over ``k`` are elementwise."""

    __slots__ = ("weights", "means", "covs", "prec", "log_dens")

    def __init__(self, weights, means, covs, prec, log_dens):
        self.weights, self.means, self.covs, self.prec, self.log_dens = weights, means, covs, prec, log_dens

    @property
    def k(self) -> int:
        return self.weights.shape[0]

    def copy(self) -> "_State":
        return _State(self.weights.copy(), self.means.copy(), self.covs.copy(), self.prec.copy(),
                      self.log_dens.copy())

    def keep(self, idx) -> None:
        """Restrict to components ``idx`` and renormalise the weights."""
        self.weights = self.weights[idx]
        self.weights = self.weights / self.weights.sum()
        self.means, self.covs, self.prec = self.means[idx], self.covs[idx], self.prec[idx]
        self.log_dens = self.log_dens[idx]


class MixtureEstimator:
    """Shared skeleton (``fit`` -> ``_fit`` -> ``_initialize`` / ``_run_em``); see module doc."""

    kind = "base"

    def __init__(self, *, reg_covar: float = 1e-6, max_iter: int = 200, tol: float = 1e-5,
                 random_state: int | None = None) -> None:
        if not (np.isfinite(reg_covar) and reg_covar >= 0):
            raise ValueError(f"reg_covar must be >= 0, got {reg_covar}")
        if int(max_iter) < 1:
            raise ValueError(f"max_iter must be >= 1, got {max_iter}")
        if not (np.isfinite(tol) and tol >= 0):
            raise ValueError(f"tol must be >= 0, got {tol}")
        self.reg_covar = float(reg_covar)
        self.max_iter = int(max_iter)
        self.tol = float(tol)
        self.random_state = random_state
        self._notes: list[str] = []

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if not k.startswith("_"))
        return f"{type(self).__name__}({args})"

    # ------------------------------------------------------------- public
    def fit(self, X, sample_weight=None) -> FitResult:
        """Fit to ``X`` ``(n, d)``; ``sample_weight`` ``(n,)`` are frequency weights (default 1)."""
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[0] < 1 or X.shape[1] < 1:
            raise ValueError(f"X must be a non-empty (n, d) array, got shape {X.shape}")
        if not np.all(np.isfinite(X)):
            raise ValueError("X contains NaN or inf")
        if sample_weight is None:
            w = np.ones(X.shape[0])
        else:
            w = np.asarray(sample_weight, dtype=np.float64).reshape(-1)
            if w.shape[0] != X.shape[0]:
                raise ValueError(f"sample_weight has {w.shape[0]} entries for {X.shape[0]} rows")
            if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
                raise ValueError("sample_weight must be finite, non-negative and not all zero")
        self._notes = []
        rng = np.random.default_rng(self.random_state)
        return self._fit(X, w, rng)

    def _fit(self, X, w, rng) -> FitResult:  # pragma: no cover - abstract
        raise NotImplementedError

    # ------------------------------------------------------ template methods
    def _initialize(self, X, w, rng, k: int) -> _State:
        """Initial parameters for ``k`` components.

        k-means++ seeding (weighted, from ``rng``) and a few Lloyd iterations on
        standardised data, then one M-step on the hard assignments; clusters with ``<= d``
        points get the global diagonal covariance. (F&J's narrow ``sigma^2 I / 10`` start
        lets the first CEM^2 update swallow every other component in 15-D.)
        """
        n, d = X.shape
        Z = _standardise(X, w)
        seeds = _kmeanspp(Z, w, rng, k)
        labels = _lloyd(Z, w, Z[seeds].copy())
        gvar = (w @ (X - (w @ X) / w.sum()) ** 2) / w.sum()
        gvar = np.where(gvar > 0, gvar, 1.0)
        weights = np.empty(k)
        means = np.empty((k, d))
        covs = np.empty((k, d, d))
        for c in range(k):
            sel = labels == c
            ws = w[sel].sum()
            weights[c] = max(ws, _EPS)
            means[c] = (w[sel] @ X[sel]) / ws if ws > 0 else X[seeds[c]]
            if np.count_nonzero(w[sel]) > d:
                diff = X[sel] - means[c]
                covs[c] = weighted_gram(diff, w[sel]) / ws + self.reg_covar * np.eye(d)
            else:
                covs[c] = np.diag(gvar) + self.reg_covar * np.eye(d)
        return self._state_from(X, weights / weights.sum(), means, covs)

    def _e_step(self, state: _State, w) -> tuple[float, np.ndarray]:
        """Eq. 8: ``(total log-likelihood, responsibilities (K, n))`` of ``state``."""
        log_norm, resp = _responsibilities(state.log_dens, state.weights)
        return float(w @ log_norm), resp

    def _m_step(self, X, w, state: _State, resp: np.ndarray) -> None:
        """Eq. 10 for all components at once (standard EM); updates ``state`` in place."""
        rw = resp * w
        nk = rw.sum(axis=1) + _EPS
        state.weights = nk / nk.sum()
        for m in range(state.k):
            self._update_gaussian(X, rw[m], state, m, recompute=False)
        state.log_dens = self._log_densities(X, state.means, state.covs, state.prec)

    def _objective(self, ll: float, state: _State, n_eff: float, dim: int) -> float:
        """Quantity minimised by the loop: ``-log-likelihood`` (ML)."""
        return -ll

    def _converged(self, old: float, new: float, n_eff: float) -> bool:
        """Relative change ``|old - new| <= tol * max(|new|, n)`` (so never stricter than
        ``tol`` nats per sample when the objective is near 0)."""
        return abs(old - new) <= self.tol * max(abs(new), n_eff)

    def _run_em(self, X, w, state: _State, n_eff: float, trace: list):
        """Shared loop: M-step, E-step, objective, convergence test; bounded by ``max_iter``.

        Returns ``(state, log_likelihood, objective, n_iter, converged)``; the returned
        log-likelihood and objective always belong to the returned parameters.
        """
        d = X.shape[1]
        ll, resp = self._e_step(state, w)
        obj = self._objective(ll, state, n_eff, d)
        converged = False
        it = 0
        for it in range(1, self.max_iter + 1):
            k_before = state.k
            self._m_step(X, w, state, resp)
            ll, resp = self._e_step(state, w)
            trace.append(ll)
            new_obj = self._objective(ll, state, n_eff, d)
            done = state.k == k_before and self._converged(obj, new_obj, n_eff)
            obj = new_obj
            if done:
                converged = True
                break
        return state, ll, obj, it, converged

    # --------------------------------------------------------------- helpers
    def _update_gaussian(self, X, rw, state: _State, m: int, recompute: bool = True) -> None:
        """Eq. 10 for component ``m`` with responsibility-times-sample weights ``rw`` (n,)."""
        nk = rw.sum() + _EPS
        mu = (rw @ X) / nk
        cov = weighted_gram(X - mu, rw) / nk
        cov, chol = stable_cholesky(cov, self.reg_covar)
        state.means[m] = mu
        state.covs[m] = cov
        state.prec[m] = inv_lower(chol)
        if recompute:
            state.log_dens[m] = log_gaussian_one(X, mu, state.prec[m])

    def _state_from(self, X, weights, means, covs) -> _State:
        k, d = means.shape
        covs = np.array(covs, dtype=np.float64)
        prec = np.empty_like(covs)
        for m in range(k):
            covs[m], chol = stable_cholesky(covs[m], 0.0)
            prec[m] = inv_lower(chol)
        means = np.array(means, float)
        return _State(np.asarray(weights, float).copy(), means, covs, prec,
                      self._log_densities(X, means, covs, prec))

    def _log_densities(self, X, means, covs, prec) -> np.ndarray:
        """``(K, n)`` ``log N_k(x_i)`` of every component (eq. 7); a hook for partly seen samples."""
        return np.ascontiguousarray(log_gaussian_all(X, means, prec).T)

    def _log_likelihood(self, X, w, gm: GaussianMixture) -> float:
        """Total sample-weighted log-likelihood of the data under ``gm`` (same hook)."""
        return float(w @ gm.log_pdf(X))

    def _result(self, X, w, state: _State, n_iter, converged, history, trace) -> FitResult:
        gm = GaussianMixture(state.weights, state.means, state.covs)
        n_eff = float(w.sum())
        ll = self._log_likelihood(X, w, gm)
        ml = message_length(ll, gm.weights, n_eff, gm.dim)
        if not history:
            history = [(gm.n_components, ml)]
        return FitResult(gm, ll, ml, int(n_iter), bool(converged), list(history), list(trace),
                         list(self._notes), n_eff)

    def _note(self, msg: str) -> None:
        if msg not in self._notes:
            self._notes.append(msg)


def _responsibilities(log_dens: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 8 from the ``(K, n)`` log densities: ``(log p(x_i) (n,), alpha (K, n))``, one exp."""
    with np.errstate(divide="ignore"):
        joint = log_dens + np.log(weights)[:, None]
    top = joint.max(axis=0)
    top = np.where(np.isfinite(top), top, 0.0)
    joint -= top
    np.exp(joint, out=joint)
    total = joint.sum(axis=0)
    joint /= total
    with np.errstate(divide="ignore"):
        return np.log(total) + top, joint


class _ScaledDensities:
    """``D[k, i] = exp(log_dens[k, i] - top_i)`` of a CEM^2 sweep (see ``MDLMixture._m_step``)."""

    #: a changed row may exceed the sweep's reference by this much (nats) before D is rebuilt
    HEADROOM = 300.0
    #: ... and a sample's mixture density may fall this far below it
    FLOOR = 1e-250

    def __init__(self, log_dens: np.ndarray):
        self._rebuild(log_dens)

    def _rebuild(self, log_dens: np.ndarray) -> None:
        top = log_dens.max(axis=0)
        self.top = np.where(np.isfinite(top), top, 0.0)
        self.D = np.exp(log_dens - self.top)

    def supports(self, weights: np.ndarray, w: np.ndarray):
        """``(s, resp_of)``: expected samples per component ``s_k = sum_i w_i alpha_k(x_i)``
        and a function giving one component's responsibilities (n,)."""
        mix = weights @ self.D
        v = w / mix
        s = weights * (self.D @ v)
        return s, lambda k: weights[k] * self.D[k] / mix

    def update(self, m: int, log_dens: np.ndarray) -> None:
        """Row ``m`` of ``log_dens`` changed."""
        row = log_dens[m] - self.top
        if row.max(initial=-np.inf) > self.HEADROOM:
            self._rebuild(log_dens)
            return
        self.D[m] = np.exp(row)
        self._check(log_dens)

    def drop(self, m: int, log_dens: np.ndarray) -> None:
        """Row ``m`` removed (``log_dens``: what is left)."""
        self.D = np.delete(self.D, m, axis=0)
        self._check(log_dens)

    def _check(self, log_dens: np.ndarray) -> None:
        if self.D.max(axis=0).min(initial=np.inf) < self.FLOOR:
            self._rebuild(log_dens)


def _standardise(X, w):
    mean = (w @ X) / w.sum()
    std = np.sqrt((w @ (X - mean) ** 2) / w.sum())
    std = np.where(std > 0, std, 1.0)
    return (X - mean) / std


def _kmeanspp(Z, w, rng, k: int) -> np.ndarray:
    """k-means++ seeding (weighted, seeded): indices of ``k`` rows of ``Z``."""
    n = Z.shape[0]
    p = w / w.sum()
    idx = [int(rng.choice(n, p=p))]
    d2 = np.sum((Z - Z[idx[0]]) ** 2, axis=1)
    for _ in range(1, k):
        q = w * d2
        s = q.sum()
        idx.append(int(rng.choice(n, p=q / s)) if s > 0 else int(rng.choice(n, p=p)))
        d2 = np.minimum(d2, np.sum((Z - Z[idx[-1]]) ** 2, axis=1))
    return np.array(idx)


def _lloyd(Z, w, centers, n_iter: int = 10) -> np.ndarray:
    """A few vectorised weighted Lloyd iterations; returns hard labels (n,)."""
    zz = np.einsum("ij,ij->i", Z, Z)
    labels = None
    for _ in range(n_iter):
        dist = zz[:, None] - 2.0 * rows_matmul(Z, centers.T) + np.einsum("ij,ij->i", centers, centers)
        new = np.argmin(dist, axis=1)
        if labels is not None and np.array_equal(new, labels):
            break
        labels = new
        for c in range(centers.shape[0]):
            sel = labels == c
            ws = w[sel].sum()
            if ws > 0:
                centers[c] = (w[sel] @ Z[sel]) / ws
    return labels


class SingleGaussian(MixtureEstimator):
    """``K = 1``: closed-form ML mean and covariance (divide by ``n``) plus ``reg_covar``."""

    kind = "single"

    def _fit(self, X, w, rng) -> FitResult:
        d = X.shape[1]
        state = _State(np.ones(1), np.zeros((1, d)), np.zeros((1, d, d)), np.zeros((1, d, d)),
                       np.zeros((1, X.shape[0])))
        self._m_step(X, w, state, np.ones((1, X.shape[0])))
        ll, _ = self._e_step(state, w)
        return self._result(X, w, state, 1, True, [], [ll])


class FixedKMixture(MixtureEstimator):
    """Standard EM with ``k`` components (eq. 8 + eq. 10, weights ``sum_i alpha_m / n``).

    Initialisation: k-means++ seeding and a few Lloyd iterations on standardised data,
    hard assignments, one M-step (clusters with ``<= d`` points get the global diagonal
    covariance). ``n_init`` restarts keep the best log-likelihood.
    """

    kind = "fixed"

    def __init__(self, k: int = 3, *, n_init: int = 1, reg_covar: float = 1e-6, max_iter: int = 200,
                 tol: float = 1e-5, random_state: int | None = None) -> None:
        super().__init__(reg_covar=reg_covar, max_iter=max_iter, tol=tol, random_state=random_state)
        if int(k) < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        if int(n_init) < 1:
            raise ValueError(f"n_init must be >= 1, got {n_init}")
        self.k = int(k)
        self.n_init = int(n_init)

    def _fit(self, X, w, rng) -> FitResult:
        if X.shape[0] < self.k:
            raise ValueError(f"need at least k={self.k} samples, got {X.shape[0]}")
        n_eff = float(w.sum())
        best = None
        for _ in range(self.n_init):
            trace: list[float] = []
            state = self._initialize(X, w, rng, self.k)
            state, ll, obj, it, conv = self._run_em(X, w, state, n_eff, trace)
            if best is None or ll > best[1]:
                best = (state, ll, it, conv, trace)
            if not conv:
                self._note(f"EM did not converge within max_iter={self.max_iter}")
        state, _, it, conv, trace = best
        return self._result(X, w, state, it, conv, [], trace)


class MDLMixture(MixtureEstimator):
    """Figueiredo & Jain (2002) component-annihilating CEM^2 with MDL selection (eq. 8-11).

    Starts from ``k_max`` components (the shared k-means++/Lloyd initialisation of
    :meth:`MixtureEstimator._initialize`), sweeps components one at a time
    (eq. 8 E-step, eq. 9 weight rule with annihilation, eq. 10 M-step) until the relative
    change of the message length is ``< tol`` (at most ``max_iter`` sweeps per stage),
    records ``(k, L)``, removes the least probable component and repeats while
    ``k > k_min``; returns the stage with the shortest message length (our reading of
    eq. 11, see module doc).

    Guards (each explained in ``FitResult.notes``): ``k_max`` is capped at ``n / N`` so
    the initial components can hold the ``N/2`` samples eq. 9 charges each of them; if
    even one component cannot (``n <= N/2``) the result is the :class:`SingleGaussian`
    fit; if a sweep would annihilate every component, the best-supported one is kept;
    annihilation never takes ``k`` below ``k_min`` (that component keeps its plain EM
    weight instead).

    ``removal`` chooses the component dropped between stages: ``"least_probable"`` (F&J,
    the default) or ``"least_loss"``, the one whose removal (weights renormalised, no
    refit) gives the shortest message length. F&J's rule deletes a genuine small cluster
    when a big one is still split in two, and the next stage then settles in a poor local
    optimum (MDL still keeps the best stage, so the result is merely over-split);
    ``"least_loss"`` avoids that at the cost of ``k`` extra log-sum-exps per stage.
    """

    kind = "mdl"

    def __init__(self, k_min: int = 1, k_max: int = 8, *, removal: str = "least_probable",
                 reg_covar: float = 1e-6, max_iter: int = 300, tol: float = 1e-5,
                 random_state: int | None = None) -> None:
        super().__init__(reg_covar=reg_covar, max_iter=max_iter, tol=tol, random_state=random_state)
        if not 1 <= int(k_min) <= int(k_max):
            raise ValueError(f"need 1 <= k_min <= k_max, got k_min={k_min}, k_max={k_max}")
        if removal not in ("least_probable", "least_loss"):
            raise ValueError(f"removal must be 'least_probable' or 'least_loss', got {removal!r}")
        self.k_min = int(k_min)
        self.k_max = int(k_max)
        self.removal = removal
        self._k_floor = self.k_min

    def _objective(self, ll: float, state: _State, n_eff: float, dim: int) -> float:
        """Eq. 11 read as F&J's message length (see :func:`message_length`)."""
        return message_length(ll, state.weights, n_eff, dim)

    def _single_gaussian(self) -> MixtureEstimator:
        """The estimator of the one-component fallback (same data handling as this one)."""
        return SingleGaussian(reg_covar=self.reg_covar, random_state=self.random_state)

    def _component_to_remove(self, state: _State, w, n_eff: float, dim: int) -> int:
        """Index of the component dropped between stages (see ``removal``)."""
        if self.removal == "least_probable":
            return int(np.argmin(state.weights))
        best, best_len = 0, np.inf
        for j in range(state.k):
            keep = [i for i in range(state.k) if i != j]
            rest = state.weights[keep] / state.weights[keep].sum()
            log_norm, _ = _responsibilities(state.log_dens[keep], rest)
            length = message_length(float(w @ log_norm), rest, n_eff, dim)
            if length < best_len:
                best, best_len = j, length
        return best

    def _m_step(self, X, w, state: _State, resp: np.ndarray) -> None:
        """One CEM^2 sweep: per component, eq. 8 E-step, eq. 9 weight (annihilate at 0), eq. 10.

        The E-step before each component's update is incremental: with ``D[k, i] =
        exp(log N_k(x_i) - top_i)`` (``top_i`` fixed for the sweep) the responsibilities are
        ``alpha_k D[k, i] / sum_j alpha_j D[j, i]``, and an update of component ``m`` changes
        row ``m`` of ``D`` only -- n exponentials per step instead of K n (the same eq. 8;
        ``D`` is rebuilt when a changed row leaves the range where it is exact). The sweep
        starts from ``state.log_dens``; the E-step's ``resp`` is not needed."""
        half_n = 0.5 * params_per_component(X.shape[1])
        m = 0
        dens = _ScaledDensities(state.log_dens)
        while m < state.k:
            s, resp_of = dens.supports(state.weights, w)
            support = np.maximum(0.0, s - half_n)
            total = support.sum()
            if total <= 0.0:
                j = int(np.argmax(s))
                self._note("every component fell below N/2 expected samples; kept the best-supported one")
                rj = resp_of(j)
                state.keep([j])
                self._update_gaussian(X, rj * w, state, 0)
                return
            wm = support[m] / total
            if wm == 0.0 and state.k <= self._k_floor:
                self._note(f"annihilation stopped at k_min={self._k_floor}; "
                           "component kept with its EM weight")
                wm = s[m] / s.sum()
            rm = resp_of(m)
            weights = state.weights.copy()
            weights[m] = wm
            state.weights = weights / weights.sum()
            if wm == 0.0:
                state.keep([i for i in range(state.k) if i != m])
                dens.drop(m, state.log_dens)
                continue
            self._update_gaussian(X, rm * w, state, m)
            dens.update(m, state.log_dens)
            m += 1

    def _fit(self, X, w, rng) -> FitResult:
        n, d = X.shape
        npar = params_per_component(d)
        n_eff = float(w.sum())
        if n_eff <= 0.5 * npar:
            self._note(f"n={n_eff:g} samples cannot support one component with N={npar} parameters "
                       f"(needs > N/2); fell back to a single Gaussian")
            res = self._single_gaussian()._fit(X, w, rng)
            res.notes = list(self._notes)
            return res
        k_cap = max(1, int(n_eff // npar))
        k_max = min(self.k_max, k_cap, n)
        k_min = min(self.k_min, k_max)
        if k_max < self.k_max:
            self._note(f"k_max lowered from {self.k_max} to {k_max}: n={n_eff:g} samples support "
                       f"about n/N={n_eff / npar:.1f} components of N={npar} parameters")
        if k_min < self.k_min:
            self._note(f"k_min lowered from {self.k_min} to {k_min}")
        self._k_floor = k_min
        state = self._initialize(X, w, rng, k_max)
        history: list[tuple[int, float]] = []
        trace: list[float] = []
        best = None
        total_iter = 0
        while True:
            state, ll, obj, it, conv = self._run_em(X, w, state, n_eff, trace)
            total_iter += it
            history.append((state.k, float(obj)))
            if best is None or obj < best[1]:
                best = (state.copy(), obj, conv)
            if not conv:
                self._note(f"a stage (k={state.k}) hit max_iter={self.max_iter} sweeps")
            if state.k <= k_min:
                break
            drop = self._component_to_remove(state, w, n_eff, d)
            state.keep([i for i in range(state.k) if i != drop])
        best_state, _, conv = best
        return self._result(X, w, best_state, total_iter, conv, history, trace)


def make_estimator(kind: str, classes: dict | None = None, **kw) -> MixtureEstimator:
    """Build an estimator by name: ``"single"``, ``"fixed"`` or ``"mdl"``.

    Keywords: ``k_fixed`` and ``n_init`` (fixed), ``k_min``/``k_max``/``removal`` (mdl), and
    ``reg_covar``/``max_iter``/``tol``/``random_state`` (all). Keys meant for another kind
    are ignored (so one config dict can drive all three); ``None`` means the default;
    unknown keys raise ``TypeError``. ``classes`` maps the kinds to other implementations
    with the same constructors (e.g. :mod:`.mixture_missing`'s).
    """
    known = {"k_fixed", "k_min", "k_max", "n_init", "removal", "reg_covar", "max_iter", "tol",
             "random_state"}
    unknown = set(kw) - known
    if unknown:
        raise TypeError(f"unknown estimator option(s): {sorted(unknown)}")
    classes = {"single": SingleGaussian, "fixed": FixedKMixture, "mdl": MDLMixture} | (classes or {})
    kw = {k: v for k, v in kw.items() if v is not None}
    common = {k: kw[k] for k in ("reg_covar", "max_iter", "tol", "random_state") if k in kw}
    kind = str(kind).lower()
    if kind == "single":
        return classes["single"](**common)
    if kind == "fixed":
        extra = {"n_init": kw["n_init"]} if "n_init" in kw else {}
        return classes["fixed"](kw.get("k_fixed", 3), **extra, **common)
    if kind == "mdl":
        extra = {"removal": kw["removal"]} if "removal" in kw else {}
        return classes["mdl"](kw.get("k_min", 1), kw.get("k_max", 8), **extra, **common)
    raise ValueError(f"unknown estimator kind {kind!r}; expected 'single', 'fixed' or 'mdl'")
