"""A handle rig with no network: local patch-blendshape fits (beyond the paper; the baseline
that CANRig-PBS's ``local_prior`` corrects, here on any mesh with a patch layout).

Every patch fits the basis offsets to the handle displacements its clamped masks see
(``local_pbs_fit``, the masks evaluated at the patch's seed vertex) and the patches blend
through the layout:

    S(d) = S_base + W_layout X(d) S_basis,   X(d)_p = local_pbs_fit(basis[:, h], d, M_p, ridge)

S is linear in the displacements d, zero displacements give the base exactly and a vertex
covered only by patches that every clamped mask misses does not move. Pose A to B:
``direct`` puts d = B[h] - A[h]; ``fit`` minimises ||S(d) - B||^2 over every vertex, a linear
least-squares problem solved matrix-free by LSMR (``lineax``) from the direct displacements;
the answer is the best of {fitted, direct, zero} by the reported error (the mean per-vertex
distance), as ``pose_a_to_b``'s, so a fit is never worse than the direct pass.
Units follow the mesh (ICT: cm).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._threads import blocking_single_threaded_blas
from ._masks import CLAMP, check_handle_parameters, influence_mask
from ._pbs import (
    PatchLayout,
    _check_points,
    _pbs_shape,
    check_basis,
    check_handle_index,
    local_fit_factor,
    local_fit_solve,
)
from ._rig import check_points


class LocalFitRig(eqx.Module):
    """The layout, the basis offsets (B - 1, V, 3) and the fit's ridge (``local_pbs_fit``)."""

    layout: PatchLayout
    basis: Float[Array, "Bm1 V 3"]
    ridge: float = eqx.field(static=True)
    clamp: float = eqx.field(static=True, default=CLAMP)

    def __check_init__(self):
        if not (np.isfinite(self.ridge) and self.ridge > 0):
            raise ValueError(f"ridge: expected a finite value > 0, got {self.ridge}")


def local_fit_rig(
    layout: PatchLayout, basis: Float[ArrayLike, "Bm1 V 3"], ridge: float = 1e-3
) -> LocalFitRig:
    """A ``LocalFitRig``, validated (``basis``: offsets from the neutral, no repeated or
    all-zero shape, the layout's vertex count)."""
    basis = check_basis(basis, layout.n_vertices)
    return LocalFitRig(layout, jnp.asarray(basis, jnp.float32), float(ridge))


def _linear_map(rig: LocalFitRig, handle_index, seed_distance, radius, falloff):
    """d -> W_layout X(d) S_basis (the offset from the base), factors computed once."""
    mask = influence_mask(seed_distance, radius, falloff, rig.clamp)
    handle_basis = rig.basis[:, handle_index]
    factor = local_fit_factor(handle_basis, mask, rig.ridge)
    zero = jnp.zeros(rig.basis.shape[1:], rig.basis.dtype)

    def offset(d):
        weights = local_fit_solve(factor, handle_basis, mask, d)
        return _pbs_shape(rig.layout, zero, rig.basis, weights)

    return offset


def _check_edit(rig: LocalFitRig, handle_index, seed_distance, radius, falloff):
    """(index, distance, radius, falloff) as device arrays (radius and falloff per handle),
    or ValueError naming the argument."""
    index = check_handle_index(handle_index, rig.basis.shape[1])
    n_patches = rig.layout.n_patches
    distance = np.asarray(seed_distance, np.float32)
    if (
        distance.shape != (n_patches, len(index))
        or np.isnan(distance).any()
        or (distance < 0).any()
    ):
        raise ValueError(
            f"seed_distance: expected ({n_patches}, {len(index)}) distances >= 0, got "
            f"{distance.shape}"
        )
    radius, falloff = check_handle_parameters(radius, falloff, len(index))
    return tuple(jnp.asarray(x) for x in (index, distance, radius, falloff))


