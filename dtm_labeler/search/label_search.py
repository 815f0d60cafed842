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

import functools
import itertools
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .problem import FrameProblem
from . import label_ops as ops
from .dtm_dp import max_product, mirrored_regions, region_candidates, regions_of, relabel_regions, shared_candidates
from .evolve import Island, Mating, evolve
from .ga import Termination
from .move_kernels import move_rows
from .sample_kernels import gumbel_argmax


@dataclass
class SearchOutcome:
    assignment: np.ndarray          # (M,) point index per label, n = missing
    fitness: float
    generations: int = 0
    evaluations: int = 0
    history: list[float] = field(default_factory=list)
    stop_reason: str = ""
    model: int = 0                  # which problem (model) the assignment is scored under
    per_model: dict = field(default_factory=dict)       # model -> (best assignment, fitness) of its island
    island_sizes: list[int] = field(default_factory=list)


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
    region_branches: int = 0            # extra DP solves per region on a point given to two labels
    wide_sweeps: int = 0                # then: sweeps over every label's body neighbourhood, relabelled as a whole
    wide_size: int = 7                  # labels per neighbourhood of those sweeps
    wide_candidates: int = 12           # points each neighbourhood's labels share
    mirror_sweeps: int = 0              # then (marker sets): the neighbourhoods joined with their mirror images
    mirror_candidates: int = 20         # points each of those shares
    mirror_branches: int = 8            # DP solves each may spend on a point given to two labels
    fresh_starts: int = 0               # a labeler's cold search: bests of fresh populations, each finished

    def __post_init__(self) -> None:
        if self.population < 4:
            raise ValueError("population must be at least 4")
        if self.max_generations < 0 or self.stagnation < 1:
            raise ValueError("generation cap must be >= 0 and stagnation >= 1")
        if not 0 <= self.p_crossover <= 1 or not 0 <= self.p_mutation <= 1:
            raise ValueError("probabilities must be in [0, 1]")
        if not 0 <= self.n_elite < self.population:
            raise ValueError("n_elite must be in [0, population)")
        if self.region_sweeps < 0 or self.region_size < 2 or self.region_branches < 0:
            raise ValueError("region_sweeps and region_branches must be >= 0 and region_size >= 2")
        if self.wide_sweeps < 0 or self.wide_size < 2 or self.wide_candidates < 1 or self.fresh_starts < 0:
            raise ValueError("wide_sweeps and fresh_starts must be >= 0, wide_size >= 2 and wide_candidates >= 1")
        if self.mirror_sweeps < 0 or self.mirror_candidates < 1 or self.mirror_branches < 0:
            raise ValueError("mirror_sweeps and mirror_branches must be >= 0 and mirror_candidates >= 1")


class LabelSearch(ABC):
    """Finds the assignment that maximises :meth:`FrameProblem.fitness`."""

    name = "base"

    @abstractmethod
    def search(self, problem: FrameProblem, rng: np.random.Generator,
               seeds: np.ndarray | None = None) -> SearchOutcome:
        """``seeds`` (S, M): assignments to start from (warm start); may be ignored."""


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
    Gumbel-max turns every draw into one arg max over the population (:func:`.sample_kernels.gumbel_argmax`).
    ``temperature`` may be one value or one per candidate (hotter = more diverse).

    With ``base`` (P, M) and ``free`` (P, M) bool, only the free labels are (re)drawn, given
    the others and the heading they imply: the *ruin-and-recreate* mutation.
    """
    M, n, T = problem.M, problem.n, problem.T
    temp = np.broadcast_to(np.asarray(temperature, dtype=np.float64), (P,))
    tri = problem.tri
    gain = problem.label_gain
    pairs = problem.model.pair_triangles
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
            pick = gumbel_argmax(val, temp[rows], rng)
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
        nb = np.flatnonzero(np.isfinite(problem.bounds[v]))        # the labels v has a distance bound to
        if nb.size:
            near = problem.dist[:, sub[:, nb]].transpose(1, 0, 2) > problem.bounds[v, nb][None, None, :]
            ok &= ~near.any(axis=2)                                # (k, n+1)
        ok[:, n] = True
        r, c = np.nonzero(ok)
        cand = sub[r].copy()
        cand[:, v] = c
        val = np.full((todo.size, n + 1), -np.inf)
        val[r, c] = problem.triangle_table(cand, bins[todo][r], [t])[:, 0] + gain[c]
        pop[todo, v] = gumbel_argmax(val, temp[todo], rng)
    # a candidate built on a pair read the wrong way round is the mirror of a good one
    if base is None and len(problem.mirror_pairs):
        mirrored = ops.mirror(pop, problem.mirror_pairs)
        better = problem.fitness(mirrored) > problem.fitness(pop)
        pop[better] = mirrored[better]
    return pop


def targeted_moves(ind: np.ndarray, n: int, mirror_pairs: np.ndarray, free_points: np.ndarray,
                   close_pairs: np.ndarray | None = None, allowed: np.ndarray | None = None,
                   release: np.ndarray | None = None) -> np.ndarray:
    """The few moves a carried-over labeling most often needs: the whole mirror image, each
    left/right pair swapped, labels on nearby points swapped (``close_pairs``: where tracks
    cross) and every label (missing or not) moved onto each free point -- only where
    ``allowed`` (M, n+1), if given, permits that label on that point (the distance bounds
    to its labelled triangle neighbours, :meth:`FrameProblem.allowed`). Written by a compiled
    kernel (:func:`~.move_kernels.move_rows`), in this order."""
    use_allowed = allowed is not None
    return move_rows(_int64(ind), n, _pairs(mirror_pairs), _pairs(close_pairs), _int64(free_points),
                     allowed if use_allowed else np.zeros((1, 1), dtype=np.bool_), use_allowed,
                     _int64(release if release is not None else ()))


def cluster_turns(ind: np.ndarray, n: int, clusters) -> np.ndarray:
    """(K, M) every other arrangement of each rigid cluster's labels over the points they hold
    in ``ind`` (clusters with every label seen): the block moves of a cluster read turned or
    mirrored as a whole -- a head's four markers each one along (the head read turned by 90
    degrees). No single swap reaches that from the truth without passing labelings that fit
    worse, so the hill-climb's moves (:func:`targeted_moves`) keep it once a frame has taken it."""
    blocks = []
    for members in clusters:
        pts = ind[members]
        if (pts >= n).any():
            continue
        perms = _arrangements(members.size)
        block = np.repeat(ind[None], len(perms), axis=0)
        block[:, members] = pts[perms]
        blocks.append(block)
    return np.concatenate(blocks) if blocks else np.zeros((0, ind.size), dtype=np.int64)


