"""Theory in practice: suboptimality rates and the instance-dependent bound.

``rates``: exact ``SubOpt(pi_hat, s1, lam)`` of R2PVI-TV/KL/chi^2 against K on a log grid, on
the simulated linear MDP and on the lower-bound hard instance, with the fitted log-log slope
(bootstrap interval) and the theorem's bound ``2 beta * term`` on the same axes.
``bound-check``: how often ``SubOpt <= 2 beta * term`` holds with the theorem's beta, and how
loose it is.

Choices (see docs/theory.md):

- the estimator the theorem is about is R2PVI with ``beta="theory"`` (``gamma = 1``, the
  "l1" penalty, ``r_max = 1``); its SubOpt is what ``bound-check`` checks, and ``rates``
  shows it next to R2PVI with a practical beta (``betas`` setting);
- the uncertainty term is computed with the fitted estimator's Gram matrices (the same for
  every beta and divergence on one dataset);
- simulated linear MDP: the paper's Appendix A.1 model with known reward parameters
  (Assumption 1); hard instance: ``HardInstance.lower_bound_instance(d, H, lam, K, D)``, the
  lower-bound proof's instance *for each K* (``delta = d^{3/2} / sqrt(2K)``), with fresh
  signs ``xi`` per replication, unknown to the learner (rewards estimated from
  ``N(r, 1)`` samples), so that it is as hard as the proof says;
- ``s1`` is state 0 in both (x1, the fixed start of the simulated MDP; the good state s1 of
  the hard instance).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ...algorithms import R2PVI
from ...envs import HardInstance, SimulatedLinearMDP
from ...evaluation import suboptimality
from ...theory import loglog_slope, theoretical_beta, uncertainty_term
from ..runner import Task
from .common import Figure, spread_note

__all__ = ["RATES", "BOUND_CHECK", "theory_replication"]

ENV_LABELS = {"simulated": "simulated linear MDP", "hard": "hard instance (lower bound)"}
_DIV_LABELS = {"tv": "TV", "kl": "KL", "chi2": "chi2"}

THEORY_DEFAULTS = {
    "envs": ["simulated", "hard"],
    "divergences": ["tv", "kl", "chi2"],
    "lam": 1.0,
    "delta": 0.05,  # the theorem's confidence
    "state": 0,  # s1
    "xi_norm": 0.2,  # simulated linear MDP
    "mdp_delta": 0.3,
    "hard_d": 2,  # hard instance: d action bits (d + 2 features), horizon H
    "hard_H": 3,
}


def _beta_label(beta) -> str:
    return "theory" if isinstance(beta, str) else f"{float(beta):g}"


def _instances(env_name, K, divergences, settings, rng):
    """``{divergence: (env, dataset, reward_weights)}`` for one replication."""
    if env_name == "simulated":
        env = SimulatedLinearMDP(delta=settings["mdp_delta"], xi_norm=settings["xi_norm"])
        data = env.collect(K, seed=rng)
        return {div: (env, data, env.theta) for div in divergences}
    if env_name == "hard":
        out = {}
        for div in divergences:
            with warnings.catch_warnings():  # the lemma's K condition: recorded in the rows
                warnings.simplefilter("ignore", UserWarning)
                env = HardInstance.lower_bound_instance(
                    settings["hard_d"], settings["hard_H"], settings["lam"], K, div, seed=rng)
            out[div] = (env, env.collect(K, policy="behavior", seed=rng), None)
        return out
    raise ValueError(f"unknown environment {env_name!r}; use 'simulated' or 'hard'")


def theory_replication(seq, *, env_name, K, replication, settings):
    """One replication: a dataset of K trajectories, R2PVI for every divergence and beta.

    Rows carry the exact ``SubOpt(pi_hat, s1, lam)`` (``value``), the uncertainty term at
    s1, the theorem's beta and bound ``2 beta * term``, whether the bound holds and the
    ratio ``SubOpt / bound``.
    """
    rng = np.random.default_rng(seq)
    lam, delta, state = settings["lam"], settings["delta"], settings["state"]
    rows = []
    for div, (env, data, rw) in _instances(env_name, K, settings["divergences"], settings,
                                           rng).items():
        beta_th = theoretical_beta(div, env.n_features, env.horizon, K, lam, delta)
        term = None
        for beta in settings["betas"]:
            est = R2PVI(div, lam, beta=beta, gamma=1.0, delta=delta, reward_weights=rw).fit(data)
            if term is None:  # the Gram matrices do not depend on beta
                term = uncertainty_term(env, est, div, lam, state=state)
            gap = suboptimality(env, est, div, lam, state=state)
            bound = 2.0 * beta_th * term
            rows.append({
                "env": env_name, "divergence": div, "K": K, "replication": replication,
                "beta": _beta_label(beta), "beta_used": est.beta_, "value": gap,
                "term": term, "beta_theory": beta_th, "bound": bound,
                "holds": bool(gap <= bound), "ratio": gap / bound if bound > 0 else math.nan,
                "lemma_condition": _lemma_condition(env, K, lam),
            })
    return rows


def _lemma_condition(env, K, lam) -> bool:
    """The hard-instance lemma's ``K > d^3 H^2 / (2 lam^2)`` (True for other models)."""
    if not isinstance(env, HardInstance):
        return True
    return bool(K > env.d**3 * env.horizon**2 / (2.0 * lam**2))


