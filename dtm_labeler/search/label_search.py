"""Per-frame label search strategies behind one interface (Stone Soup style).

* :class:`CBGASearch` -- constraint-based GA (section IV.A): valid initialisation, two-point
  crossover along the structure order with repair, constraint-based mutation, geometric
  rank selection [29], elitism; optional warm-start seeds; finished by a steepest-ascent
  pass over the one-move neighbourhood of the best individual (all label swaps and point
  moves -- the constraint-based mutation applied exhaustively).
* :class:`SimpleGASearch` -- the same budget and selection with plain operators (no
  repair); invalid offspring get the death penalty.
* :class:`GreedySearch` -- Song et al.'s dynamic programming over the elimination order
  (max-product on the DTM, :mod:`.dtm_dp`; exclusion enforced inside each clique only),
  conflicts then resolved by fitness; run at a few heading hypotheses.
* :class:`ExhaustiveSearch` -- every injective assignment, for small problems (counts
  search errors exactly).
"""
from __future__ import annotations

import itertools
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from .problem import FrameProblem
from . import label_ops as ops
from .dtm_dp import max_product, regions_of, relabel_regions
from .ga import Termination, elite_indices, rank_select


@dataclass
class SearchOutcome:
    assignment: np.ndarray          # (M,) point index per label, n = missing
    fitness: float
    generations: int = 0
    evaluations: int = 0
    history: list[float] = field(default_factory=list)
    stop_reason: str = ""


@dataclass
class GASettings:
    population: int = 48
    max_generations: int = 60
    stagnation: int = 8
    p_crossover: float = 0.8
    p_mutation: float = 0.6
    n_elite: int = 2
    selection_q: float = 0.12
    time_budget_s: float | None = None
    polish: bool = True
    polish_rounds: int = 12
    temperatures: np.ndarray = field(default_factory=lambda: np.array([1.0, 3.0, 10.0]))
    p_recreate: float = 0.25
    fresh_fraction: float = 0.25        # share of a seeded population drawn fresh (guided sampling)
    region_sweeps: int = 1              # after the polish: sweeps of exact region relabelling (0: none)
    region_size: int = 6                # labels per region of those sweeps

    def __post_init__(self) -> None:
        if self.population < 4:
            raise ValueError("population must be at least 4")
        if self.max_generations < 0 or self.stagnation < 1:
            raise ValueError("generation cap must be >= 0 and stagnation >= 1")
        if not 0 <= self.p_crossover <= 1 or not 0 <= self.p_mutation <= 1:
            raise ValueError("probabilities must be in [0, 1]")
        if not 0 <= self.n_elite < self.population:
            raise ValueError("n_elite must be in [0, population)")
        if self.region_sweeps < 0 or self.region_size < 2:
            raise ValueError("region_sweeps must be >= 0 and region_size >= 2")


class LabelSearch(ABC):
    """Finds the assignment that maximises :meth:`FrameProblem.fitness`."""

    name = "base"

    @abstractmethod
    def search(self, problem: FrameProblem, rng: np.random.Generator,
               seeds: np.ndarray | None = None) -> SearchOutcome:
        """``seeds`` (S, M): assignments to start from (warm start); may be ignored."""


def _pair_triangles(problem: FrameProblem) -> list[tuple[int, int, int]]:
    """(left, right, triangle) for every heading pair that shares a triangle."""
    out = []
    for a, b in problem.pairs:
        for t, tri in enumerate(problem.tri):
            if a in tri and b in tri:
                out.append((int(a), int(b), t))
                break
    return out


def _root_triangles(problem: FrameProblem, lft: int, rgt: int, t: int) -> tuple[np.ndarray, np.ndarray]:
    """Every plausible assignment of the triangle ``t`` holding the left/right pair: point
    pairs within the pair's distance bound, the third vertex within the bounds of both (or
    missing). Returns (candidates (K, M), heading bins (K,))."""
    n, M = problem.n, problem.M
    third = [int(v) for v in problem.tri[t] if v not in (lft, rgt)][0]
    d = problem.dist[:n, :n]
    I, J = np.nonzero((d <= problem.bounds[lft, rgt]) & ~np.eye(n, dtype=bool))
    ok = (problem.dist[I] <= problem.bounds[third, lft]) & (problem.dist[J] <= problem.bounds[third, rgt])
    ok[np.arange(I.size), I] = False
    ok[np.arange(I.size), J] = False
    ok[:, n] = True
    r, k = np.nonzero(ok)
    cand = np.full((r.size + 1, M), n, dtype=np.int64)      # last row: the pair not seen
    cand[:-1, lft], cand[:-1, rgt], cand[:-1, third] = I[r], J[r], k
    return cand, problem.candidate_bins(cand)


