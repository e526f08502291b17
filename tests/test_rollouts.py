"""Rollouts in Gymnasium environments: seeding, vectorization, policies, evaluation."""

import io

import numpy as np
import pytest

import r2pvi

gym = pytest.importorskip("gymnasium")

from r2pvi import PEVI, R2PVI, OfflineDataset  # noqa: E402
from r2pvi.envs import EpsilonGreedy, collect_episodes  # noqa: E402
from r2pvi.envs.collect import _progress_bar, episode_seeds  # noqa: E402
from r2pvi.evaluation import episode_returns, evaluate_policy  # noqa: E402
from r2pvi.features import NormalizedRBF, cross_actions  # noqa: E402


def lean(h, obs):
    return (obs[:, 2] + 0.5 * obs[:, 3] > 0).astype(np.int64)


def _same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.observations, y.observations)
        np.testing.assert_array_equal(x.actions, y.actions)
        np.testing.assert_array_equal(x.rewards, y.rewards)
        np.testing.assert_array_equal(x.terminations, y.terminations)
        np.testing.assert_array_equal(x.truncations, y.truncations)
        assert x.seed == y.seed


def test_vector_rollouts_equal_single_env_rollouts_for_the_same_seeds():
    policy = EpsilonGreedy(lean, 0.3, 2)
    single = collect_episodes(gym.make("CartPole-v1"), policy, 7, seed=3, max_steps=60)
    # The same episodes by hand: reset with each episode's seed, act with its generator.
    env_seeds, rngs = episode_seeds(3, 7)
    env = gym.make("CartPole-v1")
    for i, e in enumerate(single):
        obs, _ = env.reset(seed=int(env_seeds[i]))
        np.testing.assert_array_equal(obs, e.observations[0])
        for t in range(len(e)):
            a = policy.sample(np.array([t]), obs[None], [rngs[i]])[0]
            assert a == e.actions[t]
            obs, r, term, trunc, _ = env.step(a)
            np.testing.assert_array_equal(obs, e.observations[t + 1])
            assert term == e.terminations[t]
    for kwargs in ({"n_envs": 3}, {"n_envs": 7}):
        _same(single, collect_episodes(gym.make("CartPole-v1"), policy, 7, seed=3,
                                       max_steps=60, **kwargs))
    _same(single, collect_episodes("CartPole-v1", policy, 7, seed=3, max_steps=60, n_envs=2))
    for mode in ("NextStep", "SameStep", "Disabled"):  # a vector env of any autoreset mode
        venv = gym.vector.SyncVectorEnv([lambda: gym.make("CartPole-v1")] * 4,
                                        autoreset_mode=mode)
        _same(single, collect_episodes(venv, policy, 7, seed=3, max_steps=60))
    returns = episode_returns(gym.make("CartPole-v1"), policy, 7, seed=3, max_steps=60,
                              n_envs=4)
    np.testing.assert_array_equal(returns, [e.total_reward for e in single])


def test_episode_fields_follow_minari_conventions():
    eps = collect_episodes(gym.make("CartPole-v1"), "uniform", 5, seed=0, max_steps=12)
    for e in eps:
        assert e.observations.shape == (len(e) + 1, 4)
        assert e.terminations[-1] != e.truncations[-1]
        assert not e.terminations[:-1].any() and not e.truncations[:-1].any()
        if len(e) == 12 and not e.terminations[-1]:
            assert e.truncations[-1]  # cut by max_steps
    assert [e.id for e in eps] == list(range(5))


def test_native_vector_env_runs_in_reproducible_batches():
    def run():
        venv = gym.make_vec("CartPole-v1", 3, vectorization_mode="vector_entry_point")
        return collect_episodes(venv, lean, 5, seed=1, max_steps=40)
    a, b = run(), run()
    _same(a, b)
    assert len(a) == 5


