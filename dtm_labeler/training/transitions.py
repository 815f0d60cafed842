"""Synthesized transition paths between two actions (Ukita, section 4.2).

A transition path leaves action ``a`` at frame ``i``, passes through ``N`` synthesized
in-between poses and joins action ``b`` at frame ``j``. Steps:

**Pose vectors (4.2.1).** Every frame becomes ``y``: the 14 body points, root-centred (root =
mid-hip) and heading-normalised (rotated about the vertical so the trunk faces +x, heading
from the shoulder and hip pairs). Similarity ``s(i, j) = -||y_i^a - y_j^b|| / sqrt(14)`` --
the paper's ``-||y_i^a - y_j^b||`` divided by a constant, so the threshold reads as an RMS
distance per body point in metres (``max_distance_m``).

**End points (4.2.1).** Pairs ``(i, j)`` where ``s`` is a local maximum of the 2-D similarity
map -- the largest value in the ``(2r+1) x (2r+1)`` frame neighbourhood, ``r =
peak_radius`` (r = 1 is the 8-neighbourhood; at 120 Hz a few frames keep one peak per
gait phase instead of a ridge of tiny noise peaks) -- and above the threshold. The best
``max_pairs`` are kept.

**In-between count (P1-P2).** ``theta_k`` = angle between consecutive pose vectors,
``theta''_k = theta_k - 2 theta_{k-1} + theta_{k-2}``. Around the end points (frames
``i +- T`` of ``a`` and ``j +- T`` of ``b``) we take ``y_max`` = largest real step
``||y_{k+1} - y_k||`` and ``theta''_max`` = largest real ``|theta''|``. Readings of the
ambiguous parts, chosen to be testable:

* "``||y^s_{k+1} - y^s_k|| = y_max``" cannot hold exactly for an integer ``N``; we take the
  fewest equal steps no longer than ``y_max``: ``N = ceil(D / y_max) - 1`` with ``D`` the
  end-point distance; interpolation parameters ``u_k = k / (N + 1)`` (equal steps, hence
  "equal ``theta''_k`` for all k" up to the non-linearity of slerp + FK).
* "curvature" is the magnitude ``|theta''|`` (a negative second difference bends the path
  as much as a positive one). It is measured on the *actual* synthesized poses (after slerp
  and FK), over every stencil of the path ``y_{i-2}^a, y_{i-1}^a, y_i^a, y^s_1..y^s_N,
  y_j^b, y_{j+1}^b, y_{j+2}^b`` that touches a synthesized pose or the join -- the joins
  are where a path is least smooth, so they are part of it.
* If ``max |theta''| > theta''_max`` the end points move apart (``i -= 1, j += 1``, the
  paper's widening) and P2 restarts, at most ``max_widen`` times; a pair that never
  passes is dropped (counted in :attr:`TransitionReport.rejected`).
* P3: the reverse path ``b -> a`` is synthesized from the same end points (``j -= 1, i +=
  1`` when widening). P4 (several paths per end point pair) is not used, as in the
  paper's experiments.

**Interpolation (4.2.2).** Skeletal recordings with the same hierarchy (CMU cgspeed BVH,
CMU ASF/AMC): local joint rotations are slerped (quaternions), so every bone keeps its
length; the root orientation is slerped after turning ``b`` about the vertical so its
heading at ``j`` equals ``a``'s at ``i``; bone vectors are interpolated linearly
(``bones='morph'``, identical skeletons -> constant lengths; between two subjects each
length moves monotonically from one subject's to the other's) or taken from one side
(``bones='a'``/``'b'``: constant lengths, a small jump at the other join). Everything
else (marker recordings, different hierarchies): the root-centred, heading-normalised
body points are interpolated linearly -- limb lengths are then only approximately kept
(a rotating limb's chord is shorter than the limb, by ``1 - cos(phi/2)``).

**Root trajectory.** Cubic Hermite between ``a``'s root at ``i`` and ``b``'s (moved) root at
``j`` with the real root velocities at both ends, and ``b`` placed so the horizontal gap is
``(N + 1) dt (v_a + v_b) / 2``: the velocity stays continuous, which the eq. 12 velocity
features need (a linear root path with a standing start would teach the models zero
velocities). With equal end velocities this is the linear interpolation.

Each path is returned as a :class:`MotionClip` ``[y_i^a, synthesized..., y_j^b]`` (end points
included so the first synthesized frame has a velocity) with the provenance in ``meta``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.ndimage import maximum_filter
from scipy.spatial.transform import Rotation

from ..model.features import lateral_yaw, rotation_z
from ..motion.asf_amc import _rot_from_angles, find_asf_for, read_amc, read_asf
from ..motion.bvh import ASF_UNIT_M, axis_rotation, is_tpose, read_bvh, y_up_to_z_up, _guess_unit
from ..motion.clip import MotionClip
from ..motion.load import load_clip, motion_class_of
from ..motion.pointsets import BODY14, derive_body14

_B = {n: i for i, n in enumerate(BODY14)}
TRUNK_PAIRS = np.array([(_B["lshoulder"], _B["rshoulder"]), (_B["lhip"], _B["rhip"])])
HIPS = (_B["lhip"], _B["rhip"])


# ==================================================================== skeletal recordings
@dataclass
class SkeletalMotion:
    """A skeletal recording as per-frame local joint rotations (file units, Y up).

    FK: ``R_g[j] = R_g[parent] @ local[j]``; ``pos[j] = pos[parent] + R_ref @ vectors[j]``
    with ``R_ref = R_g[parent]`` (BVH: offsets live in the parent frame) or ``R_g[j]``
    (ASF: a bone's direction is rotated by the bone's own rotation). The root's position
    is ``root_pos``.
    """

    names: tuple[str, ...]
    parents: np.ndarray           # (J,) -1 for the root (index 0)
    vectors: np.ndarray           # (J, 3) file units
    own_frame: bool               # True: ASF convention (see class doc)
    local: np.ndarray             # (F, J, 3, 3)
    root_pos: np.ndarray          # (F, 3) file units
    scale: float                  # metres per file unit
    rate: float
    source: str = ""
    motion_class: str = ""
    marker_set: str = ""          # 'cgspeed' / 'asf' (for body14)
    frame_numbers: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return self.local.shape[0]

    def same_hierarchy(self, other: "SkeletalMotion") -> bool:
        return (self.names == other.names and np.array_equal(self.parents, other.parents)
                and self.own_frame == other.own_frame)

    def slice(self, start: int | None, stop: int | None) -> "SkeletalMotion":
        fn = None if self.frame_numbers is None else self.frame_numbers[start:stop]
        return SkeletalMotion(self.names, self.parents, self.vectors, self.own_frame, self.local[start:stop],
                              self.root_pos[start:stop], self.scale, self.rate, self.source, self.motion_class,
                              self.marker_set, fn)

    def positions(self, local: np.ndarray | None = None, root_pos: np.ndarray | None = None,
                  vectors: np.ndarray | None = None) -> np.ndarray:
        """FK -> (F, J, 3) in metres, **Z up** (the library convention)."""
        return y_up_to_z_up(fk(self.parents, self.vectors if vectors is None else vectors, self.own_frame,
                               self.local if local is None else local,
                               self.root_pos if root_pos is None else root_pos) * self.scale)

    def clip(self) -> MotionClip:
        return MotionClip(self.positions(), self.rate, self.names, source=self.source,
                          motion_class=self.motion_class,
                          meta=dict(parents=tuple(int(p) for p in self.parents), format="skeletal"))


def fk(parents: np.ndarray, vectors: np.ndarray, own_frame: bool, local: np.ndarray,
       root_pos: np.ndarray) -> np.ndarray:
    """Forward kinematics in file units: local (F, J, 3, 3), vectors (J, 3) or (F, J, 3)."""
    F, J = local.shape[:2]
    vec = np.broadcast_to(vectors, (F, J, 3))
    Rg = np.empty_like(local)
    pos = np.empty((F, J, 3))
    for j in range(J):
        p = int(parents[j])
        if p < 0:
            Rg[:, j] = local[:, j]
            pos[:, j] = root_pos
            continue
        Rg[:, j] = Rg[:, p] @ local[:, j]
        ref = Rg[:, j] if own_frame else Rg[:, p]
        pos[:, j] = pos[:, p] + np.einsum("fij,fj->fi", ref, vec[:, j])
    return pos


def skeletal_from_bvh(path: str | Path) -> SkeletalMotion:
    """Local rotations of a BVH file (T-pose frame dropped as :func:`load_bvh` does)."""
    bvh = read_bvh(path)
    J = len(bvh.joints)
    F = bvh.motion.shape[0]
    local = np.broadcast_to(np.eye(3), (F, J, 3, 3)).copy()
    root_pos = np.broadcast_to(bvh.joints[0].offset, (F, 3)).copy()
    for j, jt in enumerate(bvh.joints):
        for k, ch in enumerate(jt.channels):
            v = bvh.motion[:, jt.channel_start + k]
            if ch[1:].lower() == "position":
                if j != 0:
                    raise ValueError(f"{path}: position channels on joint {jt.name!r} (only the root may translate)")
                root_pos[:, "XYZ".index(ch[0].upper())] += v
            else:
                local[:, j] = local[:, j] @ axis_rotation(ch[0], v)
    parents = np.array([jt.parent for jt in bvh.joints])
    vectors = np.array([jt.offset if jt.parent >= 0 else np.zeros(3) for jt in bvh.joints])
    scale = _guess_unit(bvh)
    pos0 = fk(parents, vectors, False, local[:1], root_pos[:1])[0]
    first = 1 if F > 1 and is_tpose(bvh.names, pos0, up=1) else 0
    return SkeletalMotion(bvh.names, parents, vectors, False, local[first:], root_pos[first:], scale, bvh.rate,
                          str(path), motion_class_of(path)[0], "cgspeed" if bvh.is_cgspeed() else "",
                          np.arange(first, F))


def skeletal_from_asf_amc(asf_path: str | Path, amc_path: str | Path, rate: float = 120.0) -> SkeletalMotion:
    """Local rotations ``L = C M C^-1`` of a CMU ASF/AMC pair (see :mod:`.asf_amc`)."""
    skel = read_asf(asf_path)
    frames, values = read_amc(amc_path, skel)
    F = len(frames)
    to_deg = 1.0 if skel.angle_in_degrees else np.rad2deg(1.0)
    names = ("root",) + tuple(skel.bones)
    J = len(names)
    local = np.broadcast_to(np.eye(3), (F, J, 3, 3)).copy()
    rv = values.get("root", np.zeros((F, len(skel.root_order))))
    order = [o.upper() for o in skel.root_order]
    root_pos = skel.root_position + np.stack(
        [rv[:, order.index(t)] if t in order else np.zeros(F) for t in ("TX", "TY", "TZ")], axis=1)
    rot_dofs = [o for o in order if o.startswith("R")]
    m_ang = np.stack([rv[:, order.index(o)] for o in rot_dofs], axis=1) * to_deg if rot_dofs else np.zeros((F, 0))
    C = _rot_from_angles(skel.root_orientation * to_deg, skel.root_axis_order)
    local[:, 0] = C @ _rot_from_angles(m_ang, "".join(o[1] for o in rot_dofs)) @ C.T
    parents = np.full(J, -1)
    vectors = np.zeros((J, 3))
    for j, (name, b) in enumerate(skel.bones.items(), start=1):
        parents[j] = names.index(b.parent)
        vectors[j] = b.direction * b.length
        if b.dof and name in values:
            C = _rot_from_angles(b.axis * to_deg, b.axis_order)
            M = _rot_from_angles(values[name] * to_deg, "".join(d[1].upper() for d in b.dof))
            local[:, j] = C @ M @ C.T
    return SkeletalMotion(names, parents, vectors, True, local, root_pos, skel.length_unit_m, rate, str(amc_path),
                          motion_class_of(amc_path)[0], "asf", np.asarray(frames))


def load_skeletal(path: str | Path) -> SkeletalMotion | None:
    """The skeletal view of a recording (.bvh, .amc, .asf), or None for marker data."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".bvh":
        return skeletal_from_bvh(path)
    if ext in (".amc", ".asf"):
        amc = path.with_suffix(".amc") if ext == ".asf" else path
        asf = path if ext == ".asf" else find_asf_for(path)
        return skeletal_from_asf_amc(asf, amc)
    return None


