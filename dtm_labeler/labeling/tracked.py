"""The labeler: one per-frame pipeline for one model or a bank of models.

:class:`TrackedLabeler` is a template (the shape of scikit-learn's ``BaseMixture``): it owns
the stream state and every step of a frame, written once --

1. :meth:`_begin`: sanitise the cloud (non-finite points dropped), time checks (backwards,
   repeated stamps, gaps reset the stream), bound the points (``max_points`` nearest the
   body), track (:class:`~.tracker.Tracker`: ids, velocities);
2. one :class:`~dtm_labeler.search.problem.FrameProblem` per model (the fitness of eq. 14,
   18-21 with marginalisation, eq. 30-31);
3. the search (:meth:`_search_frame`): in ``stream`` mode the labels the tracks carried
   last frame seed a *fast path* -- a hill-climb over targeted moves and exact region checks
   (:mod:`.fast_path`) -- accepted when the labeling fits as well as recent
   frames did; otherwise a warm-started GA, and a full GA (repeated from fresh populations,
   ``restarts``) when that still falls short; ``single`` mode searches every frame afresh;
4. the running fitness level and its scatter (what "fits as well as recent frames" means);
5. votes over the window (eq. 32) and the published labels with confidences (:meth:`_publish`).

What a subclass says is only how a frame is searched over its models
(:class:`~.stream.StreamLabeler`: one model; :class:`~.bank_labeler.BankLabeler`: one
island per action model with migration, the active action) through a few hooks:
:meth:`_searched`, :meth:`_island_sizes`, :meth:`_migration`, :meth:`_force_full`,
:meth:`_after_frame` and :meth:`_result_fields`. Measurement noise (``noise_mm``), budgets,
restarts, seeding (``fresh_fraction``) and region sweeps are read here, so no setting can be
ignored by one of them.

The models a labeler scores with come as an :class:`Engine`: the models as trained or loaded,
widened by the declared measurement noise and warmed up (densities built, kernel compiled).
Building one is slow (about 0.1 s per model); :meth:`Engine.prepare` is pure, so a node can
build it on another thread and hand it over with :meth:`TrackedLabeler.update_settings`
(``engine=``) or :meth:`TrackedLabeler.set_engine`, which are then fast.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from ..model.body import segment_clusters
from ..model.dtm import TriangulatedModel
from ..model.features import FULL, POSITION_ONLY
from ..search import dp_kernels, frame_kernels, label_ops, move_kernels, sample_kernels
from ..search.dtm_dp import turned_labels, turned_round
from ..search.upright import BEND_PITCHES_DEG, bent_problems, upright_problems
from ..search.label_search import CBGASearch, GASearch, GASettings, LabelSearch, SearchOutcome, make_search, polish
from ..search.problem import FrameProblem
from .anonymous_presence import AnonymousPresence, anonymous_presence
from .config import LabelerSettings
from .bar_flips import take_bar_orders
from .bar_order_votes import SETTLED_S, BarOrderVotes
from .cluster_evidence import ClusterEvidence
from .confidence import CONFIRMATION_POWER, ClutterShare, label_posteriors, published_confidence, unlabelled_posteriors
from .fast_path import RESUMED_EVENT_REGIONS, RESUMED_EVENT_S, YOUNG_S, FastPath
from .fit_check import expected_share, pattern_means, term_floors
from .label_tenure import LabelTenure
from .recovery import InlineRecovery, ProcessRecovery, Recovery, RecoveryRequest, RecoveryResult
from . import label_tenure, tracker, voting
from .tracker import Tracker, TrackUpdate
from .voting import VoteBook

#: level learning rates: frames that fit teach the level fast, frames that do not (a subject
#: that fits worse than the training people) slowly
LEVEL_RATE_FIT, LEVEL_RATE_MISFIT = 0.2, 0.05
#: weight of a new frame in the running RMS scatter of good frames' fitness
SPREAD_RATE = 0.02
#: a frame teaches the level and its scatter at those rates times (share of the labels it
#: can show) ** SEEN_POWER: a frame with half the markers hidden fits a fraction of a full
#: frame's nats per point (its triangles are marginalised), and learning from it dragged the
#: level down and widened the scatter until nothing triggered a search (41 markers, 50 %
#: hidden: level 14 -> 5 nats per point, accept margin 30 -> 130 nats, a labeling 100 nats
#: below the truth carried for hundreds of frames; stream accuracy 46 -> 79 % with power 8).
#: A frame with every label seen learns as before.
SEEN_POWER = 8.0
#: a frame teaching the level less than this share of a fully seen frame does not correct a
#: level set without velocities by itself (:meth:`TrackedLabeler._level_with_velocities`)
UNTAUGHT_WEIGHT = 0.25
#: accept / refit margins in units of that scatter (when larger than the nats floors)
ACCEPT_SCATTERS, REFIT_SCATTERS = 5.0, 8.0
#: a point seen without a velocity (just appeared) carries half the dimensions of one with
POSITION_ONLY_WEIGHT = 0.5
#: audits per audit period: region sweeps, the last of them a full search from scratch
AUDITS_PER_PERIOD = 4
#: frames in a row with a label far below its floors before a background audit is asked at once
MISFIT_FRAMES = 3
#: inline: nats per labelled point below the model's own fit reference (what a right labeling of
#: the training people shows; the confidence's yardstick) past which a frame counts as lost --
#: right labelings sit 2-6 below it where the model holds, a lost one 13-17 (bank, walk -> dance)
LOST_NATS = 10.0
#: inline: nats an audit's labeling must gain per label it changes to replace the carried one.
#: The model can prefer a wrong labeling by a little (41 HDM05 markers, clean: an audit gained
#: 24 nats by changing 18 labels, the truth 39 below the carried labeling; taken, 97.4 -> 91.8 %);
#: a lost labeling's audit gains far more (bank walk -> dance: 64 nats; 41 markers: 347 nats for 9)
AUDIT_GAIN_PER_LABEL = 3.0
#: inline: the longest wait between audits, in audit periods (it doubles after an audit that
#: found nothing better, so a take the model fits badly throughout is not searched every period)
AUDIT_BACKOFF_MAX = 8


@dataclass(frozen=True)
class Engine:
    """The models a labeler scores with (one per action; one entry for a single model)."""

    names: tuple[str, ...]                       # action names ('' for a single model)
    base: tuple[TriangulatedModel, ...]          # as trained / loaded
    models: tuple[TriangulatedModel, ...]        # widened by noise_mm and warmed up
    noise_mm: float
    floors: tuple[np.ndarray, ...] = ()          # per model: triangle term floors (fit_check.term_floors)

    @classmethod
    def prepare(cls, models: TriangulatedModel | Sequence[TriangulatedModel], noise_mm: float,
                names: Sequence[str] | None = None) -> "Engine":
        """Widen every model by ``noise_mm`` of measurement noise (:meth:`TriangulatedModel.with_noise`)
        and warm it up. Slow; touches no labeler, so it may run on any thread."""
        base = (models,) if isinstance(models, TriangulatedModel) else tuple(models)
        names = tuple(names) if names is not None else ("",) * len(base)
        if not base or len(names) != len(base):
            raise ValueError("an engine needs at least one model and one name per model")
        if any(m.labels != base[0].labels for m in base[1:]):
            raise ValueError("the models of one engine must share their labels, in order")
        models = tuple(m.with_noise(noise_mm * 1e-3).warm_up() for m in base)
        frame_kernels.warm_up()
        dp_kernels.warm_up()
        move_kernels.warm_up()
        sample_kernels.warm_up()
        tracker.warm_up()
        voting.warm_up()
        label_tenure.warm_up()
        for m in models:
            pattern_means(m)                          # drawn here, not on a stream's frame
        return cls(names, base, models, float(noise_mm), tuple(term_floors(m) for m in models))

    def with_noise(self, noise_mm: float) -> "Engine":
        """The same models for another declared noise (self when it is the same)."""
        return self if noise_mm == self.noise_mm else Engine.prepare(self.base, noise_mm, self.names)

    @property
    def labels(self) -> tuple[str, ...]:
        return self.base[0].labels


@dataclass
class FrameInput:
    """One cloud after sanitising and tracking."""

    n_in: int                 # points received
    finite: np.ndarray        # (n_in,) bool
    keep: np.ndarray          # input indices that enter the search
    pts: np.ndarray           # (n, 3) their positions
    upd: TrackUpdate          # track ids and states of the kept points
    reason: str               # why the window was reset, if it was
    n_ignored: int            # finite points beyond max_points
    dt: float | None          # seconds since the previous frame
    ids: np.ndarray           # (n,) the ids reported: the input's, else the tracker's


@dataclass
class FrameResult:
    labels: np.ndarray            # (n,) published label index per input point, -1 = unlabelled
    confidence: np.ndarray        # (n,) in [0, 1]
    track_ids: np.ndarray         # (n,) int64, -1 for dropped (non-finite) points
    search_labels: np.ndarray     # (n,) this frame's search result before voting
    assignment: np.ndarray        # (M,) input point index per label from the search, -1 = missing
    log_likelihood: float         # fitness of the search result (see FrameProblem)
    latency_ms: float             # the frame's labeling, without scoring the truth (``truth_ms``)
    full_search: bool
    generations: int
    evaluations: int
    n_dropped: int = 0            # non-finite points removed
    n_ignored: int = 0            # finite points beyond max_points, left unlabelled
    reset: str = ""               # why the window was reset this frame, if it was
    heading: float = float("nan")
    truth_fitness: float = float("nan")   # fitness of the true labeling (evaluation only)
    truth_prior: float = 0.0      # nats the fast path's priors charge the truth beyond this labeling (evaluation)
    truth_ms: float = 0.0         # time scoring ``truth`` (evaluation only; 0.1-0.15 ms at 14 points), not in latency_ms
    doubtful: bool = False        # published before a search vouched for it (background recovery running)
    recovered: bool = False       # a background search's labeling joined in this frame
    recovering: bool = False      # a background search is running after this frame
    posterior: np.ndarray | None = None    # (n,) local posterior of the search's label of each point
    vote_share: np.ndarray | None = None   # (n,) votes of the published label / frames the track was seen
    confirmation: np.ndarray | None = None  # (n,) confidence counting the release in full (subject calibration)


@dataclass
class CarriedFrame:
    """A frame the labeler followed without searching it (:meth:`TrackedLabeler.observe`): each
    point gets the label (and confidence) its track was last published with, -1 for a point
    whose track is new or was unlabelled."""

    labels: np.ndarray            # (n,) label index per input point, -1 = unlabelled
    confidence: np.ndarray        # (n,)
    track_ids: np.ndarray         # (n,) int64, -1 for dropped (non-finite) points


@dataclass
class Candidate:
    """A labeling of this frame under one model: assignment (label -> point, ``n`` missing)."""

    assignment: np.ndarray
    fitness: float
    neighbourhood: tuple | None = None     # (alternatives, their fitness) around it, if already scored


#: a search from scratch fitting below this share of the level (per labellable point, as the
#: restarts judge it) also tries the body bent at the hips (:meth:`TrackedLabeler._bend_check`)
BEND_SHARE = 0.6


@dataclass
class FrameSearch:
    """What the search of one frame found: the best labeling under each searched model."""

    candidates: dict[int, Candidate]
    full: bool
    generations: int = 0
    evaluations: int = 0
    doubtful: bool = False        # no search vouches for it yet (a recovery runs in the background)
    recovered: bool = False       # a background search's labeling joined this frame

    @property
    def best_model(self) -> int:
        return max(self.candidates, key=lambda m: self.candidates[m].fitness)

    @property
    def best(self) -> Candidate:
        return self.candidates[self.best_model]

    def merge(self, other: "FrameSearch") -> None:
        """Keep, per model, the better of the two candidates (ties: ``other``)."""
        for m, c in other.candidates.items():
            if m not in self.candidates or c.fitness >= self.candidates[m].fitness:
                self.candidates[m] = c
        self.full = self.full or other.full
        self.generations += other.generations
        self.evaluations += other.evaluations

    def bests(self) -> dict[int, tuple[np.ndarray, float]]:
        """Model -> (assignment, fitness): what a :class:`RecoveryResult` carries."""
        return {m: (c.assignment, c.fitness) for m, c in self.candidates.items()}


def _find(keys: np.ndarray, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index into the sorted ``keys``, found) of each of ``tracks`` (vectorised dict lookup)."""
    if keys.size == 0:
        return np.zeros(tracks.size, dtype=np.int64), np.zeros(tracks.size, dtype=bool)
    pos = np.minimum(np.searchsorted(keys, tracks), keys.size - 1)
    return pos, keys[pos] == tracks


