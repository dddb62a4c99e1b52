"""DiffusionNet (Sharp, Attaiki, Crane & Ovsjanikov 2022) in equinox.

A network of residual blocks, each

    x_diffused = diffusion(x)                                  (learned time per channel)
    x_gradient = spatial gradient features of x_diffused        (learned complex-linear map)
    x_out      = x + MLP([x, x_diffused, x_gradient])           (per-vertex MLP, residual)

between a per-vertex linear layer in (C_in -> width) and out (width -> C_out). Outputs at
vertices, at faces (mean of the corners) or one mass-weighted mean over the mesh.

All geometry comes from a ``MeshOperators`` (``canrig_jax.mesh.mesh_operators``), computed once per
mesh and cached; the layers only consume it. One mesh per call; batch meshes of different
sizes with ``stack_operators`` + ``eqx.filter_vmap`` (padding, see ``MeshOperators``).
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from .._checks import is_concrete
from ..mesh import MeshOperators
from ._diffusion import LearnedDiffusion
from ._features import mass_weighted_mean

OUTPUTS = ("vertices", "faces", "global_mean")


def per_vertex(
    layer: Callable[[Float[Array, " C"]], Float[Array, " D"]], x: Float[Array, "V *N C"]
) -> Float[Array, "V *N D"]:
    """Apply a layer on the last axis of (V, ..., C) features (leading axes flattened)."""
    flat = x.reshape(-1, x.shape[-1])
    out = jax.vmap(layer)(flat)
    return out.reshape(x.shape[:-1] + out.shape[-1:])


class SpatialGradientFeatures(eqx.Module):
    """Features from gradients of each channel in the vertices' tangent frames.

    With g = g_x + i g_y per channel (complex in the tangent plane) and a learned map A over
    channels, the feature is tanh(Re(conj(g) * (A g))) per channel. With rotations
    (default), A = A_re + i A_im is complex-linear, so the feature does not depend on which
    tangent direction a vertex's frame calls x; without, A = A_re acts on both components.
    """

    real: eqx.nn.Linear
    imaginary: eqx.nn.Linear | None
    with_rotations: bool = eqx.field(static=True)

    def __init__(self, width: int, with_rotations: bool = True, *, key: PRNGKeyArray):
        k_re, k_im = jax.random.split(key)
        self.real = eqx.nn.Linear(width, width, use_bias=False, key=k_re)
        self.imaginary = (
            eqx.nn.Linear(width, width, use_bias=False, key=k_im) if with_rotations else None
        )
        self.with_rotations = with_rotations

    def __call__(
        self, features: Float[Array, "V *N C"], operators: MeshOperators
    ) -> Float[Array, "V *N C"]:
        return self.from_gradients(operators.gradient_x(features), operators.gradient_y(features))

    def from_gradients(
        self, grad_x: Float[Array, "V *N C"], grad_y: Float[Array, "V *N C"]
    ) -> Float[Array, "V *N C"]:
        """The features from precomputed gradient components (x, y in the vertex frames)."""
        b_x = per_vertex(self.real, grad_x)
        b_y = per_vertex(self.real, grad_y)
        if self.imaginary is not None:
            b_x = b_x - per_vertex(self.imaginary, grad_y)
            b_y = b_y + per_vertex(self.imaginary, grad_x)
        return jnp.tanh(grad_x * b_x + grad_y * b_y)


class DiffusionNetBlock(eqx.Module):
    """diffusion -> spatial gradient features -> per-vertex MLP, with a residual."""

    diffusion: LearnedDiffusion
    gradient_features: SpatialGradientFeatures
    mlp: eqx.nn.MLP

    def __init__(
        self,
        width: int,
        *,
        method: str = "spectral",
        init_time: float = 0.0,
        mlp_depth: int = 2,
        with_gradient_rotations: bool = True,
        key: PRNGKeyArray,
    ):
        k_grad, k_mlp = jax.random.split(key)
        self.diffusion = LearnedDiffusion(width, method, init_time)
        self.gradient_features = SpatialGradientFeatures(width, with_gradient_rotations, key=k_grad)
        self.mlp = eqx.nn.MLP(3 * width, width, width, mlp_depth, jax.nn.relu, key=k_mlp)

    def __call__(
        self, features: Float[Array, "V *N C"], operators: MeshOperators
    ) -> Float[Array, "V *N C"]:
        """One block on (V, C) features, or (V, N, C): N feature sets on the same mesh
        (e.g. one per pose), diffused and differentiated together."""
        diffused, grad_x, grad_y = self.diffusion.with_gradient(features, operators)
        gradient = self.gradient_features.from_gradients(grad_x, grad_y)
        combined = jnp.concatenate([features, diffused, gradient], axis=-1)
        mask = operators.vertex_mask.reshape((-1,) + (1,) * (features.ndim - 1))
        return features + per_vertex(self.mlp, combined) * mask


class DiffusionNet(eqx.Module):
    """DiffusionNet: linear in, ``n_blocks`` DiffusionNetBlocks, linear out.

    Args:
        in_size: input channels per vertex (e.g. 3 for positions, 16 for HKS).
        out_size: output channels.
        width: channels inside the blocks (DiffusionNet's default 128).
        n_blocks: residual diffusion blocks (default 4).
        method: "spectral" (needs eigenpairs in the operators) or "implicit".
        outputs: "vertices" (V, out), "faces" (F, out) or "global_mean" (out,).
        init_time: initial diffusion time of every channel (squared mesh units).
        mlp_depth: hidden layers of each block's MLP.
        with_gradient_rotations: complex-linear (True) or real gradient features.
        final_activation: applied to the output (default identity).
        key: PRNG key (keyword-only).
    """

    first: eqx.nn.Linear
    blocks: tuple[DiffusionNetBlock, ...]
    last: eqx.nn.Linear
    outputs: str = eqx.field(static=True)
    final_activation: Callable = eqx.field(static=True)

    def __init__(
        self,
        in_size: int,
        out_size: int,
        width: int = 128,
        n_blocks: int = 4,
        *,
        method: str = "spectral",
        outputs: str = "vertices",
        init_time: float = 0.0,
        mlp_depth: int = 2,
        with_gradient_rotations: bool = True,
        final_activation: Callable = lambda x: x,
        key: PRNGKeyArray,
    ):
        if outputs not in OUTPUTS:
            raise ValueError(f"outputs: expected one of {OUTPUTS}, got {outputs!r}")
        for name, value in (("in_size", in_size), ("out_size", out_size), ("width", width)):
            if int(value) < 1:
                raise ValueError(f"{name}: expected a positive size, got {value}")
        if int(n_blocks) < 0:
            raise ValueError(f"n_blocks: expected >= 0, got {n_blocks}")
        keys = jax.random.split(key, n_blocks + 2)
        self.first = eqx.nn.Linear(in_size, width, key=keys[0])
        self.blocks = tuple(
            DiffusionNetBlock(
                width,
                method=method,
                init_time=init_time,
                mlp_depth=mlp_depth,
                with_gradient_rotations=with_gradient_rotations,
                key=k,
            )
            for k in keys[1:-1]
        )
        self.last = eqx.nn.Linear(width, out_size, key=keys[-1])
        self.outputs = outputs
        self.final_activation = final_activation

    def __call__(
        self, features: Float[Array, "V C_in"], operators: MeshOperators
    ) -> Float[Array, "V out"] | Float[Array, "F out"] | Float[Array, " out"]:
        """Outputs for one mesh: (V, out), (F, out) or (out,) as configured.

        Raises ValueError (before tracing) when ``features`` is not (V, in_size) for the
        operators' V, or contains non-finite values.
        """
        shape = np.shape(features)
        n_vertices = operators.mass.shape[0]
        if len(shape) != 2 or shape != (n_vertices, self.first.in_features):
            raise ValueError(
                f"features: expected shape ({n_vertices}, {self.first.in_features}) "
                f"(vertices of the operators, in_size), got {shape}"
            )
        if is_concrete(features) and not np.all(np.isfinite(np.asarray(features))):
            raise ValueError("features: contains non-finite values")
        mask = operators.vertex_mask[:, None]
        x = per_vertex(self.first, features) * mask
        for block in self.blocks:
            x = block(x, operators)
        x = self.final_activation(per_vertex(self.last, x)) * mask
        if self.outputs == "vertices":
            return x
        if self.outputs == "faces":
            return x[operators.faces].mean(axis=1) * operators.face_mask[:, None]
        return mass_weighted_mean(x, operators)
