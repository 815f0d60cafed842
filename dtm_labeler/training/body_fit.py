"""Fitting the body terms and the broad motion components (see :mod:`dtm_labeler.model.body`).

Body terms from labelled clips
    Per label pair and per clip (positions in the body's heading-canonical frame, so that a
    turn of the whole body demonstrates nothing): the mean distance, its standard deviation within the clip,
    its largest value and the spread of the pair's difference vector (at most ``max_frames``
    frames per clip). A pair is a **segment** when its distance hardly varies within a clip
    (within-clip sd at most ``segment_abs_m``: bones 0, marker clusters on one segment a few
    mm of skin motion) -- in every clip, or in the median clip once three or more show the
    pair (:func:`clip_spread`) -- *although its direction does*: the within-clip distance sd is
    at most ``segment_ratio`` times the largest spread of the difference vector. Without the
    second test two points that a recording merely never moved apart (head and knees in an
    upright dance, the trunk in a walk) would pass for one segment and veto the next motion
    that bends them. And it must be a link of the most rigid tree
    (:func:`dtm_labeler.training.train.rigid_tree`): a hinge makes every point of the limb keep
    its distance to both ends of the hinge axis (a knee to the *other* hip in a walk without
    sideways leg motion), and only the most rigid link of each point is taken for a bone. Nor
    may it span a third point (:func:`spans_a_point`: a point on the line between them is the
    joint between two segments -- an elbow the training held at one angle), nor join the body's
    two sides unless its mirror image held as steady (:func:`unmirrored_crossing`: two feet that
    held still), nor be a one-sided pair whose mirror image, seen, moved (:func:`mirror_moved`:
    frames that happened to miss one side's motion). A
    segment's allowed range is the range of its clip
    means (each clip one person, or one marker placement), its within-person spread that
    within-clip sd times ``within_factor`` (floored at ``within_floor_m``), and its
    between-person spread ``between_rel`` of its length (for a person outside the range; by
    default 5 % for joint centres -- wider lets a ghost take a hidden joint's label: ghost
    rejection 0.72 at 15 % against 0.84 at 5 % on the CMU walk with 2 hidden + 2 ghosts -- and 30 %
    for markers, whose placement differs between sessions and labs: the CMU and HDM05 thigh
    markers sit 11 cm apart along the thigh). A body outside that range is what calibration is for.
    Every other pair gets a **reach limit**: the path length between the two points along the
    most rigid tree (:func:`dtm_labeler.training.train.rigid_tree`), each link taken at its
    longest, so only anatomically impossible distances cost anything; those whose path joins
    two limbs that held still hold on the DTM's edges only (:func:`reach_off_edges`).

Broad components by EM on held-out frames
    The last ``validation_fraction`` of every clip is held out (contiguous: other moves of the
    same take), the mixtures are fitted to the rest, and for each triangle the weight ``w`` of
    the broad conditional ``q`` -- of ``N(mu, s^2 Sigma + diag(floor))``, moment-matched to the
    fitted part; the floor ``broad_floor_m`` / ``broad_floor_mps`` keeps directions the training
    never moved in open -- beside the motion conditional ``p`` is found by EM on the held-out
    triples: ``r_i = w q_i / ((1 - w) p_i + w q_i)``, ``w = mean r_i``, for each scale ``s`` of a
    grid, keeping the ``(w, s)`` of the highest held-out likelihood. ``w`` is kept in
    ``[min_weight, max_weight]`` so that even a take whose held-out part shows nothing new (a
    steady walk) leaves unseen poses a tail. The held-out part is another stretch of the same
    takes, so it shows less novelty than another motion will: the floor stands for that, and
    it depends on the point set. For the 14 body points it is 0.06 (``dtm-eval``
    generalisation, calibrated, stream: a run with no run in the training 97.0 -> 99.7 %,
    another dancer 99.7 -> 100 %, no cell lower; single frames: the run 89.3 -> 94.9 %, one cell
    lower, lambada -> whirl 97.6 -> 96.4 %; the EM put 10 of 12 triangles of that model at the
    old floor, 0.02). For marker sets it stays 0.02: with some 40 triangles, each one's tail
    adds up, and at 0.06 wrong labelings of another lab's markers got cheap (HDM05 -> CMU 85
    calibrated 93.6 -> 77.4 %, floor moves 89.9 -> 46.8 %) while CMU 85 -> HDM05 gained
    (48.9 -> 97.5 %). The model keeps its mixtures fitted to all frames and gets the broad
    part (:class:`dtm_labeler.model.body.BroadMotion`) moment-matched to all frames with the
    chosen ``(w, s)``.
"""
from __future__ import annotations

import itertools
import warnings

from dataclasses import asdict, dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, shortest_path

from ..model.body import (BAR_TOLERANCE_M, HANDEDNESS_SHARE, ORDER_MARGIN_M, ORDER_SHARE, ORDERS_PER_BAR, REACH,
                          RIGID_SPREAD, SEGMENT, TWIST_COS_MIN, TWIST_COS_SD, BodyModel, BroadMotion, Handedness,
                          broad_covariance, segment_clusters)
from ..model.body_kernel import twist_cosines
from ..model.features import FULL, PARENTS_MAP, triangle_features
from ..model.mixture import GaussianMixture, logsumexp_rows
from ..model.structure import Structure
from ..labeling.rigid_tracks import rigid_pairs, spread_sample
from ..motion.pointsets import MARKER_SETS


#: floor of the broad component's weight by point set when ``BodySettings.min_weight`` is None (module doc)
MIN_WEIGHT_BODY14 = 0.06
MIN_WEIGHT_MARKERS = 0.02


@dataclass(frozen=True)
class BodySettings:
    """How body terms and broad components are fitted (module doc)."""

    segment_abs_m: float = 0.008
    segment_ratio: float = 0.05
    within_factor: float = 1.5
    within_floor_m: float = 0.005
    between_rel: float | None = None    # None: 0.05 for the 14 body points, 0.3 for marker sets (placement)
    reach_sd_m: float = 0.03
    # structure prior (CBGA, greedy): nats per frame for an edge of constant length. Off by default:
    # pulled onto the segments, the CBGA chose pelvis-marker hubs whose occlusion cuts many
    # conditionals (eq. 31); 41-marker streams with gaps fell from 100 % to 32 % (CMU 85_02).
    segment_edge_prior: float = 0.0
    edge_prior_sd_m: float = 0.05       # ... falling to 0 at this within-clip sd of its length
    max_frames: int = 3000
    validation_fraction: float = 0.2
    min_weight: float | None = None     # None: 0.06 for the 14 body points, 0.02 for marker sets (module doc)
    max_weight: float = 0.5
    scales: tuple = (2.0, 3.0, 4.0)
    broad_floor_m: float = 0.15         # broad component: at least this sd of every relative position ...
    broad_floor_mps: float = 1.0        # ... and of every velocity
    em_iterations: int = 50

    def check(self) -> None:
        if not 0.0 < self.validation_fraction < 0.5:
            raise ValueError("validation fraction must be in (0, 0.5)")
        floors = (self.min_weight,) if self.min_weight is not None else (MIN_WEIGHT_BODY14, MIN_WEIGHT_MARKERS)
        if not all(0.0 < w <= self.max_weight < 1.0 for w in floors):
            raise ValueError("need 0 < min_weight <= max_weight < 1")
        if (self.between_rel is not None and self.between_rel < 0) or self.within_floor_m <= 0 or self.reach_sd_m <= 0:
            raise ValueError("body spreads must be positive")


