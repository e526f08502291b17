"""Small datasets that several test files share.

``linear_data`` is a linear MDP's data whose rewards are ``phi_h^T theta_h`` (scaled and
shifted on demand), used by the tests of the reward check, error messages and estimator
options.
"""

import numpy as np

from r2pvi import OfflineDataset

K, H, D, A = 60, 3, 4, 2


def linear_data(scale=1.0, shift=0.0, seed=0, **kw):
    """``(dataset, phi, rewards, next_phi, theta)``: K = 60 trajectories, H = 3, d = 4, A = 2,
    rewards ``scale * phi_h^T theta_h + shift``; ``kw`` goes to ``from_features``."""
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(D), size=(K, H))
    nxt = rng.dirichlet(np.ones(D), size=(K, H, A))
    theta = rng.uniform(size=(H, D))
    r = scale * np.einsum("khd,hd->kh", phi, theta) + shift
    return OfflineDataset.from_features(phi, r, nxt, **kw), phi, r, nxt, theta


def fail_state_mdp(seed=0, H=3, n_actions=2, reward_high=0.1, random_initial=False):
    """A genuine linear MDP: 4 factors over 6 states; state 5 is an absorbing fail state
    (V = 0, known value 0) reached through factor 3; factor 0 puts no mass on it. Rewards
    ``theta ~ U(0, reward_high)`` (0 on factor 3); the initial distribution is uniform over
    states 0-4, or a Dirichlet draw over them with ``random_initial``."""
    from r2pvi.envs import FiniteLinearMDP

    rng = np.random.default_rng(seed)
    S, d = 6, 4
    phi = rng.dirichlet(np.ones(d), size=(S, n_actions))
    phi[5] = np.eye(d)[3]
    mu = np.zeros((H, d, S))
    for h in range(H):
        mu[h, 0, :5] = rng.dirichlet(np.ones(5))  # no mass on the V = 0 state
        mu[h, 1] = rng.dirichlet(np.ones(S))
        mu[h, 2] = rng.dirichlet(np.ones(S))
        mu[h, 3] = np.eye(S)[5]
    theta = rng.uniform(0.0, reward_high, size=(H, d))
    theta[:, 3] = 0.0
    start = rng.dirichlet(np.ones(5)) if random_initial else np.full(5, 0.2)
    return FiniteLinearMDP(phi, theta, mu, initial=np.r_[start, 0.0], fail_states=(5,))


def pooled_or_per_step_estimators():
    """``make(time_homogeneous) -> estimator`` for every rule the state-feature layout serves
    (TV, KL, chi^2, PEVI with the elliptical penalty, DRPVI; the last, variance-aware TV)."""
    from r2pvi import DRPVI, PEVI, R2PVI

    return [
        lambda th: R2PVI("tv", lam=0.3, beta=0.1, r_max=1.5, time_homogeneous=th),
        lambda th: R2PVI("kl", lam=0.5, beta=0.1, r_max=1.5, time_homogeneous=th),
        lambda th: R2PVI("chi2", lam=1.0, beta=0.1, r_max=1.5, time_homogeneous=th),
        lambda th: PEVI(beta=0.2, penalty="elliptical", r_max=1.5, time_homogeneous=th),
        lambda th: DRPVI(rho=0.2, beta=0.1, r_max=1.5, time_homogeneous=th),
        lambda th: R2PVI("tv", lam=0.3, beta=0.1, r_max=1.5, variance_aware=True,
                         time_homogeneous=th),
    ]
