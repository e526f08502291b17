"""The numerical guarantees of PEVI and R2PVI (every divergence), on ridge and exact operators.

- Ridge operators (signed weights, ties, factors with no weight, values 0..1e6, lam 1e-6..1e6):
  every factor value a step rule returns is finite and in ``[0, (H - h - 1) r_max]``.
- Exact distributions: every regularized dual is in ``[min V, E V]``, nondecreasing in lam,
  tends to the minimum (over the support, or over all states when mass can move anywhere)
  as lam -> 0 and to ``E V`` as lam -> inf.
- Ridge limits: lam -> inf gives PEVI's (projected) plain ridge estimate for every divergence;
  on non-negative ridge weights every rule is nondecreasing in lam.
- Fixed cases where a wrong dual fails: signed ridge weights, values far above lam, ties
  below the values' resolution, huge lam, a moment crossing zero, a custom divergence.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import logsumexp

from r2pvi import PEVI, R2PVI
from r2pvi.algorithms.pevi import RidgeRule
from r2pvi.algorithms.r2pvi import Chi2Rule, FDivergenceRule, KLRule, TVRule
from r2pvi.duals import (
    CHI2,
    HELLINGER,
    KL,
    TV,
    FactorExpectation,
    RidgeExpectation,
    chi2_regularized,
    cholesky_gram,
    cressie_read,
    f_regularized,
    kl_regularized,
    tv_regularized,
)
from r2pvi.duals.general_f import _mass_bound
from r2pvi.duals.ranges import project_onto_range, value_range
from r2pvi.duals.regularized import row_sums
from r2pvi.engine import StepContext
from r2pvi.envs import SimulatedLinearMDP

F_DIVERGENCES = [TV, KL, CHI2, HELLINGER, cressie_read(0.5), cressie_read(2.0),
                 cressie_read(-1.0)]


def rules(lam):
    """Every step rule of PEVI and R2PVI at ``lam``."""
    out = {"pevi": RidgeRule(), "tv": TVRule(lam, "data"), "tv0": TVRule(lam, 0.0),
           "kl": KLRule(lam), "kl-paper": KLRule(lam, "paper"), "chi2": Chi2Rule(lam)}
    for div in F_DIVERGENCES:
        out["f-" + div.name] = FDivergenceRule(lam, div, "data")
    return out


def ridge_problem(seed, n, d, kind, scale, ties, gamma):
    """A ridge operator and next-step values like the engine's."""
    rng = np.random.default_rng(seed)
    if kind == "simplex":
        phi = rng.dirichlet(np.full(d, rng.choice([0.2, 1.0, 5.0])), size=n)
    elif kind == "onehot":
        phi = np.eye(d)[rng.integers(d, size=n)]
    else:  # signed features: strongly signed ridge weights
        phi = rng.normal(size=(n, d))
    if d > 1 and rng.random() < 0.3:
        phi[:, rng.integers(d)] = 0.0  # a factor no sample activates (zero total weight)
    E = RidgeExpectation(phi, cholesky_gram(phi, gamma))
    v = rng.uniform(0.0, scale, size=n)
    if ties:
        v = np.round(v / scale * 3) * scale / 3  # few distinct values, the minimum included
    if rng.random() < 0.3:
        v[rng.random(n) < 0.5] = 0.0  # many zeros (fail states)
    return E, v


ridge_cases = st.tuples(
    st.integers(0, 2**31 - 1),
    st.integers(2, 24),
    st.integers(1, 4),
    st.sampled_from(["simplex", "onehot", "signed"]),
    st.sampled_from([1.0, 3.0, 1e3, 1e6]),
    st.booleans(),
    st.sampled_from([1e-3, 0.1, 1.0]),
    st.floats(-6.0, 6.0),
    st.integers(0, 2),
)


def context(scale, h, horizon=4):
    """A step whose bound (H - h - 1) r_max equals ``scale``."""
    return StepContext(h, horizon, scale / (horizon - h - 1), horizon * scale / (horizon - h - 1))


