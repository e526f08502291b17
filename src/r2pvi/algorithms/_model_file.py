"""The saved model file: its format version, the registry of estimator classes, the packing of
the fitted state into arrays and a JSON header (``save``), and loading (``r2pvi.load``) with
every field of the file checked, ranges included; a bad file is a ``ValueError`` naming the
file and the field."""

from __future__ import annotations

import numbers

import numpy as np
import scipy.sparse as sp

from .._io import file_array, file_error, load_npz
from .._validation import check_choice, check_scalar, plain
from ..duals._sparse_rows import _SparseProduct, _UsedFeaturesFactor
from ..duals.fdivergence import FDivergence, get_divergence
from ..engine import FittedModel

# Version 2: no (H, d, d) Cholesky factors; the elliptical penalty's fitted factors
# ``elliptical_r`` (G, r, d) and ``elliptical_c`` (G, 2) with ``elliptical_index`` (H,) when
# the penalty is "elliptical". Version 1 files (with ``gram_cholesky_``) still load.
# Version 3: header ``elliptical_kinds`` (one of "dense", "sparse", "used" per distinct factor)
# and, by kind: dense ``elliptical_r``; sparse-row dual factors ``R = C^{-1} Psi`` as
# ``elliptical_cinv`` (Gs, n, n) and Psi's CSR pieces (``elliptical_psi_data``,
# ``elliptical_psi_indices``, ``elliptical_psi_indptr`` (Gs, n + 1)); sparse-row primal factors
# ``L_U^{-1}`` on the used features U, ragged (``elliptical_linv_data``, ``elliptical_cols``,
# ``elliptical_sizes`` (Gu,)). Version-2 files (dense only, no kinds) still load.
MODEL_FORMAT_VERSION = 3
# Every LinearEstimator subclass registers itself here by name (``__init_subclass__``): a
# model file names its class, and loading dispatches on it.
ESTIMATOR_REGISTRY: dict[str, type] = {}
ELLIPTICAL_KINDS = ("dense", "sparse", "used")


def _jsonable(name, value):
    if isinstance(value, FDivergence):
        spec = value.params
        try:
            ok = bool(spec) and get_divergence(spec) == value
        except (TypeError, ValueError, KeyError):
            ok = False
        if not ok:
            raise TypeError(
                f"cannot save parameter {name}={value!r}: a custom FDivergence has code, which "
                "is never pickled; use a built-in divergence or save the weights_ yourself"
            )
        return {"__divergence__": spec}
    if value is None or isinstance(value, bool | str):
        return value if not isinstance(value, str) else str(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value)
    raise TypeError(f"cannot save parameter {name}={value!r} of type {type(value).__name__}")


