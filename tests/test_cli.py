"""The command line: help and the demo run end to end."""

import subprocess
import sys

import pytest

from r2pvi.cli import main


def test_demo_shows_returns_under_a_shift_side_by_side(capsys):
    assert main(["demo", "--trajectories", "100", "--seed", "1"]) == 0
    out = capsys.readouterr().out
    for name in ("PEVI", "R2PVI-TV", "R2PVI-KL", "R2PVI-chi2", "q = 0", "q = 1"):
        assert name in out


def test_demo_numbers_are_exact_returns_and_robustness_shows():
    from r2pvi.demo import demo_returns
    from r2pvi.envs import SimulatedLinearMDP
    from r2pvi.evaluation import expected_return, optimal_policy

    out = demo_returns(seed=0, n_datasets=3, qs=(0.0, 1.0))
    env = SimulatedLinearMDP(xi_norm=0.3)
    best = optimal_policy(env)
    nominal = out["nominal optimum (knows the model)"][0]
    assert nominal == pytest.approx([expected_return(env.perturbed(0.0), best),
                                     expected_return(env.perturbed(1.0), best)])
    pevi, tv = out["PEVI (non-robust)"].mean(0), out["R2PVI-TV   lam=0.1"].mean(0)
    assert nominal[0] >= pevi[0] - 1e-12  # nothing beats the optimum without shift
    assert abs(tv[1] - tv[0]) < abs(pevi[1] - pevi[0])  # R2PVI-TV holds up under the shift


def test_help_lists_commands():
    res = subprocess.run([sys.executable, "-m", "r2pvi", "--help"], capture_output=True,
                         text=True, check=True)
    assert "demo" in res.stdout
