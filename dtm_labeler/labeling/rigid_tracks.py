"""Whole tracks relabelled by the take's own rigid marker pairs, offline, after the take pass.

Why. With half of a capture's markers hidden at once, a marker back from a gap is labelled
from a frame whose neighbours are often hidden too, and the triangle mixtures (eq. 6-7 over
eq. 12, marginalised as eq. 30-31) cannot tell it from the next marker of its cluster: after
the take pass (:mod:`.take_pass`) 5 % of the points of a 50 %-gapped take are still wrong,
most of them whole tracks given a neighbour's label (HDM05, 41 markers: right toe / fifth
metatarsal, the back of the head; the Qualisys walk: the hand markers).

What does not change over a take is the body (:mod:`dtm_labeler.model.body`): two markers on
one rigid segment keep their distance, for this person in this session. The labels the take
pass gives are right for 95 % of the points, so the take measures its own rigid pairs: every
label pair seen together in enough frames whose distance's robust spread (1.4826 MAD) is
small and whose length is short (:func:`rigid_pairs`; a long pair that held still is a pose
of this take, not a segment). It is the body terms' segment model with the person's own
lengths (a self-calibration of every rigid pair at once), read across frames instead of
within one.

The person's body. The take's labels are its only ruler, and twice it measures wrong: when
the labeler leaves one marker out of every frame (the Qualisys walk labelled by a model of
its gapped first half, own tracker: the fifth metacarpal and a heel marker unlabelled for the
whole take), the take measures no pair of that label and no track could ever take it; and
when a marker carries a neighbour's label for most of the take (the same walk under another
search seed: the knee's epicondyle labelled as the fibula head in 118 of 170 frames), the
pairs of that label are measured on the wrong marker and the pass defends the error. The
model's body (:mod:`dtm_labeler.model.body`) knows the person's segments when it is
calibrated or was trained on one person (each segment's length range within 1 cm,
:func:`body_pairs`). Whether the take *is* that person the take says itself: of the body's
segments it measures, at least 80 % agree with the body (within two spreads or 1 cm; the
same person's takes: 92-100 % per block, another lab's person under the HDM05 body: 4-15 %).
Then every body segment the take did not measure, or measured otherwise, takes the body's
length (:meth:`RigidPairs.with_body`); for another person the take's own pairs stand alone.

The model. A track is one marker while it is seen (the premise of the votes, eq. 32), so the
variables are the pieces of tracks that hold one label, and each pair of pieces seen in the
same frame at distance ``d`` adds, when their labels ``(a, b)`` are a rigid pair of length
``D_ab`` and spread ``S_ab``, the log-likelihood ratio of that distance against a distance
spread evenly over a metre,

    e_ab(d) = log N(d; D_ab, S_ab) - log(1 / 1 m),   z = |d - D_ab| / S_ab capped at 4,

so a matching distance gains about 5 nats (spread 3 mm) and a broken one costs at most about 3.
Every pair seen together counts, however far apart: a piece given a label whose partners are
all a metre away is refuted by them. (HDM05, gapped: a forehead marker published as the fifth
metatarsal of a hidden foot -- the metatarsal's one DTM triangle had both other vertices
hidden, so the frames' search judged it by its velocity alone. Reading only the pairs within
the longest rigid length, that label scored 0 and the forehead kept it for 54 frames.)
The frames of a piece are not independent evidence: a head held at one distance from the
upper back for 17 frames matches the length of a pelvis-to-back pair in every one of them
(CMU 85 jump + twist: from the true labels, a forehead marker moved to the right hip that
way). So what one partner label says about a piece is clipped to +-``partner_cap`` (10 nats,
about two frames' worth): a piece's score for a label counts mostly *how many* of the
label's rigid partners agree with it, which a coincidence of one distance does not fake.

The energy of a labeling is the sum of these scores over the pieces. It is raised by
coordinate ascent from the take pass's labels with one move: a piece takes a label; the
pieces holding that label in its frames take the piece's old label where that leaves no
frame with it twice and their own distances support it (their score for it above 0), else
none. The moved pieces' scores are read at each step (every piece's scores are updated
after each step), a move is kept only when they gain more than ``min_gain`` (15 nats: more
than one partner's worth) and else undone, and the sweeps are bounded (without the clip the
gain would be the energy's exact change and every move would raise it). A piece
moves only to a label its distances support (its own score for it above ``min_gain``): a
pair rigid for most of a take breaks when the pose changes (an arm held still, then raised),
and then every label with rigid partners in view scores below one with fewer, which is no
reason to take it. The support asked for is lower, ``refuted_support`` (5 nats: one
partner's matching distance), when the piece's own label is *refuted*: its score for it
at or below ``-refuted`` (20 nats: two partner labels' broken distances at their cap). One broken
pair may be a pose change; two are a wrong label, and then a label one partner confirms is
the better reading. (HDM05, the back of the head given its mirror's label while its mirror
and the other back marker were hidden: as the mirror, the forehead and the upper back both
broke it, -26 nats; as itself, the forehead confirmed it over 35 frames, clipped to +10, and
the upper back broke it, +7 in all.)

A piece never takes a label from a piece that scores it at least as high: a right label whose
pose-held pairs break (a shoulder marker of a raised arm, measured at 0.2-0.4 m from the head
and the back) is refuted at once, and one coincidental partner of its mirror label then took
the mirror from the marker that holds it rightly (HDM05, gapped second half, from the true
labels: 0.77 % moved, the right shoulder unlabelled or taken as the left). With the rule, from
the true labels of 50 %-gapped copies of the shared takes: HDM05 0.42 -> 0.23 % and 0.25 ->
0.18 % moved (two gap draws), CMU 85 breakdance 0.17 -> 0.12 %, the others none as before; the
13 replayed gapped runs of :mod:`.take_pass` mean 98.23 -> 98.29 % (HDM05 gap seed 2, capture
ids, 98.68 -> 99.41 %; seed 4 97.96 -> 97.84 % / 98.03 -> 98.24 %; the rest within 0.02).

Measured. The take pass's labels of ``benchmarks/bench_captures.py``'s gaps runs (trained on
the gapped first half, 50 % hidden, the gapped second half labelled with the capture's track
ids; own tracker) -> after this pass: HDM05 41 markers 95.05 -> 99.03 % (95.92 -> 99.45 %),
the Qualisys walk 94.81 -> 99.34 % (93.89 -> 98.31 %); without the lower support for a
refuted label 98.33 % (98.78 %) and 99.25 % (97.61 %), without the body's pairs 99.03 %
(99.15 %) and 99.32 % (97.61 %), with them only where the take measured nothing 99.03 %
(99.24 %) and 99.34 % (97.91 %); the walk under search seed 1 (the knee case above), own
tracker: 91.17 -> 95.68 % (94.72 % without the body's corrections). The gap-free second
half, own tracker: Qualisys 96.36 -> 100 % (the two markers left out, with the body's
pairs). Started from the true labels of
50 %-gapped copies of every shared marker take (their trajectories as tracks), what it
changes: HDM05 0.29 % of the labels (0.07 % without the refuted rule), CMU 85 jump + twist
0.04 %, breakdance 0.10 % (0.08 %), the Qualisys walk and the MoCap Toolbox takes none.
Tried and not kept (the same two runs; from the truth: the worst take):

* no clip per partner, moves above 10 nats: 98.89 / 99.36 %, but 2.2 % of true labels moved
  (CMU 85 jump + twist); with each pair also checked over +-0.5 s around each frame, moves
  needing 2 nats per frame and blocks of 5 s: 99.36 / 98.95 %, 0.7 % moved;
* clipped at 20 / 10 / 5 nats with moves above 10: 98.23 / 99.36 % (1.6 % moved), 98.34 /
  99.57 % (0.2 %), 97.57 / 98.23 % (0.04 %);
* every pair with a small spread regardless of length: HDM05 97.14 % (a shoulder and an
  upper-arm marker of an arm held still for the take made a wrist into a shoulder);
* only a label no piece holds, or an exchange of two whole pieces: 98.51 / 99.00 %;
* each frame's points assigned to labels by their pieces' scores (Hungarian, per frame):
  97.37 % in one round and lower in each further round, the pieces fragmenting;
* pairs needing 95 % of their frames within 2 cm: 97.39 / 98.25 %, 2.9 % moved;
* the support asked for lowered to 5 nats, or to 0, for every move: 99.24 / 99.29 %, but
  0.66 % of true labels moved (CMU 85 jump + twist: pairs held for most of the take, broken
  in a jump); lowered where the old label is refuted by 5 or 10 nats: 99.24 or 99.16 % /
  99.29 %, own tracker 98.85 or 98.82 / 98.12 %, 0.66 % moved;
* only the take's pairs that the body's reach limits hold within twice their length + 5 cm
  (dropping pose-held pairs such as a hand resting on the hip): 96.67 / 97.95 %, own tracker
  97.64 / 96.54 % -- fewer pairs, less evidence everywhere.

Rounds. The pairs are measured from the labels the pass starts from, and the pieces are cut
from them; after a round more labels are right and pieces of one track that now hold one label
are one piece with more frames of evidence. So the pass runs again from its own result, at
most ``rounds`` times, until a round makes no move. Replayed from the take pass's labels of
``benchmarks/bench_captures.py``'s gapped runs (13 runs: HDM05 gap seeds 1-4, the Qualisys walk
search seeds 0, 2, 3; capture ids / own tracker), one round -> up to four: HDM05 seed 1
98.69 -> 99.20 % / 99.31 -> 99.61 %, seed 3 93.18 -> 93.33 % / 93.63 -> 94.13 %, the walk's
own tracker under search seeds 2 and 3 98.40 -> 98.80 % and 98.70 -> 99.21 %; none lower. From
the true labels of 50 %-gapped copies of the shared takes: HDM05 0.39 -> 0.42 % moved (0.43 %
before pairs beyond reach counted), the others unchanged.

Bounded: beyond the longest rigid length (+ 4 spreads) every rigid pair is broken at the cap,
so a (piece, partner piece) pair's frames there are one evidence entry weighted by their
count. Takes are relabelled in blocks of ``block`` frames (pieces cut at block edges), the
pairs measured on at most ``table_frames`` frames of each block, and a block of very many
short pieces (flicker) halved until its evidence cells fit in ``MAX_CELLS``. 600 frames of 41
markers take under a second.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..model.body import SEGMENT, BodyModel

__all__ = ["PieceEvidence", "RigidPairs", "Support", "body_pairs", "rigid_pairs", "relabel_tracks", "spread_sample"]

Z_CAP = 4.0                 # a broken distance costs at most Z_CAP^2 / 2 nats
MAX_CELLS = 20_000_000      # evidence cells (pieces x labels^2) of one block: 160 MB
BACKGROUND_M = 1.0          # the alternative: a distance spread evenly over this many metres


@dataclass(frozen=True)
class RigidPairs:
    """(M, M) symmetric: which label pairs are rigid in the take, their length and spread (m);
    ``measured``: the pairs the take showed together often enough to judge (None: all)."""

    rigid: np.ndarray
    length: np.ndarray
    spread: np.ndarray
    measured: np.ndarray | None = None

    @property
    def count(self) -> int:
        return int(self.rigid.sum() // 2)

    def evidence(self, d: np.ndarray, a: np.ndarray | slice, b: np.ndarray) -> np.ndarray:
        """(len(d), len(a)) e_ab(d) of each distance ``d[k]`` with partner label ``b[k]`` for
        the labels ``a`` (module doc; 0 where (a, b) is not rigid)."""
        R, D, S = self.rigid[a][:, b].T, self.length[a][:, b].T, self.spread[a][:, b].T
        z = np.minimum(np.abs(d[:, None] - D) / S, Z_CAP)
        e = -np.log(np.sqrt(2.0 * np.pi) * S / BACKGROUND_M) - z * z / 2.0
        return np.where(R, e, 0.0)

    def shows(self, body: "RigidPairs | None", same_share: float = 0.8, min_segments: int = 5,
              tolerance_m: float = 0.01) -> bool:
        """Whether these pairs (measured by :func:`rigid_pairs`) show the person of ``body``
        (:func:`body_pairs`): at least ``same_share`` of the body's pairs the take measures (at
        least ``min_segments``) agree with it, within two spreads or ``tolerance_m`` (module doc)."""
        if body is None or self.measured is None:
            return False
        seen = body.rigid & self.measured
        if seen.sum() // 2 < min_segments:
            return False
        agree = np.abs(self.length - body.length) <= np.maximum(2.0 * body.spread, tolerance_m)
        return bool(agree[seen].mean() >= same_share)

    def with_body(self, body: "RigidPairs | None", same_share: float = 0.8, min_segments: int = 5,
                  tolerance_m: float = 0.01) -> "RigidPairs":
        """These pairs (measured by :func:`rigid_pairs`) with the person's segments
        (:func:`body_pairs`) where the take shows that person: when at least ``same_share`` of
        the body's segments the take measures (at least ``min_segments``) agree with it -- within
        two spreads or ``tolerance_m`` -- every body segment the take did not measure, or measured
        otherwise, takes the body's length (module doc); else (another person) the take's own."""
        if not self.shows(body, same_share, min_segments, tolerance_m):
            return self
        seen = body.rigid & self.measured
        agree = np.abs(self.length - body.length) <= np.maximum(2.0 * body.spread, tolerance_m)
        use = body.rigid & ~(seen & agree)
        return RigidPairs(rigid=self.rigid | use, length=np.where(use, body.length, self.length),
                          spread=np.where(use, body.spread, self.spread), measured=self.measured)


def body_pairs(body: BodyModel | None, max_range_m: float = 0.01, spread_floor_m: float = 0.003) -> RigidPairs | None:
    """The pairs of a model's body (:mod:`dtm_labeler.model.body`) whose length it knows for one
    person, as rigid pairs: its segments whose length range ``hi - lo`` is at most ``max_range_m``
    (a calibrated body, or a model of one person), spread the within-person spread (floored at
    ``spread_floor_m``), and the trained person's rigid pairs of the segments' clusters
    (:attr:`~dtm_labeler.model.body.BodyModel.rigid_pairs`: the pairs of a marker cluster that
    are not tree links, measured on the training frames). None without such pairs.

    The cluster pairs are read as the segments are: a marker cluster on one segment is rigid in
    every pair. Measured on ``benchmarks/bench_captures.py``'s gapped halves (50 % hidden; gap
    seeds 1-4; capture ids / own tracker), segments only -> with the cluster pairs: HDM05 97.91 /
    98.43 (the same), 99.02 / 99.68 -> 98.71 / 99.65, 95.61 / 97.33 -> 96.78 / 97.83, 98.22 / 99.01
    -> 98.10 / 98.93 %; the Qualisys walk 99.55 / 99.66 -> 99.66 / 99.76, 96.49 / 92.73 -> 96.82 /
    95.46, 96.07 / 96.11 -> 96.33 / 96.51, 92.97 / 97.08 -> 93.23 / 99.60 %. Means: HDM05 98.15 ->
    98.29 %, Qualisys 96.33 -> 97.17 %. Tried and not kept: the cluster pairs filling in only
    the pairs the take did not measure (no cell lower, but means 98.15 and 96.89 %); every rigid
    pair of the training frames, not only the clusters' (Qualisys 97.97 %, HDM05 97.40 %; gap
    seed 1, capture ids, 97.91 -> 94.31 %, and 96.82 % with those pairs only filling in: a
    shoulder and an upper-arm marker steady within 11 mm over the first half of the take lie
    4 cm closer in the second, and the pass gave the upper arm's label to the shoulder)."""
    if body is None:
        return None
    seg = (body.kind == SEGMENT) & (body.hi - body.lo <= max_range_m)
    if not seg.any() and not body.rigid_pairs.shape[0]:
        return None
    M = body.n_labels
    rigid = np.zeros((M, M), dtype=bool)
    length, spread = np.zeros((M, M)), np.ones((M, M))
    u, v = body.rigid_pairs.T
    for a, b in ((u, v), (v, u)):
        rigid[a, b] = True
        length[a, b] = body.rigid_length
        spread[a, b] = np.maximum(body.rigid_spread, spread_floor_m)
    u, v = body.pairs[seg].T                          # a segment's own length where it is both
    for a, b in ((u, v), (v, u)):
        rigid[a, b] = True
        length[a, b] = (body.lo[seg] + body.hi[seg]) / 2.0
        spread[a, b] = np.maximum(body.within_sd[seg], spread_floor_m)
    return RigidPairs(rigid=rigid, length=length, spread=spread)


