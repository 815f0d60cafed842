"""Max-product DP over the DTM (Song et al.) and its uses: exactness against brute force,
the grid and per-pattern batched term evaluators against the per-triple path, body regions,
and the region checks that put a wrongly carried labeling right in the stream."""
import itertools

import numpy as np
import pytest

from dtm_labeler.search.problem import Background, FrameProblem
from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler
from dtm_labeler.model.features import point_states
from dtm_labeler.training.train import TrainConfig, train_model
from dtm_labeler.motion.synthetic import synthesize
from dtm_labeler.search import label_ops as ops

from dtm_labeler.search.dtm_dp import (Candidates, body_at_heading, max_product, mean_shape, model_regions, region_candidates,
                                       regions_of, relabel_regions, resolve_duplicates, turn_permutation,
                                       turned_labels, turned_round)

NAMES = ("neck", "lshoulder", "rshoulder", "lhip", "rhip", "lknee", "rknee", "lankle", "rankle")


@pytest.fixture(scope="module")
def model():
    clips = [synthesize(duration=2.0, seed=s, heading=h, noise_mm=2).select(NAMES)
             for s, h in [(0, 0.0), (1, 1.0), (2, 2.5)]]
    m, _ = train_model(clips, TrainConfig(mixture="fixed", k_fixed=2, structure_generations=60))
    return m


@pytest.fixture(scope="module")
def frame(model):
    """A shuffled frame with one clutter point and one point without velocity; truth."""
    clip = synthesize(duration=1.0, seed=9, heading=-1.3, noise_mm=2, start_xy=(0.5, 1.0)).select(NAMES)
    st = point_states(clip.positions, clip.rate)[40]
    perm = np.random.default_rng(0).permutation(len(NAMES))
    clutter = np.r_[st[0, :3] + [0.3, 0.4, 0.2], 0.5, 0.0, 0.0]
    states = np.vstack([st[perm], clutter])
    return states, np.argsort(perm)


def _objective(p: FrameProblem, pop: np.ndarray, b: int) -> np.ndarray:
    """What the DP maximises: triangle terms at one heading bin plus label gains."""
    return p.triangle_table(pop, np.full(len(pop), b)).sum(1) + p.label_gain[pop].sum(1)


def test_cached_terms_match_a_fresh_computation(model, frame):
    """Terms read through the frame's table (what the DP uses) equal the same keys computed
    afresh, for every observation pattern of a grid (a point without velocity, missing)."""
    states = frame[0].copy()
    states[2, 3:] = np.nan                                   # a point seen for the first time
    p = FrameProblem(model, states, Background())
    rng = np.random.default_rng(1)
    p.fitness(ops.sample(20, p.M, p.n, rng, 0.2))            # some keys cached already
    for t in (0, 1, p.T - 1):
        ca, cb, cc = (np.append(rng.choice(p.n, 4, replace=False), p.n) for _ in range(3))
        A, B, C = np.meshgrid(ca, cb, cc, indexing="ij")
        keys = p.term_key(7, t, A, B, C).ravel()
        ref = FrameProblem(model, states, Background())
        np.testing.assert_allclose(p.triple_terms(keys), ref._compute(keys), rtol=1e-10, atol=1e-9)


@pytest.mark.parametrize("pid", [26, 25, 23, 17, 8, 20, 2])
def test_batched_pattern_terms_match_each_triangle(model, pid):
    """The per-pattern batch (all triangles in one call) equals the per-triangle terms."""
    from dtm_labeler.model.features import pattern_codes
    rng = np.random.default_rng(pid)
    s = rng.normal(scale=0.3, size=(40, 18))
    codes = np.array(pattern_codes(pid))
    for v in range(3):                                       # zero what the pattern does not observe
        if codes[v] == 0:
            s[:, 6 * v:6 * v + 6] = 0.0
        elif codes[v] == 1:
            s[:, 6 * v + 3:6 * v + 6] = 0.0
    tri = rng.integers(model.structure.n_triangles, size=40)
    batch = model.batched(pid)
    got = batch(s, tri) + batch.root[tri] * -4.0
    for t in np.unique(tri):
        sel = tri == t
        val, roots = model.triangle_terms(int(t), s[sel], np.tile(codes, (sel.sum(), 1)), finite=True)
        np.testing.assert_allclose(got[sel], val + roots * -4.0, rtol=1e-10, atol=1e-9)


