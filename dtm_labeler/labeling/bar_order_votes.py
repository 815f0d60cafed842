"""A marker bar's two ends told apart live by what their tracks have shown of the bar's order.

Why. The take pass turns a wrist bar back where its order votes over a stretch say its ends are
exchanged (:mod:`.bar_flips`); live, nothing did. The two ends (LWRA / LWRB) are alike to every
distance, and where a pose is not the training's the motion mixtures (eq. 6-7 over eq. 12)
prefer the bar exchanged by a few nats a frame -- the body factor of its order
(:class:`~dtm_labeler.model.body.BarOrder`, ``ORDER_NATS`` per reversed row) is outweighed --
and the arrangement prior (:mod:`.cluster_evidence`), which sums the frames' fitness, then holds
the exchange: ``bench_stream_latency``'s 41 HDM05 markers with gaps + ghosts, corruption seed 1,
inline: the left bar exchanged from frame 472 to 661 (its first ten frames preferring the
exchange by 3-11 nats, the prior then 50-290 nats for it), 80 of the stream's 154 search-error
frames.

The reading is :mod:`.bar_flips`', made on tracks instead of stretches. A track is one marker
(eq. 32's premise), and which end of a bar it is does not change while it lives; each frame in
which both ends and a partner ``x`` of a row ``(x, near, far)`` are labelled says which of the
two tracks is nearer ``x``. Each track keeps, per partner (the markers of one rigid segment are
one partner: :func:`~dtm_labeler.model.body.segment_clusters`), the count ``c_t[x]`` of frames
saying it is the bar's first end (its lower label) minus those saying the second; what it shows
is clipped per partner, its frames not being independent (a pose held):

    E_t = sum_x clip(ORDER_NATS * c_t[x], -partner_cap, +partner_cap)

and a pair of tracks ``(p, q)`` carrying the bar is exchanged when ``(E_p - E_q) / 2`` says so by
``min_gain`` (``bar_order_gain``) or more: with ``partner_cap`` 10, two partners must agree, as in
the take pass. Halved so that a pair that was seen together counts its frames once, while a track
back from a gap beside one that stayed is judged on what the one that stayed has shown.

A frame counts only where the bar's two labels and the partner's are *settled* -- their tracks
have carried them for :data:`SETTLED_S` (the hold prior's tenure, :mod:`.label_tenure`): the votes
read which track is which end from where the labeling puts the partner and the ends, and a
labeling's passing mistakes (a chain shifted for a few frames puts the elbow's track on the
forearm's label) would count for the wrong tracks. Counted on every labelled frame, HDM05's gapped
halves (half of the samples hidden, tracks of a fraction of a second) decided a track of the elbow
as an end of a bar; the live pass of gap seed 1 lost 1.5 points. ``hold_s`` (1 s) instead of 0.25
s left a flicker stream's bar exchanged through its first second (41 markers, seed 1, 99.75 ->
99.73 %; the labels the stream starts with are no surer than later ones).

What it does (:class:`BarOrderVotes`): a decided pair puts a price on every labeling of the fast
path that gives the bar's ends the other way round (:meth:`~BarOrderVotes.cost`:
:data:`VETO_NATS`, more than any frame's or memory's preference of the motion terms: the
decision is the take pass's, which no fitness overrules), and a search's result that gives them
so has them exchanged (:meth:`~BarOrderVotes.kept`). Only for a body calibrated to a person, whose
bar rows are that lab's (:func:`~.bar_flips.take_bar_orders`), in stream mode, and not in a
calibration's self-labelling (it measures the person frame by frame, without the tracks' memory:
:func:`~dtm_labeler.training.calibrate.calibration_labeling`). Pure numpy; a frame's update is
one pass over every bar's rows (30 us at 41 markers).
"""
from __future__ import annotations

import numpy as np

from ..model.body import ORDER_NATS
from .bar_flips import bar_rows, partner_keys

__all__ = ["BarOrderVotes", "VETO_NATS", "FORGET_S", "SETTLED_S"]

