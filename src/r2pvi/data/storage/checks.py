"""Validation of step-major data, chunk by chunk: finiteness, the simplex assumption,
non-negativity."""

from __future__ import annotations

import warnings

import numpy as np

from .fields import CHUNK, widen_range


class SimplexFeatureWarning(UserWarning):
    """Features break the paper's simplex assumption (phi_i >= 0 and sum_i phi_i = 1)."""


# Rows whose computed sums are within this of 1 count as summing to 1 exactly enough for
# Phi^T W 1 = Phi^T W Phi 1_d (the engine then takes the column sums from the Gram matrix):
# the error this leaves in E(1) = Lambda^-1 Phi^T W 1 is at most the rows' deviation times
# sum_j |M_ij|, a few units of the rounding already in every ridge estimate. Dirichlet rows
# from NumPy deviate by 2-6 units of 2^-52 (d = 4 to 120).
UNIT_ROW_ATOL = 16 * 2.0 ** -52


def simplex_flags(x: np.ndarray, atol: float = 1e-8) -> tuple[bool, bool]:
    """``(negative entries, rows not summing to 1)`` of feature rows (last axis)."""
    return simplex_facts(x, atol)[:2]


def simplex_facts(x: np.ndarray, atol: float = 1e-8) -> tuple[bool, bool, bool, float, float]:
    """``(negative entries, rows not summing to 1, every row sums to 1 within
    UNIT_ROW_ATOL, least row sum, largest row sum)`` of feature rows (last axis), from one
    pass of row sums (NaN rows make the last three NaN-based: not unit rows)."""
    if x.size == 0:
        return False, False, True, np.inf, -np.inf
    # in float64, as the fits see the rows (a float32 sum can round to 1.0 exactly while the
    # float64 sum of the same float32 numbers is 3e-8 off)
    sums = x.sum(axis=-1, dtype=np.float64)
    dev = np.abs(sums - 1.0)
    worst = float(np.max(dev))  # NaN rows (known values) make it NaN: not unit rows
    return (bool((x < -atol).any()), bool((dev > 1e-6).any()), bool(worst <= UNIT_ROW_ATOL),
            float(np.min(sums)), float(np.max(sums)))


def warn_simplex(name: str, negative: bool, off_sum: bool, stacklevel: int = 3) -> bool:
    """Warn with :class:`SimplexFeatureWarning` when a flag is set; True when on the simplex."""
    if not (negative or off_sum):
        return True
    what = " and ".join(
        w for w, bad in (("negative entries", negative), ("rows not summing to 1", off_sum))
        if bad
    )
    warnings.warn(
        f"{name} has {what}: the paper's simplex assumption (phi_i >= 0, sum_i phi_i = 1) "
        "does not hold. The algorithms still run; the d-rectangular guarantees do not apply.",
        SimplexFeatureWarning,
        stacklevel=stacklevel + 1,
    )
    return False


def step_major(x, name: str, ndim: int, dtype=None) -> np.ndarray:
    """``x (K, H, ...)`` as a C-contiguous step-major float array ``(H, K, ...)``.

    No copy when ``x`` already is one in memory (e.g. ``a.transpose(1, 0, ...)`` of a
    C-contiguous ``(H, K, ...)`` array of float32 or float64); otherwise exactly one.
    """
    from ..._validation import as_array

    raw = as_array(x, name) if not isinstance(x, str) else None
    if raw is None or raw.dtype.kind not in "biuf":
        if raw is not None and raw.dtype.kind == "c":
            raise TypeError(f"{name} must be real, got a complex array")
        kind = type(x).__name__ if raw is None else f"an array of dtype {raw.dtype}"
        raise TypeError(f"{name} must be a numeric (float) array, got {kind}")
    if raw.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {raw.shape}")
    target = np.dtype(dtype) if dtype is not None else (
        raw.dtype if raw.dtype in (np.float32, np.float64) else np.dtype(np.float64))
    sm = raw.swapaxes(0, 1)
    if sm.dtype == target and sm.flags.c_contiguous:
        return sm
    with np.errstate(over="ignore"):
        out = np.ascontiguousarray(sm, dtype=target)
    check_float32_range(sm, out, name)
    return out


