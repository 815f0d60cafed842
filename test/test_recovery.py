"""Bounded frames: recovery searches in the background, results joining later frames through
the track ids, skipped frames observed by the tracker, and confidences that mean something."""
from __future__ import annotations

import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dtm_labeler.evaluation.metrics import MetricsAccumulator
from dtm_labeler.labeling.config import LabelerSettings
from dtm_labeler.labeling.recovery import (RECOVERY_NICE, RECOVERY_POLICY, DeferredRecovery, InterimReporter,
                                           ProcessRecovery, RecoveryRequest, RecoveryResult, build_spare,
                                           keep_spare_worker)
from dtm_labeler.labeling.stream import StreamLabeler
from dtm_labeler.labeling.tracker import Tracker, TrackerSettings
from dtm_labeler.motion.synthetic import synthesize
from dtm_labeler.search.dtm_dp import turned_round
from dtm_labeler.training.train import TrainConfig, train_model

CFG = TrainConfig(mixture="fixed", k_fixed=2, structure="given")


@pytest.fixture(scope="module")
def model():
    clips = [synthesize(duration=3.0, seed=s, heading=h, noise_mm=2) for s, h in [(0, 0.0), (1, 1.0), (2, 2.5)]]
    return train_model(clips, CFG)[0]


@pytest.fixture(scope="module")
def walker():
    return synthesize(duration=1.5, seed=7, heading=-2.0, noise_mm=2, start_xy=(1.0, 2.0))


def shuffled(clip, k, rng, ghosts=1):
    pts = clip.positions[k]
    g = pts.mean(0) + rng.uniform(-0.8, 0.8, size=(ghosts, 3))
    xyz = np.vstack([pts, g])
    truth = np.r_[np.arange(14), np.full(ghosts, -1)]
    perm = rng.permutation(len(xyz))
    return xyz[perm], truth[perm]


def test_deferred_recovery_publishes_doubtful_frames_then_joins(model, walker):
    """In the background mode a frame that needs a search is answered at once -- nothing
    labelled at the start, flagged doubtful -- and the search's labeling joins ``delay``
    frames later through the track ids, after which the stream is labelled right."""
    lab = StreamLabeler(model, LabelerSettings(recovery="background", audit_period_s=0))
    lab.recovery.close()
    lab.recovery = DeferredRecovery(lab, delay_frames=6)
    rng = np.random.default_rng(0)
    doubt, recovered, acc = [], [], []
    for k in range(40):
        xyz, truth = shuffled(walker, k, rng)
        r = lab.process(xyz, k / walker.rate)
        doubt.append(r.doubtful)
        recovered.append(r.recovered)
        acc.append(float(np.mean(r.labels[truth >= 0] == truth[truth >= 0])))
        if r.doubtful:
            assert (r.confidence <= 0.5 + 1e-9).all()          # doubtful frames are not published as certain
    first = recovered.index(True)
    assert first == 7                      # asked in frame 1 (the first with velocities), 6 frames later
    assert all(doubt[1:first]) and not any(r for r in recovered[first + 1:first + 3])
    assert all(a == 0 for a in acc[:first])                    # nothing known, nothing labelled
    assert np.mean(acc[first:]) >= 0.97


def test_an_audit_that_confirms_the_labeling_starts_no_region_pass(model, walker):
    """The worker's periodic audits are full searches. One whose labeling is the carried one
    confirms it: the region checks and cluster turns that follow a search that changed the
    labeling stay off (after every audit they ran in a third of a 41-marker stream's frames).
    The first search, which finds a labeling where none was carried, starts the pass."""
    lab = StreamLabeler(model, LabelerSettings(recovery="background", audit_period_s=0.2))
    lab.recovery.close()
    lab.recovery = DeferredRecovery(lab, delay_frames=2)
    rng = np.random.default_rng(1)
    joined, due, acc = [], [], []
    for k in range(walker.n_frames):
        xyz, truth = shuffled(walker, k, rng)
        r = lab.process(xyz, k / walker.rate)
        joined.append(r.recovered)
        due.append(lab._region_checks_due(lab.n_labels))
        acc.append(float(np.mean(r.labels[truth >= 0] == truth[truth >= 0])))
    first = joined.index(True)
    assert due[first]                                   # the first search's labeling: a pass over the regions
    later = [k for k in range(first + lab.n_labels + 1, len(joined)) if joined[k]]
    assert len(later) >= 4                              # audits went on joining ...
    assert not any(due[k] for k in later)               # ... and confirmed the labeling: no new pass
    assert np.mean(acc[first:]) >= 0.97