@settings(max_examples=120)
@given(ridge_cases)
def test_every_rule_is_finite_and_within_the_step_range_on_ridge_operators(case):
    seed, n, d, kind, scale, ties, gamma, log_lam, h = case
    E, v = ridge_problem(seed, n, d, kind, scale, ties, gamma)
    ctx = context(scale, h)
    lam = 10.0**log_lam
    lo, hi = value_range(v, ctx.next_value_bound)
    assert (lo, hi) == (0.0, scale)
    for name, rule in rules(lam).items():
        w = rule(E, v, ctx)
        assert w.shape == (d,), name
        assert np.all(np.isfinite(w)), (name, w)
        assert np.all((w >= lo) & (w <= hi)), (name, w, hi)


@settings(max_examples=120)
@given(ridge_cases)
def test_chi2_never_exceeds_the_plain_estimate_and_kl_stays_near_the_sample(case):
    """The exact regularized dual never exceeds E V (mu = mu0 is feasible), and neither do
    the estimates on signed ridge weights: chi^2 (whose estimated variance can be negative)
    stays at most the plain estimate, and so does every KL factor; a KL factor whose
    estimated moment is <= 0 gets the plain estimate (not the step's bound, the most
    optimistic value there is, nor ``max(E_i(v), s_i max v)``, above the lam -> inf
    limit)."""
    seed, n, d, kind, scale, ties, gamma, log_lam, h = case
    E, v = ridge_problem(seed, n, d, kind, scale, ties, gamma)
    ctx = context(scale, h)
    lam = 10.0**log_lam
    lo, hi = value_range(v, ctx.next_value_bound)
    plain = np.clip(E(v), lo, hi)
    tol = 1e-9 * scale
    assert np.all(Chi2Rule(lam)(E, v, ctx) <= plain + tol)
    s = E(np.ones(n))
    moment = E(np.exp(-(v - v.min()) / lam))
    blind = (s > 0) & (moment <= -1e-12 * np.abs(E.matrix).sum(axis=1))
    w = KLRule(lam)(E, v, ctx)
    np.testing.assert_allclose(w[blind], plain[blind], rtol=0, atol=tol)
    assert np.all(w <= plain + tol)


@settings(max_examples=40)
@given(ridge_cases)
def test_lambda_to_infinity_gives_the_plain_ridge_estimate(case):
    seed, n, d, kind, scale, ties, gamma, _, h = case
    E, v = ridge_problem(seed, n, d, kind, scale, ties, gamma)
    ctx = context(scale, h)
    plain = RidgeRule()(E, v, ctx)
    mass = np.abs(E.matrix).sum(axis=1)
    tol = 1e-6 * scale * (1.0 + mass)
    # KL's normalized form is the dual of the weights M_i / s_i: its distance to the plain
    # estimate is ~ (1 / 2 lam) |E_i((V-c)^2) - E_i(V-c)^2 / s_i| <= spread^2 (mass_i +
    # mass_i^2 / s_i) / (2 lam), so lam must grow like mass_i / s_i for factors whose signed
    # weights nearly cancel (s_i -> 0+; seed 51732652: s_0 = 1.2e-4 with mass 1.0).
    s = row_sums(E)
    live = s > 0
    kl_scale = max(1.0, float((mass[live] / s[live]).max())) if live.any() else 1.0
    for name, rule in (rules(1e8 * scale) | {"kl": KLRule(1e8 * scale * kl_scale)}).items():
        if name == "kl-paper":
            continue  # the literal form's bias -lam log s_i grows with lam (tested below)
        if name.startswith("f-") and kind != "onehot":
            # Algorithm 1 maximizes over alpha an estimate that is not concave when weights
            # are signed: the sup can pick another alpha (the range still holds).
            continue
        got = rule(E, v, ctx)
        expected = plain
        if name == "chi2":  # the paper's clip of the first moment (of V - min V) stays;
            # the cap at the plain estimate E_i(v) makes signed weights agree
            c = v.min()
            clipped = c * row_sums(E) + np.clip(E(v - c), 0.0, scale - c)
            expected = project_onto_range(np.minimum(clipped, E(v)), 0.0, scale)
        np.testing.assert_array_less(np.abs(got - expected), tol, err_msg=name)


