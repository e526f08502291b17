"""Speed of the noisy CartPole test grid (36 points x 20 episodes, RFQI protocol).

:func:`r2pvi.envs.evaluate_cartpole_grid` runs all 720 episodes as one NumPy batch. Timed,
each the median of ``--repeats`` runs, in CPU seconds of this process
(``time.process_time``) and wall seconds, BLAS on one thread:

1. the LQR expert (a linear controller: one product per step);
2. the epsilon-greedy (0.3) behaviour policy (one generator per episode and grid point);
3. a learned greedy policy: R2PVI-TV, pooled steps, lam 0.1, on 162 normalized RBF
   features x actions, fitted on ``--episodes`` behaviour episodes of the noisy CartPole
   (the fit is not timed);
4. with ``--compare``: the same grid for the expert through
   :func:`r2pvi.evaluation.evaluate_policy`, point by point, in ``NoisyCartPoleEnv``
   (a Gymnasium ``SyncVectorEnv`` of 20 sub-environments).

    python benchmarks/bench_cartpole_grid.py
    python benchmarks/bench_cartpole_grid.py --repeats 5 --compare
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from threadpoolctl import threadpool_limits

from r2pvi import R2PVI, OfflineDataset
from r2pvi.envs import EpsilonGreedy, collect_episodes, evaluate_cartpole_grid
from r2pvi.envs.experts import CartPoleLQR
from r2pvi.episodes import episode_observations
from r2pvi.features import NormalizedRBF, cross_actions


def timed(fn, repeats):
    """``(median wall s, median CPU s, last result)``."""
    walls, cpus, out = [], [], None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus), out


def learned_policy(n_episodes, behaviour):
    from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv

    eps = collect_episodes(NoisyCartPoleEnv(), behaviour, n_episodes, seed=1, n_envs=50)
    fmap = cross_actions(NormalizedRBF(n_centers=3).fit(episode_observations(eps)), 2)
    data = OfflineDataset.from_episodes(eps, fmap, 2, horizon=200)
    est = R2PVI("tv", lam=0.1, beta=0.1, gamma=1.0, r_max=1.0)
    if "time_homogeneous" in est.get_params():
        est.set_params(time_homogeneous=True)
    return est.fit(data).as_policy(fmap), data


def per_point_reference(policy, n_episodes):
    """The grid through evaluate_policy, one Gymnasium vector env per point."""
    from r2pvi.envs.cartpole_grid import perturbation_grid
    from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv
    from r2pvi.evaluation import episode_returns

    names, _, values = perturbation_grid()
    return np.array([episode_returns(NoisyCartPoleEnv(**{str(n): float(v)}), policy,
                                     n_episodes, seed=0, n_envs=20)
                     for n, v in zip(names, values, strict=True)])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=200,
                        help="behaviour episodes for the learned policy")
    parser.add_argument("--compare", action="store_true",
                        help="also time evaluate_policy point by point (several seconds)")
    args = parser.parse_args()
    expert = CartPoleLQR()
    behaviour = EpsilonGreedy(expert, 0.3, 2)
    with threadpool_limits(limits=1, user_api="blas"):
        t0 = time.perf_counter()
        greedy, data = learned_policy(args.episodes, behaviour)
        print(f"learned policy: R2PVI-TV lam 0.1 on {data} "
              f"(collected and fitted in {time.perf_counter() - t0:.1f} s, not timed)")
        print(f"\nevaluate_cartpole_grid, 36 points x 20 episodes (median of {args.repeats})")
        print(f"  {'policy':<34} {'wall s':>7} {'CPU s':>7} {'steps':>8} {'steps/CPU-s':>12} "
              f"{'nominal':>8}")
        rows = {"LQR expert (linear controller)": expert,
                "epsilon-greedy (0.3) expert": behaviour,
                "R2PVI-TV greedy, 162 features": greedy}
        for name, policy in rows.items():
            wall, cpu, res = timed(lambda p=policy: evaluate_cartpole_grid(p), args.repeats)
            steps = res.returns.sum()
            nominal = res.mean[(res.parameter == "force_mag") & (res.p == 0.0)][0]
            print(f"  {name:<34} {wall:7.3f} {cpu:7.3f} {steps:8.0f} {steps / cpu:12,.0f} "
                  f"{nominal:8.1f}")
        if args.compare:
            wall, cpu, ref = timed(lambda: per_point_reference(expert, 20), 1)
            same = np.array_equal(ref, evaluate_cartpole_grid(expert).returns)
            print(f"\nevaluate_policy point by point (NoisyCartPoleEnv, 20 sub-envs), expert: "
                  f"{wall:.2f} s wall, {cpu:.2f} s CPU; the same returns: {same}")


if __name__ == "__main__":
    main()
