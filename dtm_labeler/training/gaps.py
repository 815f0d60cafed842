"""Training on gappy captures: coverage, structure scores and triangle mixtures from partly seen frames.

Real takes (ROM, calibration, any long capture) have gaps; with 40 markers hardly a frame
shows all of them. Training uses what every frame shows:

* **coverage** (:func:`coverage_report`): per marker, the fraction of frames where it is seen
  with a velocity; a marker under :data:`MIN_COVERAGE` (or :data:`MIN_SEEN_FRAMES` frames) is
  refused with a message naming it -- a model cannot place a point it has hardly seen;
* **structure scores** (:func:`structure_scores`): when fewer than
  :data:`COMPLETE_ENOUGH` of the frames are complete, the joint covariance of the point
  states is assembled from pairs of points over the frames that show both (pairwise
  deletion), projected onto the nearest positive semi-definite matrix, and every triple is
  scored from it (:meth:`~dtm_labeler.search.structure_search.TripleScores.from_covariance`);
  triples whose three points are seen together in fewer than :data:`MIN_TRIPLE_FRAMES`
  frames are never chosen. Gap-free takes keep the complete-frame scores exactly as before;
* **triangle mixtures** (:func:`fit_triangle`): when more than :data:`PARTIAL_SHARE` of the
  frames that show something of a triangle show it only partly, the mixture is fitted by
  EM with missing data (:mod:`dtm_labeler.model.mixture_missing`); otherwise on the fully
  seen frames as before. A chosen triangle needs :data:`MIN_TRIANGLE_FRAMES` frames showing
  all three points (the joint spread of the three is learnt from those);
* **heading** (:func:`fill_yaw`): frames where no left/right pair is seen take the facing
  interpolated from the neighbouring frames of the take.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..model.features import STATE_DIM, canonicalise, lateral_yaw, point_states, triangle_features
from ..model.mixture_em import FitResult, make_estimator
from ..model.mixture_missing import PartialSamples, make_partial_estimator
from ..model.structure import Structure
from ..search import structure_search as ss
from ..search.structure_search import TripleScores

MIN_COVERAGE = 0.05          # a marker seen in fewer frames than this cannot be learnt
MIN_SEEN_FRAMES = 20
COMPLETE_ENOUGH = 0.9        # complete frames for the complete-frame structure scores
MIN_TRIPLE_FRAMES = 15       # recorded frames showing all three points of a triple the structure may use
PARTIAL_SHARE = 0.05         # partly seen share of a triangle's frames that switches to EM with missing data
MIN_TRIANGLE_FRAMES = 20
PARTIAL_TOL = 1e-3           # EM with missing data creeps: stop at 0.1 % change of the objective per sweep
                             # (measured on HDM05 triangles at 50 % gaps: the held-out likelihood of 1e-5
                             # within 0.1 nats, 3-7x fewer sweeps)


class RarelySeen(ValueError):
    """A take shows some markers too rarely to learn them (:meth:`Coverage.check`); ``names``
    are those markers, what ``--points all,-NAME,...`` leaves out."""

    def __init__(self, message: str, names: Sequence[str]):
        super().__init__(message)
        self.names = tuple(names)


@dataclass
class Coverage:
    """Per marker: frames seen (position and velocity) and the share of all frames."""

    labels: list[str]
    seen: np.ndarray
    frames: int

    @property
    def fraction(self) -> np.ndarray:
        return self.seen / max(self.frames, 1)

    def as_dict(self) -> dict[str, float]:
        return {n: round(float(f), 4) for n, f in zip(self.labels, self.fraction)}

    def check(self, min_fraction: float = MIN_COVERAGE, min_frames: int = MIN_SEEN_FRAMES) -> None:
        """:class:`RarelySeen` naming every marker seen too rarely to learn."""
        bad = [i for i in range(len(self.labels)) if self.fraction[i] < min_fraction or self.seen[i] < min_frames]
        if bad:
            what = ", ".join(f"{self.labels[i]} ({int(self.seen[i])} of {self.frames} frames, "
                             f"{100 * self.fraction[i]:.1f} %)" for i in bad[:6])
            leave = ",".join(f"-{self.labels[i]}" for i in bad)
            raise RarelySeen(f"almost never seen: {what}{' ...' if len(bad) > 6 else ''}; a model cannot learn "
                             f"where a marker goes from fewer than {100 * min_fraction:g} % of the frames or "
                             f"{min_frames} frames: leave {'it' if len(bad) == 1 else 'them'} out (--points "
                             f"all,{leave}) or add takes where {'it is' if len(bad) == 1 else 'they are'} seen",
                             [self.labels[i] for i in bad])


def coverage_report(states: np.ndarray, labels: Sequence[str]) -> Coverage:
    """:class:`Coverage` of (F, n, 6) point states."""
    seen = np.isfinite(states).all(-1)
    return Coverage(list(labels), seen.sum(0), states.shape[0])


def fill_yaw(yaw: np.ndarray) -> np.ndarray:
    """Facing angles with the NaN frames filled by interpolating the unwrapped angle of the
    nearest seen frames (ends: held); all NaN stays NaN."""
    yaw = np.asarray(yaw, dtype=np.float64)
    ok = np.isfinite(yaw)
    if ok.all() or not ok.any():
        return yaw
    t = np.arange(yaw.size)
    return np.interp(t, t[ok], np.unwrap(yaw[ok]))


def facing_states(positions: np.ndarray, pairs: np.ndarray, rate: float) -> np.ndarray:
    """(F, N, 6) point states of labelled frames (F, N, 3) at ``rate``, each frame turned so
    the body faces +x (eq. 12's frame; the facing from the left/right ``pairs``, frames
    without one interpolated, :func:`fill_yaw`)."""
    P = np.asarray(positions, dtype=np.float64)
    return canonicalise(point_states(P, rate), fill_yaw(lateral_yaw(P, pairs)))


def pairwise_covariance(states: np.ndarray) -> np.ndarray:
    """The (n*6, n*6) covariance of the stacked point states, each block from the frames that
    show both of its points (each with its own means over those frames), projected onto the
    nearest positive semi-definite matrix."""
    F, n, _ = states.shape
    seen = np.isfinite(states).all(-1).astype(np.float64)                 # (F, n)
    X = np.nan_to_num(states, nan=0.0).reshape(F, n * STATE_DIM)
    m = np.repeat(seen, STATE_DIM, axis=1)                                # (F, n*6)
    Xm = X * m
    count = m.T @ m                                                       # frames showing both coordinates
    safe = np.maximum(count, 1.0)
    s1 = Xm.T @ m                                                         # (i, j): sum of x_i where j is seen too
    S = (Xm.T @ Xm) / safe - (s1 / safe) * (s1.T / safe)
    S = 0.5 * (S + S.T)
    w, V = np.linalg.eigh(S)
    return (V * np.maximum(w, 0.0)) @ V.T


def shared_frames(states: np.ndarray) -> np.ndarray:
    """(n, n, n) frames showing all three points (position and velocity) of every triple."""
    seen = np.isfinite(states).all(-1).astype(np.float64)                 # (F, n)
    return np.einsum("fa,fb,fc->abc", seen, seen, seen, optimize=True)


def structure_scores(states: np.ndarray, reg_covar: float) -> tuple[TripleScores | None, str]:
    """``(scores, how)`` for the structure search of (F, n, 6) canonical states: complete
    frames when there are enough of them (``how`` = 'complete frames'), pairwise otherwise;
    None when no frame is complete and the take is too short to score pairs."""
    complete = np.isfinite(states).all(-1).all(-1)
    F = states.shape[0]
    if complete.sum() >= 2 and complete.mean() >= COMPLETE_ENOUGH:
        return TripleScores.from_states(states[complete], reg_covar), "complete frames"
    if F < MIN_TRIPLE_FRAMES:
        return None, ""
    usable = shared_frames(states) >= MIN_TRIPLE_FRAMES
    return TripleScores.from_covariance(pairwise_covariance(states), F, reg_covar, usable), "pairs of points"


def unattachable(scores: TripleScores, labels: Sequence[str]) -> list[str]:
    """Labels no usable triple holds (the structure search cannot place them)."""
    if scores.usable is None:
        return []
    return [labels[i] for i in np.flatnonzero(~scores.usable.any(axis=(1, 2)))]


def usable_structure(scores: TripleScores, structure: Structure, n: int, root_pairs, labels: Sequence[str],
                     keep: bool = False) -> Structure:
    """On gappy scores: the better of ``structure`` (the GA's) and the greedy one, which is
    built from usable triples only; ValueError naming the triangles when neither avoids
    triples the frames hardly show. Complete-frame scores: ``structure`` unchanged.
    ``keep``: ``structure`` is chosen for what it holds rather than for its score (the one
    grown along the rigid tree, ``--structure body``): the greedy one only replaces it when
    it needs triples the frames hardly show."""
    if scores.usable is None:
        return structure
    best = structure
    if not keep or scores.unusable_in(structure):
        try:
            greedy = ss.greedy(scores, n, root_pairs).structure
        except ValueError:
            greedy = None
        if greedy is not None and not scores.unusable_in(greedy):
            f_greedy, f_given = scores.score(np.stack([greedy.array, structure.array]))
            if keep or f_greedy > f_given:
                best = greedy
    bad = scores.unusable_in(best)
    if bad:
        raise ValueError("the structure needs triangles whose points are seen together in fewer than "
                         f"{MIN_TRIPLE_FRAMES} frames: " + ", ".join("(" + ",".join(labels[v] for v in t) + ")"
                                                                   for t in bad[:4])
                         + "; add takes or leave the rarest markers out")
    return best


def fit_rows(X: np.ndarray, config, rng: np.random.Generator, seed: int) -> FitResult:
    """A triangle's mixture (``config.mixture``) on eq. 12 feature rows ``X``, at most
    ``max_frames_per_triangle`` of them, drawn with ``rng``."""
    if X.shape[0] > config.max_frames_per_triangle:
        X = X[np.sort(rng.choice(X.shape[0], config.max_frames_per_triangle, replace=False))]
    return make_estimator(config.mixture, k_fixed=config.k_fixed, k_min=config.k_min, k_max=config.k_max,
                          reg_covar=config.reg_covar, removal=config.mdl_removal, random_state=seed).fit(X)


def fit_triangle(train_states: np.ndarray, tri: Sequence[int], config, rng: np.random.Generator, seed: int,
                 labels: Sequence[str]) -> FitResult:
    """One triangle's mixture: on its fully seen frames (as always), or by EM with missing data
    when a real share of its frames shows it only partly (module doc)."""
    tri = list(tri)
    seen = np.isfinite(train_states[:, tri]).all(-1)                       # (F, 3) position and velocity
    pos = np.isfinite(train_states[:, tri, :3]).all(-1)
    full = seen.all(1)
    partial = ~full & ((pos.sum(1) >= 2) | seen.any(1))                      # something of its shape or motion
    kw = dict(k_fixed=config.k_fixed, k_min=config.k_min, k_max=config.k_max, reg_covar=config.reg_covar,
              removal=config.mdl_removal, random_state=seed)
    names = [labels[v] for v in tri]
    if full.sum() < MIN_TRIANGLE_FRAMES:
        raise ValueError(f"triangle {names} has only {int(full.sum())} usable frames (all three points seen)")
    if partial.sum() <= PARTIAL_SHARE * (partial.sum() + full.sum()):
        return fit_rows(triangle_features(train_states[full], tri), config, rng, seed)
    data = PartialSamples.from_states(train_states[full | partial], tri)
    if data.n > config.max_frames_per_triangle:
        data = data.take(np.sort(rng.choice(data.n, config.max_frames_per_triangle, replace=False)))
    return make_partial_estimator(config.mixture, tol=PARTIAL_TOL, **kw).fit_partial(data)


def loglik_per_label(model, states: np.ndarray) -> float:
    """The typical model log-likelihood per seen label of the training frames (the stream
    labeler's starting level): the median of log P / seen labels over frames showing at
    least half the labels with velocities."""
    seen = np.isfinite(states).all(-1)
    use = seen.sum(1) >= max(3, seen.shape[1] // 2)
    if not use.any():
        return 0.0
    ll = model.frame_log_likelihood(states[use])
    return float(np.median(ll / seen[use].sum(1)))
