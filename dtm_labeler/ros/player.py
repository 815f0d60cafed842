"""Replay a rosbag2 bag over DDS on its recorded timeline (the ``ros2 bag play`` substitute).

The messages are read with ``rosbags`` and published as the recorded CDR bytes
(``Publisher.publish(bytes)``; no deserialisation), one rclpy publisher per topic with the
topic's message type, reliable QoS (matches reliable and best-effort subscribers). Timing:
message ``k`` is sent at ``start + (t_k - t_0) / rate`` on ``time.perf_counter``; the lateness
of every send is measured and reported (typically well under a millisecond here).
The timeline starts when the first message is out (a writer's first send can be held in
Fast DDS for ~0.2 s; ``PlayStats.start_held_ms``).

Options beyond ``ros2 bag play``:

* ``wait_for`` -- before starting, wait (up to ``wait_timeout`` s) until each of these topics has
  at least one subscriber (default: ``/markers/unlabeled`` when played); ``start_delay`` adds
  a pause after that (e.g. for a node that warms up after subscribing).
* ``restamp`` -- rewrite the header stamp of every message that starts with a
  ``std_msgs/Header`` to the wall-clock time it is *scheduled* for (the same new stamp for
  messages recorded with the same time, so clouds and ground truth still pair up). With it,
  ``reception time - header stamp`` downstream is the end-to-end latency; without it the
  recorded stamps are sent as they are (like ``ros2 bag play``).
* ``clock`` -- publish ``/clock`` (rosgraph_msgs/Clock) with the message time before each
  message (for ``use_sim_time``): the recorded time, or the new stamp with ``restamp``.
* ``loop`` -- play again and again until stopped; with ``restamp`` time keeps increasing,
  without it the stamps jump back (as with ``ros2 bag play --loop``).

Rule one (../shared/ros2.md) is the caller's: this module does not set
``ROS_AUTOMATIC_DISCOVERY_RANGE``; ``dtm-bag play`` and the demo do.
"""
from __future__ import annotations

import importlib
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from .bag import TOPIC_UNLABELED, BagError, RawMessage, read_raw, topic_name, typestore


@dataclass
class PlayStats:
    sent: dict = field(default_factory=dict)          # topic -> messages sent
    loops: int = 0
    lateness_ms: dict = field(default_factory=dict)   # p50, p99, max of (send - scheduled)
    waited_s: float = 0.0                             # waiting for subscribers
    matched: dict = field(default_factory=dict)       # topic -> subscribers when starting
    duration_s: float = 0.0                           # first to last send
    stopped: bool = False                             # stopped early (stop event / interrupt)
    start_held_ms: float = 0.0                        # the first send held in DDS; the timeline starts after it

    def as_dict(self) -> dict:
        return dict(sent=self.sent, loops=self.loops, lateness_ms=self.lateness_ms, waited_s=self.waited_s,
                    matched=self.matched, duration_s=self.duration_s, stopped=self.stopped,
                    start_held_ms=self.start_held_ms)


def message_class(msgtype: str):
    """The rclpy message class of ``pkg/msg/Name``."""
    pkg, kind, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ImportError, AttributeError) as e:
        raise BagError(f"message type {msgtype} is not available to rclpy here ({e})") from None


def _has_header(msgtype: str) -> bool:
    """True when the type's first field is a std_msgs/Header (its stamp is at CDR offset 4)."""
    try:
        fields = typestore().fielddefs[msgtype][1]
        return bool(fields) and fields[0][0] == "header" and fields[0][1][1] == "std_msgs/msg/Header"
    except (KeyError, IndexError, TypeError):
        return False


