"""A trained CANRig bound to one mesh: the queries of S_0 and the edge graph computed once,
handles placed (geodesic distances) once per handle set, then any number of edits with new
displacements, radii, falloffs, base shapes and beta, without recompiling.

    rig = NeuralRig(model, neutral, faces)
    handles = rig.handles([120, 5532, 4200])                # Dijkstra, once per placement
    shape = rig(handles, displacements, radius=2.0, falloff=3.0)          # from the neutral
    shape = rig(handles, displacements, radius=1.0, falloff=3.0, base=previous, beta=0.0)

Every per-call input is bundled in one pytree, ``HandleEdit`` (``rig.edit(...)`` validates it
in plain Python), and the pure, jitted ``deform(model, queries, canonical, edit, layout)`` is
the one forward pass: a solver differentiates it with respect to ``edit.displacements`` alone,
and ``jax.vmap`` batches it over edits. By default the attention is block-sparse
(``_layout.py``: each block of ~48 vertices attends only to the handles that reach it, exact);
``dense=True`` uses the dense (V x H) layout instead.

The model may also be a ``LocalFitRig`` (``_local_fit.py``: no network, local linear fits of
a data-driven basis): the same handles, edits and workflows, its own forward pass.

Distances run along the mesh's edges, so a handle on the skin never reaches a part that is a
separate piece of mesh (teeth, gums, eyelashes on a whole head): ``bridge=True`` measures
them along ``mesh.bridged_edge_graph`` instead, where every vertex of such a part is one step
(its 3D distance) from its nearest vertex of the largest piece.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._checks import check_points
from .._threads import blocking_single_threaded_blas
from ..mesh import bridged_edge_graph
from ._layout import (
    DENSE,
    BlockLayout,
    Layout,
    block_distance,
    block_layout,
    influence_reach,
    vertex_blocks,
)
from ._local_fit import LocalFitRig, local_fit_deform
from ._masks import check_handle_parameters, edge_graph, influence_mask, weighted_geodesic_distance
from ._model import AbstractCANRig, Trace


@dataclasses.dataclass(frozen=True)
class Handles:
    """Handle vertices, the (V, H) weighted geodesic distance of every vertex to them (kept on
    the device, so repeated edits do not copy it) and the (B, H) distance of each handle to
    the nearest vertex of each of the rig's vertex blocks (on the host)."""

    index: np.ndarray
    distance: Array
    block_distance: np.ndarray

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
        beta: () logit of the extra attention column (shape-preserving model only).
    """

    index: Int[Array, " H"]
    distance: Float[Array, "V H"]
    displacements: Float[Array, "H 3"]
    radius: Float[Array, " H"]
    falloff: Float[Array, " H"]
    base: Float[Array, "V 3"]
    beta: Float[Array, ""]

    def with_displacements(self, displacements: Float[Array, "H 3"]) -> HandleEdit:
        return eqx.tree_at(lambda e: e.displacements, self, displacements)

    def with_base(self, base: Float[Array, "V 3"]) -> HandleEdit:
        return eqx.tree_at(lambda e: e.base, self, base)


def edit_mask(edit: HandleEdit, clamp: float, layout: Layout = DENSE) -> Float[Array, "..."]:
    """The clamped influence masks of ``edit`` in the layout's local form."""
    return jax.tree.map(
        lambda d, r, f: influence_mask(d, r, f, clamp),
        layout.distance(edit.distance),
        layout.per_handle(edit.radius),
        layout.per_handle(edit.falloff),
    )


