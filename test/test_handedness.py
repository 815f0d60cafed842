"""The marker clusters' handedness (model/body.py ``Handedness``): a labeling that shows a cluster
mirrored pays a fixed factor per quadruple, a missing point drops it, only calibrated bodies
apply it (measured again on the person's frames), and model files keep it (format 3)."""

import numpy as np
import pytest

from dtm_labeler.model.body import HANDEDNESS_NATS, BodyModel, Handedness
from dtm_labeler.labeling.rigid_tracks import body_pairs
from dtm_labeler.labeling.take_pass import person_handedness
from dtm_labeler.model.features import point_states
from dtm_labeler.model.io import FORMAT_VERSION, load_model, save_model
from dtm_labeler.motion.load import load_clip
from dtm_labeler.search.problem import Background, FrameProblem
from dtm_labeler.evaluation.corruption import realistic_gaps
from dtm_labeler.training.body_fit import (handedness_quads, joined_clusters, person_rigid_pairs, quad_signs,
                                          rigid_quads, segment_clusters)
from dtm_labeler.training.calibrate import calibrate_on_takes, calibrated_body, labelled_positions
from dtm_labeler.training.train import TrainConfig, train_model
from model_files import as_older_format

HDM = "markers_c3d/hdm05_bd_05-01_01_120.c3d"
ARM = ["LFHD", "RFHD", "C7", "CLAV", "STRN", "LSHO", "RSHO", "LELB", "LFRM", "LWRA", "LWRB", "LFIN",
       "LFWT", "RFWT"]
TETRA = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1], [0.3, 0.3, 0.3]])


def _body(quads, signs, n=5):
    return BodyModel(n_labels=n, pairs=np.zeros((0, 2)), kind=np.zeros(0), lo=np.zeros(0), hi=np.zeros(0),
                     within_sd=np.zeros(0), between_sd=np.zeros(0), quads=quads, quad_sign=signs)


def test_factor_per_mirrored_quadruple_and_missing_points():
    hand = Handedness(_body([[0, 1, 2, 3]], [1.0]))
    assert np.linalg.det(TETRA[1:4] - TETRA[0]) > 0                       # right-handed as stored
    swapped = TETRA[[0, 2, 1, 3, 4]]                                      # labels 1 and 2 exchanged
    hidden = TETRA.copy()
    hidden[3] = np.nan
    got = hand.labelled(np.stack([TETRA, swapped, hidden, TETRA[[0, 1, 2, 4, 3]]]))
    # the last frame: 3 takes point 4, on the same side of (0, 1, 2): the same handedness
    assert got.tolist() == [0.0, -HANDEDNESS_NATS, 0.0, 0.0]
    # assignments over a frame's points (row n = "missing", NaN): the same factors
    xyz = np.vstack([TETRA, np.full((1, 3), np.nan)])
    pop = np.array([[0, 1, 2, 3, 4], [0, 2, 1, 3, 4], [0, 1, 2, 5, 4]])
    assert hand(pop, xyz).tolist() == [0.0, -HANDEDNESS_NATS, 0.0]
    with pytest.raises(ValueError, match="distinct"):
        _body([[0, 1, 1, 3]], [1.0])
    with pytest.raises(ValueError, match="quad_sign"):
        _body([[0, 1, 2, 3]], [0.5])


def test_quad_signs_keep_only_what_holds():
    rng = np.random.default_rng(0)
    F = 200
    P = np.repeat(TETRA[None], F, 0) + rng.normal(0, 0.002, (F, 5, 3))
    P[:, 4] = P[:, 3] + rng.normal(0, 0.05, (F, 3))       # point 4 wanders around point 3
    P[:, 4, 2] = np.where(np.arange(F) % 2 == 0, 0.05, -0.05)     # ... to either side of the plane (0, 1, 2)
    quads, signs = quad_signs(P, np.array([[0, 1, 2, 3], [0, 1, 2, 4]]))
    assert quads.tolist() == [[0, 1, 2, 3]] and signs.tolist() == [1.0]
    P[:30, 3] = np.nan                                    # seen in fewer frames than asked: dropped
    assert quad_signs(P, np.array([[0, 1, 2, 3]]), min_frames=171)[0].shape == (0, 4)


@pytest.fixture(scope="module")
def hdm(data_dir):
    return load_clip(data_dir / HDM).select(ARM)


