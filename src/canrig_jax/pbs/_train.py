"""Training CANRig-PBS and the Shape Transformer on whole-head shapes (CANRig eq. 8).

One example: a target shape (a training pose of the whole head), a base shape (the neutral,
or with probability ``p_neutral`` not, another training shape; always the neutral for the
Shape Transformer, which has no base), a set of handles drawn from a pool of skin vertices
with the displacements target - base at them, one radius and falloff. The loss is eq. 8:

    L = mean_v ||S_v - S*_v||^2 (mm^2, over ``n_vertices`` random moving vertices)
        + weight_loss * mean ||S_pred - (W*_target - W*_base)||^2

with W* the PBS fit (``fit_pbs``) of each training shape. The mask of a patch is the
handles' influence evaluated at the patch's seed vertex (geodesic distance on the whole
head's edge graph).

The loop, checkpoints (atomic, resumable bit-identically) and the Adam schedule are the
CANRig trainer's (``_checkpoint.train_resumably``, ``_train.adam``).
"""

import dataclasses
import os
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, ArrayLike, Float, Int

from .._checkpoint import load_checkpoint as _load_file
from .._checkpoint import read_checkpoint_state as _read_state_file
from .._checkpoint import resume_training, train_resumably
from .._metrics import CM_TO_MM
from .._sharding import data_parallel
from ..canrig._train import adam
from ..mesh import weighted_geodesic_distance
from ._basis import PatchLayout, fit_pbs
from ._model import (
    PBS_VARIANTS,
    AbstractCANRigPBS,
    ShapeTransformer,
    patch_means,
    pbs_delta_shape,
)

PBS_MODELS = (*PBS_VARIANTS, "shape_transformer")
"""The networks ``PBSTrainOptions.model`` names: ``per_patch`` (``PerPatchPBS``, the paper's
CANRig-PBS), Figure 8's ablations ``base_multiplied`` (one shared output MLP on the same
base-multiplied input) and ``no_modulation`` (one shared output MLP on the attended vector
alone), all three final ``AbstractCANRigPBS``; and ``shape_transformer``, the Shape Transformer
baseline ([CZG*22]: a transformer encoder over handle tokens, a cross-attention decoder
queried per patch; no base shape, no masks)."""
PBS_CHECKPOINT_FORMAT = "canrig-pbs-checkpoint-1"


@dataclasses.dataclass(frozen=True)
class PBSTrainOptions:
    """Model, optimiser and example settings (units: cm)."""

    model: str = "per_patch"  # one of PBS_MODELS
    n_heads: int = 4
    latent: int = 64
    width: int = 96
    n_layers: int = 3
    fourier: int = 6
    patch_width: int = 32
    local_prior: bool = False  # CANRig-PBS beyond the paper: correct a local PBS fit
    learning_rate: float = 1e-3
    decay_steps: int = 0
    decay_floor: float = 0.02
    decay_start: int = 0
    steps: int = 5_000
    max_minutes: float | None = None
    batch: int = 8
    n_handles: tuple[int, int] = (100, 300)
    handle_bucket: int = 100
    n_vertices: int = 1024
    radius_cm: tuple[float, float] = (2.0, 8.0)
    falloff_per_cm: tuple[float, float] = (0.5, 2.0)
    p_neutral: float = 0.5
    weight_loss: float = 1.0
    seed: int = 0
    checkpoint_every: int = 250
    log_every: int = 25

    def __post_init__(self):
        if self.model not in PBS_MODELS:
            raise ValueError(f"model: expected one of {PBS_MODELS}, got {self.model!r}")
        if self.local_prior and self.model == "shape_transformer":
            raise ValueError("local_prior: a CANRig-PBS option; the Shape Transformer has none")
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate: expected > 0, got {self.learning_rate}")
        lo, hi = self.n_handles
        if not 1 <= lo <= hi or self.handle_bucket < 1:
            raise ValueError(f"n_handles: expected 1 <= low <= high, got {self.n_handles}")
        for name in ("radius_cm", "falloff_per_cm"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{name}: expected 0 < low <= high, got {(lo, hi)}")
        if not 0.0 <= self.p_neutral <= 1.0:
            raise ValueError(f"p_neutral: expected a value in [0, 1], got {self.p_neutral}")
        if self.batch < 1 or self.n_vertices < 1 or self.steps < 0:
            raise ValueError("batch, n_vertices: expected >= 1; steps: expected >= 0")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "PBSTrainOptions":
        values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**values)


