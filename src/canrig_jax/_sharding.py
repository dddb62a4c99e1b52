"""Data-parallel training over the available devices with JAX's own sharding.

The batch is split along its leading axis over a one-axis ``jax.sharding.Mesh`` of N devices
(``device_mesh(N)``); parameters and optimiser state are replicated on every device. A jitted
step on such inputs is partitioned by XLA (GSPMD): each device computes its part of the
batch, and the mean loss and its gradient are all-reduced, so N devices follow the same
trajectory as one, to float tolerance (the reduction order differs).

Several processes (``canrig_jax.distributed.initialize()`` first in each): ``device_mesh(N)``
takes N / P devices of each of the P processes, process by process, so each process computes
a contiguous part of the batch. Every process feeds the same global batch (the trainers draw it
from the step number); ``shard_batch``/``replicate`` place each process's part from it, and
``to_local`` turns a replicated result back into this process's ordinary arrays.

On CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (set before JAX is imported)
gives N host devices for testing.
"""

import dataclasses
from collections.abc import Callable
from typing import TypeVar

import equinox as eqx
import jax
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

T = TypeVar("T")

BATCH_AXIS = "batch"
"""Name of the mesh axis the batch is split over."""


def device_mesh(devices: int | None = None) -> Mesh:
    """A one-axis mesh (``BATCH_AXIS``) over the first ``devices`` devices (default: all);
    with P processes, the first ``devices / P`` of each process's (``devices`` must be a
    multiple of P)."""
    available = jax.devices()
    if devices is None:
        devices = len(available)
    if isinstance(devices, bool) or not isinstance(devices, int | np.integer) or devices < 1:
        raise ValueError(f"devices: expected a positive number of devices, got {devices!r}")
    if devices > len(available):
        raise ValueError(
            f"devices: {devices} requested, {len(available)} available "
            f"({available[0].platform}); on CPU set "
            f"XLA_FLAGS=--xla_force_host_platform_device_count={devices} before importing jax"
        )
    processes = jax.process_count()
    if processes == 1:
        return Mesh(np.asarray(available[:devices]), (BATCH_AXIS,))
    if devices % processes:
        raise ValueError(
            f"devices: {devices} devices cannot be split evenly over {processes} processes "
            f"(choose a multiple of {processes})"
        )
    per = devices // processes
    chosen = [
        d for p in range(processes) for d in [d for d in available if d.process_index == p][:per]
    ]
    return Mesh(np.asarray(chosen), (BATCH_AXIS,))


def _place(leaf, sharding: NamedSharding):
    """``leaf`` placed with ``sharding``; across processes each process places its own part
    of the (identical) global value."""
    if jax.process_count() == 1:
        return jax.device_put(leaf, sharding)
    value = np.asarray(leaf)
    return jax.make_array_from_callback(value.shape, sharding, lambda index: value[index])


def to_local(tree: T) -> T:
    """Every array leaf replicated across processes as an ordinary array of this process
    (its first local copy); other leaves as they are. One process: ``tree`` unchanged."""
    if jax.process_count() == 1:
        return tree

    def local(leaf):
        if isinstance(leaf, jax.Array) and not leaf.is_fully_addressable:
            if not leaf.is_fully_replicated:
                raise ValueError("to_local: a leaf split across processes is not replicated")
            return jax.device_put(leaf.addressable_data(0), jax.local_devices()[0])
        return leaf

    return jax.tree_util.tree_map(local, tree)


def shard_batch(tree: T, mesh: Mesh) -> T:
    """Every array leaf of ``tree`` split along its leading axis over ``mesh``'s devices.

    Raises ValueError naming the leaf's shape when its leading axis is not a multiple of the
    number of devices (pad the batch or pick a batch size that divides)."""
    n = mesh.devices.size
    sharding = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))

    def put(leaf):
        if not eqx.is_array(leaf):
            return leaf
        if leaf.ndim == 0 or leaf.shape[0] % n:
            raise ValueError(
                f"batch: a leaf of shape {leaf.shape} cannot be split over {n} devices "
                "(its leading axis must be a multiple of the device count)"
            )
        return _place(leaf, sharding)

    return jax.tree_util.tree_map(put, tree)


def replicate(tree: T, mesh: Mesh) -> T:
    """Every array leaf of ``tree`` copied to all of ``mesh``'s devices."""
    sharding = NamedSharding(mesh, PartitionSpec())
    return jax.tree_util.tree_map(
        lambda leaf: _place(leaf, sharding) if eqx.is_array(leaf) else leaf, tree
    )


@dataclasses.dataclass(frozen=True)
class DataParallel:
    """Where a trainer puts its arrays: on one device, as they are (``mesh`` None: the
    single-device run is untouched, bit for bit); on several, parameters, optimiser state and
    training data replicated and each step's batch split along its leading axis."""

    mesh: Mesh | None

    def replicate(self, tree: T) -> T:
        return tree if self.mesh is None else replicate(tree, self.mesh)

    def shard(self, tree: T) -> T:
        return tree if self.mesh is None else shard_batch(tree, self.mesh)

    def local(self, tree: T) -> T:
        """A trained tree as this process's ordinary arrays (``to_local``)."""
        return tree if self.mesh is None else to_local(tree)

    @property
    def n_devices(self) -> int:
        return 1 if self.mesh is None else int(self.mesh.devices.size)


def data_parallel(devices: int | None, batch: int, batch_name: str = "batch") -> DataParallel:
    """The placement for a trainer whose steps draw ``batch`` examples (named ``batch_name``
    in the error) over ``devices`` devices (None: all); ValueError naming ``devices`` when it
    is not a positive count of available devices or does not divide the batch."""
    mesh = device_mesh(devices)
    n = int(mesh.devices.size)
    if batch % n:
        raise ValueError(
            f"devices: {batch_name} = {batch} examples per step cannot be split over {n} "
            f"devices (choose devices dividing {batch})"
        )
    return DataParallel(mesh if n > 1 else None)


def data_parallel_step(loss_fn: Callable, optimiser: optax.GradientTransformation) -> Callable:
    """A jitted optimiser step ``step(model, opt_state, batch) -> (model, opt_state, loss)``.

    ``loss_fn(model, batch)`` is the mean loss over the batch; ``optimiser`` an optax
    transformation. Called on a replicated model and state (``replicate``) and a sharded
    batch (``shard_batch``), the step runs data-parallel over the mesh; on single-device
    inputs it is the ordinary step. One function for both: the device count is a property
    of the inputs, not of the code."""

    @eqx.filter_jit
    def step(model, opt_state, batch):
        loss, grads = eqx.filter_value_and_grad(loss_fn)(model, batch)
        updates, opt_state = optimiser.update(grads, opt_state, eqx.filter(model, eqx.is_array))
        return eqx.apply_updates(model, updates), opt_state, loss

    return step
