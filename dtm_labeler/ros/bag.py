"""rosbag2 files for the labeler: recordings -> bags, offline labeling of bags, scoring.

Pure ``rosbags`` + numpy (no rclpy, no ROS install): the bags are standard rosbag2 (metadata
version 9, sqlite3 or mcap storage, CDR) that ``ros2 bag play`` / ``ros2 bag info`` accept.

Topics (absolute in the bag, as ``ros2 bag record`` stores them; the node's relative names
resolve to these in the root namespace):

``/markers/unlabeled``     sensor_msgs/msg/PointCloud2: float32 x, y, z (+ uint32 ``id``), the
                           points of one frame in random order (order carries no label).
``/markers/ground_truth``  dtm_labeler_msgs/msg/LabeledMarkerArray, same header: one marker per
                           delivered point -- true markers with ``label``/``label_index``/``track_id``
                           and the position exactly as in the cloud (float32 values), ghosts with
                           ``label = ''`` and ``label_index = -1``; ``frame_number`` = frame of the
                           source clip; ``label_names`` = the clip's point names.
``/markers/labeled``       (``dtm-bag label`` output) LabeledMarkerArray like the node publishes.
``/markers/labeled_cloud`` (``dtm-bag label`` output) PointCloud2 x, y, z, int32 label, float32
                           confidence.

Timeline: frame ``i`` is stamped (header and bag time) ``start_time + i / rate``; the default
start is 1 s after the epoch, so stamps read as clip time + 1 s.

Scoring (:class:`Scorer`) matches output markers to ground-truth markers by position (exact
float32 positions of the same cloud points, so any consumer can score without ids) within
a frame identified by its header stamp, and compares label *names*.
"""
from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from ..evaluation.corruption import CorruptedStream
from .msg_types import TYPE_NAMES, make_typestore

TOPIC_UNLABELED = "/markers/unlabeled"
TOPIC_GROUND_TRUTH = "/markers/ground_truth"
TOPIC_LABELED = "/markers/labeled"
TOPIC_LABELED_CLOUD = "/markers/labeled_cloud"
PC2 = "sensor_msgs/msg/PointCloud2"
LMA = TYPE_NAMES["LabeledMarkerArray"]
LM = TYPE_NAMES["LabeledMarker"]
STORAGES = ("mcap", "sqlite3")
DEFAULT_START_S = 1.0

_FLOAT32, _INT32, _UINT32 = 7, 5, 6


class BagError(ValueError):
    """A bag that cannot be written or read as asked (the message says why)."""


@lru_cache(maxsize=1)
def typestore():
    """The shared rosbags Jazzy typestore with dtm_labeler_msgs registered."""
    return make_typestore()


def topic_name(name: str) -> str:
    """Absolute topic name (``markers/x`` -> ``/markers/x``)."""
    return name if name.startswith("/") else "/" + name


