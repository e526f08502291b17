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
import tomllib
from pathlib import Path

__all__ = ["load_toml", "merge_settings", "parse_assignment"]


def load_toml(path) -> dict:
    """Read a TOML config file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"config file not found: {path}")
    with open(path, "rb") as fh:
        return tomllib.load(fh)


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
