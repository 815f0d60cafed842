"""Body terms on the DTM's edges, the broad motion component, subject calibration (issue 13).

The claims checked: a labeling that breaks a bone length scores worse than the true labeling
of any unseen pose of the same body (and without the body terms it does not); an edge with a
missing end point contributes nothing, so the marginalisation of eq. 30-31 is unchanged;
calibration on another person's frames sets that person's lengths; the structure prior
favours segment edges; v1 model files still load, as models without body terms.
"""
import json

import numpy as np
import pytest

from dtm_labeler.model.body import REACH, SEGMENT, BodyModel, CrossSegments, EdgeTerms
from dtm_labeler.model.io import FORMAT_VERSION, ModelFileError, load_model, model_from_arrays, save_model
from dtm_labeler.model.mixture import GaussianMixture
from dtm_labeler.model.structure import BODY14_GIVEN, Structure
from dtm_labeler.motion.pointsets import BODY14
from dtm_labeler.motion.synthetic import synthesize
from dtm_labeler.search import structure_search as ss
from dtm_labeler.search.problem import Background, FrameProblem
from dtm_labeler.training.body_fit import (broad_weight, clip_spread, fit_body, reach_limits, reach_off_edges,
                                          midline, mirror_moved, spans_a_point, unmirrored_crossing)
from dtm_labeler.training.calibrate import (CalibrationError, CalibrationSettings, calibrate, calibrated_body,
                                           fit_per_label, self_calibrate, symmetric_segments, wrong_side)
from dtm_labeler.training.train import TrainConfig, canonical_states, train_model
from dtm_labeler.model.features import point_states

I = {n: i for i, n in enumerate(BODY14)}
FAST = dict(mixture="fixed", k_fixed=2, structure="given", seed=0)


@pytest.fixture(scope="module")
def walker():
    return synthesize(duration=3.0, seed=0, heading=0.3)


@pytest.fixture(scope="module")
def models(walker):
    body, _ = train_model([walker], TrainConfig(**FAST, broad_component=True))
    today, _ = train_model([walker], TrainConfig(**FAST, body_terms=False, broad_component=False))
    return body, today


@pytest.fixture(scope="module")
def person(models, walker):
    """The model calibrated on its own training walker: that person's body terms."""
    return calibrate(models[0], walker)