def restamp_cdr(data: bytes, stamp_ns: int) -> bytes:
    """CDR bytes of a header-first message with the header stamp replaced."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    endian = "<" if data[1] & 1 else ">"
    return data[:4] + struct.pack(endian + "iI", sec, nsec) + data[12:]


def play(bag: str | Path | None = None, rate: float = 1.0, loop: bool = False, topics: Iterable[str] | None = None,
         start_delay: float = 0.0, clock: bool = False, restamp: bool = False,
         wait_for: Sequence[str] | None = None, wait_timeout: float = 30.0, stop: threading.Event | None = None,
         messages: Sequence[RawMessage] | None = None, node_name: str = "dtm_bag_player",
         on_start: Callable[[float], None] | None = None, log: Callable[[str], None] | None = None) -> PlayStats:
    """Publish a bag's messages (or ``messages``) on their timeline; returns :class:`PlayStats`.
    Starts and shuts down its own rclpy context. See the module doc for the options."""
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    if not rate > 0:
        raise BagError("rate must be positive")
    msgs = list(messages) if messages is not None else read_raw(bag, topics)
    if not msgs:
        raise BagError("nothing to play (no messages)")
    log = log or (lambda s: None)
    stop = stop or threading.Event()
    types = {m.topic: m.msgtype for m in msgs}
    header_topics = {t for t, ty in types.items() if _has_header(ty)}
    if wait_for is None:
        wait_for = [TOPIC_UNLABELED] if TOPIC_UNLABELED in types else []
    wait_for = [topic_name(t) for t in wait_for]
    unknown = set(wait_for) - set(types)
    if unknown:
        raise BagError(f"--wait-for topics not played: {', '.join(sorted(unknown))}")

    from rclpy.signals import SignalHandlerOptions

    ctx = rclpy.Context()
    # no rclpy signal handlers: Ctrl-C / SIGTERM reach the caller as exceptions
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    stats = PlayStats(sent={t: 0 for t in types})
    try:
        node = rclpy.create_node(node_name, context=ctx)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        pubs = {t: node.create_publisher(message_class(ty), t, qos) for t, ty in types.items()}
        clock_pub = None
        if clock:
            from rosgraph_msgs.msg import Clock
            clock_pub = node.create_publisher(Clock, "/clock", 10)

        stats.waited_s = _wait_for_subscribers(pubs, wait_for, wait_timeout, stop, log)
        stats.matched = {t: p.get_subscription_count() for t, p in pubs.items()}
        if start_delay > 0:
            stop.wait(start_delay)
        lateness, first_send, last_send = _send(msgs, pubs, clock_pub, header_topics, stats, stop, rate=rate,
                                                loop=loop, restamp=restamp, on_start=on_start)
        stats.stopped = stop.is_set()
        for p in pubs.values():
            p.wait_for_all_acked(Duration(seconds=2.0))
        if lateness:
            v = np.asarray(lateness) * 1e3
            stats.lateness_ms = dict(p50=float(np.percentile(v, 50)), p99=float(np.percentile(v, 99)),
                                     max=float(v.max()))
        stats.duration_s = (last_send - first_send) if first_send is not None else 0.0
        node.destroy_node()
    finally:
        if ctx.ok():
            rclpy.shutdown(context=ctx)
    return stats


def _wait_for_subscribers(pubs: dict, wait_for: Sequence[str], timeout: float, stop: threading.Event,
                          log: Callable[[str], None]) -> float:
    """Wait until every topic of ``wait_for`` has a subscriber (or ``timeout``); seconds waited."""
    t_wait = time.monotonic()
    if wait_for and timeout > 0:
        log(f"waiting for subscribers on {', '.join(wait_for)}")
        while not stop.is_set():
            if all(pubs[t].get_subscription_count() > 0 for t in wait_for):
                break
            if time.monotonic() - t_wait > timeout:
                log(f"no subscriber after {timeout:.0f} s; playing anyway")
                break
            time.sleep(0.01)
    return time.monotonic() - t_wait


def _send(msgs: Sequence[RawMessage], pubs: dict, clock_pub, header_topics: set, stats: PlayStats,
          stop: threading.Event, *, rate: float, loop: bool, restamp: bool,
          on_start: Callable[[float], None] | None) -> tuple:
    """Publish ``msgs`` on their timeline (looping when asked); (lateness list, first, last send).

    The timeline starts when the first message is out: a writer's first send can be held in
    Fast DDS for ~0.2 s (seen once in ~15 benchmark runs: ``publish`` itself took 193 ms), and
    catching up would send the next 0.2 s of frames in one burst -- late on arrival, so the
    labeler drops them as stale (7 of 1776 frames at 120 Hz, 54 of 3600 at 360 Hz, the stream's
    end-to-end maximum 196-208 ms). When the first send is late by more than a frame period,
    every later message keeps its place on the timeline from there (``start_held_ms``): on the
    wire the stream starts that much later, as a mocap system's would."""
    clock_msg = None
    if clock_pub is not None:
        from rosgraph_msgs.msg import Clock
        clock_msg = Clock()
    t_rec = np.array([m.t_ns for m in msgs], dtype=np.int64)
    t0 = int(t_rec[0])
    span_ns = int(t_rec[-1] - t0)
    steps = np.diff(np.unique(t_rec))
    period_ns = int(np.median(steps)) if steps.size else 0
    lateness = []
    wall0, perf0 = time.time(), time.perf_counter()
    if on_start is not None:
        on_start(wall0)
    first_send = last_send = None
    offset_ns = 0                     # recorded-time offset of this loop pass
    started = False                   # the first recorded time's messages are out
    while not stop.is_set():
        for m in msgs:
            if not started and m.t_ns != t0:
                started = True
                held = lateness[0] if lateness else 0.0
                if held * rate > max(period_ns, 1) * 1e-9:
                    perf0, wall0 = perf0 + held, wall0 + held
                    stats.start_held_ms = held * 1e3
            rel_ns = m.t_ns - t0 + offset_ns
            target = perf0 + rel_ns / rate * 1e-9
            while (d := target - time.perf_counter()) > 0 and not stop.is_set():
                time.sleep(min(d, 0.05))
            if stop.is_set():
                break
            stamp = int(round((wall0 + rel_ns / rate * 1e-9) * 1e9)) if restamp else m.t_ns + offset_ns
            data = restamp_cdr(m.data, stamp) if restamp and m.topic in header_topics else m.data
            if clock_msg is not None:
                clock_msg.clock.sec, clock_msg.clock.nanosec = divmod(stamp, 1_000_000_000)
                clock_pub.publish(clock_msg)
            pubs[m.topic].publish(data)
            now = time.perf_counter()
            lateness.append(now - target)
            first_send = now if first_send is None else first_send
            last_send = now
            stats.sent[m.topic] += 1
        else:
            stats.loops += 1
            if loop:
                offset_ns += span_ns + period_ns
                continue
        break
    return lateness, first_send, last_send


