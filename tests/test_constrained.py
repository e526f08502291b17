"""The constrained (uncertainty-ball) duals against brute-force primals and their limits.

The primals ``inf {E_mu V : D(mu || mu0) <= rho}`` use no dual formula: TV is a linear
program over every state (mass may move to states where mu0 = 0), KL a convex program on
the support of mu0 solved by SLSQP (in mu and in softmax coordinates, several starts; every
candidate is feasible, so the best is an upper bound that the solvers drive to the optimum).
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog, minimize
from scipy.special import softmax

from r2pvi.duals import (
    FactorExpectation,
    RidgeExpectation,
    cholesky_gram,
    kl_constrained,
    tv_constrained,
)

TOL = 1e-6


# ------------------------------------------------------------------------- brute-force primals


def tv_ball_primal(v, mu0, rho):
    """LP: min V.mu s.t. 1/2 sum |mu - mu0| <= rho, mu in the simplex over every state."""
    n = v.size
    c = np.concatenate([v, np.zeros(n)])
    eye = np.eye(n)
    a_ub = np.block([[eye, -eye], [-eye, -eye], [np.zeros((1, n)), np.ones((1, n))]])
    b_ub = np.concatenate([mu0, -mu0, [2.0 * rho]])
    a_eq = np.concatenate([np.ones(n), np.zeros(n)])[None]
    res = linprog(c, A_ub=a_ub, b_ub=b_ub, A_eq=a_eq, b_eq=[1.0],
                  bounds=[(0, None)] * (2 * n), method="highs")
    assert res.success, res.message
    return res.fun


def _kl(mu, p):
    pos = mu > 0
    return float(np.sum(mu[pos] * np.log(mu[pos] / p[pos])))


def kl_ball_primal(v, mu0, rho):
    """min V.mu s.t. KL(mu || mu0) <= rho on the support of mu0 (SLSQP, several starts)."""
    supp = mu0 > 0
    p, vv = mu0[supp], v[supp]
    scale = max(float(np.abs(vv).max()), 1e-12)
    w = vv / scale
    n = p.size
    found = []
    for x0 in (p, 0.5 * p + 0.5 * np.eye(n)[np.argmin(w)]):
        res = minimize(
            lambda x: x @ w, x0, jac=lambda x: w, method="SLSQP", bounds=[(1e-13, 1.0)] * n,
            constraints=[
                {"type": "eq", "fun": lambda x: x.sum() - 1.0, "jac": lambda x: np.ones_like(x)},
                {"type": "ineq", "fun": lambda x: rho - _kl(x, p),
                 "jac": lambda x: -(np.log(x / p) + 1.0)},
            ],
            options={"ftol": 1e-15, "maxiter": 2000},
        )
        found.append(res.x / res.x.sum())

    def kl_z(z):
        return _kl(softmax(z), p)

    def kl_z_grad(z):
        m = softmax(z)
        g = np.log(np.maximum(m, 1e-300) / p) + 1.0
        return m * (g - m @ g)

    for z0 in [np.log(p)] + [np.log(p) - w * s for s in (1.0, 5.0, 30.0)]:
        res = minimize(
            lambda z: softmax(z) @ w, z0,
            jac=lambda z: (lambda m: m * (w - m @ w))(softmax(z)), method="SLSQP",
            constraints=[{"type": "ineq", "fun": lambda z: rho - kl_z(z),
                          "jac": lambda z: -kl_z_grad(z)}],
            options={"ftol": 1e-16, "maxiter": 2000},
        )
        found.append(softmax(res.x))
    feasible = [m @ w for m in found if _kl(m, p) <= rho + 1e-10]
    assert feasible, "no feasible primal point found"
    return min(feasible) * scale


def random_factors(seed, d, n, zero_mass):
    rng = np.random.default_rng(seed)
    mu = rng.dirichlet(np.full(n, 0.7), size=d)
    if zero_mass:
        mu[rng.random((d, n)) < 0.3] = 0.0
        mu[:, 0] += 1e-3
        mu /= mu.sum(axis=1, keepdims=True)
    return rng, mu


problems = st.tuples(
    st.integers(0, 2**31 - 1),  # seed
    st.integers(1, 3),  # d
    st.integers(2, 7),  # n states
    st.booleans(),  # states outside the support of some factors
    st.sampled_from([1.0, 10.0, 100.0]),  # value scale (up to H = 100)
)


# ------------------------------------------------------------------------------------- TV


@settings(max_examples=60)
@given(problems, st.floats(0.0, 1.5))
def test_tv_ball_equals_lp_primal(p, rho_scale):
    seed, d, n, zero, scale = p
    rng, mu = random_factors(seed, d, n, zero)
    v = rng.uniform(0.0, scale, size=n)
    rho = rho_scale * rng.uniform(0.0, 1.0, size=d)
    dual = tv_constrained(FactorExpectation(mu), v, rho)
    primal = [tv_ball_primal(v, mu[i], rho[i]) for i in range(d)]
    np.testing.assert_allclose(dual, primal, atol=TOL * scale, rtol=0)


@settings(max_examples=30)
@given(problems, st.floats(0.0, 1.2), st.floats(0.01, 1.0))
def test_tv_ball_with_v_min_below_the_values_is_an_extra_state(p, rho, gap):
    """``v_min`` below min(v): a state of value v_min with mu0 = 0 that mass may move to."""
    seed, d, n, zero, scale = p
    rng, mu = random_factors(seed, d, n, zero)
    v = rng.uniform(0.0, scale, size=n)
    v_min = v.min() - gap * scale
    dual = tv_constrained(FactorExpectation(mu), v, rho, v_min=v_min)
    extra_v = np.append(v, v_min)
    primal = [tv_ball_primal(extra_v, np.append(mu[i], 0.0), rho) for i in range(d)]
    np.testing.assert_allclose(dual, primal, atol=TOL * scale, rtol=0)


def test_tv_ball_limits_and_v_min_above_the_values_is_clamped():
    mu = np.array([[0.2, 0.3, 0.5], [0.0, 0.0, 1.0]])
    v = np.array([1.0, 4.0, 2.0])
    E = FactorExpectation(mu)
    np.testing.assert_array_equal(tv_constrained(E, v, 0.0), mu @ v)
    np.testing.assert_allclose(tv_constrained(E, v, 1.0), [1.0, 1.0])
    np.testing.assert_allclose(tv_constrained(E, v, 5.0, v_min=-1.0), [-1.0, -1.0])
    # a claimed minimum above a sampled value cannot hold: it is clamped to min(v)
    np.testing.assert_allclose(tv_constrained(E, v, 0.4, v_min=3.0), tv_constrained(E, v, 0.4))


def random_ridge(seed, n, d, weighted, signed=False):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=n)
    if signed:  # features off the simplex (negative entries), as in the American put option
        phi = phi - 0.1
    w = rng.uniform(0.2, 1.0, size=n) if weighted else None
    return rng, RidgeExpectation(phi, cholesky_gram(phi, 0.5, w), w)


@settings(max_examples=40)
@given(st.integers(0, 2**31 - 1), st.integers(1, 700), st.integers(1, 8), st.booleans(),
       st.booleans(), st.booleans())
def test_tv_ball_block_search_equals_every_breakpoint(seed, n, d, weighted, signed, ties):
    """The bounded block search equals the maximum over every breakpoint computed from the
    operator's own truncation cumulants (ridge operators, weighted or not, any features)."""
    rng, E = random_ridge(seed, n, d, weighted, signed)
    v = rng.uniform(0.0, 5.0, size=n)
    if ties:
        v[rng.random(n) < 0.4] = 0.0
    rho = rng.uniform(0.0, 1.0, size=d)
    floor = v.min() - rng.uniform(0.0, 1.0)
    np.testing.assert_allclose(tv_constrained(E, v, rho, floor, method="blockwise"),
                               tv_constrained(E, v, rho, floor, method="dense"), atol=1e-10,
                               rtol=0)


