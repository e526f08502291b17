"""The command line: help and the demo run end to end."""

import subprocess
import sys

from r2pvi.cli import main


def test_demo_runs_and_prints_every_estimator(capsys):
    assert main(["demo", "--trajectories", "200", "--seed", "1"]) == 0
    out = capsys.readouterr().out
    for name in ("PEVI", "R2PVI-TV", "R2PVI-KL", "R2PVI-chi2"):
        assert name in out
    assert "greedy action" in out


def test_help_lists_commands():
    res = subprocess.run([sys.executable, "-m", "r2pvi", "--help"], capture_output=True,
                         text=True, check=True)
    assert "demo" in res.stdout
