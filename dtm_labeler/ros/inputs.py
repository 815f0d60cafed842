"""The node's input messages as numpy: one decoder per ``input_type``, no node needed.

=====================  =================================  ==========================================
``input_type``         message                            published by (topic, frame)
=====================  =================================  ==========================================
``pointcloud2``        sensor_msgs/PointCloud2            IMRCLab motion_capture_tracking
                                                          (``pointCloud``, ``world``), bags of
                                                          ``dtm-bag make``, any PCL pipeline
``mocap4r2_markers``   mocap4r2_msgs/Markers              mocap4r2 OptiTrack / Qualisys / Vicon
                                                          drivers (``markers``, ``map``/``vicon_world``)
``pointcloud``         sensor_msgs/PointCloud (v1)        natnet_ros2 (``pointcloud``, ``world``)
=====================  =================================  ==========================================

Every decoder returns a :class:`Decoded`: ``xyz`` (n, 3) float64 in the message's order (NaN kept:
the node counts and drops them), ``ids`` int64 track ids with :data:`~.pointcloud.NO_ID` (-1) for
a point without one, or None when the input carries no ids.

Track ids of mocap4r2 markers (``mocap4r2_ids``): the drivers fill ``marker_index`` with the
marker's position in the frame's list (OptiTrack, Qualisys), which is not a track id -- the
same index names another marker when one appears or drops out -- and ``marker_name`` with the
system's own marker names (Vicon: labelled subject markers, stable from frame to frame). So
``auto`` takes names as ids (``USE_NAME``/``USE_BOTH``, every name non-empty and unique in the
frame) and ignores indices; ``index`` takes ``marker_index`` (for a driver whose indices persist);
``none`` lets the tracker associate every point by position. A name becomes the id
``crc32(name) & 0x7fffffff`` (stable across processes). The Vicon driver sends a marker it does
not see at exactly (0, 0, 0): such points are read as not seen (NaN) and counted.

mocap4r2_msgs is optional: it is imported on first use, and :class:`InputUnavailable` says how
to get it. rclpy builds one Python object per marker / Point32 of these messages; the decoders
read them with one list comprehension per frame (about 0.4 us per marker), PointCloud2 with no
per-point Python at all.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from ..labeling.config import INPUT_TYPES, MOCAP4R2_IDS
from .pointcloud import NO_ID, PointCloudError, read_points_xyz

__all__ = ["INPUT_TYPES", "MOCAP4R2_IDS", "MOCAP4R2_INSTALL", "Decoded", "InputUnavailable", "message_class",
           "decode", "decode_pointcloud", "decode_markers", "name_id"]

MOCAP4R2_INSTALL = ("mocap4r2_msgs is not installed: on a ROS install `sudo apt install "
                    "ros-jazzy-mocap4r2-msgs` (or build it from source in your workspace); in this "
                    "project's venv `bash scripts/setup.sh` builds it from vendor/mocap4r2_msgs")
_USE_NAME, _USE_INDEX, _USE_BOTH = 0, 1, 2


class InputUnavailable(RuntimeError):
    """The message package of an input type is not installed (the message says what to do)."""


@dataclass(frozen=True)
class Decoded:
    xyz: np.ndarray                     # (n, 3) float64
    ids: Optional[np.ndarray]           # (n,) int64, NO_ID = none; None = the input has no ids
    frame_number: Optional[int] = None  # the driver's frame counter (mocap4r2)
    origin_points: int = 0              # points at exactly (0, 0, 0) read as not seen


def message_class(input_type: str) -> type:
    """The message class subscribed to for ``input_type`` (raises :class:`InputUnavailable`)."""
    if input_type == "pointcloud2":
        from sensor_msgs.msg import PointCloud2
        return PointCloud2
    if input_type == "pointcloud":
        from sensor_msgs.msg import PointCloud
        return PointCloud
    if input_type == "mocap4r2_markers":
        try:
            from mocap4r2_msgs.msg import Markers
        except ImportError:
            raise InputUnavailable(MOCAP4R2_INSTALL) from None
        return Markers
    raise ValueError(f"input_type must be one of {', '.join(INPUT_TYPES)}, got {input_type!r}")


def decode(input_type: str, msg: Any, mocap4r2_ids: str = "auto") -> Decoded:
    """Decode one input message (raises :class:`~.pointcloud.PointCloudError` with the reason)."""
    if input_type == "pointcloud2":
        xyz, ids = read_points_xyz(msg)
        return Decoded(xyz, ids)
    if input_type == "pointcloud":
        return decode_pointcloud(msg)
    return decode_markers(msg, mocap4r2_ids)


def decode_pointcloud(msg: Any) -> Decoded:
    """sensor_msgs/PointCloud: ``points`` (Point32) and, when present, a channel named ``id``
    (float values holding integral ids; -1 or NaN = none)."""
    pts = msg.points
    xyz = np.array([(p.x, p.y, p.z) for p in pts], dtype=np.float64).reshape(-1, 3)
    ids = None
    for ch in msg.channels:
        if ch.name != "id":
            continue
        v = np.asarray(ch.values, dtype=np.float64)
        if v.shape[0] != xyz.shape[0]:
            raise PointCloudError(f"channel 'id' has {v.shape[0]} values for {xyz.shape[0]} points")
        none = ~np.isfinite(v) | (v == -1.0)
        w = np.where(none, 0.0, v)
        if np.any(w != np.round(w)) or (w.size and w.min() < 0):
            raise PointCloudError("channel 'id' holds values that are not track ids (need integral values >= 0)")
        ids = np.where(none, NO_ID, w).astype(np.int64)
    return Decoded(xyz, ids)


def name_id(name: str) -> int:
    """The track id of a marker name: ``crc32(utf-8) & 0x7fffffff`` (stable across processes)."""
    return zlib.crc32(name.encode("utf-8")) & 0x7FFFFFFF


def decode_markers(msg: Any, ids: str = "auto") -> Decoded:
    """mocap4r2_msgs/Markers (see the module doc for ``ids``)."""
    if ids not in MOCAP4R2_IDS:
        raise ValueError(f"mocap4r2_ids must be one of {', '.join(MOCAP4R2_IDS)}, got {ids!r}")
    markers = msg.markers
    rows = [(m.translation.x, m.translation.y, m.translation.z) for m in markers]
    xyz = np.array(rows, dtype=np.float64).reshape(-1, 3)
    origin = (xyz == 0.0).all(1)
    n_origin = int(origin.sum())
    if n_origin:
        xyz[origin] = np.nan
    track = None
    if ids != "none" and markers:
        track = _marker_ids(markers, ids)
    return Decoded(xyz, track, int(msg.frame_number), n_origin)


def _marker_ids(markers, ids: str) -> Optional[np.ndarray]:
    """Track ids from names or indices when they identify every marker of the frame, else None."""
    types = {int(m.id_type) for m in markers}
    if ids in ("auto", "name") and types <= {_USE_NAME, _USE_BOTH}:
        names = [m.marker_name for m in markers]
        if all(names) and len(set(names)) == len(names):
            return np.array([name_id(x) for x in names], dtype=np.int64)
        return None
    if ids == "index" and types <= {_USE_INDEX, _USE_BOTH}:
        idx = np.array([m.marker_index for m in markers], dtype=np.int64)
        if idx.min() >= 0 and np.unique(idx).size == idx.size:
            return idx
    return None
