"""Command-line interface: ``r2pvi demo`` (more commands arrive with the experiments)."""

from __future__ import annotations

import argparse
import sys


def _demo(args) -> int:
    from .demo import run_demo

    run_demo(seed=args.seed, n_trajectories=args.trajectories)
    return 0


def _reproduce(args) -> int:
    from .experiments.config import load_toml, parse_assignment
    from .experiments.reproduce import figure_names, reproduce_figure

    names = figure_names() if args.figure == "all" else [args.figure]
    if args.figure != "all" and args.figure not in figure_names(benchmarks=True):
        print(f"r2pvi reproduce: unknown figure {args.figure!r}; choose from "
              f"{', '.join(figure_names(benchmarks=True))} or all", file=sys.stderr)
        return 2
    toml = load_toml(args.config) if args.config else None
    overrides = dict(parse_assignment(a) for a in args.set)
    for key in ("lam", "lams", "rho", "rhos", "replications", "trajectories", "xi_norms",
                "beta", "gamma", "evaluation", "test_episodes", "divergences", "repeats"):
        value = getattr(args, key, None)
        if value is not None:
            overrides[key] = value
    backend = "dask" if (args.dask or args.scheduler) else ("joblib" if args.jobs > 1
                                                            else "serial")
    for name in names:
        from .experiments.figures import FIGURES

        # Shared flags apply to the figures that have the setting (like a TOML top level).
        applicable = {k: v for k, v in overrides.items()
                      if k in FIGURES[name].defaults or args.figure != "all"}
        reproduce_figure(name, args.out, toml=toml, overrides=applicable, seed=args.seed,
                         backend=backend, jobs=args.jobs, scheduler=args.scheduler,
                         progress=not args.no_progress, plot=not args.no_plot)
    return 0


def _floats(text):
    return [float(x) for x in text.split(",")]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="r2pvi",
        description="Robust offline RL with linearly structured f-divergence regularization.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser(
        "demo",
        help="ten-second tour: PEVI and R2PVI (TV, KL, chi^2) returns under a dynamics shift",
        description="Fit PEVI and the three R2PVI variants on small datasets of the paper's "
        "simulated linear MDP and print their exact returns, side by side, in test "
        "environments with increasing shifts of the dynamics.",
    )
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("--trajectories", type=int, default=100,
                      help="K per dataset (default 100, the paper's)")
    demo.set_defaults(func=_demo)

    rep = sub.add_parser(
        "reproduce",
        help="reproduce a figure of the paper (or all of them): results, plots, summary",
        description="Run the sweep behind a figure of the paper's Experiment section and write "
        "NAME.csv and NAME.json (one row per setting x replication, with the configuration and "
        "library version), NAME.png and NAME.pdf, and print a summary table. Settings come from "
        "the figure's defaults (the paper's), then --config FILE.toml, then the flags below and "
        "--set key=value. Figures: fig1a fig1b fig1c fig1d fig2a fig2b va (the paper's) and "
        "rates bound-check (its theory); run by name only (not in 'all'): cartpole mountaincar "
        "(classic-control robustness benchmarks).",
    )
    rep.add_argument("figure", help="figure name (fig1a ... va, rates, bound-check) or 'all'")
    rep.add_argument("--out", default="results", help="output directory (default: results)")
    rep.add_argument("--config", help="TOML file with settings (top level or [figure] tables)")
    rep.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                     help="override any setting, e.g. --set qs=[0,0.5,1] (repeatable)")
    rep.add_argument("--seed", type=int, default=0, help="root seed of the sweep (default 0)")
    rep.add_argument("--jobs", type=int, default=1, help="parallel local workers (joblib)")
    rep.add_argument("--dask", action="store_true",
                     help="run on a local Dask distributed cluster with --jobs workers")
    rep.add_argument("--scheduler", metavar="ADDRESS",
                     help="run on the Dask cluster at ADDRESS (e.g. tcp://host:8786)")
    rep.add_argument("--no-progress", action="store_true", help="no progress bars")
    rep.add_argument("--no-plot", action="store_true", help="skip the PNG/PDF plots")
    common = rep.add_argument_group("common settings (applied where a figure has them)")
    common.add_argument("--lam", type=float, help="regularizer lam (fig1a, va)")
    common.add_argument("--lams", type=_floats, help="comma-separated lams (fig1b, fig1c, fig1d)")
    common.add_argument("--rho", type=float, help="uncertainty level rho (va)")
    common.add_argument("--rhos", type=_floats, help="comma-separated rhos (fig1c, fig1d)")
    common.add_argument("--replications", type=int, help="replications per setting")
    common.add_argument("--trajectories", type=int, help="dataset size K (N)")
    common.add_argument("--xi-norms", dest="xi_norms", type=_floats,
                        help="comma-separated ||xi||_1 values (linear MDP)")
    common.add_argument("--beta", type=float, help="pessimism scale beta")
    common.add_argument("--gamma", type=float, help="ridge parameter gamma")
    common.add_argument("--divergences", type=lambda t: t.split(","),
                        help="comma-separated divergences, e.g. tv,kl,chi2")
    common.add_argument("--evaluation", choices=["exact", "mc"],
                        help="exact evaluation (default) or the paper's Monte Carlo protocol")
    common.add_argument("--test-episodes", dest="test_episodes", type=int,
                        help="Monte Carlo test episodes per replication (with --evaluation mc)")
    common.add_argument("--repeats", type=int, help="timed fits per setting (fig2a, fig2b)")
    rep.set_defaults(func=_reproduce)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
