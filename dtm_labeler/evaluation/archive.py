"""Archives: many takes, one job per take, run here, in local processes or on a dask cluster.

A job (:class:`LabelJob`) is everything one take needs: the take's path, the model (as the
bytes of its file, so cluster workers need no copy of it), the labeler settings and the
corruption seed of that take. :func:`label_take` loads the take, splits it for the model
(:func:`~dtm_labeler.motion.unlabelled.model_input`), labels it, writes the labelled capture
if asked and returns a :class:`TakeResult` whose metrics accumulator the caller merges in
input order -- so every figure except the timings is the same whichever way the jobs run.

:class:`JobRunner` (:func:`run_jobs` for one batch) runs any such function over jobs:

* ``workers=1`` and no ``dask``: in this process, one after the other;
* ``workers=N``: a ``concurrent.futures`` process pool of N local processes;
* ``dask="local"``: a ``dask.distributed.LocalCluster`` of ``workers`` single-threaded
  worker processes started for the run and closed after it; ``dask="tcp://host:8786"``: a
  running scheduler (its workers need this package installed and must see the takes' and
  the outputs' paths, e.g. a shared file system).

Results come back in job order; ``progress(done, total, result)`` is called as each job
finishes (one progress bar for the whole archive). A take that fails (unreadable file,
wrong names ...) gives a result with ``error`` set; the others go on.
"""
from __future__ import annotations

import hashlib
import io
import os
import socket
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from ..labeling.anonymous_presence import AnonymousPresence
from ..labeling.stream import LabelerSettings
from ..model.io import model_from_arrays
from ..motion.clip import frame_range
from ..motion.load import load_clip
from ..motion.naming import one_subject
from ..motion.unlabelled import model_input
from ..training.calibrate import (KEPT_AS_IT_IS, CalibrationError, calibrate_from_clip, generic_view,
                                  takes_calibration)
from .labelled_capture import CaptureFormat, from_records
from .metrics import MetricsAccumulator
from .pipeline import label_clip_run

Progress = Callable[[int, int, Any], None]


@dataclass(frozen=True)
class LabelJob:
    """One take to label (see the module doc)."""

    index: int
    source: str
    settings: LabelerSettings
    frames: str | None = None
    occlude: int = 0
    clutter: int = 0
    noise_mm: float = 0.0
    gap_frames: float = 1.0
    seed: int = 0                      # corruption seed of this take
    use_ids: bool = False
    keep_unlabelled: bool = True
    ignore_names: bool = False         # label every point as unnamed (no score)
    out: str | None = None             # labelled capture to write (.c3d / .csv)
    keep_records: bool = False         # return every frame (per-point CSV)
    load: dict = field(default_factory=dict)   # load_clip keywords: up_axis, unit_scale, asf_path
    calibrate: str | None = None       # frames A:B of the take to calibrate the body terms on, label after B;
                                       # "auto": self-calibrate on the take's start, label all; None / "off"
    calibrate_labels: str = "model"    # labels of those frames: "model" (self-labelled) or "capture"
    take_votes_s: float = 0.0          # votes again over +- this many seconds around each frame (0: as live)
    take_pass: bool = True             # with take votes: each frame searched again at the take's heading
    restart_s: float = 0.0             # with take votes: fresh starts every this many seconds (0: none)


#: ``LabelJob.calibrate`` values: self-calibrate a generic body on each take's first
#: ``AUTO_CALIBRATION_S`` seconds (a shorter take: its first third or all of it, whichever the
#: model reproduces better) and keep it when it holds up
#: (:func:`~dtm_labeler.training.calibrate.auto_calibrate`), or label with the model as it is
AUTO, OFF = "auto", "off"
AUTO_CALIBRATION_S = 5.0


