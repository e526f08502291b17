"""``r2pvi reproduce cartpole``: the noisy CartPole protocol, pooled and per-step fits side by
side, on the published 36-point test grid."""

from __future__ import annotations

import csv
from collections import defaultdict

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("gymnasium")
pytest.importorskip("matplotlib")

from r2pvi.cli import main  # noqa: E402
from r2pvi.envs.cartpole_grid import PROTOCOL_GRID  # noqa: E402
from r2pvi.experiments.figures.cartpole_protocol import (  # noqa: E402
    CARTPOLE,
    DEFAULTS,
    check_settings,
    estimators,
)
from r2pvi.experiments.figures.cartpole_report import best_members, sweep_summary, table  # noqa: E402

QUICK = ["--replications", "1", "--test-episodes", "4", "--set", "episodes=20",
         "--set", "estimators=['PEVI','R2PVI']", "--set", "divergences=['tv']",
         "--set", "lams=[0.1]"]
GRID = {(name, float(p)) for name, ps in PROTOCOL_GRID.items() for p in ps}


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("cartpole")
    assert main(["reproduce", "cartpole", "--out", str(out), "--no-progress"] + QUICK) == 0
    with open(out / "cartpole.csv") as fh:
        rows = list(csv.DictReader(fh))
    return out, rows


def _nominal(rows, estimator, form):
    (r,) = [r for r in rows if r["quantity"] == "average return" and r["estimator"] == estimator
            and r["form"] == form and r["parameter"] == "force_mag" and float(r["p"]) == 0.0]
    return float(r["value"])


def test_quick_run_fits_every_estimator_in_both_forms(quick_run):
    _, rows = quick_run
    fits = [(r["estimator"], r["form"]) for r in rows if r["quantity"] == "fit time"]
    assert sorted(fits) == sorted((e, f) for e in ("PEVI", "R2PVI-TV lam=0.1")
                                  for f in ("pooled", "per-step"))
    for r in rows:
        if r["quantity"] == "fit time":
            assert r["unit"] == "CPU s" and float(r["value"]) > 0 and float(r["wall"]) > 0
            assert 0 < float(r["implicit_discount"]) <= 1
    per_step = [r for r in rows if r["quantity"] == "fit time" and r["form"] == "per-step"]
    assert all("StarvedFitWarning" in r["warnings"] for r in per_step)   # 20 rows a step
    assert rows[0]["n_features"] == "162" and rows[0]["episodes"] == "20"


def test_quick_run_tests_every_policy_on_the_published_grid(quick_run):
    _, rows = quick_run
    points = defaultdict(set)
    for r in rows:
        if r["quantity"] == "average return":
            points[(r["estimator"], r["form"])].add((r["parameter"], float(r["p"])))
            assert 1.0 <= float(r["value"]) <= 200.0
    assert set(points) == {("PEVI", "pooled"), ("PEVI", "per-step"),
                           ("R2PVI-TV lam=0.1", "pooled"), ("R2PVI-TV lam=0.1", "per-step"),
                           ("expert (LQR)", "reference"), ("behaviour (eps=0.3)", "reference")}
    assert all(p == GRID for p in points.values()) and len(GRID) == 36
    expert = _nominal(rows, "expert (LQR)", "reference")
    assert expert == 200.0 and expert > _nominal(rows, "behaviour (eps=0.3)", "reference")
    # the pooled fit learns where the per-step fit starves (20 episodes: 20 rows a step)
    assert _nominal(rows, "R2PVI-TV lam=0.1", "pooled") > \
        2 * _nominal(rows, "R2PVI-TV lam=0.1", "per-step")


def test_quick_run_writes_the_plot_and_a_table_of_both_forms(quick_run, capsys):
    out, rows = quick_run
    for ext in ("csv", "json", "png", "pdf"):
        assert (out / f"cartpole.{ext}").stat().st_size > 0
    typed = [{**r, "p": float(r["p"]), "value": float(r["value"]),
              "replication": int(r["replication"])} for r in rows]
    text = table(typed, {**DEFAULTS, "episodes": 20, "test_episodes": 4})
    lines = text.splitlines()
    assert lines[2].startswith("expert (LQR)") and lines[3].startswith("behaviour")
    assert sum(" pooled " in line for line in lines) == 2
    assert sum(" per-step " in line for line in lines) == 2


