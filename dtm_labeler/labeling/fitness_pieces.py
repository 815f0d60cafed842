"""Whole track pieces relabelled by the model's fitness summed over their frames, where the
take's rigid pairs allow it: the last step of the offline take pass.

Why. After the take pass (:mod:`.take_pass`: both searches voted, the rigid-pair relabelling
of :mod:`.rigid_tracks`, the bar flips) the errors of a 50 %-gapped take are mostly whole
track pieces given a neighbour's label -- an elbow published as the forearm marker, a finger
as a wrist-bar end, the upper arm left unlabelled -- in stretches where the neighbour was
hidden. The votes count how often each frame's search chose a label, not by how much: a piece
most of whose frames' searches give the neighbour's label, each by a few nats, keeps it
however strongly the model refutes it in the other frames. The rigid pairs cannot settle it
either when the marker has no rigid partner in view (the upper arm, the hand).

The model. A track piece is one marker over its frames (the premise of the votes, eq. 32), so
the take's log-likelihood under the model is the sum of its frames' fitness (eq. 14 with the
missing markers marginalised, eq. 30-31, and the body factors of :mod:`dtm_labeler.model.body`),
each scored at the take's facing (:func:`~.take_pass.take_heading`). A move gives piece ``p``
label ``a`` in all its frames, a label no point holds in any of them; its gain is the sum
over ``p``'s frames of the fitness change, computed exactly (one
:class:`~dtm_labeler.search.problem.FrameProblem` per frame, every candidate move of the frame
in one population). Moves are made greedily by gain, above ``min_gain`` nats (10: the gate
below carries the caution, so a move needs the model's preference only, summed over at least
``min_frames`` frames), one per piece per round, then the pieces are cut again from the new
labels and the next round scores again (at most ``rounds``).

The gate. The gapped model alone is not to be trusted with whole pieces: trained on frames
that showed half of the markers, it can prefer a hand marker's neighbour label by 1400 nats
over 105 frames (the Qualisys walk; the move without a gate was tried and not kept, see
:mod:`.take_pass`). What does not depend on the training motions is the person's rigid pairs
(:class:`~.rigid_tracks.PieceEvidence`), so a piece may only take a label

* that one of the pass's searches gave its points (the two searches of :mod:`.take_pass`:
  at most ``candidates`` labels, 5, the most frequent first),
* that its rigid evidence supports at least as well as its own label, and that the rigid
  evidence does not refute (score above ``-max_refuted``, 20 nats: two partner labels' broken
  distances at their cap, what :mod:`.rigid_tracks` calls refuted),
* and whose evidence summed without the per-partner clip falls no more than
  ``max_unclipped_loss`` (10 nats) below its own label's. The clip keeps one pose-held
  coincidence from deciding a move; but it also makes a partner that matches the piece's own
  label in every frame and one that matches the candidate only roughly count the same, +10
  each: HDM05's 22-marker rehearsal (issue 14's kept-back capture, imitated), an elbow marker
  whose forearm partner is seen took the hidden wrist's label, 13.8 cm from the forearm marker
  where the wrist is 13.1 (2.3 spreads), both clipped alike, and the gapped model preferred it
  by 18.6 nats over 22 frames.

A label held in the piece's frames is not a candidate: tried with the holders taking the
piece's old label where their rigid evidence held it (and no move where a holder had as much
evidence for the label), a point of a marker the training left out (the Qualisys walk's heel,
seen as clutter) took a metatarsal's label from the true one: that draw 99.10 -> 98.75 %
with capture ids, where with free labels only it stays at 99.10 %.

Measured on ``benchmarks/bench_captures.py``'s gapped halves (50 % hidden, the gapped first
half trains, the gapped second half is labelled; the same models before and after; capture ids /
own tracker): HDM05 draws 1-6 98.12 / 98.73 -> 98.19 / 98.83, 99.42 / 99.70 -> 99.58 / 99.78,
96.55 / 98.94 -> 96.76 / 99.03, 98.57 / 98.77 -> 98.82 / 99.04, 97.56 / 98.02 -> 97.87 / 98.49,
96.85 / 97.59 -> 97.08 / 98.47 % (means 97.85 / 98.63 -> 98.05 / 98.94 %, every cell higher);
the Qualisys walk draws 1-4 the same but draw 2 with capture ids 98.78 -> 98.96 % (means
99.11 / 99.49 -> 99.16 / 99.49 %) -- with candidates refuted down to -10 nats only (one
partner label's broken distance); at -20 nats (the default since) HDM05 draw 1 with capture
ids 98.19 -> 98.46 %, draw 4 own tracker 99.04 -> 99.16 %, draw 5 98.49 -> 98.52 % (after the
rigid-pair pass that follows in :mod:`.take_pass`), every other cell the same. A take of 600
frames of 41 markers: under a second.
Tried and not kept: the holders of the label taking the piece's old one (above), also with a
move needing 20 nats more than leaving the piece unlabelled (so that a point the labeling
explains no better than clutter does not take a label from another): the walk's draw 4 with
capture ids 99.10 -> 99.25 %, HDM05 draws 1 and 3 own tracker 98.83 -> 98.94 and 99.03 ->
99.19 %, but draw 6 98.47 -> 97.93 % and draw 3 with capture ids 96.76 -> 96.62 %; moves from
10 nats and a candidate refuted down to -20 nats, the label's holders always taking the old
label: HDM05 own tracker mean 98.88 %, but the walk's draw 2 99.18 -> 99.08 % and draw 4
99.38 -> 99.30 %; the rigid evidence's difference added to the fitness gain instead of the order
asked (HDM05 draw 1 own tracker 98.83 -> 98.97 %, draw 3 99.03 -> 98.81 %), and with it a refuted candidate
allowed where the old label is refuted too (draw 5 98.52 -> 98.99 %: an upper arm whose pose-held pairs broke;
but the walk's draw 4 with capture ids 99.10 -> 97.98 %: where both labels are refuted the gapped model decides
alone, and on the feet it decides wrong; ``results/captures.md``, 2026-12-06 evening).

The unclipped gate (``max_unclipped_loss``), the same models before and after, own tracker / capture ids: the
22-marker rehearsal's draws 1-4 (``results/captures.md``) 97.96 / 98.67 / 98.37 / 98.99 % -> **98.29** / 98.67 /
98.37 / 98.99 % (the same at 5, 20 and 40 nats; at 0 draw 3 fell to 98.18 %); HDM05's gapped halves draws 1-6 and
the Qualisys walk's draws 1-4, with either tracking, every cell the same.

Moves from 10 nats (20 before) among 5 candidates (3 before), the rest as above, the same models: HDM05 draw 5
own tracker 98.52 -> 98.60 %, the walk's draws 3 and 4 with capture ids 98.97 -> 99.03 % and 99.10 -> 99.19 %,
every other cell the same (HDM05 means 98.10 / 99.01 %, the walk 99.19 / 99.49 %); the other take-pass rows of
``bench_captures`` (real ghosts, unnamed C3D) the same.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..model.dtm import TriangulatedModel
from ..search.problem import Background, FrameProblem
from .rigid_tracks import PieceEvidence, RigidPairs, track_pieces

__all__ = ["relabel_by_fitness"]


def relabel_by_fitness(model: TriangulatedModel, background: Background, states: Sequence[np.ndarray],
                       rests: Sequence[np.ndarray | None], yaw: np.ndarray, xyz: Sequence[np.ndarray],
                       track_ids: Sequence[np.ndarray], labels: Sequence[np.ndarray],
                       searched: Sequence[Sequence[np.ndarray]], prior: RigidPairs | None = None,
                       min_gain: float = 10.0, max_refuted: float = 20.0, max_unclipped_loss: float = 10.0,
                       candidates: int = 5, min_frames: int = 3, rounds: int = 3, block: int = 2400,
                       heading_snap_deg: float = 4.0) -> tuple[list[np.ndarray], int]:
    """Per frame, the labels (-1 none) after the moves of whole track pieces (module doc), and
    the number of moves. ``states`` / ``rests``: each frame's point states and rest times as the
    take pass scored them; ``yaw``: the take's facing per frame; ``labels``: the take pass's;
    ``searched``: its searches' labels, each a per-frame sequence like ``labels``; ``prior``: the
    person's segments (:func:`~.rigid_tracks.body_pairs`). Frames are taken in blocks of
    ``block`` (pieces cut at the block edges, as :func:`~.rigid_tracks.relabel_tracks`).
    Nats: ``min_gain`` a move's fitness gain; of the rigid gate, ``max_refuted`` how far a
    candidate may be refuted, ``max_unclipped_loss`` how far its unclipped evidence may fall
    below its own label's (module doc)."""
    out: list[np.ndarray] = []
    moves = 0
    for start in range(0, len(xyz), max(1, block)):
        part = slice(start, min(len(xyz), start + max(1, block)))
        lab = [np.asarray(x, dtype=np.int64) for x in labels[part]]
        for _ in range(max(1, rounds)):
            lab, made = _round(model, background, states[part], rests[part], yaw[part], xyz[part],
                               track_ids[part], lab, [s[part] for s in searched], prior, min_gain,
                               max_refuted, max_unclipped_loss, candidates, min_frames, heading_snap_deg)
            moves += made
            if not made:
                break
        out += lab
    return out, moves