@dataclass
class TakeResult:
    index: int
    source: str
    error: str = ""
    frame_range: tuple[int, int] = (0, 0)
    named: bool = True
    unlabelled_points: int = 0         # unlabelled channels / unknown markers fed as ghosts
    unlabelled_samples: int = 0
    copies_left_out: int = 0           # unlabelled channels that copy another channel
    fragments_joined: int = 0          # unlabelled samples joined to the named marker they continue
    up_axis: str = ""
    note: str = ""
    out: str | None = None
    accumulator: MetricsAccumulator | None = None
    causal: MetricsAccumulator | None = None    # take votes: the labels as published live, scored
    voted: MetricsAccumulator | None = None     # take pass: the take-voted labels before it, scored
    records: list = field(default_factory=list)
    wall_s: float = 0.0
    rate: float = 0.0
    worker: str = ""                   # host:pid of the process that labelled the take
    calibration: dict | None = None    # the subject calibration used (``--calibrate``)
    restarts: list = field(default_factory=list)    # fresh starts over the take (``--restarts``), one dict each
    anonymous_points: dict | None = None   # what the take showed of the model's anonymous points (if any)

    @property
    def metrics(self):
        return self.accumulator.metrics()

    @property
    def settings(self) -> dict:
        """Where the labelled frames sit in the take (as :class:`~.pipeline.ClipRun` settings)."""
        return {"frame_range": list(self.frame_range), "frame_offset": self.frame_range[0], "rate": self.rate}

    def summary(self) -> dict:
        """JSON-ready description of the take (metrics are added by the caller)."""
        d = {"source": self.source, "frame_range": list(self.frame_range), "named": self.named,
             "unlabelled_points": self.unlabelled_points, "unlabelled_samples": self.unlabelled_samples,
             "copies_left_out": self.copies_left_out, "fragments_joined": self.fragments_joined,
             "up_axis": self.up_axis, "wall_s": self.wall_s,
             "worker": self.worker}
        if self.out:
            d["out"] = self.out
        if self.note:
            d["note"] = self.note
        if self.calibration is not None:
            d["calibration"] = self.calibration
        if self.restarts:
            d["restarts"] = self.restarts
        if self.anonymous_points is not None:
            d["anonymous_points"] = self.anonymous_points
        if self.error:
            d["error"] = self.error
        return d


_MODELS: dict[str, Any] = {}


def model_from_bytes(data: bytes):
    """A model from the bytes of its file, parsed once per process."""
    key = hashlib.sha1(data).hexdigest()
    if key not in _MODELS:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            _MODELS[key] = model_from_arrays({k: z[k] for k in z.files}, "model")
    return _MODELS[key]


def label_take(job: LabelJob, model_bytes: bytes, progress: Callable[[int, int], None] | None = None,
               calibration_progress: Callable[[int, int], None] | None = None) -> TakeResult:
    """Load, split, label (and write) one take; errors in the take are returned, not raised.
    ``progress``: frames labelled; ``calibration_progress``: the frames of each self-labelling
    of ``--calibrate auto``."""
    t0 = time.perf_counter()
    res = TakeResult(job.index, job.source, worker=f"{socket.gethostname()}:{os.getpid()}")
    try:
        model = model_from_bytes(model_bytes)
        clip = load_clip(job.source, **job.load)
        a, b = frame_range(job.frames, clip.n_frames)
        clip = clip.slice(a, b)
        auto = job.calibrate == AUTO
        if job.calibrate and not auto and job.calibrate != OFF:
            model, clip, res.calibration, skip = calibrated(model, clip, job.calibrate, job.calibrate_labels, a)
            a += skip
        if auto and trained_on(model, job.source):
            auto, res.calibration = False, {
                "applied": False, "source": "auto (the take's first frames, self-labelled)",
                "reason": "the take is the capture the model was trained on: the model is of its person"}
        whose = of_training_person(model, job.source) if auto else None
        kept = keeps_training_calibration(model, job.source) if auto else None
        if kept is not None:            # one of the captures the calibration was measured on: as it is
            auto, res.calibration = False, {
                "applied": False, "source": "auto (the take's first frames, self-labelled)",
                "reason": f"the model is calibrated to this capture's person ({kept})"}
        generic = generic_view(model) if auto and whose is None else None
        person, model = (model, generic) if generic is not None else (None, model)
        mi = model_input(clip, model.labels, job.keep_unlabelled, job.ignore_names)
        run = label_clip_run(model, mi.clip, job.settings, occlude=job.occlude, clutter=job.clutter,
                             noise_mm=job.noise_mm, seed=job.seed, progress=progress, use_ids=job.use_ids,
                             gap_frames=job.gap_frames, keep_records=job.keep_records or job.out is not None,
                             extra=mi.extra, named=mi.named, take_votes_s=job.take_votes_s,
                             take_pass=job.take_pass, restart_s=job.restart_s, calibrate_s=AUTO_CALIBRATION_S if auto else 0.0,
                             calibration_progress=calibration_progress, fallback=person,
                             session_check=auto and whose is not None, anonymous_check=True)
        presence = run.settings.get("anonymous_points")
        res.anonymous_points = presence
        if presence and presence["absent"]:      # labelled by the model without them
            model = model.named_only()
        if auto:
            res.calibration = run.settings["calibration"]
            if person is not None:
                res.calibration = res.calibration | training_person_note(res.calibration)
            elif whose is not None:     # another capture of the person: their calibration, checked for moved markers
                res.calibration = res.calibration | {"person": f"the model's training takes' person ({whose})"}
        if job.out:
            cap = from_records(run.records, model.labels, clip.n_frames, CaptureFormat.of(clip, a))
            res.out = str(cap.write(job.out))
        dup = clip.meta.get("unlabelled_duplicates") or {}
        anon_note = AnonymousPresence.from_dict(presence).note() if presence else ""
        notes = [n for n in (mi.note, clip.meta.get("up_axis_note", ""), clip.meta.get("fragments_note", ""),
                             anon_note) if n]
        res.fragments_joined = sum(max(0, min(f["last"] + 1, b) - max(f["first"], a))
                                   for f in clip.meta.get("unlabelled_fragments", ()))
        res.frame_range, res.named, res.note = (a, b), mi.named, "; ".join(notes)
        res.unlabelled_points, res.copies_left_out = mi.n_extra, (len(dup) if job.keep_unlabelled else 0)
        res.unlabelled_samples = int(run.settings.get("unlabelled_samples", 0))
        res.up_axis = f"{clip.meta.get('up_axis', 'Z')} ({clip.meta.get('up_axis_source', 'format')})"
        res.accumulator, res.causal, res.voted, res.rate = run.accumulator, run.causal, run.voted, clip.rate
        res.records = run.records if job.keep_records else []
        res.restarts = run.settings.get("restarts", [])
    except (ValueError, KeyError, OSError, CalibrationError) as e:
        res.error = str(e).strip("'\"")
    res.wall_s = time.perf_counter() - t0
    return res


