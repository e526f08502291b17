"""Classic-control robustness benchmark on Gymnasium's MountainCar: ``r2pvi reproduce
mountaincar``.

The protocol of robust offline RL papers on classic control (RFQI, Panaganti et al. 2022),
applied to ``MountainCar-v0`` (``r2pvi reproduce cartpole`` runs the published noisy CartPole
protocol: :mod:`r2pvi.experiments.figures.cartpole_protocol`):

1. **data**: ``trajectories`` episodes of horizon ``horizon`` from an epsilon-greedy
   (``epsilon = 0.3``) expert in the *nominal* environment. The expert is hand-built, no
   neural network: energy pumping (:mod:`r2pvi.envs.experts`);
2. **features**: a normalized Gaussian RBF grid over the observation box seen in the data,
   crossed with the actions (on the probability simplex, the paper's assumption);
3. **algorithms**, all on the same data and features: PEVI, R2PVI with each divergence and
   each ``lam``, DRPVI with each ``rho``;
4. **test**: every learned policy, the expert and the behaviour policy are rolled out in
   environments whose physical parameters are multiplied by ``1 + p`` (and with a random
   action executed with probability ``p``), ``test_episodes`` episodes per level with the
   same seeds for every policy (common random numbers), cut at the horizon.

A replication is one dataset (one task of the sweep, seeded by its own ``SeedSequence``
child); rows hold the mean return over the test episodes and its standard error, plus one
fit-time row per algorithm. The plot and the table average over replications, with the
standard error across replications.

Nothing here looks at the test environments to choose ``lam`` or ``rho``: every value of
the grids is reported (the grids are fixed by the value scale ``H r_max``; see
``docs/classic-control.md``).
"""

from __future__ import annotations

import math
import time
from collections import defaultdict

import numpy as np

from ..runner import Task
from .common import Figure, make_estimator

__all__ = ["MOUNTAINCAR", "TASKS", "replication", "summary_by_level"]

# --------------------------------------------------------------------------- the tasks
# env id, actions, nominal parameters, the expert, the reward offset for from_episodes, and
# the reward bound after the offset.
TASKS = {
    "mountaincar": {
        "env_id": "MountainCar-v0", "n_actions": 3, "expert": "MountainCarEnergy",
        "nominal": {"force": 0.001, "gravity": 0.0025},
        "reward_offset": 1.0, "r_max": 1.0,
    },
}

COMMON_DEFAULTS = {
    "horizon": 200,
    "trajectories": 100,
    "epsilon": 0.3,
    "centers": 3,
    "bandwidth": 0.0,          # 0: the grid spacing (NormalizedRBF's default)
    "beta": 0.1,
    "gamma": 1.0,
    "penalty": "l1",
    "time_homogeneous": False,
    "divergences": ["tv", "kl", "chi2"],
    "lams": [1.0, 10.0, 100.0],
    "rhos": [0.05, 0.2],
    "replications": 3,
    "test_episodes": 10,
    "references": True,
    "action_noise": [0.0, 0.25, 0.5, 0.75, 1.0],
}

MOUNTAINCAR_DEFAULTS = {
    **COMMON_DEFAULTS,
    "force": [-0.5, -0.25, 0.0, 0.5, 1.0],
    "gravity": [-0.5, 0.0, 0.25, 0.5, 1.0],
}


def _perturbations(task: str, s: dict) -> list[tuple[str, float]]:
    """``[(perturbation, level)]``: each physical parameter's ``p`` grid, then action noise."""
    names = list(TASKS[task]["nominal"]) + ["action_noise"]
    return [(name, float(p)) for name in names for p in s[name]]


def _algorithms(s: dict) -> list[tuple[str, str, float | None, str]]:
    """``(label, kind, param, divergence)`` of every algorithm of the sweep."""
    algs = [("PEVI", "PEVI", None, "none")]
    for div in s["divergences"]:
        tag = "chi2" if div == "chi2" else div.upper()
        algs += [(f"R2PVI-{tag} lam={lam:g}", "R2PVI", float(lam), div) for lam in s["lams"]]
    algs += [(f"DRPVI rho={rho:g}", "DRPVI", float(rho), "tv") for rho in s["rhos"]]
    return algs


