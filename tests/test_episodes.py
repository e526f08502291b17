"""Episodes of any length -> OfflineDataset: termination, truncation, padding, reward offsets."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi import DRPVI, PEVI, R2PVI, OfflineDataset, SimplexFeatureWarning
from r2pvi.episodes import Episode, episode_observations
from r2pvi.features import StateAggregation, cross_actions

A = 2
FMAP = cross_actions(StateAggregation(n_bins=3).fit([[0.0], [1.0]]), n_actions=A)  # d = 6


def onehot(obs, a):
    """The same map written by hand: bin of obs in [0, 1/3), [1/3, 2/3), [2/3, 1]."""
    b = min(int(obs * 3), 2)
    out = np.zeros(6)
    out[3 * a + b] = 1.0
    return out


def ep(obs, actions, rewards, end):
    T = len(actions)
    term, trunc = np.zeros(T, bool), np.zeros(T, bool)
    if T:
        (term if end == "term" else trunc)[-1] = True
    return Episode(np.array(obs, float)[:, None], np.array(actions), np.array(rewards, float),
                   term, trunc)


def test_hand_built_dataset_termination_truncation_padding_and_cut():
    H = 3
    episodes = [
        ep([0.1, 0.5, 0.9], [0, 1], [1.0, 0.5], "term"),         # terminated after 2 steps
        ep([0.9, 0.1], [1], [0.2], "trunc"),                     # truncated after 1 step
        ep([0.5, 0.5, 0.1, 0.9, 0.9], [1, 0, 1, 0], [0.1, 0.2, 0.3, 0.4], "term"),  # cut at H
    ]
    ds = OfflineDataset.from_episodes(episodes, FMAP, A, horizon=H)
    assert (ds.n_trajectories, ds.horizon, ds.n_features, ds.n_actions) == (3, 3, 6, 2)
    phi = np.zeros((3, H, 6))
    rewards = np.zeros((3, H))
    next_phi = np.zeros((3, H, A, 6))
    next_values = np.full((3, H, A), np.nan)
    for k, e in enumerate(episodes):
        for h in range(min(len(e), H)):
            phi[k, h] = onehot(e.observations[h, 0], e.actions[h])
            rewards[k, h] = e.rewards[h]
            for a in range(A):
                next_phi[k, h, a] = onehot(e.observations[h + 1, 0], a)
    next_values[0, 1] = 0.0  # terminated at its last step: absorbing, value 0
    # Padding repeats a real next state of the same step: episode 0's at h = 1, 2 ...
    next_phi[1, 1] = next_phi[0, 1]
    next_values[1, 1] = next_values[0, 1]
    next_phi[0, 2] = next_phi[2, 2]
    next_phi[1, 2] = next_phi[2, 2]
    np.testing.assert_array_equal(ds.phi, phi)
    np.testing.assert_array_equal(ds.rewards, rewards)
    np.testing.assert_array_equal(ds.next_phi[:, : H - 1], next_phi[:, : H - 1])
    np.testing.assert_array_equal(ds.next_values[:, : H - 1], next_values[:, : H - 1])
    # Episode 2 terminated at T = 4 > H: it is cut (no absorbing value at h = H-1 anyway).
    # Truncated episode 1 bootstraps: its next value at h = 0 is learned (NaN).
    assert np.isnan(ds.next_values[1, 0]).all()
    np.testing.assert_array_equal(ds.actions[:, 0], [0, 1, 1])
    np.testing.assert_array_equal(ds.states[2, :, 0], [0.5, 0.5, 0.1])


def test_horizon_defaults_to_the_longest_episode_and_dicts_work():
    d = {"observations": [[0.1], [0.2], [0.3]], "actions": [[0], [1]], "rewards": [0.0, 1.0],
         "terminations": [False, False], "truncations": [False, True]}
    ds = OfflineDataset.from_episodes([d, ep([0.5, 0.6], [1], [1.0], "term")], FMAP, A)
    assert ds.horizon == 2


def _fits(ds):
    ests = [PEVI(beta=0.3), R2PVI("tv", 0.3, beta=0.1), R2PVI("kl", 0.5, beta=0.1),
            R2PVI("chi2", 0.5, beta=0.1), DRPVI(0.2, beta=0.1)]
    return [e.fit(ds).weights_ for e in ests]


def test_padding_adds_nothing_to_any_estimator():
    rng = np.random.default_rng(0)
    H = 4
    full = []
    for _ in range(30):  # full-length episodes: no padding
        obs = rng.uniform(size=H + 1)
        full.append(ep(obs, rng.integers(A, size=H), rng.uniform(size=H), "trunc"))
    empty = ep([0.3], [], [], "trunc")  # T = 0: every step of it is padding
    base = _fits(OfflineDataset.from_episodes(full, FMAP, A, horizon=H))
    padded = _fits(OfflineDataset.from_episodes(full + [empty, empty], FMAP, A, horizon=H))
    for w0, w1 in zip(base, padded, strict=True):
        np.testing.assert_allclose(w1, w0, rtol=0, atol=1e-12)


def test_padding_next_states_do_not_lower_the_data_minimum():
    # A short episode pads steps 1..3. With zero next features the padded rows would carry
    # V = 0 and lower TV's V_min = min(v) to 0; repeating a real next state keeps it.
    rng = np.random.default_rng(1)
    H = 3
    eps = [ep(rng.uniform(0.7, 1.0, size=H + 1), np.ones(H, int), np.ones(H), "trunc")
           for _ in range(20)]
    short = ep([0.8, 0.9], [1], [1.0], "trunc")
    ds = OfflineDataset.from_episodes(eps + [short], FMAP, A, horizon=H)
    per_step = {"beta": 0.0, "time_homogeneous": False}  # steps fitted one by one
    est = R2PVI("tv", 0.2, **per_step).fit(ds)
    ref = R2PVI("tv", 0.2, **per_step).fit(OfflineDataset.from_episodes(eps, FMAP, A, horizon=H))
    # The short episode adds one real transition at h = 0 only; later steps are unchanged.
    np.testing.assert_allclose(est.weights_[1:], ref.weights_[1:], atol=1e-12)
    zero_padded = OfflineDataset.from_features(
        ds.phi, ds.rewards, np.where(ds.phi.any(-1)[..., None, None], ds.next_phi, 0.0),
        ds.next_values, check_simplex=False)
    naive = R2PVI("tv", 0.2, **per_step).fit(zero_padded)
    assert not np.allclose(naive.weights_[1], ref.weights_[1])  # the trick matters


def test_negative_rewards_are_refused_or_shifted_exactly():
    rng = np.random.default_rng(2)
    H = 3
    eps = []
    for k in range(200):
        T = int(rng.integers(1, H + 1))
        obs = rng.uniform(size=T + 1)
        eps.append(ep(obs, rng.integers(A, size=T), -np.ones(T), "term" if k % 2 else "trunc"))
    with pytest.raises(ValueError, match="reward_offset"):
        OfflineDataset.from_episodes(eps, FMAP, A)
    ds = OfflineDataset.from_episodes(eps, FMAP, A, reward_offset="auto")
    assert ds.rewards.min() == 0.0
    terminal = ~np.isnan(ds.next_values[..., 0])
    h = np.nonzero(terminal)[1]
    np.testing.assert_array_equal(ds.next_values[terminal][:, 0], H - h - 1)  # (H-h-1) * 1
    # Shifting rewards that are already >= 0 changes Q_h by exactly (H - h) * c (gamma -> 0).
    pos = [Episode(e.observations, e.actions, e.rewards + 1.5, e.terminations, e.truncations)
           for e in eps]
    c = 0.75
    q0 = PEVI(beta=0.0, gamma=1e-9, r_max=10).fit(OfflineDataset.from_episodes(pos, FMAP, A))
    qc = PEVI(beta=0.0, gamma=1e-9, r_max=10).fit(
        OfflineDataset.from_episodes(pos, FMAP, A, reward_offset=c))
    grid = np.stack([np.stack([onehot(x, a) for a in range(A)]) for x in (0.1, 0.5, 0.9)])
    for step in range(H):
        np.testing.assert_allclose(qc.q_values(grid, step),
                                   q0.q_values(grid, step) + (H - step) * c, atol=1e-6)
    with pytest.raises(ValueError, match="at least 1"):
        OfflineDataset.from_episodes(eps, FMAP, A, reward_offset=0.5)


def test_episode_validation_errors():
    good = ep([0.1, 0.2], [0], [1.0], "term")
    with pytest.raises(ValueError, match="T\\+1"):
        OfflineDataset.from_episodes([Episode(np.zeros((1, 1)), good.actions, good.rewards,
                                              good.terminations, good.truncations)], FMAP, A)
    with pytest.raises(ValueError, match="n_actions"):
        OfflineDataset.from_episodes([ep([0.1, 0.2], [5], [1.0], "term")], FMAP, A)
    with pytest.raises(TypeError, match="observations"):
        OfflineDataset.from_episodes([object()], FMAP, A)
    with pytest.raises(ValueError, match="empty"):
        OfflineDataset.from_episodes([], FMAP, A)
    with pytest.raises(ValueError, match="before the last step"):
        bad = ep([0.1, 0.2, 0.3], [0, 1], [1.0, 1.0], "term")
        bad.terminations[0] = True
        OfflineDataset.from_episodes([bad], FMAP, A)
    with pytest.raises(TypeError, match="feature_map"):
        OfflineDataset.from_episodes([good], 3, A)
    with pytest.warns(SimplexFeatureWarning):
        OfflineDataset.from_episodes([good], lambda o, a: np.ones((len(a), 2)), A)


def test_caller_arrays_are_not_mutated():
    e = ep([0.1, 0.5, 0.9], [0, 1], [-1.0, -0.5], "term")
    before = [x.copy() for x in (e.observations, e.actions, e.rewards)]
    OfflineDataset.from_episodes([e], FMAP, A, reward_offset="auto")
    for x, y in zip(before, (e.observations, e.actions, e.rewards), strict=True):
        np.testing.assert_array_equal(x, y)
    assert episode_observations([e]).shape == (3, 1)


@st.composite
def ragged_episodes(draw):
    n = draw(st.integers(1, 6))
    out = []
    for _ in range(n):
        T = draw(st.integers(0, 5))
        obs = draw(st.lists(st.floats(0, 1), min_size=T + 1, max_size=T + 1))
        acts = draw(st.lists(st.integers(0, A - 1), min_size=T, max_size=T))
        rews = draw(st.lists(st.floats(0, 1), min_size=T, max_size=T))
        out.append(ep(obs, acts, rews, draw(st.sampled_from(["term", "trunc"]))))
    return out


@settings(max_examples=25, deadline=None)
@given(eps=ragged_episodes(), order_seed=st.integers(0, 2**16))
def test_ragged_episodes_structure_and_padding_invariance(eps, order_seed):
    if max(len(e) for e in eps) == 0:
        return
    ds = OfflineDataset.from_episodes(eps, FMAP, A)
    H = ds.horizon
    for k, e in enumerate(eps):
        T = len(e)
        assert not ds.phi[k, T:].any() and not ds.rewards[k, T:].any()  # no data after the end
        for h in range(T):
            np.testing.assert_array_equal(ds.phi[k, h], onehot(e.observations[h, 0], e.actions[h]))
        known = ~np.isnan(ds.next_values[k, : H - 1, 0])
        expected = np.zeros(H - 1, bool)
        if T and e.terminations[-1] and T - 1 < H - 1:
            expected[T - 1] = True
        for h in range(T, H - 1):  # padded rows repeat a real row of their step
            real = [j for j, f in enumerate(eps) if len(f) > h]
            if real:
                assert any(np.array_equal(ds.next_phi[k, h], ds.next_phi[j, h])
                           and np.array_equal(ds.next_values[k, h], ds.next_values[j, h],
                                              equal_nan=True) for j in real)
        np.testing.assert_array_equal(known[:T], expected[:T])
    # Empty episodes and the order of the episodes change no estimator's weights.
    order = np.random.default_rng(order_seed).permutation(len(eps) + 1)
    empty = ep([0.5], [], [], "trunc")
    more = [(eps + [empty])[i] for i in order]
    for est in (R2PVI("tv", 0.3, beta=0.1), DRPVI(0.2, beta=0.1), R2PVI("chi2", 0.5, beta=0.1)):
        w0 = est.fit(ds).weights_.copy()
        w1 = est.fit(OfflineDataset.from_episodes(more, FMAP, A, horizon=H)).weights_
        np.testing.assert_allclose(w1, w0, rtol=1e-9, atol=1e-9)
