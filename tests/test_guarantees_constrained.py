"""Numerical guarantees of the constrained (uncertainty-ball) estimators DRPVI, VA-DRPVI and
DRVI-L.

For any data, each learned factor value ``w_{h,i}`` is finite, lies in the known range of
``V_{h+1}`` (``[0, (H - h - 1) r_max]``), never exceeds the plain ridge estimate of the same
step (clipped to that range: the ball contains ``mu0``), is non-increasing in ``rho`` and
tends to the plain estimate as ``rho -> 0+``; saturated balls give the least value exactly.
On exact distributions every dual lies in ``[min V, E V]``.

Besides the properties on random ridge operators, fixed cases pin down the failures a wrong
dual shows: DRVI-L's objective at the clip ``H r_max`` as ``b -> 0``, a jump at ``rho = 0``,
huge radii or ``r_max`` that lose the floor, a TV ball above the plain estimate as
``rho -> 0+``.
"""

import numpy as np
import pytest
from helpers import fail_state_mdp
from hypothesis import example, given, settings
from hypothesis import strategies as st

from r2pvi.algorithms import DRVIL, PEVI, KLBallRule, TVBallRule
from r2pvi.duals import (
    FactorExpectation,
    RidgeExpectation,
    cholesky_gram,
    kl_constrained,
    tv_constrained,
)
from r2pvi.engine import StepContext, StepRule, backward_induction
from r2pvi.envs import FiniteLinearMDP, SimulatedLinearMDP

# ------------------------------------------------------------------------------ helpers


class Spy(StepRule):
    """Wraps a rule and records ``(E, v, ctx, w)`` at every step."""

    def __init__(self, rule):
        self.rule, self.calls = rule, {}

    def __call__(self, E, v, ctx):
        w = self.rule(E, v, ctx)
        self.calls[ctx.h] = (E, v.copy(), ctx, w)
        return w


def spy_fit(ds, rule, r_max=1.0):
    spy = Spy(rule)
    model = backward_induction(ds, spy, beta=0.0, gamma=1.0, penalty="l1", r_max=r_max)
    return model, spy.calls


def value_cap(E, v, ctx):
    """The plain ridge estimate clipped to ``[0, (H - h - 1) r_max]``."""
    return np.clip(E(v), 0.0, (ctx.horizon - ctx.h - 1) * ctx.r_max)


# ------------------------------------------------------ DRVI-L: the b -> 0 artefact


@pytest.mark.parametrize("seed", [0, 4])
def test_drvil_on_a_fail_state_mdp_stays_below_the_plain_estimate_and_near_the_exact_ball(
        seed):
    """Every learned factor value is finite, in ``[0, clipped plain estimate]`` and within
    0.03 of the exact KL-ball value of the learned ``V_{h+1}`` under the true factors (the
    artefact at ``b -> 0`` puts it at the clip ``H r_max = 3`` where the values are <= 0.07)."""
    env = fail_state_mdp()
    ds = env.collect(2000, seed=seed)
    H, rho = env.horizon, 0.3
    model, calls = spy_fit(ds, KLBallRule(np.full((H, 4), rho)))
    for h in range(H - 1):
        E, v, ctx, w = calls[h]
        assert np.all(np.isfinite(w))
        assert np.all(w >= 0.0)
        assert np.all(w <= value_cap(E, v, ctx))
        # the exact KL-ball value of the learned V_{h+1} under the true factors
        v_states = np.clip(env.phi @ model.weights[h + 1], 0.0, H - h - 1).max(axis=1)
        v_states[5] = 0.0
        exact = kl_constrained(FactorExpectation(env.mu[h]), v_states, rho)
        np.testing.assert_allclose(w, exact, atol=0.03)


def shrinkage_mdp():
    """6 states, 3 actions, d = 3, H = 3, values far from 0 (V_2 in [0.73, 0.80])."""
    rng = np.random.default_rng(1)
    S, A, d, H = 6, 3, 3, 3
    return FiniteLinearMDP(rng.dirichlet(np.ones(d), size=(S, A)), rng.uniform(size=(H, d)),
                           rng.dirichlet(np.ones(S), size=(H, d)), initial=np.ones(S) / S)


