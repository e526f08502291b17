"""Roll policies out in any Gymnasium environment: collect episodes, or just their returns.

One rollout loop serves :func:`collect_episodes` and
:func:`r2pvi.evaluation.evaluate_policy`. It is

- **seeded per episode**: episode ``i`` resets the environment with its own seed and draws the
  policy's random numbers from its own generator, both from
  ``SeedSequence(seed).spawn(n_episodes)[i]``; so the episodes are the same whatever the
  number of parallel environments and their scheduling (tested: vectorized rollouts equal
  single-environment rollouts);
- **vectorized**: the policy acts on a batch of observations, one per sub-environment of a
  Gymnasium vector environment (``SyncVectorEnv``/``AsyncVectorEnv`` built from copies of
  ``env`` with ``n_envs``, or a vector environment you pass). A sub-environment that finishes
  is reset at once with the next episode's seed (``reset(options={"reset_mask": ...})``).
  Vector environments that cannot reset a subset with their own seeds (Gymnasium's
  vectorized ``CartPoleVectorEnv``) run in batches of ``num_envs`` episodes seeded once per
  batch: reproducible for a seed and a ``num_envs``, but not equal to single-environment
  rollouts.

Policies (a callable on a batch, an object with ``sample``, ``"uniform"``) are described in
:mod:`r2pvi.envs.rollout_policies`.
"""

from __future__ import annotations

import copy
import numbers
import sys
from collections import deque

import numpy as np

from ..data.episodes import Episode
from ._sampling import check_count
from .rollout_policies import as_policy_function

__all__ = ["collect_episodes", "run_episodes", "episode_seeds"]


def _require_gymnasium():
    try:
        import gymnasium
    except ImportError:
        raise ImportError(
            "rollouts in Gymnasium environments need gymnasium: pip install 'r2pvi[gym]'"
        ) from None
    return gymnasium


# ---------------------------------------------------------------------- seeding
def episode_seeds(seed, n_episodes: int):
    """``(env_seeds (n,) int, policy_rngs list)``: episode ``i``'s reset seed and generator.

    Both come from ``SeedSequence(seed).spawn(n_episodes)[i]`` (its two children), so an
    episode's randomness depends only on ``seed`` and ``i``.
    """
    if isinstance(seed, np.random.Generator):
        ss = np.random.SeedSequence(int(seed.integers(2**63)))
    elif isinstance(seed, np.random.SeedSequence):
        ss = seed
    elif seed is None or (isinstance(seed, numbers.Integral) and not isinstance(seed, bool)):
        ss = np.random.SeedSequence(seed)
    else:
        raise TypeError(
            f"seed must be None, an integer, a SeedSequence or a numpy Generator, got {seed!r}"
        )
    env_seeds = np.empty(n_episodes, dtype=np.int64)
    rngs = []
    for i, child in enumerate(ss.spawn(n_episodes)):
        env_ss, pol_ss = child.spawn(2)
        env_seeds[i] = int(env_ss.generate_state(1, np.uint32)[0])
        rngs.append(np.random.default_rng(pol_ss))
    return env_seeds, rngs


# ---------------------------------------------------------------------- vector envs
def _vector_env(env, n_envs, n_episodes):
    """``(vector_env, resets_subsets, owned)`` for ``env`` and the requested ``n_envs``.

    ``resets_subsets``: the vector env resets a subset of its sub-environments with their own
    seeds (``reset_mask``); ``owned``: built here, so closed after the run.
    """
    gymnasium = _require_gymnasium()
    from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv, VectorEnv

    if isinstance(env, VectorEnv):
        if n_envs is not None and n_envs != env.num_envs:
            raise ValueError(f"n_envs={n_envs} differs from the vector env's {env.num_envs}")
        return env, isinstance(env, SyncVectorEnv | AsyncVectorEnv), False
    if n_envs is not None:
        n_envs = check_count(n_envs, "n_envs")
    if isinstance(env, str):
        n = min(n_envs or 8, n_episodes)
        fns = [lambda: gymnasium.make(env)] * n
        return SyncVectorEnv(fns, autoreset_mode=AutoresetMode.DISABLED), True, True
    if isinstance(env, gymnasium.Env):
        n = min(n_envs or 1, n_episodes)
        replicas = [env] + [_replicate(env) for _ in range(n - 1)]
        fns = [(lambda e=e: e) for e in replicas]
        return SyncVectorEnv(fns, autoreset_mode=AutoresetMode.DISABLED), True, False
    if callable(env):
        n = min(n_envs or 1, n_episodes)
        return SyncVectorEnv([env] * n, autoreset_mode=AutoresetMode.DISABLED), True, True
    raise TypeError(
        "env must be a gymnasium.Env, a gymnasium vector env, a registered id or a factory "
        f"returning an env; got {type(env).__name__}"
    )