@settings(max_examples=15)
@given(ridge_cases)
def test_on_nonnegative_ridge_weights_every_rule_is_monotone_in_lambda(case):
    seed, n, d, _, scale, ties, gamma, _, h = case
    E, v = ridge_problem(seed, n, d, "onehot", scale, ties, gamma)  # weights 1/(n_i + gamma)
    ctx = context(scale, h)
    lams = scale * np.geomspace(1e-6, 1e6, 7)
    for name in rules(1.0):
        if name in ("pevi", "kl-paper"):
            continue
        ws = np.array([rules(lam)[name](E, v, ctx) for lam in lams])
        slack = 1e-7 * scale
        assert np.all(np.diff(ws, axis=0) >= -slack), (name, ws)


def test_kl_forms_at_large_lambda_normalized_is_plain_and_paper_is_biased():
    rng = np.random.default_rng(0)
    phi = rng.dirichlet(np.ones(3), size=40)
    E = RidgeExpectation(phi, cholesky_gram(phi, 1.0))
    v = rng.uniform(0, 2, 40)
    s = row_sums(E)
    assert np.all(s < 1)
    for lam in (1e2, 1e4):
        np.testing.assert_allclose(kl_regularized(E, v, lam), E(v), atol=2e-2 * 100 / lam)
        paper = kl_regularized(E, v, lam, v_max=1e9, form="paper")
        np.testing.assert_allclose(paper - E(v) / s, -lam * np.log(s), rtol=1e-2)


@settings(max_examples=40)
@given(ridge_cases)
def test_kl_lambda_to_zero_on_nonnegative_weights_is_the_shrunk_sample_minimum(case):
    seed, n, d, _, scale, ties, gamma, _, _ = case
    E, v = ridge_problem(seed, n, d, "onehot", scale, ties, gamma)
    m = E.matrix
    s = row_sums(E)
    seen = s > 0
    factor_min = np.where(m > 0, v[None, :], np.inf).min(axis=1)
    lam = 1e-9 * scale
    got = kl_regularized(E, v, lam)
    np.testing.assert_allclose(got[seen], s[seen] * factor_min[seen],
                               atol=1e-6 * scale, rtol=1e-9)
    np.testing.assert_array_equal(got[~seen], 0.0)


# ------------------------------------------------------------------ exact distributions


def exact_problem(seed, S, d, scale, ties):
    rng = np.random.default_rng(seed)
    mu = rng.dirichlet(np.full(S, 0.7), size=d)
    mu[rng.random((d, S)) < 0.3] = 0.0  # zero-mass states (support smaller than S)
    mu[np.arange(d), rng.integers(S, size=d)] += 0.05
    mu /= mu.sum(axis=1, keepdims=True)
    v = rng.uniform(0.0, scale, S)
    if ties:
        v = np.round(v / scale * 3) * scale / 3
    return mu, v


exact_cases = st.tuples(
    st.integers(0, 2**31 - 1),
    st.integers(1, 8),
    st.integers(1, 3),
    st.sampled_from([1.0, 3.0, 1e3, 1e6]),
    st.booleans(),
)


def exact_duals(E, v, lam):
    out = {"tv": tv_regularized(E, v, lam), "kl": kl_regularized(E, v, lam),
           "chi2": chi2_regularized(E, v, lam)}
    for div in F_DIVERGENCES:
        out["f-" + div.name] = f_regularized(E, v, lam, div)
    return out


