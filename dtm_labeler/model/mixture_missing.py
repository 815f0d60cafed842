"""Triangle mixtures from partly seen frames: EM with missing data (Hu & Wong eq. 8-11 on gappy captures).

A real capture seldom shows all three markers of a triangle with velocities; a frame that
shows some of them still says something about the triangle. What a frame shows of a
triangle is ``y = M_p X`` for its observation pattern ``p`` (:mod:`.features`: the same
linear maps that marginalise missing markers at labeling time, eq. 30-31). Under a Gaussian
component ``N(mu, S)`` of ``X``:

* the density of what is seen is ``N(y; M mu, M S M^T)`` -- the E-step responsibilities
  (eq. 8) and the likelihood use it;
* the unseen rest enters the M-step (eq. 10) through its conditional moments
  ``E[X | y] = mu + K (y - M mu)`` and ``Cov[X | y] = S - K M S``, ``K = S M^T (M S M^T)^-1``
  (the expected sufficient statistics of EM for Gaussians with missing values, Ghahramani
  & Jordan 1994), i.e. ``mu' = sum r E[X|y] / sum r`` and
  ``S' = sum r (E[X|y] E[X|y]^T + Cov[X|y]) / sum r - mu' mu'^T``.

:class:`PartialSamples` holds the samples with their patterns (batched over patterns, never
a loop over samples); the estimators are the three of :mod:`.mixture_em` with their density
and update hooks replaced (:func:`make_partial_estimator`), so the MDL rule, the
component annihilation and the initialisation (k-means++ on the conditional means under one
Gaussian) are the same code. Fully seen samples are the pattern with ``M = I``.
"""
from __future__ import annotations

import numpy as np

from .features import FEATURE_DIM, FULL, MISSING, STATE_DIM, feature_map_for, observed_map, pattern_codes, \
    pattern_id, triangle_features
from .mixture import LOG_2PI, GaussianMixture, inv_lower, logsumexp_rows, stable_cholesky
from .mixture_em import FitResult, FixedKMixture, MDLMixture, MixtureEstimator, SingleGaussian, make_estimator

__all__ = ["PartialSamples", "make_partial_estimator"]

FULL_PATTERN = 26


