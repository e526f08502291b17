"""Shared machinery of the observation feature maps: parameters, ranges, validation."""

from __future__ import annotations

import inspect
import numbers

import numpy as np

from .._compat import KeywordParams, not_fitted_error

__all__ = ["ObservationTransformer", "as_observations", "check_positive_int_or_seq",
           "SAVEABLE_MAPS", "register_saveable"]

#: The feature-map classes that :func:`~r2pvi.features.save_feature_map` writes and
#: :func:`~r2pvi.features.load_feature_map` rebuilds, by class name: r2pvi's own
#: :class:`ObservationTransformer` subclasses register themselves (``__init_subclass__``),
#: the action crossing through :func:`register_saveable`.
SAVEABLE_MAPS: dict[str, type] = {}


def register_saveable(cls: type) -> type:
    """Record an r2pvi feature-map class as one a model file may name (class decorator)."""
    SAVEABLE_MAPS[cls.__name__] = cls
    return cls


def as_observations(X, name: str = "observations", n_dims: int | None = None) -> np.ndarray:
    """Observations as a float ``(n, D)`` array (a copy never shares memory with ``X``).

    One-dimensional input is read as ``n`` scalar observations (``D = 1``); trailing axes
    beyond the first are flattened.
    """
    arr = np.asarray(X)
    if arr.dtype == object or arr.dtype.kind not in "biuf":
        raise TypeError(
            f"{name} must be a numeric array (n, D); got dtype {arr.dtype}. Flatten dict or "
            "tuple observations first (gymnasium.spaces.flatten)"
        )
    arr = arr.astype(np.float64)
    if arr.ndim == 0:
        raise ValueError(f"{name} must have one row per observation, got a scalar")
    arr = arr.reshape(arr.shape[0], -1) if arr.ndim != 1 else arr[:, None]
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinite entries")
    if n_dims is not None and arr.shape[1] != n_dims:
        if np.ndim(X) == 1 and arr.shape[0] == n_dims:
            raise ValueError(
                f"{name} of shape {np.shape(X)} read as {n_dims} observations of 1 dimension, "
                f"but the map was fitted on {n_dims}-dimensional ones: maps and policies take "
                f"a batch (n, {n_dims}); for one observation pass obs[None] (shape "
                f"(1, {n_dims}))"
            )
        raise ValueError(
            f"{name} have {arr.shape[1]} dimensions but the map was fitted on {n_dims}"
            + (f": pass a batch (n, {n_dims})" if np.ndim(X) == 1 else "")
        )
    return arr


def check_positive_int_or_seq(value, name: str, n_dims: int, minimum: int = 1) -> np.ndarray:
    """An integer (the same for every dimension) or one integer per dimension, as (D,)."""
    arr = np.asarray(value)
    if arr.dtype == bool or arr.dtype.kind not in "iu":
        raise TypeError(f"{name} must be an integer or a sequence of integers, got {value!r}")
    if arr.ndim == 0:
        arr = np.full(n_dims, int(arr))
    if arr.shape != (n_dims,):
        raise ValueError(
            f"{name} must be an integer or one integer per observation dimension ({n_dims}), "
            f"got shape {arr.shape}"
        )
    if (arr < minimum).any():
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}")
    return arr.astype(np.int64)