def _round(model, background, states, rests, yaw, xyz, track_ids, labels, searched, prior, min_gain,
           max_refuted, max_unclipped_loss, candidates, min_frames, heading_snap_deg
           ) -> tuple[list[np.ndarray], int]:
    """One round over a block: every piece's candidate moves scored, the best made."""
    pieces = track_pieces(track_ids, labels)
    ev = PieceEvidence(xyz, pieces, labels, model.n_labels, prior=prior)
    pid = ev.pid
    by_piece = _candidates(ev, labels, searched, candidates, min_frames, max_refuted, max_unclipped_loss)
    if not by_piece:
        return labels, 0
    gain: dict[tuple[int, int], float] = {(p, a): 0.0 for p, labs in by_piece.items() for a in labs}
    for f, st in enumerate(states):
        here = [(int(p), i) for i, p in enumerate(pid[f]) if int(p) in by_piece]
        if not here:
            continue
        problem = FrameProblem(model, st, background, heading_snap_deg=heading_snap_deg, rest_s=rests[f])
        problem.anchor, problem.snap = float(yaw[f]), np.pi     # every candidate at the take's facing
        lab = labels[f]
        ind = problem.empty_assignment()
        held = lab >= 0
        ind[lab[held]] = np.flatnonzero(held)
        rows, keys = [ind], []
        for p, i in here:
            old = int(ev.lab[p])
            for a in by_piece[p]:
                row = ind.copy()
                if old >= 0:
                    row[old] = problem.n
                row[a] = i
                rows.append(row)
                keys.append((p, a))
        fit = problem.fitness(np.asarray(rows))
        for k, key in enumerate(keys):
            gain[key] += float(fit[k + 1] - fit[0])
    out = [x.copy() for x in labels]
    moved: set[int] = set()
    for (p, a), g in sorted(gain.items(), key=lambda kv: -kv[1]):
        if g <= min_gain:
            break
        if p in moved:
            continue
        moved.add(p)
        for f in ev.frames[p]:
            out[f][pid[f] == p] = a
    return out, len(moved)


