"""Problem-independent GA pieces used by the one GA loop (:mod:`.evolve`).

Small pure functions over arrays (the pymoo/DEAP shape): geometric rank selection, elitism
and the termination rule. Problem-specific sampling, crossover, mutation and repair live
next to their encodings (:mod:`.structure_ops`, :mod:`.label_ops`). The paper's fitness
transformation (eq. 21) is strictly increasing, so rank selection on the log-likelihood
selects the same parents and it is never computed.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np


def geometric_rank_probabilities(n: int, q: float = 0.08) -> np.ndarray:
    """Normalised geometric ranking (Joines & Houck [29]): P(rank r) = q'(1-q)^(r-1)."""
    if not 0.0 < q < 1.0:
        raise ValueError("q must be in (0, 1)")
    p = q * (1.0 - q) ** np.arange(n)
    return p / p.sum()


def rank_select(fitness: np.ndarray, n: int, rng: np.random.Generator, q: float = 0.08) -> np.ndarray:
    """Indices of ``n`` parents drawn by geometric ranking (best rank first; NaN/-inf last)."""
    f = np.where(np.isfinite(fitness), fitness, -np.inf)
    order = np.argsort(-f, kind="stable")
    return order[rng.choice(len(f), size=n, p=geometric_rank_probabilities(len(f), q))]


def elite_indices(fitness: np.ndarray, n_elite: int) -> np.ndarray:
    f = np.where(np.isfinite(fitness), fitness, -np.inf)
    return np.argsort(-f, kind="stable")[:n_elite]


@dataclass
class Termination:
    """Stop at ``max_generations``, after ``stagnation`` generations without improvement
    of the best fitness by more than ``tol``, or when ``time_budget`` seconds are spent."""

    max_generations: int = 100
    stagnation: int = 20
    tol: float = 1e-9
    time_budget: float | None = None
    _best: float = field(default=-np.inf, init=False)
    _since: int = field(default=0, init=False)
    _t0: float = field(default_factory=time.perf_counter, init=False)
    reason: str = field(default="", init=False)

    def start(self) -> "Termination":
        self._best, self._since, self._t0, self.reason = -np.inf, 0, time.perf_counter(), ""
        return self

    def done(self, generation: int, best: float) -> bool:
        if best > self._best + self.tol:
            self._best, self._since = best, 0
        else:
            self._since += 1
        if generation >= self.max_generations:
            self.reason = "max_generations"
        elif self._since >= self.stagnation:
            self.reason = "stagnation"
        elif self.time_budget is not None and time.perf_counter() - self._t0 >= self.time_budget:
            self.reason = "time_budget"
        return bool(self.reason)
