"""The compiled term kernel (model/term_kernel.py) behind BatchedTerms, against the numpy
reference (PatternTerm per triangle), on a model whose triangles have different numbers of
mixture components -- the padded component slots must not count -- for every observation
pattern, including vertices that are missing (term 0) and positions without velocities."""
import numpy as np
import pytest

from dtm_labeler.model.dtm import BatchedTerms, TriangulatedModel
from dtm_labeler.model.features import N_PATTERNS, pattern_codes
from dtm_labeler.model.mixture import GaussianMixture
from dtm_labeler.training.train import TrainConfig, train_model
from dtm_labeler.motion.synthetic import synthesize

NAMES = ("neck", "lshoulder", "rshoulder", "lhip", "rhip", "lknee", "rknee")


@pytest.fixture(scope="module")
def model():
    clips = [synthesize(duration=2.0, seed=s, heading=h, noise_mm=2).select(NAMES) for s, h in [(0, 0.0), (1, 1.2)]]
    base, _ = train_model(clips, TrainConfig(mixture="fixed", k_fixed=2, structure_generations=30))
    rng = np.random.default_rng(3)
    mixtures = []
    for t, mix in enumerate(base.mixtures):          # 1, 2, 3, 4, ... components by triangle
        k = 1 + t % 4
        means = np.asarray(mix.means)[rng.integers(mix.n_components, size=k)] + rng.normal(0, 0.02, (k, 15))
        covs = np.asarray(mix.covariances)[rng.integers(mix.n_components, size=k)]
        w = rng.dirichlet(np.ones(k))
        mixtures.append(GaussianMixture(w, means, covs))
    m = TriangulatedModel(base.labels, base.structure, mixtures, base.heading_pairs, base.mirror_pairs,
                          dict(base.settings))
    assert len(set(m.components_per_triangle())) > 1
    return m


def _states(pid: int, n: int, rng) -> np.ndarray:
    s = rng.normal(scale=0.3, size=(n, 18))
    for v, code in enumerate(pattern_codes(pid)):        # zero what the pattern does not observe
        if code == 0:
            s[:, 6 * v:6 * v + 6] = 0.0
        elif code == 1:
            s[:, 6 * v + 3:6 * v + 6] = 0.0
    return s


@pytest.mark.parametrize("pid", range(N_PATTERNS))
def test_kernel_matches_per_triangle_reference(model, pid):
    rng = np.random.default_rng(pid)
    s = _states(pid, 60, rng)
    tri = rng.integers(model.structure.n_triangles, size=60)
    got = BatchedTerms(model.terms, pid)(s, tri)
    codes = np.tile(pattern_codes(pid), (60, 1))
    for t in np.unique(tri):
        sel = tri == t
        want, _ = model.triangle_terms(int(t), s[sel], codes[sel], finite=True)
        np.testing.assert_allclose(got[sel], want, rtol=1e-10, atol=1e-9)
    if pattern_codes(pid)[0] == 0:                      # A unobserved: conditional terms vanish
        assert np.all(got[tri > 0] == 0.0)


def test_kernel_takes_any_layout_and_empty_batches(model):
    batch = model.batched_full
    rng = np.random.default_rng(0)
    s = _states(26, 20, rng)
    tri = rng.integers(model.structure.n_triangles, size=20).astype(np.int32)
    want = batch(s, tri)
    np.testing.assert_allclose(batch(np.asfortranarray(s), tri[::-1][::-1]), want, rtol=0, atol=0)
    np.testing.assert_allclose(batch(s[::2], tri[::2]), want[::2], rtol=0, atol=0)
    assert batch(np.zeros((0, 18)), np.zeros(0, dtype=np.int64)).shape == (0,)
    # far from every component: finite, very negative, never NaN
    far = batch(np.full((1, 18), 1e3), np.zeros(1, dtype=np.int64))
    assert np.isfinite(far).all() and far[0] < -1e3
