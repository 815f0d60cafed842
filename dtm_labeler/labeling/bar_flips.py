"""A marker bar's two ends turned back over a stretch of a take, offline, by the take's order votes.

Why. A wrist bar's two ends (radial and ulnar styloid: LWRA / LWRB) lie equally far from the
forearm marker and from each other's neighbours, so the triangle mixtures (eq. 6-7 over
eq. 12) tell them apart by a few cm of a pose. Where a take's poses are not the training's,
they prefer the exchanged bar: HDM05's gapped second half under a model of its first half,
the frames of one stretch whose bar shows both ends (58 frames): the true labeling's triangle
terms 8.1 nats below the exchanged one's on the mean, its bar order
(:class:`~dtm_labeler.model.body.BarOrder`, 3 nats per reversed row) 6.6 above -- each frame's
search, the votes (eq. 32) and the take pass (:mod:`.take_pass`) all keep the exchange, and the
rigid pairs (:mod:`.rigid_tracks`) cannot see it (both ends are equally far from every
rigid partner). Of the final labels' errors on two whole gapped halves, 43-50 % are the two
wrist bars' labels, and a third of those are the two ends exchanged while both are seen.

What holds in every pose is the order: the shoulder (and upper arm, finger, clavicle) lies
nearer the radial end than the ulnar end (the bar orders, in 99.5 % of every training clip's
frames). One frame's order is weak evidence against the motion terms; a stretch of frames is
not. The reading is the one :mod:`.rigid_tracks` makes of distances: the tracks' pieces are the
variables (one marker while it is seen, eq. 32's premise), and what one partner label ``x``
says over a stretch is clipped, because its frames are not independent (a pose held):

    e(stretch) = sum_x clip(ORDER_NATS * (reversed_x - held_x), -partner_cap, +partner_cap),

``reversed_x`` / ``held_x`` the frames of the stretch whose points of ``x``, ``near`` and ``far``
show the row ``(x, near, far)`` reversed / held. The bar's ends are exchanged over the stretch
when ``e`` is at least ``min_gain``: with the defaults (``partner_cap`` 10, ``min_gain`` 15,
as the rigid pairs' move) two partner labels must agree -- one partner's order can be a pose
of the take (the clavicle's held in 80 % of a gapped HDM05 half, from the true labels).

A stretch. A piece (a run of consecutive frames of one track and one label) holding either
end is one marker, so an exchange moves whole pieces, and every piece holding an end in the
frames of a moved one must move too or a frame would show an end twice. The smallest set that
closes over that is a *stretch*: the pieces holding either end, joined while their frames
overlap (one interval of frames, every end-holding point in it). The rounds repeat (pieces are
cut again from the labels the round before left) until one exchanges nothing.

Measured (``results/captures.md``, "2026-12-06"): ``dtm-label``'s default on HDM05's whole gapped second halves
95.80 -> 96.52 % and 93.21 -> 94.58 %, its 600-frame halves 98.60 -> 98.65 % (mean of six draws), the Qualisys
walk unchanged; from the true labels nothing moves.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..model.body import ORDER_NATS
from .rigid_tracks import label_positions, track_pieces

__all__ = ["bar_rows", "bar_stretches", "flip_bars", "partner_keys", "take_bar_orders"]


def take_bar_orders(model) -> np.ndarray:
    """(K, 3) the bar order rows a take's stretches are judged by: the frame factor's
    (:attr:`~dtm_labeler.model.body.BodyModel.orders`) and the take pass's own
    (:attr:`~dtm_labeler.model.body.BodyModel.take_orders`), each row once -- for a body
    calibrated to a person only, as the frame factor (:class:`~dtm_labeler.model.body.BarOrder`):
    where a lab puts its markers decides the order. No rows (an empty array) for other models."""
    body = getattr(model, "body", None)
    if body is None or not body.calibration:
        return np.zeros((0, 3), dtype=np.int64)
    rows = np.vstack([body.orders, body.take_orders]).astype(np.int64)
    return np.unique(rows, axis=0) if rows.shape[0] else rows


def bar_rows(orders: np.ndarray) -> dict[tuple[int, int], list[tuple[int, int]]]:
    """Each bar of the order rows ``(x, near, far)`` once, as ``(a, b)`` with ``a < b``, and its
    rows as ``(x, sign)``: +1 where ``x`` lies nearer ``a``, -1 nearer ``b``."""
    bars: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for x, near, far in np.asarray(orders, dtype=np.int64).reshape(-1, 3).tolist():
        key = (min(near, far), max(near, far))
        bars.setdefault(key, []).append((x, 1 if near == key[0] else -1))
    return bars


def partner_keys(xs: np.ndarray, groups: np.ndarray | None, n_labels: int) -> np.ndarray:
    """The partner each label of ``xs`` counts as: its rigid segment's (``groups``, module doc of
    :func:`flip_bars`), or itself (``n_labels + x``) where it is on none or ``groups`` is None."""
    xs = np.asarray(xs, dtype=np.int64)
    return xs if groups is None else np.where(groups[xs] >= 0, groups[xs], n_labels + xs)


def bar_stretches(pieces: Sequence[np.ndarray], labels: Sequence[np.ndarray], ends: tuple[int, int]
                  ) -> list[tuple[int, int]]:
    """``[(first, last)]`` frames of each stretch of bar ``ends`` (module doc): the pieces holding
    either end (``pieces``: :func:`~.rigid_tracks.track_pieces`' per-frame piece ids; an untracked
    point is a piece of one frame), joined while their frames overlap."""
    spans: dict[int, list[int]] = {}
    single: list[list[int]] = []
    for f, (pid, lab) in enumerate(zip(pieces, labels)):
        lab = np.asarray(lab)
        for p in np.asarray(pid)[(lab == ends[0]) | (lab == ends[1])].tolist():
            if p < 0:
                single.append([f, f])
            elif p in spans:
                spans[p][1] = f
            else:
                spans[p] = [f, f]
    out: list[list[int]] = []
    for first, last in sorted(list(spans.values()) + single):
        if out and first <= out[-1][1]:
            out[-1][1] = max(out[-1][1], last)
        else:
            out.append([first, last])
    return [(a, b) for a, b in out]


def flip_bars(xyz: Sequence[np.ndarray], track_ids: Sequence[np.ndarray], labels: Sequence[np.ndarray],
              orders: np.ndarray, n_labels: int, partner_cap: float = 10.0, min_gain: float = 15.0,
              rounds: int = 3, groups: np.ndarray | None = None) -> tuple[list[np.ndarray], int]:
    """Per frame, the labels after every stretch whose order votes say its bar is exchanged has
    its two ends exchanged (module doc), and how many stretches were. ``orders``: the bar order
    rows ``(x, near, far)`` (:class:`~dtm_labeler.model.body.BarOrder`); a bar is a pair
    ``(near, far)`` of them (either way round). ``groups`` (n_labels,): the partners whose say is
    clipped as one -- each label's segment cluster
    (:func:`~dtm_labeler.model.body.segment_clusters`; -1: a partner of its own): the markers of
    one rigid segment (a head's four) turn together, so their orders are one pose's, not four."""
    labels = [np.asarray(lab, dtype=np.int64).copy() for lab in labels]
    orders = np.asarray(orders, dtype=np.int64).reshape(-1, 3)
    groups = None if groups is None else np.asarray(groups, dtype=np.int64)
    if not orders.shape[0] or not labels:
        return labels, 0
    bars = bar_rows(orders)
    flips = 0
    for _ in range(max(1, rounds)):
        flipped = 0
        P = label_positions(xyz, labels, n_labels)
        pieces = track_pieces(track_ids, labels)[0]     # a flip exchanges whole pieces: they stay pieces
        for (a, b), rows in bars.items():
            # +1 per frame a row holds (x nearer its near end), -1 reversed, 0 not shown
            says = np.zeros((len(rows), len(labels)))
            for r, (x, sign) in enumerate(rows):
                da = np.linalg.norm(P[:, x] - P[:, a], axis=1)
                db = np.linalg.norm(P[:, x] - P[:, b], axis=1)
                shown = np.isfinite(da) & np.isfinite(db)
                says[r, shown] = np.where(da[shown] < db[shown], sign, -sign)
            if not says.any():
                continue
            cum = np.concatenate([np.zeros((len(rows), 1)), np.cumsum(says, axis=1)], axis=1)
            xs = partner_keys([x for x, _ in rows], groups, n_labels)   # one partner per rigid segment
            for first, last in bar_stretches(pieces, labels, (a, b)):
                per_row = cum[:, last + 1] - cum[:, first]            # held minus reversed, per row
                per_x = np.array([per_row[xs == x].sum() for x in np.unique(xs)])
                evidence = np.clip(-ORDER_NATS * per_x, -partner_cap, partner_cap).sum()
                if evidence < min_gain:
                    continue
                for f in range(first, last + 1):
                    lab = labels[f]
                    ia, ib = lab == a, lab == b
                    lab[ia], lab[ib] = b, a
                P[first:last + 1, [a, b]] = P[first:last + 1, [b, a]]
                flipped += 1
        flips += flipped
        if not flipped:
            break
    return labels, flips
