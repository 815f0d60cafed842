"""Compiled kernels of the clusters' handedness (:class:`~dtm_labeler.model.body.Handedness`),
the marker bars' order (:class:`~dtm_labeler.model.body.BarOrder`) and the trunk's twist limit
(:class:`~dtm_labeler.model.body.TrunkTwist`).

A fitness call scores up to a few hundred candidate labelings; at 41 markers a calibrated body
holds some 70 quadruples, so each call takes the signed volume of 10^4 point quadruples. In
numpy that was a gather of (P, Q, 4, 3) points, a cross product and an einsum over them: 1.4 ms
per frame, more than every triangle term of the frame (HDM05, 41 markers, calibrated). Here one
loop reads each quadruple's four points where they lie and counts the mirrored ones.

The twist limit is one cosine per row; in numpy (gathers, fall-backs, norms) it cost 58 us a
call whatever the number of rows (the fast path makes 2-4 calls a frame at 14 points with
flicker, a search many more); compiled, 2-12 us for 1-300 rows. Paired offline runs (demo walker,
2 flickering + 2 ghosts, inline, CPU time per frame, median of 3): p50 1.97 ms with the factor,
2.02 ms without; the labels are the same.

Rows against the first. A fitness call's candidates are mostly one to three labels away from
its first row -- the hill-climb's moves of the carried labeling, the confidence's releases of
each label, a cluster's turns -- and a label touches a few dozen of the ~740 rigid pairs and ~70
quadruples of a calibrated 41-marker body. So :func:`pair_factors` and :func:`mirrored_quads`
score the first row in full and every other row as the first's total with the pairs (quadruples)
of its changed labels taken out and scored again (:func:`label_members` lists them per label);
a row that changes so many labels that this is no cheaper is scored in full. Counts are exact;
the pair sums agree with a full sum to rounding (1e-12 nats).
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _diff(pts, a, b):  # pragma: no cover - compiled
    """``pts[b] - pts[a]`` as three scalars (NaN where either point is missing)."""
    return pts[b, 0] - pts[a, 0], pts[b, 1] - pts[a, 1], pts[b, 2] - pts[a, 2]


def label_members(items: np.ndarray, n_labels: int) -> tuple[np.ndarray, np.ndarray]:
    """``(ptr, members)``: the rows of ``items`` (K, k) label indices that hold each label,
    ``members[ptr[l]:ptr[l + 1]]`` for label ``l`` (a row holding it twice listed once)."""
    items = np.asarray(items, dtype=np.int64)
    ptr = np.zeros(n_labels + 1, dtype=np.int64)
    if not items.size:
        return ptr, np.zeros(0, dtype=np.int64)
    items = items.reshape(items.shape[0], -1)
    rows = np.repeat(np.arange(items.shape[0]), items.shape[1])
    pair = np.unique(np.stack([items.reshape(-1), rows], 1), axis=0)
    np.add.at(ptr, pair[:, 0] + 1, 1)
    return np.cumsum(ptr), np.ascontiguousarray(pair[:, 1], dtype=np.int64)


@njit(cache=True, nogil=True, inline="always")
def _row_work(pop, p, ptr):  # pragma: no cover - compiled
    """How many items (pairs, quadruples) the labels in which row ``p`` of ``pop`` differs from
    row 0 hold, counted with repeats: a row past the items' number is scored in full."""
    work = 0
    for m in range(pop.shape[1]):
        if pop[p, m] != pop[0, m]:
            work += ptr[m + 1] - ptr[m]
    return work


@njit(cache=True, nogil=True, inline="always")
def _changed_items(pop, p, ptr, members, seen, buf):  # pragma: no cover - compiled
    """The items held by the labels in which row ``p`` of ``pop`` differs from row 0, each
    once (``seen`` marks them with ``p``), written to ``buf``; returns their count."""
    count = 0
    for m in range(pop.shape[1]):
        if pop[p, m] == pop[0, m]:
            continue
        for j in range(ptr[m], ptr[m + 1]):
            k = members[j]
            if seen[k] != p:
                seen[k] = p
                buf[count] = k
                count += 1
    return count


