"""The dtm_labeler ROS 2 node: unlabeled marker clouds in, labelled markers out, in real time.

Run::

    dtm-labeler-node --ros-args -p model_path:=/path/model.npz [--params-file params/labeler.yaml]
    ros2 run dtm_labeler labeler_node --ros-args ...          (full ROS install)
    python -m dtm_labeler.ros.node --ros-args ...

Topics (relative, remappable): in ``markers/unlabeled`` (sensor_msgs/PointCloud2: float32
x, y, z, optional uint32 ``id``; any layout :func:`read_points_xyz` decodes); out
``markers/labeled`` (dtm_labeler_msgs/LabeledMarkerArray), ``markers/labeled_cloud``
(PointCloud2 x, y, z, int32 label, float32 confidence), ``markers/visualization``
(visualization_msgs/MarkerArray) and ``/diagnostics`` (diagnostic_msgs/DiagnosticArray).
Output headers are the input's header (same stamp and frame_id). Parameters:
:mod:`dtm_labeler.ros.params` (all changeable at runtime except output_qos/output_depth).

Real-time path
--------------
* The subscription callback (executor thread) only decodes the cloud (tens of microseconds)
  and puts it in a ONE-SLOT buffer; a cloud still waiting there is overwritten and counted as
  a skipped ``stale`` frame. There is no other queue in the node (DDS history is keep-last
  ``input_depth``), so latency cannot build up: when labeling is slower than the input, the
  node labels the newest cloud and drops the ones in between.
* A dedicated worker thread owns the :class:`StreamLabeler` and is the only thread that touches
  it: it takes the newest cloud, labels it and publishes. Keeping the (possibly long) search
  off the executor thread means parameter services, the subscription and diagnostics keep
  being served while a frame is labelled; the executor is a plain single-threaded one
  (``rclpy.spin``), so callbacks never run concurrently with each other.
* Parameter changes are validated in the on-set callback (executor thread) against the WHOLE
  resulting configuration -- including loading a new model file and checking its labels -- and
  handed to the worker through the same condition variable as the frames; the worker applies
  them between two frames. A rejected set changes nothing and the old model keeps running.
* Input gaps longer than ``max_gap_s`` are judged on the stamps the node RECEIVES, not on the
  frames it labels: clouds dropped as stale while a slow search runs are not a gap (otherwise
  a cold search slower than max_gap_s would reset the window, forcing another cold search --
  a reset spiral). Time going backwards (bag loop) and repeated stamps reset via the labeler.
* Stamps come from the message headers only (``use_sim_time`` works); the wall clock is used
  for latency measurement, rates and the diagnostics period (steady clock).
"""
from __future__ import annotations

import collections
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any, Dict, List, Optional

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from dtm_labeler_msgs.msg import LabeledMarker, LabeledMarkerArray

from ..labeling.bank_labeler import BankLabeler
from ..labeling.stream import StreamLabeler
from ..model.bank import ModelBank, load_bank
from ..model.io import load_model
from . import params as P
from .pointcloud import PointCloudError, make_labeled_cloud, read_points_xyz
from .visualization import MarkerArrayBuilder, label_colors

__all__ = ["LabelerNode", "main", "NO_TRACK"]

#: LabeledMarker.track_id of points that have no track (non-finite points).
NO_TRACK = 0xFFFFFFFF
DIAG_LABELING = "labeling"
DIAG_MODEL = "model"


@dataclass
class _Frame:
    xyz: np.ndarray
    ids: Optional[np.ndarray]
    header: Any
    stamp: float
    t_recv: float          # perf_counter() at callback entry
    decode_ms: float
    gap: float = 0.0       # largest input gap > max_gap_s since the last frame taken by the worker


@dataclass
class _ModelChange:
    model: Any             # TriangulatedModel or None (unload)
    path: str


