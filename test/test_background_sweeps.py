"""A doubted frame in the background asks for the exact region sweep from the carried labeling,
and for the warm GA at most once per ``audit_period_s`` of stream time
(:meth:`~dtm_labeler.labeling.tracked.TrackedLabeler._search_kind`).

HDM05's 41 markers with half of the samples hidden (gaps of ~0.25 s): nearly every frame is
doubted. Background recovery made deterministic (``DeferredRecovery``): a GA's result 25 frames
after the request (its first interim result after 2), a sweep's after 2 -- a worker takes 10-20 ms
for a sweep at 41 markers."""
import numpy as np
import pytest

from dtm_labeler.labeling.recovery import DeferredRecovery
from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler
from background_runs import background_run, half_hidden_frames


@pytest.fixture(scope="module")
def stream(hdm05_calibrated, hdm05_take):
    """:func:`conftest.hdm05_half_hidden`'s kind of stream, frames 3600-3840 with gap draw 1:
    one whose sweeps replace the carried labeling (three joins; 74 % right). The
    conftest's draw, whose own joins recover it, has no sweep that beats the carried labeling."""
    return half_hidden_frames(hdm05_calibrated, hdm05_take, 3600, draw=1)


def _run(model, frames, period: float):
    """(share of the visible markers labelled right, [(kind, stamp) of every request],
    [kind of the request whose result each joined frame took])."""
    run = background_run(model, frames, audit_period_s=period)
    return run["accuracy"], run["asked"], run["joined"]


def test_a_doubted_stream_asks_for_sweeps_between_warm_searches(hdm05_calibrated, stream):
    acc, asked, joined = _run(hdm05_calibrated, stream, period=1.0)
    kinds = [k for k, _ in asked]
    assert kinds[0] == "full"                                   # nothing carried yet
    warm = [t for k, t in asked if k == "recover"]
    assert 1 <= len(warm) <= 3                                  # 2 s of stream: at most one per second
    assert np.all(np.diff(warm) >= 1.0 - 1e-9)
    assert kinds.count("sweep") > 10 * len(warm)                # the worker's answers come every few frames
    assert "sweep" in joined                                    # and a sweep's labeling replaced the carried one
    assert acc > 0.5


def test_without_audits_every_doubted_frame_asks_for_the_warm_search(half_hidden_background):
    """``audit_period_s`` 0 (audits off): the warm GA every time, as before the sweeps."""
    asked = half_hidden_background["asked"]                    # _run on the stream, period 0
    kinds = [k for k, _ in asked]
    assert "sweep" not in kinds and kinds.count("recover") >= 5


def test_deferred_recovery_hands_out_a_sweep_sooner(hdm05_calibrated, stream):
    """``DeferredRecovery(sweep_frames=k)``: a sweep's result k polls after the request, a GA's
    after ``delay_frames``."""
    lab = StreamLabeler(hdm05_calibrated, LabelerSettings(recovery="background", audit_period_s=0))
    lab.recovery.close()
    rec = lab.recovery = DeferredRecovery(lab, delay_frames=25, sweep_frames=2)
    for fr in stream[:3]:
        lab.process(fr.xyz, fr.stamp)
    while rec.busy:                                             # the stream's first (full) search
        rec.poll()
    problems, inp, found = lab.last_frame
    carried = found.best.assignment[None]
    polls = {}
    for kind in ("sweep", "recover"):
        rec.submit(lab._request(problems, inp, [0], carried, kind))
        k = 1
        while rec.poll() is None:
            k += 1
        polls[kind] = k
    assert polls == {"sweep": 2, "recover": 25}