class PBSTrainingSet(eqx.Module):
    """Whole-head training data, device arrays (``build_pbs_training_set`` lists the
    fields)."""

    neutral: Float[Array, "N 3"]
    shapes: Float[Array, "M N 3"]
    weights: Float[Array, "M P Bm1"]
    basis: Float[Array, "Bm1 N 3"]
    layout: PatchLayout
    seeds: Float[Array, "P 3"]
    pool: Int[Array, " Q"]
    pool_distance: Float[Array, "P Q"]
    moving: Int[Array, " A"]
    patch_base: Float[Array, "M1 P 3"]


def seed_distances(
    layout: PatchLayout, graph: sp.csr_matrix, limit: float = np.inf
) -> Float[np.ndarray, "P N"]:
    """(P, N) geodesic distance from each patch's seed to every vertex (cm)."""
    return weighted_geodesic_distance(graph, np.asarray(layout.seeds), limit=limit)


def build_pbs_training_set(
    neutral: Float[ArrayLike, "N 3"],
    shapes: Float[ArrayLike, "M N 3"],
    layout: PatchLayout,
    basis: Float[ArrayLike, "Bm1 N 3"],
    distances: Float[ArrayLike, "P N"],
    pool: Int[ArrayLike, " Q"],
) -> PBSTrainingSet:
    """The training set: PBS fits of ``shapes`` and the seed-to-pool distances (``distances``
    from ``seed_distances``).

    Returns:
        The whole-head training data for ``train_pbs`` (a ``PBSTrainingSet``, device arrays):
        ``neutral`` (N, 3), the canonical shape; ``shapes`` (M, N, 3), the training shapes
        (cm); ``weights`` (M, P, B - 1), their PBS fits; ``basis`` (B - 1, N, 3), the PBS
        offsets; ``layout``; ``seeds`` (P, 3), the seeds' canonical positions; ``pool`` (Q,),
        the candidate handle vertices, and ``pool_distance`` (P, Q), the geodesic distance
        from each patch seed to each of them (cm; inf beyond the limit); ``moving`` (A,), the
        vertices the loss samples (those some training shape moves); ``patch_base``
        (M + 1, P, 3), each training shape's mean base position per patch, then the
        neutral's (the base modulation, precomputed for training).
    """
    neutral = np.asarray(neutral, np.float32)
    shapes = np.asarray(shapes, np.float32)
    if shapes.ndim != 3 or shapes.shape[1:] != neutral.shape:
        raise ValueError(f"shapes: expected (M, {len(neutral)}, 3), got {shapes.shape}")
    pool = np.asarray(pool)
    if pool.ndim != 1 or len(pool) == 0 or pool.min() < 0 or pool.max() >= len(neutral):
        raise ValueError(f"pool: expected vertex indices in [0, {len(neutral)})")
    weights = np.concatenate(
        [
            np.asarray(fit_pbs(layout, neutral, basis, shapes[i : i + 32]))
            for i in range(0, len(shapes), 32)
        ]
    )
    moving = np.flatnonzero(np.abs(shapes - neutral).max(axis=(0, 2)) > 0)
    seeds = neutral[np.asarray(layout.seeds)]
    patch_base = np.asarray(
        patch_means(layout, jnp.asarray(np.concatenate([shapes, neutral[None]])))
    )
    return PBSTrainingSet(
        neutral=jnp.asarray(neutral),
        shapes=jnp.asarray(shapes),
        weights=jnp.asarray(weights, jnp.float32),
        basis=jnp.asarray(basis, jnp.float32),
        layout=layout,
        seeds=jnp.asarray(seeds),
        pool=jnp.asarray(pool, jnp.int32),
        pool_distance=jnp.asarray(np.asarray(distances)[:, pool], jnp.float32),
        moving=jnp.asarray(moving, jnp.int32),
        patch_base=jnp.asarray(patch_base, jnp.float32),
    )


