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
support is not held (leaving it is free); a label hidden this frame, or moved off the cluster's
points, is read at its best (max-marginal), so the prior prices what a move does to the others.

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
on a slow day's machine); every cluster's prices are one gather, computed once a frame for the fast
path and the publication (at 41 markers 0.33-0.37 ms a frame on a slow day; 0.73-0.80 ms cluster
by cluster, twice). A cluster's memory is about the tracks it was measured on: a track new
since (a marker back from a gap, a ghost) is free in it -- each arrangement is read at its best
over what it gives the new track -- so a marker back among three that stayed gets exactly the
label left, and the three keep what their frames said. Starting afresh instead left the bar's
ends to the mixtures after every gap of one of them (41 markers with gaps + ghosts, corruption
seeds 1-3, inline: 98.68 / 96.63 / 98.78 % against 98.37 / 98.11 / 99.73 %). A label moved onto
a track that was there all along is another marker's, and voids the memory: carried over, the
evidence gathered while a finger's label sat on the other hand's finger held the bar exchanged for
up to 477 frames (background recovery, flicker; three runs 99.17 / 96.14 / 95.11 % against 98.73 /
98.34 / 98.42 %). ``bench_stream_latency`` markers41, before / after (``results/stream_latency.md``,
2026-12-03 afternoon): inline, clean 98.26 -> 99.58 %, gaps + ghosts (corruption seeds 1-3) 96.99
/ 96.00 / 97.26 -> 98.25 / 97.75 / 99.73 %, flicker + ghosts 97.69 / 97.53 / 97.77 -> 99.82 / 99.55
/ 99.69 %. Pure numpy.
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


