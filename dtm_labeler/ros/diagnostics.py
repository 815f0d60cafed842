"""The node's counters and its ``/diagnostics`` status, built without a node.

:class:`NodeStats` holds what the node counts (every received frame ends either published or
skipped with a reason: ``frames_received == frames_published + sum(frames_skipped_*)``);
:class:`DiagnosticsBuilder` turns two snapshots of it (this period and the last) plus the node's
state into the two ``diagnostic_msgs/DiagnosticStatus`` entries ``<node>: labeling`` and
``<node>: model``. Levels mean something (:func:`assess`):

* ERROR -- no model loaded; no input subscription (the input type's message package is missing);
  or labeling has failed (labeler errors, nothing published) for > 1 s.
* WARN -- more than 10 % of the received frames dropped (labelled rate < 90 % of the input
  rate); resets or full searches running high (more than 2 resets, or full searches on more
  than 20 % of the labelled frames, in the period);
  stamp faults (zero, repeated, backwards, jumping) or interleaved sources in the period; no
  input for > 1 s while a publisher is matched; bad input or labeler errors in the period;
  coordinates that look like millimetres; a failed model reload; a stream that does not show the
  model's anonymous points (:mod:`dtm_labeler.labeling.anonymous_presence`: their markers taken off).
* OK otherwise (the message says the rates and the latency).
"""
from __future__ import annotations

import collections
import copy
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

__all__ = ["NodeStats", "NodeState", "DiagnosticsBuilder", "assess", "OK", "WARN", "ERROR",
           "DROP_REASONS", "STAMP_FAULTS"]

OK, WARN, ERROR = 0, 1, 2
#: why a received frame was not published (diagnostics key frames_skipped_<reason>)
DROP_REASONS = ("stale", "bad_cloud", "no_model", "error", "other_source", "inactive")
#: stamp faults the node recognises (diagnostics key stamp_faults_<kind>)
STAMP_FAULTS = ("zero", "repeated", "backwards", "jump")
RESET_KINDS = ("time_backwards", "gap", "repeated_stamp", "model_reload", "service", "source_switch", "error")
_MODEL_CONFIG = ("expected_labels", "use_bank")     # shown in the model status
_FAILING_S = 1.0              # labeling failing this long -> ERROR
_SILENT_S = 1.0               # no input this long while a publisher is matched -> WARN
_RATE_FLOOR = 0.9             # labelled rate below this fraction of the input rate -> WARN


def _counter() -> collections.Counter:
    return collections.Counter()


@dataclass
class NodeStats:
    """Running counts (only ever increase) and the last event of each kind."""

    received: int = 0
    published: int = 0
    labelled: int = 0                 # published with at least one finite point (searched or carried)
    frames_carried: int = 0           # of those, not searched (the worker was busy): the labels tracks carry
    skipped: collections.Counter = field(default_factory=_counter)       # DROP_REASONS
    resets: collections.Counter = field(default_factory=_counter)        # RESET_KINDS
    stamp_faults: collections.Counter = field(default_factory=_counter)  # STAMP_FAULTS
    lost_before_node: int = 0         # frames DDS lost before the callback (sequence numbers / stamps)
    frames_empty: int = 0
    frames_nonfinite: int = 0
    points_nonfinite: int = 0
    points_at_origin: int = 0
    frames_partial_ids: int = 0
    frames_over_max_points: int = 0
    points_ignored: int = 0
    frames_duplicates: int = 0
    frames_millimetres: int = 0
    full_searches: int = 0
    frames_doubtful: int = 0          # published before a (background) search vouched for them
    recoveries_joined: int = 0        # background searches whose labeling joined a frame
    frames_overrun: int = 0
    reloads_ok: int = 0
    reloads_failed: int = 0
    models_prepared: int = 0          # engines swapped in (loads, and re-widenings for a new noise)
    settings_applied: int = 0
    last_bad_input: str = ""
    last_error: str = ""
    last_reset: str = ""
    last_log_likelihood: float = float("nan")

    def snapshot(self) -> "NodeStats":
        return copy.deepcopy(self)


@dataclass
class NodeState:
    """What the diagnostics say besides the counts (read by the node when it publishes them)."""

    name: str
    hardware_id: str
    model_status: str = "no model"    # loaded | loading | reload failed | no model
    model_path: str = ""
    model_error: str = ""
    calibration: str = "none"         # ~/calibrate: none | collecting ... | calibrated ... | failed: ...
    labels: Tuple[str, ...] = ()
    active_model: str = ""
    actions: Tuple[str, ...] = ()
    active: bool = True               # lifecycle: labelling only while active
    input_error: str = ""             # why there is no input subscription (a missing message package)
    recovery_error: str = ""          # why the background recovery worker is not used (searches run inline)
    anonymous_absent: str = ""        # the stream does not show the model's anonymous points (why)
    time_base: str = "header"         # header stamps, or receive time after stamp faults
    publishers: int = 0               # publishers matched on the input topic
    incompatible_qos: str = ""        # publishers whose QoS cannot reach the input (params.incompatible_publishers)
    since_input_s: float = float("inf")
    since_published_s: float = float("inf")
    failing_s: float = 0.0            # labeler errors without a published frame for this long
    latency_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    labeling_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    overhead_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stall_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))   # frame ready -> labelling starts
    config: Dict[str, Any] = field(default_factory=dict)      # parameter values shown as keys


