"""Offline training: labelled clips -> canonical point states -> structure -> mixtures -> model.

Pipeline (section III and IV.A):

1. per clip, point states (positions, backward-difference velocities in m/s) and the
   per-frame heading from the labelled left/right pairs; states rotated to face +x
   (see :mod:`features` for why invariant features rather than augmentation);
   ``augment_copies`` extra copies of every frame with a small yaw jitter, a random body
   (isotropic size and per-segment proportions, :func:`scale_bodies`) and a random tempo
   (:func:`change_tempo`), drawn per frame;
2. structure: hand-given, greedy (Song et al.), CBGA or simple GA over the fully observed
   frames, scored with per-triple Gaussians (:mod:`dtm_labeler.search.structure_search`);
3. one mixture per triangle of the chosen structure over the eq. 12 feature, from every
   frame where that triangle's three points have positions and velocities: single
   Gaussian, fixed K, or EM with the MDL rule (eq. 8-11).

Other people (the augmentation of step 1)
    The eq. 12 feature of a triangle holds absolute velocities and relative positions, so a
    mixture fitted to a few recordings knows those people's segment lengths and the speeds
    at which they moved, and little else. Measured on the shared CMU recordings, a new body
    alone (the same motion replayed with another subject's segment lengths) costs almost
    nothing; what fails on a new person is the combination of new poses, new speeds and a
    different body with densities that are sharp in all three. The copies therefore put each
    recorded pose on another body and play it at another tempo: per frame an isotropic scale
    ``s`` (sd ``scale_jitter``), an independent length factor per segment of the most rigid
    point-to-point tree (sd ``proportion_jitter``; :func:`rigid_tree`) and a velocity factor
    (sd ``tempo_jitter``), all log-normal. Positions and velocities go through the same
    linear map, so the 15-D feature stays one a real body could produce. The recorded frames
    stay in the training set unchanged, which keeps the densities sharp where the data is.
    By default only models over the 14 body points get it (:meth:`TrainConfig.resolved`).
"""
from __future__ import annotations

import datetime as _dt
import time
from pathlib import Path
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from .. import __version__
from ..motion.clip import MotionClip
from ..model.body import TAKE_ORDERS_PER_BAR
from ..model.dtm import TriangulatedModel
from ..model.features import FULL, canonicalise, lateral_yaw, observation_state, point_states
from ..motion.naming import common_names, is_unnamed
from ..motion.pointsets import BODY14, left_right_pairs
from ..model.mixture import GaussianMixture
from .gaps import (MIN_TRIPLE_FRAMES, coverage_report, fill_yaw, fit_rows, fit_triangle, loglik_per_label,
                   structure_scores, unattachable, usable_structure)
from ..model.structure import BODY14_GIVEN, Structure
from ..search import structure_search as ss
from ..search.structure_search import TripleScores
from ..labeling.rest_clock import longest_rests
from .body_fit import (BodySettings, bar_orders, broad_components, edge_prior, fit_body, handedness_quads,
                       pair_statistics, side_reach, sided_reach, trunk_twists, validation_rows, person_rigid_pairs)

STRUCTURE_METHODS = ("auto", "cbga", "greedy", "given", "sga", "body")
MIXTURE_KINDS = ("mdl", "fixed", "single")

#: ``structure="auto"`` by point set (True: the 14 body points). The paper's CBGA for the 14 joint
#: centres (Table 3). For marker sets the structure grown along the rigid tree: the CBGA's triangles
#: relate markers the training motion happened to move together, which another motion breaks
#: (HDM05's standing take -> CMU 85 jump + twist, dtm-label's default: 42.6 % with CBGA, 82.8 % with
#: it), while on gapped halves of the same take both label alike (HDM05, 4 gap draws: mean 97.5 %
#: with capture ids either way, lowest 94.2 % CBGA / 96.3 % along the tree).
AUTO_STRUCTURE = {True: "cbga", False: "body"}

