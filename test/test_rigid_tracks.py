"""Whole tracks relabelled by the take's rigid pairs (labeling/rigid_tracks.py) on a real take:
HDM05's 41 markers, half of them hidden at a time, the capture's trajectories as tracks."""
import numpy as np
import pytest

from dtm_labeler.labeling.rigid_tracks import body_pairs, label_positions, relabel_tracks, rigid_pairs
from dtm_labeler.model.body import SEGMENT, BodyModel
from dtm_labeler.motion.load import load_clip
from test_gappy_training import HDM, _gapped

GHOST = "LFIN"          # a real marker the labels do not know: fed as an unlabelled point


@pytest.fixture(scope="module")
def take(data_dir):
    """Per frame: points, true labels (-1: the unknown marker), track ids (one per seen run of
    a channel, as a C3D's trajectories)."""
    clip = load_clip(data_dir / HDM)
    clip = _gapped(clip.slice(2960, 3560), missing=0.5, seed=1, gap_s=0.25)
    names = list(clip.names)
    ghost = names.index(GHOST)
    known = [n for n in names if n != GHOST]
    label_of = np.array([known.index(n) if n != GHOST else -1 for n in names])
    seen = np.isfinite(clip.positions[..., 0])                       # (F, C)
    run = np.cumsum(np.vstack([seen[:1], seen[1:] & ~seen[:-1]]), axis=0)
    xyz, truth, tracks = [], [], []
    for f in range(clip.n_frames):
        c = np.flatnonzero(seen[f])
        xyz.append(clip.positions[f, c])
        truth.append(label_of[c])
        tracks.append(c * 10_000 + run[f, c])
    return dict(xyz=xyz, truth=truth, tracks=tracks, n_labels=len(known), names=known, ghost=ghost)


def channel_tracks(clip):
    """Per frame of a gapped ``clip``: the seen channels' points, their channel indices (the
    true labels) and track ids (one per seen run of a channel, as a C3D's trajectories)."""
    seen = np.isfinite(clip.positions[..., 0])
    run = np.cumsum(np.vstack([seen[:1], seen[1:] & ~seen[:-1]]), axis=0)
    xyz, truth, tracks = [], [], []
    for f in range(clip.n_frames):
        c = np.flatnonzero(seen[f])
        xyz.append(clip.positions[f, c])
        truth.append(c.astype(np.int64))
        tracks.append(c * 10_000 + run[f, c])
    return xyz, truth, tracks


def _pieces(take):
    """{track id: [(frame, row)]} of the known markers."""
    out = {}
    for f, (tid, tr) in enumerate(zip(take["tracks"], take["truth"])):
        for i, (t, lab) in enumerate(zip(tid, tr)):
            if lab >= 0:
                out.setdefault(int(t), []).append((f, i))
    return out


def _accuracy(take, labels):
    t = np.concatenate(take["truth"])
    lab = np.concatenate(labels)
    known = t >= 0
    return float((lab[known] == t[known]).mean())


def test_rigid_pairs_are_short_and_steady(take):
    P = label_positions(take["xyz"], take["truth"], take["n_labels"])
    pairs = rigid_pairs(P)
    names = take["names"]
    R = pairs.rigid
    assert R[names.index("LFHD"), names.index("LBHD")]                 # one head
    assert R[names.index("RANK"), names.index("RHEE")]                 # one foot
    assert not R[names.index("LFHD"), names.index("LANK")]             # head to ankle: longer than a segment
    assert (pairs.length[R] <= 0.4).all() and (R == R.T).all() and not R.diagonal().any()
    assert 50 < pairs.count < 400


