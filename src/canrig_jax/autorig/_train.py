"""Training RigAnyFace with 3D supervision (the paper's stage 2).

Loss on heads normalised to the unit sphere, ``loss="squared"`` (the first recipe): the mean
squared vertex error over the poses of a batch plus ``landmark_weight`` times the same on the
68 landmark vertices, both divided by the training set's mean squared displacement (so the
loss starts near 1 whatever the units). ``loss="euclidean"``: the same with the per-vertex
Euclidean distance (divided by the root of that mean square). Either loss adds
``static_weight`` times ``static_vertex_error`` (divided by that root), the mean length of the
predicted motion of vertices whose ground truth does not move (below ``STATIC_CM``) — the term
that keeps eyeballs and the back of the head still. ``balance_poses=True`` (or 1.0) divides
each pose's fit term by that of predicting no motion for it (its own mean squared, or mean
Euclidean, displacement; floored at ``BALANCE_FLOOR`` of the training set's), so that a blink,
which moves a few eyelid vertices, weighs as much as jawOpen, which moves half the head; a value
``p`` in (0, 1) divides by ``training set's ** (1 - p) * the pose's ** p``, between the two.
``residual=True`` trains the "DT + learned residual" model (``RigAnyFace``): the training set
then carries each head's deformation-transfer poses as the base; ``residual_gate`` > 0 gates
its correction by the base's motion (``RigAnyFace``).
Adam with linear warm-up and cosine decay (optax). Each step draws ``heads_per_step`` heads
and ``poses_per_step`` of their poses from ``numpy.random.default_rng([seed, step])``, so a
run resumed from its checkpoint (one file, written atomically) draws the same batches and
ends at the same model as an uninterrupted one.
"""

import dataclasses
import functools
import os
from importlib.resources import files
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Bool, Float, Float32, Float64, Int, PyTree

from .._checkpoint import (
    load_checkpoint,
    read_checkpoint_state,
    resume_training,
    save_checkpoint,
    train_resumably,
    verify_sha256,
)
from .._metrics import CM_TO_MM
from .._sharding import data_parallel
from ..mesh import MeshOperators, mesh_operators, pad_vertices, stack_operators
from ._data import PoseSet, RiggedHead, warped_heads
from ._model import RigAnyFace, normalise

CHECKPOINT_FORMAT = "riganyface-checkpoint-1"
DEFAULT_CHECKPOINT = Path(str(files("canrig_jax.autorig") / "models" / "riganyface.eqx.xz"))
"""The default RigAnyFace model, shipped inside the package (``canrig_jax/autorig/models/``;
``load_riganyface`` reads it and checks its SHA-256, ``DEFAULT_CHECKPOINT_SHA256``): what
``canrig autorig`` loads unless given ``--model``. It is ``export_riganyface`` of the training
checkpoint ``experiments/results/autorig_half_balanced_long/checkpoint_raf.eqx`` (not
committed; the command in that folder's ``COMMAND`` rebuilds it): the same weights and
header, without the optimiser state, xz-compressed (0.6 MB instead of 2.0 MB). Width 64, 159,747
parameters, 80 training heads, squared + static loss with ``balance_poses=0.5``, 12,000 steps
(cosine completed). Chosen on validation identities by a rule written before it trained
(upper-face peak ratio >= 0.5, lower face >= 0.8, MAE on both pose classes <= 1.1x the
previous default's) over ``autorig_long`` (Euclidean + static, 7,000 steps), whose eye and
brow shapes moved about a tenth of the true amount."""
DEFAULT_CHECKPOINT_SHA256 = "7e894ad4fd0f19962d9643221c3aab5fa48df509e2b1ef92ddc0747177f5b106"
"""SHA-256 of the file ``DEFAULT_CHECKPOINT`` (a damaged or replaced file is refused)."""
RESIDUAL_CHECKPOINT = Path(
    str(files("canrig_jax.autorig") / "models" / "riganyface_residual.eqx.xz")
)
"""The packaged DT + learned residual model (``TransferResidual()``; ``canrig autorig --method
transfer-residual``): ``export_riganyface`` of
``experiments/results/autorig/checkpoint_raf_anchored_dt_residual.eqx`` (a residual on anchored
deformation transfer, chosen on validation identities)."""
RESIDUAL_CHECKPOINT_SHA256 = "4d3cce9bde900d55754d0d4c739b9e77d3b6da0e8fbdd07e4b0dac341be1eaa0"
"""SHA-256 of the file ``RESIDUAL_CHECKPOINT``."""
LOSSES = ("squared", "euclidean")
BALANCE_FLOOR = 1e-3
"""With ``balance_poses``: a pose's divisor is at least this fraction of the training set's."""
WARP_TARGETS = ("warped", "transfer")
"""``RigAnyFaceTrainOptions.warp_targets``: the warped truth, or anchored transfer
(distillation)."""
STATIC_CM = 0.001
"""A vertex is static in a pose when its ground-truth displacement is below 0.01 mm."""