def _rotate_chain(P, root, chain, angle, axis):
    """Rotate the points ``chain`` of every frame about point ``root`` (lengths kept)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    out = P.copy()
    out[:, chain] = (P[:, chain] - P[:, [root]]) @ R.T + P[:, [root]]
    return out


def _fitness(model, positions, rate, assignments):
    """Fitness of label assignments (rows: label -> point index) on every frame (velocities
    from the previous frame of ``positions``)."""
    states = point_states(positions, rate)
    out = []
    for f in range(1, positions.shape[0]):
        problem = FrameProblem(model, states[f], Background())
        out.append(problem.fitness(np.asarray(assignments)))
    return np.array(out)                                   # (F-1, A)


def test_model_has_segments_and_reach_limits(models):
    body = models[0].body
    seg = {(BODY14[u], BODY14[v]) for u, v in body.segments}
    bones = {("lhip", "lknee"), ("lknee", "lankle"), ("lshoulder", "lelbow"), ("lelbow", "lwrist"),
             ("rhip", "rknee"), ("rknee", "rankle"), ("rshoulder", "relbow"), ("relbow", "rwrist")}
    assert bones <= {tuple(sorted(p, key=BODY14.index)) for p in seg}
    assert ("lankle", "rankle") not in seg and ("lwrist", "lhip") not in seg   # these move apart
    # reach limit of a non-segment pair: at least the largest distance seen, at most the chain length
    r = body.pair_index()[I["lwrist"], I["lhip"]]
    assert body.kind[r] == REACH and 0.5 < body.hi[r] < 1.6
    # all 8 limb bones are edges of the given structure, so each carries a segment term
    assert models[0].body_edges is not None and (models[0].body_edges.inv_sd > 0).sum() >= 8


def test_wrong_bone_length_scores_worse_than_any_unseen_pose(walker, models, person):
    """Unseen poses of the right body: the left arm raised sideways and the left leg kicked out
    (rotations about the shoulder / hip: every bone length kept), never in the walk the model
    learned. Wrong labelings of the same frames, each breaking a bone length: legs exchanged
    below the hips (knees and ankles) and the left arm chain shifted by one (wrist label on the
    elbow point, elbow unlabelled). With this person's body terms (the model calibrated on its
    training walker) the true labeling of every unseen pose beats both wrong ones; with the
    motion mixtures alone a wrong labeling wins in some of them (the issue's failure)."""
    body_model, today = person, models[1]
    P = walker.positions[::3]
    unseen = _rotate_chain(P, I["lshoulder"], [I["lelbow"], I["lwrist"]], 1.2, (1, 0, 0))
    unseen = _rotate_chain(unseen, I["lhip"], [I["lknee"], I["lankle"]], 0.7, (1, 0, 0))
    for a, b in ((I["lhip"], I["lknee"]), (I["lelbow"], I["lwrist"]), (I["lknee"], I["lankle"])):
        assert np.allclose(np.linalg.norm(unseen[:, a] - unseen[:, b], axis=1),
                           np.linalg.norm(P[:, a] - P[:, b], axis=1))
    truth = np.arange(14)
    legs = truth.copy()
    for l, r in (("lknee", "rknee"), ("lankle", "rankle")):
        legs[[I[l], I[r]]] = legs[[I[r], I[l]]]
    arm = truth.copy()
    arm[I["lwrist"]], arm[I["lelbow"]] = I["lelbow"], 14               # 14 = missing
    f = _fitness(body_model, unseen, walker.rate / 3, [truth, legs, arm])
    assert (f[:, 0] - f[:, 1:].max(1) > 1).all(), (f[:, 0] - f[:, 1:].max(1)).min()
    f0 = _fitness(today, unseen, walker.rate / 3, [truth, legs, arm])
    assert (f0[:, 1:].max(1) > f0[:, 0]).any()          # the motion mixtures alone prefer a wrong one
    # and an unseen pose is not vetoed: it costs less than breaking one bone by 5 cm in a seen pose
    seen = _fitness(body_model, P, walker.rate / 3, [truth])[:, 0]
    stretched = P.copy()
    stretched[:, I["lwrist"]] += 0.05 * (P[:, I["lwrist"]] - P[:, I["lelbow"]]) / np.linalg.norm(
        P[:, I["lwrist"]] - P[:, I["lelbow"]], axis=1, keepdims=True)
    broken = _fitness(body_model, stretched, walker.rate / 3, [truth])[:, 0]
    arm_only = _fitness(body_model, _rotate_chain(P, I["lshoulder"], [I["lelbow"], I["lwrist"]], 1.2, (1, 0, 0)),
                        walker.rate / 3, [truth])[:, 0]
    assert np.median(seen - arm_only) < np.median(seen - broken)


def test_edge_terms_vanish_with_a_missing_end_point(person, walker):
    """Marginalisation: an edge whose end point is missing has no body term (factor 1), so the
    fitness of a labeling with a missing label is the marginalised motion terms (eq. 30-31)
    plus the body terms of the edges that are fully seen -- checked against an independent
    sum over the structure's edges, and the motion part against the model without a body
    (both without the broad part, which a calibrated body brings in)."""
    model = person.replace(broad=None)
    P = walker.positions[40:42].copy()
    P[1, I["lknee"]] += [0.0, 0.0, 0.12]                  # thigh and shank 12 cm off: body terms non-zero
    states = point_states(P, walker.rate)[1]
    body = model.body
    sd, idx = body.sd, body.pair_index()
    for missing in ("lknee", "lankle", "neck"):
        ind = np.arange(14)
        ind[I[missing]] = 14
        problem = FrameProblem(model, states, Background())
        plain = FrameProblem(model.replace(body=None), states, Background())
        got = float(problem.fitness(ind[None])[0] - plain.fitness(ind[None])[0])
        expect = 0.0
        seen_edges = set()
        for t, tri in enumerate(model.triangles):
            slots = ((0, 1), (0, 2), (1, 2)) if t == 0 else ((0, 1), (0, 2))
            for i, j in slots:
                u, v = int(tri[i]), int(tri[j])
                seen_edges.add(tuple(sorted((u, v))))
                if I[missing] in (u, v) or idx[u, v] < 0:
                    continue
                d = np.linalg.norm(P[1, u] - P[1, v])
                r = idx[u, v]
                x = max(0.0, body.lo[r] - d, d - body.hi[r]) / sd[r]
                expect -= 0.5 * x * x
        assert got == pytest.approx(expect, abs=1e-9)
        assert len(seen_edges) == 2 * 14 - 3                  # every edge of the DTM counted once
    assert expect < -10                                        # the displaced knee costs (when it is seen)


def test_frame_log_likelihood_includes_body_terms(person, walker):
    model = person
    states = canonical_states(walker, model.heading_pairs)[5:9]
    stretched = states.copy()
    stretched[:, I["lwrist"], :3] += np.array([0.0, 0.0, -0.10])
    d = model.frame_log_likelihood(states) - model.frame_log_likelihood(stretched)
    d0 = model.replace(body=None).frame_log_likelihood(states) - model.replace(body=None).frame_log_likelihood(stretched)
    assert (d - d0 > 5).all()          # the body terms add the cost of a 10 cm longer forearm


def test_body_edge_terms_formula():
    body = BodyModel(n_labels=3, pairs=[[0, 1], [0, 2], [1, 2]], kind=[SEGMENT, REACH, SEGMENT],
                     lo=[0.3, 0.0, 0.2], hi=[0.3, 1.0, 0.25], within_sd=[0.01, 0.03, 0.01], between_sd=[0, 0, 0])
    et = EdgeTerms(body, np.array([[0, 1, 2]]))
    d = np.array([[0.32, 1.06, 0.22], [0.3, 0.5, 0.30]])
    got = et(np.zeros(2, dtype=int), d, np.ones((2, 3), bool))
    assert got == pytest.approx([-0.5 * (2.0 ** 2 + 2.0 ** 2), -0.5 * 5.0 ** 2])
    assert et(np.zeros(1, dtype=int), d[:1], np.array([[True, False, False]])) == pytest.approx([-2.0])
    b = et.bounds(np.array([[0, 1, 2]]), 3)
    assert b[0, 1] == pytest.approx(0.3 + 6 * 0.01) and b[1, 0] == b[0, 1]
    with pytest.raises(ValueError):
        BodyModel(n_labels=3, pairs=[[1, 0]], kind=[SEGMENT], lo=[0.1], hi=[0.1], within_sd=[0.01], between_sd=[0])


def test_reach_limits_are_tree_path_lengths():
    parents = np.array([-1, 0, 1, 0])                  # chain 2-1-0-3
    longest = np.zeros((4, 4))
    for c, p, L in ((1, 0, 0.3), (2, 1, 0.25), (3, 0, 0.4)):
        longest[c, p] = longest[p, c] = L
    R = reach_limits(longest, parents)
    assert R[2, 3] == pytest.approx(0.95) and R[1, 3] == pytest.approx(0.7) and R[0, 2] == pytest.approx(0.55)


def test_reach_between_two_limbs_that_held_still_stays_on_the_edges():
    """The most rigid tree of a standing take can join the two feet (left ankle by the right
    ankle's foot, within a millimetre, while the mirror pair moved): the reach limits of the two
    legs run through that link and bind them at the training's stance. Those pairs hold their
    reach on the DTM's edges only; pairs through a trunk diagonal whose mirror image held as
    rigid (a shoulder and the other side's hip) hold it off the edges too, and a calibrated
    model's off-edge factors leave the feet free to part."""
    C, LHIP, RHIP, LANK, RANK, LSHO, RSHO = range(7)
    mirror = np.array([[LHIP, RHIP], [LANK, RANK], [LSHO, RSHO]])
    parents = np.array([-1, C, C, RANK, RHIP, RHIP, C])       # LANK hangs on the right ankle
    spread = np.full((7, 7), 0.05)
    for a, b, sd in ((C, LHIP, 0.002), (C, RHIP, 0.002), (RHIP, RANK, 0.004), (LHIP, LANK, 0.006),
                     (LANK, RANK, 0.001), (LSHO, RHIP, 0.01), (RSHO, LHIP, 0.012), (C, RSHO, 0.008)):
        spread[a, b] = spread[b, a] = sd
    segment = np.zeros((7, 7), dtype=bool)
    for a, b in ((C, LHIP), (C, RHIP), (RHIP, RANK), (LHIP, LANK)):
        segment[a, b] = segment[b, a] = True
    off = reach_off_edges(parents, segment, spread, mirror)
    assert not off[LANK, RANK] and not off[LANK, RHIP] and not off[LANK, C]     # through the feet's link
    assert off[LSHO, RANK] and off[LSHO, C] and off[C, RHIP]                    # the diagonal stays
    assert reach_off_edges(np.array([-1, C, C, LHIP, RHIP, RHIP, C]), segment, spread, mirror).all()
    # a calibrated body's factors off the edges: none on the feet's pairs, the others as before
    iu, ju = np.triu_indices(7, 1)
    body = BodyModel(n_labels=7, pairs=np.stack([iu, ju], 1), kind=np.full(iu.size, REACH), lo=np.zeros(iu.size),
                     hi=np.full(iu.size, 0.3), within_sd=np.full(iu.size, 0.03), between_sd=np.zeros(iu.size),
                     calibration={"frames": 1}, reach_off_edges=off[iu, ju])
    cross = CrossSegments(body, np.array([[C, LHIP, RHIP]]), (SEGMENT, REACH))
    held = {tuple(p) for p in cross.pairs.tolist()}
    assert (LANK, RANK) not in held and (C, LANK) not in held and (RANK, LSHO) in held and (C, LSHO) in held
    back = BodyModel.from_arrays(body.to_arrays(), 7, body.calibration)
    assert np.array_equal(back.reach_off_edges, off[iu, ju])
    old = {k: v for k, v in body.to_arrays().items() if k != "body_reach_off_edges"}   # a version 7 file
    assert BodyModel.from_arrays(old, 7).reach_off_edges.all()


def test_a_bone_noisy_in_one_clip_of_many_stays_a_segment():
    """A bone is a segment when it holds in most clips (from three on): one take whose points
    are derived from surface markers (a knee from marker means, 2 cm of play) does not undo it;
    with two clips both must hold it."""
    parents = np.array([-1, 0, 1])                     # hip - knee - ankle

    def stats(sds):
        C = len(sds)
        sd = np.full((C, 3, 3), 0.2)                   # the non-links vary a lot
        sd[:, 0, 1] = sd[:, 1, 0] = sds                # hip-knee per clip
        return {"mean": np.full((C, 3, 3), 0.4), "sd": sd, "vec": np.full((C, 3, 3), 0.5),
                "max": np.full((C, 3, 3), 0.45)}

    def kind(sds):
        b = fit_body(stats(sds), parents)
        return int(b.kind[(b.pairs[:, 0] == 0) & (b.pairs[:, 1] == 1)][0])
    assert kind([0.001, 0.002, 0.001, 0.02]) == SEGMENT          # one noisy take of four
    assert kind([0.001, 0.02, 0.001, 0.02, 0.02]) == REACH        # most takes move it
    assert kind([0.001, 0.02]) == REACH and kind([0.001, 0.002]) == SEGMENT   # two: both must hold
    sd = stats([0.001, 0.002, np.nan, 0.02])["sd"]
    assert clip_spread(sd)[0, 1] == pytest.approx(0.002)         # clips that never show it do not count
    assert clip_spread(sd[[0, 3]])[0, 1] == pytest.approx(0.02)


def test_a_rigid_pair_across_a_joint_marker_is_no_segment():
    """Upper arm to wrist held at one elbow angle is as steady as a bone, but the elbow marker
    lies on the line between them: a limb across its joint, never one segment (a reach limit).
    The forearm's pair beside it, which spans nothing, stays a segment."""
    pos = np.array([[0.0, 0, 0], [0.3, 0.01, 0], [0.55, 0.0, 0], [0.55, 0.06, 0]])    # upa, elb, wra, wrb
    length = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    spans = spans_a_point(length)
    assert spans[0, 2] and spans[2, 0] and not spans[1, 2] and not spans[2, 3] and not spans[0, 1]
    parents = np.array([-1, 2, 0, 2])                  # the tree links upa - wra (the steadiest)
    sd = np.full((1, 4, 4), 0.05)
    sd[0, 0, 2] = sd[0, 2, 0] = sd[0, 1, 2] = sd[0, 2, 1] = sd[0, 2, 3] = sd[0, 3, 2] = 0.002
    stats = {"mean": length[None], "sd": sd, "vec": np.full((1, 4, 4), 0.5), "max": length[None] + 0.01}
    b = fit_body(stats, parents)
    kind = {(int(i), int(j)): int(k) for (i, j), k in zip(b.pairs, b.kind)}
    assert kind[(0, 2)] == REACH and kind[(1, 2)] == SEGMENT and kind[(2, 3)] == SEGMENT


def test_a_bone_across_the_sides_needs_its_mirror_image():
    """A segment joining a left and a right point (not each other's mirror) stays one only when
    its mirror image held as steady (the head's diagonals); two feet that held still are not."""
    # labels: 0 LFHD, 1 RFHD, 2 LBHD, 3 RBHD, 4 LANK, 5 RANK, 6 LMT5, 7 RMT5
    mirror = np.array([[0, 1], [2, 3], [4, 5], [6, 7]])
    M = 8
    iu, ju = np.triu_indices(M, 1)
    cand = np.zeros((M, M), dtype=bool)
    for a, b in ((0, 3), (1, 2), (4, 7), (0, 1), (4, 6)):        # head diagonals, a foot pair, mirror, one side
        cand[a, b] = cand[b, a] = True
    keep = unmirrored_crossing(cand[iu, ju], iu, ju, M, mirror)
    kept = {(int(i), int(j)) for i, j, k, c in zip(iu, ju, keep, cand[iu, ju]) if c and k}
    assert kept == {(0, 3), (1, 2), (0, 1), (4, 6)}               # LANK-RMT5 lost: RANK-LMT5 is none
    cand[5, 6] = cand[6, 5] = True                               # the feet's mirror image held too
    keep = unmirrored_crossing(cand[iu, ju], iu, ju, M, mirror)
    assert keep[(iu == 4) & (ju == 7)].all()


def test_a_one_sided_bone_needs_its_mirror_image_not_to_move():
    """A pair on one side (or a side point and the midline) stays a segment unless its mirror
    image was seen and moved (:func:`mirror_moved`): never seen together, steady, or about as
    steady keeps it; an unpaired marker off the midline has no mirror image to judge by."""
    # labels: 0 LSHO, 1 RSHO, 2 LELB, 3 RELB, 4 C7 (midline), 5 RBAC (unpaired, right side)
    mirror = np.array([[0, 1], [2, 3]])
    M = 6
    x = np.array([-0.2, 0.2, -0.25, 0.25, 0.0, 0.1])              # lateral positions
    length = np.abs(x[:, None] - x[None]) + 0.1
    np.fill_diagonal(length, 0.0)
    mid = midline(length, mirror)
    assert mid.tolist() == [False, False, False, False, True, False]
    iu, ju = np.triu_indices(M, 1)
    spread = np.full((M, M), 0.001)

    def moved(sp, steady_mirror=False):
        steady = sp[iu, ju] <= 0.008
        if steady_mirror:
            steady = np.ones_like(steady)
        return {(int(i), int(j)) for i, j, m in zip(iu, ju, mirror_moved(sp, steady, iu, ju, M, mirror, length)) if m}

    assert moved(spread) == set()                                   # every image as steady
    sp = spread.copy()
    sp[4, 1] = sp[1, 4] = 0.018                                     # C7 - RSHO moved ...
    assert moved(sp) == {(0, 4)}                                    # ... so C7 - LSHO is no bone
    assert moved(sp, steady_mirror=True) == set()                   # unless the image held steady
    sp[4, 1] = sp[1, 4] = 0.004                                     # about as steady (within 5 mm)
    assert moved(sp) == set()
    sp[4, 1] = sp[1, 4] = np.nan                                    # never seen together: no evidence
    assert moved(sp) == set()
    sp = spread.copy()
    sp[5, 0] = sp[0, 5] = 0.05                                      # RBAC - LSHO is no mirror image
    assert moved(sp) == set()                                       # of RBAC - RSHO
    sp = spread.copy()
    sp[2, 0] = sp[0, 2] = 0.05                                      # LSHO - LELB moved: RSHO - RELB
    assert moved(sp) == {(1, 3)}                                    # held by its frames only


def test_broad_weight_em_recovers_contamination():
    rng = np.random.default_rng(0)
    narrow = GaussianMixture(np.ones(1), np.zeros((1, 2)), np.eye(2)[None] * 0.01)
    wide = GaussianMixture(np.ones(1), np.zeros((1, 2)), np.eye(2)[None] * 1.0)
    X = np.vstack([narrow.sample(1600, rng), wide.sample(400, rng)])
    w, _ = broad_weight(narrow.log_pdf(X), wide.log_pdf(X), 0.5, 200, (1e-3, 0.9))
    assert w == pytest.approx(0.2, abs=0.03)


def test_broad_part_of_each_conditional(models, walker, person):
    """The broad part: one Gaussian per triangle, wider than the motion mixture in every
    direction, weight from the held-out EM; applied once the body is calibrated; the term is
    log((1-w) e^motion + w e^broad), and a triangle whose new vertex is missing still
    contributes exactly 0 (eq. 30-31)."""
    generic, today = models
    assert generic.broad is not None and today.broad is None
    assert not generic.broad_applied and person.broad_applied
    body = person
    for t, (g, m) in enumerate(zip(body.broad.gaussians, today.mixtures)):
        assert np.trace(g.covariances[0]) > 2 * np.trace(m.covariances, axis1=1, axis2=2).max()
        assert np.diag(g.covariances[0])[9:].min() >= 0.15 ** 2 - 1e-12       # position floor
        assert 0.0 < body.broad.weights[t] < 0.6
    states = canonical_states(walker, body.heading_pairs)[10:12]
    s = states[:, body.triangles[3]].reshape(2, 18)
    codes = np.full((2, 3), 2)
    motion, _ = body.terms[3].evaluate(s, np.full(2, 26))
    broad, _ = body.broad_terms[3].evaluate(s, np.full(2, 26))
    got, _ = body.triangle_terms(3, s, codes)
    w = body.broad.weights[3]
    assert got == pytest.approx(np.log((1 - w) * np.exp(motion) + w * np.exp(broad)))
    codes[:, 0] = 0                                         # the new vertex A missing
    assert body.triangle_terms(3, s, codes)[0] == pytest.approx([0.0, 0.0], abs=1e-12)
    # the batched hot path gives the same terms
    problem = FrameProblem(body, point_states(walker.positions[9:12], walker.rate)[2], Background())
    table = problem.triangle_table(np.arange(14)[None], problem.candidate_bins(np.arange(14)[None]))
    assert np.isfinite(table).all()


def test_calibration_sets_the_persons_lengths(models):
    model = models[0]
    tall = synthesize(duration=1.0, seed=3, height=1.95)
    cal = calibrate(model, tall)
    b0, b1 = model.body, cal.body
    seg = b1.kind == SEGMENT
    u, v = b1.pairs[seg, 0], b1.pairs[seg, 1]
    true = np.median(np.linalg.norm(tall.positions[:, u] - tall.positions[:, v], axis=-1), axis=0)
    assert np.allclose(b1.lo[seg], true, atol=1e-6) and np.allclose(b1.hi[seg], true, atol=1e-6)
    assert (b1.between_sd[seg] == 0).all() and not np.allclose(b0.lo[seg], b1.lo[seg])
    assert cal.provenance["calibration"]["scale"] > 1.05
    # the tall person's own frames fit the calibrated body better than the generic one
    states = canonical_states(tall, model.heading_pairs)[1:]
    assert (cal.frame_log_likelihood(states) >= model.frame_log_likelihood(states) - 1e-9).all()
    assert (cal.frame_log_likelihood(states) > model.frame_log_likelihood(states) + 1).mean() > 0.5
    with pytest.raises(CalibrationError):
        calibrate(models[1], tall)                         # no body terms to calibrate
    with pytest.raises(CalibrationError):
        calibrate(model, np.zeros((5, 3, 3)))


def test_self_calibration_without_labels(models):
    model = models[0]
    other = synthesize(duration=1.0, seed=5, height=1.6, heading=2.0)
    rng = np.random.default_rng(1)
    clouds = [f[rng.permutation(14)] for f in other.positions]           # unlabelled, shuffled
    cal, confirmed = self_calibrate(model, clouds, other.rate)
    assert np.isfinite(confirmed[..., 0]).mean() > 0.8
    seg = cal.body.kind == SEGMENT
    u, v = cal.body.pairs[seg, 0], cal.body.pairs[seg, 1]
    true = np.median(np.linalg.norm(other.positions[:, u] - other.positions[:, v], axis=-1), axis=0)
    assert np.abs(cal.body.lo[seg] - true).max() < 0.01
    assert cal.provenance["calibration"]["source"] == "self-labelled"


def test_calibration_checks_left_against_right(models):
    """Confirmed labels with the right arm chain shifted by one for the whole window (the wrist
    point labelled relbow, no rwrist): its "upper arm" is the shoulder-wrist distance; the
    mirror check drops it and takes the left upper arm's length, and the untouched left side
    keeps its own. Without mirror pairs the wrong length is learnt."""
    model = models[0]
    other = synthesize(duration=1.0, seed=7, height=1.7)
    P = other.positions.copy()
    P[:, I["relbow"]] = P[:, I["rwrist"]]
    P[:, I["rwrist"]] = np.nan
    idx = model.body.pair_index()
    up_r, up_l = idx[I["rshoulder"], I["relbow"]], idx[I["lshoulder"], I["lelbow"]]
    assert model.body.kind[up_r] == SEGMENT and model.body.kind[up_l] == SEGMENT
    true_l = np.median(np.linalg.norm(other.positions[:, I["lshoulder"]] - other.positions[:, I["lelbow"]], axis=-1))
    wrong = np.median(np.linalg.norm(P[:, I["rshoulder"]] - P[:, I["relbow"]], axis=-1))
    assert wrong - true_l > 0.05
    cal = calibrate(model, P)
    assert abs(cal.body.lo[up_r] - true_l) < 0.005 and abs(cal.body.lo[up_l] - true_l) < 0.005
    assert cal.body.hi[up_r] == cal.body.lo[up_r]
    assert cal.provenance["calibration"]["segments_from_mirror"] >= 1
    naive = calibrated_body(model.body, P)[0]              # no mirror pairs: no check
    assert naive.lo[up_r] > true_l + 0.05 or naive.lo[up_r] == model.body.lo[up_r]


def test_mirror_check_only_where_both_training_ranges_agree():
    """CMU 85 + HDM05's shank markers: left shank-ankle 0.242-0.259 m, right 0.207-0.321 m over
    the training people (the labs place the right marker at another height), midpoints 1.4 cm
    apart. The person's right pair measures 0.333 m, the left 0.238 m: both are the person's, and
    neither is replaced by the other's. A pair whose training ranges agree at both ends (the
    heel-toe pairs) is still checked: the one farther outside its range takes its mirror's."""
    # labels: 0 lshank, 1 lankle, 2 rshank, 3 rankle, 4 lheel, 5 ltoe, 6 rheel, 7 rtoe
    pairs = np.array([[0, 1], [2, 3], [4, 5], [6, 7]])
    body = BodyModel(n_labels=8, pairs=pairs, kind=np.full(4, SEGMENT), lo=[0.242, 0.207, 0.224, 0.233],
                     hi=[0.259, 0.321, 0.271, 0.285], within_sd=np.full(4, 0.005), between_sd=np.full(4, 0.07))
    mirror = np.array([1, 0, 3, 2])
    measured = np.ones(4, dtype=bool)
    kept, borrowed = symmetric_segments(body, measured, np.array([0.238, 0.333, 0.221, 0.330]), mirror,
                                        CalibrationSettings())
    assert kept.tolist() == [True, True, True, False] and borrowed.tolist() == [False, False, False, True]
    kept, borrowed = symmetric_segments(body, np.array([False, True, True, True]),
                                        np.array([np.nan, 0.333, 0.221, 0.222]), mirror, CalibrationSettings())
    assert not borrowed[0]                                   # the left shank keeps its generic range


def test_calibration_checks_each_point_on_its_side(models):
    """Confirmed labels with the legs exchanged below the hips for the whole window (lknee,
    lankle on the right leg's points and vice versa; the hips kept): those labels lie on the
    wrong side of the trunk's midline, so their segments keep the generic range instead of the
    hip-to-other-knee distances; the arms, on their own sides, are calibrated."""
    model = models[0]
    other = synthesize(duration=1.0, seed=9, height=1.7, heading=1.0)
    P = other.positions.copy()
    for a, b in (("lknee", "rknee"), ("lankle", "rankle")):
        P[:, [I[a], I[b]]] = P[:, [I[b], I[a]]]
    assert wrong_side(P, model.mirror_pairs, model.heading_pairs)[[I["lknee"], I["rankle"]]].all()
    assert not wrong_side(other.positions, model.mirror_pairs, model.heading_pairs).any()
    cal = calibrate(model, P)
    idx = model.body.pair_index()
    thigh = idx[I["lhip"], I["lknee"]]
    assert model.body.kind[thigh] == SEGMENT
    assert cal.body.lo[thigh] == model.body.lo[thigh] and cal.body.hi[thigh] == model.body.hi[thigh]
    arm = idx[I["lshoulder"], I["lelbow"]]
    true_arm = np.median(np.linalg.norm(other.positions[:, I["lshoulder"]] - other.positions[:, I["lelbow"]], axis=-1))
    assert abs(cal.body.lo[arm] - true_arm) < 1e-6
    assert cal.provenance["calibration"]["wrong_side_labels"] == 4


def test_structure_prior_favours_segment_edges(walker):
    states = canonical_states(walker, np.array([[I["lhip"], I["rhip"]]]))
    scores = ss.TripleScores.from_states(states[1:])
    given = Structure.from_names(BODY14_GIVEN, BODY14).array[None]
    beta = np.zeros((14, 14))
    beta[I["lhip"], I["lknee"]] = beta[I["lknee"], I["lhip"]] = 1.5
    with_prior = scores.with_edge_prior(beta)
    assert with_prior.score(given)[0] == pytest.approx(scores.score(given)[0] + 1.5 * scores.n_frames)
    big = np.full((14, 14), 0.0)
    big[I["lankle"], I["rwrist"]] = big[I["rwrist"], I["lankle"]] = 1e3
    g = ss.greedy(scores.with_edge_prior(big), 14)
    assert (min(I["lankle"], I["rwrist"]), max(I["lankle"], I["rwrist"])) in g.structure.edges()


def test_model_file_v2_round_trip_and_v1_files(models, tmp_path, walker):
    model = models[0]
    cal = calibrate(model, walker)
    path = save_model(cal, tmp_path / "m.npz")
    back = load_model(path)
    assert FORMAT_VERSION >= 3
    for k in ("pairs", "kind", "lo", "hi", "within_sd", "between_sd", "quads", "quad_sign", "twists"):
        assert np.array_equal(getattr(back.body, k), getattr(cal.body, k))
    assert back.body.calibration["segments"] > 0
    states = canonical_states(walker, model.heading_pairs)[3:9]
    assert np.array_equal(back.frame_log_likelihood(states), calibrate(model, walker).frame_log_likelihood(states))
    assert np.array_equal(back.broad.weights, model.broad.weights)
    # format 7 keeps the body it was calibrated from; a format-6 file loads without it
    assert not back.generic_body.calibration
    for k in ("pairs", "lo", "hi", "between_sd", "rigid_pairs", "orders"):
        assert np.array_equal(getattr(back.generic_body, k), getattr(model.body, k))
    with np.load(path, allow_pickle=False) as z:
        v6 = {k: z[k] for k in z.files if not k.startswith("generic_")}
    header = json.loads(bytes(v6["header"]).decode())
    header["format_version"] = 6
    header.pop("generic_body")
    v6["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    old = model_from_arrays(v6, "v6")
    assert old.generic_body is None and old.provenance["format_version_read"] == 6
    assert np.array_equal(old.frame_log_likelihood(states), back.frame_log_likelihood(states))
    # a version-1 file (no body arrays) loads as a model without body terms
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if not k.startswith("body_")}
    header = json.loads(bytes(arrays["header"]).decode())
    header["format_version"] = 1
    header.pop("body")
    header.pop("broad")
    arrays = {k: v for k, v in arrays.items() if not k.startswith("broad")}
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    v1 = model_from_arrays(arrays, "v1")
    assert v1.body is None and v1.broad is None and v1.provenance["format_version_read"] == 1
    assert np.allclose(v1.frame_log_likelihood(states),       # the file's mixtures: the calibrated placement
                       cal.replace(body=None, broad=None).frame_log_likelihood(states))
    header["format_version"] = FORMAT_VERSION + 1
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    with pytest.raises(ModelFileError, match=f"format version {FORMAT_VERSION + 1} is not supported"):
        model_from_arrays(arrays, "v3")
    # a version-2 header announcing body terms without the arrays is refused
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if not k.startswith("body_")}
    with pytest.raises(ModelFileError, match="body"):
        model_from_arrays(arrays, "v2")