def test_tv_ball_block_search_on_factor_distributions_and_a_large_ridge_problem():
    rng, mu = random_factors(4, 5, 300, True)
    E = FactorExpectation(mu)
    v = rng.uniform(0.0, 10.0, size=300)
    rho = rng.uniform(0.0, 0.5, size=5)
    np.testing.assert_allclose(tv_constrained(E, v, rho, 0.0, method="blockwise"),
                               tv_constrained(E, v, rho, 0.0, method="dense"), atol=1e-12,
                               rtol=0)
    rng, E = random_ridge(5, 5000, 12, False)
    v = np.clip(rng.normal(3.0, 1.0, 5000), 0.0, None)
    rho = np.full(12, 0.1)
    np.testing.assert_allclose(tv_constrained(E, v, rho, 0.0, method="blockwise"),
                               tv_constrained(E, v, rho, 0.0, method="dense"), atol=1e-10,
                               rtol=0)
    with pytest.raises(ValueError, match="method must be"):
        tv_constrained(E, v, rho, method="fast")


def brute_tv_objective(E, v, rho, floor):
    """max over a dense alpha grid plus every breakpoint, by direct operator calls."""
    alphas = np.concatenate([np.linspace(floor, v.max(), 801), v, [floor]])
    vals = np.stack([E(np.minimum(v, a)) - rho * (a - floor) for a in alphas])
    return vals.max(axis=0)