def _padded(clusters, codes) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each cluster's labels padded to the largest cluster's size with its first (``valid`` False
    there), its rank codes padded with 0 (a padded column adds nothing to a pattern's code), and
    its size."""
    C, width = len(clusters), max((m.size for m in clusters), default=1)
    members = np.zeros((C, width), dtype=np.int64)
    valid = np.zeros((C, width), dtype=bool)
    padded_codes = np.zeros((C, width), dtype=np.int64)
    for c, (m, code) in enumerate(zip(clusters, codes)):
        members[c] = m[0]
        members[c, :m.size] = m
        valid[c, :m.size] = True
        padded_codes[c, :m.size] = code
    return members, valid, padded_codes, np.array([m.size for m in clusters], dtype=np.int64)


@functools.lru_cache(maxsize=None)
def _completions(k: int) -> np.ndarray:
    """For every subset of a ``k``-label cluster's labels read as not placed (digit ``k``), in
    turn, the base ``k + 1`` rank pattern of each order (:func:`_orders`' rows): where each
    arrangement counts in :meth:`ClusterEvidence._max_marginal`."""
    table = _orders(k)[0]
    codes = (k + 1) ** np.arange(k)
    return np.concatenate([np.where(mask, k, table) @ codes
                           for mask in itertools.product((False, True), repeat=k)])


class ClusterEvidence:
    """Discounted log-likelihood of each arrangement of each rigid cluster over its tracks."""

    def __init__(self, clusters, tau_s: float, every: int = MEASURE_EVERY):
        self.clusters = [np.asarray(c, dtype=np.int64) for c in clusters]
        self._codes = [(c.size + 1) ** np.arange(c.size) for c in self.clusters]   # base k + 1 rank patterns
        self._padded = _padded(self.clusters, self._codes)
        self.every = int(every)
        self.set_memory(tau_s)
        self.reset()

    def set_memory(self, tau_s: float) -> None:
        """A new memory ``tau`` (s; 0 = off); the sums kept so far stay."""
        self.tau_s = float(tau_s)
        self.active = self.tau_s > 0 and bool(self.clusters)
        self._last_cost = None

    def reset(self) -> None:
        C = len(self.clusters)
        self.keys = np.full(self._padded[0].shape, -2, dtype=np.int64)   # per cluster: its tracks, sorted, when
        self.evidence = [None] * C        # measured (-2 beyond its size); E over their arrangements (max 0)
        self.stamp = np.zeros(C)
        self._tables = [None] * C         # max-marginals of E (:meth:`_max_marginal`)
        self._pay_cache = [{} for _ in range(C)]   # ... and what each pattern pays (:meth:`_pays`)
        self._cursor = 0
        self._last_cost = None            # (the arguments, the price) of the last :meth:`cost`
        self._frame = 0

    def _ranks(self, c: int, tracks: np.ndarray, began: np.ndarray) -> np.ndarray | None:
        """The rank of each of ``tracks`` (which began at stream times ``began``) among cluster
        ``c``'s measured tracks; ``k`` (the cluster's size) for a track begun since the cluster
        was measured. None when one is neither: a track that was there but held no label of the
        cluster then -- the labeling moved a label onto another marker (a finger's label onto the
        other hand's finger), and what the frames said of the arrangement was said of another
        set of points."""
        key = self.keys[c, :self.clusters[c].size]
        rank = np.searchsorted(key, tracks)
        hit = (rank < key.size) & (key[np.minimum(rank, key.size - 1)] == tracks)
        if not (hit | (np.asarray(began) > self.stamp[c])).all():
            return None
        return np.where(hit, rank, key.size)

    def measure(self, problem, assignment: np.ndarray, point_tracks: np.ndarray, point_began: np.ndarray,
                stamp: float) -> None:
        """Every ``every``-th frame, add this frame's evidence for the next cluster whose labels
        are all on points of ``assignment`` (label -> point, ``problem.n`` = none), in turn;
        ``point_tracks`` the frame's track id per point, ``point_began`` when each track began."""
        if not self.active:
            return
        self._frame += 1
        if self._frame % self.every:
            return
        n = problem.n
        members, valid = self._padded[:2]
        seen = np.flatnonzero(((assignment[members] < n) | ~valid).all(1))
        if not seen.size:
            return
        self._cursor = self._cursor % len(seen)
        weight = float(len(seen) * self.every)          # frames the measurement stands for
        c = int(seen[self._cursor])
        self._cursor += 1
        members = self.clusters[c]
        k = members.size
        pts = assignment[members]
        perms, index = _orders(k)
        codes = k ** np.arange(k)
        block = np.repeat(assignment[None], len(perms), 0)
        block[:, members] = pts[perms]
        f = problem.fitness(block)
        tracks = point_tracks[pts]
        key = np.sort(tracks)
        rank = np.searchsorted(key, tracks)
        e = np.empty(len(perms))
        e[index[rank[perms] @ codes]] = weight * f
        then = None if self.evidence[c] is None else self._ranks(c, key, point_began[pts][np.argsort(tracks)])
        if then is not None:
            # the evidence so far, read on today's tracks: each arrangement at its best over what
            # it says of the tracks it was measured on (a track new since -- a marker back from a
            # gap -- is free; one new track among persistent ones is then exactly the one left)
            old = self._max_marginal(c)[then[perms] @ self._codes[c]]
            decay = np.exp(-max(float(stamp) - self.stamp[c], 0.0) / self.tau_s)
            e[index[perms @ codes]] += decay * old
        self.evidence[c] = e - e.max()
        self.keys[c, :k] = key
        self.stamp[c] = float(stamp)
        self._tables[c] = None
        self._pay_cache[c] = {}
        self._last_cost = None

    def _max_marginal(self, c: int) -> np.ndarray:
        """Cluster ``c``'s evidence at its best over every arrangement that gives its labels the
        given ranks, for every pattern of ranks (base ``k + 1`` codes over the cluster's labels;
        digit ``k``: that label is not placed on the cluster's tracks). Kept until the cluster is
        measured again (decay scales every entry alike)."""
        if self._tables[c] is None:
            k = self.clusters[c].size
            best = np.full((k + 1) ** k, -np.inf)
            np.maximum.at(best, _completions(k), np.tile(self.evidence[c], 2 ** k))
            self._tables[c] = best
        return self._tables[c]

    def cost(self, seed: np.ndarray, n: int, point_tracks: np.ndarray, point_began: np.ndarray, stamp: float):
        """The prior a candidate labeling pays against the carried ``seed`` (label -> point).
        For each cluster whose labels ``seed`` puts on tracks its evidence was measured on (two or
        more of them; the others hidden this frame), a candidate pays what the evidence prefers the
        carried arrangement by over the candidate's arrangement of the cluster's labels on those
        points, each side read at its best completion over the labels it does not place there
        (max-marginal): ``max(0, max_{pi ~ seed} E_c(pi) - max_{pi ~ cand} E_c(pi))``. A candidate
        that moves a label of the cluster elsewhere pays only for what it does to the others
        (the bar's ends exchanged together with the finger's label given to the other hand's
        finger was the commonest way round the prior before it did), and one that puts a hidden
        label on a point of the cluster pays for that. A marker of the cluster hidden for a frame
        is when the motion mixtures most easily exchange the others (with 2 of 41 markers hidden
        each frame, most of the wrist bar's exchanges began in such a frame). None when nothing
        applies. Every cluster at once: the clusters' labels and tracks are padded to one width
        (:func:`_padded`), and the price of a population is one gather."""
        if not self.active or point_tracks.size != n or point_began.size != n:
            return None
        args = (float(stamp), n, seed.tobytes(), point_tracks.tobytes(), np.asarray(point_began).tobytes())
        if self._last_cost is None or self._last_cost[0] != args:     # the fast path's and the publication's, one frame
            self._last_cost = (args, self._cost(seed, n, point_tracks, point_began, stamp))
        return self._last_cost[1]

    def _cost(self, seed: np.ndarray, n: int, point_tracks: np.ndarray, point_began: np.ndarray, stamp: float):
        """:meth:`cost`, computed."""
        live = np.flatnonzero([e is not None for e in self.evidence])
        if not live.size:
            return None
        members, valid, codes, size = (a[live] for a in self._padded)
        keys = self.keys[live]
        pts = seed[members]                                                    # (C, width)
        on = valid & (pts < n)
        safe = np.where(on, pts, 0)
        tracks = np.where(on, point_tracks[safe], -1)
        same = tracks[:, :, None] == keys[:, None, :]                          # (C, width, width)
        hit = on & same.any(2)
        new = point_began[safe] > self.stamp[live][:, None]
        void = (on & ~hit & ~new).any(1)                 # a label on a marker the evidence did not see it on
        rank = np.where(hit, same.argmax(2), size[:, None])
        keep = ~void & (hit.sum(1) >= 2)                 # two or more labels on the evidence's tracks
        now = (rank * codes).sum(1)
        rows, pays = [], []
        for i in np.flatnonzero(keep):
            pay = self._pays(int(live[i]), int(now[i]))
            if pay is not None:                           # else nothing the frames preferred less: no prior
                rows.append(i)
                pays.append(pay)
        if not rows:
            return None
        rows = np.asarray(rows)
        members, codes, size = members[rows], codes[rows], size[rows]
        rank_of = np.repeat(size[:, None], n + 1, 1)     # (C', n + 1): each point's rank in the cluster; k: off it
        placed = on[rows]
        rank_of[np.nonzero(placed)[0], pts[rows][placed]] = rank[rows][placed]
        patterns = (size + 1) ** size
        offsets = np.cumsum(patterns) - patterns
        flat = np.concatenate(pays)
        decays = np.exp(-np.maximum(float(stamp) - self.stamp[live[rows]], 0.0) / self.tau_s)
        which = np.arange(rows.size)[None, :, None]

        def price(cand: np.ndarray) -> np.ndarray:
            at = (rank_of[which, cand[:, members]] * codes).sum(2) + offsets   # (P, C'): rank pattern of each
            return flat[at] @ decays
        return price

    def _pays(self, c: int, now: int) -> np.ndarray | None:
        """What each pattern of ranks pays against the carried one (code ``now``), before decay;
        None when none pays. Kept until the cluster is measured again."""
        cache = self._pay_cache[c]
        if now not in cache:
            best = self._max_marginal(c)
            pay = np.where(np.isfinite(best), np.maximum(best[now] - best, 0.0), 0.0)
            cache[now] = pay if pay.any() else None
        return cache[now]


__all__ = ["MEASURE_EVERY", "ClusterEvidence"]
