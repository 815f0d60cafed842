"""Max-product dynamic programming over the DTM's elimination order (Song et al.).

A decomposable triangulated model factorises the labeling likelihood over triangles whose
first vertex ``A_t`` (t > 0) appears in no earlier triangle and whose other two vertices form
an edge of the model built so far (eq. 15). Eliminating ``A_T, ..., A_1`` in turn, each step
maximises its triangle's table plus the messages already sent to the edges ``(A_t, B_t)``
and ``(A_t, C_t)`` over ``A_t`` and sends the result to ``(B_t, C_t)``; the first triangle
collects everything, and a forward pass reads the arg maxima back. With every point a
candidate for every label this is the exact MAP of the tree-structured part of the fitness
at one heading (Song, Goncalves and Perona's greedy/DP labeling); the one-point-one-label
constraint is only enforced inside each triangle, so duplicates across triangles are
resolved afterwards (:func:`resolve_duplicates`).

Restricting each label to a few candidate points (:func:`local_candidates`: the point it
has now, its nearest neighbours, its mirror partner's point, "missing") turns the same DP
into a cheap large-neighbourhood move: the best labeling among ``prod_l |C_l|`` candidates
in ``sum_t |C_A| |C_B| |C_C|`` term evaluations. It reaches what single swaps cannot -- a
chain of labels shifted one marker along a limb is corrected in one step. The grids and the
elimination are compiled (:mod:`.dp_kernels`).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from .dp_kernels import dp_solve, grid_keys, region_table
from .problem import FrameProblem
from . import label_ops as ops

#: points each free label of a region may take by default (:func:`region_candidates`)
REGION_CANDIDATES = 6
_NOTHING_ALLOWED = np.zeros((0, 0), dtype=bool)     # region_table's ``allowed`` when no free label is missing


@dataclass(frozen=True)
class Candidates:
    """Each label's candidate points (``n`` = missing), sorted and without repeats, in one
    flat array: label ``l``'s are ``flat[off[l]:off[l + 1]]``."""
    flat: np.ndarray
    off: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray, labels: np.ndarray, M: int) -> "Candidates":
        """From (point, label) pairs in any order, repeats allowed."""
        flat, lab = np.asarray(points, dtype=np.int64), np.asarray(labels, dtype=np.int64)
        order = np.lexsort((flat, lab))
        flat, lab = flat[order], lab[order]
        keep = np.ones(flat.size, dtype=bool)
        keep[1:] = (flat[1:] != flat[:-1]) | (lab[1:] != lab[:-1])
        off = np.zeros(M + 1, dtype=np.int64)
        np.cumsum(np.bincount(lab[keep], minlength=M), out=off[1:])
        return cls(flat[keep], off)

    @classmethod
    def from_lists(cls, candidates) -> "Candidates":
        """From one array (or list) of points per label."""
        if isinstance(candidates, Candidates):
            return candidates
        arrays = [np.asarray(c, dtype=np.int64).ravel() for c in candidates]
        sizes = np.fromiter((a.size for a in arrays), dtype=np.int64, count=len(arrays))
        flat = np.concatenate(arrays) if arrays else np.zeros(0, dtype=np.int64)
        return cls.of(flat, np.repeat(np.arange(len(arrays)), sizes), len(arrays))

    def __len__(self) -> int:
        return self.off.size - 1

    def __getitem__(self, label: int) -> np.ndarray:
        return self.flat[self.off[label]:self.off[label + 1]]


