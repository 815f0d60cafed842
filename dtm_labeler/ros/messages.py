"""The node's output messages, built from one labelled frame without a node.

Pure functions over numpy and message classes (the style of sensor_msgs_py's point_cloud2):

* :func:`labeled_marker_array` -- ``markers/labeled`` (dtm_labeler_msgs/LabeledMarkerArray): every
  input point in input order (label, confidence, track id), then one ``occluded`` + ``predicted``
  marker per model label missing this frame whose track the tracker still predicts; the node
  publishes the same message as bytes written straight from the arrays
  (:func:`labeled_marker_array_cdr`, tested against this one's serialisation);
* :func:`mocap4r2_markers` -- ``markers/labeled_mocap4r2`` (mocap4r2_msgs/Markers): every input
  point with ``marker_name`` = its label ('' when unlabelled), ``marker_index`` = its track id
  (-1 without one), ``id_type`` USE_BOTH, so mocap4r2 tools (e.g. its marker visualiser) show
  our labels unchanged;
* :func:`output_header` -- the input header with ``frame_id`` filled in or overridden.

Two small stateful helpers hold what the node carries from frame to frame:
:class:`OccludedLabels` (which track carried each label last, for predictions while the
label's marker is not seen) and :class:`VizThrottle` (RViz at most every
``visualization_period_s`` of stamps; a DELETEALL after a reset or a model change).
The labelled PointCloud2 is :func:`~.pointcloud.make_labeled_cloud`; RViz markers are
:class:`~.visualization.MarkerArrayBuilder`.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

__all__ = ["NO_TRACK", "LabelledFrame", "Occluded", "labeled_marker_array", "labeled_marker_array_cdr",
           "mocap4r2_markers",
           "output_header", "OccludedLabels", "VizThrottle"]

#: LabeledMarker.track_id of a point without a track (a non-finite point).
NO_TRACK = 0xFFFFFFFF


@dataclass
class Occluded:
    """A model label not seen this frame, at its track's predicted position."""

    label: int
    track: int
    position: np.ndarray     # (3,)


@dataclass
class LabelledFrame:
    """Everything the output messages of one frame are built from."""

    header: Any                       # std_msgs/Header of the outputs (see output_header)
    frame_number: int
    xyz: np.ndarray                   # (n, 3) input points, input order
    labels: np.ndarray                # (n,) label index, -1 = unlabelled
    confidence: np.ndarray            # (n,)
    tracks: np.ndarray                # (n,) track id, -1 = none
    names: Sequence[str]              # the model's labels
    log_likelihood: float = float("nan")
    active_model: str = ""
    latency_ms: float = 0.0
    occluded: List[Occluded] = field(default_factory=list)


def output_header(header: Any, frame_id: str, override: bool) -> Any:
    """The input header, its ``frame_id`` replaced by ``frame_id`` when it is empty (or always
    with ``override``); the input message's own header is not modified."""
    if not frame_id or (header.frame_id and not override):
        return header
    from std_msgs.msg import Header
    return Header(stamp=header.stamp, frame_id=frame_id)


def labeled_marker_array(f: LabelledFrame):
    """dtm_labeler_msgs/LabeledMarkerArray of a labelled frame."""
    from dtm_labeler_msgs.msg import LabeledMarker, LabeledMarkerArray
    names = list(f.names)
    out = LabeledMarkerArray()
    out.header = f.header
    out.frame_number = int(f.frame_number)
    out.label_names = names
    out.log_likelihood = float(f.log_likelihood)
    out.active_model = f.active_model
    markers = []
    conf = np.asarray(f.confidence, dtype=float).tolist()
    for p, lab, c, t in zip(f.xyz.tolist(), f.labels.tolist(), conf, f.tracks.tolist()):
        m = LabeledMarker()
        q = m.position
        q.x, q.y, q.z = p
        if lab >= 0:
            m.label = names[lab]
            m.label_index = lab
            m.confidence = c
        m.track_id = NO_TRACK if t < 0 else t & 0xFFFFFFFF
        markers.append(m)
    for o in f.occluded:
        m = LabeledMarker()
        m.position.x, m.position.y, m.position.z = (float(v) for v in o.position)
        m.label, m.label_index = names[o.label], o.label
        m.track_id = o.track & 0xFFFFFFFF
        m.occluded = True
        m.predicted = True
        markers.append(m)
    out.markers = markers
    out.n_unlabeled = int(f.labels.size - np.count_nonzero(f.labels >= 0))
    out.latency_ms = float(f.latency_ms)
    return out


