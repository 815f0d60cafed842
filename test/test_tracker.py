"""Frame-to-frame point association: ids, velocities (m/s), coasting, deletion, crossings."""
import numpy as np
import pytest

from dtm_labeler.labeling.tracker import Tracker, TrackerSettings

RATE = 100.0
DT = 1.0 / RATE


def test_new_points_get_new_ids_and_no_velocity():
    tr = Tracker()
    u = tr.update(np.array([[0, 0, 1.0], [1, 0, 1.0]]), 0.0)
    assert u.track_ids.tolist() == [0, 1] and u.new.all() and u.lost.size == 0
    assert np.isnan(u.states[:, 3:]).all() and np.array_equal(u.states[:, :3], [[0, 0, 1], [1, 0, 1]])
    # second frame: same points moved -> same ids, velocity in m/s
    u = tr.update(np.array([[1.01, 0, 1.0], [0.0, 0.02, 1.0]]), DT)      # order shuffled
    assert u.track_ids.tolist() == [1, 0] and not u.new.any()
    np.testing.assert_allclose(u.states[:, 3:], [[1.0, 0, 0], [0, 2.0, 0]], atol=1e-9)
    # a third point appears
    u = tr.update(np.array([[0.0, 0.04, 1.0], [1.02, 0, 1.0], [5, 5, 5]]), 2 * DT)
    assert u.track_ids.tolist() == [0, 1, 2] and u.new.tolist() == [False, False, True]
    assert np.isnan(u.states[2, 3:]).all()
    np.testing.assert_allclose(u.states[:2, 3:], [[0, 2.0, 0], [1.0, 0, 0]], atol=1e-9)


def test_velocity_uses_the_true_time_step():
    tr = Tracker()
    tr.update(np.array([[0.0, 0, 0]]), 10.0)
    u = tr.update(np.array([[0.05, 0, 0]]), 10.05)              # irregular stamp: 1 m/s
    np.testing.assert_allclose(u.states[0, 3:], [1.0, 0, 0], atol=1e-9)


def test_vanishing_coasting_reappearing_and_deletion():
    tr = Tracker(TrackerSettings(max_misses=3))
    v = np.array([1.5, 0.0, 0.0])                                # 1.5 m/s along x
    still = np.array([0.0, 2.0, 1.0])
    p = lambda k: np.array([0.0, 0.0, 1.0]) + v * k * DT       # noqa: E731
    for k in range(3):
        u = tr.update(np.vstack([p(k), still]), k * DT)
    moving_id = int(u.track_ids[0])
    # gone for 3 frames (coasting), back where constant velocity predicts
    for k in range(3, 6):
        u = tr.update(still[None], k * DT)
        assert u.lost.size == 0
    np.testing.assert_allclose(tr.position_of(moving_id, 6 * DT), p(6), atol=1e-9)
    u = tr.update(np.vstack([p(6), still]), 6 * DT)
    assert int(u.track_ids[0]) == moving_id and not u.new[0]
    np.testing.assert_allclose(u.states[0, 3:], v, atol=1e-6)   # displacement over 4 frames / 4 dt
    np.testing.assert_allclose(u.unseen_s, [4 * DT, 0.0])         # back after coasting: unseen since frame 2
    u = tr.update(np.vstack([p(7), still]), 7 * DT)
    assert (u.unseen_s == 0).all()                                # seen last frame
    # gone for longer than max_misses: deleted (reported once), comes back as a new track
    lost_seen = []
    for k in range(8, 13):
        u = tr.update(still[None], k * DT)
        lost_seen += u.lost.tolist()
    assert lost_seen == [moving_id]
    assert np.isnan(tr.position_of(moving_id, 13 * DT)).all()
    u = tr.update(np.vstack([p(13), still]), 13 * DT)
    assert u.new[0] and int(u.track_ids[0]) != moving_id and np.isnan(u.states[0, 3:]).all()
    assert u.unseen_s[0] == 0.0                                   # a new track has no gap behind it
    assert len(set(u.track_ids.tolist())) == 2


