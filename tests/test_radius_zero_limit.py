"""A zero radius is PEVI's projected estimate, and the limit of every radius rho -> 0+.

DRPVI and DRVI-L with ``rho_{h,i} = 0`` estimate factor ``i`` at step ``h`` as PEVI does: the
plain ridge estimate projected onto the known value range ``[0, (H - h - 1) r_max]``; for
small positive radii the estimate tends to it (TV: within ``rho`` times the value spread;
KL: within about ``sqrt(2 rho Var V)``). Checked on signed ridge data, on Dirichlet data, per
factor (some radii zero, some not) and on exact distributions.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi import PEVI, OfflineDataset
from r2pvi.algorithms import DRPVI, DRVIL, KLBallRule, RidgeRule, TVBallRule
from r2pvi.duals import FactorExpectation, RidgeExpectation, cholesky_gram
from r2pvi.engine import StepContext


def signed_dataset(K=40, H=3, d=4, A=2, seed=0):
    """Gaussian (signed) features: plain ridge estimates far outside the value range."""
    rng = np.random.default_rng(seed)
    phi = rng.normal(size=(K, H, d))
    next_phi = rng.normal(size=(K, H, A, d))
    return OfflineDataset.from_features(phi, rng.uniform(0, 1, size=(K, H)), next_phi)


def dirichlet_dataset(K=40, H=3, d=4, A=2, seed=0):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.full(d, 0.5), size=(K, H))
    next_phi = rng.dirichlet(np.full(d, 0.5), size=(K, H, A))
    theta = rng.uniform(0, 1, size=(H, d))
    return OfflineDataset.from_features(phi, np.einsum("khd,hd->kh", phi, theta), next_phi)


pytestmark = pytest.mark.filterwarnings("ignore::r2pvi.SimplexFeatureWarning")

ESTIMATORS = {"DRPVI": DRPVI, "DRVI-L": DRVIL}


@pytest.mark.parametrize("make", [signed_dataset, dirichlet_dataset])
@pytest.mark.parametrize("name", list(ESTIMATORS))
@pytest.mark.parametrize("beta, gamma", [(0.0, 1.0), (0.3, 0.5)])
def test_zero_radius_is_pevi_and_the_limit_of_small_radii(make, name, beta, gamma):
    """rho = 0 gives PEVI's weights exactly, and rho = 1e-12, 1e-9 stay within about rho (TV)
    or sqrt(rho) (KL) of them: rho = 0 projects the plain estimate onto the value range as
    small radii do (unprojected, it has factor values below 0 on the signed data)."""
    kw = {"beta": beta, "gamma": gamma, "penalty": "l1"}
    for seed in range(3):
        ds = make(seed=seed)
        pevi = PEVI(**kw).fit(ds).weights_
        zero = ESTIMATORS[name](0.0, **kw).fit(ds).weights_
        np.testing.assert_allclose(zero, pevi, rtol=0, atol=1e-12)
        for rho in (1e-12, 1e-9):
            near = ESTIMATORS[name](rho, **kw).fit(ds).weights_
            # TV: rho times the spread (<= H); KL: sqrt(2 rho Var V); both times the
            # steps' propagation through the ridge weights
            tol = 100 * (rho if name == "DRPVI" else np.sqrt(rho)) * ds.horizon
            np.testing.assert_allclose(near, zero, rtol=0, atol=tol)


def ridge_operator(seed, n, d, signed):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.full(d, 0.6), size=n)
    if signed:
        phi = phi - 0.2
    v = rng.uniform(0.0, 1.0, size=n)
    v[rng.random(n) < 0.3] = 0.0  # ties at the minimum
    return RidgeExpectation(phi, cholesky_gram(phi, 1.0)), v


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(3, 60), st.integers(2, 6), st.booleans(),
       st.integers(0, 2**16 - 1))
def test_per_factor_zero_radii_give_pevi_in_those_factors(seed, n, d, signed, mask):
    """With per-factor radii, every factor with rho_i = 0 gets RidgeRule's (PEVI's) value
    for the same values, and the others stay in [0, that value]."""
    E, v = ridge_operator(seed, n, d, signed)
    ctx = StepContext(h=0, horizon=3, r_max=0.5, v_upper=1.5)  # values in [0, 1]
    zero = (mask >> np.arange(d)) & 1 == 1
    rho = np.where(zero, 0.0, 0.2)[None, :].repeat(3, axis=0)
    pevi = RidgeRule()(E, v, ctx)
    for rule in (TVBallRule(rho, "data"), TVBallRule(rho, 0.0), KLBallRule(rho),
                 KLBallRule(rho, None)):
        w = rule(E, v, ctx)
        np.testing.assert_array_equal(w[zero], pevi[zero])
        assert np.all(w[~zero] >= 0.0) and np.all(w[~zero] <= pevi[~zero] + 1e-15)
        for tiny in (1e-12, 1e-9):
            near = rule.__class__(np.where(zero, 0.0, tiny)[None, :].repeat(3, axis=0),
                                  *rule_args(rule))(E, v, ctx)
            tol = 4 * tiny if isinstance(rule, TVBallRule) else 4 * np.sqrt(tiny)
            np.testing.assert_allclose(near, pevi, rtol=0, atol=tol)


def rule_args(rule):
    return (rule.v_min,) if isinstance(rule, TVBallRule) else (rule.b_min, rule.form)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 4), st.integers(2, 9))
def test_zero_radius_on_exact_distributions_is_the_expectation(seed, d, n):
    """On true factor distributions a zero radius is E_i V (the projection is the identity)
    and small radii are close to it."""
    rng = np.random.default_rng(seed)
    mu = rng.dirichlet(np.full(n, 0.7), size=d)
    v = rng.uniform(0.0, 1.0, size=n)
    E = FactorExpectation(mu)
    ctx = StepContext(h=0, horizon=3, r_max=0.5, v_upper=1.5)
    rho0 = np.zeros((3, d))
    for rule in (TVBallRule(rho0, "data"), KLBallRule(rho0, None)):
        np.testing.assert_allclose(rule(E, v, ctx), mu @ v, rtol=0, atol=1e-15)
        for tiny in (1e-12, 1e-9):
            near = rule.__class__(np.full((3, d), tiny), *rule_args(rule))(E, v, ctx)
            tol = 2 * tiny if isinstance(rule, TVBallRule) else 2 * np.sqrt(tiny)
            np.testing.assert_allclose(near, mu @ v, rtol=0, atol=tol)
