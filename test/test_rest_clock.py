"""How long points have stayed put (:mod:`dtm_labeler.labeling.rest_clock`) and what the clutter
model's fixed part makes of it (``Background.fixed_after_s``)."""
import numpy as np
import pytest

from dtm_labeler.labeling.rest_clock import REST_MEMORY_S, REST_RADIUS_M, RestClock, take_rests
from dtm_labeler.labeling.tracker import Tracker
from dtm_labeler.motion.synthetic import synthesize
from dtm_labeler.search.problem import Background, FrameProblem
from dtm_labeler.training.train import TrainConfig, train_model

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


def test_a_long_rest_costs_a_label_only_beyond_what_its_training_showed():
    """The fixed reflections' term (``FrameProblem.rest_term``): a point resting beyond its
    label's limit -- the floor ``fixed_after_s`` or 1.5 x that label's longest rest in the
    training take -- pays the fixed part's loss on the one triangle that owns the label; resting
    less, or labelled as a label that stood as long in training, it pays nothing; no rests
    known, or the share 0: every term as the paper's."""
    clip = synthesize(duration=2.0, seed=3)
    P = clip.positions.copy()
    P[:, 0] = P[0, 0]                                   # label 0 stands still for the whole take
    model = train_model([clip._replace(positions=P)], TrainConfig(mixture="fixed", k_fixed=1,
                                                                    structure="given"))[0]
    longest = np.asarray(model.settings["longest_rest_s"])
    assert longest[0] == pytest.approx((clip.n_frames - 1) / clip.rate, abs=1e-3)
    assert (longest[1:] < 0.5).all()
    owner = model.label_owner
    assert (owner.sum(0) >= 0).all() and owner.sum() == model.n_labels    # one owner per label
    b = Background(fixed_share=0.002, fixed_after_s=2.0)
    limits = model.rest_limits(b.fixed_after_s)
    assert limits[0] == pytest.approx(1.5 * longest[0]) and (limits[1:] == 2.0).all()

    still = np.zeros((3, 6))
    still[:, :3] = [[0.0, 0.0, 1.0], [0.3, 0.0, 1.0], [0.0, 0.3, 1.0]]
    rest = np.array([3.0, 3.0, 1.0])                    # two points resting 3 s, one 1 s
    problem = FrameProblem(model, still, b, rest_s=rest)
    plain = FrameProblem(model, still, Background(fixed_share=0.0), rest_s=rest)
    loss = b.fixed_loss(still[:, 3:])
    n, M = 3, model.n_labels
    for label in range(M):
        for p in range(3):
            ind = np.full(M, n, dtype=np.int64)
            ind[label] = p
            cost = float(plain.fitness(ind)[0] - problem.fitness(ind)[0])
            pays = rest[p] >= limits[label]
            assert cost == pytest.approx(loss[p] if pays else 0.0, abs=1e-9), (label, p)
    assert FrameProblem(model, still, b)._rest is None               # rests unknown
    assert FrameProblem(model, still, Background(fixed_share=0.0), rest_s=rest)._rest is None
    with pytest.raises(ValueError):
        Background(fixed_after_s=-1.0)