def test_tv_ball_ridge_is_the_max_over_all_alphas():
    rng, E = random_ridge(3, 60, 4, True)
    v = rng.uniform(0.0, 3.0, size=60)
    rho = np.array([0.05, 0.2, 0.0, 0.7])
    got = tv_constrained(E, v, rho, v_min=-0.5)
    want = brute_tv_objective(E, v, rho, -0.5)
    want[2] = E(v)[2]  # rho = 0: the plain ridge estimate
    np.testing.assert_allclose(got, want, atol=1e-12)


# ------------------------------------------------------------------------------------- KL


@settings(max_examples=25)
@given(problems, st.floats(0.0, 3.0))
def test_kl_ball_equals_convex_primal(p, rho_scale):
    seed, d, n, zero, scale = p
    rng, mu = random_factors(seed, d, n, zero)
    v = rng.uniform(0.0, scale, size=n)
    rho = rho_scale * rng.uniform(0.0, 1.0, size=d)
    dual = kl_constrained(FactorExpectation(mu), v, rho)
    primal = [kl_ball_primal(v, mu[i], rho[i]) for i in range(d)]
    np.testing.assert_allclose(dual, primal, atol=TOL * scale, rtol=0)


def test_kl_ball_limits():
    mu = np.array([[0.5, 0.5, 0.0], [0.1, 0.2, 0.7], [0.0, 0.0, 1.0]])
    v = np.array([3.0, 1.0, 2.0])
    E = FactorExpectation(mu)
    np.testing.assert_array_equal(kl_constrained(E, v, 0.0), mu @ v)  # rho = 0: E[V], exactly
    # a radius beyond log(1/mu0(argmin)) puts all the mass on the support's minimum
    np.testing.assert_allclose(kl_constrained(E, v, 50.0), [1.0, 1.0, 2.0], atol=1e-9)
    # tiny radius: E[V] - sqrt(2 rho Var[V]) to first order
    rho = 1e-8
    var = mu @ v**2 - (mu @ v) ** 2
    np.testing.assert_allclose(kl_constrained(E, v, rho), mu @ v - np.sqrt(2 * rho * var),
                               atol=1e-8)


def test_kl_ball_is_stable_for_large_values_and_small_b():
    """Values up to H = 100 with the maximizing b = 1e-3: no overflow, and the dual equals the
    primal value of the tilted distribution q ~ mu0 exp(-V/b), which is feasible with
    KL(q || mu0) = rho and optimal (KKT), so the true answer is q.V."""
    rng = np.random.default_rng(0)
    v = np.concatenate([[0.0, 0.01], rng.uniform(50.0, 100.0, 30)])
    mu0 = np.concatenate([[0.5, 0.3], np.full(30, 0.2 / 30)])
    b_star = 1e-3
    log_q = np.log(mu0) - v / b_star
    q = np.exp(log_q - log_q.max())
    q /= q.sum()
    rho = _kl(q, mu0)
    got = kl_constrained(FactorExpectation(mu0[None]), v, rho, v_max=100.0)
    assert np.isfinite(got).all()
    assert got[0] == pytest.approx(q @ v, abs=1e-10)


