"""CPU time and peak memory of pooled fits on the noisy CartPole data (issue: "fits in
seconds").

The data: ``--episodes`` episodes of the epsilon-greedy (0.3) LQR expert in the noisy
CartPole (the RFQI protocol, :mod:`r2pvi.envs.noisy_cartpole`), horizon 200, 162 features
(``NormalizedRBF(n_centers=3)`` crossed with 2 actions), stored as state features once per
observation (``--dtype``). The episodes are collected once and kept in a temporary ``.npz``;
each estimator then runs in a fresh process that builds the dataset from them in memory, or
(``--dir``) opens a dataset directory written once (the state-feature layout: ``psi.npy``
memory-mapped; the episodes are not read), and fits, with one BLAS thread:

- ``fit CPU s``: ``time.process_time`` of ``fit`` alone;
- ``steps``: the steps the backward induction ran (a pooled fit stops at a fixed point);
- ``full-loop CPU s`` (``--full``): the same fit with the fixed-point stop turned off;
- ``peak RSS MB``: the whole process's peak resident memory (``ru_maxrss``): Python, NumPy,
  the episodes and the dataset built from them (or the opened directory's pages) and the fit;
- ``build CPU s`` / ``open CPU s``: reading the episodes and ``from_episodes``, or ``open``
  (which checks every number of ``psi.npy``, ``actions.npy`` and ``next_values.npy``).

With ``--dir`` the directory's size is printed, by file, next to what the dense rows would
take.

    python benchmarks/bench_pooled.py                       # 1000 episodes, float64
    python benchmarks/bench_pooled.py --episodes 5000 --dtype float32
    python benchmarks/bench_pooled.py --full --estimators tv,kl,pevi
    python benchmarks/bench_pooled.py --dir --estimators tv,pevi   # from a directory
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ESTIMATORS = {
    "tv": "R2PVI('tv', lam=0.1, beta=0.1, r_max=1.0, time_homogeneous=True)",
    "kl": "R2PVI('kl', lam=0.1, beta=0.1, r_max=1.0, time_homogeneous=True)",
    "chi2": "R2PVI('chi2', lam=0.3, beta=0.1, r_max=1.0, time_homogeneous=True)",
    "chi2-lam1": "R2PVI('chi2', lam=1.0, beta=0.1, r_max=1.0, time_homogeneous=True)",
    "pevi": "PEVI(beta=0.1, r_max=1.0, time_homogeneous=True)",
    "drpvi": "DRPVI(rho=0.1, beta=0.1, r_max=1.0, time_homogeneous=True)",
    "drvil": "DRVIL(rho=0.1, beta=0.1, r_max=1.0, time_homogeneous=True)",
}

# The episodes of the .npz file as dicts, and the feature map (the child's and the writer's).
EPISODES = r"""
with np.load(args["episodes"]) as z:
    obs, acts, rews, lens, term = (z[k] for k in ("obs", "acts", "rews", "lens", "term"))
eps, o, t = [], 0, 0
for n, tm in zip(lens, term):
    f = np.zeros(n, bool); f[-1] = tm
    eps.append({"observations": obs[o:o + n + 1], "actions": acts[t:t + n],
                "rewards": rews[t:t + n], "terminations": f,
                "truncations": ~f & (np.arange(n) == n - 1)})
    o += n + 1; t += n
fmap = cross_actions(NormalizedRBF(n_centers=3).fit(obs), 2)
"""

# From a directory the child opens it and nothing else (the episodes are not read): its
# peak RSS is the opened dataset's and the fit's.
CHILD = r"""
import json, resource, sys, time, warnings
import numpy as np
from threadpoolctl import threadpool_limits
from r2pvi import DRPVI, DRVIL, PEVI, R2PVI, OfflineDataset
from r2pvi.features import NormalizedRBF, cross_actions
args = json.loads(sys.argv[1])
warnings.simplefilter("ignore")
c = time.process_time()
if args["dir"]:
    data = OfflineDataset.open(args["dir"])
else:
""" + "\n".join("    " + line for line in EPISODES.strip().splitlines()) + r"""
    data = OfflineDataset.from_episodes(eps, fmap, 2, horizon=200, dtype=args["dtype"])
    del eps