def test_drvil_default_form_has_no_ridge_shrinkage_bias():
    """Ma et al.'s centering (form="ma") leaves the shrinkage's weight 1 - s_i at V = 0: with
    gamma = 1 the step-1 weights fall 0.012-0.024 below the exact KL-ball values (below
    min V_2 = 0.727), whatever K. The default (row-normalized) form is within 1e-3."""
    env, rho = shrinkage_mdp(), 0.3
    v2 = (env.phi @ env.theta[2]).max(axis=1)
    exact = kl_constrained(FactorExpectation(env.mu[1]), v2, rho)
    ds = env.collect(5000, seed=0)
    kw = {"beta": 0.0, "reward_weights": env.theta}
    normalized = DRVIL(rho, **kw).fit(ds).weights_[1] - env.theta[1]
    ma = DRVIL(rho, form="ma", **kw).fit(ds).weights_[1] - env.theta[1]
    np.testing.assert_allclose(normalized, exact, atol=1e-3)
    assert np.all(normalized >= v2.min() - 1e-3)
    assert np.max(np.abs(ma - exact)) > 0.01  # the bias the default form removes


def test_drvil_is_continuous_at_rho_zero():
    """DRVIL(1e-12) is within 1e-5 of DRVIL(0): no jump from the artefact at ``b -> 0``."""
    for env, K in ((fail_state_mdp(), 2000), (SimulatedLinearMDP(), 100)):
        ds = env.collect(K, seed=0)
        base = DRVIL(0.0, beta=0.0).fit(ds)
        near = DRVIL(1e-12, beta=0.0).fit(ds)
        np.testing.assert_allclose(near.weights_, base.weights_, atol=1e-5)


def test_drvil_on_the_simulated_mdp_never_exceeds_pevi():
    """DRVIL(0.1) never exceeds PEVI's weights (beta = 0, K = 100), whatever ``b_min``."""
    ds = SimulatedLinearMDP().collect(100, seed=0)
    pevi = PEVI(beta=0.0).fit(ds)
    for b_min in ("auto", None, 0.05):
        est = DRVIL(0.1, beta=0.0, b_min=b_min).fit(ds)
        assert np.all(est.weights_ <= pevi.weights_ + 1e-12)


@pytest.mark.parametrize("seed", [1, 2])
def test_drvil_default_b_min_keeps_factors_without_mass_at_the_minimum_robust(seed):
    """Without b_min (None) the ridge estimate of E[e^{-V/b}] crosses its floor as b -> 0 for
    factors with no mass on the V = 0 state, and the objective there is the plain estimate:
    at rho = 1 and 2 such factors keep their plain estimate (not robust at all). The default
    b_min="auto" stops the search before the crossing."""
    env = fail_state_mdp()
    ds = env.collect(2000, seed=seed)
    H = env.horizon
    _, calls = spy_fit(ds, KLBallRule(np.full((H, 4), 0.3)))
    for h in range(H - 1):
        E, v, ctx, _ = calls[h]
        cap = value_cap(E, v, ctx)
        for rho in (1.0, 2.0):
            w = KLBallRule(np.full((H, 4), rho))(E, v, ctx)
            assert np.all(w[cap > 1e-3] < 0.9 * cap[cap > 1e-3])


def test_b_min_default_and_validation():
    assert DRVIL(0.1).b_min == "auto"
    ds = SimulatedLinearMDP().collect(20, seed=1)
    for bad, err in ((0.0, ValueError), (-1.0, ValueError), (np.inf, ValueError),
                     ("small", ValueError), (True, TypeError), ([0.1], TypeError)):
        with pytest.raises(err, match="b_min must be"):
            DRVIL(0.1, b_min=bad).fit(ds)


# ------------------------------------------------------ huge radii and bounds


def test_huge_radii_and_bounds_on_the_simulated_mdp():
    """Saturated balls give the least value exactly: TV balls ``min V`` (0.67 here, or the
    factor's cap if lower) for rho from 10 to 1e16, KL balls at rho = 1e10 the least value 0;
    r_max = 1e10 and 1e308 give finite weights, those of r_max = 1."""
    ds = SimulatedLinearMDP().collect(100, seed=0)
    H = 3
    for rho in (10.0, 1e13, 1e16):
        _, calls = spy_fit(ds, TVBallRule(np.full((H, 4), rho), "data"))
        for h in range(H - 1):
            E, v, ctx, w = calls[h]
            # saturated: every factor gets the least value min V (or its cap if lower)
            np.testing.assert_array_equal(w, np.minimum(v.min(), value_cap(E, v, ctx)))
    _, calls = spy_fit(ds, KLBallRule(np.full((H, 4), 1e10)))
    for h in range(H - 1):
        np.testing.assert_array_equal(calls[h][3], 0.0)  # the least value of V
    ref = DRVIL(0.1, beta=0.0).fit(ds).weights_
    for r_max in (1e10, 1e308):
        w = DRVIL(0.1, beta=0.0, r_max=r_max).fit(ds).weights_
        assert np.all(np.isfinite(w))
        np.testing.assert_allclose(w, ref, rtol=1e-9, atol=1e-12)


