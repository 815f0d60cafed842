"""RViz markers for a labelled frame (``markers/visualization``), built without a node.

One :class:`visualization_msgs.msg.MarkerArray` per frame, in the input's header (stamp and
frame_id), namespaces under ``ns`` (default ``dtm_labeler``):

* ``<ns>/labelled``  id 0, SPHERE_LIST: labelled points, one colour per label (alpha grows with
  the label's confidence);
* ``<ns>/unlabelled`` id 0, SPHERE_LIST: unlabelled / ghost points, small and grey;
* ``<ns>/skeleton``  id 0, LINE_LIST: the model's structure edges (``structure.edges()``)
  between labelled points;
* ``<ns>/names``     id = label index, TEXT_VIEW_FACING: the label name above its point.

The set of markers is the same every frame: empty lists and labels not seen this frame are
sent as DELETE, so RViz never shows stale names without any per-topic state here. A DELETEALL
(first in the array) is added when ``delete_all`` is set -- the node does so on a model change
or a window reset.
"""
from __future__ import annotations

import colorsys
from typing import Any, Iterable, Optional, Sequence, Tuple

import numpy as np

__all__ = ["label_colors", "build_marker_array", "delete_all_array", "NAMESPACES"]

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
    """The MarkerArray of one labelled frame.

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
    from visualization_msgs.msg import Marker, MarkerArray
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    labels = np.asarray(labels, dtype=np.int64).reshape(-1)
    conf = np.asarray(confidence, dtype=np.float64).reshape(-1)
    M = len(label_names)
    if labels.shape[0] != xyz.shape[0] or conf.shape[0] != xyz.shape[0]:
        raise ValueError(f"labels {labels.shape} and confidence {conf.shape} must match xyz {xyz.shape}")
    cols = label_colors(M) if colors is None else np.asarray(colors, dtype=np.float64)
    finite = np.isfinite(xyz).all(1)
    valid = finite & (labels >= 0) & (labels < M)

    # one point per label: the most confident one carrying it
    point_of = np.full(M, -1, dtype=np.int64)
    idx = np.flatnonzero(valid)
    if idx.size:
        order = idx[np.lexsort((-conf[idx], labels[idx]))]
        first = np.ones(order.size, dtype=bool)
        first[1:] = labels[order[1:]] != labels[order[:-1]]
        point_of[labels[order[first]]] = order[first]

    arr = MarkerArray()
    if delete_all:
        arr.markers.append(_marker(header, ns, 0, Marker.SPHERE_LIST, Marker.DELETEALL, (1.0, 1.0, 1.0)))
    s = float(scale)

    # labelled spheres
    m = _marker(header, f"{ns}/labelled", 0, Marker.SPHERE_LIST,
                Marker.ADD if idx.size else Marker.DELETE, (s, s, s))
    if idx.size:
        m.points = [_point(p) for p in xyz[idx].tolist()]
        c = cols[labels[idx]].copy()
        c[:, 3] = 0.35 + 0.65 * np.clip(np.nan_to_num(conf[idx]), 0.0, 1.0)
        m.colors = [_color(v) for v in c.tolist()]
        m.color = _color(cols[labels[idx[0]]])
    arr.markers.append(m)

    # unlabelled spheres
    un = np.flatnonzero(finite & ~valid)
    m = _marker(header, f"{ns}/unlabelled", 0, Marker.SPHERE_LIST,
                Marker.ADD if un.size else Marker.DELETE, (0.6 * s, 0.6 * s, 0.6 * s))
    m.color = _color(_GREY)
    if un.size:
        m.points = [_point(p) for p in xyz[un].tolist()]
    arr.markers.append(m)

    # skeleton
    segs = []
    for a, b in sorted(edges or ()):
        if 0 <= a < M and 0 <= b < M and point_of[a] >= 0 and point_of[b] >= 0:
            segs.append(xyz[point_of[a]])
            segs.append(xyz[point_of[b]])
    m = _marker(header, f"{ns}/skeleton", 0, Marker.LINE_LIST,
                Marker.ADD if segs else Marker.DELETE, (0.25 * s, 0.0, 0.0))
    m.color = _color(_EDGE)
    if segs:
        m.points = [_point(p) for p in np.asarray(segs).tolist()]
    arr.markers.append(m)

    # names
    for lab in range(M):
        i = point_of[lab]
        m = _marker(header, f"{ns}/names", lab, Marker.TEXT_VIEW_FACING,
                    Marker.ADD if i >= 0 else Marker.DELETE, (0.0, 0.0, 0.8 * s))
        if i >= 0:
            m.text = str(label_names[lab])
            m.pose.position = _point(xyz[i] + np.array([0.0, 0.0, 1.2 * s]))
            m.color = _color(cols[lab])
        arr.markers.append(m)
    return arr
