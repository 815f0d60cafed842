"""The node's pure modules, without a node: output messages (dtm_labeler.ros.messages), the
diagnostics levels (dtm_labeler.ros.diagnostics), input decoders (dtm_labeler.ros.inputs), the
model-file check (dtm_labeler.ros.model_check) and the mocap4r2_msgs definition."""
from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
from std_msgs.msg import Header

import node_helpers as H
from dtm_labeler.ros import diagnostics as D
from dtm_labeler.ros.inputs import decode, name_id
from dtm_labeler.ros.messages import (NO_TRACK, LabelledFrame, OccludedLabels, VizThrottle, labeled_marker_array,
                                      output_header)

NAMES = ("a", "b", "c")


def frame(**kw):
    base = dict(header=Header(frame_id="world"), frame_number=7, xyz=np.array([[0, 0, 1.0], [1, 0, 1], [9, 9, 9]]),
                labels=np.array([1, -1, 0]), confidence=np.array([0.9, 0.0, 0.5]), tracks=np.array([4, -1, 2]),
                names=NAMES, log_likelihood=-3.5, active_model="walk", latency_ms=2.0)
    base.update(kw)
    return LabelledFrame(**base)


def test_labeled_marker_array():
    from dtm_labeler.ros.messages import Occluded
    f = frame(occluded=[Occluded(2, 11, np.array([1.0, 2.0, 3.0]))])
    m = labeled_marker_array(f)
    assert m.frame_number == 7 and list(m.label_names) == list(NAMES) and m.n_unlabeled == 1
    assert [x.label for x in m.markers] == ["b", "", "a", "c"]
    assert [x.track_id for x in m.markers] == [4, NO_TRACK, 2, 11]
    assert m.markers[3].occluded and m.markers[3].predicted and m.markers[3].position.z == 3.0
    assert m.markers[0].confidence == pytest.approx(0.9) and m.markers[1].label_index == -1


@pytest.mark.parametrize("n, frame_id, occluded", [(3, "world", True), (45, "", True), (0, "w", False),
                                                   (17, "mocap_origin", False)])
def test_labeled_marker_array_cdr_is_the_message(n, frame_id, occluded):
    """The bytes the node publishes deserialise to exactly the message rclpy would have
    serialised (every padding case: label lengths 1-8, odd counts, empty frames)."""
    from builtin_interfaces.msg import Time
    from rclpy.serialization import deserialize_message, serialize_message

    from dtm_labeler.ros.messages import Occluded, labeled_marker_array_cdr
    from dtm_labeler_msgs.msg import LabeledMarkerArray
    rng = np.random.default_rng(n)
    names = tuple("L" * (i % 8) + str(i) for i in range(41))
    labels = np.full(n, -1)
    labels[:min(n, 41)] = rng.permutation(41)[:min(n, 41)]
    rng.shuffle(labels)
    f = frame(header=Header(stamp=Time(sec=1795456025, nanosec=479829802), frame_id=frame_id),
              frame_number=2 ** 40 + n, xyz=rng.normal(size=(n, 3)), labels=labels, confidence=rng.random(n),
              tracks=np.arange(n) - 2, names=names, log_likelihood=-1234.5, active_model="run" * (n % 2),
              latency_ms=7.25, occluded=[Occluded(3, 2 ** 33 + 5, np.array([1.0, -2.0, 3.5]))] if occluded else [])
    ours = deserialize_message(labeled_marker_array_cdr(f), LabeledMarkerArray)
    ref = deserialize_message(serialize_message(labeled_marker_array(f)), LabeledMarkerArray)
    assert ours == ref
    assert len(ours.markers) == n + occluded and ours.n_unlabeled == int((labels < 0).sum())


def test_mocap4r2_markers():
    pytest.importorskip("mocap4r2_msgs.msg")
    from mocap4r2_msgs.msg import Marker

    from dtm_labeler.ros.messages import mocap4r2_markers
    m = mocap4r2_markers(frame())
    assert [x.marker_name for x in m.markers] == ["b", "", "a"] and [x.marker_index for x in m.markers] == [4, -1, 2]
    assert {x.id_type for x in m.markers} == {Marker.USE_BOTH} and m.markers[2].translation.x == 9.0