def _pack_elliptical(factors: list) -> tuple[list[int], dict, list[str]]:
    """Distinct per-step elliptical factors as arrays: ``(index (H,), arrays, kinds (G,))``.

    ``elliptical_c (G, 2)`` for every factor; by kind, in the order of ``kinds``: "dense"
    ``elliptical_r``, "sparse" (sparse-row dual form) ``elliptical_cinv`` and ``Psi``'s CSR
    pieces, "used" (sparse-row primal form) ``L_U^{-1}`` and ``U``, ragged. Pooled steps share
    one factor (G = 1); sparse rows may mix the two sparse kinds across steps."""
    seen: dict[int, int] = {}
    index, distinct = [], []
    for factor in factors:
        key = id(factor[0])
        if key not in seen:
            seen[key] = len(distinct)
            distinct.append(factor)
        index.append(seen[key])
    kinds = []
    for r, _, _ in distinct:
        if isinstance(r, np.ndarray):
            kinds.append("dense")
        elif isinstance(r, _SparseProduct):
            kinds.append("sparse")
        elif isinstance(r, _UsedFeaturesFactor):
            kinds.append("used")
        else:  # pragma: no cover - the engine makes only these
            raise TypeError(f"cannot save an elliptical factor of type {type(r).__name__}")
    # "used" factors have c0 = 0, c1 = 1; their first column carries 1 / gamma instead.
    arrays = {"elliptical_c": np.array([[1.0 / r.gamma, 1.0] if k == "used" else [c0, c1]
                                        for (r, c0, c1), k in zip(distinct, kinds,
                                                                  strict=True)])}
    of = {k: [r for (r, _, _), kk in zip(distinct, kinds, strict=True) if kk == k]
          for k in ELLIPTICAL_KINDS}
    if of["dense"]:
        if len({r.shape for r in of["dense"]}) != 1:
            raise TypeError("cannot save dense elliptical factors of different shapes")
        arrays["elliptical_r"] = np.stack(of["dense"])
    if of["sparse"]:
        if len({r.cinv.shape for r in of["sparse"]}) != 1:
            raise TypeError("cannot save sparse elliptical factors of different sizes")
        psis = [r.psi for r in of["sparse"]]
        arrays["elliptical_cinv"] = np.stack([r.cinv for r in of["sparse"]])
        arrays["elliptical_psi_data"] = np.concatenate([p.data for p in psis]).astype(float)
        arrays["elliptical_psi_indices"] = np.concatenate(
            [p.indices for p in psis]).astype(np.int64)
        arrays["elliptical_psi_indptr"] = np.stack([p.indptr for p in psis]).astype(np.int64)
    if of["used"]:
        used = of["used"]
        arrays["elliptical_sizes"] = np.array([r.cols.size for r in used], dtype=np.int64)
        arrays["elliptical_cols"] = np.concatenate([r.cols for r in used]).astype(np.int64)
        arrays["elliptical_linv_data"] = np.concatenate([r.linv.ravel() for r in used])
    return index, arrays, kinds


class _Shape:
    """What fit's parameter checks read from a dataset, rebuilt from a saved model."""

    def __init__(self, horizon: int, n_features: int):
        self.horizon, self.n_features, self.n_trajectories = horizon, n_features, 2


def load_model(path):
    """The estimator saved at ``path`` (:func:`r2pvi.load`), every field checked."""
    arrays, header = load_npz(path, "estimator", MODEL_FORMAT_VERSION)
    name = header.get("estimator")
    if not isinstance(name, str) or name not in ESTIMATOR_REGISTRY:
        raise file_error(path, "estimator", f"is {name!r}, not one of {sorted(ESTIMATOR_REGISTRY)}")
    cls = ESTIMATOR_REGISTRY[name]
    raw = header.get("params")
    if not isinstance(raw, dict):
        raise file_error(path, "params", "must be a JSON object")
    unknown = sorted(set(raw) - set(cls._param_names()))
    if unknown:
        raise file_error(path, "params", f"has unknown parameters {unknown} for {name}")
    params = {}
    for key, value in raw.items():
        if isinstance(value, dict) and "__array__" in value:
            value = file_array(path, arrays, str(value["__array__"]))
        elif isinstance(value, dict) and "__divergence__" in value:
            try:
                value = get_divergence(value["__divergence__"])
            except (TypeError, ValueError, KeyError) as exc:
                raise file_error(path, f"params.{key}", f"is not a divergence: {exc}") from None
        params[key] = value
    est = cls(**params)
    weights = file_array(path, arrays, "weights_", ndim=2)
    H, d = weights.shape
    if H < 1 or d < 1:
        raise file_error(path, "weights_", f"must have H, d >= 1, got shape {(H, d)}")
    reward_weights = file_array(path, arrays, "reward_weights_", shape=(H, d))
    inv_diag = file_array(path, arrays, "gram_inv_diag_", shape=(H, d))
    try:  # the parameters go through fit's own checks
        checked = est._validate_common(_Shape(H, d))
        checked.update(est._validate_extra(_Shape(H, d)))
        est._time_homogeneous()
    except (TypeError, ValueError) as exc:
        raise file_error(path, "params", f"fail the estimator's checks: {exc}") from None
    gamma = checked["gamma"]
    # diag(Lambda^-1) of Lambda = Phi^T W Phi + gamma I: in (0, 1 / gamma]
    if np.any(inv_diag <= 0) or np.any(inv_diag > (1.0 + _RTOL) / gamma):
        raise file_error(path, "gram_inv_diag_", f"must be > 0 and <= 1 / gamma = "
                         f"{1 / gamma:g} (the diagonal of Lambda_h^-1), got values from "
                         f"{plain(inv_diag.min())!r} to {plain(inv_diag.max())!r}")
    fit_params = header.get("fit_params")
    if not isinstance(fit_params, dict) or set(fit_params) != {"beta", "penalty", "r_max"}:
        raise file_error(path, "fit_params", "must be an object with beta, penalty and r_max")
    try:
        fp = {
            "beta": check_scalar(fit_params["beta"], "beta", low=0.0),
            "penalty": check_choice(fit_params["penalty"], "penalty", est._penalty_choices),
            "r_max": check_scalar(fit_params["r_max"], "r_max", low=0.0, low_inclusive=False),
        }
    except (TypeError, ValueError) as exc:
        raise file_error(path, "fit_params", str(exc)) from None
    for key in ("penalty", "r_max") + (() if isinstance(params.get("beta"), str) else ("beta",)):
        if fp[key] != checked[key]:
            raise file_error(path, f"fit_params.{key}", f"is {fp[key]!r} but the parameters "
                             f"say {checked[key]!r}: the file was altered")
    n_actions = header.get("n_actions")
    if isinstance(n_actions, bool) or not isinstance(n_actions, int) or n_actions < 1:
        raise file_error(path, "n_actions", f"must be an integer >= 1, got {n_actions!r}")
    ellip = _load_elliptical(path, arrays, header, H, d, fp["penalty"] == "elliptical", gamma)
    model = FittedModel(weights, reward_weights, inv_diag, ellip)
    est._set_fitted(model, fp, n_actions)
    return est


