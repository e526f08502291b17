"""Environments: factor models against the paper's transition tables, datasets, seeding, errors."""

import itertools

import numpy as np
import pytest

from r2pvi import R2PVI, OfflineDataset
from r2pvi.envs import (
    SIMULATED_ACTIONS,
    AmericanPutOption,
    FiniteLinearMDP,
    HardInstance,
    SimulatedLinearMDP,
    policy_table,
)

# ---------------------------------------------------------------------- independent tables
X1, X2, X3, X4, X5 = range(5)


def paper_transition(h, s, a, delta=0.3, xi_norm=0.2, q=None):
    """P_h(. | s, a) of the simulated linear MDP written state by state from the paper's
    description (Liu & Xu 2024, Supp. A.1, as coded by the authors): no factors involved."""
    p = delta + xi_norm / 4.0 * np.sum(a)
    out = np.zeros(5)
    if s == X4:
        out[X4] = 1.0
    elif s == X5:
        out[X5] = 1.0
    elif h == 0 and q is not None:  # perturbed first step, from any of x1..x3
        nxt = {X1: X2, X2: X2, X3: X4}[s]
        out[nxt] += 1.0 - p
        out[X4] += q * p
        out[X5] += (1.0 - q) * p
    else:
        if s == X1:
            out[X2], out[X4] = 0.999 * (1.0 - p), 0.001 * (1.0 - p)
        elif s == X2:
            out[X3], out[X4] = 0.999 * (1.0 - p), 0.001 * (1.0 - p)
        else:  # x3
            out[X4] = 1.0 - p
        out[X5] += p
    return out


def paper_reward(h, s, a, delta=0.3, xi_norm=0.2):
    if h == 0 or s == X4:
        return 0.0
    if s == X5:
        return 1.0
    return 0.0 if s == X1 else delta + xi_norm / 4.0 * np.sum(a)


def reachable(env, policy="uniform"):
    occ = env.state_distribution(policy)
    return [(h, s) for h in range(env.horizon) for s in range(env.n_states) if occ[h, s] > 0]


@pytest.mark.parametrize("delta,xi_norm", [(0.3, 0.2), (0.3, 0.1), (0.5, 0.3)])
@pytest.mark.parametrize("q", [None, 0.0, 0.4, 1.0])
def test_simulated_factor_model_reproduces_the_paper_transition_table(delta, xi_norm, q):
    env = SimulatedLinearMDP(delta, xi_norm)
    if q is not None:
        env = env.perturbed(q)
    pairs = reachable(env)
    expected_states = {(0, X1), (1, X2), (1, X4), (1, X5), (2, X3), (2, X4), (2, X5)}
    if q == 0.0:
        expected_states.discard((1, X4))  # no leak and no mass of factor 4 on x4 at step 0
    if q == 1.0:
        expected_states.discard((1, X5))  # x1 -> x5 needs 1 - q > 0 at step 0
    assert set(pairs) == expected_states
    for h, s in pairs:
        for a_idx, a in enumerate(SIMULATED_ACTIONS):
            np.testing.assert_allclose(
                env.transition_matrix(h)[s, a_idx], paper_transition(h, s, a, delta, xi_norm, q),
                atol=1e-14, err_msg=f"h={h} s=x{s + 1} a={a}",
            )
            assert env.reward_table[h, s, a_idx] == pytest.approx(
                paper_reward(h, s, a, delta, xi_norm), abs=1e-14)


def test_simulated_structure_and_perturbation_facts():
    env = SimulatedLinearMDP()
    assert env.horizon == 3 and env.n_states == 5 and env.n_actions == 16
    assert [tuple(a) for a in SIMULATED_ACTIONS] == list(itertools.product([-1, 1], repeat=4))
    np.testing.assert_array_equal(env.initial, np.eye(5)[X1])
    assert env.fail_states == (X4,)
    np.testing.assert_allclose(env.xi, [0.05] * 4)
    # q = 0 is not the nominal model: the 0.001 leak into x4 disappears at step 0 only.
    p0 = env.perturbed(0.0)
    assert not np.allclose(p0.transitions[0], env.transitions[0])
    np.testing.assert_array_equal(p0.transitions[1:], env.transitions[1:])
    np.testing.assert_array_equal(p0.mu[0, 0], np.eye(5)[X2])
    assert env.perturbed(0.3).perturbed(0.6).q == 0.6


