"""RigAnyFace (Ma et al.): a FACS-conditioned DiffusionNet that turns a neutral head into a rig.

Given a neutral head normalised to the unit sphere (``normalise``) and its ``MeshOperators``:

* a **global encoder**, a 2-block DiffusionNet over positions and normals pooled by the
  mass-weighted mean to one vector G_0 (diffusion cannot cross disconnected components —
  eyeballs, teeth, gums — so without it each part sees only itself);
* a **stem** (linear in + ``n_shared`` plain DiffusionNet blocks) computed once per head;
* ``n_conditional`` **conditional diffusion blocks**: a DiffusionNet block whose output y is
  fused with the condition c = [A_i, G_0] (pose vector, global code), replicated over the
  vertices, and refined by a small MLP: y + W_2 relu(W_y y + W_c c + b);
* a linear out to a per-vertex displacement d_i (unit-sphere units, times ``output_scale``).

With ``residual=True`` (beyond the paper: "DT + learned residual") the model is given a base
displacement of every pose (deformation transfer from the ICT head, ``transfer_poses``),
feeds it to the first fusion as a per-vertex, per-pose feature, and returns base + correction.
The output layer starts at zero, so the untrained model returns the base exactly. With
``residual_gate`` = tau > 0 the correction of a (pose, vertex) pair is multiplied by
|b|^2 / (|b|^2 + tau^2), b its base displacement: what the base leaves exactly still stays
exactly still, and the correction acts in full where the base moves by several tau.

All poses of a head go through one call as (V, P, C) features, so diffusion and the spatial
gradients act on all poses in one matrix product (optionally over chunks of ``pose_chunk``
poses, which keeps the activations in a CPU's cache); ``AbstractNetworkMethod.generate`` turns
the predictions into a ``BlendshapeRig`` in the head's own units.

The stem is our reading of the paper's "conditional diffusion blocks": the first blocks do not
depend on the pose, so computing them once per head instead of once per pose gives the same
function class at a fraction of the cost (rig generation is ~P times cheaper there).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Float64, PRNGKeyArray

from ..mesh import MeshOperators
from ._diffusion_net import DiffusionNet, DiffusionNetBlock, per_vertex

N_INPUT_FEATURES = 6
"""Per-vertex input: unit-sphere position (3) and vertex normal (3)."""


def input_features(vertices: Float[Array, "V 3"], operators: MeshOperators) -> Float[Array, "V 6"]:
    """[position, normal] per vertex (normals are the operators' frame normals)."""
    return jnp.concatenate([vertices, operators.frames[:, 2, :]], axis=-1)


class ConditionalBlock(eqx.Module):
    """A DiffusionNet block fused with a per-pose condition vector (replicated over vertices)."""

    block: DiffusionNetBlock
    from_features: eqx.nn.Linear
    from_condition: eqx.nn.Linear
    out: eqx.nn.Linear

    def __init__(self, width: int, condition_size: int, *, method: str, key: PRNGKeyArray):
        k_block, k_f, k_c, k_o = jax.random.split(key, 4)
        self.block = DiffusionNetBlock(width, method=method, key=k_block)
        self.from_features = eqx.nn.Linear(width, width, use_bias=False, key=k_f)
        self.from_condition = eqx.nn.Linear(condition_size, width, key=k_c)
        self.out = eqx.nn.Linear(width, width, key=k_o)

    def __call__(
        self,
        features: Float[Array, "V P C"] | Float[Array, "V C"],
        conditions: Float[Array, "P D"],
        operators: MeshOperators,
    ) -> Float[Array, "V P C"]:
        """P feature sets (one per pose) with their P condition vectors.

        ``features`` may also be one (V, C) set shared by all poses (the first conditional
        block's input): the block then runs once instead of P times, which is the same
        function (it is what broadcasting the input to (V, P, C) would compute)."""
        return self.fuse(self.block(features, operators), conditions, operators)

    def fuse(
        self,
        y: Float[Array, "V P C"] | Float[Array, "V C"],
        conditions: Float[Array, "P D"],
        operators: MeshOperators,
    ) -> Float[Array, "V P C"]:
        """The fusion y + W_2 relu(W_y y + W_c c + b) of the block's output y with each
        condition c (a (V, C) y is shared by all poses)."""
        if y.ndim == 2:
            y = y[:, None, :]
        condition = jax.vmap(self.from_condition)(conditions)  # (P, C)
        hidden = jax.nn.relu(per_vertex(self.from_features, y) + condition[None])
        return y + per_vertex(self.out, hidden) * operators.vertex_mask[:, None, None]


class RigAnyFace(eqx.Module):
    """The auto-rigger. Call ``model(poses, vertices, operators)`` -> (P, V, 3) displacements.

    Args:
        n_pose_inputs: length of a pose vector A_i (the rig's basis poses; ICT: 53).
        width: channels of the stem and the conditional blocks.
        n_shared: pose-independent DiffusionNet blocks (computed once per head).
        n_conditional: conditional diffusion blocks (computed once per pose).
        global_size: length of G_0; 0 disables the global encoder (the ablation).
        global_width: channels of the global encoder's 2 blocks.
        method: diffusion discretisation, "spectral" (needs eigenpairs) or "implicit".
        stem_method: discretisation of the blocks that run once per head (the global encoder
            and the stem); ``None``: ``method``. ``"implicit"`` with a spectral ``method`` is
            the hybrid: implicit diffusion (eq. (1)) reaches every vertex of a small part (the
            128 eigenpairs give a small disconnected part little more than its constant), at a
            once-per-head cost, while the per-pose blocks keep the cheap spectral products.
        output_scale: the network's raw output is multiplied by this (unit-sphere units),
            so its last layer works at O(1) values.
        residual: predict a correction on top of a given base displacement (call with
            ``base=``); the correction is exactly zero at initialisation.
        residual_gate: tau (unit-sphere units) of the gate |b|^2 / (|b|^2 + tau^2) on the
            correction of each (pose, vertex) pair with base displacement b; 0: no gate. Only
            with ``residual``.
        key: PRNG key (keyword-only).
    """

    encoder: DiffusionNet | None
    first: eqx.nn.Linear
    shared: tuple[DiffusionNetBlock, ...]
    conditional: tuple[ConditionalBlock, ...]
    last: eqx.nn.Linear
    base_in: eqx.nn.Linear | None
    n_pose_inputs: int = eqx.field(static=True)
    global_size: int = eqx.field(static=True)
    output_scale: float = eqx.field(static=True)
    residual: bool = eqx.field(static=True)
    residual_gate: float = eqx.field(static=True, default=0.0)

    def __init__(
        self,
        n_pose_inputs: int,
        *,
        width: int = 64,
        n_shared: int = 2,
        n_conditional: int = 2,
        global_size: int = 32,
        global_width: int = 32,
        method: str = "spectral",
        stem_method: str | None = None,
        output_scale: float = 0.01,
        residual: bool = False,
        residual_gate: float = 0.0,
        key: PRNGKeyArray,
    ):
        for name, value in (("n_pose_inputs", n_pose_inputs), ("width", width)):
            if int(value) < 1:
                raise ValueError(f"{name}: expected a positive size, got {value}")
        if n_conditional < 1:
            raise ValueError(f"n_conditional: expected >= 1, got {n_conditional}")
        if global_size < 0 or n_shared < 0:
            raise ValueError("global_size, n_shared: expected >= 0")
        if not residual_gate >= 0 or (residual_gate > 0 and not residual):
            raise ValueError(
                f"residual_gate: expected 0, or > 0 with residual=True; got {residual_gate} "
                f"(residual={residual})"
            )
        stem_method = method if stem_method is None else stem_method
        k_enc, k_first, k_shared, k_cond, k_last = jax.random.split(key, 5)
        self.encoder = (
            DiffusionNet(
                N_INPUT_FEATURES,
                global_size,
                global_width,
                2,
                method=stem_method,
                outputs="global_mean",
                key=k_enc,
            )
            if global_size
            else None
        )
        self.first = eqx.nn.Linear(N_INPUT_FEATURES, width, key=k_first)
        self.shared = tuple(
            DiffusionNetBlock(width, method=stem_method, key=k)
            for k in jax.random.split(k_shared, n_shared)
        )
        self.conditional = tuple(
            ConditionalBlock(width, n_pose_inputs + global_size, method=method, key=k)
            for k in jax.random.split(k_cond, n_conditional)
        )
        self.last = eqx.nn.Linear(width, 3, key=k_last)
        self.base_in = None
        if residual:
            k_last, k_base = jax.random.split(k_last)
            self.last = eqx.nn.Linear(width, 3, key=k_last)
            self.last = eqx.tree_at(
                lambda m: (m.weight, m.bias),
                self.last,
                (jnp.zeros_like(self.last.weight), jnp.zeros(3, self.last.weight.dtype)),
            )
            self.base_in = eqx.nn.Linear(3, width, use_bias=False, key=k_base)
        self.residual = bool(residual)
        self.residual_gate = float(residual_gate)
        self.n_pose_inputs = int(n_pose_inputs)
        self.global_size = int(global_size)
        self.output_scale = float(output_scale)

    def global_code(
        self, vertices: Float[Array, "V 3"], operators: MeshOperators
    ) -> Float[Array, " G"]:
        """G_0: the mass-weighted mean of the global encoder's output (empty without one)."""
        if self.encoder is None:
            return jnp.zeros((0,), vertices.dtype)
        return self.encoder(input_features(vertices, operators), operators)

    def __call__(
        self,
        poses: Float[ArrayLike, "P A"],
        vertices: Float[ArrayLike, "V 3"],
        operators: MeshOperators,
        *,
        base: Float[ArrayLike, "P V 3"] | None = None,
        pose_chunk: int | None = None,
    ) -> Float[Array, "P V 3"]:
        """Displacements (unit-sphere units) of every vertex for every pose vector.

        ``base``: (P, V, 3) base displacements (unit-sphere units), required by a residual
        model (its output is base + correction) and refused by a plain one.

        ``pose_chunk``: poses per pass through the conditional blocks (``lax.map`` over
        chunks; ``None``: all at once). The same function; on a CPU chunks of ~16 poses keep
        the (V, chunk, C) activations in cache and run about twice as fast as one pass.

        Raises ValueError (before tracing) when a pose vector's length is not
        ``n_pose_inputs``, ``vertices`` does not match the operators, or ``pose_chunk`` < 1.
        """
        if pose_chunk is not None and pose_chunk < 1:
            raise ValueError(f"pose_chunk: expected a positive number of poses, got {pose_chunk}")
        if np.ndim(poses) != 2 or np.shape(poses)[1] != self.n_pose_inputs:
            raise ValueError(
                f"poses: expected shape (P, {self.n_pose_inputs}) (one pose vector per row), "
                f"got {np.shape(poses)}"
            )
        n_vertices = operators.mass.shape[-1]
        if np.shape(vertices) != (n_vertices, 3):
            raise ValueError(
                f"vertices: expected shape ({n_vertices}, 3) to match the operators, "
                f"got {np.shape(vertices)}"
            )
        if self.residual != (base is not None):
            raise ValueError(
                "base: a residual model needs the base displacements (P, V, 3), a plain model "
                f"takes none (residual={self.residual}, base given: {base is not None})"
            )
        if base is not None and np.shape(base) != (np.shape(poses)[0], n_vertices, 3):
            raise ValueError(
                f"base: expected shape ({np.shape(poses)[0]}, {n_vertices}, 3), "
                f"got {np.shape(base)}"
            )
        poses, vertices = jnp.asarray(poses), jnp.asarray(vertices)
        base = None if base is None else jnp.asarray(base)
        mask = operators.vertex_mask[:, None]
        code = self.global_code(vertices, operators)
        x = per_vertex(self.first, input_features(vertices, operators)) * mask
        for block in self.shared:
            x = block(x, operators)
        n_poses = poses.shape[0]
        conditions = jnp.concatenate(
            [poses.astype(x.dtype), jnp.broadcast_to(code, (n_poses, code.shape[0]))], axis=1
        )
        first, *rest = self.conditional
        y = first.block(x, operators)  # shared by all poses until the first fusion

        if base is None:
            base = jnp.zeros((n_poses, 0, 3), x.dtype)  # a placeholder the plain model ignores

        def displacements(args):  # (p, D) conditions, (p, V, 3) base -> (p, V, 3)
            chunk, chunk_base = args
            z = first.fuse(y, chunk, operators)
            if self.base_in is not None:
                scaled = jnp.swapaxes(chunk_base, 0, 1) / self.output_scale  # (V, p, 3)
                z = z + per_vertex(self.base_in, scaled) * mask[:, None]
            for block in rest:
                z = block(z, chunk, operators)
            out = per_vertex(self.last, z) * mask[:, None] * self.output_scale
            out = jnp.swapaxes(out, 0, 1)
            if self.base_in is None:
                return out
            if self.residual_gate > 0:
                squared = jnp.sum(chunk_base**2, axis=-1, keepdims=True)
                out = out * (squared / (squared + self.residual_gate**2))
            return out + chunk_base

        if pose_chunk is None or n_poses <= pose_chunk:
            return displacements((conditions, base))
        n_chunks = -(-n_poses // pose_chunk)
        pad = n_chunks * pose_chunk - n_poses
        padded = jnp.pad(conditions, ((0, pad), (0, 0)))
        padded_base = jnp.pad(base, ((0, pad), (0, 0), (0, 0)))
        out = jax.lax.map(
            displacements,
            (
                padded.reshape(n_chunks, pose_chunk, -1),
                padded_base.reshape(n_chunks, pose_chunk, *base.shape[1:]),
            ),
        )
        return out.reshape(n_chunks * pose_chunk, n_vertices, 3)[:n_poses]


def normalise(
    vertices: Float[ArrayLike, "V 3"],
) -> tuple[Float64[np.ndarray, "V 3"], Float64[np.ndarray, " 3"], float]:
    """Centre and scale a head into the unit sphere, as RigAnyFace evaluates.

    Returns (normalised vertices, centre (3,), scale) with normalised = (v - centre) / scale;
    the centre is the bounding-box centre and the scale the largest distance from it.
    """
    vertices = np.asarray(vertices, np.float64)
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    scale = float(np.linalg.norm(vertices - centre, axis=1).max())
    if not scale > 0:
        raise ValueError("vertices: all positions coincide, cannot normalise the head")
    return (vertices - centre) / scale, centre, scale