def test_misplaced_tracks_get_their_labels_back(take):
    """Trajectory pieces of 15-40 frames (what the take pass leaves wrong) given the label of
    a nearby marker hidden meanwhile, and a track left unlabelled, get their own labels back;
    the unknown real marker stays unlabelled and next to nothing that was right goes wrong."""
    rng = np.random.default_rng(0)
    labels = [t.copy() for t in take["truth"]]
    for lab in labels:
        lab[lab < 0] = -1
    names = take["names"]
    pieces = {t: fr for t, fr in _pieces(take).items() if 15 <= len(fr) <= 40}
    P = label_positions(take["xyz"], take["truth"], take["n_labels"])
    busy = np.isfinite(P[..., 0])                                         # (F, M): label held
    apart = np.nanmedian(np.linalg.norm(P[:, :, None] - P[:, None], axis=-1), axis=0)   # (M, M)
    moved = []
    for t in rng.permutation(list(pieces)):
        fr = pieces[int(t)]
        frames = [f for f, _ in fr]
        own = int(take["truth"][fr[0][0]][fr[0][1]])
        near = apart[own].copy()
        near[own] = np.inf
        free = ~busy[frames].any(0)
        cand = np.flatnonzero(free & (near < 0.25))
        if not len(cand) or len(moved) >= 8:
            continue
        a = int(cand[np.argmin(near[cand])])
        for f, i in fr:
            labels[f][i] = a
        busy[frames, a] = True
        busy[frames, own] = False
        moved.append((names[own], names[a], len(fr)))
    assert len(moved) == 8
    blanked = next(t for t in rng.permutation(list(pieces))
                   if labels[pieces[int(t)][0][0]][pieces[int(t)][0][1]] == take["truth"][pieces[int(t)][0][0]][pieces[int(t)][0][1]])
    for f, i in pieces[int(blanked)]:
        labels[f][i] = -1
    before = _accuracy(take, labels)
    assert before < 0.985

    new, moves = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"])
    after = _accuracy(take, new)
    assert after > 0.997, (before, after, moved)
    assert moves >= 8
    was_right = np.concatenate([lab == t for lab, t in zip(labels, take["truth"])])
    now = np.concatenate(new)
    truth = np.concatenate(take["truth"])
    assert (now[was_right & (truth >= 0)] != truth[was_right & (truth >= 0)]).mean() < 0.005
    assert (now[truth < 0] == -1).all()                                   # the unknown marker: left out


def test_a_label_far_from_all_its_partners_is_refuted(take):
    """A head marker's trajectory piece given a foot label that is free in its frames (the
    live pass's error on a gapped HDM05 take: the foot's only triangle hidden, the head's
    velocity alone fit it): every rigid partner of the foot is a metre away, beyond the reach
    of any rigid pair, and those broken distances refute the label, so the piece gets its own
    label back."""
    names = take["names"]
    labels = [np.where(t >= 0, t, -1) for t in take["truth"]]
    P = label_positions(take["xyz"], take["truth"], take["n_labels"])
    free = ~np.isfinite(P[..., 0])                                        # (F, M)
    heads = [names.index(n) for n in ("LFHD", "RFHD", "LBHD", "RBHD")]
    feet = [names.index(n) for n in ("LMT5", "RMT5", "LTOE", "RTOE", "LHEE", "RHEE")]
    piece, head, foot = max(((fr, int(take["truth"][fr[0][0]][fr[0][1]]), a) for fr in _pieces(take).values()
                             for a in feet if take["truth"][fr[0][0]][fr[0][1]] in heads
                             and all(free[f, a] for f, _ in fr)), key=lambda c: len(c[0]))
    assert len(piece) >= 10
    # as in that take, one rigid partner of the head in view (another head marker): one
    # partner's worth of support for the piece's own label, which alone would not move it back
    frames = [f for f, _ in piece]
    partners = np.flatnonzero(rigid_pairs(P).rigid[head])
    keep = max(set(heads) & set(partners.tolist()), key=lambda h: (~free[frames, h]).sum())
    xyz, tracks = list(take["xyz"]), list(take["tracks"])
    for k, (f, i) in enumerate(piece):
        t = take["truth"][f]
        stay = ~np.isin(t, partners[partners != keep])
        xyz[f], tracks[f], labels[f] = xyz[f][stay], tracks[f][stay], labels[f][stay]
        i = int(np.flatnonzero(t[stay] == head)[0])
        labels[f][i] = foot
        piece[k] = (f, i)
    new, moves = relabel_tracks(xyz, tracks, labels, take["n_labels"])
    back = np.mean([new[f][i] == head for f, i in piece])
    assert back == 1.0 and moves >= 1


