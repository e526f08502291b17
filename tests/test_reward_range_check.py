"""``fit`` checks the rewards against ``[0, r_max]`` before it fits.

Rewards above ``r_max`` or below 0 are refused with a message that names the fix (the
``r_max`` to pass, the shift ``reward_offset`` makes); rounding passes, and so do noisy
rewards within the dataset's declared ``reward_noise``. ``reward_range`` is known for every
storage kind (memory, sparse rows, Dask, directories) and survives subsets and saves.
Where the check takes its numbers from (validation, the manifest, one read of the rewards,
never the features) is tested with the internals, in ``test_storage_internals.py``.
"""

import re

import numpy as np
import pytest
from extras import require
from helpers import A, D, H, K, linear_data

from r2pvi import DRPVI, DRVIL, PEVI, R2PVI, OfflineDataset
from r2pvi.envs import HardInstance
from r2pvi.features import StateAggregation, cross_actions
from r2pvi.sparse import SparseOfflineDataset

ESTIMATORS = [lambda **kw: PEVI(beta=0.0, **kw), lambda **kw: R2PVI("tv", lam=1.0, **kw),
              lambda **kw: R2PVI("kl", lam=1.0, **kw), lambda **kw: DRPVI(0.1, **kw),
              lambda **kw: DRVIL(0.1, **kw)]


@pytest.mark.parametrize("make", ESTIMATORS)
def test_fit_refuses_rewards_above_r_max_and_names_the_fix(make):
    data, *_ = linear_data(scale=5.0)
    high = data.reward_range[1]
    assert high == float(np.max(data.rewards)) > 1.0
    with pytest.raises(ValueError, match=re.escape(f"reach {high!r} > r_max=1.0; pass "
                                                   f"r_max={high!r} or larger")):
        make().fit(data)
    est = make(r_max=high).fit(data)  # the suggested r_max fits, and Q is not the clip
    q = est.q_values(data.next_phi[:, 0], 0)
    assert np.ptp(q) > 0 and q.max() < H * high


@pytest.mark.parametrize("make", ESTIMATORS[:2])
def test_fit_refuses_negative_rewards_and_says_how_to_shift_them(make):
    data, phi, r, nxt, _ = linear_data(shift=-2.0)
    low, high = data.reward_range
    with pytest.raises(ValueError, match="reward_offset='auto'") as info:
        make().fit(data)
    message = str(info.value)
    assert f"go down to {low!r} < 0" in message and f"c >= {-low!r}" in message
    assert f"{high - low!r} for c = {-low!r}" in message
    shifted = OfflineDataset.from_features(phi, r - low, nxt)  # the shift the message asks
    make(r_max=shifted.reward_range[1]).fit(shifted)


def test_reward_check_allows_rounding_only():
    _, phi, r, nxt, _ = linear_data()
    r = r / r.max()
    PEVI().fit(OfflineDataset.from_features(phi, r * (1 + 1e-13), nxt))
    PEVI().fit(OfflineDataset.from_features(phi, r - r.min() - 1e-13, nxt))
    with pytest.raises(ValueError, match="r_max"):
        PEVI().fit(OfflineDataset.from_features(phi, r * (1 + 1e-9), nxt))
    with pytest.raises(ValueError, match="< 0"):
        PEVI().fit(OfflineDataset.from_features(phi, r - r.min() - 1e-9, nxt))


def test_reward_check_on_sparse_and_dask_datasets():
    import scipy.sparse as sp

    _, phi, r, nxt, _ = linear_data(scale=5.0)
    sparse = SparseOfflineDataset.from_rows(
        [sp.csr_matrix(phi[:, h]) for h in range(H)], r,
        [sp.csr_matrix(nxt[:, h].reshape(K * A, D)) for h in range(H)], A)
    assert sparse.reward_range == (float(r.min()), float(r.max()))
    with pytest.raises(ValueError, match="r_max"):
        R2PVI("tv").fit(sparse)
    da = require("dask.array")
    lazy = OfflineDataset.from_dask(da.from_array(phi, chunks=(20, H, D)),
                                    da.from_array(r, chunks=(20, H)),
                                    da.from_array(nxt, chunks=(20, H, A, D)))
    assert lazy.reward_range == (float(r.min()), float(r.max()))


