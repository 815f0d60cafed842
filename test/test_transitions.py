"""Synthesized transition paths (Ukita 4.2): FK of local rotations, end points (local maxima of
the pose similarity above the threshold), limb lengths along slerped paths, the P1-P2
curvature bound, and position interpolation for marker data."""
import numpy as np
import pytest
from scipy.ndimage import maximum_filter

from dtm_labeler.motion import load_clip
from dtm_labeler.training.transitions import (TransitionSettings, TransitionSource, angle_second_difference,
                                            bone_lengths, end_point_threshold, find_end_points, load_skeletal,
                                            local_bounds, normalized_poses, similarity_matrix,
                                            synthesize_transitions)

BVH = "cmu_skeletal/bvh_from_fbx/"
WALK, RUN, DANCE = (BVH + "cmu_07_01_walk_s07.bvh", BVH + "cmu_09_11_run_s09.bvh",
                    BVH + "cmu_55_01_dance-whirl_s55.bvh")


@pytest.fixture(scope="module")
def walk(data_dir):
    return TransitionSource.load(data_dir / WALK, (0, 200))


@pytest.fixture(scope="module")
def run(data_dir):
    return TransitionSource.load(data_dir / RUN, (0, 110))


@pytest.mark.parametrize("rel", [WALK, "cmu_skeletal/asf_amc/cmu_s05_pirouette-dance.amc"])
def test_local_rotations_reproduce_the_loader(data_dir, rel):
    sk = load_skeletal(data_dir / rel)
    clip = load_clip(data_dir / rel)
    assert sk.names == clip.names and sk.n_frames == clip.n_frames
    assert np.abs(sk.positions() - clip.positions).max() < 1e-9


def test_end_points_are_local_maxima_above_threshold(walk, run):
    s = TransitionSettings()
    Ya, Yb = normalized_poses(walk.clip.positions), normalized_poses(run.clip.positions)
    thr = end_point_threshold(Ya, Yb, s)
    ends = find_end_points(Ya, Yb, thr, s.peak_radius, None)
    assert len(ends) >= 2
    S = similarity_matrix(Ya, Yb)
    peak = maximum_filter(S, size=2 * s.peak_radius + 1, mode="constant", cval=-np.inf)
    for i, j, sc in ends:
        assert sc == pytest.approx(S[i, j])
        assert sc > -thr                                   # above the threshold
        assert S[i, j] >= peak[i, j] - 1e-12               # largest in its neighbourhood
        # the paper's score is -||y_i - y_j||; ours divides by sqrt(14)
        assert -np.linalg.norm(Ya[i] - Yb[j]) / np.sqrt(14) == pytest.approx(sc)
    # a stricter threshold keeps a subset
    strict = find_end_points(Ya, Yb, -ends[0][2] + 1e-9, s.peak_radius, None)
    assert [e[:2] for e in strict] == [ends[0][:2]]
    assert [e[2] for e in ends] == sorted((e[2] for e in ends), reverse=True)


def _check_curvature(path, a, b, s):
    """max |theta''| of the accepted path (with two real frames each side) <= the nearby
    real samples' max, recomputed here from the clips."""
    m = path.meta
    i, j = m["from_frame"], m["to_frame"]
    Ya, Yb = normalized_poses(a.clip.positions), normalized_poses(b.clip.positions)
    i0, j0 = m["end_point"]
    th = max(local_bounds(Ya, i0, s.window)[0], local_bounds(Yb, j0, s.window)[0])
    seq = np.concatenate([Ya[max(i - 2, 0):i], normalized_poses(path.positions), Yb[j + 1:j + 3]])
    dd = np.abs(angle_second_difference(seq))
    assert dd.size > 0
    assert dd.max() <= th + 1e-12
    assert m["path_theta_dd"] <= m["theta_dd_max"] + 1e-12


