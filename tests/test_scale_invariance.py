"""Every estimator is scale-invariant: rewards, r_max and every value-unit parameter times c
give weights times c, for c from 1e-300 to 1e300, and are finite for any finite r_max.

The units: a value (rewards, r_max, V) scales by c. The regularized problem
``inf_mu E_mu V + lam D(mu || mu0)`` has a dimensionless divergence D (TV, KL, chi^2, every
f-divergence), so ``lam`` is in value units for every divergence: scaled by c, the problem's
value scales by c (chi^2's dual ``max_alpha E[V]_alpha - Var[V]_alpha / (4 lam)`` too: the
variance scales by c^2, ``lam`` by c). The pessimism penalty ``beta ||phi||`` is subtracted
from Q, so ``beta`` is in value units; so is DRVI-L's ``b_min`` (the dual variable ``b`` of
``-b log E e^{-V/b}``). The radii ``rho`` of the uncertainty balls are dimensionless, and so
are the variance-aware weights ``1 / sigma^2`` (the variance is measured in units of
``r_max^2``, the paper's setting ``r_max = 1``).
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi import PEVI, R2PVI, OfflineDataset
from r2pvi.algorithms import DRPVI, DRVIL

pytestmark = pytest.mark.filterwarnings("ignore::r2pvi.SimplexFeatureWarning")


def dataset(c, seed, signed, K=30, H=3, d=3, A=2):
    rng = np.random.default_rng(seed)
    if signed:
        phi, next_phi = rng.normal(size=(K, H, d)), rng.normal(size=(K, H, A, d))
    else:
        phi = rng.dirichlet(np.full(d, 0.6), size=(K, H))
        next_phi = rng.dirichlet(np.full(d, 0.6), size=(K, H, A))
    rewards = rng.uniform(0, 1, size=(K, H))
    rewards[rng.random((K, H)) < 0.2] = 0.0  # ties at the least value
    return OfflineDataset.from_features(phi, c * rewards, next_phi)


def estimators(c, lam):
    """Every estimator with its value-unit parameters (r_max, beta, lam, b_min) times c."""
    kw = {"beta": 0.1 * c, "r_max": c}
    return {
        "PEVI": PEVI(**kw),
        "R2PVI-TV": R2PVI("tv", lam=lam * c, **kw),
        "R2PVI-KL": R2PVI("kl", lam=lam * c, **kw),
        "R2PVI-chi2": R2PVI("chi2", lam=lam * c, **kw),
        "R2PVI-hellinger": R2PVI("hellinger", lam=lam * c, **kw),
        "VA-R2PVI-TV": R2PVI("tv", lam=lam * c, variance_aware=True, **kw),
        "DRPVI": DRPVI(0.2, **kw),
        "VA-DRPVI": DRPVI(0.2, variance_aware=True, **kw),
        "DRVI-L": DRVIL(0.2, **kw),
        "DRVI-L b_min": DRVIL(0.2, b_min=0.05 * c, **kw),
    }


@settings(max_examples=25, deadline=None)
@given(st.floats(-300.0, 300.0), st.integers(0, 2**16), st.booleans(),
       st.sampled_from([1e-3, 0.3, 30.0]))
def test_scaling_rewards_and_value_parameters_scales_the_weights(log_c, seed, signed, lam):
    """Weights times c, finite, to 1e-9 relative, for c from 1e-300 to 1e300: where squares of
    the values overflow (chi^2, VA-R2PVI-TV, VA-DRPVI from c = 1e155), underflow (chi^2,
    Hellinger at c = 1e-300), a variance floor in squared value units (VA-*) or an absolute
    tolerance (DRVI-L) would break it."""
    c = 10.0**log_c
    base = {k: e.fit(dataset(1.0, seed, signed)).weights_
            for k, e in estimators(1.0, lam).items()}
    scaled = dataset(c, seed, signed)
    for name, est in estimators(c, lam).items():
        w = est.fit(scaled).weights_
        assert np.all(np.isfinite(w)), name
        ref = base[name]
        np.testing.assert_allclose(w / c, ref, rtol=0, atol=1e-9 * max(1.0, np.abs(ref).max()),
                                   err_msg=f"{name}, c = {c:g}")


@pytest.mark.parametrize("r_max", [1e155, 1e300, 1.7e308 / 8])
@pytest.mark.parametrize("lam", [1e-300, 0.3, 1e300])
def test_huge_reward_bounds_give_finite_weights(r_max, lam):
    """r_max up to 1.7e308 / 8 gives finite weights for every estimator, R2PVI-chi^2 (also at
    lam = 1e-300), VA-R2PVI-TV and VA-DRPVI included."""
    ds = dataset(r_max / 4, 0, False)  # rewards up to r_max / 4 (the sums stay finite)
    for name, est in estimators(1.0, 1.0).items():
        est.set_params(r_max=r_max)
        if "lam" in est.get_params():
            est.set_params(lam=lam)
        w = est.fit(ds).weights_
        assert np.all(np.isfinite(w)), name
        assert np.all(np.abs(w) <= 10 * ds.horizon * r_max), name
