"""Step-major storage: where a dataset's numbers live, read one step at a time.

Every step of the backward induction reads only that step's data. A dataset is therefore a
*step source*: fields of shape ``(H, K, ...)`` (step-major) that can be read one step and
one range of trajectories at a time, wherever they are:

- :class:`ArrayField` — a NumPy array (or a read-only view of the caller's array, no copy);
- :class:`FileField` — a ``.npy`` file of the on-disk format, read chunk by chunk: while
  fitting, a step is memory-mapped a window of 32 MiB at a time and cast chunk by chunk into a
  reused float64 buffer (the resident memory stays bounded; ``pread`` where a file cannot be
  mapped); :meth:`FileField.read` reads a range with ``pread``, :meth:`FileField.lazy` gives a
  memory map of the whole file for browsing;
- :class:`DaskField` — a Dask array chunked along trajectories (the ``dask`` extra).

Next-state features are computed where they need not be stored (:class:`StoredNext`,
:class:`BehaviourNext` for trajectories, whose taken action's row is the next step's
features, :class:`TableNext` for finite MDPs, :class:`MapNext` for stored observations and a
feature map), and the engine asks for the next-state values ``V_{h+1}`` chunk by chunk through
:meth:`StepSource.next_state_values`.

The on-disk format (format version 2) is a directory::

    manifest.json        {"kind": "r2pvi.OfflineDataset", "format_version": 2, ...}
    phi.npy              (H, K, d)     float32 or float64, step-major
    rewards.npy          (H, K)
    next_phi.npy         (H, K, A, d)  stored next-state features, or
    next_index.npy       (H, K)        next-state indices into
    next_table.npy       (S, A, d) or (H, S, A, d)   a feature table (row h of a 4-D table
                                       holds the features used for the next states of step h)
    next_action.npy      (H, K)        or the behaviour form: the action whose row is
    next_rest.npy        (H, K, A-1, d)  phi[k, h+1] (-1: none), the other actions' rows,
    next_side.npy        (n_side, d)   the rows where none matched, by step (offsets
    next_side_offsets.npy (H+1,)       into next_side); see BehaviourNext
    next_values.npy      (H, K, A)     known next-state action values (NaN: learn); optional
    next_table_values.npy (S, A)       known values by next state (table form); optional
    gram.npy             (H, d, d)     float64 Phi_h^T Phi_h of the stored features; optional
    phi_sums.npy         (H, d)        float64 Phi_h^T 1 (column sums); optional
    extra_<name>.npy     (K, H, ...)   observed states, actions, next states; optional

Plain ``.npy`` files (no pickle, ``allow_pickle=False`` on every read), described by a JSON
manifest with the shapes, dtypes and cached facts (non-negativity of the features).
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
import warnings
import weakref
from pathlib import Path

import numpy as np

__all__ = [
    "FORMAT_VERSION",
    "CHUNK",
    "ArrayField",
    "FileField",
    "DaskField",
    "StoredNext",
    "BehaviourNext",
    "RowFile",
    "behaviour_split",
    "TableNext",
    "MapNext",
    "MappedField",
    "StepSource",
    "DatasetWriter",
    "open_directory",
    "write_directory",
    "step_major",
    "validate_source",
]

FORMAT_VERSION = 2
KIND = "r2pvi.OfflineDataset"
MANIFEST = "manifest.json"
GRAM_FILE = "gram.npy"  # (H, d, d) float64 Phi_h^T Phi_h of the stored features (optional)
SUMS_FILE = "phi_sums.npy"  # (H, d) float64 Phi_h^T 1, the column sums (optional)
# Trajectories per chunk when streaming a step: about 1 MB (taken actions) and 2 MB (next
# states, A = 2) of float64 per chunk for d = 30, about one core's L2. Measured at K = 1e6
# from the page cache (TV and KL fits from disk, min of 3-4 interleaved rounds, shared
# machine): 4096 rows 8-12% less CPU than 2048 (per-chunk Python and call overhead), 8192
# no better than 4096.
CHUNK = 1 << 12
GRAM_CACHE_MAX_D = 512  # Gram matrices Phi_h^T Phi_h are cached (H d^2 floats) up to this d


def _float_dtype(dtype) -> np.dtype:
    """float32 or float64, else a ValueError naming the choices."""
    try:
        dt = np.dtype(dtype)
    except TypeError:
        dt = None
    if dt not in (np.float32, np.float64):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    return dt


class SimplexFeatureWarning(UserWarning):
    """Features break the paper's simplex assumption (phi_i >= 0 and sum_i phi_i = 1)."""


