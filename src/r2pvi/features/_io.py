"""Save and load fitted feature maps: versioned ``.npz`` with a JSON header (no pickle)."""

from __future__ import annotations

import numbers

import numpy as np

from .._compat import not_fitted_error
from .._io import file_array, file_error, load_npz, save_npz
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


def _decode(spec, prefix: str, arrays: dict, path):
    """The observation map described by ``spec`` (the header's ``state_map``), every field
    checked: the class, the parameters (through ``fit``'s own checks), and each fitted array
    (present, numeric, finite, of the shape and, where ``fit`` determines it, the value that
    fitting the map on its own ranges gives)."""
    if not isinstance(spec, dict):
        raise file_error(path, "state_map", f"must be a JSON object, got {type(spec).__name__}")
    cls = _registry().get(spec.get("class"))
    if cls is None or not isinstance(spec.get("class"), str):
        raise file_error(path, "state_map.class", f"is {spec.get('class')!r}, not one of "
                         f"{sorted(_registry())}")
    raw, fitted = spec.get("params"), spec.get("fitted")
    if not isinstance(raw, dict):
        raise file_error(path, "state_map.params", "must be a JSON object")
    if not isinstance(fitted, list) or not all(isinstance(k, str) for k in fitted):
        raise file_error(path, "state_map.fitted", "must be a list of attribute names")
    params = {}
    for key, value in raw.items():
        if isinstance(value, dict):
            name = str(value.get("__array__"))
            file_array(path, arrays, name)  # present, numeric, finite
            value = arrays[name]
        params[key] = value
    try:
        m = cls(**params)
    except TypeError as exc:
        raise file_error(path, "state_map.params", f"do not fit {cls.__name__}: {exc}") from None
    for key in fitted:
        name = f"{prefix}fitted_{key}"
        file_array(path, arrays, name)  # present, numeric, finite
        value = arrays[name]
        setattr(m, key, value.item() if value.ndim == 0 else value)
    _check_fitted(path, prefix, m, cls, params, fitted)
    return m


def _check_fitted(path, prefix: str, m, cls, params: dict, fitted: list) -> None:
    """The loaded map's fitted attributes are those ``fit`` makes from its parameters and its
    observation ranges: refit twice on ``[low_, high_]`` (values that differ between the two
    refits are random, e.g. tile offsets without a seed: only their shapes are compared)."""
    low, high = getattr(m, "low_", None), getattr(m, "high_", None)
    if low is None or high is None or np.ndim(low) != 1 or np.shape(low) != np.shape(high) \
            or np.any(np.asarray(high) <= np.asarray(low)):
        raise file_error(path, f"{prefix}fitted_high_", "must be above low_ in every dimension "
                         "(the fitted observation ranges)")
    try:
        refits = [cls(**params).fit(np.stack([low, high])) for _ in range(2)]
    except (TypeError, ValueError) as exc:
        raise file_error(path, "state_map.params", f"fail {cls.__name__}'s checks: {exc}") \
            from None
    want = sorted(k for k in vars(refits[0]) if k.endswith("_") and not k.startswith("_"))
    if sorted(fitted) != want:
        raise file_error(path, "state_map.fitted", f"lists {sorted(fitted)}, a fitted "
                         f"{cls.__name__} has {want}")
    for key in want:
        got, ref, other = (np.asarray(getattr(x, key)) for x in (m, *refits))
        if got.shape != ref.shape:
            raise file_error(path, f"{prefix}fitted_{key}", f"must have shape {ref.shape}, got "
                             f"{got.shape}")
        if np.array_equal(ref, other) and not np.allclose(got, ref, rtol=1e-12, atol=0.0):
            raise file_error(path, f"{prefix}fitted_{key}", f"is not what {cls.__name__} "
                             "fits from its parameters and ranges: the file was altered")


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
    if "state_map" not in header:
        raise file_error(path, "state_map", "is missing")
    state_map = _decode(header["state_map"], "state_", arrays, path)
    if "n_actions" not in header:
        raise file_error(path, "n_actions", "is missing (null for an observation map)")
    n_actions = header["n_actions"]
    if n_actions is None:
        return state_map
    if isinstance(n_actions, bool) or not isinstance(n_actions, int) or n_actions < 1:
        raise file_error(path, "n_actions", f"must be null or an integer >= 1, got "
                         f"{n_actions!r}")
    return SAVEABLE_MAPS["ActionCrossing"](state_map, n_actions)


class SaveableMap:
    """Mixin of r2pvi's feature maps: ``save(path)`` writes :func:`save_feature_map`'s file."""

    def save(self, path):
        """Save the fitted map to a versioned ``.npz`` (no pickle); returns the path.

        Load it with :func:`r2pvi.features.load_feature_map`.
        """
        return save_feature_map(self, path)