def _delta(cur: NodeStats, prev: NodeStats, name: str) -> int:
    return getattr(cur, name) - getattr(prev, name)


def _cdelta(cur: NodeStats, prev: NodeStats, name: str) -> int:
    return sum(getattr(cur, name).values()) - sum(getattr(prev, name).values())


def assess(cur: NodeStats, prev: NodeStats, dt: float, st: NodeState) -> Tuple[int, str]:
    """Level and message of the labeling status for the period ``prev`` -> ``cur`` (``dt`` s)."""
    if st.input_error:
        return ERROR, st.input_error
    if st.model_status not in ("loaded",):
        what = "loading the model" if st.model_status == "loading" else "no model loaded"
        return ERROR, f"{what}: nothing is labelled" + (f" ({st.model_error})" if st.model_error else "")
    if not st.active:
        return OK, "inactive (lifecycle): not labelling"
    if st.failing_s > _FAILING_S:
        return ERROR, f"labeling failing for {st.failing_s:.1f} s: {cur.last_error}"
    rx, pub = _delta(cur, prev, "received"), _delta(cur, prev, "published")
    in_rate, out_rate = rx / dt, pub / dt
    warn: List[str] = []
    # received = published + skipped + in flight: counting the skipped, not received - published,
    # keeps a frame in flight across the period's edge from reading as a rate shortfall
    dropped = sum(cur.skipped[k] - prev.skipped[k] for k in DROP_REASONS)
    if rx >= 5 and dropped > (1.0 - _RATE_FLOOR) * rx:
        warn.append(f"labelling {out_rate:.1f} Hz of {in_rate:.1f} Hz input ({dropped} frames dropped)")
    if _cdelta(cur, prev, "stamp_faults"):
        faults = {k: cur.stamp_faults[k] - prev.stamp_faults[k] for k in STAMP_FAULTS}
        warn.append("stamp faults " + ", ".join(f"{k} {v}" for k, v in faults.items() if v)
                    + (" (labelling on receive time)" if st.time_base == "receive" else ""))
    other = cur.skipped["other_source"] - prev.skipped["other_source"]
    if other:
        warn.append(f"{other} frames of another publisher interleaved (following one)")
    resets = _cdelta(cur, prev, "resets") - (cur.resets["service"] - prev.resets["service"])
    if resets > 2:
        warn.append(f"{resets} resets")
    full, lab = _delta(cur, prev, "full_searches"), _delta(cur, prev, "labelled")
    if lab >= 5 and full > 0.2 * lab:
        warn.append(f"full searches on {full} of {lab} frames")
    doubt = _delta(cur, prev, "frames_doubtful")
    if lab >= 5 and doubt > 0.2 * lab:
        warn.append(f"{doubt} of {lab} frames published unconfirmed (searches running in the background)")
    if st.recovery_error:
        warn.append(st.recovery_error + " (searches run in the labelling thread)")
    if st.anonymous_absent:
        warn.append(st.anonymous_absent)
    if st.publishers > 0 and st.since_input_s > _SILENT_S:
        warn.append(f"no input for {st.since_input_s:.1f} s from {st.publishers} matched publisher(s)")
    if st.incompatible_qos:
        warn.append(st.incompatible_qos)
    bad, err = (cur.skipped[k] - prev.skipped[k] for k in ("bad_cloud", "error"))
    if bad or err:
        warn.append(f"skipped {bad} bad inputs, {err} labeler errors")
    if _delta(cur, prev, "frames_millimetres"):
        warn.append("coordinates look like millimetres (the node expects metres)")
    if rx == 0 and not warn:
        return OK, "waiting for input" if cur.received == 0 else "no input"
    lat = st.latency_ms
    text = (f"labelling at {out_rate:.1f} Hz (input {in_rate:.1f} Hz), latency p50 "
            f"{np.percentile(lat, 50) if lat.size else float('nan'):.3f} ms")
    return (WARN, "; ".join(warn) + f" | {text}") if warn else (OK, text)


def _pct(a: np.ndarray, q: float) -> str:
    return f"{np.percentile(a, q):.3f}" if a.size else "nan"


