"""Minari datasets made by Minari's own API from an environment r2pvi did not define."""


import re
import sys

import numpy as np
import pytest
from extras import require

from r2pvi import OfflineDataset
from r2pvi.episodes import episode_observations
from r2pvi.features import NormalizedRBF, cross_actions


@pytest.fixture
def minari(tmp_path, monkeypatch):
    require("gymnasium")
    module = require("minari")
    require("h5py")
    require("PIL")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    return module


def _buffers(gym, n):
    """Episodes recorded by hand, as any Minari user would, in Minari's EpisodeBuffer."""
    from minari.data_collector import EpisodeBuffer

    env = gym.make("CartPole-v1")
    rng = np.random.default_rng(0)
    out = []
    for k in range(n):
        obs, _ = env.reset(seed=k)
        obs_, A, R, TE, TR = [obs], [], [], [], []
        done = False
        while not done:
            a = int(rng.integers(2))
            obs, r, te, tr, _ = env.step(a)
            obs_.append(obs), A.append(a), R.append(r), TE.append(te), TR.append(tr)
            done = te or tr or len(A) == 40
        TR[-1] = TR[-1] or not TE[-1]
        out.append(EpisodeBuffer(id=k, observations=np.array(obs_), actions=np.array(A),
                                 rewards=R, terminations=TE, truncations=TR, infos={}))
    return env, out


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_third_party_minari_dataset(minari):
    import gymnasium as gym

    from r2pvi.envs.minari import from_minari

    env, buffers = _buffers(gym, 6)
    md = minari.create_dataset_from_buffers("cartpole/random-v0", buffers, env=env,
                                            algorithm_name="random")
    with pytest.raises(ValueError, match="feature_map"):
        from_minari(md)  # a named error, not an AttributeError on the environment
    fmap = cross_actions(NormalizedRBF(n_centers=2).fit(episode_observations(md)), 2)
    direct = OfflineDataset.from_episodes(md, fmap, 2)
    loaded = from_minari("cartpole/random-v0", feature_map=fmap)  # local id, no download
    by_hand = OfflineDataset.from_episodes(
        [{"observations": b.observations, "actions": b.actions, "rewards": b.rewards,
          "terminations": b.terminations, "truncations": b.truncations} for b in buffers],
        fmap, 2)
    assert direct.horizon == max(len(b.rewards) for b in buffers)
    for ds in (direct, loaded):
        np.testing.assert_allclose(ds.phi, by_hand.phi, rtol=1e-6)
        np.testing.assert_array_equal(ds.rewards, by_hand.rewards)
        np.testing.assert_array_equal(np.isnan(ds.next_values), np.isnan(by_hand.next_values))


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_collected_episodes_round_trip_through_minari(minari, tmp_path):
    import gymnasium as gym

    from r2pvi.envs import collect_episodes
    from r2pvi.envs.minari import episodes_to_minari

    eps = collect_episodes(gym.make("CartPole-v1"), "uniform", 4, seed=2, max_steps=30)
    md = episodes_to_minari(eps, "cartpole/uniform-v0", gym.make("CartPole-v1"),
                            root=tmp_path / "elsewhere", algorithm_name="uniform")
    assert md.total_episodes == 4
    for e, back in zip(eps, md.iterate_episodes(), strict=True):
        np.testing.assert_allclose(back.observations, e.observations)
        np.testing.assert_array_equal(back.actions, e.actions)
        np.testing.assert_array_equal(back.terminations, e.terminations)
        np.testing.assert_array_equal(back.truncations, e.truncations)


def _guide_block(marker):
    """The code block of docs/your-own-task.md that contains ``marker``."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "your-own-task.md").read_text()
    blocks = [b for b in re.findall(r"```py(?:thon)?\n(.*?)```", text, flags=re.S)
              if marker in b]
    assert len(blocks) == 1, marker
    return blocks[0]


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_minari_data_collector_path_of_the_guide_runs_and_fits(minari, capsys):
    # Minari's DataCollector needs jax: r2pvi's minari-collect extra (part of the test
    # extra) brings it, so CI runs this; elsewhere it is skipped with the install line.
    pytest.importorskip("jax", reason="Minari's DataCollector needs jax: pip install "
                        "'.[minari-collect]'")
    namespace = {}
    exec(compile(_guide_block("minari.DataCollector("), "your-own-task.md", "exec"),  # noqa: S102
         namespace)
    assert namespace["collected"].total_episodes == 20
    data, est = namespace["collected_data"], namespace["est"]
    assert data.n_trajectories == 20 and data.n_actions == 2
    assert np.isfinite(est.weights_).all() and est.weights_.shape == (data.horizon, 2 * 49)
    assert capsys.readouterr().out.startswith("20 OfflineDataset(K=20")



def test_minari_data_collector_without_jax_fails_as_the_guide_says(minari, monkeypatch):
    # The guide sends DataCollector users to the minari-collect extra because of this error;
    # jax is hidden (an import of it fails) so this runs whether or not jax is installed. If
    # Minari stops needing jax, this fails and the guide (and the extra) should change.
    import gymnasium as gym

    monkeypatch.setitem(sys.modules, "jax", None)
    monkeypatch.setitem(sys.modules, "jax.numpy", None)
    env = minari.DataCollector(gym.make("CartPole-v1"))
    env.reset(seed=0)
    with pytest.raises(ImportError, match="jax is not installed"):
        env.step(0)
    env.close()
