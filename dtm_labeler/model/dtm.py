"""The decomposable triangulated model (DTM): structure + one mixture per triangle.

Log-likelihood of a labelled frame (eq. 5, 14, 19)::

    log P(X | G) = log P(A0, B0, C0) + sum_{t>0} [ log P(A_t, B_t, C_t) - log P(B_t, C_t) ]

where ``P(B_t, C_t)`` is the triangle-``t`` mixture marginalised onto the parents (a linear
map of the 15-D feature, see :mod:`features`). This is the mathematically sound reading
of eq. 14, which writes joint triangle terms where eq. 5 has conditionals.

Missing markers (eq. 30-31): every triangle term is computed from the mixture pushed onto
what is observed of its three vertices -- a missing vertex is integrated out, a vertex
seen for the first time keeps its position and loses its velocity. As in the paper this is
exact when the missing vertex is a leaf (eq. 30) and the paper's approximation otherwise
(eq. 31: ``P(E|C)`` from the triangle marginalised over ``D``).

Body terms (:mod:`.body`, issue 13). A model may carry a :class:`~.body.BodyModel`: a factor
on the edges each triangle introduces (bone lengths, marker clusters on one segment, reach
limits), added to the triangle's term by :meth:`TriangulatedModel.edge_terms`. Models
without one (format version 1 files) score exactly as before.

Dimensions. A conditional term covers the 6 (or 3) dimensions of ``A_t``; a vertex whose
parents are all unobserved (and the first triangle) additionally has an absolute position
that no triangle models. :class:`TriangleTerms` reports such *roots* so the labeler can
give them the background position density, keeping every candidate labeling's likelihood
over the same dimensions.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field
import numpy as np

from ..motion.naming import is_unnamed
from .body import (SEGMENT, BarOrder, BodyModel, BroadMotion, CrossSegments, EdgeTerms, Handedness, TrunkTwist,
                   segment_clusters, slot_distances)
from .features import (FEATURE_DIM, MISSING, N_PATTERNS, PARENTS_MAP, STATE_DIM, TRIPLE_DIM, feature_map_for,
                       observation_state, observed_map, pattern_codes, pattern_id)
from .mixture import GaussianMixture
from .structure import Structure
from .term_kernel import mixture_terms

#: a label may rest this many times its longest rest in training before the rest tells
#: (:meth:`TriangulatedModel.rest_limits`)
REST_MARGIN = 1.5

#: rigid clusters of at most this many labels are turned as a block (4! = 24 arrangements)
MAX_TURNED_CLUSTER = 4

LOG_2PI = float(np.log(2.0 * np.pi))


class LinearMixtureDensity:
    """Density of ``y = G s`` under a mixture on ``X = F s``, evaluated straight from ``s``.

    Precomputes ``W_k = L_k^{-1} G`` and ``c_k = L_k^{-1} mu_k`` (``L_k`` the Cholesky factor
    of the mapped covariance) so a batch of triple states costs one matmul + logsumexp.
    """

    def __init__(self, mixture: GaussianMixture, G: np.ndarray):
        self.dim = G.shape[0]
        if self.dim == 0:
            self.W = np.zeros((0, G.shape[1]))
            return
        mapped = mixture.linear_map(feature_map_for(G))
        covs = np.asarray(mapped.covariances)
        L = np.linalg.cholesky(covs)
        Linv = np.linalg.inv(L)                                           # (K, m, m)
        self.K = covs.shape[0]
        self.W = np.einsum("kij,jl->kil", Linv, G).reshape(self.K * self.dim, G.shape[1])
        self.c = np.einsum("kij,kj->ki", Linv, np.asarray(mapped.means)).reshape(-1)
        logdet = 2.0 * np.log(np.diagonal(L, axis1=1, axis2=2)).sum(-1)
        self.logconst = np.log(np.asarray(mapped.weights)) - 0.5 * logdet - 0.5 * self.dim * LOG_2PI

    def __call__(self, s: np.ndarray) -> np.ndarray:
        """Log density for (n, 18) triple states (unobserved entries must be finite, e.g. 0)."""
        if self.dim == 0:
            return np.zeros(s.shape[0])
        z = (s @ self.W.T - self.c).reshape(s.shape[0], self.K, self.dim)
        a = self.logconst - 0.5 * np.einsum("nkm,nkm->nk", z, z)
        if self.K == 1:
            return a[:, 0]
        m = a.max(axis=1)
        return m + np.log(np.exp(a - m[:, None]).sum(axis=1))


class PatternTerm:
    """``log p(obs(A,B,C)) - log p(obs(B,C))`` for one observation pattern, fused: the joint's
    and the parents' whitening matrices are stacked so one matmul serves both, and the
    per-component squared norms come from a second matmul with a 0/1 summing matrix."""

    def __init__(self, joint: LinearMixtureDensity, parents: LinearMixtureDensity | None, root: bool):
        self.joint, self.parents, self.root = joint, parents, root
        parts = [d for d in (joint, parents) if d is not None and d.dim > 0]
        self.empty = not parts
        if self.empty:
            return
        self.W = np.vstack([d.W for d in parts]).T.copy()                       # (18, R)
        self.c = np.concatenate([d.c for d in parts])
        blocks, self.signs, self.consts, self.splits = [], [], [], []
        for d, sign in ((joint, 1.0), (parents, -1.0)):
            if d is None or d.dim == 0:
                continue
            blocks.append(np.kron(np.eye(d.K), np.ones((d.dim, 1))))             # (K*m, K)
            self.signs.append(sign)
            self.consts.append(d.logconst)
        R = self.W.shape[1]
        self.S = np.zeros((R, sum(b.shape[1] for b in blocks)))
        r = k = 0
        for b in blocks:
            self.S[r:r + b.shape[0], k:k + b.shape[1]] = b
            self.splits.append((k, k + b.shape[1]))
            r, k = r + b.shape[0], k + b.shape[1]

    def __call__(self, s: np.ndarray) -> np.ndarray:
        if self.empty:
            return np.zeros(s.shape[0])
        z = s @ self.W
        z -= self.c
        q = (z * z) @ self.S                                                     # (n, K_total)
        out = np.zeros(s.shape[0])
        for (a, b), sign, const in zip(self.splits, self.signs, self.consts):
            x = const - 0.5 * q[:, a:b]
            if b - a == 1:
                out += sign * x[:, 0]
            else:
                m = x.max(axis=1)
                out += sign * (m + np.log(np.exp(x - m[:, None]).sum(axis=1)))
        return out


class TriangleTerms:
    """``log P(A | B, C)`` (or the joint for the first triangle) for every observation pattern."""

    def __init__(self, mixture: GaussianMixture, first: bool):
        self.mixture = mixture
        self.first = first
        self._cache: dict[int, PatternTerm | None] = {}

    def pattern(self, pid: int) -> PatternTerm | None:
        if pid not in self._cache:
            self._cache[pid] = self._build(pid)
        return self._cache[pid]

    def _build(self, pid: int) -> PatternTerm | None:
        codes = pattern_codes(pid)
        if self.first:
            if all(c == MISSING for c in codes):
                return None
            return PatternTerm(LinearMixtureDensity(self.mixture, observed_map(codes)), None, True)
        if codes[0] == MISSING:
            return None                                   # A integrated out: contributes nothing
        parent_codes = (MISSING, codes[1], codes[2])
        root = codes[1] == MISSING and codes[2] == MISSING
        parents = None if root else LinearMixtureDensity(self.mixture, observed_map(parent_codes))
        return PatternTerm(LinearMixtureDensity(self.mixture, observed_map(codes)), parents, root)

    def evaluate(self, s: np.ndarray, pids: np.ndarray, finite: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Terms and root flags for (n, 18) triple states with (n,) pattern ids.

        Unobserved entries are ignored (zero weight in every map); pass ``finite=True`` when
        the caller already replaced their NaNs by zeros (the labeling hot path does)."""
        out = np.zeros(s.shape[0])
        roots = np.zeros(s.shape[0], dtype=bool)
        if not finite:
            s = np.nan_to_num(s, nan=0.0)
        upids = np.unique(pids)
        for pid in upids:
            term = self.pattern(int(pid))
            if term is None:
                continue
            if upids.size == 1:
                return term(s), np.full(s.shape[0], term.root)
            sel = np.flatnonzero(pids == pid)
            out[sel] = term(s[sel])
            roots[sel] = term.root
        return out, roots


