"""CMU ASF (skeleton) / AMC (motion) reader and vectorised forward kinematics.

Conventions (Acclaim / CMU, see shared data README section 3):

* ``C`` = rotation from a bone's ASF ``axis`` values, composed so that order ``XYZ``
  gives ``C = Rz @ Ry @ Rx``; ``M`` = rotation from the AMC dof values, dof order
  ``rx ry rz`` gives ``M = Rz @ Ry @ Rx``; local rotation ``L = C @ M @ C^-1``;
  ``R_global = R_global(parent) @ L``.
* bone end = parent end + ``R_global @ (direction * length)``; the root's "end" is its
  position (``:root position`` + TX TY TZ, with root orientation as its ``C``).
* Bones absent from an AMC frame (no dof) have identity local rotation.
* Length unit: ``:units length 0.45`` means one file unit = (1 / 0.45) inch
  = 0.0564444 m (``0.0254 / length``); angles in degrees (``angle rad`` supported).
* AMC frames are numbered from 1; there is no T-pose frame. AMC files carry no rate:
  120 Hz (CMU nominal) is assumed.
* Output of :func:`load_asf_amc`: metres, **Z up** (ASF is Y up; ``(x,y,z)->(x,-z,y)``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .bvh import axis_rotation, y_up_to_z_up
from .clip import MotionClip
from .naming import cmu_subject

CMU_RATE_HZ = 120.0


@dataclass
class AsfBone:
    name: str
    direction: np.ndarray  # (3,) unit vector, world frame at rest
    length: float
    axis: np.ndarray  # (3,) degrees
    axis_order: str  # e.g. "XYZ"
    dof: tuple[str, ...] = ()
    parent: str = ""


@dataclass
class AsfSkeleton:
    path: str
    length_unit_m: float
    angle_in_degrees: bool
    root_order: tuple[str, ...]
    root_axis_order: str
    root_position: np.ndarray
    root_orientation: np.ndarray
    bones: dict[str, AsfBone] = field(default_factory=dict)  # in hierarchy (parents-first) order

    def children(self, name: str) -> list[str]:
        return [b.name for b in self.bones.values() if b.parent == name]


def _rot_from_angles(angles_deg: np.ndarray, order: str) -> np.ndarray:
    """Rotations for angles (..., n) applied in ``order`` (first letter first):
    ``order='XYZ'`` => ``Rz @ Ry @ Rx``."""
    R = np.broadcast_to(np.eye(3), angles_deg.shape[:-1] + (3, 3)).copy()
    for k, ax in enumerate(order):
        R = axis_rotation(ax, angles_deg[..., k]) @ R
    return R


def read_asf(path: str | Path) -> AsfSkeleton:
    """Parse an ASF file. Raises ``ValueError('<file>:<line>: ...')`` on malformed input."""
    path = str(path)
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        lines = fh.read().splitlines()
    section = ""
    length = 1.0
    degrees = True
    root = dict(order=("TX", "TY", "TZ", "RX", "RY", "RZ"), axis="XYZ", position=np.zeros(3),
                orientation=np.zeros(3))
    bones: dict[str, AsfBone] = {}
    cur: dict | None = None
    hierarchy: list[tuple[int, list[str]]] = []

    def err(msg: str, ln: int) -> ValueError:
        return ValueError(f"{path}:{ln + 1}: {msg}")

    def nums(tok: list[str], n: int, ln: int) -> np.ndarray:
        try:
            v = np.array([float(x) for x in tok[:n]])
        except ValueError:
            raise err(f"expected {n} numbers, got {tok}", ln) from None
        if v.size != n:
            raise err(f"expected {n} numbers, got {tok}", ln)
        return v

    for ln, raw in enumerate(lines):
        s = raw.split("#", 1)[0].strip()
        if not s:
            continue
        tok = s.split()
        if tok[0].startswith(":"):
            section = tok[0][1:].lower()
            continue
        key = tok[0].lower()
        if section == "units":
            if key == "length":
                length = float(nums(tok[1:], 1, ln)[0])
            elif key == "angle":
                degrees = tok[1].lower().startswith("deg")
        elif section == "root":
            if key == "order":
                root["order"] = tuple(t.upper() for t in tok[1:])
            elif key == "axis":
                root["axis"] = tok[1].upper()
            elif key in ("position", "orientation"):
                root[key] = nums(tok[1:], 3, ln)
        elif section == "bonedata":
            if key == "begin":
                cur = dict(dof=(), axis=np.zeros(3), axis_order="XYZ", line=ln)
            elif key == "end":
                if cur is None or "name" not in cur or "direction" not in cur or "length" not in cur:
                    raise err("bone block without name/direction/length", ln)
                bones[cur["name"]] = AsfBone(name=cur["name"], direction=cur["direction"], length=cur["length"],
                                             axis=cur["axis"], axis_order=cur["axis_order"], dof=cur["dof"])
                cur = None
            elif cur is None:
                raise err(f"{tok[0]!r} outside begin/end", ln)
            elif key == "name":
                cur["name"] = tok[1]
            elif key == "direction":
                cur["direction"] = nums(tok[1:], 3, ln)
            elif key == "length":
                cur["length"] = float(nums(tok[1:], 1, ln)[0])
            elif key == "axis":
                cur["axis"] = nums(tok[1:], 3, ln)
                cur["axis_order"] = tok[4].upper() if len(tok) > 4 else "XYZ"
            elif key == "dof":
                dof = tuple(t.lower() for t in tok[1:])
                bad = [d for d in dof if d not in ("rx", "ry", "rz")]
                if bad:
                    raise err(f"unsupported dof {bad} (only rx ry rz)", ln)
                cur["dof"] = dof
        elif section == "hierarchy":
            if key in ("begin", "end"):
                continue
            hierarchy.append((ln, tok))
    if not bones:
        raise ValueError(f"{path}: no :bonedata")
    ordered: dict[str, AsfBone] = {}
    known = {"root"}
    pending = list(hierarchy)
    # hierarchy lines are normally parents-first; resolve in a loop to be safe
    while pending:
        progress = False
        for item in list(pending):
            ln, tok = item
            if tok[0] in known:
                for child in tok[1:]:
                    if child not in bones:
                        raise err(f"hierarchy names unknown bone {child!r}", ln)
                    bones[child].parent = tok[0]
                    ordered[child] = bones[child]
                    known.add(child)
                pending.remove(item)
                progress = True
        if not progress:
            ln, tok = pending[0]
            raise err(f"hierarchy parent {tok[0]!r} is not connected to root", ln)
    missing = set(bones) - set(ordered)
    if missing:
        raise ValueError(f"{path}: bones not in :hierarchy: {sorted(missing)}")
    return AsfSkeleton(path=path, length_unit_m=0.0254 / length, angle_in_degrees=degrees,
                       root_order=root["order"], root_axis_order=root["axis"], root_position=root["position"],
                       root_orientation=root["orientation"], bones=ordered)


def read_amc(path: str | Path, skel: AsfSkeleton) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Parse an AMC file. Returns (frame_numbers (F,), {bone or 'root': (F, n_dof) values});
    bones never listed are absent; a bone missing from some frames gets zeros there."""
    path = str(path)
    ndof = {n: len(b.dof) for n, b in skel.bones.items()}
    ndof["root"] = len(skel.root_order)
    frames: list[int] = []
    rows: list[dict[str, list[float]]] = []
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for ln, raw in enumerate(fh):
            s = raw.strip()
            if not s or s[0] in "#:":
                continue
            tok = s.split()
            if len(tok) == 1 and tok[0].isdigit():
                frames.append(int(tok[0]))
                rows.append({})
                continue
            if not rows:
                raise ValueError(f"{path}:{ln + 1}: data before the first frame number")
            name = tok[0]
            if name not in ndof:
                raise ValueError(f"{path}:{ln + 1}: bone {name!r} not in the ASF skeleton")
            if len(tok) - 1 != ndof[name]:
                raise ValueError(f"{path}:{ln + 1}: bone {name!r} has {ndof[name]} dof, got {len(tok) - 1} values")
            try:
                rows[-1][name] = [float(v) for v in tok[1:]]
            except ValueError:
                raise ValueError(f"{path}:{ln + 1}: non-numeric value in {tok}") from None
    if not rows:
        raise ValueError(f"{path}: no frames")
    names = {n for r in rows for n in r}
    values = {}
    for n in names:
        v = np.zeros((len(rows), ndof[n]))
        for f, r in enumerate(rows):
            if n in r:
                v[f] = r[n]
        values[n] = v
    return np.array(frames), values