def _labeling_values(cur: NodeStats, in_rate: float, out_rate: float, st: NodeState) -> List[Tuple[str, Any]]:
    lat, labt, ovh = st.latency_ms, st.labeling_ms, st.overhead_ms
    kv: List[Tuple[str, Any]] = [
        ("input_rate_hz", f"{in_rate:.2f}"), ("output_rate_hz", f"{out_rate:.2f}"),
        ("frames_received", cur.received), ("frames_labelled", cur.labelled), ("frames_published", cur.published),
        ("frames_carried", cur.frames_carried)]
    kv += [(f"frames_skipped_{r}", cur.skipped[r]) for r in DROP_REASONS]
    kv += [("frames_lost_before_node", cur.lost_before_node), ("frames_overrun", cur.frames_overrun),
           ("last_bad_cloud", cur.last_bad_input), ("last_error", cur.last_error),
           ("frames_empty", cur.frames_empty), ("frames_with_nonfinite", cur.frames_nonfinite),
           ("points_dropped_nonfinite", cur.points_nonfinite), ("points_at_origin", cur.points_at_origin),
           ("frames_partial_ids", cur.frames_partial_ids), ("frames_over_max_points", cur.frames_over_max_points),
           ("points_ignored_max_points", cur.points_ignored), ("frames_with_duplicates", cur.frames_duplicates),
           ("frames_millimetres", cur.frames_millimetres)]
    kv += [(f"stamp_faults_{k}", cur.stamp_faults[k]) for k in STAMP_FAULTS]
    kv += [("time_base", st.time_base)]
    kv += [(f"resets_{k}", cur.resets[k]) for k in RESET_KINDS]
    kv += [("last_reset", cur.last_reset),
           ("latency_p50_ms", _pct(lat, 50)), ("latency_p99_ms", _pct(lat, 99)),
           ("latency_max_ms", f"{lat.max():.3f}" if lat.size else "nan"),
           ("labeling_p50_ms", _pct(labt, 50)), ("labeling_p99_ms", _pct(labt, 99)),
           ("overhead_p50_ms", _pct(ovh, 50)), ("overhead_p99_ms", _pct(ovh, 99)),
           ("stall_p99_ms", _pct(st.stall_ms, 99)),
           ("stall_max_ms", f"{st.stall_ms.max():.3f}" if st.stall_ms.size else "nan"),
           ("latency_window_frames", lat.size), ("full_searches", cur.full_searches),
           ("frames_doubtful", cur.frames_doubtful), ("recoveries_joined", cur.recoveries_joined),
           ("settings_applied", cur.settings_applied),
           ("last_log_likelihood", f"{cur.last_log_likelihood:.3f}"), ("publishers_matched", st.publishers),
           ("active", st.active)]
    return kv + [(k, v) for k, v in st.config.items() if k not in _MODEL_CONFIG]


def _model_status(cur: NodeStats, st: NodeState) -> Tuple[int, str, List[Tuple[str, Any]]]:
    level, message = {
        "loaded": (OK, f"model loaded: {st.model_path}"),
        "loading": (WARN, f"loading {st.model_path}"),
        "reload failed": (WARN, f"reload failed, still running {st.model_path}: {st.model_error}"),
    }.get(st.model_status, (ERROR, f"no model: {st.model_error}"))
    kv = [("model_status", st.model_status), ("model_path", st.model_path), ("model_error", st.model_error),
          ("calibration", st.calibration),
          ("labels", ",".join(st.labels)), ("n_labels", len(st.labels)),
          ("expected_labels", ",".join(st.config.get("expected_labels", []) or [])),
          ("active_model", st.active_model), ("use_bank", st.config.get("use_bank", False)),
          ("bank_actions", ",".join(st.actions)), ("reloads_ok", cur.reloads_ok),
          ("reloads_failed", cur.reloads_failed), ("models_prepared", cur.models_prepared)]
    return level, message, kv


class DiagnosticsBuilder:
    """Builds the two statuses; remembers the previous snapshot for the per-period figures."""

    def __init__(self) -> None:
        self._prev: Optional[NodeStats] = None
        self._t_prev: Optional[float] = None

    def build(self, cur: NodeStats, st: NodeState, now: float) -> list:
        from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
        prev = self._prev if self._prev is not None else NodeStats()
        dt = max(now - self._t_prev, 1e-6) if self._t_prev is not None else 1.0
        self._prev, self._t_prev = cur, now
        level, message = assess(cur, prev, dt, st)
        in_rate, out_rate = _delta(cur, prev, "received") / dt, _delta(cur, prev, "published") / dt
        out = []
        m_level, m_message, m_values = _model_status(cur, st)
        for kind, lv, msg, kv in (("labeling", level, message, _labeling_values(cur, in_rate, out_rate, st)),
                                  ("model", m_level, m_message, m_values)):
            s = DiagnosticStatus()
            s.name = f"{st.name}: {kind}"
            s.hardware_id = st.hardware_id
            s.level = bytes([lv]) if isinstance(s.level, bytes) else lv
            s.message = msg
            s.values = [KeyValue(key=k, value=str(v)) for k, v in kv]
            out.append(s)
        return out
