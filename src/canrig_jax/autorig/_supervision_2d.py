"""Training RigAnyFace with 2D supervision (the paper's section 3.3 and its two stages).

Heads whose 3D rig is withheld ("unrigged") are supervised only through renderings of their
ground-truth poses from a few fixed views (``canrig_jax.render``, orthographic cameras on the
unit-sphere head): the **mask** of the posed head, the **2D displacement** field (each
visible neutral surface point's screen motion, neutral -> pose) and the 68 **2D landmarks**.
By default they are rendered by the fast path (``rasterise_hard`` visibility,
``interpolate``, antialiased ``silhouette``: tens of ms per 256^2 view), else by the soft
rasteriser (``Supervision2DOptions.rasteriser``).
This replaces the paper's MegActor videos and RAFT flow (their weights cannot be obtained
here) by the same three signals rendered from the held-back ground truth, so it measures how
much the 2D route can carry when its signals are clean.

Per step, for each drawn head, ``poses_2d`` of its drawn poses and every view:

* mask: mean squared difference of the predicted and the target silhouettes (antialiased,
  or soft);
* displacement: the neutral is rendered once per view with the per-vertex screen-displacement
  error of all those poses as attributes (interpolation is linear in the attributes), and the
  mean squared error over the neutral's silhouette, in pixels, divided by the target's mean
  square;
* landmarks: mean squared 2D error of the projected landmark vertices, divided the same way.

Stage 1 (``stage="2d"``) trains on all heads with the 2D loss only; stage 2 (``"3d+2d"``)
continues on the rigged heads with the 3D loss of ``_train.batch_loss`` plus
``weight_2d`` x the 2D loss; ``"3d"`` is 3D only (the baseline). The 3D loss never sees an
unrigged head: its heads are drawn from ``rigged`` only.
"""

import dataclasses
import os
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, Int32

from .._checkpoint import (
    load_checkpoint,
    read_checkpoint_state,
    resume_training,
    train_resumably,
)
from .._metrics import CM_TO_MM
from ..render import (
    Camera,
    RasterSettings,
    interpolate,
    orbit_cameras,
    project_points,
    rasterise,
    rasterise_hard,
    screen_displacement,
    silhouette,
)
from ._data import PoseSet, RiggedHead
from ._model import RigAnyFace
from ._train import RigAnyFaceTrainOptions, TrainingSet, batch_loss, make_model, optimiser

CHECKPOINT_FORMAT_2D = "riganyface-2d-checkpoint-1"
STAGES = ("2d", "3d+2d", "3d")
RASTERISERS = ("fast", "soft")


@dataclasses.dataclass(frozen=True)
class Supervision2DOptions:
    """Views and weights of the 2D loss.

    Attributes:
        image_size: pixels (square) of every rendering.
        yaw_degrees: orthographic views about +y (0 = in front).
        ortho_width: visible width in unit-sphere units; ``target_y``: the views' centre
            height (the face, not the neck).
        poses_2d: poses per head and step that are rendered (a subset of the step's poses).
        mask_weight, displacement_weight, landmark_weight: the three terms.
        weight_2d: the 2D loss's weight next to the 3D loss in stage 2.
        rasteriser: ``"fast"``: hard visibility (``rasterise_hard``), differentiable
            interpolation (``interpolate``) and antialiased masks (``silhouette``);
            ``"soft"``: the soft rasteriser (``rasterise``, seconds per view at 256^2).
        chunk_budget: the fast path's chunk budget (``rasterise_hard``): the orthographic
            views are filled by the face, whose triangles' screen boxes (front, back and
            inner parts) add up to ~7 x the image at 256^2.
        sigma, gamma, faces_per_tile: soft rasteriser settings (``RasterSettings``).
    """

    image_size: int = 48
    yaw_degrees: tuple[float, ...] = (0.0, 35.0)
    ortho_width: float = 1.3
    target_y: float = 0.15
    poses_2d: int = 4
    mask_weight: float = 1.0
    displacement_weight: float = 1.0
    landmark_weight: float = 1.0
    weight_2d: float = 1.0
    rasteriser: str = "fast"
    chunk_budget: float = 10.0
    sigma: float = 0.5
    gamma: float = 1e-2
    faces_per_tile: int = 96

    def __post_init__(self):
        if self.image_size < 8:
            raise ValueError(f"image_size: expected >= 8, got {self.image_size}")
        if not self.yaw_degrees:
            raise ValueError("yaw_degrees: expected at least one view")
        if self.rasteriser not in RASTERISERS:
            raise ValueError(f"rasteriser: expected one of {RASTERISERS}, got {self.rasteriser!r}")
        if not self.chunk_budget > 0:
            raise ValueError(f"chunk_budget: expected > 0, got {self.chunk_budget}")
        if self.poses_2d < 1:
            raise ValueError(f"poses_2d: expected >= 1, got {self.poses_2d}")
        for name in ("mask_weight", "displacement_weight", "landmark_weight", "weight_2d"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name}: expected >= 0")

    def settings(self) -> RasterSettings:
        return RasterSettings(
            sigma=self.sigma, gamma=self.gamma, tile_size=8, faces_per_tile=self.faces_per_tile
        )

    def cameras(self) -> Camera:
        return orbit_cameras(
            (0.0, self.target_y, 0.0),
            3.0,
            list(self.yaw_degrees),
            image_size=self.image_size,
            projection="orthographic",
            ortho_width=self.ortho_width,
        )

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["yaw_degrees"] = list(self.yaw_degrees)
        return d


