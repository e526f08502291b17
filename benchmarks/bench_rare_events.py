"""KL and chi^2 on rare-event data: ridge moments against valid moments, noisy CartPole.

The data of the noisy CartPole protocol (RFQI / RFZI; :mod:`r2pvi.envs.cartpole_grid`):
``--episodes`` episodes of the epsilon-greedy (0.3) LQR expert in the noisy environment, a
rare absorbing failure (tens to a few hundred failing transitions among ~1e5), 81 normalized
RBF features (``NormalizedRBF(n_centers=3)``) crossed with the 2 actions (d = 162). Every fit
is pooled (``time_homogeneous=True``), beta 0.1, gamma 1. For each dataset (seed) it prints
the nominal return and the mean return over each sweep of the test grid (force, gravity, pole
length; 12 points x 20 episodes each) of

- R2PVI-TV at lam 0.1 (the reference), and at lam 1e-6, where the factor values are ~0 and
  the greedy policy is that of the ridge fit of the reward alone (the coverage control);
- R2PVI-KL and R2PVI-chi2 at lam 0.1, 0.3, 1, 3, with ``moments="ridge"`` (the signed ridge
  moments, the earlier estimator) and ``moments="valid"`` (the floor of order 1/N_i,
  docs/user_guide/divergences.md);

with the fit's CPU seconds (one BLAS thread).

    python benchmarks/bench_rare_events.py                       # 1000 episodes, 1 dataset
    python benchmarks/bench_rare_events.py --episodes 300 --seeds 1 2 3
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from threadpoolctl import threadpool_limits

from r2pvi import R2PVI, OfflineDataset
from r2pvi.envs import EpsilonGreedy, collect_episodes, evaluate_cartpole_grid
from r2pvi.envs.experts import CartPoleLQR
from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv
from r2pvi.episodes import episode_observations
from r2pvi.features import NormalizedRBF, cross_actions

LAMS = (0.1, 0.3, 1.0, 3.0)
SWEEPS = ("force_mag", "gravity", "length")


def dataset(n_episodes: int, seed: int):
    """``(data, feature map, episodes that end in a failure)`` of one behaviour dataset."""
    behaviour = EpsilonGreedy(CartPoleLQR(), 0.3, 2)
    eps = collect_episodes(NoisyCartPoleEnv(), behaviour, n_episodes, seed=seed, n_envs=50)
    fmap = cross_actions(NormalizedRBF(n_centers=3).fit(episode_observations(eps)), 2)
    data = OfflineDataset.from_episodes(eps, fmap, 2, horizon=200)
    return data, fmap, sum(int(np.any(e.terminations)) for e in eps)


def row(est, data, fmap):
    """``(nominal, sweep means..., fit CPU s)`` of one estimator."""
    t0 = time.process_time()
    est.fit(data)
    cpu = time.process_time() - t0
    res = evaluate_cartpole_grid(est.as_policy(fmap))
    mean = res.mean
    nominal = float(mean[(res.parameter == "force_mag") & (res.p == 0.0)][0])
    return [nominal] + [float(mean[res.parameter == p].mean()) for p in SWEEPS] + [cpu]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1])
    parser.add_argument("--lams", type=float, nargs="+", default=list(LAMS))
    args = parser.parse_args()
    common = {"beta": 0.1, "gamma": 1.0, "time_homogeneous": True}
    header = (f"{'estimator':<26} {'nominal':>8} {'force':>7} {'gravity':>8} {'length':>7} "
              f"{'fit CPU s':>9}")
    with threadpool_limits(limits=1, user_api="blas"):
        for seed in args.seeds:
            data, fmap, failures = dataset(args.episodes, seed)
            print(f"\ndataset seed {seed}: {data}, {failures} episodes end in a failure")
            print(header)
            rows = [("TV lam 0.1", R2PVI("tv", lam=0.1, **common)),
                    ("TV lam 1e-6 (coverage)", R2PVI("tv", lam=1e-6, **common))]
            for div in ("kl", "chi2"):
                for lam in args.lams:
                    for moments in ("ridge", "valid"):
                        rows.append((f"{div} lam {lam:g} {moments}",
                                     R2PVI(div, lam=lam, moments=moments, **common)))
            for name, est in rows:
                vals = row(est, data, fmap)
                print(f"{name:<26} {vals[0]:8.1f} {vals[1]:7.1f} {vals[2]:8.1f} {vals[3]:7.1f} "
                      f"{vals[4]:9.2f}", flush=True)


if __name__ == "__main__":
    main()
