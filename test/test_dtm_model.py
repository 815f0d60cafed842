"""DTM likelihood (eq. 5, 14, 19) and the marginalisation primitive (eq. 30-31), checked against
independent computations (scipy, GaussianMixture.marginal / linear_map with hand-built maps,
Monte Carlo)."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from dtm_labeler.model.dtm import LinearMixtureDensity, TriangleTerms, TriangulatedModel
from dtm_labeler.model.features import (FEATURE_MATRIX, FULL, MISSING, POSITION_ONLY,
                                        observed_map, pattern_codes, pattern_id, triangle_features)
from dtm_labeler.model.mixture import GaussianMixture
from dtm_labeler.model.structure import Structure

# X dims (eq. 12): v{A,B,C}x = 0,1,2; y = 3,4,5; z = 6,7,8; (pB-pA)xyz = 9,11,13; (pC-pA)xyz = 10,12,14
VA, VB, VC = [0, 3, 6], [1, 4, 7], [2, 5, 8]
PBA, PCA = [9, 11, 13], [10, 12, 14]


def random_mixture(seed, K=3, dim=15, scale=1.0):
    rng = np.random.default_rng(seed)
    w = rng.dirichlet(np.ones(K) * 2)
    mu = rng.normal(scale=scale, size=(K, dim))
    covs = []
    for _ in range(K):
        A = rng.normal(size=(dim, dim)) * 0.3 * scale
        covs.append(A @ A.T + np.diag(rng.uniform(0.05, 0.4, dim)) * scale ** 2)
    return GaussianMixture(w, mu, np.array(covs))


def scipy_mixture_logpdf(y, weights, means, covs):
    comp = np.stack([np.log(w) + multivariate_normal(m, c).logpdf(y) for w, m, c in zip(weights, means, covs)], -1)
    return logsumexp(comp, axis=-1)


def states_from_features(X, rng):
    """Triple states s (n, 18) with F s = X (plus a random common translation)."""
    s = X @ np.linalg.pinv(FEATURE_MATRIX).T
    t = rng.normal(size=(X.shape[0], 3)) * 5
    s[:, 0:3] += t
    s[:, 6:9] += t
    s[:, 12:15] += t
    return s


def hand_map(codes):
    """y = M X for the observable part of pattern ``codes``, built by hand from eq. 12 (not from
    observed_map): velocities of FULL vertices, positions relative to the first observed one."""
    rows = []
    vel = {0: VA, 1: VB, 2: VC}
    rel = {0: None, 1: PBA, 2: PCA}            # position relative to A
    for v in range(3):
        if codes[v] == FULL:
            for d in vel[v]:
                r = np.zeros(15)
                r[d] = 1
                rows.append(r)
    obs = [v for v in range(3) if codes[v] != MISSING]
    for v in obs[1:]:
        for ax in range(3):
            r = np.zeros(15)
            if rel[v] is not None:
                r[rel[v][ax]] += 1
            if rel[obs[0]] is not None:
                r[rel[obs[0]][ax]] -= 1
            rows.append(r)
    return np.array(rows).reshape(-1, 15)


# ---------------------------------------------------------------- the primitive
@pytest.mark.parametrize("pid", [p for p in range(27) if observed_map(pattern_codes(p)).shape[0]])
def test_linear_mixture_density_matches_scipy_of_hand_mapped_parameters(pid):
    codes = pattern_codes(pid)
    mix = random_mixture(pid)
    rng = np.random.default_rng(100 + pid)
    X = mix.sample(50, rng)
    s = states_from_features(X, rng)
    # unobserved entries: garbage (finite) that must not matter
    for v in range(3):
        if codes[v] == MISSING:
            s[:, v * 6:(v + 1) * 6] = rng.normal(size=(50, 6)) * 100
        if codes[v] == POSITION_ONLY:
            s[:, v * 6 + 3:(v + 1) * 6] = rng.normal(size=(50, 3)) * 100
    dens = LinearMixtureDensity(mix, observed_map(codes))
    M = hand_map(codes)
    assert dens.dim == M.shape[0]
    y = X @ M.T
    means = mix.means @ M.T
    covs = np.einsum("ij,kjl,ml->kim", M, mix.covariances, M)
    expected = scipy_mixture_logpdf(y, mix.weights, means, covs)
    np.testing.assert_allclose(dens(s), expected, rtol=1e-8, atol=1e-8)


def test_empty_pattern_has_density_one():
    dens = LinearMixtureDensity(random_mixture(0), observed_map((MISSING, MISSING, MISSING)))
    assert dens.dim == 0
    assert np.array_equal(dens(np.zeros((4, 18))), np.zeros(4))
    # a single observed vertex without velocity has nothing translation invariant either
    for codes in [(POSITION_ONLY, MISSING, MISSING), (MISSING, POSITION_ONLY, MISSING), (MISSING, MISSING, POSITION_ONLY)]:
        d = LinearMixtureDensity(random_mixture(0), observed_map(codes))
        assert d.dim == 0 and np.array_equal(d(np.ones((3, 18))), np.zeros(3))


def test_pure_marginal_patterns_equal_gaussian_mixture_marginal():
    """C missing (or first-seen) -> y is a sub-vector of X: compare with exact sub-indexing."""
    mix = random_mixture(7)
    rng = np.random.default_rng(7)
    X = mix.sample(200, rng)
    s = states_from_features(X, rng)
    cases = {(FULL, FULL, MISSING): VA + VB + PBA,
             (FULL, FULL, POSITION_ONLY): VA + VB + PBA + PCA,
             (POSITION_ONLY, POSITION_ONLY, POSITION_ONLY): PBA + PCA,
             (FULL, MISSING, MISSING): VA}
    for codes, dims in cases.items():
        got = LinearMixtureDensity(mix, observed_map(codes))(s)
        np.testing.assert_allclose(got, mix.marginal(sorted(dims)).log_pdf(X[:, sorted(dims)]), atol=1e-8)


def test_mapped_moments_by_monte_carlo():
    """Sample X, push through the pattern's map: sample moments = mapped mixture moments, and the
    density of y integrates to one (importance sampling with a broad Gaussian proposal)."""
    mix = random_mixture(11, K=2, scale=0.5)
    rng = np.random.default_rng(11)
    codes = (MISSING, POSITION_ONLY, POSITION_ONLY)            # 3-D: position of C relative to B
    G = observed_map(codes)
    M = hand_map(codes)
    X = mix.sample(200_000, rng)
    y = X @ M.T
    w = mix.weights
    mean = (w[:, None] * (mix.means @ M.T)).sum(0)
    second = sum(wk * (M @ Sk @ M.T + np.outer(M @ mk, M @ mk)) for wk, mk, Sk in zip(w, mix.means, mix.covariances))
    cov = second - np.outer(mean, mean)
    np.testing.assert_allclose(y.mean(0), mean, atol=4 * np.sqrt(np.diag(cov).max() / 200_000) + 1e-3)
    np.testing.assert_allclose(np.cov(y, rowvar=False), cov, atol=0.03 * np.abs(cov).max())
    # integral of p(y) dy = 1: E_q[p(y)/q(y)] with q = N(mean, 4 cov)
    dens = LinearMixtureDensity(mix, G)
    q = multivariate_normal(mean, 4 * cov)
    yq = q.rvs(200_000, random_state=rng)
    s = np.zeros((yq.shape[0], 18))
    s[:, 12:15] = yq                                           # pC - pB = y, pB = 0
    ratio = np.exp(dens(s) - q.logpdf(yq))
    se = ratio.std() / np.sqrt(ratio.size)
    assert abs(ratio.mean() - 1.0) < max(5 * se, 0.01), (ratio.mean(), se)


def _proposal_for_A(mix, s0, dims_state):
    """Importance proposal over A's state entries ``dims_state`` (B, C fixed at s0): per component,
    the Gaussian in A implied by N(F s; mu_k, S_k), covariances inflated 1.5x, equal weights."""
    F = FEATURE_MATRIX
    H = F[:, dims_state]
    c = F @ np.where(np.isin(np.arange(18), dims_state), 0.0, s0)
    comps = []
    for mu, S in zip(mix.means, mix.covariances):
        Si = np.linalg.inv(S)
        P = H.T @ Si @ H
        cov = np.linalg.inv(P)
        comps.append((cov @ H.T @ Si @ (mu - c), 1.5 * cov))
    return comps


def _importance_ratio(log_p, comps, rng, n, s0, dims_state):
    K = len(comps)
    k = rng.integers(K, size=n)
    z = np.empty((n, len(dims_state)))
    for i, (m, C) in enumerate(comps):
        sel = k == i
        z[sel] = rng.multivariate_normal(m, C, size=int(sel.sum()))
    logq = logsumexp(np.stack([multivariate_normal(m, C).logpdf(z) for m, C in comps], -1), axis=-1) - np.log(K)
    s = np.repeat(s0[None], n, 0)
    s[:, dims_state] = z
    r = np.exp(log_p(s) - logq)
    return r.mean(), r.std() / np.sqrt(n)


def test_conditional_term_integrates_to_one_over_A():
    """exp(log P(A,B,C) - log P(B,C)) is a density over A's state: E_{A~q}[p(A|B,C)/q(A)] = 1,
    for A fully observed (6-D) and A first seen (3-D position only)."""
    mix = random_mixture(5, K=2, scale=0.5)
    terms = TriangleTerms(mix, first=False)
    rng = np.random.default_rng(5)
    for trial in range(2):
        s0 = states_from_features(mix.sample(1, rng), rng)[0]
        for codes, dims in [((FULL, FULL, FULL), list(range(6))), ((POSITION_ONLY, FULL, FULL), [0, 1, 2])]:
            pid = pattern_id(np.array(codes))

            def log_p(s):
                val, roots = terms.evaluate(s, np.full(s.shape[0], pid))
                assert not roots.any()
                return val

            mean, se = _importance_ratio(log_p, _proposal_for_A(mix, s0, dims), rng, 100_000, s0, dims)
            assert se < 0.01, se
            assert abs(mean - 1.0) < 5 * se + 1e-3, (codes, mean, se)
    # the joint alone (no parent term) does NOT integrate to one over A: the test has teeth
    joint_only = LinearMixtureDensity(mix, observed_map((FULL, FULL, FULL)))
    mean, se = _importance_ratio(joint_only, _proposal_for_A(mix, s0, list(range(6))), rng, 50_000, s0,
                                 list(range(6)))
    assert abs(mean - 1.0) > 10 * se


# ---------------------------------------------------------------- the model
FIG3 = ((0, 1, 2), (3, 1, 2), (4, 2, 3))          # (A,B,C) (D,B,C) (E,C,D), paper Fig. 3


def fig3_model(seed=0):
    mixtures = [random_mixture(seed + t, K=2, scale=0.5) for t in range(3)]
    return TriangulatedModel(labels=tuple("ABCDE"), structure=Structure(FIG3, 5), mixtures=mixtures)


def frame_states(model, n, rng):
    """(n, 5, 6) states drawn roughly from the model (features of triangle 0 and 1 sampled)."""
    return rng.normal(scale=0.7, size=(n, 5, 6))


def joint(mix, states, tri):
    return mix.log_pdf(triangle_features(states, tri))


def parents_bc(mix, states, tri):
    """log P(B, C) of triangle (A, B, C): (vB, vC, pC - pB) via a hand-built linear map."""
    M = np.zeros((9, 15))
    for i, d in enumerate(VB + VC):
        M[i, d] = 1
    for ax in range(3):
        M[6 + ax, PCA[ax]] = 1
        M[6 + ax, PBA[ax]] = -1
    return mix.linear_map(M).log_pdf(triangle_features(states, tri) @ M.T)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 1000))
def test_complete_frames_equal_sum_of_joint_minus_parent_terms(seed):
    model = fig3_model(seed)
    rng = np.random.default_rng(seed)
    s = frame_states(model, 20, rng)
    mx = model.mixtures
    expected = joint(mx[0], s, FIG3[0])
    for t in (1, 2):
        expected = expected + joint(mx[t], s, FIG3[t]) - parents_bc(mx[t], s, FIG3[t])
    np.testing.assert_allclose(model.frame_log_likelihood(s), expected, rtol=1e-9, atol=1e-8)
    # one root (the first triangle) per complete frame
    np.testing.assert_allclose(model.frame_log_likelihood(s, background_position=-3.0), expected - 3.0, atol=1e-8)


def test_missing_leaf_drops_exactly_its_term():
    """Eq. 30 analogue: E is a leaf (only in the last triangle); without it the frame's
    likelihood is the complete one minus triangle 2's conditional term."""
    model = fig3_model(1)
    s = frame_states(model, 30, np.random.default_rng(1))
    full = model.frame_log_likelihood(s)
    cond2 = joint(model.mixtures[2], s, FIG3[2]) - parents_bc(model.mixtures[2], s, FIG3[2])
    s_miss = s.copy()
    s_miss[:, 4] = np.nan
    np.testing.assert_allclose(model.frame_log_likelihood(s_miss), full - cond2, atol=1e-8)


