"""Whole track pieces relabelled by the model's fitness over their frames, gated by the take's
rigid pairs (labeling/fitness_pieces.py), on a real half-hidden HDM05 stretch whose true
trajectories are the tracks."""
import numpy as np
import pytest

from dtm_labeler.labeling.fitness_pieces import relabel_by_fitness
from dtm_labeler.labeling.rest_clock import take_rests
from dtm_labeler.labeling.rigid_tracks import body_pairs
from dtm_labeler.labeling.take_pass import take_heading, track_states
from dtm_labeler.search.problem import Background
from test_gappy_training import _gapped

FRAMES = (2400, 2760)


@pytest.fixture(scope="module")
def stretch(hdm05_calibrated, hdm05_take):
    """(model, xyz, track ids = true marker, true labels, states, rests) of 3 s after the
    model's training part, half of the samples hidden in real-looking gaps."""
    model = hdm05_calibrated
    clip = _gapped(hdm05_take.select(list(model.labels)), 0.5, seed=2).slice(*FRAMES)
    seen = np.isfinite(clip.positions[..., 0])
    xyz = [clip.positions[f][seen[f]] for f in range(clip.n_frames)]
    truth = [np.flatnonzero(seen[f]) for f in range(clip.n_frames)]
    states = track_states(xyz, truth, clip.rate)
    return model, xyz, truth, states, take_rests(xyz, truth, clip.rate), clip


def _run(stretch, labels, searched, **kw):
    model, xyz, truth, states, rests, _ = stretch
    yaw = take_heading(model, xyz, labels)
    return relabel_by_fitness(model, Background(), states, rests, yaw, xyz, truth, labels, searched,
                              prior=body_pairs(model.body), **kw)


def _neighbour_hidden_run(clip, model, a: str, b: str, length: int = 8) -> tuple[int, int, int, int]:
    """(index of a, of b, first and last + 1 frame) of the first run of at least ``length``
    frames where marker ``a`` is seen throughout and ``b`` hidden."""
    ia, ib = model.labels.index(a), model.labels.index(b)
    seen = np.isfinite(clip.positions[..., 0])
    ok = np.r_[0, (seen[:, ia] & ~seen[:, ib]).astype(int), 0]
    edges = np.flatnonzero(np.diff(ok))
    runs = [(s, e) for s, e in zip(edges[::2], edges[1::2]) if e - s >= length]
    assert runs, f"no {length} frames with {a} seen and {b} hidden"
    return ia, ib, *runs[0]


@pytest.mark.parametrize("a, b", [("LELB", "LUPA"), ("LUPA", "LELB"), ("RUPA", "RSHO"), ("LFIN", "LWRB"),
                                  ("RTOE", "RMT5"), ("RELB", "RFRM"), ("RFRM", "RWRA")])
def test_a_piece_given_its_hidden_neighbours_label_takes_its_own_back(stretch, a, b):
    """A marker's piece published as the neighbour hidden in those frames (the take pass's
    commonest error on 50 %-gapped takes: elbow as upper arm, finger as wrist bar, toe as
    metatarsal), one search of the pass right: the piece takes its own label back and nothing
    else moves. (Measured on this stretch: LFRM <-> LWRA, the forearm marker and the wrist
    bar's end it is rigid with, stay: their rigid evidence does not tell them apart.)"""
    model, xyz, truth, states, rests, clip = stretch
    ia, ib, f0, f1 = _neighbour_hidden_run(clip, model, a, b)
    wrong = [t.copy() for t in truth]
    for f in range(f0, f1):
        wrong[f][truth[f] == ia] = ib
    out, moves = _run(stretch, wrong, [truth, wrong])
    assert moves == 1
    assert all((o == t).all() for o, t in zip(out, truth))


def test_nothing_moves_from_the_truth_on_wrong_searches(stretch):
    """From the true labels, both searches giving every point another label drawn at random:
    no piece moves (the fitness and the rigid gate both stand by the truth)."""
    model, xyz, truth, *_ = stretch
    rng = np.random.default_rng(0)
    wrong = [np.where(t >= 0, (t + rng.integers(1, model.n_labels, t.size)) % model.n_labels, -1) for t in truth]
    out, moves = _run(stretch, [t.copy() for t in truth], [wrong, wrong])
    assert moves == 0 and all((o == t).all() for o, t in zip(out, truth))


def test_moves_need_their_gain(stretch):
    """The same corrupted piece stays when the move's gain is asked above what it brings."""
    model, xyz, truth, states, rests, clip = stretch
    ia, ib, f0, f1 = _neighbour_hidden_run(clip, model, "LELB", "LUPA")
    wrong = [t.copy() for t in truth]
    for f in range(f0, f1):
        wrong[f][truth[f] == ia] = ib
    out, moves = _run(stretch, wrong, [truth, truth], min_gain=1e9)
    assert moves == 0 and all((o == w).all() for o, w in zip(out, wrong))


def _forearm(n: int = 60, seed: int = 0):
    """A partner marker P (label 2) and two markers on one rigid body with it: A (label 0,
    0.138 m from P) and B (label 1, 0.131 m from P, as the elbow and the wrist bar's end are
    from the forearm marker), turning over ``n`` frames with 0.3 mm of noise. B is seen in the
    first half only; A's marker is a new track in the second half."""
    rng = np.random.default_rng(seed)
    xyz, ids, labels = [], [], []
    for f in range(n):
        t = 0.02 * f
        c, s = np.cos(t), np.sin(t)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        P = np.array([0.5, 0.2, 1.0]) + [0.001 * f, 0.0, 0.0]
        pts = [P + R @ [0.138, 0.0, 0.0], P + R @ [0.0, 0.131, 0.0], P]
        if f < n // 2:
            xyz.append(np.array(pts) + rng.normal(0, 3e-4, (3, 3)))
            ids.append(np.array([0, 1, 2]))
            labels.append(np.array([0, 1, 2]))
        else:
            xyz.append(np.array([pts[0], pts[2]]) + rng.normal(0, 3e-4, (2, 3)))
            ids.append(np.array([3, 2]))
            labels.append(np.array([0, 2]))
    return xyz, ids, labels


def test_a_label_whose_partner_fits_only_roughly_is_no_candidate():
    """The rigid gate weighs what every partner says unclipped too: A's piece of the second half
    matches its partner's 0.138 m in every frame and the candidate B's 0.131 m only roughly
    (2.3 spreads), both clipped to the same +10 nats. B is a candidate only while the unclipped
    evidence may fall by any amount."""
    from dtm_labeler.labeling.fitness_pieces import _candidates
    from dtm_labeler.labeling.rigid_tracks import PieceEvidence, track_pieces
    xyz, ids, labels = _forearm()
    ev = PieceEvidence(xyz, track_pieces(ids, labels), labels, 3)
    assert ev.pairs.rigid[0, 2] and ev.pairs.rigid[1, 2]
    piece = int(ev.pid[-1][0])
    assert ev.score[piece, 0] == ev.score[piece, 1] == 10.0              # both clipped alike
    searched = [[np.where(lab == 0, 1, lab) if f >= 30 else lab for f, lab in enumerate(labels)]]
    loose = _candidates(ev, labels, searched, 5, 3, 20.0, np.inf)
    assert loose.get(piece) == [1]
    assert piece not in _candidates(ev, labels, searched, 5, 3, 20.0, 10.0)