def _tasks(s):
    tasks = []
    for env_name in s["envs"]:
        for K in s["trajectories"]:
            for r in range(s["replications"]):
                # a task's time grows about linearly in K (measured: ~0.2 s at K = 100,
                # ~10-20 s at K = 100,000): weight the progress bar and its ETA by it
                tasks.append(Task(theory_replication,
                                  {"env_name": env_name, "K": int(K), "replication": r,
                                   "settings": s},
                                  label=f"{env_name} K={K} rep={r}", cost=1.0 + K / 1000))
    return tasks


def _groups(rows, keys):
    out: dict = {}
    for r in rows:
        out.setdefault(tuple(r[k] for k in keys), []).append(r)
    return out


def _by_size(rows, value="value"):
    """``(sizes, [values at each size])`` sorted by K."""
    sizes = sorted({r["K"] for r in rows})
    return sizes, [np.array([r[value] for r in rows if r["K"] == k]) for k in sizes]


def _slope(rows, s, value="value"):
    sizes, samples = _by_size(rows, value)
    return loglog_slope(sizes, samples, n_boot=s["bootstrap"], seed=s["bootstrap_seed"])


def _verdict(fit, n_sizes) -> str:
    if n_sizes < 3:
        return "needs >= 3 sizes"
    if not math.isfinite(fit.slope):
        return "no slope (SubOpt = 0)"
    if math.isfinite(fit.lo) and fit.contains(-0.5):
        return "-1/2 in CI"
    if abs(fit.slope + 0.5) <= 0.1:
        return "near -1/2"
    return "flatter than -1/2" if fit.slope > -0.5 else "steeper than -1/2"


def _signed(x: float) -> str:
    return f"{round(x, 2) + 0.0:+.2f}" if math.isfinite(x) else "n/a"  # no "-0.00"


def _fmt_fit(fit) -> str:
    if not math.isfinite(fit.slope):
        return "n/a"
    ci = "" if not math.isfinite(fit.lo) else f" [{_signed(fit.lo)}, {_signed(fit.hi)}]"
    return f"{_signed(fit.slope)}{ci}"


# --------------------------------------------------------------------------- rates
RATES_DEFAULTS = {
    **THEORY_DEFAULTS,
    "trajectories": [100, 316, 1000, 3162, 10000, 31623, 100000],
    "replications": 20,
    "betas": ["theory", 1.0],
    "bootstrap": 1000,
    "bootstrap_seed": 0,
}


