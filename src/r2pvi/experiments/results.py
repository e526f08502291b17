"""Tidy result files (one row per setting x replication) and the terminal summary."""

from __future__ import annotations

import csv
import json
import math
from collections import defaultdict
from pathlib import Path

__all__ = ["write_results", "read_results", "summarize", "format_table", "RESULTS_FORMAT"]

RESULTS_FORMAT = "r2pvi-results/2"


def _version() -> str:
    from .. import __version__

    return __version__


def write_results(rows: list[dict], out_dir, name: str, config: dict, *,
                  quantity: str | None = None, unit: str | None = None) -> dict[str, Path]:
    """Write ``name.csv`` and ``name.json`` (rows with the configuration and library version).

    Every CSV row carries the figure name and the r2pvi version, and, when given, the
    ``quantity`` and ``unit`` of its ``value`` column (say ``"average return"`` and
    ``"return"``, or ``"fit time"`` and ``"s"``), so that a CSV read on its own says what its
    numbers are. Rows that set their own ``quantity``/``unit`` keep them.

    The JSON file (format ``"r2pvi-results/2"``) holds the full configuration, the figure
    name, version, quantity and unit once, the ``columns`` and the ``rows`` as lists of values
    in column order (one compact line per row; a value a row lacks is ``null``). Read it back
    as dictionaries with :func:`read_results`.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    version = _version()
    described = {k: v for k, v in (("quantity", quantity), ("unit", unit)) if v is not None}
    rows = [_with_quantity(row, described) for row in rows]
    columns: list[str] = ["figure", "r2pvi_version"]
    for row in rows:
        for key in row:
            if key not in columns:
                columns.append(key)
    csv_path = out / f"{name}.csv"
    with open(csv_path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({"figure": name, "r2pvi_version": version,
                             **{k: row.get(k, "") for k in columns[2:]}})
    json_path = out / f"{name}.json"
    # constant quantity/unit columns are stored once, in the header
    json_columns = [c for c in columns[2:] if not (
        c in described and all(row[c] == described[c] for row in rows))]
    header = {"format": RESULTS_FORMAT, "figure": name, "r2pvi_version": version, **described,
              "config": config, "columns": json_columns}
    with open(json_path, "w") as fh:
        text = json.dumps(header, indent=1, default=_jsonable)
        fh.write(text[:-2] + ',\n "rows": [\n')
        fh.write(",\n".join(
            json.dumps([row.get(k) for k in json_columns], separators=(",", ":"),
                       default=_jsonable) for row in rows))
        fh.write("\n ]\n}\n")
    return {"csv": csv_path, "json": json_path}


def _with_quantity(row: dict, described: dict) -> dict:
    """``row`` with ``quantity`` and ``unit`` just before ``value`` (row's own win)."""
    if not described:
        return dict(row)
    out = {}
    for key, val in row.items():
        if key == "value":
            for k, v in described.items():
                out.setdefault(k, row.get(k, v))
        out.setdefault(key, val)
    for k, v in described.items():
        out.setdefault(k, v)
    return out


def read_results(path) -> dict:
    """Read a results JSON written by :func:`write_results`.

    Rows come back as dictionaries, each with the figure name and library version of the
    file (stored once); keys a row did not have (``null`` in the file) are left out.
    """
    with open(path) as fh:
        data = json.load(fh)
    if data.get("format") != RESULTS_FORMAT:
        raise ValueError(f"{path}: not an r2pvi results file of format {RESULTS_FORMAT!r} "
                         f"(found format {data.get('format')!r}); rerun r2pvi reproduce")
    columns = data.pop("columns")
    const = {k: data[k] for k in ("figure", "r2pvi_version", "quantity", "unit")
             if k in data and k not in columns}
    data["rows"] = [{**const, **{k: v for k, v in zip(columns, values, strict=True)
                                 if v is not None}} for values in data["rows"]]
    return data


def _jsonable(x):
    if hasattr(x, "tolist"):
        return x.tolist()
    if hasattr(x, "item"):
        return x.item()
    return str(x)


def summarize(rows: list[dict], keys: list[str], value: str = "value") -> list[dict]:
    """Mean, standard deviation and count of ``value`` over rows grouped by ``keys``."""
    groups: dict[tuple, list[float]] = defaultdict(list)
    for row in rows:
        groups[tuple(row.get(k) for k in keys)].append(float(row[value]))
    out = []
    for key, vals in groups.items():
        n = len(vals)
        mean = sum(vals) / n
        std = math.sqrt(sum((x - mean) ** 2 for x in vals) / (n - 1)) if n > 1 else 0.0
        out.append({**dict(zip(keys, key, strict=True)), "mean": mean, "std": std, "n": n})
    return out


def format_table(summary: list[dict], row_key: str, col_key: str, digits: int = 3) -> str:
    """A compact text table: one line per ``row_key`` value, one column per ``col_key`` value,
    cells ``mean±std`` (just the mean when it comes from a single row: no spread to show).

    Examples
    --------
    >>> rows = [{"a": "x", "q": 0, "value": 1.0}, {"a": "x", "q": 0, "value": 3.0},
    ...         {"a": "y", "q": 0, "value": 2.0}]
    >>> print(format_table(summarize(rows, ["a", "q"]), "a", "q", digits=2))
    a         0
    x 2.00±1.41
    y      2.00
    """
    rows = list(dict.fromkeys(s[row_key] for s in summary))
    cols = list(dict.fromkeys(s[col_key] for s in summary))
    cell = {(s[row_key], s[col_key]): f"{s['mean']:.{digits}f}" + (
            f"±{s['std']:.{digits}f}" if s.get("n", 2) > 1 else "") for s in summary}
    width = max([len(str(r)) for r in rows] + [len(row_key)])
    cw = max([len(c) for c in cell.values()] + [len(str(c)) for c in cols] + [4])
    lines = [f"{row_key:<{width}} " + " ".join(f"{str(c):>{cw}}" for c in cols)]
    for r in rows:
        lines.append(f"{str(r):<{width}} " + " ".join(f"{cell.get((r, c), '-'):>{cw}}"
                                                       for c in cols))
    return "\n".join(lines)
