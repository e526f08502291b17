"""Perturbed classic-control environments step like freshly built ones (independent physics)."""

import math

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

from r2pvi.envs.perturbations import (  # noqa: E402
    DiscreteTorque,
    PerturbedEnv,
    make_perturbed,
    nominal_params,
)
from r2pvi.evaluation import episode_returns  # noqa: E402


def cartpole_step(state, action, *, gravity=9.8, masscart=1.0, masspole=0.1, length=0.5,
                  force_mag=10.0, tau=0.02):
    """Barto, Sutton & Anderson's cart-pole (Florian 2005), Euler steps, written out here."""
    x, x_dot, th, th_dot = state
    force = force_mag if action == 1 else -force_mag
    total = masscart + masspole
    temp = (force + masspole * length * th_dot**2 * math.sin(th)) / total
    th_acc = (gravity * math.sin(th) - math.cos(th) * temp) / (
        length * (4.0 / 3.0 - masspole * math.cos(th) ** 2 / total))
    x_acc = temp - masspole * length * th_acc * math.cos(th) / total
    return np.array([x + tau * x_dot, x_dot + tau * x_acc, th + tau * th_dot,
                     th_dot + tau * th_acc])


@pytest.mark.parametrize("params", [
    {"gravity": 9.8 * 3.0, "length": 0.5 * 2.5},
    {"force_mag": 10.0 * 0.2, "masspole": 0.35},
    {"masscart": 2.0, "length": 0.2, "gravity": 0.0},
])
def test_perturbed_cartpole_steps_like_the_equations_with_those_parameters(params):
    for how in ("constructor", "reset_options", "set_params"):
        if how == "constructor":
            env = make_perturbed("CartPole-v1", **params)
            obs, _ = env.reset(seed=5)
        elif how == "reset_options":
            env = make_perturbed("CartPole-v1")
            obs, _ = env.reset(seed=5, options=dict(params))
        else:
            env = PerturbedEnv(gym.make("CartPole-v1"))
            env.set_params(**params)
            obs, _ = env.reset(seed=5)
        u = env.unwrapped
        assert u.total_mass == pytest.approx(u.masspole + u.masscart)
        assert u.polemass_length == pytest.approx(u.masspole * u.length)
        state = np.array(u.state, dtype=float)
        rng = np.random.default_rng(0)
        for _ in range(15):
            a = int(rng.integers(2))
            expected = cartpole_step(state, a, **params)
            obs, _, term, _, _ = env.step(a)
            np.testing.assert_allclose(u.state, expected, rtol=1e-12, atol=1e-12)
            state = np.array(u.state, dtype=float)
            if term:
                break


def test_parameters_persist_across_resets_and_spec_rebuilds_the_env():
    env = make_perturbed("CartPole-v1", gravity=20.0, action_noise=0.25)
    env.reset(seed=0)
    env.reset(seed=1)
    assert env.get_params()["gravity"] == 20.0 and env.get_params()["action_noise"] == 0.25
    rebuilt = gym.make(env.spec)
    assert rebuilt.get_wrapper_attr("get_params")()["gravity"] == 20.0
    nominal = nominal_params(gym.make("CartPole-v1"))
    assert nominal["force_mag"] == 10.0 and nominal["length"] == 0.5


def test_action_noise_replaces_actions_with_probability_p():
    def ones(h, obs):
        return np.ones(len(obs), dtype=np.int64)
    # p = 0: the wrapper is the identity.
    clean = episode_returns(gym.make("CartPole-v1"), ones, 5, seed=0)
    np.testing.assert_array_equal(
        episode_returns(make_perturbed("CartPole-v1", action_noise=0.0), ones, 5, seed=0), clean)
    # p = 1: every action is random; reproducible for a seed and independent of n_envs.
    noisy = make_perturbed("CartPole-v1", action_noise=1.0)
    a = episode_returns(noisy, ones, 6, seed=0)
    b = episode_returns(make_perturbed("CartPole-v1", action_noise=1.0), ones, 6, seed=0,
                        n_envs=3)
    np.testing.assert_array_equal(a, b)
    assert a.mean() > clean.mean()  # always pushing right falls fast; random actions do not
    # The executed actions: a fraction p of them is uniform, so p (A-1)/A differ.
    env = PerturbedEnv(Recorder(), action_noise=0.6)
    env.reset(seed=0)
    for _ in range(4000):
        env.step(3)
    executed = np.array(env.unwrapped.executed)
    assert abs((executed != 3).mean() - 0.6 * 3 / 4) < 0.03
    assert set(executed.tolist()) == {0, 1, 2, 3}