def trained_on(model, source: str) -> bool:
    """Whether the capture ``source`` is the one capture the model was trained on (its
    provenance's ``sources``). Then ``--calibrate auto`` leaves the model as it is: its body was
    measured on this person with the capture's own labels, and a self-calibration from the
    model's own labels of 5 s can only measure it worse (the Qualisys walk's gapped second half
    under the model of its first half: 99.66 % without, 98.93 % with the self-calibration it
    passed; ``results/captures.md``). A model of several captures may be of several people."""
    sources = model.provenance.get("sources") or []
    return len(sources) == 1 and _same_file(source, sources[0])


def of_training_person(model, source: str) -> str | None:
    """Why the capture ``source`` is of the person a model calibrated on its training takes
    was calibrated to -- one of those captures (:func:`keeps_training_calibration`), any capture
    when the user said the takes were the person to label (``dtm-train --calibrate``), or the
    same CMU subject (:func:`~dtm_labeler.motion.naming.one_subject`) -- else None (also for a
    model not calibrated on its training takes). ``--calibrate auto`` sets the calibration
    aside for anyone else (:func:`generic_view`): another person's segment lengths cost right
    labelings more than they save (:mod:`dtm_labeler.model.body`); on the person's other
    captures it checks the calibration for markers placed elsewhere and fits the broad weights
    to the take (:func:`~dtm_labeler.training.calibrate.session_calibrate`)."""
    cal = takes_calibration(model)
    if cal is None:
        return None
    kept = keeps_training_calibration(model, source)
    if kept is not None:
        return kept
    if cal.get("why") == "asked":
        return "the person dtm-train --calibrate was told the takes are"
    sources = [str(s) for s in model.provenance.get("sources") or []]
    return one_subject(sources + [source]) if sources else None


def keeps_training_calibration(model, source: str) -> str | None:
    """Why ``--calibrate auto`` labels the capture ``source`` with the calibration a model made
    on its training takes as it is: one of those captures (measured there on the operator's
    labels) -- else None. Another capture of the person (:func:`of_training_person`) is another
    session: the calibration is checked there
    (:func:`~dtm_labeler.training.calibrate.session_calibrate`); anyone else's capture sets it
    aside (:func:`training_person_note`)."""
    if takes_calibration(model) is None:
        return None
    sources = [str(s) for s in model.provenance.get("sources") or []]
    return "one of its training captures" if any(_same_file(source, s) for s in sources) else None


#: what labels a take when the self-calibration of a set-aside training calibration fails
TRAINING_PERSON_KEPT = "the model labels with its training takes' person's calibration"


