"""How long each point has stayed put: the evidence that tells a fixed reflection from a body marker.

A capture volume keeps reflections the cameras could not mask (floor tape, a force plate's
edge, a prop): points that sit at one place for the whole take. A body marker also stands
still -- a foot in stance, a hand at rest -- but for a while: on the shared takes the longest
rest of a marker (within 1 cm) is 0.1-1.4 s in walks, runs and the skeletal dances, 2-3.8 s in
CMU 85's breakdance and the MoCap Toolbox dance, and up to 37 s for a foot of HDM05's
standing actor (median 2.2 s there). A point's *rest* -- the time it has stayed within
:data:`REST_RADIUS_M` of where it stopped -- is what the clutter model's fixed part reads
(:class:`~dtm_labeler.search.problem.Background`): a still point is scored as possibly a
reflection only once it has rested longer than its label's limit -- the floor, or 1.5 x the
longest rest that label took in the training takes (:func:`longest_rests`).

:class:`RestClock` keeps one rest per track and carries it across a reflection's flicker: a
new track that begins where an ended one rested continues that rest (a reflection seen every
other frame ends its track after the tracker's ``max_misses`` and starts another at the same
place). Per frame the work is one compiled pass over the frame's points (12 us at 45) and, for
new tracks only, a (new x remembered) distance table.
"""
from __future__ import annotations

import numpy as np
from numba import njit

#: a point that stays within this of where it stopped is resting (a reflection's jitter is
#: under a millimetre; a marker on a planted foot moves a few)
REST_RADIUS_M = 0.01
#: how long a rest is remembered after its track was last seen (a flickering reflection's
#: longest dark spell the clock bridges)
REST_MEMORY_S = 5.0
#: most rests remembered at once (oldest seen dropped first): bounded work per frame
REST_TABLE = 256


class RestClock:
    """Per track: where its current rest began (anchor), since when, and when it was last seen."""

    def __init__(self, radius_m: float = REST_RADIUS_M, memory_s: float = REST_MEMORY_S):
        if not radius_m > 0 or not memory_s >= 0:
            raise ValueError("the rest radius must be > 0 and the memory >= 0")
        self.radius = float(radius_m)
        self.memory = float(memory_s)
        self.reset()

    def reset(self) -> None:
        self.ids = np.zeros(0, dtype=np.int64)     # track ids, sorted
        self.anchor = np.zeros((0, 3))             # where each rest began
        self.since = np.zeros(0)                   # ... and when
        self.seen = np.zeros(0)                    # when the track was last seen
        self.episode = np.zeros(0, dtype=np.int64)  # a number per rest (new anchor = new episode)
        self._next_episode = 0

    def update(self, track_ids: np.ndarray, xyz: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Rest (seconds; 0 where the point just stopped or moved) and rest episode of each of
        the frame's points ``xyz`` (n, 3) on tracks ``track_ids`` (n,: distinct, >= 0) at time ``t``."""
        tid = np.ascontiguousarray(track_ids, dtype=np.int64).reshape(-1)
        xyz = np.ascontiguousarray(xyz, dtype=np.float64).reshape(-1, 3)
        t = float(t)
        if self.seen.size and (self.seen.size > REST_TABLE or t - self.seen.min() > self.memory):
            self._forget(t)
        rows = np.full(tid.size, -1, dtype=np.int64)
        self._next_episode = _known_tracks(self.ids, self.anchor, self.since, self.seen, self.episode, tid, xyz, t,
                                           self.radius, self._next_episode, rows)
        new = np.flatnonzero(rows < 0)
        if new.size:
            self._begin(tid, xyz, t, rows, new)
        return t - self.since[rows], self.episode[rows]

    def _begin(self, tid, xyz, t, rows, new) -> None:
        """Rows for the frame's tracks the table does not hold: a rest a track not in this frame
        left at the point's place (a flickering reflection's new track continues it), else a new one."""
        if self.ids.size:
            absent = np.ones(self.ids.size, dtype=bool)
            absent[rows[rows >= 0]] = False
            cand = np.flatnonzero(absent)
            if cand.size:
                d = np.linalg.norm(xyz[new, None] - self.anchor[cand][None], axis=2)
                near = d.argmin(1)
                ok = d[np.arange(new.size), near] <= self.radius
                take, first = np.unique(cand[near[ok]], return_index=True)   # one new track per rest
                src = new[ok][first]
                self.ids[take] = tid[src]
                self.seen[take] = t
                rows[src] = take
        grow = np.flatnonzero(rows < 0)
        k = grow.size
        if k:
            rows[grow] = self.ids.size + np.arange(k)
            self.ids = np.concatenate([self.ids, tid[grow]])
            self.anchor = np.concatenate([self.anchor, xyz[grow]])
            self.since = np.concatenate([self.since, np.full(k, t)])
            self.seen = np.concatenate([self.seen, np.full(k, t)])
            self.episode = np.concatenate([self.episode, self._next_episode + np.arange(k, dtype=np.int64)])
            self._next_episode += k
        order = np.argsort(self.ids, kind="stable")                    # the table stays sorted by id
        inverse = np.empty_like(order)
        inverse[order] = np.arange(order.size)
        self._take(order)
        rows[:] = inverse[rows]

    def _forget(self, t: float) -> None:
        """Drop rests not seen for :data:`REST_MEMORY_S` (and the oldest beyond :data:`REST_TABLE`)."""
        keep = t - self.seen <= self.memory
        if keep.sum() > REST_TABLE:
            keep &= self.seen >= np.sort(self.seen)[-REST_TABLE]
        if not keep.all():
            self._take(keep)

    def _take(self, index: np.ndarray) -> None:
        for name in ("ids", "anchor", "since", "seen", "episode"):
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[index]))


