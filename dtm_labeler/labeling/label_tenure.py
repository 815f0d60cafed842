"""How long each track has carried each label: the memory behind the fast path's hold prior.

Eq. 32 counts, per track, the frames in which the search gave it each label; read as a hidden
Markov chain over a track's label, a trajectory keeps the label it has carried unless a frame's
evidence outweighs the prior against changing it. :class:`LabelTenure` keeps, for every (track,
label) pair the labeler has published, the stream time it was first published -- also while the
label is briefly elsewhere, so a label that flickers to a neighbour and back keeps the tenure it
had. Pairs go when their track does. Pure numpy (sorted int64 keys), no Python loop over tracks.
"""
from __future__ import annotations

import numpy as np


class LabelTenure:
    """First stream time at which each (track, label) pair was published."""

    def __init__(self, n_labels: int):
        self.n_labels = int(n_labels)
        self.reset()

    def reset(self) -> None:
        self._keys = np.zeros(0, dtype=np.int64)     # track * n_labels + label, sorted
        self._first = np.zeros(0)                    # stream time of each key's first publication

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

    def held_for(self, track_ids, labels, stamp: float) -> np.ndarray:
        """Seconds each track (broadcast with ``labels``) has carried that label by ``stamp``;
        0 for a pair never published."""
        key = self._key(track_ids, labels)
        out = np.zeros(key.shape)
        if not self._keys.size:
            return out
        pos = np.minimum(np.searchsorted(self._keys, key), self._keys.size - 1)
        hit = self._keys[pos] == key
        out[hit] = float(stamp) - self._first[pos[hit]]
        return out


__all__ = ["LabelTenure"]
