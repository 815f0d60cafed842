"""Compiled max-product DP over the DTM's elimination order (:mod:`.dtm_dp`).

The DP's work is small -- a few candidate points per label, a table of a few dozen entries per
triangle -- but written with numpy it paid ten array operations per triangle and per message,
about 4 ms per call at 41 markers, most of an exact region check. Here the two loops are
compiled:

* :func:`grid_keys` -- for each triangle its candidate grid (``|C_A| x |C_B| x |C_C|``) and the
  term-cache key of every entry that keeps the distance bounds and uses no point twice (-1
  elsewhere), so that all terms come from one lookup in the frame's table;
* :func:`dp_solve` -- the elimination (``A_T ... A_1``: each triangle's table plus the messages
  on its edges ``(A, B)``, ``(A, C)``, maximised over ``A`` and sent to ``(B, C)``), the first
  triangle's maximum and the forward pass reading the arg maxima back (eq. 15's order; Song et
  al.'s DP). Triangles whose labels all have one candidate only add constants and are skipped;
* :func:`region_table` -- a region check's candidates (:func:`~.dtm_dp.region_candidates`) as
  the DP reads them, in one loop (in numpy, 25 array operations: 40-60 us a check, a fifth of a
  14-point check's cost besides its terms).

Numba caches each kernel by its own file: :func:`region_table` calls
:func:`~.move_kernels.free_points`, so a change there must touch this file too.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .move_kernels import free_points


@njit(cache=True, nogil=True)
def grid_keys(cand, off, active, tri, dist, bounds, n, T, n1, hbin):  # pragma: no cover - compiled
    """(grid offsets (len(active)+1,), keys (total,)): key -1 where the entry breaks a distance
    bound or uses a point twice."""
    na = active.size
    goff = np.zeros(na + 1, dtype=np.int64)
    for q in range(na):
        t = active[q]
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        goff[q + 1] = goff[q] + (off[a + 1] - off[a]) * (off[b + 1] - off[b]) * (off[c + 1] - off[c])
    keys = np.full(goff[na], -1, dtype=np.int64)
    for q in range(na):
        t = active[q]
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        nb, nc = off[b + 1] - off[b], off[c + 1] - off[c]
        e = goff[q]
        for ia in range(off[a], off[a + 1]):
            pa = cand[ia]
            for ib in range(off[b], off[b + 1]):
                pb = cand[ib]
                okab = dist[pa, pb] <= bounds[a, b] and (pa != pb or pa == n)
                for ic in range(off[c], off[c + 1]):
                    pc = cand[ic]
                    if okab and dist[pa, pc] <= bounds[a, c] and (pa != pc or pa == n) \
                            and dist[pb, pc] <= bounds[b, c] and (pb != pc or pb == n):
                        keys[e] = (((hbin * T + t) * n1 + pa) * n1 + pb) * n1 + pc
                    e += 1
        _ = nb, nc
    return goff, keys


@njit(cache=True, nogil=True)
def dp_solve(vals, goff, active, tri, cand, off, gain, M):  # pragma: no cover - compiled
    """Pick (M,) candidate index per label maximising the sum of the active triangles' tables
    (``vals``: -inf where invalid) plus label gains; (-1, ...) when nothing is valid."""
    na = active.size
    size = off[1:] - off[:-1]
    # message buffers for every edge of the active triangles: (u < v) -> [x_u, x_v]
    eoff = np.full((M, M), -1, dtype=np.int64)
    total = 0
    for q in range(na):
        t = active[q]
        for (u, v) in ((tri[t, 0], tri[t, 1]), (tri[t, 0], tri[t, 2]), (tri[t, 1], tri[t, 2])):
            lo, hi = min(u, v), max(u, v)
            if eoff[lo, hi] < 0:
                eoff[lo, hi] = total
                total += size[lo] * size[hi]
    msg = np.zeros(total)
    best = np.zeros(goff[na], dtype=np.int64)          # arg max over A for each (B, C) entry
    for q in range(na - 1, 0, -1):                      # eliminate A_t of every active triangle but the first
        t = active[q]
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        sa, sb, sc = size[a], size[b], size[c]
        send = eoff[min(b, c), max(b, c)]
        for jb in range(sb):
            for jc in range(sc):
                top = -np.inf
                arg = 0
                for ja in range(sa):
                    x = vals[goff[q] + (ja * sb + jb) * sc + jc] + gain[cand[off[a] + ja]]
                    x += msg[eoff[min(a, b), max(a, b)] + (ja * sb + jb if a < b else jb * sa + ja)]
                    x += msg[eoff[min(a, c), max(a, c)] + (ja * sc + jc if a < c else jc * sa + ja)]
                    if x > top:
                        top = x
                        arg = ja
                best[goff[q] + jb * sc + jc] = arg
                msg[send + (jb * sc + jc if b < c else jc * sb + jb)] += top
    t = active[0]
    a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
    sa, sb, sc = size[a], size[b], size[c]
    top = -np.inf
    xa = xb = xc = -1
    for ja in range(sa):
        for jb in range(sb):
            for jc in range(sc):
                x = vals[goff[0] + (ja * sb + jb) * sc + jc]
                x += gain[cand[off[a] + ja]] + gain[cand[off[b] + jb]] + gain[cand[off[c] + jc]]
                x += msg[eoff[min(a, b), max(a, b)] + (ja * sb + jb if a < b else jb * sa + ja)]
                x += msg[eoff[min(a, c), max(a, c)] + (ja * sc + jc if a < c else jc * sa + ja)]
                x += msg[eoff[min(b, c), max(b, c)] + (jb * sc + jc if b < c else jc * sb + jb)]
                if x > top:
                    top, xa, xb, xc = x, ja, jb, jc
    pick = np.zeros(M, dtype=np.int64)
    if top == -np.inf:
        pick[0] = -1
        return pick
    pick[a], pick[b], pick[c] = xa, xb, xc
    for q in range(1, na):
        t = active[q]
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        pick[a] = best[goff[q] + pick[b] * size[c] + pick[c]]
    return pick


@njit(cache=True, nogil=True)
def region_table(dist, ind, free, allowed, n, k):  # pragma: no cover - compiled
    """(flat, off) of :class:`~.dtm_dp.Candidates` for relabelling the region ``free`` of
    ``ind`` (the rules of :func:`~.dtm_dp.region_candidates`): a kept label its own point; a
    free label "missing" (``n``) and, when it holds a point, the ``k`` pool points nearest that
    point (the pool: every point no kept label holds), else the first ``k`` pool points that
    ``allowed`` (M, n+1; :func:`~.frame_kernels.allowed_points` of the kept labels) lets it take,
    in order of their distance to the region's held points. Ties go as a stable sort orders
    them; each label's points sorted (distinct: the pool's are, and ``n`` is not among them)."""
    M = ind.size
    kept = ind.copy()
    for lab in range(M):
        if free[lab]:
            kept[lab] = n
    pool = free_points(kept, n)
    order = pool                                   # a missing label's order: nearest the region's held points
    held = np.flatnonzero(free & (ind < n))
    if held.size and (free & (ind >= n)).any():
        near = np.full(pool.size, np.inf)
        for lab in held:
            for j in range(pool.size):
                near[j] = min(near[j], dist[pool[j], ind[lab]])
        order = pool[np.argsort(near, kind="mergesort")]
    buf = np.empty((M, k + 1), dtype=np.int64)
    size = np.zeros(M, dtype=np.int64)
    for lab in range(M):
        if not free[lab]:
            buf[lab, 0] = ind[lab]
            size[lab] = 1
            continue
        buf[lab, 0] = n
        c = 1
        if ind[lab] < n:
            nearest = pool[np.argsort(dist[ind[lab]][pool], kind="mergesort")[:k]]
            buf[lab, 1:1 + nearest.size] = nearest
            c += nearest.size
        else:
            for p in order:
                if c > k:
                    break
                if allowed[lab, p]:
                    buf[lab, c] = p
                    c += 1
        buf[lab, :c] = np.sort(buf[lab, :c])
        size[lab] = c
    off = np.zeros(M + 1, dtype=np.int64)
    for lab in range(M):
        off[lab + 1] = off[lab] + size[lab]
    flat = np.empty(off[M], dtype=np.int64)
    for lab in range(M):
        flat[off[lab]:off[lab + 1]] = buf[lab, :size[lab]]
    return flat, off


def warm_up() -> None:
    """Compile (or load) every kernel of this module once."""
    cand = np.array([0, 1, 2, 3], dtype=np.int64)
    off = np.array([0, 1, 2, 4], dtype=np.int64)
    active = np.array([0], dtype=np.int64)
    tri = np.array([[0, 1, 2]], dtype=np.int64)
    dist = np.zeros((4, 4))
    bounds = np.full((3, 3), np.inf)
    goff, keys = grid_keys(cand, off, active, tri, dist, bounds, 3, 1, 4, 0)
    dp_solve(np.zeros(keys.size), goff, active, tri, cand, off, np.zeros(4), 3)
    region_table(dist, np.array([0, 1, 3], dtype=np.int64), np.array([True, False, True]),
                 np.ones((3, 4), dtype=np.bool_), 3, 2)


__all__ = ["grid_keys", "dp_solve", "region_table", "warm_up"]
