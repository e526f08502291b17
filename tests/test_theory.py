"""Theory in practice: the chi^2 ball, the uncertainty term, the theorem's beta, the figures.

The truths used here share no formula with the code under test: the chi^2 ball is solved in
the primal (exact KKT enumeration of the QCQP's faces, and SLSQP); the uncertainty term of a
two-state model is a maximization over an explicit grid of factor distributions, filtered by
the divergences' definitions; beta and the bounds are the paper's expressions typed out.
"""

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq, minimize

from r2pvi import PEVI, R2PVI, NotFittedError, OfflineDataset, load
from r2pvi.duals import (
    CHI2,
    FactorExpectation,
    RidgeExpectation,
    chi2_constrained,
    chi2_regularized,
    cholesky_gram,
)
from r2pvi.envs import FiniteLinearMDP, HardInstance, SimulatedLinearMDP
from r2pvi.evaluation import optimal_policy, robust_values, suboptimality
from r2pvi.experiments import reproduce_figure
from r2pvi.experiments.results import read_results
from r2pvi.theory import (
    admissible_radii,
    ball_sup,
    bonus_table,
    instance_dependent_bound,
    instance_independent_bound,
    loglog_slope,
    theoretical_beta,
    uncertainty_term,
    uncertainty_values,
    xi,
)

TOL = 1e-6


# ----------------------------------------------------------------------- chi^2 ball primals
def chi2_ball_kkt(v, mu0, rho):
    """Exact ``min V.mu`` over ``mu >= 0``, ``sum mu = 1``, ``sum (mu - mu0)^2 / mu0 <= rho``.

    The QCQP is convex; on the face where the states Z of the support are set to 0 (each
    costs ``mu0(s)`` of the budget) the KKT conditions with the ball active give ``mu`` in
    closed form. The best feasible candidate over all faces (or the centre of a face whose
    values are constant) is the optimum.
    """
    supp = np.flatnonzero(mu0 > 0)
    best = np.inf
    for r in range(supp.size):
        for zero in itertools.combinations(supp, r):
            free = np.setdiff1d(supp, zero)
            m0, vf = mu0[free], v[free]
            m_zero, m_free = mu0[list(zero)].sum(), m0.sum()
            budget, least = rho - m_zero, m_zero**2 / m_free  # least chi^2 on this face
            if budget < least - 1e-15:
                continue
            mean = m0 @ vf / m_free
            spread = m0 @ (vf - mean) ** 2
            if spread <= 1e-20 * m_free * (1.0 + np.max(vf**2)) or budget <= least:
                shift = m0 * m_zero / m_free
            else:
                b = np.sqrt(spread / (4.0 * (budget - least)))
                nu = mean + 2.0 * b * m_zero / m_free
                shift = m0 * (nu - vf) / (2.0 * b)
            mu = m0 + shift
            if (mu >= -1e-12).all():
                best = min(best, mu @ vf)
    return best


def chi2_ball_slsqp(v, mu0, rho):
    """The same problem by SLSQP on the support of mu0 (two starts; points feasible to 1e-8)."""
    supp = mu0 > 0
    vv, m0 = v[supp], mu0[supp]
    cons = [{"type": "eq", "fun": lambda m: m.sum() - 1.0, "jac": lambda m: np.ones_like(m)},
            {"type": "ineq", "fun": lambda m: rho - np.sum((m - m0) ** 2 / m0),
             "jac": lambda m: -2.0 * (m - m0) / m0}]
    best = np.inf
    for x0 in (m0, np.full(m0.size, 1.0 / m0.size)):
        res = minimize(lambda m: m @ vv, x0, jac=lambda m: vv, method="SLSQP",
                       bounds=[(0.0, 1.0)] * m0.size, constraints=cons,
                       options={"ftol": 1e-14, "maxiter": 2000})
        if cons[1]["fun"](res.x) > -1e-8 and abs(res.x.sum() - 1.0) < 1e-10:
            best = min(best, res.x @ vv)
    return best


