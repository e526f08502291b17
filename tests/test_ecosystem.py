"""Gymnasium adapters, Minari export/import, lazy optional imports and the user guide.

The extras ``gym`` and ``minari`` are optional: on a machine without them these tests skip,
but where ``CI`` or ``R2PVI_REQUIRE_EXTRAS`` is set a missing extra is an error, so CI can
never pass by skipping them.
"""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from extras import require

from r2pvi import R2PVI
from r2pvi.envs import AmericanPutOption, FiniteLinearMDP, HardInstance, SimulatedLinearMDP
from r2pvi.envs.gym import as_gymnasium_env
from r2pvi.evaluation import expected_return

DOCS = Path(__file__).resolve().parents[1] / "docs" / "environments.md"



@pytest.fixture
def gym():
    gymnasium = require("gymnasium")
    import r2pvi.envs.gym  # noqa: F401  (registers the ids)

    return gymnasium


@pytest.fixture
def minari(tmp_path, monkeypatch):
    require("gymnasium")
    module = require("minari")
    require("h5py")
    require("PIL")  # minari's storages import pillow
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    return module


def small_finite():
    phi = np.array([[[1.0, 0.0], [0.2, 0.8]], [[0.0, 1.0], [0.0, 1.0]]])
    mu = np.tile(np.eye(2), (3, 1, 1))
    return FiniteLinearMDP(phi, [[0.0, 1.0]] * 3, mu, [0.7, 0.3])


# ---------------------------------------------------------------------- Gymnasium
@pytest.mark.parametrize("env_id,kwargs", [
    ("r2pvi/SimulatedLinearMDP-v0", {}),
    ("r2pvi/SimulatedLinearMDP-v0", {"q": 0.6}),
    ("r2pvi/HardInstance-v0", {"d": 2, "H": 3, "lam": 1.0, "epsilon": 0.1, "delta": 0.5,
                               "xi": [1, -1]}),
    ("r2pvi/AmericanPutOption-v0", {"H": 8, "d": 6}),
    ("r2pvi/FiniteLinearMDP-v0", small_finite().init_kwargs()),
])
def test_registered_envs_pass_gymnasium_checks(gym, env_id, kwargs):
    from gymnasium.utils.env_checker import check_env

    env = gym.make(env_id, **kwargs)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=3)
    assert env.observation_space.contains(obs)
    assert info["step"] == 0 and info["phi"].shape == (env.action_space.n,
                                                         env.unwrapped.model.n_features)
    again, _ = env.reset(seed=3)
    np.testing.assert_array_equal(obs, again)
    steps, done = 0, False
    while not done:
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert isinstance(reward, float) and env.observation_space.contains(obs)
        steps += 1
        done = terminated or truncated
    assert steps <= env.unwrapped.model.horizon and info["step"] == steps
    with pytest.raises(RuntimeError, match="reset"):
        env.unwrapped.step(0)


def test_gymnasium_rollouts_have_the_exact_expected_return(gym):
    env = gym.make("r2pvi/SimulatedLinearMDP-v0", q=0.3)
    model = env.unwrapped.model
    env.reset(seed=0)
    env.action_space.seed(0)
    returns = []
    for _ in range(4000):
        env.reset()
        total, done = 0.0, False
        while not done:
            _, r, term, trunc, _ = env.step(env.action_space.sample())
            total, done = total + r, term or trunc
        returns.append(total)
    exact = expected_return(model, "uniform")
    assert abs(np.mean(returns) - exact) < 4 * np.std(returns) / np.sqrt(len(returns))


def test_fitted_estimator_acts_in_the_gymnasium_put_option(gym):
    from r2pvi.envs.gym import greedy_action

    model = AmericanPutOption(H=8, d=10)
    est = R2PVI("tv", 1.0, beta=0.1, r_max=model.r_max).fit(model.collect(300, seed=0))
    env = as_gymnasium_env(model)
    returns = []
    for episode in range(3000):
        obs, info = env.reset(seed=episode)
        total, done = 0.0, False
        while not done:
            a = greedy_action(est, info)
            assert a == model.actions(est, info["step"], obs)[0]
            obs, r, term, trunc, info = env.step(a)
            total, done = total + r, term or trunc
        returns.append(total)
    exact = expected_return(model, est)
    assert abs(np.mean(returns) - exact) < 4 * np.std(returns) / np.sqrt(len(returns))


def test_spec_rebuilds_the_model(gym):
    for model in (SimulatedLinearMDP(0.3, 0.1).perturbed(0.2), AmericanPutOption(p0=0.4, d=7),
                  HardInstance(2, 3, 0.5, 0.1, 0.2, [[1, -1]] * 3, "kl")):
        env = as_gymnasium_env(model)
        rebuilt = gym.make(env.spec).unwrapped.model
        assert type(rebuilt) is type(model) and rebuilt.init_kwargs() == model.init_kwargs()