@settings(max_examples=60)
@given(exact_cases, st.floats(-6.0, 6.0))
def test_every_exact_dual_lies_between_the_minimum_and_the_expectation(case, log_lam):
    seed, S, d, scale, ties = case
    mu, v = exact_problem(seed, S, d, scale, ties)
    E = FactorExpectation(mu)
    lam = scale * 10.0**log_lam
    tol = 1e-7 * scale
    for name, w in exact_duals(E, v, lam).items():
        assert np.all(np.isfinite(w)), name
        assert np.all(w >= v.min() - tol), (name, w)
        assert np.all(w <= mu @ v + tol), (name, w, mu @ v)


@settings(max_examples=20)
@given(exact_cases)
def test_exact_duals_are_monotone_in_lambda_with_the_right_limits(case):
    seed, S, d, scale, ties = case
    mu, v = exact_problem(seed, S, d, scale, ties)
    E = FactorExpectation(mu)
    support_min = np.where(mu > 0, v, np.inf).min(axis=1)
    p_min = np.where((mu > 0) & (v == support_min[:, None]), mu, 0.0).sum(axis=1)
    lams = scale * np.geomspace(1e-9, 1e7, 9)
    table = [exact_duals(E, v, lam) for lam in lams]
    for name in table[0]:
        ws = np.array([row[name] for row in table])
        assert np.all(np.diff(ws, axis=0) >= -1e-7 * scale), (name, ws)
        # lam -> inf: the expectation
        np.testing.assert_allclose(ws[-1], mu @ v, atol=1e-5 * scale, err_msg=name)
        # lam -> 0: TV and Hellinger (bounded conjugate domain) move mass anywhere: min V;
        # the others stay on the support: the smallest value of the support.
        moves = name == "tv" or (name.startswith("f-") and np.isfinite(
            {"f-" + div.name: div for div in F_DIVERGENCES}[name].domain_max))
        limit = np.full(d, v.min()) if moves else support_min
        # f(0) = inf (cressie_read(-1)): mass cannot leave a state, the rate is sqrt(lam)
        # chi^2 is within lam (1/p - 1) of it (p the mass at the minimum): allow for tiny p.
        rate = 3e-4 if name == "f-cressie_read(-1)" else 1e-5
        excess = np.abs(ws[0] - limit) - lams[0] * (1.0 / p_min - 1.0)
        assert np.all(excess <= rate * scale), (name, ws[0], limit)


# ------------------------------------------------------------------ Algorithm 1's interval


@settings(max_examples=60)
@given(exact_cases, st.floats(-2.0, 2.0), st.sampled_from(F_DIVERGENCES[1:]))
def test_alpha_interval_contains_the_maximizer_for_every_distribution(case, log_lam, div):
    # The search interval's mass bound alpha* <= V_j + lam f'_+(1/p_j) holds at the maximizer
    # of the exact dual, found here by a fine grid over a much wider range.
    seed, S, d, _, ties = case
    mu, v = exact_problem(seed, S, d, 3.0, ties)
    lam = 10.0**log_lam
    # the bound in alpha: _mass_bound measures it from floor + lam s0
    floor, s0 = float(v.min()), div.centre
    cap = floor + lam * s0 + _mass_bound(mu, np.ones(d), v, lam, div, floor, s0)
    grid = np.linspace(v.min() - 3 - 3 * lam, v.max() + 3 + 3 * lam, 20001)
    with np.errstate(all="ignore"):
        g = grid[:, None] - lam * np.einsum(
            "ds,gs->gd", mu, div.conjugate((grid[:, None] - v[None, :]) / lam))
    g = np.where(np.isfinite(g), g, -np.inf)
    best = g.max(axis=0)
    # every grid point within 1e-9 of the best value (the flat top) lies below the cap
    step = grid[1] - grid[0]
    for i in range(d):
        top = grid[g[:, i] >= best[i] - 1e-9]
        assert top.min() <= cap[i] + step, (div.name, top.min(), cap[i])
    got = f_regularized(FactorExpectation(mu), v, lam, div)
    # the solver is never beaten by the grid and agrees with it to the grid's resolution
    assert np.all(got >= best - 1e-9 * (1 + np.abs(best))), (div.name, got, best)
    assert np.all(got <= best + 1e-3), (div.name, got, best)