def forward_kinematics(skel: AsfSkeleton, values: dict[str, np.ndarray]) -> tuple[tuple[str, ...], np.ndarray]:
    """Bone END points in file units, ASF axes (Y up): (names=('root', bones...), (F, 1+B, 3))."""
    F = len(next(iter(values.values())))
    to_deg = 1.0 if skel.angle_in_degrees else np.rad2deg(1.0)
    rv = values.get("root", np.zeros((F, len(skel.root_order))))
    order = [o.upper() for o in skel.root_order]
    trans = skel.root_position + np.stack(
        [rv[:, order.index(t)] if t in order else np.zeros(F) for t in ("TX", "TY", "TZ")], axis=1)
    rot_dofs = [o for o in order if o.startswith("R")]
    m_ang = np.stack([rv[:, order.index(o)] for o in rot_dofs], axis=1) * to_deg if rot_dofs else np.zeros((F, 0))
    C = _rot_from_angles(skel.root_orientation * to_deg, skel.root_axis_order)
    M = _rot_from_angles(m_ang, "".join(o[1] for o in rot_dofs))
    rot = {"root": C @ M @ C.T}
    pos = {"root": trans}
    for name, b in skel.bones.items():
        C = _rot_from_angles(b.axis * to_deg, b.axis_order)
        if b.dof and name in values:
            M = _rot_from_angles(values[name] * to_deg, "".join(d[1].upper() for d in b.dof))
            R = rot[b.parent] @ (C @ M @ C.T)
        else:
            R = rot[b.parent]
        rot[name] = R
        pos[name] = pos[b.parent] + R @ (b.direction * b.length)
    names = ("root",) + tuple(skel.bones)
    return names, np.stack([pos[n] for n in names], axis=1)