_F32_MAX = float(np.finfo(np.float32).max)


def check_reward_noise(reward_noise) -> float:
    """``reward_noise`` (the rewards' noise level, ``OfflineDataset.reward_noise``) as a float
    ``>= 0``."""
    from ..._validation import check_scalar

    return float(check_scalar(reward_noise, "reward_noise", low=0.0))


def check_float32_range(x, cast, name: str) -> None:
    """Refuse finite values of ``x`` that its cast ``cast`` (to float32) turned into ``inf``
    (one pass over the cast when every value is finite)."""
    cast = np.asarray(cast)
    if cast.dtype != np.float32 or np.asarray(x).dtype.itemsize <= 4 or np.isfinite(cast).all():
        return
    x = np.asarray(x)
    big = np.isinf(cast) & np.isfinite(x)
    if big.any():
        top = float(np.max(np.abs(x[big])))
        raise ValueError(
            f"{name} holds finite values beyond float32's range (|x| up to {top:.6g} > "
            f"{_F32_MAX:.6g}): stored as float32 they would become inf; store the dataset as "
            "float64 (dtype='float64') or rescale the features")


def layout_step_major(x: np.ndarray) -> np.ndarray:
    """``x (K, H, ...)`` as a C-contiguous ``(H, K, ...)`` array of any dtype: a view when
    it already is one (e.g. a transposed memory map), else one copy."""
    sm = np.asarray(x).swapaxes(0, 1)
    return sm if sm.flags.c_contiguous else np.ascontiguousarray(sm)


def check_features_chunk(phi, rewards, next_phi, next_values, last_step: bool,
                         simplex: bool = True):
    """Validate one chunk of step-major rows; returns ``(phi, next_phi)`` simplex flags
    and non-negativity: ``(neg_phi, off_phi, neg_next, off_next, nonneg_phi, nonneg_next,
    unit_rows_phi, least_sum_phi, largest_sum_phi)`` (``unit_rows_phi``: phi's rows sum to 1
    within ``UNIT_ROW_ATOL``; the row sums' range is NaN when ``simplex=False``).

    ``last_step`` marks rows of ``h = H-1`` whose next-state data is never used. With
    ``simplex=False`` the simplex flags (row sums: most of the work) are not computed and
    returned False; everything else is checked the same.
    """
    for name, x in (("phi", phi), ("rewards", rewards)):
        if not np.isfinite(x).all():
            raise ValueError(f"{name} contains {int(np.count_nonzero(~np.isfinite(x)))} NaN or "
                             "infinite entries; clean the data first")
    if next_values is not None and not last_step and np.isinf(next_values).any():
        raise ValueError(f"next_values contains {int(np.count_nonzero(np.isinf(next_values)))} "
                         "infinite entries; use NaN where the value must be learned")
    facts = simplex_facts(phi) if simplex else (False, False, False, np.nan, np.nan)
    flags, unit, sums = facts[:2], facts[2], facts[3:]
    nonneg_phi = bool((phi >= 0).all())
    if last_step or next_phi is None:
        return flags + (False, False, nonneg_phi, True, unit) + sums
    finite = np.isfinite(next_phi).all(axis=-1)
    if not finite.all():
        # An action whose value is known needs no features: its row may be left NaN.
        known = np.zeros(finite.shape, bool) if next_values is None else ~np.isnan(next_values)
        if not (finite | known).all():
            raise ValueError(
                "next_phi contains NaN or infinite entries in steps h < H-1 where no value is "
                "known (only the last step's row and actions with a known next_values entry "
                "may be left undefined)"
            )
    # NaN rows (known values) count as neither negative nor off the simplex.
    next_flags = simplex_flags(next_phi) if simplex else (False, False)
    return flags + next_flags + (nonneg_phi, not bool((next_phi < 0).any()), unit) + sums


