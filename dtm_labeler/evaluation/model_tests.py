"""Tests of the probability model itself (Hu & Wong, section V.A: Tables 1-2, Figs. 8-9)
and of the structure search at training time (Fig. 12 / issue 2 "Structure").

Protocol (the paper's): each sequence is cut into ten contiguous segments; the first nine
train the models, the last one is held out. Three mixture kinds are trained on the hand-given
structure (``structure='given'``): a single Gaussian (JG), a fixed ``K = 3`` mixture (JMG) and
the MDL-chosen ``K`` in ``[1, 8]`` (JMGW).

All scores use the eq. 12 feature of a triple in the canonical (heading-normalised) frame,
the heading taken from the true labels of the frame, and the triangle's full 15-D mixture
density (the joint ``P(A, B, C)``, so every comparison is between densities over the same
space).

* **Method 1 ("which triple for this model")** -- for triangle ``t`` and a held-out frame,
  the candidates are *all ordered triples of distinct body points* (14 x 13 x 12 = 2184: every
  triple obtained by replacing one, two or three vertices of the true triple by other body
  points, vertex permutations included). Correct when the true ordered triple has the
  strictly highest density under triangle ``t``'s mixture. A variant restricted to the 12
  true triples of the structure (the paper's literal "the triangle with the maximum
  probability from 12 different triangles for the given model") is reported too.
* **Method 2 ("which model for this triple")** -- for the true triple of triangle ``t`` in a
  held-out frame, its density under each of the 12 triangle mixtures; correct when
  triangle ``t``'s own mixture gives the highest. Each mixture is a normalised density on
  the same 15-D space, so this is maximum-likelihood classification with equal priors --
  the sound reading of "select the model corresponding to the maximum probability from 12
  different models of a given triangle".
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..model.dtm import TriangulatedModel
from ..model.features import FEATURE_MATRIX, FULL, STATE_DIM, observation_state
from ..model.structure import BODY14_GIVEN, Structure
from ..motion.clip import MotionClip
from ..search import structure_search as ss
from ..training.train import TrainConfig, canonical_states, heading_pairs, train_model

MIXTURE_KINDS = ("single", "fixed", "mdl")
KIND_NAMES = {"single": "JG", "fixed": "JMG", "mdl": "JMGW"}
PAPER_TABLE1 = {"JG": {"W1": 85.43, "W2": 75.84, "R1": 76.10, "D1": 85.01},
                "JMG": {"W1": 100.0, "W2": 98.87, "R1": 99.58, "D1": 99.62},
                "JMGW": {"W1": 100.0, "W2": 100.0, "R1": 100.0, "D1": 100.0}}
PAPER_TABLE2 = {"JG": {"W1": 62.12, "W2": 77.17, "R1": 79.53, "D1": 78.79},
                "JMG": {"W1": 99.96, "W2": 99.12, "R1": 99.51, "D1": 99.08},
                "JMGW": {"W1": 100.0, "W2": 100.0, "R1": 100.0, "D1": 100.0}}


@dataclass(frozen=True)
class Sequence_:
    """One evaluation sequence: key (column name), data path (relative), class, subject."""

    key: str
    path: str
    motion_class: str
    subject: str
    title: str


SEQUENCES = (
    Sequence_("W1", "cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh", "walk", "7", "walk 07_01"),
    Sequence_("R1", "cmu_skeletal/bvh_from_fbx/cmu_09_11_run_s09.bvh", "run", "9", "run 09_11"),
    Sequence_("D1", "cmu_skeletal/bvh_from_fbx/cmu_55_01_dance-whirl_s55.bvh", "dance", "55", "dance 55_01"),
    Sequence_("D2", "cmu_skeletal/asf_amc/cmu_55_02_lambada-dance_s55.amc", "dance", "55", "lambada 55_02"),
    Sequence_("D3", "cmu_skeletal/asf_amc/cmu_s05_pirouette-dance.amc", "dance", "5", "pirouette 05"),
)


def split_clip(clip: MotionClip, held_out: float = 0.1) -> tuple[MotionClip, MotionClip, int]:
    """First 9/10 (train) and last 1/10 (test) of the frames, and the cut index."""
    cut = int(round((1.0 - held_out) * clip.n_frames))
    cut = min(max(cut, 2), clip.n_frames - 2)
    return clip.slice(0, cut), clip.slice(cut, None), cut


def train_kind(train: Sequence[MotionClip] | MotionClip, kind: str, structure: str = "given", seed: int = 0,
               given: Sequence[Sequence[str]] | None = None, **overrides) -> tuple[TriangulatedModel, dict]:
    """One model: ``kind`` in single / fixed / mdl (K=3 for fixed, K in [1, 8] for mdl)."""
    clips = [train] if isinstance(train, MotionClip) else list(train)
    kw = dict(mixture=kind, structure=structure, seed=seed, k_fixed=3, k_min=1, k_max=8, given_structure=given)
    kw.update(overrides)
    cfg = TrainConfig(**kw)
    model, summary = train_model(clips, cfg)
    return model, summary.as_dict()


def _ordered_triples(n: int) -> np.ndarray:
    return np.array(list(itertools.permutations(range(n), 3)), dtype=np.int64)


def held_out_states(clip: MotionClip, labels: Sequence[str], frames: np.ndarray) -> np.ndarray:
    """(F, n, 6) canonical states (heading from the true labels) of ``frames`` of ``clip``
    (velocities from the preceding frame), only frames where every point has a full state."""
    sel = clip.select(labels)
    states = canonical_states(sel, heading_pairs(labels))[frames]
    ok = (observation_state(states) == FULL).all(axis=1)
    return states[ok]


def triangle_tests(models: dict[str, TriangulatedModel], states: np.ndarray,
                   progress: Callable[[], None] | None = None) -> dict:
    """Method 1 / method 2 per triangle for every model (all on the same structure).

    ``states`` (F, n, 6) canonical held-out frames. Returns
    ``{kind: {"method1": [...T], "method1_12": [...T], "method2": [...T], ...}}`` with
    fractions in [0, 1], plus mean ranks of the true triple (method 1)."""
    F, n, _ = states.shape
    triples = _ordered_triples(n)
    lookup = {tuple(t): i for i, t in enumerate(triples.tolist())}
    X = (states[:, triples, :].reshape(F, len(triples), 3 * STATE_DIM) @ FEATURE_MATRIX.T)   # (F, P, 15)
    out = {}
    for kind, model in models.items():
        tri = model.structure.array
        T = len(tri)
        true_idx = np.array([lookup[tuple(t)] for t in tri.tolist()])
        m1, m1_12, rank, m2 = [], [], [], []
        own = np.empty((F, T, T))             # own[f, model t, data triple u]
        for t, mix in enumerate(model.mixtures):
            ll = mix.log_pdf(X.reshape(-1, X.shape[-1])).reshape(F, len(triples))
            true = ll[:, true_idx[t]]
            others = np.delete(ll, true_idx[t], axis=1)
            m1.append(float((true > others.max(axis=1)).mean()))
            rank.append(float((others >= true[:, None]).sum(axis=1).mean() + 1))
            own[:, t, :] = ll[:, true_idx]
            if progress:
                progress()
        for t in range(T):
            others = np.delete(own[:, t, :], t, axis=1)
            m1_12.append(float((own[:, t, t] > others.max(axis=1)).mean()))
            other_models = np.delete(own[:, :, t], t, axis=1)
            m2.append(float((own[:, t, t] > other_models.max(axis=1)).mean()))
        out[kind] = {"method1": m1, "method1_12": m1_12, "method2": m2, "method1_mean_rank": rank,
                     "components": model.components_per_triangle(),
                     "mean_method1": float(np.mean(m1)), "mean_method1_12": float(np.mean(m1_12)),
                     "mean_method2": float(np.mean(m2))}
    out["frames"] = int(F)
    out["candidates_method1"] = int(len(triples))
    return out


# -- structure -------------------------------------------------------------------------
def structure_comparison(train: MotionClip, test: MotionClip, test_frames: np.ndarray, labels: Sequence[str],
                         seed: int = 0, population: int = 60, generations: int = 200,
                         given_model: TriangulatedModel | None = None,
                         progress: Callable[[str], None] | None = None) -> dict:
    """CBGA vs simple GA (same population and generation budget, no early stop) vs greedy vs
    given: the structures, their Gaussian structure score, and the per-frame log-likelihood of
    training and held-out frames under MDL mixtures fitted on the training part.

    ``test`` is the whole clip; ``test_frames`` the held-out frame indices within it."""
    pairs = heading_pairs(labels)
    tr_states = canonical_states(train.select(labels), pairs)
    complete = (observation_state(tr_states) == FULL).all(axis=1)
    scores = ss.TripleScores.from_states(tr_states[complete])
    n = len(labels)
    kw = dict(population=population, generations=generations, seed=seed, root_pairs=pairs,
              stagnation=generations + 1)
    runs = {"cbga": ss.cbga(scores, n, **kw), "sga": ss.simple_ga(scores, n, **kw),
            "greedy": ss.greedy(scores, n, pairs)}
    structures = {k: r.structure for k, r in runs.items()}
    structures["given"] = Structure.from_names(BODY14_GIVEN, labels)
    te_states = held_out_states(test, labels, test_frames)
    tr_full = tr_states[complete]
    out = {"population": population, "generations": generations, "train_frames": int(complete.sum()),
           "test_frames": int(te_states.shape[0]), "structures": {}}
    for name, st in structures.items():
        if progress:
            progress(name)
        if name == "given" and given_model is not None:
            model = given_model
        else:
            model, _ = train_kind(train.select(labels), "mdl", structure="given", seed=seed,
                                  given=st.names(labels))
        r = runs.get(name)
        out["structures"][name] = {
            "triangles": st.names(labels),
            "gaussian_score_per_frame": scores.per_frame(st),
            "train_loglik_per_frame": float(np.mean(model.frame_log_likelihood(tr_full))),
            "test_loglik_per_frame": float(np.mean(model.frame_log_likelihood(te_states))),
            "components": model.components_per_triangle(),
            "history_per_frame": [h / scores.n_frames for h in r.history] if r is not None and r.history else [],
            "evaluations": int(r.evaluations) if r is not None else 0,
            "same_as_given": sorted(map(tuple, map(sorted, st.triangles))) ==
                             sorted(map(tuple, map(sorted, structures["given"].triangles))),
        }
    return out
