"""PEVI and R2PVI: hand-computed weights, exact robust weights, conventions, errors, I/O."""

import numpy as np
import pytest
from helpers import D, linear_data
from primal import chi2_primal, smooth_primal, tv_primal
from scipy.special import xlogy

from r2pvi import PEVI, R2PVI, FDivergence, NotFittedError, OfflineDataset, cressie_read, load
from r2pvi.duals import (
    CHI2,
    KL,
    TV,
    FactorExpectation,
    chi2_regularized,
    kl_regularized,
    tv_regularized,
)

# --------------------------------------------------------------------------- hand-computed


def hand_dataset():
    """H = 2, d = 2, one-hot features. At step 0, four samples with phi = e1 reach next
    states X, X, X, Y and two with phi = e2 reach Y, Y. At X the two actions have features
    e1 (value theta_1 . e1 = 1) and e2 (value 0), so V(X) = 1; at Y both have e2, V(Y) = 0."""
    e1, e2 = np.eye(2)
    X, Y = np.stack([e1, e2]), np.stack([e2, e2])
    phi = np.array([[e1, e1]] * 4 + [[e2, e2]] * 2)  # (K=6, H=2, d)
    next_phi = np.array([[X, X], [X, X], [X, X], [Y, Y], [Y, Y], [Y, Y]])  # (6, 2, A=2, 2)
    rewards = np.zeros((6, 2))
    theta = np.array([[0.0, 0.0], [1.0, 0.0]])
    return OfflineDataset.from_features(phi, rewards, next_phi), theta


@pytest.mark.parametrize(
    "est, w0",
    [
        # PEVI: sample means of V' = [1, 1, 1, 0] and [0, 0].
        (PEVI(beta=0.0, gamma=1e-12), [0.75, 0.0]),
        # TV, lam = 0.5: alpha = min V' + lam = 0.5; mean of min(V', 0.5) = 0.375.
        (R2PVI("tv", 0.5, beta=0.0, gamma=1e-12), [0.375, 0.0]),
        # TV with a known lower bound V_min = 0.2: alpha = 0.7, mean = 0.525.
        (R2PVI("tv", 0.5, beta=0.0, gamma=1e-12, v_min=0.2), [0.525, 0.0]),
        # KL, lam = 1: -log(0.75 e^-1 + 0.25).
        (R2PVI("kl", 1.0, beta=0.0, gamma=1e-12), [-np.log(0.75 / np.e + 0.25), 0.0]),
        # chi^2, lam = 1: max over alpha in [0,1] of .75 alpha - .1875 alpha^2 / 4 -> alpha = 1.
        (R2PVI("chi2", 1.0, beta=0.0, gamma=1e-12), [0.75 - 0.1875 / 4, 0.0]),
    ],
)
def test_hand_computed_weights(est, w0):
    ds, theta = hand_dataset()
    est.set_params(reward_weights=theta).fit(ds)
    np.testing.assert_allclose(est.weights_[0], w0, atol=1e-9)
    np.testing.assert_array_equal(est.weights_[1], theta[1])  # V_H = 0: exactly theta
    # Q_0 at the start state e1 and at e2
    q = est.q_values(np.array([[[1.0, 0.0], [0.0, 1.0]]]), 0)
    np.testing.assert_allclose(q[0], w0, atol=1e-9)


@pytest.mark.parametrize("div", ["tv", "kl", "chi2", "hellinger", TV, KL])
def test_last_step_is_exactly_the_reward_for_every_divergence(div):
    ds, theta = hand_dataset()
    est = R2PVI(div, 0.3, reward_weights=theta).fit(ds)
    np.testing.assert_array_equal(est.weights_[-1], theta[-1])


# --------------------------------------------------------------------------- exact weights