def test_cross_segments_formula_and_marginalisation():
    """Calibrated rigid pairs that are not edges of the triangulation (model/body.py,
    CrossSegments): the same dead-zone quadratic, dropped when an end is missing, and
    nothing for reach pairs or edges."""
    body = BodyModel(n_labels=4, pairs=[[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]],
                     kind=[SEGMENT, SEGMENT, SEGMENT, SEGMENT, SEGMENT, SEGMENT],
                     lo=[0.3] * 6, hi=[0.3] * 6, within_sd=[0.01] * 6, between_sd=[0] * 6,
                     calibration={"source": "test"})
    cs = CrossSegments(body, np.array([[0, 1, 2], [3, 0, 1]]))
    assert cs.active and cs.pairs.tolist() == [[2, 3]]              # the one pair no triangle holds
    n = 4
    dist = np.zeros((n + 1, n + 1))
    dist[2, 3] = dist[3, 2] = 0.33                                   # 3 sd beyond the calibrated length
    pop = np.array([[0, 1, 2, 3], [0, 1, 3, 2], [0, 1, 2, n]])
    assert cs(pop, dist, n) == pytest.approx([-4.5, -4.5, 0.0])
    P = np.array([[[0, 0, 0], [1, 0, 0], [0, 0, 0], [0.33, 0, 0]]], float)   # labelled frames: the same factor
    assert cs.labelled(np.concatenate([P, P])).tolist() == pytest.approx([-4.5, -4.5])
    P[0, 3] = np.nan
    assert cs.labelled(P)[0] == 0.0                                  # an unseen end drops it
    reach = BodyModel(n_labels=4, pairs=[[2, 3]], kind=[REACH], lo=[0.0], hi=[1.0], within_sd=[0.03],
                      between_sd=[0.0], calibration={"source": "test"})
    assert not CrossSegments(reach, np.array([[0, 1, 2], [3, 0, 1]])).active
    # a calibrated model holds its reach limits off the edges too: only beyond the limit
    held = CrossSegments(reach, np.array([[0, 1, 2], [3, 0, 1]]), kinds=(SEGMENT, REACH))
    far = np.zeros((n + 1, n + 1))
    far[2, 3] = far[3, 2] = 1.06                                     # 2 sd beyond the reach
    assert held.active and held(pop, far, n) == pytest.approx([-2.0, -2.0, 0.0])
    assert held(pop, dist, n) == pytest.approx([0.0, 0.0, 0.0])      # within reach: nothing