def guided_sample(problem: FrameProblem, P: int, rng: np.random.Generator,
                  temperature: float | np.ndarray = 1.0, base: np.ndarray | None = None,
                  free: np.ndarray | None = None) -> np.ndarray:
    """Constraint-respecting, model-guided initialisation (eq. 15-17 with the model as guide).

    1. Heading: each candidate picks one of the model's left/right pairs (that share a
       triangle) at random and draws that whole triangle's three points jointly (among the
       plausible ones, :func:`_root_triangles`), with probability proportional to
       ``exp(term / temperature)`` at the heading the pair implies. Different candidates
       lean on different pairs, so an occluded pair does not doom all.
    2. The other labels follow the structure's insertion order; each draws its point from
       the unused points or "missing" with probability proportional to ``exp(term / T)`` --
       the triangle's conditional given what is already placed (ancestral sampling from the
       DTM under the one-point-one-label constraint).
    Gumbel-max turns every draw into one vectorised arg max over the population.
    ``temperature`` may be one value or one per candidate (hotter = more diverse).

    With ``base`` (P, M) and ``free`` (P, M) bool, only the free labels are (re)drawn, given
    the others and the heading they imply: the *ruin-and-recreate* mutation.
    """
    M, n, T = problem.M, problem.n, problem.T
    temp = np.broadcast_to(np.asarray(temperature, dtype=np.float64), (P,))
    tri = problem.tri
    gain = problem.label_gain
    pairs = _pair_triangles(problem)
    if base is not None:
        pop = np.where(free, n, base).astype(np.int64)
        bins = problem.candidate_bins(pop)
        todo_mask = np.asarray(free, dtype=bool)
    else:
        pop = np.full((P, M), n, dtype=np.int64)
        todo_mask = None
    if base is None and pairs and n >= 2:
        which = rng.integers(len(pairs), size=P)
        bins = np.empty(P, dtype=np.int64)
        for q in np.unique(which):
            rows = np.flatnonzero(which == q)
            cand, cbins = _root_triangles(problem, *pairs[q])
            val = problem.triangle_table(cand, cbins, [pairs[q][2]])[:, 0] + gain[cand].sum(1) - gain[n] * (M - 3)
            pick = np.argmax(val[None, :] / temp[rows, None] + rng.gumbel(size=(rows.size, val.size)), axis=1)
            pop[rows] = cand[pick]
            bins[rows] = cbins[pick]
        todo_mask = pop == n
    elif base is None:
        bins = np.full(P, problem.heading_bin(np.array([problem.heading_hint]))[0])
        todo_mask = np.ones((P, M), dtype=bool)
    steps = [(int(v), 0) for v in tri[0]] + [(int(tri[t][0]), t) for t in range(1, T)]
    for v, t in steps:
        todo = np.flatnonzero(todo_mask[:, v])
        if todo.size == 0:
            continue
        sub = pop[todo]
        # candidates: unused points within the distance bounds of the labels already placed
        ok = np.ones((todo.size, n + 1), dtype=bool)
        ok[:, :n] = ~ops.used_mask(sub, n)
        near = problem.dist[:, sub].transpose(1, 0, 2) > problem.bounds[v][None, None, :]   # (k, n+1, M)
        ok &= ~near.any(axis=2)
        ok[:, n] = True
        r, c = np.nonzero(ok)
        cand = sub[r].copy()
        cand[:, v] = c
        val = np.full((todo.size, n + 1), -np.inf)
        val[r, c] = problem.triangle_table(cand, bins[todo][r], [t])[:, 0] + gain[c]
        pop[todo, v] = np.argmax(val / temp[todo, None] + rng.gumbel(size=val.shape), axis=1)
    # a candidate built on a pair read the wrong way round is the mirror of a good one
    if base is None and len(problem.mirror_pairs):
        mirrored = ops.mirror(pop, problem.mirror_pairs)
        better = problem.fitness(mirrored) > problem.fitness(pop)
        pop[better] = mirrored[better]
    return pop


