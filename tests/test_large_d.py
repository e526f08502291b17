"""Large feature spaces: the dual (Woodbury) form, sparse rows, pooled steps and cached
acting, each against an independent dense computation. (That pooled steps are views of the
arrays in memory is tested with the storage internals, in test_storage_internals_chunks.py.)"""

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

import r2pvi.engine as engine
from r2pvi import PEVI, R2PVI, OfflineDataset, load
from r2pvi._io import save_npz
from r2pvi.algorithms import DRPVI, DRVIL
from r2pvi.duals import FactorExpectation, GramFactor, RidgeExpectation, choose_form, tv_constrained
from r2pvi.duals._sparse_rows import _sparse_column_quadratic
from r2pvi.sparse import SparseOfflineDataset, StackedSparse

# ----------------------------------------------------------------------------- helpers


def _sparse_simplex(rng, shape, keep=0.3):
    """Rows on the simplex with about ``keep`` of the entries non-zero (at least one)."""
    x = rng.random(shape) * (rng.random(shape) < keep)
    x[..., 0] += 1e-3 * (x.sum(axis=-1) == 0)
    return x / x.sum(axis=-1, keepdims=True)


def _data(rng, K, H, d, A=2):
    phi = _sparse_simplex(rng, (K, H, d))
    next_phi = _sparse_simplex(rng, (K, H, A, d))
    rewards = phi @ rng.random(d)
    return phi, rewards, next_phi


def _both(phi, rewards, next_phi, next_values=None):
    """The same data as a dense OfflineDataset and as a SparseOfflineDataset."""
    K, H, A, d = next_phi.shape
    dense = OfflineDataset.from_features(phi, rewards, next_phi, next_values)
    sparse = SparseOfflineDataset.from_rows(
        [sp.csr_matrix(phi[:, h]) for h in range(H)], rewards,
        [sp.csr_matrix(next_phi[:, h].reshape(K * A, d)) for h in range(H)], A, next_values)
    return dense, sparse


def _lam_inv(phi, gamma, w=None):
    w = np.ones(phi.shape[0]) if w is None else w
    return np.linalg.inv(phi.T @ (phi * w[:, None]) + gamma * np.eye(phi.shape[1]))


ESTIMATORS = {
    "tv": lambda: R2PVI("tv", 0.3, beta=0.2),
    "kl": lambda: R2PVI("kl", 0.5, beta=0.2, penalty="l2"),
    "chi2": lambda: R2PVI("chi2", 0.5, beta=0.2),
    "drpvi": lambda: DRPVI(0.2, beta=0.2),
    "va-drpvi": lambda: DRPVI(0.2, beta=0.2, variance_aware=True),
    "drvil": lambda: DRVIL(0.3, beta=0.2),
    "pevi": lambda: PEVI(beta=0.2),
}


def _fit(make, ds, form="auto", **extra):
    est = make().set_params(**extra)
    est._gram_form = form
    return est.fit(ds)


# ----------------------------------------------------------------------------- GramFactor