def _storage_plugin(storage: str):
    from rosbags.rosbag2 import StoragePlugin
    try:
        return {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    except KeyError:
        raise BagError(f"storage must be one of {', '.join(STORAGES)}, got {storage!r}") from None


def _reliable_qos(depth: int = 100):
    """The offered QoS recorded with each connection (what ``ros2 bag play`` re-offers)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    zero = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=depth, reliability=QosReliability.RELIABLE,
               durability=QosDurability.VOLATILE, deadline=zero, lifespan=zero,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=zero,
               avoid_ros_namespace_conventions=False)


def _prepare_out(out: str | Path, force: bool) -> Path:
    out = Path(out)
    if out.exists():
        if not force:
            raise BagError(f"{out} exists (use --force to replace it)")
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


# ------------------------------------------------------------------------------- messages

def _header(stamp_ns: int, frame_id: str):
    T = typestore().types
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                    frame_id=frame_id)


def _fields(spec):
    PF = typestore().types["sensor_msgs/msg/PointField"]
    return [PF(name=n, offset=o, datatype=d, count=1) for n, o, d in spec]


def _cloud(rec: np.ndarray, spec, step: int, n: int, stamp_ns: int, frame_id: str):
    PC = typestore().types[PC2]
    return PC(header=_header(stamp_ns, frame_id), height=1, width=n, fields=_fields(spec),
              is_bigendian=False, point_step=step, row_step=step * n,
              data=np.ascontiguousarray(rec).reshape(-1).view(np.uint8).copy(),
              is_dense=bool(np.isfinite(rec.view(np.float32)[:, :3]).all()) if n else True)


def cloud_message(xyz: np.ndarray, stamp_ns: int, frame_id: str = "mocap", ids: np.ndarray | None = None):
    """rosbags PointCloud2 in the ``markers/unlabeled`` layout (like ``pointcloud.make_xyz_cloud``)."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    n = xyz.shape[0]
    if ids is None:
        return _cloud(xyz, (("x", 0, _FLOAT32), ("y", 4, _FLOAT32), ("z", 8, _FLOAT32)), 12, n, stamp_ns,
                      frame_id)
    rec = np.empty((n, 4), dtype=np.float32)
    rec[:, :3] = xyz
    rec.view(np.uint32)[:, 3] = np.asarray(ids, dtype=np.uint32)
    return _cloud(rec, (("x", 0, _FLOAT32), ("y", 4, _FLOAT32), ("z", 8, _FLOAT32), ("id", 12, _UINT32)), 16, n,
                  stamp_ns, frame_id)


def labeled_cloud_message(xyz: np.ndarray, labels: np.ndarray, confidence: np.ndarray, stamp_ns: int,
                          frame_id: str = "mocap"):
    """rosbags PointCloud2 in the ``markers/labeled_cloud`` layout (like ``make_labeled_cloud``)."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    n = xyz.shape[0]
    rec = np.empty((n, 5), dtype=np.float32)
    rec[:, :3] = xyz
    rec.view(np.int32)[:, 3] = np.asarray(labels, dtype=np.int32)
    rec[:, 4] = np.asarray(confidence, dtype=np.float32)
    spec = (("x", 0, _FLOAT32), ("y", 4, _FLOAT32), ("z", 8, _FLOAT32), ("label", 12, _INT32),
            ("confidence", 16, _FLOAT32))
    return _cloud(rec, spec, 20, n, stamp_ns, frame_id)


def marker_array_message(stamp_ns: int, frame_id: str, frame_number: int, xyz: np.ndarray,
                         label_index: np.ndarray, label_names: Sequence[str], track_ids: np.ndarray | None = None,
                         confidence: np.ndarray | None = None, log_likelihood: float = 0.0, active_model: str = "",
                         latency_ms: float = 0.0):
    """rosbags LabeledMarkerArray: one marker per point; ``label_index`` -1 = unlabeled/ghost.
    Positions are the float32 values of the cloud (so they match the cloud's points exactly)."""
    T = typestore().types
    Point = T["geometry_msgs/msg/Point"]
    Marker = T[LM]
    xyz = np.asarray(xyz, dtype=np.float32).astype(np.float64).reshape(-1, 3)
    n = xyz.shape[0]
    label_index = np.asarray(label_index, dtype=np.int64)
    track_ids = np.zeros(n, dtype=np.int64) if track_ids is None else np.asarray(track_ids, dtype=np.int64)
    confidence = (label_index >= 0).astype(float) if confidence is None else np.asarray(confidence, float)
    names = list(label_names)
    markers = [Marker(label=names[li] if li >= 0 else "", label_index=int(li), track_id=int(max(tid, 0)),
                      position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])), confidence=float(c),
                      occluded=False, predicted=False)
               for p, li, tid, c in zip(xyz, label_index, track_ids, confidence)]
    return T[LMA](header=_header(stamp_ns, frame_id), frame_number=int(frame_number), markers=markers,
                  label_names=names, log_likelihood=float(log_likelihood), active_model=active_model,
                  latency_ms=float(latency_ms), n_unlabeled=int((label_index < 0).sum()))


def stamp_ns_of(msg: Any) -> int:
    """Header stamp in ns of an rclpy or rosbags message."""
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def markers_to_arrays(msg: Any, skip_occluded: bool = True) -> tuple[np.ndarray, list[str]]:
    """``(xyz (n, 3), label names ('' = none))`` of a LabeledMarkerArray (rclpy or rosbags);
    occluded/predicted markers (not points of this frame) are left out by default."""
    ms = [m for m in msg.markers if not (skip_occluded and (m.occluded or m.predicted))]
    xyz = np.array([(m.position.x, m.position.y, m.position.z) for m in ms], dtype=np.float64).reshape(-1, 3)
    return xyz, [str(m.label) if m.label_index >= 0 else "" for m in ms]


# ---------------------------------------------------------------------------------- scoring

