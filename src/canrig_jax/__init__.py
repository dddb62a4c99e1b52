"""canrig_jax: differentiable face rigs in JAX on real assets.

The package's one door: every subpackage (``rig``, ``mesh``, ``inverse``, ``wpse``,
``canrig``, ``autorig``, ``data``, ``render``) keeps its implementation in private ``_x.py``
modules and re-exports its public names from its ``__init__``. The shared utilities below
(cache, input checks, checkpoints, atomic files, metrics, provenance, command-line
options from dataclasses) are re-exported here, with ``run_command(argv)``, the ``canrig``
console script's entry point, and data-parallel training over devices (``device_mesh``,
``shard_batch``, ``replicate``, ``data_parallel_step``).
"""

from ._cache import CACHE_ENV_VAR, cache_dir, fingerprint, mesh_fingerprint
from ._checkpoint import (
    load_checkpoint,
    read_checkpoint_state,
    run_training,
    save_checkpoint,
    seal_checkpoint,
)
from ._checks import check_finite, check_real, is_concrete, native
from ._cli import add_dataclass_options, from_args
from ._commands import main as run_command
from ._io import (
    CorruptFileError,
    atomic_path,
    check_output_path,
    save_json,
    save_npz,
    save_text,
)
from ._metrics import CM_TO_MM, distance_percentile_mm, per_vertex_distance
from ._provenance import (
    COMMAND_FILE,
    PACKAGES,
    experiment_command,
    git_commit,
    package_versions,
    provenance,
    record_command,
    with_provenance,
)
from ._sharding import (
    BATCH_AXIS,
    DataParallel,
    data_parallel,
    data_parallel_step,
    device_mesh,
    replicate,
    shard_batch,
)
from ._threads import blocking_single_threaded_blas, single_threaded_blas
from ._timing import call_times_ms, median_ms

__version__ = "0.1.0"

__all__ = [
    "call_times_ms",
    "median_ms",
    "BATCH_AXIS",
    "DataParallel",
    "data_parallel",
    "data_parallel_step",
    "device_mesh",
    "replicate",
    "shard_batch",
    "CACHE_ENV_VAR",
    "COMMAND_FILE",
    "record_command",
    "CM_TO_MM",
    "PACKAGES",
    "CorruptFileError",
    "atomic_path",
    "cache_dir",
    "check_finite",
    "check_output_path",
    "check_real",
    "add_dataclass_options",
    "from_args",
    "distance_percentile_mm",
    "experiment_command",
    "fingerprint",
    "git_commit",
    "is_concrete",
    "load_checkpoint",
    "mesh_fingerprint",
    "native",
    "package_versions",
    "per_vertex_distance",
    "provenance",
    "read_checkpoint_state",
    "run_command",
    "run_training",
    "save_checkpoint",
    "save_json",
    "save_npz",
    "save_text",
    "seal_checkpoint",
    "single_threaded_blas",
    "blocking_single_threaded_blas",
    "with_provenance",
]
