"""A handle rig (a trained CANRig, a ``LocalFitRig``, a ``PBSRig``) bound to one mesh: what
it prepares for the mesh (a CANRig's queries of S_0) and the edge graph computed once, handles
placed (geodesic distances) once per handle set, then any number of edits with new
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

The model is any member of the handle-rig family (``_handle_rig.py``): the same handles,
edits and workflows, each its own forward pass and fit.

Distances run along the mesh's edges, so a handle on the skin never reaches a part that is a
separate piece of mesh (teeth, gums, eyelashes on a whole head): ``bridge=True`` measures
them along ``mesh.bridged_edge_graph`` instead, where every vertex of such a part is one step
(its 3D distance) from its nearest vertex of the largest piece.
"""

from collections.abc import Callable, Sequence
from typing import TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, ArrayLike, Float, Int, Int32, PyTree, Shaped

from .._checks import check_points, is_concrete
from .._threads import blocking_single_threaded_blas
from ..mesh import bridged_edge_graph
from ._handle_rig import AbstractHandleRig, HandleEdit, Handles
from ._layout import (
    DENSE,
    BlockLayout,
    Layout,
    Local,
    block_distance,
    block_layout,
    vertex_blocks,
)
from ._masks import check_handle_parameters, edge_graph, weighted_geodesic_distance


@eqx.filter_jit
def deform(
    model: AbstractHandleRig,
    queries: PyTree,
    canonical: Float[Array, "V 3"],
    edit: HandleEdit,
    layout: Layout = DENSE,
    local_queries: Local | None = None,
) -> Float[Array, "V 3"]:
    """The shape of ``edit``: the one jitted forward pass of any handle rig (no validation;
    build ``edit`` with ``NeuralRig.edit``). ``queries`` is ``model.prepare(canonical)`` (the
    attention rig's queries; None for rigs without). ``layout`` (``NeuralRig.layout``) only
    changes where the work runs, not the result; ``local_queries`` may cache
    ``layout.vertices(queries, axis=-2)``. Batch over edits with ``jax.vmap``."""
    return model.deform(queries, canonical, edit, layout, local_queries)


T = TypeVar("T")


def call_blas_safe(model: AbstractHandleRig, fn: Callable[..., T], *args) -> T:
    """``fn(*args)``, with one BLAS thread when ``model``'s forward pass runs LAPACK
    (``AbstractHandleRig.lapack_in_forward``: its threads fight XLA's, see
    ``canrig_jax._threads``). Under a trace (the rig inside ``jit``) it only calls ``fn``."""
    tracing = not all(is_concrete(x) for x in jax.tree.leaves(args))
    if model.lapack_in_forward and not tracing:
        return blocking_single_threaded_blas(fn, *args)
    return fn(*args)


class _Host:
    """Host-side data of a ``NeuralRig`` (the edge graph, the vertex blocks): a static field,
    hashed and compared by identity, so the rig passes through ``eqx.filter_jit``."""

    def __init__(
        self,
        graph: sp.csr_matrix,
        faces: Int[np.ndarray, "F 3"],
        blocks: Int32[np.ndarray, "B S"],
        block_position: Int32[np.ndarray, " V"],
    ):
        self.graph = graph
        self.faces = faces
        self.blocks = blocks
        self.block_position = block_position


