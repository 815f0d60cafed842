"""Structure search at training time: CBGA, simple GA, greedy (Song et al.), given.

Fitness (eq. 18-20): the log-likelihood of the training frames under the structure,

    f(G) = sum_frames [ log P(A0,B0,C0) + sum_{t>0} ( log P(A_t,B_t,C_t) - log P(B_t,C_t) ) ]

scored with a maximum-likelihood Gaussian per triple (the entropy form of eq. 5,
``-n h(.)``). Every triple's and pair's log-likelihood is computed once, vectorised over all
``C(n,3)`` triples from the joint covariance of the point states, so one candidate
structure costs a table lookup and the GA can afford thousands of evaluations. The per-
triangle mixtures are fitted afterwards for the chosen structure only.

Structure prior (issue 13). Eq. 2-3 take equal priors ``P(G)``. With body terms (see
:mod:`dtm_labeler.model.body`) a structure can only use a segment -- a bone, a marker cluster
on one segment -- if that pair is one of its edges, so :meth:`TripleScores.with_edge_prior`
puts a prior on the edges: ``log P(G) = F sum_{edges e of G} beta_e`` (``F`` training
frames; every edge counted once, by the triangle that introduces it), which favours
structures that carry the body's segments over ones that join points only a recorded
motion happened to move together.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..model.features import FEATURE_MATRIX, FULL, MISSING, STATE_DIM, observed_map
from ..model.structure import Structure, is_valid
from . import structure_ops as ops
from .evolve import Island, evolve
from .ga import Termination

LOG_2PI = float(np.log(2 * np.pi))
UNUSABLE_PER_FRAME = -1e4     # nats per frame of a triple the training frames hardly show


@dataclass
class TripleScores:
    """Log-likelihood of every triple (15-D eq. 12 feature) and pair (9-D) under ML Gaussians."""

    triple: np.ndarray       # (n, n, n), symmetric
    pair: np.ndarray         # (n, n), symmetric
    n_frames: int
    usable: np.ndarray | None = None   # (n, n, n) bool: triples a structure may use (None: all)
    edge_prior: np.ndarray | None = None    # (n, n) log prior per edge and frame (beta_e), symmetric

    @classmethod
    def from_states(cls, states: np.ndarray, reg_covar: float = 1e-6) -> "TripleScores":
        """``states`` (F, n, 6): canonicalised, fully observed training frames."""
        F, n, _ = states.shape
        if F < 2:
            raise ValueError("structure search needs at least 2 complete frames")
        x = states.reshape(F, n * STATE_DIM)
        return cls.from_covariance(np.cov(x, rowvar=False, bias=True), F, reg_covar)

    @classmethod
    def from_covariance(cls, S: np.ndarray, n_frames: int, reg_covar: float = 1e-6,
                        usable: np.ndarray | None = None) -> "TripleScores":
        """Scores of ``n_frames`` frames from the (n*6, n*6) covariance ``S`` of the stacked
        point states; ``usable`` (n, n, n) bool: triples seen together often enough to be
        used. The others score :data:`UNUSABLE_PER_FRAME` per frame: far below any real
        triple, yet finite, so a GA population that starts with some of them climbs towards
        structures with fewer (:meth:`unusable_in` counts them in a result)."""
        n = S.shape[0] // STATE_DIM
        F = n_frames
        triples = np.array(list(itertools.combinations(range(n), 3)), dtype=np.int64)
        pairs = np.array(list(itertools.combinations(range(n), 2)), dtype=np.int64)
        off = np.arange(STATE_DIM)
        tri_idx = (triples[:, :, None] * STATE_DIM + off).reshape(len(triples), -1)       # (m, 18)
        pair_idx = (pairs[:, :, None] * STATE_DIM + off).reshape(len(pairs), -1)          # (p, 12)
        G2 = observed_map((MISSING, FULL, FULL))[:, STATE_DIM:]                            # (9, 12)
        ll3 = _gaussian_ll(S[tri_idx[:, :, None], tri_idx[:, None, :]], FEATURE_MATRIX, F, reg_covar)
        ll2 = _gaussian_ll(S[pair_idx[:, :, None], pair_idx[:, None, :]], G2, F, reg_covar)
        if usable is not None:
            ok3 = usable[triples[:, 0], triples[:, 1], triples[:, 2]]
            ll3 = np.where(ok3, ll3, UNUSABLE_PER_FRAME * F)
        triple = np.full((n, n, n), -np.inf)
        for perm in itertools.permutations(range(3)):
            triple[triples[:, perm[0]], triples[:, perm[1]], triples[:, perm[2]]] = ll3
        pair = np.full((n, n), -np.inf)
        pair[pairs[:, 0], pairs[:, 1]] = ll2
        pair[pairs[:, 1], pairs[:, 0]] = ll2
        return cls(triple, pair, F, usable)

    def with_edge_prior(self, beta: np.ndarray) -> "TripleScores":
        """These scores with the structure prior ``beta`` (n, n): nats per training frame for
        every edge a structure has (module doc)."""
        return TripleScores(self.triple, self.pair, self.n_frames, self.usable, np.asarray(beta, dtype=np.float64))

    def with_leaves(self, triangles: Sequence[Sequence[int]], leaves: Sequence[int], n_vertices: int) -> Structure:
        """The structure of ``triangles`` (over the other points) with each of ``leaves`` joined last, as a new
        vertex ``A`` on the edge ``(B, C)`` that scores it best (eq. 18-20: ``triple[A, B, C] -
        pair[B, C]`` plus the edge prior; a usable triple where there is one): the leaves are
        never a parent, so the other points' triangles are the ones they have without them."""
        tri = [tuple(int(v) for v in t) for t in triangles]
        for a in leaves:
            edges = sorted({tuple(sorted(e)) for t in tri for e in ((t[0], t[1]), (t[0], t[2]), (t[1], t[2]))})
            b, c = np.array(edges, dtype=np.int64).T
            with np.errstate(invalid="ignore"):
                gain = self.triple[a, b, c] - self.pair[b, c] + self.edge_gain(a, b) + self.edge_gain(a, c)
            gain = np.where(np.isnan(gain), -np.inf, gain)
            if self.usable is not None and self.usable[a, b, c].any():
                gain = np.where(self.usable[a, b, c], gain, -np.inf)
            k = int(np.argmax(gain))
            tri.append((int(a), int(b[k]), int(c[k])))
        return Structure(tuple(tri), n_vertices)

    def edge_gain(self, a, b) -> np.ndarray | float:
        """Prior of the edges ``(a, b)`` over all training frames (0 without a prior)."""
        return 0.0 if self.edge_prior is None else self.n_frames * self.edge_prior[a, b]

    def score(self, population: np.ndarray) -> np.ndarray:
        """Fitness of (P, T, 3) strings (invalid strings are scored too; callers penalise):
        the log-likelihood of eq. 18-20 plus the edge prior of every introduced edge."""
        pop = np.asarray(population, dtype=np.int64)
        a, b, c = pop[..., 0], pop[..., 1], pop[..., 2]
        with np.errstate(invalid="ignore"):
            terms = self.triple[a, b, c]
            terms[:, 1:] -= self.pair[b[:, 1:], c[:, 1:]]
            if self.edge_prior is not None:
                terms += self.edge_gain(a, b) + self.edge_gain(a, c)
                terms[:, 0] += self.edge_gain(b[:, 0], c[:, 0])
        return np.where(np.isnan(terms), -np.inf, terms).sum(-1)     # an unusable triple: -inf - -inf

    def unusable_in(self, structure: Structure) -> list[tuple[int, int, int]]:
        """The triangles of ``structure`` that are not usable."""
        if self.usable is None:
            return []
        return [tuple(int(v) for v in t) for t in structure.array if not self.usable[t[0], t[1], t[2]]]

    def per_frame(self, structure: Structure) -> float:
        return float(self.score(structure.array[None])[0]) / self.n_frames


