"""DERIVED joint-position CSVs (``cmu_skeletal/positions_csv``) -> MotionClip (metres, Z up).

Layout: ``#`` comment lines, header ``frame,time_s,<joint>_x,<joint>_y,<joint>_z,...``;
values in **metres**, CMU world frame, **Y up** (converted with ``(x,y,z)->(x,-z,y)``).
``frame`` is the source frame number (AMC number, or BVH index with the T-pose frame 0
dropped); it is kept in ``meta['frame_numbers']``. Joints: ``root lhip rhip lknee rknee
lankle rankle neck head headtop lshoulder rshoulder lelbow relbow lwrist rwrist``.
"""
from __future__ import annotations

from pathlib import Path

from .bvh import y_up_to_z_up
from .clip import MotionClip
from .markers_csv import read_xyz_csv

POSITIONS16 = ("root", "lhip", "rhip", "lknee", "rknee", "lankle", "rankle", "neck", "head", "headtop",
               "lshoulder", "rshoulder", "lelbow", "relbow", "lwrist", "rwrist")


def load_positions_csv(path: str | Path, up_axis: str = "Y") -> MotionClip:
    """Derived joint positions CSV -> MotionClip (metres, Z up).
    ``meta``: ``format``, ``frame_numbers``, ``comments``."""
    t = read_xyz_csv(path)
    up = up_axis.upper()
    if up not in ("Y", "Z"):
        raise ValueError(f"{path}: up_axis must be 'Y' or 'Z', got {up_axis!r}")
    xyz = y_up_to_z_up(t.xyz) if up == "Y" else t.xyz
    return MotionClip(positions=xyz, rate=t.rate(), names=t.names, source=str(path),
                      meta=dict(format="positions_csv", frame_numbers=t.frames, comments=t.comments))
