"""Offline training: labelled clips -> canonical point states -> structure -> mixtures -> model.

Pipeline (section III and IV.A):

1. per clip, point states (positions, backward-difference velocities in m/s) and the
   per-frame heading from the labelled left/right pairs; states rotated to face +x
   (see :mod:`features` for why invariant features rather than augmentation);
2. structure: hand-given, greedy (Song et al.), CBGA or simple GA over the fully observed
   frames, scored with per-triple Gaussians (:mod:`dtm_labeler.search.structure_search`);
3. one mixture per triangle of the chosen structure over the eq. 12 feature, from every
   frame where that triangle's three points have positions and velocities: single
   Gaussian, fixed K, or EM with the MDL rule (eq. 8-11).
"""
from __future__ import annotations

import datetime as _dt
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence

import numpy as np

from .. import __version__
from ..motion.clip import MotionClip
from .dtm import TriangulatedModel
from .features import (FULL, canonicalise, lateral_yaw, observation_state, point_states,
                       triangle_features)
from ..motion.pointsets import left_right_pairs
from .mixture import GaussianMixture
from .mixture_em import make_estimator
from .structure import BODY14_GIVEN, Structure

STRUCTURE_METHODS = ("cbga", "greedy", "given", "sga")
MIXTURE_KINDS = ("mdl", "fixed", "single")


@dataclass
class TrainConfig:
    mixture: str = "mdl"
    k_min: int = 1
    k_max: int = 8
    k_fixed: int = 3
    structure: str = "cbga"
    seed: int = 0
    reg_covar: float = 1e-6
    max_frames_per_triangle: int = 4000
    structure_population: int = 60
    structure_generations: int = 200
    heading_bins: int = 720
    yaw_jitter_deg: float = 4.0
    mdl_removal: str = "least_loss"     # F&J remove the least probable; least_loss keeps small real clusters
    position_floor_m: float = 0.02
    velocity_floor_mps: float = 0.2
    augment_copies: int = 1
    given_structure: Sequence[Sequence[str]] | None = None

    def check(self) -> None:
        if self.mixture not in MIXTURE_KINDS:
            raise ValueError(f"--mixture must be one of {', '.join(MIXTURE_KINDS)}")
        if self.structure not in STRUCTURE_METHODS:
            raise ValueError(f"--structure must be one of {', '.join(STRUCTURE_METHODS)}")
        if not 1 <= self.k_min <= self.k_max:
            raise ValueError("need 1 <= k_min <= k_max")
        if self.k_fixed < 1:
            raise ValueError("k_fixed must be >= 1")


@dataclass
class TrainSummary:
    labels: list[str]
    frames_total: int
    frames_complete: int
    structure: list[list[str]]
    structure_method: str
    structure_loglik_per_frame: float
    components: list[int]
    loglik_per_frame: float
    message_length: list[float]
    seconds: float
    sources: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        return asdict(self)


def heading_pairs(labels: Sequence[str]) -> np.ndarray:
    """(Q, 2) index pairs (left, right) found by name."""
    idx = {n: i for i, n in enumerate(labels)}
    return np.array([(idx[a], idx[b]) for a, b in left_right_pairs(labels)], dtype=np.int64).reshape(-1, 2)


def stable_heading_pairs(clips: Sequence[MotionClip], pairs: np.ndarray, max_rms_deg: float = 20.0,
                         keep_at_least: int = 2) -> np.ndarray:
    """The left/right pairs whose lateral direction follows the body's.

    Swinging limbs (wrists, ankles) turn their left-right vector far from the trunk's; using
    them for the heading adds noise the sharp triangle densities punish. For every pair, the
    RMS angle between its lateral vector and the consensus of all pairs is measured over the
    training frames; pairs under ``max_rms_deg`` are kept (at least the ``keep_at_least``
    best, typically shoulders and hips).
    """
    if len(pairs) <= keep_at_least:
        return pairs
    rms = []
    cons = np.concatenate([lateral_yaw(c.positions, pairs) for c in clips])
    for q in pairs:
        own = np.concatenate([lateral_yaw(c.positions, q[None]) for c in clips])
        d = np.angle(np.exp(1j * (own - cons)))
        d = d[np.isfinite(d)]
        rms.append(np.sqrt(np.mean(d ** 2)) if d.size else np.inf)
    rms = np.degrees(np.array(rms))
    keep = rms < max_rms_deg
    keep[np.argsort(rms)[:keep_at_least]] = True
    return pairs[keep]


def canonical_states(clip: MotionClip, pairs: np.ndarray, jitter_deg: float = 0.0,
                     rng: np.random.Generator | None = None) -> np.ndarray:
    """(F, N, 6) point states of ``clip`` rotated so each frame's body faces +x.

    ``jitter_deg`` adds a uniform random yaw error in [-jitter, +jitter] per frame: a small
    augmentation that keeps the model tolerant to heading noise (marker placement, twist)
    without smearing it over all headings.
    """
    states = point_states(clip.positions, clip.rate)
    yaw = lateral_yaw(clip.positions, pairs)
    if jitter_deg > 0:
        rng = rng or np.random.default_rng(0)
        yaw = yaw + np.radians(rng.uniform(-jitter_deg, jitter_deg, size=yaw.shape))
    return canonicalise(states, yaw)


