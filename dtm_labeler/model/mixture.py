"""Full-covariance Gaussian mixtures: the density of one DTM triangle (Hu & Wong, sec. III).

A triangle's feature vector ``X`` (eq. 12: nine velocity and six relative-position
components, so ``d = 15``) is modelled by a ``K``-component Gaussian mixture, eq. 6-7::

    p(x) = sum_k w_k N(x; mu_k, Sigma_k)                                   (eq. 6)
    N(x; mu, Sigma) = exp(-1/2 (x-mu)^T Sigma^-1 (x-mu)) / ((2 pi)^(d/2) |Sigma|^(1/2))   (eq. 7)

:class:`GaussianMixture` is the fitted, immutable value object. Its densities are
evaluated in log space from precomputed precision-Cholesky factors ``W_k = L_k^-1``
(``Sigma_k = L_k L_k^T``)::

    log N_k(x) = -d/2 log 2 pi + sum_i log W_k[i, i] - 1/2 |W_k (x - mu_k)|^2

so a batch of rows costs one ``(n, d) @ (d, K d)`` matmul plus a log-sum-exp (this is
the real-time hot path of the fitness function, eq. 13 and eq. 18-20).

:meth:`GaussianMixture.linear_map` gives the exact distribution of ``A x + b``; marginals
(missing markers, eq. 30-31) and the conditionals ``P(A | B, C) = P(A, B, C) / P(B, C)``
of eq. 5 and eq. 13 are built from it. The estimators live in :mod:`.mixture_em`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

__all__ = ["GaussianMixture", "stable_cholesky", "params_per_component", "logsumexp_rows"]

LOG_2PI = math.log(2.0 * math.pi)
_WEIGHT_ATOL = 1e-6   # |sum(weights) - 1| allowed on input (then renormalised exactly)
_SYM_RTOL = 1e-8      # asymmetry allowed on input, relative to max |Sigma| (then symmetrised)
_MAX_JITTER_TRIES = 16
# OpenBLAS runs a gemm single-threaded while m*n*k stays below 4 * 65536. Threads buy
# nothing at these sizes, and on a busy 2-core machine a threaded call that must wait for
# a descheduled worker costs 3-10x; so every (n, d) @ (d, p) product with large n is cut
# into row blocks that stay in the single-threaded regime (blocks, never per-sample loops).
_GEMM_SINGLE_THREAD_MNK = 1 << 18


def params_per_component(dim: int) -> int:
    """``N = d + d (d + 1) / 2``: free parameters of one full-covariance Gaussian (sec. III)."""
    return dim + dim * (dim + 1) // 2


def logsumexp_rows(a: np.ndarray) -> np.ndarray:
    """Row-wise ``log sum_k exp(a[:, k])``, stable; rows of all ``-inf`` give ``-inf``."""
    m = a.max(axis=1)
    m = np.where(np.isfinite(m), m, 0.0)
    with np.errstate(divide="ignore"):
        return np.log(np.exp(a - m[:, None]).sum(axis=1)) + m


def stable_cholesky(cov: np.ndarray, reg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Cholesky factor of ``cov + reg I``, adding more to the diagonal until it exists.

    ``cov`` is one ``(d, d)`` matrix (symmetric part is used). The jitter starts at
    ``reg`` (or ``1e-12`` x the mean diagonal when ``reg == 0``) and grows tenfold per
    failed attempt. Returns ``(cov_used, L)`` with ``cov_used = L L^T`` the regularised
    matrix actually factored, so densities stay consistent with the stored covariance.
    Raises ``ValueError`` for non-finite input.
    """
    cov = np.asarray(cov, dtype=np.float64)
    if not np.all(np.isfinite(cov)):
        raise ValueError("covariance contains NaN or inf")
    cov = 0.5 * (cov + cov.T)
    d = cov.shape[0]
    if d == 0:
        return cov, cov.copy()
    eye = np.eye(d)
    if reg > 0.0:
        cov = cov + reg * eye
    try:
        return cov, np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        pass
    scale = float(np.mean(np.abs(np.diag(cov))))
    if not scale > 0.0:
        scale = 1.0
    jitter = max(reg, 1e-12 * scale)
    for _ in range(_MAX_JITTER_TRIES):
        trial = cov + jitter * eye
        try:
            return trial, np.linalg.cholesky(trial)
        except np.linalg.LinAlgError:
            jitter *= 10.0
    raise ValueError("covariance could not be regularised to positive definite")


def inv_lower(chol: np.ndarray) -> np.ndarray:
    """``W = L^-1`` (lower triangular) of one ``(d, d)`` or a stack ``(K, d, d)`` of Cholesky factors.

    Uses numpy's LAPACK only: mixing scipy.linalg calls (a second OpenBLAS with its own
    thread pool) into numpy-BLAS loops costs ~10x on small machines (pools spin-wait).
    """
    return np.tril(np.linalg.inv(chol))


