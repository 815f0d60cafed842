"""Labeling with a bank of action models used at once (Ukita 4.1 and 4.3, adapted to the GA).

The per-frame pipeline is :class:`~.tracked.TrackedLabeler`'s, the same as the single-model
:class:`~.stream.StreamLabeler`'s (tracker, votes, fast path, warm and full GA with restarts,
measurement noise, budgets, region sweeps); what a bank adds are the hooks:

**Population spread over the models (4.1 step 1, 4.3).** Every action model gets its own
:class:`FrameProblem`; the GA population is split into one island per model
(:meth:`~dtm_labeler.search.label_search.GASearch.search_models`) and every individual is
scored under *its own* model. An assignment (label -> point) means the same
under every model because a bank holds one label set (checked when it is loaded), so an
individual can be re-scored under another model: that is what migration needs.

**Migration (4.3 step 3).** Ukita moves a particle from model m to model n with probability
``exp(-s_n^2) / (exp(-s_m^2) + exp(-s_n^2))``, ``s^2`` the particle's variance (misfit) in a
model. Our misfit of an assignment ``x`` under model m is its negative log-likelihood per
labelled point in units of a temperature ``tau`` (``migration_temperature``):
``s_m^2 = -f_m(x) / (tau k(x))`` with ``f_m`` the :meth:`FrameProblem.fitness` and ``k(x)``
the number of labelled points. The rule then reads as the logistic of the fitness difference::

    p(m -> n) = 1 / (1 + exp(-(f_n(x) - f_m(x)) / (tau k(x))))

(1/2 for equal fit; toward the better-fitting model otherwise). After every GA generation each
non-elite individual draws one other model n uniformly and moves with that probability. The
paper restricts candidates to particles whose nearest sample is synthesized; a GA individual
has no latent position, so every individual is a candidate -- the fitness gate already keeps
movement low while the models disagree strongly. The best individual of each sub-population
is not moved (elitism), and every model keeps at least ``min_share`` individuals (re-filled from
the other models' best): the paper's random redistribution (step 1), so a model that fits badly
now can still win when the action changes. The share of the population each model holds is
carried to the next frame (particles persist); in frames labelled by the fast path (no GA) the
shares follow the same rule in expectation (mean-field step with the candidates' fitnesses).

**Synthesized transitions** act through the models: each model was trained with the paths to
the others (:mod:`dtm_labeler.training.transitions`), so near a switch both models fit the
in-between poses and individuals cross over early.

**Active action (4.3 step 4, smoothed).** Model evidence per frame ``g_m`` = best fitness of any
individual scored under m this frame (the published labeling is always scored under every
model, so all models are compared on at least one common labeling). Consecutive frames are far
from independent, so the evidence is tempered to ``e_m = g_m / (score_temperature k)`` (nats per
labelled point / temperature) and filtered by a sticky HMM forward recursion::

    alpha_m(t) ∝ exp(e_m(t)) * sum_n alpha_n(t-1) A_nm,   A_nn = 1 - eps, A_nm = eps / (K - 1)
    eps = 1 - exp(-switch_rate_hz * dt)

The active action is ``argmax alpha``. The published labeling is the best individual over all
models (joint MAP over model and labeling), as the issue asks. When the active action changes,
the next frame skips the fast path and runs the full multi-model GA (seeded with the carried
labels): the carried labeling was accepted under the old model's fitness level, and a wrong
labeling adopted at the switch would otherwise become the new normal.

**Hard switching** (``strategy='hard'``, the comparison baseline: one motion hypothesis at a
time, as in switching GPDMs): the whole population lives in the active model; after each frame
the labeling is scored under every model and the active model becomes the arg max at once.

``use_bank=False`` labels with one model only (``default_action``, else the first).
``method`` is honoured as for one model (``sga`` evolves the islands with plain operators;
``greedy`` and ``exhaustive`` search each model on its own, without migration).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model.bank import ModelBank
from ..search.evolve import Island
from ..search.label_search import SearchOutcome
from ..search.problem import FrameProblem
from .config import BANK_KEYS, STRATEGIES, LabelerSettings, check_fields, validate
from .tracked import Engine, FrameInput, FrameResult, FrameSearch, TrackedLabeler

#: weight of a frame's evidence in the level of a model that was not searched (hard strategy)
UNSEARCHED_LEVEL_RATE = 0.2


@dataclass
class BankSettings:
    use_bank: bool = True
    strategy: str = "spread"
    migration_temperature: float = 1.0     # tau: nats per labelled point
    min_share: int = 4                     # individuals each model keeps
    score_temperature: float = 4.0         # evidence tempering (nats per labelled point)
    switch_rate_hz: float = 1.0            # prior rate of action changes (HMM stickiness)
    default_action: str = ""               # active at the start; '' = the first action
    search_on_switch: bool = True          # full search in the frame after the active action changes

    def __post_init__(self) -> None:
        self.default_action = self.default_action or ""
        check_fields(self, {"strategy": "bank_strategy"})


def bank_settings_from_params(values: dict) -> BankSettings:
    """The :class:`BankSettings` of a flat parameter set (missing keys take the table defaults)."""
    v = validate({k: x for k, x in values.items() if k in BANK_KEYS or k == "use_bank"})
    return BankSettings(use_bank=True, strategy=v["bank_strategy"], migration_temperature=v["migration_temperature"],
                        min_share=v["min_share"], score_temperature=v["score_temperature"],
                        switch_rate_hz=v["switch_rate_hz"], default_action=v["default_action"],
                        search_on_switch=v["search_on_switch"])


@dataclass
class BankFrameResult(FrameResult):
    active_action: str = ""
    labeled_by: str = ""                                   # action whose individual was published
    action_scores: dict = field(default_factory=dict)      # g_m of this frame
    action_posterior: dict = field(default_factory=dict)   # alpha_m after this frame
    population: dict = field(default_factory=dict)         # individuals per action (end of frame)


def migration_probability(f_from: np.ndarray, f_to: np.ndarray, k: np.ndarray, tau: float) -> np.ndarray:
    """Ukita's ``exp(-s_n^2) / (exp(-s_m^2) + exp(-s_n^2))`` with ``s^2 = -f / (tau k)``."""
    z = (np.asarray(f_to, float) - np.asarray(f_from, float)) / (tau * np.maximum(np.asarray(k, float), 1.0))
    z = np.where(np.isfinite(z), z, np.where(np.asarray(f_to) > np.asarray(f_from), 50.0, -50.0))
    return 1.0 / (1.0 + np.exp(-np.clip(z, -50, 50)))