def floor_covariances(mix: GaussianMixture, position_m: float, velocity_mps: float) -> GaussianMixture:
    """Add independent noise of ``position_m`` / ``velocity_mps`` (std) to every component.

    The ML covariances of a few hundred frames are far sharper than the spread between
    subjects, sessions and marker placements; a floor equal to that spread (convolving the
    mixture with N(0, diag(floor^2))) is what keeps the model useful on people it never saw.
    Feature order as eq. 12: nine velocity dimensions, then six relative positions.
    """
    if position_m <= 0 and velocity_mps <= 0:
        return mix
    floor = np.r_[np.full(9, velocity_mps ** 2), np.full(6, position_m ** 2)]
    return GaussianMixture(np.asarray(mix.weights), np.asarray(mix.means),
                           np.asarray(mix.covariances) + np.diag(floor))


def train_model(clips: Sequence[MotionClip], config: TrainConfig | None = None,
                progress: Callable[[str, int, int], None] | None = None) -> tuple[TriangulatedModel, TrainSummary]:
    """Train a :class:`TriangulatedModel` on clips that share the same point names."""
    config = config or TrainConfig()
    config.check()
    t0 = time.perf_counter()
    if not clips:
        raise ValueError("no training clips")
    labels = list(clips[0].names)
    for c in clips[1:]:
        if list(c.names) != labels:
            raise ValueError(f"{c.source}: point names differ from {clips[0].source}; "
                             "select one point set for all clips")
    if len(labels) < 3:
        raise ValueError("a triangulated model needs at least 3 points")
    all_pairs = heading_pairs(labels)
    pairs = stable_heading_pairs(clips, all_pairs)
    states = np.concatenate([canonical_states(c, pairs) for c in clips], axis=0)
    codes = observation_state(states)
    complete = (codes == FULL).all(axis=1)
    jrng = np.random.default_rng(config.seed + 7919)
    train_states = np.concatenate([states] + [
        np.concatenate([canonical_states(c, pairs, config.yaw_jitter_deg, jrng) for c in clips], axis=0)
        for _ in range(config.augment_copies)], axis=0) if config.yaw_jitter_deg > 0 else states
    train_codes = observation_state(train_states)
    n = len(labels)
    step = lambda msg, i, k: progress(msg, i, k) if progress else None  # noqa: E731

    # -- structure --------------------------------------------------------------------
    from ..search import structure_search as ss
    step("structure", 0, 1)
    scores = ss.TripleScores.from_states(states[complete], config.reg_covar) if complete.sum() >= 2 else None
    if config.structure == "given":
        given = config.given_structure or (BODY14_GIVEN if set(labels) == {x for t in BODY14_GIVEN for x in t}
                                           else None)
        if given is None:
            raise ValueError("--structure given needs a hand structure; the built-in one covers the "
                             "14 body points only")
        structure = Structure.from_names(given, labels)
    else:
        if scores is None:
            raise ValueError("structure search needs frames where every point is seen")
        kw = dict(population=config.structure_population, generations=config.structure_generations,
                  seed=config.seed, root_pairs=pairs if len(pairs) else None)
        if config.structure == "greedy":
            structure = ss.greedy(scores, n, kw["root_pairs"]).structure
        elif config.structure == "cbga":
            res = ss.cbga(scores, n, **kw)
            structure = ss.refine(scores, res, n, np.random.default_rng(config.seed), kw["root_pairs"]).structure
        else:
            structure = ss.simple_ga(scores, n, **kw).structure
    struct_ll = scores.per_frame(structure) if scores is not None else float("nan")
    step("structure", 1, 1)

    # -- mixtures per triangle ------------------------------------------------------------
    rng = np.random.default_rng(config.seed)
    mixtures, lengths = [], []
    for t, tri in enumerate(structure.triangles):
        step("mixtures", t, structure.n_triangles)
        ok = (train_codes[:, list(tri)] == FULL).all(axis=1)
        X = triangle_features(train_states[ok], tri)
        if X.shape[0] < 20:
            raise ValueError(f"triangle {[labels[v] for v in tri]} has only {X.shape[0]} usable frames")
        if X.shape[0] > config.max_frames_per_triangle:
            X = X[np.sort(rng.choice(X.shape[0], config.max_frames_per_triangle, replace=False))]
        est = make_estimator(config.mixture, k_fixed=config.k_fixed, k_min=config.k_min,
                             k_max=config.k_max, reg_covar=config.reg_covar, removal=config.mdl_removal,
                             random_state=config.seed + t)
        fit = est.fit(X)
        mixtures.append(floor_covariances(fit.mixture, config.position_floor_m, config.velocity_floor_mps))
        lengths.append(float(fit.message_length))
    step("mixtures", structure.n_triangles, structure.n_triangles)

    model = TriangulatedModel(
        labels=tuple(labels), structure=structure, mixtures=mixtures, heading_pairs=pairs,
        mirror_pairs=all_pairs,
        settings={"heading_bins": config.heading_bins, "feature": "eq12, yaw-canonical (lateral pairs)",
                  "velocity": "backward difference, m/s"},
        provenance={"trained": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                    "dtm_labeler": __version__, "config": {k: v for k, v in asdict(config).items()
                                                           if k != "given_structure"},
                    "sources": [c.source for c in clips], "frames": int(states.shape[0]),
                    "rates_hz": sorted({float(c.rate) for c in clips})})
    ll = model.frame_log_likelihood(states[complete]) if complete.any() else np.array([np.nan])
    # the typical model log-likelihood per labelled point: the stream labeler's starting level
    model.settings["loglik_per_label"] = float(np.median(ll) / len(labels)) if complete.any() else 0.0
    summary = TrainSummary(
        labels=labels, frames_total=int(states.shape[0]), frames_complete=int(complete.sum()),
        structure=structure.names(labels), structure_method=config.structure,
        structure_loglik_per_frame=struct_ll, components=model.components_per_triangle(),
        loglik_per_frame=float(np.mean(ll)), message_length=lengths,
        seconds=time.perf_counter() - t0, sources=[c.source for c in clips])
    return model, summary
