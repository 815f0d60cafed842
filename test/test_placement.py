"""Subject calibration adapts the motion mixtures' position means to where this session put
the markers (training/placement.py): a real HDM05 take whose right shank marker is moved 40 %
of the way down to the ankle (another session's placement) is labelled in full after a
calibration on its own labelled first 2 s, where the body-only calibration leaves that marker
out in every frame; and a self-calibration takes a label it never confirmed from the points it
left out (``completed_labels``)."""
import numpy as np
import pytest

from dtm_labeler.evaluation.pipeline import label_clip_run
from dtm_labeler.labeling.stream import LabelerSettings
from dtm_labeler.model.body import SEGMENT
from dtm_labeler.model.features import FEATURE_DIM
from dtm_labeler.training.calibrate import CalibrationSettings, calibrate, completed_labels
from dtm_labeler.training.placement import POSITION_DIMS, adapted_mixtures
from dtm_labeler.training.train import TrainConfig, train_model


@pytest.fixture(scope="module")
def model(hdm05_take):
    m, _ = train_model([hdm05_take.slice(1200, 1900)], TrainConfig(seed=0, k_max=2, structure="greedy"))
    return m


def moved(clip, marker: str, towards: str, fraction: float):
    """``clip`` with ``marker`` placed ``fraction`` of the way to ``towards`` (same segment)."""
    P = clip.positions.copy()
    i, j = clip.names.index(marker), clip.names.index(towards)
    P[:, i] += fraction * (P[:, j] - P[:, i])
    return clip._replace(positions=P)


def test_a_moved_marker_is_labelled_after_calibration(model, hdm05_take):
    """Measured: body only 96.5 %, the shank marker unlabelled in 240 of 240 frames; with the
    placement 100 %."""
    take = moved(hdm05_take, "RSHN", "RANK", 0.4).slice(2400, 2880)
    window, rest = take.slice(0, 240), take.slice(240, None)
    acc = {}
    for relevance in (0.0, 20.0):
        cal = calibrate(model, window, CalibrationSettings(placement_relevance=relevance), check_labels=False)
        d = label_clip_run(cal, rest, LabelerSettings(seed=0), seed=0).accumulator.metrics().as_dict()
        acc[relevance] = (d["accuracy"], d["per_label"]["RSHN"])
        assert ("placement" in cal.provenance["calibration"]) == (relevance > 0)
    assert acc[0.0][1] < 0.5                       # the body alone: the marker is left out
    assert acc[20.0][1] > 0.95 and acc[20.0][0] > 0.98 and acc[20.0][0] > acc[0.0][0]


def test_only_position_means_move_and_only_where_frames_reach(model, hdm05_take):
    """Weights, covariances and the velocity means are kept; a triangle no frame shows whole is
    left as it is; a component's move is the MAP step n/(n + r) of the way to its frames' mean."""
    P = hdm05_take.slice(2400, 2640).positions.copy()
    tri0 = model.triangles[0]
    P[:, tri0[0]] = np.nan                         # the first triangle never seen whole
    mixtures, summary = adapted_mixtures(model, P, relevance=20.0)
    assert summary["triangles_adapted"] == summary["triangles_total"] - sum(
        int(tri0[0] in t) for t in model.triangles)
    assert mixtures[0] is model.mixtures[0]
    vel = np.setdiff1d(np.arange(FEATURE_DIM), POSITION_DIMS)
    moved_any = False
    for new, old in zip(mixtures, model.mixtures):
        assert np.array_equal(new.weights, old.weights) and np.array_equal(new.covariances, old.covariances)
        assert np.array_equal(new.means[:, vel], old.means[:, vel])
        moved_any |= not np.array_equal(new.means, old.means)
    assert moved_any
    # a larger relevance moves less; relevance 0 is no adaptation at all
    far, _ = adapted_mixtures(model, P, relevance=2000.0)
    t = next(k for k, m in enumerate(mixtures) if m is not model.mixtures[k] and k > 0)
    step = np.abs(mixtures[t].means - model.mixtures[t].means).max()
    assert 0 < np.abs(far[t].means - model.mixtures[t].means).max() < step
    none, s0 = adapted_mixtures(model, P, relevance=0.0)
    assert all(a is b for a, b in zip(none, model.mixtures)) and s0["triangles_adapted"] == 0


def test_a_label_never_confirmed_is_taken_from_the_points_left_out(model, hdm05_take):
    """``completed_labels``: RSHN never confirmed, every other label confirmed; the one point per
    frame left out stays rigid to RSHN's segment partners and is taken, exactly; a second such
    point on the same segment makes it a guess, and nothing is taken; a label confirmed often
    enough is left as it is."""
    clip = hdm05_take.select(model.labels).slice(2400, 2640)
    P = clip.positions
    m = model.labels.index("RSHN")
    assert np.isfinite(P).all()
    confirmed = P.copy()
    confirmed[:, m] = np.nan
    rng = np.random.default_rng(0)
    clouds = [x[rng.permutation(len(x))] for x in P]
    filled, done = completed_labels(model, confirmed, clouds)
    assert done == ["RSHN"] and np.array_equal(filled, P)
    # a second point rigid to the same segment (a third of the way to a partner): no choice made
    rows = (model.body.kind == SEGMENT) & (model.body.pairs == m).any(1)
    partner = int(model.body.pairs[rows][0].sum() - m)
    decoy = P[:, m] + (P[:, partner] - P[:, m]) / 3
    twice, done = completed_labels(model, confirmed, [np.vstack([x, d]) for x, d in zip(clouds, decoy)])
    assert done == [] and np.isnan(twice[:, m]).all()
    # confirmed in more than the threshold's share of frames: not looked for
    some = confirmed.copy()
    some[::3, m] = P[::3, m]
    kept, done = completed_labels(model, some, clouds)
    assert done == [] and np.array_equal(np.isnan(kept[:, m]), np.isnan(some[:, m]))