def allocate(total: int, shares: np.ndarray, floor: int) -> np.ndarray:
    """Integer sub-population sizes: ``floor`` each plus the rest in proportion to ``shares``."""
    K = len(shares)
    total = max(total, K * floor)
    extra = total - K * floor
    w = np.asarray(shares, float)
    w = w / w.sum() if w.sum() > 0 else np.full(K, 1.0 / K)
    raw = w * extra
    n = np.floor(raw).astype(int)
    rest = extra - n.sum()
    if rest > 0:
        n[np.argsort(-(raw - n))[:rest]] += 1
    return n + floor


class Migration:
    """The per-generation hook of the bank's GA (Ukita 4.3 step 3): each non-elite individual
    of an island tries one move to a random other island with :func:`migration_probability`;
    every island keeps at least ``min_share`` individuals (re-filled with the others' best,
    re-scored under its own model)."""

    def __init__(self, problems: list[FrameProblem], settings: BankSettings, rng: np.random.Generator):
        self.problems, self.settings, self.rng = problems, settings, rng

    def __call__(self, islands: list[Island], generation: int) -> int:
        bs, rng, n = self.settings, self.rng, self.problems[0].n
        K = len(islands)
        if K < 2:
            return 0
        moves, evals = [], 0
        for m, isl in enumerate(islands):
            P = len(isl.pop)
            if P <= bs.min_share:
                continue
            cand = np.setdiff1d(np.arange(P), [int(np.argmax(isl.fit))])
            others = [q for q in range(K) if q != m]
            dest = np.asarray(others)[rng.integers(len(others), size=cand.size)]
            f_to = np.empty(cand.size)
            for q in np.unique(dest):
                sel = dest == q
                f_to[sel] = self.problems[q].fitness(isl.pop[cand[sel]])
                evals += int(sel.sum())
            k = (isl.pop[cand] < n).sum(1)
            go = np.flatnonzero(rng.random(cand.size) < migration_probability(isl.fit[cand], f_to, k,
                                                                              bs.migration_temperature))
            go = go[:P - bs.min_share]
            if go.size:
                moves.append((m, cand[go], dest[go], f_to[go]))
        for m, idx, dest, f_to in moves:
            isl = islands[m]
            for q in np.unique(dest):
                sel = dest == q
                islands[q].pop = np.concatenate([islands[q].pop, isl.pop[idx[sel]]])
                islands[q].fit = np.append(islands[q].fit, f_to[sel])
            keep = np.setdiff1d(np.arange(len(isl.pop)), idx)
            isl.pop, isl.fit = isl.pop[keep], isl.fit[keep]
        for m, isl in enumerate(islands):
            short = bs.min_share - len(isl.pop)
            if short > 0:
                pool = np.concatenate([islands[q].pop for q in range(K) if q != m])
                pf = np.concatenate([islands[q].fit for q in range(K) if q != m])
                add = pool[np.argsort(-pf)[:short]]
                isl.pop = np.concatenate([isl.pop, add])
                isl.fit = np.append(isl.fit, self.problems[m].fitness(add))
                evals += len(add)
        return evals