class _Cdr:
    """A little-endian plain-CDR writer (what rmw serialises ROS 2 messages to): primitives
    aligned to their size from the start of the payload, strings as uint32 length (with the
    terminating NUL) + bytes + NUL, sequences as uint32 count + elements."""

    HEADER = b"\x00\x01\x00\x00"        # encapsulation: CDR, little endian

    def __init__(self) -> None:
        self.parts: List[bytes] = []
        self.pos = 0

    def align(self, n: int) -> None:
        pad = -self.pos % n
        if pad:
            self.parts.append(b"\x00" * pad)
            self.pos += pad

    def put(self, fmt: str, *values, align: int = 4) -> None:
        self.align(align)
        b = struct.pack("<" + fmt, *values)
        self.parts.append(b)
        self.pos += len(b)

    def raw(self, b: bytes) -> None:
        self.parts.append(b)
        self.pos += len(b)

    def string(self, text: str | bytes) -> None:
        b = text.encode() if isinstance(text, str) else text
        self.put("I", len(b) + 1)
        self.raw(b + b"\x00")

    def bytes(self) -> bytes:
        return self.HEADER + b"".join(self.parts)


def _marker_struct(name: bytes, pos: int) -> Tuple[struct.Struct, int]:
    """The packing of one LabeledMarker with label ``name`` written at payload offset ``pos``
    (its paddings depend on ``pos`` mod 8 and the label's length), and the offset after it."""
    p4 = pos + (-pos % 4)
    q = p4 + 4 + len(name) + 1                   # label: length, bytes, NUL
    a = q + (-q % 4)                             # label_index, track_id
    b = a + 8 + (-(a + 8) % 8)                   # position (3 x float64)
    fmt = f"<{p4 - pos}xI{len(name) + 1}s{a - q}xiI{b - a - 8}xdddf??"
    return struct.Struct(fmt), b + 30            # + confidence (float32), occluded, predicted


_MARKER_STRUCTS: Dict[Tuple[bytes, int], Tuple[struct.Struct, int]] = {}


def labeled_marker_array_cdr(f: LabelledFrame) -> bytes:
    """The serialised ``dtm_labeler_msgs/LabeledMarkerArray`` of a labelled frame -- what
    ``rclpy.serialization.serialize_message(labeled_marker_array(f))`` gives (padding bytes
    zeroed), written straight from the arrays with one packing per marker (a publisher takes
    the bytes as they are): building ~45 message objects and converting them costs 0.6 ms per
    frame at 41 markers, this about a tenth of it."""
    names = [n.encode() for n in f.names]
    w = _Cdr()
    st = f.header.stamp
    w.put("iI", int(st.sec), int(st.nanosec))
    w.string(f.header.frame_id)
    w.put("Q", int(f.frame_number), align=8)
    xyz = np.asarray(f.xyz, dtype=float).tolist()
    conf = np.asarray(f.confidence, dtype=np.float32).tolist()
    labels, tracks = f.labels.tolist(), f.tracks.tolist()
    w.put("I", len(labels) + len(f.occluded))
    rows = [(names[lab] if lab >= 0 else b"", lab if lab >= 0 else -1, NO_TRACK if t < 0 else t & 0xFFFFFFFF,
             p, c if lab >= 0 else 0.0, False) for p, lab, c, t in zip(xyz, labels, conf, tracks)]
    rows += [(names[o.label], o.label, o.track & 0xFFFFFFFF, [float(v) for v in o.position], 0.0, True)
             for o in f.occluded]
    cache, parts, pos = _MARKER_STRUCTS, w.parts, w.pos
    for name, lab, track, p, c, occ in rows:
        key = (name, pos % 8)
        packing = cache.get(key)
        if packing is None:
            packing = cache[key] = _marker_struct(name, pos % 8)
        s, end = packing
        parts.append(s.pack(len(name) + 1, name + b"\x00", lab, track, p[0], p[1], p[2], c, occ, occ))
        pos += end - pos % 8
    w.pos = pos
    w.put("I", len(names))
    for n in names:
        w.string(n)
    w.put("d", float(f.log_likelihood), align=8)
    w.string(f.active_model)
    w.put("fI", float(f.latency_ms), int(f.labels.size - np.count_nonzero(f.labels >= 0)))
    return w.bytes()


