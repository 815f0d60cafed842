"""The one genetic-algorithm loop of the project (section IV.A), pymoo-style.

A GA here is a loop over generations that never changes; what differs between the
structure search (training), the label search (every frame) and the bank's multi-model
label search (Ukita) is *what* is evolved and scored. Those parts are small objects:

* an :class:`Island` is one population with its objective (``evaluate``) and its
  ``offspring`` operator (crossover, mutation and repair composed -- :class:`Mating` for
  operators that act on whole populations at once, or any callable);
* :func:`evolve` runs the loop over one or more islands: geometric rank selection
  ([29], :func:`.ga.rank_select`), elitism, offspring, evaluation, then an optional
  per-generation ``hook`` (the bank's migration between action models is such a hook),
  until the :class:`~.ga.Termination` rule stops it.

Selection acts on the log-likelihood ranks, so the paper's transformed fitness (eq. 21,
``k / (c - f)``, strictly increasing in ``f``) selects exactly the same parents and is not
computed.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol, Sequence

import numpy as np

from .ga import Termination, elite_indices, rank_select


class Offspring(Protocol):
    """``(population, parents, rng) -> children``: ``parents`` holds ``2 k`` selected indices
    into ``population``; the operator pairs them and returns ``k`` children."""

    def __call__(self, pop: np.ndarray, parents: np.ndarray, rng: np.random.Generator) -> np.ndarray: ...


@dataclass
class Mating:
    """Parents paired first half with second half; crossover applied to a share
    ``p_crossover`` of the pairs (the rest copy their first parent), then mutation -- each a
    population-wide operator ``(pop..., rng) -> pop`` that ends in its own repair, so every
    child is valid (eq. 22-29)."""

    crossover: Callable[[np.ndarray, np.ndarray, np.random.Generator], np.ndarray]
    mutation: Callable[[np.ndarray, np.random.Generator], np.ndarray]
    p_crossover: float

    def __call__(self, pop: np.ndarray, parents: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        k = len(parents) // 2
        pa, pb = pop[parents[:k]], pop[parents[k:]]
        do_x = rng.random(k) < self.p_crossover
        kids = np.where(do_x.reshape((-1,) + (1,) * (pa.ndim - 1)), self.crossover(pa, pb, rng), pa)
        return self.mutation(kids, rng)


@dataclass
class Island:
    """One population evolving under one objective."""

    pop: np.ndarray
    evaluate: Callable[[np.ndarray], np.ndarray]
    offspring: Offspring
    fit: np.ndarray | None = None

    def best(self) -> tuple[np.ndarray, float]:
        i = int(np.argmax(self.fit))
        return self.pop[i].copy(), float(self.fit[i])


@dataclass
class Evolution:
    """What a run of :func:`evolve` did."""

    generations: int
    evaluations: int
    history: list[float] = field(default_factory=list)    # best fitness over all islands per generation
    stop_reason: str = ""


def evolve(islands: Sequence[Island], rng: np.random.Generator, termination: Termination, *,
           n_elite: int = 2, selection_q: float = 0.12,
           hook: Callable[[Sequence[Island], int], int] | None = None) -> Evolution:
    """Run the GA over ``islands`` in place (their ``pop``/``fit`` hold the final populations).

    Per generation and island: the ``n_elite`` best survive unchanged; ``P - n_elite``
    children come from pairs of parents drawn by geometric ranking and the island's
    ``offspring`` operator; all are scored with ``evaluate``. Then ``hook(islands,
    generation)`` may move individuals between islands (returning the evaluations it
    spent). Islands with fewer than two individuals sit a generation out.
    """
    evals = 0
    for isl in islands:
        if isl.fit is None:
            isl.fit = isl.evaluate(isl.pop)
            evals += len(isl.pop)
    history = [_best(islands)]
    term = termination.start()
    gen = 0
    while not term.done(gen, history[-1]):
        gen += 1
        for isl in islands:
            P = len(isl.pop)
            if P < 2:
                continue
            k = min(n_elite, P - 1)
            n_kids = P - k
            elite = isl.pop[elite_indices(isl.fit, k)]
            par = rank_select(isl.fit, 2 * n_kids, rng, selection_q)
            kids = isl.offspring(isl.pop, par, rng)
            isl.pop = np.concatenate([elite, kids])
            isl.fit = isl.evaluate(isl.pop)
            evals += n_kids
        if hook is not None:
            evals += hook(islands, gen)
        history.append(_best(islands))
    return Evolution(gen, evals, history, term.reason)


def _best(islands: Sequence[Island]) -> float:
    return max((float(np.max(i.fit)) for i in islands if len(i.fit)), default=-np.inf)


__all__ = ["Island", "Mating", "Offspring", "Evolution", "evolve"]