def test_hard_instance_matches_the_construction():
    d, H, eps, delta = 3, 4, 0.05, 0.2
    rng = np.random.default_rng(3)
    xi = rng.choice([-1.0, 1.0], size=(H, d))
    env = HardInstance(d, H, lam=0.5, epsilon=eps, delta=delta, xi=xi)
    acts = np.array(list(itertools.product([0, 1], repeat=d)), dtype=float)
    np.testing.assert_array_equal(env.action_vectors, acts)
    assert env.n_features == d + 2 and env.n_states == 2
    np.testing.assert_allclose(env.initial, [(d + 1) / (d + 2), 1 / (d + 2)])
    for h in range(H):
        for i, a in enumerate(acts):
            np.testing.assert_allclose(env.features(h)[0, i],
                                       np.concatenate([a / d, [1 - a.sum() / d, 0.0]]))
            np.testing.assert_allclose(env.transition_matrix(h)[0, i], [1 - eps, eps])
            np.testing.assert_allclose(env.transition_matrix(h)[1, i], [0.0, 1.0])
            assert env.reward_table[h, 0, i] == pytest.approx(
                delta / (2 * d) * (xi[h] @ a + d))
            assert env.reward_table[h, 1, i] == 0.0
    # behaviour: uniform on {e_1, ..., e_d, 0}
    beh = env.behavior_policy
    support = {tuple(acts[i]) for i in np.flatnonzero(beh[0, 0])}
    assert support == {tuple(r) for r in np.eye(d)} | {(0.0,) * d}
    np.testing.assert_allclose(beh.sum(-1), 1.0)
    # a*_h = (1 + xi_h) / 2
    np.testing.assert_array_equal(acts[env.optimal_actions], (1 + xi) / 2)


def test_hard_instance_lower_bound_parameters():
    d, H, lam, K = 2, 3, 2.0, 10_000
    env = HardInstance.lower_bound_instance(d, H, lam, K, "kl", seed=0)
    assert env.delta == pytest.approx(d**1.5 / np.sqrt(2 * K))
    kl_eps = min(1 - 2 ** (-1 / H), d**1.5 / (64 * lam * np.sqrt(2 * K)))
    assert env.epsilon == pytest.approx(kl_eps)
    tv = HardInstance.lower_bound_instance(d, H, lam, K, "tv", xi=np.ones(d))
    assert tv.epsilon == pytest.approx(1 - 2 ** (-1 / H))
    with pytest.warns(UserWarning, match="condition"):
        HardInstance.lower_bound_instance(d, H, 0.01, 10, "chi2", seed=0)


def random_model(seed, S=4, A=3, d=3, H=3, step_dependent=False):
    rng = np.random.default_rng(seed)
    shape = (H, S, A) if step_dependent else (S, A)
    phi = rng.dirichlet(np.ones(d), size=shape)
    mu = rng.dirichlet(np.ones(S), size=(H, d))
    theta = rng.uniform(0, 1, size=(H, d))
    return FiniteLinearMDP(phi, theta, mu, rng.dirichlet(np.ones(S)))


@pytest.mark.parametrize("step_dependent", [False, True])
def test_factor_model_and_sampled_transitions_agree(step_dependent):
    env = random_model(1, step_dependent=step_dependent)
    phi = env.phi if step_dependent else np.broadcast_to(env.phi, (3,) + env.phi.shape)
    np.testing.assert_allclose(env.transitions, np.einsum("hsad,hdt->hsat", phi, env.mu))
    np.testing.assert_allclose(env.transitions.sum(-1), 1.0)
    K = 40_000
    traj = env.simulate(K, "uniform", seed=2)
    for h in range(env.horizon):
        counts = np.zeros((env.n_states, env.n_actions, env.n_states))
        np.add.at(counts, (traj.states[:, h], traj.actions[:, h], traj.next_states[:, h]), 1)
        n_sa = counts.sum(-1, keepdims=True)
        freq = counts / np.maximum(n_sa, 1)
        p = env.transitions[h]
        se = np.sqrt(p * (1 - p) / np.maximum(n_sa, 1)) + 1e-12
        assert (np.abs(freq - p) <= 4.5 * se + 1e-9).mean() > 0.99
        assert (traj.next_states[:, h] == (traj.states[:, h + 1] if h + 1 < env.horizon
                                           else traj.next_states[:, h])).all()


