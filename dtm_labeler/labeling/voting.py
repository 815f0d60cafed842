"""Votes over frames (eq. 32): ``N(track, label) += 1`` for every frame in the window where
the search gave ``label`` to ``track``; the published labeling maximises the total votes
subject to one label per track and one track per label (Hungarian assignment). The share of
a published label is its votes over the frames of the window in which the track was *seen*
(labelled or not): a marker hidden for part of the window is not less certain for it.

"Unlabelled" is a class of its own (the clutter of eq. 18-20): the frames in which the search
left a track unlabelled are its votes for "no label", and a track with more of those than
votes for its best label is published unlabelled. This is what keeps a ghost unlabelled in
the one frame its neighbouring marker is hidden and the search, short of that marker, puts
the label on the ghost (measured on the flicker demo: 103 of 104 labelled ghosts were that
case, each seen unlabelled for a median 23 frames before). Only a frame a search vouched for
votes "no label": a frame published doubtful (a recovery still running, nothing known yet)
abstains, so the labels a recovery brings are published at once.

A doubtful frame's labels are the best known while nothing is vouched for, published so
that the stream is answered, not evidence: when the first vouched frame comes to a window
that holds none, the window starts again from it. Else a recovery's right labeling had to
outvote the window of interim ones before it (41 HDM05 markers, 3 flickering + 2 ghosts, the
stream's start: 5-14 frames of a right search result published at 55-85 %)."""
from __future__ import annotations

from collections import deque

import numpy as np
from scipy.optimize import linear_sum_assignment


class VoteBook:
    def __init__(self, window: int, n_labels: int):
        if window < 1:
            raise ValueError("vote window must be >= 1 frame")
        self.window = window
        self.n_labels = n_labels
        self.reset()

    def reset(self) -> None:
        # the window's frames, one after another (oldest first): track ids, labels, and whether
        # the point votes "no label"; ``frame_sizes``: how many entries each frame holds
        self.frame_sizes: deque[int] = deque()
        self.vouched: deque[bool] = deque()         # per frame: a search vouched for it (not abstained)
        self._tids = np.zeros(0, dtype=np.int64)
        self._labs = np.zeros(0, dtype=np.int64)
        self._none = np.zeros(0, dtype=bool)

    def add(self, track_ids: np.ndarray, labels: np.ndarray, abstain: bool = False) -> None:
        """One frame's search result: ``labels[i]`` (-1 = none) for point with ``track_ids[i]``;
        ``abstain``: a doubtful frame, whose unlabelled points cast no "no label" vote and
        whose votes are dropped when a vouched frame follows a window of doubtful ones (module
        doc). The window slides by one frame: two concatenations per frame, whatever its length."""
        tids = np.asarray(track_ids, dtype=np.int64).reshape(-1)
        labs = np.asarray(labels, dtype=np.int64).reshape(-1)
        if not abstain and self.frame_sizes and not any(self.vouched):
            self.reset()
        drop = 0
        if len(self.frame_sizes) == self.window:
            drop = self.frame_sizes.popleft()
            self.vouched.popleft()
        self.frame_sizes.append(tids.size)
        self.vouched.append(not abstain)
        self._tids = np.concatenate([self._tids[drop:], tids])
        self._labs = np.concatenate([self._labs[drop:], labs])
        self._none = np.concatenate([self._none[drop:], (labs < 0) & (not abstain)])

    def tally(self, track_ids: np.ndarray) -> np.ndarray:
        """(n, n_labels) vote counts (eq. 32) for the given tracks over the window."""
        return self._count(track_ids)[0]

    def seen(self, track_ids: np.ndarray) -> np.ndarray:
        """(n,) frames of the window in which each track was seen (labelled or not)."""
        return self._count(track_ids)[1]

    def _count(self, track_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Votes (n, n_labels), frames seen (n,) and "no label" votes (n,) of ``track_ids``:
        one pass over the window."""
        track_ids = np.asarray(track_ids)
        k, M = track_ids.size, self.n_labels
        if not self.frame_sizes or k == 0:
            return np.zeros((k, M)), np.zeros(k), np.zeros(k)
        tids, labs = self._tids, self._labs
        order = np.argsort(track_ids)
        sorted_ids = track_ids[order]
        pos = np.minimum(np.searchsorted(sorted_ids, tids), k - 1)
        hit = sorted_ids[pos] == tids
        row = order[pos]
        seen = np.bincount(row[hit], minlength=k).astype(float)
        lab = hit & (labs >= 0)
        votes = np.bincount(row[lab] * M + labs[lab], minlength=k * M).astype(float).reshape(k, M)
        none = np.bincount(row[hit & self._none], minlength=k).astype(float)
        return votes, seen, none

    def publish(self, track_ids: np.ndarray, current: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Published labels (-1 none) and confidences for this frame's points.

        ``current`` is this frame's search result; it breaks ties (a half vote) so a fresh
        decision wins over an equal count of old ones. Confidence = votes for the published
        label / frames of the window in which the track was seen.
        """
        votes, seen, none = self._count(track_ids)
        cur = np.asarray(current)
        has = cur >= 0
        votes[np.flatnonzero(has), cur[has]] += 0.5
        labels = np.full(len(track_ids), -1, dtype=np.int64)
        conf = np.zeros(len(track_ids))
        if votes.size == 0 or not votes.any():
            return labels, conf
        r, c = _max_assignment(votes)
        ok = (votes[r, c] > 0) & (votes[r, c] > none[r])
        labels[r[ok]] = c[ok]
        conf[r[ok]] = np.minimum((votes[r[ok], c[ok]] - 0.5 * (cur[r[ok]] == c[ok])) / np.maximum(seen[r[ok]], 1.0),
                                 1.0)
        return labels, conf


def _max_assignment(votes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of a one-to-one assignment maximising the total ``votes``, the same
    labels as ``linear_sum_assignment(-votes)`` gives where they count (a positive vote): when
    every row with a positive vote has one strict maximum and no two such rows share its column
    -- nearly every frame of a stream on track -- each such row takes its maximum (nothing beats
    every row at its maximum, and that is the only way to reach it), without the Hungarian
    algorithm's cost; otherwise the Hungarian algorithm. Rows without a positive vote are
    left out (no label is published for them either way)."""
    best = votes.argmax(1)
    top = votes[np.arange(votes.shape[0]), best]
    rows = np.flatnonzero(top > 0)
    cols = best[rows]
    if (votes[rows] == top[rows, None]).sum() == rows.size and np.unique(cols).size == cols.size:
        return rows, cols
    return linear_sum_assignment(-votes)
