"""Line plots of sweep summaries (mean with a +-1 standard deviation band), PNG and PDF."""

from __future__ import annotations

from pathlib import Path

__all__ = ["line_panels", "save_figure"]


def _pyplot():
    try:
        import matplotlib
    except ImportError as exc:  # pragma: no cover - exercised without the extra
        raise ImportError("plots need matplotlib: pip install 'r2pvi[experiments]'") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def line_panels(panels, *, xlabel, ylabel, title=None, logx=False, logy=False, ncols=None):
    """One axis per panel; each panel is ``(panel_title, {series_label: (x, mean, std)})``.

    Returns the matplotlib figure.
    """
    plt = _pyplot()
    n = len(panels)
    ncols = ncols or min(n, 3)
    nrows = -(-n // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.2 * ncols, 3.3 * nrows), squeeze=False,
                             constrained_layout=True)
    for ax, (panel_title, series) in zip(axes.flat, panels, strict=False):
        for label, (x, mean, std) in series.items():
            exact = "(exact)" in label  # exact-evaluation series: dashed, no band
            line = ax.plot(x, mean, marker="" if exact else "o", markersize=3, label=label,
                           linestyle="--" if exact else "-")[0]
            if std is not None and not exact:
                lo = [m - s for m, s in zip(mean, std, strict=True)]
                hi = [m + s for m, s in zip(mean, std, strict=True)]
                ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.15, linewidth=0)
        ax.set_title(panel_title, fontsize=10)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        if logx:
            ax.set_xscale("log")
        if logy:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title, fontsize=11)
    return fig


def save_figure(fig, out_dir, name: str) -> dict[str, Path]:
    """Save ``name.png`` and ``name.pdf`` in ``out_dir`` and close the figure."""
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"png": out / f"{name}.png", "pdf": out / f"{name}.pdf"}
    fig.savefig(paths["png"], dpi=130)
    fig.savefig(paths["pdf"])
    plt.close(fig)
    return paths
