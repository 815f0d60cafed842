"""Compiled draw of the guided sampler (:func:`~.label_search.guided_sample`): the Gumbel-max trick.

A guided sample draws each candidate's root triangle among every plausible one -- some 15 000 at
41 markers -- and then each label's point among the frame's, all with probability
``exp(term / temperature)``: the arg max of the scores plus i.i.d. standard Gumbel noise. With
``np.argmax(scores + rng.gumbel(...))`` that is two logarithms a candidate, for every member of
the population: 0.6 s of six cold searches at 41 markers (8 %). :func:`gumbel_pick` takes the
generator's uniforms as numpy's Gumbel draw does (one double a variate, ``-log(-log(1 - u))``),
so it draws the same samples, and takes the logarithms only where a candidate can still win:
no noise of a row exceeds that of its least uniform, so a candidate whose score falls further
below the best total found than that cannot be the arg max (the shared root-triangle scores
visited best first, each row stops there). Those six searches: 0.6 -> 0.34 s, the uniforms
alone 0.075 s (``results/fast_path_kernels.md``, 2026-12-06 night).
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _noise(u):  # pragma: no cover - compiled
    """The standard Gumbel variate of uniform ``u`` as numpy draws it: ``-log(-log(1 - u))``."""
    return -np.log(-np.log(1.0 - u))


@njit(cache=True, nogil=True)
def gumbel_pick(val, temp, u):  # pragma: no cover - compiled
    """(R,) per row ``r`` of the scores ``val[r] / temp[r]`` (``val`` (R, K), or (1, K) shared by
    every row; no NaN; ``temp`` > 0) the arg max of ``score - log(-log(1 - u[r]))`` for uniforms
    ``u`` (R, K) in [0, 1): the first on ties, 0 where every score is -inf (as ``np.argmax``).
    Shared scores are visited best first (one sort), each row stopping at the first candidate
    that cannot reach the best total found; a row of its own is screened against its best
    score's total."""
    R, K = u.shape
    out = np.zeros(R, dtype=np.int64)
    shared = val.shape[0] == 1
    order = np.argsort(-val[0], kind="mergesort") if shared else np.zeros(0, dtype=np.int64)
    for r in range(R):
        row = val[0] if shared else val[r]
        t = temp[r]
        least = 1.0
        for k in range(K):
            if u[r, k] < least:
                least = u[r, k]
        most = _noise(least)                                           # no noise of the row exceeds this
        best = -np.inf
        arg = 0
        if shared:
            for j in range(K):
                k = order[j]
                sc = row[k] / t
                if sc + most < best:                                   # nor can any after it
                    break
                v = sc + _noise(u[r, k])
                if v > best or (v == best and k < arg):
                    best = v
                    arg = k
        else:
            top = 0
            for k in range(K):
                if row[k] > row[top]:
                    top = k
            reached = row[top] / t + _noise(u[r, top])                 # the row's maximum is at least this
            for k in range(K):
                sc = row[k] / t
                if sc + most >= reached:
                    v = sc + _noise(u[r, k])
                    if v > best:
                        best = v
                        arg = k
        out[r] = arg
    return out


def gumbel_argmax(val: np.ndarray, temp: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """For each of the R rows, the arg max of the scores ``val / temp[r]`` (``val`` (K,) shared by
    every row, or (R, K)) plus i.i.d. standard Gumbel noise from ``rng`` -- a draw of the row's
    categorical ``exp(val / temp[r])`` -- as ``np.argmax(val / temp[:, None] +
    rng.gumbel(size=(R, K)), axis=1)`` makes it, from the same uniforms (module doc)."""
    temp = np.ascontiguousarray(temp, dtype=np.float64).reshape(-1)
    val = np.ascontiguousarray(val, dtype=np.float64)
    val2 = val.reshape(1, -1) if val.ndim == 1 else val
    u = rng.random((temp.size, val2.shape[1]))
    if np.isnan(val2).any():                        # NaN: np.argmax's rule, every log taken
        return np.argmax(val2 / temp[:, None] - np.log(-np.log(1.0 - u)), axis=1)
    return gumbel_pick(val2, temp, u)


def warm_up() -> None:
    """Compile (or load) the kernel once."""
    gumbel_pick(np.zeros((1, 2)), np.ones(1), np.full((1, 2), 0.5))


__all__ = ["gumbel_argmax", "gumbel_pick", "warm_up"]
