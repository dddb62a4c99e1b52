"""The attention rig's fit: the exact, structured Jacobian of its forward pass with respect to
the handle displacements, and the whitened Gauss-Newton solve on it (``AbstractCANRig.fit``).

The attention weights do not depend on the displacements, so per (vertex, handle) the
Jacobian is a 3 x 3 block sum_k A^k_vh G_v^k U_h^k (+ the prior's weight times I), G the
output MLP's Jacobian at the vertex, U the value MLP's at the handle; it reaches the solver as
a ``jax.custom_jvp``. The variables are whitened by the normal matrix J^T W J of the start
(``normal_matrix``, a Cholesky factor), so each step's linear system is close to the identity
(``FitOptions``).
"""

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Float

from .._linalg import cho_solve, cholesky, solve_triangular
from ._attention import Trace
from ._handle_rig import FitOptions, FitState, HandleEdit, edit_mask
from ._layout import DENSE, Layout, Local


@runtime_checkable
class AttentionRig(Protocol):
    """What the fit needs of an attention rig (``AbstractCANRig`` is one): its forward pass
    with intermediates, the value and output MLPs and the interpolation prior."""

    @property
    def clamp(self) -> float: ...

    @property
    def n_heads(self) -> int: ...

    @property
    def interpolation_prior(self) -> bool: ...

    def trace(
        self,
        queries: Any,
        base: Any,
        handle_canonical: Any,
        handle_base: Any,
        displacements: Any,
        mask: Any,
        beta: Any = None,
        layout: Any = DENSE,
        local_queries: Any = None,
    ) -> Trace: ...

    def deform(
        self, prepared: Any, canonical: Any, edit: Any, layout: Any = DENSE, local: Any = None
    ) -> Any: ...

    def encode_values(self, displacements: Any, handle_base: Any) -> Any: ...

    def decode(self, attended: Any, base: Any, queries: Any) -> Any: ...

    def interpolation_weights(self, mask: Any) -> Any: ...


def trace_edit(
    model: AttentionRig,
    queries: Float[Array, "heads V d"],
    canonical: Float[Array, "V 3"],
    edit: HandleEdit,
    layout: Layout = DENSE,
    local_queries: Local | None = None,
) -> Trace:
    """``AbstractCANRig.trace`` of ``edit``: the forward pass with its intermediates."""
    return model.trace(
        queries,
        edit.base,
        canonical[edit.index],
        edit.base[edit.index],
        edit.displacements,
        edit_mask(edit, model.clamp, layout),
        edit.beta,
        layout,
        local_queries,
    )


def _value_jacobian(
    model: AttentionRig, displacements: Float[Array, "H 3"], handle_base: Float[Array, "H 3"]
) -> Float[Array, "H heads e 3"]:
    """(H, heads, e, 3): d values_h / d d_h per handle."""

    def one(d, b):
        return model.encode_values(d[None], b[None])[:, 0]  # (heads, e)

    return jax.vmap(jax.jacfwd(one))(displacements, handle_base)


def _decode_jacobian(
    model: AttentionRig,
    attended: Float[Array, "V latent"],
    base: Float[Array, "V 3"],
    queries: Float[Array, "heads V d"],
) -> Float[Array, "V 3 heads e"]:
    """(V, 3, heads, e): d decode_v / d attended_v per vertex (the latent axis is the heads'
    concatenation, ``merge_heads``)."""

    def one(a, b, q):
        return model.decode(a[None], b[None], q[:, None])[0]  # (3,)

    jac = jax.vmap(jax.jacrev(one), in_axes=(0, 0, 1))(attended, base, queries)
    return jac.reshape(*jac.shape[:2], model.n_heads, -1)