@pytest.fixture(scope="module")
def models(hdm):
    train = hdm.slice(1200, 1900)
    generic, _ = train_model([train], TrainConfig(seed=0, k_max=2, structure="greedy"))
    return generic, calibrate_on_takes(generic, [train])


def test_real_wrist_cluster_learnt_and_applied_once_calibrated(models, hdm, tmp_path):
    generic, calibrated = models
    names = list(generic.labels)
    bar = {names.index("LWRA"), names.index("LWRB")}
    quads = generic.body.quads
    assert len(quads) >= 5 and sum(bar <= set(q) for q in quads.tolist()) >= 1      # both wrist-bar ends
    again = handedness_quads([labelled_positions(generic, hdm.slice(1200, 1900))])
    assert {tuple(q) for q in again[0].tolist()} == {tuple(q) for q in quads.tolist()}
    # a generic body keeps them but does not apply them; the calibrated body does
    assert generic.body_handedness is None and calibrated.body_handedness is not None
    assert calibrated.body.calibration["handedness_quads"] == len(calibrated.body.quads) > 0

    # the quadruples with both wrist-bar ends are left to the bar's order (model/body.py BarOrder)
    # unless all four markers are of one segment cluster (here the elbow and forearm markers with the bar)
    assert calibrated.body.orders.shape[0] >= 1
    cluster = segment_clusters(len(names), calibrated.body.segments)
    both = [q for q in calibrated.body.quads.tolist() if bar <= set(q)]
    assert both and all(cluster[q[0]] >= 0 and (cluster[q] == cluster[q[0]]).all() for q in both)
    crossing = [q for q in generic.body.quads.tolist() if bar <= set(q) and len(set(cluster[q])) > 1]
    assert calibrated.body.calibration["handedness_left_to_orders"] >= len(crossing)
    assert not any(q in calibrated.body.quads.tolist() for q in crossing)

    # on a real frame the training never saw, whose true labels show every cluster as trained:
    # two labels of a quadruple exchanged pay exactly the factor of every quadruple the exchange mirrors
    hand = Handedness(calibrated.body)
    P = labelled_positions(calibrated, hdm.slice(2400, 2700))
    frame = int(np.flatnonzero(hand.labelled(P[1:]) == 0)[0]) + 1
    X = P[frame - 1:frame + 1]
    states = point_states(X, hdm.rate)[1]
    problem = FrameProblem(calibrated, states, Background())
    truth = np.arange(len(names))
    a, b = calibrated.body.quads[0][:2]
    swap = truth.copy()
    swap[[a, b]] = swap[[b, a]]
    pop = np.stack([truth, swap])
    with_hand = problem.fitness(pop)
    flipped = -hand.labelled(X[1][pop]) / HANDEDNESS_NATS
    calibrated.body_handedness, saved = None, calibrated.body_handedness
    try:
        without = FrameProblem(calibrated, states, Background()).fitness(pop)
    finally:
        calibrated.body_handedness = saved
    assert flipped[0] == 0 and flipped[1] >= 1
    assert np.allclose(with_hand - without, -HANDEDNESS_NATS * flipped)

    # format 3 keeps them; a format-2 file (no handedness arrays) loads as a body without them
    path = save_model(calibrated, tmp_path / "m.npz")
    back = load_model(path)
    assert FORMAT_VERSION >= 3
    assert np.array_equal(back.body.quads, calibrated.body.quads)
    assert np.array_equal(back.body.quad_sign, calibrated.body.quad_sign)
    assert np.array_equal(FrameProblem(back, states, Background()).fitness(pop), with_hand)
    v2 = as_older_format(path, 2, lambda k: k in ("body_quads", "body_quad_sign"))
    assert v2.provenance["format_version_read"] == 2 and v2.body.quads.shape == (0, 4)
    assert v2.body_handedness is None
    assert np.allclose(FrameProblem(v2, states, Background()).fitness(pop), without)


