"""Chain shifts: the fast path's move that shifts the labels of a chain of neighbouring markers
by one marker (a limb's labels carried one marker along by the tracker), on real HDM05 frames."""
import itertools

import numpy as np
import pytest

from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler
from dtm_labeler.motion.load import load_clip
from dtm_labeler.model.features import point_states
from dtm_labeler.search import label_ops as ops
from dtm_labeler.search.dtm_dp import (Candidates, _conflict, _dp_assignment, chains_of,
                                       max_product, mean_shape, model_chains, regions_of, relabel_regions,
                                       shared_candidates)
from dtm_labeler.search.label_search import sweep_regions
from dtm_labeler.search.problem import Background, FrameProblem
from dtm_labeler.training.train import TrainConfig, train_model

HDM = "markers_c3d/hdm05_bd_05-01_01_120.c3d"
ARM = ["LFHD", "RFHD", "C7", "CLAV", "STRN", "LSHO", "RSHO", "RUPA", "RELB", "RFRM", "RWRA", "RWRB", "RFIN",
       "LFWT", "RFWT"]
CHAIN = ["RFRM", "RWRA", "RWRB", "RFIN"]          # elbow side to finger


@pytest.fixture(scope="module")
def hdm(data_dir):
    return load_clip(data_dir / HDM).select(ARM)


@pytest.fixture(scope="module")
def model(hdm):
    m, _ = train_model([hdm.slice(1200, 1900)], TrainConfig(seed=0, k_max=2, structure="greedy"))
    return m


def test_chain_shifts_operator():
    n = 5
    ind = np.array([0, 1, 2, n, 4])
    chains = [np.array([[3, 2], [0, 1], [1, 3]]), np.array([[3, 2, 1]])]
    got = {tuple(c) for c in ops.chain_shifts(ind, n, chains)}
    assert (0, 1, n, 2, 4) in got                  # hole moved: 3 takes 2's point, 2 left missing
    assert (1, n, 2, n, 4) in got                  # 0 takes 1's point, 1 left missing
    assert (1, 0, 2, n, 4) in got                  # ... or takes 0's freed point (rotation)
    assert (0, n, 1, 2, 4) in got                  # three labels: 3 <- 2's, 2 <- 1's, 1 missing
    assert len(got) == 4                           # [1, 3] skipped: 3 holds no point to take
    assert ops.is_valid(ops.chain_shifts(ind, n, chains), n).all()
    only = {tuple(c) for c in ops.chain_shifts(ind, n, chains, start=ind >= n)}
    assert only == {(0, 1, n, 2, 4), (0, n, 1, 2, 4)}     # chains that start at a missing label
    allowed = np.ones((5, n + 1), dtype=bool)
    allowed[3, 2] = False                          # label 3 may not take point 2
    assert {tuple(c) for c in ops.chain_shifts(ind, n, chains, allowed, ind >= n)} == set()


def test_chain_shifts_completed_on_free_points():
    """A leg's labels passed one marker along (hip label missing, the hip's point labelled knee,
    the knee's ankle, the ankle's point unlabelled): the shift back is only whole when the
    ankle label also takes the point the carried labeling left free."""
    n = 6                                          # points: 0 hip, 1 knee, 2 ankle, 3 head, 4 ghost, 5 toe
    hip, knee, ankle, head, toe = range(5)
    ind = np.array([n, 0, 1, 3, 5])                # the carried labeling: one marker along the leg
    chains = [np.array([[hip, knee, ankle]])]
    free = np.array([2, 4])                        # the ankle's point and a ghost
    plain = {tuple(c) for c in ops.chain_shifts(ind, n, chains, start=ind >= n)}
    assert plain == {(0, 1, n, 3, 5)}              # shifted back, the ankle label left missing
    got = {tuple(c) for c in ops.chain_shifts(ind, n, chains, start=ind >= n, free=free)}
    assert got == plain | {(0, 1, 2, 3, 5), (0, 1, 4, 3, 5)}
    assert ops.is_valid(ops.chain_shifts(ind, n, chains, start=ind >= n, free=free), n).all()
    allowed = np.ones((5, n + 1), dtype=bool)
    allowed[ankle, 4] = False                      # the ghost is too far from the knee for an ankle
    got = {tuple(c) for c in ops.chain_shifts(ind, n, chains, allowed, ind >= n, free)}
    assert (0, 1, 2, 3, 5) in got and (0, 1, 4, 3, 5) not in got