FULL_PATTERN = 26          # all three vertices with position and velocity (2 + 3*2 + 9*2)


#: triangle terms kept for reuse (:func:`shared_triangle_terms`): two 41-marker models with their
#: broad parts; each holds up to ``N_PATTERNS`` built patterns (tens of kB each)
SHARED_TERMS_MAX = 160
_shared_terms: "OrderedDict[tuple, TriangleTerms]" = OrderedDict()
_shared_lock = threading.Lock()


def shared_triangle_terms(mixture: GaussianMixture, first: bool) -> TriangleTerms:
    """The :class:`TriangleTerms` of ``mixture``, shared by every model holding a mixture with
    the same numbers (least recently used first out beyond :data:`SHARED_TERMS_MAX`). A
    pattern's term is a pure function of the mixture, so sharing changes no value; it spares
    the rebuild of every pattern (eq. 30-31: ~0.2 s for a 14-point model) when a model is
    rebuilt with the same mixtures -- a subject calibration changes only the body terms, a
    reload or a ``noise_mm`` back and forth gives the same widened mixtures."""
    key = (bool(first), np.asarray(mixture.weights).tobytes(), np.asarray(mixture.means).tobytes(),
           np.asarray(mixture.covariances).tobytes(), np.asarray(mixture.means).shape)
    with _shared_lock:
        terms = _shared_terms.get(key)
        if terms is None:
            terms = _shared_terms[key] = TriangleTerms(mixture, first)
            while len(_shared_terms) > SHARED_TERMS_MAX:
                _shared_terms.popitem(last=False)
        else:
            _shared_terms.move_to_end(key)
        return terms


