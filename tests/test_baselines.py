"""The d-DRMDP baselines DRPVI and DRVI-L and the variance-aware variants VA-DRPVI and
VA-R2PVI-TV: exact robust weights on exact-count data, limits, monotonicity, the exact
breakpoint solver against Nelder-Mead, the variance weighting, errors and I/O."""

import numpy as np
import pytest
from scipy.optimize import minimize
from test_constrained import kl_ball_primal, tv_ball_primal

from r2pvi import PEVI, R2PVI, OfflineDataset, load
from r2pvi.algorithms import DRPVI, DRVIL, TVBallRule
from r2pvi.algorithms._params import floor_value
from r2pvi.algorithms._variance import variance_weights
from r2pvi.engine import backward_induction

# ------------------------------------------------------------------------------- datasets


def dirichlet_dataset(K=300, H=5, d=4, A=2, seed=0, r_scale=1.0, conc=1.0):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.full(d, conc), size=(K, H))
    next_phi = rng.dirichlet(np.full(d, conc), size=(K, H, A))
    theta = r_scale * rng.uniform(0, 1, size=(H, d))
    rewards = np.einsum("khd,hd->kh", phi, theta)
    return OfflineDataset.from_features(phi, rewards, next_phi), theta, next_phi


def exact_count_dataset(S=3, A=2, H=3, per_pair=20, seed=0):
    """Tabular MDP, one-hot features (factor = (s, a)); at every step each (s, a) appears
    per_pair times with next states in exactly the proportions of ``mu[h, (s, a)]``, and every
    state is a next state of some pair (so the sampled minimum is the minimum over states)."""
    rng = np.random.default_rng(seed)
    d = S * A
    feat = np.eye(d).reshape(S, A, d)
    counts = rng.multinomial(per_pair, np.ones(S) / S, size=(H, d))
    for h in range(H):  # every state reachable at every step
        counts[h, np.arange(S) % d, np.arange(S)] += 1
        counts[h, np.arange(S) % d, 0] -= 1
    counts = np.maximum(counts, 0)
    counts[..., 0] += per_pair - counts.sum(axis=-1)
    assert (counts >= 0).all() and (counts.sum(axis=-1) == per_pair).all()
    mu = counts / per_pair  # (H, d, S)
    theta = rng.uniform(0, 1, size=(H, d))
    K = d * per_pair
    phi = np.zeros((K, H, d))
    nphi = np.zeros((K, H, A, d))
    for h in range(H):
        k = 0
        for i in range(d):
            for s_next in range(S):
                for _ in range(counts[h, i, s_next]):
                    phi[k, h, i] = 1.0
                    nphi[k, h] = feat[s_next]
                    k += 1
    rewards = np.einsum("khd,hd->kh", phi, theta)
    return OfflineDataset.from_features(phi, rewards, nphi), feat, theta, mu


def brute_force_weights(feat, theta, mu, rho, primal):
    """Backward induction with each factor's worst case solved by a brute-force primal."""
    H, d, S = mu.shape
    weights, v_next = np.zeros((H, d)), np.zeros(S)
    for h in range(H - 1, -1, -1):
        w = np.zeros(d) if h == H - 1 else np.array(
            [primal(v_next, mu[h, i], rho[h, i]) for i in range(d)])
        weights[h] = theta[h] + w
        v_next = np.clip(feat @ weights[h], 0.0, H - h).max(axis=1)
    return weights


# ------------------------------------------------------------------------- exact weights


@pytest.mark.parametrize("rho", [0.05, 0.3])
def test_drpvi_on_exact_count_data_equals_brute_force_tv_balls(rho):
    ds, feat, theta, mu = exact_count_dataset()
    radii = np.full(theta.shape, rho)
    radii[0, 1] = 0.0  # a factor without uncertainty
    est = DRPVI(radii, beta=0.0, gamma=1e-10, reward_weights=theta).fit(ds)
    truth = brute_force_weights(feat, theta, mu, radii, tv_ball_primal)
    np.testing.assert_allclose(est.weights_, truth, atol=1e-7)


