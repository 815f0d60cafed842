"""Constraint-based operators on triangulated-structure strings (section IV.A, eq. 15-17, 22-29).

An individual is a (T, 3) integer array; row ``t`` = ``(A_t, B_t, C_t)`` (see
:mod:`dtm_labeler.model.structure`). The constraints live in one place, :func:`repair`:
walking the triangles in order with the used/unused vertex sets of eq. 16-17, 23-26 and
28-29, a gene that keeps the string valid is kept; one that does not is replaced by a
random admissible value (an unused vertex for a new-vertex gene, an existing edge for a
parent pair). Initialisation, crossover and mutation all end in :func:`repair`, so every
offspring is a valid decomposable triangulation. It is compiled (numba), drawing the same
random numbers as the Python walk it replaced: training at 41 markers spent most of its
structure search walking Python lists (HDM05, 1200 frames: 49 -> 17.5 s; the 14 body points
on every CMU clip 22 -> 18.6 s; the same models).

Domain rule (the paper's "custom rules"): with ``root_pairs`` given, the first triangle must
contain one left/right pair, so a labeling candidate's heading is fixed by its first
triangle (see :mod:`dtm_labeler.search.problem`).
"""
from __future__ import annotations

import numpy as np
from numba import njit


def _edge(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a < b else (b, a)


def root_ok(first: np.ndarray, root_pairs: np.ndarray | None) -> bool:
    """The first triangle ``first`` (3,) holds both vertices of some root pair (always, with none)."""
    return bool(_has_root_pair(np.asarray(first, dtype=np.int64).reshape(3), _pairs(root_pairs)))


def _pairs(root_pairs: np.ndarray | None) -> np.ndarray:
    """(R, 2) int64 root pairs (R = 0 for None)."""
    return np.zeros((0, 2), dtype=np.int64) if root_pairs is None else \
        np.ascontiguousarray(root_pairs, dtype=np.int64).reshape(-1, 2)


@njit(cache=True)
def _has_root_pair(first, root_pairs):  # pragma: no cover - compiled
    if root_pairs.shape[0] == 0:
        return True
    for r in range(root_pairs.shape[0]):
        has_a = has_b = False
        for i in range(3):
            has_a |= first[i] == root_pairs[r, 0]
            has_b |= first[i] == root_pairs[r, 1]
        if has_a and has_b:
            return True
    return False


@njit(cache=True)
def _take(unused, n_unused, used, v):  # pragma: no cover - compiled
    """Vertex ``v`` out of the first ``n_unused`` entries of ``unused`` (order kept) into ``used``;
    returns the new count."""
    k = 0
    while unused[k] != v:
        k += 1
    unused[k:n_unused - 1] = unused[k + 1:n_unused]
    used[v] = True
    return n_unused - 1


@njit(cache=True)
def _add_edge(ea, eb, adj, n_edges, x, y):  # pragma: no cover - compiled
    """Edge (x, y), smaller vertex first, appended at ``n_edges``; returns the new count."""
    lo, hi = min(x, y), max(x, y)
    ea[n_edges], eb[n_edges] = lo, hi
    adj[lo, hi] = adj[hi, lo] = True
    return n_edges + 1


def repair(genes: np.ndarray, n_vertices: int, rng: np.random.Generator,
           root_pairs: np.ndarray | None = None) -> np.ndarray:
    """Smallest change making ``genes`` (T, 3) valid; valid genes are kept as they are."""
    return _repair(np.array(genes, dtype=np.int64).reshape(-1, 3), n_vertices, _pairs(root_pairs), rng)


@njit(cache=True)
def _repair(g, n_vertices, root_pairs, rng):  # pragma: no cover - compiled
    """:func:`repair`, compiled, on ``g`` (T, 3) int64 in place; ``root_pairs`` (R, 2), R = 0 for
    none. The random draws are NumPy's (numba's ``Generator`` shares its bit generator and
    reproduces ``integers``), made in the order and ranges of the Python walk this replaced --
    including one draw of a kept parent per edge while the candidate edges are listed -- so a
    seed gives the structures it always gave (HDM05 41 markers: the same model, trained in 17.5 s
    instead of 49 s)."""
    n = n_vertices
    for t in range(g.shape[0]):
        for i in range(3):
            if g[t, i] < 0 or g[t, i] >= n:
                g[t, i] = -1
    # root rule: keep a proposed vertex that belongs to some pair, put its partner beside it
    R = root_pairs.shape[0]
    if not _has_root_pair(g[0], root_pairs):
        hits = np.empty(R, dtype=np.int64)
        n_hits = 0
        for r in range(R):
            for i in range(3):
                if g[0, i] == root_pairs[r, 0] or g[0, i] == root_pairs[r, 1]:
                    hits[n_hits] = r
                    n_hits += 1
                    break
        r = hits[rng.integers(0, n_hits)] if n_hits > 0 else rng.integers(0, R)
        a, b = root_pairs[r, 0], root_pairs[r, 1]
        third = -1
        for i in range(3):
            if g[0, i] != a and g[0, i] != b and g[0, i] >= 0:
                third = g[0, i]
                break
        g[0, 0], g[0, 1], g[0, 2] = a, b, third
    unused = np.arange(n)
    n_unused = n
    used = np.zeros(n, dtype=np.bool_)
    n_edges_max = 3 + 2 * max(g.shape[0] - 1, 0)
    ea = np.empty(n_edges_max, dtype=np.int64)
    eb = np.empty(n_edges_max, dtype=np.int64)
    adj = np.zeros((n, n), dtype=np.bool_)
    n_edges = 0
    cand = np.empty(n_edges_max, dtype=np.int64)
    # first triangle: three distinct vertices (eq. 16-17)
    for i in range(3):
        v = g[0, i]
        if v < 0 or used[v]:
            v = unused[rng.integers(0, n_unused)]
            g[0, i] = v
        n_unused = _take(unused, n_unused, used, v)
    a, b, c = g[0, 0], g[0, 1], g[0, 2]
    for x, y in ((a, b), (a, c), (b, c)):
        n_edges = _add_edge(ea, eb, adj, n_edges, x, y)
    # later triangles: a new vertex from the unused set, parents an existing edge (eq. 22, 27)
    for t in range(1, g.shape[0]):
        a, b, c = g[t, 0], g[t, 1], g[t, 2]
        if a < 0 or used[a]:
            a = unused[rng.integers(0, n_unused)]
        if b < 0 or c < 0 or b == c or not adj[b, c]:
            # keep one proposed parent if possible and pick a partner it shares an edge with
            keep = np.empty(2, dtype=np.int64)
            n_keep = 0
            for p in (b, c):
                if p >= 0 and used[p]:
                    keep[n_keep] = p
                    n_keep += 1
            n_cand = 0
            if n_keep > 0:
                for e in range(n_edges):
                    p = keep[rng.integers(0, n_keep)]
                    if ea[e] == p or eb[e] == p:
                        cand[n_cand] = e
                        n_cand += 1
            e = cand[rng.integers(0, n_cand)] if n_cand > 0 else rng.integers(0, n_edges)
            b, c = ea[e], eb[e]
        g[t, 0], g[t, 1], g[t, 2] = a, b, c
        n_unused = _take(unused, n_unused, used, a)
        for x in (b, c):
            n_edges = _add_edge(ea, eb, adj, n_edges, a, x)
    return g


def sample(n: int, n_vertices: int, rng: np.random.Generator, root_pairs: np.ndarray | None = None) -> np.ndarray:
    """Constraint-respecting initial population (eq. 15-17): (n, T, 3)."""
    T = n_vertices - 2
    return np.stack([repair(np.full((T, 3), -1), n_vertices, rng, root_pairs) for _ in range(n)])


def crossover(pa: np.ndarray, pb: np.ndarray, n_vertices: int, rng: np.random.Generator,
              root_pairs: np.ndarray | None = None) -> np.ndarray:
    """Two-point exchange on the flat strings (the paper's example), then repair (eq. 22-26)."""
    flat_a, flat_b = pa.reshape(-1), pb.reshape(-1)
    i, j = np.sort(rng.choice(flat_a.size + 1, size=2, replace=False))
    child = flat_a.copy()
    child[i:j] = flat_b[i:j]
    return repair(child.reshape(pa.shape), n_vertices, rng, root_pairs)


def mutate(ind: np.ndarray, n_vertices: int, rng: np.random.Generator, p_mutation: float,
           root_pairs: np.ndarray | None = None) -> np.ndarray:
    """Each gene replaced by a random vertex with probability ``p_mutation``, then repair (eq. 27-29)."""
    flat = ind.reshape(-1).copy()
    hit = rng.random(flat.size) < p_mutation
    if not hit.any():
        return ind.copy()
    flat[hit] = rng.integers(n_vertices, size=int(hit.sum()))
    return repair(flat.reshape(ind.shape), n_vertices, rng, root_pairs)


# -- the simple GA's unconstrained operators (baseline) ---------------------------------
def crossover_plain(pa: np.ndarray, pb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    flat_a, flat_b = pa.reshape(-1), pb.reshape(-1)
    i, j = np.sort(rng.choice(flat_a.size + 1, size=2, replace=False))
    child = flat_a.copy()
    child[i:j] = flat_b[i:j]
    return child.reshape(pa.shape)


def mutate_plain(ind: np.ndarray, n_vertices: int, rng: np.random.Generator, p_mutation: float) -> np.ndarray:
    flat = ind.reshape(-1).copy()
    hit = rng.random(flat.size) < p_mutation
    flat[hit] = rng.integers(n_vertices, size=int(hit.sum()))
    return flat.reshape(ind.shape)


def reattachments(ind: np.ndarray, n_vertices: int, rng: np.random.Generator,
                  root_pairs: np.ndarray | None = None) -> np.ndarray:
    """Every structure one re-attachment away: triangle ``t``'s new vertex hung on another
    edge that exists before ``t`` (then :func:`repair`), for all ``t > 0``; also the new
    vertices of consecutive triangles exchanged. The local refinement of CBGA's best."""
    out = []
    g = np.asarray(ind, dtype=np.int64)
    edges_before = set()
    a, b, c = (int(x) for x in g[0])
    edges_before |= {_edge(a, b), _edge(a, c), _edge(b, c)}
    for t in range(1, g.shape[0]):
        for e in sorted(edges_before):
            if e != _edge(int(g[t, 1]), int(g[t, 2])):
                cand = g.copy()
                cand[t, 1:] = e
                out.append(repair(cand, n_vertices, rng, root_pairs))
        if t + 1 < g.shape[0]:
            cand = g.copy()
            cand[[t, t + 1], 0] = cand[[t + 1, t], 0]
            out.append(repair(cand, n_vertices, rng, root_pairs))
        a, b, c = (int(x) for x in g[t])
        edges_before |= {_edge(a, b), _edge(a, c)}
    return np.stack(out) if out else g[None]
