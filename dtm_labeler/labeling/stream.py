"""The stream labeler: points in, labelled points out, one frame at a time.

Per frame: sanitise -> tracker (ids, velocities) -> search (warm-started from the labels the
tracks carried last frame in ``stream`` mode; from scratch in ``single`` mode) -> votes over
the window (eq. 32) -> published labels with confidences. The library side of the ROS node
and of ``dtm-label``; no ROS imports.

Work per frame is bounded: at most ``max_points`` points enter the search (the ones nearest
the body's last centre), the GA has a generation cap, a stagnation stop and an optional
time budget. The fast path hill-climbs the carried-over labeling, then relabels body regions exactly
(``region_checks`` per frame, max-product DP given the rest of the body): around points
that just appeared (a marker back from a gap, a ghost), one region per frame in turn for
one pass after a GA search (or a reset), and one every ``region_every`` frames otherwise,
so a wrong labeling that tracking would carry on is put right. It is
accepted when it fits within ``accept_drop`` nats (or 5 x the running scatter of good
frames, if larger) of the running level; otherwise a warm GA runs, and a full search when
that still falls ``refit_drop`` (or 8 x the scatter) short. A full search that falls short
of the level times every point the frame could label is repeated from fresh populations
(``restarts``); each CBGA full search ends with an exact region sweep
(:meth:`..search.label_search.CBGASearch`, ``GASettings.region_sweeps``).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from ..model.dtm import TriangulatedModel
from ..search.label_search import GASettings, LabelSearch, make_search
from ..search.problem import Background, FrameProblem
from .tracker import Tracker, TrackerSettings
from .tracked import TrackedLabeler, scatter
from .voting import VoteBook

METHODS = ("cbga", "sga", "greedy", "exhaustive", "tracker")
MODES = ("stream", "single")


@dataclass
class LabelerSettings:
    method: str = "cbga"
    mode: str = "stream"
    window: int = 10
    full: GASettings = field(default_factory=lambda: GASettings(population=64, max_generations=80,
                                                                stagnation=10))
    warm: GASettings = field(default_factory=lambda: GASettings(population=24, max_generations=10,
                                                                stagnation=3, polish=True, polish_rounds=1,
                                                                p_recreate=0.15,
                                                                fresh_fraction=0.0, region_sweeps=0))
    background: Background = field(default_factory=Background)
    tracker: TrackerSettings = field(default_factory=TrackerSettings)
    max_points: int = 0                  # 0 = 2 x labels + 8
    refit_drop: float = 60.0             # nats below the running fitness level -> full search
    restarts: int = 2                    # more full searches (fresh populations) while still refit_drop short
    accept_drop: float = 30.0            # carried-over labeling accepted without GA within this
    fast_rounds: int = 4                 # hill-climbing rounds of the fast path
    swap_radius_m: float = 0.15          # fast path also tries swapping labels this close
    region_checks: int = 1               # body regions relabelled exactly (DP) per frame on the fast path
    region_size: int = 6                 # labels per region (see search.dtm_dp.model_regions)
    region_every: int = 240              # background region check every N frames (0 = only after searches)
    max_gap_s: float = 0.5               # longer input gaps reset window and tracks
    noise_mm: float = 0.0                # measurement noise (sd per coordinate) the model is widened by
    heading_snap_deg: float = 4.0        # candidates this close to the carried labeling's yaw share it
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}")
        if self.window < 1:
            raise ValueError("window must be >= 1")
        if not 0.0 <= self.noise_mm <= 500.0:
            raise ValueError("noise_mm must be in [0, 500]")
        if self.max_points < 0 or self.refit_drop <= 0 or self.max_gap_s <= 0 or self.accept_drop <= 0:
            raise ValueError("max_points >= 0 and refit_drop, accept_drop, max_gap_s > 0 required")
        if self.region_checks < 0 or self.region_size < 2 or self.region_every < 0:
            raise ValueError("region_checks, region_every must be >= 0 and region_size >= 2")
        if self.restarts < 0:
            raise ValueError("restarts must be >= 0")
        if not 0.0 <= self.heading_snap_deg <= 30.0:
            raise ValueError("heading_snap_deg must be in [0, 30]")


@dataclass
class FrameResult:
    labels: np.ndarray            # (n,) published label index per input point, -1 = unlabelled
    confidence: np.ndarray        # (n,) in [0, 1]
    track_ids: np.ndarray         # (n,) int64, -1 for dropped (non-finite) points
    search_labels: np.ndarray     # (n,) this frame's search result before voting
    assignment: np.ndarray        # (M,) point index per label from the search, -1 = missing
    log_likelihood: float         # fitness of the search result (see FrameProblem)
    latency_ms: float
    full_search: bool
    generations: int
    evaluations: int
    n_dropped: int = 0            # non-finite points removed
    n_ignored: int = 0            # finite points beyond max_points, left unlabelled
    reset: str = ""               # why the window was reset this frame, if it was
    heading: float = float("nan")
    truth_fitness: float = float("nan")   # fitness of the true labeling (evaluation only)


class StreamLabeler(TrackedLabeler):
    """Labels a stream of unlabeled point clouds with a trained :class:`TriangulatedModel`."""

    def __init__(self, model: TriangulatedModel, settings: LabelerSettings | None = None):
        self.settings = settings or LabelerSettings()
        self.set_model(model)

    def _build(self) -> None:
        s = self.settings
        self.rng = np.random.default_rng(s.seed)
        self.tracker = Tracker(s.tracker)
        self.votes = VoteBook(s.window if s.mode == "stream" else 1, self.model.n_labels)
        method = "cbga" if s.method == "tracker" else s.method
        self.full_search: LabelSearch = make_search(method, s.full)
        self.warm_search: LabelSearch = make_search(method, s.warm)
        self.reset()

    # -- state -------------------------------------------------------------------------------
    def reset(self) -> None:
        self._reset_stream()
        self.level = None                          # running fitness per labelled point (EMA)
        self.spread = 0.0                          # running RMS of fitness minus expected (nats)
        self._provisional = False

    def set_model(self, model: TriangulatedModel) -> None:
        """Swap the model (hot reload); window and tracks restart."""
        self.base_model = model
        self.model = model.with_noise(self.settings.noise_mm * 1e-3).warm_up()
        self._build()

    def update_settings(self, settings: LabelerSettings) -> None:
        """Apply new settings between frames: search budgets take effect at once; a new
        measurement noise rebuilds the model; tracker, window, mode or method restart the stream."""
        old, self.settings = self.settings, settings
        if settings.noise_mm != old.noise_mm:
            self.set_model(self.base_model)
        elif (settings.tracker, settings.window, settings.mode, settings.method) == \
                (old.tracker, old.window, old.mode, old.method):
            self.full_search.settings = settings.full
            self.warm_search.settings = settings.warm
        else:
            self._build()

    # -- the frame -----------------------------------------------------------------------------
    def process(self, xyz: np.ndarray, stamp: float, ids: np.ndarray | None = None,
                truth: np.ndarray | None = None) -> FrameResult:
        """Label one frame. ``truth`` (M,) -- the true input index per label, -1 missing -- is
        only for evaluation: its fitness on the same problem is returned (search errors)."""
        t0 = time.perf_counter()
        s = self.settings
        inp = self._begin(xyz, stamp, ids, self.model.n_labels)
        upd = inp.upd
        problem = FrameProblem(self.model, upd.states, s.background, self.heading, s.heading_snap_deg)
        n, M = problem.n, problem.M

        velocity_known = bool((problem.codes[:-1] == 2).any())
        seeds = self._seeds(upd.track_ids, n, M) if s.mode == "stream" and not self._provisional else None
        if seeds is not None:
            problem.anchor_heading(seeds[0])
        self._provisional = not velocity_known     # a labeling without velocities is re-searched next frame
        full = True
        outcome = None
        if seeds is not None:
            if s.method == "tracker":
                a = seeds[0]
                outcome = _Outcome(a, float(problem.fitness(a[None])[0]), 0, 1)
                full = False
            else:
                outcome = self._fast_path(problem, seeds[0])
                if outcome is None:
                    outcome = self.warm_search.search(problem, self.rng, seeds)
                full = self.level is not None and self._falls_short(outcome, problem)
        if self.level is None:
            self.level = self._initial_level(problem)
        if full:
            best = self._full_search(problem, seeds)
            if outcome is None or best.fitness >= outcome.fitness:
                outcome = best
        if full or outcome.generations > 0:
            self._note_search()
        f = float(outcome.fitness)
        truth_f = self._truth_fitness(problem, truth, inp)
        per_point = f / _label_weight(outcome.assignment, problem)
        if not self._provisional:                  # no velocities yet: do not learn from it
            resid = f - self._expected(outcome.assignment, problem)
            fits = resid >= -self._accept_margin()
            if fits:                               # how much a good frame's fitness scatters
                self.spread = float(np.sqrt(0.98 * self.spread ** 2 + 0.02 * resid ** 2))
            rate = 0.2 if fits else 0.05           # a subject that fits worse than training: adapt slowly
            self.level = (1 - rate) * self.level + rate * per_point

        assign, search_labels, pub, conf = self._publish(problem, outcome.assignment, inp)
        keep, n_in = inp.keep, inp.n_in
        return FrameResult(
            labels=scatter(pub, keep, n_in, -1), confidence=scatter(conf, keep, n_in, 0.0),
            track_ids=scatter(upd.track_ids, keep, n_in, -1), search_labels=scatter(search_labels, keep, n_in, -1),
            assignment=_input_index(assign, keep),
            log_likelihood=f, latency_ms=(time.perf_counter() - t0) * 1e3, full_search=full,
            generations=outcome.generations, evaluations=outcome.evaluations,
            n_dropped=int((~inp.finite).sum()), n_ignored=inp.n_ignored, reset=inp.reason,
            heading=self.heading if self.heading is not None else float("nan"), truth_fitness=truth_f)

    def _falls_short(self, outcome, problem: FrameProblem) -> bool:
        """The labeling fits ``refit_drop`` nats (or 8 x the running scatter) worse than the
        running level predicts for its labelled points: a search should look further."""
        return outcome.fitness < self._expected(outcome.assignment, problem) - self._refit_margin()

    def _full_search(self, problem: FrameProblem, seeds):
        """The full GA, repeated from fresh populations (up to ``restarts`` times) while its
        best falls ``refit_drop`` short of the level times the frame's labellable points
        (:func:`_frame_weight`): on 28-41 markers one run can
        stall in a deep local optimum -- limbs' labels exchanged -- that its mutations do not
        leave, while independent runs rarely share it. A frame that fits well costs one run."""
        best = self.full_search.search(problem, self.rng, seeds)
        restarts = self.settings.restarts if self.settings.method in ("cbga", "sga") else 0   # others: deterministic
        # judged against every point the frame could label, not only those labelled: a stalled
        # run often leaves several points unlabelled, which a per-labelled-point level forgives
        target = self.level * _frame_weight(problem) - self._refit_margin()
        for _ in range(restarts):
            if best.fitness >= target:
                break
            again = self.full_search.search(problem, self.rng, None)
            keep = again if again.fitness > best.fitness else best
            best = dataclasses.replace(keep, generations=best.generations + again.generations,
                                       evaluations=best.evaluations + again.evaluations)
        return best

    def _fast_path(self, problem: FrameProblem, seed: np.ndarray):
        """Accept the carried-over labeling after hill-climbing its targeted neighbourhood
        (:meth:`_hill_climb`) when it fits as well per labelled point as recent frames did;
        None sends the frame to the GA."""
        if self.level is None or self.settings.method != "cbga":
            return None
        ind, f, evals = self._hill_climb(problem, seed)
        if f < self._expected(ind, problem) - self._accept_margin():
            return None
        return _Outcome(ind, f, 0, evals)

    def _initial_level(self, problem: FrameProblem) -> float:
        """Typical fitness per labelled point: the model's training log-likelihood per label
        plus the per-label gain of the background model (see FrameProblem)."""
        ll = float(self.model.settings.get("loglik_per_label", 0.0))
        gains = problem.label_gain[:-1]
        if gains.size == 0:                        # no points this frame: nothing to calibrate on
            return ll
        full_gain = gains[problem.codes[:-1] == 2]
        return ll + float(full_gain.mean() if full_gain.size else np.median(gains))

    def _margin(self, floor: float, k: float) -> float:
        """A drop threshold: ``floor`` nats, or ``k`` times the running RMS scatter of good
        frames' fitness about the expected level where that is larger -- a model over 41
        markers scatters more per frame than one over 14, and a fixed threshold would send
        good frames to the GA (false alarms cost a search each)."""
        return max(floor, k * self.spread)

    def _accept_margin(self) -> float:
        """How far below the level a carried-over labeling (or a frame the level learns from) may fit."""
        return self._margin(self.settings.accept_drop, 5.0)

    def _refit_margin(self) -> float:
        """How far below the level a search result may fit before a (further) full search."""
        return self._margin(self.settings.refit_drop, 8.0)

    def _expected(self, assignment: np.ndarray, problem: FrameProblem) -> float:
        """Running fitness level scaled to this frame's labelled points."""
        return self.level * _label_weight(assignment, problem)


def _label_weight(assignment: np.ndarray, problem: FrameProblem) -> float:
    """How many labelled points, a point without a velocity (just reappeared) counting half:
    it carries 3 observed dimensions instead of 6, and about half the fitness."""
    codes = problem.codes[assignment[assignment < problem.n]]
    return max(float((codes == 2).sum() + 0.5 * (codes == 1).sum()), 1.0)


def _frame_weight(problem: FrameProblem) -> float:
    """:func:`_label_weight` of the best case: the frame's points (at most one per label,
    those with velocities first) all labelled."""
    codes = problem.codes[:-1]
    full = min(int((codes == 2).sum()), problem.M)
    return max(full + 0.5 * min(int((codes == 1).sum()), problem.M - full), 1.0)


def _input_index(assign: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Search assignment (index into the kept points, -1 missing) -> input point index."""
    out = np.full(assign.shape, -1, dtype=np.int64)
    present = assign >= 0
    out[present] = keep[assign[present]]
    return out


@dataclass
class _Outcome:
    assignment: np.ndarray
    fitness: float
    generations: int
    evaluations: int

