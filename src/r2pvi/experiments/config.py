"""Settings of a figure: defaults, then a TOML file, then command-line overrides.

A TOML file may set keys for every figure at the top level and per figure in a table named
after it::

    replications = 10          # every figure that has this setting
    [fig1a]
    lam = 0.3
    xi_norms = [0.2]
"""

from __future__ import annotations

import ast
import math
import tomllib
from pathlib import Path

__all__ = ["load_toml", "merge_settings", "parse_assignment", "check_toml_keys",
           "check_settings", "MAX_REPLICATIONS"]

#: Upper bound on ``replications`` (each figure builds one task per setting x replication).
MAX_REPLICATIONS = 10_000


def load_toml(path) -> dict:
    """Read a TOML config file (a ``ValueError`` naming the file when it is not UTF-8 TOML)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"config file not found: {path}")
    if path.is_dir():
        raise ValueError(f"config file {path} is a directory, not a TOML file")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"config file {path} is not UTF-8 text: {exc}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"config file {path} is not valid TOML: {exc}") from None


def check_toml_keys(toml: dict, figures: dict[str, dict], source: str = "config file") -> None:
    """Reject unknown tables and keys of a TOML config, listing the valid names.

    ``figures`` maps each figure name to its default settings. Tables must be figure names;
    a top-level key must be a setting of some figure; a key in ``[fig]`` a setting of fig.
    """
    every = sorted({k for d in figures.values() for k in d})
    for key, value in toml.items():
        if isinstance(value, dict):
            if key not in figures:
                raise ValueError(
                    f"{source}: unknown table [{key}]; tables are figure names: "
                    f"{', '.join(figures)}"
                )
            for sub in value:
                if sub.replace("-", "_") not in figures[key]:
                    raise ValueError(
                        f"{source}: [{key}] has no setting {sub!r}; its settings are: "
                        f"{', '.join(sorted(figures[key]))}"
                    )
        elif key.replace("-", "_") not in every:
            raise ValueError(
                f"{source}: unknown setting {key!r}; settings are: {', '.join(every)}"
            )


def parse_assignment(text: str) -> tuple[str, object]:
    """``"key=value"`` with a Python/TOML-like literal value (number, list, string, bool)."""
    if "=" not in text:
        raise ValueError(f"--set expects key=value, got {text!r}")
    key, raw = text.split("=", 1)
    key = key.strip().replace("-", "_")
    raw = raw.strip()
    low = raw.lower()
    if low in ("true", "false"):
        return key, low == "true"
    try:
        return key, ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        return key, raw


def _coerce(name: str, value, default):
    """Match the type of the default (a scalar given for a list setting becomes a list)."""
    if isinstance(default, list) and not isinstance(value, list | tuple):
        value = [value]
    if isinstance(default, list):
        return [_coerce(name, v, default[0]) if default else v for v in value]
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise TypeError(f"setting {name!r} must be true or false, got {value!r}")
        return value
    if isinstance(default, int) and not isinstance(default, bool):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if not isinstance(value, int) or isinstance(value, bool):
            raise TypeError(f"setting {name!r} must be an integer, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TypeError(f"setting {name!r} must be a number, got {value!r}")
        return float(value)
    return value


def merge_settings(figure: str, defaults: dict, toml: dict | None = None,
                   overrides: dict | None = None) -> dict:
    """Defaults < top-level TOML keys < ``[figure]`` TOML table < command-line overrides.

    Keys the figure does not have are ignored when they come from the shared top level of a
    TOML file, and rejected (with the list of valid keys) when aimed at this figure.
    """
    settings = dict(defaults)
    toml = toml or {}
    shared = {k: v for k, v in toml.items() if not isinstance(v, dict)}
    layers = [(shared, False), (toml.get(figure, {}), True), (overrides or {}, True)]
    for layer, strict in layers:
        for key, value in layer.items():
            key = key.replace("-", "_")
            if key not in defaults:
                if strict:
                    raise ValueError(
                        f"{figure} has no setting {key!r}; its settings are: "
                        f"{', '.join(sorted(defaults))}"
                    )
                continue
            settings[key] = _coerce(key, value, defaults[key])
    return settings


# --------------------------------------------------------------------------- value checks
def _count(low=1, high=None):
    def check(name, v):
        if isinstance(v, bool) or not isinstance(v, int):
            return "must be an integer"
        if v < low:
            return f"must be >= {low}, got {v}"
        if high is not None and v > high:
            return (f"must be <= {high}, got {v}; for more, run several sweeps with different "
                    "--seed values")
        return None
    return check


def _real(low=None, high=None, low_open=False, high_open=False):
    def check(name, v):
        if isinstance(v, bool) or not isinstance(v, int | float):
            return "must be a number"
        if not math.isfinite(v):
            return f"must be finite, got {v}"
        if low is not None and (v <= low if low_open else v < low):
            return f"must be {'>' if low_open else '>='} {low}, got {v}"
        if high is not None and (v >= high if high_open else v > high):
            return f"must be {'<' if high_open else '<='} {high}, got {v}"
        return None
    return check


def _choice(*choices):
    def check(name, v):
        if v not in choices:
            return f"must be one of {', '.join(map(str, choices))}; got {v!r}"
        return None
    return check


def _divergence(name, v):
    from ..duals.fdivergence import get_divergence

    try:
        get_divergence(v)
    except (TypeError, ValueError):
        return f"names an unknown divergence {v!r}; use 'tv', 'kl', 'chi2' or 'hellinger'"
    return None


def _beta(name, v):
    if v == "theory":
        return None
    return _real(low=0.0)(name, v)


_UNIT = _real(0.0, 1.0)
_RULES = {
    "replications": _count(1, MAX_REPLICATIONS),
    "trajectories": _count(1),
    "trajectories_grid": _count(1),
    "features_grid": _count(1),
    "test_episodes": _count(2),
    "repeats": _count(1),
    "horizon": _count(1),
    "features": _count(1),
    "hard_d": _count(1, 16),
    "hard_H": _count(1),
    "bootstrap": _count(1),
    "bootstrap_seed": _count(0),
    "state": _count(0),
    "blas_threads": _count(0),
    "delta": _UNIT,
    "mdp_delta": _UNIT,
    "q": _UNIT,
    "qs": _UNIT,
    "p0": _UNIT,
    "price_up": _UNIT,
    "xi_norm": _real(0.0),
    "xi_norms": _real(0.0),
    "lam": _real(0.0, low_open=True),
    "lams": _real(0.0, low_open=True),
    "gamma": _real(0.0, low_open=True),
    "strike": _real(0.0, low_open=True),
    "anchor_span": _real(0.0, low_open=True),
    "beta": _real(0.0),
    "betas": _beta,
    "rho": _real(0.0),
    "rhos": _real(0.0),
    "evaluation": _choice("exact", "mc"),
    "penalty": _choice("l1", "l2", "elliptical"),
    "divergence": _divergence,
    "divergences": _divergence,
    "envs": _choice("simulated", "hard"),
}
# The theory figures' delta is the theorem's confidence, in (0, 1); their divergences are
# the closed forms.
_FIGURE_RULES = {
    ("rates", "delta"): _real(0.0, 1.0, low_open=True, high_open=True),
    ("bound-check", "delta"): _real(0.0, 1.0, low_open=True, high_open=True),
    ("rates", "divergences"): _choice("tv", "kl", "chi2"),
    ("bound-check", "divergences"): _choice("tv", "kl", "chi2"),
    # the noisy CartPole benchmark (r2pvi.experiments.figures.cartpole_protocol)
    ("cartpole", "episodes"): _count(2),
    ("cartpole", "centers"): _count(2),
    ("cartpole", "epsilon"): _UNIT,
    ("cartpole", "drvil_rhos"): _real(0.0, low_open=True),
    ("cartpole", "forms"): _choice("pooled", "per-step"),
    ("cartpole", "estimators"): _choice("PEVI", "R2PVI", "DRPVI", "DRVI-L"),
}


def check_settings(figure: str, settings: dict) -> dict:
    """Check every setting's value (after :func:`merge_settings`): lists non-empty, counts,
    ranges and names. Raises a ``ValueError`` naming the figure and the setting."""
    for name, value in settings.items():
        rule = _FIGURE_RULES.get((figure, name), _RULES.get(name))
        values = value if isinstance(value, list) else [value]
        if isinstance(value, list) and not value:
            raise ValueError(f"{figure}: setting {name!r} must be a non-empty list")
        if rule is None:
            continue
        for v in values:
            problem = rule(name, v)
            if problem:
                raise ValueError(f"{figure}: setting {name!r} {problem}")
    _check_simulated_mdp(figure, settings)
    return settings


def _check_simulated_mdp(figure: str, s: dict) -> None:
    """The simulated linear MDP's joint constraint ``xi_norm <= delta <= 1 - xi_norm``."""
    from ..envs import SimulatedLinearMDP

    if "xi_norms" in s and "delta" in s:
        pairs = [("delta", s["delta"], x) for x in s["xi_norms"]]
    elif "xi_norm" in s and "mdp_delta" in s and "simulated" in s.get("envs", ()):
        pairs = [("mdp_delta", s["mdp_delta"], s["xi_norm"])]
    else:
        return
    for name, delta, xi_norm in pairs:
        try:
            SimulatedLinearMDP(delta=delta, xi_norm=xi_norm)
        except ValueError as exc:
            raise ValueError(f"{figure}: settings {name!r} and xi_norm: {exc}") from None
