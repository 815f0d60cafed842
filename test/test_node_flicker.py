"""The live node under marker flicker keeps labelling (issue 12's reset spiral, real processes).

``dtm-demo`` runs the node and a bag player in their own processes over DDS (loopback, this
session's ROS_DOMAIN_ID): a synthetic walker at 120 Hz for 10 s with 2 of its 14 markers hidden
and a new pair hidden every frame, plus 2 ghost points. The node's searches run in its
background worker (the node's default), frames go on with the labels the tracks carry, and
a frame replaced while the worker was busy is still followed by the tracker and published
with the labels its tracks carry -- so the node labels nearly every frame it is sent instead
of a few per second. Floors with margin for a loaded 2-core machine.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dtm_labeler.cli.demo import ros_env

pytestmark = pytest.mark.realtime      # judged against the wall clock: README runs it alone


def test_flicker_stream_is_labelled_frame_after_frame(tmp_path):
    demo = Path(sys.executable).parent / "dtm-demo"
    cmd = [str(demo)] if demo.is_file() else [sys.executable, "-m", "dtm_labeler.cli.demo"]
    env = ros_env(int(os.environ["ROS_DOMAIN_ID"]))
    env["XDG_CACHE_HOME"] = str(tmp_path.parent / "demo_cache")        # the demo model is trained once
    out = subprocess.run(cmd + ["--occlude", "2", "--gap-frames", "1", "--clutter", "2", "--duration", "10",
                                "--json", "--quiet"], env=env, capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr[-2000:]
    d = json.loads(out.stdout[out.stdout.index("{"):])
    assert d["node_ok"] and d["frames_sent"] >= 1100
    assert d["frames_labelled"] >= 0.95 * d["frames_sent"], d      # searched, or carried by the tracks
    assert d["frames_labelled"] - d["frames_carried"] >= 0.5 * d["frames_sent"], d   # the searches keep up
    # anytime recovery: the search's interim results label the start of the stream after a few
    # frames (before them: the first ~20 frames stayed unlabelled, 97.5 % on a quiet machine)
    assert d["accuracy"] >= 0.97 and d["ghost_rejection"] >= 0.8, d
    assert d["frames_with_errors"]["accuracy_from_first_right_frame"] >= 0.98, d   # steady state