def test_noisy_rewards_pass_within_their_noise_and_a_wrong_scale_does_not():
    with pytest.warns(UserWarning, match="lemma"):
        env = HardInstance.lower_bound_instance(2, 3, 1.0, 30, "tv", seed=0)
    data = env.collect(100, policy="behavior", seed=1)
    assert data.reward_noise == 1.0 and data.reward_range[0] < 0  # N(r, 1) samples
    R2PVI("tv").fit(data)
    _, phi, r, nxt, _ = linear_data()
    noisy = r + 0.1 * np.random.default_rng(1).standard_normal(r.shape)
    with pytest.raises(ValueError, match="< 0"):
        PEVI().fit(OfflineDataset.from_features(phi, noisy, nxt))
    PEVI().fit(OfflineDataset.from_features(phi, noisy, nxt, reward_noise=0.1))
    with pytest.raises(ValueError, match="8 standard deviations of the dataset's reward_noise"):
        PEVI().fit(OfflineDataset.from_features(phi, 5 * r, nxt, reward_noise=0.1))


def test_reward_noise_survives_subset_and_saves(tmp_path):
    data, *_ = linear_data(reward_noise=0.25)
    assert data.subset([0, 1]).reward_noise == 0.25
    assert OfflineDataset.open(data.save(tmp_path / "d")).reward_noise == 0.25
    assert OfflineDataset.load(data.save(tmp_path / "d.npz")).reward_noise == 0.25
    with pytest.raises(ValueError, match="reward_noise must be >= 0"):
        linear_data(reward_noise=-1.0)


def test_pendulum_rewards_shifted_by_auto_need_their_r_max():
    require("gymnasium")
    import gymnasium as gym

    from r2pvi.envs import collect_episodes
    from r2pvi.envs.perturbations import DiscreteTorque
    from r2pvi.episodes import episode_observations

    env = DiscreteTorque(gym.make("Pendulum-v1"), n_levels=3)
    eps = collect_episodes(env, "uniform", n_episodes=4, seed=0, max_steps=10)
    fmap = cross_actions(StateAggregation(n_bins=3).fit(episode_observations(eps)), 3)
    data = OfflineDataset.from_episodes(eps, fmap, n_actions=3, reward_offset="auto")
    high = data.reward_range[1]
    assert high > 1.0
    with pytest.raises(ValueError, match=re.escape(f"pass r_max={high!r} or larger")):
        R2PVI("tv", lam=1.0).fit(data)
    R2PVI("tv", lam=1.0, r_max=high).fit(data)


def _goal_episodes(n=30, seed=0):
    """-1 per step until an episode reaches an absorbing goal (observation 1.0) or is cut."""
    rng = np.random.default_rng(seed)
    eps = []
    for _ in range(n):
        T = int(rng.integers(2, 6))
        reached = bool(rng.random() < 0.5)
        obs = np.r_[rng.random(T) * 0.9, 1.0 if reached else rng.random() * 0.9][:, None]
        term = np.zeros(T, bool)
        term[-1] = reached
        eps.append({"observations": obs, "actions": rng.integers(0, 2, T),
                    "rewards": np.full(T, -1.0), "terminations": term,
                    "truncations": ~term & (np.arange(T) == T - 1)})
    return eps


def test_an_r_max_below_the_offset_of_absorbing_episodes_is_refused_with_the_fix():
    # The goal pays the offset c = 1 at every remaining step: with r_max = 0.5 every other
    # value would be clipped below the goal's. Without absorbing states (Pendulum, above)
    # the offset bounds nothing and a smaller r_max stays allowed.
    eps = _goal_episodes()
    fmap = cross_actions(StateAggregation(n_bins=4).fit([[0.0], [1.0]]), 2)
    data = OfflineDataset.from_episodes(eps, fmap, 2, horizon=6, reward_offset="auto")
    assert data.has_known_values and data.reward_range[1] <= 1.0
    for est in (R2PVI("tv", lam=0.1, r_max=0.5), PEVI(r_max=0.5), DRPVI(0.1, r_max=0.5)):
        with pytest.raises(ValueError, match=r"r_max=0\.5 is below .* reward offset c=1\.0"
                                             r".*Pass r_max >= 1\.0"):
            est.fit(data)
    R2PVI("tv", lam=0.1, r_max=1.0).fit(data)