def _gaussian_ll(S: np.ndarray, M: np.ndarray, n: int, reg: float) -> np.ndarray:
    """Total log-likelihood of n samples under the ML Gaussian of features ``M s``."""
    C = M @ S @ M.T
    d = M.shape[0]
    Cr = C + reg * np.eye(d)
    _, logdet = np.linalg.slogdet(Cr)
    tr = np.trace(np.linalg.solve(Cr, C), axis1=-2, axis2=-1)
    return -0.5 * n * (d * LOG_2PI + logdet + tr)


@dataclass
class SearchResult:
    structure: Structure
    fitness: float                  # total log-likelihood over the training frames
    history: list[float] = field(default_factory=list)   # best fitness per generation
    evaluations: int = 0
    generations: int = 0
    stop_reason: str = ""


def cbga(scores: TripleScores, n_vertices: int, *, population: int = 60, generations: int = 200,
         p_crossover: float = 0.9, p_mutation: float = 0.05, n_elite: int = 2, stagnation: int = 60,
         seed: int = 0, root_pairs: np.ndarray | None = None,
         progress: Callable[[int, float], None] | None = None) -> SearchResult:
    """Constraint-based GA over structures (section IV.A): every individual stays valid."""
    rng = np.random.default_rng(seed)
    return _search(scores, n_vertices, rng, ops.sample(population, n_vertices, rng, root_pairs),
                   lambda a, b: ops.crossover(a, b, n_vertices, rng, root_pairs),
                   lambda x: ops.mutate(x, n_vertices, rng, p_mutation, root_pairs),
                   p_crossover, generations, n_elite, stagnation, progress, root_pairs)


