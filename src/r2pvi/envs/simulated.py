"""The paper's simulated linear MDP (Appendix A.1, from Liu & Xu 2024, Supplementary A.1)."""

from __future__ import annotations

import itertools

import numpy as np

from .._validation import check_scalar
from .finite import FiniteLinearMDP

__all__ = ["SimulatedLinearMDP", "SIMULATED_ACTIONS"]

#: The 16 actions ``{-1, 1}^4`` in ``itertools.product`` order (row ``a`` is action ``a``).
SIMULATED_ACTIONS = np.array(list(itertools.product([-1, 1], repeat=4)), dtype=float)
SIMULATED_ACTIONS.flags.writeable = False

_LEAK = 0.001  # nominal probability of falling into the fail state x4 from x1 and x2
X1, X2, X3, X4, X5 = range(5)


class SimulatedLinearMDP(FiniteLinearMDP):
    """The simulated linear MDP of the paper's Appendix A.1 (states x1..x5 are 0..4).

    H = 3 steps, start x1, actions ``{-1, 1}^4`` in ``itertools.product`` order,
    ``xi = (xi_norm / 4) (1, 1, 1, 1)`` and, with ``p(a) = delta + <xi, a>``,

    - ``phi(x1, a) = (1 - p, 0, 0, p)``, ``phi(x2, a) = (0, 1 - p, 0, p)``,
      ``phi(x3, a) = (0, 0, 1 - p, p)``, ``phi(x4, .) = e3``, ``phi(x5, .) = e4``;
    - ``theta_0 = 0`` and ``theta_1 = theta_2 = e4``: x2 and x3 pay ``p(a)``, x5 pays 1,
      x4 (the absorbing fail state, value 0) pays 0;
    - nominal factors, the same at every step: ``mu_1 = 0.999 x2 + 0.001 x4``,
      ``mu_2 = 0.999 x3 + 0.001 x4``, ``mu_3 = x4``, ``mu_4 = x5``.

    ``perturbed(q)`` changes step 0 only: ``mu_1 = x2`` and ``mu_4 = q x4 + (1 - q) x5``
    (so ``q = 0`` is not exactly the nominal model: the 0.001 leak is gone). The behaviour
    policy is uniform over actions.

    Parameters
    ----------
    delta : float, default 0.3
    xi_norm : float, default 0.2
        ``||xi||_1``; features stay on the simplex when
        ``xi_norm <= delta <= 1 - xi_norm``.
    q : float in [0, 1], optional
        Perturbation of step 0 (None: the nominal model). Prefer :meth:`perturbed`.

    Examples
    --------
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> env = SimulatedLinearMDP()
    >>> env.n_states, env.n_actions, env.n_features, env.horizon
    (5, 16, 4, 3)
    >>> env.transition_matrix(0)[0, 15].round(4).tolist()    # x1, a = (1,1,1,1): p = 0.5
    [0.0, 0.4995, 0.0, 0.0005, 0.5]
    >>> env.perturbed(0.5).transition_matrix(0)[0, 15].tolist()
    [0.0, 0.5, 0.0, 0.25, 0.25]
    """

    gym_id = "r2pvi/SimulatedLinearMDP-v0"
    actions = SIMULATED_ACTIONS

    def __init__(self, delta=0.3, xi_norm=0.2, *, q=None):
        delta = check_scalar(delta, "delta", low=0.0, high=1.0)
        xi_norm = check_scalar(xi_norm, "xi_norm", low=0.0)
        if not xi_norm <= delta <= 1.0 - xi_norm:
            raise ValueError(
                f"delta = {delta} and xi_norm = {xi_norm} give features off the simplex: "
                "delta +- <xi, a> must stay in [0, 1], i.e. xi_norm <= delta <= 1 - xi_norm"
            )
        if q is not None:
            q = check_scalar(q, "q", low=0.0, high=1.0)
        self.delta, self.xi_norm, self.q = delta, xi_norm, q
        self.xi = np.full(4, xi_norm / 4.0)
        p = delta + SIMULATED_ACTIONS @ self.xi  # (A,)
        A = SIMULATED_ACTIONS.shape[0]
        phi = np.zeros((5, A, 4))
        for s in (X1, X2, X3):
            phi[s, :, s] = 1.0 - p
            phi[s, :, 3] = p
        phi[X4, :, 2] = 1.0
        phi[X5, :, 3] = 1.0
        theta = np.zeros((3, 4))
        theta[1:, 3] = 1.0
        mu = np.tile(_nominal_factors(), (3, 1, 1))
        if q is not None:
            mu[0, 0] = np.eye(5)[X2]
            mu[0, 3] = q * np.eye(5)[X4] + (1.0 - q) * np.eye(5)[X5]
        super().__init__(phi, theta, mu, initial=X1, fail_states=(X4,))

    def perturbed(self, q) -> SimulatedLinearMDP:
        """The test environment with perturbation ``q`` at step 0 (paper, Appendix A.1).

        ``mu_1 = x2`` and ``mu_4 = q x4 + (1 - q) x5`` at step 0; the other steps keep the
        nominal factors.
        """
        return SimulatedLinearMDP(self.delta, self.xi_norm, q=q)

    def init_kwargs(self) -> dict:
        kwargs = {"delta": self.delta, "xi_norm": self.xi_norm}
        if self.q is not None:
            kwargs["q"] = self.q
        return kwargs

    def __repr__(self) -> str:
        extra = "" if self.q is None else f", q={self.q:g}"
        return f"SimulatedLinearMDP(delta={self.delta:g}, xi_norm={self.xi_norm:g}{extra})"


def _nominal_factors() -> np.ndarray:
    eye = np.eye(5)
    return np.stack([
        (1.0 - _LEAK) * eye[X2] + _LEAK * eye[X4],
        (1.0 - _LEAK) * eye[X3] + _LEAK * eye[X4],
        eye[X4],
        eye[X5],
    ])
