"""Label labelled recordings as if they were unlabeled streams, and score the result.

``label_clip`` is what ``dtm-label`` runs and what the report writer (``dtm-eval``) calls:

1. the clip's labels are stripped: the model's points are selected (derived to the 14 body
   points when needed) and every frame becomes an unordered point cloud;
2. :func:`~dtm_labeler.evaluation.corruption.corrupt_clip` hides ``occlude`` points, adds
   ``clutter`` ghost points and ``noise_mm`` noise, and shuffles each frame (keeping the truth);
3. a fresh :class:`~dtm_labeler.labeling.stream.StreamLabeler` gets the frames one by one with
   stamps ``frame / rate`` and the true assignment (only to count search errors);
4. :class:`~dtm_labeler.evaluation.metrics.MetricsAccumulator` scores the published labels.

By default the labeler gets no track ids (its own tracker associates points); with
``use_ids=True`` it gets the simulated mocap-system ids of the corrupted stream.

A take's own unlabelled points (``extra``, from :func:`~dtm_labeler.motion.unlabelled.model_input`)
go into the stream as points that must stay unlabelled (counted as ghosts). A take without
names (``named=False``) is labelled but not scored: accuracy and ghost figures stay empty.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from .corruption import CorruptedStream, corrupt_clip
from .metrics import Metrics, MetricsAccumulator
from ..labeling.anonymous_presence import AnonymousPresence, anonymous_presence
from ..labeling.stream import LabelerSettings, StreamLabeler
from ..labeling.take_pass import take_pass as second_pass
from ..labeling.take_restarts import MIN_GAIN_PER_FRAME, REJOIN_FRAMES, agrees, gain_per_frame, restart_windows
from ..labeling.take_votes import take_votes
from ..model.dtm import TriangulatedModel
from ..motion.clip import MotionClip
from ..motion.pointsets import model_points
from ..training.calibrate import auto_calibrate, recognised_person, session_calibrate

Progress = Callable[[int, int], None]


@dataclass
class FrameRecord:
    """One labelled frame (input order = the shuffled order the labeler saw)."""

    index: int                    # frame number within the clip given
    stamp: float                  # seconds
    xyz: np.ndarray               # (n, 3)
    truth: np.ndarray             # (n,) true label index, -1 = ghost
    labels: np.ndarray            # (n,) published label, -1 = unlabelled
    confidence: np.ndarray        # (n,)
    track_ids: np.ndarray         # (n,) labeler track id
    search_labels: np.ndarray     # (n,) search result before votes
    log_likelihood: float
    truth_fitness: float
    latency_ms: float
    full_search: bool
    generations: int
    evaluations: int
    reset: str = ""
    doubtful: bool = False        # published before a search vouched for it
    truth_prior: float = 0.0      # nats the fast path's priors charge the truth beyond the search's result


@dataclass
class ClipRun:
    """Result of one clip: scores, the accumulator (to merge), and the frames if kept."""

    source: str
    metrics: Metrics
    accumulator: MetricsAccumulator
    records: list[FrameRecord] = field(default_factory=list)
    settings: dict = field(default_factory=dict)
    causal: MetricsAccumulator | None = None   # with take votes: the labels as published live, scored
    voted: MetricsAccumulator | None = None    # with the take pass: the take-voted labels before it, scored


def model_clip(model: TriangulatedModel | Sequence[str], clip: MotionClip) -> MotionClip:
    """The clip's points named like the model's labels (``model`` or its label names), in the
    model's order (the 14 body points are derived from markers / joints when the model uses
    them). ValueError if the clip lacks some of them."""
    labels = model.labels if isinstance(model, TriangulatedModel) else tuple(model)
    try:
        return model_points(clip, labels)
    except KeyError as e:
        raise ValueError(str(e).strip("'\"")) from None


def run_stream(model: TriangulatedModel, stream: CorruptedStream, settings: LabelerSettings | None = None,
               use_ids: bool = False, keep_records: bool = True, progress: Progress | None = None,
               done: int = 0, total: int | None = None, scored: bool = True, take_votes_s: float = 0.0,
               take_pass: bool = False, restart_s: float = 0.0, anonymous_check: bool = False) -> ClipRun:
    """Feed a corrupted stream (label index = model label index) to a fresh labeler
    (``take_votes_s``, ``take_pass``, ``restart_s``: see :func:`run_labeler`). ``anonymous_check``
    (a model with anonymous points): a take the live pass finds without their markers
    (:mod:`~dtm_labeler.labeling.anonymous_presence`) is labelled again, from its first frame, by the
    model without them; ``settings["anonymous_points"]`` says what was found."""
    if tuple(stream.names) != tuple(model.labels):
        raise ValueError("stream label names differ from the model's labels")
    settings = settings or LabelerSettings()
    found: list[AnonymousPresence] = []

    def absent(labeler) -> bool:
        found.append(anonymous_presence(model, labeler.label_frames, len(stream)))
        return found[-1].absent
    check = anonymous_check and bool(model.anonymous.any())
    run = run_labeler(StreamLabeler(model, settings), model.labels, stream, use_ids,
                      keep_records, progress, done, total, scored=scored, take_votes_s=take_votes_s,
                      take_pass=take_pass, restart_s=restart_s, fresh=lambda: StreamLabeler(model, settings),
                      stop_after_live=absent if check else None)
    if run is None:                              # the take does not carry the anonymous points' markers
        named = model.named_only()
        run = run_stream(named, first_labels(stream, named.n_labels), settings, use_ids, keep_records, progress,
                         done, total, scored, take_votes_s, take_pass, restart_s)
    if found:
        run.settings["anonymous_points"] = found[0].as_dict()
    return run


def first_labels(stream: CorruptedStream, n: int) -> CorruptedStream:
    """``stream`` for a model of its first ``n`` labels (:meth:`TriangulatedModel.named_only`): the
    later labels' columns dropped -- no point of the stream may carry them."""
    if any((f.truth >= n).any() for f in stream):
        raise ValueError(f"the stream shows points of labels beyond its first {n}")
    frames = [replace(f, label_to_index=f.label_to_index[:n]) for f in stream]
    return replace(stream, frames=frames, names=tuple(stream.names[:n]), visible=stream.visible[:, :n],
                   occluded=stream.occluded[:, :n])