@pytest.mark.parametrize("rho", [0.005, 0.02])
def test_drvil_on_exact_count_data_equals_brute_force_kl_balls(rho):
    ds, feat, theta, mu = exact_count_dataset(seed=1)
    radii = np.full(theta.shape, rho)
    # DRVI-L's centered regression of e^{-V/b} - 1 leaks gamma / (n_i + gamma) (and rounding,
    # ~1e-16) of mass into the estimate of E[e^{-V/b}], which is not negligible next to
    # e^{-V/b} when the maximizing b is small (large rho): gamma = 1e-14 and moderate radii
    # make the ridge estimate the exact count average.
    est = DRVIL(radii, beta=0.0, gamma=1e-14, reward_weights=theta).fit(ds)
    truth = brute_force_weights(feat, theta, mu, radii, kl_ball_primal)
    np.testing.assert_allclose(est.weights_, truth, atol=1e-6)


# -------------------------------------------------------------------- limits, monotonicity


@pytest.mark.parametrize("est_cls", [DRPVI, DRVIL])
def test_zero_radius_is_the_non_robust_estimator(est_cls):
    ds, theta, _ = dirichlet_dataset()
    for penalty in ("l1", "elliptical"):
        base = PEVI(beta=0.3, gamma=0.5, penalty=penalty).fit(ds)
        est = est_cls(0.0, beta=0.3, gamma=0.5, penalty=penalty).fit(ds)
        np.testing.assert_array_equal(est.weights_, base.weights_)


@pytest.mark.parametrize("est_cls", [DRPVI, DRVIL])
def test_paper_radius_perturbs_only_factor_4_at_the_first_step(est_cls):
    """rho = [[0, 0, 0, r], [0, 0, 0, 0], ...] (the paper's linear-MDP experiment)."""
    ds, theta, _ = dirichlet_dataset(H=4, d=4)
    rho = np.zeros((4, 4))
    rho[0, 3] = 0.3
    base = PEVI(beta=0.1, penalty="l1", reward_weights=theta).fit(ds)
    est = est_cls(rho, beta=0.1, reward_weights=theta).fit(ds)
    np.testing.assert_array_equal(est.weights_[1:], base.weights_[1:])
    np.testing.assert_array_equal(est.weights_[0, :3], base.weights_[0, :3])
    assert est.weights_[0, 3] < base.weights_[0, 3]


def one_hot_dataset(K=400, H=4, S=4, A=2, seed=3):
    """Tabular features: the ridge weights are non-negative, so the fitted values are
    provably monotone in rho (the duals are monotone in V and in rho)."""
    rng = np.random.default_rng(seed)
    d = S * A
    feat = np.eye(d).reshape(S, A, d)
    s = rng.integers(S, size=(K, H))
    a = rng.integers(A, size=(K, H))
    s_next = rng.integers(S, size=(K, H))
    theta = rng.uniform(0, 1, size=(H, d))
    phi = feat[s, a]
    return OfflineDataset.from_features(phi, np.einsum("khd,hd->kh", phi, theta),
                                        feat[s_next]), feat


@pytest.mark.parametrize("est_cls, radii", [(DRPVI, np.linspace(0, 1, 11)),
                                            (DRVIL, np.linspace(0, 3, 11))])
def test_fitted_values_decrease_monotonically_in_rho(est_cls, radii):
    ds, feat = one_hot_dataset()
    starts = feat.reshape(-1, feat.shape[1], feat.shape[2])
    values = [est_cls(r, beta=0.05).fit(ds).values(starts, 0) for r in radii]
    assert np.all(np.diff(values, axis=0) <= 1e-12)
    assert values[-1].mean() < values[0].mean() - 0.1
    # simplex (Dirichlet) features: signed ridge weights, monotone on this fixed data too
    ds, _, next_phi = dirichlet_dataset(seed=7)
    values = [est_cls(r, beta=0.05).fit(ds).values(next_phi[:, 0], 0) for r in radii]
    assert np.all(np.diff(values, axis=0) <= 1e-12)


