"""BVH (Biovision hierarchy) reader and vectorised forward kinematics.

Generic: any channel order per joint (rotations compose in the listed order,
``Zrotation Yrotation Xrotation`` => ``R = Rz @ Ry @ Rx``), position channels on any
joint (added to the joint OFFSET, in the parent frame), End Sites (named
``<parent>_end``). Angles in degrees.

Output of :func:`load_bvh` is a :class:`MotionClip` in **metres, Z up**
(BVH is Y up; converted with ``(x, y, z) -> (x, -z, y)``).

Rules (documented choices):

* ``unit_scale=None``: the CMU cgspeed skeleton (root ``Hips`` with ``LHipJoint``,
  ``RHipJoint``, ``LowerBack``, ``Spine1``) is in ASF units => 0.0254/0.45 m
  (0.0564444 m). Otherwise the unit is guessed from the rest-pose size ``S`` (largest
  distance of any joint from the root): ``S < 3`` metres, ``S < 30`` ASF units,
  ``S < 300`` centimetres (the common BVH case), else millimetres.
* ``drop_tpose=None`` (auto): frame 0 is dropped when the file has more than one frame
  and frame 0 is geometrically a T-pose (both upper arms/forearms within 20 deg of
  horizontal and pointing away from each other, both legs within 20 deg of vertical).
  Arm/leg joints are looked up by cgspeed names (``LeftArm``/``LeftHand``,
  ``LeftUpLeg``/``LeftFoot`` ...); skeletons without them never drop a frame in auto
  mode. The cgspeed conversions (and all shared BVH files) start with such a frame.
  ``True``/``False`` force the choice.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .clip import MotionClip

ASF_UNIT_M = 0.0254 / 0.45  # one CMU ASF length unit (length 0.45) in metres
CGSPEED_SIGNATURE = ("Hips", "LHipJoint", "RHipJoint", "LowerBack", "Spine1")
_AXES = {"X": 0, "Y": 1, "Z": 2}


def axis_rotation(axis: str, degrees: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about ``axis`` ('X'/'Y'/'Z') by ``degrees``."""
    a = np.deg2rad(np.asarray(degrees, dtype=np.float64))
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    i = _AXES[axis.upper()]
    j, k = (i + 1) % 3, (i + 2) % 3
    R[..., i, i] = 1.0
    R[..., j, j] = c
    R[..., k, k] = c
    R[..., j, k] = -s
    R[..., k, j] = s
    return R


def y_up_to_z_up(p: np.ndarray) -> np.ndarray:
    """``(x, y, z) -> (x, -z, y)``: +90 deg about X, keeps handedness."""
    p = np.asarray(p, dtype=np.float64)
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)


@dataclass
class BvhJoint:
    name: str
    parent: int  # index into BvhSkeleton.joints, -1 for the root
    offset: np.ndarray  # (3,) in file units, parent frame
    channels: tuple[str, ...] = ()  # e.g. ("Xposition", ..., "Zrotation")
    is_end_site: bool = False
    channel_start: int = 0  # first column of this joint in the motion matrix


@dataclass
class BvhFile:
    """Parsed BVH: skeleton (depth-first order, parents first) + raw channel matrix."""

    path: str
    joints: list[BvhJoint] = field(default_factory=list)
    motion: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # frames x channels
    frame_time: float = 0.0

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    @property
    def rate(self) -> float:
        r = 1.0 / self.frame_time
        return float(round(r)) if abs(r - round(r)) < 1e-3 * r else r

    def is_cgspeed(self) -> bool:
        return all(n in self.names for n in CGSPEED_SIGNATURE) and self.joints[0].name == "Hips"


