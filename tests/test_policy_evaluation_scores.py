"""Fitted-Q evaluation scores ("fqe", "robust_fqe"): pooled and per step, against exact DP and
an independent NumPy loop; the initial-state features a dataset of episodes holds."""

import helpers
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi import DRPVI, DRVIL, PEVI, R2PVI, OfflineDataset
from r2pvi.algorithms import Scorer
from r2pvi.envs import FiniteLinearMDP
from r2pvi.evaluation import constrained_values, nominal_values, robust_values
from r2pvi.features import NormalizedRBF, cross_actions


def stationary_mdp(seed=0, H=10, n_actions=3):
    """The fail-state linear MDP of ``helpers.fail_state_mdp`` with the same factors and
    rewards at every step (a stationary task, as pooled fits assume)."""
    rng = np.random.default_rng(seed)
    S, d = 6, 4
    phi = rng.dirichlet(np.ones(d), size=(S, n_actions))
    phi[5] = np.eye(d)[3]
    mu = np.zeros((d, S))
    mu[0, :5] = rng.dirichlet(np.ones(5))
    mu[1] = rng.dirichlet(np.ones(S))
    mu[2] = rng.dirichlet(np.ones(S))
    mu[3] = np.eye(S)[5]
    theta = rng.uniform(0.0, 1.0, size=d)
    theta[3] = 0.0
    start = rng.dirichlet(np.ones(5))
    return FiniteLinearMDP(phi, np.tile(theta, (H, 1)), np.tile(mu, (H, 1, 1)),
                           initial=np.r_[start, 0.0], fail_states=(5,))


def exact_at(V, states):
    return float(np.mean(V[0][states]))


# ------------------------------------------------------------------------------ exact truth


def test_pooled_fqe_approaches_the_exact_nominal_and_robust_values_on_a_stationary_mdp():
    """With every step's transitions in one regression, FQE of the greedy policy converges
    to its exact value (and the robust variant to its exact TV-regularized value). Measured
    on 20000 held-out trajectories, H = 10: errors 0.002 (nominal, value 2.8) and < 1e-3
    (robust, value 0.97)."""
    env = stationary_mdp(0)
    est = R2PVI("tv", 0.3, beta=0.05).fit(env.collect(40, seed=0))
    held = env.collect(20_000, seed=7)
    s0 = held.states[:, 0]
    x0 = env.features(0)[s0]
    _, V = nominal_values(env, est)
    _, V_rob = robust_values(env, "tv", 0.3, est)
    assert est.score(held, kind="fqe", initial_phi=x0, pooled=True) == pytest.approx(
        exact_at(V, s0), abs=0.02)
    assert est.score(held, kind="robust_fqe", initial_phi=x0, pooled=True) == pytest.approx(
        exact_at(V_rob, s0), abs=0.02)
    assert exact_at(V, s0) - exact_at(V_rob, s0) > 1.0  # the two targets are far apart


def test_pooled_fqe_shrinks_far_less_than_per_step_fqe_on_few_held_out_trajectories():
    """A per-step regression holds K rows, the pooled one (H - 1) K: the ridge pulls each
    per-step value toward 0 and the bias compounds over the steps. Measured (H = 10, 30
    held-out trajectories, 20 repetitions): bias -0.38 pooled, -1.34 per step (value 2.8)."""
    env = stationary_mdp(0)
    est = R2PVI("tv", 0.3, beta=0.05).fit(env.collect(40, seed=0))
    _, V = nominal_values(env, est)
    bias = {True: [], False: []}
    for rep in range(10):
        held = env.collect(30, seed=1000 + rep)
        x0 = env.features(0)[held.states[:, 0]]
        for pooled in (True, False):
            got = est.score(held, kind="fqe", initial_phi=x0, pooled=pooled)
            bias[pooled].append(got - exact_at(V, held.states[:, 0]))
    assert np.mean(bias[False]) < -0.8
    assert abs(np.mean(bias[True])) < 0.5 * abs(np.mean(bias[False]))