@dataclass
class _Stats:
    received: int = 0
    labelled: int = 0
    published: int = 0
    skipped: Dict[str, int] = field(default_factory=lambda: collections.Counter())
    bad_cloud_reason: str = ""
    frames_empty: int = 0
    frames_nonfinite: int = 0
    points_nonfinite: int = 0
    frames_over_max_points: int = 0
    points_ignored: int = 0
    frames_duplicates: int = 0
    resets: Dict[str, int] = field(default_factory=lambda: collections.Counter())
    last_reset: str = ""
    full_searches: int = 0
    frames_overrun: int = 0
    last_log_likelihood: float = float("nan")
    reloads_ok: int = 0
    reloads_failed: int = 0
    labeler_error: str = ""


def _reset_kind(reason: str) -> str:
    if reason.startswith("time went backwards"):
        return "time_backwards"
    if reason.startswith("gap"):
        return "gap"
    if reason.startswith("repeated"):
        return "repeated_stamp"
    return "other"


def _engine_settings(settings):
    """The settings the node gives the StreamLabeler: gaps are detected by the node on the
    received stamps (see ``_on_cloud``), so the labeler's own gap check (on the stamps it
    processes) is switched off; time going backwards and repeated stamps stay with it."""
    return replace(settings, max_gap_s=_NO_GAP)


_NO_GAP = 1e6   # the largest max_gap_s the table allows: gaps are judged by the node


def _stamp_seconds(header) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


