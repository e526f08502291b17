"""The regularized duals against brute-force primals, limits, closed forms and a fine grid."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from primal import chi2_primal, general_primal, smooth_primal, tv_primal
from scipy.special import logsumexp, xlogy

from r2pvi.duals import (
    CHI2,
    HELLINGER,
    KL,
    TV,
    ExpectationOperator,
    FactorExpectation,
    RidgeExpectation,
    chi2_regularized,
    cholesky_gram,
    cressie_read,
    f_regularized,
    get_divergence,
    kl_regularized,
    tv_regularized,
)

TOL = 1e-6


def random_problem(seed, n, zero_mass):
    rng = np.random.default_rng(seed)
    mu0 = rng.dirichlet(np.full(n, 0.7))
    if zero_mass:
        mu0[0] = 0.0
        mu0 /= mu0.sum()
    v = rng.uniform(0.0, 3.0, size=n)
    return v, mu0


problems = st.tuples(
    st.integers(0, 2**31 - 1),
    st.integers(2, 6),
    st.booleans(),
    st.floats(0.05, 20.0),
)


def one(E, fn, *args, **kw):
    return float(fn(E, *args, **kw)[0])


@settings(max_examples=60)
@given(problems)
def test_tv_dual_equals_lp_primal(p):
    seed, n, zero, lam = p
    v, mu0 = random_problem(seed, n, zero)
    dual = one(FactorExpectation(mu0[None]), tv_regularized, v, lam)
    assert dual == pytest.approx(tv_primal(v, mu0, lam), abs=TOL)


@settings(max_examples=40)
@given(problems)
def test_kl_dual_equals_convex_primal(p):
    seed, n, zero, lam = p
    v, mu0 = random_problem(seed, n, zero)
    dual = one(FactorExpectation(mu0[None]), kl_regularized, v, lam)
    primal = smooth_primal(v, mu0, lam, lambda t: xlogy(t, t))
    assert dual == pytest.approx(primal, abs=TOL)


@settings(max_examples=60)
@given(problems)
def test_chi2_dual_equals_exact_qp_primal(p):
    seed, n, zero, lam = p
    v, mu0 = random_problem(seed, n, zero)
    dual = one(FactorExpectation(mu0[None]), chi2_regularized, v, lam)
    assert dual == pytest.approx(chi2_primal(v, mu0, lam), abs=TOL)


@settings(max_examples=25)
@given(problems, st.sampled_from(["tv", "kl", "chi2", "hellinger", 3.0, 0.5, -1.0]))
def test_general_f_dual_equals_primal(p, which):
    seed, n, zero, lam = p
    v, mu0 = random_problem(seed, n, zero)
    div = cressie_read(which) if isinstance(which, float) else get_divergence(which)
    dual = one(FactorExpectation(mu0[None]), f_regularized, v, lam, div)
    if which == "tv":
        truth = tv_primal(v, mu0, lam)
    elif which == "chi2":
        truth = chi2_primal(v, mu0, lam)
    else:
        truth = general_primal(v, mu0, lam, div)
    assert dual == pytest.approx(truth, abs=1e-6 if which != "hellinger" else 1e-5)


@settings(max_examples=60)
@given(problems)
def test_general_f_path_agrees_with_closed_forms(p):
    seed, n, zero, lam = p
    v, mu0 = random_problem(seed, n, zero)
    rng = np.random.default_rng(seed + 1)
    mu = np.vstack([mu0, rng.dirichlet(np.ones(n), size=2)])
    E = FactorExpectation(mu)
    np.testing.assert_allclose(f_regularized(E, v, lam, TV), tv_regularized(E, v, lam), atol=1e-8)
    np.testing.assert_allclose(f_regularized(E, v, lam, KL), kl_regularized(E, v, lam), atol=1e-8)
    np.testing.assert_allclose(
        f_regularized(E, v, lam, CHI2), chi2_regularized(E, v, lam), atol=1e-8
    )


def test_general_f_path_agrees_with_closed_forms_on_ridge_operator():
    # One-hot features make the ridge weights non-negative per-factor sample means; with a
    # negligible gamma each row sums to 1, the estimated dual is concave, and every path must
    # agree. (With shrinkage, rows sum to n_i / (n_i + gamma) < 1 and Algorithm 1's
    # "alpha - lam E_hat[f*]" does not shrink alpha, unlike the closed forms: a documented
    # difference of the paper's estimators, tested below.)
    rng = np.random.default_rng(7)
    idx = rng.integers(4, size=300)
    phi = np.eye(4)[idx]
    E = RidgeExpectation(phi, cholesky_gram(phi, 1e-10))
    v = rng.uniform(0, 3, size=300)
    for lam in (0.1, 1.0, 5.0):
        np.testing.assert_allclose(f_regularized(E, v, lam, TV), tv_regularized(E, v, lam),
                                   atol=1e-8)
        np.testing.assert_allclose(f_regularized(E, v, lam, KL), kl_regularized(E, v, lam),
                                   atol=1e-8)


class _Matrix(ExpectationOperator):
    """An operator with given (possibly shrunk or signed) weights, like a ridge operator."""

    def __init__(self, m):
        self.m = np.asarray(m, dtype=float)
        self.n_dims, self.n_points = self.m.shape

    def __call__(self, y):
        return self.m @ y

    def rows(self, dims=None):
        return self.m if dims is None else self.m[np.atleast_1d(dims)]


def test_general_f_with_shrunk_rows_equals_the_closed_forms():
    # Rows summing to s < 1 (ridge shrinkage): Algorithm 1 estimates the constant alpha with
    # the same weights (s alpha), so it is s times the dual of the normalized weights, like the
    # closed forms. Algorithm 1 as printed (alpha unshrunk) would add (1 - s) alpha*.
    mu = np.array([[0.3, 0.5, 0.0], [0.1, 0.2, 0.6]])  # s = 0.8, 0.9
    E = _Matrix(mu)
    v = np.array([2.0, 1.0, 0.5])
    for lam in (0.05, 0.4, 3.0):
        np.testing.assert_allclose(f_regularized(E, v, lam, TV), tv_regularized(E, v, lam),
                                   atol=1e-9)
        np.testing.assert_allclose(f_regularized(E, v, lam, KL), kl_regularized(E, v, lam),
                                   atol=1e-8)
        normalized = FactorExpectation(mu / mu.sum(axis=1, keepdims=True))
        np.testing.assert_allclose(f_regularized(E, v, lam, HELLINGER),
                                   mu.sum(axis=1) * f_regularized(normalized, v, lam, HELLINGER),
                                   atol=1e-8)


@pytest.mark.parametrize("fn", [tv_regularized, kl_regularized, chi2_regularized])
def test_lambda_to_infinity_gives_expectation(fn):
    rng = np.random.default_rng(0)
    mu = rng.dirichlet(np.ones(5), size=3)
    v = rng.uniform(0, 3, 5)
    E = FactorExpectation(mu)
    np.testing.assert_allclose(fn(E, v, 1e7), mu @ v, atol=1e-5)


@pytest.mark.parametrize("lam", [1e-3, 1e-6])
def test_lambda_to_zero_gives_minimum(lam):
    rng = np.random.default_rng(1)
    mu = rng.dirichlet(np.ones(5), size=3)
    mu[0, 2] = 0.0
    mu[0] /= mu[0].sum()
    v = rng.uniform(0, 3, 5)
    E = FactorExpectation(mu)
    # TV moves mass anywhere: the minimum over all states.
    np.testing.assert_allclose(tv_regularized(E, v, lam), np.full(3, v.min()), atol=2 * lam)
    # KL cannot leave the support: the minimum over each factor's support.
    support_min = np.array([v[row > 0].min() for row in mu])
    got = kl_regularized(E, v, lam)
    assert np.all(got >= support_min - 1e-12)
    np.testing.assert_allclose(got, support_min, atol=-lam * np.log(mu.min(where=mu > 0,
                                                                             initial=1)) + 1e-12)


@pytest.mark.parametrize("lam", [1e-3, 1e-2, 1.0, 1e2, 1e3])
def test_kl_is_finite_and_exact_over_lambda_range(lam):
    rng = np.random.default_rng(2)
    mu = rng.dirichlet(np.ones(8), size=4)
    v = rng.uniform(0, 20, 8)  # values up to H = 20
    got = kl_regularized(FactorExpectation(mu), v, lam)
    exact = -lam * logsumexp(-v / lam, b=mu, axis=1)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, exact, rtol=1e-12, atol=1e-12)


def test_kl_underflowing_factor_uses_exact_log_domain():
    # Factor 2 only sees values 3 while the global minimum is 0: exp(-3/lam) underflows at
    # lam = 1e-3 after the global shift; the answer must still be ~3, not the floor.
    phi = np.eye(2)[[0] * 50 + [1] * 50]
    v = np.r_[np.zeros(50), np.full(50, 3.0)]
    E = RidgeExpectation(phi, cholesky_gram(phi, 1e-9))
    got = kl_regularized(E, v, 1e-3, v_max=20.0)
    np.testing.assert_allclose(got, [0.0, 3.0], atol=1e-9)


def test_kl_floor_applies_to_negative_ridge_estimates():
    # A ridge estimate <= 0 is floored at exp(-v_max / lam): the estimate is v_max.
    E = FactorExpectation(np.array([[1.0, 0.0]]))
    got = kl_regularized(E, np.array([5.0, 0.0]), 1.0, v_max=2.0)
    assert got[0] == pytest.approx(2.0)


def test_chi2_exact_solver_is_never_beaten_on_a_fine_grid():
    rng = np.random.default_rng(3)
    worst = -np.inf
    for trial in range(60):
        n = int(rng.integers(2, 40))
        phi = rng.dirichlet(np.ones(3), size=n)
        E = RidgeExpectation(phi, cholesky_gram(phi, float(rng.choice([0.01, 0.1, 1.0]))))
        v = rng.uniform(-1.0 if trial % 5 == 0 else 0.0, 3.0, n)
        if trial % 7 == 0:
            v = np.round(v)  # ties
        lam = float(rng.choice([0.01, 0.1, 1.0, 10.0]))
        clips = [((0, 3), (0, 9)), (None, None), ((0, 1.0), (0, 2.0))][trial % 3]
        exact = chi2_regularized(E, v, lam, *clips, center=False)
        grid = np.unique(np.concatenate([np.linspace(v.min(), v.max(), 4001), v]))
        trunc = np.minimum(v[None, :], grid[:, None])
        e1, e2 = trunc @ E.matrix.T, (trunc**2) @ E.matrix.T
        if clips[0] is not None:
            e1, e2 = np.clip(e1, *clips[0]), np.clip(e2, *clips[1])
        g = e1 + (e1**2 - e2) / (4 * lam)
        # the maximum over alpha, at most the plain estimate E(v) (the value at mu = mu0)
        ref = np.minimum(g.max(axis=0), E(v))
        worst = max(worst, float((ref - exact).max()))
        # the exact value is attained: it is within the grid's resolution of the grid max
        assert np.all(exact >= ref - 1e-12)
        assert np.all(exact <= E(v) + 1e-12)
    assert worst <= 1e-12


@pytest.mark.parametrize("div", [TV, KL, CHI2, HELLINGER, cressie_read(2.0), cressie_read(0.5),
                                 cressie_read(-1.0), cressie_read(3.0)])
def test_conjugates_match_numerical_supremum(div):
    t = np.concatenate([np.linspace(0, 5, 20001), np.geomspace(5, 1e4, 2000)])
    fvals = div.f(t)
    for s in (-3.0, -1.0, -0.3, 0.0, 0.2, 0.45, 0.9):
        if s >= div.domain_max:
            continue
        numeric = np.max(s * t - fvals)
        assert float(div.conjugate(s)) == pytest.approx(numeric, abs=2e-3)


def test_cressie_read_special_cases():
    t = np.linspace(0, 4, 9)
    np.testing.assert_allclose(cressie_read(2.0).f(t), CHI2.f(t) / 2)
    np.testing.assert_allclose(cressie_read(0.5).f(t), 2 * HELLINGER.f(t))
    with pytest.raises(ValueError, match="k must"):
        cressie_read(1.0)
    with pytest.raises(TypeError):
        cressie_read("2")


def test_get_divergence_errors_name_the_choices():
    with pytest.raises(ValueError, match="unknown divergence"):
        get_divergence("wasserstein")
    with pytest.raises(TypeError):
        get_divergence(3)


def test_duals_are_vectorized_over_factors_and_do_not_mutate_inputs():
    rng = np.random.default_rng(4)
    mu = rng.dirichlet(np.ones(6), size=5)
    v = rng.uniform(0, 3, 6)
    v0 = v.copy()
    E = FactorExpectation(mu)
    for fn in (tv_regularized, kl_regularized, chi2_regularized):
        full = fn(E, v, 0.7)
        rows = [fn(FactorExpectation(mu[i : i + 1]), v, 0.7)[0] for i in range(5)]
        np.testing.assert_allclose(full, rows, atol=1e-12)
    np.testing.assert_array_equal(v, v0)


@settings(max_examples=40)
@given(
    st.integers(0, 2**31 - 1),
    st.integers(1, 2500),
    st.integers(1, 5),
    st.sampled_from([0.01, 0.1, 1.0, 10.0]),
    st.sampled_from(["paper", "none", "tight"]),
    st.booleans(),
)
def test_chi2_blockwise_branch_and_bound_equals_dense(seed, n, d, lam, clips, weighted):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d) * rng.choice([0.2, 1.0, 5.0]), size=n)
    if seed % 4 == 0:
        phi = phi - 0.1  # features off the simplex, negative entries
    w = rng.uniform(0.2, 1.0, n) if weighted else None
    E = RidgeExpectation(phi, cholesky_gram(phi, float(rng.choice([0.01, 1.0])), w), w)
    v = rng.uniform(-1.0 if seed % 5 == 0 else 0.0, 3.0, n)
    if seed % 3 == 0:
        v = np.round(v, 1)  # many ties
    bounds = {"paper": ((0, 3), (0, 9)), "none": (None, None), "tight": ((0, 1), (0, 2))}[clips]
    dense = chi2_regularized(E, v, lam, *bounds, method="dense")
    np.testing.assert_allclose(chi2_regularized(E, v, lam, *bounds, method="blockwise"), dense,
                               atol=1e-11)
    mu = rng.dirichlet(np.ones(n), size=d)
    F = FactorExpectation(mu)
    np.testing.assert_allclose(chi2_regularized(F, v, lam, *bounds, method="blockwise"),
                               chi2_regularized(F, v, lam, *bounds, method="dense"), atol=1e-11)


def test_chi2_method_is_checked():
    E = FactorExpectation(np.array([[1.0]]))
    with pytest.raises(ValueError, match="method must be"):
        chi2_regularized(E, np.array([1.0]), 1.0, method="fast")


def test_chi2_flat_segment_touching_a_clip_bound_is_silent_and_exact():
    # B = 0 on the segment and E1 = -0.0 / +0.0 at its ends: a "crossing" of the clip bound 0
    # whose candidate is 0/0. It must neither warn (warnings are errors here) nor change g.
    from r2pvi.duals.piecewise import segments_max

    a = np.array([[-0.0, 0.0]])
    b = np.zeros((1, 2))
    c = np.ones((1, 2))
    got = segments_max(a, b, c, np.array([1.0, 2.0]), 0.5, (0.0, 3.0), (0.0, 9.0))
    assert got[0] == pytest.approx(0.0 + (0.0 - 1.0) / 2.0)


def test_kl_matches_the_direct_formula_on_signed_ridge_estimates():
    # Signed ridge weights make some estimates of E[exp(-V/lam)] negative or tiny: the result
    # must equal -lam log max{w', exp(-v_max/lam)} computed directly (no underflow at these
    # lam), whichever path the stable computation takes.
    rng = np.random.default_rng(11)
    hits = 0
    for _ in range(40):
        n, d = 60, 4
        phi = rng.normal(size=(n, d))  # signed features, strongly signed ridge weights
        E = RidgeExpectation(phi, cholesky_gram(phi, 0.5))
        v = rng.uniform(0.0, 3.0, n)
        lam = float(rng.choice([0.5, 1.0, 2.0]))
        direct = -lam * np.log(np.maximum(E(np.exp(-v / lam)), np.exp(-3.0 / lam)))
        hits += int((E(np.exp(-v / lam)) <= 0).sum())
        np.testing.assert_allclose(kl_regularized(E, v, lam, v_max=3.0, form="paper"), direct,
                                   rtol=1e-12,
                                   atol=1e-12)
    assert hits > 0  # the negative-estimate branch was exercised