def read_bvh(path: str | Path) -> BvhFile:
    """Parse a BVH file; raises ``ValueError('<file>:<line>: ...')`` on malformed input."""
    path = str(path)
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        lines = fh.read().splitlines()
    out = BvhFile(path=path)
    stack: list[int] = []
    pending: int | None = None  # joint declared, waiting for its '{'
    n_channels = 0
    i = 0

    def err(msg: str, ln: int) -> ValueError:
        return ValueError(f"{path}:{ln + 1}: {msg}")

    while i < len(lines):
        tok = lines[i].split()
        if not tok:
            i += 1
            continue
        key = tok[0].upper()
        if key == "HIERARCHY":
            pass
        elif key in ("ROOT", "JOINT") or (key == "END" and len(tok) > 1 and tok[1].upper() == "SITE"):
            end = key == "END"
            if key == "ROOT" and (stack or out.joints):
                raise err("only one ROOT per file is supported", i)
            if key != "ROOT" and not stack:
                raise err(f"{tok[0]} outside of a ROOT block", i)
            if not end and len(tok) < 2:
                raise err(f"{tok[0]} without a name", i)
            parent = stack[-1] if stack else -1
            name = out.joints[parent].name + "_end" if end else " ".join(tok[1:])
            out.joints.append(BvhJoint(name=name, parent=parent, offset=np.zeros(3), is_end_site=end))
            pending = len(out.joints) - 1
        elif key == "{":
            if pending is None:
                raise err("unexpected '{'", i)
            stack.append(pending)
            pending = None
        elif key == "}":
            if not stack:
                raise err("unbalanced '}'", i)
            stack.pop()
        elif key == "OFFSET":
            if not stack or len(tok) != 4:
                raise err("OFFSET needs 3 numbers inside a joint block", i)
            try:
                out.joints[stack[-1]].offset = np.array([float(v) for v in tok[1:]])
            except ValueError:
                raise err(f"bad OFFSET values {tok[1:]}", i) from None
        elif key == "CHANNELS":
            if not stack:
                raise err("CHANNELS outside a joint block", i)
            try:
                n = int(tok[1])
            except (IndexError, ValueError):
                raise err("CHANNELS needs a count", i) from None
            chans = tuple(tok[2:])
            if len(chans) != n:
                raise err(f"CHANNELS says {n} but lists {len(chans)}", i)
            for c in chans:
                if len(c) < 9 or c[0].upper() not in _AXES or c[1:].lower() not in ("position", "rotation"):
                    raise err(f"unknown channel {c!r}", i)
            j = out.joints[stack[-1]]
            j.channels, j.channel_start = chans, n_channels
            n_channels += n
        elif key == "MOTION":
            break
        else:
            raise err(f"unexpected token {tok[0]!r}", i)
        i += 1
    if not out.joints:
        raise ValueError(f"{path}: no ROOT found")
    if stack or pending is not None:
        raise ValueError(f"{path}: unterminated joint block before MOTION")
    if i >= len(lines):
        raise ValueError(f"{path}: no MOTION section")
    # MOTION header
    try:
        n_frames = int(lines[i + 1].split(":")[1])
    except (IndexError, ValueError):
        raise ValueError(f"{path}:{i + 2}: expected 'Frames: <n>'") from None
    try:
        ft_line = lines[i + 2]
        if not ft_line.strip().lower().startswith("frame time"):
            raise ValueError
        out.frame_time = float(ft_line.split(":")[1])
    except (IndexError, ValueError):
        raise ValueError(f"{path}:{i + 3}: expected 'Frame Time: <seconds>'") from None
    if out.frame_time <= 0:
        raise ValueError(f"{path}:{i + 3}: frame time must be positive")
    body = [ln for ln in lines[i + 3:] if ln.strip()]
    if len(body) != n_frames:
        raise ValueError(f"{path}: header says {n_frames} frames, found {len(body)} data lines")
    try:
        data = np.array(" ".join(body).split(), dtype=np.float64)
    except ValueError:
        raise ValueError(f"{path}: non-numeric value in the MOTION data") from None
    if data.size != n_frames * n_channels:
        for k, ln in enumerate(body):  # locate the offending line
            if len(ln.split()) != n_channels:
                raise ValueError(f"{path}:{i + 4 + k}: expected {n_channels} values, got {len(ln.split())}")
        raise ValueError(f"{path}: MOTION data size mismatch")
    out.motion = data.reshape(n_frames, n_channels)
    return out


def forward_kinematics(bvh: BvhFile, frames: slice | np.ndarray | None = None) -> np.ndarray:
    """Global joint/end-site positions (frames, joints, 3) in **file units and axes**."""
    motion = bvh.motion if frames is None else bvh.motion[frames]
    F = motion.shape[0]
    J = len(bvh.joints)
    pos = np.empty((F, J, 3))
    rot = np.empty((J, F, 3, 3))
    for j, jt in enumerate(bvh.joints):
        trans = np.broadcast_to(jt.offset, (F, 3)).copy()
        R = np.broadcast_to(np.eye(3), (F, 3, 3)).copy()
        for k, ch in enumerate(jt.channels):
            v = motion[:, jt.channel_start + k]
            if ch[1:].lower() == "position":
                trans[:, _AXES[ch[0].upper()]] += v
            else:
                R = R @ axis_rotation(ch[0], v)
        if jt.parent < 0:
            pos[:, j] = trans
            rot[j] = R
        else:
            Rp = rot[jt.parent]
            pos[:, j] = pos[:, jt.parent] + np.einsum("fij,fj->fi", Rp, trans)
            rot[j] = Rp @ R
    return pos


