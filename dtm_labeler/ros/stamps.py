"""Time for the labeler from the stamps the node receives, and the source it follows.

The labeler needs a time axis that only moves forward at the capture rate: velocities (eq. 12)
are position differences over it, and the tracker predicts along it. Header stamps are that
axis when the driver fills them well; when it does not, labelling on them resets or garbles
every frame. :class:`StampGuard` names the faults and keeps the axis usable:

* ``zero`` (stamp 0), ``repeated`` (same stamp again), ``backwards`` (earlier than the last good
  one) and ``jump`` (later by more than ``max_gap_s`` while frames arrived on time) are stamp
  faults. A faulty frame gets the last labeler time plus the frame period (the median of recent
  good stamp intervals; the receive interval before one is known) times the number of periods
  since the last frame was received, so a single fault neither resets nor bends velocities.
* Three faults within 20 frames switch the time base to receive time for good (stamps that are
  zero, repeated or alternating between two clocks); 60 clean frames in a row switch back. The
  labeler's time stays continuous across both switches (an offset is kept).
* A single discontinuity in a clean stream (no fault in 20 frames, no restart of its kind in 240)
  is what it looks like: a gap longer than ``max_gap_s`` (in stamps alone, or also in receive time) or a bag
  loop / restart (stamps back by more than ``max_gap_s``) resets the window once, and the stream
  continues from the new stamps. A pause in reception itself is always a gap.
* Frames lost before the node (DDS drops, a driver skipping) are estimated from good stamp
  intervals: ``round(interval / period) - 1`` per interval.

:class:`SourceLock` follows one publisher when two interleave on the input topic, by the DDS
publication sequence number rclpy gives with each message (strictly increasing per publisher):
a frame that does not continue the followed sequence comes from another publisher and is
dropped (counted as ``other_source``) while the followed one keeps publishing; sequence gaps of
the followed publisher are frames DDS lost (exact, where the middleware reports sequence
numbers). Both classes are pure Python (no rclpy).
"""
from __future__ import annotations

import collections
import statistics
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

from ..labeling.config import STAMP_SOURCES

__all__ = ["StampGuard", "StampVerdict", "SourceLock", "STAMP_SOURCES"]

_WINDOW, _TO_FALLBACK, _TO_RECOVER, _RESTART_SPACING = 20, 3, 60, 240
_MIN_STEP = 1e-4


@dataclass
class StampVerdict:
    stamp: float          # the labeler's time for this frame (strictly increasing)
    fault: str = ""       # zero | repeated | backwards | jump | ""
    reset: str = ""       # why the labeler's window must be reset before this frame
    lost: int = 0         # frames estimated lost just before this one
    time_base: str = "header"