def test_output_header_frame_id():
    h = Header(frame_id="")
    assert output_header(h, "world", False).frame_id == "world"
    assert output_header(Header(frame_id="map"), "world", False).frame_id == "map"
    assert output_header(Header(frame_id="map"), "world", True).frame_id == "world"
    assert output_header(h, "", True) is h


def test_occluded_labels_and_viz_throttle():
    occ = OccludedLabels()
    occ.step(np.array([0, 1]), np.array([10, 11]), lambda t: np.zeros(3))
    got = occ.step(np.array([0]), np.array([10]), lambda t: np.full(3, float(t)))
    assert [(o.label, o.track, o.position[0]) for o in got] == [(1, 11, 11.0)]
    assert occ.step(np.array([0]), np.array([10]), lambda t: np.full(3, np.nan)) == []    # track gone: forgotten
    assert occ.step(np.array([0]), np.array([10]), lambda t: np.zeros(3)) == []
    v = VizThrottle()
    assert v.due(1.0, 0.05) == (True, True)
    assert v.due(1.02, 0.05) == (False, False) and v.due(1.06, 0.05) == (True, False)
    v.clear()
    assert v.due(1.07, 0.05) == (True, True)


def state(**kw):
    return D.NodeState(name="n", hardware_id="/n", model_status="loaded", **kw)


def stats(received, published, **kw):
    s = D.NodeStats(received=received, published=published, labelled=published)
    for k, v in kw.items():
        getattr(s, k).update(v) if isinstance(v, dict) else setattr(s, k, v)
    return s


@pytest.mark.parametrize("cur, st, level, words", [
    (stats(120, 119), state(), D.OK, ["labelling at"]),
    (stats(6, 5), state(), D.OK, ["labelling at"]),           # one frame in flight at the period's edge
    (stats(6, 4, skipped={"stale": 1}), state(), D.WARN, ["labelling 4.0 Hz of 6.0 Hz", "1 frames dropped"]),
    (stats(120, 60, skipped={"stale": 60}), state(), D.WARN, ["labelling 60.0 Hz of 120.0 Hz"]),
    (stats(120, 119, stamp_faults={"zero": 30}), state(time_base="receive"), D.WARN, ["zero 30", "receive time"]),
    (stats(120, 60, skipped={"other_source": 60}), state(), D.WARN, ["another publisher"]),
    (stats(120, 119, resets={"gap": 3}), state(), D.WARN, ["3 resets"]),
    (stats(120, 119, full_searches=40), state(), D.WARN, ["full searches on 40"]),
    (stats(0, 0), state(publishers=1, since_input_s=2.5), D.WARN, ["no input for 2.5 s"]),
    (stats(0, 0), state(publishers=1, since_input_s=0.5, incompatible_qos="1 publisher(s) offer best-effort"),
     D.WARN, ["best-effort"]),
    (stats(120, 119, frames_millimetres=3), state(), D.WARN, ["millimetres"]),
    (stats(120, 119), state(anonymous_absent="the stream does not show the model's 2 anonymous points"),
     D.WARN, ["anonymous points", "labelling at"]),
    (stats(120, 0, skipped={"error": 120}, last_error="boom"), state(failing_s=1.5), D.ERROR, ["failing", "boom"]),
    (stats(120, 0), D.NodeState(name="n", hardware_id="/n"), D.ERROR, ["no model"]),
    (stats(0, 0), state(input_error="input_type mocap4r2_markers: not installed"), D.ERROR, ["not installed"]),
    (stats(0, 0), state(active=False), D.OK, ["inactive"]),
])
def test_diagnostics_levels(cur, st, level, words):
    got, message = D.assess(cur, D.NodeStats(), 1.0, st)
    assert got == level, message
    for w in words:
        assert w in message