def _load_elliptical(path, arrays, header, H: int, d: int, needed: bool, gamma: float):
    """The elliptical penalty's per-step factors: version 1 stored the (H, d, d) Cholesky
    factors ``L`` (``R = L^{-1}``), version 2 the distinct factors and an index per step,
    version 3 their kinds too. Each factor ``(R, c0, c1)`` must be one a fit makes (see
    :func:`_check_factor`)."""
    if header["format_version"] == 1:
        chol = file_array(path, arrays, "gram_cholesky_", shape=(H, d, d))
        diag = np.diagonal(chol, axis1=1, axis2=2)
        if np.any(np.triu(chol, k=1)) or np.any(diag <= 0):
            raise file_error(path, "gram_cholesky_", "must be lower-triangular with a positive "
                             "diagonal (Cholesky factors of the Gram matrices)")
        if not needed:
            return None
        return [(np.linalg.solve(c, np.eye(d)), 0.0, 1.0) for c in chol]
    if not needed and "elliptical_c" not in arrays:  # saved with another penalty
        for key in ("elliptical_index", "elliptical_kinds"):
            if key in header:
                raise file_error(path, key, "is set, but the file holds no elliptical factors "
                                 "(no elliptical_c): the file was altered")
        return None
    index = header.get("elliptical_index")
    kinds = header.get("elliptical_kinds")
    if kinds is None and header["format_version"] >= 3:
        raise file_error(path, "elliptical_kinds", "is missing (a list of the factors' kinds, "
                         f"each one of {list(ELLIPTICAL_KINDS)})")
    if kinds is None:  # version 2: dense factors only
        rs = file_array(path, arrays, "elliptical_r", ndim=3)
        kinds = ["dense"] * rs.shape[0]
    if (not isinstance(kinds, list) or not kinds
            or any(k not in ELLIPTICAL_KINDS for k in kinds)):
        raise file_error(path, "elliptical_kinds", f"must be a non-empty list of "
                         f"{ELLIPTICAL_KINDS}, got {kinds!r}")
    G = len(kinds)
    cs = file_array(path, arrays, "elliptical_c", shape=(G, 2))
    if (not isinstance(index, list) or len(index) != H
            or not all(isinstance(g, int) and not isinstance(g, bool) and 0 <= g < G
                       for g in index)):
        raise file_error(path, "elliptical_index",
                         f"must be a list of H = {H} integers in [0, {G})")
    kinds_arr = np.array(kinds)
    factors: list = [None] * G
    for kind, load in (("dense", _load_dense_factors), ("sparse", _load_sparse_factors),
                       ("used", _load_used_factors)):
        mine = np.flatnonzero(kinds_arr == kind)
        if mine.size:
            for g, f in zip(mine, load(path, arrays, d, mine.size, cs[mine]), strict=True):
                _check_factor(path, g, kind, f, cs[g], gamma)
                factors[g] = f
    if not needed:  # checked all the same: a file is whole or refused
        return None
    return [(factors[g], float(cs[g, 0]), float(cs[g, 1])) if kinds[g] != "used"
            else (factors[g], 0.0, 1.0) for g in index]


