"""A tilted body stood upright, a bent one pitched back: more starts for a search from scratch.

The eq. 12 features are read in a frame turned about the vertical only -- the body's facing,
as in the frames the mixtures were trained on (section III.B) -- so a body leaning far from
vertical (a cartwheel, a handstand's way down, breakdance on the floor) shows each triangle at
an angle its mixture has hardly seen. The right labeling then still fits better than the
wrong ones where the body terms hold it (a bone keeps its length whatever the tilt), but the
GA's model-guided start (eq. 15-17: each label drawn by its triangle's term) rarely draws it,
and the search settles on an upright reading of the tilted cloud: CMU 85's breakdance on the
floor under a model of standing takes, frames of a 30-45 deg lean, cold searches 0-32 % right
at 187-218 nats against the truth's 243-299.

So a search from scratch also runs on the frame's points turned upright -- about their
centroid, by the smallest rotation that takes their long axis (the first principal axis of the
positions, its end nearer the vertical kept up) onto the vertical; velocities turn with them --
and the labeling it finds there is scored, and swept, on the frame as it is. It is taken only
when it fits better there, so an upright body loses nothing but the time of a search (none when
the long axis is within ``MIN_TILT_DEG`` of vertical). Measured on 12 frames of that take
(every 30th of ``dtm-eval``'s floor-moves stream, the long axis 18-50 deg off vertical): the search
on the turned points 100 % right at the truth's fitness in 6 of them, the search alone in 1;
the stream figures are in :meth:`~dtm_labeler.labeling.tracked.TrackedLabeler._upright_check`.

A body upside down (a handstand) has a vertical long axis and is not turned by it -- which end
is the head the points alone do not say. The bent body's starts below cover it: pitched back
twice as far (``BEND_PITCHES_DEG``) when the first pitch still fits poorly.

A long axis is a body's height only while the limbs are not spread wider than it is tall; when
they are (arms stretched in a T), the rotation lays the body down, the search there finds
nothing better and the frame keeps its labeling.

A body bent at the hips (touching the toes, picking something up) is not turned by its long
axis: legs upright and a trunk leaning 60-100 deg forward give an axis near vertical, or one
that stands neither half up. The trunk's triangles then meet their mixtures at an angle they
have hardly seen, and cold searches read the trunk upside down (CMU 85's breakdance stand-up
under a model of the jump + twist, 41 markers, trunk bent 57-101 deg: 39-71 % right, the truth
46-125 nats better). So a search that still fits poorly after its other starts also runs on the
frame pitched back by ``BEND_PITCHES_DEG[0]`` (60 deg) about a few horizontal axes (:func:`bent_problems`):
which way the trunk leans the points alone do not say, and the right turn need not be exact --
the result is swept on the frame as it is, where the legs come back. One of four azimuths
(90 deg apart) comes within 45 deg of any facing. A body whose trunk is past horizontal -- the
head below the pelvis in a flip or a roll -- is not brought near upright by 60 deg; when the
search still fits poorly after those starts, the frame is pitched back by 120 deg about the
same axes (CMU 85's jump + twist, frames of its flip under a model of the same person's
breakdance: cold searches 13-31 labels of 41 wrong with the truth up to 44 nats better; pitched
back 120 deg, 3-5 wrong).
"""
from __future__ import annotations

import numpy as np

from ..model.features import STATE_DIM
from .problem import FrameProblem

#: long axis within this many degrees of vertical: the body counts as upright, no second start
MIN_TILT_DEG = 15.0
#: points a long axis is read from, at least
MIN_POINTS = 4
#: degrees a bent body's frame is pitched back (:func:`bent_problems`), in turn while the search
#: still fits poorly: a trunk bent 57-101 deg forward, pitched back 60 deg from within 45 deg of
#: its facing, was read 83-98 % right; a body upside down in a flip (the trunk 116-153 deg from
#: the vertical, the head below the pelvis) needs the second
BEND_PITCHES_DEG = (60.0, 120.0)

__all__ = ["MIN_TILT_DEG", "BEND_PITCHES_DEG", "long_axis", "leaning_axis", "rotation_to_up", "upright_rotation",
           "upright_problems", "turned_problem", "pitch_back", "bent_problems"]


def long_axis(xyz: np.ndarray) -> np.ndarray | None:
    """(3,) unit long axis (first principal axis) of the points ``xyz`` (n, 3; NaN rows ignored),
    its end nearer +z first; None with fewer than ``MIN_POINTS`` points."""
    x = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    x = x[np.isfinite(x).all(1)]
    if x.shape[0] < MIN_POINTS:
        return None
    _, vecs = np.linalg.eigh(np.cov((x - x.mean(0)).T))
    return vecs[:, -1] * (1.0 if vecs[2, -1] >= 0 else -1.0)


def _cross_matrix(k: np.ndarray) -> np.ndarray:
    """(3, 3) ``K`` with ``K @ v = k x v`` (the Rodrigues formula's matrix)."""
    return np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])


