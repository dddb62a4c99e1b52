"""Resumable training: checkpoint files written atomically, and the loop that writes them.

The file is a JSON header line (``{"format": ..., **state, "sha256": ...}``: options, step,
elapsed time, loss history, and a SHA-256 of everything else in the file) followed by the
leaves of a pytree (model, optimiser state) serialised by ``eqx.tree_serialise_leaves``. The
header alone rebuilds the pytree's structure. A file whose bytes no longer match its hash, or
that is truncated, is reported as a corrupt checkpoint (``CorruptFileError``, with its path);
checkpoints written before the hash was added load without the check.

A checkpoint may be stored xz-compressed (``save_checkpoint(..., compress=True)``, or ``xz``
on the file): the reader recognises the xz signature and decompresses it whatever the file's
name, a damaged compressed stream being a ``CorruptFileError`` too. ``verify_sha256`` checks a
file against a digest recorded in code (the models that ship inside the package).

Every trainer resumes and saves through ``train_resumably``: it reads a checkpoint once, checks
its format and options, restores the pytree (model, optimiser state), the step, the elapsed
time and the loss history, and runs ``run_training`` with periodic atomic saves. The trainers
draw each step's batch from the step number (``numpy.random.default_rng([seed, step])``), so
the step is the whole random state and a resumed run repeats an uninterrupted one bit for bit.
"""

import dataclasses
import hashlib
import io
import json
import lzma
import os
import re
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import equinox as eqx
import jax
import numpy as np
from jax.experimental import multihost_utils
from jaxtyping import PyTree

from . import watchdog
from ._io import CorruptFileError, atomic_path

T = TypeVar("T")

_HASH_SUFFIX = re.compile(rb', "sha256": "([0-9a-f]{64})"\}$')
_XZ_MAGIC = b"\xfd7zXZ\x00"


def _digest(header: bytes, leaves: bytes) -> str:
    return hashlib.sha256(header + b"\n" + leaves).hexdigest()


def save_checkpoint(
    path: str | os.PathLike, tree: PyTree, state: dict, format: str, *, compress: bool = False
) -> Path:
    """Write ``state`` (JSON-able) and the array leaves of ``tree`` to ``path`` atomically,
    with a SHA-256 of the header and the leaves in the header; ``compress``: the file
    xz-compressed (smaller, slower to write; read back the same way)."""
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, tree)
    return _write(path, {"format": format, **state}, buffer.getvalue(), compress)


def _write(path, header: dict, leaves: bytes, compress: bool = False) -> Path:
    text = json.dumps(header).encode()
    sealed = text[:-1] + f', "sha256": "{_digest(text, leaves)}"}}'.encode()
    data = sealed + b"\n" + leaves
    if compress:
        data = lzma.compress(data, preset=9 | lzma.PRESET_EXTREME)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
    return Path(path)


def seal_checkpoint(path: str | os.PathLike, format: str) -> Path:
    """Add the integrity hash to a checkpoint written before it existed (atomically; the
    state and the arrays are unchanged, a compressed file stays compressed). A sealed
    checkpoint is checked, and kept as is."""
    state, leaves = _read(path, format)
    return _write(path, state, leaves, compress=_is_compressed(path))


def _is_compressed(path) -> bool:
    with open(path, "rb") as f:
        return f.read(len(_XZ_MAGIC)) == _XZ_MAGIC


def _file_bytes(path) -> bytes:
    """The checkpoint's bytes, decompressed when the file is xz-compressed."""
    with open(path, "rb") as f:
        data = f.read()
    if not data.startswith(_XZ_MAGIC):
        return data
    try:
        return lzma.decompress(data, format=lzma.FORMAT_XZ)
    except lzma.LZMAError as error:  # truncated, or bytes changed (xz's own CRC)
        raise CorruptFileError(
            f"path: corrupt checkpoint {path} (its xz compression is damaged: {error})"
        ) from error