def local_fit_shape(
    rig: LocalFitRig,
    base: Float[ArrayLike, "V 3"],
    handle_index: Int[ArrayLike, " H"],
    seed_distance: Float[ArrayLike, "P H"],
    displacements: Float[ArrayLike, "*F H 3"],
    radius: float | Float[ArrayLike, " H"],
    falloff: float | Float[ArrayLike, " H"],
) -> Float[Array, "*F V 3"]:
    """S(d) = base + W_layout X(d) S_basis for one edit or a batch of displacements
    (``seed_distance``: geodesic distance from each patch's seed to each handle, cm; inf
    beyond a limit). Validated, then jitted; linear in ``displacements``."""
    base = check_points("base", base, rig.basis.shape[1])
    index, distance, radius, falloff = _check_edit(
        rig, handle_index, seed_distance, radius, falloff
    )
    _check_points("displacements", displacements, len(index), batch=True)
    core = _local_fit_shape
    for _ in range(np.ndim(displacements) - 2):
        core = jax.vmap(core, (None, None, None, None, 0, None, None))
    d = jnp.asarray(displacements, jnp.float32)
    return core(rig, jnp.asarray(base), index, distance, d, radius, falloff)


@jax.jit
def _local_fit_shape(rig, base, handle_index, seed_distance, displacements, radius, falloff):
    return base + _linear_map(rig, handle_index, seed_distance, radius, falloff)(displacements)


def local_fit_a_to_b(
    rig: LocalFitRig,
    a: Float[ArrayLike, "V 3"],
    b: Float[ArrayLike, "V 3"],
    handle_index: Int[ArrayLike, " H"],
    seed_distance: Float[ArrayLike, "P H"],
    radius: float | Float[ArrayLike, " H"],
    falloff: float | Float[ArrayLike, " H"],
    max_steps: int = 0,
) -> tuple[Float[Array, "V 3"], Float[Array, "H 3"]]:
    """Pose A to B with base A: (shape, displacements), validated, then jitted (with one
    BLAS thread: the factors' Cholesky runs in SciPy's OpenBLAS, whose threads fight XLA's).
    ``max_steps`` = 0: the direct displacements B[h] - A[h]; > 0: that many LSMR iterations
    on ||S(d) - B||^2 over every vertex, started from the direct displacements (the normal
    matrices' factors computed once), then the best of fitted, direct and zero displacements
    by the mean per-vertex distance to B. ``seed_distance``: geodesic distance from each
    patch's seed to each handle (cm; inf beyond a limit)."""
    a = check_points("a", a, rig.basis.shape[1])
    b = check_points("b", b, rig.basis.shape[1])
    index, distance, radius, falloff = _check_edit(
        rig, handle_index, seed_distance, radius, falloff
    )
    if not (isinstance(max_steps, int | np.integer) and max_steps >= 0):
        raise ValueError(f"max_steps: expected an integer >= 0, got {max_steps!r}")
    return blocking_single_threaded_blas(
        _local_fit_a_to_b,
        rig,
        jnp.asarray(a),
        jnp.asarray(b),
        index,
        distance,
        radius,
        falloff,
        int(max_steps),
    )


@eqx.filter_jit
def _local_fit_a_to_b(rig, a, b, handle_index, seed_distance, radius, falloff, max_steps):
    direct = b[handle_index] - a[handle_index]
    offset = _linear_map(rig, handle_index, seed_distance, radius, falloff)
    start = a + offset(direct)
    if max_steps == 0:
        return start, direct
    operator = lx.FunctionLinearOperator(offset, jax.ShapeDtypeStruct(direct.shape, direct.dtype))
    solver = lx.LSMR(rtol=0.0, atol=0.0, max_steps=max_steps)
    step = lx.linear_solve(operator, b - start, solver, throw=False).value
    fitted = a + offset(direct + step)
    # the best of fitted, direct and zero displacements by the reported error (the mean
    # per-vertex distance; LSMR lowers the sum of squares, not that mean)
    candidates = (
        (fitted, direct + step),
        (start, direct),
        (a, jnp.zeros_like(direct)),
    )
    errors = jnp.stack([jnp.mean(jnp.linalg.norm(s - b, axis=-1)) for s, _ in candidates])
    errors = jnp.where(jnp.isfinite(errors), errors, jnp.inf)
    best = jnp.argmin(errors)
    return jax.tree.map(lambda *x: jnp.stack(x)[best], *candidates)