def _robust_cases(env):
    return [
        (R2PVI("tv", 0.3, beta=0.05), lambda e: robust_values(env, "tv", 0.3, e), 0.01),
        (R2PVI("kl", 0.3, beta=0.05), lambda e: robust_values(env, "kl", 0.3, e), 0.04),
        (R2PVI("chi2", 0.3, beta=0.05), lambda e: robust_values(env, "chi2", 0.3, e), 0.02),
        (DRPVI(rho=0.2, beta=0.05), lambda e: constrained_values(env, "tv", 0.2, e), 0.02),
        (DRVIL(rho=0.2, beta=0.05), lambda e: constrained_values(env, "kl", 0.2, e), 0.06),
        (PEVI(beta=0.05), lambda e: nominal_values(env, e), 0.02),
    ]


@pytest.mark.parametrize("case", range(6), ids=["tv", "kl", "chi2", "drpvi", "drvil", "pevi"])
@pytest.mark.parametrize("seed", [0, 1])
def test_robust_fqe_approaches_the_exact_robust_value_of_the_greedy_policy(case, seed):
    """Each estimator's step rule on the held-out ridge operator evaluates its policy under
    its own uncertainty model; with 20000 held-out trajectories of a (step-dependent) linear
    MDP it matches the exact robust value under the true factors (``r2pvi.evaluation``).
    Measured over seeds 0-9, largest errors: TV 0.002, KL 0.019, chi^2 0.007, TV ball 0.006,
    KL ball 0.034, PEVI (the nominal value) 0.007; the tolerances are below each
    estimator's gap between its nominal and robust values, so the nominal value fails."""
    env = helpers.fail_state_mdp(seed, n_actions=3, reward_high=1.0, random_initial=True)
    est, exact, tol = _robust_cases(env)[case]
    est.fit(env.collect(40, seed=seed))
    held = env.collect(20_000, seed=100 + seed)
    s0 = held.states[:, 0]
    got = est.score(held, kind="robust_fqe", initial_phi=env.features(0)[s0])
    _, V = exact(est)
    assert got == pytest.approx(exact_at(V, s0), abs=tol)
    if not isinstance(est, PEVI):
        _, V_nom = nominal_values(env, est)
        assert exact_at(V_nom, s0) - exact_at(V, s0) > 1.5 * tol


# ------------------------------------------------------------------------------ episodes


def random_episodes(rng, n, H, n_obs=2, shifted=True, p_end=None):
    """``n`` episodes of random 2-D observations and 2 actions, cut at ``H``: rewards -1 or
    0 (``shifted``: the data needs ``reward_offset``) or in [0, 1]; lengths uniform in
    ``1..H`` and terminated half the time, or (``p_end``) geometric and always terminated."""
    eps = []
    for _ in range(n):
        T = int(rng.integers(1, H + 1)) if p_end is None else min(int(rng.geometric(p_end)), H)
        term = np.zeros(T, bool)
        term[-1] = bool(rng.random() < 0.5) if p_end is None else True
        rewards = -rng.integers(0, 2, T).astype(float) if shifted else rng.random(T)
        eps.append({"observations": rng.uniform(-1, 1, (T + 1, n_obs)),
                    "actions": rng.integers(0, 2, T), "rewards": rewards,
                    "terminations": term, "truncations": ~term & (np.arange(T) == T - 1)})
    return eps


