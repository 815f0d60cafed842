"""The node's worker thread (ros/worker.py) without a node: one slot, replaced frames carried.

A frame handler that takes 15 ms per searched frame is fed a frame every 2 ms: the worker
searches the newest frame only, and every frame it replaced is handed to the handler as
*carried* (the tracker follows it, it is published with the labels its tracks carry) before
the newer one -- so no frame is lost and the order is kept. A pending reset drops the replaced
frames instead (counted stale): their tracks are about to be forgotten.
"""
from __future__ import annotations

import threading
import time

import numpy as np

from dtm_labeler.ros.worker import OBSERVED_SKIPS, Frame, LabelWorker


def _frame(k: int) -> Frame:
    return Frame(np.zeros((3, 3)), None, None, float(k), float(k), time.perf_counter(), 0.0, k)


class Recorder:
    """The frame handler: a search takes ``search_s``; with ``gate`` the first search waits
    until the test opens it (every frame submitted meanwhile: no timing involved)."""

    def __init__(self, search_s: float, gate: threading.Event | None = None):
        self.search_s = search_s
        self.gate = gate
        self.entered = threading.Event()           # the first search has begun
        self.calls: list[tuple[int, bool]] = []
        self.events: list[tuple[str, object]] = []
        self.lock = threading.Lock()

    def label(self, frame: Frame, engine, carried: bool = False) -> None:
        if not carried:
            if self.gate is not None:
                self.entered.set()
                assert self.gate.wait(10.0)
            time.sleep(self.search_s)
        with self.lock:
            self.calls.append((frame.frame_number, carried))

    def on_event(self, kind: str, detail) -> None:
        with self.lock:
            self.events.append((kind, detail))


def _run(rec: Recorder, n: int, period_s: float, reset_at: int | None = None) -> tuple[LabelWorker, int]:
    w = LabelWorker(rec.label, rec.on_event, settings=None)
    w.start()
    dropped = 0
    for k in range(n):
        if k == reset_at:
            w.request_reset("test")
        dropped += w.submit(_frame(k)) is not None
        if k == 0 and rec.gate is not None:
            assert rec.entered.wait(5.0)           # frame 0 is being searched
        time.sleep(period_s)
    if rec.gate is not None:
        rec.gate.set()
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        with rec.lock:
            handled = len(rec.calls) + sum(d for kind, d in rec.events if kind == "stale")
        if handled + dropped >= n:
            break
        time.sleep(0.01)
    assert w.stop(1.0)
    return w, dropped


def test_replaced_frames_are_carried_in_order_and_none_is_lost():
    rec = Recorder(search_s=0.010)
    _, dropped = _run(rec, 120, 0.002)
    frames = [k for k, _ in rec.calls]
    carried = sum(c for _, c in rec.calls)
    searched = len(rec.calls) - carried
    assert not [e for e in rec.events if e[0] == "stale"]
    assert len(frames) + dropped == 120 and dropped <= 8
    assert frames == sorted(set(frames)), "every frame is handled once at most, in order"
    assert carried > searched > 0      # the slow handler searched a fraction, the rest were carried
    # a carried frame is always followed (eventually) by a searched one: the newest is searched
    assert rec.calls[-1][1] is False


def test_a_long_stall_drops_only_what_falls_out_of_the_carry_list():
    rec = Recorder(search_s=0.0, gate=threading.Event())
    _, dropped = _run(rec, 60, 0.001)
    frames = [k for k, _ in rec.calls]
    assert dropped > 0                                  # more than OBSERVED_SKIPS frames piled up
    assert len(frames) + dropped == 60
    assert frames == sorted(frames) and frames[-1] == 59
    # frame 0's search waits until all are submitted; of the 58 that arrive meanwhile, the newest OBSERVED_SKIPS
    # are carried, then the newest one is searched
    assert rec.calls[0] == (0, False) and rec.calls[-1] == (59, False)
    assert rec.calls[1:-1] == [(k, True) for k in range(59 - OBSERVED_SKIPS, 59)]


def test_a_pending_reset_drops_the_replaced_frames_as_stale():
    rec = Recorder(search_s=0.0, gate=threading.Event())
    _, dropped = _run(rec, 40, 0.001, reset_at=20)
    stale = sum(d for kind, d in rec.events if kind == "stale")
    assert rec.calls == [(0, False), (39, False)]       # nothing carried across the reset
    assert stale == OBSERVED_SKIPS and dropped == 40 - 2 - OBSERVED_SKIPS
