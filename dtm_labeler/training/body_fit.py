"""Fitting the body terms and the broad motion components (see :mod:`dtm_labeler.model.body`).

Body terms from labelled clips
    Per label pair and per clip: the mean distance, its standard deviation within the clip,
    its largest value and the spread of the pair's difference vector (at most ``max_frames``
    frames per clip). A pair is a **segment** when its distance hardly varies in *every* clip
    (within-clip sd at most ``segment_abs_m``: bones 0, marker clusters on one segment a few
    mm of skin motion) *although its direction does*: the largest within-clip distance sd is
    at most ``segment_ratio`` times the largest spread of the difference vector. Without the
    second test two points that a recording merely never moved apart (head and knees in an
    upright dance, the trunk in a walk) would pass for one segment and veto the next motion
    that bends them. A segment's allowed range is the range of its clip
    means (each clip one person, or one marker placement), its within-person spread the
    largest within-clip sd times ``within_factor`` (floored at ``within_floor_m``), and its
    between-person spread ``between_rel`` of its length (for a person outside the range).
    Every other pair gets a **reach limit**: the path length between the two points along the
    most rigid tree (:func:`dtm_labeler.training.train.rigid_tree`), each link taken at its
    longest, so only anatomically impossible distances cost anything.

Broad components by EM on held-out frames
    The last ``validation_fraction`` of every clip is held out (contiguous: other moves of the
    same take), the mixtures are fitted to the rest, and for each triangle the weight ``w`` of
    a component ``N(mu, s^2 Sigma)`` (moment-matched to the fitted part) is found by EM on the
    held-out features -- ``r_i = w q_i / ((1 - w) p_i + w q_i)``, ``w = mean r_i`` -- for each
    scale ``s`` of a grid, keeping the ``(w, s)`` of the highest held-out likelihood. ``w`` is
    kept in ``[min_weight, max_weight]`` so that even a take whose held-out part shows nothing
    new (a steady walk) leaves unseen poses a tail. The model's own mixtures (fitted to all
    frames) then get that component (:func:`dtm_labeler.model.body.with_broad_component`).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import shortest_path

from ..model.body import REACH, SEGMENT, BodyModel, with_broad_component
from ..model.features import FULL, triangle_features
from ..model.mixture import GaussianMixture, logsumexp_rows
from ..model.structure import Structure
from ..motion.clip import MotionClip


@dataclass(frozen=True)
class BodySettings:
    """How body terms and broad components are fitted (module doc)."""

    segment_abs_m: float = 0.008
    segment_ratio: float = 0.05
    within_factor: float = 1.5
    within_floor_m: float = 0.005
    between_rel: float = 0.15
    reach_sd_m: float = 0.03
    max_frames: int = 3000
    validation_fraction: float = 0.2
    min_weight: float = 0.1
    max_weight: float = 0.5
    scales: tuple = (2.0, 3.0, 4.0)
    em_iterations: int = 50

    def check(self) -> None:
        if not 0.0 < self.validation_fraction < 0.5:
            raise ValueError("validation fraction must be in (0, 0.5)")
        if not 0.0 < self.min_weight <= self.max_weight < 1.0:
            raise ValueError("need 0 < min_weight <= max_weight < 1")
        if self.between_rel < 0 or self.within_floor_m <= 0 or self.reach_sd_m <= 0:
            raise ValueError("body spreads must be positive")


def pair_statistics(clips: Sequence[MotionClip], max_frames: int = 3000) -> dict[str, np.ndarray]:
    """Per clip (C, M, M): mean, within-clip sd and largest distance of every label pair and
    the spread (root of the summed variances) of its difference vector; NaN where a pair is
    never seen together in a clip."""
    means, sds, maxs, vecs = [], [], [], []
    for c in clips:
        P = c.positions[np.linspace(0, c.n_frames - 1, min(c.n_frames, max_frames)).astype(np.int64)]
        v = P[:, :, None, :] - P[:, None, :, :]
        d = np.linalg.norm(v, axis=-1)                                                  # (F, M, M)
        with np.errstate(invalid="ignore", all="ignore"):
            seen = np.isfinite(d).sum(0)
            mu = np.nanmean(np.where(seen >= 2, d, np.nan), axis=0) if d.shape[0] else d[0]
            means.append(np.where(seen >= 2, mu, np.nan))
            sds.append(np.where(seen >= 2, np.nanstd(d, axis=0), np.nan))
            maxs.append(np.where(seen >= 2, np.nanmax(np.where(np.isfinite(d), d, -np.inf), axis=0), np.nan))
            vecs.append(np.where(seen >= 2, np.sqrt(np.nanvar(v, axis=0).sum(-1)), np.nan))
    return {"mean": np.stack(means), "sd": np.stack(sds), "max": np.stack(maxs), "vec": np.stack(vecs)}


def reach_limits(longest: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(M, M) path length between every two points along the tree ``parents`` with each link
    (point, parent) at its ``longest`` distance: no pose puts them farther apart."""
    M = parents.size
    child = np.flatnonzero(parents >= 0)
    w = np.maximum(longest[child, parents[child]], 1e-6)
    graph = coo_matrix((w, (child, parents[child])), shape=(M, M))
    return shortest_path(graph, directed=False)