def _check_reset_options(venv, options: dict) -> None:
    """Refuse perturbation options that the environment would silently ignore."""
    from .perturbations import ACTION_NOISE, PARAMETERS

    names = {ACTION_NOISE}.union(*(set(t) for t in PARAMETERS.values()))
    asked = sorted(set(options) & names)
    first = getattr(venv, "envs", [None])[0]
    if not asked or first is None:
        return
    try:
        first.get_wrapper_attr("set_params")
    except AttributeError:
        raise ValueError(
            f"reset_options sets {asked}, but the environment does not read parameters at "
            "reset: wrap it in r2pvi.envs.perturbations.PerturbedEnv (or make_perturbed)"
        ) from None


def _replicate(env):
    try:
        return copy.deepcopy(env)
    except Exception as exc:  # noqa: BLE001 - any failure means: cannot copy this env
        raise ValueError(
            f"cannot copy {env} to run n_envs > 1 copies ({exc}); pass a factory "
            "(lambda: make_my_env()) or a gymnasium vector env instead"
        ) from None


# ---------------------------------------------------------------------- the rollout loop
def run_episodes(env, policy, n_episodes: int, *, seed=None, max_steps=None, n_envs=None,
                 record: bool = True, reset_options=None, progress=None):
    """Run ``n_episodes`` episodes of ``policy``: Episode objects (``record``) or returns.

    See :func:`collect_episodes` for the arguments. Returns a list of
    :class:`~r2pvi.episodes.Episode` when ``record`` is True, else the ``(n_episodes,)``
    array of undiscounted returns.
    """
    n_episodes = check_count(n_episodes, "n_episodes")
    if max_steps is not None:
        max_steps = check_count(max_steps, "max_steps")
    if reset_options is not None and not isinstance(reset_options, dict):
        raise TypeError(f"reset_options must be a dict or None, got {reset_options!r}")
    venv, per_episode, owned = _vector_env(env, n_envs, n_episodes)
    if reset_options:
        _check_reset_options(venv, reset_options)
    space = venv.single_action_space
    n_actions = int(space.n) if hasattr(space, "n") else None
    act = as_policy_function(policy, n_actions)
    seeds, rngs = episode_seeds(seed, n_episodes)
    bar = _progress_bar(progress, n_episodes)
    try:
        runner = _run_per_episode if per_episode else _run_batches
        out = runner(venv, act, seeds, rngs, max_steps, record, reset_options or {}, bar)
    finally:
        if bar is not None:
            bar.close()
        if owned:
            venv.close()
    return out


class _Recorder:
    """The growing data of the episode running in one sub-environment."""

    __slots__ = ("episode", "obs", "actions", "rewards", "t", "ret")

    def __init__(self, episode: int, obs, record: bool):
        self.episode = episode
        self.obs = [obs] if record else None
        self.actions, self.rewards = ([], []) if record else (None, None)
        self.t = 0
        self.ret = 0.0


def _finish(rec, seeds, terminated, truncated, record):
    if not record:
        return rec.ret
    T = rec.t
    term = np.zeros(T, dtype=bool)
    trunc = np.zeros(T, dtype=bool)
    if T:
        term[-1] = terminated
        trunc[-1] = truncated and not terminated
    return Episode(
        observations=np.stack(rec.obs), actions=np.asarray(rec.actions),
        rewards=np.asarray(rec.rewards, dtype=float), terminations=term, truncations=trunc,
        id=rec.episode, seed=int(seeds[rec.episode]),
    )


