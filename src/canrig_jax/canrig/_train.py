"""Training CANRig with optax (Adam, learning rate 1e-3): a jitted step on a random subset of
vertices per example, the L2 loss (eq. 3) plus the shape-preserving loss (eq. 5), tqdm
progress, and atomic checkpoints from which training resumes to exactly the same result.

Every step's examples come from ``numpy.random.default_rng([seed, step])``, so a resumed run
draws the same batches as an uninterrupted one; the checkpoint holds the model, the optimiser
state, the step, the elapsed time and the loss history, written in one file atomically.
"""

import dataclasses
import functools
import json
import os
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._checkpoint import load_checkpoint as _load_file
from .._checkpoint import read_checkpoint_state as _read_state_file
from .._checkpoint import resume_training, train_resumably
from .._checkpoint import save_checkpoint as _save_file
from .._metrics import CM_TO_MM
from .._sharding import data_parallel
from ._data import ExampleOptions, Examples, TrainingSet, sample_examples
from ._masks import influence_mask
from ._model import AbstractCANRig, CANRig, ShapePreservingCANRig

VARIANTS = {"canrig": CANRig, "shape_preserving": ShapePreservingCANRig}
LOSSES = ("squared", "euclidean")
EUCLIDEAN_SOFTNESS_MM = 0.01
"""The ``"euclidean"`` loss is sqrt(e^2 + s^2) per vertex (e the error in mm): smooth at e = 0."""
CHECKPOINT_FORMAT = "canrig-checkpoint-1"


