"""scikit-learn compatibility (scikit-learn is in the test extra, never imported by the core)."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.exceptions import NotFittedError as SklearnNotFittedError
from sklearn.model_selection import ParameterGrid
from sklearn.utils import estimator_html_repr, get_tags
from sklearn.utils.validation import check_is_fitted

import r2pvi
from r2pvi import DRPVI, DRVIL, PEVI, R2PVI, NotFittedError, OfflineDataset


def make_data(K=60, H=3, d=4, A=2, seed=0):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    theta = rng.uniform(size=(H, d))
    return OfflineDataset.from_features(phi, np.einsum("khd,hd->kh", phi, theta), next_phi)


ESTIMATORS = [PEVI(beta=0.2), R2PVI("kl", 0.5, beta=0.1, penalty="l2"), DRPVI(0.1),
              DRVIL(np.array([0.1, 0.2, 0.3, 0.4]))]


@pytest.mark.parametrize("est", ESTIMATORS, ids=lambda e: type(e).__name__)
def test_clone_params_tags_and_fitted_checks(est):
    data = make_data()
    twin = clone(est)
    assert type(twin) is type(est) and twin is not est
    for key, value in est.get_params().items():
        np.testing.assert_equal(twin.get_params()[key], value)
    assert get_tags(est).requires_fit and not get_tags(est).input_tags.two_d_array
    with pytest.raises(SklearnNotFittedError):
        check_is_fitted(twin)
    with pytest.raises(SklearnNotFittedError, match="not fitted yet"):
        twin.act(data.next_phi[:2, 0], 0)  # our own error, recognised by scikit-learn
    twin.fit(data)
    check_is_fitted(twin)
    refit = clone(twin)  # a clone of a fitted estimator is unfitted
    assert not hasattr(refit, "weights_")
    assert f"{type(est).__name__}" in estimator_html_repr(est) and est._repr_html_()


def test_not_fitted_error_is_ours_and_sklearns():
    assert issubclass(NotFittedError, SklearnNotFittedError)
    assert issubclass(NotFittedError, ValueError) and issubclass(NotFittedError, AttributeError)
    assert r2pvi.NotFittedError is NotFittedError


def test_parameter_grid_with_set_params_fits_every_setting():
    data = make_data()
    base = R2PVI(beta=0.1)
    weights = {}
    for params in ParameterGrid({"divergence": ["tv", "kl", "chi2"], "lam": [0.2, 2.0]}):
        est = clone(base).set_params(**params).fit(data)
        assert est.get_params()["lam"] == params["lam"]
        weights[(params["divergence"], params["lam"])] = est.weights_
    assert len(weights) == 6
    # Each setting is its own fit: smaller lam, more robust, smaller weights (every divergence).
    for div in ("tv", "kl", "chi2"):
        assert (weights[(div, 0.2)][0] <= weights[(div, 2.0)][0] + 1e-12).all()
    with pytest.raises(ValueError, match="invalid parameter 'lamm'"):
        base.set_params(lamm=1)


def test_import_r2pvi_does_not_import_sklearn():
    src = str(Path(r2pvi.__file__).resolve().parents[1])
    code = ("import sys, r2pvi, numpy as np\n"
            "est = r2pvi.R2PVI(); est.get_params(); repr(est); est.__sklearn_is_fitted__()\n"
            "assert 'sklearn' not in sys.modules, 'sklearn imported'\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": src}, timeout=120)
    assert res.returncode == 0, res.stderr


# scikit-learn's estimator checks that do not need X/y arrays (the estimators fit an
# OfflineDataset, which check_estimator's array-based checks cannot build)
DATA_FREE_CHECKS = ["check_no_attributes_set_in_init", "check_get_params_invariance",
                    "check_set_params", "check_parameters_default_constructible",
                    "check_estimator_repr", "check_estimator_cloneable",
                    "check_do_not_raise_errors_in_init_or_set_params",
                    "check_estimator_tags_renamed", "check_valid_tag_types", "check_mixin_order"]


@pytest.mark.parametrize("est", ESTIMATORS, ids=lambda e: type(e).__name__)
@pytest.mark.parametrize("check", DATA_FREE_CHECKS)
def test_sklearn_estimator_checks_that_apply_pass(est, check):
    from sklearn.utils import estimator_checks

    getattr(estimator_checks, check)(type(est).__name__, clone(est))
