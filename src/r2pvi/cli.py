"""Command-line interface: ``r2pvi demo`` (more commands arrive with the experiments)."""

from __future__ import annotations

import argparse
import sys


def _demo(args) -> int:
    from .demo import run_demo

    run_demo(seed=args.seed, n_trajectories=args.trajectories)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="r2pvi",
        description="Robust offline RL with linearly structured f-divergence regularization.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser(
        "demo",
        help="fit PEVI and R2PVI (TV, KL, chi^2) on a small synthetic linear MDP dataset",
        description="Build a small dataset from a random linear MDP, fit PEVI and the three "
        "R2PVI variants, and print their weights and greedy actions.",
    )
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("--trajectories", type=int, default=500, help="K (default 500)")
    demo.set_defaults(func=_demo)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
