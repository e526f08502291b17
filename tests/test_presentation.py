"""How results are shown: progress off a terminal, figure legends and titles, result files."""

import io

import numpy as np
import pytest

from r2pvi.experiments.plotting import (
    cv_score_panels,
    line_panels,
    merge_identical_exact,
    returns_panel,
    series_style,
)
from r2pvi.experiments.progress import SweepProgress
from r2pvi.experiments.results import read_results, summarize, write_results
from r2pvi.experiments.runner import Task, run_tasks

pytest.importorskip("matplotlib")


def _noop(seq, **kw):
    return [{"x": 1.0}]


def test_progress_off_a_terminal_is_a_few_plain_lines(capsys):
    tasks = [Task(_noop, cost=1.0) for _ in range(200)]
    run_tasks(tasks, progress=True, label="sweep")
    err = capsys.readouterr().err  # pytest's capture is not a terminal
    assert "\r" not in err
    lines = err.splitlines()
    assert 1 <= len(lines) <= 12  # every 10%, not every task
    assert lines[-1].startswith("[sweep] 100% (200/200 tasks)")


def test_progress_counts_cost_so_the_estimate_is_honest():
    out = io.StringIO()
    # nine cheap tasks done first, one task as expensive as 91 of them still to come
    p = SweepProgress(total=100.0, n=10, label="rates", stream=out, tty=False, interval=0.0)
    for _ in range(9):
        p.advance(1.0)
    assert "(9/10 tasks)" in out.getvalue().splitlines()[-1]
    assert p.line().split("] ")[1].startswith("9%")  # 9% of the work, not 90%
    p.advance(91.0)
    assert out.getvalue().splitlines()[-1].startswith("[rates] 100% (10/10 tasks)")


def test_rates_tasks_are_weighted_by_dataset_size():
    from r2pvi.experiments.config import merge_settings
    from r2pvi.experiments.figures import FIGURES

    fig = FIGURES["rates"]
    tasks = fig.tasks(merge_settings("rates", fig.defaults, None, {"replications": 1}))
    cost = {t.kwargs["K"]: t.cost for t in tasks}
    assert cost[100000] > 50 * cost[100]


def test_identical_exact_series_are_drawn_once_with_every_name():
    same = ([0.0, 1.0], [1.5, 0.5], None)
    series = {"PEVI": ([0.0, 1.0], [1.4, 0.6], [0.1, 0.1]),
              "nominal optimum (exact)": same,
              "TV robust optimum (exact)": same,
              "KL robust optimum (exact)": ([0.0, 1.0], [1.5, 0.5 + 1e-6], None)}
    merged = merge_identical_exact(series)
    assert list(merged) == ["PEVI", "exact optimum: nominal = TV", "KL robust optimum (exact)"]
    fig = line_panels([("a", series), ("b", series)], xlabel="q", ylabel="return",
                      title="T", spread="bands: ±1 standard deviation over 3 replications")
    legends = fig.legends
    assert len(legends) == 1 and all(ax.get_legend() is None for ax in fig.axes)
    labels = [t.get_text() for t in legends[0].get_texts()]
    assert labels == ["PEVI", "exact optimum: nominal = TV", "KL robust optimum (exact)"]
    assert "standard deviation" in legends[0].get_title().get_text()
    assert sum(len(ax.get_lines()) for ax in fig.axes) == 2 * 3


def test_one_panel_has_one_title_and_series_differ_in_marker_and_style():
    fig = line_panels([("panel", {f"s{i}": ([0, 1], [i, i], None) for i in range(6)})],
                      xlabel="x", ylabel="y", title="The title")
    assert fig.get_suptitle() == "" and fig.axes[0].get_title() == "The title"
    styles = {(series_style(i)["marker"], str(series_style(i)["linestyle"]),
               series_style(i)["color"]) for i in range(10)}
    assert len({m for m, _, _ in styles}) == 10 and len({c for _, _, c in styles}) == 10


def test_result_files_say_what_the_value_is_and_store_rows_once(tmp_path):
    rows = [{"algorithm": "A", "replication": r, "q": q, "value": float(r + q)}
            for r in range(3) for q in (0.0, 1.0)]
    rows.append({"algorithm": "exact", "replication": 0, "q": 0.0, "value": 9.0,
                 "action_x1": 3})
    write_results(rows, tmp_path, "f", {"seed": 0}, quantity="fit time", unit="s")
    header, *lines = (tmp_path / "f.csv").read_text().splitlines()
    cols = header.split(",")
    assert cols[:2] == ["figure", "r2pvi_version"]
    assert cols.index("quantity") < cols.index("unit") < cols.index("value")
    assert all(line.split(",")[cols.index("unit")] == "s" for line in lines)
    data = read_results(tmp_path / "f.json")
    assert (data["quantity"], data["unit"]) == ("fit time", "s")
    assert [{k: r[k] for k in rows[i]} for i, r in enumerate(data["rows"])] == rows
    assert all(r["quantity"] == "fit time" for r in data["rows"])
    assert "action_x1" not in data["rows"][0] and data["rows"][-1]["action_x1"] == 3
    text = (tmp_path / "f.json").read_text()
    assert text.count("fit time") == 1 and text.count("r2pvi_version") == 1
    (tmp_path / "old.json").write_text('{"figure": "f", "rows": []}')
    with pytest.raises(ValueError, match="format"):
        read_results(tmp_path / "old.json")
    # one replication: a mean without a fake "±0" spread
    assert summarize(rows[-1:], ["q"])[0]["n"] == 1


def test_timing_rows_are_one_per_fit_and_the_table_has_no_fake_spread(tmp_path, capsys):
    from r2pvi.experiments import reproduce_figure

    out = reproduce_figure("fig2a", tmp_path, progress=False, plot=False,
                           overrides={"trajectories_grid": [60], "features": 6, "repeats": 1})
    assert {r["repeat"] for r in out["rows"]} == {0}
    text = capsys.readouterr().out
    assert "one timed fit" in text and "±" not in text.split("one timed fit")[1]
    assert np.all([r["value"] > 0 for r in out["rows"]])


def test_cv_score_panels_mark_each_scores_best_value():
    import matplotlib.pyplot as plt

    results = {"mean_test_a": [1.0, 3.0, 2.0], "std_test_a": [0.1, 0.2, 0.3],
               "mean_test_b": [5.0, 1.0, 0.0], "std_test_b": [0.0, 0.0, 0.0]}
    fig, axes = plt.subplots(1, 2)
    best = cv_score_panels(axes, [0.1, 1.0, 10.0], results, {"a": "A", "b": "B"})
    assert best == [1, 0]
    star = [line for line in axes[0].lines if line.get_marker() == "*"][0]
    assert star.get_xdata()[0] == 1.0 and star.get_ydata()[0] == 3.0
    assert axes[1].get_title() == "B" and axes[0].get_xscale() == "log"
    with pytest.raises(ValueError):
        cv_score_panels(axes, [0.1, 1.0, 10.0], results, {"a": "A"})  # fewer scores than axes
    returns_panel(axes[1], [0.1, 1.0, 10.0], {"nominal": [1, 2, 3], "sweeps": [0, 1, 2]}, 1.0,
                  "truth")
    assert [line.get_label() for line in axes[1].lines][-3:] == ["nominal", "sweeps",
                                                                  "chosen"]
    plt.close(fig)
