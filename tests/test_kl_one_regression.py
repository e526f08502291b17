"""KL with one regression per step: ``E(1)`` from the column sums kept with the Gram matrix.

``kl_regularized`` needs the moment ``u = E(e^{-(V-c)/lam})``, the row sums ``s = E(1)`` and
the centered moment ``um = u - s``. It regresses one of ``u``, ``um`` (``u`` up to one value
spread, ``um`` above) and takes ``s = Lambda^-1 Phi^T 1`` from the column sums that ride along
with the Gram matrix. The truth here is the two-regression form (``u`` and ``um`` both
regressed, ``s = u - um``): on random ridge operators the two must agree within the
rounding bound of the code's comment, ``C 2^-53 cond(Lambda) (sum_j |M_ij| / s_i)`` times the
values' magnitude (plus ``lam s_i / u_i`` where the log of a small moment is taken).
How a fit from stored data gets the column sums (with the first read of a step, from the
file, or from the Gram matrix for rows on the simplex) is tested with the storage internals,
in test_storage_internals_chunks.py.
"""

from __future__ import annotations

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from r2pvi.duals import ExpectationOperator, RidgeExpectation, cholesky_gram, kl_regularized

EPS = 2.0**-53


class TwoRegressions(ExpectationOperator):
    """``E`` whose ``(E(y), E(1))`` is formed from two regressions, ``E(y) - E(y - 1)``: the
    reference form."""

    def __init__(self, E):
        self.E, self.n_dims, self.n_points = E, E.n_dims, E.n_points
        self.nonnegative = E.nonnegative

    def __call__(self, y):
        return self.E(y)

    def rows(self, dims=None):
        return self.E.rows(dims)

    def with_total_weights(self, y):
        a = self.E(y)
        return a, a - self.E(y - 1.0)


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 40), d=st.integers(1, 4),
       signed=st.booleans(), zero_factor=st.booleans(),
       log_gamma=st.floats(-2, 2), log_scale=st.floats(-3, 6), log_ratio=st.floats(-3, 3))
def test_one_regression_agrees_with_two_within_the_rounding_bound(
        seed, n, d, signed, zero_factor, log_gamma, log_scale, log_ratio):
    """Signed weights, ties, factors with no mass, values from 1e-3 to 1e6, lam from 1e-3 to
    1e3 value spreads (both sides of the switch at one spread and of expm1's at 64)."""
    rng = np.random.default_rng(seed)
    phi = rng.normal(size=(n, d)) if signed else rng.dirichlet(np.ones(d), size=n)
    if zero_factor and d > 1:
        phi[:, -1] = 0.0  # a feature no sample activates: s_i = u_i = 0
    gamma = 10.0**log_gamma
    E = RidgeExpectation(phi, cholesky_gram(phi, gamma))
    lam_mat = phi.T @ phi + gamma * np.eye(d)
    cond = np.linalg.cond(lam_mat)
    assume(cond < 1e8)
    scale = 10.0**log_scale
    v = rng.uniform(0.0, scale, size=n)
    v[: n // 3] = v[0]  # ties
    spread = float(v.max() - v.min())
    lam = max(spread, scale * 1e-9) * 10.0**log_ratio
    got = kl_regularized(E, v, lam)
    ref = kl_regularized(TwoRegressions(E), v, lam)
    m = E.rows()
    S = np.abs(m).sum(axis=1)
    s = m.sum(axis=1)
    shift = v.min()
    u = m @ np.exp(-(v - shift) / lam)
    dead = S == 0.0
    np.testing.assert_array_equal(got[dead], ref[dead])  # no mass: both the plain estimate
    # Compare where the branch is decided by more than rounding: s_i and u_i clearly positive.
    ok = ~dead & (s > 1e-6 * S) & (u > 1e-6 * S) & (u > 1e-200)
    small = u < 0.5 * s
    with np.errstate(divide="ignore", invalid="ignore"):
        tol = 64 * EPS * cond * (S / np.abs(s)) * (
            np.abs(v).max() + np.where(small, lam * s / np.abs(u), 0.0))
    assert np.all(np.abs(got - ref)[ok] <= tol[ok]), (got - ref, tol)


def test_a_single_moment_regression_breaks_the_bound_at_large_lam():
    """The guard the test above checks: regressing ``u`` alone (``um = u - s``) at 30 value
    spreads leaves an error growing like lam / spread (the reason ``um`` is regressed there).
    Measured against the two-regression form, the rejected form is off by far more than the
    chosen one."""
    rng = np.random.default_rng(3)
    phi = rng.dirichlet(np.ones(6), size=300)
    E = RidgeExpectation(phi, cholesky_gram(phi, 0.3))
    v = rng.uniform(0.0, 1.0, size=300)
    lam = 30.0
    ref = kl_regularized(TwoRegressions(E), v, lam)
    got = kl_regularized(E, v, lam)
    z = -(v - v.min()) / lam
    u, s = E(np.exp(z)), E.total_weights()
    rejected = s * (v.min() - lam * np.log1p((u - s) / s))
    ok = (u > 0.5 * s) & (s > 0)
    assert np.abs(got - ref)[ok].max() < np.abs(rejected - ref)[ok].max()


def test_total_weights_is_the_regression_of_ones_for_every_operator_form():
    rng = np.random.default_rng(0)
    phi = rng.normal(size=(50, 4))
    w = rng.uniform(0.1, 2.0, size=50)
    for weights in (None, w):
        for form in ("primal", "dual"):
            from r2pvi.duals import GramFactor

            E = RidgeExpectation(phi, GramFactor(phi, 0.5, weights, form), weights)
            xw = phi if weights is None else phi * weights[:, None]
            truth = np.linalg.solve(xw.T @ phi + 0.5 * np.eye(4), xw.T @ np.ones(50))
            np.testing.assert_allclose(E.total_weights(), truth, rtol=1e-10)
            y = rng.normal(size=50)
            a, b = E.with_total_weights(y)
            np.testing.assert_allclose(a, E(y), rtol=1e-12)
            np.testing.assert_allclose(b, truth, rtol=1e-10)
