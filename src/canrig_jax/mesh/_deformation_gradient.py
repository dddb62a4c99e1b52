"""Nonlinear blend of blendshapes through per-triangle deformation gradients.

For each triangle t and target i, the deformation gradient F_ti maps the neutral triangle's
frame (two edges and Sumner & Popović's scaled normal) onto the target's. It is polar-
decomposed F = R S; a pose w blends rotations in log space and stretches linearly,

    F_t(w) = exp(sum_i w_i log R_ti) (I + sum_i w_i (S_ti - I)),

and vertex positions are recovered from the blended triangle edges e_t(w) = F_t(w) e_t by a
sparse least-squares (screened Poisson) solve, prefactorised once per mesh: with D the
(3T, V) edge-difference operator and x_lin the linear blend,

    x(w) = x_lin + u,   u = argmin ||D (x_lin + u) - e(w)||^2 + lambda ||u||^2.

The small ridge lambda (``screening`` times the mean diagonal of D^T D) fixes translation on
every connected component and keeps the correction local: far from the triangles that the
active shapes deform, the nonlinear and linear edges agree and u decays. At a single target
(w = e_i) the blended edges are the target's own and x_lin is the target, so u = 0 and the
target is reproduced exactly.

Triangles where the decomposition is unreliable fall back to the linear blend of their edges,
e_t(w) = e_t + sum_i w_i (e_ti - e_t): degenerate (near-zero area) triangles in the neutral or a
target, inverted ones (det F < 0), and rotations within ``min_angle_to_pi`` of 180 degrees,
where log R is ill-defined.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from jaxtyping import Array, ArrayLike, Float, Float64, Int

from .._checks import check_real
from ._checks import check_mesh

_EDGES = ((0, 1), (1, 2), (2, 0))


def triangle_edges(
    vertices: Float[np.ndarray, "*batch V 3"], faces: Int[np.ndarray, "T 3"]
) -> Float[np.ndarray, "*batch T 3 3"]:
    """(..., T, 3, 3) edge vectors: column e of triangle t is x[faces[t, b]] - x[faces[t, a]]
    for the edges (0,1), (1,2), (2,0)."""
    return np.stack(
        [vertices[..., faces[:, b], :] - vertices[..., faces[:, a], :] for a, b in _EDGES], axis=-1
    )


def triangle_frames(
    vertices: Float[np.ndarray, "*batch V 3"], faces: Int[np.ndarray, "T 3"]
) -> tuple[Float[np.ndarray, "*batch T 3 3"], Float[np.ndarray, "*batch T"]]:
    """(..., T, 3, 3) frames [e1, e2, n / sqrt|n|] (Sumner & Popović 2004) and (..., T) areas."""
    p0, p1, p2 = (vertices[..., faces[:, j], :] for j in range(3))
    e1, e2 = p1 - p0, p2 - p0
    normal = np.cross(e1, e2)
    twice_area = np.linalg.norm(normal, axis=-1)
    scaled = normal / np.sqrt(np.maximum(twice_area, 1e-30))[..., None]
    return np.stack([e1, e2, scaled], axis=-1), 0.5 * twice_area


def _log_rotation(rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-angle vectors (..., 3) and angles (...) of rotation matrices (..., 3, 3)."""
    cos = np.clip((np.trace(rotation, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    skew = np.stack(
        [
            rotation[..., 2, 1] - rotation[..., 1, 2],
            rotation[..., 0, 2] - rotation[..., 2, 0],
            rotation[..., 1, 0] - rotation[..., 0, 1],
        ],
        axis=-1,
    )
    sin = np.sin(angle)
    small = angle < 1e-4
    factor = np.where(small, 0.5 + angle**2 / 12.0, angle / (2.0 * np.where(small, 1.0, sin)))
    return factor[..., None] * skew, angle


def _exp_rotation(axis_angle: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """Rodrigues' formula, safe at zero angle."""
    angle_sq = jnp.sum(axis_angle**2, axis=-1)
    angle = jnp.sqrt(jnp.maximum(angle_sq, 1e-30))
    small = angle_sq < 1e-8
    a = jnp.where(small, 1.0 - angle_sq / 6.0, jnp.sin(angle) / angle)
    b = jnp.where(
        small, 0.5 - angle_sq / 24.0, (1.0 - jnp.cos(angle)) / jnp.maximum(angle_sq, 1e-30)
    )
    x, y, z = axis_angle[..., 0], axis_angle[..., 1], axis_angle[..., 2]
    zero = jnp.zeros_like(x)
    skew = jnp.stack(
        [jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1), jnp.stack([-y, x, zero], -1)],
        axis=-2,
    )
    eye = jnp.eye(3, dtype=axis_angle.dtype)
    return eye + a[..., None, None] * skew + b[..., None, None] * (skew @ skew)


@jax.jit
def _blend_edges(
    weights: Float[Array, " K"],
    log_rotations: Float[Array, "K T 3"],
    stretch_offsets: Float[Array, "K T 3 3"],
    rest_edges: Float[Array, "T 3 3"],
    edge_offsets: Float[Array, "K T 3 3"],
    fallback: Float[Array, " T"],
) -> Float[Array, "T 3 3"]:
    rotation = _exp_rotation(jnp.tensordot(weights, log_rotations, axes=1))
    stretch = jnp.eye(3, dtype=weights.dtype) + jnp.tensordot(weights, stretch_offsets, axes=1)
    nonlinear = rotation @ stretch @ rest_edges
    linear = rest_edges + jnp.tensordot(weights, edge_offsets, axes=1)
    return jnp.where(fallback[:, None, None] > 0, linear, nonlinear)


@dataclasses.dataclass(frozen=True)
class FallbackCounts:
    """Triangles blended linearly, by reason (a triangle may have several)."""

    degenerate: int
    inverted: int
    near_half_turn: int
    total: int


class DeformationGradientBlend:
    """Prefactorised deformation-gradient blend of one mesh's blendshapes.

    Args:
        neutral: (V, 3) rest vertices.
        deltas: (K, V, 3) blendshape offsets.
        faces: (F, 3) triangles.
        min_area: triangles with area below this (squared rig units) in the neutral or any
            target are degenerate.
        min_angle_to_pi: rotations closer than this (radians) to a half turn fall back.
        screening: ridge of the solve relative to the mean diagonal of D^T D; larger keeps
            the nonlinear correction more local (1e-3: it decays over a few tens of edges).

    Call it with weights (K,) or (B, K) to get (V, 3) or (B, V, 3) float64 vertices.
    """

    def __init__(
        self,
        neutral: Float[ArrayLike, "V 3"],
        deltas: Float[ArrayLike, "K V 3"],
        faces: Int[ArrayLike, "F 3"],
        *,
        min_area: float = 1e-8,
        min_angle_to_pi: float = np.deg2rad(10.0),
        screening: float = 1e-3,
    ):
        neutral, faces = check_mesh(neutral, faces, name="neutral")
        deltas = np.asarray(deltas)
        if deltas.ndim != 3 or deltas.shape[1:] != neutral.shape or deltas.shape[0] == 0:
            raise ValueError(
                f"deltas: expected shape (K, {neutral.shape[0]}, 3) with K >= 1, got {deltas.shape}"
            )
        check_real("deltas", deltas)
        deltas = deltas.astype(np.float64)
        if not np.all(np.isfinite(deltas)):
            raise ValueError("deltas: contains non-finite values")
        for name, value, ok in (
            ("min_area", min_area, np.isfinite(min_area) and min_area >= 0),
            ("min_angle_to_pi", min_angle_to_pi, 0 <= min_angle_to_pi < np.pi),
            ("screening", screening, np.isfinite(screening) and screening > 0),
        ):
            if not ok:
                raise ValueError(f"{name}: out of range, got {value}")
        self.n_vertices, self.n_blendshapes = neutral.shape[0], deltas.shape[0]
        self.neutral, self.deltas, self.faces = neutral, deltas, faces

        rest_frame, rest_area = triangle_frames(neutral, faces)
        target_frame, target_area = triangle_frames(neutral[None] + deltas, faces)
        degenerate = (rest_area < min_area) | np.any(target_area < min_area, axis=0)
        safe_rest = np.where(degenerate[:, None, None], np.eye(3), rest_frame)
        gradient = target_frame @ np.linalg.inv(safe_rest)  # (K, T, 3, 3)
        u, sigma, vt = np.linalg.svd(gradient)
        inverted = np.any(np.linalg.det(u @ vt) < 0, axis=0)
        rotation = u @ vt
        stretch = np.swapaxes(vt, -1, -2) @ (sigma[..., None] * vt)
        log_rotation, angle = _log_rotation(rotation)
        half_turn = np.any(angle > np.pi - min_angle_to_pi, axis=0)
        fallback = degenerate | inverted | half_turn
        self.fallback_counts = FallbackCounts(
            int(degenerate.sum()), int(inverted.sum()), int(half_turn.sum()), int(fallback.sum())
        )
        self.fallback = fallback

        rest_edges = triangle_edges(neutral, faces)
        keep = ~fallback[None, :, None]
        f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
        self._blend_args = (
            f32(np.where(keep, log_rotation, 0.0)),
            f32(np.where(keep[..., None], stretch - np.eye(3), 0.0)),
            f32(rest_edges),
            f32(triangle_edges(neutral[None] + deltas, faces) - rest_edges),
            f32(fallback),
        )

        # Least squares over the 3 edges of every triangle: D x = e, D is (3T, V).
        n_tri = faces.shape[0]
        rows = np.arange(3 * n_tri)
        heads = np.concatenate([faces[:, b] for _, b in _EDGES])
        tails = np.concatenate([faces[:, a] for a, _ in _EDGES])
        self._difference = sp.csr_matrix(
            (
                np.r_[np.ones(3 * n_tri), -np.ones(3 * n_tri)],
                (np.r_[rows, rows], np.r_[heads, tails]),
            ),
            shape=(3 * n_tri, self.n_vertices),
        )
        normal_matrix = (self._difference.T @ self._difference).tocsc()
        ridge = screening * normal_matrix.diagonal().mean()
        self._solve = spla.factorized(
            (normal_matrix + ridge * sp.identity(self.n_vertices)).tocsc()
        )

    def __call__(
        self, weights: Float[ArrayLike, "*batch K"], batch_size: int = 64
    ) -> Float64[np.ndarray, "*batch V 3"]:
        weights = np.asarray(weights)
        check_real("weights", weights)
        weights = weights.astype(np.float64)
        single = weights.ndim == 1
        weights = np.atleast_2d(weights)
        if weights.ndim != 2 or weights.shape[1] != self.n_blendshapes:
            raise ValueError(
                f"weights: expected shape (K,) or (B, K) with K = {self.n_blendshapes}, "
                f"got {weights.shape}"
            )
        if not np.all(np.isfinite(weights)):
            raise ValueError("weights: contains non-finite values")
        out = np.concatenate(
            [
                self._solve_batch(weights[s : s + batch_size])
                for s in range(0, len(weights), batch_size)
            ]
        )
        return out[0] if single else out

    def _solve_batch(self, weights: np.ndarray) -> np.ndarray:
        edges = np.asarray(
            jax.vmap(_blend_edges, (0,) + (None,) * 5)(
                jnp.asarray(weights, jnp.float32), *self._blend_args
            ),
            np.float64,
        )  # (B, T, 3 coords, 3 edges)
        batch = weights.shape[0]
        targets = np.moveaxis(edges, -1, 1).reshape(batch, -1, 3)  # (B, 3T, 3), edge-major
        linear = self.neutral[:, None, :] + np.einsum("bk,kvc->vbc", weights, self.deltas)
        mismatch = np.moveaxis(targets, 0, 1).reshape(targets.shape[1], -1) - (
            self._difference @ linear.reshape(self.n_vertices, -1)
        )
        correction = self._solve(self._difference.T @ mismatch)
        return np.moveaxis(linear + correction.reshape(self.n_vertices, batch, 3), 1, 0)