def simulated_step(seed=0, h=0):
    """The step-h ridge operator and next values of PEVI (beta = 0) on the simulated MDP."""
    env = SimulatedLinearMDP(delta=0.3, xi_norm=0.3)
    ds = env.collect(100, seed=seed)
    est = PEVI(beta=0.0, gamma=0.1, reward_weights=env.theta).fit(ds)
    phi, _, next_phi, known = ds.step(h)
    v = est.values(next_phi, h + 1, known)
    return RidgeExpectation(phi, cholesky_gram(phi, 0.1)), v, env, ds


def test_general_f_on_signed_ridge_weights_stays_near_the_values():
    # Values <= 3, estimates within 1.5 max V: an interval for alpha that reached the edge of
    # the conjugate's domain (a negative weight times f* -> inf is unbounded) would give up
    # to 1e33 here.
    E, v, _, _ = simulated_step()
    assert (E.matrix < 0).any()
    for div, lam in ((HELLINGER, 0.3), (cressie_read(0.5), 0.3), (KL, 1e-3), (HELLINGER, 1e-3)):
        w = f_regularized(E, v, lam, div)
        assert np.all(np.abs(w) <= 1.5 * v.max()), (div.name, w)


# ------------------------------------------------------------------ fixed cases


def test_kl_with_zero_rewards_gives_zero_weights():
    env = SimulatedLinearMDP(delta=0.3, xi_norm=0.3)
    ds = env.collect(100, seed=1)
    zero = type(ds).from_features(ds.phi, np.zeros_like(ds.rewards), ds.next_phi,
                                  ds.next_values)
    for lam in (0.01, 1.0, 100.0):
        est = R2PVI("kl", lam, beta=0.0, gamma=0.1).fit(zero)
        np.testing.assert_array_equal(est.weights_ - est.reward_weights_, 0.0)


def test_kl_tends_to_pevi_as_lambda_grows():
    # beta = 0: the normalized form tends to PEVI as lam grows; the literal form (kl_form=
    # "paper") keeps a bias -lam log s_i that grows with lam.
    env = SimulatedLinearMDP(delta=0.3, xi_norm=0.3)
    ds = env.collect(100, seed=2)
    pevi = PEVI(beta=0.0, gamma=0.1, penalty="l1").fit(ds)
    for lam, atol in ((100.0, 1e-2), (1e4, 1e-4)):
        est = R2PVI("kl", lam, beta=0.0, gamma=0.1).fit(ds)
        np.testing.assert_allclose(est.weights_, pevi.weights_, atol=atol)
    paper = R2PVI("kl", 100.0, beta=0.0, gamma=0.1, kl_form="paper").fit(ds)
    assert np.abs(paper.weights_ - pevi.weights_).max() > 0.1  # the literal form's bias


def test_kl_estimate_does_not_hit_the_floor_on_overlapping_features():
    # Overlapping RBF-like features (signed Lambda^-1): the step bound (H - h - 1) r_max caps
    # the estimate, and with lam large the weights are the non-robust ones.
    rng = np.random.default_rng(3)
    centers = np.linspace(0, 1, 6)
    x = rng.uniform(0, 1, 400)
    phi = np.exp(-((x[:, None] - centers[None]) ** 2) / 0.05)
    phi /= phi.sum(axis=1, keepdims=True)
    E = RidgeExpectation(phi, cholesky_gram(phi, 1.0))
    v = 4.0 * np.sin(3 * x) ** 2
    ctx = StepContext(0, 30, 1.0, 30.0)
    plain = RidgeRule()(E, v, ctx)
    np.testing.assert_allclose(KLRule(1e4)(E, v, ctx), plain, atol=1e-3)
    assert np.all(KLRule(1.0)(E, v, ctx) <= ctx.next_value_bound)