def _problem(seed, n, zero_mass, scale):
    rng = np.random.default_rng(seed)
    mu = rng.dirichlet(np.full(n, 0.8), size=2)
    if zero_mass and n > 1:
        mu[0, rng.integers(n)] = 0.0
        mu /= mu.sum(axis=1, keepdims=True)
    v = scale * rng.random(n)
    if rng.random() < 0.3:  # ties
        v = np.round(v)
    return mu, v


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("rho", [0.003, 0.1, 0.7, 2.0, 50.0])
def test_chi2_ball_equals_the_exact_and_the_slsqp_primal(seed, rho):
    mu, v = _problem(seed, n=2 + seed % 5, zero_mass=seed % 3 == 0, scale=[1, 10, 100][seed % 3])
    got = chi2_constrained(FactorExpectation(mu), v, rho)
    for i in range(mu.shape[0]):
        exact = chi2_ball_kkt(v, mu[i], rho)
        assert got[i] == pytest.approx(exact, abs=TOL * max(1.0, np.abs(v).max()))
        if seed < 4:  # SLSQP agrees too (slower)
            assert got[i] == pytest.approx(chi2_ball_slsqp(v, mu[i], rho), abs=TOL * 10)


@settings(max_examples=60)
@given(st.integers(0, 2**31 - 1), st.integers(1, 8), st.booleans(),
       st.sampled_from([1.0, 10.0, 100.0]), st.floats(1e-4, 30.0), st.floats(-50.0, 50.0),
       st.floats(0.1, 10.0))
def test_chi2_ball_properties(seed, n, zero_mass, scale, rho, shift, factor):
    mu, v = _problem(seed, n, zero_mass, scale)
    E = FactorExpectation(mu)
    w = chi2_constrained(E, v, rho)
    on = mu > 0
    lowest = np.where(on, v, np.inf).min(axis=1)
    tol = 1e-9 * scale
    assert (w >= lowest - tol).all() and (w <= E(v) + tol).all()  # min V <= w <= E V
    assert (chi2_constrained(E, v, 2.0 * rho) <= w + tol).all()  # larger ball, lower value
    # translation and scale equivariance
    np.testing.assert_allclose(chi2_constrained(E, v + shift, rho), w + shift,
                               atol=1e-9 * (scale + abs(shift)))
    np.testing.assert_allclose(chi2_constrained(E, factor * v, rho), factor * w,
                               atol=1e-9 * scale * factor)
    # weak duality with the regularized problem: inf_mu E_mu V + lam chi2 <= w + lam rho
    for lam in (0.01 * scale, 0.3 * scale, 10.0 * scale):
        assert (chi2_regularized(E, v, lam) - lam * rho <= w + 1e-8 * scale).all()
    # a ball that contains delta at the lowest state gives the lowest value
    big = 1.0 / np.where(on & (v == lowest[:, None]), mu, 1.0).min() - 1.0 + 1e-9
    np.testing.assert_allclose(chi2_constrained(E, v, big), lowest, atol=tol)


def test_chi2_ball_limits_radii_and_errors():
    E = FactorExpectation(np.array([[0.5, 0.5, 0.0], [0.25, 0.25, 0.5]]))
    v = np.array([0.0, 2.0, 1.0])
    np.testing.assert_array_equal(chi2_constrained(E, v, 0.0), E(v))
    per = chi2_constrained(E, v, [0.0, 0.5])  # one radius per factor
    assert per[0] == E(v)[0] and per[1] == chi2_constrained(E, v, 0.5)[1]
    # the unconstrained-sign solution E V - sqrt(rho Var V) while mu stays >= 0
    assert chi2_constrained(E, v, 0.5)[0] == pytest.approx(1.0 - math.sqrt(0.5))
    with pytest.raises(ValueError, match="rho"):
        chi2_constrained(E, v, -0.1)
    phi = np.random.default_rng(0).dirichlet(np.ones(2), size=10)
    ridge = RidgeExpectation(phi, cholesky_gram(phi, 1.0))
    with pytest.raises(ValueError, match="distributions"):
        chi2_constrained(ridge, np.ones(10), 0.1)
    np.testing.assert_allclose(chi2_constrained(ridge, np.ones(10), 0.0), ridge(np.ones(10)))


