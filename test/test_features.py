"""Eq. 12 features, observation patterns and heading canonicalisation."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from dtm_labeler.model.features import (FEATURE_DIM, FEATURE_MATRIX, FULL, MISSING, N_PATTERNS,
                                        POSITION_ONLY, STATE_DIM, canonicalise, feature_map_for,
                                        lateral_yaw, observation_state, observed_map, pattern_codes,
                                        pattern_id, point_states, rotation_z, triangle_features)
from dtm_labeler.training.train import canonical_states, heading_pairs
from dtm_labeler.motion.pointsets import BODY14
from dtm_labeler.motion.synthetic import synthesize

ANGLES = st.floats(-np.pi, np.pi, allow_nan=False)


def _state(p, v):
    return np.r_[p, v].astype(float)


def test_feature_matrix_is_eq12_on_a_hand_example():
    A = _state([1, 2, 3], [10, 20, 30])
    B = _state([4, 6, 8], [11, 21, 31])
    C = _state([0, -1, 5], [12, 22, 32])
    s = np.stack([A, B, C])                    # (3 points, 6)
    X = triangle_features(s, (0, 1, 2))
    expected = [10, 11, 12,  20, 21, 22,  30, 31, 32,          # vAx vBx vCx vAy vBy vCy vAz vBz vCz
                4 - 1, 0 - 1, 6 - 2, -1 - 2, 8 - 3, 5 - 3]      # pBx-pAx pCx-pAx pBy-pAy pCy-pAy ...
    assert np.array_equal(X, expected)
    assert FEATURE_MATRIX.shape == (FEATURE_DIM, 3 * STATE_DIM)
    assert np.array_equal(FEATURE_MATRIX @ np.r_[A, B, C], expected)
    # vertex order matters: (B, A, C) measures positions from B
    X2 = triangle_features(s, (1, 0, 2))
    assert np.array_equal(X2[:3], [11, 10, 12]) and np.array_equal(X2[9:11], [1 - 4, 0 - 4])
    # batch shape (..., N, 6) -> (..., 15)
    assert triangle_features(np.stack([s, s + 1]), (0, 1, 2)).shape == (2, 15)
    # null space of F is exactly the common translation (3-D)
    assert np.linalg.matrix_rank(FEATURE_MATRIX) == 15


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 31), shift=st.lists(st.floats(-50, 50), min_size=3, max_size=3))
def test_translation_invariance(seed, shift):
    rng = np.random.default_rng(seed)
    s = rng.normal(size=(7, 6))
    moved = s.copy()
    moved[:, :3] += shift
    for tri in [(0, 1, 2), (6, 3, 1), (2, 5, 4)]:
        np.testing.assert_allclose(triangle_features(moved, tri), triangle_features(s, tri), atol=1e-9)


def test_point_states_and_observation_codes():
    pos = np.array([[[0, 0, 0], [1, 1, 1]],
                    [[0.01, 0, 0], [np.nan] * 3],
                    [[0.03, 0, 0], [1, 1, 1.02]]])
    s = point_states(pos, 100.0)
    assert s.shape == (3, 2, 6)
    assert np.isnan(s[0, :, 3:]).all()                       # first frame: no velocity
    np.testing.assert_allclose(s[1, 0, 3:], [1.0, 0, 0])     # m/s
    np.testing.assert_allclose(s[2, 0, 3:], [2.0, 0, 0])
    assert np.isnan(s[2, 1, 3:]).all()                       # predecessor missing
    codes = observation_state(s)
    assert codes.tolist() == [[POSITION_ONLY, POSITION_ONLY], [FULL, MISSING], [FULL, POSITION_ONLY]]


def test_pattern_ids_round_trip():
    seen = set()
    for pid in range(N_PATTERNS):
        c = pattern_codes(pid)
        assert all(x in (MISSING, POSITION_ONLY, FULL) for x in c)
        assert pattern_id(np.array(c)) == pid
        seen.add(c)
    assert len(seen) == 27
    codes = np.array([[0, 0, 0], [2, 2, 2], [1, 0, 2]])
    assert pattern_id(codes).tolist() == [0, 26, 1 + 18]


@pytest.mark.parametrize("pid", range(N_PATTERNS))
def test_observed_map_dims_and_exact_feature_map(pid):
    codes = pattern_codes(pid)
    G = observed_map(codes)
    n_full = sum(c == FULL for c in codes)
    n_obs = sum(c != MISSING for c in codes)
    assert G.shape == (3 * n_full + 3 * max(n_obs - 1, 0), 18)
    if G.shape[0] == 0:
        return
    # translation invariant, and touches only observed coordinates
    T = np.tile(np.r_[1.0, 2.0, 3.0, 0, 0, 0], 3)
    assert np.allclose(G @ T, 0)
    for v in range(3):
        if codes[v] == MISSING:
            assert not G[:, v * 6:(v + 1) * 6].any()
        if codes[v] == POSITION_ONLY:
            assert not G[:, v * 6 + 3:(v + 1) * 6].any()
    assert np.linalg.matrix_rank(G) == G.shape[0]
    M = feature_map_for(G)
    assert M.shape == (G.shape[0], 15)
    np.testing.assert_allclose(M @ FEATURE_MATRIX, G, atol=1e-12)
    # y = G s = M X for random states, including NaN-free garbage in unobserved slots
    s = np.random.default_rng(pid).normal(size=(5, 18))
    np.testing.assert_allclose(s @ G.T, (s @ FEATURE_MATRIX.T) @ M.T, atol=1e-9)


def test_feature_map_rejects_non_invariant_maps():
    G = np.zeros((1, 18))
    G[0, 0] = 1.0                             # absolute pAx is not a function of X
    with pytest.raises(AssertionError):
        feature_map_for(G)


def test_full_pattern_is_eq12_itself():
    G = observed_map((FULL, FULL, FULL))
    M = feature_map_for(G)
    # same information as X: M is invertible (a reordering of eq. 12)
    assert abs(abs(np.linalg.det(M)) - 1.0) < 1e-9


# ---------------------------------------------------------------- heading
def _toy_body(yaw, centre=(0.3, -1.2, 0.0)):
    """Two left/right pairs (hips, shoulders) and a nose point in front, facing ``yaw``."""
    body = np.array([[0, 0.1, 1.0], [0, -0.1, 1.0],     # lhip, rhip  (left on +y when facing +x)
                     [0, 0.2, 1.5], [0, -0.2, 1.5],     # lshoulder, rshoulder
                     [0.1, 0.0, 1.7]])                  # nose, in front
    R = rotation_z(np.float64(yaw))
    return body @ R.T + np.asarray(centre)


PAIRS = np.array([[0, 1], [2, 3]])


@settings(max_examples=50, deadline=None)
@given(yaw=ANGLES)
def test_lateral_yaw_recovers_facing_and_canonicalise_faces_plus_x(yaw):
    P = _toy_body(yaw)
    got = lateral_yaw(P, PAIRS)
    assert abs(np.angle(np.exp(1j * (got - yaw)))) < 1e-9
    s = np.concatenate([P, np.tile([1.3 * np.cos(yaw), 1.3 * np.sin(yaw), 0.0], (5, 1))], 1)
    c = canonicalise(s[None], np.array([got]))[0]
    assert abs(lateral_yaw(c[:, :3], PAIRS)) < 1e-9
    assert c[4, 0] > c[0, 0]                                 # nose in front (+x)
    np.testing.assert_allclose(c[:, 3:], np.tile([1.3, 0, 0], (5, 1)), atol=1e-9)   # walking along +x
    np.testing.assert_allclose(c[:, 2], P[:, 2])              # heights unchanged


def test_lateral_yaw_missing_pairs():
    P = _toy_body(0.7)
    P[0] = np.nan                                            # lhip missing: shoulders still give yaw
    assert abs(lateral_yaw(P, PAIRS) - 0.7) < 1e-9
    P[3] = np.nan                                            # rshoulder too: no complete pair
    assert np.isnan(lateral_yaw(P, PAIRS))
    assert np.isnan(lateral_yaw(P, np.zeros((0, 2))))
    # NaN yaw leaves the frame as it is
    s = np.concatenate([_toy_body(0.7), np.ones((5, 3))], 1)
    np.testing.assert_array_equal(canonicalise(s, np.array(np.nan)), s)


def test_rotation_z():
    R = rotation_z(np.array([0.3, -2.0]))
    assert R.shape == (2, 3, 3)
    for r in R:
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert abs(np.linalg.det(r) - 1) < 1e-12
    np.testing.assert_allclose(rotation_z(np.float64(np.pi / 2)) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


@settings(max_examples=15, deadline=None)
@given(yaw=ANGLES, dx=st.floats(-5, 5), dy=st.floats(-5, 5))
def test_canonical_features_are_heading_invariant(yaw, dx, dy):
    """Rotating (and moving) a whole recording about z leaves the canonical eq. 12 features unchanged."""
    clip = synthesize(duration=0.25, rate=120.0, heading=0.4, seed=3, noise_mm=1.0)
    pairs = heading_pairs(BODY14)
    assert len(pairs) == 6
    ref = canonical_states(clip, pairs)
    moved = clip._replace(positions=clip.positions @ rotation_z(np.float64(yaw)).T + [dx, dy, 0.0])
    out = canonical_states(moved, pairs)
    for tri in [(0, 1, 2), (8, 9, 10), (7, 3, 12)]:
        np.testing.assert_allclose(triangle_features(out[1:], tri), triangle_features(ref[1:], tri), atol=1e-7)
    # the facing direction is +x after canonicalisation: the walker moves along +x
    v = out[1:, :, 3:].mean(axis=(0, 1))
    assert v[0] > 1.0 and abs(v[1]) < 0.15