def test_cross_segments_join_the_fitness_once_calibrated(models, person, walker):
    """A calibrated rigid pair off the DTM's edges (the walker's most rigid pair that no
    triangle holds, made a segment at its own length) adds its factor to every labeling's fitness
    and to the frame log-likelihood of labelled frames: nothing while the pair keeps its length,
    the quadratic when it does not; a generic body has none."""
    from dataclasses import replace
    assert models[0].body_cross is None                                # a generic body: no pairs off the edges
    b = person.body
    held = person.body_cross.pairs                                     # calibrated: its reach limits only,
    assert (b.kind[b.pair_index()[held[:, 0], held[:, 1]]] == REACH).all()   # 14 points: every bone is an edge
    edge = np.zeros((14, 14), bool)
    for t in person.triangles:
        edge[np.ix_(t, t)] = True
    iu, ju = np.triu_indices(14, 1)
    off = ~edge[iu, ju]
    spread = np.std(np.linalg.norm(walker.positions[:, iu] - walker.positions[:, ju], axis=-1), axis=0)
    k = np.flatnonzero(off)[np.argmin(spread[off])]
    u, v = int(iu[k]), int(ju[k])
    r = int(b.pair_index()[u, v])
    width = float(np.median(np.linalg.norm(walker.positions[:, u] - walker.positions[:, v], axis=1)))
    kind, lo, hi = b.kind.copy(), b.lo.copy(), b.hi.copy()
    kind[r], lo[r], hi[r] = SEGMENT, width - 0.005, width + 0.005
    model = person.replace(body=replace(b, kind=kind, lo=lo, hi=hi))
    assert model.body_cross is not None and [u, v] in model.body_cross.pairs.tolist()
    ind = np.arange(14)[None]
    P = walker.positions[40:42].copy()
    for length in (width, width + 0.05):
        Q = P.copy()
        Q[1, v] = Q[1, u] + (Q[1, v] - Q[1, u]) * length / np.linalg.norm(Q[1, v] - Q[1, u])
        states = point_states(Q, walker.rate)[1]
        got = FrameProblem(model, states, Background()).fitness(ind) - FrameProblem(person, states, Background()).fitness(ind)
        z = max(0.0, length - hi[r]) / model.body.sd[r]
        assert got[0] == pytest.approx(-0.5 * z * z, abs=1e-9)
        assert (z == 0.0) == (length == width)                        # 5 cm longer costs, its own length does not
        ll = model.frame_log_likelihood(states[None]) - person.frame_log_likelihood(states[None])
        assert ll[0] == pytest.approx(-0.5 * z * z, abs=1e-9)          # log P(X|G) of labelled frames: the same
        missing = ind.copy()
        missing[0, v] = 14
        gm = FrameProblem(model, states, Background()).fitness(missing) - FrameProblem(person, states, Background()).fitness(missing)
        assert gm[0] == pytest.approx(0.0, abs=1e-9)                 # a missing end drops the factor