def _load_dense_factors(path, arrays, d: int, count: int, cs):
    rs = file_array(path, arrays, "elliptical_r", ndim=3)
    if rs.shape[0] != count or rs.shape[2] != d:
        raise file_error(path, "elliptical_r", f"must have shape ({count}, r, d = {d}), "
                         f"got {rs.shape}")
    return list(rs)


def _load_sparse_factors(path, arrays, d: int, count: int, cs):
    """Sparse-row dual factors ``R = C^{-1} Psi``: ``C^{-1}`` dense, ``Psi`` as CSR pieces."""
    cinv = file_array(path, arrays, "elliptical_cinv", ndim=3)
    n = cinv.shape[1]
    if cinv.shape != (count, n, n):
        raise file_error(path, "elliptical_cinv", f"must have shape ({count}, n, n), got "
                         f"{cinv.shape}")
    indptr = _int_array(path, arrays, "elliptical_psi_indptr", (count, n + 1))
    data = file_array(path, arrays, "elliptical_psi_data", ndim=1)
    indices = _int_array(path, arrays, "elliptical_psi_indices", data.shape)
    counts = indptr[:, -1]
    if (np.any(indptr[:, 0] != 0) or np.any(np.diff(indptr, axis=1) < 0)
            or int(counts.sum()) != data.size):
        raise file_error(path, "elliptical_psi_indptr", "must be CSR row pointers (starting "
                         "at 0, non-decreasing) whose totals add up to the stored non-zeros")
    if indices.size and (indices.min() < 0 or indices.max() >= d):
        raise file_error(path, "elliptical_psi_indices", f"must lie in [0, d = {d})")
    starts = np.concatenate([[0], np.cumsum(counts)])
    return [_SparseProduct(cinv[g], sp.csr_matrix(
        (data[starts[g]:starts[g + 1]], indices[starts[g]:starts[g + 1]], indptr[g]),
        shape=(n, d))) for g in range(count)]


def _load_used_factors(path, arrays, d: int, count: int, cs):
    """Sparse-row primal factors ``L_U^{-1}`` on the used features ``U`` (ragged)."""
    sizes = _int_array(path, arrays, "elliptical_sizes", (count,))
    if np.any(sizes < 0) or np.any(sizes > d):
        raise file_error(path, "elliptical_sizes", f"must be {count} sizes in [0, d = {d}]")
    cols = _int_array(path, arrays, "elliptical_cols", None)
    linv = file_array(path, arrays, "elliptical_linv_data", ndim=1)
    if cols.shape != (int(sizes.sum()),):
        raise file_error(path, "elliptical_sizes", f"{sizes.tolist()} do not add up to the "
                         f"{cols.size} stored features (elliptical_cols)")
    if linv.shape != (int((sizes**2).sum()),):
        raise file_error(path, "elliptical_linv_data", f"must hold sum(sizes^2) = "
                         f"{int((sizes**2).sum())} entries, got {linv.size}")
    if np.any(cs[:, 0] <= 0):
        raise file_error(path, "elliptical_c", "must hold 1 / gamma > 0 in its first column")
    ends, sq_ends = np.cumsum(sizes), np.cumsum(sizes**2)
    factors = []
    for g in range(count):
        u = int(sizes[g])
        c = cols[ends[g] - u:ends[g]]
        if np.any(c < 0) or np.any(c >= d) or np.any(np.diff(c) <= 0):
            raise file_error(path, "elliptical_cols", f"must be increasing features in [0, {d})")
        lg = linv[sq_ends[g] - u * u:sq_ends[g]].reshape(u, u)
        factors.append(_UsedFeaturesFactor(lg, c, 1.0 / float(cs[g, 0])))
    return factors


