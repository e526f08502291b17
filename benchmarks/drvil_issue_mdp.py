"""DRVI-L on issue 9's linear MDP: how far the learned factor values are from the exact KL balls.

4 factors over 6 states, state 5 an absorbing fail state (V = 0) reached through factor 3,
factor 0 without mass on it; K = 2000, rho = 0.3, beta = 0. For every dataset and step the
learned ``w_h`` is compared with the plain ridge estimate and with ``kl_constrained`` on the
true factors at the learned ``V_{h+1}`` of every state.

    PYTHONPATH=src python benchmarks/drvil_issue_mdp.py --datasets 40 [--b-min none]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from r2pvi.algorithms import KLBallRule
from r2pvi.duals import FactorExpectation, kl_constrained
from r2pvi.engine import backward_induction

# The MDP is defined once, with the regression tests that use it.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers import fail_state_mdp  # noqa: E402


class Spy(KLBallRule):
    """The DRVI-L step rule, recording the plain estimate and ``w_h`` of every step."""

    def __call__(self, E, v, ctx):
        w = super().__call__(E, v, ctx)
        self.seen[ctx.h] = (E(v), w)
        return w


def make_spy(rho, b_min):
    try:
        spy = Spy(rho, b_min)
    except TypeError:  # a version without b_min
        spy = Spy(rho)
    spy.seen = {}
    return spy


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", type=int, default=40)
    ap.add_argument("--rho", type=float, default=0.3)
    ap.add_argument("--b-min", default="auto", help="'auto', 'none' or a number")
    args = ap.parse_args()
    b_min = {"auto": "auto", "none": None}.get(args.b_min.lower(), None)
    if args.b_min.lower() not in ("auto", "none"):
        b_min = float(args.b_min)
    env = fail_state_mdp()
    H, d = env.horizon, env.n_features
    above, errs, largest = 0, [], 0.0
    for seed in range(args.datasets):
        ds = env.collect(2000, seed=seed)
        spy = make_spy(np.full((H, d), args.rho), b_min)
        model = backward_induction(ds, spy, beta=0.0, gamma=1.0, penalty="l1", r_max=1.0)
        for h in range(H - 1):
            v_states = np.clip(env.phi @ model.weights[h + 1], 0.0, H - h - 1).max(axis=1)
            v_states[5] = 0.0
            exact = kl_constrained(FactorExpectation(env.mu[h]), v_states, args.rho)
            plain, w = spy.seen[h]
            above += int(np.any(w > np.clip(plain, 0.0, None) + 1e-9))
            errs.append(np.abs(w - exact))
            largest = max(largest, float(w.max()))
    errs = np.concatenate(errs)
    print(f"{args.datasets} datasets, b_min={b_min!r}: steps with w > plain estimate "
          f"{above} of {args.datasets * (H - 1)}; |w - exact| mean {errs.mean():.4f} "
          f"max {errs.max():.4f}; largest w {largest:.3f}")


if __name__ == "__main__":
    main()
