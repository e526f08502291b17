"""Line plots of sweep summaries (mean with a +-1 standard deviation band), PNG and PDF.

Conventions shared by every figure of ``r2pvi reproduce``:

- one legend per figure, outside the axes, titled with what the bands or bars mean
  (``spread``, e.g. "bands: +-1 s.d. over 20 replications");
- every learned series has its own colour, marker *and* line style, so that curves that lie on
  top of each other stay distinguishable;
- exact-evaluation series (a label containing ``"(exact)"``) are dashed, without band; exact
  series of one panel with identical values are drawn once, labelled with every name
  (``"exact optimum: nominal = TV = KL"``);
- a figure with a single panel carries a single title.
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

import numpy as np

__all__ = ["line_panels", "save_figure", "series_style", "merge_identical_exact",
           "exact_groups", "cv_score_panels", "returns_panel"]

_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">", "*")
_LINESTYLES = ("-", (0, (5, 1.5)), "-.", (0, (1, 1)), (0, (3, 1, 1, 1, 1, 1)))
_EXACT_STYLES = ((0, (4, 2)), (0, (1, 1.5)), (0, (6, 2, 1, 2)), (0, (2, 2)))
_PNG_DPI = 130


def _pyplot():
    try:
        import matplotlib
    except ImportError as exc:  # pragma: no cover - exercised without the extra
        raise ImportError("plots need matplotlib: pip install 'r2pvi[experiments]'") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def series_style(index: int) -> dict:
    """Colour, marker and line style of the ``index``-th learned series of a figure.

    Colours cycle over 10, markers over 10 and line styles over 5 values, so two series with
    indices below 10 never share colour and marker; odd indices have hollow markers, so
    that two series with the same values both stay visible.

    Examples
    --------
    >>> series_style(0)["marker"], series_style(1)["marker"]
    ('o', 's')
    >>> series_style(0)["color"] != series_style(1)["color"]
    True
    """
    style = {"color": f"C{index % 10}", "marker": _MARKERS[index % len(_MARKERS)],
             "linestyle": _LINESTYLES[index % len(_LINESTYLES)]}
    if index % 2:  # hollow markers: a filled marker under them stays visible
        style["markerfacecolor"] = "none"
    return style


def _exact_name(label: str) -> str:
    return re.sub(r"\s*(robust\s+)?optimum\s*\(exact\)\s*$", "", label).strip() or label


def exact_groups(series: dict, atol: float = 1e-9) -> dict[str, list[str]]:
    """Group the exact series (labels containing ``"(exact)"``) whose x and values coincide.

    Returns ``{label: [original labels]}``, the label listing every name of a group of more
    than one (``"exact optimum: nominal = TV = KL"``).
    """
    groups: list[tuple[list[str], np.ndarray, np.ndarray]] = []
    for label, value in series.items():
        if "(exact)" not in label:
            continue
        x, mean = np.asarray(value[0], float), np.asarray(value[1], float)
        for names, gx, gmean in groups:
            if gx.shape == x.shape and np.allclose(gx, x) and np.allclose(gmean, mean,
                                                                          atol=atol, rtol=0):
                names.append(label)
                break
        else:
            groups.append(([label], x, mean))
    return {(names[0] if len(names) == 1 else
             "exact optimum: " + " = ".join(_exact_name(n) for n in names)): names
            for names, _, _ in groups}


def merge_identical_exact(series: dict, atol: float = 1e-9) -> dict:
    """Merge exact series (labels containing ``"(exact)"``) whose x and values coincide.

    ``series`` maps labels to ``(x, mean, std)``; the merged label lists every name,
    ``"exact optimum: nominal = TV = KL"``. Learned series are returned unchanged, in order.

    Examples
    --------
    >>> s = {"PEVI": ([0, 1], [2.0, 1.0], [0.1, 0.1]),
    ...      "nominal optimum (exact)": ([0, 1], [2.0, 1.5], None),
    ...      "TV robust optimum (exact)": ([0, 1], [2.0, 1.5], None),
    ...      "KL robust optimum (exact)": ([0, 1], [1.0, 1.0], None)}
    >>> list(merge_identical_exact(s))
    ['PEVI', 'exact optimum: nominal = TV', 'KL robust optimum (exact)']
    """
    out = {label: value for label, value in series.items() if "(exact)" not in label}
    for label, names in exact_groups(series, atol).items():
        out[label] = series[names[0]]
    return out


def line_panels(panels, *, xlabel, ylabel, title=None, xscale="linear", logy=False,
                ncols=None, spread=None, style="band", logx=False, xticks=None):
    """One axis per panel; each panel is ``(panel_title, {series_label: (x, mean, std)})``.

    Parameters
    ----------
    panels : list of (str, dict)
        ``std`` may be None (no band). Labels containing ``"(exact)"`` are exact series.
    xlabel, ylabel, title : str
        With a single panel, ``title`` replaces the panel title (one title, not two).
    xscale : {"linear", "log"} or ("symlog", linthresh)
        ``("symlog", t)``: logarithmic above ``t``, linear below, so that 0 can be shown.
    logy : bool
    ncols : int, optional
    spread : str, optional
        What the bands or bars are, shown as the legend's title, e.g.
        ``"bands: +-1 s.d. over 20 replications"``.
    style : {"band", "bars"}
        Shaded bands (dense x grids) or error bars (few points, log axes).
    logx : bool
        Shorthand for ``xscale="log"``.
    xticks : sequence of float, optional
        Tick positions, labelled with their plain values (useful on log axes).

    Returns the matplotlib figure, with one legend below (several panels) or beside (one
    panel) the axes.
    """
    plt = _pyplot()
    if logx:
        xscale = "log"
    n = len(panels)
    ncols = ncols or min(n, 3)
    nrows = -(-n // ncols)
    width = 4.2 * ncols + (2.6 if n == 1 else 0.0)
    fig, axes = plt.subplots(nrows, ncols, figsize=(width, 3.3 * nrows + (0.9 if n > 1 else 0)),
                             squeeze=False, constrained_layout=True)
    styles: dict[str, dict] = {}
    exact_styles: dict[str, dict] = {}
    handles: dict = {}
    for ax, (panel_title, series) in zip(axes.flat, panels, strict=False):
        for label, (x, mean, std) in merge_identical_exact(series).items():
            x = np.asarray(x, float)
            mean = np.asarray(mean, float)
            if "(exact)" in label or label.startswith("exact optimum"):
                st = exact_styles.setdefault(label, {
                    "color": "black" if not exact_styles else f"C{(9 - len(exact_styles)) % 10}",
                    "linestyle": _EXACT_STYLES[len(exact_styles) % len(_EXACT_STYLES)]})
                (line,) = ax.plot(x, mean, linewidth=1.6, label=label, **st)
                handles.setdefault(label, line)
                continue
            st = styles.setdefault(label, series_style(len(styles)))
            if std is not None and style == "bars":
                std = np.asarray(std, float)
                low = np.minimum(std, 0.95 * mean) if logy else std  # positive on a log axis
                line = ax.errorbar(x, mean, yerr=[low, std], markersize=4, capsize=2.5,
                                   linewidth=1.3, label=label, **st)
            else:
                (line,) = ax.plot(x, mean, markersize=4, linewidth=1.3, label=label, **st)
                if std is not None:
                    std = np.asarray(std, float)
                    ax.fill_between(x, mean - std, mean + std, color=st["color"], alpha=0.12,
                                    linewidth=0)
            handles.setdefault(label, line)
        ax.set_title(title if (n == 1 and title) else panel_title, fontsize=10)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        if isinstance(xscale, tuple):
            ax.set_xscale(xscale[0], linthresh=xscale[1], linscale=0.4)
        elif xscale != "linear":
            ax.set_xscale(xscale)
        if xticks is not None:
            ax.set_xticks(list(xticks), [f"{t:g}" for t in xticks])
            ax.minorticks_off()
        if logy:
            ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both" if logy else "major")
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    if title and n > 1:
        fig.suptitle(title, fontsize=11)
    if handles:
        # learned series first, then the exact lines
        order = [k for k in handles if k in styles] + [k for k in handles if k not in styles]
        loc = "outside right upper" if n == 1 else "outside lower center"
        ncol = 1 if n == 1 else min(len(order), 4 if len(order) > 6 else len(order))
        if spread and n == 1:  # beside a single axis: wrap, so the title stays narrow
            spread = textwrap.fill(spread, 34)
        fig.legend([handles[k] for k in order], order, loc=loc, ncols=ncol, fontsize=8,
                   title=spread, title_fontsize=8, frameon=False)
    return fig


def cv_score_panels(axes, values, cv_results: dict, scores: dict, *, xlabel: str = "lam",
                    xscale: str = "log") -> list[int]:
    """Draw the scores of a scikit-learn search over one parameter, one panel each.

    Each panel shows ``cv_results["mean_test_<name>"]`` against ``values`` with bars of
    ``+-`` the folds' standard deviation (``std_test_<name>``), and a star on the best.

    Parameters
    ----------
    axes : sequence of matplotlib Axes
        One per score.
    values : sequence of float
        The parameter's values, in the order of the search's candidates.
    cv_results : dict
        ``GridSearchCV(...).cv_results_`` (with one scorer per name in ``scores``).
    scores : dict
        Scorer name -> panel title.

    Returns
    -------
    list of int
        The index of the best value of each score.
    """
    x = np.asarray(values, dtype=float)
    best = []
    for ax, (name, title) in zip(axes, scores.items(), strict=True):
        best.append(_cv_score_panel(ax, x, cv_results, name, title, xlabel, xscale))
    return best


def _cv_score_panel(ax, x, cv_results, name, title, xlabel, xscale) -> int:
    mean = np.asarray(cv_results[f"mean_test_{name}"], dtype=float)
    std = np.asarray(cv_results[f"std_test_{name}"], dtype=float)
    ax.errorbar(x, mean, yerr=std, marker="o", capsize=3)
    i = int(np.argmax(mean))
    ax.plot(x[i], mean[i], "r*", markersize=14, label="chosen")
    ax.set_title(title, fontsize=10)
    ax.set_ylabel("CV score (mean +- sd over folds)")
    _finish(ax, xlabel, xscale)
    return i


def returns_panel(ax, values, series: dict, chosen, title: str, *,
                  chosen_label: str = "chosen", xlabel: str = "lam", xscale: str = "log"):
    """Draw true returns against a parameter next to :func:`cv_score_panels`: one line per
    ``series`` (label -> returns, a marker and line style each) and a dotted line at the
    ``chosen`` value."""
    styles = ("o-", "s--", "^-.", "D:")
    for k, (label, y) in enumerate(series.items()):
        ax.plot(values, y, styles[k % len(styles)], label=label)
    ax.axvline(chosen, color="r", linestyle=":", label=chosen_label)
    ax.set_title(title, fontsize=10)
    _finish(ax, xlabel, xscale)


def _finish(ax, xlabel: str, xscale: str) -> None:
    ax.set_xscale(xscale)
    ax.set_xlabel(xlabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


def save_figure(fig, out_dir, name: str) -> dict[str, Path]:
    """Save ``name.png`` and ``name.pdf`` in ``out_dir`` and close the figure."""
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"png": out / f"{name}.png", "pdf": out / f"{name}.pdf"}
    # Solve the layout once, as savefig would for the PNG (with a renderer at its dpi), then
    # save both files with it: savefig would otherwise solve it and draw the figure an extra
    # time for each file (more than half of the saving time).
    engine = fig.get_layout_engine()
    if engine is not None:
        dpi = fig.dpi
        fig.set_dpi(_PNG_DPI)
        try:
            engine.execute(fig)
        finally:
            fig.set_dpi(dpi)
        fig.set_layout_engine(None)  # None, not "none": savefig would draw twice
    fig.savefig(paths["png"], dpi=_PNG_DPI)
    fig.savefig(paths["pdf"])
    plt.close(fig)
    return paths
