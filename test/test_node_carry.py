"""Frames that arrive while the node's worker searches are carried, not dropped (in-process
node, no DDS peers; ros/worker.py, ros/output.py).

The first frame's search is held at a gate until five more frames have arrived -- no timing
involved. Then the worker publishes the four it replaced in order, with the labels their
tracks carry, and searches the newest: six frames out, ``frames_carried`` 4. With
``carry_max_ms`` 0 the four are too old to publish: the tracker follows them, they count
``stale``, two frames go out.
"""
from __future__ import annotations

import time

import pytest
from rclpy.serialization import deserialize_message

import node_helpers as H


@pytest.mark.parametrize("carry_max_ms, published_n, carried_n, stale_n", [(10000.0, 6, 4, 0), (0.0, 2, 0, 4)])
def test_frames_replaced_during_a_search_are_carried(carry_max_ms, published_n, carried_n, stale_n):
    import rclpy
    from rclpy.parameter import Parameter

    from dtm_labeler.ros.node import LabelerNode
    from dtm_labeler_msgs.msg import LabeledMarkerArray
    wm = H.walk_model()
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = LabelerNode(context=ctx, namespace=f"/t_carry{int(carry_max_ms)}",
                       parameter_overrides=[Parameter("model_path", value=str(wm.path)),
                                            Parameter("recovery", value="inline"),
                                            Parameter("carry_max_ms", value=carry_max_ms)])
    published = []
    node.core.outputs.labeled.publish = published.append
    core = node.core
    try:
        end = time.monotonic() + 20
        while core.worker.engine is None and time.monotonic() < end:     # loaded off the executor
            time.sleep(0.01)
        search = H.HeldSearch(core.worker.engine, timeout=20)
        feed = H.FrameFeed(wm, seed=5)
        truths = []

        def send():
            xyz, truth, stamp = feed.next()
            truths.append(truth)
            core._on_input(H.stamped_cloud(xyz, stamp))
        H.send_one_by_one(send, published, 10, end + 20)     # warm: tracks and labels established
        base = len(published)
        truths.clear()
        search.hold()
        send()
        assert search.entered.wait(20)
        for _ in range(5):
            send()
        search.release()
        end = time.monotonic() + 20
        while len(published) - base + core.stats.skipped["stale"] < 6 and time.monotonic() < end:
            time.sleep(0.002)
        out = [deserialize_message(b, LabeledMarkerArray) for b in published[base:]]
        assert len(out) == published_n and core.stats.skipped["stale"] == stale_n
        assert core.stats.frames_carried == carried_n
        H.assert_in_order_with_own_labels(out, truths, [0, 1, 2, 3, 4, 5] if published_n == 6 else [0, 5])
    finally:
        node.destroy_node()
        ctx.try_shutdown()
