"""``r2pvi demo``: a ten-second tour of why robustness matters.

Learn PEVI and R2PVI (TV, KL, chi^2) from a small offline dataset of the paper's simulated
linear MDP (Appendix A.1), then evaluate every learned policy *exactly* in test environments
whose first-step dynamics are shifted by ``q`` (factor 4 sends mass ``q`` to the fail state),
and print the returns side by side.
"""

from __future__ import annotations

import time

import numpy as np

from .algorithms import PEVI, R2PVI
from .data import OfflineDataset
from .envs._sampling import as_generator, check_count

__all__ = ["run_demo", "demo_returns", "random_linear_mdp_dataset"]

DEMO_QS = (0.0, 0.25, 0.5, 0.75, 1.0)


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


def _estimators(theta, lam):
    common = {"beta": 1.0, "gamma": 0.1, "reward_weights": theta}  # the paper's Appendix A
    return {
        "PEVI (non-robust)": PEVI(**common),
        f"R2PVI-TV   lam={lam:g}": R2PVI("tv", lam, **common),
        f"R2PVI-KL   lam={lam:g}": R2PVI("kl", lam, **common),
        f"R2PVI-chi2 lam={lam:g}": R2PVI("chi2", lam, **common),
    }


def demo_returns(seed=0, n_trajectories=100, n_datasets=10, lam=0.1, qs=DEMO_QS,
                 xi_norm=0.3):
    """Exact returns of PEVI and R2PVI-TV/KL/chi^2 under each shift ``q``.

    Fits every estimator on ``n_datasets`` independent datasets of ``n_trajectories``
    trajectories of :class:`~r2pvi.envs.SimulatedLinearMDP` and evaluates the greedy
    policies exactly in ``env.perturbed(q)``.

    Returns
    -------
    dict
        ``{name: (n_datasets, len(qs)) array}``, plus the exact nominal optimum (one row,
        it needs no data) under ``"nominal optimum (knows the model)"``.

    Examples
    --------
    >>> out = demo_returns(n_datasets=2, qs=(0.0, 1.0))
    >>> sorted(v.shape for v in out.values())[-1]
    (2, 2)
    """
    from .envs import SimulatedLinearMDP
    from .evaluation import expected_return, optimal_policy

    env = SimulatedLinearMDP(xi_norm=xi_norm)
    tests = [env.perturbed(q) for q in qs]
    children = np.random.SeedSequence(seed).spawn(n_datasets)
    out: dict = {}
    for i, child in enumerate(children):
        data = env.collect(n_trajectories, seed=np.random.default_rng(child))
        for name, est in _estimators(env.theta, lam).items():
            est.fit(data)
            out.setdefault(name, np.empty((n_datasets, len(qs))))[i] = [
                expected_return(t, est) for t in tests]
    best = optimal_policy(env)
    out["nominal optimum (knows the model)"] = np.array([[expected_return(t, best)
                                                          for t in tests]])
    return out


def run_demo(seed: int = 0, n_trajectories: int = 100, n_datasets: int = 10,
             lam: float = 0.1) -> dict:
    """Print the tour: returns of PEVI and R2PVI under increasing shifts, side by side."""
    t0 = time.perf_counter()
    qs = DEMO_QS
    out = demo_returns(seed, n_trajectories, n_datasets, lam, qs)
    print("r2pvi demo: why robustness matters\n")
    print(f"Each estimator learns from K = {n_trajectories} trajectories of the paper's "
          "simulated linear MDP\n(Appendix A.1, ||xi||_1 = 0.3), collected without any "
          "shift. Each learned policy is then\nevaluated exactly in test environments "
          "whose first step is shifted by q (factor 4 sends\nmass q to the fail state). "
          f"Average return, mean ± s.d. over {n_datasets} datasets:\n")
    width = max(len(k) for k in out) + 1
    print(" " * width + "".join(f"{'q = ' + format(q, 'g'):<13}" for q in qs) + "q=0 -> q=1")
    for name, vals in out.items():
        mean = vals.mean(axis=0)
        sd = vals.std(axis=0, ddof=1) if len(vals) > 1 else np.full_like(mean, np.nan)
        cells = "".join(f"{m:.3f}±{s:.3f}  " if np.isfinite(s) else f"{m:.3f}        "
                        for m, s in zip(mean, sd, strict=True))
        print(f"{name:<{width}}{cells}{mean[-1] - mean[0]:+.3f}")
    nominal = out["PEVI (non-robust)"].mean(axis=0)
    robust = {k: v.mean(axis=0) for k, v in out.items() if k.startswith("R2PVI")}
    steadiest = min(robust, key=lambda k: abs(robust[k][-1] - robust[k][0]))
    print(f"\nWithout shift (q = 0) PEVI earns {nominal[0]:.3f}; under the largest shift "
          f"(q = 1) it falls to {nominal[-1]:.3f}.\nThe steadiest, {steadiest.split()[0]}, "
          f"earns {robust[steadiest][0]:.3f} at q = 0 and {robust[steadiest][-1]:.3f} at "
          "q = 1: robustness trades return\nwithout shift for return under shift. Smaller "
          "lam = more robust: r2pvi reproduce fig1b.")
    print(f"({time.perf_counter() - t0:.1f} s)")
    return out