def validate_source(phi, rewards, next_phi, next_values, check_simplex=True, chunk=CHUNK,
                    stacklevel=3):
    """Validate step-major arrays chunk by chunk (no full-size temporaries).

    Returns ``(nonnegative_phi, nonnegative_next_phi, any_known, unit_rows_phi,
    reward_range, row_sums)``; ``unit_rows_phi`` is False when ``check_simplex`` is False (not
    checked), ``reward_range`` is the rewards' ``(min, max)``, taken in the same pass (the
    estimators check it against ``r_max`` without reading the rewards again), ``row_sums``
    the ``(min, max)`` of phi's row sums (None when not checked).
    """
    H, K, _ = phi.shape
    acc = [False, False, False, False, True, True]
    any_known, unit = False, bool(check_simplex)
    low, high = np.inf, -np.inf
    s_low, s_high = np.inf, -np.inf
    for h in range(H):
        last = h == H - 1
        for s in range(0, K, chunk):
            e = min(K, s + chunk)
            nv = None if next_values is None else next_values[h, s:e]
            try:
                flags = check_features_chunk(
                    phi[h, s:e], rewards[h, s:e],
                    None if next_phi is None else next_phi[h, s:e], nv, last, check_simplex)
            except ValueError as exc:
                raise _counted(exc, phi, rewards, next_values, chunk) from None
            for i in range(4):
                acc[i] = acc[i] or flags[i]
            acc[4] = acc[4] and flags[4]
            acc[5] = acc[5] and flags[5]
            unit = unit and flags[6]
            s_low, s_high = min(s_low, flags[7]), max(s_high, flags[8])
            if nv is not None and not last and not any_known:
                any_known = bool((~np.isnan(nv)).any())
            low, high = widen_range((low, high), rewards[h, s:e])
    if check_simplex:
        warn_simplex("phi", acc[0], acc[1], stacklevel)
        if next_phi is not None:
            warn_simplex("next_phi", acc[2], acc[3], stacklevel)
    row_sums = (float(s_low), float(s_high)) if check_simplex and np.isfinite(
        [s_low, s_high]).all() else None
    return acc[4], acc[5], any_known, unit, (float(low), float(high)), row_sums


def _counted(exc: ValueError, phi, rewards, next_values, chunk) -> ValueError:
    """The error of one chunk, with the count of bad entries over the whole field."""
    msg = str(exc)
    name = msg.split(" ", 1)[0]
    field = {"phi": phi, "rewards": rewards, "next_values": next_values}.get(name)
    if field is None or " contains " not in msg:
        return exc
    bad = np.isinf if name == "next_values" else (lambda x: ~np.isfinite(x))
    H, K = field.shape[:2]
    n = sum(int(np.count_nonzero(bad(field[h, s:s + chunk])))
            for h in range(H - (name == "next_values")) for s in range(0, K, chunk))
    rest = msg.split(" entries", 1)[1] if " entries" in msg else ""
    kind = "infinite" if name == "next_values" else "NaN or infinite"
    return ValueError(f"{name} contains {n} {kind} entries{rest}")


def check_map_actions(feature_map, n_actions, source: str | None = None) -> None:
    """``n_actions`` agrees with a feature map that records its own (``cross_actions``);
    ``source`` names where ``n_actions`` comes from (a dataset's manifest), else the caller's
    argument."""
    own = getattr(feature_map, "n_actions", None)
    if not (isinstance(own, int | np.integer) and not isinstance(own, bool)
            and isinstance(n_actions, int | np.integer) and int(own) != int(n_actions)):
        return
    if source is not None:
        raise ValueError(
            f"{source} n_actions = {int(n_actions)}, but the feature map "
            f"({type(feature_map).__name__}) was built for n_actions={int(own)}: pass the "
            "feature map the dataset was built with")
    raise ValueError(
        f"n_actions={int(n_actions)} disagrees with the feature map, built for "
        f"n_actions={int(own)} ({type(feature_map).__name__}); pass n_actions={int(own)} "
        f"or build the map with cross_actions(..., n_actions={int(n_actions)})"
    )
