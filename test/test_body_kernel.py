"""The body factors' kernels score rows against the first: the same figures as each row alone."""
from __future__ import annotations

import numpy as np

from dtm_labeler.model.body_kernel import label_members, mirrored_quads, pair_factors


def _population(rng, M, n, P):
    """Rows as a fitness call gets them: a labeling, its one- to three-label moves (missing
    included), itself again, and unrelated rows (a GA's)."""
    base = rng.permutation(n + 6)[:M]
    base = np.where(base >= n, n, base)
    rows = [base]
    for _ in range(P):
        r = base.copy()
        kind = rng.integers(4)
        if kind == 0:
            i, j = rng.choice(M, 2, replace=False)
            r[i], r[j] = r[j], r[i]
        elif kind == 1:
            r[rng.integers(M)] = n
        elif kind == 2:
            r[rng.choice(M, 3, replace=False)] = rng.permutation(r[rng.choice(M, 3, replace=False)])
        else:
            r = rng.permutation(n + 6)[:M]
            r = np.where(r >= n, n, r)
        rows.append(r)
    rows.append(base.copy())
    return np.ascontiguousarray(rows, dtype=np.int64)


def test_pair_factors_of_each_row_as_alone():
    rng = np.random.default_rng(3)
    M, n = 20, 24
    xyz = rng.normal(size=(n + 1, 3))
    xyz[n] = np.nan
    dist = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    iu, ju = np.triu_indices(M, 1)
    keep = rng.random(iu.size) < 0.5
    pairs = np.ascontiguousarray(np.stack([iu[keep], ju[keep]], 1), dtype=np.int64)
    lo = rng.uniform(0.5, 1.5, len(pairs))
    hi = lo + rng.uniform(0.0, 0.5, len(pairs))
    inv_sd = rng.uniform(1.0, 20.0, len(pairs))
    ptr, members = label_members(pairs, M)
    assert sorted(members[ptr[3]:ptr[4]].tolist()) == np.flatnonzero((pairs == 3).any(1)).tolist()
    pop = _population(rng, M, n, 200)
    together = pair_factors(pop, dist, n, pairs, lo, hi, inv_sd, ptr, members)
    alone = np.array([pair_factors(pop[p:p + 1], dist, n, pairs, lo, hi, inv_sd, ptr, members)[0]
                      for p in range(len(pop))])
    assert (alone < 0).sum() > 100                    # the factors are not all zero
    np.testing.assert_allclose(together, alone, rtol=0, atol=1e-9)
    assert together[-1] == together[0]                # the first row again: the same figure


def test_mirrored_quads_of_each_row_as_alone():
    rng = np.random.default_rng(4)
    M, n = 16, 20
    pts = rng.normal(size=(n + 1, 3))
    pts[n] = np.nan
    quads = np.ascontiguousarray([rng.choice(M, 4, replace=False) for _ in range(40)], dtype=np.int64)
    sign = rng.choice([-1.0, 1.0], len(quads))
    ptr, members = label_members(quads, M)
    pop = _population(rng, M, n, 200)
    together = mirrored_quads(pop, pts, quads, sign, ptr, members)
    alone = np.array([mirrored_quads(pop[p:p + 1], pts, quads, sign, ptr, members)[0] for p in range(len(pop))])
    assert len(np.unique(alone)) > 5
    np.testing.assert_array_equal(together, alone)
