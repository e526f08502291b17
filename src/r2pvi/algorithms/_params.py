"""Parameter helpers shared by the robust estimators (R2PVI, DRPVI, DRVI-L)."""

from __future__ import annotations

import numbers
import re

import numpy as np

from .._validation import check_scalar, plain

__all__ = ["floor_value", "check_v_min", "check_radius", "check_flag", "shared_docs"]

# Parameter descriptions that every estimator shares, written once: a class docstring holds
# the marker line ``{name}`` (indented as the description) and :func:`shared_docs` fills it.
_SHARED_DOCS = {
    "time_homogeneous": """\
Pooled steps: every step's regressions use the transitions of steps 0 .. H-2 (the
last step's next states are not data), with one Gram matrix factored once (per-step
work: next-state values and regressions). Valid only when the nominal dynamics and
rewards do not depend on h (a time-homogeneous MDP, e.g. a Gymnasium environment);
False is the paper's per-step estimator. "auto" pools the steps of a dataset whose
steps are stationary (:attr:`OfflineDataset.stationary
<r2pvi.OfflineDataset.stationary>`: built from episodes of an environment) and fits
the others per step (the paper's experiments); ``fit_report_.pooled`` says which.""",
}


def shared_docs(cls):
    """Class decorator: fill the marker lines ``{name}`` of ``cls.__doc__`` with the shared
    parameter descriptions (indented as the marker)."""
    doc = cls.__doc__ or ""
    for name, text in _SHARED_DOCS.items():
        for indent in set(re.findall(r"^( *)\{" + name + r"\}$", doc, flags=re.M)):
            filled = "\n".join(indent + line for line in text.splitlines())
            doc = doc.replace(indent + "{" + name + "}", filled)
    cls.__doc__ = doc
    return cls


def floor_value(v_min, v: np.ndarray) -> float:
    """``min_s V(s)``: the minimum of the sampled values ``v`` when ``v_min == "data"``,
    else the given bound."""
    return float(np.min(v)) if v_min == "data" else v_min


def check_v_min(v_min) -> str | float:
    """Validate ``v_min``: the string "data" or a finite real number."""
    if isinstance(v_min, str):
        if v_min.lower() != "data":  # case-insensitive, as every string option
            raise ValueError(f"v_min must be 'data' or a number, got {v_min!r}")
        return "data"
    if isinstance(v_min, numbers.Real) and not isinstance(v_min, bool):
        return check_scalar(v_min, "v_min")
    raise TypeError(f"v_min must be 'data' or a number, got {plain(v_min)!r}")


def check_radius(rho, horizon: int, n_features: int, name: str = "rho") -> np.ndarray:
    """Uncertainty radii as an (H, d) array from a scalar, a (d,) vector or an (H, d) array."""
    if isinstance(rho, bool | str) or rho is None:
        raise TypeError(
            f"{name} must be a number, a (d,) vector or an (H, d) array of radii, got "
            f"{plain(rho)!r}"
        )
    if isinstance(rho, np.ndarray) and rho.dtype == object:
        raise TypeError(f"{name} must be a numeric array, got dtype object")
    try:
        arr = np.array(rho, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be numeric; could not convert it: {exc}") from None
    if np.iscomplexobj(np.asarray(rho)):
        raise TypeError(f"{name} must be real, got a complex value")
    H, d = horizon, n_features
    if arr.ndim == 0:
        arr = np.full((H, d), float(arr))
    elif arr.shape == (d,):
        arr = np.broadcast_to(arr, (H, d)).copy()
    elif arr.shape != (H, d):
        raise ValueError(
            f"{name} must be a scalar, a (d,) = ({d},) vector or an (H, d) = ({H}, {d}) array "
            f"matching the dataset, got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {int((~np.isfinite(arr)).sum())} bad entries")
    if np.any(arr < 0):
        raise ValueError(
            f"{name} must be >= 0 (0 = no uncertainty for that factor), got min "
            f"{plain(arr.min())!r}"
        )
    return arr


def check_flag(value, name: str) -> bool:
    """Validate a boolean switch (True/False or a NumPy bool)."""
    if not isinstance(value, bool | np.bool_):
        raise TypeError(f"{name} must be True or False, got {plain(value)!r}")
    return bool(value)
