"""Pose space editing: per-vertex Gaussian RBF interpolation of sculpted corrections.

PSE (Lewis et al. 2000) and WPSE (Seol et al.) share one model. Given P edit poses w_i (K,)
and the displacement d_{v,i} an artist sculpted at each (desired minus base mesh), the
correction of vertex v at pose w is

    d_v(w) = sum_i x_{v,i} phi(||w - w_i||_v),   phi(r) = exp(-r^2 / (2 sigma^2)),

with the coefficients from the P x P system Phi_v X_v = D_v, (Phi_v)_{ik} = phi(||w_i - w_k||_v).
PSE uses the Euclidean distance for every vertex (one Phi for the whole mesh); WPSE the
per-vertex weighted distance of ``_metric.py`` (one Phi per edited vertex, solved by a batched
Cholesky factorisation). Displacements live in per-vertex local frames of the posed base mesh
(``_frames.py``) unless ``local_frames=False``.

Only vertices that some edit moves (by more than ``support_tol``) are stored and evaluated.
Duplicated edit poses make every Phi singular: ``fit_pose_space_edit`` raises unless
``duplicates="merge"`` (one edit with their mean displacement, what a ridge-regularised solve
tends to), and ``_layers.py`` routes a new edit close to an old one to a new layer instead.
"""

from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Float32, Int

from .._checks import check_finite as _check_finite
from .._checks import is_concrete
from .._linalg import cho_solve, cholesky
from ..rig import BlendshapeRig, evaluate
from ._frames import LocalFrames, frame_matrices, local_frames, local_to_world, to_local
from ._metric import (
    blendshape_metric,
    euclidean_metric,
    gaussian_kernel,
    pairwise_pose_distance_sq,
    pose_distance_sq,
)

DUPLICATE_DISTANCE = 1e-4
"""Edit poses closer than this (Euclidean, in weight units) count as duplicates."""


class PoseSpaceEdit(eqx.Module):
    """A trained pose-space edit (PSE or WPSE) of a rig.

    Attributes:
        poses: (P, K) edit poses.
        vertices: (S,) edited vertices (strictly increasing).
        metric: (S, K) per-vertex blendshape weights (WPSE) or (1, K) shared (PSE).
        coefficients: (S, 3, P) RBF coefficients per vertex (X_v transposed, the fast layout
            for the run-time contraction), in local-frame or world axes.
        sigma: Gaussian width, in the units of the metric's distance.
        frames: local-frame topology at ``vertices``, or None for world-space displacements.
        n_vertices: vertex count of the rig (static).
    """

    poses: Float[Array, "P K"]
    vertices: Int[Array, " S"]
    metric: Float[Array, "#S K"]
    coefficients: Float[Array, "S 3 P"]
    sigma: Float[Array, ""]
    frames: LocalFrames | None
    n_vertices: int = eqx.field(static=True)

    @property
    def n_edits(self) -> int:
        return int(self.poses.shape[0])

    @property
    def n_blendshapes(self) -> int:
        return int(self.poses.shape[1])


def check_sigma(sigma: Any) -> None:
    if np.ndim(sigma) != 0:
        raise ValueError(f"sigma: expected a scalar, got shape {np.shape(sigma)}")
    if is_concrete(sigma):
        value = float(sigma)
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"sigma: expected a finite value > 0, got {value}")


def check_edits(
    rig: BlendshapeRig, poses: Any, edits: Any
) -> tuple[Float32[np.ndarray, "P K"], Float32[np.ndarray, "P V 3"]]:
    """Validate edit poses (P, K) and displacements (P, V, 3) against a rig."""
    poses = np.asarray(poses, np.float32)
    edits = np.asarray(edits, np.float32)
    k, v = rig.n_blendshapes, rig.n_vertices
    if poses.ndim != 2 or poses.shape[1] != k or poses.shape[0] < 1:
        raise ValueError(
            f"poses: expected shape (P, {k}) with P >= 1 for a rig with {k} blendshapes, "
            f"got {poses.shape}"
        )
    if edits.shape != (poses.shape[0], v, 3):
        raise ValueError(
            f"edits: expected shape ({poses.shape[0]}, {v}, 3) (one displacement per edit "
            f"pose and rig vertex), got {edits.shape}"
        )
    _check_finite("poses", poses)
    _check_finite("edits", edits)
    return poses, edits