def test_a_right_label_refuted_by_pose_held_pairs_is_not_taken_by_its_mirror(data_dir):
    """Another draw of the same take's gaps: a raised arm breaks the right shoulder marker's
    pose-held pairs (0.2-0.4 m to the head and the back), so its right label is refuted, and the
    left shoulder's label, which one coincidental partner confirms for it, is held by the left
    shoulder marker with more support: it stays there (without that rule the right shoulder
    took it and the left shoulder was left unlabelled: 0.36 % of the labels moved)."""
    clip = _gapped(load_clip(data_dir / HDM).slice(2960, 3560), missing=0.5, seed=5, gap_s=0.25)
    xyz, truth, tracks = channel_tracks(clip)
    new, moves = relabel_tracks(xyz, tracks, truth, clip.n_points)
    assert moves == 0 and all((a == b).all() for a, b in zip(new, truth))


def test_right_labels_stay_and_untracked_points_are_kept(take):
    labels = [np.where(t >= 0, t, -1) for t in take["truth"]]
    new, moves = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"])
    assert _accuracy(take, new) > 0.999
    untracked = [np.full(len(t), -1) for t in take["tracks"]]
    same, none = relabel_tracks(take["xyz"], untracked, labels, take["n_labels"])
    assert none == 0 and all((a == b).all() for a, b in zip(same, labels))


def test_blocks_bound_the_work_and_agree_with_one_block(take):
    labels = [np.where(t >= 0, t, -1) for t in take["truth"]]
    whole, _ = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"])
    parts, _ = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"], block=300)
    agree = np.mean(np.concatenate(whole) == np.concatenate(parts))
    assert agree > 0.99


def test_many_short_pieces_make_shorter_blocks(take, monkeypatch):
    """Memory stays bounded: over MAX_CELLS evidence cells a block is halved, and the labels
    barely change for it."""
    import dtm_labeler.labeling.rigid_tracks as rt
    labels = [np.where(t >= 0, t, -1) for t in take["truth"]]
    whole, _ = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"])
    sizes = []
    real = rt._relabel_block

    def spy(xyz, *a):
        sizes.append(len(xyz))
        return real(xyz, *a)
    monkeypatch.setattr(rt, "MAX_CELLS", 100 * take["n_labels"] ** 2)
    monkeypatch.setattr(rt, "_relabel_block", spy)
    parts, _ = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"], rounds=1)
    assert sum(sizes) == len(take["xyz"]) and max(sizes) < len(take["xyz"]) // 2
    assert np.mean(np.concatenate(whole) == np.concatenate(parts)) > 0.99


def _two_segments(frames: int = 100, seed: int = 3):
    """Two rigid clusters turning independently: A, B, C (labels 0-2) on one, D, E, F, G
    (3-6) on the other, 8 cm apart (within reach of each other's pairs); (F, 7, 3) positions
    in metres."""
    rng = np.random.default_rng(seed)
    one = rng.normal(scale=0.04, size=(3, 3))
    two = rng.normal(scale=0.04, size=(4, 3)) + [0.08, 0.0, 0.0]
    t = np.linspace(0.0, 2.0 * np.pi, frames)

    def turn(pts, angle, centre):
        c, s = np.cos(angle), np.sin(angle)
        R = np.stack([np.stack([c, -s, 0 * c], -1), np.stack([s, c, 0 * c], -1),
                      np.broadcast_to([0.0, 0.0, 1.0], c.shape + (3,))], -2)    # about z
        return np.einsum("fij,pj->fpi", R, pts - centre) + centre
    return np.concatenate([turn(one, 1.5 * np.sin(t), one.mean(0)),
                           turn(two, 1.5 * np.cos(1.3 * t), two.mean(0))], axis=1)


