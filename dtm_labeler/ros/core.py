"""The labeler's ROS wiring, shared by the plain node and the managed (lifecycle) node.

Threads -- none of them waits for another's slow work:

* executor (``rclpy.spin``, single-threaded): parameter callbacks validate the whole
  configuration (a model file by its headers only, ~1 ms: :mod:`.model_check`) and hand changes
  on; the ``~/reset``, ``~/reload`` and ``~/calibrate`` services; the ``/diagnostics`` timer
  (steady clock); it creates the input subscription but does not take its messages.
* loader (:class:`~.loader.EngineLoader`): reads model files and widens models by ``noise_mm``;
  requests coalesce (the last wins) and superseded ones are dropped.
* worker (:class:`~.worker.LabelWorker`): reads the input itself (:mod:`.inbox`: the executor and
  the worker taking turns on the GIL per cloud cost more than the labelling) -- decodes each cloud
  (tens of us for PointCloud2), follows one source (:class:`~.stamps.SourceLock`), gives the frame
  its labeler time (:class:`~.stamps.StampGuard`) and puts it in the one-slot buffer
  (:meth:`_on_input`); the only thread touching the labeler: swaps prepared engines in and
  applies settings between frames, labels the newest frame, publishes
  (:class:`~.output.FrameHandler`).

Stamps come from the message headers (``use_sim_time`` works) and fall back to receive time
only after stamp faults; the wall clock is used for latency, rates and the diagnostics period.
"""
from __future__ import annotations

import threading
import time
from typing import Any, Dict, List, Optional

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.parameter import Parameter

from ..labeling.bank_labeler import bank_settings_from_params
from ..labeling.recovery import keep_spare_worker
from ..model.dtm import TriangulatedModel
from ..training.calibrate import stream_calibration_target
from . import params as P
from .calibration import CalibrationWindow
from .diagnostics import DiagnosticsBuilder, NodeState, NodeStats
from .engine import NodeSettings, Source
from .inbox import Inbox, NotExecuted, arrival_age_s, history_depth
from .inputs import InputUnavailable, decode, message_class
from .loader import EngineLoader, LoadResult
from .messages import output_header
from .model_check import check_model_file
from .output import FrameHandler, Outputs, reset_kind
from .pointcloud import PointCloudError, looks_like_millimetres
from .stamps import SourceLock, StampGuard
from .worker import OBSERVED_SKIPS, Frame, LabelWorker

__all__ = ["LabelerCore", "declare_parameters", "stamp_seconds"]


def stamp_seconds(header) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def node_settings(values: Dict[str, Any]) -> NodeSettings:
    """The labeler's and the bank's settings of a parameter set (ValueError when bad)."""
    return NodeSettings(P.settings_from_params(values), bank_settings_from_params(values))


def _param(name: str, value: Any) -> Parameter:
    if P.SPECS[name].kind == "string_array":
        return Parameter(name, Parameter.Type.STRING_ARRAY, list(value))
    return Parameter(name, value=value)


def declare_parameters(node) -> Dict[str, Any]:
    """Declare every parameter of :mod:`.params`; a start-up value of the wrong type or out of
    range is logged and replaced by the default (the node still starts). Returns the values."""
    log = node.get_logger()
    values: Dict[str, Any] = {}
    for spec in P.PARAMS:
        default = Parameter.Type.STRING_ARRAY if spec.kind == "string_array" else spec.default
        try:
            p = node.declare_parameter(spec.name, default, P.descriptor(spec))
        except Exception as e:   # InvalidParameterTypeException / ...ValueException
            log.error(f"parameter {spec.name}: bad start-up value ({e}); using the default "
                      f"{P.format_value(spec.default)}")
            p = node.declare_parameter(spec.name, default, P.descriptor(spec), ignore_override=True)
        if spec.kind == "string_array" and p.value is None:
            node.set_parameters([_param(spec.name, [])])   # an empty list has no type in rclpy
            p = node.get_parameter(spec.name)
        values[spec.name] = p.value
    for name in list(values):               # choices and cross-field checks, one by one
        try:
            P.validate({name: values[name]})
        except ValueError as e:
            log.error(f"{e}; using the default {P.format_value(P.DEFAULTS[name])}")
            values[name] = P.DEFAULTS[name]
            node.set_parameters([_param(name, P.DEFAULTS[name])])
    try:
        P.settings_from_params(values)
    except ValueError as e:
        log.error(f"parameters rejected ({e}); using the defaults of the labeler settings")
        for name in P.LABELER_KEYS:
            values[name] = P.DEFAULTS[name]
            node.set_parameters([_param(name, P.DEFAULTS[name])])
    return P.validate(values)