def displacement_jacobian(
    model: AttentionRig,
    queries: Float[Array, "heads V d"],
    canonical: Float[Array, "V 3"],
    edit: HandleEdit,
    layout: Layout = DENSE,
) -> tuple[Float[Array, "V 3"], Local]:
    """The shape of ``edit`` and the exact Jacobian of ``deform`` with respect to
    ``edit.displacements``, as 3 x 3 blocks in the layout's local form: (V, 3, H, 3) for the
    dense layout, (B, S, 3, W, 3) for a block layout (block b, slot s, its w-th handle), a
    tuple of those for a ``PartsLayout``:
    blocks[..., s, i, w, j] = d shape[s, i] / d displacements[w, j].

    Only the values depend on d, so the block of vertex v and handle h is
    sum_k A^k_vh G_v^k U_h^k + P_vh I (A the attention of head k, G the output MLP's
    Jacobian, U the value MLP's, P the interpolation prior's weight)."""
    trace = trace_edit(model, queries, canonical, edit, layout)
    value_jac = _value_jacobian(model, edit.displacements, edit.base[edit.index])  # (H,k,e,3)
    decode_jac = _decode_jacobian(model, trace.attended, edit.base, queries)  # (V, 3, k, e)
    mask = edit_mask(edit, model.clamp, layout)  # the trace's (XLA computes it once)

    def local_blocks(decode, value, attention, mask):
        # decode (.., S, 3, k, e), value (.., W, k, e, 3), attention (.., k, S, W); one head
        # at a time: (S*3 x e) @ (e x W*3) products weighted by A^k and accumulated (4x
        # faster on CPU than materialising every head's products before the sum)
        blocks = jnp.zeros((), jnp.result_type(decode, value, attention))
        for head in range(model.n_heads):
            products = jnp.einsum(
                "...sie,...wej->...siwj", decode[..., head, :], value[..., head, :, :]
            )
            blocks = blocks + attention[..., head, :, None, :, None] * products
        if model.interpolation_prior:
            prior = model.interpolation_weights(mask)  # (.., S, W)
            eye = jnp.eye(3, dtype=blocks.dtype)[:, None]
            blocks = blocks + prior[..., :, None, :, None] * eye
        return blocks

    blocks = jax.tree.map(
        local_blocks,
        layout.vertices(decode_jac, axis=0),
        layout.handles(value_jac, axis=0),
        trace.attention,
        mask,
    )
    return trace.shape, blocks


def apply_jacobian(
    blocks: Local, tangent: Float[Array, "H 3"], layout: Layout = DENSE
) -> Float[Array, "V 3"]:
    """J t for the blocks of ``displacement_jacobian`` (linear in t; JAX transposes it)."""

    def local_product(blocks, local):
        local = local.reshape(*local.shape[:-2], -1, 1)  # (.., W*3, 1)
        flat = blocks.reshape(*blocks.shape[:-4], blocks.shape[-4] * 3, -1)  # (.., S*3, W*3)
        return jnp.matmul(flat, local).reshape(*blocks.shape[:-4], -1, 3)

    return layout.scatter(jax.tree.map(local_product, blocks, layout.handles(tangent, axis=0)))


def _differentiable_shape(
    model: AttentionRig,
    queries: Float[Array, "heads V d"],
    canonical: Float[Array, "V 3"],
    edit: HandleEdit,
    layout: Layout,
    frozen_blocks: Local | None = None,
) -> Callable[[Float[Array, "H 3"]], Float[Array, "V 3"]]:
    """d -> deform(edit with displacements d), with the structured Jacobian as its JVP; with
    ``frozen_blocks``, that Jacobian (taken at the start) stands in for the exact one."""

    @jax.custom_jvp
    def shape(displacements):
        return model.deform(queries, canonical, edit.with_displacements(displacements), layout)

    @shape.defjvp
    def shape_jvp(primals, tangents):
        (displacements,), (tangent,) = primals, tangents
        moved = edit.with_displacements(displacements)
        if frozen_blocks is None:
            out, blocks = displacement_jacobian(model, queries, canonical, moved, layout)
        else:
            out, blocks = model.deform(queries, canonical, moved, layout), frozen_blocks
        return out, apply_jacobian(blocks, tangent, layout)

    return shape


# --------------------------------------------------------------------------- fitting


def normal_matrix(
    blocks: Local,
    vertex_weight: Float[Array, " V"],
    n_handles: int,
    layout: Layout = DENSE,
) -> Float[Array, "H3 H3"]:
    """J^T W J for the blocks of ``displacement_jacobian`` (W = diag(``vertex_weight``)),
    (3H, 3H) (``H3`` = 3 ``n_handles``) in handle-major order: per block one batched
    (W*3 x S*3) @ (S*3 x W*3) product, summed over the blocks listing each pair of handles
    (``Layout.sum_handle_pairs``)."""

    def local_normal(blocks, weight):
        weighted = blocks * weight[..., :, None, None, None]
        return jnp.einsum("...siwj,...sixl->...wxjl", weighted, blocks)

    local = jax.tree.map(local_normal, blocks, layout.vertices(vertex_weight, axis=0))
    pairs = layout.sum_handle_pairs(local, n_handles)  # (H, H, 3, 3)
    return jnp.swapaxes(pairs, 1, 2).reshape(3 * n_handles, 3 * n_handles)


