"""Votes over frames (eq. 32) and the published one-to-one labeling."""
import numpy as np
import pytest

from dtm_labeler.labeling.voting import VoteBook


def test_eq32_counts_over_the_window():
    vb = VoteBook(window=5, n_labels=3)
    vb.add(np.array([10, 11, 12]), np.array([0, 1, -1]))
    vb.add(np.array([11, 10]), np.array([0, 0]))             # order of points changes per frame
    vb.add(np.array([10, 12, 13]), np.array([2, 1, 0]))
    votes = vb.tally(np.array([12, 10, 11, 99]))
    assert votes.tolist() == [[0, 1, 0],          # track 12: label 1 once (-1 is no vote)
                              [2, 0, 1],          # track 10
                              [1, 1, 0],          # track 11
                              [0, 0, 0]]          # unknown track
    assert vb.tally(np.array([], dtype=np.int64)).shape == (0, 3)


def test_window_slides():
    vb = VoteBook(window=2, n_labels=2)
    vb.add(np.array([1]), np.array([0]))
    vb.add(np.array([1]), np.array([1]))
    vb.add(np.array([1]), np.array([1]))                      # first frame falls out
    assert vb.tally(np.array([1])).tolist() == [[0, 2]]
    assert len(vb.frame_sizes) == 2
    vb.reset()
    assert vb.tally(np.array([1])).tolist() == [[0, 0]]
    with pytest.raises(ValueError):
        VoteBook(window=0, n_labels=2)


def test_publish_majority_and_confidence():
    vb = VoteBook(window=4, n_labels=3)
    tracks = np.array([5, 6])
    for labs in ([0, 1], [0, 1], [1, 0], [0, 1]):
        vb.add(tracks, np.array(labs))
    labels, conf = vb.publish(tracks, np.array([0, 1]))
    assert labels.tolist() == [0, 1]
    np.testing.assert_allclose(conf, [0.75, 0.75])            # 3 of 4 frames
    # a fresh decision against an older majority does not win outright
    vb2 = VoteBook(window=4, n_labels=3)
    for labs in ([0, 1], [0, 1], [0, 1], [1, 0]):
        vb2.add(tracks, np.array(labs))
    labels, conf = vb2.publish(tracks, np.array([1, 0]))
    assert labels.tolist() == [0, 1]
    np.testing.assert_allclose(conf, [0.75, 0.75])


def test_current_frame_breaks_ties():
    vb = VoteBook(window=2, n_labels=2)
    t = np.array([1, 2])
    vb.add(t, np.array([0, 1]))
    vb.add(t, np.array([1, 0]))                               # 1:1 for both
    labels, conf = vb.publish(t, np.array([1, 0]))
    assert labels.tolist() == [1, 0]
    np.testing.assert_allclose(conf, [0.5, 0.5])


def test_hungarian_uniqueness():
    """Two tracks voting for the same label: the stronger one gets it, the other its next best."""
    vb = VoteBook(window=5, n_labels=3)
    t = np.array([1, 2, 3])
    for labs in ([0, 0, 2], [0, 0, 2], [0, 1, 2], [0, 0, 2], [1, 0, 2]):
        vb.add(t, np.array(labs))
    cur = np.array([1, 0, 2])
    labels, conf = vb.publish(t, cur)
    assert len(set(labels[labels >= 0].tolist())) == (labels >= 0).sum()       # one track per label
    assert labels.tolist() == [0, 1, 2] or labels.tolist() == [1, 0, 2]
    # total votes (plus the tie-break half vote) are maximal over all one-to-one choices
    votes = vb.tally(t)
    votes[np.arange(3), cur] += 0.5
    best = max(votes[0, a] + votes[1, b] + votes[2, 2] for a, b in [(0, 1), (1, 0)])
    assert votes[np.arange(3), labels].sum() == best
    assert conf[2] == pytest.approx(1.0)


def test_track_without_votes_stays_unlabelled():
    vb = VoteBook(window=3, n_labels=2)
    vb.add(np.array([1, 2]), np.array([0, -1]))
    labels, conf = vb.publish(np.array([1, 2]), np.array([0, -1]))
    assert labels.tolist() == [0, -1] and conf.tolist() == [1.0, 0.0]
    # more tracks than labels: only n_labels get one
    vb = VoteBook(window=1, n_labels=1)
    vb.add(np.array([1, 2]), np.array([0, 0]))
    labels, _ = vb.publish(np.array([1, 2]), np.array([0, 0]))
    assert sorted(labels.tolist()) == [-1, 0]
    # nothing at all
    labels, conf = VoteBook(window=3, n_labels=2).publish(np.array([], dtype=np.int64), np.array([], dtype=np.int64))
    assert labels.size == 0 and conf.size == 0


def test_confidence_in_unit_interval_random():
    rng = np.random.default_rng(0)
    vb = VoteBook(window=6, n_labels=5)
    for _ in range(20):
        t = rng.permutation(8)[:6]
        labs = np.where(rng.random(6) < 0.2, -1, rng.permutation(5).tolist() + [-1])
        vb.add(t, labs)
        labels, conf = vb.publish(t, labs)
        assert ((conf >= 0) & (conf <= 1)).all()
        assert len(set(labels[labels >= 0].tolist())) == (labels >= 0).sum()
        assert np.all(conf[labels < 0] == 0)


