"""The nearest-neighbour model of a dataset of episodes and the ``"model"`` score.

Truths: on a finite MDP whose states are the observations, the model is the empirical MDP
of the data (exact dynamic programming on counted transitions); a translation-invariant
system is followed exactly off the data until the rollout is farther from every observation
than the halting radius (computed by brute force).
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn.model_selection import GridSearchCV, KFold

from r2pvi import PEVI, R2PVI, OfflineDataset
from r2pvi.algorithms import Scorer
from r2pvi.data import NeighbourModel
from r2pvi.features import StateAggregation, cross_actions

S, A, H = 4, 2, 5  # states 0..S-1, state S absorbing (terminal)


def finite_mdp(seed=0):
    rng = np.random.default_rng(seed)
    P = rng.dirichlet(np.ones(S + 1) * 0.7, (S, A))  # (S, A, S + 1): last = terminal
    P[..., S] *= 0.3
    P /= P.sum(axis=2, keepdims=True)
    R = rng.random((S, A))
    return P, R


def finite_episodes(P, R, K, seed, offset=0.0):
    """Episodes of the uniform behaviour; rewards ``R - offset`` (negative when shifted)."""
    rng = np.random.default_rng(seed)
    eps = []
    for _ in range(K):
        s = int(rng.integers(S))
        obs, acts, rews, term = [[float(s)]], [], [], []
        for _h in range(H):
            a = int(rng.integers(A))
            s2 = int(rng.choice(S + 1, p=P[s, a]))
            acts.append(a)
            rews.append(R[s, a] - offset)
            obs.append([float(s2)])
            term.append(s2 == S)
            if s2 == S:
                break
            s = s2
        eps.append({"observations": obs, "actions": acts, "rewards": rews,
                    "terminations": term, "truncations": [False] * (len(acts) - 1)
                    + [not term[-1]]})
    return eps


def empirical_value(eps, policy) -> float:
    """Exact DP on the counted transitions, averaged over the episodes' initial states."""
    counts = np.zeros((S, A, S + 1))
    rsum = np.zeros((S, A))
    for e in eps:
        for t, a in enumerate(e["actions"]):
            s, s2 = int(e["observations"][t][0]), int(e["observations"][t + 1][0])
            counts[s, a, s2] += 1
            rsum[s, a] += e["rewards"][t]
    n = counts.sum(axis=2)
    assert (n > 0).all(), "every state-action pair must be observed"
    Pe, Re = counts / n[..., None], rsum / n
    V = np.zeros(S + 1)  # V[S] = 0: absorbing
    for h in range(H - 1, -1, -1):
        a = np.array([policy(h, np.array([[float(s)]]))[0] for s in range(S)])
        V = np.append(Re[np.arange(S), a] + Pe[np.arange(S), a] @ V, 0.0)
    return float(np.mean([V[int(e["observations"][0][0])] for e in eps]))


FMAP = cross_actions(StateAggregation(n_bins=S + 1).fit([[0.0], [float(S)]]), A)


def table_policy(table):
    return lambda h, obs: np.asarray(table)[np.asarray(obs, dtype=int)[:, 0]]


@pytest.mark.parametrize("table", [[0, 0, 0, 0], [1, 0, 1, 1]])
def test_on_finite_states_the_model_is_the_empirical_mdp(table):
    P, R = finite_mdp(1)
    eps = finite_episodes(P, R, 300, seed=2)
    ds = OfflineDataset.from_episodes(eps, FMAP, A, horizon=H)
    model = NeighbourModel(ds)
    policy = table_policy(table)
    ret = model.returns(policy, n_rollouts=40, seed=3)
    truth = empirical_value(eps, policy)
    se = ret.std() / np.sqrt(ret.size)
    assert abs(ret.mean() - truth) < 4 * se + 1e-9, (ret.mean(), truth, se)


def test_shifted_rewards_add_the_offset_over_the_horizon():
    """Negative rewards shifted by ``reward_offset``: a terminated rollout is paid the
    absorbing state's known value, so the shifted return is the original plus ``H c``."""
    P, R = finite_mdp(4)
    eps = finite_episodes(P, R, 300, seed=5, offset=1.0)  # rewards in [-1, 0]
    ds = OfflineDataset.from_episodes(eps, FMAP, A, horizon=H, reward_offset=1.0)
    policy = table_policy([1, 1, 0, 1])
    ret = NeighbourModel(ds).returns(policy, n_rollouts=40, seed=6)
    truth = empirical_value(eps, policy) + H * 1.0
    assert abs(ret.mean() - truth) < 4 * ret.std() / np.sqrt(ret.size)


def drift_dataset(K=30, T=20, seed=0):
    """``x' = x + 0.1 (2 a - 1)``, reward 1, from x = 0: a random walk of the actions."""
    rng = np.random.default_rng(seed)
    eps = []
    for _ in range(K):
        a = rng.integers(2, size=T)
        x = np.concatenate([[0.0], np.cumsum(0.1 * (2 * a - 1))])
        eps.append({"observations": x[:, None], "actions": a, "rewards": np.ones(T),
                    "terminations": np.zeros(T, bool), "truncations": np.r_[[False] * (T - 1),
                                                                            True]})
    fmap = cross_actions(StateAggregation(n_bins=4).fit([[-2.0], [2.0]]), 2)
    return eps, OfflineDataset.from_episodes(eps, fmap, 2, horizon=T), fmap


