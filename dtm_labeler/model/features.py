"""Per-point states, heading canonicalisation and the triangle feature of eq. 12.

Point state
    Each point carries a 6-vector ``(px, py, pz, vx, vy, vz)``: position in metres and
    velocity in m/s from consecutive frames (``(x[t] - x[t-1]) * rate``), so a model trained
    at 120 Hz applies at 60 or 200 Hz. A point seen for the first time has no velocity
    (NaN); a missing point has neither.

Triangle feature (eq. 12)
    For a triangle ``(A, B, C)`` the 15-D feature is::

        X = (vAx, vBx, vCx, vAy, vBy, vCy, vAz, vBz, vCz,
             pBx-pAx, pCx-pAx, pBy-pAy, pCy-pAy, pBz-pAz, pCz-pAz)

    i.e. ``X = F s`` for the stacked triple state ``s = (state_A, state_B, state_C)``
    (18-D) and a fixed 15 x 18 matrix ``F``. ``F`` spans every translation-invariant
    linear function of ``s``; its null space is the common translation.

Observation patterns
    Each vertex of a triangle is *missing* (0), *position only* (1) or *position and
    velocity* (2): 27 patterns. For a pattern, the observable, translation-invariant
    quantities are the velocities of the vertices that have one and the positions of the
    observed vertices relative to the first observed one: ``y = G s``. Because the rows
    of ``G`` lie in the row space of ``F``, ``y = M X`` with ``M = G F^+`` exactly, so the
    density of ``y`` is the triangle mixture pushed through the linear map ``M``
    (marginalisation, eq. 30-31) -- one primitive for missing markers, first-seen points
    and the conditionals ``P(A|B,C) = P(A,B,C) / P(B,C)``.

Heading invariance (invariant features, not augmentation)
    People walk in every direction. We canonicalise each frame about the vertical axis:
    the body's lateral axis is the mean horizontal vector from right to left points of
    the left/right pairs (``lhip``/``rhip``, ``LSHO``/``RSHO`` ...); the facing direction is
    that axis turned by -90 deg; positions and velocities are rotated so the body faces +x.
    At training time this uses the true labels; at labeling time each candidate labeling
    canonicalises with *its own* labelled pairs, so a wrong left/right assignment also
    gets a wrong heading and fits badly. We prefer this over rotation augmentation because
    augmentation smears every triangle density over all headings (the mixture must spend
    components on a ring) and weakens exactly the left/right cues the labeler needs; the
    invariant frame keeps the model as sharp as a fixed-heading one. The heading is
    quantised to ``heading_bins`` (default 720, 0.5 deg) only to cache triangle terms; a
    small yaw jitter at training time keeps the model tolerant to heading noise.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

STATE_DIM = 6
FEATURE_DIM = 15                    # eq. 12: nine velocities + six relative positions
TRIPLE_DIM = 3 * STATE_DIM          # a triangle's three stacked point states
MISSING, POSITION_ONLY, FULL = 0, 1, 2
N_PATTERNS = 27


def point_states(positions: np.ndarray, rate: float) -> np.ndarray:
    """(F, N, 3) positions -> (F, N, 6) states with backward-difference velocities (m/s)."""
    positions = np.asarray(positions, dtype=np.float64)
    vel = np.full_like(positions, np.nan)
    vel[1:] = (positions[1:] - positions[:-1]) * float(rate)
    return np.concatenate([positions, vel], axis=-1)


def observation_state(states: np.ndarray) -> np.ndarray:
    """Per-point observation code (MISSING / POSITION_ONLY / FULL) of (..., 6) states."""
    has_p = np.isfinite(states[..., :3]).all(-1)
    has_v = np.isfinite(states[..., 3:]).all(-1)
    return np.where(has_p, np.where(has_v, FULL, POSITION_ONLY), MISSING).astype(np.int8)


# -- heading ---------------------------------------------------------------------------
def lateral_yaw(positions: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Facing yaw (rad) from left/right pairs.

    ``positions`` is (..., N, 3); ``pairs`` is (Q, 2) of (left, right) point indices. The
    lateral axis is the mean of ``p_left - p_right`` over pairs where both are seen
    (horizontal part); facing = lateral turned by -90 deg (a body facing +x has its left
    on +y). Returns NaN where no pair is seen.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if pairs.size == 0:
        return np.full(positions.shape[:-2], np.nan)
    d = positions[..., pairs[:, 0], :2] - positions[..., pairs[:, 1], :2]   # (..., Q, 2)
    ok = np.isfinite(d).all(-1)
    d = np.where(ok[..., None], d, 0.0).sum(-2)
    yaw = np.arctan2(-d[..., 0], d[..., 1])          # facing = (ly, -lx)
    return np.where(ok.any(-1), yaw, np.nan)


def rotation_z(yaw: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about +z by ``yaw``."""
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def canonicalise(states: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Rotate (..., N, 6) states by ``-yaw`` about z (so the body faces +x).

    ``yaw`` has the leading shape of ``states`` without (N, 6); NaN yaw leaves a frame as is.
    """
    yaw = np.nan_to_num(np.asarray(yaw, dtype=np.float64), nan=0.0)
    R = rotation_z(-yaw)                                            # (..., 3, 3)
    out = np.empty_like(states)
    out[..., :3] = np.einsum("...ij,...nj->...ni", R, states[..., :3])
    out[..., 3:] = np.einsum("...ij,...nj->...ni", R, states[..., 3:])
    return out


# -- eq. 12 and its patterns -----------------------------------------------------------
def _feature_matrix() -> np.ndarray:
    F = np.zeros((FEATURE_DIM, 3 * STATE_DIM))
    row = 0
    for axis in range(3):                  # vAx vBx vCx vAy vBy vCy vAz vBz vCz
        for v in range(3):
            F[row, v * STATE_DIM + 3 + axis] = 1.0
            row += 1
    for axis in range(3):                  # pBx-pAx pCx-pAx pBy-pAy ...
        for v in (1, 2):
            F[row, v * STATE_DIM + axis] = 1.0
            F[row, axis] = -1.0
            row += 1
    return F


FEATURE_MATRIX = _feature_matrix()
_F_PINV = np.linalg.pinv(FEATURE_MATRIX)


def triangle_features(states: np.ndarray, triangle: Sequence[int]) -> np.ndarray:
    """Eq. 12 features (..., 15) of the triangle ``(A, B, C)`` from (..., N, 6) states."""
    s = states[..., list(triangle), :].reshape(*states.shape[:-2], 3 * STATE_DIM)
    return s @ FEATURE_MATRIX.T


def pattern_id(codes: np.ndarray) -> np.ndarray:
    """Pattern index 0..26 from (..., 3) per-vertex observation codes."""
    codes = np.asarray(codes, dtype=np.int64)
    return codes[..., 0] + 3 * codes[..., 1] + 9 * codes[..., 2]


def pattern_codes(pid: int) -> tuple[int, int, int]:
    return (pid % 3, (pid // 3) % 3, pid // 9)


def observed_map(codes: Sequence[int]) -> np.ndarray:
    """``G`` (m x 18): observable translation-invariant quantities for vertex codes.

    Rows: velocities of the vertices with FULL state, then positions of the observed
    vertices relative to the first observed one. ``m = 3*#FULL + 3*max(#observed-1, 0)``.
    """
    rows = []
    observed = [v for v in range(3) if codes[v] != MISSING]
    for v in range(3):
        if codes[v] == FULL:
            for axis in range(3):
                r = np.zeros(3 * STATE_DIM)
                r[v * STATE_DIM + 3 + axis] = 1.0
                rows.append(r)
    for v in observed[1:]:
        for axis in range(3):
            r = np.zeros(3 * STATE_DIM)
            r[v * STATE_DIM + axis] = 1.0
            r[observed[0] * STATE_DIM + axis] = -1.0
            rows.append(r)
    return np.array(rows).reshape(len(rows), 3 * STATE_DIM)


def feature_map_for(G: np.ndarray) -> np.ndarray:
    """``M`` with ``G = M F`` (so ``y = G s = M X``); exact for translation-invariant G."""
    M = G @ _F_PINV
    assert np.allclose(M @ FEATURE_MATRIX, G, atol=1e-9), "G must be translation invariant"
    return M


#: eq. 12 feature -> the parents' (B, C) part of it: the denominator of a triangle's conditional
#: (eq. 13), for densities of the full feature's marginal over the parents
PARENTS_MAP = feature_map_for(observed_map((MISSING, FULL, FULL)))
