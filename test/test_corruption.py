"""labeling.corruption: occlusion counts, ghosts, noise, shuffling, ids, reproducibility."""
import numpy as np
import pytest

from dtm_labeler.evaluation.corruption import corrupt_clip, occlusion_mask, score_frame, static_ghosts
from dtm_labeler.motion import synthesize


@pytest.fixture(scope="module")
def clip():
    c = synthesize(duration=2.0, rate=120.0, seed=3)
    c.positions[50:60, 4] = np.nan          # a gap in the clip itself
    return c


def test_clean_stream_is_the_clip_shuffled(clip):
    s = corrupt_clip(clip, seed=1)
    assert len(s) == clip.n_frames and s.names == clip.names and s.rate == clip.rate
    orders = set()
    for f in s:
        vis = np.flatnonzero(np.isfinite(clip.positions[f.index, :, 0]))
        assert sorted(f.truth) == list(vis)
        np.testing.assert_array_equal(f.xyz, clip.positions[f.index, f.truth])
        # label_to_index is the inverse of truth
        for m in range(clip.n_points):
            i = f.label_to_index[m]
            assert (i == -1) == (m not in vis)
            if i >= 0:
                assert f.truth[i] == m
        assert f.stamp == pytest.approx(f.index / clip.rate)
        orders.add(tuple(f.truth))
    assert len(orders) > len(s) // 2        # order changes from frame to frame
    unshuffled = corrupt_clip(clip, shuffle=False)
    assert all(list(f.truth) == sorted(f.truth) for f in unshuffled)


@pytest.mark.parametrize("gap_frames", [1.0, 8.0])
def test_occlusion_counts(clip, gap_frames):
    k = 3
    s = corrupt_clip(clip, occlude=k, seed=2, gap_frames=gap_frames)
    available = np.isfinite(clip.positions[..., 0])
    assert (s.occluded.sum(1) == k).all()
    assert not (s.occluded & ~available).any()            # only points that were there
    assert (s.visible == (available & ~s.occluded)).all()
    for f in s:
        assert f.n == available[f.index].sum() - k
        assert not s.occluded[f.index, f.truth].any()
    # every label gets hidden sometimes; longer gaps -> fewer on/off switches
    assert s.occluded.any(0).all()
    switches = np.abs(np.diff(s.occluded.astype(int), axis=0)).sum()
    if gap_frames > 1:
        base = corrupt_clip(clip, occlude=k, seed=2)
        assert switches < 0.5 * np.abs(np.diff(base.occluded.astype(int), axis=0)).sum()


def test_occlusion_never_more_than_available():
    avail = np.zeros((5, 6), dtype=bool)
    avail[:, :2] = True
    m = occlusion_mask(avail, 4, np.random.default_rng(0))
    assert (m.sum(1) == 2).all() and not (m & ~avail).any()
    with pytest.raises(ValueError):
        occlusion_mask(avail, 1, np.random.default_rng(0), gap_frames=0.5)


def test_ghosts_never_carry_a_true_label(clip):
    k = 4
    s = corrupt_clip(clip, clutter=k, seed=5)
    ghost_ids = set()
    for f in s:
        g = f.truth < 0
        assert g.sum() == k == f.n_ghosts
        assert not np.isin(np.flatnonzero(g), f.label_to_index).any()
        # near the body, not uniform noise: within offset range (+jitter) of some true point
        body = clip.positions[f.index][np.isfinite(clip.positions[f.index, :, 0])]
        d = np.linalg.norm(f.xyz[g][:, None] - body[None], axis=-1).min(1)
        assert (d < 0.3).all()
        ghost_ids |= set(f.ids[g].tolist())
        true_ids = set(f.ids[~g].tolist())
        assert not true_ids & set(f.ids[g].tolist())
    # short-lived tracks: several generations per slot over 2 s, but far fewer than frames
    assert k * 2 < len(ghost_ids) < k * len(s) / 5


def test_ghost_tracks_persist_and_move_with_the_body(clip):
    s = corrupt_clip(clip, clutter=2, seed=6)
    pos = {}
    for f in s:
        for i in np.flatnonzero(f.truth < 0):
            pos.setdefault(int(f.ids[i]), []).append(f.xyz[i])
    lives = [len(v) for v in pos.values()]
    assert np.median(lives) >= 0.1 * clip.rate * 0.9
    steps = np.concatenate([np.linalg.norm(np.diff(np.array(v), axis=0), axis=1) for v in pos.values()
                            if len(v) > 1])
    assert np.median(steps) < 0.03          # smooth track, not re-drawn each frame