@settings(max_examples=40)
@given(
    n=st.integers(1, 12), d=st.integers(1, 12), seed=st.integers(0, 2**31),
    log_gamma=st.floats(-2.0, 2.0), weighted=st.booleans(),
    scale=st.sampled_from([1e-3, 1.0, 1e3]),
)
def test_primal_and_dual_factors_agree_with_the_dense_inverse(n, d, seed, log_gamma, weighted,
                                                               scale):
    """Both forms, dense and sparse rows, against ``inv(Phi^T W Phi + gamma I)`` formed directly:
    signed features, repeated rows (ties), zero rows and columns, extreme scales."""
    rng = np.random.default_rng(seed)
    phi = scale * rng.standard_normal((n, d)) * (rng.random((n, d)) < 0.6)
    if n > 1:
        phi[-1] = phi[0]  # a repeated row: Psi Psi^T singular
    gamma = 10.0**log_gamma * scale**2
    w = rng.uniform(0.05, 3.0, n) if weighted else None
    inv = _lam_inv(phi, gamma, w)
    m_true = inv @ phi.T * (1.0 if w is None else w)
    y = rng.standard_normal((n, 2))
    x = rng.standard_normal((3, d)) * scale
    ell_true = np.einsum("ij,jk,ik->i", x, inv, x)
    for rows in (phi, sp.csr_matrix(phi)):
        for form in ("primal", "dual"):
            f = GramFactor(rows, gamma, w, form=form)
            tol = 1e-9 * np.abs(m_true).max() + 1e-300
            np.testing.assert_allclose(f.regress(y), m_true @ y,
                                       atol=1e-9 * np.abs(m_true @ y).max() + tol)
            np.testing.assert_allclose(f.matrix(), m_true, atol=tol)
            np.testing.assert_allclose(f.inverse_diagonal(), np.diag(inv), rtol=1e-9,
                                       atol=1e-12 / gamma)
            for xs in (x, sp.csr_matrix(x)):
                norms = engine.elliptical_norms(xs, f.elliptical_factor())
                np.testing.assert_allclose(norms**2, ell_true, rtol=1e-9,
                                           atol=1e-12 * (x * x).sum() / gamma)
            b = rng.standard_normal((d, 2))
            np.testing.assert_allclose(f.solve(b), inv @ b, rtol=1e-9,
                                       atol=1e-9 * np.abs(inv @ b).max())


def test_form_is_chosen_from_the_shapes():
    assert choose_form(300, 1152) == "dual" and choose_form(10_000, 30) == "primal"
    assert choose_form(1000, 1152) == "dual" and choose_form(1152, 1152) == "primal"
    assert choose_form(1000, 20_000, sparse=True) == "dual"
    assert GramFactor(np.ones((3, 8)), 1.0).form == "dual"
    assert GramFactor(np.ones((8, 3)), 1.0).form == "primal"
    with pytest.raises(ValueError, match="form must be one of"):
        GramFactor(np.ones((3, 3)), 1.0, form="kernel")


def test_sparse_rows_factor_the_used_features_only():
    """Tile-coding-like rows (d = 2000, a few non-zeros per row from a few used features):
    "auto" takes the primal form on the used features (a |U| x |U| factor) when |U| <= n;
    every quantity equals the dual form's, also restricted to the used features plus
    representatives of the unused ones (the engine's path)."""
    rng = np.random.default_rng(21)
    n, d = 40, 2000
    pool = rng.choice(d, size=25, replace=False)
    cols = pool[rng.integers(0, 25, size=(n, 3))]
    rows = sp.csr_matrix((rng.uniform(0.1, 1.0, 3 * n), (np.repeat(np.arange(n), 3),
                                                           cols.ravel())), shape=(n, d))
    w = rng.uniform(0.5, 2.0, n)
    used = np.unique(cols)
    primal, dual = GramFactor(rows, 0.7, w), GramFactor(rows, 0.7, w, form="dual")
    assert primal.form == "primal" and primal.chol.shape == (used.size, used.size)
    assert GramFactor(rows[:5], 0.7).form == "dual"  # 5 rows use more than 5 features
    reps = np.setdiff1d(np.arange(d), used)[:2]
    y, b = rng.standard_normal((n, 2)), rng.standard_normal(d)
    x = rng.standard_normal((4, d)) * (rng.random((4, d)) < 0.05)
    x[:, used[:3]] = 1.0
    x = sp.csr_matrix(x)
    keep = np.r_[used, reps]
    for f, g in ((primal, dual), (primal.restrict(keep), dual.restrict(keep))):
        np.testing.assert_allclose(f.regress(y), g.regress(y), atol=1e-12)
        np.testing.assert_allclose(f.matrix(), g.matrix(), atol=1e-12)
        np.testing.assert_allclose(f.inverse_diagonal(), g.inverse_diagonal(), atol=1e-12)
    np.testing.assert_allclose(primal.solve(b), dual.solve(b), atol=1e-12)
    np.testing.assert_allclose(engine.elliptical_norms(x, primal.elliptical_factor()),
                               engine.elliptical_norms(x, dual.elliptical_factor()), atol=1e-12)
    with pytest.raises(ValueError, match="every used feature"):
        primal.restrict(used[1:])


