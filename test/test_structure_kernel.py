"""The compiled structure repair (search/structure_ops.py) gives what its Python definition
gave, string for string and draw for draw: the same seed must give the same structure search
(and so the same trained model) as before it was compiled."""
import numpy as np
from hypothesis import given, settings, strategies as st

from dtm_labeler.search import structure_ops as ops


def _edge(a, b):
    return (a, b) if a < b else (b, a)


def _repair_python(genes, n_vertices, rng, root_pairs=None):
    """The repair as Python wrote it (lists of unused vertices and edges, in order)."""
    g = np.array(genes, dtype=np.int64).reshape(-1, 3)
    g = np.where((g < 0) | (g >= n_vertices), -1, g)
    if not ops.root_ok(g[0], root_pairs):
        rp = np.asarray(root_pairs)
        hits = [p for p in rp if p[0] in g[0] or p[1] in g[0]]
        a, b = hits[rng.integers(len(hits))] if hits else rp[rng.integers(len(rp))]
        third = [v for v in g[0] if v not in (a, b) and v >= 0]
        g[0] = (a, b, third[0] if third else -1)
    unused, used, edges = list(range(n_vertices)), [], []
    for i in range(3):
        v = int(g[0, i])
        if v not in unused:
            v = unused[rng.integers(len(unused))]
            g[0, i] = v
        unused.remove(v)
        used.append(v)
    a, b, c = (int(x) for x in g[0])
    edges += [_edge(a, b), _edge(a, c), _edge(b, c)]
    for t in range(1, g.shape[0]):
        a, b, c = (int(x) for x in g[t])
        if a not in unused:
            a = unused[rng.integers(len(unused))]
        if b == c or _edge(b, c) not in edges:
            keep = [p for p in (b, c) if p in used]
            cand = [e for e in edges if keep and keep[rng.integers(len(keep))] in e] if keep else []
            b, c = cand[rng.integers(len(cand))] if cand else edges[rng.integers(len(edges))]
        g[t] = (a, b, c)
        unused.remove(a)
        used.append(a)
        edges += [_edge(a, b), _edge(a, c)]
    return g


@settings(max_examples=300, deadline=None)
@given(st.integers(3, 44), st.integers(0, 2 ** 31), st.integers(0, 3), st.integers(0, 4))
def test_compiled_repair_equals_the_python_walk(n, seed, kind, n_pairs):
    gen = np.random.default_rng(seed)
    T = n - 2
    if kind == 0:                            # anything, out of range included
        genes = gen.integers(-3, n + 3, size=(T, 3))
    else:                                    # a valid string with a few genes changed (a child)
        genes = ops.repair(np.full((T, 3), -1), n, np.random.default_rng(seed + 1)).reshape(-1)
        hit = gen.integers(0, genes.size, size=kind)
        genes[hit] = gen.integers(-1, n + 1, size=kind)
        genes = genes.reshape(T, 3)
    pairs = np.array([gen.choice(n, 2, replace=False) for _ in range(n_pairs)]) if n_pairs and n >= 4 else None
    r_compiled, r_python = np.random.default_rng(seed + 2), np.random.default_rng(seed + 2)
    got = ops.repair(genes.copy(), n, r_compiled, pairs)
    assert np.array_equal(got, _repair_python(genes.copy(), n, r_python, pairs))
    assert r_compiled.bit_generator.state == r_python.bit_generator.state     # the same draws, in number too
