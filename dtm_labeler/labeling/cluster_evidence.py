"""What a rigid cluster's tracks have shown over their shared life about which label each
carries: the fast path's arrangement prior.

Eq. 32 counts a track's labels over a window of frames. Read as a hidden Markov chain over the
*arrangement* of a small rigid cluster -- which of its labels each of the tracks that carry them
holds -- every arrangement gets the log-likelihood of every frame the cluster's tracks were seen
together, discounted over the memory ``tau``:

    E_c(pi, t) = sum_k exp(-(t - t_k) / tau) * w_k * log P(X_k | G with the cluster arranged as pi)

(``w_k`` the frames a measurement stands for: clusters are measured in turn). A candidate of
the fast path that puts the cluster's labels on the same tracks in another arrangement ``pi'``
pays what the frames before preferred the carried one by, ``max(0, E_c(pi) - E_c(pi'))``
(:meth:`ClusterEvidence.cost`): a frame may prefer another arrangement, but the labeling changes
only once the frames of the tracks' shared life, as a whole, do. An arrangement the frames do not
support is not held (leaving it is free), and a candidate that moves a label of the cluster to a
point outside it is not priced (the cluster's tracks are another set then).

Why: a wrist bar (HDM05's LWRA, LWRB, 13 cm apart) and the finger beside it are a near-isosceles
triangle whose exchanges no distance sees. Trained on the take's first 70 %, the motion mixtures
prefer the bar's ends exchanged in 299 of the last 1000 frames (``bench_stream_latency``
markers41, clean), in runs of up to 49 frames that sum to -238 nats over 32 frames, while over
the whole stream the truth leads by 8.25 nats a frame; per frame the labeler followed them (660
wrong labels, all of the left hand). The arrangement is measured as a whole, not pair by pair: a
pair's exchange alone, measured while a third label of the cluster was wrong, gathered evidence
for the wrong pair (the bar exchanged in 399 of a flicker stream's first 400 frames), and pricing
only lone exchanges let every region check and cluster turn that changes three labels through.

The clusters are the model's :attr:`~dtm_labeler.model.dtm.TriangulatedModel.rigid_clusters`
(marker sets; 3-4 labels, so at most 24 arrangements). One cluster whose labels are all on points
is measured every ``MEASURE_EVERY`` frames, in turn (at 41 markers 24 fitness evaluations, 0.6 ms
on a slow day's machine). A cluster's memory is keyed
by the set of tracks that carried its labels: a new track (a marker back from a gap, a ghost)
starts it afresh. Pure numpy.
"""
from __future__ import annotations

import functools
import itertools

import numpy as np

#: a cluster is measured every this many frames (the clusters in turn; module doc)
MEASURE_EVERY = 2


