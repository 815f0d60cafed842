"""Subject calibration: a few seconds of a new person set the body terms of a model.

The way Vicon and OptiTrack work: before a session the subject moves for a few seconds (any
motion: a range-of-motion trial, a T-pose, the start of the take), those frames are labelled
-- by the operator, or by the current model and confirmed -- and the subject's own segment
lengths replace the generic ones. :func:`calibrate` does that for a model with body terms
(:mod:`dtm_labeler.model.body`):

* each **segment** pair (bone, marker cluster) gets the subject's length -- the median
  distance over the calibration frames where both points are seen -- as a single value
  (``lo = hi``), no between-person spread, and a within-person spread of the larger of the
  model's and 1.5 x the frames' own (robust, MAD-based) scatter; a segment whose labelled
  length scatters by more than ``max_spread_m`` keeps its generic range (its labels were not
  one segment);
* **left and right agree**: a person's left and right segments have the same length within a
  centimetre or two, so a segment whose measured length differs from its mirror's (left and
  right labels exchanged, :attr:`TriangulatedModel.mirror_pairs`) by more than ``mirror_abs_m``
  or ``mirror_rel`` of their length was measured on a wrong labeling -- an arm chain shifted by
  one, the wrist labelled elbow for the whole window, gives a steady "upper arm" as long as the
  bent arm -- and of the two, the one farther outside its generic range (relative to its
  length) is dropped. A segment not measured (dropped, scattering, or its labels unconfirmed)
  whose mirror was measured takes the mirror's length, with spread ``mirror_sd_m``: the
  body is the person's, and a left/right-symmetric one is closer to it than the generic range.
  Only pairs that are symmetric in the training (the shortest and the longest length over the
  training people each within the same tolerance of the mirror's) are compared: marker sets
  place some markers asymmetrically on purpose (Plug-in Gait's thigh and shank markers sit at
  different heights left and right), so their clusters' lengths differ. The midpoints of the
  two ranges alone can agree by chance: CMU 85 + HDM05's shank-to-ankle pairs, left
  0.242-0.259 m and right 0.207-0.321 m, midpoints 1.4 cm apart, while CMU 85's right shank
  marker sits 9 cm higher than its left; with the midpoints only, the floor-moves cell's
  calibration gave the left pair the right pair's 0.333 m and left LSHN out in 340 of 360
  frames;
* **each point on its side**: a label of the left or right side whose point lies on the other
  side of the body's midline (the vertical plane through the mean of the trunk's left/right
  pair midpoints, :attr:`TriangulatedModel.heading_pairs`, across their mean right-minus-left
  axis) in most calibration frames where it is seen was confirmed on its mirror point (the
  left front-head marker labelled right front head, knees exchanged below the hips): its
  segments keep their generic range. Mirror lengths alone cannot see such a swap when both
  sides exchange, or when the mirror label is never given. True labels can fail this test (a
  pirouette's crossed legs: subject 5's left knee and ankle lie right of the midline in most
  of its first 2 s), so labels from a capture skip both checks (``check_labels=False``);
* the **reach** limits are scaled by the subject's size: the median ratio of the calibrated
  segment lengths to the generic ones (clipped to [0.75, 1.33]);
* the marker **bars' order** (:class:`~dtm_labeler.model.body.BarOrder`): the training's rows
  stay unless the calibration frames show the other order in most frames (another lab's
  placement), and the handedness quadruples that hold both ends of an ordered bar are left to
  it, unless all four labels are of one cluster of the measured segments (:func:`kept_orders`,
  :func:`~dtm_labeler.model.body.quads_off_ordered_bars`);
* the **placement** of the person's markers: each triangle mixture's relative-position means
  shift together by the calibration frames' mean residual, shrunk by the evidence
  (:mod:`.placement`; weights, covariances and the velocity part are kept -- the motion is not
  the person's). A marker
  placed where the training people's never sat (another lab's shank marker 10 cm lower) is
  otherwise left out also by a calibrated body;
* the **broad weights** (:class:`~dtm_labeler.model.body.BroadMotion`: the share of each
  triangle's conditional given to its broad Gaussian): fitted again on the calibration frames by
  the training's EM, never below the training's weight and at most 0.5
  (:func:`.body_fit.window_broad_weights`; needs the frames' rate, for the velocities of eq. 12;
  ``broad_min_frames``). The training's held-out frames are more of the same takes; the window
  is a held-out stretch of the motion that will be labelled, so it measures that motion's
  novelty triangle by triangle. The floor stays the training's weight (kept in the model's
  settings, ``broad_weights_training``), so calibrations do not compound. Measured
  (``dtm-eval`` generalisation, stream / single frames, before -> after): HDM05 -> CMU 85
  jump and twist, body + calibration 98.77 / 63.11 -> 99.17 / 54.27 %, ``dtm-label``'s default
  98.73 / 57.62 -> 99.09 / 56.71 % (the two feet, which HDM05's standing take links through
  the structure's root triangle, turn against each other in the jump and twist); subject 9's
  run under a model of subjects 5, 7 and 55 98.57 / 93.75 -> 100 / 98.21 %, under the generic
  model 87.53 -> 100 % (body + calibration); floor moves, ``dtm-label``'s default 99.92 / 96.65 ->
  100 / 99.70 %; CMU 85 jump and twist -> breakdance 99.50 / 95.12 -> 99.44 / 94.51 % (the
  one cell lower); single frames of lambada -> whirl 98.51 -> 99.70 %, of subject 5's
  pirouette 96.43 -> 98.21 %; every other cell the same, pooled ECE 1.9 -> 1.8 %;
* the **fit reference** of the confidence -- the fitness per seen label a right labeling
  shows, against which a frame's confidence measures how far the frame fits below the model
  (:mod:`dtm_labeler.labeling.confidence`) -- becomes the lower of the training people's and
  the calibration frames' under the calibrated body (:func:`fit_per_label`; when their rate is
  known, for the velocities of eq. 12): a calibrated body's segment and off-edge factors and
  its broad motion component change every labeling's fitness, and a person whose motion the
  training never showed fits it worse while labelled right (subject 5's pirouette under a model
  of subjects 7, 9 and 55, self-calibrated on its first 1.6 s: 99.7 % right at a mean confidence
  of 0.80, 10 nats per label below the training reference). Measured on the generalisation
  cells, self-calibrated, labels unchanged, expected calibration error: subject 5 pirouette
  20.2 -> 5.7 %, subject 9 run 28.1 -> 7.6 %, subject 55 lambada 6.1 -> 2.1 %, CMU 85 jump
  and twist -> breakdance 3.1 -> 2.0 %. Not higher than the training reference: a window of
  an easier motion would flag the ordinary frames after it (CMU 85 breakdance -> jump and
  twist: the window's reference 8.9 vs 6.9 nats, ECE 6.9 -> 10.1 % with it). The labeler's
  starting level (``loglik_per_label``) is kept, and :func:`self_calibrate` adds the reference
  after its last round only (its rounds confirm labels by confidence: subject 9's run, with
  the window's level from the first round on, 97.0 -> 95.7 %).

The frames come either labelled (a :class:`~dtm_labeler.motion.clip.MotionClip` with the
model's labels, or an ``(F, M, 3)`` array in the model's label order with NaN for unseen
points) or unlabelled: :func:`self_label` labels them with the model itself (stream
labeler: tracks, votes) and keeps the confirmed labels -- points whose vote confidence is at
least ``min_confidence`` -- and :func:`self_calibrate` alternates labelling and calibrating
(``rounds`` times), so a calibrated model relabels the frames it learned from. Self-labelling
assumes a sparse background (``volume_m3``) and, in its first round, a generic body open to
other proportions (``open_between_rel``): a point that fits the generic body poorly (a forearm
25 % longer than the training people's, a marker placed 10 cm from where they had it) is
labelled rather than left out, so its segment can be measured; the medians over frames absorb
the few wrong labels, and the second round labels with the calibrated body -- in which a
segment the first round could not measure stays that open (:func:`_unmeasured_kept_open`), as it
does in the model returned. From the second round on, a label the round never confirmed is
taken from the points it left out when exactly one of them stays rigid to its segment partners
(:func:`completed_labels`).

*Whose body.* A model ``dtm-train`` calibrated to its training takes' person labels a capture
that nothing names as theirs (another file, not CMU take naming) with the generic body
self-calibrated on the capture's first seconds. When the lengths that self-calibration measured
are the person's (:func:`same_person`: at least 70 % of the segments both measured agree within
two of the person's spreads or 1 cm), the capture is theirs: it is labelled with the person's
calibration -- measured on operator labels over the whole training capture -- checked for this
session (:func:`session_calibrate`), not with 5 s of self-measured lengths. Measured over the
shared clips, each model of one clip calibrated to its person against every other clip's
self-calibration: the same person 12 of 12 segments (subject 55's whirl and lambada, both ways),
other people 0-63 % (CMU 85 -> HDM05 2 of 23, HDM05 -> CMU 85 0 of 22, subject 55 -> subject 5
5 of 8). Calibrated on their own labels, two parts of HDM05's take agree on 23 of 23, CMU 85's
two takes on 18 of 23 (78 %: the arm markers placed elsewhere for the breakdance), CMU 85 and
HDM05 on 2-5 of 23; hence 70 %. ``dtm-train`` reads several captures under any names as one person
the same way (:func:`one_person_by_lengths`). HDM05's whole take under a model of its gapped first half (written to another file):
self-calibrated 99.25 % (the right upper arm and elbow exchanged in 774 frames), recognised
100 %.

Library entry points for a node service: :func:`calibrate` (labelled frames, e.g. what the
node published with high confidence) and :func:`self_calibrate` (raw clouds);
:func:`auto_calibrate` (``dtm-label``'s default) self-calibrates a generic body on a take's
first frames and keeps the result only when the calibrated model reproduces what it was
measured on.
"""
from __future__ import annotations

import datetime as _dt
import warnings
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np