def spread_sample(n_frames: int, count: int) -> np.ndarray:
    """At most ``count`` frame indices spread evenly over ``n_frames`` (all when fewer)."""
    if n_frames <= 0:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.linspace(0, n_frames - 1, min(n_frames, count)).round().astype(np.int64))


def label_positions(xyz: Sequence[np.ndarray], labels: Sequence[np.ndarray], n_labels: int) -> np.ndarray:
    """(F, n_labels, 3) each label's point per frame, NaN where no point holds it."""
    P = np.full((len(xyz), n_labels, 3), np.nan)
    for f, (x, lab) in enumerate(zip(xyz, labels)):
        lab = np.asarray(lab)
        ok = lab >= 0
        P[f, lab[ok]] = np.asarray(x)[ok]
    return P


def rigid_pairs(positions: np.ndarray, max_spread_m: float = 0.008, max_length_m: float = 0.4,
                min_frames: int = 20, spread_floor_m: float = 0.003) -> RigidPairs:
    """The rigid label pairs of a take from ``positions`` (F, M, 3) (:func:`label_positions`):
    seen together in at least ``min_frames`` frames, median distance at most ``max_length_m``,
    robust spread (1.4826 MAD) at most ``max_spread_m``; spread floored at ``spread_floor_m``."""
    F, M, _ = positions.shape
    d = np.linalg.norm(positions[:, :, None] - positions[:, None], axis=-1)       # (F, M, M)
    n = np.isfinite(d).sum(0)
    length = np.full((M, M), np.nan)
    spread = np.full((M, M), np.nan)
    some = n > 0
    length[some] = np.nanmedian(d[:, some], axis=0)
    spread[some] = 1.4826 * np.nanmedian(np.abs(d[:, some] - length[some]), axis=0)
    rigid = some & (n >= min_frames) & (spread <= max_spread_m) & (length <= max_length_m)
    np.fill_diagonal(rigid, False)
    return RigidPairs(rigid=rigid, length=np.nan_to_num(length),
                      spread=np.maximum(np.nan_to_num(spread, nan=1.0), spread_floor_m), measured=n >= min_frames)


