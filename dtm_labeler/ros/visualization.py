"""RViz markers for a labelled frame (``markers/visualization``), built without a node.

One :class:`visualization_msgs.msg.MarkerArray` per frame, in the input's header (stamp and
frame_id), namespaces under ``ns`` (default ``dtm_labeler``):

* ``<ns>/labelled``  id 0, SPHERE_LIST: labelled points, one colour per label (alpha grows with
  the label's confidence);
* ``<ns>/unlabelled`` id 0, SPHERE_LIST: unlabelled / ghost points, small and grey;
* ``<ns>/skeleton``  id 0, LINE_LIST: the model's structure edges (``structure.edges()``)
  between labelled points;
* ``<ns>/names``     id = label index, TEXT_VIEW_FACING: the label name above its point.

Every marker carries ``lifetime_s`` (0 = forever): with a lifetime, RViz drops the markers of a
node that stopped publishing instead of showing its last frame for ever.

The set of markers is the same every frame: empty lists and labels not seen this frame are
sent as DELETE, so RViz never shows stale names without any per-topic state here. A DELETEALL
(first in the array) is added when ``delete_all`` is set -- the node does so on a model change
or a window reset.
"""
from __future__ import annotations

import colorsys
from typing import Any, Iterable, Optional, Sequence, Tuple

import numpy as np

__all__ = ["label_colors", "build_marker_array", "MarkerArrayBuilder", "delete_all_array", "NAMESPACES"]

NAMESPACES = ("labelled", "unlabelled", "skeleton", "names")
_GREY = (0.6, 0.6, 0.6, 0.6)
_EDGE = (0.9, 0.9, 0.9, 0.8)


def label_colors(n: int) -> np.ndarray:
    """``(n, 4)`` RGBA in [0, 1]: well separated hues (golden-angle steps), opaque."""
    out = np.ones((max(int(n), 0), 4))
    for i in range(out.shape[0]):
        h = (i * 0.618033988749895) % 1.0
        out[i, :3] = colorsys.hsv_to_rgb(h, 0.85, 0.95)
    return out


def _color(rgba: Sequence[float]):
    from std_msgs.msg import ColorRGBA
    c = ColorRGBA()
    c.r, c.g, c.b, c.a = (float(v) for v in rgba)
    return c


def _point(p: Sequence[float]):
    from geometry_msgs.msg import Point
    q = Point()
    q.x, q.y, q.z = (float(v) for v in p)
    return q


def _marker(header, ns: str, mid: int, mtype: int, action: int, scale: Tuple[float, float, float]):
    from visualization_msgs.msg import Marker
    m = Marker()
    if header is not None:
        m.header = header
    m.ns = ns
    m.id = int(mid)
    m.type = mtype
    m.action = action
    m.pose.orientation.w = 1.0
    m.scale.x, m.scale.y, m.scale.z = (float(s) for s in scale)
    m.frame_locked = False
    return m


def delete_all_array(header: Any = None, ns: str = "dtm_labeler"):
    """A MarkerArray holding a single DELETEALL marker."""
    from visualization_msgs.msg import Marker, MarkerArray
    arr = MarkerArray()
    arr.markers.append(_marker(header, ns, 0, Marker.SPHERE_LIST, Marker.DELETEALL, (1.0, 1.0, 1.0)))
    return arr


def build_marker_array(header: Any, xyz: Any, labels: Any, confidence: Any, label_names: Sequence[str],
                       edges: Optional[Iterable[Tuple[int, int]]] = None, *, scale: float = 0.05,
                       ns: str = "dtm_labeler", delete_all: bool = False,
                       colors: Optional[np.ndarray] = None):
    """The MarkerArray of one labelled frame (a fresh :class:`MarkerArrayBuilder` each call).

    Args:
        header: std_msgs Header to copy (the input cloud's).
        xyz: ``(n, 3)`` positions (non-finite points are skipped).
        labels: ``(n,)`` label index per point, -1 = unlabelled.
        confidence: ``(n,)`` in [0, 1].
        label_names: the model's labels (index order).
        edges: label index pairs to draw (the model's ``structure.edges()``).
        scale: sphere diameter in metres (text height and line width derive from it).
        delete_all: start the array with a DELETEALL marker.
        colors: optional ``(M, 4)`` RGBA per label (default :func:`label_colors`).
    """
    return MarkerArrayBuilder(label_names, edges, scale=scale, ns=ns, colors=colors).build(
        header, xyz, labels, confidence, delete_all=delete_all)


