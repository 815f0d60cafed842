"""ros.bag / dtm-bag: bags from a real recording (mcap + sqlite3), read back with rosbags and
with rclpy, ground truth vs the clip, corruption as requested, offline labeling, the player."""
import json
import threading
import time

import numpy as np
import pytest

from dtm_labeler.cli import bag as bag_cli
from dtm_labeler.cli.common import load_inputs
from dtm_labeler.ros import bag as B

WALK = "cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh"


@pytest.fixture(scope="module")
def walk(data_dir):
    return str(data_dir / WALK)


@pytest.fixture(scope="module")
def clip(walk):
    return load_inputs([walk], "body14", "200:260")[0]


@pytest.fixture(scope="module")
def bags(walk, tmp_path_factory):
    """Clean bags (mcap, sqlite3) of frames 200:260 and a corrupted mcap one."""
    d = tmp_path_factory.mktemp("bags")
    out = {}
    for storage in B.STORAGES:
        out[storage] = d / f"clean_{storage}"
        assert bag_cli.main(["make", walk, "--out", str(out[storage]), "--frames", "200:260", "--storage", storage,
                             "--seed", "3"]) == 0
    out["corrupt"] = d / "corrupt"
    assert bag_cli.main(["make", walk, "--out", str(out["corrupt"]), "--frames", "200:260", "--occlude", "2",
                         "--clutter", "3", "--noise-mm", "2", "--seed", "4", "--no-ids", "--frame-id", "world"]) == 0
    return out


def _frames(path):
    """{topic: [(bag time, rosbags msg)]}"""
    out = {}
    for topic, t, msg in B.read_messages(path):
        out.setdefault(topic, []).append((t, msg))
    return out


@pytest.mark.parametrize("storage", B.STORAGES)
def test_bag_layout_and_timeline(bags, clip, storage):
    path = bags[storage]
    info = B.bag_info(path)
    assert info["storage"] == storage == B.bag_storage(path)
    assert info["topics"] == {B.TOPIC_UNLABELED: {"type": B.PC2, "count": 60},
                              B.TOPIC_GROUND_TRUTH: {"type": B.LMA, "count": 60}}
    meta = (path / "metadata.yaml").read_text()
    assert "version: 9" in meta and f"storage_identifier: {storage}" in meta
    assert "offered_qos_profiles" in meta
    fr = _frames(path)
    for k, ((t, cloud), (tg, gt)) in enumerate(zip(fr[B.TOPIC_UNLABELED], fr[B.TOPIC_GROUND_TRUTH])):
        want = 1_000_000_000 + round(k * 1e9 / clip.rate)
        assert t == tg == want == B.stamp_ns_of(cloud) == B.stamp_ns_of(gt)
        assert cloud.header.frame_id == gt.header.frame_id == "mocap"
        assert gt.frame_number == k


@pytest.mark.parametrize("storage", B.STORAGES)
def test_ground_truth_matches_the_clip(bags, clip, storage):
    from dtm_labeler.ros.pointcloud import read_points_xyz
    fr = _frames(bags[storage])
    orders = set()
    for k, ((_, cloud), (_, gt)) in enumerate(zip(fr[B.TOPIC_UNLABELED], fr[B.TOPIC_GROUND_TRUTH])):
        xyz, ids = read_points_xyz(cloud)
        assert [f.name for f in cloud.fields] == ["x", "y", "z", "id"] and ids is not None
        assert xyz.shape == (14, 3)
        assert list(gt.label_names) == list(clip.names)
        gxyz, glab = B.markers_to_arrays(gt)
        np.testing.assert_array_equal(gxyz, xyz)                       # same points, same order
        assert sorted(glab) == sorted(clip.names)                      # every marker once
        idx = [m.label_index for m in gt.markers]
        assert [clip.names[i] for i in idx] == glab
        np.testing.assert_allclose(xyz, clip.positions[k, idx], atol=1e-5)   # float32 of the clip
        assert [m.track_id for m in gt.markers] == list(ids)
        orders.add(tuple(idx))
    assert len(orders) > 30                                             # shuffled per frame