@dataclasses.dataclass(frozen=True)
class RigAnyFaceTrainOptions:
    """Options of one RigAnyFace training run (see the module docstring for the loss).

    The mesh-quality terms (both 0 by default: the committed recipes):
        flip_weight: weight of ``flip_penalty`` (triangles whose predicted normal turns
            against the neutral's further than the truth's, or than ``flip_margin``).
        flip_margin: the cosine (between a posed and the neutral normal) from which the
            flip penalty starts; 0.5 = 60 degrees, -1 < margin <= 1.
        stretch_weight: weight of ``stretch_penalty`` (edges stretched or compressed beyond
            the truth's and beyond ``stretch_margin``).
        stretch_margin: the |log(length / neutral length)| every edge may reach for free
            (0.25: about 28 % stretch or 22 % compression).
        init_from: a RigAnyFace checkpoint (training or ``export_riganyface``'s) whose weights
            and output scale start this run (fine-tuning), instead of a fresh model of
            ``seed``; its architecture must be these options'. None: from scratch.

    Geometry beyond ICT's identity space (``augmented_heads``, which the evaluation's training
    recipe applies to its heads; 0 copies by default):
        warp_copies: smoothly warped copies of each training head added to the training set
            (``warped_heads``: stylised proportions and a low-frequency displacement field,
            the same warp on the neutral and on every posed shape).
        warp_amplitude: standard deviation of the warp's RBF weights (cm).
        warp_proportions: standard deviation of the log scale of each axis of the whole head
            (twice that for the eyes, nose and mouth regions).
        warp_radius: the RBFs' radius (cm).
        warp_targets: what the warped copies are trained to: "warped" (the ICT truth warped
            with the head) or "transfer" (distillation: anchored deformation transfer of the
            generic ICT poses onto the warped head, ``transfer_poses(static_below=ANCHOR_CM)``,
            as on a head with no ground truth).
    """

    width: int = 32
    n_shared: int = 2
    n_conditional: int = 2
    global_size: int = 32
    global_width: int = 32
    k: int = 128
    method: str = "spectral"
    stem_method: str | None = None
    learning_rate: float = 1e-3
    warmup_steps: int = 200
    steps: int = 2500
    max_minutes: float | None = None
    heads_per_step: int = 2
    poses_per_step: int = 8
    landmark_weight: float = 1.0
    seed: int = 0
    checkpoint_every: int = 200
    log_every: int = 20
    loss: str = "squared"
    static_weight: float = 0.0
    balance_poses: float = 0.0
    residual: bool = False
    residual_gate: float = 0.0
    flip_weight: float = 0.0
    flip_margin: float = 0.5
    stretch_weight: float = 0.0
    stretch_margin: float = 0.25
    init_from: str | None = None
    warp_copies: int = 0
    warp_amplitude: float = 1.0
    warp_proportions: float = 0.1
    warp_radius: float = 8.0
    warp_targets: str = "warped"

    def __post_init__(self):
        for name in ("flip_weight", "stretch_weight", "stretch_margin"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: expected a finite value >= 0, got {value}")
        if not -1 < self.flip_margin <= 1:
            raise ValueError(f"flip_margin: expected a cosine in (-1, 1], got {self.flip_margin}")
        if not isinstance(self.warp_copies, int) or self.warp_copies < 0:
            raise ValueError(f"warp_copies: expected an int >= 0, got {self.warp_copies!r}")
        for name in ("warp_amplitude", "warp_proportions"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: expected a finite value >= 0, got {value}")
        if self.warp_targets not in WARP_TARGETS:
            raise ValueError(
                f"warp_targets: expected one of {WARP_TARGETS}, got {self.warp_targets!r}"
            )
        if not (np.isfinite(self.warp_radius) and self.warp_radius > 0):
            raise ValueError(f"warp_radius: expected > 0 (cm), got {self.warp_radius}")
        if self.init_from is not None and not isinstance(self.init_from, str):
            raise ValueError(f"init_from: expected a path as str or None, got {self.init_from!r}")
        if self.loss not in LOSSES:
            raise ValueError(f"loss: expected one of {LOSSES}, got {self.loss!r}")
        if not self.static_weight >= 0:
            raise ValueError(f"static_weight: expected >= 0, got {self.static_weight}")
        if not 0 <= self.balance_poses <= 1:
            raise ValueError(f"balance_poses: expected in [0, 1], got {self.balance_poses}")
        if not self.residual_gate >= 0 or (self.residual_gate > 0 and not self.residual):
            raise ValueError(
                f"residual_gate: expected 0, or > 0 with residual=True; got {self.residual_gate}"
            )
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate: expected > 0, got {self.learning_rate}")
        if self.steps < 1 or self.warmup_steps < 0 or self.warmup_steps >= self.steps:
            raise ValueError(
                f"steps, warmup_steps: expected steps >= 1 and 0 <= warmup_steps < steps, got "
                f"{self.steps}, {self.warmup_steps}"
            )
        if self.heads_per_step < 1 or self.poses_per_step < 1:
            raise ValueError("heads_per_step, poses_per_step: expected >= 1")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def augmented_heads(heads: list[RiggedHead], options: RigAnyFaceTrainOptions) -> list[RiggedHead]:
    """``heads`` followed by ``options.warp_copies`` warped copies of each (``warped_heads``
    with the options' amplitude, proportions, radius and seed); ``heads`` unchanged at 0."""
    if not options.warp_copies:
        return list(heads)
    return list(heads) + warped_heads(
        heads,
        options.warp_copies,
        amplitude=options.warp_amplitude,
        proportions=options.warp_proportions,
        radius=options.warp_radius,
        seed=options.seed,
    )


def make_model(
    options: RigAnyFaceTrainOptions, n_pose_inputs: int, output_scale: float
) -> RigAnyFace:
    return RigAnyFace(
        n_pose_inputs,
        width=options.width,
        n_shared=options.n_shared,
        n_conditional=options.n_conditional,
        global_size=options.global_size,
        global_width=options.global_width,
        method=options.method,
        stem_method=options.stem_method,
        output_scale=output_scale,
        residual=options.residual,
        residual_gate=options.residual_gate,
        key=jax.random.PRNGKey(options.seed),
    )


def optimiser(options: RigAnyFaceTrainOptions) -> optax.GradientTransformation:
    """Adam with linear warm-up to ``learning_rate`` and cosine decay to 0 at ``steps``."""
    return _adam_warmup_cosine(options.learning_rate, options.warmup_steps, options.steps)


@functools.lru_cache(maxsize=8)
def _adam_warmup_cosine(learning_rate: float, warmup_steps: int, steps: int):
    # one object per schedule: the jitted step takes the optimiser as a static argument, so it
    # then compiles once per process, also across resumed runs
    schedule = optax.warmup_cosine_decay_schedule(0.0, learning_rate, warmup_steps, steps)
    return optax.adam(schedule)


class TrainingSet(eqx.Module):
    """Heads padded to one size and stacked, on the device (unit-sphere units).

    Attributes:
        vertices: (N, V, 3); displacements: (N, P, V, 3); operators: stacked (N, ...).
        landmarks: (N, L) landmark vertices; poses: (P, A) pose vectors.
        scale: (N,) each head's normalisation scale (its units per unit-sphere unit).
        base: (N, P, V, 3) base displacements of a residual model (deformation transfer),
            or None.
    """

    vertices: Float[Array, "N V 3"]
    displacements: Float[Array, "N P V 3"]
    operators: MeshOperators
    landmarks: Int[Array, "N L"]
    poses: Float[Array, "P A"]
    scale: Float[Array, " N"]
    base: Float[Array, "N P V 3"] | None = None

    @property
    def n_heads(self) -> int:
        return int(self.vertices.shape[0])


def head_inputs(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    k: int,
    cache: str | os.PathLike | bool | None = None,
) -> tuple[Float32[np.ndarray, "V 3"], MeshOperators, Float64[np.ndarray, " 3"], float]:
    """(unit-sphere vertices, operators, centre, scale) of one head."""
    unit, centre, scale = normalise(vertices)
    return unit.astype(np.float32), mesh_operators(unit, faces, k=k, cache=cache), centre, scale


def training_set(
    heads: list[RiggedHead],
    poses: PoseSet,
    *,
    k: int,
    cache: str | os.PathLike | bool | None = None,
    progress: bool = True,
    base: list[Float[ArrayLike, "P _V 3"]] | None = None,
) -> TrainingSet:
    """Normalise, compute (cached) operators and stack ``heads`` for training.

    ``base``: for a residual model, each head's (P, V, 3) base displacements in the head's
    units (``transfer_poses``)."""
    if not heads:
        raise ValueError("heads: expected at least one head")
    if base is not None:
        if len(base) != len(heads):
            raise ValueError(f"base: {len(base)} arrays for {len(heads)} heads")
        for head, b in zip(heads, base, strict=True):
            if np.shape(b) != head.displacements.shape:
                raise ValueError(
                    f"base: {head.name} needs shape {head.displacements.shape}, got {np.shape(b)}"
                )
    iterator = heads
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(heads, desc="operators", dynamic_ncols=True)
    units, ops, displacements, scales, bases = [], [], [], [], []
    for i, head in enumerate(iterator):
        if head.displacements.shape[0] != poses.n_poses:
            raise ValueError(
                f"heads: {head.name} has {head.displacements.shape[0]} poses, the pose set "
                f"{poses.n_poses}"
            )
        unit, operators, _, scale = head_inputs(head.vertices, head.faces, k=k, cache=cache)
        units.append(unit)
        ops.append(operators)
        displacements.append(np.moveaxis(head.displacements / scale, 0, 1))  # (V, P, 3)
        scales.append(scale)
        if base is not None:
            bases.append(np.moveaxis(np.asarray(base[i]) / scale, 0, 1))
    n_vertices = max(u.shape[0] for u in units)
    return TrainingSet(
        vertices=pad_vertices(units, n_vertices),
        displacements=jnp.moveaxis(pad_vertices(displacements, n_vertices), 2, 1),
        operators=stack_operators(ops),
        landmarks=jnp.asarray(np.stack([h.landmarks for h in heads]), jnp.int32),
        poses=jnp.asarray(poses.vectors()),
        scale=jnp.asarray(scales, jnp.float32),
        base=None
        if base is None
        else jnp.moveaxis(pad_vertices(bases, n_vertices), 2, 1).astype(jnp.float32),
    )


def mean_square_displacement(data: TrainingSet) -> float:
    """Mean over real vertices and poses of |d|^2 (unit-sphere units): the loss scale."""
    mask = np.asarray(data.operators.vertex_mask)  # (N, V)
    squared = np.sum(np.asarray(data.displacements) ** 2, axis=-1)  # (N, P, V)
    return float((squared * mask[:, None]).sum() / (mask.sum() * squared.shape[1]))


def static_vertex_error(
    predicted: Float[ArrayLike, "P V 3"],
    truth: Float[ArrayLike, "P V 3"],
    mask: Float[ArrayLike, " V"] | Bool[ArrayLike, " V"],
    threshold: float | Float[Array, ""],
) -> Float[Array, ""]:
    """Mean length of the predicted motion at the (pose, vertex) pairs whose ground truth
    moves less than ``threshold`` (same units), over real vertices (``mask``); 0 when there
    are none. Zero exactly when every static vertex is predicted still."""
    predicted, truth, mask = jnp.asarray(predicted), jnp.asarray(truth), jnp.asarray(mask)
    still = (jnp.linalg.norm(truth, axis=-1) < threshold) * mask[None]
    squared = jnp.sum(predicted**2, axis=-1)
    positive = squared > 0
    length = jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)
    return jnp.sum(length * still) / jnp.maximum(jnp.sum(still), 1.0)


def _face_normals(points: Float[Array, "... V 3"], faces: Int[Array, "F 3"]):
    a, b, c = (points[..., faces[:, i], :] for i in range(3))
    return jnp.cross(b - a, c - a)


def _safe_norm(x: Float[Array, "... 3"]) -> Float[Array, "..."]:
    squared = jnp.sum(x**2, axis=-1)
    positive = squared > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)


