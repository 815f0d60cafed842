"""Noticing loss: how well each label fits, against what the model expects of a right one.

The running fitness level (:class:`~.tracked.TrackedLabeler`) judges a frame's *total* against
recent frames, so it adapts to a wrong labeling that tracking carries on (measured: a labeling
the model likes 25-100 nats less than the truth kept for 70 frames at 41 markers, a shifted
foot chain, no search triggered). What a wrong label cannot hide is its own triangles: in
the DTM each triangle term is ``log P(A_t | B_t, C_t)`` (eq. 5, 14; the joint for the first),
and under a right labeling it is distributed as the model predicts.

:func:`term_floors` draws that distribution from the model itself -- eq. 12 features sampled
from each triangle's mixture, pushed back to point states and scored by the same compiled term
kernel the labeler uses -- and keeps a low quantile per triangle (the *floor*). No training
data is needed, and the floor moves with the model's widening by the declared measurement
noise. :func:`label_misfit` gives, per label, how far the fully observed triangles it belongs
to fall below their floors (nats; 0 = every triangle within what a right labeling shows).
With body terms (:mod:`~dtm_labeler.model.body`) a triangle's term in the frame problem also
holds the body factor of the edges it introduces; that factor is 0 within the edges' reach
(where every sample of a right labeling lies), so the floors are the mixtures' and a label
whose edges leave their reach shows the body factor as misfit. Marginalised triangles (a vertex missing or without a velocity) are not judged: their terms
have other dimensions, and the points that make them are the appearing ones the event checks
already look at.

The labeler uses the misfit to aim its exact region checks (:func:`~dtm_labeler.search.dtm_dp.relabel_regions`)
at the labels that fit worst, and as a doubt signal: a label far below its floors is
published with low confidence.

What a frame with gaps should score. The labeler judges a frame's total against a running
level per labelled point (``tracked.label_weight``). A label whose triangle neighbours are hidden
contributes only its marginal terms (eq. 30-31: fewer observed dimensions, a triangle with ``A``
unobserved none at all), so with half the markers hidden a *right* labeling fits far fewer nats
per labelled point than a fully seen frame's. :func:`pattern_means` draws, from the model itself
as the floors are, each triangle's mean term under each of the 27 observation patterns;
:func:`expected_share` is what a right labeling with a labeling's pattern is expected to score,
as a share of what a fully seen one is. (HDM05, 41 markers, half hidden: the true labeling fell
49 nats below the count's expectation at the median and 421 of 600 frames would have doubted it;
7 against the pattern's.) The labeler reads it where it publishes a doubted frame's confidence
(``tracked.TrackedLabeler._publish``); its searches keep the count (``results/search_errors.md``).
"""
from __future__ import annotations

import numpy as np

from ..model.dtm import FULL_PATTERN, TriangulatedModel
from ..model.features import FEATURE_MATRIX, FULL, MISSING, N_PATTERNS, POSITION_ONLY, STATE_DIM, pattern_codes, pattern_id
from ..search.problem import FrameProblem

#: quantile of a right labeling's term distribution taken as the floor
FLOOR_QUANTILE = 1e-3
#: feature samples per triangle for the floor
FLOOR_SAMPLES = 4000
#: feature samples per triangle for the patterns' mean terms (a mean needs far fewer than a quantile)
PATTERN_SAMPLES = 300
_F_PINV = np.linalg.pinv(FEATURE_MATRIX)


def term_floors(model: TriangulatedModel, quantile: float = FLOOR_QUANTILE, samples: int = FLOOR_SAMPLES,
                seed: int = 0) -> np.ndarray:
    """(T,) the ``quantile`` of each triangle's fully observed term under the model itself
    (kernel term, without the background density a root triangle adds in the fitness).

    Drawn once per model and arguments (~70 ms for 13 triangles), then kept on the model: a
    model is never changed in place, and every labeler made with it (a bank's, a reload's, an
    archive's takes) gets the same read-only floors."""
    cache = model.__dict__.setdefault("_term_floors", {})
    key = (float(quantile), int(samples), int(seed))
    if key not in cache:
        floors = _draw_floors(model, quantile, samples, seed)
        floors.flags.writeable = False
        cache[key] = floors
    return cache[key]


