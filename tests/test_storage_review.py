"""Storage findings of the adversarial review (2026-12-02): float32 overflow refused before
anything is written, errors that say which append and step, empty appends, a rejected chunk
that leaves the writer's flags alone, manifests with a damaged format version."""

from __future__ import annotations

import json

import numpy as np
import pytest

from r2pvi import DatasetWriter, OfflineDataset


def arrays(k, H=3, d=4, A=2, seed=0):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(k, H))
    next_phi = rng.dirichlet(np.ones(d), size=(k, H, A))
    return phi, rng.uniform(0.0, 1.0, (k, H)), next_phi


def test_float32_save_refuses_finite_values_beyond_its_range(tmp_path):
    """They became inf with only a RuntimeWarning, gram.npy was non-finite and fits NaN."""
    phi, rewards, next_phi = arrays(10)
    phi[3, 1, 2] = 1e39
    ds = OfflineDataset.from_features(phi, rewards, next_phi, check_simplex=False)
    with pytest.raises(ValueError, match="beyond float32's range.*dtype='float64'"):
        ds.save(tmp_path / "d", dtype="float32")
    assert not any(tmp_path.iterdir())  # nothing left behind
    ds.save(tmp_path / "d64", dtype="float64")  # float64 keeps them
    with pytest.raises(ValueError, match="beyond float32's range"):
        OfflineDataset.from_features(phi, rewards, next_phi, check_simplex=False,
                                     dtype="float32")
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2,
                       check_simplex=False) as w:
        with pytest.raises(ValueError, match="phi holds finite values beyond float32"):
            w.append(phi, rewards, next_phi)
        w.append(*arrays(5))
    assert OfflineDataset.open(tmp_path / "w").n_trajectories == 5


def test_a_bad_append_names_the_append_and_step_and_leaves_the_writer_as_it_was(tmp_path):
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2) as w:
        w.append(*arrays(4))
        flags = list(w._flags)
        phi, rewards, next_phi = arrays(6, seed=1)
        phi[2, 1] = -phi[2, 1]  # negative features at step 0 would flip a flag
        phi[5, 2, 0] = np.nan  # and the chunk fails at step 2
        with pytest.raises(ValueError, match=r"append #1 \(trajectories 4\.\.9.*step h = 2"):
            w.append(phi, rewards, next_phi)
        assert w._flags == flags
        w.append(*arrays(0))  # an empty batch (a stream's tail): nothing, no error
        w.append(*arrays(2, seed=2))
    ds = OfflineDataset.open(tmp_path / "w")
    assert ds.n_trajectories == 6
    assert json.loads((tmp_path / "w" / "manifest.json").read_text())["nonnegative_phi"] is True


def test_empty_append_with_mismatched_fields_is_refused(tmp_path):
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2) as w:
        phi, rewards, next_phi = arrays(3)
        with pytest.raises(ValueError, match="0 trajectories but rewards"):
            w.append(phi[:0], rewards, next_phi[:0])
        w.append(phi, rewards, next_phi)


@pytest.mark.parametrize("bad", [0, 1, -3, 2.0, "2", True, None])
def test_damaged_format_versions_are_refused_with_the_right_advice(tmp_path, bad):
    """Versions 0, -3, 1 opened; 2.0, "2", None said "upgrade r2pvi" (wrong advice)."""
    path = OfflineDataset.from_features(*arrays(3)).save(tmp_path / "d")
    mf = json.loads((path / "manifest.json").read_text())
    (path / "manifest.json").write_text(json.dumps({**mf, "format_version": bad}))
    with pytest.raises(ValueError, match="must be an integer >= 2") as err:
        OfflineDataset.open(path)
    assert "upgrade" not in str(err.value)


def test_writer_records_reward_noise_and_empty_appends_check_next_values(tmp_path):
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2,
                       reward_noise=0.1) as w:
        phi, rewards, next_phi = arrays(3)
        with pytest.raises(ValueError, match="0 trajectories but next_values"):
            w.append(phi[:0], rewards[:0], next_phi[:0], next_values=np.zeros((7, 1)))
        w.append(phi, rewards, next_phi)
    assert OfflineDataset.open(tmp_path / "w").reward_noise == 0.1