def _real_faces(vertices, faces, face_mask):
    """(F,) 1 for a real, non-degenerate neutral triangle, else 0; and its neutral normal."""
    n0 = _face_normals(vertices, faces)
    area = _safe_norm(n0)
    real = jnp.asarray(face_mask, jnp.float32) * (area > 1e-12 * jnp.max(area))
    return real, n0, area


def flip_penalty(
    predicted: Float[ArrayLike, "Q V 3"],
    truth: Float[ArrayLike, "Q V 3"],
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    face_mask: Float[ArrayLike, " F"] | Int[ArrayLike, " F"] | Bool[ArrayLike, " F"] | None = None,
    margin: float | Float[Array, ""] = 0.5,
) -> Float[Array, ""]:
    """Mean over poses and real triangles of ``relu(min(c_truth, margin) - c_predicted)``,
    where ``c`` is the cosine between a triangle's normal posed (``vertices + displacements``)
    and at rest: how far a predicted triangle turns beyond both the truth's turn and
    ``margin`` (a cosine; 0.5 = 60 degrees). The surface analogue of a negative
    deformation-gradient determinant (the tangent-plane map's determinant is the area ratio
    times that cosine), without its scale. 0 for a prediction equal to the truth and for any
    rigid motion turning triangles by less than ``arccos(margin)``; up to ``1 + margin`` for a
    triangle turned over. Degenerate rest triangles and padding (``face_mask`` 0) are left
    out. Displacements and vertices in the same units (any)."""
    predicted, truth = jnp.asarray(predicted), jnp.asarray(truth)
    vertices, faces = jnp.asarray(vertices), jnp.asarray(faces)
    mask = jnp.ones(faces.shape[0]) if face_mask is None else face_mask
    real, n0, area0 = _real_faces(vertices, faces, mask)
    area = jnp.where(real > 0, area0, 1.0)

    def cosine(displacements):
        n = _face_normals(vertices[None] + displacements, faces)  # (Q, F, 3)
        # padding and degenerate rest triangles divide by 1 (their cosine is masked out); a
        # collapsed posed triangle's length is floored at 1e-4 of its rest area (finite gradient)
        length = jnp.sqrt(jnp.sum(n**2, -1) + (1e-4 * area) ** 2)
        return jnp.sum(n * n0, axis=-1) / (length * area)

    bound = jnp.minimum(jax.lax.stop_gradient(cosine(truth)), margin)
    penalty = jax.nn.relu(bound - cosine(predicted)) * real
    return jnp.sum(penalty) / (jnp.maximum(jnp.sum(real), 1.0) * predicted.shape[0])