# -------------------------------------------------------- exact solver vs Nelder-Mead


class NelderMeadAudit(TVBallRule):
    """DRPVI's exact rule that also runs the authors' Nelder-Mead search (from H/2, per
    factor and step) on the same estimated objective and records both values."""

    def __init__(self, rho, v_min, log):
        super().__init__(rho, v_min)
        self.log = log

    def __call__(self, E, v, ctx):
        w = super().__call__(E, v, ctx)
        floor = floor_value(self.v_min, v)
        rho = self.rho[ctx.h]

        def objective(alpha, i):  # E_i[V]_alpha - rho_i (alpha - min_s [V(s)]_alpha)
            return E(np.minimum(v, alpha))[i] - rho[i] * (alpha - min(floor, alpha))

        for i in np.flatnonzero(rho > 0):
            res = minimize(lambda x, i=i: -objective(x[0], i), x0=[ctx.v_upper / 2],
                           method="Nelder-Mead")
            self.log.append((ctx.h, i, w[i], objective(res.x[0], i)))
        return w


class AuditedDRPVI(DRPVI):
    log: list

    def _make_rule(self, params):
        return NelderMeadAudit(params["rho"], params["v_min"], self.log)


def nelder_mead_shortfall(ds, rho, **kw):
    est = AuditedDRPVI(rho, **kw)
    est.log = []
    est.fit(ds)
    exact = np.array([row[2] for row in est.log])
    nm = np.array([row[3] for row in est.log])
    return exact, nm


def test_exact_breakpoint_solver_is_never_below_nelder_mead():
    exact, nm = [], []
    for seed, rho in [(0, 0.05), (1, 0.2), (2, 0.6)]:
        ds, theta, _ = dirichlet_dataset(K=400, H=6, d=5, seed=seed)
        e, n = nelder_mead_shortfall(ds, rho, beta=0.05, reward_weights=theta)
        exact.append(e)
        nm.append(n)
    exact, nm = np.concatenate(exact), np.concatenate(nm)
    assert exact.size == 3 * 5 * 5  # every factor of every step h < H-1 was audited
    assert np.all(exact >= nm - 1e-12)
    short = exact - nm
    print(f"\nNelder-Mead from H/2 vs the exact breakpoint maximum, {short.size} (step, factor) "
          f"problems: short by > 1e-9 in {np.mean(short > 1e-9):.0%}, > 1e-6 in "
          f"{np.mean(short > 1e-6):.0%}; max {short.max():.2g}, mean {short.mean():.2g}")


# ------------------------------------------------------------------- variance weighting


@pytest.mark.parametrize("make", [lambda **kw: DRPVI(0.2, **kw),
                                  lambda **kw: R2PVI("tv", 0.5, **kw)])
