"""dtm_labeler_msgs: the generated Python messages and their rosbags registration agree (CDR bytes,
type hashes, bags). Needs the message package built into the venv by scripts/setup.sh: without it
these tests FAIL (they do not skip) so that a missing build cannot go unnoticed."""
import importlib
import json
from pathlib import Path

import numpy as np
import pytest

from dtm_labeler.ros import msg_types
from dtm_labeler.ros.msg_types import (
    EMBEDDED_MSG_TEXT,
    MSG_NAMES,
    TYPE_NAMES,
    make_typestore,
    msg_text,
    register_rosbags_types,
)

REPO = Path(__file__).resolve().parents[1]
LM, LMA = TYPE_NAMES["LabeledMarker"], TYPE_NAMES["LabeledMarkerArray"]


@pytest.fixture(scope="module")
def msgs():
    """The generated dtm_labeler_msgs.msg module, or a clear failure."""
    try:
        return importlib.import_module("dtm_labeler_msgs.msg")
    except ImportError as exc:
        pytest.fail(f"dtm_labeler_msgs is not built into this environment ({exc}); "
                    f"run scripts/setup.sh (it builds msg_defs/ into .venv)", pytrace=False)


@pytest.fixture(scope="module")
def typestore():
    return make_typestore()


def _sample(msgs):
    from std_msgs.msg import Header

    arr = msgs.LabeledMarkerArray()
    arr.header = Header(frame_id="mocap_world")
    arr.header.stamp.sec, arr.header.stamp.nanosec = 1_700_000_000, 123_456_789
    arr.frame_number = 2**40 + 7
    arr.label_names = ["LFHD", "RFHD", "LKNE"]
    arr.log_likelihood = -123.456789012345
    arr.active_model = "walk"
    arr.latency_ms = 1.25
    arr.n_unlabeled = 2
    m0 = msgs.LabeledMarker(label="LKNE", label_index=2, track_id=17, confidence=0.875)
    m0.position.x, m0.position.y, m0.position.z = 0.1, -0.2, 0.95
    m1 = msgs.LabeledMarker(label="", label_index=-1, track_id=4_000_000_000, confidence=0.0)
    m1.position.x = 1e-3
    m2 = msgs.LabeledMarker(label="LFHD", label_index=0, occluded=True, predicted=True)
    m2.position.z = 1.7
    arr.markers = [m0, m1, m2]
    return arr


def _assert_same(ros, bag):
    """A rclpy LabeledMarkerArray equals a rosbags one field by field."""
    assert bag.header.frame_id == ros.header.frame_id
    assert (bag.header.stamp.sec, bag.header.stamp.nanosec) == (ros.header.stamp.sec,
                                                                ros.header.stamp.nanosec)
    assert bag.frame_number == ros.frame_number
    assert list(bag.label_names) == list(ros.label_names)
    assert bag.log_likelihood == ros.log_likelihood
    assert bag.active_model == ros.active_model
    assert np.float32(bag.latency_ms) == np.float32(ros.latency_ms)
    assert bag.n_unlabeled == ros.n_unlabeled
    assert len(bag.markers) == len(ros.markers)
    for b, r in zip(bag.markers, ros.markers):
        assert (b.label, b.label_index, b.track_id, b.occluded, b.predicted) == (
            r.label, r.label_index, r.track_id, r.occluded, r.predicted)
        assert np.float32(b.confidence) == np.float32(r.confidence)
        assert (b.position.x, b.position.y, b.position.z) == (r.position.x, r.position.y,
                                                              r.position.z)


# ------------------------------------------------------------------------ generated messages

def test_generated_messages_have_the_fields(msgs):
    m = msgs.LabeledMarker()
    assert m.label == "" and m.label_index == -1  # default: no label
    assert (m.track_id, m.confidence, m.occluded, m.predicted) == (0, 0.0, False, False)
    assert type(m.position).__name__ == "Point"
    assert msgs.LabeledMarker.get_fields_and_field_types() == {
        "label": "string", "label_index": "int32", "track_id": "uint32",
        "position": "geometry_msgs/Point", "confidence": "float", "occluded": "boolean",
        "predicted": "boolean"}
    assert msgs.LabeledMarkerArray.get_fields_and_field_types() == {
        "header": "std_msgs/Header", "frame_number": "uint64",
        "markers": "sequence<dtm_labeler_msgs/LabeledMarker>", "label_names": "sequence<string>",
        "log_likelihood": "double", "active_model": "string", "latency_ms": "float",
        "n_unlabeled": "uint32"}
    arr = _sample(msgs)
    assert arr.markers[1].track_id == 4_000_000_000 and arr.frame_number == 2**40 + 7


# ------------------------------------------------------------------------- rosbags <-> rclpy

