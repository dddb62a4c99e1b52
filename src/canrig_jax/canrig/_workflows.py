"""What an artist does with CANRig (sections 7.1-7.4), all on the one forward pass ``deform``.

- **Pose A to B, direct** (section 7.1): handles on chosen vertices of A, displacements
  B[h] - A[h], base shape A, one forward pass (``direct_edit``).
- **Pose A to B, fitted** (``fit_displacements``): the displacements that minimise the mesh
  error ||rig(A, d) - B||^2 (optionally weighted by a region, plus ``penalty`` ||d||^2), by
  ``optimistix.least_squares`` (Gauss-Newton or Levenberg-Marquardt, ``lineax.LSMR``
  linear solves) started from the direct displacements. The Jacobian of the rig with
  respect to the displacements is exact and structured (``displacement_jacobian``): the
  attention weights do not depend on the displacements, so per (vertex, handle) it is a
  3 x 3 block sum_k A^k_vh G_v^k U_h^k (+ the prior's weight times I), G the output MLP's
  Jacobian at the vertex, U the value MLP's at the handle; it reaches the solver as a
  ``jax.custom_jvp``. The variables are whitened by the normal matrix J^T W J of the start
  (``normal_matrix``, a Cholesky factor), so each step's linear system is close to the
  identity. The answer is the best of {fitted, direct, zero} by the reported error (the
  mean per-vertex Euclidean error over the region), so a fit is never worse than the direct
  pass nor than the base shape, exactly.
- **Iterative layers** (section 7.4, ``iterative_layers``): each layer's base shape is the
  previous layer's output; with fitting the error is non-increasing exactly.
- **Clip editing** (section 7.2, ``clip_edit``): one frame's handle displacements faded in and
  out over a window by a smoothstep curve, each frame its own base shape; frames outside the
  window are returned untouched (bit-identical).
- **Dialogue replacement** (section 7.2, ``dialogue_replacement``): per frame, handles around
  the mouth move to the target clip's positions, base shape the source frame, ``jax.vmap``
  over frames.

The rig's model may be a trained CANRig or a ``LocalFitRig`` (no network, ``_local_fit.py``):
every workflow runs on either. Units follow the rig (ICT: cm). Inputs are validated in plain
Python before any jit work.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, Int
from scipy.sparse.csgraph import dijkstra

from .._checks import check_points
from .._linalg import cho_solve, cholesky, solve_triangular
from .._threads import blocking_single_threaded_blas
from ._layout import DENSE, Layout
from ._local_fit import LocalFitRig, local_fit_lsmr
from ._model import AbstractCANRig
from ._rig import (
    HandleEdit,
    Handles,
    NeuralRig,
    call_blas_safe,
    deform,
    edit_mask,
    trace_edit,
)

# --------------------------------------------------------------------------- Jacobian


def _value_jacobian(model: AbstractCANRig, displacements, handle_base):
    """(H, heads, e, 3): d values_h / d d_h per handle."""

    def one(d, b):
        return model.encode_values(d[None], b[None])[:, 0]  # (heads, e)

    return jax.vmap(jax.jacfwd(one))(displacements, handle_base)


def _decode_jacobian(model: AbstractCANRig, attended, base, queries):
    """(V, 3, heads, e): d decode_v / d attended_v per vertex (the latent axis is the heads'
    concatenation, ``merge_heads``)."""

    def one(a, b, q):
        return model.decode(a[None], b[None], q[:, None])[0]  # (3,)

    jac = jax.vmap(jax.jacrev(one), in_axes=(0, 0, 1))(attended, base, queries)
    return jac.reshape(*jac.shape[:2], model.n_heads, -1)


def displacement_jacobian(
    model: AbstractCANRig,
    queries: Float[Array, "heads V d"],
    canonical: Float[Array, "V 3"],
    edit: HandleEdit,
    layout: Layout = DENSE,
) -> tuple[Float[Array, "V 3"], Float[Array, "... 3 3"]]:
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
        blocks = 0.0
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
    blocks: Float[Array, "... 3 3"], tangent: Float[Array, "H 3"], layout: Layout = DENSE
) -> Float[Array, "V 3"]:
    """J t for the blocks of ``displacement_jacobian`` (linear in t; JAX transposes it)."""

    def local_product(blocks, local):
        local = local.reshape(*local.shape[:-2], -1, 1)  # (.., W*3, 1)
        flat = blocks.reshape(*blocks.shape[:-4], blocks.shape[-4] * 3, -1)  # (.., S*3, W*3)
        return jnp.matmul(flat, local).reshape(*blocks.shape[:-4], -1, 3)

    return layout.scatter(jax.tree.map(local_product, blocks, layout.handles(tangent, axis=0)))


def _differentiable_shape(
    model, queries, canonical, edit: HandleEdit, layout: Layout, frozen_blocks=None
):
    """d -> deform(edit with displacements d), with the structured Jacobian as its JVP; with
    ``frozen_blocks``, that Jacobian (taken at the start) stands in for the exact one."""

    @jax.custom_jvp
    def shape(displacements):
        return deform(model, queries, canonical, edit.with_displacements(displacements), layout)

    @shape.defjvp
    def shape_jvp(primals, tangents):
        (displacements,), (tangent,) = primals, tangents
        moved = edit.with_displacements(displacements)
        if frozen_blocks is None:
            out, blocks = displacement_jacobian(model, queries, canonical, moved, layout)
        else:
            out, blocks = deform(model, queries, canonical, moved, layout), frozen_blocks
        return out, apply_jacobian(blocks, tangent, layout)

    return shape


# --------------------------------------------------------------------------- fitting


def normal_matrix(
    blocks: Float[Array, "... 3 3"],
    vertex_weight: Float[Array, " V"],
    n_handles: int,
    layout: Layout = DENSE,
) -> Float[Array, "3H 3H"]:
    """J^T W J for the blocks of ``displacement_jacobian`` (W = diag(``vertex_weight``)),
    (3H, 3H) in handle-major order: per block one batched (W*3 x S*3) @ (S*3 x W*3) product,
    summed over the blocks listing each pair of handles (``Layout.sum_handle_pairs``)."""

    def local_normal(blocks, weight):
        weighted = blocks * weight[..., :, None, None, None]
        return jnp.einsum("...siwj,...sixl->...wxjl", weighted, blocks)

    local = jax.tree.map(local_normal, blocks, layout.vertices(vertex_weight, axis=0))
    pairs = layout.sum_handle_pairs(local, n_handles)  # (H, H, 3, 3)
    return jnp.swapaxes(pairs, 1, 2).reshape(3 * n_handles, 3 * n_handles)


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Settings of ``fit_displacements``.

    The variables are whitened by the normal matrix of the start (z = L^T d, L L^T =
    J^T W J + (penalty + eps) I), so with the start's Jacobian (``exact_jacobian=False``)
    the linearised problem is the identity and one LSMR iteration (``lsmr_steps``) solves
    each step's linear system. ``damped=False`` takes Gauss-Newton steps (the default:
    measured on real poses it is as accurate as Levenberg-Marquardt and faster, but
    undamped steps with the start's Jacobian can overshoot after a few steps, so
    ``max_steps`` stays small: a solve's first step only evaluates the start, 3 steps
    are 2 updates, the first in closed form); ``damped=True`` takes Levenberg-Marquardt
    steps (a trust region that only accepts steps lowering the true objective).
    ``rtol``/``atol`` stop the solve on a small change of the whitened displacements;
    ``penalty`` weighs ||d||^2 (cm^2 per cm^2 of mesh error); ``exact_jacobian=True``
    recomputes the Jacobian at every step (slower, a little more accurate). Whatever the
    settings, the answer is never worse than the direct displacements or zero
    displacements (``fit_displacements`` keeps the best). A ``LocalFitRig`` is linear in d:
    its fit is ``max_steps`` LSMR iterations and ``penalty``; the other settings do not
    apply."""

    max_steps: int = 3
    rtol: float = 1e-3
    atol: float = 1e-4
    lsmr_steps: int = 1
    penalty: float = 0.0
    exact_jacobian: bool = False
    damped: bool = False

    def __post_init__(self):
        if int(self.max_steps) < 1 or int(self.lsmr_steps) < 1:
            raise ValueError(
                f"max_steps, lsmr_steps: expected >= 1, got {self.max_steps}, {self.lsmr_steps}"
            )
        for name in ("rtol", "atol"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: expected > 0, got {getattr(self, name)}")
        if not (np.isfinite(self.penalty) and self.penalty >= 0):
            raise ValueError(f"penalty: expected a finite value >= 0, got {self.penalty}")


class FitSolution(eqx.Module):
    """Result of ``fit_displacements``.

    Attributes:
        displacements: (H, 3) the chosen displacements (cm); never NaN.
        shape: (V, 3) the rig's shape with them.
        error: () mean per-vertex Euclidean error to the target over the region (cm).
        direct_error: () the same for the starting (direct) displacements.
        base_error: () the same for zero displacements (the base shape itself).
        chosen: 0 fitted, 1 direct (start), 2 zero: the lowest error, ties to the lower code.
        result: the solver's ``optimistix.RESULTS`` (successful or why not).
        steps: the solver's number of steps.
    """

    displacements: Float[Array, "H 3"]
    shape: Float[Array, "V 3"]
    error: Float[Array, ""]
    direct_error: Float[Array, ""]
    base_error: Float[Array, ""]
    chosen: Int[Array, ""]
    result: optx.RESULTS
    steps: Int[Array, ""]


def region_error(
    shape: Float[Array, "V 3"], target: Float[Array, "V 3"], region: Float[Array, " V"]
) -> Float[Array, ""]:
    """Mean per-vertex Euclidean distance, weighted by ``region`` (cm)."""
    distance = jnp.linalg.norm(shape - target, axis=-1)
    return jnp.sum(distance * region) / jnp.maximum(jnp.sum(region), 1e-12)


@eqx.filter_jit
def fit_displacements(
    model: AbstractCANRig | LocalFitRig,
    queries: Float[Array, "heads V d"],
    canonical: Float[Array, "V 3"],
    edit: HandleEdit,
    target: Float[Array, "V 3"],
    region: Float[Array, " V"],
    layout: Layout = DENSE,
    options: FitOptions = FitOptions(),
) -> FitSolution:
    """The handle displacements whose shape best matches ``target``: minimises
    sum_v region_v ||deform(edit with d)_v - target_v||^2 + penalty ||d||^2 over d with
    ``optimistix.least_squares`` (Gauss-Newton or Levenberg-Marquardt, ``lineax.LSMR``
    steps, see ``FitOptions``), started from ``edit.displacements``; undamped with the
    start's Jacobian, the first step is taken in closed form from the trace's residual. Use a
    ``PartsLayout`` (``FIT_PARTS``) for speed. Pure and jit/vmap-able; validate with
    ``NeuralRig.edit``. For a ``LocalFitRig`` (linear in d) the solve is ``max_steps`` LSMR
    iterations on the same objective (``local_fit_lsmr``; queries and layout unused).
    Its Cholesky runs in SciPy's OpenBLAS: call it inside
    ``canrig_jax._threads.single_threaded_blas()`` (as ``pose_a_to_b`` does) or it may be
    several times slower next to XLA's threads."""
    if isinstance(model, LocalFitRig):
        fitted, *rest, linear_result, steps = local_fit_lsmr(
            model, edit, target, region, options.penalty, options.max_steps
        )
        result = optx.RESULTS.promote(linear_result)
    else:
        fitted, *rest, result, steps = _gauss_newton(
            model, queries, canonical, edit, target, region, layout, options
        )
    return _best_of(edit, target, region, fitted, *rest, result, steps)


def _gauss_newton(model, queries, canonical, edit, target, region, layout, options):
    """The network's solve (see ``fit_displacements``): (fitted displacements, their shape,
    the direct shape, the solver's result, its steps)."""
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
    return value, solution.state.aux, direct_shape, solution.result, steps


def _best_of(edit, target, region, fitted, fitted_shape, direct_shape, result, steps):
    """The ``FitSolution`` of the best of {fitted, direct, zero} displacements by the
    reported error; a non-finite fit falls back to the direct displacements."""
    start = edit.displacements
    finite = jnp.all(jnp.isfinite(fitted)) & jnp.all(jnp.isfinite(fitted_shape))
    fitted = jnp.where(finite, fitted, start)
    # the candidates' shapes: the fitted one from the solver, the direct one the start's
    # pass, and zero displacements reproduce the base exactly (zero-preserving MLPs; a
    # LocalFitRig is linear in d)
    fitted_shape = jnp.where(finite, fitted_shape, direct_shape)
    candidates = jnp.stack([fitted, start, jnp.zeros_like(start)])
    shapes = jnp.stack([fitted_shape, direct_shape, edit.base])
    errors = jax.vmap(region_error, (0, None, None))(shapes, target, region)
    errors = jnp.where(jnp.isfinite(errors), errors, jnp.inf)
    chosen = jnp.argmin(errors)
    return FitSolution(
        displacements=candidates[chosen],
        shape=shapes[chosen],
        error=errors[chosen],
        direct_error=errors[1],
        base_error=errors[2],
        chosen=chosen,
        result=result,
        steps=steps,
    )


# --------------------------------------------------------------------------- checks


def _check_region(rig: NeuralRig, region, name: str = "region") -> Array:
    if region is None:
        return jnp.ones(rig.n_vertices, jnp.float32)
    region = np.asarray(region)
    if region.shape != (rig.n_vertices,):
        raise ValueError(f"{name}: expected shape ({rig.n_vertices},), got {region.shape}")
    region = region.astype(np.float32)  # bool masks become 0/1 weights
    if not np.all(np.isfinite(region)) or region.min() < 0:
        raise ValueError(f"{name}: expected finite weights >= 0")
    if not region.sum() > 0:
        raise ValueError(f"{name}: selects no vertex (all weights are 0)")
    return jnp.asarray(region)


def _check_clip(rig: NeuralRig, clip, name: str) -> np.ndarray:
    return check_points(name, clip, rig.n_vertices, frames=True)


def direct_displacements(
    source: Float[ArrayLike, "V 3"], target: Float[ArrayLike, "V 3"], handles: Handles
) -> np.ndarray:
    """(H, 3) target[h] - source[h] at the handle vertices (section 7.1)."""
    index = np.asarray(handles.index)
    return np.asarray(target, np.float32)[index] - np.asarray(source, np.float32)[index]


# --------------------------------------------------------------------------- pose A to B


FIT_WIDTH_MULTIPLE = 8
"""Block layouts of fitted edits round their width up to a multiple of this (not to a power
of two): a tighter layout for the Jacobian at the price of a few more compiled shapes."""

FIT_PARTS = (0.6, 0.3, 0.1)
"""Fitted edits split the blocks, sorted by how many handles reach them, into parts of these
fractions, each with its own width (``PartsLayout``): the Jacobian's cost grows with the
width and its normal matrix's with its square, and one width pads every block to the most
crowded one."""


def pose_a_to_b(
    rig: NeuralRig,
    handles: Handles,
    source: Float[ArrayLike, "V 3"],
    target: Float[ArrayLike, "V 3"],
    radius: float | Float[ArrayLike, " H"],
    falloff: float | Float[ArrayLike, " H"],
    *,
    fit: bool = False,
    region: Float[ArrayLike, " V"] | None = None,
    options: FitOptions = FitOptions(),
    beta: float | None = None,
    dense: bool = False,
) -> FitSolution:
    """Deform pose A (``source``, the base shape) towards pose B (``target``) with handles:
    direct (B[h] - A[h], one forward pass) or, with ``fit``, the displacements that best
    match B over ``region`` (bool or weights (V,), default every vertex). Returns a
    ``FitSolution`` either way (direct: ``chosen`` 1, ``steps`` 0)."""
    source = rig.check_base(source, "source")
    target = rig.check_base(target, "target")
    region = _check_region(rig, region)
    edit = rig.edit(
        handles,
        direct_displacements(source, target, handles),
        radius,
        falloff,
        base=source,
        beta=beta,
    )
    # the fit's Jacobian and normal matrix grow with the layout's width (linearly and
    # quadratically): parts of their own widths, multiples of 8, not one power of two
    if dense:
        layout = DENSE
    elif fit:
        layout = rig.layout(handles, radius, falloff, multiple=FIT_WIDTH_MULTIPLE, parts=FIT_PARTS)
    else:
        layout = rig.layout(handles, radius, falloff)
    if fit:
        # one BLAS thread while the fit's Cholesky runs (see canrig_jax._threads)
        return blocking_single_threaded_blas(
            fit_displacements,
            rig.model,
            rig.queries,
            rig.canonical,
            edit,
            target,
            region,
            layout,
            options,
        )
    return call_blas_safe(rig.model, _direct_solution, rig, edit, target, region, layout)


@eqx.filter_jit
def _direct(model, queries, canonical, edit, target, region, layout):
    shape = deform(model, queries, canonical, edit, layout)
    error = region_error(shape, target, region)
    return shape, error, region_error(edit.base, target, region)


def _direct_solution(rig, edit, target, region, layout) -> FitSolution:
    shape, error, base_error = _direct(
        rig.model, rig.queries, rig.canonical, edit, target, region, layout
    )
    return FitSolution(
        displacements=edit.displacements,
        shape=shape,
        error=error,
        direct_error=error,
        base_error=base_error,
        chosen=jnp.asarray(1),
        result=optx.RESULTS.successful,
        steps=jnp.asarray(0),
    )


# --------------------------------------------------------------------------- layers


@dataclasses.dataclass(frozen=True)
class LayerResult:
    """``iterative_layers``: per layer, its solution (shape, error, displacements)."""

    solutions: tuple[FitSolution, ...]

    @property
    def errors(self) -> np.ndarray:
        return np.array([float(s.error) for s in self.solutions])

    @property
    def shape(self) -> Array:
        return self.solutions[-1].shape


def iterative_layers(
    rig: NeuralRig,
    source: Float[ArrayLike, "V 3"],
    target: Float[ArrayLike, "V 3"],
    schedule: Sequence[tuple[Handles, float]],
    falloff: float,
    *,
    fit: bool = False,
    region: Float[ArrayLike, " V"] | None = None,
    options: FitOptions = FitOptions(),
) -> LayerResult:
    """Layered edits (section 7.4): layer i places ``schedule[i] = (handles, radius)`` on the
    previous layer's output (the first on ``source``) and moves them towards ``target``.
    With ``fit`` each layer's error is <= the previous one's, exactly (zero displacements
    reproduce the base, and the fit returns the best of fitted, direct and zero)."""
    schedule = list(schedule)
    if not schedule:
        raise ValueError("schedule: expected at least one (handles, radius) layer")
    for i, layer in enumerate(schedule):
        if not (isinstance(layer, tuple) and len(layer) == 2 and isinstance(layer[0], Handles)):
            raise ValueError(f"schedule[{i}]: expected a (Handles, radius) pair, got {layer!r}")
    current = rig.check_base(source, "source")
    solutions = []
    for handles, radius in schedule:
        solution = pose_a_to_b(
            rig,
            handles,
            current,
            target,
            radius,
            falloff,
            fit=fit,
            region=region,
            options=options,
        )
        solutions.append(solution)
        current = solution.shape
    return LayerResult(tuple(solutions))


# --------------------------------------------------------------------------- clips


def smoothstep_fade(n_frames: int, frame: int, half_window: int) -> np.ndarray:
    """(F,) weight of an edit at ``frame`` faded in and out over ``half_window`` frames on
    each side: 1 at the frame, smoothstep 3x^2 - 2x^3 of x = 1 - |f - frame| / (half + 1)
    inside, 0 outside; both ends have zero slope (no velocity jump)."""
    f = np.arange(n_frames, dtype=np.float64)
    x = np.clip(1.0 - np.abs(f - frame) / (half_window + 1.0), 0.0, 1.0)
    return (x * x * (3.0 - 2.0 * x)).astype(np.float32)


@eqx.filter_jit
def _edit_frames(model, queries, canonical, edit, bases, displacements, layout):
    """deform of one edit over frames: each frame its own base and displacements."""

    def one(base, d):
        return deform(model, queries, canonical, edit.with_base(base).with_displacements(d), layout)

    return jax.vmap(one)(bases, displacements)


@dataclasses.dataclass(frozen=True)
class ClipEdit:
    """``clip_edit``: the edited clip (F, V, 3) and the fade weight per frame (F,)."""

    clip: np.ndarray
    fade: np.ndarray
    window: tuple[int, int]


def clip_edit(
    rig: NeuralRig,
    clip: Float[ArrayLike, "F V 3"],
    frame: int,
    handles: Handles,
    displacements: Float[ArrayLike, "H 3"],
    radius: float | Float[ArrayLike, " H"],
    falloff: float | Float[ArrayLike, " H"],
    half_window: int,
    *,
    beta: float | None = None,
) -> ClipEdit:
    """Edit ``clip`` at ``frame`` with ``displacements`` at the handles, faded in and out
    over ``half_window`` frames on each side (``smoothstep_fade``), each frame its own base
    shape (section 7.2). Frames outside the window are the input frames, untouched."""
    clip = _check_clip(rig, clip, "clip")
    n = len(clip)
    if isinstance(frame, bool) or not isinstance(frame, int | np.integer) or not 0 <= frame < n:
        raise ValueError(f"frame: expected an integer frame index in [0, {n}), got {frame!r}")
    if isinstance(half_window, bool) or not isinstance(half_window, int | np.integer):
        raise ValueError(f"half_window: expected an integer >= 0, got {half_window!r}")
    if half_window < 0 or frame - half_window < 0 or frame + half_window >= n:
        raise ValueError(
            f"half_window: the fade window [{frame - half_window}, {frame + half_window}] must "
            f"lie inside the clip's frames [0, {n - 1}]"
        )
    edit = rig.edit(handles, displacements, radius, falloff, base=clip[frame], beta=beta)
    layout = rig.layout(handles, radius, falloff)
    fade = smoothstep_fade(n, frame, half_window)
    lo, hi = frame - half_window, frame + half_window + 1
    scaled = fade[lo:hi, None, None] * np.asarray(edit.displacements)[None]
    edited = call_blas_safe(
        rig.model,
        _edit_frames,
        rig.model,
        rig.queries,
        rig.canonical,
        edit,
        jnp.asarray(clip[lo:hi]),
        jnp.asarray(scaled),
        layout,
    )
    out = clip.copy()
    out[lo:hi] = np.asarray(edited)
    return ClipEdit(out, fade, (lo, hi - 1))


# --------------------------------------------------------------------------- dialogue


@eqx.filter_jit
def _fit_frames(model, queries, canonical, edit, bases, targets, region, layout, options):
    def one(base, target):
        index = edit.index
        start = edit.with_base(base).with_displacements(target[index] - base[index])
        return fit_displacements(model, queries, canonical, start, target, region, layout, options)

    return jax.vmap(one)(bases, targets)


def dialogue_replacement(
    rig: NeuralRig,
    source: Float[ArrayLike, "F V 3"],
    target: Float[ArrayLike, "F V 3"],
    handles: Handles,
    radius: float | Float[ArrayLike, " H"],
    falloff: float | Float[ArrayLike, " H"],
    *,
    fit: bool = False,
    region: Float[ArrayLike, " V"] | None = None,
    options: FitOptions = FitOptions(),
    beta: float | None = None,
) -> np.ndarray:
    """Replace the mouth of ``source`` with that of ``target`` (section 7.2), frame by frame
    (``jax.vmap``): handles (around the mouth and chin) move to the target frame's positions,
    base shape the source frame; with ``fit``, the displacements that best match the target
    over ``region`` (e.g. a mouth mask). Vertices outside every clamped mask keep the source
    frame exactly. Returns (F, V, 3)."""
    source = _check_clip(rig, source, "source")
    target = _check_clip(rig, target, "target")
    if source.shape != target.shape:
        raise ValueError(
            f"target: expected the source's shape {source.shape} (frame by frame), got "
            f"{target.shape}"
        )
    weights = _check_region(rig, region)
    index = np.asarray(handles.index)
    displacements = target[:, index] - source[:, index]
    edit = rig.edit(handles, displacements[0], radius, falloff, base=source[0], beta=beta)
    if fit:
        layout = rig.layout(handles, radius, falloff, multiple=FIT_WIDTH_MULTIPLE, parts=FIT_PARTS)
        solutions = blocking_single_threaded_blas(
            _fit_frames,
            rig.model,
            rig.queries,
            rig.canonical,
            edit,
            jnp.asarray(source),
            jnp.asarray(target),
            weights,
            layout,
            options,
        )
        return np.asarray(solutions.shape)
    layout = rig.layout(handles, radius, falloff)
    out = call_blas_safe(
        rig.model,
        _edit_frames,
        rig.model,
        rig.queries,
        rig.canonical,
        edit,
        jnp.asarray(source),
        jnp.asarray(displacements),
        layout,
    )
    return np.asarray(out)


def interior_vertices(rig: NeuralRig, region: Float[ArrayLike, " V"], margin: float) -> np.ndarray:
    """Vertices of the boolean ``region`` (V,) whose geodesic distance to every vertex
    outside it exceeds ``margin`` (cm): handles there, with ``influence_reach`` <= margin,
    cannot move anything outside the region."""
    region = np.asarray(region, bool)
    if region.shape != (rig.n_vertices,):
        raise ValueError(f"region: expected shape ({rig.n_vertices},), got {region.shape}")
    outside = np.flatnonzero(~region)
    if len(outside) == 0:
        return np.flatnonzero(region)
    if not region.any():
        raise ValueError("region: selects no vertex")
    if not margin >= 0:
        raise ValueError(f"margin: expected >= 0, got {margin}")
    distance = dijkstra(rig.graph, directed=False, indices=outside, min_only=True)
    return np.flatnonzero(region & (distance > margin))


def expression_region(
    rig,
    include: Sequence[str] = ("jaw", "mouth"),
    exclude: Sequence[str] = ("eye", "brow"),
    threshold: float = 0.1,
) -> np.ndarray:
    """(V,) bool: the vertices that some expression whose name starts with one of
    ``include`` moves by more than ``threshold`` (rig units; ICT: 0.1 cm = 1 mm) and that no
    expression starting with one of ``exclude`` moves that much. On ICT the default is the
    mouth region: lips, chin, jaw line and cheeks, without the eyelids."""
    names = tuple(rig.names)
    deltas = np.asarray(rig.deltas)
    moved = np.linalg.norm(deltas, axis=-1) > threshold  # (K, V)

    def any_of(prefixes):
        rows = [i for i, n in enumerate(names) if n.startswith(tuple(prefixes))]
        return moved[rows].any(axis=0) if rows else np.zeros(deltas.shape[1], bool)

    if not any(n.startswith(tuple(include)) for n in names):
        raise ValueError(f"include: no expression of the rig starts with {tuple(include)}")
    return any_of(include) & ~any_of(exclude)


def max_acceleration(clip: Float[ArrayLike, "F V 3"]) -> float:
    """The largest per-vertex second difference ||x_{f+1} - 2 x_f + x_{f-1}|| of a clip
    (units per frame^2); 0 for fewer than 3 frames."""
    clip = np.asarray(clip, np.float64)
    if len(clip) < 3:
        return 0.0
    second = clip[2:] - 2.0 * clip[1:-1] + clip[:-2]
    return float(np.linalg.norm(second, axis=-1).max())