from ..labeling.confidence import CONFIRMED
from ..labeling.stream import LabelerSettings, StreamLabeler
from ..model.body import SEGMENT, BodyModel, BroadMotion, quads_off_ordered_bars, segment_clusters
from ..model.dtm import TriangulatedModel
from ..motion.clip import MotionClip
from ..motion.pointsets import model_points
from ..search.problem import Background
from .body_fit import person_rigid_pairs, quad_signs, sides, window_broad_weights
from .placement import adapted_mixtures
from .gaps import facing_states, loglik_per_label


@dataclass(frozen=True)
class CalibrationSettings:
    min_frames: int = 10             # a pair seen together in fewer frames keeps its generic range
    max_spread_m: float = 0.02       # a segment whose length scatters more (robust sd) keeps its generic
                                     # range: its labels are not one segment (an arm labelled wrist-for-elbow)
    within_factor: float = 1.5
    scale_clip: tuple = (0.75, 1.33)
    min_confidence: float = CONFIRMED    # self-labelling: confidence a label needs to count as confirmed
    volume_m3: float = 1000.0        # self-labelling: clutter density (larger: a point that fits the generic
                                     # body poorly is still labelled; the medians are robust to a few wrong ones)
    open_between_rel: float = 0.3    # self-labelling: between-person spread of the generic body in the first
                                     # round, and of a segment no round could measure (relative to its length)
    rounds: int = 2                  # self-calibration: label, calibrate, label again, ...
    complete_below: float = 0.2      # self-calibration, last round: a label confirmed in fewer of the window's
                                     # frames is looked for among the points left out (completed_labels)
    complete_present: float = 0.5    # ... in at least this share of the frames, rigid to its segment partners
    complete_tol_m: float = 0.015    # ... within this of one distance to each partner
    mirror_abs_m: float = 0.02       # left/right segment lengths that differ by more than this ...
    mirror_rel: float = 0.08         # ... and by more than this fraction of their length disagree
    mirror_sd_m: float = 0.01        # spread of a segment length taken from its mirror
    min_kept: float = 0.9            # auto calibration: share of the generic model's confirmed labels the
                                     # calibrated model must keep on the same frames (auto_calibrate)
    attempts: int = 2                # auto calibration: self-labellings tried, each with its own search seed,
                                     # before the generic model is kept (auto_calibrate)
    broad_first_round: bool = True   # auto calibration: a self-calibration that fails its check is tried again
                                     # with the broad motion part open in its first round (auto_calibrate)
    placement_relevance: float = 20.0    # frames: MAP relevance of the motion means' placement adaptation
                                         # (training/placement.py); 0: the motion mixtures are kept as they are
    max_search_share: float = 0.5    # auto calibration: a self-labelling that needs a full search in more of
                                     # the window's frames stops there, and the generic model is kept
                                     # (SearchBudget, WindowNotFollowed)
    search_budget: float = 1.0       # auto calibration: full searches all its self-labellings may spend
                                     # together, per frame of the window (SearchBudget)
    broad_min_frames: int = 20       # broad weights fitted again on the window (body_fit.window_broad_weights)
                                     # for triangles with at least this many frames; 0: the training's kept
    moved_m: float = 0.01            # session check: a person's segment whose length on a new capture differs
    moved_sd: float = 2.0            # ... by more than this and this many of its spreads was placed again


MAX_CENTRES = 300                    # completed_labels: candidate clusters examined per label


class CalibrationError(ValueError):
    """Frames that cannot calibrate the model (no body terms, too few frames, wrong points)."""


class WindowNotFollowed(CalibrationError):
    """The self-labelling had to search more of the window's frames from scratch than its
    :class:`SearchBudget` allows: the model does not follow the take's points from frame to
    frame there (:func:`auto_calibrate`)."""


#: how a refused self-calibration's reason ends (:func:`auto_calibrate` returns the model it was
#: given); ``dtm-label`` says otherwise where it labels with another model then
#: (:func:`dtm_labeler.evaluation.archive.label_take`)
KEPT_AS_IT_IS = "the generic model is kept"
#: ... and a session check's (:func:`session_calibrate`)
SESSION_KEPT = "the person's calibration is kept as it is"


@dataclass
class SearchBudget:
    """The full searches a self-calibration may spend (:func:`auto_calibrate`): ``share`` of each
    self-labelling's frames, and ``total`` over all of its self-labellings together. A full
    search is the labeler's expensive step (0.2-0.5 s at 47 labels); a model that follows the
    take needs one or two per self-labelling."""
    share: float
    total: float
    spent: int = 0

    @property
    def left(self) -> float:
        return self.total - self.spent

    def spend(self, searched: int, frame: int, frames: int) -> None:
        """One more full search, the ``searched``-th of this self-labelling, at its ``frame``
        (1-based) of ``frames``; :class:`WindowNotFollowed` when it is over either bound."""
        self.spent += 1
        if searched > self.share * frames:
            raise WindowNotFollowed(
                f"the model needed a full search in {searched} of the first {frame} of {frames} frames "
                f"(at most {100 * self.share:.0f} % of them): it does not follow this take's points from frame "
                f"to frame, so labels to measure the person on would be a guess; {KEPT_AS_IT_IS}")
        if self.left < 0:
            raise WindowNotFollowed(
                f"the self-labellings spent the {self.total:g} full searches their window allows without a "
                "calibration that holds up: the model hardly follows this take's points from frame to frame; "
                f"{KEPT_AS_IT_IS}")


