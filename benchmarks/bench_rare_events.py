"""KL and chi^2 on rare-event data: ridge moments against valid moments, noisy CartPole.

The data of the noisy CartPole protocol (RFQI / RFZI; :mod:`r2pvi.envs.cartpole_grid`):
``--episodes`` episodes of the epsilon-greedy (0.3) LQR expert in the noisy environment, a
rare absorbing failure (tens to a few hundred failing transitions among ~1e5), normalized RBF
features (``NormalizedRBF(n_centers=N)``, ``N = --centers``: ``N^4`` features crossed with the
2 actions, d = 162 at the default N = 3, 512 at 4, 1250 at 5). Every fit is pooled
(``time_homogeneous=True``), beta 0.1, gamma 1, the "l1" penalty. For each dataset (seed) it
prints the nominal return and the mean return over each sweep of the test grid (force,
gravity, pole length; 12 points x 20 episodes each) of the estimators ``--estimators``
selects (default: tv, kl, chi2):

- ``tv``: R2PVI-TV at lam 0.1 (the reference), and at lam 1e-6, where the factor values are
  ~0 and the greedy policy is that of the ridge fit of the reward alone (the coverage
  control);
- ``kl``, ``chi2``: R2PVI-KL and R2PVI-chi2 at each lam of ``--lams`` (0.1, 0.3, 1, 3), with
  ``moments="ridge"`` (the signed ridge moments, the earlier estimator) and
  ``moments="valid"`` (the floor of order 1/N_i, docs/user_guide/rare-events.md);
- ``pevi``: PEVI;
- ``drpvi``: DRPVI (TV balls) at each rho of ``--rhos`` (0.05, 0.1, 0.2);
- ``drvil``: DRVI-L (KL balls) at each rho of ``--drvil-rhos`` (0.1; a pooled fit takes
  about 2 min on 1000 episodes);

with the fit's CPU seconds (one BLAS thread) and, to tell a bootstrapped value from a
one-step one, three numbers on the dataset's initial states (one per episode): the learned Q
(``Q0``: the mean of ``q_values(initial_features(), 0)`` over the states and both actions),
the action gap relative to it (``gap/Q0``: the mean ``|Q(s, 0) - Q(s, 1)|`` divided by
``Q0``) and the share of the states where the greedy action is the LQR expert's
(``agree``).

    python benchmarks/bench_rare_events.py                       # 1000 episodes, 1 dataset
    python benchmarks/bench_rare_events.py --episodes 300 --seeds 1 2 3
    python benchmarks/bench_rare_events.py --estimators pevi drpvi drvil --seeds 1 2 3
    python benchmarks/bench_rare_events.py --estimators tv pevi drpvi --rhos 0.1 --centers 4
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from threadpoolctl import threadpool_limits

from r2pvi import DRPVI, DRVIL, PEVI, R2PVI, OfflineDataset
from r2pvi.envs import EpsilonGreedy, collect_episodes, evaluate_cartpole_grid
from r2pvi.envs.experts import CartPoleLQR
from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv
from r2pvi.episodes import episode_observations
from r2pvi.features import NormalizedRBF, cross_actions

LAMS = (0.1, 0.3, 1.0, 3.0)
RHOS = (0.05, 0.1, 0.2)
DRVIL_RHOS = (0.1,)
ESTIMATORS = ("tv", "kl", "chi2", "pevi", "drpvi", "drvil")
DEFAULT_ESTIMATORS = ("tv", "kl", "chi2")
SWEEPS = ("force_mag", "gravity", "length")
COMMON = {"beta": 0.1, "gamma": 1.0, "penalty": "l1", "time_homogeneous": True}


def dataset(n_episodes: int, seed: int, n_centers: int = 3):
    """``(data, feature map, episodes that end in a failure, the expert's actions at the
    initial states)`` of one behaviour dataset."""
    expert = CartPoleLQR()
    behaviour = EpsilonGreedy(expert, 0.3, 2)
    eps = collect_episodes(NoisyCartPoleEnv(), behaviour, n_episodes, seed=seed, n_envs=50)
    fmap = cross_actions(NormalizedRBF(n_centers=n_centers).fit(episode_observations(eps)), 2)
    data = OfflineDataset.from_episodes(eps, fmap, 2, horizon=200)
    expert_actions = expert(0, np.stack([np.asarray(e.observations[0]) for e in eps]))
    return data, fmap, sum(int(np.any(e.terminations)) for e in eps), expert_actions


def estimators(names, lams, rhos, drvil_rhos):
    """``[(label, unfitted estimator)]`` of the families ``names``, in the order of
    :data:`ESTIMATORS`."""
    rows = []
    if "tv" in names:
        rows += [("TV lam 0.1", R2PVI("tv", lam=0.1, **COMMON)),
                 ("TV lam 1e-6 (coverage)", R2PVI("tv", lam=1e-6, **COMMON))]
    for div in ("kl", "chi2"):
        if div in names:
            for lam in lams:
                for moments in ("ridge", "valid"):
                    rows.append((f"{div} lam {lam:g} {moments}",
                                 R2PVI(div, lam=lam, moments=moments, **COMMON)))
    if "pevi" in names:
        rows.append(("PEVI", PEVI(**COMMON)))
    if "drpvi" in names:
        rows += [(f"DRPVI rho {rho:g}", DRPVI(rho, **COMMON)) for rho in rhos]
    if "drvil" in names:
        rows += [(f"DRVI-L rho {rho:g}", DRVIL(rho, **COMMON)) for rho in drvil_rhos]
    return rows


def initial_q(est, data, expert_actions):
    """``(Q0, gap / Q0, agree)``: the mean learned ``Q_0`` over the dataset's initial states
    and both actions, the mean ``|Q_0(s, 0) - Q_0(s, 1)|`` over them relative to it, and the
    share of them where the greedy action is ``expert_actions``'."""
    q = est.q_values(data.initial_features(), 0)
    mean = float(q.mean())
    gap = float(np.abs(q[:, 0] - q[:, 1]).mean())
    agree = float(np.mean(np.argmax(q, axis=1) == expert_actions))
    return mean, (gap / mean if mean > 0 else float("nan")), agree