def pair_statistics(clips: Sequence[np.ndarray], max_frames: int = 3000) -> dict[str, np.ndarray]:
    """Per clip (C, M, M) of (F, M, 3) heading-canonical positions: mean, within-clip sd and
    largest distance of every label pair and the spread (root of the summed variances) of its
    difference vector in the body's frame; NaN where a pair is never seen together in a clip."""
    means, sds, maxs, vecs = [], [], [], []
    for c in clips:
        P = c[np.linspace(0, c.shape[0] - 1, min(c.shape[0], max_frames)).astype(np.int64)]
        v = P[:, :, None, :] - P[:, None, :, :]
        d = np.linalg.norm(v, axis=-1)                                                  # (F, M, M)
        with np.errstate(all="ignore"), warnings.catch_warnings():    # pairs seen < 2 times: NaN, no warning
            warnings.simplefilter("ignore", RuntimeWarning)
            seen = np.isfinite(d).sum(0)
            mu = np.nanmean(np.where(seen >= 2, d, np.nan), axis=0) if d.shape[0] else d[0]
            means.append(np.where(seen >= 2, mu, np.nan))
            sds.append(np.where(seen >= 2, np.nanstd(d, axis=0), np.nan))
            maxs.append(np.where(seen >= 2, np.nanmax(np.where(np.isfinite(d), d, -np.inf), axis=0), np.nan))
            vecs.append(np.where(seen >= 2, np.sqrt(np.nanvar(v, axis=0).sum(-1)), np.nan))
    return {"mean": np.stack(means), "sd": np.stack(sds), "max": np.stack(maxs), "vec": np.stack(vecs)}