def _expert(task: str):
    from ...envs import experts

    return getattr(experts, TASKS[task]["expert"])()


def _test_env(task: str, perturbation: str, level: float):
    from ...envs.perturbations import make_perturbed

    spec = TASKS[task]
    if perturbation == "action_noise":
        return make_perturbed(spec["env_id"], action_noise=level)
    return make_perturbed(spec["env_id"], **{perturbation: spec["nominal"][perturbation]
                                             * (1.0 + level)})


def _seed_int(seq: np.random.SeedSequence) -> int:
    return int(seq.generate_state(1, np.uint32)[0])


def replication(seq, *, task, replication, settings):
    """One dataset: collect, build features, fit every algorithm, test every policy.

    Returns rows with ``quantity = "average return"`` (one per algorithm x perturbation x
    level; ``value`` the mean over the test episodes and ``stderr`` its standard error) and
    ``quantity = "fit time"`` (one per algorithm, seconds).
    """
    import gymnasium

    from ...data import OfflineDataset
    from ...data.episodes import episode_observations
    from ...envs import EpsilonGreedy, collect_episodes
    from ...evaluation import evaluate_policy
    from ...features import NormalizedRBF, cross_actions

    s = settings
    spec = TASKS[task]
    H, A = s["horizon"], spec["n_actions"]
    data_seq, test_seq = seq.spawn(2)
    expert = _expert(task)
    behaviour = EpsilonGreedy(expert, s["epsilon"], A)
    episodes = collect_episodes(gymnasium.make(spec["env_id"]), behaviour, s["trajectories"],
                                seed=data_seq, max_steps=H, n_envs=min(s["trajectories"], 50))
    rbf = NormalizedRBF(n_centers=s["centers"], bandwidth=s["bandwidth"] or None)
    fmap = cross_actions(rbf.fit(episode_observations(episodes)), A)
    data = OfflineDataset.from_episodes(episodes, fmap, A, horizon=H,
                                        reward_offset=spec["reward_offset"])
    d = data.n_features
    common = {"beta": s["beta"], "gamma": s["gamma"], "penalty": s["penalty"],
              "r_max": spec["r_max"]}
    base = {"replication": replication, "task": task, "trajectories": s["trajectories"],
            "n_features": d, "data_return": float(np.mean([e.total_reward for e in episodes]))}
    rows, policies = [], []
    for label, kind, param, divergence in _algorithms(s):
        est = make_estimator(kind, param, divergence=divergence, **common)
        est.set_params(time_homogeneous=bool(s["time_homogeneous"]))  # not "auto"
        t0 = time.perf_counter()
        est.fit(data)
        seconds = time.perf_counter() - t0
        rows.append({**base, "algorithm": label, "kind": kind, "divergence": divergence,
                     "param": param, "perturbation": "none", "level": 0.0,
                     "quantity": "fit time", "unit": "s", "value": seconds,
                     "stderr": float("nan")})
        policies.append((label, kind, param, divergence, est.as_policy(fmap)))
    if s["references"]:
        policies.append(("expert", "reference", None, "none", expert))
        policies.append((f"behaviour (eps={s['epsilon']:g})", "reference", s["epsilon"],
                         "none", behaviour))
    levels = _perturbations(task, s)
    seeds = [_seed_int(c) for c in test_seq.spawn(len(levels))]
    n_test = s["test_episodes"]
    # Returns are measured in the environment, in its own reward scale (no offset).
    for (perturbation, level), seed in zip(levels, seeds, strict=True):
        env = _test_env(task, perturbation, level)
        for label, kind, param, divergence, policy in policies:
            mean, se = evaluate_policy(env, policy, n_test, seed=seed, max_steps=H,
                                       n_envs=n_test)
            rows.append({**base, "algorithm": label, "kind": kind, "divergence": divergence,
                         "param": param, "perturbation": perturbation, "level": level,
                         "quantity": "average return", "unit": "return",
                         "value": mean, "stderr": se})
    return rows