def test_all_points_missing_in_a_frame():
    tr = Tracker()
    a = np.array([[0, 0, 1.0], [0.5, 0, 1.0]])
    tr.update(a, 0.0)
    tr.update(a + [0.01, 0, 0], DT)
    u = tr.update(np.zeros((0, 3)), 2 * DT)
    assert u.track_ids.shape == (0,) and u.states.shape == (0, 6) and u.lost.size == 0
    u = tr.update(a + [0.03, 0, 0], 3 * DT)
    assert u.track_ids.tolist() == [0, 1] and not u.new.any()
    np.testing.assert_allclose(u.states[:, 3:], [[1.0, 0, 0]] * 2, atol=1e-9)


def test_two_points_crossing_at_speed():
    """Two markers pass each other 1 cm apart at 2 m/s each (4 m/s closing speed, 3.3 cm per
    frame at 120 Hz): constant-velocity prediction keeps the ids on the right points."""
    rate = 120.0
    tr = Tracker()
    ids_a, ids_b = set(), set()
    for k in range(-20, 21):
        t = k / rate
        a = np.array([2.0 * t, 0.0, 1.0])
        b = np.array([-2.0 * t, 0.01, 1.0])
        pts = np.vstack([a, b]) if k % 2 else np.vstack([b, a])     # input order alternates
        u = tr.update(pts, t + 5.0)
        ia, ib = (u.track_ids[0], u.track_ids[1]) if k % 2 else (u.track_ids[1], u.track_ids[0])
        ids_a.add(int(ia))
        ids_b.add(int(ib))
        if k > -19:
            va = u.states[0 if k % 2 else 1, 3:]
            np.testing.assert_allclose(va, [2.0, 0, 0], atol=1e-6)
    assert len(ids_a) == 1 and len(ids_b) == 1 and ids_a != ids_b


def test_input_ids_are_honoured():
    tr = Tracker()
    u = tr.update(np.array([[0, 0, 0], [1, 1, 1.0]]), 0.0, ids=np.array([7, 42]))
    assert u.track_ids.tolist() == [7, 42] and u.new.all()
    # ids, not positions, decide: the two points jump far and swap places
    u = tr.update(np.array([[0, 0, 0], [1, 1, 1.0]]), DT, ids=np.array([42, 7]))
    assert u.track_ids.tolist() == [42, 7] and not u.new.any()
    np.testing.assert_allclose(u.states[0, 3:], [-100.0] * 3)
    # an unknown id starts a track; generated ids never collide with given ones later
    u = tr.update(np.array([[0, 0, 0]]), 2 * DT, ids=np.array([100]))
    assert u.new.tolist() == [True] and u.track_ids.tolist() == [100]
    u = tr.update(np.array([[0, 0, 0], [9, 9, 9.0]]), 3 * DT)
    assert 100 in u.track_ids.tolist() and u.track_ids.max() > 100


def test_gate_and_settings():
    with pytest.raises(ValueError):
        TrackerSettings(gate_m=0)
    with pytest.raises(ValueError):
        TrackerSettings(max_misses=-1)
    tr = Tracker(TrackerSettings(gate_m=0.05, gate_speed_factor=0.0))
    tr.update(np.array([[0, 0, 0.0]]), 0.0)
    u = tr.update(np.array([[0.2, 0, 0.0]]), DT)                   # outside the gate: a new track
    assert u.new.all() and u.track_ids.tolist() == [1]


def test_time_going_backwards_gives_no_velocity():
    tr = Tracker()
    tr.update(np.array([[0, 0, 0.0]]), 1.0)
    u = tr.update(np.array([[0.01, 0, 0.0]]), 0.99)
    assert np.isnan(u.states[0, 3:]).all() and not u.new[0]


def test_reset():
    tr = Tracker()
    tr.update(np.array([[0, 0, 0.0]]), 0.0)
    tr.reset()
    u = tr.update(np.array([[0, 0, 0.0]]), 0.1)
    assert u.new.all() and u.track_ids.tolist() == [0] and tr.t == 0.1