def test_diagnostics_statuses_and_keys():
    b = D.DiagnosticsBuilder()
    st = state(latency_ms=np.array([1.0, 2.0, 3.0]), config={"method": "cbga", "expected_labels": ["x"]})
    lab, model = b.build(stats(10, 8, skipped={"stale": 2}), st, now=1.0)
    kv = {x.key: x.value for x in lab.values}
    assert kv["frames_received"] == "10" and kv["frames_skipped_stale"] == "2" and kv["method"] == "cbga"
    assert int(kv["frames_published"]) + sum(int(v) for k, v in kv.items() if k.startswith("frames_skipped_")) == 10
    assert {"stamp_faults_zero", "frames_lost_before_node", "time_base", "latency_p99_ms"} <= set(kv)
    assert "expected_labels" not in kv and {x.key: x.value for x in model.values}["expected_labels"] == "x"
    assert lab.name == "n: labeling" and model.hardware_id == "/n"


def test_decoders():
    pytest.importorskip("mocap4r2_msgs.msg")
    xyz = np.array([[0.1, 0.2, 1.0], [0.3, -0.2, 1.2], [0.0, 0.0, 0.0]])
    d = decode("pointcloud", H.make_input("pointcloud", xyz))
    np.testing.assert_allclose(d.xyz, xyz, atol=1e-6)
    assert d.ids is None
    d = decode("mocap4r2_markers", H.make_input("mocap4r2_markers", xyz, frame_number=42))
    assert d.ids is None and d.frame_number == 42                       # list indices are not ids
    assert d.origin_points == 1 and np.isnan(d.xyz[2]).all()           # (0, 0, 0) = not seen
    d = decode("mocap4r2_markers", H.make_input("mocap4r2_markers", xyz), "index")
    assert d.ids.tolist() == [0, 1, 2]
    d = decode("mocap4r2_markers", H.make_input("mocap4r2_markers", xyz, names=["LASI", "RASI", "C7"]))
    assert d.ids.tolist() == [name_id("LASI"), name_id("RASI"), name_id("C7")]
    d = decode("mocap4r2_markers", H.make_input("mocap4r2_markers", xyz, names=["LASI", "LASI", "C7"]))
    assert d.ids is None                                                # two subjects' names: not ids


def test_model_file_check(tmp_path):
    from dtm_labeler.ros.model_check import check_model_file
    wm = H.walk_model()
    c = check_model_file(wm.path, list(wm.labels))
    assert c.kind == "model" and c.labels == wm.labels and 0 < c.array_bytes < 2 ** 20
    with np.load(wm.path) as z:
        arrays = {k: z[k] for k in z.files}
    big = tmp_path / "big.npz"
    with zipfile.ZipFile(big, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as out:
        for k, a in arrays.items():
            buf = io.BytesIO()
            np.save(buf, np.zeros(9 * 2 ** 20) if k == "tri0_means" else a)
            out.writestr(k + ".npy", buf.getvalue())
    with pytest.raises(ValueError, match="tri0_means.*far beyond a model's size"):
        check_model_file(big)
    pickled = tmp_path / "obj.npz"
    np.savez(pickled, header=arrays["header"], x=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="object array"):
        check_model_file(pickled)
    with pytest.raises(ValueError, match="not a regular file"):
        check_model_file(tmp_path)
    with pytest.raises(ValueError, match="missing head"):
        check_model_file(wm.mismatched_path, list(wm.labels))


def test_mocap4r2_definition_has_the_upstream_type_hashes():
    """The .msg files in vendor/ are the published interface: same RIHS01 type hashes as the
    mocap4r2_msgs build of the MOCAP4ROS2 project (Jazzy)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    msg_dir = H.REPO / "vendor" / "mocap4r2_msgs" / "msg"
    for name in ("Marker", "Markers"):
        ts.register(get_types_from_msg((msg_dir / f"{name}.msg").read_text(), f"mocap4r2_msgs/msg/{name}"))
    assert ts.hash_rihs01("mocap4r2_msgs/msg/Marker") == (
        "RIHS01_0cadb14b00eb93dfd5d1b774f04f13efc0c2e08a3bee1abbaef9f67f6b10b943")
    assert ts.hash_rihs01("mocap4r2_msgs/msg/Markers") == (
        "RIHS01_36a59e85fa0dcebed1f0a91d748ca17e259b187f779e725af5c6701e8a03054a")
