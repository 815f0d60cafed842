"""Checks that save a user's day: units that cannot be a human body, rates that disagree with stamps.

Both raise ``ValueError`` with a message that says what was measured, what it should be,
and what to pass instead, because the failure they prevent is silent and total: a take in
millimetres read as metres has velocities of kilometres per second (every triangle density
rejects it), a 120 Hz take labelled as 60 Hz has half its true velocities.

* :func:`check_body_units` -- on clips in metres: the median over frames of the body's
  longest extent (a person: 0.25-3.5 m, from a crouch to arms overhead) and of the distance
  from each point to its nearest neighbour (markers and joints: 2 mm-0.8 m). Either outside
  its range names the unit the numbers look like (mm, cm, m, inch).
* :func:`check_rate` -- a declared rate against the file's time stamps (2 % tolerance).

Clips with fewer than 5 visible points per frame are not judged (no body to measure).
"""
from __future__ import annotations

import math

import numpy as np

EXTENT_RANGE_M = (0.25, 3.5)
NEIGHBOUR_RANGE_M = (0.002, 0.8)
TYPICAL_EXTENT_M = 1.6
RATE_TOLERANCE = 0.02
_UNITS_M = {"mm": 1e-3, "cm": 1e-2, "inch": 0.0254, "dm": 0.1, "m": 1.0}


def body_size(positions: np.ndarray, max_frames: int = 300) -> tuple[float, float]:
    """``(median longest extent, median nearest-neighbour distance)`` of (F, N, 3) points,
    NaN when no frame shows 5 points."""
    P = np.asarray(positions, dtype=np.float64)
    if P.ndim != 3 or P.shape[0] == 0 or P.shape[1] < 5:
        return float("nan"), float("nan")
    P = P[np.linspace(0, P.shape[0] - 1, min(P.shape[0], max_frames)).astype(np.int64)]
    seen = np.isfinite(P).all(-1)
    P = P[seen.sum(1) >= 5]
    if not len(P):
        return float("nan"), float("nan")
    ext = (np.nanmax(P, axis=1) - np.nanmin(P, axis=1)).max(axis=1)
    d = np.linalg.norm(P[:, :, None, :] - P[:, None, :, :], axis=-1)
    n = P.shape[1]
    d[:, np.arange(n), np.arange(n)] = np.inf
    d = np.where(np.isfinite(d), d, np.inf)
    nn = d.min(axis=2)
    nn = nn[np.isfinite(nn) & (nn > 0)]
    return float(np.median(ext)), float(np.median(nn)) if nn.size else float("nan")


def likely_unit(extent_m: float, unit_scale: float) -> str:
    """The unit whose reading makes a body of ``extent_m`` (read with ``unit_scale`` m per
    unit) closest to a typical person (1.6 m)."""
    raw = extent_m / unit_scale                          # the number in the file
    return min(_UNITS_M, key=lambda u: abs(math.log(raw * _UNITS_M[u] / TYPICAL_EXTENT_M)))


def check_body_units(positions: np.ndarray, unit_scale: float = 1.0, units: str = "", where: str = "") -> None:
    """Raise ValueError when the points (metres) cannot be a human body (see module doc)."""
    ext, nn = body_size(positions)
    if not np.isfinite(ext):
        return
    bad_ext = not EXTENT_RANGE_M[0] <= ext <= EXTENT_RANGE_M[1]
    bad_nn = np.isfinite(nn) and not NEIGHBOUR_RANGE_M[0] <= nn <= NEIGHBOUR_RANGE_M[1]
    far_off = not EXTENT_RANGE_M[0] / 10 <= ext <= EXTENT_RANGE_M[1] * 10
    if not (bad_ext and (bad_nn or far_off)):     # a few markers on one limb may measure 10 cm
        return
    guess = likely_unit(ext, unit_scale)
    said = f"the file's units ({units!r})" if units else f"the units used ({unit_scale:g} m per unit)"
    raise ValueError(
        f"{where + ': ' if where else ''}the body measures {ext:.4g} m along its longest axis and neighbouring "
        f"points are {nn:.3g} m apart (medians over frames); a person measures {EXTENT_RANGE_M[0]:g}-"
        f"{EXTENT_RANGE_M[1]:g} m with points {NEIGHBOUR_RANGE_M[0] * 1000:g} mm-{NEIGHBOUR_RANGE_M[1]:g} m apart. "
        f"{said[0].upper() + said[1:]} look wrong: the numbers look like {guess} (pass --units {guess})")


def check_rate(rate: float, times: np.ndarray, where: str = "", what: str = "the rate") -> None:
    """Raise ValueError when ``rate`` (Hz) disagrees with the time stamps ``times`` (s) by more
    than 2 % (median step). Fewer than 3 stamps, or non-increasing ones, are not judged."""
    t = np.asarray(times, dtype=np.float64)
    if t.size < 3:
        return
    dt = np.diff(t)
    dt = dt[np.isfinite(dt)]
    if not dt.size or np.median(dt) <= 0:
        return
    stamped = 1.0 / float(np.median(dt))
    if abs(stamped / rate - 1.0) > RATE_TOLERANCE:
        raise ValueError(f"{where + ': ' if where else ''}{what} is {rate:g} Hz but the time stamps advance "
                         f"{1000 * np.median(dt):.4g} ms per frame ({stamped:.4g} Hz); velocities would be off by "
                         f"a factor {rate / stamped:.3g}: fix the rate or the stamps in the file")