def labelled_positions(model: TriangulatedModel, source: MotionClip | np.ndarray) -> np.ndarray:
    """(F, M, 3) positions in the model's label order from a labelled clip or an array."""
    if isinstance(source, MotionClip):
        try:
            return model_points(source, model.labels).positions
        except (KeyError, ValueError) as e:
            raise CalibrationError(str(e).strip("'\"")) from None
    P = np.asarray(source, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (model.n_labels, 3):
        raise CalibrationError(f"calibration frames must be (F, {model.n_labels}, 3), got {P.shape}")
    return P


def mirror_rows(body: BodyModel, mirror_pairs: np.ndarray | None) -> np.ndarray:
    """(P,) the row of each pair's mirror pair (left and right labels exchanged) in ``body``,
    -1 where it has none or is its own mirror (neck-head, the hips' pair)."""
    _, m = sides(body.n_labels, mirror_pairs)
    rows = body.pair_index()[m[body.pairs[:, 0]], m[body.pairs[:, 1]]]
    rows[rows == np.arange(rows.size)] = -1
    return rows


def wrong_side(positions: np.ndarray, mirror_pairs: np.ndarray | None, heading_pairs: np.ndarray | None,
               min_frames: int = 10) -> np.ndarray:
    """(M,) labels whose point lies on the other side of the body's midline in more than half
    of the frames (at least ``min_frames``) where it and the trunk are seen (module doc). The
    vertical axis is z."""
    M = positions.shape[1]
    out = np.zeros(M, dtype=bool)
    mp = np.asarray(mirror_pairs if mirror_pairs is not None else np.zeros((0, 2)), dtype=np.int64).reshape(-1, 2)
    hp = np.asarray(heading_pairs if heading_pairs is not None else np.zeros((0, 2)), dtype=np.int64).reshape(-1, 2)
    if not len(mp) or not len(hp):
        return out
    xy = positions[..., :2]
    right = xy[:, hp[:, 1]] - xy[:, hp[:, 0]]                                       # (F, H, 2)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        axis = np.nanmean(right / np.linalg.norm(right, axis=-1, keepdims=True), axis=1)   # (F, 2)
        centre = np.nanmean(0.5 * (xy[:, hp[:, 0]] + xy[:, hp[:, 1]]), axis=1)           # (F, 2)
    side, _ = sides(M, mp)
    offset = np.einsum("fmk,fk->fm", xy - centre[:, None], axis) * side                # > 0: own side
    seen = np.isfinite(offset) & (side != 0)
    wrong = (np.where(seen, offset, 0.0) < 0).sum(0)
    n = seen.sum(0)
    out[:] = (n >= min_frames) & (wrong > 0.5 * n)
    return out


def symmetric_segments(body: BodyModel, measured: np.ndarray, length: np.ndarray, mirror: np.ndarray,
                       s: CalibrationSettings, check: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Which measured segments to keep and which to take from their mirror (module doc):
    returns (kept (P,) bool, borrowed (P,) bool). ``check=False`` (trusted labels): keep every
    measured segment, only fill the unmeasured ones from their mirrors."""
    mr = np.where(mirror >= 0, mirror, 0)
    generic = 0.5 * (body.lo + body.hi)
    tol = np.maximum(s.mirror_abs_m, s.mirror_rel * 0.5 * (generic + generic[mr]))
    has = ((mirror >= 0) & (np.abs(body.lo - body.lo[mr]) <= tol)        # both ends of the training
           & (np.abs(body.hi - body.hi[mr]) <= tol))                    # ranges agree (module doc)
    both = measured & has & measured[mr]
    with np.errstate(invalid="ignore"):
        gap = np.abs(length - length[mr])
        off = check & both & (gap > np.maximum(s.mirror_abs_m, s.mirror_rel * 0.5 * (length + length[mr])))
        outside = np.maximum(np.maximum(body.lo - length, length - body.hi), 0.0) / generic
    rows = np.arange(length.size)
    wrong = off & ((outside > outside[mr]) | ((outside == outside[mr]) & (rows > mr)))
    kept = measured & ~wrong
    borrowed = (body.kind == SEGMENT) & ~kept & has & kept[mr]
    return kept, borrowed


def pair_lengths(positions: np.ndarray, pairs: np.ndarray, settings: CalibrationSettings | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Median distance and robust (MAD) spread of each label pair (P, 2) over the frames of
    ``positions`` (F, M, 3; NaN = unseen) where both are seen, and whether it is measured: seen in
    at least ``min_frames`` frames, scattering no more than ``max_spread_m`` (NaN where never seen)."""
    s = settings or CalibrationSettings()
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    d = np.linalg.norm(positions[:, pairs[:, 0]] - positions[:, pairs[:, 1]], axis=-1)      # (F, P)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # pairs never seen together: NaN
        med = np.nanmedian(d, axis=0)
        mad = 1.4826 * np.nanmedian(np.abs(d - med), axis=0)
    measured = (np.isfinite(d).sum(0) >= s.min_frames) & (np.nan_to_num(mad, nan=np.inf) <= s.max_spread_m)
    return med, mad, measured


def calibrated_body(body: BodyModel, positions: np.ndarray, settings: CalibrationSettings | None = None,
                    mirror_pairs: np.ndarray | None = None, heading_pairs: np.ndarray | None = None,
                    check_labels: bool = True, leaves: np.ndarray | None = None) -> tuple[BodyModel, dict]:
    """The body of the person in ``positions`` (F, M, 3) (module doc); and a summary.
    ``mirror_pairs`` (left, right) label pairs: check left against right, ``heading_pairs``
    (the trunk's pairs): check each sided point's side (none: no check); ``check_labels=False``
    trusts the labels (an operator-labelled trial: a dancer's crossed legs are not a swap) and
    skips both checks. ``leaves`` (M,) bool: labels whose segments join no two segment clusters
    (a model's anonymous points, :mod:`dtm_labeler.training.anonymous`: the named points' rigid
    pairs and bars are those of the model without them; they have none)."""
    s = settings or CalibrationSettings()
    u, v = body.pairs[:, 0], body.pairs[:, 1]
    med, mad, measured = pair_lengths(positions, body.pairs, s)
    measured &= body.kind == SEGMENT
    flipped = (wrong_side(positions, mirror_pairs, heading_pairs, s.min_frames) if check_labels
               else np.zeros(body.n_labels, dtype=bool))
    measured &= ~(flipped[u] | flipped[v])
    mirror = mirror_rows(body, mirror_pairs)
    seg, borrowed = symmetric_segments(body, measured, med, mirror, s, check_labels)
    if not seg.any():
        raise CalibrationError(f"no segment seen in at least {s.min_frames} calibration frames "
                               f"({positions.shape[0]} frames given)")
    generic = 0.5 * (body.lo + body.hi)
    leaf = np.zeros(body.pairs.shape[0], dtype=bool) if leaves is None or not np.any(leaves) else \
        np.asarray(leaves, dtype=bool)[u] | np.asarray(leaves, dtype=bool)[v]
    scaled = seg & ~leaf if (seg & ~leaf).any() else seg        # the named segments set the scale
    ratio = np.clip(np.median(med[scaled] / generic[scaled]), *s.scale_clip)
    lo, hi = body.lo.copy(), body.hi.copy()
    within, between = body.within_sd.copy(), body.between_sd.copy()
    lo[seg] = hi[seg] = med[seg]
    within[seg] = np.maximum(body.within_sd[seg], s.within_factor * np.nan_to_num(mad[seg]))
    between[seg] = 0.0
    src = mirror[borrowed]
    lo[borrowed] = hi[borrowed] = med[src]
    within[borrowed] = np.maximum(within[src], s.mirror_sd_m)
    between[borrowed] = 0.0
    reach = body.kind != SEGMENT
    hi[reach] = body.hi[reach] * ratio
    between[reach] = 0.0
    summary = {"frames": int(positions.shape[0]), "segments": int(seg.sum()),
               "segments_total": int((body.kind == SEGMENT).sum()), "scale": float(ratio),
               "segments_from_mirror": int(borrowed.sum()),
               "asymmetric_dropped": int((measured & ~seg).sum()),
               "wrong_side_labels": int(flipped.sum()),
               "median_change_m": float(np.median(np.abs(med[seg] - generic[seg]))),
               "calibrated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
    quads, signs = quad_signs(positions, body.quads)     # the person's clusters as this session placed them
    if check_labels:
        quads, signs, summary["handedness_flips_dropped"] = unflipped_quads(body, quads, signs)
    orders = kept_orders(body.orders, positions)         # the bars' order, unless the person reverses it
    summary["bar_orders"] = int(orders.shape[0])
    summary["bar_orders_dropped"] = int(body.orders.shape[0] - orders.shape[0])
    take_orders = kept_orders(body.take_orders, positions)     # the take pass's, likewise
    summary["take_bar_orders"] = int(take_orders.shape[0])
    joins = (seg | borrowed) & ~leaf
    quads, signs, summary["handedness_left_to_orders"] = quads_off_ordered_bars(
        quads, signs, orders, segment_clusters(body.n_labels, body.pairs[joins]))
    summary["handedness_quads"] = int(quads.shape[0])
    rigid = cluster_pairs(body, positions, joins, leaves)
    summary["rigid_pairs"] = int(rigid["rigid_pairs"].shape[0])
    return replace(body, lo=lo, hi=hi, within_sd=within, between_sd=between, calibration=summary,
                   quads=quads, quad_sign=signs, orders=orders, take_orders=take_orders, **rigid), summary


def kept_orders(orders: np.ndarray, positions: np.ndarray, min_frames: int = 10) -> np.ndarray:
    """Of the training's bar ``orders`` (:class:`~dtm_labeler.model.body.BarOrder`, rows
    ``(x, near, far)``), those the calibration frames (F, M, 3) do not contradict: ``x`` nearer
    ``near`` in at least half of the frames that show all three, or in fewer than ``min_frames``
    frames shown. The order is a property of the limb, which the training saw in every clip, and
    not of a window: self-labelled frames show a bar exchanged in some frames (the floor-moves
    cell's first 225 frames: the right wrist bar in 28), so a share as strict as the training's
    would drop the order exactly where it is needed; another lab's placement that reverses it
    shows the other order in most frames."""
    rows = np.asarray(orders, dtype=np.int64).reshape(-1, 3)
    if rows.shape[0] == 0:
        return rows
    x, near, far = (positions[:, rows[:, k]] for k in range(3))                    # (F, K, 3) each
    with np.errstate(invalid="ignore"):
        gap = np.linalg.norm(x - far, axis=-1) - np.linalg.norm(x - near, axis=-1)   # > 0: as trained
    seen = np.isfinite(gap)
    n = seen.sum(0)
    held = (np.where(seen, gap, -1.0) > 0).sum(0)
    return rows[(n < min_frames) | (2 * held >= n)]


def cluster_pairs(body: BodyModel, positions: np.ndarray, calibrated: np.ndarray,
                  leaves: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The calibrated person's rigid pairs within the segment clusters
    (:attr:`~dtm_labeler.model.body.BodyModel.rigid_pairs`), measured on the calibration frames
    as training measures them (:func:`~dtm_labeler.training.body_fit.person_rigid_pairs`), the
    clusters those of the ``calibrated`` (P,) segments -- for a marker body (one with handedness
    quadruples or rigid pairs); none for joint centres. The trained person's pairs are not this
    person's, so they are never kept. ``leaves`` (M,) bool: labels that join no clusters
    (:func:`~dtm_labeler.training.body_fit.person_rigid_pairs`)."""
    marker_body = bool(body.quads.shape[0] or body.rigid_pairs.shape[0])
    own = () if leaves is None else np.flatnonzero(leaves)
    return person_rigid_pairs([positions] if marker_body else [], body.pairs[calibrated & (body.kind == SEGMENT)],
                              leaves=own)


def unflipped_quads(body: BodyModel, quads: np.ndarray, signs: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Of the person's quadruples (:func:`~.body_fit.quad_signs` of the calibration frames),
    those whose handedness is the one the training learnt; and how many were dropped.

    Labels the model gave itself (a self-calibration) can show a cluster mirrored because the
    window's labels exchanged two of its markers, and a sign learnt from them holds the
    exchange from then on. The training people agree with the person's true labels on nearly
    every quadruple (HDM05's training signs against CMU 85's true labels: 45 of the 46 that its
    first 5 s show at 99 %), while the HDM05 model self-calibrated on that window learnt 4
    quadruples the other way round (the trunk's C7-CLAV-LSHO-RSHO, the left wrist bar's
    LUPA-LELB-LWRA-LWRB, one of the right arm, one across the knees). So a quadruple whose sign
    flipped in self-labelled frames is taken as the labels' error rather than the person's
    cluster: it is dropped (neither sign applies).
    ``dtm-eval``'s 41-marker generalisation cells (``dtm-label`` default, stream): HDM05 -> CMU
    85 92.18 -> 92.86 % (the LTOE/LMT5 exchange of 82 frames gone; the wrist bars still
    exchanged in ~80 frames each), the other four identical (100, 99.50, 99.92, 93.55 %).
    Labels from a capture (``check_labels=False``) are trusted and keep every sign they show."""
    trained = {tuple(q): sg for q, sg in zip(np.asarray(body.quads).reshape(-1, 4).tolist(), body.quad_sign)}
    keep = np.array([trained.get(tuple(q), sg) == sg for q, sg in zip(quads.tolist(), signs)], dtype=bool)
    return quads[keep], signs[keep], int((~keep).sum())


def fit_per_label(model: TriangulatedModel, positions: np.ndarray, rate: float) -> float | None:
    """The typical fitness per seen label of labelled frames (F, M, 3) at ``rate`` under
    ``model`` -- heading-canonical eq. 12 states, as training measures its reference
    (:func:`~dtm_labeler.training.gaps.loglik_per_label`); None when no frame shows half the
    labels with velocities."""
    P = np.asarray(positions, dtype=np.float64)
    seen = np.isfinite(P).all(-1)
    seen[1:] &= seen[:-1]                           # velocities need the point in the frame before
    if not (seen.sum(1) >= max(3, P.shape[1] // 2)).any():
        return None
    return loglik_per_label(model, facing_states(P, model.heading_pairs, rate))


def calibrate(model: TriangulatedModel, source: MotionClip | np.ndarray,
              settings: CalibrationSettings | None = None, check_labels: bool = True,
              rate: float | None = None) -> TriangulatedModel:
    """``model`` with the body terms of the person in ``source``: a labelled clip (the
    model's labels or points derivable from it) or (F, M, 3) positions in the model's label
    order (NaN = unseen). The model's structure is kept, its mixtures' position means adapted
    to the frames (``settings.placement_relevance``, :mod:`.placement`) and, when the frames'
    rate is known, each triangle's broad weight fitted again on them (``settings.broad_min_frames``,
    :func:`.body_fit.window_broad_weights`); the confidence's fit
    reference (``settings["fit_reference_per_label"]``) is measured on the frames too (module
    doc) when their rate is known (a clip's, or ``rate``). ``check_labels``: check left against right and each
    point's side (labels from a model); False trusts them (an operator-labelled capture).
    The body before the calibration stays with the model (``generic_body``, :func:`generic_view`)
    and a calibrated model is calibrated again from it: one person's lengths are never the
    starting range of another's."""
    if model.body is None:
        raise CalibrationError("the model has no body terms to calibrate (format version 1 or trained "
                               "without them); retrain with dtm-train")
    s = settings or CalibrationSettings()
    P = labelled_positions(model, source)
    # calibrations do not compound: a calibrated model is calibrated again from its generic body
    generic = model.generic_body if model.body.calibration else model.body
    body, summary = calibrated_body(generic or model.body, P, s, model.mirror_pairs, model.heading_pairs,
                                    check_labels, leaves=model.anonymous)
    mixtures = model.mixtures
    if s.placement_relevance > 0:
        mixtures, summary["placement"] = adapted_mixtures(model, P, s.placement_relevance, s.min_frames)
    rate = source.rate if isinstance(source, MotionClip) and rate is None else rate
    broad, trained = model.broad, None
    if broad is not None and rate and s.broad_min_frames > 0:     # velocities need the rate
        trained = np.asarray(model.settings.get("broad_weights_training", broad.weights), dtype=np.float64)
        w, summary["broad"] = window_broad_weights(broad, mixtures, model.triangles,
                                                   facing_states(P, model.heading_pairs, rate), trained,
                                                   s.broad_min_frames)
        broad = BroadMotion(w, broad.gaussians)
    # the body before any calibration stays with the model (:func:`generic_view`)
    out = model.replace(body=body, mixtures=mixtures, broad=broad, generic_body=generic)
    out.settings.pop("fit_reference_per_label", None)     # calibrations do not compound
    out.settings.pop("named_fit_reference_per_label", None)
    if trained is not None:
        out.settings["broad_weights_training"] = trained.tolist()
    ref = fit_per_label(out, P, rate) if rate else None
    training = out.settings.get("loglik_per_label")
    if ref is not None and np.isfinite(ref) and training is not None:
        out.settings["fit_reference_per_label"] = min(float(training), ref)
        summary["fit_per_label"] = {"training": training, "calibration_frames": ref}
        if out.anonymous.any():       # ... and of the model without its anonymous points (named_only)
            named = out.named_only()
            own = fit_per_label(named, P[:, ~out.anonymous], rate)
            if own is not None and np.isfinite(own):
                out.settings["named_fit_reference_per_label"] = min(float(named.settings["loglik_per_label"]), own)
    out.provenance["calibration"] = summary
    return out


def generic_view(model: TriangulatedModel) -> TriangulatedModel | None:
    """``model`` with its calibration set aside: its body as it was before it was calibrated
    (:attr:`TriangulatedModel.generic_body`), so the segment terms, the broad part and the
    clusters' handedness wait for a calibration again; None when the model is not calibrated or
    did not keep that body (files before format 7). The mixtures keep the calibration's
    placement (:mod:`.placement`), which for a calibration on the training takes themselves
    (:func:`calibrate_on_takes`) is their own frames again, and the broad weights it fitted
    (applied only once calibrated again, which fits them anew from the training ones)."""
    if model.body is None or not model.body.calibration or model.generic_body is None:
        return None
    out = model.replace(body=model.generic_body, generic_body=None)
    out.provenance.pop("calibration", None)
    out.settings.pop("fit_reference_per_label", None)     # the calibration's yardstick (:func:`calibrate`)
    out.settings.pop("named_fit_reference_per_label", None)
    return out


#: the provenance ``source`` of a calibration on a model's own training takes (:func:`calibrate_on_takes`)
TAKES_SOURCE = "training takes"


def takes_calibration(model: TriangulatedModel) -> dict | None:
    """The provenance of ``model``'s calibration when it was calibrated on its own training takes
    (:func:`calibrate_on_takes`; ``why`` says why they were taken for one person, "asked" when the
    user said so), else None."""
    cal = model.provenance.get("calibration") or {}
    return cal if model.body is not None and cal.get("source") == TAKES_SOURCE else None


def calibrate_on_takes(model: TriangulatedModel, clips: Sequence[MotionClip]) -> TriangulatedModel:
    """``model`` calibrated to the one person of its labelled training ``clips`` (``dtm-train
    --calibrate``): :func:`calibrate` on all their frames, the labels trusted as an operator's;
    with captures of several sessions, each segment's range spans its sessions' lengths
    (:func:`session_ranges`)."""
    positions = [labelled_positions(model, c) for c in clips]
    P = np.concatenate(positions)
    rates = {float(c.rate) for c in clips}
    out = calibrate(model, P, check_labels=False, rate=rates.pop() if len(rates) == 1 else None)
    captures: dict[str, list[np.ndarray]] = {}
    for c, x in zip(clips, positions):
        captures.setdefault(str(c.source), []).append(x)
    sessions = None
    if len(captures) > 1 and out.generic_body is not None:
        body, sessions = session_ranges(out.body, out.generic_body.within_sd,
                                        [np.concatenate(x) for x in captures.values()])
        out = out.replace(body=body)
    out.provenance["calibration"] = dict(out.provenance["calibration"], source=TAKES_SOURCE,
                                         captures=[c.source for c in clips])
    if sessions is not None:
        out.provenance["calibration"]["session_ranges"] = sessions
    return out


def session_ranges(body: BodyModel, within_sd: np.ndarray, captures: Sequence[np.ndarray],
                   settings: CalibrationSettings | None = None) -> tuple[BodyModel, int]:
    """A calibrated ``body`` whose measured segments span the lengths of the person's
    ``captures`` (each (F, M, 3), one per capture session): ``[lo, hi]`` from the smallest to the
    largest of the captures' median lengths (each seen in ``min_frames`` frames and scattering no
    more than ``max_spread_m``), the spread the larger of ``within_sd`` (the generic body's) and
    1.5 x the largest within-capture scatter; and how many segments span more than ``moved_m``.

    Why: the markers are stuck on again for each session (:func:`session_calibrate`), and a
    median over the pooled frames of two sessions is the larger session's length: CMU 85's
    breakdance (2250 frames) and jump + twist (810), the left upper arm marker to the elbow 126.9
    and 104.9 mm, pooled 125.3 mm with a spread of 6.5 mm -- the jump + twist, one of the
    model's own captures, 3 spreads off it in every frame. As a range (eq. body factor's dead
    zone, :mod:`dtm_labeler.model.body`) both sessions' lengths cost nothing."""
    s = settings or CalibrationSettings()
    rows = np.flatnonzero((body.kind == SEGMENT) & (body.between_sd == 0))
    meds, mads = [], []
    for P in captures:
        med, mad, ok = pair_lengths(P, body.pairs[rows], s)
        meds.append(np.where(ok, med, np.nan))
        mads.append(np.where(ok, mad, np.nan))
    meds, mads = np.array(meds), np.array(mads)
    measured = np.isfinite(meds).any(0)
    rows, meds, mads = rows[measured], meds[:, measured], mads[:, measured]
    lo, hi, within = body.lo.copy(), body.hi.copy(), body.within_sd.copy()
    lo[rows], hi[rows] = np.nanmin(meds, 0), np.nanmax(meds, 0)
    within[rows] = np.maximum(within_sd[rows], s.within_factor * np.nanmax(mads, 0))
    spans = int(((hi[rows] - lo[rows]) > s.moved_m).sum())
    return replace(body, lo=lo, hi=hi, within_sd=within), spans


def confirmed_positions(labels: np.ndarray, confidence: np.ndarray, xyz: np.ndarray, n_labels: int,
                        min_confidence: float = CONFIRMED) -> np.ndarray:
    """(M, 3) positions of one labelled frame in label order: the points labelled with at least
    ``min_confidence`` (NaN for the other labels) -- what a calibration takes as confirmed."""
    out = np.full((n_labels, 3), np.nan)
    ok = (np.asarray(labels) >= 0) & (np.asarray(confidence) >= min_confidence)
    out[np.asarray(labels)[ok]] = np.asarray(xyz, dtype=np.float64)[ok]
    return out


def confirmation_of(result) -> np.ndarray:
    """(n,) what a calibration confirms a label by: the labeler's ``confirmation`` (its confidence
    with the release alternative counted in full, :func:`~dtm_labeler.labeling.confidence.label_posteriors`),
    else the published confidence."""
    c = getattr(result, "confirmation", None)
    return np.asarray(result.confidence if c is None else c, dtype=float)


def completed_labels(model: TriangulatedModel, confirmed: np.ndarray, clouds: Sequence[np.ndarray],
                     settings: CalibrationSettings | None = None) -> tuple[np.ndarray, list[str]]:
    """``confirmed`` (F, M, 3) with the labels the self-labelling (almost) never confirmed
    filled in from the points it left out, where one such point stays rigid to the label's
    segment partners; and the names of the labels filled.

    A marker placed where the training people's never sat is left out by the generic model in
    every frame (CMU 85 -> HDM05: the right shank marker 10 cm lower), so none of its segments
    and none of its triangles' placement can be measured, and the calibrated model leaves it
    out too. Its point is still in the clouds, and it is on a segment: its distance to each
    *partner* -- a label the body calls one segment with it (``SEGMENT``) and that was
    confirmed in at least ``1 - complete_below`` of the frames -- stays the same in every
    frame, whatever its value. For a label confirmed in under ``complete_below`` of the frames,
    every left-out point of a frame that shows its partners gives a vector of distances to them;
    the vectors within ``complete_tol_m`` of the most populous one are one physical marker, and
    it is taken when it shows in at least ``complete_present`` of the frames and no other such
    cluster does (a second rigid point would make the choice a guess). One point per frame, the
    closest to the cluster's centre. Measured on the self-calibration of the generalisation
    cells: the points taken were the true marker in every frame (RSHN, CMU 85 -> HDM05: 393 of
    393, the cell 97.56 -> 100 %). A looser completion (partners confirmed in 60 % of the frames,
    no check for a second rigid point) also took the true RMT5 of HDM05 -> CMU 85 (193 of 193)
    but lowered that cell 92.18 -> 90.66 %; this one leaves RMT5 out and the cell as it was."""
    s = settings or CalibrationSettings()
    P = np.array(confirmed, dtype=np.float64)
    F = P.shape[0]
    seen = np.isfinite(P[..., 0])
    share = seen.mean(0)
    body, done = model.body, []
    segment = body.kind == SEGMENT
    for m in np.flatnonzero(share < s.complete_below):
        partners = body.pairs[segment & (body.pairs == m).any(1)].sum(1) - m
        partners = partners[share[partners] >= 1.0 - s.complete_below]
        if partners.size == 0:
            continue
        points, vectors, frames = [], [], []          # every left-out point of a frame showing the partners
        for f in np.flatnonzero(seen[:, partners].all(1)):
            x = np.asarray(clouds[f], dtype=np.float64).reshape(-1, 3)
            left = np.abs(x[:, None, :] - P[f][seen[f]][None]).max(-1).min(1, initial=np.inf) >= 1e-9
            points.append(x[left])
            vectors.append(np.linalg.norm(x[left][:, None, :] - P[f, partners][None], axis=-1))
            frames.append(np.full(int(left.sum()), f))
        if not points:
            continue
        X, V, owner = np.concatenate(points), np.concatenate(vectors), np.concatenate(frames)
        if not len(X):
            continue
        # clusters around at most MAX_CENTRES of the vectors (bounded memory with many left-out points)
        centres = np.unique(np.linspace(0, len(V) - 1, min(len(V), MAX_CENTRES)).astype(np.int64))
        close = np.abs(V[centres][:, None] - V[None]).max(-1) < s.complete_tol_m          # (C, N)
        shows = np.array([np.unique(owner[c]).size for c in close])                        # frames per cluster
        best = int(np.argmax(shows))
        if shows[best] < s.complete_present * F:
            continue
        apart = ~close[:, close[best]].any(1)            # clusters sharing no point with the best one
        if (shows[apart] >= s.complete_present * F).any():
            continue                                     # a second rigid point shown as often: no choice
        members = np.flatnonzero(close[best])
        gap = np.abs(V[members] - V[members].mean(0)).max(1)
        for k in members[np.argsort(gap)[::-1]]:         # the closest to the centre written last: kept
            P[owner[k], m] = X[k]
        done.append(model.labels[m])
    return P, done


def calibration_labeling(settings: LabelerSettings | None = None) -> LabelerSettings:
    """The settings a calibration's self-labelling runs with: ``settings`` (default ones when
    None) without the arrangement memory (:func:`self_label`) nor the bar order votes (the same
    memory of a bar's ends; a second round labels with the first's calibrated body, whose bars
    they would read: ``dtm-eval``'s floor moves, single frames after the window 99.09 -> 96.95 %
    with them), and without the full search's
    wide sweeps (``wide_sweeps``, ``mirror_sweeps``). The window is labelled by a model of other people; a search
    that relabels whole body neighbourhoods finds more of what that model prefers where it is
    wrong about this person, and the calibration then measures it: ``dtm-eval``'s subject 9 run
    left out, body + calibration, stream / single frames 100 / 98.21 -> 71.43 / 75.60 % with
    them (one segment taken from its mirror, 94.5 % of the window confirmed instead of 98.6 %)."""
    s = settings or LabelerSettings()
    return replace(s, cluster_memory_s=0.0, bar_order_gain=0.0, full=replace(s.full, wide_sweeps=0, mirror_sweeps=0))


def self_label(model: TriangulatedModel, clouds: Sequence[np.ndarray] | np.ndarray, rate: float,
               settings: LabelerSettings | None = None, min_confidence: float = CONFIRMED,
               progress: Callable[[int, int], None] | None = None,
               budget: SearchBudget | None = None) -> np.ndarray:
    """Label unlabelled clouds (one (n, 3) array per frame, or (F, N, 3)) with ``model`` in
    stream mode and return the confirmed labels as (F, M, 3) positions (NaN where a label
    was not given with at least ``min_confidence``); ``progress(frames done, frames)`` after
    each frame. ``budget``: each full search spent from it, :class:`WindowNotFollowed` (the
    rest of the window not labelled) once it is over (:class:`SearchBudget`).

    The labeler runs without the arrangement memory (``cluster_memory_s`` 0; :mod:`~dtm_labeler.
    labeling.cluster_evidence`): a calibration measures the person from what each frame shows, as
    its confirmation does; the memory keeps the arrangement the window's first frames preferred,
    and under a model of other people that is the model's, not the person's. With it, ``dtm-eval``'s
    floor moves under ``dtm-label``'s default lost the self-calibration (refused by its check: the
    generic body labelled, stream 100 -> 97.35 %, single frames 96.65 -> 82.93 %); without it, as
    before."""
    lab = StreamLabeler(model, calibration_labeling(settings))
    out = np.full((len(clouds), model.n_labels, 3), np.nan)
    searched = 0
    for f, xyz in enumerate(clouds):
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        xyz = xyz[np.isfinite(xyz).all(1)]
        res = lab.process(xyz, f / rate)
        if res.full_search and budget is not None:
            searched += 1
            budget.spend(searched, f + 1, len(clouds))
        out[f] = confirmed_positions(res.labels, confirmation_of(res), xyz, model.n_labels, min_confidence)
        if progress is not None:
            progress(f + 1, len(clouds))
    return out


def self_calibrate(model: TriangulatedModel, clouds: Sequence[np.ndarray] | np.ndarray, rate: float,
                   settings: CalibrationSettings | None = None,
                   labeler: LabelerSettings | None = None) -> tuple[TriangulatedModel, np.ndarray]:
    """Calibrate on unlabelled clouds: label them with the model (:func:`self_label`),
    calibrate on the confirmed labels, and repeat with the calibrated model (``rounds``).
    Returns the calibrated model and the last confirmed labels (F, M, 3)."""
    current, rounds = _self_calibration(model, clouds, rate, settings, labeler)
    return current, rounds[-1]


def _self_calibration(model: TriangulatedModel, clouds, rate: float, settings: CalibrationSettings | None,
                      labeler: LabelerSettings | None, first: np.ndarray | None = None,
                      progress: Callable[[int, int], None] | None = None,
                      budget: SearchBudget | None = None,
                      broad: bool = False) -> tuple[TriangulatedModel, list[np.ndarray]]:
    """:func:`self_calibrate`, returning every round's confirmed labels (F, M, 3); ``first``:
    the first round's, when an earlier self-calibration of the same frames has them;
    ``progress``, ``budget``: each self-labelling's (:func:`self_label`); ``broad``: the first
    round with the broad motion part open (:func:`auto_calibrate`)."""
    s = settings or CalibrationSettings()
    current = model
    rounds = []
    labeler = labeler or LabelerSettings(background=Background(volume_m3=s.volume_m3))
    if model.body is not None:               # first round: a body open to other people's proportions
        b = model.body
        wide = np.maximum(b.between_sd, s.open_between_rel * 0.5 * (b.lo + b.hi))
        current = model.replace(body=replace(b, between_sd=wide), broad_open=broad)
    completed: list[str] = []
    for k in range(max(1, s.rounds)):
        rounds.append(first if k == 0 and first is not None
                      else self_label(current, clouds, rate, labeler, s.min_confidence, progress,
                                      budget))
        positions = rounds[-1]
        if k > 0:       # after a first calibration: the first round's generic model reads wrong distances
            positions, completed = completed_labels(model, positions, clouds, s)
        # the fit reference joins after the last round (module doc): the rounds confirm with
        # the training reference's confidences
        current = calibrate(model, positions, s, rate=rate if k == max(1, s.rounds) - 1 else None)
        current, still_open = _unmeasured_kept_open(current, wide if model.body is not None else None)
    current.provenance["calibration"] = dict(current.provenance["calibration"], source="self-labelled",
                                             rounds=max(1, s.rounds), completed=completed,
                                             segments_open=still_open)
    return current, rounds


def _unmeasured_kept_open(model: TriangulatedModel, wide: np.ndarray | None) -> tuple[TriangulatedModel, int]:
    """``model`` with every segment its calibration could not measure (still a between-person
    spread) as open as the self-labelling's first round (``wide``); and how many.

    A segment goes unmeasured when the generic body never let the model confirm one of its
    labels: the person's forearm 27 % shorter than the training person's (CMU subject 5 under a
    body of subject 55: 0.138 m against 0.188 m, 5.5 between-person sd) leaves the wrists out
    in every frame. With the generic spread kept, the calibrated model left them out too, for
    the whole take (85.7 % on 150 frames, both wrists 0 %); open, the next round and the take
    can label them -- the person's other segments, now measured, hold the rest of the body in
    place -- and the auto calibration's check still judges the result."""
    if wide is None:
        return model, 0
    b = model.body
    still = (b.kind == SEGMENT) & (b.between_sd > 0) & (wide > b.between_sd)
    if not still.any():
        return model, 0
    return model.replace(body=replace(b, between_sd=np.where(still, wide, b.between_sd))), int(still.sum())


def calibratable(model: TriangulatedModel) -> bool:
    """Whether :func:`auto_calibrate` would calibrate ``model``: a generic body with segments
    (not yet calibrated to a person; models without body terms have nothing to calibrate)."""
    return model.body is not None and not model.body.calibration and bool((model.body.kind == SEGMENT).any())


def stream_calibration_target(model: TriangulatedModel) -> TriangulatedModel | None:
    """What a self-calibration on a live stream of an unknown person calibrates (the node's
    ``auto_calibrate``): a generic body as it is (:func:`calibratable`); a body ``dtm-train``
    calibrated to its training takes' person (:func:`calibrate_on_takes`, unless the user said
    the takes are the person to label: ``why`` "asked") seen as generic again
    (:func:`generic_view`) -- a stream is not known to be that person's, and another person's
    lengths and placement cost right labelings (``dtm-label --calibrate auto``'s rule for a
    capture not known to be theirs). Measured, stream mode as ``dtm-eval`` feeds it: CMU 85's two
    takes -> HDM05 97.2 % generic, 66.0 % under subject 85's calibration; HDM05 -> CMU 85 20.7 %
    generic, 0.8 % under the HDM05 person's (self-calibrated on the stream: 100 / 99.0 %). None:
    nothing to calibrate (no body terms, a person's own calibration, a file without the generic
    body)."""
    if calibratable(model):
        return model
    cal = takes_calibration(model)
    if cal is None or cal.get("why") == "asked":
        return None
    generic = generic_view(model)
    return generic if generic is not None and calibratable(generic) else None


#: share of the segments two calibrations both measured that must agree for one person
SAME_PERSON_SHARE = 0.7
#: ... of at least this many segments
SAME_PERSON_MIN_SEGMENTS = 5
#: a segment agrees within two of the person's spreads or this many metres
SAME_PERSON_TOLERANCE_M = 0.01


def segments_agree(body: BodyModel, person: BodyModel) -> tuple[int, int]:
    """``(agreeing, compared)``: of the segments both calibrations measured (``between_sd`` 0,
    :func:`calibrated_body`; the same model's body, so the same pairs), those whose lengths agree
    within two of ``person``'s spreads or :data:`SAME_PERSON_TOLERANCE_M` (with its range where
    ``person`` spans several sessions, :func:`session_ranges`)."""
    if body.pairs.shape != person.pairs.shape or not np.array_equal(body.pairs, person.pairs):
        return 0, 0
    both = (body.kind == SEGMENT) & (body.between_sd == 0) & (person.between_sd == 0)
    length = 0.5 * (body.lo + body.hi)
    tol = np.maximum(2.0 * person.within_sd, SAME_PERSON_TOLERANCE_M)
    agree = (length >= person.lo - tol) & (length <= person.hi + tol)     # a person of several sessions: a range
    return int((both & agree).sum()), int(both.sum())


def same_person(body: BodyModel, person: BodyModel) -> bool:
    """Whether a take's self-calibrated ``body`` is the calibrated ``person`` (module doc,
    *Whose body*): at least :data:`SAME_PERSON_SHARE` of at least
    :data:`SAME_PERSON_MIN_SEGMENTS` segments both measured agree (:func:`segments_agree`)."""
    return _one_person(*segments_agree(body, person))


def _one_person(agree: int, compared: int) -> bool:
    return compared >= SAME_PERSON_MIN_SEGMENTS and agree >= SAME_PERSON_SHARE * compared


def one_person_by_lengths(model: TriangulatedModel, clips: Sequence[MotionClip]) -> str | None:
    """Why labelled captures of several files are one person, read from their bodies: each
    capture calibrated alone (:func:`calibrate_on_takes`, its labels trusted) measures the same
    person as the first (:func:`same_person`) -- ``dtm-train``'s reason to calibrate to them
    where no CMU take naming says so; None when a capture is someone else's, a capture cannot be
    calibrated, or all the clips are of one file."""
    by: dict[str, list[MotionClip]] = {}
    for c in clips:
        by.setdefault(str(c.source), []).append(c)
    if len(by) < 2 or model.body is None:
        return None
    groups = iter(by.values())
    counts = []
    try:
        first = calibrate_on_takes(model, next(groups)).body
        for group in groups:                     # stops at the first capture of someone else
            counts.append(segments_agree(calibrate_on_takes(model, group).body, first))
            if not _one_person(*counts[-1]):
                return None
    except CalibrationError:
        return None
    worst = min(counts, key=lambda ac: ac[0] / max(ac[1], 1))
    return (f"one person by their segment lengths ({len(by)} captures; at least {worst[0]} of {worst[1]} "
            "segments agree)")


def kept_share(before: np.ndarray, after: np.ndarray) -> float:
    """Of the labels confirmed in ``before`` (F, M, 3; NaN = not confirmed), the share that
    ``after`` confirms on the same point (1.0 when ``before`` confirmed none)."""
    had = np.isfinite(before[..., 0])
    same = had & (np.nan_to_num(np.abs(after - before), nan=np.inf).max(-1) < 1e-9)
    return float(same.sum() / had.sum()) if had.any() else 1.0


def auto_calibrate(model: TriangulatedModel, clouds: Sequence[np.ndarray] | np.ndarray, rate: float,
                   settings: CalibrationSettings | None = None,
                   progress: Callable[[int, int], None] | None = None) -> tuple[TriangulatedModel, dict]:
    """``model`` self-calibrated on the unlabelled ``clouds`` of a take's start when the
    calibration holds up, else ``model`` itself; and a JSON-ready summary (``applied`` says
    which, ``reason`` why not). A model calibrated to a person, on another capture of theirs,
    is checked with :func:`session_calibrate` instead.

    The self-calibration (:func:`self_calibrate`) is a hypothesis about the person, built on
    the labels the model confirmed. It is kept only when the calibrated model, labelling the
    same frames again, keeps at least ``min_kept`` of the labels the generic model confirmed
    in its first round (:func:`kept_share`): a calibration that overturns the evidence it was
    measured on -- the lengths of an arm chain confirmed one marker along, or a short window
    of a run whose calibrated legs then swap below the hips -- describes no consistent body.
    Measured on ``dtm-eval``'s generalisation cells as ``dtm-label`` feeds a take (points
    shuffled; stream accuracy over the take's first 5 s, at most a third of it, and the 360-480
    frames after them, model as it is -> default;
    ``benchmarks/bench_auto_calibration.py``, a short take calibrated on its first third and on
    all of its first 5 s, the better reproduced kept): subject 5 pirouette 73.7 -> 99.9 %,
    subject 9 run 80.4 -> 98.3 %, subject 55 lambada 86.1 -> 100 %, CMU 85 breakdance -> jump
    and twist 86.0 -> 99.95 %, HDM05 -> CMU 85 69.0 -> 95.5 %; floor moves not applied (kept
    77 %, 69.9 % either way); no cell lower. The check matters: the same windows with the points
    in label order gave two calibrations that would have lowered the cell (subject 9 80.4 ->
    74.1 %, CMU 85 -> HDM05 96.1 -> 73.7 %); both keep under 90 % (83 and 69 %) and are dropped.

    The self-labelling is a search, and a stream that starts wrong can stay wrong for the whole
    window (the floor moves, below). When the check fails, it is tried again with another seed of
    its searches, ``attempts`` in all (``attempts`` in the summary says how many ran): floor moves,
    training and search seeds 0 / 2 / 3, 27.34 / 71.99 / 87.55 -> 27.34 / **95.81** / 87.55 % (seed 2's
    second self-labelling passes); a calibration that passes the first time is unchanged, and one
    that fails costs its time twice.

    The calibrated model also reads the marker placement from the window (:mod:`.placement`).
    When that model fails the check, the body alone is tried on the same first-round labels
    (``placement_dropped`` in the summary says so): a window of floor moves gives each
    triangle the shift of poses the training never showed, not of a marker's place -- kept
    59 % with the placement, 95 % without (stream 93.55 % as before the placement).

    The self-calibration stops, and the generic model is kept (``not_followed`` in the summary),
    once one self-labelling has needed a full search in more than ``max_search_share`` of the
    window's frames, or all of them together in more than ``search_budget`` times its frames
    (:class:`SearchBudget`): the model then does not follow the take's points from frame to
    frame, each frame's labels are a search of their own, and the attempts would cost minutes
    for nothing. Measured: the self-labellings of ``dtm-eval``'s generalisation cells need a full
    search in at most 18 % of their frames (subject 9's run under a model of other people; 0-2 %
    in the others), apart from a short take's first-third window (20 frames of a 60-frame take,
    where the first frames are searched until tracks hold: 41 markers, 11 of the first 11), which
    now stops and leaves the choice to the take's longer window (``bench_auto_calibration.py
    --short``: every figure as without the bound). On the gapped second halves of
    ``bench_captures`` (50 % of the samples hidden, 47 labels, 0.2-0.5 s a full search) the
    Qualisys walk's gap seed 1 needs one in 9-20 % of its frames (applied, as before), gap seed 3
    in 79-88 %: its self-calibration ran for over 11 minutes (both windows, two attempts, every
    round) and now stops after about 30 s (gap seed 4: about 55 s), the generic model kept as it
    was then.

    When every attempt fails its check, the self-calibration is tried once more with the broad
    motion part open in its first round (``broad_first_round``; ``first_round`` in the summary
    says which was kept, ``attempts`` counts it).
    The generic body holds the broad part back until a calibration (:mod:`dtm_labeler.model.body`,
    "Whose lengths": with no person's lengths its tails let a ghost take a hidden label), and a
    model of one motion then cannot label a pose that motion never showed: ``dtm-train``'s model
    of subject 7's walk (its structure hangs the legs' triangles on the wrists, which a walk
    swings against them) left both arms of subject 55's whirl unlabelled in the window -- the
    truth 700 nats below that labeling a frame, the broad part bounding it to -15 -- so the
    calibration measured no arm and failed its check (kept 90 %), and ``dtm-label`` fell back to
    the walker's calibration: 54.7 %. Open in the first round only: the window is labelled by
    votes and confirmed, the lengths measured there hold the calibrated model's ghosts off, and
    the check judges the result as before. Tried again that way: kept 94 %, the whirl 94.2 %
    (100 % with the take pass keeping held labels, :func:`~dtm_labeler.labeling.take_pass.
    take_pass`). Only after a failed check: as the first hypothesis it overturned a passing one
    (the same walk model on subject 5's pirouette: kept 69 %, 99.9 -> 38.8 %), and at 41
    markers a second self-calibration costs 25-40 s. Measured on every case of
    ``bench_auto_calibration.py`` (``results/auto_calibration.md``): no cell changed -- the
    one failing check there (``dtm-eval``'s walk model, the paper's hand-given structure, on the
    whirl) fails again with it (kept 2 %). Tried and not kept: the broad round also where a
    passing first round left a label out of the window, kept where it confirmed more there
    (the walk model on the lambada, arm exchanged by the first round's calibration, 86.8 ->
    100 %; the bench's cells the same or up to 0.9 points higher) -- ``dtm-train``'s model of
    subject 9's run then labelled the lambada's whole body mirrored (100 -> 14.3 %): the broad
    round confirmed more, of the mirror image, which its calibration reproduces (kept 93 %).
    What the round confirms more of is no sign of which body is right.
    """
    s = settings or CalibrationSettings()
    clouds = [np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in clouds]
    clouds = [x[np.isfinite(x).all(1)] for x in clouds]
    summary = {"applied": False, "source": "auto (the take's first frames, self-labelled)", "frames": len(clouds)}
    if not calibratable(model):
        summary["reason"] = ("the body is already calibrated" if model.body is not None and model.body.calibration
                             else "the model has no body terms to calibrate")
        return model, summary
    if len(clouds) < s.min_frames:
        summary["reason"] = f"{len(clouds)} frames, under the {s.min_frames} a calibration needs"
        return model, summary
    attempts = max(1, s.attempts)
    first = None
    budget = SearchBudget(share=s.max_search_share, total=s.search_budget * len(clouds))
    for attempt in range(attempts):
        out, info = _self_calibration_checked(model, clouds, rate, s, dict(summary, attempts=attempt + 1), attempt,
                                              budget, progress)
        if info["applied"]:
            return out, info
        first = first or (out, info)
        if info.get("not_followed"):          # another seed of the searches does not make the tracks hold
            attempts = attempt + 1
            break
    if s.broad_first_round and model.broad is not None and not first[1].get("not_followed"):
        out, info = _self_calibration_checked(model, clouds, rate, s, dict(summary, attempts=attempts + 1), 0,
                                              budget, progress, broad=True)
        if info["applied"]:
            return out, info
    first[1]["attempts"] = attempts
    return first


def _self_calibration_checked(model: TriangulatedModel, clouds: list[np.ndarray], rate: float,
                              s: CalibrationSettings, summary: dict, seed: int, budget: SearchBudget | None = None,
                              progress: Callable[[int, int], None] | None = None,
                              broad: bool = False) -> tuple[TriangulatedModel, dict]:
    """One attempt of :func:`auto_calibrate`: the self-calibration with the labeler's search
    seed ``seed`` and its check; ``model`` itself when the check fails. ``budget``: the full
    searches left (:class:`SearchBudget`); ``progress``: each self-labelling's frames;
    ``broad``: its first round with the broad motion part open (``first_round`` in the summary)."""
    labeler = LabelerSettings(background=Background(volume_m3=s.volume_m3), seed=seed)
    bound = dict(progress=progress, budget=budget)
    summary = dict(summary, first_round="broad" if broad else "generic")
    try:
        calibrated, rounds = _self_calibration(model, clouds, rate, s, labeler, broad=broad, **bound)
        kept = kept_share(rounds[0], self_label(calibrated, clouds, rate, labeler, s.min_confidence, **bound))
        if kept < s.min_kept and s.placement_relevance > 0:
            # the placement read from a window the model labels poorly (floor poses) can carry its
            # poses rather than the markers' places: the body alone, measured on the same labels
            summary["placement_dropped"] = f"kept {100 * kept:.0f} % with the placement adapted"
            s = replace(s, placement_relevance=0.0)
            calibrated, rounds = _self_calibration(model, clouds, rate, s, labeler, first=rounds[0], broad=broad,
                                                   **bound)
            kept = kept_share(rounds[0], self_label(calibrated, clouds, rate, labeler, s.min_confidence, **bound))
    except CalibrationError as e:
        summary["reason"] = str(e)
        summary["not_followed"] = isinstance(e, WindowNotFollowed)
        return model, summary
    info = calibrated.provenance["calibration"]
    summary.update({k: info[k] for k in ("segments", "segments_total", "scale", "completed") if k in info},
                   kept_share=kept)
    if kept < s.min_kept:
        summary["reason"] = (f"the calibrated model relabels {100 * (1 - kept):.0f} % of the labels it was "
                             f"measured on (at most {100 * (1 - s.min_kept):.0f} %): {KEPT_AS_IT_IS}")
        return model, summary
    summary["applied"] = True
    calibrated.provenance["calibration"] = dict(info, source=summary["source"], kept_share=kept)
    return calibrated, summary


def moved_pairs(pairs: np.ndarray, lo: np.ndarray, hi: np.ndarray, spread: np.ndarray, positions: np.ndarray,
                settings: CalibrationSettings | None = None, wrong: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which of a person's label ``pairs`` (P, 2) of known lengths ``[lo, hi]`` and ``spread``
    (P,) sit elsewhere in ``positions`` (F, M, 3; the confirmed labels of a new capture of the
    person): those whose median distance there, seen in at least ``min_frames`` frames and
    scattering no more than ``max_spread_m``, lies outside ``[lo, hi]`` by more than ``moved_m``
    and ``moved_sd`` spreads, neither label ``wrong`` (M,; on the wrong side of the body,
    :func:`wrong_side`). Returns (rows, their median distances, their robust spreads)."""
    s = settings or CalibrationSettings()
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    med, mad, measured = pair_lengths(positions, pairs, s)
    length = np.nan_to_num(med, nan=np.inf)
    off = np.maximum(lo - length, length - hi)
    ok = ~(wrong[pairs[:, 0]] | wrong[pairs[:, 1]]) if wrong is not None else True
    rows = np.flatnonzero(measured & (off > np.maximum(s.moved_m, s.moved_sd * spread)) & ok)
    return rows, med[rows], np.nan_to_num(mad[rows])


def _moved_body(model: TriangulatedModel, first: np.ndarray, rows: np.ndarray, med: np.ndarray, mad: np.ndarray,
                wrong: np.ndarray, s: CalibrationSettings) -> tuple[TriangulatedModel, int]:
    """:func:`session_calibrate`'s model with the segments ``rows`` at the window's lengths ``med``
    (their spread the larger of theirs and 1.5 x the window's ``mad``), and the rigid pairs the
    take pass reads likewise (:func:`moved_pairs` on the window's confirmed labels ``first``);
    and how many of those rigid pairs moved."""
    b = model.body
    lo, hi, within = b.lo.copy(), b.hi.copy(), b.within_sd.copy()
    lo[rows] = hi[rows] = med
    within[rows] = np.maximum(within[rows], s.within_factor * mad)
    r_rows, r_med, r_mad = moved_pairs(b.rigid_pairs, b.rigid_length, b.rigid_length, b.rigid_spread, first, s,
                                       wrong)
    length, spread = b.rigid_length.copy(), b.rigid_spread.copy()
    length[r_rows], spread[r_rows] = r_med, np.maximum(spread[r_rows], r_mad)
    body = replace(b, lo=lo, hi=hi, within_sd=within, rigid_length=length, rigid_spread=spread)
    return model.replace(body=body), int(r_rows.size)


def session_calibrate(model: TriangulatedModel, clouds: Sequence[np.ndarray] | np.ndarray, rate: float,
                      settings: CalibrationSettings | None = None,
                      progress: Callable[[int, int], None] | None = None) -> tuple[TriangulatedModel, dict]:
    """A model calibrated to a person (:func:`calibrate_on_takes`), checked on a new capture of
    theirs -- its unlabelled ``clouds``' start -- for what that session and that motion change:
    ``dtm-label --calibrate auto`` on another take of the training takes' CMU subject.

    * **Markers placed again.** A marker set's pair lengths are the person's *and* the
      session's: the markers are stuck on again for each session. The model labels the window as
      it is (:func:`self_label`); each segment whose confirmed length there lies outside the
      person's (:func:`moved_pairs`: by over ``moved_m`` and ``moved_sd`` spreads) takes the
      window's median, with the larger of its spread and 1.5 x the window's scatter, and so does
      each rigid pair the take pass reads as the person's ruler (``rigid_pairs``). CMU subject
      85's breakdance and jump + twist: the upper arm marker to the elbow 126.9 -> 104.9 mm
      (left) and 215.8 -> 198.9 mm (right), the elbow to the forearm marker 153.3 -> 174.1 and
      94.5 -> 108.4 mm (medians over each take) -- 3-4 times the calibration's spread -- while
      the breakdance model's leg and head segments moved under 5 mm.
    * **This take's motion.** The broad motion component's weights are fitted again on the
      window's confirmed labels, as :func:`calibrate` fits them on its frames
      (:func:`.body_fit.window_broad_weights`, never below the training's): the take is a held-out
      stretch of the motion to be labelled, and a new motion of the same person is as new to the
      motion mixtures as another person's.

    The other lengths, the placement of the motion means and the fit reference stay the training
    takes' (measured on operator labels). Kept when the model so measured keeps at least
    ``min_kept`` of the labels it was measured on (:func:`kept_share`, as :func:`auto_calibrate`);
    the model as it is when nothing changes.

    ``dtm-eval``'s same-person cells (a model of one take, calibrated to its person, labelling
    the other take; stream / single frames), the calibration as it was -> checked here: CMU 85
    jump + twist -> breakdance 99.33 / 95.73 -> 99.72 / 99.09 % (five segments moved: the arms'
    and the left shank marker's, 2.6 cm), breakdance -> jump + twist 99.82 / 88.72 -> 99.82 /
    89.63 % (four; the single frames still wrong are mid-jump, poses the breakdance never
    showed), subject 55's lambada -> whirl 100 / 97.62 -> 100 / 98.81 % and whirl -> lambada
    99.99 / 98.51 % as before (joint centres: nothing moved; the broad weights only). The lengths
    alone: 99.73 / 98.17, 99.82 / 89.63, 100 / 97.62, 99.99 / 98.51 %; with the placement of the
    motion means adapted on the window as well: 99.46 / 95.73, 99.82 / 92.99, 100 / 100, 99.99 /
    98.81 % (not taken: lower on the first). ``dtm-train`` then ``dtm-label`` on the C3D files:
    the breakdance's first half -> the jump + twist 99.55 -> 100 %.

    Why not the generic body self-calibrated, as for anyone else (:func:`auto_calibrate`): on
    the same cells about as good (99.44 / 97.56, 99.88 / 96.04, 100 / 99.70, 99.99 / 98.81 %),
    but it measures every length again from 5 s of the model's own labels where the person's
    were measured on operator labels: subject 55's whirl under a small model of the lambada 100
    -> 91.67 % (that self-calibration held up, keeping 92.5 % of its labels); checked here, 100 %."""
    s = settings or CalibrationSettings()
    clouds = [np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in clouds]
    clouds = [x[np.isfinite(x).all(1)] for x in clouds]
    summary = {"applied": False, "source": "session check (the take's first frames, self-labelled)",
               "frames": len(clouds)}
    if model.body is None or not model.body.calibration:
        summary["reason"] = "the model is not calibrated to a person"
        return model, summary
    if len(clouds) < s.min_frames:
        summary["reason"] = f"{len(clouds)} frames, under the {s.min_frames} a session check needs"
        return model, summary
    labeler = LabelerSettings(background=Background(volume_m3=s.volume_m3))
    budget = SearchBudget(share=s.max_search_share, total=s.search_budget * len(clouds))
    try:
        first = self_label(model, clouds, rate, labeler, s.min_confidence, progress, budget)
        b = model.body
        wrong = wrong_side(first, model.mirror_pairs, model.heading_pairs, s.min_frames)
        seg = np.flatnonzero((b.kind == SEGMENT) & (b.between_sd == 0))      # the lengths measured on the person
        rows, med, mad = moved_pairs(b.pairs[seg], b.lo[seg], b.hi[seg], b.within_sd[seg], first, s, wrong)
        rows = seg[rows]
        names = model.labels
        summary["moved"] = [f"{names[b.pairs[k, 0]]}-{names[b.pairs[k, 1]]} {1000 * b.lo[k]:.1f}"
                            + (f"-{1000 * b.hi[k]:.1f}" if b.hi[k] > b.lo[k] else "") + f" -> {1000 * m:.1f} mm"
                            for k, m in zip(rows, med)]
        session, summary["rigid_pairs_moved"] = _moved_body(model, first, rows, med, mad, wrong, s) \
            if rows.size else (model, 0)
        broad = session.broad
        if broad is not None and s.broad_min_frames > 0:       # this take's motion, as calibrate() reads it
            trained = np.asarray(model.settings.get("broad_weights_training", broad.weights), dtype=np.float64)
            w, summary["broad"] = window_broad_weights(broad, session.mixtures, model.triangles,
                                                       facing_states(first, model.heading_pairs, rate), trained,
                                                       s.broad_min_frames)
            if not np.array_equal(w, broad.weights):
                session = session.replace(broad=BroadMotion(w, broad.gaussians))
        if session is model:
            summary["reason"] = ("no segment of the person's moved on this capture and its motion asks no other "
                                 "broad weights: their calibration as it is")
            return model, summary
        kept = kept_share(first, self_label(session, clouds, rate, labeler, s.min_confidence, progress, budget))
    except CalibrationError as e:
        summary["reason"] = str(e).replace(KEPT_AS_IT_IS, SESSION_KEPT)
        return model, summary
    summary["kept_share"] = kept
    if kept < s.min_kept:
        summary["reason"] = (f"so measured, the model relabels {100 * (1 - kept):.0f} % of the labels it "
                             f"was measured on (at most {100 * (1 - s.min_kept):.0f} %): {SESSION_KEPT}")
        return model, summary
    summary["applied"] = True
    session.provenance["calibration"] = dict(model.provenance.get("calibration", {}),
                                             session={k: summary.get(k) for k in ("frames", "moved", "rigid_pairs_moved",
                                                                                   "broad", "kept_share")})
    return session, summary


def recognised_person(calibrated: TriangulatedModel, person: TriangulatedModel | None,
                      clouds: Sequence[np.ndarray] | np.ndarray, rate: float) -> tuple[TriangulatedModel, dict] | None:
    """When a take's self-calibrated model (``calibrated``) measured ``person``'s lengths
    (:func:`same_person`; module doc, *Whose body*): ``person`` checked for this session on the
    same ``clouds`` (:func:`session_calibrate`) and its summary, ``recognised`` saying so
    (``applied``: the model returned is the one to label with); else None."""
    if person is None or person.body is None or calibrated.body is None:
        return None
    agree, compared = segments_agree(calibrated.body, person.body)
    if not _one_person(agree, compared):
        return None
    out, summary = session_calibrate(person, clouds, rate)
    said = (f"the training takes' person: {agree} of {compared} segments the self-calibration measured agree "
            "with theirs")
    out = out.replace(provenance=dict(out.provenance, calibration=dict(out.provenance.get("calibration") or {},
                                                                       recognised=said, recognised_frames=len(clouds),
                                                                       moved=summary.get("moved", []))))
    return out, dict(summary, applied=True, recognised=said)


def auto_calibrate_bytes(model_bytes: bytes, clouds: Sequence[np.ndarray], rate: float,
                         person_bytes: bytes | None = None) -> tuple[bytes | None, dict]:
    """:func:`auto_calibrate` on a model file's bytes, for a process of its own (the node runs
    it away from its labelling thread): the calibrated model's file bytes (None when not
    applied) and the summary. ``person_bytes``: the model calibrated to its training takes'
    person whose generic body ``model_bytes`` is; where the take is theirs, their calibration
    checked for the session (:func:`recognised_person`)."""
    from ..model.io import model_from_bytes, model_to_bytes
    model = model_from_bytes(model_bytes)
    out, summary = auto_calibrate(model, clouds, rate)
    if summary["applied"] and person_bytes is not None:
        found = recognised_person(out, model_from_bytes(person_bytes), clouds, rate)
        if found is not None:
            out, summary = found
    return (model_to_bytes(out) if summary["applied"] else None), summary


def idle_priority(pid: int) -> None:
    """Process ``pid`` (0: this one) at idle priority: Linux ``SCHED_IDLE`` (it runs only on a
    core nothing else wants), elsewhere nice 19; silently as it is where neither is allowed."""
    import os
    try:
        os.sched_setscheduler(pid, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        try:
            os.setpriority(os.PRIO_PROCESS, pid, 19)
        except (AttributeError, OSError):
            pass


def auto_calibration_process(conn, model_bytes: bytes, clouds: Sequence[np.ndarray], rate: float,
                             person_bytes: bytes | None = None) -> None:
    """Entry point of a process of its own (``multiprocessing``, spawned; its starter sets it
    to :func:`idle_priority` right away, so that its imports run there too):
    :func:`auto_calibrate_bytes` and its result sent on ``conn`` (an error as
    ``(None, {"applied": False, "reason": ...})``)."""
    try:
        result = auto_calibrate_bytes(model_bytes, clouds, rate, person_bytes)
    except Exception as e:      # anything: the node keeps its model and says why
        result = (None, {"applied": False, "reason": f"{type(e).__name__}: {e}"})
    conn.send(result)
    conn.close()


LABEL_SOURCES = ("auto", "model", "capture")


def clip_clouds(model: TriangulatedModel, clip: MotionClip) -> np.ndarray:
    """The points the labeler would see of ``clip``, labels ignored: the model's points when
    the clip has them (or they derive from its markers), otherwise every point of the clip."""
    try:
        return model_points(clip, model.labels).positions
    except (KeyError, ValueError):
        return clip.positions


def calibrate_from_clip(model: TriangulatedModel, clip: MotionClip, labels: str = "auto",
                        settings: CalibrationSettings | None = None) -> tuple[TriangulatedModel, dict]:
    """Calibrate on the frames of ``clip``: ``labels='capture'`` uses the clip's own labels
    (an operator-labelled calibration trial), ``'model'`` labels the clip's points with the
    model and keeps the confirmed labels (:func:`self_calibrate`), ``'auto'`` takes the
    capture's labels when it has the model's points and self-labels otherwise. Returns the
    calibrated model and a summary (``source`` says which was used)."""
    if labels not in LABEL_SOURCES:
        raise CalibrationError(f"calibration labels must be one of {', '.join(LABEL_SOURCES)}")
    if labels == "auto":
        try:
            model_points(clip, model.labels)
            labels = "capture"
        except (KeyError, ValueError):
            labels = "model"
    if labels == "capture":
        out = calibrate(model, clip, settings, check_labels=False)
        out.provenance["calibration"] = dict(out.provenance["calibration"], source="capture labels")
    else:
        out, confirmed = self_calibrate(model, clip_clouds(model, clip), clip.rate, settings)
        out.provenance["calibration"]["confirmed_fraction"] = float(np.isfinite(confirmed[..., 0]).mean())
    out.provenance["calibration"]["capture"] = clip.source
    return out, dict(out.provenance["calibration"])


__all__ = ["LABEL_SOURCES", "auto_calibrate", "auto_calibrate_bytes", "auto_calibration_process", "idle_priority", "calibratable", "stream_calibration_target", "takes_calibration", "TAKES_SOURCE", "generic_view", "kept_share", "calibrate_from_clip", "calibrate_on_takes", "calibration_labeling", "confirmed_positions", "confirmation_of", "clip_clouds", "CalibrationSettings", "CalibrationError", "calibrate", "calibrated_body", "mirror_rows", "wrong_side", "self_label",
           "self_calibrate", "labelled_positions"]