# ==================================================================== sources
@dataclass
class TransitionSource:
    """One recording of one action, as body points (and local rotations when skeletal)."""

    clip: MotionClip                       # BODY14, metres, Z up
    skeletal: SkeletalMotion | None = None

    @classmethod
    def load(cls, path: str | Path, frames: tuple[int, int] | None = None, skeletal: bool = True) -> "TransitionSource":
        clip = load_clip(path, points="body14")
        sk = load_skeletal(path) if skeletal else None
        if sk is not None and sk.n_frames != clip.n_frames:
            sk = None                                          # disagreeing views: use positions only
        if frames is not None:
            a, b = frames
            clip = clip.slice(a, b)
            clip.meta["frame_range"] = [int(a), int(b)]
            sk = sk.slice(a, b) if sk is not None else None
        return cls(clip, sk)

    @property
    def name(self) -> str:
        return Path(self.clip.source).name


def normalized_poses(positions: np.ndarray) -> np.ndarray:
    """(F, 14, 3) body points -> (F, 42) root-centred, heading-normalised pose vectors."""
    P = np.asarray(positions, dtype=np.float64)
    root = P[:, list(HIPS)].mean(axis=1)
    yaw = np.nan_to_num(lateral_yaw(P, TRUNK_PAIRS), nan=0.0)
    rel = np.einsum("fij,fnj->fni", rotation_z(-yaw), P - root[:, None])
    return rel.reshape(P.shape[0], -1)


