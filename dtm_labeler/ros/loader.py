"""The node's loader thread: model files and noise widening off the executor and the worker.

A :class:`LoadRequest` asks for the engine of a source (model or bank) at a measurement noise.
Requests coalesce -- the last one wins: a request still waiting when a newer one arrives is
dropped, the loader waits :attr:`EngineLoader.SETTLE_S` before starting (a burst of parameter
sets becomes one rebuild), and a result that a newer request superseded while it was being
built is dropped too. So 100 ``noise_mm`` sets cost one or two rebuilds, and labeling goes on
with the old engine meanwhile. The file is read again only when the source changed or a reload
was asked for (``model_path`` set, even to the same path; ``~/reload``); a new noise re-widens
the model already loaded. Results go to ``deliver`` (the worker swaps them in between frames).
A calibration (``~/calibrate``) is a request too: the loaded model calibrated to the positions
it carries, kept for later noise changes until the file is read again; like any request it is
superseded by a newer one (a parameter set in the same instant: call ``~/calibrate`` again).
"""
from __future__ import annotations

import multiprocessing
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

from ..labeling.bank_labeler import BankSettings
from ..model.bank import ModelBank
from ..model.io import model_from_bytes, model_to_bytes
from ..training.calibrate import auto_calibration_process, calibrate, idle_priority, stream_calibration_target
from .engine import Prepared, Source, load, prepare

__all__ = ["LoadRequest", "LoadResult", "EngineLoader"]


@dataclass(frozen=True)
class LoadRequest:
    source: Source
    noise_mm: float
    bank_settings: BankSettings = field(default_factory=BankSettings)   # a bank's engine depends on them
    reload: bool = False       # read the file again even when the source is the loaded one
    generation: int = 0
    why: str = ""
    calibration: Optional[Any] = None    # a clip of confirmed labels: calibrate the loaded model to them
    clouds: Optional[tuple] = None       # with it, the window's points: the auto calibration (module doc)


@dataclass(frozen=True)
class LoadResult:
    request: LoadRequest
    prepared: Optional[Prepared]      # None: no model (empty source) or failed (error set)
    error: str = ""
    seconds: float = 0.0