def max_product(problem: FrameProblem, candidates, heading_bin: int, branches: int = 0) -> np.ndarray:
    """The assignment maximising the sum of triangle terms and label gains over
    ``candidates[l]`` (point indices, ``problem.n`` = missing; a list of arrays or
    :class:`Candidates`) at one heading bin, one label per point. Returns (M,) point indices.

    The DP enforces "one point, one label" inside each triangle only. Where its optimum gives a
    point to labels of different triangles, :func:`resolve_duplicates` keeps the best claimant
    and leaves the others missing -- which can lose what a one-to-one relabelling would find: a
    label shifted onto its neighbour's point (LWRA's point labelled LFIN, LFIN's point left
    unlabelled) is undone only if LWRA takes its point back *and* LFIN the free point, while
    the unconstrained optimum gives the free point to nobody and LWRA's point to both. With
    ``branches`` > 0 the conflict is branched on instead (each claimant in turn keeps the
    point and the others lose it as a candidate; then none of them keeps it), breadth first, up
    to ``branches`` more DP solves on the cached terms; the best one-to-one labeling found by
    fitness is returned (the resolved unconstrained optimum among them). Every one-to-one
    labeling lies in one branch, so with an unlimited budget this is the exact one-to-one
    optimum of the DP's objective. Measured: CMU 85 model, self-calibrated, on
    HDM05 -- a shift carried for 254 of 360 frames that the region checks could not undo (the
    resolved optimum was the labeling they started from) is undone at the first check. Off in
    the labeler by default (``sweep_branches``, ``region_branches``: the wider search also
    finds wrong labelings the model prefers elsewhere; see the parameter table)."""
    n, M = problem.n, problem.M
    table = Candidates.from_lists(candidates)
    flat, off = table.flat, table.off
    if (np.diff(off) == 0).any():
        raise ValueError("every label needs at least one candidate (n = missing)")
    if off.size - 1 != M:
        raise ValueError(f"{off.size - 1} candidate lists for {M} labels")
    raw = _dp_assignment(problem, flat, off, heading_bin)
    if raw is None:
        raise ValueError("no candidate labeling satisfies the distance bounds")
    best = resolve_duplicates(problem, raw)
    if branches <= 0 or _conflict(raw, n) is None:
        return best
    cand = np.split(flat, off[1:-1])
    leaves = [best]
    queue, solves = deque([(cand, raw)]), 0
    while queue and solves < branches:
        cs, assign = queue.popleft()
        q, labs = _conflict(assign, n)
        for keep in [*labs, None]:                # each claimant keeps the point, then none of them
            if solves >= branches:
                break
            sub = [c[c != q] if (lab in labs and lab != keep) else c for lab, c in enumerate(cs)]
            solves += 1
            part = Candidates.from_lists(sub)
            a = _dp_assignment(problem, part.flat, part.off, heading_bin)
            if a is None:
                continue
            if _conflict(a, n) is None:
                leaves.append(a)
            else:
                leaves.append(resolve_duplicates(problem, a))
                queue.append((sub, a))
    leaves = np.unique(np.asarray(leaves), axis=0)
    return leaves[int(np.argmax(problem.fitness(leaves)))]


def _dp_assignment(problem: FrameProblem, flat: np.ndarray, off: np.ndarray, heading_bin: int) -> np.ndarray | None:
    """The DP's optimum over the candidates ``flat[off[l]:off[l + 1]]`` of each label ``l``
    (duplicates across triangles possible); None when a label has no candidate or no candidate
    labeling satisfies the distance bounds."""
    n, M, tri = problem.n, problem.M, problem.tri
    sizes = np.diff(off)
    if (sizes == 0).any():
        return None
    # a triangle whose three labels have one candidate each only adds a constant: skipped
    multi = (sizes[tri] > 1).any(1)
    multi[0] = True
    active = np.flatnonzero(multi)
    goff, keys = grid_keys(flat, off, active, tri, problem.dist, problem.bounds, n, problem.T, n + 1,
                           int(heading_bin))
    vals = problem.triple_terms(keys)                  # -inf where a key is -1 (outside the bounds)
    pick = dp_solve(vals, goff, active, tri, flat, off, problem.label_gain, M)
    if pick[0] < 0:
        return None
    return flat[off[:M] + np.asarray(pick[:M], dtype=np.int64)]


def _conflict(assign: np.ndarray, n: int):
    """The first point given to several labels and those labels, or None."""
    twice = np.flatnonzero(np.bincount(assign[assign < n], minlength=n) > 1)
    if not twice.size:
        return None
    q = int(twice[0])
    return q, np.flatnonzero(assign == q)


def resolve_duplicates(problem: FrameProblem, assign: np.ndarray) -> np.ndarray:
    """One label per point: where the DP gave a point to several labels (it enforces
    exclusion inside each triangle only), the claimant whose keeping it gives the best
    fitness keeps it and the others become missing (one conflict at a time)."""
    n = problem.n
    assign = np.asarray(assign, dtype=np.int64).copy()
    while (conflict := _conflict(assign, n)) is not None:
        labs = conflict[1]
        options = np.repeat(assign[None], labs.size, 0)
        options[:, labs] = n
        options[np.arange(labs.size), labs] = assign[labs]
        assign = options[int(np.argmax(problem.fitness(options)))]
    return assign


