"""Table and plot of ``r2pvi reproduce cartpole`` (rows of
:func:`r2pvi.experiments.figures.cartpole_protocol.replication`)."""

from __future__ import annotations

from collections import defaultdict

import numpy as np

__all__ = ["summary", "sweep_summary", "best_members", "table", "plot"]

SWEEPS = ("force_mag", "gravity", "length")
_COLORS = {"PEVI": "tab:brown", "R2PVI-TV": "tab:blue", "R2PVI-KL": "tab:green",
           "R2PVI-chi2": "tab:purple", "DRPVI": "tab:red", "DRVI-L": "tab:orange"}
_FORM_STYLE = {"pooled": {"linestyle": "-", "marker": "o"},
               "per-step": {"linestyle": (0, (4, 2)), "marker": "x"}}
_REFERENCE_STYLE = {"expert": {"color": "black", "linestyle": (0, (1, 1.5)), "marker": ""},
                    "behaviour": {"color": "0.45", "linestyle": "-.", "marker": ""}}


def _key(r) -> tuple[str, str]:
    return r["estimator"], r["form"]


def _returns(rows) -> list[dict]:
    return [r for r in rows if r.get("quantity") == "average return"]


def _nominal(points: list[dict]) -> float:
    """The unperturbed point's return (force_mag p = 0; with common random numbers every
    sweep's p = 0 point is the same episodes in the same environment)."""
    zero = [r for r in points if r["p"] == 0.0]
    first = [r for r in zero if r["parameter"] == "force_mag"] or zero
    return float(first[0]["value"]) if first else float("nan")


def sweep_summary(rows) -> dict:
    """``{(estimator, form): {"nominal" | sweep: [one value per dataset]}}`` and the family
    of each key, from the return rows: nominal return and each sweep's mean over its
    points, per dataset."""
    per = defaultdict(list)
    for r in _returns(rows):
        per[(_key(r), r["replication"])].append(r)
    out: dict = {}
    for (key, _rep), points in per.items():
        cell = out.setdefault(key, {"family": points[0]["family"], "nominal": []})
        cell["nominal"].append(_nominal(points))
        for sweep in SWEEPS:
            vals = [r["value"] for r in points if r["parameter"] == sweep]
            if vals:
                cell.setdefault(sweep, []).append(float(np.mean(vals)))
    return out


def summary(rows) -> list[dict]:
    """Mean and standard deviation over datasets per estimator x form x grid point."""
    groups = defaultdict(list)
    for r in _returns(rows):
        groups[(_key(r), r["parameter"], r["p"])].append(r)
    out = []
    for ((est, form), parameter, p), rs in groups.items():
        vals = [r["value"] for r in rs]
        out.append({"estimator": est, "form": form, "family": rs[0]["family"],
                    "parameter": parameter, "p": p, "mean": float(np.mean(vals)),
                    "std": float(np.std(vals, ddof=1)) if len(vals) > 1 else float("nan"),
                    "n": len(vals)})
    return out


def best_members(rows) -> dict[tuple[str, str], str]:
    """``{(family, form): estimator}``: per family and form, the member with the highest
    mean return over every grid point and dataset (references keep their one member)."""
    means = defaultdict(list)
    family = {}
    for r in _returns(rows):
        means[_key(r)].append(r["value"])
        family[_key(r)] = r["family"]
    best: dict = {}
    for (est, form), vals in means.items():
        k = (family[(est, form)], form)
        if k not in best or np.mean(vals) > np.mean(means[(best[k], form)]):
            best[k] = est
    return best


def _cell(vals) -> str:
    if not vals:
        return "-"
    if len(vals) == 1:
        return f"{vals[0]:.1f}"
    return f"{np.mean(vals):.1f}±{np.std(vals, ddof=1):.1f}"