def tabular_exact_count_dataset(seed=0, S=3, A=2, H=3, per_pair=10):
    """A tabular MDP with one-hot features (d = S A) and transition probabilities in tenths;
    every (h, s, a) appears per_pair times with next states in exactly those proportions."""
    rng = np.random.default_rng(seed)
    d = S * A
    feat = np.eye(d).reshape(S, A, d)
    counts = rng.multinomial(10, np.ones(S) / S, size=(H, S, A))
    counts[..., 0] += (counts.sum(axis=-1) == 0)  # at least one state per pair
    probs = counts / counts.sum(axis=-1, keepdims=True)
    theta = rng.uniform(0, 1, size=(H, d))
    rows = []
    for s in range(S):
        for a in range(A):
            for h in range(H):
                for s_next in range(S):
                    rows += [(s, a, s_next)] * int(round(probs[h, s, a, s_next] * 10 * per_pair))
    # one "trajectory" per (s, a) sample index: step h uses the h-th block
    n = min(sum(1 for r in rows if r[:2] == (s, a)) // H for s in range(S) for a in range(A))
    phi, nphi = [], []
    for s in range(S):
        for a in range(A):
            blocks = [[r for r in rows if r[:2] == (s, a)][h * n : (h + 1) * n] for h in range(H)]
            for j in range(n):
                phi.append([feat[s, a]] * H)
                nphi.append([feat[blocks[h][j][2]] for h in range(H)])
    phi, nphi = np.array(phi), np.array(nphi)
    rewards = np.einsum("khd,hd->kh", phi, theta)
    mu = np.transpose(probs.reshape(H, d, S), (0, 1, 2))  # factor (s, a) -> next-state law
    return OfflineDataset.from_features(phi, rewards, nphi), feat, theta, mu


def brute_force_robust_weights(mu, theta, feat, lam, divergence):
    """Backward induction with every factor's inf solved by a brute-force primal."""
    H, d, S = mu.shape
    primal = {
        "tv": tv_primal,
        "chi2": chi2_primal,
        "kl": lambda v, m0, lam: smooth_primal(v, m0, lam, lambda t: xlogy(t, t)),
    }[divergence]
    weights = np.zeros((H, d))
    v_next = np.zeros(S)
    for h in range(H - 1, -1, -1):
        w = np.zeros(d) if h == H - 1 else np.array([primal(v_next, mu[h, i], lam)
                                                      for i in range(d)])
        weights[h] = theta[h] + w
        v_next = (feat @ weights[h]).max(axis=1)
    return weights


@pytest.mark.parametrize("divergence", ["tv", "kl", "chi2"])
@pytest.mark.parametrize("lam", [0.2, 1.5])
def test_exact_count_data_recovers_brute_force_robust_weights(divergence, lam):
    ds, feat, theta, mu = tabular_exact_count_dataset()
    est = R2PVI(divergence, lam, beta=0.0, gamma=1e-10, reward_weights=theta, r_max=1.0)
    est.fit(ds)
    truth = brute_force_robust_weights(mu, theta, feat, lam, divergence)
    np.testing.assert_allclose(est.weights_, truth, atol=2e-6)


def linear_mdp(seed=1, S=5, A=2, d=3, H=3):
    rng = np.random.default_rng(seed)
    feat = rng.dirichlet(np.ones(d), size=(S, A))
    mu = rng.dirichlet(np.ones(S), size=(H, d))
    theta = rng.uniform(0, 1, size=(H, d))
    return feat, mu, theta


def sample(feat, mu, theta, K, seed):
    rng = np.random.default_rng(seed)
    S, A, d = feat.shape
    H = mu.shape[0]
    s = rng.integers(S, size=K)
    phi, nphi = np.zeros((K, H, d)), np.zeros((K, H, A, d))
    for h in range(H):
        a = rng.integers(A, size=K)
        phi[:, h] = feat[s, a]
        p = phi[:, h] @ mu[h]
        s = (p.cumsum(axis=1) > rng.random((K, 1))).argmax(axis=1)
        nphi[:, h] = feat[s]
    return OfflineDataset.from_features(phi, np.einsum("khd,hd->kh", phi, theta), nphi)


def exact_robust_weights(feat, mu, theta, dual):
    H, d, S = mu.shape
    weights, v_next = np.zeros((H, d)), np.zeros(S)
    for h in range(H - 1, -1, -1):
        w = np.zeros(d) if h == H - 1 else dual(FactorExpectation(mu[h]), v_next)
        weights[h] = theta[h] + w
        v_next = np.clip(feat @ weights[h], 0, H - h).max(axis=1)
    return weights


@pytest.mark.parametrize(
    "divergence, dual",
    [
        ("tv", lambda E, v: tv_regularized(E, v, 0.5)),
        ("kl", lambda E, v: kl_regularized(E, v, 0.5)),
        ("chi2", lambda E, v: chi2_regularized(E, v, 0.5)),
    ],
)
def test_large_sample_converges_to_exact_robust_weights(divergence, dual):
    feat, mu, theta = linear_mdp()
    truth = exact_robust_weights(feat, mu, theta, dual)
    errors = []
    for K in (1_000, 30_000):
        est = R2PVI(divergence, 0.5, beta=0.0, gamma=1.0, reward_weights=theta)
        est.fit(sample(feat, mu, theta, K, seed=K))
        errors.append(np.abs(est.weights_ - truth).max())
    assert errors[1] < 0.03
    assert errors[1] < errors[0]


# --------------------------------------------------------------------------- conventions


def small_dataset(K=60, seed=0):
    feat, mu, theta = linear_mdp()
    return sample(feat, mu, theta, K, seed), feat, theta


def test_init_only_stores_parameters_and_fit_validates():
    est = R2PVI("nope", -1.0)  # no error yet: sklearn convention
    assert est.get_params()["lam"] == -1.0
    ds, _, _ = small_dataset()
    with pytest.raises(ValueError, match="lam must be > 0"):
        est.fit(ds)


@pytest.mark.parametrize(
    "params, err, match",
    [
        ({"lam": 0.0}, ValueError, "lam must be > 0"),
        ({"gamma": 0.0}, ValueError, "gamma must be > 0"),
        ({"beta": -1.0}, ValueError, "beta must be >= 0"),
        ({"r_max": 0}, ValueError, "r_max"),
        ({"penalty": "l3"}, ValueError, "penalty must be one of"),
        ({"v_min": "min"}, ValueError, "v_min must be 'data' or a number"),
        ({"v_min": [0.0]}, TypeError, "v_min"),
        ({"divergence": "wasserstein"}, ValueError, "unknown divergence"),
        ({"divergence": 3}, TypeError, "divergence must be"),
        ({"lam": "1"}, TypeError, "lam must be a real number"),
        ({"reward_weights": np.zeros((2, 3))}, ValueError, r"reward_weights must have shape"),
    ],
)
def test_fit_rejects_bad_parameters(params, err, match):
    ds, _, _ = small_dataset()
    with pytest.raises(err, match=match):
        R2PVI(**params).fit(ds)


def test_fit_returns_self_and_rejects_non_datasets():
    ds, _, theta = small_dataset()
    est = R2PVI(reward_weights=theta)
    assert est.fit(ds) is est
    with pytest.raises(TypeError, match="OfflineDataset"):
        est.fit(np.zeros((3, 3)))


def test_get_set_params_and_clone():
    est = R2PVI("kl", 0.3, beta=0.2)
    params = est.get_params()
    assert params == {"divergence": "kl", "lam": 0.3, "beta": 0.2, "gamma": 1.0,
                      "penalty": "l1", "v_min": "data", "reward_weights": None, "r_max": 1.0,
                      "variance_aware": False, "delta": 0.05, "kl_form": "normalized",
                      "time_homogeneous": "auto", "moments": "valid"}
    clone = type(est)(**params)
    assert clone.get_params() == params
    assert est.set_params(lam=2.0) is est and est.lam == 2.0
    with pytest.raises(ValueError, match="invalid parameter"):
        est.set_params(alpha=1)
    assert repr(est) == "R2PVI(divergence='kl', lam=2.0, beta=0.2)"


def test_fit_is_deterministic_and_does_not_mutate_the_dataset():
    ds, _, theta = small_dataset()
    before = ds.phi.copy(), ds.next_phi.copy(), ds.rewards.copy()
    a = R2PVI("chi2", 0.4, reward_weights=theta).fit(ds).weights_
    b = R2PVI("chi2", 0.4, reward_weights=theta).fit(ds).weights_
    np.testing.assert_array_equal(a, b)
    for x, y in zip(before, (ds.phi, ds.next_phi, ds.rewards), strict=True):
        np.testing.assert_array_equal(x, y)


def test_reward_weights_are_ridge_estimated_when_not_given():
    ds, _, _ = small_dataset()
    est = PEVI(gamma=0.7).fit(ds)
    for h in range(ds.horizon):
        x, r = ds.phi[:, h], ds.rewards[:, h]
        ridge = np.linalg.solve(x.T @ x + 0.7 * np.eye(x.shape[1]), x.T @ r)
        np.testing.assert_allclose(est.reward_weights_[h], ridge, atol=1e-10)


@pytest.mark.parametrize("penalty", ["l1", "l2", "elliptical"])
def test_penalty_forms_and_clipping(penalty):
    ds, feat, theta = small_dataset()
    beta = 0.3
    est = R2PVI("tv", 1.0, beta=beta, penalty=penalty, reward_weights=theta).fit(ds)
    H = ds.horizon
    for h in range(H):
        x = ds.phi[:, h]  # an independent Gram matrix (gamma = 1)
        inv = np.linalg.inv(x.T @ x + np.eye(x.shape[1]))
        lin = feat @ est.weights_[h]
        gamma_pen = {
            "l1": beta * np.abs(feat) @ np.sqrt(np.diag(inv)),
            "l2": beta * np.sqrt(feat**2 @ np.diag(inv)),
            "elliptical": beta * np.sqrt(np.einsum("sad,de,sae->sa", feat, inv, feat)),
        }[penalty]
        np.testing.assert_allclose(est.q_values(feat, h), np.clip(lin - gamma_pen, 0, H - h),
                                   atol=1e-10)
        np.testing.assert_allclose(est.gram_inv_diag_[h], np.diag(inv), rtol=1e-10)


def test_more_pessimism_lowers_q_values_not_weights():
    ds, feat, theta = small_dataset()
    lo = R2PVI("tv", 1.0, beta=0.0, reward_weights=theta).fit(ds)
    hi = R2PVI("tv", 1.0, beta=0.5, reward_weights=theta).fit(ds)
    np.testing.assert_array_equal(lo.weights_[-1], hi.weights_[-1])
    assert np.all(hi.q_values(feat, 0) <= lo.q_values(feat, 0) + 1e-12)


def test_q_values_known_values_act_and_errors():
    ds, feat, theta = small_dataset()
    est = R2PVI("tv", 1.0, reward_weights=theta)
    with pytest.raises(NotFittedError, match="not fitted"):
        est.q_values(feat, 0)
    est.fit(ds)
    known = np.full(feat.shape[:2], np.nan)
    known[:, 1] = 5.0
    q = est.q_values(feat, 0, known_values=known)
    np.testing.assert_array_equal(q[:, 1], 5.0)
    np.testing.assert_array_equal(est.act(feat, 0, known_values=known), 1)
    np.testing.assert_array_equal(est.values(feat, 0), est.q_values(feat, 0).max(axis=1))
    with pytest.raises(ValueError, match="phi_all must have shape"):
        est.q_values(feat[0], 0)
    with pytest.raises(ValueError, match=r"h must be a 0-based step in \[0, 3\)"):
        est.q_values(feat, 3)
    with pytest.raises(TypeError, match="h must be an integer"):
        est.q_values(feat, 1.0)
    with pytest.raises(ValueError, match="known_values must have shape"):
        est.q_values(feat, 0, known_values=known[:, :1])


def test_general_f_estimator_agrees_with_closed_form_on_one_hot_data():
    ds, feat, theta, _ = tabular_exact_count_dataset(seed=3)
    for name, obj in (("tv", TV), ("kl", KL), ("chi2", CHI2)):
        closed = R2PVI(name, 0.7, beta=0.0, gamma=1e-10, reward_weights=theta).fit(ds)
        general = R2PVI(obj, 0.7, beta=0.0, gamma=1e-10, reward_weights=theta).fit(ds)
        np.testing.assert_allclose(general.weights_, closed.weights_, atol=1e-7)


# --------------------------------------------------------------------------- I/O


@pytest.mark.parametrize(
    "est",
    [
        PEVI(beta=0.2),
        R2PVI("tv", 0.5, v_min=0.0, penalty="l2"),
        R2PVI("kl", 0.5),
        R2PVI(cressie_read(3.0), 0.5),
        R2PVI("chi2", 0.5, penalty="elliptical"),
    ],
)
def test_save_load_round_trip(tmp_path, est):
    ds, feat, theta = small_dataset()
    est.set_params(reward_weights=theta).fit(ds)
    path = est.save(tmp_path / "model")
    back = type(est).load(path)
    assert type(back) is type(est)
    assert repr(back) == repr(est)
    np.testing.assert_array_equal(back.reward_weights, theta)
    for h in range(ds.horizon):
        np.testing.assert_array_equal(back.q_values(feat, h), est.q_values(feat, h))
    assert type(load(path)) is type(est)


def test_save_refuses_custom_divergences_and_load_checks_class(tmp_path):
    ds, _, _ = small_dataset()
    custom = FDivergence("mine", CHI2.f, CHI2.conjugate)
    est = R2PVI(custom, 1.0).fit(ds)
    with pytest.raises(TypeError, match="custom FDivergence"):
        est.save(tmp_path / "m")
    path = PEVI().fit(ds).save(tmp_path / "p")
    with pytest.raises(TypeError, match="not a R2PVI"):
        R2PVI.load(path)
    with pytest.raises(NotFittedError, match="not fitted"):
        PEVI().save(tmp_path / "q")


def test_string_options_are_case_insensitive():
    data, *_ = linear_data()
    for make, upper, lower in ((lambda p: R2PVI("tv", penalty=p), "L1", "l1"),
                               (lambda p: PEVI(penalty=p), "Elliptical", "elliptical"),
                               (lambda v: R2PVI("tv", v_min=v), "DATA", "data"),
                               (lambda v: R2PVI(v), "KL", "kl")):
        a, b = make(upper).fit(data), make(lower).fit(data)
        assert np.array_equal(a.weights_, b.weights_)
        phi_all = data.next_phi[:4, 0]
        assert np.array_equal(a.q_values(phi_all, 0), b.q_values(phi_all, 0))
    policy = PEVI().fit(data).as_policy(lambda o, a: np.eye(D)[a % D], beyond_horizon="Last")
    assert policy.beyond_horizon == "last"