def test_max_product_is_exact_over_its_candidates(model, frame):
    """Labels restricted to {true point, the clutter point, missing}: the DP's choice scores
    the brute-force maximum of the objective over every injective combination."""
    states, truth = frame
    p = FrameProblem(model, states, Background())
    b = int(p.heading_bin(p.yaw(truth[None]))[0])
    cands = [np.array([truth[lab], p.n - 1, p.n]) for lab in range(p.M)]
    combos = np.array(list(itertools.product(*cands)), dtype=np.int64)
    combos = combos[ops.is_valid(combos, p.n)]
    within = np.array([not (p.dist[np.ix_(c, c)] > p.bounds).any() for c in combos])
    best = _objective(p, combos[within], b).max()
    got = max_product(p, cands, b)
    assert ops.is_valid(got[None], p.n).all()
    assert _objective(p, got[None], b)[0] == pytest.approx(best, abs=1e-6)


def test_the_body_turned_round_is_turned_back(model, frame):
    """The body seen from behind -- every left label on its right partner's point, so the
    labeling faces 180 deg from the truth -- fits worse than the truth but no single move or
    region sweep turns it; the whole-body max-product at the opposite facing does."""
    states, truth = frame
    p = FrameProblem(model, states, Background())
    behind = ops.mirror(truth[None], p.mirror_pairs)[0]
    b_true, b_behind = (int(x) for x in p.candidate_bins(np.stack([truth, behind])))
    off = abs((b_behind - b_true + p.bins // 2) % p.bins - p.bins // 2)
    assert off > p.bins // 4                                  # it faces the other way
    f_true, f_behind = (float(x) for x in p.fitness(np.stack([truth, behind])))
    assert f_true > f_behind
    got, f, evals = turned_round(p, behind, f_behind)
    assert evals > 0 and f >= f_true - 1e-6
    assert (got == truth).mean() >= 8 / 9
    assert ops.is_valid(got[None], p.n).all()


def test_turned_labels_turn_the_body_back_without_a_dp(model, frame):
    """The turned-round body's permutation exchanges the sides (the neck stays), and reading
    the labeling seen from behind through it gives the truth back in one evaluation -- what the
    whole-body DP at the opposite facing finds in many."""
    states, truth = frame
    p = FrameProblem(model, states, Background())
    perm = turn_permutation(model)
    assert sorted(perm) == list(range(p.M))
    side = {n: n[0] for n in NAMES if n[0] in "lr"}
    for i, j in enumerate(perm):
        a, b = NAMES[i], NAMES[j]
        assert (a not in side and b == a) or (a in side and side[b] != side[a] and b[1:] == a[1:])
    behind = ops.mirror(truth[None], p.mirror_pairs)[0]
    f_true, f_behind = (float(x) for x in p.fitness(np.stack([truth, behind])))
    got, f, evals = turned_labels(p, behind, f_behind)
    assert np.array_equal(got, truth) and f == pytest.approx(f_true) and evals == 1
    again, f_again, _ = turned_labels(p, truth, f_true)             # never worse: the truth stays
    assert np.array_equal(again, truth) and f_again == f_true


def test_turned_round_never_worsens_and_the_whole_body_dp_is_valid(model, frame):
    states, truth = frame
    p = FrameProblem(model, states, Background())
    f_true = float(p.fitness(truth[None])[0])
    got, f, _ = turned_round(p, truth, f_true)
    assert f >= f_true and (f > f_true or np.array_equal(got, truth))
    whole = body_at_heading(p, int(p.candidate_bins(truth[None])[0]))
    assert ops.is_valid(whole[None], p.n).all()
    assert (whole == truth).mean() >= 8 / 9                  # the exact DP at the true facing


def test_region_relabelling_repairs_a_shifted_chain(model, frame):
    states, truth = frame
    p = FrameProblem(model, states, Background())
    b = int(p.heading_bin(p.yaw(truth[None]))[0])
    regions = model_regions(model, max_size=5)
    region = max(regions, key=len)
    wrong = truth.copy()
    wrong[region] = np.roll(truth[region], 1)               # labels shifted one point along the region
    free = np.zeros(p.M, dtype=bool)
    free[region] = True
    fixed = max_product(p, region_candidates(p, wrong, free), b)
    assert np.array_equal(fixed[~free], wrong[~free])        # the rest of the body untouched
    assert _objective(p, fixed[None], b)[0] >= _objective(p, truth[None], b)[0] - 1e-6
    assert np.array_equal(fixed, truth)


def test_region_candidates_are_each_labels_sorted_distinct_points(model, frame):
    """The flat candidate table is what one sorted, repeat-free array per label would be: a
    kept label its own point, a free label with a point its nearest pool points and missing, a
    free missing label the pool points its distance bounds allow and missing; a list of arrays
    with repeats gives the same table, and ``max_product`` the same labeling from either."""
    states, truth = frame
    p = FrameProblem(model, states, Background())
    b = int(p.heading_bin(p.yaw(truth[None]))[0])
    ind = truth.copy()
    ind[3] = p.n                                             # one free label missing
    free = np.zeros(p.M, dtype=bool)
    free[[1, 3, 5]] = True
    c = region_candidates(p, ind, free, max_candidates=3)
    assert len(c) == p.M and c.off[0] == 0 and c.off[-1] == c.flat.size
    for lab in range(p.M):
        got = c[lab]
        assert np.array_equal(got, np.unique(got))           # sorted, no repeats
        if not free[lab]:
            assert got.tolist() == [ind[lab]]
        else:
            assert got[-1] == p.n and (got[:-1] < p.n).all()
    assert c[1].size == 4 and ind[1] in c[1]                 # 3 nearest (its own point first of them) + missing
    lists = [np.r_[c[lab], c[lab][::-1]] for lab in range(p.M)]    # the same, repeated and reversed
    again = Candidates.from_lists(lists)
    assert np.array_equal(again.flat, c.flat) and np.array_equal(again.off, c.off)
    assert np.array_equal(max_product(p, lists, b), max_product(p, c, b))


def _region_candidates_numpy(p: FrameProblem, ind: np.ndarray, free: np.ndarray, k: int) -> Candidates:
    """``region_candidates``' rules in numpy (what it ran until 2026-12-06): the reference."""
    n, M = p.n, p.M
    kept = np.where(free, n, ind)
    pool = np.flatnonzero(~ops.used_mask(kept[None], n)[0])
    fixed = np.flatnonzero(~free)
    points, labels = [ind[fixed], np.full(int(free.sum()), n)], [fixed, np.flatnonzero(free)]
    have = free & (ind < n)
    held = np.flatnonzero(have)
    if held.size:
        near = np.argsort(p.dist[ind[held]][:, pool], axis=1, kind="stable")[:, :k]
        points.append(pool[near].ravel())
        labels.append(np.repeat(held, near.shape[1]))
    missing = np.flatnonzero(free & (ind >= n))
    if missing.size:
        ref = ind[have]
        d = p.dist[pool][:, ref].min(1) if ref.size else np.zeros(pool.size)
        order = pool[np.argsort(d, kind="stable")]
        ok = p.allowed(kept)[missing][:, order]
        r, c = np.nonzero(ok & (np.cumsum(ok, axis=1) <= k))
        points.append(order[c])
        labels.append(missing[r])
    return Candidates.of(np.concatenate(points), np.concatenate(labels), M)


def test_compiled_region_candidates_are_the_numpy_rules(model, frame):
    """The compiled table (``dp_kernels.region_table``) is what the rules give in numpy, over
    random labelings (points missing, shuffled, on clutter), regions and candidate counts, with
    points at equal distances (ties are broken as a stable sort breaks them)."""
    states, truth = frame
    rng = np.random.default_rng(3)
    tied = np.vstack([states, states[2] + np.r_[0.05, 0.0, 0.0, 0, 0, 0], states[2] - np.r_[0.05, 0.0, 0.0, 0, 0, 0]])
    for st in (states, tied):
        p = FrameProblem(model, st, Background())
        for trial in range(60):
            ind = np.full(p.M, p.n, dtype=np.int64)
            shown = rng.permutation(p.n)[:rng.integers(0, min(p.n, p.M) + 1)]
            ind[rng.permutation(p.M)[:shown.size]] = shown
            free = rng.random(p.M) < rng.uniform(0.1, 0.9)
            k = int(rng.integers(1, 7))
            got = region_candidates(p, ind, free, max_candidates=k)
            want = _region_candidates_numpy(p, ind, free, k)
            assert np.array_equal(got.flat, want.flat) and np.array_equal(got.off, want.off), (trial, k)


def test_model_regions_hold_the_nearest_labels_on_the_mean_body(model):
    regions = model_regions(model, max_size=4)
    assert len(regions) == model.n_labels
    pos = mean_shape(model)
    assert pos.shape == (model.n_labels, 3) and np.isfinite(pos).all()
    G = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    partner = {a: b for a, b in model.mirror_pairs.tolist()} | {b: a for a, b in model.mirror_pairs.tolist()}
    for lab, reg in enumerate(regions):
        assert lab in reg and len(reg) == 4 and len(set(reg.tolist())) == 4
        if lab in partner:
            assert partner[lab] in reg
        others = [x for x in reg if x != lab and x != partner.get(lab)]
        outside = [x for x in range(model.n_labels) if x not in reg]
        assert max(G[lab, others]) <= min(G[lab, outside]) + 1e-12     # nearest first


def test_relabel_regions_never_worsens_and_repairs(model, frame):
    states, truth = frame
    p = FrameProblem(model, states, Background())
    regions = regions_of(model, 5)
    assert regions_of(model, 5) is regions                   # cached per model and size
    f_true = float(p.fitness(truth[None])[0])
    region = max(regions, key=len)
    wrong = truth.copy()
    wrong[region] = np.roll(truth[region], 1)
    f_wrong = float(p.fitness(wrong[None])[0])
    assert f_wrong < f_true
    calls = []

    def refine(x, fx):
        calls.append(fx)
        return x, fx, 0
    ind, f, evals = relabel_regions(p, wrong, f_wrong, regions, range(p.M), refine)
    assert f == pytest.approx(float(p.fitness(ind[None])[0])) and f >= f_true - 1e-9
    assert np.array_equal(ind, truth) and calls and evals > 0
    same, f2, _ = relabel_regions(p, truth, f_true, regions, range(p.M))
    assert np.array_equal(same, truth) and f2 == f_true      # already optimal: unchanged


def test_resolve_duplicates_keeps_the_best_claimant(model, frame):
    states, truth = frame
    p = FrameProblem(model, states, Background())
    dup = truth.copy()
    dup[1] = truth[0]                                        # label 1 also claims label 0's point
    out = resolve_duplicates(p, dup)
    assert ops.is_valid(out[None], p.n).all()
    options = [np.where(np.arange(p.M) == k, p.n, dup) for k in (0, 1)]
    assert p.fitness(out[None])[0] == pytest.approx(max(p.fitness(np.stack(options))))


def test_stream_region_checks_put_a_wrong_carried_labeling_right(model):
    """Tracks carrying a chain of shifted labels (as a start-up search error would leave
    them): the fast path's region checks restore the truth within a pass over the regions."""
    clip = synthesize(duration=1.5, seed=4, heading=0.7, noise_mm=1).select(NAMES)
    P = clip.positions
    results = {}
    for checks in (0, 1):
        lab = StreamLabeler(model, LabelerSettings(region_checks=checks, region_every=1, accept_drop=1e6,
                                                   refit_drop=1e6))
        wrong_frames = []
        for f in range(P.shape[0]):
            r = lab.process(P[f], f / clip.rate, ids=np.arange(len(NAMES)))
            if f == 20:                                      # corrupt what the tracks carry
                region = max(model_regions(model), key=len)
                tl = dict(lab.track_label)
                inv = {v: k for k, v in tl.items()}
                tracks = [inv[int(x)] for x in region]
                for tr, x in zip(tracks, np.roll(region, 1)):
                    lab.track_label[tr] = int(x)
            if f > 20:
                wrong_frames.append(not np.array_equal(r.search_labels, np.arange(len(NAMES))))
        results[checks] = np.array(wrong_frames)
    assert results[1][model.n_labels + 2:].sum() == 0       # repaired within one pass and kept
    assert results[1].sum() < results[0].sum() or results[0].sum() == 0


def test_region_checks_are_due_after_searches_and_periodically(model):
    clip = synthesize(duration=1.0, seed=5, heading=0.2, noise_mm=1).select(NAMES)
    lab = StreamLabeler(model, LabelerSettings(region_every=25))
    M = model.n_labels
    due = []
    for f in range(clip.n_frames):
        due.append(lab._region_checks_due(M))
        r = lab.process(clip.positions[f], f / clip.rate, ids=np.arange(M))
        assert f < 2 or not r.full_search or f == 0
    due = np.array(due)
    searches = 2                                  # the start-up frames (no velocities, then a full search)
    assert due[:M + searches - 1].all()           # one pass over the regions after the searches
    steady = np.flatnonzero(~due)
    assert steady.size > 0 and due[M + searches + 1:].sum() == sum(
        1 for f in range(M + searches + 1, clip.n_frames) if f % 25 == 0)
