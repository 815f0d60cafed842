"""Shared utilities for tests that run the dtm_labeler node as a real process over real DDS.

Import from test modules (``from node_helpers import ...``); nothing here is a pytest fixture
by itself, so modules can wrap these in fixtures of any scope.

* :func:`walk_model` -- a model trained once per test session (cached; the 07_01 walk BVH
  from ../shared/data when present, else the synthetic walker), plus the walk frames to feed,
  a corrupt model file and one with mismatched labels.
* :func:`node_env` -- the child environment: the test's own environment (venv python, same
  LD_LIBRARY_PATH -- never a modified one, see ../shared/ros2.md) with
  ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, the session's ROS_DOMAIN_ID and the fast-announce
  Fast DDS profile.
* :class:`NodeProcess` -- ``python -m dtm_labeler.ros.node`` in a namespace, log to a file,
  ``stop(signal)`` returns the exit code.
* :class:`NodeClient` -- an rclpy node in the test process (own context, executor thread):
  publishes clouds, collects every output topic, waits on predicates (never fixed sleeps),
  sets/gets parameters through the standard services.
"""
from __future__ import annotations

import atexit
import functools
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
FASTDDS_PROFILE = HERE / "fastdds_fast_announce.xml"
DATA_DIR = Path(os.environ.get("DTM_DATA_DIR", REPO.parent / "shared" / "data"))
WALK_BVH = DATA_DIR / "cmu_skeletal" / "bvh_from_fbx" / "cmu_07_01_walk_s07.bvh"
PARAMS_FILE = REPO / "params" / "labeler.yaml"
#: a query to a node (get_state, parameters) unanswered this long is sent again (NodeClient.call)
RESEND_S = 2.0


# ----------------------------------------------------------------------------- model + data
@dataclass
class WalkModel:
    path: Path                  # good model file
    alt_path: Path              # the same model under another path (reload to a new path)
    corrupt_path: Path          # not a model file
    mismatched_path: Path       # a valid model whose labels differ (upper-cased names)
    labels: tuple
    positions: np.ndarray       # (F, M, 3) frames to feed, columns in model label order
    rate: float
    source: str                 # "bvh" | "synthetic"


_TMP: List[str] = []


def _tmpdir() -> Path:
    if not _TMP:
        d = tempfile.mkdtemp(prefix="dtm_node_test_")
        _TMP.append(d)
        atexit.register(shutil.rmtree, d, True)
    return Path(_TMP[0])


@functools.lru_cache(maxsize=1)
def walk_model() -> WalkModel:
    """Train (once per session) a BODY14 walk model; see module doc."""
    from dtm_labeler.model.dtm import TriangulatedModel
    from dtm_labeler.model.io import save_model
    from dtm_labeler.training.train import TrainConfig, train_model
    from dtm_labeler.motion import load_clip, synthesize, to_point_set

    if WALK_BVH.is_file():
        clip = to_point_set(load_clip(WALK_BVH), "body14")
        source = "bvh"
    else:
        clip = synthesize(duration=3.0, rate=120.0, seed=1)
        source = "synthetic"
    # fixed K + greedy structure: ~0.5 s instead of ~7 s for MDL + CBGA, and it labels this
    # walk just as well (the node tests are about the node, not the model)
    model, _ = train_model([clip], TrainConfig(mixture="fixed", k_fixed=3, structure="greedy"))
    d = _tmpdir()
    path = save_model(model, d / "walk.npz")
    alt = shutil.copy(path, d / "walk_copy.npz")
    corrupt = d / "corrupt.npz"
    corrupt.write_bytes(b"PK\x03\x04 this is not a model file" * 10)
    other = TriangulatedModel(labels=tuple(x.upper() for x in model.labels), structure=model.structure,
                              mixtures=model.mixtures, heading_pairs=model.heading_pairs,
                              settings=model.settings, provenance=model.provenance)
    mismatched = save_model(other, d / "mismatched.npz")
    idx = [list(clip.names).index(x) for x in model.labels]
    pos = np.asarray(clip.positions)[:, idx, :]
    pos = pos[np.isfinite(pos).all(axis=(1, 2))]
    return WalkModel(Path(path), Path(alt), corrupt, Path(mismatched), tuple(model.labels), pos,
                     float(clip.rate), source)