@njit(cache=True)
def _known_tracks(ids, anchor, since, seen, episode, tid, xyz, t, radius, next_episode, rows):  # pragma: no cover
    """For each point on a track the table holds (``ids`` sorted): its row in ``rows``, a new
    rest where it left its anchor by more than ``radius``, seen at ``t``. Returns the next
    episode number."""
    r2 = radius * radius
    for p in range(tid.size):
        i = np.searchsorted(ids, tid[p])
        if i >= ids.size or ids[i] != tid[p]:
            continue
        rows[p] = i
        d2 = 0.0
        for c in range(3):
            e = xyz[p, c] - anchor[i, c]
            d2 += e * e
        if not d2 <= r2:
            for c in range(3):
                anchor[i, c] = xyz[p, c]
            since[i] = t
            episode[i] = next_episode
            next_episode += 1
        seen[i] = t
    return next_episode


def take_rests(xyz, track_ids, rate: float, radius_m: float = REST_RADIUS_M) -> list[np.ndarray]:
    """Per frame of a whole take, each point's rest *over the take*: the full length of the rest
    episode it is in (its past and its future), the offline counterpart of :class:`RestClock`'s
    rest so far -- a reflection is known as one from its first frame."""
    clock = RestClock(radius_m)
    sizes = [len(t) for t in track_ids]
    rests, episodes = [], []
    for f, (x, tid) in enumerate(zip(xyz, track_ids)):
        tid = np.asarray(tid, dtype=np.int64)
        r, e = np.zeros(tid.size), np.full(tid.size, -1, dtype=np.int64)
        ok = tid >= 0                                    # untracked points never rest
        r[ok], e[ok] = clock.update(tid[ok], np.asarray(x, dtype=np.float64).reshape(-1, 3)[ok], f / float(rate))
        rests.append(r)
        episodes.append(e)
    if not sum(sizes):
        return [np.zeros(0) for _ in sizes]
    ep = np.concatenate(episodes)
    rest = np.concatenate(rests)
    longest = np.zeros(int(ep.max()) + 2)               # slot -1: the untracked points (0)
    np.maximum.at(longest, ep, rest)
    longest[-1] = 0.0
    return np.split(longest[ep], np.cumsum(sizes)[:-1])


def longest_rests(clips) -> np.ndarray:
    """(M,) each point's longest rest (seconds) over the clips (sharing their point order): what a
    model keeps of its training takes (``settings["longest_rest_s"]``) so that a label is allowed
    the rests its body point took (:meth:`~dtm_labeler.model.dtm.TriangulatedModel.rest_limits`).
    A point's rest goes on across its gaps (up to :data:`REST_MEMORY_S`) when it comes back within
    :data:`REST_RADIUS_M` -- a gappy take's stance foot rests as long as a clean one's."""
    longest = None
    for clip in clips:
        P = np.asarray(clip.positions, dtype=np.float64)
        if longest is None:
            longest = np.zeros(P.shape[1])
        seen = np.isfinite(P).all(-1)
        labels = [np.flatnonzero(ok) for ok in seen]           # the labels are the tracks
        rests = take_rests([P[f, lab] for f, lab in enumerate(labels)], labels, float(clip.rate))
        if seen.any():
            np.maximum.at(longest, np.concatenate(labels), np.concatenate(rests))
    return np.zeros(0) if longest is None else longest
