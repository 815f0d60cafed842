"""Constraint-based GA operators on label assignments (section IV.A applied to labeling).

An individual is an int array of length M (model labels); entry ``l`` is the index of the
point given label ``l`` or ``n`` (= number of points) when the label is *missing*
(occluded). The constraints are: every entry in ``0..n``; a point carries at most one
label (each label has at most one point by construction); points not used are clutter.
They are enforced in one place, :func:`repair`, in the spirit of eq. 22-29: a gene that
conflicts is replaced by a value from the *unused* set (or "missing" when none is left).

All functions act on a whole population ``(P, M)`` at once: loops run over labels or
candidate moves, never over individuals or points.
"""
from __future__ import annotations

import numpy as np


def sample(P: int, M: int, n: int, rng: np.random.Generator, p_missing: float = 0.0) -> np.ndarray:
    """Random valid assignments: a random injective map labels -> points (eq. 15-17 analogue)."""
    width = max(n, M)
    pop = np.argsort(rng.random((P, width)), axis=1)[:, :M]
    pop = np.where(pop >= n, n, pop)
    if p_missing > 0:
        pop[rng.random((P, M)) < p_missing] = n
    return pop.astype(np.int64)


def used_mask(pop: np.ndarray, n: int) -> np.ndarray:
    """(P, n) True where a point carries a label."""
    used = np.zeros((pop.shape[0], n + 1), dtype=bool)
    np.put_along_axis(used, pop, True, axis=1)
    return used[:, :n]


def repair(pop: np.ndarray, n: int, rng: np.random.Generator, fill: bool = True) -> np.ndarray:
    """Make every row a valid assignment.

    Out-of-range values become missing. When a point is claimed by several labels, one
    (chosen at random) keeps it; the others get a random *unused* point (``fill``) or become
    missing. Valid rows come back unchanged.
    """
    pop = np.array(pop, dtype=np.int64)
    P, M = pop.shape
    pop[(pop < 0) | (pop > n)] = n
    noise = rng.random((P, M))          # drawn either way: the random stream does not depend on the rows
    if is_valid(pop, n).all():
        return pop                      # valid rows (the labeler's seed, nearly every frame): nothing to do
    # duplicates: order each row by (value, random key); a repeat of the previous value loses
    key = pop * 2.0 + noise
    order = np.argsort(key, axis=1)
    sorted_vals = np.take_along_axis(pop, order, axis=1)
    dup_sorted = np.zeros_like(sorted_vals, dtype=bool)
    dup_sorted[:, 1:] = (sorted_vals[:, 1:] == sorted_vals[:, :-1]) & (sorted_vals[:, 1:] < n)
    losers = np.zeros_like(dup_sorted)
    np.put_along_axis(losers, order, dup_sorted, axis=1)
    if not losers.any():
        return pop
    pop[losers] = n
    if fill and n > 0:
        used = used_mask(pop, n)
        # unused points in random order first
        cand = np.argsort(used + rng.random((P, n)), axis=1)            # unused (0.x) before used (1.x)
        n_free = (~used).sum(1)
        rank = np.cumsum(losers, axis=1) - 1                             # k-th loser of its row
        ok = losers & (rank < n_free[:, None])
        rows, cols = np.nonzero(ok)
        pop[rows, cols] = cand[rows, rank[rows, cols]]
    return pop