def test_collect_builds_the_dataset_from_the_model():
    env = SimulatedLinearMDP()
    ds = env.collect(2000, seed=0)
    assert isinstance(ds, OfflineDataset)
    assert (ds.n_trajectories, ds.horizon, ds.n_features, ds.n_actions) == (2000, 3, 4, 16)
    s, a, ns = ds.states, ds.actions, ds.next_states
    assert (s[:, 0] == X1).all()
    np.testing.assert_array_equal(s[:, 1:], ns[:, :-1])
    np.testing.assert_array_equal(ds.phi, env.phi[s, a])
    np.testing.assert_array_equal(ds.next_phi[:, :2], env.phi[ns[:, :2]])
    np.testing.assert_array_equal(ds.rewards, env.reward_table[np.arange(3), s, a])
    nv = ds.next_values[:, :2]
    fail = ns[:, :2] == X4
    assert fail.any() and np.isnan(nv[~fail]).all() and (nv[fail] == 0.0).all()
    # the behaviour policy is uniform over the 16 actions
    counts = np.bincount(a.ravel(), minlength=16) / a.size
    assert np.abs(counts - 1 / 16).max() < 4 * np.sqrt(1 / 16 * 15 / 16 / a.size)


def test_seeding_is_reproducible_and_generators_continue():
    env = SimulatedLinearMDP()
    a = env.collect(50, seed=7)
    b = env.collect(50, seed=7)
    np.testing.assert_array_equal(a.actions, b.actions)
    np.testing.assert_array_equal(a.next_states, b.next_states)
    assert not np.array_equal(env.collect(50, seed=8).actions, a.actions)
    rng = np.random.default_rng(7)
    first = env.collect(50, seed=rng)
    second = env.collect(50, seed=rng)
    np.testing.assert_array_equal(first.actions, a.actions)
    assert not np.array_equal(second.actions, first.actions)
    np.testing.assert_array_equal(env.collect(5, seed=np.random.SeedSequence(1)).actions,
                                  env.collect(5, seed=1).actions)


def test_hard_instance_dataset_has_gaussian_rewards_and_behaviour_actions():
    env = HardInstance(2, 3, lam=1.0, epsilon=0.1, delta=0.5, xi=[1, -1])
    ds = env.collect(20_000, policy="behavior", seed=0)
    assert set(np.unique(ds.actions)) <= set(env.behavior_actions.tolist())
    mean = env.reward_table[np.arange(3), ds.states, ds.actions]
    noise = ds.rewards - mean
    assert abs(noise.mean()) < 4 / np.sqrt(noise.size)
    assert noise.std() == pytest.approx(1.0, abs=0.02)
    np.testing.assert_allclose(np.bincount(ds.states[:, 0]) / 20_000, env.initial, atol=0.01)
    fail_next = ds.next_states[:, :2] == 1
    assert (ds.next_values[:, :2][fail_next] == 0).all()


def test_put_option_dataset_follows_the_lattice_and_known_payoffs():
    env = AmericanPutOption()
    assert env.anchors[0] == 80 and env.spacing == pytest.approx(2.0)
    assert AmericanPutOption(anchor_span=100, d=30).spacing == pytest.approx(100 / 30)
    ds = env.collect(3000, seed=1)
    s, ns = ds.states, ds.next_states
    assert (ds.actions == 0).all() and (ds.rewards == 0).all()
    assert ((s[:, 0] >= 95) & (s[:, 0] <= 105)).all()
    np.testing.assert_allclose(s[:, 1:], ns[:, :-1])
    ratio = ns / s
    up = np.isclose(ratio, 1.02)
    assert (up | np.isclose(ratio, 0.98)).all()
    assert abs(up.mean() - 0.5) < 4 * np.sqrt(0.25 / up.size)
    hats = np.maximum(0.0, 1 - np.abs(s[..., None] - (80 + 2.0 * np.arange(30))) / 2.0)
    np.testing.assert_allclose(ds.phi, hats)
    np.testing.assert_allclose(ds.next_values[:, :-1, 1], np.maximum(0, 100 - ns[:, :-1]))
    assert np.isnan(ds.next_values[:, :-1, 0]).all()
    assert (ds.next_phi[..., 1, :] == 0).all()
    fixed = AmericanPutOption(s0=98.0).collect(10, seed=0)
    assert (fixed.states[:, 0] == 98.0).all()


