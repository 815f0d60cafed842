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
* the **reach** limits are scaled by the subject's size: the median ratio of the calibrated
  segment lengths to the generic ones (clipped to [0.75, 1.33]);
* the motion mixtures are kept (the motion is not the person's).

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
the few wrong labels, and the second round labels with the calibrated body.

Library entry points for a node service: :func:`calibrate` (labelled frames, e.g. what the
node published with high confidence) and :func:`self_calibrate` (raw clouds).
"""
from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from ..labeling.stream import LabelerSettings, StreamLabeler
from ..model.body import SEGMENT, BodyModel
from ..model.dtm import TriangulatedModel
from ..motion.clip import MotionClip
from ..motion.pointsets import model_points
from ..search.problem import Background


@dataclass(frozen=True)
class CalibrationSettings:
    min_frames: int = 10             # a pair seen together in fewer frames keeps its generic range
    max_spread_m: float = 0.02       # a segment whose length scatters more (robust sd) keeps its generic
                                     # range: its labels are not one segment (an arm labelled wrist-for-elbow)
    within_factor: float = 1.5
    scale_clip: tuple = (0.75, 1.33)
    min_confidence: float = 0.3      # self-labelling: confidence a label needs to count as confirmed
    volume_m3: float = 1000.0        # self-labelling: clutter density (larger: a point that fits the generic
                                     # body poorly is still labelled; the medians are robust to a few wrong ones)
    open_between_rel: float = 0.3    # self-labelling, first round: between-person spread of the generic body
    rounds: int = 2                  # self-calibration: label, calibrate, label again, ...


class CalibrationError(ValueError):
    """Frames that cannot calibrate the model (no body terms, too few frames, wrong points)."""


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


def calibrated_body(body: BodyModel, positions: np.ndarray, settings: CalibrationSettings | None = None
                    ) -> tuple[BodyModel, dict]:
    """The body of the person in ``positions`` (F, M, 3) (module doc); and a summary."""
    s = settings or CalibrationSettings()
    u, v = body.pairs[:, 0], body.pairs[:, 1]
    d = np.linalg.norm(positions[:, u] - positions[:, v], axis=-1)                   # (F, P)
    seen = np.isfinite(d).sum(0)
    with np.errstate(all="ignore"):
        med = np.nanmedian(np.where(np.isfinite(d), d, np.nan), axis=0)
        mad = 1.4826 * np.nanmedian(np.abs(d - med), axis=0)
    seg = (body.kind == SEGMENT) & (seen >= s.min_frames) & (np.nan_to_num(mad, nan=np.inf) <= s.max_spread_m)
    if not seg.any():
        raise CalibrationError(f"no segment seen in at least {s.min_frames} calibration frames "
                               f"({positions.shape[0]} frames given)")
    generic = 0.5 * (body.lo + body.hi)
    ratio = np.clip(np.median(med[seg] / generic[seg]), *s.scale_clip)
    lo, hi = body.lo.copy(), body.hi.copy()
    within, between = body.within_sd.copy(), body.between_sd.copy()
    lo[seg] = hi[seg] = med[seg]
    within[seg] = np.maximum(body.within_sd[seg], s.within_factor * np.nan_to_num(mad[seg]))
    between[seg] = 0.0
    reach = body.kind != SEGMENT
    hi[reach] = body.hi[reach] * ratio
    between[reach] = 0.0
    summary = {"frames": int(positions.shape[0]), "segments": int(seg.sum()),
               "segments_total": int((body.kind == SEGMENT).sum()), "scale": float(ratio),
               "median_change_m": float(np.median(np.abs(med[seg] - generic[seg]))),
               "calibrated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
    return replace(body, lo=lo, hi=hi, within_sd=within, between_sd=between, calibration=summary), summary


def calibrate(model: TriangulatedModel, source: MotionClip | np.ndarray,
              settings: CalibrationSettings | None = None) -> TriangulatedModel:
    """``model`` with the body terms of the person in ``source``: a labelled clip (the
    model's labels or points derivable from it) or (F, M, 3) positions in the model's label
    order (NaN = unseen). The model's own settings, structure and mixtures are kept."""
    if model.body is None:
        raise CalibrationError("the model has no body terms to calibrate (format version 1 or trained "
                               "without them); retrain with dtm-train")
    P = labelled_positions(model, source)
    body, summary = calibrated_body(model.body, P, settings)
    return model.replace(body=body, provenance=dict(model.provenance, calibration=summary))


def confirmed_positions(labels: np.ndarray, confidence: np.ndarray, xyz: np.ndarray, n_labels: int,
                        min_confidence: float = 0.3) -> np.ndarray:
    """(M, 3) positions of one labelled frame in label order: the points labelled with at least
    ``min_confidence`` (NaN for the other labels) -- what a calibration takes as confirmed."""
    out = np.full((n_labels, 3), np.nan)
    ok = (np.asarray(labels) >= 0) & (np.asarray(confidence) >= min_confidence)
    out[np.asarray(labels)[ok]] = np.asarray(xyz, dtype=np.float64)[ok]
    return out


def self_label(model: TriangulatedModel, clouds: Sequence[np.ndarray] | np.ndarray, rate: float,
               settings: LabelerSettings | None = None, min_confidence: float = 0.3) -> np.ndarray:
    """Label unlabelled clouds (one (n, 3) array per frame, or (F, N, 3)) with ``model`` in
    stream mode and return the confirmed labels as (F, M, 3) positions (NaN where a label
    was not given with at least ``min_confidence``)."""
    lab = StreamLabeler(model, settings or LabelerSettings())
    out = np.full((len(clouds), model.n_labels, 3), np.nan)
    for f, xyz in enumerate(clouds):
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        xyz = xyz[np.isfinite(xyz).all(1)]
        res = lab.process(xyz, f / rate)
        out[f] = confirmed_positions(res.labels, res.confidence, xyz, model.n_labels, min_confidence)
    return out


def self_calibrate(model: TriangulatedModel, clouds: Sequence[np.ndarray] | np.ndarray, rate: float,
                   settings: CalibrationSettings | None = None,
                   labeler: LabelerSettings | None = None) -> tuple[TriangulatedModel, np.ndarray]:
    """Calibrate on unlabelled clouds: label them with the model (:func:`self_label`),
    calibrate on the confirmed labels, and repeat with the calibrated model (``rounds``).
    Returns the calibrated model and the last confirmed labels (F, M, 3)."""
    s = settings or CalibrationSettings()
    current = model
    P = None
    labeler = labeler or LabelerSettings(background=Background(volume_m3=s.volume_m3))
    if model.body is not None:               # first round: a body open to other people's proportions
        b = model.body
        wide = np.maximum(b.between_sd, s.open_between_rel * 0.5 * (b.lo + b.hi))
        current = model.replace(body=replace(b, between_sd=wide))
    for _ in range(max(1, s.rounds)):
        P = self_label(current, clouds, rate, labeler, s.min_confidence)
        current = calibrate(model, P, s)
    current.provenance["calibration"] = dict(current.provenance["calibration"], source="self-labelled",
                                             rounds=max(1, s.rounds))
    return current, P


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
        out = calibrate(model, clip, settings)
        out.provenance["calibration"] = dict(out.provenance["calibration"], source="capture labels")
    else:
        out, confirmed = self_calibrate(model, clip_clouds(model, clip), clip.rate, settings)
        out.provenance["calibration"]["confirmed_fraction"] = float(np.isfinite(confirmed[..., 0]).mean())
    out.provenance["calibration"]["capture"] = clip.source
    return out, dict(out.provenance["calibration"])


__all__ = ["LABEL_SOURCES", "calibrate_from_clip", "confirmed_positions", "clip_clouds", "CalibrationSettings", "CalibrationError", "calibrate", "calibrated_body", "self_label",
           "self_calibrate", "labelled_positions"]
