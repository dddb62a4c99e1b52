"""Block-sparse inference: influence masks are local, so each vertex needs only the handles
whose clamped mask on it is non-zero.

The mesh's vertices are split once into compact blocks (recursive median bisection along the
longest axis, equal sizes). Per call, each block gathers the handles that influence any of
its vertices (at most ``width`` per block, a static size chosen on the host as the next power
of two above the largest count, so the result is exact, never truncated), and the attention
runs on (block vertices x block handles) instead of (V x H). Handles outside a block's list
have mask 0 on all of its vertices and contribute nothing, so this equals the dense forward
up to float rounding.
"""

from __future__ import annotations

import functools

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


@functools.partial(jax.jit, static_argnums=4)
def block_handle_counts(blocks, distance, radius, falloff, clamp):
    """(B,) how many handles influence some vertex of each block."""
    mask = influence_mask(distance, radius, falloff, clamp)
    padded = jnp.concatenate([mask, jnp.zeros((1, mask.shape[1]), mask.dtype)])
    return jnp.sum(jnp.max(padded[blocks], axis=1) > 0, axis=1)


@eqx.filter_jit
def blocked_deform(
    model: CANRig,
    block_queries: Float[Array, "B heads S d"],
    blocks: Int[Array, "B S"],
    position: Int[Array, " V"],
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
    """The forward pass of ``rig.deform`` with block-sparse attention (``width`` handles per
    block, static; must be >= every ``block_handle_counts``)."""
    mask = influence_mask(distance, radius, falloff, model.clamp)
    mask = jnp.where(mask < model.clamp, 0.0, mask)
    padded = jnp.concatenate([mask, jnp.zeros((1, mask.shape[1]), mask.dtype)])
    block_mask = padded[blocks]  # (B, S, H); padding rows are all 0
    score = jnp.max(block_mask, axis=1)  # (B, H)
    _, chosen = jax.lax.top_k(score, width)  # (B, W) all influencing handles first
    sub_mask = jnp.take_along_axis(block_mask, chosen[:, None, :], axis=2)  # (B, S, W)
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
