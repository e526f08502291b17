"""Figure 1(d), the variance-aware comparison and Figures 2(a)-(b): the American put option."""

from __future__ import annotations

import time

import numpy as np

from ...envs import AmericanPutOption
from ...evaluation import option_value
from ..plotting import line_panels
from ..results import format_table, summarize
from ..runner import Task
from .common import Figure, evaluate, make_estimator, plot_series, series_panels, spread_note

__all__ = ["FIG1D", "FIG_VA", "FIG2A", "FIG2B"]

PUT_DEFAULTS = {
    "p0": 0.5,
    "horizon": 20,
    "features": 30,
    "strike": 100.0,
    "anchor_span": 60.0,
    "trajectories": 100,
    "beta": 0.1,
    "gamma": 1.0,
    "penalty": "l1",
    "replications": 10,
    "evaluation": "exact",
    "test_episodes": 100,
    "price_up": [0.2, 0.4, 0.6, 0.8, 1.0],
}


def _div(name: str) -> str:
    return name if name == "chi2" else name.upper()


def _env(s, d=None):
    return AmericanPutOption(p0=s["p0"], d=d or s["features"], H=s["horizon"],
                             strike=s["strike"], anchor_span=s["anchor_span"])


def _common(s, env):
    # Holding pays 0: the reward weights are known zeros. Q is clipped at (H - h) r_max with
    # r_max the largest payoff the option can reach.
    return {"beta": s["beta"], "gamma": s["gamma"], "penalty": s["penalty"],
            "reward_weights": np.zeros((env.horizon, env.n_features)), "r_max": env.r_max}


def put_replication(seq, *, replication, algorithms, settings):
    """Collect N always-hold trajectories at p0, fit every algorithm, evaluate at each
    price-up probability (exactly on the binomial lattice, or by Monte Carlo)."""
    rng = np.random.default_rng(seq)
    env = _env(settings)
    data = env.collect(settings["trajectories"], seed=rng)
    price_up = settings["price_up"]
    rows = []
    for label, kind, param, divergence in algorithms:
        est = make_estimator(kind, param, divergence=divergence, **_common(settings, env))
        est.fit(data)
        if settings["evaluation"] == "exact":
            # One lattice pass for every price-up probability: the policy's switch prices
            # do not depend on it.
            values = [float(v) for v in option_value(env, est, price_up=price_up)]
        else:
            values = [evaluate(env.perturbed(p), est, settings["evaluation"],
                               settings["test_episodes"], rng) for p in price_up]
        for p, value in zip(price_up, values, strict=True):
            rows.append({"replication": replication, "algorithm": label, "kind": kind,
                         "divergence": divergence, "param": param, "price_up": p,
                         "value": value})
    return rows


def _put_tasks(algorithms):
    def tasks(s):
        return [Task(put_replication, {"replication": r, "algorithms": algorithms(s),
                                       "settings": s}, label=f"rep={r}")
                for r in range(s["replications"])]
    return tasks


def _put_plot(title):
    def plot(rows, s):
        rows = [dict(r, panel="American put option") for r in rows]
        return plot_series(rows, "panel", "algorithm", "price_up",
                           xlabel="price-up probability", ylabel="average return",
                           title=title, spread=spread_note(s["replications"]))
    return plot


def _put_table(rows, s):
    return ("average return by price-up probability (mean±std over replications)\n"
            + format_table(summarize(rows, ["algorithm", "price_up"]), "algorithm", "price_up"))


# --------------------------------------------------------------------------- fig1d
FIG1D_DEFAULTS = {**PUT_DEFAULTS, "lams": [1.0, 3.0, 5.0], "rhos": [0.2, 0.1, 0.025],
                  "divergence": "tv"}


def _fig1d_algorithms(s):
    algs = [("PEVI", "PEVI", None, "none")]
    algs += [(f"R2PVI-{_div(s['divergence'])} lam={lam}", "R2PVI", lam, s["divergence"])
             for lam in s["lams"]]
    algs += [(f"DRPVI rho={rho}", "DRPVI", rho, "tv") for rho in s["rhos"]]
    return algs


FIG1D = Figure(
    "fig1d",
    "R2PVI is robust to shifts of the price-up probability and matches DRPVI for suitable "
    "lam and rho.",
    FIG1D_DEFAULTS, _put_tasks(_fig1d_algorithms),
    _put_plot("American put option: PEVI, R2PVI and DRPVI"), _put_table,
)

# --------------------------------------------------------------------------- va
FIG_VA_DEFAULTS = {**PUT_DEFAULTS, "lam": 1.0, "rho": 0.2}