def _read(path, format: str) -> tuple[dict, bytes]:
    """(state, leaves bytes) of a checkpoint, its integrity checked when it has a hash."""
    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"path: expected a file path, got {type(path).__name__}")
    if not os.path.exists(path):
        raise ValueError(f"path: checkpoint {path} does not exist")
    if os.path.isdir(path):
        raise ValueError(f"path: {path} is a folder, not a checkpoint file")
    sealed, newline, leaves = _file_bytes(path).partition(b"\n")
    try:
        state = json.loads(sealed)
    except (json.JSONDecodeError, UnicodeDecodeError):
        state = None
    if not isinstance(state, dict):
        if format.encode() in sealed or not newline:
            raise CorruptFileError(f"path: corrupt checkpoint {path} (unreadable header)")
        raise ValueError(f"path: {path} is not a {format} checkpoint")
    if state.get("format") != format:
        raise ValueError(f"path: {path} is not a {format} checkpoint")
    if "sha256" in state:
        match = _HASH_SUFFIX.search(sealed)
        header = sealed[: match.start()] + b"}" if match else b""
        if match is None or _digest(header, leaves) != match.group(1).decode():
            raise CorruptFileError(
                f"path: corrupt checkpoint {path} (its bytes do not match the stored SHA-256)"
            )
        state.pop("sha256")
    return state, leaves


def verify_sha256(path: str | os.PathLike, expected: str) -> None:
    """Check that the file ``path`` has the SHA-256 ``expected`` (hex): ``CorruptFileError``
    naming the file when it does not (a damaged or replaced file)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    if digest.hexdigest() != expected:
        raise CorruptFileError(
            f"{path}: corrupt file (its SHA-256 is {digest.hexdigest()}, expected {expected}); "
            "reinstall canrig_jax to restore it"
        )


def read_checkpoint_state(path: str | os.PathLike, format: str) -> dict:
    """The header of a checkpoint; ValueError when missing or of another format,
    ``CorruptFileError`` (a ValueError) when damaged."""
    return _read(path, format)[0]


def load_checkpoint(path: str | os.PathLike, like: T, format: str) -> tuple[T, dict]:
    """(tree, state) from ``save_checkpoint``; ``like`` gives the tree's structure."""
    state, leaves = _read(path, format)
    return _deserialise(path, leaves, like), state


def _deserialise(path, leaves: bytes, like):
    try:
        return eqx.tree_deserialise_leaves(io.BytesIO(leaves), like)
    except Exception as error:  # truncated or resized leaves: equinox/numpy errors
        raise CorruptFileError(
            f"path: corrupt checkpoint {path} (its arrays do not fit the model described by "
            f"its header: {type(error).__name__})"
        ) from error


def parameter_count(model: eqx.Module) -> int:
    """Number of trainable scalars (array leaves)."""
    leaves = jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))
    return int(sum(leaf.size for leaf in leaves))


def run_training(
    step_fn: Callable[[int], dict],
    save_fn: Callable[[int, float, list], None],
    options: Any,
    step: int,
    seconds: float,
    history: list,
    progress: bool,
    desc: str,
    stop_after: int | None = None,
) -> tuple[int, float]:
    """The resumable training loop shared by the trainers.

    Runs ``step_fn(step)`` (one optimiser step; it draws its own batch from the step number,
    so a resumed run repeats an uninterrupted one, and returns a dict of scalar metrics) until
    ``options.steps`` steps or ``options.max_minutes`` of accumulated step time, starting from
    ``step`` and ``seconds`` (a resumed checkpoint's). Every ``options.log_every`` steps (and
    the last) the metrics go to ``history`` and the tqdm bar; every
    ``options.checkpoint_every`` steps and at the end ``save_fn(step, seconds, history)`` is
    called. ``stop_after`` ends this call after that many steps (a simulated interruption,
    for tests). Returns (step, seconds).
    """
    steps, max_minutes = options.steps, options.max_minutes
    log_every, checkpoint_every = options.log_every, options.checkpoint_every
    budget = None if max_minutes is None else max_minutes * 60.0
    several = jax.process_count() > 1
    bar = None
    if progress and jax.process_index() == 0:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, initial=step, desc=desc, dynamic_ncols=True)
    done_here = 0
    while step < steps and (budget is None or seconds < budget):
        if stop_after is not None and done_here >= stop_after:
            break
        start = time.perf_counter()
        metrics = step_fn(step)
        if step % log_every == 0 or step + 1 == steps:
            record = {"step": step, **{k: float(v) for k, v in metrics.items()}}
            history.append(record)
            if bar is not None:
                bar.set_postfix({k: f"{v:.3f}" for k, v in record.items() if k != "step"})
        else:
            jax.block_until_ready(metrics)
        seconds += time.perf_counter() - start
        if several and budget is not None:  # process 0's clock decides when every one stops
            seconds = float(multihost_utils.broadcast_one_to_all(np.float64(seconds)))
        step += 1
        done_here += 1
        watchdog.progress(f"{desc} step {step}")
        if bar is not None:
            bar.update(1)
        if step % checkpoint_every == 0:
            save_fn(step, seconds, history)
    if bar is not None:
        bar.close()
    save_fn(step, seconds, history)
    return step, seconds


