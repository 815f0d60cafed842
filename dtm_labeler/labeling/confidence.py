"""Confidence a consumer can threshold: of the labels published with confidence c, about a
fraction c is right.

Two pieces of evidence, both from the model:

* **This frame** -- how much the chosen labeling beats the ones that differ from it in one
  label. Treating the fitness (the DTM log-likelihood, eq. 14 with eq. 30-31) as a log
  posterior over labelings and the chosen labeling's one-move neighbourhood (the label given
  to another free point or left missing, swapped with another label, its left/right partner
  exchanged) as the alternatives that matter, the posterior of label ``l``'s point is

      p_l = 1 / (1 + sum_{a changes l} exp((f(a) - f(x)) / tau))

  -- a Laplace-like reading of the marginal posterior from the local neighbourhood.
  ``tau`` (``confidence_temperature``) corrects for the terms of one frame not being
  independent evidence (the mixtures are fitted to correlated frames); it is the one
  calibrated constant (:mod:`dtm_labeler.evaluation.calibration` measures the reliability).
* **The window** -- the share of the last ``window`` frames whose search gave the track the
  published label (eq. 32's votes).

* **The model's fit** -- a labeling can be the best the model knows and still wrong when the
  motion is one the model never saw: then the whole frame fits far worse per labelled point
  than the training frames did (measured on the shared data: 2-6 nats per label below the
  training median where the model holds, 8-30 where it does not). Beyond ``FIT_SLACK`` nats
  every confidence of the frame is scaled by ``exp(-(deficit - FIT_SLACK) / FIT_SCALE)``. With
  a known system noise (``noise_mm``) the yardstick is lowered by what the noise costs a right
  labeling under the widened model
  (:meth:`~dtm_labeler.model.dtm.TriangulatedModel.noise_fit_drop`: 6 nats per label at 10 mm).

The three factors are multiplied -- ``p_l`` times the vote share (a label carried for one frame
after a change of mind is worth less than one held for the whole window) times the fit factor
-- and the product is tempered, ``c = (p_l * share * fit) ** CONFIDENCE_POWER``: the factors are
not independent evidence (the votes count the same frames' searches that ``p_l`` reads, the fit
deficit lowers both), so their plain product double-counts and is under-confident at every
level (the 90 stream cells of ``dtm-eval``'s generalisation section, 358k labels: 0.46 mean
confidence where 60 % were right, 0.75 where 83 %; expected calibration error 5.3 %). The
power is the one constant fitted to that reliability table (0.6: ECE 5.3 -> 1.0 %); on streams
it was not fitted to, the shared takes the model holds, ECE falls as well (10 bins, tau 3,
power 1 -> 0.6: 14 points with gaps and ghosts 2.0 -> 0.7 %, with flicker 2.0 -> 1.2 %; 41
markers with gaps and ghosts 3.0 -> 1.5 %, with flicker 4.3 -> 1.8 %). Refitted to 0.45 once
the release alternative was capped (below): the whole ``dtm-eval`` report's 267 stream cells,
584k labels, were still under-confident between 0.1 and 0.7 (0.55 where 74 % were right), ECE
2.4 % at 0.6; estimated from its bins 1.7 % at 0.45. On the bench streams it was not fitted
to (``bench_stream_latency.py``, seeds 1-2, labels unchanged): 41 markers pooled 1.80 -> 1.29 %
(flicker 1.8-3.0 -> 1.0-2.0 %, gaps 1.8 -> 1.4-2.2 %), 14 points pooled 0.24 -> 0.26 % (flicker
1.0 -> 0.7 %, gaps 0.6-0.8 -> 1.3-1.4 %: the one kind of stream it makes a little
over-confident). Refitted to 0.40 (2026-12-07), the priors since having made the labels they hold
surer than the local posterior says: the report's 347 stream cells, 787k labels, under-confident in
every bin from 0.4 up (0.86 where 93.5 % were right, 0.992 where 99.8 %), pooled ECE 2.05 % at 0.45,
1.72 % at 0.40 (its markers and generalisation sections, 737k of the labels, rerun; the same
labels). On the bench streams (inline, seeds 1-2, the same labels) 14 points pooled 0.51 -> 0.46 %,
41 markers 0.34 -> 0.31 %; every stream lower but the 14 points with gaps, seed 2, 0.90 -> 1.08 %
(over-confident there). A *calibrated* body's
published confidences leave the fit factor out. Its labels are held by what does not depend on
the motion -- the person's segment lengths, marker placement and cluster handedness -- while the
fit deficit reads mostly the motion mixtures, which a motion the training never showed leaves far
below their training fit whether the labels are right or not: HDM05 -> CMU 85 jump + twist,
calibrated, 97.7 % right with every frame 12-32 nats per label below the reference (median 18;
fit factor 0.45 on average), cell ECE 38 %. Measured against ``fit_reference_per_label`` (the
lower of the training fit and the calibration frames', :func:`~dtm_labeler.training.calibrate.calibrate`)
the self-calibrated generalisation cells had gone from ECE 5.7-28 % to 2.0-7.6 %; without the
factor (``dtm-eval``'s generalisation section, 2026-11-28, labels unchanged) that cell's 38.0 ->
9.1 %, CMU 85 breakdance -> jump + twist 5.9 -> 1.7 %, the generic model on subject 9's run (87.5 %
right) 9.7 -> 10.1 %, the other calibrated cells as before; the report's 315 stream cells pooled
2.83 -> 1.81 %. The strict confirmation keeps the factor, so the subject calibration confirms the
same labels. Still not calibrated there:
the local posterior of a calibrated body (its temperature was set for generic bodies) --
subject 5's pirouette 99.7 % right at a mean local posterior of 0.91, and a calibrated
41-marker stream of a known motion shows ECE 3.6 % (its labels below 0.3 are right 79 % of
the time). A frame published
before a search vouched for it (background recovery running) has its confidences halved after
that -- unless its labeling fits what a right one with its observation pattern fits
(``tracked.pattern_weight``, :func:`~.fit_check.expected_share`): with half of the markers hidden
the running level, per labelled point, doubts nearly every frame for the markers it cannot show,
and their labels went out halved (and at a cold start zeroed as lost) whether right or not
(``bench_stream_latency``'s half-hidden 41-marker stream, background, seeds 1-5: ECE 24-32 % over
two runs, right labels at 0.49; judged on the pattern 15.5 %; the standard background streams
within their run-to-run spread: 41 markers with gaps 1.0 / 1.9 -> 1.5 / 1.6 %, with flicker 1.3 / 0.5
-> 0.8 / 1.2 %, 14 points the same) -- and a label the window disagrees with gets ``(1 - p)`` of the labels the search gave
instead. Thresholds on the published scale: 0.5 means as likely right as wrong.

**A label the votes keep on a point the frame's search left unlabelled.** A label the window disagrees
with gets ``(1 - p)`` of the search's label; where the search gave the point no label at all, ``p``
is the local posterior that the point stays unlabelled (:func:`unlabelled_posteriors`: against the
alternatives one move away that put a label on it, the window's among them), not 0 -- which had
published the window's label at its vote share alone, as if the frame had no word on it. Measured on
``bench_stream_latency``'s streams (inline, seeds 1-2, labels unchanged): such labels are 0.1-0.8 % of
those published, and were 17-58 % right with 3 gaps + 2 ghosts at confidence 0.86-0.88 (41 markers,
14 points), 57-100 % right with flicker at 0.85-0.92; now 0.38-0.49 and 0.50-0.59 (their summed
miscalibration 91 -> 32 labels' worth); the streams' ECE as before (14 points with gaps 0.81 / 0.96 ->
0.85 / 0.65 %, the rest within 0.04; pooled 0.18 -> 0.25 % and 0.44 -> 0.44 %); ``dtm-eval``'s markers
section (gaps and clutter at 28-41 markers) moves 18 of its 44360 labels to lower bins, its ECE 0.2 ->
0.3 %, the report's pooled 2.7 % either way. Counting, besides, the
relabels of a labelled point into a missing neighbour label among the alternatives (a marker hidden
next to its neighbour: the neighbour's label on its point, 1-11 nats below the chosen labeling in the
wrong cases) made the right labels of flicker streams under-confident (14 points 0.88 / 0.76 -> 1.43 /
1.10 %) and cost a fitness call per frame. The HDM05 gap stream of
``test_published_confidence.py``: 35 such labels, 63 % right, 0.84 -> 0.63.
**Transfers on young tracks.** Those relabels are now counted in the *published* posterior for the
labels whose track has carried them for less than ``hold_s`` (``transfers``,
:meth:`~.fast_path.FastPath._transfer_alternatives`): a label held for seconds is not doubted for a
neighbour hidden this frame (the hold prior's reading), while with half of a marker set hidden, where
tracks live a fraction of a second, the labels published as sure were wrong that way most often. The
half-hidden 41-marker stream's ECE 11-12 -> 6.5-7.3 % inline, 12.4 -> 10.0 % in the background; the
standard streams' within 0.05 points; labels unchanged.

**A cold start's interim labeling the model scores as lost** is published at confidence 0. Until a
search has vouched for a frame since the stream began (or was reset), a background search's interim
result -- its best so far, the GA's first generation refined -- labels the frames; when that labeling
fits more than ``LOST_NATS`` (10) per label below the model's fit reference, the labeler's own loss
threshold, its labels are published with confidence 0 (the labels themselves unchanged). The fit factor
cannot say this for a calibrated body, whose confidence leaves it out, and the local posterior and the
votes read a labeling against its own neighbours. Measured on the 41-marker demo stream (HDM05, its
calibrated model, 3 flickering + 2 ghosts, background recovery at 120 Hz, corruption seeds 1-8, first 150
frames): seed 1's 22 such frames, 687 labels fitting 14-30 nats per label below the reference, were 3 %
right at confidence 0.33; seeds 2, 5 and 7's interim labels, 7-8 below it, 68-79 % right at 0.16-0.20,
are not touched; seeds 3, 4, 6 and 8 published no label before the first search joined.

What is left at 41 markers is not the temperature (2026-11-26, the HDM05 bench streams of
``benchmarks/bench_stream_latency.py``, gaps and flicker seeds 1-3 and the clean one, inline,
labels unchanged): pooled ECE at tau 1.5 / 2 / 3 / 4.5 / 6 = 3.01 / 2.78 / 2.39 / 2.51 / 3.69 %
(14 points, tau 2 / 3: 0.34 / 0.25 %). The streams err in both directions -- flicker under-
confident in every bin below 0.9, the worst gaps seed over-confident between 0.2 and 0.9 -- and
the local posterior is too sharp at the low end there: of 370k labels over ten streams, those
with ``p_l`` < 0.1 were right 71 % of the time (at 14 points 41 %), so one tempering or one
monotone map of the scale cannot serve both.

What makes a calibrated body of another lab under-confident (traced 2026-11-26: HDM05 -> CMU 85
calibrated, ``dtm-eval``'s generalisation cell, 360 frames, 14296 labels, 93.6 % right): every
bin below 0.8 is 93-96 % right; the bin 0-0.1 holds 1617 labels at 0.024, 94 % right. Their
local posterior is 0.002-0.03 (the heels, toes, LMT5, RSHN, the ankles, CLAV: right 95-100 %)
because one alternative outweighs the rest: leaving the label missing, which that model scores
11-102 nats above the published labeling (median 21.6; the best alternative for all 1543 labels
with ``p_l`` < 0.05). The model fits these true markers worse than clutter, and the fast path
does not release them (``release_moves`` releases only labels on young tracks, and none of a
marker set: at 41 markers releasing made search errors 113 -> 207 of 1000), so the published
labeling keeps them, rightly -- and its confidence should
not be judged by an alternative the search never weighs. So the *published* posterior caps each
release at the published labeling's fitness (it may tie, never outweigh), while the **strict**
posterior counts it in full: that one gives ``FrameResult.confirmation``, what the subject
calibration confirms a label by (:data:`CONFIRMED`; a label the model would rather leave unseen
is not taken as a measurement of the person -- confirming by the capped one moved ``dtm-label``'s
checked self-calibration: floor moves 93.55 -> 27.34 %, 85_02 -> 85_12 99.14 -> 91.35 %).
Measured (``dtm-eval``, generalisation section, the 120 stream cells, 491k labels): pooled ECE
4.16 -> 2.80 %, every cell's labels the same (calibrated and self-calibrated cells too).

**The release is weighed by the clutter the stream shows.** The fitness compares a labelled point
with the same point as clutter under the background density alone -- even prior odds that a point
is a marker or clutter. A stream says how often a point is clutter: the share of its points its
searches leave unlabelled (:class:`ClutterShare`: a running mean over about 50 frames, from
:data:`CLUTTER_PRIOR` = 0.1 at the start; a doubtful frame does not count). The published posterior
weighs each release by those prior odds before the cap, ``min(w_rel * s / (1 - s), 1)``: on a stream
without ghosts a label the model would merely rather leave unseen (a new person or motion fitting
worse than clutter) no longer goes out at a tie, and where ghosts are many a release counts as
before. The strict posterior (the calibration's confirmation) counts the release in full, as
before. What those tied labels were (inline streams, before): 99.6 % right in the calibrated HDM05 ->
CMU 85 cell (18 % of its labels), 90-100 % in the generalisation cells, 96 % in a clean 41-marker
stream, 74-82 % with 3 gaps + 2 ghosts at 41 markers. Measured (``dtm-eval``, every section with stream
cells rerun before and after, every one of the 315 stream cells' labels the same): pooled ECE 2.72 ->
1.72 % (the format-1 baseline left out: 2.07 -> 1.14 %); calibrated cells 1.3 -> 0.3 %, ``dtm-label``'s
default 1.6 -> 0.3 %, the generic body 4.5 -> 3.9 %; markers 0.25 -> 0.31 %, cross-subject 2.01 -> 1.86 %,
Table 3 0.36 -> 0.41 %, noise 0.85 -> 0.57 %.
``bench_stream_latency``'s streams (inline, seeds 1-2, same labels): pooled 0.78 -> 0.67 %; clean and
flicker + 2 ghosts 0.04-1.12 -> 0.01-0.85 %, 3 gaps + 2 ghosts 0.65-0.85 -> 0.86-1.21 % (their shares of
clutter 0.05 at 41 markers, 0.11-0.15 at 14 points).
Where a clean stream's labels are wrong because the model prefers them (HDM05 frames 5000-5200 under
the model of its first 2000, 81 % right) the release had been their one doubt: their confidence
0.88 -> 0.93.
"""
from __future__ import annotations