# ------------------------------------------------------------------ the uncertainty term
def _bernoulli_divergence(name, p, p0):
    """D(Bern(p) || Bern(p0)) from the definitions (D_TV = 1/2 L1, f(t) = (t-1)^2 for chi^2)."""
    q, q0 = np.array([1 - p, p]), np.array([1 - p0, p0])
    if name == "tv":
        return 0.5 * np.abs(q - q0).sum()
    if name == "kl":
        pos = q > 0
        return float(np.sum(q[pos] * np.log(q[pos] / q0[pos])))
    return float(np.sum((q - q0) ** 2 / q0))


def _factor_grid(name, p0, rho, n=201):
    """Grid of p = mu(state 1) in the ball, with the ball's ends (found by root finding on
    the definition) added to the grid."""
    grid = list(np.linspace(0.0, 1.0, n)) + [p0]
    excess = lambda p: _bernoulli_divergence(name, p, p0) - rho  # noqa: E731
    for end in (0.0, 1.0):
        if excess(end) > 0:
            grid.append(brentq(excess, min(p0, end), max(p0, end), xtol=1e-15))
    grid = np.array(grid)
    keep = np.array([excess(p) <= 1e-12 for p in grid])
    return grid[keep]


def two_state_model(seed, H=3, d=2, A=2):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(2, A))
    mu = rng.dirichlet(np.ones(2), size=(H, d))
    theta = rng.uniform(0.0, 1.0, size=(H, d))
    return FiniteLinearMDP(phi, theta, mu, initial=np.array([0.6, 0.4]))


def brute_force_term(env, inv_diag, name, lam, policy=None):
    """``max`` over the grid-enumerated admissible set of ``E^{pi,P}[sum_h c_h]``, per start.

    Every factor ``mu_{h,i}`` ranges over the grid points of its ball (radius
    ``max_s V*_{h+1} / lam`` from the exact V*). For each (h, s) the next-state probability
    ``q = sum_i phi_i(s, pi(s)) p_i`` takes every value of the product grid; the objective is
    ``c_h(s) + (1 - q) J_{h+1}(0) + q J_{h+1}(1)`` and the choices at different (h, s) are
    independent (the set is a product), so the maximum over the whole product is taken
    stage by stage over the enumerated values.
    """
    H = env.horizon
    _, v_star = robust_values(env, name, lam)
    pi = optimal_policy(env, name, lam) if policy is None else policy
    J = np.zeros(2)
    for h in range(H - 1, -1, -1):
        rho = v_star[h + 1].max() / lam
        grids = [_factor_grid(name, env.mu[h, i, 1], rho) for i in range(env.n_features)]
        new = np.empty(2)
        for s in range(2):
            phi = env.features(h)[s, pi[h, s]]
            cost = phi @ np.sqrt(inv_diag[h])
            q = sum(phi[i] * g.reshape((1,) * i + (-1,) + (1,) * (len(grids) - i - 1))
                    for i, g in enumerate(grids))
            new[s] = cost + np.max((1.0 - q) * J[0] + q * J[1])
        J = new
    return J