def score_by_position(gt_xyz: np.ndarray, gt_labels: Sequence[str], out_xyz: np.ndarray,
                      out_labels: Sequence[str], known: set[str] | None = None,
                      tol: float = 1e-5) -> tuple[int, int, int, int]:
    """``(correct, true_markers, ghosts_unlabelled, ghosts)`` of one frame. A true marker (label
    in ``known``, default any) is correct when the output point at its position carries its
    label; a ghost ('' label) is rejected when the output point there has no label."""
    gt_xyz = np.asarray(gt_xyz, dtype=np.float64).reshape(-1, 3)
    out_xyz = np.asarray(out_xyz, dtype=np.float64).reshape(-1, 3)
    got = [""] * len(gt_labels)
    if len(gt_labels) and len(out_labels):
        d = np.abs(gt_xyz[:, None, :] - out_xyz[None, :, :]).max(-1)
        j = np.argmin(d, axis=1)
        for i, (jj, dd) in enumerate(zip(j, d[np.arange(len(j)), j])):
            if dd <= tol:
                got[i] = out_labels[jj]
    correct = total = rej = ghosts = 0
    for want, have in zip(gt_labels, got):
        if want:
            if known is None or want in known:
                total += 1
                correct += int(have == want)
        else:
            ghosts += 1
            rej += int(have == "")
    return correct, total, rej, ghosts


@dataclass
class Scorer:
    """Accumulates accuracy of labelled frames against ground-truth frames, matched by stamp
    (either may arrive first). ``known``: the model's label names (others are not scored)."""

    known: set[str] | None = None
    correct: int = 0
    total: int = 0
    ghosts_rejected: int = 0
    ghosts: int = 0
    frames_scored: int = 0
    #: (stamp ns, correct, true markers) of every scored frame, in scoring order
    per_frame: list = field(default_factory=list)
    _gt: dict = field(default_factory=dict)
    _out: dict = field(default_factory=dict)

    def add_truth(self, stamp_ns: int, xyz: np.ndarray, labels: Sequence[str]) -> None:
        if stamp_ns in self._out:
            self._score(stamp_ns, self._out.pop(stamp_ns), (xyz, labels))
        else:
            self._gt[stamp_ns] = (xyz, labels)

    def add_output(self, stamp_ns: int, xyz: np.ndarray, labels: Sequence[str]) -> None:
        if stamp_ns in self._gt:
            self._score(stamp_ns, (xyz, labels), self._gt.pop(stamp_ns))
        else:
            self._out[stamp_ns] = (xyz, labels)

    def _score(self, stamp_ns: int, out, gt) -> None:
        c, t, r, g = score_by_position(gt[0], gt[1], out[0], out[1], self.known)
        self.per_frame.append((stamp_ns, c, t))
        self.correct += c
        self.total += t
        self.ghosts_rejected += r
        self.ghosts += g
        self.frames_scored += 1

    @property
    def accuracy(self) -> float:
        return self.correct / self.total if self.total else float("nan")

    @property
    def ghost_rejection(self) -> float:
        return self.ghosts_rejected / self.ghosts if self.ghosts else float("nan")


# --------------------------------------------------------------------------------- writing

def write_bag(stream: CorruptedStream, out: str | Path, storage: str = "mcap", frame_id: str = "mocap",
              ids: bool = True, start_time: float = DEFAULT_START_S, rate_hz: float | None = None,
              ground_truth: bool = True, force: bool = False) -> dict:
    """Write a corrupted stream as a bag (``/markers/unlabeled`` + ``/markers/ground_truth``).
    ``rate_hz`` re-times the frames (default: the stream's rate). Returns a summary dict."""
    from rosbags.rosbag2 import Writer

    plugin = _storage_plugin(storage)
    out = _prepare_out(out, force)
    ts = typestore()
    rate = float(rate_hz or stream.rate)
    if not rate > 0:
        raise BagError("rate must be positive")
    t0 = int(round(start_time * 1e9))
    n_points = n_ghosts = 0
    with Writer(out, version=9, storage_plugin=plugin) as w:
        qos = [_reliable_qos()]
        c_cloud = w.add_connection(TOPIC_UNLABELED, PC2, typestore=ts, offered_qos_profiles=qos)
        c_gt = w.add_connection(TOPIC_GROUND_TRUTH, LMA, typestore=ts, offered_qos_profiles=qos) \
            if ground_truth else None
        for k, f in enumerate(stream):
            t = t0 + int(round(k * 1e9 / rate))
            w.write(c_cloud, t, ts.serialize_cdr(cloud_message(f.xyz, t, frame_id, f.ids if ids else None), PC2))
            if c_gt is not None:
                msg = marker_array_message(t, frame_id, f.index, f.xyz, f.truth, stream.names, f.ids,
                                           (f.truth >= 0).astype(float))
                w.write(c_gt, t, ts.serialize_cdr(msg, LMA))
            n_points += f.n
            n_ghosts += f.n_ghosts
    F = len(stream)
    return dict(out=str(out), storage=storage, frames=F, rate_hz=rate, duration_s=F / rate,
                start_time_s=t0 / 1e9, labels=list(stream.names), points_per_frame=n_points / max(F, 1),
                ghosts_per_frame=n_ghosts / max(F, 1), occluded_per_frame=float(stream.occluded.sum()) / max(F, 1),
                ids=bool(ids), topics=[TOPIC_UNLABELED] + ([TOPIC_GROUND_TRUTH] if ground_truth else []),
                source=stream.source, corruption=dict(stream.settings))