def duplicate_groups(
    poses: Float[np.ndarray, "P K"], tol: float = DUPLICATE_DISTANCE
) -> list[list[int]]:
    """Groups of edit indices whose poses lie within ``tol`` of each other (transitively)."""
    p = poses.shape[0]
    distance = np.linalg.norm(poses[:, None, :] - poses[None, :, :], axis=-1)
    label = np.arange(p)
    for i in range(p):
        for j in np.flatnonzero(distance[i, i + 1 :] < tol) + i + 1:
            label[label == label[j]] = label[i]
    return [np.flatnonzero(label == g).tolist() for g in np.unique(label)]


def fit_pose_space_edit(
    rig: BlendshapeRig,
    poses: Float[ArrayLike, "P K"],
    edits: Float[ArrayLike, "P V 3"],
    *,
    sigma: float,
    metric: Literal["weighted", "euclidean"] = "weighted",
    local_frames: bool = True,
    epsilon: float = 1e-3,
    ridge: float = 1e-6,
    support_tol: float = 0.0,
    duplicates: Literal["raise", "merge"] = "raise",
    rest_pose: bool = False,
) -> PoseSpaceEdit:
    """Fit PSE (``metric="euclidean"``) or WPSE (``metric="weighted"``) to sculpted edits.

    Args:
        rig: the base rig being corrected (its posed meshes give the local frames).
        poses: (P, K) weights of the edited frames.
        edits: (P, V, 3) world-space displacements sculpted at each pose (desired - base).
        sigma: Gaussian width (> 0); see ``_sigma.py`` for the GUI mapping and the LOO fit.
        metric: per-vertex weighted distance (WPSE) or the Euclidean one (PSE).
        local_frames: store displacements in local frames of the posed base mesh.
        epsilon: WPSE metric regulariser (``blendshape_metric``).
        ridge: added to the diagonal of every Phi (whose diagonal is 1), for float32 safety.
        support_tol: vertices whose largest edit is at most this (rig units) are not stored.
        duplicates: "raise" (ValueError) or "merge" duplicated edit poses into one edit with
            the mean displacement.
        rest_pose: add the rest pose (all weights 0) as an edit with zero displacement, so the
            correction vanishes there (not in the paper; off by default). Ignored when an
            edit already sits at the rest pose.
    """
    check_sigma(sigma)
    data = prepare_edits(
        rig,
        poses,
        edits,
        metric=metric,
        local_frames=local_frames,
        epsilon=epsilon,
        support_tol=support_tol,
        duplicates=duplicates,
        rest_pose=rest_pose,
    )
    return fit_prepared(data, sigma, ridge)


class EditData(eqx.Module):
    """Edits made ready for the RBF solve (``prepare_edits`` lists the fields)."""

    poses: Float[Array, "P K"]
    vertices: Int[Array, " S"]
    metric: Float[Array, "#S K"]
    displacements: Float[Array, "S P 3"]
    frames: LocalFrames | None
    n_vertices: int = eqx.field(static=True)


def prepare_edits(
    rig: BlendshapeRig,
    poses: Float[ArrayLike, "P K"],
    edits: Float[ArrayLike, "P V 3"],
    *,
    metric: Literal["weighted", "euclidean"] = "weighted",
    local_frames: bool = True,
    epsilon: float = 1e-3,
    support_tol: float = 0.0,
    duplicates: Literal["raise", "merge"] = "raise",
    rest_pose: bool = False,
) -> EditData:
    """Validate edits, restrict them to their support, pick the metric, rotate into local
    frames (arguments as ``fit_pose_space_edit``).

    Returns:
        An ``EditData`` for ``fit_prepared``, ``fit_width`` and ``fit_sigma`` (what training
        and the width fits share): ``poses`` (P, K), the edited ``vertices`` (S,), their
        ``metric`` (S or 1, K), the ``displacements`` (S, P, 3) (in local frames when asked,
        ``frames``, else None) and the mesh's ``n_vertices``.
    """
    if not isinstance(rig, BlendshapeRig):
        raise ValueError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    poses, edits = check_edits(rig, poses, edits)
    if metric not in ("weighted", "euclidean"):
        raise ValueError(f"metric: expected 'weighted' or 'euclidean', got {metric!r}")
    if not np.isfinite(support_tol) or support_tol < 0:
        raise ValueError(f"support_tol: expected a finite value >= 0, got {support_tol}")
    if duplicates not in ("raise", "merge"):
        raise ValueError(f"duplicates: expected 'raise' or 'merge', got {duplicates!r}")
    if rig.faces is None and local_frames:
        raise ValueError("rig: local_frames=True needs a rig with faces")
    groups = duplicate_groups(poses)
    if len(groups) < poses.shape[0]:
        if duplicates == "raise":
            repeated = [g for g in groups if len(g) > 1][:5]
            raise ValueError(
                f"poses: edits {repeated} are at the same pose (within {DUPLICATE_DISTANCE}), "
                "which makes the RBF system singular; pass duplicates='merge' to average them, "
                "or add the later edit to a new layer (canrig_jax.wpse.fit_layered)"
            )
        poses = np.stack([poses[g].mean(axis=0) for g in groups])
        edits = np.stack([edits[g].mean(axis=0) for g in groups])
    if rest_pose and np.all(np.linalg.norm(poses, axis=1) >= DUPLICATE_DISTANCE):
        poses = np.concatenate([poses, np.zeros_like(poses[:1])])
        edits = np.concatenate([edits, np.zeros_like(edits[:1])])

    magnitude = np.linalg.norm(edits, axis=2).max(axis=0)
    vertices = np.flatnonzero(magnitude > support_tol).astype(np.int32)
    edits = jnp.asarray(edits[:, vertices])  # (P, S, 3)
    if metric == "weighted":
        weights = blendshape_metric(rig.deltas, epsilon)[vertices]
    else:
        weights = euclidean_metric(rig.n_blendshapes)
    frames = None
    if local_frames:
        frames = local_frames_of(rig, vertices)
        edits = _edits_to_local(rig, frames, jnp.asarray(poses), edits)
    return EditData(
        poses=jnp.asarray(poses),
        vertices=jnp.asarray(vertices),
        metric=jnp.asarray(weights),
        displacements=jnp.moveaxis(edits, 0, 1),
        frames=frames,
        n_vertices=rig.n_vertices,
    )


