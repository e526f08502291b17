"""OfflineDataset in memory: constructors, validation, simplex warnings, read-only views,
subsets, the ``.npz`` round trip. (Directories: test_dataset_directory.py; the writer:
test_dataset_writer.py; other storage kinds: test_storage_kinds.py.)"""

import warnings

import numpy as np
import pytest

from r2pvi import OfflineDataset, SimplexFeatureWarning


def arrays(K=4, H=3, d=2, A=2, seed=0):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    return phi, rng.random((K, H)), next_phi


def test_from_features_shapes_and_views():
    phi, r, nphi = arrays()
    ds = OfflineDataset.from_features(phi, r, nphi)
    assert (ds.n_trajectories, ds.horizon, ds.n_features, ds.n_actions) == (4, 3, 2, 2)
    np.testing.assert_array_equal(ds.phi, phi)
    np.testing.assert_array_equal(ds.rewards, r)
    np.testing.assert_array_equal(ds.next_phi[:, :2], nphi[:, :2])
    assert np.isnan(ds.next_values).all() and not ds.has_known_values
    with pytest.raises(ValueError):
        ds.phi[0, 0, 0] = 5.0  # read-only views


def test_inputs_are_copied_not_mutated():
    phi, r, nphi = arrays()
    nphi[:, -1] = np.nan  # the unused last row may be undefined
    before = nphi.copy()
    ds = OfflineDataset.from_features(phi, r, nphi)
    np.testing.assert_array_equal(nphi, before)
    phi[0, 0, 0] = 123.0
    assert ds.phi[0, 0, 0] != 123.0


@pytest.mark.parametrize(
    "mutate, err, match",
    [
        (lambda p, r, n: (p[:0], r[:0], n[:0]), ValueError, "K = 0"),
        (lambda p, r, n: (p, r[:, :2], n), ValueError, "rewards must have shape"),
        (lambda p, r, n: (p, r, n[:, :, :, :1]), ValueError, "next_phi must have shape"),
        (lambda p, r, n: (p[..., 0], r, n), ValueError, "phi must have 3 dimensions"),
        (lambda p, r, n: (np.where(p > 0.5, np.nan, p), r, n), ValueError, "NaN or infinite"),
        (lambda p, r, n: (p, np.full_like(r, np.inf), n), ValueError, "NaN or infinite"),
        (lambda p, r, n: (p.astype(str), r, n), TypeError, "numeric"),
        (lambda p, r, n: (p, r, np.where(n > 0.5, np.nan, n)), ValueError, "h < H-1"),
    ],
)
def test_validation_errors_name_the_argument(mutate, err, match):
    with pytest.raises(err, match=match):
        OfflineDataset.from_features(*mutate(*arrays()))


def test_next_values_shape_and_infinity_are_checked():
    phi, r, nphi = arrays()
    with pytest.raises(ValueError, match="next_values must have shape"):
        OfflineDataset.from_features(phi, r, nphi, np.zeros((4, 3, 3)))
    with pytest.raises(ValueError, match="infinite"):
        OfflineDataset.from_features(phi, r, nphi, np.full((4, 3, 2), np.inf))
    known = np.full((4, 3, 2), np.nan)
    known[:, 0, 1] = 0.0
    ds = OfflineDataset.from_features(phi, r, nphi, known)
    assert ds.has_known_values
    assert np.isnan(ds.next_values[:, -1]).all()  # the last step's row is never used


def test_simplex_assumption_warns_but_does_not_fail():
    phi, r, nphi = arrays()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        OfflineDataset.from_features(phi, r, nphi)  # on the simplex: silent
    with pytest.warns(SimplexFeatureWarning, match="simplex"):
        OfflineDataset.from_features(2 * phi, r, nphi)
    with pytest.warns(SimplexFeatureWarning, match="negative"):
        OfflineDataset.from_features(phi - 0.6, r, nphi)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        OfflineDataset.from_features(2 * phi, r, nphi, check_simplex=False)