def test_learned_policy_acts_batched_and_beyond_its_horizon():
    eps = collect_episodes(gym.make("CartPole-v1"), EpsilonGreedy(lean, 0.3, 2), 30, seed=0,
                           max_steps=20)
    obs = np.concatenate([e.observations for e in eps])
    fmap = cross_actions(NormalizedRBF(n_centers=2).fit(obs), n_actions=2)
    ds = OfflineDataset.from_episodes(eps, fmap, 2, horizon=20)
    est = R2PVI("tv", 0.5, beta=0.05).fit(ds)
    policy = est.as_policy(fmap)
    h = np.array([0, 5, 19, 25])
    batch = obs[:4]
    acts = policy(h, batch)
    phi_all = fmap.all_actions(batch)
    for i in range(3):
        assert acts[i] == est.act(phi_all[i:i + 1], int(h[i]))[0]
    assert acts[3] == est.act(phi_all[3:4], 0)[0]  # receding horizon: Q_0
    assert est.as_policy(fmap, beyond_horizon="last")(h, batch)[3] == est.act(phi_all[3:4], 19)[0]
    with pytest.raises(ValueError, match="beyond the fitted horizon"):
        est.as_policy(fmap, beyond_horizon="error")(h, batch)
    # A fitted observation transformer is crossed with the actions for the policy too.
    np.testing.assert_array_equal(est.as_policy(fmap.state_map)(h, batch), acts)
    mean, se = evaluate_policy(gym.make("CartPole-v1"), policy, 6, seed=0, max_steps=50,
                               n_envs=3)
    assert 0 < mean <= 50 and se >= 0
    with pytest.raises(r2pvi.NotFittedError, match="not fitted"):
        PEVI().as_policy(fmap)


def test_rollout_argument_errors():
    env = gym.make("CartPole-v1")
    with pytest.raises(ValueError, match="n_episodes"):
        evaluate_policy(env, lean, 0)
    with pytest.raises(TypeError, match="policy"):
        evaluate_policy(env, 3, 2)
    with pytest.raises(ValueError, match="one action per observation"):
        evaluate_policy(env, lambda h, o: np.zeros(len(o) + 1, int), 2, seed=0)
    with pytest.raises(TypeError, match="env"):
        evaluate_policy(42, lean, 2)
    with pytest.raises(ValueError, match="epsilon"):
        EpsilonGreedy(lean, 1.5, 2)
    with pytest.raises(TypeError, match="seed"):
        evaluate_policy(env, lean, 2, seed="x")


def test_progress_bar_only_on_a_terminal(monkeypatch):
    pytest.importorskip("tqdm")
    monkeypatch.setattr("sys.stderr", io.StringIO())
    assert _progress_bar(None, 1000) is None
    bar = _progress_bar(True, 10)
    assert bar is not None
    bar.close()
    assert _progress_bar(False, 1000) is None


def test_greedy_action_accepts_a_vector_envs_info():
    import r2pvi.envs.gym  # noqa: F401  (registers the ids)
    from r2pvi.envs import SimulatedLinearMDP
    from r2pvi.envs.gym import greedy_action

    model = SimulatedLinearMDP()
    est = R2PVI("tv", 0.3, beta=0.1).fit(model.collect(50, seed=0))
    venv = gym.make_vec("r2pvi/SimulatedLinearMDP-v0", 3, vectorization_mode="sync")
    obs, info = venv.reset(seed=0)
    for _ in range(model.horizon):
        actions = greedy_action(est, info)
        assert actions.shape == (3,)
        for i in range(3):
            one = {k: info[k][i] for k in ("phi", "known", "known_values", "step")}
            assert greedy_action(est, one) == actions[i]
        obs, _, _, _, info = venv.step(actions)


def test_environments_never_import_the_adapters():
    import ast
    from pathlib import Path

    import r2pvi

    root = Path(r2pvi.__file__).parent / "envs"
    adapters = {"gym", "minari", "collect", "perturbations"}
    for path in root.glob("*.py"):
        if path.stem in adapters | {"__init__"}:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                assert (node.module or "").split(".")[0] not in {"gym", "minari"}, path.name