class PartialSamples:
    """Partly seen eq. 12 features of one triangle (module doc).

    Samples are stored sorted by observation pattern, padded so that every pattern has the
    same shapes: ``Y`` (n, 15) what each sample shows (zeros after its pattern's ``dims[g]``
    numbers), ``M`` (G, 15, 15) each pattern's map with zero rows below its ``dims[g]`` rows,
    pattern ``g`` holding samples ``bounds[g]:bounds[g + 1]``. A padded row adds an identity
    block to ``M S M^T`` and a zero residual, so one batched Cholesky per component update
    serves every pattern, and each pattern costs two small matmuls (no loop over samples)."""

    def __init__(self, Y: np.ndarray, bounds: np.ndarray, M: np.ndarray, dims: np.ndarray):
        self.Y, self.bounds, self.M, self.dims = Y, bounds, M, dims
        self.pad = np.zeros_like(M)
        for g, m in enumerate(dims):
            self.pad[g, np.arange(m, FEATURE_DIM), np.arange(m, FEATURE_DIM)] = 1.0

    @property
    def n(self) -> int:
        return self.Y.shape[0]

    @property
    def group(self) -> np.ndarray:
        """(n,) pattern of every sample."""
        return np.repeat(np.arange(len(self.dims)), np.diff(self.bounds))

    @classmethod
    def from_states(cls, states: np.ndarray, triangle, min_dim: int = 1) -> "PartialSamples":
        """From (F, N, 6) point states (NaN = unseen); frames showing fewer than ``min_dim``
        numbers of the triangle are left out."""
        tri = list(triangle)
        s = states[:, tri, :]
        has_p = np.isfinite(s[..., :3]).all(-1)
        has_v = np.isfinite(s[..., 3:]).all(-1)
        pids = pattern_id(np.where(has_p, np.where(has_v, FULL, 1), MISSING))
        flat = np.nan_to_num(s.reshape(len(s), 3 * STATE_DIM), nan=0.0)
        maps, dims, parts = [], [], []
        for pid in np.unique(pids):
            sel = np.flatnonzero(pids == pid)
            if pid == FULL_PATTERN:
                M, Y = np.eye(FEATURE_DIM), triangle_features(states[sel], tri)
            else:
                G = observed_map(pattern_codes(int(pid)))
                if G.shape[0] < min_dim:
                    continue
                M, Y = feature_map_for(G), np.zeros((sel.size, FEATURE_DIM))
                Y[:, :G.shape[0]] = flat[sel] @ G.T
            Mp = np.zeros((FEATURE_DIM, FEATURE_DIM))
            Mp[:M.shape[0]] = M
            maps.append(Mp)
            dims.append(M.shape[0])
            parts.append(Y)
        sizes = [len(p) for p in parts]
        Y = np.concatenate(parts) if parts else np.zeros((0, FEATURE_DIM))
        return cls(Y, np.r_[0, np.cumsum(sizes)].astype(np.int64),
                   np.array(maps).reshape(-1, FEATURE_DIM, FEATURE_DIM), np.array(dims, dtype=np.int64))

    @property
    def complete(self) -> int:
        """How many samples are fully seen."""
        return int(sum(np.diff(self.bounds)[self.dims == FEATURE_DIM]))

    def take(self, idx: np.ndarray) -> "PartialSamples":
        """The samples ``idx`` (sorted indices keep the pattern order)."""
        idx = np.sort(np.asarray(idx))
        counts = np.array([np.count_nonzero((idx >= a) & (idx < b)) for a, b in zip(self.bounds[:-1],
                                                                                  self.bounds[1:])])
        return PartialSamples(self.Y[idx], np.r_[0, np.cumsum(counts)].astype(np.int64), self.M, self.dims)

    # -- one Gaussian component ---------------------------------------------------------------
    def _factors(self, mu: np.ndarray, S: np.ndarray):
        """Per pattern ``L^-1`` of ``A = M S M^T`` (padded), ``log det A`` and ``M mu``."""
        A = self.M @ S @ self.M.transpose(0, 2, 1) + self.pad
        L = np.linalg.cholesky(A)
        logdet = 2.0 * np.log(np.diagonal(L, axis1=1, axis2=2)).sum(1)
        return np.linalg.inv(L), logdet, self.M @ mu

    def _slices(self):
        return enumerate(zip(self.bounds[:-1], self.bounds[1:]))

    def log_pdf(self, mu: np.ndarray, S: np.ndarray) -> np.ndarray:
        """(n,) log density of what each sample shows under ``N(mu, S)``."""
        Linv, logdet, Mmu = self._factors(mu, S)
        out = np.empty(self.n)
        for g, (a, b) in self._slices():
            z = (self.Y[a:b] - Mmu[g]) @ Linv[g].T
            out[a:b] = -0.5 * ((z * z).sum(1) + logdet[g] + self.dims[g] * LOG_2PI)
        return out

    def conditional(self, mu: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(E[X|y] (n, 15), Cov[X|y] per pattern (G, 15, 15))`` under ``N(mu, S)``."""
        Linv, _, Mmu = self._factors(mu, S)
        Ainv = Linv.transpose(0, 2, 1) @ Linv
        K = S @ self.M.transpose(0, 2, 1) @ Ainv                              # (G, 15, 15)
        Xh = np.empty_like(self.Y)
        for g, (a, b) in self._slices():
            Xh[a:b] = mu + (self.Y[a:b] - Mmu[g]) @ K[g].T
        return Xh, S - K @ self.M @ S

    def moments(self, r: np.ndarray, mu: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 10 with missing values: the weighted mean and covariance of ``X`` from the
        expected sufficient statistics under the current ``N(mu, S)`` (module doc)."""
        Xh, C = self.conditional(mu, S)
        s0 = float(r.sum()) + 1e-300
        per_group = np.add.reduceat(r, self.bounds[:-1]) if self.n else np.zeros(len(self.dims))
        per_group = np.where(np.diff(self.bounds) > 0, per_group, 0.0)
        mean = (r @ Xh) / s0
        D = Xh - mean
        cov = ((D.T * r) @ D + np.einsum("g,gij->ij", per_group, C)) / s0
        return mean, cov

    def impute(self, mu: np.ndarray, S: np.ndarray) -> np.ndarray:
        """(n, 15) conditional means ``E[X | y]``."""
        return self.conditional(mu, S)[0]

    def single_gaussian(self, w: np.ndarray, reg: float, iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
        """ML ``(mu, S)`` of one Gaussian by EM with missing data, started from the fully seen
        samples (or a unit covariance around zero)."""
        full = self.Y[np.isin(self.group, np.flatnonzero(self.dims == FEATURE_DIM))]
        if full.shape[0] > FEATURE_DIM:
            mu, S = full.mean(0), np.cov(full, rowvar=False, bias=True)
        else:
            mu, S = np.zeros(FEATURE_DIM), np.eye(FEATURE_DIM)
        S, _ = stable_cholesky(S, reg)
        for _ in range(iterations):
            mu_new, S_new = self.moments(w, mu, S)
            S_new, _ = stable_cholesky(S_new, reg)
            done = np.abs(mu_new - mu).max() < 1e-9 and np.abs(S_new - S).max() < 1e-9
            mu, S = mu_new, S_new
            if done:
                break
        return mu, S


class _PartialData:
    """Mixin: the hooks of :class:`~.mixture_em.MixtureEstimator` for :class:`PartialSamples`
    (``X`` in the shared code is the conditional mean, used only to initialise)."""

    data: PartialSamples

    def fit_partial(self, data: PartialSamples, sample_weight=None) -> FitResult:
        """Fit to partly seen samples (module doc)."""
        if data.n < 1:
            raise ValueError("no samples")
        self.data = data
        w = np.ones(data.n) if sample_weight is None else np.asarray(sample_weight, dtype=np.float64)
        self._notes = []
        rng = np.random.default_rng(self.random_state)
        mu, S = data.single_gaussian(w, self.reg_covar)
        return self._fit(data.impute(mu, S), w, rng)

    def _update_gaussian(self, X, rw, state, m: int, recompute: bool = True) -> None:
        mu, cov = self.data.moments(rw, state.means[m], state.covs[m])
        cov, chol = stable_cholesky(cov, self.reg_covar)
        state.means[m] = mu
        state.covs[m] = cov
        state.prec[m] = inv_lower(chol)
        if recompute:
            state.log_dens[m] = self.data.log_pdf(mu, cov)

    def _log_densities(self, X, means, covs, prec) -> np.ndarray:
        return np.stack([self.data.log_pdf(means[k], covs[k]) for k in range(means.shape[0])])

    def _log_likelihood(self, X, w, gm: GaussianMixture) -> float:
        comp = self._log_densities(X, np.asarray(gm.means), np.asarray(gm.covariances), None)
        return float(w @ logsumexp_rows(comp.T + np.log(np.asarray(gm.weights))))


class PartialSingleGaussian(_PartialData, SingleGaussian):
    """:class:`~.mixture_em.SingleGaussian` on partly seen samples (EM for one Gaussian)."""

    def _fit(self, X, w, rng) -> FitResult:
        mu, S = self.data.single_gaussian(w, self.reg_covar, iterations=200)
        state = self._state_from(X, np.ones(1), mu[None], S[None])
        ll = self._log_likelihood(X, w, GaussianMixture(np.ones(1), mu[None], S[None]))
        return self._result(X, w, state, 1, True, [], [ll])


class PartialFixedK(_PartialData, FixedKMixture):
    """:class:`~.mixture_em.FixedKMixture` on partly seen samples."""


class PartialMDL(_PartialData, MDLMixture):
    """:class:`~.mixture_em.MDLMixture` on partly seen samples."""

    def _single_gaussian(self) -> MixtureEstimator:
        single = PartialSingleGaussian(reg_covar=self.reg_covar, random_state=self.random_state)
        single.data = self.data
        return single


def make_partial_estimator(kind: str, **kw) -> MixtureEstimator:
    """Like :func:`~.mixture_em.make_estimator` (same keywords), for :meth:`_PartialData.fit_partial`."""
    return make_estimator(kind, classes={"single": PartialSingleGaussian, "fixed": PartialFixedK, "mdl": PartialMDL},
                          **kw)