def test_static_ghosts_stay_put_within_reach_of_the_body(clip):
    """Fixed reflections: one place for the whole take, on the floor or up to 2 m, horizontally
    within reach of the body's path; fed as extra points they are never labelled truth and
    keep one id."""
    g = static_ghosts(clip.positions, 6, seed=1, floor_share=0.5)
    assert g.shape == (clip.n_frames, 6, 3) and np.isfinite(g).all()
    assert (g == g[:1]).all()
    path = np.nanmedian(clip.positions, axis=1)
    lo, hi = path.min(0), path.max(0)
    assert ((g[0, :, :2] >= lo[:2] - 1.5) & (g[0, :, :2] <= hi[:2] + 1.5)).all()
    assert ((g[0, :, 2] >= 0) & (g[0, :, 2] <= 2.0)).all()
    assert (static_ghosts(clip.positions, 40, seed=2, floor_share=1.0)[0, :, 2] <= 0.02).all()
    assert static_ghosts(clip.positions, 0).shape == (clip.n_frames, 0, 3)
    with pytest.raises(ValueError):
        static_ghosts(clip.positions, -1)
    s = corrupt_clip(clip, extra=g, seed=4)
    ids = {i: set() for i in range(6)}
    for f in s:
        fake = np.flatnonzero(f.truth < 0)
        assert fake.size == 6
        for i in fake:
            k = int(np.flatnonzero((np.abs(g[0] - f.xyz[i]) < 1e-9).all(1))[0])
            ids[k].add(int(f.ids[i]))
    assert all(len(v) == 1 for v in ids.values())


def test_ids_persist_while_visible_and_change_after_gaps(clip):
    s = corrupt_clip(clip, occlude=1, gap_frames=5.0, seed=7)
    last = {}
    for f in s:
        for i, m in enumerate(f.truth):
            m = int(m)
            if m in last and s.visible[f.index - 1, m]:
                assert f.ids[i] == last[m]
            elif m in last:
                assert f.ids[i] != last[m]
            last[m] = int(f.ids[i])
        assert len(set(f.ids.tolist())) == f.n
        assert (f.ids >= 0).all() and (f.ids < 2**32).all()
    # the clip's own gap (label 4, frames 50..59) ends the track too
    before = s[49].ids[s[49].label_to_index[4]] if s[49].label_to_index[4] >= 0 else None
    after = s[60].ids[s[60].label_to_index[4]] if s[60].label_to_index[4] >= 0 else None
    if before is not None and after is not None:
        assert before != after


def test_noise_level(clip):
    s = corrupt_clip(clip, noise_mm=5.0, seed=8)
    err = np.concatenate([f.xyz - clip.positions[f.index, f.truth] for f in s])
    assert np.std(err) * 1e3 == pytest.approx(5.0, rel=0.05)
    assert abs(np.mean(err)) < 5e-4


def test_reproducible_and_independent_effects(clip):
    a = corrupt_clip(clip, occlude=2, clutter=3, noise_mm=2.0, seed=11)
    b = corrupt_clip(clip, occlude=2, clutter=3, noise_mm=2.0, seed=11)
    c = corrupt_clip(clip, occlude=2, clutter=3, noise_mm=2.0, seed=12)
    for fa, fb in zip(a, b):
        np.testing.assert_array_equal(fa.xyz, fb.xyz)
        np.testing.assert_array_equal(fa.truth, fb.truth)
        np.testing.assert_array_equal(fa.ids, fb.ids)
    assert any(not np.array_equal(fa.truth, fc.truth) for fa, fc in zip(a, c))
    # noise does not change which points are hidden
    d = corrupt_clip(clip, occlude=2, clutter=3, noise_mm=0.0, seed=11)
    np.testing.assert_array_equal(a.occluded, d.occluded)


def test_score_frame_and_errors(clip):
    labels = np.array([0, 1, -1, 2, -1])
    truth = np.array([0, 2, -1, 2, -1])
    assert score_frame(labels, truth) == (2, 3, 2, 2)
    with pytest.raises(ValueError):
        corrupt_clip(clip, occlude=-1)
    with pytest.raises(ValueError):
        corrupt_clip(clip, clutter=1, ghost_life_s=(0.0, 0.1))