def test_default_estimators_cover_every_family_of_the_brief():
    labels = [e[0] for e in estimators(DEFAULTS)]
    assert labels == ["PEVI"] + [f"R2PVI-{d} lam={lam}" for d in ("TV", "KL", "chi2")
                                 for lam in ("0.1", "1", "10")] \
        + ["DRPVI rho=0.05", "DRPVI rho=0.2"]
    assert DEFAULTS["episodes"] == 1000 and DEFAULTS["replications"] == 3
    assert DEFAULTS["forms"] == ["pooled", "per-step"]
    with_drvil = estimators({**DEFAULTS, "estimators": ["DRVI-L"]})
    assert [e[0] for e in with_drvil] == ["DRVI-L rho=0.1"]


@pytest.mark.parametrize(("setting", "value", "message"), [
    ("forms", "['pooled','nested']", "'forms' must be one of pooled, per-step"),
    ("estimators", "['PEVI','FQI']", "'estimators' must be one of PEVI, R2PVI, DRPVI"),
    ("episodes", "1", "'episodes' must be >= 2"),
    ("epsilon", "1.5", "'epsilon' must be <= 1"),
    ("drvil_rhos", "[0]", "'drvil_rhos' must be > 0"),
    ("lams", "[0]", "'lams' must be > 0"),
])
def test_settings_out_of_range_are_usage_errors(tmp_path, capsys, setting, value, message):
    argv = ["reproduce", "cartpole", "--out", str(tmp_path / "x"), "--no-progress",
            "--set", f"{setting}={value}"]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()        # rejected before any work


def test_old_protocol_settings_are_rejected_with_the_valid_names(tmp_path, capsys):
    assert main(["reproduce", "cartpole", "--out", str(tmp_path), "--trajectories", "5"]) == 2
    err = capsys.readouterr().err
    assert "no setting 'trajectories'" in err and "episodes" in err


@given(key=st.sampled_from(["forms", "estimators", "divergences", "lams", "rhos",
                            "drvil_rhos"]), data=st.data())
@settings(max_examples=25, deadline=None)
def test_a_value_listed_twice_is_refused(key, data):
    values = list(DEFAULTS[key] if key != "estimators" else ["PEVI", "R2PVI", "DRVI-L"])
    twice = values + [data.draw(st.sampled_from(values))]
    check_settings({**DEFAULTS, key: values})
    with pytest.raises(ValueError, match=f"setting '{key}' lists a value twice"):
        check_settings({**DEFAULTS, key: twice})
    with pytest.raises(ValueError, match="twice"):
        CARTPOLE.tasks({**DEFAULTS, key: twice})


def _rows(means: dict, n_rep: int) -> list[dict]:
    """Synthetic return rows: every grid point of ``(estimator, form)`` holds ``mean + rep``."""
    out = []
    for (est, form), mean in means.items():
        family = est.split(" ")[0]
        for rep in range(n_rep):
            for name, p in sorted(GRID):
                out.append({"quantity": "average return", "estimator": est, "form": form,
                            "family": family, "replication": rep, "parameter": name,
                            "p": p, "value": mean + rep})
    return out


@given(means=st.lists(st.integers(0, 199), min_size=1, max_size=4, unique=True),
       n_rep=st.integers(1, 3))
@settings(max_examples=30, deadline=None)
def test_the_plot_shows_the_member_with_the_best_grid_mean(means, n_rep):
    members = {(f"R2PVI-TV lam={i}", form): m + (form == "pooled")
               for i, m in enumerate(means) for form in ("pooled", "per-step")}
    rows = _rows(members, n_rep)
    best = best_members(rows)
    top = int(np.argmax(means))
    assert best == {("R2PVI-TV", "pooled"): f"R2PVI-TV lam={top}",
                    ("R2PVI-TV", "per-step"): f"R2PVI-TV lam={top}"}
    summ = sweep_summary(rows)
    for (est, form), m in members.items():
        expect = [m + rep for rep in range(n_rep)]
        assert summ[(est, form)]["nominal"] == expect
        for sweep in PROTOCOL_GRID:
            np.testing.assert_allclose(summ[(est, form)][sweep], expect)
