"""The trunk's twist limit (model/body.py ``TrunkTwist``): a labeling that exchanges the hips under
shoulders that are not exchanged pays a dead-zone quadratic in the cosine of the two axes, any
twist a spine makes costs nothing, a missing shoulder falls back to the midline point (so leaving
a shoulder out does not escape it), the axes come from the point set's names, a generic body
applies it, and model files keep it (format 4; format-3 files load without it)."""

import numpy as np
import pytest

from dtm_labeler.model.body import TWIST_COS_MIN, TWIST_COS_SD, BodyModel, TrunkTwist
from dtm_labeler.model.io import FORMAT_VERSION, load_model, save_model
from dtm_labeler.motion.pointsets import BODY14
from dtm_labeler.motion.synthetic import synthesize
from dtm_labeler.search.problem import Background, FrameProblem
from dtm_labeler.training.body_fit import trunk_twists
from dtm_labeler.training.train import TrainConfig, canonical_states, train_model
from model_files import as_older_format

I = {n: i for i, n in enumerate(BODY14)}
CMU41 = ("LFHD RFHD LBHD RBHD C7 T10 CLAV STRN RBAC LSHO LUPA LELB LFRM LWRA LWRB LFIN RSHO RUPA RELB RFRM "
         "RWRA RWRB RFIN LFWT RFWT LBWT RBWT LTHI LKNE LSHN LANK LHEE LTOE LMT5 RTHI RKNE RSHN RANK RHEE "
         "RTOE RMT5").split()


def _trunk(twist_deg: float) -> np.ndarray:
    """Points (left shoulder, neck, right shoulder, left hip, right hip): shoulders along +x,
    hips turned by ``twist_deg`` about the vertical."""
    a = np.radians(twist_deg)
    hip = 0.1 * np.array([np.cos(a), np.sin(a), 0.0])
    return np.array([[-0.2, 0, 1.4], [0, 0, 1.45], [0.2, 0, 1.4], [*-hip[:2], 0.9], [*hip[:2], 0.9]])


def test_factor_is_zero_for_any_spine_twist_and_costs_an_exchange():
    body = BodyModel(5, np.zeros((0, 2)), [], [], [], [], [], twists=[[0, 1, 2, 3, 4]])
    twist = TrunkTwist(body)
    frames = np.stack([_trunk(0), _trunk(60), _trunk(89), _trunk(120), _trunk(180)])
    got = twist.labelled(frames)
    assert got[:3].tolist() == [0.0, 0.0, 0.0]                           # up to 90 degrees: free
    assert got[3] == pytest.approx(-0.5 * ((TWIST_COS_MIN - np.cos(np.radians(120))) / TWIST_COS_SD) ** 2)
    assert got[4] == pytest.approx(-0.5 * ((TWIST_COS_MIN + 1.0) / TWIST_COS_SD) ** 2) and got[4] < -10
    # assignments over a frame's points (row n = "missing", NaN): hips exchanged, a shoulder left
    # out (the neck stands in for it), both shoulders left out (no axis: the factor drops)
    xyz = np.vstack([_trunk(10), np.full((1, 3), np.nan)])
    pop = np.array([[0, 1, 2, 3, 4], [0, 1, 2, 4, 3], [5, 1, 2, 4, 3], [0, 1, 5, 4, 3], [5, 1, 5, 4, 3],
                    [5, 5, 5, 4, 3]])
    f = twist(pop, xyz)
    assert f[0] == 0.0 and (f[1:4] < -10).all()
    assert f[4] == 0.0 and f[5] == 0.0
    # the compiled factor is the dead-zone quadratic of the cosines' reading, also without a mid point
    rng = np.random.default_rng(0)
    pts = np.vstack([rng.normal(size=(6, 3)), np.full((1, 3), np.nan)])
    pop = rng.integers(0, 7, size=(400, 5))
    for rows in ([[0, 1, 2, 3, 4]], [[0, -1, 2, 3, 4]], [[0, 1, 2, 3, 4], [2, -1, 0, 4, 1]]):
        tw = TrunkTwist(BodyModel(5, np.zeros((0, 2)), [], [], [], [], [], twists=rows))
        c = tw.cosines(pts, pop)
        x = np.maximum(TWIST_COS_MIN - c, 0.0) / TWIST_COS_SD
        assert np.allclose(tw(pop, pts), -0.5 * np.where(np.isfinite(x), x * x, 0.0).sum(1))
    with pytest.raises(ValueError, match="twists"):
        BodyModel(5, np.zeros((0, 2)), [], [], [], [], [], twists=[[0, -1, 2, 3, 7]])


def test_axes_from_the_names_and_kept_where_the_training_holds_them():
    assert trunk_twists(BODY14).tolist() == [[I["lshoulder"], I["neck"], I["rshoulder"], I["lhip"], I["rhip"]]]
    ix = {n: i for i, n in enumerate(CMU41)}
    assert trunk_twists(CMU41).tolist() == [[ix["LSHO"], ix["C7"], ix["RSHO"], ix["LFWT"], ix["RFWT"]],
                                            [ix["LSHO"], ix["C7"], ix["RSHO"], ix["LBWT"], ix["RBWT"]]]
    assert trunk_twists(["lshoulder", "rshoulder", "lknee"]).shape == (0, 5)     # no hips: none
    walker = synthesize(duration=2.0, seed=1).positions
    assert trunk_twists(BODY14, [walker]).shape == (1, 5)
    swapped = walker.copy()
    swapped[:, [I["lhip"], I["rhip"]]] = walker[:, [I["rhip"], I["lhip"]]]     # "left" named the other way
    assert trunk_twists(BODY14, [swapped]).shape == (0, 5)


@pytest.fixture(scope="module")
def trained():
    walker = synthesize(duration=3.0, seed=0, heading=0.3)
    model, _ = train_model([walker], TrainConfig(mixture="fixed", k_fixed=2, structure="given", seed=0,
                                                 broad_component=True))
    return model, walker


def test_generic_body_applies_it_in_the_frame_fitness(trained):
    model, walker = trained
    assert not model.body.calibration and model.body_twist is not None      # a generic body: applied
    states = canonical_states(walker, model.heading_pairs)[40]
    problem = FrameProblem(model, states, Background())
    truth = np.arange(14)
    legs = truth.copy()
    for a, b in (("lhip", "rhip"), ("lknee", "rknee"), ("lankle", "rankle")):
        legs[[I[a], I[b]]] = legs[[I[b], I[a]]]                          # the lower body exchanged
    pop = np.stack([truth, legs])
    with_twist = problem.fitness(pop)
    model.body_twist, saved = None, model.body_twist
    try:
        without = FrameProblem(model, states, Background()).fitness(pop)
    finally:
        model.body_twist = saved
    assert with_twist[0] == without[0]                                   # the truth pays nothing
    assert with_twist[1] < without[1] - 10                               # the exchange pays > 10 nats
    # the labelled-frame log-likelihood has the same factor
    frames = canonical_states(walker, model.heading_pairs)[40:41]
    ex = frames[:, legs]
    assert model.frame_log_likelihood(ex)[0] - model.frame_log_likelihood(frames)[0] < -10


def test_model_files_keep_it_and_format_3_files_load_without(trained, tmp_path):
    model, walker = trained
    path = save_model(model, tmp_path / "m.npz")
    back = load_model(path)
    assert FORMAT_VERSION >= 4 and np.array_equal(back.body.twists, model.body.twists)
    v3 = as_older_format(path, 3, lambda k: k == "body_twists")
    assert v3.provenance["format_version_read"] == 3 and v3.body.twists.shape == (0, 5) and v3.body_twist is None
