"""Unlabelled fragments of named markers: a ``*`` trajectory that carries a named one across its gap.

Why. A system's auto-labelling breaks a named trajectory where it loses the marker for a
moment (an occlusion, a merge with a neighbour), tracks the marker on as a new trajectory and,
not sure whose it is, writes that as an unlabelled ``*`` channel (Vicon Nexus, QTM). Such a
fragment is not a ghost: it is the named marker, seen. Fed to the labeler as an extra point
it is scored as a ghost to reject -- the labeler that gives it its marker's name, which is
right, is counted wrong -- and in training its frames are lost to the marker's coverage
(:mod:`dtm_labeler.training.gaps`).

The rule is the one a system's own gap filling reads, a trajectory's continuity. A run of
frames in which an unlabelled channel is seen is a fragment of named marker ``M`` when

* ``M`` is unseen in every frame of the run (one marker is never two points at once);
* the run starts where ``M``'s trajectory stopped -- at most :data:`MAX_GAP_S` later, its first
  point within :func:`tolerance` of ``M``'s last point carried on at ``M``'s last velocity --
  or ends where ``M``'s trajectory resumes (the same, backwards in time); or it does both,
  each within :data:`MAX_BRIDGE_S` (a marker lost, then tracked on unlabelled after an
  occlusion until the system labels it again: the tolerance grows with the gap, and both
  ends must meet the one trajectory);
* the run copies no seen named marker in any frame (:data:`COPY_M`: a partial copy of a
  channel is that channel's point, not another's fragment);
* no other named marker continues into it as well: the runner-up's distance, in tolerances,
  is at least :data:`CLEAR_RATIO` times the best one's (else the run stays unlabelled).

A joined run extends ``M``'s trajectory, so a chain of fragments joins run by run. Other
channels' points never move. A ghost beside a marker never qualifies (it is seen with the
marker), nor does another marker passing by (it is seen with it before or after; and a marker
riding on the body is not where the named one vanished at the frame it vanished).
Copies of a channel (:mod:`.naming`) are left out before this.

Pure numpy over the channels' runs; a loader's step, not the live path (a live point cloud has
no channels).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .naming import ChannelSplit

#: a fragment may start at most this long after its marker's last sample (or end this long before it resumes)
MAX_GAP_S = 0.025
#: ... or, when both its ends meet the marker's trajectory, this long on each side
MAX_BRIDGE_S = 0.25
#: how far (m) a fragment's first point may lie from where its marker was heading, before speed
BASE_TOLERANCE_M = 0.01
#: ... plus this share of the displacement over the gap at the marker's (or the run's) last velocity
SPEED_SHARE = 0.25
#: a run that comes this near (m) a seen named marker in any of its frames is a copy of it, not a fragment
COPY_M = 0.002
#: the runner-up marker must fit at least this many times worse, in tolerances
CLEAR_RATIO = 2.0
#: at most this many passes (each joins what the last one's joins made continuous)
MAX_PASSES = 20

__all__ = ["Fragment", "find_fragments", "join_fragments", "join_channel_fragments", "fragments_note", "tolerance"]


@dataclass(frozen=True)
class Fragment:
    """One run of an unlabelled channel joined to the named marker it continues."""

    channel: str       # the unlabelled channel's name as written
    marker: str        # the named marker it continues
    first: int         # first frame of the run (0-based, within the take)
    last: int          # last frame of the run (inclusive)
    distance_m: float  # how far its joining point lay from where the marker was heading

    @property
    def samples(self) -> int:
        return self.last - self.first + 1

    def as_dict(self) -> dict:
        return {"channel": self.channel, "marker": self.marker, "first": self.first, "last": self.last,
                "distance_m": round(self.distance_m, 4)}


def tolerance(step_m: np.ndarray | float, frames: np.ndarray | int) -> np.ndarray:
    """How far (m) a fragment's joining point may lie from the extrapolated position, given the
    last step it was carried on at (m per frame) and the frames between them."""
    return BASE_TOLERANCE_M + SPEED_SHARE * np.asarray(step_m) * np.asarray(frames)


def _runs(seen: np.ndarray) -> list[tuple[int, int]]:
    """``(first, last)`` of each run of True in ``seen``."""
    if not seen.any():
        return []
    d = np.diff(np.concatenate([[0], seen.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    return list(zip(starts.tolist(), stops.tolist()))


def _copies(named: np.ndarray, run: np.ndarray) -> bool:
    """Whether the run's points (n, 3) coincide with a seen named marker (n, N, 3) in some frame."""
    d = np.linalg.norm(named - run[:, None], axis=2)
    return bool(np.any(d <= COPY_M))