def targeted_moves(ind: np.ndarray, n: int, mirror_pairs: np.ndarray, free_points: np.ndarray,
                   close_pairs: np.ndarray | None = None, allowed: np.ndarray | None = None) -> np.ndarray:
    """The few moves a carried-over labeling most often needs: the whole mirror image, each
    left/right pair swapped, labels on nearby points swapped (``close_pairs``: where tracks
    cross) and every label (missing or not) moved onto each free point -- only where
    ``allowed`` (M, n+1), if given, permits that label on that point (the distance bounds
    to its labelled triangle neighbours, :meth:`FrameProblem.allowed`)."""
    out = [ind[None], ops.mirror(ind[None], mirror_pairs)]
    if close_pairs is not None and len(close_pairs):
        sw = np.repeat(ind[None], len(close_pairs), 0)
        r = np.arange(len(close_pairs))
        sw[r, close_pairs[:, 0]], sw[r, close_pairs[:, 1]] = ind[close_pairs[:, 1]], ind[close_pairs[:, 0]]
        out.append(sw)
    if len(mirror_pairs):
        sw = np.repeat(ind[None], len(mirror_pairs), 0)
        r = np.arange(len(mirror_pairs))
        sw[r, mirror_pairs[:, 0]], sw[r, mirror_pairs[:, 1]] = ind[mirror_pairs[:, 1]], ind[mirror_pairs[:, 0]]
        out.append(sw)
    if free_points.size:
        lab, pt = np.meshgrid(np.arange(ind.size), free_points, indexing="ij")
        lab, pt = lab.ravel(), pt.ravel()
        if allowed is not None:
            ok = allowed[lab, pt]
            lab, pt = lab[ok], pt[ok]
        mv = np.repeat(ind[None], lab.size, 0)
        mv[np.arange(lab.size), lab] = pt
        out.append(mv)
    return np.concatenate(out)


def polish(problem: FrameProblem, ind: np.ndarray, fit: float | None, rounds: int,
           deadline: float | None = None, neighbours=None) -> tuple[np.ndarray, float, int]:
    """Steepest ascent (at most ``rounds`` moves) over ``neighbours(ind)``; by default the
    full one-move :func:`label_ops.neighbourhood` within the distance bounds. ``fit`` None:
    the start is scored in the same batch as its first neighbourhood (one term-cache fill
    for both: what a new frame's carried labeling needs)."""
    if neighbours is None:
        def neighbours(x):
            return ops.neighbourhood(x, problem.n, pairs=problem.mirror_pairs, allowed=problem.allowed(x))
    evals = 0
    for _ in range(rounds):
        if deadline is not None and time.perf_counter() > deadline:
            break
        cand = neighbours(ind)
        if fit is None:
            f = problem.fitness(np.concatenate([ind[None], cand]))
            fit, f = float(f[0]), f[1:]
            evals += 1
        else:
            f = problem.fitness(cand)
        evals += len(cand)
        i = int(np.argmax(f))
        if f[i] <= fit + 1e-9:
            break
        ind, fit = cand[i], float(f[i])
    if fit is None:
        fit = float(problem.fitness(ind[None])[0])
        evals += 1
    return ind, fit, evals