def mocap4r2_markers(f: LabelledFrame):
    """mocap4r2_msgs/Markers of a labelled frame (raises ImportError without mocap4r2_msgs)."""
    from mocap4r2_msgs.msg import Marker, Markers
    names = list(f.names)
    out = Markers()
    out.header = f.header
    out.frame_number = int(f.frame_number) & 0xFFFFFFFF
    markers = []
    for p, lab, t in zip(f.xyz.tolist(), f.labels.tolist(), f.tracks.tolist()):
        m = Marker()
        m.id_type = Marker.USE_BOTH
        m.marker_index = int(t) if 0 <= t < 2 ** 31 else -1
        m.marker_name = names[lab] if lab >= 0 else ""
        m.translation.x, m.translation.y, m.translation.z = p
        markers.append(m)
    out.markers = markers
    return out


class OccludedLabels:
    """Which track carried each label last, so a label whose marker is not seen this frame can
    be published at its track's predicted position while the tracker still coasts it."""

    def __init__(self) -> None:
        self._track_of: Dict[int, int] = {}

    def clear(self) -> None:
        self._track_of = {}

    def step(self, labels: np.ndarray, tracks: np.ndarray, predict: Callable[[int], np.ndarray],
             enabled: bool = True) -> List[Occluded]:
        """Update with this frame's (labels, tracks); return the occluded labels to publish
        (``predict(track)`` gives a position, NaN when the track is gone)."""
        present = set(labels[labels >= 0].tolist())
        out: List[Occluded] = []
        if enabled and labels.size:
            seen = set(tracks.tolist())
            for lab, t in sorted(self._track_of.items()):
                if lab in present or t in seen:
                    continue
                p = np.asarray(predict(t), dtype=float)
                if np.isfinite(p).all():
                    out.append(Occluded(lab, t, p))
                else:
                    present.add(lab)          # the track is gone: forget the label below
        # a track carries at most one label; a label at most one track
        now = {int(t): int(lab) for lab, t in zip(labels.tolist(), tracks.tolist()) if lab >= 0 and t >= 0}
        self._track_of = {lab: t for lab, t in self._track_of.items() if lab not in present and t not in now}
        self._track_of.update({lab: t for t, lab in now.items()})
        return out


class VizThrottle:
    """RViz output at most every ``period`` seconds of header stamps (0 = every frame); the next
    one after :meth:`clear` (reset, model change) starts with a DELETEALL."""

    def __init__(self) -> None:
        self._last: Optional[float] = None
        self._clear = True

    def clear(self) -> None:
        self._clear = True

    def due(self, stamp: float, period: float) -> Tuple[bool, bool]:
        """``(publish now, with a DELETEALL first)``; marks the frame published when due."""
        last = self._last
        if not (self._clear or last is None or stamp < last or stamp - last >= period):
            return False, False
        delete_all, self._clear, self._last = self._clear, False, stamp
        return True, delete_all
