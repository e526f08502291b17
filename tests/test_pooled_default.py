"""Datasets of episodes are stationary and fitted in the pooled form by default; the paper's
datasets keep the per-step form; the flag and the reward shift survive subsets and files."""

import numpy as np
import pytest

from r2pvi import PEVI, R2PVI, OfflineDataset
from r2pvi.features import NormalizedRBF, cross_actions

FMAP = cross_actions(NormalizedRBF(n_centers=3).fit(np.array([[0.0], [1.0]])), 2)


def _episodes(seed=0, K=40, H=6, reward=1.0):
    rng = np.random.default_rng(seed)
    eps = []
    for _ in range(K):
        T = int(rng.integers(1, H + 1))
        term = np.zeros(T, dtype=bool)
        term[-1] = rng.random() < 0.5
        eps.append({"observations": rng.random((T + 1, 1)), "actions": rng.integers(0, 2, T),
                    "rewards": np.full(T, reward), "terminations": term,
                    "truncations": ~term & (np.arange(T) == T - 1)})
    return eps


def test_episode_datasets_are_stationary_and_feature_datasets_are_not():
    ds = OfflineDataset.from_episodes(_episodes(), FMAP, 2, horizon=6)
    assert ds.stationary and ds.subset([0, 2, 3]).stationary
    dense = OfflineDataset.from_episodes(_episodes(), lambda o, a: FMAP(o, a), 2, horizon=6)
    assert dense.stationary
    plain = OfflineDataset.from_features(ds.phi, ds.rewards, ds.next_phi, ds.next_values,
                                         check_simplex=False)
    assert not plain.stationary


@pytest.mark.parametrize("form", ["directory", "npz"])
def test_stationarity_and_the_reward_shift_are_saved_with_the_dataset(tmp_path, form):
    ds = OfflineDataset.from_episodes(_episodes(reward=-1.0), FMAP, 2, horizon=6,
                                      reward_offset="auto")
    path = tmp_path / ("d" if form == "directory" else "d.npz")
    ds.save(path)
    back = OfflineDataset.open(path) if form == "directory" else OfflineDataset.load(path)
    assert back.stationary
    assert back._source.reward_offset == ds._source.reward_offset == 1.0
    a = R2PVI("tv", lam=0.5, beta=0.1, r_max=1.0).fit(ds)
    b = R2PVI("tv", lam=0.5, beta=0.1, r_max=1.0).fit(back)
    assert a.fit_report_.pooled and b.fit_report_.pooled
    np.testing.assert_allclose(a.weights_, b.weights_, rtol=1e-10, atol=1e-12)


def test_the_default_pools_episode_data_and_fits_paper_data_per_step():
    ds = OfflineDataset.from_episodes(_episodes(), FMAP, 2, horizon=6)
    auto = PEVI(beta=0.1).fit(ds)
    assert auto.fit_report_.pooled
    np.testing.assert_array_equal(auto.weights_,
                                  PEVI(beta=0.1, time_homogeneous=True).fit(ds).weights_)
    per_step = PEVI(beta=0.1, time_homogeneous=False).fit(ds)
    assert not per_step.fit_report_.pooled
    assert not np.allclose(per_step.weights_, auto.weights_)
    plain = OfflineDataset.from_features(ds.phi, ds.rewards, ds.next_phi, ds.next_values,
                                         check_simplex=False)
    assert not PEVI(beta=0.1).fit(plain).fit_report_.pooled
    assert PEVI(beta=0.1, time_homogeneous="AUTO").fit(ds).fit_report_.pooled


def test_time_homogeneous_rejects_other_values():
    ds = OfflineDataset.from_episodes(_episodes(), FMAP, 2, horizon=6)
    with pytest.raises(TypeError, match="'auto', True or False"):
        PEVI(time_homogeneous="yes").fit(ds)


@pytest.mark.parametrize("crossed", [True, False])
def test_a_reward_shift_adds_exactly_h_steps_of_it_to_pooled_q_values(crossed):
    # absorbing states hold (H - h - 1) c at their own row's step h; a pooled step h' must see
    # (H - h' - 1) c there, so that the shift adds (H - h') c to Q_h' as per step
    H, c = 5, 0.75
    eps = _episodes(seed=3, K=300, H=H, reward=0.5)
    fmap = FMAP if crossed else (lambda o, a: FMAP(o, a))
    base = OfflineDataset.from_episodes(eps, fmap, 2, horizon=H)
    shifted = OfflineDataset.from_episodes(eps, fmap, 2, horizon=H, reward_offset=c)
    est = {"beta": 0.0, "gamma": 1e-9, "r_max": 10.0, "time_homogeneous": True}
    q0, qc = PEVI(**est).fit(base), PEVI(**est).fit(shifted)
    grid = FMAP.all_actions(np.array([[0.1], [0.5], [0.9]]))
    for h in range(H):
        np.testing.assert_allclose(qc.q_values(grid, h), q0.q_values(grid, h) + (H - h) * c,
                                   atol=1e-6)