def crossover(pa: np.ndarray, pb: np.ndarray, order: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Two-point exchange along the structure's vertex order (labels of one limb stay
    together), then :func:`repair` (eq. 22-26)."""
    P, M = pa.shape
    pos = np.empty(M, dtype=np.int64)
    pos[order] = np.arange(M)
    ij = np.sort(rng.integers(0, M + 1, size=(P, 2)), axis=1)
    mask = (pos[None, :] >= ij[:, :1]) & (pos[None, :] < ij[:, 1:])
    return repair(np.where(mask, pb, pa), n, rng)


def mutate(pop: np.ndarray, n: int, rng: np.random.Generator, p_mutation: float,
           p_missing: float = 0.05, pairs: np.ndarray | None = None, p_mirror: float = 0.05) -> np.ndarray:
    """Constraint-based mutation (eq. 27-29): each selected individual gets one move that
    keeps it valid -- give a label a random point (swapping with the label holding it, if
    any), or swap two labels, or mark a label missing; with ``pairs``, a few individuals are
    mirrored as a whole (:func:`mirror`)."""
    pop = pop.copy()
    if pairs is not None and len(pairs):
        flip = rng.random(pop.shape[0]) < p_mirror
        pop[flip] = mirror(pop[flip], pairs)
    P, M = pop.shape
    hit = np.flatnonzero(rng.random(P) < p_mutation)
    if hit.size == 0:
        return pop
    lab = rng.integers(0, M, size=hit.size)
    kind = rng.random(hit.size)
    target = rng.integers(0, n + 1, size=hit.size) if n > 0 else np.zeros(hit.size, dtype=np.int64)
    other = rng.integers(0, M, size=hit.size)
    # swap two labels
    sw = kind < 0.35
    a, b = pop[hit[sw], lab[sw]], pop[hit[sw], other[sw]]
    pop[hit[sw], lab[sw]], pop[hit[sw], other[sw]] = b, a
    # missing
    ms = (kind >= 0.35) & (kind < 0.35 + p_missing)
    pop[hit[ms], lab[ms]] = n
    # give a point (swap with its holder)
    gv = kind >= 0.35 + p_missing
    rows, labs, pts = hit[gv], lab[gv], target[gv]
    holder = (pop[rows] == pts[:, None]) & (pts[:, None] < n)            # (k, M)
    has = holder.any(1)
    hl = holder.argmax(1)
    old = pop[rows, labs]
    pop[rows[has], hl[has]] = old[has]
    pop[rows, labs] = pts
    return pop


def mirror(pop: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Swap the points of every left/right label pair at once (always valid).

    The body seen from behind with left and right exchanged is a strong local optimum
    (heading flipped by 180 deg, every limb mirrored); no single swap leaves it, this does.
    """
    out = np.array(pop, copy=True)
    if len(pairs):
        out[..., pairs[:, 0]], out[..., pairs[:, 1]] = pop[..., pairs[:, 1]], pop[..., pairs[:, 0]]
    return out


def neighbourhood(ind: np.ndarray, n: int, with_missing: bool = True,
                  pairs: np.ndarray | None = None, allowed: np.ndarray | None = None) -> np.ndarray:
    """Every individual one move away from ``ind``: all label swaps, every label given every
    point (swapping with its holder) and, optionally, every label made missing."""
    M = ind.shape[0]
    i, j = np.triu_indices(M, 1)
    if allowed is not None:       # (M, n+1): label may take point (domain constraint)
        keep = allowed[i, ind[j]] & allowed[j, ind[i]]
        i, j = i[keep], j[keep]
    swaps = np.repeat(ind[None], i.size, 0)
    swaps[np.arange(i.size), i], swaps[np.arange(i.size), j] = ind[j], ind[i]
    lab, pt = np.meshgrid(np.arange(M), np.arange(n), indexing="ij")
    lab, pt = lab.ravel(), pt.ravel()
    keep = ind[lab] != pt
    holder = np.full(n + 1, -1)
    holder[ind[ind < n]] = np.flatnonzero(ind < n)
    if allowed is not None:
        hh = holder[pt]
        keep &= allowed[lab, pt] & ((hh < 0) | allowed[np.maximum(hh, 0), ind[lab]])
    lab, pt = lab[keep], pt[keep]
    moves = np.repeat(ind[None], lab.size, 0)
    h = holder[pt]
    r = np.arange(lab.size)
    moves[r[h >= 0], h[h >= 0]] = ind[lab[h >= 0]]
    moves[r, lab] = pt
    out = [swaps, moves]
    if pairs is not None and len(pairs):
        out.append(mirror(ind[None], pairs))
    if with_missing:
        out.append(releases(ind, n))
    return np.concatenate(out, axis=0)


def releases(ind: np.ndarray, n: int) -> np.ndarray:
    """(L, M) ``ind`` with each of its L labelled labels left on no point (``n``), in label order."""
    present = np.flatnonzero(ind < n)
    rows = np.repeat(ind[None], present.size, 0)
    rows[np.arange(present.size), present] = n
    return rows