def test_sparse_column_quadratic():
    rng = np.random.default_rng(3)
    psi = sp.random(30, 50, density=0.2, random_state=4, format="csr")
    dense = psi.toarray()
    dense[:, 7] = 1.0  # a column with every row: 900 pairs
    psi = sp.csr_matrix(dense)
    a = rng.standard_normal((30, 30))
    ginv = a @ a.T
    dense = psi.toarray()
    expected = np.einsum("kj,kl,lj->j", dense, ginv, dense)
    dense[:, 3] = 0.0  # an unused column
    expected = np.einsum("kj,kl,lj->j", dense, ginv, dense)
    np.testing.assert_allclose(_sparse_column_quadratic(sp.csr_matrix(dense), ginv), expected,
                               rtol=1e-12, atol=1e-12)


# ----------------------------------------------------------------------------- estimators


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
@pytest.mark.parametrize("K,d", [(12, 30), (40, 6)])  # d > K and d < K
def test_dual_primal_sparse_fits_are_the_same_numbers(name, K, d):
    rng = np.random.default_rng(K + d)
    phi, rewards, next_phi = _data(rng, K, 3, d)
    dense, sparse = _both(phi, rewards, next_phi)
    ref = _fit(ESTIMATORS[name], dense, "primal")
    feat = _sparse_simplex(rng, (5, 2, d))
    for ds, form in ((dense, "dual"), (sparse, "primal"), (sparse, "dual"), (sparse, "auto")):
        est = _fit(ESTIMATORS[name], ds, form)
        np.testing.assert_allclose(est.weights_, ref.weights_, atol=1e-9, rtol=1e-9)
        np.testing.assert_allclose(est.gram_inv_diag_, ref.gram_inv_diag_, rtol=1e-9)
        for h in range(3):
            np.testing.assert_allclose(est.q_values(feat, h), ref.q_values(feat, h), atol=1e-9)


def test_sparse_dataset_keeps_known_values_and_subsets():
    rng = np.random.default_rng(5)
    phi, rewards, next_phi = _data(rng, 20, 3, 25)
    nv = np.full((20, 3, 2), np.nan)
    nv[::3, :, 1] = 0.0  # absorbing fail states
    dense, sparse = _both(phi, rewards, next_phi, nv)
    idx = np.array([0, 3, 4, 9, 11, 17])
    a = R2PVI("tv", 0.5, beta=0.1).fit(dense.subset(idx))
    b = R2PVI("tv", 0.5, beta=0.1).fit(sparse.subset(idx))
    np.testing.assert_allclose(a.weights_, b.weights_, atol=1e-10)
    assert "nnz" in repr(sparse)
    with pytest.raises(TypeError, match="no dense phi"):
        sparse.phi  # noqa: B018
    with pytest.raises(TypeError, match="not supported"):
        sparse.save("x.npz")
    with pytest.raises(ValueError, match="one sparse matrix per step"):
        SparseOfflineDataset.from_rows([sp.csr_matrix(phi[:, 0])], rewards, [], 2)
    with pytest.raises(TypeError, match="scipy.sparse"):
        SparseOfflineDataset.from_rows([phi[:, h] for h in range(3)], rewards,
                                       [phi[:, h] for h in range(3)], 2)


def test_sparse_from_transitions_feature_map():
    """A feature map returning sparse one-hot rows gives the dense map's fit."""
    rng = np.random.default_rng(6)
    K, H, S, A = 30, 3, 7, 2
    s, a = rng.integers(0, S, (K, H)), rng.integers(0, A, (K, H))
    ns, r = rng.integers(0, S, (K, H)), rng.random((K, H))
    eye = np.eye(S * A)

    def sparse_map(states, actions):
        idx = states * A + actions
        return sp.csr_matrix((np.ones(idx.size), (np.arange(idx.size), idx)), (idx.size, S * A))

    dense = OfflineDataset.from_transitions(s, a, r, ns, lambda x, u: eye[x * A + u], A)
    sparse = SparseOfflineDataset.from_transitions(s, a, r, ns, sparse_map, A)
    for make in (lambda: R2PVI("chi2", 0.4, beta=0.1), lambda: PEVI(beta=0.1)):
        np.testing.assert_allclose(make().fit(sparse).weights_, make().fit(dense).weights_,
                                   atol=1e-10)