@functools.lru_cache(maxsize=None)
def _orders(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Every order of ``range(k)`` (identity first) and a table from the base-``k`` code of an
    order to its row. A cluster's evidence has a row per order: row ``r`` is the arrangement in
    which label ``i`` of the cluster holds the track of rank ``orders[r, i]`` among its tracks."""
    perms = np.array(list(itertools.permutations(range(k))), dtype=np.int64).reshape(-1, k)
    index = np.full(k ** k, -1, dtype=np.int64)
    index[perms @ (k ** np.arange(k))] = np.arange(len(perms))
    return perms, index


class ClusterEvidence:
    """Discounted log-likelihood of each arrangement of each rigid cluster over its tracks."""

    def __init__(self, clusters, tau_s: float, every: int = MEASURE_EVERY):
        self.clusters = [np.asarray(c, dtype=np.int64) for c in clusters]
        self.every = int(every)
        self.set_memory(tau_s)
        self.reset()

    def set_memory(self, tau_s: float) -> None:
        """A new memory ``tau`` (s; 0 = off); the sums kept so far stay."""
        self.tau_s = float(tau_s)
        self.active = self.tau_s > 0 and bool(self.clusters)

    def reset(self) -> None:
        self.keys = [None] * len(self.clusters)      # per cluster: its tracks, sorted, when measured
        self.evidence = [None] * len(self.clusters)  # ... and E over the orders of those tracks (max 0)
        self.stamp = np.zeros(len(self.clusters))
        self._tables = [{} for _ in self.clusters]  # max-marginals per pattern of seen labels
        self._cursor = 0
        self._frame = 0

    def _ranks(self, members: np.ndarray, pts: np.ndarray, point_tracks: np.ndarray):
        """The cluster's tracks sorted, and each point's rank among them."""
        tracks = point_tracks[pts]
        order = np.argsort(tracks)
        rank = np.empty(members.size, dtype=np.int64)
        rank[order] = np.arange(members.size)
        return tracks[order], rank

    def measure(self, problem, assignment: np.ndarray, point_tracks: np.ndarray, stamp: float) -> None:
        """Every ``every``-th frame, add this frame's evidence for the next cluster whose labels
        are all on points of ``assignment`` (label -> point, ``problem.n`` = none), in turn;
        ``point_tracks`` the frame's track id per point."""
        if not self.active:
            return
        self._frame += 1
        if self._frame % self.every:
            return
        n = problem.n
        seen = [c for c, m in enumerate(self.clusters) if (assignment[m] < n).all()]
        if not seen:
            return
        self._cursor = self._cursor % len(seen)
        weight = float(len(seen) * self.every)          # frames the measurement stands for
        c = seen[self._cursor]
        self._cursor += 1
        members = self.clusters[c]
        pts = assignment[members]
        perms, index = _orders(members.size)
        block = np.repeat(assignment[None], len(perms), 0)
        block[:, members] = pts[perms]
        f = problem.fitness(block)
        tracks, rank = self._ranks(members, pts, point_tracks)
        e = np.empty(len(perms))
        e[index[rank[perms] @ (members.size ** np.arange(members.size))]] = weight * f
        old = self.evidence[c]
        if old is not None and np.array_equal(self.keys[c], tracks):
            e += np.exp(-max(float(stamp) - self.stamp[c], 0.0) / self.tau_s) * old
        self.evidence[c] = e - e.max()
        self.keys[c] = tracks
        self.stamp[c] = float(stamp)
        self._tables[c] = {}

    def _max_marginal(self, c: int, seen: tuple) -> np.ndarray:
        """Cluster ``c``'s evidence at its best over every arrangement that gives the labels
        ``seen`` (positions in the cluster) the given ranks, for every pattern of ranks (base
        ``k + 1`` codes; digit ``k``: that label is not placed on the cluster's tracks). Kept
        until the cluster is measured again (decay scales every entry alike)."""
        cache = self._tables[c]
        if seen not in cache:
            k = self.clusters[c].size
            table = _orders(k)[0][:, list(seen)]
            codes = (k + 1) ** np.arange(len(seen))
            best = np.full((k + 1) ** len(seen), -np.inf)
            for mask in itertools.product((False, True), repeat=len(seen)):
                np.maximum.at(best, np.where(mask, k, table) @ codes, self.evidence[c])
            cache[seen] = best
        return cache[seen]

    def cost(self, seed: np.ndarray, n: int, point_tracks: np.ndarray, stamp: float):
        """The prior a candidate labeling pays against the carried ``seed`` (label -> point).
        For each cluster whose labels ``seed`` puts on tracks its evidence was measured on (two or
        more of them; the others hidden this frame), a candidate pays what the evidence prefers the
        carried arrangement by over the candidate's arrangement of the labels it leaves on those
        points, each side read at its best completion over the labels it does not place there
        (max-marginal): ``max(0, max_{pi ~ seed} E_c(pi) - max_{pi ~ cand} E_c(pi))``. A candidate
        that moves a label of the cluster elsewhere pays only for what it does to the others:
        the bar's ends exchanged together with the finger's label given to the other hand's
        finger was the commonest way round the prior before it did. A marker of the cluster
        hidden for a frame is when the motion mixtures most easily exchange the others (with 2 of
        41 markers hidden each frame, most of the wrist bar's exchanges began in such a frame).
        None when nothing applies."""
        if not self.active or point_tracks.size != n:
            return None
        terms = []
        for c, members in enumerate(self.clusters):
            e = self.evidence[c]
            if e is None:
                continue
            seen = np.flatnonzero(seed[members] < n)
            if seen.size < 2:
                continue
            pts = seed[members[seen]]
            rank = np.searchsorted(self.keys[c], point_tracks[pts])
            if (rank >= self.keys[c].size).any() or not np.array_equal(self.keys[c][rank], point_tracks[pts]):
                continue                              # a track the evidence was not measured on
            k = members.size
            codes = (k + 1) ** np.arange(seen.size)   # base k + 1: digit k = the label left the cluster
            best = self._max_marginal(c, tuple(seen.tolist()))
            pay = np.where(np.isfinite(best), np.maximum(best[rank @ codes] - best, 0.0), 0.0)
            if not pay.any():
                continue                              # nothing the frames preferred less: no prior
            pay *= np.exp(-max(float(stamp) - self.stamp[c], 0.0) / self.tau_s)
            rank_of = np.full(n + 1, k, dtype=np.int64)
            rank_of[pts] = rank
            terms.append((members[seen], rank_of, codes, pay))
        if not terms:
            return None

        def price(cand: np.ndarray) -> np.ndarray:
            out = np.zeros(cand.shape[0])
            for labels, rank_of, codes, pay in terms:
                out += pay[rank_of[cand[:, labels]] @ codes]            # rank of each label's point, k: out
            return out
        return price


__all__ = ["MEASURE_EVERY", "ClusterEvidence"]