def _va_algorithms(s):
    return [
        ("DRPVI", "DRPVI", s["rho"], "tv"),
        ("VA-DRPVI", "VA-DRPVI", s["rho"], "tv"),
        ("R2PVI-TV", "R2PVI", s["lam"], "tv"),
        ("VA-R2PVI-TV", "VA-R2PVI-TV", s["lam"], "tv"),
    ]


FIG_VA = Figure(
    "va",
    "Variance-aware weighting (VA-DRPVI, rho = 0.2; VA-R2PVI-TV, lam = 1) on the American "
    "put option, beside the unweighted algorithms.",
    FIG_VA_DEFAULTS, _put_tasks(_va_algorithms),
    _put_plot("Variance-aware variants on the American put option"), _put_table,
)

# --------------------------------------------------------------------------- timing
TIMING_ALGORITHMS = [
    ("PEVI", "PEVI", None, "none"),
    ("R2PVI-TV", "R2PVI", 1.0, "tv"),
    ("R2PVI-KL", "R2PVI", 1.0, "kl"),
    ("R2PVI-chi2", "R2PVI", 1.0, "chi2"),
    ("DRPVI", "DRPVI", 0.1, "tv"),
    ("DRVI-L", "DRVI-L", 0.1, "kl"),
]


def timing_task(seq, *, trajectories, features, repeats, settings):
    """Fit every algorithm ``repeats`` times on one put-option dataset; one row per timed fit
    holds its wall-clock seconds (after one untimed warm-up fit).

    BLAS runs with ``settings["blas_threads"]`` threads (default 1, 0 leaves it alone): on a
    shared 2-core machine, multi-threaded OpenBLAS busy-waits when the cores are taken and
    turns millisecond fits into seconds; one thread gives every algorithm the same, stable
    conditions.
    """
    threads = settings.get("blas_threads", 1)
    if threads:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=threads, user_api="blas"):
            return _timed_fits(seq, trajectories, features, repeats, settings)
    return _timed_fits(seq, trajectories, features, repeats, settings)


def _timed_fits(seq, trajectories, features, repeats, settings):
    rng = np.random.default_rng(seq)
    env = _env(settings, d=features)
    data = env.collect(trajectories, seed=rng)
    rows = []
    for label, kind, param, divergence in TIMING_ALGORITHMS:
        est = make_estimator(kind, param, divergence=divergence, **_common(settings, env))
        est.fit(data)
        for repeat in range(repeats):  # one tidy row per timed fit
            t0 = time.perf_counter()
            est.fit(data)
            rows.append({"algorithm": label, "trajectories": trajectories,
                         "features": features, "repeat": repeat,
                         "value": time.perf_counter() - t0})
    return rows


def _timing_figure(name, axis, grid_key, fixed_key, claim):
    defaults = {**{k: PUT_DEFAULTS[k] for k in ("p0", "horizon", "strike", "anchor_span",
                                                  "beta", "gamma", "penalty")},
                "repeats": 5, "blas_threads": 1}
    if axis == "trajectories":
        defaults.update({grid_key: [1000, 5000, 10000], fixed_key: 30})
    else:
        defaults.update({grid_key: [30, 60, 120], fixed_key: 1000})

    def tasks(s):
        out = []
        for value in s[grid_key]:
            kw = {"trajectories": value, "features": s[fixed_key]} if axis == "trajectories" \
                else {"trajectories": s[fixed_key], "features": value}
            out.append(Task(timing_task, {**kw, "repeats": s["repeats"], "settings": s},
                            label=f"{axis}={value}"))
        return out

    def plot(rows, s):
        panels = series_panels([dict(r, panel="fit time") for r in rows], "panel", "algorithm",
                               axis)
        return line_panels(panels, xlabel="N (trajectories)" if axis == "trajectories"
                           else "d (features)", ylabel="seconds per fit", logy=True,
                           style="bars", title=f"Fit time against "
                           f"{'N' if axis == 'trajectories' else 'd'} (American put option)",
                           spread=spread_note(s["repeats"], "timed fits", "bars"))

    def table(rows, s):
        summary = summarize(rows, ["algorithm", axis])
        what = (f"mean±std over {s['repeats']} timed fits" if s["repeats"] > 1
                else "one timed fit")
        return (f"seconds per fit ({what})\n"
                + format_table(summary, "algorithm", axis, digits=4))

    return Figure(name, claim, defaults, tasks, plot, table, serial=True,
                  quantity="fit time", unit="s")


FIG2A = _timing_figure(
    "fig2a", "trajectories", "trajectories_grid", "features",
    "R2PVI's fit is as cheap as PEVI's and cheaper than DRPVI's and DRVI-L's as N grows.",
)
FIG2B = _timing_figure(
    "fig2b", "features", "features_grid", "trajectories",
    "R2PVI's fit is as cheap as PEVI's and cheaper than DRPVI's and DRVI-L's as d grows.",
)