def relabel_tracks(xyz: Sequence[np.ndarray], track_ids: Sequence[np.ndarray], labels: Sequence[np.ndarray],
                   n_labels: int, min_gain: float = 15.0, partner_cap: float = 10.0, refuted: float = 20.0,
                   refuted_support: float = 5.0, block: int = 2400, table_frames: int = 1200,
                   max_sweeps: int = 20, prior: RigidPairs | None = None, rounds: int = 4,
                   **pair_kw) -> tuple[list[np.ndarray], int]:
    """Per frame, the labels (-1 none) after the rigid-pair relabelling of whole track pieces
    (module doc), and the number of moves made. Points without a track (-1) keep their label.
    ``rounds``: at most this many rounds per block, each measuring the pairs and cutting the
    pieces again from the labels the round before left, until one makes no move.
    Nats: ``min_gain`` a move's gain and the support a new label needs, ``refuted_support``
    the support it needs when the old label scores at or below ``-refuted``; ``partner_cap`` the
    clip of one partner label's share. ``prior``: the person's segments (:func:`body_pairs` of
    the model), used where the take is that person (:meth:`RigidPairs.with_body`). ``pair_kw``:
    :func:`rigid_pairs`'s thresholds."""
    support = Support(min_gain, refuted, refuted_support)
    F = len(xyz)
    out, moves = [], 0
    start = 0
    while start < F:
        stop = min(F, start + max(1, block))
        pieces = track_pieces(track_ids[start:stop], labels[start:stop])
        while stop - start > 1 and pieces[1] * n_labels ** 2 > MAX_CELLS:
            stop = start + (stop - start) // 2             # many short pieces (flicker): a shorter block
            pieces = track_pieces(track_ids[start:stop], labels[start:stop])
        lab = labels[start:stop]
        for r in range(max(1, rounds)):
            if r:
                pieces = track_pieces(track_ids[start:stop], lab)
            lab, m = _relabel_block(xyz[start:stop], pieces, lab, n_labels,
                                    support, partner_cap, table_frames, max_sweeps, prior, pair_kw)
            moves += m
            if not m:
                break
        out += lab
        start = stop
    return out, moves


