"""Figures 1(a)-(c): the simulated linear MDP of the paper's Appendix A.1."""

from __future__ import annotations

import numpy as np

from ...envs import SimulatedLinearMDP
from ...envs.policies import policy_table
from ..results import format_table, summarize
from ..runner import Task
from .common import Figure, evaluate, make_estimator, plot_series, spread_note

__all__ = ["FIG1A", "FIG1B", "FIG1C"]

Q_GRID = [round(0.1 * i, 1) for i in range(11)]


def _div(name: str) -> str:
    """Display name of a divergence: TV, KL, chi2."""
    return name if name == "chi2" else name.upper()

# Settings of the paper's Appendix A (Table "Hyper-parameters") shared by fig1a-c.
LINEAR_MDP_DEFAULTS = {
    "xi_norms": [0.3, 0.2, 0.1],
    "delta": 0.3,
    "trajectories": 100,
    "beta": 1.0,
    "gamma": 0.1,
    "replications": 20,
    "evaluation": "exact",
    "test_episodes": 100,
    "penalty": "l1",
}


def linear_mdp_replication(seq, *, xi_norm, replication, algorithms, qs, settings):
    """One replication: collect K trajectories, fit every algorithm, evaluate on each q.

    ``algorithms`` is a list of ``(label, kind, param, divergence)``; rows carry the label,
    kind, parameter, xi_norm, q and the (exact or Monte Carlo) average return.
    """
    rng = np.random.default_rng(seq)
    env = SimulatedLinearMDP(delta=settings["delta"], xi_norm=xi_norm)
    data = env.collect(settings["trajectories"], seed=rng)
    tests = [(q, env.perturbed(q)) for q in qs]
    rows = []
    for label, kind, param, divergence in algorithms:
        if kind == "DRPVI" and param is not None:
            rho = np.zeros((env.horizon, env.n_features))
            rho[0, 3] = param  # the paper's experiment: factor 4 at the first step only
            param_value = rho
        else:
            param_value = param
        est = make_estimator(kind, param_value, divergence=divergence, beta=settings["beta"],
                             gamma=settings["gamma"], penalty=settings["penalty"],
                             reward_weights=env.theta, r_max=env.r_max).fit(data)
        # The greedy action table, once: the test environments differ from env only in
        # their factors (same features and known values), so it is the same in each.
        policy = policy_table(env, est)
        for q, test_env in tests:
            value = evaluate(test_env, policy, settings["evaluation"],
                             settings["test_episodes"], rng)
            rows.append({"xi_norm": xi_norm, "replication": replication, "algorithm": label,
                         "kind": kind, "divergence": divergence, "param": param, "q": q,
                         "value": value})
    return rows


def exact_optimum_rows(seq, *, xi_norm, qs, divergences, lam, settings):
    """The exact robust-regularized optimal policy (true factors) and the nominal optimal
    policy, evaluated on every q: no data, no randomness."""
    from ...evaluation import expected_return, optimal_policy

    env = SimulatedLinearMDP(delta=settings["delta"], xi_norm=xi_norm)
    policies = [("nominal optimum (exact)", optimal_policy(env), "none")]
    for div in divergences:
        policies.append((f"{div.upper() if div != 'chi2' else 'chi2'} robust optimum (exact)",
                         optimal_policy(env, div, lam), div))
    rows = []
    for label, policy, div in policies:
        for q in qs:
            rows.append({"xi_norm": xi_norm, "replication": 0, "algorithm": label,
                         "kind": "exact", "divergence": div, "param": lam, "q": q,
                         "value": float(expected_return(env.perturbed(q), policy)),
                         "action_x1": int(policy[0, 0])})
    return rows


def _replicated(settings, algorithms, qs, extra_tasks=()):
    tasks = []
    for xi_norm in settings["xi_norms"]:
        for r in range(settings["replications"]):
            tasks.append(Task(linear_mdp_replication,
                              {"xi_norm": xi_norm, "replication": r, "algorithms": algorithms,
                               "qs": qs, "settings": settings},
                              label=f"xi={xi_norm} rep={r}"))
    return tasks + list(extra_tasks)


def _merge_exact_rows(rows):
    """Exact optima with identical values on every q share one row (as in the plot)."""
    from ..plotting import exact_groups

    exact: dict = {}
    for r in rows:
        if r["kind"] == "exact":
            x, v, _ = exact.setdefault(r["algorithm"], ([], [], None))
            x.append(r["q"])
            v.append(r["value"])
    rename = {old: new for new, olds in exact_groups(exact).items() for old in olds}
    out, seen = [], set()
    for r in rows:
        if r["kind"] == "exact":
            r = dict(r, algorithm=rename[r["algorithm"]])
            if (r["algorithm"], r["q"]) in seen:
                continue
            seen.add((r["algorithm"], r["q"]))
        out.append(r)
    return out
def _shown_columns(values, preferred, limit):
    """The q columns of a summary table: every q when there are at most ``limit``, else the
    ``preferred`` ones that were run, else ``limit`` evenly spaced ones (never none)."""
    values = sorted(set(values))
    if len(values) <= limit:
        return values
    chosen = [v for v in preferred if v in values]
    if len(chosen) >= 2:
        return chosen
    idx = np.unique(np.linspace(0, len(values) - 1, limit).round().astype(int))
    return [values[i] for i in idx]


def _table_by_q(rows, settings, columns=(0.0, 0.2, 0.4, 0.6, 0.8, 1.0)):
    out = []
    columns = _shown_columns(settings["qs"], columns, len(columns))
    for xi_norm in settings["xi_norms"]:
        sub = [r for r in _merge_exact_rows([r for r in rows if r["xi_norm"] == xi_norm])
               if r["q"] in columns]  # merged on every q, shown on a few
        out.append(f"||xi||_1 = {xi_norm}: average return (mean±std over replications) by q")
        out.append(format_table(summarize(sub, ["algorithm", "q"]), "algorithm", "q"))
    return "\n".join(out)