def test_missing_parent_gives_eq31_form():
    """D missing: P(A,B,C,E) = P(A,B,C) P(E|C), with P(E|C) from triangle (E,C,D) marginalised over D."""
    model = fig3_model(2)
    s = frame_states(model, 30, np.random.default_rng(2))
    s[:, 3] = np.nan
    Xe = triangle_features(np.nan_to_num(s), FIG3[2])      # (E, C, D): A=E, B=C
    m2 = model.mixtures[2]
    ec = sorted(VA + VB + PBA)
    p_e_given_c = m2.marginal(ec).log_pdf(Xe[:, ec]) - m2.marginal(sorted(VB)).log_pdf(Xe[:, sorted(VB)])
    expected = joint(model.mixtures[0], s, FIG3[0]) + p_e_given_c
    np.testing.assert_allclose(model.frame_log_likelihood(s), expected, atol=1e-8)
    # only the first triangle is a root here (E's parent C is seen)
    np.testing.assert_allclose(model.frame_log_likelihood(s, -2.0), expected - 2.0, atol=1e-8)


def test_orphaned_vertex_is_a_root_and_first_seen_points_lose_velocity():
    model = fig3_model(3)
    s = frame_states(model, 10, np.random.default_rng(3))
    s[:, 2] = np.nan
    s[:, 3] = np.nan                       # E's parents C, D both missing -> E is a root
    m2 = model.mixtures[2]
    Xe = triangle_features(np.nan_to_num(s), FIG3[2])
    # triangle 0 (A,B,C) with C missing: joint over (vA, vB, pB-pA)
    m0 = model.mixtures[0]
    X0 = triangle_features(np.nan_to_num(s), FIG3[0])
    ab = sorted(VA + VB + PBA)
    expected = m0.marginal(ab).log_pdf(X0[:, ab]) + m2.marginal(VA).log_pdf(Xe[:, VA])
    np.testing.assert_allclose(model.frame_log_likelihood(s), expected, atol=1e-8)
    np.testing.assert_allclose(model.frame_log_likelihood(s, -1.5), expected - 3.0, atol=1e-8)   # two roots
    # first-seen E (position only): its term is P(pE | pC, pD) with no velocities for E
    s2 = frame_states(model, 10, np.random.default_rng(4))
    s2[:, 4, 3:] = np.nan
    Xe = triangle_features(np.nan_to_num(s2), FIG3[2])
    keep = sorted(VB + VC + PBA + PCA)
    par = TriangleTerms(m2, first=False).pattern(pattern_id(np.array([POSITION_ONLY, FULL, FULL])))
    assert par.parents is not None and not par.root
    full = model.frame_log_likelihood(s2)
    head = (joint(model.mixtures[0], s2, FIG3[0]) + joint(model.mixtures[1], s2, FIG3[1])
            - parents_bc(model.mixtures[1], s2, FIG3[1]))
    expected_e = m2.marginal(keep).log_pdf(Xe[:, keep]) - parents_bc(m2, np.nan_to_num(s2), FIG3[2])
    np.testing.assert_allclose(full, head + expected_e, atol=1e-8)