# body augmentation of models over the 14 body points (relative sds), chosen by cross-subject
# measurement (README "Other subjects"); other point sets get 0 unless asked for
BODY_AUGMENTATION = {"scale_jitter": 0.05, "proportion_jitter": 0.10, "tempo_jitter": 0.20}


@dataclass
class TrainConfig:
    mixture: str = "mdl"
    k_min: int = 1
    k_max: int = 8
    k_fixed: int = 3
    structure: str = "auto"                 # see resolved(): cbga for the 14 body points, body for marker sets
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
    # other people, per frame of every copy; None = BODY_AUGMENTATION for the 14 body points,
    # 0 for other point sets (see resolved()):
    scale_jitter: float | None = None       # relative sd of the isotropic body scale
    proportion_jitter: float | None = None  # relative sd of each segment's length factor
    tempo_jitter: float | None = None       # relative sd of the velocity factor (same poses, faster / slower)
    given_structure: Sequence[Sequence[str]] | None = None
    # issue 13 (model/body.py, training/body_fit.py): motion-independent edge terms and one broad
    # component per mixture fitted on held-out frames. Reach limits apply always; segment lengths
    # and the broad component once the body is calibrated to a person (a generic body's broad
    # tails make ghosts cheap). Both False reproduce the format-1 models.
    body_terms: bool = True
    broad_component: bool = True
    body: BodySettings = field(default_factory=BodySettings)

    def check(self) -> None:
        if self.mixture not in MIXTURE_KINDS:
            raise ValueError(f"--mixture must be one of {', '.join(MIXTURE_KINDS)}")
        if self.structure not in STRUCTURE_METHODS:
            raise ValueError(f"--structure must be one of {', '.join(STRUCTURE_METHODS)}")
        if not 1 <= self.k_min <= self.k_max:
            raise ValueError("need 1 <= k_min <= k_max")
        if self.k_fixed < 1:
            raise ValueError("k_fixed must be >= 1")
        if self.augment_copies < 0:
            raise ValueError("augment_copies must be >= 0")
        if not 0.0 <= self.yaw_jitter_deg <= 180.0:
            raise ValueError("yaw_jitter_deg must be in [0, 180]")
        for name in BODY_AUGMENTATION:
            value = getattr(self, name)
            if value is not None and not 0.0 <= value <= 0.5:
                raise ValueError(f"{name.replace('_', '-')} must be in [0, 0.5] (a relative standard deviation)")
        self.body.check()

    def resolved(self, labels: Sequence[str]) -> "TrainConfig":
        """This config with every unset (None) body jitter filled in for a model over ``labels``:
        :data:`BODY_AUGMENTATION` when all labels are among the 14 body points (joint centres,
        >= 15 cm apart: what the augmentation was measured on), 0 for other point sets. Dense
        marker sets tell neighbouring markers apart by a few centimetres; there the wider
        densities cost ghost rejection and accuracy within a session (README "Other subjects").
        ``structure="auto"`` becomes :data:`AUTO_STRUCTURE`'s choice for the point set."""
        body = set(labels) <= set(BODY14)
        fill = {k: (v if body else 0.0) for k, v in BODY_AUGMENTATION.items() if getattr(self, k) is None}
        if self.structure == "auto":
            fill["structure"] = AUTO_STRUCTURE[body]
        return replace(self, **fill) if fill else self

    @property
    def reshapes_bodies(self) -> bool:
        """True when the copies get other body sizes or proportions (needs the body tree)."""
        return bool(self.scale_jitter) or bool(self.proportion_jitter)

    @property
    def augments(self) -> bool:
        """True when training adds augmented copies of the recorded frames."""
        return self.augment_copies > 0 and (self.yaw_jitter_deg > 0 or self.reshapes_bodies or bool(self.tempo_jitter))


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
    notes: list[str] = field(default_factory=list)
    coverage: dict[str, float] = field(default_factory=dict)     # per label: share of frames seen
    structure_scored_on: str = ""

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
    yaw = fill_yaw(lateral_yaw(clip.positions, pairs))          # frames without a left/right pair: interpolated
    if jitter_deg > 0:
        rng = rng or np.random.default_rng(0)
        yaw = yaw + np.radians(rng.uniform(-jitter_deg, jitter_deg, size=yaw.shape))
    return canonicalise(states, yaw)


