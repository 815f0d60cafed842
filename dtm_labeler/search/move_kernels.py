"""Compiled neighbourhood of a carried-over labeling (the fast path's moves).

The moves are few -- a few dozen rows of M labels -- and scoring them all is one call of
:meth:`~.problem.FrameProblem.fitness` (13-20 us at 14 points, the terms cached). Built with
numpy (meshgrids, repeats, fancy assignments over small arrays) they cost more than that: on
the demo's flicker stream at 14 points, ~100 us per hill-climb round plus 30 us for the close
pairs. Compiled here (with :func:`~.frame_kernels.allowed_points`), 14-19 us. The rows come in
the order numpy wrote them, so the hill-climb's arg max breaks ties as before:

1. the labeling itself, its mirror image (every left/right pair swapped at once);
2. each close label pair swapped, then each left/right pair swapped;
3. every label moved onto each free point where ``allowed`` permits it (label-major);
4. every label in ``release`` left missing.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def move_rows(ind, n, mirror_pairs, close_pairs, free_points, allowed, use_allowed, release):  # pragma: no cover - compiled
    """(R, M) candidate rows (module doc). ``allowed`` (M, n+1) is read only when ``use_allowed``."""
    M = ind.size
    n_mp, n_cp, n_free, n_rel = mirror_pairs.shape[0], close_pairs.shape[0], free_points.size, release.size
    n_mv = 0
    for lab in range(M):
        for q in range(n_free):
            if not use_allowed or allowed[lab, free_points[q]]:
                n_mv += 1
    out = np.empty((2 + n_cp + n_mp + n_mv + n_rel, M), dtype=np.int64)
    for r in range(out.shape[0]):
        for lab in range(M):
            out[r, lab] = ind[lab]
    # the mirror image: numpy's simultaneous assignment (left from right, then right from left)
    for k in range(n_mp):
        out[1, mirror_pairs[k, 0]] = ind[mirror_pairs[k, 1]]
    for k in range(n_mp):
        out[1, mirror_pairs[k, 1]] = ind[mirror_pairs[k, 0]]
    r = 2
    for k in range(n_cp):
        out[r, close_pairs[k, 0]] = ind[close_pairs[k, 1]]
        out[r, close_pairs[k, 1]] = ind[close_pairs[k, 0]]
        r += 1
    for k in range(n_mp):
        out[r, mirror_pairs[k, 0]] = ind[mirror_pairs[k, 1]]
        out[r, mirror_pairs[k, 1]] = ind[mirror_pairs[k, 0]]
        r += 1
    for lab in range(M):
        for q in range(n_free):
            p = free_points[q]
            if not use_allowed or allowed[lab, p]:
                out[r, lab] = p
                r += 1
    for k in range(n_rel):
        out[r, release[k]] = n
        r += 1
    return out


@njit(cache=True, nogil=True)
def close_label_pairs(ind, n, dist, radius):  # pragma: no cover - compiled
    """(K, 2) label pairs ``(a, b)``, ``a < b``, both labelled and their points closer than
    ``radius``; in row-major order."""
    M = ind.size
    K = 0
    for a in range(M):
        if ind[a] < n:
            for b in range(a + 1, M):
                if ind[b] < n and dist[ind[a], ind[b]] < radius:
                    K += 1
    out = np.empty((K, 2), dtype=np.int64)
    k = 0
    for a in range(M):
        if ind[a] < n:
            for b in range(a + 1, M):
                if ind[b] < n and dist[ind[a], ind[b]] < radius:
                    out[k, 0] = a
                    out[k, 1] = b
                    k += 1
    return out


@njit(cache=True, nogil=True)
def free_points(ind, n):  # pragma: no cover - compiled
    """Points ``0..n-1`` no label holds, ascending."""
    used = np.zeros(n + 1, dtype=np.bool_)
    for lab in range(ind.size):
        used[ind[lab]] = True
    k = 0
    for p in range(n):
        if not used[p]:
            k += 1
    out = np.empty(k, dtype=np.int64)
    k = 0
    for p in range(n):
        if not used[p]:
            out[k] = p
            k += 1
    return out


def warm_up() -> None:
    """Compile (or load) every kernel of this module once."""
    ind = np.array([0, 2], dtype=np.int64)
    pairs = np.array([[0, 1]], dtype=np.int64)
    move_rows(ind, 2, pairs, pairs, free_points(ind, 2), np.ones((2, 3), dtype=np.bool_), True,
              np.zeros(1, dtype=np.int64))
    close_label_pairs(ind, 2, np.zeros((3, 3)), 0.1)


__all__ = ["move_rows", "close_label_pairs", "free_points", "warm_up"]
