"""Save and load fitted feature maps: versioned ``.npz`` with a JSON header (no pickle)."""

from __future__ import annotations

import numbers

import numpy as np

from .._compat import not_fitted_error
from .._io import load_npz, save_npz
from ._base import SAVEABLE_MAPS

__all__ = ["save_feature_map", "load_feature_map", "SaveableMap"]

FEATURE_MAP_FORMAT_VERSION = 1


def _registry() -> dict:
    """The saveable observation maps (the action crossing is the file's outer layer)."""
    return {n: c for n, c in SAVEABLE_MAPS.items() if n != "ActionCrossing"}


def _encode(state_map, prefix: str, arrays: dict) -> dict:
    name = type(state_map).__name__
    if name not in _registry() or type(state_map) is not _registry()[name]:
        raise TypeError(
            f"only r2pvi's feature maps can be saved, got {name}; save your own map's "
            "parameters yourself"
        )
    if not hasattr(state_map, "low_"):
        raise not_fitted_error()(f"this {name} is not fitted yet; call fit(observations) first")
    params = {}
    for key, value in state_map.get_params().items():
        if value is None or isinstance(value, bool | str):
            params[key] = value
        elif isinstance(value, numbers.Integral):
            params[key] = int(value)
        elif isinstance(value, numbers.Real):
            params[key] = float(value)
        else:
            arr = np.asarray(value)
            if arr.dtype.kind not in "iuf":
                raise TypeError(
                    f"cannot save parameter {key}={value!r} of {name}: pass an integer seed "
                    "(not a Generator) or numeric arrays"
                )
            arrays[f"{prefix}param_{key}"] = arr
            params[key] = {"__array__": f"{prefix}param_{key}"}
    fitted = sorted(k for k in vars(state_map) if k.endswith("_") and not k.startswith("_"))
    for key in fitted:
        arrays[f"{prefix}fitted_{key}"] = np.asarray(getattr(state_map, key))
    return {"class": name, "params": params, "fitted": fitted}


def _decode(spec: dict, prefix: str, arrays: dict):
    cls = _registry().get(spec.get("class"))
    if cls is None:
        raise ValueError(f"unknown feature map class {spec.get('class')!r}")
    params = {k: arrays[v["__array__"]] if isinstance(v, dict) else v
              for k, v in spec["params"].items()}
    m = cls(**params)
    for key in spec["fitted"]:
        value = arrays[f"{prefix}fitted_{key}"]
        if value.ndim == 0:
            value = value.item()
        setattr(m, key, value)
    return m


def save_feature_map(feature_map, path):
    """Save a fitted r2pvi feature map (an observation map or its :class:`ActionCrossing`).

    Returns the path written; :func:`load_feature_map` reads it back.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from r2pvi.features import TileCoding, cross_actions, load_feature_map
    >>> X = np.random.default_rng(0).normal(size=(50, 2))
    >>> fmap = cross_actions(TileCoding(n_tilings=2, n_tiles=3).fit(X), n_actions=2)
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     back = load_feature_map(fmap.save(os.path.join(tmp, "fmap.npz")))
    >>> bool((back(X, np.ones(50, int)) == fmap(X, np.ones(50, int))).all())
    True
    """
    arrays: dict = {}
    if isinstance(feature_map, SAVEABLE_MAPS["ActionCrossing"]):
        meta = {"state_map": _encode(feature_map.state_map, "state_", arrays),
                "n_actions": feature_map.n_actions}
    else:
        meta = {"state_map": _encode(feature_map, "state_", arrays), "n_actions": None}
    return save_npz(path, "feature_map", FEATURE_MAP_FORMAT_VERSION, arrays, meta)


def load_feature_map(path):
    """Load a feature map written by :func:`save_feature_map` (fitted, ready to transform)."""
    arrays, header = load_npz(path, "feature_map", FEATURE_MAP_FORMAT_VERSION)
    state_map = _decode(header["state_map"], "state_", arrays)
    n_actions = header.get("n_actions")
    crossing = SAVEABLE_MAPS["ActionCrossing"]
    return state_map if n_actions is None else crossing(state_map, int(n_actions))


class SaveableMap:
    """Mixin of r2pvi's feature maps: ``save(path)`` writes :func:`save_feature_map`'s file."""

    def save(self, path):
        """Save the fitted map to a versioned ``.npz`` (no pickle); returns the path.

        Load it with :func:`r2pvi.features.load_feature_map`.
        """
        return save_feature_map(self, path)
