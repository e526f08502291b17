"""Measure what the authors' script choices change on the simulated linear MDP (fig1a setting).

CleanRL-style single file. Each variant is fitted on the same 20 datasets (K = 100, uniform
behaviour, beta = 1, gamma = 0.1, lam = 0.1, ||xi||_1 = 0.3) and evaluated exactly on the
perturbed environments q = 0 and q = 1:

- paper: r2pvi as the paper writes it (l1 penalty, chi^2 maximized over alpha);
- l2 penalty: the authors' sqrt(sum_i phi_i^2 [Lambda^-1]_ii);
- chi^2 minimized over alpha: the authors' linear-MDP code minimizes the estimated dual
  (Nelder-Mead); here the exact minimum over every breakpoint and a fine grid;
- the 0-clip: how often the unclipped Q_h = phi^T w - Gamma is negative at a state-action of
  the MDP, and how often clipping at 0 changes a greedy action (the authors do not clip).

    python scripts/authors_differences.py
"""

import numpy as np

from r2pvi import R2PVI
from r2pvi.algorithms.r2pvi import Chi2Rule
from r2pvi.duals.piecewise import chi2_objective
from r2pvi.engine import StepRule, penalty_values
from r2pvi.envs import SimulatedLinearMDP
from r2pvi.evaluation import expected_return

LAM, BETA, GAMMA, K, REPS = 0.1, 1.0, 0.1, 100, 20


class Chi2MinRule(StepRule):
    """The authors' chi^2: the estimated objective *minimized* over alpha in [0, H]."""

    def __call__(self, E, v, ctx):
        top = ctx.v_upper
        alphas = np.unique(np.concatenate([v, np.linspace(0.0, top, 2001)]))
        trunc = np.minimum(v[None, :], alphas[:, None])
        e1, e2 = E(trunc.T), E((trunc**2).T)  # (d, n_alpha)
        return chi2_objective(e1, e2, LAM).min(axis=1)


class R2PVIChi2Min(R2PVI):
    def _make_rule(self, params):
        return Chi2MinRule()


def main():
    env = SimulatedLinearMDP(xi_norm=0.3)
    tests = {q: env.perturbed(q) for q in (0.0, 1.0)}
    variants = {
        "R2PVI-TV, paper (l1)": lambda: R2PVI("tv", LAM, beta=BETA, gamma=GAMMA),
        "R2PVI-TV, l2 penalty": lambda: R2PVI("tv", LAM, beta=BETA, gamma=GAMMA, penalty="l2"),
        "R2PVI-KL, paper (l1)": lambda: R2PVI("kl", LAM, beta=BETA, gamma=GAMMA),
        "R2PVI-KL, l2 penalty": lambda: R2PVI("kl", LAM, beta=BETA, gamma=GAMMA, penalty="l2"),
        "R2PVI-chi2, paper (max over alpha)": lambda: R2PVI("chi2", LAM, beta=BETA, gamma=GAMMA),
        "R2PVI-chi2, min over alpha (authors)": lambda: R2PVIChi2Min(
            "chi2", LAM, beta=BETA, gamma=GAMMA),
    }
    assert Chi2Rule  # the paper's rule, for reference
    results = {name: {q: [] for q in tests} for name in variants}
    negative, flips, total = 0, 0, 0
    seeds = np.random.SeedSequence(0).spawn(REPS)
    for seq in seeds:
        data = env.collect(K, seed=np.random.default_rng(seq))
        for name, make in variants.items():
            est = make().set_params(reward_weights=env.theta).fit(data)
            for q, test in tests.items():
                results[name][q].append(expected_return(test, est))
            if name == "R2PVI-TV, paper (l1)":
                for h in range(env.horizon):
                    phi = env.features(h)  # (S, A, d)
                    lin = phi @ est.weights_[h]
                    pen = penalty_values(phi, "l1", BETA, est.gram_inv_diag_[h])
                    raw = lin - pen
                    negative += int((raw < 0).sum())
                    total += raw.size
                    clipped = np.clip(raw, 0, env.horizon - h)
                    flips += int((raw.argmax(axis=1) != clipped.argmax(axis=1)).sum())
    print(f"{'variant':<40s} {'q = 0':>14s} {'q = 1':>14s}   (mean±std over {REPS} datasets)")
    for name, res in results.items():
        cells = [f"{np.mean(res[q]):.3f}±{np.std(res[q], ddof=1):.3f}" for q in tests]
        print(f"{name:<40s} {cells[0]:>14s} {cells[1]:>14s}")
    print(f"\nR2PVI-TV (l1): unclipped Q_h < 0 at {negative} of {total} (h, s, a); clipping at 0 "
          f"changes the greedy action at {flips} of {REPS * env.horizon * env.n_states} (h, s)")


if __name__ == "__main__":
    main()