def test_model_chains_follow_the_body(model, hdm):
    """The mean body the chains come from matches the take's marker distances, and the arm's
    chains step between the markers along it, in both orders."""
    pos = mean_shape(model)
    d_model = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    P = hdm.slice(1200, 1900).positions
    d_data = np.nanmedian(np.linalg.norm(P[:, :, None] - P[:, None], axis=-1), axis=0)
    iu = np.triu_indices(len(ARM), 1)
    assert np.median(np.abs(d_model[iu] - d_data[iu])) < 0.03
    chains = model_chains(model, max_len=3, k_near=4)
    assert [c.shape[1] for c in chains] == [2, 3]
    pairs = {tuple(x) for x in chains[0].tolist()}
    idx = {name: i for i, name in enumerate(model.labels)}
    for a, b in zip(CHAIN[:-1], CHAIN[1:]):
        assert (idx[a], idx[b]) in pairs and (idx[b], idx[a]) in pairs
    assert all(len(set(c)) == len(c) for c in chains[1].tolist())
    assert chains_of(model, 3, 4) is chains_of(model, 3, 4)


def _stream(model, hdm, chain_moves: int, fast_rounds: int, shift_at: int = 10, frames: int = 40):
    """Labels of a stream whose tracks carry the arm chain shifted by one marker from frame
    ``shift_at`` on (the RFRM point labelled RWRA, RWRA's RWRB, RWRB's RFIN; RFIN's point
    unlabelled): per later frame, whether the search labels are the truth."""
    clip = hdm.slice(2000, 2000 + frames)
    lab = StreamLabeler(model, LabelerSettings(chain_moves=chain_moves, fast_rounds=fast_rounds, region_checks=0, accept_drop=1e6,
                                               refit_drop=1e6, recovery="inline"))
    idx = {name: i for i, name in enumerate(model.labels)}
    right = []
    for f in range(clip.n_frames):
        r = lab.process(clip.positions[f], f / clip.rate, ids=np.arange(len(ARM)))
        if f == shift_at:
            inv = {v: k for k, v in lab.track_label.items()}
            tracks = [inv[idx[name]] for name in CHAIN]
            for tr, name in zip(tracks[:-1], CHAIN[1:]):
                lab.track_label[tr] = idx[name]
            del lab.track_label[tracks[-1]]
        if f > shift_at:
            right.append(np.array_equal(r.search_labels, np.arange(len(ARM))))
    return np.array(right)


def test_chain_moves_put_a_shifted_limb_right(model, hdm):
    """With one hill-climbing move per frame (and no region checks) single moves walk the hole
    back one marker a frame; a chain move of the whole chain puts it right in the next frame,
    and so do two chain moves of three labels with two rounds."""
    assert not _stream(model, hdm, chain_moves=0, fast_rounds=1)[:2].any()
    assert _stream(model, hdm, chain_moves=4, fast_rounds=1).all()
    assert _stream(model, hdm, chain_moves=3, fast_rounds=2).all()


def _region_case(model, hdm, frame):
    st = point_states(hdm.positions[frame - 1:frame + 1], hdm.rate)[-1]
    return FrameProblem(model, st, Background()), np.arange(model.n_labels)


def test_a_label_moved_onto_its_neighbour_is_undone_by_the_branched_region_check(model, hdm):
    """Label ``a``'s point labelled as its region neighbour ``b``, ``b``'s point left unlabelled,
    ``a`` missing (a cross-lab stream carried such a shift for 254 of 360 frames): the region's
    unconstrained DP gives ``a``'s point to both, and resolving that after keeps the shift in
    some cases; branching on the conflict restores the truth in every case."""
    regions = regions_of(model, 6)
    restored = {0: 0, 6: 0}
    cases = 0
    for frame in range(2000, 3000, 100):
        p, truth = _region_case(model, hdm, frame)
        f_true = float(p.fitness(truth[None])[0])
        for a in range(p.M):
            for b in regions[a]:
                wrong = truth.copy()
                wrong[b], wrong[a] = truth[a], p.n
                f_wrong = float(p.fitness(wrong[None])[0])
                if b == a or f_wrong >= f_true:
                    continue
                cases += 1
                for branches in restored:
                    ind, f, _ = relabel_regions(p, wrong, f_wrong, regions, [a], branches=branches)
                    assert f >= f_wrong and ops.is_valid(ind[None], p.n).all()
                    restored[branches] += f >= f_true - 1e-9
    assert cases > 500
    assert restored[6] == cases
    assert restored[0] < cases            # resolving the conflict after the DP loses some