class StampGuard:
    """See the module doc. ``source``: ``auto`` (header stamps, receive time after faults),
    ``header`` (stamps only: faults are named, never fallen back from) or ``receive``."""

    def __init__(self, max_gap_s: float = 0.5, source: str = "auto"):
        if source not in STAMP_SOURCES:
            raise ValueError(f"stamp source must be one of {', '.join(STAMP_SOURCES)}, got {source!r}")
        self.max_gap_s = float(max_gap_s)
        self.source = source
        self.reset()

    def reset(self) -> None:
        self.time_base = "receive" if self.source == "receive" else "header"
        self._lab: Optional[float] = None          # last labeler time
        self._recv: Optional[float] = None         # last receive time
        self._good: Optional[float] = None         # last good header stamp
        self._offset = 0.0                         # labeler time = header stamp + offset
        self._faults: collections.deque = collections.deque(maxlen=_WINDOW)
        self._clean = 0
        self._since_restart = _RESTART_SPACING     # frames since the last restart (a loop, a jump)
        self._restart_kind = ""
        self._dts: collections.deque = collections.deque(maxlen=32)    # good stamp intervals
        self._rts: collections.deque = collections.deque(maxlen=32)    # receive intervals
        self._period: Optional[float] = None
        self._period_age = 0                       # samples since the period was computed

    def configure(self, max_gap_s: float, source: str) -> None:
        """New parameters for the running stream: the labeler's time goes on without a step
        (a new guard would restart it at the next header stamp: a jump the labeler is not told of)."""
        if source not in STAMP_SOURCES:
            raise ValueError(f"stamp source must be one of {', '.join(STAMP_SOURCES)}, got {source!r}")
        self.max_gap_s = float(max_gap_s)
        if source != self.source:
            self.source = source
            self.time_base = "receive" if source == "receive" else "header"
            if self.time_base == "header" and self._lab is not None and self._good is not None:
                self._offset = self._lab - self._good
            self._faults.clear()
            self._clean = 0

    @property
    def period(self) -> Optional[float]:
        """The frame period (s): median good stamp interval, else median receive interval
        (recomputed every 8 new intervals: the callback stays in microseconds)."""
        if self._period is None or self._period_age >= 8:
            src = self._dts if len(self._dts) >= 4 else self._rts
            self._period = statistics.median(src) if len(src) >= 4 else None
            self._period_age = 0
        return self._period

    def check(self, stamp: float, t_recv: float) -> StampVerdict:
        """The labeler time of a frame with header ``stamp`` received at ``t_recv`` (s, steady)."""
        if self._lab is None:
            return self._first(stamp, t_recv)
        r = max(t_recv - self._recv, 0.0)
        self._recv = t_recv
        if r > 0:
            self._rts.append(r)
            self._period_age += 1
        if self.time_base == "receive":
            return self._on_receive_time(stamp, r)
        fault, d = self._classify(stamp)
        if not fault:
            return self._good_frame(stamp, d)
        return self._discontinuity(stamp, r, d, fault)

    # -- cases ---------------------------------------------------------------------------------
    def _first(self, stamp: float, t_recv: float) -> StampVerdict:
        self._recv = t_recv
        if self.source == "receive" or stamp == 0.0:
            self._lab = t_recv
            self._offset = t_recv - stamp
            fault = "zero" if stamp == 0.0 and self.source != "receive" else ""
            self._note(fault)
            return StampVerdict(self._lab, fault, time_base=self.time_base)
        self._lab, self._good = stamp, stamp
        return StampVerdict(stamp, time_base=self.time_base)

    def _classify(self, stamp: float) -> Tuple[str, float]:
        d = stamp - self._good if self._good is not None else float("nan")
        if stamp == 0.0:
            return "zero", d
        if self._good is None:
            return "", d
        if d == 0.0:
            return "repeated", d
        if d < 0.0:
            return "backwards", d
        if d > self.max_gap_s:
            return "jump", d
        return "", d

    def _good_frame(self, stamp: float, d: float) -> StampVerdict:
        lost = 0
        if d == d:                                  # not the first good stamp
            p = self.period if len(self._dts) >= 8 else None
            if p and d > 1.5 * p:
                lost = int(round(d / p)) - 1
            else:
                self._dts.append(d)
                self._period_age += 1
        self._good = stamp
        self._note("")
        return self._emit(stamp + self._offset, "", "", lost)

    def _discontinuity(self, stamp: float, r: float, d: float, fault: str) -> StampVerdict:
        clean = not any(self._faults) and (self._since_restart >= _RESTART_SPACING or fault != self._restart_kind)
        if fault == "jump" and r > 0.5 * self.max_gap_s:
            return self._restart(stamp, "", f"gap of {d:.2f} s")          # the stream really paused
        if clean and fault in ("jump", "backwards") and abs(d) > self.max_gap_s:
            reason = f"gap of {d:.2f} s" if d > 0 else f"time went backwards by {-d:.2f} s"
            return self._restart(stamp, fault, reason)                   # one step: a new timeline
        self._note(fault)
        if self.source == "auto" and sum(self._faults) >= _TO_FALLBACK:
            self.time_base = "receive"
            self._clean = 0
        return self._emit(self._lab + self._step(r), fault, "", 0)

    def _restart(self, stamp: float, fault: str, reason: str) -> StampVerdict:
        self._note(fault)
        if fault:
            self._since_restart, self._restart_kind = 0, fault
        self._good = stamp
        lab = self._lab + max(self._step(0.0), _MIN_STEP)
        self._offset = lab - stamp
        return self._emit(lab, fault, reason, 0)

    def _on_receive_time(self, stamp: float, r: float) -> StampVerdict:
        fault = ""
        if self.source == "auto":         # watch the stamps: 60 clean ones in a row switch back
            fault, _ = self._classify(stamp)
            self._clean = 0 if fault else self._clean + 1
            if stamp != 0.0:
                self._good = stamp        # a new timeline (clock step, loop) can become clean
        lab = self._lab + self._step(r)
        if self.source == "auto" and self._clean >= _TO_RECOVER:
            self.time_base = "header"
            self._faults.clear()
            self._offset = lab - stamp
        return self._emit(lab, fault, "", 0)

    # -- helpers -------------------------------------------------------------------------------
    def _step(self, r: float) -> float:
        p = self.period
        if p:
            return p * max(1, int(round(r / p)))
        return max(r, _MIN_STEP)

    def _note(self, fault: str) -> None:
        self._faults.append(bool(fault))
        self._since_restart += 1

    def _emit(self, lab: float, fault: str, reset: str, lost: int) -> StampVerdict:
        lab = max(lab, self._lab + _MIN_STEP) if self._lab is not None else lab
        self._lab = lab
        return StampVerdict(lab, fault, reset, lost, self.time_base)


class SourceLock:
    """Follows one publisher by its publication sequence numbers (see the module doc)."""

    MAX_STEP = 256               # a larger step is another publisher (or the followed one restarted)

    def __init__(self, silence_s: float = 0.5):
        self.silence_s = float(silence_s)
        self.reset()

    def reset(self) -> None:
        self._seq: Optional[int] = None
        self._t = 0.0
        self.lost = 0            # sequence gaps of the followed publisher

    def accept(self, seq: Optional[int], t_recv: float,
               publishers: Callable[[], int] = lambda: 2) -> Tuple[bool, str]:
        """``(take the frame, event)``; event ``""``, ``"other"`` (dropped: another publisher) or
        ``"switched"`` (now following this one: the followed one went silent, or is the only one
        left matched -- ``publishers()`` <= 1, asked only then)."""
        if seq is None:
            return True, ""
        if self._seq is None:
            self._seq, self._t = seq, t_recv
            return True, ""
        step = seq - self._seq
        if 0 < step <= self.MAX_STEP:
            self.lost += step - 1
            self._seq, self._t = seq, t_recv
            return True, ""
        if t_recv - self._t > self.silence_s or publishers() <= 1:
            self._seq, self._t = seq, t_recv
            return True, "switched"
        return False, "other"
