"""Exact evaluation against Monte Carlo, brute force, independent primals and closed forms;
the evaluation functions' errors and warnings."""

import itertools
import warnings

import numpy as np
import pytest
from extras import require
from primal import chi2_primal, general_primal, smooth_primal, tv_primal
from scipy.optimize import linprog, minimize
from scipy.special import xlogy

from r2pvi import R2PVI
from r2pvi.duals import HELLINGER, cressie_read
from r2pvi.envs import AmericanPutOption, FiniteLinearMDP, HardInstance, SimulatedLinearMDP
from r2pvi.evaluation import (
    constrained_values,
    expected_return,
    greedy_policy,
    monte_carlo_return,
    nominal_values,
    optimal_policy,
    option_value,
    robust_values,
    suboptimality,
)

DIVERGENCES = ["tv", "kl", "chi2", "hellinger"]


def small_model(seed=0, S=3, A=2, d=2, H=2):
    """A random finite linear MDP whose factors miss some states (so that TV can move
    mass off the nominal support while KL and chi^2 cannot)."""
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(S, A))
    mu = rng.dirichlet(np.ones(S), size=(H, d))
    mu[:, 0, 0] = 0.0  # factor 0 never reaches state 0
    mu /= mu.sum(-1, keepdims=True)
    theta = rng.uniform(0, 1, size=(H, d))
    return FiniteLinearMDP(phi, theta, mu, rng.dirichlet(np.ones(S)))


def all_deterministic_policies(env):
    H, S, A = env.horizon, env.n_states, env.n_actions
    for flat in itertools.product(range(A), repeat=H * S):
        yield np.array(flat).reshape(H, S)


# ---------------------------------------------------------------------- nominal vs Monte Carlo
def _stochastic(env, seed):
    return np.random.default_rng(seed).dirichlet(np.ones(env.n_actions),
                                                 size=(env.horizon, env.n_states))


@pytest.mark.parametrize("case", [
    "simulated-uniform", "simulated-best", "simulated-stochastic", "perturbed-0.6",
    "random-step-dependent", "hard-instance-noisy",
])
def test_exact_expected_return_agrees_with_monte_carlo(case):
    if case.startswith("simulated"):
        env = SimulatedLinearMDP()
        policy = {"simulated-uniform": "uniform", "simulated-best": np.full((3, 5), 15),
                  "simulated-stochastic": _stochastic(env, 1)}[case]
    elif case == "perturbed-0.6":
        env, policy = SimulatedLinearMDP().perturbed(0.6), np.full((3, 5), 15)
    elif case == "random-step-dependent":
        rng = np.random.default_rng(5)
        phi = rng.dirichlet(np.ones(3), size=(4, 5, 3))
        env = FiniteLinearMDP(phi, rng.uniform(size=(4, 3)), rng.dirichlet(np.ones(5), (4, 3)),
                              rng.dirichlet(np.ones(5)))
        policy = _stochastic(env, 2)
    else:
        env = HardInstance(3, 4, lam=1.0, epsilon=0.2, delta=0.5, xi=[1, -1, 1])
        policy = "behavior"
    exact = expected_return(env, policy)
    mean, se = monte_carlo_return(env, policy, 20_000, seed=11)
    assert abs(mean - exact) < 4 * se, (exact, mean, se)
    assert se > 0


def test_perturbation_changes_the_return_as_the_model_says():
    env = SimulatedLinearMDP()
    best = np.full((3, 5), 15)  # p(a) = 0.5 at every state
    v1_x2 = nominal_values(env, best)[1][1, 1]
    for q in (0.0, 0.3, 1.0):
        expected = 0.5 * v1_x2 + 0.5 * (1 - q) * 2.0  # x2 w.p. 1-p, x5 (value 2) w.p. p(1-q)
        assert expected_return(env.perturbed(q), best) == pytest.approx(expected, abs=1e-12)