def test_chi2_constant_values_return_the_constant_exactly():
    mu = np.random.default_rng(0).dirichlet(np.ones(7), size=3)
    E = FactorExpectation(mu)
    for lam in (1e-300, 1e-4, 1.0, 1e300):
        np.testing.assert_array_equal(chi2_regularized(E, np.full(7, 1e9), lam), 1e9)


def test_chi2_constant_values_on_ridge_and_clipped_moments_are_exact():
    # The centered moments: no E[V^2] - E[V]^2 cancellation (which gives ~1e19 here).
    rng = np.random.default_rng(2)
    phi = rng.dirichlet(np.ones(3), size=50)
    E = RidgeExpectation(phi, cholesky_gram(phi, 0.1))
    np.testing.assert_array_equal(chi2_regularized(E, np.full(50, 1e9), 1e-4),
                                  1e9 * row_sums(E))
    F = FactorExpectation(rng.dirichlet(np.ones(5), size=3))
    np.testing.assert_array_equal(
        chi2_regularized(F, np.full(5, 1e9), 1e-4, (0.0, 2e9), (0.0, 4e18)), 1e9)


def test_chi2_large_values_and_small_lambda_match_the_exact_primal():
    # Values up to 1e6 and lam = 1e-3: a rounding of ~eps V^2 / lam would double the true
    # excess over the minimum; the exact dual's proven interval holds it.
    # Truth: with gaps >> lam the primal's optimum is the point mass on the support's
    # minimum m (KKT), at cost lam chi^2 = lam (1/p - 1); the scaled QP agrees.
    from primal import chi2_primal

    rng = np.random.default_rng(1)
    v = np.array([0.0, 5e5 + 0.123, 7e5, 1e6, 3e5 + 0.7])
    mu = rng.dirichlet(np.ones(5), size=3)
    mu[:, 0] = 0.0
    mu /= mu.sum(axis=1, keepdims=True)
    lam = 1e-3
    m = np.where(mu > 0, v, np.inf).min(axis=1)
    p = np.where(v == m[:, None], mu, 0.0).sum(axis=1)
    truth = m + lam * (1.0 / p - 1.0)
    scaled = np.array([chi2_primal(v / 1e6, row, lam / 1e6) for row in mu]) * 1e6
    np.testing.assert_allclose(scaled - m, truth - m, rtol=1e-6)
    np.testing.assert_allclose(chi2_regularized(FactorExpectation(mu), v, lam), truth,
                               rtol=0, atol=1e-7)


@pytest.mark.parametrize("seed", [12, 54, 70])
def test_chi2_below_the_values_resolution_stays_in_the_proven_interval(seed):
    # The exact dual lies in [m, m + lam (1/p - 1)] (m: the support's minimum, p: its mass).
    # With ties and lam far below the values' resolution, a rounding of ~eps V^2 / lam would
    # leave the interval (by up to 1e172).
    rng = np.random.default_rng(seed)
    S = rng.integers(2, 9)
    mu = rng.dirichlet(np.full(S, rng.choice([0.05, 0.7])), size=2)
    v = rng.uniform(0, 1e6, S) * rng.choice([1, 1e-9, 1e9])
    if seed % 3 == 0:
        v = np.round(v, -3)
    lam = 10.0 ** rng.uniform(-300, 2)
    got = chi2_regularized(FactorExpectation(mu), v, lam)
    m = np.where(mu > 0, v, np.inf).min(axis=1)
    p = np.where(v == m[:, None], mu, 0.0).sum(axis=1)
    assert np.all(got >= m)
    assert np.all(got <= np.minimum(mu @ v, m + lam * (1.0 / p - 1.0)) * (1 + 1e-15))