def test_sparse_rows_reach_the_operator_without_densifying(monkeypatch):
    """The engine hands CSR rows to the factor and the duals (no dense (K, d) copy)."""
    rng = np.random.default_rng(7)
    _, sparse = _both(*_data(rng, 10, 2, 40))
    seen = []
    real = engine.steps.GramFactor

    def spy(phi, *args, **kwargs):
        seen.append(sp.issparse(phi))
        return real(phi, *args, **kwargs)

    monkeypatch.setattr(engine.steps, "GramFactor", spy)
    DRPVI(0.3).fit(sparse)
    assert seen and all(seen)
    _, _, nxt, _ = sparse.step(0)
    assert isinstance(nxt, StackedSparse) and nxt.shape == (10, 2, 40)


# ----------------------------------------------------------------------------- acting


@pytest.mark.parametrize("form", ["primal", "dual"])
def test_acting_factors_nothing(monkeypatch, form):
    """q_values/act after fit: the elliptical norm comes from the fitted factor; every
    factorization or inverse routine is disabled while acting."""
    rng = np.random.default_rng(8)
    phi, rewards, next_phi = _data(rng, 25, 3, 40)
    ds = OfflineDataset.from_features(phi, rewards, next_phi)
    est = _fit(lambda: PEVI(beta=0.5), ds, form)
    feat = _sparse_simplex(rng, (6, 2, 40))
    inv = _lam_inv(phi[:, 1], 1.0)
    expected = np.clip(feat @ est.weights_[1]
                       - 0.5 * np.sqrt(np.einsum("sad,de,sae->sa", feat, inv, feat)), 0, 2)

    def forbidden(*args, **kwargs):
        raise AssertionError("acting must not factor or invert a matrix")

    import scipy.linalg

    for mod, name in ((np.linalg, "cholesky"), (np.linalg, "solve"), (np.linalg, "inv"),
                      (scipy.linalg.lapack, "dtrtri"), (scipy.linalg, "solve_triangular")):
        monkeypatch.setattr(mod, name, forbidden)
    np.testing.assert_allclose(est.q_values(feat, 1), expected, atol=1e-10)
    assert est.act(feat, 1).shape == (6,)


def test_elliptical_factors_save_load_and_old_format(tmp_path):
    rng = np.random.default_rng(9)
    phi, rewards, next_phi = _data(rng, 15, 3, 20)
    ds = OfflineDataset.from_features(phi, rewards, next_phi)
    feat = _sparse_simplex(rng, (4, 2, 20))
    for th in (False, True):
        est = PEVI(beta=0.3, time_homogeneous=th).fit(ds)
        back = load(est.save(tmp_path / f"m{th}"))
        for h in range(3):
            np.testing.assert_array_equal(back.q_values(feat, h), est.q_values(feat, h))
    # A version-1 file stored the (H, d, d) Cholesky factors.
    est = PEVI(beta=0.3).fit(ds)
    chol = np.stack([np.linalg.cholesky(np.linalg.inv(_lam_inv(phi[:, h], 1.0)))
                     for h in range(3)])
    params, arrays = est._params_to_json()
    arrays.update(weights_=est.weights_, reward_weights_=est.reward_weights_,
                  gram_cholesky_=chol, gram_inv_diag_=est.gram_inv_diag_)
    meta = {"estimator": "PEVI", "params": params, "fit_params": est._fit_params, "n_actions": 2}
    old = load(save_npz(tmp_path / "v1.npz", "estimator", 1, arrays, meta))
    np.testing.assert_allclose(old.q_values(feat, 1), est.q_values(feat, 1), atol=1e-12)
    # Sparse rows (version 3): R = C^-1 Psi saved as its two factors, Psi in CSR pieces.
    # Sparse rows (version 3): R = C^-1 Psi saved as its two factors, Psi in CSR pieces
    # (dual form, d > K); L_U^-1 on the used features U (primal form, |U| <= K).
    rng2 = np.random.default_rng(10)
    for K, d, stored in ((10, 30, "elliptical_cinv"), (30, 8, "elliptical_linv_data")):
        _, sparse = _both(*_data(rng2, K, 2, d))
        feat = _sparse_simplex(rng2, (4, 2, d))
        for th in (False, True):
            est = PEVI(beta=0.3, time_homogeneous=th).fit(sparse)
            path = est.save(tmp_path / f"s{th}{d}")
            with np.load(path, allow_pickle=False) as npz:
                assert "elliptical_r" not in npz.files and stored in npz.files
            back = load(path)
            for h in range(2):
                np.testing.assert_array_equal(back.q_values(feat, h), est.q_values(feat, h))