def test_a_refuted_label_yields_to_one_confirming_partner():
    """A's track is labelled D for 20 frames while D and C are hidden: D's three partners
    E, F, G refute it (-30 nats, each clipped at -10), and only B confirms A (+10, under the
    15 nats a move needs). The refuted label gives way to A; with the old rule (no lower
    support for a refuted label) it stays D."""
    pos = _two_segments()
    F = len(pos)
    xyz, labels, tracks = [], [], []
    for f in range(F):
        shown = np.arange(7)
        wrong = 60 <= f < 80
        if wrong:
            shown = shown[(shown != 2) & (shown != 3)]                   # C and D hidden
        lab = shown.copy()
        tid = shown.copy()
        if wrong:
            lab[shown == 0] = 3                                          # A labelled D
            tid[shown == 0] = 100                                        # a new trajectory
        xyz.append(pos[f, shown])
        labels.append(lab)
        tracks.append(tid)
    new, moves = relabel_tracks(xyz, tracks, labels, 7)
    assert moves >= 1
    assert all((n == s).all() for n, s in ((new[f], np.arange(7)[(np.arange(7) != 2) & (np.arange(7) != 3)])
                                           for f in range(60, 80)))
    assert all((new[f] == labels[f]).all() for f in range(F) if not 60 <= f < 80)
    kept, _ = relabel_tracks(xyz, tracks, labels, 7, refuted_support=15.0)
    assert all((kept[f] == labels[f]).all() for f in range(F))


def _body_of(take, frames: slice, scale: float = 1.0) -> BodyModel:
    """A one-person body from the true labels of ``frames`` (what a calibration measures): every
    rigid pair a segment at its length (times ``scale``: another person's proportions)."""
    P = label_positions(take["xyz"][frames], take["truth"][frames], take["n_labels"])
    measured = rigid_pairs(P)
    u, v = np.nonzero(np.triu(measured.rigid))
    L = measured.length[u, v] * scale
    return BodyModel(n_labels=take["n_labels"], pairs=np.stack([u, v], 1), kind=np.full(len(u), SEGMENT),
                     lo=L, hi=L, within_sd=np.full(len(u), 0.005), between_sd=np.zeros(len(u)))


def test_a_label_the_take_never_shows_gets_its_pairs_from_the_body(take):
    """The labeler left one marker out in every frame (the Qualisys walk under a gapped model,
    own tracker: two markers unlabelled for the whole take). The take's own labels then say
    nothing about that label's pairs; the model's body, which knows the person's segment
    lengths, does: with it the marker's tracks get their label where two of its partners are in
    view (a new label needs more than one partner's worth; at 50 % hidden, two thirds of its
    points), without it they stay out -- and with another person's body (15 % longer
    segments: the take's segments disagree with it) too."""
    names = take["names"]
    gone = names.index("LBHD")
    body = _body_of(take, slice(0, 300))                               # "calibration": the first 300 frames
    assert (body.pairs == gone).any(1).sum() >= 3
    labels = [np.where((t >= 0) & (t != gone), t, -1) for t in take["truth"]]
    truth = np.concatenate(take["truth"])
    without, _ = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"])
    with_body, _ = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"], prior=body_pairs(body))
    other, _ = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"],
                              prior=body_pairs(_body_of(take, slice(0, 300), scale=1.15)))
    assert (np.concatenate(without)[truth == gone] == gone).mean() < 0.05
    assert (np.concatenate(with_body)[truth == gone] == gone).mean() > 0.6
    assert (np.concatenate(other)[truth == gone] == gone).mean() < 0.05
    others = (truth >= 0) & (truth != gone)
    assert (np.concatenate(with_body)[others] == truth[others]).mean() > 0.999
    generic = BodyModel(n_labels=take["n_labels"], pairs=body.pairs, kind=body.kind, lo=body.lo * 0.8,
                        hi=body.hi * 1.2, within_sd=body.within_sd, between_sd=body.between_sd)
    assert body_pairs(generic) is None                               # lengths over people: not one person's