def scatter(values: np.ndarray, keep: np.ndarray, n_in: int, fill) -> np.ndarray:
    """Per-kept-point values back to input order (``fill`` for dropped points)."""
    out = np.full(n_in, fill, dtype=np.asarray(values).dtype)
    out[keep] = values
    return out


def label_weight(assignment: np.ndarray, problem: FrameProblem) -> float:
    """How many labelled points, a point without a velocity (just reappeared) counting half:
    it carries 3 observed dimensions instead of 6, and about half the fitness."""
    codes = problem.codes[assignment[assignment < problem.n]]
    return max(float((codes == FULL).sum() + POSITION_ONLY_WEIGHT * (codes == POSITION_ONLY).sum()), 1.0)


def pattern_weight(assignment: np.ndarray, problem: FrameProblem) -> float:
    """How many fully seen labels' worth of fitness a right labeling with ``assignment``'s
    observation pattern is expected to show: the model's count of labels times the share
    :func:`~.fit_check.expected_share` reads from its own mean terms per pattern (a label whose
    triangle neighbours are hidden weighs what its marginal terms, eq. 30-31, are worth);
    :func:`label_weight` for a model whose fully seen expectation is not positive."""
    share = expected_share(problem, assignment)
    return max(problem.M * share, 1.0) if np.isfinite(share) else label_weight(assignment, problem)


def frame_weight(problem: FrameProblem) -> float:
    """:func:`label_weight` of the best case: the frame's points (at most one per label,
    those with velocities first) all labelled."""
    codes = problem.codes[:-1]
    full = min(int((codes == FULL).sum()), problem.M)
    return max(full + POSITION_ONLY_WEIGHT * min(int((codes == POSITION_ONLY).sum()), problem.M - full), 1.0)


def full_settings(settings) -> GASettings:
    """The full search's settings of a labeler's ``settings``: the mirrored sweeps
    (``mirror_sweeps``) in single-frame mode only, where every frame is a search from scratch.
    In a stream the full searches are cold starts and recoveries, which tracking then carries:
    there they cost the suite a minute and the 12 upper-body markers half hidden their take
    pass's lift (80.65 -> 80.14 % after the second pass, a mirrored neighbourhood being the whole
    body), the 55-marker Qualisys walk's gapped halves 99.49 -> 99.29 % while HDM05's rose 99.01 ->
    99.18 % (``results/search_errors.md``, 2026-12-07)."""
    return settings.full if settings.mode == "single" else replace(settings.full, mirror_sweeps=0)