def local_candidates(problem: FrameProblem, ind: np.ndarray, k_near: int = 3,
                     with_missing: bool = False) -> list[np.ndarray]:
    """Candidate points per label around the labeling ``ind``: the label's point and its
    ``k_near - 1`` nearest points (labelled or not), the point of its mirror partner, and
    "missing". A missing label gets the ``k_near`` free points within its distance bounds
    that are nearest (relative to those bounds) to its labelled triangle neighbours."""
    n, M = problem.n, problem.M
    out = [np.array([n])] * M
    if n == 0:
        return out
    k = min(k_near, n)
    d = problem.dist[:n, :n]
    nearest = np.argpartition(d, k - 1, axis=1)[:, :k] if k < n else np.tile(np.arange(n), (n, 1))
    partner = np.full(M, -1, dtype=np.int64)
    mp = problem.mirror_pairs
    if len(mp):
        partner[mp[:, 0]], partner[mp[:, 1]] = mp[:, 1], mp[:, 0]
    used = ops.used_mask(ind[None], n)[0]
    free = np.flatnonzero(~used)
    allowed = problem.allowed(ind) if free.size else None
    bounds = problem.bounds
    for lab in range(M):
        p = int(ind[lab])
        extra = [] if p < n and not with_missing else [n]
        if partner[lab] >= 0 and ind[partner[lab]] < n:
            extra.append(int(ind[partner[lab]]))
        if p < n:
            out[lab] = np.concatenate([nearest[p], extra])
        elif free.size:
            ok = free[allowed[lab, free]]
            nb = np.flatnonzero(np.isfinite(bounds[lab]) & (ind < n))
            if ok.size > k and nb.size:
                score = (problem.dist[np.ix_(ok, ind[nb])] / bounds[lab, nb]).sum(1)
                ok = ok[np.argsort(score)[:k]]
            out[lab] = np.concatenate([ok[:max(k, 0)] if nb.size else ok[:k], extra])
        else:
            out[lab] = np.array(extra)
    return out


def region_candidates(problem: FrameProblem, ind: np.ndarray, free: np.ndarray,
                      max_candidates: int = REGION_CANDIDATES) -> Candidates:
    """Candidates for relabelling the region ``free`` (M,) bool of ``ind`` with the other
    labels kept. The pool is every point not held by a kept label; a free label with a
    point gets the ``max_candidates`` pool points nearest to it (its own included), a
    missing free label the pool points within its distance bounds to the kept labels,
    nearest to the region's points; both may also be missing. A kept label has its own
    point only. :func:`max_product` over these is the best relabelling of the region (at
    one heading) given the rest of the body; the cap bounds the work when many points are
    unlabelled. Compiled (:func:`~.dp_kernels.region_table`)."""
    n = problem.n
    ind = np.ascontiguousarray(ind, dtype=np.int64)
    free = np.ascontiguousarray(free, dtype=bool)
    missing = free & (ind >= n)
    allowed = problem.allowed(np.where(free, n, ind)) if missing.any() else _NOTHING_ALLOWED
    return Candidates(*region_table(problem.dist, ind, free, allowed, n, int(max_candidates)))


def shared_candidates(problem: FrameProblem, ind: np.ndarray, free: np.ndarray,
                      max_candidates: int = 12) -> Candidates:
    """Candidates for relabelling the region ``free`` (M,) bool of ``ind`` as a whole: every
    free label gets the same ``max_candidates`` points -- those of the pool (the points no kept
    label holds) nearest to the points the region holds now, its own included -- and
    "missing"; a kept label its own point. Where :func:`region_candidates` lets each label move
    only near its current point, here any label of the region may take any of its points: a
    permutation of a whole limb's labels (a search from scratch that settled on the right arm's
    six labels scrambled over its markers) is undone in one relabelling. The DP's cost grows
    with the cube of the candidates per triangle, not with the region's size (the model is
    triangulated), so a region of 7 labels over 12 points is a few thousand term evaluations."""
    n, M = problem.n, problem.M
    ind = np.asarray(ind, dtype=np.int64)
    kept = np.where(free, n, ind)
    pool = np.flatnonzero(~ops.used_mask(kept[None], n)[0])
    held = ind[free & (ind < n)]
    if held.size and pool.size > max_candidates:
        near = problem.dist[np.ix_(pool, held)].min(1)
        pool = np.sort(pool[np.argsort(near, kind="stable")[:max_candidates]])
    elif pool.size > max_candidates:
        pool = pool[:max_candidates]
    fixed, region = np.flatnonzero(~free), np.flatnonzero(free)
    shared = np.append(pool, n)
    return Candidates.of(np.concatenate([ind[fixed], np.tile(shared, region.size)]),
                         np.concatenate([fixed, np.repeat(region, shared.size)]), M)