# -- the simple GA's unconstrained operators (baseline) --------------------------------
def crossover_plain(pa: np.ndarray, pb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    P, M = pa.shape
    ij = np.sort(rng.integers(0, M + 1, size=(P, 2)), axis=1)
    pos = np.arange(M)
    mask = (pos[None, :] >= ij[:, :1]) & (pos[None, :] < ij[:, 1:])
    return np.where(mask, pb, pa)


def mutate_plain(pop: np.ndarray, n: int, rng: np.random.Generator, p_gene: float,
                 swap: bool = False) -> np.ndarray:
    """The simple GA's mutation: random genes get random values (no repair). With ``swap``,
    half of the mutated genes exchange values with another random gene instead -- the
    textbook permutation mutation, valid by itself -- so the baseline is not crippled by
    the death penalty when every point is in use."""
    pop = pop.copy()
    hit = rng.random(pop.shape) < p_gene
    if swap:
        r, c = np.nonzero(hit)
        do = rng.random(r.size) < 0.5
        other = rng.integers(0, pop.shape[1], size=int(do.sum()))
        a, b = pop[r[do], c[do]].copy(), pop[r[do], other].copy()
        pop[r[do], c[do]], pop[r[do], other] = b, a
        hit[r[do], c[do]] = False
    pop[hit] = rng.integers(0, n + 1, size=int(hit.sum()))
    return pop


def is_valid(pop: np.ndarray, n: int) -> np.ndarray:
    """(P,) True where each point is used at most once and values are in 0..n."""
    pop = np.asarray(pop)
    in_range = ((pop >= 0) & (pop <= n)).all(1)
    s = np.sort(np.where(pop >= n, -1 - np.arange(pop.shape[1]), pop), axis=1)
    distinct = (np.diff(s, axis=1) != 0).all(1)
    return in_range & distinct


def chain_shifts(ind: np.ndarray, n: int, chains: list[np.ndarray], allowed: np.ndarray | None = None,
                 start: np.ndarray | None = None, free: np.ndarray | None = None) -> np.ndarray:
    """Every labeling one *chain shift* away from ``ind`` (M,): for a chain of labels
    ``(c_0, ..., c_k)`` (``chains``: one (C, k+1) array per chain length), each label takes the
    point of the next one, ``c_i <- ind[c_{i+1}]``; ``c_0``'s point (if any) is freed and the
    last label is left missing or takes that freed point (a rotation). A chain whose labels
    ``c_1 .. c_k`` do not all hold points is skipped (nothing to shift), and so is one whose
    ``c_0`` is not in ``start`` (M,) bool, if given, or a shift that ``allowed`` (M, n+1), if
    given, forbids for some step. Chains listed in both orders give the shift forward and
    backward. With ``free`` (the points no label of ``ind`` holds), each shift is also given
    with its last label on each of them (where ``allowed``): the shift *completed* -- a limb's
    labels passed one marker along leave its end marker unlabelled, and the shift back is only
    better than the carried labeling once that marker has its label again. Always valid
    assignments (a permutation of the chain's points, one possibly dropped or replaced by a
    free point)."""
    out = []
    for ch in chains:
        if start is not None:
            ch = ch[start[ch[:, 0]]]
        if not len(ch):
            continue
        nxt = ind[ch[:, 1:]]                                     # (C, k) the points taken
        ok = (nxt < n).all(1)
        if allowed is not None:
            ok &= allowed[ch[:, :-1], nxt].all(1)
        ch, nxt = ch[ok], nxt[ok]
        if not len(ch):
            continue
        r = np.arange(len(ch))[:, None]
        shifted = np.repeat(ind[None], len(ch), 0)
        shifted[r, ch[:, :-1]] = nxt
        shifted[r[:, 0], ch[:, -1]] = n                          # the last label left missing
        out.append(shifted)
        first = ind[ch[:, 0]]
        rot = first < n
        if allowed is not None:
            rot &= allowed[ch[:, -1], first]
        if rot.any():
            rotated = shifted[rot]
            rotated[np.arange(len(rotated)), ch[rot, -1]] = first[rot]
            out.append(rotated)
        if free is not None and len(free):
            last = ch[:, -1]
            fits = np.ones((len(ch), len(free)), dtype=bool) if allowed is None else allowed[last[:, None], free[None]]
            rows, pts = np.nonzero(fits)
            if rows.size:
                completed = shifted[rows]
                completed[np.arange(rows.size), last[rows]] = free[pts]
                out.append(completed)
    return np.concatenate(out) if out else np.zeros((0, ind.size), dtype=np.int64)