def _end_fit(named: np.ndarray, seen: np.ndarray, point: np.ndarray, inner: np.ndarray, frame: int,
             direction: int, max_gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per named marker, how far the run's edge ``point`` (at ``frame``) and the marker's
    trajectory miss each other when the marker was last seen before ``frame`` (``direction`` -1)
    or first seen after it (+1), within ``max_gap`` missing frames: ``(in tolerances, in metres,
    frames away)``, inf where it was not seen so near. The frame nearest the run's edge in which
    a marker is seen decides for it. Either side's velocity carries it across (the marker's own
    last step, or the run's, ``point - inner``, when the marker shows one frame only there); the
    better reading counts."""
    F, N = seen.shape
    run_step = point - inner if np.isfinite(inner).all() else np.zeros(3)
    run_speed = float(np.linalg.norm(run_step))
    ratio, metres, away = np.full(N, np.inf), np.full(N, np.inf), np.full(N, np.inf)
    for k in range(1, max_gap + 2):
        f = frame + direction * k
        if not 0 <= f < F:
            break
        here = seen[f] & ~np.isfinite(ratio)
        if not here.any():
            continue
        g = f + direction
        step = np.zeros((N, 3))
        if 0 <= g < F:
            both = here & seen[g]
            step[both] = named[f, both] - named[g, both]
        dist = np.linalg.norm(point[None] - (named[f] + step * k), axis=1)          # the marker's heading
        r = dist / tolerance(np.linalg.norm(step, axis=1), k)
        dist_run = np.linalg.norm(named[f] - (point + run_step * k)[None], axis=1)  # the run's
        r_run = dist_run / tolerance(run_speed, k)
        use_run = r_run < r
        ratio[here] = np.where(use_run, r_run, r)[here]
        metres[here] = np.where(use_run, dist_run, dist)[here]
        away[here] = k
    return ratio, metres, away


def find_fragments(named: np.ndarray, names: tuple[str, ...] | list[str], unnamed: np.ndarray,
                   unnamed_names: tuple[str, ...] | list[str], rate: float) -> list[Fragment]:
    """The runs of the ``unnamed`` channels (F, K, 3; NaN = unseen) that continue a ``named``
    marker (F, N, 3) across its gap (module doc), in the order they were joined. Inputs are
    not changed (:func:`join_fragments` moves the points)."""
    return join_fragments(named.copy(), names, unnamed.copy(), unnamed_names, rate)[2]


def join_fragments(named: np.ndarray, names: tuple[str, ...] | list[str], unnamed: np.ndarray,
                   unnamed_names: tuple[str, ...] | list[str], rate: float
                   ) -> tuple[np.ndarray, np.ndarray, list[Fragment]]:
    """``(named, unnamed, fragments)``: the fragments' points moved from their unlabelled channels
    into the named markers they continue (module doc). Works in place on the arrays given."""
    F, N = named.shape[:2]
    K = unnamed.shape[1] if unnamed.ndim == 3 else 0
    found: list[Fragment] = []
    if not F or not N or not K:
        return named, unnamed, found
    max_gap = max(0, int(round(MAX_GAP_S * float(rate))))
    max_bridge = max(max_gap, int(round(MAX_BRIDGE_S * float(rate))))
    seen = np.isfinite(named).all(axis=2)
    for _ in range(MAX_PASSES):
        joined = 0
        useen = np.isfinite(unnamed).all(axis=2)
        for k in range(K):
            for a, b in _runs(useen[:, k]):
                free = ~seen[a:b + 1].any(axis=0)                   # markers unseen over the whole run
                if not free.any() or _copies(named[a:b + 1], unnamed[a:b + 1, k]):
                    continue
                r0, m0, k0 = _end_fit(named, seen, unnamed[a, k], unnamed[min(a + 1, b), k], a, -1, max_bridge)
                r1, m1, k1 = _end_fit(named, seen, unnamed[b, k], unnamed[max(b - 1, a), k], b, +1, max_bridge)
                # one end next to the marker's trajectory, or both ends across a longer gap
                one0, one1 = np.where(k0 <= max_gap + 1, r0, np.inf), np.where(k1 <= max_gap + 1, r1, np.inf)
                ratio = np.minimum(np.minimum(one0, one1), np.maximum(r0, r1))
                metres = np.where(r0 <= r1, m0, m1)
                ratio[~free] = np.inf
                order = np.argsort(ratio)
                best = int(order[0])
                if not ratio[best] <= 1.0:
                    continue
                if N > 1 and ratio[order[1]] < CLEAR_RATIO * max(ratio[best], 1e-9):
                    continue                                         # two markers continue into it
                named[a:b + 1, best] = unnamed[a:b + 1, k]
                unnamed[a:b + 1, k] = np.nan
                seen[a:b + 1, best] = True
                found.append(Fragment(str(unnamed_names[k]), str(names[best]), a, b, float(metres[best])))
                joined += 1
        if not joined:
            break
    return named, unnamed, found


def fragments_note(fragments: list[Fragment]) -> str:
    """One line for a user: how many fragments were joined to which markers ('' for none)."""
    if not fragments:
        return ""
    per: dict[str, int] = {}
    for fr in fragments:
        per[fr.marker] = per.get(fr.marker, 0) + fr.samples
    top = sorted(per.items(), key=lambda kv: -kv[1])
    shown = ", ".join(f"{m} {n}" for m, n in top[:6]) + (" ..." if len(top) > 6 else "")
    return (f"{len(fragments)} unlabelled fragment{'s' if len(fragments) != 1 else ''} "
            f"({sum(per.values())} samples) continue named markers across their gaps and were joined to them "
            f"({shown})")


def join_channel_fragments(xyz: np.ndarray, split: ChannelSplit, rate: float) -> tuple[np.ndarray, list[Fragment]]:
    """A loader's step: ``xyz`` (F, channels, 3, metres, Z up) with the fragments of its unlabelled
    channels moved into the named channels they continue; copies (``split.duplicates``) stay as
    they are. Returns a new array and the fragments joined."""
    indep = [split.unnamed[k] for k in split.independent]
    if not indep or not split.named:
        return xyz, []
    named, unnamed, found = join_fragments(xyz[:, split.named].copy(), split.names, xyz[:, indep].copy(),
                                           [split.unnamed_names[k] for k in split.independent], rate)
    if not found:
        return xyz, []
    out = xyz.copy()
    out[:, split.named] = named
    out[:, indep] = unnamed
    return out, found