class LabelerCore:
    """See the module doc. ``node``: an rclpy Node or LifecycleNode (``lifecycle`` = publishers
    are lifecycle publishers, active only while the node is)."""

    def __init__(self, node, *, start_worker: bool = True, lifecycle: bool = False):
        self.node, self.log, self.lifecycle = node, node.get_logger(), lifecycle
        self.lock = threading.Lock()
        self.stats = NodeStats()
        self.values = declare_parameters(node)
        self.settings = node_settings(self.values)
        # a recovery worker process started now is up (imports done) when the first model arrives
        keep_spare_worker(self.values["recovery"] in ("auto", "background"))
        self.guard = StampGuard(self.values["max_gap_s"], self.values["stamp_source"])
        self.sources = SourceLock()
        self.model: Dict[str, Any] = dict(status="no model", path="", error="", labels=(), actions=(), active="",
                                          calibration="none")
        self.handler = FrameHandler(node, self.stats, self.lock, lambda: self.values, lambda: self.worker.stopping)
        self.handler.resize(self.values["latency_window"])
        self.handler.on_calibration = self._calibration_collected
        self.inbox = Inbox(node.context)
        self._input_lock = threading.Lock()    # input state: the worker reads, the executor (re)configures
        self.worker = LabelWorker(self.handler, self._on_worker_event, self.settings, inbox=self.inbox,
                                  receive=self._on_messages)
        self.loader = EngineLoader(self.worker.install)
        self.diag = DiagnosticsBuilder()
        self.sub = None
        self.input_error = ""
        self.active = False
        self.outputs: Optional[Outputs] = None
        self._diag_pub = self._timer = None
        self._services: List[Any] = []
        self._staged = None
        self._t_input: Optional[float] = None
        self._stamp_lost = 0
        self._mm_warned = False
        self._n_frames = 0
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        node.add_on_set_parameters_callback(self._on_set)
        node.add_post_set_parameters_callback(self._post_set)
        if start_worker:
            self.worker.start()

    # ------------------------------------------------------------------ model
    def source(self, values: Optional[Dict[str, Any]] = None) -> Source:
        v = values or self.values
        return Source(v["bank_path"] if v["use_bank"] else v["model_path"], bool(v["use_bank"]),
                      tuple(v["expected_labels"]))

    def load_model(self, why: str = "start-up") -> bool:
        """Check the configured model file now and have the loader load it; False (logged, and
        shown in /diagnostics) when there is none or it is refused."""
        src = self.source()
        if src.empty:
            msg = "use_bank is true but bank_path is empty" if src.bank else "model_path is empty"
            self._set_model(status="no model", error=msg)
            self.log.warning(f"{msg}; nothing is labelled until it is set")
            return False
        try:
            check_model_file(src.path, src.expected_labels, bank=src.bank)
        except ValueError as e:
            with self.lock:
                self.stats.reloads_failed += 1
            self._set_model(status="no model", error=f"{why} model rejected: {e}")
            self.log.error(f"{why} model rejected: {e}; running without a model, set model_path to a good "
                           "model file to start labelling")
            return False
        if self.model["status"] == "no model":
            self._set_model(status="loading", path=src.path, error="")
        self.loader.request(src, self.settings.labeler.noise_mm, self.settings.bank, reload=True, why=why)
        return True

    def _set_model(self, **kw) -> None:
        with self.lock:
            self.model.update(kw)

    def _on_worker_event(self, kind: str, detail: Any) -> None:
        """Worker thread: what it did between frames."""
        if kind == "loaded":
            self._on_loaded(detail)
        elif kind == "load_failed":
            self._on_load_failed(detail)
        elif kind == "reset":
            self._note_reset(detail)
            self.handler.clear()
        elif kind == "settings":
            with self.lock:
                self.stats.settings_applied += 1
        elif kind == "stale":                # replaced frames not carried (a reset was pending)
            with self.lock:
                self.stats.skipped["stale"] += int(detail)
        else:
            self.log.error(f"worker: {detail}")

    def _on_loaded(self, detail) -> None:
        result, change = detail
        replaced = change == "replaced"
        if change in ("swapped", "replaced", "new"):
            with self.lock:
                self.stats.models_prepared += 1
        p = result.prepared
        engine = self.worker.engine
        if p is None:
            self._set_model(status="no model", path="", labels=(), actions=(), active="",
                            error="use_bank is true but bank_path is empty" if result.request.source.bank
                            else "model_path is empty")
            self.log.info("model unloaded (model_path is empty)")
            return
        self._set_model(status="loaded", path=p.source.path, error="", labels=p.labels,
                        actions=engine.actions if engine else (), active=engine.active_model if engine else "")
        if result.request.calibration is not None:
            self._calibration_applied(p.base.provenance.get("calibration", {}))
            return
        if result.request.reload:
            self._set_model(calibration="none")
        if result.request.reload or change == "new":
            self._open_auto_window(p)
        self.handler.clear()
        if replaced:
            self._note_reset(f"model {'reload' if result.request.reload else 'rebuilt'} ({result.request.why})")
        if result.request.reload:
            with self.lock:
                self.stats.reloads_ok += 1
            self.log.info(f"model {'reloaded' if replaced else 'loaded'}: {p.source.path} ({len(p.labels)} labels, "
                          f"{result.seconds * 1e3:.0f} ms off the labeling thread)")

    def _calibration_applied(self, c: dict) -> None:
        auto = "kept_share" in c
        if c.get("recognised"):         # the training takes' person: their calibration, checked
            moved = c.get("moved") or []
            text = (f"calibrated (auto) on {c.get('recognised_frames', 0)} frames: recognised {c['recognised']}; their "
                    f"calibration, {len(moved)} segment(s) placed elsewhere this session")
        else:
            text = (f"calibrated{' (auto)' if auto else ''} on {c.get('frames', 0)} frames: {c.get('segments', 0)} of "
                    f"{c.get('segments_total', 0)} segments, scale {c.get('scale', 1.0):.3f}"
                    + (f", {100 * c['kept_share']:.0f} % of the confirmed labels kept" if auto else ""))
        self._set_model(calibration=text)
        self.log.info(f"subject calibration applied ({text}); tracks kept")

    def _on_load_failed(self, result: LoadResult) -> None:
        running = self.worker.engine
        if result.request.calibration is not None:
            self._set_model(calibration=f"failed: {result.error}")
            self.log.warning(f"subject calibration failed, the model is unchanged: {result.error}")
            return
        with self.lock:
            self.stats.reloads_failed += 1
        self._set_model(status="reload failed" if running else "no model", error=result.error,
                        path=running.prepared.source.path if running else self.model["path"])
        self.log.error(f"model rejected, keeping {running.prepared.source.path if running else 'no model'}: "
                       f"{result.error}")

    def _note_reset(self, reason: str) -> None:
        with self.lock:
            self.stats.resets[reset_kind(reason)] += 1
            self.stats.last_reset = reason
        self.log.info(f"window reset: {reason}", throttle_duration_sec=1.0)

    # ------------------------------------------------------------------ parameters (executor)
    def _on_set(self, params: List[Parameter]) -> SetParametersResult:
        """Validate the WHOLE resulting configuration; stage it for the post-set callback."""
        self._staged = None
        new = dict(self.values)
        for p in params:
            if p.name in P.SPECS:
                new[p.name] = p.value
        try:
            values = P.validate(new)
            settings = node_settings(values)
            reload = self._check_source(params, values)
            if values["input_type"] != self.values["input_type"]:
                message_class(values["input_type"])
        except (ValueError, OSError, InputUnavailable) as e:
            return SetParametersResult(successful=False, reason=str(e))
        self._staged = (values, settings, reload)
        return SetParametersResult(successful=True)

    def _check_source(self, params: List[Parameter], values: Dict[str, Any]) -> bool:
        """True when the set asks for a (re)load; raises ValueError when the file is refused."""
        names = {p.name for p in params}
        src = self.source(values)
        running = self.model["path"] if self.model["status"] in ("loaded", "reload failed") else ""
        if names & {"use_bank", "bank_path" if values["use_bank"] else "model_path"}:
            if src.empty:
                if src.bank:
                    raise ValueError("use_bank is true but bank_path is empty")
                return True
            try:
                check_model_file(src.path, src.expected_labels, bank=src.bank)
            except ValueError as e:
                reason = f"{'bank_path' if src.bank else 'model_path'} rejected, keeping {running or 'no model'}: {e}"
                with self.lock:
                    self.stats.reloads_failed += 1
                self._set_model(error=reason, status="reload failed" if running else "no model")
                self.log.error(reason)
                raise ValueError(reason) from None
            return True
        if values["expected_labels"] != self.values["expected_labels"] and running:
            P.check_labels(self.model["labels"], values["expected_labels"], where=f"running model {running}")
        return False

    def _post_set(self, params: List[Parameter]) -> None:
        staged, self._staged = self._staged, None
        if staged is None:
            return
        try:
            self._commit(params, *staged)
        except Exception as e:  # pragma: no cover - validated already; never kill the service
            self.log.error(f"applying parameters failed: {type(e).__name__}: {e}")

    def _commit(self, params: List[Parameter], values, settings, reload: bool) -> None:
        old, old_settings = self.values, self.settings
        self.values, self.settings = values, settings
        changed = [p.name for p in params if p.name in P.SPECS]
        rebuild = (settings.labeler.noise_mm != old_settings.labeler.noise_mm
                   or (values["use_bank"] and settings.bank != old_settings.bank))
        if reload or rebuild:
            src = self.source()
            if reload and not src.empty and self.model["status"] == "no model":
                self._set_model(status="loading", path=src.path, error="")
            self.loader.request(src, settings.labeler.noise_mm, settings.bank, reload=reload,
                                why="model_path set" if reload else "noise_mm / bank settings set")
        if settings != old_settings:
            self.worker.settings(settings)
        if any(old[k] != values[k] for k in P.INPUT_KEYS) and (self.sub is not None or self.input_error):
            self.open_input()           # (not on an inactive lifecycle node: activate opens it)
        if old["diagnostics_period_s"] != values["diagnostics_period_s"] and self._timer is not None:
            self._make_timer()
        if old["latency_window"] != values["latency_window"]:
            self.handler.resize(values["latency_window"])
        if values["auto_calibrate"] != old["auto_calibrate"]:
            window = self.handler.calibration
            if not values["auto_calibrate"] and window is not None and window.keep_clouds:
                self.handler.calibration = None              # an auto window still collecting: closed
                self._set_model(calibration="none")
            elif values["auto_calibrate"] and window is None and self.model["calibration"] == "none":
                self._open_auto_window()
        if (old["max_gap_s"], old["stamp_source"]) != (values["max_gap_s"], values["stamp_source"]):
            with self._input_lock:
                self.guard.configure(values["max_gap_s"], values["stamp_source"])
        if changed:
            self.log.info("parameters set: " + ", ".join(f"{n}={P.format_value(values[n])}" for n in changed))

    # ------------------------------------------------------------------ I/O
    def open_outputs(self) -> None:
        """Publishers (lifecycle ones on a managed node), services and the diagnostics timer."""
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import PointCloud2
        from std_srvs.srv import Trigger
        from visualization_msgs.msg import MarkerArray

        from dtm_labeler_msgs.msg import LabeledMarkerArray
        make = self.node.create_lifecycle_publisher if self.lifecycle else self.node.create_publisher
        qos = P.qos_profile(self.values["output_qos"], self.values["output_depth"])
        out = Outputs(make(LabeledMarkerArray, "markers/labeled", qos), make(PointCloud2, "markers/labeled_cloud", qos),
                      make(MarkerArray, "markers/visualization", qos))
        try:
            from mocap4r2_msgs.msg import Markers
            out.mocap4r2 = make(Markers, "markers/labeled_mocap4r2", qos)
        except ImportError:
            self.log.info("mocap4r2_msgs not installed: markers/labeled_mocap4r2 is not published")
        self.outputs = self.handler.outputs = out
        self._diag_pub = self.node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._services = [self.node.create_service(Trigger, "~/reset", self._srv_reset),
                          self.node.create_service(Trigger, "~/reload", self._srv_reload),
                          self.node.create_service(Trigger, "~/calibrate", self._srv_calibrate)]
        self._make_timer()

    def close_outputs(self) -> None:
        destroy_pub = self.node.destroy_lifecycle_publisher if self.lifecycle else self.node.destroy_publisher
        if self.outputs is not None:
            for pub in (self.outputs.labeled, self.outputs.cloud, self.outputs.viz, self.outputs.mocap4r2):
                if pub is not None:
                    destroy_pub(pub)
        for srv in self._services:
            self.node.destroy_service(srv)
        if self._timer is not None:
            self.node.destroy_timer(self._timer)
        if self._diag_pub is not None:
            self.node.destroy_publisher(self._diag_pub)
        self.outputs = self.handler.outputs = None
        self._services, self._timer, self._diag_pub = [], None, None

    def open_input(self) -> None:
        """(Re)create the subscription of ``input_type`` (logged and shown in /diagnostics
        when its message package is missing)."""
        recreated = self.sub is not None
        self.close_input()
        try:
            cls = message_class(self.values["input_type"])
        except InputUnavailable as e:
            self.input_error = f"input_type {self.values['input_type']}: {e}"
            self.log.error(self.input_error)
            return
        self.input_error = ""
        depth = history_depth(self.values["input_depth"], OBSERVED_SKIPS)
        qos = P.qos_profile(self.values["input_qos"], depth)
        # the worker takes its messages (ros/inbox.py); the callback is never called by the executor
        self.sub = self.node.create_subscription(cls, "markers/unlabeled", self._on_input, qos,
                                                 callback_group=NotExecuted())
        with self._input_lock:
            self.sources.reset()
        self._t_input = time.monotonic()     # silence counts from listening, not from before it
        self.active = True
        self.inbox.attach(self.sub, depth)
        if recreated:
            self.log.info(f"input subscription recreated ({self.values['input_qos']}, depth "
                          f"{self.values['input_depth']}) for {self.values['input_type']}")

    def close_input(self) -> None:
        if self.sub is not None:
            self.inbox.attach(None)
            self.node.destroy_subscription(self.sub)     # (after the worker's wait on it, if any)
            self.sub = None
        self.active = False
        for _ in range(self.worker.discard()):
            self._skip("inactive")

    def unload(self, reason: str) -> None:
        """Free the model (lifecycle cleanup / shutdown)."""
        self.worker.drop_engine()
        self.loader.forget()
        self._set_model(status="no model", path="", error=reason, labels=(), actions=(), active="")

    def _make_timer(self) -> None:
        if self._timer is not None:
            self.node.destroy_timer(self._timer)
        self._timer = self.node.create_timer(self.values["diagnostics_period_s"], self.publish_diagnostics,
                                             clock=self._steady)

    # ------------------------------------------------------------------ input (executor)
    def _skip(self, reason: str, detail: str = "") -> None:
        with self.lock:
            self.stats.skipped[reason] += 1
            if detail:
                self.stats.last_bad_input = detail

    def _on_messages(self, sub, messages: List[tuple], full: bool) -> None:
        """Worker thread: the messages the inbox took from ``sub``, oldest first. ``full``: the
        subscription's history was full, so sequence gaps before the first message are frames
        pushed out while the worker was busy -- stale (too old to carry), not lost before the node."""
        if sub is not self.sub:          # the subscription was closed or replaced meanwhile
            for _ in messages:
                self._skip("inactive")
            return
        for k, (msg, info) in enumerate(messages):
            lost = self.sources.lost
            self._on_input(msg, info)
            if k == 0 and full and self.sources.lost > lost:
                with self._input_lock:
                    n, self.sources.lost = self.sources.lost - lost, lost
                with self.lock:
                    self.stats.skipped["stale"] += n
                    self.stats.lost_before_node = self.sources.lost

    def _on_input(self, msg, info: Optional[dict] = None) -> None:
        """One input message (``info``: rclpy's message info, with its DDS reception time);
        called by the worker (:meth:`_on_messages`), or directly by tests."""
        t0 = time.perf_counter()
        age = arrival_age_s(info)
        now = time.monotonic() - age
        with self.lock:
            self.stats.received += 1
        self._t_input = now
        seq = info.get("publication_sequence_number") if info else None
        with self._input_lock:
            take, event = self.sources.accept(seq, now, self._publishers)
        if not take:
            return self._skip("other_source")
        try:
            dec = decode(self.values["input_type"], msg, self.values["mocap4r2_ids"])
        except Exception as e:        # PointCloudError, or anything odd in a malformed message
            reason = str(e) if isinstance(e, PointCloudError) else f"{type(e).__name__}: {e}"
            self._skip("bad_cloud", reason)
            self.log.warning(f"bad cloud skipped: {reason}", throttle_duration_sec=2.0)
            return
        with self._input_lock:
            frame = self._frame(msg.header, dec, t0, t0 - age, now, seq)
        if event == "switched":
            frame.resets.append("source switched (the followed publisher went silent)")
            self._note_reset(frame.resets[-1])
        if self.worker.submit(frame) is not None:
            self._skip("stale")

    def _publishers(self) -> int:
        return self.sub.get_publisher_count() if self.sub is not None else 0

    def _incompatible_qos(self) -> str:
        """Publishers on the input topic whose QoS cannot reach the subscription ('' if none)."""
        if self.sub is None:
            return ""
        try:
            infos = self.node.get_publishers_info_by_topic(self.sub.topic_name)
        except Exception:            # pragma: no cover - graph queries fail only at shutdown
            return ""
        return P.incompatible_publishers(self.sub.qos_profile, [i.qos_profile for i in infos])

    def _frame(self, header, dec, t0: float, t_recv: float, now: float, seq) -> Frame:
        h_stamp = stamp_seconds(header)
        v = self.values
        ids, partial = dec.ids, False
        if ids is not None and ids.size and ids.min() < 0:
            ids, partial = None, True        # the tracker takes ids for all points or none
        out_header = output_header(header, v["frame_id"], v["override_frame_id"])
        frame = Frame(dec.xyz, ids, out_header, h_stamp, h_stamp, t_recv, 0.0, dec.frame_number)
        xyz = dec.xyz
        if xyz.size and not np.isfinite(xyz).all():
            xyz = xyz[np.isfinite(xyz).all(1)]
        if xyz.size:                         # the labeler sees only frames with points
            verdict = self.guard.check(h_stamp, now)
            frame.stamp = verdict.stamp
            self._stamp_lost += verdict.lost
            if verdict.reset:
                frame.resets.append(verdict.reset)
                self._note_reset(verdict.reset)
            self._n_frames += 1
            mm = self._n_frames % 8 == 1 and looks_like_millimetres(xyz)      # a sample is enough
            with self.lock:
                s = self.stats
                if verdict.fault:
                    s.stamp_faults[verdict.fault] += 1
                s.lost_before_node = self.sources.lost if seq is not None else self._stamp_lost
                s.points_at_origin += dec.origin_points
                s.frames_partial_ids += partial
                s.frames_millimetres += mm
            if mm and not self._mm_warned:
                self._mm_warned = True
                self.log.warning("input coordinates look like millimetres (the cloud spans more than 50 units); "
                                 "the node expects metres: convert at the driver")
        frame.decode_ms = (time.perf_counter() - t0) * 1e3
        return frame

    # ------------------------------------------------------------------ services (executor)
    def _srv_reset(self, request, response):
        self.worker.request_reset("reset service (~/reset)")
        response.success = True
        response.message = ("window, tracks and votes reset" if self.worker.engine is not None
                            else "no model loaded: nothing to reset")
        return response

    def _srv_reload(self, request, response):
        ok = self.load_model("reload")
        response.success = ok
        response.message = (f"reloading {self.source().describe()}; /diagnostics says when it runs" if ok
                            else f"not reloaded: {self.model['error']}")
        return response

    def _srv_calibrate(self, request, response):
        """Open a calibration window of ``calibration_s`` (ros/calibration.py); the calibrated
        model replaces the running one when it closes (/diagnostics ``calibration``)."""
        engine = self.worker.engine
        why_not = ("no model loaded" if engine is None else
                   "a bank cannot be calibrated live (calibrate its models with dtm-calibrate)"
                   if self.values["use_bank"] else
                   "the model has no body terms (format 1 or trained without them): retrain with dtm-train"
                   if getattr(engine.prepared.base, "body", None) is None else "")
        if why_not:
            response.success, response.message = False, f"not calibrating: {why_not}"
            return response
        window = CalibrationWindow(self.values["calibration_s"], engine.labels)
        self.handler.calibration = window
        self._set_model(calibration=window.status)
        response.success = True
        response.message = (f"collecting {window.seconds:g} s of confirmed labels (any motion); /diagnostics "
                            "'calibration' says when the calibrated model runs")
        return response

    def _calibration_collected(self, frames, clouds=None) -> None:
        """Worker thread: the window is full (a clip of its confirmed labels; with ``clouds``,
        the auto calibration's window); the loader calibrates and the worker swaps."""
        auto = clouds is not None
        self._set_model(calibration=f"calibrating{' (auto)' if auto else ''} on {frames.n_frames} frames")
        self.loader.request(self.source(), self.settings.labeler.noise_mm, self.settings.bank,
                            why="auto calibration" if auto else "calibration", calibration=frames, clouds=clouds)

    def _open_auto_window(self, prepared=None) -> None:
        """``auto_calibrate``: a window that keeps its clouds, opened on a freshly loaded generic
        body or one ``dtm-train`` calibrated to its training takes' person (the stream's person
        is not known: :func:`~dtm_labeler.training.calibrate.stream_calibration_target`); not a
        bank, not a model calibrated to a person by the user."""
        p = prepared if prepared is not None else (self.worker.engine.prepared if self.worker.engine else None)
        if not self.values["auto_calibrate"] or p is None or not isinstance(p.base, TriangulatedModel) \
                or stream_calibration_target(p.base) is None:        # (a bank's base is a ModelBank)
            return
        window = CalibrationWindow(self.values["calibration_s"], p.labels, keep_clouds=True)
        self.handler.calibration = window
        self._set_model(calibration=f"auto: {window.status}")

    # ------------------------------------------------------------------ diagnostics
    def state(self) -> NodeState:
        now = time.monotonic()
        h = self.handler
        with self.lock:
            lat, labt, ovh, stall = (np.asarray(d) for d in (h.latency, h.labeling, h.overhead, h.stall))
            m = dict(self.model)
        v = self.values
        engine = self.worker.engine
        return NodeState(
            name=self.node.get_name(), hardware_id=self.node.get_fully_qualified_name(), model_status=m["status"],
            model_path=m["path"], model_error=m["error"], labels=tuple(m["labels"]),
            calibration=((("auto: " if h.calibration.keep_clouds else "") + h.calibration.status)
                         if h.calibration is not None else m["calibration"]),
            active_model=(engine.active_model if engine else "") or v["model_name"],
            actions=engine.actions if engine else (), active=self.active, input_error=self.input_error,
            recovery_error=engine.recovery_failed if engine else "",
            anonymous_absent=engine.anonymous_absent if engine else "",
            time_base=self.guard.time_base, publishers=self._publishers(),
            incompatible_qos=self._incompatible_qos(),
            since_input_s=now - self._t_input if self._t_input is not None else float("inf"),
            failing_s=now - h.t_failing if h.t_failing is not None else 0.0,
            latency_ms=lat, labeling_ms=labt, overhead_ms=ovh, stall_ms=stall,
            config={k: v[k] for k in ("method", "mode", "window", "max_points", "input_type", "noise_mm",
                                      "expected_labels", "use_bank")}
            | {"input_qos": f"{v['input_qos']} depth {v['input_depth']}"})

    def diagnostics(self) -> list:
        """The DiagnosticStatus entries (labeling, model) as published on /diagnostics."""
        with self.lock:
            snap = self.stats.snapshot()
        return self.diag.build(snap, self.state(), time.monotonic())

    def publish_diagnostics(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        try:
            arr = DiagnosticArray()
            arr.header.stamp = self.node.get_clock().now().to_msg()
            arr.status = self.diagnostics()
            self._diag_pub.publish(arr)
        except Exception as e:  # pragma: no cover - diagnostics must never take the node down
            self.log.error(f"diagnostics failed: {type(e).__name__}: {e}", throttle_duration_sec=10.0)

    # ------------------------------------------------------------------ shutdown
    def shutdown(self, timeout: float = 0.3) -> bool:
        """Stop the worker and the loader (and the labeler's recovery worker, when the worker
        thread has let go of it); True when the worker thread ended within ``timeout``."""
        done = self.worker.stop(timeout)
        self.loader.stop(0.05)
        if done:
            self.inbox.close()
        if done and self.worker.engine is not None:
            self.worker.engine.close()
        return done


class CoreOwner:
    """What the plain and the managed node expose of their :class:`LabelerCore` (mixed in
    before the rclpy node class, so ``destroy_node`` stops the core first)."""

    core: LabelerCore

    def diagnostics(self):
        """The DiagnosticStatus entries (labeling, model) as published on /diagnostics."""
        return self.core.diagnostics()

    def stop(self, timeout: float = 0.3) -> bool:
        """Stop the worker and loader threads; True when they ended within ``timeout``."""
        return self.core.shutdown(timeout)

    def destroy_node(self):
        self.stop()
        return super().destroy_node()
