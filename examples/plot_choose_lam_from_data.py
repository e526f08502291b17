"""
Choosing lam from data alone
============================

Without a simulator, ``lam`` is chosen by cross-validation over whole trajectories of the
data: every estimator has a ``score``, and an :class:`~r2pvi.OfflineDataset` splits by
trajectory, so scikit-learn's ``GridSearchCV`` works as it is. Which score to trust matters
more than the search:

- ``Scorer("model", feature_map=fmap)``: each candidate's greedy policy simulated in the
  nearest-neighbour model of the held-out episodes (each step takes the change of state of
  the nearest held-out transition of the policy's action; a rollout that leaves the data
  halts with value 0). An estimate of the return along the policy's *own* states: the
  score to select a policy by. In the user guide's selection experiment it picked the
  best configuration on CartPole and on Acrobot; on MountainCar its three best candidates
  tied within the spread of their fold scores - read the error bars below before trusting
  a pick.
- ``Scorer("fqe", evaluation_map=..., gamma=0.01)``: fitted-Q evaluation of each
  candidate's greedy policy on the held-out trajectories, all candidates evaluated on one
  richer feature map (here ``NormalizedRBF(n_centers=4)``, ``d = 512``) with a small ridge.
  It ranks CartPole's candidates, but it regresses on the data's states: on Acrobot it
  rates a policy that never reaches the goal first.
- ``Scorer("bellman")``: minus the held-out Bellman residual of the fitted ``Q``. It checks
  the fit, not the policy, and rewards small values: it ranks ``lam`` right here, but it
  also prefers an estimator whose ``Q`` is shrunk to ~0 by a huge ridge (see the user
  guide's model-selection page).

The data: 300 episodes of the epsilon-greedy (0.3) LQR expert in the noisy CartPole; R2PVI-TV
on ``NormalizedRBF(n_centers=3)`` features (pooled steps) at five ``lam``. The truth, for
comparison only: each refitted policy's return on the CartPole test grid (nominal, and the
mean over the force, gravity and pole-length sweeps).
"""

# %%
import warnings

import matplotlib.pyplot as plt
import numpy as np
from sklearn.model_selection import GridSearchCV, KFold

from r2pvi import R2PVI, OfflineDataset
from r2pvi.algorithms import Scorer
from r2pvi.envs import EpsilonGreedy, collect_episodes, evaluate_cartpole_grid
from r2pvi.envs.experts import CartPoleLQR
from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv
from r2pvi.episodes import episode_observations
from r2pvi.experiments.plotting import cv_score_panels, returns_panel
from r2pvi.features import NormalizedRBF, cross_actions

warnings.simplefilter("ignore")  # sklearn's and the fits' notes are not the point here
episodes = collect_episodes(NoisyCartPoleEnv(), EpsilonGreedy(CartPoleLQR(), 0.3, 2), 300,
                            seed=1, n_envs=50)
observations = episode_observations(episodes)
fmap = cross_actions(NormalizedRBF(n_centers=3).fit(observations), 2)
data = OfflineDataset.from_episodes(episodes, fmap, 2, horizon=200)
evaluation_map = cross_actions(NormalizedRBF(n_centers=4).fit(observations), 2)

lams = [0.03, 0.1, 0.3, 1.0, 3.0]
scoring = {"model": Scorer("model", feature_map=fmap),
           "fqe": Scorer("fqe", evaluation_map=evaluation_map, gamma=0.01),
           "bellman": Scorer("bellman")}
search = GridSearchCV(R2PVI("tv", beta=0.1, r_max=1.0), {"lam": lams}, scoring=scoring,
                      refit="model", cv=KFold(3, shuffle=True, random_state=0)).fit(data)
print("chosen by the model score:", search.best_params_)

# %%
# The truth, for comparison: each lam refitted on all the data, tested on the grid
truth = []
for lam in lams:
    result = evaluate_cartpole_grid(R2PVI("tv", lam, beta=0.1).fit(data).as_policy(fmap))
    nominal = result.mean[(result.parameter == "force_mag") & (result.p == 0.0)][0]
    truth.append((nominal, result.mean.mean()))
truth = np.array(truth)

# %%
# Scores (left, from the data alone) and returns (right, from the test environments)
# ----------------------------------------------------------------------------------
res = search.cv_results_
fig, axes = plt.subplots(1, 4, figsize=(15, 3.6), constrained_layout=True)
cv_score_panels(axes[:3], lams, res, {"model": "neighbour-model return (rewards)",
                                      "fqe": "FQE on one evaluation map (rewards)",
                                      "bellman": "minus the Bellman residual"})
returns_panel(axes[3], lams, {"nominal return": truth[:, 0],
                              "mean over the sweeps": truth[:, 1]},
              search.best_params_["lam"], "true returns (test environments)",
              chosen_label="chosen by the model score")
fig.suptitle("R2PVI-TV on 300 noisy CartPole episodes: lam by trajectory cross-validation")
plt.show()