def test_elliptical_models_with_mixed_factor_kinds_save_and_load(tmp_path):
    """Sparse rows whose steps take different forms (dual where the rows use more features
    than there are rows, the used-feature primal on steps without data) save and load."""
    from r2pvi.features import TileCoding, cross_actions

    rng = np.random.default_rng(19)
    eps = [{"observations": rng.random((3, 2)), "actions": [0, 1], "rewards": [1.0, 0.5],
            "terminations": [False, True], "truncations": [False, False]} for _ in range(4)]
    obs = np.concatenate([e["observations"] for e in eps])
    fmap = cross_actions(TileCoding(n_tilings=2, n_tiles=3, sparse=True).fit(obs), 2)
    ds = OfflineDataset.from_episodes(eps, fmap, 2, horizon=4)  # steps 2-3: no data
    est = PEVI(beta=0.1, time_homogeneous=False).fit(ds)  # per step: mixed kinds
    path = est.save(tmp_path / "mixed")
    with np.load(path, allow_pickle=False) as npz:
        assert {"elliptical_cinv", "elliptical_sizes"} <= set(npz.files)
    back = load(path)
    feat = fmap.all_actions(rng.random((5, 2)))
    for h in range(4):
        np.testing.assert_array_equal(back.q_values(feat, h), est.q_values(feat, h))


def test_tampered_sparse_elliptical_factors_are_named(tmp_path):
    _, sparse = _both(*_data(np.random.default_rng(17), 10, 2, 30))
    good = PEVI(beta=0.3).fit(sparse).save(tmp_path / "good")
    with np.load(good, allow_pickle=False) as npz:
        ptr = npz["elliptical_psi_indptr"]
    _assert_tampering_is_named(good, tmp_path, (
        ("elliptical_psi_indices",
         lambda a, m: a.update(elliptical_psi_indices=a["elliptical_psi_indices"] + 30)),
        ("elliptical_psi_indptr", lambda a, m: a.update(elliptical_psi_indptr=ptr[:, ::-1].copy())),
        ("elliptical_psi_indptr", lambda a, m: a.update(elliptical_psi_indptr=ptr.astype(float))),
        ("elliptical_cinv", lambda a, m: a.update(elliptical_cinv=np.ones((2, 3, 4)))),
        ("elliptical_kinds", lambda a, m: m.update(elliptical_kinds=["csc"] * 2)),
        # sparse factors declared dense: the dense arrays they would need are missing
        ("elliptical_r", lambda a, m: m.update(elliptical_kinds=["dense", "dense"]))))
    rng = np.random.default_rng(18)
    phi, rewards, next_phi = _data(rng, 30, 2, 8)
    phi[..., 3] = next_phi[..., 3] = 0.0  # an unused feature (rows renormalized)
    phi[..., 0] += 1e-3
    next_phi[..., 0] += 1e-3
    phi /= phi.sum(axis=-1, keepdims=True)
    next_phi /= next_phi.sum(axis=-1, keepdims=True)
    _, sparse = _both(phi, rewards, next_phi)
    good = PEVI(beta=0.3).fit(sparse).save(tmp_path / "used")
    with np.load(good, allow_pickle=False) as npz:
        cols, sizes = npz["elliptical_cols"], npz["elliptical_sizes"]
    _assert_tampering_is_named(good, tmp_path, (
        ("elliptical_cols", lambda a, m: a.update(elliptical_cols=cols[::-1].copy())),
        ("elliptical_sizes", lambda a, m: a.update(elliptical_sizes=sizes + 1)),
        ("elliptical_linv_data", lambda a, m: a.update(elliptical_linv_data=np.ones(3))),
        ("elliptical_c", lambda a, m: a.update(elliptical_c=-a["elliptical_c"]))))