def transfer_moves(ind: np.ndarray, n: int, labels: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """(K, M) each of ``labels`` (labelled in ``ind``) handing its point to a missing label that
    ``allowed`` (M, n+1; :meth:`FrameProblem.allowed`) permits there, itself left missing: the
    one move that reads a point as the hidden marker next to the one it was labelled as. Not a
    move of the searches (taken, it followed the model's own preferences, ``results/search_errors.md``);
    the published confidence weighs it (:func:`~dtm_labeler.labeling.confidence.label_posteriors`)."""
    ind = _int64(ind)
    labels = _int64(labels)
    missing = np.flatnonzero(ind >= n)
    if not missing.size or not labels.size:
        return np.zeros((0, ind.size), dtype=np.int64)
    to, frm = np.nonzero(allowed[missing[:, None], ind[labels][None, :]])
    rows = np.repeat(ind[None], to.size, axis=0)
    k = np.arange(to.size)
    rows[k, missing[to]] = ind[labels[frm]]
    rows[k, labels[frm]] = n
    return rows


@functools.lru_cache(maxsize=None)
def _arrangements(k: int) -> np.ndarray:
    """(k! - 1, k) every order of ``range(k)`` but the identity (built once per size)."""
    return np.array(list(itertools.permutations(range(k)))[1:], dtype=np.int64).reshape(-1, k)

def _int64(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


def _pairs(pairs: np.ndarray | None) -> np.ndarray:
    """(K, 2) int64 label pairs (K = 0 for None or none)."""
    return _int64(pairs if pairs is not None else ()).reshape(-1, 2)


def polish(problem: FrameProblem, ind: np.ndarray, fit: float | None, rounds: int,
           deadline: float | None = None, neighbours=None, last: dict | None = None,
           cost=None) -> tuple[np.ndarray, float, int]:
    """Steepest ascent (at most ``rounds`` moves) over ``neighbours(ind)``; by default the
    full one-move :func:`label_ops.neighbourhood` within the distance bounds. ``cost``, if
    given, maps (K, M) candidates to what each must pay (nats) against the start ``ind``: the
    ascent is then on fitness minus cost (a prior on moves away from the start; the returned
    fitness is the candidate's own). ``fit`` None:
    the start is scored in the same batch as its first neighbourhood (one term-cache fill
    for both: what a new frame's carried labeling needs). ``last``, if given, receives the
    final neighbourhood and its fitnesses when the ascent stopped at a local optimum
    (``ind``, ``cand``, ``fitness``): what the confidence of that optimum is read from."""
    if neighbours is None:
        def neighbours(x):
            return ops.neighbourhood(x, problem.n, pairs=problem.mirror_pairs, allowed=problem.allowed(x))
    evals = 0
    paid = 0.0                      # the cost of the current ``ind`` against the start
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
        price = np.zeros(len(cand)) if cost is None else cost(cand)
        i = int(np.argmax(f - price))
        if f[i] - price[i] <= fit - paid + 1e-9:
            if last is not None:
                last.update(ind=ind, cand=cand, fitness=f)
            break
        ind, fit, paid = cand[i], float(f[i]), float(price[i])
    if fit is None:
        fit = float(problem.fitness(ind[None])[0])
        evals += 1
    return ind, fit, evals


class GASearch(LabelSearch):
    """The label GA: :func:`.evolve.evolve` over one island per model, then (CBGA) a polish
    of the best and of its mirror image and ``region_sweeps`` exact region sweeps.

    Subclasses say how a population is sampled (:meth:`_sample`), how children are made
    (:meth:`_mating`) and whether invalid individuals exist (:meth:`_valid`). One model
    (:meth:`search`) is one island; a bank of models (:meth:`search_models`, Ukita) is one
    island per model with a per-generation ``hook`` (migration)."""

    finish = True

    def __init__(self, settings: GASettings | None = None):
        self.settings = settings or GASettings()

    def _sample(self, problem: FrameProblem, P: int, rng: np.random.Generator) -> np.ndarray:
        return ops.sample(P, problem.M, problem.n, rng)

    def _mating(self, problem: FrameProblem) -> Mating:
        raise NotImplementedError

    def _valid(self, problem: FrameProblem):
        return None

    def initial_population(self, problem: FrameProblem, P: int, rng: np.random.Generator,
                           seeds: np.ndarray | None = None) -> np.ndarray:
        """``P`` individuals: without seeds, :meth:`_sample`; with seeds (warm start), the
        seeds, mutants of the first seed and a share ``fresh_fraction`` of fresh samples."""
        M, n = problem.M, problem.n
        if seeds is None or not len(seeds):
            return self._sample(problem, P, rng)
        seeds = ops.repair(np.asarray(seeds, dtype=np.int64).reshape(-1, M), n, rng)
        k = min(len(seeds), P)
        fresh = int((P - k) * self.settings.fresh_fraction)
        return np.concatenate([seeds[:k], ops.mutate(np.repeat(seeds[:1], P - k - fresh, 0), n, rng, 1.0),
                               self._sample(problem, fresh, rng) if fresh else np.zeros((0, M), np.int64)])

    def search(self, problem, rng, seeds=None):
        return self.search_models([problem], [self.settings.population], rng, seeds)

    def search_models(self, problems: Sequence[FrameProblem], sizes: Sequence[int], rng: np.random.Generator,
                      seeds: np.ndarray | None = None, hook=None) -> SearchOutcome:
        """One GA over one island per problem (model), ``sizes[i]`` individuals each; the
        outcome is the best individual over all islands (``model`` says under which),
        finished on its own problem; ``per_model`` holds every island's best."""
        s = self.settings
        deadline = None if s.time_budget_s is None else time.perf_counter() + s.time_budget_s
        islands = [Island(self.initial_population(p, int(size), rng, seeds), self._evaluator(p), self._mating(p))
                   for p, size in zip(problems, sizes)]
        evo = evolve(islands, rng, Termination(max_generations=s.max_generations, stagnation=s.stagnation,
                                               time_budget=s.time_budget_s),
                     n_elite=s.n_elite, selection_q=s.selection_q, hook=hook)
        per_model = {m: isl.best() for m, isl in enumerate(islands) if len(isl.pop)}
        m = max(per_model, key=lambda q: per_model[q][1])
        ind, f = per_model[m]
        evals, history = evo.evaluations, evo.history
        if self.finish and s.polish:
            ind, f, e = self._finish(problems[m], ind, f, deadline)
            evals += e
            history.append(f)
            per_model[m] = (ind, f)
        return SearchOutcome(ind, f, evo.generations, evals, history, evo.stop_reason, model=m,
                             per_model=per_model, island_sizes=[len(i.pop) for i in islands])

    def _evaluator(self, problem: FrameProblem):
        valid = self._valid(problem)
        if valid is None:
            return problem.fitness
        return lambda pop: np.where(valid(pop), problem.fitness(pop), -np.inf)

    def _finish(self, problem: FrameProblem, ind: np.ndarray, f: float, deadline,
                mirrored: bool = True) -> tuple[np.ndarray, float, int]:
        """Polish the best and its mirror image (a flipped body is a deep local optimum),
        then the region sweeps (the mirrored ones with ``mirrored``: :meth:`_mirror_sweeps`)."""
        evals = 0
        starts = [ind] + ([ops.mirror(ind[None], problem.mirror_pairs)[0]] if len(problem.mirror_pairs) else [])
        for start in starts:
            f0 = float(problem.fitness(start[None])[0])
            cand, fc, e = polish(problem, start, f0, self.settings.polish_rounds, deadline)
            evals += e + 1
            if fc > f:
                ind, f = cand, fc
        ind, f, e = self._sweep_regions(problem, ind, f, deadline)
        s = self.settings
        if s.wide_sweeps:
            ind, f, e2 = sweep_regions(problem, ind, f, s.wide_sweeps, s.wide_size, s.polish_rounds, deadline,
                                       wide=s.wide_candidates)
            e += e2
        if mirrored:
            ind, f, e2 = self._mirror_sweeps(problem, ind, f, deadline)
            e += e2
        return ind, f, evals + e

    def _mirror_sweeps(self, problem: FrameProblem, ind: np.ndarray, f: float, deadline) -> tuple[np.ndarray, float, int]:
        """A marker set's sweeps over the body neighbourhoods joined with their mirror images
        (``mirror_sweeps``; :func:`sweep_regions` with ``mirrored``); nothing for joint centres
        or a marker set without left/right pairs (its wide sweeps covered those regions)."""
        s = self.settings
        if not s.mirror_sweeps or not problem.model.marker_set or not len(problem.mirror_pairs):
            return ind, f, 0
        return sweep_regions(problem, ind, f, s.mirror_sweeps, s.wide_size, s.polish_rounds, deadline,
                             s.mirror_branches, wide=s.mirror_candidates, mirrored=True)

    def _sweep_regions(self, problem, ind, f, deadline):
        """:func:`sweep_regions` with this search's settings."""
        s = self.settings
        return sweep_regions(problem, ind, f, s.region_sweeps, s.region_size, s.polish_rounds, deadline,
                             s.region_branches)


def sweep_regions(problem: FrameProblem, ind: np.ndarray, f: float, sweeps: int, region_size: int,
                  polish_rounds: int, deadline: float | None = None,
                  branches: int = 0, wide: int = 0, mirrored: bool = False) -> tuple[np.ndarray, float, int]:
    """``sweeps`` passes of :func:`relabel_regions` over every label's region, each accepted
    relabelling polished; stops early when a pass changes nothing. The GA and polish leave
    labelings that are wrong over a few neighbouring labels at once (a limb shifted along its
    markers); this settles them exactly (``branches``: see :func:`relabel_regions`). ``wide``:
    each label's body neighbourhood instead, its labels sharing ``wide`` points;
    ``mirrored``: those neighbourhoods joined with their mirror images
    (:func:`~.dtm_dp.mirrored_regions`). Returns (ind, fitness, evaluations)."""
    evals = 0
    if sweeps <= 0 or problem.M <= 3 or problem.n == 0:
        return ind, f, evals
    regions = mirrored_regions(problem.model, region_size) if mirrored else \
        regions_of(problem.model, region_size, partner=not wide)
    # wide: each label's body neighbourhood, its labels sharing ``wide`` points
    candidates = functools.partial(shared_candidates, max_candidates=wide) if wide else region_candidates

    def refine(x, fx):
        return polish(problem, x, fx, polish_rounds, deadline)
    for _ in range(sweeps):
        if deadline is not None and time.perf_counter() > deadline:
            break
        f0 = f
        ind, f, e = relabel_regions(problem, ind, f, regions, range(problem.M), refine, branches, candidates)
        evals += e
        if f <= f0 + 1e-9:
            break
    return ind, f, evals


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


class CBGASearch(GASearch):
    """Constraint-based GA (section IV.A): model-guided initialisation, crossover along the
    structure order with repair, constraint-based mutation plus ruin-and-recreate."""

    name = "cbga"

    def _sample(self, problem, P, rng):
        # a ladder of temperatures: exact ancestral samples plus hotter, more diverse ones
        return guided_sample(problem, P, rng, self.settings.temperatures[np.arange(P) % len(self.settings.temperatures)])

    def _mating(self, problem):
        s, n = self.settings, problem.n
        order = np.array(problem.model.structure.to_string()[:3] +
                         [t[0] for t in problem.model.structure.triangles[1:]])
        return Mating(lambda a, b, rng: ops.crossover(a, b, order, n, rng),
                      lambda p, rng: ruin_and_recreate(problem, ops.mutate(p, n, rng, s.p_mutation,
                                                                           pairs=problem.mirror_pairs),
                                                       rng, s.p_recreate),
                      s.p_crossover)


class SimpleGASearch(GASearch):
    """The simple GA baseline: plain operators, invalid children get the death penalty."""

    name = "sga"
    finish = False

    def _mating(self, problem):
        s, n, M = self.settings, problem.n, problem.M
        return Mating(lambda a, b, rng: ops.crossover_plain(a, b, rng),
                      lambda p, rng: ops.mutate_plain(p, n, rng, s.p_mutation / max(M, 1) * 2, swap=True),
                      s.p_crossover)

    def _valid(self, problem):
        return lambda pop: ops.is_valid(pop, problem.n)


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
    return cls(settings) if issubclass(cls, GASearch) else cls()
