"""Structure strings (eq. 15): validity rules, round trips, elimination order, and the
constraint-based structure operators (eq. 16-17, 22-29) against the simple GA's plain ones."""
import itertools
import re

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from dtm_labeler.model.structure import (BODY14_GIVEN, Structure, StructureError, is_valid,
                                         structure_problem)
from dtm_labeler.motion.pointsets import BODY14, left_right_pairs
from dtm_labeler.search import structure_ops as ops

# 5 vertices, the paper's Fig. 3 shape: (A,B,C), (D,B,C), (E,C,D)
FIG3 = [(0, 1, 2), (3, 1, 2), (4, 2, 3)]


def _problem(tri, n):
    return structure_problem(np.asarray(tri, dtype=np.int64).reshape(-1, 3), n)


# ---------------------------------------------------------------- validity rules
@pytest.mark.parametrize("tri,n,message", [
    ([], 2, "need at least 3 vertices"),
    ([(0, 1, 2)], 4, "4 vertices need 2 triangles, got 1"),
    ([(0, 1, 2), (3, 1, 2), (4, 1, 2)], 4, "4 vertices need 2 triangles, got 3"),
    ([(0, 1, 2), (5, 1, 2)], 4, "vertex index out of range 0..3"),
    ([(0, 1, 2), (-1, 1, 2)], 4, "vertex index out of range"),
    ([(0, 1, 1), (3, 1, 2)], 4, "first triangle [0, 1, 1] repeats a vertex"),
    ([(0, 1, 2), (1, 0, 2)], 4, "triangle 1: new vertex 1 is already in the graph"),
    ([(0, 1, 2), (3, 1, 1)], 4, "triangle 1: parents 1,1 must be two distinct vertices"),
    ([(0, 1, 2), (3, 1, 4), (4, 0, 1)], 5, "triangle 1: parents 1,4 must be two distinct vertices already"),
    # both parents of triangle 2 are in the graph, but (2, 3) was never an edge
    ([(0, 1, 2), (3, 0, 1), (4, 2, 3)], 5, "triangle 2: parents (2,3) are not an edge of an earlier triangle"),
])
def test_each_violation_has_its_message(tri, n, message):
    got = _problem(np.asarray(tri, dtype=np.int64).reshape(-1, 3), n)
    assert message in got, got
    if n >= 3 and len(tri):
        with pytest.raises(StructureError, match=re.escape(message)):
            Structure(tuple(map(tuple, tri)), n)
        assert not is_valid(np.asarray(tri), n)


def test_valid_examples_and_vertex_set():
    assert _problem(FIG3, 5) == ""
    s = Structure(tuple(FIG3), 5)
    assert s.n_triangles == 3 and s.n_vertices == 5
    assert s.edges() == {(0, 1), (0, 2), (1, 2), (1, 3), (2, 3), (2, 4), (3, 4)}
    assert is_valid(np.array(FIG3), 5)
    # 3 vertices: one triangle, any order
    for p in itertools.permutations(range(3)):
        assert is_valid(np.array([p]), 3)


def test_edge_rule_is_stricter_than_used_vertices():
    # both parents used, but (1, 3) is not an edge: the paper's loose reading would accept it
    tri = [(0, 1, 2), (3, 0, 2), (4, 1, 3)]
    assert "not an edge" in _problem(tri, 5)


def test_string_round_trips():
    s = Structure.from_string([0, 1, 2, 3, 1, 2, 4, 2, 3])
    assert s.triangles == tuple(FIG3)
    assert s.n_vertices == 5
    assert Structure.from_string(s.to_string()) == s
    assert Structure.from_string(np.array(s.to_string()), 5) == s
    assert np.array_equal(s.array, np.array(FIG3))
    labels = ["a", "b", "c", "d", "e"]
    names = s.names(labels)
    assert names == [["a", "b", "c"], ["d", "b", "c"], ["e", "c", "d"]]
    assert Structure.from_names(names, labels) == s
    with pytest.raises(StructureError, match="not a multiple of 3"):
        Structure.from_string([0, 1, 2, 3])
    with pytest.raises(StructureError, match="unknown label 'zz'"):
        Structure.from_names([["a", "b", "zz"]], ["a", "b", "c"])
    # explicit n_vertices disagreeing with the string length
    with pytest.raises(StructureError, match="need"):
        Structure.from_string([0, 1, 2], 4)


def _is_simplicial_order(s: Structure, order):
    adj = {v: set() for v in range(s.n_vertices)}
    for a, b in s.edges():
        adj[a].add(b)
        adj[b].add(a)
    remaining = set(range(s.n_vertices))
    for v in order:
        nb = adj[v] & remaining
        for x, y in itertools.combinations(nb, 2):
            if y not in adj[x]:
                return False
        remaining.discard(v)
    return True


