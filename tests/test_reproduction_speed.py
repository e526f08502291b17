"""The fast paths behind `r2pvi reproduce all` give the same numbers as the direct formulas.

Each test compares a fast path with an independent, literal implementation of what it
replaces (per-sample categorical draws, the dense hat-feature formula, the estimator's own
argmax, an uncached backward induction): equality is exact, not approximate.
"""

import warnings

import numpy as np
import pytest
from extras import require
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi import PEVI, R2PVI
from r2pvi.envs import AmericanPutOption, HardInstance, SimulatedLinearMDP
from r2pvi.envs._sampling import sample_categorical, sample_rows
from r2pvi.envs.policies import policy_table
from r2pvi.evaluation import robust_values
from r2pvi.evaluation.dynamic_programming import finite_backward, regularized_step


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(1, 5), m=st.sampled_from([1, 2, 3, 16, 17, 40]),
       n=st.integers(1, 300), zeros=st.floats(0.0, 0.9), seed=st.integers(0, 2**32 - 1))
def test_sample_rows_draws_what_per_sample_categorical_draws(rows, m, n, zeros, seed):
    rng = np.random.default_rng(seed)
    table = rng.random((rows, m)) * (rng.random((rows, m)) >= zeros)  # zero-mass categories
    table[:, rng.integers(m)] += 1e-3  # no all-zero row
    table /= table.sum(axis=1, keepdims=True)
    idx = rng.integers(rows, size=n)
    fast = sample_rows(table, idx, np.random.default_rng(seed + 1))
    slow = sample_categorical(table[idx], np.random.default_rng(seed + 1))
    np.testing.assert_array_equal(fast, slow)
    assert (table[idx, fast] > 0).all()  # never a zero-probability category


def _reference_simulate(env, K, policy, seed):
    """The per-sample simulation loop the fast one replaces: gather every sample's
    distribution, then draw (states, actions, rewards, next states)."""
    pi = policy_table(env, policy)
    rng = np.random.default_rng(seed)
    H = env.horizon
    out = [np.empty((K, H), dtype=np.int64) for _ in range(3)] + [np.empty((K, H))]
    s = sample_categorical(np.broadcast_to(env.initial, (K, env.n_states)), rng)
    for h in range(H):
        a = sample_categorical(pi[h, s], rng)
        nxt = sample_categorical(env.transitions[h, s, a], rng)
        out[0][:, h], out[1][:, h], out[2][:, h] = s, a, nxt
        out[3][:, h] = env.reward_table[h, s, a]
        if env.reward_noise > 0.0:
            out[3][:, h] += env.reward_noise * rng.standard_normal(K)
        s = nxt
    return out


def test_finite_mdp_simulation_and_dataset_match_the_per_sample_loop():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        hard = HardInstance.lower_bound_instance(2, 3, 1.0, 100, "kl", seed=4)
    for env, policy in ((SimulatedLinearMDP(), "uniform"), (hard, "behavior")):
        traj = env.simulate(500, policy, seed=7)
        ref = _reference_simulate(env, 500, policy, seed=7)
        for got, want in zip((traj.states, traj.actions, traj.next_states, traj.rewards), ref,
                             strict=True):
            np.testing.assert_array_equal(got, want)
        ds = env.make_dataset(*traj)
        np.testing.assert_array_equal(ds.phi, env.features(0)[ref[0], ref[1]])
        np.testing.assert_array_equal(ds.rewards, ref[3])


prices = st.one_of(st.floats(-50.0, 300.0), st.sampled_from([np.nan, np.inf, -np.inf, 0.0]))


@settings(max_examples=60, deadline=None)
@given(d=st.integers(1, 40), span=st.floats(1.0, 150.0), first=st.floats(0.0, 120.0),
       s=st.lists(prices, min_size=1, max_size=40), exact=st.booleans())
def test_put_option_hat_features_match_the_dense_formula(d, span, first, s, exact):
    env = AmericanPutOption(d=d, anchor_span=span, first_anchor=first)
    s = np.array(s, dtype=float)
    if exact:  # on and next to the anchors, where round-off decides the window
        s = np.concatenate([s, env.anchors, np.nextafter(env.anchors, np.inf),
                            np.nextafter(env.anchors, -np.inf), env.anchors + env.spacing])
    with np.errstate(invalid="ignore"):
        dense = np.maximum(0.0, 1.0 - np.abs(s[:, None] - env.anchors) / env.spacing)
    dense[np.isnan(s)] = 0.0
    np.testing.assert_array_equal(env.features(s), dense)
    both = env.phi_all(s)
    np.testing.assert_array_equal(both[:, 0], dense)
    assert not both[:, 1].any()


