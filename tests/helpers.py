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