def rigid_tree(clips: Sequence[MotionClip], max_frames: int = 2000, leaves: Sequence[int] = ()) -> np.ndarray:
    """Parent index per point (-1 at the root): the spanning tree of the most rigid links.

    Edge weight = standard deviation of the point-to-point distance within each clip
    (averaged over clips, so different subjects do not make a bone look elastic), plus a
    tie-breaker of 0.1 % of the mean distance (exactly rigid skeleton joints: the shorter
    link wins). The minimum spanning tree of that is the skeleton: for the 14 body points
    the bones plus one trunk link (a shoulder to a hip), for marker sets the segments'
    markers joined through the joints. Rooted at the medoid point (smallest summed mean
    distance, e.g. a hip). Pairs never seen together get a large weight. ``leaves`` (the
    anonymous points, :mod:`.anonymous`): the tree of the other points, each of these joined
    to its most rigid link among them -- the other points' tree, and so their segments and
    reach limits, the ones they have without them.
    """
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
    n = clips[0].n_points
    var_sum, mean_sum, cnt = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n))
    for c in clips:
        P = c.positions[np.linspace(0, c.n_frames - 1, min(c.n_frames, max_frames)).astype(np.int64)]
        d = np.linalg.norm(P[:, :, None, :] - P[:, None, :, :], axis=-1)       # (F, n, n)
        ok = np.isfinite(d)
        k = ok.sum(0)
        mu = np.where(ok, d, 0.0).sum(0) / np.maximum(k, 1)
        var = np.where(ok, (d - mu) ** 2, 0.0).sum(0) / np.maximum(k, 1)
        seen = k >= 2
        var_sum += np.where(seen, var, 0.0)
        mean_sum += np.where(seen, mu, 0.0)
        cnt += seen
    sd = np.sqrt(var_sum / np.maximum(cnt, 1))
    mean = mean_sum / np.maximum(cnt, 1)
    w = np.where(cnt > 0, sd + 1e-3 * mean + 1e-9, 1e6)
    np.fill_diagonal(w, 0.0)
    inner = np.setdiff1d(np.arange(n), np.asarray(leaves, dtype=np.int64))
    sub = np.ix_(inner, inner)
    tree = minimum_spanning_tree(w[sub])
    root = int(np.argmin(np.where(cnt[sub] > 0, mean[sub], 1e3).sum(1)))
    _, pred = breadth_first_order(tree, root, directed=False)
    parents = np.full(n, -1, dtype=np.int64)
    parents[inner] = np.where(pred < 0, -1, inner[np.maximum(pred, 0)])
    for a in leaves:
        parents[a] = inner[int(np.argmin(w[a, inner]))]
    return parents


def tree_order(parents: np.ndarray) -> np.ndarray:
    """Point indices ordered so that every parent comes before its children."""
    parents = np.asarray(parents, dtype=np.int64)
    depth = np.zeros(parents.size, dtype=np.int64)
    for i in range(parents.size):
        j, d = i, 0
        while parents[j] >= 0:
            j, d = parents[j], d + 1
            if d > parents.size:
                raise ValueError("parents do not form a tree")
        depth[i] = d
    return np.argsort(depth, kind="stable")


