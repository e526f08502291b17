"""The classic-control experts and the MountainCar robustness benchmark (``r2pvi reproduce
mountaincar``); ``r2pvi reproduce cartpole`` is tested in test_reproduce_cartpole.py."""

from __future__ import annotations

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

from r2pvi.algorithms import PEVI  # noqa: E402
from r2pvi.envs.experts import CartPoleLQR, MountainCarEnergy, cartpole_linearization  # noqa: E402
from r2pvi.evaluation import evaluate_policy  # noqa: E402
from r2pvi.experiments.figures.classic_control import (  # noqa: E402
    MOUNTAINCAR,
    MOUNTAINCAR_DEFAULTS,
    _algorithms,
    replication,
)
from r2pvi.experiments.reproduce import figure_names  # noqa: E402


# --------------------------------------------------------------------------- experts
def test_linearization_matches_gymnasium_step():
    """(A, B) against finite differences of Gymnasium's own CartPole step (the truth)."""
    env = gym.make("CartPole-v1").unwrapped
    env.reset(seed=0)
    A, B = cartpole_linearization()

    def step(state, action):
        env.state = np.array(state, dtype=float)
        env.steps_beyond_terminated = None
        env.step(action)
        return np.array(env.state, dtype=float)   # float64 (the observation is float32)

    # f(0, +-F) = +-B exactly: the dynamics are linear in the force at the upright state.
    np.testing.assert_allclose(step(np.zeros(4), 1), B[:, 0], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(step(np.zeros(4), 0), -B[:, 0], rtol=1e-6, atol=1e-7)
    eps = 1e-5
    jac = np.column_stack([(step(eps * e, 1) - step(-eps * e, 1)) / (2 * eps)
                           for e in np.eye(4)])
    np.testing.assert_allclose(jac, A, rtol=1e-4, atol=1e-6)


def test_lqr_gain_stabilizes_the_linear_model_and_balances():
    expert = CartPoleLQR()
    A, B = cartpole_linearization()
    closed = A - B @ expert.gain_[None]
    assert np.max(np.abs(np.linalg.eigvals(closed))) < 1.0
    # The gain is the LQR optimum: perturbing it raises the infinite-horizon cost from s0.
    s0 = np.array([0.1, 0.0, 0.05, 0.0])

    def cost(K):
        s, total = s0.copy(), 0.0
        for _ in range(3000):
            u = -K @ s
            total += s @ np.diag([1.0, 1.0, 10.0, 1.0]) @ s + u * u
            s = A @ s + B[:, 0] * u
        return total

    best = cost(expert.gain_)
    rng = np.random.default_rng(0)
    for _ in range(5):
        assert cost(expert.gain_ + 0.05 * rng.normal(size=4)) > best
    # Bang-bang in the real (nonlinear) environment: 200 steps balanced, every episode.
    mean, se = evaluate_policy(gym.make("CartPole-v1"), expert, 5, seed=3, max_steps=200,
                               n_envs=5)
    assert (mean, se) == (200.0, 0.0)
    assert expert(0, np.array([0.0, 0.0, 0.05, 0.0])).tolist() == [1]   # lean right: push right
    assert expert(0, np.array([[0.0, 0.0, -0.05, 0.0]])).tolist() == [0]


def test_expert_input_validation():
    with pytest.raises(ValueError, match="state_cost"):
        CartPoleLQR(state_cost=(1.0, 1.0))
    with pytest.raises(ValueError, match="unknown CartPole parameter"):
        CartPoleLQR(mass=2.0)
    with pytest.raises(ValueError, match=r"shape \(n, 2\)"):
        MountainCarEnergy()(0, np.zeros((3, 4)))


def test_mountaincar_expert_reaches_the_flag():
    returns = []
    for seed in range(3):
        mean, _ = evaluate_policy(gym.make("MountainCar-v0"), MountainCarEnergy(), 2,
                                  seed=seed, max_steps=200, n_envs=2)
        returns.append(mean)
    assert all(-200 < r < -80 for r in returns)   # terminated before the 200-step limit


# --------------------------------------------------------------------------- benchmark
def test_benchmarks_run_by_name_only(tmp_path):
    from r2pvi.cli import build_parser, plan_reproduce

    assert "cartpole" not in figure_names() and "mountaincar" not in figure_names()
    assert {"cartpole", "mountaincar"} <= set(figure_names(benchmarks=True))
    planned = [name for name, _ in plan_reproduce(build_parser().parse_args(
        ["reproduce", "all", "--out", str(tmp_path), "--no-plot"]))]
    assert "fig1a" in planned and "cartpole" not in planned and "mountaincar" not in planned
    planned = plan_reproduce(build_parser().parse_args(["reproduce", "cartpole"]))
    assert [name for name, _ in planned] == ["cartpole"]


def test_replication_is_seeded_and_mountaincar_runs():
    s = {**MOUNTAINCAR_DEFAULTS, "horizon": 12, "trajectories": 4, "test_episodes": 2,
         "lams": [10.0], "rhos": [], "divergences": ["tv"], "centers": 2, "force": [0.0],
         "gravity": [0.5], "action_noise": [0.0], "references": False}
    seq = lambda: np.random.SeedSequence(7).spawn(1)[0]  # noqa: E731
    rows = replication(seq(), task="mountaincar", replication=0, settings=s)
    again = replication(seq(), task="mountaincar", replication=0, settings=s)
    strip = lambda rs: [{k: str(v) for k, v in r.items()  # noqa: E731 - NaN-safe, timing-free
                         if r["quantity"] != "fit time" or k != "value"} for r in rs]
    assert strip(rows) == strip(again)
    rets = [r["value"] for r in rows if r["quantity"] == "average return"]
    assert len(rets) == 2 * 3 and all(-12.0 <= v <= 0.0 for v in rets)   # -1 per step


def test_settings_and_time_homogeneous():
    s = {**MOUNTAINCAR_DEFAULTS}
    labels = [a[0] for a in _algorithms(s)]
    assert labels[0] == "PEVI" and len(labels) == 1 + 3 * 3 + 2
    with pytest.raises(ValueError, match="epsilon"):
        MOUNTAINCAR.tasks({**s, "epsilon": 1.5})
    with pytest.raises(ValueError, match="force"):
        MOUNTAINCAR.tasks({**s, "force": [-1.0]})
    tiny = {**s, "horizon": 8, "trajectories": 3, "test_episodes": 2, "lams": [], "rhos": [],
            "force": [0.0], "gravity": [], "action_noise": [], "references": False,
            "centers": 2, "time_homogeneous": True}
    assert "time_homogeneous" in PEVI._param_names()
    rows = replication(np.random.SeedSequence(1), task="mountaincar", replication=0,
                       settings=tiny)
    assert [r["quantity"] for r in rows] == ["fit time", "average return"]