@njit(cache=True, nogil=True, inline="always")
def _mirrored(idx, p, pts, quads, sign, q):  # pragma: no cover - compiled
    """1 when row ``p`` shows quadruple ``q`` with the sign opposite to ``sign[q]``, else 0."""
    u0, u1, u2 = _diff(pts, idx[p, quads[q, 0]], idx[p, quads[q, 1]])
    v0, v1, v2 = _diff(pts, idx[p, quads[q, 0]], idx[p, quads[q, 2]])
    w0, w1, w2 = _diff(pts, idx[p, quads[q, 0]], idx[p, quads[q, 3]])
    vol = (u1 * v2 - u2 * v1) * w0 + (u2 * v0 - u0 * v2) * w1 + (u0 * v1 - u1 * v0) * w2
    return 1 if vol * sign[q] < 0 else 0     # NaN compares False


@njit(cache=True, nogil=True)
def mirrored_quads(idx, pts, quads, sign, ptr, members):  # pragma: no cover - compiled
    """(P,) number of quadruples each row of ``idx`` (P, M) shows mirrored: for quadruple ``q``
    (label indices ``quads[q]``), the points ``pts[idx[p, quads[q]]]`` (N, 3) whose signed
    volume ``det[x_b - x_a, x_c - x_a, x_d - x_a]`` has the sign opposite to ``sign[q]``; a NaN
    point (missing) leaves the quadruple unmirrored. Rows after the first: against it (module
    doc; ``ptr``, ``members``: :func:`label_members` of ``quads``)."""
    P, Q = idx.shape[0], quads.shape[0]
    out = np.zeros(P, dtype=np.int64)
    if P == 0:
        return out
    base = np.empty(Q, dtype=np.int64)
    for q in range(Q):
        base[q] = _mirrored(idx, 0, pts, quads, sign, q)
        out[0] += base[q]
    seen, buf = np.zeros(Q, dtype=np.int64), np.empty(Q, dtype=np.int64)
    for p in range(1, P):
        if _row_work(idx, p, ptr) >= Q:
            for q in range(Q):
                out[p] += _mirrored(idx, p, pts, quads, sign, q)
            continue
        out[p] = out[0]
        for i in range(_changed_items(idx, p, ptr, members, seen, buf)):
            out[p] += _mirrored(idx, p, pts, quads, sign, buf[i]) - base[buf[i]]
    return out


@njit(cache=True, nogil=True, inline="always")
def _twist_cosine(idx, p, pts, tw, k):  # pragma: no cover - compiled
    """Cosine of the shoulder axis (right - left; with a shoulder missing, its half through the
    mid point, if any) and the hip axis (right - left) of row ``p`` of ``idx`` for twist row
    ``tw[k]`` (left shoulder, mid or -1, right shoulder, left hip, right hip); NaN when either
    axis is not seen."""
    h0, h1, h2 = _diff(pts, idx[p, tw[k, 3]], idx[p, tw[k, 4]])
    if not (h0 == h0 and h1 == h1 and h2 == h2):
        return np.nan
    a, b = idx[p, tw[k, 0]], idx[p, tw[k, 2]]
    if not (pts[a, 0] == pts[a, 0] and pts[b, 0] == pts[b, 0]):
        if tw[k, 1] < 0:
            return np.nan
        mid = idx[p, tw[k, 1]]
        if not pts[mid, 0] == pts[mid, 0]:
            return np.nan
        if pts[b, 0] == pts[b, 0]:
            a = mid
        elif pts[a, 0] == pts[a, 0]:
            b = mid
        else:
            return np.nan
    s0, s1, s2 = _diff(pts, a, b)
    norm = np.sqrt((s0 * s0 + s1 * s1 + s2 * s2) * (h0 * h0 + h1 * h1 + h2 * h2))
    if not norm > 0:
        return np.nan
    return (s0 * h0 + s1 * h1 + s2 * h2) / norm


@njit(cache=True, nogil=True)
def twist_cosines(idx, pts, twists):  # pragma: no cover - compiled
    """(P, K) cosine of each twist row's shoulder and hip axes (:func:`_twist_cosine`) for each
    row of ``idx`` (P, M: label -> row of ``pts`` (N, 3); NaN = missing)."""
    out = np.empty((idx.shape[0], twists.shape[0]))
    for p in range(idx.shape[0]):
        for k in range(twists.shape[0]):
            out[p, k] = _twist_cosine(idx, p, pts, twists, k)
    return out