def trace_edit(
    model: AbstractCANRig,
    queries: Float[Array, "heads V d"],
    canonical: Float[Array, "V 3"],
    edit: HandleEdit,
    layout: Layout = DENSE,
    local_queries: Float[Array, "..."] | None = None,
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


@eqx.filter_jit
def deform(
    model: AbstractCANRig,
    queries: Float[Array, "heads V d"],
    canonical: Float[Array, "V 3"],
    edit: HandleEdit,
    layout: Layout = DENSE,
    local_queries: Float[Array, "..."] | None = None,
) -> Float[Array, "V 3"]:
    """The shape of ``edit``: the one jitted forward pass (no validation; build ``edit``
    with ``NeuralRig.edit``). ``layout`` (``NeuralRig.layout``) only changes where the
    attention runs, not the result; ``local_queries`` may cache
    ``layout.vertices(queries, axis=-2)``. Batch over edits with ``jax.vmap``. A
    ``LocalFitRig`` (no network) has no queries and no layout: its own pass."""
    if isinstance(model, LocalFitRig):
        return local_fit_deform(model, edit)
    return trace_edit(model, queries, canonical, edit, layout, local_queries).shape


def call_blas_safe(model, fn, *args):
    """``fn(*args)``, with one BLAS thread when ``model`` is a ``LocalFitRig``: its forward
    pass factors every patch's normal matrix in LAPACK, whose threads fight XLA's
    (``canrig_jax._threads``); a network's pass runs none."""
    if isinstance(model, LocalFitRig):
        return blocking_single_threaded_blas(fn, *args)
    return fn(*args)


class NeuralRig:
    """A CANRig model (or a ``LocalFitRig``) on a mesh with its cached queries (see the
    module docstring)."""

    def __init__(
        self,
        model: AbstractCANRig,
        canonical: Float[ArrayLike, "V 3"],
        faces: Int[ArrayLike, "F 3"],
        *,
        edge_factor: np.ndarray | None = None,
        block_size: int = 48,
        bridge: bool = False,
    ):
        if not isinstance(model, AbstractCANRig | LocalFitRig):
            raise TypeError(
                f"model: expected a CANRig model or a LocalFitRig, got {type(model).__name__}"
            )
        canonical = np.asarray(canonical, np.float32)
        if isinstance(model, LocalFitRig) and model.layout.n_vertices != len(canonical):
            raise ValueError(
                f"canonical: {len(canonical)} vertices, the LocalFitRig's layout has "
                f"{model.layout.n_vertices}"
            )
        self.model = model
        if bridge:
            # exit edges lead out of the floating parts (teeth, eyelashes): reversed, the paths
            # from a handle on the skin lead into them (distances are measured from handles)
            self.graph = bridged_edge_graph(canonical, np.asarray(faces), edge_factor).T.tocsr()
        else:
            self.graph = edge_graph(canonical, np.asarray(faces), edge_factor)
        self.canonical = jnp.asarray(canonical)
        self.faces = np.asarray(faces)
        blocks = vertex_blocks(canonical, block_size)
        flat = blocks.ravel()
        position = np.zeros(len(canonical), np.int32)
        position[flat[flat >= 0]] = np.flatnonzero(flat >= 0)
        self.blocks = np.where(blocks < 0, len(canonical), blocks).astype(np.int32)
        self.block_position = position
        self._device_blocks = (jnp.asarray(self.blocks), jnp.asarray(position))
        self.queries = self.block_queries = None  # a LocalFitRig attends to nothing
        if isinstance(model, AbstractCANRig):
            self.queries = eqx.filter_jit(type(model).encode_queries)(model, self.canonical)
            # the queries gathered into the blocks once (the layout's first step, cached)
            chosen = jnp.zeros((len(blocks), 1), jnp.int32)
            blocked = BlockLayout(*self._device_blocks, chosen=chosen)
            self.block_queries = blocked.vertices(self.queries, axis=-2)

    @property
    def n_vertices(self) -> int:
        return int(self.canonical.shape[0])

    def handles(self, index: ArrayLike, *, limit: float = np.inf) -> Handles:
        """Place handles at vertex ``index`` (H,), distinct vertices: computes their geodesic
        distances (Dijkstra, once per placement)."""
        index = np.asarray(index)
        if index.ndim != 1 or index.size == 0:
            raise ValueError(
                f"index: expected at least one handle as a 1-D array, got {index.shape}"
            )
        if not np.issubdtype(index.dtype, np.integer):
            raise ValueError(f"index: expected integer vertex indices, got {index.dtype}")
        if index.min() < 0 or index.max() >= self.n_vertices:
            raise ValueError(
                f"index: handle vertices must lie in [0, {self.n_vertices}), "
                f"got {index.min()}..{index.max()}"
            )
        unique, counts = np.unique(index, return_counts=True)
        if len(unique) < len(index):
            raise ValueError(
                f"index: handle vertices must be distinct; repeated: {unique[counts > 1][:10]}"
            )
        distance = np.ascontiguousarray(
            weighted_geodesic_distance(self.graph, index, limit=limit).T
        )
        nearest = block_distance(self.blocks, distance)
        return Handles(index.astype(np.int32), jnp.asarray(distance), nearest)

    def _check_handles(self, handles: Handles) -> int:
        if not isinstance(handles, Handles) or handles.n_handles == 0:
            raise ValueError("handles: expected a non-empty Handles from NeuralRig.handles")
        h = handles.n_handles
        if tuple(handles.distance.shape) != (self.n_vertices, h):
            raise ValueError(
                f"handles: distances of shape {handles.distance.shape} do not fit this mesh "
                f"({self.n_vertices} vertices)"
            )
        if handles.block_distance.shape != (self.blocks.shape[0], h):
            raise ValueError(
                "handles: placed on a rig with other vertex blocks; place them with this rig's "
                "handles()"
            )
        return h

    def check_base(self, base: Float[ArrayLike, "V 3"] | None, name: str = "base") -> Array:
        """``base`` as a checked (V, 3) float32 device array; None: the neutral."""
        if base is None:
            return self.canonical
        return jnp.asarray(check_points(name, base, self.n_vertices))

    def edit(
        self,
        handles: Handles,
        displacements: Float[ArrayLike, "H 3"],
        radius: float | Float[ArrayLike, " H"],
        falloff: float | Float[ArrayLike, " H"],
        *,
        base: Float[ArrayLike, "V 3"] | None = None,
        beta: float | None = None,
    ) -> HandleEdit:
        """A validated ``HandleEdit``: ``displacements`` relative to ``base`` (default the
        neutral); radius (cm) and falloff (1/cm) per handle or shared; ``beta`` for the
        shape-preserving model (default 0)."""
        h = self._check_handles(handles)
        displacements = np.asarray(displacements, np.float32)
        if displacements.shape != (h, 3):
            raise ValueError(f"displacements: expected shape ({h}, 3), got {displacements.shape}")
        if not np.all(np.isfinite(displacements)):
            raise ValueError("displacements: contains non-finite values (NaN or inf)")
        radius, falloff = check_handle_parameters(radius, falloff, h)
        beta = 0.0 if beta is None else beta
        if not np.isfinite(beta):
            raise ValueError(f"beta: expected a finite number, got {beta}")
        return HandleEdit(
            index=jnp.asarray(handles.index),
            distance=handles.distance,
            displacements=jnp.asarray(displacements),
            radius=jnp.asarray(radius),
            falloff=jnp.asarray(falloff),
            base=self.check_base(base),
            beta=jnp.asarray(beta, jnp.float32),
        )

    def layout(
        self,
        handles: Handles,
        radius: float | Float[ArrayLike, " H"],
        falloff: float | Float[ArrayLike, " H"],
        *,
        width: int | None = None,
        multiple: int | None = None,
        parts: tuple[float, ...] | None = None,
    ) -> Layout:
        """The block-sparse layout of these handles at this radius and falloff (host-side:
        which handles reach which vertex block). One layout serves any displacements and base
        shapes, e.g. every frame of a clip. ``width``/``multiple``/``parts``: see
        ``block_layout``. A ``LocalFitRig`` has no attention to lay out: ``DENSE``."""
        h = self._check_handles(handles)
        radius, falloff = check_handle_parameters(radius, falloff, h)
        if isinstance(self.model, LocalFitRig):
            return DENSE  # no attention to lay out
        reach = influence_reach(radius, falloff, self.model.clamp)
        return block_layout(
            *self._device_blocks,
            handles.block_distance,
            reach,
            width=width,
            multiple=multiple,
            parts=parts,
        )

    def deform(self, edit: HandleEdit, layout: Layout = DENSE) -> Float[Array, "V 3"]:
        """``deform`` with this rig's model, queries and neutral (and, for one of its block
        layouts, the queries already gathered into the blocks)."""
        cached = None
        if isinstance(layout, BlockLayout) and layout.blocks is self._device_blocks[0]:
            cached = self.block_queries
        return call_blas_safe(
            self.model, deform, self.model, self.queries, self.canonical, edit, layout, cached
        )

    def __call__(
        self,
        handles: Handles,
        displacements: Float[ArrayLike, "H 3"],
        radius: float | Float[ArrayLike, " H"],
        falloff: float | Float[ArrayLike, " H"],
        *,
        base: Float[ArrayLike, "V 3"] | None = None,
        beta: float | None = None,
        dense: bool = False,
    ) -> Float[Array, "V 3"]:
        """The shape for ``displacements`` at the handles (see ``edit``); block-sparse
        unless ``dense``."""
        edit = self.edit(handles, displacements, radius, falloff, base=base, beta=beta)
        layout = DENSE if dense else self.layout(handles, radius, falloff)
        return self.deform(edit, layout)