def test_calibration_measures_its_fit_reference(models):
    """A calibrated model's fit reference for the confidence (``fit_reference_per_label``) is
    the lower of the training people's fit per label and that of the calibration frames under
    the calibrated body (a clip gives the rate for the velocities; an array needs ``rate``,
    without it there is none); the labeler's starting level (``loglik_per_label``) is kept."""
    model = models[0]
    train = model.settings["loglik_per_label"]
    other = synthesize(duration=2.0, seed=5, height=1.9, heading=0.7)       # another, taller person
    cal = calibrate(model, other)
    ref = fit_per_label(cal, other.positions, other.rate)
    states = canonical_states(other, model.heading_pairs)[1:]                # frame 0 has no velocities
    assert ref == pytest.approx(float(np.median(cal.frame_log_likelihood(states) / 14)))
    assert cal.settings["fit_reference_per_label"] == pytest.approx(min(train, ref))
    assert cal.provenance["calibration"]["fit_per_label"] == {"training": train, "calibration_frames": ref}
    assert cal.settings["loglik_per_label"] == train and "fit_reference_per_label" not in model.settings
    assert "fit_reference_per_label" not in calibrate(model, other.positions).settings
    assert calibrate(model, other.positions, rate=other.rate).settings["fit_reference_per_label"] == \
        pytest.approx(min(train, ref))
    # a labeling of frames the body does not fit (the person's arms 25 % longer than calibrated)
    # lowers the reference below the training one; calibrations do not compound
    long = other.positions.copy()
    for s_, e in (("lshoulder", "lelbow"), ("rshoulder", "relbow")):
        long[:, I[e]] = long[:, I[s_]] + 1.25 * (long[:, I[e]] - long[:, I[s_]])
    worse = fit_per_label(cal, long, other.rate)
    assert worse < ref
    again = calibrate(cal.replace(settings=dict(cal.settings, fit_reference_per_label=-1e9)), other)
    assert again.settings["fit_reference_per_label"] == pytest.approx(
        min(train, fit_per_label(again, other.positions, other.rate)))
    assert again.settings["fit_reference_per_label"] == pytest.approx(min(train, ref), abs=0.05)