#: what a labeling of the fast path pays for a decided bar's ends the other way round (module doc)
VETO_NATS = 1.0e3
#: a frame's order counts where the bar's and the partner's labels have been on their tracks this
#: long (s; module doc)
SETTLED_S = 0.25
#: a track's counts are forgotten once it has not been seen with its bar for this long (s): the
#: tracker has let it go (its coasting lasts a fraction of that)
FORGET_S = 2.0


class _Bar:
    """One bar ``(a, b)`` (``a < b``), its rows as partner labels, the sign of each row (+1: the
    partner lies nearer ``a``), each row's partner index, and each track's counts per partner
    with their clipped sum ``E_t``."""

    def __init__(self, a: int, b: int, rows: list[tuple[int, int]], groups: np.ndarray | None, n_labels: int):
        self.a, self.b = a, b
        self.x = np.array([x for x, _ in rows], dtype=np.int64)
        self.sign = np.array([s for _, s in rows], dtype=float)
        _, self.partner = np.unique(partner_keys(self.x, groups, n_labels), return_inverse=True)
        self.n_partners = int(self.partner.max()) + 1
        self.counts: dict[int, np.ndarray] = {}      # track -> frames saying it is ``a`` minus ``b``, per partner
        self.evidence: dict[int, float] = {}         # track -> E_t of its counts (module doc)
        self.seen: dict[int, float] = {}             # track -> stamp it was last seen carrying an end