def test_slerp_paths_keep_limb_lengths_and_curvature_bound(data_dir):
    """Two parts of one recording (same skeleton): slerp of local rotations keeps every bone."""
    a = TransitionSource.load(data_dir / DANCE, (0, 500))
    b = TransitionSource.load(data_dir / DANCE, (900, 1400))
    s = TransitionSettings(max_pairs=3)
    rep = synthesize_transitions(a, b, s)
    assert rep.paths, "no accepted path"
    for p in rep.paths:
        assert p.meta["method"] == "slerp"
        L = bone_lengths(p.meta["skeletal_positions"], p.meta["skeletal_parents"])
        assert L.std(axis=0).max() < 1e-3                            # < 1 mm
        body = p.positions
        assert np.isfinite(body).all() and p.meta["synthesized_mask"].sum() == p.meta["n_inbetween"]
        src, dst = (a, b) if p.meta["from_frame"] < 500 else (b, a)
        # the path starts on the real pose it leaves
        k = p.meta["from_frame"] - int(src.clip.meta["frame_range"][0])
        assert np.allclose(body[0], src.clip.positions[k], atol=1e-9)
    # P3: both directions
    assert {p.meta["from_source"] for p in rep.paths} == {a.clip.source}


def test_cross_subject_paths(walk, run):
    s = TransitionSettings(bones="a")
    rep = synthesize_transitions(walk, run, s)
    assert rep.paths and rep.rejected >= 0
    for p in rep.paths:
        L = bone_lengths(p.meta["skeletal_positions"], p.meta["skeletal_parents"])
        assert L.std(axis=0).max() < 1e-3                            # one skeleton throughout
        a, b = (walk, run) if p.meta["from_class"] == "walk" else (run, walk)
        _check_curvature(p, a, b, s)
        assert p.meta["n_inbetween"] >= 1
    # morphing bones: every length moves monotonically from one subject's to the other's
    for p in synthesize_transitions(walk, run, TransitionSettings(bones="morph")).paths:
        L = bone_lengths(p.meta["skeletal_positions"], p.meta["skeletal_parents"])
        d = np.diff(L, axis=0)
        assert ((d >= -1e-9).all(0) | (d <= 1e-9).all(0)).all()


def test_rejected_pairs_never_violate_the_bound(walk, data_dir):
    dance = TransitionSource.load(data_dir / DANCE, (0, 400))
    s = TransitionSettings(max_widen=3)
    rep = synthesize_transitions(walk, dance, s)
    assert len(rep.paths) + rep.rejected == 2 * len(rep.end_points)
    for p in rep.paths:
        a, b = (walk, dance) if p.meta["from_class"] == "walk" else (dance, walk)
        _check_curvature(p, a, b, s)


def test_marker_data_position_interpolation(data_dir):
    """Marker recordings: body points interpolated linearly (root-centred, heading-normalised);
    equal steps no longer than y_max; limb lengths only approximately kept."""
    a = TransitionSource.load(data_dir / "markers_csv/mct_walk1_28markers_60hz.csv")
    b = TransitionSource.load(data_dir / "markers_csv/mct_dance1_28markers_60hz.csv", (0, 600))
    assert a.skeletal is None
    s = TransitionSettings(max_pairs=2)
    rep = synthesize_transitions(a, b, s)
    assert rep.paths
    for p in rep.paths:
        assert p.meta["method"] == "linear positions"
        Y = normalized_poses(p.positions)
        steps = np.linalg.norm(np.diff(Y, axis=0), axis=1)
        assert steps.max() <= p.meta["y_max"] * (1 + 1e-6) + 1e-9
        assert np.allclose(steps, steps[0], rtol=1e-6)               # equal steps (P2)
        P = p.positions
        thigh = np.linalg.norm(P[:, 8] - P[:, 10], axis=1)           # lhip - lknee
        assert thigh.std() / thigh.mean() < 0.05
        _check_curvature(p, a if p.meta["from_class"] == "walk" else b, b if p.meta["from_class"] == "walk" else a, s)