import numpy as np

from ..search.label_ops import releases
from ..search.problem import FrameProblem

#: ratio by which a doubtful frame's confidences are lowered
DOUBTFUL_FACTOR = 0.5
#: nats per labelled point below the model's training fit that a right labeling shows, and the
#: scale of the confidence fall beyond it
FIT_SLACK, FIT_SCALE = 6.0, 15.0
#: published confidence a label needs to count as confirmed (subject calibration): as likely
#: right as wrong
CONFIRMED = 0.5
#: tempering of the product of the three factors (module doc: fitted to the reliability table)
CONFIDENCE_POWER = 0.40
#: the share of a stream's points taken as clutter before its searches show any, and the weight of
#: each frame in the running share (:class:`ClutterShare`; about 50 frames' memory)
CLUTTER_PRIOR, CLUTTER_RATE = 0.1, 0.02
#: the same for the strict confirmation (``FrameResult.confirmation``): the scale on which
#: :data:`CONFIRMED` was set (the published one's before the release cap), kept so that the subject
#: calibration confirms the same labels
CONFIRMATION_POWER = 0.6


class ClutterShare:
    """The running share of a stream's points its searches leave unlabelled: the prior that a
    point is clutter, whose odds weigh the release in the published posterior (module doc).
    Starts at :data:`CLUTTER_PRIOR`; each searched frame moves it by :data:`CLUTTER_RATE`."""

    def __init__(self) -> None:
        self.share = CLUTTER_PRIOR

    def update(self, search_labels: np.ndarray) -> None:
        """One frame's search labels per point (-1: unlabelled)."""
        if len(search_labels):
            self.share += CLUTTER_RATE * (float(np.mean(np.asarray(search_labels) < 0)) - self.share)

    @property
    def odds(self) -> float:
        s = min(self.share, 0.99)
        return s / (1.0 - s)