class MarkerArrayBuilder:
    """Builds the per-frame MarkerArray, reusing its message objects between frames.

    Constructing ``visualization_msgs/Marker`` objects dominates the cost in Python (about
    70 us each); the builder makes every marker once and only updates positions, colours and
    actions afterwards. The returned array is the same object every call: publish it (rclpy
    serialises it synchronously) before building the next frame.
    """

    def __init__(self, label_names: Sequence[str], edges: Optional[Iterable[Tuple[int, int]]] = None, *,
                 scale: float = 0.05, ns: str = "dtm_labeler", colors: Optional[np.ndarray] = None,
                 lifetime_s: float = 0.0):
        from visualization_msgs.msg import Marker
        self.lifetime_s = float(lifetime_s)
        self.names = [str(x) for x in label_names]
        M = len(self.names)
        self.edges = sorted((int(a), int(b)) for a, b in (edges or ()) if 0 <= a < M and 0 <= b < M)
        self.scale = float(scale)
        self.ns = ns
        self.colors = label_colors(M) if colors is None else np.asarray(colors, dtype=np.float64)
        s = self.scale
        self._delete_all = _marker(None, ns, 0, Marker.SPHERE_LIST, Marker.DELETEALL, (1.0, 1.0, 1.0))
        self._labelled = _marker(None, f"{ns}/labelled", 0, Marker.SPHERE_LIST, Marker.ADD, (s, s, s))
        self._unlabelled = _marker(None, f"{ns}/unlabelled", 0, Marker.SPHERE_LIST, Marker.ADD,
                                   (0.6 * s, 0.6 * s, 0.6 * s))
        self._unlabelled.color = _color(_GREY)
        self._skeleton = _marker(None, f"{ns}/skeleton", 0, Marker.LINE_LIST, Marker.ADD, (0.25 * s, 0.0, 0.0))
        self._skeleton.color = _color(_EDGE)
        self._texts = []
        for lab in range(M):
            m = _marker(None, f"{ns}/names", lab, Marker.TEXT_VIEW_FACING, Marker.ADD, (0.0, 0.0, 0.8 * s))
            m.text = self.names[lab]
            m.color = _color(self.colors[lab])
            self._texts.append(m)
        self._label_colors = [_color(c) for c in self.colors]
        sec = int(self.lifetime_s)
        for m in [self._labelled, self._unlabelled, self._skeleton, *self._texts]:
            m.lifetime.sec, m.lifetime.nanosec = sec, int(round((self.lifetime_s - sec) * 1e9))
        self._points: list = []
        self._colors: list = []

    def _pool(self, k: int) -> list:
        while len(self._points) < k:
            self._points.append(_point((0.0, 0.0, 0.0)))
        return self._points

    def _fill(self, xyz: np.ndarray, offset: int) -> list:
        pool = self._pool(offset + xyz.shape[0])
        out = pool[offset:offset + xyz.shape[0]]
        for q, (x, y, z) in zip(out, xyz.tolist()):
            q.x = x
            q.y = y
            q.z = z
        return out

    def _point_per_label(self, labels: np.ndarray, conf: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """(M,) the most confident point carrying each label, -1 for none."""
        point_of = np.full(len(self.names), -1, dtype=np.int64)
        idx = np.flatnonzero(valid)
        if idx.size:
            order = idx[np.lexsort((-conf[idx], labels[idx]))]
            first = np.ones(order.size, dtype=bool)
            first[1:] = labels[order[1:]] != labels[order[:-1]]
            point_of[labels[order[first]]] = order[first]
        return point_of

    def _labelled_spheres(self, xyz: np.ndarray, labels: np.ndarray, conf: np.ndarray, idx: np.ndarray):
        """The SPHERE_LIST of labelled points (colour per label, alpha by confidence)."""
        from visualization_msgs.msg import Marker
        m = self._labelled
        m.action = Marker.ADD if idx.size else Marker.DELETE
        m.points = self._fill(xyz[idx], 0)
        while len(self._colors) < idx.size:
            self._colors.append(_color((1.0, 1.0, 1.0, 1.0)))
        cols = self.colors[labels[idx]].copy()
        cols[:, 3] = 0.35 + 0.65 * np.clip(np.nan_to_num(conf[idx]), 0.0, 1.0)
        for c, (r, g, b, a) in zip(self._colors, cols.tolist()):
            c.r = r
            c.g = g
            c.b = b
            c.a = a
        m.colors = self._colors[:idx.size]
        if idx.size:
            m.color = self._label_colors[labels[idx[0]]]
        return m

    def build(self, header: Any, xyz: Any, labels: Any, confidence: Any, delete_all: bool = False):
        from visualization_msgs.msg import Marker, MarkerArray
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        labels = np.asarray(labels, dtype=np.int64).reshape(-1)
        conf = np.asarray(confidence, dtype=np.float64).reshape(-1)
        M = len(self.names)
        if labels.shape[0] != xyz.shape[0] or conf.shape[0] != xyz.shape[0]:
            raise ValueError(f"labels {labels.shape} and confidence {conf.shape} must match xyz {xyz.shape}")
        finite = np.isfinite(xyz).all(1)
        valid = finite & (labels >= 0) & (labels < M)

        point_of = self._point_per_label(labels, conf, valid)
        idx = np.flatnonzero(valid)
        markers = []
        if delete_all:
            self._delete_all.header = header if header is not None else self._delete_all.header
            markers.append(self._delete_all)
        markers.append(self._labelled_spheres(xyz, labels, conf, idx))
        used = idx.size
        # unlabelled spheres
        un = np.flatnonzero(finite & ~valid)
        m = self._unlabelled
        m.action = Marker.ADD if un.size else Marker.DELETE
        m.points = self._fill(xyz[un], used)
        used += un.size
        markers.append(m)
        # skeleton
        ends = [(point_of[a], point_of[b]) for a, b in self.edges if point_of[a] >= 0 and point_of[b] >= 0]
        m = self._skeleton
        m.action = Marker.ADD if ends else Marker.DELETE
        seg = xyz[np.asarray(ends, dtype=np.int64).reshape(-1)] if ends else np.zeros((0, 3))
        m.points = self._fill(seg, used)
        markers.append(m)
        # names
        lift = 1.2 * self.scale
        for lab, m in enumerate(self._texts):
            i = point_of[lab]
            if i >= 0:
                m.action = Marker.ADD
                p = m.pose.position
                p.x, p.y, p.z = float(xyz[i, 0]), float(xyz[i, 1]), float(xyz[i, 2]) + lift
            else:
                m.action = Marker.DELETE
            markers.append(m)
        if header is not None:
            for m in markers:
                m.header = header
        arr = MarkerArray()
        arr.markers = markers
        return arr
