"""The dtm_labeler_msgs message definitions for bag tools (no build and no rclpy needed).

``rosbags`` reads and writes rosbag2 files without ROS; it needs the ``.msg`` text of custom
types. :func:`msg_text` finds it at runtime, in this order:

1. the installed package: ``share/dtm_labeler_msgs/msg`` found through the ament index
   (``AMENT_PREFIX_PATH``, full ROS installs / colcon workspaces), next to the installed
   ``dtm_labeler_msgs`` Python package (venv built by ``scripts/setup.sh``), or under
   ``sys.prefix`` -- this is what rclpy's generated types were built from;
2. the source tree: ``msg_defs/msg`` of this repository;
3. :data:`EMBEDDED_MSG_TEXT`, a copy generated from ``msg_defs/msg`` (the tests check that it
   is identical; refresh it with ``python -m dtm_labeler.ros.msg_types --write-embedded``).

:func:`register_rosbags_types` registers both types in a ``rosbags`` typestore, with type
hashes (RIHS01) equal to those of the rosidl build, so bags written with rosbags deserialize
with rclpy (and ``ros2 bag``) and vice versa.
"""
from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

__all__ = [
    "PACKAGE",
    "MSG_NAMES",
    "TYPE_NAMES",
    "EMBEDDED_MSG_TEXT",
    "msg_dir",
    "msg_text",
    "register_rosbags_types",
    "make_typestore",
]

PACKAGE = "dtm_labeler_msgs"
#: Message names in dependency order (LabeledMarkerArray uses LabeledMarker).
MSG_NAMES = ("LabeledMarker", "LabeledMarkerArray")
#: Full ROS 2 type names, as used in bags and by rosbags.
TYPE_NAMES = {name: f"{PACKAGE}/msg/{name}" for name in MSG_NAMES}

_REPO_MSG_DIR = Path(__file__).resolve().parents[2] / "msg_defs" / "msg"

# Generated from msg_defs/msg by `python -m dtm_labeler.ros.msg_types --write-embedded`;
# do not edit by hand (test_msgs.py checks it equals the .msg files).
# BEGIN EMBEDDED
EMBEDDED_MSG_TEXT: Dict[str, str] = {
    "LabeledMarker": '# One marker of a labeled motion-capture frame (dtm_labeler).\n# Either a point seen this frame (occluded = false) or a model label whose marker is not seen\n# this frame (occluded = true; position is then the tracker\'s prediction when predicted = true).\n\n# Label name from the model (e.g. "LKNE"); empty when the point is unlabeled or a ghost.\nstring label\n# Index of the label in LabeledMarkerArray.label_names; -1 (the default) = no label (unlabeled / ghost).\nint32 label_index -1\n# Track id of the point (frame-to-frame association; the input cloud\'s "id" field when given).\nuint32 track_id\n# Position in metres, in the frame of the array\'s header.frame_id.\ngeometry_msgs/Point position\n# Confidence of the label in [0, 1] (per-track vote share); 0 when unlabeled.\nfloat32 confidence\n# True when this label\'s marker is not seen this frame (position is then the prediction, if any).\nbool occluded\n# True when position is predicted (not measured this frame).\nbool predicted\n',
    "LabeledMarkerArray": '# One labeled motion-capture frame published by the dtm_labeler node (markers/labeled).\n\n# Stamp of the input cloud and its frame_id (positions are in this frame).\nstd_msgs/Header header\n# Running frame counter of the labeler (0-based, counts processed input clouds).\nuint64 frame_number\n# Labeled, unlabeled (label_index = -1) and occluded (occluded = true) markers of this frame.\nLabeledMarker[] markers\n# The model\'s label names in index order (LabeledMarker.label_index indexes this list).\nstring[] label_names\n# Log-likelihood of the published labeling under the model (log P(X|G)); natural log.\nfloat64 log_likelihood\n# Active motion model / action (e.g. "walk"); empty when the labeler has a single model.\nstring active_model\n# Processing time of this frame in milliseconds (cloud received -> labeling published).\nfloat32 latency_ms\n# Number of input points left unlabeled (rejected as ghosts / clutter) this frame.\nuint32 n_unlabeled\n',
}
# END EMBEDDED


def _has_all(d: Path) -> bool:
    return all((d / f"{name}.msg").is_file() for name in MSG_NAMES)


