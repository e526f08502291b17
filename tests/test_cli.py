"""The command line: help and the demo run end to end."""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import r2pvi
from r2pvi.cli import main


def test_demo_shows_returns_under_a_shift_side_by_side(capsys):
    assert main(["demo", "--trajectories", "100", "--seed", "1"]) == 0
    out = capsys.readouterr().out
    for name in ("PEVI", "q = 0", "q = 1", "nominal optimum"):
        assert name in out
    for div in ("TV", "KL", "chi2"):
        for fraction in ("0.1 R", "0.01 R", "0.001 R"):
            assert re.search(rf"^R2PVI-{div} +lam=\S+ \({fraction}\)", out, re.M), (div, out)
        assert re.search(rf"^  {div} +(\d\.\d{{3}} +){{3}}(above|not above) PEVI", out, re.M)
    # the rule that sets lam is printed, and it reads the data only
    assert "fractions (0.1, 0.01, 0.001) of R = (H - 1) x the largest reward" in out
    assert "never the test" in out and "Why KL and chi^2 need a smaller lam than TV" in out


def test_demo_lams_are_fractions_of_the_data_value_range_not_of_test_results():
    from r2pvi.demo import demo_returns
    from r2pvi.envs import SimulatedLinearMDP

    res = demo_returns(seed=0, n_datasets=3, qs=(0.0, 1.0))
    env = SimulatedLinearMDP(xi_norm=0.3)
    datasets = [env.collect(100, seed=np.random.default_rng(c))
                for c in np.random.SeedSequence(0).spawn(3)]
    R = (env.horizon - 1) * max(ds.rewards.max() for ds in datasets)
    assert res.value_range == R == 2.0  # the goal state pays 1, two steps remain
    assert sorted({(d, f) for d, f, _ in res.settings.values()}) == sorted(
        (d, f) for d in ("tv", "kl", "chi2") for f in (0.1, 0.01, 0.001))
    for _, fraction, lam in res.settings.values():
        assert lam == pytest.approx(fraction * R)
    other = demo_returns(seed=0, n_datasets=3, qs=(0.5,))  # other tests, same data: same lam
    assert other.settings == res.settings


def test_demo_numbers_are_exact_returns_and_each_divergence_shows_robustness():
    from r2pvi.demo import demo_returns
    from r2pvi.envs import SimulatedLinearMDP
    from r2pvi.evaluation import expected_return, optimal_policy

    res = demo_returns(seed=0, qs=(0.0, 1.0))  # the demo's own 10 datasets
    env = SimulatedLinearMDP(xi_norm=0.3)
    best = optimal_policy(env)
    nominal = res.returns["nominal optimum (knows the model)"][0]
    assert nominal == pytest.approx([expected_return(env.perturbed(0.0), best),
                                     expected_return(env.perturbed(1.0), best)])
    pevi = res.returns["PEVI (non-robust)"].mean(0)
    assert nominal[0] >= pevi[0] - 1e-12  # nothing beats the optimum without shift
    for div in ("tv", "kl", "chi2"):
        rows = {f: res.returns[name].mean(0) for name, (d, f, _) in res.settings.items()
                if d == div}
        smallest = rows[min(rows)]
        # at the smallest lam every divergence keeps more than PEVI under the largest shift
        # and loses less from q = 0 to q = 1 (with lam = 0.1 alone, KL and chi^2 did not)
        assert smallest[1] > pevi[1] + 0.05, (div, rows, pevi)
        assert abs(smallest[1] - smallest[0]) < abs(pevi[1] - pevi[0]), (div, rows, pevi)


def test_help_lists_commands():
    res = subprocess.run([sys.executable, "-m", "r2pvi", "--help"], capture_output=True,
                         text=True, check=True)
    assert "demo" in res.stdout


