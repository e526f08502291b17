"""Writing a dataset bigger than memory, a chunk of trajectories at a time."""

from __future__ import annotations

import os
import shutil
import weakref
from pathlib import Path

import numpy as np

from .behaviour import _action_dtype, _behaviour_files, _next_form, behaviour_split
from .checks import check_features_chunk, check_reward_noise, step_major, warn_simplex
from .fields import _float_dtype, widen_range
from .files import FileField
from .format import (
    BASE_FORMAT_VERSION,
    GRAM_FILE,
    KIND,
    SUMS_FILE,
    _add_gram,
    _finish,
    _temp_dir,
    check_target,
)
from .npy import _write_npy_header


class DatasetWriter:
    """Write a dataset bigger than memory, a chunk of trajectories at a time.

    Each :meth:`append` takes the arrays :meth:`OfflineDataset.from_features` takes, for a
    chunk of trajectories, validates them exactly as it does (chunk by chunk) and writes them
    step-major to a temporary directory; :meth:`close` assembles the on-disk format there
    (streaming, bounded memory) and renames it to ``path`` in one step, so ``path`` never
    holds a partial dataset. Use it as a context manager: an exception discards the data.

    Parameters
    ----------
    path : str or Path
        The dataset directory to create.
    horizon, n_features, n_actions : int
        H, d and A.
    dtype : {"float32", "float64"}, default "float32"
        Storage type of the features (rewards and values stay float64). Fitting accumulates
        in float64 either way.
    check_simplex : bool, default True
        Warn once (at :meth:`close`) when features leave the simplex.
    overwrite : bool, default False
        Replace an existing dataset at ``path`` (a dataset directory holding only its own
        files, a dataset ``.npz`` file, or an empty directory); anything else there is a
        ``FileExistsError``, as without ``overwrite``.
    reward_noise : float, default 0.0
        The rewards' noise level, recorded in the manifest (``OfflineDataset.reward_noise``:
        ``fit`` lets rewards pass ``[0, r_max]`` by 8 of it).
    next_form : {"full", "behaviour"}, default "full"
        How the next-state features are stored. ``"full"``: every action's row,
        ``next_phi (H, K, A, d)``. ``"behaviour"``: each sample's row that is bitwise equal to
        the trajectory's next taken-action features ``phi[k, h+1]`` (the behaviour action's;
        the chunk holds all H steps, so step h+1 is at hand) is not stored, only the other
        ``A - 1`` rows and the action's index; samples where no row matches (episode ends,
        padded steps, independent transitions, rows of known values, the last step) keep
        their missing row in a side table. Fits are bitwise equal to the full form's; at
        A = 2 on trajectories it stores about a third fewer bytes (docs/storage.md).

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from r2pvi import DatasetWriter, OfflineDataset
    >>> rng = np.random.default_rng(0)
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     with DatasetWriter(os.path.join(tmp, "ds"), horizon=2, n_features=3,
    ...                        n_actions=2) as w:
    ...         for _ in range(3):                      # 3 chunks of 10 trajectories
    ...             w.append(rng.dirichlet(np.ones(3), (10, 2)), rng.random((10, 2)),
    ...                      rng.dirichlet(np.ones(3), (10, 2, 2)))
    ...     ds = OfflineDataset.open(os.path.join(tmp, "ds"))
    ...     ds.n_trajectories, ds.phi.dtype
    (30, dtype('float32'))

    Trajectories, stored without the behaviour action's next-state row:

    >>> K, H, A, d = 40, 5, 2, 3
    >>> nxt = rng.dirichlet(np.ones(d), (K, H, A)).astype(np.float32)
    >>> taken = rng.integers(A, size=(K, H))                # a_{h+1} of each trajectory
    >>> phi = np.empty((K, H, d), np.float32)
    >>> phi[:, 0] = rng.dirichlet(np.ones(d), K)
    >>> phi[:, 1:] = nxt[np.arange(K)[:, None], np.arange(H - 1), taken[:, 1:]]
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     for form in ("full", "behaviour"):
    ...         with DatasetWriter(os.path.join(tmp, form), horizon=H, n_features=d,
    ...                            n_actions=A, next_form=form) as w:
    ...             w.append(phi, rng.random((K, H)), nxt)
    ...     full = OfflineDataset.open(os.path.join(tmp, "full"))
    ...     beh = OfflineDataset.open(os.path.join(tmp, "behaviour"))
    ...     same = np.array_equal(full.next_phi, beh.next_phi)
    ...     n_side = len(np.load(os.path.join(tmp, "behaviour", "next_side.npy")))
    >>> same, n_side                                    # only the last step's K rows
    (True, 40)
    """

    def __init__(self, path, *, horizon, n_features, n_actions, dtype="float32",
                 check_simplex=True, overwrite=False, next_form="full", reward_noise=0.0):
        from ..._validation import check_scalar

        self.path = Path(os.fspath(path))
        self.horizon = check_scalar(horizon, "horizon", low=1, integer=True)
        self.n_features = check_scalar(n_features, "n_features", low=1, integer=True)
        self.n_actions = check_scalar(n_actions, "n_actions", low=1, integer=True)
        self.dtype = _float_dtype(dtype)
        self.check_simplex = check_simplex
        self.overwrite = overwrite
        self.next_form = _next_form(next_form)
        self.reward_noise = check_reward_noise(reward_noise)
        check_target(self.path, overwrite)  # before any work (checked again at close)
        self._tmp: Path | None = _temp_dir(self.path)
        # A writer dropped without close() leaves no temporary directory behind.
        self._cleanup = weakref.finalize(self, shutil.rmtree, str(self._tmp), True)
        self._shards: list[tuple[int, bool]] = []  # (K of the chunk, has next_values)
        self._flags = [False, False, False, False, True, True]
        self._reward_range = (np.inf, -np.inf)  # (min, max) of the appended rewards
        self.n_trajectories = 0

    def append(self, phi, rewards, next_phi, next_values=None) -> None:
        """Validate and write a chunk of trajectories: ``phi (k, H, d)``, ``rewards (k, H)``,
        ``next_phi (k, H, A, d)``, optional ``next_values (k, H, A)``."""
        if self._tmp is None:
            raise RuntimeError("this DatasetWriter is closed")
        H, d, A = self.horizon, self.n_features, self.n_actions
        p = step_major(phi, "phi", 3, self.dtype)
        k = p.shape[1]
        if p.shape != (H, k, d):
            raise ValueError(f"phi must have shape (k, H, d) = (k, {H}, {d}), got "
                             f"{np.shape(phi)}")
        if k == 0:  # an empty batch (the tail of a stream): nothing to write
            for name, x in (("rewards", rewards), ("next_phi", next_phi),
                            ("next_values", next_values)):
                if x is not None and np.shape(x)[:1] != (0,):
                    raise ValueError(f"phi holds 0 trajectories but {name} has shape "
                                     f"{np.shape(x)}")
            return
        r = step_major(rewards, "rewards", 2, np.float64)
        if r.shape != (H, k):
            raise ValueError(f"rewards must have shape (k, H) = {(k, H)}, got {np.shape(rewards)}")
        n = step_major(next_phi, "next_phi", 4, self.dtype)
        if n.shape != (H, k, A, d):
            raise ValueError(f"next_phi must have shape (k, H, A, d) = {(k, H, A, d)}, got "
                             f"{np.shape(next_phi)}")
        nv = None
        if next_values is not None:
            nv = step_major(next_values, "next_values", 3, np.float64)
            if nv.shape != (H, k, A):
                raise ValueError(f"next_values must have shape (k, H, A) = {(k, H, A)}, got "
                                 f"{np.shape(next_values)}; use NaN where the value is learned")
        first = self.n_trajectories
        flags = list(self._flags)  # merged only once the whole chunk is valid
        for h in range(H):
            try:
                f = check_features_chunk(p[h], r[h], n[h], None if nv is None else nv[h],
                                         h == H - 1, self.check_simplex)
            except ValueError as exc:  # say where: the append, its trajectories, the step
                raise ValueError(
                    f"append #{len(self._shards)} (trajectories {first}..{first + k - 1} of the "
                    f"dataset, rows 0..{k - 1} of this chunk), step h = {h}: {exc}; nothing "
                    "of this chunk was written") from exc
            for i in range(4):
                flags[i] = flags[i] or f[i]
            flags[4] &= f[4]
            flags[5] &= f[5]
        self._flags[:] = flags
        self._reward_range = widen_range(self._reward_range, r)
        i = len(self._shards)
        shard = self._tmp / f"shard{i:06d}"
        shard.mkdir()
        np.save(shard / "phi.npy", p, allow_pickle=False)
        np.save(shard / "rewards.npy", r, allow_pickle=False)
        last = np.nan_to_num(n[H - 1], nan=0.0)
        if not np.array_equal(last, n[H - 1], equal_nan=False):
            n = n.copy()
            n[H - 1] = last
        if self.next_form == "behaviour":  # step h+1 of the same trajectories is in p
            parts = [behaviour_split(p[h + 1] if h < H - 1 else None, n[h]) for h in range(H)]
            np.save(shard / "next_action.npy", np.stack([q[0] for q in parts]),
                    allow_pickle=False)
            np.save(shard / "next_rest.npy", np.stack([q[1] for q in parts]),
                    allow_pickle=False)
            np.save(shard / "next_side.npy", np.concatenate([q[2] for q in parts]),
                    allow_pickle=False)
            np.save(shard / "next_side_counts.npy", np.array([len(q[2]) for q in parts]),
                    allow_pickle=False)
        else:
            np.save(shard / "next_phi.npy", n, allow_pickle=False)
        if nv is not None:
            np.save(shard / "next_values.npy", nv, allow_pickle=False)
        self._shards.append((k, nv is not None))
        self.n_trajectories += k

    def close(self) -> Path:
        """Assemble the step-major files, write the manifest, rename; returns the path."""
        if self._tmp is None:
            raise RuntimeError("this DatasetWriter is closed")
        if not self._shards:
            raise ValueError("no trajectories were appended; a dataset needs at least one")
        tmp, self._tmp = self._tmp, None
        try:
            H, K, d, A = self.horizon, self.n_trajectories, self.n_features, self.n_actions
            any_nv = any(has for _, has in self._shards)
            fields = {"phi": ((H, K, d), self.dtype), "rewards": ((H, K), np.float64)}
            behaviour = self.next_form == "behaviour"
            if behaviour:
                fields["next_action"] = ((H, K), _action_dtype(A))
                fields["next_rest"] = ((H, K, A - 1, d), self.dtype)
            else:
                fields["next_phi"] = ((H, K, A, d), self.dtype)
            if any_nv:
                fields["next_values"] = ((H, K, A), np.float64)
            grams = np.zeros((H, d, d))
            sums = np.zeros((H, d))
            row_sums = [np.inf, -np.inf]
            for name, (shape, dt) in fields.items():
                shards = [FileField(tmp / f"shard{i:06d}" / f"{name}.npy") if
                          (name != "next_values" or has) else None
                          for i, (_, has) in enumerate(self._shards)]
                with open(tmp / f"{name}.npy", "wb") as fh:
                    _write_npy_header(fh, shape, dt)
                    for h in range(H):  # file order: step, then trajectory
                        for (k, _), f in zip(self._shards, shards, strict=True):
                            rows = (np.full((k, A), np.nan) if f is None else f.read(h))
                            fh.write(np.ascontiguousarray(rows, dtype=dt).tobytes())
                            if name == "phi":
                                _add_gram(grams[h], rows, sums[h], row_sums)
                for f in shards:
                    if f is not None:
                        f.close()
            files = {name: f"{name}.npy" for name in fields}
            shapes = {name: list(shape) for name, (shape, _) in fields.items()}
            extra = {}
            if behaviour:
                extra["next_behaviour"] = self._assemble_side(tmp, files, shapes)
            for i in range(len(self._shards)):
                shutil.rmtree(tmp / f"shard{i:06d}")
            np.save(tmp / GRAM_FILE, grams, allow_pickle=False)
            np.save(tmp / SUMS_FILE, sums, allow_pickle=False)
            fl = self._flags
            if self.check_simplex:
                warn_simplex("phi", fl[0], fl[1], 2)
                warn_simplex("next_phi", fl[2], fl[3], 2)
            manifest = {
                "kind": KIND, "format_version": BASE_FORMAT_VERSION, "layout": "step-major",
                "n_trajectories": K, "horizon": H, "n_features": d, "n_actions": A,
                "dtype": self.dtype.name, "next": "behaviour" if behaviour else "stored",
                "files": {**files, "gram": GRAM_FILE, "phi_sums": SUMS_FILE}, "shapes": shapes,
                "extras": [], "nonnegative_phi": fl[4], "nonnegative_next_phi": fl[5],
                "reward_range": [float(x) for x in self._reward_range],
                **extra,
            }
            if np.isfinite(row_sums).all():
                manifest["phi_row_sums"] = [float(x) for x in row_sums]
            if self.reward_noise:
                manifest["reward_noise"] = self.reward_noise
            return _finish(tmp, self.path, manifest, self.overwrite)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise

    def _assemble_side(self, tmp: Path, files, shapes) -> dict:
        """The behaviour form's side table from the shards': step by step, then in
        trajectory order (the shards are consecutive trajectories)."""
        H, d, A = self.horizon, self.n_features, self.n_actions
        shards = [tmp / f"shard{i:06d}" for i in range(len(self._shards))]
        counts = np.stack([np.load(s / "next_side_counts.npy", allow_pickle=False)
                           for s in shards])  # (shards, H)
        starts = np.concatenate([np.zeros((len(shards), 1), np.int64),
                                 np.cumsum(counts, axis=1)], axis=1)
        offsets = np.concatenate([[0], np.cumsum(counts.sum(axis=0))]).astype(np.int64)
        n_side = int(offsets[-1])
        with open(tmp / "next_side.npy", "wb") as fh:
            _write_npy_header(fh, (n_side, d), self.dtype)
            sides = [np.load(s / "next_side.npy", mmap_mode="r", allow_pickle=False)
                     for s in shards]
            for h in range(H):
                for i, side in enumerate(sides):
                    rows = side[starts[i, h]:starts[i, h + 1]]
                    fh.write(np.ascontiguousarray(rows, dtype=self.dtype).tobytes())
            del sides
        np.save(tmp / "next_side_offsets.npy", offsets, allow_pickle=False)
        return _behaviour_files(files, shapes, H, self.n_trajectories, A, d, n_side)

    def abort(self):
        """Discard everything written so far."""
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            if self._tmp is not None:
                self.close()
        else:
            self.abort()
        return False