def refine(scores: TripleScores, res: SearchResult, n_vertices: int, rng: np.random.Generator,
           root_pairs: np.ndarray | None = None, rounds: int = 50) -> SearchResult:
    """Steepest ascent over :func:`structure_ops.reattachments` from a search's best
    (training runs it after CBGA; kept separate so GA comparisons use equal budgets)."""
    best, fit = res.structure.array, res.fitness
    evals = res.evaluations
    for _ in range(rounds):
        cand = ops.reattachments(best, n_vertices, rng, root_pairs)
        f = scores.score(cand)
        evals += len(cand)
        i = int(np.argmax(f))
        if f[i] <= fit + 1e-9:
            break
        best, fit = cand[i], float(f[i])
    return SearchResult(Structure.from_string(best, n_vertices), fit, res.history + [fit], evals,
                        res.generations, res.stop_reason)


def simple_ga(scores: TripleScores, n_vertices: int, *, population: int = 60, generations: int = 200,
              p_crossover: float = 0.9, p_mutation: float = 0.05, n_elite: int = 2, stagnation: int = 60,
              seed: int = 0, root_pairs: np.ndarray | None = None,
              progress: Callable[[int, float], None] | None = None) -> SearchResult:
    """Baseline: the same GA with plain operators; invalid offspring get the death penalty."""
    rng = np.random.default_rng(seed)
    return _search(scores, n_vertices, rng, ops.sample(population, n_vertices, rng, root_pairs),
                   lambda a, b: ops.crossover_plain(a, b, rng),
                   lambda x: ops.mutate_plain(x, n_vertices, rng, p_mutation),
                   p_crossover, generations, n_elite, stagnation, progress, root_pairs)


def _search(scores, n_vertices, rng, pop, cross, mutate, p_crossover, generations, n_elite, stagnation,
            progress, root_pairs) -> SearchResult:
    """:func:`.evolve.evolve` on one island of structure strings. The structure operators
    act on one string at a time (``repair`` walks the triangles), so children are made pair
    by pair (consecutive parents): crossover with probability ``p_crossover`` (else a copy of
    the first parent), then mutation."""
    def fitness(p):
        f = scores.score(p)
        valid = np.array([is_valid(x, n_vertices) and ops.root_ok(x[0], root_pairs) for x in p])
        return np.where(valid, f, -np.inf)

    def offspring(pop, parents, _rng):
        return np.stack([mutate(cross(pop[a], pop[b]) if rng.random() < p_crossover else pop[a].copy())
                         for a, b in zip(parents[0::2], parents[1::2])])

    def hook(islands, gen):
        if progress:
            progress(gen, float(islands[0].fit.max()))
        return 0

    island = Island(pop, fitness, offspring)
    evo = evolve([island], rng, Termination(max_generations=generations, stagnation=stagnation),
                 n_elite=n_elite, selection_q=0.08, hook=hook)
    best, f = island.best()
    return SearchResult(Structure.from_string(best, n_vertices), f, evo.history, evo.evaluations,
                        evo.generations, evo.stop_reason)


