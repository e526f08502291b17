"""Speed of the classic-control benchmark (``r2pvi reproduce cartpole``).

1. **Fit time** of every default estimator of the benchmark on its data: ``--data-episodes``
   episodes (100 here; 1000 in the benchmark) of the epsilon-greedy (0.3) LQR expert in the
   noisy CartPole (:class:`~r2pvi.envs.noisy_cartpole_gym.NoisyCartPoleEnv`), horizon 200,
   normalized RBF features (3^4 centers x 2 actions = 162 features); per-step estimators,
   and pooled steps (``time_homogeneous=True``). Each timing is the
   median of ``--repeats`` round-robin rounds (after one warm-up fit), with BLAS on one
   thread, in wall-clock and in CPU seconds of this process (``time.process_time``: on a
   shared, overloaded machine the wall clock measures the other jobs too).
2. **Rollout throughput**: environment steps per second of
   :func:`r2pvi.evaluation.evaluate_policy` for the expert and for a learned greedy policy,
   in one environment and in ``--n-envs`` sub-environments (a ``SyncVectorEnv``), and the
   raw ``gymnasium`` loop (no policy overhead, one env) as a reference.

    python benchmarks/bench_classic_control.py
    python benchmarks/bench_classic_control.py --repeats 5 --episodes 40 --n-envs 20
    python benchmarks/bench_classic_control.py --repeats 1 --data-episodes 1000
"""

from __future__ import annotations

import argparse
import statistics
import time

import gymnasium
import numpy as np
from threadpoolctl import threadpool_limits

from r2pvi.envs.experts import CartPoleLQR
from r2pvi.evaluation import episode_returns
from r2pvi.experiments.figures.cartpole_protocol import DEFAULTS, estimators, protocol_dataset
from r2pvi.experiments.figures.common import make_estimator


def default_data(episodes, seed=0):
    _, fmap, data, _, _ = protocol_dataset(np.random.SeedSequence(seed), {**DEFAULTS,
                                                                   "episodes": episodes})
    return data, fmap


def fit_times(data, repeats, pooled):
    s = DEFAULTS
    common = {"beta": s["beta"], "gamma": s["gamma"], "penalty": s["penalty"], "r_max": 1.0}
    ests = {}
    for label, _family, kind, param, div in estimators(s):
        est = make_estimator(kind, param, divergence=div, **common)
        est.set_params(time_homogeneous=pooled)   # not "auto" (pooled for episodes)
        ests[label] = est
    times = {k: [] for k in ests}
    cpu = {k: [] for k in ests}
    for est in ests.values():
        est.fit(data)
    for _ in range(repeats):
        for label, est in ests.items():
            t0, c0 = time.perf_counter(), time.process_time()
            est.fit(data)
            times[label].append(time.perf_counter() - t0)
            cpu[label].append(time.process_time() - c0)
    return ({k: (statistics.median(times[k]), statistics.median(cpu[k])) for k in ests},
            ests)


def raw_steps_per_second(n_steps=20000):
    """``(steps/s wall, steps/s CPU)`` of a plain gymnasium loop driven by the expert."""
    env = gymnasium.make("CartPole-v1")
    expert = CartPoleLQR()
    obs, _ = env.reset(seed=0)
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(n_steps):
        obs, _, term, trunc, _ = env.step(int(expert(0, obs)[0]))
        if term or trunc:
            obs, _ = env.reset()
    return n_steps / (time.perf_counter() - t0), n_steps / (time.process_time() - c0)


def rollout_rate(policy, episodes, n_envs, horizon=200):
    """``(steps/s wall, steps/s CPU, mean return)``."""
    env = gymnasium.make("CartPole-v1")
    t0, c0 = time.perf_counter(), time.process_time()
    returns = episode_returns(env, policy, episodes, seed=0, max_steps=horizon, n_envs=n_envs)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    steps = float(returns.sum())   # CartPole pays 1 per step
    return steps / wall, steps / cpu, float(returns.mean())


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=20, help="test episodes per rollout")
    parser.add_argument("--n-envs", type=int, default=20, help="vectorized sub-environments")
    parser.add_argument("--data-episodes", type=int, default=100,
                        help="behaviour episodes of the fitted dataset")
    args = parser.parse_args()
    t0 = time.perf_counter()
    data, fmap = default_data(args.data_episodes)
    print(f"default data: {data} (collected and featurized in {time.perf_counter() - t0:.2f} s)")
    with threadpool_limits(limits=1, user_api="blas"):
        learned = None
        for pooled in (False, True):
            times, ests = fit_times(data, args.repeats, pooled)
            learned = learned or ests["PEVI"]
            print(f"\nfit time, {'pooled steps' if pooled else 'per-step'} "
                  f"(median of {args.repeats}; wall s, CPU s)")
            for label, (wall, cpu) in times.items():
                print(f"  {label:<22} {wall:8.3f} {cpu:8.3f}")
        wall, cpu = raw_steps_per_second()
        print(f"\nraw gymnasium loop, one env, expert: {wall:,.0f} steps/s wall, "
              f"{cpu:,.0f} steps/CPU-s")
        policies = {"expert": CartPoleLQR(), "PEVI (greedy, 162 features)": learned.as_policy(fmap)}
        for name, policy in policies.items():
            for n_envs in (1, args.n_envs):
                wall, cpu, mean = rollout_rate(policy, args.episodes, n_envs)
                print(f"evaluate_policy, {name}, n_envs={n_envs:>3}: {wall:>9,.0f} steps/s wall, "
                      f"{cpu:>9,.0f} steps/CPU-s (mean return {mean:.1f} over {args.episodes} "
                      "episodes)")


if __name__ == "__main__":
    np.seterr(all="raise")
    main()