def fit_body(clips: Sequence[MotionClip], parents: np.ndarray, settings: BodySettings | None = None) -> BodyModel:
    """The generic body of ``clips`` (all with the same point names): segments, ranges,
    spreads and reach limits (module doc)."""
    s = settings or BodySettings()
    st = pair_statistics(clips, s.max_frames)
    M = clips[0].n_points
    with np.errstate(invalid="ignore", all="ignore"):
        length = np.nanmean(st["mean"], axis=0)
        sd_max = np.nanmax(st["sd"], axis=0)
        vec_max = np.nanmax(st["vec"], axis=0)
        lo, hi = np.nanmin(st["mean"], axis=0), np.nanmax(st["mean"], axis=0)
        longest = np.nanmax(st["max"], axis=0)
    iu, ju = np.triu_indices(M, 1)
    seen = np.isfinite(length[iu, ju]) & np.isfinite(sd_max[iu, ju])
    sd_p = sd_max[iu, ju]
    seg = seen & (sd_p <= s.segment_abs_m) & (sd_p <= s.segment_ratio * np.nan_to_num(vec_max[iu, ju]))
    longest = np.where(np.isfinite(longest), longest, 0.0)
    reach = reach_limits(longest, parents)
    kind = np.where(seg, SEGMENT, REACH)
    L = np.where(seg, length[iu, ju], reach[iu, ju])
    pair_lo = np.where(seg, lo[iu, ju], 0.0)
    pair_hi = np.where(seg, hi[iu, ju], reach[iu, ju])
    within = np.where(seg, np.maximum(s.within_factor * np.nan_to_num(sd_p), s.within_floor_m),
                      s.reach_sd_m)
    between = s.between_rel * L
    keep = seen | ~seg
    return BodyModel(n_labels=M, pairs=np.stack([iu, ju], 1)[keep], kind=kind[keep], lo=pair_lo[keep],
                     hi=pair_hi[keep], within_sd=within[keep], between_sd=between[keep])


# -- broad components ---------------------------------------------------------------------------
def validation_rows(clip_frames: Sequence[int], copies: int, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Row masks over the recorded frames (``clip_frames`` per clip, concatenated) and over
    the training rows (the recorded frames then ``copies`` augmented copies of them, as
    :func:`dtm_labeler.training.train.training_states` stacks them): held out = the last
    ``fraction`` of every clip (and every copy of those frames)."""
    held = np.concatenate([np.arange(n) >= n - max(1, int(round(fraction * n))) for n in clip_frames])
    return held, np.tile(held, copies + 1)


def broad_weight(log_p: np.ndarray, log_q: np.ndarray, w0: float, iterations: int,
                 bounds: tuple[float, float]) -> tuple[float, float]:
    """EM for the weight of the broad density ``q`` beside the mixture ``p`` on held-out rows:
    returns ``(w, total log-likelihood)``, ``w`` clipped to ``bounds``."""
    w = w0
    stack = np.stack([log_p, log_q], 1)
    for _ in range(iterations):
        lw = stack + np.log([1.0 - w, w])
        r = np.exp(lw[:, 1] - logsumexp_rows(lw))
        w = float(np.clip(r.mean(), *bounds))
    return w, float(logsumexp_rows(stack + np.log([1.0 - w, w])).sum())


def moments(X: np.ndarray, floor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance (plus the diagonal ``floor``) of feature rows."""
    return X.mean(0), np.cov(X, rowvar=False, bias=True) + np.diag(floor)


def add_broad_components(mixtures: list[GaussianMixture], structure: Structure, train_states: np.ndarray,
                         train_codes: np.ndarray, held_rows: np.ndarray, recorded: np.ndarray,
                         fit: Callable[[np.ndarray, int], GaussianMixture], floor: np.ndarray,
                         settings: BodySettings | None = None,
                         progress: Callable[[int, int], None] | None = None) -> tuple[list[GaussianMixture], dict]:
    """``mixtures`` each with its broad component fitted on held-out frames (module doc).

    ``train_states`` / ``train_codes``: the rows the mixtures were fitted to; ``held_rows``
    marks those held out for the fit of ``(w, s)``, ``recorded`` those that are recorded
    (not augmented) -- the held-out likelihood is measured on recorded frames only.
    ``fit(X, t)`` fits triangle ``t``'s mixture (floored) to feature rows ``X``."""
    s = settings or BodySettings()
    out, weights, scales = [], [], []
    for t, tri in enumerate(structure.triangles):
        if progress:
            progress(t, structure.n_triangles)
        ok = (train_codes[:, list(tri)] == FULL).all(axis=1)
        X_fit = triangle_features(train_states[ok & ~held_rows], tri)
        X_val = triangle_features(train_states[ok & held_rows & recorded], tri)
        X_all = triangle_features(train_states[ok], tri)
        w, scale = s.min_weight, 3.0
        if X_fit.shape[0] >= 20 and X_val.shape[0] >= 10:
            part = fit(X_fit, t)
            mu, cov = moments(X_fit, floor)
            log_p = part.log_pdf(X_val)
            best = -np.inf
            for sc in s.scales:
                log_q = GaussianMixture(np.ones(1), mu[None], (sc ** 2 * cov)[None]).log_pdf(X_val)
                wt, ll = broad_weight(log_p, log_q, 0.1, s.em_iterations, (s.min_weight, s.max_weight))
                if ll > best:
                    best, w, scale = ll, wt, sc
        mu, cov = moments(X_all, floor)
        out.append(with_broad_component(mixtures[t], w, scale, mu, cov))
        weights.append(w)
        scales.append(scale)
    if progress:
        progress(structure.n_triangles, structure.n_triangles)
    return out, {"weights": weights, "scales": scales, "settings": dict(asdict(s), scales=list(s.scales))}
