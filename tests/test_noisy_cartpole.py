"""The noisy CartPole protocol of RFQI: Gymnasium's step at sigma = 0, the published noise,
initial states, failure, rewards and horizon, common random numbers and the test grid."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi.envs import EpsilonGreedy, evaluate_cartpole_grid
from r2pvi.envs.cartpole_grid import PROTOCOL_GRID, perturbation_grid
from r2pvi.envs.experts import CartPoleLQR
from r2pvi.envs.noisy_cartpole import (
    INITIAL_HIGH,
    NOMINAL,
    THETA_THRESHOLD,
    NoisyCartPoleBatch,
    cartpole_step,
    failed,
)

LQR = CartPoleLQR()


def published_step(state, action, eps, *, sigma, gravity=9.8, masscart=1.0, masspole=0.1,
                   length=0.5, force_mag=10.0, tau=0.02):
    """The RFQI / RFZI environment's step, written out with scalars (noise eps = 2 normals)."""
    x, x_dot, th, th_dot = state
    force = force_mag if action == 1 else -force_mag
    total = masscart + masspole
    temp = (force + masspole * length * th_dot**2 * math.sin(th)) / total
    th_acc = (gravity * math.sin(th) - math.cos(th) * temp) / (
        length * (4.0 / 3.0 - masspole * math.cos(th) ** 2 / total) + sigma * eps[0])
    x_acc = temp - masspole * length * th_acc * math.cos(th) / total + sigma * eps[1]
    return np.array([x + tau * x_dot, x_dot + tau * x_acc, th + tau * th_dot,
                     th_dot + tau * th_acc])


# ---------------------------------------------------------------------- dynamics
states = st.lists(st.tuples(st.floats(-2.4, 2.4), st.floats(-3, 3), st.floats(-0.21, 0.21),
                            st.floats(-3, 3), st.integers(0, 1)), min_size=1, max_size=12)
grid_params = st.fixed_dictionaries({
    "gravity": st.sampled_from([9.8, -19.6, 0.0, 34.3]) | st.floats(-20, 35),
    "length": st.sampled_from([0.5, 0.1, 2.3]) | st.floats(0.1, 2.3),
    "force_mag": st.sampled_from([10.0, 2.0, 46.0]) | st.floats(2, 46),
    "masspole": st.sampled_from([0.1]) | st.floats(0.05, 1.0),
    "masscart": st.sampled_from([1.0]) | st.floats(0.5, 2.0),
})


@settings(max_examples=60)
@given(rows=states, params=grid_params)
def test_one_step_at_sigma_zero_is_gymnasiums_cartpole_step(rows, params):
    gym = pytest.importorskip("gymnasium")
    import r2pvi.envs.gym  # noqa: F401  (registers r2pvi/NoisyCartPole-v0)
    from r2pvi.envs.perturbations import make_perturbed

    s = np.array([r[:4] for r in rows])
    a = np.array([r[4] for r in rows])
    reference = make_perturbed("CartPole-v1", **params)
    expected, fell = [], []
    for state, action in zip(s, a, strict=True):
        reference.reset(seed=0)
        reference.unwrapped.state = state.copy()
        _, reward, terminated, _, _ = reference.step(int(action))
        expected.append(reference.unwrapped.state)
        fell.append(terminated)
    expected = np.array(expected)
    tol = 1e-12 * np.maximum(1.0, np.abs(expected))
    noise = np.random.default_rng(0).standard_normal((len(s), 2))   # drawn, but sigma = 0
    assert (np.abs(cartpole_step(s, a, sigma=0.0, noise=noise, **params) - expected)
            <= tol).all()
    assert (failed(cartpole_step(s, a, **params)) == np.array(fell)).all()

    batch = NoisyCartPoleBatch(len(s), sigma=0.0, **params)          # the batch steps alike
    batch.start(s, np.zeros((len(s), batch.max_steps, 2)))
    batch.step(a)
    assert (np.abs(batch.state - expected) <= tol).all()

    env = gym.make("r2pvi/NoisyCartPole-v0", sigma=0.0, **params)     # and the single env
    env.reset(seed=1)
    env.unwrapped.state = s[0].copy()
    env.step(int(a[0]))
    assert (np.abs(env.unwrapped.state - expected[0]) <= tol[0]).all()


