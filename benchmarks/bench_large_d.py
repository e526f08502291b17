"""Large feature spaces (issue 14): fit times against the linear-algebra floor, peak memory.

CartPole-like data built with NumPy (no Gymnasium needed): K episodes of H = 200 steps of
the CartPole equations (Euler, tau = 0.02, force 10) under an epsilon-greedy (0.3) linear
state-feedback controller, reward 1 while the pole is up; episodes are not cut at failure
(every step carries data), so each step has K transitions.

- ``rbf``: dense normalized Gaussian RBF on a 4 x 4 x 6 x 6 grid over (x, x_dot, theta,
  theta_dot), crossed with the 2 actions block-wise: d = 1152.
- ``tiles``: tile coding, 8 tilings of 6^4 tiles each, averaged over the tilings (8 non-zeros
  of 1/8 per row), crossed with the actions: d = 20,736, stored as ``scipy.sparse`` rows.
- ``solvers``: one tile-coding step at K = 300, 1000, 3000, solved every exact way (the
  choice of factorization for sparse rows, see :func:`solvers_case`).
- ``act``: per-state acting time at d = 450 (RBF 3 x 3 x 5 x 5 x 2 actions), PEVI
  (elliptical penalty) against R2PVI-TV (l1 penalty).

The floor is the issue's: for one step, one K x d Gram matrix + Cholesky + solve in the primal
(d x d) and in the dual (K x K) form; ``floor = H * min(primal, dual)``, timed in the same run.
The pooled-step fit has its own floor (:func:`pooled_floor`): one Gram matrix of the H K rows,
then at every step one pass over the H K A next-state features and one over the H K rows —
memory-bound, H times the data read per step. Every case runs in its own subprocess (peak RSS
is the child's ``ru_maxrss``), with one BLAS thread by default. Times are the process's CPU
seconds (``time.process_time``): with one thread they are the work done, whatever else runs on
the machine (on a quiet machine they equal wall time; ``--wall`` reports wall time instead).

    python benchmarks/bench_large_d.py                   # every case
    python benchmarks/bench_large_d.py --cases rbf300 tiles300 act
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np
import scipy.sparse as sp

H = 200
A = 2


# ----------------------------------------------------------------------------- data


def cartpole_episodes(K, seed=0, eps=0.3):
    """States (K, H+1, 4), actions (K, H), rewards (K, H) of a CartPole-like system."""
    rng = np.random.default_rng(seed)
    g, mc, mp, length, force, tau = 9.8, 1.0, 0.1, 0.5, 10.0, 0.02
    total, pml = mc + mp, mp * length
    gain = np.array([1.0, 1.5, 18.0, 3.0])  # a stabilizing state feedback (hand-tuned)
    s = rng.uniform(-0.05, 0.05, size=(K, 4))
    states = np.empty((K, H + 1, 4))
    actions = np.empty((K, H), dtype=np.int64)
    rewards = np.empty((K, H))
    for h in range(H):
        states[:, h] = s
        a = (s @ gain > 0).astype(np.int64)
        explore = rng.random(K) < eps
        a[explore] = rng.integers(0, A, explore.sum())
        f = np.where(a == 1, force, -force)
        x, xd, th, thd = s.T
        ct, st_ = np.cos(th), np.sin(th)
        temp = (f + pml * thd**2 * st_) / total
        thacc = (g * st_ - ct * temp) / (length * (4.0 / 3.0 - mp * ct**2 / total))
        xacc = temp - pml * thacc * ct / total
        s = np.stack([x + tau * xd, xd + tau * xacc, th + tau * thd, thd + tau * thacc], axis=1)
        actions[:, h] = a
        rewards[:, h] = ((np.abs(s[:, 0]) < 2.4) & (np.abs(s[:, 2]) < 0.2095)).astype(float)
    states[:, H] = s
    return states, actions, rewards


LOW = np.array([-2.4, -3.0, -0.21, -3.0])
HIGH = -LOW


def rbf_map(grid):
    """Normalized Gaussian RBF on a grid of centers, crossed with the actions: (n, A * prod)."""
    axes = [np.linspace(lo, hi, k) for lo, hi, k in zip(LOW, HIGH, grid, strict=True)]
    centers = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 4)
    width = (HIGH - LOW) / (np.array(grid) - 1)
    m = centers.shape[0]

    def feature_map(obs, act):
        z = (obs[:, None, :] - centers[None]) / width
        # A softmax: shifting by the row's largest logit keeps states far from every center
        # finite (exp(-0.5 |z|^2) alone underflows to 0/0 = NaN there).
        logits = -0.5 * np.einsum("nmj,nmj->nm", z, z)
        k = np.exp(logits - logits.max(axis=1, keepdims=True))
        k /= k.sum(axis=1, keepdims=True)
        out = np.zeros((obs.shape[0], A * m))
        for a in range(A):
            rows = act == a
            out[rows, a * m:(a + 1) * m] = k[rows]
        return out

    return feature_map, A * m


def tile_map(tiles=6, tilings=8, seed=1):
    """Tile coding averaged over tilings, crossed with the actions: sparse (n, A * T * tiles^4)."""
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(0, 1, size=(tilings, 4))
    per = tiles**4
    d = A * tilings * per

    def feature_map(obs, act):
        u = (np.clip(obs, LOW, HIGH) - LOW) / (HIGH - LOW) * (tiles - 1)
        n = obs.shape[0]
        idx = np.floor(u[:, None, :] + offsets[None]).astype(np.int64)  # (n, T, 4)
        idx = np.clip(idx, 0, tiles - 1)
        flat = ((idx[..., 0] * tiles + idx[..., 1]) * tiles + idx[..., 2]) * tiles + idx[..., 3]
        cols = act[:, None] * tilings * per + np.arange(tilings)[None] * per + flat
        rows = np.repeat(np.arange(n), tilings)
        return sp.csr_matrix((np.full(n * tilings, 1.0 / tilings), (rows, cols.ravel())),
                             shape=(n, d))

    return feature_map, d


def dense_dataset(K, grid, seed=0):
    """Step-major dense dataset (built without the (K, H, ...) copies of from_features)."""
    from r2pvi import OfflineDataset

    states, actions, rewards = cartpole_episodes(K, seed)
    fmap, d = rbf_map(grid)
    phi = np.empty((H, K, d))
    next_phi = np.empty((H, K, A, d))
    for h in range(H):
        phi[h] = fmap(states[:, h], actions[:, h])
        for a in range(A):
            next_phi[h, :, a] = fmap(states[:, h + 1], np.full(K, a))
    # Step-major float64 arrays handed over as (K, H, ...) views: from_features keeps them
    # without a copy (at K = 1000 a copy would be a second 5.5 GB).
    ds = OfflineDataset.from_features(phi.transpose(1, 0, 2), rewards,
                                      next_phi.transpose(1, 0, 2, 3), check_simplex=False)
    return ds, d


def sparse_dataset(K, seed=0):
    from r2pvi.sparse import SparseOfflineDataset

    states, actions, rewards = cartpole_episodes(K, seed)
    fmap, d = tile_map()
    return SparseOfflineDataset.from_transitions(states[:, :-1], actions, rewards,
                                                 states[:, 1:], fmap, A), d


# ----------------------------------------------------------------------------- timing


def step_floor(phi, rewards, gamma=1.0, repeats=3):
    """(primal, dual) seconds of one Gram matrix + Cholesky + solve for a K x d step.

    Sparse rows: the dual's Gram matrix is a sparse product (then a dense K x K Cholesky),
    the primal's a dense |U| x |U| matrix on the used features (:func:`sparse_step_floor`).
    Dense rows: the primal (a dense d x d factorization) is not timed above d = 4096.
    """
    if sp.issparse(phi):
        return sparse_step_floor(phi, rewards, gamma, repeats)
    dense = phi

    def primal():
        g = dense.T @ dense
        g[np.diag_indices_from(g)] += gamma
        c = np.linalg.cholesky(g)
        np.linalg.solve(c.T, np.linalg.solve(c, dense.T @ rewards))

    def dual():
        g = dense @ dense.T
        g[np.diag_indices_from(g)] += gamma
        c = np.linalg.cholesky(g)
        dense.T @ np.linalg.solve(c.T, np.linalg.solve(c, rewards))

    out = []
    for fn in (primal, dual):
        if fn is primal and dense.shape[1] > 4096:  # a dense d x d Gram matrix: GBs, minutes
            out.append(np.inf)
            continue
        best = np.inf
        for _ in range(repeats):
            best = min(best, timed(fn))
        out.append(best)
    return out


def sparse_step_floor(phi, rewards, gamma, repeats):
    """(primal on the used features, dual) for sparse rows: no row has an entry off the used
    features U, so the primal Gram matrix is |U| x |U| (dense) plus gamma I elsewhere."""
    used = np.unique(phi.indices)
    sub = phi[:, used]

    def primal():
        g = (sub.T @ sub).toarray()
        g[np.diag_indices_from(g)] += gamma
        c = np.linalg.cholesky(g)
        np.linalg.solve(c.T, np.linalg.solve(c, sub.T @ rewards))

    def dual():
        g = (phi @ phi.T).toarray()
        g[np.diag_indices_from(g)] += gamma
        c = np.linalg.cholesky(g)
        phi.T @ np.linalg.solve(c.T, np.linalg.solve(c, rewards))

    return [min(timed(fn) for _ in range(repeats)) for fn in (primal, dual)]


CLOCK = time.process_time


def pooled_floor(ds, gamma=1.0):
    """What any pooled-step (time-homogeneous) fit must do: one Gram matrix of all H K rows
    with its Cholesky factor, then at every step one pass over the H K A stored next-state
    features (V_{h+1} at every pooled next state) and one over the H K rows (the regression):
    ``gram + H * (one matrix-vector product each)``."""
    from r2pvi.engine import pooled_steps

    phi, rewards, next_phi, _ = ds._source.pooled(pooled_steps(ds.horizon))
    flat = next_phi.reshape(-1, next_phi.shape[-1])
    w = np.full(phi.shape[1], 1.0 / phi.shape[1])

    def gram():
        g = phi.T @ phi
        g[np.diag_indices_from(g)] += gamma
        np.linalg.cholesky(g)

    def step():
        v = (flat @ w).reshape(next_phi.shape[:-1]).max(axis=1)
        phi.T @ (rewards + v)

    return timed(gram) + H * min(timed(step) for _ in range(3))


def timed(fn):
    t0 = CLOCK()
    fn()
    return CLOCK() - t0


def fits(ds, names, pooled):
    from r2pvi import PEVI, R2PVI
    from r2pvi.algorithms import DRPVI

    makers = {
        "TV": lambda **k: R2PVI("tv", 0.3, beta=0.05, **k),
        "chi2": lambda **k: R2PVI("chi2", 1.0, beta=0.05, **k),
        "DRPVI": lambda **k: DRPVI(0.1, beta=0.05, **k),
        "PEVI": lambda **k: PEVI(beta=0.05, **k),
    }
    out = {}
    for name in names:
        out[name] = timed(lambda n=name: makers[n]().fit(ds))
    for name in pooled:
        out[name + " pooled"] = timed(lambda n=name: makers[n](time_homogeneous=True).fit(ds))
    return out


def run_case(case):
    t0 = CLOCK()
    if case.startswith("rbf"):
        K = int(case[3:])
        ds, d = dense_dataset(K, (4, 4, 6, 6))
        names, pooled = ["TV", "DRPVI", "chi2", "PEVI"], ["TV"]
    elif case.startswith("tiles"):
        K = int(case[5:])
        ds, d = sparse_dataset(K)
        names, pooled = ["TV", "DRPVI", "chi2", "PEVI"], []
    elif case == "act":
        return act_case()
    elif case == "solvers":
        return solvers_case()
    else:
        raise SystemExit(f"unknown case {case!r}")
    build = CLOCK() - t0
    phi, rewards, _, _ = ds.step(H // 2)
    primal, dual = step_floor(phi, rewards)
    res = {"case": case, "K": K, "d": d, "build_s": build, "floor_primal_s": H * primal,
           "floor_dual_s": H * dual, "floor_s": H * min(primal, dual)}
    if pooled:
        res["pooled floor_s"] = pooled_floor(ds)
    res.update({f"fit {k}": v for k, v in fits(ds, names, pooled).items()})
    res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return res


def solvers_case(Ks=(300, 1000, 3000), step=100):
    """One tile-coding step (d = 20,736) at several K: every way to get what a step needs —
    the ridge weights AND all of ``diag(Lambda^{-1})`` (the l1 penalty) — exactly:

    - ``used primal``: dense |U| x |U| Cholesky on the used features U (what r2pvi does when
      |U| <= K), weights and diagonal from ``L_U^{-1}``;
    - ``dual``: K x K Cholesky of the sparse product ``Psi Psi^T`` (r2pvi when |U| > K);
    - ``splu``: SciPy's SuperLU on the sparse d x d Gram matrix: weights by one solve, the
      diagonal by |U| solves (blocks of 512 unit vectors);
    - ``cg``: conjugate gradients (rtol 1e-12) for the weights only — the diagonal would take
      |U| more solves, so CG cannot serve the l1 penalty by itself.
    """
    fmap, d = tile_map()
    res = {"case": "solvers", "d": d}
    for K in Ks:
        states, actions, rewards = cartpole_episodes(K, 0)
        phi = sp.csr_matrix(fmap(states[:, step], actions[:, step]))
        res.update(_solvers_at(phi, rewards[:, step], f"K={K}"))
    return res


def _solvers_at(phi, y, label):
    import scipy.sparse.linalg as spl

    from r2pvi.duals import GramFactor

    d = phi.shape[1]
    used = np.unique(phi.indices)

    def factor(form):
        f = GramFactor(phi, 1.0, form=form)
        return f.regress(y), f.inverse_diagonal()

    def superlu():
        lu = spl.splu(sp.csc_matrix(phi.T @ phi + sp.identity(d)))
        w = lu.solve(phi.T @ y)
        diag = np.ones(d)
        for s in range(0, used.size, 512):
            c = used[s:s + 512]
            e = np.zeros((d, c.size))
            e[c, np.arange(c.size)] = 1.0
            diag[c] = lu.solve(e)[c, np.arange(c.size)]
        return w, diag

    def cg():
        op = spl.LinearOperator((d, d), matvec=lambda x: phi.T @ (phi @ x) + x)
        return spl.cg(op, phi.T @ y, rtol=1e-12, maxiter=10_000)[0]

    w_ref, diag_ref = factor("dual")
    res = {f"{label} used features": int(used.size)}
    for name, fn in (("used primal", lambda: factor("primal")), ("dual", lambda: factor("dual")),
                     ("splu", superlu)):
        w, diag = fn()
        assert np.allclose(w, w_ref, atol=1e-9) and np.allclose(diag, diag_ref, atol=1e-9)
        res[f"{label} {name} ms"] = 1e3 * min(timed(fn) for _ in range(3))
    assert np.allclose(cg(), w_ref, atol=1e-8)
    res[f"{label} cg (weights only) ms"] = 1e3 * min(timed(cg) for _ in range(3))
    return res


def act_case(n_states=2000):
    """Per-state act time at d = 450 (one state per call, as in a rollout)."""
    from r2pvi import PEVI, R2PVI

    ds, d = dense_dataset(300, (3, 3, 5, 5))
    fmap, _ = rbf_map((3, 3, 5, 5))
    rng = np.random.default_rng(1)
    obs = rng.uniform(LOW / 4, HIGH / 4, size=(n_states, 4))
    feats = np.stack([fmap(obs, np.full(n_states, a)) for a in range(A)], axis=1)
    res = {"case": "act", "d": d}
    for name, est in (("PEVI", PEVI(beta=0.05)), ("R2PVI-TV", R2PVI("tv", 0.3, beta=0.05))):
        est.fit(ds)
        t = timed(lambda e=est: [e.act(feats[i:i + 1], 10) for i in range(n_states)])
        res[f"act {name} ms/state"] = 1e3 * t / n_states
    res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return res


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+",
                        default=["act", "solvers", "rbf300", "rbf1000", "tiles300",
                                 "tiles1000"])
    parser.add_argument("--threads", type=int, default=1, help="BLAS threads per case")
    parser.add_argument("--wall", action="store_true", help="wall time instead of CPU time")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        global CLOCK
        if args.wall:
            CLOCK = time.perf_counter
        print(json.dumps(run_case(args.child)))
        return
    env = dict(os.environ, OPENBLAS_NUM_THREADS=str(args.threads),
               OMP_NUM_THREADS=str(args.threads), MKL_NUM_THREADS=str(args.threads))
    print(f"# {time.strftime('%Y-%m-%d %H:%M')} UTC, load {os.getloadavg()[0]:.1f}, "
          f"{args.threads} BLAS thread(s), H = {H}, "
          f"{'wall' if args.wall else 'CPU'} seconds")
    for case in args.cases:
        proc = subprocess.run([sys.executable, __file__, "--child", case]
                              + (["--wall"] if args.wall else []), env=env,
                              capture_output=True, text=True)
        if proc.returncode:
            print(f"{case}: failed\n{proc.stderr[-2000:]}")
            continue
        res = json.loads(proc.stdout.strip().splitlines()[-1])
        floor = res.get("floor_s")
        print(f"\n## {case}")
        for key, value in res.items():
            if key == "case":
                continue
            extra = ""
            if key.startswith("fit") and key.endswith("pooled") and res.get("pooled floor_s"):
                extra = f"   ({value / res['pooled floor_s']:.2f}x pooled floor)"
            elif key.startswith("fit") and floor:
                extra = f"   ({value / floor:.2f}x floor)"
            shown = f"{value:.3f}" if isinstance(value, float) else value
            print(f"  {key:28s} {shown}{extra}")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