class LabelerNode(Node):
    """See the module docstring. ``kwargs`` go to :class:`rclpy.node.Node` (e.g. ``context``,
    ``parameter_overrides``, ``namespace``); ``start_worker=False`` is for tests."""

    def __init__(self, node_name: str = P.NODE_NAME, *, start_worker: bool = True, **kwargs):
        super().__init__(node_name, **kwargs)
        self._cond = threading.Condition()
        self._stats_lock = threading.Lock()
        self._slot: Optional[_Frame] = None
        self._pending: List[Any] = []          # settings / _ModelChange, applied by the worker
        self._stop = False
        self._stats = _Stats()
        self._staged = None
        self._frame_number = 0
        self._prev_stamp: Optional[float] = None
        self._last_rx_stamp: Optional[float] = None
        self._label_track: Dict[int, int] = {}
        self._last_viz_stamp: Optional[float] = None
        self._viz_clear = True
        self._colors = np.zeros((0, 4))
        self._edges: list = []
        self._viz_builder: Optional[MarkerArrayBuilder] = None

        self._values = self._declare_all()
        n = self._values["latency_window"]
        self._latency: collections.deque = collections.deque(maxlen=n)    # receive -> published, ms
        self._labeling: collections.deque = collections.deque(maxlen=n)   # StreamLabeler.process, ms
        self._overhead: collections.deque = collections.deque(maxlen=n)   # decode + build + publish, ms
        settings = P.settings_from_params(self._values)

        # model at start-up: a bad one leaves the node running without a model
        self._model_path = ""
        self._model_status = "no model"
        self._model_error = ""
        self._labeler: Optional[StreamLabeler] = None     # worker-owned
        self._model = None                                 # the model of the accepted configuration
        path = self._values["bank_path"] if self._values["use_bank"] else self._values["model_path"]
        if path or self._values["use_bank"]:
            try:
                model, path = self._load_engine(self._values)
                self._set_model_now(model, path, settings)
                self._model = model
                self.get_logger().info(f"model {path}: {model.n_labels} labels ({', '.join(model.labels)})")
            except ValueError as e:
                self._model_status = "no model"
                self._model_error = f"start-up model rejected: {e}"
                self._stats.reloads_failed += 1
                self.get_logger().error(f"{self._model_error}; running without a model, set model_path "
                                        "to a good model file to start labelling")
        else:
            self._model_error = "model_path is empty"
            self.get_logger().warning("no model_path given; nothing is labelled until model_path is set")
        self._settings = settings

        out_qos = P.qos_profile(self._values["output_qos"], self._values["output_depth"])
        self._pub_labeled = self.create_publisher(LabeledMarkerArray, "markers/labeled", out_qos)
        self._pub_cloud = self.create_publisher(PointCloud2, "markers/labeled_cloud", out_qos)
        self._pub_viz = self.create_publisher(MarkerArray, "markers/visualization", out_qos)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._sub = None
        self._make_subscription()
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._diag_timer = None
        self._make_diag_timer()
        self._last_diag = (time.monotonic(), 0, 0)

        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._post_set_parameters)
        self._worker = threading.Thread(target=self._run, name="dtm_labeler_worker", daemon=True)
        if start_worker:
            self._worker.start()

    # ------------------------------------------------------------------ parameters
    def _declare_all(self) -> Dict[str, Any]:
        """Declare every parameter; a start-up override of the wrong type or out of range is
        logged and replaced by the default (the node still starts)."""
        values: Dict[str, Any] = {}
        for spec in P.PARAMS:
            desc = P.descriptor(spec)
            default = Parameter.Type.STRING_ARRAY if spec.kind == "string_array" else spec.default
            try:
                p = self.declare_parameter(spec.name, default, desc)
            except Exception as e:   # InvalidParameterTypeException / ...ValueException
                self.get_logger().error(f"parameter {spec.name}: bad start-up value ({e}); "
                                        f"using the default {P.format_value(spec.default)}")
                p = self.declare_parameter(spec.name, default, P.descriptor(spec), ignore_override=True)
            if spec.kind == "string_array" and p.value is None:
                # declared by type only (an empty list has no type in rclpy): give it a value,
                # so get_parameters works for it
                self.set_parameters([self._param(spec.name, [])])
                p = self.get_parameter(spec.name)
            values[spec.name] = p.value
        # whole-configuration check (choices, cross-field); bad entries fall back to defaults
        for name in list(values):
            try:
                P.validate({name: values[name]})
            except ValueError as e:
                self.get_logger().error(f"{e}; using the default {P.format_value(P.DEFAULTS[name])}")
                values[name] = P.DEFAULTS[name]
                self.set_parameters([self._param(name, P.DEFAULTS[name])])
        try:
            out = P.validate(values)
            P.settings_from_params(out)
        except ValueError as e:
            self.get_logger().error(f"parameters rejected ({e}); using the defaults of the labeler settings")
            for name in P.LABELER_KEYS:
                values[name] = P.DEFAULTS[name]
                self.set_parameters([self._param(name, P.DEFAULTS[name])])
            out = P.validate(values)
        return out

    @staticmethod
    def _param(name: str, value: Any) -> Parameter:
        if P.SPECS[name].kind == "string_array":
            return Parameter(name, Parameter.Type.STRING_ARRAY, list(value))
        return Parameter(name, value=value)

    @staticmethod
    def _load_checked(path: str, expected: List[str]):
        model = load_model(path)          # ModelFileError (a ValueError) with the reason
        P.check_labels(model.labels, expected, where=f"model {path}")
        return model

    @staticmethod
    def _load_engine(values: Dict[str, Any]):
        """(model or bank, path) of a configuration: the bank at ``bank_path`` when ``use_bank``,
        else the model at ``model_path`` ((None, '') when that is empty)."""
        if values["use_bank"]:
            path = values["bank_path"]
            if not path:
                raise ValueError("use_bank is true but bank_path is empty")
            bank = load_bank(path)        # BankFileError (a ValueError) with the reason
            P.check_labels(bank.labels, values["expected_labels"], where=f"bank {path}")
            return bank, path
        path = values["model_path"]
        return (LabelerNode._load_checked(path, values["expected_labels"]), path) if path else (None, "")

    def _on_set_parameters(self, params: List[Parameter]) -> SetParametersResult:
        """Validate the WHOLE resulting configuration; stage it for the post-set callback."""
        self._staged = None
        new = dict(self._values)
        for p in params:
            if p.name not in P.SPECS:
                continue                     # use_sim_time etc.
            new[p.name] = p.value
        try:
            values = P.validate(new)
            settings = P.settings_from_params(values)
        except ValueError as e:
            return SetParametersResult(successful=False, reason=str(e))
        change = None
        expected = values["expected_labels"]
        try:
            engine_keys = {"use_bank", "bank_path" if values["use_bank"] else "model_path"}
            if any(p.name in engine_keys for p in params):
                # an explicit set reloads (even the same path: a retrained file in place)
                change = _ModelChange(*self._load_engine(values))
            elif expected != self._values["expected_labels"] and self._model is not None:
                P.check_labels(self._model.labels, expected, where=f"running model {self._model_path}")
        except (ValueError, OSError) as e:
            reason = f"model_path rejected, keeping {self._model_path or 'no model'}: {e}"
            with self._stats_lock:
                self._stats.reloads_failed += 1
                self._model_error = reason
                if self._labeler is not None:
                    self._model_status = "reload failed"
            self.get_logger().error(reason)
            return SetParametersResult(successful=False, reason=reason)
        except Exception as e:  # never let a reload take the node down
            reason = f"model_path rejected ({type(e).__name__}: {e}); keeping {self._model_path or 'no model'}"
            with self._stats_lock:
                self._stats.reloads_failed += 1
                self._model_error = reason
            self.get_logger().error(reason)
            return SetParametersResult(successful=False, reason=reason)
        self._staged = (values, settings, change)
        return SetParametersResult(successful=True)

    def _post_set_parameters(self, params: List[Parameter]) -> None:
        staged, self._staged = self._staged, None
        if staged is None:
            return
        try:
            self._commit(params, *staged)
        except Exception as e:  # pragma: no cover - validated already; never kill the service
            self.get_logger().error(f"applying parameters failed: {type(e).__name__}: {e}")

    def _commit(self, params: List[Parameter], values, settings, change) -> None:
        old = self._values
        self._values = values
        with self._cond:
            if change is not None:
                self._model = change.model
                self._pending.append(change)
                # report the new model right away (the worker swaps it before the next frame)
                with self._stats_lock:
                    self._model_path = change.path
                    self._model_status = "loaded" if change.model is not None else "no model"
                    self._model_error = "" if change.model is not None else "model_path is empty"
                    self._stats.reloads_ok += 1
                self.get_logger().info(f"model reloaded: {change.path}" if change.model is not None
                                       else "model unloaded (model_path is empty)")
            if change is not None or not P.settings_equal(settings, self._settings):
                self._pending.append(settings)
                self._settings = settings
            self._cond.notify()
        if any(old[k] != values[k] for k in P.INPUT_QOS_KEYS):
            self._make_subscription()
        if old["diagnostics_period_s"] != values["diagnostics_period_s"]:
            self._make_diag_timer()
        if old["latency_window"] != values["latency_window"]:
            with self._stats_lock:
                n = values["latency_window"]
                self._latency = collections.deque(self._latency, maxlen=n)
                self._labeling = collections.deque(self._labeling, maxlen=n)
                self._overhead = collections.deque(self._overhead, maxlen=n)
        changed = [p.name for p in params if p.name in P.SPECS]
        if changed:
            self.get_logger().info("parameters set: " + ", ".join(
                f"{n}={P.format_value(values[n])}" for n in changed))

    def _make_subscription(self) -> None:
        qos = P.qos_profile(self._values["input_qos"], self._values["input_depth"])
        old = self._sub
        self._sub = self.create_subscription(PointCloud2, "markers/unlabeled", self._on_cloud, qos)
        if old is not None:
            self.destroy_subscription(old)
            self.get_logger().info(f"input subscription recreated ({self._values['input_qos']}, "
                                   f"depth {self._values['input_depth']})")

    def _make_diag_timer(self) -> None:
        if self._diag_timer is not None:
            self.destroy_timer(self._diag_timer)
        self._diag_timer = self.create_timer(self._values["diagnostics_period_s"], self._publish_diagnostics,
                                             clock=self._steady)

    # ------------------------------------------------------------------ input (executor thread)
    def _on_cloud(self, msg: PointCloud2) -> None:
        t0 = time.perf_counter()
        with self._stats_lock:
            self._stats.received += 1
        try:
            xyz, ids = read_points_xyz(msg)
        except Exception as e:        # PointCloudError, or anything odd in a malformed message
            reason = str(e) if isinstance(e, PointCloudError) else f"{type(e).__name__}: {e}"
            with self._stats_lock:
                self._stats.skipped["bad_cloud"] += 1
                self._stats.bad_cloud_reason = reason
            self.get_logger().warning(f"bad cloud skipped: {reason}", throttle_duration_sec=2.0)
            return
        stamp = _stamp_seconds(msg.header)
        # input gaps are judged on the RECEIVED stamps: frames dropped as stale while a slow
        # search runs must not look like a gap (that would reset the window and force another
        # slow cold search -- a reset spiral)
        # (only clouds with points count: the labeler never sees the others either)
        gap = 0.0
        if xyz.shape[0] and np.isfinite(xyz).all(1).any():
            if self._last_rx_stamp is not None and stamp - self._last_rx_stamp > self._values["max_gap_s"]:
                gap = stamp - self._last_rx_stamp
            self._last_rx_stamp = stamp
        frame = _Frame(xyz, ids, msg.header, stamp, t0, (time.perf_counter() - t0) * 1e3, gap)
        with self._cond:
            if self._slot is not None:
                frame.gap = max(frame.gap, self._slot.gap)
                with self._stats_lock:
                    self._stats.skipped["stale"] += 1
            self._slot = frame
            self._cond.notify()

    # ------------------------------------------------------------------ worker thread
    def _run(self) -> None:
        while True:
            with self._cond:
                while self._slot is None and not self._pending and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                frame, self._slot = self._slot, None
                pending, self._pending = self._pending, []
            for item in pending:
                try:
                    self._apply(item)
                except Exception as e:   # pragma: no cover - settings were validated
                    self.get_logger().error(f"could not apply {type(item).__name__}: {e}")
            if frame is not None:
                try:
                    self._label(frame)
                except Exception as e:
                    if self._stop:
                        return
                    with self._stats_lock:
                        self._stats.skipped["error"] += 1
                        self._stats.labeler_error = f"{type(e).__name__}: {e}"
                    self.get_logger().error(f"frame skipped, labeler error: {type(e).__name__}: {e}",
                                            throttle_duration_sec=2.0)
                    if self._labeler is not None:
                        self._labeler.reset()

    def _set_model_now(self, model, path: str, settings) -> None:
        if isinstance(model, ModelBank):       # use_bank: every action model at once
            self._labeler = BankLabeler(model, _engine_settings(settings))
            model = model[model.actions[0]]     # same labels in every model: colours, edges
        else:
            self._labeler = StreamLabeler(model, _engine_settings(settings)) if model is not None else None
        self._colors = label_colors(model.n_labels) if model is not None else np.zeros((0, 4))
        self._edges = sorted(model.structure.edges()) if model is not None else []
        self._label_track = {}
        self._viz_clear = True
        self._viz_builder = None
        with self._stats_lock:
            self._model_path = path
            self._model_status = "loaded" if model is not None else "no model"
            self._model_error = "" if model is not None else "model_path is empty"

    def _apply(self, item) -> None:
        if isinstance(item, _ModelChange):
            self._set_model_now(item.model, item.path, self._settings)
            with self._stats_lock:
                self._stats.resets["model_reload"] += 1
                self._stats.last_reset = "model reload"
        else:
            item = _engine_settings(item)
            if self._labeler is not None and not P.settings_equal(item, self._labeler.settings):
                self._labeler.update_settings(item)
                self._label_track = {}

    def _label(self, f: _Frame) -> None:
        lab = self._labeler
        if lab is None:
            with self._stats_lock:
                self._stats.skipped["no_model"] += 1
            self.get_logger().warning("no model loaded: frame not labelled (set model_path)",
                                      throttle_duration_sec=5.0)
            return
        values = self._values
        model = lab.model
        xyz = f.xyz
        n = xyz.shape[0]
        finite = np.isfinite(xyz).all(1)
        n_finite = int(finite.sum())
        t_lab0 = time.perf_counter()
        gap_reason = ""
        if f.gap > 0.0:
            lab.reset()
            gap_reason = f"gap of {f.gap:.2f} s"
        if n_finite == 0:
            # nothing to search: publish every point unlabelled (the labeler needs points)
            labels = np.full(n, -1, dtype=np.int64)
            conf = np.zeros(n)
            tracks = np.full(n, -1, dtype=np.int64)
            loglik, reset, ignored, full = float("nan"), gap_reason, 0, False
        else:
            res = lab.process(xyz, f.stamp, f.ids)
            labels, conf, tracks = res.labels, res.confidence, res.track_ids
            loglik, reset, ignored, full = res.log_likelihood, gap_reason or res.reset, res.n_ignored, res.full_search
        t_lab1 = time.perf_counter()
        dup = False
        if 1 < n_finite <= 4096:
            dup = np.unique(xyz[finite], axis=0).shape[0] < n_finite

        # -- LabeledMarkerArray
        names = list(model.labels)
        out = LabeledMarkerArray()
        out.header = f.header
        out.frame_number = self._frame_number
        out.label_names = names
        out.log_likelihood = float(loglik)
        out.active_model = getattr(lab, "active_action", "") or values["model_name"]
        markers = []
        pos = xyz.tolist()
        for p, l, c, t in zip(pos, labels.tolist(), np.asarray(conf, dtype=float).tolist(), tracks.tolist()):
            m = LabeledMarker()
            q = m.position
            q.x, q.y, q.z = p
            if l >= 0:
                m.label = names[l]
                m.label_index = l
                m.confidence = c
            m.track_id = NO_TRACK if t < 0 else t & 0xFFFFFFFF
            markers.append(m)
        present = set(int(x) for x in labels[labels >= 0])
        if reset:
            self._label_track = {}
        if values["publish_occluded"] and n_finite:
            seen_tracks = set(tracks.tolist())
            for l in range(len(names)):
                if l in present or l not in self._label_track:
                    continue
                tid = self._label_track[l]
                if tid in seen_tracks:
                    continue
                p = lab.tracker.position_of(tid, f.stamp)
                if not np.isfinite(p).all():
                    del self._label_track[l]
                    continue
                m = LabeledMarker()
                m.position.x, m.position.y, m.position.z = (float(v) for v in p)
                m.label, m.label_index = names[l], l
                m.track_id = tid & 0xFFFFFFFF
                m.occluded = True
                m.predicted = True
                markers.append(m)
        # remember which track carried each label last (for predictions while it is missing);
        # a track carries at most one label
        now_tracks = {}
        for i in np.flatnonzero(labels >= 0).tolist():
            if tracks[i] >= 0:
                now_tracks[int(tracks[i])] = int(labels[i])
        self._label_track = {l: t for l, t in self._label_track.items()
                             if l not in present and t not in now_tracks}
        self._label_track.update({l: t for t, l in now_tracks.items()})
        out.markers = markers
        out.n_unlabeled = int(n - np.count_nonzero(labels >= 0))
        out.latency_ms = float((time.perf_counter() - f.t_recv) * 1e3)
        if self._stop:                       # shutting down: the publishers may be gone
            return
        self._pub_labeled.publish(out)
        # the optional outputs are only built when someone listens (a cheap graph query)
        if values["publish_cloud"] and self._pub_cloud.get_subscription_count() > 0:
            self._pub_cloud.publish(make_labeled_cloud(xyz, labels, np.asarray(conf, dtype=np.float32),
                                                       header=f.header))
        if values["publish_visualization"] and self._pub_viz.get_subscription_count() > 0:
            period = values["visualization_period_s"]
            last = self._last_viz_stamp
            if (reset or self._viz_clear or last is None or f.stamp < last or f.stamp - last >= period):
                vb = self._viz_builder
                if vb is None or vb.scale != values["marker_scale"] or vb.names != names:
                    vb = self._viz_builder = MarkerArrayBuilder(names, self._edges, scale=values["marker_scale"],
                                                                colors=self._colors)
                self._pub_viz.publish(vb.build(f.header, xyz, labels, conf,
                                               delete_all=bool(reset) or self._viz_clear))
                self._last_viz_stamp = f.stamp
                self._viz_clear = False
        t_end = time.perf_counter()
        self._frame_number += 1
        # overrun: this frame took longer (receive -> published) than the stamp interval
        overrun = (self._prev_stamp is not None and 0.0 < f.stamp - self._prev_stamp < t_end - f.t_recv)
        self._prev_stamp = f.stamp

        with self._stats_lock:
            s = self._stats
            s.published += 1
            if n_finite:
                s.labelled += 1
            if n == 0:
                s.frames_empty += 1
            if n_finite < n:
                s.frames_nonfinite += 1
                s.points_nonfinite += n - n_finite
            if ignored:
                s.frames_over_max_points += 1
                s.points_ignored += ignored
            if dup:
                s.frames_duplicates += 1
            if full:
                s.full_searches += 1
            if overrun:
                s.frames_overrun += 1
            if reset:
                s.resets[_reset_kind(reset)] += 1
                s.last_reset = f"{reset} (stamp {f.stamp:.3f})"
            s.last_log_likelihood = float(loglik)
            self._latency.append((t_end - f.t_recv) * 1e3)
            self._labeling.append((t_lab1 - t_lab0) * 1e3)
            self._overhead.append(f.decode_ms + (t_end - t_lab1) * 1e3)
        if reset:
            self.get_logger().info(f"window reset: {reset} (stamp {f.stamp:.3f})", throttle_duration_sec=1.0)

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self) -> List[DiagnosticStatus]:
        """The two DiagnosticStatus entries (labeling, model) as published on /diagnostics."""
        now = time.monotonic()
        v = self._values
        with self._stats_lock:
            s = self._stats
            t_last, rec_last, pub_last = self._last_diag
            dt = max(now - t_last, 1e-6)
            in_rate = (s.received - rec_last) / dt
            out_rate = (s.published - pub_last) / dt
            self._last_diag = (now, s.received, s.published)
            lat = np.asarray(self._latency)
            labt = np.asarray(self._labeling)
            ovh = np.asarray(self._overhead)
            skipped = dict(s.skipped)
            resets = dict(s.resets)
            snap = {k: getattr(s, k) for k in (
                "received", "labelled", "published", "bad_cloud_reason", "frames_empty", "frames_nonfinite",
                "points_nonfinite", "frames_over_max_points", "points_ignored", "frames_duplicates",
                "last_reset", "full_searches", "frames_overrun", "last_log_likelihood", "reloads_ok", "reloads_failed",
                "labeler_error")}
            model_path, model_status, model_error = self._model_path, self._model_status, self._model_error

        def pct(a, q):
            return f"{np.percentile(a, q):.3f}" if a.size else "nan"

        lab = self._labeler
        accepted = self._model                   # the accepted model (the worker swaps it in before the next frame)
        if isinstance(accepted, ModelBank):
            accepted = accepted[accepted.actions[0]]
        labels = list(accepted.labels) if accepted is not None else []
        kv = [
            ("input_rate_hz", f"{in_rate:.2f}"), ("output_rate_hz", f"{out_rate:.2f}"),
            ("frames_received", snap["received"]), ("frames_labelled", snap["labelled"]),
            ("frames_published", snap["published"]),
            ("frames_skipped_stale", skipped.get("stale", 0)),
            ("frames_overrun", snap["frames_overrun"]),
            ("frames_skipped_bad_cloud", skipped.get("bad_cloud", 0)),
            ("frames_skipped_no_model", skipped.get("no_model", 0)),
            ("frames_skipped_error", skipped.get("error", 0)),
            ("last_bad_cloud", snap["bad_cloud_reason"]), ("last_error", snap["labeler_error"]),
            ("frames_empty", snap["frames_empty"]), ("frames_with_nonfinite", snap["frames_nonfinite"]),
            ("points_dropped_nonfinite", snap["points_nonfinite"]),
            ("frames_over_max_points", snap["frames_over_max_points"]),
            ("points_ignored_max_points", snap["points_ignored"]),
            ("frames_with_duplicates", snap["frames_duplicates"]),
            ("resets_time_backwards", resets.get("time_backwards", 0)), ("resets_gap", resets.get("gap", 0)),
            ("resets_repeated_stamp", resets.get("repeated_stamp", 0)),
            ("resets_model_reload", resets.get("model_reload", 0)), ("last_reset", snap["last_reset"]),
            ("latency_p50_ms", pct(lat, 50)), ("latency_p99_ms", pct(lat, 99)),
            ("latency_max_ms", f"{lat.max():.3f}" if lat.size else "nan"),
            ("labeling_p50_ms", pct(labt, 50)), ("labeling_p99_ms", pct(labt, 99)),
            ("overhead_p50_ms", pct(ovh, 50)), ("overhead_p99_ms", pct(ovh, 99)),
            ("latency_window_frames", lat.size), ("full_searches", snap["full_searches"]),
            ("last_log_likelihood", f"{snap['last_log_likelihood']:.3f}"),
            ("method", v["method"]), ("mode", v["mode"]), ("window", v["window"]),
            ("max_points", v["max_points"]), ("input_qos", f"{v['input_qos']} depth {v['input_depth']}"),
        ]
        st = DiagnosticStatus()
        st.name = f"{self.get_name()}: {DIAG_LABELING}"
        st.hardware_id = self.get_fully_qualified_name()
        if lab is None:
            st.level, st.message = DiagnosticStatus.ERROR, "no model loaded: nothing is labelled"
        elif snap["received"] == 0:
            st.level, st.message = DiagnosticStatus.OK, "waiting for markers/unlabeled"
        else:
            st.level = DiagnosticStatus.OK
            st.message = f"labelling at {out_rate:.1f} Hz (input {in_rate:.1f} Hz), latency p50 {pct(lat, 50)} ms"
            if skipped.get("bad_cloud", 0) or skipped.get("error", 0):
                st.level = DiagnosticStatus.WARN
                st.message += f"; skipped {skipped.get('bad_cloud', 0)} bad clouds, {skipped.get('error', 0)} errors"
        st.values = [KeyValue(key=k, value=str(x)) for k, x in kv]

        sm = DiagnosticStatus()
        sm.name = f"{self.get_name()}: {DIAG_MODEL}"
        sm.hardware_id = self.get_fully_qualified_name()
        sm.level = {"loaded": DiagnosticStatus.OK, "reload failed": DiagnosticStatus.WARN}.get(
            model_status, DiagnosticStatus.ERROR)
        sm.message = {"loaded": f"model loaded: {model_path}",
                      "reload failed": f"reload failed, still running {model_path}"}.get(
            model_status, f"no model: {model_error}")
        sm.values = [KeyValue(key=k, value=str(x)) for k, x in [
            ("model_status", model_status), ("model_path", model_path), ("model_error", model_error),
            ("labels", ",".join(labels)), ("n_labels", len(labels)),
            ("expected_labels", ",".join(v["expected_labels"])),
            ("active_model", getattr(lab, "active_action", "") or v["model_name"]),
            ("use_bank", v["use_bank"]), ("bank_actions", ",".join(getattr(lab, "actions", []))),
            ("reloads_ok", snap["reloads_ok"]), ("reloads_failed", snap["reloads_failed"])]]
        return [st, sm]

    def _publish_diagnostics(self) -> None:
        try:
            arr = DiagnosticArray()
            now = self.get_clock().now()
            arr.header.stamp = now.to_msg()
            arr.status = self.diagnostics()
            self._pub_diag.publish(arr)
        except Exception as e:  # pragma: no cover - diagnostics must never take the node down
            self.get_logger().error(f"diagnostics failed: {type(e).__name__}: {e}", throttle_duration_sec=10.0)

    # ------------------------------------------------------------------ shutdown
    def stop_worker(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._worker.is_alive():
            self._worker.join(timeout)

    def destroy_node(self):
        self.stop_worker()
        return super().destroy_node()


def main(args: Optional[List[str]] = None) -> int:
    """Entry point of ``dtm-labeler-node`` / ``ros2 run dtm_labeler labeler_node``."""
    rclpy.init(args=args)
    node = None
    try:
        node = LabelerNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