def test_first_search_waits_for_velocities(model, walker):
    """Background recovery: the stream's first frame (no velocities, nothing carried) asks for
    no search; the second asks for the full one, with velocities, and the stream is labelled
    right once it joins (DeferredRecovery: each search runs when asked and joins 3 frames
    later). A reset starts the same way. Inline the first frame keeps its full search."""
    lab = StreamLabeler(model, LabelerSettings(recovery="background", audit_period_s=0))
    lab.recovery.close()
    lab.recovery = DeferredRecovery(lab, delay_frames=3)
    asked, recover = [], lab.recover
    lab.recover = lambda request, **kw: asked.append((request.kind, request.frame)) or recover(request, **kw)
    rng = np.random.default_rng(3)
    acc = []
    for k in range(16):
        xyz, truth = shuffled(walker, k, rng)
        r = lab.process(xyz, k / walker.rate)
        acc.append(float(np.mean(r.labels[truth >= 0] == truth[truth >= 0])))
        if k == 0:
            assert not asked and r.doubtful and (r.labels < 0).all()
    assert asked[0] == ("full", 1)               # asked in the stream's second frame
    assert min(acc[6:]) >= 0.9 and np.mean(acc[6:]) >= 0.97
    n = len(asked)
    lab.reset()
    lab.process(shuffled(walker, 0, rng)[0], 0.0)
    assert len(asked) == n                       # after a reset too: nothing without velocities
    lab.process(shuffled(walker, 1, rng)[0], 1 / walker.rate)
    assert asked[n][0] == "full"
    inline = StreamLabeler(model, LabelerSettings(recovery="inline"))
    asked2, rec2 = [], inline.recover
    inline.recover = lambda request, **kw: asked2.append(request.kind) or rec2(request, **kw)
    inline.process(shuffled(walker, 0, rng)[0], 0.0)
    assert asked2 == ["recover"]                 # inline: the full search (nothing to seed it)


def test_process_recovery_worker_joins_and_stops(model, walker):
    """The real worker process: the first frames go on while it searches, its result joins, and
    close() ends it."""
    lab = StreamLabeler(model, LabelerSettings(recovery="background", audit_period_s=0.2))
    rec = lab.recovery
    assert isinstance(rec, ProcessRecovery)
    deadline = time.monotonic() + 60
    while not rec.ready and time.monotonic() < deadline:     # the worker imports numpy, builds its models
        rec.poll()
        time.sleep(0.05)
    assert rec.ready, rec.failed
    # background priority, set once: RECOVERY_NICE, not the parent's setting plus the child's own
    assert os.getpriority(os.PRIO_PROCESS, rec._proc.pid) == max(RECOVERY_NICE, os.getpriority(os.PRIO_PROCESS, 0))
    # ... under SCHED_BATCH (no wake-up preemption of the labeling thread), all of its threads
    tasks = list(Path(f"/proc/{rec._proc.pid}/task").iterdir())
    assert tasks and all(os.sched_getscheduler(int(t.name)) == RECOVERY_POLICY for t in tasks)
    rng = np.random.default_rng(1)
    got, acc = False, []
    for k in range(160):
        xyz, truth = shuffled(walker, k, rng)
        r = lab.process(xyz, k / walker.rate)
        got |= r.recovered
        if got:
            acc.append(float(np.mean(r.labels[truth >= 0] == truth[truth >= 0])))
        time.sleep(1 / 240)
    assert got and not rec.failed
    assert np.mean(acc) >= 0.95
    lab.close()
    assert rec._proc.wait(5) == 0


def _first_request(model, walker) -> RecoveryRequest:
    """The full search the stream asks for in its second frame (the first with velocities)."""
    lab = StreamLabeler(model, LabelerSettings(recovery="background", audit_period_s=0))
    lab.recovery.close()
    lab.recovery = DeferredRecovery(lab, delay_frames=100)
    rng = np.random.default_rng(3)
    for k in range(2):
        xyz, _ = shuffled(walker, k, rng, ghosts=2)
        lab.process(xyz, k / walker.rate)
    req = lab.recovery._result.request
    assert req.kind == "full"
    return req