class NeuralRig(eqx.Module):
    """A handle rig (any ``AbstractHandleRig``: a trained CANRig, a ``LocalFitRig``, a
    ``PBSRig``) on a mesh with what it prepared for that mesh cached (see the module
    docstring). An ``eqx.Module``: it passes through ``eqx.filter_jit`` and ``eqx.filter_vmap``
    (its device arrays are leaves; the edge graph and vertex blocks are static host data).

    Attributes:
        model: the handle rig.
        canonical: (V, 3) the mesh's neutral (cm).
        queries: ``model.prepare(canonical)`` (the attention rig's queries; None otherwise).
        block_queries: ``model.local(queries, blocks)`` (None for rigs with nothing per vertex).
        device_blocks: the vertex blocks (B, S) (padded with V) and each vertex's slot (V,).
    """

    model: AbstractHandleRig
    canonical: Float[Array, "V 3"]
    queries: PyTree
    block_queries: Shaped[Array, "B ..."] | None
    device_blocks: tuple[Int[Array, "B S"], Int[Array, " V"]]
    host: _Host = eqx.field(static=True)

    def __init__(
        self,
        model: AbstractHandleRig,
        canonical: Float[ArrayLike, "V 3"],
        faces: Int[ArrayLike, "F 3"],
        *,
        edge_factor: Float[ArrayLike, " E"] | None = None,
        block_size: int = 48,
        bridge: bool = False,
    ):
        if not isinstance(model, AbstractHandleRig):
            raise TypeError(
                "model: expected a handle rig (canrig_jax.canrig.HANDLE_RIGS, e.g. a trained "
                f"CANRig or a LocalFitRig), got {type(model).__name__}"
            )
        canonical = np.asarray(canonical, np.float32)
        model.check_mesh(len(canonical))
        self.model = model
        if bridge:
            # exit edges lead out of the floating parts (teeth, eyelashes): reversed, the paths
            # from a handle on the skin lead into them (distances are measured from handles)
            graph = bridged_edge_graph(canonical, np.asarray(faces), edge_factor).T.tocsr()
        else:
            graph = edge_graph(canonical, np.asarray(faces), edge_factor)
        self.canonical = jnp.asarray(canonical)
        blocks = vertex_blocks(canonical, block_size)
        flat = blocks.ravel()
        position = np.zeros(len(canonical), np.int32)
        position[flat[flat >= 0]] = np.flatnonzero(flat >= 0)
        blocks = np.where(blocks < 0, len(canonical), blocks).astype(np.int32)
        self.host = _Host(
            graph=graph, faces=np.asarray(faces), blocks=blocks, block_position=position
        )
        self.device_blocks = (jnp.asarray(blocks), jnp.asarray(position))
        self.queries = eqx.filter_jit(type(model).prepare)(model, self.canonical)
        # what the rig lays out per vertex block, gathered into the blocks once (cached)
        chosen = jnp.zeros((len(blocks), 1), jnp.int32)
        blocked = BlockLayout(*self.device_blocks, chosen=chosen)
        self.block_queries = model.local(self.queries, blocked)

    @property
    def graph(self) -> sp.csr_matrix:
        """The (V, V) edge graph the handles' geodesic distances run along (SciPy CSR)."""
        return self.host.graph

    @property
    def faces(self) -> Int[np.ndarray, "F 3"]:
        return self.host.faces

    @property
    def blocks(self) -> Int32[np.ndarray, "B S"]:
        """(B, S) the vertex blocks of the block-sparse layout (padded with V)."""
        return self.host.blocks

    @property
    def block_position(self) -> Int32[np.ndarray, " V"]:
        """(V,) each vertex's slot in the flattened (B * S) block order."""
        return self.host.block_position

    @property
    def n_vertices(self) -> int:
        return int(self.canonical.shape[0])

    def handles(
        self, index: Int[ArrayLike, " H"] | Sequence[int], *, limit: float = np.inf
    ) -> Handles:
        """Place handles at vertex ``index`` (H,), distinct vertices: computes their geodesic
        distances (Dijkstra, once per placement), within ``limit`` (cm; farther: inf).

        Returns the placement (a ``Handles``) that the workflows and ``edit`` take: ``index``
        (H,), the handle vertices, and ``n_handles``; ``distance`` (V, H), the weighted
        geodesic distance of every vertex to them (kept on the device, so repeated edits do
        not copy it); ``block_distance`` (B, H), the distance of each handle to the nearest
        vertex of each of the rig's vertex blocks (on the host)."""
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

    def check_base(
        self, base: Float[ArrayLike, "V 3"] | None, name: str = "base"
    ) -> Float[Array, "V 3"]:
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
        ``block_layout``. A rig without attention (``reach`` None) has none: ``DENSE``."""
        h = self._check_handles(handles)
        radius, falloff = check_handle_parameters(radius, falloff, h)
        reach = self.model.reach(radius, falloff)
        if reach is None:
            return DENSE  # nothing to lay out
        return block_layout(
            *self.device_blocks,
            handles.block_distance,
            reach,
            width=width,
            multiple=multiple,
            parts=parts,
        )

    def deform(self, edit: HandleEdit, layout: Layout = DENSE) -> Float[Array, "V 3"]:
        """The shape of ``edit`` (built by ``edit``): the one jitted forward pass that the
        workflows, training, the fits and ``jax.vmap`` share, with this rig's model, queries
        and neutral (and, for one of its block layouts, the queries already gathered into the
        blocks). ``layout`` (from ``layout``) only changes where the work runs, not the result."""
        cached = None
        if isinstance(layout, BlockLayout) and layout.blocks is self.device_blocks[0]:
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
