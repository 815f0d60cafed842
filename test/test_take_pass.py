"""The take's second pass (labeling/take_pass.py): the facing from the whole take, states along
the tracks, and the pass itself on a real half-hidden capture through dtm-label's path."""
import copy

import numpy as np
import pytest

from dtm_labeler.evaluation.pipeline import label_clip_run, passed
from dtm_labeler.labeling.stream import LabelerSettings
from dtm_labeler.labeling.take_pass import (clutter_points, filled_trajectories, held_labels, kept_clutter, take_heading,
                                           track_states)
from dtm_labeler.motion.synthetic import synthesize
from dtm_labeler.search.problem import FrameProblem
from dtm_labeler.model.features import lateral_yaw
from dtm_labeler.motion.load import load_clip
from dtm_labeler.motion.pointsets import to_point_set
from dtm_labeler.training.calibrate import calibrate_from_clip
from dtm_labeler.training.train import TrainConfig, train_model
from test_gappy_training import HDM, _gapped


def _angle(a, b):
    return np.degrees(np.abs(np.angle(np.exp(1j * (a - b)))))


def test_filled_trajectories_interpolate_each_label_over_its_gaps():
    xyz = [np.array([[0.0, 0, 0], [1, 1, 1]]), np.array([[5.0, 5, 5]]), np.array([[2.0, 0, 0], [9, 9, 9]])]
    labels = [np.array([0, 1]), np.array([-1]), np.array([0, -1])]
    P = filled_trajectories(xyz, labels, 3)
    assert np.allclose(P[:, 0], [[0, 0, 0], [1, 0, 0], [2, 0, 0]])      # label 0: linear across its gap
    assert np.allclose(P[:, 1], [[1, 1, 1]] * 3)                           # label 1: held after its last sighting
    assert np.isnan(P[:, 2]).all()                                         # never given: NaN


def test_track_states_difference_along_tracks_only():
    xyz = [np.array([[0.0, 0, 0], [1, 0, 0]]), np.array([[1.1, 0, 0], [0.2, 0, 0]]), np.array([[0.4, 0, 0]])]
    tracks = [np.array([7, 8]), np.array([8, 7]), np.array([-1])]
    st = track_states(xyz, tracks, rate=10.0)
    assert np.isnan(st[0][:, 3:]).all()                                    # first frame: no velocity
    assert np.allclose(st[1][:, 3], [1.0, 2.0])                            # per track, not per row
    assert np.isnan(st[2][0, 3:]).all()                                    # untracked
    assert np.allclose(st[1][:, :3], xyz[1])


@pytest.fixture(scope="module")
def hdm41(data_dir):
    return load_clip(data_dir / HDM)


def test_take_heading_holds_where_the_frames_own_pairs_do_not(hdm41):
    """Half of 41 markers hidden: the facing from the pairs each frame shows is tens of degrees
    off in some frames; from the take's filled label trajectories it stays within a few."""
    clip = hdm41.slice(2960, 3560)
    gap = _gapped(hdm41, 0.5, gap_s=0.25).slice(2960, 3560)
    pairs = np.array([(i, clip.names.index("R" + n[1:])) for i, n in enumerate(clip.names)
                      if n.startswith("L") and "R" + n[1:] in clip.names])

    class Model:                      # what take_heading reads of a model
        n_labels = clip.n_points
        heading_pairs = pairs
    true = lateral_yaw(clip.positions, pairs)
    own = lateral_yaw(gap.positions, pairs)
    seen = np.isfinite(gap.positions[..., 0])
    xyz = [gap.positions[f][seen[f]] for f in range(gap.n_frames)]
    labels = [np.flatnonzero(seen[f]) for f in range(gap.n_frames)]
    take = take_heading(Model, xyz, labels)
    assert np.nanmax(_angle(own, true)) > 30.0
    assert np.percentile(_angle(take, true), 99) < 10.0


def test_second_pass_lifts_a_half_hidden_take(gappy_upper):
    """12 upper-body HDM05 markers, half hidden (real-looking gaps), model of another part of
    the take: live 51 %, votes over +-1 s 62 %, then the second pass 71 % (measured); since a
    heavily hidden stream's level is set again with velocities (``tracked.UNTAUGHT_WEIGHT``)
    live 73 %, votes 77 %, the pass 81 %."""
    model, clip = gappy_upper                      # the model of frames 1200-2400 of the gapped take
    part = clip.slice(2760, 3120)
    second = label_clip_run(model, part, LabelerSettings(), keep_records=True, take_votes_s=1.0, take_pass=True)
    votes = second.voted.metrics()                 # the take-voted labels before the pass
    assert second.settings["take_pass"] and second.settings["take_votes_s"] == 1.0
    assert second.metrics.accuracy > votes.accuracy + 0.03 and votes.accuracy > second.causal.metrics().accuracy + 0.03
    # the records carry the labels of the pass (what a labelled capture is written from)
    right = sum(int((r.labels == r.truth)[r.truth >= 0].sum()) for r in second.records)
    assert right / sum(int((r.truth >= 0).sum()) for r in second.records) == pytest.approx(second.metrics.accuracy)