@eqx.filter_jit
def _edits_to_local(rig, frames, poses, edits):
    posed = jax.vmap(evaluate, (None, 0))(rig, poses)
    rotation = jax.vmap(frame_matrices, (None, 0))(frames, posed)  # (P, S, 3, 3)
    return jax.vmap(to_local)(rotation, edits)


def fit_prepared(data: EditData, sigma: Float[ArrayLike, ""], ridge: float = 1e-6) -> PoseSpaceEdit:
    """Solve the RBF systems of prepared edits at one sigma."""
    check_sigma(sigma)
    if not np.isfinite(ridge) or ridge < 0:
        raise ValueError(f"ridge: expected a finite value >= 0, got {ridge}")
    sigma = jnp.asarray(sigma, jnp.float32)
    coefficients = solve_coefficients(data.metric, data.poses, data.displacements, sigma, ridge)
    if not bool(jnp.all(jnp.isfinite(coefficients))):
        raise ValueError(
            f"sigma: the RBF system is numerically singular at sigma={float(sigma)} (edit poses "
            "too close for this width); use a smaller sigma, a larger ridge, or layers"
        )
    residual = reproduction_error(data, coefficients, sigma)
    if residual > REPRODUCTION_TOL:
        raise ValueError(
            f"sigma: at sigma={float(sigma):.4g} the edits are no longer reproduced at their own "
            f"poses (largest error {residual:.1%} of the largest edit; the Gaussians are so wide "
            "that the RBF system is ill-conditioned); use a smaller sigma (e.g. wpse.fit_sigma)"
        )
    return PoseSpaceEdit(
        poses=data.poses,
        vertices=data.vertices,
        metric=data.metric,
        coefficients=jnp.swapaxes(coefficients, 1, 2),
        sigma=sigma,
        frames=data.frames,
        n_vertices=data.n_vertices,
    )


REPRODUCTION_TOL = 5e-2
"""Largest error of a fitted edit at its own pose, relative to the largest edit, that
``fit_prepared`` accepts. An RBF interpolant reproduces its data; the ridge and float32 leave
about 1e-6 at small widths and up to a few per cent at twice the leave-one-out width with 50
real ICT edits (measured: WPSE 1.7 % at sigma 0.38, PSE 1.7 % at 2.9), while over-wide
Gaussians miss by tens of per cent (50 edits, sigma 20: PSE 30 %, WPSE 93 %)."""


@jax.jit
def _reproduction_error(metric, poses, displacements, coefficients, sigma):
    phi = basis_matrices(metric, poses, sigma, 0.0)  # (S or 1, P, P)
    phi = jnp.broadcast_to(phi, (coefficients.shape[0],) + phi.shape[1:])
    reproduced = jnp.einsum("spq,sqc->spc", phi, coefficients)
    error = jnp.max(jnp.linalg.norm(reproduced - displacements, axis=-1))
    return error / jnp.maximum(jnp.max(jnp.linalg.norm(displacements, axis=-1)), 1e-30)