def run_labeler(labeler, labels: Sequence[str], stream: CorruptedStream, use_ids: bool = False,
                keep_records: bool = True, progress: Progress | None = None, done: int = 0,
                total: int | None = None, on_frame=None, scored: bool = True,
                take_votes_s: float = 0.0, take_pass: bool = False, restart_s: float = 0.0,
                fresh: Callable[[], object] | None = None,
                stop_after_live: Callable[[object], bool] | None = None) -> ClipRun | None:
    """Run any labeler with the ``process`` interface (StreamLabeler, BankLabeler) over a
    corrupted stream and score it (``scored=False``: a take without names, nothing to score
    against; frames and latencies are still counted); ``on_frame(result)`` sees every frame's
    result. ``take_votes_s`` > 0 (offline only): the published labels are voted again over
    the frames +- that many seconds around each frame (:mod:`~dtm_labeler.labeling.take_votes`);
    the run's metrics score those, :attr:`ClipRun.causal` the labels as published live.
    ``take_pass`` (with take votes, single-model labelers): then every frame searched again at
    the take's heading and voted again (:mod:`~dtm_labeler.labeling.take_pass`); progress
    counts its frames after the labeler's. ``restart_s`` > 0 with take votes and ``fresh`` (a
    factory of new labelers like ``labeler``): before the votes, the take is labelled again
    from fresh starts every ``restart_s`` seconds and each kept where it fits better
    (:func:`restarted`; ``settings["restarts"]`` says what each did); :attr:`ClipRun.causal`
    stays the first labeler's, as published live. ``stop_after_live(labeler)`` True after the
    live pass: no more is done and None is returned (the take is to be labelled otherwise)."""
    acc = MetricsAccumulator(labels, stream.rate)
    records: list[FrameRecord] = []
    revote = take_votes_s > 0
    passing = revote and take_pass and len(getattr(labeler, "models", ())) == 1      # the pass: two searches per frame
    windows = restart_windows(len(stream), stream.rate, restart_s) if revote and fresh is not None and \
        restart_s > 0 else []
    restart_frames = sum(stop - first for first, _, stop in windows)
    total = total if total is not None else len(stream) * (3 if passing else 1) + restart_frames
    t_wall = time.perf_counter()
    for i, f in enumerate(stream):
        res = labeler.process(f.xyz, f.stamp, ids=f.ids if use_ids else None,
                              truth=f.label_to_index if scored else None)
        acc.add_result(f.truth, res, valid=np.isfinite(f.xyz).all(1) & scored)
        if on_frame is not None:
            on_frame(res)
        if keep_records or revote:
            records.append(_record(f, res))
        if progress is not None:
            progress(done + i + 1, total)
    if stop_after_live is not None and stop_after_live(labeler):
        return None
    causal = voted = None
    restarts = []
    if windows:
        restarts = restarted(records, stream, fresh, windows, use_ids, scored,
                             None if progress is None else (lambda k: progress(done + len(stream) + k, total)))
        done += restart_frames
    if revote:
        causal = acc
        acc = revoted(records, labels, stream.rate, take_votes_s, scored)
        if passing:
            voted, n = acc, len(stream)
            acc = passed(records, labels, stream.rate, take_votes_s, labeler.models[0], labeler.settings, scored,
                         progress=None if progress is None else (lambda k, _: progress(done + n + k, total)))
    wall = time.perf_counter() - t_wall
    return ClipRun(source=stream.source, metrics=acc.metrics(), accumulator=acc,
                   records=records if keep_records else [],
                   settings=dict(stream.settings, use_ids=use_ids, wall_s=wall, scored=scored,
                                 take_votes_s=take_votes_s, take_pass=passing,
                                 restart_s=restart_s if windows else 0.0, restarts=restarts),
                   causal=causal, voted=voted)


