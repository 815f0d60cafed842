"""The worker reads the input subscription itself (ros/inbox.py): clouds that arrive over DDS
while it searches wait in the subscription's history, and are then carried, in order, before
the newest is searched; when more arrived than the history holds, the ones pushed out count
as stale, not as lost before the node. The executor never runs the input callback and stays
free meanwhile (a parameter request is answered while the search is held).

In-process node (the search is held at a gate: no timing involved) spun by its executor on a
thread, a publisher node in the same process over DDS (reliable: ``wait_for_all_acked`` says
every cloud is in the node's subscription history before the gate opens).
"""
from __future__ import annotations

import threading
import time

from rclpy.serialization import deserialize_message

import node_helpers as H

SENT_WHILE_HELD = 25         # more than the history (OBSERVED_SKIPS + 1 = 17)


def test_clouds_arriving_during_a_search_wait_in_dds_and_are_carried():
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from dtm_labeler.ros.node import LabelerNode
    from dtm_labeler.ros.worker import OBSERVED_SKIPS
    from dtm_labeler_msgs.msg import LabeledMarkerArray
    wm = H.walk_model()
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ns = "/t_inbox"
    node = LabelerNode(context=ctx, namespace=ns,
                       parameter_overrides=[Parameter("model_path", value=str(wm.path)),
                                            Parameter("recovery", value="inline"),
                                            Parameter("input_qos", value="reliable"),
                                            Parameter("carry_max_ms", value=10000.0)])
    core = node.core
    published = []
    core.outputs.labeled.publish = published.append
    called_by_executor = []
    node.core.sub.callback = lambda *a: called_by_executor.append(a)     # the executor must never call it
    pub_node = rclpy.create_node("t_inbox_player", namespace=ns, context=ctx)
    pub = pub_node.create_publisher(PointCloud2, "markers/unlabeled",
                                    QoSProfile(depth=64, reliability=ReliabilityPolicy.RELIABLE))
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    spinner.start()
    try:
        end = time.monotonic() + 30
        while (core.worker.engine is None or pub.get_subscription_count() == 0) and time.monotonic() < end:
            time.sleep(0.01)
        assert core.worker.engine is not None and pub.get_subscription_count() == 1
        search = H.HeldSearch(core.worker.engine, timeout=30)
        feed = H.FrameFeed(wm, seed=5)
        truths = []

        def send():
            xyz, truth, stamp = feed.next()
            truths.append(truth)
            pub.publish(H.stamped_cloud(xyz, stamp))
        H.send_one_by_one(send, published, 10, end + 30)     # warm: tracks and labels established
        base = len(published)
        truths.clear()
        search.hold()
        send()
        assert search.entered.wait(30)                # frame 0 is being searched
        for _ in range(SENT_WHILE_HELD):
            send()
        assert pub.wait_for_all_acked(rclpy.duration.Duration(seconds=30))    # all in the node's history
        # the executor is free while the worker searches: a parameter request is answered
        assert node.get_parameter("carry_max_ms").value == 10000.0
        search.release()
        kept = OBSERVED_SKIPS + 1                # the subscription's history: the newest 17 clouds
        pushed_out = SENT_WHILE_HELD - kept
        end = time.monotonic() + 30
        while len(published) - base < 1 + kept and time.monotonic() < end:
            time.sleep(0.002)
        out = [deserialize_message(b, LabeledMarkerArray) for b in published[base:]]
        assert len(out) == 1 + kept
        assert core.stats.frames_carried == kept - 1
        assert core.stats.skipped["stale"] == pushed_out and core.stats.lost_before_node == 0
        assert not called_by_executor
        H.assert_in_order_with_own_labels(out, truths, [0] + list(range(1 + pushed_out, 1 + SENT_WHILE_HELD)))
    finally:
        search.release() if "search" in locals() else None
        ex.shutdown(timeout_sec=1.0)
        node.destroy_node()
        pub_node.destroy_node()
        ctx.try_shutdown()