def _sampled_states(model: TriangulatedModel, samples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(T s, 18) triple states drawn from each triangle's own mixture (eq. 12 features pushed
    back to point states), and (T s,) the triangle of each row."""
    rng = np.random.default_rng(seed)
    X = np.concatenate([m.sample(samples, rng) for m in model.mixtures])            # (T s, 15)
    return X @ _F_PINV.T, np.repeat(np.arange(model.structure.n_triangles), samples)    # F s = X


def _draw_floors(model: TriangulatedModel, quantile: float, samples: int, seed: int) -> np.ndarray:
    s, tri = _sampled_states(model, samples, seed)
    terms = model.batched(FULL_PATTERN)(s, tri).reshape(-1, samples)
    return np.quantile(terms, quantile, axis=1)


def pattern_means(model: TriangulatedModel, samples: int = PATTERN_SAMPLES, seed: int = 0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(T, 27) mean kernel term of each triangle under each observation pattern
    (:func:`~dtm_labeler.model.features.pattern_id`) for states drawn from the triangle's own
    mixture, and (T, 27) whether the pattern leaves the triangle a root (its absolute position
    then scored by the background, as in the frame's fitness). Unobserved entries are zeroed, as
    the frame kernel gets them. Drawn once per model (~0.15 s at 41 markers) and kept on it, as
    :func:`term_floors`."""
    cache = model.__dict__.setdefault("_pattern_means", {})
    key = (int(samples), int(seed))
    if key not in cache:
        T = model.structure.n_triangles
        s, tri = _sampled_states(model, samples, seed)
        mean, root = np.zeros((T, N_PATTERNS)), np.zeros((T, N_PATTERNS), dtype=bool)
        for pid in range(N_PATTERNS):
            sp = s.copy()
            for v, code in enumerate(pattern_codes(pid)):
                if code == MISSING:
                    sp[:, STATE_DIM * v:STATE_DIM * (v + 1)] = 0.0
                elif code == POSITION_ONLY:
                    sp[:, STATE_DIM * v + 3:STATE_DIM * (v + 1)] = 0.0
            terms = model.batched(pid)
            mean[:, pid] = terms(sp, tri).reshape(T, samples).mean(1)
            root[:, pid] = terms.root
        mean.flags.writeable = root.flags.writeable = False
        cache[key] = (mean, root)
    return cache[key]


def expected_share(problem: FrameProblem, ind: np.ndarray) -> float:
    """What a right labeling with ``ind``'s observation pattern (label -> point, ``n``
    missing) is expected to score, as a share of a fully seen frame's expectation (module
    doc): the triangles' mean terms for their patterns (:func:`pattern_means`, roots scored by
    the background) plus the labelled and missing labels' gains over clutter. NaN when the
    fully seen expectation is not positive (a model that fits its own samples below clutter:
    no scale to read)."""
    mean, root = pattern_means(problem.model)
    ind = np.asarray(ind, dtype=np.int64)
    b = problem.background
    t = np.arange(problem.T)
    pid = pattern_id(problem.codes[ind[problem.tri]])
    got = float((mean[t, pid] + root[t, pid] * b.log_position).sum() + problem.label_gain[ind].sum())
    full_gain = np.log(b.detection_probability) - b.log_position - b.log_velocity
    full = float((mean[:, FULL_PATTERN] + root[:, FULL_PATTERN] * b.log_position).sum() + problem.M * full_gain)
    return got / full if full > 0 else float("nan")


def label_misfit(problem: FrameProblem, ind: np.ndarray, floors: np.ndarray) -> np.ndarray:
    """(M,) per label: summed deficit (nats) below the floors of the fully observed triangles
    it is a vertex of, for the labeling ``ind`` (label -> point, ``n`` missing)."""
    ind = np.asarray(ind, dtype=np.int64)
    tri = problem.tri                                                              # (T, 3)
    full = (problem.codes[ind[tri]] == FULL).all(1)
    out = np.zeros(problem.M)
    if not full.any():
        return out
    ts = np.flatnonzero(full)
    bins = problem.candidate_bins(ind[None])
    terms = problem.triangle_table(ind[None], bins, ts)[0]
    terms = terms - problem.model.batched(FULL_PATTERN).root[ts] * problem.background.log_position
    deficit = np.maximum(floors[ts] - terms, 0.0)
    np.add.at(out, tri[ts].ravel(), np.repeat(deficit, 3))
    return out


__all__ = ["term_floors", "label_misfit", "pattern_means", "expected_share", "FLOOR_QUANTILE", "PATTERN_SAMPLES"]