def numpy_pooled_fqe(est, ds, x0, robust_lam=None, evaluation=None, x0_eval=None):
    """Independent pooled FQE on the dense arrays, every step (no fixed-point stop):
    ``Q^pi_h = clip(phi^T (theta + E(v)), 0, (H - h) r_max)``, or TV's
    ``clip(E(min(v, min v + lam)), lower, upper)`` for ``E(v)``; absorbing next states
    (episodes shifted by ``c``) have value ``(H - h - 1) c`` at step ``h``. ``evaluation``:
    the same episodes with other features to regress on (the policy acts on ``ds``)."""
    H = ds.horizon
    r_max, c = 1.0, float(ds._source.reward_offset)
    P = max(H - 1, 1)
    own = ds.next_phi[:, :P].reshape(-1, ds.n_actions, ds.n_features)
    ev = ds if evaluation is None else evaluation
    d = ev.n_features
    X = ev.phi[:, :P].reshape(-1, d)
    nphi = ev.next_phi[:, :P].reshape(-1, ds.n_actions, d)
    absorbing = ~np.isnan(ds.next_values[:, :P].reshape(-1, ds.n_actions))
    lam_inv = np.linalg.inv(X.T @ X + est.gamma * np.eye(d))
    theta = lam_inv @ X.T @ ds.rewards[:, :P].reshape(-1)
    w = theta.copy()  # step H - 1
    for h in range(H - 2, -1, -1):
        known = np.where(absorbing, (H - h - 1) * c, np.nan)
        act = est.act(own, h + 1, known)
        v = np.clip(nphi[np.arange(len(act)), act] @ w, 0.0, (H - h - 1) * r_max)
        v = np.where(absorbing[:, 0], (H - h - 1) * c, v)
        if robust_lam is None:
            w = theta + lam_inv @ X.T @ v
        else:
            lo, hi = min(0.0, v.min()), max((H - h - 1) * r_max, v.max())
            w = theta + np.clip(lam_inv @ X.T @ np.minimum(v, v.min() + robust_lam), lo, hi)
    a0 = est.act(x0, 0)
    x0 = x0 if x0_eval is None else x0_eval
    return float(np.mean(np.clip(x0[np.arange(len(a0)), a0] @ w, 0.0, H * r_max)))


def check_against_numpy(eps, H, lam, beta):
    fmap = cross_actions(NormalizedRBF(n_centers=2).fit(
        np.concatenate([e["observations"] for e in eps])), 2)
    ds = OfflineDataset.from_episodes(eps, fmap, 2, horizon=H, reward_offset="auto")
    assert ds.stationary and ds._source.phi.psi is not None
    est = R2PVI("tv", lam, beta=beta, r_max=1.0).fit(ds)
    x0 = ds.initial_features()
    for robust in (False, True):
        got = est.score(ds, kind="robust_fqe" if robust else "fqe")
        want = numpy_pooled_fqe(est, ds, x0, lam if robust else None)
        assert got == pytest.approx(want, rel=1e-8, abs=1e-10)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), H=st.integers(1, 12), lam=st.sampled_from([0.05, 0.5, 5.0]),
       beta=st.sampled_from([0.0, 0.2]), shifted=st.booleans())
def test_pooled_fqe_of_episodes_matches_an_independent_numpy_loop(seed, H, lam, beta, shifted):
    """Episodes stored as state features (crossed rows never formed), terminations with
    shifted rewards (step-dependent absorbing values) or not, padded steps after an episode's
    end: the same numbers as a dense loop over every step."""
    check_against_numpy(random_episodes(np.random.default_rng(seed), 12, H, shifted=shifted),
                        H, lam, beta)


def test_the_fixed_point_stop_of_pooled_fqe_changes_no_number(monkeypatch):
    """Episodes that end (absorbing, value 0) with probability 1/2 a step: the policy's
    values converge geometrically, so the pooled evaluation stops at a fixed point long
    before step 0, and gives the numbers of the full loop."""
    import r2pvi.algorithms._fqe as fqe

    stops = []
    original = fqe.converged
    monkeypatch.setattr(fqe, "converged",
                        lambda a, b: stops.append(original(a, b)) or stops[-1])
    rng = np.random.default_rng(3)
    check_against_numpy(random_episodes(rng, 40, 80, shifted=False, p_end=0.5), 80, 0.5, 0.1)
    assert sum(stops) == 2  # one stop for each of fqe and robust_fqe
    assert len(stops) < 2 * 60  # well before the 80 steps