# ----------------------------------------------------------------------------------- monitor

def _diag_values(status) -> dict:
    """The status's key/values, plus its message under ``_message``."""
    return {**{kv.key: kv.value for kv in status.values}, "_message": status.message}


class ReplayMonitor:
    """Listens to a replay: ``markers/labeled`` (the node's output), ``markers/ground_truth``
    (the player's) and ``/diagnostics``; scores output against truth (matched by stamp and
    position) and measures end-to-end latency = DDS reception time of the labelled message
    (rclpy's message info, wall clock) - header stamp (meaningful when the player restamps with
    wall-clock times). Runs its own rclpy context and executor
    thread; use as a context manager or call :meth:`start` / :meth:`close`.

    ``labeled_qos``: 'reliable' (default, matches the node's default output) or 'sensor_data'.
    """

    def __init__(self, known_labels: Sequence[str] | None = None, labeled_qos: str = "reliable",
                 node_name: str = "dtm_replay_monitor", diag_node: str = "dtm_labeler"):
        from .bag import Scorer
        self.scorer = Scorer(known=set(known_labels) if known_labels else None)
        self.labeled_qos = labeled_qos
        self.node_name = node_name
        self.diag_node = diag_node
        self.lock = threading.Lock()
        self.n_labeled = 0
        self.n_truth = 0
        self.latency_ms: list[float] = []       # reception - stamp, per labelled frame
        self.node_latency_ms: list[float] = []  # the node's own latency_ms field
        self.stamps: list[int] = []             # labelled stamps in arrival order
        self.recv_times: list[float] = []       # DDS reception time (wall clock) per labelled frame
        self.truth_stamps: list[int] = []       # ground-truth stamps in arrival order
        self.out_of_order = 0
        self._pending: list = []                # (kind, stamp, serialised message) not scored yet
        self._score_lock = threading.Lock()
        self.diag: dict = {}                    # last /diagnostics values of the labeler
        self.diag_count = 0
        self.model_diag: dict = {}              # last values of its model status (model_status, model_path)
        self._ctx = None
        self._thread = None

    # -- life cycle
    def start(self) -> "ReplayMonitor":
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from diagnostic_msgs.msg import DiagnosticArray
        from dtm_labeler_msgs.msg import LabeledMarkerArray

        self._ctx = rclpy.Context()
        rclpy.init(context=self._ctx, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(self.node_name, context=self._ctx)
        rel = ReliabilityPolicy.RELIABLE if self.labeled_qos == "reliable" else ReliabilityPolicy.BEST_EFFORT
        # raw: the callbacks read the stamp off the bytes and queue them; messages are decoded
        # and scored when asked (snapshot), so a 41-marker stream does not back this executor
        # up -- a late callback here would count as the labeler's latency
        self.node.create_subscription(LabeledMarkerArray, "markers/labeled", self._on_labeled,
                                      QoSProfile(depth=1000, reliability=rel), raw=True)
        self.node.create_subscription(LabeledMarkerArray, "markers/ground_truth", self._on_truth,
                                      QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE), raw=True)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self._executor = SingleThreadedExecutor(context=self._ctx)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name="replay_monitor", daemon=True)
        self._thread.start()
        return self

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException
        try:
            while self._ctx.ok():
                self._executor.spin_once(timeout_sec=0.1)
        except (ExternalShutdownException, Exception):  # context shut down under us
            pass

    def close(self) -> None:
        import rclpy
        if self._ctx is None:
            return
        ctx, self._ctx = self._ctx, None
        rclpy.shutdown(context=ctx)
        if self._thread is not None:
            self._thread.join(2.0)
        try:
            self._executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        except Exception:
            pass

    def __enter__(self) -> "ReplayMonitor":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- callbacks (executor thread)
    def _on_labeled(self, raw: bytes, info: dict) -> None:
        # when DDS received it, not when this callback ran: a garbage collection in this process
        # (35-75 ms, every ~11 s in dtm-demo's: 110 k objects) or its scoring holding the GIL
        # would otherwise count as the node's latency
        ns = info.get("received_timestamp") if info else None
        now = int(ns) * 1e-9 if ns else time.time()
        st = _cdr_stamp_ns(raw)
        with self.lock:
            if self.stamps and st <= self.stamps[-1]:
                self.out_of_order += 1
            self.stamps.append(st)
            self.recv_times.append(now)
            self.n_labeled += 1
            self.latency_ms.append((now - st * 1e-9) * 1e3)
            self._pending.append(("out", st, raw))

    def _on_truth(self, raw: bytes) -> None:
        st = _cdr_stamp_ns(raw)
        with self.lock:
            self.n_truth += 1
            self.truth_stamps.append(st)
            self._pending.append(("truth", st, raw))

    def _score_pending(self) -> None:
        """Decode and score the messages received since the last call (in arrival order)."""
        from rclpy.serialization import deserialize_message
        from dtm_labeler_msgs.msg import LabeledMarkerArray
        from .bag import markers_to_arrays
        with self._score_lock:
            with self.lock:
                pending, self._pending = self._pending, []
            decoded = [(kind, st, deserialize_message(raw, LabeledMarkerArray)) for kind, st, raw in pending]
            with self.lock:
                for kind, st, msg in decoded:
                    xyz, labels = markers_to_arrays(msg)
                    if kind == "out":
                        self.node_latency_ms.append(float(msg.latency_ms))
                        self.scorer.add_output(st, xyz, labels)
                    else:
                        self.scorer.add_truth(st, xyz, labels)

    def _on_diag(self, msg) -> None:
        for st in msg.status:
            if self.diag_node and not st.name.startswith(self.diag_node):
                continue
            if st.name.endswith(": labeling"):
                with self.lock:
                    self.diag = _diag_values(st)
                    self.diag_count += 1
            elif st.name.endswith(": model"):
                with self.lock:
                    self.model_diag = _diag_values(st)

    # -- queries
    def publishers_ready(self, topics: Sequence[str] = ("markers/labeled", "/diagnostics")) -> bool:
        return all(self.node.count_publishers(t if t.startswith("/") else "/" + t) > 0 for t in topics)

    def wait_ready(self, timeout: float = 20.0, alive: Callable[[], bool] | None = None,
                   topics: Sequence[str] = ("markers/labeled",)) -> bool:
        """Wait until the node's topics have publishers (the node is up); False on timeout or
        when ``alive()`` turns False."""
        t = time.monotonic()
        while time.monotonic() - t < timeout:
            if self.publishers_ready(topics):
                return True
            if alive is not None and not alive():
                return False
            time.sleep(0.05)
        return False

    def wait_model_loaded(self, timeout: float = 60.0, alive: Callable[[], bool] | None = None) -> bool:
        """Wait until the node's model status says ``loaded``; False on timeout or when
        ``alive()`` turns False."""
        t = time.monotonic()
        while time.monotonic() - t < timeout:
            with self.lock:
                if self.model_diag.get("model_status") == "loaded":
                    return True
            if alive is not None and not alive():
                return False
            time.sleep(0.05)
        return False

    def wait_diag(self, predicate: Callable[[dict], bool], timeout: float = 5.0) -> dict:
        """Wait for a /diagnostics message whose values satisfy ``predicate``; the last values."""
        t = time.monotonic()
        while True:
            with self.lock:
                d = dict(self.diag)
            if d and predicate(d):
                return d
            if time.monotonic() - t > timeout:
                return d
            time.sleep(0.05)

    def skipped(self, d: dict | None = None) -> int:
        """Frames the node counted as skipped (all reasons) in diagnostics ``d`` (default last)."""
        d = self.diag if d is None else d
        return sum(int(v) for k, v in d.items() if k.startswith("frames_skipped_"))

    def snapshot(self, score: bool = True) -> dict:
        """Counts, latency and (``score``: decoding what arrived since) accuracy so far."""
        if score:
            self._score_pending()
        with self.lock:
            lat = np.asarray(self.latency_ms)
            node_lat = np.asarray(self.node_latency_ms)
            d = dict(self.diag)
            s = self.scorer
            return dict(labeled=self.n_labeled, truth=self.n_truth, accuracy=s.accuracy, correct=s.correct,
                        true_markers=s.total, ghost_rejection=s.ghost_rejection, ghosts=s.ghosts,
                        frames_scored=s.frames_scored, out_of_order=self.out_of_order,
                        latency_ms=_pcts(lat), node_latency_ms=_pcts(node_lat),
                        node_received=int(d.get("frames_received", 0)), node_published=int(d.get(
                            "frames_published", 0)), node_carried=int(d.get("frames_carried", 0)),
                        node_skipped=self.skipped(d),
                        node_skipped_detail={k[len("frames_skipped_"):]: int(v) for k, v in d.items()
                                             if k.startswith("frames_skipped_")})


def _cdr_stamp_ns(raw: bytes) -> int:
    """Header stamp (ns) of a serialised message that starts with a std_msgs/Header (CDR:
    4 bytes of encapsulation -- the second says the byte order -- then int32 sec, uint32
    nanosec)."""
    sec, nsec = struct.unpack_from("<iI" if raw[1] & 1 else ">iI", raw, 4)
    return sec * 1_000_000_000 + nsec


def _pcts(v: np.ndarray) -> dict:
    if not v.size:
        return dict(p50=float("nan"), p99=float("nan"), max=float("nan"), mean=float("nan"), n=0)
    return dict(p50=float(np.percentile(v, 50)), p99=float(np.percentile(v, 99)), max=float(v.max()),
                mean=float(v.mean()), n=int(v.size))
