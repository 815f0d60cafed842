"""Anonymous model points: unlabelled trajectories of a training capture that ride on the body.

Why. A real capture often holds markers the labelling set does not name: a back marker, a
finger, a toe or a prop left out of the skeleton, written as ``*`` channels. The model learns
nothing of them, so on a new take such a marker is only clutter to it (the paper's uniform
background, eq. 29). When the named marker beside it is hidden -- its neighbours in the DTM
too, as in real occlusions -- the real marker fits the hidden one's place well enough that
labelling it is more likely than clutter: in HDM05's gapped second half with six unnamed
markers as ``*`` channels, a back marker took RSHO's label in all of its 539 samples
(``results/captures.md``).

The reading. What the labeler is missing is a hypothesis for those markers. The paper's
model gives one without a new term: a point of the DTM. Each unlabelled trajectory of the
training capture that is seen often enough to be learnt (the coverage floors of
:mod:`.gaps`) and rides on the body -- its distance to some named marker hardly varies
(:data:`RIGID_SPREAD_M`), and it stays near it (:data:`NEAR_M`) -- becomes a model point
named ``*by<MARKER>`` (a ``*`` name: unlabelled, :func:`~dtm_labeler.motion.naming.is_unnamed`).
It is trained as any point -- structure, triangle mixtures (eq. 12-13), body terms -- and
searched as any label, so eq. 14 now compares "the marker beside a hidden RSHO is RSHO" with
"it is the marker the training saw there", and its own triangles decide. The labeler
publishes it as unlabelled (:attr:`TriangulatedModel.anonymous
<dtm_labeler.model.dtm.TriangulatedModel>`): a consumer sees the named labels only, and the
point counts as a rejected ghost.

Not taken: a trajectory never seen in a frame where some named marker is seen, though that
marker is seen often (:data:`EXCLUSIVE_SHARE`): an unlabelled *fragment* of that marker (what
a system's auto-labelling leaves behind at a gap) would otherwise become a point competing
with the marker itself. Several captures (``dtm-train a.c3d b.c3d``) take none: their ``*``
channels are not one marker across files.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..motion.clip import MotionClip
from ..motion.unlabelled import unlabelled_channels
from .gaps import MIN_COVERAGE, MIN_SEEN_FRAMES

#: robust spread (m) of the distance to a named marker under which a trajectory rides on its segment
RIGID_SPREAD_M = 0.015
#: ... and the median distance (m) within which it stays (a marker on the same segment)
NEAR_M = 0.35
#: a trajectory seen with a named marker in under this share of the frames expected from their
#: coverage is taken for that marker's fragment
EXCLUSIVE_SHARE = 0.1

__all__ = ["RidingMarker", "riding_markers", "with_riding_markers", "RIGID_SPREAD_M", "NEAR_M"]


@dataclass(frozen=True)
class RidingMarker:
    """One unlabelled trajectory taken as an anonymous model point."""

    name: str            # the model point's name, ``*by<partner>``
    channel: str         # the capture's channel it came from
    partner: str         # the named marker it rides with
    spread_m: float      # robust spread of their distance
    distance_m: float    # median distance
    coverage: float      # share of the frames it is seen in


def _robust_spread(d: np.ndarray) -> float:
    q1, q3 = np.percentile(d, [25, 75])
    return float((q3 - q1) / 1.349)


def riding_markers(clip: MotionClip) -> list[RidingMarker]:
    """The unlabelled trajectories of ``clip`` that ride on the body (module doc), best first."""
    pts, names = unlabelled_channels(clip)
    if not len(names) or not clip.n_points:
        return []
    F = clip.n_frames
    named_seen = np.isfinite(clip.positions).all(-1)                 # (F, M)
    floor = max(MIN_SEEN_FRAMES, int(np.ceil(MIN_COVERAGE * F)))
    out: list[RidingMarker] = []
    used: dict[str, int] = {}
    for k, ch in enumerate(names):
        seen = np.isfinite(pts[:, k]).all(-1)
        if (seen[1:] & seen[:-1]).sum() < floor:         # seen with a velocity, as the coverage check counts
            continue
        both = named_seen & seen[:, None]                             # (F, M)
        expected = seen.mean() * named_seen.sum(0)
        if ((both.sum(0) < EXCLUSIVE_SHARE * expected) & (expected >= MIN_SEEN_FRAMES)).any():
            continue                                                  # a named marker's fragment
        best = None
        for m in np.flatnonzero(both.sum(0) >= floor):
            d = np.linalg.norm(pts[both[:, m], k] - clip.positions[both[:, m], m], axis=-1)
            med, spread = float(np.median(d)), _robust_spread(d)
            if med <= NEAR_M and spread <= RIGID_SPREAD_M and (best is None or spread < best[1]):
                best = (int(m), spread, med)
        if best is None:
            continue
        partner = clip.names[best[0]]
        used[partner] = used.get(partner, 0) + 1
        name = f"*by{partner}" + (f"_{used[partner]}" if used[partner] > 1 else "")
        out.append(RidingMarker(name, ch, partner, best[1], best[2], float(seen.mean())))
    return out


def with_riding_markers(clips: Sequence[MotionClip], leave_out: Sequence[str] = ()
                        ) -> tuple[list[MotionClip], list[RidingMarker]]:
    """``clips`` with the riding trajectories of a single capture appended as anonymous points
    (module doc), but those named in ``leave_out``, and what was taken. Several clips are
    returned as they are."""
    clips = list(clips)
    if len(clips) != 1:
        return clips, []
    clip = clips[0]
    riding = [r for r in riding_markers(clip) if r.name not in set(leave_out)]
    if not riding:
        return clips, []
    pts, names = unlabelled_channels(clip)
    cols = [names.index(r.channel) for r in riding]
    taken = set(cols)
    meta = dict(clip.meta)
    if isinstance(meta.get("unlabelled"), np.ndarray):     # the rest stay unlabelled channels
        rest = [k for k in range(len(names)) if k not in taken]
        meta["unlabelled"] = pts[:, rest]
        meta["unlabelled_names"] = tuple(names[k] for k in rest)
        meta["unlabelled_duplicates"] = {}
    out = clip._replace(positions=np.concatenate([clip.positions, pts[:, cols]], axis=1),
                        names=tuple(clip.names) + tuple(r.name for r in riding), meta=meta)
    return [out], riding