def test_put_option_exercise_ends_the_episode():
    env = AmericanPutOption(H=6, d=5)
    traj = env.simulate(2000, "uniform", seed=3)
    ex = traj.actions == 1
    first = np.where(ex.any(1), ex.argmax(1), env.H)
    for k in range(200):
        t = first[k]
        if t < env.H:
            assert traj.rewards[k, t] == pytest.approx(max(0.0, 100 - traj.states[k, t]))
            assert np.isnan(traj.next_states[k, t:]).all()
            assert np.isnan(traj.states[k, t + 1 :]).all()
            assert (traj.rewards[k, t + 1:] == 0).all()
    ds = env.make_dataset(*traj)
    ended = np.isnan(ds.states)
    assert (ds.phi[ended] == 0).all()
    after = np.isnan(ds.next_states[:, :-1])
    assert (ds.next_values[:, :-1][after] == 0).all()


def test_estimators_act_in_the_models():
    env = SimulatedLinearMDP()
    ds = env.collect(300, seed=0)
    est = R2PVI("tv", 0.3, beta=0.1).fit(ds)
    table = policy_table(env, est)
    for h in range(3):
        q = est.q_values(env.features(h), h, known_values=env.known_values)
        np.testing.assert_array_equal(table[h].argmax(1), q.argmax(1))
    put = AmericanPutOption(H=5, d=6)
    est = R2PVI("kl", 1.0, beta=0.1, r_max=put.r_max).fit(put.collect(200, seed=0))
    prices = np.array([85.0, 99.0, 120.0])
    q = est.q_values(put.phi_all(prices), 2, put.known_values(prices))
    np.testing.assert_array_equal(put.actions(est, 2, prices), q.argmax(1))


# ---------------------------------------------------------------------- errors
GOOD = dict(phi=np.full((2, 2, 2), 0.5), theta=np.zeros((2, 2)),
            mu=np.full((2, 2, 2), 0.5), initial=[1.0, 0.0])


@pytest.mark.parametrize("change,err,match", [
    ({"phi": np.full((2, 2, 2), 0.6)}, ValueError, "phi.*sum to 1"),
    ({"phi": np.array([[[1.5, -0.5]] * 2] * 2)}, ValueError, "phi has a negative"),
    ({"phi": np.ones((2, 2))}, ValueError, "phi must have shape"),
    ({"phi": "abc"}, TypeError, "phi must be a numeric"),
    ({"mu": np.full((2, 2, 3), 0.5)}, ValueError, r"mu must have shape \(H, d, S\)"),
    ({"mu": np.full((2, 2, 2), 0.4)}, ValueError, "mu.*sum to 1"),
    ({"theta": np.zeros((2, 3))}, ValueError, "phi has d = 2 features but theta"),
    ({"initial": [0.5, 0.6]}, ValueError, "initial must be a probability distribution"),
    ({"initial": [1.0, 0, 0]}, ValueError, "initial must be a distribution over the S = 2"),
    ({"initial": 5}, ValueError, "initial state must lie in"),
    ({"fail_states": [1]}, ValueError, "fail state 1 must be absorbing"),
    ({"fail_states": [7]}, ValueError, "fail_states must be state indices"),
    ({"fail_states": [0.5]}, TypeError, "fail_states must be a sequence of integer"),
    ({"reward_noise": -1.0}, ValueError, "reward_noise must be >= 0"),
    ({"behavior_policy": np.zeros((2, 2, 2))}, ValueError, "behavior_policy.*sum to 1"),
])
def test_finite_mdp_rejects_bad_input(change, err, match):
    with pytest.raises(err, match=match):
        FiniteLinearMDP(**{**GOOD, **change})


