"""Every LabelerSettings field changes what both labelers do (one model and a bank).

The per-frame pipeline is written once (:class:`~dtm_labeler.labeling.tracked.TrackedLabeler`),
so a setting cannot be honoured by one labeler and ignored by the other (the bank once ignored
``noise_mm``, budgets, restarts, seeding and region sweeps). For every field a changed value
must change the trace of a short, hard stream (ghosts, gaps, noise, a noise burst, a time
gap): labels, fitness, evaluations, generations, full searches or resets of some frame. The
base settings have a small full GA so that the test stays quick.
"""
from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from dtm_labeler.labeling.bank_labeler import BankLabeler, BankSettings
from dtm_labeler.labeling.config import LabelerSettings
from dtm_labeler.labeling.recovery import DeferredRecovery
from dtm_labeler.labeling.stream import StreamLabeler
from dtm_labeler.labeling import tracked
from dtm_labeler.labeling.fast_path import YOUNG_S, FastPath
from dtm_labeler.labeling.tracker import TrackerSettings
from dtm_labeler.model.bank import ModelBank
from dtm_labeler.model.dtm import TriangulatedModel
from dtm_labeler.motion.synthetic import synthesize
from dtm_labeler.search.dtm_dp import regions_of
from dtm_labeler.search.label_search import GASettings
from dtm_labeler.search.problem import Background
from dtm_labeler.training.train import TrainConfig, train_model

CFG = TrainConfig(mixture="fixed", k_fixed=2, structure="given")
FRAMES = 40
HOLE = 20                            # 0.03 s between frames 19 and 20
BURST = (30, 31)                     # a frame with 2 cm of extra noise: the carried labeling falls short
# the tracker's one 6 cm radius (also for known velocities) follows the 2 cm burst frame's points,
# so the carried labeling falls short there instead of the tracks starting afresh
BASE = LabelerSettings(full=GASettings(population=16, max_generations=6, stagnation=3, polish_rounds=4,
                                       region_sweeps=1), tracker=TrackerSettings(known_gate_m=0.06))

#: a changed value per field, each chosen to matter on the stream below
CHANGES = {
    "method": "sga",
    "mode": "single",
    "window": 1,
    "full": GASettings(population=12, max_generations=3, stagnation=2, region_sweeps=0),
    "warm": GASettings(population=6, max_generations=2, stagnation=1, polish=False, fresh_fraction=0.5,
                       region_sweeps=0),
    "background": Background(volume_m3=0.5, max_speed_mps=1.0, detection_probability=0.5),
    "tracker": TrackerSettings(gate_m=0.004, gate_speed_factor=0.0, max_misses=0),
    "max_points": 12,
    "refit_drop": 1e6,
    "restarts": 0,
    "accept_drop": 1e6,
    "fast_rounds": 0,
    "swap_radius_m": 2.0,
    "release_moves": False,
    "recovery": "background",
    "audit_period_s": 0.05,
    "misfit_nats": 0.01,
    "confidence_temperature": 0.3,
    "chain_moves": 3,
    "mirror_switch_nats": 1000.0,
    "hold_nats": 1000.0,
    "hold_s": 0.0,
    "cluster_memory_s": 0.0,
    "bar_order_gain": 25.0,
    "cluster_turns": False,
    "turn_check": False,
    "upright_deg": 1.0,
    "bend_starts": 0,
    "region_checks": 0,
    "region_size": 2,
    "region_every": 1,
    "young_checks": 0,
    "young_candidates": 1,
    "region_branches": 6,
    "max_gap_s": 0.02,
    "noise_mm": 30.0,
    "heading_snap_deg": 0.0,
    "seed": 7,
}


@pytest.fixture(scope="module")
def models():
    walk = train_model([synthesize(duration=2.0, seed=s, heading=h, noise_mm=2) for s, h in [(0, 0.0), (1, 1.5)]],
                       CFG)[0]
    fast = train_model([synthesize(duration=2.0, seed=s, heading=h, noise_mm=2, speed=1.9)
                        for s, h in [(2, 0.5), (3, 2.5)]], CFG)[0]
    return walk, ModelBank({"walk": walk, "fast": fast})