def test_chi2_tiny_lambda_is_finite_and_the_support_minimum():
    rng = np.random.default_rng(1)
    mu = rng.dirichlet(np.ones(6), size=3)
    mu[0, :2] = 0.0
    mu[0] /= mu[0].sum()
    v = rng.uniform(0.0, 1e6, 6)
    got = chi2_regularized(FactorExpectation(mu), v, 1e-300)
    np.testing.assert_array_equal(got, np.where(mu > 0, v, np.inf).min(axis=1))


def test_chi2_estimator_with_tiny_lambda_is_finite_and_in_range():
    _, _, env, ds = simulated_step()
    for lam in (1e-300, 1e-4):
        est = R2PVI("chi2", lam, beta=0.0, gamma=0.1, reward_weights=env.theta).fit(ds)
        w = est.weights_ - env.theta
        assert np.all(np.isfinite(w))
        assert np.all((w >= 0) & (w <= (2 - np.arange(3))[:, None] + 1e-12))


def test_range_projection_is_a_contraction_towards_any_point_of_the_range():
    rng = np.random.default_rng(5)
    for _ in range(100):
        w = rng.normal(0, 5, 4)
        truth = rng.uniform(0, 2, 4)
        plain = truth + rng.uniform(0, 3, 4)
        p = project_onto_range(w, 0.0, 2.0, plain=plain)
        assert np.all(np.abs(p - truth) <= np.abs(w - truth) + 1e-15)


def test_direct_kl_formula_log_domain_agrees():
    # The normalized form equals s_i (c - lam log(E_i[e^{-(V-c)/lam}] / s_i)) computed directly.
    rng = np.random.default_rng(9)
    phi = rng.dirichlet(np.ones(4), size=60)
    E = RidgeExpectation(phi, cholesky_gram(phi, 0.5))
    v = rng.uniform(0, 3, 60)
    s = row_sums(E)
    for lam in (0.05, 0.5, 5.0):
        log_u, sign = logsumexp(-(v - v.min()) / lam, b=E.matrix, axis=1, return_sign=True)
        direct = s * (v.min() - lam * (np.where(sign > 0, log_u, -np.inf) - np.log(s)))
        # capped at the plain estimate (a moment <= 0: lam = 0.05 here, factor 2, where
        # max(E(v), s max v) = 2.96 is above its plain 1.78)
        direct = np.minimum(np.minimum(direct, E(v)), v.max())
        np.testing.assert_allclose(kl_regularized(E, v, lam), direct, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("bad", ["lit", None, 3])
def test_kl_form_is_validated(bad):
    env = SimulatedLinearMDP(delta=0.3, xi_norm=0.3)
    with pytest.raises(ValueError, match="kl_form"):
        R2PVI("kl", 1.0, kl_form=bad).fit(env.collect(5, seed=0))


@pytest.mark.parametrize("scale", [1e-6, 1.0])
@pytest.mark.parametrize("lam", [1e4, 1e8, 1e12])
def test_general_f_equals_the_closed_forms_at_huge_lambda(scale, lam):
    """Algorithm 1 computed around f'(1) equals the closed forms to the values' rounding and
    never exceeds E V, at lam up to 1e12 on values ~1e-6 (as ``s alpha - lam E[f*]`` it would
    cancel two terms of size lam: KL 3.4e-7 above E V at lam = 1e4, -100% at 1e12)."""
    mu = np.array([[0.2, 0.5, 0.3], [0.6, 0.1, 0.3]])
    v = np.array([1.0, 2.0, 3.0]) * scale
    E = FactorExpectation(mu)
    ev = mu @ v
    for div, closed in ((KL, kl_regularized(E, v, lam)),
                        (CHI2, chi2_regularized(E, v, lam)),
                        (cressie_read(2.0), chi2_regularized(E, v, lam / 2.0))):
        got = f_regularized(E, v, lam, div)
        np.testing.assert_allclose(got, closed, rtol=1e-12, err_msg=div.name)
        assert np.all(got <= ev), div.name


def test_general_f_is_insensitive_to_an_ulp_in_the_row_sums():
    """A 1-ulp change of the row sums (stored column sums against recomputed ones: the same
    data from memory and from a file) changes the result by at most 1e-13: the built-ins
    give f'_+ exactly (a right secant with step 1e-7 for the bound on alpha would turn it
    into ~4e-9 here, Hellinger)."""
    rng = np.random.default_rng(3)
    phi = rng.dirichlet(np.full(8, 0.5), size=300)
    v = rng.uniform(0.0, 2.0, 300)

    class Shifted(RidgeExpectation):
        def total_weights(self):
            return super().total_weights() * (1.0 + 2.0**-52)

    E = RidgeExpectation(phi, cholesky_gram(phi, 0.96))
    F = Shifted(phi, cholesky_gram(phi, 0.96))
    for div in (HELLINGER, cressie_read(2.0), cressie_read(0.5), KL):
        a, b = f_regularized(E, v, 0.358, div), f_regularized(F, v, 0.358, div)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13, err_msg=div.name)