class Recorder(gym.Env):
    """Records the actions it executes."""

    observation_space = gym.spaces.Discrete(1)
    action_space = gym.spaces.Discrete(4)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.executed = []
        return 0, {}

    def step(self, action):
        self.executed.append(int(action))
        return 0, 0.0, False, False, {}


def test_mountain_car_force_and_gravity():
    env = make_perturbed("MountainCar-v0", force=0.002, gravity=0.001)
    env.reset(seed=0)
    pos, vel = env.unwrapped.state
    env.step(2)
    expected_v = vel + (2 - 1) * 0.002 + math.cos(3 * pos) * (-0.001)
    assert env.unwrapped.state[1] == pytest.approx(expected_v, abs=1e-12)


def test_discretized_pendulum_follows_max_torque():
    env = PerturbedEnv(DiscreteTorque(gym.make("Pendulum-v1"), n_levels=3), max_torque=1.0,
                       m=1.5)
    env.reset(seed=0)
    th, thdot = env.unwrapped.state
    env.step(2)  # +max_torque = 1.0
    g, m, length, dt = 10.0, 1.5, 1.0, 0.05
    acc = 3 * g / (2 * length) * np.sin(th) + 3.0 / (m * length**2) * 1.0
    newthdot = np.clip(thdot + acc * dt, -8, 8)
    assert env.unwrapped.state[1] == pytest.approx(newthdot, abs=1e-6)
    assert env.unwrapped.action_space.high[0] == 1.0


def test_acrobot_parameters():
    env = make_perturbed("Acrobot-v1", link_mass_2=2.0, link_length_1=1.5)
    assert env.unwrapped.LINK_MASS_2 == 2.0 and type(env.unwrapped).LINK_MASS_2 == 1.0


def test_perturbation_errors():
    with pytest.raises(ValueError, match="unknown parameter"):
        make_perturbed("CartPole-v1", mass=2.0)
    with pytest.raises(ValueError, match="> 0"):
        make_perturbed("CartPole-v1", length=0.0)
    with pytest.raises(ValueError, match="action_noise"):
        make_perturbed("CartPole-v1", action_noise=1.5)
    with pytest.raises(TypeError, match="no known physical parameters"):
        make_perturbed("FrozenLake-v1", gravity=3.0)
    env = make_perturbed("FrozenLake-v1", action_noise=0.5)  # noise alone works anywhere
    env.reset(seed=0)
    with pytest.raises(ValueError, match="PerturbedEnv"):  # never silently nominal
        episode_returns(gym.make("CartPole-v1"), "uniform", 2, reset_options={"gravity": 20.0})


def test_native_cartpole_vector_env_perturbed_like_the_single_env():
    from r2pvi.envs.perturbations import set_env_params

    params = {"gravity": 15.0, "masspole": 0.3, "length": 0.8, "force_mag": 4.0}
    venv = gym.make_vec("CartPole-v1", 3, vectorization_mode="vector_entry_point")
    set_env_params(venv, **params)
    venv.reset(seed=0)
    states = np.array(venv.unwrapped.state, dtype=float)  # (4, n)
    venv.step(np.array([0, 1, 1]))
    for i, a in enumerate([0, 1, 1]):
        expected = cartpole_step(states[:, i], a, **params)
        np.testing.assert_allclose(venv.unwrapped.state[:, i], expected, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="PerturbedEnv"):
        set_env_params(venv, action_noise=0.1)
