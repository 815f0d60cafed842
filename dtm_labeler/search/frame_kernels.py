"""Compiled pieces of one frame's fitness (:class:`~.problem.FrameProblem`), the hot path.

A fitness call scores a few dozen to a few hundred candidate labelings. In numpy each step --
the facing of every candidate, the heading bin, the key of every (bin, triangle, triple), the
lookup of those keys in the frame's term cache, the insertion of new ones, the rotated states
of new triples -- is a handful of array operations with a fixed cost of 5-30 microseconds
each; together they were most of a frame (measured: 45 % of the per-frame CPU at 14 points,
before the mixture kernel itself). Here each is one compiled loop:

* :func:`facing` -- every candidate's yaw from its labelled left/right pairs (the stable pairs
  where any is complete, else any pair, else the hint) and its heading bin, snapped to the
  anchor's within ``snap`` (see :mod:`.problem`);
* :class:`TermTable` -- an open-addressing hash table int64 key -> float64 term for the frame
  (:func:`table_claim`, :func:`table_store`, :func:`table_refill`, :func:`table_grow`), replacing
  a sorted array with ``searchsorted``/``insert``;
* :func:`allowed_points` -- which label may take which point given the rest of a labeling (the
  distance bounds to its triangle neighbours' points), what every move of the fast path asks;
* :func:`frame_geometry` -- each point's observation code and the frame's point distances (the
  row of "missing" and unseen points 0), what every :class:`~.problem.FrameProblem` starts with
  (in numpy 25-50 us a frame at 41 markers, most of building the problem);
* :func:`frame_terms` -- the terms of new triples in one loop: each triple's 18-D canonical
  state rotated about z by its bin's heading on the fly (no per-bin copies of the frame), its
  observation pattern, that pattern's mixture term, the broad part and the edges' body factor.

All are pure functions of arrays, cached on disk by numba (``cache=True``) and compiled when a
model is warmed up (:func:`warm_up`), never on a frame. Numba's cache of a function is keyed on
its own file only: :func:`frame_terms` inlines :func:`~dtm_labeler.model.term_kernel.row_term`,
so a change there must come with a change here (last: row_term's three entries a pass,
2026-12-06) or a checkout keeps running the old compiled kernel.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ..model.term_kernel import log_add_exp, row_term

EMPTY = np.int64(-1)              # free slot of the hash table (keys are non-negative)


@njit(cache=True, nogil=True)
def facing(pop, xy, pairs, mirror_pairs, hint, anchor, snap, nbins):  # pragma: no cover - compiled
    """(bins (P,), yaw (P,)) of candidates ``pop`` (P, M) over points ``xy`` (n+1, 2) (row n =
    missing, NaN). ``anchor`` NaN: no snap."""
    P = pop.shape[0]
    yaw = np.empty(P)
    bins = np.empty(P, dtype=np.int64)
    step = 2.0 * np.pi / nbins
    for r in range(P):
        y = hint
        for which in range(2):
            prs = pairs if which == 0 else mirror_pairs
            sx = 0.0
            sy = 0.0
            have = False
            for q in range(prs.shape[0]):
                a = xy[pop[r, prs[q, 0]]]
                b = xy[pop[r, prs[q, 1]]]
                dx = a[0] - b[0]
                dy = a[1] - b[1]
                if dx == dx and dy == dy:            # both seen (not NaN)
                    sx += dx
                    sy += dy
                    have = True
            if have:
                y = np.arctan2(-sx, sy)
                break
        if anchor == anchor:
            off = np.abs((y - anchor + np.pi) % (2.0 * np.pi) - np.pi)
            if off <= snap:
                y = anchor
        yaw[r] = y
        b = np.int64(np.rint(y / step)) % nbins
        bins[r] = b + nbins if b < 0 else b
    return bins, yaw


@njit(cache=True, nogil=True)
def _slot(keys, key):  # pragma: no cover - compiled
    mask = keys.size - 1
    h = (key * np.int64(0x9E3779B97F4A7C15)) & np.int64(0x7FFFFFFFFFFFFFFF)
    i = h & mask
    while keys[i] != EMPTY and keys[i] != key:
        i = (i + 1) & mask
    return i


@njit(cache=True, nogil=True)
def allowed_points(dist, ind, bounds, n):  # pragma: no cover - compiled
    """(M, n+1): label ``l`` may take point ``p`` given the labeling ``ind`` -- within
    ``bounds[l, m]`` of the point of every label ``m`` it shares a triangle with (finite
    bound); "missing" (column ``n``) always."""
    M = ind.size
    ok = np.ones((M, n + 1), dtype=np.bool_)
    for lab in range(M):
        for m in range(M):
            b = bounds[lab, m]
            if b == np.inf:
                continue
            q = ind[m]
            for p in range(n):
                if ok[lab, p] and dist[p, q] > b:
                    ok[lab, p] = False
    return ok


@njit(cache=True, nogil=True, inline="always")
def _cell_key(pop, bins, tri, ts, n1, T, q):  # pragma: no cover - compiled
    """Term-cache key of cell ``q`` of a population's (P, len(ts)) table, row-major: candidate
    ``pop[r]`` at heading ``bins[r]``, triangle ``ts[c]``."""
    r = q // ts.size
    t = ts[q - r * ts.size]
    return (((bins[r] * T + t) * n1 + pop[r, tri[t, 0]]) * n1 + pop[r, tri[t, 1]]) * n1 + pop[r, tri[t, 2]]


@njit(cache=True, nogil=True, inline="always")
def _read_or_claim(tkeys, tvals, key, out, q, miss, m, room):  # pragma: no cover - compiled
    """``out[q]`` = ``key``'s term where the table has it; else, with ``room`` > 0, the key
    claimed (stored with a NaN term, so that a repeat of it is not claimed again), ``out[q]``
    NaN and the key appended to ``miss`` at ``m``. Returns the misses after, -1 when full."""
    i = _slot(tkeys, key)
    if tkeys[i] == key:
        out[q] = tvals[i]
        return m
    if room == 0:
        return -1
    tkeys[i] = key
    tvals[i] = np.nan
    out[q] = np.nan
    miss[m] = key
    return m + 1


@njit(cache=True, nogil=True)
def table_claim(tkeys, tvals, pop, bins, tri, ts, n1, T, out, miss, start, m, room):  # pragma: no cover - compiled
    """Terms of triangles ``ts`` for candidates ``pop`` (P, M) at ``bins`` into ``out`` (P *
    len(ts),), row-major from cell ``start``, each :func:`_read_or_claim`-ed; stops before the
    ``room + 1``-th claim. Returns (cells done, misses)."""
    full = m + room
    for q in range(start, pop.shape[0] * ts.size):
        m2 = _read_or_claim(tkeys, tvals, _cell_key(pop, bins, tri, ts, n1, T, q), out, q, miss, m, full - m)
        if m2 < 0:
            return q, m
        m = m2
    return pop.shape[0] * ts.size, m


@njit(cache=True, nogil=True)
def table_claim_keys(tkeys, tvals, keys, out, miss, start, m, room):  # pragma: no cover - compiled
    """:func:`table_claim` for arbitrary ``keys``; a negative key has no term: -inf."""
    full = m + room
    for q in range(start, keys.size):
        if keys[q] < 0:
            out[q] = -np.inf
            continue
        m2 = _read_or_claim(tkeys, tvals, keys[q], out, q, miss, m, full - m)
        if m2 < 0:
            return q, m
        m = m2
    return keys.size, m


@njit(cache=True, nogil=True)
def table_store(tkeys, tvals, miss, vals):  # pragma: no cover - compiled
    """The claimed (present) keys ``miss`` given their terms ``vals``."""
    for q in range(miss.size):
        tvals[_slot(tkeys, miss[q])] = vals[q]


@njit(cache=True, nogil=True)
def table_refill_keys(tkeys, tvals, keys, out):  # pragma: no cover - compiled
    """The NaN entries of ``out`` (terms of ``keys``, from :func:`table_claim_keys`) read again."""
    for q in range(out.size):
        if out[q] != out[q]:
            out[q] = tvals[_slot(tkeys, keys[q])]


@njit(cache=True, nogil=True)
def table_refill(tkeys, tvals, pop, bins, tri, ts, n1, T, out):  # pragma: no cover - compiled
    """The NaN entries of ``out`` (from :func:`table_claim`) read again."""
    for q in range(out.size):
        if out[q] != out[q]:
            out[q] = tvals[_slot(tkeys, _cell_key(pop, bins, tri, ts, n1, T, q))]


@njit(cache=True, nogil=True)
def table_grow(tkeys, tvals, capacity):  # pragma: no cover - compiled
    """A table of ``capacity`` slots (a power of two) holding ``tkeys``' entries."""
    keys = np.full(capacity, EMPTY, dtype=np.int64)
    vals = np.empty(capacity)
    for q in range(tkeys.size):
        if tkeys[q] != EMPTY:
            i = _slot(keys, tkeys[q])
            keys[i] = tkeys[q]
            vals[i] = tvals[q]
    return keys, vals