def test_put_option_decisions_are_the_estimators_argmax():
    env = AmericanPutOption()
    data = env.collect(60, seed=1)
    common = {"beta": 0.1, "reward_weights": np.zeros((env.H, env.d)), "r_max": env.r_max}
    grid = np.concatenate([np.linspace(60.0, 160.0, 5001), [np.nan, 100.0]])
    for est in (PEVI(**common).fit(data), R2PVI("tv", 1.0, **common).fit(data)):
        for h in (0, 7, env.H - 1):
            want = est.act(env.phi_all(grid), h, env.known_values(grid))
            np.testing.assert_array_equal(env.actions(est, h, grid), want)


def test_optimal_values_are_cached_per_environment_and_copied_out():
    env = SimulatedLinearMDP()
    Q, V = robust_values(env, "kl", 0.3)
    Q0, V0 = finite_backward(env, regularized_step("kl", 0.3))  # uncached
    np.testing.assert_array_equal(Q, Q0)
    np.testing.assert_array_equal(V, V0)
    V[:] = -1.0  # the caller's copy; the cache is untouched
    np.testing.assert_array_equal(robust_values(env, "kl", 0.3)[1], V0)
    other = robust_values(env.perturbed(1.0), "kl", 0.3)[1]  # another env: its own values
    assert not np.array_equal(other, V0)
    assert not np.array_equal(robust_values(env, "kl", 0.1)[1], V0)  # and another lam


def _rows(name):
    """Synthetic result rows of a figure (its plot reads only these keys)."""
    rng = np.random.default_rng(0)
    if name in ("fig1d", "va"):
        return [{"algorithm": a, "price_up": p, "replication": r, "value": float(rng.random())}
                for a in ("PEVI", "R2PVI") for p in (0.2, 0.6, 1.0) for r in range(3)]
    if name == "fig1a":
        return [{"xi_norm": x, "algorithm": a, "q": q, "replication": r, "kind": "R2PVI",
                 "value": float(rng.random())}
                for x in (0.3, 0.1) for a in ("PEVI", "R2PVI-TV") for q in (0.0, 0.5, 1.0)
                for r in range(3)]
    return [{"algorithm": a, "trajectories": k, "features": 30, "repeat": r,
             "value": float(rng.uniform(1e-3, 1.0))}  # fig2a: log axis, error bars
            for a in ("PEVI", "DRPVI") for k in (1000, 5000, 10000) for r in range(3)]


def _settings(name):
    from r2pvi.experiments.figures import FIGURES

    return {**FIGURES[name].defaults, "replications": 3, "repeats": 3, "xi_norms": [0.3, 0.1]}


def test_draw_plots_in_parallel_writes_every_plot(tmp_path):
    require("matplotlib")
    require("joblib")
    from r2pvi.experiments.reproduce import draw_plots

    done = [(name, _rows(name), _settings(name)) for name in ("fig1d", "va")]
    paths = draw_plots(done, tmp_path, jobs=2)
    assert list(paths) == ["fig1d", "va"]
    for name in ("fig1d", "va"):
        for ext in ("png", "pdf"):
            assert paths[name][ext] == tmp_path / f"{name}.{ext}"
            assert paths[name][ext].stat().st_size > 1000


@pytest.mark.parametrize("name", ["fig2a"])
def test_saved_png_is_what_savefig_draws(tmp_path, name):
    """Solving the layout once for both files leaves the PNG pixel for pixel unchanged."""
    require("matplotlib")
    import matplotlib.image as mpimg

    from r2pvi.experiments.figures import FIGURES
    from r2pvi.experiments.plotting import _pyplot, save_figure

    fig = FIGURES[name]
    plain = fig.plot(_rows(name), _settings(name))
    plain.savefig(tmp_path / "plain.png", dpi=130)
    _pyplot().close(plain)
    paths = save_figure(fig.plot(_rows(name), _settings(name)), tmp_path, name)
    assert paths["pdf"].stat().st_size > 1000
    np.testing.assert_array_equal(mpimg.imread(tmp_path / "plain.png"),
                                  mpimg.imread(paths["png"]))