def along_tree(scores: TripleScores, parents: np.ndarray, root_pairs: np.ndarray | None = None) -> SearchResult:
    """Song et al.'s greedy construction grown along the body (issue 13): every new vertex
    ``A_t`` joins the graph through its neighbour ``P`` in the most rigid tree (``parents``:
    bones, marker clusters; :func:`dtm_labeler.training.train.rigid_tree`) and one partner
    ``C`` that already shares an edge with ``P``, the pair ``(A_t, C)`` chosen by the largest
    conditional log-likelihood ``triple[A, P, C] - pair[P, C]`` (plus the edge prior) over
    the whole frontier. So ``(A_t, P)`` -- a segment -- is always an edge and carries its body
    term, and each triangle relates a point to the body part it hangs from rather than to
    points a training motion happened to move together. The first triangle is the best
    left/right root pair (``root_pairs``; else the best tree link) with its best third vertex
    adjacent in the tree to either."""
    n = len(parents)
    pair = scores.pair
    adj = np.zeros((n, n), dtype=bool)
    child = np.flatnonzero(parents >= 0)
    adj[child, parents[child]] = adj[parents[child], child] = True
    if root_pairs is not None and len(root_pairs):
        rp = np.asarray(root_pairs)
        b, c = (int(x) for x in rp[np.argmax(pair[rp[:, 0], rp[:, 1]])])
    else:
        b, c = (int(x) for x in np.unravel_index(np.argmax(np.where(adj, pair, -np.inf)), pair.shape))
    third = np.flatnonzero((adj[b] | adj[c]) & (np.arange(n) != b) & (np.arange(n) != c))
    if third.size == 0:
        third = np.setdiff1d(np.arange(n), [b, c])
    gain = scores.triple[third, b, c] - pair[b, c] + scores.edge_gain(third, b) + scores.edge_gain(third, c)
    a = int(third[np.argmax(gain)])
    tris, used = [(a, b, c)], {a, b, c}
    nbr = {v: set() for v in range(n)}
    for u, v in ((a, b), (a, c), (b, c)):
        nbr[u].add(v)
        nbr[v].add(u)
    evals = third.size
    while len(used) < n:
        best = (-np.inf, None)
        for A in range(n):
            if A in used:
                continue
            for P in np.flatnonzero(adj[A]):
                P = int(P)
                if P not in used:
                    continue
                Cs = np.array(sorted(nbr[P]))
                g = scores.triple[A, P, Cs] - pair[P, Cs] + scores.edge_gain(A, P) + scores.edge_gain(A, Cs)
                evals += Cs.size
                i = int(np.argmax(g))
                if g[i] > best[0]:
                    best = (float(g[i]), (A, P, int(Cs[i])))
        if best[1] is None:                      # a point not connected by the tree: plain greedy step
            A = min(set(range(n)) - used)
            P, C = max(((u, v) for u in used for v in nbr[u] if u < v), key=lambda e: scores.triple[A, e[0], e[1]])
            best = (0.0, (A, P, C))
        A, P, C = best[1]
        tris.append((A, P, C))
        used.add(A)
        for u in (P, C):
            nbr[A].add(u)
            nbr[u].add(A)
    st = Structure(tuple(tris), n)
    return SearchResult(st, float(scores.score(st.array[None])[0]), [], evals, 0, "complete")


def greedy(scores: TripleScores, n_vertices: int, root_pairs: np.ndarray | None = None) -> SearchResult:
    """Song et al.'s greedy construction: start from the best pair (the best left/right
    pair when ``root_pairs`` is given), then repeatedly attach the (vertex, existing edge)
    with the largest conditional log-likelihood (least entropy)."""
    pair = scores.pair.copy()
    allowed = np.isfinite(pair)
    if root_pairs is not None and len(root_pairs):
        allowed = np.zeros_like(allowed)
        rp = np.asarray(root_pairs)
        allowed[rp[:, 0], rp[:, 1]] = True
    b, c = np.unravel_index(np.argmax(np.where(allowed, pair, -np.inf)), pair.shape)
    gain = scores.triple[:, b, c] - pair[b, c] + scores.edge_gain(np.arange(n_vertices), b) \
        + scores.edge_gain(np.arange(n_vertices), c)
    gain[[b, c]] = -np.inf
    a = int(np.argmax(gain))
    tris = [(a, int(b), int(c))]
    used = {a, int(b), int(c)}
    edges = {tuple(sorted(e)) for e in ((a, b), (a, c), (b, c))}
    evals = n_vertices
    while len(used) < n_vertices:
        best = (-np.inf, None)
        unused = np.array(sorted(set(range(n_vertices)) - used))
        for (p, q) in edges:
            g = scores.triple[unused, p, q] - pair[p, q] + scores.edge_gain(unused, p) + scores.edge_gain(unused, q)
            evals += len(unused)
            i = int(np.argmax(g))
            if g[i] > best[0]:
                best = (g[i], (int(unused[i]), p, q))
        if best[1] is None:
            raise ValueError(f"no usable triangle attaches points {sorted(unused.tolist())} to the structure "
                             "(seen together with the others too rarely)")
        tris.append(best[1])
        a, p, q = best[1]
        used.add(a)
        edges |= {tuple(sorted((a, p))), tuple(sorted((a, q)))}
    s = Structure(tuple(tris), n_vertices)
    return SearchResult(s, float(scores.score(s.array[None])[0]), [], evals, 0, "complete")
