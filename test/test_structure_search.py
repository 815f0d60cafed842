"""Structure search (section IV.A): triple/pair scores vs direct Gaussian log-likelihoods, and
CBGA against greedy and the simple GA on data with a known chain-like dependency."""
import functools
import itertools

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from dtm_labeler.model.features import triangle_features
from dtm_labeler.model.structure import Structure, is_valid, structure_problem
from dtm_labeler.search import ga
from dtm_labeler.search import structure_ops as ops
from dtm_labeler.search import structure_search as ss

N = 9


def chain_states(n=N, F=400, seed=0):
    """Fully observed (F, n, 6) states where each point depends on the two before it in a
    random order (a second-order chain: exactly a triangulated dependency)."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(n)
    s = np.zeros((F, n, 6))
    prev, prev2 = rng.normal(size=(F, 6)), np.zeros((F, 6))
    for k, v in enumerate(order):
        cur = 0.8 * prev + 0.5 * prev2 + rng.normal(scale=rng.uniform(0.05, 0.3), size=(F, 6)) if k else prev
        s[:, v] = cur
        prev2, prev = prev, cur
    return s, order


def direct_ll(Y, reg):
    mu = Y.mean(0)
    C = np.cov(Y, rowvar=False, bias=True) + reg * np.eye(Y.shape[1])
    return multivariate_normal(mu, C).logpdf(Y).sum()


def pair_features(states, b, c):
    """(vB, vC, pC - pB): the 9-D parent feature of a triangle (., B, C)."""
    return np.c_[states[:, b, 3:], states[:, c, 3:], states[:, c, :3] - states[:, b, :3]]


def test_triple_and_pair_scores_equal_direct_gaussian_log_likelihoods():
    s, _ = chain_states(n=6, F=300, seed=3)
    reg = 1e-6
    sc = ss.TripleScores.from_states(s, reg)
    assert sc.n_frames == 300 and sc.triple.shape == (6, 6, 6) and sc.pair.shape == (6, 6)
    for tri in [(0, 1, 2), (5, 3, 1), (2, 4, 0)]:
        want = direct_ll(triangle_features(s, tri), reg)
        for perm in itertools.permutations(tri):       # symmetric: every vertex order, same value
            assert sc.triple[perm] == pytest.approx(want, rel=1e-9, abs=1e-6)
            assert direct_ll(triangle_features(s, perm), reg) == pytest.approx(want, rel=1e-9, abs=1e-6)
    for b, c in [(0, 1), (4, 2), (3, 5)]:
        want = direct_ll(pair_features(s, b, c), reg)
        assert sc.pair[b, c] == pytest.approx(want, rel=1e-9, abs=1e-6)
        assert sc.pair[c, b] == pytest.approx(want, rel=1e-9, abs=1e-6)
    assert np.isneginf(sc.triple[0, 0, 1]) and np.isneginf(sc.pair[2, 2])
    # a structure's score is its eq. 18-20 sum
    st = Structure(((0, 1, 2), (3, 1, 2), (4, 2, 3), (5, 3, 4)), 6)
    want = sc.triple[0, 1, 2] + sum(sc.triple[a, b, c] - sc.pair[b, c] for a, b, c in st.triangles[1:])
    assert sc.score(st.array[None])[0] == pytest.approx(want)
    assert sc.per_frame(st) == pytest.approx(want / 300)
    with pytest.raises(ValueError, match="at least 2"):
        ss.TripleScores.from_states(s[:1])


def test_greedy_is_valid_and_respects_root_pairs():
    s, _ = chain_states(seed=1)
    sc = ss.TripleScores.from_states(s)
    g = ss.greedy(sc, N)
    assert structure_problem(g.structure.array, N) == ""
    assert g.fitness == pytest.approx(sc.score(g.structure.array[None])[0])
    rp = np.array([[5, 7], [0, 8]])
    g2 = ss.greedy(sc, N, rp)
    assert ops.root_ok(g2.structure.array[0], rp)
    assert g2.fitness <= g.fitness + 1e-9 or ops.root_ok(g.structure.array[0], rp)


def test_ga_results_are_valid_and_monotone():
    s, _ = chain_states(seed=2)
    sc = ss.TripleScores.from_states(s)
    rp = np.array([[1, 2], [3, 4]])
    for fn in (ss.cbga, ss.simple_ga):
        r = fn(sc, N, population=20, generations=15, stagnation=100, seed=0, root_pairs=rp)
        assert is_valid(r.structure.array, N) and ops.root_ok(r.structure.array[0], rp)
        assert r.fitness == pytest.approx(sc.score(r.structure.array[None])[0])
        assert np.all(np.diff(r.history) >= -1e-9), "elitism: the best never gets worse"
        assert r.history[-1] == pytest.approx(r.fitness)
        assert r.generations == 15 and r.stop_reason == "max_generations"
        assert r.evaluations == 20 + 15 * 18
    # same seed, same result
    a = ss.cbga(sc, N, population=20, generations=10, seed=4)
    b = ss.cbga(sc, N, population=20, generations=10, seed=4)
    assert a.structure == b.structure and a.history == b.history


# Fixed a priori: the first 8 seeds; an equal budget for both GAs (no early stop: 40 x 100).
SEEDS = range(8)
BUDGET = dict(population=40, generations=100, stagnation=100)


@functools.lru_cache(maxsize=None)
def _runs(seed):
    s, _ = chain_states(seed=seed)
    sc = ss.TripleScores.from_states(s)
    g = ss.greedy(sc, N)
    c = ss.cbga(sc, N, seed=seed, **BUDGET)
    a = ss.simple_ga(sc, N, seed=seed, **BUDGET)
    assert c.evaluations == a.evaluations
    r = ss.refine(sc, c, N, np.random.default_rng(seed))      # what training does after CBGA
    return g.fitness, c.fitness, a.fitness, r.fitness


def test_cbga_beats_simple_ga_same_budget():
    """A GA is stochastic: at equal evaluations CBGA must win on average and on most seeds
    (one seed in eight lost narrowly when this was written; that is reported, not hidden)."""
    runs = [_runs(s) for s in SEEDS]
    c = np.array([r[1] for r in runs])
    a = np.array([r[2] for r in runs])
    assert c.mean() > a.mean(), f"CBGA mean {c.mean():.1f} <= SGA mean {a.mean():.1f}"
    assert (c >= a - 1e-6).sum() >= len(SEEDS) - 2, list(zip(c.round(1), a.round(1)))


@pytest.mark.parametrize("seed", SEEDS)
def test_refined_cbga_at_least_greedy(seed):
    g, c, _, r = _runs(seed)
    assert r >= c - 1e-9, "refinement never loses fitness"
    assert r >= g - 1e-6, f"seed {seed}: refined CBGA {r:.1f} < greedy {g:.1f}"


# ---------------------------------------------------------------- GA pieces
def test_ga_pieces():
    p = ga.geometric_rank_probabilities(5, 0.2)
    assert p.sum() == pytest.approx(1) and np.all(np.diff(p) < 0)
    with pytest.raises(ValueError):
        ga.geometric_rank_probabilities(5, 1.5)
    rng = np.random.default_rng(0)
    picks = ga.rank_select(np.array([0.0, np.nan, 5.0, -np.inf]), 4000, rng, q=0.5)
    counts = np.bincount(picks, minlength=4)
    assert counts[2] > counts[0] > counts[1] and counts[2] > counts[3]
    assert list(ga.elite_indices(np.array([1.0, np.nan, 3.0, 2.0]), 2)) == [2, 3]
    t = ga.Termination(max_generations=50, stagnation=3).start()
    assert not t.done(0, 1.0)
    assert not t.done(1, 1.0) and not t.done(2, 1.0)
    assert t.done(3, 1.0) and t.reason == "stagnation"
    t = ga.Termination(max_generations=2, stagnation=10).start()
    assert not t.done(1, 1.0) and t.done(2, 2.0) and t.reason == "max_generations"