@pytest.mark.parametrize("call,err,match", [
    (lambda: SimulatedLinearMDP(delta=0.1, xi_norm=0.2), ValueError, "xi_norm <= delta"),
    (lambda: SimulatedLinearMDP(delta="0.3"), TypeError, "delta must be a real"),
    (lambda: SimulatedLinearMDP().perturbed(1.5), ValueError, "q must be <= 1"),
    (lambda: HardInstance(2, 3, 1.0, 0.1, 0.5, [1, 0]), ValueError, "xi must contain only"),
    (lambda: HardInstance(2, 3, 1.0, 1.0, 0.5, [1, 1]), ValueError, "epsilon must lie in"),
    (lambda: HardInstance(2, 3, 0.0, 0.1, 0.5, [1, 1]), ValueError, "lam must be > 0"),
    (lambda: HardInstance(2, 3, 1.0, 0.1, 0.5, [1, 1, 1]), ValueError, "xi must have shape"),
    (lambda: HardInstance(2, 3, 1.0, 0.1, 0.5, [1, 1], divergence=3), TypeError, "divergence"),
    (lambda: AmericanPutOption(p0=1.2), ValueError, "p0 must be <= 1"),
    (lambda: AmericanPutOption(d=0), ValueError, "d must be >= 1"),
    (lambda: AmericanPutOption(s0_range=(105, 95)), ValueError, "s0_range must be"),
    (lambda: AmericanPutOption(up=0.9), ValueError, "down must be smaller than up"),
    (lambda: SimulatedLinearMDP().collect(0), ValueError, "n_trajectories must be >= 1"),
    (lambda: SimulatedLinearMDP().collect(2.5), TypeError, "n_trajectories must be a positive"),
    (lambda: SimulatedLinearMDP().collect(5, seed="x"), TypeError, "seed must be"),
    (lambda: SimulatedLinearMDP().collect(5, policy="greedy"), ValueError, "'uniform'"),
    (lambda: SimulatedLinearMDP().collect(5, policy=np.zeros((3, 4), int)), ValueError,
     r"shape \(H, S\) = \(3, 5\)"),
    (lambda: SimulatedLinearMDP().collect(5, policy=np.full((3, 5), 16)), ValueError,
     r"action indices must lie in \[0, 16\)"),
    (lambda: SimulatedLinearMDP().collect(5, policy=np.full((3, 5), True)), TypeError, "dtype"),
    (lambda: SimulatedLinearMDP().collect(5, policy=np.full((3, 5, 16), 0.1)), ValueError,
     "sum to 1 over actions"),
    (lambda: SimulatedLinearMDP().collect(5, policy=lambda h, s: 0), ValueError,
     "one action per state"),
    (lambda: SimulatedLinearMDP().collect(5, policy=R2PVI()), ValueError, "unfitted"),
    (lambda: AmericanPutOption().collect(5, policy=lambda h, p: p), ValueError,
     r"0 \(hold\) or 1 \(exercise\)"),
    (lambda: AmericanPutOption().collect(5, policy=3), TypeError, "put-option policy"),
    (lambda: AmericanPutOption().make_dataset(np.ones((2, 3)), np.zeros((2, 3), int),
                                              np.zeros((2, 3)), np.ones((2, 3))),
     ValueError, "H = 20"),
])
def test_bad_input_is_named_with_a_fix(call, err, match):
    with pytest.raises(err, match=match):
        call()


def test_estimator_with_another_shape_is_refused():
    est = R2PVI(beta=0.1).fit(SimulatedLinearMDP().collect(50, seed=0))
    env = HardInstance(3, 3, 1.0, 0.1, 0.5, [1, 1, 1])  # d + 2 = 5 features, not 4
    with pytest.raises(ValueError, match="fit it on a dataset of this environment"):
        policy_table(env, est)
    with pytest.raises(ValueError, match="H = 20 and d = 30"):
        AmericanPutOption().collect(5, policy=est)