def test_new_input_ids_continue_a_lost_track():
    """A marker back from a one-frame occlusion under a new input id continues its track (the id
    becomes an alias), so the labels carried by the track stay."""
    tr = Tracker()
    p = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 1.0], [1.0, 0.0, 1.0]])
    tr.update(p, 0.00, ids=np.array([10, 11, 12]))
    tr.update(p[[0, 2]] + [0.01, 0, 0], 0.01, ids=np.array([10, 12]))            # 11 hidden
    u = tr.update(p + [0.02, 0, 0], 0.02, ids=np.array([10, 99, 12]))            # back as 99
    assert u.track_ids.tolist() == [10, 11, 12] and not u.new.any()
    assert np.isfinite(u.states[1, 3:]).all()
    u = tr.update(p + [0.03, 0, 0], 0.03, ids=np.array([10, 99, 12]))            # the alias holds
    assert u.track_ids.tolist() == [10, 11, 12]
    far = tr.update(np.vstack([p + [0.04, 0, 0], [[5.0, 5.0, 1.0]]]), 0.04, ids=np.array([10, 99, 12, 50]))
    assert far.track_ids.tolist() == [10, 11, 12, 50] and far.new.tolist() == [False, False, False, True]


def test_warm_up_loads_the_kernel_the_tracker_calls():
    """A fresh process: after tracker.warm_up() (Engine.prepare calls it) the matching kernel is
    loaded with the very signature Tracker.update calls it with, so a stream's second frame
    does not load it (20-50 ms, several frame budgets)."""
    import subprocess
    import sys
    code = (
        "import numpy as np\n"
        "from dtm_labeler.labeling import tracker\n"
        "assert not tracker.gated_cost.signatures\n"
        "tracker.warm_up()\n"
        "warm = list(tracker.gated_cost.signatures)\n"
        "tr = tracker.Tracker()\n"
        "x = np.random.default_rng(0).normal(size=(5, 3))\n"
        "tr.update(x, 0.0)\n"
        "tr.update(x + 0.001, 1 / 120)\n"
        "assert len(warm) == 1 and list(tracker.gated_cost.signatures) == warm, (warm, tracker.gated_cost.signatures)\n"
        "print('ok')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_known_velocity_gate_keeps_a_neighbour_off_a_coasting_track():
    """A track whose velocity is known predicts its point closely: a neighbouring marker
    appearing 4.5 cm from the prediction while the track's own marker is hidden starts a track
    of its own (``known_gate_m`` 3 cm) instead of taking the hidden one's. A point seen once
    (no velocity) is still followed 5 cm on (``gate_m`` 6 cm)."""
    tr = Tracker(TrackerSettings(gate_speed_factor=0.0))
    for k in range(3):                                       # a still marker: velocity known
        u = tr.update(np.array([[0, 0, 1.0]]), k * DT)
    hidden_id = int(u.track_ids[0])
    u = tr.update(np.zeros((0, 3)), 3 * DT)                  # hidden: its track coasts
    u = tr.update(np.array([[0.045, 0, 1.0]]), 4 * DT)       # a neighbour appears
    assert u.new.all() and u.track_ids[0] != hidden_id
    u = tr.update(np.array([[0.0, 0, 1.0], [0.045, 0, 1.0]]), 5 * DT)   # the hidden one is back
    assert hidden_id in u.track_ids.tolist()
    fresh = Tracker(TrackerSettings(gate_speed_factor=0.0))
    fresh.update(np.array([[0, 0, 1.0]]), 0.0)
    u = fresh.update(np.array([[0.05, 0, 1.0]]), DT)          # seen once: no velocity, wide gate
    assert not u.new.any()
    with pytest.raises(ValueError):
        TrackerSettings(known_gate_m=0)


def test_tracks_of_a_gappy_dense_marker_set_stay_pure(data_dir):
    """The 55-marker Qualisys walk with half of its samples in realistic gaps (mean 0.1 s, the
    capture benchmark's settings): few samples lie on a track that held another marker before
    (6 cm for every track: 183 of 4679 on this half, 3.9 %)."""
    from collections import Counter, defaultdict

    from dtm_labeler.evaluation.corruption import realistic_gaps
    from dtm_labeler.motion.load import load_clip
    clip = load_clip(data_dir / "markers_c3d" / "qualisys_walk_55markers.c3d")
    P = clip.positions.copy()
    P[realistic_gaps(clip.n_frames, clip.n_points, clip.rate, missing=0.5, mean_gap_s=0.1, spread=20.0,
                     seed=1)] = np.nan
    P = P[clip.n_frames // 2:]

    def impure_share(settings):
        tr, held = Tracker(settings), defaultdict(Counter)
        for k, frame in enumerate(P):
            seen = np.flatnonzero(np.isfinite(frame).all(1))
            u = tr.update(frame[seen], k / clip.rate)
            for t, marker in zip(u.track_ids, seen):
                held[int(t)][int(marker)] += 1
        return sum(sum(c.values()) - max(c.values()) for c in held.values()) / sum(
            sum(c.values()) for c in held.values())

    assert impure_share(TrackerSettings()) < 0.01
    assert impure_share(TrackerSettings(known_gate_m=0.06)) > 0.02       # one wide radius for all


def test_an_id_seen_before_never_continues_another_track():
    """With input ids, a new id may continue a track that lost its point (a system that gives a
    marker back from occlusion a new id); an id seen before whose track ended is the same marker
    back (a C3D channel after a long gap) and starts a track of its own, even beside another
    marker's coasting track."""
    tr = Tracker(TrackerSettings(gate_speed_factor=0.0, max_misses=2))
    tr.update(np.array([[0, 0, 1.0], [0.5, 0, 1.0]]), 0.0, ids=np.array([3, 4]))
    tr.update(np.array([[0, 0, 1.0], [0.5, 0, 1.0]]), DT, ids=np.array([3, 4]))
    for k in range(2, 6):                                    # id 3 hidden: its track ends
        tr.update(np.array([[0.5, 0, 1.0]]), k * DT, ids=np.array([4]))
    tr.update(np.array([[0.2, 0, 1.0]]), 6 * DT, ids=np.array([8]))        # another marker ...
    tr.update(np.array([[0.2, 0, 1.0]]), 7 * DT, ids=np.array([8]))        # ... then hidden: coasts
    u = tr.update(np.array([[0.21, 0, 1.0]]), 8 * DT, ids=np.array([3]))   # id 3 back beside it
    assert u.new.all() and u.track_ids.tolist() == [3]
    u = tr.update(np.array([[0.21, 0, 1.0]]), 9 * DT, ids=np.array([9]))   # a new id: continues
    assert not u.new.any() and u.track_ids.tolist() == [3]


def test_when_tracks_began_were_last_seen_and_where_coasting_ones_are_predicted():
    tr = Tracker()
    v = np.array([1.0, 0.0, 0.0])
    a = np.array([0.0, 0.0, 1.0])
    for k in range(3):                                            # track 0 from t = 0
        pts = [a + v * k * DT] + ([[2.0, 0.0, 1.0]] if k >= 1 else [])   # track 1 from t = DT
        tr.update(np.array(pts), k * DT)
    tr.update(np.array([[2.0, 0.0, 1.0]]), 3 * DT)                # track 0 hidden: it coasts
    np.testing.assert_allclose(tr.began([1, 0, 99]), [DT, 0.0, np.nan])
    last, pred, known = tr.coasting(np.array([0, 1, 99]), 5 * DT)
    np.testing.assert_allclose(last, [2 * DT, 3 * DT, np.nan])
    assert known.tolist() == [True, True, False]
    np.testing.assert_allclose(pred[0], a + v * 5 * DT, atol=1e-9)           # constant velocity
    np.testing.assert_allclose(pred[1], [2.0, 0.0, 1.0], atol=1e-9)
    assert np.isnan(pred[2]).all()
    assert np.isnan(Tracker().began([0])).all()


def test_member_is_isin_for_the_hot_paths_arrays():
    """``member`` (a broadcast comparison) answers as ``np.isin`` does: small and large arrays
    (the sorted path beyond ``MEMBER_PAIRS``), empty ones, 2-d values."""
    from dtm_labeler.labeling.tracker import MEMBER_PAIRS, member
    rng = np.random.default_rng(0)
    for a_n, b_n in [(0, 5), (5, 0), (1, 1), (17, 4096), (300, 300), (4, 3)]:
        a, b = rng.integers(0, 400, a_n), rng.integers(0, 400, b_n)
        assert np.array_equal(member(a, b), np.isin(a, b))
    assert 300 * 300 > MEMBER_PAIRS
    a2 = rng.integers(0, 20, (6, 5))
    assert np.array_equal(member(a2, np.arange(10)), np.isin(a2, np.arange(10)))


def test_position_of_is_the_predicted_row():
    """``position_of`` predicts one track (also through an input id that continues it) exactly
    as ``predicted`` does for every track."""
    tr = Tracker()
    tr.update(np.array([[0.0, 0, 1], [1, 0, 1], [2, 0, 1]]), 0.0, ids=np.array([5, 6, 7]))
    tr.update(np.array([[0.01, 0.02, 1], [1.03, 0, 1]]), DT, ids=np.array([5, 6]))
    tr.update(np.array([[0.021, 0.04, 1]]), 2 * DT, ids=np.array([5]))
    t = 4.5 * DT
    pred = tr.predicted(t)
    for k, tid in enumerate(tr.ids):
        assert np.array_equal(tr.position_of(int(tid), t), pred[k])
    assert np.isnan(tr.position_of(99, t)).all()


@pytest.mark.parametrize("hidden_frames, region_size, event", [(1, 3, False), (8, 3, True), (8, 6, False)])
def test_a_marker_back_from_a_bridged_gap_is_an_event_a_flicker_is_not(hidden_frames, region_size, event):
    """The fast path checks the region of a point whose track began last frame (a marker back on
    a new track); a marker back on a track the tracker bridged across its gap is such an event
    too (``RESUMED_EVENT_S``: the arm's chain shifted by one while its elbow and wrist were hidden
    stayed so for 40 frames of a 41-marker stream), a marker hidden for a frame (flicker) is not,
    and neither is one of a body of under ``RESUMED_EVENT_REGIONS`` regions (the walker's 14
    points in regions of 6; of 3 they are more)."""
    from dtm_labeler.labeling.fast_path import RESUMED_EVENT_REGIONS, RESUMED_EVENT_S
    from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler
    from dtm_labeler.motion.synthetic import synthesize
    from dtm_labeler.training.train import TrainConfig, train_model
    model = train_model([synthesize(duration=2.0, seed=s, heading=h, noise_mm=2) for s, h in [(0, 0.0), (1, 1.5)]],
                        TrainConfig(mixture="fixed", k_fixed=2, structure="given"))[0]
    clip = synthesize(duration=0.5, seed=9, heading=-1.0, noise_mm=2)
    wrist = list(model.labels).index("rwrist")
    assert 1 / clip.rate < RESUMED_EVENT_S < 8 / clip.rate
    assert (model.n_labels >= RESUMED_EVENT_REGIONS * region_size) is (region_size == 3)
    back = 20 + hidden_frames
    with StreamLabeler(model, LabelerSettings(region_size=region_size)) as lab:
        for k in range(back + 1):
            xyz = clip.positions[k].copy()
            if 20 <= k < back:
                xyz[wrist] = np.nan                                  # hidden: its track coasts
            lab.process(xyz, k / clip.rate)
            if k == back:
                assert lab.tracker.misses.max() == 0                 # the wrist is back on its old track
                assert (wrist in lab._event_points.tolist()) is event
