"""Shared test configuration: reproducible hypothesis runs in CI."""

import os

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    print_blob=True,
)
settings.register_profile("dev", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("ci" if os.environ.get("CI") else "dev")


@pytest.fixture(scope="module")
def cluster_client():
    """A ``distributed`` client of a local cluster of 2 in-process workers (one thread each)."""
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                       dashboard_address=None)
    client = distributed.Client(cluster)
    yield client
    client.close()
    cluster.close()


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """The same numbers in memory, as a saved directory and written by chunks."""
    from storage_helpers import stored_datasets

    return stored_datasets(tmp_path_factory.mktemp("storage"))