def model_regions(model, max_size: int = 8, partner: bool = True) -> list[np.ndarray]:
    """One body region per label: the label, its left/right mirror partner (so that a limb
    swapped with its mirror image is repaired in one relabelling) and the labels nearest to
    it on the model's mean body (:func:`mean_shape`), up to ``max_size`` labels. Without the
    ``partner`` (the wide sweeps' body neighbourhoods, for :func:`shared_candidates`): the
    label and its nearest only -- a limb's whole chain with its attachment. A region must
    hold the markers a carried labeling can confuse, which are the close ones on the body:
    a limb's chain (elbow, forearm, wrist bar, finger) whose labels were passed one marker
    along. Nearness along the learned triangles (geodesic over their mean separations, the
    regions until 2026-11-25) followed edges that are cheap to describe rather than
    anatomical -- a CBGA structure of HDM05 joins a wrist marker to the back of the head and a
    knee, so the upper arm's region (6 labels) held the back of the head, one end of the wrist
    bar and not the other, nor the finger. Measured,
    inline, geodesic -> mean body (accuracy, search errors): HDM05 41 markers, 3 gapped + 2
    ghosts 93.6 -> 95.4 % (113 -> 70), 2 flickering 94.6 -> 95.5 % (72 -> 45); CMU 85_12's
    model on 85_02 88.1 -> 90.6 %, 91.5 -> 96.5 % (187 -> 65); MoCap Toolbox dance model on
    the walk 60.8 -> 67.1 %, 69.2 -> 82.9 %; 14 body points, the dance, the Qualisys walk and
    HDM05 calibrated unchanged (within 0.3 %). Captures with realistic gaps (``dtm-label``'s
    path, ``bench_captures.py``): mixed, net slightly ahead -- HDM05 model of the gap-free
    half on the 50 %-gapped half 89.4 -> 91.3 % (take votes), on 25 % gaps 97.0 -> 96.4 %
    (mean of 3 gap seeds), the gappy half's model 94.5 -> 94.3 %; Qualisys 86.3 -> 88.7 % and
    95.1 -> 94.8 %. Computed once per model (:func:`regions_of`)."""
    M = model.n_labels
    pos = mean_shape(model)
    D = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    mirror = mirror_partners(model) if partner else np.full(M, -1, dtype=np.int64)
    regions = []
    for lab in range(M):
        first = [lab] + ([int(mirror[lab])] if mirror[lab] >= 0 else [])
        rest = [int(x) for x in np.argsort(D[lab], kind="stable") if x not in first]
        regions.append(np.sort(np.array((first + rest)[:max_size], dtype=np.int64)))
    return regions


def regions_of(model, max_size: int, partner: bool = True) -> list[np.ndarray]:
    """:func:`model_regions` of ``model``, computed once per model, size and ``partner``."""
    cache = model.__dict__.setdefault("_regions", {})
    key = (max_size, partner)
    if key not in cache:
        cache[key] = model_regions(model, max_size, partner)
    return cache[key]


def mirrored_regions(model, max_size: int) -> list[np.ndarray]:
    """Each label's body neighbourhood (:func:`model_regions` without the partner: the label and
    its nearest ``max_size - 1`` on the mean body) joined with its left/right mirror image: both
    hands' or both feet's markers in one region. For :func:`shared_candidates`, whose labels may
    each take any of the region's points: a search from scratch of a crouched body with its hands
    together settles on the two arms' chains interleaved (CMU 85's breakdance, 41 markers: RELB
    read as LFIN, LFIN as RELB, LWRB as LUPA, RWRB as LWRB ... 62 nats below the truth), which
    no region of one side undoes. Computed once per model and size."""
    cache = model.__dict__.setdefault("_regions", {})
    key = ("mirrored", max_size)
    if key not in cache:
        partner = mirror_partners(model)
        cache[key] = [np.unique(np.concatenate([r, partner[r][partner[r] >= 0]]))
                      for r in regions_of(model, max_size, partner=False)]
    return cache[key]


