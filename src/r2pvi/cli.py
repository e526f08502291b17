"""Command-line interface: ``r2pvi demo``, ``r2pvi reproduce`` and ``r2pvi --version``.

Every setting is checked before any work starts. A usage error prints one line
``r2pvi: error: ...`` on standard error and exits with status 2 (argparse's convention); an
error while running prints one line and exits with status 1. ``--debug`` (before the
command: ``r2pvi --debug reproduce ...``) shows the traceback instead.
"""

from __future__ import annotations

import argparse
import difflib
import importlib.util
import os
import sys
import tempfile
from pathlib import Path

EXIT_USAGE = 2
EXIT_FAILURE = 1


class UsageError(Exception):
    """A bad command line or configuration: reported in one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``r2pvi: error: ...``); subcommands inherit it."""

    def error(self, message):
        raise UsageError(f"{message} (see '{self.prog} --help')")


# --------------------------------------------------------------------------- argument types
def _floats(text):
    return [float(x) for x in text.split(",")]


_floats.__name__ = "comma-separated numbers"


def _names(text):
    return [x.strip() for x in text.split(",")]


# --------------------------------------------------------------------------- demo
def _demo(args) -> int:
    from .demo import run_demo

    if args.trajectories < 1:
        raise UsageError(f"--trajectories must be >= 1, got {args.trajectories}")
    if args.seed < 0:
        raise UsageError(f"--seed must be >= 0, got {args.seed}")
    run_demo(seed=args.seed, n_trajectories=args.trajectories)
    return 0


# --------------------------------------------------------------------------- reproduce
_FLAG_SETTINGS = ("lam", "lams", "rho", "rhos", "replications", "trajectories", "xi_norms",
                  "beta", "gamma", "evaluation", "test_episodes", "divergences", "repeats")


def _need(module: str, extra: str, what: str):
    if importlib.util.find_spec(module) is None:
        raise UsageError(f"{what} needs {module}: pip install 'r2pvi[{extra}]'")


