"""Which process of how many this is, and starting JAX's multi-controller runtime for it.

Every process of a multi-process run calls ``initialize()`` before anything else touches JAX.
The process count, this process's id and the coordinator's address come from, in order: the
arguments, the ``CANRIG_*`` environment variables (``CANRIG_COORDINATOR``, ``CANRIG_PROCESSES``,
``CANRIG_PROCESS_ID``: what ``canrig launch`` and a Kubernetes Job set), then a cluster's own
environment, which JAX's cluster detection reads (SLURM's ``srun``: ``SLURM_NTASKS``,
``SLURM_PROCID``, the first node of ``SLURM_STEP_NODELIST`` as coordinator; a Kubernetes
indexed Job's ``JOB_COMPLETION_INDEX`` is this process's id). Nothing set: one process, and
nothing is started.

On CPU the collectives run over TCP with Gloo (``jax_cpu_collectives_implementation``). A
process that dies is noticed by the others within ``heartbeat_s`` seconds: JAX's coordination
service then ends every process with "Terminating process because the JAX distributed service
detected fatal errors ... another task died" (exit status 134), so a run never hangs on a lost
process.
"""

import argparse
import dataclasses
import os
from collections.abc import Mapping

import jax

ENV_COORDINATOR = "CANRIG_COORDINATOR"
ENV_PROCESSES = "CANRIG_PROCESSES"
ENV_PROCESS_ID = "CANRIG_PROCESS_ID"

_ENV_NAMES = (ENV_COORDINATOR, ENV_PROCESSES, ENV_PROCESS_ID)
_NAMES = ("coordinator", "processes", "process_id")
_SLURM = ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_NTASKS", "SLURM_PROCID", "SLURM_LOCALID")
"""The variables JAX's SLURM detection needs (``srun`` sets them in every task)."""


@dataclasses.dataclass(frozen=True)
class ProcessGroup:
    """This process's place in a run (``initialize`` lists the fields)."""

    processes: int
    process_id: int
    coordinator: str | None
    source: str

    @property
    def is_main(self) -> bool:
        """Process 0: the one that writes outputs and checkpoints and prints progress."""
        return self.process_id == 0

    def describe(self) -> str:
        where = f" (coordinator {self.coordinator})" if self.coordinator else ""
        return f"process {self.process_id} of {self.processes}{where}, from {self.source}"