def _idle_action(space):
    """A fixed valid action for sub-environments with no episode left to run."""
    if hasattr(space, "n") and hasattr(space, "start"):
        return space.start
    return space.sample()


def _check_actions(actions, n: int, space=None):
    """The policy's actions for ``n`` observations, each checked to be an element of a
    ``Discrete`` action ``space`` (integers, or floats with integer values, in
    ``[start, start + n)``): a ``ValueError`` naming the action and the space, never the
    environment's bare assertion or a silent cast of 0.5 to 0."""
    a = np.asarray(actions)
    if a.shape != (n,):
        raise ValueError(
            f"the policy must return one action per observation, shape ({n},); got {a.shape}"
        )
    if space is None or not (hasattr(space, "n") and hasattr(space, "start")):
        return a  # not Discrete: the environment checks its own actions
    lo, hi = int(space.start), int(space.start) + int(space.n)
    if a.dtype.kind in "iu":
        bad = (a < lo) | (a >= hi)
    elif a.dtype.kind == "f":
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(a) | (a != np.round(a)) | (a < lo) | (a >= hi)
    else:
        bad = np.ones(n, bool)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"the policy returned action {getattr(a[i], 'item', lambda: a[i])()!r} (for "
            f"observation {i} of the batch), "
            f"which is not in the environment's action space {space}: actions must be "
            f"integers in [{lo}, {hi})")
    return a.astype(np.int64)


def _final_obs(info, i, fallback):
    if "final_obs" in info and info.get("_final_obs", np.zeros(i + 1, bool))[i]:
        return info["final_obs"][i]
    return fallback


def _advance(slots, rows, a, step, max_steps, record, seeds, results, bar) -> list:
    """Record one step of the episodes in ``slots[rows]``; returns the slots that finished."""
    nxt, rew, term, trunc, info = step
    finished = []
    for j, i in enumerate(rows):
        rec = slots[i]
        rec.t += 1
        rec.ret += float(rew[i])
        done = bool(term[i] or trunc[i])
        if record:
            rec.obs.append(_final_obs(info, i, nxt[i]) if done else nxt[i])
            rec.actions.append(a[j])
            rec.rewards.append(float(rew[i]))
        cut = max_steps is not None and rec.t >= max_steps
        if done or cut:
            results[rec.episode] = _finish(rec, seeds, bool(term[i]), bool(trunc[i]) or cut,
                                           record)
            finished.append(i)
            if bar is not None:
                bar.update(1)
    return finished


def _act(act, slots, rows, obs, rngs, space=None):
    h = np.array([slots[i].t for i in rows], dtype=np.int64)
    return _check_actions(act(h, obs[rows], [rngs[slots[i].episode] for i in rows]), len(rows),
                          space)


def _run_per_episode(venv, act, seeds, rngs, max_steps, record, options, bar):
    """Each sub-environment runs the next pending episode, reset with that episode's seed."""
    N = venv.num_envs
    pending = deque(range(len(seeds)))
    results: list = [None] * len(seeds)
    first = [pending.popleft() if pending else None for _ in range(N)]
    obs, _ = venv.reset(seed=[None if e is None else int(seeds[e]) for e in first],
                        options=dict(options) if options else None)
    slots = [None if e is None else _Recorder(e, obs[i], record) for i, e in enumerate(first)]
    idle_action = _idle_action(venv.single_action_space)
    while any(s is not None for s in slots):
        rows = [i for i, s in enumerate(slots) if s is not None]
        a = _act(act, slots, rows, obs, rngs, venv.single_action_space)
        actions = np.array([idle_action] * N)
        actions[rows] = a
        step = venv.step(actions)
        obs, term, trunc = step[0], step[2], step[3]
        reset = term | trunc  # idle sub-environments that ended must be reset too
        for i in _advance(slots, rows, a, step, max_steps, record, seeds, results, bar):
            slots[i] = None
            reset[i] = True
        if reset.any():
            starts = [pending.popleft() if r and pending and slots[i] is None else None
                      for i, r in enumerate(reset)]
            opts = dict(options)
            opts["reset_mask"] = np.asarray(reset, dtype=bool)
            obs, _ = venv.reset(seed=[None if e is None else int(seeds[e]) for e in starts],
                                options=opts)
            for i, e in enumerate(starts):
                if e is not None:
                    slots[i] = _Recorder(e, obs[i], record)
    return results if record else np.asarray(results, dtype=float)