def test_fit_reference_moves_confidences_not_labels(models, person):
    """The confidence's fit factor reads ``fit_reference_per_label``: a reference 40 nats per
    label above the frames' fit lowers every confidence of a generic body (the frames look unlike
    the model), one far below leaves the factor at 1; the labels stay the same. A calibrated
    body's published confidences leave the factor out (its labels are held by the person's body,
    not by how well the motion fits), its strict confirmations keep it."""
    from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler
    clip = synthesize(duration=0.5, seed=7, heading=0.4)
    for model, calibrated in ((models[0], False), (person, True)):
        runs = {}
        for shift in (None, 40.0, -40.0):
            m = model if shift is None else model.replace(
                settings=dict(model.settings, fit_reference_per_label=model.settings["loglik_per_label"] + shift))
            lab = StreamLabeler(m, LabelerSettings(seed=0))
            runs[shift] = [lab.process(x, k / clip.rate) for k, x in enumerate(clip.positions)]
        for k in (40.0, -40.0):
            assert all(np.array_equal(a.labels, b.labels) for a, b in zip(runs[None], runs[k]))
        labelled = np.array([r.labels for r in runs[None][5:]]) >= 0
        conf = {k: np.array([r.confidence for r in runs[k][5:]])[labelled] for k in runs}
        confirm = {k: np.array([r.confirmation for r in runs[k][5:]])[labelled] for k in runs}
        assert (confirm[40.0] < 0.5 * confirm[None]).all()
        assert (confirm[-40.0] >= confirm[None] - 1e-12).all()
        if calibrated:
            np.testing.assert_allclose(conf[40.0], conf[None])
            np.testing.assert_allclose(conf[-40.0], conf[None])
        else:
            assert (conf[40.0] < 0.5 * conf[None]).all()
            assert (conf[-40.0] >= conf[None] - 1e-12).all()
        assert conf[None].mean() > 0.9


