"""Labeling with a bank of action models used at once (Ukita 4.1 and 4.3, adapted to the GA).

Per frame, the shared parts are those of :class:`~dtm_labeler.labeling.stream.StreamLabeler`
(same :class:`Tracker`, :class:`VoteBook`, :class:`FrameProblem`, GA operators); what differs:

**Population spread over the models (4.1 step 1, 4.3).** Every action model gets its own
:class:`FrameProblem`; the GA population is split into one sub-population per model and every
individual is scored under *its own* model. An assignment (label -> point) means the same
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
The search is always the multi-model CBGA (``method='tracker'`` keeps its meaning: carried
labels, search only to start); other ``method`` values are treated as ``cbga``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..model.bank import ModelBank
from ..search import label_ops as ops
from ..search.ga import elite_indices, rank_select
from ..search.label_search import GASettings, guided_sample, polish, ruin_and_recreate
from ..search.problem import FrameProblem
from .stream import FrameResult, LabelerSettings
from .tracker import Tracker
from .tracked import TrackedLabeler, scatter
from .voting import VoteBook

STRATEGIES = ("spread", "hard")


@dataclass
class BankSettings:
    use_bank: bool = True
    strategy: str = "spread"
    migration_temperature: float = 1.0     # tau: nats per labelled point
    min_share: int = 4                     # individuals each model keeps
    score_temperature: float = 4.0         # evidence tempering (nats per labelled point)
    switch_rate_hz: float = 1.0            # prior rate of action changes (HMM stickiness)
    default_action: str | None = None
    search_on_switch: bool = True          # full search in the frame after the active action changes

    def __post_init__(self) -> None:
        if self.strategy not in STRATEGIES:
            raise ValueError(f"strategy must be one of {', '.join(STRATEGIES)}")
        if not self.migration_temperature > 0 or not self.score_temperature > 0:
            raise ValueError("temperatures must be > 0")
        if self.min_share < 1 or not self.switch_rate_hz > 0:
            raise ValueError("min_share >= 1 and switch_rate_hz > 0 required")


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


@dataclass
class _Sub:
    pop: np.ndarray
    fit: np.ndarray


class BankLabeler(TrackedLabeler):
    """Labels a point-cloud stream with every model of a :class:`ModelBank` at once."""

    def __init__(self, bank: ModelBank, settings: LabelerSettings | None = None,
                 bank_settings: BankSettings | None = None):
        if len(bank) == 0:
            raise ValueError("empty model bank")
        self.settings = settings or LabelerSettings()
        self.bank_settings = bank_settings or BankSettings()
        self.bank = bank
        self._build()

    # -- set-up ------------------------------------------------------------------------
    def _build(self) -> None:
        s, b = self.settings, self.bank_settings
        # the bank searches with its own multi-model CBGA; 'tracker' keeps its meaning (carry labels,
        # search only to start); any other method name (sga, greedy, exhaustive) also uses the CBGA
        acts = self.bank.actions
        if not b.use_bank:
            one = b.default_action or acts[0]
            self.bank[one]
            acts = [one]
        self.actions = list(acts)
        self.models = [self.bank[a].warm_up() for a in self.actions]    # densities, kernel: now, not on a frame
        self.M = self.models[0].n_labels
        self.rng = np.random.default_rng(s.seed)
        self.tracker = Tracker(s.tracker)
        self.votes = VoteBook(s.window if s.mode == "stream" else 1, self.M)
        K = len(self.actions)
        start = self.actions.index(b.default_action) if b.default_action in self.actions else 0
        self.log_alpha = np.full(K, -np.log(K))
        self.shares = np.full(K, 1.0 / K)
        self.active = start
        if b.strategy == "hard":
            self.log_alpha = np.where(np.arange(K) == start, 0.0, -np.inf)
        self.reset()

    def reset(self) -> None:
        """Forget tracks, votes and levels (the action belief is kept: a short gap does not
        change what the person is doing)."""
        self._reset_stream()
        self.level = np.full(len(self.actions), np.nan)
        self._switched = False

    def set_bank(self, bank: ModelBank) -> None:
        self.bank = bank
        self._build()

    def update_settings(self, settings: LabelerSettings, bank_settings: BankSettings | None = None) -> None:
        self.settings = settings
        if bank_settings is not None:
            self.bank_settings = bank_settings
        self._build()

    @property
    def active_action(self) -> str:
        return self.actions[self.active]

    @property
    def model(self):
        """The active action's model (StreamLabeler compatibility)."""
        return self.models[self.active]

    # -- the frame ---------------------------------------------------------------------------
    def process(self, xyz: np.ndarray, stamp: float, ids: np.ndarray | None = None,
                truth: np.ndarray | None = None) -> BankFrameResult:
        t0 = time.perf_counter()
        s, bs = self.settings, self.bank_settings
        inp = self._begin(xyz, stamp, ids, self.M)
        upd, dt = inp.upd, inp.dt
        problems = [FrameProblem(m, upd.states, s.background, self.heading, s.heading_snap_deg) for m in self.models]
        n = problems[0].n
        K = len(self.actions)
        hard = bs.strategy == "hard"
        searched = [self.active] if hard else list(range(K))

        seeds = self._seeds(upd.track_ids, n, self.M) if s.mode == "stream" else None
        if seeds is not None:
            for p in problems:
                p.anchor_heading(seeds[0])
        cands: dict[int, tuple[np.ndarray, float]] = {}
        gens = evals = 0
        full = True
        switched, self._switched = self._switched, False
        # when the motion hypothesis changed last frame, the carried labeling was chosen under the
        # old model: that frame gets a full search (seeded with it) under all models
        if seeds is not None and not (switched and bs.search_on_switch):
            if s.method == "tracker":
                for m in searched:
                    cands[m] = (seeds[0], float(problems[m].fitness(seeds[0][None])[0]))
                full = False
            else:
                fast = {m: self._hill_climb(problems[m], seeds[0])[:2] for m in searched}
                if any(c[1] >= self._expected(m, c[0], n) - s.accept_drop for m, c in fast.items()):
                    cands, full = fast, False
                    evals += len(cands)
                else:
                    res, g, e = self._bank_ga(problems, searched, s.warm, seeds)
                    cands, gens, evals = res, gens + g, evals + e
                    m_best = max(cands, key=lambda m: cands[m][1])
                    full = (np.isnan(self.level[m_best]) or
                            cands[m_best][1] < self._expected(m_best, cands[m_best][0], n) - s.refit_drop)
        if full:
            res, g, e = self._bank_ga(problems, searched, s.full, seeds)
            gens, evals = gens + g, evals + e
            for m, c in res.items():
                if m not in cands or c[1] >= cands[m][1]:
                    cands[m] = c
        if gens > 0 or full:
            self._note_search()
        # published: best individual over the searched models (each under its own model)
        m_pub = max(cands, key=lambda m: cands[m][1])
        assign_n, f = cands[m_pub]
        k_lab = max(int((assign_n < n).sum()), 1)
        # evidence per model: best fitness scored under it; the published labeling under all
        g = np.full(K, -np.inf)
        for m in range(K):
            fm = float(problems[m].fitness(assign_n[None])[0])
            g[m] = max(fm, cands[m][1]) if m in cands else fm
        for m in range(K):
            if np.isfinite(g[m]):
                lvl = g[m] / k_lab if m not in cands else cands[m][1] / max(int((cands[m][0] < n).sum()), 1)
                self.level[m] = lvl if np.isnan(self.level[m]) or full else 0.8 * self.level[m] + 0.2 * lvl
        self._update_action(g, k_lab, dt)
        if not full and not hard:
            self._mean_field_shares(g, k_lab)

        truth_f = self._truth_fitness(problems[m_pub], truth, inp)
        assign, search_labels, pub, conf = self._publish(problems[m_pub], assign_n, inp)
        keep, n_in = inp.keep, inp.n_in
        present = assign >= 0
        a_in = np.full(assign.shape, -1, dtype=np.int64)
        a_in[present] = keep[assign[present]]
        post = np.exp(self.log_alpha - self.log_alpha.max())
        post /= post.sum()
        sizes = allocate(s.full.population, self.shares, bs.min_share) if not hard else \
            np.where(np.arange(K) == self.active, s.full.population, 0)
        return BankFrameResult(
            labels=scatter(pub, keep, n_in, -1), confidence=scatter(conf, keep, n_in, 0.0),
            track_ids=scatter(upd.track_ids, keep, n_in, -1), search_labels=scatter(search_labels, keep, n_in, -1),
            assignment=a_in, log_likelihood=f,
            latency_ms=(time.perf_counter() - t0) * 1e3, full_search=full, generations=gens, evaluations=evals,
            n_dropped=int((~inp.finite).sum()), n_ignored=inp.n_ignored, reset=inp.reason,
            heading=self.heading if self.heading is not None else float("nan"), truth_fitness=truth_f,
            active_action=self.active_action, labeled_by=self.actions[m_pub],
            action_scores={a: float(g[i]) for i, a in enumerate(self.actions)},
            action_posterior={a: float(post[i]) for i, a in enumerate(self.actions)},
            population={a: int(sizes[i]) for i, a in enumerate(self.actions)})

    # -- action belief ---------------------------------------------------------------------
    def _update_action(self, g: np.ndarray, k: int, dt: float | None) -> None:
        before = self.active
        self._update_belief(g, k, dt)
        self._switched = self.active != before

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

    # -- search ------------------------------------------------------------------------------
    def _expected(self, m: int, assignment: np.ndarray, n: int) -> float:
        lvl = self.level[m]
        if np.isnan(lvl):
            return -np.inf
        return lvl * max(int((assignment < n).sum()), 1)

    def _initial(self, problem: FrameProblem, size: int, seeds: np.ndarray | None, ga: GASettings) -> np.ndarray:
        M, n = problem.M, problem.n
        if seeds is not None and len(seeds):
            sd = ops.repair(np.asarray(seeds, dtype=np.int64).reshape(-1, M), n, self.rng)
            k = min(len(sd), size)
            fresh = (size - k) // 4
            parts = [sd[:k], ops.mutate(np.repeat(sd[:1], size - k - fresh, 0), n, self.rng, 1.0)]
            if fresh:
                parts.append(guided_sample(problem, fresh, self.rng, ga.temperatures[np.arange(fresh) % len(ga.temperatures)]))
            return np.concatenate(parts)
        return guided_sample(problem, size, self.rng, ga.temperatures[np.arange(size) % len(ga.temperatures)])

    def _bank_ga(self, problems: list[FrameProblem], searched: list[int], ga: GASettings,
                 seeds: np.ndarray | None) -> tuple[dict[int, tuple[np.ndarray, float]], int, int]:
        """One frame's GA with a sub-population per model and migration between them."""
        bs = self.bank_settings
        rng = self.rng
        n = problems[0].n
        if len(searched) == 1:
            sizes = {searched[0]: ga.population}
        else:
            alloc = allocate(ga.population, self.shares[searched], bs.min_share)
            sizes = dict(zip(searched, alloc))
        subs: dict[int, _Sub] = {}
        evals = 0
        for m in searched:
            pop = self._initial(problems[m], int(sizes[m]), seeds, ga)
            subs[m] = _Sub(pop, problems[m].fitness(pop))
            evals += len(pop)
        orders = {m: np.array(problems[m].model.structure.to_string()[:3] +
                              [t[0] for t in problems[m].model.structure.triangles[1:]]) for m in searched}
        best_hist = [max(float(sb.fit.max()) for sb in subs.values())]
        stall, gen = 0, 0
        while gen < ga.max_generations and stall < ga.stagnation:
            gen += 1
            for m in searched:
                sb, pr = subs[m], problems[m]
                P = len(sb.pop)
                if P < 2:
                    continue
                n_el = min(max(ga.n_elite, 1), P - 1)
                elite = sb.pop[elite_indices(sb.fit, n_el)]
                kids_n = P - n_el
                par = rank_select(sb.fit, 2 * kids_n, rng, ga.selection_q)
                pa, pb = sb.pop[par[:kids_n]], sb.pop[par[kids_n:]]
                do_x = rng.random(kids_n) < ga.p_crossover
                kids = np.where(do_x[:, None], ops.crossover(pa, pb, orders[m], n, rng), pa)
                kids = ops.mutate(kids, n, rng, ga.p_mutation, pairs=pr.mirror_pairs)
                kids = ruin_and_recreate(pr, kids, rng, ga.p_recreate)
                sb.pop = np.concatenate([elite, kids])
                sb.fit = pr.fitness(sb.pop)
                evals += kids_n
            if len(searched) > 1:
                evals += self._migrate(subs, problems, searched)
            best = max(float(sb.fit.max()) for sb in subs.values())
            stall = stall + 1 if best <= best_hist[-1] + 1e-9 else 0
            best_hist.append(max(best, best_hist[-1]))
        out = {}
        for m in searched:
            sb = subs[m]
            i = int(np.argmax(sb.fit))
            out[m] = (sb.pop[i].copy(), float(sb.fit[i]))
        if ga.polish:
            m = max(out, key=lambda q: out[q][1])
            pr = problems[m]
            ind, f = out[m]
            starts = [ind] + ([ops.mirror(ind[None], pr.mirror_pairs)[0]] if len(pr.mirror_pairs) else [])
            for st in starts:
                f0 = float(pr.fitness(st[None])[0])
                c, fc, e = polish(pr, st, f0, ga.polish_rounds)
                evals += e + 1
                if fc > f:
                    ind, f = c, fc
            out[m] = (ind, f)
        if len(searched) > 1:
            tot = sum(len(subs[m].pop) for m in searched)
            for m in searched:
                self.shares[m] = len(subs[m].pop) / tot
            self.shares = self.shares / self.shares.sum()
        return out, gen, evals

    def _migrate(self, subs: dict[int, _Sub], problems: list[FrameProblem], searched: list[int]) -> int:
        """Each non-elite individual tries one move to a random other model (Ukita 4.3 step 3)."""
        bs, rng = self.bank_settings, self.rng
        n = problems[0].n
        moves: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        evals = 0
        for m in searched:
            sb = subs[m]
            P = len(sb.pop)
            if P <= bs.min_share:
                continue
            cand = np.setdiff1d(np.arange(P), [int(np.argmax(sb.fit))])
            others = [q for q in searched if q != m]
            dest = np.asarray(others)[rng.integers(len(others), size=cand.size)]
            f_to = np.empty(cand.size)
            for q in np.unique(dest):
                sel = dest == q
                f_to[sel] = problems[q].fitness(sb.pop[cand[sel]])
                evals += int(sel.sum())
            k = (sb.pop[cand] < n).sum(1)
            p = migration_probability(sb.fit[cand], f_to, k, bs.migration_temperature)
            go = np.flatnonzero(rng.random(cand.size) < p)
            room = P - bs.min_share
            go = go[:room]
            if go.size:
                moves.append((m, 0, cand[go], np.stack([dest[go], f_to[go]], 1)))
        for m, _, idx, dest_f in moves:
            sb = subs[m]
            for (q, fq), i in zip(dest_f, idx):
                q = int(q)
                subs[q].pop = np.concatenate([subs[q].pop, sb.pop[i][None]])
                subs[q].fit = np.append(subs[q].fit, fq)
            keep = np.setdiff1d(np.arange(len(sb.pop)), idx)
            sb.pop, sb.fit = sb.pop[keep], sb.fit[keep]
        # every model keeps min_share individuals: refill with the best of the others, re-scored
        for m in searched:
            sb = subs[m]
            short = bs.min_share - len(sb.pop)
            if short > 0:
                pool = np.concatenate([subs[q].pop for q in searched if q != m])
                pf = np.concatenate([subs[q].fit for q in searched if q != m])
                add = pool[np.argsort(-pf)[:short]]
                sb.pop = np.concatenate([sb.pop, add])
                sb.fit = np.append(sb.fit, problems[m].fitness(add))
                evals += len(add)
        return evals


__all__ = ["BankLabeler", "BankSettings", "BankFrameResult", "migration_probability", "allocate", "STRATEGIES"]