def ma_objective(E, v, b, rho, v_max):
    """Ma et al. (2022): -b log(1 + clip(E(e^{-V/b} - 1), e^{-m/b} - 1, 0)) - b rho, with
    the floor applied to log u (1 + (e^{-m/b} - 1) underflows for small b); the floor is
    Jensen's, m = min(E(v), V_max) the plain estimate (Ma et al. use m = V_max)."""
    est = E(np.expm1(-v / b))
    with np.errstate(divide="ignore"):
        log_u = np.log(1.0 + np.clip(est, -1.0, 0.0))
    m = np.minimum(E(v), v_max)
    return -b * np.maximum(log_u, -m / b) - b * rho


@pytest.mark.parametrize("seed", range(4))
def test_kl_ball_centered_ridge_estimate_matches_a_dense_search(seed):
    """The centered (DRVI-L) estimate is the sup of Ma et al.'s clipped ridge objective
    (b_min=None: the search runs down to b ~ 1e-9)."""
    rng, E = random_ridge(seed, 150, 5, seed % 2 == 1)
    v = rng.uniform(0.0, 4.0, size=150)
    rho = rng.uniform(0.01, 1.0, size=5)
    got = kl_constrained(E, v, rho, v_max=5.0, centered=True)
    ts = np.linspace(np.log(5e-9), np.log(5e3), 4000)  # the solver's search range of log b
    dense = np.array([ma_objective(E, v, np.exp(t), rho, 5.0) for t in ts])  # (4000, d)
    # refine each factor's best grid cell with a second, local grid (the objective jumps
    # where the clip switches on, so a smooth local solver would not do)
    best = dense.max(axis=0)
    for i, k in enumerate(dense.argmax(axis=0)):
        local = np.linspace(ts[max(k - 1, 0)], ts[min(k + 1, ts.size - 1)], 4001)
        vals = [ma_objective(E, v, np.exp(t), rho, 5.0)[i] for t in local]
        best[i] = max(best[i], max(vals))
    assert np.all(got >= best - 1e-10)
    np.testing.assert_allclose(got, best, atol=1e-6)


def normalized_objective(E, v, b, rho, v_max):
    """DRVI-L's default estimate per unit of row mass at every ``b (J,)``: (d, J) values of
    -b log(E(e^{-V/b}) / s) - b rho with s = E(1) (computed shifted by min v), the log
    floored at Jensen's -m/(s b), m = min(E(v), V_max) the plain estimate; -inf where
    E(e^{-V/b}) <= 0 (then the floor)."""
    s = E(np.ones_like(v))[:, None]
    c = v.min()  # in the log domain shifted by the least value (no underflow at small b)
    est = E(np.exp(-(v[:, None] - c) / b[None, :])) / s
    with np.errstate(divide="ignore", invalid="ignore"):
        log_u = np.where(est > 0, -c / b + np.log(np.where(est > 0, est, 1.0)), -np.inf)
    m = np.minimum(E(v), v_max)[:, None] / s
    return -b * np.maximum(log_u, -m / b) - b * rho[:, None]


@pytest.mark.parametrize("seed", range(4))
def test_kl_ball_normalized_ridge_estimate_matches_a_dense_search(seed):
    """The normalized estimate is s_i times the sup over b of the row-normalized objective
    (b_min=None); values far from 0 (where Ma et al.'s centering is off) for seeds 2, 3."""
    rng, E = random_ridge(seed, 150, 5, seed % 2 == 1, signed=seed == 3)
    v = rng.uniform(0.0, 4.0, size=150) + (3.0 if seed >= 2 else 0.0)
    rho = rng.uniform(0.01, 1.0, size=5)
    s = E(np.ones(150))
    got = kl_constrained(E, v, rho, v_max=8.0, normalized=True)
    # the solver's search range of log b: where the floor binds as b -> 0 (signed weights at
    # the least value) the sup cap - b rho is approached at its lower end, 1e-9 max|v|
    ts = np.linspace(np.log(1e-9 * np.abs(v).max()), np.log(5e3), 4000)
    dense = normalized_objective(E, v, np.exp(ts), rho, 8.0)  # (d, 4000)
    best = dense.max(axis=1)
    for i, k in enumerate(dense.argmax(axis=1)):  # a local grid around each best cell
        local = np.linspace(ts[max(k - 1, 0)], ts[min(k + 1, ts.size - 1)], 4001)
        best[i] = max(best[i], normalized_objective(E, v, np.exp(local), rho, 8.0)[i].max())
    cap = np.minimum(E(v), 8.0)
    want = np.minimum(np.where(s > 0, s * best, cap), cap)
    assert np.all(got >= want - 1e-9)
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_kl_ball_normalized_refuses_centered_too():
    rng, E = random_ridge(0, 20, 3, False)
    with pytest.raises(ValueError, match="not both"):
        kl_constrained(E, rng.random(20), 0.1, centered=True, normalized=True)