class TrackedLabeler(FastPath):
    """The per-frame pipeline (module doc). Subclasses call :meth:`_init_engine` and fill
    the hooks; ``result_type`` is the dataclass of :meth:`process`'s result."""

    result_type = FrameResult
    _interim = None              # the InterimReporter of the recovery search running here (a worker's)
    #: inline: audit a frame that fits ``LOST_NATS`` per label below the model's fit reference
    #: (:meth:`_inline_audit`). Off for one model: on motions it never saw, right labelings fit
    #: that far below too and the audit's from-scratch labeling, which the model prefers, is the
    #: wrong one (dtm-eval generalisation streams with it: other take of a dance 98.9 -> 94.1 %,
    #: leave-subject-55-out 94.8 -> 83.1 %, a walk of another lab 100 -> 88.9 %). A bank holds
    #: the motions it labels, and a change of motion is where its recovery search can land on a
    #: wrong labeling (:class:`~.bank_labeler.BankLabeler` turns it on).
    audit_when_lost = False

    def _init_engine(self, engine: Engine, settings: LabelerSettings | None) -> None:
        self.settings = settings or LabelerSettings()
        self.engine = engine.with_noise(self.settings.noise_mm)
        self.recovery: Recovery = InlineRecovery(self)
        self._epoch = 0
        self._build()
        self._configure_recovery()

    def _configure_recovery(self) -> None:
        """The executor of recovery searches the settings ask for, told about the current
        models and settings."""
        background = self.settings.recovery == "background"        # "auto" is inline here: the node resolves it
        if background == self.recovery.inline or self.recovery.failed == "closed":
            self.recovery.close()
            self.recovery = ProcessRecovery(self) if background else InlineRecovery(self)
        else:
            self.recovery.configure(self)

    def close(self) -> None:
        """Stop the background recovery worker, if any (the labeler then searches inline)."""
        self.recovery.close()
        self.recovery = InlineRecovery(self)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- set-up --------------------------------------------------------------------------------
    @property
    def models(self) -> tuple[TriangulatedModel, ...]:
        return self.engine.models

    @property
    def n_labels(self) -> int:
        return self.models[0].n_labels

    def _build(self) -> None:
        """Everything the settings and the engine determine; restarts the stream."""
        s = self.settings
        self.rng = np.random.default_rng(s.seed)
        self.tracker = Tracker(s.tracker)
        self.votes = VoteBook(s.window if s.mode == "stream" else 1, self.n_labels)
        self.tenure = LabelTenure(self.n_labels)
        self.cluster_evidence = ClusterEvidence(self.models[0].rigid_clusters, s.cluster_memory_s)
        self.bar_votes = self._bar_votes()
        method = "cbga" if s.method == "tracker" else s.method
        self.full_search: LabelSearch = make_search(method, full_settings(s))
        self.warm_search: LabelSearch = make_search(method, s.warm)
        # searched frames in which each label held a point, anonymous points included (what
        # :mod:`.anonymous_presence` reads of a take)
        self.label_frames = np.zeros(self.n_labels, dtype=np.int64)
        self.frames_searched = 0
        self.reset()

    def _bar_votes(self) -> BarOrderVotes:
        """The bar orders' votes (:mod:`.bar_order_votes`) of the first model's body: rows only
        for a body calibrated to a person (:func:`~.bar_flips.take_bar_orders`)."""
        m = self.models[0]
        orders = take_bar_orders(m)
        groups = segment_clusters(m.n_labels, m.body.segments) if orders.shape[0] and m.body is not None else None
        return BarOrderVotes(orders, m.n_labels, groups, self._bar_gain())

    def _bar_gain(self) -> float:
        """``bar_order_gain`` in ``stream`` mode; 0 (off) in ``single`` mode, where every frame is
        labelled on its own: the votes are the tracks' memory, as the fast path's priors are."""
        return float(self.settings.bar_order_gain) if self.settings.mode == "stream" else 0.0

    def _settled(self, assignment: np.ndarray, n: int) -> np.ndarray:
        """(n_labels,) bool: of the labels the bar votes read, those ``assignment`` puts on points
        whose tracks have carried them for :data:`~.bar_order_votes.SETTLED_S`
        (:mod:`.label_tenure`), as published this frame."""
        read = self.bar_votes.labels
        on = read[assignment[read] < n]
        out = np.zeros(len(assignment), dtype=bool)
        if on.size and self._frame_tracks.size == n:
            held = self.tenure.held_for(self._frame_tracks[assignment[on]], on, self.last_stamp)
            out[on] = held >= SETTLED_S
        return out

    def reset(self) -> None:
        """Forget tracks, votes and fitness levels (the next frame is searched afresh)."""
        self.tracker.reset()
        self.votes.reset()
        self.tenure.reset()
        self.cluster_evidence.reset()
        self.bar_votes.reset()
        self.track_label: dict[int, int] = {}      # label each track carries (also while coasting)
        self._frame_tracks = np.zeros(0, dtype=np.int64)   # this frame's points' track ids
        self._frame_priors = {}            # id(problem) -> the fast path's move prior this frame (or None)
        self._track_began = None                   # ... and when each began (:meth:`_frame_track_began`)
        self._carried = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))  # last published, by track
        self._label_confidence = np.zeros(self.n_labels)     # last published confidence of each label
        self._release_evidence = np.zeros(self.n_labels)     # what leaving each label out gained (_weigh_releases)
        self.last_stamp = None
        self.heading = None
        self.centre = None
        self._since_search = 0                     # frames since the last GA search (or reset)
        self._frame_no = 0
        self._new_tracks = np.zeros(0, dtype=np.int64)   # tracks started last frame
        self._event_points = np.zeros(0, dtype=np.int64)
        self._coasting = np.zeros(self.n_labels, dtype=bool)  # labels whose tracks coast (not seen this frame)
        self._coast_track = np.full(self.n_labels, -1, dtype=np.int64)   # ... and those tracks
        self._region_cursor = -1
        self._young_cursor = -1
        self._stream_start = None                  # stamp of the first frame since the reset (its tracks are not young)
        self._provisional = False
        self._vouched = False                      # a frame published since the reset that a search vouched for
        self.clutter = ClutterShare()              # the share of points the searches leave unlabelled (confidence)
        self._epoch = getattr(self, "_epoch", 0) + 1   # results of searches asked before are dropped
        self._last_search_stamp = None
        self._last_recover_stamp = None            # background: the last warm GA a doubted frame asked for
        self._last_audit_stamp = None              # inline: the last misfit audit (its rate limit)
        self._audit_wait = None                    # inline: seconds before the next one may run
        self._lost_run = 0                         # inline: frames in a row fitting LOST_NATS below the reference
        self._audits = 0
        self._misfit_run = 0                       # frames in a row with a label below its floors
        self._fresh_search = False                 # new models under carried labels: search from scratch
        self._reset_levels()

    def _reset_levels(self) -> None:
        K = len(self.models)
        self.level = np.full(K, np.nan)            # running fitness per labelled point, per model
        self.spread = np.zeros(K)                  # running RMS of good frames' fitness about it
        self._level_on_positions = np.zeros(K, dtype=bool)   # a level set on a frame without velocities
        self._level_from_model = np.zeros(K, dtype=bool)     # set again from the model: a heavily hidden stream

    def set_engine(self, engine: Engine) -> None:
        """Swap the models (hot reload); the stream restarts. Fast when ``engine`` was
        prepared for the current ``noise_mm``."""
        self.engine = engine.with_noise(self.settings.noise_mm)
        self._build()
        self._configure_recovery()

    def update_settings(self, settings: LabelerSettings, engine: Engine | None = None) -> None:
        """Apply new settings between frames. Search budgets take effect at once; a new
        measurement noise swaps the widened models (``engine``, prepared for it elsewhere,
        makes that fast) and restarts the fitness levels but keeps the tracks; tracker,
        window, mode or method restart the stream; a new seed restarts the random stream."""
        old, self.settings = self.settings, settings
        if settings.noise_mm != self.engine.noise_mm or engine is not None:
            self.engine = (engine or self.engine).with_noise(settings.noise_mm)
            self._reset_levels()
            # the next search is a full one from scratch (an audit), joined when it fits
            # better: the tracks carry a labeling chosen under the old models, which new ones
            # (a person's calibrated body) may rank below another, and a warm search from it
            # stays in its basin (:attr:`_fresh_search`)
            self._fresh_search = True
            self.bar_votes = self._bar_votes()      # the new body's bar rows (a calibration's)
        if (settings.tracker, settings.window, settings.mode, settings.method) == \
                (old.tracker, old.window, old.mode, old.method):
            self.full_search.settings = full_settings(settings)
            self.warm_search.settings = settings.warm
            if settings.seed != old.seed:
                self.rng = np.random.default_rng(settings.seed)
            self.cluster_evidence.set_memory(settings.cluster_memory_s)
            self.bar_votes.min_gain = self._bar_gain()
        else:
            self._build()
        self._configure_recovery()

    def observe(self, xyz: np.ndarray, stamp: float, ids: np.ndarray | None = None) -> CarriedFrame:
        """A frame that will not be searched (the consumer was busy and takes a newer one): the
        tracks follow it, so that labels stay on their markers across the skip, and each point
        gets the label its track was last published with (:class:`CarriedFrame`). Costs the
        tracker update and a lookup (a fraction of a millisecond); the votes, levels and search
        state are not touched -- nothing searched vouches for this frame."""
        inp = self._begin(xyz, stamp, ids)
        lost = set(int(t) for t in inp.upd.lost)
        if lost:
            self.track_label = {t: lab for t, lab in self.track_label.items() if t not in lost}
        tracks = inp.upd.track_ids
        tids, labs, conf = self._carried
        pos, seen = _find(tids, tracks)
        lab = np.where(seen, labs[pos], -1) if tids.size else np.full(tracks.size, -1, dtype=np.int64)
        cf = np.where(seen, conf[pos], 0.0) if tids.size else np.zeros(tracks.size)
        # a track that coasted through the last searched frame (a marker hidden then) carries the
        # label the search left on it, at that label's last published confidence -- unless a
        # track published this frame already holds the label
        if self.track_label and not seen.all():
            keys, vals = self._track_labels()
            pos, hit = _find(keys, tracks)
            coast = np.where(hit & ~seen, vals[pos], -1)
            coast[tracker.member(coast, lab[lab >= 0])] = -1
            lab = np.where(coast >= 0, coast, lab)
            cf = np.where(coast >= 0, self._label_confidence[np.maximum(coast, 0)], cf)
        keep, n_in = inp.keep, inp.n_in
        lab = self.models[0].published(lab.astype(np.int64))
        return CarriedFrame(scatter(lab, keep, n_in, -1), scatter(cf, keep, n_in, 0.0),
                            scatter(inp.ids, keep, n_in, -1))

    def anonymous_presence(self) -> AnonymousPresence | None:
        """Whether the stream so far shows the first model's anonymous points
        (:mod:`.anonymous_presence`, over the frames searched since the labeler was built); None
        for a model without them."""
        return anonymous_presence(self.models[0], self.label_frames, self.frames_searched)

    def predicted_position(self, track_id: int, stamp: float) -> np.ndarray:
        """Where a (possibly coasting) track is predicted at ``stamp`` (NaN if unknown)."""
        return self.tracker.position_of(track_id, stamp)

    # -- hooks ---------------------------------------------------------------------------------
    def _searched(self) -> list[int]:
        """Indices of the models searched this frame."""
        return list(range(len(self.models)))

    def _island_sizes(self, ga_population: int, searched: list[int]) -> list[int]:
        """GA individuals per searched model."""
        return [ga_population] * len(searched)

    def _migration(self, problems: list[FrameProblem], searched: list[int]):
        """Per-generation hook of the multi-model GA (None: islands evolve alone)."""
        return None

    def _force_full(self) -> bool:
        """Skip the fast path and the warm GA this frame."""
        return False

    def _after_frame(self, problems: list[FrameProblem], found: FrameSearch, published: int,
                     inp: FrameInput) -> None:
        """After the search and the level update, before the votes."""

    def _result_fields(self, published: int) -> dict:
        """Extra fields of ``result_type``."""
        return {}

    # -- the frame -----------------------------------------------------------------------------
    def process(self, xyz: np.ndarray, stamp: float, ids: np.ndarray | None = None,
                truth: np.ndarray | None = None):
        """Label one frame. ``truth`` (M,) -- the true input index per label, -1 missing -- is
        only for evaluation: its fitness on the same problem is returned (search errors)."""
        t0 = time.perf_counter()
        s = self.settings
        inp = self._begin(xyz, stamp, ids)
        self._frame_priors = {}
        problems = [FrameProblem(m, inp.upd.states, s.background, self.heading, s.heading_snap_deg, inp.upd.rest_s)
                    for m in self.models]
        found = self._bar_orders_kept(problems, self._search_frame(problems, inp, self._join(inp)))
        self.last_frame = (problems, inp, found)             # for diagnostics: what this frame saw
        m_pub = found.best_model
        self._learn(problems, found)
        self._after_frame(problems, found, m_pub, inp)
        best = found.best
        e0 = time.perf_counter()
        truth_f, truth_prior = self._truth_fitness(problems[m_pub], truth, inp, best.assignment,
                                                   self._frame_priors.get(id(problems[m_pub])))
        truth_s = time.perf_counter() - e0 if truth is not None else 0.0
        assign, search_labels, pub, conf, confirmation, post, share = self._publish(problems[m_pub], best, inp,
                                                                                   found.doubtful)
        keep, n_in, model = inp.keep, inp.n_in, problems[m_pub].model
        held = pub[pub >= 0]
        self.label_frames[held[held < self.label_frames.size]] += 1
        self.frames_searched += 1
        return self.result_type(
            labels=scatter(model.published(pub), keep, n_in, -1), confidence=scatter(conf, keep, n_in, 0.0),
            track_ids=scatter(inp.ids, keep, n_in, -1),
            search_labels=scatter(model.published(search_labels), keep, n_in, -1),
            assignment=_input_index(assign, keep),
            log_likelihood=float(best.fitness), latency_ms=(time.perf_counter() - t0 - truth_s) * 1e3,
            truth_ms=truth_s * 1e3,
            full_search=found.full, generations=found.generations, evaluations=found.evaluations,
            n_dropped=int((~inp.finite).sum()), n_ignored=inp.n_ignored, reset=inp.reason,
            heading=self.heading if self.heading is not None else float("nan"), truth_fitness=truth_f,
            truth_prior=truth_prior, doubtful=found.doubtful, recovered=found.recovered, recovering=self.recovery.busy,
            posterior=scatter(post, keep, n_in, np.nan), vote_share=scatter(share, keep, n_in, 0.0),
            confirmation=scatter(confirmation, keep, n_in, 0.0),
            **self._result_fields(m_pub))

    def _bar_orders_kept(self, problems: list[FrameProblem], found: FrameSearch) -> FrameSearch:
        """``found`` with each candidate that gives a bar's ends the other way round from what
        their tracks' order votes decided exchanged back (:meth:`.bar_order_votes.BarOrderVotes.kept`):
        a search's result, which no move prior judged, or a chain shift's."""
        if not self.bar_votes.active:
            return found
        for m, c in found.candidates.items():
            kept = self.bar_votes.kept(c.assignment, self._frame_tracks)
            if kept is not c.assignment:
                found.candidates[m] = Candidate(kept, float(problems[m].fitness(kept[None])[0]))
        return found

    def _search_frame(self, problems: list[FrameProblem], inp: FrameInput,
                      joined: tuple[np.ndarray, bool] | None) -> FrameSearch:
        """Fast path; when it cannot vouch for the frame, a recovery search (warm GA, full GA
        with restarts) -- at once (inline) or in the background while the best labeling known
        is published as doubtful. ``joined``: a finished background search's labelings mapped
        onto this frame and whether it was a full search (:meth:`_join`), preferred to the
        carried one when it fits better; a full search's labeling taken in place of the carried
        one restarts the region pass."""
        s = self.settings
        n = problems[0].n
        searched = self._searched()
        velocity_known = bool((problems[0].codes[:-1] == FULL).any())
        if velocity_known and self._level_on_positions.any() and self.recovery.inline:
            self._level_with_velocities(problems[0])
        seeds = self._seeds(inp.upd.track_ids, n) if s.mode == "stream" and not self._provisional else None
        start = self._start_labeling(inp.upd.track_ids, n)
        if joined is not None:
            labeling, full = joined
            labeling = self._readings_released(problems, searched, labeling)
            carried, seeds = seeds, self._prefer(problems, searched, seeds, labeling)
            if full and (carried is None or not np.array_equal(seeds[0], carried[0])):
                self._since_search = 0          # a full search changed the labeling: check it region by region
        if seeds is not None:
            for p in problems:
                p.anchor_heading(seeds[0])
        self._provisional = not velocity_known     # a labeling without velocities is re-searched next frame
        fast = None
        if seeds is not None and not self._force_full():
            if s.method == "tracker":
                self._init_levels(problems, searched)
                return FrameSearch({m: Candidate(seeds[0], float(problems[m].fitness(seeds)[0])) for m in searched},
                                   full=False, evaluations=len(searched))
            fast = self._fast_path(problems, searched, seeds[0])
            if fast is not None and not fast.doubtful:
                fast.recovered = joined is not None
                return self._maybe_audit(problems, inp, searched, fast)
        if self.recovery.inline:
            res = self.recover(self._request(problems, inp, searched, seeds, "recover"), problems=problems)
            found = FrameSearch({m: Candidate(*self._settled_clutter_released(problems[m], a, f))
                                 for m, (a, f) in res.candidates.items()}, res.full,
                                res.generations, res.evaluations)
            if found.full or found.generations > 0:
                self._since_search = 0
            if start is not None:
                self._keep_start(problems, searched, found, start)
            return found
        return self._while_recovering(problems, inp, searched, seeds, fast)

    def _search_kind(self, seeds: np.ndarray | None) -> str:
        """What a doubted frame asks the worker for (background): a full search when nothing is
        carried (``full``); new models under a carried labeling, a search from scratch
        (``audit``); else a warm GA from the carried labeling, going on to a full search when it
        falls short (``recover``) -- at most once per ``audit_period_s`` of stream time -- and
        between those the exact region sweep from it (``sweep``: every label's region relabelled
        given the rest, the full search's final sweep, :meth:`_sweep`).

        Why: a warm GA holds the worker for 0.3-0.9 s at 41 markers (longer when it goes on to a
        full search), and while it runs the frames go on with the fast path alone. Where many
        markers are hidden at once nearly every frame is doubted (a frame showing half of the
        markers fits below the level), so what the worker returns, and how often, is the
        labeling. A sweep takes 10-20 ms there: results join every few frames, each a local
        repair of the carried labeling, and a lost labeling still gets the GA and the full search
        once per period. Measured, ``bench_stream_latency``'s 41 markers with half of the samples
        hidden (HDM05, gaps of 0.25 s), the worker on a real-time feed, seeds 1-3, 10 runs each
        way: 57.0 % (every doubted frame a warm GA) -> 70.5 % (this); sweeps only, no GA: 67.4 %;
        the gapped second half under the gapped first half's model 73.2 -> 80.5 %
        (``results/stream_latency.md``, 2026-12-05 later). ``audit_period_s`` 0 (audits off)
        asks for the warm GA every time, as before."""
        if seeds is None:
            return "full"
        if self._fresh_search:
            return "audit"
        period, last = self.settings.audit_period_s, self._last_recover_stamp
        if period > 0 and last is not None and self.last_stamp - last < period:
            return "sweep"
        self._last_recover_stamp = self.last_stamp
        return "recover"

    def _while_recovering(self, problems, inp, searched, seeds, fast) -> FrameSearch:
        """Background mode, the frame needs a search: ask for one (unless one runs) and publish
        the best labeling known meanwhile -- the hill-climbed carried one, else the carried one,
        else none -- flagged doubtful (confidence 0, not learnt from).

        A frame without velocities (the stream's first, or the first after a reset) asks for
        nothing: the next frame, a frame period later, asks for the full search with them.
        Searching the first frame on positions alone (one short GA) held the worker for 25 ms
        at 14 points and its labeling was wrong (1 of 12 labels right on the demo walker, a
        limb chain shifted by one); the warm GA that followed from it stayed wrong too, so
        the full search began 70 ms into the stream. Measured side by side, background
        recovery on a real-time feed (first frame fully right; 8 runs):
        demo walker, 2 flickering + 2 ghosts: frames 6-17 (median 10) -> 3-4;
        41 HDM05 markers, flicker + 2 ghosts, 12 seeds, 200 frames: median first right
        0.54 -> 0.34 s, accuracy after it 80.6 -> 89.2 % (a short first search, then a
        full one: 0.70 s, 78.9 %). In the node, ``dtm-demo --occlude 2 --gap-frames 1 --clutter 2
        --duration 8`` (``frames_with_errors``): 7-24 frames wrong at the start -> 3-4,
        accuracy 98.7-99.3 -> 99.5-99.6 %."""
        if not self.recovery.busy and not self._provisional:
            self.recovery.submit(self._request(problems, inp, searched, seeds, self._search_kind(seeds)))
        self._init_levels(problems, searched)
        if fast is None:
            ind = seeds[0] if seeds is not None else problems[0].empty_assignment()
            fast = FrameSearch({m: Candidate(ind, float(problems[m].fitness(ind[None])[0])) for m in searched},
                               full=False, evaluations=len(searched))
        fast.doubtful = True
        return fast

    def _maybe_audit(self, problems, inp, searched, fast: FrameSearch) -> FrameSearch:
        """Background recovery: audits of a labeling the fast path accepted, every
        ``audit_period_s`` / 4 of stream time while the worker is idle -- an exact region sweep
        from it (every label's region relabelled given the rest), and every fourth time a full
        search from scratch; the result joins a later frame when it fits better (:meth:`_join`).
        The running level adapts to a wrong labeling that tracking carries on -- a limb's labels
        shifted one marker, a ghost holding a hidden marker's label; an independent search does
        not. The worker's core would be idle otherwise. Inline (offline) there are none: every
        frame's labeling is already the search's."""
        period = self.settings.audit_period_s / AUDITS_PER_PERIOD
        if self.recovery.inline:
            return self._inline_audit(problems, inp, searched, fast)
        if period <= 0 or self.recovery.busy or self._provisional or \
                self.settings.method != "cbga" or not self.recovery.background_ready:
            return fast
        now = self.last_stamp
        due = self._last_search_stamp is None or now - self._last_search_stamp >= period or self._fresh_search
        if not due and self._misfit_run < MISFIT_FRAMES:
            return fast
        self._audits += 1
        kind = "audit" if self._audits % AUDITS_PER_PERIOD == 0 or self._fresh_search else "sweep"
        best = fast.best.assignment
        self.recovery.submit(self._request(problems, inp, searched, best[None], kind))
        return fast

    def _inline_audit(self, problems, inp, searched, fast: FrameSearch) -> FrameSearch:
        """Inline (offline): no periodic audits -- but a labeling that stays lost for
        ``MISFIT_FRAMES`` frames gets the audit now, a full search from scratch in this frame,
        kept when it fits better. Lost: a label far below its floors (:meth:`_misfit_centres`),
        or (``audit_when_lost``: a bank) the whole frame ``LOST_NATS`` per labelled point below
        what the model expects of a right labeling (its fit reference, not the running level, which adapts to a wrong
        labeling within frames). Without it a wrong labeling was carried for the rest of a take
        (HDM05, 41 markers, clean, 1000 frames: from frame ~600 on, 343 search errors) or for a
        second (``dtm-eval --bank``, run -> walk -> dance, seed 2: at the walk -> dance join the
        recovery search itself found a wrong labeling; 0-5 of 12 labels right for 122 frames,
        15 nats per label below the reference, the truth 60-120 nats above them, while the
        running level fell from 13 to 2 nats per label). At most one per ``audit_period_s`` of
        stream time after an audit that helped, up to ``AUDIT_BACKOFF_MAX`` periods after ones
        that did not (a motion the model never saw fits below its reference throughout); an
        audit's labeling replaces the carried one only when it gains ``AUDIT_GAIN_PER_LABEL``
        nats per label it changes."""
        best = fast.best
        p = problems[fast.best_model]
        lost = self.audit_when_lost and self._fit_deficit(p, best) > LOST_NATS
        self._lost_run = self._lost_run + 1 if lost else 0
        period = self.settings.audit_period_s
        wait = self._audit_wait if self._audit_wait is not None else period
        last = self._last_audit_stamp
        if max(self._misfit_run, self._lost_run) < MISFIT_FRAMES or self._provisional or period <= 0 or \
                self.settings.method != "cbga" or (last is not None and self.last_stamp - last < wait):
            return fast
        self._misfit_run = self._lost_run = 0
        self._last_audit_stamp = self.last_stamp
        res = self.recover(self._request(problems, inp, searched, best.assignment[None], "audit"),
                           problems=problems)
        audit = FrameSearch({m: Candidate(a, f) for m, (a, f) in res.candidates.items()}, res.full,
                            res.generations, res.evaluations)
        changed = int((audit.best.assignment != best.assignment).sum())
        if changed and audit.best.fitness > best.fitness + AUDIT_GAIN_PER_LABEL * changed:
            self._since_search = 0
            self._audit_wait = period
            return audit
        self._audit_wait = min(2.0 * wait, AUDIT_BACKOFF_MAX * period)
        return fast

    def _request(self, problems, inp, searched, seeds, kind: str) -> RecoveryRequest:
        if kind == "audit":
            self._fresh_search = False
        self._last_search_stamp = self.last_stamp
        seed = 0 if self.recovery.inline else int(self.rng.integers(2 ** 31))   # inline: this labeler's stream
        return RecoveryRequest(self._epoch, self._frame_no, inp.upd.states, inp.upd.track_ids, self.heading,
                               seeds, searched, self._search_state(), seed, kind, inp.upd.rest_s)

    def recover(self, request: RecoveryRequest, rng: np.random.Generator | None = None,
                problems: list[FrameProblem] | None = None, interim=None) -> RecoveryResult:
        """Run a recovery search (what :class:`~.recovery.Recovery` executors call): a warm GA
        from the request's seeds; a full GA with restarts when there are none or the warm
        result falls short of the level. Inline it runs on this labeler's own state and random
        stream; in a worker, on the request's. ``interim`` (a worker's
        :class:`~.recovery.InterimReporter`) sends the GA's best so far while it runs."""
        self._interim = interim
        try:
            return self._recover(request, rng, problems)
        finally:
            self._interim = None

    def _recover(self, request: RecoveryRequest, rng, problems) -> RecoveryResult:
        s = self.settings
        if rng is not None:                       # a worker: the asking labeler's state
            self.rng = rng
            self._set_search_state(request.state)
        seeds, searched = request.seeds, request.searched
        if problems is None:
            problems = [FrameProblem(m, request.states, s.background, request.heading, s.heading_snap_deg,
                                     request.rest_s) for m in self.models]
            if seeds is not None:
                for p in problems:
                    p.anchor_heading(seeds[0])
        if request.kind == "sweep":
            return self._sweep(problems, searched, seeds[0], request)
        found = None
        if seeds is not None and request.kind == "recover":
            found = self._ga(self.warm_search, problems, searched, seeds)
            found.full = False
            m = found.best_model
            found.full = not np.isnan(self.level[m]) and self._falls_short(found.best, problems[m], m)
        self._init_levels(problems, searched)
        if found is None or found.full:
            audit = request.kind == "audit"
            full = self._full_search(problems, searched, seeds if not audit else None, turn=not audit)
            if found is None:
                found = full
            else:
                found.merge(full)
        return RecoveryResult(request, found.bests(), found.full, found.generations, found.evaluations,
                              self._search_state())

    def _sweep(self, problems, searched, ind, request) -> RecoveryResult:
        """The sweep audit: exact region relabelling of every label's region from ``ind``
        (the full search's final sweep, :meth:`GASearch._sweep_regions`), under each model."""
        cands, evals = {}, 0
        for m in searched:
            f = float(problems[m].fitness(ind[None])[0])
            if isinstance(self.full_search, GASearch):
                a, f, e = self.full_search._sweep_regions(problems[m], ind, f, None)
            else:
                a, e = ind, 0
            cands[m], evals = (a, f), evals + e + 1
        return RecoveryResult(request, cands, False, 0, evals, self._search_state())

    def _init_levels(self, problems: list[FrameProblem], searched: list[int]) -> None:
        for m in searched:
            if np.isnan(self.level[m]):
                self.level[m] = self._initial_level(problems[m])
                self._level_on_positions[m] = not (problems[m].codes[:-1] == FULL).any()

    def _level_with_velocities(self, problem: FrameProblem) -> None:
        """The first frame with velocities after a level was set on one without: set the level
        again from the model where this frame would teach it little (``UNTAUGHT_WEIGHT``), and
        judge full searches' restarts on what a right labeling with each frame's observation
        pattern fits from then on (:meth:`_restart_target`). Inline recovery only.

        Why: the level is set on the stream's first frame, which has no velocities, and per
        labelled point a position-only frame fits several nats below one with velocities (the
        background's gain on 3 dimensions instead of 6: 12.05 against 18.29 nats on HDM05 with
        half of the samples hidden). A fully seen stream teaches that low start up within
        frames; a heavily hidden one teaches it ``(seen share) ** SEEN_POWER`` of a fully seen
        frame, kept it for the whole take (13.01 after 1200 frames), and labelings fitting far
        below a right one were accepted without a search. ``bench_captures``' gapped halves
        (HDM05, 41 markers, half of the samples hidden in gaps of 0.25 s, gap draws 1-6, 600
        frames), the plain stream labeler: 81.6 -> 87.2 % mean (78.3 -> 82.2 % the least gain),
        5-38 -> 45-56 ms a frame; through ``dtm-label``'s default (take votes, fresh starts) its
        causal labels 83.3 -> 86.6 %, search errors 255-366 -> 22-111 of 590 frames, the final
        labels 98.58 -> 98.60 % (``results/captures.md``, 2026-12-05 night). Without the quarter
        condition subject 55's whirl under a model of her lambada (``test_calibrate_cli``) fell
        from over 95 to 71 %: a motion the model never saw fell short of the model's level in
        every frame and the searches relabelled it; such a stream, fully seen, teaches the level
        its own fit. Not in background recovery (the node): there every frame of such a stream
        is doubted, no frame is ever vouched for, and the published confidence of the half-hidden
        test stream fell to 0.42 for labels 78 % right (``test_published_confidence``); live
        accuracy, 3 runs each way of two whole gapped halves, moved 65.96 -> 73.88 % and 67.58 ->
        66.34 %."""
        flagged = self._level_on_positions
        if (frame_weight(problem) / problem.M) ** SEEN_POWER < UNTAUGHT_WEIGHT:
            self.level[flagged] = np.nan
            self.spread[flagged] = 0.0
            self._level_from_model |= flagged
        flagged[:] = False

    def _restart_target(self, c: Candidate, problem: FrameProblem, m: int) -> float:
        """What a full search's best must fit before its restarts stop: the level over the
        frame's points (:func:`frame_weight`); on a stream whose level came from the model
        (:meth:`_level_with_velocities`), what a right labeling with ``c``'s observation pattern
        fits (:meth:`_pattern_expected`) -- a frame showing half of the markers never reaches a
        fully seen frame's level per point, and every restart ran on every frame searched (0.24 s
        a frame at 41 markers, half hidden, against 0.06 s, for about the same labels)."""
        if self._level_from_model[m]:
            return self._pattern_expected(c, problem, m) - self._refit_margin(m)
        return self.level[m] * frame_weight(problem) - self._refit_margin(m)

    def _search_state(self) -> dict:
        """What a search reads of the labeler (the worker gets it with each request)."""
        return {"level": self.level.copy(), "spread": self.spread.copy()}

    def _set_search_state(self, state: dict) -> None:
        self.level, self.spread = state["level"].copy(), state["spread"].copy()

    def _join(self, inp: FrameInput) -> tuple[np.ndarray, bool] | None:
        """A finished background search, mapped onto this frame: label -> the point of the
        track it labelled in the frame it was asked for (missing where that track is gone);
        labels it left out keep the carried labeling's points where those are free; with it,
        whether it came from a full search. None when nothing finished, or it belongs to an
        earlier stream (reset since).

        Rows of the returned (k, M) array: the search's labels with the carried labeling's
        filling the labels whose tracks are gone, and -- when any are, and no search has vouched
        for a frame of the stream yet -- the search's labels alone, those labels left for the
        fast path to place (:meth:`_prefer` takes the one that fits). Where markers keep
        disappearing, few of a search's tracks outlive it, and before any frame was vouched for
        the carried labeling beside them is only what the fast path made of the stream's first
        guesses: on HDM05's second half with half of the samples hidden (gaps of 0.25 s), the
        worker's cold search's first good interim result (16 frames after it was asked) still
        held 9 of the frame's 21 points right, the carried labeling 3; filled with the carried
        labels it fitted -624 nats against the carried 70 (a right wrist beside a knee carried
        onto the head), so the search never joined; alone, 9 right labels and nothing to
        contradict them. Measured (41 markers, half hidden): background recovery made
        deterministic (``DeferredRecovery``, 12 streams of 240 frames) 47.0 -> 54.9 %; the
        worker on the gapped half's model 46 -> 62 % (4-5 runs, its first second 13 -> 45 %);
        ``bench_stream_latency``'s half-hidden stream within its spread (runs vary 20 points).
        Offered after a vouched frame as well, that stream's seed 1 fell 66.9 -> 54.5 % and its
        seed 3 rose 50.6 -> 61.5 % (8 runs each); before a vouched frame only, 62.3 / 61.1 %
        (5 runs): the start-up gains without displacing a carried labeling a search vouched for."""
        res = self.recovery.poll()
        if res is None or res.request.epoch != self._epoch or self.recovery.inline:
            return None
        req = res.request
        m = max(res.candidates, key=lambda q: res.candidates[q][1])
        assign = np.asarray(res.candidates[m][0])
        n_req = req.track_ids.size
        tid = np.where(assign < n_req, req.track_ids[np.minimum(assign, max(n_req - 1, 0))], -1)
        now = inp.upd.track_ids
        order = np.argsort(now)
        pos = np.minimum(np.searchsorted(now[order], tid), max(now.size - 1, 0))
        hit = (tid >= 0) & (now.size > 0) & (now[order][pos] == tid) if now.size else np.zeros_like(tid, bool)
        n = now.size
        out = np.full(self.n_labels, n, dtype=np.int64)
        out[hit] = order[pos[hit]]
        carried = self._seeds(now, n)
        if carried is None:
            return out[None], res.full
        filled = out.copy()
        free = ~tracker.member(carried[0], out) & (out == n)
        filled[free] = carried[0][free]
        return (np.stack([filled, out]) if free.any() and not self._vouched else filled[None]), res.full

    def _readings_released(self, problems, searched, readings: np.ndarray) -> np.ndarray:
        """A joined search's readings (:meth:`_join`), each with the labels it puts on tracks in
        the clutter state released as an inline search's result is
        (:meth:`~.fast_path.FastPath._settled_clutter_released`, under the model it fits best)."""
        if self.tenure.longest_clutter(self.last_stamp) < self.settings.hold_s:
            return readings
        out = readings.copy()
        for i, a in enumerate(readings):
            f = [float(problems[m].fitness(a[None])[0]) for m in searched]
            k = int(np.argmax(f))
            out[i] = self._settled_clutter_released(problems[searched[k]], a, f[k])[0]
        return out

    def _prefer(self, problems, searched, seeds, joined) -> np.ndarray:
        """Seeds with the best of the carried labeling and a joined search's readings
        (:meth:`_join`; a joined one first on ties), judged on this frame under each searched
        model."""
        cand = joined if seeds is None else np.concatenate([joined, seeds[:1]])
        f = np.max([problems[m].fitness(cand) for m in searched], axis=0)
        return cand[np.argsort(-f, kind="stable")]

    def _ga(self, search: LabelSearch, problems: list[FrameProblem], searched: list[int],
            seeds: np.ndarray | None) -> FrameSearch:
        """One search over the searched models: a GA with one island per model (migration
        between them, :meth:`_migration`), or a deterministic search per model."""
        if isinstance(search, GASearch):
            hook = self._migration(problems, searched)
            if self._interim is not None:
                refine = (lambda m, a, f: self._interim_refine(search, problems[m], a, f)) \
                    if search.finish and search.settings.polish else None
                hook = self._interim.hook(searched, hook, refine)
            out = search.search_models([problems[m] for m in searched],
                                       self._island_sizes(search.settings.population, searched),
                                       self.rng, seeds, hook)
            self._after_ga(searched, out)
            return FrameSearch({searched[i]: Candidate(a, f) for i, (a, f) in out.per_model.items()},
                               full=True, generations=out.generations, evaluations=out.evaluations)
        found = FrameSearch({}, full=True)
        for m in searched:
            out: SearchOutcome = search.search(problems[m], self.rng, seeds)
            found.merge(FrameSearch({m: Candidate(out.assignment, out.fitness)}, True, out.generations,
                                    out.evaluations))
        return found

    def _interim_refine(self, search: GASearch, problem: FrameProblem, ind: np.ndarray, f: float):
        """An interim labeling refined, one step after another (each yielded as
        ``(assignment, fitness, evaluations)``, sent as it comes): finished (polish, mirror,
        region sweeps); then, with the turned-round check on, read through the turned-round
        body and swept (:func:`turned_labels`). Then the search's ``fresh_starts`` more starts, each
        the best of a fresh model-guided population, refined the same way (:meth:`_fresh_starts`).

        The first generation's best, refined, is right in most cold starts at 41 markers, and
        its failures are the start's, not the frame's: another population's best refined is
        right again with the same odds, while the GA from a bad start took 1.5-5 s and could
        end wrong (HDM05, 41 markers, 3 gaps + 2 ghosts, corruption seed 3, frame 1: the
        stream labeler's first worker seed ended at 569 nats, 11 labels wrong, after 5 s; the
        truth 638). Drawn from their own random stream (the request's seed), so the GA's is
        untouched."""
        yield from self._refined(search, problem, ind, f)
        if self._interim is not None:
            yield from self._fresh_starts(search, problem, np.random.default_rng([self._interim.request.seed, 1]))

    def _refined(self, search: GASearch, problem: FrameProblem, ind: np.ndarray, f: float):
        """``ind`` finished (polish, mirror, region sweeps; a marker set's mirrored sweeps too
        unless in a worker's interim steps), then read through the turned-round body and swept
        (:func:`turned_labels`) when the turned-round check is on; each step yielded as
        ``(assignment, fitness, evaluations)``. A worker's stream waits for these steps (the
        first finished labeling joins it), and at 41 markers the mirrored sweeps are up to a
        second more (measured while streams had them too: the demo's 41-marker flicker stream was
        first right at frame 66-102 instead of 38-41); the worker's GA still ends with them
        (:meth:`~dtm_labeler.search.label_search.GASearch._finish`). Streams have none at all
        (:func:`full_settings`): this matters for a worker of a single-frame labeler."""
        yield search._finish(problem, ind, f, None, mirrored=self._interim is None)
        if self.settings.turn_check and self.settings.method == "cbga" and problem.M > 3:
            yield turned_labels(problem, ind, f, lambda y, fy: search._sweep_regions(problem, y, fy, None))

    def _fresh_starts(self, search: GASearch, problem: FrameProblem, rng: np.random.Generator):
        """``fresh_starts`` starts (the search's settings), each the best of a fresh model-guided
        population drawn from ``rng``, :meth:`_refined` (CBGA only)."""
        if not isinstance(search, CBGASearch):
            return
        for _ in range(search.settings.fresh_starts):
            pop = search._sample(problem, search.settings.population, rng)
            fit = problem.fitness(pop)
            i = int(np.argmax(fit))
            a, fa, e = next(steps := self._refined(search, problem, pop[i], float(fit[i])))
            yield a, fa, e + len(pop)
            yield from steps

    def _after_ga(self, searched: list[int], out: SearchOutcome) -> None:
        """The islands' final sizes (the bank carries its models' shares to the next frame)."""

    def _full_search(self, problems: list[FrameProblem], searched: list[int],
                     seeds: np.ndarray | None, turn: bool = True) -> FrameSearch:
        """The full GA, repeated from fresh populations (up to ``restarts`` times) while its
        best falls ``refit_drop`` short of the level times the frame's labellable points
        (:func:`frame_weight`): on 28-41 markers one run can stall in a deep local optimum --
        limbs' labels exchanged -- that its mutations do not leave, while independent runs
        rarely share it. A frame that fits well costs one run. Judged against every point the
        frame could label, not only those labelled: a stalled run often leaves several points
        unlabelled, which a per-labelled-point level forgives. A search without seeds (a cold
        start; ``turn``: not the background's periodic audits, ~1 s more each at 41 markers)
        also checks the body turned round (:meth:`_turn_round`). In a worker the finished
        result is sent as an interim one before that check, so the stream does not wait for
        it: at 41 markers the check is 1.2-1.5 s of a 1.6-2.3 s cold search, and the
        finished labeling, often better than the GA's last interim one by its region sweeps
        (662 -> 764 nats on an HDM05 start), joined at 0.42 s instead of 1.26 s. 12 starts
        with flicker + 2 ghosts, first 200 frames: 84.8 -> 87.7 % right.

        In a worker, where the stream does not wait for the search, a cold search does more
        and sends each step as it comes. The check's quick half (the GA's labels read through
        the turned-round body) runs on the first GA's result at once: a GA that settled on the
        body seen from behind restarts into the same basin (the demo's 41-marker stream,
        corruption seed 9: the GA and both restarts 0 % right at 250-258 nats, the truth 608;
        the quick half from the first GA's result gives the truth, at 0.45 s of the search
        instead of 0.94 s). And every restart runs, whatever the level says: at 41 markers the
        level's margin (``refit_drop``, 60 nats) passes a GA result 138 nats below the truth
        (seed 2: 505 nats, 61 % right; the first restart finds the truth, 643). Inline the
        restarts stay judged on the GA's own result and the quick half follows them (judging
        them on the quick half's result moved 16 cells of ``dtm-eval``'s single-frame and
        generalisation sections both ways, 78.6 -> 27.4 % and 93.6 -> 100 %).
        (Library, the demo's 41-marker stream paced at 120 Hz, 12 corruption seeds, first 240
        frames, with :meth:`_interim_refine`: share right 90.9 -> 91.9 %, seed 9 82.5 ->
        88.1 %, seed 6 86.6 -> 92.8 %, seed 1 91.8 -> 89.7 %.)"""
        check = turn and self.settings.turn_check and seeds is None and self.settings.method == "cbga"
        found = self._ga(self.full_search, problems, searched, seeds)
        # single frames (no worker): the fresh starts now, from their own stream; not in an inline
        # stream, where they moved its few cold starts (12 half-hidden markers: 78 -> 61 % live)
        if self._interim is None and seeds is None and self.settings.mode == "single":
            rng = np.random.default_rng([self.settings.seed, self._frame_no, 1])
            for m in searched:
                for a, fa, e in self._fresh_starts(self.full_search, problems[m], rng):
                    found.merge(FrameSearch({m: Candidate(a, fa)}, False, 0, e))
        quick = None
        if check and self._interim is not None:     # a worker: the quick half joins before any restart
            quick = FrameSearch(dict(found.candidates), found.full)
            self._turn_round(problems, quick, dict(found.candidates), turned_labels)
            self._interim.report(quick.bests(), found.generations)
        restarts = self.settings.restarts if self.settings.method in ("cbga", "sga") else 0   # others: deterministic
        for _ in range(restarts):
            m = found.best_model
            if quick is None and found.best.fitness >= self._restart_target(found.best, problems[m], m):
                break
            found.merge(self._ga(self.full_search, problems, searched, None))
            if quick is not None:
                self._interim.report(found.bests(), found.generations)
        if check:
            ga = dict(found.candidates)
            self._turn_round(problems, found, ga, turned_labels)
            if quick is not None:
                found.merge(quick)
            if self._interim is not None:       # joins before the check's second, slow half
                self._interim.report(found.bests(), found.generations)
            self._turn_round(problems, found, ga, turned_round)
        if seeds is None and self.settings.upright_deg > 0 and self.settings.method == "cbga":
            self._upright_check(problems, searched, found)
        if seeds is None and self.settings.bend_starts > 0 and self.settings.method == "cbga":
            self._bend_check(problems, searched, found)
        if self._interim is not None:         # never less than a labeling already sent (its refinements)
            found.merge(FrameSearch({m: Candidate(a, f) for m, (a, f) in self._interim.best.items()
                                     if m in found.candidates and f > found.candidates[m].fitness}, False))
        return found

    def _upright_check(self, problems: list[FrameProblem], searched: list[int], found: FrameSearch) -> None:
        """A search from scratch of a leaning body runs again on its points turned upright
        (:mod:`~dtm_labeler.search.upright`, ``upright_deg``: the long axis of the points the
        search labelled under the model, and of all the points where that differs); under each
        model whose points lean, each result, scored and swept on the frame as it is, replaces
        the labeling found when it fits better (:meth:`_turned_starts`).

        A cold start that misreads a leaning body is carried by the tracks: ``dtm-eval``'s
        floor-moves cell (CMU 85's breakdance on the floor, model of CMU 85's jump + twist and
        HDM05's standing take, 41 markers, 360 frames), stream / single frames, before -> with
        the check: the generic body 27.34 / 58.23 -> 97.26 / 82.32 % (search errors 355 -> 19 of
        360 frames), calibrated 91.61 / 49.39 -> 96.48 / 87.50 %, ``dtm-label``'s default 27.34 /
        58.23 -> 96.48 / 87.50 %, the motion mixtures alone 78.62 / 54.57 -> 78.62 / 73.17 %. Of
        the report's other cells: CMU 85's breakdance stream with gaps 95.97 -> 98.96 %, clean
        99.14 -> 100 %; breakdance -> jump + twist single frames, calibrated 86.28 -> 92.99 %;
        the MoCap Toolbox walk clean 99.28 -> 100 %; the lowest: subject 9's run left out, single
        frames without body augmentation 15.48 -> 11.31 % (7 labels), the breakdance -> jump +
        twist generic body's single frames 82.32 -> 82.01 %. With the axis of all the points
        only (no ``body``), the generic body's floor stream was 96.15 % and a ghost beside an
        upright body asked for the check."""
        starts = {}
        for m in searched:
            a = found.candidates[m].assignment
            starts[m] = upright_problems(problems[m], self.settings.upright_deg, a[a < problems[m].n])
        self._turned_starts(problems, searched, found, starts)

    def _bend_check(self, problems: list[FrameProblem], searched: list[int], found: FrameSearch) -> None:
        """A search from scratch under a marker set's model that, after all its other starts,
        still fits below ``BEND_SHARE`` of the level (per labellable point, as the restarts
        judge it) runs again on the frame pitched back about ``bend_starts`` horizontal axes
        (:func:`~dtm_labeler.search.upright.bent_problems`: a body bent at the hips), each result
        scored and swept on the frame as it is and kept when it fits better.

        Measured (``dtm-eval``'s generalisation section, before -> with the check): CMU 85 jump +
        twist -> breakdance, 41 markers, calibrated, single frames 94.51 -> 97.56 % (the
        stand-up, the trunk bent 57-101 deg forward: cold searches 39-71 % right, the truth
        46-125 nats better than what they found); HDM05 -> CMU 85 jump + twist, generic body,
        stream / single 4.36 / 11.28 -> 15.16 / 12.80 %, calibrated 99.09 / 56.71 -> 99.13 /
        59.15 %; the floor moves' generic body single frames 82.32 -> 82.93 %. The markers
        section: the MoCap Toolbox walk with gaps 71.76 -> 97.93 % (search errors 34 -> 1 of 35
        frames), with clutter 100 -> 98.77 % (one search error in 35 frames, where there was
        none); no other cell moved. Why marker sets only: a marker set's small rigid clusters (a
        head's four markers, the pelvis's) each show which way is up, the 14 body points' bones
        do not, and a pitched reading of a runner leaning forward fitted better than the upright
        truth (subject 9's run left out, calibrated stream 100 -> 71.43 %, ``dtm-label``'s
        default 100 -> 20.06 %). Why below a share of the level: a frame of another motion fits at 65-80 % of
        the level of the model's own take, a misread bent trunk at 49-57 %; checking every frame
        below the level doubled the cold searches' time on such a take. Why with at least half
        the labels' points in the frame: 4 points of 12 upper-body markers do not show a pose, and
        the best of four more searches fits some pitched reading better by chance (HDM05's upper
        body, half the markers hidden, under a model of 12 markers: a first frame of 4 points, a
        pitched reading 6 nats better; the stream 78.04 -> 48.98 % right, voted 86.73 -> 63.60 %).

        A frame still poor after those starts runs them again pitched back twice as far
        (``BEND_PITCHES_DEG``: 60, then 120 deg), for a body upside down -- the head below the
        pelvis in a flip or a roll, which 60 deg leaves past horizontal. CMU 85 breakdance ->
        jump + twist, calibrated, 24 single frames: 92.58 -> 96.65 % (the flip's frames 13-31
        labels wrong -> 3-5); HDM05 -> CMU 85 jump + twist, calibrated: 63.82 -> 66.06 %.
        ``dtm-eval`` (markers and generalisation sections, 8 single frames a cell): the first
        91.16 -> 96.04 %, the HDM05 model's generic body on CMU 85 stream 3.63 -> 20.70 %; no cell
        lower."""
        for pitch in BEND_PITCHES_DEG:          # deeper only while still poor (a flip's head-down frames)
            starts = {}
            for m in searched:
                p = problems[m]
                poor = found.candidates[m].fitness < BEND_SHARE * self.level[m] * frame_weight(p)
                if poor and p.model.marker_set and 2 * p.n >= p.M:
                    starts[m] = bent_problems(p, self.settings.bend_starts, pitch)
            if not starts:
                return
            self._turned_starts(problems, [m for m in searched if m in starts], found, starts)

    def _turned_starts(self, problems: list[FrameProblem], searched: list[int], found: FrameSearch,
                       starts: dict[int, list[FrameProblem]]) -> None:
        """GA searches on turned copies of the frame (``starts``: model -> its turned problems,
        the k-th of every model searched together), each result scored and swept on the frame
        as it is and kept in ``found`` when it fits better there. Their interim results are not
        reported (they are the turned frame's)."""
        sweep = self.full_search._sweep_regions
        for k in range(max((len(v) for v in starts.values()), default=0)):
            turned = [m for m in searched if len(starts[m]) > k]
            upright = list(problems)
            for m in turned:
                upright[m] = starts[m][k]
            interim, self._interim = self._interim, None      # its interim results are the turned frame's
            try:
                res = self._ga(self.full_search, upright, turned, None)
            finally:
                self._interim = interim
            found.evaluations += res.evaluations
            for m, c in res.candidates.items():
                p = problems[m]
                f = float(p.fitness(c.assignment[None])[0])
                ind, f, e = sweep(p, c.assignment, f, None)
                found.evaluations += e
                if f > found.candidates[m].fitness + 1e-9:
                    found.candidates[m] = Candidate(ind, f)

    def _turn_round(self, problems: list[FrameProblem], found: FrameSearch, ga: dict, check) -> None:
        """A search from scratch also checks the body turned round, under each searched model,
        from the GA's result ``ga`` (model -> Candidate): first its labels read through the
        turned-round body (:func:`turned_labels`, milliseconds), then the whole-body max-product
        at the facing opposite to the GA's (:func:`turned_round`, about 1 s at 41 markers), each
        polished and swept as the GA's result; the best of them is kept. In a worker the
        first's result joins the stream before the second runs. Measured (the cold search of a
        stream's second frame, 41 markers, 2 flickering + 2 ghosts, six starts per take; mean
        share right of the labeling that joins first / of the final one, before -> with the
        first half): a CMU 85 model on HDM05 38.7 / 59.2 -> 60.8 / 61.7 % (the GA's result seen
        from behind at two starts: 0 and 3 % right until the max-product's second, 87 and 49 %
        with the first); on CMU 85's breakdance 69.2 / 69.2 -> 73.8 / 73.8 %; an HDM05 model on
        CMU 85 4.5 / 15.2 -> 10.0 / 15.2 %; on HDM05's own take 80.7 % as before."""
        sweep = self.full_search._sweep_regions          # the CBGA's (only it runs the check)
        for m, c in ga.items():
            p = problems[m]
            if p.n == 0 or p.M <= 3:
                continue
            ind, f, e = check(p, c.assignment, c.fitness, lambda x, fx, p=p: sweep(p, x, fx, None))
            found.evaluations += e
            if f > found.candidates[m].fitness:
                found.candidates[m] = Candidate(ind, f)

    def _fast_path(self, problems: list[FrameProblem], searched: list[int], seed: np.ndarray):
        """The carried-over labeling hill-climbed over its targeted neighbourhood
        (:meth:`_hill_climb`) under each searched model; accepted when under some model it
        fits as well per labelled point as recent frames did, the returning points it leaves
        out counted in (:meth:`_expected_leaving_out`; else ``doubtful``); None when there is
        no level to judge by yet (or the method is not the CBGA)."""
        if self.settings.method != "cbga" or any(np.isnan(self.level[m]) for m in searched):
            return None
        cands, evals = {}, 0
        for m in searched:
            last = {}
            ind, f, e = self._hill_climb(problems[m], seed, last)
            hood = (last["cand"], last["fitness"]) if last and np.array_equal(last["ind"], ind) else None
            cands[m], evals = Candidate(ind, f, hood), evals + e
        ok = any(c.fitness >= self._expected_leaving_out(c.assignment, problems[m], m) - self._accept_margin(m)
                 for m, c in cands.items())
        return FrameSearch(cands, full=False, evaluations=evals, doubtful=not ok)

    # -- fitness level -------------------------------------------------------------------------
    def _learn(self, problems: list[FrameProblem], found: FrameSearch) -> None:
        """Update each searched model's running level (per labelled point) and the scatter of
        good frames about it; a frame without velocities teaches nothing, a frame with labels
        hidden little (``SEEN_POWER``)."""
        if self._provisional or found.doubtful:
            return
        for m, c in found.candidates.items():
            p = problems[m]
            resid = c.fitness - self._expected(c.assignment, p, m)
            fits = resid >= -self._accept_margin(m)
            weight = (frame_weight(p) / p.M) ** SEEN_POWER
            if fits:
                sr = SPREAD_RATE * weight
                self.spread[m] = float(np.sqrt((1 - sr) * self.spread[m] ** 2 + sr * resid ** 2))
            rate = (LEVEL_RATE_FIT if fits else LEVEL_RATE_MISFIT) * weight
            self.level[m] = (1 - rate) * self.level[m] + rate * c.fitness / label_weight(c.assignment, p)

    def _fit_deficit(self, problem: FrameProblem, c: Candidate) -> float:
        """Nats per labelled point by which ``c`` fits below what the model expects of a right
        labeling (its ``fit_reference_per_label``; 0 with no label): the confidence's fit factor
        (:mod:`.confidence`) and, in a bank, the inline loss check (:meth:`_inline_audit`)."""
        if not (c.assignment < problem.n).any():
            return 0.0
        return self._initial_level(problem, "fit_reference_per_label") - c.fitness / label_weight(c.assignment, problem)

    def _initial_level(self, problem: FrameProblem, setting: str = "loglik_per_label") -> float:
        """Typical fitness per labelled point: the model's ``setting`` -- its training
        log-likelihood per label; ``fit_reference_per_label``, the confidence's yardstick, which
        a calibration may lower (:func:`~dtm_labeler.training.calibrate.calibrate`) -- plus the
        per-label gain of the background model (see FrameProblem)."""
        ll = float(problem.model.settings.get(setting, problem.model.settings.get("loglik_per_label", 0.0)))
        gains = problem.label_gain[:-1]
        if gains.size == 0:                        # no points this frame: nothing to calibrate on
            return ll
        full_gain = gains[problem.codes[:-1] == FULL]
        return ll + float(full_gain.mean() if full_gain.size else np.median(gains))

    def _margin(self, floor: float, k: float, m: int) -> float:
        """A drop threshold: ``floor`` nats, or ``k`` times the running RMS scatter of good
        frames' fitness about the expected level where that is larger -- a model over 41
        markers scatters more per frame than one over 14, and a fixed threshold would send
        good frames to the GA (false alarms cost a search each)."""
        return max(floor, k * self.spread[m])

    def _accept_margin(self, m: int) -> float:
        """How far below the level a carried-over labeling (or a frame the level learns from) may fit."""
        return self._margin(self.settings.accept_drop, ACCEPT_SCATTERS, m)

    def _refit_margin(self, m: int) -> float:
        """How far below the level a search result may fit before a (further) full search."""
        return self._margin(self.settings.refit_drop, REFIT_SCATTERS, m)

    def _expected(self, assignment: np.ndarray, problem: FrameProblem, m: int) -> float:
        """Running fitness level of model ``m`` scaled to this frame's labelled points."""
        return self.level[m] * label_weight(assignment, problem)

    def _expected_leaving_out(self, assignment: np.ndarray, problem: FrameProblem, m: int) -> float:
        """What the fast path's labeling must fit to be accepted: :meth:`_expected`, with the labels
        ``assignment`` leaves on no point beyond those the frame cannot show counted in at the
        level, up to the number of points on young tracks it leaves unlabelled.

        The reading (eq. 18-20, 32). The level is per labelled point, so a labeling that leaves a
        label on no point is expected to fit one label's worth less: right where the label's
        marker is hidden, not where the marker is seen and called clutter. A frame of ``n``
        points, a share ``s`` of them clutter (:class:`ClutterShare`), shows about ``n (1 - s)``
        body points, so a right labeling leaves about ``M - n (1 - s)`` labels missing; a label
        left out beyond those is a body point the labeling calls clutter. Which one is read from
        the tracks: a point on a track that began after the stream's start, less than
        ``YOUNG_S`` ago (a marker back from its gap, or a ghost), left unlabelled, is owed an
        explanation; tracks the labeling has called clutter for longer have given their evidence
        already (the clutter share counts them). Measured, ``bench_stream_latency``'s 14-point
        gap stream, corruption seed 3: a ghost held the hidden left wrist's label; the wrist and
        the elbow came back on new tracks and the carried labeling left both out (the right
        ankle's label moved), 40-60 nats below the truth yet within the accept margin of its own
        few labels, for 11 frames; counted, they are searched (search errors 14 -> 4 of 890).
        Without the young-track bound (every label left out beyond those counted) the
        uncalibrated cross-subject cells of ``dtm-eval`` swung by up to 40 points either way
        (``results/search_errors.md``, 2026-12-08)."""
        n = problem.n
        extra = int((assignment >= n).sum()) - max(problem.M - n * (1.0 - self.clutter.share), 0.0)
        if extra > 0 and self._frame_tracks.size == n:
            left = np.ones(n, dtype=bool)
            left[assignment[assignment < n]] = False
            began = self._frame_track_began()
            young = left & (began > self._stream_start) & (self.last_stamp - began < YOUNG_S)
            extra = min(extra, float(young.sum()))
        else:
            extra = 0.0
        return self.level[m] * (label_weight(assignment, problem) + extra)

    def _pattern_expected(self, c: Candidate, problem: FrameProblem, m: int) -> float:
        """What a right labeling with ``c``'s observation pattern is expected to fit: the
        running level times :func:`pattern_weight`, the labels it leaves missing beyond those
        the frame cannot show counted in at the pattern's mean missing label. The frame shows
        about ``n (1 - s)`` body points, ``s`` the stream's clutter share
        (:class:`ClutterShare`), so a right labeling leaves about ``M`` minus that missing; one
        that leaves more is expected to fit as if it had labelled them (the pattern alone would
        forgive a label left out its neighbours' terms as well as its own)."""
        w = pattern_weight(c.assignment, problem)
        missing = int((c.assignment >= problem.n).sum())
        if missing and w < problem.M:
            hidden = max(problem.M - problem.n * (1.0 - self.clutter.share), 0.0)
            w += max(missing - hidden, 0.0) * (problem.M - w) / missing
        return self.level[m] * w

    def _fits_its_pattern(self, c: Candidate, problem: FrameProblem, m: int) -> bool:
        """Whether ``c`` fits within the accept margin of :meth:`_pattern_expected`."""
        return c.fitness >= self._pattern_expected(c, problem, m) - self._accept_margin(m)

    def _falls_short(self, c: Candidate, problem: FrameProblem, m: int) -> bool:
        """The labeling fits ``refit_drop`` nats (or 8 x the running scatter) worse than the
        running level predicts for its labelled points: a search should look further."""
        return c.fitness < self._expected(c.assignment, problem, m) - self._refit_margin(m)

    # -- input ---------------------------------------------------------------------------------
    def _begin(self, xyz: np.ndarray, stamp: float, ids: np.ndarray | None) -> FrameInput:
        s = self.settings
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        finite = np.isfinite(xyz).all(1)
        reason, dt = "", None
        if self.last_stamp is not None:
            dt = stamp - self.last_stamp
            if stamp < self.last_stamp:
                reason = "time went backwards"
            elif dt > s.max_gap_s:
                reason = f"gap of {dt:.2f} s"
            elif stamp == self.last_stamp:
                reason = "repeated stamp"
        if reason:
            self.reset()
        if self._stream_start is None:
            self._stream_start = stamp
        self.last_stamp = stamp
        keep = np.flatnonzero(finite)
        max_pts = s.max_points or 2 * self.n_labels + 8
        n_ignored = 0
        if keep.size > max_pts:        # bounded work: the points nearest the body's last centre
            ref = self.centre if self.centre is not None else np.median(xyz[keep], axis=0)
            d = np.linalg.norm(xyz[keep] - ref, axis=1)
            n_ignored = keep.size - max_pts
            keep = np.sort(keep[np.argsort(d)[:max_pts]])
        pts = xyz[keep]
        upd = self.tracker.update(pts, stamp, None if ids is None else np.asarray(ids)[keep])
        # points whose velocity is first known this frame (their track began last frame), and
        # points back on a track that coasted through a gap (:data:`~.fast_path.RESUMED_EVENT_S`)
        back = (upd.unseen_s is not None and self.n_labels >= RESUMED_EVENT_REGIONS * s.region_size
                and upd.unseen_s >= RESUMED_EVENT_S)
        self._event_points = np.flatnonzero((upd.track_ids[:, None] == self._new_tracks[None]).any(1) | back)
        self._new_tracks = upd.track_ids[upd.new]
        self._frame_tracks = upd.track_ids
        self._track_began = None
        out_ids = upd.track_ids if ids is None else np.asarray(ids, dtype=np.int64)[keep]
        return FrameInput(xyz.shape[0], finite, keep, pts, upd, reason, n_ignored, dt, out_ids)

    def _track_labels(self) -> tuple[np.ndarray, np.ndarray]:
        """:attr:`track_label` as (track ids sorted, their labels), for :func:`_find`."""
        tl = self.track_label
        tids = np.fromiter(tl.keys(), dtype=np.int64, count=len(tl))
        labs = np.fromiter(tl.values(), dtype=np.int64, count=len(tl))
        order = np.argsort(tids)
        return tids[order], labs[order]

    def _seeds(self, track_ids: np.ndarray, n: int) -> np.ndarray | None:
        """Warm start: the labels the tracks carried last frame (vectorised lookup); None when
        fewer than half of the frame's labels can be carried (a fresh search is due)."""
        M = self.n_labels
        self._coasting = np.zeros(M, dtype=bool)
        self._coast_track = np.full(M, -1, dtype=np.int64)
        if not self.track_label:
            return None
        tids, labs = self._track_labels()
        seed = self._carried_labels(track_ids, n, (tids, labs))
        unseen = ~tracker.member(tids, track_ids)         # labels of tracks not seen this frame
        self._coasting[labs[unseen]] = True
        self._coast_track[labs[unseen]] = tids[unseen]
        if 2 * int((seed < n).sum()) < min(M, n):
            return None                  # most tracks are new (e.g. the input's ids restarted): search afresh
        if self.settings.method == "tracker":
            return seed[None]
        return label_ops.repair(seed[None], n, self.rng, fill=False)

    def _carried_labels(self, track_ids: np.ndarray, n: int,
                        tracks: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """The labels the tracks carry (:attr:`track_label`) on this frame's points (label ->
        point, ``n`` where its track is not seen). One label per track and one track per
        point, so it is a valid assignment as it is. ``tracks``: :meth:`_track_labels`, when
        the caller already has it."""
        tids, labs = self._track_labels() if tracks is None else tracks
        out = np.full(self.n_labels, n, dtype=np.int64)
        pos, hit = _find(tids, track_ids)
        out[labs[pos[hit]]] = np.flatnonzero(hit)
        return out

    def _start_labeling(self, track_ids: np.ndarray, n: int) -> np.ndarray | None:
        """The labeling of the provisional frame before this one (the stream's first frame, or
        the first after a reset: positions only, no velocities), carried to this frame by its
        tracks; None when there is none or it labels nothing here.

        Inline, such a frame is searched on positions and searched afresh in the next frame, once
        velocities are known, and that search is a GA: it can end below the labeling the frame
        before already had. Kept beside it, the better of the two under the model is taken
        (:meth:`_keep_start`). In the background a provisional frame asks for no search
        (:meth:`_while_recovering`) and publishes nothing, so there is none to keep. Measured
        (``dtm-eval`` generalisation cells, inline): subject 9's run under the generic model, seed 2: the
        frame-1 search left the left knee unlabelled and the ankle label on the knee's point,
        4 nats below the first frame's labeling carried on, and the fast path kept that shift
        for 50 frames -- 94.68 -> 100 % (the generic body) and 92.99 -> 100 % (``dtm-label``'s
        default); CMU 85 -> HDM05, generic body, 91.59 -> 97.17 %; Table 3's simple GA in stream
        mode W1 / R1 / D1 83.71 / 98.74 / 1.04 -> 100 / 99.16 / 99.93 %; bench_stream_latency's and
        bench_captures' streams unchanged. The better start is not always a right one: on the floor
        moves (41 markers, poses the training never showed) both starts of the self-calibration's
        window are half wrong; the kept one (49 % right) held the window while the searches from
        the worse one (32 %) had found the truth by frame ~50, so the calibration's first round
        confirms labels 65 % right instead of 97 %, and ``dtm-label``'s default falls 96.97 ->
        27.34 % at seed 0 (seeds 1-3: 94.37 / 71.99 / 62.80 -> 96.23 / 71.99 / 87.55 %)."""
        if not self._provisional or self.settings.mode != "stream" or not self.track_label:
            return None
        start = self._carried_labels(track_ids, n)
        return start if (start < n).any() else None

    def _keep_start(self, problems: list[FrameProblem], searched: list[int], found: FrameSearch,
                    start: np.ndarray) -> None:
        """Inline: the provisional frame's labeling carried here (:meth:`_start_labeling`),
        hill-climbed, replaces a search result it beats under the same model."""
        for m in searched:
            p = problems[m]
            ind, f, e = polish(p, start, None, self.settings.fast_rounds, neighbours=self._moves(p, start))
            found.evaluations += e
            if f > found.candidates[m].fitness:
                found.candidates[m] = Candidate(ind, f)

    # -- output --------------------------------------------------------------------------------
    @staticmethod
    def _truth_fitness(problem: FrameProblem, truth: np.ndarray | None, inp: FrameInput, chosen: np.ndarray,
                       prior=None) -> tuple[float, float]:
        """Fitness of the true labeling (``truth``: input index per label, -1 missing), and what
        the fast path's move ``prior`` (:meth:`~.fast_path.FastPath._move_cost`, None when the
        frame was not climbed) charges it beyond the ``chosen`` assignment: a frame whose truth
        fits better (a search error by the model alone) but pays more than that in the priors
        was held by them, not missed by the search (:mod:`~dtm_labeler.evaluation.metrics`)."""
        if truth is None:
            return float("nan"), 0.0
        n = problem.n
        pos = np.full(inp.n_in + 1, n, dtype=np.int64)
        pos[inp.keep] = np.arange(inp.keep.size)
        tr = np.asarray(truth, dtype=np.int64)
        true = np.where(tr < 0, n, pos[np.where(tr < 0, inp.n_in, tr)])
        fitness = float(problem.fitness(true[None])[0])
        if prior is None:
            return fitness, 0.0
        paid = prior(np.stack([chosen, true]))
        return fitness, float(paid[1] - paid[0])

    def _publish(self, problem: FrameProblem, best: Candidate, inp: FrameInput, doubtful: bool):
        """Votes (eq. 32), confidences (:mod:`.confidence`) and bookkeeping after the search.
        Returns (assignment with -1 for missing, this frame's search labels per point,
        published labels, confidences, confirmations, local posteriors, vote shares)."""
        n = problem.n
        assignment = best.assignment
        assign = np.where(assignment >= n, -1, assignment)
        search_labels = np.full(n, -1, dtype=np.int64)
        present = assign >= 0
        search_labels[assign[present]] = np.flatnonzero(present)
        upd = inp.upd
        self.votes.add(upd.track_ids, search_labels, abstain=doubtful)
        if self.settings.mode == "stream":
            pub, share = self.votes.publish(upd.track_ids, search_labels)
        else:
            pub, share = search_labels.copy(), (search_labels >= 0).astype(float)
        alt, f_alt = best.neighbourhood or (self._moves(problem, assignment)(assignment), None)
        if f_alt is None and len(alt):       # scored once: the labels' and the free points' posteriors read them
            f_alt = problem.fitness(alt)
        # an alternative that rearranges a rigid cluster against what its tracks' frames preferred
        # is that much less likely: the published odds carry the arrangement prior too
        began = self._frame_track_began()
        prior = self.cluster_evidence.cost(assignment, n, upd.track_ids, began, self.last_stamp)
        alt_prior = None if prior is None or not len(alt) else prior(alt)
        if not doubtful:
            self.clutter.update(search_labels)
        f_rel = self._weigh_releases(problem, assignment, best.fitness)
        post, strict = label_posteriors(problem, assignment, best.fitness, alt, self.settings.confidence_temperature,
                                        f_alt, alt_prior, self.clutter.odds,
                                        self._transfer_alternatives(problem, assignment, prior), f_rel)
        post_point, strict_point = np.full(n, np.nan), np.full(n, np.nan)
        post_point[assign[present]] = post[present]
        strict_point[assign[present]] = strict[present]
        deficit = self._fit_deficit(problem, best)
        calibrated = problem.model.body is not None and bool(problem.model.body.calibration)
        # a doubted frame (background: a search asked for, the best labeling known published) is
        # judged on what a right labeling with its observation pattern fits (:func:`pattern_weight`)
        # before its confidence is halved or, at a cold start, zeroed as lost: per labelled point a
        # right labeling of a half-hidden frame fits far below a fully seen one's, and the doubt and
        # the loss then come from the hidden markers, not from the labels
        unvouched_lost = doubtful and not self._vouched and deficit > LOST_NATS and \
            self._initial_level(problem, "fit_reference_per_label") - \
            best.fitness / pattern_weight(best.assignment, problem) > LOST_NATS
        pattern_fit = doubtful and self._vouched and \
            self._fits_its_pattern(best, problem, self.models.index(problem.model))
        # a label the votes publish on a point this frame's search left unlabelled: what the search
        # says of that point is how likely it is to stay unlabelled (not a certainty of the label)
        # (rare: a few frames in a hundred of a stream with gaps and ghosts)
        if ((pub >= 0) & (search_labels < 0)).any():
            p_free = unlabelled_posteriors(problem, assignment, best.fitness, alt,
                                           self.settings.confidence_temperature, f_alt, alt_prior)
            post_pub = np.where(np.isnan(post_point), p_free, post_point)
        else:
            post_pub = post_point
        conf = published_confidence(post_pub, search_labels, pub, share, doubtful and not pattern_fit,
                                    0.0 if calibrated else deficit, lost=unvouched_lost)
        confirmation = published_confidence(strict_point, search_labels, pub, share, doubtful, deficit,
                                            CONFIRMATION_POWER)
        # the next frame starts from this frame's search result, not from the votes: a
        # correction must not be undone by the window's older majority. Labels stay with
        # their tracks while they coast (occluded for a few frames).
        published = {int(t): int(lab) for t, lab in zip(upd.track_ids, search_labels) if lab >= 0}
        taken = set(published.values())
        seen = set(int(t) for t in upd.track_ids)
        lost = set(int(t) for t in upd.lost)
        self.tenure.update(upd.track_ids, search_labels, upd.lost, self.last_stamp)
        if not doubtful:
            self._vouched = True
            self.cluster_evidence.measure(problem, assignment, upd.track_ids, began, self.last_stamp)
            if self.bar_votes.active:
                self.bar_votes.update(assignment, inp.pts, upd.track_ids, self.last_stamp, self._settled(assignment, n))
        self.track_label = {t: lab for t, lab in self.track_label.items()
                            if t not in seen and t not in lost and lab not in taken}
        self.track_label.update(published)
        order = np.argsort(upd.track_ids, kind="stable")
        conf_f = np.asarray(conf, dtype=float)
        self._carried = (upd.track_ids[order], pub[order].astype(np.int64), conf_f[order])
        self._label_confidence[pub[pub >= 0]] = conf_f[pub >= 0]
        self._since_search += 1
        self._frame_no += 1
        if present.any():
            self.centre = inp.pts[assign[present]].mean(0)
            self.heading = float(problem.yaw(np.where(assign < 0, n, assign)[None])[0])
        return assign, search_labels, pub, conf, confirmation, post_point, share


def _input_index(assign: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Search assignment (index into the kept points, -1 missing) -> input point index."""
    out = np.full(assign.shape, -1, dtype=np.int64)
    present = assign >= 0
    out[present] = keep[assign[present]]
    return out


__all__ = ["TrackedLabeler", "Engine", "FrameResult", "CarriedFrame", "FrameInput", "FrameSearch", "Candidate", "scatter",
           "label_weight", "pattern_weight", "frame_weight"]