def mirror_partners(model) -> np.ndarray:
    """(M,) each label's left/right mirror partner (``model.mirror_pairs``), -1 for none."""
    partner = np.full(model.n_labels, -1, dtype=np.int64)
    mp = np.asarray(model.mirror_pairs, dtype=np.int64).reshape(-1, 2)
    partner[mp[:, 0]], partner[mp[:, 1]] = mp[:, 1], mp[:, 0]
    return partner


def relabel_regions(problem: FrameProblem, ind: np.ndarray, fit: float, regions: list[np.ndarray],
                    centres, refine=None, branches: int = 0,
                    candidates=region_candidates) -> tuple[np.ndarray, float, int]:
    """Region by region (``regions[c]`` for each of ``centres``), the exact best relabelling
    of the region given the rest of ``ind`` (:func:`max_product` over
    :func:`region_candidates`, at the labeling's heading); a relabelling is taken only when
    it raises the fitness, and then handed to ``refine(ind, fit) -> (ind, fit, evals)``
    (e.g. a polish) before the next region; ``branches``: :func:`max_product`'s budget for
    points given to two labels. Returns (ind, fit, term evaluations): never a labeling worse
    than the start. ``candidates(problem, ind, free)``: each region's candidate points
    (:func:`region_candidates`, or :func:`shared_candidates` for whole-region permutations)."""
    evals = 0
    b = int(problem.candidate_bins(ind[None])[0])
    for c in centres:
        free = np.zeros(problem.M, dtype=bool)
        free[regions[c]] = True
        e0 = problem.evaluations
        try:
            cand = max_product(problem, candidates(problem, ind, free), b, branches)
        except ValueError:                 # no relabelling within the distance bounds
            continue
        fc = float(problem.fitness(cand[None])[0])
        evals += problem.evaluations - e0 + 1
        if fc > fit + 1e-9:
            ind, fit = cand, fc
            if refine is not None:
                ind, fit, e = refine(ind, fit)
                evals += e
            b = int(problem.candidate_bins(ind[None])[0])
    return ind, fit, evals


def body_at_heading(problem: FrameProblem, heading_bin: int) -> np.ndarray:
    """The exact best labeling of the whole frame at one heading bin: :func:`max_product` with
    every point (and "missing") a candidate for every label -- the DTM's max-product over all
    of its triangles (the decomposable model's exact inference; duplicates resolved after).
    ValueError when no labeling satisfies the distance bounds. What :func:`turned_round`
    runs; about 1 s per heading at 41 markers (the terms of every triple at a new heading),
    ~10 ms at 14 points."""
    everything = np.arange(problem.n + 1, dtype=np.int64)
    return max_product(problem, [everything] * problem.M, heading_bin)


def _refined_if_better(problem: FrameProblem, e0: int, ind: np.ndarray, fit: float, cand: np.ndarray,
                       refine) -> tuple[np.ndarray, float, int]:
    """``cand`` scored and ``refine``-d, taken when it fits better than ``ind``: (ind, fitness,
    term evaluations since ``e0``)."""
    fc = float(problem.fitness(cand[None])[0])
    evals = problem.evaluations - e0 + 1
    if refine is not None:
        cand, fc, e = refine(cand, fc)
        evals += e
    if fc > fit + 1e-9:
        return cand, fc, evals
    return ind, fit, evals


def turn_permutation(model) -> np.ndarray:
    """(M,) the label each label becomes when the body is seen from behind: the model's mean
    body (:func:`mean_shape`, heading-canonical, z up) turned 180 deg about the vertical axis
    through its centre, each label matched one to one to the label nearest to where it lands
    (Hungarian on the distances): left front -> right back (a front waist marker -> the other
    side's back waist marker, the sternum -> the spine, left and right limbs exchanged).
    Computed once per model."""
    cache = model.__dict__.setdefault("_turn", {})
    if "perm" not in cache:
        from scipy.optimize import linear_sum_assignment
        pos = mean_shape(model)
        turned = pos.copy()
        turned[:, :2] = 2.0 * pos[:, :2].mean(0) - pos[:, :2]
        _, cache["perm"] = linear_sum_assignment(np.linalg.norm(turned[:, None] - pos[None], axis=-1))
    return cache["perm"]


