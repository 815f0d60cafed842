"""How long each track has carried each label: the memory behind the fast path's hold prior.

Eq. 32 counts, per track, the frames in which the search gave it each label; read as a hidden
Markov chain over a track's label, a trajectory keeps the label it has carried unless a frame's
evidence outweighs the prior against changing it. :class:`LabelTenure` keeps, for every (track,
label) pair the labeler has published, the stream time it was first published -- also while the
label is briefly elsewhere, so a label that flickers to a neighbour and back keeps the tenure it
had. Pairs go when their track does. Beside them, the chain's other state: since when each track
has been left unlabelled without a break (:meth:`LabelTenure.clutter_since`; eq. 18-20's background
class, which a ghost holds while the body's markers hold their labels). Sorted int64 keys, no Python loop over tracks; a lookup
(:meth:`LabelTenure.held_for`, asked 5-8 times a frame by the fast path's priors and the
published confidence) is one compiled loop (:func:`_held`; in numpy 8-12 us each).
"""
from __future__ import annotations

import numpy as np
from numba import njit


class LabelTenure:
    """First stream time at which each (track, label) pair was published."""

    def __init__(self, n_labels: int):
        self.n_labels = int(n_labels)
        self.reset()

    def reset(self) -> None:
        self._keys = np.zeros(0, dtype=np.int64)     # track * n_labels + label, sorted
        self._first = np.zeros(0)                    # stream time of each key's first publication
        self._idle = np.zeros(0, dtype=np.int64)     # tracks left unlabelled since ``_since``, sorted
        self._since = np.zeros(0)
        self.last_published = np.full(self.n_labels, -np.inf)   # stream time each label was last on a track

    def __len__(self) -> int:
        return self._keys.size

    def _key(self, track_ids, labels) -> np.ndarray:
        return np.asarray(track_ids, dtype=np.int64) * self.n_labels + np.asarray(labels, dtype=np.int64)

    def update(self, track_ids: np.ndarray, labels: np.ndarray, lost: np.ndarray, stamp: float) -> None:
        """This frame's labels (``labels[i]`` of track ``track_ids[i]``, -1 none) at ``stamp``;
        the pairs of ``lost`` tracks are forgotten."""
        track_ids = np.asarray(track_ids, dtype=np.int64)
        labels = np.asarray(labels, dtype=np.int64)
        has = labels >= 0
        keys, first = self._keys, self._first
        lost = np.asarray(lost, dtype=np.int64)
        if lost.size and keys.size:
            keep = ~np.isin(keys // self.n_labels, lost)
            keys, first = keys[keep], first[keep]
        new = np.sort(self._key(track_ids[has], labels[has]))     # unique: one label per track
        if keys.size and new.size:
            new = new[keys[np.minimum(np.searchsorted(keys, new), keys.size - 1)] != new]
        if new.size:
            at = np.searchsorted(keys, new)
            keys, first = np.insert(keys, at, new), np.insert(first, at, float(stamp))
        self._keys, self._first = keys, first
        self.last_published[labels[has]] = float(stamp)
        self._idle, self._since = _runs(self._idle, self._since, track_ids, has, lost, float(stamp))

    def held_for(self, track_ids, labels, stamp: float) -> np.ndarray:
        """Seconds each track (broadcast with ``labels``) has carried that label by ``stamp``;
        0 for a pair never published."""
        key = self._key(track_ids, labels)
        return _held(self._keys, self._first, key.ravel(), float(stamp)).reshape(key.shape)

    def longest_clutter(self, stamp: float) -> float:
        """Seconds the longest unbroken run of frames left unlabelled has lasted by ``stamp``."""
        return float(stamp - self._since.min()) if self._since.size else 0.0

    def clutter_since(self, track_ids) -> np.ndarray:
        """Stream time each track's unbroken run of frames left unlabelled began (NaN for a
        track labelled in its last published frame)."""
        track_ids = np.asarray(track_ids, dtype=np.int64)
        out = np.full(track_ids.shape, np.nan)
        if self._idle.size:
            at = np.minimum(np.searchsorted(self._idle, track_ids), self._idle.size - 1)
            found = self._idle[at] == track_ids
            out[found] = self._since[at[found]]
        return out

    def clutter_for(self, track_ids, stamp: float) -> np.ndarray:
        """Seconds each track has been published unlabelled without a break by ``stamp`` (while
        seen or coasting); 0 for a track labelled in its last published frame."""
        return np.nan_to_num(float(stamp) - self.clutter_since(track_ids), nan=0.0)


@njit(cache=True, nogil=True)
def _held(keys, first, query, stamp):  # pragma: no cover - compiled
    """``stamp`` minus the first time of each of ``query`` in the sorted ``keys``, 0 where absent."""
    out = np.zeros(query.size)
    for i in range(query.size):
        pos = np.searchsorted(keys, query[i])
        if pos < keys.size and keys[pos] == query[i]:
            out[i] = stamp - first[pos]
    return out


@njit(cache=True, nogil=True)
def _runs(idle, since, track_ids, labelled, lost, stamp):  # pragma: no cover - compiled
    """The unlabelled runs (sorted track ids ``idle``, each run's start ``since``) after a frame:
    runs of labelled and lost tracks end, unlabelled tracks without a run start one at ``stamp``."""
    keep = np.ones(idle.size, dtype=np.bool_)
    new = np.empty(track_ids.size, dtype=np.int64)
    k = 0
    for i in range(track_ids.size):
        t = track_ids[i]
        if t < 0:
            continue
        pos = np.searchsorted(idle, t)
        found = pos < idle.size and idle[pos] == t
        if labelled[i]:
            if found:
                keep[pos] = False
        elif not found:
            new[k] = t
            k += 1
    for j in range(lost.size):
        pos = np.searchsorted(idle, lost[j])
        if pos < idle.size and idle[pos] == lost[j]:
            keep[pos] = False
    new = np.unique(new[:k])
    old_ids, old_since = idle[keep], since[keep]
    out_ids = np.empty(old_ids.size + new.size, dtype=np.int64)
    out_since = np.empty(out_ids.size)
    a = b = 0
    for o in range(out_ids.size):
        if b >= new.size or (a < old_ids.size and old_ids[a] < new[b]):
            out_ids[o], out_since[o] = old_ids[a], old_since[a]
            a += 1
        else:
            out_ids[o], out_since[o] = new[b], stamp
            b += 1
    return out_ids, out_since


def warm_up() -> None:
    """Compile (or load) the lookup once, before a stream."""
    tenure = LabelTenure(2)
    tenure.update(np.array([0, 1]), np.array([1, -1]), np.zeros(0, dtype=np.int64), 0.0)
    tenure.held_for(np.array([0, 1]), np.array([1, 0]), 1.0)


__all__ = ["LabelTenure", "warm_up"]