def track_pieces(track_ids: Sequence[np.ndarray], labels: Sequence[np.ndarray]) -> tuple[list[np.ndarray], int]:
    """Per frame, each point's piece: a run of consecutive frames of one (track, label);
    -1 for untracked points."""
    pid, last, n = [], {}, 0
    for f, (tid, lab) in enumerate(zip(track_ids, labels)):
        p = np.full(len(tid), -1, dtype=np.int64)
        for i, key in enumerate(zip(np.asarray(tid).tolist(), np.asarray(lab).tolist())):
            if key[0] < 0:
                continue
            prev = last.get(key)
            if prev is not None and prev[1] == f - 1:
                p[i] = prev[0]
            else:
                p[i], n = n, n + 1
            last[key] = (int(p[i]), f)
        pid.append(p)
    return pid, n


@dataclass(frozen=True)
class Support:
    """What a move needs (nats, module doc): a gain above ``min_gain``, and the piece's own
    score for the new label above ``min_gain``, or above ``refuted_support`` when its score for
    the old label is at or below ``-refuted``."""

    min_gain: float
    refuted: float
    refuted_support: float

    def needed(self, old_score: float | None) -> float:
        """The score a new label needs, given the piece's score for its old label (None: none)."""
        if old_score is not None and old_score <= -self.refuted:
            return min(self.refuted_support, self.min_gain)
        return self.min_gain