def numpy_per_step_fqe(est, ds, x0, gamma=None):
    """Independent per-step FQE: step ``h`` regresses ``r_h + Q^pi_{h+1}(s', pi(s'))`` on
    its own rows (ridge ``gamma``, the estimator's by default)."""
    H, d = ds.horizon, ds.n_features
    gamma = est.gamma if gamma is None else gamma
    w = None
    for h in range(H - 1, -1, -1):
        X, y = ds.phi[:, h], ds.rewards[:, h].copy()
        if h < H - 1:
            nphi, known = ds.next_phi[:, h], ds.next_values[:, h]
            act = est.act(nphi, h + 1, known)
            rows = np.arange(len(act))
            v = np.clip(nphi[rows, act] @ w, 0.0, (H - h - 1) * est.r_max)
            y += np.where(np.isnan(known[rows, act]), v, known[rows, act])
        w = np.linalg.solve(X.T @ X + gamma * np.eye(d), X.T @ y)
    a0 = est.act(x0, 0)
    return float(np.mean(np.clip(x0[np.arange(len(a0)), a0] @ w, 0.0, H * est.r_max)))


@pytest.mark.parametrize("penalty", ["elliptical", "l1"])
def test_fqe_of_a_per_step_fit_matches_independent_loops_in_both_forms(penalty):
    """A per-step fit acts with a different penalty at every step: its policy at the pooled
    next states changes with the step, and the evaluation follows it (pooled or per step)."""
    env = stationary_mdp(1, H=6)
    est = R2PVI("tv", 0.3, beta=0.3, penalty=penalty).fit(env.collect(50, seed=0))
    held = env.collect(200, seed=1)
    x0 = env.features(0)[held.states[:, 0]]
    assert est.score(held, kind="fqe", initial_phi=x0) == pytest.approx(
        numpy_per_step_fqe(est, held, x0), rel=1e-9)
    assert est.score(held, kind="fqe", initial_phi=x0, pooled=True) == pytest.approx(
        numpy_pooled_fqe(est, held, x0), rel=1e-9)


def episode_data(n=30, H=8, seed=0):
    rng = np.random.default_rng(seed)
    eps = random_episodes(rng, n, H)
    fmap = cross_actions(NormalizedRBF(n_centers=2).fit(
        np.concatenate([e["observations"] for e in eps])), 2)
    return eps, fmap, OfflineDataset.from_episodes(eps, fmap, 2, horizon=H,
                                                   reward_offset="auto")


def test_episode_datasets_hold_their_initial_features_and_fqe_defaults_to_them():
    eps, fmap, ds = episode_data()
    first = np.stack([e["observations"][0] for e in eps])
    want = np.stack([fmap(first, np.full(len(eps), a)) for a in range(2)], axis=1)
    np.testing.assert_allclose(ds.initial_features(), want, rtol=1e-12)
    np.testing.assert_allclose(ds[[3, 1]].initial_features(), want[[3, 1]], rtol=1e-12)
    est = R2PVI("tv", 0.5, beta=0.1, r_max=1.0).fit(ds[:20])
    held = ds[20:]
    for kind in ("fqe", "robust_fqe"):
        assert est.score(held, kind=kind) == est.score(held, kind=kind,
                                                       initial_phi=want[20:])
        assert Scorer(kind)(est, held) == est.score(held, kind=kind)
    # pooled by default: the dataset is stationary
    assert est.score(held, kind="fqe") == est.score(held, kind="fqe", pooled=True)
    assert est.score(held, kind="fqe") != est.score(held, kind="fqe", pooled=False)