@settings(max_examples=30)
@given(rows=states, sigma=st.sampled_from([0.1, 0.3]), seed=st.integers(0, 2**32 - 1))
def test_noise_enters_the_angular_denominator_and_the_cart_acceleration(rows, sigma, seed):
    s = np.array([r[:4] for r in rows])
    a = np.array([r[4] for r in rows])
    eps = np.random.default_rng(seed).standard_normal((len(s), 2))
    ours = cartpole_step(s, a, sigma=sigma, noise=eps, length=0.7)
    for i in range(len(s)):
        want = published_step(s[i], a[i], eps[i], sigma=sigma, length=0.7)
        if np.isfinite(want).all():
            assert np.allclose(ours[i], want, rtol=1e-10, atol=1e-12)


# ---------------------------------------------------------------------- episodes
def test_initial_states_fill_the_published_ranges():
    batch = NoisyCartPoleBatch(4000)
    obs = batch.reset(seed=3)
    high = np.abs(batch.state).max(axis=0)
    assert (high <= INITIAL_HIGH).all() and (high > 0.98 * INITIAL_HIGH).all()
    assert high[2] > 0.19 and high[[0, 1, 3]].max() <= 0.05          # theta ~ U(-0.2, 0.2)
    assert (np.abs(batch.state.mean(axis=0)) < 0.05 * INITIAL_HIGH).all()
    assert obs.dtype == np.float32 and np.array_equal(obs, batch.state.astype(np.float32))


def test_failure_thresholds_are_2_4_and_12_degrees_inclusive_inside():
    inside = np.array([[2.4, 0, THETA_THRESHOLD, 0], [-2.4, 0, -THETA_THRESHOLD, 0]])
    assert not failed(inside).any()
    for i, j in [(0, 0), (0, 2), (1, 0), (1, 2)]:
        out = inside.copy()
        out[i, j] = np.nextafter(out[i, j], np.sign(out[i, j]) * np.inf)
        assert failed(out)[i] and not failed(out)[1 - i]
    assert math.isclose(THETA_THRESHOLD, math.radians(12), rel_tol=1e-15)
    assert failed(np.array([[np.nan, 0, 0, 0], [0, 0, np.inf, 0]])).all()


def test_reward_is_one_per_step_including_the_failing_step_then_zero():
    # Row 0 starts at the right edge moving out: it fails on its first step. Row 1 balances.
    batch = NoisyCartPoleBatch(2, sigma=0.0)
    batch.start(np.array([[2.399, 1.0, 0.0, 0.0], [0.0, 0.0, 0.01, 0.0]]),
                np.zeros((2, batch.max_steps, 2)))
    obs, reward, terminated, truncated = batch.step(np.array([1, 1]))
    assert reward.tolist() == [1.0, 1.0] and terminated.tolist() == [True, False]
    assert not truncated.any() and obs[0, 0] > 2.4
    _, reward, terminated, _ = batch.step(np.array([1, 0]))
    assert reward.tolist() == [0.0, 1.0] and not terminated[0]          # finished: 0, frozen
    assert batch.state[0, 0] == pytest.approx(2.399 + 0.02)


def test_episodes_last_at_most_200_steps_and_then_refuse_to_step():
    batch = NoisyCartPoleBatch(5, sigma=0.0)
    obs = batch.reset(seed=0)
    total, flags = np.zeros(5), []
    for t in range(200):
        obs, reward, terminated, truncated = batch.step(LQR(t, obs))
        total += reward
        flags.append(truncated.copy())
    assert total.tolist() == [200.0] * 5 and batch.done.all()
    assert flags[-1].all() and not np.array(flags[:-1]).any()
    with pytest.raises(RuntimeError, match="reset"):
        batch.step(np.ones(5, dtype=int))
    assert NoisyCartPoleBatch(2, max_steps=7).reset(seed=0).shape == (2, 4)


def test_single_env_rewards_failure_and_cap():
    gym = pytest.importorskip("gymnasium")
    import r2pvi.envs.gym  # noqa: F401  (registers r2pvi/NoisyCartPole-v0)

    env = gym.make("r2pvi/NoisyCartPole-v0", sigma=0.0)
    obs, _ = env.reset(seed=4)
    steps = 0
    while True:
        obs, reward, terminated, truncated, _ = env.step(int(LQR(0, obs)[0]))
        steps += 1
        assert reward == 1.0
        if terminated or truncated:
            break
    assert steps == 200 and truncated and not terminated
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)
    env.reset(seed=4)
    steps = 0
    while True:                       # always push left: falls, reward 1 on the failing step
        _, reward, terminated, truncated, _ = env.step(0)
        steps += 1
        assert reward == 1.0
        if terminated or truncated:
            break
    assert terminated and not truncated and steps < 200
    env.reset(seed=0)
    with pytest.raises(ValueError, match="0 \\(push left\\) or 1"):
        env.step(2)


