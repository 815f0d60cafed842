"""Which axis of a marker file points up, and the rotations to and from the library's Z up.

Every clip is Z up inside the library. Marker formats say their vertical axis in different
ways, or not at all; :func:`resolve_up_axis` decides, in this order:

1. the user (``--up-axis X|Y|Z``);
2. the file: C3D ``POINT:Y_SCREEN`` (the axis pointing up on the screen; only its letter
   is read -- Qualisys QTM writes ``-Z`` for its Z-up captures, as the shared walk shows),
   our own CSV comment ``# up axis: Y``;
3. the body: the axis along which the visible points spread most in the median frame
   (a person's long axis: standing, walking, dancing, even the shared breakdance take
   reads Z in 75 % of its frames). A take in a T-pose is as wide as tall; then the floor
   decides between the two longest axes: labs put the origin on the floor, so the vertical
   is the one whose lowest point sits at 0-25 cm in the median frame (the feet).

A file's statement is checked against the body: when the body spreads at least
:data:`OVERRULE_RATIO` times as far along another axis as along the stated one, and the
stated axis does not stand on the floor, the body wins, with a note in
``meta['up_axis_note']`` (a wrong vertical makes every heading, and so every label, wrong).
The bar is high because a take of the upper body in a T-pose is wider than tall. Clips with fewer than
:data:`MIN_POINTS` visible points per frame have no usable body: the file's axis or Z.

Only positive axes are handled (``-Y`` up is read as ``Y``); the rotations keep handedness:
``Y`` up: ``(x, y, z) -> (x, -z, y)``; ``X`` up: ``(x, y, z) -> (y, z, x)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

AXES = ("X", "Y", "Z")
CONFIDENT_RATIO = 1.3
MIN_POINTS = 5
OVERRULE_RATIO = 2.0
FLOOR_M = (-0.05, 0.25)          # lowest marker above the lab floor (metres): the feet


def to_z_up(p: np.ndarray, up: str) -> np.ndarray:
    """Points (..., 3) in a file whose vertical is ``up`` -> Z up (proper rotation)."""
    p = np.asarray(p, dtype=np.float64)
    up = check_axis(up)
    if up == "Z":
        return p
    if up == "Y":
        return np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)
    return np.stack([p[..., 1], p[..., 2], p[..., 0]], axis=-1)


def from_z_up(p: np.ndarray, up: str) -> np.ndarray:
    """The inverse of :func:`to_z_up`: Z-up points back into the file's axes."""
    p = np.asarray(p, dtype=np.float64)
    up = check_axis(up)
    if up == "Z":
        return p
    if up == "Y":
        return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)
    return np.stack([p[..., 2], p[..., 0], p[..., 1]], axis=-1)


def check_axis(axis: str) -> str:
    """``'x'``, ``'+Y'``, ``'-z'`` ... -> ``'X'``/``'Y'``/``'Z'``; ValueError otherwise."""
    a = str(axis).strip().upper().lstrip("+-")
    if a not in AXES:
        raise ValueError(f"up_axis must be X, Y or Z, got {axis!r}")
    return a


@dataclass
class BodyAxis:
    """The body's long axis over a take: ``axis`` (None without a body), the median extent of
    the visible points along X, Y, Z per frame (metres or file units), and how clear it is."""

    axis: str | None
    extents: np.ndarray
    ratio: float
    by_floor: bool = False
    lows: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))   # median lowest point per axis

    def on_floor(self, axis: str) -> bool:
        low = self.lows[AXES.index(axis)]
        return bool(FLOOR_M[0] <= low <= FLOOR_M[1])

    @property
    def confident(self) -> bool:
        return self.axis is not None and (self.ratio >= CONFIDENT_RATIO or self.by_floor)


def body_axis(xyz: np.ndarray, max_frames: int = 600) -> BodyAxis:
    """:class:`BodyAxis` of (F, N, 3) points in metres (NaN = missing), in the file's own axes."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 3 or xyz.shape[0] == 0 or xyz.shape[1] == 0:
        return BodyAxis(None, np.full(3, np.nan), 0.0)
    idx = np.linspace(0, xyz.shape[0] - 1, min(xyz.shape[0], max_frames)).astype(np.int64)
    P = xyz[idx]
    seen = np.isfinite(P).all(-1)
    enough = seen.sum(1) >= MIN_POINTS
    if not enough.any():
        return BodyAxis(None, np.full(3, np.nan), 0.0)
    ext = np.nanmax(P[enough], axis=1) - np.nanmin(P[enough], axis=1)     # (f, 3): >= 5 points each
    med = np.median(ext, axis=0)
    order = np.argsort(med)[::-1]
    ratio = float(med[order[0]] / med[order[1]]) if med[order[1]] > 0 else float("inf")
    low = np.median(np.nanmin(P[enough], axis=1), axis=0)
    if ratio < CONFIDENT_RATIO:                       # as wide as tall: which of the two stands on the floor?
        on_floor = [int(a) for a in order[:2] if FLOOR_M[0] <= low[a] <= FLOOR_M[1]]
        if len(on_floor) == 1:
            return BodyAxis(AXES[on_floor[0]], med, ratio, by_floor=True, lows=low)
    return BodyAxis(AXES[int(order[0])], med, ratio, lows=low)


@dataclass
class UpAxis:
    """The decision of :func:`resolve_up_axis`: ``axis``, where it came from, and a note
    (empty unless the body overruled the file)."""

    axis: str
    source: str
    note: str = ""


def resolve_up_axis(xyz: np.ndarray, forced: str | None = None, file_axis: str | None = None,
                    file_source: str = "file", default: str = "Z", where: str = "") -> UpAxis:
    """Decide the vertical axis of ``xyz`` (F, N, 3, file axes) as described in the module doc."""
    if forced is not None and str(forced).lower() != "auto":
        return UpAxis(check_axis(forced), "--up-axis")
    body = body_axis(xyz)
    if file_axis:
        fa = check_axis(file_axis)
        spread = body.extents[AXES.index(body.axis)] / body.extents[AXES.index(fa)] if body.axis else 0.0
        if body.axis is not None and body.axis != fa and spread >= OVERRULE_RATIO and not body.on_floor(fa):
            note = (f"{where + ': ' if where else ''}{file_source} says {file_axis!r} is up but the body's long axis "
                    f"is {body.axis} (median extents X {body.extents[0]:.3g}, Y {body.extents[1]:.3g}, "
                    f"Z {body.extents[2]:.3g}); using {body.axis} (force with --up-axis)")
            return UpAxis(body.axis, "body", note)
        return UpAxis(fa, file_source)
    if body.axis is not None and body.confident:
        return UpAxis(body.axis, "body")
    return UpAxis(check_axis(default), "default")