def _installed_msg_dirs():
    """Candidate share/dtm_labeler_msgs/msg directories of an installed build (best first)."""
    if os.environ.get("AMENT_PREFIX_PATH"):
        try:
            from ament_index_python.packages import get_package_share_directory
            yield Path(get_package_share_directory(PACKAGE)) / "msg"
        except Exception:  # not installed in that index / ament_index_python missing
            pass
    try:
        spec = importlib.util.find_spec(PACKAGE)
    except (ImportError, ValueError):
        spec = None
    if spec is not None and spec.origin:
        # <prefix>/lib/pythonX.Y/site-packages/dtm_labeler_msgs/__init__.py -> <prefix>/share/...
        for parent in Path(spec.origin).resolve().parents[1:6]:
            yield parent / "share" / PACKAGE / "msg"
    yield Path(sys.prefix) / "share" / PACKAGE / "msg"


def msg_dir() -> Tuple[Optional[Path], str]:
    """Where the .msg files are read from: ``(directory, "installed"|"source")`` or
    ``(None, "embedded")`` when neither an installed build nor the source tree is found."""
    for d in _installed_msg_dirs():
        if _has_all(d):
            return d, "installed"
    if _has_all(_REPO_MSG_DIR):
        return _REPO_MSG_DIR, "source"
    return None, "embedded"


def msg_text(name: str) -> str:
    """The ``.msg`` text of ``LabeledMarker`` or ``LabeledMarkerArray`` (see module doc for where
    it comes from). Also accepts the full type name ``dtm_labeler_msgs/msg/<Name>``."""
    short = name.rsplit("/", 1)[-1]
    if short not in MSG_NAMES:
        raise KeyError(f"{name!r} is not a {PACKAGE} message (have {', '.join(MSG_NAMES)})")
    d, _ = msg_dir()
    if d is None:
        return EMBEDDED_MSG_TEXT[short]
    return (d / f"{short}.msg").read_text(encoding="utf-8")


def register_rosbags_types(typestore: Any) -> Dict[str, Any]:
    """Register ``dtm_labeler_msgs/msg/LabeledMarker`` and ``.../LabeledMarkerArray`` in a
    ``rosbags`` typestore (e.g. ``get_typestore(Stores.ROS2_JAZZY)``); idempotent.

    Returns the registered ``{typename: parsed definition}`` dict. Afterwards
    ``typestore.types[TYPE_NAMES['LabeledMarkerArray']]`` is the message class,
    ``typestore.serialize_cdr`` / ``deserialize_cdr`` are byte-compatible with rclpy, and a
    ``rosbags`` writer can ``add_connection(topic, typename, typestore=typestore)``.

    Raises:
        rosbags.typesys.TypesysError: the store already holds a different definition.
    """
    from rosbags.typesys import get_types_from_msg

    types: Dict[str, Any] = {}
    for name in MSG_NAMES:
        types.update(get_types_from_msg(msg_text(name), TYPE_NAMES[name]))
    typestore.register(types)
    return types


def make_typestore(store: Any = None) -> Any:
    """A fresh rosbags typestore (default ``Stores.ROS2_JAZZY``) with the dtm_labeler_msgs types."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY if store is None else store)
    register_rosbags_types(ts)
    return ts


def _render_embedded(src: Path = _REPO_MSG_DIR) -> str:
    lines = ["EMBEDDED_MSG_TEXT: Dict[str, str] = {"]
    for name in MSG_NAMES:
        lines.append(f"    {name!r}: {(src / f'{name}.msg').read_text(encoding='utf-8')!r},"
                     .replace(f"'{name}'", f'"{name}"', 1))
    lines.append("}")
    return "\n".join(lines) + "\n"


def _write_embedded() -> None:
    """Rewrite the EMBEDDED block of this file from msg_defs/msg."""
    me = Path(__file__).resolve()
    text = me.read_text(encoding="utf-8")
    begin = text.index("\n", text.index("# BEGIN EMBEDDED")) + 1
    end = text.index("# END EMBEDDED")
    me.write_text(text[:begin] + _render_embedded() + text[end:], encoding="utf-8")


if __name__ == "__main__":  # pragma: no cover - maintenance entry point
    if sys.argv[1:] == ["--write-embedded"]:
        _write_embedded()
        print(f"updated the embedded .msg text in {Path(__file__).resolve()}")
    else:
        d, where = msg_dir()
        print(f"{PACKAGE} .msg source: {where} {d or ''}")