# --------------------------------------------------------------------------------- reading

@dataclass
class RawMessage:
    topic: str
    msgtype: str
    t_ns: int          # bag (log) time
    data: bytes        # CDR, as recorded


def bag_info(path: str | Path) -> dict:
    """Topics (type, count), duration, storage and message count of a bag."""
    r = _reader(path)
    try:
        topics = {c.topic: dict(type=c.msgtype, count=c.msgcount) for c in r.connections}
        return dict(path=str(path), storage=bag_storage(path), messages=r.message_count,
                    start_s=r.start_time / 1e9 if r.message_count else 0.0,
                    duration_s=(r.end_time - r.start_time) / 1e9 if r.message_count else 0.0, topics=topics)
    finally:
        r.close()


def bag_storage(path: str | Path) -> str:
    """``mcap`` or ``sqlite3``: the storage of a bag directory (from its files)."""
    p = Path(path)
    files = [p] if p.is_file() else list(p.iterdir())
    return "mcap" if any(f.suffix == ".mcap" for f in files) else "sqlite3"


def _reader(path):
    from rosbags.rosbag2 import Reader, ReaderError
    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such bag")
    try:
        r = Reader(p)
        r.open()
    except ReaderError as e:
        raise BagError(f"{p}: not a readable rosbag2 bag ({e})") from None
    return r


def _select(connections, topics: Iterable[str] | None):
    if topics is None:
        return list(connections)
    want = {topic_name(t) for t in topics}
    have = {c.topic for c in connections}
    missing = want - have
    if missing:
        raise BagError(f"topics not in the bag: {', '.join(sorted(missing))} (have {', '.join(sorted(have))})")
    return [c for c in connections if c.topic in want]


def read_raw(path: str | Path, topics: Iterable[str] | None = None) -> list[RawMessage]:
    """All messages (optionally of some topics) in bag-time order, as CDR bytes."""
    r = _reader(path)
    try:
        conns = _select(r.connections, topics)
        return [RawMessage(c.topic, c.msgtype, int(t), bytes(raw)) for c, t, raw in r.messages(connections=conns)]
    finally:
        r.close()


def read_messages(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, Any]]:
    """``(topic, bag time ns, rosbags message)`` in bag-time order."""
    ts = typestore()
    r = _reader(path)
    try:
        conns = _select(r.connections, topics)
        for c, t, raw in r.messages(connections=conns):
            yield c.topic, int(t), ts.deserialize_cdr(raw, c.msgtype)
    finally:
        r.close()


# -------------------------------------------------------------------------------- labeling

def _percentiles(v) -> dict:
    v = np.asarray(v, dtype=float)
    if not v.size:
        return dict(p50=float("nan"), p99=float("nan"), max=float("nan"), mean=float("nan"))
    return dict(p50=float(np.percentile(v, 50)), p99=float(np.percentile(v, 99)), max=float(v.max()),
                mean=float(v.mean()))


def _names_of(labels: np.ndarray, names: Sequence[str]) -> list:
    return [names[i] if i >= 0 else "" for i in labels]


def _open_labeled_writer(out_path, force: bool, storage: str, conns, ts):
    """A rosbags writer for ``label_bag``: the input's connections copied, plus the outputs."""
    from rosbags.rosbag2 import Writer
    out = _prepare_out(out_path, force)
    writer = Writer(out, version=9, storage_plugin=_storage_plugin(storage))
    writer.open()
    qos = [_reliable_qos()]
    copy = {c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest,
                                        offered_qos_profiles=qos) for c in conns}
    c_lab = writer.add_connection(TOPIC_LABELED, LMA, typestore=ts, offered_qos_profiles=qos)
    c_cloud = writer.add_connection(TOPIC_LABELED_CLOUD, PC2, typestore=ts, offered_qos_profiles=qos)
    return writer, copy, c_lab, c_cloud


