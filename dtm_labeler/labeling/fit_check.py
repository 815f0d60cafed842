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
"""
from __future__ import annotations

import numpy as np

from ..model.dtm import FULL_PATTERN, TriangulatedModel
from ..model.features import FEATURE_MATRIX, FULL
from ..search.problem import FrameProblem

#: quantile of a right labeling's term distribution taken as the floor
FLOOR_QUANTILE = 1e-3
#: feature samples per triangle for the floor
FLOOR_SAMPLES = 4000
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


def _draw_floors(model: TriangulatedModel, quantile: float, samples: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = model.structure.n_triangles
    X = np.concatenate([m.sample(samples, rng) for m in model.mixtures])            # (T s, 15)
    s = X @ _F_PINV.T                                                                  # (T s, 18): F s = X
    tri = np.repeat(np.arange(T), samples)
    terms = model.batched(FULL_PATTERN)(s, tri).reshape(T, samples)
    return np.quantile(terms, quantile, axis=1)


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


__all__ = ["term_floors", "label_misfit", "FLOOR_QUANTILE"]
