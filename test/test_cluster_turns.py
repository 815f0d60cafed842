"""A rigid cluster's labels turned as a block (search/label_search.py ``cluster_turns``,
``TrackedLabeler._cluster_turns``, setting ``cluster_turns``): every other arrangement of each
small cluster's labels over its points, and on real frames of CMU 85's floor moves a head read
turned by 90 degrees -- four labels each one along, which no single swap undoes -- put right."""
import numpy as np
import pytest

from dtm_labeler.evaluation.pipeline import model_clip
from dtm_labeler.labeling.config import LabelerSettings
from dtm_labeler.labeling.stream import StreamLabeler
from dtm_labeler.model.body import segment_clusters
from dtm_labeler.motion.synthetic import synthesize
from dtm_labeler.search.label_search import cluster_turns
from dtm_labeler.training.train import TrainConfig, train_model

HEAD = ["LFHD", "LBHD", "RBHD", "RFHD"]           # each one along: the head turned by 90 degrees


def test_every_other_arrangement_of_each_fully_seen_cluster():
    ind = np.array([4, 0, 2, 7, 1, 3, 9])           # 7 labels over points 0..8, 9 = missing
    n = 9
    got = cluster_turns(ind, n, (np.array([0, 1, 2]), np.array([3, 4]), np.array([5, 6])))
    assert got.shape == (5 + 1, 7)                   # 3! - 1 and 2! - 1; the last cluster has a missing label
    assert len({tuple(r) for r in got}) == 6 and not (got == ind).all(1).any()
    for r in got:
        changed = np.flatnonzero(r != ind)
        assert set(changed) <= {0, 1, 2} or set(changed) <= {3, 4}
        assert sorted(r[changed]) == sorted(ind[changed])           # the same points, other labels
    assert cluster_turns(ind, n, ()).shape == (0, 7)


@pytest.fixture(scope="module")
def floor(case_cell):
    """``dtm-eval``'s floor-moves cell: a generic body of CMU 85's jump + twist and HDM05's
    standing take, and the breakdance on the floor (its first 130 frames)."""
    model, test = case_cell("m_floor")
    return model, model_clip(model, test.slice(0, 130))


def _head_recovered(model, clip, turns: bool) -> list[bool]:
    """Frames 21, 31, ..., 121 of a stream labelled with true point ids: the fast path's climb
    (a region-check frame) from the frame's truth with the head turned by one marker."""
    L = list(model.labels)
    head = np.array([L.index(name) for name in HEAD])
    truth = np.arange(len(L))
    start = truth.copy()
    start[head] = truth[np.roll(head, 1)]
    out = []
    with StreamLabeler(model, LabelerSettings(recovery="inline", cluster_turns=turns)) as lab:
        for f in range(clip.n_frames):
            lab.process(clip.positions[f], f / clip.rate, ids=truth)
            if f >= 21 and f % 10 == 1:
                problems, _, found = lab.last_frame
                lab._since_search = 0
                ind, _, _ = lab._hill_climb(problems[found.best_model], start)
                out.append(bool(np.array_equal(ind[head], truth[head])))
    return out


def test_a_head_turned_by_one_marker_is_turned_back(floor):
    model, clip = floor
    assert [[model.labels[i] for i in c] for c in model.rigid_clusters if model.labels[c[0]] == "LFHD"] == \
        [["LFHD", "RFHD", "LBHD", "RBHD"]]
    on, off = _head_recovered(model, clip, True), _head_recovered(model, clip, False)
    assert sum(on) >= 9 and sum(off) <= 4, (on, off)


def test_joint_centres_have_no_rigid_cluster():
    """The 14 body points' segments are bones joined at joints: a synthetic walker's limbs
    (shoulder-elbow-wrist, hip-knee-ankle) are components of three, and are not turned."""
    model, _ = train_model([synthesize(duration=2.0, seed=0)], TrainConfig(mixture="fixed", k_fixed=1,
                                                                          structure="given", augment_copies=0))
    comp = segment_clusters(model.n_labels, model.body.segments)
    sizes = np.bincount(comp[comp >= 0])
    assert (sizes == 3).any() and model.rigid_clusters == ()
