"""Data, estimators and comparisons that the storage tests share, and ``set_chunk``.

The truth for every fit from stored data is the in-memory fit of the same numbers
(``assert_same_fit``). ``set_chunk`` is the one storage internal that tests of public
behaviour set: no public API chooses how many trajectories a step is read at a time, and
the tests must make it small to cut each step into many chunks.
"""

from __future__ import annotations

import numpy as np
import pytest

import r2pvi
from r2pvi import DatasetWriter, OfflineDataset
from r2pvi.algorithms import DRPVI, DRVIL

K, H, D, A = 600, 4, 5, 3  # K >= 512: chi^2 takes its blockwise (branch and bound) path


def make_arrays(k=K, seed=0, known=True):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(D), size=(k, H))
    nphi = rng.dirichlet(np.ones(D), size=(k, H, A))
    rewards = phi @ rng.uniform(0, 1, D)
    nv = None
    if known:
        nv = np.full((k, H, A), np.nan)
        nv[rng.random((k, H)) < 0.2, 0] = 0.0  # a known-value action (an exercise, a fail)
    return phi, rewards, nphi, nv


ESTIMATORS = {
    "PEVI": lambda: r2pvi.PEVI(beta=0.1),
    "TV": lambda: r2pvi.R2PVI("tv", 0.3, beta=0.1),
    "KL": lambda: r2pvi.R2PVI("kl", 0.3, beta=0.1),
    "chi2": lambda: r2pvi.R2PVI("chi2", 0.3, beta=0.1),
    "DRPVI": lambda: DRPVI(0.2, beta=0.1),
    "DRVI-L": lambda: DRVIL(0.2, beta=0.1),
    "VA-TV": lambda: r2pvi.R2PVI("tv", 0.3, beta=0.1, variance_aware=True),
}


def assert_same_fit(a, b, atol=1e-10):
    for name in ("weights_", "reward_weights_", "gram_inv_diag_"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=atol,
                                   err_msg=name)
    if getattr(a, "_elliptical", None) is not None:  # the elliptical penalty's fitted factors
        for (ra, *ca), (rb, *cb) in zip(a._elliptical, b._elliptical, strict=True):
            np.testing.assert_allclose(ra, rb, rtol=0, atol=atol, err_msg="elliptical")
            assert ca == cb


def stored_datasets(root):
    """The same numbers in memory, as a saved directory and written by chunks."""
    phi, rewards, nphi, nv = make_arrays()
    mem = OfflineDataset.from_features(phi, rewards, nphi, nv)
    saved = mem.save(root / "saved")
    with DatasetWriter(root / "written", horizon=H, n_features=D, n_actions=A,
                       dtype="float64") as w:
        for s, e in ((0, 1), (1, 250), (250, 251), (251, K)):  # uneven chunks
            w.append(phi[s:e], rewards[s:e], nphi[s:e], nv[s:e])
    return mem, saved, root / "written"


def dask_and_memory(chunk):
    """The same data as Dask arrays (``chunk`` trajectories per block) and in memory."""
    da = pytest.importorskip("dask.array")
    arrays = make_arrays()
    ds = OfflineDataset.from_dask(*(da.from_array(a, chunks=(chunk,) + (-1,) * (a.ndim - 1))
                                    for a in arrays))
    return ds, OfflineDataset.from_features(*arrays)


def set_chunk(ds, rows):
    """Make fits of ``ds`` read each step ``rows`` trajectories at a time (a private knob of
    the step source: no public API sets it)."""
    ds._source.chunk = rows


def small_arrays(k, H=3, d=4, A=2, seed=0):
    """``(phi, rewards, next_phi)`` of ``k`` trajectories on the simplex (default H = 3, d = 4,
    A = 2)."""
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(k, H))
    next_phi = rng.dirichlet(np.ones(d), size=(k, H, A))
    return phi, rng.uniform(0.0, 1.0, (k, H)), next_phi