def _rates_plot(rows, s):
    from ..plotting import _pyplot, series_style

    plt = _pyplot()
    envs = [e for e in s["envs"] if any(r["env"] == e for r in rows)]
    divs = [d for d in s["divergences"] if any(r["divergence"] == d for r in rows)]
    betas = list(dict.fromkeys(r["beta"] for r in rows))
    fig, axes = plt.subplots(len(envs), len(divs), figsize=(4.4 * len(divs),
                                                            3.5 * len(envs) + 0.9),
                             squeeze=False, constrained_layout=True)
    groups = _groups(rows, ["env", "divergence", "beta"])
    handles: dict = {}
    for i, env_name in enumerate(envs):
        for j, div in enumerate(divs):
            ax = axes[i, j]
            first = None
            slopes = []
            for b, beta in enumerate(betas):
                sub = groups.get((env_name, div, beta), [])
                if not sub:
                    continue
                first = first or sub
                sizes, samples = _by_size(sub)
                means = np.array([x.mean() for x in samples])
                sd = np.array([x.std(ddof=1) if x.size > 1 else 0.0 for x in samples])
                pos = means > 0
                fit = _slope(sub, s)
                slopes.append(f"beta={beta}: {_fmt_fit(fit)}")
                st = series_style(b)
                low = np.minimum(sd, 0.95 * means)  # log axes: keep the bars above 0
                line = ax.errorbar(np.array(sizes)[pos], means[pos],
                                   yerr=[low[pos], sd[pos]], markersize=4, capsize=2,
                                   **st)
                handles.setdefault(f"mean SubOpt, beta = {beta}", line)
                if math.isfinite(fit.slope):
                    k = np.array(fit.sizes)
                    ax.plot(k, 10 ** fit.intercept * k ** fit.slope, linestyle=":",
                                    linewidth=1.2, color=st["color"])
                    handles.setdefault("least-squares fit (log-log)", ax.plot(
                        [], [], linestyle=":", color="gray")[0])
            if first:
                sizes, bounds = _by_size(first, "bound")
                handles.setdefault("bound 2 beta_theory * term", ax.plot(
                    sizes, [x.mean() for x in bounds], marker="s", markersize=3,
                    color="black")[0])
                sizes, terms = _by_size(first, "term")
                handles.setdefault("uncertainty term", ax.plot(
                    sizes, [t.mean() for t in terms], marker="^", markersize=3,
                    color="gray", linestyle="--")[0])
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_title(f"{ENV_LABELS.get(env_name, env_name)}: R2PVI-{_DIV_LABELS[div]}\n"
                         f"slope {'; '.join(slopes)}", fontsize=8)
            ax.set_xlabel("K (trajectories)")
            ax.set_ylabel(f"SubOpt(pi_hat, s1, lam={s['lam']})")
            ax.grid(alpha=0.3, which="both")
    reps = max((r["replication"] for r in rows), default=-1) + 1
    fig.legend(list(handles.values()), list(handles), loc="outside lower center",
               ncols=min(len(handles), 5), fontsize=8, frameon=False, title_fontsize=8,
               title=spread_note(reps, kind="bars") + " (lower bars clipped on the log axis); "
               "slopes with 95% bootstrap intervals")
    fig.suptitle("Exact suboptimality against K", fontsize=11)
    return fig


def _rates_table(rows, s):
    lines = [f"log-log slope of mean SubOpt(pi_hat, s1) in K (95% bootstrap CI), lam = {s['lam']}"]
    header = (f"{'environment':<12} {'div':<5} {'beta':<7} {'slope [CI]':<22} {'verdict':<21} "
              f"{'SubOpt@Kmin':>11} {'SubOpt@Kmax':>11} {'term slope':>11} {'bound@Kmax':>10}")
    lines.append(header)
    for (env_name, div, beta), sub in _groups(rows, ["env", "divergence", "beta"]).items():
        fit = _slope(sub, s)
        term_fit = _slope(sub, s, "term")
        sizes, vals = _by_size(sub)
        _, bounds = _by_size(sub, "bound")
        lines.append(
            f"{env_name:<12} {_DIV_LABELS[div]:<5} {beta:<7} {_fmt_fit(fit):<22} "
            f"{_verdict(fit, len(sizes)):<21} {vals[0].mean():>11.4g} {vals[-1].mean():>11.4g} "
            f"{_signed(term_fit.slope):>11} {bounds[-1].mean():>10.4g}")
    ks = sorted({r["K"] for r in rows})
    reps = max((r["replication"] for r in rows), default=-1) + 1
    lines.append(f"(K = {ks}; {reps} replications; SubOpt = 0 has no log: such K are left out "
                 "of a fit)")
    return "\n".join(lines)


RATES = Figure(
    "rates",
    "On the lower-bound hard instance SubOpt decays like K^-1/2, as the instance-dependent "
    "term does; on the fixed simulated MDP it reaches 0 or a plateau; the bound "
    "2 beta * term with the theorem's beta lies orders of magnitude above.",
    RATES_DEFAULTS, _tasks, _rates_plot, _rates_table,
    notes=["about 2 minutes serially on 2 cores (--jobs 2 halves it)"],
    quantity="SubOpt(pi_hat, s1, lam)", unit="return", plot_cost=7.0,
)