def training_person_note(calibration: dict) -> dict:
    """What ``--calibrate auto`` did with a model calibrated to its training takes' person on a
    capture not known to be theirs (:func:`of_training_person`): the calibration was set aside
    and the generic body self-calibrated on the take (``set_aside``); when that self-calibration
    did not hold up, the take is labelled with the training person's calibration
    (``kept``), not the generic body. Another person's lengths are a better prior than none: the
    calibrated body also holds the broad motion component, so a motion the training never showed
    is not vetoed. Measured (``dtm-label``'s default, generic body -> the training person's
    calibration; models of one capture as ``dtm-train`` makes them; other captures with 30-45 %
    of the samples in gaps, where the self-calibration was refused in every case: the
    generic body needed a full search in over half of the window's frames): MoCap Toolbox dance ->
    walk 86.78 -> 95.46 %, with three ghosts and the dance model of a gapped first half 73.60 ->
    93.31 %, the gapped walk's model -> the gapped dance 24.25 -> 61.25 %; another lab's markers,
    HDM05 (first 30 %) -> CMU 85 jump + twist 7.95 -> 23.74 %, CMU 85 jump + twist -> HDM05 (first
    20 %) 73.31 -> 79.53 %. Where the self-calibration holds, it wins (the same pairs without gaps:
    HDM05 -> CMU 85 79.91 % against 50.66 % with HDM05's person, CMU 85 -> HDM05 100 % against
    69.85 %; lambada -> subject 5's pirouette 100 % against 41.61 %). Without a self-calibration
    neither body suits every take (subject 55's lambada -> subject 7's walk, no gaps: 64.29 % with
    the generic body, 51.08 % with subject 55's); none of the takes where it was refused labelled
    better with the generic body."""
    if calibration.get("recognised"):          # the self-calibration measured that person
        return {"person": calibration["recognised"] + " (their calibration, checked for this session)"}
    if calibration.get("applied"):
        return {"set_aside": "the model's calibration to its training takes' person, for a capture not known "
                             "to be theirs"}
    reason = calibration.get("reason", "").replace(KEPT_AS_IT_IS, TRAINING_PERSON_KEPT)
    return {"reason": reason, "kept": TRAINING_PERSON_KEPT}


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except (OSError, TypeError, ValueError):            # gone, moved, or not a path
        return False


def calibrated(model, clip, frames: str, labels: str, first: int = 0):
    """``(model calibrated on frames A:B of clip, the frames after B, calibration summary, B)``
    (:func:`~dtm_labeler.training.calibrate.calibrate_from_clip`); ``first``: the take's frame
    number of ``clip``'s first frame (for the summary)."""
    a, b = frame_range(frames, clip.n_frames)
    if b >= clip.n_frames:
        raise CalibrationError(f"--calibrate {frames} leaves no frames to label")
    cal, summary = calibrate_from_clip(model, clip.slice(a, b), labels)
    return cal, clip.slice(b, None), dict(summary, frames=[first + a, first + b]), b


class JobRunner:
    """Runs ``fn(job, shared)`` over jobs here, in local processes or on dask (module doc);
    a context manager, so the pool or cluster serves every :meth:`map` until it closes."""

    def __init__(self, workers: int = 1, dask: str | None = None):
        self.workers, self.dask = max(1, int(workers)), dask
        self._pool = self._client = self._cluster = None

    def __enter__(self) -> "JobRunner":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()
        self._pool = self._client = self._cluster = None

    @property
    def parallel(self) -> bool:
        return bool(self.dask) or self.workers > 1

    def _dask_client(self):
        if self._client is None:
            try:
                from distributed import Client, LocalCluster
            except ImportError as e:                         # pragma: no cover - pinned in requirements
                raise RuntimeError(f"--dask needs dask.distributed ({e})") from None
            if self.dask == "local":
                self._cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                             dashboard_address=None, silence_logs=40)
                self._client = Client(self._cluster)
            else:
                self._client = Client(self.dask, timeout="30s")
        return self._client

    def map(self, fn: Callable, jobs: Sequence, shared: Any = None, progress: Progress | None = None) -> list:
        """``[fn(job, shared) for job in jobs]``, in job order; ``progress(done, total, result)``
        after each job."""
        jobs = list(jobs)
        out: list = [None] * len(jobs)
        done = 0

        def finished(i: int, r) -> None:
            nonlocal done
            out[i] = r
            done += 1
            if progress is not None:
                progress(done, len(jobs), r)

        if self.dask:
            from distributed import as_completed as dask_completed
            client = self._dask_client()
            ref = client.scatter(shared, broadcast=True) if shared is not None else None
            futs = client.map(fn, jobs, [ref] * len(jobs), pure=False)
            index = {f.key: i for i, f in enumerate(futs)}
            for f in dask_completed(futs):
                finished(index[f.key], f.result())
        elif self.workers <= 1 or len(jobs) <= 1:
            for i, job in enumerate(jobs):
                finished(i, fn(job, shared))
        else:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(max_workers=self.workers)
            futs = {self._pool.submit(fn, job, shared): i for i, job in enumerate(jobs)}
            for f in as_completed(futs):
                finished(futs[f], f.result())
        return out


def run_jobs(fn: Callable, jobs: Sequence, shared: Any = None, workers: int = 1, dask: str | None = None,
             progress: Progress | None = None) -> list:
    """One :meth:`JobRunner.map` with a runner opened and closed for it."""
    with JobRunner(workers, dask) as runner:
        return runner.map(fn, jobs, shared, progress)


def call_task(task: tuple, shared: Any = None):
    """``fn(**kwargs)`` for a ``(fn, kwargs)`` task (a job function for :class:`JobRunner`)."""
    fn, kwargs = task
    return fn(**kwargs)


def default_workers() -> int:
    """Local processes for ``--jobs 0`` (auto): the CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:                                   # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)
