"""What R2PVI-chi2 and DRPVI pay beyond R2PVI-TV, part by part (issue 12: <= 3x the floor).

Both duals maximize over every sorted value of V_{h+1} by a branch and bound over blocks of
16 sorted values (``r2pvi.duals.piecewise``). Its unavoidable part is one sort of the K
values and the block sums of the features in sorted order (a gather of the (K, d) rows in
sorted order, three moments per block, Lambda^-1); the rest is the bounds and the exact
refinement of the (factor, block) pairs that may hold the maximum.

Each estimator is timed as usual and with one part of every step handed over for free (its
result on this exact data, computed in a first fit): the sort; the sorted block sums (sort
included); the whole dual (then the fit does what R2PVI-TV does: next-state values, Gram
matrices, one regression). The differences are what the parts cost inside a fit. CPU time
of the process, one BLAS thread, every variant fitted once per round, round-robin; the
minimum and the median over the rounds.

    python benchmarks/bench_sort_floor.py                # K=10000, d=30, H=20, 30 rounds
    python benchmarks/bench_sort_floor.py --rounds 60 --K 20000
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from bench_fit import estimators, floor_fit, forget_grams, make_dataset

from r2pvi._threads import limit_blas
from r2pvi.algorithms.drpvi import TVBallRule
from r2pvi.algorithms.r2pvi import Chi2Rule
from r2pvi.duals import RidgeExpectation
from r2pvi.duals import operator as operator_module
from r2pvi.duals.sorting import SortedBlocks, fine_blocks, group_sums

_SORT = operator_module.sort_breakpoints
_BLOCKS = RidgeExpectation.sorted_blocks
_RULES = {rule: rule.__call__ for rule in (Chi2Rule, TVBallRule)}


def _key(v):
    return (v.size, float(v[0]), float(v[-1]), float(np.sum(v)))


class Given:
    """Hands over precomputed results of one part (None: nothing handed over)."""

    def __init__(self):
        self.part, self.cache = None, {}

    def install(self):
        given = self

        def sort_breakpoints(v, extra=()):
            if given.part != "sort":
                return _SORT(v, extra)
            k = ("sort", _key(v), tuple(extra))
            if k not in given.cache:
                given.cache[k] = tuple(np.copy(x) if isinstance(x, np.ndarray) else x
                                       for x in _SORT(v, extra))
            return given.cache[k]

        def sorted_blocks(self, v, breakpoints_extra=(), moments=3, group=1):
            if given.part != "blocks":
                return _BLOCKS(self, v, breakpoints_extra, moments, group)
            self.phi  # noqa: B018 - the Gram matrix, as the full fit forms it here
            k = ("blocks", _key(v), tuple(breakpoints_extra), moments)
            if k not in given.cache:
                # the sums of every block of 16 (group 1), copied: the buffers are reused
                sb = _BLOCKS(self, v, breakpoints_extra, moments)
                arrays = [np.copy(x) for x in (sb.alphas, sb.sums, sb.sabs)]
                # the exact pair weights as the operator forms them, from a copy of the
                # sorted rows (its buffer is reused by the next step)
                rows = self._sorted_features(v, breakpoints_extra)[1]
                x3 = rows.reshape(-1, 16, self.n_dims).copy()
                gram_inv = self.chol_inverse.T @ self.chol_inverse
                given.cache[k] = (arrays, sb.m, x3, gram_inv)
            (alphas, sums, sabs), m, x3, gram_inv = given.cache[k]

            def fine(rows, blocks):
                r, idx = rows[:, None], fine_blocks(blocks, group, sabs.shape[1])
                return sums[:, r, idx], sabs[r, idx]

            def pairs(rows, blocks):
                return np.matmul(x3[blocks], gram_inv[rows][:, :, None])[:, :, 0]

            return SortedBlocks(alphas, m, group, group_sums(sums, group, axis=2),
                                group_sums(sabs, group, axis=1), fine, pairs)

        def rule_call(rule_cls):
            def call(self, E, v, ctx):
                if given.part != "dual":
                    return _RULES[rule_cls](self, E, v, ctx)
                k = ("dual", rule_cls.__name__, ctx.h, _key(v))
                if k not in given.cache:
                    given.cache[k] = _RULES[rule_cls](self, E, v, ctx)
                return given.cache[k].copy()
            return call

        operator_module.sort_breakpoints = sort_breakpoints
        RidgeExpectation.sorted_blocks = sorted_blocks
        for rule_cls in _RULES:
            rule_cls.__call__ = rule_call(rule_cls)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--K", type=int, default=10_000)
    ap.add_argument("--d", type=int, default=30)
    ap.add_argument("--H", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=30)
    args = ap.parse_args(argv)
    ds, theta = make_dataset(args.K, args.H, args.d)
    ests = estimators(theta)
    given = Given()
    given.install()
    parts = (None, "sort", "blocks", "dual")
    fns = {("floor", None): lambda: floor_fit(ds),
           ("R2PVI-TV", None): lambda: ests["R2PVI-TV"].fit(forget_grams(ds))}
    for name in ("R2PVI-chi2", "DRPVI"):
        for part in parts:
            fns[(name, part)] = lambda name=name: ests[name].fit(forget_grams(ds))
    times = {k: [] for k in fns}
    weights = {}
    with limit_blas():
        for (_name, part), fn in fns.items():  # warm-up; fills the cache of given results
            given.part = part
            fn()
        for _ in range(args.rounds):
            for (name, part), fn in fns.items():
                given.part = part
                t0 = time.process_time()
                out = fn()
                times[(name, part)].append(time.process_time() - t0)
                if part in (None, "sort", "blocks") and name != "floor":
                    weights.setdefault(name, []).append(out.weights_)
    given.part = None
    lo = {k: min(t) for k, t in times.items()}
    med = {k: statistics.median(t) for k, t in times.items()}
    print(f"K={args.K} d={args.d} H={args.H} A=2; CPU time, min / median of {args.rounds} "
          "rounds; x = / floor (min / median)")
    label = {None: "full fit", "sort": "sort given", "blocks": "block sums given",
             "dual": "dual given"}
    for (name, part) in fns:
        k = (name, part)
        print(f"{name:<11s} {label[part]:<17s} {lo[k] * 1e3:7.1f} / {med[k] * 1e3:7.1f} ms "
              f"{lo[k] / lo[('floor', None)]:5.2f}x / {med[k] / med[('floor', None)]:5.2f}x")
    for name in ("R2PVI-chi2", "DRPVI"):
        full, srt = lo[(name, None)], lo[(name, "sort")]
        blocks, dual = lo[(name, "blocks")], lo[(name, "dual")]
        fl = lo[("floor", None)]
        print(f"{name}: the sort {(full - srt) * 1e3:.1f} ms ({(full - srt) / fl:.2f}x floor), "
              f"sort + block sums {(full - blocks) * 1e3:.1f} ms ({(full - blocks) / fl:.2f}x), "
              f"the rest of the dual {(blocks - dual) * 1e3:.1f} ms ({(blocks - dual) / fl:.2f}x)"
              " (minima)")
        diff = max(np.abs(w - weights[name][0]).max() for w in weights[name])
        print(f"{name}: given parts change the weights by at most {diff:.1e}")


if __name__ == "__main__":
    main()
