"""What a fit checks in the data it did not validate at construction (dataset directories,
Dask arrays, features computed by a feature map): every number it uses is finite and every
reward lies in ``[0, r_max]``.

The checks ride on numbers the fit forms anyway: a step's Gram matrix and products
``Phi^T y`` (a NaN or an infinity anywhere in a row makes them non-finite), the sums of the
next-state products ``phi^T u`` before the clip (a clip would hide an infinity), the min and
max of the rewards the step reads. Only when one is off is the step searched for the first
bad entry, and the error names where it is (the file, or the field), the step, the index and
the fix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Rewards may pass the bounds [0, r_max] by this much relative rounding: r_max (1 + 1e-12),
# and noisy rewards (OfflineDataset.reward_noise = sigma) by REWARD_NOISE_Z sigma more: a
# Gaussian sample lies that far out with probability 1.2e-15.
REWARD_RTOL = 1e-12
REWARD_NOISE_Z = 8.0

# The fields a source may have checked when it was built (StepSource.checked).
FIELDS = frozenset({"phi", "rewards", "next"})

_FILE_FIX = ("the file changed after the dataset was written (r2pvi's writers refuse such "
             "numbers): write the dataset again from clean data (OfflineDataset.from_features"
             "(...).save(path) and DatasetWriter check every number)")
_DASK_FIX = ("OfflineDataset.from_dask does not compute the arrays to check them: clean them "
             "first (e.g. drop that trajectory), or build the dataset with "
             "OfflineDataset.from_features, which refuses such numbers")
_MAP_FIX = ("make the feature map return finite features for every observation "
            "(OfflineDataset.from_observations evaluates it while fitting)")
_ARRAY_FIX = ("clean the data and build the dataset with OfflineDataset.from_features, which "
              "refuses such numbers")


@dataclass(frozen=True)
class Origin:
    """Where a field's numbers come from, for the errors: ``label`` names it (a file path,
    or the field), ``fix`` says what to do, ``file_index`` whether the index within the file
    (step-major) is worth giving."""

    label: str
    fix: str
    file_index: bool = False
    verb: str = "holds"
    of: str = ""  # what the number is of, e.g. " for the taken-action features"


def file_origin(path) -> Origin:
    return Origin(str(path), _FILE_FIX, True)


def dask_origin(name: str) -> Origin:
    return Origin(f"{name} (a Dask array)", _DASK_FIX)


def map_origin(what: str) -> Origin:
    return Origin("the feature_map", _MAP_FIX, verb="returned", of=f" for the {what}")


def array_origin(name: str) -> Origin:
    return Origin(name, _ARRAY_FIX)


def subset_origin(origin: Origin) -> Origin:
    """The origin of rows taken from a field (``subset``, ``OfflineDataset.load``): the
    trajectory numbers are those of the selection."""
    if origin.label.endswith("(selected trajectories)"):
        return origin
    return Origin(f"{origin.label} (selected trajectories)", origin.fix, verb=origin.verb,
                  of=origin.of)


class NonFiniteRows(ValueError):
    """A chunk of next-state features holds a non-finite entry the values would use:
    ``index`` is ``(i, a, j)`` within the chunk, ``value`` the number; with ``known``, an
    infinite known value at ``(i, a)``. The next-state forms turn it into an error naming
    the step and the trajectory (:meth:`~r2pvi.storage.NextStates.nonfinite`)."""

    def __init__(self, index, value, known: bool = False):
        super().__init__(f"non-finite next-state {'value' if known else 'feature'} {value!r} "
                         f"at {tuple(index)}")
        self.index, self.value = tuple(int(i) for i in index), float(value)
        self.known = bool(known)


def first_nonfinite(x: np.ndarray, skip: np.ndarray | None = None):
    """``(index, value)`` of the first non-finite entry of ``x`` in C order, or None;
    entries whose row ``skip[...]`` is True (``skip`` has the shape of ``x`` but its last
    axis) are not looked at."""
    x = np.asarray(x)
    bad = ~np.isfinite(x)
    if skip is not None:
        bad &= ~np.asarray(skip, dtype=bool)[..., None]
    flat = np.flatnonzero(bad)
    if flat.size == 0:
        return None
    idx = tuple(int(i) for i in np.unravel_index(int(flat[0]), x.shape))
    return idx, float(x[idx])


def check_next_products(q: np.ndarray, feats: np.ndarray, known=None) -> None:
    """Raise :class:`NonFiniteRows` when next-state features ``feats
    (n, A, d)`` hold a non-finite entry in a row whose value is not known (NaN in ``known``),
    or ``known (n, A)`` an infinity: a NaN or an infinity in a row makes its product ``q (n,
    A)`` non-finite, so one sum of the products (taken before the clip) settles it, and the
    rows are searched only when it is not finite."""
    if known is None:
        total = np.add.reduce(q, axis=None)
    else:
        inf = np.isinf(known)
        if inf.any():
            i, a = (int(x) for x in np.argwhere(inf)[0])
            raise NonFiniteRows((i, a), known[i, a], known=True)
        total = np.add.reduce(np.where(np.isnan(known), q, 0.0), axis=None)
    if np.isfinite(total):
        return
    hit = first_nonfinite(feats, None if known is None else ~np.isnan(known))
    if hit is not None:  # else the finite products overflowed: not the data's fault
        raise NonFiniteRows(*hit)


def _where(h: int, k: int, action=None, feature=None) -> str:
    parts = [f"step {h}", f"trajectory {k}"]
    if action is not None:
        parts.append(f"action {action}")
    if feature is not None:
        parts.append(f"feature {feature}")
    return ", ".join(parts)


def nonfinite_error(origin: Origin, h: int, k: int, value: float, action=None, feature=None,
                    file_index=None) -> ValueError:
    """The error for a non-finite number at step ``h``, trajectory ``k`` (and ``action``,
    ``feature``); ``file_index`` is the entry's index in the file when it differs from
    ``[h, k, (action,) (feature)]`` (side tables, feature tables)."""
    if file_index is None:
        file_index = [h, k] + [i for i in (action, feature) if i is not None]
    at = f" at index {list(file_index)}" if origin.file_index else ""
    return ValueError(
        f"{origin.label} {origin.verb} {value!r}{origin.of}{at} "
        f"({_where(h, k, action, feature)}): a fit "
        f"uses only finite numbers. Fix: {origin.fix}")


def reward_limits(r_max: float, noise: float) -> tuple[float, float]:
    """``[low, high]`` the rewards must lie in: ``[0, r_max]`` widened by rounding
    (``REWARD_RTOL r_max``) and ``REWARD_NOISE_Z`` standard deviations of the noise."""
    tol = REWARD_RTOL * r_max + REWARD_NOISE_Z * noise
    return -tol, r_max + tol


def check_step_rewards(rewards: np.ndarray, h: int, r_max: float, noise: float,
                       origin: Origin, recorded=None) -> None:
    """Refuse rewards of step ``h`` that are not finite or leave ``[0, r_max]`` (up to
    :func:`reward_limits`): one min and one max of the numbers the step reads anyway; the
    first bad index is searched for only when one is off. ``recorded`` is the range the
    dataset recorded (a directory's manifest), named in the error."""
    if rewards.size == 0:
        return
    low, high = reward_limits(r_max, noise)
    lo, hi = float(np.min(rewards)), float(np.max(rewards))
    if lo >= low and hi <= high:  # False for NaN
        return
    ok = (rewards >= low) & (rewards <= high)
    k = int(np.flatnonzero(~ok)[0])
    value = float(rewards[k])
    if not np.isfinite(value):
        raise nonfinite_error(origin, h, k, value)
    at = f" at index {[h, k]}" if origin.file_index else ""
    noisy = (f" (beyond {REWARD_NOISE_Z:g} standard deviations of the dataset's "
             f"reward_noise={noise!r})" if noise else "")
    if recorded is not None:
        fix = (f"its manifest records reward_range {list(recorded)}, so {origin.fix}")
    else:
        fix = ("shift the rewards into [0, r_max] (OfflineDataset.from_episodes(..., "
               "reward_offset='auto') does it) or pass a larger r_max; every estimator clips "
               "Q_h to [0, (H - h) r_max]")
    raise ValueError(
        f"{origin.label} holds the reward {value!r}{at} ({_where(h, k)}), outside "
        f"[0, r_max={r_max!r}]{noisy}: the fit would clip the values silently. Fix: {fix}")
