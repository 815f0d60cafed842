"""A wrist bar's two ends exchanged over a stretch of a real take, turned back by the take's order
votes (labeling/bar_flips.py): HDM05's 41 markers, half of them hidden at a time, the capture's
trajectories as tracks."""
import numpy as np
import pytest

from dtm_labeler.labeling.bar_flips import bar_stretches, flip_bars
from dtm_labeler.labeling.rigid_tracks import track_pieces
from dtm_labeler.motion.load import load_clip
from test_gappy_training import HDM, _gapped
from test_rigid_tracks import channel_tracks

#: the left wrist bar's rows (x, near, far): the shoulder, upper arm and finger nearer the radial end
ROWS = [("LSHO", "LWRA", "LWRB"), ("LUPA", "LWRA", "LWRB"), ("LFIN", "LWRA", "LWRB")]


@pytest.fixture(scope="module")
def take(data_dir):
    """Per frame: points, true labels, track ids (one per seen run of a channel)."""
    clip = load_clip(data_dir / HDM)
    clip = _gapped(clip.slice(2960, 3560), missing=0.5, seed=1, gap_s=0.25)
    names = list(clip.names)
    xyz, truth, tracks = channel_tracks(clip)
    rows = np.array([[names.index(n) for n in row] for row in ROWS])
    return dict(xyz=xyz, truth=truth, tracks=tracks, names=names, rows=rows, bar=tuple(rows[0, 1:]),
                P=clip.positions)


def _exchanged(labels, stretches, bar):
    out = [lab.copy() for lab in labels]
    a, b = bar
    for first, last in stretches:
        for f in range(first, last + 1):
            ia, ib = out[f] == a, out[f] == b
            out[f][ia], out[f][ib] = b, a
    return out


def _shown(take, stretch, rows):
    """Frames of ``stretch`` whose points show each of ``rows``."""
    P = take["P"][stretch[0]:stretch[1] + 1]
    return [int(np.isfinite(P[:, list(r), 0]).all(1).sum()) for r in rows]


def test_the_rows_hold_on_the_true_labels(take):
    P = take["P"]
    for x, near, far in take["rows"]:
        d_near = np.linalg.norm(P[:, x] - P[:, near], axis=1)
        d_far = np.linalg.norm(P[:, x] - P[:, far], axis=1)
        ok = np.isfinite(d_near) & np.isfinite(d_far)
        assert ok.sum() > 50 and (d_near[ok] < d_far[ok]).mean() > 0.99


def test_stretches_cover_every_end_once(take):
    stretches = bar_stretches(track_pieces(take["tracks"], take["truth"])[0], take["truth"], take["bar"])
    assert len(stretches) > 3
    covered = np.zeros(len(take["truth"]), dtype=int)
    for first, last in stretches:
        assert first <= last
        covered[first:last + 1] += 1
    holds = np.array([np.isin(lab, take["bar"]).any() for lab in take["truth"]])
    assert (covered <= 1).all() and (covered[holds] == 1).all()
    starts = [s for s, _ in stretches]
    assert starts == sorted(starts)


def test_true_labels_stay(take):
    out, flips = flip_bars(take["xyz"], take["tracks"], take["truth"], take["rows"], len(take["names"]))
    assert flips == 0
    assert all((o == t).all() for o, t in zip(out, take["truth"]))


def _shown_stretches(take, rows, min_frames=4):
    """The stretches in which every one of ``rows`` is shown in ``min_frames`` frames or more."""
    return [s for s in bar_stretches(track_pieces(take["tracks"], take["truth"])[0], take["truth"], take["bar"])
            if min(_shown(take, s, rows)) >= min_frames]


def test_an_exchanged_bar_is_turned_back(take):
    stretches = _shown_stretches(take, take["rows"][:2])
    assert len(stretches) >= 2
    wrong = _exchanged(take["truth"], stretches[:2], take["bar"])
    out, flips = flip_bars(take["xyz"], take["tracks"], wrong, take["rows"], len(take["names"]))
    assert flips == 2
    assert all((o == t).all() for o, t in zip(out, take["truth"]))


def test_one_partner_alone_does_not_turn_a_bar(take):
    """A partner's order over a stretch can be a pose the take holds: one partner label's say is
    clipped below the gain a flip needs, two agreeing reach it."""
    two = take["rows"][:2]
    stretches = _shown_stretches(take, two, min_frames=10)
    assert stretches
    wrong = _exchanged(take["truth"], stretches[:1], take["bar"])
    _, flips = flip_bars(take["xyz"], take["tracks"], wrong, two[:1], len(take["names"]))
    assert flips == 0
    out, flips = flip_bars(take["xyz"], take["tracks"], wrong, two, len(take["names"]))
    assert flips == 1 and all((o == t).all() for o, t in zip(out, take["truth"]))


def test_one_segments_markers_are_one_partner(take):
    """The head's markers turn together: two of them ordering the bar are one pose's say (with the
    segment clusters as ``groups``), not two partners'."""
    names = take["names"]
    head = np.array([[names.index(x), *take["bar"]] for x in ("LFHD", "LBHD")])
    P = take["P"]
    for x, near, far in head:
        d_near, d_far = (np.linalg.norm(P[:, x] - P[:, e], axis=1) for e in (near, far))
        ok = np.isfinite(d_near) & np.isfinite(d_far)
        assert (d_near[ok] < d_far[ok]).mean() > 0.99                # both hold on the true labels
    stretches = _shown_stretches(take, head, min_frames=10)
    assert stretches
    wrong = _exchanged(take["truth"], stretches[:1], take["bar"])
    _, flips = flip_bars(take["xyz"], take["tracks"], wrong, head, len(names))
    assert flips == 1
    groups = np.full(len(names), -1)
    groups[[names.index(x) for x in ("LFHD", "RFHD", "LBHD", "RBHD")]] = 0
    _, flips = flip_bars(take["xyz"], take["tracks"], wrong, head, len(names), groups=groups)
    assert flips == 0
