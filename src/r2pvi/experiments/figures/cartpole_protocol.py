"""``r2pvi reproduce cartpole``: the noisy CartPole protocol of RFQI / RFZI, both fit forms.

The protocol of robust offline RL papers on CartPole (Panaganti et al. 2022), as the library
implements it (:mod:`r2pvi.envs.noisy_cartpole`):

1. **environment**: :class:`~r2pvi.envs.noisy_cartpole_gym.NoisyCartPoleEnv`, Gymnasium's
   CartPole with dynamics noise ``sigma = 0.1``, ``theta ~ U(-0.2, 0.2)`` at reset, reward
   1 per step (the failing one included) and 200 steps;
2. **data**: ``episodes`` episodes of the epsilon-greedy (``epsilon = 0.3``) LQR expert
   (:class:`~r2pvi.envs.experts.CartPoleLQR`) in the nominal environment; one dataset per
   replication, each from its own ``SeedSequence`` child;
3. **features**: a normalized Gaussian RBF grid (``centers`` per dimension) over the
   observations of the data, crossed with the 2 actions (``d = 2 centers^4``: 162);
4. **estimators**, all on the same data and features, each in the pooled form
   (``time_homogeneous=True``: one regression over every transition) and in the paper's
   per-step form: PEVI, R2PVI with each divergence and each ``lam``, DRPVI with each
   ``rho``; DRVI-L with each of ``drvil_rhos`` when ``estimators`` lists it (its pooled fit
   is the slowest: not in the default run);
5. **test**: every learned policy, the expert and the behaviour policy on the published grid
   (:func:`~r2pvi.envs.evaluate_cartpole_grid`: force_mag and pole length ``x (1 + p)``,
   ``p = -0.8 .. 3.6``; gravity ``p = -3 .. 2.5``; 36 points), ``test_episodes`` episodes a
   point with common random numbers (the same episodes for every policy of a dataset).

Rows: ``quantity = "average return"``, one per dataset x estimator x form x grid point
(``value`` the mean return, ``stderr`` its standard error over the test episodes, ``std``
their standard deviation); ``quantity = "fit time"``, one per dataset x estimator x form
(``value`` CPU seconds of the fit, ``wall`` its wall-clock seconds, and what the fit saw:
``implicit_discount``, ``steps_without_absorbing``, the ``warnings`` it raised).

Nothing here looks at the test grid to choose ``lam`` or ``rho``: every member of every
grid is reported (the plot shows, per family, the member with the best grid mean, and says
so; the table has them all).
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from ..runner import Task
from .cartpole_report import plot, table
from .common import Figure, make_estimator

__all__ = ["CARTPOLE", "DEFAULTS", "FORMS", "FAMILIES", "estimators", "protocol_dataset",
           "replication", "check_settings"]

#: The fit forms: ``time_homogeneous`` of each.
FORMS = {"pooled": True, "per-step": False}
#: Estimator families a run may include (``estimators`` setting).
FAMILIES = ("PEVI", "R2PVI", "DRPVI", "DRVI-L")

DEFAULTS = {
    "episodes": 1000,          # the documented larger setting: --set episodes=5000
    "replications": 3,
    "epsilon": 0.3,
    "centers": 3,
    "beta": 0.1,
    "gamma": 1.0,
    "penalty": "l1",
    "forms": ["pooled", "per-step"],
    "estimators": ["PEVI", "R2PVI", "DRPVI"],   # add "DRVI-L" (slow pooled fits)
    "divergences": ["tv", "kl", "chi2"],
    "lams": [0.1, 1.0, 10.0],
    "rhos": [0.05, 0.2],       # DRPVI's TV-ball radii
    "drvil_rhos": [0.1],       # DRVI-L's KL-ball radii (when "DRVI-L" is an estimator)
    "test_episodes": 20,
    "references": True,
}


def estimators(s: dict) -> list[tuple[str, str, str, float | None, str]]:
    """``(label, family, kind, param, divergence)`` of every estimator of the run."""
    fams = s["estimators"]
    out = []
    if "PEVI" in fams:
        out.append(("PEVI", "PEVI", "PEVI", None, "none"))
    if "R2PVI" in fams:
        for div in s["divergences"]:
            family = f"R2PVI-{'chi2' if div == 'chi2' else div.upper()}"
            out += [(f"{family} lam={lam:g}", family, "R2PVI", float(lam), div)
                    for lam in s["lams"]]
    if "DRPVI" in fams:
        out += [(f"DRPVI rho={rho:g}", "DRPVI", "DRPVI", float(rho), "tv") for rho in s["rhos"]]
    if "DRVI-L" in fams:
        out += [(f"DRVI-L rho={rho:g}", "DRVI-L", "DRVI-L", float(rho), "kl")
                for rho in s["drvil_rhos"]]
    return out


def _seed_int(seq: np.random.SeedSequence) -> int:
    return int(seq.generate_state(1, np.uint32)[0])


def protocol_dataset(seq, s):
    """Collect the behaviour episodes and build the features and the dataset.

    Parameters
    ----------
    seq : SeedSequence
        Seeds the episodes (episode ``i`` uses child ``i``).
    s : dict
        Settings: ``episodes``, ``epsilon``, ``centers``.

    Returns
    -------
    tuple
        ``(episodes, feature_map, dataset, expert, behaviour)``.
    """
    from ...data import OfflineDataset
    from ...data.episodes import episode_observations
    from ...envs import EpsilonGreedy, collect_episodes
    from ...envs.experts import CartPoleLQR
    from ...envs.noisy_cartpole import MAX_STEPS
    from ...envs.noisy_cartpole_gym import NoisyCartPoleEnv
    from ...features import NormalizedRBF, cross_actions

    expert = CartPoleLQR()
    behaviour = EpsilonGreedy(expert, s["epsilon"], 2)
    n = s["episodes"]
    episodes = collect_episodes(NoisyCartPoleEnv(), behaviour, n, seed=seq,
                                n_envs=min(n, 50), progress=False)
    fmap = cross_actions(NormalizedRBF(n_centers=s["centers"]).fit(
        episode_observations(episodes)), 2)
    data = OfflineDataset.from_episodes(episodes, fmap, 2, horizon=MAX_STEPS)
    return episodes, fmap, data, expert, behaviour


def _fit(est, data) -> dict:
    """Fit ``est``; the fit's CPU and wall seconds and what its fit report saw."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        c0, t0 = time.process_time(), time.perf_counter()
        est.fit(data)
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    report = getattr(est, "fit_report_", None)
    discount = getattr(report, "implicit_discount", None)
    empty = getattr(report, "steps_without_absorbing", None)
    return {"value": cpu, "wall": wall,
            "implicit_discount": float("nan") if discount is None else discount,
            "steps_without_absorbing": -1 if empty is None else int(empty),
            "warnings": " ".join(sorted({w.category.__name__ for w in caught}))}