def gauss_newton(
    model: AttentionRig,
    queries: Float[Array, "heads V d"],
    canonical: Float[Array, "V 3"],
    edit: HandleEdit,
    target: Float[Array, "V 3"],
    region: Float[Array, " V"],
    layout: Layout,
    options: FitOptions,
) -> FitState:
    """The attention rig's solve (``AbstractCANRig.fit``, see ``FitOptions``), whitened by the
    start's normal matrix; undamped with the start's Jacobian, the first step is taken in
    closed form from the trace's residual."""
    weight = jnp.sqrt(region)[:, None]
    root_penalty = jnp.sqrt(jnp.asarray(options.penalty, target.dtype))
    start = edit.displacements
    n_handles = start.shape[0]
    # whitened variables z = L^T d, L L^T = J^T W J + (penalty + eps) I at the start: the
    # damped normal equations are then close to the identity and LSMR needs one or two
    # iterations per step (eps = 1e-3 x the mean diagonal keeps handles that move nothing
    # finite)
    direct_shape, blocks = displacement_jacobian(model, queries, canonical, edit, layout)
    normal = normal_matrix(blocks, region, n_handles, layout)
    eps = 1e-3 * jnp.mean(jnp.diagonal(normal)) + 1e-12
    # factor D^-1/2 (N + lambda I) D^-1/2 = L_C L_C^T, D its diagonal, with couplings below
    # 1e-12 flushed to 0 (only the preconditioner changes, negligibly): unscaled, the
    # float32 factorisation ran into subnormal numbers on a real checkpoint and took 0.5 s
    # instead of 7 ms. Then L = D^1/2 L_C.
    root = jnp.sqrt(jnp.diagonal(normal) + options.penalty + eps)
    identity = jnp.eye(3 * n_handles, dtype=normal.dtype)
    scaled = (normal + (options.penalty + eps) * identity) / (root[:, None] * root[None, :])
    scaled = jnp.where(jnp.abs(scaled) < 1e-12, 0.0, scaled)
    factor = root[:, None] * cholesky(scaled)
    frozen = None if options.exact_jacobian else blocks
    shape_of = _differentiable_shape(model, queries, canonical, edit, layout, frozen)

    def unwhiten(z):
        d = solve_triangular(factor, z.reshape(-1), transpose=True)
        return d.reshape(n_handles, 3)

    def residual(z, args):
        del args
        displacements = unwhiten(z)
        shape = shape_of(displacements)
        # the shape rides along as aux: optimistix returns the accepted point's, so the
        # fitted shape costs no extra forward pass
        return ((shape - target) * weight, root_penalty * displacements), shape

    # a fixed number of LSMR iterations per step (truncated: tolerances 0)
    linear_solver = lx.LSMR(rtol=0.0, atol=0.0, max_steps=options.lsmr_steps)
    solver_class = optx.LevenbergMarquardt if options.damped else optx.GaussNewton
    solver = solver_class(rtol=options.rtol, atol=options.atol, linear_solver=linear_solver)
    first, max_steps = start, options.max_steps
    if not options.damped and not options.exact_jacobian and max_steps >= 2:
        # optimistix's first step only evaluates the start, whose shape the trace already
        # gave: take that Gauss-Newton step here, d1 = d0 - (L L^T)^-1 (J^T W r0 + penalty d0)
        weighted = (direct_shape - target) * region[:, None]
        gradient = (
            jax.linear_transpose(lambda t: apply_jacobian(blocks, t, layout), start)(weighted)[0]
            + options.penalty * start
        )
        step = cho_solve(factor, gradient.reshape(-1))
        first, max_steps = start - step.reshape(n_handles, 3), max_steps - 1
    z0 = (factor.T @ first.reshape(-1)).reshape(n_handles, 3)
    solution = optx.least_squares(
        residual, solver, z0, has_aux=True, max_steps=max_steps, throw=False
    )
    value = unwhiten(solution.value)
    # the shape at ``solution.value``: the Gauss-Newton state's aux (``solution.aux`` is the
    # previous accepted point's; tested against ``deform``)
    steps = solution.stats["num_steps"] + (options.max_steps - max_steps)
    return FitState(value, solution.state.aux, direct_shape, solution.result, steps)
