"""The worker-thread half of the node: label one frame, publish what it gives, count it.

:class:`FrameHandler` is what :class:`~.worker.LabelWorker` calls per frame. It owns the state
outputs carry from frame to frame (the frame counter, :class:`~.messages.OccludedLabels`,
:class:`~.messages.VizThrottle`, the RViz builder), runs the engine, builds the messages with
:mod:`.messages` and publishes them on the publishers of :class:`Outputs` -- the optional ones
only while someone subscribes (a cheap graph query). Counts go to the node's
:class:`~.diagnostics.NodeStats` under its lock. Nothing is published once the node is stopping
(its publishers may be gone).
"""
from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, Optional

import numpy as np

from ..training.calibrate import confirmation_of
from .diagnostics import NodeStats
from .engine import NodeLabeler
from .messages import LabelledFrame, OccludedLabels, VizThrottle, labeled_marker_array_cdr, mocap4r2_markers
from .pointcloud import make_labeled_cloud
from .visualization import MarkerArrayBuilder, label_colors
from .calibration import CalibrationWindow
from .worker import Frame

__all__ = ["Outputs", "FrameHandler", "reset_kind"]


@dataclass
class Outputs:
    """The node's publishers (``mocap4r2`` None when mocap4r2_msgs is not installed)."""

    labeled: Any
    cloud: Any
    viz: Any
    mocap4r2: Any = None


def reset_kind(reason: str) -> str:
    """The diagnostics key (resets_<kind>) of a reset reason."""
    for prefix, kind in (("time went backwards", "time_backwards"), ("gap", "gap"), ("repeated", "repeated_stamp"),
                         ("model", "model_reload"), ("reset service", "service"), ("source", "source_switch"),
                         ("labeler error", "error")):
        if reason.startswith(prefix):
            return kind
    return "error"


def _has_duplicates(xyz: np.ndarray) -> bool:
    """Whether two rows of ``xyz`` are identical (a driver that sends a marker twice); the
    full row comparison only when two x coordinates are equal (almost never)."""
    x = np.sort(xyz[:, 0])
    if not (x[1:] == x[:-1]).any():
        return False
    return np.unique(xyz, axis=0).shape[0] < xyz.shape[0]