def reproduction_error(
    data: EditData, coefficients: Float[Array, "S P 3"], sigma: Float[ArrayLike, ""]
) -> float:
    """max_v,i |Phi_v X_v - D_v|_i / max |D|: how far the fitted edits miss their own poses
    (relative to the largest edit; 0 for no edits)."""
    if data.displacements.size == 0:
        return 0.0
    return float(
        _reproduction_error(data.metric, data.poses, data.displacements, coefficients, sigma)
    )


def local_frames_of(rig: BlendshapeRig, vertices: Int[ArrayLike, " S"]) -> LocalFrames:
    return local_frames(np.asarray(rig.faces), vertices, rig.n_vertices)


def basis_matrices(
    metric: Float[Array, "#S K"],
    poses: Float[Array, "P K"],
    sigma: Float[ArrayLike, ""],
    ridge: float | Float[Array, ""] = 0.0,
) -> Float[Array, "#S P P"]:
    """Phi_v + ridge I for every row of the metric."""
    phi = gaussian_kernel(pairwise_pose_distance_sq(metric, poses), sigma)
    return phi + ridge * jnp.eye(poses.shape[0], dtype=phi.dtype)


@jax.jit
def solve_coefficients(
    metric: Float[Array, "#S K"],
    poses: Float[Array, "P K"],
    edits: Float[Array, "S P 3"],
    sigma: Float[Array, ""],
    ridge: float | Float[Array, ""],
) -> Float[Array, "S P 3"]:
    """X_v = Phi_v^{-1} D_v by a batched Cholesky factorisation (one Phi when shared)."""
    phi = basis_matrices(metric, poses, sigma, ridge)
    factor = cholesky(phi)
    if metric.shape[0] == 1:  # PSE: one system, every vertex a right-hand side
        s, p = edits.shape[0], edits.shape[1]
        rhs = jnp.moveaxis(edits, 1, 0).reshape(p, s * 3)
        x = cho_solve(factor[0], rhs)
        return jnp.moveaxis(x.reshape(p, s, 3), 0, 1)
    return cho_solve(factor, edits)


def correction(
    model: PoseSpaceEdit,
    weights: Float[ArrayLike, " K"],
    posed: Float[ArrayLike, "V 3"] | None = None,
) -> Float[Array, "S 3"]:
    """World-space correction at ``model.vertices`` for pose ``weights``; jit- and vmap-safe.

    ``posed`` (V, 3), the base rig's mesh at ``weights``, is needed for local frames.
    """
    weights = jnp.asarray(weights)
    r2 = pose_distance_sq(model.metric, weights, model.poses)  # (S, P) or (1, P)
    phi = gaussian_kernel(r2, model.sigma)
    offsets = jnp.einsum(
        "sp,scp->sc",
        jnp.broadcast_to(phi, (model.coefficients.shape[0], phi.shape[1])),
        model.coefficients,
    )
    if model.frames is None:
        return offsets
    if posed is None:
        raise ValueError("posed: the model stores local frames; pass the base rig's mesh")
    return local_to_world(model.frames, posed, offsets)


def check_pose(model: PoseSpaceEdit, weights: Any, posed: Any) -> None:
    """Shapes of a run-time pose and base mesh (and finiteness when concrete)."""
    if np.shape(weights) != (model.n_blendshapes,):
        raise ValueError(
            f"weights: expected shape ({model.n_blendshapes},), got {np.shape(weights)}; "
            "batch with jax.vmap"
        )
    if np.shape(posed) != (model.n_vertices, 3):
        raise ValueError(f"posed: expected shape ({model.n_vertices}, 3), got {np.shape(posed)}")
    _check_finite("weights", weights)
    _check_finite("posed", posed)


def apply(
    model: PoseSpaceEdit, weights: Float[ArrayLike, " K"], posed: Float[ArrayLike, "V 3"]
) -> Float[Array, "V 3"]:
    """The edited mesh: ``posed`` (the base rig at ``weights``) plus the correction.

    Raises ValueError (before tracing) for shapes that do not match the model.
    """
    check_pose(model, weights, posed)
    weights = jnp.asarray(weights, model.poses.dtype)
    posed = jnp.asarray(posed, model.poses.dtype)
    return posed.at[model.vertices].add(
        correction(model, weights, posed), indices_are_sorted=True, unique_indices=True
    )


def edited_mesh(
    model: PoseSpaceEdit, rig: BlendshapeRig, weights: Float[ArrayLike, " K"]
) -> Float[Array, "V 3"]:
    """The base rig at ``weights`` with the edit applied."""
    return apply(model, weights, evaluate(rig, weights))
