"""Point sets: the paper's 14 body points and how to derive them from each source.

Each body point is the mean of one or more source points (markers or skeleton
joints); a mean is missing (NaN) in a frame if **any** of its sources is missing.

Sources (``MARKER_SETS`` keys):

* ``body14``   -- the clip already has the 14 points (also the 16-joint positions CSVs).
* ``cgspeed``  -- CMU cgspeed BVH/FBX joints (README section 3 table; neck = ``Neck``,
  which sits ~11.6 cm lower than the ASF ``thorax`` end because cgspeed has no thorax).
* ``asf``      -- CMU ASF bone END points (neck = thorax end, head = upperneck end, ...).
* ``cmu41``    -- CMU / HDM05 41-marker Vicon set. Hip = mean(front, back waist marker):
  a pelvis landmark above the hip joint, no marker sits on the joint.
* ``mct28``    -- MoCap Toolbox 28-marker set (the toolbox's own ``m2jpar`` choices).
* ``qualisys55`` -- Qualisys ISB-style 55-marker set. Hip = mean(L_IAS, L_IPS)
  (anterior + posterior superior iliac spine), the same pelvis landmarks that ``cmu41``
  (FWT/BWT) and ``mct28`` (Hip_F*/Hip_B*) use, so the three marker sets agree on what
  "hip" means; the greater trochanter (``L_FTC``) is lateral and moves with the thigh,
  so it was not used. Elbow/knee/ankle/wrist = mean of the medial+lateral landmarks.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .clip import MotionClip

BODY14 = ("head", "neck", "lshoulder", "rshoulder", "lelbow", "relbow", "lwrist", "rwrist",
          "lhip", "rhip", "lknee", "rknee", "lankle", "rankle")


def _sided(table: dict[str, tuple[str, ...]], left, right) -> dict[str, tuple[str, ...]]:
    """Expand a table whose l*-entries use '{s}' placeholders into l* and r* entries."""
    out = {}
    for k, v in table.items():
        if "{" in "".join(v):
            out["l" + k] = tuple(s.format(s=left[0], S=left[1]) for s in v)
            out["r" + k] = tuple(s.format(s=right[0], S=right[1]) for s in v)
        else:
            out[k] = v
    return {p: out[p] for p in BODY14}


MARKER_SETS: dict[str, dict[str, tuple[str, ...]]] = {
    "body14": {p: (p,) for p in BODY14},
    "cgspeed": _sided({"head": ("Head",), "neck": ("Neck",), "shoulder": ("{S}Arm",), "elbow": ("{S}ForeArm",),
                       "wrist": ("{S}Hand",), "hip": ("{S}UpLeg",), "knee": ("{S}Leg",), "ankle": ("{S}Foot",)},
                      ("", "Left"), ("", "Right")),
    "asf": _sided({"head": ("upperneck",), "neck": ("thorax",), "shoulder": ("{s}clavicle",),
                   "elbow": ("{s}humerus",), "wrist": ("{s}radius",), "hip": ("{s}hipjoint",),
                   "knee": ("{s}femur",), "ankle": ("{s}tibia",)}, ("l", ""), ("r", "")),
    "cmu41": _sided({"head": ("LFHD", "RFHD", "LBHD", "RBHD"), "neck": ("C7", "CLAV"), "shoulder": ("{S}SHO",),
                     "elbow": ("{S}ELB",), "wrist": ("{S}WRA", "{S}WRB"), "hip": ("{S}FWT", "{S}BWT"),
                     "knee": ("{S}KNE",), "ankle": ("{S}ANK",)}, ("", "L"), ("", "R")),
    "mct28": _sided({"head": ("Head_FL", "Head_FR", "Head_BL", "Head_BR"), "neck": ("Shoulder_L", "Shoulder_R"),
                     "shoulder": ("Shoulder_{S}",), "elbow": ("Elbow_{S}",), "wrist": ("Radius_{S}", "Ulna_{S}"),
                     "hip": ("Hip_F{S}", "Hip_B{S}"), "knee": ("Knee_{S}",), "ankle": ("Ankle_{S}",)},
                    ("", "L"), ("", "R")),
    "qualisys55": _sided({"head": ("L_HDF", "L_HDB", "R_HDB", "R_HDF"), "neck": ("CV7", "SNJ"),
                          "shoulder": ("{S}_SAJ",), "elbow": ("{S}_HLE", "{S}_HME"), "wrist": ("{S}_RSP", "{S}_UHE"),
                          "hip": ("{S}_IAS", "{S}_IPS"), "knee": ("{S}_FLE", "{S}_FME"),
                          "ankle": ("{S}_FAL", "{S}_TAM")}, ("", "L"), ("", "R")),
}


def detect_marker_set(names: Sequence[str]) -> str:
    """The first ``MARKER_SETS`` key whose source points are all in ``names``."""
    have = set(names)
    for key, table in MARKER_SETS.items():
        if all(s in have for srcs in table.values() for s in srcs):
            return key
    raise ValueError("cannot derive BODY14: names match no known marker set "
                     f"({', '.join(MARKER_SETS)}); got {', '.join(list(names)[:12])}...")


def derive_body14(clip: MotionClip, marker_set: str | None = None) -> MotionClip:
    """A BODY14 clip (same frames/rate/source/class) derived from ``clip``.
    ``meta['marker_set']`` records the source set; other meta entries are kept."""
    key = detect_marker_set(clip.names) if marker_set is None else marker_set
    if key not in MARKER_SETS:
        raise ValueError(f"unknown marker set {key!r}; have {', '.join(MARKER_SETS)}")
    table = MARKER_SETS[key]
    out = np.empty((clip.n_frames, len(BODY14), 3))
    for k, p in enumerate(BODY14):
        idx = [clip.index(s) for s in table[p]]
        out[:, k] = clip.positions[:, idx].mean(axis=1)  # NaN propagates: missing if any is missing
    meta = dict(clip.meta)
    meta.pop("parents", None)
    meta.update(marker_set=key, point_set="body14")
    return clip._replace(positions=out, names=BODY14, meta=meta)


@dataclass(frozen=True)
class AllBut:
    """Every point of a clip but ``names`` (``--points all,-NAME,...``): a marker a take hardly
    shows, left out without typing every other name."""

    names: tuple[str, ...]


def to_point_set(clip: MotionClip, points: str | Sequence[str] | AllBut = "body14",
                 marker_set: str | None = None) -> MotionClip:
    """``points``: ``"all"`` (clip unchanged), ``"body14"`` (derived BODY14), :class:`AllBut`
    (every point but some), or a list of names taken from the clip's own points and, where
    absent, from the derived BODY14."""
    if isinstance(points, AllBut):
        unknown = [n for n in points.names if n not in clip.names]
        if unknown:
            raise ValueError(f"no point named {', '.join(unknown)} to leave out (its points: "
                             f"{', '.join(clip.names[:8])}{' ...' if clip.n_points > 8 else ''})")
        keep = [n for n in clip.names if n not in points.names]
        if len(keep) < 3:
            raise ValueError(f"leaving out {', '.join(points.names)} leaves {len(keep)} points; a model needs 3")
        points = keep                  # the clip's own names: selected below
    if isinstance(points, str):
        if points.lower() == "all":
            return clip
        if points.lower() == "body14":
            return derive_body14(clip, marker_set)
        raise ValueError(f"points must be 'all', 'body14' or a list of names, got {points!r}")
    names = list(points)
    if all(n in clip.names for n in names):
        out = clip.select(names)
        out.meta.pop("parents", None)  # parent indices refer to the unselected columns
        return out
    b14 = derive_body14(clip, marker_set)
    cols = [clip.positions[:, clip.index(n)] if n in clip.names else b14.positions[:, b14.index(n)] for n in names]
    return clip._replace(positions=np.stack(cols, axis=1), names=tuple(names),
                         meta=dict(b14.meta, point_set="custom"))


def model_points(clip: MotionClip, labels: Sequence[str]) -> MotionClip:
    """The clip's points named like a model's ``labels``, in that order (the 14 body points
    are derived from markers or joints when the model uses them). ValueError naming the
    missing points otherwise."""
    if set(labels) <= set(clip.names):
        return clip.select(labels)
    if set(labels) <= set(BODY14):
        return to_point_set(clip, "body14").select(labels)
    missing = sorted(set(labels) - set(clip.names))
    raise ValueError(f"{clip.source}: has no points named {', '.join(missing[:6])}"
                     f"{' ...' if len(missing) > 6 else ''} (model labels)")


# ---------------------------------------------------------------- left / right
_MIRROR_RULES = (  # tried in order; group 'side' holds the side marker
    re.compile(r"(?i)(?P<side>left|right)"),                  # LeftArm, right_knee
    re.compile(r"^(?P<side>[LlRr])(?=[_.\- ])"),              # L_SAJ, l.hand
    re.compile(r"(?<=[_.\- ])(?:[FBfb])?(?P<side>[LlRr])$"),  # Shoulder_L, Head_FL, Hip_BR
    re.compile(r"^(?P<side>[LR])(?=[A-Z0-9])"),               # LSHO, LHipJoint, LThumb
    re.compile(r"^(?P<side>[lr])(?=[a-z])"),                  # lhip, lfemur
)


def _swap_char(c: str) -> str:
    return {"l": "r", "r": "l", "L": "R", "R": "L"}[c]


def _swap_word(w: str) -> str:
    repl = "right" if w.lower() == "left" else "left"
    if w.isupper():
        return repl.upper()
    if w[0].isupper():
        return repl.capitalize()
    return repl


def mirror_name(name: str) -> str | None:
    """The opposite-side label by naming style (``LeftArm<->RightArm``, ``L_SAJ<->R_SAJ``,
    ``Shoulder_L<->Shoulder_R``, ``LSHO<->RSHO``, ``lhip<->rhip``), or None when the name
    has no side marker. The result may not exist in a given set (``lowerback`` ->
    ``rowerback``); :func:`left_right_pairs` only pairs names that both exist."""
    for rx in _MIRROR_RULES:
        m = rx.search(name)
        if m:
            a, b = m.span("side")
            w = m.group("side")
            return name[:a] + (_swap_word(w) if len(w) > 1 else _swap_char(w)) + name[b:]
    return None


def side_of(name: str) -> str | None:
    """'L', 'R' or None: which side ``name`` is on by the same rules as :func:`mirror_name`."""
    for rx in _MIRROR_RULES:
        m = rx.search(name)
        if m:
            return "L" if m.group("side")[0].lower() == "l" else "R"
    return None


def left_right_pairs(names: Sequence[str]) -> list[tuple[str, str]]:
    """(left, right) label pairs present in ``names``, in order of the left label."""
    have = set(names)
    pairs = []
    for n in names:
        m = mirror_name(n)
        if m is not None and m in have and m != n and side_of(n) == "L" and side_of(m) == "R":
            pairs.append((n, m))
    return pairs