def test_branching_on_conflicts_finds_the_exact_one_to_one_optimum(model, hdm):
    """A region's labels free over their own points, their neighbours' points and "missing", the
    rest fixed: without a budget the branched DP returns the brute-force maximum of the DP's
    objective over every one-to-one combination; with a small one never less than resolving
    the conflict after."""
    regions = regions_of(model, 5)
    conflicts = 0
    for frame in (2100, 2500, 2900):
        p, truth = _region_case(model, hdm, frame)
        b = int(p.candidate_bins(truth[None])[0])
        for a in (model.labels.index("RWRA"), model.labels.index("RELB")):
            reg = regions[a]
            cands = [np.array([truth[lab]]) for lab in range(p.M)]
            for lab in reg:
                cands[lab] = np.unique(np.append(truth[reg], p.n))
            combos = np.array(list(itertools.product(*cands)), dtype=np.int64)
            combos = combos[ops.is_valid(combos, p.n)]
            within = np.array([not (p.dist[np.ix_(c, c)] > p.bounds).any() for c in combos])

            def objective(pop):
                return p.triangle_table(pop, np.full(len(pop), b)).sum(1) + p.label_gain[pop].sum(1)
            best = objective(combos[within]).max()
            plain, exact = max_product(p, cands, b), max_product(p, cands, b, branches=100_000)
            budget = max_product(p, cands, b, branches=2)
            assert objective(exact[None])[0] == pytest.approx(best, abs=1e-6)
            assert objective(budget[None])[0] >= objective(plain[None])[0] - 1e-9
            assert ops.is_valid(np.stack([plain, exact, budget]), p.n).all()
            table = Candidates.from_lists(cands)
            conflicts += _conflict(_dp_assignment(p, table.flat, table.off, b), p.n) is not None
    assert conflicts >= 1                 # the branching was exercised


def test_a_scrambled_arm_is_put_right_by_the_wide_sweep(model, hdm):
    """A search from scratch at 41 markers settled on the right arm's labels permuted over its
    markers (upper arm on the wrist bar, elbow unlabelled, finger on the elbow: 37 nats under
    the truth). Here the arm reversed along itself, with six ghosts around the hand: one sweep
    over the body neighbourhoods whose labels share the region's points (``wide``) puts it
    right (or finds what the model likes better) on every frame; the label-and-partner regions, each label choosing among the points
    nearest to where it is now (the ghosts, for the labels on the hand), do not."""
    arm = [ARM.index(x) for x in ("RUPA", "RELB", "RFRM", "RWRA", "RWRB", "RFIN")]
    rng = np.random.default_rng(3)
    wide = plain = cases = 0
    for frame in range(2000, 3000, 100):
        p, truth = _region_case(model, hdm, frame)
        hand = p.states[truth[arm[-1]]]
        ghosts = np.repeat(hand[None], 6, 0)
        way = rng.normal(size=(6, 3))
        ghosts[:, :3] += 0.12 * way / np.linalg.norm(way, axis=1, keepdims=True)     # 12 cm from the hand
        p = FrameProblem(model, np.vstack([p.states[:p.n], ghosts]), Background())
        wrong = truth.copy()
        wrong[arm] = truth[arm[::-1]]                       # the arm's labels reversed along it
        f_true, f_wrong = (float(x) for x in p.fitness(np.stack([truth, wrong])))
        if f_wrong >= f_true:
            continue
        cases += 1
        ind, f, _ = sweep_regions(p, wrong, f_wrong, 1, 7, 4, wide=12)
        assert f >= f_wrong and ops.is_valid(ind[None], p.n).all()
        wide += f >= f_true - 1e-9                          # the truth, or what the model likes better
        ind, f, _ = sweep_regions(p, wrong, f_wrong, 1, 6, 4)
        plain += f >= f_true - 1e-9
    assert cases >= 8
    assert wide == cases
    assert plain < cases


def test_shared_candidates_give_a_region_one_pool(model, hdm):
    """Every label of the region gets the same points -- the region's own and the free ones
    nearest to them, at most ``max_candidates`` -- and "missing"; a kept label its own point."""
    p, truth = _region_case(model, hdm, 2500)
    ind = truth.copy()
    ind[ARM.index("RELB")] = p.n
    hoods = regions_of(model, 7, partner=False)
    assert regions_of(model, 7, partner=False) is hoods and len(hoods) == p.M
    region = hoods[ARM.index("RFRM")]
    assert ARM.index("RFRM") in region and region.size == 7
    free = np.zeros(p.M, dtype=bool)
    free[region] = True
    c = shared_candidates(p, ind, free, max_candidates=5)
    pools = {tuple(c[lab]) for lab in region}
    assert len(pools) == 1
    pool = np.array(next(iter(pools)))
    assert pool[-1] == p.n and pool.size <= 6
    held = ind[free & (ind < p.n)]
    kept = set(ind[~free].tolist())
    assert not kept & set(pool[:-1].tolist())
    assert set(held.tolist()) <= set(pool.tolist()) or pool.size == 6
    for lab in np.flatnonzero(~free):
        assert c[lab].tolist() == [ind[lab]]
