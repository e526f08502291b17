"""The step source: the per-step provider the engine reads while fitting."""

from __future__ import annotations

import numpy as np

from ._finite import (
    FIELDS,
    check_step_rewards,
    file_origin,
    first_nonfinite,
)
from .fields import CHUNK, Field, _as_float64
from .next_states import NextStates
from .sparse_rows import stack_rows

GRAM_CACHE_MAX_D = 512  # Gram matrices Phi_h^T Phi_h are cached (H d^2 floats) up to this d


class StepSource:
    """The per-step provider behind an :class:`~r2pvi.OfflineDataset`.

    ``phi (H, K, d)`` and ``rewards (H, K)`` fields, a :class:`NextStates`, trajectory-major
    extras and cached facts. While fitting, the engine reads the data only through
    :meth:`phi_chunks` (a step's features by chunk), :meth:`phi_step` (a whole step, for rules
    that need explicit rows), :meth:`remote_products` (Dask: sums formed on the workers),
    :meth:`phi_times`, :meth:`rewards_step` and :meth:`next_state_values`; :meth:`gram` and
    :meth:`phi_sums` give cached or stored sums.

    ``checked`` names the fields (``"phi"``, ``"rewards"``, ``"next"``) whose every number
    was checked when the source was built (finite; the rewards' range taken); a fit checks
    the others as it reads them (``data.storage._finite``). Stored ``grams`` and ``sums`` are
    checked here (``H d^2`` numbers); ``stored_files`` maps ``"gram"`` and ``"phi_sums"`` to
    the files they were read from, for the errors; ``range_recorded`` says that
    ``reward_range`` is what a directory's manifest records (named by the errors).

    The source never says which storage kind it holds: each field offers the reads and
    products a fit needs (see :class:`~r2pvi.data.storage.fields.Field`).
    """

    def __init__(self, phi: Field, rewards: Field, nxt: NextStates, extras=None,
                 nonnegative_phi: bool | None = None, chunk: int = CHUNK, grams=None,
                 sums=None, unit_rows: bool = False, reward_range=None,
                 reward_noise: float = 0.0, row_sums=None, checked=(), stored_files=None,
                 range_recorded: bool = False, stationary: bool = False,
                 reward_offset: float = 0.0):
        self.phi, self.rewards, self.next = phi, rewards, nxt
        # The steps are draws of one stationary environment (OfflineDataset.stationary).
        self.stationary = bool(stationary)
        # The shift c added to every reward (episodes with reward_offset): a known next value
        # (an absorbing state's) holds (H - h - 1) c for the step h of its row. A pooled fit's
        # step h' uses (H - h' - 1) c there instead (see engine.pooled).
        self.reward_offset = float(reward_offset)
        self.checked = frozenset(checked)
        if not self.checked <= FIELDS:
            raise ValueError(f"checked must name fields among {sorted(FIELDS)}, got "
                             f"{sorted(self.checked)}")
        stored_files = dict(stored_files or {})
        for name, what, value in (("gram", "Gram matrix Phi_h^T Phi_h", grams),
                                  ("phi_sums", "column sums Phi_h^T 1", sums)):
            if value is not None:
                _check_stored(value, name, what, stored_files.get(name))
        # The range a directory's manifest records for its rewards file (named by errors).
        self._recorded_range = reward_range if range_recorded else None
        # The rewards' (min, max) when known (from validation or the manifest), else found
        # by reward_bounds() from the rewards alone (never the features) and kept.
        self.reward_range = None if reward_range is None else (
            float(reward_range[0]), float(reward_range[1]))
        # Standard deviation of zero-mean noise on the rewards (0: exact); see
        # OfflineDataset.reward_noise.
        self.reward_noise = float(reward_noise)
        self.extras = dict(extras or {})
        self.nonnegative_phi = nonnegative_phi
        # True when validation found every taken-action row summing to 1 (within
        # storage.checks.UNIT_ROW_ATOL): then Phi^T W 1 = Phi^T W Phi 1_d, the Gram
        # matrix's row sums, and E(1) needs no pass of its own.
        self.unit_rows = bool(unit_rows)
        # (low, high) of the taken-action rows' sums when known (validation, or a directory's
        # manifest): with non-negative rows it bounds phi_h^T theta_h without reading them.
        self.phi_row_sums = None if row_sums is None else (
            float(row_sums[0]), float(row_sums[1]))
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

    @property
    def dense_rows(self) -> bool:
        """Whether a step's taken-action rows are an ndarray (False: sparse rows), so that
        a step's operator can be accumulated by chunk."""
        return self.phi.dense_rows

    def phi_step(self, h: int, out: np.ndarray | None = None):
        """Step ``h``'s taken-action features ``(K, d)`` as float64: a view when they are
        stored so in memory, else written into ``out`` (a reused buffer) or a new array;
        sparse rows as they are stored (CSR)."""
        return self.phi.step_rows(h, self.chunk, out)

    def phi_chunks(self, h: int):
        """``(start, stop, rows)`` over step ``h``'s taken-action features, ``rows`` a float64
        ``(stop - start, d)`` array to read, valid until the next iteration and not to be
        written: a reused buffer, a view of an in-memory array, or (native float64 files) a
        read-only view of the memory-mapped file (see ``storage.files._prefetched``); copy
        what must outlive the iteration."""
        return self.phi.float64_chunks(h, self.chunk)

    def remote_products(self, h: int, cols, weights=None, with_gram: bool = True):
        """``(Phi_h^T W Phi_h or None, [Phi_h^T W c for c in cols])`` formed where the data
        is (the Dask workers) for features held as Dask arrays; None for data the client
        reads itself (memory, files, computed features), which the engine sums by chunk."""
        return self.phi.products(h, cols, weights, with_gram)

    def phi_times(self, h: int, z: np.ndarray) -> np.ndarray:
        """``Phi_h @ z`` (``(K,)`` or ``(K, m)``, float64): in memory one product, on disk by
        chunk, for Dask arrays on the workers (one task per trajectory chunk)."""
        return self.phi.times(h, z, self.chunk)

    def reward_bounds(self) -> tuple[float, float]:
        """The rewards' ``(min, max)``: known since validation or from the manifest, else
        read from the rewards field once (``H K`` numbers, no feature) and kept."""
        if self.reward_range is None:
            self.reward_range = self.rewards.bounds()
        return self.reward_range

    def step(self, h: int):
        """Step ``h``'s ``(phi (K, d), rewards (K,), next_phi (K, A, d), next_values (K, A) or
        None)``: the taken-action rows as :meth:`phi_step` gives them (float64, or CSR for
        sparse rows), the next-state rows as the next-state form gives them (an ndarray, or a
        :class:`~r2pvi.data.storage.sparse_rows.StackedSparse`)."""
        nv = self.next.known(h) if self.next.has_known_values else None
        return self.phi_step(h), self.rewards_step(h), self.next.features(h), nv

    def pooled(self, P: int):
        """The transitions of steps 0 to P-1 as one: ``(phi (P K, d), rewards (P K,),
        next_phi (P K, A, d), next_values (P K, A) or None)``, step-major (row ``h K + tau``):
        views of the stored arrays when they are held in memory as step-major float64 (see
        :meth:`pooled_views`), else stacked step by step (dense or sparse rows)."""
        views = self.pooled_views(P)
        if views is not None:
            return views
        crossed = self.pooled_crossed(P)
        if crossed is not None:
            return crossed
        steps = [self.step(h) for h in range(P)]
        if any(s[3] is not None for s in steps):
            A = self.n_actions
            known = np.concatenate([
                np.full((self.n_trajectories, A), np.nan) if s[3] is None else s[3]
                for s in steps
            ])
        else:
            known = None
        return (stack_rows([s[0] for s in steps]), np.concatenate([s[1] for s in steps]),
                stack_rows([s[2] for s in steps]), known)

    def pooled_views(self, P: int):
        """:meth:`pooled` without a copy of the features when they are held in memory as
        step-major float64 arrays: ``(H, K, ...)`` reshaped to ``(H K, ...)`` is a view; the
        first ``P`` steps are a prefix of the rows. None otherwise (files, Dask, float32,
        computed next features, sparse rows)."""
        phi = self.phi.float64_array()
        if phi is None:
            return None
        H, K, d = phi.shape
        n = P * K
        nxt = self.next.pooled_view(n)
        if nxt is None:
            return None
        rewards = np.asarray(self.rewards.lazy(), dtype=float).reshape(H * K)[:n]
        return phi.reshape(H * K, d)[:n], rewards, nxt[0], nxt[1]

    def pooled_crossed(self, P: int):
        """:meth:`pooled` of state features stored once per observation
        (:mod:`~r2pvi.data.storage.crossed`): the taken-action and next-state rows as
        :class:`~r2pvi.data.storage.crossed.CrossedRows` (views), never formed; None for the
        other kinds."""
        rows = getattr(self.phi, "pooled_rows", None)
        nxt = getattr(self.next, "pooled_rows", None)
        if rows is None or nxt is None:
            return None
        n = P * self.n_trajectories
        rewards = np.asarray(self.rewards.lazy(), dtype=float).reshape(-1)[:n]
        return (rows(P), rewards) + nxt(n)

    def rewards_step(self, h: int) -> np.ndarray:
        return _as_float64(self.rewards.read(h))

    def check_rewards(self, h: int, rewards: np.ndarray, r_max: float) -> None:
        """Refuse step ``h``'s ``rewards`` (as read by :meth:`rewards_step`) when one is not
        finite or leaves ``[0, r_max]`` (beyond rounding and the declared noise); nothing
        when the rewards were checked at construction."""
        if "rewards" not in self.checked:
            check_step_rewards(rewards, h, r_max, self.reward_noise,
                               self.rewards.origin("rewards"), self._recorded_range)

    def phi_error(self, h: int, rows: np.ndarray | None = None) -> ValueError | None:
        """The error naming the first non-finite taken-action feature of step ``h`` (read
        again by chunk: only after a fit's sums were not finite), or None when there is none
        (the sums overflowed). ``rows`` searches rows already in memory instead: step ``h``'s
        ``(K, d)``, or the pooled steps' ``(P K, d)`` (step-major) with ``h = None``."""
        from ._finite import nonfinite_error

        if rows is None and "phi" in self.checked:
            return None  # checked finite when the source was built: the sums overflowed
        origin, K = self.phi.origin("phi"), self.n_trajectories
        if rows is not None:
            hit = first_nonfinite(rows)
            if hit is None:
                return None
            (i, j), value = hit
            step, k = (i // K, i % K) if h is None else (h, i)
            return nonfinite_error(origin, step, k, value, feature=j)
        for s, _, chunk in self.phi_chunks(h):
            hit = first_nonfinite(chunk)
            if hit is not None:
                (i, j), value = hit
                return nonfinite_error(origin, h, s + i, value, feature=j)
        return None

    def next_state_values(self, h: int, qmax, out: np.ndarray | None = None) -> np.ndarray:
        """``V_{h+1}`` at the K sampled next states; ``qmax(feats (n, A, d), known, nonneg)``;
        written into ``out (K,)`` when given (returned)."""
        return self.next.values(h, qmax, self.n_trajectories, self.chunk, out=out)

    def take(self, idx) -> StepSource:
        extras = {}
        for k, v in self.extras.items():
            extras[k] = np.asarray(v[idx])
            extras[k].flags.writeable = False
        phi, rewards = self.phi.subset(idx, "phi"), self.rewards.subset(idx, "rewards")
        return StepSource(phi, rewards, self._take_next(idx, phi), extras, self.nonnegative_phi,
                          self.chunk, unit_rows=self.unit_rows, reward_noise=self.reward_noise,
                          row_sums=self.phi_row_sums,  # a subset's sums lie in the range
                          checked=self.checked,  # the same numbers, checked or not
                          stationary=self.stationary, reward_offset=self.reward_offset)

    def _take_next(self, idx, phi) -> NextStates:
        """The next states of the trajectories ``idx``; with state features whose taken-action
        field and next states share one ``psi`` (``from_episodes``), sharing its subset
        ``phi``'s copy."""
        if getattr(self.next, "psi", None) is not None and \
                getattr(self.phi, "psi", None) is self.next.psi:
            return self.next.take(idx, psi=phi.psi)
        return self.next.take(idx)


def _check_stored(value: np.ndarray, name: str, what: str, path) -> None:
    """Refuse stored per-step sums (``(H, d, d)`` Gram matrices, ``(H, d)`` column sums) that
    are not finite: a fit would use them in place of the features' own."""
    hit = first_nonfinite(value[..., None])
    if hit is None:
        return
    idx, v = hit
    idx = list(idx[:-1])
    label = f"the stored {name}" if path is None else str(path)
    fix = (file_origin(path).fix if path is not None else
           "pass finite sums, or none (a fit then forms them from the features)")
    raise ValueError(
        f"{label} holds {v!r} at index {idx} (step {idx[0]}, the {what}): a fit uses only "
        f"finite numbers. Fix: {fix}")