class ObservationTransformer(KeywordParams):
    """Base of the observation maps: scikit-learn transformer conventions.

    ``__init__`` stores keyword parameters; :meth:`fit` validates them, learns the
    observation ranges (``low_``, ``high_``) and returns ``self``; :meth:`transform` maps
    observations ``(n, D)`` to features ``(n, m)`` whose rows lie on the probability simplex.
    """

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.__module__.startswith("r2pvi.features."):  # r2pvi's own maps, not users'
            register_saveable(cls)


    sparse = False

    # ------------------------------------------------------------------ parameters
    def __repr__(self) -> str:
        sig = inspect.signature(type(self).__init__).parameters
        shown = []
        for name, value in self.get_params().items():
            default = sig[name].default
            if isinstance(value, np.ndarray) or isinstance(default, np.ndarray):
                shown.append(f"{name}=...")
            elif value is not default and value != default:
                shown.append(f"{name}={value!r}")
        return f"{type(self).__name__}({', '.join(shown)})"

    # ------------------------------------------------------------------ fitting
    def _fit_ranges(self, X: np.ndarray) -> None:
        """``low_``, ``high_`` (D,): the given ``ranges`` or the data's min and max."""
        D = X.shape[1]
        ranges = getattr(self, "ranges", None)
        if ranges is None:
            low, high = X.min(axis=0), X.max(axis=0)
        else:
            r = np.asarray(ranges, dtype=float)
            if r.shape == (2,) and D == 1:
                r = r[None]
            if r.shape != (D, 2):
                raise ValueError(
                    f"ranges must be (low, high) per observation dimension, shape ({D}, 2); "
                    f"got shape {r.shape}"
                )
            if not np.isfinite(r).all():
                raise ValueError(
                    "ranges must be finite; leave ranges=None to take them from the data "
                    "(Gymnasium's velocity bounds are often infinite)"
                )
            low, high = r[:, 0].copy(), r[:, 1].copy()
            if (high < low).any():
                raise ValueError("ranges must have low <= high in every dimension")
        width = high - low
        width[width <= 0] = 1.0  # a constant dimension: any positive width maps it to one cell
        self.low_, self.high_, self.width_ = low, low + width, width
        self.n_features_in_ = D

    def fit(self, X, y=None):
        """Learn the observation ranges from ``X (n, D)`` and return ``self``."""
        X = as_observations(X)
        if X.shape[0] == 0:
            raise ValueError("fit needs at least one observation")
        self._fit_ranges(X)
        self._fit_more(X)
        return self

    def _fit_more(self, X: np.ndarray) -> None:
        pass

    def _check_fitted(self) -> None:
        if not hasattr(self, "low_"):
            raise not_fitted_error()(
                f"this {type(self).__name__} is not fitted yet; call fit(observations) first "
                "(r2pvi.episodes.episode_observations(episodes) stacks an episode list's "
                "observations)"
            )

    def _scaled(self, X) -> np.ndarray:
        """Observations mapped to the unit box: ``(x - low) / (high - low)``, (n, D)."""
        self._check_fitted()
        return self._unit(as_observations(X, n_dims=self.n_features_in_))

    def _unit(self, X: np.ndarray) -> np.ndarray:
        """``(X - low) / width``, clipped to ``[-1e6, 1e6]``.

        Beyond 1e6 widths from the box every map is constant to machine precision (edge
        cells; one-hot RBF weights), so clipping keeps features finite and unchanged, even for
        a tiny (subnormal) fitted width.
        """
        with np.errstate(over="ignore"):
            u = (X - self.low_) / self.width_
        return np.clip(u, -1e6, 1e6, out=u)

    def transform(self, X):
        """Features of the observations ``X (n, D)``: ``(n, n_features_out_)``."""
        raise NotImplementedError

    def fit_transform(self, X, y=None):
        """``fit(X)`` then ``transform(X)``."""
        return self.fit(X).transform(X)


def grid_indices(u: np.ndarray, n_cells: np.ndarray, offset: np.ndarray | None = None):
    """Cell of each unit-box point on a grid of ``n_cells`` per dimension, as a flat index.

    ``u (n, D)`` in unit coordinates; ``offset (D,)`` shifts the grid (in cell units);
    points outside the box fall in the edge cells. Returns ``(n,)`` int64.
    """
    pos = u * n_cells if offset is None else u * (n_cells - 1) + offset
    cells = np.clip(np.floor(pos).astype(np.int64), 0, n_cells - 1)
    strides = np.concatenate([np.cumprod(n_cells[::-1])[-2::-1], [1]]).astype(np.int64)
    return cells @ strides


def is_int(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)