def _integer(value, name: str) -> int:
    if isinstance(value, bool):
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    try:
        return int(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected an integer, got {value!r}") from None


def _check_address(address: str, name: str) -> str:
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{name}: expected HOST:PORT (e.g. node001:12321), got {address!r}")
    return address


def process_group(
    coordinator: str | None = None,
    processes: int | None = None,
    process_id: int | None = None,
    *,
    environ: Mapping[str, str] | None = None,
) -> ProcessGroup:
    """This process's ``ProcessGroup`` from the arguments, else the environment (module
    docstring; ``environ`` defaults to ``os.environ``). Nothing is started. ValueError naming
    the argument or variable when a value is malformed, when a multi-process run lacks a
    coordinator or an id, or when the id is out of range."""
    env = os.environ if environ is None else environ
    given = (coordinator, processes, process_id)
    values = [g if g is not None else env.get(k) for g, k in zip(given, _ENV_NAMES, strict=True)]
    # a value is named as it was given: the argument, else the variable it came from
    label = [
        k if g is None and k in env else n
        for g, n, k in zip(given, _NAMES, _ENV_NAMES, strict=True)
    ]
    if all(v is None for v in values) and all(k in env for k in _SLURM):
        n = _integer(env["SLURM_NTASKS"], "SLURM_NTASKS")
        i = _integer(env["SLURM_PROCID"], "SLURM_PROCID")
        return _checked(n, i, None, "SLURM", ("SLURM_NTASKS", "SLURM_PROCID"))
    if all(v is None for v in values):
        return ProcessGroup(1, 0, None, "one process")
    source = "arguments" if any(g is not None for g in given) else "CANRIG_* environment"
    if values[2] is None and "JOB_COMPLETION_INDEX" in env:
        values[2], label[2] = env["JOB_COMPLETION_INDEX"], "JOB_COMPLETION_INDEX"
        source = f"{source} and Kubernetes indexed Job"
    n = 1 if values[1] is None else _integer(values[1], label[1])
    if n > 1 and values[0] is None:
        raise ValueError(
            f"{label[0]}: a run of {n} processes needs the coordinator's HOST:PORT "
            f"(process 0's host; set {ENV_COORDINATOR} or pass --coordinator)"
        )
    if n > 1 and values[2] is None:
        raise ValueError(
            f"{label[2]}: a run of {n} processes needs this process's id, 0 to {n - 1} "
            f"(set {ENV_PROCESS_ID} or pass --process-id; `canrig launch` sets it)"
        )
    i = 0 if values[2] is None else _integer(values[2], label[2])
    address = None if values[0] is None else _check_address(str(values[0]), label[0])
    return _checked(n, i, address, source, (label[1], label[2]))


def _checked(n: int, i: int, address, source: str, label) -> ProcessGroup:
    if n < 1:
        raise ValueError(f"{label[0]}: expected at least 1 process, got {n}")
    if not 0 <= i < n:
        raise ValueError(f"{label[1]}: expected a process id from 0 to {n - 1}, got {i}")
    return ProcessGroup(n, i, address, source)


def initialize(
    coordinator: str | None = None,
    processes: int | None = None,
    process_id: int | None = None,
    *,
    heartbeat_s: int = 15,
    timeout_s: int = 120,
) -> ProcessGroup:
    """Start JAX's multi-controller runtime (``jax.distributed.initialize``) for this process,
    with the values ``process_group`` resolves; one process: nothing is started.

    Call it first in every process, before any JAX computation. ``heartbeat_s``: a process
    silent that long counts as dead and ends the others (with JAX's "another task died"
    message); ``timeout_s``: how long to wait for every process to join. Afterwards
    ``jax.devices()`` lists every process's devices (``jax.local_devices()`` this one's), and
    the trainers and ``gather_frames``/``map_items`` work across processes. Calling it again
    with the same values returns the group; other values raise ValueError.

    Returns:
        This process's place in the run, a ``ProcessGroup``: ``processes``, how many run the
        same program; ``process_id``, this one's index (``0 <= process_id < processes``);
        ``coordinator``, ``host:port`` of process 0's coordination service (None for one
        process or when the cluster's detection finds it, SLURM); ``source``, where the values
        came from (``"arguments"``, ``"CANRIG_* environment"``, ``"SLURM"``, ``"Kubernetes
        indexed Job"``, ``"one process"``); ``is_main``, True in process 0 (the one that
        writes outputs and checkpoints and prints progress); ``describe()``, one line.
    """
    group = process_group(coordinator, processes, process_id)
    for value, name in ((heartbeat_s, "heartbeat_s"), (timeout_s, "timeout_s")):
        if _integer(value, name) < 1:
            raise ValueError(f"{name}: expected a positive number of seconds, got {value!r}")
    if group.processes == 1:
        return group
    if jax.distributed.is_initialized():
        if (jax.process_count(), jax.process_index()) != (group.processes, group.process_id):
            raise ValueError(
                f"processes, process_id: already initialized as process {jax.process_index()} "
                f"of {jax.process_count()}, asked for {group.describe()}"
            )
        return group
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(
            coordinator_address=group.coordinator,
            num_processes=None if group.source == "SLURM" else group.processes,
            process_id=None if group.source == "SLURM" else group.process_id,
            initialization_timeout=int(timeout_s),
            heartbeat_timeout_seconds=int(heartbeat_s),
        )
    except RuntimeError as error:
        if "before any JAX" in str(error) or "must be called before" in str(error):
            raise RuntimeError(
                "canrig_jax.distributed.initialize: call it first in every process, before "
                "any JAX computation (JAX's backends are already running here)"
            ) from error
        raise
    return group


def add_process_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add ``--processes``, ``--process-id`` and ``--coordinator`` to ``parser`` (each
    defaulting to the environment, module docstring); read them with
    ``initialize_from_args``. Returns ``parser``."""
    group = parser.add_argument_group("several processes (jax.distributed)")
    group.add_argument(
        "--processes",
        type=int,
        default=None,
        help=f"processes in the run (default: ${ENV_PROCESSES}, SLURM's, else 1)",
    )
    group.add_argument(
        "--process-id",
        type=int,
        default=None,
        help=f"this process's index (default: ${ENV_PROCESS_ID}, SLURM's or the Job's)",
    )
    group.add_argument(
        "--coordinator",
        default=None,
        help=f"HOST:PORT of process 0 (default: ${ENV_COORDINATOR}, SLURM's first node)",
    )
    return parser


def initialize_from_args(args: argparse.Namespace) -> ProcessGroup:
    """``initialize`` with the options ``add_process_options`` added."""
    return initialize(args.coordinator, args.processes, args.process_id)