def _tasks_for(task):
    def tasks(s):
        _check_settings(task, s)
        return [Task(replication, {"task": task, "replication": r, "settings": s},
                     label=f"{task} rep={r}") for r in range(s["replications"])]
    return tasks


def _check_settings(task: str, s: dict) -> None:
    for key in ("horizon", "trajectories", "replications", "centers"):
        if s[key] < 1:
            raise ValueError(f"{task}: setting {key!r} must be >= 1, got {s[key]}")
    if s["test_episodes"] < 2:
        raise ValueError(f"{task}: test_episodes must be >= 2 (a standard error needs two), "
                         f"got {s['test_episodes']}")
    if not 0.0 <= s["epsilon"] <= 1.0:
        raise ValueError(f"{task}: epsilon must be in [0, 1], got {s['epsilon']}")
    for p in s["action_noise"]:
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"{task}: action_noise levels must be in [0, 1], got {p}")
    for name in TASKS[task]["nominal"]:
        for p in s[name]:
            if name not in ("gravity",) and p <= -1.0:
                raise ValueError(f"{task}: {name} levels p must be > -1 (the parameter is "
                                 f"multiplied by 1 + p), got {p}")


# --------------------------------------------------------------------------- summaries
def _mean_se(values: list[float]) -> tuple[float, float]:
    n = len(values)
    mean = sum(values) / n
    if n < 2:
        return mean, float("nan")
    var = sum((v - mean) ** 2 for v in values) / (n - 1)
    return mean, math.sqrt(var / n)


def summary_by_level(rows) -> list[dict]:
    """Mean over replications and its standard error, per algorithm x perturbation x level.

    With one replication, ``stderr`` is the test-episode standard error of that replication.
    """
    groups: dict = defaultdict(list)
    for r in rows:
        if r.get("quantity") == "average return":
            groups[(r["algorithm"], r["perturbation"], r["level"])].append(r)
    out = []
    for (alg, pert, level), rs in groups.items():
        mean, se = _mean_se([r["value"] for r in rs])
        if len(rs) == 1:
            se = rs[0]["stderr"]
        out.append({"algorithm": alg, "kind": rs[0]["kind"],
                    "divergence": rs[0]["divergence"], "perturbation": pert,
                    "level": level, "mean": mean, "stderr": se, "n": len(rs)})
    return out


def _fit_times(rows) -> dict[str, float]:
    groups: dict = defaultdict(list)
    for r in rows:
        if r.get("quantity") == "fit time":
            groups[r["algorithm"]].append(r["value"])
    return {k: sum(v) / len(v) for k, v in groups.items()}


def _table(task):
    def table(rows, s):
        summ = summary_by_level(rows)
        algs = list(dict.fromkeys(r["algorithm"] for r in summ))
        perts = list(dict.fromkeys(r["perturbation"] for r in summ))
        nominal = {r["algorithm"]: r for r in summ
                   if r["perturbation"] == perts[0] and r["level"] == 0.0}
        by = defaultdict(list)
        for r in summ:
            by[(r["algorithm"], r["perturbation"])].append(r["mean"])
        fit = _fit_times(rows)
        head = ["algorithm", "nominal"] + [f"{p} (avg)" for p in perts] + ["fit s"]
        lines = []
        for alg in algs:
            nom = nominal.get(alg)
            cells = [alg, "-" if nom is None else f"{nom['mean']:.1f}±{nom['stderr']:.1f}"]
            cells += [f"{np.mean(by[(alg, p)]):.1f}" for p in perts]
            cells.append(f"{fit[alg]:.2f}" if alg in fit else "-")
            lines.append(cells)
        widths = [max(len(str(c)) for c in col) for col in zip(head, *lines, strict=True)]
        fmt = lambda cells: "  ".join(f"{c:<{w}}" if i == 0 else f"{c:>{w}}"  # noqa: E731
                                      for i, (c, w) in enumerate(zip(cells, widths,
                                                                     strict=True)))
        n_rep = len({r["replication"] for r in rows})
        title = (f"{task}: average return (nominal: mean±s.e. over {n_rep} dataset(s); "
                 "'avg': mean over the perturbation's levels), fit time in seconds")
        return "\n".join([title, fmt(head)] + [fmt(c) for c in lines])
    return table


