"""The frame kernel (search/frame_kernels.py ``frame_terms``): one compiled call scores new
triples of any observation pattern, with the broad part and the edges' body factor folded in.
Against the reference it replaced -- the triples' rotated states, one batched call per
observation pattern (``TriangulatedModel.batched``), the background density of unmodelled
roots and ``TriangulatedModel.edge_terms`` -- on a real marker take, for a generic body (body
factors, no broad part) and a calibrated one (broad part applied), on a frame with missing
points, points without velocity and clutter, over all heading bins."""
import numpy as np
import pytest

from dtm_labeler.model.features import observation_state, pattern_id, point_states
from dtm_labeler.motion.load import load_clip
from dtm_labeler.search.frame_kernels import frame_terms
from dtm_labeler.search.problem import Background, FrameProblem
from dtm_labeler.training.calibrate import calibrate_on_takes, labelled_positions
from dtm_labeler.training.train import TrainConfig, train_model

HDM = "markers_c3d/hdm05_bd_05-01_01_120.c3d"
ARM = ["LFHD", "RFHD", "C7", "CLAV", "STRN", "LSHO", "RSHO", "LELB", "LFRM", "LWRA", "LWRB", "LFIN",
       "LFWT", "RFWT"]


@pytest.fixture(scope="module")
def models(data_dir):
    clip = load_clip(data_dir / HDM).select(ARM)
    train = clip.slice(0, 400)          # mixtures of 3-5 components: padded slots in the kernel
    generic, _ = train_model([train], TrainConfig(structure="greedy", seed=0))
    calibrated = calibrate_on_takes(generic, [train])
    return generic, calibrated, clip


def _frame(model, clip, rng):
    """States of a later frame: two points hidden, one seen for the first time, two ghosts."""
    P = labelled_positions(model, clip.slice(2000, 2002))
    st = point_states(P, clip.rate)[1]
    st[3] = np.nan                                        # missing
    st[8] = np.nan
    st[5, 3:] = np.nan                                    # no velocity yet
    ghosts = np.hstack([st[:2, :3] + rng.normal(0, 0.2, (2, 3)), np.full((2, 3), np.nan)])
    return np.vstack([st, ghosts])[rng.permutation(st.shape[0] + 2)]


def _reference(p: FrameProblem, keys: np.ndarray) -> np.ndarray:
    """The terms as the per-pattern batches computed them."""
    n1, T, B = p.n + 1, p.T, p.bins
    k, j, i = keys % n1, (keys // n1) % n1, (keys // n1 ** 2) % n1
    rest = keys // n1 ** 3
    t, b = rest % T, rest // T
    ang = -b * 2.0 * np.pi / B
    c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
    trip = np.stack([i, j, k], axis=1)
    st = np.nan_to_num(p.states[trip])                    # (m, 3, 6), unobserved 0
    for blk in (0, 3):
        x, y = st[..., blk].copy(), st[..., blk + 1].copy()
        st[..., blk], st[..., blk + 1] = c * x - s * y, s * x + c * y
    st = st.reshape(-1, 18)
    pids = pattern_id(p.codes[trip])
    out = np.empty(keys.size)
    for pid in np.unique(pids):
        sel = pids == pid
        terms = p.model.batched(int(pid))
        out[sel] = terms(st[sel], t[sel]) + terms.root[t[sel]] * p.background.log_position
    a, e = trip[:, [0, 0, 1]], trip[:, [1, 2, 2]]
    return out + p.model.edge_terms(t, p.dist[a, e], (a < p.n) & (e < p.n))


@pytest.mark.parametrize("which", ["generic", "calibrated"])
def test_frame_kernel_equals_the_per_pattern_batches(models, which):
    generic, calibrated, clip = models
    model = generic if which == "generic" else calibrated
    assert model.body_edges is not None
    assert model.broad_applied == (which == "calibrated")
    rng = np.random.default_rng(5)
    p = FrameProblem(model, _frame(model, clip, rng), Background())
    n1 = p.n + 1
    m = 3000
    tri = rng.integers(p.T, size=m)
    pts = rng.integers(n1, size=(m, 3))                    # row n: missing
    bins = rng.integers(p.bins, size=m)
    keys = np.unique(p.term_key(bins, tri, pts[:, 0], pts[:, 1], pts[:, 2]))
    pids = pattern_id(p.codes[np.stack([(keys // n1 ** 2) % n1, (keys // n1) % n1, keys % n1], 1)])
    assert np.unique(pids).size >= 15                      # most observation patterns in one call
    got = p._compute(keys)
    want = _reference(p, keys)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)   # the same arithmetic, up to rounding
    assert np.isfinite(got).all()
    assert p.evaluations == keys.size


def test_frame_kernel_arrays_are_the_models_own(models):
    """Empty broad and edge tables where the model has none; one set of tables per model."""
    generic, calibrated, _ = models
    bare = generic.replace(body=None)
    args = bare.kernel_tables
    assert args is bare.kernel_tables
    assert args[10].shape[0] == 0 and args[-1].shape[0] == 0          # broad stack, edge weights
    assert calibrated.kernel_tables[10].shape[0] == 27
    p = FrameProblem(bare, point_states(np.zeros((1, 4, 3)) + np.arange(4)[:, None] * 0.1, 120.0)[0],
                     Background())
    keys = p.term_key(0, 0, 0, 1, 2)[None]
    stacked, _ = bare.stacked
    pid = int(pattern_id(observation_state(p.states)[[0, 1, 2]]))
    got = frame_terms(keys, p.states, p.codes, p.dist, p.n + 1, p.T, p.bins, 0.0, *bare.kernel_tables)
    assert got.shape == (1,) and np.isfinite(got[0])
    assert stacked.W.shape[0] == 27 and pid == 9 * 1 + 3 * 1 + 1      # positions only (no velocities)


def test_frame_geometry_is_the_numpy_reading():
    """Each point's observation code and the distances between points (0 for unseen points
    and "missing") from the compiled loop are numpy's, value for value, on states with full,
    position-only, partly and wholly missing rows."""
    from dtm_labeler.model.features import FULL, MISSING, POSITION_ONLY
    from dtm_labeler.search.frame_kernels import frame_geometry
    rng = np.random.default_rng(5)
    for trial in range(20):
        st = rng.normal(size=(int(rng.integers(1, 40)), 6))
        st[rng.random(st.shape) < 0.08] = np.nan                   # a coordinate or a velocity lost
        st[rng.random(len(st)) < 0.2, :3] = np.nan                 # a whole position
        st = np.vstack([st, np.full(6, np.nan)])                   # the row of "missing"
        codes, dist = frame_geometry(st, FULL, POSITION_ONLY, MISSING)
        assert np.array_equal(codes, observation_state(st))
        diff = st[:, None, :3] - st[None, :, :3]
        want = np.sqrt((diff * diff).sum(-1))
        want[np.isnan(want)] = 0.0
        assert np.array_equal(dist, want)