def _run_batches(venv, act, seeds, rngs, max_steps, record, options, bar):
    """Vector envs without per-subset seeding: batches of ``num_envs`` episodes, one seed each
    (the first episode of every sub-environment is kept)."""
    N = venv.num_envs
    n = len(seeds)
    results: list = [None] * n
    for start in range(0, n, N):
        batch = list(range(start, min(start + N, n)))
        obs, _ = venv.reset(seed=int(seeds[start]), options=dict(options) if options else None)
        slots = [_Recorder(e, obs[i], record) for i, e in enumerate(batch)]
        live = list(range(len(batch)))
        while live:
            a = _act(act, slots, live, obs, rngs, venv.single_action_space)
            actions = np.zeros(N, dtype=np.int64)
            actions[live] = a
            step = venv.step(actions)
            obs = step[0]
            done = set(_advance(slots, live, a, step, max_steps, record, seeds, results, bar))
            live = [i for i in live if i not in done]
    return results if record else np.asarray(results, dtype=float)


def _progress_bar(progress, total):
    """A tqdm bar when asked (True), or by default when tqdm is installed and on a TTY."""
    if progress is None:
        progress = total >= 100 and hasattr(sys.stderr, "isatty") and sys.stderr.isatty()
    if not progress:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm(total=total, unit="episode", leave=False)


def collect_episodes(env, policy, n_episodes: int, *, seed=None, max_steps=None, n_envs=None,
                     reset_options=None, progress=None) -> list:
    """Collect ``n_episodes`` episodes of ``policy`` in a Gymnasium environment.

    Parameters
    ----------
    env : gymnasium.Env, gymnasium vector env, registered id or factory
        A single environment runs alone, or as ``n_envs`` copies (``copy.deepcopy``) in a
        ``SyncVectorEnv``; an id or a factory builds ``n_envs`` environments (8 for an id by
        default); a vector environment is used as is (see the module docstring).
    policy : callable, policy object or "uniform"
        ``policy(h, observations) -> actions`` on a batch, or an object with
        ``sample(h, observations, rngs)`` (:class:`EpsilonGreedy`, :class:`UniformPolicy`),
        or a fitted estimator's ``as_policy(feature_map)``.
    n_episodes : int
    seed : int, SeedSequence or Generator, optional
        Episode ``i`` uses ``SeedSequence(seed).spawn(n_episodes)[i]`` (reset seed and the
        policy's random numbers): the result does not depend on ``n_envs``.
    max_steps : int, optional
        Cut episodes after this many steps (marked truncated); None relies on the
        environment's own time limit.
    n_envs : int, optional
        Number of parallel sub-environments.
    reset_options : dict, optional
        Passed to every ``reset`` (RRLS-style perturbations: ``{"gravity": 12.0}``).
    progress : bool, optional
        A tqdm progress bar; None shows one on a terminal for 100 episodes or more.

    Returns
    -------
    list of :class:`~r2pvi.episodes.Episode`
        In episode order, with Minari's fields (``observations`` T+1, ``actions``,
        ``rewards``, ``terminations``, ``truncations``), ready for
        :meth:`r2pvi.OfflineDataset.from_episodes`.

    Examples
    --------
    >>> import gymnasium as gym
    >>> from r2pvi.envs import collect_episodes
    >>> eps = collect_episodes(gym.make("CartPole-v1"), "uniform", 3, seed=0)
    >>> [ep.observations.shape[0] == len(ep) + 1 for ep in eps], bool(eps[0].terminations[-1])
    ([True, True, True], True)
    """
    return run_episodes(env, policy, n_episodes, seed=seed, max_steps=max_steps,
                        n_envs=n_envs, record=True, reset_options=reset_options,
                        progress=progress)