def test_rclpy_deserialises_the_bag(bags):
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    from dtm_labeler.ros.pointcloud import read_points_xyz
    from dtm_labeler_msgs.msg import LabeledMarkerArray
    for storage in B.STORAGES:
        raw = B.read_raw(bags[storage])
        ref = _frames(bags[storage])
        assert [m.topic for m in raw[:2]] == [B.TOPIC_UNLABELED, B.TOPIC_GROUND_TRUTH]
        clouds = [deserialize_message(m.data, PointCloud2) for m in raw if m.topic == B.TOPIC_UNLABELED]
        gts = [deserialize_message(m.data, LabeledMarkerArray) for m in raw if m.topic == B.TOPIC_GROUND_TRUTH]
        assert len(clouds) == len(gts) == 60
        for c, g, (_, rc), (_, rg) in zip(clouds, gts, ref[B.TOPIC_UNLABELED], ref[B.TOPIC_GROUND_TRUTH]):
            a, ia = read_points_xyz(c)
            b, ib = read_points_xyz(rc)
            np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(ia, ib)
            assert B.stamp_ns_of(c) == B.stamp_ns_of(rc)
            assert [m.label for m in g.markers] == [m.label for m in rg.markers]
            assert [m.label_index for m in g.markers] == [m.label_index for m in rg.markers]
            assert g.n_unlabeled == 0 and list(g.label_names) == list(rg.label_names)


def test_gaps_ghosts_noise_as_requested(bags, clip):
    from dtm_labeler.ros.pointcloud import read_points_xyz
    fr = _frames(bags["corrupt"])
    resid = []
    for k, ((_, cloud), (_, gt)) in enumerate(zip(fr[B.TOPIC_UNLABELED], fr[B.TOPIC_GROUND_TRUTH])):
        xyz, ids = read_points_xyz(cloud)
        assert ids is None and [f.name for f in cloud.fields] == ["x", "y", "z"]
        assert cloud.header.frame_id == "world"
        assert xyz.shape == (14 - 2 + 3, 3)
        gxyz, glab = B.markers_to_arrays(gt)
        np.testing.assert_array_equal(gxyz, xyz)
        ghosts = [m for m in gt.markers if m.label_index < 0]
        assert len(ghosts) == 3 and all(m.label == "" for m in ghosts) and gt.n_unlabeled == 3
        real = [(i, m.label_index) for i, m in enumerate(gt.markers) if m.label_index >= 0]
        assert len(real) == 12 and len({l for _, l in real}) == 12
        resid.append(xyz[[i for i, _ in real]] - clip.positions[k, [l for _, l in real]])
        # ghosts are near the body, not at a true marker
        body = clip.positions[k]
        for m in ghosts:
            p = np.array([m.position.x, m.position.y, m.position.z])
            d = np.linalg.norm(body - p, axis=1).min()
            assert 0.02 < d < 0.32
    std_mm = np.std(np.concatenate(resid)) * 1e3
    assert 1.7 < std_mm < 2.3


@pytest.fixture(scope="module")
def model_path(walk, tmp_path_factory):
    from dtm_labeler.cli import train
    p = tmp_path_factory.mktemp("model") / "walk.npz"
    assert train.main([walk, "--frames", "0:60%", "--out", str(p), "--quiet"]) == 0
    return p


