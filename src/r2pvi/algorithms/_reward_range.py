"""The check every fit runs first: rewards in ``[0, r_max]`` (or those ``reward_weights``
imply on the data), named with the ``r_max`` to pass or the shift to apply."""

from __future__ import annotations

import contextlib

import numpy as np

from ..data import OfflineDataset
from ..data.storage._finite import REWARD_NOISE_Z, REWARD_RTOL  # also the fit's own checks

__all__ = ["check_reward_range"]


def check_reward_range(dataset: OfflineDataset, r_max: float, reward_weights=None) -> None:
    """Refuse rewards outside ``[0, r_max]`` (noisy ones beyond their noise, see
    :attr:`~r2pvi.OfflineDataset.reward_noise`): every estimator clips ``Q_h`` to
    ``[0, (H - h) r_max]`` (the paper's ``min{., H - h + 1}^+`` with rewards in [0, 1]), so
    larger rewards would be cut off and negative ones lifted to 0, silently: constant Q and
    an arbitrary policy when every reward is out of range.

    The rewards' range is the dataset's :attr:`~r2pvi.OfflineDataset.reward_range` (taken
    when the data was validated or written: no pass over the features); rewards the dataset
    did not check when it was built (a directory's files, Dask arrays) are checked again,
    step by step, by the fit as it reads them (finite and in range). With
    ``reward_weights`` the rewards are ``phi_h^T theta_h`` on the data: on simplex features
    they lie in ``[min_i theta_hi, max_i theta_hi]``, which settles most steps without reading
    a feature; other steps are computed (one product ``phi_h theta_h``).

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset, PEVI
    >>> ds = OfflineDataset.from_features(np.full((4, 2, 2), 0.5), np.full((4, 2), 3.0),
    ...                                   np.full((4, 2, 1, 2), 0.5))
    >>> PEVI().fit(ds)
    Traceback (most recent call last):
    ...
    ValueError: rewards reach 3.0 > r_max=1.0; pass r_max=3.0 or larger (every estimator ...
    >>> PEVI(r_max=3.0).fit(ds).weights_.shape
    (2, 2)
    """
    tol = REWARD_RTOL * r_max
    if reward_weights is None:
        low, high = dataset.reward_range
        if not np.isfinite([low, high]).all():
            return  # rewards not checked when built: the fit names the bad one as it reads it
        what, where = "rewards", ""
        noise = REWARD_NOISE_Z * dataset.reward_noise
        if noise:
            tol += noise
            where = (f" (beyond the {REWARD_NOISE_Z:g} standard deviations of the dataset's "
                     f"reward_noise={dataset.reward_noise!r})")
    else:
        low, high = _implied_reward_range(dataset, reward_weights, -tol, r_max + tol)
        what, where = "the rewards phi_h^T theta_h of reward_weights", " on the data"
    if low < -tol:
        shift = -low
        raise ValueError(
            f"{what} go down to {low!r} < 0{where}, but every estimator clips Q_h to "
            f"[0, (H - h) r_max], so the values would be wrong (all 0 if every reward is "
            f"negative). Shift the rewards by c >= {shift!r}: add c to every reward and "
            "(H - h - 1) c to known next_values (OfflineDataset.from_episodes(..., "
            "reward_offset='auto') does both; the greedy policy is unchanged"
            + ("; with simplex features adding c to every entry of reward_weights adds c to "
               "every reward" if reward_weights is not None else "")
            + f"), and pass r_max >= the largest shifted reward ({high + shift!r} for "
            f"c = {shift!r})"
        )
    if high > r_max + tol:
        raise ValueError(
            f"{what} reach {high!r} > r_max={r_max!r}{where}; pass r_max={high!r} or larger "
            "(every estimator clips Q_h to [0, (H - h) r_max])"
        )


def _implied_reward_range(dataset, theta: np.ndarray, low_ok: float, high_ok: float):
    """``(min, max)`` of ``phi_h^T theta_h`` over the taken actions, exact where it matters:
    a step whose bound ``[min theta_h, max theta_h]`` (simplex rows), ``[min(s t), max(s t)]``
    over the recorded range of the rows' sums ``s`` and ``t`` in ``{min theta_h, max
    theta_h}`` (non-negative rows whose sums are known) or ``0`` (``theta_h = 0``) lies in
    ``[low_ok, high_ok]`` is not read."""
    source = getattr(dataset, "_source", None)
    nonneg = source is not None and source.nonnegative_phi is True
    simplex = nonneg and source.unit_rows
    # non-negative rows whose sums lie in [s_lo, s_hi] (found by validation or recorded in a
    # directory's manifest; e.g. float32 rows, 1 within ~1e-7): phi^T theta lies in
    # [min(s t_min), max(s t_max)]
    sums = getattr(source, "phi_row_sums", None) if nonneg and not simplex else None
    # features not checked when the dataset was built: an infinity is named below, not warned
    unchecked = source is not None and "phi" not in source.checked
    low, high = np.inf, -np.inf
    for h in range(dataset.horizon):
        t = theta[h]
        if not t.any():
            bounds = (0.0, 0.0)
        elif simplex:
            bounds = (float(t.min()), float(t.max()))
        elif sums is not None:
            ends = (sums[0] * float(t.min()), sums[1] * float(t.min()),
                    sums[0] * float(t.max()), sums[1] * float(t.max()))
            bounds = (min(ends), max(ends))
        else:
            bounds = (-np.inf, np.inf)
        if not (low_ok <= bounds[0] and bounds[1] <= high_ok):
            with np.errstate(invalid="ignore", over="ignore") if unchecked else (
                    contextlib.nullcontext()):
                r = dataset._step_product(h, t)
            bounds = (float(r.min()), float(r.max())) if r.size else (0.0, 0.0)
            if not np.isfinite(bounds).all() and source is not None:  # features not checked
                err = source.phi_error(h)
                if err is not None:
                    raise err
        low, high = min(low, bounds[0]), max(high, bounds[1])
    return low, high