def test_interim_results_report_the_best_so_far(model, walker):
    """Anytime recovery: the search sends its best labeling so far at the end of generations in
    which it improved -- flagged interim, fitness rising, never above the final result's -- and
    sends nothing when not asked to. (Without the fresh starts, which the final result keeps
    when they beat the GA, the reporter only reads.)"""
    req = _first_request(model, walker)
    assert req.kind == "full"
    no_fresh = LabelerSettings(recovery="inline", full=replace(LabelerSettings().full, fresh_starts=0))
    worker = StreamLabeler(model, no_fresh)
    sent = []
    rep = InterimReporter(req, sent.append, period_s=0.0)
    res = worker.recover(req, rng=np.random.default_rng(0), interim=rep)
    assert len(sent) >= 1 and rep.sent == len(sent)
    assert all(isinstance(r, RecoveryResult) and r.interim and r.request is req for r in sent)
    assert set(sent[0].candidates) == set(req.searched)
    fits = [max(f for _, f in r.candidates.values()) for r in sent]
    assert all(b > a for a, b in zip(fits, fits[1:]))         # only improvements are sent
    assert not res.interim and fits[-1] <= max(f for _, f in res.candidates.values()) + 1e-9
    # the same search without a reporter gives the same final labeling (the hook only reads)
    again = StreamLabeler(model, no_fresh).recover(req, rng=np.random.default_rng(0))
    for m in res.candidates:
        assert np.array_equal(res.candidates[m][0], again.candidates[m][0])


def test_the_first_interim_result_is_finished_at_once(model, walker):
    """The GA's first reported best is finished (polish, mirror, region sweeps) at once and
    sent too when that is better: the sweeps settle in tens of milliseconds what the GA climbs
    to over hundreds at 41 markers. Once per search; the first call of the search's finish is
    on exactly the first labeling sent."""
    req = _first_request(model, walker)
    worker = StreamLabeler(model, LabelerSettings(recovery="inline"))
    sent, calls = [], []
    finish = worker.full_search._finish
    def spy(problem, ind, f, deadline, **kw):
        out = finish(problem, ind, f, deadline, **kw)
        calls.append((len(sent), ind.copy(), f, out))
        return out
    worker.full_search._finish = spy
    rep = InterimReporter(req, sent.append, period_s=0.0)
    worker.recover(req, rng=np.random.default_rng(0), interim=rep)
    assert rep.refined == 1
    n_before, ind, f, (a, fa, _) = calls[0]
    assert n_before == 1                                      # right after the first report
    (m, (first, f_first)), = sent[0].candidates.items()
    assert np.array_equal(ind, first) and f == pytest.approx(f_first)
    if fa > f_first + 1e-9:                                   # an improvement is sent next
        assert np.array_equal(sent[1].candidates[m][0], a)


def test_fresh_starts_are_refined_and_kept_when_better(model, walker):
    """A worker's cold search refines, after the first generation's best, ``fresh_starts``
    bests of fresh model-guided populations (each finished: one more call of the search's
    finish), drawn from their own random stream: the GA's result is the same with or without
    them, and the final result is never below anything sent. Single frames (inline) run them after
    the first GA, and the result is never below them either; an inline stream does not."""
    req = _first_request(model, walker)
    runs = {}
    for fresh in (0, 3):
        worker = StreamLabeler(model, LabelerSettings(recovery="inline",
                                                      full=replace(LabelerSettings().full, fresh_starts=fresh)))
        calls, sent, gas = [], [], []
        finish, ga = worker.full_search._finish, worker._ga
        def spy(problem, ind, f, deadline, finish=finish, calls=calls, **kw):
            calls.append(f)
            return finish(problem, ind, f, deadline, **kw)
        def ga_spy(*a, ga=ga, gas=gas, **k):
            out = ga(*a, **k)
            gas.append({m: c.assignment.copy() for m, c in out.candidates.items()})
            return out
        worker.full_search._finish, worker._ga = spy, ga_spy
        res = worker.recover(req, rng=np.random.default_rng(0), interim=InterimReporter(req, sent.append, period_s=0.0))
        best_sent = max(max(f for _, f in r.candidates.values()) for r in sent)
        assert max(f for _, f in res.candidates.values()) >= best_sent - 1e-9
        runs[fresh] = (len(calls), gas)
    assert runs[3][0] == runs[0][0] + 3
    assert len(runs[3][1]) == len(runs[0][1])
    for a, b in zip(runs[0][1], runs[3][1]):                 # the GA's runs untouched
        assert all(np.array_equal(a[m], b[m]) for m in a)
    inline = StreamLabeler(model, LabelerSettings(recovery="inline", mode="single"))   # single frames: after the first GA
    starts = []
    fresh = inline._fresh_starts
    def fresh_spy(search, problem, rng):
        for a, fa, e in fresh(search, problem, rng):
            starts.append(fa)
            yield a, fa, e
    inline._fresh_starts = fresh_spy
    res = inline.recover(req)
    assert len(starts) >= 3 and max(f for _, f in res.candidates.values()) >= max(starts) - 1e-9
    starts.clear()
    stream = StreamLabeler(model, LabelerSettings(recovery="inline"))
    stream._fresh_starts = fresh_spy
    stream.recover(req)
    assert not starts