def test_label_bag_offline(bags, model_path, tmp_path, capsys):
    from dtm_labeler.model.io import load_model
    from dtm_labeler.ros.pointcloud import read_points_xyz
    out = tmp_path / "labeled"
    assert bag_cli.main(["label", str(model_path), str(bags["corrupt"]), "--out", str(out), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    for key in ("accuracy", "ghost_rejection", "latency_ms", "fps", "frames", "method", "mode"):
        assert key in s
    assert s["frames"] == 60 and s["scored_frames"] == 60 and s["true_markers"] == 60 * 12
    assert s["accuracy"] > 0.75 and s["ghosts"] == 180            # 2 hidden + 3 ghosts + 2 mm, unseen frames
    assert set(s["latency_ms"]) >= {"p50", "p99", "max"}
    info = B.bag_info(out)
    assert info["storage"] == "mcap"
    assert {t: d["count"] for t, d in info["topics"].items()} == {
        B.TOPIC_UNLABELED: 60, B.TOPIC_GROUND_TRUTH: 60, B.TOPIC_LABELED: 60, B.TOPIC_LABELED_CLOUD: 60}
    fr = _frames(out)
    labels = list(load_model(model_path).labels)
    scorer = B.Scorer(known=set(labels))
    for (_, cloud), (_, lab), (_, lc), (_, gt) in zip(fr[B.TOPIC_UNLABELED], fr[B.TOPIC_LABELED],
                                                      fr[B.TOPIC_LABELED_CLOUD], fr[B.TOPIC_GROUND_TRUTH]):
        assert B.stamp_ns_of(lab) == B.stamp_ns_of(cloud) == B.stamp_ns_of(lc)
        assert lab.header.frame_id == "world" and list(lab.label_names) == labels
        xyz, _ = read_points_xyz(cloud)
        np.testing.assert_array_equal(B.markers_to_arrays(lab)[0], xyz)
        from dtm_labeler.ros.pointcloud import cloud_to_structured
        arr = cloud_to_structured(lc)
        assert list(arr["label"]) == [m.label_index for m in lab.markers]
        scorer.add_truth(B.stamp_ns_of(gt), *B.markers_to_arrays(gt))
        scorer.add_output(B.stamp_ns_of(lab), *B.markers_to_arrays(lab))
    assert scorer.accuracy == pytest.approx(s["accuracy"])
    # sqlite3 output on request, score-only without --out
    assert bag_cli.main(["label", str(model_path), str(bags["sqlite3"]), "--out", str(tmp_path / "sq"),
                         "--storage", "sqlite3", "--json"]) == 0
    s2 = json.loads(capsys.readouterr().out)
    assert B.bag_info(tmp_path / "sq")["storage"] == "sqlite3" and s2["accuracy"] > 0.9 and s2["ghosts"] == 0
    assert bag_cli.main(["label", str(model_path), str(bags["sqlite3"]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["out"] is None


def test_cli_errors_and_info(bags, walk, tmp_path, capsys):
    assert bag_cli.main(["make", walk, "--out", str(bags["mcap"])]) == 2           # exists, no --force
    assert "exists" in capsys.readouterr().err
    assert bag_cli.main(["info", str(tmp_path / "nope")]) == 2
    assert bag_cli.main(["label", str(tmp_path / "nope.npz"), str(bags["mcap"])]) == 2
    assert bag_cli.main(["info", str(bags["mcap"]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["topics"][B.TOPIC_UNLABELED]["count"] == 60
    with pytest.raises(SystemExit):
        bag_cli.main(["make", walk, "--out", str(tmp_path / "x"), "--occlude", "-1"])


def test_restamp_cdr():
    from dtm_labeler.ros.player import restamp_cdr
    ts = B.typestore()
    msg = B.cloud_message(np.zeros((2, 3)), 5_000_000_123, "f", ids=[1, 2])
    raw = bytes(ts.serialize_cdr(msg, B.PC2))
    back = ts.deserialize_cdr(restamp_cdr(raw, 1_700_000_000_987_654_321), B.PC2)
    assert (back.header.stamp.sec, back.header.stamp.nanosec) == (1_700_000_000, 987_654_321)
    assert back.header.frame_id == "f" and back.width == 2


def test_player_timeline_and_restamp(bags):
    """play() in this process into an rclpy subscriber: every message, in order, on the timeline
    (within a few ms), restamped to the send schedule with clouds and truth still paired."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import PointCloud2

    from dtm_labeler.ros.player import play
    from dtm_labeler_msgs.msg import LabeledMarkerArray

    ctx = rclpy.Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    got = {"c": [], "g": []}
    node = rclpy.create_node("test_player_sink", context=ctx)
    qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(PointCloud2, "markers/unlabeled",
                             lambda m: got["c"].append((time.time(), B.stamp_ns_of(m))), qos)
    node.create_subscription(LabeledMarkerArray, "markers/ground_truth",
                             lambda m: got["g"].append(B.stamp_ns_of(m)), qos)
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    stop = threading.Event()
    th = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)])
    th.start()
    try:
        stats = play(bags["mcap"], restamp=True, wait_for=["markers/unlabeled", "markers/ground_truth"],
                     wait_timeout=20)
        t_end = time.monotonic()
        while len(got["c"]) < 60 and time.monotonic() - t_end < 3:
            time.sleep(0.01)
    finally:
        stop.set()
        th.join()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    assert stats.sent == {B.TOPIC_UNLABELED: 60, B.TOPIC_GROUND_TRUTH: 60} and stats.loops == 1
    assert stats.matched[B.TOPIC_UNLABELED] >= 1
    # ~0.1 ms on an idle machine; generous bounds for a loaded 2-core CI box
    assert stats.lateness_ms["p50"] < 2.0 and stats.lateness_ms["p99"] < 25.0
    assert abs(stats.duration_s - 59 / 120) < 0.03
    recv, stamps = np.array([r for r, _ in got["c"]]), np.array([s for _, s in got["c"]])
    assert len(stamps) == 60 and (np.diff(stamps) > 0).all()
    assert sorted(got["g"]) == list(stamps)                       # truth restamped identically
    np.testing.assert_allclose(np.diff(stamps) * 1e-9, 1 / 120, atol=2e-6)   # schedule kept
    assert abs(stamps[0] * 1e-9 - time.time()) < 30                # wall-clock stamps
    lag = recv - stamps * 1e-9                                     # delivery after the schedule
    assert np.median(lag) < 0.01 and lag.min() > -0.001


class _HeldSink:
    """Stands in for an rclpy publisher in ``_send``: records what is sent and when; the first
    send is held ``hold_s`` as Fast DDS sometimes holds a writer's first ``publish`` (193 ms seen
    in a benchmark run; not reproducible on demand, hence the stand-in)."""

    def __init__(self, hold_s: float = 0.0):
        self.hold_s, self.sent = hold_s, []

    def publish(self, data: bytes) -> None:
        if self.hold_s and not self.sent:
            time.sleep(self.hold_s)
        self.sent.append((time.perf_counter(), data))


def _play_to_sinks(pubs: dict, n: int) -> tuple:
    """``_send`` of ``n`` frames at 120 Hz, restamped, one cloud per frame on each topic of
    ``pubs`` (publisher stand-ins); (stats, lateness, {topic: the stamps sent})."""
    from dtm_labeler.ros.player import PlayStats, _send
    ts = B.typestore()
    raw = bytes(ts.serialize_cdr(B.cloud_message(np.zeros((2, 3)), 0, "f"), B.PC2))
    msgs = [B.RawMessage(t, B.PC2, k * round(1e9 / 120), raw) for k in range(n) for t in pubs]
    stats = PlayStats(sent={t: 0 for t in pubs})
    lateness, _, _ = _send(msgs, pubs, None, set(pubs), stats, threading.Event(), rate=1.0, loop=False,
                           restamp=True, on_start=None)
    stamps = {t: np.array([B.stamp_ns_of(ts.deserialize_cdr(d, B.PC2)) for _, d in p.sent]) for t, p in pubs.items()}
    return stats, lateness, stamps


def test_a_first_send_held_in_dds_starts_the_timeline_after_it():
    """A first send held 0.15 s: the later frames keep their spacing from where the stream
    started (not sent in one burst to catch up), their stamps stay a frame period apart and
    clouds and truth keep one stamp per frame; the hold is reported."""
    n = 20
    pubs = {B.TOPIC_UNLABELED: _HeldSink(0.15), "/truth": _HeldSink()}
    stats, lateness, stamps = _play_to_sinks(pubs, n)
    assert stats.sent == {B.TOPIC_UNLABELED: n, "/truth": n}
    assert stats.start_held_ms >= 140
    np.testing.assert_array_equal(stamps[B.TOPIC_UNLABELED], stamps["/truth"])
    s = stamps["/truth"]
    assert (s[1] - s[0]) * 1e-9 >= 1 / 120 + 0.14                   # the stream starts after the hold
    np.testing.assert_allclose(np.diff(s[1:]) * 1e-9, 1 / 120, atol=2e-6)
    sent_at = np.array([t for t, _ in pubs["/truth"].sent])
    # on the timeline from there: one frame a period (a burst would send frames 1-18 at once)
    assert np.median(np.diff(sent_at[1:])) > 0.5 / 120
    assert max(lateness[2:]) < 0.15                                 # no frame after the first waits for the hold


def test_a_first_send_on_time_keeps_the_timeline():
    stats, _, stamps = _play_to_sinks({B.TOPIC_UNLABELED: _HeldSink()}, 6)
    assert stats.start_held_ms == 0.0
    np.testing.assert_allclose(np.diff(stamps[B.TOPIC_UNLABELED]) * 1e-9, 1 / 120, atol=2e-6)


def test_the_monitor_times_delivery_not_its_own_callbacks():
    """ReplayMonitor's latency is the DDS reception time minus the stamp: a labelled message
    that arrives while the monitor's own thread is held (here its lock, 0.4 s; in dtm-demo a
    garbage collection of 35-75 ms) counts its delivery, not the hold."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from dtm_labeler.ros.player import ReplayMonitor
    from dtm_labeler_msgs.msg import LabeledMarkerArray

    ts = B.typestore()
    ctx = rclpy.Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("test_monitor_source", context=ctx)
    pub = node.create_publisher(LabeledMarkerArray, "markers/labeled",
                                QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    def send():
        stamp = time.time_ns()
        pub.publish(bytes(ts.serialize_cdr(B.marker_array_message(stamp, "f", 0, np.zeros((1, 3)), np.array([0]),
                                                                  ["a"]), B.LMA)))
    try:
        with ReplayMonitor(known_labels=["a"]) as mon:
            deadline = time.monotonic() + 20
            while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            send()                                   # a first one, delivered as usual
            while mon.n_labeled < 1 and time.monotonic() < deadline:
                time.sleep(0.01)
            with mon.lock:                           # the monitor's thread is held from here ...
                send()                               # ... in this message's callback
                time.sleep(0.1)
                send()                               # arrives while it is held
                time.sleep(0.3)
            while mon.n_labeled < 3 and time.monotonic() < deadline:
                time.sleep(0.01)
            with mon.lock:
                lat = list(mon.latency_ms)
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    assert len(lat) == 3
    assert lat[2] < 150, lat                         # held 0.3 s after it arrived: not counted (~300 before)
