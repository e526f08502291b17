"""Tidy result files (one row per setting x replication) and the terminal summary."""

from __future__ import annotations

import csv
import json
import math
from collections import defaultdict
from pathlib import Path

__all__ = ["write_results", "read_results", "summarize", "format_table"]


def _version() -> str:
    from .. import __version__

    return __version__


def write_results(rows: list[dict], out_dir, name: str, config: dict) -> dict[str, Path]:
    """Write ``name.csv`` and ``name.json`` (rows with the configuration and library version).

    Every row carries the figure name and the r2pvi version; the JSON file also holds the
    full configuration that produced the rows.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    version = _version()
    rows = [{"figure": name, "r2pvi_version": version, **row} for row in rows]
    columns: list[str] = []
    for row in rows:
        for key in row:
            if key not in columns:
                columns.append(key)
    csv_path = out / f"{name}.csv"
    with open(csv_path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k, "") for k in columns})
    json_path = out / f"{name}.json"
    with open(json_path, "w") as fh:
        json.dump({"figure": name, "r2pvi_version": version, "config": config, "rows": rows},
                  fh, indent=1, default=_jsonable)
    return {"csv": csv_path, "json": json_path}


def read_results(path) -> dict:
    """Read a results JSON written by :func:`write_results`."""
    with open(path) as fh:
        return json.load(fh)


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
    cells ``mean±std``."""
    rows = list(dict.fromkeys(s[row_key] for s in summary))
    cols = list(dict.fromkeys(s[col_key] for s in summary))
    cell = {(s[row_key], s[col_key]): f"{s['mean']:.{digits}f}±{s['std']:.{digits}f}"
            for s in summary}
    width = max([len(str(r)) for r in rows] + [len(row_key)])
    cw = max([len(c) for c in cell.values()] + [len(str(c)) for c in cols] + [4])
    lines = [f"{row_key:<{width}} " + " ".join(f"{str(c):>{cw}}" for c in cols)]
    for r in rows:
        lines.append(f"{str(r):<{width}} " + " ".join(f"{cell.get((r, c), '-'):>{cw}}"
                                                       for c in cols))
    return "\n".join(lines)
