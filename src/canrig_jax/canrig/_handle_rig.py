"""The family of handle-driven rigs: what every model that deforms a mesh from handle
displacements has, whatever runs inside it.

A handle rig takes a ``HandleEdit`` (handle vertices, their geodesic distances, displacements,
radius, falloff, base shape, beta) and returns the deformed shape. Every one of them

- is zero-preserving: zero displacements give the base shape exactly;
- is local: a vertex outside every handle's clamped influence mask (``support``) does not
  move at all;
- ``prepare``s what depends on the mesh alone once (the attention rig's queries), then
  ``deform``s any number of edits, pure and jit/vmap-able;
- ``fit``s displacements to a target shape (the solve behind ``fit_displacements``);
- lays its work out over the handles' reach (``reach``: the attention rig's block-sparse
  layout; ``None``: nothing to lay out, the dense pass).

The members (``HANDLE_RIGS`` in ``canrig_jax.canrig``; ``canrig_jax.pbs`` adds its own):
``CANRig`` and ``ShapePreservingCANRig`` (masked cross-attention, ``_model.py``),
``LocalFitRig`` (local patch-blendshape fits, no network) and ``PBSRig`` (a CANRig-PBS network
with its patch basis), both in ``canrig_jax.pbs``. ``NeuralRig`` binds any of them to a mesh,
and every workflow (``pose_a_to_b``, ``iterative_layers``, ``clip_edit``,
``dialogue_replacement``) runs on any of them through these methods alone.
"""

import abc
import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int, PyTree

from ._layout import DENSE, Layout, Local
from ._masks import influence_mask


@dataclasses.dataclass(frozen=True)
class Handles:
    """Handle vertices and their distances (``NeuralRig.handles`` lists the fields)."""

    index: Int[np.ndarray, " H"]
    distance: Float[Array, "V H"]
    block_distance: Float[np.ndarray, "B H"]

    @property
    def n_handles(self) -> int:
        return len(self.index)


class HandleEdit(eqx.Module):
    """Everything one forward pass needs besides the model and the mesh, as one pytree.

    Attributes:
        index: (H,) handle vertices.
        distance: (V, H) geodesic distance of every vertex to each handle (cm; inf: far).
        displacements: (H, 3) handle displacements from the base shape (cm).
        radius: (H,) mask radius per handle (cm).
        falloff: (H,) mask falloff per handle (1/cm).
        base: (V, 3) base shape S_B (cm); the neutral for reconstruction.
        beta: () logit of the extra attention column (shape-preserving models only).
    """

    index: Int[Array, " H"]
    distance: Float[Array, "V H"]
    displacements: Float[Array, "H 3"]
    radius: Float[Array, " H"]
    falloff: Float[Array, " H"]
    base: Float[Array, "V 3"]
    beta: Float[Array, ""]

    def with_displacements(self, displacements: Float[Array, "H 3"]) -> "HandleEdit":
        return eqx.tree_at(lambda e: e.displacements, self, displacements)

    def with_base(self, base: Float[Array, "V 3"]) -> "HandleEdit":
        return eqx.tree_at(lambda e: e.base, self, base)