class FrameFeed:
    """Frames of the walk, shuffled per frame, with increasing stamps (loops over the clip)."""

    def __init__(self, wm: WalkModel, seed: int = 0, start_stamp: float = 100.0):
        self.wm = wm
        self.rng = np.random.default_rng(seed)
        self.i = 0
        self.stamp = start_stamp

    def next(self, dt: Optional[float] = None):
        """``(xyz (M, 3), truth (M,) label index per row, stamp)``; advances time by one frame
        (or ``dt`` seconds)."""
        F = self.wm.positions.shape[0]
        x = self.wm.positions[self.i % F]
        perm = self.rng.permutation(x.shape[0])
        self.i += 1
        self.stamp += (1.0 / self.wm.rate) if dt is None else dt
        return x[perm].copy(), perm, self.stamp


def stamped_cloud(xyz: np.ndarray, stamp: float, frame_id: str = "m"):
    """A PointCloud2 of ``xyz`` whose header is stamped ``stamp`` seconds (what a driver sends)."""
    from std_msgs.msg import Header

    from dtm_labeler.ros.pointcloud import make_xyz_cloud
    sec = int(stamp)
    hdr = Header(frame_id=frame_id)
    hdr.stamp.sec, hdr.stamp.nanosec = sec, int((stamp - sec) * 1e9)
    return make_xyz_cloud(xyz, header=hdr)


class HeldSearch:
    """A slow search without timing: after :meth:`hold`, the labeler's next ``process`` call
    sets ``entered`` and waits at a gate until :meth:`release`."""

    def __init__(self, labeler, timeout: float):
        self.entered, self.gate = threading.Event(), threading.Event()
        self._labeler, self._real, self._timeout = labeler, labeler.process, timeout

    def _held(self, *a, **k):
        if not self.gate.is_set():
            self.entered.set()
            assert self.gate.wait(self._timeout)
        return self._real(*a, **k)

    def hold(self) -> None:
        self._labeler.process = self._held

    def release(self) -> None:
        self.gate.set()


def send_one_by_one(send, published: list, frames: int, deadline: float) -> None:
    """``send`` ``frames`` frames, each after the previous one was published (tracks and
    labels established before a test starts holding searches)."""
    for _ in range(frames):
        n0 = len(published)
        send()
        while len(published) == n0 and time.monotonic() < deadline:
            time.sleep(0.002)


def assert_in_order_with_own_labels(out: list, truths: list, sent: list) -> None:
    """Published ``LabeledMarkerArray`` messages ``out`` come in stamp order, one per frame, and
    each carries its own points' labels (>= 90 % right; ``sent[i]``: the index in ``truths`` of
    the frame ``out[i]`` is)."""
    stamps = [m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec for m in out]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    for m, k in zip(out, sent):
        got = np.array([x.label_index for x in m.markers if not x.occluded])
        truth = truths[k]
        assert np.mean(got[truth >= 0] == truth[truth >= 0]) >= 0.9


# ----------------------------------------------------------------------------- processes
def node_env(extra: Optional[Dict[str, str]] = None) -> Dict[str, str]:
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("ROS_DOMAIN_ID", str(40 + os.getpid() % 50))
    if FASTDDS_PROFILE.is_file():
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FASTDDS_PROFILE)
    env["RCUTILS_LOGGING_BUFFERED_STREAM"] = "0"
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


