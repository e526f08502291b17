"""Is held-out fitted-Q evaluation unstable for the candidates it misjudges? (A measured check.)

Pooled FQE of a policy ``pi`` iterates ``W -> theta + M_pi W`` with
``M_pi = Lambda^{-1} sum_i phi(s_i, a_i) phi(s'_i, pi(s'_i))^T`` over the transitions whose
next state is not absorbing. Off-policy, ``M_pi`` need not be a contraction, and an expansive
iteration would make FQE's value meaningless: a candidate rule for selection would drop the
candidates whose iteration expands. This script fits every candidate of
``bench_selection.py``'s grid on its task's training episodes and prints the spectral radius
of ``M_pi`` on the evaluation map, at the evaluation ridges 0.01 and 1, for ``pi`` the
candidate's greedy policy at step 1 (clip and known values as it acts)::

    python benchmarks/bench_fqe_contraction.py --task acrobot
    python benchmarks/bench_fqe_contraction.py --task cartpole

It also prints the median feature mass ``sum phi_i^2`` of the evaluation map over the
training transitions. The result (docs/user_guide/model-selection.md): on Acrobot every
radius is below 1 and the candidates FQE ranks right and wrong barely differ, so instability
is not the cause there.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from bench_selection import acrobot_task, cartpole_task

from r2pvi.algorithms._fqe import _Policy, _Rows, evaluation_features


def fqe_radius(est, data, evaluation_map, gamma: float, step: int = 1) -> float:
    """The spectral radius of pooled FQE's iteration matrix ``M_pi`` (see the module
    docstring) for ``est``'s greedy policy at ``step``, on ``evaluation_map``'s features."""
    rows = _Rows(data, gamma, True, evaluation_map)
    known = None
    if rows.rows is not None and rows.rows.size:
        known = (rows.rows, rows.row_known + (rows.H - 1) * rows.offset)
    act = _Policy(est).actions(rows.policy_feats, step, known, -1)
    taken = rows.E.crossed
    psi, a_taken, A = np.asarray(taken.psi, float), np.asarray(taken.actions), taken.n_actions
    psi_next = np.asarray(rows.feats.psi, float)
    m = psi.shape[1]
    boot = a_taken >= 0  # a real transition...
    if known is not None:
        boot[rows.rows] = False  # ...whose next value is bootstrapped, not known
    lam, cross = np.zeros((A * m, A * m)), np.zeros((A * m, A * m))
    for a in range(A):
        sel = a_taken == a
        lam[a * m:(a + 1) * m, a * m:(a + 1) * m] = psi[sel].T @ psi[sel] + gamma * np.eye(m)
        for b in range(A):
            both = sel & boot & (act == b)
            cross[a * m:(a + 1) * m, b * m:(b + 1) * m] = psi[both].T @ psi_next[both]
    return float(np.max(np.abs(np.linalg.eigvals(np.linalg.solve(lam, cross)))))


def feature_mass(data, evaluation_map) -> float:
    """The median over the evaluation map's features of ``sum phi_i^2`` over the dataset's
    transitions (a feature is a state feature crossed with an action)."""
    states, _ = evaluation_features(data, evaluation_map)
    actions = np.asarray(data._source.phi.actions)
    masses = [(states[actions == a] ** 2).sum(axis=0) for a in range(data.n_actions)]
    return float(np.median(np.concatenate(masses)))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=["cartpole", "acrobot"], default="acrobot")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    task = acrobot_task(False) if args.task == "acrobot" else cartpole_task(False)
    first = task.dataset(task.grid[0].feature_map)
    n = int((np.asarray(first._source.phi.actions) >= 0).sum())
    print(f"{args.task}: {n} transitions; median feature mass of the evaluation map: "
          f"{feature_mass(first, task.eval_map):.3f}")
    print(f"{'candidate':<34} {'map':<7} {'rho (gamma 0.01)':>17} {'rho (gamma 1)':>14}")
    for cand in task.grid:
        data = task.dataset(cand.feature_map)
        c = time.process_time()
        est = cand.estimator.fit(data)
        fit = time.process_time() - c
        radii = [fqe_radius(est, data, task.eval_map, g) for g in (0.01, 1.0)]
        print(f"{cand.label:<34} {cand.feature_map:<7} {radii[0]:17.4f} {radii[1]:14.4f}"
              f"   (fit {fit:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