def test_observation_datasets_hold_their_initial_features():
    rng = np.random.default_rng(0)
    K, H, A = 5, 3, 2
    obs = rng.random((K, H, 1))

    def fmap(x, a):
        return np.stack([x[:, 0] * (a == 0), x[:, 0] * (a == 1), 1 - x[:, 0]], axis=1)

    ds = OfflineDataset.from_observations(obs, rng.integers(A, size=(K, H)), rng.random((K, H)),
                                          rng.random((K, H, 1)), fmap, A)
    want = np.stack([fmap(obs[:, 0], np.full(K, a)) for a in range(A)], axis=1)
    np.testing.assert_allclose(ds.initial_features(), want)


def test_fqe_without_initial_features_names_the_argument():
    env = helpers.fail_state_mdp(0)
    ds = env.collect(30, seed=0)
    assert ds.initial_features() is None
    est = PEVI().fit(ds)
    for kind in ("fqe", "robust_fqe"):
        with pytest.raises(ValueError, match="needs initial_phi.*initial_features"):
            est.score(ds, kind=kind)


def test_score_form_arguments_are_checked():
    _, _, ds = episode_data()
    est = R2PVI("tv", 0.5, r_max=1.0).fit(ds)
    with pytest.raises(ValueError, match="pooled must be 'auto'"):
        est.score(ds, kind="fqe", pooled="yes")
    with pytest.raises(TypeError, match="pooled must be 'auto'"):
        est.score(ds, kind="fqe", pooled=1)
    with pytest.raises(ValueError, match="pooled is used by kind='fqe' and 'robust_fqe' only"):
        est.score(ds, pooled=True)
    with pytest.raises(ValueError, match="gamma is used by kind='fqe' and 'robust_fqe' only"):
        est.score(ds, gamma=0.1)
    with pytest.raises(ValueError, match="gamma is used by .* drop it for kind='model'"):
        est.score(ds, kind="model", gamma=0.1)
    with pytest.raises(ValueError, match="n_neighbors is used by kind='model' only"):
        est.score(ds, kind="fqe", n_neighbors=3)
    with pytest.raises(ValueError, match="n_rollouts, random_state are used by kind='model'"):
        Scorer("bellman", n_rollouts=2, random_state=1)
    with pytest.raises(ValueError, match="gamma must be"):
        est.score(ds, kind="fqe", gamma=0.0)
    with pytest.raises(ValueError, match="initial_phi, pooled and gamma are used by"):
        Scorer("bellman", initial_phi=lambda d: d.initial_features())
    assert repr(Scorer("robust_fqe")) == "Scorer('robust_fqe')"
    assert repr(Scorer("fqe", gamma=0.01)) == "Scorer('fqe', gamma=0.01)"


def test_the_evaluation_ridge_parameter_is_the_estimators_unless_given():
    """``gamma`` of the score is the evaluation's own: scores of estimators fitted with
    different ``gamma`` are then comparable (the same regression of the same targets)."""
    env = stationary_mdp(0, H=5)
    train, held = env.collect(60, seed=0), env.collect(300, seed=1)
    x0 = env.features(0)[held.states[:, 0]]
    a = R2PVI("tv", 0.3, gamma=1.0).fit(train)
    b = R2PVI("tv", 0.3, gamma=0.1).fit(train)
    want = numpy_per_step_fqe(a, held, x0, gamma=0.1)
    assert a.score(held, kind="fqe", initial_phi=x0, gamma=0.1) == pytest.approx(want, rel=1e-9)
    assert a.score(held, kind="fqe", initial_phi=x0) != pytest.approx(want, rel=1e-6)
    assert b.score(held, kind="fqe", initial_phi=x0) == b.score(held, kind="fqe",
                                                                initial_phi=x0, gamma=0.1)


@pytest.mark.filterwarnings("ignore::UserWarning")  # tiny per-step fits starve: not the point
@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31), penalty=st.sampled_from(["l1", "l2", "elliptical"]),
       n_episodes=st.sampled_from([3, 40]))