def test_tv_ball_huge_radius_keeps_the_floor_exactly():
    """For radii up to 1e300 the TV ball's value is exactly the floor ``min V = 0.67`` (``rho
    alpha`` must not cancel against ``rho V_min``); on signed ridge weights, the smaller of
    ``min V`` and the clipped plain estimate."""
    E = FactorExpectation(np.array([[0.5, 0.25, 0.25], [0.0, 0.5, 0.5]]))
    v = np.array([0.67, 1.5, 3.0])
    for rho in (1.0, 10.0, 1e13, 1e16, 1e300):
        np.testing.assert_array_equal(tv_constrained(E, v, rho), [0.67, 0.67])
    rng = np.random.default_rng(0)
    phi = rng.dirichlet(np.ones(3), size=50) - 0.05  # signed features
    E = RidgeExpectation(phi, cholesky_gram(phi, 1.0))
    v = rng.uniform(0.67, 3.0, size=50)
    for rho in (1e13, 1e16, 1e300):
        got = tv_constrained(E, v, rho, v_range=(0.0, 3.0))
        np.testing.assert_array_equal(got, np.minimum(v.min(), np.clip(E(v), 0.0, 3.0)))


# --------------------------------------------------------- DRPVI at rho -> 0+


def test_drpvi_is_continuous_at_rho_zero_on_signed_ridge_weights():
    """With signed ridge weights ``max_alpha E_i[V]_alpha`` exceeds ``E_i[V]``; for rho from
    1e-15 to 1e-9 the TV ball stays within ``2 rho`` of the clipped plain estimate (its value
    at rho = 0) and never above it."""
    rng = np.random.default_rng(3)
    phi = rng.dirichlet(np.full(4, 0.5), size=40)
    E = RidgeExpectation(phi, cholesky_gram(phi, 1.0))
    v = rng.uniform(0.0, 1.0, size=40)
    floor = float(v.min())
    dense = np.stack([E(np.minimum(v, a)) for a in np.sort(v)]).max(axis=0)
    assert np.any(dense > E(v) + 1e-6)  # the max over alpha exceeds the plain estimate
    for rho in (1e-15, 1e-12, 1e-9):
        got = tv_constrained(E, v, rho, floor, v_range=(0.0, 1.0))
        np.testing.assert_allclose(got, np.clip(E(v), 0.0, 1.0), atol=2 * rho + 1e-15)
        assert np.all(got <= np.clip(E(v), 0.0, 1.0))


# ------------------------------------------------- the guarantee on random ridge operators


def ridge_case(seed, n, d, signed, weighted, ties, zero_mass, scale):
    """A ridge operator with the hard features: signed, variance weights (VA-DRPVI), tied
    values, and a factor with (almost) no mass at the lowest values."""
    rng = np.random.default_rng(seed)
    v = scale * rng.uniform(0.0, 1.0, size=n)
    if ties:
        v[rng.random(n) < 0.4] = 0.0
        v[rng.random(n) < 0.2] = scale
    phi = rng.dirichlet(np.full(d, 0.6), size=n)
    if zero_mass:  # factor 0 carries almost no weight on the lowest third of the values
        low = v <= np.quantile(v, 1 / 3)
        phi[low, 0] *= 1e-3
        phi /= phi.sum(axis=1, keepdims=True)
    if signed:
        phi = phi - 0.1
    w = rng.uniform(0.1, 1.0, size=n) if weighted else None
    return E_of(phi, w), v


def E_of(phi, w):
    return RidgeExpectation(phi, cholesky_gram(phi, 1.0, w), w)


ridge_cases = st.tuples(
    st.integers(0, 2**31 - 1),  # seed
    st.integers(2, 120),  # n
    st.integers(1, 5),  # d
    st.booleans(),  # signed features
    st.booleans(),  # variance weights
    st.booleans(),  # ties
    st.booleans(),  # factor without mass at the minimum
    st.sampled_from([1e-3, 1.0, 30.0, 1e6]),  # value scale
)


def rules(rho, d):
    radii = np.full((3, d), rho)
    return {"DRPVI": TVBallRule(radii, "data"), "DRPVI v_min=0": TVBallRule(radii, 0.0),
            "DRVI-L": KLBallRule(radii), "DRVI-L b_min=None": KLBallRule(radii, None)}