@pytest.mark.parametrize("name", ["tv", "kl", "chi2"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_uncertainty_term_equals_brute_force_on_a_two_state_model(name, seed):
    env = two_state_model(seed)
    inv_diag = np.random.default_rng(seed + 10).uniform(0.01, 1.0, size=(3, 2))
    lam = [0.7, 2.0, 5.0][seed]  # radii from above 1 (TV: the whole simplex) to small
    brute = brute_force_term(env, inv_diag, name, lam)
    U = uncertainty_values(env, inv_diag, name, lam)
    np.testing.assert_allclose(U[0], brute, atol=1e-9)
    for s in range(2):
        assert uncertainty_term(env, inv_diag, name, lam, state=s) == pytest.approx(brute[s])
    assert uncertainty_term(env, inv_diag, name, lam) == pytest.approx(env.initial @ brute)
    # any other deterministic policy, through the policy= argument
    other = np.random.default_rng(seed).integers(env.n_actions, size=(3, 2))
    np.testing.assert_allclose(uncertainty_values(env, inv_diag, name, lam, policy=other)[0],
                               brute_force_term(env, inv_diag, name, lam, policy=other),
                               atol=1e-9)


@pytest.mark.parametrize("name", ["tv", "kl", "chi2"])
def test_uncertainty_term_without_shift_is_the_nominal_expectation(name):
    # No reward: V* = 0, every radius is 0 and U^lam(P0) = {P0}, so the term is the nominal
    # E^{pi*, P0}[sum_h c_h] (pi*: all actions tie, the lowest index is taken).
    sim = SimulatedLinearMDP()
    env = FiniteLinearMDP(sim.phi, np.zeros((3, 4)), sim.mu, sim.initial)
    est = R2PVI(name, 1.0).fit(sim.collect(300, seed=1))
    pi = optimal_policy(env, name, 1.0)
    assert (pi == 0).all()
    dist = env.state_distribution(pi)
    costs = bonus_table(env, est)
    nominal = sum(dist[h] @ costs[h][:, 0] for h in range(3))
    assert uncertainty_term(env, est, name, 1.0) == pytest.approx(nominal, rel=1e-12)
    # with the rewards, the radii are positive: the same policy can only see more uncertainty
    assert uncertainty_term(sim, est, name, 1.0, policy=pi) >= nominal - 1e-12


def test_admissible_radii_ball_sup_and_bonus_table():
    _, v_star = robust_values(SimulatedLinearMDP(), "kl", 0.5)
    np.testing.assert_allclose(admissible_radii(v_star, 0.5), v_star[1:].max(axis=1) / 0.5)
    assert admissible_radii(v_star, 0.5)[-1] == 0.0
    E = FactorExpectation(np.array([[0.2, 0.8, 0.0]]))
    u = np.array([1.0, 0.0, 3.0])
    assert ball_sup("tv", E, u, 0.1)[0] == pytest.approx(0.2 + 0.3)  # 0.1 mass to u = 3
    assert ball_sup("tv", E, u, 0.0)[0] == pytest.approx(0.2)
    assert ball_sup(CHI2, E, u, 1e6)[0] == pytest.approx(1.0)  # support only: max is 1
    assert 0.2 < ball_sup("kl", E, u, 0.3)[0] < 1.0
    env = HardInstance(2, 2, 1.0, 0.1, 0.2, [1, -1])
    inv = np.array([[1.0, 4.0, 9.0, 16.0], [0.25, 0.25, 0.25, 0.25]])
    c = bonus_table(env, inv)
    expected = np.einsum("sad,hd->hsa", env.phi, np.sqrt(inv))
    np.testing.assert_allclose(c, expected)


def test_uncertainty_term_errors():
    env = SimulatedLinearMDP()
    inv = np.full((3, 4), 0.1)
    with pytest.raises(ValueError, match="'tv', 'kl' and 'chi2'"):
        uncertainty_term(env, inv, "hellinger", 1.0)
    with pytest.raises(ValueError, match="shape"):
        uncertainty_term(env, np.full((2, 4), 0.1), "tv", 1.0)
    with pytest.raises(NotFittedError, match="not fitted"):
        uncertainty_term(env, R2PVI(), "tv", 1.0)
    with pytest.raises(TypeError, match="finite linear MDP"):
        uncertainty_term("env", inv, "tv", 1.0)
    with pytest.raises(ValueError, match="state"):
        uncertainty_term(env, inv, "tv", 1.0, state=7)
    with pytest.raises(ValueError, match="lam"):
        uncertainty_term(env, inv, "tv", 0.0)


# ------------------------------------------------------------------ suboptimality >= 0
@pytest.mark.parametrize("name", ["tv", "kl", "chi2"])
def test_suboptimality_on_the_theory_instances(name):
    # test_evaluation covers random small models; here: the instances of the experiments
    # and the learned policies they evaluate, at every state.
    lam = 1.0
    with pytest.warns(UserWarning, match="lemma"):
        hard = HardInstance.lower_bound_instance(2, 3, lam, 30, name, seed=0)
    for env in (hard, SimulatedLinearMDP()):
        star = optimal_policy(env, name, lam)
        ds = env.collect(200, policy="behavior", seed=1)
        rng = np.random.default_rng(2)
        policies = [R2PVI(name, lam, beta=b).fit(ds) for b in ("theory", 1.0, 0.0)]
        policies += [rng.dirichlet(np.ones(env.n_actions), size=(3, env.n_states))]
        for s in range(env.n_states):
            assert suboptimality(env, star, name, lam, state=s) == pytest.approx(0, abs=1e-12)
            for pol in policies:
                assert suboptimality(env, pol, name, lam, state=s) >= -1e-12


# ------------------------------------------------------------------ beta and the bounds
@pytest.mark.parametrize("d,H,K,lam,delta", [(4, 3, 100, 1.0, 0.05), (2, 10, 10**5, 0.3, 0.01),
                                             (8, 1, 7, 20.0, 0.5)])
def test_theoretical_beta_is_the_papers(d, H, K, lam, delta):
    log = math.log
    xi_tv = 2 * log(1024 * H * d**0.5 * K**2 / delta)
    xi_kl = log(1024 * d * lam**2 * K**3 * H / delta)
    xi_chi2 = log(192 * K**5 * H**6 * d**3 * (1 + H / (2 * lam)) ** 3 / delta)
    betas = {"tv": 16 * H * d * math.sqrt(xi_tv),
             "kl": 16 * d * lam * math.exp(H / lam) * math.sqrt(H / lam + xi_kl),
             "chi2": 8 * d * H * (1 + 3 * H / (4 * lam)) * math.sqrt(xi_chi2)}
    corollary = {"tv": 16 * H**2 * d**2 * math.sqrt(xi_tv),
                 "kl": 16 * lam * math.exp(H / lam) * d**2 * H * math.sqrt(H / lam + xi_kl),
                 "chi2": 8 * d**2 * H**2 * (1 + 3 * H / (4 * lam)) * math.sqrt(xi_chi2)}
    for name, x in (("tv", xi_tv), ("kl", xi_kl), ("chi2", xi_chi2)):
        assert xi(name, d, H, K, lam, delta) == pytest.approx(x, rel=1e-12)
        beta = theoretical_beta(name, d, H, K, lam, delta)
        assert beta == pytest.approx(betas[name], rel=1e-12)
        assert instance_dependent_bound(name, d, H, K, lam, delta, 0.25) == pytest.approx(
            0.5 * beta, rel=1e-12)
        c = 0.3
        assert instance_independent_bound(name, d, H, K, lam, delta, c) == pytest.approx(
            corollary[name] / math.sqrt(c * K), rel=1e-12)


def test_theoretical_beta_edge_cases():
    assert theoretical_beta("kl", 2, 800, 10, 1.0, 0.05) == math.inf  # e^{H/lam} overflows
    with pytest.raises(ValueError, match="divergence"):
        theoretical_beta("hellinger", 2, 3, 10, 1.0, 0.05)
    with pytest.raises(ValueError, match="delta"):
        theoretical_beta("tv", 2, 3, 10, 1.0, 1.0)
    with pytest.raises(ValueError, match="term"):
        instance_dependent_bound("tv", 2, 3, 10, 1.0, 0.05, -1.0)


# ------------------------------------------------------------------ beta = "theory"
def _dataset(K=150, seed=0):
    return SimulatedLinearMDP().collect(K, seed=seed)


@pytest.mark.parametrize("name", ["tv", "kl", "chi2"])
def test_beta_theory_fits_with_the_theorems_beta(name, tmp_path):
    ds = _dataset()
    est = R2PVI(name, 0.5, beta="theory", delta=0.1).fit(ds)
    beta = theoretical_beta(name, ds.n_features, ds.horizon, ds.n_trajectories, 0.5, 0.1)
    assert est.beta_ == pytest.approx(beta)
    same = R2PVI(name, 0.5, beta=beta).fit(ds)
    np.testing.assert_array_equal(est.weights_, same.weights_)
    phi_all = ds.next_phi[:, 0]
    np.testing.assert_array_equal(est.q_values(phi_all, 0), same.q_values(phi_all, 0))
    assert R2PVI(name, 0.5, beta=0.3).fit(ds).beta_ == 0.3
    back = load(est.save(tmp_path / "m.npz"))
    assert back.beta == "theory" and back.delta == 0.1 and back.beta_ == pytest.approx(beta)
    np.testing.assert_array_equal(back.q_values(phi_all, 1), est.q_values(phi_all, 1))


@pytest.mark.parametrize("kwargs,match", [
    ({"divergence": "hellinger"}, "'tv', 'kl' or 'chi2'"),
    ({"divergence": CHI2}, "'tv', 'kl' or 'chi2'"),
    ({"variance_aware": True}, "variance_aware=False"),
    ({"penalty": "l2"}, "penalty='l1'"),
    ({"gamma": 0.1}, "gamma=1"),
    ({"r_max": 2.0}, "r_max=1"),
    ({"divergence": "kl", "lam": 0.001}, "overflows"),
    ({"delta": 1.0}, "delta"),
    ({"delta": 0.0}, "delta"),
    ({"beta": "theroy"}, "'theory'"),
])
def test_beta_theory_errors(kwargs, match):
    params = {"divergence": "tv", "lam": 1.0, "beta": "theory", **kwargs}
    est = R2PVI(**params)  # parameters are only stored: validation happens in fit
    with pytest.raises(ValueError, match=match):
        est.fit(_dataset(40))


def test_beta_theory_is_only_for_r2pvi():
    with pytest.raises(ValueError, match="beta=.theory. .* exists for R2PVI"):
        PEVI(beta="theory").fit(_dataset(40))
    assert "delta" not in PEVI().get_params()


def test_beta_theory_uses_the_datasets_sizes():
    rng = np.random.default_rng(0)
    K, H, d = 64, 4, 5
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    ds = OfflineDataset.from_features(phi, phi[..., 0], rng.dirichlet(np.ones(d), (K, H, 3)))
    est = R2PVI("chi2", 2.0, beta="theory").fit(ds)
    assert est.beta_ == pytest.approx(theoretical_beta("chi2", d, H, K, 2.0, 0.05))


# ------------------------------------------------------------------ rates and figures
def test_loglog_slope():
    rng = np.random.default_rng(1)
    K = [100, 1000, 10000, 100000]
    fit = loglog_slope(K, [k**-0.5 * rng.uniform(0.8, 1.2, 30) for k in K], n_boot=300)
    assert fit.slope == pytest.approx(-0.5, abs=0.03) and fit.lo < -0.5 < fit.hi
    assert fit.sizes == tuple(float(k) for k in K)
    zeros = loglog_slope(K, [np.array([1.0, 0.0]), np.array([0.1]), np.zeros(3),
                             np.array([0.01])], n_boot=50)
    assert zeros.sizes == (100.0, 1000.0, 100000.0)  # K = 10^4 has mean 0: left out
    assert math.isfinite(zeros.slope) and zeros.slope < 0
    none = loglog_slope(K, [np.zeros(2)] * 4)
    assert math.isnan(none.slope) and none.sizes == ()
    with pytest.raises(ValueError, match="sizes"):
        loglog_slope(K, [np.ones(2)] * 3)


def test_rates_and_bound_check_figures_run_end_to_end(tmp_path, capsys):
    tiny = {"trajectories": [100, 300, 1000], "replications": 2, "bootstrap": 50}
    out = reproduce_figure("rates", tmp_path, overrides=tiny, progress=False)
    rows = out["rows"]
    assert len(rows) == 2 * 3 * 2 * 3 * 2  # envs x K x replications x divergences x betas
    assert {r["beta"] for r in rows} == {"theory", "1"}
    for r in rows:
        assert r["value"] >= -1e-12 and r["term"] > 0 and r["bound"] > r["term"]
        assert r["holds"] and r["ratio"] == pytest.approx(r["value"] / r["bound"])
        if r["beta"] == "theory":
            assert r["beta_used"] == pytest.approx(r["beta_theory"])
    for ext in ("csv", "json", "png", "pdf"):
        assert (tmp_path / f"rates.{ext}").stat().st_size > 0
    text = capsys.readouterr().out
    assert "log-log slope" in text and "hard" in text and "simulated" in text
    check = reproduce_figure("bound-check", tmp_path, progress=False,
                             overrides={"trajectories": [200], "replications": 3,
                                        "divergences": ["kl", "chi2"]})
    assert len(check["rows"]) == 2 * 3 * 2
    assert "holds" in capsys.readouterr().out
    saved = read_results(tmp_path / "bound-check.json")
    assert saved["config"]["settings"]["betas"] == ["theory"]
    # the same seed gives the same numbers
    again = reproduce_figure("bound-check", tmp_path, progress=False, plot=False,
                             overrides={"trajectories": [200], "replications": 3,
                                        "divergences": ["kl", "chi2"]})
    assert [r["value"] for r in again["rows"]] == [r["value"] for r in check["rows"]]
