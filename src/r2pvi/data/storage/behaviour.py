"""The behaviour next-state form: next-state features stored without the row of the
trajectory's next taken action (``phi[k, h+1]``), rebuilt bitwise when read."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from ._finite import Origin, array_origin, file_origin, nonfinite_error
from .fields import Field, _as_float64
from .memory import ArrayField
from .next_states import NextStates, StoredNext
from .npy import _write_npy_header, npy_header

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

    def __init__(self, path, name: str = "next_side"):
        self.path = Path(path)
        self.shape, self.dtype, self.offset = npy_header(self.path, name, 1)
        self._row = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize

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
            got = self.phi.read(h + 1, start, stop, out=src)  # into src, or a view
            if got is not src:
                np.copyto(src, got)
        if any_miss:
            src[miss] = self._side(h, start, stop, before)
        if A == 2:  # read straight into the stage (files), or copied from a view
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

    def origin(self, known=False):
        return (self.next_values.origin("next_values") if known
                else self.rest.origin("next_rest"))

    def nonfinite(self, h, s, exc):
        """Name the file the bad row was rebuilt from: the next step's taken-action features,
        the side table or the other actions' rows."""
        if exc.known:
            return super().nonfinite(h, s, exc)
        i, a, j = exc.index
        k = s + i
        act = self._index(h)[0]
        m = int(act[k])
        if m == a:
            origin, idx = self.phi.origin("phi"), [h + 1, k, j]
        elif m < 0 and a == 0:
            miss = self._index(h)[1][0]
            row = int(self.offsets[h]) + int(np.count_nonzero(miss[:k]))
            origin = (file_origin(self.side.path) if isinstance(self.side, RowFile)
                      else array_origin("next_side"))
            idx = [row, j]
        else:
            origin, idx = self.rest.origin("next_rest"), [h, k, a - (a > max(m, 0)), j]
        return nonfinite_error(origin, h, k, exc.value, action=a, feature=j, file_index=idx)

    def values(self, h, qmax, n, chunk, out=None):
        index = self._index(h)
        A, d = self.n_actions, self.rest.shape[3]
        m = min(chunk, n)
        stage = np.empty((A, m, d), self.rest.dtype)  # reused buffers, as StoredNext's
        order = np.empty((m, A), dtype=np.intp)
        rows = np.arange(m)
        f64 = np.empty((m, A, d))
        out = np.empty(n) if out is None else out
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            feats = f64[: e - s]
            o = self._order(index[2], s, e, rows[: e - s], m, order[: e - s])
            np.copyto(feats, self._staged(h, s, e, index, stage, o))
            out[s:e] = self._chunk_values(h, s, e, feats, qmax)
        return out

    def take(self, idx):
        idx = np.asarray(idx)
        feats = np.stack([self.features(h)[idx] for h in range(self.rest.shape[0])])
        nv = None if self.next_values is None else ArrayField(self.next_values.take(idx))
        rebuilt = self.rest.origin("next_rest")
        rebuilt = Origin(f"next_phi rebuilt from {rebuilt.label} and the files beside it "
                         "(selected trajectories)", rebuilt.fix)
        return StoredNext(ArrayField(feats, rebuilt), nv, self.nonnegative)


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
