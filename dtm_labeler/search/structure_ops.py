"""Constraint-based operators on triangulated-structure strings (section IV.A, eq. 15-17, 22-29).

An individual is a (T, 3) integer array; row ``t`` = ``(A_t, B_t, C_t)`` (see
:mod:`dtm_labeler.model.structure`). The constraints live in one place, :func:`repair`:
walking the triangles in order with the used/unused vertex sets of eq. 16-17, 23-26 and
28-29, a gene that keeps the string valid is kept; one that does not is replaced by a
random admissible value (an unused vertex for a new-vertex gene, an existing edge for a
parent pair). Initialisation, crossover and mutation all end in :func:`repair`, so every
offspring is a valid decomposable triangulation.

Domain rule (the paper's "custom rules"): with ``root_pairs`` given, the first triangle must
contain one left/right pair, so a labeling candidate's heading is fixed by its first
triangle (see :mod:`dtm_labeler.search.problem`).
"""
from __future__ import annotations

import numpy as np


def _edge(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a < b else (b, a)


def root_ok(first: np.ndarray, root_pairs: np.ndarray | None) -> bool:
    if root_pairs is None or len(root_pairs) == 0:
        return True
    f = set(int(v) for v in first)
    return any(int(a) in f and int(b) in f for a, b in root_pairs)


def repair(genes: np.ndarray, n_vertices: int, rng: np.random.Generator,
           root_pairs: np.ndarray | None = None) -> np.ndarray:
    """Smallest change making ``genes`` (T, 3) valid; valid genes are kept as they are."""
    g = np.array(genes, dtype=np.int64).reshape(-1, 3)
    g = np.where((g < 0) | (g >= n_vertices), -1, g)
    if not root_ok(g[0], root_pairs):
        # keep a proposed vertex that belongs to some pair, put its partner beside it
        rp = np.asarray(root_pairs)
        hits = [p for p in rp if p[0] in g[0] or p[1] in g[0]]
        a, b = hits[rng.integers(len(hits))] if hits else rp[rng.integers(len(rp))]
        third = [v for v in g[0] if v not in (a, b) and v >= 0]
        g[0] = (a, b, third[0] if third else -1)
    unused = list(range(n_vertices))
    used: list[int] = []
    edges: list[tuple[int, int]] = []
    edge_set: set[tuple[int, int]] = set()

    def take(v: int) -> None:
        unused.remove(v)
        used.append(v)

    # first triangle: three distinct vertices (eq. 16-17)
    for i in range(3):
        v = int(g[0, i])
        if v not in unused:
            v = unused[rng.integers(len(unused))]
            g[0, i] = v
        take(v)
    a, b, c = (int(x) for x in g[0])
    for e in (_edge(a, b), _edge(a, c), _edge(b, c)):
        edges.append(e)
        edge_set.add(e)
    # later triangles: a new vertex from the unused set, parents an existing edge (eq. 22, 27)
    for t in range(1, g.shape[0]):
        a, b, c = (int(x) for x in g[t])
        if a not in unused:
            a = unused[rng.integers(len(unused))]
        if b == c or _edge(b, c) not in edge_set:
            # keep one proposed parent if possible and pick a partner it shares an edge with
            keep = [p for p in (b, c) if p in used]
            cand = [e for e in edges if keep and keep[rng.integers(len(keep))] in e] if keep else []
            b, c = cand[rng.integers(len(cand))] if cand else edges[rng.integers(len(edges))]
        g[t] = (a, b, c)
        take(a)
        for e in (_edge(a, b), _edge(a, c)):
            edges.append(e)
            edge_set.add(e)
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