class NodeProcess:
    """The labeler node as a child process in namespace ``ns``. Every one started is killed at
    the end of the test session if a test left it running (:func:`kill_leftovers`). Lock-step
    tests (one frame, then its output) run the node's searches inline unless ``params`` say
    otherwise: in the background mode the first frames are published unconfirmed until the
    worker's search joins (tested on its own, under a real-time stream)."""

    started: List["NodeProcess"] = []

    def __init__(self, ns: str, params: Optional[Dict[str, Any]] = None, params_file: Optional[Path] = None,
                 extra_args: Sequence[str] = (), console_script: bool = False, module: str = "dtm_labeler.ros.node",
                 cmd: Optional[Sequence[str]] = None, env: Optional[Dict[str, str]] = None):
        self.ns = ns.strip("/")
        params = {"recovery": "inline"} | dict(params or {})
        self.log_path = _tmpdir() / f"node_{self.ns}_{time.monotonic_ns()}.log"
        script = Path(sys.executable).parent / "dtm-labeler-node"
        if cmd is not None:
            cmd = list(cmd)
        elif console_script and script.is_file():
            cmd = [str(script)]
        else:
            cmd = [sys.executable, "-m", module]
        args = cmd + ["--ros-args", "-r", f"__ns:=/{self.ns}"]
        if params_file is not None:
            args += ["--params-file", str(params_file)]
        for k, v in (params or {}).items():
            if isinstance(v, bool):
                v = "true" if v else "false"
            elif isinstance(v, (list, tuple)):
                v = "[" + ",".join(f"'{x}'" for x in v) + "]"
            args += ["-p", f"{k}:={v}"]
        args += list(extra_args)
        self.args = args
        self._log = open(self.log_path, "wb")
        self.t_start = time.monotonic()
        self.proc = subprocess.Popen(args, env=env or node_env(), stdout=self._log, stderr=subprocess.STDOUT,
                                     cwd=str(REPO), start_new_session=True)
        NodeProcess.started.append(self)

    @property
    def fqn(self) -> str:
        return f"/{self.ns}/dtm_labeler"

    def topic(self, name: str) -> str:
        return f"/{self.ns}/{name}"

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def wait_log(self, text: str, timeout: float = 5.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if text in self.log():
                return True
            time.sleep(0.02)
        return text in self.log()

    def stop(self, sig: int = signal.SIGINT, timeout: float = 10.0) -> int:
        self.stop_seconds = 0.0
        if self.proc.poll() is None:
            t = time.monotonic()
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
            self.stop_seconds = time.monotonic() - t
        self._log.close()
        return self.proc.returncode


# ----------------------------------------------------------------------------- in-process client
class NodeClient:
    """Talks to one node process: publisher, subscribers, parameter client, all on a private
    rclpy context spun by a background executor thread."""

    def __init__(self, node: NodeProcess, input_reliable: bool = True):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.parameter_client import AsyncParameterClient
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray

        from dtm_labeler_msgs.msg import LabeledMarkerArray

        self.target = node
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node(f"test_client_{node.ns}", context=self.ctx)
        self.cond = threading.Condition()
        self.labeled: List[Any] = []
        self.clouds: List[Any] = []
        self.viz: List[Any] = []
        self.diags: List[Dict[str, str]] = []
        q = QoSProfile(depth=50)
        self.pub = self.node.create_publisher(
            PointCloud2, node.topic("markers/unlabeled"),
            QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE if input_reliable
                       else ReliabilityPolicy.BEST_EFFORT))
        self.labeled_times: List[float] = []       # time.monotonic() at reception, one per labeled
        self.sub_l = self.node.create_subscription(LabeledMarkerArray, node.topic("markers/labeled"),
                                                   self._on_labeled, q)
        self.sub_c = self.node.create_subscription(PointCloud2, node.topic("markers/labeled_cloud"),
                                                   self._store(self.clouds), q)
        self.sub_v = self.node.create_subscription(MarkerArray, node.topic("markers/visualization"),
                                                   self._store(self.viz), q)
        self.sub_d = self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, q)
        self.mocap4r2: List[Any] = []
        self._input_pubs: Dict[str, Any] = {"pointcloud2": self.pub}
        self._input_nodes: List[Any] = []
        self._clients: Dict[Any, Any] = {}          # (service type, name) -> client
        self._input_qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE if input_reliable
                                     else ReliabilityPolicy.BEST_EFFORT)
        try:
            from mocap4r2_msgs.msg import Markers
            self.sub_m = self.node.create_subscription(Markers, node.topic("markers/labeled_mocap4r2"),
                                                       self._store(self.mocap4r2), q)
        except ImportError:
            self.sub_m = None
        self.params = AsyncParameterClient(self.node, node.fqn)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        from rclpy.executors import ExternalShutdownException
        try:
            self.ex.spin()
        except (ExternalShutdownException, Exception):
            pass

    def _store(self, lst):
        def cb(msg):
            with self.cond:
                lst.append(msg)
                self.cond.notify_all()
        return cb

    def _on_labeled(self, msg):
        with self.cond:
            self.labeled.append(msg)
            self.labeled_times.append(time.monotonic())
            self.cond.notify_all()

    def max_gap(self, t0: float, t1: float) -> float:
        """The longest time without a labelled output between ``t0`` and ``t1`` (monotonic)."""
        with self.cond:
            t = [x for x in self.labeled_times if t0 <= x <= t1]
        return float(np.max(np.diff([t0] + t + [t1])))

    def max_node_stall(self, t0: float, t1: float) -> float:
        """The longest time between ``t0`` and ``t1`` in which the node's worker was not labelling:
        each gap between two outputs less the time the second frame spent in the node
        (``latency_ms``: receive -> published, the labeler's own search included). What remains is
        the node not labelling (swapping engines, applying settings, waiting on anything) plus
        up to one frame period of waiting for input."""
        with self.cond:
            pairs = [(t, m.latency_ms * 1e-3) for t, m in zip(self.labeled_times, self.labeled) if t0 <= t <= t1]
        if not pairs:
            return t1 - t0
        times = [t0] + [t for t, _ in pairs]
        stall = [t - prev - lat for prev, (t, lat) in zip(times, pairs)]
        return float(max(max(stall), t1 - times[-1]))

    def _on_diag(self, msg):
        vals: Dict[str, str] = {}
        for st in msg.status:
            if st.hardware_id != self.target.fqn:
                continue
            kind = st.name.rsplit(": ", 1)[-1]
            vals[f"{kind}.level"] = str(int.from_bytes(st.level, "little") if isinstance(st.level, bytes)
                                        else int(st.level))
            vals[f"{kind}.message"] = st.message
            for kv in st.values:
                vals[kv.key] = kv.value
        if vals:
            with self.cond:
                self.diags.append(vals)
                self.cond.notify_all()

    # -- waiting ---------------------------------------------------------------------------
    def wait_for(self, pred: Callable[[], Any], timeout: float = 10.0, what: str = "condition"):
        end = time.monotonic() + timeout
        with self.cond:
            while True:
                r = pred()
                if r:
                    return r
                left = end - time.monotonic()
                if left <= 0:
                    if not self.target.alive():
                        raise AssertionError(f"node died while waiting for {what}:\n{self.target.log()[-3000:]}")
                    raise AssertionError(f"timed out after {timeout} s waiting for {what}")
                self.cond.wait(min(left, 0.05))

    def wait_connected(self, timeout: float = 20.0) -> None:
        """Node process up: our publisher matched, its publishers matched, services ready."""
        end = time.monotonic() + timeout

        def ok():
            return (self.pub.get_subscription_count() > 0 and self.sub_l.get_publisher_count() > 0
                    and self.sub_c.get_publisher_count() > 0 and self.sub_v.get_publisher_count() > 0)
        while not ok():
            if not self.target.alive():
                raise AssertionError(f"node exited (rc {self.target.proc.returncode}):\n{self.target.log()[-3000:]}")
            if time.monotonic() > end:
                raise AssertionError(f"node not matched within {timeout} s:\n{self.target.log()[-3000:]}")
            time.sleep(0.02)
        if not self.params.wait_for_services(timeout_sec=max(end - time.monotonic(), 1.0)):
            raise AssertionError("parameter services not available")
        self.probe(max(end - time.monotonic(), 2.0))

    def probe(self, timeout: float = 5.0) -> None:
        """Matched is not yet delivered (a best-effort reader drops samples of a writer it has
        not matched yet): publish empty clouds until the node answers (an empty labelled array,
        or a diagnostics message counting the cloud when it has no model). Empty clouds do
        not touch the labeler's state."""
        end = time.monotonic() + timeout
        stamp = 1.0
        with self.cond:
            n0, l0 = len(self.diags), len(self.labeled)
            received0 = int(self.diags[-1].get("frames_received", "0")) if self.diags else 0
        while True:
            self.publish(np.zeros((0, 3)), stamp)
            try:
                self.wait_for(lambda: any(abs(self.stamp_of(m) - stamp) < 1e-9 for m in self.labeled[l0:]) or any(
                    int(d.get("frames_received", "0")) > received0 for d in self.diags[n0:]), 0.1, "probe")
                return
            except AssertionError:
                if time.monotonic() > end:
                    raise AssertionError(f"node does not answer:\n{self.target.log()[-3000:]}")

    def wait_diag(self, pred: Callable[[Dict[str, str]], Any], timeout: float = 10.0,
                  what: str = "diagnostics") -> Dict[str, str]:
        """The first diagnostics message received from now on that satisfies ``pred``."""
        with self.cond:
            start = len(self.diags)
        found: List[Dict[str, str]] = []

        def check():
            for d in self.diags[start:]:
                if pred(d):
                    found.append(d)
                    return True
            return False
        self.wait_for(check, timeout, what)
        return found[0]

    # -- input -----------------------------------------------------------------------------
    def publish(self, xyz, stamp: float, frame_id: str = "mocap", ids=None, msg=None):
        from builtin_interfaces.msg import Time
        from std_msgs.msg import Header

        from dtm_labeler.ros.pointcloud import make_xyz_cloud
        sec = int(np.floor(stamp))
        header = Header(stamp=Time(sec=sec, nanosec=int(round((stamp - sec) * 1e9)) % 1_000_000_000),
                        frame_id=frame_id)
        if msg is None:
            msg = make_xyz_cloud(xyz, header=header, ids=ids)
        else:
            msg.header = header
        self.pub.publish(msg)
        return header

    def input_pub(self, kind: str):
        """The publisher on markers/unlabeled for input type ``kind``. Each other type gets a
        participant of its own (its own context): Fast DDS refuses a second type on a topic
        name a participant has used, even after the first publisher is destroyed."""
        if kind not in self._input_pubs:
            import rclpy
            from dtm_labeler.ros.inputs import message_class
            ctx = rclpy.Context()
            rclpy.init(context=ctx)
            node = rclpy.create_node(f"test_input_{kind}_{self.target.ns}", context=ctx)
            self._input_nodes.append((node, ctx))
            self._input_pubs[kind] = node.create_publisher(message_class(kind), self.target.topic(
                "markers/unlabeled"), self._input_qos)
        return self._input_pubs[kind]

    def publish_as(self, kind: str, xyz, stamp: float, frame_id: str = "mocap", names=None, frame_number: int = 0):
        """Publish one frame as ``kind`` (pointcloud2 | mocap4r2_markers | pointcloud); mocap4r2
        markers carry ``names`` (USE_NAME) when given, else list indices (USE_INDEX, as the
        OptiTrack driver sends them)."""
        if kind == "pointcloud2":
            return self.publish(xyz, stamp, frame_id=frame_id)
        from builtin_interfaces.msg import Time
        from std_msgs.msg import Header
        sec = int(np.floor(stamp))
        header = Header(stamp=Time(sec=sec, nanosec=int(round((stamp - sec) * 1e9)) % 1_000_000_000),
                        frame_id=frame_id)
        msg = make_input(kind, xyz, names, frame_number)
        msg.header = header
        self.input_pub(kind).publish(msg)
        return header

    def call(self, srv_type, name: str, request=None, timeout: float = 10.0,
             resend_after: Optional[float] = None):
        """Call a service of the node (``name`` relative to its full name, e.g. 'reset').

        A node that answers before DDS has matched this client's response reader loses the
        answer: rmw_fastrtps waits 100 ms for the match, then logs "failed to send response
        (timeout)". On a loaded machine that happens at the first call to a node just started.
        A request that may be repeated (a query) is sent again every ``resend_after`` s until
        one is answered; None sends it once (a reload, a reset, a transition)."""
        key = (srv_type, name)
        cli = self._clients.get(key)
        if cli is None:
            cli = self._clients[key] = self.node.create_client(srv_type, f"{self.target.fqn}/{name}")
        if not cli.wait_for_service(timeout_sec=timeout):
            raise AssertionError(f"service {name} not available")
        req = request or srv_type.Request()
        return self._wait_future(lambda: cli.call_async(req), timeout, resend_after)

    @staticmethod
    def stamp_of(msg) -> float:
        return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec

    def labeled_at(self, stamp: float):
        for m in reversed(self.labeled):
            if abs(self.stamp_of(m) - stamp) < 1e-6:
                return m
        return None

    def send(self, xyz, stamp: float, timeout: float = 5.0, **kw):
        """Publish one cloud and wait for its LabeledMarkerArray (matched by stamp)."""
        self.publish(xyz, stamp, **kw)
        return self.wait_for(lambda: self.labeled_at(stamp), timeout, f"labelled frame at {stamp:.3f}")

    def run_frames(self, feed: FrameFeed, n: int, timeout: float = 5.0) -> float:
        """Send ``n`` frames in lock step; returns the labelling accuracy over them."""
        hits = total = 0
        for _ in range(n):
            xyz, truth, stamp = feed.next()
            out = self.send(xyz, stamp, timeout)
            lab = np.array([m.label_index for m in out.markers if not m.occluded])
            hits += int(np.sum(lab == truth))
            total += truth.size
        return hits / max(total, 1)

    # -- parameters --------------------------------------------------------------------------
    def _wait_future(self, send: Callable[[], Any], timeout: float = 10.0,
                     resend_after: Optional[float] = None):
        """The first answer to ``send()`` (a call returning a future), sent again every
        ``resend_after`` s while none has come (see :meth:`call`)."""
        end = time.monotonic() + timeout
        futures = [send()]
        sent = time.monotonic()
        while not any(f.done() for f in futures):
            if not self.target.alive():
                raise AssertionError(f"{self.target.fqn} exited (status {self.target.proc.returncode}) "
                                     "while a service call to it was waiting")
            now = time.monotonic()
            if now > end:
                raise AssertionError(f"service call to {self.target.fqn} timed out after {timeout:g} s "
                                     f"(node {'running' if self.target.alive() else 'gone'}, "
                                     f"sent {len(futures)} time(s))")
            if resend_after is not None and now - sent > resend_after:
                futures.append(send())
                sent = now
            time.sleep(0.002)
        return next(f for f in futures if f.done()).result()

    def set(self, **values) -> List[Any]:
        """Set parameters one by one (SetParameters); returns the SetParametersResult list."""
        return list(self._wait_future(lambda: self.params.set_parameters(_to_params(values))).results)

    def set_atomically(self, **values) -> Any:
        return self._wait_future(lambda: self.params.set_parameters_atomically(_to_params(values))).result

    def get(self, *names: str) -> Dict[str, Any]:
        from rclpy.parameter import parameter_value_to_python
        res = self._wait_future(lambda: self.params.get_parameters(list(names)), resend_after=RESEND_S)
        return {n: parameter_value_to_python(v) for n, v in zip(names, res.values)}

    def describe(self, *names: str) -> List[Any]:
        return list(self._wait_future(lambda: self.params.describe_parameters(list(names)),
                                      resend_after=RESEND_S).descriptors)

    def list_names(self) -> List[str]:
        return list(self._wait_future(self.params.list_parameters, resend_after=RESEND_S).result.names)

    def close(self) -> None:
        for node, ctx in self._input_nodes:
            node.destroy_node()
            ctx.try_shutdown()
        try:
            self.ex.shutdown(timeout_sec=1.0)
        except Exception:
            pass
        self.node.destroy_node()
        self.ctx.try_shutdown()
        self.thread.join(2.0)