def rows_matmul(X: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``X @ B`` for ``X`` ``(n, d)``, in row blocks small enough for single-threaded BLAS."""
    n, d = X.shape
    p = B.shape[1]
    step = max(1, _GEMM_SINGLE_THREAD_MNK // max(1, d * p))
    if n <= step:
        return X @ B
    out = np.empty((n, p))
    for i in range(0, n, step):
        np.matmul(X[i:i + step], B, out=out[i:i + step])
    return out


def weighted_gram(D: np.ndarray, rw: np.ndarray) -> np.ndarray:
    """``sum_i rw_i D_i D_i^T`` (``(d, d)``) for ``D`` ``(n, d)``, in single-threaded BLAS blocks."""
    n, d = D.shape
    step = max(1, _GEMM_SINGLE_THREAD_MNK // max(1, d * d))
    out = np.zeros((d, d))
    for i in range(0, n, step):
        blk = D[i:i + step]
        out += (blk.T * rw[i:i + step]) @ blk
    return out


def log_gaussian_one(X: np.ndarray, mean: np.ndarray, prec_chol: np.ndarray) -> np.ndarray:
    """``log N(x_i; mean, Sigma)`` (eq. 7) for all rows, given ``W = chol(Sigma)^-1``."""
    d = X.shape[1]
    y = rows_matmul(X, prec_chol.T)
    y -= prec_chol @ mean
    return (-0.5 * d * LOG_2PI + np.log(np.diag(prec_chol)).sum()) - 0.5 * np.einsum("ij,ij->i", y, y)


def log_gaussian_all(X: np.ndarray, means: np.ndarray, prec_chol: np.ndarray) -> np.ndarray:
    """``(n, K)`` matrix of ``log N_k(x_i)`` (eq. 7), one batched matmul for all components."""
    k, d = means.shape
    n = X.shape[0]
    wcat = prec_chol.transpose(2, 0, 1).reshape(d, k * d)        # columns: rows of each W_k
    offs = np.einsum("kij,kj->ki", prec_chol, means).reshape(k * d)
    y = rows_matmul(X, wcat)
    y -= offs
    y = y.reshape(n, k, d)
    const = -0.5 * d * LOG_2PI + np.log(np.diagonal(prec_chol, axis1=1, axis2=2)).sum(axis=1)
    return const - 0.5 * np.einsum("nkd,nkd->nk", y, y)


def _as_rng(rng) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    return np.random.default_rng(rng)


@dataclass(frozen=True, eq=False, repr=False)
class GaussianMixture:
    """Immutable ``K``-component, ``d``-dimensional full-covariance Gaussian mixture (eq. 6-7).

    Parameters
    ----------
    weights : (K,) positive, summing to 1 within 1e-6 (renormalised exactly).
    means : (K, d)
    covariances : (K, d, d) symmetric (within 1e-8 relative; symmetrised) positive definite.

    Construction validates and raises ``ValueError`` with a clear message otherwise, then
    precomputes the precision-Cholesky factors and log-normalisers once; the arrays are
    made read-only so the cache can never go stale. ``d = 0`` (the mixture of an empty
    :meth:`linear_map`) is allowed: its density is 1, i.e. ``log_pdf`` is 0 for every row.
    """

    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    _prec_chol: np.ndarray = field(init=False, repr=False)
    _wcat: np.ndarray = field(init=False, repr=False)
    _offs: np.ndarray = field(init=False, repr=False)
    _const: np.ndarray = field(init=False, repr=False)
    _chol: np.ndarray = field(init=False, repr=False)
    _marginal_cache: dict = field(init=False, repr=False)

    def __post_init__(self) -> None:
        w = np.array(self.weights, dtype=np.float64, copy=True)
        mu = np.array(self.means, dtype=np.float64, copy=True)
        cov = np.array(self.covariances, dtype=np.float64, copy=True)
        if w.ndim != 1 or w.shape[0] < 1:
            raise ValueError(f"weights must be a non-empty 1-D array, got shape {w.shape}")
        k = w.shape[0]
        if mu.ndim != 2 or mu.shape[0] != k:
            raise ValueError(f"means must have shape (K={k}, d), got {mu.shape}")
        d = mu.shape[1]
        if cov.shape != (k, d, d):
            raise ValueError(f"covariances must have shape (K, d, d) = {(k, d, d)}, got {cov.shape}")
        for name, arr in (("weights", w), ("means", mu), ("covariances", cov)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contain NaN or inf")
        if np.any(w <= 0.0):
            raise ValueError(f"weights must be strictly positive, got min {w.min():.3g}")
        total = w.sum()
        if abs(total - 1.0) > _WEIGHT_ATOL:
            raise ValueError(f"weights must sum to 1 (within {_WEIGHT_ATOL:g}), they sum to {total!r}")
        if abs(total - 1.0) > 8.0 * k * np.finfo(float).eps:   # idempotent: no re-rounding on reload
            w /= total
        chol = np.zeros_like(cov)
        if d:
            cov_t = cov.transpose(0, 2, 1)
            asym = np.abs(cov - cov_t).max(axis=(1, 2))
            scale = np.maximum(np.abs(cov).max(axis=(1, 2)), np.finfo(float).tiny)
            bad = np.flatnonzero(asym > _SYM_RTOL * scale)
            if bad.size:
                i = int(bad[0])
                raise ValueError(f"covariance {i} is not symmetric (max |S - S^T| = {asym[i]:.3g})")
            cov = 0.5 * (cov + cov_t)
            try:
                chol = np.linalg.cholesky(cov)
            except np.linalg.LinAlgError:
                for i in range(k):
                    try:
                        np.linalg.cholesky(cov[i])
                    except np.linalg.LinAlgError:
                        raise ValueError(f"covariance {i} is not positive definite") from None
                raise  # pragma: no cover - the batch failed, so one component must have
            if not np.all(np.diagonal(chol, axis1=1, axis2=2) > 0.0):
                raise ValueError("a covariance is not positive definite")
        prec = inv_lower(chol) if d else chol.copy()
        if not np.all(np.isfinite(prec)):
            raise ValueError("covariance too ill-conditioned to invert")
        wcat = prec.transpose(2, 0, 1).reshape(d, k * d).copy()
        offs = np.einsum("kij,kj->ki", prec, mu).reshape(k * d)
        const = (np.log(w) - 0.5 * d * LOG_2PI
                 + np.log(np.diagonal(prec, axis1=1, axis2=2)).sum(axis=1))
        for arr in (w, mu, cov, chol, prec, wcat, offs, const):
            arr.setflags(write=False)
        object.__setattr__(self, "weights", w)
        object.__setattr__(self, "means", mu)
        object.__setattr__(self, "covariances", cov)
        object.__setattr__(self, "_chol", chol)
        object.__setattr__(self, "_prec_chol", prec)
        object.__setattr__(self, "_wcat", wcat)
        object.__setattr__(self, "_offs", offs)
        object.__setattr__(self, "_const", const)
        object.__setattr__(self, "_marginal_cache", {})

    # ------------------------------------------------------------------ shape
    @property
    def n_components(self) -> int:
        """``K``."""
        return int(self.weights.shape[0])

    @property
    def dim(self) -> int:
        """``d``."""
        return int(self.means.shape[1])

    @property
    def n_parameters(self) -> int:
        """Free parameters: ``K - 1`` weights plus ``K N``, ``N = d + d(d+1)/2`` (sec. III)."""
        k = self.n_components
        return k - 1 + k * params_per_component(self.dim)

    def __repr__(self) -> str:
        return (f"GaussianMixture(n_components={self.n_components}, dim={self.dim}, "
                f"weights={np.array2string(self.weights, precision=3)})")

    # ---------------------------------------------------------------- density
    def _rows(self, X) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        if X.ndim == 1:
            X = X.reshape(1, -1)
        if X.ndim != 2 or X.shape[1] != self.dim:
            raise ValueError(f"X must have shape (n, {self.dim}), got {X.shape}")
        return X

    def component_log_pdf(self, X) -> np.ndarray:
        """``(n, K)`` matrix of ``log w_k + log N_k(x_i)`` (eq. 6-7).

        ``X`` is ``(n, d)`` (a 1-D array is one row). Row-wise ``max`` of this is the
        paper's eq. 13 score, its row-wise log-sum-exp is :meth:`log_pdf`.
        """
        X = self._rows(X)
        n, d, k = X.shape[0], self.dim, self.n_components
        if d == 0:
            return np.broadcast_to(self._const, (n, k)).copy()
        y = rows_matmul(X, self._wcat)
        y -= self._offs
        y = y.reshape(n, k, d)
        return self._const - 0.5 * np.einsum("nkd,nkd->nk", y, y)

    def log_pdf(self, X) -> np.ndarray:
        """``(n,)`` log mixture density ``log p(x_i)`` (eq. 6), stable log-sum-exp."""
        X = self._rows(X)
        if self.dim == 0:
            return np.zeros(X.shape[0])
        if self.n_components == 1:
            return self.component_log_pdf(X)[:, 0]
        return logsumexp_rows(self.component_log_pdf(X))

    def pdf(self, X) -> np.ndarray:
        """``exp(log_pdf(X))``."""
        return np.exp(self.log_pdf(X))

    def responsibilities(self, X) -> np.ndarray:
        """``(n, K)`` posterior component probabilities ``alpha_k(x_i)`` (eq. 8)."""
        lp = self.component_log_pdf(X)
        return np.exp(lp - logsumexp_rows(lp)[:, None])

    # ------------------------------------------------------- linear transforms
    def linear_map(self, A, b=None) -> "GaussianMixture":
        """Distribution of ``y = A x + b``: same weights, means ``A mu_k + b``, covs ``A Sigma_k A^T``.

        ``A`` is ``(m, d)`` with ``m <= d`` and full row rank (then every image covariance
        is positive definite). Covariances are symmetrised; only if a Cholesky factor then
        fails (rank-deficient or badly conditioned ``A``) is the smallest sufficient jitter
        added to its diagonal (see :func:`stable_cholesky`). ``m = 0`` gives the ``d = 0``
        mixture whose ``log_pdf`` is 0 for every row (the density of nothing).
        """
        A = np.asarray(A, dtype=np.float64)
        if A.ndim == 1 and A.size == 0:
            A = A.reshape(0, self.dim)
        if A.ndim != 2 or A.shape[1] != self.dim:
            raise ValueError(f"A must have shape (m, {self.dim}), got {A.shape}")
        if not np.all(np.isfinite(A)):
            raise ValueError("A contains NaN or inf")
        m = A.shape[0]
        means = self.means @ A.T
        if b is not None:
            b = np.asarray(b, dtype=np.float64).reshape(-1)
            if b.shape != (m,):
                raise ValueError(f"b must have shape ({m},), got {b.shape}")
            means = means + b
        covs = np.einsum("ij,kjl,ml->kim", A, self.covariances, A)
        covs = 0.5 * (covs + covs.transpose(0, 2, 1))
        try:
            return GaussianMixture(self.weights, means, covs)
        except ValueError:
            if not m:
                raise
        for i in range(covs.shape[0]):   # rare: rank-deficient / ill-conditioned A
            try:
                np.linalg.cholesky(covs[i])
            except np.linalg.LinAlgError:
                covs[i] = stable_cholesky(covs[i], 0.0)[0]
        return GaussianMixture(self.weights, means, covs)

    def marginal(self, dims: Sequence[int]) -> "GaussianMixture":
        """Marginal over the coordinates ``dims`` (in that order): ``linear_map`` with rows of ``I``.

        Implemented by exact sub-indexing (no rounding) and cached per ``dims`` tuple, since
        the labeler asks for the same few marginals (missing markers, eq. 30-31) every frame.
        """
        key = tuple(int(i) for i in dims)
        hit = self._marginal_cache.get(key)
        if hit is not None:
            return hit
        d = self.dim
        for i in key:
            if not -d <= i < d:
                raise ValueError(f"dimension index {i} out of range for dim {d}")
        idx = np.array([i % d for i in key], dtype=np.intp) if key else np.zeros(0, np.intp)
        if len(set(idx.tolist())) != len(idx):
            raise ValueError(f"repeated dimension in {key}")
        out = GaussianMixture(self.weights, self.means[:, idx],
                              self.covariances[:, idx][:, :, idx])
        self._marginal_cache[key] = out
        return out

    # ------------------------------------------------------------- sampling
    def sample(self, n: int, rng=None) -> np.ndarray:
        """Draw ``n`` rows ``(n, d)``; ``rng`` is a ``numpy.random.Generator``, a seed or None."""
        rng = _as_rng(rng)
        n = int(n)
        if n < 0:
            raise ValueError("n must be non-negative")
        comp = rng.choice(self.n_components, size=n, p=self.weights)
        z = rng.standard_normal((n, self.dim))
        out = np.empty((n, self.dim))
        for k in range(self.n_components):
            sel = comp == k
            out[sel] = self.means[k] + z[sel] @ self._chol[k].T
        return out

    # ------------------------------------------------------------ model file
    def to_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """Plain arrays for an ``.npz`` model file (no pickle): ``weights``, ``means``, ``covariances``."""
        return {prefix + "weights": np.array(self.weights),
                prefix + "means": np.array(self.means),
                prefix + "covariances": np.array(self.covariances)}

    @classmethod
    def from_arrays(cls, d: Mapping[str, np.ndarray], prefix: str = "") -> "GaussianMixture":
        """Inverse of :meth:`to_arrays`; validates (``ValueError`` on missing keys, bad
        shapes, NaN/inf, non-positive or unnormalised weights, asymmetric or non-PD covariances)."""
        try:
            arrays = [np.asarray(d[prefix + key]) for key in ("weights", "means", "covariances")]
        except KeyError as exc:
            raise ValueError(f"model arrays lack key {exc.args[0]!r}") from None
        for key, arr in zip(("weights", "means", "covariances"), arrays):
            if arr.dtype == object or not np.issubdtype(arr.dtype, np.number):
                raise ValueError(f"{prefix}{key} must be a numeric array, got dtype {arr.dtype}")
        return cls(*arrays)
