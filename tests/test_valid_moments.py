"""KL and chi^2 with valid moments on learned data (``moments="valid"``, R2PVI's default).

With signed ridge weights the KL moment ``E_i[e^{-(V - c)/lam}]`` can be <= 0 and the chi^2
variance negative; the valid estimate gives every factor's normalized weights a mass of at
least ``f_i = 1 / (1 + N_i)`` at the least value (``N_i = s_i^2 / [Lambda^-1]_ii``), which
holds the normalized KL moment in ``[max(f_i, e^{-spread/lam}), 1]`` and chi^2 at most the
largest dual of such a distribution. The truth of the last test is exact dynamic programming
on a finite linear MDP with a rare absorbing failure.
"""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi import R2PVI
from r2pvi.duals import (
    FactorExpectation,
    RidgeExpectation,
    chi2_regularized,
    cholesky_gram,
    kl_regularized,
)
from r2pvi.duals._valid_moments import effective_counts
from r2pvi.envs import FiniteLinearMDP
from r2pvi.evaluation import robust_values


def signed_ridge(seed, n, d, kind, ties, no_mass_at_min, scale, gamma):
    """A ridge operator with signed weights (overlapping or signed features), the values at
    ``scale`` with ties at the least value, a factor without mass where the values are least."""
    rng = np.random.default_rng(seed)
    v = scale * rng.uniform(0.0, 1.0, size=n)
    if ties:
        v[rng.random(n) < 0.3] = 0.0  # many transitions to a zero-value (failure) state
    if kind == "simplex":
        phi = rng.dirichlet(np.full(d, 0.5), size=n)
    else:
        phi = rng.normal(size=(n, d)) + 0.3
    if no_mass_at_min and d > 1:
        phi[v <= np.quantile(v, 0.3), 0] = 0.0
    return RidgeExpectation(phi, cholesky_gram(phi, gamma)), v


ridge_cases = dict(
    seed=st.integers(0, 2**32 - 1), n=st.integers(2, 40), d=st.integers(1, 5),
    kind=st.sampled_from(["simplex", "signed"]), ties=st.booleans(),
    no_mass_at_min=st.booleans(), scale=st.sampled_from([1e-6, 1.0, 1e6]),
    gamma=st.sampled_from([1e-3, 0.1, 1.0]), log_lam=st.floats(-3.0, 3.0))


@settings(max_examples=200, deadline=None)
@given(**ridge_cases)
def test_valid_kl_moment_stays_within_its_range_on_signed_ridge_data(
        seed, n, d, kind, ties, no_mass_at_min, scale, gamma, log_lam):
    """``w_i = s_i (c - lam log r_i)`` is decreasing in the normalized moment ``r_i``, so
    ``r_i`` in ``[max(f_i, e^{-x}), 1]`` (``x = spread / lam``) is ``w_i`` in ``[s_i c, s_i (c +
    min(lam log(1 + N_i), spread))]``; the caps at the plain estimate ``E_i(v)`` and at ``max v``
    can only lower it. The ridge moments break the upper end: a factor whose moment is <= 0
    gets the plain estimate, above every valid value at small lam."""
    E, v = signed_ridge(seed, n, d, kind, ties, no_mass_at_min, scale, gamma)
    spread = float(v.max() - v.min())
    lam = max(spread, scale) * 10.0**log_lam
    w = kl_regularized(E, v, lam, moments="valid")
    s, plain, c = E.total_weights(), E(v), float(v.min())
    count = effective_counts(E, s)
    live = s > 0.0
    tol = 1e-9 * scale * (1.0 + np.abs(E.rows()).sum(axis=1))
    assert np.all(np.isfinite(w))
    cap = float(v.max())
    np.testing.assert_allclose(w[~live], np.minimum(plain, cap)[~live], rtol=0, atol=tol.max())
    with np.errstate(over="ignore"):
        top = s * (c + np.minimum(lam * np.log1p(count), spread))
    assert np.all(w[live] <= np.minimum(plain, top)[live] + tol[live])
    assert np.all(w[live] >= np.minimum(np.minimum(s * c, plain), cap)[live] - tol[live])


@settings(max_examples=120, deadline=None)
@given(**ridge_cases)
def test_valid_chi2_stays_within_the_range_of_a_floored_distribution_on_signed_ridge_data(
        seed, n, d, kind, ties, no_mass_at_min, scale, gamma, log_lam):
    """chi^2's valid estimate is ``s_i`` times the dual of the normalized weights, at least
    ``s_i c`` (the objective at ``alpha = c``), at most ``s_i (c + lam N_i)`` (the largest dual
    of a distribution with mass ``1 / (1 + N_i)`` at ``c``) and at most ``E_i(v)``. The ridge
    moments break the range: with row sums away from 1 the estimated variance
    ``E_i(V^2) - E_i(V)^2`` is off by ``(s_i - s_i^2) E(V)^2``."""
    E, v = signed_ridge(seed, n, d, kind, ties, no_mass_at_min, scale, gamma)
    lam = max(float(v.max() - v.min()), scale) * 10.0**log_lam
    w = chi2_regularized(E, v, lam, moments="valid")
    s, plain, c = E.total_weights(), E(v), float(v.min())
    count = effective_counts(E, s)
    live = s > 0.0
    tol = 1e-8 * scale * (1.0 + np.abs(E.rows()).sum(axis=1) ** 2)
    assert np.all(np.isfinite(w))
    np.testing.assert_allclose(w[~live], plain[~live], rtol=0, atol=tol.max())
    with np.errstate(over="ignore"):
        top = s * (c + lam * count)
    assert np.all(w[live] <= np.minimum(plain, top)[live] + tol[live])
    assert np.all(w[live] >= np.minimum(s * c, plain)[live] - tol[live])


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), S=st.integers(1, 30), d=st.integers(1, 5),
       ties=st.booleans(), sparse=st.booleans(), scale=st.sampled_from([1e-6, 1.0, 1e6]),
       log_lam=st.floats(-4.0, 4.0))
