"""A handle rig with no network: local patch-blendshape fits (beyond the paper; the baseline
that CANRig-PBS's ``local_prior`` corrects, here on any mesh with a patch layout).

Every patch fits the basis offsets to the handle displacements its clamped masks see
(``local_pbs_fit``, the masks evaluated at the patch's seed vertex); the patches blend
through the layout, and each vertex's offset is scaled by a gate g_v of its largest clamped
mask:

    S(d) = S_base + g * W_layout X(d) S_basis,   X(d)_p = local_pbs_fit(basis[:, h], d, M_p, ridge)
    g_v = min(1, 2 max_h M_vh)

so the edit has full strength within every handle's radius (M = 0.5 at the radius), fades
with the mask beyond it and stops where the clamped masks do: a vertex outside every clamped
mask (g_v = 0) does not move, as with CANRig's attention. (Without the gate the patches'
fits would move every vertex of a reached patch, however far from the handles: on Table 4's
200 random handles / 2 cm that is 25 % less error, and the radius would not mean what it
says.) S is linear in the displacements d; zero displacements give the base exactly.

It is a handle model like a trained CANRig: bind it to a mesh with ``NeuralRig(local_rig,
neutral, faces)`` and every workflow runs on it unchanged (``pose_a_to_b`` direct and
fitted, ``iterative_layers``, ``clip_edit``, ``dialogue_replacement``). ``deform`` is one
pass above; ``fit_displacements`` minimises the region-weighted ||S(d) - B||^2 (+ penalty
||d||^2), a linear least-squares problem, by ``FitOptions.max_steps`` LSMR iterations
(``lineax``, matrix-free) from the direct displacements, and keeps the best of fitted,
direct and zero displacements as for the network. Units follow the mesh (ICT: cm).
"""

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, Int, PyTree

from ..canrig import CLAMP, AbstractHandleRig, FitOptions, HandleEdit, influence_mask
from ..canrig._handle_rig import FitState
from ..canrig._layout import DENSE, Layout, Local
from ._basis import PatchLayout, _pbs_shape, check_basis, local_fit_factor, local_fit_solve


class LocalFitRig(AbstractHandleRig):
    """The layout, the basis offsets (B - 1, V, 3) and the fit's ridge (``local_pbs_fit``).
    A handle rig (``canrig.AbstractHandleRig``) bound to its layout's mesh; nothing to
    prepare or lay out; ``fit`` is LSMR on the linear map."""

    layout: PatchLayout
    basis: Float[Array, "Bm1 V 3"]
    ridge: float = eqx.field(static=True)
    clamp: float = eqx.field(static=True, default=CLAMP)

    lapack_in_forward: ClassVar[bool] = True  # every patch's normal matrix is factored

    def __check_init__(self):
        if not (np.isfinite(self.ridge) and self.ridge > 0):
            raise ValueError(f"ridge: expected a finite value > 0, got {self.ridge}")

    def check_mesh(self, n_vertices: int) -> None:
        if self.layout.n_vertices != n_vertices:
            raise ValueError(
                f"canonical: {n_vertices} vertices, the LocalFitRig's layout has "
                f"{self.layout.n_vertices}"
            )

    def deform(
        self,
        prepared: PyTree,
        canonical: Float[Array, "V 3"],
        edit: HandleEdit,
        layout: Layout = DENSE,
        local: Local | None = None,
    ) -> Float[Array, "V 3"]:
        del prepared, canonical, layout, local
        return local_fit_deform(self, edit)

    def fit(
        self,
        prepared: PyTree,
        canonical: Float[Array, "V 3"],
        edit: HandleEdit,
        target: Float[Array, "V 3"],
        region: Float[Array, " V"],
        layout: Layout,
        options: FitOptions,
    ) -> FitState:
        del prepared, canonical, layout
        fitted, shape, start_shape, result, steps = local_fit_lsmr(
            self, edit, target, region, options.penalty, options.max_steps
        )
        return FitState(fitted, shape, start_shape, optx.RESULTS.promote(result), steps)


def local_fit_rig(
    layout: PatchLayout, basis: Float[ArrayLike, "Bm1 V 3"], ridge: float = 1e-3
) -> LocalFitRig:
    """A ``LocalFitRig``, validated (``basis``: offsets from the neutral, no repeated or
    all-zero shape, the layout's vertex count)."""
    basis = check_basis(basis, layout.n_vertices)
    return LocalFitRig(layout=layout, basis=jnp.asarray(basis, jnp.float32), ridge=float(ridge))


def _linear_map(
    rig: LocalFitRig, edit: HandleEdit
) -> Callable[[Float[Array, "H 3"]], Float[Array, "V 3"]]:
    """d -> g * W_layout X(d) S_basis (the offset from the base) for a ``HandleEdit``, its
    factors computed once: the patch masks at the seeds, the gate g at every vertex."""
    masks = influence_mask(edit.distance, edit.radius, edit.falloff, rig.clamp)  # (V, H)
    mask = masks[rig.layout.seeds]  # (P, H), at each patch's seed
    gate = jnp.minimum(1.0, 2.0 * jnp.max(masks, axis=1))
    handle_basis = rig.basis[:, edit.index]
    factors = local_fit_factor(handle_basis, mask, rig.ridge)
    zero = jnp.zeros(rig.basis.shape[1:], rig.basis.dtype)

    def offset(d):
        weights = local_fit_solve(factors, handle_basis, mask, d)
        return gate[:, None] * _pbs_shape(rig.layout, zero, rig.basis, weights)

    return offset


def local_fit_deform(rig: LocalFitRig, edit: HandleEdit) -> Float[Array, "V 3"]:
    """The shape of a ``HandleEdit`` (``NeuralRig.edit``): base + g * W_layout X(d) S_basis.
    Pure and jit/vmap-able (``LocalFitRig.deform``)."""
    return edit.base + _linear_map(rig, edit)(edit.displacements)


def local_fit_lsmr(
    rig: LocalFitRig,
    edit: HandleEdit,
    target: Float[Array, "V 3"],
    region: Float[Array, " V"],
    penalty: float,
    steps: int,
) -> tuple[
    Float[Array, "H 3"], Float[Array, "V 3"], Float[Array, "V 3"], lx.RESULTS, Int[Array, ""]
]:
    """``steps`` LSMR iterations on sum_v region_v ||S(d)_v - target_v||^2 + penalty ||d||^2
    from ``edit.displacements``: (fitted displacements, their shape, the start's shape, the
    lineax result, the iterations run). ``fit_displacements`` picks the best candidate."""
    offset = _linear_map(rig, edit)
    start = edit.displacements
    start_shape = edit.base + offset(start)
    weight = jnp.sqrt(region)[:, None]
    root_penalty = jnp.sqrt(jnp.asarray(penalty, start.dtype))

    def operator(step):
        return weight * offset(step), root_penalty * step

    linear = lx.FunctionLinearOperator(operator, jax.ShapeDtypeStruct(start.shape, start.dtype))
    rhs = (weight * (target - start_shape), -root_penalty * start)
    solver = lx.LSMR(rtol=0.0, atol=0.0, max_steps=steps)
    solution = lx.linear_solve(linear, rhs, solver, throw=False)
    fitted = start + solution.value
    return (
        fitted,
        edit.base + offset(fitted),
        start_shape,
        solution.result,
        solution.stats["num_steps"],
    )