def handedness_quads(clips: Sequence[np.ndarray], share: float = HANDEDNESS_SHARE, neighbours: int = 4,
                     min_frames: int = 20, max_frames: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """The marker clusters' handedness (:class:`~dtm_labeler.model.body.Handedness`) from (F, M, 3)
    labelled positions per clip: for each label and every three of its ``neighbours`` closest
    partners, the quadruple and the sign of its signed volume where one sign holds in at least
    ``share`` of the frames that show all four (at least ``min_frames`` of them) and the four
    hold together (:func:`rigid_quads`). Returns ``(quads (Q, 4), signs (Q,))``.

    A label's partners are the labels whose distance to it varies least over the clips (sd):
    the markers of its own segment. Nearest by median distance, a toe marker's partners took in
    the other foot's toe whenever the training stood with the feet together, and its sign
    taught the labeler to exchange the toe markers once the feet moved apart. Measured on the
    41-marker generalisation cells, ``dtm-label``'s default self-calibration
    (``benchmarks/bench_auto_calibration.py``), nearest by median -> by sd: HDM05 -> CMU 85
    jump + twist 97.16 -> 97.96 %, floor moves 89.13 -> 93.64 %, CMU 85 breakdance -> jump +
    twist 99.95 -> 100 %, the other two as they were (99.12, 100 %). Tried and not kept: the
    four least varying among the eight nearest (floor moves 83.62 %, HDM05 -> CMU 85 97.98 %),
    mutual partners only (77.06 %, 97.72 %), and a spread limit of 0.07 instead of 0.3 in
    :func:`rigid_quads` (94.76 %, 98.28 %, but CMU 85 breakdance -> jump + twist 99.48 % and
    jump + twist -> breakdance 98.97 %). A training part that hardly moves (HDM05's first 30 %:
    most distances vary by 1-3 mm) still pairs some markers across joints."""
    P = np.concatenate([c[np.linspace(0, c.shape[0] - 1, min(c.shape[0], max_frames)).astype(np.int64)]
                        for c in clips])
    M = P.shape[1]
    if M < 4:
        return np.zeros((0, 4), dtype=np.int64), np.zeros(0)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sd = np.nanstd(np.linalg.norm(P[:, :, None] - P[:, None], axis=-1), axis=0)
    sd[~np.isfinite(sd)] = np.inf
    np.fill_diagonal(sd, np.inf)
    near = np.argsort(sd, axis=1)[:, :min(neighbours, M - 1)]
    cand = {tuple(sorted((a, *map(int, trio)))) for a in range(M)
            for trio in itertools.combinations(near[a], 3) if np.isfinite(sd[a, list(trio)]).all()}
    if not cand:
        return np.zeros((0, 4), dtype=np.int64), np.zeros(0)
    return quad_signs(P, np.array(sorted(cand), dtype=np.int64), share, min_frames)


def bars(positions: np.ndarray, segments: np.ndarray, tolerance: float = BAR_TOLERANCE_M) -> np.ndarray:
    """(B, 2) the marker bars (:class:`~dtm_labeler.model.body.BarOrder`) of (F, M, 3) labelled
    positions: two labels of one segment cluster (:func:`segment_clusters` of ``segments``) with
    at least one more label in it, each of which lies as far from the one as from the other
    within ``tolerance`` (median over the frames)."""
    P = np.asarray(positions, dtype=np.float64)
    M = P.shape[1]
    cluster = segment_clusters(M, segments)
    out = []
    for c in np.unique(cluster[cluster >= 0]):
        members = np.flatnonzero(cluster == c)
        if members.size < 3:
            continue
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            d = np.linalg.norm(P[:, members, None] - P[:, None, members], axis=-1)           # (F, C, C)
            for i, j in itertools.combinations(range(members.size), 2):
                rest = np.delete(np.arange(members.size), [i, j])
                gap = np.nanmedian(np.abs(d[:, i, rest] - d[:, j, rest]), axis=0)
                if np.isfinite(gap).all() and (gap < tolerance).all():
                    out.append((members[i], members[j]))
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def bar_orders(clips: Sequence[np.ndarray], segments: np.ndarray, triangles: np.ndarray | None,
               share: float = ORDER_SHARE, margin: float = ORDER_MARGIN_M, per_bar: int = ORDERS_PER_BAR,
               min_frames: int = 20, max_frames: int = 3000, reach: np.ndarray | None = None) -> np.ndarray:
    """(K, 3) the marker bars' order (:class:`~dtm_labeler.model.body.BarOrder`) from (F, M, 3)
    labelled positions per clip: for each bar (:func:`bars`), the labels within two edges of the
    structure's ``triangles`` of either end (but the ends), whose nearer end is the same in at
    least ``share`` of the frames of every clip that shows it (at least ``min_frames``) and
    whose median margin is at least ``margin``; the ``per_bar`` with the clearest margin
    (median over robust spread, 5 mm added), as rows ``(x, near, far)``.

    Labels of the bar's own cluster count too. The finger or hand marker hangs from the wrist
    bar by a segment to one end only, and the hand turns about the wrist's flexion axis, the
    line through the two ends: the turn leaves its distance to each end as it was, so its
    nearer end is the steadiest order there is (HDM05, left wrist: the finger nearer the radial
    end in 99.8 % of the take's first 70 % and in 100 % of the rest, where the clavicle's and
    the right shoulder's orders, which turn with the whole arm, held in 69 % and 78 %). A
    member that keeps one distance to both ends has no margin and is never taken.

    ``reach`` (M, M) bool: the labels each label's bar may be ordered by, besides the triangles'
    reach (:func:`sided_reach` for the model's rows) or instead of it (``triangles`` None:
    :func:`side_reach` for the take pass's rows, :attr:`~dtm_labeler.model.body.BodyModel.take_orders`)."""
    clips = [np.asarray(c, dtype=np.float64)[spread_sample(len(c), max_frames)] for c in clips if len(c)]
    if not clips:
        return np.zeros((0, 3), dtype=np.int64)
    P = np.concatenate(clips)
    M = P.shape[1]
    near = np.ones((M, M), dtype=bool)
    if triangles is not None:
        adjacent = np.eye(M, dtype=np.int64)
        for tri in np.asarray(triangles, dtype=np.int64).reshape(-1, 3):
            adjacent[np.ix_(tri, tri)] = 1
        near = (adjacent @ adjacent) > 0                               # within two triangle edges
    if reach is not None:
        near &= np.asarray(reach, dtype=bool)
    rows = []
    for a, b in bars(P, segments):
        candidates = np.flatnonzero(near[a] | near[b])
        candidates = candidates[(candidates != a) & (candidates != b)]
        if candidates.size == 0:
            continue
        holds = np.ones(candidates.size, dtype=bool)
        sides = []
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for c in clips:
                gap = (np.linalg.norm(c[:, candidates] - c[:, [a]], axis=-1)
                       - np.linalg.norm(c[:, candidates] - c[:, [b]], axis=-1))        # (F, X) > 0: b nearer
                seen = np.isfinite(gap)
                n = seen.sum(0)
                nearer_b = (gap > 0).sum(0) / np.maximum(n, 1)
                counted = n >= min_frames
                holds &= ~counted | (np.maximum(nearer_b, 1.0 - nearer_b) >= share)
                sides.append(np.where(counted, np.sign(nearer_b - 0.5), 0.0))
            gap = (np.linalg.norm(P[:, candidates] - P[:, [a]], axis=-1)
                   - np.linalg.norm(P[:, candidates] - P[:, [b]], axis=-1))
            median = np.nanmedian(gap, axis=0)
            spread = 1.4826 * np.nanmedian(np.abs(gap - median), axis=0)
        sides = np.array(sides)
        agree = ((sides == np.sign(median)) | (sides == 0)).all(0) & (np.abs(sides).sum(0) > 0)
        ok = holds & agree & (np.abs(np.nan_to_num(median)) >= margin)
        clear = np.abs(median) / (np.nan_to_num(spread, nan=np.inf) + 0.005)
        for k in np.flatnonzero(ok)[np.argsort(-clear[ok], kind="stable")][:per_bar]:
            x = candidates[k]
            rows.append((x, b, a) if median[k] > 0 else (x, a, b))
    return np.array(rows, dtype=np.int64).reshape(-1, 3)


def side_reach(mirror_pairs: np.ndarray, n_labels: int) -> np.ndarray:
    """(M, M) bool: the labels on one side of the body (one column of the left/right
    ``mirror_pairs``), each with the others of its side. What a bar's order over a stretch of a
    take may be read from (:attr:`~dtm_labeler.model.body.BodyModel.take_orders`): the bar's own
    arm and shoulder, wherever the DTM's triangles put them; not the trunk's middle labels, which
    lie on the bar's side or the other as the arm crosses the body."""
    side = np.full(n_labels, -1)
    pairs = np.asarray(mirror_pairs, dtype=np.int64).reshape(-1, 2)
    side[pairs[:, 0]], side[pairs[:, 1]] = 0, 1
    return (side[:, None] == side[None, :]) & (side[:, None] >= 0)


def sided_reach(mirror_pairs: np.ndarray, n_labels: int) -> np.ndarray:
    """(M, M) bool: :func:`side_reach`, and every label for a label without a mirror partner
    (a point set of one arm: whose side is not known). What the model's own bar orders
    (:attr:`~dtm_labeler.model.body.BodyModel.orders`) may be read from besides the triangles'
    reach (:func:`bar_orders`): a bar on one side of the body is ordered by labels of its side.

    Within two triangle edges of a wrist bar, a take that mostly stands still also holds the
    other side's and the midline's labels in one order: HDM05's first 2000 frames ordered the
    left wrist bar by RFHD, the right one by STRN, C7 and the *left* upper arm, orders a pose
    held for a while. Measured on the model the demo and the node use (that training, CBGA,
    K <= 2, calibrated), frames 2400-3000 with 3 gaps + 2 ghosts + 1 mm, inline, corruption
    seeds 1-7 (``results/search_errors.md``, 2026-12-06): 99.42 / 97.16 / 99.22 / 90.18 /
    97.65 / 96.27 / 98.69 -> 99.38 / 97.30 / 99.22 / 99.23 / 98.30 / 98.68 / 98.72 % (mean
    96.94 -> 98.69 %), ghosts labelled 659 -> 514 of 8400; frames 4144-4744, seeds 1-4, 96.15
    -> 96.31 %; ``bench_stream_latency``'s model (70 % of the take, whose rows were all of the
    bar's side already) unchanged. Rows only from labels the body's rigid tree joins to the
    bar within two links (tried): the right bars of that model and of ``dtm-eval``'s HDM05
    body then kept no row, and the bench's stream lost 0.6-1.8 points."""
    reach = side_reach(mirror_pairs, n_labels)
    reach[~reach.any(1)] = True
    return reach


def trunk_twists(labels: Sequence[str], clips: Sequence[np.ndarray] = (), share: float = 0.999) -> np.ndarray:
    """The trunk's twist limits (:class:`~dtm_labeler.model.body.TrunkTwist`) of a point set:
    rows ``(left shoulder, midline point or -1, right shoulder, left hip, right hip)`` of label
    indices, one per pair of pelvis points, from the names of every known point set
    (:data:`~dtm_labeler.motion.pointsets.MARKER_SETS`: the 14 body points' shoulders, neck and
    hips; a marker set's shoulder, C7 / CV7 and pelvis markers) that ``labels`` hold. With
    training frames ``clips`` ((F, M, 3) labelled positions), a row is kept only where its
    cosine stays above the limit plus two spreads in ``share`` of the frames that show it (a
    point set whose "left" is the other side's left is not limited). Training attaches them to
    the 14 body points only (:class:`~dtm_labeler.model.body.TrunkTwist`: measured on marker
    sets, they moved the 41-marker cells both ways)."""
    index = {name: i for i, name in enumerate(labels)}
    rows = []
    for table in MARKER_SETS.values():
        ls, rs = table["lshoulder"][0], table["rshoulder"][0]
        mids = [m for m in table["neck"] if m in index and m not in (ls, rs)]
        for lh, rh in zip(table["lhip"], table["rhip"]):
            if all(n in index for n in (ls, rs, lh, rh)):
                rows.append((index[ls], index[mids[0]] if mids else -1, index[rs], index[lh], index[rh]))
    twists = np.array(sorted(set(rows)), dtype=np.int64).reshape(-1, 5)
    if twists.shape[0] and len(clips):
        P = np.concatenate([np.asarray(c, dtype=np.float64) for c in clips])
        M = P.shape[1]
        c = twist_cosines(np.arange(P.shape[0] * M).reshape(-1, M), P.reshape(-1, 3), twists)
        with np.errstate(invalid="ignore"):
            low = np.array([np.quantile(col[np.isfinite(col)], 1.0 - share) if np.isfinite(col).any() else np.inf
                            for col in c.T])
        twists = twists[low >= TWIST_COS_MIN + 2.0 * TWIST_COS_SD]
    return twists


def quad_signs(positions: np.ndarray, quads: np.ndarray, share: float = HANDEDNESS_SHARE,
               min_frames: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Of label ``quads`` (Q, 4), those whose signed volume shows one sign in at least ``share``
    of the frames of ``positions`` (F, M, 3) that show all four (at least ``min_frames``) and
    that hold together as one cluster (:func:`rigid_quads`), and that sign:
    ``(quads (K, 4), signs (K,))``."""
    quads = np.asarray(quads, dtype=np.int64).reshape(-1, 4)
    v = Handedness.volumes(positions[:, quads])                 # (F, Q)
    seen = np.isfinite(v)
    pos = ((v > 0) & seen).sum(0)
    n = seen.sum(0)
    sign = np.where(2 * pos >= n, 1.0, -1.0)
    agree = np.where(sign > 0, pos, n - pos)
    keep = (n >= min_frames) & (agree >= share * np.maximum(n, 1)) & rigid_quads(positions, quads, seen)
    return quads[keep], sign[keep]


def rigid_quads(positions: np.ndarray, quads: np.ndarray, seen: np.ndarray | None = None,
                max_spread: float = RIGID_SPREAD) -> np.ndarray:
    """(Q,) whether each of ``quads`` (Q, 4) keeps its six distances within ``max_spread``
    (sd over median) over the frames of ``positions`` (F, M, 3) that show all four (``seen``,
    (F, Q), when known).

    A handedness factor is a property of a rigid cluster
    (:class:`~dtm_labeler.model.body.Handedness`): four points spread over two limbs (a foot's
    markers and the other heel, both shins) show one sign only while the pose keeps them so.
    Training frames of a motion that hardly moves its legs can show such a quadruple with one
    sign in 99 % of them; the next motion shows both. Measured, HDM05 -> CMU 85 jump + twist:
    with the true labels of the take's first 600 frames the quadruples across the two feet
    spread 0.64-0.78 (0.08-0.29 in the HDM05 training frames), and those labels show the learnt
    sign in 32-62 % of frames 300-600, which made the labeler exchange LTOE/LMT5 and RTOE/RMT5
    to suit them; the clusters on one segment spread under 0.25 (head, trunk, one foot, a wrist
    bar). The frames the self-calibration confirmed there stand still (spread 0.05-0.08), so in
    that cell the partner rule of :func:`handedness_quads` is what removes those quadruples;
    this check removes them where the calibration window moves: ``dtm-label``'s self-calibrated
    floor-moves cell (``benchmarks/bench_auto_calibration.py``) went 69.97 -> 89.13 %, the
    other 41-marker cells as before."""
    quads = np.asarray(quads, dtype=np.int64).reshape(-1, 4)
    if quads.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    a, b = np.triu_indices(4, 1)
    X = positions[:, quads]                                          # (F, Q, 4, 3)
    d = np.linalg.norm(X[:, :, a] - X[:, :, b], axis=-1)             # (F, Q, 6)
    if seen is not None:
        d = np.where(seen[..., None], d, np.nan)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        spread = np.nanstd(d, axis=0) / np.nanmedian(d, axis=0)     # (Q, 6)
    return np.nan_to_num(spread, nan=np.inf).max(1) <= max_spread


#: clips needed before a pair's within-clip spread is read from the median clip rather than the worst
MEDIAN_CLIPS = 3
#: two segment clusters are one where this many short pairs between them held rigid (:func:`joined_clusters`)
JOIN_LINKS = 2
#: ... each at most this long (m): within one segment's reach, not across a joint
JOIN_LENGTH_M = 0.2
#: ... and with a robust spread at most this (m): tighter than a rigid pair need be (8 mm)
JOIN_SPREAD_M = 0.005
#: frames a pair must be seen together in to be measured as the person's rigid pair
PERSON_PAIR_MIN_FRAMES = 10


def person_rigid_pairs(clips: Sequence[np.ndarray], segments: np.ndarray, max_frames: int = 3000,
                       min_frames: int = PERSON_PAIR_MIN_FRAMES, leaves: Sequence[int] = ()) -> dict[str, np.ndarray]:
    """The trained person's rigid marker pairs (:attr:`BodyModel.rigid_pairs`) from the (F, M, 3)
    positions of the training clips, pooled (at most ``max_frames`` frames spread over them): the
    pairs the take pass measures on a take (:func:`dtm_labeler.labeling.rigid_tracks.rigid_pairs`:
    seen together often, short, robust spread of a few mm), measured on the training labels, and
    kept where both labels lie in one rigid cluster of the body's ``segments`` (the connected
    components of the structure's tree links that held rigid, :func:`segment_clusters`, joined
    where the tree split one segment's markers, below).

    Why: the offline pass over a take (:mod:`dtm_labeler.labeling.rigid_tracks`) reads the
    person's rigid pairs from the take's own labels, which are wrong where it needs them most,
    and from the body's segments, which are only the tree's links (HDM05's 41 markers: 24
    segments). A marker cluster on one segment is rigid in every pair, as
    :class:`~dtm_labeler.model.body.CrossSegments` reads it; a model of one person knows those
    pairs' lengths. Why only within the clusters: a pair that merely held still in the training
    frames need not hold in another motion -- HDM05's left shoulder and upper-arm markers, steady
    within 11 mm over the first half of the take, lie 4 cm closer in the second, and with them
    the take pass gave the upper arm's label to the shoulder (gap seed 1, capture ids, 97.91 ->
    94.31 %; :func:`~dtm_labeler.labeling.rigid_tracks.body_pairs` has the figures). Pooled over
    several people the spreads grow and most pairs drop out; the take pass uses them only where
    the take agrees with the body (``RigidPairs.with_body``).

    Clusters the tree split (:func:`joined_clusters`). On a gappy training take the structure
    can tie a rarely seen marker only to triples seen together often enough
    (:data:`~dtm_labeler.training.gaps.MIN_TRIPLE_FRAMES`), mostly the markers that are nearly
    always seen: the Qualisys walk's 170 training frames at 50 % gaps put the right forefoot's
    fifth metatarsal in a triangle with the head and the left elbow, and one foot's markers fell
    in three clusters. Without the foot's pairs across them the take pass kept the fifth
    metatarsal's trajectory under the first's label in all 79 frames of it, 39 of them showing the
    lateral malleolus, 113 mm from the one and 158 mm from the other; on another draw the left
    forefoot's two markers were on no segment at all. So two clusters -- a label on no segment
    counting as a cluster of its own -- with at least :data:`JOIN_LINKS` short pairs
    (:data:`JOIN_LENGTH_M`) between them that held within :data:`JOIN_SPREAD_M` are one here, and
    a pair counts as measured from :data:`PERSON_PAIR_MIN_FRAMES` frames seen together (20
    before: the foot's pairs are seen together in 11-14 of the 170 frames). Measured on
    ``benchmarks/bench_captures.py``'s gapped halves (train the gapped first half as
    ``dtm-train`` does, ``dtm-label``'s default on the gapped second half; capture ids / own
    tracker), before -> after: the Qualisys walk, gap draws 1-4, 99.21 / 99.68, 97.62 / 96.77,
    97.10 / 96.84, 95.87 / 97.69 -> 99.59 / 99.79, 98.78 / 99.18, 98.97 / 99.59, 99.10 / 99.38 %
    (means 97.45 / 97.75 -> 99.11 / 99.49 %); HDM05, gap draws 1-6, the same but draw 2 99.50 /
    99.70 -> 99.42 / 99.70 and draw 5 97.85 / 98.05 -> 97.56 / 98.02 % (means 97.91 / 98.63 ->
    97.85 / 98.63 %). Tried and not kept: links of any spread up to the rigid pairs' 8 mm (HDM05
    draw 1: a finger marker joined the wrist bar's cluster on a 7 mm link, and the bar's ends
    were exchanged over 50 frames, own tracker 98.73 -> 98.31 %; the walk 98.99 / 99.56 %); a
    single label joining on three links only (two leave a point free to turn about the line
    through its partners, as the hand about the wrist bar's ends: HDM05 draw 5 back to 97.85 /
    98.05 %, but the walk's draw 3 96.53 / 96.84 %, its forefoot out again); only the short tight
    links kept as pairs across the joined clusters (the walk's means 98.81 / 99.33 %); no label
    on no segment joining (the walk 98.57 / 98.75 %: the left forefoot's markers stay out); links
    of any length (the walk's 0.85 s held a thigh and an elbow marker within 6 mm, and the
    clusters chained into one):
    the walk 98.72 / 98.60 % but HDM05 draw 1 98.12 / 98.73 -> 97.18 / 97.25 %.

    ``leaves``: labels that join no two clusters and have no pairs (a model's anonymous points,
    :mod:`dtm_labeler.training.anonymous`: a marker riding between two clusters would make them
    one, and the named points' pairs would not be those of the model without it)."""
    P = np.concatenate([np.asarray(c, dtype=np.float64) for c in clips]) if len(clips) else np.zeros((0, 0, 3))
    if P.shape[0] == 0:
        return {"rigid_pairs": np.zeros((0, 2), dtype=np.int64), "rigid_length": np.zeros(0),
                "rigid_spread": np.zeros(0)}
    measured = rigid_pairs(P[spread_sample(P.shape[0], max_frames)], min_frames=min_frames)
    short = measured.rigid & (measured.length <= JOIN_LENGTH_M) & (measured.spread <= JOIN_SPREAD_M)
    cluster = segment_clusters(P.shape[1], segments)
    out = np.zeros(P.shape[1], dtype=bool)
    out[np.asarray(leaves, dtype=np.int64)] = True
    short &= ~out[:, None] & ~out[None, :]
    cluster = np.where(out, -1, joined_clusters(cluster, short))
    u, v = np.nonzero(np.triu(measured.rigid & (cluster[:, None] == cluster[None, :]) & (cluster[:, None] >= 0), 1))
    return {"rigid_pairs": np.stack([u, v], 1), "rigid_length": measured.length[u, v],
            "rigid_spread": measured.spread[u, v]}


def joined_clusters(cluster: np.ndarray, rigid: np.ndarray, links: int = JOIN_LINKS) -> np.ndarray:
    """(M,) ``cluster`` (:func:`segment_clusters`; -1 on no segment) with two clusters made one
    wherever at least ``links`` pairs between them are ``rigid`` (M, M, symmetric), repeated until
    no two join (:func:`person_rigid_pairs`). A label on no segment is a cluster of its own here:
    it joins a cluster it has ``links`` rigid pairs to, and is -1 again if it joins none."""
    cluster = np.asarray(cluster).copy()
    alone = cluster < 0
    cluster[alone] = cluster.max(initial=-1) + 1 + np.arange(alone.sum())
    while True:
        ids = np.unique(cluster)
        member = (cluster[None, :] == ids[:, None]).astype(np.int64)            # (C, M)
        between = member @ rigid.astype(np.int64) @ member.T                   # (C, C) rigid pairs between
        np.fill_diagonal(between, 0)
        a, b = np.nonzero(np.triu(between >= links, 1))
        if not a.size:
            break
        cluster[cluster == ids[b[0]]] = ids[a[0]]
    ids, counts = np.unique(cluster, return_counts=True)
    cluster[alone & np.isin(cluster, ids[counts == 1])] = -1
    return cluster


def clip_spread(sd: np.ndarray) -> np.ndarray:
    """(M, M) the within-person spread of each pair from its within-clip sds ``sd`` (C, M, M; NaN
    where a clip never shows the pair): the worst clip's while one or two clips show the pair, the
    median clip's from :data:`MEDIAN_CLIPS` on -- a segment must hold in most recordings, not in
    every one. Points derived from surface markers (the 14 body points of a marker take: joint
    centres from marker means) move 1-3.5 cm against each other on a bone; with one such take
    among eleven, the worst-clip rule left a model of every shared person 2 of its 12 bones and
    a calibration nothing to measure (``dtm-eval`` generic-model rows, calibrated, stream /
    single: pirouette 98.6 / 97.0 -> 100 / 99.7 %, run single frames 85.1 -> 94.0 %). Two clips
    keep the worst-clip rule: their median is their mean, and a pair rigid in one take only (a
    standing take's planted feet) became a segment (41 markers, CMU 85 jump + twist and HDM05's
    standing take -> the floor moves: 22 -> 30 segments, ``dtm-label``'s default 97.0 -> 75.0 %)."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        n = np.isfinite(sd).sum(0)
        return np.where(n >= MEDIAN_CLIPS, np.nanmedian(sd, axis=0), np.nanmax(sd, axis=0))


def reach_limits(longest: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(M, M) path length between every two points along the tree ``parents`` with each link
    (point, parent) at its ``longest`` distance: no pose puts them farther apart."""
    M = parents.size
    child = np.flatnonzero(parents >= 0)
    w = np.maximum(longest[child, parents[child]], 1e-6)
    graph = coo_matrix((w, (child, parents[child])), shape=(M, M))
    return shortest_path(graph, directed=False)


#: a link joining the body's two sides is the trunk's when its mirror image held about as rigid:
#: its distance spread at most this many times the link's, or this much more (m)
MIRROR_RIGID_RATIO, MIRROR_RIGID_SLACK_M = 2.0, 0.005


def limb_links(parents: np.ndarray, segment: np.ndarray, spread: np.ndarray,
               mirror_pairs: np.ndarray | None) -> np.ndarray:
    """(M,) whether the link of each point to its parent in the most rigid tree ``parents``
    joins two limbs: a left and a right point (``mirror_pairs``) that are no segment
    (``segment`` (M, M)), either mirror partners or a pair whose mirror image did not hold about
    as rigid (``spread`` (M, M), within-clip distance sd; :data:`MIRROR_RIGID_RATIO`). A link
    between the body's two sides whose mirror image held as rigid is the trunk's or the head's
    (a shoulder and the other side's hip); two limbs that merely held still are not held
    together by anything (HDM05's standing take: the left ankle by the right fifth metatarsal,
    1.3 mm, while the right ankle to the left metatarsal varied 16 mm)."""
    M = parents.size
    side, mate = sides(M, mirror_pairs)
    child = np.flatnonzero(parents >= 0)
    par = parents[child]
    sd = np.where(np.isfinite(spread), spread, np.inf)
    link_sd, mirror_sd = sd[child, par], sd[mate[child], mate[par]]
    trunk_like = mirror_sd <= np.maximum(MIRROR_RIGID_RATIO * link_sd, link_sd + MIRROR_RIGID_SLACK_M)
    out = np.zeros(M, dtype=bool)
    out[child] = (side[child] * side[par] < 0) & ~segment[child, par] & ((mate[child] == par) | ~trunk_like)
    return out


def reach_off_edges(parents: np.ndarray, segment: np.ndarray, spread: np.ndarray,
                    mirror_pairs: np.ndarray | None) -> np.ndarray:
    """(M, M) whether a pair's reach limit may hold off the DTM's edges too
    (:class:`~dtm_labeler.model.body.CrossSegments`): its path along the most rigid tree crosses
    no :func:`limb_links` link. Such a link's longest in the training is no anatomical bound but
    the stance the training showed, and every pair of the two limbs has its reach through it:
    HDM05's standing take (its first 30 %) kept the left ankle within 0.40 m of the right foot.
    On the DTM's edges those limits always held (where the motion terms were trained on the same
    stance); off the edges they bind every pair of the two legs at once, and a CMU 85 person
    self-calibrated on that body paid some 400 nats a frame for parting the feet (``dtm-eval``,
    HDM05 -> CMU 85 jump + twist, calibrated stream 99.13 % before the off-edge limits, 82.76 %
    with them on every pair). Measured and not kept: reach limits run through the trunk instead
    of that link (the tree's pieces joined again by other links) -- they loosen the limits on the
    edges too, and the generic bodies there labelled worse (``dtm-eval`` markers: the MoCap
    Toolbox walk with gaps 97.8 -> 73.4 %, CMU 85's breakdance clean 100 -> 97.0 %; CMU 85 ->
    HDM05 calibrated 100 -> 92.7 %)."""
    M = parents.size
    keep = (parents >= 0) & ~limb_links(parents, segment, spread, mirror_pairs)
    child = np.flatnonzero(keep)
    graph = coo_matrix((np.ones(child.size), (child, parents[child])), shape=(M, M))
    _, piece = connected_components(graph, directed=False)
    return piece[:, None] == piece[None, :]


#: an unpaired point is on the midline when its distances to the mirror pairs' two points differ
#: by at most this share of their mean (median over the pairs; shared marker sets: midline markers
#: 0.7-2.7 %, the right back / scapula markers 12-15 %)
MIDLINE_ASYMMETRY = 0.05


def midline(length: np.ndarray, mirror_pairs: np.ndarray | None) -> np.ndarray:
    """(M,) whether each label is a midline point: unpaired (no mirror partner) and about as far
    from the left point of a mirror pair as from the right one (median over the pairs of the
    difference of the mean distances ``length`` (M, M), relative to their mean, at most
    :data:`MIDLINE_ASYMMETRY`). A marker set names some markers without a partner although they
    sit on one side -- CMU's and HDM05's right back marker (RBAC), placed so that the two sides
    can be told apart: 10 cm from the right shoulder marker, 30 cm from the left one."""
    M = length.shape[0]
    side, mate = sides(M, mirror_pairs)
    pairs = np.asarray(mirror_pairs if mirror_pairs is not None else np.zeros((0, 2)), dtype=np.int64).reshape(-1, 2)
    out = side == 0
    if not len(pairs):
        return out
    left, right = length[:, pairs[:, 0]], length[:, pairs[:, 1]]
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        asym = np.nanmedian(np.abs(left - right) / (0.5 * (left + right)), axis=1)
    return out & (np.nan_to_num(asym, nan=np.inf) <= MIDLINE_ASYMMETRY)


def mirror_moved(spread: np.ndarray, steady: np.ndarray, iu: np.ndarray, ju: np.ndarray, M: int,
                 mirror_pairs: np.ndarray, length: np.ndarray) -> np.ndarray:
    """For the pairs ``iu``, ``ju``: True where a pair on one side of the body (two points of one
    side, or one of a side and a :func:`midline` point; ``length`` (M, M) the pairs' mean
    distances) has a mirror image that was seen and moved: not
    ``steady`` (the segment tests, per pair of ``iu``, ``ju``) and its distance spread
    (``spread`` (M, M), within-clip sd; NaN where never seen together) more than
    :data:`MIRROR_RIGID_RATIO` times the pair's own, or :data:`MIRROR_RIGID_SLACK_M` more.

    The body is left-right symmetric: whether two points lie on one segment is a property of
    the body, not of one side. A pair that held rigid while its mirror image moved freely was
    held by the frames it was seen in, not by a bone. A gappy take shows a pair only where both
    markers happened to be seen, and those frames can miss a side's motion altogether: HDM05's
    first half with half its samples hidden (gap seed 1) showed C7 and the left shoulder marker
    together in 177 frames, all before the shrug of the half's last 129, within 0.7 mm (C7 and
    the right shoulder: 18 mm over 366 frames; the gap-free half 7.9 mm over 51 mm); taken for a
    segment of 144 mm, calibrated to 5 mm, it charged the true labeling of the second half --
    the shoulders raised, C7 to the left shoulder 100-107 mm -- 30-39 nats a frame, and the
    labeler shifted the left arm's labels one along instead (the shoulder's point labelled upper
    arm). A pair whose mirror image was never seen together keeps the decision its own frames
    gave."""
    side, mate = sides(M, mirror_pairs)
    held = _pair_matrix(steady, iu, ju, M)
    mi, mj = mate[iu], mate[ju]
    placed = (side != 0) | midline(length, mirror_pairs)       # a side, or truly the midline
    one_sided = placed[iu] & placed[ju] & (side[iu] * side[ju] >= 0) & (side[iu] + side[ju] != 0)
    own = np.nan_to_num(spread[iu, ju], nan=np.inf)
    image = spread[mi, mj]
    with np.errstate(invalid="ignore"):
        moved = np.isfinite(image) & (image > np.maximum(MIRROR_RIGID_RATIO * own, own + MIRROR_RIGID_SLACK_M))
    return one_sided & moved & ~held[mi, mj]


def fit_body(stats: dict[str, np.ndarray], parents: np.ndarray, settings: BodySettings | None = None,
             joint_centres: bool = True, mirror_pairs: np.ndarray | None = None,
             leaves: Sequence[int] = ()) -> BodyModel:
    """The generic body from :func:`pair_statistics` of the training clips: segments,
    ranges, spreads and reach limits (module doc). ``joint_centres``: the points are the 14
    body points (between-person spread 5 % of a length by default) rather than markers, whose
    placement varies between sessions and labs (30 %). ``mirror_pairs`` (left, right label
    indices): the sides, for :func:`unmirrored_crossing`. ``leaves``: labels no pair of the others
    spans (:func:`spans_a_point`; a model's anonymous points: the named pairs are those of the
    model without them)."""
    s = settings or BodySettings()
    between_rel = s.between_rel if s.between_rel is not None else (0.05 if joint_centres else 0.3)
    st = stats
    M = st["mean"].shape[1]
    with np.errstate(all="ignore"), warnings.catch_warnings():   # pairs never seen together (gappy takes): NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        length = np.nanmean(st["mean"], axis=0)
        sd_clip = clip_spread(st["sd"])
        vec_max = np.nanmax(st["vec"], axis=0)
        lo, hi = np.nanmin(st["mean"], axis=0), np.nanmax(st["mean"], axis=0)
        longest = np.nanmax(st["max"], axis=0)
    iu, ju = np.triu_indices(M, 1)
    seen = np.isfinite(length[iu, ju]) & np.isfinite(sd_clip[iu, ju])
    sd_p = sd_clip[iu, ju]
    link = np.zeros((M, M), dtype=bool)
    child = np.flatnonzero(parents >= 0)
    link[child, parents[child]] = link[parents[child], child] = True
    steady = seen & (sd_p <= s.segment_abs_m) & (sd_p <= s.segment_ratio * np.nan_to_num(vec_max[iu, ju]))
    seg = steady & link[iu, ju] & ~spans_a_point(length, leaves)[iu, ju]
    if mirror_pairs is not None and len(mirror_pairs):
        seg &= unmirrored_crossing(steady, iu, ju, M, mirror_pairs)
        seg &= ~mirror_moved(sd_clip, steady, iu, ju, M, mirror_pairs, length)
    longest = np.where(np.isfinite(longest), longest, 0.0)
    segment = np.zeros((M, M), dtype=bool)
    segment[iu, ju] = segment[ju, iu] = seg
    reach = reach_limits(longest, parents)
    off_edges = reach_off_edges(parents, segment, sd_clip, mirror_pairs)
    kind = np.where(seg, SEGMENT, REACH)
    L = np.where(seg, length[iu, ju], reach[iu, ju])
    pair_lo = np.where(seg, lo[iu, ju], 0.0)
    pair_hi = np.where(seg, hi[iu, ju], reach[iu, ju])
    within = np.where(seg, np.maximum(s.within_factor * np.nan_to_num(sd_p), s.within_floor_m),
                      s.reach_sd_m)
    between = between_rel * L
    keep = seen | ~seg
    return BodyModel(n_labels=M, pairs=np.stack([iu, ju], 1)[keep], kind=kind[keep], lo=pair_lo[keep],
                     hi=pair_hi[keep], within_sd=within[keep], between_sd=between[keep],
                     reach_off_edges=off_edges[iu, ju][keep])


#: a pair spans a third point lying within this share of its length of the straight line between
#: them (the two legs of the detour through it at most this much longer than the pair)
SPAN_DETOUR = 1.05


def spans_a_point(length: np.ndarray, leaves: Sequence[int] = ()) -> np.ndarray:
    """(M, M) pairs that span a third point: one lying on the straight line between them (the
    detour through it at most ``SPAN_DETOUR`` of the pair's mean length; ``length`` (M, M)).
    The markers of one segment form a cluster on it; on a limb a point between two others is
    the joint between their segments, so such a pair is never one segment, however little its
    distance varied in the training. HDM05's standing take held the left elbow at one angle:
    upper arm to wrist varied 7 mm over 0.41 m (detour through the elbow marker 1.04) and passed
    for a segment; calibrated to a CMU 85 person, the jump + twist then paid about 9 nats a frame
    for its bending arm, and the stream exchanged the wrist bar's two markers to shorten it
    (``dtm-eval``, HDM05 -> CMU 85 jump + twist, calibrated: 94.80 -> 96.05 %, single frames
    45.4 -> 64.9 %; no other cell moved). No bone of the 14 body points spans one."""
    M = length.shape[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        detour = (length[:, :, None] + length.T[None, :, :]) / length[:, None, :]     # (i, k, j)
    eye = np.eye(M, dtype=bool)
    detour[eye[:, :, None] | eye.T[None, :, :]] = np.inf                              # k = i or k = j
    detour[:, np.asarray(leaves, dtype=np.int64), :] = np.inf                           # never the point spanned
    out = (np.nan_to_num(detour, nan=np.inf) < SPAN_DETOUR).any(axis=1)
    np.fill_diagonal(out, False)
    return out


def sides(M: int, mirror_pairs: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(side, mate)`` of ``M`` labels from ``mirror_pairs`` (left, right label indices, or
    None): side -1 left, +1 right, 0 midline; mate the mirror partner's index (itself when it
    has none)."""
    pairs = np.asarray(mirror_pairs if mirror_pairs is not None else np.zeros((0, 2)), dtype=np.int64).reshape(-1, 2)
    side = np.zeros(M)
    side[pairs[:, 0]], side[pairs[:, 1]] = -1.0, 1.0
    mate = np.arange(M)
    mate[pairs[:, 0]], mate[pairs[:, 1]] = pairs[:, 1], pairs[:, 0]
    return side, mate


def _pair_matrix(values: np.ndarray, iu: np.ndarray, ju: np.ndarray, M: int) -> np.ndarray:
    """(M, M) bool, symmetric: ``values`` of the pairs ``iu``, ``ju`` at both (i, j) and (j, i)."""
    out = np.zeros((M, M), dtype=bool)
    out[iu, ju] = out[ju, iu] = values
    return out


def unmirrored_crossing(steady: np.ndarray, iu: np.ndarray, ju: np.ndarray, M: int,
                        mirror_pairs: np.ndarray) -> np.ndarray:
    """For the pairs ``iu``, ``ju``: False where a pair joins a left and a right point
    (``mirror_pairs``: (left, right) label indices) whose mirror image -- the pair of the two
    points' mirror partners -- did not hold ``steady`` (the segment tests' distance spread) in
    the training. A bone joining the body's two sides belongs to the head or the trunk, which are
    symmetric: its mirror image is as rigid (the head's two diagonals, a shoulder and the other
    side's hip of a skeleton). Two limbs that merely held still are not: HDM05's standing take
    kept the left ankle 0.36 m from the right fifth metatarsal within 1.3 mm (the left foot
    pivoting about the right forefoot) while the right ankle to the left metatarsal varied 16 mm;
    a CMU 85 person calibrated on it then paid for every wider stance, and the stream rotated
    the right foot's labels one along (``dtm-eval``, HDM05 -> CMU 85 jump + twist, calibrated
    stream 96.05 -> 97.74 %, ``dtm-label``'s default 95.86 -> 97.62 %; no other cell moved)."""
    side, mate = sides(M, mirror_pairs)
    held = _pair_matrix(steady, iu, ju, M)
    crossing = (side[iu] * side[ju] < 0) & (mate[iu] != ju)
    return ~crossing | held[mate[iu], mate[ju]]


def edge_prior(stats: dict[str, np.ndarray], settings: BodySettings | None = None) -> np.ndarray:
    """(M, M) structure prior per edge and frame (:meth:`TripleScores.with_edge_prior
    <dtm_labeler.search.structure_search.TripleScores.with_edge_prior>`): ``beta (1 - sd / sd0)``
    for a pair whose largest within-clip distance sd is below ``sd0``, else 0 -- an edge whose
    length a motion does not change (bones, clusters, the trunk) keeps its triangle's relative
    positions the same in motions the training never showed."""
    s = settings or BodySettings()
    with np.errstate(all="ignore"):
        sd = np.nanmax(stats["sd"], axis=0)
    beta = s.segment_edge_prior * np.clip(1.0 - np.nan_to_num(sd, nan=np.inf) / s.edge_prior_sd_m, 0.0, 1.0)
    np.fill_diagonal(beta, 0.0)
    return beta


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


def window_broad_weights(broad: BroadMotion, mixtures: Sequence[GaussianMixture], triangles: np.ndarray,
                         states: np.ndarray, floor_weights: np.ndarray | None = None, min_frames: int = 20,
                         max_weight: float = 0.5, iterations: int = 50) -> tuple[np.ndarray, dict]:
    """The broad weights of a calibrated model: each triangle's ``w`` fitted again by the EM of
    :func:`broad_components`, on the calibration frames (``states`` (F, M, 6), heading-canonical
    eq. 12 states of the person's labelled window), never below the training's
    (``floor_weights``, else ``broad.weights``) nor above ``max_weight``.

    The training's held-out frames are another stretch of the same takes: they show less
    novelty than another motion will, which is why its weights sit at their floor for most
    triangles. The calibration window is a held-out stretch of the motion to be labelled, so
    its triples measure that motion's novelty for each triangle (``r_i = w q_i / ((1 - w) p_i +
    w q_i)``, ``w = mean r_i`` -- the training's EM, the Gaussians ``q`` and ``p`` kept). A
    weight only rises: a window that shows nothing new does not show that the rest of the take
    will not. Triangles with fewer than ``min_frames`` window frames showing all three points
    (with velocities) keep the training's weight. Read for the paper: the weight of a
    component of the conditional of eq. 7, the others' parameters fixed, estimated on the new
    data -- a MAP adaptation of the mixture weights (Reynolds et al. 2000) with the training's
    weight as the lower bound rather than as a prior.

    HDM05's standing take links the two feet through the structure's root triangle (LMT5,
    LTOE, RTOE) and the next one (RMT5, RTOE, LTOE); a CMU 85 person's jump and twist turns the
    feet against each other, which the standing take never showed (window median conditional
    -5.6 nats under the motion mixture against -0.3 under the broad Gaussian): the window's EM
    puts the right foot's triangles at 0.43-0.5 from 0.02."""
    base = np.asarray(broad.weights if floor_weights is None else floor_weights, dtype=np.float64)
    out = base.copy()
    frames = np.zeros(len(out), dtype=np.int64)
    for t, tri in enumerate(np.asarray(triangles)):
        X = triangle_features(states, tri)
        X = X[np.isfinite(X).all(1)]
        frames[t] = X.shape[0]
        if X.shape[0] < min_frames or base[t] >= max_weight:
            continue
        log_p = conditional_log_pdf(mixtures[t], X, t == 0)
        log_q = conditional_log_pdf(broad.gaussians[t], X, t == 0)
        out[t], _ = broad_weight(log_p, log_q, max(base[t], 0.1), iterations, (base[t], max_weight))
    raised = out > base + 1e-9
    return out, {"triangles_raised": int(raised.sum()), "triangles_measured": int((frames >= min_frames).sum()),
                 "largest_weight": float(out.max()) if out.size else 0.0}


def moments(X: np.ndarray, floor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance (plus the diagonal ``floor``) of feature rows."""
    return X.mean(0), np.cov(X, rowvar=False, bias=True) + np.diag(floor)




def conditional_log_pdf(mix: GaussianMixture, X: np.ndarray, first: bool) -> np.ndarray:
    """``log P(A | B, C)`` of eq. 12 feature rows under ``mix`` (the joint for the first triangle)."""
    out = mix.log_pdf(X)
    return out if first else out - mix.linear_map(PARENTS_MAP).log_pdf(X @ PARENTS_MAP.T)


def broad_components(structure: Structure, train_states: np.ndarray, train_codes: np.ndarray,
                     held_rows: np.ndarray, recorded: np.ndarray, fit: Callable[[np.ndarray, int], GaussianMixture],
                     floor: np.ndarray, settings: BodySettings | None = None,
                     progress: Callable[[int, int], None] | None = None,
                     joint_centres: bool = True) -> tuple[BroadMotion, dict]:
    """The broad part of every triangle's conditional, fitted on held-out frames (module doc).

    ``train_states`` / ``train_codes``: the rows the mixtures are fitted to; ``held_rows``
    marks those held out for the fit of ``(w, s)``, ``recorded`` those that are recorded
    (not augmented) -- the held-out likelihood is measured on recorded frames only.
    ``fit(X, t)`` fits triangle ``t``'s motion mixture (floored) to feature rows ``X``;
    ``floor`` is the covariance floor of the mixtures; ``joint_centres``: the points are the
    14 body points (the weight's floor, module doc)."""
    s = settings or BodySettings()
    min_w = s.min_weight if s.min_weight is not None else (MIN_WEIGHT_BODY14 if joint_centres else MIN_WEIGHT_MARKERS)
    bfloor = np.r_[np.full(9, s.broad_floor_mps ** 2), np.full(6, s.broad_floor_m ** 2)]
    gaussians, weights, scales = [], [], []
    for t, tri in enumerate(structure.triangles):
        if progress:
            progress(t, structure.n_triangles)
        ok = (train_codes[:, list(tri)] == FULL).all(axis=1)
        X_fit = triangle_features(train_states[ok & ~held_rows], tri)
        X_val = triangle_features(train_states[ok & held_rows & recorded], tri)
        X_all = triangle_features(train_states[ok], tri)
        w, scale = min_w, s.scales[len(s.scales) // 2]
        if X_fit.shape[0] >= 20 and X_val.shape[0] >= 10:
            log_p = conditional_log_pdf(fit(X_fit, t), X_val, t == 0)
            mu, cov = moments(X_fit, floor)
            best = -np.inf
            for sc in s.scales:
                g = GaussianMixture(np.ones(1), mu[None], broad_covariance(cov, sc, bfloor)[None])
                wt, ll = broad_weight(log_p, conditional_log_pdf(g, X_val, t == 0), 0.1, s.em_iterations,
                                      (min_w, s.max_weight))
                if ll > best:
                    best, w, scale = ll, wt, sc
        mu, cov = moments(X_all, floor)
        gaussians.append(GaussianMixture(np.ones(1), mu[None], broad_covariance(cov, scale, bfloor)[None]))
        weights.append(w)
        scales.append(scale)
    if progress:
        progress(structure.n_triangles, structure.n_triangles)
    return BroadMotion(np.array(weights), gaussians), {
        "weights": weights, "scales": scales, "settings": dict(asdict(s), scales=list(s.scales), min_weight=min_w)}