def stretch_penalty(
    predicted: Float[ArrayLike, "Q V 3"],
    truth: Float[ArrayLike, "Q V 3"],
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    face_mask: Float[ArrayLike, " F"] | Int[ArrayLike, " F"] | Bool[ArrayLike, " F"] | None = None,
    margin: float | Float[Array, ""] = 0.25,
) -> Float[Array, ""]:
    """Mean over poses and the edges of real triangles (each triangle's three; an interior
    edge counts twice) of ``relu(|log r_predicted| - max(|log r_truth|, margin))``, with ``r``
    an edge's posed length over its rest length: how far an edge is stretched or compressed
    beyond both the truth and ``margin``. 0 for a prediction equal to the truth and for any
    rigid motion. Rest edges of zero length and padding are left out."""
    predicted, truth = jnp.asarray(predicted), jnp.asarray(truth)
    vertices, faces = jnp.asarray(vertices), jnp.asarray(faces)
    mask = jnp.ones(faces.shape[0]) if face_mask is None else jnp.asarray(face_mask, jnp.float32)
    tails = jnp.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    heads = jnp.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    rest = _safe_norm(vertices[heads] - vertices[tails])
    real = jnp.tile(mask, 3) * (rest > 1e-9 * jnp.max(rest))
    rest = jnp.where(real > 0, rest, 1.0)

    def log_ratio(displacements):
        x = vertices[None] + displacements
        length = jnp.sqrt(jnp.sum((x[:, heads] - x[:, tails]) ** 2, -1) + 1e-30)
        return jnp.abs(jnp.log(length / rest))

    bound = jnp.maximum(jax.lax.stop_gradient(log_ratio(truth)), margin)
    penalty = jax.nn.relu(log_ratio(predicted) - bound) * real
    return jnp.sum(penalty) / (jnp.maximum(jnp.sum(real), 1.0) * predicted.shape[0])