def test_exact_duals_are_unchanged_on_exact_distributions(seed, S, d, ties, sparse, scale,
                                                          log_lam):
    """On true factor distributions ``moments`` changes nothing, to the last bit."""
    rng = np.random.default_rng(seed)
    mu = rng.dirichlet(np.full(S, 0.3 if sparse else 1.0), size=d)
    if sparse:
        mu[mu < 0.05] = 0.0
        mu /= mu.sum(axis=1, keepdims=True)
    v = scale * rng.uniform(size=S)
    if ties:
        v[rng.random(S) < 0.4] = 0.0
    E = FactorExpectation(mu)
    lam = scale * 10.0**log_lam
    for dual in (kl_regularized, chi2_regularized):
        np.testing.assert_array_equal(dual(E, v, lam, moments="valid"),
                                      dual(E, v, lam, moments="ridge"))


def rare_failure_mdp(seed, S=10, A=3, d=6, H=4):
    """A linear MDP whose last state is an absorbing failure reached with probability 0,
    0.003, 0.01 or 0.03 through 5 overlapping factors (Dirichlet features, so ridge weights
    are signed); rewards 0.3-1 per step while alive."""
    rng = np.random.default_rng(seed)
    fail = S - 1
    phi = np.zeros((S, A, d))
    phi[:fail, :, :d - 1] = rng.dirichlet(np.full(d - 1, 0.7), size=(fail, A))
    phi[fail, :, d - 1] = 1.0
    p = np.array([0.0, 0.0, 0.003, 0.01, 0.03])
    mu = np.zeros((H, d, S))
    for h in range(H):
        for i in range(d - 1):
            mu[h, i, :fail] = rng.dirichlet(np.ones(fail)) * (1.0 - p[i])
            mu[h, i, fail] = p[i]
        mu[h, d - 1, fail] = 1.0
    theta = np.zeros((H, d))
    theta[:, :d - 1] = rng.uniform(0.3, 1.0, size=(H, d - 1))
    return FiniteLinearMDP(phi, theta, mu, initial=np.r_[np.full(fail, 1.0 / fail), 0.0],
                           fail_states=(fail,))


def test_valid_kl_is_far_less_optimistic_than_the_ridge_moments_against_exact_dp():
    """Against the exact robust Q-values (dynamic programming on the true factors), the fitted
    Q of R2PVI-KL (lam 0.1, no penalty) with the ridge moments overshoots by up to 0.45-1.25
    (0.80 on average over 10 datasets: factors whose moment is <= 0 get the plain estimate,
    as if failure were impossible); with valid moments by at most 0.48 and 0.10 on average,
    lower on every dataset. (Its mean absolute error is larger, 0.33 against 0.17: the floor
    errs on the pessimistic side.)"""
    lam, worst = 0.1, {"ridge": [], "valid": []}
    for seed in range(10):
        env = rare_failure_mdp(seed)
        data = env.collect(300, seed=seed + 100)
        q_star, _ = robust_values(env, "kl", lam)
        H = env.horizon
        for moments in worst:
            weights = R2PVI("kl", lam, beta=0.0, gamma=1.0, moments=moments).fit(data).weights_
            q = np.stack([np.clip(env.phi @ weights[h], 0.0, H - h) for h in range(H)])
            worst[moments].append(float(np.max(q - q_star)))  # the largest overshoot
    ridge, valid = np.array(worst["ridge"]), np.array(worst["valid"])
    assert np.all(valid <= ridge)
    assert ridge.mean() > 0.7 and valid.mean() < 0.15


def test_r2pvi_uses_valid_moments_by_default_and_names_a_bad_choice():
    env = rare_failure_mdp(0)
    data = env.collect(50, seed=1)
    est = R2PVI("kl", 0.1)
    assert est.get_params()["moments"] == "valid"
    same = R2PVI("kl", 0.1, moments="valid").fit(data).weights_
    np.testing.assert_array_equal(est.fit(data).weights_, same)
    try:
        R2PVI("chi2", 0.1, moments="clipped").fit(data)
    except ValueError as exc:
        assert "moments" in str(exc) and "valid" in str(exc)
    else:  # pragma: no cover
        raise AssertionError("an unknown moments value was accepted")