def _record(f, res) -> FrameRecord:
    """The record of stream frame ``f`` labelled as ``res`` (a labeler's ``process`` result)."""
    return FrameRecord(
        index=f.index, stamp=f.stamp, xyz=f.xyz, truth=f.truth, labels=res.labels,
        confidence=res.confidence, track_ids=res.track_ids, search_labels=res.search_labels,
        log_likelihood=res.log_likelihood, truth_fitness=res.truth_fitness, latency_ms=res.latency_ms,
        full_search=res.full_search, generations=res.generations, evaluations=res.evaluations,
        reset=res.reset, doubtful=bool(getattr(res, "doubtful", False)),
        truth_prior=float(getattr(res, "truth_prior", 0.0)))


#: track ids of the ``k``-th fresh start's frames are offset by ``k`` times this (they are its own tracks)
RESTART_TRACK_OFFSET = 1 << 40


def restarted(records: list[FrameRecord], stream: CorruptedStream, make, windows, use_ids: bool = False,
              scored: bool = True, progress: Callable[[int], None] | None = None,
              min_gain_per_frame: float = MIN_GAIN_PER_FRAME) -> list[dict]:
    """Fresh starts over a labelled take (:mod:`~dtm_labeler.labeling.take_restarts`), in place:
    for each ``(first, start, stop)`` of ``windows`` a new labeler from ``make()`` is fed frames
    ``first`` on, stopped where it agrees with ``records`` for ``REJOIN_FRAMES`` frames in a
    row; its records from ``start`` to there (or to ``stop``) replace those of ``records`` when
    they fit better by ``min_gain_per_frame`` (:func:`~dtm_labeler.labeling.take_restarts.fits_better`;
    their track ids offset: its own tracks). ``progress(frames so far)``, a stopped start's
    frames counted as fed. Returns one dict per window: ``start_s`` and ``rejoined_s`` (stamps;
    None: it never agreed), ``kept``, ``gain_per_frame`` (nats)."""
    out, fed = [], 0
    for k, (first, start, stop) in enumerate(windows, start=1):
        fresh: list[FrameRecord] = []
        run, rejoined = 0, None
        with make() as labeler:
            for i in range(first, stop):
                f = stream[i]
                res = labeler.process(f.xyz, f.stamp, ids=f.ids if use_ids else None,
                                      truth=f.label_to_index if scored else None)
                if progress is not None:
                    progress(fed + i - first + 1)
                if i < start:
                    continue
                fresh.append(_record(f, res))
                run = run + 1 if agrees(records[i].labels, res.labels) else 0
                if run >= REJOIN_FRAMES:
                    rejoined = i
                    break
        fed += stop - first
        gain = gain_per_frame([r.log_likelihood for r in fresh],
                              [r.log_likelihood for r in records[start:start + len(fresh)]])
        kept = gain > min_gain_per_frame
        if kept:
            for j, r in enumerate(fresh):
                r.track_ids = np.where(r.track_ids >= 0, r.track_ids + k * RESTART_TRACK_OFFSET, -1)
                records[start + j] = r
        out.append({"start_s": float(stream[start].stamp), "kept": bool(kept),
                    "rejoined_s": None if rejoined is None else float(stream[rejoined].stamp),
                    "gain_per_frame": float(gain)})
    if progress is not None:
        progress(fed)
    return out


