"""The bar orders' live votes (:mod:`dtm_labeler.labeling.bar_order_votes`): which tracked end of a
marker bar is which, from what the tracks have shown of the bar's order."""
from __future__ import annotations

import numpy as np

from dtm_labeler.labeling.bar_order_votes import VETO_NATS, BarOrderVotes

# labels: 0 / 1 the bar's ends, 2 and 3 partners nearer end 0, 4 a partner on 3's segment
A, B, X, Y, Z = range(5)
M = 5
ORDERS = np.array([[X, A, B], [Y, A, B], [Z, A, B]])
GROUPS = np.array([-1, -1, -1, 3, 3])        # Y and Z: one rigid segment, one partner


def frame(rng):
    """Points of one frame: the bar's true ``A`` end at x = 0.1, ``B`` at x = 0.2, partners at
    x <= 0, all jittered; the points in the order of their labels."""
    pts = np.array([[0.1, 0, 0], [0.2, 0, 0], [0.0, 0.1, 0], [-0.1, 0.0, 0], [-0.1, 0.05, 0]])
    return pts + rng.normal(0, 0.005, pts.shape)


def run(votes, frames: int, assignment, tracks, rng, t0=0.0):
    for k in range(frames):
        votes.update(assignment, frame(rng), tracks, t0 + k / 120)


def test_an_exchanged_bar_is_decided_back_once_two_partners_agree():
    rng = np.random.default_rng(0)
    votes = BarOrderVotes(ORDERS, M, GROUPS)
    tracks = np.array([10, 11, 12, 13, 14])
    swapped = np.array([B, A, X, Y, Z])          # label -> point: the ends exchanged
    run(votes, 1, swapped, tracks, rng)
    # one frame: 3 nats per partner, two partners (Y and Z are one): not yet decided
    assert votes.decided(swapped, tracks) == []
    assert votes.kept(swapped, tracks) is swapped
    run(votes, 5, swapped, tracks, rng)
    assert votes.decided(swapped, tracks) == [(A, B, 0, 1)]     # A belongs on point 0, B on point 1
    right = votes.kept(swapped, tracks)
    assert right.tolist() == [0, 1, X, Y, Z]
    price = votes.cost(swapped, tracks)(np.stack([swapped, right]))
    assert price.tolist() == [VETO_NATS, 0.0]
    # the decision is about the tracks, not the labels they carry: the same once labelled right
    assert votes.decided(right, tracks) == [(A, B, 0, 1)]


def test_one_partner_never_decides_and_a_segment_counts_once():
    rng = np.random.default_rng(1)
    lone = BarOrderVotes(ORDERS[1:], M, GROUPS)       # Y and Z only: one segment
    tracks = np.arange(20, 25)
    swapped = np.array([B, A, X, Y, Z])
    run(lone, 200, swapped, tracks, rng)
    assert lone.decided(swapped, tracks) == []
    apart = BarOrderVotes(ORDERS[1:], M, None)        # counted as two partners they decide
    run(apart, 10, swapped, tracks, rng)
    assert apart.decided(swapped, tracks) == [(A, B, 0, 1)]


def test_a_track_back_from_a_gap_is_judged_by_the_one_that_stayed():
    rng = np.random.default_rng(2)
    votes = BarOrderVotes(np.vstack([ORDERS, [[2, A, B]]]), M, None)    # X counted twice: 3 partners
    right = np.array([A, B, X, Y, Z])
    run(votes, 20, right, np.array([30, 31, 32, 33, 34]), rng)
    # B's marker back on a new track (35); a search gives the new track A's label
    back = np.array([30, 35, 32, 33, 34])
    swapped = np.array([B, A, X, Y, Z])
    assert votes.decided(swapped, back) == [(A, B, 0, 1)]        # track 30 showed it is A: 30 nats / 2
    assert votes.kept(swapped, back).tolist() == [0, 1, X, Y, Z]
    # nothing to say where both tracks are new, nor where an end is not on a point
    assert votes.decided(swapped, np.array([40, 41, 32, 33, 34])) == []
    assert votes.decided(np.array([5, A, X, Y, Z]), back) == []