def test_the_finished_search_is_sent_before_the_turned_round_check(model, walker):
    """A cold full search sends its finished result (GA, restarts, region sweeps, the labels read
    through the turned-round body) as an interim one before it checks the body turned round by
    a whole-body DP -- ~1 s at 41 markers, and the stream should not wait for it -- and the
    final result is never worse."""
    req = _first_request(model, walker)
    worker = StreamLabeler(model, LabelerSettings(recovery="inline"))
    sent, at_check, quick = [], [], []
    turn = worker._turn_round
    def spy(problems, found, ga, check):
        if check is turned_round:
            at_check.append((len(sent), {m: c.fitness for m, c in found.candidates.items()}))
        else:
            quick.append(len(sent))
        turn(problems, found, ga, check)
    worker._turn_round = spy
    class FinishedOnly(InterimReporter):       # no per-generation reports: only what is sent for itself
        def hook(self, searched, inner=None, refine=None):
            return inner
    res = worker.recover(req, rng=np.random.default_rng(0), interim=FinishedOnly(req, sent.append))
    assert len(at_check) == 1 and quick[0] == 0               # the quick half before anything is sent
    n_sent, fits = at_check[0]
    assert n_sent >= 1 and all(r.interim for r in sent)
    last = sent[n_sent - 1].candidates
    assert max(f for _, f in last.values()) == pytest.approx(max(fits.values()))   # what the check starts from
    assert max(f for _, f in res.candidates.values()) >= max(fits.values()) - 1e-9


@pytest.mark.parametrize("worker", [False, True])
@pytest.mark.parametrize("falls_short", [False, True])
def test_cold_search_steps(model, walker, falls_short, worker):
    """Inline, a cold search restarts only while it falls short of the level and then reads
    its labels through the turned-round body, then the slow whole-body check from the same
    labels. In a worker (an interim reporter) the quick half runs on the first GA's result at
    once and is sent, every restart runs and is sent, and the quick half is read again from
    their best; the final result is never below what was sent."""
    req = _first_request(model, walker)
    worker_lab = StreamLabeler(model, LabelerSettings(recovery="inline", restarts=2))
    steps, sent = [], []
    ga, turn = worker_lab._ga, worker_lab._turn_round
    def ga_spy(*a, **k):
        steps.append(("ga", None))
        return ga(*a, **k)
    def turn_spy(problems, found, start, check):
        steps.append((check.__name__, {m: c.assignment.copy() for m, c in start.items()}))
        turn(problems, found, start, check)
    worker_lab._ga, worker_lab._turn_round = ga_spy, turn_spy
    if falls_short:                     # a level no labeling reaches
        level = req.state["level"].copy()
        level[:] = 1e6
        req = replace(req, state={**req.state, "level": level})
    rep = InterimReporter(req, sent.append) if worker else None
    res = worker_lab.recover(req, rng=np.random.default_rng(0), interim=rep)
    names = [name for name, _ in steps]
    if worker:
        assert names == ["ga", "turned_labels", "ga", "ga", "turned_labels", "turned_round"]
        best_sent = max(max(f for _, f in r.candidates.values()) for r in sent)
        assert max(f for _, f in res.candidates.values()) >= best_sent - 1e-9
    elif falls_short:
        assert names == ["ga", "ga", "ga", "turned_labels", "turned_round"]
    else:
        assert names == ["ga", "turned_labels", "turned_round"]
    quick_start, slow_start = steps[-2][1], steps[-1][1]          # both halves from the same labels
    for m in slow_start:
        assert np.array_equal(quick_start[m], slow_start[m])