def similarity_matrix(ya: np.ndarray, yb: np.ndarray) -> np.ndarray:
    """``s(i, j) = -||y_i^a - y_j^b|| / sqrt(points)`` (minus the RMS distance per point, m);
    NaN poses give ``-inf``."""
    pts = ya.shape[1] // 3
    d2 = (ya ** 2).sum(1)[:, None] + (yb ** 2).sum(1)[None] - 2.0 * ya @ yb.T
    s = -np.sqrt(np.maximum(d2, 0.0) / pts)
    return np.where(np.isfinite(s), s, -np.inf)


def find_end_points(ya: np.ndarray, yb: np.ndarray, max_distance_m: float, radius: int = 4,
                    max_pairs: int | None = None, margin: int = 2) -> list[tuple[int, int, float]]:
    """End-point pairs ``(i, j, s)``: local maxima of the similarity (largest in the
    ``(2 radius + 1)^2`` neighbourhood, first of equal values) above ``-max_distance_m``,
    best first. ``margin`` frames at each clip end are skipped (the curvature needs
    neighbours)."""
    S = similarity_matrix(ya, yb)
    if S.size == 0:
        return []
    peak = S >= maximum_filter(S, size=2 * radius + 1, mode="constant", cval=-np.inf)
    ok = peak & (S > -max_distance_m) & np.isfinite(S)
    ok[:margin] = ok[-margin:] = False
    ok[:, :margin] = ok[:, -margin:] = False
    ii, jj = np.nonzero(ok)
    order = np.argsort(-S[ii, jj], kind="stable")
    out, taken = [], set()
    for k in order:
        i, j = int(ii[k]), int(jj[k])
        if any(abs(i - a) <= radius and abs(j - b) <= radius for a, b in taken):   # plateau duplicates
            continue
        taken.add((i, j))
        out.append((i, j, float(S[i, j])))
        if max_pairs is not None and len(out) >= max_pairs:
            break
    return out