# --------------------------------------------------------------------------- plot
_FAMILY_COLORS = {"PEVI": "black", "tv": "tab:blue", "kl": "tab:green", "chi2": "tab:purple",
                  "DRPVI": "tab:red", "expert": "tab:gray", "behaviour": "tab:olive"}
_XLABEL = {"action_noise": "probability p of a random action"}


def _style(row, rank: dict) -> dict:
    alg = row["algorithm"]
    if row["kind"] == "reference":
        key = "expert" if alg == "expert" else "behaviour"
        return {"color": _FAMILY_COLORS[key], "linestyle": ":", "marker": ""}
    if row["kind"] == "PEVI":
        return {"color": "black", "linestyle": "-", "marker": "o", "linewidth": 2.0}
    fam = "DRPVI" if row["kind"] == "DRPVI" else row["divergence"]
    dashes = ["-", "--", "-.", (0, (1, 1)), (0, (3, 1, 1, 1))]
    markers = ["s", "^", "v", "D", "x"]
    i = rank.get(alg, 0)
    return {"color": _FAMILY_COLORS.get(fam, "tab:brown"), "linestyle": dashes[i % 5],
            "marker": markers[i % 5]}


def _plot(task):
    def plot(rows, s):
        from ..plotting import _pyplot

        plt = _pyplot()
        summ = summary_by_level(rows)
        perts = list(dict.fromkeys(r["perturbation"] for r in summ))
        algs = list(dict.fromkeys(r["algorithm"] for r in summ))
        first = {r["algorithm"]: r for r in summ}
        families = defaultdict(list)
        for a in algs:
            r = first[a]
            families[r["divergence"] if r["kind"] == "R2PVI" else r["kind"]].append(a)
        rank = {a: i for fam in families.values() for i, a in enumerate(fam)}
        ncols = min(len(perts), 4)
        nrows = -(-len(perts) // ncols)
        fig, axes = plt.subplots(nrows, ncols, figsize=(4.0 * ncols, 3.4 * nrows + 1.2),
                                 squeeze=False)
        n_rep = len({r["replication"] for r in rows})
        for ax, pert in zip(axes.flat, perts, strict=False):
            for alg in algs:
                pts = sorted((r for r in summ if r["algorithm"] == alg
                              and r["perturbation"] == pert), key=lambda r: r["level"])
                if not pts:
                    continue
                x = [r["level"] for r in pts]
                y = [r["mean"] for r in pts]
                e = [0.0 if not np.isfinite(r["stderr"]) else r["stderr"] for r in pts]
                style = {"linewidth": 1.2, **_style(first[alg], rank)}
                ax.errorbar(x, y, yerr=e, label=alg, markersize=3.5, capsize=2, **style)
            ax.set_title(pert if pert == "action_noise" else f"{pert} x (1 + p)", fontsize=10)
            ax.set_xlabel(_XLABEL.get(pert, "p"))
            ax.set_ylabel("average return")
            ax.grid(alpha=0.3)
        for ax in list(axes.flat)[len(perts):]:
            ax.set_visible(False)
        handles, labels = axes.flat[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 5), fontsize=7,
                   frameon=False)
        band = ("error bars: standard error across datasets" if n_rep > 1 else
                "error bars: standard error over test episodes (one dataset)")
        fig.suptitle(f"{task}: return under perturbed dynamics ({s['trajectories']} episodes of "
                     f"an eps={s['epsilon']:g}-greedy expert, H={s['horizon']}; {band})",
                     fontsize=10)
        fig.tight_layout(rect=(0, 0.06 + 0.03 * math.ceil(len(labels) / 5), 1, 0.95))
        return fig
    return plot



MOUNTAINCAR = Figure(
    "mountaincar",
    "Classic-control benchmark, second environment: the same algorithms learned from "
    "eps-greedy energy-pumping data on nominal MountainCar, tested under perturbed force, "
    "gravity and random actions.",
    MOUNTAINCAR_DEFAULTS, _tasks_for("mountaincar"), _plot("mountaincar"),
    _table("mountaincar"),
)
