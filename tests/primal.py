"""Brute-force primal solutions of ``inf_mu E_mu V + lam D(mu || mu0)``: the independent truth.

None of these uses a dual formula: TV is a linear program, chi^2 a convex QP solved exactly
by enumerating active sets (KKT on each support), KL and the other f-divergences a smooth
convex program solved numerically on the support of ``mu0``.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.optimize import linprog, minimize


def tv_primal(v, mu0, lam):
    """LP: min V.mu + lam/2 sum t, t >= |mu - mu0|, mu in the simplex (any state)."""
    n = v.size
    c = np.concatenate([v, np.full(n, lam / 2.0)])
    eye = np.eye(n)
    a_ub = np.block([[eye, -eye], [-eye, -eye]])
    b_ub = np.concatenate([mu0, -mu0])
    a_eq = np.concatenate([np.ones(n), np.zeros(n)])[None]
    res = linprog(c, A_ub=a_ub, b_ub=b_ub, A_eq=a_eq, b_eq=[1.0],
                  bounds=[(0, None)] * (2 * n), method="highs")
    assert res.success, res.message
    return res.fun


def chi2_primal(v, mu0, lam):
    """Exact QP min V.mu + lam sum (mu - mu0)^2 / mu0 over the simplex (support of mu0).

    For each candidate support S' the KKT conditions give mu in closed form; the minimum
    over the feasible candidates is the exact optimum of the convex QP.
    """
    supp = np.flatnonzero(mu0 > 0)
    best = np.inf
    for r in range(1, supp.size + 1):
        for subset in itertools.combinations(supp, r):
            s = np.array(subset)
            # V_s + 2 lam (mu_s - mu0_s) / mu0_s = eta on S', sum mu_s = 1.
            m0 = mu0[s]
            eta = (1.0 - m0.sum() + (m0 * v[s]).sum() / (2 * lam)) / (m0.sum() / (2 * lam))
            mu_s = m0 * (1.0 + (eta - v[s]) / (2 * lam))
            if (mu_s < -1e-12).any():
                continue
            mu = np.zeros_like(mu0)
            mu[s] = np.maximum(mu_s, 0.0)
            mu /= mu.sum()
            on = mu0 > 0
            val = mu @ v + lam * np.sum((mu[on] - mu0[on]) ** 2 / mu0[on])
            best = min(best, val)
    return best


def smooth_primal(v, mu0, lam, f):
    """min over mu on the support of mu0 of V.mu + lam sum mu0 f(mu/mu0), via softmax
    coordinates and BFGS, polished by SLSQP; several starts, best value."""
    supp = mu0 > 0
    vv, m0 = v[supp], mu0[supp]

    def obj_mu(mu):
        return mu @ vv + lam * np.sum(m0 * f(mu / m0))

    def obj_z(z):
        z = z - z.max()
        mu = np.exp(z) / np.exp(z).sum()
        return obj_mu(mu)

    best = np.inf
    starts = [np.log(m0), np.zeros(m0.size), np.log(m0) - vv / max(lam, 1e-3)]
    for z0 in starts:
        res = minimize(obj_z, z0, method="BFGS", options={"gtol": 1e-12, "maxiter": 5000})
        z = res.x - res.x.max()
        mu = np.exp(z) / np.exp(z).sum()
        res2 = minimize(obj_mu, mu, method="SLSQP", bounds=[(0, 1)] * mu.size,
                        constraints=[{"type": "eq", "fun": lambda m: m.sum() - 1.0}],
                        options={"ftol": 1e-15, "maxiter": 1000})
        best = min(best, res.fun, res2.fun if res2.success else np.inf)
    return best


def general_primal(v, mu0, lam, divergence):
    """SLSQP on the whole simplex with ``divergence.divergence`` (mass off the support allowed
    when the divergence permits it)."""
    n = v.size
    free = np.ones(n, bool) if np.isfinite(divergence.domain_max) else mu0 > 0

    def obj(x):
        mu = np.zeros(n)
        mu[free] = x
        return mu @ v + lam * divergence.divergence(mu, mu0)

    best = np.inf
    nf = int(free.sum())
    for x0 in (mu0[free] / mu0[free].sum(), np.ones(nf) / nf):
        with np.errstate(all="ignore"):
            res = minimize(obj, x0, method="SLSQP", bounds=[(0, 1)] * nf,
                           constraints=[{"type": "eq", "fun": lambda m: m.sum() - 1.0}],
                           options={"ftol": 1e-15, "maxiter": 2000})
        if np.isfinite(res.fun):
            best = min(best, res.fun)
    return best