def scale_bodies(states: np.ndarray, parents: np.ndarray, scale: np.ndarray, factors: np.ndarray) -> np.ndarray:
    """(F, N, 6) states of the same motion performed by other bodies, one body per frame.

    Along the tree ``parents`` every point is its parent plus the (parent -> point) vector
    times ``scale[f] * factors[f, point]``; the root is ``scale[f]`` times itself. The map
    is linear in the points with constant coefficients per frame, so the velocities (the
    derivative of the positions) take the same map: a body ``s`` times as large moving with
    the same joint angles and timing has ``s`` times the relative positions *and* the
    velocities of eq. 12, which keeps the 15-D feature consistent. ``factors`` of the root
    is ignored. A missing parent makes its subtree missing in that frame.
    """
    scale = np.asarray(scale, dtype=np.float64)
    factors = np.asarray(factors, dtype=np.float64)
    out = np.empty_like(states)
    for c in tree_order(parents):
        p = parents[c]
        if p < 0:
            out[:, c] = states[:, c] * scale[:, None]
        else:
            out[:, c] = out[:, p] + (scale * factors[:, c])[:, None] * (states[:, c] - states[:, p])
    return out


def change_tempo(states: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """(F, N, 6) states of the same poses performed ``factor[f]`` times as fast: positions kept,
    every velocity (the nine velocity dimensions of eq. 12, including the whole body's
    translation) multiplied by ``factor[f]``."""
    out = states.copy()
    out[..., 3:] *= np.asarray(factor, dtype=np.float64)[:, None, None]
    return out


def body_draws(rng: np.random.Generator, n_frames: int, n_points: int, scale_sd: float,
               proportion_sd: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame body scale (F,) and segment factors (F, N): ``exp(sd * z)``, ``z`` standard
    normal clipped to +-2.5 (log-normal, so 1.1x and 1/1.1x are equally likely; for small
    ``sd`` the relative standard deviation is ``sd``). A zero ``sd`` draws nothing."""
    def draw(sd, shape):
        return np.exp(sd * np.clip(rng.standard_normal(shape), -2.5, 2.5)) if sd > 0 else np.ones(shape)
    return draw(scale_sd, (n_frames,)), draw(proportion_sd, (n_frames, n_points))


def augmented_copy(clip: MotionClip, pairs: np.ndarray, config: "TrainConfig", parents: np.ndarray | None,
                   yaw_rng: np.random.Generator, body_rng: np.random.Generator) -> np.ndarray:
    """One augmented copy of ``clip``'s canonical states: yaw jitter, then (if configured) a
    random body per frame (:func:`scale_bodies`) and a random tempo per frame
    (:func:`change_tempo`). The yaw draws come from ``yaw_rng`` alone and ``body_rng`` draws
    nothing for a zero jitter, so zero scale/proportion/tempo jitter reproduces the copies of
    a model trained without them."""
    states = canonical_states(clip, pairs, config.yaw_jitter_deg, yaw_rng)
    if config.reshapes_bodies:
        scale, factors = body_draws(body_rng, states.shape[0], states.shape[1], config.scale_jitter,
                                    config.proportion_jitter)
        states = scale_bodies(states, parents, scale, factors)
    if config.tempo_jitter:
        states = change_tempo(states, body_draws(body_rng, states.shape[0], 0, config.tempo_jitter, 0.0)[0])
    return states


def training_states(clips: Sequence[MotionClip], pairs: np.ndarray, config: "TrainConfig"
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(states, train_states, parents)``: the recorded canonical states of all clips, the
    states the mixtures are fitted to (recorded + ``augment_copies`` augmented copies; the
    recorded ones alone without any jitter) and the body tree used (None without body jitter).
    Unset body jitters are resolved for the clips' point names (:meth:`TrainConfig.resolved`)."""
    config = config.resolved(clips[0].names)
    states = np.concatenate([canonical_states(c, pairs) for c in clips], axis=0)
    if not config.augments:
        return states, states, None
    yaw_rng = np.random.default_rng(config.seed + 7919)
    body_rng = np.random.default_rng(config.seed + 104729)
    parents = rigid_tree(clips, leaves=unnamed_points(clips[0].names)) if config.reshapes_bodies else None
    copies = [np.concatenate([augmented_copy(c, pairs, config, parents, yaw_rng, body_rng) for c in clips], axis=0)
              for _ in range(config.augment_copies)]
    return states, np.concatenate([states] + copies, axis=0), parents


def augmentation_summary(config: "TrainConfig", recorded: int, total: int) -> dict:
    """What the mixtures were fitted to (stored in the model's settings)."""
    if not config.augments:
        return {"copies": 0, "recorded_frames": recorded, "frames": total}
    return {"copies": config.augment_copies, "yaw_jitter_deg": config.yaw_jitter_deg,
            "scale_sd": config.scale_jitter, "proportion_sd": config.proportion_jitter,
            "tempo_sd": config.tempo_jitter, "recorded_frames": recorded, "frames": total}


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


def unnamed_points(labels: Sequence[str]) -> list[int]:
    """Indices of the anonymous points (``*`` names, :mod:`.anonymous`) among ``labels``."""
    return [i for i, name in enumerate(labels) if is_unnamed(name)]


def _level_per_label(model: TriangulatedModel, states: np.ndarray, scored_on: str) -> float:
    """``settings["loglik_per_label"]`` of ``model`` on its training ``states``, as
    :func:`train_model` measures it (the median complete frame's per label, or on gappy takes
    :func:`~.gaps.loglik_per_label`)."""
    if scored_on != "complete frames":
        return loglik_per_label(model, states)
    complete = (observation_state(states) == FULL).all(axis=1)
    ll = model.frame_log_likelihood(states[complete]) if complete.any() else np.array([np.nan])
    return float(np.median(ll) / model.n_labels)


def _renumbered(pairs: np.ndarray, idx: Sequence[int]) -> np.ndarray:
    """Index pairs among ``idx`` renumbered to positions in ``idx`` (pairs leaving ``idx`` dropped)."""
    pos = {int(v): k for k, v in enumerate(idx)}
    return np.array([[pos[int(a)], pos[int(b)]] for a, b in np.asarray(pairs).reshape(-1, 2)
                     if int(a) in pos and int(b) in pos], dtype=np.int64).reshape(-1, 2)


def _structure_search(prior: TripleScores, scores: TripleScores, clips: Sequence[MotionClip],
                      parents: np.ndarray | None, pairs: np.ndarray, labels: Sequence[str],
                      config: TrainConfig) -> Structure:
    """``config.structure``'s search over ``labels`` (the points of ``clips``, ``scores``):
    greedy, along the rigid tree (``body``), CBGA or the simple GA; on gappy scores the usable
    one (:func:`~.gaps.usable_structure`)."""
    n = len(labels)
    kw = dict(population=config.structure_population, generations=config.structure_generations,
              seed=config.seed, root_pairs=pairs if len(pairs) else None)
    if config.structure == "greedy":
        structure = ss.greedy(prior, n, kw["root_pairs"]).structure
    elif config.structure == "body":
        structure = ss.along_tree(prior, parents if parents is not None else rigid_tree(clips),
                                  kw["root_pairs"]).structure
    elif config.structure == "cbga":
        res = ss.cbga(prior, n, **kw)
        structure = ss.refine(prior, res, n, np.random.default_rng(config.seed), kw["root_pairs"]).structure
    else:
        structure = ss.simple_ga(prior, n, **kw).structure
    return usable_structure(scores, structure, n, kw["root_pairs"], labels, keep=config.structure == "body")


def train_model(clips: Sequence[MotionClip], config: TrainConfig | None = None,
                progress: Callable[[str, int, int], None] | None = None) -> tuple[TriangulatedModel, TrainSummary]:
    """Train a :class:`TriangulatedModel` on clips that share the same point names."""
    config = config or TrainConfig()
    config.check()
    t0 = time.perf_counter()
    if not clips:
        raise ValueError("no training clips")
    labels, names_note = common_names([c.names for c in clips], [Path(c.source).name or f"clip {i + 1}"
                                                                for i, c in enumerate(clips)])
    clips = [c if list(c.names) == labels else c.select(labels) for c in clips]
    if len(labels) < 3:
        raise ValueError("a triangulated model needs at least 3 points")
    config = config.resolved(labels)
    all_pairs = heading_pairs(labels)
    pairs = stable_heading_pairs(clips, all_pairs)
    states, train_states, parents = training_states(clips, pairs, config)
    codes = observation_state(states)
    complete = (codes == FULL).all(axis=1)
    n = len(labels)
    step = lambda msg, i, k: progress(msg, i, k) if progress else None  # noqa: E731

    coverage = coverage_report(states, labels)
    coverage.check()
    anon = unnamed_points(labels)       # anonymous points (training/anonymous.py): leaves of the tree and structure
    named = [i for i in range(n) if i not in set(anon)]      # the other points
    named_on = None                     # what the named points' own structure was scored on (with anon)

    # -- structure --------------------------------------------------------------------
    step("structure", 0, 1)
    scores, scored_on = structure_scores(states, config.reg_covar)
    lost = unattachable(scores, labels) if scores is not None and config.structure != "given" else []
    if lost:
        raise ValueError(f"{', '.join(lost)}: never seen together with two other points in {MIN_TRIPLE_FRAMES} "
                         "frames; the structure cannot hold them (leave them out with --points or add takes)")
    body, prior = None, scores       # body terms; structure search scores with the edge prior
    joint_centres = set(labels) <= set(BODY14)      # the 14 body points, not markers (body_fit's defaults)
    if config.body_terms:
        positions = [canonical_states(c, pairs)[..., :3] for c in clips]
        stats = pair_statistics(positions, config.body.max_frames)
        body = fit_body(stats, parents if parents is not None else rigid_tree(clips, leaves=anon), config.body,
                        joint_centres=joint_centres, mirror_pairs=all_pairs, leaves=anon)
        # the segments that join clusters (rigid pairs, bars): none of an anonymous point, so
        # the named points' are those of the model without them
        joining = body.segments[~np.isin(body.segments, anon).any(1)] if anon else body.segments
        if not joint_centres:        # marker clusters: their handedness (model/body.py Handedness)
            quads, signs = handedness_quads([x[:, named] for x in positions], max_frames=config.body.max_frames)
            quads = np.asarray(named, dtype=np.int64)[quads]
            body = replace(body, quads=quads, quad_sign=signs,
                           **person_rigid_pairs(positions, joining, config.body.max_frames, leaves=anon))
        else:                        # joint centres: the trunk's twist limit (model/body.py TrunkTwist)
            body = replace(body, twists=trunk_twists(labels, positions))
        if scores is not None and config.body.segment_edge_prior > 0:
            prior = scores.with_edge_prior(edge_prior(stats, config.body))
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
        # anonymous points (training/anonymous.py) join last, as leaves: the named points keep the
        # structure they have without them, so a take that hides or lacks them labels as before
        if anon:                # scored on the named points' own states (their complete frames, their pairs)
            names = [labels[i] for i in named]
            inner_scores, named_on = structure_scores(states[:, named], config.reg_covar)
            inner_prior = inner_scores if prior.edge_prior is None else \
                inner_scores.with_edge_prior(prior.edge_prior[np.ix_(named, named)])
            inner = _structure_search(inner_prior, inner_scores, [c.select(names) for c in clips],
                                      None, _renumbered(pairs, named), names, config)
            structure = prior.with_leaves([[named[v] for v in t] for t in inner.triangles], anon, n)
        else:
            structure = _structure_search(prior, scores, clips, parents, pairs, labels, config)
    struct_ll = scores.per_frame(structure) if scores is not None else float("nan")
    step("structure", 1, 1)
    if body is not None and not joint_centres:      # marker bars: their order (model/body.py BarOrder)
        body = replace(body, orders=bar_orders(positions, joining, structure.array,
                                               max_frames=config.body.max_frames,
                                               reach=sided_reach(all_pairs, len(labels))),
                       take_orders=bar_orders(positions, joining, None, per_bar=TAKE_ORDERS_PER_BAR,
                                              max_frames=config.body.max_frames,
                                              reach=side_reach(all_pairs, len(labels))))

    # -- mixtures per triangle ------------------------------------------------------------
    rng = np.random.default_rng(config.seed)

    mixtures, lengths = [], []
    for t, tri in enumerate(structure.triangles):
        step("mixtures", t, structure.n_triangles)
        fit = fit_triangle(train_states, tri, config, rng, config.seed + t, labels)
        mixtures.append(floor_covariances(fit.mixture, config.position_floor_m, config.velocity_floor_mps))
        lengths.append(float(fit.message_length))
    step("mixtures", structure.n_triangles, structure.n_triangles)
    broad, broad_info = None, None
    if config.broad_component:
        def fit_features(X: np.ndarray, t: int) -> GaussianMixture:      # triangle t's floored mixture on rows X
            return floor_covariances(fit_rows(X, config, rng, config.seed + t).mixture, config.position_floor_m,
                                     config.velocity_floor_mps)

        train_codes = observation_state(train_states)
        held, held_rows = validation_rows([c.n_frames for c in clips], train_states.shape[0] // states.shape[0] - 1,
                                          config.body.validation_fraction)
        recorded = np.arange(train_states.shape[0]) < states.shape[0]
        floor = np.r_[np.full(9, config.velocity_floor_mps ** 2), np.full(6, config.position_floor_m ** 2)]
        broad, broad_info = broad_components(structure, train_states, train_codes, held_rows, recorded,
                                             fit_features, floor, config.body,
                                             lambda i, k: step("broad components", i, k),
                                             joint_centres=joint_centres)

    model = TriangulatedModel(
        labels=tuple(labels), structure=structure, mixtures=mixtures, heading_pairs=pairs,
        mirror_pairs=all_pairs, body=body, broad=broad,
        settings={"heading_bins": config.heading_bins, "feature": "eq12, yaw-canonical (lateral pairs)",
                  "velocity": "backward difference, m/s",
                  "augmentation": augmentation_summary(config, states.shape[0], train_states.shape[0]),
                  "broad_component": broad_info},
        provenance={"trained": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                    "dtm_labeler": __version__, "config": {k: v for k, v in asdict(config).items()
                                                           if k != "given_structure"},
                    "sources": [c.source for c in clips], "frames": int(states.shape[0]),
                    "body_tree": None if parents is None else
                    [[labels[p], labels[c]] for c, p in enumerate(parents) if p >= 0],
                    "rates_hz": sorted({float(c.rate) for c in clips})})
    if scored_on == "complete frames" or not scored_on:
        ll = model.frame_log_likelihood(states[complete]) if complete.any() else np.array([np.nan])
    else:                                           # gappy takes: marginalised over what each frame misses
        ll = model.frame_log_likelihood(states[np.isfinite(states).all(-1).sum(1) >= 3])
    # how long each label's point stood still in training (the rests a label is allowed)
    model.settings["longest_rest_s"] = [round(float(r), 3) for r in longest_rests(clips)]
    # the share of the training frames each label's point was seen in (how often a take should show it)
    model.settings["seen_share"] = [round(float(f), 4) for f in coverage.fraction]
    # the typical model log-likelihood per labelled point: the stream labeler's starting level
    model.settings["loglik_per_label"] = _level_per_label(model, states, scored_on)
    if anon:                            # ... and that of the model without them (TriangulatedModel.named_only)
        model.settings["named_loglik_per_label"] = _level_per_label(model.named_only(), states[:, named],
                                                                    named_on or scored_on)
    summary = TrainSummary(
        labels=labels, frames_total=int(states.shape[0]), frames_complete=int(complete.sum()),
        structure=structure.names(labels), structure_method=config.structure,
        structure_loglik_per_frame=struct_ll, components=model.components_per_triangle(),
        loglik_per_frame=float(np.mean(ll)), message_length=lengths,
        seconds=time.perf_counter() - t0, sources=[c.source for c in clips], notes=[names_note] if names_note else [],
        coverage=coverage.as_dict(), structure_scored_on=scored_on)
    return model, summary