def test_worker_sends_interim_results_before_the_final_one(model, walker):
    """The real worker process: polling while a full search runs returns interim results
    (classes of the package module, not of the worker's __main__) while the request stays
    busy, then the final result."""
    req = _first_request(model, walker)
    lab = StreamLabeler(model, LabelerSettings(recovery="background", audit_period_s=0))
    rec = lab.recovery
    deadline = time.monotonic() + 60
    while not rec.ready and time.monotonic() < deadline:
        rec.poll()
        time.sleep(0.05)
    assert rec.ready, rec.failed
    rec.submit(req)
    got = []
    while time.monotonic() < deadline:
        r = rec.poll()
        if r is not None:
            got.append(r)
            if not r.interim:
                break
            assert rec.busy                                      # the final result is still to come
        time.sleep(0.0005)
    assert got and not got[-1].interim and not rec.busy, rec.failed
    assert any(r.interim for r in got[:-1])
    assert all(type(r) is RecoveryResult for r in got)
    lab.close()


def _final_result(rec, timeout: float = 60.0):
    """The first final (not interim) result ``rec`` returns, polled for up to ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        assert time.monotonic() < deadline, rec.failed
        r = rec.poll()
        if r is not None and not r.interim:
            return r
        time.sleep(0.005)


def test_a_request_made_before_the_worker_connects_waits_for_it(model, walker):
    """Right after start-up the worker process is still importing: a request then is not
    searched in the frame (that held a live stream for 70-110 ms) but waits and is sent the
    moment the worker connects; its results come back from the worker."""
    req = _first_request(model, walker)
    keep_spare_worker(False)            # an in-process node test may have left a spare, already up
    lab = StreamLabeler(model, LabelerSettings(recovery="background", audit_period_s=0))
    rec = lab.recovery
    assert rec._conn is None                                  # still importing
    rec.submit(req)
    assert rec.busy and rec._inline is None and not rec.ready
    final = _final_result(rec)
    assert (final.request.frame, final.request.seed) == (req.frame, req.seed)       # came back from the worker
    assert rec.ready and not rec.busy and not rec.failed
    lab.close()


def test_observed_frames_keep_the_tracks(model, walker):
    """Frames the consumer skips are observed by the tracker: after a skip of 12 frames the
    carried labeling goes on without a search; without observing, the gates widen with the
    skipped time (tracks also survive, as a late frame would)."""
    rng = np.random.default_rng(2)
    lab = StreamLabeler(model, LabelerSettings(audit_period_s=0))
    for k in range(10):
        xyz, _ = shuffled(walker, k, rng)
        lab.process(xyz, k / walker.rate)
    for k in range(10, 22):
        xyz, truth = shuffled(walker, k, rng)
        carried = lab.observe(xyz, k / walker.rate)     # what the node publishes for a skipped frame
        seen = truth >= 0
        assert np.mean(carried.labels[seen] == truth[seen]) >= 0.9
        assert (carried.labels[~seen] == -1).all() and (carried.track_ids >= 0).all()
    xyz, truth = shuffled(walker, 22, rng)
    r = lab.process(xyz, 22 / walker.rate)
    assert not r.full_search and r.generations == 0
    assert np.mean(r.labels[truth >= 0] == truth[truth >= 0]) == 1.0


def test_tracker_gate_grows_with_skipped_time_only():
    """A late update (frames skipped) widens every gate by the acceleration and new-track
    speed bounds; an occluded marker's coasting track keeps its ordinary gate."""
    tr = Tracker(TrackerSettings(gate_m=0.05, known_gate_m=0.05, gate_speed_factor=0.0, accel_mps2=50.0,
                                 new_track_speed_mps=2.0))
    p = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]])
    for k in range(5):
        tr.update(p + [0.01 * k, 0, 0], k / 100)
    normal = tr.gate(5 / 100)
    np.testing.assert_allclose(normal, 0.05, atol=1e-9)
    late = tr.gate(15 / 100)                                   # 10 frames late
    assert (late > 0.05 + 0.5 * 50.0 * 0.09 ** 2 - 1e-6).all()
    u = tr.update(p + [0.15, 0, 0], 15 / 100)                  # moved 10 cm: still the same tracks
    assert not u.new.any()