class BarOrderVotes:
    """Each tracked end's order votes (module doc), per bar of ``orders`` (rows ``(x, near,
    far)``, :class:`~dtm_labeler.model.body.BarOrder`; a bar is a pair ``(near, far)``, either way
    round); ``groups`` (n_labels,) the partners counted as one (-1: a partner of its own)."""

    def __init__(self, orders: np.ndarray, n_labels: int, groups: np.ndarray | None = None,
                 min_gain: float = 15.0, partner_cap: float = 10.0):
        groups = None if groups is None else np.asarray(groups, dtype=np.int64)
        self.bars = [_Bar(a, b, r, groups, n_labels) for (a, b), r in sorted(bar_rows(orders).items())]
        self.min_gain, self.partner_cap = float(min_gain), float(partner_cap)
        # every bar's rows in one table, read in one pass a frame (:meth:`update`): each row's bar,
        # partner label, sign and slot (its bar's first slot plus its partner index)
        sizes = [bar.x.size for bar in self.bars]
        self._ends = np.array([[bar.a, bar.b] for bar in self.bars], dtype=np.int64).reshape(-1, 2)
        self._row_bar = np.repeat(np.arange(len(self.bars)), sizes)
        self._row_x = np.concatenate([bar.x for bar in self.bars]) if self.bars else np.zeros(0, np.int64)
        self._row_sign = np.concatenate([bar.sign for bar in self.bars]) if self.bars else np.zeros(0)
        first = np.cumsum([0] + [bar.n_partners for bar in self.bars])
        self._slots = [(int(first[i]), int(first[i + 1])) for i in range(len(self.bars))]
        self._row_slot = (np.concatenate([bar.partner + first[i] for i, bar in enumerate(self.bars)])
                          if self.bars else np.zeros(0, np.int64))
        #: the labels the votes read (ends and partners): whether they are settled is all they ask
        self.labels = np.unique(np.concatenate([self._ends.ravel(), self._row_x]))

    @property
    def active(self) -> bool:
        return bool(self.bars) and self.min_gain > 0

    def reset(self) -> None:
        for bar in self.bars:
            bar.counts.clear()
            bar.evidence.clear()
            bar.seen.clear()

    def update(self, assignment: np.ndarray, pts: np.ndarray, point_tracks: np.ndarray, stamp: float,
               settled: np.ndarray | None = None) -> None:
        """Count what this frame's labeling (label -> point, ``len(pts)`` = none) shows: for each
        bar with both ends and a partner on points, which of the ends' tracks lies nearer.
        ``settled`` (n_labels,) bool: the labels whose tracks have carried them long enough to be
        read (module doc); a row counts only where its three labels are (None: all)."""
        if not self.active:
            return
        n = len(pts)
        if point_tracks.size != n:
            return
        ends = assignment[self._ends]                                   # (bars, 2) points of the ends
        ok = (ends < n).all(1)
        if settled is not None:
            ok &= settled[self._ends].all(1)
        xs = assignment[self._row_x]
        rows = ok[self._row_bar] & (xs < n)
        if settled is not None:
            rows &= settled[self._row_x]
        if not rows.any():
            return
        bar_of = self._row_bar[rows]
        near = pts[xs[rows]]
        da = ((near - pts[ends[bar_of, 0]]) ** 2).sum(1)               # squared: only their order counts
        db = ((near - pts[ends[bar_of, 1]]) ** 2).sum(1)
        says = np.where(da < db, self._row_sign[rows], -self._row_sign[rows])   # +1: the ``a`` end's track is ``a``
        votes_all = np.bincount(self._row_slot[rows], weights=says, minlength=self._slots[-1][1])
        cap = self.partner_cap
        for i in np.flatnonzero(np.bincount(bar_of, minlength=len(self.bars))).tolist():
            bar = self.bars[i]
            votes = votes_all[self._slots[i][0]:self._slots[i][1]]
            ia, ib = ends[i]
            for track, sign in ((int(point_tracks[ia]), 1.0), (int(point_tracks[ib]), -1.0)):
                if track < 0:
                    continue
                c = bar.counts.get(track)
                c = sign * votes if c is None else c + sign * votes
                bar.counts[track] = c
                bar.evidence[track] = sum(min(max(ORDER_NATS * v, -cap), cap) for v in c.tolist())
                bar.seen[track] = float(stamp)
            if len(bar.seen) > 8:
                for track in [t for t, s in bar.seen.items() if stamp - s > FORGET_S]:
                    del bar.seen[track], bar.counts[track], bar.evidence[track]

    def _evidence(self, bar: _Bar, track: int) -> float:
        """``E_t``: what track ``track`` has shown of being the bar's end ``a`` (module doc), kept
        as the counts change."""
        return bar.evidence.get(int(track), 0.0)

    def decided(self, assignment: np.ndarray, point_tracks: np.ndarray) -> list[tuple[int, int, int, int]]:
        """``[(a, b, point of a, point of b)]``: the bars whose ends ``assignment`` puts on two
        tracked points, with the points their tracks' votes give each end, where those votes
        decide (``min_gain``)."""
        if not self.active:
            return []
        n = point_tracks.size
        out = []
        for bar in self.bars:
            ia, ib = int(assignment[bar.a]), int(assignment[bar.b])
            if ia >= n or ib >= n:
                continue
            d = 0.5 * (self._evidence(bar, point_tracks[ia]) - self._evidence(bar, point_tracks[ib]))
            if d >= self.min_gain:
                out.append((bar.a, bar.b, ia, ib))
            elif d <= -self.min_gain:
                out.append((bar.a, bar.b, ib, ia))
        return out

    def cost(self, seed: np.ndarray, point_tracks: np.ndarray):
        """The price (:data:`VETO_NATS`) a candidate labeling pays for giving a decided bar's ends
        (decided on the tracks ``seed`` puts them on) the other way round; None when no bar is
        decided."""
        bars = self.decided(seed, point_tracks)
        if not bars:
            return None
        a, b, pa, pb = (np.array(v, dtype=np.int64) for v in zip(*bars))

        def price(cand: np.ndarray) -> np.ndarray:
            cand = np.atleast_2d(cand)
            wrong = (cand[:, a] == pb) | (cand[:, b] == pa)
            return VETO_NATS * wrong.sum(1)
        return price

    def kept(self, assignment: np.ndarray, point_tracks: np.ndarray) -> np.ndarray:
        """``assignment`` with each decided bar whose ends it gives the other way round
        exchanged (the same array when there is none)."""
        out = assignment
        for a, b, pa, pb in self.decided(assignment, point_tracks):
            if out[a] == pb and out[b] == pa:
                out = out.copy() if out is assignment else out
                out[a], out[b] = pa, pb
        return out