def test_the_body_corrects_pairs_the_take_measured_on_a_wrong_marker(take):
    """A marker carries its neighbour's label for most of the take (its own marker hidden
    meanwhile): the take then measures that label's pairs on the wrong marker and defends the
    error. The person's body, which the rest of the take agrees with, gives those pairs their
    lengths back, and the marker its label."""
    names = take["names"]
    own, wrong = names.index("RANK"), names.index("RHEE")
    truth = take["truth"]
    labels, xyz, tracks = [], [], []
    for f, (t, x, tid) in enumerate(zip(truth, take["xyz"], take["tracks"])):
        keep = t != wrong                                              # the true RHEE hidden throughout
        lab = np.where(t[keep] >= 0, t[keep], -1)
        lab[lab == own] = wrong                                        # RANK labelled RHEE
        labels.append(lab)
        xyz.append(x[keep])
        tracks.append(tid[keep])
    truth_kept = [t[t != wrong] for t in truth]
    right = np.concatenate(truth_kept)

    def acc(new):
        lab = np.concatenate(new)
        return (lab[right == own] == own).mean()
    assert acc(labels) == 0.0
    alone, _ = relabel_tracks(xyz, tracks, labels, take["n_labels"])
    body = body_pairs(_body_of(take, slice(0, 600)))
    fixed, _ = relabel_tracks(xyz, tracks, labels, take["n_labels"], prior=body)
    assert acc(alone) < 0.05
    assert acc(fixed) > 0.95


def _off_the_tree(body: BodyModel) -> BodyModel:
    """The same pairs as a trained person's rigid pairs off the structure's tree, no segment."""
    return BodyModel(n_labels=body.n_labels, pairs=np.zeros((0, 2)), kind=np.zeros(0), lo=np.zeros(0),
                     hi=np.zeros(0), within_sd=np.zeros(0), between_sd=np.zeros(0), rigid_pairs=body.pairs,
                     rigid_length=(body.lo + body.hi) / 2.0, rigid_spread=body.within_sd)


def test_the_persons_pairs_off_the_tree_fill_in_what_the_take_does_not_measure(take):
    """A model of one person carries all of that person's rigid pairs, not only the tree's
    segments (BodyModel.rigid_pairs). They give a label the take never shows its pairs, as
    segments do -- and for another person (15 % longer) they are not used."""
    gone = take["names"].index("LBHD")
    labels = [np.where((t >= 0) & (t != gone), t, -1) for t in take["truth"]]
    truth = np.concatenate(take["truth"])
    person = _off_the_tree(_body_of(take, slice(0, 300)))
    prior = body_pairs(person)
    assert prior is not None and prior.count == person.rigid_pairs.shape[0]
    filled, _ = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"], prior=prior)
    other, _ = relabel_tracks(take["xyz"], take["tracks"], labels, take["n_labels"],
                              prior=body_pairs(_off_the_tree(_body_of(take, slice(0, 300), scale=1.15))))
    assert (np.concatenate(filled)[truth == gone] == gone).mean() > 0.6
    assert (np.concatenate(other)[truth == gone] == gone).mean() < 0.05
    others = (truth >= 0) & (truth != gone)
    assert (np.concatenate(filled)[others] == truth[others]).mean() > 0.999


def test_the_persons_cluster_pairs_correct_what_the_take_measured_on_a_wrong_marker(take):
    """Read as segments are: where the take measured a pair on the wrong marker (RANK labelled
    RHEE for the whole take), the person's pairs give the length back, and the marker its label."""
    names = take["names"]
    own, wrong = names.index("RANK"), names.index("RHEE")
    labels, xyz, tracks = [], [], []
    for t, x, tid in zip(take["truth"], take["xyz"], take["tracks"]):
        keep = t != wrong
        lab = np.where(t[keep] >= 0, t[keep], -1)
        lab[lab == own] = wrong
        labels.append(lab)
        xyz.append(x[keep])
        tracks.append(tid[keep])
    right = np.concatenate([t[t != wrong] for t in take["truth"]])
    fixed, _ = relabel_tracks(xyz, tracks, labels, take["n_labels"],
                              prior=body_pairs(_off_the_tree(_body_of(take, slice(0, 600)))))
    assert (np.concatenate(fixed)[right == own] == own).mean() > 0.95