def test_confidence_reliability_is_measured():
    acc = MetricsAccumulator(["a", "b"], 100.0)
    acc.add(np.array([0, 1]), np.array([0, 1]), confidence=np.array([0.95, 0.95]))
    acc.add(np.array([0, 1]), np.array([1, 0]), confidence=np.array([0.15, 0.15]))
    m = acc.metrics()
    assert m.calibration_error == pytest.approx(0.5 * 0.05 + 0.5 * 0.15)
    assert [r[2] for r in m.reliability] == [2, 2]


def test_worker_rebuilds_a_bank_labeler_from_its_spec(model, walker):
    """What a worker process gets (model file bytes, names, settings) rebuilds the same kind of
    labeler -- a bank with its actions -- searching inline, and it answers a request."""
    from dtm_labeler.labeling.bank_labeler import BankLabeler, BankSettings
    from dtm_labeler.labeling.recovery import build_worker_labeler, worker_spec
    from dtm_labeler.model.bank import ModelBank
    bank = ModelBank({"walk": model, "walk2": model})
    lab = BankLabeler(bank, LabelerSettings(recovery="inline", audit_period_s=0), BankSettings(min_share=2))
    w = build_worker_labeler(worker_spec(lab))
    assert isinstance(w, BankLabeler) and w.actions == ["walk", "walk2"] and w.recovery.inline
    rng = np.random.default_rng(3)
    for k in range(3):
        xyz, truth = shuffled(walker, k, rng)
        lab.process(xyz, k / walker.rate)
    problems, inp, _ = lab.last_frame
    req = lab._request(problems, inp, [0, 1], None, "full")
    res = w.recover(req, rng=np.random.default_rng(req.seed))
    assert set(res.candidates) == {0, 1} and res.full and "shares" in res.state
    best = max(res.candidates.values(), key=lambda c: c[1])[0]
    pts = inp.keep[best[best < len(inp.keep)]]
    assert np.mean(truth[pts] == np.flatnonzero(best < len(inp.keep))) >= 0.9


def test_a_spare_worker_built_ahead_serves_at_once_and_the_next_starts_later(model, walker, monkeypatch):
    """A node's loader has the spare worker build the labeler while it prepares its own
    (``build_spare``): the labeler built after over the same model finds its worker ready, with
    no set-up of its own, and its first search comes back from it. The next spare is started
    ``RESTOCK_DELAY_S`` after one is taken, not at once (its imports compete with the start of
    the stream); a labeler over another noise does not take the prepared build."""
    import dtm_labeler.labeling.recovery as recovery
    monkeypatch.setattr(recovery, "RESTOCK_DELAY_S", 0.5)
    keep_spare_worker(True)
    try:
        wait = build_spare([model], [""], "StreamLabeler", LabelerSettings(noise_mm=1.0))
        assert wait is not None and wait(60)
        spare = recovery._spare
        assert spare.preset_ready
        lab = StreamLabeler(model, LabelerSettings(recovery="background", audit_period_s=0, noise_mm=1.0))
        rec = lab.recovery
        assert rec._worker is spare and rec.ready and rec._spec_sent      # no set-up of its own
        assert recovery._spare is None                                   # the next one comes later ...
        req = _first_request(model, walker)
        rec.submit(req)
        final = _final_result(rec)
        assert final.request.frame == req.frame and not rec.failed
        lab.close()
        deadline = time.monotonic() + 10
        while recovery._spare is None and time.monotonic() < deadline:    # ... after RESTOCK_DELAY_S
            time.sleep(0.05)
        assert recovery._spare is not None and recovery._spare is not spare
        # another noise: the prepared build is not this labeler's; it sets its worker up itself
        wait = build_spare([model], [""], "StreamLabeler", LabelerSettings(noise_mm=1.0))
        assert wait(60)
        other = StreamLabeler(model, LabelerSettings(recovery="background", audit_period_s=0, noise_mm=3.0))
        assert not other.recovery.ready
        deadline = time.monotonic() + 60
        while not other.recovery.ready and time.monotonic() < deadline:
            other.recovery.poll()
            time.sleep(0.02)
        assert other.recovery.ready and not other.recovery.failed
        other.close()
    finally:
        keep_spare_worker(False)