def test_broad_weight_floor_by_point_set(models, walker, data_dir):
    """The broad weight's floor (held-out frames of the same takes show less novelty than
    another motion will): 0.06 for the 14 body points, 0.02 for marker sets (about 40
    triangles, whose tails add up); an explicit ``min_weight`` wins."""
    from dtm_labeler.motion.load import load_clip
    from dtm_labeler.training.body_fit import MIN_WEIGHT_BODY14, MIN_WEIGHT_MARKERS, BodySettings
    body14 = models[0]
    assert body14.settings["broad_component"]["settings"]["min_weight"] == MIN_WEIGHT_BODY14 == 0.06
    assert body14.broad.weights.min() >= MIN_WEIGHT_BODY14 - 1e-12
    arm = ["C7", "CLAV", "LSHO", "RSHO", "LELB", "RELB", "LWRA", "RWRA"]
    hdm = load_clip(data_dir / "markers_c3d/hdm05_bd_05-01_01_120.c3d").select(arm).slice(1200, 1800)
    markers, _ = train_model([hdm], TrainConfig(mixture="fixed", k_fixed=2, structure="greedy", seed=0))
    assert markers.settings["broad_component"]["settings"]["min_weight"] == MIN_WEIGHT_MARKERS == 0.02
    assert markers.broad.weights.min() >= MIN_WEIGHT_MARKERS - 1e-12
    assert markers.broad.weights.min() < MIN_WEIGHT_BODY14          # the EM went below the body-14 floor
    explicit, _ = train_model([walker], TrainConfig(**FAST, body=BodySettings(min_weight=0.3)))
    assert explicit.broad.weights.min() >= 0.3 - 1e-12
    with pytest.raises(ValueError):                  # a cap below the body-14 floor, the floor left unset
        BodySettings(max_weight=0.04).check()
    BodySettings(min_weight=0.01, max_weight=0.04).check()
