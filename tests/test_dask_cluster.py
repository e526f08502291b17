"""Dask arrays fitted on a ``distributed`` cluster: the data is persisted on the workers once,
so no step's graph carries it, and the fit equals the in-memory fit."""

from __future__ import annotations

import logging
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import r2pvi

da = pytest.importorskip("dask.array")
distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(processes=False, n_workers=2, threads_per_worker=1,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as c:
        yield c


def _arrays(K=20_000, H=6, d=8, A=2, seed=3):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    rewards = rng.uniform(size=(K, H))
    return phi, rewards, next_phi


class _Records(logging.Handler):
    def __init__(self):
        super().__init__()
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def _fit_recording(ds, divergence):
    """The fit and the ``distributed`` large-graph warnings it caused (threshold 200 kB: a
    graph carrying one step's features, here 1.3 MB, warns)."""
    import dask

    records = _Records()
    log = logging.getLogger("distributed")
    log.addHandler(records)
    try:
        with warnings.catch_warnings(record=True) as caught, \
                dask.config.set({"distributed.admin.large-graph-warning-threshold": "200kB"}):
            warnings.simplefilter("always")
            est = r2pvi.R2PVI(divergence, lam=0.5, beta=0.1).fit(ds)
    finally:
        log.removeHandler(records)
    return est, [m for m in records.messages + [str(w.message) for w in caught]
                 if "large graph" in m.lower()]


def _lazy(phi, rewards, next_phi, chunk=5000):
    K, H, A, d = next_phi.shape
    return (da.from_array(phi, chunks=(chunk, H, d)), da.from_array(rewards, chunks=(chunk, H)),
            da.from_array(next_phi, chunks=(chunk, H, A, d)))


@pytest.mark.parametrize("divergence", ["kl", "tv"])
def test_cluster_fit_equals_memory_and_sends_the_data_once(client, divergence):
    phi, rewards, next_phi = _arrays()
    memory = r2pvi.R2PVI(divergence, lam=0.5, beta=0.1).fit(
        r2pvi.OfflineDataset.from_features(phi, rewards, next_phi))
    est, large = _fit_recording(r2pvi.OfflineDataset.from_dask(*_lazy(phi, rewards, next_phi)),
                                divergence)
    # Arrays wrapping client memory travel once each (phi, rewards, next_phi), when first
    # persisted, not with every step's graph (H = 6 steps).
    assert len(large) <= 3
    np.testing.assert_allclose(est.weights_, memory.weights_, rtol=0, atol=1e-10)


def test_cluster_fit_of_persisted_arrays_sends_no_large_graph(client):
    phi, rewards, next_phi = _arrays()
    persisted = client.persist(list(_lazy(phi, rewards, next_phi)))
    distributed.wait(persisted)
    memory = r2pvi.R2PVI("kl", lam=0.5, beta=0.1).fit(
        r2pvi.OfflineDataset.from_features(phi, rewards, next_phi))
    est, large = _fit_recording(r2pvi.OfflineDataset.from_dask(*persisted), "kl")
    assert large == []
    np.testing.assert_allclose(est.weights_, memory.weights_, rtol=0, atol=1e-10)


@pytest.mark.parametrize("beta", [0.0, 0.1])
def test_cluster_fit_of_float32_arrays_equals_the_float32_memory_fit(client, beta):
    # Non-negative features with no penalty or the l1 penalty: the workers compute the
    # next-state values as one matrix-vector product per sub-chunk (in float64), as the
    # in-memory fit does; whether the features are non-negative is learned once.
    phi, rewards, next_phi = (a.astype(np.float32) if a.ndim > 2 else a for a in _arrays())
    memory = r2pvi.R2PVI("tv", lam=0.5, beta=beta).fit(
        r2pvi.OfflineDataset.from_features(phi, rewards, next_phi))
    ds = r2pvi.OfflineDataset.from_dask(*_lazy(phi, rewards, next_phi))
    assert ds._source.next.nonnegative is None
    est = r2pvi.R2PVI("tv", lam=0.5, beta=beta).fit(ds)
    assert ds._source.next.nonnegative is True
    np.testing.assert_allclose(est.weights_, memory.weights_, rtol=0, atol=1e-10)


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_cluster_fit_names_a_non_finite_next_state_feature(client, value):
    # NaN: features not known non-negative (the general form); +inf: the linear form's check
    phi, rewards, next_phi = _arrays()
    next_phi[12_345, 2, 1, 4] = value
    ds = r2pvi.OfflineDataset.from_dask(*_lazy(phi, rewards, next_phi))
    with pytest.raises(ValueError, match=r"12345"):
        r2pvi.R2PVI("kl", lam=0.5, beta=0.1).fit(ds)


def test_scale_out_guide_runs_and_its_cluster_fit_equals_the_disk_fit(tmp_path):
    """docs/scale-out.md's example, run as a script in a fresh interpreter (as a user runs
    it; its worker processes import it)."""
    import os
    import re
    import subprocess
    import sys
    from pathlib import Path

    doc = Path(__file__).resolve().parents[1] / "docs" / "scale-out.md"
    (block,) = re.findall(r"```python\n(.*?)```", doc.read_text(), flags=re.S)
    script = tmp_path / "scale_out.py"
    script.write_text(block)
    src = str(Path(r2pvi.__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [src] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    run = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip().splitlines()[-1] == "True"


# ---------------------------------------------------------------- what a step sends and reads
def test_a_steps_columns_are_scattered_to_the_worker_that_holds_its_features(client):
    from r2pvi.data.storage.dask_tasks import scatter_parts

    phi, rewards, next_phi = _arrays(K=8_000, H=3)
    ds = r2pvi.OfflineDataset.from_dask(*_lazy(phi, rewards, next_phi, chunk=1_000))
    field = ds._source.phi
    for h in range(3):
        chunks = field.step_chunks(h)
        where = field.placement(h)  # once the persist has finished
        holders = client.who_has(chunks)
        assert where == [min(holders[c.key]) for c in chunks]
        y = np.arange(8_000.0)[:, None]
        parts = scatter_parts(y, field.bounds_of_chunks(), where)
        held = client.who_has(parts)
        assert [list(held[p.key]) for p in parts] == [[w] for w in where]
        np.testing.assert_array_equal(np.concatenate(client.gather(parts)), y)
    assert len(set(field.placement(0))) == 2  # both workers hold chunks: a real placement


@pytest.mark.parametrize("cluster", [False, True])
@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(order=st.permutations(range(7)), steps_per_block=st.integers(1, 8))
def test_rewards_are_read_in_blocks_of_steps_whatever_the_order(client, monkeypatch, cluster,
                                                                order, steps_per_block):
    """Any order of steps returns each step's rewards; a backward pass (a fit's order)
    computes once per block of steps."""
    import contextlib

    import dask
    from dask.callbacks import Callback

    from r2pvi.data.storage import dask_arrays

    K, H = 300, 7
    rewards = np.random.default_rng(steps_per_block).uniform(size=(K, H))
    monkeypatch.setattr(dask_arrays, "READ_AHEAD_BYTES", steps_per_block * K * 8)
    phi, _, next_phi = _arrays(K=K, H=H)
    scheduler = contextlib.nullcontext() if cluster else dask.config.set(scheduler="threads")
    def rewards_field():
        return r2pvi.OfflineDataset.from_dask(
            *_lazy(phi, rewards, next_phi, chunk=100))._source.rewards

    with scheduler:
        field = rewards_field()
        for h in order:
            np.testing.assert_array_equal(field.read(h), rewards[:, h])
        if not cluster:  # the local scheduler's computes are counted by its callbacks
            field, starts = rewards_field(), []
            with Callback(start=lambda dsk: starts.append(1)):
                for h in range(H - 1, -1, -1):
                    np.testing.assert_array_equal(field.read(h), rewards[:, h])
            assert len(starts) == -(-H // steps_per_block)