class _GABase(LabelSearch):
    def __init__(self, settings: GASettings | None = None):
        self.settings = settings or GASettings()

    def _operators(self, problem, rng):
        raise NotImplementedError

    def _initial(self, problem, P, rng):
        return ops.sample(P, problem.M, problem.n, rng)

    def search(self, problem, rng, seeds=None):
        s = self.settings
        M, n = problem.M, problem.n
        deadline = None if s.time_budget_s is None else time.perf_counter() + s.time_budget_s
        if seeds is not None and len(seeds):
            # warm start: the seeds, mutants of the first seed, and a share of fresh samples
            seeds = ops.repair(np.asarray(seeds, dtype=np.int64).reshape(-1, M), n, rng)
            k = min(len(seeds), s.population)
            fresh = int((s.population - k) * s.fresh_fraction)
            pop = np.concatenate([seeds[:k], ops.mutate(np.repeat(seeds[:1], s.population - k - fresh, 0), n, rng, 1.0),
                                  self._initial(problem, fresh, rng) if fresh else np.zeros((0, M), np.int64)])
        else:
            pop = self._initial(problem, s.population, rng)
        cross, mutate, valid = self._operators(problem, rng)
        fit = self._fitness(problem, pop, valid)
        history = [float(fit.max())]
        evals = len(pop)
        term = Termination(max_generations=s.max_generations, stagnation=s.stagnation,
                           time_budget=s.time_budget_s).start()
        gen = 0
        while not term.done(gen, history[-1]):
            gen += 1
            n_kids = s.population - s.n_elite
            elite = pop[elite_indices(fit, s.n_elite)]
            par = rank_select(fit, 2 * n_kids, rng, s.selection_q)
            pa, pb = pop[par[:n_kids]], pop[par[n_kids:]]
            do_x = rng.random(n_kids) < s.p_crossover
            kids = np.where(do_x[:, None], cross(pa, pb), pa)
            kids = mutate(kids)
            pop = np.concatenate([elite, kids])
            fit = self._fitness(problem, pop, valid)
            evals += n_kids
            history.append(float(fit.max()))
        best = int(np.argmax(fit))
        ind, f = pop[best].copy(), float(fit[best])
        if self._polish and s.polish:
            # polish the best and its mirror image: a flipped body is a deep local optimum
            starts = [ind] + ([ops.mirror(ind[None], problem.mirror_pairs)[0]] if len(problem.mirror_pairs) else [])
            for start in starts:
                f0 = float(problem.fitness(start[None])[0])
                cand, fc, e = polish(problem, start, f0, s.polish_rounds, deadline)
                evals += e + 1
                if fc > f:
                    ind, f = cand, fc
            ind, f, e = self._sweep_regions(problem, ind, f, deadline)
            evals += e
            history.append(f)
        return SearchOutcome(ind, f, gen, evals, history, term.reason)

    def _sweep_regions(self, problem, ind, f, deadline):
        """``region_sweeps`` passes of :func:`relabel_regions` over every label's region,
        each accepted relabelling polished; stops early when a pass changes nothing. The GA
        and polish leave labelings that are wrong over a few neighbouring labels at once (a
        limb shifted along its markers); this settles them exactly."""
        s, evals = self.settings, 0
        if s.region_sweeps <= 0 or problem.M <= 3 or problem.n == 0:
            return ind, f, evals
        regions = regions_of(problem.model, s.region_size)

        def refine(x, fx):
            return polish(problem, x, fx, s.polish_rounds, deadline)
        for _ in range(s.region_sweeps):
            if deadline is not None and time.perf_counter() > deadline:
                break
            f0 = f
            ind, f, e = relabel_regions(problem, ind, f, regions, range(problem.M), refine)
            evals += e
            if f <= f0 + 1e-9:
                break
        return ind, f, evals

    @staticmethod
    def _fitness(problem, pop, valid):
        f = problem.fitness(pop)
        if valid is not None:
            f = np.where(valid(pop), f, -np.inf)
        return f


def ruin_and_recreate(problem: FrameProblem, pop: np.ndarray, rng: np.random.Generator,
                      rate: float, temperature: float = 3.0) -> np.ndarray:
    """Model-guided mutation: for a fraction ``rate`` of individuals, clear the labels of one
    triangle (the same random triangle for all of them this generation, so the redraw costs
    three vectorised sampling steps) and redraw them with :func:`guided_sample` given the
    rest. Reaches multi-label moves (a chain of shifted labels) that no swap reaches."""
    hit = np.flatnonzero(rng.random(pop.shape[0]) < rate)
    if hit.size == 0:
        return pop
    free = np.zeros((hit.size, pop.shape[1]), dtype=bool)
    free[:, problem.tri[rng.integers(problem.T)]] = True
    out = pop.copy()
    out[hit] = guided_sample(problem, hit.size, rng, temperature, base=pop[hit], free=free)
    return out