def test_single_env_passes_gymnasium_checks_and_takes_parameters_like_perturbed_env():
    gym = pytest.importorskip("gymnasium")
    from gymnasium.utils.env_checker import check_env

    import r2pvi.envs.gym  # noqa: F401  (registers r2pvi/NoisyCartPole-v0)
    from r2pvi.envs import collect_episodes
    from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv
    from r2pvi.envs.perturbations import PerturbedEnv

    env = NoisyCartPoleEnv(length=1.0)
    check_env(env, skip_render_check=True)
    assert env.get_params() == {**NOMINAL, "length": 1.0, "sigma": 0.1}
    env.reset(seed=0, options={"gravity": 19.6, "sigma": 0.0})
    assert env.get_params()["gravity"] == 19.6 and env.get_params()["sigma"] == 0.0
    env.set_params(masspole=0.2)
    assert env.unwrapped.polemass_length == pytest.approx(0.2 * 1.0)
    wrapped = PerturbedEnv(NoisyCartPoleEnv(), action_noise=0.1, force_mag=20.0)
    assert wrapped.get_params()["force_mag"] == 20.0
    eps = collect_episodes(NoisyCartPoleEnv(), LQR, 3, seed=0, reset_options={"length": 1.5})
    assert [len(e) for e in eps] and all(len(e) <= 200 for e in eps)
    assert gym.make("r2pvi/NoisyCartPole-v0").unwrapped.max_steps == 200


# ---------------------------------------------------------------------- random numbers
def implied_noise(before, after, action, sigma, **params):
    """The two standard normals that took ``before`` to ``after`` (inverting the step)."""
    p = {**NOMINAL, **params}
    x, x_dot, th, th_dot = before
    force = p["force_mag"] if action == 1 else -p["force_mag"]
    total = p["masscart"] + p["masspole"]
    temp = (force + p["masspole"] * p["length"] * th_dot**2 * math.sin(th)) / total
    th_acc = (after[3] - th_dot) / p["tau"]
    den = (p["gravity"] * math.sin(th) - math.cos(th) * temp) / th_acc
    den0 = p["length"] * (4 / 3 - p["masspole"] * math.cos(th) ** 2 / total)
    x_acc0 = temp - p["masspole"] * p["length"] * th_acc * math.cos(th) / total
    return np.array([(den - den0) / sigma, ((after[1] - x_dot) / p["tau"] - x_acc0) / sigma])


def test_grid_points_see_the_same_initial_states_and_noise_draws():
    names, _, values = perturbation_grid()
    k_force, k_length = 0, len(values) - 1                # force x 0.2 and length x 4.6
    E = 4
    length = np.full(2 * E, 0.5)
    force = np.full(2 * E, 10.0)
    force[:E] = values[k_force]
    length[E:] = values[k_length]
    batch = NoisyCartPoleBatch(2 * E, force_mag=force, length=length)
    episodes = np.r_[np.arange(E), np.arange(E)[::-1]]     # the second point in reverse
    obs0 = batch.reset(seed=11, episodes=episodes)
    assert np.array_equal(obs0[:E], obs0[E:][::-1]) and len(np.unique(obs0[:E, 2])) == E
    before = batch.state.copy()
    batch.step(np.ones(2 * E, dtype=int))
    for e in range(E):
        r = 2 * E - 1 - e                                  # the row running episode e
        n1 = implied_noise(before[e], batch.state[e], 1, 0.1, force_mag=force[e])
        n2 = implied_noise(before[r], batch.state[r], 1, 0.1, length=length[r])
        assert np.allclose(n1, n2, atol=1e-6)
        if e:
            assert not np.allclose(n1, implied_noise(before[0], batch.state[0], 1, 0.1,
                                                     force_mag=force[0]), atol=1e-3)


def test_grid_returns_are_evaluate_policy_returns_of_the_single_env_at_each_point():
    pytest.importorskip("gymnasium")
    from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv
    from r2pvi.evaluation import episode_returns

    behaviour = EpsilonGreedy(LQR, 0.3, 2)                       # stochastic: its rngs too
    result = evaluate_cartpole_grid(behaviour, n_episodes=6, seed=5)
    for k in (0, 7, 14, 30):
        env = NoisyCartPoleEnv(**{str(result.parameter[k]): result.value[k]})
        assert np.array_equal(episode_returns(env, behaviour, 6, seed=5), result.returns[k])
    nominal = result.p == 0.0                                    # three nominal points
    assert nominal.sum() == 3 and (result.returns[nominal] == result.returns[nominal][0]).all()