class PBSExamples(eqx.Module):
    target: Int[Array, " E"]
    base: Int[Array, " E"]  # -1: the neutral
    handles: Int[Array, "E H"]  # indices into the pool
    radius: Float[Array, " E"]
    falloff: Float[Array, " E"]
    vertices: Int[Array, "E S"]  # indices into ``moving``


def sample_pbs_examples(
    rng: np.random.Generator, n_shapes: int, n_pool: int, n_moving: int, o: PBSTrainOptions
) -> PBSExamples:
    """One batch; the handle count is a multiple of ``handle_bucket`` (few compilations)."""
    lo, hi = o.n_handles
    n = int(rng.integers(lo, hi + 1))
    n = int(min(max(lo, round(n / o.handle_bucket) * o.handle_bucket), hi, n_pool))
    e = o.batch
    target = rng.integers(0, n_shapes, e)
    other = (target + rng.integers(1, max(n_shapes, 2), e)) % n_shapes
    neutral = rng.random(e) < o.p_neutral
    if o.model == "shape_transformer":
        neutral[:] = True
    handles = np.stack([rng.choice(n_pool, n, replace=False) for _ in range(e)])
    log_low, log_high = np.log(o.radius_cm)
    radius = np.exp(rng.uniform(log_low, log_high, e))
    falloff = rng.uniform(*o.falloff_per_cm, e)
    vertices = rng.integers(0, n_moving, (e, o.n_vertices))
    return PBSExamples(
        target=jnp.asarray(target, jnp.int32),
        base=jnp.asarray(np.where(neutral, -1, other), jnp.int32),
        handles=jnp.asarray(handles, jnp.int32),
        radius=jnp.asarray(radius, jnp.float32),
        falloff=jnp.asarray(falloff, jnp.float32),
        vertices=jnp.asarray(vertices, jnp.int32),
    )


def make_pbs_model(
    options: PBSTrainOptions,
    neutral: Float[ArrayLike, "N 3"],
    n_patches: int,
    n_weights: int,
    scale: float,
) -> AbstractCANRigPBS | ShapeTransformer:
    """The untrained model of ``options.model`` (``scale``: the displacement scale, cm)."""
    neutral = np.asarray(neutral)
    key = jax.random.PRNGKey(options.seed)
    if options.model == "shape_transformer":
        return ShapeTransformer(
            neutral,
            n_weights,
            latent=options.latent,
            n_heads=options.n_heads,
            width=options.width,
            n_layers=2,
            fourier=options.fourier,
            displacement_scale=scale,
            key=key,
        )
    return PBS_VARIANTS[options.model](
        neutral,
        n_patches,
        n_weights,
        patch_width=options.patch_width,
        local_prior=options.local_prior,
        n_heads=options.n_heads,
        latent=options.latent,
        width=options.width,
        n_layers=options.n_layers,
        fourier=options.fourier,
        displacement_scale=scale,
        key=key,
    )


def predict_pbs_weights(
    model: AbstractCANRigPBS | ShapeTransformer,
    data: PBSTrainingSet,
    handle_vertices: Int[Array, " H"],
    handle_distance: Float[Array, "P H"],
    base: Float[Array, "N 3"],
    displacements: Float[Array, "H 3"],
    radius: float | Float[ArrayLike, ""],
    falloff: float | Float[ArrayLike, ""],
    *,
    queries: Float[Array, "..."] | None = None,
    patch_base: Float[Array, "P 3"] | None = None,
) -> Float[Array, "P Bm1"]:
    """S_pred for one edit (the Shape Transformer ignores the base, masks and radius).
    ``queries`` (``model.encode_patches(data.seeds)``) and ``patch_base`` (``patch_means``
    of ``base``) may be given when cached."""
    if queries is None:
        queries = model.encode_patches(data.seeds)
    return model.from_edit(
        queries,
        data,
        handle_vertices,
        handle_distance,
        base,
        displacements,
        radius,
        falloff,
        patch_base,
    )