class Streamer:
    """Publishes the walk at ``rate`` Hz from a thread of the test process (a live driver);
    with ``ids``, every marker carries a persistent id (as Qualisys and Vicon streams do)."""

    def __init__(self, client: "NodeClient", feed: FrameFeed, rate: float = 120.0, ids: bool = False):
        self.client, self.feed, self.rate, self.ids = client, feed, rate, ids
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        t_next = time.monotonic()
        while not self._stop.is_set():
            xyz, truth, stamp = self.feed.next()
            self.client.publish(xyz, stamp, ids=truth + 100 if self.ids else None)
            self.sent += 1
            t_next += 1.0 / self.rate
            self._stop.wait(max(t_next - time.monotonic(), 0.0))

    def stop(self):
        self._stop.set()
        self._thread.join(2.0)


def make_input(kind: str, xyz, names=None, frame_number: int = 0):
    """An input message of type ``kind`` holding ``xyz`` (header left empty)."""
    if kind == "pointcloud":
        from geometry_msgs.msg import Point32
        from sensor_msgs.msg import PointCloud
        msg = PointCloud()
        msg.points = [Point32(x=float(x), y=float(y), z=float(z)) for x, y, z in np.asarray(xyz)]
        return msg
    from geometry_msgs.msg import Point
    from mocap4r2_msgs.msg import Marker, Markers
    msg = Markers(frame_number=int(frame_number))
    for i, (x, y, z) in enumerate(np.asarray(xyz, dtype=float)):
        m = Marker(translation=Point(x=x, y=y, z=z), marker_index=i)
        if names is not None:
            m.id_type, m.marker_name = Marker.USE_NAME, str(names[i])
        else:
            m.id_type = Marker.USE_INDEX
        msg.markers.append(m)
    return msg


def _to_params(values: Dict[str, Any]):
    from rclpy.parameter import Parameter
    out = []
    for k, v in values.items():
        if isinstance(v, (list, tuple)) and all(isinstance(x, str) for x in v):
            out.append(Parameter(k, Parameter.Type.STRING_ARRAY, list(v)))
        else:
            out.append(Parameter(k, value=v))
    return out


def kill_leftovers() -> None:
    """Kill node processes (with their recovery workers) that tests left running."""
    for p in NodeProcess.started:
        if p.alive():
            try:
                os.killpg(p.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    NodeProcess.started.clear()


def start(ns: str, **kw) -> tuple:
    """Start a node process and a connected client: ``(NodeProcess, NodeClient)``; with a
    ``model_path``, also wait until the node has loaded it (or refused it): the node loads
    models on its loader thread, after it is up."""
    proc = NodeProcess(ns, **kw)
    try:
        client = NodeClient(proc)
        client.wait_connected()
        if (kw.get("params") or {}).get("model_path"):
            client.wait_diag(lambda d: d.get("model_status") not in (None, "loading"), 20, "model loaded")
    except BaseException:
        proc.stop(signal.SIGKILL)
        raise
    return proc, client
