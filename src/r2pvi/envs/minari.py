"""Export offline datasets to Minari's format and import them back (optional extra ``minari``).

:func:`to_minari` writes a Minari dataset directory (``<root>/<dataset_id>/data`` with
``metadata.json`` and the episode storage, HDF5 by default) straight from the dataset's
episode buffers: no network, no hub, no data collector. Each trajectory is one episode
whose observations are the Gymnasium observations of :mod:`r2pvi.envs.gym` (state indices,
or prices), with ``truncated=True`` at the horizon and ``terminated=True`` when the put
option is exercised. The Gymnasium spec is recorded when the environment's parameters are
JSON-friendly, so ``MinariDataset.recover_environment()`` rebuilds the environment.

:func:`from_minari` reads such a dataset (a :class:`minari.MinariDataset`, a local dataset
id or a directory) and rebuilds the :class:`~r2pvi.OfflineDataset` through the
environment's features and known values.

This module imports without Minari installed; using it then raises an ImportError that
names the extra.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..data import OfflineDataset
from .finite import FiniteLinearMDP
from .put_option import EXERCISE, AmericanPutOption

__all__ = ["to_minari", "from_minari", "episodes_to_minari"]

MINARI_FORMAT_TAG = "r2pvi.envs.minari/1"


def _require_minari():
    try:
        import gymnasium  # noqa: F401
        import minari
    except ImportError:
        raise ImportError(
            "Minari export/import needs minari and gymnasium: pip install 'r2pvi[minari]' "
            "(or pip install 'minari[hdf5]' gymnasium)"
        ) from None
    return minari


def _check_env(env):
    if not isinstance(env, FiniteLinearMDP | AmericanPutOption):
        raise TypeError(
            "env must be an r2pvi environment (FiniteLinearMDP, SimulatedLinearMDP, "
            f"HardInstance or AmericanPutOption), got {type(env).__name__}"
        )


def to_minari(dataset: OfflineDataset, env, dataset_id: str, *, root=None,
              data_format: str = "hdf5", author=None, author_email=None, description=None,
              algorithm_name=None, code_permalink=None):
    """Write ``dataset`` as the Minari dataset ``dataset_id``.

    Parameters
    ----------
    dataset : OfflineDataset
        A dataset that keeps its states and actions (``env.collect(...)``, or loaded back
        from a file written by ``save``).
    env : FiniteLinearMDP or AmericanPutOption
        The environment the data come from (observation/action spaces, Gymnasium spec).
    dataset_id : str
        Minari id, ``(namespace/)(env_name/)dataset_name-v(version)``.
    root : path, optional
        Directory holding Minari datasets; None uses Minari's own root
        (``MINARI_DATASETS_PATH`` or ``~/.minari/datasets``). The dataset is written to
        ``root/dataset_id/data``, exactly where ``minari.load_dataset`` looks.
    data_format : {"hdf5", "arrow"}, default "hdf5"
    author, author_email, description, algorithm_name, code_permalink : optional
        Minari metadata (``algorithm_name`` defaults to the behaviour policy's name).

    Returns
    -------
    minari.MinariDataset

    Examples
    --------
    >>> import tempfile
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> from r2pvi.envs.minari import from_minari, to_minari
    >>> env = SimulatedLinearMDP()
    >>> ds = env.collect(20, seed=0)
    >>> with tempfile.TemporaryDirectory() as root:                         # doctest: +SKIP
    ...     md = to_minari(ds, env, "r2pvi/simulated/uniform-v0", root=root)
    ...     back = from_minari(md, env)
    ...     md.total_episodes, bool((back.phi == ds.phi).all())
    (20, True)
    """
    minari = _require_minari()
    from minari.data_collector.episode_buffer import EpisodeBuffer
    from minari.dataset.minari_dataset import MinariDataset, parse_dataset_id
    from minari.dataset.minari_storage import MinariStorage

    from .gym import as_gymnasium_env

    if not isinstance(dataset, OfflineDataset):
        raise TypeError(f"dataset must be an r2pvi.OfflineDataset, got {type(dataset).__name__}")
    _check_env(env)
    if not isinstance(dataset_id, str):
        raise TypeError(f"dataset_id must be a string, got {dataset_id!r}")
    parse_dataset_id(dataset_id)  # raises a ValueError naming the expected syntax
    states, actions, next_states = dataset.states, dataset.actions, dataset.next_states
    if states is None or actions is None or next_states is None:
        raise ValueError(
            "dataset has no states and actions (it was built from features only): export a "
            "dataset collected with env.collect(...) or built with from_transitions"
        )
    rebuilt = env.make_dataset(states, actions, dataset.rewards, next_states)
    if rebuilt.phi.shape != dataset.phi.shape or not np.allclose(rebuilt.phi, dataset.phi):
        raise ValueError(
            "dataset's features do not match env's features at its states: pass the "
            "environment the data were collected in"
        )
    gym_env = as_gymnasium_env(env)
    if root is None:
        from minari.storage.datasets_root_dir import get_dataset_path

        data_path = Path(get_dataset_path(dataset_id)) / "data"
    else:
        # absolute: Minari's size bookkeeping breaks on relative paths
        data_path = Path(os.fspath(root)).resolve() / dataset_id / "data"
    if data_path.exists():
        raise ValueError(
            f"a Minari dataset already exists at {data_path.parent}: choose another "
            "dataset_id (bump its version) or delete it"
        )
    data_path.mkdir(parents=True)
    storage = MinariStorage.new(
        data_path,
        observation_space=gym_env.observation_space,
        action_space=gym_env.action_space,
        env_spec=gym_env.spec,
        data_format=data_format,
    )
    meta = {
        "dataset_id": dataset_id,
        "minari_version": minari.__version__,
        "algorithm_name": algorithm_name or "r2pvi behaviour policy",
        "r2pvi_format": MINARI_FORMAT_TAG,
        "r2pvi_env": type(env).__name__,
    }
    for key, value in (("author", author), ("author_email", author_email)):
        if value is not None:
            meta[key] = {value} if isinstance(value, str) else set(value)
    if description is not None:
        meta["description"] = description
    if code_permalink is not None:
        meta["code_permalink"] = code_permalink
    storage.update_metadata(meta)
    storage.update_episodes(_episode_buffers(env, states, actions, dataset.rewards,
                                             next_states, EpisodeBuffer))
    return MinariDataset(storage)


def _episode_buffers(env, states, actions, rewards, next_states, EpisodeBuffer):
    H = states.shape[1]
    put = isinstance(env, AmericanPutOption)
    for k in range(states.shape[0]):
        length = H
        terminated = False
        if put:
            ex = np.flatnonzero(actions[k] == EXERCISE)
            if ex.size:
                length, terminated = int(ex[0]) + 1, True
        obs = np.append(states[k, :length], states[k, length - 1] if terminated
                        else next_states[k, length - 1])
        obs = obs[:, None].astype(np.float64) if put else obs.astype(np.int64)
        term = np.zeros(length, dtype=bool)
        trunc = np.zeros(length, dtype=bool)
        (term if terminated else trunc)[-1] = True
        yield EpisodeBuffer(
            id=k,
            observations=obs,
            actions=np.asarray(actions[k, :length], dtype=np.int64),
            rewards=list(np.asarray(rewards[k, :length], dtype=float)),
            terminations=list(term),
            truncations=list(trunc),
            infos={},
        )


def episodes_to_minari(episodes, dataset_id: str, env, *, root=None, **metadata):
    """Write episodes (e.g. from :func:`r2pvi.envs.collect_episodes`) as a Minari dataset.

    Uses Minari's own ``create_dataset_from_buffers``; ``env`` (a Gymnasium environment or
    id) records the spaces and the spec. ``root`` sets ``MINARI_DATASETS_PATH`` for the
    call; ``metadata`` goes to Minari (``algorithm_name``, ``author``, ...).

    Returns
    -------
    minari.MinariDataset
    """
    _require_minari()
    from minari import create_dataset_from_buffers
    from minari.data_collector.episode_buffer import EpisodeBuffer

    from ..data.episodes import as_episode_list

    buffers = []
    for k, ep in enumerate(as_episode_list(episodes)):
        buffers.append(EpisodeBuffer(
            id=k,
            seed=getattr(ep, "seed", None),
            observations=np.asarray(ep.observations),
            actions=np.asarray(ep.actions),
            rewards=[float(r) for r in ep.rewards],
            terminations=[bool(t) for t in ep.terminations],
            truncations=[bool(t) for t in ep.truncations],
            infos={},
        ))
    old = os.environ.get("MINARI_DATASETS_PATH")
    if root is not None:
        os.environ["MINARI_DATASETS_PATH"] = str(Path(os.fspath(root)).resolve())
    try:
        return create_dataset_from_buffers(dataset_id, buffers, env=env, **metadata)
    finally:
        if root is not None:
            if old is None:
                os.environ.pop("MINARI_DATASETS_PATH", None)
            else:
                os.environ["MINARI_DATASETS_PATH"] = old


def from_minari(source, env=None, *, feature_map=None, n_actions=None, horizon=None,
                reward_offset=None) -> OfflineDataset:
    """Read a Minari dataset into an :class:`~r2pvi.OfflineDataset`.

    Any Minari dataset with discrete actions (one written by Minari's own
    ``create_dataset_from_buffers`` or ``DataCollector`` from any Gymnasium environment) is
    read through a ``feature_map`` on its observations; datasets of r2pvi's environments
    (written by :func:`to_minari`) are read through the environment's own features.

    Parameters
    ----------
    source : minari.MinariDataset, str or path
        A loaded dataset, a directory (the dataset's ``data`` directory or its parent) or a
        local dataset id (never downloaded).
    env : FiniteLinearMDP or AmericanPutOption, optional
        The r2pvi environment whose features and known values build the dataset; None
        recovers it from the dataset's Gymnasium spec (datasets written by
        :func:`to_minari`). Not used with ``feature_map``.
    feature_map : callable or fitted transformer, optional
        Build the dataset with :meth:`OfflineDataset.from_episodes` on the episodes'
        observations: ``feature_map(observations, actions) -> (n, d)`` or a fitted
        observation transformer (crossed with the actions).
    n_actions : int, optional
        With ``feature_map``: the number of actions (default: the dataset's Discrete
        action space).
    horizon, reward_offset
        With ``feature_map``: as in :meth:`OfflineDataset.from_episodes`.

    Returns
    -------
    OfflineDataset
        With ``states``, ``actions`` and ``next_states`` kept. Put-option episodes that end
        by exercise are padded to H steps with the ended state (NaN, value 0).
    """
    minari = _require_minari()
    from minari.dataset.minari_dataset import MinariDataset

    if isinstance(source, MinariDataset):
        md = source
    elif isinstance(source, str | os.PathLike):
        path = Path(os.fspath(source)).resolve()
        if (path / "metadata.json").is_file():
            md = MinariDataset(path)
        elif (path / "data" / "metadata.json").is_file():
            md = MinariDataset(path / "data")
        elif isinstance(source, str):
            md = minari.load_dataset(source, download=False)
        else:
            raise FileNotFoundError(f"no Minari dataset at {path}")
    else:
        raise TypeError(
            f"source must be a minari.MinariDataset, a dataset id or a path, got {source!r}"
        )
    if feature_map is not None:
        if n_actions is None:
            space = md.spec.action_space
            if not hasattr(space, "n"):
                raise ValueError(
                    f"the dataset's action space {space} is not Discrete: r2pvi needs "
                    "discrete actions (pass n_actions= if the actions are indices)"
                )
            n_actions = int(space.n)
        return OfflineDataset.from_episodes(md, feature_map, n_actions, horizon,
                                            reward_offset=reward_offset)
    if env is None:
        env_spec = md.spec.env_spec
        if env_spec is None or not str(env_spec.id).startswith("r2pvi/"):
            name = "no environment" if env_spec is None else f"environment {env_spec.id!r}"
            raise ValueError(
                f"the Minari dataset records {name}, not an r2pvi environment: pass "
                "feature_map= (e.g. r2pvi.features.cross_actions(NormalizedRBF().fit(obs), "
                "n_actions)) to build features from its observations, or env= (the r2pvi "
                "environment the data come from)"
            )
        from . import gym as _gym  # noqa: F401  (registers the ids)

        env = md.recover_environment().unwrapped.model
    _check_env(env)
    H = env.horizon
    put = isinstance(env, AmericanPutOption)
    episodes = list(md.iterate_episodes())
    if not episodes:
        raise ValueError("the Minari dataset has no episodes")
    K = len(episodes)
    dtype = float if put else np.int64
    fill = np.nan if put else 0
    states = np.full((K, H), fill, dtype=dtype)
    next_states = np.full((K, H), fill, dtype=dtype)
    actions = np.zeros((K, H), dtype=np.int64)
    rewards = np.zeros((K, H))
    for k, ep in enumerate(episodes):
        T = len(ep.rewards)
        obs = np.asarray(ep.observations).reshape(T + 1)
        ended = bool(np.asarray(ep.terminations)[-1]) if T else False
        if T > H or (T < H and not (put and ended)):
            raise ValueError(
                f"episode {ep.id} has {T} steps; this environment's episodes have H = {H} "
                "steps (only an exercised put option ends early)"
            )
        states[k, :T] = obs[:T]
        next_states[k, :T] = obs[1 : T + 1]
        actions[k, :T] = np.asarray(ep.actions).reshape(T)
        rewards[k, :T] = np.asarray(ep.rewards).reshape(T)
        if put and ended and actions[k, T - 1] == EXERCISE:
            next_states[k, T - 1] = np.nan
    return env.make_dataset(states, actions, rewards, next_states)
