"""Step-major storage: where a dataset's numbers live, read one step at a time.

Every step of the backward induction reads only that step's data. A dataset is therefore a
*step source*: fields of shape ``(H, K, ...)`` (step-major) that can be read one step and
one range of trajectories at a time, wherever they are:

- :class:`ArrayField` — a NumPy array (or a read-only view of the caller's array, no copy);
- :class:`FileField` — a ``.npy`` file of the on-disk format, read chunk by chunk: while
  fitting, a float32 step is read with ``pread`` into a reused buffer and cast chunk by chunk
  into a reused float64 one; a float64 step is memory-mapped a window of 32 MiB at a time and
  each chunk is a view of it, with no copy (the resident memory stays bounded; ``pread`` where
  a file cannot be mapped); :meth:`FileField.read` reads a range with ``pread``,
  :meth:`FileField.lazy` gives a memory map of the whole file for browsing;
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
manifest with the shapes, dtypes and cached facts (non-negativity of the features, the
rewards' ``reward_range`` [min, max] checked by ``fit`` against ``r_max``, the range
``phi_row_sums`` [min, max] of the stored taken-action rows' sums, and ``reward_noise``
when the rewards are noisy samples).

The modules, each importing only those listed before it: ``_finite`` (what a fit checks in
data not checked when the dataset was built, and the errors naming it), ``_fields`` (the
fields, ``CHUNK``),
``_reads`` (a file step streamed by chunk: ``pread`` and a cast, or views of
memory-mapped windows, ``MAP_WINDOW``), ``_next``
(the next-state forms), ``_format`` (manifest, ``.npy`` headers, atomic directories),
``_behaviour`` (the behaviour form, ``SIDE_BLOCK``), ``_source`` (:class:`StepSource`),
``_checks`` (validation), ``_directory`` (:func:`open_directory`, :func:`write_directory`),
``_writer`` (:class:`DatasetWriter`). This package re-exports their names; a module-level
constant is read where it is defined, so change it there (e.g. ``storage._reads.MAP_WINDOW``).
"""

# The names code, tests, benchmarks and docs reach as ``storage.X`` (private ones included).
from ._behaviour import (  # noqa: F401
    BEHAVIOUR_VERSION,
    NEXT_FORMS,
    SIDE_BLOCK,
    BehaviourNext,
    RowFile,
    _next_form,
    behaviour_split,
)
from ._checks import (  # noqa: F401
    SimplexFeatureWarning,
    check_features_chunk,
    check_map_actions,
    check_reward_noise,
    layout_step_major,
    simplex_flags,
    step_major,
    validate_source,
    warn_simplex,
)
from ._directory import open_directory, write_directory
from ._fields import (  # noqa: F401
    CHUNK,
    ArrayField,
    DaskField,
    Field,
    FileField,
    MappedField,
    _float_dtype,
    widen_range,
)
from ._format import FORMAT_VERSION, GRAM_FILE, KIND, MANIFEST, SUMS_FILE  # noqa: F401
from ._next import MapNext, NextStates, StoredNext, TableNext  # noqa: F401
from ._reads import MAP_WINDOW, _prefetched  # noqa: F401
from ._source import GRAM_CACHE_MAX_D, StepSource  # noqa: F401
from ._writer import DatasetWriter

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