def test_held_labels_count_each_tracks_frames_under_its_label():
    tracks = [np.array([3, 4, -1]), np.array([3, 4]), np.array([4, 3])]
    labels = [np.array([0, 1, 2]), np.array([0, 1]), np.array([0, 1])]
    held = held_labels(tracks, labels, hold_frames=2)
    # track 3 carries label 0 twice and label 1 once; track 4 label 1 twice, label 0 once
    assert [h.tolist() for h in held] == [[True, True, False], [True, True], [False, False]]


def test_clutter_points_count_each_tracks_frames_left_unlabelled():
    tracks = [np.array([3, 4, -1]), np.array([3, 4]), np.array([4, 3])]
    labels = [np.array([0, -1, -1]), np.array([-1, -1]), np.array([-1, 1])]
    clutter = clutter_points(tracks, labels, hold_frames=2)
    # track 4 is unlabelled in all three frames, track 3 in one; an untracked point never counts
    assert [c.tolist() for c in clutter] == [[False, True, False], [False, True], [True, False]]


def test_the_second_pass_gives_back_a_label_it_put_on_a_tracks_clutter():
    """take_pass.kept_clutter: a label a search moved onto a point whose track the start leaves
    unlabelled for hold_s of the take (a real capture's ghost) goes back to the start's point
    where keeping it gains less than hold_nats -- not where the point is not such clutter, and
    not where the start's point fits far worse (a label the frame's evidence moves)."""
    clip = synthesize(duration=0.5, seed=3, heading=0.5, noise_mm=2)
    model, _ = train_model([synthesize(duration=3.0, seed=s, heading=h, noise_mm=2) for s, h in [(0, 0.0), (1, 1.0)]],
                           TrainConfig(mixture="fixed", k_fixed=2, structure="given"))
    background = LabelerSettings().background
    hold = LabelerSettings().hold_nats
    head = model.labels.index("head")
    pos = clip.positions[30]
    for ghost_offset, true_offset, given_back in ((0.01, 0.0, True), (0.0, 0.6, False)):
        xyz = np.vstack([pos, pos[head] + [ghost_offset, 0.0, 0.0]])
        xyz[head] += [true_offset, 0.0, 0.0]
        states = np.hstack([xyz, np.full_like(xyz, np.nan)])
        problem = FrameProblem(model, states, background)
        start = np.arange(model.n_labels)                        # each label on its point; the ghost last
        ind = start.copy()
        ind[head] = problem.n - 1                                # a search gave the head's label to the ghost
        problem.anchor_heading(start)
        fit = float(problem.fitness(ind[None])[0])
        ghost = np.zeros(problem.n, dtype=bool)
        ghost[-1] = True
        out = kept_clutter(problem, start, ind, fit, ghost, hold)
        assert bool(out[head] == head) == given_back
        assert np.array_equal(kept_clutter(problem, start, ind, fit, np.zeros(problem.n, dtype=bool), hold), ind)


def test_the_second_pass_keeps_a_label_its_track_holds(data_dir):
    """Subject 7's walk alone (``dtm-train``'s default structure, which hangs the legs' triangles
    on the wrists: a walk swings the arms against the legs), calibrated to subject 55 on the
    whirl's first 600 frames: the model prefers the left wrist's point as clutter by a few nats a
    frame, which the live pass's hold prior outweighs (``hold_nats``) once a track holds the label.
    The second pass searches every frame again without the tracks, and left the wrist on no point
    in every frame of 600-1000 (92.9 %, the left wrist 0 %; measured); with the same hold it keeps
    it where the live pass's track held it.

    Scored on the frames whose live (voted) labeling has the wrist on its point: whether the
    velocity search of the window's second frame takes the wrist or leaves it out (8 nats apart
    on one machine's training, the other way on another's) decides only how many such frames
    there are (all 400, or 336 when the tracks pick it up later)."""
    bvh = data_dir / "cmu_skeletal" / "bvh_from_fbx"
    walk = to_point_set(load_clip(bvh / "cmu_07_01_walk_s07.bvh"))
    whirl = to_point_set(load_clip(bvh / "cmu_55_01_dance-whirl_s55.bvh"))
    model, _ = train_model([walk], TrainConfig())
    model, _ = calibrate_from_clip(model, whirl.slice(0, 600), labels="capture")
    part = whirl.slice(600, 1000)
    voted = label_clip_run(model, part, LabelerSettings(), keep_records=True, take_votes_s=1.0)
    wrist = model.labels.index("lwrist")

    def held(records):                   # per frame: the left wrist's label on its true point
        return np.array([bool(((r.truth == wrist) & (r.labels == wrist)).any()) for r in records])

    live = held(voted.records)
    assert live.mean() > 0.6
    after = {}
    for hold in (0.0, LabelerSettings().hold_nats):
        records = copy.deepcopy(voted.records)
        acc = passed(records, model.labels, part.rate, 1.0, model, LabelerSettings(hold_nats=hold)).metrics()
        after[hold] = (held(records)[live].mean(), acc.accuracy)
    assert after[0.0][0] < 0.5                                   # the searches alone drop it
    assert after[LabelerSettings().hold_nats][0] > 0.99          # the hold keeps what the track held
    assert after[LabelerSettings().hold_nats][1] > 0.99