def _candidates(ev: PieceEvidence, labels, searched, candidates: int, min_frames: int,
                max_refuted: float, max_unclipped_loss: float) -> dict[int, list[int]]:
    """Per piece of at least ``min_frames`` frames, the labels worth scoring (module doc): the
    ones the searches gave its points most often, free in all its frames, whose rigid evidence
    is no worse than its own label's, refuted by less than ``max_refuted``, and unclipped no
    more than ``max_unclipped_loss`` below its own label's."""
    M, pid = ev.M, ev.pid
    piece = np.concatenate([np.asarray(p, dtype=np.int64) for p in pid])
    tracked = piece >= 0
    counts = np.zeros((ev.n_pieces, M + 1), dtype=np.int64)
    for run in searched:
        lab = np.concatenate([np.asarray(x, dtype=np.int64) for x in run])[tracked]
        np.add.at(counts, (piece[tracked], np.where(lab >= 0, lab, M)), 1)
    counts = counts[:, :M]
    # held[p, a]: label a is given to some point in one of piece p's frames
    frame = np.repeat(np.arange(len(labels)), [len(x) for x in labels])
    given = np.zeros((len(labels), M), dtype=bool)
    lab = np.concatenate([np.asarray(x, dtype=np.int64) for x in labels])
    given[frame[lab >= 0], lab[lab >= 0]] = True
    score = ev.score
    # the evidence of every partner label summed without the clip: both labels' matching partners
    # may be clipped alike while one of them matches every frame and the other only roughly
    raw = None if ev.empty else ev.per_partner.sum(-1)
    out: dict[int, list[int]] = {}
    for p in np.flatnonzero(counts.sum(1) > 0):
        if len(ev.frames[p]) < min_frames:
            continue
        old = int(ev.lab[p])
        c = counts[p].copy()
        if old >= 0:
            c[old] = 0
        held = given[ev.frames[p]].any(0)
        keep = [int(a) for a in np.argsort(-c, kind="stable")[:candidates]
                if c[a] > 0 and not held[a] and score[p, a] > -max_refuted
                and (old < 0 or score[p, a] >= score[p, old])
                and (raw is None or old < 0 or raw[p, a] >= raw[p, old] - max_unclipped_loss)]
        if keep:
            out[int(p)] = keep
    return out
