"""A small end-to-end run: data from a random linear MDP, PEVI and R2PVI fits, greedy actions."""

from __future__ import annotations

import numpy as np

from .algorithms import PEVI, R2PVI
from .data import OfflineDataset
from .envs._sampling import as_generator, check_count


def random_linear_mdp_dataset(n_trajectories=500, horizon=3, n_states=6, n_actions=3,
                              n_features=4, seed=0):
    """A random tabular linear MDP with simplex features, sampled by a uniform policy.

    Returns the dataset, the features ``phi (S, A, d)`` and the reward weights ``theta (H, d)``.
    """
    K = check_count(n_trajectories, "n_trajectories")
    rng = as_generator(seed)
    S, A, d, H = n_states, n_actions, n_features, horizon
    phi = rng.dirichlet(0.3 * np.ones(d), size=(S, A))  # simplex features
    mu = rng.dirichlet(0.5 * np.ones(S), size=(H, d))  # factor distributions over states
    theta = rng.uniform(0.0, 1.0, size=(H, d))
    states = np.zeros((K, H), dtype=int)
    actions = rng.integers(A, size=(K, H))
    next_states = np.zeros((K, H), dtype=int)
    s = rng.integers(S, size=K)
    for h in range(H):
        states[:, h] = s
        p = np.einsum("kd,ds->ks", phi[s, actions[:, h]], mu[h])
        s = (p.cumsum(axis=1) > rng.random((K, 1))).argmax(axis=1)
        next_states[:, h] = s
    rewards = np.einsum("khd,hd->kh", phi[states, actions], theta)
    ds = OfflineDataset.from_transitions(
        states, actions, rewards, next_states, lambda st, a: phi[st, a], A
    )
    return ds, phi, theta


def run_demo(seed: int = 0, n_trajectories: int = 500) -> dict:
    """Fit PEVI and R2PVI-TV/KL/chi^2 on a small dataset and print what they learned."""
    ds, phi, theta = random_linear_mdp_dataset(n_trajectories=n_trajectories, seed=seed)
    print(f"dataset: {ds}")
    estimators = {
        "PEVI": PEVI(beta=0.1, reward_weights=theta),
        "R2PVI-TV (lam=0.5)": R2PVI("tv", 0.5, beta=0.1, reward_weights=theta),
        "R2PVI-KL (lam=0.5)": R2PVI("kl", 0.5, beta=0.1, reward_weights=theta),
        "R2PVI-chi2 (lam=0.5)": R2PVI("chi2", 0.5, beta=0.1, reward_weights=theta),
    }
    out = {}
    for name, est in estimators.items():
        est.fit(ds)
        acts = np.stack([est.act(phi, h) for h in range(ds.horizon)])
        out[name] = est
        fmt = {"float_kind": lambda x: f"{x:.3f}"}
        print(f"\n{name}")
        print("  weights_ (rows: steps h = 0..H-1, columns: features)")
        print("    " + np.array2string(est.weights_, prefix="    ", formatter=fmt))
        print("  greedy action per step (rows) and state (columns)")
        print("    " + np.array2string(acts, prefix="    "))
    return out
