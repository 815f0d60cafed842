"""How long points have stayed put (:mod:`dtm_labeler.labeling.rest_clock`) and what the clutter
model's fixed part makes of it (``Background.fixed_after_s``)."""
import numpy as np
import pytest

from dtm_labeler.labeling.rest_clock import REST_MEMORY_S, REST_RADIUS_M, RestClock, take_rests
from dtm_labeler.labeling.tracker import Tracker
from dtm_labeler.search.problem import Background

RATE = 100.0


def test_a_still_point_rests_a_moving_one_does_not():
    clock = RestClock()
    for f in range(200):
        t = f / RATE
        xyz = np.array([[0.3, 0.2, 0.01 + 0.0004 * np.sin(f)],       # a reflection, sub-mm jitter
                        [t, 0.0, 1.0]])                               # a marker moving at 1 m/s
        rest, episode = clock.update(np.array([4, 9]), xyz, t)
    assert rest[0] == pytest.approx(1.99)
    assert rest[1] == 0.0
    # a step beyond the radius starts a new rest (a new episode) at once
    rest2, episode2 = clock.update(np.array([4, 9]), xyz + [[2 * REST_RADIUS_M, 0, 0], [0.01, 0, 0]], 2.0)
    assert rest2[0] == 0.0 and episode2[0] != episode[0]


def test_a_flickering_reflection_keeps_its_rest_across_new_tracks():
    """Seen 12 frames of every 20, each time on a new track id, as a tracker that deletes tracks
    after a few misses reports it: the rest goes on from the first frame; a new track elsewhere
    starts at 0."""
    clock = RestClock()
    for f in range(291):
        if f % 20 >= 12:
            rest, _ = clock.update(np.array([1]), np.array([[2 * f / RATE, 0.0, 1.0]]), f / RATE)
            continue
        ids = np.array([1, 1000 + f // 20, 5000 + f // 20])
        xyz = np.array([[2 * f / RATE, 0.0, 1.0], [0.5, 0.5, 0.01], [-0.5 + (f // 20) * 0.1, 0.5, 0.01]])
        rest, _ = clock.update(ids, xyz, f / RATE)
    assert rest[1] == pytest.approx(2.90)
    assert rest[2] < 0.12                     # moved 10 cm between its appearances
    # forgotten after the memory: the same place, much later, starts afresh
    rest, _ = clock.update(np.array([7777]), np.array([[0.5, 0.5, 0.01]]), 2.9 + REST_MEMORY_S + 0.1)
    assert rest[0] == 0.0


def test_take_rests_know_a_rest_from_its_first_frame():
    """Offline the whole episode is known: every frame of a 2 s rest reads 2 s, untracked points 0."""
    F = 300
    xyz, ids = [], []
    for f in range(F):
        still = [0.2, 0.2, 0.0] if f < 200 else [0.9, 0.2, 0.0]      # stops at one place, then another
        xyz.append(np.array([still, [2 * f / RATE, 0, 1], [0, 0, 0]]))
        ids.append(np.array([3, 8, -1]))
    rests = take_rests(xyz, ids, RATE)
    assert rests[0][0] == pytest.approx(1.99) and rests[199][0] == pytest.approx(1.99)
    assert rests[200][0] == pytest.approx(0.99)
    assert all(r[1] == 0.0 and r[2] == 0.0 for r in rests)


def test_the_tracker_reports_rests():
    tr = Tracker()
    for f in range(150):
        upd = tr.update(np.array([[0.1, 0.1, 0.005], [2 * f / RATE, 0.0, 1.0]]), f / RATE)
    assert upd.rest_s[0] == pytest.approx(1.49) and upd.rest_s[1] == 0.0
    tr.reset()
    assert tr.update(np.array([[0.1, 0.1, 0.005]]), 2.0).rest_s[0] == 0.0


def test_the_fixed_part_waits_for_a_long_rest():
    """With ``fixed_after_s`` a still point is scored as possibly a reflection only once it has
    rested that long; before, and with no rests known, the clutter is the uniform density exactly."""
    b = Background(fixed_share=0.002, fixed_after_s=2.0)
    v = np.zeros((3, 3))
    rest = np.array([0.5, 1.99, 2.5])
    loss = b.log_velocity_of(v, rest) - b.log_velocity
    assert loss[0] == 0.0 and loss[1] == 0.0 and 8.0 < loss[2] < 10.0
    assert (b.log_velocity_of(v) == b.log_velocity).all()
    every = Background(fixed_share=0.002)                   # 0: every still point, rests or not
    assert np.allclose(every.log_velocity_of(v, rest), every.log_velocity_of(v))
    assert (every.log_velocity_of(v) - every.log_velocity > 8.0).all()
    with pytest.raises(ValueError):
        Background(fixed_after_s=-1.0)