@njit(cache=True, nogil=True)
def twist_factors(idx, pts, twists, cos_min, cos_sd):  # pragma: no cover - compiled
    """(P,) summed twist factors ``-1/2 (max(0, cos_min - c) / cos_sd)^2`` of each row of ``idx``
    over ``twists``, ``c`` the cosine of :func:`_twist_cosine`; no axis: no factor."""
    out = np.zeros(idx.shape[0])
    for p in range(idx.shape[0]):
        total = 0.0
        for k in range(twists.shape[0]):
            x = (cos_min - _twist_cosine(idx, p, pts, twists, k)) / cos_sd
            if x > 0:                            # NaN compares False
                total -= 0.5 * x * x
        out[p] = total
    return out


@njit(cache=True, nogil=True)
def reversed_orders(idx, pts, orders):  # pragma: no cover - compiled
    """(P,) number of bar orders each row of ``idx`` (P, M) shows reversed: for order ``k``
    (label indices ``orders[k] = (x, near, far)``), the point of ``x`` farther from the point of
    ``near`` than from the point of ``far``; a NaN point (missing) leaves the order as it is."""
    out = np.zeros(idx.shape[0], dtype=np.int64)
    for p in range(idx.shape[0]):
        count = 0
        for k in range(orders.shape[0]):
            x = idx[p, orders[k, 0]]
            a0, a1, a2 = _diff(pts, x, idx[p, orders[k, 1]])
            b0, b1, b2 = _diff(pts, x, idx[p, orders[k, 2]])
            if a0 * a0 + a1 * a1 + a2 * a2 > b0 * b0 + b1 * b1 + b2 * b2:    # NaN compares False
                count += 1
        out[p] = count
    return out


@njit(cache=True, nogil=True, inline="always")
def _pair_square(pop, p, dist, n, pairs, lo, hi, inv_sd, k):  # pragma: no cover - compiled
    """``(max(0, lo - d, d - hi) / sd)^2`` of pair ``k`` in row ``p`` (0 when an end is missing)."""
    a = pop[p, pairs[k, 0]]
    b = pop[p, pairs[k, 1]]
    if a >= n or b >= n:
        return 0.0
    d = dist[a, b]
    x = max(lo[k] - d, d - hi[k], 0.0) * inv_sd[k]
    return x * x


@njit(cache=True, nogil=True)
def pair_factors(pop, dist, n, pairs, lo, hi, inv_sd, ptr, members):  # pragma: no cover - compiled
    """(P,) summed dead-zone quadratics ``-1/2 (max(0, lo - d, d - hi) / sd)^2`` of the label
    pairs ``pairs`` (K, 2) for each row of ``pop`` (P, M) (``n`` = missing: the pair drops),
    ``d`` read from the frame's point distances ``dist`` (n+1, n+1) (:class:`~dtm_labeler.model.body.CrossSegments`).
    A calibrated 41-marker body holds some 740 pairs off the edges: in numpy the gathers cost
    54 us for one row and 1.4 ms for 60. Rows after the first: against it (module doc;
    ``ptr``, ``members``: :func:`label_members` of ``pairs``)."""
    P, K = pop.shape[0], pairs.shape[0]
    out = np.zeros(P)
    if P == 0:
        return out
    base = np.empty(K)
    total = 0.0
    for k in range(K):
        base[k] = _pair_square(pop, 0, dist, n, pairs, lo, hi, inv_sd, k)
        total += base[k]
    out[0] = -0.5 * total
    seen, buf = np.zeros(K, dtype=np.int64), np.empty(K, dtype=np.int64)
    for p in range(1, P):
        acc = 0.0
        if _row_work(pop, p, ptr) >= K:
            for k in range(K):
                acc += _pair_square(pop, p, dist, n, pairs, lo, hi, inv_sd, k)
        else:
            acc = total
            for i in range(_changed_items(pop, p, ptr, members, seen, buf)):
                acc += _pair_square(pop, p, dist, n, pairs, lo, hi, inv_sd, buf[i]) - base[buf[i]]
        out[p] = -0.5 * acc
    return out


__all__ = ["label_members", "mirrored_quads", "pair_factors", "reversed_orders", "twist_cosines", "twist_factors"]