def label_bag(model, in_path: str | Path, out_path: str | Path | None, settings=None, storage: str | None = None,
              topic: str = TOPIC_UNLABELED, force: bool = False,
              progress: Callable[[int, int], None] | None = None,
              on_frame: Callable[[np.ndarray, Any, int], None] | None = None) -> dict:
    """Label every cloud of ``topic`` with a :class:`StreamLabeler` (header stamps as time),
    write the input topics plus ``/markers/labeled`` and ``/markers/labeled_cloud`` to
    ``out_path`` (None: write nothing) and score against ``/markers/ground_truth`` when present.
    ``on_frame(xyz, result, stamp_ns)`` sees every labelled cloud (e.g. to write a labelled C3D).
    Returns a summary dict (accuracy, ghost_rejection, latency_ms {p50, p99, max, mean}, fps, ...;
    for a model with anonymous points, ``anonymous_points``: whether the bag shows them,
    :mod:`~dtm_labeler.labeling.anonymous_presence` -- ``dtm-bag label`` labels it again without
    them where it does not)."""
    from ..labeling.anonymous_presence import anonymous_presence
    from ..labeling.stream import StreamLabeler
    from .pointcloud import complete_ids, read_points_xyz

    ts, labeler, names = typestore(), StreamLabeler(model, settings), list(model.labels)
    scorer, topic, r = Scorer(known=set(names)), topic_name(topic), _reader(in_path)
    writer, lat, resets, n_frames = None, [], 0, 0
    try:
        storage = storage or bag_storage(in_path)
        conns = list(r.connections)
        if not any(c.topic == topic for c in conns):
            raise BagError(f"{in_path}: no topic {topic} (have {', '.join(c.topic for c in conns)})")
        total = sum(c.msgcount for c in conns if c.topic == topic)
        if out_path is not None:
            writer, copy, c_lab, c_cloud = _open_labeled_writer(out_path, force, storage, conns, ts)
        t_start = time.perf_counter()
        for c, t, raw in r.messages():
            if writer is not None:
                writer.write(copy[c.id], t, raw)
            if c.topic == TOPIC_GROUND_TRUTH and c.msgtype == LMA:
                m = ts.deserialize_cdr(raw, LMA)
                scorer.add_truth(stamp_ns_of(m), *markers_to_arrays(m))
                continue
            if c.topic != topic:
                continue
            msg = ts.deserialize_cdr(raw, c.msgtype)
            xyz, ids = read_points_xyz(msg)
            stamp = stamp_ns_of(msg)
            res = labeler.process(xyz, stamp * 1e-9, ids=complete_ids(ids))
            if on_frame is not None:
                on_frame(xyz, res, stamp)
            lat.append(res.latency_ms)
            resets += bool(res.reset)
            lab = np.asarray(res.labels)
            scorer.add_output(stamp, xyz.astype(np.float32).astype(np.float64), _names_of(lab, names))
            if writer is not None:
                frame_id = msg.header.frame_id
                out_msg = marker_array_message(stamp, frame_id, n_frames, xyz, lab, names, res.track_ids,
                                               res.confidence, res.log_likelihood, "", res.latency_ms)
                writer.write(c_lab, t, ts.serialize_cdr(out_msg, LMA))
                writer.write(c_cloud, t, ts.serialize_cdr(
                    labeled_cloud_message(xyz, lab, res.confidence, stamp, frame_id), PC2))
            n_frames += 1
            if progress is not None:
                progress(n_frames, total)
        wall = time.perf_counter() - t_start
    finally:
        r.close()
        if writer is not None:
            writer.close()
    s = settings or labeler.settings
    presence = anonymous_presence(model, labeler.label_frames, n_frames)
    return dict(({"anonymous_points": presence.as_dict()} if presence is not None else {}),
                bag=str(in_path), out=None if out_path is None else str(out_path), frames=n_frames,
                labels=len(names), method=s.method, mode=s.mode, window=s.window,
                accuracy=scorer.accuracy, scored_frames=scorer.frames_scored, true_markers=scorer.total,
                ghost_rejection=scorer.ghost_rejection, ghosts=scorer.ghosts, resets=resets,
                latency_ms=_percentiles(lat), fps=n_frames / wall if wall > 0 else float("nan"),
                seconds=wall)