def test_elimination_order():
    s = Structure(tuple(FIG3), 5)
    assert s.elimination_order() == [4, 3, 0, 1, 2]
    assert _is_simplicial_order(s, s.elimination_order())
    # not every order is one: eliminating 1 first leaves neighbours 0, 2, 3 with 0-3 unjoined
    assert not _is_simplicial_order(s, [1, 0, 2, 3, 4])


def test_body14_given_is_valid_and_covers_body14():
    s = Structure.from_names(BODY14_GIVEN, BODY14)
    assert s.n_triangles == 12 and s.n_vertices == 14
    assert {v for t in BODY14_GIVEN for v in t} == set(BODY14)
    pairs = np.array([(BODY14.index(a), BODY14.index(b)) for a, b in left_right_pairs(BODY14)])
    assert ops.root_ok(s.array[0], pairs)          # shoulders: the heading pair is in the root
    assert _is_simplicial_order(s, s.elimination_order())


# ---------------------------------------------------------------- operators (property tests)
def _pairs(n):
    """Disjoint (left, right) pairs over the first vertices, like a body's mirror pairs."""
    k = max(1, n // 3)
    return np.array([(2 * i, 2 * i + 1) for i in range(k) if 2 * i + 1 < n], dtype=np.int64)


def _check(g, n, root_pairs):
    g = np.asarray(g)
    assert g.shape == (n - 2, 3)
    assert structure_problem(g, n) == "", structure_problem(g, n)
    Structure.from_string(g.ravel(), n)       # constructible
    if root_pairs is not None:
        assert ops.root_ok(g[0], root_pairs), g[0]
        first = set(g[0].tolist())
        assert any(a in first and b in first for a, b in root_pairs.tolist())


N_VERTS = st.integers(min_value=3, max_value=16)


@settings(max_examples=60, deadline=None)
@given(n=N_VERTS, seed=st.integers(0, 2 ** 31), use_pairs=st.booleans(), p_mut=st.floats(0.0, 1.0))
def test_cb_operators_always_valid(n, seed, use_pairs, p_mut):
    rng = np.random.default_rng(seed)
    rp = _pairs(n) if use_pairs else None
    pop = ops.sample(6, n, rng, rp)
    assert pop.shape == (6, n - 2, 3)
    for g in pop:
        _check(g, n, rp)
    for i in range(5):
        child = ops.crossover(pop[i], pop[i + 1], n, rng, rp)
        _check(child, n, rp)
        _check(ops.mutate(child, n, rng, p_mut, rp), n, rp)


@settings(max_examples=60, deadline=None)
@given(n=N_VERTS, seed=st.integers(0, 2 ** 31), use_pairs=st.booleans(), data=st.data())
def test_repair_of_arbitrary_strings_is_valid(n, seed, use_pairs, data):
    rng = np.random.default_rng(seed)
    rp = _pairs(n) if use_pairs else None
    raw = np.array(data.draw(st.lists(st.integers(-3, n + 3), min_size=3 * (n - 2), max_size=3 * (n - 2))))
    _check(ops.repair(raw.reshape(n - 2, 3), n, rng, rp), n, rp)


@settings(max_examples=40, deadline=None)
@given(n=N_VERTS, seed=st.integers(0, 2 ** 31))
def test_repair_keeps_valid_strings(n, seed):
    rng = np.random.default_rng(seed)
    g = ops.sample(1, n, rng)[0]
    assert np.array_equal(ops.repair(g, n, rng), g)
    rp = _pairs(n)
    g = ops.sample(1, n, rng, rp)[0]
    assert np.array_equal(ops.repair(g, n, rng, rp), g)
    # mutation with probability 0 is the identity too
    assert np.array_equal(ops.mutate(g, n, rng, 0.0, rp), g)


def test_repair_enforces_root_pair_on_a_valid_string():
    rp = np.array([[3, 4]])
    g = np.array(FIG3)                      # valid, but (3, 4) is not in the first triangle
    out = ops.repair(g, 5, np.random.default_rng(0), rp)
    _check(out, 5, rp)
    assert not np.array_equal(out, g)


def test_plain_operators_do_produce_invalid_strings():
    """The comparison CBGA vs SGA is only meaningful if SGA's operators break constraints."""
    rng = np.random.default_rng(1)
    n = 10
    pop = ops.sample(40, n, rng)
    bad_x = bad_m = 0
    for i in range(200):
        a, b = pop[rng.integers(40)], pop[rng.integers(40)]
        bad_x += not is_valid(ops.crossover_plain(a, b, rng), n)
        bad_m += not is_valid(ops.mutate_plain(a, n, rng, 0.1), n)
    assert bad_x > 40, bad_x
    assert bad_m > 40, bad_m
    # ...while the constraint-based ones never do
    for i in range(200):
        a, b = pop[rng.integers(40)], pop[rng.integers(40)]
        assert is_valid(ops.mutate(ops.crossover(a, b, n, rng), n, rng, 0.1), n)