def test_self_labelled_frames_do_not_flip_a_trained_quadruple(models, hdm):
    """A self-calibration's frames carry the model's own labels: a quadruple they show mirrored
    (here the wrist bar's ends exchanged in every frame) is dropped, not learnt the other way
    round -- it would hold the exchange from then on. Labels from a capture are trusted and
    keep the sign they show."""
    generic, _ = models
    names = list(generic.labels)
    a, b = names.index("LWRA"), names.index("LWRB")
    P = labelled_positions(generic, hdm.slice(1200, 1900))
    P[:, [a, b]] = P[:, [b, a]]
    trained = {tuple(q): s for q, s in zip(generic.body.quads.tolist(), generic.body.quad_sign)}
    own, summary = calibrated_body(generic.body, P, check_labels=True)
    assert summary["handedness_flips_dropped"] >= 1                  # the bar's own quadruple
    assert all(trained[tuple(q)] == s for q, s in zip(own.quads.tolist(), own.quad_sign))
    assert len(own.quads) == summary["handedness_quads"] > 0          # the rest of the clusters stay
    capture, _ = calibrated_body(generic.body, P, check_labels=False)
    flipped = [tuple(q) for q, s in zip(capture.quads.tolist(), capture.quad_sign) if trained[tuple(q)] != s]
    assert len(flipped) == summary["handedness_flips_dropped"]
    assert all({a, b} & set(q) for q in flipped)


def test_only_rigid_clusters_get_a_handedness(hdm):
    """A quadruple over two limbs (the forearm's markers and the waist's) can show one sign in
    every training frame of a motion that keeps the arm by the side, but it is no cluster: its
    distances spread with the pose, and its sign is the pose's. Only quadruples that hold
    together (:func:`rigid_quads`) are learnt."""
    names = list(hdm.names)
    P = hdm.slice(1200, 1900).positions
    idx = {n: names.index(n) for n in names}
    forearm = [idx[n] for n in ("LELB", "LFRM", "LWRA", "LWRB")]
    across = [idx[n] for n in ("LELB", "LFRM", "LWRA", "LFWT")]
    quads = np.array([sorted(forearm), sorted(across)])
    v = Handedness.volumes(P[:, quads])
    assert (np.sign(v) == np.sign(v[0])).all()                      # one sign in every frame, both
    assert rigid_quads(P, quads).tolist() == [True, False]
    kept, _ = quad_signs(P, quads)
    assert [tuple(q) for q in kept.tolist()] == [tuple(sorted(forearm))]
    learnt = {tuple(q) for q in handedness_quads([P])[0].tolist()}
    assert tuple(sorted(forearm)) in learnt and tuple(sorted(across)) not in learnt
    assert rigid_quads(P, np.array(sorted(learnt))).all()


def test_toe_quadruples_do_not_take_in_the_other_foot(data_dir):
    """Partners are the labels whose distance varies least, not the nearest: in the part of the
    HDM05 take the generalisation cells train on (its first 30 %), the feet stand close together
    and a toe marker's nearest by median distance took in the other foot's toe (LANK-LHEE-LTOE-
    RTOE among others). Such a quadruple's sign is the pose's, not a cluster's: no learnt
    quadruple may hold toe markers of both feet, while each foot's own cluster is learnt."""
    clip = load_clip(data_dir / HDM)
    P = clip.slice(0, int(0.3 * clip.n_frames)).positions
    names = list(clip.names)
    toes = {side: {names.index(side + m) for m in ("TOE", "MT5")} for side in "LR"}
    learnt = {tuple(q) for q in handedness_quads([P])[0].tolist()}
    for side in "LR":
        assert tuple(sorted(names.index(side + m) for m in ("ANK", "HEE", "TOE", "MT5"))) in learnt
    assert not any(set(q) & toes["L"] and set(q) & toes["R"] for q in learnt)


