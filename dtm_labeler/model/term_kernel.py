"""Compiled kernel of the hot path: conditional mixture terms for a batch of triple states.

For row ``r`` with triangle ``t = tri[r]`` and (18,) stacked state ``s[r]`` (the three
vertices' canonical position + velocity, unobserved entries zero), :class:`BatchedTerms
<dtm_labeler.model.dtm.BatchedTerms>` has stacked, per triangle, the whitening of the joint
density of what is observed (``kj`` component slots of ``mj`` rows) and of its parents
(``kp`` slots of ``mp`` rows): ``z = s W_t - c_t``. The term is

    log sum_k exp(cj[t, k] - |z_jk|^2 / 2)  -  [np_[t] > 0] log sum_k exp(cp[t, k] - |z_pk|^2 / 2)

i.e. ``log p(obs(A, B, C)) - log p(obs(B, C))`` (eq. 5/14 with eq. 30-31 marginalisation).

Why compiled: the labeler evaluates a few hundred to a few thousand terms per frame, spread
over several observation patterns and dozens of triangles, in batches of 10-300 rows. In
numpy each batch pays a fixed cost of some 15 array operations (gathers, norms, two
log-sum-exps) of about 100 us, which is most of a frame's budget; here one batch costs a few
microseconds plus about 1 us per row at 41 markers (R = 192 whitened coordinates). Each row
only touches its own triangle's components (``nj[t]``, ``np_[t]``; the padding slots of
triangles with fewer components are skipped) and the state entries that are non-zero
(a marginalised vertex contributes nothing).

Compiled on first use and cached on disk (numba ``cache=True``); :meth:`TriangulatedModel.warm_up
<dtm_labeler.model.dtm.TriangulatedModel.warm_up>` calls it once so a node never compiles on
a frame.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def mixture_terms(s, tri, W, c, cj, cp, nj, np_, mj, mp):  # pragma: no cover - compiled
    """Terms for rows ``s`` (n, 18) of triangles ``tri`` (n,): see the module doc. ``W``
    (T, 18, R), ``c`` (T, R); ``cj`` (T, kj) / ``cp`` (T, kp) log weights + normalisers;
    ``nj[t]`` / ``np_[t]`` components of the joint / parents (``np_[t] = 0``: no parent
    term); joint component ``k`` occupies columns ``[k mj, (k+1) mj)``, parents' component
    ``k`` columns ``[off + k mp, off + (k+1) mp)`` with ``off = kj mj``."""
    n = s.shape[0]
    out = np.empty(n)
    z = np.empty(W.shape[2])
    q = np.empty(max(cj.shape[1], cp.shape[1]))
    off = cj.shape[1] * mj
    for r in range(n):
        out[r] = row_term(s[r], tri[r], W, c, cj, cp, nj, np_, mj, mp, off, z, q)
    return out


@njit(cache=True, nogil=True, inline="always")
def row_term(s, t, W, c, cj, cp, nj, np_, mj, mp, off, z, q):  # pragma: no cover - compiled
    """The term of one (18,) state ``s`` of triangle ``t`` (arrays as :func:`mixture_terms`;
    ``off`` the first parents' column, ``z`` / ``q`` scratch of ``R`` / ``max(kj, kp)``).
    ``z`` is accumulated three state entries (one vertex's position or velocity) per pass:
    one pass per entry loaded and stored ``z`` 18 times a row; per block of three, 0.54 ->
    0.41 us a row at 14 points (results/stream_latency.md, 2026-12-06 evening), the same terms
    to 2e-12 nats (the sums are associated differently)."""
    hi_j = nj[t] * mj
    hi_p = off + np_[t] * mp
    for col in range(hi_j):
        z[col] = -c[t, col]
    for col in range(off, hi_p):
        z[col] = -c[t, col]
    for j in range(0, s.shape[0], 3):            # one vertex's position or velocity per pass over z
        v0 = s[j]
        v1 = s[j + 1]
        v2 = s[j + 2]
        if v0 == 0.0 and v1 == 0.0 and v2 == 0.0:
            continue                                 # unobserved (marginalised): contributes nothing
        for col in range(hi_j):
            z[col] += v0 * W[t, j, col] + v1 * W[t, j + 1, col] + v2 * W[t, j + 2, col]
        for col in range(off, hi_p):
            z[col] += v0 * W[t, j, col] + v1 * W[t, j + 1, col] + v2 * W[t, j + 2, col]
    out = _lse_block(z, 0, nj[t], mj, cj[t], q)
    if np_[t] > 0:
        out -= _lse_block(z, off, np_[t], mp, cp[t], q)
    return out


@njit(cache=True, nogil=True, inline="always")
def log_add_exp(a, b):  # pragma: no cover - compiled
    """``log(exp(a) + exp(b))`` as numpy's ``logaddexp`` computes it."""
    if a == b:
        return a + np.log(2.0)
    d = a - b
    if d > 0:
        return a + np.log1p(np.exp(-d))
    if d <= 0:
        return b + np.log1p(np.exp(d))
    return d


@njit(cache=True, nogil=True, inline="always")
def _lse_block(z, start, k_count, dim, const, q):  # pragma: no cover - compiled
    """log sum_k exp(const[k] - |z[start + k dim : start + (k+1) dim]|^2 / 2)."""
    top = -np.inf
    for k in range(k_count):
        acc = 0.0
        base = start + k * dim
        for d in range(dim):
            x = z[base + d]
            acc += x * x
        q[k] = const[k] - 0.5 * acc
        if q[k] > top:
            top = q[k]
    if top == -np.inf:
        return top
    total = 0.0
    for k in range(k_count):
        total += np.exp(q[k] - top)
    return top + np.log(total)