# ==================================================================== curvature (P1)
def step_angles(Y: np.ndarray) -> np.ndarray:
    """``theta_k`` = angle between ``Y[k]`` and ``Y[k-1]`` (length len(Y) - 1)."""
    a, b = Y[1:], Y[:-1]
    c = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.arccos(np.clip(c, -1.0, 1.0))


def angle_second_difference(Y: np.ndarray) -> np.ndarray:
    """``theta''_k = (theta_k - theta_{k-1}) - (theta_{k-1} - theta_{k-2})`` (length len(Y) - 3)."""
    th = step_angles(Y)
    return th[2:] - 2.0 * th[1:-1] + th[:-2]


def local_bounds(Y: np.ndarray, centre: int, T: int) -> tuple[float, float]:
    """(max ``|theta''|``, max step ``||y_{k+1} - y_k||``) over real frames ``centre +- T``."""
    lo, hi = max(centre - T, 0), min(centre + T + 1, len(Y))
    seg = Y[lo:hi]
    seg = seg[np.isfinite(seg).all(1)]
    if len(seg) < 4:
        return float("nan"), float("nan")
    dd = np.abs(angle_second_difference(seg))
    steps = np.linalg.norm(np.diff(seg, axis=0), axis=1)
    return float(dd.max()), float(steps.max())