def _check_out(out: str) -> Path:
    """Create the output directory and check that a file can be written there."""
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise UsageError(f"--out {out}: exists and is not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        raise UsageError(f"--out {out}: not a writable directory ({exc.strerror or exc})") \
            from None
    return path


def _jobs(jobs: int) -> int:
    if jobs == -1:
        return os.cpu_count() or 1
    if jobs < 1:
        raise UsageError(f"--jobs must be >= 1, or -1 for one worker per core; got {jobs}")
    return jobs


def plan_reproduce(args) -> list[tuple[str, dict]]:
    """Every figure to run with its checked settings; raises UsageError before any work."""
    from .experiments.config import (
        check_settings,
        check_toml_keys,
        load_toml,
        merge_settings,
        parse_assignment,
    )
    from .experiments.figures import FIGURES, IN_ALL

    if args.figure != "all" and args.figure not in FIGURES:
        raise UsageError(f"unknown figure {args.figure!r}; choose from {', '.join(FIGURES)} "
                         "or all")
    # 'all' is the paper's figures; the classic-control benchmarks run by name only.
    names = list(IN_ALL) if args.figure == "all" else [args.figure]
    if args.seed < 0:
        raise UsageError(f"--seed must be >= 0, got {args.seed}")
    defaults = {name: fig.defaults for name, fig in FIGURES.items()}
    toml = None
    if args.config:
        try:
            toml = load_toml(args.config)
            check_toml_keys(toml, defaults, source=f"config file {args.config}")
        except (OSError, ValueError) as exc:
            raise UsageError(str(exc)) from None
    overrides = {}
    for text in args.set:
        try:
            key, value = parse_assignment(text)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        overrides[key] = value
    for key in _FLAG_SETTINGS:
        value = getattr(args, key, None)
        if value is not None:
            overrides[key] = value
    valid = sorted({k for n in names for k in defaults[n]})
    for key in overrides:
        if key not in valid:
            where = f"{args.figure} has no" if args.figure != "all" else "no figure has a"
            close = difflib.get_close_matches(key, valid, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise UsageError(f"{where} setting {key!r}; {hint}settings are: {', '.join(valid)}")
    plan = []
    for name in names:
        # Settings given for 'all' apply to the figures that have them (like a TOML top level).
        applicable = {k: v for k, v in overrides.items() if k in defaults[name]}
        try:
            settings = merge_settings(name, defaults[name], toml, applicable)
            check_settings(name, settings)
        except (TypeError, ValueError) as exc:
            raise UsageError(f"{name}: {exc}" if not str(exc).startswith(name) else str(exc)) \
                from None
        plan.append((name, settings))
    return plan


def _reproduce(args) -> int:
    plan = plan_reproduce(args)
    jobs = _jobs(args.jobs)
    if args.dask or args.scheduler:
        _need("distributed", "dask", "--dask/--scheduler")
        backend = "dask"
    else:
        backend = "joblib" if jobs > 1 else "serial"
        if backend == "joblib":
            _need("joblib", "experiments", f"--jobs {args.jobs}")
    if not args.no_plot:
        _need("matplotlib", "experiments", "plotting (pass --no-plot to skip the plots)")
    if not args.no_progress:
        _need("tqdm", "experiments", "the progress bars (pass --no-progress)")
    out = _check_out(args.out)  # last check: it creates the directory
    from .experiments import reproduce

    finished = []
    for name, settings in plan:
        result = reproduce.reproduce_figure(
            name, out, overrides=settings, seed=args.seed, backend=backend, jobs=jobs,
            scheduler=args.scheduler, progress=not args.no_progress, plot=False)
        finished.append((name, result["rows"], result["settings"]))
    if not args.no_plot:
        # The plots are drawn after the sweeps, in parallel (joblib) when there are several:
        # drawn one by one between the sweeps they kept a core idle.
        parallel = jobs if backend == "joblib" else 1
        if len(finished) > 1:
            print(f"\ndrawing {len(finished)} plots"
                  + (f" in {min(parallel, len(finished))} processes" if parallel > 1 else ""),
                  flush=True)
        reproduce.draw_plots(finished, out, jobs=parallel)
        if len(finished) > 1:
            print(f"plots (PNG and PDF) in {out}")
    return 0


# --------------------------------------------------------------------------- parser
def _version() -> str:
    from . import __version__

    return __version__


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="r2pvi",
        description="Robust offline RL with linearly structured f-divergence regularization.",
        epilog="Errors print one line and exit with status 2 (usage) or 1 (failure); "
        "r2pvi --debug COMMAND ... shows the traceback.",
    )
    parser.add_argument("--debug", action="store_true",
                        help="show the full traceback of an error")
    parser.add_argument("-V", "--version", action="version", version=f"r2pvi {_version()}",
                        help="print the installed version (r2pvi X.Y.Z) and exit")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser(
        "demo",
        help="one-second tour: PEVI and R2PVI (TV, KL, chi^2) returns under a dynamics shift",
        description="Fit PEVI and the three R2PVI variants on small datasets of the paper's "
        "simulated linear MDP and print their exact returns, side by side, in test "
        "environments with increasing shifts of the dynamics. Every divergence runs at the "
        "same three lam: 0.1, 0.01 and 0.001 times the value range of the data.",
    )
    demo.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                      help="show the full traceback of an error")
    demo.add_argument("--seed", type=int, default=0, help="random seed >= 0 (default 0)")
    demo.add_argument("--trajectories", type=int, default=100,
                      help="K >= 1 per dataset (default 100, the paper's)")
    demo.set_defaults(func=_demo)

    rep = sub.add_parser(
        "reproduce",
        help="reproduce a figure of the paper (or all of them): results, plots, summary",
        description="Run the sweep behind a figure of the paper's Experiment section and write "
        "NAME.csv and NAME.json (one row per setting x replication, with the configuration and "
        "library version), NAME.png and NAME.pdf, and print a summary table. Settings come from "
        "the figure's defaults (the paper's), then --config FILE.toml, then the flags below and "
        "--set key=value; unknown settings and bad values are rejected before any work. "
        "Figures: fig1a fig1b fig1c fig1d fig2a fig2b va (the paper's) and rates bound-check "
        "(its theory); run by name only (not in 'all'): cartpole mountaincar "
        "(classic-control robustness benchmarks). Each worker process uses one BLAS thread "
        "(set R2PVI_BLAS_THREADS to change it).",
    )
    rep.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                     help="show the full traceback of an error")
    rep.add_argument("figure", help="figure name (fig1a ... va, rates, bound-check) or 'all'")
    rep.add_argument("--out", default="results", help="output directory (default: results)")
    rep.add_argument("--config", help="TOML file with settings (top level or [figure] tables)")
    rep.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                     help="override any setting, e.g. --set qs=[0,0.5,1] (repeatable)")
    rep.add_argument("--seed", type=int, default=0, help="root seed of the sweep, >= 0 "
                     "(default 0)")
    rep.add_argument("--jobs", type=int, default=-1,
                     help="local worker processes (joblib), one BLAS thread each; -1 (the "
                     "default) = one per core, 1 = run serially in this process")
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
    common.add_argument("--replications", type=int, help="replications per setting (1 to "
                        "10000)")
    common.add_argument("--trajectories", type=int, help="dataset size K (N)")
    common.add_argument("--xi-norms", dest="xi_norms", type=_floats,
                        help="comma-separated ||xi||_1 values (linear MDP)")
    common.add_argument("--beta", type=float, help="pessimism scale beta")
    common.add_argument("--gamma", type=float, help="ridge parameter gamma")
    common.add_argument("--divergences", type=_names,
                        help="comma-separated divergences, e.g. tv,kl,chi2")
    common.add_argument("--evaluation", choices=["exact", "mc"],
                        help="exact evaluation (default) or the paper's Monte Carlo protocol")
    common.add_argument("--test-episodes", dest="test_episodes", type=int,
                        help="Monte Carlo test episodes per replication (>= 2, with "
                        "--evaluation mc)")
    common.add_argument("--repeats", type=int, help="timed fits per setting (fig2a, fig2b)")
    rep.set_defaults(func=_reproduce)
    return parser


def _fail(message: str, status: int) -> int:
    print(f"r2pvi: error: {message}", file=sys.stderr)
    return status


def main(argv=None) -> int:
    """Run the command line; returns the exit status (0, 1 or 2)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in argv[: argv.index("--") if "--" in argv else len(argv)]
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except UsageError as exc:
        if debug:
            raise
        return _fail(str(exc), EXIT_USAGE)
    except KeyboardInterrupt:
        if debug:
            raise
        return _fail("interrupted", 130)
    except MemoryError:
        if debug:
            raise
        return _fail("out of memory: use smaller settings (trajectories, features, "
                     "replications) or fewer --jobs", EXIT_FAILURE)
    except Exception as exc:  # one line for users; --debug shows the traceback
        if debug:
            raise
        text = " ".join(str(exc).split()) or type(exc).__name__
        return _fail(f"{text} ({type(exc).__name__}; rerun with --debug for the traceback)",
                     EXIT_FAILURE)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
