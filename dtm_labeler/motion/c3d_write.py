"""Write marker trajectories as a C3D file (via ezc3d), the way C3D readers expect them.

``POINT:LABELS`` (one per channel; unlabelled channels as ``*N``), ``POINT:UNITS`` and the
numbers in those units, ``POINT:RATE`` (and the header rate), the header's first frame,
``POINT:X_SCREEN``/``Y_SCREEN`` for the vertical, floating-point data (``POINT:SCALE`` -1).
A missing sample is written the C3D way: coordinates 0 and residual -1 (ezc3d and the usual
viewers read it as a gap; :func:`~dtm_labeler.motion.c3d.load_c3d` gives NaN back).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from .axes import check_axis, from_z_up

UNITS_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "dm": 0.1}
# screen axes that put ``up`` up (right-handed view, first axis to the right)
DEFAULT_SCREEN = {"Z": ("+X", "+Z"), "Y": ("+X", "+Y"), "X": ("+Y", "+X")}


def write_c3d(path: str | Path, positions: np.ndarray, names: Sequence[str], rate: float, units: str = "mm",
              up_axis: str = "Z", first_frame: int = 0, screen: tuple[str, str] | None = None,
              write_screen: bool = True) -> Path:
    """Write (F, N, 3) ``positions`` (metres, Z up, NaN = missing) named ``names`` to ``path``
    in ``units`` with ``up_axis`` vertical (the file's own axes); ``screen`` = (X_SCREEN,
    Y_SCREEN) to keep an input's values (default: the one that shows ``up_axis`` up);
    ``write_screen=False`` leaves them out (as many exporters do)."""
    import ezc3d  # local import: only needed for C3D

    P = np.asarray(positions, dtype=np.float64)
    if P.ndim != 3 or P.shape[2] != 3 or P.shape[1] != len(names):
        raise ValueError(f"positions must be (frames, {len(names)}, 3), got {P.shape}")
    if units not in UNITS_M:
        raise ValueError(f"units must be one of {', '.join(UNITS_M)}, got {units!r}")
    if not rate > 0:
        raise ValueError(f"rate must be positive, got {rate}")
    up = check_axis(up_axis)
    F, N, _ = P.shape
    xyz = from_z_up(P, up) / UNITS_M[units]
    missing = ~np.isfinite(xyz).all(axis=2)                         # (F, N)
    xyz[missing] = 0.0
    data = np.ones((4, N, F))
    data[:3] = np.transpose(xyz, (2, 1, 0))
    residuals = np.where(missing.T, -1.0, 0.0)[None]                # (1, N, F)
    c = ezc3d.c3d()
    pt = c["parameters"]["POINT"]
    pt["RATE"]["value"] = [float(rate)]
    pt["LABELS"]["value"] = tuple(str(n) for n in names)
    pt["DESCRIPTIONS"]["value"] = tuple("" for _ in names)
    c["data"]["points"] = data
    c["data"]["meta_points"] = {"residuals": residuals, "camera_masks": np.zeros((7, N, F), dtype=bool)}
    c.add_parameter("POINT", "UNITS", units)
    try:                                   # an input's screen axes, when they agree with the vertical
        keep = screen is not None and check_axis(screen[1]) == up
    except ValueError:
        keep = False
    xs, ys = screen if keep else DEFAULT_SCREEN[up]
    if write_screen:
        c.add_parameter("POINT", "X_SCREEN", xs)
        c.add_parameter("POINT", "Y_SCREEN", ys)
    c["header"]["points"]["first_frame"] = int(first_frame)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    c.write(str(path))
    return path