def edit_mask(edit: HandleEdit, clamp: float, layout: Layout = DENSE) -> Local:
    """The clamped influence masks of ``edit`` in the layout's local form ((V, H) dense)."""
    return jax.tree.map(
        lambda d, r, f: influence_mask(d, r, f, clamp),
        layout.distance(edit.distance),
        layout.per_handle(edit.radius),
        layout.per_handle(edit.falloff),
    )


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Settings of ``fit_displacements``.

    The attention rig's solve whitens the variables by the normal matrix of the start (z =
    L^T d, L L^T = J^T W J + (penalty + eps) I), so with the start's Jacobian
    (``exact_jacobian=False``) the linearised problem is the identity and one LSMR iteration
    (``lsmr_steps``) solves each step's linear system. ``damped=False`` takes Gauss-Newton
    steps (the default: measured on real poses it is as accurate as Levenberg-Marquardt and
    faster, but undamped steps with the start's Jacobian can overshoot after a few steps, so
    ``max_steps`` stays small: a solve's first step only evaluates the start, 3 steps are 2
    updates, the first in closed form); ``damped=True`` takes Levenberg-Marquardt steps (a
    trust region that only accepts steps lowering the true objective). ``rtol``/``atol``
    stop the solve on a small change of the whitened displacements; ``penalty`` weighs
    ||d||^2 (cm^2 per cm^2 of mesh error); ``exact_jacobian=True`` recomputes the Jacobian at
    every step (slower, a little more accurate). Whatever the settings, the answer is never
    worse than the direct displacements or zero displacements (``fit_displacements`` keeps
    the best). A ``LocalFitRig`` is linear in d: its fit is ``max_steps`` LSMR iterations and
    ``penalty``; a ``PBSRig`` takes ``max_steps`` Gauss-Newton steps with its autodiff
    Jacobian; the other settings do not apply to them."""

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


class FitState(eqx.Module):
    """What a handle rig's ``fit`` returns; ``fit_displacements`` keeps the best of
    {fitted, direct, zero} displacements from it.

    Attributes:
        fitted: (H, 3) the solver's displacements (cm).
        fitted_shape: (V, 3) the shape with them.
        direct_shape: (V, 3) the shape with the start (``edit.displacements``).
        result: the solver's ``optimistix.RESULTS``.
        steps: () the solver's number of steps.
    """

    fitted: Float[Array, "H 3"]
    fitted_shape: Float[Array, "V 3"]
    direct_shape: Float[Array, "V 3"]
    result: optx.RESULTS
    steps: Int[Array, ""]


class AbstractHandleRig(eqx.Module):
    """A model that deforms a mesh from handle displacements (module docstring): the
    operations every handle rig has. Concrete rigs are final."""

    clamp: eqx.AbstractVar[float]

    lapack_in_forward: ClassVar[bool] = False
    """Whether the forward pass factors matrices in LAPACK (SciPy's OpenBLAS), whose threads
    fight XLA's: ``NeuralRig`` then runs it with one BLAS thread (``canrig_jax._threads``)."""

    def check_mesh(self, n_vertices: int) -> None:
        """Raise ``ValueError`` (naming ``canonical``) if the rig cannot deform a mesh of
        ``n_vertices`` vertices (a rig with per-vertex data is bound to its mesh)."""
        del n_vertices

    def prepare(self, canonical: Float[Array, "V 3"]) -> PyTree:
        """What depends on the mesh alone (the attention rig's queries), computed once per
        mesh and passed back to ``deform`` and ``fit``; ``None`` when there is nothing."""
        del canonical

    def reach(
        self, radius: Float[np.ndarray, " H"], falloff: Float[np.ndarray, " H"]
    ) -> Float[np.ndarray, " H"] | None:
        """How far (cm) each handle's clamped mask reaches, for the block-sparse layout of its
        work; ``None``: the rig has no attention to lay out (always the dense pass)."""
        del radius, falloff

    def local(self, prepared: PyTree, layout: Layout) -> PyTree:
        """``prepared`` gathered into ``layout``'s local form once, for ``deform``'s ``local``
        (``NeuralRig`` caches it for its vertex blocks); ``None``: the rig has nothing laid out
        per vertex (the default)."""
        del prepared, layout

    def support(self, edit: HandleEdit) -> Bool[Array, " V"]:
        """(V,) the vertices ``edit`` may move: those inside some handle's clamped mask. Every
        other vertex keeps the base shape exactly (the family's locality, tested)."""
        mask = influence_mask(edit.distance, edit.radius, edit.falloff, self.clamp)  # dense
        return jnp.any(mask > 0, axis=-1)

    @abc.abstractmethod
    def deform(
        self,
        prepared: PyTree,
        canonical: Float[Array, "V 3"],
        edit: HandleEdit,
        layout: Layout = DENSE,
        local: Local | None = None,
    ) -> Float[Array, "V 3"]:
        """The shape of ``edit`` (pure, jit/vmap-able). ``layout`` changes where the work
        runs, never the result; ``local`` is ``layout.vertices(prepared, axis=-2)`` when the
        caller cached it."""

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
        """Displacements that lower sum_v region_v ||deform(d)_v - target_v||^2 + penalty
        ||d||^2 from ``edit.displacements``: by default ``options.max_steps`` Gauss-Newton
        steps (``optimistix``) with the Jacobian of ``deform`` by forward-mode autodiff, each
        step's linear system solved by SVD (``lineax.SVD``, robust to handles the region
        ignores): right for a few handles; rigs with structure to exploit override it."""
        weight = jnp.sqrt(region)[:, None]
        root_penalty = jnp.sqrt(jnp.asarray(options.penalty, target.dtype))

        def residual(d, args):
            del args
            shape = self.deform(prepared, canonical, edit.with_displacements(d), layout)
            return ((shape - target) * weight, root_penalty * d), shape

        solver = optx.GaussNewton(rtol=options.rtol, atol=options.atol, linear_solver=lx.SVD())
        start = edit.displacements
        direct = self.deform(prepared, canonical, edit, layout)
        solution = optx.least_squares(
            residual, solver, start, has_aux=True, max_steps=options.max_steps, throw=False
        )
        return FitState(
            fitted=solution.value,
            fitted_shape=solution.state.aux,
            direct_shape=direct,
            result=solution.result,
            steps=solution.stats["num_steps"],
        )