def _shape_at(data: PBSTrainingSet, base, weights, vertices):
    """base + W_layout S_pred S_basis at some vertices only."""
    patches = data.layout.vertex_patches[vertices]  # (S, C)
    blended = jnp.einsum("sc,scb->sb", data.layout.vertex_weights[vertices], weights[patches])
    return base[vertices] + jnp.einsum("sb,bsk->sk", blended, data.basis[:, vertices])


def pbs_example_loss(
    model: AbstractCANRigPBS | ShapeTransformer,
    data: PBSTrainingSet,
    ex: PBSExamples,
    weight_loss: float,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """Eq. 8's loss over the batch ``ex`` (module docstring) and its parts: the mean
    per-vertex error (mm) and the weights' mean squared error."""
    queries = model.encode_patches(data.seeds)  # once per batch

    def one(target, base_index, handles, radius, falloff, vertices):
        is_neutral = base_index < 0
        patch_base = data.patch_base[jnp.where(is_neutral, -1, base_index)]
        base_index = jnp.maximum(base_index, 0)
        base = jnp.where(is_neutral, data.neutral, data.shapes[base_index])
        base_weights = jnp.where(is_neutral, 0.0, data.weights[base_index])
        goal = data.shapes[target]
        h = data.pool[handles]
        predicted = predict_pbs_weights(
            model,
            data,
            h,
            data.pool_distance[:, handles],
            base,
            goal[h] - base[h],
            radius,
            falloff,
            queries=queries,
            patch_base=patch_base,
        )
        v = data.moving[vertices]
        shape = _shape_at(data, base, predicted, v)
        error = (shape - goal[v]) * CM_TO_MM
        shape_mse = jnp.mean(jnp.sum(error**2, axis=-1))
        weight_mse = jnp.mean((predicted - (data.weights[target] - base_weights)) ** 2)
        return shape_mse, weight_mse, jnp.mean(jnp.linalg.norm(error, axis=-1))

    shape_mse, weight_mse, error = jax.vmap(one)(
        ex.target, ex.base, ex.handles, ex.radius, ex.falloff, ex.vertices
    )
    total = jnp.mean(shape_mse) + weight_loss * jnp.mean(weight_mse)
    return total, {"error_mm": jnp.mean(error), "weight_mse": jnp.mean(weight_mse)}


@eqx.filter_jit
def _pbs_train_step(model, opt_state, data, ex, optimiser, weight_loss):
    (total, aux), grads = eqx.filter_value_and_grad(pbs_example_loss, has_aux=True)(
        model, data, ex, weight_loss
    )
    updates, opt_state = optimiser.update(grads, opt_state, eqx.filter(model, eqx.is_array))
    return eqx.apply_updates(model, updates), opt_state, total, aux


def _optimiser(options: PBSTrainOptions):
    return adam(
        options.learning_rate, options.decay_steps, options.decay_floor, options.decay_start
    )


def load_pbs_model(
    path: str | os.PathLike,
    neutral: Float[ArrayLike, "N 3"],
    n_patches: int,
    n_weights: int,
) -> tuple[AbstractCANRigPBS | ShapeTransformer, dict[str, Any]]:
    """(model, header) of a ``train_pbs`` checkpoint."""
    state = _read_state_file(path, PBS_CHECKPOINT_FORMAT)
    options = PBSTrainOptions.from_dict(state["options"])
    like = make_pbs_model(options, neutral, n_patches, n_weights, state["displacement_scale"])
    like_opt = _optimiser(options).init(eqx.filter(like, eqx.is_array))
    (model, _), state = _load_file(path, (like, like_opt), PBS_CHECKPOINT_FORMAT)
    return model, state


def train_pbs(
    data: PBSTrainingSet,
    options: PBSTrainOptions,
    *,
    checkpoint: str | os.PathLike | None = None,
    displacement_scale: float = 1.0,
    progress: bool = True,
    stop_after: int | None = None,
    devices: int | None = None,
) -> tuple[AbstractCANRigPBS | ShapeTransformer, int, float, list[dict[str, Any]]]:
    """Train (or resume from ``checkpoint``) CANRig-PBS or the Shape Transformer until
    ``options.steps`` or ``options.max_minutes``. Returns (model, step, seconds, history).

    ``devices`` (default: all): data-parallel over that many devices
    (``canrig_jax._sharding.data_parallel``), each step's examples split over them, parameters
    and training set replicated; across processes (``canrig_jax.distributed.initialize``
    first) the devices of every process, process 0 writing the checkpoint."""
    if not isinstance(options, PBSTrainOptions):
        raise TypeError(f"options: expected PBSTrainOptions, got {type(options).__name__}")
    placement = data_parallel(devices, options.batch, "batch")
    n_patches, n_weights = data.weights.shape[1:]
    optimiser = _optimiser(options)

    def init(header):
        model = make_pbs_model(options, data.neutral, n_patches, n_weights, displacement_scale)
        return model, optimiser.init(eqx.filter(model, eqx.is_array))

    run = resume_training(
        checkpoint,
        PBS_CHECKPOINT_FORMAT,
        init,
        options,
        PBSTrainOptions.from_dict,
        may_change=("steps", "max_minutes"),
    )
    sizes = (data.shapes.shape[0], data.pool.shape[0], data.moving.shape[0])
    data, run.tree = placement.replicate((data, run.tree))

    def one_step(tree, step):
        model, opt_state = tree
        ex = sample_pbs_examples(np.random.default_rng([options.seed, step]), *sizes, options)
        model, opt_state, loss, aux = _pbs_train_step(
            model, opt_state, data, placement.shard(ex), optimiser, options.weight_loss
        )
        return (model, opt_state), {"loss": loss, **aux}

    header = {"options": options.to_dict(), "displacement_scale": displacement_scale}
    train_resumably(
        one_step,
        run,
        options,
        checkpoint=checkpoint,
        format=PBS_CHECKPOINT_FORMAT,
        header=header,
        progress=progress,
        desc=options.model,
        stop_after=stop_after,
    )
    return placement.local(run.tree[0]), run.step, run.seconds, run.history


@eqx.filter_jit
def pbs_reconstruct(
    model: AbstractCANRigPBS | ShapeTransformer,
    data: PBSTrainingSet,
    handle_vertices: Int[Array, " H"],
    handle_distance: Float[Array, "P H"],
    base: Float[Array, "N 3"] | Float[Array, "F N 3"],
    targets: Float[Array, "F N 3"],
    radius: float,
    falloff: float,
    queries: Float[Array, "..."] | None = None,
) -> Float[Array, "F N 3"]:
    """Whole-head shapes with the handles moved to each target (displacements target - base
    at the handles), mapped over the targets; ``base`` is one shape for all of them or one
    per target (e.g. the source frames of a dialogue replacement). The Shape Transformer has
    no base: give it the neutral. ``queries``: ``model.encode_patches(data.seeds)``, cached
    by the caller (they depend only on the canonical shape), else computed here."""
    if queries is None:
        queries = model.encode_patches(data.seeds)

    def one(base, target, patch_base):
        d = target[handle_vertices] - base[handle_vertices]
        weights = predict_pbs_weights(
            model,
            data,
            handle_vertices,
            handle_distance,
            base,
            d,
            radius,
            falloff,
            queries=queries,
            patch_base=patch_base,
        )
        return pbs_delta_shape(data.layout, base, data.basis, weights)

    if base.ndim == 2:
        patch_base = patch_means(data.layout, base)
        return jax.lax.map(lambda t: one(base, t, patch_base), targets)
    return jax.lax.map(
        lambda bt: one(bt[0], bt[1], patch_means(data.layout, bt[0])), (base, targets)
    )
