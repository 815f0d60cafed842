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
from numba import njit
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
        one pass over the window (:func:`_window_counts`)."""
        track_ids = np.ascontiguousarray(track_ids, dtype=np.int64).reshape(-1)
        k, M = track_ids.size, self.n_labels
        if not self.frame_sizes or k == 0:
            return np.zeros((k, M)), np.zeros(k), np.zeros(k)
        return _window_counts(track_ids, self._tids, self._labs, self._none, M)

    def publish(self, track_ids: np.ndarray, current: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Published labels (-1 none) and confidences for this frame's points.

        ``current`` is this frame's search result; it breaks ties (a half vote) so a fresh
        decision wins over an equal count of old ones. Confidence = votes for the published
        label / frames of the window in which the track was seen.
        """
        votes, seen, none = self._count(track_ids)
        cur = np.ascontiguousarray(current, dtype=np.int64).reshape(-1)
        cols, clear = _row_maxima(votes, cur)
        if not clear:                  # a tie or a shared maximum: the Hungarian algorithm decides
            ahead = votes.copy()
            has = np.flatnonzero(cur >= 0)
            ahead[has, cur[has]] += 0.5
            r, c = linear_sum_assignment(-ahead)
            cols = np.full(len(cur), -1, dtype=np.int64)
            cols[r] = c
        return _published(votes, seen, none, cur, cols)


@njit(cache=True, nogil=True)
def _window_counts(track_ids, tids, labs, none_votes, M):  # pragma: no cover - compiled
    """:meth:`VoteBook._count` in one pass over the window's entries."""
    k = track_ids.size
    order = np.argsort(track_ids)
    sorted_ids = track_ids[order]
    votes = np.zeros((k, M))
    seen = np.zeros(k)
    none = np.zeros(k)
    for e in range(tids.size):
        pos = np.searchsorted(sorted_ids, tids[e])
        if pos >= k or sorted_ids[pos] != tids[e]:
            continue
        row = order[pos]
        seen[row] += 1.0
        if labs[e] >= 0:
            votes[row, labs[e]] += 1.0
        if none_votes[e]:
            none[row] += 1.0
    return votes, seen, none


@njit(cache=True, nogil=True)
def _row_maxima(votes, cur):  # pragma: no cover - compiled
    """Each row's label by its votes, this frame's label ``cur`` adding half a vote: (column of
    every row with a positive vote, -1 for the others; True) when each such row has one strict
    maximum and no two share it -- nearly every frame of a stream on track. Then each row at its
    maximum is what the Hungarian algorithm gives where it counts (nothing beats every row at
    its maximum); else (unset, False) and the caller asks the Hungarian algorithm."""
    k, M = votes.shape
    cols = np.full(k, -1, dtype=np.int64)
    taken = np.zeros(M, dtype=np.bool_)
    for r in range(k):
        best = -1
        top = 0.0
        ties = False
        for c in range(M):
            v = votes[r, c] + (0.5 if c == cur[r] else 0.0)
            if best < 0 or v > top:
                best, top, ties = c, v, False
            elif v == top:
                ties = True
        if top <= 0.0:
            continue
        if ties or taken[best]:
            return cols, False
        taken[best] = True
        cols[r] = best
    return cols, True


@njit(cache=True, nogil=True)
def _published(votes, seen, none, cur, cols):  # pragma: no cover - compiled
    """Labels (-1 none) and confidences of rows assigned ``cols``: a row's label is published
    when its votes (with this frame's half vote) are positive and beat its "no label" votes;
    its confidence is its votes over the frames the track was seen."""
    k = votes.shape[0]
    labels = np.full(k, -1, dtype=np.int64)
    conf = np.zeros(k)
    for r in range(k):
        c = cols[r]
        if c < 0:
            continue
        v = votes[r, c] + (0.5 if cur[r] == c else 0.0)
        if v > 0.0 and v > none[r]:
            labels[r] = c
            conf[r] = min(votes[r, c] / max(seen[r], 1.0), 1.0)
    return labels, conf


def warm_up() -> None:
    """Compile (or load) the module's kernels once, before a stream."""
    book = VoteBook(2, 3)
    book.add(np.array([0, 1]), np.array([0, -1]))
    book.publish(np.array([0, 1]), np.array([0, 2]))
