"""
Your own dataset from plain NumPy arrays
========================================

Everything r2pvi needs is four arrays of shape ``(K, H)`` — states, actions, rewards, next
states — and a feature map onto the probability simplex. Here the data come from a small
"cliff walk" simulated with NumPy: states 0..6 on a path, goal 6 (reward 1 per step there),
and a cliff (state 7, absorbing, worth 0). Action 0 walks (one step right with probability
0.8, else stays); action 1 jumps (two steps right with probability 0.8, else falls off the
cliff).
"""

# %%
# The arrays
# ----------
import matplotlib.pyplot as plt
import numpy as np

from r2pvi import PEVI, R2PVI, OfflineDataset

S, A, H, K = 8, 2, 6, 400
GOAL, CLIFF = 6, 7
rng = np.random.default_rng(0)


def step(s, a, rng):
    """Vectorized dynamics: next states for states ``s`` and actions ``a``."""
    u = rng.random(s.shape)
    walk = np.where(u < 0.8, np.minimum(s + 1, GOAL), s)
    jump = np.where(u < 0.8, np.minimum(s + 2, GOAL), CLIFF)
    nxt = np.where(a == 0, walk, jump)
    return np.where((s == GOAL) | (s == CLIFF), s, nxt)  # absorbing goal and cliff


states = np.zeros((K, H), dtype=int)
actions = rng.integers(A, size=(K, H))          # a uniform behaviour policy
next_states = np.zeros((K, H), dtype=int)
s = rng.integers(0, 4, size=K)                  # start somewhere in the first half
for h in range(H):
    states[:, h] = s
    s = step(s, actions[:, h], rng)
    next_states[:, h] = s
rewards = (states == GOAL).astype(float)

# %%
# Features and the dataset
# ------------------------
# One-hot features of (state, action) are on the simplex (d = S A = 16): the tabular case of
# a linear MDP. The cliff's value is known (0 for every action): ``next_values`` carries it,
# NaN elsewhere means "learn this value". Rewards are not given as parameters: with
# ``reward_weights=None`` the estimators regress them on the features.
features = np.eye(S * A)


def feature_map(s, a):
    return features[s * A + a]


next_values = np.where((next_states == CLIFF)[..., None], 0.0, np.nan) * np.ones(A)
data = OfflineDataset.from_transitions(states, actions, rewards, next_states, feature_map,
                                       n_actions=A, next_values=next_values)
print(data)

# %%
# Fit and look at the learned policies
# ------------------------------------
# R2PVI-KL lets an adversary reweight each transition's outcomes at a price ``lam * KL``:
# the jump's 20% chance of falling weighs more and more as ``lam`` shrinks.
estimators = {"PEVI": PEVI(beta=0.1), "R2PVI-KL, lam = 1": R2PVI("kl", 1.0, beta=0.1),
              "R2PVI-KL, lam = 0.1": R2PVI("kl", 0.1, beta=0.1)}
all_states = np.arange(S)
phi_all = np.stack([feature_map(all_states, np.full(S, a)) for a in range(A)], axis=1)

fig, axes = plt.subplots(1, len(estimators), figsize=(11, 3.2), constrained_layout=True,
                         sharey=True)
for ax, (name, est) in zip(axes, estimators.items(), strict=False):
    est.fit(data)
    jump = np.array([est.act(phi_all, h) for h in range(H)])[:, :GOAL]  # (H, path states)
    ax.imshow(jump, cmap="coolwarm", vmin=0, vmax=1, aspect="auto")
    for (h, s_), a in np.ndenumerate(jump):
        ax.text(s_, h, "jump" if a else "walk", ha="center", va="center", fontsize=7)
    ax.set_title(name, fontsize=10)
    ax.set_xlabel("state (goal = 6, not shown)")
axes[0].set_ylabel("step h")
fig.suptitle("Greedy action per step and state, learned from the arrays")
plt.show()

# %%
# The learned value of the start states, ``max_a Q_0(s, a)``: lower for smaller ``lam``,
# since the estimator accounts for an adversary who makes falls more likely.
for name, est in estimators.items():
    print(f"{name:<20}", np.round(est.q_values(phi_all[:4], 0).max(axis=1), 3))