class BankLabeler(TrackedLabeler):
    """Labels a point-cloud stream with every model of a :class:`ModelBank` at once."""

    result_type = BankFrameResult
    audit_when_lost = True       # a change of motion can leave the labeling lost (TrackedLabeler)

    def __init__(self, bank: ModelBank, settings: LabelerSettings | None = None,
                 bank_settings: BankSettings | None = None, engine: Engine | None = None):
        if len(bank) == 0:
            raise ValueError("empty model bank")
        self.bank = bank
        self.bank_settings = bank_settings or BankSettings()
        settings = settings or LabelerSettings()
        self._init_engine(engine or self.prepare(bank, self.bank_settings, settings.noise_mm), settings)

    @staticmethod
    def prepare(bank: ModelBank, bank_settings: BankSettings, noise_mm: float) -> Engine:
        """The bank's engine: every action model, or only ``default_action`` (else the first)
        when ``use_bank`` is off. Slow (see :meth:`Engine.prepare`)."""
        acts = BankLabeler.engine_actions(bank, bank_settings)
        return Engine.prepare([bank[a] for a in acts], noise_mm, acts)

    @staticmethod
    def engine_actions(bank: ModelBank, bank_settings: BankSettings) -> list[str]:
        """The actions whose models :meth:`prepare` puts in the engine."""
        acts = list(bank.actions)
        if not bank_settings.use_bank:
            one = bank_settings.default_action or acts[0]
            bank[one]                                    # KeyError naming the action if unknown
            acts = [one]
        return acts

    # -- set-up ------------------------------------------------------------------------
    def _build(self) -> None:
        b = self.bank_settings
        K = len(self.actions)
        start = self.actions.index(b.default_action) if b.default_action in self.actions else 0
        self.log_alpha = np.full(K, -np.log(K))
        self.shares = np.full(K, 1.0 / K)
        self.active = start
        if b.strategy == "hard":
            self.log_alpha = np.where(np.arange(K) == start, 0.0, -np.inf)
        super()._build()

    def reset(self) -> None:
        """Forget tracks, votes and levels (the action belief is kept: a short gap does not
        change what the person is doing)."""
        super().reset()
        self._switched = False

    def update_settings(self, settings: LabelerSettings, bank_settings: BankSettings | None = None,
                        engine: Engine | None = None) -> None:
        if bank_settings is not None and bank_settings != self.bank_settings:
            self.bank_settings = bank_settings
            self.engine = engine or self.prepare(self.bank, bank_settings, settings.noise_mm)
            self.settings = settings
            self._build()
            return
        super().update_settings(settings, engine)

    @property
    def actions(self) -> list[str]:
        return list(self.engine.names)

    @property
    def active_action(self) -> str:
        return self.actions[self.active]

    @property
    def model(self):
        """The active action's model."""
        return self.models[self.active]

    # -- hooks -------------------------------------------------------------------------------
    def _searched(self) -> list[int]:
        return [self.active] if self.bank_settings.strategy == "hard" else list(range(len(self.actions)))

    def _island_sizes(self, ga_population: int, searched: list[int]) -> list[int]:
        if len(searched) == 1:
            return [ga_population]
        return [int(x) for x in allocate(ga_population, self.shares[searched], self.bank_settings.min_share)]

    def _migration(self, problems: list[FrameProblem], searched: list[int]):
        return Migration([problems[m] for m in searched], self.bank_settings, self.rng) if len(searched) > 1 else None

    def _after_ga(self, searched: list[int], out: SearchOutcome) -> None:
        if len(searched) > 1 and sum(out.island_sizes):
            tot = sum(out.island_sizes)
            for i, m in enumerate(searched):
                self.shares[m] = out.island_sizes[i] / tot
            self.shares = self.shares / self.shares.sum()

    def _search_state(self) -> dict:
        return super()._search_state() | {"shares": self.shares.copy()}

    def _set_search_state(self, state: dict) -> None:
        super()._set_search_state(state)
        self.shares = state["shares"].copy()

    def _force_full(self) -> bool:
        """When the motion hypothesis changed last frame, the carried labeling was chosen under
        the old model: that frame gets a full search (seeded with it) under all models."""
        switched, self._switched = self._switched, False
        return switched and self.bank_settings.search_on_switch

    def _after_frame(self, problems: list[FrameProblem], found: FrameSearch, published: int,
                     inp: FrameInput) -> None:
        """Evidence per model (best fitness scored under it; the published labeling is scored
        under every model), levels of models not searched, the action belief and the shares."""
        assign = found.best.assignment
        n = problems[0].n
        k_lab = max(int((assign < n).sum()), 1)
        g = np.array([float(p.fitness(assign[None])[0]) for p in problems])
        for m, c in found.candidates.items():
            g[m] = max(g[m], c.fitness)
        for m in range(len(problems)):
            if m not in found.candidates and np.isfinite(g[m]):
                lvl = g[m] / k_lab
                self.level[m] = lvl if np.isnan(self.level[m]) or found.full else \
                    (1 - UNSEARCHED_LEVEL_RATE) * self.level[m] + UNSEARCHED_LEVEL_RATE * lvl
        self._g = g
        before = self.active
        self._update_belief(g, k_lab, inp.dt)
        self._switched = self.active != before
        if not found.full and self.bank_settings.strategy != "hard":
            self._mean_field_shares(g, k_lab)

    def _result_fields(self, published: int) -> dict:
        K = len(self.actions)
        post = np.exp(self.log_alpha - self.log_alpha.max())
        post /= post.sum()
        pop = self.settings.full.population
        sizes = allocate(pop, self.shares, self.bank_settings.min_share) if self.bank_settings.strategy != "hard" \
            else np.where(np.arange(K) == self.active, pop, 0)
        return dict(active_action=self.active_action, labeled_by=self.actions[published],
                    action_scores={a: float(self._g[i]) for i, a in enumerate(self.actions)},
                    action_posterior={a: float(post[i]) for i, a in enumerate(self.actions)},
                    population={a: int(sizes[i]) for i, a in enumerate(self.actions)})

    # -- action belief ---------------------------------------------------------------------
    def _update_belief(self, g: np.ndarray, k: int, dt: float | None) -> None:
        K = len(self.actions)
        if self.bank_settings.strategy == "hard":
            self.active = int(np.argmax(g))
            self.log_alpha = np.where(np.arange(K) == self.active, 0.0, -np.inf)
            return
        e = g / (self.bank_settings.score_temperature * k)
        e = np.where(np.isfinite(e), e, -1e9)
        if K > 1:
            step = dt if dt is not None and dt > 0 else 1.0 / 120.0
            eps = -np.expm1(-self.bank_settings.switch_rate_hz * step)
            A = np.full((K, K), np.log(eps / (K - 1)))
            np.fill_diagonal(A, np.log1p(-eps))
            prior = np.logaddexp.reduce(self.log_alpha[:, None] + A, axis=0)
        else:
            prior = np.zeros(1)
        la = prior + e
        self.log_alpha = la - np.logaddexp.reduce(la)
        self.active = int(np.argmax(self.log_alpha))

    def _mean_field_shares(self, g: np.ndarray, k: int) -> None:
        K = len(self.actions)
        if K < 2:
            return
        tau = self.bank_settings.migration_temperature
        P = migration_probability(g[:, None], g[None, :], np.full((K, K), k), tau)   # P[m, n]: m -> n
        np.fill_diagonal(P, 0.0)
        flow = self.shares[:, None] * P / (K - 1)
        self.shares = self.shares - flow.sum(1) + flow.sum(0)
        self.shares = np.maximum(self.shares, 1e-6)
        self.shares /= self.shares.sum()


__all__ = ["BankLabeler", "BankSettings", "bank_settings_from_params", "BankFrameResult", "Migration", "migration_probability", "allocate",
           "STRATEGIES"]
