"""The expectation-operator interface (``r2pvi.duals.ExpectationOperator``) is all a dual needs.

An operator that provides only the required members (``n_dims``, ``n_points``,
``nonnegative``, ``E(y)``, ``rows``) runs every dual and gives the numbers of the library's
own operators with the same weights; a dual that needs several expectations at once asks for
them together through the interface (``apply_pair``), so an operator that streams its points
reads them once for all of them, without the dual asking what kind of operator it holds.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi.duals import (
    HELLINGER,
    ExpectationOperator,
    FactorExpectation,
    RidgeExpectation,
    chi2_constrained,
    chi2_regularized,
    cholesky_gram,
    f_regularized,
    kl_constrained,
    kl_regularized,
    tv_constrained,
    tv_regularized,
)


class Minimal(ExpectationOperator):
    """The required members only, over an explicit weight matrix."""

    def __init__(self, m, nonnegative=False):
        self.m = np.asarray(m, dtype=float)
        self.n_dims, self.n_points = self.m.shape
        self.nonnegative = nonnegative

    def __call__(self, y):
        return self.m @ y

    def rows(self, dims=None):
        return self.m if dims is None else self.m[np.atleast_1d(dims)]


DUALS = {
    "tv_regularized": lambda E, v: tv_regularized(E, v, 0.4),
    "kl_regularized": lambda E, v: kl_regularized(E, v, 0.4),
    "chi2_regularized": lambda E, v: chi2_regularized(E, v, 0.4),
    "f_regularized": lambda E, v: f_regularized(E, v, 0.4, HELLINGER),
    "tv_constrained": lambda E, v: tv_constrained(E, v, 0.2),
    "kl_constrained": lambda E, v: kl_constrained(E, v, 0.2, v_range=(0.0, 3.0)),
    "kl_constrained normalized": lambda E, v: kl_constrained(E, v, 0.2, normalized=True,
                                                             v_range=(0.0, 3.0)),
}


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(20, 700), st.integers(1, 5),
       st.sampled_from(sorted(DUALS)))
def test_every_dual_runs_on_an_operator_with_only_the_required_members(seed, n, d, name):
    """Ridge weights (signed, shrunk) through the minimal operator: the dual's value is the
    one on the ridge operator itself (its fast paths reorder sums: 1e-9 of the values)."""
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=n) - 0.05 * rng.random((n, d))
    ridge = RidgeExpectation(phi, cholesky_gram(phi, 0.5))
    v = rng.uniform(0.0, 3.0, n)
    got = DUALS[name](Minimal(ridge.matrix), v)
    want = DUALS[name](ridge, v)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", sorted(DUALS) + ["chi2_constrained"])
def test_every_dual_runs_on_a_minimal_operator_whose_rows_are_distributions(name):
    rng = np.random.default_rng(3)
    mu = rng.dirichlet(np.ones(40), size=4)
    v = rng.uniform(0.0, 3.0, 40)
    dual = DUALS.get(name, lambda E, v: chi2_constrained(E, v, 0.3))
    got = dual(Minimal(mu, nonnegative=True), v)
    np.testing.assert_allclose(got, dual(FactorExpectation(mu), v), rtol=1e-12, atol=1e-12)


class Streaming(Minimal):
    """Counts reads of its points: one per call, one per ``apply_pair`` (both columns)."""

    def __init__(self, m):
        super().__init__(m)
        self.reads = []

    def __call__(self, y):
        self.reads.append(("call", np.ndim(y)))
        return super().__call__(y)

    def apply_pair(self, y1, y2):
        self.reads.append(("pair", np.ndim(y1), np.ndim(y2)))
        return super().__call__(y1), super().__call__(y2)


@pytest.mark.parametrize("normalized", [False, True])
def test_kl_ball_reads_the_points_once_for_the_plain_estimate_and_its_grid(normalized):
    """``kl_constrained``'s first read is one ``apply_pair``: ``E(v)`` with the grid's columns
    (not ``E(v)`` and then the grid, two reads of a streamed step's features)."""
    rng = np.random.default_rng(0)
    phi = rng.dirichlet(np.ones(4), size=300)
    E = Streaming(RidgeExpectation(phi, cholesky_gram(phi, 1.0)).matrix)
    v = rng.uniform(0.0, 2.0, 300)
    got = kl_constrained(E, v, 0.1, normalized=normalized, v_range=(0.0, 2.0))
    assert E.reads[0] == ("pair", 1, 2), E.reads
    assert ("call", 1) not in E.reads  # E(v) is never asked for on its own
    want = kl_constrained(Minimal(E.m), v, 0.1, normalized=normalized, v_range=(0.0, 2.0))
    np.testing.assert_array_equal(got, want)
