"""The fast path's compiled pieces give what their numpy definitions give, row for row (the
hill-climb's arg max breaks ties by row order, so the order is part of the contract)."""
import numpy as np
from hypothesis import given, settings, strategies as st

from dtm_labeler.search import label_ops as ops
from dtm_labeler.search.frame_kernels import allowed_points
from dtm_labeler.search.label_search import targeted_moves
from dtm_labeler.search.move_kernels import close_label_pairs, free_points

SIZES = st.tuples(st.integers(0, 12), st.integers(1, 12))       # (n points, M labels)


def _moves_numpy(ind, n, mirror_pairs, free, close_pairs, allowed, release):
    """The neighbourhood as numpy wrote it (mirror image, close-pair swaps, left/right swaps,
    labels onto free points label-major, releases)."""
    out = [ind[None], ops.mirror(ind[None], mirror_pairs)]
    for pairs in (close_pairs, mirror_pairs):
        if len(pairs):
            sw = np.repeat(ind[None], len(pairs), 0)
            r = np.arange(len(pairs))
            sw[r, pairs[:, 0]], sw[r, pairs[:, 1]] = ind[pairs[:, 1]], ind[pairs[:, 0]]
            out.append(sw)
    if free.size:
        lab, pt = np.meshgrid(np.arange(ind.size), free, indexing="ij")
        lab, pt = lab.ravel(), pt.ravel()
        if allowed is not None:
            ok = allowed[lab, pt]
            lab, pt = lab[ok], pt[ok]
        mv = np.repeat(ind[None], lab.size, 0)
        mv[np.arange(lab.size), lab] = pt
        out.append(mv)
    if len(release):
        rel = np.repeat(ind[None], len(release), 0)
        rel[np.arange(len(release)), release] = n
        out.append(rel)
    return np.concatenate(out)


def _frame(rng, n, M):
    xyz = rng.random((n + 1, 3))
    dist = np.sqrt(((xyz[:, None] - xyz[None]) ** 2).sum(-1))
    dist[-1, :] = dist[:, -1] = 0.0
    bounds = np.full((M, M), np.inf)
    for a in range(M):
        for b in rng.choice(M, min(M, 3), replace=False):
            if a != b:
                bounds[a, b] = bounds[b, a] = rng.random() * 1.2
    return dist, bounds


@settings(max_examples=60, deadline=None)
@given(size=SIZES, seed=st.integers(0, 2 ** 31), with_allowed=st.booleans(), with_release=st.booleans())
def test_compiled_moves_equal_the_numpy_rows(size, seed, with_allowed, with_release):
    n, M = size
    rng = np.random.default_rng(seed)
    ind = ops.sample(1, M, n, rng, 0.4)[0]
    dist, bounds = _frame(rng, n, M)
    free = np.flatnonzero(~ops.used_mask(ind[None], n)[0])
    assert free_points(ind, n).tolist() == free.tolist()
    mirror = np.array([(2 * i, 2 * i + 1) for i in range(M // 2)], dtype=np.int64).reshape(-1, 2)
    # close pairs: labelled label pairs a < b whose points are nearer than the radius, row-major
    have = np.flatnonzero(ind < n)
    i, j = np.nonzero(np.triu(dist[np.ix_(ind[have], ind[have])] < 0.5, 1))
    close = np.stack([have[i], have[j]], axis=1).astype(np.int64)
    assert close_label_pairs(ind, n, dist, 0.5).tolist() == close.tolist()
    # allowed: within the bound of every labelled triangle neighbour; "missing" always
    d = dist[:, ind]
    allowed = ~(d[None, :, :] > bounds[:, None, :]).any(axis=2)
    allowed[:, n] = True
    assert np.array_equal(allowed_points(dist, ind, bounds, n), allowed)
    release = have if with_release else np.zeros(0, dtype=np.int64)
    got = targeted_moves(ind, n, mirror, free, close, allowed if with_allowed else None, release)
    want = _moves_numpy(ind, n, mirror, free, close, allowed if with_allowed else None, release)
    assert got.dtype == np.int64 and np.array_equal(got, want)