build = time.process_time() - c
if args["full"]:
    import r2pvi.algorithms.base as base
    original = base.backward_induction
    base.backward_induction = lambda *a, **k: original(*a, **{**k, "early_stop": False})
est = eval(args["estimator"])
with threadpool_limits(1, "blas"):
    c = time.process_time()
    est.fit(data)
    cpu = time.process_time() - c
stop = est.fit_report_.stopped_at
print(json.dumps({"cpu": cpu, "build": build, "steps": 199 if stop is None else 199 - stop,
                  "rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "repr": repr(data)}))
"""


def collect(n_episodes: int, path: Path) -> None:
    import numpy as np

    from r2pvi.envs import EpsilonGreedy, collect_episodes
    from r2pvi.envs.experts import CartPoleLQR
    from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv

    eps = collect_episodes(NoisyCartPoleEnv(), EpsilonGreedy(CartPoleLQR(), 0.3, 2),
                           n_episodes, seed=1, n_envs=50)
    np.savez(path, obs=np.concatenate([e.observations for e in eps]),
             acts=np.concatenate([e.actions for e in eps]),
             rews=np.concatenate([e.rewards for e in eps]),
             lens=np.array([len(e) for e in eps]),
             term=np.array([bool(e.terminations[-1]) for e in eps]))


def write_directory(episodes: Path, target: Path, dtype: str) -> None:
    code = (CHILD.split("c = time.process_time()")[0] + EPISODES
            + f"OfflineDataset.from_episodes(eps, fmap, 2, horizon=200, dtype={dtype!r})"
            + f".save({str(target)!r})\n")
    subprocess.run([sys.executable, "-c", code, json.dumps({"episodes": str(episodes)})],
                   check=True)


def directory_size(path: Path) -> str:
    """The dataset directory's bytes by file, and what the dense rows would take."""
    sizes = {p.name: p.stat().st_size for p in sorted(path.iterdir())}
    mf = json.loads((path / "manifest.json").read_text())
    H, K, d, A = (mf[k] for k in ("horizon", "n_trajectories", "n_features", "n_actions"))
    item = 4 if mf["dtype"] == "float32" else 8
    dense = H * K * d * (1 + A) * item  # phi (H, K, d) and next_phi (H, K, A, d)
    files = ", ".join(f"{n} {b / 2**20:.1f}" for n, b in sizes.items())
    return (f"directory: {sum(sizes.values()) / 2**20:.1f} MiB ({files}); the dense rows "
            f"(phi.npy and next_phi.npy) would be {dense / 2**20:.1f} MiB")


def run(estimator: str, episodes: Path, dtype: str, directory, full: bool) -> dict:
    args = {"estimator": ESTIMATORS[estimator], "episodes": str(episodes), "dtype": dtype,
            "dir": None if directory is None else str(directory), "full": full}
    out = subprocess.run([sys.executable, "-c", CHILD, json.dumps(args)], check=True,
                         capture_output=True, text=True, env={**os.environ})
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    parser.add_argument("--estimators", default=",".join(ESTIMATORS))
    parser.add_argument("--dir", action="store_true",
                        help="fit from a dataset directory written once (else from memory)")
    parser.add_argument("--full", action="store_true",
                        help="also time the full loop (no fixed-point stop)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        episodes = Path(tmp) / "episodes.npz"
        collect(args.episodes, episodes)
        directory = None
        if args.dir:
            directory = Path(tmp) / "data"
            write_directory(episodes, directory, args.dtype)
            print(directory_size(directory))
        first = True
        build = "open CPU s" if args.dir else "build CPU s"
        for name in args.estimators.split(","):
            r = run(name, episodes, args.dtype, directory, False)
            if first:
                print(f"{r['repr']}, {args.dtype}, "
                      f"{'directory' if args.dir else 'memory'}; one BLAS thread")
                print(f"{'estimator':<10} {'fit CPU s':>10} {'steps':>6} "
                      f"{'full-loop CPU s':>16} {'peak RSS MB':>12} {build:>16}")
                first = False
            full = run(name, episodes, args.dtype, directory, True)["cpu"] if args.full \
                else float("nan")
            print(f"{name:<10} {r['cpu']:10.2f} {r['steps']:6d} {full:16.2f} {r['rss']:12.0f} "
                  f"{r['build']:16.2f}", flush=True)


if __name__ == "__main__":
    main()