def turned_labels(problem: FrameProblem, ind: np.ndarray, fit: float, refine=None) -> tuple[np.ndarray, float, int]:
    """The cheap half of :func:`turned_round`: a labeling of the body seen from behind has each
    point under the label the turned-round body puts there (:func:`turn_permutation`), so the
    labeling read back through that permutation -- point of label ``l`` -> label ``perm[l]`` --
    ``refine``-d, is the body turned round without a DP at a new facing (milliseconds instead
    of about 1 s at 41 markers). Taken when it fits better; (ind, fitness, term evaluations)."""
    e0 = problem.evaluations
    cand = np.empty_like(ind)
    cand[turn_permutation(problem.model)] = ind
    return _refined_if_better(problem, e0, ind, fit, cand, refine)


def turned_round(problem: FrameProblem, ind: np.ndarray, fit: float, refine=None) -> tuple[np.ndarray, float, int]:
    """The body turned round, checked: :func:`body_at_heading` at the facing opposite to that of
    ``ind`` (M,), ``refine(x, fx) -> (x, fx, evals)``-d, and taken when it fits better. A cold
    search under a model of another lab or person can settle on the body seen from behind --
    facing 180 deg off, left and right exchanged to match -- which fits the model well enough
    that nothing flags it while the truth fits far better (CMU 85 model on HDM05 started at
    frame 600: 413 nats against the truth's 554, 2.4 % right for 300 frames; larger GAs 38-59 %);
    the GA's moves and region sweeps cannot turn a whole body round, the DP at the opposite
    facing can (there: 542.8 nats, 90 % of the labels right, before refining). Returns (ind,
    fitness, term evaluations): never a labeling worse than the start."""
    e0 = problem.evaluations
    b = int(problem.candidate_bins(ind[None])[0])
    try:
        cand = body_at_heading(problem, (b + problem.bins // 2) % problem.bins)
    except ValueError:
        return ind, fit, problem.evaluations - e0
    return _refined_if_better(problem, e0, ind, fit, cand, refine)


def mean_shape(model) -> np.ndarray:
    """(M, 3) the model's mean body in its heading-canonical frame: the weighted mean relative
    positions of each triangle's mixture (eq. 12 rows 9-14) chained along the structure --
    triangle 0 placed at the origin, every later triangle's new vertex ``A_t`` at the mean of
    where its edge ``(B_t, C_t)`` puts it. Unlike :func:`mean_separations` it gives a distance
    between every two labels, not only between those the (learned, not necessarily
    anatomical) triangles join."""
    pos = np.zeros((model.n_labels, 3))
    for t, (tri, mix) in enumerate(zip(model.triangles, model.mixtures)):
        mu = np.asarray(mix.weights) @ np.asarray(mix.means)
        rb, rc = mu[[9, 11, 13]], mu[[10, 12, 14]]
        a, b, c = (int(v) for v in tri)
        if t == 0:
            pos[a], pos[b], pos[c] = 0.0, rb, rc
        else:
            pos[a] = 0.5 * ((pos[b] - rb) + (pos[c] - rc))
    return pos


def model_chains(model, max_len: int = 3, k_near: int = 4) -> list[np.ndarray]:
    """Chains of labels a carried labeling may have shifted by one marker (what
    :func:`~.label_ops.chain_shifts` undoes): every sequence of 2 .. ``max_len`` distinct labels
    in which each two consecutive labels are neighbours on the model's mean body
    (:func:`mean_shape`: one is among the ``k_near`` nearest of the other) -- limb chains such as elbow, forearm, wrist, finger, in
    both orders. One (C, length) array per length."""
    pos = mean_shape(model)
    M = model.n_labels
    if M < 2 or max_len < 2:
        return []
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    k = min(k_near, M - 1)
    adj = np.zeros((M, M), dtype=bool)
    np.put_along_axis(adj, np.argsort(d, axis=1, kind="stable")[:, :k], True, axis=1)
    adj |= adj.T                                                       # neighbours either way
    out = [np.argwhere(adj)]
    for _ in range(max_len - 2):
        prev = out[-1]
        r, nxt = np.nonzero(adj[prev[:, -1]])
        ext = np.concatenate([prev[r], nxt[:, None]], axis=1)
        ext = ext[~(ext[:, :-1] == ext[:, -1:]).any(1)]                 # no label twice
        out.append(ext)
    return [c.astype(np.int64) for c in out]


def chains_of(model, max_len: int, k_near: int = 4) -> list[np.ndarray]:
    """:func:`model_chains` of ``model``, computed once per model and setting."""
    cache = model.__dict__.setdefault("_chains", {})
    key = (max_len, k_near)
    if key not in cache:
        cache[key] = model_chains(model, max_len, k_near)
    return cache[key]