class EngineLoader:
    """See the module doc. ``deliver(result)`` is called from the loader thread."""

    SETTLE_S = 0.03

    def __init__(self, deliver: Callable[[LoadResult], None], name: str = "dtm_labeler_loader"):
        self._deliver = deliver
        self._cond = threading.Condition()
        self._pending: Optional[LoadRequest] = None
        self._generation = 0
        self._busy = False
        self._stop = False
        self._cached: Optional[tuple] = None      # (source, base) last loaded
        self._calibrated: Optional[tuple] = None  # (source, base calibrated to the subject)
        self._last: Optional[Prepared] = None     # last delivered
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def generation(self) -> int:
        return self._generation

    def request(self, source: Source, noise_mm: float, bank_settings: BankSettings, reload: bool = False,
                why: str = "", calibration: Optional[Any] = None, clouds: Optional[tuple] = None) -> int:
        """Queue a request (replacing any waiting one); returns its generation. ``calibration``:
        a clip of confirmed labels to calibrate the loaded model's body terms to (``why``
        should say so); the calibrated model then serves every later request of the same
        source until the file is read again."""
        with self._cond:
            self._generation += 1
            self._pending = LoadRequest(source, float(noise_mm), bank_settings, reload, self._generation, why,
                                        calibration, None if clouds is None else tuple(clouds))
            self._cond.notify_all()
            return self._generation

    def idle(self) -> bool:
        with self._cond:
            return self._pending is None and not self._busy

    def wait_idle(self, timeout: float, alive: Callable[[], bool] = lambda: True) -> bool:
        """Wait until nothing is pending or being built (False on timeout or when ``alive()``
        turns false, e.g. the process is shutting down)."""
        end = time.monotonic() + timeout
        with self._cond:
            while self._pending is not None or self._busy:
                left = end - time.monotonic()
                if left <= 0 or self._stop or not alive():
                    return False
                self._cond.wait(min(left, 0.05))
            return True

    def forget(self) -> None:
        """Drop the cached model and engine (their memory); a waiting request is dropped too."""
        with self._cond:
            self._pending = None
            self._generation += 1
            self._cached = self._last = None

    def stop(self, timeout: float = 0.2) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout)

    # -- loader thread -------------------------------------------------------------------------
    def _superseded(self, req: LoadRequest) -> bool:
        return self._stop or self._generation != req.generation

    def _take(self) -> Optional[LoadRequest]:
        with self._cond:
            while self._pending is None and not self._stop:
                self._cond.wait()
            if self._stop:
                return None
            req, self._pending = self._pending, None
            self._busy = True
        time.sleep(self.SETTLE_S)            # let a burst of requests settle on its last one
        return None if self._superseded(req) else req

    def _run(self) -> None:
        while not self._stop:
            req = self._take()
            try:
                if req is not None:
                    self._serve(req)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _serve(self, req: LoadRequest) -> None:
        t0 = time.perf_counter()
        try:
            prepared = self._build(req)
        except Exception as e:        # ValueError (bad file) or anything a broken file raises
            if not self._superseded(req):
                msg = str(e) if isinstance(e, ValueError) else f"{type(e).__name__}: {e}"
                self._deliver(LoadResult(req, None, msg, time.perf_counter() - t0))
            return
        if prepared is not _DROPPED and not self._superseded(req):
            self._last = prepared
            self._deliver(LoadResult(req, prepared, "", time.perf_counter() - t0))

    def _build(self, req: LoadRequest) -> Any:
        if req.source.empty:
            return None
        if req.calibration is not None:
            return self._calibrate(req)
        last = self._last
        if (not req.reload and last is not None and last.source == req.source and last.noise_mm == req.noise_mm
                and (last.bank_settings is None or last.bank_settings == req.bank_settings)):
            return last                                  # nothing to do: the same engine
        cached = self._cached
        if req.reload or cached is None or cached[0] != req.source:
            base = load(req.source)
            self._cached, self._calibrated = (req.source, base), None
        elif self._calibrated is not None and self._calibrated[0] == req.source:
            base = self._calibrated[1]
        else:
            base = cached[1]
        if self._superseded(req):
            return _DROPPED
        return prepare(req.source, base, req.noise_mm, req.bank_settings)


    def _calibrate(self, req: LoadRequest) -> Any:
        """The loaded model calibrated to ``req.calibration`` (always from the file's model, so
        calibrations do not compound), widened for ``req.noise_mm``."""
        cached = self._cached
        if cached is None or cached[0] != req.source:
            raise ValueError("the model changed while calibrating; call ~/calibrate again")
        if isinstance(cached[1], ModelBank):
            raise ValueError("a bank cannot be calibrated (calibrate its models with dtm-calibrate)")
        base = (calibrate(cached[1], req.calibration) if req.clouds is None
                else self._auto_calibrated(cached[1], req))
        if base is _DROPPED or self._superseded(req):
            return _DROPPED
        self._calibrated = (req.source, base)
        return prepare(req.source, base, req.noise_mm, req.bank_settings, spare=False)   # swapped in: tracks stay


    def _auto_calibrated(self, model: Any, req: LoadRequest) -> Any:
        """``model`` self-calibrated on the window's clouds by
        :func:`~dtm_labeler.training.calibrate.auto_calibrate` in a spawned process at idle
        priority (seconds of Python that would hold the labelling thread's GIL here); dropped
        (the process ended) when a newer request supersedes it; ValueError when not applied (the
        running model stays). A model calibrated to its training takes' person is calibrated from
        its generic body (:func:`~dtm_labeler.training.calibrate.stream_calibration_target`), and
        where that measures the person's lengths their calibration is kept, checked for this
        session (:func:`~dtm_labeler.training.calibrate.recognised_person`)."""
        target = stream_calibration_target(model)
        if target is None:
            raise ValueError("auto calibration not applied: the model's body is calibrated to a person already "
                             "(or has no body terms)")
        person = model_to_bytes(model) if target is not model else None      # recognised by their lengths
        model = target
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=auto_calibration_process, name="dtm_labeler_calibration", daemon=True,
                           args=(child, model_to_bytes(model), list(req.clouds), float(req.calibration.rate), person))
        proc.start()
        idle_priority(proc.pid)          # from its imports on (seconds of CPU), not only once it runs
        child.close()
        try:
            while not parent.poll(0.05):
                if self._superseded(req):
                    return _DROPPED
                if not proc.is_alive():
                    raise ValueError("the calibration process ended without a result")
            data, summary = parent.recv()
        finally:
            if proc.is_alive():
                proc.terminate()
            proc.join(1.0)
            parent.close()
        if data is None:
            raise ValueError(f"auto calibration not applied: {summary.get('reason', '')}")
        return model_from_bytes(data, "calibrated model")     # its provenance holds the calibration


_DROPPED = object()