# --------------------------------------------------------------------------- bound-check
BOUND_CHECK_DEFAULTS = {
    **THEORY_DEFAULTS,
    "trajectories": [100, 1000, 10000],
    "replications": 50,
    "betas": ["theory"],
}


def _summary(sub):
    ratios = np.array([r["ratio"] for r in sub])
    held = np.array([r["holds"] for r in sub])
    need = np.array([r["value"] / (2 * r["term"]) if r["term"] > 0 else math.nan
                     for r in sub])
    return held.mean(), held.size, float(np.median(ratios)), float(np.max(ratios)), need


def _bound_check_table(rows, s):
    rows = [r for r in rows if r["beta"] == "theory"]
    lines = [f"SubOpt <= 2 beta * term with the theorem's beta (delta = {s['delta']}: the "
             f"theorem says a fraction >= {1 - s['delta']:g}), lam = {s['lam']}"]
    lines.append(f"{'environment':<12} {'div':<5} {'K':>7} {'holds':>9} {'median ratio':>13} "
                 f"{'max ratio':>10} {'beta_theory':>12} {'median beta needed':>19}")
    groups = _groups(rows, ["env", "divergence", "K"])
    order = {key: i for i, key in enumerate(
        (e, d, k) for e in s["envs"] for d in s["divergences"] for k in s["trajectories"])}
    for (env_name, div, K), sub in sorted(groups.items(),
                                          key=lambda kv: order.get(kv[0], len(order))):
        frac, n, med, mx, need = _summary(sub)
        lines.append(f"{env_name:<12} {_DIV_LABELS[div]:<5} {K:>7} {frac:>6.0%}/{n:<2} "
                     f"{med:>13.3g} {mx:>10.3g} {sub[0]['beta_theory']:>12.4g} "
                     f"{np.nanmedian(need):>19.3g}")
    lines.append("(ratio = SubOpt / bound; beta needed = SubOpt / (2 term), the smallest beta "
                 "for which the bound would hold)")
    return "\n".join(lines)


def _bound_check_plot(rows, s):
    from ..plotting import _pyplot

    plt = _pyplot()
    rows = [r for r in rows if r["beta"] == "theory"]
    envs = [e for e in s["envs"] if any(r["env"] == e for r in rows)]
    fig, axes = plt.subplots(1, len(envs), figsize=(5.0 * len(envs), 3.8), squeeze=False,
                             constrained_layout=True)
    groups = _groups(rows, ["env", "divergence"])
    for ax, env_name in zip(axes[0], envs, strict=True):
        for div in s["divergences"]:
            sub = groups.get((env_name, div), [])
            if not sub:
                continue
            sizes, ratios = _by_size(sub, "ratio")
            frac = [np.mean([r["holds"] for r in sub if r["K"] == k]) for k in sizes]
            pos = [np.where(x > 0, x, np.nan) for x in ratios]
            line = ax.plot(sizes, [np.nanmedian(x) if np.isfinite(x).any() else np.nan
                                   for x in pos],
                           marker="o", markersize=3,
                           label=f"{_DIV_LABELS[div]} (holds: "
                                 + ", ".join(f"{f:.0%}" for f in frac) + ")")[0]
            for k, x in zip(sizes, pos, strict=True):
                x = x[np.isfinite(x)]
                ax.scatter(np.full(x.size, k), x, s=4, alpha=0.3, color=line.get_color())
        ax.axhline(1.0, color="black", linewidth=0.8, label="ratio = 1 (bound tight)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("K (trajectories)")
        ax.set_ylabel("SubOpt / (2 beta_theory * term)")
        ax.set_title(ENV_LABELS.get(env_name, env_name), fontsize=10)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.suptitle("How loose is the instance-dependent bound? (median and replications)",
                 fontsize=11)
    return fig


BOUND_CHECK = Figure(
    "bound-check",
    "With the theorem's beta, SubOpt <= 2 beta * term holds in every replication (the theorem "
    "asks for a fraction >= 1 - delta); the bound is loose by a factor 400 to 110,000.",
    BOUND_CHECK_DEFAULTS, _tasks, _bound_check_plot, _bound_check_table,
    quantity="SubOpt(pi_hat, s1, lam)", unit="return", plot_cost=4.0,
)
