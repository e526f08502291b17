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
- :class:`DaskField` — a Dask array chunked along trajectories (the ``dask`` extra);
- :class:`SparseRowsField` — sparse rows, one CSR matrix per step (tile coding);
- :class:`MappedField` — features computed from stored observations by a feature map.

Every kind implements the :class:`Field` protocol: besides the reads, the products a fit
needs of a step (its rows whole or by chunk, ``Phi_h z``, sums formed where the numbers are),
so :class:`StepSource` and the engine never ask which kind they hold. A new storage kind is a
new module with a :class:`Field` subclass (and, if its next-state rows are stored its own
way, a :class:`NextStates` subclass).

Next-state features are computed where they need not be stored (:class:`StoredNext`,
:class:`BehaviourNext` for trajectories, whose taken action's row is the next step's
features, :class:`TableNext` for finite MDPs, :class:`MapNext` for stored observations and a
feature map, :class:`SparseNext` for sparse rows), and the engine asks for the next-state
values ``V_{h+1}`` chunk by chunk through :meth:`StepSource.next_state_values`.

The on-disk format (format version 2; 3 for state features) is a directory::

    manifest.json        {"kind": "r2pvi.OfflineDataset", "format_version": 2, ...}
    phi.npy              (H, K, d)     float32 or float64, step-major, or
    psi.npy              (H+1, K, m)   state features once per observation and
    actions.npy          (H, K)        the taken actions' indices (-1: no data): episodes
                                       of a crossed map, phi and next-state rows in one
                                       (format version 3, see state_files)
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

The modules, each importing only those listed before it. Shared pieces: ``_finite`` (what a
fit checks in data not checked when the dataset was built, and the errors naming it),
``fields`` (the field protocol, ``CHUNK``), ``npy`` (``.npy`` headers). One module per storage
kind: ``memory`` (:class:`ArrayField`), ``files`` (:class:`FileField`: a file step streamed by
chunk, ``pread`` and a cast or views of memory-mapped windows, ``MAP_WINDOW``),
``dask_tasks`` and ``dask_arrays`` (:class:`DaskField`, products formed on the workers),
then the next-state forms ``next_states`` (:class:`NextStates`, :class:`StoredNext`,
:class:`TableNext`),
``sparse_rows`` (:class:`SparseRowsField`, :class:`SparseNext`: one CSR matrix per step),
``observations`` (:class:`MappedField`, :class:`MapNext`), ``format`` (manifest names, atomic
directories), ``behaviour`` (the behaviour form, ``SIDE_BLOCK``), ``source``
(:class:`StepSource`), ``checks`` (validation), ``manifest`` (what an open checks),
``crossed`` (state features: :class:`CrossedField`, :class:`CrossedNext`), ``state_files``
(their directory files), ``directory`` (:func:`open_directory`, :func:`write_directory`),
``writer``
(:class:`DatasetWriter`). This package re-exports their public names; a module-level constant
is read where it is defined, so change it there (e.g. ``storage.files.MAP_WINDOW``).
"""

# The names code, tests, benchmarks and docs reach as ``storage.X``.
from .behaviour import (  # noqa: F401
    BEHAVIOUR_VERSION,
    NEXT_FORMS,
    SIDE_BLOCK,
    BehaviourNext,
    RowFile,
    behaviour_split,
)
from .checks import (  # noqa: F401
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
from .dask_arrays import DaskField
from .directory import open_directory, write_directory
from .fields import CHUNK, Field, widen_range  # noqa: F401
from .files import MAP_WINDOW, FileField  # noqa: F401
from .format import FORMAT_VERSION, GRAM_FILE, KIND, MANIFEST, SUMS_FILE  # noqa: F401
from .memory import ArrayField
from .next_states import NextStates, StoredNext, TableNext
from .observations import MapNext, MappedField
from .source import GRAM_CACHE_MAX_D, StepSource  # noqa: F401
from .sparse_rows import SparseNext, SparseRowsField, StackedSparse
from .writer import DatasetWriter

__all__ = [
    "FORMAT_VERSION",
    "CHUNK",
    "Field",
    "ArrayField",
    "FileField",
    "DaskField",
    "NextStates",
    "StoredNext",
    "BehaviourNext",
    "RowFile",
    "behaviour_split",
    "TableNext",
    "MapNext",
    "MappedField",
    "SparseRowsField",
    "SparseNext",
    "StackedSparse",
    "StepSource",
    "DatasetWriter",
    "SimplexFeatureWarning",
    "open_directory",
    "write_directory",
    "step_major",
    "validate_source",
]