def rotation_to_up(axis: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking the unit ``axis`` (its z >= 0) onto +z (Rodrigues)."""
    cos = float(np.clip(axis[2], -1.0, 1.0))
    K = _cross_matrix(np.array([axis[1], -axis[0], 0.0]))  # axis x z: the rotation's axis, |k| = sin
    return np.eye(3) + K + K @ K / (1.0 + cos)


def tilt_deg(axis: np.ndarray) -> float:
    """Degrees between ``axis`` (unit, z >= 0) and the vertical."""
    return float(np.degrees(np.arccos(np.clip(axis[2], -1.0, 1.0))))


def leaning_axis(xyz: np.ndarray, min_tilt_deg: float = MIN_TILT_DEG) -> np.ndarray | None:
    """The long axis of the points ``xyz`` (:func:`long_axis`) when it leans at least
    ``min_tilt_deg`` off vertical; None when it cannot be read or stands upright."""
    axis = long_axis(xyz)
    return None if axis is None or tilt_deg(axis) < min_tilt_deg else axis


def upright_rotation(xyz: np.ndarray, min_tilt_deg: float = MIN_TILT_DEG) -> np.ndarray | None:
    """(3, 3) the smallest rotation taking the long axis of the points ``xyz`` onto +z, its end
    nearer +z kept up; None when it cannot be read or is within ``min_tilt_deg`` of vertical
    (:func:`leaning_axis`, module doc)."""
    axis = leaning_axis(xyz, min_tilt_deg)
    return None if axis is None else rotation_to_up(axis)


def upright_problems(problem: FrameProblem, min_tilt_deg: float = MIN_TILT_DEG,
                     body: np.ndarray | None = None, distinct_deg: float = 10.0) -> list[FrameProblem]:
    """``problem``'s frame turned upright (every point and velocity, about the centroid of the
    points the axis is read from), under the same model and background: by the long axis of the
    points ``body`` (point indices; all when None) when it leans more than ``min_tilt_deg``, and
    then also by the long axis of all the points when that differs by more than
    ``distinct_deg``. Empty when the body points stand upright.

    The labeler passes the points a search labelled: a ghost or two in a frame of 14 points tilt
    the axis of all of them by 20 deg and more, and the search leaves them out -- but a search
    that misread a leaning body also leaves some of its points out (CMU 85's breakdance: 9 of
    41, their axis 19 deg off vertical where all 41 lean 44 deg), so both are tried."""
    states = problem.states[:-1]
    pts = states[:, :3] if body is None else states[np.asarray(body, dtype=np.int64), :3]
    axis = leaning_axis(pts, min_tilt_deg)
    if axis is None:
        return []
    starts = [(axis, pts)]
    if body is not None:
        whole = long_axis(states[:, :3])
        if whole is not None and np.degrees(np.arccos(np.clip(abs(whole @ axis), 0.0, 1.0))) > distinct_deg:
            starts.append((whole, states[:, :3]))
    return [turned_problem(problem, rotation_to_up(ax), np.nanmean(p, axis=0)) for ax, p in starts]


def turned_problem(problem: FrameProblem, R: np.ndarray, centre: np.ndarray) -> FrameProblem:
    """``problem``'s frame turned by the rotation ``R`` (3, 3) about ``centre`` (every point and
    velocity), under the same model and background."""
    states = problem.states[:-1]
    turned = np.empty_like(states)
    turned[:, :3] = (states[:, :3] - centre) @ R.T + centre
    turned[:, 3:STATE_DIM] = states[:, 3:STATE_DIM] @ R.T
    return FrameProblem(problem.model, turned, problem.background, heading_snap_deg=float(np.degrees(problem.snap)),
                        rest_s=problem.rest_s)


def pitch_back(azimuth: float, pitch_deg: float) -> np.ndarray:
    """(3, 3) the rotation about the horizontal axis square to the azimuth ``azimuth`` (radians
    from +x) that lifts a direction leaning that way by ``pitch_deg`` (Rodrigues)."""
    d = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    K = _cross_matrix(np.cross(d, [0.0, 0.0, 1.0]))     # turning about it by +angle lifts d
    a = np.radians(pitch_deg)
    return np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * K @ K


def bent_problems(problem: FrameProblem, starts: int, pitch_deg: float = BEND_PITCHES_DEG[0]) -> list[FrameProblem]:
    """``problem``'s frame pitched back by ``pitch_deg`` about the centroid of its points, once
    for each of ``starts`` azimuths spread evenly round the vertical (module doc: a body bent at
    the hips, its trunk's facing unknown). Empty with fewer than ``MIN_POINTS`` points."""
    xyz = problem.states[:-1, :3]
    if starts <= 0 or np.isfinite(xyz).all(1).sum() < MIN_POINTS:
        return []
    centre = np.nanmean(xyz, axis=0)
    return [turned_problem(problem, pitch_back(2.0 * np.pi * k / starts, pitch_deg), centre) for k in range(starts)]