class FrameHandler:
    def __init__(self, node: Any, stats: NodeStats, lock: threading.Lock, values: Callable[[], Dict[str, Any]],
                 stopping: Callable[[], bool]):
        self.node = node
        self.log = node.get_logger()
        self.stats, self.lock = stats, lock
        self.values = values
        self.stopping = stopping
        self.outputs: Optional[Outputs] = None
        self.frame_number = 0
        self._prev_stamp: Optional[float] = None
        self.occluded = OccludedLabels()
        self.viz = VizThrottle()
        self._viz_builder: Optional[MarkerArrayBuilder] = None
        self.t_published = time.monotonic()
        self.t_failing: Optional[float] = None          # first labeler error since the last published frame
        self.latency = collections.deque(maxlen=500)    # receive -> published, ms
        self.labeling = collections.deque(maxlen=500)   # NodeLabeler.process, ms
        self.overhead = collections.deque(maxlen=500)   # decode + build + publish, ms
        self.stall = collections.deque(maxlen=500)      # frame ready -> its labelling starts, ms
        self._t_done = 0.0                              # perf_counter() when the last frame was done
        self.calibration: Optional[CalibrationWindow] = None     # open ~/calibrate window (worker thread)
        # (clip of confirmed labels, the window's clouds or None): the window is full
        self.on_calibration: Callable[[Any, Optional[list]], None] = lambda positions, clouds: None

    def clear(self) -> None:
        """Forget per-stream state (a model change, a reset)."""
        self.occluded.clear()
        self.viz.clear()
        self._viz_builder = None

    def resize(self, n: int) -> None:
        with self.lock:
            self.latency = collections.deque(self.latency, maxlen=n)
            self.labeling = collections.deque(self.labeling, maxlen=n)
            self.overhead = collections.deque(self.overhead, maxlen=n)
            self.stall = collections.deque(self.stall, maxlen=n)

    # -- the frame ------------------------------------------------------------------------------
    def __call__(self, f: Frame, engine: Optional[NodeLabeler], carried: bool = False) -> None:
        """Label ``f`` and publish it; ``carried``: the worker does not search it (it was
        replaced in the slot by a newer frame) -- its points get the labels their tracks carry
        (:meth:`NodeLabeler.observe`), published in order before the newer frame, unless it is
        older than ``carry_max_ms`` by now (then only the tracker follows it; counted stale)."""
        if engine is None:
            with self.lock:
                self.stats.skipped["no_model"] += 1
            self.log.warning("no model loaded: frame not labelled (set model_path)", throttle_duration_sec=5.0)
            return
        try:
            self._handle(f, engine, carried)
        except Exception as e:
            if self.stopping():
                return
            reason = f"{type(e).__name__}: {e}"
            with self.lock:
                self.stats.skipped["error"] += 1
                self.stats.last_error = reason
                self.t_failing = self.t_failing or time.monotonic()
            self.log.error(f"frame skipped, labeler error: {reason}", throttle_duration_sec=2.0)
            engine.reset()
            self.clear()

    def _handle(self, f: Frame, engine: NodeLabeler, carried: bool = False) -> None:
        if carried and (time.perf_counter() - f.t_recv) * 1e3 > self.values()["carry_max_ms"]:
            engine.observe(f.xyz, f.stamp, f.ids)      # too late to publish: the tracks still follow it
            with self.lock:
                self.stats.skipped["stale"] += 1
            return
        if f.resets:                         # counted and logged where they were decided (executor)
            engine.reset()
            self.clear()
        finite = np.isfinite(f.xyz).all(1)
        n, n_finite = f.xyz.shape[0], int(finite.sum())
        t0 = time.perf_counter()
        # the node's own stall: from "a frame is there and the last one is done" to labelling it
        # (engine swaps, settings, resets in between -- and any thread holding the worker up)
        stall_ms = (t0 - max(f.t_recv, self._t_done)) * 1e3
        if n_finite and carried:
            res = engine.observe(f.xyz, f.stamp, f.ids)
            labels, conf, tracks = res.labels, res.confidence, res.track_ids
            res = None                       # no search result: nothing below reads one
        elif n_finite:
            res = engine.process(f.xyz, f.stamp, f.ids)
            labels, conf, tracks = res.labels, np.asarray(res.confidence, dtype=float), res.track_ids
        else:   # nothing to search: every point published unlabelled (the labeler needs points)
            res = None
            labels, conf, tracks = np.full(n, -1, np.int64), np.zeros(n), np.full(n, -1, np.int64)
        t1 = time.perf_counter()
        v = self.values()
        occluded = self.occluded.step(labels, tracks, lambda t: engine.predicted_position(t, f.stamp),
                                      enabled=v["publish_occluded"] and n_finite > 0)
        frame = LabelledFrame(f.header, self.frame_number, f.xyz, labels, conf, tracks, engine.labels,
                              res.log_likelihood if res is not None else float("nan"),
                              engine.active_model or v["model_name"], 0.0, occluded)
        frame.latency_ms = (time.perf_counter() - f.t_recv) * 1e3
        if self.stopping():
            return
        self._publish(frame, f, engine, v)
        if self.calibration is not None and res is not None:
            self._calibrate(f.stamp, labels, confirmation_of(res), f.xyz)
        self._count(f, res, n, n_finite, t0, t1, carried)
        if not carried:
            with self.lock:
                self.stall.append(stall_ms)

    def _calibrate(self, stamp: float, labels: np.ndarray, conf: np.ndarray, xyz: np.ndarray) -> None:
        window = self.calibration
        positions = window.add(stamp, labels, conf, xyz) if window is not None else None
        if positions is not None:
            self.calibration = None
            self.on_calibration(positions, window.clouds if window.keep_clouds else None)

    def _publish(self, frame: LabelledFrame, f: Frame, engine: NodeLabeler, v: Dict[str, Any]) -> None:
        out = self.outputs
        out.labeled.publish(labeled_marker_array_cdr(frame))     # serialised here: a fraction of the cost
        if v["publish_cloud"] and out.cloud.get_subscription_count() > 0:
            out.cloud.publish(make_labeled_cloud(frame.xyz, frame.labels, frame.confidence.astype(np.float32),
                                                 header=frame.header))
        if v["publish_mocap4r2"] and out.mocap4r2 is not None and out.mocap4r2.get_subscription_count() > 0:
            if f.frame_number is not None:
                frame.frame_number = f.frame_number
            out.mocap4r2.publish(mocap4r2_markers(frame))
        if v["publish_visualization"] and out.viz.get_subscription_count() > 0:
            due, delete_all = self.viz.due(f.header_stamp, v["visualization_period_s"])
            if due:
                out.viz.publish(self._viz(engine, v).build(frame.header, frame.xyz, frame.labels, frame.confidence,
                                                           delete_all=delete_all))

    def _viz(self, engine: NodeLabeler, v: Dict[str, Any]) -> MarkerArrayBuilder:
        b = self._viz_builder
        if (b is None or b.scale != v["marker_scale"] or b.names != list(engine.labels)
                or b.ns != v["viz_namespace"] or b.lifetime_s != v["viz_marker_lifetime_s"]):
            b = self._viz_builder = MarkerArrayBuilder(
                engine.labels, engine.edges, scale=v["marker_scale"], ns=v["viz_namespace"],
                colors=label_colors(len(engine.labels)), lifetime_s=v["viz_marker_lifetime_s"])
        return b

    def _count(self, f: Frame, res, n: int, n_finite: int, t0: float, t1: float, carried: bool = False) -> None:
        t_end = time.perf_counter()
        self.frame_number += 1
        # overrun: this frame took longer (receive -> published) than the stamp interval
        overrun = self._prev_stamp is not None and 0.0 < f.stamp - self._prev_stamp < t_end - f.t_recv
        self._prev_stamp = f.stamp
        dup = 1 < n_finite <= 4096 and _has_duplicates(f.xyz[np.isfinite(f.xyz).all(1)])
        with self.lock:
            s = self.stats
            s.published += 1
            s.labelled += bool(n_finite)
            s.frames_carried += bool(n_finite) and carried
            s.frames_empty += n == 0
            s.frames_nonfinite += n_finite < n
            s.points_nonfinite += n - n_finite
            s.frames_duplicates += bool(dup)
            s.frames_overrun += bool(overrun)
            if res is not None:
                s.frames_over_max_points += bool(res.n_ignored)
                s.points_ignored += res.n_ignored
                s.full_searches += bool(res.full_search)
                s.frames_doubtful += bool(res.doubtful)
                s.recoveries_joined += bool(res.recovered)
                s.last_log_likelihood = float(res.log_likelihood)
            self.latency.append((t_end - f.t_recv) * 1e3)
            if not carried:                  # labeling time is the searched frames'
                self.labeling.append((t1 - t0) * 1e3)
            self.overhead.append(f.decode_ms + (t_end - t1) * 1e3)
            self.t_published, self.t_failing = time.monotonic(), None
        self._t_done = time.perf_counter()
