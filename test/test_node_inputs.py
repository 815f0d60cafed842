"""The node behind each driver kind (real process, real DDS): the same frames as
sensor_msgs/PointCloud2, mocap4r2_msgs/Markers and sensor_msgs/PointCloud get the same labels; a
mocap4r2 subscriber reads our labels; Vicon-style marker names become track ids; ~/reset resets
and is counted; frame_id fills an empty input frame. One node process (namespace t_inputs)."""
from __future__ import annotations

import signal

import numpy as np
import pytest

import node_helpers as H

pytest.importorskip("mocap4r2_msgs.msg", reason="mocap4r2_msgs not built: run bash scripts/setup.sh")

N_FRAMES = 30


@pytest.fixture(scope="module")
def running():
    wm = H.walk_model()
    proc, client = H.start("t_inputs", params={"model_path": wm.path, "diagnostics_period_s": 0.1,
                                               "input_qos": "reliable", "frame_id": "world"})
    feed = H.FrameFeed(wm, seed=5)
    frames = [feed.next()[:2] for _ in range(N_FRAMES)]
    yield proc, client, feed, wm, frames
    client.close()
    if proc.alive():
        proc.stop(signal.SIGKILL)


def switch_input(cl, kind: str, **params):
    assert all(r.successful for r in cl.set(input_type=kind, **params)), kind
    pub = cl.input_pub(kind)
    cl.wait_for(lambda: pub.get_subscription_count() > 0, 10, f"{kind} subscription")


def run_pass(cl, feed, kind: str, frames, names=None):
    """Reset the node, send ``frames`` as ``kind`` in lock step; labels (names) per frame."""
    from std_srvs.srv import Trigger
    assert cl.call(Trigger, "reset").success
    out = []
    for i, (xyz, truth) in enumerate(frames):
        feed.stamp += 1.0 / feed.wm.rate
        stamp = feed.stamp
        cl.publish_as(kind, xyz, stamp, frame_id="", names=None if names is None else [names[t] for t in truth],
                      frame_number=1000 + i)
        msg = cl.wait_for(lambda: cl.labeled_at(stamp), 10, f"{kind} frame {i}")
        out.append([m.label for m in msg.markers if not m.occluded])
    return out, msg


def accuracy(labels, frames, wm):
    hits = sum(np.sum(np.array(lab) == np.array([wm.labels[t] for t in truth]))
               for lab, (xyz, truth) in zip(labels, frames))
    return hits / sum(len(t) for _, t in frames)


def test_same_labels_from_every_input_type(running):
    proc, cl, feed, wm, frames = running
    resets0 = int(cl.wait_diag(lambda d: True)["resets_service"])
    ref, last = run_pass(cl, feed, "pointcloud2", frames)
    assert accuracy(ref, frames, wm) > 0.95
    assert last.header.frame_id == "world"                 # empty input frame_id -> the frame_id parameter
    for kind in ("mocap4r2_markers", "pointcloud"):
        switch_input(cl, kind)
        got, last = run_pass(cl, feed, kind, frames)
        same = np.mean([a == b for la, lb in zip(ref, got) for a, b in zip(la, lb)])
        assert same > 0.97, (kind, same)
        assert accuracy(got, frames, wm) > 0.95
        assert last.header.frame_id == "world"
    d = cl.wait_diag(lambda d: int(d["resets_service"]) >= resets0 + 3)
    assert d["input_type"] == "pointcloud" and d["frames_skipped_bad_cloud"] == "0"
    switch_input(cl, "pointcloud2")


def test_mocap4r2_subscriber_reads_our_labels(running):
    from mocap4r2_msgs.msg import Marker
    proc, cl, feed, wm, frames = running
    switch_input(cl, "mocap4r2_markers")
    labels, last = run_pass(cl, feed, "mocap4r2_markers", frames[:10])
    stamp = cl.stamp_of(last)
    out = cl.wait_for(lambda: [m for m in cl.mocap4r2 if abs(cl.stamp_of(m) - stamp) < 1e-6], 5, "mocap4r2 output")[0]
    assert [m.marker_name for m in out.markers] == labels[-1]
    assert all(m.id_type == Marker.USE_BOTH for m in out.markers)
    assert [m.marker_index for m in out.markers] == [m.track_id for m in last.markers if not m.occluded]
    assert out.frame_number == 1009 and out.header.frame_id == "world"    # the driver's frame counter
    # OptiTrack-style list indices are not track ids: the node tracks by position
    assert len({m.track_id for m in last.markers}) == len(last.markers)
    switch_input(cl, "pointcloud2")


def test_vicon_marker_names_become_track_ids(running):
    from dtm_labeler.ros.inputs import name_id
    proc, cl, feed, wm, frames = running
    switch_input(cl, "mocap4r2_markers", override_frame_id=True)
    names = [f"S1:{x.upper()}" for x in wm.labels]
    labels, last = run_pass(cl, feed, "mocap4r2_markers", frames[:8], names=names)
    truth = frames[7][1]
    assert [m.track_id for m in last.markers if not m.occluded] == [name_id(names[t]) for t in truth]
    assert accuracy(labels, frames[:8], wm) > 0.95
    # a marker the Vicon driver does not see comes at exactly (0, 0, 0): read as not seen
    xyz, truth = frames[0]
    xyz = xyz.copy()
    xyz[0] = 0.0
    feed.stamp += 1.0 / wm.rate
    before = int(cl.wait_diag(lambda d: True)["points_at_origin"])
    cl.publish_as("mocap4r2_markers", xyz, feed.stamp, frame_id="vicon_world", names=[names[t] for t in truth])
    out = cl.wait_for(lambda: cl.labeled_at(feed.stamp), 10, "frame with a point at the origin")
    assert out.markers[0].label_index == -1 and out.header.frame_id == "world"     # override_frame_id
    cl.wait_diag(lambda d: int(d["points_at_origin"]) >= before + 1)
    switch_input(cl, "pointcloud2", override_frame_id=False)


def test_node_survived(running):
    proc, cl, feed, wm, frames = running
    assert proc.alive() and proc.stop(signal.SIGTERM) == 0
    assert "Traceback" not in proc.log()


def test_starts_without_mocap4r2_msgs_and_says_what_to_install(monkeypatch):
    """In-process node with mocap4r2_msgs made unimportable (as on a machine without it)."""
    import sys

    import rclpy
    from rclpy.parameter import Parameter

    from dtm_labeler.ros.node import LabelerNode
    monkeypatch.setitem(sys.modules, "mocap4r2_msgs", None)
    monkeypatch.setitem(sys.modules, "mocap4r2_msgs.msg", None)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = LabelerNode(context=ctx, namespace="/t_nomocap", start_worker=False,
                       parameter_overrides=[Parameter("input_type", value="mocap4r2_markers")])
    try:
        assert node.core.sub is None and node.core.outputs.mocap4r2 is None
        assert "ros-jazzy-mocap4r2-msgs" in node.core.input_error
        st = {s.name.rsplit(": ", 1)[1]: s for s in node.diagnostics()}
        assert "ros-jazzy-mocap4r2-msgs" in st["labeling"].message
        r = node.set_parameters([Parameter("input_type", value="pointcloud2")])[0]
        assert r.successful and node.core.sub is not None and not node.core.input_error
        r = node.set_parameters([Parameter("input_type", value="mocap4r2_markers")])[0]
        assert not r.successful and "mocap4r2_msgs is not installed" in r.reason
    finally:
        node.destroy_node()
        ctx.try_shutdown()