# --------------------------------------------------------------------------- fig1a
FIG1A_DEFAULTS = {**LINEAR_MDP_DEFAULTS, "lam": 0.1, "qs": Q_GRID,
                  "divergences": ["tv", "kl", "chi2"], "exact_optimum": True}


def _fig1a_tasks(s):
    algorithms = [("PEVI", "PEVI", None, "none")] + [
        (f"R2PVI-{d.upper() if d != 'chi2' else 'chi2'}", "R2PVI", s["lam"], d)
        for d in s["divergences"]
    ]
    extra = []
    if s["exact_optimum"]:
        extra = [Task(exact_optimum_rows, {"xi_norm": x, "qs": s["qs"],
                                           "divergences": s["divergences"], "lam": s["lam"],
                                           "settings": s}, label=f"exact xi={x}")
                 for x in s["xi_norms"]]
    return _replicated(s, algorithms, s["qs"], extra)


def _fig1a_plot(rows, s):
    return plot_series(rows, "xi_norm", "algorithm", "q", xlabel="perturbation q",
                       ylabel="average return", panel_fmt="||xi||_1 = {}",
                       title=f"Simulated linear MDP, lam = {s['lam']}",
                       spread=spread_note(s["replications"]) + "; dashed: exact optima")


FIG1A = Figure(
    "fig1a",
    "PEVI beats R2PVI when the perturbation is small but falls below it under a large shift.",
    FIG1A_DEFAULTS, _fig1a_tasks, _fig1a_plot, _table_by_q, plot_cost=2.0,
)

# --------------------------------------------------------------------------- fig1b
FIG1B_DEFAULTS = {**LINEAR_MDP_DEFAULTS, "lams": [0.05, 0.1, 0.3, 1.0, 3.0], "qs": Q_GRID,
                  "divergences": ["tv", "kl", "chi2"]}


def _fig1b_tasks(s):
    algorithms = [(f"{d}, lam={lam}", "R2PVI", lam, d) for d in s["divergences"]
                  for lam in s["lams"]]
    return _replicated(s, algorithms, s["qs"])


def _fig1b_plot(rows, s):
    rows = [dict(r, panel=f"R2PVI-{_div(r['divergence'])}, ||xi||_1 = {r['xi_norm']}",
                 series=f"lam = {r['param']}") for r in rows]
    return plot_series(rows, "panel", "series", "q", xlabel="perturbation q",
                       ylabel="average return", title="R2PVI: smaller lam, more robust",
                       ncols=len(s["divergences"]), spread=spread_note(s["replications"]))


def _fig1b_table(rows, s):
    columns = _shown_columns(s["qs"], (0.0, 0.5, 1.0), 3)
    sub = [dict(r, setting=f"xi={r['xi_norm']} {r['algorithm']}") for r in rows
           if r["q"] in columns]
    return ("average return by q (mean±std over replications)\n"
            + format_table(summarize(sub, ["setting", "q"]), "setting", "q"))


FIG1B = Figure(
    "fig1b",
    "A smaller regularizer lam makes R2PVI more robust to the perturbation.",
    FIG1B_DEFAULTS, _fig1b_tasks, _fig1b_plot, _fig1b_table, plot_cost=5.0,
)

# --------------------------------------------------------------------------- fig1c
FIG1C_DEFAULTS = {**LINEAR_MDP_DEFAULTS, "q": 0.9,
                  "rhos": [0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0],
                  "lams": [0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 2.0],
                  "divergences": ["tv", "kl", "chi2"]}


def _fig1c_tasks(s):
    algorithms = [("DRPVI (x = rho)", "DRPVI", rho, "tv") for rho in s["rhos"]]
    algorithms += [(f"R2PVI-{_div(d)} (x = lam)", "R2PVI", lam, d) for d in s["divergences"]
                   for lam in s["lams"]]
    return _replicated(s, algorithms, [s["q"]])


def _fig1c_plot(rows, s):
    # rho and lam span two decades; rho = 0 (DRPVI = PEVI-like) must stay visible: a log axis
    # above the smallest positive grid value, linear below it.
    values = sorted({float(v) for v in list(s["rhos"]) + list(s["lams"])})
    positive = [v for v in values if v > 0]
    xscale = ("symlog", min(positive)) if values and values[0] == 0 else "log"
    ticks = [v for v in (0, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10, 20)
             if (v > 0 or values[0] == 0) and values[0] <= v <= values[-1]]
    return plot_series(rows, "xi_norm", "algorithm", "param",
                       xlabel="rho (DRPVI) / lam (R2PVI), log axis",
                       ylabel=f"average return at q = {s['q']}", panel_fmt="||xi||_1 = {}",
                       title="Fixed target q: DRPVI against rho, R2PVI against lam",
                       xscale=xscale, xticks=ticks, spread=spread_note(s["replications"]))


def _fig1c_table(rows, s):
    out = []
    for xi_norm in s["xi_norms"]:
        sub = [r for r in rows if r["xi_norm"] == xi_norm]
        out.append(f"||xi||_1 = {xi_norm}, q = {s['q']}: average return by rho / lam")
        out.append(format_table(summarize(sub, ["algorithm", "param"]), "algorithm", "param"))
    return "\n".join(out)


FIG1C = Figure(
    "fig1c",
    "At a fixed target q = 0.9, lam in R2PVI plays the role of 1/rho in DRPVI: the ranges of "
    "the average return are about the same and the trends are opposite.",
    FIG1C_DEFAULTS, _fig1c_tasks, _fig1c_plot, _fig1c_table, plot_cost=2.0,
)