@dataclasses.dataclass
class TrainingState:
    """Where a resumable run stands.

    Attributes:
        tree: the trained pytree, (model, optimiser state).
        step: steps done; with the seed it fixes every later batch (the run's random state).
        seconds: accumulated step time (s).
        history: the logged metrics, one dict per logged step.
        header: the header of the checkpoint resumed from; ``{}`` for a fresh run.
    """

    tree: Any
    step: int = 0
    seconds: float = 0.0
    history: list = dataclasses.field(default_factory=list)
    header: dict = dataclasses.field(default_factory=dict)


def resume_training(
    checkpoint: str | os.PathLike | None,
    format: str,
    init: Callable[[dict], Any],
    options: Any,
    read_options: Callable[[dict], Any],
    may_change: Sequence[str] = ("max_minutes",),
    check: Callable[[dict], None] | None = None,
) -> TrainingState:
    """The state to train from: ``init({})`` at step 0 when ``checkpoint`` is None or absent,
    else the checkpoint's (read once). A resume is refused (``ValueError`` naming
    ``checkpoint``) when the file holds a model's weights only, when its options
    (``read_options(header["options"])``) differ from ``options`` in anything but the fields
    ``may_change`` (the budget), or when ``check(header)`` raises. ``init(header)`` gives the
    pytree's structure (it may read the header, e.g. a stored output scale)."""
    if checkpoint is None or not os.path.exists(checkpoint):
        return _same_step_everywhere(TrainingState(init({})), checkpoint)
    header, leaves = _read(checkpoint, format)
    if header.get("weights_only"):
        raise ValueError(
            f"checkpoint: {checkpoint} holds a model's weights only (export_riganyface), "
            "not a training state to resume from"
        )
    saved = read_options(header["options"])
    budget = {name: getattr(options, name) for name in may_change}
    if dataclasses.replace(saved, **budget) != options:
        raise ValueError(f"checkpoint: {checkpoint} was written with different options")
    if check is not None:
        check(header)
    tree = _deserialise(checkpoint, leaves, init(header))
    run = TrainingState(tree, header["step"], header["seconds"], header["history"], header)
    return _same_step_everywhere(run, checkpoint)


def _same_step_everywhere(run: "TrainingState", checkpoint) -> "TrainingState":
    """Across processes: refuse a run whose processes resumed from different steps (one did
    not see the checkpoint file)."""
    if jax.process_count() > 1:
        steps = np.asarray(multihost_utils.process_allgather(np.int32(run.step))).ravel()
        if len(set(steps.tolist())) > 1:
            raise ValueError(
                f"checkpoint: {checkpoint}: the processes resumed from different steps "
                f"({steps.tolist()}); every process must read the same file (a shared file "
                "system)"
            )
    return run


def train_resumably(
    step_fn: Callable[[Any, int], tuple[Any, dict]],
    run: TrainingState,
    options: Any,
    *,
    checkpoint: str | os.PathLike | None,
    format: str,
    header: dict,
    progress: bool,
    desc: str,
    stop_after: int | None = None,
) -> TrainingState:
    """``run_training`` from ``run`` (``resume_training``'s): ``step_fn(tree, step)`` returns
    the updated tree and the step's scalar metrics. When ``checkpoint`` is a path, the state
    is saved to it atomically every ``options.checkpoint_every`` steps and at the end, as
    ``{**header, "step", "seconds", "history"}`` and the leaves of the tree. Returns ``run``,
    updated in place."""

    def one_step(step):
        run.tree, metrics = step_fn(run.tree, step)
        return metrics

    def save(step, seconds, history):
        if checkpoint is not None and jax.process_index() == 0:  # one writer across processes
            state = {**header, "step": step, "seconds": seconds, "history": history}
            save_checkpoint(checkpoint, run.tree, state, format)

    run.step, run.seconds = run_training(
        one_step, save, options, run.step, run.seconds, run.history, progress, desc, stop_after
    )
    return run