# ==================================================================== interpolation
def _slerp(Ra: np.ndarray, Rb: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Per-joint slerp of rotation matrices (J, 3, 3) at parameters u (K,) -> (K, J, 3, 3)."""
    qa, qb = Rotation.from_matrix(Ra), Rotation.from_matrix(Rb)
    rel = (qa.inv() * qb).as_rotvec()                              # shortest arc, (J, 3)
    out = np.empty((len(u),) + Ra.shape)
    for k, uk in enumerate(u):
        out[k] = (qa * Rotation.from_rotvec(uk * rel)).as_matrix()
    return out


def _hermite(p0: np.ndarray, p1: np.ndarray, v0: np.ndarray, v1: np.ndarray, u: np.ndarray, dur: float) -> np.ndarray:
    u = u[:, None]
    h00, h10 = 2 * u ** 3 - 3 * u ** 2 + 1, u ** 3 - 2 * u ** 2 + u
    h01, h11 = -2 * u ** 3 + 3 * u ** 2, u ** 3 - u ** 2
    return h00 * p0 + h10 * dur * v0 + h01 * p1 + h11 * dur * v1


def _velocity(x: np.ndarray, k: int, rate: float) -> np.ndarray:
    """Central (one-sided at the ends) difference of x (F, d) at frame k, per second."""
    lo, hi = max(k - 1, 0), min(k + 1, len(x) - 1)
    if hi == lo:
        return np.zeros(x.shape[1])
    v = (x[hi] - x[lo]) / ((hi - lo) / rate)
    return np.where(np.isfinite(v), v, 0.0)


def _root_and_yaw(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    root = P[:, list(HIPS)].mean(axis=1)
    return root, lateral_yaw(P, TRUNK_PAIRS)


def _place_b(ra: np.ndarray, va: np.ndarray, rb: np.ndarray, vb: np.ndarray, n_steps: int,
             rate: float) -> np.ndarray:
    """Horizontal translation that puts b's root where a continuous root path arrives."""
    dt = n_steps / rate
    target = ra[:2] + dt * 0.5 * (va[:2] + vb[:2])
    t = np.zeros(3)
    t[:2] = target - rb[:2]
    return t


def interpolate_positions(a: MotionClip, i: int, b: MotionClip, j: int, n: int) -> np.ndarray:
    """(n + 2, 14, 3) path [a_i, n in-betweens, b_j (moved)] by linear interpolation of the
    root-centred, heading-normalised body points (limb lengths only approximately kept)."""
    Pa, Pb = a.positions, b.positions
    ra, ya = _root_and_yaw(Pa)
    rb, yb = _root_and_yaw(Pb)
    va, vb_raw = _velocity(ra, i, a.rate), _velocity(rb, j, b.rate)
    dpsi = float(ya[i] - yb[j])
    Rz = rotation_z(np.array(dpsi))
    vb = Rz @ vb_raw
    rb_j = Rz @ rb[j]
    t = _place_b(ra[i], va, rb_j, vb, n + 1, a.rate)
    u = np.arange(n + 2) / (n + 1)
    Ya = normalized_poses(Pa[i:i + 1]).reshape(-1, 3)
    Yb = normalized_poses(Pb[j:j + 1]).reshape(-1, 3)
    Y = (1 - u)[:, None, None] * Ya + u[:, None, None] * Yb
    root = _hermite(ra[i], rb_j + t, va, vb, u, (n + 1) / a.rate)
    yaw = np.full(n + 2, ya[i])
    out = root[:, None] + np.einsum("kij,knj->kni", rotation_z(yaw), Y)
    out[0] = Pa[i]
    out[-1] = np.einsum("ij,nj->ni", Rz, Pb[j]) + t
    return out


def interpolate_skeletal(sa: SkeletalMotion, i: int, sb: SkeletalMotion, j: int, n: int,
                         bones: str = "morph") -> tuple[np.ndarray, np.ndarray]:
    """(n + 2, J, 3) FK positions (m, Z up) of [a_i, n slerped poses, b_j (moved)] and the
    (n + 2, J, 3) bone vectors used (file units)."""
    if not sa.same_hierarchy(sb):
        raise ValueError("skeletal interpolation needs the same hierarchy on both sides")
    if bones not in ("morph", "a", "b"):
        raise ValueError("bones must be 'morph', 'a' or 'b'")
    u = np.arange(n + 2) / (n + 1)
    # turn b about the vertical (file Y) so its heading at j equals a's at i
    Pa = derive_body14(sa.slice(i, i + 1).clip(), sa.marker_set or None).positions
    Pb_all = sb.slice(max(j - 1, 0), j + 2)
    Pb = derive_body14(sb.slice(j, j + 1).clip(), sb.marker_set or None).positions
    dpsi = float(lateral_yaw(Pa, TRUNK_PAIRS)[0] - lateral_yaw(Pb, TRUNK_PAIRS)[0])
    Ry = axis_rotation("Y", np.degrees(dpsi))                      # file-Y rotation == Z-up yaw
    La, Lb = sa.local[i].copy(), sb.local[j].copy()
    Lb[0] = Ry @ Lb[0]
    local = _slerp(La, Lb, u)
    local[0], local[-1] = La, Lb
    # root: Hermite with real end velocities; b moved so the horizontal path is continuous
    rate = sa.rate
    ra = sa.root_pos
    rb = np.einsum("ij,fj->fi", Ry, sb.root_pos)
    va, vb = _velocity(ra, i, rate), _velocity(rb, j, sb.rate)
    # horizontal plane in file axes is (x, z): map to a (2,) view for _place_b
    xz = [0, 2]
    t2 = _place_b(ra[i][xz], va[xz], rb[j][xz], vb[xz], n + 1, rate)[:2]
    t = np.zeros(3)
    t[xz] = t2
    root = _hermite(ra[i], rb[j] + t, va, vb, u, (n + 1) / rate)
    if bones == "morph":
        vec = (1 - u)[:, None, None] * sa.vectors + u[:, None, None] * sb.vectors
    else:
        vec = np.broadcast_to((sa if bones == "a" else sb).vectors, (n + 2,) + sa.vectors.shape).copy()
    pos = y_up_to_z_up(fk(sa.parents, vec, sa.own_frame, local, root) * sa.scale)
    del Pb_all
    return pos, vec


# ==================================================================== paths (P2, P3)
@dataclass
class TransitionSettings:
    max_distance_m: float = 0.10        # end points: RMS distance per body point below this ...
    relative_to_best: float | None = 1.25   # ... or below this x the pair's best distance (None: off)
    peak_radius: int = 4                # local maximum over (2r+1)^2 frames
    max_pairs: int = 4                  # end-point pairs kept per pair of recordings
    window: int = 30                    # T of P1 (frames each side)
    max_widen: int = 30                 # P2 restarts (i -= 1, j += 1) before a pair is dropped
    bones: str = "morph"                # skeletal: 'morph' | 'a' | 'b'
    both_directions: bool = True        # P3
    skeletal: bool = True               # False: always interpolate positions

    def __post_init__(self) -> None:
        if not self.max_distance_m > 0 or self.peak_radius < 1 or self.window < 3 or self.max_widen < 0:
            raise ValueError("max_distance_m > 0, peak_radius >= 1, window >= 3, max_widen >= 0 required")
        if self.max_pairs is not None and self.max_pairs < 1:
            raise ValueError("max_pairs must be >= 1")
        if self.bones not in ("morph", "a", "b"):
            raise ValueError("bones must be 'morph', 'a' or 'b'")


@dataclass
class TransitionReport:
    paths: list[MotionClip] = field(default_factory=list)
    end_points: list[tuple[int, int, float]] = field(default_factory=list)
    rejected: int = 0

    @property
    def frames(self) -> int:
        return int(sum(int(np.sum(p.meta["synthesized_mask"])) for p in self.paths))


def _context(Y: np.ndarray, k: int, step: int, count: int) -> np.ndarray:
    """Up to ``count`` real poses before (step=-1) or after (step=+1) frame k, path order."""
    idx = [k + step * m for m in range(1, count + 1) if 0 <= k + step * m < len(Y)]
    out = Y[idx]
    return out[::-1] if step < 0 else out


def synthesize_path(a: TransitionSource, i: int, b: TransitionSource, j: int,
                    settings: TransitionSettings | None = None, direction_a_to_b: bool = True,
                    score: float = float("nan")) -> MotionClip | None:
    """One accepted path from ``a`` (around frame i) to ``b`` (around frame j), or None.

    ``direction_a_to_b``: widening moves i back and j forward (leave a earlier, join b later).
    """
    s = settings or TransitionSettings()
    Ya, Yb = normalized_poses(a.clip.positions), normalized_poses(b.clip.positions)
    th_a, ymax_a = local_bounds(Ya, i, s.window)
    th_b, ymax_b = local_bounds(Yb, j, s.window)
    th_max, y_max = np.nanmax([th_a, th_b]), np.nanmax([ymax_a, ymax_b])
    if not (np.isfinite(th_max) and np.isfinite(y_max) and y_max > 0):
        return None
    use_skel = (s.skeletal and a.skeletal is not None and b.skeletal is not None
                and a.skeletal.same_hierarchy(b.skeletal))
    for w in range(s.max_widen + 1):
        ia, jb = i - w, j + w
        if ia < 0 or jb >= len(Yb) or not (np.isfinite(Ya[ia]).all() and np.isfinite(Yb[jb]).all()):
            break
        D = float(np.linalg.norm(Ya[ia] - Yb[jb]))
        n = max(int(math.ceil(D / y_max)) - 1, 0)
        if use_skel:
            full, vec = interpolate_skeletal(a.skeletal, ia, b.skeletal, jb, n, s.bones)
            names = a.skeletal.names
            body = derive_body14(MotionClip(full, a.clip.rate, names), a.skeletal.marker_set or None).positions
        else:
            full = body = interpolate_positions(a.clip, ia, b.clip, jb, n)
            names, vec = BODY14, None
        Ys = normalized_poses(body)
        seq = np.concatenate([_context(Ya, ia, -1, 2), Ys, _context(Yb, jb, +1, 2)])
        n_before = len(_context(Ya, ia, -1, 2))
        dd = np.abs(angle_second_difference(seq))
        # stencil k covers seq[k .. k+3]; keep those touching the path body (incl. joins)
        first_path, last_path = n_before, n_before + len(Ys) - 1
        ks = np.arange(len(dd))
        touch = (ks + 3 >= first_path + 1) & (ks <= last_path - 1)
        path_dd = float(dd[touch].max()) if touch.any() else 0.0
        if path_dd <= th_max:
            mask = np.zeros(n + 2, dtype=bool)
            mask[1:-1] = True
            src_a, src_b = a.clip, b.clip
            meta = dict(
                synthesized=True, synthesized_mask=mask, method="slerp" if use_skel else "linear positions",
                bones=s.bones if use_skel else "", from_source=src_a.source, from_class=src_a.motion_class,
                from_frame=int(ia) + int(src_a.meta.get("frame_range", [0])[0]),
                to_source=src_b.source, to_class=src_b.motion_class,
                to_frame=int(jb) + int(src_b.meta.get("frame_range", [0])[0]),
                end_point=(int(i), int(j)), widened=int(w), n_inbetween=int(n), distance=D,
                similarity=float(score), y_max=y_max, theta_dd_max=float(th_max), path_theta_dd=path_dd,
                point_set="body14")
            if use_skel:
                meta["skeletal_positions"] = full
                meta["skeletal_names"] = names
                meta["skeletal_parents"] = tuple(int(p) for p in a.skeletal.parents)
                meta["bone_vectors"] = vec
                meta["unit_scale"] = a.skeletal.scale
            cls = f"{src_a.motion_class}->{src_b.motion_class}"
            return MotionClip(body, a.clip.rate, BODY14, source=f"transition:{Path(src_a.source).name}@{ia}"
                              f"->{Path(src_b.source).name}@{jb}", motion_class=cls, meta=meta)
    return None


def end_point_threshold(Ya: np.ndarray, Yb: np.ndarray, settings: TransitionSettings) -> float:
    """The distance threshold of one pair of recordings: ``max_distance_m``, raised to
    ``relative_to_best`` x the pair's smallest distance when that is larger. The paper sets
    the threshold by hand; two actions whose *closest* poses are far apart (walk vs a whirl
    dance with raised arms) would otherwise get no path at all."""
    t = settings.max_distance_m
    if settings.relative_to_best is not None:
        S = similarity_matrix(Ya, Yb)
        if S.size and np.isfinite(S).any():
            t = max(t, settings.relative_to_best * float(-S.max()))
    return t


def synthesize_transitions(a: TransitionSource, b: TransitionSource,
                           settings: TransitionSettings | None = None) -> TransitionReport:
    """All accepted paths between two recordings: a -> b at every end point, and b -> a (P3)."""
    s = settings or TransitionSettings()
    Ya, Yb = normalized_poses(a.clip.positions), normalized_poses(b.clip.positions)
    ends = find_end_points(Ya, Yb, end_point_threshold(Ya, Yb, s), s.peak_radius, s.max_pairs)
    rep = TransitionReport(end_points=ends)
    for i, j, sc in ends:
        p = synthesize_path(a, i, b, j, s, score=sc)
        rep.paths.append(p) if p is not None else None
        rep.rejected += p is None
        if s.both_directions:
            q = synthesize_path(b, j, a, i, s, score=sc)
            rep.paths.append(q) if q is not None else None
            rep.rejected += q is None
    return rep


def transitions_between(sources_a: Sequence[TransitionSource], sources_b: Sequence[TransitionSource],
                        settings: TransitionSettings | None = None) -> TransitionReport:
    """Paths between every recording of action a and every recording of action b."""
    out = TransitionReport()
    for a in sources_a:
        for b in sources_b:
            r = synthesize_transitions(a, b, settings)
            out.paths += r.paths
            out.end_points += r.end_points
            out.rejected += r.rejected
    return out


def bone_lengths(positions: np.ndarray, parents: Sequence[int]) -> np.ndarray:
    """(F, bones) distance of every non-root node from its parent."""
    idx = [j for j, p in enumerate(parents) if p >= 0]
    par = [parents[j] for j in idx]
    return np.linalg.norm(positions[:, idx] - positions[:, par], axis=-1)


__all__ = ["SkeletalMotion", "load_skeletal", "TransitionSource", "TransitionSettings", "TransitionReport",
           "normalized_poses", "similarity_matrix", "find_end_points", "step_angles", "angle_second_difference",
           "local_bounds", "interpolate_positions", "interpolate_skeletal", "synthesize_path",
           "synthesize_transitions", "transitions_between", "bone_lengths", "ASF_UNIT_M"]