def revoted(records: list[FrameRecord], labels: Sequence[str], rate: float, take_votes_s: float,
            scored: bool = True) -> MetricsAccumulator:
    """The records' labels and confidences voted again over +- ``take_votes_s`` around each
    frame (:func:`~dtm_labeler.labeling.take_votes.take_votes`; in place) and scored afresh."""
    half = max(0, int(round(take_votes_s * rate)))
    new_labels, new_conf = take_votes([r.track_ids for r in records], [r.search_labels for r in records],
                                      len(labels), half, [r.doubtful for r in records])
    return _rescored(records, labels, rate, new_labels, new_conf, scored)


def passed(records: list[FrameRecord], labels: Sequence[str], rate: float, take_votes_s: float, model, settings,
           scored: bool = True, progress: Progress | None = None) -> MetricsAccumulator:
    """The take's second pass (:func:`~dtm_labeler.labeling.take_pass.take_pass`) from the
    records' (voted) labels, votes over +- ``take_votes_s``; in place, scored afresh."""
    half = max(0, int(round(take_votes_s * rate)))
    new_labels, new_conf = second_pass(model, settings.background, [r.xyz for r in records],
                                       [r.track_ids for r in records], [r.labels for r in records], rate, half,
                                       region_size=settings.full.region_size,
                                       polish_rounds=settings.full.polish_rounds,
                                       heading_snap_deg=settings.heading_snap_deg, progress=progress,
                                       hold_nats=settings.hold_nats, hold_s=settings.hold_s)
    return _rescored(records, labels, rate, new_labels, new_conf, scored)


def _rescored(records, labels, rate, new_labels, new_conf, scored) -> MetricsAccumulator:
    acc = MetricsAccumulator(labels, rate)
    for r, lab, conf in zip(records, new_labels, new_conf):
        r.labels, r.confidence = lab, conf
        acc.add(r.truth, lab, latency_ms=r.latency_ms, log_likelihood=r.log_likelihood,
                truth_fitness=r.truth_fitness, search_labels=r.search_labels, full_search=r.full_search,
                valid=np.isfinite(r.xyz).all(1) & scored, confidence=conf, truth_prior=r.truth_prior)
    return acc


def label_clip(model: TriangulatedModel, clip: MotionClip, settings: LabelerSettings | None = None,
               occlude: int = 0, clutter: int = 0, noise_mm: float = 0.0, seed: int = 0,
               progress: Progress | None = None, use_ids: bool = False, gap_frames: float = 1.0,
               keep_records: bool = True) -> tuple[Metrics, list[FrameRecord]]:
    """Strip, corrupt, shuffle, label and score one clip. Returns ``(metrics, records)``;
    ``progress(done, total)`` is called after every frame."""
    run = label_clip_run(model, clip, settings, occlude, clutter, noise_mm, seed, progress, use_ids,
                         gap_frames, keep_records)
    return run.metrics, run.records