def test_the_penalty_at_crossed_next_states_is_the_engines(seed, penalty, n_episodes):
    """The penalty formed from ``psi`` and one action's block of the fitted factor equals
    the engine's on the dense rows (primal factor with many episodes, dual with few)."""
    from r2pvi.algorithms._fqe import _penalty_values
    from r2pvi.engine.pooled import next_penalty

    rng = np.random.default_rng(seed)
    eps = random_episodes(rng, n_episodes, 5, n_obs=3)
    fmap = cross_actions(NormalizedRBF(n_centers=2).fit(
        np.concatenate([e["observations"] for e in eps])), 2)
    ds = OfflineDataset.from_episodes(eps, fmap, 2, horizon=5, reward_offset="auto")
    est = R2PVI("tv", 0.5, beta=0.3, penalty=penalty, r_max=1.0,
                time_homogeneous=False).fit(ds)
    feats = ds._source.pooled(4)[2]
    dense = feats.dense()
    for h in range(5):
        ellip = None if est._elliptical is None else est._elliptical[h]
        got = _penalty_values(feats, penalty, 0.3, est.gram_inv_diag_[h], ellip)
        want = next_penalty(dense, penalty, 0.3, est.gram_inv_diag_[h], ellip)
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


def test_fqe_with_an_evaluation_map_regresses_on_its_features_and_acts_on_the_estimators():
    """Estimators fitted with different maps are scored on one scale: the regressions use
    the evaluation map's features of the same episodes (an independent dense loop over a
    dataset built with that map), the greedy actions the estimator's own features."""
    rng = np.random.default_rng(4)
    eps = random_episodes(rng, 40, 9, n_obs=2)
    obs = np.concatenate([e["observations"] for e in eps])
    own = cross_actions(NormalizedRBF(n_centers=2).fit(obs), 2)
    fine = cross_actions(NormalizedRBF(n_centers=4).fit(obs), 2)
    ds = OfflineDataset.from_episodes(eps, own, 2, horizon=9, reward_offset="auto")
    ds_fine = OfflineDataset.from_episodes(eps, fine, 2, horizon=9, reward_offset="auto")
    est = R2PVI("tv", 0.5, beta=0.1, r_max=1.0).fit(ds[:25])
    held, held_fine = ds[25:], ds_fine[25:]
    got = est.score(held, kind="fqe", evaluation_map=fine, gamma=0.1)
    want = numpy_pooled_fqe(est, held, held.initial_features(), evaluation=held_fine,
                            x0_eval=held_fine.initial_features())
    # numpy_pooled_fqe regresses with est.gamma (1.0): compare at the same ridge
    assert est.score(held, kind="fqe", evaluation_map=fine, gamma=1.0) == pytest.approx(
        want, rel=1e-9)
    assert got != pytest.approx(want, rel=1e-6)
    # the estimator's own map as the evaluation map: the plain score
    assert est.score(held, kind="fqe", evaluation_map=own) == pytest.approx(
        est.score(held, kind="fqe"), rel=1e-10)
    assert Scorer("fqe", evaluation_map=fine)(est, held) == est.score(
        held, kind="fqe", evaluation_map=fine)
    for kw in ({"kind": "robust_fqe"}, {"kind": "fqe", "pooled": False},
               {"kind": "fqe", "initial_phi": held.initial_features()}):
        with pytest.raises(ValueError, match="evaluation_map is for kind='fqe' with pooled"):
            est.score(held, evaluation_map=fine, **kw)
    with pytest.raises(ValueError, match="crossed with 3 actions"):
        est.score(held, kind="fqe", evaluation_map=cross_actions(fine.state_map, 3))
    with pytest.raises(ValueError, match="used by kind='fqe' only"):
        Scorer("robust_fqe", evaluation_map=fine)
    env = stationary_mdp(0, H=4)
    finite = env.collect(30, seed=0)
    with pytest.raises(ValueError, match="needs a dataset of episodes"):
        PEVI().fit(finite).score(finite, kind="fqe", evaluation_map=fine, pooled=True,
                                 initial_phi=None)