def _int_array(path, arrays: dict, name: str, shape: tuple | None) -> np.ndarray:
    if name not in arrays:
        raise file_error(path, name, "is missing")
    arr = arrays[name]
    if arr.dtype.kind not in "iu":
        raise file_error(path, name, f"must be integers, got dtype {arr.dtype}")
    if shape is not None and arr.shape != shape:
        raise file_error(path, name, f"must have shape {shape}, got {arr.shape}")
    return arr.astype(np.int64)



# Relative rounding allowed where a saved value must equal one computed from the parameters.
_RTOL = 1e-9


def _check_factor(path, g: int, kind: str, factor, c, gamma: float) -> None:
    """Factor ``g`` gives ``||x||^2_{Lambda^-1} = c0 ||x||^2 + c1 ||R x||^2`` as a fit makes
    it: the primal form ``(L^-1, 0, 1)`` with ``L^-1`` lower-triangular with a positive
    diagonal, or the dual form ``(C^-1 Psi, 1/gamma, -1/gamma)`` with ``||R|| <= 1`` (so the
    quadratic is never negative), or for "used" factors ``c = (1/gamma, 1)`` and ``L_U^-1``
    as the primal's. Anything else (a negative or rescaled ``elliptical_c``, a factor that
    is no inverse Cholesky factor) is an error naming the field."""
    c0, c1 = float(c[0]), float(c[1])

    def near(x, y):
        return abs(x - y) <= _RTOL * max(abs(y), 1e-300)

    primal = kind != "sparse" and c0 == 0.0 and c1 == 1.0
    dual = kind != "used" and near(c0, 1 / gamma) and near(c1, -1 / gamma)
    used = kind == "used" and near(c0, 1 / gamma) and c1 == 1.0
    if not (primal or dual or used):
        forms = {"dense": "(0, 1) (primal form) or (1/gamma, -1/gamma) (dual form)",
                 "sparse": "(1/gamma, -1/gamma)", "used": "(1/gamma, 1)"}[kind]
        raise file_error(path, "elliptical_c", f"row {g} is {[c0, c1]}, not {forms} with "
                         f"gamma = {gamma!r} (the estimator's parameter): the file was altered")
    if kind == "sparse":
        rrt = factor.cinv @ (factor.psi @ factor.psi.T).toarray() @ factor.cinv.T
        _check_contraction(path, "elliptical_cinv", g, rrt)
    elif kind == "used":
        _check_lower_triangular(path, "elliptical_linv_data", g, factor.linv)
    elif primal:
        _check_lower_triangular(path, "elliptical_r", g, factor)
    else:
        _check_contraction(path, "elliptical_r", g, factor @ factor.T)


def _check_lower_triangular(path, name: str, g: int, r) -> None:
    """``r`` is square, lower-triangular with a positive diagonal (``L^-1`` of a Cholesky
    factor ``L``)."""
    if r.ndim != 2 or r.shape[0] != r.shape[1] or np.any(np.triu(r, k=1)) or np.any(
            np.diagonal(r) <= 0):
        raise file_error(path, name, f"factor {g} must be a square lower-triangular matrix "
                         "with a positive diagonal (the inverse of a Cholesky factor of "
                         "Lambda_h): the file was altered")


def _check_contraction(path, name: str, g: int, rrt) -> None:
    """``R R^T`` (given) has eigenvalues <= 1: ``||R x|| <= ||x||``, so the dual form's
    ``(||x||^2 - ||R x||^2) / gamma`` is never negative."""
    top = float(np.linalg.eigvalsh((rrt + rrt.T) / 2).max(initial=0.0)) if rrt.size else 0.0
    if not top <= 1.0 + 1e-8:
        raise file_error(path, name, f"factor {g} has norm {np.sqrt(max(top, 0.0)):.6g} > 1: "
                         "the dual form's penalty would be negative; the file was altered")
