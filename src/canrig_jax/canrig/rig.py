"""A trained CANRig bound to one mesh: the queries of S_0 and the edge graph computed once,
handles placed (geodesic distances) once per handle set, then any number of edits with new
displacements, radii, falloffs, base shapes and beta, without recompiling.

    rig = NeuralRig(model, neutral, faces)
    handles = rig.handles([120, 5532, 4200])                # Dijkstra, once per placement
    shape = rig(handles, displacements, radius=2.0, falloff=3.0)          # from the neutral
    shape = rig(handles, displacements, radius=1.0, falloff=3.0, base=previous, beta=0.0)

Every argument is validated in plain Python before the jitted forward pass. By default the
forward pass is block-sparse (``blocks.py``: each block of ~48 vertices attends only to the
handles that influence it, exact); ``dense=True`` runs the dense (V x H) attention instead.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .blocks import block_distance, blocked_deform, influence_reach, vertex_blocks
from .masks import check_handle_parameters, edge_graph, influence_mask, weighted_geodesic_distance
from .model import CANRig


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


@eqx.filter_jit
def deform(
    model: CANRig,
    queries: Float[Array, "heads V d"],
    canonical: Float[Array, "V 3"],
    base: Float[Array, "V 3"],
    handle_index: Int[Array, " H"],
    distance: Float[Array, "V H"],
    displacements: Float[Array, "H 3"],
    radius: Float[Array, " H"],
    falloff: Float[Array, " H"],
    beta: Float[Array, ""] | None = None,
) -> Float[Array, "V 3"]:
    """The jitted dense forward pass on every vertex (no validation; use ``NeuralRig``)."""
    mask = influence_mask(distance, radius, falloff, model.clamp)
    return model(
        queries,
        base,
        canonical[handle_index],
        base[handle_index],
        displacements,
        mask,
        beta,
    )


class NeuralRig:
    """A CANRig model on a mesh with its cached queries (see the module docstring)."""

    def __init__(
        self,
        model: CANRig,
        canonical: Float[ArrayLike, "V 3"],
        faces: Int[ArrayLike, "F 3"],
        *,
        edge_factor: np.ndarray | None = None,
        block_size: int = 48,
    ):
        canonical = np.asarray(canonical, np.float32)
        self.model = model
        self.graph = edge_graph(canonical, np.asarray(faces), edge_factor)
        self.canonical = jnp.asarray(canonical)
        self.faces = np.asarray(faces)
        self.queries = eqx.filter_jit(type(model).encode_queries)(model, self.canonical)
        blocks = vertex_blocks(canonical, block_size)
        flat = blocks.ravel()
        position = np.zeros(len(canonical), np.int32)
        position[flat[flat >= 0]] = np.flatnonzero(flat >= 0)
        self.blocks = jnp.asarray(blocks)
        self.block_position = jnp.asarray(position)
        # queries per block (B, heads, S, d); padding slots get zero queries, mask 0
        padded = jnp.concatenate([self.queries, jnp.zeros_like(self.queries[:, :1])], axis=1)
        self.block_queries = jnp.moveaxis(padded[:, self.blocks], 0, 1)

    @property
    def n_vertices(self) -> int:
        return int(self.canonical.shape[0])

    def handles(self, index: ArrayLike, *, limit: float = np.inf) -> Handles:
        """Place handles at vertex ``index`` (H,): computes their geodesic distances."""
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
        distance = np.ascontiguousarray(
            weighted_geodesic_distance(self.graph, index, limit=limit).T
        )
        nearest = block_distance(np.asarray(self.blocks), distance)
        return Handles(index.astype(np.int32), jnp.asarray(distance), nearest)

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
        """The shape for ``displacements`` at the handles (relative to ``base``, default the
        neutral); radius and falloff per handle or shared; ``beta`` for the shape-preserving
        model (default 0)."""
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
        displacements = np.asarray(displacements, np.float32)
        if displacements.shape != (h, 3):
            raise ValueError(f"displacements: expected shape ({h}, 3), got {displacements.shape}")
        if not np.all(np.isfinite(displacements)):
            raise ValueError("displacements: contains non-finite values (NaN or inf)")
        radius, falloff = check_handle_parameters(radius, falloff, h)
        if base is None:
            base = self.canonical
        else:
            base = np.asarray(base, np.float32)
            if base.shape != (self.n_vertices, 3):
                raise ValueError(
                    f"base: expected shape ({self.n_vertices}, 3) (the mesh's vertex count), "
                    f"got {base.shape}"
                )
            if not np.all(np.isfinite(base)):
                raise ValueError("base: contains non-finite values")
        if beta is not None:
            if not np.isfinite(beta):
                raise ValueError(f"beta: expected a finite number, got {beta}")
            beta = jnp.asarray(beta, jnp.float32)
        args = (
            self.canonical,
            jnp.asarray(base),
            jnp.asarray(handles.index),
            handles.distance,
            jnp.asarray(displacements),
            jnp.asarray(radius),
            jnp.asarray(falloff),
            beta,
        )
        if dense:
            return deform(self.model, self.queries, *args)
        reach = influence_reach(radius, falloff, self.model.clamp)
        within = handles.block_distance <= reach[None, :]  # (B, H)
        most = max(int(within.sum(axis=1).max()), 1)
        width = min(1 << (most - 1).bit_length(), h)  # next power of two: few compilations
        return blocked_deform(
            self.model,
            self.block_queries,
            self.blocks,
            self.block_position,
            jnp.asarray(within, jnp.float32),
            *args,
            width,
        )
