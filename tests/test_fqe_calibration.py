"""Behaviour-policy fitted-Q evaluation and the calibration errors of an evaluation setting,
against exact dynamic programming on a tabular (hence linear) MDP with an absorbing state."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from r2pvi import OfflineDataset
from r2pvi.algorithms._calibration import (
    behaviour_weights,
    calibration_errors,
    observed_returns,
)
from r2pvi.features import StateAggregation, cross_actions

S, A = 4, 2  # live states; state S absorbs (the episode terminates on entering it)


def tabular_task(seed: int):
    """Random dynamics ``P (S, A, S+1)``, mean rewards ``R (S, A)`` in [0, 1], a stochastic
    behaviour ``b (S, A)`` and an initial distribution over the live states."""
    rng = np.random.default_rng(seed)
    P = rng.dirichlet(np.ones(S + 1), size=(S, A))
    R = rng.uniform(0.0, 1.0, (S, A))
    b = rng.dirichlet(np.ones(A), size=S)
    start = rng.dirichlet(np.ones(S))
    return P, R, b, start


def exact_behaviour_q(P, R, b, H: int, offset: float = 0.0) -> np.ndarray:
    """``Q^b_0 (S, A)`` by backward induction, rewards ``R`` (the shifted ones); the
    absorbing state pays ``offset`` at every step left."""
    V = np.zeros(S)
    for h in range(H - 1, -1, -1):
        Q = R + P[:, :, :S] @ V + P[:, :, S] * offset * (H - h - 1)
        V = (b * Q).sum(axis=1)
    return Q


def episodes(P, R, b, start, n: int, H: int, rng, offset: float = 0.0):
    """``n`` episodes of the behaviour (observation: the state index), cut at ``H``; rewards
    ``R - offset`` (so that ``reward_offset=offset`` shifts them back)."""
    out = []
    for _ in range(n):
        s = int(rng.choice(S, p=start))
        obs, acts, rews, term = [s], [], [], []
        for _ in range(H):
            a = int(rng.choice(A, p=b[s]))
            nxt = int(rng.choice(S + 1, p=P[s, a]))
            acts.append(a)
            rews.append(R[s, a] - offset)
            obs.append(nxt)
            term.append(nxt == S)
            if nxt == S:
                break
            s = nxt
        term = np.array(term)
        out.append({"observations": np.array(obs, float)[:, None], "actions": np.array(acts),
                    "rewards": np.array(rews), "terminations": term,
                    "truncations": ~term & (np.arange(len(term)) == len(term) - 1)})
    return out


def one_hot_map():
    """``e_a (x) e_s``: one cell per state (the absorbing state's own cell)."""
    return cross_actions(StateAggregation(n_bins=S + 1).fit([[0.0], [float(S)]]), A)


def dataset(eps, H, offset=0.0):
    return OfflineDataset.from_episodes(eps, one_hot_map(), A, horizon=H,
                                        reward_offset=offset if offset else None)


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 10_000), shifted=st.booleans())
@example(seed=1500, shifted=True)  # the absorbing state's offset above every shifted reward
def test_behaviour_fqe_converges_to_the_exact_behaviour_value(seed, shifted):
    """Tabular features make the behaviour's ``Q^b`` linear: with many episodes and a small
    ridge, the mean initial-state value of the pooled SARSA-style evaluation is the exact
    value of the behaviour policy (absorbing state and shifted rewards included)."""
    P, R, b, start = tabular_task(seed)
    H, offset = 6, (1.0 if shifted else 0.0)
    rng = np.random.default_rng(seed + 1)
    ds = dataset(episodes(P, R, b, start, 4000, H, rng, offset), H, offset)
    W = behaviour_weights(ds, gamma=1e-3)
    x0 = ds.initial_features()  # (K, A, d)
    a0 = np.asarray(ds._source.phi.actions)[0]
    got = x0[np.arange(len(a0)), a0] @ W[0]
    # the exact Q^b_0 at the sampled initial states and actions (the sampling of the initial
    # pairs is then no error of the evaluation)
    s0 = np.asarray(ds.states)[:, 0].astype(int).ravel()
    want = exact_behaviour_q(P, R, b, H, offset)[s0, a0]
    # estimation error of 4000 episodes (measured over 540 tasks: at most 0.7 of these
    # bounds, 3.3% on the mean; clipping values at the largest reward instead of the
    # absorbing state's offset was off by 9.6% on a shifted task)
    pair = s0 * A + a0  # pointwise at the pairs that start 200 episodes or more (a rarely
    common = np.bincount(pair, minlength=S * A)[pair] >= 200  # taken pair is estimated loosely)
    np.testing.assert_allclose(got[common], want[common], rtol=0.08, atol=0.04)
    assert float(got.mean()) == pytest.approx(float(want.mean()), rel=0.05)
    # the observed returns are an unbiased sample of the same values
    ret = observed_returns(ds)
    assert abs(float(ret.mean()) - float(want.mean())) <= 6 * ret.std() / np.sqrt(ret.size)


def test_observed_returns_are_the_episode_returns_in_the_shifted_units():
    P, R, b, start = tabular_task(3)
    H = 5
    eps = episodes(P, R, b, start, 50, H, np.random.default_rng(0), offset=1.0)
    got = observed_returns(dataset(eps, H, offset=1.0))
    # each step pays r + 1; the absorbing state pays 1 a step until H
    want = [np.sum(e["rewards"]) + H for e in eps]
    assert np.allclose(got, want)


def test_a_huge_ridge_is_the_miscalibrated_setting():
    """A ridge far above the features' mass shrinks every value toward 0: its behaviour
    values miss the held-out returns, a small ridge's do not."""
    P, R, b, start = tabular_task(7)
    H = 8
    rng = np.random.default_rng(0)
    train = dataset(episodes(P, R, b, start, 1500, H, rng), H)
    held = dataset(episodes(P, R, b, start, 500, H, rng), H)
    small = calibration_errors(train, held, gamma=0.01)
    huge = calibration_errors(train, held, gamma=1e5)
    assert abs(small["bias"]) < 0.1 * float(observed_returns(held).mean())
    assert huge["bias"] < -0.5 * float(observed_returns(held).mean())
    assert huge["rmse"] > 2 * small["rmse"]


def test_a_dataset_without_observations_is_refused_with_the_fix():
    phi = np.full((3, 2, 2), 0.5)
    ds = OfflineDataset.from_features(phi, np.zeros((3, 2)), np.full((3, 2, 1, 2), 0.5))
    with pytest.raises(ValueError, match="cross_actions"):
        behaviour_weights(ds, gamma=1.0)