def test_kl_ball_centered_equals_plain_for_distributions():
    rng, mu = random_factors(5, 3, 6, True)
    v = rng.uniform(0.0, 10.0, size=6)
    E = FactorExpectation(mu)
    np.testing.assert_allclose(kl_constrained(E, v, 0.3, centered=True),
                               kl_constrained(E, v, 0.3), atol=1e-10)


def test_kl_ball_b_min_restricts_the_search():
    rng, mu = random_factors(2, 2, 5, False)
    v = rng.uniform(0.0, 5.0, size=5)
    E = FactorExpectation(mu)
    free = kl_constrained(E, v, 3.0)
    restricted = kl_constrained(E, v, 3.0, b_min=1.0)
    assert np.all(restricted <= free + 1e-12)
    at_b_min = [-np.log(mu[i] @ np.exp(-v)) - 3.0 for i in range(2)]  # the max is at b_min
    # ... raised to the least value V can take (every expectation is at least min V)
    np.testing.assert_allclose(restricted, np.maximum(at_b_min, v.min()), atol=1e-10)
    moderate = kl_constrained(E, v, 0.05, b_min=1.0)
    want = [max(-b * np.log(mu[i] @ np.exp(-v / b)) - 0.05 * b
                for b in np.exp(np.linspace(0.0, 8.0, 20001))) for i in range(2)]
    np.testing.assert_allclose(moderate, want, atol=1e-6)


# ------------------------------------------------------------------------ shared properties


@pytest.mark.parametrize("dual", [tv_constrained, kl_constrained])
@pytest.mark.parametrize("ridge", [False, True])
def test_zero_radius_is_the_plain_expectation_and_larger_radii_are_lower(dual, ridge):
    if ridge:
        rng, E = random_ridge(11, 80, 4, False)
        v = rng.uniform(0.0, 5.0, size=80)
    else:
        rng, mu = random_factors(11, 4, 8, True)
        E = FactorExpectation(mu)
        v = rng.uniform(0.0, 5.0, size=8)
    np.testing.assert_array_equal(dual(E, v, 0.0), E(v))
    mixed = dual(E, v, np.array([0.0, 0.3, 0.0, 0.1]))
    np.testing.assert_array_equal(mixed[[0, 2]], E(v)[[0, 2]])
    prev = dual(E, v, 1e-4)
    for rho in [0.01, 0.05, 0.2, 0.5, 1.0, 3.0]:
        cur = dual(E, v, rho)
        assert np.all(cur <= prev + 1e-12)
        prev = cur


@pytest.mark.parametrize("dual", [tv_constrained, kl_constrained])
def test_bad_radii_raise(dual):
    E = FactorExpectation(np.array([[0.5, 0.5], [1.0, 0.0]]))
    v = np.array([0.0, 1.0])
    with pytest.raises(ValueError, match="rho must be finite and >= 0"):
        dual(E, v, -0.1)
    with pytest.raises(ValueError, match="rho must be finite"):
        dual(E, v, np.array([np.nan, 0.1]))
    with pytest.raises(ValueError, match=r"shape \(d,\) = \(2,\)"):
        dual(E, v, np.array([0.1, 0.2, 0.3]))


def test_kl_bad_b_min_raises():
    E = FactorExpectation(np.array([[0.5, 0.5]]))
    with pytest.raises(ValueError, match="b_min must be a positive number"):
        kl_constrained(E, np.array([0.0, 1.0]), 0.1, b_min=0.0)