# --------------------------------------------------------------------------- fields
class Field:
    """A step-major array ``(H, K, ...)`` read by step and range of trajectories."""

    shape: tuple
    dtype: np.dtype

    def read(self, h: int, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Rows ``[h, start:stop]`` as an ndarray (may be a read-only view)."""
        raise NotImplementedError

    def lazy(self):
        """The whole field ``(H, K, ...)`` without reading it (a view or memory map)."""
        raise NotImplementedError

    def take(self, idx: np.ndarray) -> np.ndarray:
        """The trajectories ``idx`` of every step, ``(H, len(idx), ...)``, in memory."""
        return np.stack([self.read(h)[idx] for h in range(self.shape[0])])

    def chunks(self, h: int, chunk: int):
        """``(start, stop, rows)`` over the trajectories of step ``h``."""
        K = self.shape[1]
        for s in range(0, K, chunk):
            e = min(K, s + chunk)
            yield s, e, self.read(h, s, e)


class ArrayField(Field):
    """A field held in a NumPy array (kept as a read-only view; never copied)."""

    def __init__(self, array: np.ndarray):
        view = array.view() if isinstance(array, np.ndarray) else np.asarray(array)
        view.flags.writeable = False
        self.array = view
        self.shape, self.dtype = view.shape, view.dtype

    def read(self, h, start=0, stop=None):
        return self.array[h, start:stop]

    def lazy(self):
        return self.array

    def take(self, idx):
        return self.array[:, idx]


class FileField(Field):
    """A field in a ``.npy`` file: :meth:`read` reads a range with ``pread`` (into ``out`` or a
    fresh array); fits stream a step through windows of a memory map (``_prefetched``)."""

    def __init__(self, path):
        self.path = Path(path)
        with open(self.path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
            else:
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
            self.offset = fh.tell()
        if fortran or dtype.hasobject:
            raise ValueError(f"{self.path} is not a C-ordered numeric .npy file")
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)
        self._row = int(np.prod(self.shape[2:], dtype=np.int64)) * self.dtype.itemsize
        size = self.offset + int(np.prod(self.shape, dtype=np.int64)) * self.dtype.itemsize
        if os.path.getsize(self.path) < size:
            raise ValueError(f"{self.path} is truncated: expected {size} bytes")
        self._fd: int | None = None

    def _file(self) -> int:
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDONLY)
        return self._fd

    def read(self, h, start=0, stop=None, out=None):
        K = self.shape[1]
        stop = K if stop is None else min(stop, K)
        shape = (stop - start,) + self.shape[2:]
        if out is None or out.shape != shape or out.dtype != self.dtype:
            out = np.empty(shape, dtype=self.dtype)
        nbytes = out.nbytes
        if nbytes:
            pos = self.offset + (h * K + start) * self._row
            view = memoryview(out.reshape(-1).view(np.uint8))
            done = 0
            while done < nbytes:  # pread may return less than asked for
                got = os.preadv(self._file(), [view[done:]], pos + done)
                if got <= 0:
                    raise OSError(f"unexpected end of {self.path}")
                done += got
        return out

    def lazy(self):
        return np.load(self.path, mmap_mode="r", allow_pickle=False)

    def take(self, idx):
        return np.asarray(self.lazy()[:, idx])

    def close(self):
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self):  # pragma: no cover - interpreter shutdown
        try:
            self.close()
        except Exception:
            pass

    def __getstate__(self):  # picklable for process pools: reopen the file there
        state = dict(self.__dict__)
        state["_fd"] = None
        return state


class DaskField(Field):
    """A field held as a Dask array ``(H, K, ...)`` chunked along trajectories."""

    def __init__(self, array):
        self.array = array
        self.shape, self.dtype = tuple(array.shape), np.dtype(array.dtype)

    def read(self, h, start=0, stop=None):
        return np.asarray(self.array[h, start:stop].compute())

    def lazy(self):
        return self.array

    def take(self, idx):
        return np.asarray(self.array[:, np.asarray(idx)].compute())

    def chunks(self, h, chunk):
        # Dask's own chunks along trajectories, computed where the data is.
        bounds = np.cumsum((0,) + tuple(self.array.chunks[1]))
        for s, e in zip(bounds[:-1], bounds[1:], strict=True):
            yield int(s), int(e), self.read(h, int(s), int(e))


class MappedField(Field):
    """Taken-action features computed from stored observations and actions by a feature map:
    ``read(h, s, e) = feature_map(observations[h, s:e], actions[h, s:e])`` ``(n, d)``."""

    def __init__(self, observations: Field, actions: Field, feature_map, n_features: int):
        self.observations, self.actions, self.feature_map = observations, actions, feature_map
        H, K = observations.shape[:2]
        self.shape, self.dtype = (H, K, int(n_features)), np.dtype(np.float64)

    def read(self, h, start=0, stop=None):
        obs = self.observations.read(h, start, stop)
        act = np.asarray(self.actions.read(h, start, stop), dtype=np.int64)
        out = np.asarray(self.feature_map(obs, act), dtype=np.float64)
        if out.shape != (obs.shape[0], self.shape[2]):
            raise ValueError(f"feature_map returned shape {out.shape} for {obs.shape[0]} "
                             f"observations; expected (n, d) = ({obs.shape[0]}, {self.shape[2]})")
        return out

    def lazy(self):
        return np.stack([self.read(h) for h in range(self.shape[0])])

    def take(self, idx):
        return self.lazy()[:, idx]


# --------------------------------------------------------------------------- next states
class NextStates:
    """Where the next-state features come from; the engine only asks for values."""

    n_actions: int
    nonnegative: bool | None = None  # every used next-state feature >= 0 (None: unknown)
    has_known_values: bool = False

    def features(self, h, start=0, stop=None) -> np.ndarray:
        """Features of every action at the next states ``(n, A, d)`` (float64 or float32)."""
        raise NotImplementedError

    def known(self, h, start=0, stop=None):
        """Known next-state action values ``(n, A)`` (NaN: learn), or None."""
        return None

    def values(self, h, qmax, n, chunk) -> np.ndarray:
        """``V_{h+1}`` at the K next states: ``qmax(features, known, nonneg) -> (n,)`` by chunk."""
        out = np.empty(n)
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            feats = _as_float64(self.features(h, s, e))
            nonneg = self.nonnegative
            if nonneg is None:
                nonneg = bool((feats >= 0).all())
            out[s:e] = qmax(feats, self.known(h, s, e), nonneg)
        return out

    def take(self, idx) -> NextStates:
        raise NotImplementedError


class StoredNext(NextStates):
    """Stored next-state features ``(H, K, A, d)`` and optional known values ``(H, K, A)``."""

    def __init__(self, next_phi: Field, next_values: Field | None = None, nonnegative=None):
        self.next_phi, self.next_values = next_phi, next_values
        self.n_actions = next_phi.shape[2]
        self.nonnegative = nonnegative
        self.has_known_values = next_values is not None

    def features(self, h, start=0, stop=None):
        return self.next_phi.read(h, start, stop)

    def known(self, h, start=0, stop=None):
        return None if self.next_values is None else _as_float64(
            self.next_values.read(h, start, stop))

    def values(self, h, qmax, n, chunk, out=None):
        field = self.next_phi
        if isinstance(field, DaskField):
            v = _dask_values(self, h, qmax)
            if out is None:
                return v
            out[...] = v
            return out
        # Two reused buffers (a chunk read in the storage type, then cast to float64): no
        # fresh allocation, so no page faults, per chunk.
        out = np.empty(n) if out is None else out
        shape = (min(chunk, n),) + field.shape[2:]
        if isinstance(field, FileField):
            reads = _prefetched(field, h, n, chunk, shape)
        else:
            reads = ((s, min(n, s + chunk), field.read(h, s, min(n, s + chunk)))
                     for s in range(0, n, chunk))
        f64 = np.empty(shape)

        def float64_rows():
            for s, e, rows in reads:
                if not (rows.dtype == np.float64 and rows.flags.c_contiguous):
                    np.copyto(f64[: e - s], rows)
                    rows = f64[: e - s]
                yield s, e, rows

        linear = getattr(qmax, "linear", None)
        lin = None
        if linear is not None and self.next_values is None and self.nonnegative is not None:
            lin = linear(self.nonnegative)
        if lin is not None:
            # V = clip(max_a phi_a^T u, 0, upper): one matrix-vector product per chunk into a
            # reused buffer, the max over actions into the output, one clip at the end.
            u, upper = lin
            A, d = field.shape[2], field.shape[3]
            q = np.empty(shape[0] * A)
            for s, e, rows in float64_rows():
                qa = np.matmul(rows.reshape(-1, d), u, out=q[: (e - s) * A]).reshape(e - s, A)
                if A == 1:
                    out[s:e] = qa[:, 0]
                elif A == 2:
                    np.maximum(qa[:, 0], qa[:, 1], out=out[s:e])
                else:
                    np.max(qa, axis=1, out=out[s:e])
            np.clip(out, 0.0, upper, out=out)
            return out
        for s, e, feats in float64_rows():
            nonneg = self.nonnegative
            if nonneg is None:
                nonneg = bool((feats >= 0).all())
            out[s:e] = qmax(feats, self.known(h, s, e), nonneg)
        return out

    def take(self, idx):
        nv = None if self.next_values is None else ArrayField(self.next_values.take(idx))
        return StoredNext(ArrayField(self.next_phi.take(idx)), nv, self.nonnegative)


class TableNext(NextStates):
    """Next-state indices ``(H, K)`` into a feature table (finite MDPs): nothing per sample.

    ``table`` is ``(S, A, d)``, or ``(H, S, A, d)`` with row ``h`` the features of the next
    states of step ``h``; ``known_table (S, A)`` gives known values by next state. ``V_{h+1}``
    is computed once per state and gathered by index (when ``S <= K``).
    """

    def __init__(self, index: Field, table: np.ndarray, known_table: np.ndarray | None = None):
        self.index, self.table, self.known_table = index, table, known_table
        self.n_actions = table.shape[-2]
        used = table if table.ndim == 3 else table[: max(index.shape[0] - 1, 1)]
        self.nonnegative = bool((used >= 0).all())
        self.has_known_values = known_table is not None

    def _table(self, h):
        return self.table if self.table.ndim == 3 else self.table[h]

    def features(self, h, start=0, stop=None):
        return self._table(h)[self.index.read(h, start, stop)]

    def known(self, h, start=0, stop=None):
        if self.known_table is None:
            return None
        return self.known_table[self.index.read(h, start, stop)]

    def values(self, h, qmax, n, chunk):
        table = _as_float64(self._table(h))
        if table.shape[0] > n:  # more states than samples: evaluate the sampled ones only
            return super().values(h, qmax, n, chunk)
        v_table = qmax(table, self.known_table, self.nonnegative)
        out = np.empty(n)
        for s, e, idx in self.index.chunks(h, chunk):
            np.take(v_table, idx, out=out[s:e])
        return out

    def take(self, idx):
        return TableNext(ArrayField(self.index.take(idx)), self.table, self.known_table)


class MapNext(NextStates):
    """Stored next observations ``(H, K, ...)`` and a feature map evaluated chunk by chunk.

    ``feature_map(observations (n, ...), actions (n,)) -> (n, d)``; ``known_values``, when
    given, maps next observations ``(n, ...)`` to known action values ``(n, A)`` (NaN: learn).
    """

    def __init__(self, observations: Field, feature_map, n_actions: int, n_features: int,
                 known_values=None):
        self.observations, self.feature_map = observations, feature_map
        self.n_actions, self.n_features = int(n_actions), int(n_features)
        self.known_values = known_values
        self.has_known_values = known_values is not None
        self.nonnegative = None

    def features(self, h, start=0, stop=None):
        obs = self.observations.read(h, start, stop)
        n = obs.shape[0]
        out = np.empty((n, self.n_actions, self.n_features))
        for a in range(self.n_actions):
            f = np.asarray(self.feature_map(obs, np.full(n, a)), dtype=float)
            if f.shape != (n, self.n_features):
                raise ValueError(
                    f"feature_map returned shape {f.shape} for {n} next observations; "
                    f"expected (n, d) = ({n}, {self.n_features})")
            out[:, a] = f
        return out

    def known(self, h, start=0, stop=None):
        if self.known_values is None:
            return None
        if isinstance(self.known_values, Field):  # stored known values (H, K, A)
            return _as_float64(self.known_values.read(h, start, stop))
        obs = self.observations.read(h, start, stop)
        kv = np.asarray(self.known_values(obs), dtype=float)
        if kv.shape != (obs.shape[0], self.n_actions):
            raise ValueError(f"known_values returned shape {kv.shape}, expected (n, A)")
        return kv

    def take(self, idx):
        kv = self.known_values
        if isinstance(kv, Field):
            kv = ArrayField(kv.take(idx))
        return MapNext(ArrayField(self.observations.take(idx)), self.feature_map,
                       self.n_actions, self.n_features, kv)


# --------------------------------------------------------------------------- behaviour form
NEXT_FORMS = ("full", "behaviour")
BEHAVIOUR_VERSION = 1  # version of the "behaviour" next-state field set in the manifest


def _next_form(next_form) -> str:
    if next_form not in NEXT_FORMS:
        raise ValueError(f"next_form must be 'full' or 'behaviour', got {next_form!r}")
    return next_form


def _action_dtype(n_actions: int) -> np.dtype:
    """The smallest signed integer type holding ``-1 .. A-1``."""
    for dt in (np.int8, np.int16, np.int32):
        if n_actions <= np.iinfo(dt).max:
            return np.dtype(dt)
    return np.dtype(np.int64)


def behaviour_split(following, rows):
    """Split one step's next-state rows into the behaviour form.

    ``rows (n, A, d)`` are the next-state features of every action of ``n`` samples of step
    ``h``; ``following (n, d)`` the same samples' taken-action features at step ``h+1``
    (``phi[:, h+1]``, in the storage type), or None for the last step. Returns

    - ``action (n,)``: the first action ``a`` with ``rows[i, a]`` bitwise equal to
      ``following[i]`` (that row is then not stored), or -1 where none is (episode ends,
      padding, independent transitions, NaN rows of known values, the last step);
    - ``rest (n, A-1, d)``: the rows of every action but ``m_i`` (``m_i = action[i]``, or 0
      where ``action[i] = -1``), in increasing action order;
    - ``side (n_side, d)``: ``rows[i, 0]`` of the samples with ``action[i] = -1``, in order.

    Bitwise equality (not ``==``) makes the rebuilt rows the stored ones exactly: ``-0.0`` and
    ``0.0`` or two NaN payloads are told apart.
    """
    n, A, _ = rows.shape
    if following is None or A == 0:
        action = np.full(n, -1, dtype=_action_dtype(A))
    else:
        u = np.dtype(f"u{rows.dtype.itemsize}")
        eq = (rows.view(u) == following.view(u)[:, None, :]).all(axis=2)
        hit = eq.any(axis=1)
        action = np.where(hit, eq.argmax(axis=1), -1).astype(_action_dtype(A))
    missing = np.maximum(action, 0)
    keep = np.ones((n, A), dtype=bool)
    keep[np.arange(n), missing] = False
    rest = rows[keep].reshape(n, A - 1, rows.shape[2])
    side = rows[action < 0, 0]
    return action, rest, side


class RowFile:
    """Rows ``(n, ...)`` of a ``.npy`` file read by range with ``pread`` (the side table)."""

    def __init__(self, path):
        self.path = Path(path)
        with open(self.path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                    else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read(fh)
            self.offset = fh.tell()
        if fortran or dtype.hasobject or len(shape) < 1:
            raise ValueError(f"{self.path} is not a C-ordered numeric .npy file")
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)
        self._row = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize
        size = self.offset + self.shape[0] * self._row
        if os.path.getsize(self.path) < size:
            raise ValueError(f"{self.path} is truncated: expected {size} bytes")

    def read(self, start, stop):
        out = np.empty((stop - start,) + self.shape[1:], dtype=self.dtype)
        if out.nbytes:
            with open(self.path, "rb") as fh:
                fh.seek(self.offset + start * self._row)
                if fh.readinto(memoryview(out.reshape(-1).view(np.uint8))) != out.nbytes:
                    raise OSError(f"unexpected end of {self.path}")
        return out


SIDE_BLOCK = 4096  # side-table positions are kept per block of samples (one count each)


class BehaviourNext(NextStates):
    """Next-state features stored without the behaviour action's row: ``phi[:, h+1]``.

    For sample ``(k, h)`` the trajectory's next taken action ``a = action[h, k]`` has the
    next-state features ``next_phi[k, h, a] = phi[k, h+1]`` (bitwise, as stored), so only the
    other ``A - 1`` rows are stored (``rest (H, K, A-1, d)``). Where the identity breaks
    (``action = -1``: episode ends, padding, independent transitions, rows of known values,
    the last step) the missing row (action 0's) is in a side table: ``side (n_side, d)``,
    step by step and in trajectory order within a step, ``offsets (H+1,)`` its step bounds.
    :meth:`features` rebuilds exactly the rows of the full form.

    ``phi`` is the dataset's taken-action field (read at step ``h+1``); ``side`` is an array
    or a :class:`RowFile`.
    """

    def __init__(self, action: Field, rest: Field, phi: Field, side, offsets,
                 next_values: Field | None = None, nonnegative=None):
        self.action, self.rest, self.phi, self.side = action, rest, phi, side
        self.offsets = np.asarray(offsets, dtype=np.int64)
        self.next_values = next_values
        self.n_actions = rest.shape[2] + 1
        self.nonnegative = nonnegative
        self.has_known_values = next_values is not None
        # (h, actions (K,), side rows before each (K+1,), staged block of each row (K, A))
        self._step = (None, None, None, None)

    def _index(self, h):
        """Step ``h``'s behaviour actions and side-table positions (validated, cached)."""
        if self._step[0] != h:
            act = np.asarray(self.action.read(h))
            A = self.n_actions
            if act.size and (act.min() < -1 or act.max() >= A):
                raise ValueError(f"next_action of step {h} holds values outside [-1, {A}): "
                                 "the dataset is corrupt")
            # side rows before sample s: before[s // SIDE_BLOCK] + those in the block to s
            miss = act < 0
            K = act.size
            blocks = np.zeros(K // SIDE_BLOCK + 2, dtype=np.int64)
            full = K // SIDE_BLOCK * SIDE_BLOCK
            np.cumsum(np.count_nonzero(miss[:full].reshape(-1, SIDE_BLOCK), axis=1),
                      out=blocks[1:-1])
            blocks[-1] = blocks[-2] + np.count_nonzero(miss[full:])
            want = int(self.offsets[h + 1] - self.offsets[h])
            if blocks[-1] != want:
                raise ValueError(
                    f"next_action of step {h} marks {blocks[-1]} samples as side-table rows "
                    f"but next_side_offsets gives {want}: the dataset is corrupt")
            if h == self.rest.shape[0] - 1 and blocks[-1] != K:
                raise ValueError("next_action of the last step must be -1 everywhere (no step "
                                 "h+1): the dataset is corrupt")
            # block[a, i]: the stage block holding out[i, a] (0: row m_i, 1 + j: rest[i, j])
            m = np.maximum(act, 0)
            block = np.empty((A, K), act.dtype)
            for a in range(A):  # one action at a time: no broadcasts over a tiny axis
                np.greater(m, a, out=block[a], casting="unsafe")
                block[a] += a
                block[a] *= m != a
            self._step = (h, act, (miss, blocks), block)
        return self._step[1:]

    def _order(self, block, start, stop, rows, m, out=None):
        """``(n, A)`` stage rows of ``out[i, a]``: ``block[a, i] * m + rows[i]``."""
        A = block.shape[0]
        order = np.empty((stop - start, A), dtype=np.intp) if out is None else out
        for a in range(A):
            np.multiply(block[a, start:stop], m, out=order[:, a], dtype=np.intp)
            order[:, a] += rows
        return order

    def _side(self, h, start, stop, before):
        miss, blocks = before

        def count(s):
            b = s // SIDE_BLOCK
            return int(blocks[b]) + np.count_nonzero(miss[b * SIDE_BLOCK:s])

        lo = int(self.offsets[h]) + count(start)
        hi = lo + np.count_nonzero(miss[start:stop])
        return self.side.read(lo, hi) if isinstance(self.side, RowFile) else self.side[lo:hi]

    def _staged(self, h, start, stop, index, stage, order):
        """The rows of samples ``start:stop`` as ``(n, A, d)`` in the storage type.

        ``stage (A, m, d)`` (``m >= n``) is a reused buffer: block 0 receives each sample's
        row ``m_i`` (``phi[k, h+1]``, read straight into it, or the side table's row), blocks
        1.. the stored rows of the other actions; one gather of whole rows (``d`` floats
        each, as opaque bytes) by ``order (n, A)`` (:meth:`_order`) puts them in action
        order."""
        n = stop - start
        A, m, d = stage.shape
        before = index[1]
        miss = before[0][start:stop]
        src = stage[0, :n]
        any_miss = bool(miss.any())
        if h + 1 < self.phi.shape[0] and not (any_miss and miss.all()):
            got = (self.phi.read(h + 1, start, stop, out=src) if isinstance(self.phi, FileField)
                   else self.phi.read(h + 1, start, stop))
            if got is not src:
                np.copyto(src, got)
        if any_miss:
            src[miss] = self._side(h, start, stop, before)
        if A == 2 and isinstance(self.rest, FileField):
            dst = stage[1, :n].reshape(n, 1, d)
            got = self.rest.read(h, start, stop, out=dst)
            if got is not dst:
                np.copyto(dst, got)
        elif A > 1:
            np.copyto(stage[1:, :n], np.moveaxis(self.rest.read(h, start, stop), 1, 0))
        # out[i, a] is row order[i, a] of the stage
        whole = stage.reshape(A * m, d).view(np.dtype((np.void, d * stage.itemsize)))
        return np.take(whole.reshape(-1), order.reshape(-1)).view(stage.dtype).reshape(n, A, d)

    def features(self, h, start=0, stop=None):
        K = self.rest.shape[1]
        stop = K if stop is None else min(stop, K)
        m = max(stop - start, 1)
        stage = np.empty((self.n_actions, m, self.rest.shape[3]), self.rest.dtype)
        index = self._index(h)
        order = self._order(index[2], start, stop, np.arange(stop - start), m)
        return self._staged(h, start, stop, index, stage, order)

    def known(self, h, start=0, stop=None):
        return None if self.next_values is None else _as_float64(
            self.next_values.read(h, start, stop))

    def values(self, h, qmax, n, chunk):
        index = self._index(h)
        A, d = self.n_actions, self.rest.shape[3]
        m = min(chunk, n)
        stage = np.empty((A, m, d), self.rest.dtype)  # reused buffers, as StoredNext's
        order = np.empty((m, A), dtype=np.intp)
        rows = np.arange(m)
        f64 = np.empty((m, A, d))
        out = np.empty(n)
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            feats = f64[: e - s]
            o = self._order(index[2], s, e, rows[: e - s], m, order[: e - s])
            np.copyto(feats, self._staged(h, s, e, index, stage, o))
            nonneg = self.nonnegative
            if nonneg is None:
                nonneg = bool((feats >= 0).all())
            out[s:e] = qmax(feats, self.known(h, s, e), nonneg)
        return out

    def take(self, idx):
        idx = np.asarray(idx)
        feats = np.stack([self.features(h)[idx] for h in range(self.rest.shape[0])])
        nv = None if self.next_values is None else ArrayField(self.next_values.take(idx))
        return StoredNext(ArrayField(feats), nv, self.nonnegative)


def _prefetched(field: FileField, h, n, chunk, shape):
    """``(start, stop, rows)`` over step ``h`` with ``rows`` in float64 (a reused buffer, valid
    until the next iteration), read in the calling thread in file order.

    The step's bytes are memory-mapped a window at a time (``MAP_WINDOW`` bytes, then
    unmapped: the resident memory stays bounded whatever K) and each chunk is cast from the
    mapped pages straight into the float64 buffer: the page cache is read once, with no copy
    into an intermediate buffer (``pread`` copies every byte once more; measured at K = 1e6,
    d = 30, A = 2, float32, in fresh processes taken in turn: R2PVI-TV 2.25-2.38 s of CPU
    against 2.46-2.65 s with ``pread``, R2PVI-KL 2.37-2.52 against 2.65-3.06). The files must
    not be truncated while a fit reads them (the writers of this module never do: they write a
    new directory and rename it into place). Where the file cannot be mapped, ``pread`` into a
    reused buffer. Sequential access either way, so the kernel's read-ahead fetches pages not
    yet cached while a chunk is computed.

    Also measured there: a reader thread that read and cast the next chunk while this one was
    computed cost about twice the CPU time per pass (wall time no better), and asking the
    kernel to read ahead (``posix_fadvise(WILLNEED)``) took 10% of a TV fit's samples for
    pages already cached.
    """
    import mmap

    f64 = np.empty(shape)
    fd, row = field._file(), field._row
    base = field.offset + h * field.shape[1] * row
    win = max(1, MAP_WINDOW // max(1, chunk * row)) * chunk
    count = int(np.prod(field.shape[2:], dtype=np.int64))
    ws = 0
    while ws < n:
        we = min(n, ws + win)
        start = base + ws * row
        off = start % mmap.ALLOCATIONGRANULARITY
        try:
            mm = mmap.mmap(fd, (we - ws) * row + off, access=mmap.ACCESS_READ,
                           offset=start - off)
        except (OSError, ValueError):  # not mappable (e.g. some network file systems)
            yield from _pread_chunks(field, h, ws, n, chunk, f64)
            return
        mapped = None
        try:
            mapped = np.frombuffer(mm, dtype=field.dtype, count=(we - ws) * count,
                                   offset=off).reshape((we - ws,) + field.shape[2:])
            for s in range(ws, we, chunk):
                e = min(we, s + chunk)
                np.copyto(f64[: e - s], mapped[s - ws: e - ws])
                yield s, e, f64[: e - s]  # a copy: nothing outside holds the mapped pages
        finally:
            mapped = None
            mm.close()
        ws = we


MAP_WINDOW = 1 << 25  # bytes of a step mapped at a time by _prefetched (32 MiB)


def _pread_chunks(field: FileField, h, start, n, chunk, f64):
    """:func:`_prefetched` with ``pread`` into a reused buffer, from trajectory ``start``."""
    raw = f64 if field.dtype == np.float64 else np.empty(f64.shape, field.dtype)
    view = memoryview(raw.reshape(-1).view(np.uint8))
    fd, row = field._file(), field._row
    base = field.offset + h * field.shape[1] * row
    for s in range(start, n, chunk):
        e = min(n, s + chunk)
        nbytes = (e - s) * row
        if os.preadv(fd, [view[:nbytes]], base + s * row) != nbytes:
            field.read(h, s, e, out=raw[: e - s])  # a short read: the careful loop
        if raw is not f64:
            np.copyto(f64[: e - s], raw[: e - s])
        yield s, e, f64[: e - s]


def _dask_values(nxt: StoredNext, h, qmax):
    """Next-state values computed on the Dask workers, one task per trajectory chunk."""
    import dask.array as da

    feats = nxt.next_phi.array[h]
    nonneg = nxt.nonnegative

    def block(f, k=None):
        f = np.asarray(f, dtype=np.float64)
        nn = bool((f >= 0).all()) if nonneg is None else nonneg
        return qmax(f, None if k is None else np.asarray(k[..., 0], dtype=np.float64), nn)

    if nxt.next_values is None:
        v = da.map_blocks(block, feats, drop_axis=[1, 2], dtype=np.float64)
    else:
        kv = nxt.next_values.array[h].rechunk((feats.chunks[0], -1))
        v = da.map_blocks(block, feats, kv[:, :, None], drop_axis=[1, 2], dtype=np.float64)
    return np.asarray(v.compute(), dtype=np.float64)


def _dask_products(field: DaskField, h, cols, weights, with_gram):
    """``(Phi_h^T W Phi_h or None, [Phi_h^T W c for c in cols])`` summed on the Dask workers.

    One task per trajectory chunk forms that chunk's products in float64 (the columns, and
    the weights ``W``, travel to the workers with the graph), Dask adds the partial sums up
    in a tree, and only the ``d x (d + m)`` sums reach the client: the step's features never
    do. Equal to the local chunked sums up to the order of the additions.
    """
    import dask.array as da

    x = field.array[h]
    x = x.rechunk((x.chunks[0], -1))  # chunks along trajectories only
    K, d = x.shape
    cols = [np.asarray(c, dtype=np.float64) for c in cols]
    widths = [1 if c.ndim == 1 else int(np.prod(c.shape[1:])) for c in cols]
    m = sum(widths)
    y = np.empty((K, m + (0 if weights is None else 1)))
    if m:
        y[:, :m] = np.column_stack([c.reshape(K, -1) for c in cols])
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        y[:, :m] *= w[:, None]
        y[:, m] = w
    g = d if with_gram else 0
    width = g + m

    def block(xb, yb):
        xb = np.asarray(xb, dtype=np.float64)
        out = np.empty((d, width))
        if with_gram:
            xw = xb if weights is None else xb * yb[:, m:]
            out[:, :d] = xw.T @ xb
        out[:, g:] = xb.T @ yb[:, :m]
        return out.reshape(1, d * width)

    nb = len(x.chunks[0])
    parts = da.map_blocks(block, x, da.from_array(y, chunks=(x.chunks[0], -1)),
                          chunks=((1,) * nb, (d * width,)), dtype=np.float64)
    total = np.asarray(parts.sum(axis=0).compute(), dtype=np.float64).reshape(d, width)
    gram = total[:, :d].copy() if with_gram else None
    out, at = [], g
    for c, k in zip(cols, widths, strict=True):
        piece = total[:, at:at + k]
        out.append(piece[:, 0].copy() if c.ndim == 1 else piece.reshape((d,) + c.shape[1:]))
        at += k
    return gram, out


def _as_float64(a):
    if a is None:
        return None
    return np.ascontiguousarray(a, dtype=np.float64)


# --------------------------------------------------------------------------- the source
class StepSource:
    """The per-step provider behind an :class:`~r2pvi.OfflineDataset`.

    ``phi (H, K, d)`` and ``rewards (H, K)`` fields, a :class:`NextStates`, trajectory-major
    extras and cached facts. The engine calls :meth:`phi_step`, :meth:`rewards_step` and
    :meth:`next_state_values`; nothing else of the data is read while fitting.
    """

    def __init__(self, phi: Field, rewards: Field, nxt: NextStates, extras=None,
                 nonnegative_phi: bool | None = None, chunk: int = CHUNK, grams=None,
                 sums=None):
        self.phi, self.rewards, self.next = phi, rewards, nxt
        self.extras = dict(extras or {})
        self.nonnegative_phi = nonnegative_phi
        self.chunk = int(chunk)
        self.horizon, self.n_trajectories, self.n_features = phi.shape
        # Phi_h^T Phi_h of every step (float64, no ridge), a cache: stored with the data, or
        # kept from the first fit that formed them (see gram()).
        self._grams = [None] * self.horizon if grams is None else list(grams)
        # Phi_h^T 1 (column sums; E(1) = Lambda^-1 of them), cached the same way.
        self._sums = [None] * self.horizon if sums is None else list(sums)

    def gram(self, h: int) -> np.ndarray | None:
        """The unweighted ``Phi_h^T Phi_h (d, d)`` of step ``h`` if known (stored with the
        dataset or formed by an earlier fit), else None. A copy: the caller may modify it."""
        g = self._grams[h]
        return None if g is None else np.array(g, dtype=np.float64)

    def remember_gram(self, h: int, gram: np.ndarray) -> None:
        """Keep ``Phi_h^T Phi_h`` (formed by a fit) for later fits; kept for
        ``d <= GRAM_CACHE_MAX_D`` only (``H d^2`` floats)."""
        if self.n_features <= GRAM_CACHE_MAX_D and self._grams[h] is None:
            g = np.array(gram, dtype=np.float64)
            g.flags.writeable = False
            self._grams[h] = g

    def phi_sums(self, h: int) -> np.ndarray | None:
        """The column sums ``Phi_h^T 1 (d,)`` of step ``h`` if known (stored with the dataset
        or formed by an earlier fit), else None. A copy."""
        c = self._sums[h]
        return None if c is None else np.array(c, dtype=np.float64)

    def remember_phi_sums(self, h: int, sums: np.ndarray) -> None:
        """Keep ``Phi_h^T 1`` (formed by a fit) for later fits."""
        if self._sums[h] is None:
            c = np.array(sums, dtype=np.float64)
            c.flags.writeable = False
            self._sums[h] = c

    @property
    def n_actions(self) -> int:
        return self.next.n_actions

    def phi_step(self, h: int, out: np.ndarray | None = None) -> np.ndarray:
        """Step ``h``'s taken-action features ``(K, d)`` as float64: a view when they are
        stored so in memory, else written into ``out`` (a reused buffer) or a new array."""
        field = self.phi
        if isinstance(field, DaskField) or (isinstance(field, ArrayField) and (
                field.dtype == np.float64 or out is None)):
            return _as_float64(field.read(h))
        shape = (self.n_trajectories, self.n_features)
        if out is None or out.shape != shape or out.dtype != np.float64:
            out = np.empty(shape)
        if isinstance(field, ArrayField):
            np.copyto(out, field.read(h))
            return out
        if isinstance(field, FileField):
            chunk_shape = (min(self.chunk, shape[0]), shape[1])
            for s, e, rows in _prefetched(field, h, shape[0], self.chunk, chunk_shape):
                out[s:e] = rows
            return out
        for s in range(0, shape[0], self.chunk):
            e = min(shape[0], s + self.chunk)
            out[s:e] = field.read(h, s, e)
        return out

    def phi_chunks(self, h: int):
        """``(start, stop, rows)`` over step ``h``'s taken-action features, ``rows`` a float64
        ``(stop - start, d)`` array valid until the next iteration (reused buffers; on disk
        a reader thread fetches the next chunk while the caller computes on this one)."""
        field, K = self.phi, self.n_trajectories
        shape = (min(self.chunk, K), self.n_features)
        if isinstance(field, FileField):
            yield from _prefetched(field, h, K, self.chunk, shape)
            return
        reads = field.chunks(h, self.chunk)  # a Dask array: its own chunks
        f64 = None
        for s, e, rows in reads:
            if rows.dtype != np.float64 or not rows.flags.c_contiguous:
                if f64 is None or f64.shape[0] < e - s:
                    f64 = np.empty((max(e - s, shape[0]), shape[1]))
                np.copyto(f64[: e - s], rows)
                rows = f64[: e - s]
            yield s, e, rows

    def remote_products(self, h: int, cols, weights=None, with_gram: bool = True):
        """``(Phi_h^T W Phi_h or None, [Phi_h^T W c for c in cols])`` formed where the data
        is (the Dask workers) for features held as Dask arrays; None for data the client
        reads itself (memory, files, computed features), which the engine sums by chunk."""
        if not isinstance(self.phi, DaskField):
            return None
        return _dask_products(self.phi, h, cols, weights, with_gram)

    def phi_times(self, h: int, z: np.ndarray) -> np.ndarray:
        """``Phi_h @ z`` (``(K,)`` or ``(K, m)``, float64): in memory one product, on disk by
        chunk, for Dask arrays on the workers (one task per trajectory chunk)."""
        field = self.phi
        if isinstance(field, DaskField):
            x = field.array[h]
            x = x.rechunk((x.chunks[0], -1))
            out = x.map_blocks(lambda b: np.asarray(b, dtype=np.float64) @ z,
                               chunks=(x.chunks[0],) + z.shape[1:], dtype=np.float64,
                               drop_axis=None if z.ndim == 2 else 1)
            return np.asarray(out.compute(), dtype=np.float64)
        if isinstance(field, ArrayField) and field.dtype == np.float64:
            return field.read(h) @ z
        out = np.empty((self.n_trajectories,) + z.shape[1:])
        for s, e, rows in self.phi_chunks(h):
            out[s:e] = rows @ z
        return out

    def rewards_step(self, h: int) -> np.ndarray:
        return _as_float64(self.rewards.read(h))

    def next_state_values(self, h: int, qmax, out: np.ndarray | None = None) -> np.ndarray:
        """``V_{h+1}`` at the K sampled next states; ``qmax(feats (n, A, d), known, nonneg)``;
        written into ``out (K,)`` when given (returned)."""
        if out is not None and isinstance(self.next, StoredNext):
            return self.next.values(h, qmax, self.n_trajectories, self.chunk, out=out)
        v = self.next.values(h, qmax, self.n_trajectories, self.chunk)
        if out is None:
            return v
        out[...] = v
        return out

    def take(self, idx) -> StepSource:
        extras = {}
        for k, v in self.extras.items():
            extras[k] = np.asarray(v[idx])
            extras[k].flags.writeable = False
        phi = self.phi
        phi = MappedField(ArrayField(phi.observations.take(idx)),
                          ArrayField(phi.actions.take(idx)), phi.feature_map,
                          phi.shape[2]) if isinstance(phi, MappedField) else ArrayField(
                              phi.take(idx))
        return StepSource(phi, ArrayField(self.rewards.take(idx)),
                          self.next.take(idx), extras, self.nonnegative_phi, self.chunk)


# --------------------------------------------------------------------------- validation
def simplex_flags(x: np.ndarray, atol: float = 1e-8) -> tuple[bool, bool]:
    """``(negative entries, rows not summing to 1)`` of feature rows (last axis)."""
    if x.size == 0:
        return False, False
    return bool((x < -atol).any()), bool((np.abs(x.sum(axis=-1) - 1.0) > 1e-6).any())


def warn_simplex(name: str, negative: bool, off_sum: bool, stacklevel: int = 3) -> bool:
    """Warn with :class:`SimplexFeatureWarning` when a flag is set; True when on the simplex."""
    if not (negative or off_sum):
        return True
    what = " and ".join(
        w for w, bad in (("negative entries", negative), ("rows not summing to 1", off_sum))
        if bad
    )
    warnings.warn(
        f"{name} has {what}: the paper's simplex assumption (phi_i >= 0, sum_i phi_i = 1) "
        "does not hold. The algorithms still run; the d-rectangular guarantees do not apply.",
        SimplexFeatureWarning,
        stacklevel=stacklevel + 1,
    )
    return False


def step_major(x, name: str, ndim: int, dtype=None) -> np.ndarray:
    """``x (K, H, ...)`` as a C-contiguous step-major float array ``(H, K, ...)``.

    No copy when ``x`` already is one in memory (e.g. ``a.transpose(1, 0, ...)`` of a
    C-contiguous ``(H, K, ...)`` array of float32 or float64); otherwise exactly one.
    """
    raw = np.asarray(x) if not isinstance(x, str) else None
    if raw is None or raw.dtype.kind not in "biuf":
        if raw is not None and raw.dtype.kind == "c":
            raise TypeError(f"{name} must be real, got a complex array")
        kind = type(x).__name__ if raw is None else f"an array of dtype {raw.dtype}"
        raise TypeError(f"{name} must be a numeric (float) array, got {kind}")
    if raw.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {raw.shape}")
    target = np.dtype(dtype) if dtype is not None else (
        raw.dtype if raw.dtype in (np.float32, np.float64) else np.dtype(np.float64))
    sm = raw.swapaxes(0, 1)
    if sm.dtype == target and sm.flags.c_contiguous:
        return sm
    return np.ascontiguousarray(sm, dtype=target)


def layout_step_major(x: np.ndarray) -> np.ndarray:
    """``x (K, H, ...)`` as a C-contiguous ``(H, K, ...)`` array of any dtype: a view when
    it already is one (e.g. a transposed memory map), else one copy."""
    sm = np.asarray(x).swapaxes(0, 1)
    return sm if sm.flags.c_contiguous else np.ascontiguousarray(sm)


def check_features_chunk(phi, rewards, next_phi, next_values, last_step: bool,
                         simplex: bool = True):
    """Validate one chunk of step-major rows; returns ``(phi, next_phi)`` simplex flags
    and non-negativity: ``(neg_phi, off_phi, neg_next, off_next, nonneg_phi, nonneg_next)``.

    ``last_step`` marks rows of ``h = H-1`` whose next-state data is never used. With
    ``simplex=False`` the simplex flags (row sums: most of the work) are not computed and
    returned False; everything else is checked the same.
    """
    for name, x in (("phi", phi), ("rewards", rewards)):
        if not np.isfinite(x).all():
            raise ValueError(f"{name} contains {int(np.count_nonzero(~np.isfinite(x)))} NaN or "
                             "infinite entries; clean the data first")
    if next_values is not None and not last_step and np.isinf(next_values).any():
        raise ValueError(f"next_values contains {int(np.count_nonzero(np.isinf(next_values)))} "
                         "infinite entries; use NaN where the value must be learned")
    flags = simplex_flags(phi) if simplex else (False, False)
    nonneg_phi = bool((phi >= 0).all())
    if last_step or next_phi is None:
        return flags + (False, False, nonneg_phi, True)
    finite = np.isfinite(next_phi).all(axis=-1)
    if not finite.all():
        # An action whose value is known needs no features: its row may be left NaN.
        known = np.zeros(finite.shape, bool) if next_values is None else ~np.isnan(next_values)
        if not (finite | known).all():
            raise ValueError(
                "next_phi contains NaN or infinite entries in steps h < H-1 where no value is "
                "known (only the last step's row and actions with a known next_values entry "
                "may be left undefined)"
            )
    # NaN rows (known values) count as neither negative nor off the simplex.
    next_flags = simplex_flags(next_phi) if simplex else (False, False)
    return flags + next_flags + (nonneg_phi, not bool((next_phi < 0).any()))


def validate_source(phi, rewards, next_phi, next_values, check_simplex=True, chunk=CHUNK,
                    stacklevel=3):
    """Validate step-major arrays chunk by chunk (no full-size temporaries).

    Returns ``(nonnegative_phi, nonnegative_next_phi, any_known)``.
    """
    H, K, _ = phi.shape
    acc = [False, False, False, False, True, True]
    any_known = False
    for h in range(H):
        last = h == H - 1
        for s in range(0, K, chunk):
            e = min(K, s + chunk)
            nv = None if next_values is None else next_values[h, s:e]
            try:
                flags = check_features_chunk(
                    phi[h, s:e], rewards[h, s:e],
                    None if next_phi is None else next_phi[h, s:e], nv, last, check_simplex)
            except ValueError as exc:
                raise _counted(exc, phi, rewards, next_values, chunk) from None
            for i in range(4):
                acc[i] = acc[i] or flags[i]
            acc[4] = acc[4] and flags[4]
            acc[5] = acc[5] and flags[5]
            if nv is not None and not last and not any_known:
                any_known = bool((~np.isnan(nv)).any())
    if check_simplex:
        warn_simplex("phi", acc[0], acc[1], stacklevel)
        if next_phi is not None:
            warn_simplex("next_phi", acc[2], acc[3], stacklevel)
    return acc[4], acc[5], any_known


def _counted(exc: ValueError, phi, rewards, next_values, chunk) -> ValueError:
    """The error of one chunk, with the count of bad entries over the whole field."""
    msg = str(exc)
    name = msg.split(" ", 1)[0]
    field = {"phi": phi, "rewards": rewards, "next_values": next_values}.get(name)
    if field is None or " contains " not in msg:
        return exc
    bad = np.isinf if name == "next_values" else (lambda x: ~np.isfinite(x))
    H, K = field.shape[:2]
    n = sum(int(np.count_nonzero(bad(field[h, s:s + chunk])))
            for h in range(H - (name == "next_values")) for s in range(0, K, chunk))
    rest = msg.split(" entries", 1)[1] if " entries" in msg else ""
    kind = "infinite" if name == "next_values" else "NaN or infinite"
    return ValueError(f"{name} contains {n} {kind} entries{rest}")


# --------------------------------------------------------------------------- on disk
def _manifest(path: Path) -> dict:
    mf = path / MANIFEST
    if not mf.is_file():
        raise ValueError(f"{path} is not an r2pvi dataset directory (no {MANIFEST})")
    with open(mf) as fh:
        header = json.load(fh)
    if header.get("kind") != KIND:
        raise ValueError(f"{path} holds a {header.get('kind')!r}, not a {KIND!r}")
    version = header.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise ValueError(
            f"{path} has format version {version!r}; this r2pvi reads versions <= "
            f"{FORMAT_VERSION}: upgrade r2pvi"
        )
    return header


def open_directory(path, feature_map=None) -> StepSource:
    """A :class:`StepSource` over a dataset directory; nothing is read but the headers.

    A dataset stored as observations (``"phi": "map"`` or ``"next": "map"`` in the
    manifest) needs the ``feature_map`` it was built with."""
    path = Path(os.fspath(path))
    if not path.exists():
        raise FileNotFoundError(f"no such dataset directory: {path}")
    mf = _manifest(path)
    files = mf["files"]

    def field(name):
        f = FileField(path / files[name])
        if list(f.shape) != list(mf["shapes"][name]):
            raise ValueError(f"{path / files[name]} has shape {f.shape}, the manifest says "
                             f"{mf['shapes'][name]}")
        return f

    needs_map = mf.get("phi", "stored") == "map" or mf["next"] == "map"
    if needs_map and not callable(feature_map):
        raise ValueError(
            f"{path} stores observations, not features: pass the feature_map it was built "
            "with, OfflineDataset.open(path, feature_map=f) with f(observations, actions) -> "
            "(n, d)")
    d = int(mf["n_features"])
    if mf.get("phi", "stored") == "map":
        phi: Field = MappedField(field("observations"), field("actions"), feature_map, d)
    else:
        phi = field("phi")
    rewards = field("rewards")
    if mf["next"] == "map":
        kv = field("next_values") if "next_values" in files else None
        nxt: NextStates = MapNext(field("next_observations"), feature_map,
                                  int(mf["n_actions"]), d, kv)
    elif mf["next"] == "stored":
        nxt = StoredNext(field("next_phi"),
                                     field("next_values") if "next_values" in files else None,
                                     mf.get("nonnegative_next_phi"))
    elif mf["next"] == "behaviour":
        nxt = _open_behaviour(path, mf, field, phi)
    elif mf["next"] == "table":
        table = np.load(path / files["next_table"], allow_pickle=False)
        kt = (np.load(path / files["next_table_values"], allow_pickle=False)
              if "next_table_values" in files else None)
        nxt = TableNext(field("next_index"), table, kt)
    else:
        raise ValueError(f"{path}: unknown next-state form {mf['next']!r}")
    extras = {}
    for name in mf.get("extras", []):
        extras[name] = np.load(path / f"extra_{name}.npy", mmap_mode="r", allow_pickle=False)
    grams = None
    if "gram" in files:
        grams = np.load(path / files["gram"], allow_pickle=False)
        H, d_ = int(mf["horizon"]), int(mf["n_features"])
        if grams.shape != (H, d_, d_) or grams.dtype != np.float64:
            raise ValueError(f"{path / files['gram']} must hold (H, d, d) = {(H, d_, d_)} "
                             f"float64 Gram matrices, got {grams.shape} {grams.dtype}")
    sums = None
    if "phi_sums" in files:  # optional (datasets written before it have none)
        sums = np.load(path / files["phi_sums"], allow_pickle=False)
        H, d_ = int(mf["horizon"]), int(mf["n_features"])
        if sums.shape != (H, d_) or sums.dtype != np.float64:
            raise ValueError(f"{path / files['phi_sums']} must hold (H, d) = {(H, d_)} "
                             f"float64 column sums, got {sums.shape} {sums.dtype}")
    return StepSource(phi, rewards, nxt, extras, mf.get("nonnegative_phi"), grams=grams,
                      sums=sums)


def _open_behaviour(path: Path, mf: dict, field, phi: Field) -> BehaviourNext:
    """The behaviour form's fields, checked against the manifest (each error names the
    field)."""
    files = mf["files"]
    spec = mf.get("next_behaviour")
    if not isinstance(spec, dict) or not isinstance(spec.get("version"), int):
        raise ValueError(f"{path}: the manifest's 'next_behaviour' entry (a dict with a "
                         "'version') is missing or malformed")
    if spec["version"] > BEHAVIOUR_VERSION:
        raise ValueError(f"{path}: next_behaviour version {spec['version']}; this r2pvi reads "
                         f"versions <= {BEHAVIOUR_VERSION}: upgrade r2pvi")
    for name in ("next_action", "next_rest", "next_side", "next_side_offsets"):
        if name not in files or name not in mf.get("shapes", {}):
            raise ValueError(f"{path}: the manifest lists no {name!r} field, which the "
                             "behaviour next-state form needs")
        if not (path / files[name]).is_file():
            raise ValueError(f"{path}: the {name!r} field's file {files[name]} is missing")
    if not isinstance(phi, FileField):
        raise ValueError(f"{path}: the behaviour next-state form needs stored features "
                         "('phi': 'stored')")
    H, K, d = phi.shape
    A = int(mf["n_actions"])
    store = phi.dtype
    action, rest = field("next_action"), field("next_rest")
    if action.dtype.kind != "i":
        raise ValueError(f"{path}: next_action must hold signed integers, got {action.dtype}")
    if action.shape != (H, K):
        raise ValueError(f"{path}: next_action has shape {action.shape}, expected {(H, K)}")
    if rest.shape != (H, K, A - 1, d) or rest.dtype != store:
        raise ValueError(f"{path}: next_rest must be {(H, K, A - 1, d)} {store}, got "
                         f"{rest.shape} {rest.dtype}")
    side = RowFile(path / files["next_side"])
    if list(side.shape) != list(mf["shapes"]["next_side"]) or side.shape[1:] != (d,) or \
            side.dtype != store:
        raise ValueError(f"{path}: next_side must be (n_side, d) {store} as the manifest says "
                         f"{mf['shapes']['next_side']}, got {side.shape} {side.dtype}")
    offsets = np.load(path / files["next_side_offsets"], allow_pickle=False)
    if (offsets.shape != (H + 1,) or offsets.dtype.kind not in "iu" or offsets[0] != 0
            or (np.diff(offsets) < 0).any() or (np.diff(offsets) > K).any()
            or offsets[-1] != side.shape[0] or offsets[-1] - offsets[-2] != K
            or spec.get("n_side") != side.shape[0]):
        raise ValueError(
            f"{path}: next_side_offsets must be (H+1,) = ({H + 1},) non-decreasing integers "
            f"from 0 to the side table's {side.shape[0]} rows (at most K per step, K at the "
            "last step, n_side in the manifest): the dataset is corrupt")
    kv = field("next_values") if "next_values" in files else None
    return BehaviourNext(action, rest, phi, side, offsets, kv, mf.get("nonnegative_next_phi"))


def _temp_dir(path: Path) -> Path:
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    return tmp


def _finish(tmp: Path, path: Path, manifest: dict, overwrite: bool) -> Path:
    with open(tmp / MANIFEST, "w") as fh:
        json.dump(manifest, fh, indent=1, sort_keys=True)
    if path.exists():
        if not overwrite:
            shutil.rmtree(tmp, ignore_errors=True)
            raise FileExistsError(f"{path} exists; pass overwrite=True or choose a new path")
        old = path.parent / f".{path.name}.old-{uuid.uuid4().hex[:8]}"
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, path)  # atomic: readers see the old state or the complete dataset
    return path


def _add_gram(gram: np.ndarray, rows: np.ndarray, sums: np.ndarray) -> None:
    """``gram += X^T X`` and ``sums += X^T 1`` for rows ``X (n, d)`` in float64 (by blocks of
    ``CHUNK`` rows)."""
    for s in range(0, rows.shape[0], CHUNK):
        x = np.asarray(rows[s:s + CHUNK], dtype=np.float64)
        gram += x.T @ x
        sums += np.ones(x.shape[0]) @ x


def _write_npy_header(fh, shape, dtype):
    np.lib.format.write_array_header_2_0(
        fh, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False,
             "shape": tuple(int(s) for s in shape)})


def _stream_field(out_path: Path, field: Field, dtype, chunk: int, transform=None):
    """Write ``field`` step by step into a .npy file (bounded memory)."""
    with open(out_path, "wb") as fh:
        _write_npy_header(fh, field.shape, dtype)
        for h in range(field.shape[0]):
            for s, e, rows in field.chunks(h, chunk):
                if transform is not None:
                    rows = transform(h, s, e, rows)
                fh.write(np.ascontiguousarray(rows, dtype=dtype).tobytes())


class _Computed(Field):
    """A field computed by a function of (h, start, stop): next_phi of a feature map."""

    def __init__(self, shape, dtype, fn):
        self.shape, self.dtype, self.fn = tuple(shape), np.dtype(dtype), fn

    def read(self, h, start=0, stop=None):
        return self.fn(h, start, self.shape[1] if stop is None else stop)


def write_directory(source: StepSource, path, *, dtype=None, overwrite=False,
                    next_form="full") -> Path:
    """Write ``source`` in the on-disk format (streamed step by step; atomic rename).

    ``next_form="behaviour"`` stores stored next-state features without the rows that equal
    the next step's taken-action features (:class:`BehaviourNext`)."""
    path = Path(os.fspath(path))
    next_form = _next_form(next_form)
    store = np.dtype(dtype) if dtype is not None else np.dtype(
        np.float32 if source.phi.dtype == np.float32 else np.float64)
    if store not in (np.float32, np.float64):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    tmp = _temp_dir(path)
    try:
        files, shapes = {}, {}

        def put(name, field, dt, transform=None):
            files[name] = name + ".npy"
            shapes[name] = list(field.shape)
            _stream_field(tmp / files[name], field, dt, source.chunk, transform)

        phi_kind = "stored"
        if next_form == "behaviour" and (isinstance(source.phi, MappedField) or isinstance(
                source.next, MapNext | TableNext)):
            raise ValueError(
                "next_form='behaviour' applies to stored next-state features; this dataset "
                "stores observations or next-state indices, which hold no next-state features "
                "to spare: save it with next_form='full'")
        if isinstance(source.phi, MappedField):  # store what it is computed from
            phi_kind = "map"
            put("observations", source.phi.observations, source.phi.observations.dtype)
            put("actions", source.phi.actions, source.phi.actions.dtype)
        else:  # with the Gram matrices of the stored (rounded) features, as they stream by
            grams = np.zeros((source.horizon, source.n_features, source.n_features))
            sums = np.zeros((source.horizon, source.n_features))

            def gram_of_stored(h, s, e, rows):
                rows = np.asarray(rows, dtype=store)
                _add_gram(grams[h], rows, sums[h])
                return rows

            put("phi", source.phi, store, gram_of_stored)
            files["gram"] = GRAM_FILE
            np.save(tmp / GRAM_FILE, grams, allow_pickle=False)
            files["phi_sums"] = SUMS_FILE
            np.save(tmp / SUMS_FILE, sums, allow_pickle=False)
        put("rewards", source.rewards, np.float64)
        nxt = source.next
        H, K, d = source.phi.shape
        A = nxt.n_actions
        meta = {"nonnegative_phi": source.nonnegative_phi, "phi": phi_kind}
        if isinstance(nxt, MapNext):
            kind = "map"
            put("next_observations", nxt.observations, nxt.observations.dtype)
            if nxt.has_known_values:
                put("next_values", _Computed((H, K, A), np.float64,
                                             lambda h, s, e: nxt.known(h, s, e)), np.float64)
        elif isinstance(nxt, TableNext):
            kind = "table"
            put("next_index", nxt.index, np.int64)
            files["next_table"] = "next_table.npy"
            np.save(tmp / files["next_table"], np.asarray(nxt.table), allow_pickle=False)
            if nxt.known_table is not None:
                files["next_table_values"] = "next_table_values.npy"
                np.save(tmp / files["next_table_values"], nxt.known_table, allow_pickle=False)
        else:
            kind = "stored"
            feats = nxt.next_phi if isinstance(nxt, StoredNext) else _Computed(
                (H, K, A, d), store, nxt.features)
            if next_form == "behaviour":
                kind = "behaviour"
                meta["next_behaviour"] = _write_behaviour(tmp, files, shapes, source.phi,
                                                          feats, store, source.chunk)
            else:
                put("next_phi", feats, store,
                    lambda h, s, e, rows: np.nan_to_num(rows, nan=0.0) if h == H - 1 else rows)
            if nxt.has_known_values:
                kv = nxt.next_values if isinstance(nxt, StoredNext) else _Computed(
                    (H, K, A), np.float64,
                    lambda h, s, e: nxt.known(h, s, e))
                put("next_values", kv, np.float64)
            meta["nonnegative_next_phi"] = nxt.nonnegative
        extras = []
        for name, value in source.extras.items():
            value = np.asarray(value)
            if value.dtype.hasobject:
                raise TypeError(f"cannot save {name!r}: object arrays are not supported")
            np.save(tmp / f"extra_{name}.npy", value, allow_pickle=False)
            extras.append(name)
        manifest = {
            "kind": KIND, "format_version": FORMAT_VERSION, "layout": "step-major",
            "n_trajectories": K, "horizon": H, "n_features": d, "n_actions": A,
            "dtype": store.name, "next": kind, "files": files, "shapes": shapes,
            "extras": extras, **meta,
        }
        return _finish(tmp, path, manifest, overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _behaviour_files(files, shapes, H, K, A, d, n_side):
    names = {"next_action": (H, K), "next_rest": (H, K, A - 1, d), "next_side": (n_side, d),
             "next_side_offsets": (H + 1,)}
    for name, shape in names.items():
        files[name] = name + ".npy"
        shapes[name] = list(shape)
    return {"version": BEHAVIOUR_VERSION, "n_side": int(n_side)}


def _write_behaviour(tmp: Path, files, shapes, phi: Field, next_phi: Field, store, chunk):
    """Stream ``next_phi`` into the behaviour form's files (see :class:`BehaviourNext`)."""
    H, K, A, d = next_phi.shape
    offsets = np.zeros(H + 1, dtype=np.int64)
    raw = tmp / "next_side.raw"
    with open(tmp / "next_action.npy", "wb") as fa, open(tmp / "next_rest.npy", "wb") as fr, \
            open(raw, "wb") as fs:
        _write_npy_header(fa, (H, K), _action_dtype(A))
        _write_npy_header(fr, (H, K, A - 1, d), store)
        for h in range(H):
            for s, e, rows in next_phi.chunks(h, chunk):
                rows = np.ascontiguousarray(rows, dtype=store)
                if h == H - 1:
                    rows = np.nan_to_num(rows, nan=0.0)
                    following = None
                else:
                    following = np.ascontiguousarray(phi.read(h + 1, s, e), dtype=store)
                action, rest, side = behaviour_split(following, rows)
                fa.write(action.tobytes())
                fr.write(np.ascontiguousarray(rest).tobytes())
                fs.write(np.ascontiguousarray(side).tobytes())
                offsets[h + 1] += side.shape[0]
    offsets = np.cumsum(offsets)
    n_side = int(offsets[-1])
    with open(tmp / "next_side.npy", "wb") as fh, open(raw, "rb") as fs:
        _write_npy_header(fh, (n_side, d), store)
        shutil.copyfileobj(fs, fh, 1 << 22)
    raw.unlink()
    np.save(tmp / "next_side_offsets.npy", offsets, allow_pickle=False)
    return _behaviour_files(files, shapes, H, K, A, d, n_side)


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
        Replace an existing dataset at ``path``.
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
                 check_simplex=True, overwrite=False, next_form="full"):
        from ._validation import check_scalar

        self.path = Path(os.fspath(path))
        self.horizon = check_scalar(horizon, "horizon", low=1, integer=True)
        self.n_features = check_scalar(n_features, "n_features", low=1, integer=True)
        self.n_actions = check_scalar(n_actions, "n_actions", low=1, integer=True)
        self.dtype = _float_dtype(dtype)
        self.check_simplex = check_simplex
        self.overwrite = overwrite
        self.next_form = _next_form(next_form)
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path} exists; pass overwrite=True or choose a new path")
        self._tmp: Path | None = _temp_dir(self.path)
        # A writer dropped without close() leaves no temporary directory behind.
        self._cleanup = weakref.finalize(self, shutil.rmtree, str(self._tmp), True)
        self._shards: list[tuple[int, bool]] = []  # (K of the chunk, has next_values)
        self._flags = [False, False, False, False, True, True]
        self.n_trajectories = 0

    def append(self, phi, rewards, next_phi, next_values=None) -> None:
        """Validate and write a chunk of trajectories: ``phi (k, H, d)``, ``rewards (k, H)``,
        ``next_phi (k, H, A, d)``, optional ``next_values (k, H, A)``."""
        if self._tmp is None:
            raise RuntimeError("this DatasetWriter is closed")
        H, d, A = self.horizon, self.n_features, self.n_actions
        p = step_major(phi, "phi", 3, self.dtype)
        k = p.shape[1]
        if p.shape != (H, k, d) or k == 0:
            raise ValueError(f"phi must have shape (k, H, d) = (k, {H}, {d}) with k >= 1, got "
                             f"{np.shape(phi)}")
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
        for h in range(H):
            f = check_features_chunk(p[h], r[h], n[h], None if nv is None else nv[h],
                                     h == H - 1, self.check_simplex)
            for i in range(4):
                self._flags[i] = self._flags[i] or f[i]
            self._flags[4] &= f[4]
            self._flags[5] &= f[5]
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
                                _add_gram(grams[h], rows, sums[h])
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
                "kind": KIND, "format_version": FORMAT_VERSION, "layout": "step-major",
                "n_trajectories": K, "horizon": H, "n_features": d, "n_actions": A,
                "dtype": self.dtype.name, "next": "behaviour" if behaviour else "stored",
                "files": {**files, "gram": GRAM_FILE, "phi_sums": SUMS_FILE}, "shapes": shapes,
                "extras": [], "nonnegative_phi": fl[4], "nonnegative_next_phi": fl[5],
                **extra,
            }
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