def test_kl_is_continuous_as_the_estimated_moment_crosses_zero():
    """As lam moves the estimated moment across zero (near lam = 1.4426 here), the value is
    continuous and at most ``max(E(v), s max v)``: the floor of the normalized moment (a
    plain estimate only where the moment is <= 0 would jump from 0.571 to the bound 2.0)."""
    phi = np.array([[1.0], [-0.5]])
    E = RidgeExpectation(phi, cholesky_gram(phi, 0.5))
    v = np.array([1.0, 0.0])
    lams = np.linspace(1.40, 1.60, 401)
    w = np.array([kl_regularized(E, v, lam, v_max=2.0)[0] for lam in lams])
    assert np.all(w <= max(E(v)[0], E(np.ones(2))[0] * v.max()) + 1e-12)
    assert np.max(np.abs(np.diff(w))) < 1e-3


def test_a_custom_divergence_must_declare_its_slope_at_one():
    """The general dual is evaluated around the tangent at s0 = f'(1) (f*(s0) = s0): KL written
    by hand with the default slope_at_one (0, 0) would give 0.467 where the dual is 0.283, so
    it is refused, naming the fix; with the right slope it equals the closed form."""
    from scipy.special import xlogy

    from r2pvi import FDivergence

    def f(t):
        return xlogy(t, t)

    def conj(s):
        return np.exp(np.asarray(s) - 1.0)

    with pytest.raises(ValueError, match=r"slope_at_one=\(0.0, 0.0\).*\(1, 1\)"):
        FDivergence("kl-by-hand", f, conj)
    good = FDivergence("kl-by-hand", f, conj, slope_at_one=(1.0, 1.0))
    E = FactorExpectation(np.array([[0.5, 0.5], [0.9, 0.1]]))
    v = np.array([0.0, 1.0])
    for lam in (0.5, 2.0):
        np.testing.assert_allclose(f_regularized(E, v, lam, good), kl_regularized(E, v, lam),
                                   rtol=1e-9)


def test_general_f_never_exceeds_the_plain_estimate_on_signed_weights():
    """On signed ridge weights the sup over alpha of the estimated objective can pass E_i V
    (Hellinger by up to 0.65, TV as an FDivergence 0.46): the value is capped there."""
    worst = -np.inf
    for seed in range(12):
        rng = np.random.default_rng(seed)
        phi = rng.normal(size=(30, 4))
        v = rng.uniform(0.0, 6.0, 30)
        E = RidgeExpectation(phi, cholesky_gram(phi, 0.5))
        plain = E(v)
        for div in (HELLINGER, TV, cressie_read(2.0)):
            for lam in (0.3, 30.0):
                worst = max(worst, float(np.max(f_regularized(E, v, lam, div) - plain)))
    assert worst <= 1e-12