@pytest.fixture(scope="module")
def stream():
    """A walker with 3 ghosts, one point hidden for 4 frames at a time, 4 mm noise, a frame with
    2 cm noise, points shuffled, and a 0.03 s hole in the stamps."""
    clip = synthesize(duration=FRAMES / 120 + 0.2, seed=9, heading=-1.0, noise_mm=4, start_xy=(0.5, 0.5))
    rng = np.random.default_rng(3)
    frames, t = [], 0.0
    for k in range(FRAMES):
        pts = clip.positions[k].copy()
        pts[(k // 4) % 14] = np.nan                                 # a marker hidden for 4 frames
        if BURST[0] <= k < BURST[1]:
            pts = pts + rng.normal(0.0, 0.02, size=pts.shape)
        ghosts = pts[~np.isnan(pts).any(1)].mean(0) + rng.uniform(-0.6, 0.6, size=(3, 3))
        xyz = np.vstack([pts, ghosts])[rng.permutation(17)]
        t += 0.03 if k == HOLE else 1 / 120
        frames.append((xyz, t))
    return frames


def trace(labeler, stream, base: list | None = None) -> list:
    """Per frame what the labeler did; with ``base``, stops at the first frame that differs."""
    out = []
    with labeler:
        for xyz, t in stream:
            r = labeler.process(xyz, t)
            out.append((r.labels.tolist(), np.round(r.confidence, 6).tolist(), round(float(r.log_likelihood), 6), r.evaluations, r.generations,
                        r.full_search, r.reset))
            if base is not None and out[-1] != base[len(out) - 1]:
                break
    return out


#: fields that act only while searches run in the background: compared with background recovery
#: made deterministic (DeferredRecovery)
BACKGROUND_ONLY = {"audit_period_s"}
#: fields that act only where a region's best relabelling gives a point to two labels: compared
#: with region checks over the whole body on every frame
WHOLE_BODY_REGIONS = {"region_branches"}
#: fields that act only when the carried labeling reads the body mirrored (which this walker's
#: stream never does): compared on the fast path's climb from the mirror image of a frame's
#: labeling, without region checks (which may turn the body round region by region)
MIRRORED_CARRY = {"mirror_switch_nats"}
#: fields that act only when a move would take a label a track has carried for a while onto a
#: point no label holds and the move gains by it (which this stream may never offer): compared on
#: what the fast path's hill-climb would pay for every such move (:meth:`TrackedLabeler._hold_cost`)
HELD_CARRY = {"hold_nats", "hold_s"}
#: fields that act only where the model has small rigid clusters (marker sets; the 14 body points'
#: bones form one) and the carried labeling reads one turned: compared on the fast path's climb from
#: a frame's labeling with three of its labels each one along, the model given them as a cluster
TURNED_CLUSTER = {"cluster_turns"}
#: fields that act only where the model has small rigid clusters and a move would rearrange one
#: against what its tracks' frames preferred: compared on what the fast path would pay for every
#: arrangement of a cluster after 30 frames, the models given the right arm as their one cluster
ARRANGED_CLUSTER = {"cluster_memory_s"}
#: fields that act only where a calibrated body has marker bars (this walker has none): compared on
#: what the fast path would pay for the right knee and ankle exchanged after the stream's 40 frames
#: (labels are read once their tracks have held them 0.25 s: the legs are never hidden here), the
#: models given the left knee's and ankle's order of that pair as their bar rows, each label a
#: partner of its own (two partners: 20 nats at most)
BARRED = {"bar_order_gain"}
#: fields that act only on labels of tracks begun after the stream's first frame, less than
#: ``YOUNG_S`` ago (this stream's labelled points keep the tracks they began with): compared on the
#: fast path's climb with the stream made older, every track young, from a frame's labeling with
#: three labels of the first label's region each one along
YOUNG_TRACKS = {"young_checks"}
#: fields that act only on a young check's relabelling: compared on the same climb with the young
#: check centred on that region's first label (which the young checks' turn may not pick)
YOUNG_REGION = {"young_candidates"}
#: fields that act only on a marker set's searches from scratch that fit below ``BEND_SHARE`` of
#: the level (this walker is 14 body points and fits well): compared with the walker's models
#: taken as a marker set and every search from scratch due for the check
POOR_MARKER_COLD = {"bend_starts"}


def make(kind, models, settings, background=False):
    walk, bank = models
    lab = StreamLabeler(walk, settings) if kind == "stream" else BankLabeler(bank, settings, BankSettings(min_share=2))
    if background:
        lab.recovery.close()
        lab.recovery = DeferredRecovery(lab, delay_frames=3)
    return lab


def frame_after(lab, stream, frames: int):
    """Label the stream's first ``frames`` frames; the last one's problem and published
    assignment."""
    for xyz, t in stream[:frames]:
        lab.process(xyz, t)
    problems, _, found = lab.last_frame
    return problems[found.best_model], found.best.assignment


def climb_from(kind, models, settings, stream, start_of) -> tuple:
    """The fast path's hill-climb (:meth:`TrackedLabeler._hill_climb`) of frame 10, started from
    ``start_of(problem, labeler, published assignment)``."""
    lab = make(kind, models, settings)
    with lab:
        p, a = frame_after(lab, stream, 10)
        ind, f, _ = lab._hill_climb(p, start_of(p, lab, a))
    return ind.tolist(), round(float(f), 6)


def mirrored_climb(kind, models, settings, stream) -> tuple:
    """The climb from the mirror image of frame 10's published labeling."""
    from dtm_labeler.search.label_ops import mirror
    return climb_from(kind, models, settings, stream, lambda p, lab, a: mirror(a[None], p.mirror_pairs)[0])


def turned_climb(kind, models, settings, stream) -> tuple:
    """The climb, on a region-check frame, from frame 10's labeling with the right arm's three
    labels each one along, the frame's model given those three as its one small rigid cluster
    (:attr:`TriangulatedModel.rigid_clusters`)."""
    def start_of(p, lab, a):
        arm = np.array([p.model.labels.index(n) for n in ("rshoulder", "relbow", "rwrist")])
        p.model._rigid_clusters = (arm,)
        lab._since_search = 0                              # a region-check frame
        start = a.copy()
        start[arm] = a[np.roll(arm, 1)]
        return start
    return climb_from(kind, models, settings, stream, start_of)


def young_climb(kind, models, settings, stream) -> tuple:
    """The climb from frame 10's labeling with three labels of the first labelled label's region
    each one along, the stream's start moved ``2 YOUNG_S`` back (its tracks, begun in its first
    frame, are then young tracks of an older stream)."""
    def start_of(p, lab, a):
        lab._stream_start -= 2 * YOUNG_S
        first = int(np.flatnonzero(a < p.n)[0])
        region = [m for m in regions_of(p.model, lab.settings.region_size)[first] if a[m] < p.n][:3]
        start = a.copy()
        start[region] = a[np.roll(region, 1)]
        return start
    return climb_from(kind, models, settings, stream, start_of)


def held_prices(kind, models, settings, stream) -> list:
    """What the fast path's hill-climb would pay for moving each labelled point's label onto each
    unlabelled point, after 10 and after 30 frames of the stream (None: nothing to pay)."""
    lab = make(kind, models, settings)
    out = []
    with lab:
        for k, (xyz, t) in enumerate(stream[:30]):
            lab.process(xyz, t)
            if k + 1 in (10, 30):
                problems, _, found = lab.last_frame
                p = problems[found.best_model]
                a = found.best.assignment
                held, free = np.flatnonzero(a < p.n), np.setdiff1d(np.arange(p.n), a)
                cand = np.repeat(a[None], held.size * free.size, 0)
                cand[np.arange(len(cand)), np.repeat(held, free.size)] = np.tile(free, held.size)
                price = lab._hold_cost(p, a)
                out.append(None if price is None else price(cand).tolist())
    return out


def arrangement_prices(kind, models, settings, stream) -> list | None:
    """What the fast path would pay for each arrangement of the right arm's labels over their
    points after 30 frames, every model given the arm as its one small rigid cluster (None:
    nothing to pay)."""
    lab = make(kind, models, settings)
    with lab:
        p, a = frame_after(lab, stream, 30)
        arm = np.array([p.model.labels.index(n) for n in ("rshoulder", "relbow", "rwrist")])
        cand = np.repeat(a[None], 6, 0)
        for row, order in enumerate(itertools.permutations(range(3))):
            cand[row, arm] = a[arm[list(order)]]
        tracks = lab._frame_tracks
        price = lab.cluster_evidence.cost(a, p.n, tracks, lab.tracker.began(tracks), lab.last_stamp)
    return None if price is None else np.round(price(cand), 6).tolist()


def bar_prices(kind, models, settings, stream) -> list | None:
    """What the fast path would pay for the right knee's and ankle's points exchanged after the
    stream's 40 frames (None: nothing to pay)."""
    lab = make(kind, models, settings)
    with lab:
        p, a = frame_after(lab, stream, FRAMES)
        ends = [p.model.labels.index(n) for n in ("rknee", "rankle")]
        cand = np.stack([a, a])
        cand[1, ends] = a[ends[::-1]]
        price = lab.bar_votes.cost(a, lab._frame_tracks)
    return None if price is None else price(cand).tolist()


def test_every_field_has_a_change():
    assert set(CHANGES) == {f.name for f in dataclasses.fields(LabelerSettings)}


@pytest.mark.parametrize("kind", ["stream", "bank"])
def test_every_setting_changes_both_labelers(kind, models, stream, monkeypatch):
    base = trace(make(kind, models, BASE), stream)
    assert trace(make(kind, models, BASE), stream) == base          # deterministic
    ignored = [name for name, value in CHANGES.items()
               if name not in BACKGROUND_ONLY | WHOLE_BODY_REGIONS | MIRRORED_CARRY | HELD_CARRY | TURNED_CLUSTER |
               YOUNG_TRACKS | YOUNG_REGION | POOR_MARKER_COLD | ARRANGED_CLUSTER | BARRED and
               trace(make(kind, models, dataclasses.replace(BASE, **{name: value})), stream, base) == base]
    bg = dataclasses.replace(BASE, recovery="background")
    for name in BACKGROUND_ONLY:
        base_bg = trace(make(kind, models, bg, True), stream)
        if trace(make(kind, models, dataclasses.replace(bg, **{name: CHANGES[name]}), True), stream, base_bg) == base_bg:
            ignored.append(name)
    whole = dataclasses.replace(BASE, region_size=16, region_every=1, region_checks=2)
    base_whole = trace(make(kind, models, whole), stream)
    for name in WHOLE_BODY_REGIONS:
        if trace(make(kind, models, dataclasses.replace(whole, **{name: CHANGES[name]})), stream, base_whole) == base_whole:
            ignored.append(name)
    no_regions = dataclasses.replace(BASE, region_checks=0)
    base_mirror = mirrored_climb(kind, models, no_regions, stream)
    for name in MIRRORED_CARRY:
        if mirrored_climb(kind, models, dataclasses.replace(no_regions, **{name: CHANGES[name]}), stream) == base_mirror:
            ignored.append(name)
    short_hold = dataclasses.replace(BASE, hold_s=0.1)          # the stream is 0.33 s long
    base_held = held_prices(kind, models, short_hold, stream)
    for name in HELD_CARRY:
        if held_prices(kind, models, dataclasses.replace(short_hold, **{name: CHANGES[name]}), stream) == base_held:
            ignored.append(name)
    no_regions_chains = dataclasses.replace(BASE, region_checks=0, fast_rounds=0)
    base_turned = turned_climb(kind, models, no_regions_chains, stream)
    for name in TURNED_CLUSTER:
        if turned_climb(kind, models, dataclasses.replace(no_regions_chains, **{name: CHANGES[name]}), stream) == base_turned:
            ignored.append(name)
    base_young = young_climb(kind, models, no_regions_chains, stream)
    for name in YOUNG_TRACKS:
        if young_climb(kind, models, dataclasses.replace(no_regions_chains, **{name: CHANGES[name]}), stream) == base_young:
            ignored.append(name)
    with monkeypatch.context() as patch:
        patch.setattr(TriangulatedModel, "rigid_clusters",
                      property(lambda self: (np.array([self.labels.index(n) for n in ("rshoulder", "relbow", "rwrist")]),)))
        base_arranged = arrangement_prices(kind, models, BASE, stream)
        assert base_arranged is not None and max(base_arranged) > 0      # the arm's frames preferred one arrangement
        for name in ARRANGED_CLUSTER:
            if arrangement_prices(kind, models, dataclasses.replace(BASE, **{name: CHANGES[name]}), stream) == base_arranged:
                ignored.append(name)
    with monkeypatch.context() as patch:
        def legs_order(model):
            lk, la, rk, ra = (model.labels.index(n) for n in ("lknee", "lankle", "rknee", "rankle"))
            return np.array([[lk, rk, ra], [la, ra, rk]])
        patch.setattr(tracked, "take_bar_orders", legs_order)
        patch.setattr(tracked, "segment_clusters", lambda M, segments: np.full(M, -1))
        base_barred = bar_prices(kind, models, BASE, stream)
        assert base_barred is not None and max(base_barred) > 0         # the left leg decided the pair
        for name in BARRED:
            if bar_prices(kind, models, dataclasses.replace(BASE, **{name: CHANGES[name]}), stream) == base_barred:
                ignored.append(name)
    with monkeypatch.context() as patch:
        patch.setattr(FastPath, "_young_centres", lambda self, p, ind: [int(np.flatnonzero(ind < p.n)[0])])
        base_region = young_climb(kind, models, no_regions_chains, stream)
        for name in YOUNG_REGION:
            if young_climb(kind, models, dataclasses.replace(no_regions_chains, **{name: CHANGES[name]}), stream) == base_region:
                ignored.append(name)
    with monkeypatch.context() as patch:
        patch.setattr(TriangulatedModel, "marker_set", property(lambda self: True))
        patch.setattr(tracked, "BEND_SHARE", 10.0)
        base_cold = trace(make(kind, models, BASE), stream)
        for name in POOR_MARKER_COLD:
            if trace(make(kind, models, dataclasses.replace(BASE, **{name: CHANGES[name]})), stream, base_cold) == base_cold:
                ignored.append(name)
    assert not ignored, f"{kind} labeler ignores {ignored}"