def test_forgotten_tracks_and_off():
    rng = np.random.default_rng(3)
    votes = BarOrderVotes(ORDERS, M, GROUPS)
    right = np.array([A, B, X, Y, Z])
    for k in range(12):                                   # many pairs of tracks over 3 s
        votes.update(right, frame(rng), np.array([100 + 2 * k, 101 + 2 * k, 2, 3, 4]), k * 0.25)
    kept = votes.bars[0].counts.keys()
    assert {100, 101} & set(kept) == set() and {122, 123} <= set(kept)
    off = BarOrderVotes(ORDERS, M, GROUPS, min_gain=0.0)
    assert not off.active
    run(off, 10, right, np.arange(5), rng)
    assert off.decided(right, np.arange(5)) == [] and off.cost(right, np.arange(5)) is None
    assert not BarOrderVotes(np.zeros((0, 3)), M).active


def test_a_real_stream_decides_both_wrist_bars_and_a_search_result_exchanged_is_turned_back(hdm05_calibrated,
                                                                                             hdm05_take):
    """HDM05's 41 markers under its calibrated model: after two seconds of the stream (the labels are
    read once their tracks have held them for ``hold_s``, 1 s) both wrist bars' tracks are decided the way the capture names them; a search result with the left bar's ends
    exchanged is turned back (its fitness scored again), and the fast path's moves pay for it."""
    from dtm_labeler.labeling.config import LabelerSettings
    from dtm_labeler.labeling.stream import StreamLabeler
    from dtm_labeler.labeling.tracked import Candidate, FrameSearch
    clip = hdm05_take.slice(2000, 2240)
    lab = StreamLabeler(hdm05_calibrated, LabelerSettings(recovery="inline"))
    names = list(hdm05_calibrated.labels)
    la, lb, ra, rb = (names.index(n) for n in ("LWRA", "LWRB", "RWRA", "RWRB"))
    with lab:
        for k in range(clip.n_frames):
            lab.process(clip.positions[k], k / clip.rate)
        problems, inp, found = lab.last_frame
        m = found.best_model
        truth = found.best.assignment
        tracks = lab._frame_tracks
        assert [int(inp.keep[truth[i]]) for i in (la, lb, ra, rb)] == [la, lb, ra, rb]   # as the capture names them
        assert sorted(lab.bar_votes.decided(truth, tracks)) == [(la, lb, truth[la], truth[lb]),
                                                               (ra, rb, truth[ra], truth[rb])]
        swapped = truth.copy()
        swapped[[la, lb]] = truth[[lb, la]]
        f = float(problems[m].fitness(swapped[None])[0])
        kept = lab._bar_orders_kept(problems, FrameSearch({m: Candidate(swapped, f)}, full=True))
        assert kept.best.assignment.tolist() == truth.tolist()
        assert kept.best.fitness == float(problems[m].fitness(truth[None])[0])
        price = lab._move_cost(problems[m], truth)(np.stack([truth, swapped]))
        assert price[1] - price[0] >= VETO_NATS
        off = StreamLabeler(hdm05_calibrated, LabelerSettings(recovery="inline", bar_order_gain=0.0))
        with off:
            for k in range(clip.n_frames):
                off.process(clip.positions[k], k / clip.rate)
            problems, _, found = off.last_frame
            assert off._bar_orders_kept(problems, FrameSearch({m: Candidate(swapped, f)}, full=True)
                                        ).best.assignment.tolist() == swapped.tolist()


def test_single_frame_mode_has_no_bar_votes(hdm05_calibrated):
    """Every frame labelled on its own: no track memory, so no votes (as no fast-path prior)."""
    from dtm_labeler.labeling.config import LabelerSettings
    from dtm_labeler.labeling.stream import StreamLabeler
    with StreamLabeler(hdm05_calibrated, LabelerSettings(mode="single")) as single, \
            StreamLabeler(hdm05_calibrated, LabelerSettings()) as stream:
        assert not single.bar_votes.active and stream.bar_votes.active
        stream.update_settings(LabelerSettings(bar_order_gain=0.0))
        assert not stream.bar_votes.active
