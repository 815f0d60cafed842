"""Subject calibration of the motion terms: the person's marker placement in the triangle means.

The paper's triangle mixtures (eq. 6-7 over the eq. 12 feature) learn the motion *and* where
the training people's markers sat: the six relative-position coordinates of a triangle's
feature (``pB - pA``, ``pC - pA``) hold both the pose and the placement. Labs and sessions
place markers differently -- Plug-in Gait's shank and thigh markers sit at heights that change
from session to session, and CMU subject 85's right shank marker is 9 cm below the knee where
HDM05's is 19 cm -- so a model of one lab's people finds the other lab's marker where its
mixtures never had it and leaves it out, also after the body terms are calibrated to the
person (:func:`~.calibrate.calibrated_body`): HDM05 labelled by a model of CMU 85, calibrated
on the capture's own labels of its first 3.3 s, 97.3 % with the right shank marker unlabelled
in 359 of 360 frames.

What this module does is a bias-only adaptation of each triangle's mixture (the bias case of
maximum-likelihood linear regression, Leggetter & Woodland 1995, with the MAP shrinkage of
Reynolds, Quatieri & Dunn 2000), read for eq. 6-7: the calibration frames' features of a
triangle are assigned to its components (E-step, responsibilities ``g_tk`` under the mixture
marginalised onto the position coordinates, eq. 30-31's primitive -- velocities are left out:
they belong to the window's motion, not to the person), and every component's mean moves by
the same shift, the frames' mean residual, shrunk by the evidence::

    n = sum_tk g_tk,   d = sum_tk g_tk (x_t - mu_k) / n,
    mu_k <- mu_k + n / (n + r) * d                  (position coordinates only, every k)

with relevance ``r`` (frames). One shift per triangle is a placement: the marker sits
elsewhere on the segment in every pose; weights and covariances are kept (the motion's spread
is not the person's), and so is the structure. A triangle with fewer than ``min_frames``
frames showing all three of its points is left as it is -- also a marker the model never
confirmed in a self-calibration window, so a placement far from every training person's can
still be left out.

Measured (``dtm-eval`` generalisation cells as ``dtm-label`` runs them, self-calibrated on the
take's first 5 s, at most a third; stream accuracy before -> after, see
:func:`~.calibrate.auto_calibrate`): CMU 85 -> HDM05 94.11 -> 97.56 % (the right shank marker,
never confirmed in the window, still left out; 100 % once the self-calibration takes it from
the points it left out, :func:`~.calibrate.completed_labels`), CMU 85 jump and twist -> breakdance 99.14
-> 99.50 %, HDM05 -> CMU 85 92.25 -> 92.18 %, the other 41-marker cells as before; the
14-point other-person cells 100 % stream (subject 9's run 99.74 -> 100 %) and single frames up
1-4 points (pirouette 92.26 -> 96.43 %); with the capture's own labels (``dtm-calibrate --labels capture``) CMU 85 -> HDM05
97.33 -> 100 %. Tried and not kept: a move of each component towards its own frames' mean
(Reynolds' mean-only MAP, ``mu_k += n_k / (n_k + r) (xbar_k - mu_k)``): HDM05 -> CMU 85 93.6 %,
but the components take the window's poses as well as the places -- subject 5's pirouette
100 -> 97.2 %, subject 9's run 99.7 -> 97.5 %; opening the placement for the self-calibration's
first round (position variance + 2 (4 cm)^2, so that a marker the model leaves out there gets
confirmed and shifted): CMU 85 -> HDM05 97.56 -> 90.24 %, HDM05 -> CMU 85 92.18 -> 91.36 %.
"""
from __future__ import annotations

import numpy as np

from ..model.dtm import TriangulatedModel
from ..model.features import FEATURE_DIM, triangle_features
from ..model.mixture import GaussianMixture
from .gaps import facing_states

__all__ = ["POSITION_DIMS", "adapted_mixtures"]

POSITION_DIMS = np.arange(9, FEATURE_DIM)      # eq. 12: pB - pA, pC - pA (after the nine velocities)


def adapted_mixtures(model: TriangulatedModel, positions: np.ndarray, relevance: float = 20.0,
                     min_frames: int = 10) -> tuple[list[GaussianMixture], dict]:
    """The triangle mixtures of ``model`` with their position means adapted to the labelled
    frames ``positions`` (F, M, 3) in label order, NaN = unseen (module doc); and a summary:
    triangles adapted, the median over them and the largest shift of a relative-position
    coordinate (m)."""
    out, moves = [], []
    if relevance <= 0:
        return list(model.mixtures), {"triangles_adapted": 0, "triangles_total": len(model.mixtures),
                                      "median_move_m": 0.0, "largest_move_m": 0.0}
    S = facing_states(positions, model.heading_pairs, 1.0)       # velocities unused here: any rate
    for tri, mix in zip(model.triangles, model.mixtures):
        X = triangle_features(S, tri)[:, POSITION_DIMS]
        X = X[np.isfinite(X).all(1)]
        if X.shape[0] < min_frames:
            out.append(mix)
            continue
        g = mix.marginal(POSITION_DIMS).responsibilities(X)          # (n, K)
        mu = np.array(mix.means)
        n = X.shape[0]                                                # sum over t, k of g_tk
        d = X.mean(0) - (g.sum(0) / n) @ mu[:, POSITION_DIMS]       # the frames' mean residual
        step = n / (n + relevance) * d
        mu[:, POSITION_DIMS] += step
        moves.append(float(np.abs(step).max()))
        out.append(GaussianMixture(np.array(mix.weights), mu, np.array(mix.covariances)))
    summary = {"triangles_adapted": len(moves), "triangles_total": len(out),
               "median_move_m": float(np.median(moves)) if moves else 0.0,
               "largest_move_m": float(max(moves)) if moves else 0.0}
    return out, summary