class CBGASearch(_GABase):
    name = "cbga"
    _polish = True

    def _initial(self, problem, P, rng):
        # a ladder of temperatures: exact ancestral samples plus hotter, more diverse ones
        return guided_sample(problem, P, rng, self.settings.temperatures[np.arange(P) % len(self.settings.temperatures)])

    def _operators(self, problem, rng):
        order = np.array(problem.model.structure.to_string()[:3] +
                         [t[0] for t in problem.model.structure.triangles[1:]])
        n = problem.n
        return (lambda a, b: ops.crossover(a, b, order, n, rng),
                lambda p: ruin_and_recreate(problem, ops.mutate(p, n, rng, self.settings.p_mutation,
                                                                pairs=problem.mirror_pairs), rng, self.settings.p_recreate),
                None)


class SimpleGASearch(_GABase):
    name = "sga"
    _polish = False

    def _operators(self, problem, rng):
        n, M = problem.n, problem.M
        return (lambda a, b: ops.crossover_plain(a, b, rng),
                lambda p: ops.mutate_plain(p, n, rng, self.settings.p_mutation / max(M, 1) * 2, swap=True),
                lambda p: ops.is_valid(p, n))


class GreedySearch(LabelSearch):
    """Max-product DP over the elimination order (Song et al.), at ``n_headings`` headings."""

    name = "greedy"

    def __init__(self, n_headings: int = 8):
        self.n_headings = n_headings

    def search(self, problem, rng, seeds=None):
        best = (None, -np.inf)
        evals = 0
        bins = problem.bins
        cand_bins = np.unique((np.arange(self.n_headings) * bins) // self.n_headings)
        if seeds is not None and len(seeds):          # heading of the warm start, if any
            cand_bins = np.unique(np.append(cand_bins, problem.candidate_bins(np.asarray(seeds)[:1])))
        for b in cand_bins:
            ind = self._dp(problem, int(b))
            evals += problem.T * (problem.n + 1) ** 3
            f = float(problem.fitness(ind[None])[0])
            if f > best[1]:
                best = (ind, f)
        return SearchOutcome(best[0], best[1], 0, evals, [best[1]], "complete")

    @staticmethod
    def _dp(problem: FrameProblem, b: int) -> np.ndarray:
        """Every point (and "missing") a candidate for every label: :func:`dtm_dp.max_product`."""
        return max_product(problem, [np.arange(problem.n + 1)] * problem.M, b)


class ExhaustiveSearch(LabelSearch):
    """All injective assignments (labels may be missing only when points run out)."""

    name = "exhaustive"

    def __init__(self, max_candidates: int = 3_000_000, batch: int = 20000):
        self.max_candidates = max_candidates
        self.batch = batch

    def search(self, problem, rng, seeds=None):
        M, n = problem.M, problem.n
        slots = list(range(n)) + [n] * max(M - n, 0)
        count = math.perm(len(slots), M) if len(slots) >= M else 0
        if count > self.max_candidates:
            raise ValueError(f"exhaustive search over {count} assignments is too large "
                             f"(limit {self.max_candidates}); use cbga")
        best, best_f, evals = None, -np.inf, 0
        it = itertools.permutations(slots, M)
        while True:
            chunk = np.array(list(itertools.islice(it, self.batch)), dtype=np.int64)
            if chunk.size == 0:
                break
            f = problem.fitness(chunk)
            evals += len(chunk)
            i = int(np.argmax(f))
            if f[i] > best_f:
                best, best_f = chunk[i], float(f[i])
        return SearchOutcome(best, best_f, 0, evals, [best_f], "complete")


SEARCHES = {"cbga": CBGASearch, "sga": SimpleGASearch, "greedy": GreedySearch, "exhaustive": ExhaustiveSearch}


def make_search(name: str, settings: GASettings | None = None) -> LabelSearch:
    if name not in SEARCHES:
        raise ValueError(f"unknown search method {name!r}; choose from {', '.join(SEARCHES)}")
    cls = SEARCHES[name]
    return cls(settings) if issubclass(cls, _GABase) else cls()