def _float32_simplex(seed, K=4000, H=4, d=6, A=2):
    rng = np.random.default_rng(seed)
    phi = rng.random((K, H, d), dtype=np.float32)
    phi /= phi.sum(-1, keepdims=True)  # sums 1 within ~1e-7 in float64: not unit rows
    nphi = rng.random((K, H, A, d), dtype=np.float32)
    nphi /= nphi.sum(-1, keepdims=True)
    return phi, nphi


def test_directories_record_row_sums_and_the_reward_check_reads_no_features(tmp_path):
    """float32 simplex rows (sums 1 within ~1e-7, not unit rows): both writers record the
    range of the stored rows' sums (``phi_row_sums``), and ``fit``'s reward check with
    ``reward_weights`` settles every step from it, reading no feature (it read all of phi
    before: 0.62 s of a 2.06 s TV fit at K = 1e6). The bound is rigorous: rewards above
    ``r_max`` are still refused, and a manifest without the record still reads the rows."""
    from r2pvi import R2PVI
    from r2pvi.algorithms import base

    phi, nphi = _float32_simplex(0)
    H, d = phi.shape[1], phi.shape[2]
    theta = np.random.default_rng(1).uniform(0.0, 0.99, (H, d))
    rewards = np.einsum("khd,hd->kh", phi, theta)
    with DatasetWriter(tmp_path / "w", horizon=H, n_features=d, n_actions=2) as w:
        w.append(phi, rewards, nphi)
    OfflineDataset.from_features(phi.astype(float), rewards, nphi.astype(float),
                                 check_simplex=False).save(tmp_path / "s", dtype="float32")
    for name in ("w", "s"):
        mf = json.loads((tmp_path / name / "manifest.json").read_text())
        lo, hi = mf["phi_row_sums"]
        sums = phi.astype(np.float64).sum(-1)
        assert lo == pytest.approx(sums.min(), abs=1e-15) and lo < 1.0 - 1e-9
        assert hi == pytest.approx(sums.max(), abs=1e-15) and hi > 1.0 + 1e-9
        ds = OfflineDataset.open(tmp_path / name)
        reads = []
        original = type(ds)._step_product

        def spy(self, h, t, original=original, reads=reads):
            reads.append(h)
            return original(self, h, t)

        with pytest.MonkeyPatch.context() as m:
            m.setattr(type(ds), "_step_product", spy)
            R2PVI("tv", 1.0, reward_weights=theta, r_max=1.0).fit(ds)
            assert reads == []
            too_big = theta.copy()
            too_big[2, 0] = 1.5  # rewards up to ~1.5 on the rows that weigh feature 0
            with pytest.raises(ValueError, match="r_max"):
                base.check_reward_range(ds, 1.0, too_big)
    # a manifest written before the record: the rows are read, the answer is the same
    mf = json.loads((tmp_path / "w" / "manifest.json").read_text())
    del mf["phi_row_sums"]
    (tmp_path / "w" / "manifest.json").write_text(json.dumps(mf))
    ds = OfflineDataset.open(tmp_path / "w")
    assert ds._source.phi_row_sums is None
    reads = []
    original = type(ds)._step_product
    with pytest.MonkeyPatch.context() as m:
        m.setattr(type(ds), "_step_product",
                  lambda self, h, t: (reads.append(h), original(self, h, t))[1])
        base.check_reward_range(ds, 1.0, theta)
    assert reads == list(range(H))


def test_validated_arrays_know_their_row_sums_and_the_reward_check_reads_no_features():
    """In memory too: validation records phi's row-sum range (float32-rounded simplex rows,
    not unit rows), so ``reward_weights`` are checked without a product per step; without the
    simplex check (no row sums) every step is read."""
    from r2pvi.algorithms import base

    phi, nphi = _float32_simplex(2)
    H, d = phi.shape[1], phi.shape[2]
    theta = np.random.default_rng(3).uniform(0.0, 0.99, (H, d))
    rewards = np.einsum("khd,hd->kh", phi, theta)
    for check, expected in ((True, []), (False, list(range(H)))):
        ds = OfflineDataset.from_features(phi.astype(float), rewards, nphi.astype(float),
                                          check_simplex=check)
        assert (ds._source.phi_row_sums is not None) == check
        assert not ds._source.unit_rows
        reads = []
        original = type(ds)._step_product
        with pytest.MonkeyPatch.context() as m:
            m.setattr(type(ds), "_step_product",
                      lambda self, h, t, reads=reads, original=original:
                      (reads.append(h), original(self, h, t))[1])
            base.check_reward_range(ds, 1.0, theta)
        assert reads == expected