def find_asf_for(amc_path: str | Path) -> Path:
    """The skeleton for an AMC: same stem ``.asf``; else the subject's skeleton by CMU naming
    (``93_04.amc`` -> ``93.asf``); else the only ``.asf`` in the folder; else ValueError
    (pass the skeleton: ``asf_path=`` / ``--asf PATH``)."""
    amc_path = Path(amc_path)
    same = amc_path.with_suffix(".asf")
    if same.is_file():
        return same
    cands = sorted(set(amc_path.parent.glob("*.asf")) | set(amc_path.parent.glob("*.ASF")))
    subject = cmu_subject(amc_path.stem)
    if subject is not None:
        by_subject = [c for c in cands if c.stem in (subject, subject.zfill(2), subject.lstrip("0") or "0")]
        if len(by_subject) == 1:
            return by_subject[0]
    if len(cands) == 1:
        return cands[0]
    raise ValueError(f"{amc_path}: no {same.name}" + (f" nor {subject}.asf" if subject is not None else "")
                     + f" and {len(cands)} .asf files in the folder; pass the skeleton with --asf PATH")


def load_asf_amc(asf_path: str | Path, amc_path: str | Path, unit_scale: float | None = None,
                 rate: float = CMU_RATE_HZ) -> MotionClip:
    """ASF + AMC -> MotionClip (metres, Z up): ``root`` position + every bone's END point,
    named after the bone. ``unit_scale`` overrides metres per file unit.
    ``meta``: ``frame_numbers`` (AMC numbers), ``unit_scale``, ``parents``, ``format``."""
    skel = read_asf(asf_path)
    frames, values = read_amc(amc_path, skel)
    names, pos = forward_kinematics(skel, values)
    scale = skel.length_unit_m if unit_scale is None else float(unit_scale)
    parent_idx = tuple(-1 if n == "root" else names.index(skel.bones[n].parent) for n in names)
    meta = dict(format="asf_amc", unit_scale=scale, frame_numbers=frames, parents=parent_idx, asf=str(asf_path))
    return MotionClip(positions=y_up_to_z_up(pos * scale), rate=rate, names=names, source=str(amc_path), meta=meta)