def _guess_unit(bvh: BvhFile) -> float:
    if bvh.is_cgspeed():
        return ASF_UNIT_M
    rest = np.zeros((len(bvh.joints), 3))
    for j, jt in enumerate(bvh.joints):
        rest[j] = jt.offset + (rest[jt.parent] if jt.parent >= 0 else 0.0)
    size = float(np.max(np.linalg.norm(rest - rest[0], axis=1)))
    if size < 3:
        return 1.0
    if size < 30:
        return ASF_UNIT_M
    if size < 300:
        return 0.01
    return 0.001


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def is_tpose(names: tuple[str, ...], pose: np.ndarray, up: int = 1, tol_deg: float = 20.0) -> bool:
    """True if ``pose`` (joints x 3, any units) is a T-pose with cgspeed joint names."""
    need = ("LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm", "RightHand",
            "LeftUpLeg", "LeftFoot", "RightUpLeg", "RightFoot")
    if any(n not in names for n in need):
        return False
    P = {n: pose[names.index(n)] for n in need}
    sin_tol = np.sin(np.deg2rad(tol_deg))
    cos_tol = np.cos(np.deg2rad(tol_deg))
    arms = []
    for side in ("Left", "Right"):
        for a, b in (("Arm", "ForeArm"), ("ForeArm", "Hand")):
            d = _unit(P[side + b] - P[side + a])
            if abs(d[up]) > sin_tol:
                return False
        arms.append(_unit(P[side + "Hand"] - P[side + "Arm"]))
        leg = _unit(P[side + "Foot"] - P[side + "UpLeg"])
        if -leg[up] < cos_tol:
            return False
    return float(arms[0] @ arms[1]) < -cos_tol


def load_bvh(path: str | Path, unit_scale: float | None = None, drop_tpose: bool | None = None,
             up_axis: str = "Y", include_end_sites: bool = True) -> MotionClip:
    """BVH -> MotionClip (metres, Z up) of all joints (and End Sites ``<parent>_end``).

    ``unit_scale``: metres per file unit (None: see module doc). ``drop_tpose``: see module
    doc. ``up_axis``: the file's up axis, 'Y' (BVH convention) or 'Z'.
    ``meta``: ``frame_numbers`` (source frame index of each clip frame), ``unit_scale``,
    ``dropped_tpose``, ``parents`` (parent index per point, -1 for root), ``format``.
    """
    bvh = read_bvh(path)
    scale = _guess_unit(bvh) if unit_scale is None else float(unit_scale)
    pos = forward_kinematics(bvh)
    up = up_axis.upper()
    if up not in ("Y", "Z"):
        raise ValueError(f"{path}: up_axis must be 'Y' or 'Z', got {up_axis!r}")
    if drop_tpose is None:
        drop_tpose = pos.shape[0] > 1 and is_tpose(bvh.names, pos[0], up=_AXES[up])
    first = 1 if drop_tpose else 0
    if pos.shape[0] - first < 1:
        raise ValueError(f"{path}: no motion frames left")
    pos = pos[first:] * scale
    if up == "Y":
        pos = y_up_to_z_up(pos)
    keep = [j for j, jt in enumerate(bvh.joints) if include_end_sites or not jt.is_end_site]
    remap = {j: k for k, j in enumerate(keep)}
    parents = tuple(remap.get(bvh.joints[j].parent, -1) for j in keep)
    meta = dict(format="bvh", unit_scale=scale, dropped_tpose=bool(drop_tpose),
                frame_numbers=np.arange(first, first + pos.shape[0]), parents=parents,
                cgspeed=bvh.is_cgspeed())
    return MotionClip(positions=pos[:, keep], rate=bvh.rate, names=tuple(bvh.names[j] for j in keep),
                      source=str(path), meta=meta)
