"""Fresh starts over a take, offline: a labeling lost for good is replaced where a fresh start fits better.

Live, a labeler carries its labeling from frame to frame (the tracks, the votes of eq. 32) and
searches again only when the labeling fits below what it expects (:mod:`.tracked`). Where half of
a capture's markers are hidden at once, a frame that shows half of the markers fits below the
expected level whether it is right or not, so a labeling that goes wrong can stay wrong for the
rest of a take: the votes and the take pass (:mod:`.take_votes`, :mod:`.take_pass`) then defend
it. Measured (``bench_captures.py``'s HDM05 take, 50 % of the samples hidden in gaps of 0.25 s,
the model of the gapped first half; the whole second half, 2960 frames): gap draw 4 was
labelled 96-98 % right per 300 frames up to frame 1200, then 77, 39, 75, 26, 2 and 4 % -- the
true labeling fitting 100-150 nats per frame above the published one from there on, with no
full search in the last 1800 frames -- while a labeler started afresh at frame 2100 labelled the
same frames 86-95 % right. The model tells the two apart as soon as the comparison is over a
long stretch instead of one frame: summed over the frames after a restart point, the lost
labeling fits 93-141 nats per frame below the fresh start's.

Offline the whole take is there, so the labeler is started again every ``period_s`` seconds of
the take (:func:`restart_windows`), each fresh labeler ``lead_s`` seconds before its restart
point so that its cold start (the first frames' full searches, its tracks' first guesses) is
over by then. A fresh start that agrees with the carried labeling for ``REJOIN_FRAMES``
frames in a row (:func:`agrees`) would go on as the carried one did: it is stopped there.
From the restart point to there (or to the next restart point) the labeling that fits better
summed over those frames is kept (:func:`fits_better`; each frame's published labeling's
log-likelihood under the same model and background, the fitness of eq. 14 and 18-21 with the missing
markers marginalised as eq. 30-31, so the two are comparable frame by frame) -- on a take the
model holds, fresh starts rejoin within a second and nothing changes; where the carried
labeling found its way back by itself, the fresh start's frames before that are kept when
they fit better. Measured, ``benchmarks/bench_restarts.py`` (the whole gapped second halves,
``dtm-label``'s default, gap draws 1-6): 86.20 -> 94.01 %, every draw higher (draw 4 62.17 ->
93.84 %). It is the Ukita-style comparison of hypotheses by their likelihood
(several models at once, ``001``), here several starts of one model over time.
"""
from __future__ import annotations

import numpy as np

__all__ = ["RESTART_S", "LEAD_S", "REJOIN_FRAMES", "REJOIN_SHARE", "MIN_GAIN_PER_FRAME",
           "restart_windows", "agrees", "gain_per_frame", "fits_better"]

#: dtm-label's default: a fresh start every this many seconds of a take (``--restarts``)
RESTART_S = 10.0
#: a fresh labeler starts this many seconds before its restart point (its cold start is over by then)
LEAD_S = 2.0
#: frames in a row, after the restart point, on which a fresh start agreeing with the carried
#: labeling is stopped (it would carry on as the carried one did)
REJOIN_FRAMES = 30
#: share of a frame's labelled points that must carry the same label in both for it to agree
REJOIN_SHARE = 0.95
#: nats per frame by which a fresh start must fit better, summed over its frames, to be kept: about
#: two markers' worth (a seen HDM05 marker adds ~10 nats). Measured on the whole gapped HDM05 halves
#: (draws 1-4 under the model of the whole gapped first half, 1-5 under one of its last 600 frames; a
#: fresh start every 5 s; its live labels against the carried ones over the same frames): of the starts
#: that fit better by over 30 nats per frame 10 of 10 were more accurate (+3 to +77 points), by 10-30
#: 8 of 10 (-1.8 to +10), by under 10 1 of 6 (-5.0 to +4.8) (``results/take_restarts.md``)
MIN_GAIN_PER_FRAME = 20.0


def restart_windows(n_frames: int, rate: float, period_s: float = RESTART_S,
                    lead_s: float = LEAD_S) -> list[tuple[int, int, int]]:
    """``(first, start, stop)`` frame indices of each fresh start: it is fed frames ``first``
    to ``stop`` (exclusive) and, when kept, its labels replace the carried ones from ``start``
    on. Restart points every ``period_s`` seconds from the take's start (none at frame 0:
    that is the first labeler's start); none when ``period_s`` <= 0 or the take is shorter."""
    step = int(round(period_s * rate))
    if step <= 0 or n_frames <= step:
        return []
    lead = max(0, int(round(lead_s * rate)))
    return [(max(0, s - lead), s, min(n_frames, s + step)) for s in range(step, n_frames, step)]


def agrees(carried: np.ndarray, fresh: np.ndarray, share: float = REJOIN_SHARE) -> bool:
    """Whether two labelings of one frame's points (-1: unlabelled) agree: of the points either
    labels, at least ``share`` get the same label from both (a frame neither labels agrees)."""
    carried, fresh = np.asarray(carried), np.asarray(fresh)
    either = (carried >= 0) | (fresh >= 0)
    if not either.any():
        return True
    return float((carried[either] == fresh[either]).mean()) >= share


def gain_per_frame(fresh_loglik: np.ndarray, carried_loglik: np.ndarray) -> float:
    """Nats per frame by which a fresh start's published labelings fit better than the carried
    ones over the same frames (summed log-likelihood; frames either leaves unscored, NaN, count
    0); NaN when the two are not over the same (non-empty) frames."""
    f = np.nan_to_num(np.asarray(fresh_loglik, dtype=float), nan=0.0)
    c = np.nan_to_num(np.asarray(carried_loglik, dtype=float), nan=0.0)
    if f.size != c.size or not f.size:
        return float("nan")
    return float(f.sum() - c.sum()) / f.size


def fits_better(fresh_loglik: np.ndarray, carried_loglik: np.ndarray,
                min_gain_per_frame: float = MIN_GAIN_PER_FRAME) -> bool:
    """Whether a fresh start fits better than the carried labelings by more than
    ``min_gain_per_frame`` nats per frame (:func:`gain_per_frame`)."""
    return bool(gain_per_frame(fresh_loglik, carried_loglik) > min_gain_per_frame)