# ---------------------------------------------------------------------- robust DP
@pytest.mark.parametrize("divergence", DIVERGENCES)
@pytest.mark.parametrize("lam", [0.1, 1.0])
def test_robust_dp_equals_brute_force_over_deterministic_policies(divergence, lam):
    env = small_model(seed=3)
    Q_star, V_star = robust_values(env, divergence, lam)
    values = np.array([robust_values(env, divergence, lam, pol)[1][0]
                       for pol in all_deterministic_policies(env)])  # (64, S)
    np.testing.assert_allclose(values.max(axis=0), V_star[0], atol=1e-9)
    _, V_opt = robust_values(env, divergence, lam, greedy_policy(Q_star))
    np.testing.assert_allclose(V_opt, V_star, atol=1e-12)
    assert (values <= V_star[0] + 1e-9).all()


def _primal_inner(divergence, lam):
    if divergence == "tv":
        return lambda v, mu0: tv_primal(v, mu0, lam)
    if divergence == "kl":
        return lambda v, mu0: smooth_primal(v, mu0, lam, lambda t: xlogy(t, t))
    if divergence == "chi2":
        return lambda v, mu0: chi2_primal(v, mu0, lam)
    return lambda v, mu0: general_primal(v, mu0, lam, HELLINGER)


def primal_policy_values(env, policy, inner):
    """V^{pi,lam} by backward induction with each factor's inner problem solved in the
    primal (LP, QP or numerical optimization over the simplex): no dual formula."""
    pi = policy if policy.ndim == 3 else np.eye(env.n_actions)[policy]
    V = np.zeros(env.n_states)
    for h in range(env.horizon - 1, -1, -1):
        w = np.array([inner(V, env.mu[h, i]) for i in range(env.n_features)])
        Q = env.reward_table[h] + env.features(h) @ w
        V = np.einsum("sa,sa->s", pi[h], Q)
    return V


@pytest.mark.parametrize("divergence", DIVERGENCES)
def test_robust_policy_values_agree_with_an_independent_primal_dp(divergence):
    env = small_model(seed=4)
    lam = 0.4
    rng = np.random.default_rng(0)
    policies = [optimal_policy(env, divergence, lam), rng.integers(2, size=(2, 3)),
                rng.dirichlet(np.ones(2), size=(2, 3))]
    for pol in policies:
        exact = robust_values(env, divergence, lam, pol)[1][0]
        primal = primal_policy_values(env, pol, _primal_inner(divergence, lam))
        np.testing.assert_allclose(exact, primal, atol=2e-6)


def test_tv_robust_value_of_the_simulated_mdp_by_hand():
    # Values at step 2: x1..x3 pay p(a) <= 0.5, x4 0, x5 1; min V = 0 (the fail state x4),
    # so every factor's TV dual is E[min(V, lam)]. With lam = 0.3:
    # V_0(x1) = 0.5 * 0.999 * 0.3 + 0.5 * 0.3.
    Q, V = robust_values(SimulatedLinearMDP(), "tv", 0.3)
    assert V[0, 0] == pytest.approx(0.5 * 0.999 * 0.3 + 0.5 * 0.3, abs=1e-14)
    assert V[1, 4] == pytest.approx(1.3, abs=1e-14)  # x5 at step 1: 1 + min(V_2(x5), 0.3)
    assert V[1, 3] == 0.0 and V[3].max() == 0.0


