"""Parameters and models never stall labeling (real process, real DDS, a 120 Hz stream from this
process): 100 noise_mm sets coalesce into a few rebuilds off the labeling thread; a model file
holding an array far beyond a model's size is refused from its headers before anything is
allocated; a good reload happens while labelling goes on; SIGTERM during a load and a search
exits 0 within a second.

"Stall" = the longest time a frame waited for the worker while the worker was not labelling
(``stall_max_ms`` in /diagnostics, measured in the node over its last 500 frames: from "a frame
is there and the previous one is done" to "its labelling starts" -- engine swaps, settings,
resets, and any thread holding the worker up); bound 0.5 s, as in issue 12. It is measured in
the node because this test's own process (a 120 Hz publisher, 100 service calls) is starved as
much as the node on a loaded 2-core machine: the gaps it sees include its own delays (they are
shown in the assertion messages). The labeler's own search time is not the node's: a reload or a new noise starts a new
labeler, whose first frame is a full search (100-650 ms here under load), and its bounded
per-frame time is the labeler's part of issue 12. The stream carries persistent marker ids (as
Qualisys and Vicon streams do), so skipped frames do not break the labeler's tracks."""
from __future__ import annotations

import io
import signal
import time
import zipfile

import numpy as np
import pytest

import node_helpers as H

pytestmark = pytest.mark.realtime      # output gaps and exit times against the wall clock: run alone

MAX_STALL_S = 0.5


@pytest.fixture(scope="module")
def streaming():
    wm = H.walk_model()
    proc, cl = H.start("t_stall", params={"model_path": wm.path, "diagnostics_period_s": 0.1,
                                          "publish_visualization": False})
    streamer = H.Streamer(cl, H.FrameFeed(wm, seed=9), rate=120.0, ids=True)
    cl.wait_for(lambda: len(cl.labeled) > 30, 10, "a labelled stream")
    yield proc, cl, wm
    streamer.stop()
    cl.close()
    if proc.alive():
        proc.stop(signal.SIGKILL)


def node_stall(cl) -> float:
    """The node's longest stall (s) over its last 500 frames, from the next diagnostics."""
    n = len(cl.labeled)
    cl.wait_for(lambda: len(cl.labeled) > n + 5, 10, "more labelled frames")
    return float(cl.wait_diag(lambda d: True)["stall_max_ms"]) * 1e-3


def bomb_file() -> str:
    """A model file whose one array declares 256 MB (of zeros: the archive is small). np.load
    would allocate and inflate it; the node's header check refuses it."""
    wm = H.walk_model()
    with np.load(wm.path) as z:
        arrays = {k: z[k] for k in z.files}
    path = H._tmpdir() / "bomb.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as out:
        for k, a in arrays.items():
            buf = io.BytesIO()
            np.save(buf, a if k != "tri0_covariances" else np.zeros((32 * 2 ** 20,)))
            out.writestr(k + ".npy", buf.getvalue())
    return str(path)


def test_parameter_storm_coalesces(streaming):
    proc, cl, wm = streaming
    d0 = cl.wait_diag(lambda d: True)
    t0 = time.monotonic()
    for i in range(100):
        assert cl.set(noise_mm=float(1 + i % 10))[0].successful

    d = cl.wait_diag(lambda d: d["noise_mm"] == "10.0", 10, "the last noise_mm")
    cl.wait_diag(lambda d: int(d["models_prepared"]) > int(d0["models_prepared"]), 30, "the rebuilt model")
    t2 = time.monotonic()
    cl.wait_for(lambda: time.monotonic() > t2 + 0.5, 3, "more stream after the swap")
    assert node_stall(cl) < MAX_STALL_S, (cl.max_gap(t0, t2 + 0.5), cl.max_node_stall(t0, t2 + 0.5))
    d1 = cl.wait_diag(lambda d: True)
    rebuilds = int(d1["models_prepared"]) - int(d0["models_prepared"])
    assert 1 <= rebuilds <= 10, rebuilds        # 100 sets, the last wins: a few rebuilds at most
    assert d1["resets_model_reload"] == d0["resets_model_reload"]      # a new noise keeps the tracks
    assert int(d["frames_skipped_error"]) == 0


def test_oversized_model_file_refused_without_stalling(streaming):
    proc, cl, wm = streaming
    path = bomb_file()
    t0 = time.monotonic()
    r = cl.set(model_path=path)[0]
    assert not r.successful and "far beyond a model's size" in r.reason and f"keeping {wm.path}" in r.reason
    t1 = time.monotonic()
    assert t1 - t0 < MAX_STALL_S                 # answered from the headers
    cl.wait_for(lambda: time.monotonic() > t1 + 0.5, 3, "more stream")
    assert node_stall(cl) < MAX_STALL_S, (cl.max_gap(t0, t1 + 0.5), cl.max_node_stall(t0, t1 + 0.5))
    assert cl.get("model_path")["model_path"] == str(wm.path)


def test_reload_while_streaming(streaming):
    proc, cl, wm = streaming
    t0 = time.monotonic()
    assert cl.set(model_path=str(wm.alt_path))[0].successful
    cl.wait_diag(lambda d: d["model_path"] == str(wm.alt_path) and d["model_status"] == "loaded", 10, "reloaded")
    t1 = time.monotonic()
    cl.wait_for(lambda: time.monotonic() > t1 + 0.5, 3, "more stream")
    assert node_stall(cl) < MAX_STALL_S, (cl.max_gap(t0, t1 + 0.5), cl.max_node_stall(t0, t1 + 0.5))
    n = len(cl.labeled)
    cl.wait_for(lambda: len(cl.labeled) > n + 20, 5, "labelled frames after the reload")
    stamp = cl.stamp_of(cl.labeled[-1])
    assert stamp > 0 and cl.labeled[-1].label_names


def test_sigterm_during_a_load_and_a_search_exits_0_within_a_second(streaming):
    proc, cl, wm = streaming
    assert cl.set(model_path=str(wm.path), noise_mm=3.0)[0].successful     # a load under way
    assert proc.stop(signal.SIGTERM) == 0
    assert proc.stop_seconds < 1.0, proc.stop_seconds
    assert "Traceback" not in proc.log()