def test_unlabelled_is_a_vote_of_its_own():
    """A ghost track left unlabelled by 5 searches and given a label in the 6th (its marker
    hidden) stays unlabelled; a track labelled in most frames keeps its label."""
    vb = VoteBook(window=10, n_labels=3)
    for _ in range(5):
        vb.add(np.array([7, 8]), np.array([-1, 2]))
    vb.add(np.array([7, 8]), np.array([2, -1]))              # the label jumps to the ghost
    labels, conf = vb.publish(np.array([7, 8]), np.array([2, -1]))
    assert labels[0] == -1 and conf[0] == 0.0
    assert labels[1] == 2 and conf[1] == pytest.approx(5 / 6)


def test_doubtful_frames_abstain_from_the_unlabelled_vote():
    """Frames published doubtful (a recovery running, nothing known) cast no "no label" votes:
    the labels a recovery brings are published at once."""
    vb = VoteBook(window=10, n_labels=2)
    for _ in range(6):
        vb.add(np.array([1, 2]), np.array([-1, -1]), abstain=True)
    vb.add(np.array([1, 2]), np.array([0, 1]))
    labels, _ = vb.publish(np.array([1, 2]), np.array([0, 1]))
    assert labels.tolist() == [0, 1]
    vb.add(np.array([1, 2]), np.array([-1, -1]))             # voting frames: now 1 label vs 1 none each
    vb.add(np.array([1, 2]), np.array([-1, -1]))
    labels, _ = vb.publish(np.array([1, 2]), np.array([-1, -1]))
    assert labels.tolist() == [-1, -1]


def test_a_vouched_frame_drops_a_window_of_doubtful_ones():
    """Labels published while nothing is vouched for (a recovery's interim results) do not
    outvote the first vouched labeling; a window that holds a vouched frame keeps its votes."""
    vb = VoteBook(window=10, n_labels=3)
    for _ in range(8):                                       # interim: tracks 1, 2 read as 0, 1
        vb.add(np.array([1, 2]), np.array([0, 1]), abstain=True)
    vb.add(np.array([1, 2]), np.array([1, 0]))              # the search's result: the other way round
    labels, conf = vb.publish(np.array([1, 2]), np.array([1, 0]))
    assert labels.tolist() == [1, 0] and conf.tolist() == [1.0, 1.0]
    vb.add(np.array([1, 2]), np.array([0, 1]), abstain=True)
    vb.add(np.array([1, 2]), np.array([0, 1]))              # a vouched frame is in the window: votes kept
    assert vb.tally(np.array([1, 2])).tolist() == [[2, 1, 0], [1, 2, 0]]


def test_sliding_window_equals_a_recount():
    """The window kept as one concatenation, slid by a frame per add, counts what a recount of
    the window's frames from scratch counts (votes, frames seen, "no label" votes)."""
    rng = np.random.default_rng(3)
    vb, frames = VoteBook(window=7, n_labels=4), []
    for _ in range(40):
        k = int(rng.integers(0, 7))
        t = rng.permutation(10)[:k]
        labs = np.where(rng.random(k) < 0.3, -1, rng.integers(0, 4, k))
        abstain = bool(rng.random() < 0.2)
        vb.add(t, labs, abstain=abstain)
        if not abstain and not any(not a for _, _, a in frames):
            frames = []                                       # a window of doubtful frames starts again
        frames = (frames + [(t, labs, abstain)])[-7:]
        ask = np.arange(11)
        votes, seen, none = vb._count(ask)
        for i, tr in enumerate(ask):
            exp_votes = [sum(int(((t == tr) & (labs == lab)).sum()) for t, labs, _ in frames) for lab in range(4)]
            assert votes[i].tolist() == exp_votes
            assert seen[i] == sum(int((t == tr).sum()) for t, _, _ in frames)
            assert none[i] == sum(int(((t == tr) & (labs < 0)).sum()) for t, labs, a in frames if not a)


def test_the_assignment_without_the_hungarian_algorithm_publishes_what_it_would():
    """``_row_maxima`` takes each row's strict maximum when no two positive rows share it
    and hands the frame to the Hungarian algorithm otherwise: on random vote tables (counts, the
    current frame's half vote, ties, shared maxima, "no label" votes, more tracks than labels
    and fewer) what it publishes is what the Hungarian algorithm publishes, and both ways occur."""
    from scipy.optimize import linear_sum_assignment

    from dtm_labeler.labeling import voting
    rng = np.random.default_rng(3)
    fast = slow = 0
    for trial in range(600):
        n, M = int(rng.integers(1, 9)), int(rng.integers(1, 7))
        votes = rng.integers(0, 4, size=(n, M)).astype(float)
        votes[rng.random((n, M)) < 0.6] = 0.0
        seen = votes.sum(1) + rng.integers(0, 3, size=n)
        none = rng.integers(0, 3, size=n).astype(float) * (rng.random(n) < 0.3)
        cur = rng.integers(-1, M, size=n) if trial % 2 else np.full(n, -1)
        v = votes.copy()
        v[np.flatnonzero(cur >= 0), cur[cur >= 0]] += 0.5
        want, want_conf = np.full(n, -1), np.zeros(n)
        if v.any():
            r, c = linear_sum_assignment(-v)
            ok = (v[r, c] > 0) & (v[r, c] > none[r])
            want[r[ok]] = c[ok]
            want_conf[r[ok]] = np.minimum((v[r[ok], c[ok]] - 0.5 * (cur[r[ok]] == c[ok])) / np.maximum(seen[r[ok]], 1), 1)
        before = votes.copy()
        cols, clear = voting._row_maxima(votes, cur)
        if not clear:
            slow += 1
            continue
        fast += 1
        labels, conf = voting._published(votes, seen, none, cur, cols)
        assert np.array_equal(votes, before)                              # left as it was
        assert labels.tolist() == want.tolist(), (votes, cur)
        assert np.allclose(conf, want_conf)
    assert fast > 100 and slow > 100                                      # both ways were tried