def label_posteriors(problem: FrameProblem, ind: np.ndarray, fit: float, alternatives: np.ndarray,
                     temperature: float, fitness: np.ndarray | None = None,
                     prior: np.ndarray | None = None, clutter_odds: float = 1.0,
                     transfers: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                     release_fitness: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Local posterior of each label's point (module doc), twice: (published, strict), each (M,)
    with NaN for missing labels. ``alternatives`` (A, M): labelings near ``ind`` (those equal to
    it are ignored), with their ``fitness`` if already known; the release of every labelled
    label is added here. *published* caps each release at the published labeling's fitness (it
    may tie, never outweigh: the search does not release labels, so its labels are not judged by
    an alternative it never weighs); *strict* counts the release in full -- what the subject
    calibration confirms by (:data:`CONFIRMED`): a label the model would rather leave unseen is
    not taken as a measurement of the person. ``prior`` (A,): what each alternative pays besides
    its fitness in the stream's priors (the arrangement prior of
    :class:`~dtm_labeler.labeling.cluster_evidence.ClusterEvidence`), counted in *published* only:
    a consumer's confidence is the stream's, a calibration's confirmation the frame's own.
    ``clutter_odds``: the stream's prior odds that a point is clutter (:class:`ClutterShare`), by
    which *published* weighs each release before the cap (1: the fitness's own even odds).
    ``transfers`` (rows (T, M), their fitness, their prior): young labels handed to hidden ones
    (:meth:`~.fast_path.FastPath._transfer_alternatives`), counted in *published* only (module
    doc: a calibration confirms by the frame's own one-move neighbourhood, as before).
    ``release_fitness``: the releases' fitness if already scored (each labelled label left on no
    point, in label order)."""
    n, M = problem.n, problem.M
    have = np.flatnonzero(ind < n)
    f_rel = problem.fitness(releases(ind, n)) if release_fitness is None else np.asarray(release_fitness, dtype=float)
    if len(alternatives):
        f_alt = problem.fitness(alternatives) if fitness is None else np.asarray(fitness, dtype=float)
        changed = alternatives != ind[None]
        keep = changed.any(1)
        changed = changed[keep]
        odds = _label_odds(changed, f_alt[keep], fit, temperature)
        odds_pub = odds if prior is None else \
            _label_odds(changed, f_alt[keep] - np.asarray(prior)[keep], fit, temperature)
    else:
        odds = odds_pub = np.zeros(M)
    if transfers is not None and len(transfers[0]):
        rows, f_rows, p_rows = transfers
        odds_pub = odds_pub + _label_odds(np.asarray(rows) != ind[None],
                                          np.asarray(f_rows, dtype=float) - np.asarray(p_rows, dtype=float),
                                          fit, temperature)
    w_rel = _weight(f_rel, fit, temperature)                             # one release per labelled label
    published, strict = np.full(M, np.nan), np.full(M, np.nan)
    published[have] = 1.0 / (1.0 + odds_pub[have] + np.minimum(w_rel * clutter_odds, 1.0))
    strict[have] = 1.0 / (1.0 + odds[have] + w_rel)
    return published, strict


def unlabelled_posteriors(problem: FrameProblem, ind: np.ndarray, fit: float, alternatives: np.ndarray,
                          temperature: float, fitness: np.ndarray | None = None,
                          prior: np.ndarray | None = None) -> np.ndarray:
    """(n,) for each point ``ind`` leaves unlabelled, the local posterior that it stays so --
    ``1 / (1 + sum of the odds of the alternatives that give it a label)``, the same reading as
    :func:`label_posteriors`' (the published one: ``prior`` counted) -- NaN for the labelled
    points. What the frame's search says of a point it gave no label, where the votes publish
    one (module doc)."""
    n = problem.n
    out = np.full(n, np.nan)
    free = np.ones(n + 1, dtype=bool)
    free[np.asarray(ind)[np.asarray(ind) < n]] = False
    free[n] = False
    out[free[:n]] = 1.0
    if not len(alternatives) or not free.any():
        return out
    f_alt = problem.fitness(alternatives) if fitness is None else np.asarray(fitness, dtype=float)
    if prior is not None:
        f_alt = f_alt - np.asarray(prior)
    alts = np.asarray(alternatives)
    hit = free[alts]                                             # (A, M): a label put on a free point
    rows, cols = np.nonzero(hit)
    odds = np.zeros(n + 1)
    np.add.at(odds, alts[rows, cols], _weight(f_alt[rows], fit, temperature))
    out[free[:n]] = 1.0 / (1.0 + odds[:n][free[:n]])
    return out


def _label_odds(changed: np.ndarray, f: np.ndarray, fit: float, temperature: float) -> np.ndarray:
    """(M,) per label, the summed odds (:func:`_weight`) of the alternatives (rows of ``changed``,
    (A, M): which labels each moves) that change it."""
    return changed.T.astype(float) @ _weight(f, fit, temperature)


def _weight(f: np.ndarray, fit: float, temperature: float) -> np.ndarray:
    """exp((f(a) - f(x)) / tau), clipped against overflow: an alternative's odds against ``x``."""
    return np.exp(np.clip((np.asarray(f, dtype=float) - fit) / temperature, -60.0, 60.0))


def published_confidence(posterior_of_point: np.ndarray, search_labels: np.ndarray, published: np.ndarray,
                         vote_share: np.ndarray, doubtful: bool, fit_deficit: float = 0.0,
                         power: float = CONFIDENCE_POWER, lost: bool = False) -> np.ndarray:
    """(n,) confidence of each point's published label (module doc): ``posterior_of_point``
    the search's local posterior for the label it gave the point (NaN if none);
    ``fit_deficit`` nats per labelled point below the model's training fit; ``power`` the
    tempering (:data:`CONFIDENCE_POWER`; :data:`CONFIRMATION_POWER` for the confirmation);
    ``lost``: a cold start's unvouched labeling the model scores as lost (module doc) -- 0."""
    if lost:
        return np.zeros(len(published))
    p = np.where(np.isnan(posterior_of_point), 0.0, posterior_of_point)
    agree = published == search_labels
    fit = float(np.exp(-max(fit_deficit - FIT_SLACK, 0.0) / FIT_SCALE)) if np.isfinite(fit_deficit) else 1.0
    conf = np.clip(np.where(agree, p, 1.0 - p) * vote_share * fit, 0.0, 1.0) ** power
    conf = np.where(published >= 0, conf, 0.0)
    return conf * DOUBTFUL_FACTOR if doubtful else conf


__all__ = ["ClutterShare", "label_posteriors", "unlabelled_posteriors", "published_confidence", "CONFIDENCE_POWER", "CONFIRMATION_POWER", "CONFIRMED", "DOUBTFUL_FACTOR",
           "FIT_SLACK", "FIT_SCALE"]
