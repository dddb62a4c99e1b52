"""Block-sparse inference: influence masks are local, so each vertex needs only the handles
whose clamped mask on it is non-zero.

The mesh's vertices are split once into compact blocks (recursive median bisection along the
longest axis, equal sizes). Once per handle placement, the distance from each handle to the
nearest vertex of each block is kept (``block_distance``). A clamped mask is exactly 0 beyond
a distance that depends only on the handle's radius and falloff (``influence_reach``), so per
call the host counts the handles within reach of each block without touching the (V, H)
masks, and each block gathers those handles (at most ``width``, a static size: the next power
of two above the largest count, so nothing is ever truncated). Masks and attention are
computed on (block vertices x block handles) instead of (V x H). Handles outside a block's
list have mask 0 on all of its vertices and contribute nothing, so this equals the dense
forward up to float rounding.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .attention import masked_attention_weights
from .masks import influence_mask
from .model import CANRig


def vertex_blocks(vertices: np.ndarray, max_size: int = 48) -> np.ndarray:
    """(B, S) vertex indices in compact blocks of equal size S <= max_size (-1 pads the last
    slots of blocks one shorter). Recursive median bisection along the longest extent."""
    vertices = np.asarray(vertices, np.float64)
    if max_size < 1:
        raise ValueError(f"max_size: expected >= 1, got {max_size}")
    blocks = [np.arange(len(vertices))]
    while max(len(b) for b in blocks) > max_size:
        split = []
        for block in blocks:
            points = vertices[block]
            axis = int(np.argmax(points.max(axis=0) - points.min(axis=0)))
            order = block[np.argsort(points[:, axis], kind="stable")]
            half = (len(order) + 1) // 2
            split += [order[:half], order[half:]]
        blocks = split
    size = max(len(b) for b in blocks)
    out = np.full((len(blocks), size), -1, np.int64)
    for row, block in enumerate(blocks):
        out[row, : len(block)] = block
    return out.astype(np.int32)


def block_distance(blocks: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """(B, H) distance from each handle to the nearest vertex of each block (host, once per
    handle placement); ``distance`` is (V, H), padding slots of ``blocks`` count as infinite."""
    distance = np.asarray(distance, np.float32)
    padded = np.concatenate([distance, np.full((1, distance.shape[1]), np.inf, np.float32)])
    return padded[blocks].min(axis=1)


def influence_reach(radius: np.ndarray, falloff: np.ndarray, clamp: float) -> np.ndarray:
    """(H,) distance beyond which a handle's clamped mask is exactly 0.

    0.5 (1 - tanh(g (d - r))) < clamp  <=>  d > r + atanh(1 - 2 clamp) / g. A relative and
    absolute margin of 1e-3 covers float32 rounding of the mask (a handle kept a little past
    its reach only adds zeros). With clamp 0 no mask is exactly 0 in exact arithmetic, so
    every handle reaches everywhere.
    """
    radius = np.asarray(radius, np.float64)
    if clamp <= 0.0:
        return np.full(radius.shape, np.inf)
    reach = radius + np.arctanh(1.0 - 2.0 * clamp) / np.asarray(falloff, np.float64)
    return reach * (1.0 + 1e-3) + 1e-3


@eqx.filter_jit
def blocked_deform(
    model: CANRig,
    block_queries: Float[Array, "B heads S d"],
    blocks: Int[Array, "B S"],
    position: Int[Array, " V"],
    within: Float[Array, "B H"],
    canonical: Float[Array, "V 3"],
    base: Float[Array, "V 3"],
    handle_index: Int[Array, " H"],
    distance: Float[Array, "V H"],
    displacements: Float[Array, "H 3"],
    radius: Float[Array, " H"],
    falloff: Float[Array, " H"],
    beta: Float[Array, ""] | None,
    width: int,
) -> Float[Array, "V 3"]:
    """The forward pass of ``rig.deform`` with block-sparse attention.

    ``within`` is 1 where a handle is within reach of a block (``block_distance`` <=
    ``influence_reach``), else 0; ``width`` (static) must be >= its largest row sum. Each
    block takes those handles first (``top_k`` on the indicator), then the masks are computed
    on the (block vertices x chosen handles) distances only."""
    _, chosen = jax.lax.top_k(within, width)  # (B, W): every handle within reach first
    padded = jnp.concatenate([distance, jnp.full((1, distance.shape[1]), jnp.inf)])
    sub_distance = padded[blocks[:, :, None], chosen[:, None, :]]  # (B, S, W); padding: inf
    sub_mask = influence_mask(
        sub_distance, radius[chosen][:, None, :], falloff[chosen][:, None, :], model.clamp
    )
    keys = model.encode_keys(canonical[handle_index])  # (heads, H, d)
    values = model.encode_values(displacements, base[handle_index])
    block_keys = jnp.moveaxis(keys[:, chosen], 0, 1)  # (B, heads, W, d)
    block_values = jnp.moveaxis(values[:, chosen], 0, 1)
    scale = 1.0 / jnp.sqrt(jnp.asarray(keys.shape[-1], keys.dtype))
    logits = jnp.matmul(block_queries, jnp.swapaxes(block_keys, -1, -2)) * scale
    weights, normaliser = masked_attention_weights(
        logits, sub_mask[:, None], model.attention_beta(beta)
    )
    attended = jnp.matmul(weights, block_values) / normaliser  # (B, heads, S, e)
    attended = jnp.moveaxis(attended, 1, 2).reshape(-1, model.latent)  # (B*S, latent)
    attended = attended[position]  # back to vertex order
    queries = jnp.moveaxis(block_queries, 1, 2).reshape(-1, model.latent)[position]
    out = base + model.decode(attended, base, queries)
    if model.interpolation_prior:
        moved = model.interpolate(sub_mask, displacements[chosen])  # (B, S, 3)
        out = out + moved.reshape(-1, 3)[position]
    return out