def test_tv_moves_mass_to_states_outside_every_factor_support():
    # One action, one-hot features: factor i is state i's transition. State 2 pays nothing
    # and no factor used from states 0 and 1 reaches it at step 0, so V_1 = (1, 1, 0).
    # TV (and Hellinger) may still move mass there, KL and chi^2 may not: with lam = 0.3,
    # TV's primal moves everything, w = min(1, min_s V_1(s) + lam) = 0.3.
    phi = np.eye(3)[:, None, :]                                   # (S=3, A=1, d=3)
    theta = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    mu = np.array([[[0.5, 0.5, 0.0], [0.2, 0.8, 0.0], [1.0, 0.0, 0.0]],
                   [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])
    env = FiniteLinearMDP(phi, theta, mu, [1.0, 0.0, 0.0])
    _, V = robust_values(env, "tv", 0.3)
    np.testing.assert_allclose(V[1], [1.0, 1.0, 0.0])
    np.testing.assert_allclose(V[0], [0.3, 0.3, 0.3], atol=1e-14)
    for div in ("kl", "chi2"):
        np.testing.assert_allclose(robust_values(env, div, 0.3)[1][0], [1.0, 1.0, 1.0])
    assert (robust_values(env, "hellinger", 0.3)[1][0] < 1.0 - 1e-3).all()


@pytest.mark.parametrize("divergence", DIVERGENCES + [cressie_read(3.0)])
def test_robust_values_are_below_nominal_and_increase_with_lam(divergence):
    env = small_model(seed=6, S=4, A=3, d=3, H=3)
    pol = _stochastic(env, 3)
    _, nominal = nominal_values(env, pol)
    previous = None
    for lam in (0.05, 0.3, 1.0, 5.0):
        _, V = robust_values(env, divergence, lam, pol)
        assert (V <= nominal + 1e-9).all()
        if previous is not None:
            assert (V >= previous - 1e-9).all()
        previous = V
    _, far = robust_values(env, divergence, 1e5, pol)
    np.testing.assert_allclose(far, nominal, atol=1e-3)


def test_tv_with_lam_above_the_value_range_is_nominal():
    env = small_model(seed=7)
    _, nominal = nominal_values(env)
    _, V = robust_values(env, "tv", lam=10.0)  # values lie in [0, 2]
    np.testing.assert_allclose(V, nominal, atol=1e-14)


def test_builtin_objects_and_names_agree():
    from r2pvi.duals import CHI2, KL, TV
    env = small_model(seed=8)
    for name, obj in (("tv", TV), ("kl", KL), ("chi2", CHI2)):
        np.testing.assert_array_equal(robust_values(env, name, 0.5)[1],
                                      robust_values(env, obj, 0.5)[1])


# ---------------------------------------------------------------------- constrained (balls)
def tv_ball_primal(v, mu0, rho):
    """LP: min V.mu s.t. 1/2 sum |mu - mu0| <= rho over the simplex of every state."""
    n = v.size
    eye = np.eye(n)
    res = linprog(np.concatenate([v, np.zeros(n)]),
                  A_ub=np.block([[eye, -eye], [-eye, -eye], [np.zeros((1, n)), np.ones((1, n))]]),
                  b_ub=np.concatenate([mu0, -mu0, [2.0 * rho]]),
                  A_eq=np.concatenate([np.ones(n), np.zeros(n)])[None], b_eq=[1.0],
                  bounds=[(0, None)] * (2 * n), method="highs")
    assert res.success
    return res.fun


def kl_ball_primal(v, mu0, rho):
    """SLSQP: min V.mu s.t. KL(mu || mu0) <= rho on the support of mu0 (feasible starts)."""
    on = mu0 > 0
    vv, m0 = v[on], mu0[on]
    cons = [{"type": "eq", "fun": lambda m: m.sum() - 1.0},
            {"type": "ineq", "fun": lambda m: rho - np.sum(xlogy(m, m / m0))}]
    best = float(m0 @ vv)
    for tilt in (0.0, 1.0, 5.0, 20.0):
        start = m0 * np.exp(-tilt * (vv - vv.min()))
        start /= start.sum()
        if np.sum(xlogy(start, start / m0)) > rho:
            continue
        res = minimize(lambda m: m @ vv, start, method="SLSQP", bounds=[(0, 1)] * vv.size,
                       constraints=cons, options={"ftol": 1e-14, "maxiter": 500})
        if res.success and np.sum(xlogy(res.x, res.x / m0)) <= rho + 1e-9:
            best = min(best, float(res.fun))
    return best


@pytest.mark.parametrize("divergence,primal", [("tv", tv_ball_primal), ("kl", kl_ball_primal)])
def test_constrained_values_agree_with_primal_dp_and_brute_force(divergence, primal):
    env = small_model(seed=10)
    rho = np.array([[0.05, 0.2], [0.3, 0.1]])  # (H, d)
    Q_star, V_star = constrained_values(env, divergence, rho)
    values = np.array([constrained_values(env, divergence, rho, pol)[1][0]
                       for pol in all_deterministic_policies(env)])
    np.testing.assert_allclose(values.max(axis=0), V_star[0], atol=1e-9)
    pol = greedy_policy(Q_star)
    V = np.zeros(env.n_states)
    for h in range(env.horizon - 1, -1, -1):  # primal backward induction
        w = np.array([primal(V, env.mu[h, i], rho[h, i]) for i in range(env.n_features)])
        V = (env.reward_table[h] + env.features(h) @ w)[np.arange(env.n_states), pol[h]]
    np.testing.assert_allclose(V, V_star[0], atol=1e-6)


@pytest.mark.parametrize("divergence", ["tv", "kl"])
def test_constrained_values_limits(divergence):
    env = small_model(seed=11, S=4, A=3, d=3, H=3)
    _, nominal = nominal_values(env)
    np.testing.assert_allclose(constrained_values(env, divergence, 0.0)[1], nominal, atol=1e-12)
    previous = nominal
    for rho in (0.01, 0.1, 0.5):
        _, V = constrained_values(env, divergence, rho)
        assert (V <= previous + 1e-9).all()
        previous = V
    per_factor = constrained_values(env, divergence, [0.1, 0.1, 0.1])[1]
    np.testing.assert_allclose(per_factor, constrained_values(env, divergence, 0.1)[1])
    if divergence == "tv":  # radius 1: every factor sees only the worst state
        _, V = constrained_values(env, "tv", 1.0)
        for h in range(env.horizon):
            expected = env.reward_table[h].max(1) + V[h + 1].min()
            np.testing.assert_allclose(V[h], expected, atol=1e-12)


# ---------------------------------------------------------------------- suboptimality
@pytest.mark.parametrize("divergence", ["tv", "kl", "chi2"])
def test_suboptimality_is_zero_at_the_optimum_and_never_negative(divergence):
    env = small_model(seed=9)
    lam = 0.5
    star = optimal_policy(env, divergence, lam)
    for s in range(env.n_states):
        assert suboptimality(env, star, divergence, lam, state=s) == pytest.approx(0, abs=1e-12)
    _, V_star = robust_values(env, divergence, lam)
    gaps = []
    for pol in all_deterministic_policies(env):
        gap = V_star[0] - robust_values(env, divergence, lam, pol)[1][0]
        assert (gap >= -1e-12).all()
        gaps.append(suboptimality(env, pol, divergence, lam))
    assert min(gaps) == pytest.approx(0, abs=1e-12) and max(gaps) > 1e-3
    assert suboptimality(env, _stochastic(env, 0), divergence, lam) > 0


def test_suboptimality_of_a_learned_policy():
    env = SimulatedLinearMDP()
    ds = env.collect(200, seed=0)
    for div in ("tv", "kl", "chi2"):
        est = R2PVI(div, 0.3, beta=0.1, gamma=0.1).fit(ds)
        gap = suboptimality(env, est, div, 0.3)
        assert 0 <= gap < 1
        assert suboptimality(env, est, div, 0.3, state=0) == pytest.approx(gap)


# ---------------------------------------------------------------------- hard instance
@pytest.mark.parametrize("divergence", ["tv", "kl", "chi2"])
@pytest.mark.parametrize("lam", [0.1, 1.0, 10.0])
def test_hard_instance_optimal_action_is_the_papers(divergence, lam):
    rng = np.random.default_rng(int(lam * 10))
    env = HardInstance(4, 3, lam, epsilon=0.1, delta=0.3, xi=rng.choice([-1, 1], size=(3, 4)))
    np.testing.assert_array_equal(optimal_policy(env, divergence, lam)[:, 0],
                                  env.optimal_actions)


@pytest.mark.parametrize("divergence", ["tv", "kl", "chi2"])
def test_hard_instance_values_obey_the_papers_lemma(divergence):
    # Lemma (bounding the robust value function): with V <= lam, for any policy
    # 0 <= delta/(2d) sum_j (1-eps)^(j-h) (d + <xi_j, a_j>) - V_h(s1) <= f_h(eps).
    d, H, delta, lam, eps = 3, 4, 0.05, 1.0, 0.05
    rng = np.random.default_rng(0)
    env = HardInstance(d, H, lam, eps, delta, rng.choice([-1, 1], size=(H, d)))
    f = {"tv": 0.0, "kl": lam * eps * (np.e - 1), "chi2": lam * eps * (1 - eps) / 4}[divergence]
    for _ in range(5):
        pol = rng.integers(env.n_actions, size=(H, 2))
        a = env.action_vectors[pol[:, 0]]
        formula = [delta / (2 * d) * sum((1 - eps) ** (j - h) * (d + env.xi[j] @ a[j])
                                         for j in range(h, H)) for h in range(H)]
        gap = np.array(formula) - robust_values(env, divergence, lam, pol)[1][:H, 0]
        assert (gap >= -1e-12).all()
        assert (gap <= f * (H - 1 - np.arange(H)) + 1e-12).all()


# ---------------------------------------------------------------------- put option
def _band_value(env, h, lo, hi):
    """Exact value of 'exercise at step h iff lo < price < hi' with s0 ~ U[95, 105]: a sum
    over the lattice nodes of a linear payoff integrated over an interval of s0."""
    from math import comb
    a, b = env.s0_range
    total = 0.0
    for u in range(h + 1):
        c = 1.02**u * 0.98 ** (h - u)
        prob = comb(h, u) * env.p0**u * (1 - env.p0) ** (h - u)
        left, right = max(a, lo / c), min(b, hi / c, env.strike / c)
        if right > left:
            total += prob * (env.strike * (right - left) - c * (right**2 - left**2) / 2)
    return total / (b - a)


def test_put_option_closed_forms():
    env = AmericanPutOption()
    assert option_value(env, "exercise") == pytest.approx(1.25, abs=1e-12)
    assert option_value(env, "hold") == 0.0
    band = lambda h, p: ((h == 2) & (p > 96.0) & (p < 96.3)).astype(int)  # noqa: E731
    assert option_value(env, band) == pytest.approx(_band_value(env, 2, 96.0, 96.3), abs=1e-9)
    below = lambda h, p: (h == 5) & (p < 100)  # noqa: E731
    assert option_value(env, below) == pytest.approx(_band_value(env, 5, 0, 100), abs=1e-9)


@pytest.fixture(scope="module")
def put_estimator():
    env = AmericanPutOption()
    est = R2PVI("tv", 1.0, beta=0.1, r_max=env.r_max).fit(env.collect(500, seed=0))
    return env, est


def test_put_option_lattice_integration_is_exact(put_estimator):
    from r2pvi.evaluation.lattice import _decisions, decision_cuts

    env, est = put_estimator
    exact = option_value(env, est)
    assert option_value(env, est, price_resolution=0.05) == pytest.approx(exact, abs=1e-9)
    assert option_value(env, est, price_resolution=0.004) == pytest.approx(exact, abs=1e-9)
    # every node's decision is constant inside every piece between the cuts (pieces
    # narrower than the bisection tolerance, where a switch meets a payoff kink, weigh
    # nothing in the integral)
    cuts = decision_cuts(env, est)
    left, width = cuts[:-1], np.diff(cuts)
    left, width = left[width > 1e-8], width[width > 1e-8]
    reference = _decisions(env, est, left + 0.5 * width)
    for frac in (0.001, 0.25, 0.75, 0.999):
        inside = _decisions(env, est, left + frac * width)
        assert all(np.array_equal(a, b) for a, b in zip(inside, reference, strict=True))
    # a midpoint rule over 2,000 initial prices errs only at the jumps of V(s0)
    s0 = 95 + 10 * (np.arange(2000) + 0.5) / 2000
    assert abs(option_value(env, est, s0=s0).mean() - exact) < 5e-4
    assert exact > 0.5


def test_put_option_values_for_many_price_up_probabilities_match_one_by_one(put_estimator):
    env, est = put_estimator
    ps = [0.2, 0.5, 0.55, 1.0]
    threshold = lambda h, p: p < 97.0 - 0.2 * h  # noqa: E731
    for pol in (est, threshold, "uniform"):
        together = option_value(env, pol, price_up=ps)
        one_by_one = [option_value(env.perturbed(p), pol) for p in ps]
        assert together.shape == (4,)
        np.testing.assert_allclose(together, one_by_one, rtol=0, atol=1e-12)
    s0 = np.array([96.0, 101.5])
    np.testing.assert_allclose(option_value(env, est, s0=s0, price_up=ps),
                               [option_value(env.perturbed(p), est, s0=s0) for p in ps],
                               rtol=0, atol=1e-12)
    for bad in ([], [0.5, 1.5], [[0.5]]):
        with pytest.raises(ValueError, match="price_up"):
            option_value(env, est, price_up=bad)


def test_put_option_lattice_agrees_with_monte_carlo(put_estimator):
    env, est = put_estimator
    threshold = lambda h, p: p < 97.0 - 0.2 * h  # noqa: E731
    for pol in (est, threshold, "uniform"):
        exact = option_value(env, pol)
        mean, se = monte_carlo_return(env, pol, 40_000, seed=5)
        assert abs(mean - exact) < 4 * se, (pol, exact, mean, se)
    fixed = AmericanPutOption(s0=102.0)
    exact = expected_return(fixed, est)
    assert exact == pytest.approx(option_value(env, est, s0=102.0))
    mean, se = monte_carlo_return(fixed, est, 40_000, seed=6)
    assert se > 0 and abs(mean - exact) < 4 * se
    perturbed = env.perturbed(0.3)
    mean, se = monte_carlo_return(perturbed, est, 40_000, seed=7)
    assert abs(mean - expected_return(perturbed, est)) < 4 * se


# ---------------------------------------------------------------------- errors
@pytest.mark.parametrize("call,err,match", [
    (lambda: robust_values(AmericanPutOption(), "tv", 1.0), TypeError, "no factor model"),
    (lambda: robust_values(SimulatedLinearMDP(), "tv", 0.0), ValueError, "lam must be > 0"),
    (lambda: robust_values(SimulatedLinearMDP(), "js", 1.0), ValueError, "unknown divergence"),
    (lambda: robust_values(SimulatedLinearMDP(), 3, 1.0), TypeError, "divergence must be"),
    (lambda: robust_values(SimulatedLinearMDP(), "tv", 1.0, np.zeros((3, 4), int)),
     ValueError, "policy as action indices must have shape"),
    (lambda: expected_return("env", "uniform"), TypeError, "env must be"),
    (lambda: monte_carlo_return(SimulatedLinearMDP(), "uniform", 0), ValueError, "n_episodes"),
    (lambda: suboptimality(SimulatedLinearMDP(), "uniform", "tv", 1.0, state=9), ValueError,
     "state must lie in"),
    (lambda: optimal_policy(SimulatedLinearMDP(), "tv"), ValueError, "needs its .* lam"),
    (lambda: option_value(SimulatedLinearMDP(), "hold"), TypeError, "AmericanPutOption"),
    (lambda: constrained_values(SimulatedLinearMDP(), "chi2", 0.1), ValueError,
     "supports the 'tv' and 'kl' balls"),
    (lambda: constrained_values(SimulatedLinearMDP(), "tv", np.ones(3)), ValueError,
     r"rho must be a scalar, a \(d,\)"),
    (lambda: constrained_values(SimulatedLinearMDP(), "kl", -0.1), ValueError, "rho must be >= 0"),
    (lambda: option_value(AmericanPutOption(), "hold", price_resolution=0), ValueError,
     "price_resolution must be > 0"),
])
def test_evaluation_errors_name_the_argument(call, err, match):
    with pytest.raises(err, match=match):
        call()


def test_one_episode_warns_that_it_has_no_standard_error():
    require("gymnasium")
    import gymnasium as gym

    from r2pvi.evaluation import evaluate_policy

    with pytest.warns(UserWarning, match="n_episodes >= 2"):
        mean, se = evaluate_policy(gym.make("CartPole-v1"), "uniform", 1, seed=0, max_steps=5)
    assert np.isnan(se) and mean > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isfinite(evaluate_policy(gym.make("CartPole-v1"), "uniform", 2, seed=0,
                                           max_steps=5)[1])