@settings(max_examples=150, deadline=None)
@given(ridge_cases, st.floats(-6.0, 6.0))
def test_ridge_factor_values_are_in_range_below_plain_and_monotone(case, log_rho):
    E, v = ridge_case(*case)
    scale = case[-1]
    ctx = StepContext(h=0, horizon=3, r_max=scale / 2, v_upper=1.5 * scale)  # hi = scale
    cap = value_cap(E, v, ctx)
    tol = 1e-9 * scale
    radii = 10.0 ** log_rho * np.array([1.0, 10.0, 1e3])
    for name in rules(1.0, E.n_dims):
        ws = [rules(r, E.n_dims)[name](E, v, ctx) for r in radii]
        for w in ws:
            assert np.all(np.isfinite(w)), name
            assert np.all(w >= 0.0) and np.all(w <= scale), name
            assert np.all(w <= cap), name  # exactly: the ball contains mu0
        if name == "DRVI-L b_min=None":
            # Not guaranteed: below b_min the estimated objective has narrow spikes (where the
            # ridge estimate of E[e^{-V/b}] crosses its floor) that the grid may miss at one
            # radius and hit at another; hypothesis found one (2% of the scale). The default
            # b_min excludes that region.
            continue
        assert np.all(np.diff(ws, axis=0) <= tol), name  # non-increasing in rho


@settings(max_examples=100, deadline=None)
@given(ridge_cases)
def test_ridge_factor_values_tend_to_the_plain_estimate_as_rho_vanishes(case):
    E, v = ridge_case(*case)
    scale = case[-1]
    ctx = StepContext(h=0, horizon=3, r_max=scale / 2, v_upper=1.5 * scale)
    cap = value_cap(E, v, ctx)
    for name, rule in rules(1e-14, E.n_dims).items():
        w = rule(E, v, ctx)
        # TV: within rho (max V - min V); KL: within sqrt(2 rho Var V) ~ 1e-7 scale
        np.testing.assert_allclose(w, cap, atol=1e-6 * scale, rtol=0, err_msg=name)
    for rule in rules(0.0, E.n_dims).values():  # rho = 0: the plain estimate, projected
        np.testing.assert_array_equal(rule(E, v, ctx), cap)  # PEVI's projection


# ------------------------------------------------------------ exact distributions


exact_cases = st.tuples(
    st.integers(0, 2**31 - 1), st.integers(1, 4), st.integers(2, 9), st.booleans(),
    st.sampled_from([1e-3, 1.0, 1e6]),
)


def exact_case(seed, d, n, zero, scale):
    rng = np.random.default_rng(seed)
    mu = rng.dirichlet(np.full(n, 0.7), size=d)
    v = scale * rng.uniform(0.0, 1.0, size=n)
    if zero:  # no mass on the lowest state for some factors; ties at the top
        mu[rng.random(d) < 0.5, np.argmin(v)] = 0.0
        v[rng.random(n) < 0.3] = v.max()
        mu[:, np.argmax(v)] += 1e-3
        mu /= mu.sum(axis=1, keepdims=True)
    return FactorExpectation(mu), mu, v


@settings(max_examples=200, deadline=None)
@given(exact_cases, st.floats(-6.0, 6.0))
def test_exact_duals_lie_between_min_v_and_the_mean_and_decrease_in_rho(case, log_rho):
    E, mu, v = exact_case(*case)
    scale = case[-1]
    support_min = np.where(mu > 0, v, np.inf).min(axis=1)
    mean = E(v)
    radii = 10.0 ** log_rho * np.array([1.0, 10.0, 1e3])
    kl = [kl_constrained(E, v, r) for r in radii]
    tv = [tv_constrained(E, v, r) for r in radii]
    ulp = 4e-16 * scale  # E(v) itself is rounded: it may fall 1 ulp below min V (ties)
    for w in kl:
        assert np.all(w >= support_min - ulp) and np.all(w <= mean)
    for w in tv:
        assert np.all(w >= v.min() - ulp) and np.all(w <= mean)
    for ws in (kl, tv):
        assert np.all(np.diff(ws, axis=0) <= 1e-9 * scale)


@settings(max_examples=150, deadline=None)
@given(exact_cases)
@example((5797, 4, 2, True, 0.001))  # a grid value 1 ulp above the minimum, without the branch
def test_saturated_exact_balls_give_the_minimum_exactly(case):
    E, mu, v = exact_case(*case)
    support_min = np.where(mu > 0, v, np.inf).min(axis=1)
    p_min = np.where(v[None, :] == support_min[:, None], mu, 0.0).sum(axis=1) / mu.sum(axis=1)
    rho = -np.log(p_min) * 1.0001 + 1e-12  # just past log(1 / mu0(argmin))
    want = np.minimum(support_min, E(v))  # E(v) may be 1 ulp below min V (ties)
    np.testing.assert_array_equal(kl_constrained(E, v, rho), want)
    np.testing.assert_array_equal(kl_constrained(E, v, 1e300), want)
    for rho in (1.0, 3.0, 1e300):
        np.testing.assert_array_equal(tv_constrained(E, v, rho), np.minimum(v.min(), E(v)))
    np.testing.assert_array_equal(tv_constrained(E, v, 2.0, v_min=-5.0), -5.0)