class BatchedTerms:
    """Every triangle's term for one observation pattern in one compiled call.

    The common case on the hot path is a batch of triples from *different* triangles with
    the same observation pattern (mostly: all three points with position and velocity).
    The whitening matrices of all triangles are zero-padded to a common width with fixed
    component slots (joint component ``k`` in columns ``[k mj, (k+1) mj)``, parents'
    component ``k`` in ``[kj mj + k mp, ...)``) so that one kernel
    (:func:`~dtm_labeler.model.term_kernel.mixture_terms`) serves the whole batch. A
    triangle whose term vanishes for the pattern (vertex A unobserved) has all-zero
    matrices and one zero component: term 0. ``root[t]``: the pattern leaves triangle
    ``t``'s absolute position unmodelled.
    """

    def __init__(self, terms: "list[TriangleTerms]", pid: int = FULL_PATTERN):
        parts = [t.pattern(pid) for t in terms]
        parts = [None if p is None or p.empty else p for p in parts]
        T = len(parts)
        live = [p for p in parts if p is not None]
        mj = {p.joint.dim for p in live}
        mp = {p.parents.dim for p in live if len(p.splits) > 1}
        if len(mj) > 1 or len(mp) > 1:
            raise ValueError(f"pattern {pid}: observed dimensions differ between triangles")
        self.mj, self.mp = (mj.pop() if mj else 1), (mp.pop() if mp else 0)
        self.kj = max([p.joint.K for p in live], default=1)
        self.kp = max([p.parents.K for p in live if len(p.splits) > 1], default=0)
        R = self.kj * self.mj + self.kp * self.mp
        self.W = np.zeros((T, TRIPLE_DIM, R))
        self.c = np.zeros((T, R))
        self.cj = np.full((T, self.kj), -np.inf)
        self.cp = np.full((T, max(self.kp, 1)), -np.inf)
        self.nj = np.ones(T, dtype=np.int64)          # components per triangle (joint, parents)
        self.np_ = np.zeros(T, dtype=np.int64)
        self.root = np.array([p is not None and p.root for p in parts], dtype=bool)
        dead = np.array([p is None for p in parts], dtype=bool)
        self.cj[dead, 0] = 0.0                       # log-sum-exp of one zero component: term 0
        off = self.kj * self.mj
        for t, p in enumerate(parts):
            if p is None:
                continue
            rj = p.joint.K * self.mj
            self.W[t, :, :rj] = p.W[:, :rj]
            self.c[t, :rj] = p.c[:rj]
            self.cj[t, :p.joint.K] = p.joint.logconst
            self.nj[t] = p.joint.K
            if len(p.splits) > 1:
                rp = p.parents.K * self.mp
                self.W[t, :, off:off + rp] = p.W[:, rj:rj + rp]
                self.c[t, off:off + rp] = p.c[rj:rj + rp]
                self.cp[t, :p.parents.K] = p.parents.logconst
                self.np_[t] = p.parents.K

    def __call__(self, s: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """Terms for (n, 18) states (unobserved entries zero) of triangles ``tri`` (n,)."""
        return mixture_terms(np.ascontiguousarray(s, dtype=np.float64),
                             np.ascontiguousarray(tri, dtype=np.int64),
                             self.W, self.c, self.cj, self.cp, self.nj, self.np_, self.mj, self.mp)


class MixedBatchedTerms:
    """Batched terms of the two-part conditional ``(1 - w) P_motion + w P_broad`` (see
    :mod:`.body`): one kernel call for the motion mixtures, one for the broad Gaussians, and
    a log-add-exp per row. ``root`` as the motion part's."""

    def __init__(self, motion: BatchedTerms, broad: BatchedTerms, mix: BroadMotion):
        self.motion, self.broad, self.mix = motion, broad, mix
        self.root = motion.root

    def __call__(self, s: np.ndarray, tri: np.ndarray) -> np.ndarray:
        return self.mix.combine(tri, self.motion(s, tri), self.broad(s, tri))


class StackedTerms:
    """Every observation pattern's :class:`BatchedTerms` in one set of padded arrays, indexed
    by pattern first: ``W[pid]`` is pattern ``pid``'s ``W`` padded to the widest pattern's
    ``R`` columns, ``off[pid]`` its first parents' column (``kj mj``), ``mj`` / ``mp`` its
    observed dimensions. What the frame kernel
    (:func:`~dtm_labeler.search.frame_kernels.frame_terms`) reads, so that one compiled call
    scores a batch of triples whatever their observation patterns (eq. 30-31: a frame with
    gaps spreads one batch over ten or more patterns, each a kernel call of its own before).
    ``empty()``: no terms (the broad part of a model without one)."""

    def __init__(self, patterns: "list[BatchedTerms]"):
        P = len(patterns)
        T = patterns[0].W.shape[0] if P else 0
        R = max((b.W.shape[2] for b in patterns), default=1)
        kj = max((b.cj.shape[1] for b in patterns), default=1)
        kp = max((b.cp.shape[1] for b in patterns), default=1)
        self.W = np.zeros((P, T, TRIPLE_DIM, R))
        self.c = np.zeros((P, T, R))
        self.cj = np.full((P, T, kj), -np.inf)
        self.cp = np.full((P, T, kp), -np.inf)
        self.nj = np.ones((P, T), dtype=np.int64)
        self.np_ = np.zeros((P, T), dtype=np.int64)
        self.mj = np.ones(P, dtype=np.int64)
        self.mp = np.zeros(P, dtype=np.int64)
        self.off = np.zeros(P, dtype=np.int64)
        self.root = np.zeros((P, T), dtype=bool)
        for p, b in enumerate(patterns):
            r = b.W.shape[2]
            self.W[p, :, :, :r] = b.W
            self.c[p, :, :r] = b.c
            self.cj[p, :, :b.cj.shape[1]] = b.cj
            self.cp[p, :, :b.cp.shape[1]] = b.cp
            self.nj[p], self.np_[p], self.root[p] = b.nj, b.np_, b.root
            self.mj[p], self.mp[p], self.off[p] = b.mj, b.mp, b.cj.shape[1] * b.mj

    @classmethod
    def empty(cls) -> "StackedTerms":
        return cls([])

    @property
    def arrays(self) -> tuple:
        """The arrays in the kernel's argument order."""
        return self.W, self.c, self.cj, self.cp, self.nj, self.np_, self.mj, self.mp, self.off


@dataclass
class TriangulatedModel:
    """Labels, structure, one mixture per triangle (eq. 12 features), settings, provenance."""

    labels: tuple[str, ...]
    structure: Structure
    mixtures: list[GaussianMixture]
    heading_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    mirror_pairs: np.ndarray | None = None      # all left/right pairs (default: heading_pairs)
    settings: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    body: BodyModel | None = None               # motion-independent edge terms (None: none)
    broad: BroadMotion | None = None            # broad part of every triangle's conditional (None: none)
    # a calibrated model's body before its calibration: what dtm-label sets the calibration to the
    # training takes' person aside for on a capture of someone else (None: not kept)
    generic_body: BodyModel | None = None
    # the broad part applies before a calibration too: a self-calibration's first labelling of a
    # motion the generic body's training never showed (training/calibrate.py ``broad_first_round``).
    # Not stored in a model file, not carried by :meth:`replace` unless given.
    broad_open: bool = False

    def __post_init__(self) -> None:
        self.labels = tuple(self.labels)
        self.heading_pairs = np.asarray(self.heading_pairs, dtype=np.int64).reshape(-1, 2)
        self.mirror_pairs = (self.heading_pairs.copy() if self.mirror_pairs is None
                             else np.asarray(self.mirror_pairs, dtype=np.int64).reshape(-1, 2))
        if self.structure.n_vertices != len(self.labels):
            raise ValueError(f"structure has {self.structure.n_vertices} vertices, model has "
                             f"{len(self.labels)} labels")
        if len(self.mixtures) != self.structure.n_triangles:
            raise ValueError(f"{len(self.mixtures)} mixtures for {self.structure.n_triangles} triangles")
        for t, m in enumerate(self.mixtures):
            if m.dim != FEATURE_DIM:
                raise ValueError(f"triangle {t}: mixture dimension {m.dim}, expected {FEATURE_DIM} (eq. 12)")
        for name, pr in (("heading", self.heading_pairs), ("mirror", self.mirror_pairs)):
            if pr.size and (pr.min() < 0 or pr.max() >= len(self.labels)):
                raise ValueError(f"{name} pair index out of range")
        self.terms = [shared_triangle_terms(m, first=(t == 0)) for t, m in enumerate(self.mixtures)]
        self.triangles = self.structure.array
        # anonymous points (``*`` names, :mod:`dtm_labeler.training.anonymous`): searched as
        # labels, published as unlabelled
        self.anonymous = np.array([is_unnamed(n) for n in self.labels], dtype=bool)
        for b in (self.body, self.generic_body):
            if b is not None and b.n_labels != len(self.labels):
                raise ValueError(f"body terms for {b.n_labels} labels, model has {len(self.labels)}")
        edges = EdgeTerms(self.body, self.triangles, self.body.applied_kinds) if self.body is not None else None
        self.body_edges = edges if edges is not None and edges.active else None
        cross = CrossSegments(self.body, self.triangles, self.body.applied_kinds) if self.body is not None and \
            SEGMENT in self.body.applied_kinds else None
        self.body_cross = cross if cross is not None and cross.active else None     # pairs off the edges
        hand = Handedness(self.body) if self.body is not None and self.body.calibration else None
        self.body_handedness = hand if hand is not None and hand.active else None  # clusters' handedness
        order = BarOrder(self.body) if self.body is not None and self.body.calibration else None
        self.body_order = order if order is not None and order.active else None     # the bars' order
        twist = TrunkTwist(self.body) if self.body is not None else None
        self.body_twist = twist if twist is not None and twist.active else None     # trunk's twist limit
        if self.broad is not None and len(self.broad.gaussians) != len(self.mixtures):
            raise ValueError(f"{len(self.broad.gaussians)} broad components for {len(self.mixtures)} triangles")
        # the broad part applies once the body is calibrated to a person (model/body.py, "Whose lengths"),
        # or where asked before that (``broad_open``)
        self.broad_applied = self.broad is not None and self.body is not None and \
            (bool(self.body.calibration) or self.broad_open)
        self.broad_terms = None if not self.broad_applied else \
            [shared_triangle_terms(g, first=(t == 0)) for t, g in enumerate(self.broad.gaussians)]

    def edge_terms(self, tri: np.ndarray, d: np.ndarray, observed: np.ndarray) -> np.ndarray:
        """Body factor (:mod:`.body`) of triangles ``tri`` (n,) given the distances ``d`` (n, 3)
        of their edge slots (A,B), (A,C), (B,C) and whether both ends are seen (n, 3); zeros
        for a model without body terms."""
        if self.body_edges is None:
            return np.zeros(np.shape(tri))
        return self.body_edges(tri, d, observed)

    def replace(self, **changes) -> "TriangulatedModel":
        """A copy with some fields replaced (mixtures, body, settings, provenance ...)."""
        kw = dict(labels=self.labels, structure=self.structure, mixtures=self.mixtures,
                  heading_pairs=self.heading_pairs, mirror_pairs=self.mirror_pairs, settings=dict(self.settings),
                  provenance=dict(self.provenance), body=self.body, broad=self.broad,
                  generic_body=self.generic_body)
        kw.update(changes)
        return TriangulatedModel(**kw)

    def named_only(self) -> "TriangulatedModel":
        """The model without its anonymous points (:mod:`dtm_labeler.training.anonymous`): what
        labels a take that does not show them (:mod:`dtm_labeler.labeling.anonymous_presence`).
        They are its last labels and leaves of the structure, joined last (their triangles the
        last ones), so the named points keep their labels' indices, triangles, mixtures and body
        terms -- those of the model ``dtm-train --ignore-unlabelled`` makes of the same capture
        (training keeps the anonymous points out of the segment clusters, the handedness quadruples
        and the bars; ``test_anonymous_points.py``). A model without anonymous points: itself."""
        n = int((~self.anonymous).sum())
        if n == self.n_labels:
            return self
        tri = self.triangles
        T = int((tri < n).all(1).sum())
        if self.anonymous[:n].any() or (tri[:T] >= n).any():
            raise ValueError("the anonymous points are not the model's last labels and triangles")
        settings = dict(self.settings)
        for key in ("loglik_per_label", "fit_reference_per_label"):   # their levels, if training measured them
            own = settings.pop("named_" + key, None)
            if own is not None:
                settings[key] = own
        for key, size in (("longest_rest_s", n), ("seen_share", n), ("broad_weights_training", T)):
            if isinstance(settings.get(key), list):
                settings[key] = settings[key][:size]
        if isinstance(settings.get("broad_component"), dict):
            settings["broad_component"] = {k: v[:T] if isinstance(v, list) and len(v) == len(tri) else v
                                           for k, v in settings["broad_component"].items()}
        pairs = [pr[(pr < n).all(1)] for pr in (self.heading_pairs, self.mirror_pairs)]
        return TriangulatedModel(
            labels=self.labels[:n], structure=Structure(tuple(map(tuple, tri[:T].tolist())), n),
            mixtures=list(self.mixtures[:T]), heading_pairs=pairs[0], mirror_pairs=pairs[1], settings=settings,
            provenance=dict(self.provenance), body=None if self.body is None else self.body.first_labels(n),
            broad=None if self.broad is None else BroadMotion(self.broad.weights[:T], list(self.broad.gaussians[:T])),
            generic_body=None if self.generic_body is None else self.generic_body.first_labels(n),
            broad_open=self.broad_open)

    @property
    def n_labels(self) -> int:
        return len(self.labels)

    def published(self, labels: np.ndarray) -> np.ndarray:
        """Label indices (-1 none) as a consumer gets them: the anonymous points
        (:attr:`anonymous`) unlabelled. ``labels`` itself when the model has none."""
        if not self.anonymous.any():
            return labels
        return np.where(self.anonymous[np.maximum(labels, 0)] & (labels >= 0), -1, labels)

    @property
    def heading_bins(self) -> int:
        return int(self.settings.get("heading_bins", 720))

    @property
    def marker_set(self) -> bool:
        """True when the body holds marker clusters: handedness quadruples
        (:class:`~.body.Handedness`), which joint centres and models without body terms have none
        of. The fast path's block turns are for marker sets, its young checks for the others."""
        return self.body is not None and bool(self.body.quads.shape[0])

    @property
    def rigid_clusters(self) -> tuple[np.ndarray, ...]:
        """The label sets of the body's small rigid clusters: the connected components of its
        segments (:func:`~.body.segment_clusters`) of 3 to ``MAX_TURNED_CLUSTER`` labels (a head's
        four markers, a wrist bar with its forearm marker) of a marker set (:attr:`marker_set`); none
        for joint centres, whose segments are bones joined at joints
        (a synthetic walker's limbs, shoulder-elbow-wrist, are such components, and turning them
        cost the flicker demo up to 1.2 points and 20 ms of p99) -- and none without body terms.
        What the fast path turns as a block (:func:`~dtm_labeler.search.label_search.cluster_turns`).
        Built once."""
        if getattr(self, "_rigid_clusters", None) is None:
            out = []
            if self.marker_set:
                comp = segment_clusters(self.n_labels, self.body.segments)
                for c in np.unique(comp[comp >= 0]):
                    members = np.flatnonzero(comp == c)
                    if 3 <= members.size <= MAX_TURNED_CLUSTER:
                        out.append(members)
            self._rigid_clusters = tuple(out)
        return self._rigid_clusters

    @property
    def pair_triangles(self) -> tuple[tuple[int, int, int], ...]:
        """(left, right, triangle) for every heading pair that shares a triangle, the first
        such triangle: where the GA's guided sampling anchors a candidate's facing
        (:func:`~dtm_labeler.search.label_search.guided_sample`). Built once: a property of
        the structure, not of a frame (rebuilt per call it was a fifth of a cold 41-marker GA)."""
        if getattr(self, "_pair_triangles", None) is None:
            tri = np.asarray(self.triangles, dtype=np.int64)
            out = []
            for a, b in np.asarray(self.heading_pairs, dtype=np.int64).reshape(-1, 2):
                hit = np.flatnonzero((tri == a).any(1) & (tri == b).any(1))
                if hit.size:
                    out.append((int(a), int(b), int(hit[0])))
            self._pair_triangles = tuple(out)
        return self._pair_triangles

    def with_noise(self, position_sd_m: float, rate_hz: float | None = None) -> "TriangulatedModel":
        """The model convolved with i.i.d. measurement noise of ``position_sd_m`` per coordinate:
        relative positions gain variance 2 sd^2 and backward-difference velocities 2 sd^2 rate^2
        (``rate_hz`` defaults to the highest training rate). Without it, 10 mm of noise at
        120 Hz (1.7 m/s of velocity noise) makes every true labeling look impossible."""
        if position_sd_m <= 0:
            return self
        rate = rate_hz or max(self.provenance.get("rates_hz") or [120.0])
        pos, vel = np.sqrt(2.0) * position_sd_m, np.sqrt(2.0) * position_sd_m * rate
        floor = np.r_[np.full(9, vel ** 2), np.full(6, pos ** 2)]
        mixtures = [GaussianMixture(np.asarray(m.weights), np.asarray(m.means),
                                    np.asarray(m.covariances) + np.diag(floor)) for m in self.mixtures]
        settings = dict(self.settings)
        reference = settings.get("fit_reference_per_label", settings.get("loglik_per_label"))
        if reference is not None:
            settings["fit_reference_per_label"] = float(reference) - self.noise_fit_drop(floor)
        return self.replace(mixtures=mixtures, provenance=dict(self.provenance, measurement_noise_m=position_sd_m),
                            body=None if self.body is None else self.body.with_noise(position_sd_m),
                            broad=None if self.broad is None else self.broad.with_floor(floor), settings=settings)

    def noise_fit_drop(self, floor: np.ndarray) -> float:
        """Nats per label by which a right labeling of frames with measurement noise of feature
        variances ``floor`` (15,) fits the widened model (:meth:`with_noise`) below how a clean
        frame fits the clean model: the yardstick of the published confidence's fit factor
        (``fit_reference_per_label``, :mod:`~dtm_labeler.labeling.confidence`) moves down by it,
        so a known system noise does not read as a motion the model never saw.

        Per mixture component ``N(mu, S)`` of a triangle's eq. 12 feature, with noise ``N(0, D)``
        (``D = diag(floor)``), the expected log density falls by
        ``1/2 [log det(S + D) - log det S]``; the conditional of eq. 13 (a joint over its
        parents' marginal) by that of the joint minus that of the parents' (``P S P^T``, ``P D
        P^T``); the first triangle is a joint. Summed over the triangles (component weights as
        the mixtures give them) and divided by the labels. Measured (a CMU walk's 14 points,
        stream mode, 480 frames): 3.9 / 6.1 / 8.7 nats per label at 5 / 10 / 20 mm, and the
        stream's expected calibration error at 10 / 20 mm 5.7 / 11.1 -> 3.2 / 4.6 %, the labels
        unchanged (the loss checks keep the training level)."""
        D = np.diag(np.asarray(floor, dtype=np.float64))
        P = PARENTS_MAP
        total = 0.0
        for t, mix in enumerate(self.mixtures):
            C = np.asarray(mix.covariances, dtype=np.float64)
            drop = 0.5 * (np.linalg.slogdet(C + D)[1] - np.linalg.slogdet(C)[1])
            if t > 0:
                PC, PD = P @ C @ P.T, P @ D @ P.T
                drop = drop - 0.5 * (np.linalg.slogdet(PC + PD)[1] - np.linalg.slogdet(PC)[1])
            total += float(np.asarray(mix.weights, dtype=np.float64) @ drop)
        return total / max(self.n_labels, 1)

    def warm_up(self) -> "TriangulatedModel":
        """Build every observation pattern's densities, the batched terms, the distance bounds
        and the heading pairs' triangles now (model load / hot reload) instead of on the first
        frame that needs them."""
        for term in self.terms + (self.broad_terms or []):
            for pid in range(N_PATTERNS):
                term.pattern(pid)
        _ = self.batched_full, self.distance_bounds, self.kernel_tables, self.pair_triangles
        self.batched_full(np.zeros((1, TRIPLE_DIM)), np.zeros(1, dtype=np.int64))     # compile (or load) the kernel
        if self.body_handedness is not None:                                          # and the handedness kernel
            self.body_handedness(np.zeros((1, self.n_labels), dtype=np.int64), np.zeros((1, 3)))
        if self.body_twist is not None:                                               # and the twist kernel
            self.body_twist(np.zeros((1, self.n_labels), dtype=np.int64), np.zeros((1, 3)))
        if self.body_cross is not None:                                               # and the pairs off the edges
            self.body_cross(np.zeros((1, self.n_labels), dtype=np.int64), np.zeros((1, 1)), 0)
        return self

    @property
    def distance_bounds(self) -> np.ndarray:
        """(M, M) largest plausible distance (m) between labels that share a triangle, inf
        otherwise: per component, |mean| + 5 sd (largest eigenvalue) of their relative
        position under the triangle's mixture and broad Gaussian; the max over components
        and triangles -- and, for an edge with a body term, at most its allowed range plus
        6 sd (the broad part alone would allow far more). A search constraint: candidates
        farther apart are never evaluated."""
        if getattr(self, "_bounds", None) is None:
            M = self.n_labels
            D = np.full((M, M), np.inf)
            best = np.zeros((M, M))
            seen = np.zeros((M, M), dtype=bool)
            # eq. 12 rows of pB - pA and pC - pA
            rows = {(1, 0): [9, 11, 13], (2, 0): [10, 12, 14]}
            for t, tri in enumerate(self.triangles):
                mix = self.mixtures[t]
                mu, cov = np.asarray(mix.means), np.asarray(mix.covariances)
                if self.broad_applied:
                    g = self.broad.gaussians[t]
                    mu, cov = np.vstack([mu, g.means]), np.concatenate([cov, g.covariances])
                maps = {}
                for (i, j), r in rows.items():
                    A = np.zeros((3, FEATURE_DIM))
                    A[np.arange(3), r] = 1.0
                    maps[(i, j)] = A
                maps[(2, 1)] = maps[(2, 0)] - maps[(1, 0)]
                for (i, j), A in maps.items():
                    m = mu @ A.T
                    c = np.einsum("ij,kjl,ml->kim", A, cov, A)
                    b = float(np.max(np.linalg.norm(m, axis=1) + 5.0 * np.sqrt(np.linalg.eigvalsh(c)[:, -1])))
                    u, v = int(tri[i]), int(tri[j])
                    best[u, v] = best[v, u] = max(best[u, v], b)
                    seen[u, v] = seen[v, u] = True
            D[seen] = best[seen]
            if self.body_edges is not None:
                D = np.minimum(D, self.body_edges.bounds(self.triangles, M))
            self._bounds = D
        return self._bounds

    def _batched_for(self, pid: int) -> "BatchedTerms | MixedBatchedTerms":
        motion = BatchedTerms(self.terms, pid)
        if not self.broad_applied:
            return motion
        return MixedBatchedTerms(motion, BatchedTerms(self.broad_terms, pid), self.broad)

    @property
    def stacked(self) -> tuple[StackedTerms, StackedTerms]:
        """Every pattern's batched terms stacked (:class:`StackedTerms`): the motion mixtures'
        and, for a model whose broad part applies, the broad Gaussians' (else empty)."""
        if getattr(self, "_stacked", None) is None:
            motion = StackedTerms([BatchedTerms(self.terms, pid) for pid in range(N_PATTERNS)])
            broad = StackedTerms([BatchedTerms(self.broad_terms, pid) for pid in range(N_PATTERNS)]) \
                if self.broad_applied else StackedTerms.empty()
            self._stacked = (motion, broad)
        return self._stacked

    @property
    def label_owner(self) -> np.ndarray:
        """(T, 3) bool: the triangle whose term carries each label's own terms (the first
        triangle holding it), per corner -- where a term of one label, not of a triple, is added
        once (:meth:`~dtm_labeler.search.problem.FrameProblem.rest_term`). Built once."""
        if getattr(self, "_label_owner", None) is None:
            tri = np.asarray(self.triangles, dtype=np.int64)
            first = np.full(self.n_labels, -1, dtype=np.int64)
            for t in range(tri.shape[0] - 1, -1, -1):        # T x 3 once per model
                first[tri[t]] = t
            self._label_owner = first[tri] == np.arange(tri.shape[0])[:, None]
        return self._label_owner

    def rest_limits(self, floor_s: float) -> np.ndarray:
        """(M,) how long a point may rest (stay within 1 cm) as each label before the rest reads
        as a fixed reflection's: ``floor_s``, or :data:`REST_MARGIN` x the label's longest rest in
        the training takes (``settings["longest_rest_s"]``, :func:`~dtm_labeler.labeling.rest_clock.longest_rests`)
        where that is longer -- a foot that stood for 12 s in training may stand as long again.
        Models trained before the training rests were kept: ``floor_s`` for every label."""
        cache = self.__dict__.setdefault("_rest_limits", {})
        if floor_s not in cache:
            longest = self.settings.get("longest_rest_s")
            out = np.full(self.n_labels, float(floor_s))
            if longest is not None and len(longest) == self.n_labels:
                out = np.maximum(out, REST_MARGIN * np.asarray(longest, dtype=np.float64))
            out.setflags(write=False)
            cache[floor_s] = out
        return cache[floor_s]

    @property
    def kernel_tables(self) -> tuple:
        """Every array the compiled frame kernel reads
        (:func:`~dtm_labeler.search.frame_kernels.frame_terms`), in its argument order: the
        stacked motion terms and their roots, the stacked broad terms and the broad weights
        ``log(1 - w)``, ``log w`` (empty where the broad part does not apply), the edges' body
        factors ``lo``, ``hi``, ``1 / sd`` (T, 3) (empty without body terms). Built once."""
        if getattr(self, "_kernel_tables", None) is None:
            motion, broad = self.stacked
            weights = (self.broad.log_1mw, self.broad.log_w) if self.broad_applied else (np.zeros(0), np.zeros(0))
            e = self.body_edges
            edges = (e.lo, e.hi, e.inv_sd) if e is not None else (np.zeros((0, 3)),) * 3
            self._kernel_tables = (*motion.arrays, motion.root, *broad.arrays,
                                   *(np.ascontiguousarray(a, dtype=np.float64) for a in (*weights, *edges)))
        return self._kernel_tables

    @property
    def batched_full(self) -> "BatchedTerms | MixedBatchedTerms":
        """Batched terms of the fully observed pattern (the hot path)."""
        if getattr(self, "_batched_full", None) is None:
            self._batched_full = self._batched_for(FULL_PATTERN)
        return self._batched_full

    def batched(self, pid: int) -> "BatchedTerms | MixedBatchedTerms":
        """Batched terms of observation pattern ``pid`` (built on first use): :class:`BatchedTerms`,
        or :class:`MixedBatchedTerms` for a model with broad components."""
        if pid == FULL_PATTERN:
            return self.batched_full
        cache = self.__dict__.setdefault("_batched_patterns", {})
        if pid not in cache:
            cache[pid] = self._batched_for(pid)
        return cache[pid]

    def triangle_terms(self, t: int, s: np.ndarray, codes: np.ndarray,
                       finite: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Term of triangle ``t`` for (n, 18) triple states and (n, 3) observation codes (the
        two-part conditional of :mod:`.body` when the model has broad components)."""
        pids = pattern_id(codes)
        val, roots = self.terms[t].evaluate(s, pids, finite)
        if not self.broad_applied:
            return val, roots
        broad, _ = self.broad_terms[t].evaluate(s, pids, finite)
        return self.broad.combine(np.full(val.shape, t), val, broad), roots

    def frame_log_likelihood(self, states: np.ndarray, background_position: float = 0.0) -> np.ndarray:
        """log P(X|G) of labelled, canonicalised frames: (F, n_labels, 6) -> (F,).

        Missing points (NaN) are marginalised; every root adds ``background_position``
        (the log density of an unmodelled absolute position; 0 gives the pure model term).
        Body terms (if any) included: the edge factors and a calibrated body's rigid pairs off
        the edges (:class:`~dtm_labeler.model.body.CrossSegments`), the clusters' handedness
        (:class:`~dtm_labeler.model.body.Handedness`), the bars' order
        (:class:`~dtm_labeler.model.body.BarOrder`) and the trunk's twist limit
        (:class:`~dtm_labeler.model.body.TrunkTwist`), as the frame fitness has them.
        """
        states = np.asarray(states, dtype=np.float64)
        codes = observation_state(states)
        total = np.zeros(states.shape[0])
        for t, tri in enumerate(self.triangles):
            s = states[:, tri, :].reshape(states.shape[0], 3 * STATE_DIM)
            val, roots = self.triangle_terms(t, s, codes[:, tri])
            total += val + roots * background_position
        if self.body_edges is not None:
            d, ok = slot_distances(states[..., :3], self.triangles)
            F, T = d.shape[:2]
            total += self.body_edges(np.tile(np.arange(T), F), d.reshape(F * T, 3), ok.reshape(F * T, 3)).reshape(F, T).sum(1)
        if self.body_cross is not None:
            total += self.body_cross.labelled(states[..., :3])
        if self.body_handedness is not None:
            total += self.body_handedness.labelled(states[..., :3])
        if self.body_order is not None:
            total += self.body_order.labelled(states[..., :3])
        if self.body_twist is not None:
            total += self.body_twist.labelled(states[..., :3])
        return total

    def components_per_triangle(self) -> list[int]:
        return [m.n_components for m in self.mixtures]


__all__ = ["TriangulatedModel", "TriangleTerms", "LinearMixtureDensity", "StackedTerms", "N_PATTERNS"]
