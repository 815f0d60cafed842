"""Motion-independent body terms on the DTM's edges, and the broad motion component.

Why. The per-triangle motion mixtures (eq. 6-7, 12) describe the poses and speeds a few
recordings showed. On a motion they never showed, the true labeling falls in their tails and
a wrong one -- legs exchanged below the hips, an arm chain shifted by one marker, a wrist
left out as clutter -- may fit them better. What does not change between motions is the
body: the distance between two points on one rigid segment (a bone, a marker cluster on one
segment) is the same for one person whatever they do, and no two points are farther apart
than the chain of segments between them allows.

The model (extending eq. 5, 14 and 18-20). Each triangle ``t`` of the DTM keeps its motion
term ``log P(A_t | B_t, C_t)`` and gains a body factor over the edges it *introduces*: in a
decomposable triangulated model every edge enters exactly once -- the first triangle's three
edges, then the two edges ``(A_t, B_t)``, ``(A_t, C_t)`` of each new vertex -- so the body
factors are attached without counting an edge twice, and the fitness keeps the DTM's form

    log P(X | G) = sum_t [ log P(A_t | B_t, C_t) + sum_{(u,v) introduced by t} b_uv(|x_u - x_v|) ]

with, per edge, a dead-zone quadratic in the distance ``d``:

    b_uv(d) = -1/2 (max(0, lo_uv - d, d - hi_uv) / sd_uv)^2

* a **segment** pair (rigid: its distance hardly varies within any training recording) has
  ``[lo, hi]`` = the range of its length over the training people (one value for a calibrated
  person) and ``sd`` = the within-person spread, widened for people outside the training set;
* any other pair has a **reach limit**: ``lo = 0``, ``hi`` = the longest chain of segments
  between the two points (path lengths along the most rigid tree), so only anatomically
  impossible distances cost anything.

``b`` is 0 wherever the body allows the distance, so it only ever subtracts: a factor on the
clique (a product of experts with the motion term), not a density of its own, and labelings
with different numbers of labelled points keep comparing over the same dimensions
(:mod:`dtm_labeler.search.problem`). It depends on distances only: no heading, no velocity.

Whose lengths. Segment lengths hold for one person. A generic body (lengths over the training
people) applies only its reach limits: measured on people outside the training set (another
lab's joint centres from surface markers, other proportions) its segment ranges cost right
labelings more than they save (cross-subject stream 99.9 % without them, 85 % with them), so
the segment terms wait for a subject calibration (:mod:`dtm_labeler.training.calibrate`),
which gives the person's own lengths; :attr:`BodyModel.applied_kinds` says which apply. The
broad motion component (below) is stored with the model and applies from the calibration on
too: with the generic body its tails also make a ghost near the body cheap to label (flicker
demo: ghosts rejected 91 % without, 67 % with it), with the person's segment lengths they do
not (2 hidden + 2 ghosts: 99.5 / 99.6 % calibrated with it), and the poses the training never
showed stop being vetoed (leave-one-subject-out, calibrated: subject 5 37.5 -> 99.5 %, subject
55 82.2 -> 100 %, subject 9 74.2 -> 84.6 %; 240 stream frames). One labelling opens it before a
calibration (:attr:`TriangulatedModel.broad_open <dtm_labeler.model.dtm.TriangulatedModel>`): the
first round of a self-calibration tried again after every attempt failed its check
(:func:`dtm_labeler.training.calibrate.auto_calibrate`) -- a model of one motion otherwise never
labels, and so never measures, a limb in a pose that motion did not show.

Missing markers (eq. 30-31): an edge with an unobserved end point has no term (factor 1). This
is exact where the motion density of the missing point lies inside the distances the body
allows (``exp(b) = 1`` there, so integrating the point out leaves the motion marginal of
eq. 30-31 unchanged) and an upper bound otherwise -- the same approximation as eq. 31. The 27
observation patterns, the CBGA, the max-product DP of the region checks and the conditionals
keep working unchanged.

The broad motion component. The mixtures must not veto an unseen pose. Each triangle's
conditional becomes a two-part mixture (extending eq. 5 / 13)

    P(A_t | B_t, C_t) = (1 - w_t) P_motion(A_t | B_t, C_t) + w_t P_broad(A_t | B_t, C_t)

(the joint of the first triangle likewise), with ``P_broad`` the conditional of one Gaussian
``N(mu_t, s^2 Sigma_t + diag(floor))`` around the moment-matched Gaussian of the triangle's
training features (:class:`BroadMotion`). Mixing the *conditionals* rather than adding a
component to the joint mixture matters: in a joint mixture, parents that fit the training
motion well make the posterior put all weight on the sharp components, under which a new
position of ``A`` is impossible. Here a pose the training never showed costs at most about
``-log w_t - log P_broad`` nats per triangle, a wrong bone length ``z^2 / 2`` more for each edge
it breaks. ``w_t`` and ``s`` are fitted by EM on held-out frames
(:mod:`dtm_labeler.training.body_fit`). Both parts are marginalised the same way (eq. 30-31:
a missing ``A`` gives ``log((1 - w) + w) = 0``), and both go through the same compiled kernel.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .body_kernel import label_members, mirrored_quads, pair_factors, reversed_orders, twist_cosines, twist_factors
from .mixture import GaussianMixture

SEGMENT, REACH = 0, 1
KIND_NAMES = ("segment", "reach")


@dataclass
class BodyModel:
    """Per label pair ``(u, v)``, ``u < v``: kind, allowed distance range and spread.

    ``lo``/``hi`` (m): distances in ``[lo, hi]`` cost nothing; ``within_sd`` (m): spread for one
    person (skin motion, joint-centre error); ``between_sd`` (m): the extra spread for a person
    the range was not measured on (0 once calibrated). ``calibration``: provenance of the
    subject calibration (empty for a generic body). ``quads`` / ``quad_sign``: the marker
    clusters' handedness (:class:`Handedness`; none for joint centres). ``twists``: the trunk's
    twist limits (:class:`TrunkTwist`), rows ``(upper left, upper mid or -1, upper right,
    lower left, lower right)``. ``rigid_pairs`` / ``rigid_length`` / ``rigid_spread``: the rigid
    marker pairs of the one person the model was trained on -- every pair of one segment cluster
    (the segments' connected components) whose distance held within a few mm over the training
    frames, a tree link or not (median length and robust spread, m; none for joint centres, few
    for a model of several people; a calibration measures them again on its person).
    No term of the frame fitness: the offline pass over a whole take reads them as the person's
    ruler (:func:`dtm_labeler.labeling.rigid_tracks.body_pairs`). ``orders``: the marker bars'
    order (:class:`BarOrder`), rows ``(x, near, far)`` of label indices (none for joint centres).
    ``take_orders``: more such rows, read from the labels of the bar's side of the body however
    far apart the DTM's triangles put them (:func:`~dtm_labeler.training.body_fit.side_reach`);
    no term of the frame fitness: the offline pass reads them, with ``orders``, over whole
    stretches of a take (:mod:`dtm_labeler.labeling.bar_flips`).
    ``reach_off_edges``: whether each pair's reach limit holds off the DTM's edges too
    (:class:`CrossSegments`; None: all).
    """

    n_labels: int
    pairs: np.ndarray                  # (P, 2) int, u < v
    kind: np.ndarray                   # (P,) SEGMENT / REACH
    lo: np.ndarray                     # (P,)
    hi: np.ndarray                     # (P,)
    within_sd: np.ndarray              # (P,)
    between_sd: np.ndarray             # (P,)
    calibration: dict = field(default_factory=dict)
    quads: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), dtype=np.int64))   # (Q, 4) labels
    quad_sign: np.ndarray = field(default_factory=lambda: np.zeros(0))                    # (Q,) +1 / -1
    twists: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), dtype=np.int64))  # (K, 5) labels
    rigid_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))  # (R, 2), u < v
    rigid_length: np.ndarray = field(default_factory=lambda: np.zeros(0))                      # (R,) m
    rigid_spread: np.ndarray = field(default_factory=lambda: np.zeros(0))                      # (R,) m
    orders: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))       # (K, 3) labels
    take_orders: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))  # (K', 3) labels
    reach_off_edges: np.ndarray | None = None    # (P,) bool: a reach limit held off the DTM's edges too

    def __post_init__(self) -> None:
        for name in ("orders", "take_orders"):
            rows = np.asarray(getattr(self, name), dtype=np.int64).reshape(-1, 3)
            if rows.size and (rows.min() < 0 or rows.max() >= self.n_labels
                              or (np.diff(np.sort(rows, axis=1), axis=1) == 0).any()):
                raise ValueError(f"body {name} must be three distinct label indices (x, near, far)")
            setattr(self, name, rows)
        self.quads = np.asarray(self.quads, dtype=np.int64).reshape(-1, 4)
        self.quad_sign = np.asarray(self.quad_sign, dtype=np.float64).reshape(-1)
        if self.quad_sign.shape[0] != self.quads.shape[0] or not np.isin(self.quad_sign, (-1.0, 1.0)).all():
            raise ValueError("body quad_sign needs one +1 / -1 per quadruple")
        if self.quads.size and (self.quads.min() < 0 or self.quads.max() >= self.n_labels
                                or (np.diff(np.sort(self.quads, axis=1), axis=1) == 0).any()):
            raise ValueError("body quads must be four distinct label indices")
        self.twists = np.asarray(self.twists, dtype=np.int64).reshape(-1, 5)
        if self.twists.size and (self.twists.max() >= self.n_labels or self.twists[:, [0, 2, 3, 4]].min() < 0
                                 or self.twists[:, 1].min() < -1):
            raise ValueError("body twists must be label indices (the upper mid may be -1)")
        self.rigid_pairs = np.asarray(self.rigid_pairs, dtype=np.int64).reshape(-1, 2)
        R = self.rigid_pairs.shape[0]
        self.rigid_length = np.asarray(self.rigid_length, dtype=np.float64).reshape(-1)
        self.rigid_spread = np.asarray(self.rigid_spread, dtype=np.float64).reshape(-1)
        if self.rigid_length.shape[0] != R or self.rigid_spread.shape[0] != R:
            raise ValueError("body rigid pairs need one length and one spread each")
        if R and (self.rigid_pairs.min() < 0 or self.rigid_pairs.max() >= self.n_labels
                  or (self.rigid_pairs[:, 0] >= self.rigid_pairs[:, 1]).any()
                  or not np.isfinite(self.rigid_length).all() or not (self.rigid_spread > 0).all()):
            raise ValueError("body rigid pairs must be label index pairs (u, v), u < v, with finite lengths "
                             "and positive spreads")
        self.pairs = np.asarray(self.pairs, dtype=np.int64).reshape(-1, 2)
        P = self.pairs.shape[0]
        self.kind = np.asarray(self.kind, dtype=np.int64).reshape(P)
        for name in ("lo", "hi", "within_sd", "between_sd"):
            arr = np.asarray(getattr(self, name), dtype=np.float64).reshape(P)
            if not np.isfinite(arr).all() or (arr < 0).any():
                raise ValueError(f"body {name} must be finite and >= 0")
            setattr(self, name, arr)
        if P and (self.pairs.min() < 0 or self.pairs.max() >= self.n_labels
                  or (self.pairs[:, 0] >= self.pairs[:, 1]).any()):
            raise ValueError("body pairs must be label index pairs (u, v) with u < v")
        if (self.hi < self.lo).any():
            raise ValueError("body ranges need lo <= hi")
        if ((self.kind != SEGMENT) & (self.kind != REACH)).any():
            raise ValueError("body pair kinds must be 0 (segment) or 1 (reach)")
        if not (self.sd > 0).all():
            raise ValueError("body spreads must be positive")
        off = np.ones(P, dtype=bool) if self.reach_off_edges is None else np.asarray(self.reach_off_edges)
        if off.shape != (P,) or not np.isin(off, (0, 1)).all():
            raise ValueError("body reach_off_edges needs one 0 / 1 per pair")
        self.reach_off_edges = off.astype(bool)

    @property
    def sd(self) -> np.ndarray:
        """Total spread per pair: within- and between-person spread combined."""
        return np.hypot(self.within_sd, self.between_sd)

    @property
    def segments(self) -> np.ndarray:
        """(S, 2) the rigid pairs."""
        return self.pairs[self.kind == SEGMENT]

    def matrix(self, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        """(M, M) symmetric matrix of a per-pair quantity (``fill`` elsewhere)."""
        out = np.full((self.n_labels, self.n_labels), fill)
        out[self.pairs[:, 0], self.pairs[:, 1]] = values
        out[self.pairs[:, 1], self.pairs[:, 0]] = values
        return out

    def pair_index(self) -> np.ndarray:
        """(M, M) row of each pair in :attr:`pairs`, -1 where none."""
        idx = np.full((self.n_labels, self.n_labels), -1, dtype=np.int64)
        r = np.arange(self.pairs.shape[0])
        idx[self.pairs[:, 0], self.pairs[:, 1]] = r
        idx[self.pairs[:, 1], self.pairs[:, 0]] = r
        return idx

    def with_noise(self, position_sd_m: float) -> "BodyModel":
        """Widened by i.i.d. measurement noise of ``position_sd_m`` per coordinate (the
        distance between two noisy points scatters by about sqrt(2) sd)."""
        if position_sd_m <= 0:
            return self
        return replace(self, within_sd=np.hypot(self.within_sd, np.sqrt(2.0) * position_sd_m))

    def first_labels(self, n: int) -> "BodyModel":
        """The terms among labels ``0 .. n-1`` only: every pair, quadruple, twist and bar order
        that names a later label dropped (a model without its anonymous points,
        :meth:`~dtm_labeler.model.dtm.TriangulatedModel.named_only`: they are its last labels)."""
        if n >= self.n_labels:
            return self

        def rows(a: np.ndarray) -> np.ndarray:
            return (a < n).all(1) if a.size else np.zeros(a.shape[0], dtype=bool)
        p, q, r = rows(self.pairs), rows(self.quads), rows(self.rigid_pairs)
        return replace(self, n_labels=n, pairs=self.pairs[p], kind=self.kind[p], lo=self.lo[p], hi=self.hi[p],
                       within_sd=self.within_sd[p], between_sd=self.between_sd[p],
                       reach_off_edges=self.reach_off_edges[p], quads=self.quads[q], quad_sign=self.quad_sign[q],
                       twists=self.twists[rows(self.twists)], rigid_pairs=self.rigid_pairs[r],
                       rigid_length=self.rigid_length[r], rigid_spread=self.rigid_spread[r],
                       orders=self.orders[rows(self.orders)], take_orders=self.take_orders[rows(self.take_orders)])

    # -- model file ------------------------------------------------------------------
    @property
    def applied_kinds(self) -> tuple[int, ...]:
        """The pair kinds whose terms the labeler applies: segments and reach limits once
        calibrated to a person, reach limits only for a generic body (module doc)."""
        return (SEGMENT, REACH) if self.calibration else (REACH,)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"body_pairs": self.pairs.astype(np.int64), "body_kind": self.kind.astype(np.int64),
                "body_lo": self.lo, "body_hi": self.hi, "body_within_sd": self.within_sd,
                "body_between_sd": self.between_sd, "body_quads": self.quads, "body_quad_sign": self.quad_sign,
                "body_twists": self.twists, "body_rigid_pairs": self.rigid_pairs,
                "body_rigid_length": self.rigid_length, "body_rigid_spread": self.rigid_spread,
                "body_orders": self.orders, "body_take_orders": self.take_orders,
                "body_reach_off_edges": self.reach_off_edges.astype(np.int64)}

    @classmethod
    def from_arrays(cls, arrays: dict, n_labels: int, calibration: dict | None = None) -> "BodyModel":
        try:
            kw = {k: np.asarray(arrays["body_" + k]) for k in ("pairs", "kind", "lo", "hi", "within_sd",
                                                                 "between_sd")}
        except KeyError as e:
            raise ValueError(f"body terms lack {e.args[0]!r}") from None
        for k in ("quads", "quad_sign", "twists", "rigid_pairs", "rigid_length", "rigid_spread", "orders",
                  "reach_off_edges", "take_orders"):
            # format 3: handedness, 4: twists, 5: the person's rigid pairs, 6: bar orders (older: none),
            # 8: which reach limits hold off the edges (older: all), 9: the take pass's bar orders (older: none)
            if "body_" + k in arrays:
                kw[k] = np.asarray(arrays["body_" + k])
        for k, a in kw.items():
            if a.dtype == object or not np.issubdtype(a.dtype, np.number):
                raise ValueError(f"body_{k} must be a numeric array")
        return cls(n_labels=n_labels, calibration=dict(calibration or {}), **kw)


class EdgeTerms:
    """The body factors of a structure, laid out per triangle for vectorised evaluation.

    Triangle ``t = (A, B, C)`` has edge slots ``(A, B)``, ``(A, C)``, ``(B, C)``; the slots of
    edges it does not introduce (``(B, C)`` for ``t > 0``) and of pairs without a term have
    ``inv_sd = 0`` and contribute nothing.
    """

    SLOTS = ((0, 1), (0, 2), (1, 2))

    def __init__(self, body: BodyModel, triangles: np.ndarray, kinds: tuple[int, ...] = (SEGMENT, REACH)):
        tri = np.asarray(triangles, dtype=np.int64)
        T = tri.shape[0]
        self.lo = np.zeros((T, 3))
        self.hi = np.zeros((T, 3))
        self.inv_sd = np.zeros((T, 3))
        idx = body.pair_index()
        sd = body.sd
        for s, (i, j) in enumerate(self.SLOTS):
            rows = idx[tri[:, i], tri[:, j]]
            live = rows >= 0
            live[live] = np.isin(body.kind[rows[live]], kinds)
            if s == 2:
                live[1:] = False                      # (B_t, C_t) was introduced by an earlier triangle
            self.lo[live, s] = body.lo[rows[live]]
            self.hi[live, s] = body.hi[rows[live]]
            self.inv_sd[live, s] = 1.0 / sd[rows[live]]
        self.active = bool((self.inv_sd > 0).any())

    def __call__(self, tri: np.ndarray, d: np.ndarray, observed: np.ndarray) -> np.ndarray:
        """Body factor of triangles ``tri`` (n,) for slot distances ``d`` (n, 3) whose two end
        points are observed where ``observed`` (n, 3) is true."""
        lo, hi, w = self.lo[tri], self.hi[tri], self.inv_sd[tri]
        x = np.maximum(np.maximum(lo - d, d - hi), 0.0) * w
        return -0.5 * np.where(observed, x * x, 0.0).sum(axis=1)

    def bounds(self, triangles: np.ndarray, n_labels: int, n_sd: float = 6.0) -> np.ndarray:
        """(M, M) largest distance the body terms leave plausible (``hi + n_sd sd``) for the
        edges that carry one, inf elsewhere."""
        out = np.full((n_labels, n_labels), np.inf)
        tri = np.asarray(triangles, dtype=np.int64)
        for s, (i, j) in enumerate(self.SLOTS):
            live = self.inv_sd[:, s] > 0
            u, v = tri[live, i], tri[live, j]
            b = self.hi[live, s] + n_sd / self.inv_sd[live, s]
            out[u, v] = np.minimum(out[u, v], b)
            out[v, u] = np.minimum(out[v, u], b)
        return out


class CrossSegments:
    """Body factors of the rigid pairs the triangulation does not hold as an edge.

    A DTM keeps ``2M - 3`` of the ``M (M - 1) / 2`` pairs as edges; a marker cluster on one
    segment (a wrist bar, the forearm marker, the hand marker) is rigid in every pair, but only
    some of those pairs are edges, and the ones that tell two neighbouring markers apart may
    not be. Once the body is calibrated to a person (segments applied, module doc), every
    calibrated segment pair that is not an edge of any triangle gets the same dead-zone
    quadratic ``b_uv`` as an edge, as one more factor of the product of experts:

        log P(X | G) = sum_t [ ... eq. 14 + edge factors ... ] + sum_{(u,v) cross} b_uv(|x_u - x_v|)

    A missing end drops the factor (exact where the motion density of the missing point lies
    within the calibrated length, as for the edges; eq. 30-31 unchanged). The factor is not a
    term of any triangle, so it is added to a labeling's fitness after the triangle terms
    (:meth:`dtm_labeler.search.problem.FrameProblem.fitness`): the CBGA, the hill-climb and the
    confidences see it; the max-product DP of the region checks does not (its relabelling is
    re-scored by the full fitness and kept only when that rises). Measured (HDM05 41 markers,
    model of the take's first 70 % calibrated on it, the last 30 % with 3 hidden + 2 ghosts +
    1 mm, 1000 frames flicker / 250 gaps): 94.9 -> 97.2 % and 95.3 -> 96.9 % (search errors 28 -> 4);
    the wrist bars' exchange that remains is the take's own: its left forearm marker sits 6 mm
    differently in the last 30 % (LWRA-LFRM 131 -> 125 mm, LWRB-LFRM 124 -> 130 mm).

    ``kinds``: the pair kinds held; a calibrated model holds its reach limits off the edges too
    (:class:`~dtm_labeler.model.dtm.TriangulatedModel`), so that no labelled point lies farther
    from any other than the chain of the person's segments between them allows. On the edges
    alone, a label whose triangle neighbours are all hidden is bound to nothing: with 22
    markers and half of them hidden, fixed floor reflections 2.3 m from the body held RTOE and
    LMT5 for 2-3 s while the true toe, seen, stayed unlabelled. A reach limit whose path joins
    two limbs that held still in the training (:attr:`BodyModel.reach_off_edges`,
    :func:`~dtm_labeler.training.body_fit.reach_off_edges`) holds on the edges only.
    """

    def __init__(self, body: BodyModel, triangles: np.ndarray, kinds: tuple[int, ...] = (SEGMENT,)):
        tri = np.asarray(triangles, dtype=np.int64)
        M = body.n_labels
        edge = np.zeros((M, M), dtype=bool)
        for i, j in EdgeTerms.SLOTS:
            edge[tri[:, i], tri[:, j]] = edge[tri[:, j], tri[:, i]] = True
        keep = (np.isin(body.kind, kinds) & ~edge[body.pairs[:, 0], body.pairs[:, 1]]
                & ((body.kind == SEGMENT) | body.reach_off_edges))
        self.pairs = np.ascontiguousarray(body.pairs[keep], dtype=np.int64)
        self.lo, self.hi = (np.ascontiguousarray(x[keep], dtype=np.float64) for x in (body.lo, body.hi))
        self.inv_sd = np.ascontiguousarray(1.0 / body.sd[keep], dtype=np.float64)
        self.members = label_members(self.pairs, M)          # the pairs of each label (rows against the first)
        self.active = bool(keep.any())

    def __call__(self, pop: np.ndarray, dist: np.ndarray, n: int) -> np.ndarray:
        """(P,) summed factors of (P, M) assignments (``n`` = missing) given the frame's (n+1, n+1)
        point distances."""
        return pair_factors(np.ascontiguousarray(pop, dtype=np.int64), np.ascontiguousarray(dist, dtype=np.float64),
                            int(n), self.pairs, self.lo, self.hi, self.inv_sd, *self.members)

    def labelled(self, positions: np.ndarray) -> np.ndarray:
        """(F,) summed factors of labelled frames (F, M, 3) (NaN = unseen: the factor drops)."""
        d = np.linalg.norm(positions[:, self.pairs[:, 0]] - positions[:, self.pairs[:, 1]], axis=-1)
        x = np.maximum(np.maximum(self.lo - d, d - self.hi), 0.0) * self.inv_sd
        return -0.5 * np.where(np.isfinite(d), x * x, 0.0).sum(axis=1)


class PointFactor:
    """A body factor read from the labelled points themselves rather than from the edges'
    distances (:class:`Handedness`, :class:`BarOrder`, :class:`TrunkTwist`): one more factor of
    the product of experts, scored for a search's candidate assignments and for labelled frames
    alike. Subclasses give ``_factors(idx, pts)``: (P,) summed factors of the rows of ``idx``
    (P, M), label -> row of ``pts`` (N, 3), a NaN row being a missing point."""

    def __call__(self, pop: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """(P,) summed factors of (P, M) assignments given the frame's (n+1, 3) positions
        (row ``n``, "missing", NaN: the factor drops)."""
        return self._factors(np.ascontiguousarray(pop, dtype=np.int64), np.ascontiguousarray(xyz, dtype=np.float64))

    def labelled(self, positions: np.ndarray) -> np.ndarray:
        """(F,) summed factors of labelled frames (F, M, 3) (NaN = unseen: the factor drops)."""
        F, M = positions.shape[:2]
        return self._factors(np.arange(F * M, dtype=np.int64).reshape(F, M),
                             np.ascontiguousarray(positions, dtype=np.float64).reshape(F * M, 3))

    def _factors(self, idx: np.ndarray, pts: np.ndarray) -> np.ndarray:
        raise NotImplementedError


class Handedness(PointFactor):
    """Body factors of the marker clusters' handedness: a labeling that mirrors a cluster.

    Two neighbouring markers of one cluster (the two ends of a wrist bar, two toe markers)
    keep their distances to the rest of the cluster within a few millimetres, and the motion
    mixtures see little difference between them: exchanged, they cost the distance terms a
    few mm and the eq. 12 features a few cm, which the motion of a take the mixtures never saw
    easily outweighs (HDM05 41 markers, 3 flickering + 2 ghosts: 80 % of the wrong labels were
    the two wrist bars exchanged). What an exchange always changes is the handedness of the
    cluster: the sign of the signed volume ``det[x_b - x_a, x_c - x_a, x_d - x_a]`` of four
    neighbouring points, which no rotation changes, so no motion of a (nearly) rigid cluster
    does. The training fixes, for quadruples ``q`` of neighbouring labels (each label and three
    of the four whose distance to it varies least: its own segment's markers) that hold together
    (six distances within ``RIGID_SPREAD``) and show one sign in at least
    ``HANDEDNESS_SHARE`` of the training frames, that sign; a labeling whose points show the
    other sign pays ``HANDEDNESS_NATS`` per quadruple -- one more factor of the product of
    experts, as :class:`CrossSegments`:

        log P(X | G) = ... eq. 14 + edge factors ... + sum_q -w [sign V_q(X) = -s_q]

    (``w`` = ``HANDEDNESS_NATS``, 3: a frame that shows a cluster mirrored is e^3 = 20 times
    less likely than one that shows it as trained; 1 gained little on the streams below). A
    quadruple with a missing point drops its factor (eq. 30-31 unchanged). Marker sets only:
    joint centres have no rigid clusters, and the sign of four joints across a joint changes
    with the pose (:func:`~dtm_labeler.training.body_fit.handedness_quads` is not run for the
    14 body points).

    Whose handedness. The sign depends on where a lab puts its markers as much as on the body:
    a generic body keeps the training's quadruples but does not apply them; a subject
    calibration measures each quadruple's sign again on the person's frames and keeps those
    that hold (:func:`~dtm_labeler.training.calibrate.calibrated_body`; on self-labelled
    frames only those that hold with the training's sign,
    :func:`~dtm_labeler.training.calibrate.unflipped_quads`), and from then on the factor
    applies, as the segment lengths do. Measured (stream %, 2 flickering + 2 ghosts +
    1 mm unless said, inline search, handedness applied / not):

    * HDM05 41 markers, model of the take's first 70 %, calibrated on them, the next 1000
      frames: 98.79 -> 99.24 % (2 flickering), 96.12 -> 96.24 % (3 gapped);
    * applied to the generic body, within one lab it helped (CMU 85_02 -> 85_12: 84.7 ->
      93.8 %; 85_12 -> 85_02 95.0 -> 96.1 %; HDM05 itself 94.6 -> 95.4 %), across labs it
      failed: HDM05 -> CMU 85_02 46.6 -> 3.3 % (the two labs' clusters are placed with
      other handedness) -- hence calibrated bodies only.

    What a still window cannot tell: HDM05's model calibrated on CMU 85 jump + twist's first
    270 frames keeps (RELB | RFRM, RWRA, RWRB, RFIN) -- their sign holds in the standing
    training and in the standing window -- while the take's true labels show it in 68-74 % of
    frames (the hand flexes at the wrist), and the wrist bar is published exchanged in 81 of
    360 (``dtm-eval``'s calibrated cell, 97.7 %). Tried: only quadruples within one segment
    cluster (the segments' connected components, as the take pass's rigid pairs): that cell
    97.74 -> 96.17 %, CMU 85 -> HDM05 calibrated 93.62 -> 78.05 %, breakdance -> jump + twist
    100 -> 98.06 % (2026-11-28, not kept). What holds instead is the bar's order
    (:class:`BarOrder`): a calibrated body leaves the quadruples with both ends of an ordered bar
    to it, but for those within one segment cluster (:func:`quads_off_ordered_bars`).
    """

    def __init__(self, body: BodyModel):
        self.quads = np.ascontiguousarray(body.quads, dtype=np.int64).reshape(-1, 4)
        self.sign = np.ascontiguousarray(body.quad_sign, dtype=np.float64)
        self.members = label_members(self.quads, body.n_labels)   # the quadruples of each label
        self.active = bool(self.quads.shape[0])

    @staticmethod
    def volumes(x: np.ndarray) -> np.ndarray:
        """Signed volumes of (..., 4, 3) points."""
        a = x[..., 0, :]
        return np.einsum("...i,...i->...", np.cross(x[..., 1, :] - a, x[..., 2, :] - a), x[..., 3, :] - a)

    def _factors(self, idx: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """(P,) summed factors of the rows of ``idx`` (P, M), label -> row of ``pts`` (N, 3)."""
        return -HANDEDNESS_NATS * mirrored_quads(idx, pts, self.quads, self.sign, *self.members)


#: a quadruple's handedness is learnt when one sign holds in this share of the training frames
HANDEDNESS_SHARE = 0.99
#: nats a labeling pays per quadruple it shows mirrored (measured: 1 gained little, 3 best; again
#: with the rigid partners, bench_auto_calibration's 41-marker cells at 2 / 3 / 5 nats: floor moves
#: 87.4 / 93.6 / 78.2 %, HDM05 -> CMU 85 98.01 / 97.96 / 98.09 %, the other three within 0.01)
HANDEDNESS_NATS = 3.0
#: a quadruple is a cluster when its six distances spread (sd / median) at most this much
#: (one segment's markers: under 0.25; across two limbs: 0.6-0.8 in a take that moves them)
RIGID_SPREAD = 0.3


class BarOrder(PointFactor):
    """Body factors of the marker bars' order: which end of a bar lies nearer the rest of the limb.

    Some clusters hold two markers that are each other's mirror image on their segment: the two
    ends of a wrist bar (radial and ulnar styloid), equally far from the forearm marker. An
    exchange of the two costs the cluster's distances nothing, the eq. 12 features of a triangle
    a few cm, and the clusters' handedness (:class:`Handedness`) holds only while the hand does
    not flex: the quadruples that tell the two ends apart take the finger or hand marker, which
    turns about the wrist's flexion axis -- the very line between the two ends -- and shows
    either sign (CMU 85's true labels: 68-74 % of the jump + twist frames). Distances to the two
    ends do not turn with it. What holds in every pose is the order: the shoulder and upper-arm
    markers lie nearer the radial end than the ulnar end in every frame of the shared takes
    (CMU 85's jump + twist and breakdance, HDM05's standing take, both arms: 0-0.3 % of frames the
    other way, median margins 3-10 cm), as pronation turns the bar about the forearm but leaves
    the radius on the upper arm's side. The training fixes, for every *bar* -- two labels of one
    segment cluster whose distances to each other label of the cluster differ by less than
    ``BAR_TOLERANCE_M`` (median over the frames) -- the labels ``x`` near it (within two
    triangle edges of either end in the model's structure, and on the bar's side of the body:
    :func:`~dtm_labeler.training.body_fit.sided_reach`) whose nearer end is the same in at
    least ``ORDER_SHARE`` of the frames of every training clip, with a median margin of at least
    ``ORDER_MARGIN_M``; the ``ORDERS_PER_BAR`` of them with the clearest margin (median over
    robust spread) are kept as rows ``(x, near, far)``. A labeling whose points show ``x``
    nearer ``far`` pays ``ORDER_NATS`` per row, one more factor of the product of experts as
    :class:`Handedness`:

        log P(X | G) = ... eq. 14 + edge factors ... + sum_k -w [|x_x - x_near| > |x_x - x_far|]

    A row with a missing point drops its factor (eq. 30-31 unchanged). Marker sets only (joint
    centres have no bars). Whose order: as the handedness, a generic body keeps its rows but does
    not apply them, a calibrated one does (:func:`~dtm_labeler.training.calibrate.calibrated_body`
    keeps the rows the person's frames do not contradict): the order depends on where a lab puts
    its markers (HDM05's finger marker lies as near one end as the other).
    """

    def __init__(self, body: BodyModel):
        self.orders = np.ascontiguousarray(body.orders, dtype=np.int64).reshape(-1, 3)
        self.active = bool(self.orders.shape[0])

    def _factors(self, idx: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """(P,) summed factors (compiled: :func:`~dtm_labeler.model.body_kernel.reversed_orders`)."""
        return -ORDER_NATS * reversed_orders(idx, pts, self.orders)


def quads_off_ordered_bars(quads: np.ndarray, signs: np.ndarray, orders: np.ndarray,
                           cluster: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """The handedness quadruples (and signs) that do not hold both ends of a bar with an order
    (:class:`BarOrder`), and how many did.

    A bar's two ends and two more labels show one sign only while the cluster is rigid, and the
    labels that tell the ends apart sit across the joint the bar marks: the hand turns about the
    wrist's flexion axis, the line between the wrist bar's ends. HDM05's model calibrated on CMU
    85 jump + twist's first 270 frames kept (RELB | RFRM, RWRA, RWRB, RFIN), whose sign holds in
    the standing window and in 68-74 % of the take's frames; against them the bar's order lost,
    and the wrist bar stayed exchanged in 40 of 360 frames (98.33 %); with the bar left to its
    order, none (98.77 %). Quadruples that hold one end only keep telling the cluster's mirror
    image apart.

    ``cluster`` ((M,) :func:`segment_clusters`, -1 off every segment): a quadruple whose four
    labels are all of one segment cluster keeps its sign beside the order. There the other two
    labels sit on the bar's own segment or hang from it by segments, and the quadruple is the
    cluster's own shape, which the calibration measured on the person: HDM05's (LFRM, LWRA, LWRB,
    LFIN), the forearm marker on one side of the plane through the bar and the finger, holds its
    sign in 99.1 % of the take's first 70 % and 97.6 % of the rest. Both of the 41-marker stream's
    left-hand errors mirror it -- the bar's ends exchanged, and the finger exchanged with the ulnar
    end (LWRA, LWRB and LFIN are a near-isosceles triangle) -- where the order's rows see only
    the first. ``bench_stream_latency`` markers41, inline: clean 97.82 -> 98.28 %, gaps + ghosts
    and flicker + ghosts (corruption seeds 1-3) 0.3-0.5 points higher in five of six streams,
    the sixth -0.03 (``results/stream_latency.md``). CMU 85's (RELB | RFRM, RWRA, RWRB, RFIN)
    crosses the elbow, off HDM05's forearm cluster, and stays left to the order."""
    q = np.asarray(quads, dtype=np.int64).reshape(-1, 4)
    ends = np.asarray(orders, dtype=np.int64).reshape(-1, 3)[:, 1:]
    if q.shape[0] == 0 or ends.shape[0] == 0:
        return q, np.asarray(signs), 0
    both = ((q[:, None, :, None] == ends[None, :, None, :]).any(2).all(2)).any(1)      # (Q,)
    if cluster is not None:
        c = np.asarray(cluster, dtype=np.int64)[q]                                     # (Q, 4)
        both &= ~((c >= 0) & (c == c[:, :1])).all(1)
    return q[~both], np.asarray(signs)[~both], int(both.sum())


def segment_clusters(M: int, segments: np.ndarray) -> np.ndarray:
    """(M,) the rigid cluster of each label: the connected components of the body's segments
    (``segments`` (S, 2) label pairs); -1 for a label on no segment."""
    seg = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    _, comp = connected_components(coo_matrix((np.ones(len(seg)), (seg[:, 0], seg[:, 1])), shape=(M, M)),
                                   directed=False)
    on = np.zeros(M, dtype=bool)
    on[seg.reshape(-1)] = True
    return np.where(on, comp, -1)


#: two labels of a cluster are a bar when their distances to each other label of it differ less
BAR_TOLERANCE_M = 0.015
#: a label's nearer end of a bar is learnt when it is the same in this share of every clip's frames
ORDER_SHARE = 0.995
#: ... with at least this median margin (m)
ORDER_MARGIN_M = 0.01
#: labels kept per bar (the clearest margins)
ORDERS_PER_BAR = 3
#: ... and for the take pass's rows (:attr:`BodyModel.take_orders`): from the bar's side of the body
TAKE_ORDERS_PER_BAR = 4
#: nats a labeling pays per order it shows reversed (as a mirrored quadruple, HANDEDNESS_NATS)
ORDER_NATS = 3.0


class TrunkTwist(PointFactor):
    """Body factors of the trunk's twist limit: hips exchanged under shoulders that are not.

    The spine turns the shoulder girdle against the pelvis by some 30-50 degrees each way; no
    person turns it by 90. Exchanging the two hips (with the legs below them) leaves every
    distance the body terms see plausible -- the pelvis is as wide either way -- and a motion
    the mixtures never saw may fit the exchanged legs better (single frames, calibrated,
    lambada -> whirl of subject 55: the whole lower body exchanged; other people's pirouette
    and lambada). What the exchange always changes is the direction of the hip line against
    the shoulder line: the cosine of the angle between the left-to-right axis of the shoulders
    ``s`` and of the hips ``h``

        c(X) = s . h / (|s| |h|),     s = x_rs - x_ls (or x_rs - x_mid, x_mid - x_ls),  h = x_rh - x_lh

    goes from near 1 to near -1. The factor is a dead-zone quadratic in it, as the edges' body
    factor is in a distance, one more factor of the product of experts (as
    :class:`CrossSegments`):

        log P(X | G) = ... eq. 14 + edge factors ... + sum_k -1/2 (max(0, c_min - c_k(X)) / c_sd)^2

    with ``c_min`` = ``TWIST_COS_MIN`` (0: a twist of 90 degrees) and ``c_sd`` = ``TWIST_COS_SD``;
    it is 0 for every twist a spine can make (the shared recordings' truth: cosine >= 0.68, a
    pirouette's, 0.87-0.98 elsewhere). The shoulder axis falls back to one shoulder and the
    midline point between them (the neck, C7) when the other shoulder is not labelled -- else
    a labeling could escape the factor by leaving a shoulder out; with no axis on either side
    the factor drops (eq. 30-31 unchanged). It depends on the body alone, not on a person's
    proportions or a lab's marker placement (only on left and right being named as they are),
    so a generic body applies it too, as it does the reach limits. The axes come from the
    point set's names (:func:`dtm_labeler.training.body_fit.trunk_twists`): the 14 body points'
    shoulders, neck and hips, or a known marker set's shoulder, neck and pelvis markers.

    Measured (``dtm-eval`` generalisation, calibrated on the take's first seconds, single frames:
    24 frames, 336 labels per cell; without -> with): lambada -> whirl of subject 55 96.43 ->
    97.02 %, subject 5's pirouette (model of subjects 7, 9, 55) 85.71 -> 92.26 %, subject 55's
    lambada (model of 5, 7, 9) 94.64 -> 96.43 %; subject 9's run 94.94 -> 92.86 % (two search
    errors: over three search seeds 23 / 20 / 23 labels wrong without, 24 / 20 / 21 with); every
    stream cell unchanged. Training attaches it to the 14 body points only: on marker sets (the
    shoulder markers with C7, and each pair of pelvis markers) the 41-marker cells moved both
    ways by tens of points -- CMU 85 -> HDM05 calibrated 48.9 -> 94.1 %, but the same under
    ``dtm-label``'s default 94.1 -> 5.1 % and the floor moves 93.6 -> 37.1 %; the half-hidden
    12-marker upper body 86 -> 68 % with one search seed, 44 -> 45 % with another -- so marker
    sets keep the clusters' handedness (:class:`Handedness`) and no twist limit.
    """

    def __init__(self, body: BodyModel):
        self.twists = np.ascontiguousarray(body.twists, dtype=np.int64).reshape(-1, 5)
        self.active = bool(self.twists.shape[0])

    def cosines(self, pts: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """(P, K) cosine of the shoulder and hip axes (NaN where either is not seen) for label
        -> row ``idx`` (P, M) of points ``pts`` (N, 3) (NaN rows: not seen)."""
        return twist_cosines(np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(pts, dtype=np.float64),
                             self.twists)

    def _factors(self, idx: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """(P,) summed factors (compiled: :func:`~dtm_labeler.model.body_kernel.twist_factors`)."""
        return twist_factors(idx, pts, self.twists, TWIST_COS_MIN, TWIST_COS_SD)


#: cosine of the shoulder and hip axes below which the trunk's twist costs (0: 90 degrees)
TWIST_COS_MIN = 0.0
#: its spread: an exchange of the hips (cosine about -0.9) costs about 10 nats
TWIST_COS_SD = 0.2


def slot_distances(positions: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances (F, T, 3) of every triangle's edge slots in (F, N, 3) labelled positions and
    whether both end points are seen (F, T, 3)."""
    tri = np.asarray(triangles, dtype=np.int64)
    d = np.empty(positions.shape[:1] + (tri.shape[0], 3))
    for s, (i, j) in enumerate(EdgeTerms.SLOTS):
        d[..., s] = np.linalg.norm(positions[:, tri[:, i]] - positions[:, tri[:, j]], axis=-1)
    ok = np.isfinite(d)
    return np.where(ok, d, 0.0), ok


def broad_covariance(cov: np.ndarray, scale: float, floor: np.ndarray) -> np.ndarray:
    """``scale^2 cov + diag(floor)``: the moment-matched covariance widened, and at least
    ``floor`` (variances) in every feature dimension -- a motion that never moved a point in
    some direction (an arm swinging in the sagittal plane only) must not make moving it that
    way impossible."""
    return scale ** 2 * np.asarray(cov) + np.diag(np.asarray(floor, dtype=np.float64))


@dataclass
class BroadMotion:
    """Per triangle ``t``: the weight ``w_t`` of the broad conditional and its Gaussian (one
    component over the eq. 12 feature); see the module doc."""

    weights: np.ndarray                 # (T,) in (0, 1)
    gaussians: list                     # T single-component GaussianMixture (dim 15)

    def __post_init__(self) -> None:
        self.weights = np.asarray(self.weights, dtype=np.float64).reshape(-1)
        if len(self.gaussians) != self.weights.size:
            raise ValueError(f"{len(self.gaussians)} broad Gaussians for {self.weights.size} weights")
        if not ((self.weights > 0) & (self.weights < 1)).all():
            raise ValueError("broad weights must lie in (0, 1)")
        for g in self.gaussians:
            if g.n_components != 1 or g.dim != 15:
                raise ValueError("a broad component is one 15-D Gaussian")
        self.log_w = np.log(self.weights)
        self.log_1mw = np.log1p(-self.weights)

    def combine(self, tri: np.ndarray, motion: np.ndarray, broad: np.ndarray) -> np.ndarray:
        """``log((1 - w) exp(motion) + w exp(broad))`` per row of triangles ``tri``."""
        return np.logaddexp(self.log_1mw[tri] + motion, self.log_w[tri] + broad)

    def with_floor(self, floor: np.ndarray) -> "BroadMotion":
        """Every Gaussian's covariance plus ``diag(floor)`` (measurement noise)."""
        return BroadMotion(self.weights, [GaussianMixture(g.weights, g.means, np.asarray(g.covariances)
                                                          + np.diag(floor)) for g in self.gaussians])

    def to_arrays(self) -> dict[str, np.ndarray]:
        out = {"broad_weights": self.weights}
        for t, g in enumerate(self.gaussians):
            out[f"broad{t}_mean"] = np.asarray(g.means[0])
            out[f"broad{t}_covariance"] = np.asarray(g.covariances[0])
        return out

    @classmethod
    def from_arrays(cls, arrays: dict, n_triangles: int) -> "BroadMotion":
        try:
            w = np.asarray(arrays["broad_weights"], dtype=np.float64)
            gs = [GaussianMixture(np.ones(1), np.asarray(arrays[f"broad{t}_mean"], dtype=np.float64)[None],
                                  np.asarray(arrays[f"broad{t}_covariance"], dtype=np.float64)[None])
                  for t in range(n_triangles)]
        except KeyError as e:
            raise ValueError(f"broad components lack {e.args[0]!r}") from None
        return cls(w, gs)


__all__ = ["BarOrder", "BodyModel", "PointFactor", "BroadMotion", "EdgeTerms", "Handedness", "HANDEDNESS_SHARE", "HANDEDNESS_NATS",
           "ORDER_NATS", "SEGMENT", "quads_off_ordered_bars", "segment_clusters",
           "REACH", "KIND_NAMES", "slot_distances", "broad_covariance"]