def _fit_cpu(rows) -> dict:
    groups = defaultdict(list)
    for r in rows:
        if r.get("quantity") == "fit time":
            groups[_key(r)].append(r["value"])
    return {k: float(np.mean(v)) for k, v in groups.items()}


def table(rows, s) -> str:
    """References first, then every estimator with its forms on adjacent lines."""
    summ = sweep_summary(rows)
    fit = _fit_cpu(rows)
    keys = sorted(summ, key=lambda k: (summ[k]["family"] not in ("expert", "behaviour"),))
    head = ["estimator", "form", "nominal"] + [f"{p} (mean)" for p in SWEEPS] + ["fit CPU s"]
    lines = [[est, form, _cell(summ[(est, form)]["nominal"])]
             + [_cell(summ[(est, form)].get(p, [])) for p in SWEEPS]
             + [f"{fit[(est, form)]:.2f}" if (est, form) in fit else "-"]
             for est, form in keys]
    widths = [max(len(str(c)) for c in col) for col in zip(head, *lines, strict=True)]

    def fmt(cells):
        return "  ".join(f"{c:<{w}}" if i < 2 else f"{c:>{w}}"
                         for i, (c, w) in enumerate(zip(cells, widths, strict=True)))

    n_rep = len({r["replication"] for r in rows})
    title = (f"cartpole: return (of 200) on the noisy CartPole grid, {s['episodes']} episodes "
             f"a dataset, {s['test_episodes']} test episodes a point; mean"
             + ("±s.d. over" if n_rep > 1 else " of") + f" {n_rep} dataset(s); nominal = "
             "p = 0, a sweep's mean over its 12 points; fit: mean CPU seconds")
    return "\n".join([title, fmt(head)] + [fmt(c) for c in lines])


def plot(rows, s):
    """One panel per parameter: the expert, the behaviour policy and, per family, the best
    pooled (solid) and best per-step (dashed) member by grid mean."""
    from ..plotting import _pyplot

    plt = _pyplot()
    summ = summary(rows)
    best = best_members(rows)
    shown = sorted(best.items(), key=lambda kv: (kv[0][1] != "reference",
                                                 list(_COLORS).index(kv[0][0])
                                                 if kv[0][0] in _COLORS else -1,
                                                 kv[0][1] != "pooled"))
    fig, axes = plt.subplots(1, len(SWEEPS), figsize=(13.5, 4.0), sharey=True,
                             constrained_layout=True)
    handles = {}
    n_rep = len({r["replication"] for r in rows})
    for ax, parameter in zip(axes, SWEEPS, strict=True):
        for (family, form), est in shown:
            pts = sorted((r for r in summ if r["estimator"] == est and r["form"] == form
                          and r["parameter"] == parameter), key=lambda r: r["p"])
            if not pts:
                continue
            if form == "reference":
                style, label, width = _REFERENCE_STYLE[family], est, 1.8
            else:
                style = {"color": _COLORS.get(family, "tab:gray"), **_FORM_STYLE[form]}
                label, width = f"{est}, {form}", 1.4
            x = [r["p"] for r in pts]
            y = [r["mean"] for r in pts]
            (line,) = ax.plot(x, y, linewidth=width, markersize=4, label=label, **style)
            handles.setdefault(label, line)
        ax.axvline(0.0, color="0.8", linewidth=0.8, zorder=0)
        ax.set_title(f"{parameter} x (1 + p)", fontsize=10)
        ax.set_xlabel("p")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("return (of 200)")
    axes[0].set_ylim(-5, 205)
    fig.suptitle(f"Noisy CartPole grid: mean return over {n_rep} dataset(s) of "
                 f"{s['episodes']} eps={s['epsilon']:g}-greedy LQR episodes", fontsize=11)
    fig.legend(list(handles.values()), list(handles), loc="outside right upper", fontsize=8,
               frameon=False, title="per family: the member with the\nbest grid mean; "
               "every member\nand the spread over datasets\nare in the table", title_fontsize=8)
    return fig