def test_gymnasium_step_errors(gym):
    env = as_gymnasium_env(SimulatedLinearMDP())
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must lie in \[0, 16\)"):
        env.step(16)
    with pytest.raises(TypeError, match="action must be an integer"):
        env.step(0.5)


# ---------------------------------------------------------------------- Minari
@pytest.mark.parametrize("make", [
    lambda: (SimulatedLinearMDP(), "uniform"),
    lambda: (HardInstance(2, 3, 1.0, 0.2, 0.5, [1, -1]), "behavior"),
    lambda: (AmericanPutOption(H=6, d=5), "uniform"),  # early termination by exercise
])
def test_minari_round_trip(minari, tmp_path, make):
    env, policy = make()
    ds = env.collect(40, policy=policy, seed=1)
    from r2pvi.envs.minari import from_minari, to_minari

    md = to_minari(ds, env, "r2pvi/test/data-v0", author="r2pvi", description="round trip")
    assert md.total_episodes == 40

    loaded = minari.load_dataset("r2pvi/test/data-v0")  # Minari's own loader finds it
    for source, given in ((md, env), (loaded, None), ("r2pvi/test/data-v0", env),
                          (tmp_path / "minari" / "r2pvi/test/data-v0", None)):
        back = from_minari(source, given)
        for name in ("phi", "rewards", "next_phi", "states", "next_states"):
            np.testing.assert_array_equal(getattr(back, name), getattr(ds, name), err_msg=name)
        np.testing.assert_array_equal(back.next_values, ds.next_values)
        np.testing.assert_array_equal(back.actions, ds.actions)
    episode = next(iter(loaded.iterate_episodes()))
    assert episode.truncations[-1] or episode.terminations[-1]
    recovered = loaded.recover_environment().unwrapped.model
    assert recovered.init_kwargs() == env.init_kwargs()


def test_minari_export_refusals(minari, tmp_path):
    from r2pvi import OfflineDataset
    from r2pvi.envs.minari import from_minari, to_minari

    env = SimulatedLinearMDP()
    ds = env.collect(5, seed=0)
    to_minari(ds, env, "r2pvi/dup-v0", root=tmp_path)
    with pytest.raises(ValueError, match="already exists"):
        to_minari(ds, env, "r2pvi/dup-v0", root=tmp_path)
    bare = OfflineDataset.from_features(ds.phi, ds.rewards, ds.next_phi)
    with pytest.raises(ValueError, match="no states and actions"):
        to_minari(bare, env, "r2pvi/bare-v0", root=tmp_path)
    with pytest.raises(ValueError, match="pass the environment the data were collected in"):
        to_minari(ds, SimulatedLinearMDP(0.5, 0.3), "r2pvi/other-v0", root=tmp_path)
    with pytest.raises(TypeError, match="env must be an r2pvi environment"):
        to_minari(ds, "SimulatedLinearMDP", "r2pvi/x-v0", root=tmp_path)
    with pytest.raises(ValueError, match="H = 20"):
        from_minari(tmp_path / "r2pvi/dup-v0", AmericanPutOption())
    with pytest.raises(FileNotFoundError):
        from_minari("r2pvi/missing-v0", env)


# ---------------------------------------------------------------------- optional imports
def test_core_and_envs_never_import_the_extras():
    code = ("import sys, r2pvi, r2pvi.envs, r2pvi.evaluation, r2pvi.envs.minari; "
            "print([m for m in ('gymnasium', 'minari', 'h5py') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]"


def test_adapters_import_without_the_extras_and_name_them_on_use():
    code = """
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('gymnasium', 'minari'):
            raise ImportError('blocked ' + name)
sys.meta_path.insert(0, Block())
import r2pvi.envs.gym, r2pvi.envs.minari
from r2pvi.envs import SimulatedLinearMDP
env = SimulatedLinearMDP()
calls = (lambda: r2pvi.envs.gym.as_gymnasium_env(env),
         lambda: r2pvi.envs.minari.to_minari(env.collect(2), env, 'a-v0'))
for call in calls:
    try:
        call()
    except ImportError as exc:
        print(exc)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 2
    assert "r2pvi[gym]" in lines[0] and "r2pvi[minari]" in lines[1]


# ---------------------------------------------------------------------- the user guide
def test_user_guide_snippets_run(gym, minari, tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", DOCS.read_text(), flags=re.S)
    assert len(blocks) >= 5
    monkeypatch.chdir(tmp_path)
    namespace = {}
    for block in blocks:
        exec(compile(block, str(DOCS), "exec"), namespace)  # noqa: S102