def test_model_validation():
    good = fig3_model(0)
    with pytest.raises(ValueError, match="3 mixtures for|mixtures for"):
        TriangulatedModel(labels=tuple("ABCDE"), structure=good.structure, mixtures=good.mixtures[:2])
    with pytest.raises(ValueError, match="structure has 5 vertices"):
        TriangulatedModel(labels=tuple("ABCD"), structure=good.structure, mixtures=good.mixtures)
    with pytest.raises(ValueError, match="dimension 9"):
        TriangulatedModel(labels=tuple("ABCDE"), structure=good.structure,
                          mixtures=good.mixtures[:2] + [random_mixture(0, dim=9)])
    with pytest.raises(ValueError, match="heading pair"):
        TriangulatedModel(labels=tuple("ABCDE"), structure=good.structure, mixtures=good.mixtures,
                          heading_pairs=[[0, 7]])
    assert good.n_labels == 5 and good.components_per_triangle() == [2, 2, 2]
    assert good.heading_bins == 720


def test_models_with_the_same_mixtures_share_their_built_patterns():
    """model/dtm.py shared_triangle_terms: a model rebuilt with mixtures of the same numbers (a
    subject calibration, a reload, the same noise_mm again) reuses the patterns already built;
    other numbers, another place in the structure (first triangle or not) or an evicted entry
    build afresh, and a shared term scores exactly as a fresh one."""
    from dtm_labeler.model import dtm
    a = fig3_model(11)
    b = TriangulatedModel(labels=a.labels, structure=a.structure,
                          mixtures=[GaussianMixture(np.array(m.weights), np.array(m.means), np.array(m.covariances))
                                    for m in a.mixtures])
    assert all(x is y for x, y in zip(a.terms, b.terms))
    assert a.with_noise(1e-3).terms[0] is a.with_noise(1e-3).terms[0]
    assert a.with_noise(1e-3).terms[0] is not a.terms[0] and fig3_model(12).terms[0] is not a.terms[0]
    assert dtm.shared_triangle_terms(a.mixtures[0], first=False) is not a.terms[0]
    rng = np.random.default_rng(0)
    s = frame_states(a, 30, rng)
    s[:5, 2] = np.nan                                    # a missing point: marginal patterns too
    before = a.frame_log_likelihood(s)
    fresh = TriangleTerms(a.mixtures[1], first=False)
    for pid in range(dtm.N_PATTERNS):
        p, q = a.terms[1].pattern(pid), fresh.pattern(pid)
        assert (p is None) == (q is None)
        if p is not None and not p.empty:
            x = rng.normal(size=(4, 18))
            np.testing.assert_array_equal(p(x), q(x))
    for i in range(dtm.SHARED_TERMS_MAX):                 # evicted: built afresh, same values
        dtm.shared_triangle_terms(random_mixture(5000 + i, K=1), first=False)
    c = TriangulatedModel(labels=a.labels, structure=a.structure, mixtures=a.mixtures)
    assert c.terms[1] is not a.terms[1]
    np.testing.assert_array_equal(c.frame_log_likelihood(s), before)