@pytest.mark.parametrize("flag", ["--version", "-V"])
def test_version_flag_prints_the_installed_version_and_exits_0(flag, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([flag])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert out == f"r2pvi {r2pvi.__version__}\n"
    assert re.fullmatch(r"r2pvi \d+\.\d+\.\d+\S*\n", out)


def test_version_flag_from_the_command_line():
    env = {**os.environ, "PYTHONPATH": SRC}
    res = subprocess.run([sys.executable, "-m", "r2pvi", "--version"], capture_output=True,
                         text=True, env=env, timeout=120)
    assert res.returncode == 0 and res.stderr == ""
    assert res.stdout == f"r2pvi {r2pvi.__version__}\n"


# --------------------------------------------------------------------------- usage errors
SRC = str(Path(r2pvi.__file__).resolve().parents[1])


def _bad_files(tmp):
    (tmp / "typo.toml").write_text("lamm = 0.3\n")
    (tmp / "table.toml").write_text("[fig7]\nlam = 1\n")
    (tmp / "key.toml").write_text("[fig1a]\nrho = 1\n")
    (tmp / "bad.toml").write_text("[fig1a\n")
    (tmp / "latin1.toml").write_bytes("lam = 0.3 # \xe9\n".encode("latin-1"))
    (tmp / "afile").write_text("x")
    return tmp


USAGE_CASES = [
    (["reproduce", "all", "--set", "lamm=0.3"], "no figure has a setting 'lamm'; did you mean"
                                                " 'lam'?"),
    (["reproduce", "fig1a", "--set", "rho=0.3"], "fig1a has no setting 'rho'"),
    (["reproduce", "fig1a", "--replications", "0"], "'replications' must be >= 1, got 0"),
    (["reproduce", "all", "--replications", "1000000000"], "'replications' must be <= 10000"),
    (["reproduce", "fig1a", "--jobs", "0"], "--jobs must be >= 1, or -1"),
    (["reproduce", "fig1a", "--jobs", "-2"], "--jobs must be >= 1, or -1"),
    (["reproduce", "fig1a", "--seed", "-1"], "--seed must be >= 0"),
    (["reproduce", "fig1a", "--set", "qs=[]"], "'qs' must be a non-empty list"),
    (["reproduce", "fig1a", "--set", "qs=1.5"], "'qs' must be <= 1.0, got 1.5"),
    (["reproduce", "fig1a", "--set", "xi_norms=abc"], "'xi_norms' must be a number"),
    (["reproduce", "fig1a", "--set", "exact_optimum=3"], "must be true or false"),
    (["reproduce", "fig1a", "--set", "novalue"], "--set expects key=value"),
    (["reproduce", "fig1a", "--lams", "1,a"], "invalid comma-separated numbers value"),
    (["reproduce", "fig1a", "--divergences", "tv,foo"], "unknown divergence 'foo'"),
    (["reproduce", "rates", "--divergences", "hellinger"], "'divergences' must be one of tv"),
    (["reproduce", "fig1a", "--test-episodes", "1"], "'test_episodes' must be >= 2"),
    (["reproduce", "fig9"], "unknown figure 'fig9'"),
    (["reproduce", "fig1a", "--config", "{tmp}/typo.toml"], "unknown setting 'lamm'"),
    (["reproduce", "fig1a", "--config", "{tmp}/table.toml"], "unknown table [fig7]"),
    (["reproduce", "fig1a", "--config", "{tmp}/key.toml"], "[fig1a] has no setting 'rho'"),
    (["reproduce", "fig1a", "--config", "{tmp}/bad.toml"], "is not valid TOML"),
    (["reproduce", "fig1a", "--config", "{tmp}/latin1.toml"], "is not UTF-8"),
    (["reproduce", "fig1a", "--config", "{tmp}/absent.toml"], "config file not found"),
    (["reproduce", "fig1a", "--out", "{tmp}/afile"], "exists and is not a directory"),
    (["reproduce", "fig1a", "--out", "{tmp}/afile/sub"], "not a writable directory"),
    (["demo", "--trajectories", "-5"], "--trajectories must be >= 1"),
    (["demo", "--seed", "-3"], "--seed must be >= 0"),
    (["bogus"], "invalid choice: 'bogus'"),
    (["reproduce", "fig1a", "--xi-norms", "0.5"], "'delta' and xi_norm: delta = 0.3 and xi_norm"
                                                  " = 0.5 give features off the simplex"),
    (["reproduce", "rates", "--set", "xi_norm=0.9"], "'mdp_delta' and xi_norm"),
]


def test_usage_errors_in_process_are_one_line_exit_2(tmp_path, capsys):
    tmp = _bad_files(tmp_path)
    for argv, match in USAGE_CASES:
        argv = [a.format(tmp=tmp) for a in argv]
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("r2pvi: error: ") and err.count("\n") == 1, (argv, err)
        assert match in err, (argv, err)
    assert sorted(p.name for p in tmp.iterdir()) == sorted(
        ["typo.toml", "table.toml", "key.toml", "bad.toml", "latin1.toml", "afile"]
    )  # no output directory, no result file: nothing ran


def test_usage_errors_from_the_command_line_in_subprocesses(tmp_path):
    tmp = _bad_files(tmp_path)
    env = {**os.environ, "PYTHONPATH": SRC}
    # A few cases end to end (each starts Python); every case runs in process above.
    picked = [USAGE_CASES[i] for i in (0, 3, 20, 25)]
    procs = [(argv, match, subprocess.Popen(
        [sys.executable, "-m", "r2pvi", *(a.format(tmp=tmp) for a in argv)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env))
        for argv, match in picked]
    for argv, match, proc in procs:
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 2, (argv, err)
        assert err.startswith("r2pvi: error: ") and err.count("\n") == 1, (argv, err)
        assert match in err and "Traceback" not in err, (argv, err)
    debug = subprocess.run([sys.executable, "-m", "r2pvi", "reproduce", "fig1a",
                            "--replications", "0", "--debug"], capture_output=True, text=True,
                           env=env, timeout=120)
    assert debug.returncode != 0 and "Traceback" in debug.stderr
    assert "UsageError: fig1a: setting 'replications' must be >= 1" in debug.stderr


def test_missing_matplotlib_is_a_usage_error_before_work(tmp_path, monkeypatch, capsys):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "matplotlib" else real(name, *a))
    out = tmp_path / "res"
    assert main(["reproduce", "fig1a", "--out", str(out), "--jobs", "1"]) == 2
    assert "plotting (pass --no-plot" in capsys.readouterr().err
    assert not out.exists()


def test_failures_while_running_are_one_line_exit_1(tmp_path, capsys, monkeypatch):
    from r2pvi.experiments import reproduce

    def boom(*a, **k):
        raise ValueError("the solver\nfailed")

    monkeypatch.setattr(reproduce, "reproduce_figure", boom)
    assert main(["reproduce", "fig1a", "--out", str(tmp_path), "--no-progress", "--no-plot",
                 "--jobs", "1"]) == 1
    err = capsys.readouterr().err
    assert err == ("r2pvi: error: the solver failed (ValueError; rerun with --debug for the "
                   "traceback)\n")


def test_summary_tables_show_the_qs_that_ran(tmp_path, capsys):
    for qs, want in (("0.5", ["0.5"]), ("[0.25,0.75]", ["0.25", "0.75"])):
        assert main(["reproduce", "fig1a", "--out", str(tmp_path), "--set", f"qs={qs}",
                     "--set", "xi_norms=0.3", "--replications", "1", "--no-progress",
                     "--no-plot", "--jobs", "1", "--divergences", "tv"]) == 0
        table = capsys.readouterr().out
        header = next(line for line in table.splitlines() if line.startswith("algorithm"))
        assert header.split()[1:] == want, table
        assert "R2PVI-TV" in table and "±" in table