def padded_faces(heads: list[RiggedHead]) -> Int32[Array, "N F 3"]:
    """(N, F, 3) int32 faces of ``heads`` padded with degenerate (0, 0, 0) triangles, which
    the rasteriser skips (zero screen area)."""
    n_faces = max(h.faces.shape[0] for h in heads)
    out = np.zeros((len(heads), n_faces, 3), np.int32)
    for i, h in enumerate(heads):
        out[i, : h.faces.shape[0]] = h.faces
    return jnp.asarray(out)


def loss_2d(
    predicted: Float[Array, "Q V 3"],
    truth: Float[Array, "Q V 3"],
    vertices: Float[Array, "V 3"],
    faces: Int[Array, "F 3"],
    landmarks: Int[Array, " L"],
    cameras: Camera,
    options: Supervision2DOptions,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """2D loss of one head: ``predicted`` and ``truth`` (Q, V, 3) displacements (unit-sphere
    units) of its ``vertices`` (V, 3). Returns (loss, dict of the three terms)."""
    settings = options.settings()
    truth = jax.lax.stop_gradient(truth)
    posed_pred = vertices[None] + predicted
    posed_true = vertices[None] + truth

    def one_view(camera):
        if options.rasteriser == "fast":

            def fragments(v):
                return rasterise_hard(v, faces, camera, chunk_budget=options.chunk_budget)

            def mask(posed):
                return silhouette(posed, faces, camera, fragments(posed))

            def field(attributes: Float[Array, "V C"]) -> tuple[Array | None, Array]:
                """(no silhouette, the attributes at the pixels)"""
                values = interpolate(vertices, faces, camera, neutral, attributes).attributes
                assert values is not None  # attributes were given
                return None, values

            neutral = fragments(vertices)
            inside = neutral.covered[..., None]
        else:

            def mask(posed):
                return rasterise(posed, faces, camera, settings=settings).silhouette

            def field(attributes: Float[Array, "V C"]) -> tuple[Array | None, Array]:
                """(the silhouette, the attributes at the pixels)"""
                rendering = rasterise(vertices, faces, camera, attributes, settings=settings)
                assert rendering.attributes is not None  # attributes were given
                return rendering.silhouette, rendering.attributes

            inside = None
        sil_pred = jax.vmap(mask)(posed_pred)
        sil_true = jax.lax.stop_gradient(jax.vmap(mask)(posed_true))
        mask_term = jnp.mean((sil_pred - sil_true) ** 2)
        flow_pred = screen_displacement(camera, vertices, posed_pred)  # (Q, V, 2)
        flow_true = screen_displacement(camera, vertices, posed_true)
        covered, error = field(
            jnp.moveaxis(flow_pred - flow_true, 0, 1).reshape(vertices.shape[0], -1)
        )
        _, target = field(jnp.moveaxis(flow_true, 0, 1).reshape(vertices.shape[0], -1))
        if inside is None:
            assert covered is not None  # the soft rasteriser's silhouette
            inside = covered[..., None]
        area = jnp.maximum(jnp.sum(inside), 1.0)
        flow_error = jnp.sum(inside * error**2) / area
        flow_scale = jnp.sum(inside * target**2) / area
        lm_pred, _ = project_points(camera, posed_pred[:, landmarks])
        lm_true, _ = project_points(camera, posed_true[:, landmarks])
        lm_error = jnp.mean(jnp.sum((lm_pred - lm_true) ** 2, -1))
        lm_scale = jnp.mean(
            jnp.sum((lm_true - project_points(camera, vertices[landmarks])[0]) ** 2, -1)
        )
        scale = jax.lax.stop_gradient(jnp.maximum(flow_scale, 1e-6))
        lm_scale = jax.lax.stop_gradient(jnp.maximum(lm_scale, 1e-6))
        return mask_term, flow_error / scale, lm_error / lm_scale

    mask_term, flow_term, lm_term = (jnp.mean(t) for t in jax.vmap(one_view)(cameras))
    total = (
        options.mask_weight * mask_term
        + options.displacement_weight * flow_term
        + options.landmark_weight * lm_term
    )
    return total, {"mask": mask_term, "flow": flow_term, "landmarks": lm_term}


def _step_loss(model, data, faces, cameras, heads, poses, rigged_heads, reference, stage, opts2d):
    """Loss of one step: 2D on ``heads`` (B,) x the first ``poses_2d`` of ``poses`` (B, Q),
    3D on ``rigged_heads`` (B,) x ``poses``."""
    metrics = {}
    total = 0.0
    if stage in ("2d", "3d+2d"):

        def one(h, pose_ids):
            ops = jax.tree.map(lambda x: x[h], data.operators)
            ids = pose_ids[: opts2d.poses_2d]
            predicted = model(data.poses[ids], data.vertices[h], ops)
            truth = data.displacements[h][ids]
            return loss_2d(
                predicted,
                truth,
                data.vertices[h],
                faces[h],
                data.landmarks[h],
                cameras,
                opts2d,
            )

        heads_2d = heads if stage == "2d" else rigged_heads
        loss2, terms = jax.vmap(one)(heads_2d, poses)
        weight = 1.0 if stage == "2d" else opts2d.weight_2d
        total = total + weight * jnp.mean(loss2)
        metrics.update({k: jnp.mean(v) for k, v in terms.items()})
    if stage in ("3d", "3d+2d"):
        loss3, distance = batch_loss(model, data, rigged_heads, poses, 1.0, reference)
        total = total + loss3
        metrics["loss_3d"] = loss3
        metrics["error_unit"] = distance
    return total, metrics


@eqx.filter_jit
def _train_step(
    model, opt_state, data, faces, cameras, heads, poses, rigged, reference, optim, stage, opts2d
):
    (loss, metrics), grads = eqx.filter_value_and_grad(_step_loss, has_aux=True)(
        model, data, faces, cameras, heads, poses, rigged, reference, stage, opts2d
    )
    updates, opt_state = optim.update(grads, opt_state, eqx.filter(model, eqx.is_array))
    return eqx.apply_updates(model, updates), opt_state, loss, metrics


def rigged_reference(data: TrainingSet, rigged: Int[ArrayLike, " R"]) -> float:
    """Mean square displacement (unit-sphere units) over the rigged heads only: the 3D loss
    scale and the model's output scale (no unrigged head's 3D rig enters it)."""
    rigged = np.asarray(rigged)
    mask = np.asarray(data.operators.vertex_mask)[rigged]
    squared = np.sum(np.asarray(data.displacements)[rigged] ** 2, axis=-1)
    return float((squared * mask[:, None]).sum() / (mask.sum() * squared.shape[1]))


def train_2d(
    data: TrainingSet,
    faces: Int[ArrayLike, "N F 3"],
    poses: PoseSet,
    rigged: Int[ArrayLike, " R"] | Sequence[int],
    options: RigAnyFaceTrainOptions,
    opts2d: Supervision2DOptions,
    *,
    stage: str,
    init: RigAnyFace | None = None,
    checkpoint: str | os.PathLike | None = None,
    progress: bool = True,
    stop_after: int | None = None,
) -> tuple[RigAnyFace, int, float, list]:
    """Train one stage (``"2d"``, ``"3d+2d"`` or ``"3d"``) for ``options.steps`` steps (or
    ``options.max_minutes``), resuming from ``checkpoint`` when it exists. ``init``: the
    model to start from (stage 2 starts from stage 1's), else a fresh one. ``rigged``: indices
    of the heads whose 3D rig may be used; 2D stage-1 steps draw from all heads.

    Returns (model, step, seconds, history)."""
    rigged = _check_stage_inputs(data, rigged, options, opts2d, stage)
    reference = rigged_reference(data, rigged)
    optim = optimiser(options)

    def start(header):
        model = init
        if model is None:
            model = make_model(options, poses.n_basis, float(np.sqrt(reference)))
        return model, optim.init(eqx.filter(model, eqx.is_array))

    # stage "3d" renders nothing: its checkpoint does not depend on the 2D options
    options_2d = None if stage == "3d" else opts2d.to_dict()

    def check(header):
        if (stage != "3d" and header["options_2d"] != options_2d) or header["stage"] != stage:
            raise ValueError(f"checkpoint: {checkpoint} was written with different options")

    run = resume_training(
        checkpoint,
        CHECKPOINT_FORMAT_2D,
        start,
        options,
        lambda d: RigAnyFaceTrainOptions(**d),
        check=check,
    )
    header = {
        "options": options.to_dict(),
        "options_2d": options_2d,
        "stage": stage,
        "poses": poses.to_dict(),
        "output_scale": float(np.sqrt(reference)),
    }
    train_resumably(
        _step_function(data, faces, poses, rigged, options, opts2d, stage, optim, reference),
        run,
        options,
        checkpoint=checkpoint,
        format=CHECKPOINT_FORMAT_2D,
        header=header,
        progress=progress,
        desc=f"riganyface-{stage}",
        stop_after=stop_after,
    )
    return run.tree[0], run.step, run.seconds, run.history


def _check_stage_inputs(data, rigged, options, opts2d, stage) -> np.ndarray:
    """``rigged`` as int64 indices, after checking the stage's arguments."""
    if stage not in STAGES:
        raise ValueError(f"stage: expected one of {STAGES}, got {stage!r}")
    rigged = np.asarray(rigged, np.int64)
    if rigged.size == 0 or rigged.min() < 0 or rigged.max() >= data.n_heads:
        raise ValueError(f"rigged: expected head indices in [0, {data.n_heads})")
    if options.residual:
        raise ValueError("options: 2D supervision trains the pure model (residual=False)")
    if opts2d.poses_2d > options.poses_per_step:
        raise ValueError("poses_2d: exceeds options.poses_per_step")
    return rigged


def _step_function(data, faces, poses, rigged, options, opts2d, stage, optim, reference):
    """One optimiser step of ``stage`` on (model, optimiser state), its heads and poses drawn
    from the step number and the stage."""
    cameras = opts2d.cameras()
    reference_j = jnp.asarray(reference, jnp.float32)
    mm_per_unit = float(np.mean(np.asarray(data.scale))) * CM_TO_MM

    def one_step(tree, step):
        model, opt_state = tree
        rng = np.random.default_rng([options.seed, step, STAGES.index(stage)])
        heads = rng.integers(0, data.n_heads, options.heads_per_step)
        rigged_heads = rigged[rng.integers(0, rigged.size, options.heads_per_step)]
        pose_ids = np.stack(
            [
                rng.choice(poses.n_poses, options.poses_per_step, replace=False)
                for _ in range(options.heads_per_step)
            ]
        )
        model, opt_state, loss, metrics = _train_step(
            model,
            opt_state,
            data,
            faces,
            cameras,
            jnp.asarray(heads),
            jnp.asarray(pose_ids),
            jnp.asarray(rigged_heads),
            reference_j,
            optim,
            stage,
            opts2d,
        )
        out = {"loss": loss, **metrics}
        if "error_unit" in metrics:
            out["error_mm"] = metrics["error_unit"] * mm_per_unit
        return (model, opt_state), out

    return one_step


def load_model_2d(path: str | os.PathLike, poses: PoseSet | None = None) -> tuple[RigAnyFace, dict]:
    """(model, header) of a ``train_2d`` checkpoint."""
    state = read_checkpoint_state(path, CHECKPOINT_FORMAT_2D)
    options = RigAnyFaceTrainOptions(**state["options"])
    poses = PoseSet.from_dict(state["poses"]) if poses is None else poses
    like = make_model(options, poses.n_basis, state["output_scale"])
    like_opt = optimiser(options).init(eqx.filter(like, eqx.is_array))
    (model, _), state = load_checkpoint(path, (like, like_opt), CHECKPOINT_FORMAT_2D)
    return model, state
