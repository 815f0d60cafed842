"""One frame's labeling problem: the fitness of candidate assignments (eq. 14, 18-21, 30-31).

For an assignment ``a`` (label -> point index, or ``n`` for missing) of the frame's points
with states ``x`` (position, velocity; velocity NaN for a point seen for the first time):

    f(a) = sum_t term_t(x[a[A_t]], x[a[B_t]], x[a[C_t]])          DTM, marginalised (eq. 30-31)
                                                                    + body factor of t's edges
         + sum_{roots} log b_pos                                    unmodelled absolute positions
         + sum_{points not labelled} log b(x_p)                     clutter (background density)
         + (#labelled) log p_detect + (#missing) log(1 - p_detect)

``log b(x) = log b_pos + [x has velocity] log b_vel`` is a uniform density over the capture
volume and a velocity range. Written relative to "every point is clutter", each labelled
point gains its model term minus ``log b(x)``, so labelings with different numbers of
labelled points compare over the same dimensions. The constant ``sum_p log b(x_p)`` is
left out of :meth:`FrameProblem.fitness` (it does not change the arg max).

Heading: each candidate is canonicalised with the yaw of *its own* labelled left/right
pairs (see :mod:`dtm_labeler.model.features`), quantised to ``heading_bins`` so triangle
terms can be cached by ``(bin, triangle, i, j, k)`` for the whole frame. With an *anchor*
(:meth:`FrameProblem.anchor_heading`: the yaw of the labeling a search starts from) a
candidate whose own yaw lies within ``heading_snap_deg`` of it is canonicalised with the
anchor's yaw instead. The heading is a nuisance parameter the model is trained to tolerate
(uniform yaw jitter of a few degrees at training time); what it must catch is a gross
error -- a labeling with left and right exchanged turns its heading by tens of degrees or
180 -- and that still gets its own heading. Without the snap, a move of one marker
label turns the yaw of a 41-marker body by a fraction of a degree, which lands in
another 0.5 deg bin about half the time and costs all ``T`` triangle terms again at
that bin; with it such a move costs only the terms of its own triangles.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.dtm import TriangulatedModel
from ..model.features import FULL, MISSING, POSITION_ONLY, STATE_DIM
from .frame_kernels import TermTable, allowed_points, facing, frame_geometry, frame_terms


@dataclass(frozen=True)
class Background:
    """Clutter / missing-marker densities used by the fitness.

    Clutter positions are uniform over the capture volume; clutter velocities uniform within
    ``+-max_speed_mps`` per axis (the paper's clutter), plus the volume's fixed reflections
    (floor tape, a force plate's edge, a prop): a share ``fixed_share`` of the velocity density
    in a Gaussian of ``fixed_speed_mps`` per axis about 0, for points that stay put for good.

    Why: with a label's triangle neighbours hidden, every term of that label is marginalised
    (eq. 30-31) and a point scores only the label's gain over clutter. A body marker's velocity
    marginal puts much of its mass near 0, the uniform clutter very little: a still point looks
    ~9 nats likelier on the body, so a fixed reflection takes the label of a marker whose
    neighbours are hidden and the hold prior keeps it there. The fixed part takes
    :meth:`fixed_loss` back from such a point (9 nats perfectly still at a share of 0.002, 4.5
    at 6 cm/s, nothing above ~10 cm/s).

    A body marker stays put too -- a foot in stance -- and its instantaneous velocity is the
    reflection's. What tells them apart is how long (:mod:`dtm_labeler.labeling.rest_clock`): the
    loss is paid only by a point resting beyond its label's limit
    (:meth:`TriangulatedModel.rest_limits`: ``fixed_after_s``, or 1.5 x the label's longest rest in
    the training takes), through :meth:`FrameProblem.rest_term`. With ``fixed_after_s`` 0 and a
    model without training rests every still point pays (the first, instantaneous form: on
    ``dtm-eval``'s clean takes it cost up to 12 points). ``fixed_share`` 0: the paper's clutter,
    bit for bit."""

    volume_m3: float = 60.0            # capture volume for the uniform position density
    max_speed_mps: float = 4.0         # clutter velocities uniform in a cube of this half-width
    detection_probability: float = 0.95
    fixed_share: float = 0.002         # share of the clutter velocity density at rest (fixed reflections)
    fixed_speed_mps: float = 0.02      # their measured speed spread per axis
    fixed_after_s: float = 2.0         # ... paid only by points resting this long (and their label's limit)

    def __post_init__(self) -> None:
        if not self.volume_m3 > 0 or not self.max_speed_mps > 0:
            raise ValueError("clutter volume and speed range must be positive")
        if not 0.0 < self.detection_probability < 1.0:
            raise ValueError("detection probability must be in (0, 1)")
        if not 0.0 <= self.fixed_share < 1.0 or not self.fixed_speed_mps > 0 or not self.fixed_after_s >= 0:
            raise ValueError("the fixed reflections' share must be in [0, 1), their speed spread positive "
                             "and their rest time >= 0")

    def fixed_loss(self, v: np.ndarray) -> np.ndarray:
        """(n,) nats the fixed reflections take from labelling a point with velocity ``v`` (n, 3)
        (NaN rows: 0): the log-ratio of the clutter velocity density with and without its fixed
        part, ``log1p(share N(v) / U)`` -- 0 wherever the Gaussian underflows, about 9 for a
        perfectly still point at a share of 0.002."""
        v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(v.shape[0])
        ok = np.isfinite(v).all(1)
        if self.fixed_share <= 0 or not ok.any():
            return out
        sd2 = self.fixed_speed_mps ** 2
        w = v[ok]
        log_n = -0.5 * (w * w).sum(1) / sd2 - 1.5 * np.log(2.0 * np.pi * sd2)
        out[ok] = np.log1p(self.fixed_share * np.exp(log_n - self.log_velocity))
        return out

    @property
    def log_position(self) -> float:
        return -float(np.log(self.volume_m3))

    @property
    def log_velocity(self) -> float:
        return -float(np.log((2.0 * self.max_speed_mps) ** 3))


class FrameProblem:
    """Fitness of assignments for one frame; caches triangle terms across the whole search."""

    def __init__(self, model: TriangulatedModel, states: np.ndarray, background: Background,
                 heading_hint: float | None = None, heading_snap_deg: float = 0.0,
                 rest_s: np.ndarray | None = None):
        states = np.asarray(states, dtype=np.float64).reshape(-1, STATE_DIM)
        self.rest_s = rest_s                       # (n,) how long each point has stayed put, if known
        self.model = model
        self.n = states.shape[0]
        self.M = model.n_labels
        self.background = background
        self.heading_hint = 0.0 if heading_hint is None or not np.isfinite(heading_hint) else float(heading_hint)
        self.snap = float(np.radians(heading_snap_deg))
        self.anchor: float | None = None           # yaw that candidates within ``snap`` of it are scored at
        self.states = np.empty((self.n + 1, STATE_DIM))                        # row n = missing
        self.states[:-1] = states
        self.states[-1] = np.nan
        # observation codes; distances, 0 for "missing" (never too far) and unseen points
        self.codes, self.dist = frame_geometry(self.states, FULL, POSITION_ONLY, MISSING)
        self.bounds = np.ascontiguousarray(model.distance_bounds, dtype=np.float64)
        self._xy = np.ascontiguousarray(self.states[:, :2])
        self.bins = model.heading_bins
        self.T = model.structure.n_triangles
        self.tri = np.ascontiguousarray(model.triangles, dtype=np.int64)
        self._all_triangles = np.arange(self.T, dtype=np.int64)
        self.pairs = model.heading_pairs          # for the yaw of a candidate
        self.mirror_pairs = model.mirror_pairs    # every left/right pair (mirror moves, yaw fallback)
        b = background
        has_v = self.codes[:-1] == 2
        # gain of labelling point p (relative to it being clutter), before model terms
        log_detect, log_pos = np.log(b.detection_probability), b.log_position
        self.label_gain = np.empty(self.n + 1)
        self.label_gain[:-1] = np.where(has_v, log_detect - (log_pos + b.log_velocity), log_detect - log_pos)
        self._rest = self._rest_inputs(rest_s)
        self.label_gain[-1] = np.log1p(-b.detection_probability)
        self.cache = TermTable()
        self.evaluations = 0

    # -- heading -------------------------------------------------------------------------
    def yaw(self, pop: np.ndarray) -> np.ndarray:
        """Facing yaw of each candidate from its labelled left/right pairs: the stable
        (heading) pairs where any is complete, else any left/right pair, else the hint."""
        return self._facing(pop, snap=False)[1]

    def _facing(self, pop: np.ndarray, snap: bool = True) -> tuple[np.ndarray, np.ndarray]:
        anchor = self.anchor if snap and self.anchor is not None else np.nan
        return facing(np.ascontiguousarray(pop, dtype=np.int64), self._xy, self.pairs, self.mirror_pairs,
                      self.heading_hint, anchor, self.snap, self.bins)

    def heading_bin(self, yaw: np.ndarray) -> np.ndarray:
        step = 2.0 * np.pi / self.bins
        return np.mod(np.rint(yaw / step), self.bins).astype(np.int64)

    def anchor_heading(self, ind: np.ndarray) -> None:
        """Anchor the heading on the labeling ``ind`` (M,): from now on a candidate whose
        yaw is within ``heading_snap_deg`` of ``ind``'s is canonicalised with ``ind``'s yaw
        (module doc). Clears the term cache (its bins may change meaning)."""
        if self.snap <= 0:
            return
        self.anchor = float(self.yaw(np.asarray(ind, dtype=np.int64).reshape(1, -1))[0])
        self.cache = TermTable()

    def candidate_bins(self, pop: np.ndarray) -> np.ndarray:
        """Heading bin each (P, M) candidate is scored at: its own yaw, or the anchor's
        where they are within the snap radius."""
        return self._facing(pop)[0]

    # -- fitness -------------------------------------------------------------------------
    def triangle_table(self, pop: np.ndarray, bins: np.ndarray, triangles=None) -> np.ndarray:
        """(P, len(triangles)) terms (roots included) for assignments ``pop`` at heading ``bins``."""
        ts = self._all_triangles if triangles is None else np.atleast_1d(np.asarray(triangles, dtype=np.int64))
        pop = np.ascontiguousarray(pop, dtype=np.int64)
        bins = np.ascontiguousarray(bins, dtype=np.int64)
        return self.cache.population_terms(pop, bins, self.tri, ts, self.n + 1, self.T, self._compute)

    def triple_terms(self, keys: np.ndarray) -> np.ndarray:
        """Terms of the frame's term-cache ``keys`` (:meth:`term_key`; -1: no triple, -inf), computed
        once per frame (one kernel call for the new ones). What the max-product DP
        (:mod:`dtm_labeler.search.dtm_dp`) evaluates."""
        return self.cache.terms(np.asarray(keys, dtype=np.int64).reshape(-1), self._compute)

    def term_key(self, bins, ts, i, j, k) -> np.ndarray:
        """Term-cache keys of triangles ``ts`` with points ``(i, j, k)`` (``n`` = missing) at
        heading ``bins`` (broadcast arrays)."""
        n1 = self.n + 1
        return (((np.asarray(bins) * self.T + ts) * n1 + i) * n1 + j) * n1 + k

    def _compute(self, keys: np.ndarray) -> np.ndarray:
        """Terms of new keys: one compiled call (:func:`frame_terms`) for the triples' canonical
        states, whatever their observation patterns, with the broad part and the edges' body
        factor (:meth:`TriangulatedModel.edge_terms`) folded in."""
        out = frame_terms(np.ascontiguousarray(keys, dtype=np.int64), self.states, self.codes, self.dist,
                          self.n + 1, self.T, self.bins, self.background.log_position, *self.model.kernel_tables)
        if self._rest is not None:
            out -= self.rest_term(keys)
        self.evaluations += keys.size
        return out

    def _rest_inputs(self, rest_s):
        """What :meth:`rest_term` reads, or None when no point this frame could pay it (the
        paper's clutter; every term as the kernel computes it)."""
        b = self.background
        if b.fixed_share <= 0 or not self.n:
            return None
        limit = self.model.rest_limits(b.fixed_after_s)
        rest = np.zeros(self.n) if rest_s is None else np.asarray(rest_s, dtype=np.float64).reshape(-1)
        resting = rest >= limit.min()
        if not resting.any():                      # the usual frame: nobody has rested that long
            return None
        loss = b.fixed_loss(self.states[:-1, 3:6])
        if not (loss[resting] > 0).any():
            return None
        return np.r_[loss, 0.0], np.r_[rest, -np.inf], limit

    def rest_term(self, keys: np.ndarray) -> np.ndarray:
        """(K,) nats the fixed reflections take from term-cache ``keys``: for each label the
        triangle owns (:attr:`TriangulatedModel.label_owner`) whose point has rested at least the
        label's limit (:meth:`TriangulatedModel.rest_limits`), that point's
        :meth:`Background.fixed_loss`.

        The reading: the clutter is the paper's uniform density plus a share of fixed
        reflections, which stay put for good; a body point stays put too, but a label rests
        only as long as its training showed (a foot in stance, not the head). A point resting
        beyond its label's limit is explained as well by a reflection as by that label, so
        labelling it gains the label's terms minus the fixed part's likelihood ratio. Kept in
        the DTM's form -- a term of one label added to one triangle's term -- so the CBGA, the
        DP and the region checks see it through the term cache like every other term."""
        loss, rest, limit = self._rest
        n1 = self.n + 1
        keys = np.asarray(keys, dtype=np.int64)
        pts = np.stack([(keys // (n1 * n1)) % n1, (keys // n1) % n1, keys % n1], axis=1)
        t = (keys // (n1 * n1 * n1)) % self.T
        labels = self.tri[t]
        hit = self.model.label_owner[t] & (rest[pts] >= limit[labels])
        return (loss[pts] * hit).sum(1)

    def fitness(self, pop: np.ndarray, return_bins: bool = False):
        """Fitness (relative log-likelihood, see module doc) of (P, M) assignments."""
        pop = np.asarray(pop, dtype=np.int64)
        if pop.ndim == 1:
            pop = pop[None]
        bins = self.candidate_bins(pop)
        f = self.triangle_table(pop, bins).sum(1) + self.label_gain[pop].sum(1)
        if self.model.body_cross is not None:      # calibrated rigid pairs that are not edges (model/body.py)
            f = f + self.model.body_cross(pop, self.dist, self.n)
        if self.model.body_handedness is not None:  # marker clusters shown mirrored (model/body.py)
            f = f + self.model.body_handedness(pop, self.states[:, :3])
        if self.model.body_order is not None:       # a marker bar's ends exchanged (model/body.py)
            f = f + self.model.body_order(pop, self.states[:, :3])
        if self.model.body_twist is not None:       # hips exchanged under the shoulders (model/body.py)
            f = f + self.model.body_twist(pop, self.states[:, :3])
        return (f, bins) if return_bins else f

    def plausible(self, pop: np.ndarray, labels: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Whether giving ``labels[k]`` the point ``points[k]`` in row ``pop[k]`` keeps every
        triangle neighbour of that label within the model's distance bound (the search's
        domain constraint; see :attr:`TriangulatedModel.distance_bounds`)."""
        d = self.dist[points[:, None], pop]                          # (K, M) to every label's point
        return ~(d > self.bounds[labels]).any(axis=1)

    def allowed(self, ind: np.ndarray) -> np.ndarray:
        """(M, n+1): label ``l`` may take point ``p`` given the rest of ``ind`` (distance
        bounds to its assigned triangle neighbours); "missing" always allowed."""
        return allowed_points(self.dist, np.ascontiguousarray(ind, dtype=np.int64), self.bounds, self.n)

    def empty_assignment(self) -> np.ndarray:
        return np.full(self.M, self.n, dtype=np.int64)