def test_a_model_of_one_person_keeps_all_its_rigid_pairs(models, hdm, tmp_path):
    """Beside the structure's tree segments, a marker model keeps every pair of a segment cluster
    that held rigid over its training frames (BodyModel.rigid_pairs: the take pass's ruler for
    that person); a calibration measures them again on its person; model files keep them
    (format 5) and a format-4 file loads without them."""
    generic, calibrated = models
    names = list(generic.labels)
    body = generic.body
    pairs = [tuple(p) for p in body.rigid_pairs.tolist()]
    bar = tuple(sorted((names.index("LWRA"), names.index("LWRB"))))
    assert bar in pairs and len(pairs) > len(body.segments)
    assert tuple(sorted((names.index("LFHD"), names.index("LWRA")))) not in pairs      # head to wrist: no
    P = labelled_positions(generic, hdm.slice(1200, 1900))
    d = np.linalg.norm(P[:, bar[0]] - P[:, bar[1]], axis=-1)
    assert body.rigid_length[pairs.index(bar)] == pytest.approx(np.nanmedian(d), abs=1e-3)
    assert (body.rigid_spread > 0).all() and (body.rigid_length <= 0.4).all()
    cluster = segment_clusters(len(names), body.segments)            # each pair within one rigid cluster
    assert (cluster[body.rigid_pairs[:, 0]] == cluster[body.rigid_pairs[:, 1]]).all()
    assert (cluster[body.rigid_pairs] >= 0).all()
    # calibrated: the person of the calibration frames measured again (here the same frames)
    assert calibrated.body.calibration["rigid_pairs"] == len(calibrated.body.rigid_pairs) > 0
    again = {tuple(p): x for p, x in zip(calibrated.body.rigid_pairs.tolist(), calibrated.body.rigid_length)}
    assert again[bar] == pytest.approx(body.rigid_length[pairs.index(bar)], abs=1e-3)

    path = save_model(generic, tmp_path / "g.npz")
    back = load_model(path)
    assert FORMAT_VERSION >= 5 and np.array_equal(back.body.rigid_pairs, body.rigid_pairs)
    assert np.allclose(back.body.rigid_length, body.rigid_length) and np.allclose(back.body.rigid_spread,
                                                                                  body.rigid_spread)
    v4 = as_older_format(path, 4, lambda k: k.startswith("body_rigid_"))
    assert v4.provenance["format_version_read"] == 4 and v4.body.rigid_pairs.shape == (0, 2)
    with pytest.raises(ValueError, match="rigid pairs"):
        BodyModel(n_labels=3, pairs=np.zeros((0, 2)), kind=np.zeros(0), lo=np.zeros(0), hi=np.zeros(0),
                  within_sd=np.zeros(0), between_sd=np.zeros(0), rigid_pairs=[[1, 0]], rigid_length=[0.1],
                  rigid_spread=[0.003])


def test_segment_clusters_are_the_segments_connected_components():
    got = segment_clusters(7, np.array([[0, 1], [2, 3], [1, 4], [3, 5]]))
    assert got[0] == got[1] == got[4] >= 0 and got[2] == got[3] == got[5] >= 0 and got[0] != got[2]
    assert got[6] == -1                                                   # on no segment


def test_clusters_join_where_two_short_pairs_between_them_held_rigid():
    cluster = np.array([0, 0, 1, 1, 2, 2, -1, -1])                    # 6, 7: on no segment
    rigid = np.zeros((8, 8), dtype=bool)
    for u, v in ((1, 2), (0, 3), (3, 4), (5, 6), (4, 6), (0, 7)):      # 0-1: two links; 1-2: one; 6: two to 2; 7: one
        rigid[u, v] = rigid[v, u] = True
    got = joined_clusters(cluster, rigid)
    assert got[0] == got[1] == got[2] == got[3] and got[4] == got[5] == got[6] != got[0] and got[7] == -1
    rigid[2, 5] = rigid[5, 2] = True                                    # a second link: the chain joins
    assert len(set(joined_clusters(cluster, rigid)[:7].tolist())) == 1


def test_a_label_joins_a_cluster_only_on_tight_short_links():
    """A marker on no segment, 0.11 m from both ends of a two-marker cluster: at 2 mm of jitter
    its two pairs join it to the cluster (both kept as the person's pairs); at 6.5 mm (rigid by the
    8 mm rule, looser than a join needs) it stays out."""
    rng = np.random.default_rng(3)
    base = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.05, 0.1, 1.0]])

    def pairs(jitter):
        P = np.repeat(base[None], 300, axis=0)
        P[:, 2] += rng.normal(0.0, jitter, size=(300, 3))
        return {tuple(p) for p in person_rigid_pairs([P], np.array([[0, 1]]))["rigid_pairs"].tolist()}
    assert pairs(0.002) == {(0, 1), (0, 2), (1, 2)}
    assert pairs(0.0065) == {(0, 1)}


