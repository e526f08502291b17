"""Choosing settings from data alone: each held-out score, by 5-fold trajectory CV, on two tasks.

For every task a grid of estimators (R2PVI-TV, -KL, -chi2, PEVI, DRPVI) x lam/rho x beta x
fit form (pooled / per step) x feature map is

1. scored by 5-fold cross-validation over the **training trajectories only**
   (``KFold(5, shuffle=True, random_state=0)``; each candidate fitted on 4 folds and scored on
   the fifth with ``est.score``): ``bellman`` (minus the nominal Bellman residual), ``fqe``
   (fitted-Q evaluation of the greedy policy, pooled, on the candidate's own features and
   ridge ``gamma``: the library's default), ``fqe eval-map`` (the same on one richer
   evaluation map shared by every candidate, ridge 0.01: ``evaluation_map=``, ``gamma=``),
   ``fqe gamma=0.01`` (the candidate's own map, ridge 0.01), ``fqe eval-map LCB`` (the
   eval-map FQE minus one standard deviation of its five fold values), ``robust_fqe``
   (the policy's value under the candidate's own uncertainty model) and ``model`` (the
   greedy policy simulated in the nearest-neighbour model of the held-out episodes,
   :class:`r2pvi.data.neighbour_model.NeighbourModel`, default settings);
2. refitted on all training trajectories and evaluated in the test environments: the
   nominal return, and the mean over the perturbation sweeps (every point of every sweep).

For each score the pick is the candidate with the best mean CV score; it is compared with
the oracle (the best nominal return in the grid, known only from the test environment) and
the best sweep mean in the grid. Targets (issue "Settings from data alone"): the pick's
nominal return within 2 % of the oracle's, its sweep mean within 5 % of the best.

Tasks:

- ``cartpole``: the noisy CartPole protocol (:mod:`r2pvi.envs.noisy_cartpole`): 1000 episodes
  of ``EpsilonGreedy(CartPoleLQR(), 0.3)``, horizon 200, test grid
  :func:`r2pvi.envs.evaluate_cartpole_grid` (force, gravity and pole length sweeps, 36
  points x 20 episodes); maps ``NormalizedRBF(n_centers=3)`` (``d = 162``) and
  ``NormalizedRBF(n_centers=2)`` (``d = 32``), crossed with the 2 actions; evaluation map
  ``NormalizedRBF(n_centers=4)`` (``d = 512``).
- ``acrobot``: ``Acrobot-v1``, 200 episodes of an epsilon-greedy (0.3) energy pump (torque in
  the direction of the second joint's angular velocity), horizon 500, rewards shifted by
  ``reward_offset="auto"`` (``r_max = 1``); test: nominal and link 1's mass and length x 0.5,
  1.5, 2 (:func:`r2pvi.envs.perturbations.make_perturbed`), 20 episodes each, 500 steps; maps
  ``NormalizedRBF(n_centers=2)`` on the 6 observations (``d = 192``) and
  ``NormalizedRBF([1, 2, 1, 2, 3, 3])`` (``d = 108``: the sines and the velocities);
  evaluation map ``NormalizedRBF([2, 2, 2, 2, 3, 3])`` (``d = 432``). chi^2 is left out
  here: one fit takes 32 s of CPU at ``d = 192`` (499 steps: no fixed point with shifted
  rewards; 38 s before the batched sorted blocks).

- ``mountaincar`` (``--task mountaincar``; not part of ``both``): ``MountainCar-v0``, 200
  episodes of an epsilon-greedy (0.3) velocity push, horizon 200, rewards shifted; test:
  nominal and ``force`` x 0.75, 0.9, 1.25 and ``gravity`` x 0.8, 1.1, 1.25, 20 episodes each;
  maps ``NormalizedRBF(n_centers=6)`` (``d = 108``) and ``n_centers=4`` (``d = 48``);
  evaluation map ``n_centers=8``. Added after the ``model`` score's design was settled on
  the quick grids of the other two tasks: a task none of its choices saw.

Candidates run in ``--jobs`` processes (fork), BLAS on one thread each. The whole script
takes about 15-30 minutes on 2 cores.

    python benchmarks/bench_selection.py                     # both tasks
    python benchmarks/bench_selection.py --task acrobot --jobs 2
    python benchmarks/bench_selection.py --quick             # a small smoke run
    python benchmarks/bench_selection.py --task mountaincar  # the unseen third task
    python benchmarks/bench_selection.py --json rows         # also rows.<task>.json (folds)
    python benchmarks/bench_selection.py --calibration       # only the calibration table
    python benchmarks/bench_selection.py --model-check       # the model on the behaviour

``--calibration`` measures, for every evaluation setting (each map's own features and the
evaluation map, ridge ``gamma`` in 0.01, 0.1, 1), how well fitted-Q evaluation of the
behaviour policy on 4 training folds reproduces the fifth fold's observed returns
(:mod:`r2pvi.algorithms._calibration`): a data-only check of the evaluation's setting.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
from sklearn.base import clone
from sklearn.model_selection import KFold
from threadpoolctl import threadpool_limits

from r2pvi import DRPVI, PEVI, R2PVI, OfflineDataset
from r2pvi.episodes import episode_observations
from r2pvi.features import NormalizedRBF, cross_actions

SCORES = ("bellman", "fqe", "fqe gamma=0.01", "fqe eval-map", "robust_fqe", "model")
# a sensitivity check of the model score's settings (not a default): --scores "model k=5"
EXTRA_SCORES = ("model k=5",)
_ACTIVE: tuple = SCORES  # the scores this run computes (--scores)
# derived from the folds' scores: the eval-map FQE minus one standard deviation over folds
DERIVED = ("fqe eval-map LCB",)
CALIBRATION_GAMMAS = (0.01, 0.1, 1.0)


def score_arguments(task) -> dict:
    """``est.score`` keywords of each score (the evaluation map is the task's)."""
    return {"bellman": {"kind": "bellman"}, "fqe": {"kind": "fqe"},
            "fqe gamma=0.01": {"kind": "fqe", "gamma": 0.01},
            "fqe eval-map": {"kind": "fqe", "evaluation_map": task.eval_map, "gamma": 0.01},
            "robust_fqe": {"kind": "robust_fqe"}, "model": {"kind": "model"},
            "model k=5": {"kind": "model", "n_neighbors": 5, "n_rollouts": 5}}


@dataclass
class Candidate:
    label: str
    estimator: object
    feature_map: str


@dataclass
class Task:
    name: str
    episodes: list
    maps: dict  # name -> fitted feature map (crossed with the actions)
    eval_map: object  # the one map every candidate's FQE "eval-map" regresses on
    n_actions: int
    horizon: int
    reward_offset: object
    grid: list
    evaluate: object  # policy -> (nominal, sweep mean, {sweep: mean})
    behaviour: object
    datasets: dict = field(default_factory=dict)

    def dataset(self, map_name: str) -> OfflineDataset:
        if map_name not in self.datasets:
            self.datasets[map_name] = OfflineDataset.from_episodes(
                self.episodes, self.maps[map_name], self.n_actions, horizon=self.horizon,
                reward_offset=self.reward_offset)
        return self.datasets[map_name]


# ---------------------------------------------------------------------------- CartPole
def cartpole_task(quick: bool) -> Task:
    from r2pvi.envs import EpsilonGreedy, collect_episodes, evaluate_cartpole_grid
    from r2pvi.envs.experts import CartPoleLQR
    from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv

    behaviour = EpsilonGreedy(CartPoleLQR(), 0.3, 2)
    eps = collect_episodes(NoisyCartPoleEnv(), behaviour, 200 if quick else 1000, seed=1,
                           n_envs=50)
    obs = episode_observations(eps)
    maps = {"rbf3": cross_actions(NormalizedRBF(n_centers=3).fit(obs), 2),
            "rbf2": cross_actions(NormalizedRBF(n_centers=2).fit(obs), 2)}
    eval_map = cross_actions(NormalizedRBF(n_centers=4).fit(obs), 2)

    def evaluate(policy):
        r = evaluate_cartpole_grid(policy)
        sweeps = {p: float(r.mean[r.parameter == p].mean())
                  for p in ("force_mag", "gravity", "length")}
        nominal = float(r.mean[(r.parameter == "force_mag") & (r.p == 0.0)][0])
        return nominal, float(r.mean.mean()), sweeps

    def tv(lam, beta=0.1, form="auto", **kw):
        return R2PVI("tv", lam, beta=beta, r_max=1.0, time_homogeneous=form, **kw)

    lams = (0.03, 0.3, 3.0) if quick else (0.03, 0.1, 0.3, 1.0, 3.0)
    grid = [Candidate(f"TV lam={lam} beta=0.1", tv(lam), "rbf3") for lam in lams]
    if not quick:
        grid += [
            Candidate("TV lam=0.1 beta=0", tv(0.1, 0.0), "rbf3"),
            Candidate("TV lam=0.1 beta=0.1 per-step", tv(0.1, form=False), "rbf3"),
            Candidate("KL lam=0.1 beta=0.1", R2PVI("kl", 0.1, beta=0.1, r_max=1.0), "rbf3"),
            Candidate("PEVI beta=0.1", PEVI(beta=0.1, r_max=1.0), "rbf3"),
            # useless by construction: a huge ridge shrinks every Q towards 0
            Candidate("TV lam=0.03 beta=0.1 gamma=1e3", tv(0.03, gamma=1e3), "rbf3"),
            Candidate("TV lam=0.03 beta=0.1", tv(0.03), "rbf2"),
            Candidate("TV lam=0.3 beta=0.1", tv(0.3), "rbf2"),
            Candidate("KL lam=0.1 beta=0.1", R2PVI("kl", 0.1, beta=0.1, r_max=1.0), "rbf2"),
            Candidate("PEVI beta=0.1", PEVI(beta=0.1, r_max=1.0), "rbf2"),
        ]
    grid += [
        Candidate("chi2 lam=1.0 beta=0.1", R2PVI("chi2", 1.0, beta=0.1, r_max=1.0), "rbf2"),
        Candidate("DRPVI rho=0.1 beta=0.1", DRPVI(rho=0.1, beta=0.1, r_max=1.0), "rbf2"),
    ]
    return Task("cartpole", eps, maps, eval_map, 2, 200, None, grid, evaluate, behaviour)


# ---------------------------------------------------------------------------- Acrobot
def energy_pump(h, observations):
    """Torque (+1: action 2, -1: action 0) in the direction of the second joint's angular
    velocity: pumps energy into the swing."""
    obs = np.atleast_2d(observations)
    return np.where(obs[:, 5] >= 0.0, 2, 0).astype(np.int64)


ACROBOT_SWEEPS = {"link_mass_1": (0.5, 1.5, 2.0), "link_length_1": (0.5, 1.5, 2.0)}


def goal_task(name: str, env_id: str, behaviour_fn, n_episodes: int, horizon: int,
              centers: dict, eval_centers, sweeps: dict, quick: bool) -> Task:
    """A Gymnasium task with a distant goal (Acrobot, MountainCar): ``n_episodes`` of the
    epsilon-greedy (0.3) ``behaviour_fn``, rewards shifted, two maps (``centers``: name ->
    ``NormalizedRBF(n_centers=...)``, the first one the main map), ``beta = 0.01``; test:
    nominal and every value of every sweep, 20 episodes each."""
    import gymnasium as gym

    from r2pvi.envs import EpsilonGreedy, collect_episodes
    from r2pvi.envs.perturbations import make_perturbed
    from r2pvi.evaluation import evaluate_policy

    behaviour = EpsilonGreedy(behaviour_fn, 0.3, 3)
    eps = collect_episodes(gym.make(env_id), behaviour, n_episodes // 2 if quick else n_episodes,
                           seed=1, n_envs=50)
    obs = episode_observations(eps)
    maps = {k: cross_actions(NormalizedRBF(n_centers=c).fit(obs), 3) for k, c in centers.items()}
    eval_map = cross_actions(NormalizedRBF(n_centers=eval_centers).fit(obs), 3)
    main, second = centers

    def run(env, policy):
        return evaluate_policy(env, policy, 20, seed=0, n_envs=20, max_steps=horizon)[0]

    def evaluate(policy):
        nominal = run(gym.make(env_id), policy)
        means = {}
        for param, values in sweeps.items():
            runs = [nominal] + [run(make_perturbed(env_id, **{param: v}), policy)
                                for v in values]
            means[param] = float(np.mean(runs))
        return float(nominal), float(np.mean(list(means.values()))), means

    def tv(lam, beta=0.01, form="auto"):
        return R2PVI("tv", lam, beta=beta, r_max=1.0, time_homogeneous=form)

    grid = [Candidate(f"TV lam={lam} beta=0.01", tv(lam), main)
            for lam in ((0.3, 5.0) if quick else (0.3, 1.0, 5.0, 20.0))]
    if not quick:
        grid += [
            Candidate("TV lam=5.0 beta=0.01 per-step", tv(5.0, 0.01, False), main),
            Candidate("KL lam=1.0 beta=0.01", R2PVI("kl", 1.0, beta=0.01, r_max=1.0), main),
            Candidate("PEVI beta=0.01", PEVI(beta=0.01, r_max=1.0), main),
            Candidate("TV lam=5.0 beta=0.01", tv(5.0), second),
            Candidate("DRPVI rho=0.1 beta=0.01", DRPVI(rho=0.1, beta=0.01, r_max=1.0), second),
        ]
    grid.append(Candidate("PEVI beta=0.01", PEVI(beta=0.01, r_max=1.0), second))
    return Task(name, eps, maps, eval_map, 3, horizon, "auto", grid, evaluate, behaviour)


def acrobot_task(quick: bool) -> Task:
    return goal_task("acrobot", "Acrobot-v1", energy_pump, 200, 500,
                     {"rbf2": 2, "rbf-sv": [1, 2, 1, 2, 3, 3]}, [2, 2, 2, 2, 3, 3],
                     ACROBOT_SWEEPS, quick)


# ---------------------------------------------------------------------------- MountainCar
def velocity_push(h, observations):
    """Push (action 2) in the direction of the velocity, else pull (action 0)."""
    obs = np.atleast_2d(observations)
    return np.where(obs[:, 1] >= 0.0, 2, 0).astype(np.int64)


MOUNTAINCAR_SWEEPS = {"force": (0.00075, 0.0009, 0.00125),
                      "gravity": (0.002, 0.00275, 0.003125)}


def mountaincar_task(quick: bool) -> Task:
    """``MountainCar-v0``: added after the model score was designed on the other two tasks,
    as a task none of its design choices saw (see the module docstring)."""
    return goal_task("mountaincar", "MountainCar-v0", velocity_push, 200, 200,
                     {"rbf6": 6, "rbf4": 4}, 8, MOUNTAINCAR_SWEEPS, quick)


# ---------------------------------------------------------------------------- running
_TASK: Task | None = None  # the task of the forked workers (inherited, never sent)


def run_candidate(index: int) -> dict:
    """CV scores, refit and test returns of one candidate (in a worker)."""
    task = _TASK
    cand = task.grid[index]
    data = task.dataset(cand.feature_map)
    cv = KFold(5, shuffle=True, random_state=0)
    warnings.simplefilter("ignore")  # per-step fits warn that they starve (by design here)
    out = {"label": cand.label, "map": cand.feature_map, "d": data.n_features}
    scores = {name: [] for name in _ACTIVE}
    arguments = score_arguments(task)
    c0 = time.process_time()
    with threadpool_limits(1, "blas"):
        fit_cpu = 0.0
        for train, test in cv.split(data):
            c = time.process_time()
            est = clone(cand.estimator).fit(data[train])
            fit_cpu += time.process_time() - c
            held = data[test]
            for name in _ACTIVE:
                extra = ({"feature_map": task.maps[cand.feature_map]}
                         if name.startswith("model") else {})
                scores[name].append(est.score(held, **arguments[name], **extra))
        cv_cpu = time.process_time() - c0
        est = clone(cand.estimator).fit(data)
        policy = est.as_policy(task.maps[cand.feature_map])
        nominal, sweep, sweeps = task.evaluate(policy)
    cv_mean = {k: float(np.mean(v)) for k, v in scores.items()}
    if "fqe eval-map" in scores:
        spread = float(np.std(scores["fqe eval-map"], ddof=1))
        cv_mean["fqe eval-map LCB"] = cv_mean["fqe eval-map"] - spread
    out.update(cv=cv_mean, folds={k: [float(x) for x in v] for k, v in scores.items()},
               nominal=nominal, sweep=sweep, sweeps=sweeps,
               fit_cpu=fit_cpu / 5, cv_cpu=cv_cpu, cpu=time.process_time() - c0)
    return out


def run_task(task: Task, jobs: int) -> list[dict]:
    global _TASK
    for name in task.maps:  # built before forking: the workers share them
        task.dataset(name)
    _TASK = task
    if jobs <= 1:
        return [run_candidate(i) for i in range(len(task.grid))]
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(jobs) as pool:
        return pool.map(run_candidate, range(len(task.grid)), chunksize=1)


def calibrate_setting(setting: tuple) -> dict:
    """Behaviour-policy calibration of one evaluation setting ``(map name or "eval-map",
    gamma)`` by 5-fold trajectory CV on the training episodes (in a worker): SARSA-style
    FQE of the behaviour on 4 folds, its initial-state values against the fifth fold's
    observed returns (mean bias, RMSE per trajectory) and its one-step (TD) error there."""
    from r2pvi.algorithms._calibration import calibration_errors

    task = _TASK
    map_name, gamma = setting
    emap = task.eval_map if map_name == "eval-map" else None
    data = task.dataset(next(iter(task.maps)) if emap is not None else map_name)
    cv = KFold(5, shuffle=True, random_state=0)
    with threadpool_limits(1, "blas"):
        res = [calibration_errors(data[tr], data[te], gamma, emap) for tr, te in cv.split(data)]
    return {"map": map_name, "gamma": gamma,
            **{k: float(np.mean([r[k] for r in res])) for k in ("bias", "rmse", "td")}}


def run_calibration(task: Task, jobs: int) -> list[dict]:
    global _TASK
    for name in task.maps:
        task.dataset(name)
    _TASK = task
    settings = [(m, g) for m in (*task.maps, "eval-map") for g in CALIBRATION_GAMMAS]
    if jobs <= 1:
        return [calibrate_setting(s) for s in settings]
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(jobs) as pool:
        return pool.map(calibrate_setting, settings, chunksize=1)


def calibration_report(task: Task, rows: list[dict]) -> str:
    lines = [f"\n## {task.name}: behaviour-policy calibration of the evaluation settings\n",
             "| evaluation map | gamma | bias of the initial-state value | RMSE | TD error |",
             "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['map']} | {r['gamma']:g} | {r['bias']:.2f} | {r['rmse']:.2f} | "
                     f"{r['td']:.4g} |")
    best = min(rows, key=lambda r: r["rmse"])
    lines.append(f"\nbest calibrated (RMSE): {best['map']}, gamma {best['gamma']:g}; "
                 f"smallest TD error: "
                 + "{0[map]}, gamma {0[gamma]:g}".format(min(rows, key=lambda r: r["td"])))
    return "\n".join(lines)


def model_check(task: Task) -> str:
    """The nearest-neighbour model of each held-out fold against the data's own policy: the
    behaviour's simulated return (5 rollouts per initial observation) next to the fold's
    observed returns, 5-fold trajectory CV on the training episodes."""
    from r2pvi.algorithms._calibration import observed_returns
    from r2pvi.data import NeighbourModel

    data = task.dataset(next(iter(task.maps)))
    rng = np.random.default_rng(0)

    def behaviour(h, obs):
        return np.asarray(task.behaviour.sample(np.full(len(obs), h), obs, [rng] * len(obs)))

    sim, seen = [], []
    for _, test in KFold(5, shuffle=True, random_state=0).split(data):
        held = data[test]
        sim.append(float(NeighbourModel(held).returns(behaviour, n_rollouts=5).mean()))
        seen.append(float(observed_returns(held).mean()))
    return (f"\n{task.name}: the behaviour's return in the held-out folds' models "
            f"{np.round(sim, 1).tolist()} (mean {np.mean(sim):.1f}); observed "
            f"{np.round(seen, 1).tolist()} (mean {np.mean(seen):.1f}), in the dataset's "
            "reward units")


def gap(value: float, best: float) -> float:
    """Shortfall of ``value`` below ``best`` in % of ``|best|`` (0 when at or above)."""
    return max(0.0, best - value) / abs(best) * 100.0


def report(task: Task, rows: list[dict], behaviour: tuple) -> str:
    lines = [f"\n## {task.name}: {len(task.episodes)} training episodes, "
             f"{len(rows)} candidates\n"]
    lines.append(f"behaviour policy: nominal {behaviour[0]:.1f}, sweep mean "
                 f"{behaviour[1]:.1f}\n")
    names = [k for k in (*SCORES, *EXTRA_SCORES, *DERIVED) if k in rows[0]["cv"]]
    head = ["candidate", "map (d)", *names, "nominal", "sweep mean", "fit CPU s",
            "CV CPU s"]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    for r in rows:
        cells = [r["label"], f"{r['map']} ({r['d']})",
                 *(f"{r['cv'][k]:.4g}" for k in names),
                 f"{r['nominal']:.1f}", f"{r['sweep']:.1f}", f"{r['fit_cpu']:.2f}",
                 f"{r['cv_cpu']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    oracle = max(rows, key=lambda r: r["nominal"])
    best_sweep = max(r["sweep"] for r in rows)
    lines.append(f"\noracle (best nominal on the test environment): {oracle['label']} "
                 f"({oracle['map']}): nominal {oracle['nominal']:.1f}; best sweep mean in the "
                 f"grid: {best_sweep:.1f}\n")
    head = ["score", "pick", "nominal", "sweep mean", "gap to oracle nominal",
            "gap to best sweep mean", "targets (2 % / 5 %)"]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    for name in names:
        pick = max(rows, key=lambda r: r["cv"][name])
        g1, g2 = gap(pick["nominal"], oracle["nominal"]), gap(pick["sweep"], best_sweep)
        met = ("met" if g1 <= 2 and g2 <= 5 else "missed") + f" ({g1 <= 2}, {g2 <= 5})"
        lines.append(f"| {name} | {pick['label']} ({pick['map']}) | {pick['nominal']:.1f} | "
                     f"{pick['sweep']:.1f} | {g1:.1f} % | {g2:.1f} % | {met} |")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", choices=["cartpole", "acrobot", "mountaincar", "both"],
                        default="both", help="both: CartPole and Acrobot")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="small data and grid (smoke)")
    parser.add_argument("--calibration", action="store_true",
                        help="only the behaviour-policy calibration of the evaluation settings")
    parser.add_argument("--json", help="write the candidates' rows (fold scores) here")
    parser.add_argument("--model-check", action="store_true",
                        help="only the model's simulated return of the behaviour policy "
                             "against the held-out observed returns")
    parser.add_argument("--scores", nargs="+", choices=SCORES + EXTRA_SCORES,
                        help="compute only these scores (default: every score but the "
                             "sensitivity check 'model k=5')")
    args = parser.parse_args()
    global _ACTIVE
    if args.scores:
        _ACTIVE = tuple(args.scores)
    t0 = time.perf_counter()
    names = ["cartpole", "acrobot"] if args.task == "both" else [args.task]
    for name in names:
        t = time.perf_counter()
        task = {"cartpole": cartpole_task, "acrobot": acrobot_task,
                "mountaincar": mountaincar_task}[name](args.quick)
        if args.model_check:
            print(model_check(task), flush=True)
            continue
        if args.calibration:
            print(calibration_report(task, run_calibration(task, args.jobs)), flush=True)
            print(f"\n{name}: {time.perf_counter() - t:.0f} s wall", flush=True)
            continue
        rows = run_task(task, args.jobs)
        if args.json:
            with open(f"{args.json}.{name}.json", "w") as f:
                json.dump(rows, f, indent=1)
        behaviour = task.evaluate(task.behaviour)
        print(report(task, rows, behaviour), flush=True)
        print(f"\n{name}: {time.perf_counter() - t:.0f} s wall", flush=True)
    print(f"total: {time.perf_counter() - t0:.0f} s wall, {args.jobs} processes")


if __name__ == "__main__":
    main()