def test_variance_weighting_with_unit_variance_reproduces_the_unweighted_estimator(make):
    """Values below 1 (r_max = 0.1): the estimated variance is floored at 1, the weights are
    all 1 and the second pass is the first, exactly."""
    ds, theta, _ = dirichlet_dataset(r_scale=0.1)
    plain = make(beta=0.1, r_max=0.1).fit(ds)
    va = make(beta=0.1, r_max=0.1, variance_aware=True).fit(ds)
    np.testing.assert_array_equal(va.weights_, plain.weights_)
    np.testing.assert_array_equal(va.gram_inv_diag_, plain.gram_inv_diag_)
    # and the weighted engine itself, given unit weights, computes the same model
    est = make(beta=0.1, r_max=0.1)
    params = {**est._validate_common(ds), **est._validate_extra(ds)}
    ones = est._run_engine(ds, params, sample_weights=np.ones((ds.horizon, ds.n_trajectories)))
    np.testing.assert_allclose(ones.weights, plain.weights_, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("cls", [DRPVI, R2PVI])
@pytest.mark.parametrize("c", [1.0, 4.0])
def test_constant_variance_reaches_gram_targets_and_penalty(cls, c):
    """Constant sigma^2 = c: the weighted Gram matrix is Lambda / c when gamma is divided by c,
    the weighted regression targets give the same weights and the penalty with the weighted
    Gram matrix is sqrt(c) times larger, which beta / sqrt(c) undoes."""

    class ConstantVariance(cls):
        def _sample_weights(self, dataset, first, params):
            return np.full((dataset.horizon, dataset.n_trajectories), 1.0 / c)

    args = (0.2,) if cls is DRPVI else ("tv", 0.5)
    ds, _, next_phi = dirichlet_dataset(seed=4)
    plain = cls(*args, beta=0.3, gamma=1.0).fit(ds)
    va = ConstantVariance(*args, beta=0.3 / np.sqrt(c), gamma=1.0 / c,
                          variance_aware=True).fit(ds)
    np.testing.assert_allclose(va.weights_, plain.weights_, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(va.gram_inv_diag_, c * plain.gram_inv_diag_, rtol=1e-10)
    for h in range(ds.horizon):
        np.testing.assert_allclose(va.q_values(next_phi[:, h], h),
                                   plain.q_values(next_phi[:, h], h), atol=1e-10)


def test_variance_weights_follow_the_formula_from_the_first_pass():
    """sigma_h^2 = max{1, [phi^T z2]_[0,H^2] - ([phi^T z1]_[0,H])^2}, with z1, z2 ridge
    regressions of U, U^2, U = V_{h+1} / r_max (in units of r_max; computed here from the first
    pass's next-state values and explicit Gram matrices), and the second pass run with
    1 / sigma^2."""
    H, K, d, r_max = 6, 300, 4, 3.0
    rng = np.random.default_rng(5)
    phi = rng.dirichlet(np.full(d, 0.1), size=(K, H))
    next_phi = rng.dirichlet(np.full(d, 0.1), size=(K, H, 2))
    theta = np.full((H, d), r_max)
    # a zero-value fail state, reached with a probability that depends on factor 0: next
    # values 0 or about (H - h - 1) r_max, variances (in units of r_max) well above 1
    fail = rng.random((K, H)) < 0.1 + 0.8 * phi[..., 0]
    next_values = np.where(fail[..., None], 0.0, np.nan).repeat(2, axis=2)
    ds = OfflineDataset.from_features(phi, np.einsum("khd,hd->kh", phi, theta), next_phi,
                                      next_values)
    gamma, beta, rho = 0.7, 0.05, 0.1
    kw = {"beta": beta, "gamma": gamma, "reward_weights": theta, "r_max": r_max}
    first = DRPVI(rho, **kw).fit(ds)
    rule = TVBallRule(np.full((H, d), rho), "data")
    first_model = backward_induction(ds, rule, beta=beta, gamma=gamma, penalty="l1",
                                     r_max=r_max, reward_weights=theta, value_moments=True)
    np.testing.assert_array_equal(first_model.weights, first.weights_)
    top = H  # in units of r_max
    weights = np.ones((H, ds.n_trajectories))
    for h in range(H - 1):
        p = ds.phi[:, h]
        v = first_model.next_state_values[h] / r_max
        gram = p.T @ p + gamma * np.eye(d)
        z1, z2 = np.linalg.solve(gram, p.T @ v), np.linalg.solve(gram, p.T @ v**2)
        var = np.clip(p @ z2, 0, top**2) - np.clip(p @ z1, 0, top) ** 2
        weights[h] = 1.0 / np.maximum(1.0, var)
    assert weights.min() < 0.9  # the variance exceeds 1 here: the weighting is active
    va = DRPVI(rho, variance_aware=True, **kw).fit(ds)
    model = backward_induction(ds, rule, beta=beta, gamma=gamma, penalty="l1", r_max=r_max,
                               reward_weights=theta, sample_weights=weights)
    np.testing.assert_allclose(va.weights_, model.weights, atol=1e-10)
    assert not np.allclose(va.weights_, first.weights_)
    # the library's helper computes the same weights from the first pass's fitted model
    np.testing.assert_allclose(variance_weights(ds, first_model, top), weights, rtol=1e-10)


# ------------------------------------------------------------------------ errors and I/O


@pytest.mark.parametrize(
    "make, err, match",
    [
        (lambda: DRPVI(-0.1), ValueError, "rho must be >= 0"),
        (lambda: DRPVI(np.array([0.1, np.nan, 0, 0])), ValueError, "rho must be finite"),
        (lambda: DRPVI(np.zeros(3)), ValueError, r"\(d,\) = \(4,\) vector or an \(H, d\)"),
        (lambda: DRPVI(np.zeros((2, 4))), ValueError, r"\(H, d\) = \(5, 4\)"),
        (lambda: DRPVI("big"), TypeError, "rho must be a number"),
        (lambda: DRPVI(True), TypeError, "rho must be a number"),
        (lambda: DRPVI(None), TypeError, "rho must be a number"),
        (lambda: DRVIL(-1.0), ValueError, "rho must be >= 0"),
        (lambda: DRVIL([[0.1, 0.2]]), ValueError, "rho must be a scalar"),
        (lambda: DRPVI(0.1, v_min="min"), ValueError, "v_min must be 'data' or a number"),
        (lambda: DRPVI(0.1, variance_aware="yes"), TypeError, "variance_aware must be True"),
        (lambda: DRPVI(0.1, penalty="l3"), ValueError, "penalty must be one of"),
        (lambda: DRVIL(0.1, gamma=0.0), ValueError, "gamma must be > 0"),
        (lambda: R2PVI("kl", variance_aware=True), ValueError, "only defined for divergence='tv'"),
        (lambda: R2PVI("chi2", variance_aware=1), TypeError, "variance_aware must be True"),
    ],
)
def test_bad_parameters_raise_clear_errors_at_fit(make, err, match):
    ds, _, _ = dirichlet_dataset()
    est = make()  # __init__ only stores
    with pytest.raises(err, match=match):
        est.fit(ds)


def test_drvil_has_no_variance_aware_or_v_min_parameter():
    with pytest.raises(TypeError):
        DRVIL(0.1, variance_aware=True)
    assert set(DRVIL(0.1).get_params()) == {"rho", "beta", "gamma", "penalty",
                                            "reward_weights", "r_max", "b_min", "form",
                                            "time_homogeneous"}


@pytest.mark.parametrize(
    "est",
    [
        DRPVI(np.array([[0.0, 0.0, 0.0, 0.3]] + [[0.0] * 4] * 4), beta=0.1),
        DRPVI(0.2, v_min=0.0, variance_aware=True, penalty="l2"),
        DRVIL(np.array([0.1, 0.0, 0.2, 0.05]), beta=0.1),
        R2PVI("tv", 0.5, variance_aware=True),
    ],
)
def test_save_load_round_trip(tmp_path, est):
    ds, _, next_phi = dirichlet_dataset()
    est.fit(ds)
    back = load(est.save(tmp_path / "model.npz"))
    assert type(back) is type(est)
    for name, value in est.get_params().items():
        np.testing.assert_array_equal(np.asarray(getattr(back, name)), np.asarray(value))
    np.testing.assert_array_equal(back.weights_, est.weights_)
    np.testing.assert_array_equal(back.q_values(next_phi[:, 1], 1), est.q_values(next_phi[:, 1], 1))