class TermTable:
    """The frame's term cache: key -> term, an open-addressing table (linear probing) that
    grows when half full (:meth:`_claimed`).

    :meth:`terms` asks for many keys at once -- the DP's grid of every candidate triple of a
    region or of the whole body (up to a million keys at 41 markers, most of them new), a
    population's triangles: one compiled pass reads what is there and claims a slot for each
    new key (so a key asked twice is computed once, without sorting), the new keys are
    computed in one call, and a second pass touches only the claimed slots and the cells that
    were missing. Growing copies the live entries in one compiled pass. Measured on six cold
    single-mode searches at 41 markers (CMU 85's breakdance under ``dtm-eval``'s floor-moves
    generic body; 10.2 M new terms, the biggest table 1.66 M): growing and inserting 0.94 ->
    0.33 s (lookups, a sort of the missing keys and a second lookup of every key gone besides),
    the six searches 5-9 % faster in five alternating pairs of runs, the same labelings to the
    bit (``results/fast_path_kernels.md``, 2026-12-06 night)."""

    def __init__(self, capacity: int = 4096):
        if capacity < 2 or capacity & (capacity - 1):
            raise ValueError(f"capacity must be a power of two >= 2, got {capacity}")
        self.keys = np.full(capacity, EMPTY, dtype=np.int64)
        self.vals = np.zeros(capacity)
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def _claimed(self, claim, args: tuple, out: np.ndarray, miss: np.ndarray) -> int:
        """Runs the compiled ``claim(keys, vals, *args, out, miss, start, m, room) -> (cells done,
        misses)`` over ``out``'s cells, growing the table whenever it is half full: to hold the
        cells still to do at the share of them missing so far (a DP grid's new keys arrive in one
        call: one growth, not five doublings), at least twice the size. Returns the misses."""
        cells = out.size
        q = m = 0
        while True:
            q2, m2 = claim(self.keys, self.vals, *args, out, miss, q, m, self.keys.size // 2 - self.size)
            self.size += m2 - m
            if q2 == cells:
                return m2
            rate = (m2 - m) / (q2 - q) if q2 > q else 0.0     # nothing read yet: double
            q, m = q2, m2
            need = 2 * (self.size + int(np.ceil(1.25 * rate * (cells - q))) + 1)
            cap = 2 * self.keys.size
            while cap < need:
                cap *= 2
            self.keys, self.vals = table_grow(self.keys, self.vals, cap)

    def terms(self, keys: np.ndarray, compute) -> np.ndarray:
        """Terms of int64 ``keys`` (any shape, repeats allowed; a negative key -- no triple, e.g.
        outside the distance bounds -- gives -inf); ``compute(new) -> terms`` of the keys not in
        the table yet (each once), which are then stored."""
        keys = np.ascontiguousarray(keys, dtype=np.int64)
        flat = keys.reshape(-1)
        out = np.empty(flat.size)
        miss = np.empty(flat.size, dtype=np.int64)
        m = self._claimed(table_claim_keys, (flat,), out, miss)
        if m:
            self._store(miss[:m], compute)
            table_refill_keys(self.keys, self.vals, flat, out)
        return out.reshape(keys.shape)

    def population_terms(self, pop: np.ndarray, bins: np.ndarray, tri: np.ndarray, ts: np.ndarray,
                         n1: int, T: int, compute) -> np.ndarray:
        """(P, len(ts)) terms of triangles ``ts`` for candidates ``pop`` (P, M) at heading
        ``bins`` (P,): :meth:`terms` of their keys ``((bin T + t) n1 + i) n1 + j) n1 + k``, the
        keys formed in the same compiled pass."""
        out = np.empty(pop.shape[0] * ts.size)
        miss = np.empty(out.size, dtype=np.int64)
        m = self._claimed(table_claim, (pop, bins, tri, ts, n1, T), out, miss)
        if m:
            self._store(miss[:m], compute)
            table_refill(self.keys, self.vals, pop, bins, tri, ts, n1, T, out)
        return out.reshape(pop.shape[0], ts.size)

    def _store(self, miss: np.ndarray, compute) -> None:
        try:
            vals = np.ascontiguousarray(compute(miss), dtype=np.float64)
        except BaseException:
            self.clear()                         # the claimed slots hold no terms: forget everything
            raise
        table_store(self.keys, self.vals, miss, vals)

    def clear(self) -> None:
        """Every entry dropped (the capacity kept)."""
        self.keys.fill(EMPTY)
        self.size = 0


@njit(cache=True, nogil=True)
def frame_geometry(states, full, position_only, missing):  # pragma: no cover - compiled
    """(codes (N,) int8, dist (N, N)) of (N, 6) states: ``full`` where position and velocity are
    finite, ``position_only`` where the position is, else ``missing``; the distances between
    positions, 0 where either is not finite (the last row, "missing", included) -- each the
    same float operations as ``sqrt(((x_i - x_j) ** 2).sum(-1))``."""
    N = states.shape[0]
    codes = np.empty(N, dtype=np.int8)
    seen = np.empty(N, dtype=np.bool_)
    for i in range(N):
        p = True
        for c in range(3):
            if not np.isfinite(states[i, c]):
                p = False
        v = True
        for c in range(3, 6):
            if not np.isfinite(states[i, c]):
                v = False
        seen[i] = p
        codes[i] = (full if v else position_only) if p else missing
    dist = np.zeros((N, N))
    for i in range(N):
        if not seen[i]:
            continue
        for j in range(i + 1, N):
            if not seen[j]:
                continue
            dx = states[i, 0] - states[j, 0]
            dy = states[i, 1] - states[j, 1]
            dz = states[i, 2] - states[j, 2]
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            dist[i, j] = d
            dist[j, i] = d
    return codes, dist


@njit(cache=True, nogil=True)
def frame_terms(keys, states, codes, dist, n1, T, nbins, log_position,
                W, c, cj, cp, nj, np_, mj, mp, off, root,
                bW, bc, bcj, bcp, bnj, bnp, bmj, bmp, boff, log_1mw, log_w,
                e_lo, e_hi, e_w):  # pragma: no cover - compiled
    """Triangle terms of new term-cache keys ``(bin, triangle, i, j, k)``, all in one loop: the
    triple's (18,) state rotated about z by ``-bin 2 pi / nbins`` (unobserved entries 0), its observation
    pattern from the points' ``codes``, the conditional mixture term of that pattern (eq.
    30-31; ``W ... off`` a :class:`~dtm_labeler.model.dtm.StackedTerms`, indexed by pattern),
    mixed with the broad Gaussian's where the model has one (``bW ...``, empty otherwise:
    ``log((1 - w) e^motion + w e^broad)``), the background density of an unmodelled root
    (``root[pid, t] log_position``) and the body factor of the edges the triangle introduces
    (``e_lo``, ``e_hi``, ``e_w`` (T, 3) from :class:`~dtm_labeler.model.body.EdgeTerms`, empty
    without body terms; ``dist`` the frame's (n+1, n+1) point distances, row ``n`` missing).
    The same arithmetic, in the same order, as one batch per pattern
    (:meth:`~dtm_labeler.model.dtm.TriangulatedModel.batched`) plus
    :meth:`~dtm_labeler.model.dtm.TriangulatedModel.edge_terms`, which it replaced on the hot path."""
    m = keys.size
    n = n1 - 1
    out = np.empty(m)
    s = np.zeros(18)
    z = np.empty(W.shape[3])
    q = np.empty(max(cj.shape[2], cp.shape[2]))
    broad = bW.shape[0] > 0
    bz = np.empty(bW.shape[3])
    bq = np.empty(max(bcj.shape[2], bcp.shape[2]))
    edges = e_w.shape[0] > 0
    step = 2.0 * np.pi / nbins
    pts = np.empty(3, dtype=np.int64)
    for r in range(m):
        key = keys[r]
        pts[2] = key % n1
        pts[1] = (key // n1) % n1
        pts[0] = (key // (n1 * n1)) % n1
        rest = key // (n1 * n1 * n1)
        t = rest % T
        b = rest // T
        co = np.cos(-b * step)
        sn = np.sin(-b * step)
        for v in range(3):
            pt = pts[v]
            for blk in range(2):                 # position, velocity
                o = 6 * v + 3 * blk
                x = states[pt, 3 * blk]
                y = states[pt, 3 * blk + 1]
                zz = states[pt, 3 * blk + 2]
                if x == x and y == y and zz == zz:
                    s[o] = co * x - sn * y
                    s[o + 1] = sn * x + co * y
                    s[o + 2] = zz
                else:
                    s[o] = 0.0
                    s[o + 1] = 0.0
                    s[o + 2] = 0.0
        p = codes[pts[0]] + 3 * codes[pts[1]] + 9 * codes[pts[2]]
        val = row_term(s, t, W[p], c[p], cj[p], cp[p], nj[p], np_[p], mj[p], mp[p], off[p], z, q)
        if broad:
            bval = row_term(s, t, bW[p], bc[p], bcj[p], bcp[p], bnj[p], bnp[p], bmj[p], bmp[p], boff[p], bz, bq)
            val = log_add_exp(log_1mw[t] + val, log_w[t] + bval)
        if root[p, t]:
            val += log_position
        if edges:
            acc = 0.0
            for slot in range(3):                # (A, B), (A, C), (B, C), both ends seen
                a = pts[0] if slot < 2 else pts[1]
                e = pts[1] if slot == 0 else pts[2]
                if a < n and e < n:
                    d = dist[a, e]
                    g = max(max(e_lo[t, slot] - d, d - e_hi[t, slot]), 0.0) * e_w[t, slot]
                    acc += g * g
            val += -0.5 * acc
        out[r] = val
    return out


def warm_up() -> None:
    """Compile (or load) every kernel of this module once."""
    pop = np.zeros((1, 3), dtype=np.int64)
    xy = np.zeros((2, 2))
    pairs = np.zeros((1, 2), dtype=np.int64)
    facing(pop, xy, pairs, pairs, 0.0, np.nan, 0.0, 720)
    tab = TermTable(2)
    tri = np.array([[0, 1, 2]], dtype=np.int64)
    ts = np.array([0], dtype=np.int64)
    tab.population_terms(pop, np.zeros(1, dtype=np.int64), tri, ts, 2, 1, np.zeros_like)
    tab.terms(np.arange(3), np.zeros_like)                 # grows
    allowed_points(np.zeros((2, 2)), np.zeros(3, dtype=np.int64), np.full((3, 3), np.inf), 1)
    frame_geometry(np.zeros((2, 6)), 2, 1, 0)
    stack = (np.zeros((1, 1, 18, 1)), np.zeros((1, 1, 1)), np.zeros((1, 1, 1)), np.zeros((1, 1, 1)),
             np.ones((1, 1), dtype=np.int64), np.zeros((1, 1), dtype=np.int64), np.ones(1, dtype=np.int64),
             np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64))
    frame_terms(np.zeros(1, dtype=np.int64), np.zeros((2, 6)), np.zeros(2, dtype=np.int8), np.zeros((2, 2)), 2, 1,
                720, 0.0, *stack, np.zeros((1, 1), dtype=bool), *stack, np.zeros(1), np.zeros(1),
                np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)))


__all__ = ["allowed_points", "facing", "frame_geometry", "TermTable", "table_claim", "table_claim_keys", "table_grow",
           "table_refill", "table_refill_keys", "table_store", "frame_terms", "warm_up"]