def _assert_tampering_is_named(good, tmp_path, changes):
    """Each ``(field, change(arrays, meta))`` applied to a copy of the model file ``good``
    makes load raise a ValueError naming ``field``."""
    import json

    with np.load(good, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    meta = json.loads(str(arrays.pop("__r2pvi_meta__")))
    for i, (field, change) in enumerate(changes):
        a, m = dict(arrays), json.loads(json.dumps(meta))
        change(a, m)
        kind, version = m.pop("kind"), m.pop("format_version")
        bad = save_npz(tmp_path / f"bad{i}.npz", kind, version, a, m)  # not named after field
        with pytest.raises(ValueError, match=field):
            load(bad)


# ----------------------------------------------------------------------------- pooled steps


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
def test_pooled_equals_per_step_when_H_is_1(name):
    rng = np.random.default_rng(11)
    ds = OfflineDataset.from_features(*_data(rng, 30, 1, 5))
    a = _fit(ESTIMATORS[name], ds)
    b = _fit(ESTIMATORS[name], ds, time_homogeneous=True)
    np.testing.assert_array_equal(a.weights_, b.weights_)


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
def test_pooled_equals_per_step_when_every_step_sees_the_same_transitions(name):
    """H copies of the same K transitions: pooled fits use steps 0 .. H-2 (P = H - 1 copies;
    the last step's next states are not data), so the pooled Gram matrix is ``P (Phi^T Phi +
    gamma/P I)`` and pooled (gamma, beta) is the per-step estimator with (gamma / P,
    beta / sqrt(P)) — weights, penalties and Q-values (ties in every sorted dual)."""
    rng = np.random.default_rng(12)
    K, H, d = 25, 4, 6
    P = engine.pooled_steps(H)
    phi1, r1, next1 = _data(rng, K, 1, d)
    phi, rewards, next_phi = (np.repeat(x, H, axis=1) for x in (phi1, r1, next1))
    ds = OfflineDataset.from_features(phi, rewards, next_phi)
    # DRVI-L's b_min="auto" depends on the number of samples (P K pooled, K per step): fix it
    extra = {"b_min": 0.05} if name == "drvil" else {}
    pooled = _fit(ESTIMATORS[name], ds, gamma=0.8, time_homogeneous=True, **extra)
    per_step = _fit(ESTIMATORS[name], ds, gamma=0.8 / P, beta=0.2 / np.sqrt(P), **extra)
    np.testing.assert_allclose(pooled.weights_, per_step.weights_, atol=1e-10)
    np.testing.assert_allclose(pooled.gram_inv_diag_ * P, per_step.gram_inv_diag_, rtol=1e-10)
    feat = _sparse_simplex(rng, (5, 2, d))
    for h in range(H):
        np.testing.assert_allclose(pooled.q_values(feat, h), per_step.q_values(feat, h),
                                   atol=1e-10)


def test_pooled_factors_one_gram_matrix(monkeypatch):
    rng = np.random.default_rng(13)
    ds = OfflineDataset.from_features(*_data(rng, 20, 5, 8))
    calls = []
    real = engine.steps.GramFactor

    def count(phi, *args, **kwargs):
        calls.append(phi.shape)
        return real(phi, *args, **kwargs)

    monkeypatch.setattr(engine.steps, "GramFactor", count)
    DRPVI(0.2).set_params(time_homogeneous=True).fit(ds)
    assert calls == [(80, 8)]  # one factorization of the (H - 1) K = 80 pooled transitions
    calls.clear()
    real_primal = engine.steps._primal_factor  # per-step fits accumulate Lambda_h by chunk

    def count_primal(gram, gamma, weights, shape):
        calls.append(tuple(shape))
        return real_primal(gram, gamma, weights, shape)

    monkeypatch.setattr(engine.steps, "_primal_factor", count_primal)
    monkeypatch.setattr(engine.steps, "GramFactor", real)
    DRPVI(0.2).fit(ds)
    assert calls == [(20, 8)] * 5
    with pytest.raises(TypeError, match="time_homogeneous"):
        PEVI(time_homogeneous="yes").fit(ds)


def test_pooled_ridge_matches_a_brute_force_pooled_regression():
    """PEVI with beta = 0 and pooled steps: w_h is the ridge regression, over the (H - 1) K
    transitions of steps 0 .. H-2, of V_{h+1} at their next states (brute force, no engine).
    The last step's next states are not data: NaN there changes nothing."""
    rng = np.random.default_rng(14)
    K, H, d, A = 15, 3, 4, 2
    phi, rewards, next_phi = _data(rng, K, H, d, A)
    next_phi[:, H - 1] = np.nan  # "ignored and may hold anything" (from_features)
    ds = OfflineDataset.from_features(phi, rewards, next_phi)
    est = PEVI(beta=0.0, gamma=0.5, time_homogeneous=True).fit(ds)
    x = phi[:, :H - 1].transpose(1, 0, 2).reshape(-1, d)
    nx = next_phi[:, :H - 1].transpose(1, 0, 2, 3).reshape(-1, A, d)
    inv = _lam_inv(x, 0.5)
    theta = inv @ x.T @ rewards[:, :H - 1].T.reshape(-1)
    w = theta.copy()
    expected = [None] * H
    expected[H - 1] = theta
    for h in range(H - 2, -1, -1):
        v = np.clip(nx @ w, 0, H - h - 1).max(axis=1)
        w = theta + inv @ x.T @ v
        expected[h] = w
    np.testing.assert_allclose(est.weights_, np.array(expected), atol=1e-12)


def test_duals_on_factor_operators_unchanged():
    """The exact path (FactorExpectation) is untouched by the ridge changes."""
    E = FactorExpectation(np.array([[0.5, 0.5, 0.0]]))
    assert tv_constrained(E, np.array([1.0, 3.0, 0.0]), rho=0.25)[0] == 1.25
    phi = np.random.default_rng(0).random((5, 9))
    E2 = RidgeExpectation(phi, GramFactor(phi, 1.0))
    assert E2.factor.form == "dual" and not E2.primal_dense
    with pytest.raises(AttributeError, match="primal form only"):
        E2.chol_inverse  # noqa: B018


@pytest.mark.parametrize("name", ["tv", "kl", "chi2", "drpvi", "drvil", "va-drpvi", "pevi"])
def test_unused_sparse_features_are_reduced_exactly(name):
    """Each step's rows use 8 of 60 features; the rule runs on the used features plus one
    representative per distinct radius; the numbers match the dense primal fit."""
    rng = np.random.default_rng(15)
    K, H, d = 20, 3, 60
    phi, rewards, next_phi = _data(rng, K, H, d)
    for h in range(H):
        mask = np.zeros(d, bool)
        mask[rng.choice(d, 8, replace=False)] = True
        phi[:, h, ~mask] = 0.0
        phi[:, h, mask] += 1e-3
        phi[:, h] /= phi[:, h].sum(axis=1, keepdims=True)
    dense, sparse = _both(phi, rewards, next_phi)
    rho = rng.choice([0.0, 0.1, 0.3], size=(H, d))
    makers = dict(ESTIMATORS, drpvi=lambda: DRPVI(rho, beta=0.2),
                  drvil=lambda: DRVIL(rho, beta=0.2))
    seen = []
    est = _fit(makers[name], sparse, "auto")
    ref = _fit(makers[name], dense, "primal")
    np.testing.assert_allclose(est.weights_, ref.weights_, atol=1e-9, rtol=1e-9)
    rule = makers[name]()._make_rule({**makers[name]()._validate_extra(sparse), "r_max": 1.0,
                                      "beta": 0.2})
    real_call = type(rule).__call__

    def spy(self, E, v, ctx):
        seen.append(E.n_dims)
        return real_call(self, E, v, ctx)

    type(rule).__call__ = spy
    try:
        engine.backward_induction(sparse, rule, beta=0.2, gamma=1.0, penalty="l1", r_max=1.0)
    finally:
        type(rule).__call__ = real_call
    assert seen and max(seen) <= 8 + 3


def test_tampered_elliptical_factors_are_named(tmp_path):
    rng = np.random.default_rng(16)
    ds = OfflineDataset.from_features(*_data(rng, 10, 2, 5))
    good = PEVI(beta=0.3).fit(ds).save(tmp_path / "good")
    _assert_tampering_is_named(good, tmp_path, (
        ("elliptical_index", lambda a, m: m.update(elliptical_index=[0, 5])),
        ("elliptical_r", lambda a, m: a.update(elliptical_r=np.ones((2, 3))))))


def _ragged_episodes(rng, n, horizon, n_actions, obs_dim=2):
    """Episodes of 1..horizon+1 steps, terminated, truncated or cut at the horizon."""
    eps = []
    for k in range(n):
        T = int(rng.integers(1, horizon + 2))
        eps.append({"observations": rng.uniform(-1, 1, (T + 1, obs_dim)),
                    "actions": rng.integers(0, n_actions, T), "rewards": rng.random(T),
                    "terminations": np.r_[np.zeros(T - 1, bool), [k % 3 == 0]],
                    "truncations": np.r_[np.zeros(T - 1, bool), [k % 3 == 1]]})
    return eps


def test_sparse_feature_maps_give_sparse_episode_datasets():
    """from_episodes with a sparse tile coding: the dense dataset's every array and fit,
    with no row densified (an OfflineDataset of sparse rows)."""
    from r2pvi.features import TileCoding, cross_actions

    rng = np.random.default_rng(3)
    H, A = 6, 3
    eps = _ragged_episodes(rng, 25, H, A)
    obs = np.concatenate([e["observations"] for e in eps])
    maps = [cross_actions(TileCoding(n_tilings=4, n_tiles=4, sparse=s).fit(obs), A)
            for s in (False, True)]
    dense, sparse = (OfflineDataset.from_episodes(eps, m, A, horizon=H) for m in maps)
    assert type(sparse) is type(dense) is OfflineDataset
    assert sparse.storage == "memory (sparse rows)" and dense.storage == "memory"
    for h in range(H):
        a, b = dense.step(h), sparse.step(h)
        assert sp.issparse(b[0]) and isinstance(b[2], StackedSparse)
        np.testing.assert_array_equal(a[0], b[0].toarray())
        np.testing.assert_array_equal(a[1], b[1])
        np.testing.assert_array_equal(a[2], b[2].matrix.toarray().reshape(a[2].shape))
        if h < H - 1:
            np.testing.assert_array_equal(a[3], b[3])
    for est in (R2PVI("tv", 0.3, beta=0.05), PEVI(beta=0.1), DRPVI(0.2, beta=0.05)):
        w_dense = est.fit(dense).weights_.copy()
        np.testing.assert_allclose(est.fit(sparse).weights_, w_dense, rtol=0, atol=1e-10)


@pytest.mark.parametrize("name", ["pevi", "tv", "drvil"])
def test_pooled_fits_ignore_the_last_steps_next_states(name, tmp_path):
    """Row H-1 of the next-state data "is ignored and may hold anything" (from_features), so
    pooled fits must not use it: memory with NaN there, memory with other values and the
    saved dataset (which stores zeros) give the same, finite fit."""
    rng = np.random.default_rng(21)
    K, H, d = 12, 3, 4
    phi, rewards, next_phi = _data(rng, K, H, d)
    a, b = next_phi.copy(), next_phi.copy()
    a[:, H - 1] = np.nan
    b[:, H - 1] = rng.random(b[:, H - 1].shape)
    fits = [_fit(ESTIMATORS[name], OfflineDataset.from_features(phi, rewards, x),
                 time_homogeneous=True) for x in (a, b)]
    path = OfflineDataset.from_features(phi, rewards, a).save(tmp_path / "ds")
    fits.append(_fit(ESTIMATORS[name], OfflineDataset.open(path), time_homogeneous=True))
    assert np.all(np.isfinite(fits[0].weights_))
    for other in fits[1:]:
        np.testing.assert_allclose(other.weights_, fits[0].weights_, rtol=0, atol=1e-12)