def label_clip_run(model: TriangulatedModel, clip: MotionClip, settings: LabelerSettings | None = None,
                   occlude: int = 0, clutter: int = 0, noise_mm: float = 0.0, seed: int = 0,
                   progress: Progress | None = None, use_ids: bool = False, gap_frames: float = 1.0,
                   keep_records: bool = True, done: int = 0, total: int | None = None,
                   extra: np.ndarray | None = None, named: bool = True, take_votes_s: float = 0.0,
                   take_pass: bool = False, restart_s: float = 0.0, calibrate_s: float = 0.0,
                   calibration_progress: Progress | None = None,
                   fallback: TriangulatedModel | None = None, session_check: bool = False,
                   anonymous_check: bool = False) -> ClipRun:
    """:func:`label_clip` returning the full :class:`ClipRun`; ``extra`` (F, K, 3): the take's
    unlabelled points; ``named=False``: ``clip`` holds no truth (labelled, not scored).
    ``calibrate_s`` > 0: a generic body is first self-calibrated on the stream's first
    ``calibrate_s`` seconds (:func:`_auto_calibrated`; the points as the labeler gets them, no
    label used) and kept when it holds up (:func:`~dtm_labeler.training.calibrate.auto_calibrate`);
    every frame is then labelled -- by ``fallback``, when given, if the calibration is not
    kept, and by ``fallback`` checked for this session when the calibration measured
    ``fallback``'s person (:func:`~dtm_labeler.training.calibrate.recognised_person`);
    ``session_check``: ``model`` is calibrated to the person of the take, whose markers may
    sit elsewhere this session (:func:`~dtm_labeler.training.calibrate.session_calibrate` instead);
    ``settings["calibration"]`` says what was done; ``calibration_progress``: the frames
    of each of its self-labellings; ``anonymous_check``: see :func:`run_stream`."""
    mc = clip if not named else model_clip(model, clip)
    stream = corrupt_clip(mc, occlude=occlude, clutter=clutter, noise_mm=noise_mm, seed=seed,
                          gap_frames=gap_frames, extra=extra)
    calibration = None
    if calibrate_s > 0:
        model, calibration = _auto_calibrated(model, stream, calibrate_s, calibration_progress,
                                              session_calibrate if session_check else auto_calibrate)
        found = recognised_person(model, fallback, [stream[i].xyz for i in range(calibration["window"])],
                                  stream.rate) if calibration["applied"] else None
        if found is not None:                    # the take shows the training takes' person
            model, calibration = found
        elif fallback is not None and not calibration["applied"]:
            model = fallback
    run = run_stream(model, stream, settings, use_ids=use_ids, keep_records=keep_records, progress=progress,
                     done=done, total=total, scored=named, take_votes_s=take_votes_s, take_pass=take_pass,
                     restart_s=restart_s, anonymous_check=anonymous_check)
    if calibration is not None:
        run.settings["calibration"] = calibration
    return run


def _auto_calibrated(model: TriangulatedModel, stream: CorruptedStream, seconds: float,
                     progress: Progress | None = None, calibrate=auto_calibrate):
    """:func:`~dtm_labeler.training.calibrate.auto_calibrate` (or ``calibrate``, of the same
    signature) on the stream's first ``seconds``;
    on a take shorter than three times that, on its first third and on all of its first
    ``seconds`` both, keeping the calibration the model reproduces best (the larger share of its
    confirmed labels kept). Neither window is right for every short take: subject 9's 1.4 s run
    keeps 90 % of its labels over the first third (94.7 % right after) and 96 % over all of it
    (98.3 %); subject 5's 4.9 s pirouette 98 % over the first third (99.9 %) and 62 % over all
    of it (rejected)."""
    full = int(min(round(seconds * stream.rate), len(stream)))
    best = None
    for window in sorted({min(full, len(stream) // 3), full}):
        out = calibrate(model, [stream[i].xyz for i in range(window)], stream.rate, progress=progress)
        out[1]["window"] = window            # the frames it was measured on
        if best is None or (out[1]["applied"], out[1].get("kept_share", 0.0)) > \
                (best[1]["applied"], best[1].get("kept_share", 0.0)):
            best = out
    return best


def label_clips(model: TriangulatedModel, clips: Sequence[MotionClip], settings: LabelerSettings | None = None,
                occlude: int = 0, clutter: int = 0, noise_mm: float = 0.0, seed: int = 0,
                progress: Progress | None = None, use_ids: bool = False, gap_frames: float = 1.0,
                keep_records: bool = False) -> tuple[Metrics, list[ClipRun]]:
    """:func:`label_clip` over several clips (clip ``i`` corrupted with ``seed + i``, each with
    a fresh labeler). Returns the pooled metrics (latencies pooled, durations added, swaps
    never counted across clips) and the per-clip runs."""
    clips = list(clips)
    if not clips:
        raise ValueError("no clips to label")
    # check every clip before the (long) labeling starts
    prepared = [model_clip(model, c) for c in clips]
    total = sum(c.n_frames for c in prepared)
    runs, done = [], 0
    for i, mc in enumerate(prepared):
        runs.append(label_clip_run(model, mc, settings, occlude, clutter, noise_mm, seed + i, progress, use_ids,
                                   gap_frames, keep_records, done=done, total=total))
        done += mc.n_frames
    pooled = MetricsAccumulator.merge(r.accumulator for r in runs).metrics()
    return pooled, runs
