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
"""

from __future__ import annotations

import hashlib
import io
import json
import lzma
import os
import re
import time
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax

from . import watchdog
from ._io import CorruptFileError, atomic_path

_HASH_SUFFIX = re.compile(rb', "sha256": "([0-9a-f]{64})"\}$')
_XZ_MAGIC = b"\xfd7zXZ\x00"


def _digest(header: bytes, leaves: bytes) -> str:
    return hashlib.sha256(header + b"\n" + leaves).hexdigest()


def save_checkpoint(path, tree, state: dict, format: str, *, compress: bool = False) -> Path:
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


def seal_checkpoint(path, format: str) -> Path:
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


def verify_sha256(path, expected: str) -> None:
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


def read_checkpoint_state(path, format: str) -> dict:
    """The header of a checkpoint; ValueError when missing or of another format,
    ``CorruptFileError`` (a ValueError) when damaged."""
    return _read(path, format)[0]


def load_checkpoint(path, like, format: str):
    """(tree, state) from ``save_checkpoint``; ``like`` gives the tree's structure."""
    state, leaves = _read(path, format)
    try:
        tree = eqx.tree_deserialise_leaves(io.BytesIO(leaves), like)
    except Exception as error:  # truncated or resized leaves: equinox/numpy errors
        raise CorruptFileError(
            f"path: corrupt checkpoint {path} (its arrays do not fit the model described by "
            f"its header: {type(error).__name__})"
        ) from error
    return tree, state


def run_training(
    step_fn: Callable[[int], dict],
    save_fn: Callable[[int, float, list], None],
    options,
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
    bar = None
    if progress:
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