def batch_loss(
    model: RigAnyFace,
    data: TrainingSet,
    heads: Int[Array, " B"],
    poses: Int[Array, "B Q"],
    landmark_weight: float | Float[Array, ""],
    reference: float | Float[Array, ""],
    loss_kind: str = "squared",
    static_weight: float | Float[Array, ""] = 0.0,
    balance_poses: float = 0.0,
    quality: tuple[float, float, float, float] = (0.0, 0.5, 0.0, 0.25),
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Loss and mean vertex error (unit-sphere units) of ``heads`` (B,) x ``poses`` (B, Q).

    ``quality``: (flip_weight, flip_margin, stretch_weight, stretch_margin) of the mesh-quality
    terms (``flip_penalty``, ``stretch_penalty``; Python floats: a zero weight leaves its term
    out of the computation)."""
    flip_weight, flip_margin, stretch_weight, stretch_margin = quality

    def one(h, pose_ids):
        ops = jax.tree.map(lambda x: x[h], data.operators)
        base = None if data.base is None else data.base[h][pose_ids]
        predicted = model(data.poses[pose_ids], data.vertices[h], ops, base=base)  # (Q, V, 3)
        truth = data.displacements[h][pose_ids]
        error = predicted - truth
        squared = jnp.sum(error**2, axis=-1)  # (Q, V)
        mask = ops.vertex_mask
        distances = jnp.sqrt(squared + 1e-20)
        distance = jnp.sum(distances * mask) / (jnp.sum(mask) * squared.shape[0])
        root = jnp.sqrt(reference)
        # mean predicted motion where the truth is still, over the loss's own scale
        static = static_vertex_error(predicted, truth, mask, STATIC_CM / data.scale[h]) / root
        terms_quality = 0.0
        if flip_weight:
            terms_quality = terms_quality + flip_weight * flip_penalty(
                predicted, truth, data.vertices[h], ops.faces, ops.face_mask, flip_margin
            )
        if stretch_weight:
            terms_quality = terms_quality + stretch_weight * stretch_penalty(
                predicted, truth, data.vertices[h], ops.faces, ops.face_mask, stretch_margin
            )
        if loss_kind == "squared":
            per_vertex, scale = squared, reference
        else:
            per_vertex, scale = distances, root
        if balance_poses:  # per pose (Q,), each over what predicting no motion scores
            size = jnp.sum(truth**2, axis=-1)
            size = size if loss_kind == "squared" else jnp.sqrt(size + 1e-20)

            def terms(x):
                return jnp.sum(x * mask, axis=1) / jnp.sum(mask) + landmark_weight * jnp.mean(
                    x[:, data.landmarks[h]], axis=1
                )

            divisor = jnp.maximum(terms(size), BALANCE_FLOOR * scale)
            if balance_poses != 1:
                divisor = scale ** (1 - balance_poses) * divisor**balance_poses
            fit = jnp.mean(terms(per_vertex) / divisor)
            return fit + static_weight * static + terms_quality, distance
        # the balanced branch's mean with every divisor = scale, summed in the order the committed
        # checkpoints were trained with, so their commands regenerate them bit for bit
        vertex_term = jnp.sum(per_vertex * mask) / (jnp.sum(mask) * squared.shape[0])
        landmark_term = jnp.mean(per_vertex[:, data.landmarks[h]])
        fit = (vertex_term + landmark_weight * landmark_term) / scale
        return fit + static_weight * static + terms_quality, distance

    loss, distance = jax.vmap(one)(heads, poses)
    return jnp.mean(loss), jnp.mean(distance)


@eqx.filter_jit
def train_step(
    model: RigAnyFace,
    opt_state: PyTree,
    data: TrainingSet,
    heads: Int[Array, " B"],
    poses: Int[Array, "B Q"],
    optim: optax.GradientTransformation,
    landmark_weight: float | Float[Array, ""],
    reference: float | Float[Array, ""],
    loss_kind: str = "squared",
    static_weight: float | Float[Array, ""] = 0.0,
    balance_poses: float = 0.0,
    quality: tuple[float, float, float, float] = (0.0, 0.5, 0.0, 0.25),
) -> tuple[RigAnyFace, PyTree, Float[Array, ""], Float[Array, ""]]:
    (loss, distance), grads = eqx.filter_value_and_grad(batch_loss, has_aux=True)(
        model,
        data,
        heads,
        poses,
        landmark_weight,
        reference,
        loss_kind,
        static_weight,
        balance_poses,
        quality,
    )
    updates, opt_state = optim.update(grads, opt_state, eqx.filter(model, eqx.is_array))
    return eqx.apply_updates(model, updates), opt_state, loss, distance


@dataclasses.dataclass
class RigAnyFaceTrainResult:
    model: RigAnyFace
    step: int
    seconds: float
    history: list


def load_riganyface(path: str | os.PathLike) -> tuple[RigAnyFace, PoseSet, dict]:
    """(model, pose set, header) of a training checkpoint, or of its weights-only copy
    (``export_riganyface``). The packaged default (``DEFAULT_CHECKPOINT``) is first checked
    against its recorded SHA-256 (``CorruptFileError`` naming the file if it differs)."""
    for packaged, digest in packaged_models().items():
        if _is_same_file(path, packaged):
            verify_sha256(path, digest)
    state = read_checkpoint_state(path, CHECKPOINT_FORMAT)
    options = RigAnyFaceTrainOptions(**state["options"])
    poses = PoseSet.from_dict(state["poses"])
    if state.get("weights_only"):
        # the model's structure without initialising it (no compiled work: ~3 s less)
        like = eqx.filter_eval_shape(make_model, options, poses.n_basis, state["output_scale"])
        model, state = load_checkpoint(path, like, CHECKPOINT_FORMAT)
        return model, poses, state
    like = make_model(options, poses.n_basis, state["output_scale"])
    like_opt = optimiser(options).init(eqx.filter(like, eqx.is_array))
    (model, _), state = load_checkpoint(path, (like, like_opt), CHECKPOINT_FORMAT)
    return model, poses, state


def packaged_models() -> dict:
    """Every model shipped in the package and the SHA-256 it is checked against on load."""
    return {
        DEFAULT_CHECKPOINT: DEFAULT_CHECKPOINT_SHA256,
        RESIDUAL_CHECKPOINT: RESIDUAL_CHECKPOINT_SHA256,
    }


def _is_same_file(path, packaged: Path) -> bool:
    return (
        isinstance(path, str | os.PathLike)
        and os.path.isfile(path)
        and packaged.is_file()
        and os.path.samefile(path, packaged)
    )


def export_riganyface(checkpoint: str | os.PathLike, path: str | os.PathLike) -> Path:
    """A weights-only, xz-compressed copy of the training checkpoint ``checkpoint`` at
    ``path`` (atomically): the model and the header (options, pose set, training history),
    without the optimiser state, about a third of the size. ``load_riganyface`` reads it to
    the same model; training cannot resume from it. The packaged default model
    (``DEFAULT_CHECKPOINT``) is made this way."""
    model, _, state = load_riganyface(checkpoint)
    state = {k: v for k, v in state.items() if k != "format"}
    return save_checkpoint(
        path, model, {**state, "weights_only": True}, CHECKPOINT_FORMAT, compress=True
    )


def train_riganyface(
    data: TrainingSet,
    poses: PoseSet,
    options: RigAnyFaceTrainOptions,
    *,
    checkpoint: str | os.PathLike | None = None,
    progress: bool = True,
    stop_after: int | None = None,
    devices: int | None = None,
) -> RigAnyFaceTrainResult:
    """Train (or resume from ``checkpoint`` when it exists) for ``options.steps`` steps or
    ``options.max_minutes`` of accumulated training time, whichever comes first. A checkpoint
    resumes only with the same options except ``max_minutes``. ``stop_after`` ends this call
    after that many steps (a simulated interruption, for tests). ``devices`` (default: all):
    data-parallel over that many devices (``canrig_jax._sharding.data_parallel``), each step's heads
    split over them, parameters and training set replicated; across processes
    (``canrig_jax.distributed.initialize`` first) the devices of every process, process 0
    writing the checkpoint."""
    _check_training_inputs(data, poses, options)
    placement = data_parallel(devices, options.heads_per_step, "heads_per_step")
    reference = mean_square_displacement(data)
    optim = optimiser(options)

    initial = _initial_model(options, poses)
    # a fine-tuned model keeps the output scale of the model it starts from
    start_scale = float(np.sqrt(reference)) if initial is None else initial[1]

    def init(header):
        # a resumed model keeps the output scale it was built with
        scale = header.get("output_scale", start_scale)
        model = make_model(options, poses.n_basis, scale) if initial is None else initial[0]
        return model, optim.init(eqx.filter(model, eqx.is_array))

    run = resume_training(
        checkpoint, CHECKPOINT_FORMAT, init, options, lambda d: RigAnyFaceTrainOptions(**d)
    )
    header = {
        "options": options.to_dict(),
        "poses": poses.to_dict(),
        "output_scale": run.header.get("output_scale", start_scale),
        "reference": reference,
    }
    data, run.tree = placement.replicate((data, run.tree))
    train_resumably(
        _step_function(data, poses, options, optim, reference, placement),
        run,
        options,
        checkpoint=checkpoint,
        format=CHECKPOINT_FORMAT,
        header=header,
        progress=progress,
        desc="riganyface",
        stop_after=stop_after,
    )
    return RigAnyFaceTrainResult(
        model=placement.local(run.tree[0]),
        step=run.step,
        seconds=run.seconds,
        history=run.history,
    )


ARCHITECTURE_FIELDS = ("width", "n_shared", "n_conditional", "global_size", "global_width",
                       "k", "method", "stem_method", "residual", "residual_gate")  # fmt: skip
"""The options that define a RigAnyFace network's structure (``init_from`` must match them)."""


def _initial_model(options: RigAnyFaceTrainOptions, poses: PoseSet):
    """(model, output scale) of ``options.init_from``, or None."""
    if options.init_from is None:
        return None
    if not os.path.isfile(options.init_from):
        raise ValueError(f"init_from: no such file {options.init_from!r}")
    model, their_poses, state = load_riganyface(options.init_from)
    theirs = state["options"]
    differ = [f for f in ARCHITECTURE_FIELDS if theirs.get(f) != getattr(options, f)]
    if differ:
        raise ValueError(
            f"init_from: {options.init_from} was built with other "
            + ", ".join(f"{f}={theirs.get(f)!r} (options: {getattr(options, f)!r})" for f in differ)
        )
    if their_poses != poses:
        raise ValueError(f"init_from: {options.init_from} has another pose set")
    return model, float(state["output_scale"])


def _check_training_inputs(data: TrainingSet, poses: PoseSet, options: RigAnyFaceTrainOptions):
    if data.poses.shape[0] != poses.n_poses:
        raise ValueError(f"data: {data.poses.shape[0]} poses, the pose set {poses.n_poses}")
    if options.residual != (data.base is not None):
        raise ValueError(
            "data: a residual model trains on a training set with base displacements "
            f"(training_set(..., base=...)); residual={options.residual}, "
            f"base given: {data.base is not None}"
        )
    if options.poses_per_step > poses.n_poses:
        raise ValueError(
            f"poses_per_step: {options.poses_per_step} exceeds the {poses.n_poses} poses"
        )


def _quality(options: RigAnyFaceTrainOptions) -> tuple[float, float, float, float]:
    return (
        float(options.flip_weight),
        float(options.flip_margin),
        float(options.stretch_weight),
        float(options.stretch_margin),
    )


def _step_function(data, poses, options, optim, reference: float, placement):
    """One optimiser step on (model, optimiser state), its heads and poses drawn from the
    step number."""
    landmark_weight = jnp.asarray(options.landmark_weight, jnp.float32)
    static_weight = jnp.asarray(options.static_weight, jnp.float32)
    reference_j = jnp.asarray(reference, jnp.float32)
    mm_per_unit = float(np.mean(np.asarray(data.scale))) * CM_TO_MM

    def one_step(tree, step):
        model, opt_state = tree
        rng = np.random.default_rng([options.seed, step])
        heads = rng.integers(0, data.n_heads, options.heads_per_step)
        pose_ids = np.stack(
            [
                rng.choice(poses.n_poses, options.poses_per_step, replace=False)
                for _ in range(options.heads_per_step)
            ]
        )
        heads, pose_ids = placement.shard((heads, pose_ids))
        model, opt_state, loss, distance = train_step(
            model,
            opt_state,
            data,
            heads,
            pose_ids,
            optim,
            landmark_weight,
            reference_j,
            options.loss,
            static_weight,
            options.balance_poses,
            _quality(options),
        )
        metrics = {"loss": loss, "error_unit": distance, "error_mm": distance * mm_per_unit}
        return (model, opt_state), metrics

    return one_step
