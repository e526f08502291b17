"""The chunked ridge operator's requests: columns asked for together share one read of the
step's features and give the bits of single requests; a result is never handed out for an
array's old contents."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi.engine import ChunkedRidgeExpectation
from r2pvi.storage import ArrayField, StepSource, StoredNext


def make_operator(seed, k=40, d=3, chunk=16, weighted=False):
    """A fresh source each time: nothing remembered from another operator's passes."""
    rng = np.random.default_rng(seed)
    phi = rng.random((2, k, d))
    src = StepSource(ArrayField(phi), ArrayField(rng.random((2, k))),
                     StoredNext(ArrayField(rng.random((2, k, 2, d)))), chunk=chunk)
    w = rng.uniform(0.5, 2.0, k) if weighted else None
    return ChunkedRidgeExpectation(src, h=1, gamma=1.0, weights=w), phi[1], w


def ridge(x, w, y):
    xw = x if w is None else x * w[:, None]
    return np.linalg.solve(xw.T @ x + np.eye(x.shape[1]), xw.T @ y)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**16), k=st.integers(1, 70), d=st.integers(1, 6),
       chunk=st.integers(1, 33), weighted=st.booleans())
def test_requests_asked_together_share_one_read_with_the_bits_of_single_requests(
        seed, k, d, chunk, weighted):
    rng = np.random.default_rng(seed + 1)
    y1, y2 = rng.normal(size=k), rng.normal(size=k)

    def single(y):
        E, _, _ = make_operator(seed, k, d, chunk, weighted)
        return E(y)

    E, _, _ = make_operator(seed, k, d, chunk, weighted)
    total = E.total_weights()
    requests = {
        "apply_pair": (lambda E: E.apply_pair(y1, y2), [single(y1), single(y2)]),
        "with_total_weights": (lambda E: E.with_total_weights(y1), [single(y1), total]),
        "pair_with_total_weights": (lambda E: E.pair_with_total_weights(y1, y2),
                                    [single(y1), single(y2), total]),
    }
    for name, (ask, want) in requests.items():
        E, _, _ = make_operator(seed, k, d, chunk, weighted)
        got = ask(E)
        assert E.passes == 1, name
        assert len(got) == len(want)
        for g, t in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, t, err_msg=name)


def test_a_registered_column_changed_after_its_result_was_handed_out_is_computed_again():
    E, x, w = make_operator(0)
    y = np.linspace(0.0, 1.0, x.shape[0])
    E.include(y)
    np.testing.assert_allclose(E(y), ridge(x, w, y), rtol=1e-12)
    assert E.passes == 1  # Lambda and the registered column together
    y[:] = y[::-1] + 3.0  # the same array object, new contents
    np.testing.assert_allclose(E(y), ridge(x, w, y), rtol=1e-12)


def test_requests_asked_again_with_the_same_arrays_see_their_new_contents():
    for weighted in (False, True):
        E, x, w = make_operator(1, weighted=weighted)
        a, b = np.ones(x.shape[0]), np.arange(x.shape[0], dtype=float)
        for step in range(3):  # a reused work buffer: new contents each time
            a += step
            b *= -0.5
            e1, e2 = E.apply_pair(a, b)
            np.testing.assert_allclose(e1, ridge(x, w, a), rtol=1e-12)
            np.testing.assert_allclose(e2, ridge(x, w, b), rtol=1e-12)
            e1, e2, s = E.pair_with_total_weights(a, b)
            np.testing.assert_allclose(e1, ridge(x, w, a), rtol=1e-12)
            np.testing.assert_allclose(e2, ridge(x, w, b), rtol=1e-12)
            np.testing.assert_allclose(s, ridge(x, w, np.ones(x.shape[0])), rtol=1e-12)


def test_a_column_asked_for_twice_in_one_request_gets_two_arrays():
    E, x, w = make_operator(2)
    y = np.linspace(-1.0, 1.0, x.shape[0])
    e1, e2 = E.apply_pair(y, y)
    np.testing.assert_array_equal(e1, e2)
    assert e1 is not e2 and E.passes == 1
