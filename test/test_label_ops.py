"""Constraint-based label-assignment operators: every output is a valid assignment."""
import inspect
import itertools

import numpy as np
import pytest
from hypothesis import assume, given, settings, strategies as st

from dtm_labeler.search import label_ops as ops
from dtm_labeler.search.label_search import targeted_moves


def brute_valid(row, n):
    row = np.asarray(row)
    if ((row < 0) | (row > n)).any():
        return False
    pts = row[row < n]
    return len(set(pts.tolist())) == pts.size


SIZES = st.tuples(st.integers(0, 9), st.integers(1, 9))       # (n points, M labels): n<M, n==M, n>M


def test_is_valid_matches_brute_force():
    rng = np.random.default_rng(0)
    for n, M in [(0, 3), (2, 5), (4, 4), (7, 3)]:
        pop = rng.integers(-1, n + 2, size=(300, M))
        assert ops.is_valid(pop, n).tolist() == [brute_valid(r, n) for r in pop]
    # several missing labels are fine, a repeated point is not
    assert ops.is_valid(np.array([[3, 3, 0], [3, 0, 0]]), 3).tolist() == [True, False]


@settings(max_examples=80, deadline=None)
@given(size=SIZES, seed=st.integers(0, 2 ** 31), p_missing=st.sampled_from([0.0, 0.3]))
def test_sample_is_valid_and_uses_points(size, seed, p_missing):
    n, M = size
    rng = np.random.default_rng(seed)
    pop = ops.sample(12, M, n, rng, p_missing)
    assert pop.shape == (12, M) and pop.dtype == np.int64
    assert ops.is_valid(pop, n).all()
    if p_missing == 0:
        # an injective map: min(n, M) labels get a point
        assert ((pop < n).sum(1) == min(n, M)).all()


@settings(max_examples=80, deadline=None)
@given(size=SIZES, seed=st.integers(0, 2 ** 31), p_mut=st.floats(0, 1))
def test_crossover_and_mutate_outputs_are_valid(size, seed, p_mut):
    n, M = size
    rng = np.random.default_rng(seed)
    pa, pb = ops.sample(10, M, n, rng, 0.2), ops.sample(10, M, n, rng, 0.2)
    order = rng.permutation(M)
    kids = ops.crossover(pa, pb, order, n, rng)
    assert kids.shape == pa.shape and ops.is_valid(kids, n).all()
    mut = ops.mutate(kids, n, rng, p_mut)
    assert ops.is_valid(mut, n).all()
    assert ops.is_valid(ops.mutate(mut, n, rng, 1.0, p_missing=0.5), n).all()
    # every gene of a child comes from a parent at the same label, or was repaired
    inherited = (kids == pa) | (kids == pb)
    assert inherited.mean() > 0.5
    if "pairs" in inspect.signature(ops.mutate).parameters and M >= 2:
        pairs = np.array([[0, 1]])
        assert ops.is_valid(ops.mutate(kids, n, rng, p_mut, pairs=pairs, p_mirror=0.5), n).all()


@settings(max_examples=80, deadline=None)
@given(size=SIZES, seed=st.integers(0, 2 ** 31), fill=st.booleans(), data=st.data())
def test_repair_makes_any_rows_valid_and_keeps_valid_rows(size, seed, fill, data):
    n, M = size
    rng = np.random.default_rng(seed)
    raw = np.array(data.draw(st.lists(st.lists(st.integers(-2, n + 2), min_size=M, max_size=M),
                                      min_size=1, max_size=8)))
    out = ops.repair(raw, n, rng, fill=fill)
    assert out.shape == raw.shape and ops.is_valid(out, n).all()
    valid_rows = np.array([brute_valid(r, n) for r in raw])
    assert np.array_equal(out[valid_rows], raw[valid_rows])
    # a point held by one label only, in range, is never taken away
    for r, o in zip(raw, out):
        for lab, v in enumerate(r):
            if 0 <= v < n and (r == v).sum() == 1:
                assert o[lab] == v
        # every conflicting point stays with exactly one of its claimants
        for v in set(r[(r >= 0) & (r < n)].tolist()):
            assert (o == v).sum() == 1
        if fill:
            # losers get free points while there are any: labelled count = min(M, distinct + free)
            claimed = len(set(r[(r >= 0) & (r < n)].tolist()))
            losers = int(((r >= 0) & (r < n)).sum()) - claimed
            assert (o < n).sum() == claimed + min(losers, n - claimed)


def test_used_mask():
    pop = np.array([[0, 3, 2], [3, 3, 3]])
    assert ops.used_mask(pop, 3).tolist() == [[True, False, True], [False, False, False]]


def _expected_neighbours(ind, n, with_missing):
    ind = list(int(v) for v in ind)
    M = len(ind)
    out = set()
    for i, j in itertools.combinations(range(M), 2):
        r = ind.copy()
        r[i], r[j] = r[j], r[i]
        out.add(tuple(r))
    for lab in range(M):
        for p in range(n):
            if ind[lab] == p:
                continue
            r = ind.copy()
            if p in ind:
                r[ind.index(p)] = ind[lab]
            r[lab] = p
            out.add(tuple(r))
    if with_missing:
        for lab in range(M):
            if ind[lab] < n:
                r = ind.copy()
                r[lab] = n
                out.add(tuple(r))
    return out


@settings(max_examples=60, deadline=None)
@given(size=SIZES, seed=st.integers(0, 2 ** 31), with_missing=st.booleans())
def test_neighbourhood_is_all_single_swaps_and_moves(size, seed, with_missing):
    n, M = size
    rng = np.random.default_rng(seed)
    ind = ops.sample(1, M, n, rng, 0.3)[0]
    nb = ops.neighbourhood(ind, n, with_missing)
    assert ops.is_valid(nb, n).all()
    assert {tuple(r) for r in nb.tolist()} == _expected_neighbours(ind, n, with_missing)
    present = int((ind < n).sum())
    assert len(nb) == M * (M - 1) // 2 + M * n - present + (present if with_missing else 0)