def test_a_policy_follows_the_changes_of_state_and_halts_off_the_data():
    eps, ds, _ = drift_dataset()
    states = np.concatenate([np.asarray(e["observations"])[:-1, 0] for e in eps])
    scale = states.std()
    uniq = np.unique(states)
    gaps = [np.min(np.abs(np.delete(states, i) - x)) for i, x in enumerate(states)]
    radius = max(gaps) / scale  # brute force: the largest nearest-neighbour distance
    T = ds.horizon
    expected = 0
    for t in range(T):  # always action 1: x_t = 0.1 t, while it stays near the data
        if np.min(np.abs(uniq - 0.1 * t)) / scale > radius + 1e-12:
            break
        expected += 1
    model = NeighbourModel(ds)
    assert model.radius_ == pytest.approx(radius)
    up = model.returns(lambda h, obs: np.ones(len(obs), dtype=int))
    assert expected < T  # the walk leaves the data
    np.testing.assert_allclose(up, expected)
    never = NeighbourModel(ds, radius=np.inf).returns(lambda h, obs: np.ones(len(obs), int))
    np.testing.assert_allclose(never, T)


def test_the_model_score_is_the_empirical_value_of_the_greedy_policy():
    P, R = finite_mdp(7)
    eps = finite_episodes(P, R, 400, seed=8)
    ds = OfflineDataset.from_episodes(eps, FMAP, A, horizon=H)
    est = PEVI(beta=0.0).fit(ds[:200])
    held = ds[200:]
    score = est.score(held, kind="model", feature_map=FMAP, n_rollouts=40, random_state=1)
    truth = empirical_value(eps[200:], est.as_policy(FMAP))
    assert score == pytest.approx(truth, abs=0.08 * H)
    # the same seed gives the same number; a Generator is accepted
    assert est.score(held, kind="model", feature_map=FMAP, n_rollouts=40,
                     random_state=1) == score
    assert np.isfinite(est.score(held, kind="model", feature_map=FMAP,
                                 random_state=np.random.default_rng(0)))


def test_grid_search_selects_with_the_model_score():
    eps, ds, fmap = drift_dataset(K=40)
    search = GridSearchCV(R2PVI("tv", r_max=1.0, beta=0.0), {"lam": [0.1, 1.0]},
                          cv=KFold(2, shuffle=True, random_state=0),
                          scoring=Scorer("model", feature_map=fmap)).fit(ds)
    assert search.best_params_["lam"] in (0.1, 1.0)
    scores = search.cv_results_["mean_test_score"]
    assert np.all((scores >= 0) & (scores <= ds.horizon))


def test_model_arguments_are_checked():
    eps, ds, fmap = drift_dataset(K=5)
    est = R2PVI("tv", 0.5, r_max=1.0).fit(ds)
    with pytest.raises(ValueError, match="needs feature_map"):
        est.score(ds, kind="model")
    with pytest.raises(ValueError, match="needs feature_map"):
        Scorer("model")
    with pytest.raises(ValueError, match="feature_map is used by kind='model' only"):
        est.score(ds, kind="fqe", feature_map=fmap)
    with pytest.raises(ValueError, match="n_neighbors must be an integer >= 1"):
        est.score(ds, kind="model", feature_map=fmap, n_neighbors=0)
    with pytest.raises(ValueError, match="n_rollouts must be an integer >= 1"):
        NeighbourModel(ds).returns(lambda h, o: np.zeros(len(o), int), n_rollouts=0)
    with pytest.raises(ValueError, match="radius"):
        NeighbourModel(ds, radius=-1.0)
    with pytest.raises(ValueError, match=r"must return 5 integer actions in \[0, 2\)"):
        NeighbourModel(ds).returns(lambda h, o: np.full(len(o), 2))
    rng = np.random.default_rng(0)
    feats = OfflineDataset.from_features(rng.dirichlet(np.ones(3), (6, 2)), rng.random((6, 2)),
                                         rng.dirichlet(np.ones(3), (6, 2, 2)))
    with pytest.raises(ValueError, match="needs a dataset of episodes"):
        NeighbourModel(feats)
    one = [dict(e, actions=np.zeros(len(e["actions"]), int)) for e in eps]
    only0 = OfflineDataset.from_episodes(one, fmap, 2)
    with pytest.raises(ValueError, match="never takes action 1"):
        NeighbourModel(only0).returns(lambda h, o: np.ones(len(o), int))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), k=st.integers(1, 4), n_points=st.integers(2, 12))
def test_draws_take_the_action_among_the_k_nearest_distinct_observations(seed, k, n_points):
    """Ties (repeated observations) and several neighbours: a drawn transition has the
    asked action and an observation no farther than the k-th nearest distinct one."""
    rng = np.random.default_rng(seed)
    grid = rng.normal(size=(n_points, 2)).round(1)  # few distinct points: many ties
    eps = []
    for _ in range(6):
        idx = rng.integers(n_points, size=5)
        eps.append({"observations": grid[idx], "actions": rng.integers(2, size=4),
                    "rewards": np.ones(4), "terminations": np.zeros(4, bool),
                    "truncations": np.r_[False, False, False, True]})
    fmap = cross_actions(StateAggregation(n_bins=2).fit(grid), 2)
    model = NeighbourModel(OfflineDataset.from_episodes(eps, fmap, 2), n_neighbors=k)
    x = rng.normal(size=(30, 2))
    for a in range(2):
        mine = model.actions == a
        if not mine.any():
            continue
        j = model.draw(x, a, rng)
        assert (model.actions[j] == a).all()
        obs = model.states / model.scale_
        distinct = np.unique(obs[mine], axis=0)
        d_all = np.linalg.norm(x[:, None] / model.scale_ - distinct[None], axis=2)
        kth = np.sort(d_all, axis=1)[:, min(k, len(distinct)) - 1]
        d_drawn = np.linalg.norm(x / model.scale_ - obs[j], axis=1)
        assert (d_drawn <= kth + 1e-9).all()
