"""Recovery searches, run where they do not hold the stream up.

When the fast path cannot vouch for a frame (no carried labeling, or one that fits worse
than the model expects), the labeler needs a search: a warm-started GA and, if that still
falls short, full GAs with restarts. Such a search costs 50 ms to 1 s -- six to a hundred
frames of a 120 Hz stream. Where it runs is the :class:`Recovery` executor's business:

* :class:`InlineRecovery` runs it at once, in the frame that asked (offline labeling:
  deterministic, every frame gets the searched labeling; the paper's setting);
* :class:`ProcessRecovery` hands it to a worker process that holds its own copy of the
  labeler (same class, models and settings) and returns at once. The stream goes on with the
  best labeling known (carried by the tracks, flagged as doubtful); the result joins a later
  frame through the track ids of the frame it was asked for
  (:meth:`~.tracked.TrackedLabeler._join`), and is taken only if the current frame's problem
  scores it higher. A process, not a thread: a search is Python-heavy and would hold the GIL
  the frame loop needs; on two cores the worker runs beside it.

A request carries everything the search needs (the frame's point states and track ids,
heading hint, seeds, the fitness levels the restart rule reads, the bank's shares), so the
worker keeps nothing between requests but its models and settings. The worker is started
with the labeler and connects over a local socket (authenticated with a random key passed on
its stdin); until it has connected, and if it ever dies, requests run inline (a request sent
while it builds its labeler waits there, not in the stream).
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from multiprocessing.connection import Client, Connection, Listener

import numpy as np

#: recovery kinds: a warm-started search (full GA when it falls short), a full search, audits: a
#: region sweep of the current labeling or a full search from scratch while the labeling looks fine
KINDS = ("recover", "full", "sweep", "audit")
#: kinds whose best-so-far is worth publishing: searches the stream asked for because it had no
#: labeling it could vouch for (an audit checks a labeling that already fits)
INTERIM_KINDS = ("recover", "full")


@dataclass
class RecoveryRequest:
    epoch: int                      # stream epoch (resets start a new one; old results are dropped)
    frame: int                      # frame number it was asked in
    states: np.ndarray              # (n, 6) the frame's point states
    track_ids: np.ndarray           # (n,) their track ids
    heading: float | None           # heading hint of the frame
    seeds: np.ndarray | None        # (S, M) warm-start labelings (first = heading anchor)
    searched: list[int]             # models searched
    state: dict                     # labeler state the search reads (fitness levels, shares)
    seed: int                       # random seed of the search
    kind: str = "recover"
    rest_s: np.ndarray | None = None   # (n,) how long each point has stayed put


@dataclass
class RecoveryResult:
    request: RecoveryRequest
    candidates: dict                # model -> (assignment, fitness) over the request's points
    full: bool
    generations: int
    evaluations: int
    state: dict = field(default_factory=dict)
    seconds: float = 0.0
    interim: bool = False           # the search's best so far; the final result follows


#: the shortest time between two interim results of one search (:class:`InterimReporter`)
INTERIM_PERIOD_S = 0.004


#: the recovery kinds whose first interim result is also finished (:meth:`InterimReporter.hook`)
REFINED_KINDS = ("full",)


class InterimReporter:
    """Anytime recovery: while a background search runs, its best labeling so far goes to the
    stream as an *interim* result -- at the end of a GA generation in which the best improved,
    at most once per :data:`INTERIM_PERIOD_S`. On the demo walker a full search takes 40-200 ms
    (the GA, its region sweeps, restarts when the first run falls short), but the GA's best is
    the right labeling after its first generation or two in most frames: waiting for the end
    left the first 20 frames of a stream without labels. An interim result joins a frame the
    way the final one does (:meth:`~.tracked.TrackedLabeler._join`: taken only where it fits
    the frame better than the labeling carried), so a poor one costs nothing."""

    def __init__(self, request: RecoveryRequest, send, period_s: float = INTERIM_PERIOD_S):
        self.request, self.send, self.period_s = request, send, period_s
        self._last_t = -np.inf
        self._sent_f = -np.inf
        self.sent = 0
        self.refined = 0
        self.best: dict = {}            # model -> (assignment, fitness): the best sent under each model

    def hook(self, searched: list[int], inner=None, refine=None):
        """A per-generation hook for :func:`~..search.evolve.evolve` over the islands of
        ``searched`` (after ``inner``, e.g. the bank's migration).

        ``refine(model, assignment, fitness)`` yields ``(assignment, fitness, evaluations)``,
        one refinement after another (:meth:`~.tracked.TrackedLabeler._interim_refine`: the
        search's finish -- polish, its mirror image, region sweeps -- then the labels read
        through the turned-round body), each reported as it comes. It runs once per search from
        scratch (:data:`REFINED_KINDS`; a warm search starts from a labeling that was right a
        frame ago), on the best island's best at the first report. A cold GA at 41 markers is
        slow to climb, but its first generation is a good start for the exact region sweeps: on
        the 41-marker demo stream (HDM05, 3 flickering + 2 ghosts) the GA's best was 29-55 %
        right over its first 80 generations (95-230 ms into the search), the sweeps from its
        first generation's best gave the right labeling in 40-60 ms, and the whole search's
        sweeps joined at 320-360 ms. The GA itself is untouched (its population and random
        stream): the search's final result is the same, later by the refinement's time."""
        def report(islands, gen: int) -> int:
            evals = inner(islands, gen) if inner is not None else 0
            now = time.perf_counter()
            if now - self._last_t < self.period_s:
                return evals
            bests = {searched[i]: isl.best() for i, isl in enumerate(islands) if len(isl.pop)}
            self.report(bests, gen, now)
            if refine is not None and not self.refined and bests and self.request.kind in REFINED_KINDS:
                m = max(bests, key=lambda q: bests[q][1])
                ind, f = bests[m]
                self.refined += 1
                for a, fa, e in refine(m, np.array(ind, copy=True), float(f)):
                    self.report({**bests, m: (a, fa)}, gen)
                    evals += e
            return evals
        return report

    def report(self, bests: dict, generations: int, now: float | None = None) -> None:
        """Send ``bests`` (model -> (assignment, fitness)) when it is better than what was sent."""
        top = max((f for _, f in bests.values()), default=-np.inf)
        for m, (a, f) in bests.items():
            if m not in self.best or f > self.best[m][1]:
                self.best[m] = (np.array(a, copy=True), float(f))
        if top > self._sent_f:
            self.send(RecoveryResult(self.request, bests, False, generations, 0, interim=True))
            self._last_t, self._sent_f = time.perf_counter() if now is None else now, top
            self.sent += 1


class Recovery:
    """Executor interface: ``submit`` a request, ``poll`` for the result (None while running)."""

    inline = False
    failed = ""
    last_error = ""

    @property
    def busy(self) -> bool:
        return False

    @property
    def background_ready(self) -> bool:
        """A background worker is up to take requests (audits wait for it)."""
        return False

    def submit(self, request: RecoveryRequest) -> None:
        raise NotImplementedError

    def poll(self) -> RecoveryResult | None:
        raise NotImplementedError

    def configure(self, labeler) -> None:
        """The labeler's models or settings changed: searches from now on use the new ones."""

    def close(self) -> None:
        """Free the executor's resources (idempotent)."""


class InlineRecovery(Recovery):
    """Runs every request at once on the labeler itself (same random stream)."""

    inline = True

    def __init__(self, labeler):
        self.labeler = labeler
        self._result: RecoveryResult | None = None

    def submit(self, request: RecoveryRequest) -> None:
        self._result = self.labeler.recover(request)

    def poll(self) -> RecoveryResult | None:
        out, self._result = self._result, None
        return out


class DeferredRecovery(Recovery):
    """Background recovery made deterministic, for evaluation: the search runs at once in this
    process (on its own random stream, as a worker would), its result is handed out
    ``delay_frames`` polls later -- the frames a worker would take. With ``interim_frames``
    the search's first interim result (what a worker's :class:`InterimReporter` sends first)
    is handed out that many polls after the request, before the final one. With
    ``sweep_frames`` a region sweep's result is handed out that many polls later instead (a
    worker takes 10-20 ms for one at 41 markers, where a GA takes hundreds)."""

    def __init__(self, labeler, delay_frames: int = 12, interim_frames: int | None = None,
                 sweep_frames: int | None = None):
        self.labeler, self.delay = labeler, int(delay_frames)
        self.interim_frames = interim_frames
        self.sweep_frames = sweep_frames
        self._result: RecoveryResult | None = None
        self._interim: RecoveryResult | None = None
        self._wait = 0
        self._delay_now = self.delay               # the delay of the search under way

    @property
    def busy(self) -> bool:
        return self._result is not None

    @property
    def background_ready(self) -> bool:
        return True

    def submit(self, request: RecoveryRequest) -> None:
        state = self.labeler._search_state()
        rng = self.labeler.rng
        sent: list[RecoveryResult] = []
        reporter = InterimReporter(request, sent.append) if self.interim_frames is not None and \
            request.kind in INTERIM_KINDS else None
        self._result = self.labeler.recover(request, rng=np.random.default_rng(request.seed), interim=reporter)
        self._interim = sent[0] if sent else None
        self.labeler._set_search_state(state)
        self.labeler.rng = rng
        sweep = request.kind == "sweep" and self.sweep_frames is not None
        self._delay_now = int(self.sweep_frames) if sweep else self.delay
        self._wait = self._delay_now

    def poll(self) -> RecoveryResult | None:
        if self._result is None:
            return None
        self._wait -= 1
        if self._interim is not None and self._delay_now - self._wait >= self.interim_frames:
            out, self._interim = self._interim, None
            return out
        if self._wait > 0:
            return None
        out, self._result = self._result, None
        return out


def worker_spec(labeler) -> dict:
    """What a worker needs to rebuild ``labeler``: its class, models (model file bytes, never
    pickled objects), action names and settings."""
    from ..model.io import model_to_bytes
    return {"cls": type(labeler).__name__, "names": list(labeler.engine.names),
            "models": [model_to_bytes(m) for m in labeler.engine.base],
            "settings": labeler.settings, "bank_settings": getattr(labeler, "bank_settings", None)}


def build_worker_labeler(spec: dict):
    """The labeler a worker searches with (inline recovery, no worker of its own)."""
    from ..model.bank import ModelBank
    from ..model.io import model_from_bytes
    from .bank_labeler import BankLabeler
    from .stream import StreamLabeler
    from .tracked import Engine
    settings = replace(spec["settings"], recovery="inline")     # a worker searches itself
    models = [model_from_bytes(b, "recovery worker") for b in spec["models"]]
    engine = Engine.prepare(models, settings.noise_mm, spec["names"])
    if spec["cls"] == "BankLabeler":
        bank = ModelBank(dict(zip(spec["names"], models)))
        return BankLabeler(bank, settings, spec["bank_settings"], engine=engine)
    return StreamLabeler(engine, settings)


class WorkerProcess:
    """A started worker process (``python -m dtm_labeler.labeling.recovery``) and, once it has
    connected, the connection to it. Starting one costs 1-2 s of imports; :func:`keep_spare_worker`
    keeps one started ahead, so that a labeler built later (a node's first model, a reload)
    finds its worker already up."""

    def __init__(self):
        self.failed = ""
        self.conn: Connection | None = None
        self._lock = threading.Lock()
        key = os.urandom(16)
        self._listener = Listener(family="AF_UNIX", authkey=key)
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
        self.proc = subprocess.Popen([sys.executable, "-m", "dtm_labeler.labeling.recovery",
                                      self._listener.address], stdin=subprocess.PIPE, env=env,
                                     start_new_session=True)
        background_priority(self.proc.pid)      # from its imports on (1-2 s of CPU a starting stream needs)
        self.proc.stdin.write(key.hex().encode() + b"\n")
        self.proc.stdin.close()
        self.on_connect = None
        self.preset: dict | None = None       # the spec it was given ahead of a labeler (build_spare)
        self.preset_ready = False             # ... and has built
        threading.Thread(target=self._accept, name="dtm_labeler_recovery_accept", daemon=True).start()

    def _accept(self) -> None:
        try:
            conn = self._listener.accept()
        except (OSError, EOFError) as e:
            self.failed = self.failed or f"recovery worker did not connect: {e}"
            return
        with self._lock:
            self.conn = conn
            hook = self.on_connect
        if hook is not None:
            hook()

    def alive(self) -> bool:
        return not self.failed and self.proc.poll() is None

    def close(self) -> None:
        with self._lock:
            conn, self.conn = self.conn, None
            self.failed = self.failed or "closed"
        if conn is not None:
            try:
                conn.send(("stop", None))
            except (OSError, EOFError):
                pass
            conn.close()
        if self.proc.poll() is None:
            try:
                # a worker that never connected holds nothing: no need to wait for it to start
                self.proc.wait(1.0 if conn is not None else 0.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        try:
            self._listener.close()
        except OSError:
            pass


_spare: WorkerProcess | None = None
_keep_spare = False
_spare_lock = threading.Lock()


def keep_spare_worker(keep: bool = True) -> None:
    """Keep one worker process started ahead of need (a long-running node asks for this)."""
    global _keep_spare, _spare
    with _spare_lock:
        _keep_spare = keep
        if keep and (_spare is None or not _spare.alive()):
            _spare = WorkerProcess()
        elif not keep and _spare is not None:
            _spare.close()
            _spare = None


def build_spare(models, names, cls: str, settings, bank_settings=None):
    """Have the spare worker (:func:`keep_spare_worker`) build the labeler for ``models`` now,
    while the caller prepares its own engine: a node's loader calls this before
    :meth:`~.tracked.Engine.prepare`, so that the worker's build (its own engine, 1-2 s at 41
    markers) runs beside the node's instead of after it. Without it the first searches of a
    stream that starts right after a load waited for that build: measured in the node (HDM05
    41 markers, flicker + ghosts, 120 Hz), the first 0.4 s of labels were wrong, 2-6 % right,
    against 0.2 s when the worker was ready. A labeler built later over the same models, labels
    and noise takes this worker without a new build (:class:`ProcessRecovery`; its settings are
    sent after). Returns ``wait(timeout) -> bool`` (True once the worker has built it), or None
    when no spare is kept."""
    from ..model.io import model_to_bytes
    with _spare_lock:
        w = _spare if _keep_spare and _spare is not None and _spare.alive() else None
    if w is None:
        return None
    spec = {"cls": cls, "names": list(names), "models": [model_to_bytes(m) for m in models],
            "settings": replace(settings, recovery="inline"), "bank_settings": bank_settings}
    w.preset, w.preset_ready = spec, False

    def wait(timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while w.conn is None and w.alive() and time.monotonic() < deadline:
            time.sleep(0.01)
        with w._lock:
            if w.conn is None or w.on_connect is not None:
                w.preset = None                     # not connected in time, or taken: a normal set-up
                return False
            try:
                w.conn.send(("setup", spec))
                while time.monotonic() < deadline and w.conn.poll(max(deadline - time.monotonic(), 0.0)):
                    kind, payload = w.conn.recv()
                    if kind == "ready":
                        w.preset_ready = True
                        return True
                    if kind == "error":
                        w.preset = None
                        return False
            except (OSError, EOFError):
                w.preset = None
        return False
    return wait


def _same_build(a: dict, b: dict) -> bool:
    """Two worker specs build the same labeler up to its settings (class, names, model files,
    noise)."""
    return (a["cls"] == b["cls"] and a["names"] == b["names"] and a["models"] == b["models"]
            and a["settings"].noise_mm == b["settings"].noise_mm)


def _take_worker() -> WorkerProcess:
    """The spare worker (or a new one); the next spare is started :data:`RESTOCK_DELAY_S` later,
    not now: its imports (1-2 s of CPU) would compete with the first searches of the labeler that
    took this one -- a stream's start-up (measured at 41 markers: its first 0.3 s 56-77 % right
    with the spare started at once, against 84-97 % without)."""
    global _spare
    with _spare_lock:
        w, _spare = _spare, None
        if _keep_spare:
            timer = threading.Timer(RESTOCK_DELAY_S, _restock)
            timer.daemon = True
            timer.start()
    return w if w is not None and w.alive() else WorkerProcess()


#: seconds after a spare worker is taken until the next is started (:func:`_take_worker`)
RESTOCK_DELAY_S = 5.0


def _restock() -> None:
    global _spare
    with _spare_lock:
        if _keep_spare and (_spare is None or not _spare.alive()):
            _spare = WorkerProcess()


class ProcessRecovery(Recovery):
    """Recovery in a worker process. A request made before the worker has connected waits
    (the newest one) and is sent the moment it connects; one sent while it builds its labeler
    waits there (it serves in order). The stream is never held by a search meanwhile: a node
    streamed to right after start-up had searched its first frame inline, 70-110 ms, and
    dropped the next 5-7 frames as stale. Only if the worker fails do requests run inline, in
    the frame that asks."""

    def __init__(self, labeler):
        self.failed = ""
        self._labeler = labeler                 # runs requests inline until the worker is up
        self._sent = 0                          # requests sent
        self._answered = 0                      # of them answered (results are read in order)
        self.ready = False                      # the worker has built its labeler
        self._inline: RecoveryResult | None = None
        self._waiting: RecoveryRequest | None = None     # asked before the worker connected
        self._spec = worker_spec(labeler)
        self._base = labeler.engine.base
        self._spec_sent = False
        self._worker = _take_worker()
        pre = self._worker.preset
        if pre is not None and _same_build(pre, self._spec):       # built ahead (:func:`build_spare`)
            self._spec_sent, self.ready = True, self._worker.preset_ready
            self._send_settings(self._conn)
        self._worker.on_connect = self._ready
        if self._worker.conn is not None:
            self._ready()                       # the worker builds its labeler now, before any request

    @property
    def _conn(self) -> Connection | None:
        return self._worker.conn

    @property
    def _proc(self):
        return self._worker.proc

    def _ready(self) -> Connection | None:
        """The connection once the worker is up (with its current spec sent), else None."""
        conn = self._worker.conn
        if conn is None or self.failed or self._worker.failed:
            return None
        with self._worker._lock:
            try:
                if not self._spec_sent:
                    conn.send(("setup", self._spec))
                    self._spec_sent = True
                if self._waiting is not None:
                    request, self._waiting = self._waiting, None
                    conn.send(("recover", request))
            except (OSError, EOFError) as e:
                self._fail(e)
                return None
        return conn

    def configure(self, labeler) -> None:
        """Models changed: the worker rebuilds from the new spec; settings only: it takes them."""
        self._labeler = labeler
        base = labeler.engine.base
        if len(base) != len(self._base) or any(a is not b for a, b in zip(base, self._base)):
            self._base = base
            self._spec, self._spec_sent = worker_spec(labeler), False
        else:
            self._spec = dict(self._spec, settings=labeler.settings,
                              bank_settings=getattr(labeler, "bank_settings", None))
            self._send_settings(self._ready() if self._spec_sent else None)

    def _send_settings(self, conn: Connection | None) -> None:
        """The spec's settings to a worker that has (or is building) the labeler."""
        if conn is None:
            return
        try:
            conn.send(("settings", (self._spec["settings"], self._spec["bank_settings"])))
        except (OSError, EOFError) as e:
            self._fail(e)

    @property
    def busy(self) -> bool:
        return self._answered < self._sent

    @property
    def background_ready(self) -> bool:
        return self.ready and not self.failed

    def submit(self, request: RecoveryRequest) -> None:
        # connected: the request queues behind the worker's set-up (it serves in order), so the
        # stream is never held by a search while the worker builds its labeler
        conn = self._ready()
        if conn is None and not self.failed and self._worker.alive():     # still starting: wait for it
            with self._worker._lock:
                self._waiting = request
                self._sent += 1
            self._ready()                       # it may have connected meanwhile
            return
        if conn is None:                        # the worker failed: search here and now
            self._inline = self._labeler.recover(request)
            return
        try:
            conn.send(("recover", request))
            self._sent += 1
        except (OSError, EOFError) as e:
            self._fail(e)
            self._inline = self._labeler.recover(request)

    def poll(self) -> RecoveryResult | None:
        if self._inline is not None:
            out, self._inline = self._inline, None
            return out
        if self._waiting is not None and not self._worker.alive():      # it never connected
            request, self._waiting = self._waiting, None
            self._answered += 1
            return self._labeler.recover(request)
        if self._conn is None or (self.ready and not self.busy):
            return None
        self._ready()
        interim = None
        try:
            while self._conn.poll():
                kind, payload = self._conn.recv()
                if kind == "ready":
                    self.ready = True
                elif kind == "error":             # that request failed; the worker goes on
                    self._answered += 1
                    self.last_error = str(payload)
                elif kind == "interim":           # the latest best-so-far of the running search
                    interim = payload
                elif kind == "result":
                    self._answered += 1
                    return payload
        except Exception as e:      # OSError/EOFError: gone; anything else: a reply that does not unpickle
            self._fail(e)
        return interim

    def _fail(self, why) -> None:
        self.failed = f"recovery worker failed: {why}"
        self._answered = self._sent

    def close(self) -> None:
        self.failed = self.failed or "closed"
        self._worker.close()


def serve(address: str, key: bytes) -> int:
    """The worker: rebuild the labeler from ``setup``, run ``recover`` requests, stop on ``stop``
    or when the labeler's process goes away (its end of the connection closes)."""
    try:
        conn = Client(address, family="AF_UNIX", authkey=key)
    except OSError:                       # the labeler closed before this worker was up
        return 0
    labeler = None
    try:
        while True:
            kind, payload = conn.recv()
            if kind == "stop":
                return 0
            try:
                reply = _handle(kind, payload, labeler, lambda r: conn.send(("interim", r)))
            except (OSError, EOFError):
                raise
            except Exception as e:        # report, keep serving: one bad request must not end the worker
                conn.send(("error", f"{type(e).__name__}: {e}"))
                continue
            if kind == "setup":
                labeler = reply
                conn.send(("ready", None))
            elif reply is not None:
                conn.send(("result", reply))
    except (OSError, EOFError):
        return 0


def _handle(kind: str, payload, labeler, send_interim=None):
    if kind == "setup":
        return build_worker_labeler(payload)
    if kind == "settings":
        settings, bank_settings = payload
        settings = replace(settings, recovery="inline")
        if bank_settings is not None:
            labeler.update_settings(settings, bank_settings)
        else:
            labeler.update_settings(settings)
        return None
    if kind == "recover":
        t0 = time.perf_counter()
        interim = InterimReporter(payload, send_interim) if send_interim is not None and \
            payload.kind in INTERIM_KINDS else None
        res = labeler.recover(payload, rng=np.random.default_rng(payload.seed), interim=interim)
        res.seconds = time.perf_counter() - t0
        return res
    raise ValueError(f"unknown request {kind!r}")


#: scheduling niceness of the worker process: its searches use the cores the stream leaves
#: idle and yield them to the labeling thread (and the driver) whenever those need them.
#: ``SCHED_IDLE`` instead (what the auto calibration's process gets) measured no better:
#: ``dtm-demo --occlude 2 --gap-frames 1 --clutter 2 --duration 8``, 5 alternating runs each,
#: end-to-end p99 8.9-18.0 (median 10.3) vs 9.8-12.3 (11.3) ms, node p99 median 7.7 vs 8.2 ms.
#: (Until 2026-11-27 the worker ran at 19: the parent's ``setpriority`` and the child's ``os.nice``
#: added up. At 10, the 41-marker demo, 3 alternating runs each, 19 -> 10: accuracy 97.06 /
#: 96.86 / 97.80 -> 97.58 / 97.25 / 97.09 %, frames before the first right one 74 / 62 / 39 ->
#: 41 / 53 / 45, e2e p99 22.1 / 21.4 / 20.9 -> 19.7 / 19.4 / 13.1 ms; 14 points unchanged.)
RECOVERY_NICE = 10

#: scheduling policy of the worker process (Linux; None where the platform has none):
#: ``SCHED_BATCH``, the normal policy without wake-up preemption. Under the normal policy a
#: request sent to the idle worker woke it onto the sending core ahead of the labeling thread
#: (it had slept, so it was owed time), and the frame then waited for the worker's search:
#: library, ``body14`` gaps + ghosts, background, 120 Hz, two runs each, ``submit`` 3.6-5.1 ms of
#: wall time with ~0.1 ms of CPU every periodic check, frame wall p99 5.1 / 5.2 -> 3.1 / 2.4 ms,
#: wall minus CPU p99 3.4 / 3.3 -> 0.04 / 0.01 ms. ``SCHED_IDLE`` for the worker's threads once it is
#: up, the same stream, 8 runs each, alternating blocks of 4 (2026-12-06): steady p99 1.73-1.82 ms
#: (frames that waited > 1 ms for the CPU: 0-1 a run) against 1.72-2.92 ms (0-4), the same labels.
RECOVERY_POLICY = getattr(os, "SCHED_BATCH", None)


def background_priority(pid: int) -> None:
    """Process ``pid`` (0: this one) at niceness :data:`RECOVERY_NICE`, set absolutely (not
    ``os.nice``'s increment): the parent sets it on the worker it starts, the worker on itself
    in case it ran first, and the two must not add up. Then ``SCHED_BATCH``
    (:data:`RECOVERY_POLICY`): the worker does not preempt the labeling thread when a request
    wakes it. Both are inherited by the threads the worker starts later. Left unchanged where
    not permitted."""
    try:
        os.setpriority(os.PRIO_PROCESS, pid, RECOVERY_NICE)
    except OSError:                     # pragma: no cover - not permitted here: run at the same priority
        pass
    if RECOVERY_POLICY is not None:
        try:
            os.sched_setscheduler(pid, RECOVERY_POLICY, os.sched_param(0))
        except OSError:                 # pragma: no cover - not permitted: the default policy
            pass


def main() -> int:
    key = bytes.fromhex(sys.stdin.readline().strip())
    background_priority(0)
    return serve(sys.argv[1], key)


if __name__ == "__main__":
    # run as the package's module, not as __main__: what the worker sends must unpickle as
    # dtm_labeler.labeling.recovery classes in the labeler's process
    from dtm_labeler.labeling.recovery import main as _main
    sys.exit(_main())