def replication(seq, *, replication, settings):
    """One dataset: collect, build features, fit every estimator in every form, test every
    policy (and the references) on the 36-point grid."""
    from ...envs import evaluate_cartpole_grid

    s = settings
    data_seq, test_seq = seq.spawn(2)
    episodes, fmap, data, expert, behaviour = protocol_dataset(data_seq, s)
    base = {"replication": replication, "episodes": s["episodes"],
            "transitions": int(sum(len(e) for e in episodes)), "n_features": data.n_features,
            "data_return": float(np.mean([e.total_reward for e in episodes]))}
    common = {"beta": s["beta"], "gamma": s["gamma"], "penalty": s["penalty"], "r_max": 1.0}
    rows, policies = [], []
    for label, family, kind, param, divergence in estimators(s):
        for form in s["forms"]:
            est = make_estimator(kind, param, divergence=divergence, **common)
            est.set_params(time_homogeneous=FORMS[form])
            who = {"estimator": label, "family": family, "kind": kind, "param": param,
                   "divergence": divergence, "form": form}
            rows.append({**base, **who, "parameter": "none", "p": 0.0, "parameter_value":
                         float("nan"), "quantity": "fit time", "unit": "CPU s",
                         **_fit(est, data), "stderr": float("nan")})
            policies.append((who, est.as_policy(fmap)))
    if s["references"]:
        for label, family, policy in (("expert (LQR)", "expert", expert),
                                      (f"behaviour (eps={s['epsilon']:g})", "behaviour",
                                       behaviour)):
            who = {"estimator": label, "family": family, "kind": "reference",
                   "param": None, "divergence": "none", "form": "reference"}
            policies.append((who, policy))
    test_seed = _seed_int(test_seq)   # the same test episodes for every policy
    for who, policy in policies:
        grid = evaluate_cartpole_grid(policy, n_episodes=s["test_episodes"], seed=test_seed)
        for point in grid.rows():
            rows.append({**base, **who, "parameter": point["parameter"], "p": point["p"],
                         "parameter_value": point["value"], "quantity": "average return",
                         "unit": "return", "value": point["mean"], "stderr": point["se"],
                         "std": point["std"]})
    return rows


def check_settings(s: dict) -> None:
    """Raise ``ValueError`` when ``forms``, ``estimators``, ``divergences``, ``lams``,
    ``rhos`` or ``drvil_rhos`` list a value twice (two identical fits). Ranges and names
    are checked before, with every figure's settings
    (:func:`r2pvi.experiments.config.check_settings`)."""
    for key in ("forms", "estimators", "divergences", "lams", "rhos", "drvil_rhos"):
        if len(set(s[key])) != len(s[key]):
            raise ValueError(f"cartpole: setting {key!r} lists a value twice: {s[key]}; "
                             "give each once")


def _tasks(s: dict) -> list[Task]:
    check_settings(s)
    cost = 1.0 + len(estimators(s)) * len(s["forms"]) * s["episodes"] / 1000
    return [Task(replication, {"replication": r, "settings": s}, label=f"cartpole rep={r}",
                 cost=cost) for r in range(s["replications"])]


CARTPOLE = Figure(
    "cartpole",
    "Noisy CartPole (RFQI protocol): PEVI, R2PVI-TV/KL/chi2, DRPVI and DRVI-L learned from "
    "eps-greedy LQR data, pooled and per-step fits side by side, tested on the published "
    "36-point grid of force, gravity and pole length.",
    DEFAULTS, _tasks, plot, table, plot_cost=2.0,
)
