"""The node's worker thread: owns the labeler, labels the newest frame, never queues.

* Frames arrive in a ONE-SLOT buffer (:meth:`LabelWorker.submit`): a frame still
  waiting there is replaced by the newer one -- there is no other queue of searches in the node
  (DDS history is keep-last), so latency cannot build up: when labeling is slower than the input,
  the node searches the newest frame only. The replaced frames are not dropped: the newest
  ``OBSERVED_SKIPS`` of them are *carried* before the newest is searched -- the tracker follows
  each (:meth:`NodeLabeler.observe`, a fraction of a millisecond) and it is published, in order,
  with the labels its tracks carry (diagnostics ``frames_carried``). The tracks -- and their
  labels -- survive the skip, the next frame needs no new search, and a burst of slow frames
  leaves no hole in the output. A frame older than ``carry_max_ms`` by the time the worker
  reaches it is only followed by the tracker (the handler decides), one pushed out of that
  list or replaced while a reset is pending (a gap, a loop: the tracks are about to be
  forgotten) is dropped; those count ``stale``. A reset a dropped frame asked for is carried
  over to the frame that replaces it.
* With an ``inbox`` (:class:`~.inbox.Inbox`, the node's case) the worker reads the input itself:
  it waits on the inbox when it has nothing to do, else takes what arrived during the last frame,
  and hands the messages to ``receive(sub, messages, full)`` (the node decodes them and submits,
  in this thread); :meth:`submit` from another thread (tests) and every request below wake it.
* Between two frames the worker swaps in what the loader prepared (:meth:`install`), applies the
  newest settings (:meth:`settings`; older ones waiting are dropped) and runs a requested reset
  (:meth:`request_reset`) -- all fast: the slow part (reading files, widening the model) was done
  by the loader thread.
* The worker is the only thread that touches the :class:`~.engine.NodeLabeler`. It calls
  ``label(frame, engine)`` (the node's frame handler; ``label(frame, engine, True)`` for a frame
  to carry) and ``on_event(kind, detail)`` for what the node reports: ``loaded`` ((LoadResult,
  new | replaced | swapped | same | unloaded)), ``load_failed`` (LoadResult), ``settings``,
  ``reset`` (reason), ``stale`` (how many replaced frames were dropped), ``error`` (text). :meth:`stop` returns within its timeout even during a long search (the
  thread is a daemon; the handler must not publish once :attr:`stopping` is set).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Callable, List, Optional

from .engine import NodeLabeler
from .loader import LoadResult

__all__ = ["Frame", "LabelWorker", "OBSERVED_SKIPS"]

#: replaced frames carried (followed by the tracker, published) before the next searched frame
OBSERVED_SKIPS = 16


@dataclass
class Frame:
    """One decoded input frame on its way to the labeler."""

    xyz: Any                     # (n, 3) float64
    ids: Any                     # (n,) int64 for every point, or None (partial ids are dropped)
    header: Any                  # the output header (frame_id filled in)
    stamp: float                 # the labeler's time (stamps.StampGuard)
    header_stamp: float          # the header's own stamp (visualisation throttle)
    t_recv: float                # perf_counter() at callback entry
    decode_ms: float
    frame_number: Optional[int] = None
    resets: List[str] = field(default_factory=list)     # reset the window first, for these reasons


class LabelWorker:
    def __init__(self, label: Callable[..., None],
                 on_event: Callable[[str, Any], None], settings: Any, name: str = "dtm_labeler_worker",
                 inbox: Any = None, receive: Optional[Callable[[Any, list, bool], None]] = None):
        self._label = label
        self._inbox, self._receive = inbox, receive
        self.current_settings = settings      # what engines are built with (newest applied)
        self._on_event = on_event
        self._cond = threading.Condition()
        self._slot: Optional[Frame] = None
        self._skipped: List[Frame] = []       # frames replaced in the slot, for the tracker
        self._result: Optional[LoadResult] = None
        self._settings: Any = None
        self._reset: List[str] = []
        self._stop = False
        self._paused = False
        self.engine: Optional[NodeLabeler] = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    @property
    def stopping(self) -> bool:
        return self._stop

    def start(self) -> None:
        if not self._thread.is_alive():
            self._thread.start()

    def stop(self, timeout: float = 0.3) -> bool:
        """Stop; True when the thread ended within ``timeout``."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._wake()
        if self._thread.is_alive():
            self._thread.join(timeout)
        return not self._thread.is_alive()

    # -- from other threads ------------------------------------------------------------------
    def submit(self, frame: Frame) -> Optional[Frame]:
        """Put ``frame`` in the slot; the frame it replaces joins the frames to carry. Returns
        the frame dropped for good (stale: pushed out of that list), if any."""
        with self._cond:
            old, self._slot = self._slot, frame
            dropped = None
            if old is not None:
                frame.resets = old.resets + frame.resets
                self._skipped.append(old)
                if len(self._skipped) > OBSERVED_SKIPS:
                    dropped = self._skipped.pop(0)
            self._cond.notify()
        if threading.current_thread() is not self._thread:
            self._wake()
        return dropped

    def install(self, result: LoadResult) -> None:
        with self._cond:
            self._result = result
            self._cond.notify()
        self._wake()

    def settings(self, settings: Any) -> None:
        with self._cond:
            self._settings = settings
            self._cond.notify()
        self._wake()

    def request_reset(self, reason: str) -> None:
        with self._cond:
            self._reset.append(reason)
            self._cond.notify()
        self._wake()

    def discard(self) -> int:
        """Drop the waiting frame and the frames to carry (input closed); returns how many."""
        with self._cond:
            n = (self._slot is not None) + len(self._skipped)
            self._slot, self._skipped = None, []
            return n

    def drop_engine(self) -> None:
        """Forget the engine and anything the loader delivered for it (lifecycle cleanup)."""
        with self._cond:
            old, self.engine, self._result = self.engine, None, None
        if old is not None:
            old.close()

    # -- worker thread -------------------------------------------------------------------------
    def _wake(self) -> None:
        if self._inbox is not None:
            self._inbox.wake()

    def _idle(self) -> bool:
        return self._slot is None and self._result is None and self._settings is None and not self._reset

    def _run(self) -> None:
        while True:
            if self._inbox is not None:          # read the input here (ros/inbox.py)
                with self._cond:
                    idle = self._idle()
                if self._stop:
                    return
                # wait only with nothing to do; else just take what came during the last frame
                sub, messages, full = self._inbox.poll(None if idle else 0.0)
                if messages:
                    try:
                        self._receive(sub, messages, full)
                    except Exception as e:     # never let the worker die
                        self._on_event("error", f"input: {type(e).__name__}: {e}")
            with self._cond:
                while self._inbox is None and self._idle() and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                frame, self._slot = self._slot, None
                skipped, self._skipped = self._skipped, []
                result, self._result = self._result, None
                settings, self._settings = self._settings, None
                resets, self._reset = self._reset, []
            self._between_frames(result, settings, resets)
            if frame is not None and not self._stop:
                if resets or frame.resets:
                    if skipped:
                        self._on_event("stale", len(skipped))
                else:
                    for f in skipped:
                        if self._stop:
                            break
                        self._label(f, self.engine, True)
                self._label(frame, self.engine)
            elif skipped:
                self._on_event("stale", len(skipped))

    def _between_frames(self, result: Optional[LoadResult], settings: Any, resets: List[str]) -> None:
        try:
            if settings is not None:
                self.current_settings = settings
            if result is not None:
                self._swap(result)
            if settings is not None and self.engine is not None and self.engine.update_settings(settings):
                self._on_event("settings", settings)
            if resets and self.engine is not None:
                self.engine.reset()
                for reason in resets:
                    self._on_event("reset", reason)
        except Exception as e:   # never let the worker die
            self._on_event("error", f"{type(e).__name__}: {e}")

    def _swap(self, result: LoadResult) -> None:
        if result.error:
            self._on_event("load_failed", result)
            return
        p, old = result.prepared, self.engine
        if p is None:
            self.engine, change = None, "unloaded"
        elif old is not None and old.prepared is p:
            change = "same"                        # the same models: nothing to swap
        elif old is not None and not result.request.reload and old.same_source(p):
            old.swap_models(p)                     # another noise (or bank settings): tracks stay
            change = "swapped"
        else:
            self.engine = NodeLabeler(p, self.current_settings)
            change = "replaced" if old is not None else "new"
        if old is not None and self.engine is not old:
            old.close()
        self._on_event("loaded", (result, change))