def test_seeds_reproduce_the_evaluation_and_other_seeds_change_it():
    first = evaluate_cartpole_grid(EpsilonGreedy(LQR, 0.3, 2), n_episodes=5, seed=1)
    again = evaluate_cartpole_grid(EpsilonGreedy(LQR, 0.3, 2), n_episodes=5, seed=1)
    other = evaluate_cartpole_grid(EpsilonGreedy(LQR, 0.3, 2), n_episodes=5, seed=2)
    assert np.array_equal(first.returns, again.returns)
    assert not np.array_equal(first.returns, other.returns)
    b1, b2 = NoisyCartPoleBatch(3), NoisyCartPoleBatch(3)
    assert np.array_equal(b1.reset(seed=9), b2.reset(seed=9))
    for t in range(30):
        b1.step(LQR(t, b1.state))
        b2.step(LQR(t, b2.state))
    assert np.array_equal(b1.state, b2.state) and not b1.done.all()
    assert not np.array_equal(b1.reset(seed=9), NoisyCartPoleBatch(3).reset(seed=10))


# ---------------------------------------------------------------------- the grid
def test_the_grid_has_the_36_published_points():
    names, p, values = perturbation_grid()
    assert len(p) == 36 and list(PROTOCOL_GRID) == ["force_mag", "gravity", "length"]
    steps = [-0.8 + 0.4 * i for i in range(12)]
    for name, want_p in [("force_mag", steps), ("length", steps),
                         ("gravity", [-3.0 + 0.5 * i for i in range(12)])]:
        rows = names == name
        assert np.allclose(p[rows], want_p, atol=1e-12) and rows.sum() == 12
        assert np.allclose(values[rows], NOMINAL[name] * (1 + np.array(want_p)), atol=1e-12)
    assert 0.0 in p[names == "gravity"].tolist() and 3.6 == pytest.approx(p[-1])
    result = evaluate_cartpole_grid(LQR, n_episodes=3)
    assert result.returns.shape == (36, 3) and len(result.rows()) == 36
    row = result.rows()[2]
    assert set(row) == {"parameter", "p", "value", "mean", "std", "se"}
    assert row["mean"] == 200.0 and row["std"] == 0.0                   # the expert, nominal
    sweep_p, mean, std = result.sweep("length")
    assert sweep_p.shape == mean.shape == std.shape == (12,)


# ---------------------------------------------------------------------- errors
@pytest.mark.parametrize("kwargs,name", [
    ({"length": 0.0}, "length"), ({"masspole": -1.0}, "masspole"), ({"tau": 0.0}, "tau"),
    ({"gravity": float("nan")}, "gravity"), ({"sigma": -0.1}, "sigma"),
    ({"force_mag": np.inf}, "force_mag"), ({"mass": 1.0}, "mass"),
    ({"length": np.ones(3)}, "length"),
])
def test_bad_parameters_are_refused_by_name(kwargs, name):
    with pytest.raises(ValueError, match=name):
        NoisyCartPoleBatch(2, **kwargs)
    with pytest.raises(ValueError, match=name):
        evaluate_cartpole_grid(LQR, n_episodes=1, **kwargs)


def test_bad_grids_episodes_and_actions_are_refused_by_name():
    with pytest.raises(ValueError, match="length"):
        evaluate_cartpole_grid(LQR, grid={"length": [-1.0]})          # a pole of length 0
    with pytest.raises(ValueError, match="unknown CartPole parameter 'mass'"):
        perturbation_grid({"mass": [0.0]})
    with pytest.raises(ValueError, match="n_episodes"):
        evaluate_cartpole_grid(LQR, n_episodes=0)
    with pytest.raises(ValueError, match="the policy's actions must be 0"):
        evaluate_cartpole_grid(lambda h, obs: np.full(len(obs), 0.5), n_episodes=1)
    with pytest.raises(ValueError, match="episodes"):
        NoisyCartPoleBatch(2).reset(seed=0, episodes=[0, -1])
    batch = NoisyCartPoleBatch(2)
    batch.reset(seed=0)
    with pytest.raises(ValueError, match="shape \\(2,\\)"):
        batch.step(np.ones(3, int))


def test_single_env_refuses_bad_parameters_by_name():
    pytest.importorskip("gymnasium")
    from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv

    with pytest.raises(ValueError, match="length"):
        NoisyCartPoleEnv(length=-1.0)
    env = NoisyCartPoleEnv()
    with pytest.raises(ValueError, match="sigma"):
        env.set_params(sigma=-1.0)
    with pytest.raises(ValueError, match="unknown CartPole parameter.*'low'"):
        env.reset(options={"low": -0.1})
    with pytest.raises(ValueError, match="PerturbedEnv"):
        env.reset(options={"action_noise": 0.2})