def test_a_gappy_takes_person_pairs_span_one_foot_the_tree_split(data_dir):
    """The Qualisys walk's first 170 frames at 50 % gaps (``bench_captures``' draw): a gapped
    training's tree left the right foot's markers in three clusters (its segments below); the
    person's rigid pairs still hold the foot's pairs across them -- the lateral malleolus to
    the fifth metatarsal, which tells that marker from the first -- at the length the whole
    take shows, and nothing across the knee."""
    clip = load_clip(data_dir / "markers_c3d/qualisys_walk_55markers.c3d")
    names = ["R_FTC", "R_FME", "R_FAX", "R_WAND2", "R_TAM", "R_FAL", "R_FM1", "R_FCC", "R_FM5"]
    gapped = clip.positions.copy()
    gapped[realistic_gaps(clip.n_frames, clip.n_points, clip.rate, missing=0.5, mean_gap_s=0.1, spread=20.0,
                          seed=2)] = np.nan
    cols = [list(clip.names).index(n) for n in names]
    whole, P = clip.positions[:, cols], gapped[:170, cols]
    ix = {n: i for i, n in enumerate(names)}
    segments = np.array([[ix[a], ix[b]] for a, b in (("R_FTC", "R_FME"), ("R_FAX", "R_TAM"), ("R_WAND2", "R_TAM"),
                                                       ("R_FAL", "R_FM1"), ("R_FCC", "R_FM5"))])
    cluster = segment_clusters(len(names), segments)
    assert len({cluster[ix[n]] for n in ("R_TAM", "R_FAL", "R_FCC")}) == 3
    out = person_rigid_pairs([P], segments)
    got = {(names[u], names[v]): length for (u, v), length in zip(out["rigid_pairs"].tolist(), out["rigid_length"])}
    seen = np.isfinite(P[:, [ix["R_FAL"], ix["R_FM5"]], 0]).all(1).sum()
    assert seen < 20                                                    # fewer frames than a take's pairs need
    true = np.nanmedian(np.linalg.norm(whole[:, ix["R_FAL"]] - whole[:, ix["R_FM5"]], axis=-1))
    assert got[("R_FAL", "R_FM5")] == pytest.approx(true, abs=0.003)
    assert ("R_TAM", "R_FCC") in got and ("R_FAL", "R_FCC") in got
    thigh = {"R_FTC", "R_FME"}
    assert not [p for p in got if len(thigh & set(p)) == 1]             # the thigh's cluster joined nothing
    alone = person_rigid_pairs([P], segments[:-1])                      # R_FCC, R_FM5 on no segment: they join too
    assert [ix["R_FAL"], ix["R_FM5"]] in alone["rigid_pairs"].tolist()


def test_the_take_pass_applies_a_generic_bodys_handedness_only_to_its_person(models, hdm):
    """The take pass searches with the clusters' handedness when the model's body is one person's
    and the take shows that person (take_pass.person_handedness); another person's proportions,
    or no one-person body, leave the model as it is. (Frames of the training window: a window
    whose poses break the person's pairs -- this small model's elbow-to-hand pairs held over its
    700 training frames and not in 2400-2700 -- is judged another person, and nothing changes.)"""
    generic, calibrated = models
    names = list(generic.labels)
    P = labelled_positions(generic, hdm.slice(1400, 1700))
    xyz = [p[np.isfinite(p).all(1)] for p in P]
    labels = [np.flatnonzero(np.isfinite(p).all(1)) for p in P]
    prior = body_pairs(generic.body)
    same = person_handedness(generic, xyz, labels, prior)
    assert same is not generic and same.body_handedness is not None and generic.body_handedness is None
    assert same.labels == generic.labels and same.body is generic.body
    other = person_handedness(generic, [x * 1.15 for x in xyz], labels, prior)      # 15 % larger person
    assert other is generic
    assert person_handedness(generic, xyz, labels, None) is generic
    late = labelled_positions(generic, hdm.slice(2400, 2700))
    assert person_handedness(generic, [p[np.isfinite(p).all(1)] for p in late],
                             [np.flatnonzero(np.isfinite(p).all(1)) for p in late], prior) is generic
    assert person_handedness(calibrated, xyz, labels, body_pairs(calibrated.body)) is calibrated   # applied already
    # the copy scores a mirrored wrist cluster lower, the model it came from does not
    a, b = names.index("LWRA"), names.index("LWRB")
    X = P[:2]
    states = point_states(X, hdm.rate)[1]
    truth = np.arange(len(names))
    swap = truth.copy()
    swap[[a, b]] = swap[[b, a]]
    pop = np.stack([truth, swap])
    gain = FrameProblem(same, states, Background()).fitness(pop) - FrameProblem(generic, states, Background()).fitness(pop)
    assert gain[0] == 0.0 and gain[1] < 0