def test_from_transitions_matches_from_features():
    rng = np.random.default_rng(1)
    S, A, d, K, H = 5, 3, 4, 6, 2
    table = rng.dirichlet(np.ones(d), size=(S, A))
    states = rng.integers(S, size=(K, H))
    actions = rng.integers(A, size=(K, H))
    nxt = rng.integers(S, size=(K, H))
    r = rng.random((K, H))
    fail = lambda s: np.where((s == 0)[:, None], 0.0, np.nan) * np.ones((1, A))  # noqa: E731
    ds = OfflineDataset.from_transitions(states, actions, r, nxt, lambda s, a: table[s, a], A,
                                         next_values=fail)
    np.testing.assert_array_equal(ds.phi, table[states, actions])
    np.testing.assert_array_equal(ds.next_phi[:, 0], table[nxt[:, 0]])
    assert np.array_equal(np.isnan(ds.next_values[:, 0, 0]), nxt[:, 0] != 0)
    np.testing.assert_array_equal(ds.states, states)
    with pytest.raises(ValueError, match=r"actions must lie in \[0, 3\)"):
        OfflineDataset.from_transitions(states, actions + 3, r, nxt, lambda s, a: table[s, a], A)
    with pytest.raises(TypeError, match="feature_map must be callable"):
        OfflineDataset.from_transitions(states, actions, r, nxt, table, A)


def test_save_load_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    table = rng.dirichlet(np.ones(3), size=(4, 2))
    states = rng.integers(4, size=(5, 2))
    ds = OfflineDataset.from_transitions(states, np.zeros((5, 2), int), rng.random((5, 2)),
                                         rng.integers(4, size=(5, 2)), lambda s, a: table[s, a], 2)
    legacy = ds.save(tmp_path / "data.npz")  # the version-1 single file still round-trips
    assert legacy.suffix == ".npz" and legacy.is_file()
    directory = ds.save(tmp_path / "data")  # the step-major directory (format version 2)
    assert directory.is_dir()
    for back in (OfflineDataset.load(legacy), OfflineDataset.load(directory),
                 OfflineDataset.open(directory)):
        for name in ("phi", "rewards", "next_phi", "states", "actions", "next_states"):
            np.testing.assert_array_equal(getattr(back, name)[:, :1], getattr(ds, name)[:, :1])
        np.testing.assert_array_equal(back.next_values, ds.next_values)


def test_load_rejects_foreign_and_future_files(tmp_path):
    np.savez(tmp_path / "plain.npz", phi=np.ones(3))
    with pytest.raises(ValueError, match="not an r2pvi file"):
        OfflineDataset.load(tmp_path / "plain.npz")
    from r2pvi._io import save_npz

    save_npz(tmp_path / "future.npz", "OfflineDataset", 99, {}, {})
    with pytest.raises(ValueError, match="format version 99"):
        OfflineDataset.load(tmp_path / "future.npz")
    with pytest.raises(FileNotFoundError):
        OfflineDataset.load(tmp_path / "missing.npz")


def test_subset_selects_trajectories():
    ds = OfflineDataset.from_features(*arrays(K=6))
    sub = ds.subset([0, 2])
    np.testing.assert_array_equal(sub.phi, ds.phi[[0, 2]])
    mask = np.zeros(6, bool)
    mask[[1, 5]] = True
    assert ds.subset(mask).n_trajectories == 2
    with pytest.raises(ValueError):
        ds.subset([])


def test_from_features_keeps_observed_states_and_checks_their_shape(tmp_path):
    phi, r, nphi = arrays()
    states = np.arange(12).reshape(4, 3)
    ds = OfflineDataset.from_features(phi, r, nphi, states=states, actions=np.zeros((4, 3)),
                                      next_states=states + 1)
    np.testing.assert_array_equal(ds.states, states)
    assert ds.actions.dtype == np.int64
    back = OfflineDataset.load(ds.save(tmp_path / "d"))
    np.testing.assert_array_equal(back.next_states, states + 1)
    np.testing.assert_array_equal(ds.subset([1]).states, states[[1]])
    with pytest.raises(ValueError, match=r"states must start with \(K, H\)"):
        OfflineDataset.from_features(phi, r, nphi, states=states[:2])