def test_rclpy_to_rosbags_and_back_cdr_compatible(msgs, typestore):
    from rclpy.serialization import deserialize_message, serialize_message

    ros = _sample(msgs)
    raw = serialize_message(ros)
    bag = typestore.deserialize_cdr(raw, LMA)
    _assert_same(ros, bag)
    again = bytes(typestore.serialize_cdr(bag, LMA))
    # Same CDR layout. (Not byte-for-byte: Fast CDR leaves the alignment padding bytes
    # uninitialised, rosbags writes zeros; readers ignore padding.)
    assert len(again) == len(raw)
    back = deserialize_message(again, msgs.LabeledMarkerArray)
    assert back == ros
    # rosbags -> rclpy -> rosbags reproduces rosbags' bytes exactly
    assert bytes(typestore.serialize_cdr(typestore.deserialize_cdr(serialize_message(back), LMA),
                                         LMA)) == again


def test_rosbags_built_message_deserialises_with_rclpy(msgs, typestore):
    from rclpy.serialization import deserialize_message

    T = typestore.types
    Point, Header, Time = (T["geometry_msgs/msg/Point"], T["std_msgs/msg/Header"],
                           T["builtin_interfaces/msg/Time"])
    marker = T[LM](label="RKNE", label_index=5, track_id=9, position=Point(x=1.0, y=2.0, z=3.0),
                   confidence=0.5, occluded=False, predicted=False)
    ghost = T[LM](label="", label_index=-1, track_id=10, position=Point(x=0.0, y=0.0, z=-1.0),
                  confidence=0.0, occluded=False, predicted=False)
    bag = T[LMA](header=Header(stamp=Time(sec=3, nanosec=4), frame_id="w"), frame_number=99,
                 markers=[marker, ghost], label_names=["a"] * 6, log_likelihood=-1.5,
                 active_model="", latency_ms=0.75, n_unlabeled=1)
    ros = deserialize_message(bytes(typestore.serialize_cdr(bag, LMA)), msgs.LabeledMarkerArray)
    _assert_same(ros, bag)
    assert ros.markers[1].label_index == -1


def test_type_hashes_match_the_rosidl_build(msgs, typestore):
    d, where = msg_types.msg_dir()
    assert where == "installed", f"expected the installed share/ directory, got {where} ({d})"
    for name in MSG_NAMES:
        desc = json.loads((d / f"{name}.json").read_text())
        built = {h["type_name"]: h["hash_string"] for h in desc["type_hashes"]}
        assert typestore.hash_rihs01(TYPE_NAMES[name]) == built[TYPE_NAMES[name]], name


def test_bag_written_by_rosbags_reads_with_rclpy(msgs, typestore, tmp_path):
    from rclpy.serialization import deserialize_message, serialize_message
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    ros = _sample(msgs)
    bag = typestore.deserialize_cdr(serialize_message(ros), LMA)
    for plugin in (StoragePlugin.SQLITE3, StoragePlugin.MCAP):
        path = tmp_path / f"bag_{plugin.name.lower()}"
        with Writer(path, version=9, storage_plugin=plugin) as writer:
            conn = writer.add_connection("markers/labeled", LMA, typestore=typestore)
            writer.write(conn, 42, typestore.serialize_cdr(bag, LMA))
        with Reader(path) as reader:
            (conn,) = reader.connections
            assert conn.msgtype == LMA and conn.digest == typestore.hash_rihs01(LMA)
            ((_, stamp, raw),) = list(reader.messages())
        assert stamp == 42
        assert deserialize_message(bytes(raw), msgs.LabeledMarkerArray) == ros


# ------------------------------------------------------------------------------- .msg text

def test_embedded_text_equals_msg_files():
    for name in MSG_NAMES:
        assert EMBEDDED_MSG_TEXT[name] == (REPO / "msg_defs" / "msg" / f"{name}.msg").read_text(), (
            f"{name}: the embedded copy is stale; run "
            f"`python -m dtm_labeler.ros.msg_types --write-embedded`")


def test_installed_text_equals_msg_files(msgs):
    d, _ = msg_types.msg_dir()
    for name in MSG_NAMES:
        assert msg_text(name) == (REPO / "msg_defs" / "msg" / f"{name}.msg").read_text(), (
            f"{name}: the installed build in {d} is stale; run scripts/setup.sh")
    assert msg_text(LMA) == msg_text("LabeledMarkerArray")
    with pytest.raises(KeyError):
        msg_text("Nope")


def test_fallbacks_source_then_embedded(monkeypatch, tmp_path):
    from rosbags.typesys import Stores, get_typestore

    monkeypatch.setattr(msg_types, "_installed_msg_dirs", lambda: iter([tmp_path / "none"]))
    assert msg_types.msg_dir() == (REPO / "msg_defs" / "msg", "source")
    monkeypatch.setattr(msg_types, "_REPO_MSG_DIR", tmp_path / "missing")
    assert msg_types.msg_dir() == (None, "embedded")
    ts = get_typestore(Stores.ROS2_JAZZY)
    types = register_rosbags_types(ts)
    assert set(types) == {LM, LMA}
    assert ts.hash_rihs01(LMA) == make_typestore().hash_rihs01(LMA)
    register_rosbags_types(ts)  # idempotent