class PieceEvidence:
    """The rigid-pair evidence of one block's track pieces (module doc), kept current as pieces
    change label.

    ``pieces``: :func:`track_pieces` of the block's frames; the pairs are measured on the
    block's ``labels`` (at most ``table_frames`` frames of it) with the person's segments
    (``prior``, :meth:`RigidPairs.with_body`). Holds, per piece, its label ``lab`` and its frames
    ``frames``; ``score[p, a]``: the evidence for piece ``p`` holding label ``a`` from the pieces
    labelled in its frames, each partner label's share clipped to +- ``partner_cap``;
    ``holder[f, a]``: the piece holding label ``a`` in frame ``f`` (-1 none). ``empty``: no rigid
    pair or no piece (every score 0)."""

    def __init__(self, xyz, pieces, labels, M: int, partner_cap: float = 10.0, table_frames: int = 1200,
                 prior: RigidPairs | None = None, pair_kw: dict | None = None):
        F = len(xyz)
        self.M, self.partner_cap = M, partner_cap
        labels = [np.asarray(lab, dtype=np.int64) for lab in labels]
        positions = label_positions(xyz, labels, M)
        self.pairs = pairs = rigid_pairs(positions[spread_sample(F, table_frames)], **(pair_kw or {})).with_body(prior)
        self.pid, n_pieces = pieces
        self.n_pieces = n_pieces
        self.lab = lab = np.full(n_pieces, -1, dtype=np.int64)
        members: list[list[int]] = [[] for _ in range(n_pieces)]
        for f in range(F):
            p = self.pid[f]
            tracked = p >= 0
            lab[p[tracked]] = labels[f][tracked]
            for q in p[tracked]:
                members[q].append(f)
        self.frames = [np.asarray(m, dtype=np.int64) for m in members]
        self.score = np.zeros((n_pieces, M))
        self.holder = np.full((F, M), -1, dtype=np.int64)
        for p in np.flatnonzero(lab >= 0):
            self.holder[self.frames[p], lab[p]] = p
        self.empty = not pairs.count or not n_pieces
        if self.empty:
            return
        reach = float(np.max(np.where(pairs.rigid, pairs.length + Z_CAP * pairs.spread, 0.0)))
        # evidence entries: piece, partner piece, distance, weight. Within reach one entry per frame;
        # beyond it every rigid pair's distance is broken at the cap whatever it is, so the frames of
        # one (piece, partner) are a single entry at distance inf weighted by their count
        P, Q, D = [], [], []
        far = []                               # n_pieces * piece + partner, per frame seen beyond reach
        for f in range(F):
            p = self.pid[f]
            tracked = p >= 0
            x = np.asarray(xyz[f], dtype=np.float64)[tracked]
            pp = p[tracked]
            d = np.linalg.norm(x[:, None] - x[None], axis=-1)
            near = d <= reach
            i, j = np.nonzero(near & ~np.eye(len(pp), dtype=bool))
            P.append(pp[i])
            Q.append(pp[j])
            D.append(d[i, j])
            i, j = np.nonzero(~near)
            far.append(pp[i] * n_pieces + pp[j])
        key, count = np.unique(np.concatenate(far), return_counts=True)
        self.W = np.concatenate([np.ones(sum(len(x) for x in P)), count.astype(np.float64)])
        self.P = np.concatenate(P + [key // n_pieces])
        self.Q = np.concatenate(Q + [key % n_pieces])
        self.D = np.concatenate(D + [np.full(key.size, np.inf)])
        self.by_partner = np.split(np.argsort(self.Q, kind="stable"),
                                   np.cumsum(np.bincount(self.Q, minlength=n_pieces))[:-1])
        # per_partner[p, a, b]: evidence for piece p holding label a from the pieces labelled b in
        # its frames; score = its sum over b, each partner label's share clipped
        self.per_partner = np.zeros((n_pieces, M, M))
        self._add(np.arange(len(self.P)), lab[self.Q], 1.0)
        self._rescore(np.arange(n_pieces))

    def _add(self, entries: np.ndarray, partner_label, sign: float) -> None:
        b = np.broadcast_to(partner_label, entries.shape)
        ok = b >= 0
        if ok.any():
            e = entries[ok]
            ev = self.pairs.evidence(self.D[e], slice(None), b[ok])
            np.add.at(self.per_partner, (self.P[e][:, None], np.arange(self.M)[None], b[ok][:, None]),
                      sign * self.W[e][:, None] * ev)

    def _rescore(self, pieces: np.ndarray) -> None:
        self.score[pieces] = np.clip(self.per_partner[pieces], -self.partner_cap, self.partner_cap).sum(-1)

    def relabel(self, p: int, new: int) -> None:
        """Piece ``p`` takes label ``new`` (-1 none); the scores of the pieces it is seen with follow."""
        old = self.lab[p]
        if old >= 0:
            self.holder[self.frames[p], old] = -1
        if new >= 0:
            self.holder[self.frames[p], new] = p
        if not self.empty:
            e = self.by_partner[p]
            if len(e):
                self._add(e, old, -1.0)
                self._add(e, new, 1.0)
                self._rescore(np.unique(self.P[e]))
        self.lab[p] = new

    def labels(self, labels) -> list[np.ndarray]:
        """Per frame, ``labels`` with every tracked point given its piece's label."""
        out = []
        for f, lab in enumerate(labels):
            new = np.asarray(lab, dtype=np.int64).copy()
            tracked = self.pid[f] >= 0
            new[tracked] = self.lab[self.pid[f][tracked]]
            out.append(new)
        return out


def _relabel_block(xyz, pieces, labels, M, support, partner_cap, table_frames, max_sweeps, prior, pair_kw):
    """One block: ``pieces`` = :func:`track_pieces` of its frames."""
    min_gain = support.min_gain
    ev = PieceEvidence(xyz, pieces, labels, M, partner_cap, table_frames, prior, pair_kw)
    if ev.empty:
        return [np.asarray(lab, dtype=np.int64) for lab in labels], 0
    lab, score, holder, frames, relabel = ev.lab, ev.score, ev.holder, ev.frames, ev.relabel
    n_pieces = ev.n_pieces

    def attempt(p: int, a: int) -> float:
        """Piece p takes label a; the pieces holding a in p's frames take p's old label where
        that leaves no frame with it twice and their scores for it are above 0, else none; not
        at all (-inf) when one of them scores a at least as high as p does.
        Returns what the moved pieces' scores gained, each read at its step; the caller undoes
        a move not worth it."""
        done.clear()
        old = int(lab[p])
        others = sorted(set(holder[frames[p], a].tolist()) - {-1})
        if any(score[q, a] >= score[p, a] for q in others):     # a holder as well supported keeps it
            return -np.inf
        steps = [(p, -1)] + [(q, -1) for q in others]
        for q in others:
            if old >= 0 and not (set(holder[frames[q], old].tolist()) - {-1, p} - set(others)):
                steps.append((q, old))
        steps.append((p, a))
        gained = 0.0
        for q, new in steps:
            prev = int(lab[q])
            if prev == new or (q != p and new >= 0 and score[q, new] <= 0.0):   # displaced: only where it fits
                continue
            gained += (score[q, new] if new >= 0 else 0.0) - (score[q, prev] if prev >= 0 else 0.0)
            relabel(q, new)
            done.append((q, prev))
        return gained

    def undo() -> None:
        for q, prev in reversed(done):
            relabel(q, prev)
        done.clear()

    done: list[tuple[int, int]] = []
    moves = 0
    for _ in range(max_sweeps):
        made = 0
        held = np.where(lab >= 0, score[np.arange(n_pieces), np.maximum(lab, 0)], 0.0)
        for p in np.argsort(-(score.max(1) - held)):
            old = lab[p]
            gain = score[p] - (score[p, old] if old >= 0 else 0.0)
            needed = support.needed(float(score[p, old]) if old >= 0 else None)
            if old >= 0:
                gain[old] = -np.inf
            for a in np.argsort(-gain)[:5]:
                if gain[a] <= min_gain:
                    break
                if score[p, a] <= needed:                        # no evidence for it: only against the old
                    continue
                if attempt(p, int(a)) > min_gain:
                    made += 1
                    break
                undo()
        moves += made
        if not made:
            break
    return ev.labels(labels), moves