def row(est, data, fmap, expert_actions):
    """``(nominal, sweep means..., fit CPU s, Q0, gap / Q0, agree)`` of one estimator."""
    t0 = time.process_time()
    est.fit(data)
    cpu = time.process_time() - t0
    res = evaluate_cartpole_grid(est.as_policy(fmap))
    mean = res.mean
    nominal = float(mean[(res.parameter == "force_mag") & (res.p == 0.0)][0])
    return ([nominal] + [float(mean[res.parameter == p].mean()) for p in SWEEPS] + [cpu]
            + list(initial_q(est, data, expert_actions)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1])
    parser.add_argument("--estimators", nargs="+", choices=ESTIMATORS,
                        default=list(DEFAULT_ESTIMATORS),
                        help="families to fit (default: tv kl chi2)")
    parser.add_argument("--lams", type=float, nargs="+", default=list(LAMS),
                        help="lam of R2PVI-KL and -chi2")
    parser.add_argument("--rhos", type=float, nargs="+", default=list(RHOS),
                        help="radii of DRPVI")
    parser.add_argument("--drvil-rhos", type=float, nargs="+", default=list(DRVIL_RHOS),
                        help="radii of DRVI-L")
    parser.add_argument("--centers", type=int, default=3,
                        help="NormalizedRBF(n_centers=N): d = 2 N^4 (default 3: d = 162)")
    args = parser.parse_args()
    if args.centers < 2:
        parser.error(f"--centers must be at least 2, got {args.centers}")
    header = (f"{'estimator':<26} {'nominal':>8} {'force':>7} {'gravity':>8} {'length':>7} "
              f"{'fit CPU s':>9} {'Q0':>8} {'gap/Q0':>8} {'agree':>6}")
    with threadpool_limits(limits=1, user_api="blas"):
        for seed in args.seeds:
            data, fmap, failures, expert_actions = dataset(args.episodes, seed, args.centers)
            print(f"\ndataset seed {seed}: {data}, {failures} episodes end in a failure; "
                  f"NormalizedRBF(n_centers={args.centers}): d = {data.n_features}")
            print(header)
            for name, est in estimators(set(args.estimators), args.lams, args.rhos,
                                        args.drvil_rhos):
                vals = row(est, data, fmap, expert_actions)
                print(f"{name:<26} {vals[0]:8.1f} {vals[1]:7.1f} {vals[2]:8.1f} {vals[3]:7.1f} "
                      f"{vals[4]:9.2f} {vals[5]:8.3f} {vals[6]:8.2e} {vals[7]:6.3f}", flush=True)


if __name__ == "__main__":
    main()