@dataclasses.dataclass(frozen=True)
class TrainOptions:
    variant: str = "shape_preserving"
    n_heads: int = 4
    latent: int = 64
    width: int = 64
    n_layers: int = 3
    fourier: int = 0
    linear_skip: bool = False
    query_modulation: bool = False
    interpolation_prior: bool = False
    value_position: bool = False
    learning_rate: float = 1e-3
    decay_steps: int = 0  # 0: constant rate; else cosine decay over this many steps
    decay_floor: float = 0.05
    decay_start: int = 0  # the cosine begins at this step (constant rate before it)
    steps: int = 20_000
    max_minutes: float | None = None
    beta: float = 0.0
    sp_weight: float = 1.0
    loss: str = "squared"  # per-vertex penalty: "squared" (eq. 3) or "euclidean"
    seed: int = 0
    checkpoint_every: int = 250
    log_every: int = 25
    examples: ExampleOptions = ExampleOptions()

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"variant: expected one of {sorted(VARIANTS)}, got {self.variant!r}")
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate: expected > 0, got {self.learning_rate}")
        if self.steps < 0:
            raise ValueError(f"steps: expected >= 0, got {self.steps}")
        if self.decay_steps < 0 or self.decay_start < 0:
            raise ValueError(
                f"decay_steps, decay_start: expected >= 0, got {self.decay_steps}, "
                f"{self.decay_start}"
            )
        if self.value_position and self.variant != "shape_preserving":
            raise ValueError("value_position: only the shape_preserving variant has it")
        if self.loss not in LOSSES:
            raise ValueError(f"loss: expected one of {sorted(LOSSES)}, got {self.loss!r}")
        if not 0.0 <= self.decay_floor <= 1.0:
            raise ValueError(f"decay_floor: expected a value in [0, 1], got {self.decay_floor}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TrainOptions":
        d = dict(d)
        examples: dict[str, Any] = {
            k: tuple(v) if isinstance(v, list) else v for k, v in d.pop("examples").items()
        }
        return cls(**d, examples=ExampleOptions(**examples))


@functools.lru_cache(maxsize=8)
def adam(
    learning_rate: float, decay_steps: int = 0, decay_floor: float = 0.05, decay_start: int = 0
) -> optax.GradientTransformation:
    """optax.adam, one object per setting: the jitted step (which takes the optimiser as a
    static argument) then compiles once per process, also across resumed runs. With
    ``decay_steps`` > 0 the rate is ``learning_rate`` until step ``decay_start``, then follows
    a cosine down to ``decay_floor * learning_rate`` over ``decay_steps`` steps (and stays
    there)."""
    if decay_steps > 0:
        schedule = optax.cosine_decay_schedule(learning_rate, decay_steps, decay_floor)
        if decay_start > 0:
            schedule = optax.join_schedules(
                [optax.constant_schedule(learning_rate), schedule], [decay_start]
            )
        return optax.adam(schedule)
    return optax.adam(learning_rate)


def make_optimiser(options: TrainOptions) -> optax.GradientTransformation:
    return adam(
        options.learning_rate, options.decay_steps, options.decay_floor, options.decay_start
    )


def make_model(
    options: TrainOptions, canonical: Float[ArrayLike, "V 3"], displacement_scale: float = 1.0
) -> AbstractCANRig:
    """The untrained model of ``options`` (its variant, sizes and seed) on ``canonical``."""
    return VARIANTS[options.variant](
        np.asarray(canonical),
        n_heads=options.n_heads,
        latent=options.latent,
        width=options.width,
        n_layers=options.n_layers,
        fourier=options.fourier,
        linear_skip=options.linear_skip,
        query_modulation=options.query_modulation,
        interpolation_prior=options.interpolation_prior,
        displacement_scale=displacement_scale,
        key=jax.random.PRNGKey(options.seed),
        **({"value_position": True} if options.value_position else {}),
    )


def vertex_penalty(difference: Float[ArrayLike, "N 3"], loss: str) -> Float[Array, ""]:
    """Mean over vertices of the squared error (mm^2; eq. 3) or, for ``loss="euclidean"``,
    of the smoothed Euclidean error sqrt(e^2 + s^2) (mm), the measure the evaluation reports."""
    squared = jnp.sum(difference**2, axis=1) * CM_TO_MM**2
    if loss == "squared":
        return jnp.mean(squared)
    return jnp.mean(jnp.sqrt(squared + EUCLIDEAN_SOFTNESS_MM**2))


def example_loss(
    model: AbstractCANRig,
    data: TrainingSet,
    ex: Examples,
    beta: float | Float[Array, ""],
    sp_weight: float | Float[Array, ""],
    loss: str = "squared",
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """Mean over the batch of (L2 + sp_weight * L_sp) on each example's vertex subset, with
    the per-vertex penalty ``loss`` (``vertex_penalty``); also the mean squared error (mm^2)
    and the mean per-vertex error (mm) on those vertices."""

    def one(target, base, nearby, handles, valid, vertices, radius, falloff):
        target_shape = data.shapes[target]
        base_shape = jnp.where(
            nearby == 1,
            data.nearby[target],
            jnp.where(base < 0, data.neutral, data.shapes[jnp.maximum(base, 0)]),
        )
        handle_vertex = data.pool[handles]
        distance = data.pool_distance[vertices][:, handles]
        n = handles.shape[0]
        mask = influence_mask(distance, jnp.full(n, radius), jnp.full(n, falloff), model.clamp)
        mask = mask * valid[None, :]
        queries = model.encode_queries(data.neutral[vertices])
        displacements = (target_shape[handle_vertex] - base_shape[handle_vertex]) * valid[:, None]
        predicted = model(
            queries,
            base_shape[vertices],
            data.neutral[handle_vertex],
            base_shape[handle_vertex],
            displacements,
            mask,
            beta,
        )
        truth = target_shape[vertices]
        # eq. (5): outside the region (blend mask from the largest influence) keep the base
        blend = jnp.max(mask, axis=1)[:, None]
        blended = blend * truth + (1.0 - blend) * base_shape[vertices]
        fit = vertex_penalty(predicted - truth, loss)
        l_sp = vertex_penalty(predicted - blended, loss)
        squared = jnp.mean(jnp.sum((predicted - truth) ** 2, axis=1))
        error = jnp.mean(jnp.linalg.norm(predicted - truth, axis=1))
        return fit, l_sp, squared, error

    fit, l_sp, squared, error = jax.vmap(one)(
        ex.target,
        ex.base,
        ex.base_nearby,
        ex.handles,
        ex.handle_valid,
        ex.vertices,
        ex.radius,
        ex.falloff,
    )
    total = jnp.mean(fit) + sp_weight * jnp.mean(l_sp)
    aux = {"l2_mm2": jnp.mean(squared) * CM_TO_MM**2, "error_mm": jnp.mean(error) * CM_TO_MM}
    return total, aux


@eqx.filter_jit
def train_step(
    model: AbstractCANRig,
    opt_state: PyTree,
    data: TrainingSet,
    ex: Examples,
    optimiser: optax.GradientTransformation,
    beta: float | Float[Array, ""],
    sp_weight: float | Float[Array, ""],
    loss: str = "squared",
) -> tuple[AbstractCANRig, PyTree, Float[Array, ""], dict[str, Float[Array, ""]]]:
    """One Adam step on ``example_loss`` over the batch ``ex``: the updated model and
    optimiser state, the loss and its parts (``example_loss``'s aux)."""
    (total, aux), grads = eqx.filter_value_and_grad(example_loss, has_aux=True)(
        model, data, ex, beta, sp_weight, loss
    )
    updates, opt_state = optimiser.update(grads, opt_state, eqx.filter(model, eqx.is_array))
    return eqx.apply_updates(model, updates), opt_state, total, aux


# --------------------------------------------------------------------------- checkpoints


def save_checkpoint(
    path: str | os.PathLike, model: AbstractCANRig, opt_state: PyTree, state: dict[str, Any]
) -> Path:
    """One file, written atomically (``canrig_jax.checkpoint``): a JSON header line
    (``state``), then the leaves of (model, opt_state)."""
    return _save_file(path, (model, opt_state), state, CHECKPOINT_FORMAT)


def read_checkpoint_state(path: str | os.PathLike) -> dict[str, Any]:
    """The JSON header of a training checkpoint (options, step, history, ...)."""
    return _read_state_file(path, CHECKPOINT_FORMAT)


def load_checkpoint(
    path: str | os.PathLike, like_model: AbstractCANRig, like_opt_state: PyTree
) -> tuple[AbstractCANRig, PyTree, dict[str, Any]]:
    """(model, opt_state, state) from ``save_checkpoint``; ``like_*`` give the structure."""
    (model, opt_state), state = _load_file(path, (like_model, like_opt_state), CHECKPOINT_FORMAT)
    return model, opt_state, state


def load_model(
    path: str | os.PathLike, canonical: Float[ArrayLike, "V 3"]
) -> tuple[AbstractCANRig, dict[str, Any]]:
    """The trained model of a checkpoint (its options are in the header) and the header."""
    state = read_checkpoint_state(path)
    options = TrainOptions.from_dict(state["options"])
    like = make_model(options, canonical, state["displacement_scale"])
    optimiser = make_optimiser(options)
    like_opt = optimiser.init(eqx.filter(like, eqx.is_array))
    model, _, state = load_checkpoint(path, like, like_opt)
    return model, state


# --------------------------------------------------------------------------- training


@dataclasses.dataclass
class TrainResult:
    """What ``train`` returns (its docstring lists the fields)."""

    model: AbstractCANRig
    step: int
    seconds: float
    history: list[dict[str, Any]]


def train(
    data: TrainingSet,
    options: TrainOptions,
    *,
    checkpoint: str | os.PathLike | None = None,
    displacement_scale: float = 1.0,
    progress: bool = True,
    stop_after: int | None = None,
    data_options: dict[str, Any] | None = None,
    devices: int | None = None,
) -> TrainResult:
    """Train (or resume from ``checkpoint`` if it exists) until ``options.steps`` steps or
    ``options.max_minutes`` of accumulated training time. A checkpoint resumes only with the
    same options, except the budget (steps, max_minutes), which may be extended. ``stop_after``
    ends this call early after that many steps (a simulated interruption, for tests).

    ``data_options`` (JSON-able, e.g. ``build_training_set``'s keyword arguments and its seed)
    describe how ``data`` was built; they are stored in the checkpoint, and a resume with
    other data options is refused (a checkpoint written before they were stored resumes with
    any).

    ``devices`` (default: all): data-parallel over that many devices (``canrig_jax.
    data_parallel``), each step's examples split over them, parameters replicated; the
    trajectory equals the single-device one to float tolerance, and a checkpoint resumes on
    any device count. Across processes (``canrig_jax.distributed.initialize`` first), the
    devices of every process; process 0 writes the checkpoint.

    Returns:
        A ``TrainResult``: ``model``, the trained network (also in the checkpoint, which
        ``load_model`` reads); ``step``, its step count; ``seconds``, the accumulated training
        time (s); ``history``, the logged history (one dict per ``log_every`` steps).
    """
    if not isinstance(options, TrainOptions):
        raise TypeError(f"options: expected TrainOptions, got {type(options).__name__}")
    placement = data_parallel(devices, options.examples.batch, "examples.batch")
    if data_options is not None:
        data_options = json.loads(json.dumps(data_options))  # as the checkpoint stores them
    optimiser = make_optimiser(options)

    def init(header):
        model = make_model(options, data.neutral, displacement_scale)
        return model, optimiser.init(eqx.filter(model, eqx.is_array))

    run = resume_training(
        checkpoint,
        CHECKPOINT_FORMAT,
        init,
        options,
        TrainOptions.from_dict,
        may_change=("steps", "max_minutes"),
        check=functools.partial(_check_data_options, checkpoint, data_options),
    )
    header = {
        "options": options.to_dict(),
        "data_options": run.header.get("data_options") if data_options is None else data_options,
        "displacement_scale": displacement_scale,
    }
    data, run.tree = placement.replicate((data, run.tree))
    step_fn = _step_function(data, options, optimiser, placement)
    train_resumably(
        step_fn,
        run,
        options,
        checkpoint=checkpoint,
        format=CHECKPOINT_FORMAT,
        header=header,
        progress=progress,
        desc="canrig",
        stop_after=stop_after,
    )
    model = placement.local(run.tree[0])
    return TrainResult(model=model, step=run.step, seconds=run.seconds, history=run.history)


def _check_data_options(checkpoint, data_options: dict | None, header: dict) -> None:
    """Refuse to resume a checkpoint written with other data options (one written before
    they were stored resumes with any)."""
    saved = header.get("data_options")
    if saved is not None and data_options is not None and saved != data_options:
        changed = sorted(
            k for k in set(saved) | set(data_options) if saved.get(k) != data_options.get(k)
        )
        raise ValueError(
            f"checkpoint: {checkpoint} was written with other data options "
            f"(changed: {', '.join(changed)}); delete it to start afresh"
        )


def _step_function(data: TrainingSet, options: TrainOptions, optimiser, placement):
    """One optimiser step on (model, optimiser state), its examples drawn from the step."""
    n_shapes, n_pool, n_vertices = (
        data.shapes.shape[0],
        data.pool.shape[0],
        data.neutral.shape[0],
    )
    handle_sets = None if data.handle_sets is None else np.asarray(data.handle_sets)
    beta = jnp.asarray(options.beta, jnp.float32)

    def one_step(tree, step):
        model, opt_state = tree
        rng = np.random.default_rng([options.seed, step])
        ex = sample_examples(
            rng,
            n_shapes,
            n_pool,
            n_vertices,
            options.examples,
            handle_sets=handle_sets,
            n_capture=data.n_capture,
        )
        model, opt_state, loss, aux = train_step(
            model,
            opt_state,
            data,
            placement.shard(ex),
            optimiser,
            beta,
            options.sp_weight,
            options.loss,
        )
        return (model, opt_state), {"loss": loss, "error_mm": aux["error_mm"]}

    return one_step