def test_neighbourhood_mirror_move_when_supported():
    if "pairs" not in inspect.signature(ops.neighbourhood).parameters:
        pytest.skip("neighbourhood has no mirror move in this version")
    ind = np.array([0, 1, 2, 3, 6])
    nb = ops.neighbourhood(ind, 6, pairs=np.array([[0, 1], [2, 3]]))
    assert ops.is_valid(nb, 6).all()
    assert [1, 0, 3, 2, 6] in nb.tolist()


def _allowed_targeted(ind, n, pairs, free):
    """Rows a targeted move may produce: ind itself, its full mirror, one pair swapped, or one
    label moved onto a free point."""
    ind = np.asarray(ind)
    out = {tuple(ind)}
    mir = ind.copy()
    mir[pairs[:, 0]], mir[pairs[:, 1]] = ind[pairs[:, 1]], ind[pairs[:, 0]]
    out.add(tuple(mir))
    for a, b in pairs:
        r = ind.copy()
        r[a], r[b] = ind[b], ind[a]
        out.add(tuple(r))
    for lab in range(ind.size):
        for p in free:
            r = ind.copy()
            r[lab] = p
            out.add(tuple(r))
    return out


def test_targeted_moves():
    n = 6
    ind = np.array([0, 1, 6, 3, 6])               # labels 2 and 4 missing, points 2, 4, 5 free
    pairs = np.array([[0, 1], [3, 4]])
    free = np.array([2, 4, 5])
    out = targeted_moves(ind, n, pairs, free)
    rows = {tuple(r) for r in out.tolist()}
    assert tuple(out[0]) == tuple(ind)
    assert (1, 0, 6, 3, 6) in rows                # swap (0, 1)
    assert (0, 1, 6, 6, 3) in rows                # swap (3, 4): 3 goes to label 4, label 3 missing
    for lab in (2, 4):                            # every missing label onto every free point
        for p in free:
            r = ind.copy()
            r[lab] = p
            assert tuple(r) in rows
    assert rows <= _allowed_targeted(ind, n, pairs, free)
    assert ops.is_valid(out, n).all()
    full = np.array([0, 1, 2, 3, 4])
    out = targeted_moves(full, n, pairs, np.array([5]))
    rows = {tuple(r) for r in out.tolist()}
    assert {(0, 1, 2, 3, 4), (1, 0, 2, 3, 4), (0, 1, 2, 4, 3)} <= rows <= _allowed_targeted(full, n, pairs, [5])
    assert ops.is_valid(out, n).all()
    assert {tuple(r) for r in targeted_moves(full, n, np.zeros((0, 2), np.int64),
                                             np.zeros(0, np.int64)).tolist()} == {(0, 1, 2, 3, 4)}


@settings(max_examples=40, deadline=None)
@given(size=SIZES, seed=st.integers(0, 2 ** 31))
def test_targeted_moves_valid_for_random_rows(size, seed):
    n, M = size
    assume(M >= 2)
    rng = np.random.default_rng(seed)
    ind = ops.sample(1, M, n, rng, 0.4)[0]
    free = np.flatnonzero(~ops.used_mask(ind[None], n)[0])
    pairs = np.array([(2 * i, 2 * i + 1) for i in range(M // 2)]).reshape(-1, 2)
    out = targeted_moves(ind, n, pairs, free)
    assert ops.is_valid(out, n).all()
    assert {tuple(r) for r in out.tolist()} <= _allowed_targeted(ind, n, pairs, free)


def test_plain_operators_break_constraints():
    rng = np.random.default_rng(3)
    n, M = 8, 8
    pa, pb = ops.sample(200, M, n, rng), ops.sample(200, M, n, rng)
    assert not ops.is_valid(ops.crossover_plain(pa, pb, rng), n).all()
    assert not ops.is_valid(ops.mutate_plain(pa, n, rng, 0.2), n).all()
    assert ops.is_valid(ops.mutate_plain(pa, n, rng, 0.0), n).all()


def test_targeted_moves_respect_allowed():
    n, ind = 6, np.array([0, 1, 2, 6])
    pairs = np.array([[1, 2]])
    allowed = np.ones((4, n + 1), dtype=bool)
    allowed[:, 4] = False                  # point 4 is beyond every label's bounds
    allowed[3, 5] = False                  # label 3 may not take point 5
    out = targeted_moves(ind, n, pairs, np.array([4, 5]), allowed=allowed)
    assert not (out == 4).any()
    assert not ((out[:, 3] == 5)).any()
    assert sum(1 for r in out if (r == 5).any()) == 3       # labels 0, 1, 2 onto point 5


def test_repair_draws_the_same_random_numbers_whether_or_not_a_row_needs_it():
    """A single valid row comes back as it was (the shortcut the labeler's seed takes), a single
    row with a repeated point is repaired, and both use the random stream alike: what a search
    draws after a repair does not depend on whether the seed needed one."""
    valid, bad = np.array([[0, 3, 5, 2]]), np.array([[0, 3, 3, 2]])
    a, b = np.random.default_rng(7), np.random.default_rng(7)
    assert np.array_equal(ops.repair(valid, 6, a, fill=False), valid)
    fixed = ops.repair(bad, 6, b, fill=False)
    assert sorted(fixed[0][fixed[0] < 6].tolist()) == [0, 2, 3] and (fixed[0] == 6).sum() == 1
    assert a.random() == b.random()
